"""Footprints with smooth edges: `Disc`, `Ellipse`, `Polygon`, and the fraction of each element
they cover.

Lengths are in metres, times in seconds, angles in radians (counter-clockwise from the x axis).
A shape's parameters are numbers or time courses (`diffeit.scene.Press`, `Ramp`, `Path`).

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
disc meshed at h = 0.1, 0.01 m at h = 0.05, with level 8). The samples then resolve the edge,
and the derivatives of the covered area in a disc's radius and centre are accurate (a blur
whose width jumps between elements would no longer be a normalised kernel, so the width is
one for the mesh). A finer mesh (or a higher level) gives a sharper default, converging to the exact area
fraction. Pass `edge_width` (metres) for a physical edge that does not depend on the mesh; keep
it well below the radius (the area bias is (edge_width / r)^2: small touches need a fine mesh
or a narrow edge) and above the sample spacing (narrower edges make the gradients jumpy).
"""

# No `from __future__ import annotations`: equinox reads `AbstractVar` annotations as types.

import abc
import math
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from equinox import AbstractVar
from jax.scipy.special import erfc

from .._arrays import concrete_floats
from ..mesh import Mesh, element_sample_points
from ._time_courses import AbstractTimeCourse, ArrayLike, as_float, float_array, reach, value_at


class AbstractShape(eqx.Module):
    """A footprint (of a touch or a region), with a smooth edge.

    Its parameters are numbers or time courses (metres, radians): `Disc`, `Ellipse` and
    `Polygon` are the shapes.

    Attributes:
        centre: (2,) a point of it, metres (a number or a time course).
    """

    centre: AbstractVar[ArrayLike | AbstractTimeCourse]

    @abc.abstractmethod
    def signed_distance(self, points: jax.Array, t: ArrayLike = 0.0) -> jax.Array:
        """The signed distance of points to the footprint's boundary at a time.

        Negative inside, 0 on the boundary, with unit gradient at the boundary.

        Arguments:
            points: (..., 2) points, metres.
            t: The time, seconds.

        Returns:
            (...) the distances, metres.
        """


def _check_centre(centre: ArrayLike | AbstractTimeCourse, name: str, surface: bool = False) -> None:
    values = reach(centre, name)
    if values is None or values.shape[1:] == (2,) or (surface and values.shape[1:] == (3,)):
        return
    if surface:
        raise ValueError(
            f"{name} must be a point (x, y) on a flat skin or (x, y, z) on a curved one, in metres; got values of "
            f"shape {values.shape[1:]}"
        )
    raise ValueError(
        f"{name} must be a point (x, y) in metres, shape (2,); got values of shape {values.shape[1:]} "
        "(only a Disc may lie on a curved skin, with a centre (x, y, z))"
    )


def _safe_norm(v: jax.Array) -> jax.Array:
    """|v| over the last axis, with a zero (not NaN) gradient at v = 0."""
    squared = jnp.sum(v * v, axis=-1)
    positive = squared > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, squared, 1.0)), 0.0)


class Disc(AbstractShape):
    """A round footprint; its centre and radius may be time courses.

    On a flat skin the centre is (x, y). On a curved skin (`Skin` kinds "cylinder_patch" and
    "sphere_cap", meshes with (N, 3) nodes) it is a point (x, y, z) on the surface, and the
    disc is the part of the surface within `radius` of it, distances measured as the 3D chord
    between the points rather than along the surface: for a geodesic radius s on a surface
    of curvature radius rho the chord is shorter by about s^3 / (24 rho^2), a relative error
    of s^2 / (24 rho^2) (0.2% for s = 0.2 rho, 0.7% for s = 0.4 rho): the disc reaches that
    much further along the surface than `radius`. A moving centre (`Path`, `Ramp` of points
    (x, y, z)) goes along the straight segments between its waypoints, each point moved to
    the nearest point of the skin's surface (`diffeit.scene.project_to_surface`, applied by
    `stimulus` and `touch_field` when given the skin's `surface`).

    Attributes:
        centre: (2,) metres on a flat skin, (3,) on a curved one, or a time course of such
            points (`Path` for a slide).
        radius: Metres, > 0, or a time course of such (`Ramp` for a growing contact).

    Raises:
        ValueError: For a centre that is not a point (2,) or (3,), or a radius that is not one
            positive number (at every breakpoint of a time course).
    """

    centre: ArrayLike | AbstractTimeCourse = eqx.field(converter=float_array("Disc.centre"))
    radius: ArrayLike | AbstractTimeCourse = eqx.field(converter=float_array("Disc.radius"))

    def __check_init__(self) -> None:
        _check_centre(self.centre, "Disc.centre", surface=True)
        radius = reach(self.radius, "Disc.radius")
        if radius is not None:
            if radius.shape[1:] != ():
                raise ValueError(f"Disc.radius must be a number (metres); got values of shape {radius.shape[1:]}")
            if np.any(radius <= 0):
                raise ValueError(f"Disc.radius must be positive (metres); got {radius.min()}")

    def signed_distance(self, points: jax.Array, t: ArrayLike = 0.0) -> jax.Array:
        """The signed distance |x - centre| - radius, exact (the chord on a curved skin).

        Arguments:
            points: (..., 2) points, metres ((..., 3) for a centre (x, y, z)).
            t: The time, seconds.

        Returns:
            (...) the distances, metres, negative inside.
        """
        t = as_float(t)
        return _safe_norm(points - value_at(self.centre, t)) - value_at(self.radius, t)


class Ellipse(AbstractShape):
    """An elliptic footprint; each of its parameters may be a time course.

    The signed distance is the first-order estimate d = k0 (k0 - 1) / k1, k0 = |q / (a, b)|,
    k1 = |q / (a^2, b^2)|, q the point in the ellipse's axes: exact on the boundary with unit
    gradient there (so `edge_width` is a width across the edge, in metres), exact for a circle,
    an estimate away from the boundary (where the edge weight is 0 or 1 anyway).

    Attributes:
        centre: (2,) metres, or a time course of such points.
        semi_axes: (2,) the semi-axes (a, b), metres, > 0, or a time course of such.
        angle: The angle of the first semi-axis, radians counter-clockwise from the x axis
            (default 0), or a time course of such.

    Raises:
        ValueError: For a centre that is not a point (2,), semi-axes that are not two positive
            numbers, or an angle that is not one number.
    """

    centre: ArrayLike | AbstractTimeCourse = eqx.field(converter=float_array("Ellipse.centre"))
    semi_axes: ArrayLike | AbstractTimeCourse = eqx.field(converter=float_array("Ellipse.semi_axes"))
    angle: ArrayLike | AbstractTimeCourse = eqx.field(default=0.0, converter=float_array("Ellipse.angle"))

    def __check_init__(self) -> None:
        _check_centre(self.centre, "Ellipse.centre")
        axes = reach(self.semi_axes, "Ellipse.semi_axes")
        if axes is not None:
            if axes.shape[1:] != (2,):
                raise ValueError(
                    f"Ellipse.semi_axes must be two lengths (a, b) in metres, shape (2,); got shape {axes.shape[1:]}"
                )
            if np.any(axes <= 0):
                raise ValueError(f"Ellipse.semi_axes must be positive (metres); got {axes.min()}")
        angle = reach(self.angle, "Ellipse.angle")
        if angle is not None and angle.shape[1:] != ():
            raise ValueError(f"Ellipse.angle must be a number (radians); got values of shape {angle.shape[1:]}")

    def signed_distance(self, points: jax.Array, t: ArrayLike = 0.0) -> jax.Array:
        """The first-order estimate of the signed distance (exact on the boundary).

        Arguments:
            points: (..., 2) points, metres.
            t: The time, seconds.

        Returns:
            (...) the distances, metres, negative inside (-min(a, b) at the centre itself).
        """
        t = as_float(t)
        axes, angle = value_at(self.semi_axes, t), value_at(self.angle, t)
        offset = points - value_at(self.centre, t)
        cos, sin = jnp.cos(angle), jnp.sin(angle)
        q = jnp.stack([cos * offset[..., 0] + sin * offset[..., 1], cos * offset[..., 1] - sin * offset[..., 0]], -1)
        k0 = _safe_norm(q / axes)
        k1 = _safe_norm(q / axes**2)
        positive = k1 > 0
        # At the centre itself the estimate has no limit; any value well inside does.
        return jnp.where(positive, k0 * (k0 - 1) / jnp.where(positive, k1, 1.0), -jnp.min(axes))


class Polygon(AbstractShape):
    """A polygonal footprint or region (the region of a non-uniform background, a half of the skin).

    A simple polygon in either orientation, fixed in time. The signed distance is exact: the
    distance to the nearest edge, negative inside (even-odd rule).

    Attributes:
        vertices: (K, 2) metres, K >= 3.

    Raises:
        ValueError: For vertices that are not (K, 2) finite numbers with K >= 3, or that
            repeat a vertex (an edge of zero length).
    """

    vertices: ArrayLike = eqx.field(converter=float_array("Polygon.vertices"))

    def __check_init__(self) -> None:
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
        """(2,) the mean of the vertices, metres."""
        return jnp.mean(as_float(self.vertices), axis=0)

    def signed_distance(self, points: jax.Array, t: ArrayLike = 0.0) -> jax.Array:
        """The exact signed distance: to the nearest edge, negative inside (even-odd rule).

        Arguments:
            points: (..., 2) points, metres.
            t: The time, seconds (unused: a polygon does not move).

        Returns:
            (...) the distances, metres.
        """
        start = as_float(self.vertices)
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


# --- Fractions on a mesh --------------------------------------------------------------------


# Why twice the sample spacing of the largest element: over ten discs well inside unit discs
# meshed at h = 0.15, 0.1 and 0.05, the derivative of the covered area in the radius is 2 pi r
# within 9e-4 and in the centre 0 within 4e-4 of 2 pi r. Narrower defaults did worse: one sample
# spacing up to 2e-3, and the local spacing of each element up to 2e-2 (a blur whose width jumps
# between elements is no longer a normalised kernel).
def default_edge_width(mesh: Mesh, level: int = 8) -> float:
    """The default edge width of a mesh: 2 sqrt(max element area) / level.

    Twice the spacing of the sample points in the largest element, one width for the whole
    mesh (module docstring).

    Arguments:
        mesh: The mesh.
        level: level^2 sample points per element (a positive integer).

    Returns:
        The edge width, metres.

    Raises:
        ValueError: For a level that is not a positive integer.
    """
    check_level(level)
    return 2.0 * math.sqrt(float(np.max(mesh.element_areas))) / level


def check_level(level: int) -> None:
    """Check a sampling level: level^2 sample points per element.

    Arguments:
        level: The level.

    Raises:
        ValueError: Unless `level` is a positive integer.
    """
    if not isinstance(level, int | np.integer) or isinstance(level, bool) or level < 1:
        raise ValueError(f"level must be a positive integer (level^2 samples per element); got {level!r}")


def covered_fraction(
    points: np.ndarray, default_width: float, shape: AbstractShape, width: ArrayLike | None, t: jax.Array
) -> jax.Array:
    """The fraction of each element under a shape: the mean edge weight over its sample points.

    The weight is erfc(d / (sqrt(2) width)) / 2, d the signed distance (module docstring).

    Arguments:
        points: (E, S, 2) the sample points of each element, metres.
        default_width: The edge width when `width` is None, metres.
        shape: The footprint.
        width: The edge's standard deviation, metres, or None.
        t: The time, seconds.

    Returns:
        (E,) fractions in [0, 1].
    """
    width = default_width if width is None else width
    distance = shape.signed_distance(points, t)
    return jnp.mean(0.5 * erfc(distance / (math.sqrt(2) * width)), axis=1)


def shape_fraction(
    mesh: Mesh, shape: AbstractShape, t: ArrayLike = 0.0, *, edge_width: ArrayLike | None = None, level: int = 8
) -> jax.Array:
    """The fraction of each element under a shape at a time, with a Gaussian-blurred edge.

    Averaged over level^2 sample points per element (module docstring). Pure JAX in the
    shape's parameters and t: jit, grad and vmap work.

    Arguments:
        mesh: The mesh.
        shape: The footprint (`Disc`, `Ellipse` or `Polygon`).
        t: The time, seconds.
        edge_width: The edge's standard deviation, metres (default `default_edge_width`).
        level: level^2 sample points per element (a positive integer).

    Returns:
        (E,) fractions in [0, 1].

    Raises:
        ValueError: For a level that is not a positive integer, or a `shape` that is not a
            shape.
    """
    check_level(level)
    if not isinstance(shape, AbstractShape):
        raise ValueError(f"shape must be a Disc or an Ellipse; got {shape!r}")
    return _shape_fraction(mesh, shape, as_float(t), edge_width, level)


@partial(jax.jit, static_argnames=("mesh", "level"))
def _shape_fraction(
    mesh: Mesh, shape: AbstractShape, t: jax.Array, edge_width: ArrayLike | None, level: int
) -> jax.Array:
    return covered_fraction(element_sample_points(mesh, level), default_edge_width(mesh, level), shape, edge_width, t)
