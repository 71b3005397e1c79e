"""The memory fit of a labelled calibration session: known footprints and hold windows, unknown depths.

In a calibration session every press k has a known footprint (`patterns[k]`, the fraction of
each element under it, 0..1) and a known hold window [start_k, end_k] (seconds); only its depth
d_k (dsigma/sigma at full cover, < 0 for a touch) is unknown. The memoryless stimulus is then

    a(t)_e = sum_k d_k patterns_ke [start_k <= t <= end_k]

(a step press, held between frames as the memory model holds it: a press or release between
frames is seen at the next frame), and the images are modelled as the memory response from a
rested, virgin skin at times[0], images = R_p(a) + noise (`diffeit.memory.memory_response`). The
free memory parameters p (in the unconstrained coordinates of `memory_to_unconstrained`) and the
K depths are fitted together by weighted least squares (Levenberg-Marquardt on the exact
Jacobian, `jax.jacfwd`), and every parameter's standard error comes from the Gauss-Newton
covariance (J^T W J)^-1 at the fit, scaled by the reduced chi-square where it exceeds 1 and
carried to natural units by the delta method. Unlike `memory`, no segments are searched for: the
stimulus is known up to K numbers, so the parameters are well determined by a few presses of
different holds.
"""

from __future__ import annotations

from collections.abc import Collection

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._threads import host_algebra
from ..memory import MemoryParameters, memory_response, over_foam
from ..results import RESULTS, throw_if_failed
from ._memory import (
    _NOISE_FLOOR,
    DEFAULT_FREE,
    _checked_initial,
    _checked_noise,
    _on_elements,
    check_images,
    memory_from_unconstrained,
    memory_to_unconstrained,
    noise_level,
    reported_memory,
)

# Levenberg-Marquardt stops when the Gauss-Newton step would lower the chi-square (the misfit in
# noise units, where 1 is one standard error's worth) by less than this: far below anything the
# standard errors resolve.
_PREDICTED_DECREASE = 1e-8
# The damping's start, growth on a rejected step and shrink on an accepted one, and its limit
# (beyond it no step lowers the misfit: the fit stands where rounding allows).
_DAMPING, _GROW, _SHRINK, _DAMPING_LIMIT = 1e-3, 10.0, 0.3, 1e12
# The information matrix is taken as singular below this ratio of its eigenvalues.
_SINGULAR = 1e-12


class PressMemoryFit(eqx.Module):
    """The result of `memory_from_presses` (from images) and `memory_from_press_readings` (from
    readings: `depths` as given, no depth errors, `response` and `noise` per reading).

    Attributes:
        memory: The fitted `diffeit.memory.MemoryParameters` (the free fields fitted, the others
            as given); with both modes free, the quicker one is named fast (`ordered_modes`).
        depths: (K,) each press's depth, dsigma/sigma at full cover of an element (< 0 for a
            touch).
        standard_errors: The standard error of each free memory field by name, in its natural
            units (seconds for times, dimensionless for fractions), and under "depths" the (K,)
            errors of the depths (dsigma/sigma); inf for what the images do not determine.
            From the Gauss-Newton covariance, scaled by the reduced chi-square where it exceeds 1.
        response: (T, E) the images as the fitted model explains them (dsigma/sigma).
        misfit: ||images - response|| / ||images|| over all frames and elements (dimensionless).
        reduced_chi_square: The weighted misfit sum over its degrees of freedom, on the elements
            the presses cover (about 1 when the noise is right and the model fits).
        noise: (E,) the noise standard deviation of each element's images (dsigma/sigma), as
            given or estimated (`noise_level`).
        steps: The Levenberg-Marquardt steps taken (accepted or not).
        result: `RESULTS.successful`, `max_iterations_reached`, `stalled` (no step lowers the
            misfit while the predicted decrease is still large) or `nonfinite`.
    """

    memory: MemoryParameters
    depths: np.ndarray
    standard_errors: dict
    response: jax.Array
    misfit: float
    reduced_chi_square: float
    noise: np.ndarray
    steps: int
    result: RESULTS


class _PressProblem(eqx.Module):
    """The weighted residuals of the images of the covered elements, as a function of the
    unknowns x = (free memory fields, unconstrained, in `names` order; the K depths)."""

    images: jax.Array  # (T, n)
    times: jax.Array  # (T,)
    held: jax.Array  # (T, K) 1 while press k is held
    patterns: jax.Array  # (K, n)
    scale: jax.Array  # (n,) noise standard deviations
    base: MemoryParameters
    names: tuple[str, ...] = eqx.field(static=True)

    def memory(self, x: jax.Array) -> MemoryParameters:
        return memory_from_unconstrained(dict(zip(self.names, x[: len(self.names)], strict=True)), self.base)

    def stimulus(self, depths: jax.Array) -> jax.Array:
        return (self.held * depths) @ self.patterns

    def residuals(self, x: jax.Array) -> jax.Array:
        depths = x[len(self.names) :]
        response = memory_response(self.stimulus(depths), self.times, self.memory(x))
        return ((self.images - response) / self.scale).ravel()


class _ReadingsProblem(eqx.Module):
    """The weighted residuals of a session's readings that no press signature explains, as a
    function of the free memory fields x (unconstrained, in `names` order): variable projection,
    the signatures (and the reference's offset) solved by least squares at every x."""

    readings: jax.Array  # (T, M) over each reading's noise
    times: jax.Array  # (T,)
    stimulus: jax.Array  # (T, K) each press's depth while it is held, else 0
    bends: jax.Array  # (K,)
    base: MemoryParameters
    names: tuple[str, ...] = eqx.field(static=True)

    def memory(self, x: jax.Array) -> MemoryParameters:
        return memory_from_unconstrained(dict(zip(self.names, x, strict=True)), self.base)

    def columns(self, x: jax.Array) -> jax.Array:
        """(T, 1 + 2K): a constant, each press's response r_k(t) as its readings bend,
        r / (1 + b r), and a step at each press's start."""
        response = memory_response(self.stimulus, self.times, self.memory(x))
        bent = response / (1 + self.bends * response)
        started = jnp.cumsum(self.stimulus != 0, axis=0) > 0
        return jnp.concatenate([jnp.ones_like(bent[:, :1]), bent, started.astype(bent.dtype)], axis=1)

    def residuals(self, x: jax.Array) -> jax.Array:
        basis = jnp.linalg.qr(self.columns(x))[0]
        return (self.readings - basis @ (basis.T @ self.readings)).ravel()


@eqx.filter_jit
def _linearise(problem: _PressProblem | _ReadingsProblem, x: jax.Array) -> tuple[jax.Array, jax.Array]:
    return problem.residuals(x), jax.jacfwd(problem.residuals)(x)


@eqx.filter_jit
def _residuals(problem: _ReadingsProblem, x: jax.Array) -> jax.Array:
    return problem.residuals(x)


@eqx.filter_jit
def _chi_square(problem: _PressProblem | _ReadingsProblem, x: jax.Array) -> jax.Array:
    return jnp.sum(problem.residuals(x) ** 2)


@host_algebra
def memory_from_presses(
    images: jax.Array | np.ndarray,
    times: jax.Array | np.ndarray,
    patterns: jax.Array | np.ndarray,
    windows: jax.Array | np.ndarray,
    *,
    initial: MemoryParameters | None = None,
    free: Collection[str] = DEFAULT_FREE,
    noise: float | jax.Array | np.ndarray | None = None,
    max_steps: int = 200,
    throw: bool = True,
) -> PressMemoryFit:
    """Fit the memory parameters and each press's depth to a labelled calibration session.

    The stimulus is a_ke = sum_k d_k patterns_ke [start_k <= t <= end_k]; the images are its
    memory response from a rested, virgin skin at times[0] plus noise; the free memory fields
    (shared by all elements) and the depths d_k are fitted by weighted least squares
    (Levenberg-Marquardt), weighted by each element's noise. Only the elements some pattern
    covers take part (the model predicts no change elsewhere). The gain is never fitted (it
    trades exactly with the depths). See the module docstring.

    Arguments:
        images: (T, E) relative changes dsigma/sigma (one-step images of the session against its
            reference), T >= 3.
        times: (T,) frame times, seconds, increasing.
        patterns: (K, E) the fraction of each element each press covers (0..1; for a disc,
            `diffeit.mesh.disc_fraction`).
        windows: (K, 2) each press's hold start and end, seconds, within [times[0], times[-1]],
            start <= end, each holding at least one frame.
        initial: The start and the fixed values (`MemoryParameters` of scalars for the free
            fields); default `diffeit.memory.over_foam()`.
        free: The fields fitted; default that of `memory` (the mode fractions and time constants
            and the relaxation). The two fractions are free or fixed together; never the gain.
        noise: The images' noise standard deviation (dsigma/sigma, a number or (E,)); default
            estimated from the images (`noise_level`). Floored at 1e-3 of the largest |image|.
        max_steps: The most Levenberg-Marquardt steps.
        throw: Raise for a fit that does not converge (True), or return it in `result` (False).

    Returns:
        The `PressMemoryFit`.

    Raises:
        ValueError: For images or times that are not finite or do not match, patterns that are
            not (K, E) with E the images' or not in [0, 1] or cover no element, windows that are
            not (K, 2), not finite, reversed, outside the times or holding no frame, and invalid
            initial parameters, free names or noise.
        diffeit.results.SolverError: With `throw=True`, for a fit that does not converge.
    """
    images, times = check_images(images, times)
    n_frames, n_elements = images.shape
    if n_frames < 3:
        raise ValueError(f"the press memory fit needs at least 3 frames; got {n_frames}")
    patterns = np.asarray(patterns, dtype=float)
    if patterns.ndim != 2 or patterns.shape[1] != n_elements or patterns.shape[0] == 0:
        raise ValueError(
            f"patterns must have shape (K, E) = (presses, {n_elements} elements of the images); got {patterns.shape}"
        )
    n_presses = patterns.shape[0]
    if not (np.all(np.isfinite(patterns)) and np.all((patterns >= 0) & (patterns <= 1))):
        raise ValueError("patterns must be fractions of each element covered, in [0, 1]")
    if not np.all(patterns.max(axis=1) > 0):
        raise ValueError(f"patterns {np.flatnonzero(patterns.max(axis=1) <= 0).tolist()} cover no element")
    held = _held_frames(windows, np.asarray(times), n_presses)
    initial, names = _checked_start(initial, free, max_steps)

    values = np.asarray(images)
    noise = noise_level(values) if noise is None else _checked_noise(noise, n_elements)
    peak = float(np.max(np.abs(values)))
    scale = np.maximum(noise, _NOISE_FLOOR * max(peak, np.finfo(float).tiny))
    covered = patterns.max(axis=0) > 0
    # Every field an array (a leaf the jit traces), so that other initial values compile nothing anew.
    base = jax.tree_util.tree_map(
        lambda value: jnp.asarray(value, float), _on_elements(initial, np.flatnonzero(covered), n_elements)
    )
    problem = _PressProblem(
        jnp.asarray(values[:, covered]),
        times,
        jnp.asarray(held, dtype=float),
        jnp.asarray(patterns[:, covered]),
        jnp.asarray(scale[covered]),
        base,
        names,
    )
    # The depths start from the memoryless least squares images = sum_k d_k patterns_k [held].
    basis = (held.T[:, :, None] * patterns[:, None, covered]) / scale[covered]  # (K, T, n)
    start_depths = np.linalg.lstsq(basis.reshape(n_presses, -1).T, (values[:, covered] / scale[covered]).ravel())[0]
    start_memory = memory_to_unconstrained(initial, names)
    x = jnp.concatenate([jnp.stack([start_memory[n] for n in names]), jnp.asarray(start_depths)])

    x, jacobian, chi_square, steps, result = _levenberg_marquardt(problem, x, max_steps)

    fitted_full = memory_from_unconstrained(dict(zip(names, x[: len(names)], strict=True)), initial)
    depths = np.asarray(x[len(names) :])
    degrees = max(jacobian.shape[0] - jacobian.shape[1], 1)
    reduced = chi_square / degrees
    errors = _standard_errors(jacobian, x, names, initial, max(reduced, 1.0))
    memory = _with_errors_ordered(fitted_full, names, errors)
    stimulus = (jnp.asarray(held, dtype=float) * jnp.asarray(depths)) @ jnp.asarray(patterns)
    response = memory_response(stimulus, times, fitted_full)
    size = float(jnp.linalg.norm(images))
    misfit = float(jnp.linalg.norm(images - response)) / size if size > 0 else 0.0
    fit = PressMemoryFit(
        memory=memory,
        depths=depths,
        standard_errors=errors,
        response=response,
        misfit=misfit,
        reduced_chi_square=reduced,
        noise=np.asarray(noise),
        steps=steps,
        result=result,
    )
    return throw_if_failed(fit, result, "press memory fit") if throw else fit


@host_algebra
def memory_from_press_readings(
    readings: jax.Array | np.ndarray,
    times: jax.Array | np.ndarray,
    windows: jax.Array | np.ndarray,
    depths: jax.Array | np.ndarray,
    *,
    bends: jax.Array | np.ndarray | None = None,
    initial: MemoryParameters | None = None,
    free: Collection[str] = DEFAULT_FREE,
    max_steps: int = 200,
    throw: bool = True,
) -> PressMemoryFit:
    """Fit the memory parameters to the readings of a labelled calibration session, each press's
    signature learned from its own frames.

    Press k (held over `windows[k]`, depth d_k) makes the response r_k(t) =
    `memory_response`(d_k [start_k <= t <= end_k]) from a rested skin at times[0], and the
    readings are modelled as

        readings(t) = c + sum_k [s_k r_k(t) / (1 + b_k r_k(t)) + u_k [t >= start_k]] + noise,

    with c (M,) the reference's offset, s_k (M,) press k's signature and u_k (M,) a lasting step
    from its start, all free: for each memory x they are the least-squares solution (variable
    projection), so the fit needs no forward model and no image, and what a model or an image
    gets wrong of a press's pattern does not enter. The steps take up what a press leaves for
    good: the first-cycle offset, which is the largest change an element has seen and so does
    not add up where footprints overlap (without them 0.34-0.64 of the parameters lay within
    two standard errors of the truth, docs/tutorials/calibration.md). b_k (`bends`) is how
    press k's readings bend with its depth (a forward model's readings under the press,
    projected on their linear part: a / (1 + b a) at relative change a). The free memory fields
    are fitted by Levenberg-Marquardt on the exact Jacobian, weighted by each reading's noise,
    which is estimated from the residuals (a first fit at equal weights, then one at the
    estimated weights; T - 2K - 1 degrees of freedom per reading), and their standard errors
    come from the Gauss-Newton covariance of the projected problem (Golub and Pereyra 2003),
    scaled by the reduced chi-square where it exceeds 1.

    What the images' fit (`memory_from_presses`) cannot give: its elements' residuals are those
    of an image, correlated in space and shaped by the image's blur, and its standard errors
    were several times too small through a one-step image (docs/tutorials/calibration.md).
    The signatures add up, so the memory of presses whose footprints overlap is taken as the
    sum of each press's own (as the model's modes are; its fatigue scales a later press's whole
    response, which its signature takes up).

    Arguments:
        readings: (T, M) each frame's readings less the reference's (any unit; signed, or
            magnitudes of readings that keep their sign), T > 2K + 2.
        times: (T,) frame times, seconds, increasing.
        windows: (K, 2) each press's hold start and end, seconds, as in `memory_from_presses`.
        depths: (K,) each press's depth, dsigma/sigma (< 0 for a touch that lowers the
            conductivity), nonzero: the memory's parts that do not scale with the depth
            (first-cycle offset, fatigue) and the bends act on it.
        bends: (K,) b_k, finite, with 1 + b_k d_k > 0; default 0 (readings linear in the change).
        initial: The start and the fixed values; default `diffeit.memory.over_foam()`.
        free: The fields fitted, as in `memory_from_presses`.
        max_steps: The most Levenberg-Marquardt steps of each of the two fits.
        throw: Raise for a fit that does not converge (True), or return it in `result` (False).

    Returns:
        The `PressMemoryFit`: `depths` as given, `standard_errors` of the free memory fields,
        `response` (T, M) the readings as the fit explains them, `noise` (M,) each reading's
        estimated noise (the readings' unit), `misfit` and `reduced_chi_square` of the readings.

    Raises:
        ValueError: For readings or times that are not finite or do not match, too few frames,
            windows as in `memory_from_presses`, depths or bends that are not (K,), not finite,
            depths of 0 or bends with 1 + b_k d_k <= 0, and invalid initial parameters or free
            names.
        diffeit.results.SolverError: With `throw=True`, for a fit that does not converge.
    """
    readings, times = check_images(readings, times, "readings")
    n_frames, n_readings = readings.shape
    depths = np.atleast_1d(np.asarray(depths, dtype=float))
    n_presses = len(depths)
    if depths.ndim != 1 or not np.all(np.isfinite(depths)) or np.any(depths == 0):
        raise ValueError(f"depths must be (K,) finite, nonzero relative changes (dsigma/sigma); got {depths}")
    if n_frames <= 2 * n_presses + 2:
        raise ValueError(
            f"the readings' memory fit of {n_presses} presses needs more than {2 * n_presses + 2} frames; "
            f"got {n_frames}"
        )
    bends = np.zeros(n_presses) if bends is None else np.asarray(bends, dtype=float)
    if bends.shape != (n_presses,) or not np.all(np.isfinite(bends)) or np.any(1 + bends * depths <= 0):
        raise ValueError(f"bends must be (K,) = ({n_presses},), finite, with 1 + b d > 0 at each depth; got {bends}")
    held = _held_frames(windows, np.asarray(times), n_presses)
    initial, names = _checked_start(initial, free, max_steps)
    base = jax.tree_util.tree_map(lambda value: jnp.asarray(value, float), initial)
    start = memory_to_unconstrained(initial, names)
    x = jnp.stack([start[n] for n in names])
    values = np.asarray(readings)
    problem = _ReadingsProblem(readings, times, jnp.asarray(held * depths), jnp.asarray(bends), base, names)
    per_reading = n_frames - 2 * n_presses - 1
    noise = np.ones(n_readings)
    for _ in range(2):  # equal weights from the start, then each reading's noise at the first fit
        left = np.asarray(_residuals(problem, x)).reshape(n_frames, n_readings) * noise
        noise = np.sqrt(np.sum(left**2, axis=0) / per_reading)
        noise = np.maximum(noise, _NOISE_FLOOR * max(float(np.max(noise)), np.finfo(float).tiny))
        problem = eqx.tree_at(lambda p: p.readings, problem, jnp.asarray(values / noise))
        x, jacobian, chi_square, steps, result = _levenberg_marquardt(problem, x, max_steps)
    degrees = max(per_reading * n_readings - len(names), 1)
    reduced = chi_square / degrees
    errors = _standard_errors(jacobian, x, names, initial, max(reduced, 1.0))
    fitted_full = memory_from_unconstrained(dict(zip(names, x, strict=True)), initial)
    memory = _with_errors_ordered(fitted_full, names, errors)
    response = values - np.asarray(_residuals(problem, x)).reshape(n_frames, n_readings) * noise
    size = float(np.linalg.norm(values))
    fit = PressMemoryFit(
        memory=memory,
        depths=depths,
        standard_errors=errors,
        response=jnp.asarray(response),
        misfit=float(np.linalg.norm(values - response)) / size if size > 0 else 0.0,
        reduced_chi_square=reduced,
        noise=noise,
        steps=steps,
        result=result,
    )
    return throw_if_failed(fit, result, "press readings' memory fit") if throw else fit


def _with_errors_ordered(fitted: MemoryParameters, names: tuple[str, ...], errors: dict) -> MemoryParameters:
    """The memory as reported (`reported_memory`: the quicker mode named fast); where the modes
    were exchanged, so are their `errors` (in place)."""
    memory = reported_memory(fitted, names)
    if memory is not fitted:
        for fast, slow in (("fast_fraction", "slow_fraction"), ("fast_time", "slow_time")):
            errors[fast], errors[slow] = errors[slow], errors[fast]
    return memory


def _checked_start(
    initial: MemoryParameters | None, free: Collection[str], max_steps: int
) -> tuple[MemoryParameters, tuple[str, ...]]:
    """The press fits' start (default `over_foam`) and free names, checked (`_checked_initial`),
    and a ValueError for `max_steps` that is not an integer >= 1."""
    if isinstance(max_steps, bool) or not (isinstance(max_steps, int) and max_steps >= 1):
        raise ValueError(f"max_steps must be an integer >= 1; got {max_steps!r}")
    return _checked_initial(over_foam() if initial is None else initial, free)


def _held_frames(windows: np.ndarray, frame_times: np.ndarray, n_presses: int) -> np.ndarray:
    """(T, K) whether press k is held at frame t, for hold `windows` (K, 2) seconds; ValueError
    for windows not (K, 2), not finite, reversed, outside the times or holding no frame."""
    windows = np.asarray(windows, dtype=float)
    if windows.shape != (n_presses, 2):
        raise ValueError(
            f"windows must have shape (K, 2) = ({n_presses}, 2), start and end seconds; got {windows.shape}"
        )
    if not np.all(np.isfinite(windows)):
        raise ValueError("windows must be finite (seconds)")
    if np.any(windows[:, 1] < windows[:, 0]):
        raise ValueError(
            f"windows end before they start: presses {np.flatnonzero(windows[:, 1] < windows[:, 0]).tolist()}"
        )
    outside = (windows[:, 0] < frame_times[0]) | (windows[:, 1] > frame_times[-1])
    if outside.any():
        raise ValueError(
            f"windows of presses {np.flatnonzero(outside).tolist()} lie outside the times "
            f"[{frame_times[0]}, {frame_times[-1]}] s"
        )
    held = (frame_times[:, None] >= windows[:, 0]) & (frame_times[:, None] <= windows[:, 1])
    if not held.any(axis=0).all():
        raise ValueError(f"windows of presses {np.flatnonzero(~held.any(axis=0)).tolist()} hold no frame")
    return held


def _levenberg_marquardt(
    problem: _PressProblem | _ReadingsProblem, x: jax.Array, max_steps: int
) -> tuple[jax.Array, np.ndarray, float, int, RESULTS]:
    """Minimise the chi-square sum(residuals^2) from `x`: the minimiser, the Jacobian and the
    chi-square there, the steps taken and the result code."""
    residuals, jacobian = (np.asarray(a) for a in _linearise(problem, x))
    chi_square = float(residuals @ residuals)
    if not (np.isfinite(chi_square) and np.all(np.isfinite(jacobian))):
        return x, jacobian, chi_square, 0, RESULTS.nonfinite
    damping = _DAMPING
    for step in range(1, max_steps + 1):
        information = jacobian.T @ jacobian
        gradient = jacobian.T @ residuals
        diagonal = np.maximum(np.diag(information), _SINGULAR * max(float(np.diag(information).max()), 1e-300))
        try:
            newton = np.linalg.solve(information + _SINGULAR * np.diag(diagonal), -gradient)
        except np.linalg.LinAlgError:
            newton = np.linalg.lstsq(information, -gradient)[0]
        # The chi-square the Gauss-Newton step would remove: -g.delta (for the undamped step).
        if -float(gradient @ newton) < _PREDICTED_DECREASE:
            return x, jacobian, chi_square, step - 1, RESULTS.successful
        while True:
            delta = np.linalg.solve(information + damping * np.diag(diagonal), -gradient)
            trial = x + jnp.asarray(delta)
            trial_chi_square = float(_chi_square(problem, trial))
            if np.isfinite(trial_chi_square) and trial_chi_square < chi_square:
                damping = max(damping * _SHRINK, 1e-12)
                break
            damping *= _GROW
            if damping > _DAMPING_LIMIT:
                return x, jacobian, chi_square, step, RESULTS.stalled
        x = trial
        residuals, jacobian = (np.asarray(a) for a in _linearise(problem, x))
        chi_square = float(residuals @ residuals)
        if not (np.isfinite(chi_square) and np.all(np.isfinite(jacobian))):
            return x, jacobian, chi_square, step, RESULTS.nonfinite
    return x, jacobian, chi_square, max_steps, RESULTS.max_iterations_reached


def _standard_errors(
    jacobian: np.ndarray,
    x: jax.Array,
    names: tuple[str, ...],
    initial: MemoryParameters,
    factor: float,
) -> dict:
    """The standard errors, natural units: the covariance factor (J^T J)^-1 of the unknowns,
    times `factor`, carried from the unconstrained memory fields to the natural ones by their
    derivatives (the delta method; the two mode fractions share both coordinates); the unknowns
    after the memory fields, where there are any, are the depths ("depths")."""
    n_memory, n_unknowns = len(names), jacobian.shape[1]
    with_depths = n_unknowns > n_memory
    information = jacobian.T @ jacobian
    eigenvalues = np.linalg.eigvalsh(information)
    if not (np.all(np.isfinite(eigenvalues)) and eigenvalues.min() > _SINGULAR * eigenvalues.max()):
        errors: dict = {name: float("inf") for name in names}
        if with_depths:
            errors["depths"] = np.full(n_unknowns - n_memory, np.inf)
        return errors
    covariance = np.linalg.inv(information) * factor

    def natural(unconstrained: jax.Array) -> jax.Array:
        memory = memory_from_unconstrained(dict(zip(names, unconstrained, strict=True)), initial)
        return jnp.stack([jnp.asarray(getattr(memory, name), float) for name in names])

    derivative = np.asarray(jax.jacfwd(natural)(x[:n_memory]))
    memory_covariance = derivative @ covariance[:n_memory, :n_memory] @ derivative.T
    errors = {name: float(np.sqrt(memory_covariance[i, i])) for i, name in enumerate(names)}
    if with_depths:
        errors["depths"] = np.sqrt(np.diag(covariance)[n_memory:])
    return errors
