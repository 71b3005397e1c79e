"""The skin's conductivity without touches: a uniform value, regions of their own value, or a
function of position. Sheet conductivity in S/sq, lengths in metres."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._arrays import concrete_floats, is_concrete
from ..mesh import Mesh, element_sample_points
from ._shapes import AbstractShape, check_level, covered_fraction, default_edge_width
from ._time_courses import ArrayLike, as_float


class Region(eqx.Module):
    """Part of the skin with its own conductivity, under a footprint with a smooth edge.

    Attributes:
        shape: The footprint (`Disc`, `Ellipse` or `Polygon`).
        conductivity: Its sheet conductivity, S/sq, > 0.
        edge_width: The standard deviation of its blurred edge, metres, > 0; None: the mesh's
            default (`default_edge_width`), as touches.

    Raises:
        ValueError: Naming the field, for a shape that is not a shape, a conductivity that is
            not finite and positive, or an edge width that is not one positive number.
    """

    shape: AbstractShape
    conductivity: ArrayLike
    edge_width: ArrayLike | None = None

    def __check_init__(self) -> None:
        if not isinstance(self.shape, AbstractShape):
            raise ValueError(f"Region.shape must be a Disc, an Ellipse or a Polygon; got {self.shape!r}")
        _check_positive(self.conductivity, "Region.conductivity", "S/sq")
        if self.edge_width is not None:
            width = concrete_floats(self.edge_width, "Region.edge_width")
            if width is not None and (width.shape != () or width <= 0):
                raise ValueError(f"Region.edge_width must be a positive number (metres) or None; got {width}")


class Background(eqx.Module):
    """The skin's conductivity without touches, S/sq.

    A uniform value or a function of position, with regions of other values applied in order:
    each replaces what lies under it, with a smooth edge, sigma <- sigma + f (sigma_region -
    sigma). Element values are means over `level`^2 sample points, like touches
    (`values_on`).

    Attributes:
        conductivity: The uniform value, S/sq, > 0 (default 0.01).
        regions: `Region`s of other values, applied in order.
        function: A map instead of the uniform value, points (..., 2) in metres -> S/sq
            (static; a JAX function is differentiable; a scene with a function cannot be
            saved as TOML); None for the uniform value.

    Raises:
        ValueError: For a conductivity that is not finite and positive, a region that is not
            a `Region`, or a function that is not callable.
    """

    conductivity: ArrayLike = 0.01
    regions: tuple[Region, ...] = eqx.field(default=(), converter=tuple)
    function: Callable[[jax.Array], jax.Array] | None = eqx.field(default=None, static=True)

    def __check_init__(self) -> None:
        _check_positive(self.conductivity, "background.conductivity", "S/sq")
        for index, region in enumerate(self.regions):
            if not isinstance(region, Region):
                raise ValueError(f"background.regions[{index}] must be a Region; got {region!r}")
        if self.function is not None and not callable(self.function):
            raise ValueError(f"background.function must be a function of points (..., 2); got {self.function!r}")

    def values_on(self, mesh: Mesh, *, level: int = 8) -> jax.Array:
        """The element-wise sheet conductivity on a mesh.

        Arguments:
            mesh: The skin's mesh.
            level: level^2 sample points per element (a positive integer).

        Returns:
            (E,) sigma, S/sq.

        Raises:
            ValueError: When a concrete element value is not positive and finite (naming the
                first such element).
        """
        check_level(level)
        function_values = None
        if self.function is not None:  # called outside the program: it may be a NumPy function
            points = jnp.asarray(element_sample_points(mesh, level))
            function_values = jnp.mean(jnp.asarray(self.function(points), dtype=float), axis=1)
        values = _values_on(self.conductivity, self.regions, function_values, mesh, level)
        if is_concrete(values):
            bad = np.flatnonzero(~(np.asarray(values) > 0))
            if bad.size:
                raise ValueError(
                    f"background conductivity must be positive and finite (S/sq); element {bad[0]} has "
                    f"{float(values[bad[0]])}"
                )
        return values


@partial(jax.jit, static_argnames=("mesh", "level"))
def _values_on(
    conductivity: ArrayLike,
    regions: tuple[Region, ...],
    function_values: jax.Array | None,
    mesh: Mesh,
    level: int,
) -> jax.Array:
    # One program: op by op, a polygon region's distances compiled some 20 programs for each mesh.
    if function_values is None:
        values = jnp.broadcast_to(as_float(conductivity), (mesh.n_elements,))
    else:
        values = function_values
    points, width = element_sample_points(mesh, level), default_edge_width(mesh, level)
    for region in regions:
        fraction = covered_fraction(points, width, region.shape, region.edge_width, as_float(0.0))
        values = values + fraction * (region.conductivity - values)
    return values


def _check_positive(value: Any, name: str, unit: str) -> None:
    array = concrete_floats(value, name)
    if array is not None and not np.all(array > 0):
        raise ValueError(f"{name} must be positive ({unit}); got {array}")
