"""Contacts that drift during a session, against the touches read from it: the median position
error on presses the calibration did not use, for the one-step images' prior spread q of each
electrode's change in ln z (`diffeit.inverse.CONTACT_IMPEDANCE_SPREAD`, docs/science.md
"Contact impedance drift").

    python benchmarks/contact_drift.py [--seeds 5] [--test 60]

The skin and board are the calibration benchmark's (`benchmarks/calibration.py`: 80 mm, 16
electrodes, opposition drive, magnitudes, the artefacts of real boards, medium noise), 50
labelled presses and `--test` more, one frame each with an untouched frame after it. Four
sessions per seed: the presses anywhere within 0.8 of the radius or at the rim (0.8-0.95),
each with the contacts held or drifting (each electrode's contact impedance drifting
exponentially to a factor exp(u 0.3) by the session's end, u uniform in [-1, 1]). The test
recording is the untouched frames, then the test presses: the contacts have drifted between
them. Each is read after `de.calibrate` from the reference alone at q = 0 (the contacts held),
1, the default, 3 and 10 (a `OneStep` solver object at the "auto" hyperparameter; the default
column is `de.reconstruct`'s defaults), and after `de.calibrate` with the first 50 presses at
the defaults. A press without a touch read counts as missed, left out of the median. Beside
each, in square brackets, how many of the untouched frames after the test presses read a
touch (none should: a drift the rest anchors do not follow shows as touches there).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from _common import MarkdownTable, skin_benchmark, write_tables
from calibration import calibration_session, cell, press_errors, session, split, touches_read

CALIBRATION_PRESSES = 50
DRIFT = 0.3  # the largest change in ln z by the session's end
SPREADS = (0.0, 1.0, None, 3.0, 10.0)  # None: the default
PLACES = {"within 0.8": (0.0, 0.8), "at the rim (0.8-0.95)": (0.8, 0.95)}


def read_cell(recording, presses, calibration, solver=None) -> str:
    """The median error and misses (`cell`), and in square brackets how many of the untouched
    frames, one after each press, read a touch."""
    found = touches_read(recording, calibration, solver)
    after = np.array([frames[-1] + 1 for frames in presses.frames(recording.times)])
    after = after[after < recording.n_frames]
    return f"{cell(press_errors(recording, presses, found))} [{int(np.sum(found.count[after] > 0))}]"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    started = skin_benchmark(parser, __file__, seeds=5, test=60)
    if started is None:
        return
    options, printed = started
    import diffeit as de
    from diffeit.inverse import CONTACT_IMPEDANCE_SPREAD, OneStep

    print(
        f"\nmedian position error (mm) of the strongest touch on {options.test} test presses, misses in brackets, "
        "and in square brackets the untouched frames (one after each press) read touched; "
        f"from the reference alone at each spread q, and after {CALIBRATION_PRESSES} labelled presses at the "
        f"default (q = {CONTACT_IMPEDANCE_SPREAD:g})\n"
    )
    spreads = [f"q = {CONTACT_IMPEDANCE_SPREAD:g} (default)" if q is None else f"q = {q:g}" for q in SPREADS]
    table = MarkdownTable(["presses", "contacts", "seed", *spreads, f"{CALIBRATION_PRESSES} presses"])
    for place, (inner, reach) in PLACES.items():
        for drift in (0.0, DRIFT):
            for seed in range(options.seeds):
                recording, presses, _ = session(
                    seed, CALIBRATION_PRESSES + options.test, inner=inner, reach=reach, contact_drift=drift
                )
                test, test_presses = split(recording, presses, CALIBRATION_PRESSES, options.test)
                alone = de.calibrate(calibration_session(recording, 0))
                cells = []
                for q in SPREADS:
                    solver = None if q is None else OneStep(prior="noser", contact_impedance_spread=q)
                    cells.append(read_cell(test, test_presses, alone, solver))
                labelled = de.calibrate(
                    calibration_session(recording, CALIBRATION_PRESSES),
                    presses.select(np.arange(CALIBRATION_PRESSES)),
                )
                cells.append(read_cell(test, test_presses, labelled))
                contacts = "held" if drift == 0 else f"drifting (up to {np.exp(drift):.2f}x)"
                table.row([place, contacts, str(seed), *cells])
    print()
    write_tables("contact_drift", printed)


if __name__ == "__main__":
    main()
