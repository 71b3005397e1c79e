"""The linearised problem every linear reconstruction shares: the Jacobian at a background,
normalised so that hyperparameters are unit-free, the prior applied to it, and the
measurement-space eigendecomposition; with the checks of the frames a reconstruction takes."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from .._arrays import is_concrete
from .._messages import name_indices
from .._threads import host_algebra
from ..forward import ForwardModel
from .priors import AbstractPrior, prior_named

# `diffeit.reconstruct`'s one-step prior spread of each electrode's change in ln z between the
# reference and a frame: as loose as the conductivity's prior per element (about 1.8), since the
# balance between the two decides how much of a contact's drift is imaged. 1 left a drift's
# artefacts, 3 and 10 blurred touches at the rim (docs/science.md#contact-impedance-drift).
CONTACT_IMPEDANCE_SPREAD = 2.0


class LinearisedProblem(eqx.Module):
    """The linearisation of a model at a background, normalised so that hyperparameters are unit-free.

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
    the prior, the mesh, the drive current or the background level
    (docs/science.md#linearised-reconstruction).

    With `contact_impedance_spread` q > 0, each electrode's contact impedance may also change
    between the reference and a frame: the unknowns are x and w = d(ln z) (L,), w with prior
    covariance q^2 I, and the data-space covariance becomes G = J_n P J_n^T / c + q^2 Z_n Z_n^T,
    Z_n = diag(1/s) dV/dz diag(z) (M, L). The solvers' x is then the conductivity part of the
    joint estimate: the readings a contact change explains are not imaged as conductivity
    (an electrode's contact drying or wetting during a session would otherwise show as a hill
    at the rim beside it; docs/science.md#contact-impedance-drift).

    Eigenvalues of G below M eps max(G) are set to exactly 0: adjacent data are
    rank-deficient (reciprocity pairs readings), and in the null space of G no change x can
    explain the data (J^T u = 0 there), so the solvers leave those components out instead of
    dividing rounding errors by a tiny hyperparameter.

    Arguments:
        model: The forward model.
        prior: A name ("tikhonov", "noser", "laplace", "matern") or a prior of
            `diffeit.inverse.priors` (default "noser").
        background: The background conductivity, S/sq, scalar or (E,), finite and positive.
        normalised: Normalised differences dV / V_ref (True) rather than absolute ones.
        contact_impedance_spread: q, the prior standard deviation of each electrode's change in
            ln z between the reference and a frame (unit-free, >= 0); 0 holds the contact
            impedances (no nuisance).

    Attributes:
        model: The forward model.
        prior: The prior.
        background: (E,) the background conductivity, S/sq.
        normalised: Whether data are normalised differences (static).
        contact_impedance_spread: q (static).
        reference: (M,) V_0, the model's voltages at the background, volts.
        data_scale: (M,) s, volts (signed for normalised differences).
        jacobian: (M, E) J_n, the normalised Jacobian (unit-free).
        prior_jacobian: (E, M) P J_n^T / c.
        gram: (M, M) G = J_n P J_n^T / c (+ q^2 Z_n Z_n^T), the data-space prior covariance.
        prior_scale: c = trace(J_n P J_n^T) / M.
        eigenvalues: (M,) the eigenvalues of G, ascending, those below rounding set to 0.
        eigenvectors: (M, M) the eigenvectors of G, one per column.

    Raises:
        ValueError: For a prior that is not a name or a prior, a background of the wrong
            shape or not finite and positive, a `contact_impedance_spread` that is negative or
            not finite, or (normalised differences) reference voltages near zero at this
            background.
    """

    model: ForwardModel
    prior: AbstractPrior
    background: np.ndarray
    normalised: bool = eqx.field(static=True)
    contact_impedance_spread: float = eqx.field(static=True)
    reference: np.ndarray = eqx.field(repr=False)
    data_scale: np.ndarray = eqx.field(repr=False)
    jacobian: np.ndarray = eqx.field(repr=False)
    prior_jacobian: np.ndarray = eqx.field(repr=False)
    gram: np.ndarray = eqx.field(repr=False)
    prior_scale: float = eqx.field(repr=False)
    eigenvalues: np.ndarray = eqx.field(repr=False)
    eigenvectors: np.ndarray = eqx.field(repr=False)

    @host_algebra
    def __init__(
        self,
        model: ForwardModel,
        prior: str | AbstractPrior = "noser",
        background: float | np.ndarray = 1.0,
        *,
        normalised: bool = False,
        contact_impedance_spread: float = 0.0,
    ) -> None:
        spread = checked_spread(contact_impedance_spread)
        self.model = model
        self.prior = prior_named(prior) if isinstance(prior, str) else prior
        if not isinstance(self.prior, AbstractPrior):
            raise ValueError(f"prior must be a name or a diffeit.inverse prior; got {prior!r}")
        self.background = _checked_background(background, model.n_elements)
        self.normalised = bool(normalised)
        self.contact_impedance_spread = spread
        self.reference = np.asarray(model.measure(jnp.asarray(self.background)))
        self.data_scale = _data_scale(self.reference, self.normalised)
        self.jacobian = (
            np.asarray(model.jacobian(jnp.asarray(self.background))) * self.background / self.data_scale[:, None]
        )
        prior_jacobian = self.prior.covariance_times_jacobian_transpose(model.mesh, self.jacobian)
        gram = self.jacobian @ prior_jacobian
        self.prior_scale = float(np.trace(gram) / len(gram))
        self.prior_jacobian = prior_jacobian / self.prior_scale
        gram = gram / self.prior_scale
        if self.contact_impedance_spread > 0:
            contact = _contact_jacobian(model, self.background, self.data_scale)
            gram = gram + self.contact_impedance_spread**2 * (contact @ contact.T)
        self.gram = 0.5 * (gram + gram.T)  # symmetric up to rounding; make it exactly so
        eigenvalues, self.eigenvectors = scipy.linalg.eigh(self.gram)
        eigenvalues[eigenvalues < len(eigenvalues) * np.finfo(float).eps * eigenvalues[-1]] = 0.0
        self.eigenvalues = eigenvalues

    def normalised_data(self, voltage_difference: jax.Array, reference: jax.Array | None = None) -> jax.Array:
        """The normalised data y from voltage differences.

        Absolute differences divide by s; normalised differences divide by the measured
        reference reading by reading.

        Arguments:
            voltage_difference: (..., M) dV, volts.
            reference: (M,) the measured reference, volts, for normalised differences (None:
                the model's V_0). Unused for absolute differences.

        Returns:
            (..., M) y, unit-free.
        """
        if not self.normalised:
            return voltage_difference / self.data_scale
        return voltage_difference / (self.reference if reference is None else reference)


def checked_spread(contact_impedance_spread: float) -> float:
    """A contact spread q as a float, or a ValueError for one negative or not finite."""
    if not (np.isfinite(contact_impedance_spread) and contact_impedance_spread >= 0):
        raise ValueError(f"contact_impedance_spread must be finite and >= 0; got {contact_impedance_spread}")
    return float(contact_impedance_spread)


def _contact_jacobian(model: ForwardModel, background: np.ndarray, data_scale: np.ndarray) -> np.ndarray:
    """(M, L) Z_n = diag(1/s) dV/dz diag(z): the normalised readings' derivative in each
    electrode's ln z (zero for point electrodes)."""
    contact = np.broadcast_to(np.asarray(model.contact_impedance, np.float64), (model.mesh.n_electrodes,))
    derivative = np.asarray(model.jacobian(jnp.asarray(background), wrt="contact_impedance"))
    return derivative * contact / data_scale[:, None]


def _checked_background(background: float | np.ndarray, n_elements: int) -> np.ndarray:
    """(E,) float64 copy of a scalar or per-element background conductivity, S/sq."""
    array = np.asarray(background, dtype=np.float64)
    if array.shape not in ((), (n_elements,)):
        raise ValueError(f"background has shape {array.shape}; expected a scalar or ({n_elements},)")
    if not np.all(np.isfinite(array) & (array > 0)):
        raise ValueError("background conductivity must be finite and positive (S/sq), one value or one per element")
    return np.broadcast_to(array, (n_elements,)).copy()


def _data_scale(reference: np.ndarray, normalised: bool) -> np.ndarray:
    """s (M,) volts: RMS(V_0) on every reading, or V_0 itself (signed) for normalised differences."""
    if not normalised:
        return np.full(len(reference), np.sqrt(np.mean(reference**2)))
    small = np.abs(reference) < 1e-6 * np.sqrt(np.mean(reference**2))
    if np.any(small):
        raise ValueError(
            f"normalised differences divide by the reference voltages, and readings "
            f"{name_indices(np.flatnonzero(small))} are near zero at this background: use absolute differences"
        )
    return reference


@host_algebra
def regularised_inverse(problem: LinearisedProblem, hyperparameter: float) -> np.ndarray:
    """The regularised inverse P J_n^T (G + lambda^2 I)^-1 / c, through the eigendecomposition of G.

    Components in the null space of G (eigenvalue 0) are left out.

    Arguments:
        problem: The `LinearisedProblem`.
        hyperparameter: lambda, unit-free.

    Returns:
        (E, M) the matrix from normalised data y to the relative change x.
    """
    inverse = 1.0 / (problem.eigenvalues + hyperparameter**2)
    inverse[problem.eigenvalues == 0] = 0.0  # see LinearisedProblem.eigenvalues
    # The M x M regularised inverse first: one E x M x M product instead of two.
    return problem.prior_jacobian @ ((problem.eigenvectors * inverse) @ problem.eigenvectors.T)


def check_frames(frames: jax.Array, n_measurements: int, what: str) -> jax.Array:
    """Frames as a float JAX array of shape (M,) or (T, M), checked.

    NumPy input is checked before it is moved, a JAX array where it lives: only one flag per
    frame travels.

    Arguments:
        frames: (M,) or (T, M) frames (integers become floats).
        n_measurements: M.
        what: What the frames are, for the error message.

    Returns:
        The frames as a float JAX array.

    Raises:
        ValueError: For another shape, or concrete frames that are not finite (naming them).
    """
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
def apply_matrix(matrix: jax.Array, frames: jax.Array) -> jax.Array:
    """Apply a reconstruction matrix to frames: frames @ matrix.T, in the frames' dtype.

    Under jit the transpose and the conversion fold into the product instead of copying the
    K x M matrix on every call. Works under an outer jit and vmap.

    Arguments:
        matrix: (K, M) the reconstruction matrix.
        frames: (..., M) the frames.

    Returns:
        (..., K).
    """
    return frames @ matrix.T.astype(frames.dtype)
