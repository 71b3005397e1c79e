"""`Scene`: a skin, its background, touches over time and the effects to simulate, with TOML files.

A scene is data: immutable, a JAX pytree whose continuous parameters (contact impedance,
background values and regions, every touch parameter, memory, noise and drift parameters) are
leaves, so `jax.grad` differentiates a simulation with respect to them. Its structure (the
skin's geometry, the frame times, which effects) is static.

## The TOML file
Numbers are in SI units (lengths in metres, times in seconds, sheet conductivity in S/sq,
contact impedance in ohm m, current in amperes); a string names its unit: `radius = "5 mm"`,
`conductivity = "100 ohm/sq"`, `amplitude = "-30 %"`. A unit of the wrong kind, an unknown
key or an unknown effect is a `ValueError` naming the field. Saved scenes hold SI numbers.

```toml
name = "single touch"
frame_rate = 10.0                 # frames per second
duration = 3.0                    # seconds; frames at k / frame_rate, k = 0 .. n - 1

[skin]                            # the sheet: a generator of diffeit.mesh and its arguments
kind = "disc"                     # "disc" | "rectangle" | "polygon"
radius = 1.0
n_electrodes = 16
electrode_width = 0.2
h = 0.1                           # element size of the reconstruction mesh (m)
simulation_h = 0.05               # of the simulation mesh (default h / 2: data on a finer mesh)
contact_impedance = 0.01          # ohm m, or one value per electrode
drive_current = 1e-3              # A
protocol = "adjacent"             # "adjacent" | "opposite" | "skip K"

[background]
conductivity = 0.01               # S/sq
[[background.regions]]            # optional: regions of another conductivity, in order
shape = "polygon"                 # "disc" | "ellipse" | "polygon", as touches
vertices = [[0, -2], [2, -2], [2, 2], [0, 2]]   # the right half; edges well beyond the rim
conductivity = 0.002

[[touches]]
shape = "disc"                    # "disc" (centre, radius) | "ellipse" (centre, semi_axes, angle)
centre = [0.5, 0.0]               #   | "polygon" (vertices)
radius = 0.2
amplitude = -0.3                  # dsigma/sigma at full press; or pressure = "20 kPa" (FoamStack)
envelope = { kind = "press", start = 0.5, ramp_in = 0.0, hold = 1.0, ramp_out = 0.0 }

[effects.noise]                   # only the effects listed here are simulated
level = "medium"                  # or percent = 0.5, snr_db = 46, volts = "10 uV"
seed = 0
```

A parameter of a shape or a touch may move in time: a table `{kind = "ramp", initial, final,
start, duration}` or `{kind = "path", times = [...], values = [...]}` (a sliding finger's
centre), as `diffeit.scene.Ramp` and `Path`; envelopes are `{kind = "press", ...}` or those.
The effects (`EFFECT_NAMES`): "memory" (`MemoryParameters` fields, or `preset = "bare_skin" |
"over_foam"`), "noise", "common_mode_drift" (`CommonModeDrift` fields), "contact_drift"
(`rate`, `kind`), "open_electrode" (`electrodes`, `fill`), "electrode_position_error"
(`offsets` per electrode, or `std` and `seed`).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import partial
from importlib import resources
from pathlib import Path as FilePath
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .. import mesh as meshes
from .. import protocol as protocols
from .._arrays import concrete_floats, is_concrete
from .._pytree import register_dataclass
from ..mesh import Mesh, element_sample_points
from ..protocol import Protocol
from ._instrument import CommonModeDrift, ContactDrift, Noise
from ._memory import MemoryParameters
from ._stimuli import (
    AbstractShape,
    Touch,
    check_touches,
    default_edge_width,
)

ArrayLike = float | jax.Array | np.ndarray

SKIN_KINDS = ("disc", "rectangle", "polygon")
# Keys of [skin] that are the mesh generator's arguments, per kind (h is added per mesh).
GEOMETRY_KEYS = {
    "disc": {"n_electrodes": None, "electrode_width": "length", "radius": "length", "first_electrode_angle": "angle"},
    "rectangle": {"n_electrodes": None, "electrode_width": "length", "width": "length", "height": "length"},
    "polygon": {"n_electrodes": None, "electrode_width": "length", "vertices": "length"},
}


# --- Skin -----------------------------------------------------------------------------------


@partial(register_dataclass, static=("geometry", "h", "simulation_h", "drive_current", "protocol"))
@dataclass(frozen=True, eq=False, kw_only=True)
class Skin:
    """The sheet, its electrodes and how it is driven.

    - `geometry`: the sheet for a `diffeit.mesh` generator: `kind` ("disc", "rectangle",
      "polygon") and that generator's keyword arguments (lengths in metres) except `h`, e.g.
      `{"kind": "disc", "radius": 1.0, "n_electrodes": 16, "electrode_width": 0.2}`.
    - `h`: element size of the reconstruction mesh, metres.
    - `simulation_h`: element size of the simulation mesh, metres; default h / 2, so simulated
      data never come from the mesh they are reconstructed on.
    - `contact_impedance`: ohm m, a scalar or one value per electrode (a pytree leaf).
    - `drive_current`: amperes. `protocol`: "adjacent", "opposite" or "skip K".
    """

    geometry: tuple = (("kind", "disc"), ("n_electrodes", 16), ("electrode_width", 0.2), ("radius", 1.0))
    h: float = 0.1
    simulation_h: float | None = None
    contact_impedance: ArrayLike = 0.01
    drive_current: float = 1e-3
    protocol: str = "adjacent"

    def __post_init__(self) -> None:
        geometry = _frozen(dict(self.geometry) if not isinstance(self.geometry, Mapping) else self.geometry)
        object.__setattr__(self, "geometry", geometry)
        kind = dict(geometry).get("kind")
        if kind not in SKIN_KINDS:
            raise ValueError(f"skin.kind must be one of {SKIN_KINDS}; got {kind!r}")
        unknown = sorted(set(dict(geometry)) - {"kind"} - set(GEOMETRY_KEYS[kind]))
        if unknown:
            raise ValueError(f"skin: unknown keys {unknown} for a {kind}; known: {sorted(GEOMETRY_KEYS[kind])}")
        for name in ("h", "drive_current") + (("simulation_h",) if self.simulation_h is not None else ()):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"skin.{name} must be a positive number; got {value!r}")
        if self.simulation_h is None:
            object.__setattr__(self, "simulation_h", self.h / 2)
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
        return dict(self.geometry)["kind"]

    @property
    def n_electrodes(self) -> int:
        return int(dict(self.geometry).get("n_electrodes", 16))

    def mesh(self, h: float | None = None, electrode_offsets: tuple[float, ...] | None = None) -> Mesh:
        """The skin's mesh with element size `h` (metres; default the reconstruction mesh's),
        electrodes moved along the boundary by `electrode_offsets` (metres, counter-clockwise)."""
        return _mesh(self.geometry, self.h if h is None else h, electrode_offsets)

    def make_protocol(self) -> Protocol:
        return protocol_of(self.protocol, self.n_electrodes)

    def contact_impedances(self) -> jax.Array:
        """(L,) contact impedance per electrode, ohm m."""
        return jnp.broadcast_to(jnp.asarray(self.contact_impedance, dtype=float), (self.n_electrodes,))

    def geometry_with_h(self, h: float) -> dict[str, Any]:
        """The geometry description of `diffeit.io` (keyword arguments of the generator), with `h`."""
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
    if electrode_offsets is not None:
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
    """Mappings and lists as nested tuples: hashable, for static pytree data and caches."""
    if isinstance(value, Mapping):
        return tuple((key, _frozen(value[key])) for key in value)
    if isinstance(value, list | tuple | np.ndarray):
        return tuple(_frozen(v) for v in value)
    return value


def thawed(geometry: tuple) -> dict[str, Any]:
    def lists(value: Any) -> Any:
        return [lists(v) for v in value] if isinstance(value, tuple) else value

    return {key: lists(value) for key, value in geometry}


# --- Background -----------------------------------------------------------------------------


@register_dataclass
@dataclass(frozen=True, eq=False)
class Region:
    """Part of the skin with its own conductivity: a footprint (`Disc`, `Ellipse`, `Polygon`),
    its sheet conductivity (S/sq, > 0) and the width of its blurred edge (metres; None: the
    mesh's default, as touches)."""

    shape: AbstractShape
    conductivity: ArrayLike
    edge_width: ArrayLike | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.shape, AbstractShape):
            raise ValueError(f"Region.shape must be a Disc, an Ellipse or a Polygon; got {self.shape!r}")
        _check_positive(self.conductivity, "Region.conductivity", "S/sq")
        if self.edge_width is not None:
            width = concrete_floats(self.edge_width, "Region.edge_width")
            if width is not None and (width.shape != () or width <= 0):
                raise ValueError(f"Region.edge_width must be a positive number (metres) or None; got {width}")


@partial(register_dataclass, static=("function",))
@dataclass(frozen=True, eq=False)
class Background:
    """The skin's conductivity without touches, S/sq.

    `conductivity`: the uniform value (> 0); `regions`: regions of other values, applied in
    order (each replaces what lies under it, with a smooth edge); `function`: a map instead of
    the uniform value, points (..., 2) in metres -> S/sq (a JAX function is differentiable;
    a scene with a function cannot be saved as TOML). Element values are means over
    `level`^2 sample points, like touches.
    """

    conductivity: ArrayLike = 0.01
    regions: tuple[Region, ...] = ()
    function: Callable[[jax.Array], jax.Array] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "regions", tuple(self.regions))
        _check_positive(self.conductivity, "background.conductivity", "S/sq")
        for index, region in enumerate(self.regions):
            if not isinstance(region, Region):
                raise ValueError(f"background.regions[{index}] must be a Region; got {region!r}")
        if self.function is not None and not callable(self.function):
            raise ValueError(f"background.function must be a function of points (..., 2); got {self.function!r}")

    def values_on(self, mesh: Mesh, *, level: int = 8) -> jax.Array:
        """(E,) the element-wise sheet conductivity on `mesh`, S/sq. ValueError when a concrete
        value is not positive."""
        from ._stimuli import _float, _fraction

        points = element_sample_points(mesh, level)
        if self.function is None:
            values = jnp.broadcast_to(_float(self.conductivity), (mesh.n_elements,))
        else:
            values = jnp.mean(jnp.asarray(self.function(jnp.asarray(points)), dtype=float), axis=1)
        width = default_edge_width(mesh, level)
        for region in self.regions:
            fraction = _fraction(points, width, region.shape, region.edge_width, _float(0.0))
            values = values + fraction * (region.conductivity - values)
        if is_concrete(values):
            bad = np.flatnonzero(~(np.asarray(values) > 0))
            if bad.size:
                raise ValueError(
                    f"background conductivity must be positive and finite (S/sq); element {bad[0]} has "
                    f"{float(values[bad[0]])}"
                )
        return values


def _check_positive(value: Any, name: str, unit: str) -> None:
    array = concrete_floats(value, name)
    if array is not None and not np.all(array > 0):
        raise ValueError(f"{name} must be positive ({unit}); got {array}")


# --- Pressure: the optional force mapping ---------------------------------------------------


@register_dataclass
@dataclass(frozen=True, eq=False)
class FoamStack:
    """How a pressure on the skin over soft foam changes its conductivity (skin1 of the
    multi-layer skin stack the tactile-skin dissertation builds on): the relative resistance
    rises by `sensitivity` per kPa up to the `knee` (kPa), then by `sensitivity_above` per kPa.
    Sensitivities are fractions per kPa (1.3 %/kPa = 0.013), each a pytree leaf."""

    sensitivity: ArrayLike = 0.013
    knee: ArrayLike = 38.0
    sensitivity_above: ArrayLike = 0.002

    def __post_init__(self) -> None:
        for name in ("sensitivity", "knee", "sensitivity_above"):
            array = concrete_floats(getattr(self, name), f"FoamStack.{name}")
            if array is not None and not np.all(array >= 0):
                raise ValueError(f"FoamStack.{name} must be >= 0; got {array}")


def pressure_to_change(pressure: ArrayLike, stack: FoamStack | None = None) -> jax.Array:
    """dsigma/sigma (dimensionless, in (-1, 0]) under a pressure (kPa, >= 0) through the foam
    stack: the bilinear relative resistance change x = s p for p <= knee, s knee + s_above
    (p - knee) above; R = R0 (1 + x) gives dsigma/sigma = -x / (1 + x). With the defaults
    20 kPa gives x = 0.26 (dsigma/sigma = -0.206), 38 kPa x = 0.494, 100 kPa x = 0.618."""
    stack = FoamStack() if stack is None else stack
    p = jnp.asarray(pressure, dtype=float)
    if is_concrete(p) and not np.all(np.asarray(p) >= 0):
        raise ValueError(f"pressure must be >= 0 (kPa); got {np.asarray(p)}")
    below = stack.sensitivity * jnp.minimum(p, stack.knee)
    above = stack.sensitivity_above * jnp.maximum(p - stack.knee, 0.0)
    x = below + above
    return -x / (1 + x)


# --- Effects --------------------------------------------------------------------------------


@partial(register_dataclass, static=("seed",))
@dataclass(frozen=True, eq=False)
class MeasurementNoise:
    """The effect "noise": Gaussian noise of `noise` (a `Noise`) on every reading of every frame
    and of the reference, drawn from `jax.random.key(seed)`."""

    noise: Noise
    seed: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.noise, Noise):
            raise ValueError(f"effects.noise needs a Noise; got {self.noise!r}")
        if not isinstance(self.seed, int) or isinstance(self.seed, bool):
            raise ValueError(f"effects.noise.seed must be an integer; got {self.seed!r}")


@partial(register_dataclass, static=("electrodes", "fill"))
@dataclass(frozen=True, eq=False)
class OpenElectrodes:
    """The effect "open_electrode": the electrodes (indices) that carry no current; their
    readings are replaced by `fill` volts and flagged (`Simulation.lost`)."""

    electrodes: tuple[int, ...]
    fill: float = 0.0

    def __post_init__(self) -> None:
        electrodes = np.atleast_1d(np.asarray(self.electrodes))
        if electrodes.ndim != 1 or electrodes.size == 0 or not np.issubdtype(electrodes.dtype, np.integer):
            raise ValueError(f"effects.open_electrode.electrodes must be electrode indices; got {self.electrodes!r}")
        object.__setattr__(self, "electrodes", tuple(int(e) for e in electrodes))
        if not (isinstance(self.fill, int | float) and math.isfinite(self.fill)):
            raise ValueError(f"effects.open_electrode.fill must be a finite voltage; got {self.fill!r}")


@partial(register_dataclass, static=("offsets",))
@dataclass(frozen=True, eq=False)
class ElectrodePositionError:
    """The effect "electrode_position_error": every electrode of the simulation mesh moved along
    the boundary by `offsets` (metres, counter-clockwise; one per electrode), while the
    reconstruction mesh keeps the nominal positions. Static: it changes the mesh, so it has no
    gradient."""

    offsets: tuple[float, ...]

    def __post_init__(self) -> None:
        offsets = concrete_floats(self.offsets, "effects.electrode_position_error.offsets")
        if offsets is None or offsets.ndim != 1:
            raise ValueError("effects.electrode_position_error.offsets must be one number per electrode (metres)")
        object.__setattr__(self, "offsets", tuple(float(v) for v in offsets))

    @classmethod
    def random(cls, n_electrodes: int, std: float, seed: int = 0) -> ElectrodePositionError:
        """Independent Gaussian offsets of standard deviation `std` metres."""
        if not (math.isfinite(std) and std >= 0):
            raise ValueError(f"effects.electrode_position_error.std must be >= 0 (metres); got {std}")
        return cls(tuple(np.random.default_rng(seed).normal(0.0, std, n_electrodes)))


# Names of the effects in scene files, and their types.
EFFECTS: dict[str, type] = {
    "memory": MemoryParameters,
    "noise": MeasurementNoise,
    "common_mode_drift": CommonModeDrift,
    "contact_drift": ContactDrift,
    "open_electrode": OpenElectrodes,
    "electrode_position_error": ElectrodePositionError,
}
EFFECT_NAMES = tuple(EFFECTS)


def effect_name(effect: Any) -> str:
    for name, kind in EFFECTS.items():
        if isinstance(effect, kind):
            return name
    raise ValueError(f"not an effect: {effect!r}; effects are {EFFECT_NAMES}")


# --- Scene ----------------------------------------------------------------------------------


@partial(register_dataclass, static=("frame_rate", "duration", "name", "description"))
@dataclass(frozen=True, eq=False, kw_only=True)
class Scene:
    """What to simulate: a skin, its background, touches over time, and the effects.

    - `skin`: `Skin`; `background`: `Background` (S/sq); `touches`: `Touch`es (dsigma/sigma
      over time; see `diffeit.scene.Touch`).
    - `frame_rate` (frames per second) and `duration` (seconds): frames at k / frame_rate for
      k = 0 .. n_frames - 1, n_frames = floor(duration x frame_rate) (at least 1).
    - `effects`: instances of the types in `EFFECTS`, at most one of each; only these are
      simulated (`diffeit.scene.pipeline`).
    - `name`, `description`: free text.

    Construction checks everything concrete and raises `ValueError` naming the field (a touch
    whose centre is off the skin, a duplicated effect, ...). `Scene.from_toml(path)` and
    `scene.to_toml(path)` read and write scene files (module docstring).
    """

    skin: Skin = field(default_factory=Skin)
    background: Background = field(default_factory=Background)
    touches: tuple[Touch, ...] = ()
    frame_rate: float = 10.0
    duration: float = 1.0
    effects: tuple[Any, ...] = ()
    name: str = ""
    description: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "touches", tuple(self.touches))
        object.__setattr__(self, "effects", tuple(self.effects))
        # Integer parameters (hold = 2, vertices [[0, -2], ...]) as floats: jax.grad needs them so.
        for name in ("skin", "background", "touches", "effects"):
            object.__setattr__(self, name, jax.tree_util.tree_map(_float_leaf, getattr(self, name)))
        if not isinstance(self.skin, Skin):
            raise ValueError(f"skin must be a Skin; got {self.skin!r}")
        if not isinstance(self.background, Background):
            raise ValueError(f"background must be a Background; got {self.background!r}")
        for name in ("frame_rate", "duration"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)) or (
                value <= 0
            ):
                raise ValueError(
                    f"{name} must be a positive number ({'Hz' if name == 'frame_rate' else 's'}); got {value!r}"
                )
        seen = set()
        for index, effect in enumerate(self.effects):
            try:
                name = effect_name(effect)
            except ValueError:
                raise ValueError(f"effects[{index}] is not an effect: {effect!r}; effects are {EFFECT_NAMES}") from None
            if name in seen:
                raise ValueError(f"effects: {name!r} is given twice")
            seen.add(name)
        opened = self.effect("open_electrode")
        if (opened is not None and max(opened.electrodes) >= self.skin.n_electrodes) or (
            opened is not None and min(opened.electrodes) < 0
        ):
            raise ValueError(
                f"effects.open_electrode.electrodes {list(opened.electrodes)} out of range: the skin has "
                f"electrodes 0..{self.skin.n_electrodes - 1}"
            )
        moved = self.effect("electrode_position_error")
        if moved is not None and len(moved.offsets) != self.skin.n_electrodes:
            raise ValueError(
                f"effects.electrode_position_error.offsets has {len(moved.offsets)} values; the skin has "
                f"{self.skin.n_electrodes} electrodes"
            )
        self._check_contact_drift()
        try:
            mesh = self.simulation_mesh()
        except ValueError as error:
            raise ValueError(f"effects.electrode_position_error: {error}") from None
        # On the simulation mesh, finer than the reconstruction's: its rim reaches further out.
        check_touches(mesh, self.touches)

    def _check_contact_drift(self) -> None:
        drift = self.effect("contact_drift")
        rate = None if drift is None else concrete_floats(drift.rate, "effects.contact_drift.rate")
        if rate is None:
            return
        if rate.ndim == 1 and len(rate) not in (1, self.skin.n_electrodes):
            raise ValueError(
                f"effects.contact_drift.rate has {len(rate)} values; give one, or one per electrode "
                f"({self.skin.n_electrodes})"
            )
        last = self.times[-1]
        if drift.kind == "linear" and np.any(1 + rate * last <= 0):
            raise ValueError(
                f"effects.contact_drift: a linear rate of {rate.min():.4g} 1/s takes the contact impedance to "
                f'z0 (1 + rate t) <= 0 by t = {last:g} s; use a smaller rate or kind = "exponential"'
            )

    @property
    def n_frames(self) -> int:
        return max(1, math.floor(self.duration * self.frame_rate + 1e-9))

    @property
    def times(self) -> np.ndarray:
        """(T,) frame times, seconds."""
        return np.arange(self.n_frames) / self.frame_rate

    def effect(self, name: str) -> Any:
        """The effect named `name` (one of `EFFECT_NAMES`), or None when the scene has none."""
        if name not in EFFECTS:
            raise ValueError(f"unknown effect {name!r}; effects are {EFFECT_NAMES}")
        return next((e for e in self.effects if isinstance(e, EFFECTS[name])), None)

    def replace(self, **changes: Any) -> Scene:
        """A copy with `changes` (keyword fields) applied, checked."""
        values = {name: getattr(self, name) for name in self.__dataclass_fields__}
        return Scene(**{**values, **changes})

    def simulation_mesh(self) -> Mesh:
        """The mesh the data are simulated on: element size skin.simulation_h, electrodes moved
        by the electrode position error when declared."""
        moved = self.effect("electrode_position_error")
        return self.skin.mesh(self.skin.simulation_h, None if moved is None else moved.offsets)

    def reconstruction_mesh(self) -> Mesh:
        """The nominal skin meshed at skin.h."""
        return self.skin.mesh()

    # --- files ---

    def to_dict(self) -> dict[str, Any]:
        """The scene as TOML-ready data (SI numbers); ValueError for what TOML cannot hold."""
        from ._scene_file import scene_to_dict

        return scene_to_dict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Scene:
        """The scene described by `data` (as read from TOML; module docstring)."""
        from ._scene_file import scene_from_dict

        return scene_from_dict(data)

    def to_toml(self, path: str | FilePath, *, overwrite: bool = False) -> FilePath:
        """Write the scene as TOML to `path` (refusing to replace a file unless `overwrite`)."""
        import tomli_w

        path = FilePath(path)
        if path.exists() and not overwrite:
            raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
        path.write_text(tomli_w.dumps(self.to_dict()))
        return path

    def to_toml_string(self) -> str:
        import tomli_w

        return tomli_w.dumps(self.to_dict())

    @classmethod
    def from_toml(cls, path: str | FilePath) -> Scene:
        """Read a scene file."""
        path = FilePath(path)
        if not path.is_file():
            raise FileNotFoundError(f"no scene file {path}")
        return cls.from_toml_string(path.read_text(), source=str(path))

    @classmethod
    def from_toml_string(cls, text: str, *, source: str = "scene") -> Scene:
        import tomllib

        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as error:
            raise ValueError(f"{source} is not valid TOML: {error}") from None
        return cls.from_dict(data)


def _float_leaf(value: Any) -> Any:
    if is_concrete(value) and np.issubdtype(np.asarray(value).dtype, np.integer):
        return jnp.asarray(value, dtype=float)
    return value


# --- Examples -------------------------------------------------------------------------------

EXAMPLES = ("single_touch", "three_touches", "sliding_finger", "non_uniform_background", "repeated_touches_memory")


def example(name: str) -> Scene:
    """A named example scene shipped with diffeit (`EXAMPLES`); its TOML file is
    `example_path(name)`."""
    return Scene.from_toml_string(example_path(name).read_text(), source=f"example {name}")


def example_path(name: str) -> FilePath:
    if name not in EXAMPLES:
        raise ValueError(f"unknown example scene {name!r}; examples are {EXAMPLES}")
    return FilePath(str(resources.files(__package__).joinpath("examples", f"{name}.toml")))
