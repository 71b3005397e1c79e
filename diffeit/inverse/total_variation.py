"""Total-variation difference reconstruction: sharp-edged changes (touches) on the linearised
problem, solved with L-BFGS (optimistix): one jitted solve for every frame of a batch, in groups of
`batch_size` frames vmapped together (on CPU one at a time is fastest).

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
expected contrast keeps edges sharp; smaller makes the problem stiffer (more L-BFGS steps).

The difference operator D (n_edges, E), (D x)_e = x_i - x_j, is applied by gathers (its
transpose, in the gradient, by scatter-adds): nothing E x E is formed. The warm start is the
one-step Laplace solution at the same lambda (`OneStep`'s measurement-space formula).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._arrays import is_concrete
from .._messages import name_indices
from ..forward import ForwardModel
from ..mesh import element_adjacency
from .one_step import LinearisedProblem, check_frames, regularised_inverse
from .priors import Laplace, Tikhonov

STOP_REASONS = ("converged", "max_steps", "stalled", "failed")
"""`TotalVariationSolution.stop_code` indexes this. "stalled": the solver's test (small
changes of x and f) was met but the gradient certificate was not: L-BFGS crept along without
reaching the minimiser, as it can when a huge hyperparameter makes the problem very stiff.
"failed": a line-search or descent failure or a non-finite iterate, as optimistix reports it."""


class ConvergenceWarning(UserWarning):
    """An iterative reconstruction stopped before its convergence test was met."""


class TotalVariationSolution(NamedTuple):
    """What `TotalVariation.solve` returns; with a batch of T frames every field has a leading
    T axis.

    - `conductivity_change`: (E,) dsigma in S/sq.
    - `objective`: f(x) at the solution (unit-free, see the module docstring).
    - `residual_norm`: ||J_n x - y||, the normalised data misfit (compare it with the noise
      norm sqrt(M) p/100 for p% noise).
    - `total_variation`: TV_beta(x) at the solution (unit-free).
    - `gradient_norm`: max |grad f(x)| / max |grad f(0)| (max over elements), a convergence
      certificate independent of the solver's own test.
    - `steps`: L-BFGS steps taken (accepted and rejected).
    - `converged`: bool, the solver's test (changes of x and f below rtol/atol) met and
      `gradient_norm` <= the reconstruction's `gradient_tolerance`.
    - `stop_code`: int index into `STOP_REASONS`; `stop_reason` gives the words.
    """

    conductivity_change: jax.Array
    objective: jax.Array
    residual_norm: jax.Array
    total_variation: jax.Array
    gradient_norm: jax.Array
    steps: jax.Array
    converged: jax.Array
    stop_code: jax.Array

    @property
    def stop_reason(self) -> str | list[str]:
        """The words for `stop_code`: one string, or a list of one per frame."""
        codes = np.asarray(self.stop_code)
        return STOP_REASONS[int(codes)] if codes.ndim == 0 else [STOP_REASONS[int(c)] for c in codes]


class _Operator(NamedTuple):
    """The arrays of the objective: J_n (M, E), the edges' element pairs and weights w_e."""

    jacobian: jax.Array
    first: jax.Array
    second: jax.Array
    weights: jax.Array


@dataclass(frozen=True, eq=False)
class TotalVariation:
    """Smoothed total-variation difference reconstruction on the linearised problem.

    `TotalVariation(model, hyperparameter=0.05, smoothing=1e-3, background=1.0, *,
    max_steps=10_000, rtol=1e-6, atol=1e-8, gradient_tolerance=1e-4, history_length=10,
    warm_start=True, batch_size=1)`

    Minimises f(x) = ||J_n x - y||^2 + hyperparameter^2 TV_smoothing(x) over the relative
    change x = dsigma / background (see the module docstring for the normalisation and the
    edge weights) by L-BFGS (`optimistix.LBFGS`), and returns dsigma = background x in S/sq.
    Set-up builds J_n, the edge list and the warm-start matrix once; a batch runs through one
    jitted solve vmapped over `batch_size` frames at a time, compiled once per reconstruction
    shape whatever the number of frames. Absolute differences only.

    **Arguments:**

    - `model`: the forward model of the reconstruction mesh.
    - `hyperparameter`: lambda > 0, unit-free. Larger flattens the image and lowers its
      contrast (TV's known bias); smaller lets noise through and needs more steps. For p%
      noise (DESIGN.md) start near 2 to 5 times p/100 (see the module docstring).
    - `smoothing`: beta > 0, in units of the relative change (1e-3 = 0.1% of the background).
    - `background`: the reference conductivity, scalar or (E,), S/sq.
    - `max_steps`: the L-BFGS step limit; frames that reach it report `converged=False`.
    - `rtol`, `atol`: optimistix's termination test: the step in x and the change in f both
      below atol + rtol |.| (max norm over elements).
    - `gradient_tolerance`: the largest `gradient_norm` (see `TotalVariationSolution`) that
      counts as converged.
    - `history_length`: L-BFGS memory (pairs of steps and gradient changes kept).
    - `warm_start`: start from the one-step Laplace solution at the same lambda (True) or from
      zero (False).
    - `batch_size`: frames solved together by `jax.vmap` (a last, partial group is padded with
      zero frames, which converge at once); groups run in sequence. A vmapped group steps
      until its slowest frame has converged. 1, the default, is fastest on CPU: vmapped,
      optimistix's L-BFGS copies its history buffers on every step (10 frames on 1,348
      elements: 29 s vmapped, 8 s in sequence). On an accelerator, larger groups may fill the
      device.
    """

    model: ForwardModel
    hyperparameter: float = 0.05
    smoothing: float = 1e-3
    background: float | np.ndarray = 1.0
    max_steps: int = 10_000
    rtol: float = 1e-6
    atol: float = 1e-8
    gradient_tolerance: float = 1e-4
    history_length: int = 10
    warm_start: bool = True
    batch_size: int = 1
    problem: LinearisedProblem = field(init=False, repr=False)
    operator: _Operator = field(init=False, repr=False)
    initial_matrix: jax.Array = field(init=False, repr=False)
    """(E, M) maps y to the warm start x_0 (zeros without `warm_start`)."""

    def __post_init__(self) -> None:
        for name in ("hyperparameter", "smoothing", "gradient_tolerance"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be finite and positive; got {value}")
        if not (np.isfinite(self.rtol) and np.isfinite(self.atol) and self.rtol >= 0 and self.atol >= 0):
            raise ValueError(f"rtol and atol must be finite and non-negative; got {self.rtol}, {self.atol}")
        if self.rtol == 0 and self.atol == 0:
            raise ValueError("rtol and atol are both zero: the solver could never stop; set either")
        for name in ("max_steps", "history_length", "batch_size"):
            value = getattr(self, name)
            if int(value) != value or value < 1:
                raise ValueError(f"{name} must be a positive integer; got {value}")
        mesh = self.model.mesh
        first, second, lengths = element_adjacency(mesh)
        if len(first) == 0:
            raise ValueError("the mesh has no interior edges: total variation is undefined")
        # J_n does not depend on the prior; Laplace's covariance serves only the warm start.
        problem = LinearisedProblem.at(self.model, Laplace() if self.warm_start else Tikhonov(), self.background)
        # l_ref = sqrt(A / pi): TV is a length ratio, independent of the mesh size (module docstring).
        reference_length = np.sqrt(mesh.element_areas.sum() / np.pi)
        operator = _Operator(
            jacobian=jnp.asarray(problem.jacobian),
            first=jnp.asarray(first),
            second=jnp.asarray(second),
            weights=jnp.asarray(lengths / reference_length),
        )
        if self.warm_start:
            initial = regularised_inverse(problem, self.hyperparameter)
        else:
            initial = np.zeros((self.model.n_elements, self.model.n_measurements))
        object.__setattr__(self, "problem", problem)
        object.__setattr__(self, "operator", operator)
        object.__setattr__(self, "initial_matrix", jnp.asarray(initial))

    def objective(self, conductivity_change: jax.Array, voltage_difference: jax.Array) -> jax.Array:
        """f(x) (unit-free) for dsigma (E,) in S/sq and dV (M,) in volts, x = dsigma /
        background: a pure JAX function (grad, jit and vmap work on it)."""
        x = jnp.asarray(conductivity_change) / self.problem.background
        y = jnp.asarray(voltage_difference) / self.problem.data_scale
        return _objective(x, (self.operator, y, self.hyperparameter, self.smoothing))

    def solve(self, voltage_difference: jax.Array) -> TotalVariationSolution:
        """Reconstruct dV = V - V_reference (volts), (M,) or a batch (T, M), and report the
        solver's outcome per frame (see `TotalVariationSolution`). Non-finite or wrongly shaped
        frames raise ValueError. The solve runs in float64; dsigma is returned in the input's
        dtype."""
        dv = check_frames(voltage_difference, self.model.n_measurements, "voltage differences")
        n_frames, size = (1 if dv.ndim == 1 else len(dv)), int(self.batch_size)
        y = jnp.atleast_2d(dv).astype(jnp.float64) / self.problem.data_scale
        y = jnp.concatenate([y, jnp.zeros((-n_frames % size, y.shape[1]))]) if n_frames % size else y
        settings = jnp.asarray(
            [self.hyperparameter, self.smoothing, self.gradient_tolerance, self.rtol, self.atol], dtype=jnp.float64
        )
        groups = [
            _solve_group(
                self.operator,
                y[start : start + size],
                self.initial_matrix,
                settings,
                max_steps=int(self.max_steps),
                history_length=int(self.history_length),
            )
            for start in range(0, len(y), size)
        ]
        solution = jax.tree_util.tree_map(lambda *parts: jnp.concatenate(parts)[:n_frames], *groups)
        change = (solution.conductivity_change * self.problem.background).astype(dv.dtype)
        solution = solution._replace(conductivity_change=change)
        return jax.tree_util.tree_map(lambda a: a[0], solution) if dv.ndim == 1 else solution

    def reconstruct(self, voltage_difference: jax.Array) -> jax.Array:
        """dsigma (S/sq): (E,) for dV (M,) in volts, (T, E) for a batch (T, M), in the input's
        dtype. Warns (`ConvergenceWarning`) naming the frames that did not converge; `solve`
        returns the details."""
        solution = self.solve(voltage_difference)
        if is_concrete(solution.converged):
            failed = np.flatnonzero(~np.atleast_1d(np.asarray(solution.converged)))
            if len(failed):
                reasons = sorted({STOP_REASONS[int(c)] for c in np.atleast_1d(np.asarray(solution.stop_code))[failed]})
                warnings.warn(
                    f"total variation did not converge in frame(s) {name_indices(failed)} ({', '.join(reasons)}; "
                    f"max_steps={self.max_steps}): raise max_steps, loosen rtol/atol/gradient_tolerance or change "
                    "the hyperparameter; solve() reports each frame",
                    ConvergenceWarning,
                    stacklevel=2,
                )
        return solution.conductivity_change


def _total_variation(x: jax.Array, operator: _Operator, smoothing: jax.Array) -> jax.Array:
    """TV_beta(x) = sum_e w_e (sqrt((D x)_e^2 + beta^2) - beta), D x by two gathers."""
    difference = x[operator.first] - x[operator.second]
    # sqrt(d^2 + b^2) - b written as d^2 / (sqrt(d^2 + b^2) + b): no cancellation for d << b.
    return jnp.sum(operator.weights * difference**2 / (jnp.sqrt(difference**2 + smoothing**2) + smoothing))


def _objective(x: jax.Array, args: tuple) -> jax.Array:
    operator, y, hyperparameter, smoothing = args
    residual = operator.jacobian @ x - y
    return residual @ residual + hyperparameter**2 * _total_variation(x, operator, smoothing)


@partial(jax.jit, static_argnames=("max_steps", "history_length"))
def _solve_group(
    operator: _Operator,
    y: jax.Array,
    initial_matrix: jax.Array,
    settings: jax.Array,
    *,
    max_steps: int,
    history_length: int,
) -> TotalVariationSolution:
    """One L-BFGS solve per row of y (B, M), vmapped; x in relative units. `settings` holds
    lambda, beta, the gradient tolerance, rtol and atol: traced, so changing them does not
    compile again."""
    hyperparameter, smoothing, gradient_tolerance, rtol, atol = settings
    solver = optx.LBFGS(rtol=rtol, atol=atol, history_length=history_length)
    gradient = jax.grad(_objective)

    def one(frame: jax.Array) -> TotalVariationSolution:
        args = (operator, frame, hyperparameter, smoothing)
        start = initial_matrix @ frame
        # throw=False: a frame's failure is a value in the result, not an exception under vmap.
        solution = optx.minimise(_objective, solver, start, args, max_steps=max_steps, throw=False)
        x = solution.value
        residual = operator.jacobian @ x - frame
        scale = jnp.max(jnp.abs(gradient(jnp.zeros_like(x), args)))
        gradient_norm = jnp.max(jnp.abs(gradient(x, args))) / jnp.where(scale > 0, scale, 1.0)
        code = jnp.select(
            [
                ~jnp.all(jnp.isfinite(x)),
                solution.result == optx.RESULTS.nonlinear_max_steps_reached,
                solution.result != optx.RESULTS.successful,
                ~(gradient_norm <= gradient_tolerance),
            ],
            [3, 1, 3, 2],
            0,
        )
        return TotalVariationSolution(
            conductivity_change=x,
            objective=_objective(x, args),
            residual_norm=jnp.sqrt(residual @ residual),
            total_variation=_total_variation(x, operator, smoothing),
            gradient_norm=gradient_norm,
            steps=solution.stats["num_steps"],
            converged=code == 0,
            stop_code=code,
        )

    return jax.vmap(one)(y)
