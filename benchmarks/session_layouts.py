"""How a calibration session is laid out, against the touches read from it: the median position
error on presses the calibration did not use, for the ways labelled presses are stored.

    python benchmarks/session_layouts.py [--seeds 2] [--test 60]

The skin and board are the calibration benchmark's (`benchmarks/calibration.py`: 80 mm, 16
electrodes, opposition drive, magnitudes, the artefacts of real boards, medium noise), 50
labelled presses and `--test` more, one frame each. The layouts:

- **rests between**: 20 untouched frames, then the presses with an untouched frame after each
  (the calibration benchmark's);
- **back to back**: 20 untouched frames, then the presses one after another;
- **one untouched frame**: the first frame untouched, then the presses one after another (no
  noise to test frames against: each is tested against its own, `subspace_statistic`);
- **a separate reference**: the recording's reference is one untouched frame, its frames the
  presses one after another;
- **held 1 s**: as "rests between", each press held 10 frames (1 s) with 10 untouched frames
  after it, labelled with its hold (start and end: `de.calibrate` fits the skin's memory);
- **labelled at random**: as "held 1 s", the 50 presses the calibration uses drawn at random
  from the session's (a split of a labelled session into calibration and test presses), so
  that presses not labelled come before the first labelled one;
- **in rows**: as "rests between", the presses in rows from the bottom up (a robot's raster),
  so that the 50 the calibration uses cover the lower part of the skin alone (its lower 45%),
  and the test presses the rest: what the labelled presses teach must carry beyond them;
- **an electrode lost**: as "rests between", electrode 5 coming off half way through the test
  presses (the readings on it read zero, those of the drives through it saturate at ten times
  the largest reading): `de.reconstruct` finds it and masks the readings on it
  (`diffeit.calibration.lost_electrodes`);
- **lost while labelled**: the same, electrode 5 coming off half way through the 50 presses
  the calibration uses: `de.calibrate` holds the readings on it and leaves out the presses
  from then on (`diffeit.calibration.held_lost_readings`).

Each is read three ways: with no calibration (`de.reconstruct`, `de.touches` at their
defaults), after `de.calibrate` from the reference alone, and after `de.calibrate` with 50
presses (the first, or those drawn); the test presses are the others, and a press without a
touch read counts as missed, left out of the median.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from _common import MarkdownTable, skin_benchmark, write_tables
from calibration import REFERENCE_FRAMES, cell, errors, session

CALIBRATION_PRESSES = 50
LAYOUTS = (
    "rests between",
    "back to back",
    "one untouched frame",
    "a separate reference",
    "held 1 s",
    "labelled at random",
    "in rows",
    "an electrode lost",
    "lost while labelled",
)
LOST_ELECTRODE = 5
HELD_FRAMES = 10  # "held 1 s": frames of each hold, at the calibration benchmark's 10 frames a second


def laid_out(layout: str, seed: int, n_presses: int):
    """The session of `seed` with `n_presses` presses, laid out as `layout`: the recording and
    the presses."""
    import diffeit as de

    hold = HELD_FRAMES if layout in ("held 1 s", "labelled at random") else 1
    between = ("rests between", "held 1 s", "labelled at random", "in rows", "an electrode lost", "lost while labelled")
    period = 2 * hold if layout in between else 1
    recording, presses, _ = session(seed, n_presses, hold=hold, period=period, rows=layout == "in rows")
    if layout in ("an electrode lost", "lost while labelled"):
        protocol = recording.protocol
        through = protocol.drive[protocol.drive_index, LOST_ELECTRODE] != 0
        on = (protocol.measure[:, LOST_ELECTRODE] != 0) | through
        frames = np.array(recording.frames)
        # Half way through the test presses or the calibration's (the first CALIBRATION_PRESSES).
        if layout == "an electrode lost":
            lost = REFERENCE_FRAMES + period * (CALIBRATION_PRESSES + (n_presses - CALIBRATION_PRESSES) // 2)
        else:
            lost = REFERENCE_FRAMES + period * (CALIBRATION_PRESSES // 2)
        frames[lost:, on] = 0.0
        frames[lost:, through] = 10 * np.abs(frames).max()
        return dataclasses.replace(recording, frames=frames), presses
    if layout in ("rests between", "back to back", "held 1 s", "labelled at random", "in rows"):
        return recording, presses
    frames, times = np.asarray(recording.frames), np.asarray(recording.times)
    kept = slice(REFERENCE_FRAMES - 1, None) if layout == "one untouched frame" else slice(REFERENCE_FRAMES, None)
    reference = frames[REFERENCE_FRAMES - 1] if layout == "a separate reference" else None
    return (
        de.io.Recording(
            frames=frames[kept],
            times=times[kept],
            protocol=recording.protocol,
            geometry=recording.geometry,
            readings=recording.readings,
            voltage_unit=recording.voltage_unit,
            reference=reference,
        ),
        presses,
    )


def labelled(layout: str, seed: int, n_presses: int) -> np.ndarray:
    """The indices of the `CALIBRATION_PRESSES` presses of `layout`'s session of `seed` (of
    `n_presses`) that the calibration uses: the first, or for "labelled at random" a draw."""
    if layout != "labelled at random":
        return np.arange(CALIBRATION_PRESSES)
    return np.sort(np.random.default_rng(seed).choice(n_presses, CALIBRATION_PRESSES, replace=False))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    started = skin_benchmark(parser, __file__, seeds=2, test=60)
    if started is None:
        return
    options, printed = started
    import diffeit as de

    print(
        f"\nmedian position error (mm) of the strongest touch on {options.test} test presses, misses in brackets; "
        f"the calibration from the reference alone and with {CALIBRATION_PRESSES} presses (the first, or those drawn)\n"
    )
    table = MarkdownTable(["layout", "seed", "no calibration", "reference alone", f"{CALIBRATION_PRESSES} presses"])
    for layout in LAYOUTS:
        for seed in range(options.seeds):
            recording, presses = laid_out(layout, seed, CALIBRATION_PRESSES + options.test)
            used = labelled(layout, seed, presses.n_presses)
            test = presses.select(np.setdiff1d(np.arange(presses.n_presses), used))
            cells = [cell(errors(recording, test, None))]
            for given in (None, presses.select(used)):
                cells.append(cell(errors(recording, test, de.calibrate(recording, given))))
            table.row([layout, str(seed), *cells])
    print()
    write_tables("session_layouts", printed)


if __name__ == "__main__":
    main()
