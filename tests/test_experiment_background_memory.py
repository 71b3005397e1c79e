"""experiments/background.py (Fig. 5.6) and experiments/memory.py (Fig. 5.7): each small mode runs,
writes its files and shows its headline finding."""

import csv

import experiments.background
import experiments.memory


def test_a_fitted_background_map_reads_the_same_touch_alike_on_both_halves(tmp_path):
    findings = experiments.background.STUDY.run(tmp_path, small=True, progress=False)
    values = findings.values
    assert values["fitted_agrees"]
    # The fitted map: the two touches' peaks within 10%, its halves within 10% of 0.01 and 0.002 S/sq.
    assert abs(values["peak_ratio"]["fitted"] - 1) <= 0.1
    assert values["map_error"] <= 0.1
    assert abs(values["integral_ratio"]["fitted"] - 1) <= 0.1
    # A uniform background misreports the touch on the less conductive half by more than 30%.
    assert values["peak_ratio"]["uniform"] > 1.3 and values["integral_ratio"]["uniform"] > 1.3
    assert all(path.exists() and path.stat().st_size > 0 for path in findings.files)
    with (tmp_path / "background_touches.csv").open() as file:
        rows = list(csv.DictReader(file))
    assert {row["background"] for row in rows} == {"uniform", "true", "fitted"}


def test_the_memory_correction_removes_the_ghosts_and_evens_the_presses(tmp_path):
    findings = experiments.memory.STUDY.run(tmp_path, small=True, progress=False)
    values = findings.values
    assert values["corrected"]
    assert values["ghost_removed_min"] >= 0.8
    assert values["peak_deviation_after"] <= 0.1
    # Without the correction a later press's step from the last baseline reads more than 10% low.
    assert max(values["step_ratio"]["noise-free"]) < 0.9
    assert all(path.exists() and path.stat().st_size > 0 for path in findings.files)
    with (tmp_path / "memory_ghosts.csv").open() as file:
        kinds = {row["images"] for row in csv.DictReader(file)}
    assert {"before", "after", "noise-free", "noise only"} <= kinds
