"""experiments.stimuli (Fig. 5.3) and experiments.scaling (Figs. 5.4-5.5): each small mode runs,
writes its files and shows its headline finding."""

import csv

import numpy as np

import experiments.scaling
import experiments.stimuli


def test_the_hyperparameter_comes_down_with_more_touches(tmp_path):
    findings = experiments.stimuli.STUDY.run(tmp_path, small=True, progress=False)
    values = findings.values
    assert values["comes_down"] and values["closes_from_above"] and values["automatic_choices_fall"]
    # One, two, three touches: two or three merge at less than half of one touch's upper end.
    merge = values["merge_limit"]
    assert max(merge[1:]) * 2 <= merge[0]
    assert np.all(np.diff(values["gcv"]) < 0) and np.all(np.diff(values["lcurve"]) < 0)
    # The clean range exists for every number of touches, and the optimal is its lower end.
    assert all(0 < low < high for low, high in zip(values["optimal"], merge, strict=True))
    # Equal touches at one radius image alike: none falls below half of the overall peak.
    assert min(values["peak_spread"]) > 0.9
    assert all(path.exists() and path.stat().st_size > 0 for path in findings.files)
    with (tmp_path / "stimuli_optimal.csv").open() as file:
        assert [row["touches"] for row in csv.DictReader(file)] == ["1", "2", "3"]


def test_the_scaling_matrix_restores_off_centre_peaks_at_the_working_point(tmp_path):
    findings = experiments.scaling.STUDY.run(tmp_path, small=True, progress=False)
    values = findings.values
    assert values["restored_at_working_point"]
    # Before: off-centre peaks far above the centre's and sizes below; after: within 10%.
    assert values["working_peak_before"] > 0.3 and values["working_peak_after"] <= 0.10
    assert values["working_size_after"] < values["working_size_before"]
    # The factors are unit-free in the background: twice the background, the same ratios.
    deviations = values["deviations"]
    assert abs(deviations["background 0.02 S/sq"]["peak_after"] - deviations["working point"]["peak_after"]) < 0.01
    assert all(path.exists() and path.stat().st_size > 0 for path in findings.files)
    with (tmp_path / "scaling_ratios.csv").open() as file:
        rows = list(csv.DictReader(file))
    working = [row for row in rows if row["setting"] == "working point"]
    assert [float(row["position_r_over_R"]) for row in working] == values["positions_r_over_R"]
    assert all(abs(float(row["peak_after"]) - 1) <= 0.10 for row in working)
