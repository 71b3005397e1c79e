"""experiments/: every study's small mode runs, writes its files and shows its headline finding;
`diffeit experiment` runs and lists them."""

import csv

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
