"""Real tank recordings through `diffeit.reconstruct` with its defaults, and the comparison that
chose those defaults (which differences, which hyperparameter rule).

The data (`tests/data/`): the Montreal 1995 set, a non-conductive rod moved round a 30 cm tank
(`zc_demo3`) and across it (`zc_demo4`), magnitudes with a gain per channel; and the IIRC 2006
set, a 2 cm rod moved round a 20 cm tank (`v_rotate`), complex readings with those on the
driven electrodes. Neither records where electrode 0 sat or which way the electrodes run, so
the images may be rotated or mirrored against the tanks; the tracks' shapes are what counts.

For every recording and every choice, how well the rod's track keeps its shape: the median
distance of the image centroids from their least-squares circle over its radius (the rod
going round), or the spread across the track's principal line over its length (the rod
going across). Smaller is better.

Run: `python examples/real_recordings.py [-o real_recordings.png]` (about a minute).
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import jax
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.collections import LineCollection

jax.config.update("jax_enable_x64", True)  # diffeit computes in float64

import diffeit as de
from diffeit.plotting import plot_elements

DATA = Path(__file__).resolve().parents[1] / "tests" / "data"
RECORDINGS = {
    "Montreal rod round the tank": ("montreal_data_1995.mat", "zc_demo3", "zc_h_demo3", "circle"),
    "Montreal rod across the tank": ("montreal_data_1995.mat", "zc_demo4", "zc_h_demo4", "line"),
    "IIRC rod round the tank": ("iirc_data_2006.mat", "v_rotate", "v_reference", "circle"),
}
DIFFERENCES = ("calibrated", "normalised")
RULES = ("lcurve", "gcv", "noise_figure")


def read(name: str) -> de.io.Recording:
    file, variable, reference, _ = RECORDINGS[name]
    return de.io.read_eidors_mat(DATA / file, variable, reference=reference)


def track_error(positions: np.ndarray, shape: str) -> float:
    """Circle: median distance from the least-squares circle over its radius. Line: RMS
    distance from the principal line over the track's length."""
    if shape == "circle":
        design = np.column_stack([2 * positions, np.ones(len(positions))])
        (a, b, c), *_ = np.linalg.lstsq(design, np.sum(positions**2, axis=1), rcond=None)
        radius = np.sqrt(c + a**2 + b**2)
        return float(np.median(np.abs(np.linalg.norm(positions - [a, b], axis=1) - radius)) / radius)
    centred = positions - positions.mean(axis=0)
    _, singular, axes = np.linalg.svd(centred, full_matrices=False)
    return float(singular[1] / np.sqrt(len(positions)) / np.ptp(centred @ axes[0]))


def centroids(result: de.io.Recording) -> np.ndarray:
    """(T, 2) the half-amplitude centroid of each image's negative part (the non-conductive rod)."""
    return np.array([de.metrics.half_amplitude_centroid(result.mesh, -image) for image in result.images])


def reconstruct_quietly(recording: de.io.Recording, **options) -> tuple[de.io.Recording, list[str]]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", de.calibration.CalibrationWarning)
        result = de.reconstruct(recording, progress=False, **options)
    return result, [str(w.message) for w in caught if issubclass(w.category, de.calibration.CalibrationWarning)]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", default="real_recordings.png", help="PNG to write")
    arguments = parser.parse_args(argv)

    header = "| recording | " + " | ".join(f"{d}, {r}" for d in DIFFERENCES for r in RULES) + " | default |"
    print(header)
    print("|---" * (2 + len(DIFFERENCES) * len(RULES)) + "|")
    results = {}
    for name, (*_, shape) in RECORDINGS.items():
        recording = read(name)
        cells = []
        for difference in DIFFERENCES:
            for rule in RULES:
                result, _ = reconstruct_quietly(recording, difference=difference, hyperparameter=rule)
                value = result.provenance["metadata"]["hyperparameter"]
                cells.append(f"{track_error(centroids(result), shape):.3f} ({value:.2g})")
        default, notes = reconstruct_quietly(recording)
        results[name] = default
        metadata = default.provenance["metadata"]
        cells.append(
            f"{track_error(centroids(default), shape):.3f} ({metadata['difference']}, "
            f"{metadata['hyperparameter_choice']['method']} {metadata['hyperparameter']:.2g})"
        )
        print(f"| {name} | " + " | ".join(cells) + " |")
        calibration = metadata["calibration"]
        print(
            f"|   calibration: orientation {calibration['orientation']!r}, misfit {calibration['misfit']:.3f}, "
            f"correlation {calibration['correlation']:.3f}, readings used {calibration['readings_used']}, "
            f"driven readings {calibration['driven_readings']}; warnings: {'; '.join(notes) or 'none'} |"
        )

    figure, axes = plt.subplots(len(results), 5, figsize=(17, 3.3 * len(results)))
    for row, (name, result) in zip(axes, results.items(), strict=True):
        frames = np.linspace(0, result.n_frames - 1, 4).round().astype(int)
        for ax, frame in zip(row[:4], frames, strict=True):
            plot_elements(ax, result.mesh, result.images[frame], label="dsigma / sigma")
            ax.set_title(f"{name}\nframe {frame}" if frame == 0 else f"frame {frame}", fontsize=9)
        positions = centroids(result)
        row[4].add_collection(LineCollection(result.mesh.nodes[result.mesh.boundary_edges], colors="0.6"))
        row[4].scatter(*positions.T, c=np.arange(len(positions)), cmap="viridis", s=12)
        row[4].set_aspect("equal")
        row[4].set_title("image centroids (colour: frame)", fontsize=9)
    figure.suptitle("diffeit.reconstruct with its defaults on real tank recordings", fontsize=12)
    figure.tight_layout()
    figure.savefig(arguments.output, dpi=90)
    print(f"wrote {arguments.output}")


if __name__ == "__main__":
    main()
