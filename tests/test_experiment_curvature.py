"""experiments/curvature.py: a touch on domes of the flat disc's area is placed about as well as on
the disc, and worse when the dome's data are imaged on its flattened mesh."""

import csv

import numpy as np

import experiments


def test_a_dome_places_a_touch_as_the_flat_disc_does_and_its_flattening_worse(tmp_path):
    findings = experiments.run("curvature", tmp_path, small=True, progress=False)
    flat, dome, flattened = (findings.values[key] for key in ("flat", "dome", "flattened"))
    # Measured (small mode): flat 0.022 R; dome 60 degrees 0.025 R on its own mesh, 0.043 R flattened.
    assert dome[60.0] <= 1.2 * flat + 0.01 and flattened[60.0] > 1.3 * dome[60.0], findings.values
    assert all(path.exists() and path.stat().st_size > 0 for path in findings.files)
    with (tmp_path / "curvature_table.csv").open() as file:
        rows = list(csv.DictReader(file))
    # Every image found its touch within 0.15 R (measured: at most 0.12 R, flattened), and its size
    # near the touch's 0.2 R (measured 0.18-0.30 R).
    errors = np.array([float(row["position_error"]) for row in rows])
    sizes = np.array([float(row["size"]) for row in rows if row["model"] != "flattened"])
    assert np.all(errors < 0.15) and np.all(np.abs(sizes - 0.2) < 0.1), (errors.max(), sizes.min(), sizes.max())
