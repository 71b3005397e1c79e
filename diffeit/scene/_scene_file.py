"""Scene files: reading a file's TOML data (`read_scene_file`) into the arguments of a `Scene`
(checking every field, converting units) and writing a scene back as SI numbers. The format is
described in the docstring of the module of `Scene` (`diffeit.scene._scene`), which calls into
this one."""

from __future__ import annotations

import contextlib
import dataclasses
import tomllib
from collections.abc import Iterator, Mapping
from pathlib import Path as FilePath
from typing import Any

import jax.numpy as jnp

from .._arrays import concrete_floats
from ..memory import bare_skin, over_foam
from ._background import Background, Region
from ._effects import EFFECT_NAMES, EFFECTS, effect_name
from ._instrument import (
    CommonModeDrift,
    ContactDrift,
    ElectrodePositionError,
    MeasurementNoise,
    Noise,
    OpenElectrodes,
    ReadingGains,
    ReadoutMixing,
)
from ._shapes import AbstractShape, Disc, Ellipse, Polygon
from ._skin import GEOMETRY_KEYS, SKIN_KINDS, Skin, thawed
from ._time_courses import AbstractTimeCourse, Path, Press, Ramp
from ._touches import FoamStack, Touch, pressure_to_change
from ._units import quantities

# --- Reading --------------------------------------------------------------------------------


def read_scene_file(path: FilePath) -> dict[str, Any]:
    """The TOML data of the scene file at `path`.

    Raises `FileNotFoundError` for a missing file and `ValueError` naming the file for one that
    is not UTF-8 text (TOML's encoding; a PNG, an HDF5 file), not TOML, holds no key (empty), or
    whose last line does not end in a newline: the file is cut short (a line cut within a
    number would read as another number), or its editor left the newline out (add it). A scene
    file carries no checksum: a digit changed to another digit, or a file cut at the end of a
    line, reads as what the file now says (the keys cut off take their defaults).
    """
    if not path.is_file():
        raise FileNotFoundError(f"no scene file {path}")
    data = path.read_bytes()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as error:
        raise ValueError(
            f"{path} is not a scene file: byte {error.start} is not UTF-8 text (TOML's encoding)"
        ) from None
    if text and not text.endswith(("\n", "\r")):
        raise ValueError(
            f"{path}: the last line does not end in a newline: the file is cut short, or its editor left the "
            "newline out (add it if the file is whole)"
        )
    try:
        table = tomllib.loads(text)
    except (tomllib.TOMLDecodeError, RecursionError) as error:  # tomllib recurses into nested arrays
        raise ValueError(f"{path} is not valid TOML: {error}") from None
    if not table:
        raise ValueError(f"{path} holds no scene: no key")
    return table


class _Table:
    """A TOML table being read: values by key, each converted once, unknown keys refused."""

    def __init__(self, data: Any, path: str) -> None:
        if not isinstance(data, Mapping):
            raise ValueError(f"{path} must be a table; got {data!r}")
        self.data, self.path, self.used = dict(data), path, set()

    def field(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path else key

    def has(self, key: str) -> bool:
        return key in self.data

    def raw(self, key: str, default: Any = None) -> Any:
        self.used.add(key)
        return self.data.get(key, default)

    def get(self, key: str, kind: str, default: Any = None) -> Any:
        """A quantity (or nested list of them) in SI units, or a time course table."""
        self.used.add(key)
        if key not in self.data:
            return default
        value = self.data[key]
        if isinstance(value, Mapping):
            return _course(_Table(value, self.field(key)), kind)
        return quantities(value, kind, self.field(key))

    def done(self) -> None:
        unknown = sorted(set(self.data) - self.used)
        if unknown:
            known = ", ".join(sorted(self.used))
            raise ValueError(f"{self.path or 'scene'}: unknown keys {unknown} (known here: {known})")


def _leaf(value: Any) -> Any:
    """A list read from a file as one array leaf (per electrode, per element), as in code."""
    return jnp.asarray(value, dtype=float) if isinstance(value, list) else value


def _word(table: _Table, key: str, default: str | None = None) -> str | None:
    """A string-valued key (a name from a fixed set), refused when it is not a string."""
    value = table.raw(key, default)
    if not isinstance(value, str):
        raise ValueError(f"{table.field(key)} must be a string (a name); got {value!r}")
    return value


def _course(table: _Table, kind: str) -> AbstractTimeCourse:
    course = table.raw("kind")
    smooth = table.raw("smooth", False)
    if not isinstance(smooth, bool):
        raise ValueError(f"{table.field('smooth')} must be true or false; got {smooth!r}")
    if course == "press":
        made = Press(
            start=table.get("start", "time", 0.0),
            ramp_in=table.get("ramp_in", "time", 0.0),
            hold=table.get("hold", "time", 1.0),
            ramp_out=table.get("ramp_out", "time", 0.0),
            smooth=smooth,
        )
    elif course == "ramp":
        made = Ramp(
            initial=_required(table, "initial", kind),
            final=_required(table, "final", kind),
            start=table.get("start", "time", 0.0),
            duration=table.get("duration", "time", 1.0),
            smooth=smooth,
        )
    elif course == "path":
        made = Path(times=_required(table, "times", "time"), values=_required(table, "values", kind), smooth=smooth)
    else:
        raise ValueError(f'{table.field("kind")} must be "press", "ramp" or "path"; got {course!r}')
    table.done()
    return made


def _required(table: _Table, key: str, kind: str) -> Any:
    if not table.has(key):
        raise ValueError(f"{table.field(key)} is missing")
    return table.get(key, kind)


def _shape(table: _Table) -> AbstractShape:
    kind = table.raw("shape", "disc")
    with _naming(table.path):
        if kind == "disc":
            return Disc(centre=_required(table, "centre", "length"), radius=_required(table, "radius", "length"))
        if kind == "ellipse":
            return Ellipse(
                centre=_required(table, "centre", "length"),
                semi_axes=_required(table, "semi_axes", "length"),
                angle=table.get("angle", "angle", 0.0),
            )
        if kind == "polygon":
            return Polygon(vertices=_required(table, "vertices", "length"))
    raise ValueError(f'{table.field("shape")} must be "disc", "ellipse" or "polygon"; got {kind!r}')


@contextlib.contextmanager
def _naming(path: str) -> Iterator[None]:
    """Re-raise a constructor's ValueError ("Disc.radius must ...") prefixed by the field's path."""
    try:
        yield
    except ValueError as error:
        if str(error).startswith(path):
            raise
        raise ValueError(f"{path}: {error}") from None


def _skin(table: _Table) -> Skin:
    kind = table.raw("kind", "disc")
    if kind not in SKIN_KINDS:
        raise ValueError(f"skin.kind must be one of {SKIN_KINDS}; got {kind!r}")
    geometry: dict[str, Any] = {"kind": kind}
    for key, unit in GEOMETRY_KEYS[kind].items():
        if table.has(key):
            geometry[key] = table.raw(key) if unit is None else table.get(key, unit)
    n = geometry.get("n_electrodes", 16)
    if not isinstance(n, int) or isinstance(n, bool) or n < 2:
        raise ValueError(f"skin.n_electrodes must be an integer >= 2; got {n!r}")
    contact = table.get("contact_impedance", "contact impedance", 0.01)
    skin = Skin(
        geometry=geometry,
        h=table.get("h", "length", 0.1),
        simulation_h=table.get("simulation_h", "length"),
        contact_impedance=_leaf(contact),
        drive_current=table.get("drive_current", "current", 1e-3),
        protocol=table.raw("protocol", "adjacent"),
    )
    table.done()
    return skin


def _background(table: _Table) -> Background:
    regions = table.raw("regions", [])
    if not isinstance(regions, list):
        raise ValueError(f"background.regions must be an array of tables; got {regions!r}")
    made = []
    for index, data in enumerate(regions):
        region = _Table(data, f"background.regions[{index}]")
        shape = _shape(region)
        with _naming(region.path):
            made.append(
                Region(
                    shape,
                    _required(region, "conductivity", "sheet conductivity"),
                    region.get("edge_width", "length"),
                )
            )
        region.done()
    background = Background(table.get("conductivity", "sheet conductivity", 0.01), tuple(made))
    table.done()
    return background


def _touch(table: _Table) -> Touch:
    shape = _shape(table)
    if table.has("amplitude") == table.has("pressure"):
        raise ValueError(f"{table.path}: give either amplitude (dsigma/sigma) or pressure (kPa)")
    for key in ("amplitude", "pressure"):
        if isinstance(table.data.get(key), Mapping):
            raise ValueError(f"{table.field(key)} must be a number; a time course goes in {table.field('envelope')}")
    if table.has("amplitude"):
        amplitude = table.get("amplitude", "ratio")
    else:
        foam = table.raw("foam", {})
        stack = _Table(foam, table.field("foam"))
        with _naming(stack.path):
            made = FoamStack(
                **{
                    key: stack.get(key, kind)
                    for key, kind in (("sensitivity", "ratio"), ("knee", "pressure"), ("sensitivity_above", "ratio"))
                    if stack.has(key)
                }
            )
        stack.done()
        with _naming(table.field("pressure")):
            amplitude = float(pressure_to_change(table.get("pressure", "pressure"), made))
    envelope = table.get("envelope", "ratio")
    if envelope is not None and not isinstance(envelope, AbstractTimeCourse):
        raise ValueError(f'{table.field("envelope")} must be a time course table such as {{kind = "press", ...}}')
    with _naming(table.path):
        touch = Touch(shape, amplitude, envelope, table.get("edge_width", "length"))
    table.done()
    return touch


def _effect(name: str, table: _Table, skin: Skin) -> Any:
    n_electrodes = skin.n_electrodes
    with _naming(table.path):
        if name == "memory":
            preset = _word(table, "preset", "over_foam")
            presets = {"over_foam": over_foam, "bare_skin": bare_skin}
            if preset not in presets:
                raise ValueError(f"preset must be one of {sorted(presets)}; got {preset!r}")
            base = presets[preset]()
            units = {"fast_time": "time", "slow_time": "time", "fatigue_recovery_time": "time", "fatigue_rate": "rate"}
            values = {f: _leaf(table.get(f, units.get(f, "ratio"))) for f in _field_names(base) if table.has(f)}
            made = dataclasses.replace(base, **values)
        elif name == "noise":
            given = [key for key in ("level", "percent", "snr_db", "volts") if table.has(key)]
            if len(given) != 1:
                raise ValueError(f"give exactly one of level, percent, snr_db, volts; got {given or 'none'}")
            key = given[0]
            if key == "level":
                noise = Noise.level(_word(table, "level"))
            else:
                unit = {"percent": "percent", "snr_db": "decibel", "volts": "voltage"}[key]
                noise = Noise(table.get(key, unit), key)
            made = MeasurementNoise(noise, table.raw("seed", 0))
        elif name == "common_mode_drift":
            units = {"offset": "voltage", "rate": "voltage rate", "amplitude": "voltage", "period": "time"}
            units |= {"phase": "angle", "gain_rate": "rate"}
            given = {key: _leaf(table.get(key, unit)) for key, unit in units.items() if table.has(key)}
            made = CommonModeDrift(**given)
        elif name == "contact_drift":
            made = ContactDrift(_leaf(table.get("rate", "rate", 0.0)), _word(table, "kind", "exponential"))
        elif name == "open_electrode":
            made = OpenElectrodes(table.raw("electrodes"), table.get("fill", "voltage", 0.0))
        elif name == "electrode_position_error":
            if table.has("offsets") == table.has("std"):
                raise ValueError("give either offsets (one per electrode, metres) or std (metres) and seed")
            if table.has("offsets"):
                made = ElectrodePositionError(tuple(table.get("offsets", "length")))
            else:
                made = ElectrodePositionError.random(n_electrodes, table.get("std", "length"), table.raw("seed", 0))
        elif name == "readout_mixing":
            if table.has("largest") == any(table.has(key) for key in ("source", "sink", "offsets")):
                raise ValueError(
                    "give either source, sink and offsets (one per electrode; unit-free weights) or largest and seed"
                )
            if table.has("largest"):
                made = ReadoutMixing.random(n_electrodes, table.get("largest", "ratio"), _seed(table))
            else:
                made = ReadoutMixing(
                    table.get("source", "ratio", 0.0),
                    table.get("sink", "ratio", 0.0),
                    _required(table, "offsets", "ratio"),
                )
        else:
            if table.has("gains") == table.has("spread"):
                raise ValueError("give either gains (one per reading; unit-free) or spread and seed")
            if table.has("gains"):
                made = ReadingGains(table.get("gains", "ratio"))
            else:
                n_measurements = skin.make_protocol().n_measurements
                made = ReadingGains.random(n_measurements, table.get("spread", "ratio"), _seed(table))
    table.done()
    return made


def _seed(table: _Table) -> int:
    """The integer `seed` of a random effect (default 0)."""
    seed = table.raw("seed", 0)
    if not isinstance(seed, int) or isinstance(seed, bool):
        raise ValueError(f"{table.field('seed')} must be an integer; got {seed!r}")
    return seed


def scene_arguments(data: Mapping[str, Any]) -> dict[str, Any]:
    """The keyword arguments of the `Scene` that `data` (as read from TOML) describes, each
    checked; ValueError naming the field."""
    top = _Table(data, "")
    skin = _skin(_Table(top.raw("skin", {}), "skin"))
    background = _background(_Table(top.raw("background", {}), "background"))
    touches = top.raw("touches", [])
    if not isinstance(touches, list):
        raise ValueError(f"touches must be an array of tables ([[touches]]); got {touches!r}")
    effects_table = top.raw("effects", {})
    if not isinstance(effects_table, Mapping):
        raise ValueError(f"effects must be a table of effect tables ([effects.noise], ...); got {effects_table!r}")
    effects = []
    for name, value in effects_table.items():
        if name not in EFFECTS:
            raise ValueError(f"effects.{name}: unknown effect; effects are {EFFECT_NAMES}")
        effects.append(_effect(name, _Table(value, f"effects.{name}"), skin))
    for key in ("name", "description"):
        if not isinstance(top.raw(key, ""), str):
            raise ValueError(f"{key} must be a string")
    arguments = {
        "skin": skin,
        "background": background,
        "touches": tuple(_touch(_Table(t, f"touches[{i}]")) for i, t in enumerate(touches)),
        "frame_rate": top.get("frame_rate", "frequency", 10.0),
        "duration": top.get("duration", "time", 1.0),
        "effects": tuple(effects),
        "name": top.raw("name", ""),
        "description": top.raw("description", ""),
    }
    top.done()
    return arguments


# --- Writing --------------------------------------------------------------------------------


def _plain(value: Any, name: str) -> Any:
    """A concrete number or array as TOML data (floats, nested lists)."""
    if isinstance(value, AbstractTimeCourse):
        return _course_dict(value, name)
    array = concrete_floats(value, name)
    if array is None:
        raise ValueError(f"{name} is traced: only a scene of values can be saved")
    return array.tolist() if array.ndim else float(array)


def _course_dict(course: AbstractTimeCourse, name: str) -> dict[str, Any]:
    if isinstance(course, Press):
        data = {
            "kind": "press",
            **{k: _plain(getattr(course, k), name) for k in ("start", "ramp_in", "hold", "ramp_out")},
        }
    elif isinstance(course, Ramp):
        data = {
            "kind": "ramp",
            **{k: _plain(getattr(course, k), name) for k in ("initial", "final", "start", "duration")},
        }
    elif isinstance(course, Path):
        data = {"kind": "path", "times": _plain(course.times, name), "values": _plain(course.values, name)}
    else:
        raise ValueError(f"{name}: a {type(course).__name__} cannot be saved in a scene file")
    if course.smooth:
        data["smooth"] = True
    return data


def _shape_dict(shape: AbstractShape, name: str) -> dict[str, Any]:
    if isinstance(shape, Disc):
        return {"shape": "disc", "centre": _plain(shape.centre, name), "radius": _plain(shape.radius, name)}
    if isinstance(shape, Ellipse):
        return {
            "shape": "ellipse",
            "centre": _plain(shape.centre, name),
            "semi_axes": _plain(shape.semi_axes, name),
            "angle": _plain(shape.angle, name),
        }
    if isinstance(shape, Polygon):
        return {"shape": "polygon", "vertices": _plain(shape.vertices, name)}
    raise ValueError(f"{name}: a {type(shape).__name__} cannot be saved in a scene file")


def _effect_dict(effect: Any) -> dict[str, Any]:
    name = effect_name(effect)
    where = f"effects.{name}"
    if isinstance(effect, MeasurementNoise):
        return {effect.noise.kind: _plain(effect.noise.value, where), "seed": effect.seed}
    if isinstance(effect, ContactDrift):
        return {"rate": _plain(effect.rate, where), "kind": effect.kind}
    if isinstance(effect, OpenElectrodes):
        return {"electrodes": list(effect.electrodes), "fill": effect.fill}
    if isinstance(effect, ElectrodePositionError):
        return {"offsets": list(effect.offsets)}
    return {f: _plain(getattr(effect, f), f"{where}.{f}") for f in _field_names(effect)}


def _field_names(block: Any) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(block))


def scene_to_dict(scene: Any) -> dict[str, Any]:
    """A `Scene` as TOML-ready data (SI numbers); ValueError for what TOML cannot hold."""
    skin = scene.skin
    skin_data = {**thawed(skin.geometry), "h": skin.h, "simulation_h": skin.simulation_h}
    skin_data |= {
        "contact_impedance": _plain(skin.contact_impedance, "skin.contact_impedance"),
        "drive_current": skin.drive_current,
        "protocol": skin.protocol,
    }
    background = scene.background
    if background.function is not None:
        raise ValueError("background.function is a Python function: a scene file holds numbers and regions only")
    regions = []
    for index, region in enumerate(background.regions):
        where = f"background.regions[{index}]"
        data = {**_shape_dict(region.shape, where), "conductivity": _plain(region.conductivity, where)}
        if region.edge_width is not None:
            data["edge_width"] = _plain(region.edge_width, where)
        regions.append(data)
    touches = []
    for index, touch in enumerate(scene.touches):
        where = f"touches[{index}]"
        data = {**_shape_dict(touch.shape, where), "amplitude": _plain(touch.amplitude, where)}
        if touch.envelope is not None:
            data["envelope"] = _course_dict(touch.envelope, where)
        if touch.edge_width is not None:
            data["edge_width"] = _plain(touch.edge_width, where)
        touches.append(data)
    data: dict[str, Any] = {"name": scene.name, "description": scene.description}
    data |= {"frame_rate": float(scene.frame_rate), "duration": float(scene.duration), "skin": skin_data}
    data["background"] = {"conductivity": _plain(background.conductivity, "background.conductivity")}
    if regions:
        data["background"]["regions"] = regions
    if touches:
        data["touches"] = touches
    if scene.effects:
        data["effects"] = {effect_name(e): _effect_dict(e) for e in scene.effects}
    return data
