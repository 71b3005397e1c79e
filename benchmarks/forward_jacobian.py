"""Forward solve and Jacobian: diffeit against pyEIT 1.2.4, and diffeit's backends and precisions.

    python benchmarks/forward_jacobian.py [--sizes 700 2800 8000 30000] [--repeats 5]
        [--backends host_sparse dense_cholesky conjugate_gradient] [--precisions float64 float32]
        [--dense-limit 10000] [--skip-pyeit] [--blas-threads N] [--json PATH]

The problem: unit disc, 16 electrodes of width 0.2, adjacent protocol (208 voltages), contact
impedance 0.01, a log-normal conductivity (standard deviation 0.2 in ln sigma).

Table 1, diffeit against pyEIT: diffeit's default (host sparse backend, float64, the complete
electrode model, eager public calls `model.measure` and `model.jacobian`) against pyEIT (point
electrodes at the electrode centres, the closest it offers) on the very same nodes and triangles.
The ratio columns are diffeit's time over pyEIT's ("1/20": diffeit 20 times faster). The fwd+Jac
column is one forward solve and one Jacobian at the same conductivity (they share the host
factorisation). pyEIT's Jacobian inverts a dense N x N matrix: skipped above PYEIT_JACOBIAN_LIMIT.

Table 2, backends and precision: every backend of `diffeit.linear_solve` (`--backends`) in every
precision (`--precisions`), timed through `jax.jit(model.measure)` and `jax.jit(model.jacobian)`
(under jit the concrete-input checks and the float32 precision check, an estimate of the float32
error costing two more solves, do not run: the table times the computation). Accuracy is taken
against host_sparse float64 computed in the same process at the same conductivity:

- voltage error: ||V - V_ref||_2 / ||V_ref||_2 over the 208 voltages;
- Jacobian error: max |J - J_ref| / max |J_ref| (entrywise error relative to the largest entry;
  a plain entrywise relative error is meaningless for the near-zero entries far from the electrodes);
- residual: the largest relative residual ||b - A x|| / ||b|| of the 16 drive columns of the
  forward system, computed in the working precision;
- CG iterations: conjugate-gradient iterations of the forward solve (the loop runs until its
  slowest column converges), counted in one separate instrumented solve, outside the timings.

The ratio columns are each case's time over host_sparse float64's measured in the same run
("0.50x": twice as fast). Dense Cholesky forms the n x n matrix (memory n^2, time n^3): it is
skipped above `--dense-limit` triangles (default DENSE_CHOLESKY_LIMIT; raise it on an accelerator).

How: each mesh size runs in its own process, so that its peak memory (growth of the peak resident
set over the set-up of table 1, host memory only, never accelerator memory) is its own. Times are
medians over `--repeats` calls after a warm-up call; every call gets a conductivity of its own, so
that no cached host factorisation is reused (except in the fwd+Jac column, by design). Compile
time is the first call minus the median (it includes one-time set-up such as the host's
fill-reducing ordering). A series of table 2 stops early, after at least MIN_RUNS calls, once its
timed calls exceed SLOW_CASE_SECONDS (slow cases, e.g. CG on large meshes on few CPU cores); the
runs column says how many calls each median has.

Caveats:

- float32 with host_sparse assembles the matrix in float32 but factorises and solves in float64
  on the host, then rounds the result to float32: its float32 time measures the float32 assembly
  and the conversions, never a float32 solve; its error the float32 rounding of inputs and
  outputs. dense_cholesky and conjugate_gradient compute in float32 (CG to a relative residual of
  1e-6 in float32, 1e-12 in float64).
- The JAX backends run on the default device, `jax.devices()[0]` (named in the header line);
  host_sparse runs on the host through a callback, on an accelerator with the transfers included.
  The script runs unchanged on a GPU machine; `--skip-pyeit` leaves out pyEIT (CPU only).
- On a shared machine the times depend on the load (its load average is in the header line).
  Multithreaded BLAS suffers most from other processes on the same cores: dense Cholesky (LAPACK
  through OpenBLAS) and host_sparse (SuperLU calls BLAS) can then run several times slower, and
  erratically; `--blas-threads 1` steadies them.
"""

from __future__ import annotations

import argparse
import itertools
import resource
import statistics
import sys
import time
from collections.abc import Callable

from _common import (
    MarkdownTable,
    child_work,
    describe_machine,
    disc_with_about,
    driver_arguments,
    format_seconds,
    fraction,
    machine_line,
    measure_sizes,
    record_output,
    relative,
    save_json,
    write_tables,
)

PYEIT_JACOBIAN_LIMIT = 10_000  # pyEIT inverts the dense N x N matrix: beyond this it takes minutes
DENSE_CHOLESKY_LIMIT = 10_000  # triangles; dense Cholesky forms an n x n matrix (n about triangles / 2)
SLOW_CASE_SECONDS = 20.0  # a table 2 series stops early once its timed calls take this long ...
MIN_RUNS = 2  # ... but not before this many calls
BACKENDS = ("host_sparse", "dense_cholesky", "conjugate_gradient")
PRECISIONS = ("float64", "float32")
REFERENCE = ("host_sparse", "float64")


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _timed(function: Callable[[], object], repeats: int, budget: float | None = None) -> tuple[float, float, int]:
    """(median seconds over the calls after the first, first-call seconds, number of timed calls).

    At most `repeats` timed calls; with a `budget`, no more once they took `budget` seconds in all
    and there were at least MIN_RUNS of them."""
    start = time.perf_counter()
    function()
    first = time.perf_counter() - start
    times: list[float] = []
    while len(times) < repeats:
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
        if budget is not None and len(times) >= MIN_RUNS and sum(times) > budget:
            break
    return statistics.median(times), first, len(times)


def run_one(n_triangles: int, options: argparse.Namespace) -> dict:
    import jax
    import numpy as np

    import diffeit as de

    mesh = disc_with_about(n_triangles)
    model = de.ForwardModel(mesh, de.protocol.adjacent(16), contact_impedance=0.01)
    base = np.exp(np.random.default_rng(0).normal(0.0, 0.2, mesh.n_elements))
    fresh = itertools.count(1)

    def conductivity(dtype=np.float64):
        # A new matrix every call: no hits in the host backend's factorisation cache.
        return jax.numpy.asarray(base * (1 + 1e-4 * next(fresh)), dtype)

    row = {"triangles": mesh.n_elements, "nodes": mesh.n_nodes}
    rss_before = _peak_rss_mb()
    forward, forward_first, _ = _timed(lambda: model.measure(conductivity()).block_until_ready(), options.repeats)
    jacobian, jacobian_first, _ = _timed(lambda: model.jacobian(conductivity()).block_until_ready(), options.repeats)

    def both() -> None:
        sigma = conductivity()
        model.measure(sigma).block_until_ready()
        model.jacobian(sigma).block_until_ready()

    both_time, _, _ = _timed(both, options.repeats)
    row.update(
        forward=forward,
        forward_compile=forward_first - forward,
        jacobian=jacobian,
        jacobian_compile=jacobian_first - jacobian,
        forward_and_jacobian=both_time,
        peak_mb=_peak_rss_mb() - rss_before,
    )
    if options.skip_pyeit:
        row.update(pyeit_forward=None, pyeit_jacobian=None, pyeit_note="pyEIT skipped (--skip-pyeit)")
    else:
        row.update(_pyeit(mesh, base, options.repeats))
    row["backends"] = _backends(mesh, base, conductivity, options)
    return row


def _backends(mesh, base, conductivity, options: argparse.Namespace) -> list[dict]:
    """Table 2 for one mesh: host_sparse float64 first (the reference), then every other case."""
    import jax
    import numpy as np

    import diffeit as de

    cases = [REFERENCE] + [
        (backend, precision)
        for backend in options.backends
        for precision in options.precisions
        if (backend, precision) != REFERENCE
    ]
    results, reference = [], None
    for backend, precision in cases:
        result = {"backend": backend, "precision": precision}
        results.append(result)
        if backend == "dense_cholesky" and mesh.n_elements > options.dense_limit:
            result["skipped"] = f"dense_cholesky skipped above {options.dense_limit} triangles (n x n matrix)"
            continue
        try:
            model = de.ForwardModel(mesh, de.protocol.adjacent(16), contact_impedance=0.01, solver=backend)
            measure, jacobian, potentials = jax.jit(model.measure), jax.jit(model.jacobian), jax.jit(model.potentials)
            dtype = np.dtype(precision)
            # Timings first, so that their first calls compile.
            for name, function in (("forward", measure), ("jacobian", jacobian)):
                median, first, runs = _timed(
                    lambda function=function, dtype=dtype: function(conductivity(dtype)).block_until_ready(),
                    options.repeats,
                    SLOW_CASE_SECONDS,
                )
                result.update({name: median, f"{name}_compile": first - median, f"{name}_runs": runs})
            sigma = jax.numpy.asarray(base, dtype)
            voltages = np.asarray(measure(sigma), np.float64)
            sensitivity = np.asarray(jacobian(sigma), np.float64)
            result["residual"] = float(np.max(np.asarray(potentials(sigma).relative_residual)))
            if reference is None:
                reference = voltages, sensitivity
            else:
                result["voltage_error"] = float(np.linalg.norm(voltages - reference[0]) / np.linalg.norm(reference[0]))
                result["jacobian_error"] = float(
                    np.max(np.abs(sensitivity - reference[1])) / np.max(np.abs(reference[1]))
                )
            if backend == "conjugate_gradient":
                result["iterations"] = _cg_iterations(model, sigma)
        except Exception as error:  # a failing case is reported, not fatal for the others
            result["error"] = f"{type(error).__name__}: {(str(error).strip().splitlines() or [''])[0]}"
            if reference is None:  # without the reference there is nothing to compare against
                break
    return results


def _cg_iterations(model, sigma) -> int | None:
    """Iterations of the conjugate-gradient forward solve, counted by a sparse product that
    reports each call (one per iteration) to the host."""
    import jax
    import jax.numpy as jnp

    from diffeit.linear_solve import SparsityPattern

    calls: list[int] = []

    class CountingPattern(SparsityPattern):
        def matvec(self, values, x):
            jax.debug.callback(lambda: calls.append(1))
            return super().matvec(values, x)

    try:
        system = model.system
        pattern = system.pattern
        counting = CountingPattern(pattern.rows, pattern.cols, pattern.indptr, pattern.size, pattern.fingerprint)
        values = system.values(sigma, model.contact_impedance.astype(sigma.dtype))
        rhs = system.current_rhs(model.drive_current * jnp.asarray(model.protocol.drive, sigma.dtype))
        jax.block_until_ready(model.solver.solve(counting, values, rhs))
        jax.effects_barrier()
    except Exception:  # a diagnostic on diffeit's internals: never fatal
        return None
    return len(calls)


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
    fresh = itertools.count(1)
    result = {}
    result["pyeit_forward"], _, _ = _timed(lambda: forward.solve_eit(perm=base * (1 + 1e-4 * next(fresh))), repeats)
    if mesh.n_elements <= PYEIT_JACOBIAN_LIMIT:
        result["pyeit_jacobian"], _, _ = _timed(
            lambda: forward.compute_jac(perm=base * (1 + 1e-4 * next(fresh))), max(2, min(repeats, 5))
        )
    else:
        result["pyeit_jacobian"] = None
        result["pyeit_note"] = f"pyEIT Jacobian skipped above {PYEIT_JACOBIAN_LIMIT} triangles (dense N x N inverse)"
    return result


def _error(value: float | None) -> str:
    return "-" if value is None else f"{value:.1e}"


def _backend_cells(row: dict, result: dict, reference: dict) -> list[str]:
    is_reference = (result["backend"], result["precision"]) == REFERENCE
    compile_times = (
        f"{format_seconds(result.get('forward_compile'))} / {format_seconds(result.get('jacobian_compile'))}"
    )
    runs = f"{result['forward_runs']} / {result['jacobian_runs']}" if "forward_runs" in result else "-"
    return [
        str(row["triangles"]),
        result["backend"],
        result["precision"],
        format_seconds(result.get("forward")),
        format_seconds(result.get("jacobian")),
        "1 (ref)" if is_reference else relative(result.get("forward"), reference.get("forward")),
        "1 (ref)" if is_reference else relative(result.get("jacobian"), reference.get("jacobian")),
        compile_times,
        "ref" if is_reference else _error(result.get("voltage_error")),
        "ref" if is_reference else _error(result.get("jacobian_error")),
        _error(result.get("residual")),
        str(result["iterations"]) if result.get("iterations") is not None else "-",
        runs,
    ]


def _child_command(options: argparse.Namespace, size: int) -> list[str]:
    command = [sys.executable, __file__, "--one", str(size), "--repeats", str(options.repeats)]
    command += ["--backends", *options.backends, "--precisions", *options.precisions]
    command += ["--dense-limit", str(options.dense_limit)]
    return command + (["--skip-pyeit"] if options.skip_pyeit else [])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    driver_arguments(parser, [700, 2800, 8000, 30000])
    parser.add_argument(
        "--backends", nargs="+", choices=BACKENDS, default=list(BACKENDS), help="backends of table 2 (default: all)"
    )
    parser.add_argument(
        "--precisions", nargs="+", choices=PRECISIONS, default=list(PRECISIONS), help="precisions of table 2"
    )
    parser.add_argument(
        "--dense-limit",
        type=int,
        default=DENSE_CHOLESKY_LIMIT,
        help=f"skip dense_cholesky above this many triangles (default {DENSE_CHOLESKY_LIMIT})",
    )
    parser.add_argument("--skip-pyeit", action="store_true", help="leave pyEIT out of table 1")
    options = parser.parse_args()
    if options.repeats < 1:
        parser.error("--repeats must be at least 1")
    if child_work(options, run_one):
        return

    machine = describe_machine(__file__, options.blas_threads)
    printed = record_output()  # the tables also go to docs/benchmarks/forward_jacobian.md
    print(machine_line(machine, with_pyeit=not options.skip_pyeit) + f", {options.repeats} repeats")
    print()
    print("diffeit (host_sparse, float64) against pyEIT:")
    print()
    table = MarkdownTable(
        [
            "triangles",
            "nodes",
            "forward",
            "Jacobian",
            "fwd+Jac (same sigma)",
            "compile fwd / Jac",
            "peak memory",
            "pyEIT forward",
            "pyEIT Jacobian",
            "forward ratio",
            "Jacobian ratio",
        ]
    )
    rows, notes, failures = [], [], []
    for row, failure in measure_sizes(options, lambda size: _child_command(options, size)):
        if row is None:
            failures.append(failure)
            continue
        rows.append(row)
        table.row(
            [
                str(row["triangles"]),
                str(row["nodes"]),
                format_seconds(row["forward"]),
                format_seconds(row["jacobian"]),
                format_seconds(row["forward_and_jacobian"]),
                f"{format_seconds(row['forward_compile'])} / {format_seconds(row['jacobian_compile'])}",
                f"{row['peak_mb']:.0f} MB",
                format_seconds(row["pyeit_forward"]),
                format_seconds(row["pyeit_jacobian"]),
                fraction(row["forward"], row["pyeit_forward"]),
                fraction(row["jacobian"], row["pyeit_jacobian"]),
            ]
        )
        if row.get("pyeit_note"):
            notes.append(row["pyeit_note"])
    for note in dict.fromkeys(notes + failures):
        print(f"note: {note}")

    print()
    print(f"backends and precision (device {machine['device']}; accuracy against host_sparse float64):")
    print()
    table = MarkdownTable(
        [
            "triangles",
            "backend",
            "precision",
            "forward",
            "Jacobian",
            "forward / host f64",
            "Jacobian / host f64",
            "compile fwd / Jac",
            "voltage error",
            "Jacobian error",
            "residual",
            "CG iterations",
            "runs fwd / Jac",
        ]
    )
    notes = []
    for row in rows:
        reference = row["backends"][0]
        for result in row["backends"]:
            if "skipped" in result:
                notes.append(result["skipped"])
            elif "error" in result:
                notes.append(f"{result['backend']} {result['precision']} at {row['triangles']}: {result['error']}")
            else:
                table.row(_backend_cells(row, result, reference))
    host_float32 = [result for row in rows for result in row["backends"][1:] if result["backend"] == "host_sparse"]
    if any("forward" in result for result in host_float32):
        notes.append("host_sparse float32 solves in float64 on the host: its time measures the conversion only")
    for note in dict.fromkeys(notes):
        print(f"note: {note}")
    write_tables("forward_jacobian", printed)

    save_json(options, machine, rows)


if __name__ == "__main__":
    main()
