"""experiments/metrics.py (Fig. 5.1) and experiments/size.py (Fig. 5.8): the small modes run,
write their files and show their headline findings."""

import csv

import experiments.metrics
import experiments.size


def test_the_working_point_gives_one_clean_component_and_a_too_small_hyperparameter_artifacts(tmp_path):
    findings = experiments.metrics.STUDY.run(tmp_path, small=True, progress=False)
    values = findings.values
    assert values["working_point"] == 0.2 and values["too_small"] == 0.003
    assert values["working_clean"]  # one component, at the touch, in every draw
    assert values["working_worst_position_error_R"] < 0.15
    assert 0.15 < values["working_mean_equivalent_radius_R"] < 0.3  # true 0.2 R
    assert values["too_small_fewest_artifacts"] > 0  # every draw has extra blobs
    assert all(path.exists() and path.stat().st_size > 0 for path in findings.files)
    with (tmp_path / "metrics_summary.csv").open() as file:
        rows = list(csv.DictReader(file))
    assert [float(row["hyperparameter"]) for row in rows] == [0.2, 0.05, 0.003]
    # Correlation with the truth falls as the hyperparameter becomes too small.
    correlation = [float(row["mean_correlation"]) for row in rows]
    assert correlation[0] > correlation[1] > correlation[2]


def test_reconstructed_size_orders_with_the_touch_shrinks_with_the_hyperparameter_and_hits_a_limit(tmp_path):
    findings = experiments.size.STUDY.run(tmp_path, small=True, progress=False)
    values = findings.values
    ordered = values["ordered_at_working_point"]
    assert ordered["noise-free"] and ordered["low"]  # 0.1 R < 0.2 R < 0.5 R at hp 0.05
    assert all(values["noise_free_shrinks"].values())
    assert all(ratio > 1.5 for ratio in values["noise_free_shrink_ratio"].values())  # hp 1 -> 0.003
    assert all(all(by_size.values()) for by_size in values["noisy_shrinks_to_working_point"].values())
    # At 0.003 every image, of every touch, low and medium noise, has broken up into artifacts.
    assert all(
        all(f == 1 for f in by_size.values()) for by_size in values["fraction_with_artifacts_at_smallest_hp"].values()
    )
    # The 0.025 R touch: far larger than it is, a tiny peak, about in proportion to its area.
    assert values["tiny_radius_over_true"] >= 5
    assert values["tiny_peak_over_0.2R_peak"] < 0.05
    assert 0.5 < values["tiny_peak_over_0.1R_peak"] / (0.025 / 0.1) ** 2 < 2
    assert values["signal_percent"]["0.025"] < 0.1  # below the low noise level
    assert all(path.exists() and path.stat().st_size > 0 for path in findings.files)
    with (tmp_path / "size_summary.csv").open() as file:
        rows = list(csv.DictReader(file))
    assert {float(row["touch_radius_R"]) for row in rows} == {0.025, 0.1, 0.2, 0.5}
