"""`Scene`: a skin, its background, touches over time and the effects to simulate, with TOML files.

A scene is data: immutable, an `equinox.Module` whose continuous parameters (contact impedance,
background values and regions, every touch parameter, memory, noise, drift, readout mixing and
gain parameters) are leaves, so `jax.grad` differentiates a simulation with respect to them. Its
structure (the skin's geometry, the frame times, which effects) is static.

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
(`offsets` per electrode, or `std` and `seed`), "readout_mixing" (`source`, `sink` and
`offsets` per electrode, unit-free; or `largest` and `seed`, `ReadoutMixing.random`),
"reading_gains" (`gains` per reading of the protocol, unit-free; or `spread` and `seed`,
`ReadingGains.random`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import KW_ONLY
from importlib import resources
from pathlib import Path as FilePath
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._arrays import concrete_floats, is_concrete
from ..mesh import Mesh
from ._background import Background
from ._effects import EFFECT_NAMES, EFFECTS, effect_name
from ._scene_file import read_scene_file, scene_arguments, scene_to_dict
from ._skin import Skin
from ._touches import Touch, check_shape_fits, check_touches

# --- Scene ----------------------------------------------------------------------------------


def _float_leaves(block: Any) -> Any:
    """Integer leaves (hold = 2, vertices [[0, -2], ...]) as floats: jax.grad needs them so."""

    def leaf(value: Any) -> Any:
        if is_concrete(value) and np.issubdtype(np.asarray(value).dtype, np.integer):
            return jnp.asarray(value, dtype=float)
        return value

    return jax.tree_util.tree_map(leaf, block)


def _float_tuple(blocks: Any) -> tuple:
    return _float_leaves(tuple(blocks))


class Scene(eqx.Module):
    """What to simulate: a skin, its background, touches over time, and the effects.

    A scene is data: an immutable `equinox.Module` built from keyword arguments, whose
    continuous parameters (contact impedance, background values and regions, every touch
    parameter, memory, noise, drift, readout mixing and gain parameters) are leaves, so
    `jax.grad` differentiates a `simulate` with respect to them; `frame_rate`, `duration`,
    `name` and `description` are static. `from_toml` and `to_toml` read and write scene files
    (their format is in the docstring of `diffeit.scene` and docs/tutorials/scenes.md).

    Attributes:
        skin: The `Skin`: sheet, electrodes, contact impedance, drive current, protocol.
        background: The `Background` conductivity, S/sq.
        touches: The `Touch`es: dsigma/sigma over time (see `diffeit.scene.Touch`).
        frame_rate: Frames per second: frames at k / frame_rate for k = 0 .. n_frames - 1.
        duration: Seconds; n_frames = floor(duration x frame_rate), at least 1.
        effects: Instances of the types in `EFFECTS`, at most one of each; only these are
            simulated (`diffeit.scene.pipeline`).
        name: Free text.
        description: Free text.

    Raises:
        ValueError: Naming the field, for anything concrete out of range: a skin or
            background of the wrong type, a frame rate or duration that is not positive, an
            effect that is not one or is given twice, open electrodes the skin lacks,
            electrode position offsets not one per electrode (or moving electrodes off the
            sheet), a contact drift rate of the wrong length or taking z to zero, readout
            mixing offsets not one per electrode, reading gains not one per reading of the
            skin's protocol, a touch off the skin, a touch or background region whose shape
            does not fit the skin (on a curved skin only `Disc`s with centres (x, y, z)), an
            electrode position error on a curved skin.
    """

    _: KW_ONLY
    skin: Skin = eqx.field(default_factory=Skin, converter=_float_leaves)
    background: Background = eqx.field(default_factory=Background, converter=_float_leaves)
    touches: tuple[Touch, ...] = eqx.field(default=(), converter=_float_tuple)
    frame_rate: float = eqx.field(default=10.0, static=True)
    duration: float = eqx.field(default=1.0, static=True)
    effects: tuple[Any, ...] = eqx.field(default=(), converter=_float_tuple)
    name: str = eqx.field(default="", static=True)
    description: str = eqx.field(default="", static=True)

    def __check_init__(self) -> None:
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
        self._check_readout()
        try:
            mesh = self.simulation_mesh()
        except ValueError as error:
            raise ValueError(f"effects.electrode_position_error: {error}") from None
        # On the simulation mesh, finer than the reconstruction's: its rim reaches further out.
        check_touches(mesh, self.touches, surface=self.skin.surface)
        for index, region in enumerate(self.background.regions):
            check_shape_fits(mesh, region.shape, f"background.regions[{index}].shape")

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

    def _check_readout(self) -> None:
        """One mixing offset per electrode and one gain per reading of the skin's protocol."""
        mixing = self.effect("readout_mixing")
        if mixing is not None and np.shape(mixing.offsets) != (self.skin.n_electrodes,):
            raise ValueError(
                f"effects.readout_mixing.offsets has shape {np.shape(mixing.offsets)}; give one weight per "
                f"electrode ({self.skin.n_electrodes})"
            )
        gains = self.effect("reading_gains")
        if gains is not None:
            n_measurements = self.skin.make_protocol().n_measurements
            if np.shape(gains.gains) != (n_measurements,):
                raise ValueError(
                    f"effects.reading_gains.gains has shape {np.shape(gains.gains)}; give one gain per reading of "
                    f"the protocol {self.skin.protocol!r} ({n_measurements})"
                )

    @property
    def n_frames(self) -> int:
        """T, the number of frames: floor(duration x frame_rate), at least 1."""
        return max(1, math.floor(self.duration * self.frame_rate + 1e-9))

    @property
    def times(self) -> np.ndarray:
        """(T,) frame times, seconds."""
        return np.arange(self.n_frames) / self.frame_rate

    def effect(self, name: str) -> Any:
        """The scene's effect of one kind, or None when the scene has none of it.

        Arguments:
            name: The effect's name, one of `EFFECT_NAMES` (the keys of `EFFECTS`), e.g.
                "noise" or "open_electrode".

        Returns:
            The scene's instance of `EFFECTS[name]`, or None.

        Raises:
            ValueError: For a name not in `EFFECT_NAMES`.
        """
        if name not in EFFECTS:
            raise ValueError(f"unknown effect {name!r}; effects are {EFFECT_NAMES}")
        return next((e for e in self.effects if isinstance(e, EFFECTS[name])), None)

    def replace(self, **changes: Any) -> Scene:
        """A copy with `changes` (keyword fields) applied, checked."""
        return dataclasses.replace(self, **changes)

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
        return scene_to_dict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Scene:
        """The scene that a scene file's data describe.

        The data are those of a scene file as read from TOML (the format is in
        docs/tutorials/scenes.md#scene-files): numbers in SI units, or strings that name their
        unit (`radius = "5 mm"`); keys left out take their defaults. `to_dict` writes such data.

        Arguments:
            data: The tables and values of a scene file (`skin`, `background`, `touches`,
                `effects`, `frame_rate`, `duration`, `name`, `description`).

        Returns:
            The `Scene`.

        Raises:
            ValueError: Naming the field, for an unknown key or effect, a value of the wrong
                type, a unit of the wrong kind, or a value the `Scene` refuses.
        """
        return cls(**scene_arguments(data))

    def to_toml(self, path: str | FilePath, *, overwrite: bool = False) -> FilePath:
        """Write the scene to a TOML file (SI numbers).

        Arguments:
            path: The file to write.
            overwrite: Replace an existing file at `path`.

        Returns:
            `path`, as a `Path`.

        Raises:
            FileExistsError: For an existing `path` without `overwrite=True`.
            ValueError: For what TOML cannot hold (see `to_dict`).
        """
        import tomli_w

        path = FilePath(path)
        if path.exists() and not overwrite:
            raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
        path.write_text(tomli_w.dumps(self.to_dict()))
        return path

    def to_toml_string(self) -> str:
        """The scene as TOML text (see `to_toml`)."""
        import tomli_w

        return tomli_w.dumps(self.to_dict())

    @classmethod
    def from_toml(cls, path: str | FilePath) -> Scene:
        """Read a scene from a TOML file.

        Numbers are in SI units, or strings that name their unit (`radius = "5 mm"`); the
        format is in the docstring of `diffeit.scene`. A scene file carries no checksum: a
        digit changed to another digit, or a file cut at the end of a line, reads as what the
        file now says (the keys cut off take their defaults).

        Arguments:
            path: The scene file.

        Returns:
            The `Scene`.

        Raises:
            FileNotFoundError: For a missing file.
            ValueError: Naming the file, for one that is not UTF-8 text, not TOML, holds no
                key, or whose last line does not end in a newline (cut short); and naming the
                file and the field for an unknown key or effect, a unit of the wrong kind, or
                a value the `Scene` refuses.
        """
        path = FilePath(path)
        data = read_scene_file(path)
        try:
            return cls.from_dict(data)
        except ValueError as error:
            raise ValueError(f"{path}: {error}") from None

    @classmethod
    def from_toml_string(cls, text: str, *, source: str = "scene") -> Scene:
        """The scene of TOML text, as `from_toml` reads it from a file.

        Arguments:
            text: The scene file's text (format as in `from_toml`).
            source: What to call the text in error messages.

        Returns:
            The `Scene`.

        Raises:
            ValueError: For text that is not TOML (naming `source`), and as `from_dict` for its
                data.
        """
        import tomllib

        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as error:
            raise ValueError(f"{source} is not valid TOML: {error}") from None
        return cls.from_dict(data)


# --- Examples -------------------------------------------------------------------------------

EXAMPLES = ("single_touch", "three_touches", "sliding_finger", "non_uniform_background", "repeated_touches_memory")


def example(name: str) -> Scene:
    """A named example scene shipped with diffeit.

    Read from the scene file `example_path(name)`, which can be copied as a starting point for
    a scene of one's own.

    Arguments:
        name: One of `EXAMPLES`, e.g. "single_touch".

    Returns:
        The `Scene`.

    Raises:
        ValueError: For a name not in `EXAMPLES`.
    """
    return Scene.from_toml_string(example_path(name).read_text(), source=f"example {name}")


def example_path(name: str) -> FilePath:
    """The TOML scene file of a named example scene shipped with diffeit.

    Arguments:
        name: One of `EXAMPLES`, e.g. "single_touch".

    Returns:
        The path of the file, inside the installed package (read it, do not write it).

    Raises:
        ValueError: For a name not in `EXAMPLES`.
    """
    if name not in EXAMPLES:
        raise ValueError(f"unknown example scene {name!r}; examples are {EXAMPLES}")
    return FilePath(str(resources.files(__package__).joinpath("examples", f"{name}.toml")))
