"""Touches on the skin: a footprint, an amplitude and its time course, and the stimulus of a scene.

A touch lowers the sheet conductivity under its footprint (strain breaks percolation paths in
the graphite-latex sheet). Its stimulus is the relative conductivity change dsigma/sigma
(dimensionless) that an ideal, memoryless skin would show, per element and frame:

    field_e(t) = amplitude(t) x fraction_e(shape at t),

with `fraction_e` in [0, 1] the part of element e under the footprint, smooth-edged (see
`diffeit.scene.shape_fraction`). Lengths are in metres, times in seconds.

## Several touches
Overlapping touches add their strains, and R = R0 (1 + GF strain) makes their relative
resistance changes add: with rho_i = -a_i / (1 + a_i) the resistance change of stimulus a_i,
the combined stimulus is a = -rho / (1 + rho), rho = sum_i rho_i (pairwise,
a (+) b = (a + b + 2 a b) / (1 - a b)): a touch whose field is 0 somewhere (unpressed or of
amplitude 0) changes nothing there, bit for bit; touches apart sum to rounding (a + b to first
order); and the result stays above -1 for touches lowering the conductivity (two touches of -0.7
on one spot give -0.82, not -1.4). Conductivity increases (a > 0) combine
by the same rule; `stimulus` refuses those whose resistance drops could together reach 100%.

## Pressure
A touch may be given by the pressure it applies (kPa) instead of its amplitude: `FoamStack`
maps the pressure on a skin over soft foam to dsigma/sigma (`pressure_to_change`).
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._arrays import concrete_floats, is_concrete
from ..mesh import Mesh, distance_to_segments, element_sample_points
from ._shapes import AbstractShape, Disc, check_level, covered_fraction, default_edge_width
from ._time_courses import AbstractTimeCourse, ArrayLike, Press, as_float, check_shape, float_array, reach, value_at

# Sample points held in memory at once by `stimulus` (frames x elements x samples): frames are
# mapped in batches of this size, so long scenes on fine meshes stay within a few hundred MB.
_SAMPLES_PER_BATCH = 1 << 22
# Points per segment of a moving centre checked to lie on the skin (between breakpoints).
_CHECKS_PER_SEGMENT = 16
# A point is on the skin when its barycentric coordinates in some triangle are all above this.
_INSIDE_TOLERANCE = -1e-9
# On a curved skin a centre is on the skin within this fraction of the mesh's longest edge of it
# (the flat triangles lie up to a^2 / (8 rho) inside the surface for edges a, rho its radius).
_SURFACE_TOLERANCE = 0.5
# The surfaces a curved skin lies on (`Skin.surface`).
SURFACES = ("cylinder", "sphere")


class Touch(eqx.Module):
    """One touch: a footprint, an amplitude and its time course.

    Its stimulus at time t is amplitude x envelope(t) x the fraction of each element under the
    footprint (`touch_field`). Amplitude, edge width and every continuous parameter of the
    shape and courses are leaves (jit, grad, vmap); the kinds of shape and course and their
    `smooth` flags are structure. Concrete values are checked on construction, the position
    on the skin by `check_touches` (called by `touch_field` and `stimulus`).

    Attributes:
        shape: The footprint (a `Disc`, `Ellipse` or `Polygon`; its parameters may move in
            time).
        amplitude: The relative conductivity change dsigma/sigma under the footprint at full
            press (dimensionless, > -1: negative for a touch, about -0.2 at 2% strain to -0.7
            at 25%).
        envelope: A time course in [0, 1] multiplying the amplitude (`Press`, or a
            `Ramp`/`Path` of such values); None: pressed all the time.
        edge_width: The standard deviation (metres, > 0) of the footprint's Gaussian-blurred
            edge; None: `default_edge_width` of the mesh.

    Raises:
        ValueError: Naming the field, for a shape that is not a shape, an amplitude that is
            not one finite number > -1, an envelope that is not a time course of numbers in
            [0, 1], or an edge width that is not one positive number.
    """

    shape: AbstractShape
    amplitude: ArrayLike = eqx.field(converter=float_array("Touch.amplitude"))
    envelope: AbstractTimeCourse | None = None
    edge_width: ArrayLike | None = eqx.field(default=None, converter=float_array("Touch.edge_width"))

    def __check_init__(self) -> None:
        if not isinstance(self.shape, AbstractShape):
            raise ValueError(f"Touch.shape must be a Disc or an Ellipse; got {self.shape!r}")
        amplitude = concrete_floats(self.amplitude, "Touch.amplitude")
        if amplitude is not None:
            check_shape(amplitude, "Touch.amplitude", (), "a number")
            if amplitude <= -1:
                raise ValueError(
                    f"Touch.amplitude (dsigma/sigma) must be > -1: at -1 the conductivity vanishes; got {amplitude}"
                )
        if self.envelope is not None:
            if not isinstance(self.envelope, AbstractTimeCourse):
                raise ValueError(
                    f"Touch.envelope must be a time course (Press, Ramp, Path) or None; got {self.envelope!r}"
                )
            values = reach(self.envelope, "Touch.envelope")
            if values is not None and (values.shape[1:] != () or np.any((values < 0) | (values > 1))):
                raise ValueError(f"Touch.envelope must take numbers in [0, 1]; got breakpoint values {values}")
        if self.edge_width is not None:
            width = concrete_floats(self.edge_width, "Touch.edge_width")
            if width is not None and (width.shape != () or width <= 0):
                raise ValueError(f"Touch.edge_width must be a positive number (metres) or None; got {width}")

    def amplitude_at(self, t: ArrayLike) -> jax.Array:
        """The amplitude at a time: amplitude x envelope(t).

        Arguments:
            t: Seconds, a scalar or an array.

        Returns:
            dsigma/sigma at full coverage, the shape of `t` (a scalar without envelope).
        """
        amplitude = as_float(self.amplitude)
        return amplitude if self.envelope is None else amplitude * self.envelope(t)


# --- Fields on a mesh -----------------------------------------------------------------------


def touch_field(
    mesh: Mesh, touch: Touch, t: ArrayLike, *, level: int = 8, surface: tuple[str, float] | None = None
) -> jax.Array:
    """The relative conductivity change of one touch at one time, per element.

    amplitude(t) x the fraction of each element under its footprint at t (`shape_fraction`).
    Exactly 0 where the amplitude is 0. On a curved skin the footprint is a `Disc` centred
    on the surface (its docstring).

    Arguments:
        mesh: The skin's mesh.
        touch: The `Touch`.
        t: The time, seconds.
        level: level^2 sample points per element (a positive integer).
        surface: The curved surface of the skin (`Skin.surface`): the centre at t is moved to
            its nearest point (`project_to_surface`); None: used as it is.

    Returns:
        (E,) dsigma/sigma.

    Raises:
        ValueError: For a level that is not a positive integer, or a concrete touch whose
            centre leaves the skin or whose shape does not fit it (`check_touches`).
    """
    check_level(level)
    check_touches(mesh, [touch], surface=surface)
    return _jitted_touch_field(mesh, touch, as_float(t), level, surface)


@partial(jax.jit, static_argnames=("mesh", "level", "surface"))
def _jitted_touch_field(
    mesh: Mesh, touch: Touch, t: jax.Array, level: int, surface: tuple[str, float] | None
) -> jax.Array:
    return _touch_field(element_sample_points(mesh, level), default_edge_width(mesh, level), touch, t, surface)


def _touch_field(
    points: np.ndarray, default_width: float, touch: Touch, t: jax.Array, surface: tuple[str, float] | None = None
) -> jax.Array:
    shape = touch.shape
    if surface is not None and isinstance(shape, Disc):
        centre = project_to_surface(surface, value_at(shape.centre, t))
        shape = eqx.tree_at(lambda disc: disc.centre, shape, centre)
    return touch.amplitude_at(t) * covered_fraction(points, default_width, shape, touch.edge_width, t)


def project_to_surface(surface: tuple[str, float], points: ArrayLike) -> jax.Array:
    """The nearest points of a curved skin's surface.

    On ("cylinder", rho) (axis the z axis) a point keeps its z and azimuth and moves to
    distance rho from the axis; on ("sphere", rho) (centred at the origin) it keeps its
    direction and moves to distance rho from the centre. Pure JAX (jit, grad), smooth away
    from the axis (the centre), where the nearest point is not unique (a point there stays
    there).

    Arguments:
        surface: ("cylinder", rho) or ("sphere", rho), rho in metres (`Skin.surface`).
        points: (..., 3) points, metres.

    Returns:
        (..., 3) the projected points, metres.

    Raises:
        ValueError: For an unknown surface.
    """
    kind, radius = surface
    if kind not in SURFACES:
        raise ValueError(f"surface must be one of {SURFACES} with a radius; got {surface!r}")
    points = as_float(points)
    moved = points[..., :2] if kind == "cylinder" else points
    squared = jnp.sum(moved * moved, axis=-1, keepdims=True)
    positive = squared > 0
    scale = jnp.where(positive, radius / jnp.sqrt(jnp.where(positive, squared, 1.0)), 1.0)
    if kind == "cylinder":
        return jnp.concatenate([points[..., :2] * scale, points[..., 2:]], axis=-1)
    return points * scale


def stimulus(
    mesh: Mesh,
    touches: Sequence[Touch],
    times: ArrayLike,
    *,
    level: int = 8,
    surface: tuple[str, float] | None = None,
) -> jax.Array:
    """The stimulus of several touches: dsigma/sigma per frame and element.

    Each touch's `touch_field`, overlaps combined as their relative resistance changes add
    (module docstring; zeros without touches). Pure JAX in the touches' parameters and the
    times (jit, grad and vmap work); frames are mapped in batches (`jax.lax.map` with
    `batch_size`, vmap within a batch) so memory stays bounded on long scenes, and touches
    alike (the same footprint and time course) in one vmapped program each, so compiling does
    not grow with their number.

    Arguments:
        mesh: The skin's mesh.
        touches: The `Touch`es.
        times: (T,) the frame times, seconds.
        level: level^2 sample points per element (a positive integer).
        surface: The curved surface of the skin (`Skin.surface`): each centre is moved to
            its nearest point at every frame (`project_to_surface`); None: used as it is.

    Returns:
        (T, E) dsigma/sigma.

    Raises:
        ValueError: For a level that is not a positive integer, a touch that is not a `Touch`
            or whose concrete centre leaves the skin or whose shape does not fit it
            (`check_touches`), times that are not 1D
            or (concrete) not finite, and conductivity increases whose resistance drops sum to
            100% or more (sum of a / (1 + a) over positive amplitudes >= 1): where they
            overlap the conductivity would not be positive.
    """
    check_level(level)
    touches = tuple(touches)
    check_touches(mesh, touches, surface=surface)
    times = as_float(times)
    if times.ndim != 1:
        raise ValueError(f"times must be a 1D array of frame times (seconds); got shape {times.shape}")
    if is_concrete(times) and not np.all(np.isfinite(np.asarray(times))):
        raise ValueError("times must be finite (seconds)")
    _check_increases(touches)
    batch = max(1, min(times.shape[0], _SAMPLES_PER_BATCH // (mesh.n_elements * level**2)))
    return _stimulus(mesh, touches, times, level, batch, surface)


@partial(jax.jit, static_argnames=("mesh", "level", "batch", "surface"))
def _stimulus(
    mesh: Mesh,
    touches: tuple[Touch, ...],
    times: jax.Array,
    level: int,
    batch: int,
    surface: tuple[str, float] | None,
) -> jax.Array:
    points, default_width = element_sample_points(mesh, level), default_edge_width(mesh, level)
    groups = _stacked_alike(touches)

    def frame(t: jax.Array) -> jax.Array:
        # The touches' relative resistance changes add (module docstring), a sum over each group.
        resistance = jnp.zeros(mesh.n_elements, dtype=jnp.result_type(float))
        for group in groups:
            changes = jax.vmap(lambda touch: _touch_field(points, default_width, touch, t, surface))(group)
            resistance = resistance + jnp.sum(-changes / (1 + changes), axis=0)
        return -resistance / (1 + resistance)

    return jax.lax.map(frame, times, batch_size=batch)


def _stacked_alike(touches: tuple[Touch, ...]) -> list[Touch]:
    """The touches in groups of one structure (footprint and time course alike), each stacked
    into one `Touch` of leading axis K_g, in order of their first touch: the stimulus maps a
    group's fields in one program, so compiling it does not grow with the number of touches
    (unrolled, 200 presses had taken 11 s to compile, 0.3 s to run)."""
    groups: dict[jax.tree_util.PyTreeDef, list[Touch]] = {}
    for touch in touches:
        groups.setdefault(jax.tree_util.tree_structure(touch), []).append(touch)
    return [jax.tree.map(lambda *leaves: jnp.stack(leaves), *group) for group in groups.values()]


def _check_increases(touches: tuple[Touch, ...]) -> None:
    """Refuse conductivity increases that, pressed at once, lower the resistance by 100% or more
    together (their combination then leaves the conductivity positive nowhere they overlap). A
    touch whose envelope is a `Press` is pressed from its start to its end only (presses one
    after another never add up); any other, always."""
    increases = []  # (start, end, amplitude) of each increase
    for touch in touches:
        if not is_concrete(touch.amplitude) or float(touch.amplitude) <= 0:
            continue
        course = touch.envelope
        pressed = (-np.inf, np.inf)
        if isinstance(course, Press) and is_concrete(course.start) and is_concrete(course.end):
            pressed = (float(course.start), float(course.end))
        increases.append((*pressed, float(touch.amplitude)))
    for start, _, _ in increases:
        together = [a for begin, end, a in increases if begin <= start and (start < end or begin == end)]
        drops = [a / (1 + a) for a in together]  # each resistance drop, as a fraction
        if len(drops) > 1 and sum(drops) >= 1:
            raise ValueError(
                f"touch amplitudes: the conductivity increases (positive Touch.amplitude) {together}, pressed at "
                f"once, lower the resistance by {sum(drops):.0%} together (sum of a / (1 + a)); where they overlap "
                "the conductivity would not stay positive; use smaller increases"
            )


def check_touches(mesh: Mesh, touches: Sequence[Touch], *, surface: tuple[str, float] | None = None) -> None:
    """Check that every touch's centre lies on the skin at every time.

    The centre (or a moving centre's breakpoints and points along the segments between them)
    must lie inside some triangle of `mesh`. A footprint may overhang the rim (a finger at the
    edge): the part off the skin covers no element. Traced centres are not checked.

    On a curved skin (a mesh with (N, 3) nodes) a touch must be a `Disc` with a centre
    (x, y, z) within half the mesh's longest edge of its triangles (the triangles are chords of
    the surface, a point on the surface lies a little outside them); the points along a moving
    centre's segments are first moved onto `surface` when given (`project_to_surface`), as
    `stimulus` moves them.

    Arguments:
        mesh: The skin's mesh.
        touches: The touches.
        surface: The curved surface of the skin (`Skin.surface`), or None.

    Raises:
        ValueError: For an item that is not a `Touch`, a shape that does not fit the skin
            (an `Ellipse` or `Polygon`, or a centre (x, y), on a curved skin; a centre
            (x, y, z) on a flat one), or a centre off the skin (naming the touch and the point).
    """
    for index, touch in enumerate(touches):
        if not isinstance(touch, Touch):
            raise ValueError(f"touches[{index}] must be a Touch; got {touch!r}")
        check_shape_fits(mesh, touch.shape, f"touches[{index}].shape")
        centres = reach(touch.shape.centre, f"touches[{index}].shape.centre")
        if centres is None:
            continue
        dimension = centres.shape[1]
        fractions = np.linspace(0.0, 1.0, _CHECKS_PER_SEGMENT + 1)[:-1, None, None]
        along = (centres[:-1] + fractions * (centres[1:] - centres[:-1])).reshape(-1, dimension)
        if surface is not None and len(along):
            along = np.asarray(project_to_surface(surface, along))
        points = np.concatenate([centres, along])
        if dimension == 2:
            outside = ~_on_mesh(mesh, points)
            where_off = "lies outside the skin"
        else:
            tolerance = _SURFACE_TOLERANCE * _longest_edge(mesh)
            outside = _distance_to_surface(mesh, points) > tolerance
            where_off = f"lies further than {tolerance:.3g} m (half the mesh's longest edge) from the skin's surface"
        if np.any(outside):
            where = points[np.flatnonzero(outside)[0]]
            moving = " (along its path)" if len(centres) > 1 else ""
            coordinates = ", ".join(f"{value:.6g}" for value in where)
            raise ValueError(
                f"touches[{index}].shape.centre{moving} {where_off} at ({coordinates}) m; "
                "a touch's centre must be on the mesh"
            )


def check_shape_fits(mesh: Mesh, shape: AbstractShape, name: str) -> None:
    """Check that a shape can lie on a skin: a flat shape on a flat skin, a `Disc` with a
    centre (x, y, z) on a curved one.

    Arguments:
        mesh: The skin's mesh ((N, 2) nodes flat, (N, 3) curved).
        shape: The footprint.
        name: Its name, for the error message.

    Raises:
        ValueError: Naming `name`, for an `Ellipse` or `Polygon` (or a centre (x, y)) on a
            curved skin, or a centre (x, y, z) on a flat one.
    """
    curved = mesh.nodes.shape[1] == 3
    if curved and not isinstance(shape, Disc):
        raise ValueError(
            f"{name}: {'an' if type(shape).__name__[0] in 'AEIOU' else 'a'} {type(shape).__name__} is flat-only; "
            "on a curved skin (cylinder_patch, sphere_cap) use a "
            "Disc with a centre (x, y, z) on the surface"
        )
    if not isinstance(shape, Disc):
        return
    centres = reach(shape.centre, f"{name}.centre")
    if centres is None:
        return
    if curved and centres.shape[1] != 3:
        raise ValueError(
            f"{name}.centre must be a point (x, y, z) on a curved skin, metres; got {centres.shape[1]} values"
        )
    if not curved and centres.shape[1] != 2:
        raise ValueError(f"{name}.centre must be a point (x, y) on a flat skin, metres; got {centres.shape[1]} values")


def _longest_edge(mesh: Mesh) -> float:
    corners = mesh.nodes[mesh.triangles]
    return float(np.max(np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2)))


def _distance_to_surface(mesh: Mesh, points: np.ndarray) -> np.ndarray:
    """(P,) the distance from each point (P, 3) to the nearest triangle of a surface mesh:
    to its plane where the point's projection falls inside it, else to its nearest edge."""
    corners = mesh.nodes[mesh.triangles]  # (E, 3, 3)
    origin, edge1, edge2 = corners[:, 0], corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    normal = np.cross(edge1, edge2)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    # Barycentric coordinates of the projection on each plane: the Gram matrix of the edges.
    g11, g12, g22 = np.sum(edge1 * edge1, 1), np.sum(edge1 * edge2, 1), np.sum(edge2 * edge2, 1)
    determinant = g11 * g22 - g12 * g12
    starts = np.concatenate([corners[:, 0], corners[:, 1], corners[:, 2]])
    stops = np.concatenate([corners[:, 1], corners[:, 2], corners[:, 0]])
    distances = np.empty(len(points))
    for start in range(0, len(points), 64):  # bounds the (points x elements) temporaries
        offset = points[start : start + 64, None, :] - origin  # (p, E, 3)
        d1, d2 = np.einsum("pex,ex->pe", offset, edge1), np.einsum("pex,ex->pe", offset, edge2)
        u = (g22 * d1 - g12 * d2) / determinant
        v = (g11 * d2 - g12 * d1) / determinant
        inside = (u >= 0) & (v >= 0) & (u + v <= 1)
        height = np.abs(np.einsum("pex,ex->pe", offset, normal))
        to_plane = np.min(np.where(inside, height, np.inf), axis=1)
        to_edge = distance_to_segments(points[start : start + 64], starts, stops)
        distances[start : start + 64] = np.minimum(to_plane, to_edge)
    return distances


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


# --- Pressure: the optional force mapping ---------------------------------------------------


class FoamStack(eqx.Module):
    """How a pressure on the skin over soft foam changes its conductivity.

    skin1 of the multi-layer skin stack the tactile-skin dissertation builds on: the relative
    resistance dR/R0 rises by `sensitivity` per kPa up to the `knee`, then by
    `sensitivity_above` per kPa (docs/science.md#pressure). See `pressure_to_change`.

    Attributes:
        sensitivity: dR/R0 per kPa below the knee, a fraction (1.3 %/kPa = 0.013, the
            default), >= 0; a leaf.
        knee: The end of the linear range, kPa (default 38), >= 0; a leaf.
        sensitivity_above: dR/R0 per kPa above the knee (default 0.002), >= 0; a leaf.

    Raises:
        ValueError: Naming the field, for a value that is not finite numbers or is negative.
    """

    sensitivity: ArrayLike = 0.013
    knee: ArrayLike = 38.0
    sensitivity_above: ArrayLike = 0.002

    def __check_init__(self) -> None:
        for name in ("sensitivity", "knee", "sensitivity_above"):
            array = concrete_floats(getattr(self, name), f"FoamStack.{name}")
            if array is not None and not np.all(array >= 0):
                raise ValueError(f"FoamStack.{name} must be >= 0; got {array}")


def pressure_to_change(pressure: ArrayLike, stack: FoamStack | None = None) -> jax.Array:
    """The relative conductivity change under a pressure, through the foam stack.

    The bilinear relative resistance change x = s p for p <= knee, s knee + s_above (p - knee)
    above; R = R0 (1 + x) gives dsigma/sigma = -x / (1 + x). With the defaults 20 kPa gives
    x = 0.26 (dsigma/sigma = -0.206), 38 kPa x = 0.494, 100 kPa x = 0.618.

    Arguments:
        pressure: kPa, >= 0, any shape.
        stack: The `FoamStack` (default `FoamStack()`).

    Returns:
        dsigma/sigma, in (-1, 0], the shape of `pressure`.

    Raises:
        ValueError: For a concrete negative pressure.
    """
    stack = FoamStack() if stack is None else stack
    p = jnp.asarray(pressure, dtype=float)
    if is_concrete(p) and not np.all(np.asarray(p) >= 0):
        raise ValueError(f"pressure must be >= 0 (kPa); got {np.asarray(p)}")
    below = stack.sensitivity * jnp.minimum(p, stack.knee)
    above = stack.sensitivity_above * jnp.maximum(p - stack.knee, 0.0)
    x = below + above
    return -x / (1 + x)
