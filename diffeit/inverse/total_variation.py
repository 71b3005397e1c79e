"""Total-variation difference reconstruction: sharp-edged changes (touches) on the linearised
problem, solved by the primal-dual Newton method of Chan, Golub and Mulet (1999) in tens of
iterations, each a sparse solve and a small dense one; a batch of frames is one jitted call,
vmapped over the frames.

On the normalised linearised problem of `LinearisedProblem` (x = dsigma / background, y = dV / s,
J_n), `TotalVariation` minimises the unit-free objective

    f(x) = ||J_n x - y||^2 + lambda^2 TV_beta(x),
    TV_beta(x) = sum_edges w_e (sqrt((x_i - x_j)^2 + beta^2) - beta),   w_e = l_e / l_ref,

over the interior edges e shared by elements i and j (l_e the edge's length, l_ref = sqrt(A / pi)
for the sheet's area A), so that lambda is unit-free and independent of the mesh. The
primal-dual Newton step, its blend with the lagged-diffusivity step, the line search, the
stopping test, the low-rank Woodbury solve of the Newton system and the measurements behind the
defaults are in docs/science.md#total-variation.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._threads import one_blas_thread_in_xla
from ..forward import ForwardModel
from ..linear_solve import AbstractLinearSolver, SparsityPattern, solve_spd
from ..mesh import element_adjacency
from ..results import RESULTS
from .linearised import LinearisedProblem, check_frames, regularised_inverse
from .priors import Laplace, Tikhonov
from .solution import AbstractSolver, Solution, finished, model_of

_RIDGE = 1e-8
"""eps (docs/science.md#total-variation): at least this times the mean diagonal of 2 J_n^T J_n ..."""
_CONDITION = 1e-10
"""... and at least this times the largest diagonal entry of lambda^2 D^T W K D."""
_RANK_FRACTION = 1e-2
"""Eigenvalues of J_n J_n^T below this times lambda^2 are left out of the Newton matrix."""
_ARMIJO = 1e-4
_HALVINGS = 40


class _Outcome(eqx.Module):
    """One primal-dual Newton solve per frame, in relative units (see `TotalVariation.solve`)."""

    x: jax.Array
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


class TotalVariation(AbstractSolver):
    """Smoothed total-variation difference reconstruction: sharp-edged changes (touches).

    Minimises f(x) = ||J_n x - y||^2 + hyperparameter^2 TV_smoothing(x) over the relative
    change x = dsigma / background on the normalised linearised problem of
    `LinearisedProblem` (absolute differences), TV weighed by edge length so that the
    hyperparameter is unit-free, by the primal-dual Newton method of Chan, Golub and Mulet
    (1999): tens of iterations, each one sparse solve (the model's solver backend) and one
    small dense one, starting from the one-step Laplace image at the same hyperparameter.
    Set-up builds the Newton matrix's pattern, a low-rank factor of J_n^T J_n and the
    warm-start matrix once; `solve` is one jitted function vmapped over the frames of a batch
    (which iterate together until the slowest has stopped, each with its own result). The
    objective, the method and measurements of its settings are in
    docs/science.md#total-variation.

    Arguments:
        model: The forward model of the reconstruction mesh; None for an unbound solver (see
            `bound`).
        hyperparameter: lambda > 0, unit-free. Larger flattens the image and lowers its
            contrast; smaller lets noise through and needs more iterations. For p% noise start
            near 2 to 5 times p/100.
        smoothing: beta > 0, in units of the relative change (1e-3 = 0.1% of the background).
        background: The reference conductivity, S/sq, scalar or (E,).
        max_iterations: The iteration limit (`RESULTS.max_iterations_reached` beyond it).
        gradient_tolerance: The largest gradient norm max |grad f(x)| / max |grad f(0)| that
            counts as converged.
        warm_start: Start from the one-step Laplace solution at the same lambda (True) or from
            zero (False).

    Attributes:
        hyperparameter: lambda (static).
        smoothing: beta (static).
        background: The background conductivity as given (S/sq, scalar or (E,)).
        max_iterations: The iteration limit (static).
        gradient_tolerance: As given (static).
        warm_start: As given (static).
        problem: The `LinearisedProblem`: J_n and the data scale; its Laplace prior serves
            only the warm start. None when unbound.
        operator: The edges, their weights, the low-rank factor of J_n^T J_n and the Newton
            matrix's pattern (internal); None when unbound.
        initial_matrix: (E, M) maps y to the warm start x_0 (zeros without `warm_start`);
            None when unbound.

    Raises:
        ValueError: For a hyperparameter, smoothing or gradient tolerance that is not finite
            and positive, a `max_iterations` that is not a positive integer, a background
            that is not finite and positive or of the wrong shape, or a mesh without interior
            edges.
    """

    hyperparameter: float = eqx.field(static=True)
    smoothing: float = eqx.field(static=True)
    background: float | np.ndarray = eqx.field(repr=False)
    max_iterations: int = eqx.field(static=True)
    gradient_tolerance: float = eqx.field(static=True)
    warm_start: bool = eqx.field(static=True)
    problem: LinearisedProblem | None = eqx.field(repr=False)
    operator: _Operator | None = eqx.field(repr=False)
    initial_matrix: jax.Array | None = eqx.field(repr=False)

    def __init__(
        self,
        model: ForwardModel | None = None,
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
        self.background = background
        if model is None:
            self.problem = self.operator = self.initial_matrix = None
            return
        # J_n does not depend on the prior; Laplace's covariance serves only the warm start.
        self.problem = LinearisedProblem(model, Laplace() if warm_start else Tikhonov(), background)
        self.operator = _newton_operator(self.problem, self.hyperparameter)
        if warm_start:
            initial = regularised_inverse(self.problem, self.hyperparameter)
        else:
            initial = np.zeros((model.n_elements, model.n_measurements))
        self.initial_matrix = jnp.asarray(initial)

    @property
    def model(self) -> ForwardModel | None:
        """The forward model of the reconstruction mesh (None when unbound)."""
        return None if self.problem is None else self.problem.model

    def bound(
        self, model: ForwardModel, background: float | np.ndarray | None = None, *, hyperparameter: float | None = None
    ) -> TotalVariation:
        """This solver's settings on another model (see `AbstractSolver.bound`).

        Arguments:
            model: The forward model to reconstruct on.
            background: The background conductivity (S/sq, scalar or (E,)); None keeps this
                solver's.
            hyperparameter: lambda replacing this solver's; None keeps it.

        Returns:
            A new `TotalVariation` on `model`.
        """
        return TotalVariation(
            model,
            self.hyperparameter if hyperparameter is None else hyperparameter,
            self.smoothing,
            self.background if background is None else background,
            max_iterations=self.max_iterations,
            gradient_tolerance=self.gradient_tolerance,
            warm_start=self.warm_start,
        )

    def objective(self, conductivity_change: jax.Array, voltage_difference: jax.Array) -> jax.Array:
        """The objective f(x) (unit-free) of an image.

        A pure JAX function: grad, jit and vmap work on it.

        Arguments:
            conductivity_change: dsigma (E,), S/sq (x = dsigma / background).
            voltage_difference: dV (M,), volts.

        Returns:
            f(x), a scalar.

        Raises:
            ValueError: For an unbound solver.
        """
        model_of(self)
        x = jnp.asarray(conductivity_change) / self.problem.background
        y = jnp.asarray(voltage_difference) / self.problem.data_scale
        return _objective(x, (self.operator, y, self.hyperparameter, self.smoothing))

    def solve(self, data: jax.Array, *, throw: bool = True) -> Solution:
        """Reconstruct voltage differences dV = V - V_reference, volts.

        The solve runs in float64; the image comes back in the input's dtype.

        Arguments:
            data: dV, (M,) or a batch (T, M), volts.
            throw: Raise for a frame that did not converge (True), or return its code.

        Returns:
            The `Solution`: `value` dsigma (E,) or (T, E), S/sq; `result` per frame
            `RESULTS.successful` when the gradient norm reached `gradient_tolerance`,
            `RESULTS.max_iterations_reached`, `RESULTS.stalled` (no step along the Newton
            direction, down to 2^-40 of it, decreased f: the iteration reached the rounding
            level of f) or `RESULTS.nonfinite` (a failed linear solve; the image is then the
            last finite iterate). `stats` (one value per frame): "objective" f(x) at the
            solution; "residual_norm" ||J_n x - y||, the normalised data misfit (compare it
            with sqrt(M) p/100 for p% noise); "total_variation" TV_beta(x); "gradient_norm"
            max |grad f(x)| / max |grad f(0)| (1 at x = 0, 0 at the minimiser);
            "iterations" the Newton iterations taken.

        Raises:
            ValueError: For data of the wrong shape or not finite, or an unbound solver.
            diffeit.results.SolverError: With `throw=True`, for a frame that did not converge.
        """
        model = model_of(self)
        dv = check_frames(data, model.n_measurements, "voltage differences")
        y = jnp.atleast_2d(dv).astype(jnp.float64) / self.problem.data_scale
        settings = jnp.asarray([self.hyperparameter, self.smoothing, self.gradient_tolerance], dtype=jnp.float64)
        outcome = _solve_frames(
            self.operator,
            y,
            self.initial_matrix,
            settings,
            max_iterations=self.max_iterations,
            solver=model.solver,
        )
        if dv.ndim == 1:
            outcome = jax.tree_util.tree_map(lambda a: a[0], outcome)
        value = (outcome.x * self.problem.background).astype(dv.dtype)
        stats = {
            "objective": outcome.objective,
            "residual_norm": outcome.residual_norm,
            "total_variation": outcome.total_variation,
            "gradient_norm": outcome.gradient_norm,
            "iterations": outcome.iterations,
        }
        return finished(value, outcome.result, stats, "total variation", throw)


def _newton_operator(problem: LinearisedProblem, hyperparameter: float) -> _Operator:
    """The edges, their weights, the low-rank factor of J_n^T J_n and the sparsity pattern of
    the Newton matrix (docs/science.md#total-variation)."""
    mesh = problem.model.mesh
    first, second, lengths = element_adjacency(mesh)
    if len(first) == 0:
        raise ValueError("the mesh has no interior edges: total variation is undefined")
    # l_ref = sqrt(A / pi): TV is a length ratio, independent of the mesh size (docs/science.md#total-variation).
    reference_length = np.sqrt(mesh.element_areas.sum() / np.pi)
    n_elements = mesh.n_elements
    jacobian = problem.jacobian
    # B = Q^T J_n: B^T B = J_n^T Q Q^T J_n, J_n^T J_n without its smallest eigenvalues, but
    # exact on constant images (docs/science.md#total-variation).
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
) -> _Outcome:
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

    def one(frame: jax.Array) -> _Outcome:
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
        return _Outcome(
            x=state.x,
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
