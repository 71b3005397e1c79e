"""The one optimisation loop of diffeit.fit: L-BFGS (optimistix), one jitted step at a time, so
that long fits show progress, record their history and can stop and resume anywhere."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from tqdm.auto import tqdm

from ..results import RESULTS

# Successful after this many accepted steps in a row that hardly lowered the objective; stalled
# after this many rejected trial steps in a row (the backtracking line search halves its step each
# time: 2^-40 of a step is no step).
_PATIENCE = 3
_STALL = 40


class History(eqx.Module):
    """An optimisation's progress: `objective` and `gradient_norm` (max |gradient| over the
    unknowns, in the units the optimiser works in), NumPy arrays with one entry for the start
    and one per accepted step."""

    objective: np.ndarray
    gradient_norm: np.ndarray


class Minimum(NamedTuple):
    """What `minimise` found.

    - `value`: the minimiser, a pytree like the initial value.
    - `objective`: (steps + 1,) the objective at the start and after every accepted step.
    - `gradient_norm`: (steps + 1,) max |gradient| at the same points, with respect to the
      scaled unknowns w (`minimise`'s `units`).
    - `result`: `RESULTS.successful` (the objective stopped decreasing, `minimise`),
      `max_iterations_reached`, `nonfinite` (the objective or its gradient is NaN or inf at an
      accepted step; `value` is then the last point where both were finite) or
      `stalled` (the line search found no lower point in `_STALL` trial steps in a row).
    """

    value: Any
    objective: np.ndarray
    gradient_norm: np.ndarray
    result: RESULTS


def minimise(
    objective: Callable[[Any], jax.Array],
    initial: Any,
    *,
    units: Any = None,
    max_steps: int = 500,
    rtol: float = 1e-6,
    atol: float = 1e-10,
    progress: bool = True,
    description: str = "fit",
    on_step: Callable[[Minimum], None] | None = None,
) -> Minimum:
    """Minimise the scalar `objective(y)` over the pytree of arrays `y` from `initial` by L-BFGS.

    It stops, successful, when `_PATIENCE` accepted steps in a row each lowered the objective by
    at most `atol + rtol |J|`. Not optimistix's own test, which also stops where the line
    search has shrunk its step to nothing: that is a stall, not a minimum, and is reported as
    `RESULTS.stalled`. `max_steps` counts trial steps, rejected ones included. The step is
    jitted (compiled again only for another objective: a new function, or a Module of another
    type or shapes); the loop runs in Python, one step at a time, with a tqdm progress bar
    (`progress=False` hides it).

    `units`: a pytree like `initial` (leaves broadcasting against its leaves), the scale of each
    unknown: L-BFGS works on w = (y - initial) / units, one flat vector, so that a step of 1 is
    about as large in every unknown (1 / sqrt of the objective's curvature there is the usual
    choice: a diagonal preconditioner). Default 1 for every unknown.

    `on_step`: called at the start and after every accepted step whose objective and gradient
    are finite, with the minimisation so far: a `Minimum` whose `value` is the current iterate,
    `objective` and `gradient_norm` its history up to it, and `result`
    `RESULTS.max_iterations_reached` (not finished). What it raises ends the minimisation and
    propagates: a caller saves the state from it, and stops at a step by raising.
    """
    if max_steps < 0:
        raise ValueError(f"max_steps must be >= 0; got {max_steps}")
    # Zero tolerances switch optimistix's own termination off (its test divides by them).
    solver = optx.LBFGS(rtol=0.0, atol=0.0)

    units = jax.tree_util.tree_map(jnp.ones_like, initial) if units is None else units
    scaled = _Scaled(objective, initial, units)
    flat = jnp.zeros(sum(jnp.size(leaf) for leaf in jax.tree_util.tree_leaves(initial)), _dtype(initial))
    state = _init(solver, scaled, flat)

    def record(value, gradient) -> None:
        objectives.append(float(value))
        norms.append(max((float(jnp.max(jnp.abs(g))) for g in jax.tree_util.tree_leaves(gradient)), default=0.0))

    def report(w: jax.Array) -> None:
        if on_step is not None:
            unfinished = RESULTS.max_iterations_reached
            on_step(Minimum(scaled.unscaled(w), np.asarray(objectives), np.asarray(norms), unfinished))

    objectives: list[float] = []
    norms: list[float] = []
    # optimistix's first step evaluates the start and accepts it: the start's value and gradient,
    # with no program of their own to compile.
    y, state, _ = _step(solver, scaled, flat, state)
    record(state.f_info.f, state.f_info.grad)
    accepted, result = 1, RESULTS.max_iterations_reached
    small, rejected, finite = 0, 0, flat
    if not np.isfinite(objectives[0]) or not np.isfinite(norms[0]):
        return Minimum(scaled.unscaled(flat), np.asarray(objectives), np.asarray(norms), RESULTS.nonfinite)
    report(y)
    with tqdm(total=max_steps, initial=min(max_steps, 1), desc=description, disable=not progress, leave=False) as bar:
        for _ in range(max_steps - 1):
            y, state, _ = _step(solver, scaled, y, state)
            bar.update()
            if not bool(state.result == optx.RESULTS.successful):
                result = RESULTS.stalled
                break
            # optimistix's first accepted step is the initial point, recorded above.
            if int(state.num_accepted_steps) > max(accepted, 1):
                record(state.f_info.f, state.f_info.grad)
                bar.set_postfix(objective=f"{objectives[-1]:.4g}")
                if not np.isfinite(objectives[-1]) or not np.isfinite(norms[-1]):
                    # The last point with a finite objective and gradient is returned.
                    objectives.pop(), norms.pop()
                    y, result = finite, RESULTS.nonfinite
                    break
                finite = y
                report(y)
                decrease = objectives[-2] - objectives[-1]
                small = small + 1 if decrease <= atol + rtol * abs(objectives[-1]) else 0
                rejected = 0
                if small >= _PATIENCE:
                    result = RESULTS.successful
                    break
            else:
                rejected += 1
                if rejected >= _STALL:
                    result = RESULTS.stalled
                    break
            accepted = int(state.num_accepted_steps)
    return Minimum(scaled.unscaled(y), np.asarray(objectives), np.asarray(norms), result)


class _Scaled(eqx.Module):
    """The objective as optimistix calls it, on the flat scaled unknowns w: a Module, so that the
    jitted step below is compiled once per objective type and shapes, not once per call (an
    objective that is itself a Module, such as the memory fit's, is then reused across rounds)."""

    objective: Callable[[Any], jax.Array]
    initial: Any
    units: Any

    def unscaled(self, w: jax.Array) -> Any:
        """The unknowns y = initial + units * w, w split and shaped like `initial`'s leaves."""
        leaves, treedef = jax.tree_util.tree_flatten(self.initial)
        bounds = np.cumsum([0] + [int(np.size(leaf)) for leaf in leaves])
        steps = [w[a:b].reshape(jnp.shape(leaf)) for a, b, leaf in zip(bounds[:-1], bounds[1:], leaves, strict=True)]
        step = jax.tree_util.tree_unflatten(treedef, steps)
        return jax.tree_util.tree_map(lambda y, unit, dy: y + unit * dy, self.initial, self.units, step)

    def value(self, w: jax.Array) -> jax.Array:
        return self.objective(self.unscaled(w))

    def __call__(self, w: jax.Array, _args: Any) -> tuple[jax.Array, None]:
        return self.value(w), None


def _dtype(tree: Any):
    leaves = jax.tree_util.tree_leaves(tree)
    return jnp.result_type(*leaves) if leaves else jnp.result_type(float)


@eqx.filter_jit
def _init(solver: optx.LBFGS, scaled: _Scaled, w: jax.Array) -> Any:
    """The solver's state at `w`. Jitted, although it computes little: the state holds the
    inverse Hessian as a function traced anew on each call (a new jaxpr), and `_step` would be
    compiled again for each one; jitted, a second call returns the first call's."""
    return solver.init(scaled, w, None, {}, jax.ShapeDtypeStruct((), w.dtype), None, frozenset())


@eqx.filter_jit
def _step(solver: optx.LBFGS, scaled: _Scaled, w: jax.Array, state: Any) -> tuple[jax.Array, Any, Any]:
    return solver.step(scaled, w, None, {}, state, frozenset())
