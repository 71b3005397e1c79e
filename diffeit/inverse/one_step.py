"""One-step linearised difference reconstruction, solved in measurement space."""

from __future__ import annotations

from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from .._arrays import is_concrete
from .._messages import name_indices
from .._threads import host_algebra
from ..forward import ForwardModel
from .priors import AbstractPrior, prior_named


@dataclass(frozen=True, eq=False)
class LinearisedProblem:
    """The linearisation of a model at a background, normalised so that hyperparameters are
    unit-free.

    `LinearisedProblem.at(model, prior, background, normalised=False)`

    Unknowns: the relative change x = dsigma / background per element. Data: y = dV / s with
    s = RMS(V_0) on every reading (absolute differences), or y = dV / V_ref reading by reading
    (normalised differences, `normalised=True`, s = V_0, signed), V_0 = V(background) the
    model's voltages and V_ref the measured reference. The ratio dV / V_ref is the same for
    signed voltages and for the magnitudes some instruments report, so normalised differences
    also restore the sign such data lost.
    The normalised Jacobian is J_n = diag(1/s) J diag(background). The prior covariance P is
    scaled by c = trace(J_n P J_n^T) / n_meas, so that the data-space prior covariance
    `gram` = J_n P J_n^T / c has unit mean diagonal: the hyperparameter lambda then weighs the
    noise variance against the average signal a change drawn from the prior gives, whatever
    the prior, the mesh, the drive current or the background level.

    Fields: `reference` (M,) V_0 in volts; `data_scale` (M,) s in volts (signed for
    normalised differences); `jacobian` (M, E)
    J_n; `prior_jacobian` (E, M) P J_n^T / c; `gram` (M, M); `prior_scale` c; `eigenvalues`
    (M,) and `eigenvectors` (M, M) of G, ascending. Eigenvalues below M eps max(G) are set to
    exactly 0: adjacent data are rank-deficient (reciprocity pairs readings), and in the null
    space of G no change x can explain the data (J^T u = 0 there), so the solvers leave those
    components out instead of dividing rounding errors by a tiny hyperparameter.
    """

    model: ForwardModel
    prior: AbstractPrior
    background: np.ndarray
    normalised: bool
    reference: np.ndarray = field(repr=False)
    data_scale: np.ndarray = field(repr=False)
    jacobian: np.ndarray = field(repr=False)
    prior_jacobian: np.ndarray = field(repr=False)
    gram: np.ndarray = field(repr=False)
    prior_scale: float = field(repr=False)
    eigenvalues: np.ndarray = field(repr=False)
    eigenvectors: np.ndarray = field(repr=False)

    @classmethod
    @host_algebra
    def at(
        cls,
        model: ForwardModel,
        prior: str | AbstractPrior = "noser",
        background: float | np.ndarray = 1.0,
        *,
        normalised: bool = False,
    ) -> LinearisedProblem:
        prior = prior_named(prior) if isinstance(prior, str) else prior
        if not isinstance(prior, AbstractPrior):
            raise ValueError(f"prior must be a name or a diffeit.inverse prior; got {prior!r}")
        background = np.broadcast_to(np.asarray(background, dtype=np.float64), (model.n_elements,)).copy()
        if not np.all(np.isfinite(background) & (background > 0)):
            raise ValueError("background conductivity must be finite and positive (S/sq), one value or one per element")
        reference = np.asarray(model.measure(jnp.asarray(background)))
        if normalised:
            small = np.abs(reference) < 1e-6 * np.sqrt(np.mean(reference**2))
            if np.any(small):
                raise ValueError(
                    f"normalised differences divide by the reference voltages, and readings "
                    f"{name_indices(np.flatnonzero(small))} are near zero at this background: use absolute differences"
                )
            data_scale = reference  # signed: see the class docstring
        else:
            data_scale = np.full(len(reference), np.sqrt(np.mean(reference**2)))
        jacobian = np.asarray(model.jacobian(jnp.asarray(background))) * background / data_scale[:, None]
        prior_jacobian = prior.covariance_times_jacobian_transpose(model.mesh, jacobian)
        gram = jacobian @ prior_jacobian
        prior_scale = float(np.trace(gram) / len(gram))
        gram = 0.5 * (gram + gram.T) / prior_scale  # symmetric up to rounding; make it exactly so
        eigenvalues, eigenvectors = scipy.linalg.eigh(gram)
        eigenvalues[eigenvalues < len(gram) * np.finfo(float).eps * eigenvalues[-1]] = 0.0
        return cls(
            model=model,
            prior=prior,
            background=background,
            normalised=normalised,
            reference=reference,
            data_scale=data_scale,
            jacobian=jacobian,
            prior_jacobian=prior_jacobian / prior_scale,
            gram=gram,
            prior_scale=prior_scale,
            eigenvalues=eigenvalues,
            eigenvectors=eigenvectors,
        )

    def normalised_data(self, voltage_difference: jax.Array, reference: jax.Array | None = None) -> jax.Array:
        """y (..., M) from dV (..., M) in volts; normalised differences divide by the measured
        `reference` (M,) reading by reading (falling back to the model's V_0 when None)."""
        if not self.normalised:
            return voltage_difference / self.data_scale
        return voltage_difference / (self.reference if reference is None else reference)


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
      of p% (DESIGN.md), lambda near p/100 balances noise and signal.
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
        return _apply(self.matrix, dv)


@host_algebra
def regularised_inverse(problem: LinearisedProblem, hyperparameter: float) -> np.ndarray:
    """(E, M) P J_n^T (G + lambda^2 I)^-1 / c, through the eigendecomposition of G."""
    inverse = 1.0 / (problem.eigenvalues + hyperparameter**2)
    inverse[problem.eigenvalues == 0] = 0.0  # see LinearisedProblem.eigenvalues
    # The M x M regularised inverse first: one E x M x M product instead of two.
    return problem.prior_jacobian @ ((problem.eigenvectors * inverse) @ problem.eigenvectors.T)


def check_frames(frames: jax.Array, n_measurements: int, what: str) -> jax.Array:
    """`frames` as a float JAX array of shape (M,) or (T, M), refusing other shapes and, for
    concrete input, non-finite values (naming the frames). NumPy input is checked before it is
    moved, a JAX array where it lives: only one flag per frame travels."""
    if isinstance(frames, jax.Array):
        array = frames
    else:
        array = np.asarray(frames)
        if not np.issubdtype(array.dtype, np.floating):
            array = array.astype(float)
    if array.ndim not in (1, 2) or array.shape[-1] != n_measurements:
        raise ValueError(f"{what} have shape {array.shape}; expected ({n_measurements},) or (T, {n_measurements})")
    if is_concrete(array):
        xp = jnp if isinstance(array, jax.Array) else np
        finite = np.asarray(xp.all(xp.isfinite(array.reshape(-1, n_measurements)), axis=1))
        if not np.all(finite):
            raise ValueError(f"{what} are not finite (NaN or inf) in frame(s) {name_indices(np.flatnonzero(~finite))}")
    array = jnp.asarray(array)
    return array if jnp.issubdtype(array.dtype, jnp.floating) else array.astype(float)


@jax.jit
def _apply(matrix: jax.Array, frames: jax.Array) -> jax.Array:
    """frames @ matrix.T in the frames' dtype: under jit the transpose and the conversion fold
    into the product instead of copying the E x M matrix on every call."""
    return frames @ matrix.T.astype(frames.dtype)
