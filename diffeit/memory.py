"""The memory effect: the skin's viscoelastic response per element, integrated exactly per frame.

The stimulus a(t) is the relative conductivity change dsigma/sigma (dimensionless) that an ideal,
memoryless skin would show: <= 0 under a touch (strain breaks percolation paths). The skin reads
a response r(t) (also dsigma/sigma) that remembers its history: an instant rise on loading,
relaxation while held, an instant drop on release, a slow recovery with two time constants, a
permanent first-cycle (Mullins) offset and a lower sensitivity shortly after a touch
(the tactile-skin dissertation's memory effects). Every element evolves on its own.

## Input between frames
The stimulus is held between frames (zero-order hold, piecewise constant): a(t) = a_k for
t_k <= t < t_{k+1}, and the response of frame k is r(t_k) just after any step at t_k. A press or a
release at a frame time is represented exactly at any frame rate (a press between frames is seen
at the next frame), and between frames the model is linear with a constant input, so each
interval is integrated in closed form (exponentials): no step-size error, and responses at shared
frame times do not depend on the frame rate.

## The model
State per element: the held stimulus a_prev; kappa, the sensitivity the present load was applied
with (1 on a rested skin); two Prony (generalised Maxwell) modes b_fast, b_slow (dsigma/sigma);
a_max, the stimulus of largest magnitude seen so far (the running maximum of |a|, with its sign);
the fatigue phi (fractional loss of sensitivity, 0 when rested). Mode i has the fraction f_i and
the time constant tau_i (s); rho is the relaxed fraction; F = f_fast + f_slow; s = 1 - phi.

- At a frame, instantly. Loading (|a_k| > |a_prev| on a_prev's side) enters at the present
  sensitivity: kappa <- s + (kappa - s) w, w = a_prev / a_k (kappa a is the load weighted by the
  sensitivity each part of it was applied with), and every mode takes the increment of kappa a:
  b_i <- b_i + kappa' a_k - kappa a_prev. Unloading (|a_k| <= |a_prev|, same side) keeps kappa
  (the load eases in proportion) and moves no mode: paths break at once but re-form slowly. A
  stimulus of the other sign than a_prev is a fresh load in the other direction: kappa <- s and
  b_i <- b_i + s a_k; the old load leaves the modes slowly, as after a release. The response is
  then continuous in a_k everywhere, zero included. a_max <- a_k when |a_k| > |a_max|.
- Between frames, a held: db_i/dt = ((1 - rho) kappa a - b_i) / tau_i, that is
  b_i(t + dt) = b_i(t) e^(-dt/tau_i) + (1 - rho) kappa a (1 - e^(-dt/tau_i)): under a held touch a
  fraction rho of each mode relaxes (the network partly re-forms under strain); after release
  (a = 0) each mode recovers to zero with its own time constant.
- Fatigue builds while loaded, in proportion to the stimulus, and recovers with its own time
  constant: dphi/dt = k |a| (phi_max - phi) - phi / tau_phi, that is
  phi(t + dt) = phi(t) e^(-lambda dt) + phi_inf (1 - e^(-lambda dt)), lambda = k |a| + 1/tau_phi,
  phi_inf = phi_max x / (1 + x), x = k |a| tau_phi. It lowers the gain of the next loading, not
  the change already there; proportional to |a|, so the faint tails of a smooth-edged touch do
  not fatigue the whole skin.
- Response: r = g [(1 - F) kappa a + f_fast b_fast + f_slow b_slow] + mu a_max
  = g kappa a + g sum_i f_i (b_i - kappa a) + mu a_max: the gain times the stimulus, the Prony
  memory and the permanent first-cycle offset. The first loading to a new depth reads
  mu |a| larger than later ones, and after it the baseline stays shifted by mu a_max.

Why not a linear Maxwell model alone: in any linear time-invariant model a response that relaxes
while held leaves a residual of the opposite sign after release (r = a [G(t) - G(t - H)] < 0 for a
decreasing relaxation function G). The skin's residual keeps the sign of the touch, so loading
and unloading differ: the modes follow loading at once and unloading slowly.

## A press of height a at t0, held H seconds (the closed form the tests check)
On a skin of fatigue phi0, sensitivity s0 = 1 - phi0, with modes b_i0 (0 when rested), for
0 <= t - t0 = v < H: b_i = (1 - rho) s0 a + (b_i0 + s0 a - (1 - rho) s0 a) e^(-v/tau_i),
phi = phi_inf + (phi0 - phi_inf) e^(-lambda v), r = g [(1 - F) s0 a + sum_i f_i b_i] + mu a_max;
after release, u = v - H: b_i = b_i(H) e^(-u/tau_i), phi = phi(H) e^(-u/tau_phi),
r = g sum_i f_i b_i + mu a_max. On a rested skin: r = g a [1 - rho sum_i f_i (1 - e^(-v/tau_i))]
+ mu a_max while held.

## Defaults
The presets `bare_skin` and `over_foam` (`MemoryParameters()` is `over_foam()`), their values
and how they were calibrated are in docs/science.md#memory.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._arrays import concrete_floats, is_concrete
from ._precision import ensure_float64

ArrayLike = float | jax.Array | np.ndarray

# The fields of MemoryParameters that are time constants (> 0, seconds) and fractions ([0, 1]).
_TIMES = ("fast_time", "slow_time", "fatigue_recovery_time")
# Stimuli below this magnitude (far below anything measurable) never divide (`apply_stimulus`).
_TINY = 1e-100
_FRACTIONS = ("fast_fraction", "slow_fraction", "relaxation", "first_cycle_offset", "fatigue_limit")

# Calibration of the presets (summarised in docs/science.md#memory). A reference press a = -0.3
# (dR/R0 about 43%, the middle of the dissertation's finger presses) held 5 s on a
# preconditioned, rested skin; changes measured from the baseline before the press, the peak is
# the change at the press:
#
# |                                                  | bare_skin            | over_foam         |
# | fast mode: fraction, time constant               | 0.30, 0.5 s          | 0.30, 1.0 s       |
# | slow mode: fraction, time constant               | 0.22, 5.7 s          | 0.30, 7.7 s       |
# | relaxed fraction rho (response lost over 5 s)    | 0.15 (6%)            | 0.25 (11%)        |
# | left just after release                          | 46% of the peak      | 49%               |
# | recovery to 10% of the peak, after release       | 4.0 s (3.6-4.4 s for | 7.5 s (6.3-8.2 s) |
# |                                                  | holds of 30-1 s)     |                   |
#
# Both: gain g = 1; first-cycle offset mu = 0.05 (5% of the largest stimulus stays, so the first
# touch reads 5% of its depth larger; the dissertation gives no figure); fatigue limit
# phi_max = 0.4 (cycling lowers the sensitivity about 40%), fatigue rate k = 1.3 /s per unit
# |stimulus|, fatigue recovery time tau_phi = 100 s: a second reference press 30 s after the
# first reads 25% less than on a rested skin (between 4% less for a 1 s tap of -0.1 and 29% less
# for long or deep presses), and 5 minutes later 1.7% less (the dissertation spaced its tests 5
# minutes apart to be safe).


class MemoryParameters(eqx.Module):
    """Parameters of the memory effect (the model is in the module docstring).

    Every field is a scalar or an array broadcasting against the elements (for example one value
    per element, for a skin partly over foam); every field is a leaf, so `jax.grad`
    differentiates with respect to all of them. Defaults are `over_foam()`. Concrete values are
    checked on construction; traced values are not.

    Attributes:
        gain: g, response per unit stimulus of a rested, preconditioned skin (dimensionless,
            > 0).
        fast_fraction: f_fast, the part of the response carried by the fast Prony mode
            ([0, 1]; `fast_fraction + slow_fraction <= 1`).
        fast_time: tau_fast, its time constant (seconds, > 0).
        slow_fraction: f_slow, the part carried by the slow Prony mode ([0, 1]).
        slow_time: tau_slow, its time constant (seconds, > 0).
        relaxation: rho, the fraction of each mode that relaxes while a touch is held
            ([0, 1]).
        first_cycle_offset: mu, the permanent baseline shift per unit of the largest stimulus
            seen so far (the Mullins effect; [0, 1]).
        fatigue_limit: phi_max, the largest fractional loss of sensitivity ([0, 1]).
        fatigue_rate: k, the build-up rate of fatigue per unit |stimulus| (1/s, >= 0).
        fatigue_recovery_time: tau_phi, the recovery time constant of fatigue (seconds, > 0).

    Raises:
        ValueError: Naming the offending field, for a concrete value that is not numbers, not
            finite or out of its range.
    """

    gain: ArrayLike = 1.0
    fast_fraction: ArrayLike = 0.30
    fast_time: ArrayLike = 1.0
    slow_fraction: ArrayLike = 0.30
    slow_time: ArrayLike = 7.7
    relaxation: ArrayLike = 0.25
    first_cycle_offset: ArrayLike = 0.05
    fatigue_limit: ArrayLike = 0.4
    fatigue_rate: ArrayLike = 1.3
    fatigue_recovery_time: ArrayLike = 100.0

    def __check_init__(self) -> None:
        _check_parameters(self)


def _check_parameters(parameters: MemoryParameters) -> None:
    """ValueError naming the field for concrete values out of range; traced values pass."""
    values = {}
    for f in dataclasses.fields(parameters):
        value = concrete_floats(getattr(parameters, f.name), f"MemoryParameters.{f.name}")
        if value is not None:
            values[f.name] = value
    for name, value in values.items():
        if name in _TIMES and not np.all(value > 0):
            raise ValueError(f"MemoryParameters.{name} is a time constant: it must be positive (seconds); got {value}")
        if name in _FRACTIONS and not np.all((value >= 0) & (value <= 1)):
            raise ValueError(f"MemoryParameters.{name} is a fraction: it must lie in [0, 1]; got {value}")
    if "gain" in values and not np.all(values["gain"] > 0):
        raise ValueError(f"MemoryParameters.gain must be positive; got {values['gain']}")
    if "fatigue_rate" in values and not np.all(values["fatigue_rate"] >= 0):
        raise ValueError(f"MemoryParameters.fatigue_rate must be >= 0 (1/s); got {values['fatigue_rate']}")
    if "fast_fraction" in values and "slow_fraction" in values:
        total = values["fast_fraction"] + values["slow_fraction"]
        if not np.all(total <= 1):
            raise ValueError(
                f"MemoryParameters.fast_fraction + MemoryParameters.slow_fraction must be <= 1; got {total}"
            )


def bare_skin() -> MemoryParameters:
    """The memory of a skin on a rigid backing.

    Faster than `over_foam`: after a held press the response recovers to 10% of its peak
    about 4 s after release (docs/science.md#memory).

    Returns:
        The `MemoryParameters`.
    """
    return MemoryParameters(fast_fraction=0.30, fast_time=0.5, slow_fraction=0.22, slow_time=5.7, relaxation=0.15)


def over_foam() -> MemoryParameters:
    """The memory of a skin over soft open-cell foam: the defaults of `MemoryParameters`.

    The padding dominates the memory: after a held press the response recovers to 10% of its
    peak about 7.5 s after release (docs/science.md#memory).

    Returns:
        The `MemoryParameters`.
    """
    return MemoryParameters()


class MemoryState(eqx.Module):
    """The memory of every element at one time.

    Every field but `time` has the elements' shape. Make one with `initial_state`; `advance`,
    `apply_stimulus` and `integrate_memory` return new ones.

    Attributes:
        time: () seconds, the time the state refers to.
        stimulus: a_prev, the stimulus held since the last frame (dsigma/sigma).
        sensitivity: kappa, the sensitivity the present load was applied with (1 when rested).
        fast: The fast Prony mode b_fast (dsigma/sigma).
        slow: The slow Prony mode b_slow (dsigma/sigma).
        extreme: a_max, the stimulus of largest magnitude seen so far, with its sign
            (dsigma/sigma).
        fatigue: phi, the fractional loss of sensitivity to new loading (0 when rested).
    """

    time: jax.Array
    stimulus: jax.Array
    sensitivity: jax.Array
    fast: jax.Array
    slow: jax.Array
    extreme: jax.Array
    fatigue: jax.Array


def initial_state(
    shape: int | tuple[int, ...], *, time: ArrayLike = 0.0, preconditioned: ArrayLike = 0.0, dtype=None
) -> MemoryState:
    """A rested skin at `time` with no stimulus: modes and fatigue zero, sensitivity 1.

    Arguments:
        shape: The elements' shape: the shape of every field but `time`.
        time: The time of the state, seconds (kept in the default float precision).
        preconditioned: The largest stimulus the skin has already seen (dsigma/sigma, with its
            sign, broadcasting to `shape`): its first cycle is behind it up to there, so it
            reads the offset mu a_max from the start and a press no deeper shows no further
            first-cycle effect. 0 (the default) is a virgin skin.
        dtype (jax.typing.DTypeLike | None): The dtype of the fields but `time`; default JAX's
            default float.

    Returns:
        The `MemoryState`.
    """
    default = jnp.result_type(float)
    dtype = default if dtype is None else dtype
    zeros = jnp.zeros(shape, dtype)
    extreme = jnp.broadcast_to(jnp.asarray(preconditioned, dtype), zeros.shape)
    # Time stays in the default precision (float64): float32 seconds lose milliseconds after hours.
    return MemoryState(jnp.asarray(time, default), zeros, jnp.ones(shape, dtype), zeros, zeros, extreme, zeros)


def _settle(value: jax.Array, target: jax.Array, decay: jax.Array, growth: jax.Array) -> jax.Array:
    """value e^(-dt/tau) + target (1 - e^(-dt/tau)), given decay = e^(-dt/tau) and growth =
    1 - e^(-dt/tau) (from expm1, accurate for short intervals). Exactly `value` when dt = 0."""
    return value * decay + target * growth


def advance(state: MemoryState, parameters: MemoryParameters, until: ArrayLike) -> MemoryState:
    """The state at a later time, the stimulus held: the exact solution over the interval.

    The modes settle towards (1 - rho) kappa a_prev and the fatigue towards its equilibrium,
    in closed form (exponentials; the model is in the module docstring). Stimulus,
    sensitivity and extreme are unchanged. Not checked: `until` must not precede
    `state.time`.

    Arguments:
        state: The state now.
        parameters: The `MemoryParameters`.
        until: The time to advance to, seconds, >= `state.time`.

    Returns:
        The `MemoryState` at `until`, its fields in the dtypes of `state`.
    """
    p = parameters
    duration = jnp.asarray(until) - state.time
    dtype = state.fast.dtype  # the carry keeps its dtype (float32 stays float32)

    def exponentials(rate: jax.Array) -> tuple[jax.Array, jax.Array]:
        return jnp.exp(-rate * duration).astype(dtype), (-jnp.expm1(-rate * duration)).astype(dtype)

    relaxed = (1 - p.relaxation) * state.sensitivity * state.stimulus
    fast = _settle(state.fast, relaxed, *exponentials(1 / p.fast_time))
    slow = _settle(state.slow, relaxed, *exponentials(1 / p.slow_time))
    drive = p.fatigue_rate * jnp.abs(state.stimulus) * p.fatigue_recovery_time  # x = k |a| tau_phi
    fatigue_target = p.fatigue_limit * drive / (1 + drive)
    fatigue = _settle(state.fatigue, fatigue_target, *exponentials((1 + drive) / p.fatigue_recovery_time))
    return dataclasses.replace(
        state,
        time=jnp.asarray(until, state.time.dtype),
        fast=fast.astype(dtype),
        slow=slow.astype(dtype),
        fatigue=fatigue.astype(dtype),
    )


def apply_stimulus(state: MemoryState, stimulus: ArrayLike) -> MemoryState:
    """The instant reaction to the stimulus of a new frame.

    Deeper loading (|a_k| > |a_prev|) enters at the present sensitivity s = 1 - phi: kappa <-
    s + (kappa - s) w with w = a_prev / a_k (clipped to [0, 1]; kappa a is then the
    sensitivity-weighted load), and every mode takes the increment of kappa a at once.
    Unloading keeps kappa (the load eases proportionally) and moves no mode: the modes follow it
    through `advance`. A stimulus of the other sign loads afresh (w = 0) from zero: the modes take
    s a_k, and the old load leaves them through `advance`. The running extreme a_max follows |a|.

    Arguments:
        state: The state at the frame's time (after `advance`).
        stimulus: a_k, the frame's stimulus (dsigma/sigma, <= 0 under a touch), broadcasting
            to the elements' shape.

    Returns:
        The new `MemoryState` (the same time).
    """
    previous = state.stimulus
    stimulus = jnp.broadcast_to(jnp.asarray(stimulus, previous.dtype), previous.shape)
    reversed_ = stimulus * previous < 0
    loading = (jnp.abs(stimulus) > jnp.abs(previous)) | reversed_
    # Safe denominator: where() differentiates both branches, and 0/0 would poison the gradient;
    # so would the derivative -a_prev / a_k^2, which overflows for the 1e-200 tails of a
    # smooth-edged touch: below _TINY a load enters at the present sensitivity (w = 1).
    divides = loading & (jnp.abs(stimulus) > _TINY)
    weight = jnp.where(divides, jnp.clip(previous / jnp.where(divides, stimulus, 1), 0, 1), 1)
    fresh = 1 - state.fatigue
    # Written as s + (kappa - s) w so that kappa stays exactly 1 on a skin that never fatigues.
    sensitivity = jnp.where(loading, fresh + (state.sensitivity - fresh) * weight, state.sensitivity)
    # A reversed load starts from zero: the old one is not taken out of the modes at once, so the
    # response does not jump where the stimulus crosses zero.
    increment = jnp.where(loading, sensitivity * stimulus - jnp.where(reversed_, 0, state.sensitivity * previous), 0)
    extreme = jnp.where(jnp.abs(stimulus) > jnp.abs(state.extreme), stimulus, state.extreme)
    return dataclasses.replace(
        state,
        stimulus=stimulus,
        sensitivity=sensitivity,
        fast=state.fast + increment,
        slow=state.slow + increment,
        extreme=extreme,
    )


def read_response(state: MemoryState, parameters: MemoryParameters) -> jax.Array:
    """The skin's response r in `state`: g [(1 - F) kappa a + f_fast b_fast + f_slow b_slow] + mu a_max.

    F = f_fast + f_slow. With no memory (F = 0, kappa = 1, mu = 0) it is exactly g a.

    Arguments:
        state: The `MemoryState`.
        parameters: The `MemoryParameters`.

    Returns:
        r, dsigma/sigma, the elements' shape.
    """
    p = parameters
    # Ordered so that with no memory (f = 0, kappa = 1, mu = 0) it is exactly g a, bit for bit.
    network = (1 - (p.fast_fraction + p.slow_fraction)) * (state.sensitivity * state.stimulus)
    network = network + p.fast_fraction * state.fast + p.slow_fraction * state.slow
    return p.gain * network + p.first_cycle_offset * state.extreme


def integrate_memory(
    stimulus: ArrayLike,
    times: ArrayLike,
    parameters: MemoryParameters,
    state: MemoryState | None = None,
) -> tuple[jax.Array, MemoryState]:
    """Responses to `stimulus` (T, ...) at frame `times` (T,) seconds, and the final state.

    Each frame advances the state exactly from the previous frame (`advance`), applies the frame's
    stimulus (`apply_stimulus`) and reads the response (`read_response`), in one `jax.lax.scan`;
    jit, vmap and grad (in the stimulus, the times and every parameter) work. `state` defaults
    to a rested virgin skin at times[0] (`initial_state`); pass a returned state to continue a
    long scene in pieces with identical results.

    Arguments:
        stimulus: (T, ...) a per frame and element, the response of an ideal memoryless skin
            (dsigma/sigma, <= 0 under a touch); integers are converted to floats.
        times: (T,) the frame times, seconds, not decreasing.
        parameters: The `MemoryParameters`.
        state: The state to start from (default: `initial_state` at `times[0]`, in the
            stimulus' dtype).

    Returns:
        ((T, ...) the response r, dsigma/sigma; the `MemoryState` after the last frame).

    Raises:
        ValueError: For `times` not of shape (T,); and, on concrete inputs, for a stimulus or
            times not finite, or times that decrease (or start before `state.time`).
    """
    ensure_float64()
    stimulus = jnp.asarray(stimulus)
    if not jnp.issubdtype(stimulus.dtype, jnp.floating):
        stimulus = stimulus.astype(jnp.result_type(float))
    times = jnp.asarray(times)
    if stimulus.ndim < 1 or times.shape != stimulus.shape[:1]:
        raise ValueError(
            f"times must have shape (T,) for a stimulus of shape (T, ...); got {times.shape} and {stimulus.shape}"
        )
    if state is None:
        state = initial_state(stimulus.shape[1:], time=times[0] if times.shape[0] else 0.0, dtype=stimulus.dtype)
    _check_frames(stimulus, times, state)

    return _integrate(stimulus, times, parameters, state)


@jax.jit  # compiled once per shape and dtype: scenes call this with many parameter values
def _integrate(
    stimulus: jax.Array, times: jax.Array, parameters: MemoryParameters, state: MemoryState
) -> tuple[jax.Array, MemoryState]:
    def frame(state: MemoryState, inputs: tuple[jax.Array, jax.Array]) -> tuple[MemoryState, jax.Array]:
        value, time = inputs
        state = apply_stimulus(advance(state, parameters, time), value)
        return state, read_response(state, parameters)

    state, responses = jax.lax.scan(frame, state, (stimulus, times))
    return responses, state


def memory_response(
    stimulus: ArrayLike, times: ArrayLike, parameters: MemoryParameters, state: MemoryState | None = None
) -> jax.Array:
    """The skin's response to a stimulus: `integrate_memory` without the final state.

    Arguments:
        stimulus: (T, ...) a per frame and element (dsigma/sigma, <= 0 under a touch).
        times: (T,) the frame times, seconds, not decreasing.
        parameters: The `MemoryParameters`.
        state: The state to start from (default: a rested virgin skin at `times[0]`).

    Returns:
        (T, ...) the response r, dsigma/sigma.

    Raises:
        ValueError: As `integrate_memory`.
    """
    return integrate_memory(stimulus, times, parameters, state)[0]


def _check_frames(stimulus: jax.Array, times: jax.Array, state: MemoryState) -> None:
    if is_concrete(stimulus) and not np.all(np.isfinite(np.asarray(stimulus))):
        raise ValueError("stimulus must be finite")
    if is_concrete(times) and is_concrete(state.time) and times.shape[0]:
        steps = np.diff(np.concatenate([np.asarray(state.time, float).reshape(1), np.asarray(times, float)]))
        if not np.all(np.isfinite(steps)):
            raise ValueError("times must be finite (seconds)")
        if np.any(steps < 0):
            first = int(np.flatnonzero(steps < 0)[0])
            where = "times[0] is before state.time" if first == 0 else f"times[{first}] < times[{first - 1}]"
            raise ValueError(f"times must not decrease: {where}")
