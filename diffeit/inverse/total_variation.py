"""Total-variation difference reconstruction: sharp-edged changes (touches) on the linearised
problem, solved by the primal-dual Newton method of Chan, Golub and Mulet (1999) in tens of
iterations, each a sparse solve and a small dense one; a batch of frames is one jitted call,
vmapped over the frames.

On the normalised linearised problem of `LinearisedProblem` (x = dsigma / background per
element, unit-free; y = dV / s with s = RMS(V_0) volts; J_n = diag(1/s) J diag(background)),
`TotalVariation` minimises the unit-free objective

    f(x) = ||J_n x - y||^2 + lambda^2 TV_beta(x),
    TV_beta(x) = sum_edges w_e (sqrt((x_i - x_j)^2 + beta^2) - beta),   w_e = l_e / l_ref,

over the interior edges e shared by elements i and j, with l_e the edge's length (m) and
l_ref = sqrt(A / pi) the radius of the disc with the sheet's area A (m; 1 on the unit disc).
As beta -> 0, TV_beta(x) -> (1/l_ref) sum_e l_e |x_i - x_j| = (1/l_ref) int |grad x| dA, the
jump of the relative change times the length of the jump set: a disc of radius r and relative
contrast a has TV = 2 pi r |a| / l_ref whatever the mesh. So lambda, like `OneStep`'s, is
unit-free and does not move with the drive current, the background level or the mesh size
(edge-length weights, not edge counts: the best lambda was 0.05 on unit-disc meshes of h = 0.06,
0.08 and 0.12 alike). On a touch on the unit disc with p% noise the best lambda (highest
correlation with the truth) was 2 to 5 times p/100 (0.02-0.05 at 0.3%, 0.05 at 1%, 0.1 at
3%): about twice the best one-step Laplace lambda, the same order, as both penalties are
weighed against the same unit-free data misfit. The `- beta` only makes TV_beta(0) = 0; it
changes no minimiser. beta is in the units of x (a relative change): 1e-3..1e-2 of the
expected contrast keeps edges sharp; smaller makes the problem stiffer (more iterations).

The method. With d = D x the edge differences ((D x)_e = x_i - x_j, D of shape (n_edges, E))
and psi_e = sqrt(d_e^2 + beta^2), the gradient is

    grad f(x) = 2 J_n^T (J_n x - y) + lambda^2 D^T W d / psi,   W = diag(w_e).

The primal-dual Newton method adds a dual variable u_e per edge (|u_e| <= 1; u = d / psi at
the minimiser) and linearises the pair of equations 2 J_n^T (J_n x - y) + lambda^2 D^T W u = 0
and psi u - d = 0. Eliminating the dual step leaves, for the primal step delta,

    (2 J_n^T J_n + lambda^2 D^T W K D) delta = -grad f(x),   K_e = (1 - u_e d_e / psi_e) / psi_e,

and the dual step du = K D delta + d / psi - u. K_e > 0 while |u_e| <= 1, so the matrix is
positive definite and delta a descent direction of f. At u = d / psi this is Newton's method on
f (K_e = beta^2 / psi_e^3: tiny across an edge, which makes the plain Newton iteration crawl); at
u = 0 it is the lagged-diffusivity (IRLS) step (K_e = 1 / psi_e, the curvature of a quadratic
that majorises TV_beta: safe but linearly convergent). Here:

- u starts at 0, and the iteration uses K_e = (1 - (1 - omega) u_e d_e / psi_e) / psi_e, the
  blend omega / psi_e + (1 - omega) K_e of the two curvatures: omega starts at 1, is halved
  after each iteration that took the full step and doubled (at most 1) after one whose step
  had to be shortened. The early iterations, where the warm start's smooth slopes have to
  become flat plateaus and jumps, no longer crawl: on the touch (2,894 triangles, four noise
  draws) 11 to 15 iterations at lambda 0.05 (the plain primal-dual method, omega = 0: 13 to
  15), 12 to 14 at lambda 0.02 (17 to 25), 18 to 24 at lambda 0.01 and beta 1e-4 (100 to 170).
- The primal step is scaled by backtracking (halving from 1) until f decreases by at least
  1e-4 of what the slope promises (Armijo): f decreases at every iteration.
- Each edge's dual variable takes the full step du_e or 0.99 of the way to |u_e| = 1,
  whichever is shorter.
- The iteration stops when `gradient_norm` = max |grad f(x)| / max |grad f(0)| is at most
  `gradient_tolerance`: the stop certifies the optimality condition, whatever the iteration
  did to get there. Near the minimiser the gradient falls by 10 to 1,000 per iteration. The
  minimum is flat: on the touch, 1e-6, the default, put the image within 1.5e-3 of its peak
  from the minimiser's (found with the tolerance 1e-12), 1e-4 left up to 12%.

L-BFGS, which this module used before, took about 700 to 2,500 steps on the same problem
(unit-disc meshes of 700 to 8,000 triangles); benchmarks/inverse.py (table 6) compares the two.

The linear system, without anything E x E. With A = lambda^2 D^T W K D + eps I (sparse, on the
element-adjacency pattern plus the diagonal) and 2 J_n^T J_n replaced by 2 B^T B (B of shape
(k, E), below), the Woodbury identity gives

    delta = A^-1 r - A^-1 B^T (I / 2 + B A^-1 B^T)^-1 B A^-1 r,   r = -grad f(x):

one sparse solve (`diffeit.linear_solve.solve_spd`, the model's solver backend) with k + 1
right-hand sides and a k x k Cholesky factorisation per iteration. eps makes A invertible
(D^T W K D vanishes on constant images): 1e-8 times the mean diagonal of 2 J_n^T J_n, or 1e-10
times the largest diagonal entry of lambda^2 D^T W K D if that is more (which keeps A's
condition number within what a factorisation in float64 resolves at huge lambda). B = Q^T J_n,
Q an orthonormal basis of the eigenvectors of J_n J_n^T with eigenvalues of at least 1e-2
lambda^2 (and above rounding) and of J_n 1, the data of a uniform change: B^T B is J_n^T J_n
without the data's curvature that lambda^2 TV_beta dwarfs, but whole on constant images, where
TV has none (k = 54 to 64 of the 104 independent adjacent readings at lambda 0.05 on unit-disc
meshes of 700 to 8,000 triangles: fewer right-hand sides, a faster solve). Both change only
the matrix, that is the step, never the gradient: the minimiser and the stopping test are
exact.

The warm start is the one-step Laplace solution at the same lambda (`OneStep`'s
measurement-space formula).
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._arrays import IdentityModule
from .._threads import one_blas_thread_in_xla
from ..forward import ForwardModel
from ..linear_solve import AbstractLinearSolver, SparsityPattern, solve_spd
from ..mesh import element_adjacency
from ..results import RESULTS, throw_if_failed
from .linearised import LinearisedProblem, check_frames, regularised_inverse
from .priors import Laplace, Tikhonov

_RIDGE = 1e-8
"""eps of the module docstring: at least this times the mean diagonal of 2 J_n^T J_n ..."""
_CONDITION = 1e-10
"""... and at least this times the largest diagonal entry of lambda^2 D^T W K D."""
_RANK_FRACTION = 1e-2
"""Eigenvalues of J_n J_n^T below this times lambda^2 are left out of the Newton matrix."""
_ARMIJO = 1e-4
_HALVINGS = 40


class TotalVariationSolution(eqx.Module):
    """What `TotalVariation.solve` returns; with a batch of T frames every field has a leading
    T axis.

    - `conductivity_change`: (E,) dsigma in S/sq.
    - `objective`: f(x) at the solution (unit-free, see the module docstring).
    - `residual_norm`: ||J_n x - y||, the normalised data misfit (compare it with the noise
      norm sqrt(M) p/100 for p% noise).
    - `total_variation`: TV_beta(x) at the solution (unit-free).
    - `gradient_norm`: max |grad f(x)| / max |grad f(0)| (max over elements), the convergence
      certificate (1 at x = 0, 0 at the minimiser).
    - `iterations`: primal-dual Newton iterations taken (linear systems solved).
    - `result`: `RESULTS.successful` when `gradient_norm` <= the reconstruction's
      `gradient_tolerance`; `RESULTS.max_iterations_reached` when the iteration limit came
      first; `RESULTS.stalled` when no step along the Newton direction (down to 2^-40 of it)
      decreased f enough (the Armijo test, allowing for rounding in f) before the gradient
      test was met: the iteration has reached the rounding level of f; `RESULTS.nonfinite`
      for a non-finite step (a linear solve that failed), the image then being the last
      finite iterate. One code per frame for a batch.
    """

    conductivity_change: jax.Array
    objective: jax.Array
    residual_norm: jax.Array
    total_variation: jax.Array
    gradient_norm: jax.Array
    iterations: jax.Array
    result: RESULTS


class _Operator(eqx.Module):
    """The arrays of the objective and of the Newton matrix.

    `jacobian` J_n (M, E); `first`, `second` (n_edges,) the elements of each interior edge and
    `weights` its w_e; `factor` B^T (E, k), the low-rank factor of J_n^T J_n (module
    docstring); `pattern` and `slots`: where the diagonal (E entries, first) and then the
    entries (i, i), (j, j), (i, j), (j, i) of each edge go in the values of A; `ridge` the
    least eps (1e-8 times the mean diagonal of 2 J_n^T J_n).
    """

    jacobian: jax.Array
    first: jax.Array
    second: jax.Array
    weights: jax.Array
    factor: jax.Array
    pattern: SparsityPattern = eqx.field(static=True)
    slots: jax.Array
    ridge: jax.Array


class TotalVariation(IdentityModule):
    """Smoothed total-variation difference reconstruction on the linearised problem.

    Minimises f(x) = ||J_n x - y||^2 + hyperparameter^2 TV_smoothing(x) over the relative
    change x = dsigma / background (see the module docstring for the normalisation, the edge
    weights and the method) by the primal-dual Newton method, and returns dsigma =
    background x in S/sq. Set-up builds J_n, the edge list, the sparsity pattern of the Newton
    matrix, the low-rank factor of J_n^T J_n and the warm-start matrix once. `solve` runs one
    jitted function, vmapped over the frames of a batch (compiled once per reconstruction
    shape whatever the number of frames; the frames of a batch iterate together until the
    slowest has stopped, each keeping its own result). The sparse solves use the model's
    solver backend (`model.solver`): with the host backend each iteration sends the matrices
    of all frames of a batch to the host in one callback, which factorises them one after
    the other, so on CPU a batch costs about as much per frame as single calls (the batch
    runs as many iterations as its slowest frame). Absolute differences only.

    `solve` and `reconstruct` take `throw=True` (the default): a frame that does not converge
    raises `diffeit.results.SolverError`; with `throw=False` the solution's `result` holds
    each frame's `diffeit.results.RESULTS` code (see `TotalVariationSolution`).

    **Arguments:**

    - `model`: the forward model of the reconstruction mesh.
    - `hyperparameter`: lambda > 0, unit-free. Larger flattens the image and lowers its
      contrast (TV's known bias); smaller lets noise through and needs more iterations. For
      p% noise (docs/science.md#noise) start near 2 to 5 times p/100 (see the module docstring).
    - `smoothing`: beta > 0, in units of the relative change (1e-3 = 0.1% of the background).
    - `background`: the reference conductivity, scalar or (E,), S/sq (held by `problem`).
    - `max_iterations`: the iteration limit (`RESULTS.max_iterations_reached` beyond it).
      The touch at the default settings takes 9 to 15 iterations on meshes of 400 to 8,000
      triangles; lambda = 0.01 (5 times below the advice for 1% noise) 15 to 25.
    - `gradient_tolerance`: the largest `gradient_norm` (see `TotalVariationSolution`) that
      counts as converged. Near the minimiser each iteration multiplies the gradient by
      1e-1 to 1e-3, so a tighter tolerance costs one or two iterations.
    - `warm_start`: start from the one-step Laplace solution at the same lambda (True) or from
      zero (False).
    """

    problem: LinearisedProblem = eqx.field(repr=False)
    """J_n and the data scale; its Laplace prior serves only the warm start."""
    hyperparameter: float = eqx.field(static=True)
    smoothing: float = eqx.field(static=True)
    max_iterations: int = eqx.field(static=True)
    gradient_tolerance: float = eqx.field(static=True)
    warm_start: bool = eqx.field(static=True)
    operator: _Operator = eqx.field(repr=False)
    initial_matrix: jax.Array = eqx.field(repr=False)
    """(E, M) maps y to the warm start x_0 (zeros without `warm_start`)."""

    def __init__(
        self,
        model: ForwardModel,
        hyperparameter: float = 0.05,
        smoothing: float = 1e-3,
        background: float | np.ndarray = 1.0,
        *,
        max_iterations: int = 100,
        gradient_tolerance: float = 1e-6,
        warm_start: bool = True,
    ) -> None:
        for name, value in (
            ("hyperparameter", hyperparameter),
            ("smoothing", smoothing),
            ("gradient_tolerance", gradient_tolerance),
        ):
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be finite and positive; got {value}")
        if int(max_iterations) != max_iterations or max_iterations < 1:
            raise ValueError(f"max_iterations must be a positive integer; got {max_iterations}")
        self.hyperparameter, self.smoothing = float(hyperparameter), float(smoothing)
        self.max_iterations, self.gradient_tolerance = int(max_iterations), float(gradient_tolerance)
        self.warm_start = bool(warm_start)
        # J_n does not depend on the prior; Laplace's covariance serves only the warm start.
        self.problem = LinearisedProblem(model, Laplace() if warm_start else Tikhonov(), background)
        self.operator = _newton_operator(self.problem, self.hyperparameter)
        if warm_start:
            initial = regularised_inverse(self.problem, self.hyperparameter)
        else:
            initial = np.zeros((model.n_elements, model.n_measurements))
        self.initial_matrix = jnp.asarray(initial)

    @property
    def model(self) -> ForwardModel:
        """The forward model of the reconstruction mesh."""
        return self.problem.model

    def objective(self, conductivity_change: jax.Array, voltage_difference: jax.Array) -> jax.Array:
        """f(x) (unit-free) for dsigma (E,) in S/sq and dV (M,) in volts, x = dsigma /
        background: a pure JAX function (grad, jit and vmap work on it)."""
        x = jnp.asarray(conductivity_change) / self.problem.background
        y = jnp.asarray(voltage_difference) / self.problem.data_scale
        return _objective(x, (self.operator, y, self.hyperparameter, self.smoothing))

    def solve(self, voltage_difference: jax.Array, *, throw: bool = True) -> TotalVariationSolution:
        """Reconstruct dV = V - V_reference (volts), (M,) or a batch (T, M), and report the
        solver's outcome per frame (see `TotalVariationSolution`). Non-finite or wrongly shaped
        frames raise ValueError; with `throw=True` a frame that did not converge raises
        `diffeit.results.SolverError` naming it. The solve runs in float64; dsigma is returned
        in the input's dtype."""
        dv = check_frames(voltage_difference, self.model.n_measurements, "voltage differences")
        y = jnp.atleast_2d(dv).astype(jnp.float64) / self.problem.data_scale
        settings = jnp.asarray([self.hyperparameter, self.smoothing, self.gradient_tolerance], dtype=jnp.float64)
        solution = _solve_frames(
            self.operator,
            y,
            self.initial_matrix,
            settings,
            max_iterations=self.max_iterations,
            solver=self.model.solver,
        )
        change = (solution.conductivity_change * self.problem.background).astype(dv.dtype)
        solution = eqx.tree_at(lambda s: s.conductivity_change, solution, change)
        if dv.ndim == 1:
            solution = jax.tree_util.tree_map(lambda a: a[0], solution)
        return throw_if_failed(solution, solution.result, "total variation") if throw else solution

    def reconstruct(self, voltage_difference: jax.Array, *, throw: bool = True) -> jax.Array:
        """dsigma (S/sq): (E,) for dV (M,) in volts, (T, E) for a batch (T, M), in the input's
        dtype; `solve` returns the details, and `throw` is its."""
        return self.solve(voltage_difference, throw=throw).conductivity_change


def _newton_operator(problem: LinearisedProblem, hyperparameter: float) -> _Operator:
    """The edges, their weights, the low-rank factor of J_n^T J_n and the sparsity pattern of
    the Newton matrix (module docstring)."""
    mesh = problem.model.mesh
    first, second, lengths = element_adjacency(mesh)
    if len(first) == 0:
        raise ValueError("the mesh has no interior edges: total variation is undefined")
    # l_ref = sqrt(A / pi): TV is a length ratio, independent of the mesh size (module docstring).
    reference_length = np.sqrt(mesh.element_areas.sum() / np.pi)
    n_elements = mesh.n_elements
    jacobian = problem.jacobian
    # B = Q^T J_n: B^T B = J_n^T Q Q^T J_n, J_n^T J_n without its smallest eigenvalues, but
    # exact on constant images (module docstring).
    eigenvalues, eigenvectors = np.linalg.eigh(jacobian @ jacobian.T)
    floor = max(_RANK_FRACTION * hyperparameter**2, len(eigenvalues) * np.finfo(float).eps * eigenvalues[-1])
    uniform = jacobian.sum(axis=1, keepdims=True)  # J_n 1
    basis = np.linalg.qr(np.hstack([eigenvectors[:, eigenvalues >= floor], uniform]))[0]
    diagonal = np.arange(n_elements)
    pattern, slots = SparsityPattern.from_entries(
        np.concatenate([diagonal, first, second, first, second]),
        np.concatenate([diagonal, first, second, second, first]),
        n_elements,
    )
    return _Operator(
        jacobian=jnp.asarray(jacobian),
        first=jnp.asarray(first),
        second=jnp.asarray(second),
        weights=jnp.asarray(lengths / reference_length),
        factor=jnp.asarray(jacobian.T @ basis),
        pattern=pattern,
        slots=jnp.asarray(slots),
        ridge=jnp.asarray(_RIDGE * 2 * np.sum(jacobian**2) / n_elements),
    )


def _total_variation(x: jax.Array, operator: _Operator, smoothing: jax.Array) -> jax.Array:
    """TV_beta(x) = sum_e w_e (sqrt((D x)_e^2 + beta^2) - beta), D x by two gathers."""
    return _edge_penalty(x[operator.first] - x[operator.second], operator.weights, smoothing)


def _edge_penalty(difference: jax.Array, weights: jax.Array, smoothing: jax.Array) -> jax.Array:
    # sqrt(d^2 + b^2) - b written as d^2 / (sqrt(d^2 + b^2) + b): no cancellation for d << b.
    return jnp.sum(weights * difference**2 / (jnp.sqrt(difference**2 + smoothing**2) + smoothing))


def _objective(x: jax.Array, args: tuple) -> jax.Array:
    operator, y, hyperparameter, smoothing = args
    residual = operator.jacobian @ x - y
    return residual @ residual + hyperparameter**2 * _total_variation(x, operator, smoothing)


def _edge_transpose(values: jax.Array, operator: _Operator) -> jax.Array:
    """D^T v for v (n_edges,): two scatter-adds."""
    size = operator.jacobian.shape[1]
    return jnp.zeros(size, values.dtype).at[operator.first].add(values).at[operator.second].add(-values)


class _State(NamedTuple):
    x: jax.Array
    dual: jax.Array
    residual: jax.Array  # J_n x - y
    value: jax.Array  # f(x)
    gradient: jax.Array
    iterations: jax.Array
    blend: jax.Array  # omega, the weight of the lagged-diffusivity curvature
    stop: RESULTS  # successful while going on, else why it stopped early: stalled or nonfinite


@partial(jax.jit, static_argnames=("max_iterations", "solver"))
def _solve_frames(
    operator: _Operator,
    y: jax.Array,
    initial_matrix: jax.Array,
    settings: jax.Array,
    *,
    max_iterations: int,
    solver: AbstractLinearSolver,
) -> TotalVariationSolution:
    """One primal-dual Newton solve per row of y (T, M), vmapped; x in relative units.
    `settings` holds lambda, beta and the gradient tolerance: traced, so changing them does not
    compile again."""
    hyperparameter, smoothing, gradient_tolerance = settings
    weight = hyperparameter**2 * operator.weights
    jacobian, factor = operator.jacobian, operator.factor
    n_elements, rank = factor.shape

    def gradient(x: jax.Array, residual: jax.Array) -> jax.Array:
        difference = x[operator.first] - x[operator.second]
        slope = difference / jnp.sqrt(difference**2 + smoothing**2)
        return 2 * jacobian.T @ residual + _edge_transpose(weight * slope, operator)

    def newton_step(state: _State) -> _State:
        x, dual = state.x, state.dual
        difference = x[operator.first] - x[operator.second]
        magnitude = jnp.abs(difference)
        psi = jnp.sqrt(difference**2 + smoothing**2)
        # K = (1 - (1 - omega) u d / psi) / psi, written without cancellation as 1 - |d| / psi =
        # beta^2 / (psi (psi + |d|)): both terms are >= 0 while |u| <= 1.
        blended = (1 - state.blend) * dual
        curvature = (smoothing**2 / (psi + magnitude) + magnitude - blended * difference) / psi**2
        coupling = weight * curvature
        diagonal = (
            jnp.zeros(n_elements, coupling.dtype).at[operator.first].add(coupling).at[operator.second].add(coupling)
        )
        ridge = jnp.maximum(operator.ridge, _CONDITION * jnp.max(diagonal))
        entries = jnp.concatenate([jnp.broadcast_to(ridge, (n_elements,)), coupling, coupling, -coupling, -coupling])
        values = jnp.zeros(operator.pattern.nnz, entries.dtype).at[operator.slots].add(entries)
        # A^-1 [-grad f, B^T] in one solve with k + 1 right-hand sides, then Woodbury.
        solved = solve_spd(
            operator.pattern, values, jnp.concatenate([-state.gradient[:, None], factor], axis=1), solver
        )
        plain, spread = solved[:, 0], solved[:, 1:]
        capacitance = 0.5 * jnp.eye(rank) + factor.T @ spread
        capacitance = 0.5 * (capacitance + capacitance.T)
        correction = jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(capacitance, lower=True), factor.T @ plain)
        step = plain - spread @ correction

        # Backtracking on f: f(x + s step) <= f(x) + 1e-4 s slope, s = 1, 1/2, ... The last
        # term allows for rounding in f, so steps at its rounding level are still taken.
        slope = state.gradient @ step
        step_difference = step[operator.first] - step[operator.second]
        step_residual = jacobian @ step
        allowance = 4 * jnp.finfo(state.value.dtype).eps * jnp.abs(state.value)

        def trial(length: jax.Array) -> jax.Array:
            residual = state.residual + length * step_residual
            penalty = _edge_penalty(difference + length * step_difference, weight, smoothing)
            return residual @ residual + penalty

        def too_high(search: tuple) -> jax.Array:
            length, value, halvings = search
            return (value > state.value + _ARMIJO * length * slope + allowance) & (halvings < _HALVINGS)

        def halve(search: tuple) -> tuple:
            length, _value, halvings = search
            return 0.5 * length, trial(0.5 * length), halvings + 1

        length, value, halvings = jax.lax.while_loop(too_high, halve, (jnp.ones(()), trial(jnp.ones(())), 0))
        accepted = (value <= state.value + _ARMIJO * length * slope + allowance) & (slope < 0)
        length = jnp.where(accepted, length, 0.0)
        stop = RESULTS.where(
            jnp.all(jnp.isfinite(step)), RESULTS.where(accepted, RESULTS.successful, RESULTS.stalled), RESULTS.nonfinite
        )

        # The dual step, edge by edge: the full Newton step, or 0.99 of the way to |u| = 1.
        dual_step = curvature * step_difference + difference / psi - dual
        room = jnp.where(dual_step > 0, 1 - dual, -1 - dual) / jnp.where(dual_step == 0, 1.0, dual_step)
        dual = dual + jnp.minimum(1.0, 0.99 * jnp.where(dual_step == 0, jnp.inf, room)) * dual_step

        x = jnp.where(accepted, x + length * step, x)
        residual = jnp.where(accepted, state.residual + length * step_residual, state.residual)
        return _State(
            x=x,
            dual=jnp.where(accepted, dual, state.dual),
            residual=residual,
            value=jnp.where(accepted, value, state.value),
            gradient=gradient(x, residual),
            iterations=state.iterations + 1,
            blend=jnp.minimum(1.0, jnp.where(halvings == 0, 0.5, 2.0) * state.blend),
            stop=stop,
        )

    def one(frame: jax.Array) -> TotalVariationSolution:
        scale = jnp.max(jnp.abs(2 * jacobian.T @ frame))  # max |grad f(0)|
        scale = jnp.where(scale > 0, scale, 1.0)
        x = initial_matrix @ frame
        difference = x[operator.first] - x[operator.second]
        residual = jacobian @ x - frame
        start = _State(
            x=x,
            dual=jnp.zeros_like(difference),
            residual=residual,
            value=residual @ residual + _edge_penalty(difference, weight, smoothing),
            gradient=gradient(x, residual),
            iterations=jnp.zeros((), jnp.int32),
            blend=jnp.ones(()),
            stop=RESULTS.successful,
        )

        def going_on(state: _State) -> jax.Array:
            norm = jnp.max(jnp.abs(state.gradient))
            # `norm > tolerance` is False for NaN: a non-finite gradient stops the iteration.
            going = (norm > gradient_tolerance * scale) & (state.iterations < max_iterations)
            return going & (state.stop == RESULTS.successful)

        state = jax.lax.while_loop(going_on, newton_step, start)
        gradient_norm = jnp.max(jnp.abs(state.gradient)) / scale
        finite = jnp.all(jnp.isfinite(state.x)) & jnp.isfinite(gradient_norm)
        result = RESULTS.where(
            gradient_norm <= gradient_tolerance,
            RESULTS.successful,
            RESULTS.where(
                finite,
                RESULTS.where(state.stop == RESULTS.successful, RESULTS.max_iterations_reached, state.stop),
                RESULTS.nonfinite,
            ),
        )
        # The figures afresh (the iteration updates the residual by increments).
        residual = jacobian @ state.x - frame
        total_variation = _total_variation(state.x, operator, smoothing)
        return TotalVariationSolution(
            conductivity_change=state.x,
            objective=residual @ residual + hyperparameter**2 * total_variation,
            residual_norm=jnp.sqrt(residual @ residual),
            total_variation=total_variation,
            gradient_norm=gradient_norm,
            iterations=state.iterations,
            result=result,
        )

    # The k x k Cholesky factorisations call LAPACK on CPU, the host solves SciPy: both on one
    # BLAS thread for the whole solve, taken and released once (see `diffeit._threads`).
    return one_blas_thread_in_xla(jax.vmap(one))(y)
