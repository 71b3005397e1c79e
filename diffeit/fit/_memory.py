"""The memory effect in image space: its causal correction with known parameters (`correct_memory`),
and the fit of its parameters and of the memoryless stimulus from a sequence of images (`memory`).

Images, stimuli and responses are relative changes dsigma/sigma (dimensionless), per frame and
element; times are in seconds. The memory model is `diffeit.memory.MemoryParameters`
(docs/science.md#memory): every element evolves on its own, r = R_p(a). The correction is an
exact inverse of R_p, piece by piece of its piecewise linear response, with a dead band for
noisy images (docs/science.md#memory-correction); the fit constrains the stimulus to hold between
a few changes per element (docs/science.md#memory-fit).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Collection, Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._arrays import concrete_floats, is_concrete
from .._precision import ensure_float64
from ..memory import (
    MemoryParameters,
    MemoryState,
    advance,
    apply_stimulus,
    initial_state,
    memory_response,
    over_foam,
    read_response,
)
from ..results import RESULTS, throw_if_failed
from ._optimise import History, minimise

MEMORY_FIELDS = tuple(field.name for field in dataclasses.fields(MemoryParameters))
# The unconstrained transform of each memory parameter: log, logit, and the multinomial logit of
# the pair of mode fractions against 1 - their sum (the pair is free or fixed together).
_LOG = ("gain", "fast_time", "slow_time", "fatigue_rate", "fatigue_recovery_time")
_LOGIT = ("relaxation", "first_cycle_offset", "fatigue_limit")
_SHARES = ("fast_fraction", "slow_fraction")
# Boundary values (a fatigue rate of 0, a fraction of 0 or 1) move this far inside before their
# transform, which would be infinite there.
_INSIDE = 1e-9
_LOG_LIMIT = 14.0
DEFAULT_FREE = ("fast_fraction", "fast_time", "slow_fraction", "slow_time", "relaxation")
# The fields of the two recovery modes (`ordered_modes`).
MODE_FIELDS = ("fast_fraction", "fast_time", "slow_fraction", "slow_time")
# Elements whose misfit after a round exceeds this many times the median (or the noise level,
# whichever is larger) are left out of the next round: a change of touch was missed there.
_OUTLIER = 4.0
# The noise levels that weight the misfit are floored at this fraction of the largest |image|
# (noise-free images).
_NOISE_FLOOR = 1e-3
# The dead band (noise levels) of the correction that finds the segments: narrower than the final
# correction's, which on elements a few noise levels above their noise would swallow releases (a
# held segment must then explain a recovery, by relaxation); segments split by noise are joined
# after the fit.
_SEGMENT_BAND = 1.0
# The lower quartile of |x| for a standard normal x (`noise_level`).
_QUARTILE = 0.31863936396437514


# --- The correction -----------------------------------------------------------------------------


def correct_memory_step(
    state: MemoryState,
    image: jax.Array,
    time: jax.Array,
    memory: MemoryParameters,
    tolerance: float | jax.Array = 0.0,
) -> tuple[jax.Array, MemoryState]:
    """One frame of `correct_memory`: the stimulus whose response is `image`, and the next state.

    Pure JAX and unchecked: jit it for live use, frame by frame, starting from
    `diffeit.memory.initial_state(n_elements, time=first_time)` for a rested skin. The inverse
    and its dead band are in docs/science.md#memory-correction.

    Arguments:
        state: The skin's memory before this frame (`diffeit.memory.MemoryState`).
        image: The frame's image dsigma/sigma, one value per element of `state`.
        time: The frame's time, seconds, >= `state.time`.
        memory: The memory parameters.
        tolerance: The dead band (dsigma/sigma, scalar or per element): an image within it of
            the held stimulus' response keeps the stimulus. 0: the exact inverse.

    Returns:
        (stimulus, state): the memoryless stimulus dsigma/sigma per element, and the state
        after it.
    """
    held = advance(state, memory, time)
    previous, kappa, extreme = held.stimulus, held.sensitivity, held.extreme
    image = jnp.asarray(image, previous.dtype)
    holding = read_response(held, memory)
    deviation = image - holding
    size = jnp.abs(deviation)
    followed = jnp.where(size > 2 * tolerance, deviation, 2 * jnp.sign(deviation) * jnp.maximum(size - tolerance, 0))
    image = holding + followed

    # The lines r = intercept + slope a of the pieces (docs/science.md#memory-correction), from -inf to +inf.
    fraction = memory.fast_fraction + memory.slow_fraction
    unloading = memory.gain * (1 - fraction) * kappa
    loading = memory.gain * (1 - held.fatigue)
    constant = holding - unloading * previous
    # Loading on a_prev's side keeps the old load at its old sensitivity; on the other side a load
    # starts afresh from zero, continuing the unloading line there.
    same = constant + (unloading - loading) * previous
    negative, positive = jnp.where(previous < 0, same, constant), jnp.where(previous < 0, constant, same)
    offset = memory.first_cycle_offset
    intercepts = jnp.stack([negative - offset * extreme, negative, constant, positive, positive - offset * extreme])
    slopes = jnp.broadcast_to(
        jnp.stack(jnp.broadcast_arrays(loading + offset, loading, unloading, loading, loading + offset)),
        intercepts.shape,
    )
    knots = jnp.stack([-jnp.abs(extreme), jnp.minimum(previous, 0), jnp.maximum(previous, 0), jnp.abs(extreme)])
    unbounded = jnp.full_like(knots[:1], jnp.inf)
    lower, upper = jnp.concatenate([-unbounded, knots]), jnp.concatenate([knots, unbounded])
    candidates = jnp.clip((image - intercepts) / slopes, lower, upper)
    # The piece whose (clipped) solution reproduces the image; where rounding makes two agree at a
    # knot, unloading first, then the nearer loading pieces.
    order = jnp.asarray([2, 1, 3, 0, 4])
    misfit = jnp.abs(intercepts + slopes * candidates - image)[order]
    best = order[jnp.argmin(misfit, axis=0)]
    stimulus = jnp.take_along_axis(candidates, best[None], axis=0)[0]
    stimulus = jnp.where(size <= tolerance, previous, stimulus)
    return stimulus, apply_stimulus(held, stimulus)


def correct_memory(
    images: jax.Array | np.ndarray,
    times: jax.Array | np.ndarray,
    memory: MemoryParameters,
    *,
    state: MemoryState | None = None,
    tolerance: float | jax.Array | np.ndarray = 0.0,
) -> jax.Array:
    """The memoryless stimulus whose memory response is `images`, with known memory parameters.

    The causal inverse of `diffeit.memory.memory_response`: frame k uses frames 0..k only, in
    closed form, in one `jax.lax.scan`; jit, vmap and grad (in the images and every parameter)
    work. With `tolerance=0`, `memory_response(correct_memory(r)) == r` to rounding for any
    images the model can produce, and for images the model made the stimulus is recovered to
    rounding. `correct_memory_step` continues frame by frame from any state (live use). The
    inverse and its dead band are in docs/science.md#memory-correction.

    Arguments:
        images: (T, E) relative changes dsigma/sigma per frame and element (for example
            one-step images against the first frame).
        times: (T,) frame times, seconds, increasing.
        memory: The memory parameters (`diffeit.memory.MemoryParameters`).
        state: The skin's memory before the first frame (`diffeit.memory.initial_state`, or the
            state `integrate_memory` returned); default a rested, virgin skin at times[0].
        tolerance: The dead band for noisy images (dsigma/sigma, >= 0, scalar or (E,)), about 3
            noise standard deviations of the images. 0: the exact inverse.

    Returns:
        (T, E) the memoryless stimulus dsigma/sigma.

    Raises:
        ValueError: For concrete images that are not finite or not (T, E), times that do not
            increase (or start before `state.time`), lengths that differ, a negative tolerance,
            and fractions with f_fast + f_slow >= 1 (the unloading response would not depend
            on the stimulus).
    """
    images, times = check_images(images, times)
    _check_invertible(memory)
    tolerance = jnp.asarray(tolerance, images.dtype)
    if is_concrete(tolerance):
        value = np.asarray(tolerance)
        if not (np.all(np.isfinite(value)) and np.all(value >= 0)):
            raise ValueError(f"tolerance must be finite and >= 0 (dsigma/sigma); got {value}")
    if state is None:
        state = initial_state(images.shape[1:], time=times[0], dtype=images.dtype)
    elif is_concrete(state.time) and is_concrete(times) and float(times[0]) < float(state.time):
        raise ValueError(f"times[0] = {float(times[0])} s is before state.time = {float(state.time)} s")
    return _correct(images, times, memory, state, tolerance)


@eqx.filter_jit
def _correct(
    images: jax.Array, times: jax.Array, memory: MemoryParameters, state: MemoryState, tolerance: jax.Array
) -> jax.Array:
    def frame(state: MemoryState, inputs: tuple[jax.Array, jax.Array]) -> tuple[MemoryState, jax.Array]:
        image, time = inputs
        stimulus, state = correct_memory_step(state, image, time, memory, tolerance)
        return state, stimulus

    return jax.lax.scan(frame, state, (images, times))[1]


def check_images(images, times, what: str = "images") -> tuple[jax.Array, jax.Array]:
    """Check a sequence of images (or other per-frame rows, named by `what`) and their times,
    and return them as float arrays.

    Traced values (under jit) are checked for shape only.

    Arguments:
        images: (T, E) images, one row per frame, T >= 1.
        times: (T,) frame times, seconds, increasing.
        what: What the rows are, for the error messages.

    Returns:
        (images, times): (T, E) and (T,) float JAX arrays.

    Raises:
        ValueError: Naming the problem, for images that are not (T, E), hold no frame or are
            not finite, and for times as `check_times`.
    """
    ensure_float64()  # the fits' tolerances and a 1e-3 change of a time constant need float64
    images = jnp.asarray(images)
    if not jnp.issubdtype(images.dtype, jnp.floating):
        images = images.astype(jnp.result_type(float))
    if images.ndim != 2:
        raise ValueError(f"{what} must have shape (T, E), one row per frame; got shape {images.shape}")
    if images.shape[0] == 0:
        raise ValueError(f"{what} must hold at least one frame")
    if is_concrete(images):
        finite = np.all(np.isfinite(np.asarray(images)), axis=1)
        if not finite.all():
            raise ValueError(f"{what} must be finite; frame {int(np.flatnonzero(~finite)[0])} is not")
    return images, check_times(times, images.shape[0], what)


def check_times(times, n_frames: int, what: str = "frames") -> jax.Array:
    """Check frame times, and return them as a float array.

    Traced values (under jit) are checked for shape only.

    Arguments:
        times: (T,) frame times, seconds, increasing.
        n_frames: T, the number of frames the times must match.
        what: What the frames are, for the error message.

    Returns:
        (T,) the times, a float JAX array.

    Raises:
        ValueError: Naming the problem, for times that are not (n_frames,), not finite, or do
            not increase.
    """
    times = jnp.asarray(times, jnp.result_type(float))
    if times.ndim != 1:
        raise ValueError(f"times must have shape (T,), seconds; got shape {times.shape}")
    if times.shape[0] != n_frames:
        raise ValueError(
            f"{what} and times must have the same length; got {n_frames} {what} and {times.shape[0]} times"
        )
    if is_concrete(times):
        values = np.asarray(times)
        if not np.all(np.isfinite(values)):
            raise ValueError("times must be finite (seconds)")
        steps = np.diff(values)
        if np.any(steps <= 0):
            k = int(np.flatnonzero(steps <= 0)[0]) + 1
            raise ValueError(f"times must increase: times[{k}] = {values[k]} s <= times[{k - 1}] = {values[k - 1]} s")
    return times


def _check_invertible(memory: MemoryParameters) -> None:
    fast = concrete_floats(memory.fast_fraction, "MemoryParameters.fast_fraction")
    slow = concrete_floats(memory.slow_fraction, "MemoryParameters.slow_fraction")
    if fast is not None and slow is not None and np.any(fast + slow >= 1):
        raise ValueError(
            "the memory correction needs fast_fraction + slow_fraction < 1 (otherwise an easing load does not "
            f"change the response, and the response does not determine the stimulus); got {fast + slow}"
        )


# --- The memory parameters' unconstrained space ---------------------------------------------------


def _logit(value: jax.Array) -> jax.Array:
    value = jnp.clip(value, _INSIDE, 1 - _INSIDE)
    return jnp.log(value) - jnp.log1p(-value)


def memory_to_unconstrained(memory: MemoryParameters, names: Collection[str]) -> dict[str, jax.Array]:
    """Some fields of memory parameters in the fits' unconstrained space.

    ln of the gain, time constants and fatigue rate; logit of relaxation, first-cycle offset
    and fatigue limit; ln(f / (1 - f_fast - f_slow)) of each mode fraction f. Values on the
    boundary (a rate of 0, a fraction of 0 or 1) move 1e-9 inside first.
    `memory_from_unconstrained` is the inverse.

    Arguments:
        memory: The `MemoryParameters`.
        names: The fields to transform.

    Returns:
        The unconstrained value of each field, by name (scalar or (E,), as the field).
    """
    values = {}
    for name in names:
        value = jnp.asarray(getattr(memory, name), dtype=float)
        if name in _LOG:
            values[name] = jnp.log(jnp.maximum(value, _INSIDE))
        elif name in _LOGIT:
            values[name] = _logit(value)
        else:
            rest = 1 - jnp.asarray(memory.fast_fraction, float) - jnp.asarray(memory.slow_fraction, float)
            values[name] = jnp.log(jnp.maximum(value, _INSIDE)) - jnp.log(jnp.maximum(rest, _INSIDE))
    return values


def memory_from_unconstrained(values: Mapping[str, jax.Array], base: MemoryParameters) -> MemoryParameters:
    """Memory parameters from unconstrained values: the inverse of `memory_to_unconstrained`.

    The log-transformed fields are held within e^+-14 (1e-6 .. 1e6 s for a time constant); the
    two mode fractions are mapped back together (a softmax against 1 - their sum).

    Arguments:
        values: Unconstrained values by field name, as `memory_to_unconstrained` gives them
            (both mode fractions or neither).
        base: The `MemoryParameters` whose other fields are kept exactly.

    Returns:
        `base` with the fields of `values` mapped back and replaced.
    """
    changes = {}
    for name, value in values.items():
        if name in _LOG:
            # Held within e^+-14 (1e-6 .. 1e6 s for a time constant): data that cannot resolve
            # a mode otherwise walk its time constant to overflow.
            changes[name] = jnp.exp(jnp.clip(value, -_LOG_LIMIT, _LOG_LIMIT))
        elif name in _LOGIT:
            changes[name] = jax.nn.sigmoid(value)
    if _SHARES[0] in values:
        fast, slow = jnp.broadcast_arrays(values[_SHARES[0]], values[_SHARES[1]])
        shares = jax.nn.softmax(jnp.stack([fast, slow, jnp.zeros_like(fast)]), axis=0)
        changes[_SHARES[0]], changes[_SHARES[1]] = shares[0], shares[1]
    return dataclasses.replace(base, **changes)


def ordered_modes(memory: MemoryParameters) -> MemoryParameters:
    """Name the two recovery modes of memory parameters by their time constants.

    Where the fast mode came out slower than the slow one, their fractions and time constants
    are exchanged (per element, for fields given per element). The memory model treats the two
    modes alike, so the exchange changes no response: a fit can end with either labelling, and
    the fits report this one.

    Arguments:
        memory: The memory parameters, of concrete values (call it outside `jax.jit`).

    Returns:
        The `MemoryParameters` with fast_time <= slow_time everywhere (`memory` itself when
        they already are).

    Raises:
        ValueError: For anything but a `MemoryParameters`, for traced values, or for mode
            fields that are not finite numbers.
    """
    if not isinstance(memory, MemoryParameters):
        raise ValueError(f"ordered_modes takes a MemoryParameters; got {type(memory).__name__}")
    values = {name: concrete_floats(getattr(memory, name), f"MemoryParameters.{name}") for name in MODE_FIELDS}
    if any(value is None for value in values.values()):
        raise ValueError("ordered_modes needs the memory parameters' values, not traced arrays (call it outside jit)")
    swap = values["fast_time"] > values["slow_time"]
    if not np.any(swap):
        return memory
    changes = {}
    for fast, slow in (("fast_fraction", "slow_fraction"), ("fast_time", "slow_time")):
        a, b = values[fast], values[slow]
        for name, value in ((fast, np.where(swap, b, a)), (slow, np.where(swap, a, b))):
            changes[name] = float(value) if value.ndim == 0 else jnp.asarray(value)
    return dataclasses.replace(memory, **changes)


def reported_memory(memory: MemoryParameters, fitted: Collection[str]) -> MemoryParameters:
    """The memory parameters a fit reports, its modes ordered when the fit moved them.

    `ordered_modes(memory)` when all four mode fields were among the `fitted` fields;
    `memory` as it is when a mode was held (its labels are then the caller's).

    Arguments:
        memory: The fitted `MemoryParameters`, of concrete values.
        fitted: The fields the fit moved.

    Returns:
        The `MemoryParameters` to report.

    Raises:
        ValueError: As `ordered_modes`, when it is called.
    """
    return ordered_modes(memory) if set(MODE_FIELDS) <= set(fitted) else memory


# --- The fit --------------------------------------------------------------------------------------


class MemoryFit(eqx.Module):
    """The result of `memory`: the fitted memory parameters, the stimulus and the response.

    Attributes:
        memory: The fitted `diffeit.memory.MemoryParameters` (the free fields fitted, one value
            shared by all elements; the others as given); with both modes free, the quicker one
            is named fast (`ordered_modes`).
        stimulus: (T, E) the memoryless stimulus dsigma/sigma, `correct_memory` of the images
            with the fitted parameters and the dead band at the images' noise level.
        response: (T, E) `memory_response(stimulus)`, the images as the fitted model explains
            them.
        misfit: ||images - response|| / ||images|| over all frames and elements (dimensionless;
            about the noise level of the images relative to their size).
        noise: (E,) the noise standard deviation of each element's images (dsigma/sigma), as
            given or estimated from the images.
        elements: (E,) bool, the elements whose images informed the parameters (above the noise
            threshold, and not left out as outliers).
        history: `History` of the optimisation, the rounds one after the other.
        result: `RESULTS` of the last round's optimisation.
    """

    memory: MemoryParameters
    stimulus: jax.Array
    response: jax.Array
    misfit: float
    noise: np.ndarray
    elements: np.ndarray
    history: History
    result: RESULTS


class MemoryObjective(eqx.Module):
    """The objective of `memory`'s parameter fit, over the n chosen elements.

    The weighted least-squares misfit of the images against the memory response of a stimulus
    that is constant within segments of frames,

        J = 1/2 sum_e w_e sum_k (y_ke - R_p(a)_ke)^2,   a_ke = S[seg_ke, e] exp(u[seg_ke, e]),
        w_e = 1 / (T n sigma_e^2),

    a function of the unknowns `(memory, u)`: the free memory parameters, unconstrained
    (`memory_to_unconstrained`), and the (T, n) log-magnitudes u of the levels, row j those of
    segment j of each element. The signs S are fixed: each element's touch sign (that of its
    largest |image|) on touched segments, 0 on resting ones (their stimulus is 0), so a level
    keeps its sign (why: docs/science.md#memory-fit).

    Attributes:
        images: (T, n) the chosen elements' images y, dsigma/sigma.
        times: (T,) the frame times, seconds.
        weights: (n,) w_e, 0 for elements left out.
        segments: (T, n) int, the segment of each frame, per element.
        signs: (T, n) S, per segment (rows past an element's last segment are unused).
        base: The `MemoryParameters` the free fields replace.
    """

    images: jax.Array
    times: jax.Array
    weights: jax.Array
    segments: jax.Array
    signs: jax.Array
    base: MemoryParameters

    def stimulus(self, log_levels: jax.Array) -> jax.Array:
        """The stimulus of the segment levels: a_ke = S[seg_ke, e] exp(u[seg_ke, e]).

        Arguments:
            log_levels: (T, n) u, the log-magnitudes of the levels, row j segment j's.

        Returns:
            (T, n) the stimulus a, dsigma/sigma.
        """
        return jnp.take_along_axis(self.signs * jnp.exp(log_levels), self.segments, axis=0)

    def units(self, unknowns: tuple[dict[str, jax.Array], jax.Array]) -> tuple[dict[str, jax.Array], jax.Array]:
        """The optimiser's unit of each unknown: 1 / sqrt of the objective's curvature there.

        The Gauss-Newton curvature at `unknowns`, a diagonal preconditioner: the memory
        parameters' by forward differentiation of the residuals, each level's from the
        response's slope taken as 1 (w_e a^2 times its number of frames).

        Arguments:
            unknowns: `(memory, u)`, as `__call__` takes them.

        Returns:
            The units, in the structure of `unknowns`.
        """
        memory, log_levels = unknowns
        curvatures = {}
        for name in memory:
            tangent = {other: jnp.zeros_like(value) for other, value in memory.items()}
            tangent[name] = jnp.ones_like(memory[name])
            _, derivative = jax.jvp(lambda values: self.residuals((values, log_levels)), (memory,), (tangent,))
            curvatures[name] = jnp.sum(self.weights * derivative**2)
        counts = jax.vmap(lambda segments: jnp.bincount(segments, length=log_levels.shape[0]), in_axes=1, out_axes=1)(
            self.segments
        )
        levels = (self.signs * jnp.exp(log_levels)) ** 2
        level_curvatures = self.weights * counts * levels
        return jax.tree_util.tree_map(lambda c: 1 / jnp.sqrt(c + 1e-12), (curvatures, level_curvatures))

    def residuals(self, unknowns: tuple[dict[str, jax.Array], jax.Array]) -> jax.Array:
        """The residuals y - R_p(a) of the images against the model.

        Arguments:
            unknowns: `(memory, u)`: the free memory parameters, unconstrained, by name, and
                (T, n) the levels' log-magnitudes.

        Returns:
            (T, n) images minus responses, dsigma/sigma.
        """
        memory, levels = unknowns
        parameters = memory_from_unconstrained(memory, self.base)
        return self.images - memory_response(self.stimulus(levels), self.times, parameters)

    def __call__(self, unknowns: tuple[dict[str, jax.Array], jax.Array]) -> jax.Array:
        """J at `unknowns` (`(memory, u)`, as `residuals` takes them): a scalar, about 1/2 at the noise level."""
        return 0.5 * jnp.sum(self.weights * self.residuals(unknowns) ** 2)


def memory(
    images: jax.Array | np.ndarray,
    times: jax.Array | np.ndarray,
    *,
    initial: MemoryParameters | None = None,
    free: Collection[str] = DEFAULT_FREE,
    jump: float = 0.3,
    threshold: float = 5.0,
    tolerance: float = 3.0,
    rounds: int = 2,
    noise: float | jax.Array | np.ndarray | None = None,
    max_elements: int = 200,
    max_steps: int = 1000,
    throw: bool = True,
    progress: bool = True,
) -> MemoryFit:
    """Fit the memory model's parameters and the memoryless stimulus to a sequence of images.

    The images are relative changes (for example one-step images against the first frame),
    modelled per element e and frame k as images_ke = R_p(a)_ke + noise: R_p the memory
    response (`diffeit.memory.memory_response`) from a rested, virgin skin at times[0], p the
    memory parameters (the free ones shared by all elements), a the memoryless stimulus. Any p
    explains the images exactly with a free stimulus, so the stimulus is taken as constant within
    segments of frames per element (touches hold between a few changes), and p and the segment
    levels are fitted together by weighted least squares (L-BFGS), in `rounds` rounds that find
    the segments again. The gain is never fitted, and the first-cycle offset and fatigue are
    held by default. The prior, the segments, the choice of elements and what the images
    determine are in docs/science.md#memory-fit.

    Arguments:
        images: (T, E) relative changes dsigma/sigma, T >= 3.
        times: (T,) frame times, seconds, increasing.
        initial: The start and the fixed values (`MemoryParameters` of scalars for the free
            fields); default `diffeit.memory.over_foam()`.
        free: The fields fitted; default the fractions, time constants and relaxation. The two
            fractions are free or fixed together (their sum stays below 1); never the gain.
        jump: A segment starts where the stimulus changes by more than `jump` (in (0, 1)) times
            the element's largest |stimulus|; a segment whose level is below `jump` / 2 of it is
            a rest (stimulus 0), and neighbours whose levels differ by less are joined.
        threshold: Elements whose largest |image| is below `threshold` times their noise level
            take no part in the fit (they are still corrected).
        tolerance: The dead band of the final correction, in noise levels (`correct_memory`).
        rounds: How many rounds of segmentation and fit at most.
        noise: The images' noise standard deviation (dsigma/sigma, a number or (E,)), when it is
            known (for one-step images, from the readings' noise through the reconstruction
            matrix); default estimated from the images' second differences in time.
        max_elements: How many of the elements above the threshold (the strongest, by largest
            |image| over noise) fit the parameters at most.
        max_steps: The limit of each L-BFGS run (a round runs one or two).
        throw: Raise for a fit that does not converge (True), or return it in `result` (False).
        progress: Show progress bars.

    Returns:
        The `MemoryFit`.

    Raises:
        ValueError: For non-finite images, fewer than 3 frames, times that do not increase,
            images and times of different lengths, invalid initial parameters or options,
            unknown or refused free names, and images in which no element exceeds the noise
            threshold.
        diffeit.results.SolverError: With `throw=True`, for a fit that does not converge.
    """
    images, times = check_images(images, times)
    initial = over_foam() if initial is None else initial
    initial, free = _checked_initial(initial, free)
    _check_options(jump, threshold, tolerance, rounds)
    if isinstance(max_elements, bool) or not (isinstance(max_elements, int) and max_elements >= 1):
        raise ValueError(f"max_elements must be an integer >= 1; got {max_elements!r}")
    if images.shape[0] < 3:
        raise ValueError(f"the memory fit needs at least 3 frames; got {images.shape[0]}")

    values = np.asarray(images)
    peak = np.max(np.abs(values), axis=0)
    noise = noise_level(values) if noise is None else _checked_noise(noise, values.shape[1])
    scale = np.maximum(noise, _NOISE_FLOOR * max(float(peak.max()), np.finfo(float).tiny))
    elements = (peak > 0) & (peak >= threshold * scale)
    if not elements.any():
        raise ValueError(
            f"no element's images exceed {threshold} times their noise level: there is no touch to fit the memory to"
        )

    # The parameters are shared: the strongest elements (peak over noise) determine them as well
    # as all would, at a fraction of the cost on fine meshes.
    if elements.sum() > max_elements:
        strength = np.where(elements, peak / scale, -np.inf)
        elements = np.zeros_like(elements)
        elements[np.argsort(strength)[-max_elements:]] = True
    # The unknowns keep their shapes through all rounds (levels for up to T segments, every
    # candidate element, those left out weighted 0), so that the optimisation compiles once.
    candidates = np.flatnonzero(elements)
    chosen = np.ones(candidates.size, bool)
    data = jnp.asarray(values[:, candidates])
    strongest = np.argmax(np.abs(values[:, candidates]), axis=0)
    touch_signs = np.sign(values[strongest, candidates])
    base = _on_elements(initial, candidates, values.shape[1])
    unknowns = memory_to_unconstrained(initial, free)
    objectives, norms = [], []
    used = detected = None
    for round_ in range(rounds):
        weights = jnp.asarray(np.where(chosen, 1 / (values.shape[0] * chosen.sum() * scale[candidates] ** 2), 0))
        current = memory_from_unconstrained(unknowns, base)
        held = np.asarray(correct_memory(data, times, current, tolerance=_SEGMENT_BAND * noise[candidates]))
        segments = _segments(held, jump)
        if used is not None and np.array_equal(chosen, used) and np.array_equal(segments, detected):
            break  # the same problem as the last round's, solved already
        used, detected = chosen, segments
        levels = _segment_medians(held, segments)
        # Fit; then join the segments whose levels came out alike (noise, not a touch: such a
        # boundary is a kink of the objective, which stalls L-BFGS) and fit once more.
        for attempt in range(2):
            touched = (levels * touch_signs > 0) & (np.abs(levels) >= jump / 2 * np.max(np.abs(levels), axis=0))
            signs = np.where(touched, touch_signs, 0.0)
            objective = MemoryObjective(data, times, weights, jnp.asarray(segments), jnp.asarray(signs), base)
            start = (unknowns, jnp.asarray(np.log(np.where(touched, np.abs(levels), 1.0))))
            found = minimise(
                objective,
                start,
                units=_units(objective, start),
                max_steps=max_steps,
                # J is about 1/2 at the noise level: 1e-8 of that is far below any real change.
                atol=1e-8,
                progress=progress,
                description=f"memory fit {round_ + 1}/{rounds}",
            )
            unknowns = found.value[0]
            levels = signs * np.exp(np.asarray(found.value[1]))
            if found.result == RESULTS.nonfinite:
                break
            objectives.append(found.objective)
            norms.append(found.gradient_norm)
            joined = _joined(levels, segments, jump / 2)
            if attempt or np.array_equal(joined, segments):
                break
            levels = _segment_medians(np.take_along_axis(levels, segments, axis=0), joined)
            segments = joined
        if found.result == RESULTS.nonfinite:
            break  # no further round from a point where the gradient is not finite
        spread = np.mean(np.asarray(objective.residuals(found.value)) ** 2, axis=0) / scale[candidates] ** 2
        chosen = used & (spread <= _OUTLIER * max(float(np.median(spread[used])), 1.0))
    elements[candidates] = used

    fitted = memory_from_unconstrained(unknowns, initial)
    stimulus = correct_memory(images, times, fitted, tolerance=jnp.asarray(tolerance * noise))
    response = memory_response(stimulus, times, fitted)
    size = float(jnp.linalg.norm(images))
    misfit = float(jnp.linalg.norm(images - response)) / size if size > 0 else 0.0
    fit = MemoryFit(
        memory=reported_memory(fitted, free),
        stimulus=stimulus,
        response=response,
        misfit=misfit,
        noise=noise,
        elements=elements,
        history=History(np.concatenate(objectives), np.concatenate(norms)),
        result=found.result,
    )
    return throw_if_failed(fit, found.result, "memory fit") if throw else fit


@eqx.filter_jit
def _units(objective: MemoryObjective, start: tuple[dict[str, jax.Array], jax.Array]):
    return objective.units(start)


def noise_level(images: np.ndarray) -> np.ndarray:
    """An estimate of the noise standard deviation of each element's images.

    The lower quartile of the absolute second differences in time, scaled to a standard
    deviation of white noise (the quartile of |N(0, 6)| is 0.3186 sqrt(6)). Steps (touches) and
    the memory's decays move second differences up, at up to three frames per step: the
    quartile ignores them while they take fewer than about half the frames, and overestimates
    the noise (never underestimates it) in elements touched more often than that.

    Arguments:
        images: (T, E) images, T >= 3, any unit (dsigma/sigma for the memory fit).

    Returns:
        (E,) the noise standard deviation of each element, in the images' unit.
    """
    second = np.abs(np.diff(images, 2, axis=0))
    return np.quantile(second, 0.25, axis=0) / (_QUARTILE * np.sqrt(6.0))


def _checked_noise(noise, n_elements: int) -> np.ndarray:
    value = np.asarray(noise, dtype=float)
    if value.shape not in ((), (n_elements,)):
        raise ValueError(f"noise must be a number or one value per element ({n_elements},); got shape {value.shape}")
    if not np.all(np.isfinite(value) & (value >= 0)):
        raise ValueError("noise must be finite and >= 0 (dsigma/sigma)")
    return np.broadcast_to(value, (n_elements,))


def _segments(stimulus: np.ndarray, jump: float) -> np.ndarray:
    """(T, E) int: the segment of each frame, per element; a segment starts where the stimulus
    changes by more than `jump` times the element's largest |stimulus|."""
    peak = np.max(np.abs(stimulus), axis=0)
    changes = np.abs(np.diff(stimulus, axis=0)) > jump * peak
    return np.concatenate([np.zeros((1, stimulus.shape[1]), int), np.cumsum(changes, axis=0)])


def _joined(levels: np.ndarray, segments: np.ndarray, closeness: float) -> np.ndarray:
    """`segments` without the boundaries where the levels on either side differ by less than
    `closeness` times the element's largest |level|."""
    peak = np.max(np.abs(levels), axis=0)
    stimulus = np.take_along_axis(levels, segments, axis=0)
    kept = (np.diff(segments, axis=0) != 0) & (np.abs(np.diff(stimulus, axis=0)) >= closeness * peak)
    return np.concatenate([np.zeros((1, segments.shape[1]), int), np.cumsum(kept, axis=0)])


def _segment_medians(stimulus: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """(T, E) the median stimulus of each segment and element in the first rows, zeros after (an
    element has at most T segments): the levels the fit starts from."""
    levels = np.zeros(stimulus.shape)
    for index in range(int(segments.max()) + 1):
        inside = segments == index
        present = inside.any(axis=0)
        masked = np.where(inside[:, present], stimulus[:, present], np.nan)
        levels[index, present] = np.nanmedian(masked, axis=0)
    return levels


def _on_elements(parameters: MemoryParameters, chosen: np.ndarray, n_elements: int) -> MemoryParameters:
    """`parameters` with its per-element fields ((E,) arrays) restricted to the `chosen` elements."""
    changes = {}
    for name in MEMORY_FIELDS:
        value = getattr(parameters, name)
        if np.shape(value) == (n_elements,):
            changes[name] = jnp.asarray(value)[chosen]
    return dataclasses.replace(parameters, **changes)


def _checked_initial(initial: MemoryParameters, free: Collection[str]) -> tuple[MemoryParameters, tuple[str, ...]]:
    """`initial` re-built, so that its checks run (a Module changed by `eqx.tree_at` skips them),
    and the names in `free`, checked and in field order."""
    if not isinstance(initial, MemoryParameters):
        raise ValueError(f"initial must be a MemoryParameters; got {type(initial).__name__}")
    initial = MemoryParameters(**{name: getattr(initial, name) for name in MEMORY_FIELDS})
    names = (free,) if isinstance(free, str) else tuple(free)
    unknown = sorted(set(names) - set(MEMORY_FIELDS))
    if unknown:
        raise ValueError(f"free: unknown names {unknown}; the fields of MemoryParameters are {list(MEMORY_FIELDS)}")
    if not names:
        raise ValueError("free names no memory parameter: there is nothing to fit")
    if "gain" in names:
        raise ValueError("free: the gain trades exactly with the stimulus amplitude and cannot be fitted here")
    if (_SHARES[0] in names) != (_SHARES[1] in names):
        raise ValueError("free: fast_fraction and slow_fraction are fitted together (their sum stays below 1)")
    for name in names:
        value = concrete_floats(getattr(initial, name), f"MemoryParameters.{name}")
        if value is None:
            raise ValueError(f"the initial memory must hold values, not traced arrays (MemoryParameters.{name})")
        if value.shape != ():
            raise ValueError(f"the fitted parameters are shared by all elements: initial.{name} must be a scalar")
        inside = value > 0 if name in _LOG else 0 < value < 1
        if not inside:
            raise ValueError(f"initial.{name} = {float(value)} is on the boundary of its range: free ones start inside")
    _check_invertible(initial)
    return initial, tuple(name for name in MEMORY_FIELDS if name in names)


def _check_options(jump: float, threshold: float, tolerance: float, rounds: int) -> None:
    if not (np.isfinite(jump) and 0 < jump < 1):
        raise ValueError(f"jump must lie in (0, 1) (a fraction of each element's largest stimulus); got {jump}")
    if not (np.isfinite(threshold) and threshold >= 0):
        raise ValueError(f"threshold must be finite and >= 0 (noise levels); got {threshold}")
    if not (np.isfinite(tolerance) and tolerance >= 0):
        raise ValueError(f"tolerance must be finite and >= 0 (noise levels); got {tolerance}")
    if not (isinstance(rounds, int) and rounds >= 1):
        raise ValueError(f"rounds must be an integer >= 1; got {rounds}")
