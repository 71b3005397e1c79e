"""A finger sliding across the skin: its touches read frame by frame against the rest before them
(`de.touches`' default, `baseline="rest"`; `diffeit.touch`, "Rest anchors") and against the
recording's reference.

    python benchmarks/slides.py [--seeds 8] [--speeds 0.3 1.0]

The skin and board of benchmarks/calibration.py (a disc of radius 80 mm, 16 electrodes,
opposition drive, magnitudes only, the artefacts real boards have, medium noise), without
memory, calibrated from its 20 untouched frames alone (`de.calibrate`). Then four slides, one
after another with 1 s of rest between: a touch of radius 10 mm, dsigma/sigma = -0.3, pressed
in over 0.1 s at a random point within 0.6 of the radius, sliding in a straight line to another
such point at a constant speed (`--speeds`, radii a second), and lifted at once. Per session and
baseline: the frames of the slides (the touch fully pressed), the median and 90th percentile
distance from the strongest touch read to the touch's centre (over those read), the slides'
frames with no touch read, the untouched frames (0.05 s before a slide to 0.15 s after it
excluded) that read a touch, and the frames read against an anchor other than the reference.
Without memory the rest level does not move: both baselines should read alike, no anchor moved.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from _common import MarkdownTable, skin_benchmark, write_tables
from calibration import RADIUS, REFERENCE_FRAMES, calibration_session, read_by_the_board, session_scene

SLIDES, REACH, TOUCH_RADIUS, CHANGE = 4, 0.6, 0.01, -0.3  # -, fraction of the radius, m, dsigma/sigma
PRESS_IN, REST = 0.1, 1.0  # s


def slid(seed: int, speed: float):
    """The session of `seed` (its skin and board, `calibration.session`) with the slides at `speed`
    radii a second: the recording (magnitudes), each frame's touch centre (T, 2) m (NaN where the
    touch is not fully pressed) and the untouched frames (T,) bool."""
    from diffeit.scene import Disc, Path, Press, Touch

    scene = session_scene(seed, 1)[0]  # its press is replaced
    rng = np.random.default_rng(1000 + seed)
    slides, start = [], REFERENCE_FRAMES / scene.frame_rate
    for _ in range(SLIDES):
        begin, end = RADIUS * REACH * np.sqrt(rng.uniform(0, 1, (2, 1))) * _directions(rng, 2)
        duration = float(np.linalg.norm(end - begin)) / (speed * RADIUS)
        slides.append((start, duration, begin, end))
        start += PRESS_IN + duration + REST
    touches = tuple(
        Touch(
            Disc(Path([s + PRESS_IN, s + PRESS_IN + d], [a, b]), TOUCH_RADIUS),
            CHANGE,
            Press(start=s, ramp_in=PRESS_IN, hold=d),
        )
        for s, d, a, b in slides
    )
    recording = read_by_the_board(scene.replace(touches=touches, duration=start))
    times = np.asarray(recording.times)
    centre = np.full((len(times), 2), np.nan)
    untouched = np.ones(len(times), bool)
    for s, d, a, b in slides:
        on = (times >= s + PRESS_IN) & (times <= s + PRESS_IN + d)
        centre[on] = a + np.clip((times[on] - s - PRESS_IN) / d, 0, 1)[:, None] * (b - a)
        untouched &= (times < s - 0.05) | (times > s + PRESS_IN + d + 0.15)
    return recording, centre, untouched


def _directions(rng: np.random.Generator, count: int) -> np.ndarray:
    """(count, 2) unit vectors at uniform random angles."""
    angle = rng.uniform(0, 2 * np.pi, count)
    return np.stack([np.cos(angle), np.sin(angle)], axis=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--speeds", type=float, nargs="+", default=[0.3, 1.0], help="radii a second")
    started = skin_benchmark(parser, __file__, seeds=8)
    if started is None:
        return
    options, printed = started
    if not all(np.isfinite(speed) and speed > 0 for speed in options.speeds):
        parser.error(f"--speeds must be positive numbers of radii a second; got {options.speeds}")
    import diffeit as de

    print(
        f"\n{SLIDES} slides a session; distances (mm) from the strongest touch read to the touch's centre on the "
        "slides' frames; frames of the slides with no touch read; untouched frames read touched; frames read against "
        "an anchor other than the reference\n"
    )
    table = MarkdownTable(
        [
            "seed",
            "speed, radii/s",
            "baseline",
            "slides' frames",
            "median",
            "90th percentile",
            "missed",
            "untouched read touched",
            "against a moved anchor",
        ]
    )
    for seed in range(options.seeds):
        for speed in options.speeds:
            recording, centre, untouched = slid(seed, speed)
            calibration = de.calibrate(calibration_session(recording, 0))
            images = de.reconstruct(recording, calibration=calibration, progress=False, throw=False)
            sliding = ~np.isnan(centre[:, 0])
            for baseline in ("rest", "reference"):
                found = de.touches(images, calibration, baseline=baseline)
                distance = 1e3 * np.linalg.norm(found.position[sliding, 0] - centre[sliding], axis=1)
                moved = 0 if found.anchor is None else int(np.sum(np.any(found.anchor != -1, axis=1)))
                table.row(
                    [
                        str(seed),
                        f"{speed:g}",
                        baseline,
                        str(int(sliding.sum())),
                        f"{np.nanmedian(distance):.1f}",
                        f"{np.nanpercentile(distance, 90):.1f}",
                        str(int(np.sum(found.count[sliding] == 0))),
                        f"{int(np.sum(found.count[untouched] > 0))}/{int(untouched.sum())}",
                        str(moved),
                    ]
                )
    print()
    write_tables("slides", printed)


if __name__ == "__main__":
    main()
