"""Touches on the skin: footprints with smooth edges, time courses, and the stimulus of a scene.

A touch lowers the sheet conductivity under its footprint (strain breaks percolation paths in
the graphite-latex sheet). Its stimulus is the relative conductivity change dsigma/sigma
(dimensionless) that an ideal, memoryless skin would show, per element and frame:

    field_e(t) = amplitude(t) x fraction_e(shape at t),

with `fraction_e` in [0, 1] the part of element e under the footprint. Lengths are in metres,
times in seconds, angles in radians (counter-clockwise from the x axis).

## Smooth edges
An exact area fraction is piecewise constant in the touch's position and size wherever no
element corner crosses the boundary, and jumps elsewhere: useless for gradients. Here each
sample point x of an element counts with the weight

    weight(x) = P(N(0, edge_width^2) > d(x)) = erfc(d(x) / (sqrt(2) edge_width)) / 2,

d(x) the signed distance to the footprint's boundary (negative inside): the indicator of the
footprint blurred by a Gaussian of standard deviation `edge_width` across its edge (exact for a
straight edge). The fraction of an element is the mean weight over the level^2 barycentric
sample points of `diffeit.mesh.disc_fraction` (the centroids of level^2 congruent
sub-triangles), so as edge_width -> 0 it becomes disc_fraction's area fraction, error O(1/level)
of an element the edge cuts. An erf edge rather than a logistic one: its tails fall like
exp(-d^2 / 2 edge_width^2), so the field is 0 to rounding a few widths outside the touch (and
1 inside), where a logistic edge would leak exp(-d / edge_width) over the whole skin.
Blurring keeps the boundary (weight 1/2 on it) and, for a disc, the integral of the weight over
the plane is pi (r^2 + edge_width^2): the area is biased by (edge_width / r)^2 relative, and
its derivative in r is exactly 2 pi r.

Default edge width (`default_edge_width`): twice the spacing of the sample points in the
largest element, 2 sqrt(max area) / level, one width for the whole mesh (about 0.02 m on a unit
disc meshed at h = 0.1, 0.01 m at h = 0.05, with level 8). The samples then resolve the edge:
over ten discs well inside unit discs meshed at h = 0.15, 0.1 and 0.05, the derivative of the
covered area in the radius is 2 pi r within 9e-4 and in the centre 0 within 4e-4 of 2 pi r.
Narrower defaults did worse: one sample spacing up to 2e-3, and the local spacing of each
element up to 2e-2 (a blur whose width jumps between elements is no longer a normalised
kernel). A finer mesh (or a higher level) gives a sharper default, converging to the exact area
fraction. Pass `edge_width` (metres) for a physical edge that does not depend on the mesh; keep
it well below the radius (the area bias is (edge_width / r)^2: small touches need a fine mesh
or a narrow edge) and above the sample spacing (narrower edges make the gradients jumpy).

## Time courses
Callables t -> value (`Press`, `Ramp`, `Path`), JAX pytrees, composed by placing them where a
value goes: a shape parameter (centre, radius, semi-axes, angle) or a touch's `envelope` may be
a time course. Piecewise linear by default: continuous in t with slope jumps at the breakpoints
(jax.grad in t gives the slope of the segment t lies in, the later one at a breakpoint);
`smooth=True` uses the smoothstep 3s^2 - 2s^3 on every segment: continuously differentiable,
with zero slope at every breakpoint. A segment of zero duration is a step, right-continuous
(the new value holds from the step's time on); its gradient in the step time is zero.

## Several touches
Overlapping touches add their strains, and R = R0 (1 + GF strain) makes their relative
resistance changes add: with rho_i = -a_i / (1 + a_i) the resistance change of stimulus a_i,
the combined stimulus is a = -rho / (1 + rho), rho = sum_i rho_i. Pairwise,
a (+) b = (a + b + 2 a b) / (1 - a b): exactly a where b = 0 (a touch whose field is 0 there,
unpressed or of amplitude 0, changes nothing, bit for bit), a + b to first order (touches apart
sum to rounding), and always above -1 for touches lowering the conductivity (two touches of -0.7
on one spot give -0.82, not -1.4). Conductivity increases (a > 0) combine
by the same rule; `stimulus` refuses those whose resistance drops could together reach 100%.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import erfc

from .._arrays import concrete_floats, is_concrete
from .._pytree import register_dataclass
from ..mesh import Mesh, element_sample_points

ArrayLike = float | jax.Array | np.ndarray

# Sample points held in memory at once by `stimulus` (frames x elements x samples): frames are
# mapped in batches of this size, so long scenes on fine meshes stay within a few hundred MB.
_SAMPLES_PER_BATCH = 1 << 22
# Points per segment of a moving centre checked to lie on the skin (between breakpoints).
_CHECKS_PER_SEGMENT = 16
# A point is on the skin when its barycentric coordinates in some triangle are all above this.
_INSIDE_TOLERANCE = -1e-9


def _sequences_to_arrays(obj, names: tuple[str, ...]) -> None:
    """Replace list and tuple values of the fields `names` by arrays: as pytrees they would make
    every number a leaf of its own (and hide tracers inside them from the checks)."""
    for name in names:
        value = getattr(obj, name)
        if isinstance(value, list | tuple):
            try:
                object.__setattr__(obj, name, jnp.asarray(value, dtype=float))
            except (TypeError, ValueError):
                raise ValueError(
                    f"{type(obj).__name__}.{name} must be a number or an array of numbers; got {value!r}"
                ) from None


def _shape_of(value, name: str, shape: tuple[int, ...], what: str) -> None:
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


def _float(value) -> jax.Array:
    array = jnp.asarray(value)
    return array if jnp.issubdtype(array.dtype, jnp.floating) else array.astype(jnp.result_type(float))


# --- Time courses ---------------------------------------------------------------------------


class AbstractTimeCourse(abc.ABC):
    """A value that changes in time: `course(t)` for t in seconds (a scalar, or an array:
    element-wise, the result of shape t.shape + value shape). A JAX pytree whose continuous
    parameters are leaves: jit, grad (in t and in the parameters) and vmap work."""

    def __call__(self, t: ArrayLike) -> jax.Array:
        """The value at time `t` (seconds)."""
        return _evaluate(self, _float(t))

    @abc.abstractmethod
    def _value(self, t: jax.Array) -> jax.Array:
        """The value at time `t` (seconds, a float array)."""

    @abc.abstractmethod
    def breakpoint_values(self) -> np.ndarray | None:
        """(K, ...) the values at the breakpoints, in time order (None when traced). Between
        consecutive breakpoints the value moves monotonically along the straight segment joining
        them, so these bound the course and trace its path (validation uses them)."""


@dataclass(frozen=True, eq=False)
class Press(AbstractTimeCourse):
    """A press envelope in [0, 1]: 0 until `start`, up to 1 over `ramp_in`, held 1 for `hold`,
    down to 0 over `ramp_out`, 0 after (seconds). Multiplies a touch's amplitude.

    Key times: 0 at `start` (1 if ramp_in = 0), 1 from start + ramp_in to start + ramp_in + hold,
    0 from start + ramp_in + hold + ramp_out on (a step release: 0 at the release time itself).
    Durations >= 0; a duration of 0 is a step (the skin's instant rise and drop). `smooth` (static)
    selects smoothstep ramps (see the module docstring for the derivatives).
    """

    start: ArrayLike = 0.0
    ramp_in: ArrayLike = 0.0
    hold: ArrayLike = 1.0
    ramp_out: ArrayLike = 0.0
    smooth: bool = False

    def __post_init__(self) -> None:
        _sequences_to_arrays(self, ("start", "ramp_in", "hold", "ramp_out"))
        for name in ("start", "ramp_in", "hold", "ramp_out"):
            value = concrete_floats(getattr(self, name), f"Press.{name}")
            if value is None:
                continue
            _shape_of(value, f"Press.{name}", (), "a number")
            if name != "start" and value < 0:
                raise ValueError(f"Press.{name} is a duration: it must be >= 0 (seconds); got {value}")

    def _value(self, t: jax.Array) -> jax.Array:
        t = _float(t)
        rise = _ramp(t - self.start, _float(self.ramp_in), self.smooth)
        release = self.start + self.ramp_in + self.hold
        fall = _ramp(t - release, _float(self.ramp_out), self.smooth)
        return rise * (1 - fall)

    @property
    def end(self) -> ArrayLike:
        """The time (seconds) from which the envelope is 0 again."""
        return self.start + self.ramp_in + self.hold + self.ramp_out

    def breakpoint_values(self) -> np.ndarray:
        return np.array([0.0, 1.0, 1.0, 0.0])


@dataclass(frozen=True, eq=False)
class Ramp(AbstractTimeCourse):
    """`initial` until `start`, then linearly (or by smoothstep, `smooth`, static) to `final` over
    `duration` seconds, `final` after: a growing contact (radius from r0 to r1, metres), a rising
    load (an envelope from 0 to 1), a straight move of a centre (two points). Values are numbers
    or arrays of one shape; duration >= 0 (0 is a step to `final` at `start`)."""

    initial: ArrayLike
    final: ArrayLike
    start: ArrayLike = 0.0
    duration: ArrayLike = 1.0
    smooth: bool = False

    def __post_init__(self) -> None:
        _sequences_to_arrays(self, ("initial", "final", "start", "duration"))
        initial = concrete_floats(self.initial, "Ramp.initial")
        final = concrete_floats(self.final, "Ramp.final")
        if initial is not None and final is not None and initial.shape != final.shape:
            raise ValueError(f"Ramp.initial and Ramp.final must have one shape; got {initial.shape} and {final.shape}")
        start = concrete_floats(self.start, "Ramp.start")
        if start is not None:
            _shape_of(start, "Ramp.start", (), "a number")
        duration = concrete_floats(self.duration, "Ramp.duration")
        if duration is not None:
            _shape_of(duration, "Ramp.duration", (), "a number")
            if duration < 0:
                raise ValueError(f"Ramp.duration must be >= 0 (seconds); got {duration}")

    def _value(self, t: jax.Array) -> jax.Array:
        s = _ramp(_float(t) - self.start, _float(self.duration), self.smooth)
        initial = _float(self.initial)
        return _interpolate(initial, _float(self.final), s, initial.ndim)

    def breakpoint_values(self) -> np.ndarray | None:
        if not (is_concrete(self.initial) and is_concrete(self.final)):
            return None
        return np.stack([np.asarray(self.initial, dtype=float), np.asarray(self.final, dtype=float)])


@dataclass(frozen=True, eq=False)
class Path(AbstractTimeCourse):
    """Waypoints `values` (K, ...) reached at `times` (K,) seconds, strictly increasing, K >= 2;
    linear (or smoothstep, `smooth`, static: the mover stops at every waypoint) in between,
    held at the first value before times[0] and at the last after times[-1]. A sliding finger is
    `Disc(centre=Path(times, points), ...)` with points (K, 2) in metres. Exactly values[k] at
    times[k]."""

    times: ArrayLike
    values: ArrayLike
    smooth: bool = False

    def __post_init__(self) -> None:
        _sequences_to_arrays(self, ("times", "values"))
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
        t = _float(t)
        times, values = _float(self.times), _float(self.values)
        # The segment [times[k], times[k+1]) holding t: waypoints are few, so comparing with all
        # inner times is cheaper than a binary search (and right-continuous at every waypoint).
        segment = jnp.sum(t[..., None] >= times[1:-1], axis=-1)
        s = _ramp(t - times[segment], times[segment + 1] - times[segment], self.smooth)
        return _interpolate(values[segment], values[segment + 1], s, values.ndim - 1)

    def breakpoint_values(self) -> np.ndarray | None:
        return np.asarray(self.values, dtype=float) if is_concrete(self.values) else None


@jax.jit  # eager evaluation would compile each of a course's few dozen operations on its own
def _evaluate(course: AbstractTimeCourse, t: jax.Array) -> jax.Array:
    return course._value(t)


def _at(value, t: jax.Array) -> jax.Array:
    """A parameter at time t: the course's value, or the plain value."""
    return value(t) if isinstance(value, AbstractTimeCourse) else _float(value)


def _reach(value, name: str) -> np.ndarray | None:
    """(K, ...) the values a parameter takes at its breakpoints (one row for a plain value),
    None when traced; ValueError naming `name` when not finite."""
    values = value.breakpoint_values() if isinstance(value, AbstractTimeCourse) else value
    array = concrete_floats(values, name) if values is not None else None
    if array is None:
        return None
    return array if isinstance(value, AbstractTimeCourse) else array[None]


# --- Footprints -----------------------------------------------------------------------------


class AbstractShape(abc.ABC):
    """A touch footprint. Its parameters are numbers or time courses (metres, radians)."""

    centre: ArrayLike | AbstractTimeCourse

    @abc.abstractmethod
    def signed_distance(self, points: jax.Array, t: ArrayLike = 0.0) -> jax.Array:
        """(...) the distance (metres) of `points` (..., 2) to the footprint's boundary at time
        `t` (seconds): negative inside, 0 on the boundary, with unit gradient at the boundary."""


def _check_centre(centre, name: str) -> None:
    reach = _reach(centre, name)
    if reach is not None and reach.shape[1:] != (2,):
        raise ValueError(f"{name} must be a point (x, y) in metres, shape (2,); got values of shape {reach.shape[1:]}")


def _safe_norm(v: jax.Array) -> jax.Array:
    """|v| over the last axis, with a zero (not NaN) gradient at v = 0."""
    squared = jnp.sum(v * v, axis=-1)
    positive = squared > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, squared, 1.0)), 0.0)


@dataclass(frozen=True, eq=False)
class Disc(AbstractShape):
    """A round footprint: `centre` (2,) and `radius` (> 0), metres; either may be a time
    course (`Path` for a slide, `Ramp` for a growing contact)."""

    centre: ArrayLike | AbstractTimeCourse
    radius: ArrayLike | AbstractTimeCourse

    def __post_init__(self) -> None:
        _sequences_to_arrays(self, ("centre", "radius"))
        _check_centre(self.centre, "Disc.centre")
        radius = _reach(self.radius, "Disc.radius")
        if radius is not None:
            if radius.shape[1:] != ():
                raise ValueError(f"Disc.radius must be a number (metres); got values of shape {radius.shape[1:]}")
            if np.any(radius <= 0):
                raise ValueError(f"Disc.radius must be positive (metres); got {radius.min()}")

    def signed_distance(self, points: jax.Array, t: ArrayLike = 0.0) -> jax.Array:
        t = _float(t)
        return _safe_norm(points - _at(self.centre, t)) - _at(self.radius, t)


@dataclass(frozen=True, eq=False)
class Ellipse(AbstractShape):
    """An elliptic footprint: `centre` (2,) and `semi_axes` (2,) (> 0) in metres, the first
    semi-axis turned `angle` radians counter-clockwise from the x axis; each may be a time course.

    The signed distance is the first-order estimate d = k0 (k0 - 1) / k1, k0 = |q / (a, b)|,
    k1 = |q / (a^2, b^2)|, q the point in the ellipse's axes: exact on the boundary with unit
    gradient there (so `edge_width` is a width across the edge, in metres), exact for a circle,
    an estimate away from the boundary (where the edge weight is 0 or 1 anyway)."""

    centre: ArrayLike | AbstractTimeCourse
    semi_axes: ArrayLike | AbstractTimeCourse
    angle: ArrayLike | AbstractTimeCourse = 0.0

    def __post_init__(self) -> None:
        _sequences_to_arrays(self, ("centre", "semi_axes", "angle"))
        _check_centre(self.centre, "Ellipse.centre")
        axes = _reach(self.semi_axes, "Ellipse.semi_axes")
        if axes is not None:
            if axes.shape[1:] != (2,):
                raise ValueError(
                    f"Ellipse.semi_axes must be two lengths (a, b) in metres, shape (2,); got shape {axes.shape[1:]}"
                )
            if np.any(axes <= 0):
                raise ValueError(f"Ellipse.semi_axes must be positive (metres); got {axes.min()}")
        angle = _reach(self.angle, "Ellipse.angle")
        if angle is not None and angle.shape[1:] != ():
            raise ValueError(f"Ellipse.angle must be a number (radians); got values of shape {angle.shape[1:]}")

    def signed_distance(self, points: jax.Array, t: ArrayLike = 0.0) -> jax.Array:
        t = _float(t)
        axes, angle = _at(self.semi_axes, t), _at(self.angle, t)
        offset = points - _at(self.centre, t)
        cos, sin = jnp.cos(angle), jnp.sin(angle)
        q = jnp.stack([cos * offset[..., 0] + sin * offset[..., 1], cos * offset[..., 1] - sin * offset[..., 0]], -1)
        k0 = _safe_norm(q / axes)
        k1 = _safe_norm(q / axes**2)
        positive = k1 > 0
        # At the centre itself the estimate has no limit; any value well inside does.
        return jnp.where(positive, k0 * (k0 - 1) / jnp.where(positive, k1, 1.0), -jnp.min(axes))


@dataclass(frozen=True, eq=False)
class Polygon(AbstractShape):
    """A polygonal footprint or region: `vertices` (K, 2) in metres, K >= 3, a simple polygon in
    either orientation (the region of a non-uniform background, a half of the skin). The signed
    distance is exact: the distance to the nearest edge, negative inside (even-odd rule). Its
    `centre` is the mean of the vertices."""

    vertices: ArrayLike

    def __post_init__(self) -> None:
        _sequences_to_arrays(self, ("vertices",))
        vertices = concrete_floats(self.vertices, "Polygon.vertices")
        if vertices is not None:
            if vertices.ndim != 2 or vertices.shape[1] != 2 or len(vertices) < 3:
                raise ValueError(
                    f"Polygon.vertices must be (K, 2) points in metres, K >= 3; got shape {vertices.shape}"
                )
            edges = np.roll(vertices, -1, axis=0) - vertices
            if np.any(np.hypot(edges[:, 0], edges[:, 1]) == 0):
                raise ValueError("Polygon.vertices must not repeat a vertex: an edge has zero length")

    @property
    def centre(self) -> jax.Array:
        return jnp.mean(_float(self.vertices), axis=0)

    def signed_distance(self, points: jax.Array, t: ArrayLike = 0.0) -> jax.Array:
        start = _float(self.vertices)
        stop = jnp.roll(start, -1, axis=0)
        edge = stop - start
        offset = points[..., None, :] - start  # (..., K, 2)
        along = jnp.clip(jnp.sum(offset * edge, -1) / jnp.sum(edge * edge, -1), 0.0, 1.0)
        distance = jnp.min(_safe_norm(offset - along[..., None] * edge), axis=-1)
        x, y = points[..., 0:1], points[..., 1:2]
        straddles = (start[:, 1] > y) != (stop[:, 1] > y)
        rise = jnp.where(straddles, edge[:, 1], 1.0)
        crossing = start[:, 0] + (y - start[:, 1]) * edge[:, 0] / rise
        inside = jnp.sum(straddles & (x < crossing), axis=-1) % 2 == 1
        return jnp.where(inside, -distance, distance)


# --- Touches --------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Touch:
    """One touch: a footprint, an amplitude and its time course.

    - `shape`: the footprint (`Disc` or `Ellipse`; its parameters may move in time).
    - `amplitude`: the relative conductivity change dsigma/sigma under the footprint at full
      press (dimensionless, > -1: negative for a touch, about -0.2 at 2% strain to -0.7 at 25%).
    - `envelope`: a time course in [0, 1] multiplying the amplitude (`Press`, or a `Ramp`/`Path`
      of such values); None: pressed all the time.
    - `edge_width`: the standard deviation (metres, > 0) of the footprint's Gaussian-blurred edge;
      None: `default_edge_width` of the mesh (module docstring).

    A JAX pytree: amplitude, edge width and every continuous parameter of the shape and courses
    are leaves (jit, grad, vmap); the kinds of shape and course and their `smooth` flags are
    structure. Concrete values are checked on construction, the position on the skin by
    `check_touches` (called by `touch_field` and `stimulus`): `ValueError` names the field.
    """

    shape: AbstractShape
    amplitude: ArrayLike
    envelope: AbstractTimeCourse | None = None
    edge_width: ArrayLike | None = None

    def __post_init__(self) -> None:
        _sequences_to_arrays(self, ("amplitude", "edge_width"))
        if not isinstance(self.shape, AbstractShape):
            raise ValueError(f"Touch.shape must be a Disc or an Ellipse; got {self.shape!r}")
        amplitude = concrete_floats(self.amplitude, "Touch.amplitude")
        if amplitude is not None:
            _shape_of(amplitude, "Touch.amplitude", (), "a number")
            if amplitude <= -1:
                raise ValueError(
                    f"Touch.amplitude (dsigma/sigma) must be > -1: at -1 the conductivity vanishes; got {amplitude}"
                )
        if self.envelope is not None:
            if not isinstance(self.envelope, AbstractTimeCourse):
                raise ValueError(
                    f"Touch.envelope must be a time course (Press, Ramp, Path) or None; got {self.envelope!r}"
                )
            reach = _reach(self.envelope, "Touch.envelope")
            if reach is not None and (reach.shape[1:] != () or np.any((reach < 0) | (reach > 1))):
                raise ValueError(f"Touch.envelope must take numbers in [0, 1]; got breakpoint values {reach}")
        if self.edge_width is not None:
            width = concrete_floats(self.edge_width, "Touch.edge_width")
            if width is not None and (width.shape != () or width <= 0):
                raise ValueError(f"Touch.edge_width must be a positive number (metres) or None; got {width}")

    def amplitude_at(self, t: ArrayLike) -> jax.Array:
        """dsigma/sigma at full coverage at time `t` (seconds): amplitude x envelope(t)."""
        amplitude = _float(self.amplitude)
        return amplitude if self.envelope is None else amplitude * self.envelope(t)


for _cls in (Press, Ramp, Path):
    register_dataclass(_cls, static=("smooth",))
for _cls in (Disc, Ellipse, Polygon, Touch):
    register_dataclass(_cls)


# --- Fields on a mesh -----------------------------------------------------------------------


def default_edge_width(mesh: Mesh, level: int = 8) -> float:
    """The default edge width of `mesh`, metres: 2 sqrt(max element area) / level, twice the
    spacing of the sample points in the largest element (module docstring)."""
    _check_level(level)
    return 2.0 * math.sqrt(float(np.max(mesh.element_areas))) / level


def _check_level(level: int) -> None:
    if not isinstance(level, int | np.integer) or isinstance(level, bool) or level < 1:
        raise ValueError(f"level must be a positive integer (level^2 samples per element); got {level!r}")


def _fraction(points: np.ndarray, default_width: float, shape: AbstractShape, width, t: jax.Array) -> jax.Array:
    width = default_width if width is None else width
    distance = shape.signed_distance(points, t)
    return jnp.mean(0.5 * erfc(distance / (math.sqrt(2) * width)), axis=1)


def shape_fraction(
    mesh: Mesh, shape: AbstractShape, t: ArrayLike = 0.0, *, edge_width: ArrayLike | None = None, level: int = 8
) -> jax.Array:
    """(E,) the fraction in [0, 1] of each element under `shape` at time `t` (seconds), with a
    Gaussian-blurred edge of standard deviation `edge_width` (metres; default
    `default_edge_width`), averaged over level^2 sample points per element (module docstring).
    Pure JAX in the shape's parameters and t: jit, grad and vmap work."""
    _check_level(level)
    if not isinstance(shape, AbstractShape):
        raise ValueError(f"shape must be a Disc or an Ellipse; got {shape!r}")
    return _shape_fraction(mesh, shape, _float(t), edge_width, level)


@partial(jax.jit, static_argnames=("mesh", "level"))
def _shape_fraction(mesh: Mesh, shape: AbstractShape, t: jax.Array, edge_width, level: int) -> jax.Array:
    return _fraction(element_sample_points(mesh, level), default_edge_width(mesh, level), shape, edge_width, t)


def touch_field(mesh: Mesh, touch: Touch, t: ArrayLike, *, level: int = 8) -> jax.Array:
    """(E,) the relative conductivity change dsigma/sigma (dimensionless) of one touch at time
    `t` (seconds): amplitude(t) x the fraction of each element under its footprint at t.
    Exactly 0 where the amplitude is 0. Checks concrete touches with `check_touches`."""
    _check_level(level)
    check_touches(mesh, [touch])
    return _jitted_touch_field(mesh, touch, _float(t), level)


@partial(jax.jit, static_argnames=("mesh", "level"))
def _jitted_touch_field(mesh: Mesh, touch: Touch, t: jax.Array, level: int) -> jax.Array:
    return _touch_field(element_sample_points(mesh, level), default_edge_width(mesh, level), touch, t)


def _touch_field(points: np.ndarray, default_width: float, touch: Touch, t: jax.Array) -> jax.Array:
    return touch.amplitude_at(t) * _fraction(points, default_width, touch.shape, touch.edge_width, t)


def combine_changes(first: ArrayLike, second: ArrayLike) -> jax.Array:
    """Two relative conductivity changes (dsigma/sigma, each > -1) of overlapping touches, combined
    by adding their relative resistance changes (strains add; module docstring):
    (a + b + 2 a b) / (1 - a b). Exactly `first` where `second` is 0 and vice versa; symmetric and
    associative; above -1 whenever 1 - a b > 0 (always when neither is positive)."""
    a, b = _float(first), _float(second)
    product = a * b
    return (a + b + 2 * product) / (1 - product)


def stimulus(mesh: Mesh, touches: Sequence[Touch], times: ArrayLike, *, level: int = 8) -> jax.Array:
    """(T, E) the relative conductivity change dsigma/sigma (dimensionless) per frame and element
    of several touches at frame `times` (T,) seconds: each touch's `touch_field`, overlaps
    combined by `combine_changes` in order (zeros without touches).

    Pure JAX in the touches' parameters and the times (jit, grad and vmap work); frames are mapped
    in batches (`jax.lax.map` with `batch_size`, vmap within a batch) so memory stays bounded on
    long scenes. Checks concrete inputs: `check_touches`, finite 1D times, and conductivity
    increases whose resistance drops sum to 100% or more (sum of a / (1 + a) over positive
    amplitudes >= 1) are refused, since where they overlap the conductivity would not be positive.
    """
    _check_level(level)
    touches = tuple(touches)
    check_touches(mesh, touches)
    times = _float(times)
    if times.ndim != 1:
        raise ValueError(f"times must be a 1D array of frame times (seconds); got shape {times.shape}")
    if is_concrete(times) and not np.all(np.isfinite(np.asarray(times))):
        raise ValueError("times must be finite (seconds)")
    _check_increases(touches)
    batch = max(1, min(times.shape[0], _SAMPLES_PER_BATCH // (mesh.n_elements * level**2)))
    return _stimulus(mesh, touches, times, level, batch)


@partial(jax.jit, static_argnames=("mesh", "level", "batch"))
def _stimulus(mesh: Mesh, touches: tuple[Touch, ...], times: jax.Array, level: int, batch: int) -> jax.Array:
    points, default_width = element_sample_points(mesh, level), default_edge_width(mesh, level)

    def frame(t: jax.Array) -> jax.Array:
        field = jnp.zeros(mesh.n_elements, dtype=jnp.result_type(float))
        for index, touch in enumerate(touches):
            change = _touch_field(points, default_width, touch, t)
            field = change if index == 0 else combine_changes(field, change)
        return field

    return jax.lax.map(frame, times, batch_size=batch)


def _check_increases(touches: tuple[Touch, ...]) -> None:
    increases = [float(t.amplitude) for t in touches if is_concrete(t.amplitude) and float(t.amplitude) > 0]
    drops = [a / (1 + a) for a in increases]  # each resistance drop, as a fraction
    if len(drops) > 1 and sum(drops) >= 1:
        raise ValueError(
            f"touch amplitudes: the conductivity increases (positive Touch.amplitude) {increases} lower the "
            f"resistance by {sum(drops):.0%} together (sum of a / (1 + a)); where they overlap the conductivity "
            "would not stay positive; use smaller increases"
        )


def check_touches(mesh: Mesh, touches: Sequence[Touch]) -> None:
    """ValueError unless every touch's centre lies on the skin at every time: the centre (or a
    moving centre's breakpoints and points along the segments between them) inside some triangle
    of `mesh`. A footprint may overhang the rim (a finger at the edge): the part off the skin
    covers no element. Traced centres are not checked."""
    for index, touch in enumerate(touches):
        if not isinstance(touch, Touch):
            raise ValueError(f"touches[{index}] must be a Touch; got {touch!r}")
        reach = _reach(touch.shape.centre, f"touches[{index}].shape.centre")
        if reach is None:
            continue
        fractions = np.linspace(0.0, 1.0, _CHECKS_PER_SEGMENT + 1)[:-1, None, None]
        along = (reach[:-1] + fractions * (reach[1:] - reach[:-1])).reshape(-1, 2)
        points = np.concatenate([reach, along])
        outside = ~_on_mesh(mesh, points)
        if np.any(outside):
            where = points[np.flatnonzero(outside)[0]]
            moving = " (along its path)" if len(reach) > 1 else ""
            raise ValueError(
                f"touches[{index}].shape.centre{moving} lies outside the skin at ({where[0]:.6g}, {where[1]:.6g}) m; "
                "a touch's centre must be on the mesh"
            )


def _on_mesh(mesh: Mesh, points: np.ndarray) -> np.ndarray:
    """(P,) whether each point (P, 2) lies in some triangle (boundary included, to rounding)."""
    corners = mesh.nodes[mesh.triangles]  # (E, 3, 2)
    origin, edge1, edge2 = corners[:, 0], corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    determinant = edge1[:, 0] * edge2[:, 1] - edge1[:, 1] * edge2[:, 0]
    inside = np.zeros(len(points), dtype=bool)
    for start in range(0, len(points), 64):  # bounds the (points x elements) temporaries
        offset = points[start : start + 64, None, :] - origin
        u = (offset[..., 0] * edge2[:, 1] - offset[..., 1] * edge2[:, 0]) / determinant
        v = (edge1[:, 0] * offset[..., 1] - edge1[:, 1] * offset[..., 0]) / determinant
        coordinates = np.stack([1 - u - v, u, v])
        inside[start : start + 64] = np.any(np.all(coordinates >= _INSIDE_TOLERANCE, axis=0), axis=1)
    return inside
