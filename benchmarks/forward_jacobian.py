"""Forward solve and Jacobian: diffeit against pyEIT 1.2.4 on the same meshes, in the same run.

    python benchmarks/forward_jacobian.py [--sizes 700 2800 8000 30000] [--repeats 5]

Unit disc, 16 electrodes of width 0.2, adjacent protocol (208 voltages), float64. diffeit runs the
complete electrode model; pyEIT (point electrodes at the electrode centres, the closest it offers)
runs on the very same nodes and triangles. Times are medians of `--repeats` runs after a warm-up,
each run at a different conductivity so that no cached factorisation is reused; compile time
(first call minus median) is reported apart. Each mesh runs in its own process so that the peak
memory (growth of the peak resident set over the set-up) is its own.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time

PYEIT_JACOBIAN_LIMIT = 10_000  # pyEIT inverts the dense N x N matrix: beyond this it takes minutes


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _disc_with_about(n_triangles: int):
    import diffeit as de

    h = 2.7 / n_triangles**0.5
    for _ in range(4):
        mesh = de.mesh.disc(16, electrode_width=0.2, h=h)
        if abs(mesh.n_elements / n_triangles - 1) < 0.08:
            break
        h *= (mesh.n_elements / n_triangles) ** 0.5
    return mesh


def _timed(function, repeats: int) -> tuple[float, float]:
    """(median seconds over `repeats` calls after the first, first-call seconds)."""
    start = time.perf_counter()
    function(0)
    first = time.perf_counter() - start
    times = []
    for i in range(1, repeats + 1):
        start = time.perf_counter()
        function(i)
        times.append(time.perf_counter() - start)
    return statistics.median(times), first


def run_one(n_triangles: int, repeats: int) -> dict:
    import jax
    import numpy as np

    import diffeit as de

    mesh = _disc_with_about(n_triangles)
    model = de.ForwardModel(mesh, de.protocol.adjacent(16), contact_impedance=0.01)
    base = np.exp(np.random.default_rng(0).normal(0.0, 0.2, mesh.n_elements))

    def conductivity(i: int):
        return jax.numpy.asarray(base * (1 + 1e-3 * i))  # a new matrix every call: no cache hits

    row = {"triangles": mesh.n_elements, "nodes": mesh.n_nodes}
    rss_before = _peak_rss_mb()
    forward, forward_first = _timed(lambda i: model.measure(conductivity(i)).block_until_ready(), repeats)
    jacobian, jacobian_first = _timed(lambda i: model.jacobian(conductivity(i)).block_until_ready(), repeats)

    def both(i: int) -> None:
        sigma = conductivity(i)
        model.measure(sigma).block_until_ready()
        model.jacobian(sigma).block_until_ready()

    both_time, _ = _timed(both, repeats)
    row.update(
        forward=forward,
        forward_compile=forward_first - forward,
        jacobian=jacobian,
        jacobian_compile=jacobian_first - jacobian,
        forward_and_jacobian=both_time,
        peak_mb=_peak_rss_mb() - rss_before,
    )
    row.update(_pyeit(mesh, base, repeats))
    return row


def _pyeit(mesh, base, repeats: int) -> dict:
    import numpy as np

    try:
        from pyeit.eit import protocol as pyeit_protocol
        from pyeit.eit.fem import EITForward
        from pyeit.mesh import PyEITMesh
    except ImportError:
        return {"pyeit_forward": None, "pyeit_jacobian": None, "pyeit_note": "pyEIT not installed"}
    centres = []
    for chain in mesh.electrodes:
        midpoint = mesh.nodes[chain].mean(axis=0)
        centres.append(chain[np.argmin(np.linalg.norm(mesh.nodes[chain] - midpoint, axis=1))])
    electrode_nodes = set(np.concatenate(mesh.electrodes).tolist())
    reference = next(i for i in np.argsort(np.linalg.norm(mesh.nodes, axis=1)) if i not in electrode_nodes)
    pyeit_mesh = PyEITMesh(
        node=mesh.nodes, element=mesh.triangles, perm=1.0, el_pos=np.array(centres), ref_node=int(reference)
    )
    forward = EITForward(pyeit_mesh, pyeit_protocol.create(16, dist_exc=1, step_meas=1, parser_meas="std"))
    result = {}
    result["pyeit_forward"], _ = _timed(lambda i: forward.solve_eit(perm=base * (1 + 1e-3 * i)), repeats)
    if mesh.n_elements <= PYEIT_JACOBIAN_LIMIT:
        result["pyeit_jacobian"], _ = _timed(
            lambda i: forward.compute_jac(perm=base * (1 + 1e-3 * i)), max(2, min(repeats, 5))
        )
    else:
        result["pyeit_jacobian"] = None
        result["pyeit_note"] = f"pyEIT Jacobian skipped above {PYEIT_JACOBIAN_LIMIT} triangles (dense N x N inverse)"
    return result


def _format(seconds: float | None) -> str:
    if seconds is None:
        return "-"
    return f"{seconds * 1e3:.1f} ms" if seconds < 1 else f"{seconds:.2f} s"


def _ratio(ours: float, theirs: float | None) -> str:
    return "-" if theirs is None else f"1/{theirs / ours:.0f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[700, 2800, 8000, 30000])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)  # internal: run one size, print JSON
    arguments = parser.parse_args()
    if arguments.one:
        print(json.dumps(run_one(arguments.one, arguments.repeats)))
        return

    import jax

    print(
        f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
        f"{platform.python_implementation()} {platform.python_version()}, jax {jax.__version__} "
        f"on {jax.devices()[0].platform}, float64"
    )
    header = (
        "| triangles | nodes | forward | Jacobian | fwd+Jac (same sigma) | compile fwd / Jac | peak memory "
        "| pyEIT forward | pyEIT Jacobian | forward ratio | Jacobian ratio |"
    )
    print(header)
    print("|" + "---|" * header.count("|")[:-1] if False else "|" + "---|" * (header.count("|") - 1))
    notes = []
    for size in arguments.sizes:
        output = subprocess.run(
            [sys.executable, __file__, "--one", str(size), "--repeats", str(arguments.repeats)],
            check=True,
            capture_output=True,
            text=True,
        ).stdout
        row = json.loads(output.strip().splitlines()[-1])
        print(
            f"| {row['triangles']} | {row['nodes']} | {_format(row['forward'])} | {_format(row['jacobian'])} "
            f"| {_format(row['forward_and_jacobian'])} | {_format(row['forward_compile'])} / "
            f"{_format(row['jacobian_compile'])} | {row['peak_mb']:.0f} MB | {_format(row['pyeit_forward'])} "
            f"| {_format(row['pyeit_jacobian'])} | {_ratio(row['forward'], row['pyeit_forward'])} "
            f"| {_ratio(row['jacobian'], row['pyeit_jacobian'])} |",
            flush=True,
        )
        if row.get("pyeit_note"):
            notes.append(row["pyeit_note"])
    for note in dict.fromkeys(notes):
        print(f"note: {note}")


if __name__ == "__main__":
    main()
