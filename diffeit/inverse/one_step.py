"""One-step linearised difference reconstruction, solved in measurement space."""

from __future__ import annotations

from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import jax.scipy.linalg
import numpy as np

from ..forward import ForwardModel

_PRIORS = ("noser",)
_NOSER_EXPONENT = 0.5


@dataclass(frozen=True, eq=False)
class OneStep:
    """Linearised difference reconstruction dsigma = R dV, with R built once.

    `OneStep(model, prior="noser", hyperparameter=0.05, background=1.0)`

    The problem is normalised so that the hyperparameter is unit-free: with V_0 = V(background)
    and s = RMS(V_0), the data are dV / s and the unknowns the relative change
    x = dsigma / background, with Jacobian J_n = J diag(background) / s. Then

        x = P J_n^T (J_n P J_n^T + hyperparameter^2 I)^-1 dV / s

    in measurement space (an n_meas x n_meas Cholesky solve, never n_elem x n_elem), which
    minimises ||J_n x - dV/s||^2 + hyperparameter^2 x^T P^-1 x. NOSER prior:
    P = diag(J_n^T J_n)^-1/2.

    **Arguments:**

    - `model`: the forward model of the reconstruction mesh.
    - `prior`: "noser".
    - `hyperparameter`: lambda > 0, unit-free.
    - `background`: the reference conductivity, scalar or (E,), S/sq.
    """

    model: ForwardModel
    prior: str = "noser"
    hyperparameter: float = 0.05
    background: float | np.ndarray = 1.0
    matrix: jax.Array = field(init=False, repr=False)
    """(E, n_meas) reconstruction matrix: dsigma = matrix @ dV, S/sq per volt."""

    def __post_init__(self) -> None:
        if self.prior not in _PRIORS:
            raise ValueError(f"unknown prior {self.prior!r}; choose one of {_PRIORS}")
        if not (np.isfinite(self.hyperparameter) and self.hyperparameter > 0):
            raise ValueError(f"hyperparameter must be finite and positive; got {self.hyperparameter}")
        background = jnp.broadcast_to(jnp.asarray(self.background, float), (self.model.n_elements,))
        reference = self.model.measure(background)
        scale = jnp.sqrt(jnp.mean(reference**2))
        jacobian = self.model.jacobian(background) * background / scale
        covariance = jnp.sum(jacobian**2, axis=0) ** -_NOSER_EXPONENT  # diagonal of P
        weighted = jacobian * covariance  # J_n P, (n_meas, E)
        gram = weighted @ jacobian.T + self.hyperparameter**2 * jnp.eye(len(reference))
        factor = jax.scipy.linalg.cho_factor(gram)
        matrix = jax.scipy.linalg.cho_solve(factor, weighted).T * (background / scale)[:, None]
        object.__setattr__(self, "matrix", matrix)

    def reconstruct(self, voltage_difference: jax.Array) -> jax.Array:
        """Conductivity change dsigma (S/sq) per element for dV = V - V_reference (volts).

        `voltage_difference` is (n_meas,) or a batch (T, n_meas); the result is (E,) or (T, E).
        """
        dv = np.asarray(voltage_difference, dtype=float)
        n_meas = self.model.n_measurements
        if dv.ndim not in (1, 2) or dv.shape[-1] != n_meas:
            raise ValueError(f"voltage differences have shape {dv.shape}; expected ({n_meas},) or (T, {n_meas})")
        if not np.all(np.isfinite(dv)):
            frames = np.flatnonzero(~np.all(np.isfinite(np.atleast_2d(dv)), axis=1))
            raise ValueError(f"voltage differences are not finite (NaN or inf) in frame(s) {frames.tolist()}")
        return dv @ self.matrix.T
