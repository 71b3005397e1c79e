"""The skin of a scene: its sheet and electrodes (meshed on demand), contact impedance, drive
current and protocol. Lengths in metres, contact impedance in ohm m, current in amperes."""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import mesh as meshes
from .. import protocol as protocols
from .._arrays import concrete_floats
from ..mesh import Mesh
from ..protocol import Protocol

ArrayLike = float | jax.Array | np.ndarray

SKIN_KINDS = ("disc", "rectangle", "polygon", "cylinder_patch", "sphere_cap")
# The kinds on curved surfaces (meshes with (N, 3) nodes), and the keys their generators need.
CURVED_KINDS = ("cylinder_patch", "sphere_cap")
_REQUIRED_KEYS = {"cylinder_patch": ("radius", "length", "angle"), "sphere_cap": ("radius", "polar_angle")}
# Keys of [skin] that are the mesh generator's arguments, per kind (h is added per mesh).
GEOMETRY_KEYS = {
    "disc": {"n_electrodes": None, "electrode_width": "length", "radius": "length", "first_electrode_angle": "angle"},
    "rectangle": {"n_electrodes": None, "electrode_width": "length", "width": "length", "height": "length"},
    "polygon": {"n_electrodes": None, "electrode_width": "length", "vertices": "length"},
    "cylinder_patch": {
        "n_electrodes": None,
        "electrode_width": "length",
        "radius": "length",
        "length": "length",
        "angle": "angle",
    },
    "sphere_cap": {"n_electrodes": None, "electrode_width": "length", "radius": "length", "polar_angle": "angle"},
}


class Skin(eqx.Module):
    """The sheet, its electrodes and how it is driven; meshed on demand.

    Built from keyword arguments named as the attributes. Lengths in metres, contact
    impedance in ohm m, current in amperes. Both meshes are generated (and cached) at
    construction, so a geometry that cannot be meshed fails here.

    Attributes:
        geometry: The sheet for a `diffeit.mesh` generator: `kind` ("disc", "rectangle",
            "polygon", or on a curved surface "cylinder_patch", "sphere_cap") and that
            generator's keyword arguments (lengths in metres, angles in radians) except `h`,
            e.g. `{"kind": "disc", "radius": 1.0, "n_electrodes": 16, "electrode_width":
            0.2}` or `{"kind": "cylinder_patch", "radius": 0.04, "length": 0.15, "angle":
            2.6, "n_electrodes": 16}` (a forearm: radius, length and angle are required);
            given as a dict, held as nested tuples (static). A curved skin's mesh has (N, 3)
            nodes: its touches are `Disc`s with centres (x, y, z) on the surface.
        h: Element size of the reconstruction mesh, metres.
        simulation_h: Element size of the simulation mesh, metres; default h / 2, so
            simulated data never come from the mesh they are reconstructed on.
        contact_impedance: Ohm m, a scalar or one value per electrode (a leaf).
        drive_current: Amperes.
        protocol: "adjacent", "opposite" or "skip K".

    Raises:
        ValueError: Naming the field, for an unknown kind or geometry key, a missing key a
            curved kind requires, an `h`,
            `simulation_h` or drive current that is not a positive number, a contact
            impedance of the wrong shape, not finite or not positive, an unknown protocol or
            one the electrodes do not allow, or a geometry that cannot be meshed.
    """

    geometry: tuple = eqx.field(static=True)
    h: float = eqx.field(static=True)
    simulation_h: float = eqx.field(static=True)
    contact_impedance: ArrayLike
    drive_current: float = eqx.field(static=True)
    protocol: str = eqx.field(static=True)

    def __init__(
        self,
        *,
        geometry: tuple | Mapping[str, Any] = (
            ("kind", "disc"),
            ("n_electrodes", 16),
            ("electrode_width", 0.2),
            ("radius", 1.0),
        ),
        h: float = 0.1,
        simulation_h: float | None = None,
        contact_impedance: ArrayLike = 0.01,
        drive_current: float = 1e-3,
        protocol: str = "adjacent",
    ) -> None:
        geometry = _frozen(dict(geometry) if not isinstance(geometry, Mapping) else geometry)
        kind = dict(geometry).get("kind")
        if kind not in SKIN_KINDS:
            raise ValueError(f"skin.kind must be one of {SKIN_KINDS}; got {kind!r}")
        unknown = sorted(set(dict(geometry)) - {"kind"} - set(GEOMETRY_KEYS[kind]))
        if unknown:
            raise ValueError(f"skin: unknown keys {unknown} for a {kind}; known: {sorted(GEOMETRY_KEYS[kind])}")
        missing = [key for key in _REQUIRED_KEYS.get(kind, ()) if key not in dict(geometry)]
        if missing:
            raise ValueError(f"skin: a {kind} needs {missing} (lengths in metres, angles in radians)")
        given = {"h": h, "drive_current": drive_current} | (
            {} if simulation_h is None else {"simulation_h": simulation_h}
        )
        for name, value in given.items():
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"skin.{name} must be a positive number; got {value!r}")
        self.geometry = geometry
        self.h = h
        self.simulation_h = h / 2 if simulation_h is None else simulation_h
        self.contact_impedance = contact_impedance
        self.drive_current = drive_current
        self.protocol = protocol

    def __check_init__(self) -> None:
        z = concrete_floats(self.contact_impedance, "skin.contact_impedance")
        if z is not None:
            if z.ndim > 1 or (z.ndim == 1 and len(z) != self.n_electrodes):
                raise ValueError(
                    f"skin.contact_impedance must be a scalar or one value per electrode ({self.n_electrodes},) "
                    f"in ohm m; got shape {z.shape}"
                )
            if np.any(z <= 0):
                raise ValueError(f"skin.contact_impedance must be positive (ohm m); got {z}")
        protocol_of(self.protocol, self.n_electrodes)
        try:  # both meshes (cached): a geometry that cannot be meshed is the skin's fault
            self.mesh()
            self.mesh(self.simulation_h)
        except ValueError as error:
            raise ValueError(f"skin: {error}") from None

    @property
    def kind(self) -> str:
        """The sheet's kind: "disc", "rectangle", "polygon", "cylinder_patch" or "sphere_cap"."""
        return dict(self.geometry)["kind"]

    @property
    def surface(self) -> tuple[str, float] | None:
        """The curved surface the skin lies on: ("cylinder", radius) about the z axis,
        ("sphere", radius) centred at the origin (radius in metres), or None for a flat skin.

        `diffeit.scene.project_to_surface` moves points onto it."""
        kind = self.kind
        if kind not in CURVED_KINDS:
            return None
        return ("cylinder" if kind == "cylinder_patch" else "sphere", float(dict(self.geometry)["radius"]))

    @property
    def n_electrodes(self) -> int:
        """L, the number of electrodes (16 unless the geometry says)."""
        return int(dict(self.geometry).get("n_electrodes", 16))

    def mesh(self, h: float | None = None, electrode_offsets: tuple[float, ...] | None = None) -> Mesh:
        """The skin's mesh at an element size, its electrodes nominal or moved along the boundary.

        Generated by the `diffeit.mesh` generator of the skin's kind and cached: the same
        arguments give the same `Mesh`.

        Arguments:
            h: Element size, metres; None for the reconstruction mesh's, `h`.
            electrode_offsets: One offset per electrode along the boundary, metres,
                counter-clockwise, as a tuple (hashable, for the cache); None for the nominal
                positions. Flat skins only: a curved skin's generator places the electrodes
                evenly.

        Returns:
            The `diffeit.mesh.Mesh`: (N, 2) nodes for a flat skin, (N, 3) for a curved one.

        Raises:
            ValueError: For `electrode_offsets` on a curved skin, and from the generator for a
                geometry it cannot mesh (for example electrodes moved onto each other).
        """
        return _mesh(self.geometry, self.h if h is None else h, electrode_offsets)

    def make_protocol(self) -> Protocol:
        """The `diffeit.protocol.Protocol` that `protocol` names, on the skin's electrodes."""
        return protocol_of(self.protocol, self.n_electrodes)

    def contact_impedances(self) -> jax.Array:
        """(L,) contact impedance per electrode, ohm m."""
        return jnp.broadcast_to(jnp.asarray(self.contact_impedance, dtype=float), (self.n_electrodes,))

    def geometry_with_h(self, h: float) -> dict[str, Any]:
        """The skin's geometry as the geometry description of `diffeit.io`, with an element size.

        What a frames file stores as its geometry, and `diffeit.io.mesh_from_geometry` meshes.

        Arguments:
            h: The element size, metres.

        Returns:
            A dict of "kind", the generator's keyword arguments (lengths in metres, angles in
            radians; nested tuples as lists) and "h".
        """
        return {**thawed(self.geometry), "h": h}


def protocol_of(name: str, n_electrodes: int) -> Protocol:
    """The protocol a scene names: "adjacent", "opposite" or "skip K"."""
    words = name.split() if isinstance(name, str) else []
    try:
        if words == ["adjacent"]:
            return protocols.adjacent(n_electrodes)
        if words == ["opposite"]:
            return protocols.opposite(n_electrodes)
        if len(words) == 2 and words[0] == "skip" and words[1].isdigit():
            return protocols.skip(n_electrodes, int(words[1]))
    except ValueError as error:
        raise ValueError(f"skin.protocol {name!r}: {error}") from None
    raise ValueError(f'skin.protocol must be "adjacent", "opposite" or "skip K" (K an integer); got {name!r}')


@functools.lru_cache(maxsize=16)
def _mesh(geometry: tuple, h: float, electrode_offsets: tuple[float, ...] | None) -> Mesh:
    keywords = thawed(geometry)
    kind = keywords.pop("kind")
    if kind in CURVED_KINDS:
        if electrode_offsets is not None:
            raise ValueError(f"a {kind} places its electrodes evenly: electrode position errors are flat skins' only")
        keywords.setdefault("n_electrodes", 16)
    elif electrode_offsets is not None:
        n = keywords.get("n_electrodes", 16)
        if kind == "disc":
            radius = keywords.get("radius", 1.0)
            nominal = keywords.pop("first_electrode_angle", 0.0) + 2 * np.pi * np.arange(n) / n
            keywords["electrode_angles"] = nominal + np.asarray(electrode_offsets) / radius
        else:
            nominal = _nominal_centres(kind, keywords, n)
            keywords["electrode_centres"] = nominal + np.asarray(electrode_offsets)
    return getattr(meshes, kind)(h=h, **keywords)


def _nominal_centres(kind: str, keywords: dict, n: int) -> np.ndarray:
    if kind == "rectangle":
        perimeter = 2 * (keywords.get("width", 1.0) + keywords.get("height", 1.0))
    else:
        vertices = np.asarray(keywords["vertices"], dtype=float)
        perimeter = float(np.sum(np.linalg.norm(np.roll(vertices, -1, axis=0) - vertices, axis=1)))
    return (np.arange(n) + 0.5) * perimeter / n


def _frozen(value: Any) -> Any:
    """Mappings and lists as nested tuples of plain Python values: hashable, for static data
    and caches."""
    if isinstance(value, Mapping):
        return tuple((key, _frozen(value[key])) for key in value)
    if isinstance(value, list | tuple | np.ndarray):
        return tuple(_frozen(v) for v in value)
    # NumPy scalars are arrays to equinox, which warns when they sit in a static field.
    return value.item() if isinstance(value, np.generic) else value


def thawed(geometry: tuple) -> dict[str, Any]:
    """The geometry tuples back as the generator's keyword arguments (nested tuples as lists)."""

    def lists(value: Any) -> Any:
        return [lists(v) for v in value] if isinstance(value, tuple) else value

    return {key: lists(value) for key, value in geometry}
