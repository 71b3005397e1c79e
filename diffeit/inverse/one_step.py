"""One-step linearised difference reconstruction, solved in measurement space."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._arrays import IdentityModule, is_concrete
from .._messages import name_indices
from ..forward import ForwardModel
from .linearised import LinearisedProblem, apply_matrix, check_frames, regularised_inverse
from .priors import AbstractPrior


class OneStep(IdentityModule):
    """Linearised difference reconstruction dsigma = R dV, with R built once.

    With the normalisation of `LinearisedProblem` (x = dsigma / background, y = dV / s,
    J_n, P scaled to a unit-mean data-space covariance G = J_n P J_n^T):

        x = P J_n^T (G + hyperparameter^2 I)^-1 y

    the minimiser of ||J_n x - y||^2 + hyperparameter^2 x^T P^-1 x, computed in measurement
    space (an eigendecomposition of the M x M matrix G, never anything E x E). `matrix` maps volts to
    S/sq, so a batch of T frames is one (T, M) @ (M, E) product.

    **Arguments:**

    - `model`: the forward model of the reconstruction mesh (it may differ from the mesh the
      data came from).
    - `prior`: "tikhonov", "noser", "laplace", "matern" or a prior instance of
      `diffeit.inverse.priors` (e.g. `Matern(correlation_length=0.1)`).
    - `hyperparameter`: lambda > 0, unit-free (see `diffeit.inverse.select_hyperparameter`, and
      `diffeit.inverse.to_external_hyperparameter` for EIDORS's and pyEIT's values). With noise
      of p% (docs/science.md#noise), lambda near p/100 balances noise and signal.
    - `background`: the reference conductivity, scalar or (E,), S/sq.
    - `normalised`: reconstruct from normalised differences dV / V_ref (pass the measured
      reference to `reconstruct`), which cancels per-channel gain errors of an instrument.

    The model, prior, background and `normalised` are those of `problem`.
    """

    problem: LinearisedProblem = eqx.field(repr=False)
    hyperparameter: float = eqx.field(static=True)
    matrix: jax.Array = eqx.field(repr=False)
    """(E, M) reconstruction matrix: dsigma (S/sq) = matrix @ y, y = dV in volts (absolute
    differences) or dV / V_ref (normalised differences)."""

    def __init__(
        self,
        model: ForwardModel,
        prior: str | AbstractPrior = "noser",
        hyperparameter: float = 0.05,
        background: float | np.ndarray = 1.0,
        *,
        normalised: bool = False,
    ) -> None:
        if not (np.isfinite(hyperparameter) and hyperparameter > 0):
            raise ValueError(f"hyperparameter must be finite and positive; got {hyperparameter}")
        self.hyperparameter = float(hyperparameter)
        self.problem = LinearisedProblem(model, prior, background, normalised=normalised)
        matrix = self.problem.background[:, None] * regularised_inverse(self.problem, self.hyperparameter)
        if not normalised:
            matrix = matrix / self.problem.data_scale  # volts in
        self.matrix = jnp.asarray(matrix)

    @property
    def model(self) -> ForwardModel:
        """The forward model of the reconstruction mesh."""
        return self.problem.model

    def reconstruct(self, voltage_difference: jax.Array, reference: jax.Array | None = None) -> jax.Array:
        """Conductivity change dsigma (S/sq) per element for dV = V - V_reference (volts).

        `voltage_difference` is (M,) or a batch (T, M); the result is (E,) or (T, E), in the
        dtype of the input (float32 in, float32 out). Normalised reconstruction needs the
        measured `reference` voltages (M,).
        """
        n_meas = self.model.n_measurements
        dv = check_frames(voltage_difference, n_meas, "voltage differences")
        if self.problem.normalised:
            if reference is None:
                raise ValueError("normalised reconstruction divides by the reference: pass reference=V_ref (volts)")
            reference = check_frames(reference, n_meas, "the reference")
            if reference.ndim != 1:
                raise ValueError(f"the reference must be one frame of shape ({n_meas},); got {reference.shape}")
            if is_concrete(reference) and np.any(np.asarray(reference) == 0):
                raise ValueError(
                    f"the reference is zero at readings {name_indices(np.flatnonzero(np.asarray(reference) == 0))}"
                )
            dv = dv / reference
        elif reference is not None:
            raise ValueError("a reference is only used for normalised differences (normalised=True)")
        return apply_matrix(self.matrix, dv)
