"""Reading touches from a reconstructed session: the time `de.touches` takes a frame, from the
images (`method="image"`) and by fitting discs to each frame's voltages (`method="fit"`).

    python benchmarks/touches.py [--frames 60] [--repeats 3]

The skin and board of benchmarks/calibration.py (a disc of radius 80 mm, 16 electrodes,
opposition drive, magnitudes only, the artefacts real boards have, medium noise), its mesh at
about 1,000 triangles; the calibration from 20 reference frames and 50 labelled presses; then a
recording of the reference frames and `--frames` other presses, reconstructed once
(`de.reconstruct(..., calibration=...)`). Times are medians of `--repeats` calls of
`de.touches(images, calibration, method=...)` over the whole recording, after a warm-up call
that compiles (not counted), divided by the number of frames (every frame is read, touched or
not), and by the number of pressed frames (the fit's work is on them: an untouched frame costs
the voltage test alone). The targets are 5 ms a frame from the images and 50 ms with the fit. The median position
error on the pressed frames is printed beside them, and what they read of the presses' size and
depth (each a disc of radius 10 mm where dsigma/sigma = -0.3): the medians, with their quartiles,
of the strongest touch's radius and depth. An image is a blurred picture of a touch, its
half-amplitude set wider than a small contact and its peak shallower: the calibration's size map,
fitted on the labelled presses, takes them to the presses' (the row "image, no size map" reads the
same images without it); the fit reads the disc.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from _common import MarkdownTable, skin_benchmark, with_about, write_tables
from calibration import PRESS_CHANGE, PRESS_RADIUS, REFERENCE_FRAMES, session

CALIBRATION_PRESSES = 50
TRIANGLES = 1000


def quartiles(values: np.ndarray, form: str, unit: str) -> str:
    """The median of `values` (NaN left out) and, in brackets, its quartiles."""
    low, middle, high = (form.format(q) for q in np.nanpercentile(values, [25, 50, 75]))
    return f"{middle}{unit} ({low} to {high})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=60, help="test presses in the timed recording")
    parser.add_argument("--repeats", type=int, default=3)
    started = skin_benchmark(parser, __file__)
    if started is None:
        return
    options, printed = started
    import equinox as eqx

    import diffeit as de

    recording, presses, _ = session(0, CALIBRATION_PRESSES + options.frames)
    used = REFERENCE_FRAMES + 2 * CALIBRATION_PRESSES
    skin = recording.geometry
    mesh = with_about(
        lambda h: de.mesh.disc(16, electrode_width=skin["electrode_width"], h=h, radius=skin["radius"]),
        TRIANGLES,
        skin["h"],
    )
    calibration = de.calibrate(
        de.io.Recording(
            frames=recording.frames[:used],
            times=recording.times[:used],
            protocol=recording.protocol,
            mesh=mesh,
            readings="magnitude",
        ),
        presses.select(np.arange(CALIBRATION_PRESSES)),
    )
    tested = np.r_[np.arange(REFERENCE_FRAMES), np.arange(used, recording.n_frames)]
    test = de.io.Recording(
        frames=recording.frames[tested],
        times=recording.times[tested],
        protocol=recording.protocol,
        mesh=mesh,
        readings="magnitude",
    )
    images = de.reconstruct(test, calibration=calibration, progress=False)
    test_presses = presses.select(np.arange(CALIBRATION_PRESSES, CALIBRATION_PRESSES + options.frames))
    pressed = np.array([frames[0] for frames in test_presses.frames(test.times)])
    print(
        f"\n`de.touches` on {test.n_frames} frames ({REFERENCE_FRAMES} reference frames, {options.frames} presses each "
        "followed by an untouched frame), "
        f"{calibration.model.n_elements} triangles, 16 electrodes, {test.n_measurements} magnitudes; "
        f"medians of {options.repeats} calls after a warm-up\n"
    )
    table = MarkdownTable(
        [
            "method",
            "per frame",
            "per pressed frame",
            "whole recording",
            "target per frame",
            "median error on presses",
            f"radius (true {1e3 * PRESS_RADIUS:.0f} mm)",
            f"depth (true {PRESS_CHANGE:+.2f})",
        ]
    )
    unsized = eqx.tree_at(lambda c: c.size_map, calibration, None, is_leaf=lambda node: node is None)
    for name, method, skin_model, target in (
        ("image", "image", calibration, 5e-3),
        ("image, no size map", "image", unsized, 5e-3),
        ("fit", "fit", calibration, 50e-3),
    ):
        found = de.touches(images, skin_model, method=method)  # compiles
        seconds = []
        for _ in range(options.repeats):
            start = time.perf_counter()
            found = de.touches(images, skin_model, method=method)
            seconds.append(time.perf_counter() - start)
        whole = statistics.median(seconds)
        error = np.linalg.norm(found.position[pressed, 0] - test_presses.centres, axis=1)
        table.row(
            [
                name,
                f"{1e3 * whole / test.n_frames:.2f} ms",
                f"{1e3 * whole / options.frames:.2f} ms",
                f"{whole:.2f} s",
                f"{1e3 * target:.0f} ms",
                f"{1e3 * np.nanmedian(error):.1f} mm ({int(np.isnan(error).sum())} missed)",
                quartiles(1e3 * found.radius[pressed, 0], "{:.1f}", " mm"),
                quartiles(found.depth[pressed, 0], "{:+.2f}", ""),
            ]
        )
    print()
    write_tables("touches", printed)


if __name__ == "__main__":
    main()
