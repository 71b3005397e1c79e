"""Reconstruction: one-step set-up, per-frame and batch throughput (against pyEIT 1.2.4's JAC and
the machine's matrix-multiply rate), absolute Gauss-Newton (against pyEIT's gn() on the same mesh
and data in the same run), and total variation (against L-BFGS, the method it replaced).

    python benchmarks/inverse.py [--sizes 700 2800 8000] [--repeats 5] [--frames 1000]
        [--skip-pyeit] [--skip-gn] [--skip-tv] [--pyeit-gn-limit 4000] [--blas-threads N] [--json PATH]

The problem: unit disc, 16 electrodes of width 0.2, adjacent protocol (M = 208 voltages), contact
impedance 0.01, background 1 S/sq. The data: a touch (conductivity -50% in a disc of radius 0.2
at (0.5, 0)) simulated with diffeit's complete electrode model on the reconstruction mesh itself,
plus 1% noise (docs, Conventions: standard deviation 1% of RMS(V_ref), seeded); a batch is `--frames`
frames of that touch, each with noise of its own. diffeit reconstructs with
`OneStep(model, "noser", HYPERPARAMETER)`; pyEIT with `JAC` and `setup(p=0.5, lamb, method="kotre",
perm=1.0)`, the same NOSER prior, `lamb` converted from diffeit's hyperparameter by
`diffeit.inverse.to_external_hyperparameter` (the same regularisation), point electrodes at
diffeit's point-electrode nodes (the closest pyEIT offers), on the very same nodes and triangles
and the same data (volts per ampere: pyEIT drives 1 A). The position errors of both images (the
"position error" column, metres) show that both solve the same problem.

Table 1, set-up, the time until the reconstruction matrix is ready:

- diffeit: `OneStep(model, ...)` and `.matrix.block_until_ready()`: the model's voltages and
  Jacobian at the background (one sparse factorisation), the prior, the 208 x 208
  measurement-space eigendecomposition and the (E, M) matrix. The model is built beforehand
  (its construction is the "model" column). Each timed call has a background of its own
  (1 + k 1e-6), so no host factorisation cached by an earlier call is reused. "first set-up" is
  the first `OneStep` on a new `ForwardModel` in the process: it includes the JIT compilation of
  the forward solve and the Jacobian, which happens once per mesh. "new model on an equal mesh +
  set-up": a `ForwardModel` on the same mesh generated anew and its first `OneStep` (one call):
  compiled functions are keyed by the mesh's content, so it compiles nothing.
- pyEIT: `JAC(mesh, protocol)` and `setup(...)`: its Jacobian (a dense N x N inverse), J^T J,
  and the inverse of the E x E matrix J^T J + lamb R. No warm-up call (pure NumPy, nothing to
  compile); the series stops after MIN_RUNS calls once they took SLOW_CASE_SECONDS (the runs
  column).

The ratio column is diffeit's set-up time over pyEIT's ("1/30": diffeit 30 times faster).

Table 2, one frame (M,) in float64, medians over PER_FRAME_CALLS calls:

- `reconstruct`: `rec.solve(dv).value` with dv a NumPy array, what users call: the input checks
  (shape, finiteness, in NumPy), the product and the finiteness of the image (its result code)
  under `jax.jit`, and the check of the code (`throw=True`);
- `dv @ matrix.T`: the same product evaluated eagerly, for comparison (eager JAX materialises
  the transposed matrix on every call, which is why reconstruct jits it);
- `jit product`: `jax.jit(lambda dv, m: dv @ m.T)` on arrays on the device (the transpose is
  folded into the product);
- `NumPy`: `dv @ matrix.T` in NumPy (OpenBLAS), the machine's matrix-vector rate;
- `pyEIT solve`: `solver.solve(v1, v0)`, one frame.

Table 3, a batch of T = `--frames` frames (T, M), medians over `--repeats` calls after a warm-up:

- `reconstruct`: `rec.solve(frames).value`, frames a NumPy float64 array; frames per second;
- `NumPy matmul`: `frames @ matrix.T` in NumPy with the same shapes and dtype, in the same
  process with the same BLAS threads: the machine's matrix-multiply rate for these shapes, in
  GFLOP/s = 2 T M E / time; `ours / NumPy` is reconstruct's time over it (the target: at most 2x);
- `jit product`: the product under `jax.jit` on the default device with the operands already
  there (XLA's own matrix multiply; on an accelerator, the device's rate);
- float32: the same three with float32 frames (float32 in, float32 out; `reconstruct` converts
  the float64 matrix inside its jitted product); `f32 error`: the relative 2-norm difference of the
  float32 images from the float64 ones;
- `pyEIT loop`: pyEIT has no batch call: `solve` in a Python loop over the T frames (all of them,
  no extrapolation); `ours / pyEIT` is reconstruct's time over it.

`CPU/wall` is the process's CPU time over the wall time in the timed calls of that column: about
the number of cores it kept busy (XLA's CPU matmul uses its own threads, not BLAS's, so it may
use more cores than `--blas-threads` gives NumPy).

Table 4, where reconstruct's time goes (same sizes, float64 and float32): the input checks alone
(`diffeit.inverse.linearised.check_frames`), what an eager `matrix.T.astype(dtype)` would cost on
every call (reconstruct's jitted product avoids it), and the product with the transposed matrix
made beforehand.

Table 5, absolute Gauss-Newton with at most GN_ITERATIONS = 20 iterations, on the scene of
tests/test_gauss_newton.py: a disc of radius 0.2 at (0.5, 0) with 10 times the background of
2 S/sq, absolute voltages simulated with the complete electrode model on a finer data mesh
(8,864 triangles, or at least DATA_REFINEMENT times the reconstruction's triangles), plus 1% noise
(1% of RMS(v), seeded):

- diffeit: `AbsoluteGaussNewton(model, "laplace", 1e-2, max_iterations=20).solve(v)` (the
  tests' settings) on the reconstruction mesh's model (complete electrode model, contact impedance 0.01,
  built beforehand). No noise level is given, so the discrepancy principle does not stop it; it
  may still stop before 20 iterations when its objective stagnates (a relative decrease below
  1e-6): the "iterations" column says how many it took and why it stopped. The time includes its
  start (the best homogeneous conductivity, three scalar Newton steps, and the prior at the start);
  "ours start" is the same call with `max_iterations=0` (the start alone), "ours per iteration"
  (total - start) / iterations, and "ratio at 20 (projected)" pyEIT's time over start + 20 x per
  iteration: what 20 iterations would cost if diffeit did not stop. Medians of `--repeats` calls
  after one warm-up call (the "first call" column: it compiles the batched forward solve and
  Jacobian); every call scales the data by 1 + k 1e-12 (k counting the calls), so no call
  reuses an earlier call's factorisations of the same iterates from the solver's cache.
- pyEIT: `gn(v / drive_current, x0=start, maxiter=20, gtol=0, method="kotre", p=0.5, lamb=1e-3)`
  on the same nodes, triangles and data (volts per ampere: pyEIT drives 1 A), from diffeit's
  homogeneous start (the solution's `stats["reference"]`), with `generator=True` to count the iterates:
  gtol=0 makes it do exactly 20 iterations (its default 1e-4 may stop it earlier, and then drops
  the last step). Each iteration recomputes pyEIT's Jacobian (a dense N x N inverse and a Python
  loop over the elements) and inverts the E x E matrix J^T J + lamb R. The `JAC.setup` that gn()
  requires is done before and not timed (gn() does not use its work). lamb was chosen by hand on
  this scene (see PYEIT_GN_LAMB); pyEIT's gn() iterates on the conductivity itself (no positivity)
  and its regulariser only damps each step (no pull towards the start). Every call is timed (no
  warm-up); the series stops after one call once the calls took SLOW_CASE_SECONDS, and pyEIT is
  left out above `--pyeit-gn-limit` triangles (default 4,000: at 8,000 an iteration takes tens of
  seconds).
- Quality, both images alike (tests/test_gauss_newton.py): the background is the area-weighted
  mean conductivity beyond 0.15 of the disc's edge; "position error" that of the change from it
  (`diffeit.metrics.position_error`, m), "correlation" `diffeit.metrics.correlation` with the
  truth (the inclusion interpolated onto the reconstruction mesh), "peak / true" the largest
  conductivity over the true 20 S/sq.

Table 6, total variation (diffeit only: pyEIT 1.2.4 has no TV solver): `TotalVariation(model,
0.05)` (its default hyperparameter, advised for 1% noise; primal-dual Newton) on the one-step touch
(-50% in a disc of radius 0.2 at (0.5, 0)), simulated on the data mesh with 1% noise (of
RMS(V_ref)), against the method it replaced as a peer: `optimistix.LBFGS` (rtol 1e-6, atol 1e-8,
history 10, at most 10,000 steps: TotalVariation's former defaults) minimising the same objective
`TotalVariation.objective` from the same one-step Laplace warm start, jitted. "set-up": the
constructor (the linearised problem, the edge list, the Newton matrix's pattern and low-rank
factor, the warm-start matrix) at a background of its own per call (as table 1); "reconstruct":
`solve(dv)` for one frame (`reconstruct` is `solve` plus a convergence warning); "batch of
TV_BATCH, per frame": `solve(frames)` for TV_BATCH = 10 frames of the touch with noise of their
own, one call, over 10; "L-BFGS": the peer on the one frame. The three are interleaved, medians
after one warm-up call each ("first reconstruct": the JIT compilation of the solve). Iterations
(linear systems solved) against L-BFGS steps; "gradient": max |grad f| / max |grad f(0)| at each
image (jax.grad of the objective, the convergence certificate); the figures as in table 5, "peak /
true" the image's peak over the true -0.5, "edge width" the 10-90% transition width of
tests/test_total_variation.py (the area where the image lies between 10% and 90% of its peak,
over the true edge length 2 pi 0.2; the true image interpolated onto the mesh has the value in
brackets). The target line: one frame at about TARGET_TV_SIZE triangles in at most
TARGET_TV_SECONDS. Left out, with a note, when `diffeit.inverse.total_variation` or optimistix
cannot be imported.

How: each mesh size runs in its own process. Calls of the columns of a table are interleaved
(one call of each in turn, per repeat), so that a change of load on a shared machine hits them
alike; times are medians after one warm-up call of each. `--blas-threads N` sets
OPENBLAS_NUM_THREADS, OMP_NUM_THREADS and MKL_NUM_THREADS for the measuring processes: it
governs NumPy's matmul and pyEIT (and SciPy's LAPACK in the set-ups), not XLA, which runs
diffeit's products on its own thread pool (the CPU/wall columns show how many cores each used).

Caveats:

- The matrix-multiply rate is NumPy's OpenBLAS at the BLAS thread setting; XLA's product (the
  jit column) can be faster or slower than OpenBLAS for the same shapes.
- Tables 1-4: the touch data are simulated on the reconstruction mesh (an inverse crime): the position errors
  are a sanity check that both tools reconstruct the same touch, not a quality figure (see
  tests/test_one_step.py for that).
  Tables 5 and 6 simulate their data on a finer mesh, so their figures are quality figures.
- Table 5: pyEIT's point electrodes do not model the electrodes' width and contact impedance,
  which the data have: at the homogeneous start its voltages differ from the data by about 10%
  (diffeit's model matches the data's physics). For absolute imaging this is a real handicap for
  pyEIT's image quality; its cost is unaffected. diffeit usually stops before 20 iterations
  (stagnation): compare the per-iteration and projected columns for equal iteration counts.
- diffeit's model is the complete electrode model, pyEIT's point electrodes: their Jacobians
  differ a little, their costs hardly.
- The script runs unchanged on a GPU machine (with `--skip-pyeit`, pyEIT is CPU only). There,
  `reconstruct` includes the host-to-device transfer of the frames and the device-to-host copy of
  its finiteness check, and leaves the images on the device; NumPy's matmul is the host CPU's.
- On a shared machine the times depend on the load (its load average is in the header line);
  `--blas-threads 1` steadies NumPy's and pyEIT's times on few cores.
"""

from __future__ import annotations

import argparse
import itertools
import math
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

HYPERPARAMETER = 0.2  # diffeit's unit-free lambda (about what GCV picks for these data); pyEIT's lamb converted
TOUCH_CENTRE, TOUCH_RADIUS, TOUCH_CHANGE = (0.5, 0.0), 0.2, -0.5
NOISE_PERCENT = 1.0
SEED = 0
PER_FRAME_CALLS = 100  # calls per median in table 2
SLOW_CASE_SECONDS = 30.0  # a pyEIT series stops once its timed calls take this long ...
MIN_RUNS = 2  # ... but not before this many calls
TARGET_SETUP_SPEEDUP, TARGET_SETUP_SIZE = 30.0, 2800  # issue targets: set-up >= 30x faster at about 2,800
TARGET_MATMUL_RATIO = 2.0  # batch reconstruct within 2x of the matmul time

# Tables 5 and 6: the absolute scene (tests/test_gauss_newton.py) and the touch, simulated on a finer mesh.
GN_CENTRE, GN_RADIUS, GN_CONTRAST, GN_BACKGROUND = (0.5, 0.0), 0.2, 10.0, 2.0  # a disc 10x a background of 2 S/sq
DATA_H = 0.03  # the data mesh (8,864 triangles, as the tests) ...
DATA_REFINEMENT = 2.5  # ... or finer: at least this many times the reconstruction's triangles
GN_ITERATIONS = 20
GN_PRIOR, GN_HYPERPARAMETER = "laplace", 1e-2  # diffeit's settings in tests/test_gauss_newton.py
# pyEIT's gn(): Kotre's prior as in tables 1-4. lamb chosen on this scene among 1e-4 .. 1 (kotre p=0.5, and "lm"):
# 1e-3 gave about the best correlation (0.89-0.90 at 700 and 2,800 triangles) with a positive image; 1e-2 and
# above flatten the disc (peak 12-32% of the truth), 3e-4 and below bring the minimum towards 0, "lm" (NOSER) with
# lamb 0.1 goes negative (-8.6 S/sq), with lamb 1 correlates at 0.64.
PYEIT_GN_METHOD, PYEIT_GN_P, PYEIT_GN_LAMB = "kotre", 0.5, 1e-3
PYEIT_GN_LIMIT = 4000  # no pyEIT gn() above this many triangles (an E x E inverse per iteration: ~30 s at 8,000)
TARGET_GN_SPEEDUP, TARGET_GN_SIZE = 30.0, 2800  # issue target: Gauss-Newton >= 30x faster than pyEIT at ~2,800
TV_HYPERPARAMETER = 0.05  # TotalVariation's default, its docstring's advice for 1% noise
TV_BATCH = 10  # frames in table 6's batch
# Table 6's peer, the method TotalVariation used before: optimistix.LBFGS with its old defaults.
TV_LBFGS_RTOL, TV_LBFGS_ATOL, TV_LBFGS_MAX_STEPS, TV_LBFGS_HISTORY = 1e-6, 1e-8, 10_000, 10
TARGET_TV_SECONDS, TARGET_TV_SIZE = 0.2, 2900  # issue target: TV at most 0.2 s a frame at about 2,900 triangles


class Series:
    """Wall and CPU times of the timed calls of one function."""

    def __init__(self) -> None:
        self.first: float | None = None
        self.wall: list[float] = []
        self.cpu: list[float] = []

    def call(self, function: Callable[[], object]) -> object:
        wall, cpu = time.perf_counter(), time.process_time()
        result = function()
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        if self.first is None:
            self.first = wall
        else:
            self.wall.append(wall)
            self.cpu.append(cpu)
        return result

    def summary(self) -> dict:
        if not self.wall:
            return {"median": self.first, "first": self.first, "runs": 1, "cores": None}
        return {
            "median": statistics.median(self.wall),
            "first": self.first,
            "runs": len(self.wall),
            "cores": sum(self.cpu) / sum(self.wall) if sum(self.wall) > 0 else None,
        }


def _interleaved(functions: dict[str, Callable[[], object]], repeats: int) -> dict[str, dict]:
    """Each function once (warm-up), then `repeats` rounds of one timed call of each in turn."""
    series = {name: Series() for name in functions}
    for _ in range(repeats + 1):
        for name, function in functions.items():
            series[name].call(function)
    return {name: s.summary() for name, s in series.items()}


def _budgeted(
    function: Callable[[], object], repeats: int, warm_up: bool = True, min_runs: int = MIN_RUNS
) -> tuple[dict, object]:
    """(summary, last result) of up to `repeats` timed calls, fewer once they took
    SLOW_CASE_SECONDS (at least `min_runs`); without `warm_up` the first call is timed too."""
    series = Series()
    if not warm_up:
        series.first = 0.0  # nothing to warm up: every call counts
    result = series.call(function)
    while len(series.wall) < repeats and not (len(series.wall) >= min_runs and sum(series.wall) > SLOW_CASE_SECONDS):
        result = series.call(function)
    summary = series.summary()
    if not warm_up:
        summary["first"] = None
    return summary, result


def run_one(n_triangles: int, options: argparse.Namespace) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    import diffeit as de
    from diffeit.inverse import OneStep

    jnp.zeros(1).block_until_ready()  # start the backend outside the timings
    mesh = disc_with_about(n_triangles)
    protocol = de.protocol.adjacent(16)

    def new_model():
        return de.ForwardModel(mesh, protocol, contact_impedance=0.01)

    row: dict = {"triangles": mesh.n_elements, "nodes": mesh.n_nodes, "frames": options.frames}

    # Table 1: set-up. The first OneStep on a fresh model compiles; later ones at new backgrounds don't reuse
    # a cached factorisation.
    model = new_model()
    fresh = itertools.count(1)

    def set_up():
        reconstruction = OneStep(model, "noser", HYPERPARAMETER, background=1.0 + 1e-6 * next(fresh))
        reconstruction.matrix.block_until_ready()
        return reconstruction

    setup, _ = _budgeted(set_up, options.repeats)
    model_time, _ = _budgeted(new_model, options.repeats)
    row.update(setup=setup, model=model_time)
    # A model on an equal mesh generated anew, and its first set-up: compiled functions are
    # keyed by the mesh's content, so this compiles nothing.
    equal_mesh = disc_with_about(n_triangles)
    start = time.perf_counter()
    equal_model = de.ForwardModel(equal_mesh, protocol, contact_impedance=0.01)
    OneStep(equal_model, "noser", HYPERPARAMETER).matrix.block_until_ready()
    row["equal_mesh_setup"] = time.perf_counter() - start

    # The data: a touch simulated on this mesh, 1% noise, seeded.
    reconstruction = OneStep(model, "noser", HYPERPARAMETER)
    matrix = reconstruction.matrix
    n_meas, n_elem = model.n_measurements, model.n_elements
    reference = np.asarray(model.measure(np.ones(n_elem)))
    touch = 1.0 + TOUCH_CHANGE * de.mesh.disc_fraction(mesh, TOUCH_CENTRE, TOUCH_RADIUS)
    clean = np.asarray(model.measure(touch)) - reference
    rng = np.random.default_rng(SEED)
    noise = NOISE_PERCENT / 100 * np.sqrt(np.mean(reference**2))
    difference = clean + noise * rng.standard_normal(n_meas)
    frames = clean + noise * rng.standard_normal((options.frames, n_meas))
    image = np.asarray(reconstruction.solve(difference).value)
    row["position_error"] = de.metrics.position_error(mesh, image, TOUCH_CENTRE)

    pyeit = None
    if options.skip_pyeit:
        row["pyeit_note"] = "pyEIT skipped (--skip-pyeit)"
    else:
        pyeit = _pyeit_solver(model, reconstruction)
        if isinstance(pyeit, str):
            row["pyeit_note"], pyeit = pyeit, None
    if pyeit is not None:
        row["pyeit_setup"], solver = _budgeted(pyeit, options.repeats, warm_up=False)
        volts_per_amp = difference / model.drive_current  # pyEIT drives 1 A
        zeros = np.zeros(n_meas)
        pyeit_image = np.real(solver.solve(v1=volts_per_amp, v0=zeros, normalize=False))
        row["pyeit_position_error"] = de.metrics.position_error(mesh, pyeit_image, TOUCH_CENTRE)

    # Table 2: one frame.
    product = jax.jit(lambda dv, m: dv @ m.T)
    matrix_host = np.asarray(matrix)
    difference_device = jax.device_put(difference)
    per_frame = {
        "reconstruct": lambda: reconstruction.solve(difference).value.block_until_ready(),
        "eager": lambda: (difference_device @ matrix.T).block_until_ready(),
        "jit": lambda: product(difference_device, matrix).block_until_ready(),
        "numpy": lambda: difference @ matrix_host.T,
    }
    if pyeit is not None:
        per_frame["pyeit"] = lambda: solver.solve(v1=volts_per_amp, v0=zeros, normalize=False)
    row["per_frame"] = _interleaved(per_frame, PER_FRAME_CALLS)

    # Table 3: a batch, float64 and float32.
    frames32, matrix32_host = frames.astype(np.float32), matrix_host.astype(np.float32)
    frames_device, frames32_device = jax.device_put(frames), jax.device_put(frames32)
    matrix32 = jax.device_put(matrix32_host)
    batch = {
        "reconstruct": lambda: reconstruction.solve(frames).value.block_until_ready(),
        "numpy": lambda: frames @ matrix_host.T,
        "jit": lambda: product(frames_device, matrix).block_until_ready(),
        "reconstruct32": lambda: reconstruction.solve(frames32).value.block_until_ready(),
        "numpy32": lambda: frames32 @ matrix32_host.T,
        "jit32": lambda: product(frames32_device, matrix32).block_until_ready(),
    }
    row["batch"] = _interleaved(batch, options.repeats)
    row["flop"] = 2.0 * options.frames * n_meas * n_elem
    images = np.asarray(reconstruction.solve(frames).value)
    images32 = np.asarray(reconstruction.solve(frames32).value)
    row["batch_dtype"] = str(reconstruction.solve(frames).value.dtype)
    row["batch32_dtype"] = str(images32.dtype)
    row["batch_error"] = float(np.linalg.norm(images - frames @ matrix_host.T) / np.linalg.norm(images))
    row["float32_error"] = float(np.linalg.norm(images32 - images) / np.linalg.norm(images))
    if pyeit is not None:

        def pyeit_loop():
            for frame in frames / model.drive_current:
                solver.solve(v1=frame, v0=zeros, normalize=False)

        row["pyeit_batch"], _ = _budgeted(pyeit_loop, options.repeats)

    row["breakdown"] = _breakdown(reconstruction, difference, frames, options.repeats)

    # Tables 5 and 6: data simulated on a finer mesh.
    if not (options.skip_gn and options.skip_tv):
        data_h = min(DATA_H, 2.7 / (DATA_REFINEMENT * mesh.n_elements) ** 0.5)  # h ~ 2.7 / sqrt(triangles)
        data_mesh = de.mesh.disc(16, electrode_width=0.2, h=data_h)
        data_model = de.ForwardModel(data_mesh, protocol, contact_impedance=0.01)
        row["data_triangles"] = data_mesh.n_elements
    if not options.skip_gn:
        row["gauss_newton"] = _gauss_newton(model, data_model, options)
    if not options.skip_tv:
        row["total_variation"] = _total_variation(model, data_model, options)
    return row


def _pyeit_problem(model) -> tuple[object, object]:
    """pyEIT's mesh (the same nodes and triangles, point electrodes at diffeit's point-electrode
    nodes) and its adjacent protocol (the same 208 voltages in the same order)."""
    import numpy as np
    from pyeit.eit import protocol as pyeit_protocol
    from pyeit.mesh import PyEITMesh

    import diffeit as de

    point = de.ForwardModel(model.mesh, model.protocol, electrode_model="point")
    mesh = PyEITMesh(
        node=model.mesh.nodes,
        element=model.mesh.triangles,
        perm=1.0,
        el_pos=np.asarray(point.system.electrode_nodes),
        ref_node=0,
    )
    return mesh, pyeit_protocol.create(16, dist_exc=1, step_meas=1, parser_meas="std")


def _pyeit_solver(model, reconstruction) -> Callable[[], object] | str:
    """A function building and setting up pyEIT's JAC for the same problem, or why there is none."""
    import diffeit as de

    try:
        from pyeit.eit.jac import JAC
    except ImportError:
        return "pyEIT not installed"
    mesh, protocol = _pyeit_problem(model)
    lamb = de.inverse.to_external_hyperparameter(reconstruction, "pyeit")

    def set_up():
        solver = JAC(mesh, protocol)
        solver.setup(p=0.5, lamb=lamb, method="kotre", perm=1.0)
        return solver

    return set_up


def _breakdown(reconstruction, difference, frames, repeats: int) -> dict:
    """Table 4: the parts of `reconstruct` timed one by one (diffeit internals: never fatal)."""
    import jax.numpy as jnp
    import numpy as np

    try:
        from diffeit.inverse.linearised import check_frames
    except ImportError as error:
        return {"error": str(error)}
    matrix, n_meas = reconstruction.matrix, reconstruction.model.n_measurements
    result = {}
    for label, data, calls in (
        ("frame", difference, PER_FRAME_CALLS),
        ("batch", frames, repeats),
        ("batch32", frames.astype(np.float32), repeats),
    ):
        dtype = jnp.dtype(data.dtype)
        data_device = jnp.asarray(data)
        transposed = matrix.T.astype(dtype).block_until_ready()
        result[label] = _interleaved(
            {
                "reconstruct": lambda data=data: reconstruction.solve(data).value.block_until_ready(),
                "checks": lambda data=data: check_frames(data, n_meas, "frames").block_until_ready(),
                "transpose": lambda dtype=dtype: matrix.T.astype(dtype).block_until_ready(),
                "product": lambda d=data_device, t=transposed: (d @ t).block_until_ready(),
            },
            calls,
        )
    return result


def _absolute_quality(mesh, conductivity, truth) -> dict:
    """The figures of tests/test_gauss_newton.py: the background (area-weighted mean beyond
    0.15 of the disc's edge), the position error of the change from it, the correlation with the
    truth, and the peak over the true peak."""
    import numpy as np

    import diffeit as de

    conductivity = np.asarray(conductivity, dtype=float)
    outside = de.mesh.disc_fraction(mesh, GN_CENTRE, GN_RADIUS + 0.15) == 0
    background = float(np.average(conductivity[outside], weights=mesh.element_areas[outside]))
    return {
        "background": background,
        "position_error": de.metrics.position_error(mesh, conductivity - background, GN_CENTRE),
        "correlation": de.metrics.correlation(mesh, truth, conductivity),
        "peak": float(conductivity.max() / (GN_CONTRAST * GN_BACKGROUND)),
        "minimum": float(conductivity.min()),
    }


def _gauss_newton(model, data_model, options: argparse.Namespace) -> dict:
    """Table 5: absolute Gauss-Newton, diffeit against pyEIT's gn(), on the same data."""
    import jax.numpy as jnp
    import numpy as np

    import diffeit as de
    from diffeit.inverse import AbsoluteGaussNewton

    mesh, fine = model.mesh, data_model.mesh
    inclusion = GN_BACKGROUND * (1 + (GN_CONTRAST - 1) * de.mesh.disc_fraction(fine, GN_CENTRE, GN_RADIUS))
    clean = np.asarray(data_model.measure(jnp.asarray(inclusion)))
    rng = np.random.default_rng(SEED)  # 1% of RMS(v), as tests/test_gauss_newton.py
    voltages = clean + NOISE_PERCENT / 100 * np.sqrt(np.mean(clean**2)) * rng.standard_normal(clean.shape)
    truth = de.mesh.interpolate(inclusion, fine, mesh)

    results, calls = {}, itertools.count()

    def run(iterations: int):
        # Data scaled by 1 + k 1e-12 per call: the iterates differ, so no call finds an earlier
        # call's factorisations in the solver's cache.
        # A capped run: stopping at the iteration limit is the intent, not a failure.
        solver = AbsoluteGaussNewton(model, GN_PRIOR, GN_HYPERPARAMETER, max_iterations=iterations)
        results[iterations] = solver.solve(voltages * (1 + 1e-12 * next(calls)), throw=False)

    timings = _interleaved({"full": lambda: run(GN_ITERATIONS), "start": lambda: run(0)}, options.repeats)
    result = results[GN_ITERATIONS]
    entry = {
        "ours": timings["full"],
        "start": timings["start"],
        "iterations": int(result.stats["iterations"]),
        "stop_reason": _outcomes(result.result, success="stagnation")[0],  # no noise level: no discrepancy stop
        "homogeneous_start": float(result.stats["reference"][0]),
        "quality": _absolute_quality(mesh, result.value, truth),
    }

    if options.skip_pyeit:
        entry["pyeit_note"] = "pyEIT skipped (--skip-pyeit)"
        return entry
    if mesh.n_elements > options.pyeit_gn_limit:
        entry["pyeit_note"] = (
            f"pyEIT gn() left out above {options.pyeit_gn_limit} triangles (an E x E inverse per iteration; "
            "--pyeit-gn-limit)"
        )
        return entry
    try:
        from pyeit.eit.jac import JAC
    except ImportError:
        entry["pyeit_note"] = "pyEIT not installed"
        return entry
    pyeit_mesh, protocol = _pyeit_problem(model)
    solver = JAC(pyeit_mesh, protocol)
    # gn() refuses to run before setup(); setup's own work (at perm 1) is not used by gn() and not timed.
    solver.setup(p=PYEIT_GN_P, lamb=PYEIT_GN_LAMB, method=PYEIT_GN_METHOD, perm=1.0)
    volts_per_amp = voltages / model.drive_current  # pyEIT drives 1 A
    start = np.asarray(result.stats["reference"], dtype=float)

    def pyeit_gn() -> tuple[int, np.ndarray]:
        count, image = 0, start
        for image in solver.gn(  # noqa: B007 (the last iterate is the image)
            volts_per_amp,
            x0=start.copy(),
            maxiter=GN_ITERATIONS,
            gtol=0.0,  # never stops early: exactly GN_ITERATIONS iterations
            p=PYEIT_GN_P,
            lamb=PYEIT_GN_LAMB,
            method=PYEIT_GN_METHOD,
            generator=True,
        ):
            count += 1
        return count, np.real(image)

    entry["pyeit"], (count, image) = _budgeted(pyeit_gn, options.repeats, warm_up=False, min_runs=1)
    entry["pyeit_iterations"] = count
    entry["pyeit_quality"] = _absolute_quality(mesh, image, truth)
    return entry


def _total_variation(model, data_model, options: argparse.Namespace) -> dict:
    """Table 6: TotalVariation's set-up, one frame and a batch, against L-BFGS (optimistix) on
    the same objective from the same warm start, the touch simulated on the data mesh."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import diffeit as de

    try:
        import optimistix as optx

        from diffeit.inverse.total_variation import TotalVariation
    except ImportError as error:
        return {"note": f"TotalVariation or optimistix not available ({error}): no TV rows"}
    mesh, fine = model.mesh, data_model.mesh
    reference = np.asarray(data_model.measure(jnp.ones(fine.n_elements)))
    touch = 1.0 + TOUCH_CHANGE * de.mesh.disc_fraction(fine, TOUCH_CENTRE, TOUCH_RADIUS)
    rng = np.random.default_rng(SEED)
    clean = np.asarray(data_model.measure(jnp.asarray(touch))) - reference
    noise_level = NOISE_PERCENT / 100 * np.sqrt(np.mean(reference**2))
    difference = clean + noise_level * rng.standard_normal(len(reference))
    frames = clean + noise_level * rng.standard_normal((TV_BATCH, len(reference)))  # noise of their own
    truth = de.mesh.interpolate(touch - 1.0, fine, mesh)

    fresh = itertools.count(1)

    def set_up():  # a background of its own per call, as table 1: no cached factorisation reused
        reconstruction = TotalVariation(model, TV_HYPERPARAMETER, background=1.0 + 1e-6 * next(fresh))
        jax.block_until_ready((reconstruction.operator, reconstruction.initial_matrix))
        return reconstruction

    setup, _ = _budgeted(set_up, options.repeats)
    reconstruction = TotalVariation(model, TV_HYPERPARAMETER)
    problem = reconstruction.problem

    # The previous method, as a peer: L-BFGS (optimistix) on the same f, in the same relative units,
    # from the same warm start, with the tolerances TotalVariation had before.
    lbfgs = optx.LBFGS(rtol=TV_LBFGS_RTOL, atol=TV_LBFGS_ATOL, history_length=TV_LBFGS_HISTORY)

    @jax.jit
    def peer(voltage_difference):
        start = reconstruction.initial_matrix @ (voltage_difference / problem.data_scale) * problem.background
        solution = optx.minimise(
            lambda x, _: reconstruction.objective(x, voltage_difference),
            lbfgs,
            start,
            max_steps=TV_LBFGS_MAX_STEPS,
            throw=False,
        )
        return solution.value, solution.stats["num_steps"], solution.result == optx.RESULTS.successful

    def ours():
        return jax.block_until_ready(reconstruction.solve(difference, throw=False))

    def ours_batch():
        return jax.block_until_ready(reconstruction.solve(frames, throw=False))

    def theirs():
        return jax.block_until_ready(peer(jnp.asarray(difference)))

    timings = _interleaved({"ours": ours, "batch": ours_batch, "lbfgs": theirs}, options.repeats)
    solution, batch = ours(), ours_batch()
    peer_image, peer_steps, peer_success = theirs()
    gradient = jax.jit(jax.grad(reconstruction.objective))
    gradient_scale = float(jnp.abs(gradient(jnp.zeros(mesh.n_elements), difference)).max())

    def figures(image) -> dict:
        image = np.asarray(image)
        return {
            "position_error": de.metrics.position_error(mesh, image, TOUCH_CENTRE),
            "correlation": de.metrics.correlation(mesh, truth, image),
            "peak": float(image[np.argmax(np.abs(image))] / TOUCH_CHANGE),
            "edge_width": _transition_width(mesh, image),
            "gradient": float(jnp.abs(gradient(jnp.asarray(image), difference)).max()) / gradient_scale,
            "objective": float(reconstruction.objective(jnp.asarray(image), difference)),
        }

    return {
        "setup": setup,
        "frame": timings["ours"],
        "batch": timings["batch"],
        "lbfgs": timings["lbfgs"],
        "iterations": int(solution.stats["iterations"]),
        "stop_reason": _outcomes(solution.result)[0],
        "batch_iterations": [int(n) for n in np.asarray(batch.stats["iterations"])],
        "batch_stop_reasons": _outcomes(batch.result),
        "lbfgs_steps": int(peer_steps),
        "lbfgs_stop": "converged" if bool(peer_success) else "not converged",
        "ours_quality": figures(solution.value),
        "lbfgs_quality": figures(peer_image),
        "truth_edge_width": _transition_width(mesh, np.asarray(truth)),
    }


_OUTCOMES = {
    "successful": "converged",
    "max_iterations_reached": "max_iterations",
    "line_search_failed": "line_search_failed",
    "stalled": "stalled",
    "nonfinite": "failed",
}


def _outcomes(result, success: str = "converged") -> list[str]:
    """A word for each frame's `diffeit.results.RESULTS` code (`success` for a successful one)."""
    import numpy as np

    from diffeit.results import RESULTS

    matches = {name: np.atleast_1d(np.asarray(result == getattr(RESULTS, name))) for name in _OUTCOMES}
    words = {**_OUTCOMES, "successful": success}
    return [words[next(name for name in _OUTCOMES if matches[name][k])] for k in range(len(matches["successful"]))]


def _transition_width(mesh, image) -> float:
    """Edge blur (m) of a touch-sized disc's image (`diffeit.metrics.transition_width`)."""
    import diffeit as de

    return de.metrics.transition_width(mesh, image, 2 * math.pi * TOUCH_RADIUS)


# ---------------------------------------------------------------------------------------------
# Tables


def _median(entry: dict | None) -> float | None:
    return None if entry is None else entry["median"]


def _cores(entry: dict | None) -> str:
    return "-" if entry is None or entry.get("cores") is None else f"{entry['cores']:.1f}"


def _rate(flop: float, entry: dict) -> str:
    return f"{flop / entry['median'] / 1e9:.1f}"


def _print_tables(rows: list[dict], machine: dict, options: argparse.Namespace) -> None:
    _print_setup(rows)
    _print_one_frame(rows)
    _print_batch(rows, machine, options)
    _print_breakdown(rows)
    _print_gauss_newton([row for row in rows if "gauss_newton" in row])
    _print_total_variation([row for row in rows if "setup" in row.get("total_variation", {})])


def _pair(ours: dict, theirs: dict | None, key: str, digits: int) -> str:
    """The figure `key` as "ours / theirs", or ours alone when the peer did not run."""
    return f"{ours[key]:.{digits}f}" + (f" / {theirs[key]:.{digits}f}" if theirs else "")


def _print_setup(rows: list[dict]) -> None:
    print("set-up (diffeit OneStep NOSER against pyEIT JAC kotre p=0.5, the same lamb):")
    print()
    table = MarkdownTable(
        [
            "triangles",
            "nodes",
            "set-up",
            "first set-up (compile)",
            "new model on an equal mesh + set-up",
            "model",
            "pyEIT set-up",
            "set-up ratio",
            "pyEIT runs",
            "position error ours / pyEIT",
        ]
    )
    for row in rows:
        pyeit = row.get("pyeit_setup")
        errors = f"{row['position_error']:.3f}"
        if row.get("pyeit_position_error") is not None:
            errors += f" / {row['pyeit_position_error']:.3f}"
        table.row(
            [
                str(row["triangles"]),
                str(row["nodes"]),
                format_seconds(row["setup"]["median"]),
                format_seconds(row["setup"]["first"]),
                format_seconds(row.get("equal_mesh_setup")),
                format_seconds(row["model"]["median"]),
                format_seconds(_median(pyeit)),
                fraction(row["setup"]["median"], _median(pyeit)),
                str(pyeit["runs"]) if pyeit else "-",
                errors + " m",
            ]
        )


def _print_one_frame(rows: list[dict]) -> None:
    print()
    print(f"one frame (float64, medians of {PER_FRAME_CALLS} calls):")
    print()
    table = MarkdownTable(
        [
            "triangles",
            "reconstruct",
            "dv @ matrix.T (eager)",
            "jit product",
            "NumPy",
            "pyEIT solve",
            "reconstruct / NumPy",
            "reconstruct / pyEIT",
        ]
    )
    for row in rows:
        frame = row["per_frame"]
        ours = frame["reconstruct"]["median"]
        table.row(
            [
                str(row["triangles"]),
                format_seconds(ours),
                format_seconds(frame["eager"]["median"]),
                format_seconds(frame["jit"]["median"]),
                format_seconds(frame["numpy"]["median"]),
                format_seconds(_median(frame.get("pyeit"))),
                relative(ours, frame["numpy"]["median"]),
                fraction(ours, _median(frame.get("pyeit"))),
            ]
        )


def _print_batch(rows: list[dict], machine: dict, options: argparse.Namespace) -> None:
    print()
    print(
        f"batch of {options.frames} frames (T, 208) -> (T, E) (NumPy matmul: {machine['blas']}, "
        f"{options.blas_threads or 'default'} BLAS threads; jit product: XLA on {machine['device']}):"
    )
    print()
    table = MarkdownTable(
        [
            "triangles",
            "reconstruct",
            "frames/s",
            "NumPy matmul",
            "NumPy GFLOP/s",
            "ours / NumPy",
            "jit product",
            "jit GFLOP/s",
            "ours / jit",
            "CPU/wall ours / NumPy / jit",
            "f32 reconstruct",
            "f32 NumPy",
            "f32 NumPy GFLOP/s",
            "f32 ours / NumPy",
            "f32 jit",
            "f32 error",
            "pyEIT loop",
            "ours / pyEIT",
        ]
    )
    for row in rows:
        batch, flop = row["batch"], row["flop"]
        ours, ours32 = batch["reconstruct"]["median"], batch["reconstruct32"]["median"]
        table.row(
            [
                str(row["triangles"]),
                format_seconds(ours),
                f"{row['frames'] / ours:,.0f}",
                format_seconds(batch["numpy"]["median"]),
                _rate(flop, batch["numpy"]),
                relative(ours, batch["numpy"]["median"]),
                format_seconds(batch["jit"]["median"]),
                _rate(flop, batch["jit"]),
                relative(ours, batch["jit"]["median"]),
                f"{_cores(batch['reconstruct'])} / {_cores(batch['numpy'])} / {_cores(batch['jit'])}",
                format_seconds(ours32),
                format_seconds(batch["numpy32"]["median"]),
                _rate(flop, batch["numpy32"]),
                relative(ours32, batch["numpy32"]["median"]),
                format_seconds(batch["jit32"]["median"]),
                f"{row['float32_error']:.1e}",
                format_seconds(_median(row.get("pyeit_batch"))),
                fraction(ours, _median(row.get("pyeit_batch"))),
            ]
        )


def _print_breakdown(rows: list[dict]) -> None:
    print()
    print("where reconstruct's time goes (input checks; an eager matrix.T.astype(dtype), which its jitted product")
    print("avoids; the product with a transposed matrix made beforehand):")
    print()
    table = MarkdownTable(["triangles", "input", "reconstruct", "checks", "matrix.T.astype", "product alone"])
    for row in rows:
        breakdown = row["breakdown"]
        if "error" in breakdown:
            continue
        for label, name in (("frame", "1 frame f64"), ("batch", f"{row['frames']} f64"), ("batch32", "... f32")):
            parts = breakdown[label]
            table.row(
                [
                    str(row["triangles"]),
                    name,
                    *(
                        format_seconds(parts[part]["median"])
                        for part in ("reconstruct", "checks", "transpose", "product")
                    ),
                ]
            )


def _print_gauss_newton(gn_rows: list[dict]) -> None:
    if not gn_rows:
        return
    print()
    print(
        f"absolute Gauss-Newton, {GN_ITERATIONS} iterations at most: ours AbsoluteGaussNewton({GN_PRIOR!r}, "
        f"{GN_HYPERPARAMETER:g}, max_iterations={GN_ITERATIONS}), no noise level (so no discrepancy stop); pyEIT "
        f"gn(maxiter={GN_ITERATIONS}, gtol=0, method={PYEIT_GN_METHOD!r}, p={PYEIT_GN_P:g}, "
        f"lamb={PYEIT_GN_LAMB:g}) from our homogeneous start; a disc r {GN_RADIUS:g} at {GN_CENTRE}, "
        f"{GN_CONTRAST:g}x a background of {GN_BACKGROUND:g} S/sq, simulated on the data mesh, "
        f"{NOISE_PERCENT:g}% noise. per iteration: ours (total - start) / iterations, pyEIT total / iterations; "
        f"at {GN_ITERATIONS} (projected): ours start + {GN_ITERATIONS} x per iteration, over pyEIT's total:"
    )
    print()
    table = MarkdownTable(
        [
            "triangles",
            "data triangles",
            "iterations ours (stop) / pyEIT",
            "ours",
            "first call (compile)",
            "ours start",
            "ours per iteration",
            "pyEIT",
            "pyEIT per iteration",
            "pyEIT runs",
            "ratio",
            "per-iteration ratio",
            f"ratio at {GN_ITERATIONS} (projected)",
            "position error ours / pyEIT",
            "correlation ours / pyEIT",
            "peak / true ours / pyEIT",
            "background ours / pyEIT",
        ]
    )
    for row in gn_rows:
        gn = row["gauss_newton"]
        figures = _gn_figures(gn)
        pyeit, ours, theirs = gn.get("pyeit"), gn["quality"], gn.get("pyeit_quality")

        iterations = f"{gn['iterations']} ({gn['stop_reason']})"
        if pyeit:
            iterations += f" / {gn['pyeit_iterations']}"
        table.row(
            [
                str(row["triangles"]),
                str(row["data_triangles"]),
                iterations,
                format_seconds(gn["ours"]["median"]),
                format_seconds(gn["ours"]["first"]),
                format_seconds(gn["start"]["median"]),
                format_seconds(figures["ours_per_iteration"]),
                format_seconds(_median(pyeit)),
                format_seconds(figures.get("pyeit_per_iteration")),
                str(pyeit["runs"]) if pyeit else "-",
                fraction(gn["ours"]["median"], _median(pyeit)),
                fraction(figures["ours_per_iteration"], figures.get("pyeit_per_iteration")),
                fraction(figures["ours_projected"], _median(pyeit)),
                _pair(ours, theirs, "position_error", 3) + " m",
                _pair(ours, theirs, "correlation", 2),
                _pair(ours, theirs, "peak", 2),
                _pair(ours, theirs, "background", 2) + " S/sq",
            ]
        )


def _print_total_variation(tv_rows: list[dict]) -> None:
    if not tv_rows:
        return
    print()
    print(
        f"total variation (diffeit only: pyEIT has none): TotalVariation(model, {TV_HYPERPARAMETER:g}), "
        "primal-dual Newton, against L-BFGS (optimistix, "
        f"rtol {TV_LBFGS_RTOL:g}, atol {TV_LBFGS_ATOL:g}, max_steps {TV_LBFGS_MAX_STEPS}, "
        f"history {TV_LBFGS_HISTORY}: the previous method) on the same objective from the same warm start; "
        f"one frame of the touch ({TOUCH_CHANGE:+.0%} in a disc r {TOUCH_RADIUS:g} at {TOUCH_CENTRE}) "
        f"simulated on the data mesh, {NOISE_PERCENT:g}% noise, and a batch of {TV_BATCH} such frames "
        "(noise of their own) in one call; gradient: max |grad f| / max |grad f(0)|; edge width: 10-90% "
        "transition area over the true edge length (truth: the interpolated true image's):"
    )
    print()
    table = MarkdownTable(
        [
            "triangles",
            "set-up",
            "first set-up",
            "reconstruct",
            "first reconstruct (compile)",
            f"batch of {TV_BATCH}, per frame",
            "L-BFGS",
            "ours / L-BFGS",
            "runs",
            "iterations (stop) / L-BFGS steps (stop)",
            "gradient ours / L-BFGS",
            "position error ours / L-BFGS",
            "correlation ours / L-BFGS",
            "peak / true ours / L-BFGS",
            "edge width ours / L-BFGS (truth)",
        ]
    )
    for row in tv_rows:
        tv = row["total_variation"]
        ours, theirs = tv["ours_quality"], tv["lbfgs_quality"]

        table.row(
            [
                str(row["triangles"]),
                format_seconds(tv["setup"]["median"]),
                format_seconds(tv["setup"]["first"]),
                format_seconds(tv["frame"]["median"]),
                format_seconds(tv["frame"]["first"]),
                format_seconds(tv["batch"]["median"] / TV_BATCH),
                format_seconds(tv["lbfgs"]["median"]),
                fraction(tv["frame"]["median"], tv["lbfgs"]["median"]),
                str(tv["frame"]["runs"]),
                f"{tv['iterations']} ({tv['stop_reason']}) / {tv['lbfgs_steps']} ({tv['lbfgs_stop']})",
                f"{ours['gradient']:.0e} / {theirs['gradient']:.0e}",
                _pair(ours, theirs, "position_error", 3) + " m",
                _pair(ours, theirs, "correlation", 3),
                _pair(ours, theirs, "peak", 3),
                _pair(ours, theirs, "edge_width", 3) + f" ({tv['truth_edge_width']:.3f}) m",
            ]
        )


def _gn_figures(gn: dict) -> dict:
    """Per-iteration times and diffeit's projection to GN_ITERATIONS iterations (see table 5)."""
    total, start = gn["ours"]["median"], gn["start"]["median"]
    per_iteration = (total - start) / gn["iterations"] if gn["iterations"] else None
    figures = {
        "ours_per_iteration": per_iteration,
        "ours_projected": None if per_iteration is None else start + GN_ITERATIONS * per_iteration,
    }
    if gn.get("pyeit") and gn["pyeit_iterations"]:
        figures["pyeit_per_iteration"] = gn["pyeit"]["median"] / gn["pyeit_iterations"]
    return figures


def _targets(rows: list[dict]) -> list[str]:
    lines = []
    timed = [row for row in rows if row.get("pyeit_setup")]
    if timed:
        row = min(timed, key=lambda row: abs(row["triangles"] - TARGET_SETUP_SIZE))
        speedup = row["pyeit_setup"]["median"] / row["setup"]["median"]
        first = row["pyeit_setup"]["median"] / row["setup"]["first"]
        verdict = "met" if speedup >= TARGET_SETUP_SPEEDUP else "NOT met"
        lines.append(
            f"set-up at {row['triangles']} triangles: {speedup:.0f}x faster than pyEIT "
            f"(target {TARGET_SETUP_SPEEDUP:.0f}x: {verdict}); {first:.1f}x including the first call's compilation"
        )
    compared = [row for row in rows if row.get("gauss_newton", {}).get("pyeit")]
    if compared:
        row = min(compared, key=lambda row: abs(row["triangles"] - TARGET_GN_SIZE))
        gn, figures = row["gauss_newton"], _gn_figures(row["gauss_newton"])
        pyeit = gn["pyeit"]["median"]
        speedup = pyeit / gn["ours"]["median"]
        verdict = "met" if speedup >= TARGET_GN_SPEEDUP else "NOT met"
        line = (
            f"absolute Gauss-Newton at {row['triangles']} triangles: {speedup:.0f}x faster than pyEIT's "
            f"{gn['pyeit_iterations']}-iteration gn() (ours: {gn['iterations']} iterations, {gn['stop_reason']}; "
            f"target {TARGET_GN_SPEEDUP:.0f}x: {verdict})"
        )
        if figures["ours_projected"] is not None:
            projected = pyeit / figures["ours_projected"]
            verdict = "met" if projected >= TARGET_GN_SPEEDUP else "NOT met"
            line += (
                f"; at the same {GN_ITERATIONS} iterations (projected) {projected:.0f}x ({verdict}), "
                f"per iteration {figures['pyeit_per_iteration'] / figures['ours_per_iteration']:.0f}x"
            )
        lines.append(line + f"; {pyeit / gn['ours']['first']:.1f}x including the first call's compilation")
    tv_rows = [row for row in rows if "setup" in row.get("total_variation", {})]
    if tv_rows:
        row = min(tv_rows, key=lambda row: abs(row["triangles"] - TARGET_TV_SIZE))
        tv = row["total_variation"]
        frame = tv["frame"]["median"]
        verdict = "met" if frame <= TARGET_TV_SECONDS else "NOT met"
        lines.append(
            f"TV at ~{TARGET_TV_SIZE} triangles ({row['triangles']}): {frame:.3f} s per frame "
            f"(target {TARGET_TV_SECONDS:g} s: {verdict}); {tv['iterations']} iterations against "
            f"{tv['lbfgs_steps']} L-BFGS steps, {tv['lbfgs']['median'] / frame:.0f}x faster; in a batch of "
            f"{TV_BATCH}: {tv['batch']['median'] / TV_BATCH:.3f} s per frame"
        )
    for row in rows:
        ratio = row["batch"]["reconstruct"]["median"] / row["batch"]["numpy"]["median"]
        verdict = "met" if ratio <= TARGET_MATMUL_RATIO else "NOT met"
        lines.append(
            f"batch at {row['triangles']} triangles: reconstruct takes {ratio:.2f}x the NumPy matmul's time "
            f"(target <= {TARGET_MATMUL_RATIO:.0f}x: {verdict})"
        )
    return lines


def _child_command(options: argparse.Namespace, size: int) -> list[str]:
    command = [sys.executable, __file__, "--one", str(size), "--repeats", str(options.repeats)]
    command += ["--frames", str(options.frames), "--pyeit-gn-limit", str(options.pyeit_gn_limit)]
    flags = {"--skip-pyeit": options.skip_pyeit, "--skip-gn": options.skip_gn, "--skip-tv": options.skip_tv}
    return command + [flag for flag, given in flags.items() if given]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    driver_arguments(parser, [700, 2800, 8000])
    parser.add_argument("--frames", type=int, default=1000, help="frames in a batch (default 1000)")
    parser.add_argument("--skip-pyeit", action="store_true", help="leave pyEIT out")
    parser.add_argument("--skip-gn", action="store_true", help="leave out table 5 (absolute Gauss-Newton)")
    parser.add_argument("--skip-tv", action="store_true", help="leave out table 6 (total variation)")
    parser.add_argument(
        "--pyeit-gn-limit",
        type=int,
        default=PYEIT_GN_LIMIT,
        metavar="TRIANGLES",
        help=f"run pyEIT's gn() only up to this many triangles (default {PYEIT_GN_LIMIT})",
    )
    options = parser.parse_args()
    if options.repeats < 1:
        parser.error("--repeats must be at least 1")
    if options.frames < 1:
        parser.error("--frames must be at least 1")
    if child_work(options, run_one):
        return

    machine = describe_machine(__file__, options.blas_threads)
    printed = record_output()  # the tables also go to docs/benchmarks/inverse.md
    print(
        machine_line(machine, with_pyeit=not options.skip_pyeit)
        + f", {options.repeats} repeats, {options.frames} frames"
    )
    print()
    rows, notes = [], []
    for row, failure in measure_sizes(options, lambda size: _child_command(options, size)):
        if row is None:
            notes.append(failure)
            continue
        rows.append(row)
        if row.get("pyeit_note"):
            notes.append(row["pyeit_note"])
        if "error" in row["breakdown"]:
            notes.append(f"no breakdown: {row['breakdown']['error']}")
        if row.get("gauss_newton", {}).get("pyeit_note"):
            notes.append(row["gauss_newton"]["pyeit_note"])
        if row.get("total_variation", {}).get("note"):
            notes.append(row["total_variation"]["note"])
    if rows:
        _print_tables(rows, machine, options)
    print()
    for line in _targets(rows):
        print(f"target: {line}")
    for note in dict.fromkeys(notes):
        print(f"note: {note}")
    write_tables("inverse", printed)

    save_json(options, machine, rows)


if __name__ == "__main__":
    main()
