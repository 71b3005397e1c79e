"""Skins on curved surfaces: what a surface mesh ((N, 3) nodes) costs against a flat disc of
about as many triangles, in the forward solve and the Jacobian.

    python benchmarks/surface.py [--sizes 1000 4000] [--repeats 10]

The meshes, each with 16 electrodes and the adjacent protocol (208 voltages), contact impedance
0.01, a log-normal conductivity (standard deviation 0.2 in ln sigma):

- **disc**: the unit disc, electrodes of width 0.2 (`diffeit.mesh.disc`), the reference;
- **sphere cap**: a cap of polar angle 1.2 rad on the unit sphere (`diffeit.mesh.sphere_cap`,
  a fingertip);
- **cylinder patch**: half the surface of a cylinder of radius 1, length 2 (`diffeit.mesh.
  cylinder_patch`, a forearm);
- **flat twin** of each surface: the same triangles, numbering and electrodes with (N, 2)
  nodes, the surface mapped back to the plane it was meshed in (the cap by the azimuthal
  equidistant map, the patch unrolled): what the third coordinate alone costs.

The disc's h is tuned to within 8% of the wanted number of triangles, the surfaces' to within 2%
of the disc's. Times are medians of
`--repeats` eager calls of `model.measure(sigma)` and `model.jacobian(sigma)` (host sparse
backend, float64) after a warm-up call per mesh and function, which compiles and is not
counted; every call gets a conductivity of its own, so that no cached factorisation is reused.
The three meshes of a size are timed in turn within each repeat, each going first as often as
the others, so that a change in the load of a shared machine affects them alike. The ratio
columns are each mesh's time over the disc's ("/ disc") and, for a surface, over its flat twin's
("/ twin"); the target is at most 1.3x. The disc and the surfaces differ in more than the third
coordinate (shape, electrode widths, node numbering, and so the fill of the factorisation); the
twins differ in nothing else.
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from _common import (
    MarkdownTable,
    describe,
    describe_machine,
    disc_with_about,
    format_seconds,
    machine_line,
    record_output,
    relative,
    with_about,
    write_tables,
)

N_ELECTRODES = 16


def meshes(n_triangles: int) -> dict:
    """The disc of about `n_triangles` triangles, and the sphere cap and cylinder patch of
    about as many as it has."""
    import diffeit as de

    disc = disc_with_about(n_triangles)
    guess = 2.7 / disc.n_elements**0.5
    # Within 2% of the disc's triangles, in at most 8 meshes each.
    cap = with_about(lambda h: de.mesh.sphere_cap(1.0, 1.2, N_ELECTRODES, h), disc.n_elements, guess, 0.02, 8)
    patch = with_about(
        lambda h: de.mesh.cylinder_patch(1.0, 2.0, np.pi, N_ELECTRODES, h), disc.n_elements, guess, 0.02, 8
    )
    # The flat twins: the surfaces mapped back to the plane they were meshed in (the azimuthal
    # equidistant map of the cap, the unrolling of the patch), same triangles and numbering.
    x, y, z = cap.nodes.T
    polar = np.arccos(np.clip(z, -1.0, 1.0))
    cap_twin = np.stack([polar * np.cos(np.arctan2(y, x)), polar * np.sin(np.arctan2(y, x))], axis=1)
    x, y, z = patch.nodes.T
    patch_twin = np.stack([np.arctan2(y, x), z], axis=1)
    return {
        "disc": disc,
        "sphere cap": cap,
        "sphere cap, flat twin": de.Mesh(cap_twin, cap.triangles, cap.electrodes),
        "cylinder patch": patch,
        "cylinder patch, flat twin": de.Mesh(patch_twin, patch.triangles, patch.electrodes),
    }


def timings(n_triangles: int, repeats: int) -> dict[str, dict]:
    """{mesh name: its triangles and nodes, and median seconds of measure and jacobian}."""
    import jax.numpy as jnp

    import diffeit as de

    fresh = itertools.count(1)
    cases = {}
    for name, mesh in meshes(n_triangles).items():
        model = de.ForwardModel(mesh, de.protocol.adjacent(N_ELECTRODES), contact_impedance=0.01)
        base = np.exp(np.random.default_rng(0).normal(0.0, 0.2, mesh.n_elements))

        def conductivity(base=base):
            # A new matrix every call: no hits in the host backend's factorisation cache.
            return jnp.asarray(base * (1 + 1e-4 * next(fresh)))

        calls = {
            "measure": lambda model=model, conductivity=conductivity: model.measure(conductivity()),
            "jacobian": lambda model=model, conductivity=conductivity: model.jacobian(conductivity()),
        }
        for call in calls.values():
            call().block_until_ready()  # compiles: not counted
        cases[name] = {"mesh": mesh, "calls": calls, "times": {key: [] for key in calls}}
    for repeat in range(repeats):
        # Each mesh goes first as often as the others: the first call of a round can pay more.
        order = list(cases.values())
        for case in order[repeat % len(order) :] + order[: repeat % len(order)]:
            for key, call in case["calls"].items():
                start = time.perf_counter()
                call().block_until_ready()
                case["times"][key].append(time.perf_counter() - start)
    return {
        name: {
            "triangles": case["mesh"].n_elements,
            "nodes": case["mesh"].n_nodes,
            **{key: statistics.median(times) for key, times in case["times"].items()},
        }
        for name, case in cases.items()
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[1000, 4000], help="about how many triangles")
    parser.add_argument("--repeats", type=int, default=10, help="timed calls per median (after a warm-up call)")
    parser.add_argument("--describe", action="store_true", help=argparse.SUPPRESS)  # internal: the machine
    options = parser.parse_args()
    if options.describe:
        print(json.dumps(describe()))
        return
    machine = describe_machine(__file__, None)
    printed = record_output()
    print(machine_line(machine, with_pyeit=False))
    print(
        f"\nmedian of {options.repeats} calls after a warm-up (compilation not counted), 16 electrodes, "
        "adjacent protocol; ratios: a mesh's time over the disc's of about as many triangles, and a surface's over "
        "its flat twin's (the same triangles with (N, 2) nodes)\n"
    )
    columns = ["size", "mesh", "triangles", "nodes", "measure", "/ disc", "/ twin", "jacobian", "/ disc", "/ twin"]
    table = MarkdownTable(columns)
    worst = {"disc": 0.0, "twin": 0.0}
    for size in options.sizes:
        rows = timings(size, options.repeats)
        disc = rows["disc"]
        for name, row in rows.items():
            twin = rows.get(f"{name}, flat twin")
            cells = [f"~{size:,}", name, f"{row['triangles']:,}", f"{row['nodes']:,}"]
            for key in ("measure", "jacobian"):
                cells += [format_seconds(row[key]), relative(row[key], disc[key])]
                cells.append(relative(row[key], twin[key]) if twin else "-")
                if twin:
                    worst["disc"] = max(worst["disc"], row[key] / disc[key])
                    worst["twin"] = max(worst["twin"], row[key] / twin[key])
            table.row(cells)
    print(
        f"\nlargest ratio of a surface's time to the disc's: {worst['disc']:.2f}x, to its flat twin's: "
        f"{worst['twin']:.2f}x (target: at most 1.3x)"
    )
    write_tables("surface", printed)


if __name__ == "__main__":
    main()
