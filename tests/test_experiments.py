"""experiments/: every study's small mode runs, writes its files and shows its headline finding;
`diffeit experiment` runs and lists them."""

import csv
from pathlib import Path

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
    with (tmp_path / "accuracy_time_front.csv").open() as file:
        front = list(csv.DictReader(file))
    for scene in ("touch", "contrast"):  # along the front, more time buys less error
        line = [row for row in front if row["scene"] == scene]
        assert [float(r["time_per_frame_s"]) for r in line] == sorted(float(r["time_per_frame_s"]) for r in line)
        assert [float(r["amplitude_error"]) for r in line] == sorted(
            (float(r["amplitude_error"]) for r in line), reverse=True
        )


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
