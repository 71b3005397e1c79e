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
from jax.flatten_util import ravel_pytree
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
) -> Minimum:
    """Minimise the scalar `objective(y)` over the pytree of arrays `y` from `initial` by L-BFGS.

    It stops, successful, when `_PATIENCE` accepted steps in a row each lowered the objective by
    at most `atol + rtol |J|`. Not optimistix's own test, which also stops where the line
    search has shrunk its step to nothing: that is a stall, not a minimum, and is reported as
    `RESULTS.stalled`. `max_steps` counts trial steps, rejected ones included. The step is
    jitted once per call; the loop runs in Python, one step at a time, with a tqdm progress bar
    (`progress=False` hides it).

    `units`: a pytree like `initial` (leaves broadcasting against its leaves), the scale of each
    unknown: L-BFGS works on w = (y - initial) / units, one flat vector, so that a step of 1 is
    about as large in every unknown (1 / sqrt of the objective's curvature there is the usual
    choice: a diagonal preconditioner). Default 1 for every unknown.
    """
    if max_steps < 0:
        raise ValueError(f"max_steps must be >= 0; got {max_steps}")
    # Zero tolerances switch optimistix's own termination off (its test divides by them).
    solver = optx.LBFGS(rtol=0.0, atol=0.0)

    units = jax.tree_util.tree_map(jnp.ones_like, initial) if units is None else units
    flat, unravel = ravel_pytree(jax.tree_util.tree_map(jnp.zeros_like, initial))

    def unscaled(w: jax.Array) -> Any:
        return jax.tree_util.tree_map(lambda y, unit, step: y + unit * step, initial, units, unravel(w))

    def scaled(w: jax.Array) -> jax.Array:
        return objective(unscaled(w))

    def function(w, _args):
        return scaled(w), None

    tags = frozenset()
    state = solver.init(function, flat, None, {}, jax.ShapeDtypeStruct((), flat.dtype), None, tags)
    step = eqx.filter_jit(lambda y, state: solver.step(function, y, None, {}, state, tags))
    value_and_gradient = eqx.filter_jit(eqx.filter_value_and_grad(scaled))

    def record(value, gradient) -> None:
        objectives.append(float(value))
        norms.append(max((float(jnp.max(jnp.abs(g))) for g in jax.tree_util.tree_leaves(gradient)), default=0.0))

    objectives: list[float] = []
    norms: list[float] = []
    record(*value_and_gradient(flat))
    y, accepted, result = flat, 0, RESULTS.max_iterations_reached
    small, rejected, finite = 0, 0, flat
    if not np.isfinite(objectives[0]) or not np.isfinite(norms[0]):
        return Minimum(unscaled(y), np.asarray(objectives), np.asarray(norms), RESULTS.nonfinite)
    with tqdm(total=max_steps, desc=description, disable=not progress, leave=False) as bar:
        for _ in range(max_steps):
            y, state, _ = step(y, state)
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
    return Minimum(unscaled(y), np.asarray(objectives), np.asarray(norms), result)
