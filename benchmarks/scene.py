"""Simulation cost grows with a scene's effects, not with the catalogue of effects.

    python benchmarks/scene.py [--frames 100] [--h 0.1] [--repeats 3] [--blas-threads N]

One skin (the unit disc of the example scenes: 16 electrodes, adjacent protocol, reconstruction
mesh h, simulation mesh h / 2), `--frames` frames at 25 Hz, and a ladder of scenes: nothing on
the skin; one press (held for the middle half of the scene); then the press with one or more
effects. For each: the stages `diffeit.scene.pipeline` built, the forward solves (one per
distinct conductivity and contact-impedance state, reference included), and the median wall time
of `diffeit.simulate` over `--repeats` runs after a warm-up run (compilation excluded; meshes
are cached between runs). "vs press" is the time over the plain press's.

A second table times what a user first waits for: `diffeit.simulate` of a session of presses
one after another (`--presses` of them, radius 0.1, two frames each at 10 Hz, at seeded random
places), in a fresh process each, where every program it runs is compiled first, against the
same call again in that process.

What to read: instrument effects (noise, common-mode drift, open electrode) act on voltages and
cost almost nothing; effects that make every frame a state of its own (memory: the skin keeps
recovering; contact drift) cost one solve per frame. A scene pays only for what it declares.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (
    MarkdownTable,
    describe,
    describe_machine,
    format_seconds,
    machine_line,
    record_output,
    write_tables,
)
from threadpoolctl import threadpool_limits


def scenes(frames: int, h: float) -> list[tuple[str, object]]:
    import diffeit as de
    from diffeit.scene import (
        CommonModeDrift,
        ContactDrift,
        Disc,
        MeasurementNoise,
        Noise,
        OpenElectrodes,
        Press,
        Scene,
        Skin,
        Touch,
    )

    rate = 25.0
    duration = frames / rate
    press = Touch(Disc([0.5, 0.0], 0.2), -0.3, Press(start=duration / 4, hold=duration / 2))
    base = Scene(skin=Skin(h=h), frame_rate=rate, duration=duration)
    touched = base.replace(touches=(press,))
    noise = MeasurementNoise(Noise.level("medium"))
    drift = CommonModeDrift(offset=1e-4, rate=1e-5)
    opened = OpenElectrodes((5,))
    memory = de.scene.over_foam()
    contact = ContactDrift(0.01)
    return [
        ("nothing on the skin", base),
        ("press", touched),
        ("press + noise", touched.replace(effects=(noise,))),
        ("press + noise + drift + open electrode", touched.replace(effects=(noise, drift, opened))),
        ("press + memory", touched.replace(effects=(memory,))),
        ("press + contact drift", touched.replace(effects=(contact,))),
        ("press + all six effects", touched.replace(effects=(memory, noise, drift, opened, contact))),
    ]


def session(presses: int, h: float):
    """A scene of `presses` presses one after another on the unit-disc skin (two frames each)."""
    import numpy as np

    from diffeit.scene import Disc, Press, Scene, Skin, Touch

    rate, rng = 10.0, np.random.default_rng(0)
    angle, distance = rng.uniform(0, 2 * np.pi, presses), 0.7 * np.sqrt(rng.uniform(0, 1, presses))
    touches = tuple(
        Touch(Disc((r * np.cos(a), r * np.sin(a)), 0.1), -0.3, Press(start=(2 * k + 0.5) / rate, hold=1 / rate))
        for k, (a, r) in enumerate(zip(angle, distance, strict=True))
    )
    return Scene(skin=Skin(h=h), touches=touches, frame_rate=rate, duration=2 * presses / rate)


def first_simulation(presses: int, h: float) -> dict:
    """In this (fresh) process: the first `diffeit.simulate` of a session, then the same again."""
    import diffeit as de

    scene = session(presses, h)
    times = []
    for _ in range(2):
        start = time.perf_counter()
        simulation = de.simulate(scene, progress=False)
        simulation.frames.block_until_ready()
        times.append(time.perf_counter() - start)
    return {"presses": presses, "frames": int(simulation.frames.shape[0]), "first": times[0], "again": times[1]}


def run_first(options: argparse.Namespace) -> list[dict]:
    """`first_simulation` of each `--presses` count, each in a fresh Python process."""
    rows = []
    for presses in options.presses:
        command = [sys.executable, __file__, "--first-of", str(presses), "--h", str(options.h)]
        output = subprocess.run(command, capture_output=True, text=True, check=True).stdout
        rows.append(json.loads(output.strip().splitlines()[-1]))
    return rows


def run(options: argparse.Namespace) -> list[dict]:
    import diffeit as de

    rows = []
    for name, scene in scenes(options.frames, options.h):
        de.simulate(scene, progress=False)
        times = []
        for _ in range(options.repeats):
            start = time.perf_counter()
            simulation = de.simulate(scene, progress=False)
            simulation.frames.block_until_ready()
            times.append(time.perf_counter() - start)
        rows.append(
            {
                "scene": name,
                "stages": list(simulation.stages),
                "solves": simulation.solves,
                "frames": int(simulation.frames.shape[0]),
                "triangles": simulation.mesh.n_elements,
                "seconds": statistics.median(times),
            }
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=100, help="frames per scene (at 25 Hz)")
    parser.add_argument("--h", type=float, default=0.1, help="reconstruction element size; simulation uses h / 2")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per median (after a warm-up)")
    parser.add_argument("--blas-threads", type=int, help="BLAS threads of the measurements")
    parser.add_argument("--presses", type=int, nargs="+", default=[10, 50, 200], help="presses of the first runs")
    parser.add_argument("--json", help="also write the rows as JSON to this path")
    parser.add_argument("--describe", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--first-of", type=int, help=argparse.SUPPRESS)
    options = parser.parse_args()
    if options.describe:
        print(json.dumps(describe()))
        return
    if options.first_of is not None:
        print(json.dumps(first_simulation(options.first_of, options.h)))
        return
    machine = describe_machine(__file__, options.blas_threads)
    # This process has loaded its BLAS already: environment variables would no longer reach it.
    with threadpool_limits(limits=options.blas_threads, user_api="blas"):
        rows = run(options)
    first = run_first(options)
    printed = record_output()  # the table also goes to docs/benchmarks/scene.md
    print(machine_line(machine, with_pyeit=False))
    print(f"\nScene cost by effect: {rows[0]['frames']} frames, {rows[0]['triangles']} triangles (simulation mesh)\n")
    press = next(row["seconds"] for row in rows if row["scene"] == "press")
    table = MarkdownTable(["scene", "stages", "forward solves", "time", "vs press", "per frame"])
    for row in rows:
        table.row(
            [
                row["scene"],
                ", ".join(row["stages"]),
                str(row["solves"]),
                format_seconds(row["seconds"]),
                f"{row['seconds'] / press:.2f}",
                format_seconds(row["seconds"] / row["frames"]),
            ]
        )
    print(
        "\nThe first simulation in a fresh process (every program compiled first) against the same call again: "
        f"presses one after another, two frames each, {rows[0]['triangles']} triangles\n"
    )
    table = MarkdownTable(["presses", "frames", "first simulate (compiles)", "again", "first / again"])
    for row in first:
        table.row(
            [
                str(row["presses"]),
                str(row["frames"]),
                format_seconds(row["first"]),
                format_seconds(row["again"]),
                f"{row['first'] / row['again']:.1f}",
            ]
        )
    write_tables("scene", printed)
    if options.json:
        Path(options.json).write_text(json.dumps({"machine": machine, "rows": rows, "first": first}, indent=1))


if __name__ == "__main__":
    main()
