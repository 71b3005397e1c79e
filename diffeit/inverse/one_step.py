"""One-step linearised difference reconstruction, solved in measurement space."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._arrays import is_concrete
from .._messages import name_indices
from ..forward import ForwardModel
from ..results import RESULTS
from .linearised import LinearisedProblem, apply_matrix, check_frames, checked_spread, regularised_inverse
from .priors import AbstractPrior, prior_named
from .solution import AbstractSolver, Solution, finished, finite_codes, model_of


class OneStep(AbstractSolver):
    """One-step linearised difference reconstruction: dsigma = R dV, with R built once.

    Minimises ||J_n x - y||^2 + hyperparameter^2 x^T (P/c)^-1 x over the relative change
    x = dsigma / background, on the normalised problem of `LinearisedProblem` (J_n the
    normalised Jacobian, P/c the scaled prior covariance, y the normalised data), in
    measurement space: x = (P/c) J_n^T (G + hyperparameter^2 I)^-1 y with G = J_n (P/c) J_n^T,
    an eigendecomposition of the M x M matrix G and never anything E x E. `matrix` maps volts
    to S/sq, so a batch of T frames is one (T, M) @ (M, E) product, under jit and vmap too.
    The equations are in docs/science.md#linearised-reconstruction.

    Arguments:
        model: The forward model of the reconstruction mesh (it may differ from the mesh the
            data came from); None for an unbound solver (see `bound`).
        prior: "tikhonov", "noser", "laplace", "matern" or a prior of
            `diffeit.inverse.priors` (e.g. `Matern(correlation_length=0.1)`).
        hyperparameter: lambda > 0, unit-free: with p% noise (docs/science.md#noise) lambda
            near p/100 balances noise and signal (`diffeit.inverse.select_hyperparameter`
            chooses it; `to_external_hyperparameter` converts it for EIDORS and pyEIT).
        background: The reference conductivity, S/sq, scalar or (E,).
        normalised: Reconstruct from normalised differences dV / V_ref, which cancel
            per-channel gain errors of an instrument; needs `reference`.
        reference: The measured reference voltages V_ref (M,), volts, that normalised
            differences divide by.
        contact_impedance_spread: q >= 0, the prior spread of each electrode's change in ln z
            between the reference and a frame (`LinearisedProblem`): the readings a contact
            change explains are not imaged. 0 (the default here) holds the contacts;
            `diffeit.reconstruct` images with `CONTACT_IMPEDANCE_SPREAD`.
        problem: The `LinearisedProblem` of `model` with this prior, background,
            normalisation and contact spread, when one is already built (choosing the
            hyperparameter builds it: `diffeit.inverse.select_hyperparameter`): used rather
            than built again.

    Attributes:
        prior: The prior.
        hyperparameter: lambda (static).
        background: The background conductivity as given (S/sq, scalar or (E,)).
        normalised: Whether data are normalised differences (static).
        contact_impedance_spread: q (static).
        reference: The measured reference V_ref (M,) of normalised differences, volts; else
            None (and None when unbound).
        problem: The `LinearisedProblem` on the model (None when unbound).
        matrix: (E, M) reconstruction matrix: dsigma (S/sq) = matrix @ y, y = dV in volts
            (absolute differences) or dV / V_ref (normalised differences); None when unbound.

    Raises:
        ValueError: For a hyperparameter that is not finite and positive, a prior that is
            not a name or a prior, a `reference` without `normalised=True`, normalised
            differences on a model without a `reference`, a reference that is not one finite
            frame (M,) or is zero at some reading, a background that is not finite and
            positive or of the wrong shape, reference voltages of the model near zero
            (normalised differences), a contact spread that is negative or not finite, or a
            `problem` of another model, prior, background, normalisation or contact spread.
    """

    prior: AbstractPrior
    hyperparameter: float = eqx.field(static=True)
    background: float | np.ndarray = eqx.field(repr=False)
    normalised: bool = eqx.field(static=True)
    contact_impedance_spread: float = eqx.field(static=True)
    reference: jax.Array | None = eqx.field(repr=False)
    problem: LinearisedProblem | None = eqx.field(repr=False)
    matrix: jax.Array | None = eqx.field(repr=False)

    def __init__(
        self,
        model: ForwardModel | None = None,
        prior: str | AbstractPrior = "noser",
        hyperparameter: float = 0.05,
        background: float | np.ndarray = 1.0,
        *,
        normalised: bool = False,
        reference: jax.Array | np.ndarray | None = None,
        contact_impedance_spread: float = 0.0,
        problem: LinearisedProblem | None = None,
    ) -> None:
        if not (np.isfinite(hyperparameter) and hyperparameter > 0):
            raise ValueError(f"hyperparameter must be finite and positive; got {hyperparameter}")
        self.hyperparameter = float(hyperparameter)
        self.prior = prior_named(prior) if isinstance(prior, str) else prior
        if not isinstance(self.prior, AbstractPrior):
            raise ValueError(f"prior must be a name or a diffeit.inverse prior; got {prior!r}")
        self.background = background
        self.normalised = bool(normalised)
        self.contact_impedance_spread = checked_spread(contact_impedance_spread)
        if reference is not None and not normalised:
            raise ValueError("a reference is only used for normalised differences (normalised=True)")
        self.reference = None if model is None or reference is None else _checked_reference(reference, model)
        if model is None:
            self.problem, self.matrix = None, None
            return
        if normalised and reference is None:
            raise ValueError("normalised differences divide by the measured reference: pass reference=V_ref (volts)")
        if problem is None:
            problem = LinearisedProblem(
                model,
                self.prior,
                background,
                normalised=normalised,
                contact_impedance_spread=self.contact_impedance_spread,
            )
        else:
            _check_problem(problem, model, self.prior, background, normalised, self.contact_impedance_spread)
        self.problem = problem
        matrix = self.problem.background[:, None] * regularised_inverse(self.problem, self.hyperparameter)
        if not normalised:
            matrix = matrix / self.problem.data_scale  # volts in
        self.matrix = jnp.asarray(matrix)

    @property
    def model(self) -> ForwardModel | None:
        """The forward model of the reconstruction mesh (None when unbound)."""
        return None if self.problem is None else self.problem.model

    def bound(
        self, model: ForwardModel, background: float | np.ndarray | None = None, *, hyperparameter: float | None = None
    ) -> OneStep:
        """This solver's settings on another model (see `AbstractSolver.bound`).

        A normalised solver keeps its reference, which must fit the model's readings.

        Arguments:
            model: The forward model to reconstruct on.
            background: The background conductivity (S/sq, scalar or (E,)); None keeps this
                solver's.
            hyperparameter: lambda replacing this solver's; None keeps it.

        Returns:
            A new `OneStep` on `model`.

        Raises:
            ValueError: As the constructor (for example a reference that does not fit the
                model's readings).
        """
        return OneStep(
            model,
            self.prior,
            self.hyperparameter if hyperparameter is None else hyperparameter,
            self.background if background is None else background,
            normalised=self.normalised,
            reference=self.reference,
            contact_impedance_spread=self.contact_impedance_spread,
        )

    def solve(self, data: jax.Array, *, throw: bool = True) -> Solution:
        """Reconstruct voltage differences dV = V - V_reference, volts.

        Works under jit and vmap; the image is in the dtype of the input (float32 in, float32
        out). `stats` is empty: the product is the whole method.

        Arguments:
            data: dV, (M,) or a batch (T, M), volts.
            throw: Raise for a frame whose image is not finite (True), or return its code.

        Returns:
            The `Solution`: `value` dsigma (E,) or (T, E), S/sq; `result` per frame
            `RESULTS.successful`, or `RESULTS.nonfinite` for an image that is not finite (an
            overflow).

        Raises:
            ValueError: For data of the wrong shape or not finite, or an unbound solver.
            diffeit.results.SolverError: With `throw=True`, for a frame whose image is not finite.
        """
        model = model_of(self)
        dv = check_frames(data, model.n_measurements, "voltage differences")
        if self.normalised:
            dv = dv / self.reference.astype(dv.dtype)
        images, codes = _images(self.matrix, dv)
        return finished(images, codes, {}, "one-step reconstruction", throw)


@jax.jit
def _images(matrix: jax.Array, frames: jax.Array) -> tuple[jax.Array, RESULTS]:
    """The images of `frames` (..., M) by `matrix` (E, M) in the frames' dtype, and their
    codes (`finite_codes`): one compiled call."""
    images = apply_matrix(matrix, frames)
    return images, finite_codes(images)


def _check_problem(
    problem: LinearisedProblem,
    model: ForwardModel,
    prior: AbstractPrior,
    background: float | np.ndarray,
    normalised: bool,
    contact_impedance_spread: float,
) -> None:
    """Refuse a linearisation built for another model, prior, background, normalisation or
    contact spread than the solver's: its matrix would reconstruct another problem."""
    same_background = np.array_equal(
        problem.background, np.broadcast_to(np.asarray(background, float), problem.background.shape)
    )
    if (
        problem.model is not model
        or problem.normalised != normalised
        or not (problem.prior is prior or eqx.tree_equal(problem.prior, prior))
        or not same_background
        or problem.contact_impedance_spread != contact_impedance_spread
    ):
        raise ValueError(
            "problem is the linearisation of another model, prior, background, normalisation or contact spread "
            "than this solver's"
        )


def _checked_reference(reference: jax.Array | np.ndarray, model: ForwardModel) -> jax.Array:
    """The measured reference (M,) of normalised differences, refused when of the wrong shape,
    not finite or zero at some reading (concrete values)."""
    n_meas = model.n_measurements
    reference = check_frames(reference, n_meas, "the reference")
    if reference.ndim != 1:
        raise ValueError(f"the reference must be one frame of shape ({n_meas},); got {reference.shape}")
    if is_concrete(reference) and np.any(np.asarray(reference) == 0):
        zero = np.flatnonzero(np.asarray(reference) == 0)
        raise ValueError(f"the reference is zero at readings {name_indices(zero)}")
    return reference
