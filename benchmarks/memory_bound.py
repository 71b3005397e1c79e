"""What the frames determine of the skin's memory: the Cramer-Rao bound of the memory parameters
(`diffeit.fit.memory_uncertainty`) against the scene's design and the noise, and the errors of
the memory fit over noise seeds beside it.

    python benchmarks/memory_bound.py [--size 900] [--seeds 5] [--designs presses varied ...]
        [--fit-designs presses varied]

Each design is a sequence of presses at one place (the worked example's skin, touch and memory,
`examples/fit_memory.py`), given by its (start, hold) pairs, duration and frame rate. For each:

- **bound**: the relative standard errors of the fast and slow fractions, their time constants and
  the relaxation that `memory_uncertainty` reports at the truth (a joint fit stopped at its start,
  the truth, on a disc of about `--size` triangles): the smallest spread any unbiased estimate can
  have, with the spatial pattern of the touch known and its depth per press unknown. It is
  computed once and scaled to each noise level (it grows in proportion to the noise: a test
  checks it).
- **memory fit**: the RMS relative errors over `--seeds` noise seeds of `diffeit.fit.memory` on
  one-step images of frames simulated on a mesh twice as fine (NOSER, hyperparameter 0.3: the
  joint fit's start), at each noise level, for the designs of `--fit-designs` (default the two
  short ones); 0 seeds skips it. Where the bound exceeds about 30%, the memory fit's errors can
  come out below it: the fit is then held near its start (over_foam, within 50% of the truth)
  more than by the data, which the bound (for unbiased estimates) does not count.

Errors near the bound are what the data allow; errors far above it are the estimator's.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))

import numpy as np
from _common import (
    MarkdownTable,
    describe,
    describe_machine,
    disc_with_about,
    machine_line,
    record_output,
    write_tables,
)

NOISES = {"low": 0.1, "medium": 0.5, "high": 2.0}
FIELDS = ("fast_fraction", "fast_time", "slow_fraction", "slow_time", "relaxation")
# (presses as (start, hold) in seconds, duration in seconds, frame rate in Hz)
DESIGNS = {
    "presses": (((1.0, 1.5), (4.5, 1.0), (7.0, 1.0)), 10.0, 2.0),
    "varied": (((1.0, 3.0), (10.0, 0.5), (12.5, 1.5)), 16.0, 2.0),
    "varied-10Hz": (((1.0, 3.0), (10.0, 0.5), (12.5, 1.5)), 16.0, 10.0),
    "long-5Hz": (((1.0, 8.0), (25.0, 1.0), (30.0, 3.0)), 40.0, 5.0),
}
# The hyperparameter of the one-step images the memory fit reads (the joint fit's least).
IMAGE_HYPERPARAMETER = 0.3


def _scene(design: str, h: float, noise: str, seed: int):
    import dataclasses

    from fit_memory import memory_scene

    presses, duration, rate = DESIGNS[design]
    scene = memory_scene(h, noise=noise, seed=seed, presses=presses, duration=duration)
    return dataclasses.replace(scene, frame_rate=rate)


def bound(design: str, size: int) -> np.ndarray:
    """(5,) the relative standard errors of `FIELDS` at the truth, at medium noise."""
    import diffeit as de
    from diffeit import fit

    mesh = disc_with_about(size)
    scene = _scene(design, 2.7 / size**0.5, "medium", 1)
    simulation = de.simulate(scene, progress=False)
    frames, times = np.asarray(simulation.frames), np.asarray(simulation.times)
    model = de.ForwardModel(mesh, scene.skin.make_protocol(), contact_impedance=0.005)
    start = {
        "background": 0.01,
        "contact_impedance": 0.005,
        "memory": scene.effect("memory"),
        "stimulus": np.asarray(de.scene.stimulus(mesh, scene.touches, scene.times)),
    }
    at_truth = fit.joint(
        model, frames, times, initial=start, noise=NOISES["medium"], max_steps=0, progress=False, throw=False
    )
    uncertainty = fit.memory_uncertainty(model, frames, at_truth)
    return np.array([uncertainty.relative_error[uncertainty.names.index(name)] for name in FIELDS])


def fit_errors(design: str, size: int, noise: str, seeds: int) -> np.ndarray:
    """(5,) the RMS relative errors of the memory fit over `seeds` noise seeds."""
    import diffeit as de
    from diffeit import fit

    mesh = disc_with_about(size)
    errors = []
    for seed in range(1, seeds + 1):
        scene = _scene(design, 2.7 / size**0.5, noise, seed)
        truth = scene.effect("memory")
        simulation = de.simulate(scene, progress=False)
        frames, times = np.asarray(simulation.frames), np.asarray(simulation.times)
        model = de.ForwardModel(mesh, scene.skin.make_protocol(), contact_impedance=0.005)
        one_step = de.inverse.OneStep(model, "noser", IMAGE_HYPERPARAMETER, 0.01)
        images = np.asarray(one_step.solve(frames - frames[0]).value) / 0.01
        found = fit.memory(images, times, progress=False, throw=False).memory
        errors.append([float(getattr(found, name)) / float(getattr(truth, name)) - 1 for name in FIELDS])
    return np.sqrt(np.mean(np.square(errors), axis=0))


def _percent(error: float) -> str:
    # A fit that walked a time constant to its clip (e^14) would fill the column.
    return f"{error:.0%}" if error < 10 else ">1000%"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, default=900, help="about how many triangles the fits' mesh has")
    parser.add_argument("--seeds", type=int, default=5, help="noise seeds of the memory fit (0: the bound only)")
    parser.add_argument("--designs", nargs="+", choices=tuple(DESIGNS), default=list(DESIGNS))
    parser.add_argument(
        "--fit-designs",
        nargs="+",
        choices=tuple(DESIGNS),
        default=["presses", "varied"],
        help="the designs whose memory fits run (the long ones take minutes and gigabytes per seed)",
    )
    parser.add_argument("--describe", action="store_true", help=argparse.SUPPRESS)  # internal: the machine
    options = parser.parse_args()
    if options.describe:
        print(json.dumps(describe()))
        return

    machine = describe_machine(__file__, None)
    printed = record_output()  # the table also goes to docs/benchmarks/memory_bound.md
    print(machine_line(machine, with_pyeit=False))
    print(
        "\nrelative errors of the memory parameters: fast fraction / fast time / slow fraction / slow time / "
        "relaxation; bound: the Cramer-Rao bound (standard deviation) at the truth; memory fit: RMS over "
        f"{options.seeds} noise seeds\n"
    )
    table = MarkdownTable(["design", "frames", "noise", "bound", "memory fit"])
    for design in options.designs:
        start = time.perf_counter()
        medium = bound(design, options.size)
        presses, duration, rate = DESIGNS[design]
        for noise, percent in NOISES.items():
            scaled = medium * percent / NOISES["medium"]
            run = options.seeds and design in options.fit_designs
            fitted = fit_errors(design, options.size, noise, options.seeds) if run else None
            table.row(
                [
                    f"{design} ({', '.join(f'{s:g}+{h:g} s' for s, h in presses)})",
                    f"{round(duration * rate)} at {rate:g} Hz",
                    f"{noise} ({percent}%)",
                    " / ".join(f"{e:.0%}" for e in scaled),
                    "-" if fitted is None else " / ".join(_percent(e) for e in fitted),
                ]
            )
        print(f"({design}: {time.perf_counter() - start:.0f} s)", file=sys.stderr)
    print()
    write_tables("memory_bound", printed)


if __name__ == "__main__":
    main()
