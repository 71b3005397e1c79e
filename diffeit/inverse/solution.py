"""What every reconstruction returns (`Solution`) and the interface every solver follows
(`AbstractSolver`).

As in optimistix (`minimise(fn, solver, y0, throw=) -> Solution`), each reconstruction method
is a solver object holding its settings, with one call: `solver.solve(data, throw=True)`
returns a `Solution` holding the image(s), one result code per frame and the method's extras.
`diffeit.reconstruct` takes any solver and binds it to the model it calibrates
(`AbstractSolver.bound`).
"""

from __future__ import annotations

import abc
from typing import Any, Self

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._arrays import IdentityModule
from ..forward import ForwardModel
from ..results import RESULTS, throw_if_failed


class Solution(eqx.Module):
    """The result of a reconstruction: the image(s), a result code per frame, and extras.

    Every solver's `solve` returns one. For a batch of T frames every field gains a leading T
    axis (a history, whose length varies by frame, is a tuple of T arrays).

    Attributes:
        value: The image. For difference imaging (`OneStep`, `GREIT`, `GaussNewton`,
            `TotalVariation`) the conductivity change dsigma in S/sq per element of the
            solver's mesh, (E,) for one frame or (T, E) for a batch; for `AbsoluteGaussNewton`
            the conductivity sigma, S/sq; for the joint fit (`diffeit.fit.JointImaging`, which
            takes the readings of T frames) dsigma (T, E) from its fitted background, S/sq.
        result: A `diffeit.results.RESULTS` code, one per frame: `RESULTS.successful`, or why
            the frame failed (see each solver). Compare with `==`.
        stats: The method's extras, keyed by name; each solver documents its keys.
    """

    value: jax.Array | np.ndarray
    result: RESULTS
    stats: dict[str, Any]


class AbstractSolver(IdentityModule):
    """A reconstruction method: settings on the object, one call `solve(data, throw=)`.

    A solver is built on a `diffeit.ForwardModel` (its mesh, protocol and contact impedance)
    at a background conductivity, and computes what it can once (a reconstruction matrix, a
    factorised prior). It may also be built without a model, holding its settings only:
    `bound(model, background)` then returns the solver on a model, which is how
    `diffeit.reconstruct` uses a solver on the model it calibrates. Solvers compare and hash
    by identity, as models do.
    """

    @abc.abstractmethod
    def solve(self, data: jax.Array, *, throw: bool = True) -> Solution:
        """Reconstruct one frame (M,) or a batch (T, M) of data.

        Arguments:
            data: Voltage differences V - V_ref in volts (readings, for absolute imaging),
                (M,) or (T, M).
            throw: Raise for a frame that failed (True), or return its code in
                `Solution.result` (False).

        Returns:
            The `Solution`.

        Raises:
            ValueError: For data of the wrong shape or not finite, or an unbound solver.
            diffeit.results.SolverError: With `throw=True`, for a frame that failed.
        """

    @abc.abstractmethod
    def bound(
        self, model: ForwardModel, background: float | np.ndarray | None = None, *, hyperparameter: float | None = None
    ) -> Self:
        """This solver's settings on another model.

        Arguments:
            model: The forward model to reconstruct on.
            background: The background conductivity (S/sq, scalar or (E,)); None keeps this
                solver's.
            hyperparameter: A hyperparameter replacing this solver's; None keeps it.

        Returns:
            A new solver of the same class and settings on `model`.
        """


def model_of(solver: AbstractSolver) -> ForwardModel:
    """The model of a solver, which must be bound.

    Every solver has a `model`, None when unbound. (A function, not a method: an equinox bound
    method costs more than a small solve.)

    Arguments:
        solver: The solver.

    Returns:
        Its `ForwardModel`.

    Raises:
        ValueError: For an unbound solver.
    """
    model = solver.model
    if model is None:
        name = type(solver).__name__
        raise ValueError(
            f"this {name} has no model: build it on one ({name}(model, ...)) or bind it "
            "(solver.bound(model, background))"
        )
    return model


def finished(value: jax.Array | np.ndarray, result: RESULTS, stats: dict[str, Any], what: str, throw: bool) -> Solution:
    """The `Solution` of a value, result and stats, after raising for failed frames when asked.

    Arguments:
        value: The image(s).
        result: The `RESULTS` code(s), one per frame.
        stats: The method's extras.
        what: The computation's name, for the error message.
        throw: Raise for failed frames (`diffeit.results.throw_if_failed`).

    Returns:
        The `Solution`.

    Raises:
        diffeit.results.SolverError: With `throw=True`, for a failed frame (at run time under
            jit).
    """
    solution = Solution(value, result, stats)
    return throw_if_failed(solution, result, what) if throw else solution


def finite_codes(images: jax.Array) -> RESULTS:
    """One code per frame: `RESULTS.successful` where the frame is finite, `RESULTS.nonfinite` where not.

    Works under jit and vmap.

    Arguments:
        images: (E,) or (T, E) images (any unit).

    Returns:
        The `RESULTS` code, one for (E,), (T,) for a batch.
    """
    finite = jnp.all(jnp.isfinite(images), axis=-1)

    def code(ok: jax.Array) -> RESULTS:
        return RESULTS.where(ok, RESULTS.successful, RESULTS.nonfinite)

    return code(finite) if finite.ndim == 0 else jax.vmap(code)(finite)
