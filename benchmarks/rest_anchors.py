"""Touches on a skin with memory: each touch read against the recording's reference, and against
the rest just before it (`de.touches(..., baseline="rest")`, the default; `diffeit.touch`,
"Rest anchors").

    python benchmarks/rest_anchors.py [--seeds 2] [--test 40]

The skin and board of benchmarks/calibration.py (a disc of radius 80 mm, 16 electrodes,
opposition drive, magnitudes only, the artefacts real boards have, medium noise) with the
`diffeit.memory` preset `over_foam` (it keeps about half a press just after its release, and
the rest fades over seconds), pressed for 0.5 s once a second (presses of radius 10 mm,
dsigma/sigma = -0.3, held 5 frames of 10 per second, 5 frames between them), after 20
untouched frames; and pressed in quick succession, each press held one frame with two frames
of rest between, or one (the memory's rest level moves at every press, and each touch is read
against what the one before left). The calibration uses the reference frames alone, or them
and the first 50 presses (their holds labelled); the whole session is reconstructed at it
(`de.reconstruct(..., calibration=...)`) and its touches read on the `--test` presses after
those 50. A press's error is the median, over its held frames, of the distance from its centre
to the strongest touch read; a press without a touch on any held frame is missed (left out of
the median, counted). Beside it: the frames between the test presses that read a touch (and of
them, those `de.touches` says are likely what the last touch left, `Touches.remains`), the test
presses' held frames it says so of (against the rest before), and the time `de.touches` takes
a frame (the image method). The last two rows read the same skin without memory, whose rest
level does not move: the two baselines read the same touches.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from _common import MarkdownTable, skin_benchmark, write_tables
from calibration import REFERENCE_FRAMES, session

# The presses' cadences, frames: held, and one every.
CADENCES = {"held 1/2 s": (5, 10), "1 frame, 2 rest": (1, 3), "1 frame, 1 rest": (1, 2)}
CALIBRATION_PRESSES = 50


def read(images, calibration, presses, between: np.ndarray, baseline: str) -> tuple[np.ndarray, str, str, float]:
    """(K,) each test press's error, m (NaN: missed); how many of the frames `between` (bool,
    (T,)) read a touch, and of them were said remains, and how many of the presses' held frames
    were said remains (as text); and the seconds `de.touches` took a frame."""
    import diffeit as de

    start = time.perf_counter()
    found = de.touches(images, calibration, baseline=baseline)
    seconds = (time.perf_counter() - start) / images.n_frames
    errors = []
    for centre, frames in zip(presses.centres, presses.frames(images.times), strict=True):
        distance = np.linalg.norm(found.position[frames, 0] - centre, axis=1)
        errors.append(np.nanmedian(distance) if np.isfinite(distance).any() else np.nan)
    remains = np.zeros(images.n_frames, bool) if found.remains is None else found.remains
    touched = between & (found.count > 0)
    held = ~between & np.isin(np.arange(images.n_frames), np.concatenate(presses.frames(images.times)))
    said = f" ({int(np.sum(touched & remains))} said remains)" if found.remains is not None else ""
    count = f"{int(touched.sum())}/{int(between.sum())}{said}"
    return np.array(errors), count, f"{int(np.sum(held & remains))}/{int(held.sum())}", seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    started = skin_benchmark(parser, __file__, seeds=2, test=40)
    if started is None:
        return
    options, printed = started
    import diffeit as de
    from diffeit.memory import over_foam

    print(
        f"\nmedian position error (mm) of the strongest touch on {options.test} test presses (10 frames a second), "
        "misses in brackets; the frames between test presses that read a touch; `de.touches` time a frame\n"
    )
    table = MarkdownTable(
        [
            "skin",
            "presses",
            "seed",
            "calibration",
            "against the reference",
            "against the rest before",
            "touched between",
            "held frames said remains",
            "time",
        ]
    )
    runs = [(seed, over_foam(), cadence) for cadence in CADENCES for seed in range(options.seeds)]
    runs += [(0, None, cadence) for cadence in CADENCES]
    for seed, memory, cadence in runs:
        n_presses = CALIBRATION_PRESSES + options.test
        hold, period = CADENCES[cadence]
        recording, presses, _ = session(seed, n_presses, hold=hold, period=period, memory=memory)
        used = REFERENCE_FRAMES + period * CALIBRATION_PRESSES
        test_presses = presses.select(np.arange(CALIBRATION_PRESSES, CALIBRATION_PRESSES + options.test))
        between = np.ones(recording.n_frames, bool)
        between[:used] = False
        for frames in test_presses.frames(recording.times):
            between[frames] = False
        for label, count in (("reference", 0), (f"{CALIBRATION_PRESSES} presses", CALIBRATION_PRESSES)):
            end = REFERENCE_FRAMES if count == 0 else used
            calibration = de.calibrate(
                de.io.Recording(
                    frames=recording.frames[:end],
                    times=recording.times[:end],
                    protocol=recording.protocol,
                    geometry=recording.geometry,
                    readings="magnitude",
                ),
                presses.select(np.arange(count)) if count else None,
            )
            images = de.reconstruct(recording, calibration=calibration, progress=False, throw=False)
            cells, touched, seconds = [], [], []
            for baseline in ("reference", "rest"):
                errors, count_between, said, per_frame = read(images, calibration, test_presses, between, baseline)
                cells.append(f"{1e3 * np.nanmedian(errors):.1f} ({int(np.isnan(errors).sum())})")
                touched.append(count_between)
                seconds.append(f"{1e3 * per_frame:.2f} ms")
            table.row(
                [
                    "over_foam" if memory is not None else "no memory",
                    cadence,
                    str(seed),
                    label,
                    *cells,
                    " -> ".join(touched),
                    said,
                    " -> ".join(seconds),
                ]
            )
    print()
    write_tables("rest_anchors", printed)


if __name__ == "__main__":
    main()
