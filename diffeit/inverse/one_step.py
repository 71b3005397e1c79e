"""One-step linearised difference reconstruction, solved in measurement space."""

from __future__ import annotations

from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from .._arrays import is_concrete
from .._messages import name_indices
from ..forward import ForwardModel
from .linearised import LinearisedProblem, apply_matrix, check_frames, regularised_inverse
from .priors import AbstractPrior


@dataclass(frozen=True, eq=False)
class OneStep:
    """Linearised difference reconstruction dsigma = R dV, with R built once.

    `OneStep(model, prior="noser", hyperparameter=0.05, background=1.0, *, normalised=False)`

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
      of p% (README, Conventions), lambda near p/100 balances noise and signal.
    - `background`: the reference conductivity, scalar or (E,), S/sq.
    - `normalised`: reconstruct from normalised differences dV / V_ref (pass the measured
      reference to `reconstruct`), which cancels per-channel gain errors of an instrument.
    """

    model: ForwardModel
    prior: str | AbstractPrior = "noser"
    hyperparameter: float = 0.05
    background: float | np.ndarray = 1.0
    normalised: bool = False
    problem: LinearisedProblem = field(init=False, repr=False)
    matrix: jax.Array = field(init=False, repr=False)
    """(E, M) reconstruction matrix: dsigma (S/sq) = matrix @ y, y = dV in volts (absolute
    differences) or dV / V_ref (normalised differences)."""

    def __post_init__(self) -> None:
        if not (np.isfinite(self.hyperparameter) and self.hyperparameter > 0):
            raise ValueError(f"hyperparameter must be finite and positive; got {self.hyperparameter}")
        problem = LinearisedProblem.at(self.model, self.prior, self.background, normalised=self.normalised)
        matrix = problem.background[:, None] * regularised_inverse(problem, self.hyperparameter)
        if not self.normalised:
            matrix = matrix / problem.data_scale  # volts in
        object.__setattr__(self, "problem", problem)
        object.__setattr__(self, "matrix", jnp.asarray(matrix))

    def reconstruct(self, voltage_difference: jax.Array, reference: jax.Array | None = None) -> jax.Array:
        """Conductivity change dsigma (S/sq) per element for dV = V - V_reference (volts).

        `voltage_difference` is (M,) or a batch (T, M); the result is (E,) or (T, E), in the
        dtype of the input (float32 in, float32 out). Normalised reconstruction needs the
        measured `reference` voltages (M,).
        """
        n_meas = self.model.n_measurements
        dv = check_frames(voltage_difference, n_meas, "voltage differences")
        if self.normalised:
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
