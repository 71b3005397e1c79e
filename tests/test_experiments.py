"""experiments/: every study's small mode runs, writes its files and shows its headline finding;
`diffeit experiment` runs and lists them."""

import csv
from pathlib import Path

import numpy as np
import pytest

import experiments
from diffeit.cli import main


def test_the_optimal_hyperparameter_rises_with_noise(tmp_path):
    findings = experiments.run("hyperparameter", tmp_path, small=True, progress=False)
    assert findings.values["rises_with_noise"]
    optimal = findings.values["optimal"]["0.01"]  # low, medium, high noise
    assert optimal[0] < optimal[1] < optimal[2]
    assert all(path.exists() and path.stat().st_size > 0 for path in findings.files)
    with (tmp_path / "hyperparameter_optimal.csv").open() as file:
        rows = list(csv.DictReader(file))
    assert [row["noise"] for row in rows] == ["low", "medium", "high"]
    # GCV and the L-curve are reported beside it, and also rise with noise.
    assert float(rows[0]["lcurve"]) < float(rows[2]["lcurve"]) and float(rows[0]["gcv"]) < float(rows[2]["gcv"])


def test_the_command_lists_and_runs_studies(tmp_path, capsys):
    assert main(["experiment", "--list"]) == 0
    listed = capsys.readouterr().out
    assert all(name in listed for name in experiments.STUDIES)
    assert main(["experiment", "hyperparameter", "--small", "-o", str(tmp_path / "out")]) == 0
    report = capsys.readouterr().out
    assert "rises with noise" in report and (tmp_path / "out" / "hyperparameter_optimal.png").exists()
    assert main(["experiment", "nonsense", "-o", str(tmp_path / "x")]) == 2
    assert "no study 'nonsense'" in capsys.readouterr().err


def test_an_unknown_study_is_refused():
    with pytest.raises(ValueError, match="no study"):
        experiments.run("nonsense", "unused")


def test_nonlinear_iterations_lower_the_amplitude_error_on_a_high_contrast_scene(tmp_path):
    findings = experiments.run("accuracy_time", tmp_path, small=True, progress=False)
    errors = findings.values["gauss_newton_amplitude_error"]  # 0: the one-step linearisation
    assert findings.values["iterations_help"] and errors["5"] < errors["1"] < errors["0"]
    with (tmp_path / "accuracy_time.csv").open() as file:
        rows = list(csv.DictReader(file))
    assert {row["scene"] for row in rows} == {"touch", "contrast"}
    assert all(float(row["time_per_frame_s"]) > 0 and 0 <= float(row["one_minus_correlation"]) <= 2 for row in rows)
    iterative = {"Gauss-Newton x1", "Gauss-Newton x5", "total variation"}
    assert {row["method"] for row in rows if row["converged"] != ""} == iterative
    assert all(0 <= float(row["converged"]) <= 1 for row in rows if row["method"] in iterative)
    # Total variation runs to its gradient test on every frame of these scenes.
    assert all(float(row["converged"]) == 1 for row in rows if row["method"] == "total variation")
    with (tmp_path / "accuracy_time_front.csv").open() as file:
        front = list(csv.DictReader(file))
    for scene in ("touch", "contrast"):  # along each front, more time buys less error
        for error in ("amplitude_error", "one_minus_correlation"):
            line = [row for row in front if row["scene"] == scene and row["front_of"] == error]
            assert line and line[0]["time_per_frame_s"] == min(
                (r["time_per_frame_s"] for r in rows if r["scene"] == scene), key=float
            )
            assert [float(r["time_per_frame_s"]) for r in line] == sorted(float(r["time_per_frame_s"]) for r in line)
            assert [float(r[error]) for r in line] == sorted((float(r[error]) for r in line), reverse=True)
    with (tmp_path / "accuracy_time_budget.csv").open() as file:
        budget = list(csv.DictReader(file))
    assert {row["budget_s"] for row in budget} >= {"1", "10", "100"}
    for row in budget:  # the best within a budget fits it, and no row that fits does better
        limit = float(row["budget_s"])
        assert float(row["time_per_frame_s"]) <= limit
        fitting = [r for r in rows if r["scene"] == row["scene"] and float(r["time_per_frame_s"]) <= limit]
        assert float(row["value"]) == pytest.approx(min(float(r[row["error"]]) for r in fitting), rel=1e-5)


@pytest.mark.slow
def test_the_linear_against_nonlinear_notebook_executes_in_its_small_mode():
    """The notebook (a jupytext percent script) runs top to bottom in a kernel, SMALL = True."""
    import jupytext  # the [notebooks] extra, which make test installs
    import nbclient

    notebook = jupytext.read(Path(experiments.__file__).parent / "notebooks" / "linear_vs_nonlinear.py")
    parameters = next(cell for cell in notebook.cells if cell.cell_type == "code" and "SMALL = False" in cell.source)
    parameters.source = parameters.source.replace("SMALL = False", "SMALL = True")
    nbclient.NotebookClient(notebook, timeout=900, kernel_name="python3").execute()
    printed = "".join(
        output.get("text", "")
        for cell in notebook.cells
        if cell.cell_type == "code"
        for output in cell.get("outputs", [])
    )
    assert "| touch | Gauss-Newton x5 |" in printed and "| IIRC | greit |" in printed
    figures = [o for c in notebook.cells for o in c.get("outputs", []) if "image/png" in o.get("data", {})]
    assert len(figures) == 2


def test_a_sweep_on_two_local_dask_workers_equals_the_single_process_run(tmp_path):
    from experiments.sweep import problem_arrays, simulated, sweep

    differences, truths, centres = simulated(5, 0.1, 0.16)
    arrays = {prior: problem_arrays(0.16, prior, differences, truths, centres) for prior in ("noser", "laplace")}
    grid = np.logspace(-2, 0, 7)
    alone = sweep(arrays, grid, block=3)
    clustered = sweep(arrays, grid, block=3, workers=2)
    for prior in arrays:
        assert alone[prior].shape == (7, 5, 3)
        np.testing.assert_allclose(clustered[prior], alone[prior], rtol=1e-10, atol=1e-12)
    # The batched figures are the library's: correlation and position error of one point.
    import diffeit as de
    from diffeit.inverse import OneStep
    from experiments._study import BACKGROUND, model, skin

    mesh = skin(0.16)
    image = np.asarray(OneStep(model(mesh), "noser", grid[3], BACKGROUND).solve(differences[2]).value) / BACKGROUND
    assert alone["noser"][3, 2, 0] == pytest.approx(de.metrics.correlation(mesh, truths[2], image), rel=1e-8)
    assert alone["noser"][3, 2, 2] == pytest.approx(de.metrics.position_error(mesh, image, centres[2]), rel=1e-8)


def test_the_sweep_study_runs_in_its_small_mode(tmp_path):
    findings = experiments.run("sweep", tmp_path, small=True, progress=False)
    assert set(findings.values["best"]) == {"tikhonov", "noser", "laplace"}
    assert all(1e-3 <= value <= 1.0 for value in findings.values["best"].values())
    assert findings.values["timing"][0]["microseconds_per_point"] > 0


def test_the_sweep_shards_its_hyperparameters_over_several_devices():
    """In a process that sees two (host) devices, a block is split over both and gives the
    figures of the unsharded computation."""
    import os
    import subprocess
    import sys

    script = """
import jax, numpy as np
from experiments.sweep import _block, _figures, problem_arrays, simulated
assert len(jax.devices()) == 2, jax.devices()
differences, truths, centres = simulated(3, 0.12, 0.18)
arrays = problem_arrays(0.18, "noser", differences, truths, centres)
grid = np.logspace(-2, 0, 5)  # odd: one device gets a padded value
sharded = _block(arrays, grid)
plain = np.asarray(_figures(**arrays, lambdas=grid))
np.testing.assert_allclose(sharded, plain, rtol=1e-12, atol=1e-14)
print("sharded over", len(jax.devices()), "devices:", sharded.shape)
"""
    # The suite's XLA flags (conftest.py) kept: with XLA's defaults the process took 6.5-7.3 s
    # of CPU, with them 5.1 s.
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2".strip()
    environment = {"XLA_FLAGS": flags, "PATH": "/usr/bin:/bin"}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=environment, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "sharded over 2 devices: (5, 3, 3)" in done.stdout
