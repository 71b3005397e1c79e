"""Result codes of diffeit's iterative and fallible computations.

Every solve that can fall short (a conjugate-gradient solve, Gauss-Newton, total variation,
hyperparameter selection, the joint fit) returns a result value carrying a `result` field, an
item of `RESULTS`, and takes a `throw=` choice:

- `throw=True` (the default): a result other than `RESULTS.successful` raises, with the code's
  message. A call on concrete values raises at the call; under your own `jax.jit` the error
  is raised at run time (`equinox.error_if`), and since JAX dispatches asynchronously it
  surfaces where an output is read (`np.asarray`, `.block_until_ready()`), not necessarily at
  the call (`equinox.filter_jit` waits for it). JAX's persistent compilation cache changes
  nothing here: programs with run-time checks are not written to it, so every process checks.
- `throw=False`: nothing raises; inspect `solution.result` yourself. Compare codes with `==`
  (`solution.result == RESULTS.max_iterations_reached`); a batched solve carries one code per
  frame, and `RESULTS[item]` gives the message of a single code.

The codes are shared by every solver, as in optimistix, so code that handles one handles all.
"""

from __future__ import annotations

from typing import TypeVar

import equinox as eqx
import numpy as np

from ._messages import name_indices

__all__ = ["RESULTS", "SolverError", "failed", "messages", "names", "throw_if_failed"]


class RESULTS(eqx.Enumeration):
    """The outcome of an iterative or fallible computation (see the module docstring).

    An `equinox.Enumeration`: each item's value is its message; `RESULTS[item]` gives the
    message of a single code.

    Attributes:
        successful: The computation succeeded (message "").
        max_iterations_reached: The iteration limit was reached before convergence.
        line_search_failed: No step along the search direction decreased the objective.
        stalled: Steps no longer change the objective although the gradient tolerance is not
            met.
        nonfinite: A non-finite value appeared (a failed linear solve, or non-finite input).
        linear_solve_not_converged: A conjugate-gradient solve did not reach its tolerance
            within its iteration limit.
        selection_at_boundary: The selected hyperparameter is at an end of the candidates (or
            the criterion's level is not reached within them).
    """

    successful = ""
    max_iterations_reached = (
        "the iteration limit was reached before convergence: raise `max_iterations` or loosen the tolerance"
    )
    line_search_failed = (
        "no step along the search direction decreased the objective: the iterate is as good as the "
        "precision of the forward model allows, or the problem is badly scaled"
    )
    stalled = (
        "steps no longer change the objective although the gradient tolerance is not met: the tolerance "
        "is below what the precision resolves"
    )
    nonfinite = "a non-finite value appeared (a failed linear solve, or non-finite input)"
    linear_solve_not_converged = (
        "the conjugate-gradient solve did not reach its tolerance within its iteration limit: raise "
        "`max_iterations`, or use the host or dense backend for this ill-conditioned system"
    )
    selection_at_boundary = (
        "the selected hyperparameter is at an end of the candidates (or the criterion's level is not "
        "reached within them): widen the candidates"
    )


class SolverError(RuntimeError):
    """A computation ended with a result other than `RESULTS.successful` and `throw=True`."""


def failed(result: RESULTS) -> np.ndarray:
    """Which frames of a concrete result failed.

    Arguments:
        result: A concrete `RESULTS` value, one code or one per frame.

    Returns:
        Boolean mask, True where the code is not `RESULTS.successful`: 0-d for one code,
        (T,) for a batch.
    """
    # NumPy on the concrete codes: an eager JAX comparison costs more than a small solve.
    return np.asarray(result._value) != np.asarray(RESULTS.successful._value)


def messages(result: RESULTS) -> list[str]:
    """The message of each code of a concrete result.

    Arguments:
        result: A concrete `RESULTS` value, one code or one per frame.

    Returns:
        One message per frame (one for a single code), "" for success.
    """
    return [RESULTS._index_to_message[code] for code in np.atleast_1d(np.asarray(result._value)).tolist()]


def names(result: RESULTS) -> list[str]:
    """The name of each code of a concrete result: what files and reports store.

    Arguments:
        result: A concrete `RESULTS` value, one code or one per frame.

    Returns:
        One name per frame (one for a single code): "successful", "max_iterations_reached",
        and so on.
    """
    by_value = {int(item._value): name for name, item in RESULTS._name_to_item.items()}
    return [by_value[code] for code in np.atleast_1d(np.asarray(result._value)).tolist()]


Value = TypeVar("Value")


def throw_if_failed(value: Value, result: RESULTS, what: str) -> Value:
    """Raise for a failed result; else return the value unchanged.

    On a traced result (under jit or vmap) the check is `equinox.error_if`, at run time, with
    the code's message.

    Arguments:
        value: What to return (under jit, the value the run-time check is attached to).
        result: The `RESULTS` value, one code or one per frame.
        what: The computation's name, for the message.

    Returns:
        `value`.

    Raises:
        SolverError: For a concrete result with a failed code, naming `what`, the failing
            frames of a batch and the first failure's message.
        equinox.EquinoxRuntimeError: For a traced result with a failed code, at run time.
    """
    if result.is_traced():
        return result.error_if(value, result != RESULTS.successful)
    mask = np.atleast_1d(failed(result))
    if not mask.any():
        return value
    frames = np.flatnonzero(mask)
    where = f" (frames {name_indices(frames)})" if np.ndim(failed(result)) else ""
    raise SolverError(f"{what}{where}: {messages(result)[frames[0]]}; pass throw=False to get the result instead")
