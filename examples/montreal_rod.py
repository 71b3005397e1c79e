"""A rod moving around a tank: one-step NOSER images of the Montreal 1995 data set.

The data (EIDORS's Montreal set, `tests/data/montreal_data_1995.mat`, CC BY-ND 2.5, (C) 1995
Andy Adler): a 30 cm diameter saline tank with 16 electrodes, adjacent drive and measurement;
`zc_demo3` holds 99 frames (7 frames/s) of a non-conductive rod moved in a circle around the
tank, `zc_h_demo3` the homogeneous tank. The values are magnitudes in device units with a gain
per channel, so the frames are imaged from normalised differences (V - V_ref) / V_ref. Where
electrode 0 sat, and which way the electrodes were numbered, is not recorded: the images may
be rotated or mirrored against the tank.

Run: `python examples/montreal_rod.py [-o montreal_rod.png]`.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)  # diffeit computes in float64

import diffeit as de
import diffeit.io
from diffeit.plotting import plot_image_strip

DATA = Path(__file__).resolve().parents[1] / "tests" / "data" / "montreal_data_1995.mat"
TANK_RADIUS = 0.15  # m: the readme's 30 cm diameter tank
ELECTRODE_WIDTH = 0.01  # m: not recorded; about the size of the electrodes of such tanks
H = 0.015  # m: element size (about 900 triangles)
FRAME_RATE = 7.0  # frames per second, the readme's
HYPERPARAMETER = 0.3  # unit-free; the circle below holds from 0.1 to 3, and starts to break up at 0.03
BACKGROUND = 1.0  # S/sq: the tank's conductivity is not recorded; only the image's shape counts


@dataclass(frozen=True)
class MontrealResult:
    images: np.ndarray  # (T, E) conductivity change, S/sq (relative to BACKGROUND)
    mesh: de.Mesh
    positions: np.ndarray  # (T, 2) half-amplitude centroid of each image, m
    times: np.ndarray  # (T,) s


def reconstruct_montreal(
    path: str | Path = DATA, *, hyperparameter: float = HYPERPARAMETER, h: float = H
) -> MontrealResult:
    """Image every `zc_demo3` frame against `zc_h_demo3` (one-step NOSER) on a disc model of
    the tank; return the images, the mesh and each image's half-amplitude centroid."""
    recording = diffeit.io.read_eidors_mat(path, "zc_demo3", reference="zc_h_demo3", frame_rate=FRAME_RATE)
    mesh = de.mesh.disc(16, electrode_width=ELECTRODE_WIDTH, h=h, radius=TANK_RADIUS)
    model = de.ForwardModel(mesh, recording.protocol, contact_impedance=0.01)
    # Normalised differences (V - V_ref) / V_ref cancel each channel's gain, and their ratio is
    # the same for the recorded magnitudes as for signed voltages.
    solver = de.inverse.OneStep(
        model,
        prior="noser",
        hyperparameter=hyperparameter,
        background=BACKGROUND,
        normalised=True,
        reference=recording.reference,
    )
    images = np.asarray(solver.solve(recording.difference()).value)
    positions = np.array([de.metrics.half_amplitude_centroid(mesh, image) for image in images])
    return MontrealResult(images, mesh, positions, recording.times)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", default="montreal_rod.png", help="PNG to write")
    parser.add_argument("--hyperparameter", type=float, default=HYPERPARAMETER)
    arguments = parser.parse_args(argv)
    result = reconstruct_montreal(hyperparameter=arguments.hyperparameter)
    shown = plot_image_strip(
        arguments.output,
        result.mesh,
        result.images,
        times=result.times,
        max_panels=18,
        title=f"Montreal 1995, rod around the tank: one-step NOSER, hyperparameter {arguments.hyperparameter:g}",
    )
    angles = np.degrees(np.arctan2(result.positions[:, 1], result.positions[:, 0]))
    print(f"{len(result.images)} frames on {result.mesh.n_elements} triangles; wrote {arguments.output}")
    for frame in shown:
        x, y = result.positions[frame]
        when = f"t={result.times[frame]:5.2f} s"
        print(f"frame {frame:3d}  {when}  rod at ({x:+.3f}, {y:+.3f}) m, {angles[frame]:+6.1f} deg")


if __name__ == "__main__":
    main()
