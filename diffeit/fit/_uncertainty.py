"""How well the frames determine a joint fit's memory parameters: their standard errors and
correlations from the Fisher information of the misfit (`memory_uncertainty`).

Around the fit each free memory parameter moves by a relative change and the stimulus by one
amplitude per segment of frames (segments start at the touches' changes); the covariance of
the relative changes is the Cramer-Rao bound, with the amplitudes as nuisances and the priors
left out. The model of the uncertainty, why it is a lower bound, and how to read it are in
docs/science.md#memory-uncertainty.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._threads import host_algebra
from ..forward import ForwardModel
from ..inverse.linearised import check_frames
from ._joint import JointFit, JointProblem
from ._memory import memory_to_unconstrained

# A segment starts where the frames change by more than this fraction of their largest change from
# one frame to the next, and by more than `_NOISE_CHANGES` times the norm noise alone gives the
# difference of two frames, s sqrt(2 M) (its squared norm then exceeds the noise's 2.25 times; the
# noise's own spread is a fraction sqrt(2 / M) of it). A segment is touched when its mean stimulus
# (area-weighted norm) exceeds `_TOUCHED` of the largest: the others hold no stimulus and have no
# amplitude.
_CHANGE = 0.3
_NOISE_CHANGES = 1.5
_TOUCHED = 0.1


class MemoryUncertainty(eqx.Module):
    """The uncertainty of a joint fit's memory parameters: a lower bound, the data's alone.

    What `memory_uncertainty` returns; `lines()` formats it. How it is computed and how to read
    it: docs/science.md#memory-uncertainty.

    Attributes:
        names: The free memory fields, in `MemoryParameters` order.
        values: (P,) their fitted values.
        relative_error: (P,) the standard deviation of each, relative to its value (0.1: 10%);
            inf for one the readings do not see (for example on its boundary: a relaxation of
            0), and for all when the rest trade exactly.
        correlation: (P, P) the correlations of their errors (0 with a parameter of infinite
            error).
        segments: (T,) int, the segment of each frame (segments start at the touches' changes).
        touched: (S,) bool, the segments whose stimulus had an amplitude.
    """

    names: tuple[str, ...] = eqx.field(static=True)
    values: np.ndarray
    relative_error: np.ndarray
    correlation: np.ndarray
    segments: np.ndarray
    touched: np.ndarray

    def error_text(self, name: str) -> str:
        """The relative standard error of one parameter, as text.

        Arguments:
            name: A free memory field, one of `names`.

        Returns:
            The error as a percentage of the value, "+- 12%", or "not determined" when it is
            infinite.

        Raises:
            ValueError: For a name not in `names`.
        """
        error = self.relative_error[self.names.index(name)]
        return f"+- {error:.0%}" if np.isfinite(error) else "not determined"

    def lines(self) -> list[str]:
        """One line per parameter: its value, relative error and strongest correlation."""
        lines = []
        for i, name in enumerate(self.names):
            line = f"{name} {self.values[i]:.3g} {self.error_text(name)}"
            others = [j for j in range(len(self.names)) if j != i and np.isfinite(self.relative_error[j])]
            if others and np.isfinite(self.relative_error[i]):
                j = max(others, key=lambda j: abs(self.correlation[i, j]))
                line += f" (correlation {self.correlation[i, j]:+.2f} with {self.names[j]})"
            lines.append(line)
        return lines


@host_algebra
def memory_uncertainty(model: ForwardModel, frames: jax.Array | np.ndarray, fit: JointFit) -> MemoryUncertainty:
    """The standard errors and correlations of the memory parameters a joint fit fitted.

    The Cramer-Rao bound at the fit: each free memory parameter moves by a relative change, the
    stimulus keeps the fit's pattern with one free amplitude per segment of frames, and the
    readings' noise is the fit's data scale; the priors are left out. It is a lower bound (what
    the data determine, whatever the estimator), and small errors do not prove that the joint
    fit finds the parameters: docs/science.md#memory-uncertainty.

    Arguments:
        model: The fit's forward model.
        frames: (T, M) the frames the fit was made on, volts.
        fit: The `JointFit`.

    Returns:
        The `MemoryUncertainty`.

    Raises:
        ValueError: When the fit fitted no memory parameter or fitted one per element, and for
            frames that are not the fit's shape or not finite.
    """
    names = fit.settings.memory_fitted
    if not names:
        raise ValueError("the fit held every memory parameter fixed: there is no memory uncertainty to report")
    frames = check_frames(frames, model.n_measurements, "frames")
    if frames.shape != (len(fit.times), model.n_measurements):
        raise ValueError(f"frames have shape {frames.shape}; the fit was made on {len(fit.times)} frames")
    problem = JointProblem(model, frames, fit.times, fit.settings)
    segments, touched = _segments(np.asarray(frames), np.asarray(fit.stimulus), model, fit.settings.data_scale)
    fitted = [np.asarray(getattr(fit.memory, name), dtype=float) for name in names]
    if any(value.size != 1 for value in fitted):
        raise ValueError("the fit's memory parameters vary per element: the uncertainty is for shared ones")
    values = np.array([float(value.reshape(())) for value in fitted])
    n_touched = int(touched.sum())
    amplitude_index = jnp.asarray(np.where(touched, np.cumsum(touched) - 1, n_touched))

    def residuals(unknowns: jax.Array) -> jax.Array:
        relative, amplitudes = unknowns[: len(names)], unknowns[len(names) :]
        memory = dataclasses.replace(
            fit.memory, **{name: value * jnp.exp(r) for name, value, r in zip(names, values, relative, strict=True)}
        )
        scales = jnp.concatenate([amplitudes, jnp.ones(1)])[amplitude_index][jnp.asarray(segments)]
        parameters = dataclasses.replace(
            fit.parameters,
            memory=memory_to_unconstrained(memory, names),
            stimulus=fit.stimulus * scales[:, None],
        )
        return ((problem.voltages(parameters) - problem.frames) / fit.settings.data_scale).ravel()

    start = jnp.concatenate([jnp.zeros(len(names)), jnp.ones(n_touched)])
    jacobian = np.asarray(eqx.filter_jit(jax.jacfwd(residuals))(start))
    # A parameter the readings do not see (one on its boundary: a relaxation of 0 has no relative
    # change) has no finite error; the others' come from the rest of the information.
    sizes = np.linalg.norm(jacobian, axis=0)
    seen = sizes > 1e-9 * sizes.max()
    seen[len(names) :] = True
    information = jacobian[:, seen].T @ jacobian[:, seen]
    eigenvalues = np.linalg.eigvalsh(information)
    error = np.full(len(names), np.inf)
    correlation = np.eye(len(names))
    if eigenvalues.min() > 1e-12 * eigenvalues.max():
        inner = seen[: len(names)]
        covariance = np.linalg.inv(information)[: inner.sum(), : inner.sum()]
        error[inner] = np.sqrt(np.diag(covariance))
        correlation[np.ix_(inner, inner)] = covariance / np.outer(error[inner], error[inner])
    return MemoryUncertainty(names, values, error, correlation, segments, touched)


def _segments(
    frames: np.ndarray, stimulus: np.ndarray, model: ForwardModel, data_scale: float
) -> tuple[np.ndarray, np.ndarray]:
    """(T,) the segment of each frame, and (S,) which segments are touched (docs/science.md#memory-uncertainty)."""
    change = np.linalg.norm(np.diff(frames, axis=0), axis=1)
    noise = _NOISE_CHANGES * data_scale * np.sqrt(2 * frames.shape[1])
    starts = (change > _CHANGE * change.max()) & (change > noise) if change.size else change.astype(bool)
    segments = np.concatenate([[0], np.cumsum(starts)])
    areas = np.asarray(model.mesh.element_areas)
    counts = np.bincount(segments)
    means = np.zeros((counts.size, stimulus.shape[1]))
    np.add.at(means, segments, stimulus)
    size = np.sqrt((means / counts[:, None]) ** 2 @ areas)
    return segments, size > _TOUCHED * max(float(size.max()), np.finfo(float).tiny)
