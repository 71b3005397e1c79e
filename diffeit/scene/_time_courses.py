"""Time courses: values that change in time, for the parameters of touches and their envelopes.

A time course is a callable t -> value (`Press`, `Ramp`, `Path`), an `equinox.Module` whose
continuous parameters are leaves, composed by placing it where a value goes: a shape parameter
(centre, radius, semi-axes, angle) or a touch's `envelope` may be a time course. Times are in
seconds; values in the unit of the parameter they stand for.

Piecewise linear by default: continuous in t with slope jumps at the breakpoints (jax.grad in t
gives the slope of the segment t lies in, the later one at a breakpoint); `smooth=True` uses the
smoothstep 3s^2 - 2s^3 on every segment: continuously differentiable, with zero slope at every
breakpoint. A segment of zero duration is a step, right-continuous (the new value holds from
the step's time on); its gradient in the step time is zero.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._arrays import concrete_floats, is_concrete

ArrayLike = float | jax.Array | np.ndarray


def as_float(value: Any) -> jax.Array:
    """A value as a JAX array of a floating dtype (integers become the default float).

    Arguments:
        value: A number, array or anything `jnp.asarray` takes.

    Returns:
        The JAX array.
    """
    array = jnp.asarray(value)
    return array if jnp.issubdtype(array.dtype, jnp.floating) else array.astype(jnp.result_type(float))


def float_array(name: str) -> Callable[[Any], Any]:
    """A field converter: lists and tuples become one float array; other values pass unchanged.

    As pytrees, lists and tuples would make every number a leaf of its own, and hide tracers
    inside them from the checks.

    Arguments:
        name: The field's name, for the error message.

    Returns:
        The converter; it raises `ValueError` naming the field for a list or tuple that is not
        numbers.
    """

    def convert(value: Any) -> Any:
        if not isinstance(value, list | tuple):
            return value
        try:
            return jnp.asarray(value, dtype=float)
        except (TypeError, ValueError):
            raise ValueError(f"{name} must be a number or an array of numbers; got {value!r}") from None

    return convert


def check_shape(value: Any, name: str, shape: tuple[int, ...], what: str) -> None:
    """Check the shape of a value.

    Arguments:
        value: The value.
        name: Its name, for the error message.
        shape: The shape it must have.
        what: What it should be, in words ("a number"), for the error message.

    Raises:
        ValueError: Naming `name`, unless `value` has `shape`.
    """
    if np.shape(value) != shape:
        raise ValueError(f"{name} must be {what} (shape {shape}); got shape {np.shape(value)}")


def _ramp(elapsed: jax.Array, duration: jax.Array, smooth: bool) -> jax.Array:
    """Progress in [0, 1] of a segment `elapsed` seconds after its start: 0 before, 1 after,
    linear (or smoothstep) in between; a step (1 from elapsed = 0 on) when duration is 0."""
    positive = duration > 0
    # Safe denominator: where() differentiates both branches, and x / 0 would poison the gradient.
    s = jnp.clip(elapsed / jnp.where(positive, duration, 1.0), 0.0, 1.0)
    if smooth:
        s = s * s * (3 - 2 * s)
    return jnp.where(positive, s, (elapsed >= 0).astype(s.dtype))


def _interpolate(start: jax.Array, end: jax.Array, s: jax.Array, value_ndim: int) -> jax.Array:
    """start + (end - start) s, with s (t's shape) broadcast over the value's `value_ndim`
    trailing axes; exactly `start` at s = 0 and exactly `end` at s = 1."""
    s = jnp.reshape(s, s.shape + (1,) * value_ndim)
    return (1 - s) * start + s * end


class AbstractTimeCourse(eqx.Module):
    """A value that changes in time: `course(t)` for t in seconds.

    Its continuous parameters are leaves: jit, grad (in t and in the parameters) and vmap
    work. `Press`, `Ramp` and `Path` are the courses.
    """

    def __call__(self, t: ArrayLike) -> jax.Array:
        """The value at a time.

        Arguments:
            t: Seconds, a scalar or an array (element-wise).

        Returns:
            The value, of shape t.shape + the value's shape, in the unit of the parameter the
            course stands for.
        """
        return _evaluate(self, as_float(t))

    @abc.abstractmethod
    def _value(self, t: jax.Array) -> jax.Array:
        """The value at time `t` (seconds, a float array)."""

    @abc.abstractmethod
    def breakpoint_values(self) -> np.ndarray | None:
        """The values at the breakpoints, in time order.

        Between consecutive breakpoints the value moves monotonically along the straight
        segment joining them, so these bound the course and trace its path (validation uses
        them).

        Returns:
            (K, ...) the values, or None when they are traced.
        """


class Press(AbstractTimeCourse):
    """A press envelope in [0, 1]: 0, a ramp up to 1, a hold at 1, a ramp down, 0.

    Multiplies a touch's amplitude. Key times: 0 at `start` (1 if ramp_in = 0), 1 from
    start + ramp_in to start + ramp_in + hold, 0 from start + ramp_in + hold + ramp_out on (a
    step release: 0 at the release time itself). A duration of 0 is a step (the skin's instant
    rise and drop).

    Attributes:
        start: When the ramp in starts, seconds (default 0).
        ramp_in: Its duration, seconds, >= 0 (default 0).
        hold: How long it holds 1, seconds, >= 0 (default 1).
        ramp_out: The duration of the ramp out, seconds, >= 0 (default 0).
        smooth: Smoothstep ramps (static; the module docstring gives the derivatives).

    Raises:
        ValueError: Naming the field, for a value that is not one finite number, or a
            negative duration.
    """

    start: ArrayLike = eqx.field(default=0.0, converter=float_array("Press.start"))
    ramp_in: ArrayLike = eqx.field(default=0.0, converter=float_array("Press.ramp_in"))
    hold: ArrayLike = eqx.field(default=1.0, converter=float_array("Press.hold"))
    ramp_out: ArrayLike = eqx.field(default=0.0, converter=float_array("Press.ramp_out"))
    smooth: bool = eqx.field(default=False, static=True)

    def __check_init__(self) -> None:
        for name in ("start", "ramp_in", "hold", "ramp_out"):
            value = concrete_floats(getattr(self, name), f"Press.{name}")
            if value is None:
                continue
            check_shape(value, f"Press.{name}", (), "a number")
            if name != "start" and value < 0:
                raise ValueError(f"Press.{name} is a duration: it must be >= 0 (seconds); got {value}")

    def _value(self, t: jax.Array) -> jax.Array:
        t = as_float(t)
        rise = _ramp(t - self.start, as_float(self.ramp_in), self.smooth)
        release = self.start + self.ramp_in + self.hold
        fall = _ramp(t - release, as_float(self.ramp_out), self.smooth)
        return rise * (1 - fall)

    @property
    def end(self) -> ArrayLike:
        """The time (seconds) from which the envelope is 0 again."""
        return self.start + self.ramp_in + self.hold + self.ramp_out

    def breakpoint_values(self) -> np.ndarray:
        """The values at the breakpoints: 0, 1, 1, 0.

        Returns:
            (4,) the values.
        """
        return np.array([0.0, 1.0, 1.0, 0.0])


class Ramp(AbstractTimeCourse):
    """A ramp from one value to another: `initial` until `start`, then to `final` over `duration`.

    Linear (or smoothstep), `final` after: a growing contact (radius from r0 to r1, metres), a
    rising load (an envelope from 0 to 1), a straight move of a centre (two points). A duration
    of 0 is a step to `final` at `start`.

    Attributes:
        initial: The value before `start`, a number or an array, in the parameter's unit.
        final: The value from start + duration on, the shape of `initial`.
        start: When the ramp starts, seconds (default 0).
        duration: Seconds, >= 0 (default 1).
        smooth: A smoothstep ramp rather than a linear one (static).

    Raises:
        ValueError: Naming the field, for values that are not finite numbers, `initial` and
            `final` of different shapes, a start or duration that is not one number, or a
            negative duration.
    """

    initial: ArrayLike = eqx.field(converter=float_array("Ramp.initial"))
    final: ArrayLike = eqx.field(converter=float_array("Ramp.final"))
    start: ArrayLike = eqx.field(default=0.0, converter=float_array("Ramp.start"))
    duration: ArrayLike = eqx.field(default=1.0, converter=float_array("Ramp.duration"))
    smooth: bool = eqx.field(default=False, static=True)

    def __check_init__(self) -> None:
        initial = concrete_floats(self.initial, "Ramp.initial")
        final = concrete_floats(self.final, "Ramp.final")
        if initial is not None and final is not None and initial.shape != final.shape:
            raise ValueError(f"Ramp.initial and Ramp.final must have one shape; got {initial.shape} and {final.shape}")
        start = concrete_floats(self.start, "Ramp.start")
        if start is not None:
            check_shape(start, "Ramp.start", (), "a number")
        duration = concrete_floats(self.duration, "Ramp.duration")
        if duration is not None:
            check_shape(duration, "Ramp.duration", (), "a number")
            if duration < 0:
                raise ValueError(f"Ramp.duration must be >= 0 (seconds); got {duration}")

    def _value(self, t: jax.Array) -> jax.Array:
        s = _ramp(as_float(t) - self.start, as_float(self.duration), self.smooth)
        initial = as_float(self.initial)
        return _interpolate(initial, as_float(self.final), s, initial.ndim)

    def breakpoint_values(self) -> np.ndarray | None:
        """The values at the breakpoints: `initial`, `final`.

        Returns:
            (2, ...) the values, or None when either is traced.
        """
        if not (is_concrete(self.initial) and is_concrete(self.final)):
            return None
        return np.stack([np.asarray(self.initial, dtype=float), np.asarray(self.final, dtype=float)])


class Path(AbstractTimeCourse):
    """Waypoints reached at given times: linear (or smoothstep) in between.

    Held at the first value before times[0] and at the last after times[-1]; exactly
    values[k] at times[k]. A sliding finger is `Disc(centre=Path(times, points), ...)` with
    points (K, 2) in metres.

    Attributes:
        times: (K,) seconds, strictly increasing, K >= 2.
        values: (K, ...) the waypoints, in the parameter's unit.
        smooth: Smoothstep segments: the mover stops at every waypoint (static).

    Raises:
        ValueError: Naming the field, for values that are not finite numbers, times that are
            not 1D, fewer than 2 or not strictly increasing, or values not one per time.
    """

    times: ArrayLike = eqx.field(converter=float_array("Path.times"))
    values: ArrayLike = eqx.field(converter=float_array("Path.values"))
    smooth: bool = eqx.field(default=False, static=True)

    def __check_init__(self) -> None:
        times = concrete_floats(self.times, "Path.times")
        values = concrete_floats(self.values, "Path.values")
        if times is not None:
            if times.ndim != 1 or len(times) < 2:
                raise ValueError(
                    f"Path.times must be a 1D array of at least 2 waypoint times; got shape {times.shape} "
                    "(use a plain value for a fixed one)"
                )
            if np.any(np.diff(times) <= 0):
                first = int(np.flatnonzero(np.diff(times) <= 0)[0]) + 1
                raise ValueError(
                    f"Path.times must be strictly increasing (seconds); times[{first}] = {times[first]} "
                    f"<= times[{first - 1}] = {times[first - 1]}"
                )
        if times is not None and values is not None and (values.ndim < 1 or len(values) != len(times)):
            raise ValueError(
                f"Path.values must have one waypoint per time: shape ({len(times)}, ...); got {values.shape}"
            )

    def _value(self, t: jax.Array) -> jax.Array:
        t = as_float(t)
        times, values = as_float(self.times), as_float(self.values)
        # The segment [times[k], times[k+1]) holding t: waypoints are few, so comparing with all
        # inner times is cheaper than a binary search (and right-continuous at every waypoint).
        segment = jnp.sum(t[..., None] >= times[1:-1], axis=-1)
        s = _ramp(t - times[segment], times[segment + 1] - times[segment], self.smooth)
        return _interpolate(values[segment], values[segment + 1], s, values.ndim - 1)

    def breakpoint_values(self) -> np.ndarray | None:
        """The waypoints.

        Returns:
            (K, ...) the values, or None when they are traced.
        """
        return np.asarray(self.values, dtype=float) if is_concrete(self.values) else None


@jax.jit  # eager evaluation would compile each of a course's few dozen operations on its own
def _evaluate(course: AbstractTimeCourse, t: jax.Array) -> jax.Array:
    return course._value(t)


def value_at(value: Any, t: jax.Array) -> jax.Array:
    """A parameter at a time: the course's value, or the plain value.

    Arguments:
        value: A plain value or an `AbstractTimeCourse`.
        t: The time, seconds.

    Returns:
        The value at `t`, as a float array.
    """
    return value(t) if isinstance(value, AbstractTimeCourse) else as_float(value)


def reach(value: Any, name: str) -> np.ndarray | None:
    """The values a parameter takes at its breakpoints, for validation.

    Arguments:
        value: A plain value or an `AbstractTimeCourse`.
        name: Its name, for the error message.

    Returns:
        (K, ...) the values (one row for a plain value), or None when traced.

    Raises:
        ValueError: Naming `name`, for values that are not numbers or not finite.
    """
    values = value.breakpoint_values() if isinstance(value, AbstractTimeCourse) else value
    array = concrete_floats(values, name) if values is not None else None
    if array is None:
        return None
    return array if isinstance(value, AbstractTimeCourse) else array[None]
