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


class History(eqx.Module):
    """An optimisation's progress: `objective` and `gradient_norm` (max |gradient| over the
    unknowns), NumPy arrays with one entry for the start and one per accepted step."""

    objective: np.ndarray
    gradient_norm: np.ndarray


class Minimum(NamedTuple):
    """What `minimise` found.

    - `value`: the minimiser, a pytree like the initial value.
    - `objective`: (steps + 1,) the objective at the start and after every accepted step.
    - `gradient_norm`: (steps + 1,) max |gradient| at the same points.
    - `result`: `RESULTS.successful` (the relative or absolute tolerance was met),
      `max_iterations_reached`, `nonfinite` (the objective or its gradient is NaN or inf) or
      `stalled` (the line search made no progress before the tolerance).
    """

    value: Any
    objective: np.ndarray
    gradient_norm: np.ndarray
    result: RESULTS


def minimise(
    objective: Callable[[Any], jax.Array],
    initial: Any,
    *,
    max_steps: int = 500,
    rtol: float = 1e-6,
    atol: float = 1e-10,
    progress: bool = True,
    description: str = "fit",
) -> Minimum:
    """Minimise the scalar `objective(y)` over the pytree of arrays `y` from `initial` by L-BFGS.

    `rtol`, `atol`: optimistix's convergence test on the step and the objective (relative and
    absolute, max norm). The step and the stopping test are jitted once per call; the loop runs
    in Python, one step at a time, with a tqdm progress bar (`progress=False` hides it).
    """
    if max_steps < 0:
        raise ValueError(f"max_steps must be >= 0; got {max_steps}")
    solver = optx.LBFGS(rtol=rtol, atol=atol)

    def function(y, _args):
        return objective(y), None

    leaves = jax.tree_util.tree_leaves(initial)
    dtype = jnp.result_type(*leaves) if leaves else jnp.result_type(float)
    tags = frozenset()
    state = solver.init(function, initial, None, {}, jax.ShapeDtypeStruct((), dtype), None, tags)
    step = eqx.filter_jit(lambda y, state: solver.step(function, y, None, {}, state, tags))
    terminate = eqx.filter_jit(lambda y, state: solver.terminate(function, y, None, {}, state, tags))
    value_and_gradient = eqx.filter_jit(eqx.filter_value_and_grad(objective))

    def record(value, gradient) -> None:
        objectives.append(float(value))
        norms.append(max((float(jnp.max(jnp.abs(g))) for g in jax.tree_util.tree_leaves(gradient)), default=0.0))

    objectives: list[float] = []
    norms: list[float] = []
    record(*value_and_gradient(initial))
    y, accepted, result = initial, 0, RESULTS.max_iterations_reached
    with tqdm(total=max_steps, desc=description, disable=not progress, leave=False) as bar:
        for _ in range(max_steps):
            done, solver_result = terminate(y, state)
            if bool(done):
                result = RESULTS.successful if solver_result == optx.RESULTS.successful else RESULTS.stalled
                break
            y, state, _ = step(y, state)
            # optimistix's first accepted step is the initial point, recorded above.
            if int(state.num_accepted_steps) > max(accepted, 1):
                record(state.f_info.f, state.f_info.grad)
            accepted = int(state.num_accepted_steps)
            bar.set_postfix(objective=f"{objectives[-1]:.4g}")
            bar.update()
            if not np.isfinite(objectives[-1]) or not np.isfinite(norms[-1]):
                result = RESULTS.nonfinite
                break
        else:
            done, solver_result = terminate(y, state)
            if bool(done) and solver_result == optx.RESULTS.successful:
                result = RESULTS.successful
    return Minimum(y, np.asarray(objectives), np.asarray(norms), result)
