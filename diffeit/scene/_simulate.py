"""The simulator: a pipeline of the stages a scene declares, and its result.

`pipeline(scene)` builds the stages from the scene alone: touches, then the memory effect, the
conductivity per frame, the contact impedance per frame (drift, open electrodes), one forward
solve per distinct state, then the instrument (readout mixing, reading gains, noise, common-mode
drift, lost readings). A stage exists only when the scene calls for it: a scene without memory
never runs the integrator, one without noise returns exact voltages, one without readout mixing
keeps no electrode potentials, and a static scene costs one forward solve. Each stage is
a small `equinox.Module`, a pure function of the `State` flowing through (`stage(state) ->
state`), so `simulate` is differentiable in every continuous parameter of the scene (a
`Scene` is a pytree): `jax.grad(lambda s: loss(simulate(s).frames))(scene)`.

Conventions: conductivity in S/sq, times in seconds, voltages in volts, contact impedance in
ohm m. The reference frame is the untouched skin (its background) at the first frame time,
measured like a frame (mixing, gains, noise, drift and lost readings apply to it too).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path as FilePath
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from .. import io
from .._arrays import is_concrete
from ..forward import ForwardModel
from ..memory import MemoryParameters, memory_response
from ..mesh import Mesh, interpolate
from ..protocol import Protocol
from ._instrument import (
    CommonModeDrift,
    ContactDrift,
    MeasurementNoise,
    OpenElectrodes,
    ReadingGains,
    ReadoutMixing,
    add_drift,
    add_noise,
    contact_impedance,
    lost_readings,
    open_contact_impedance,
)
from ._scene import Scene
from ._touches import Touch, stimulus

# Forward solves per batch: one host call each, and one step of the progress bar.
_SOLVES_PER_BATCH = 16
# Sample points per element for touch and background fields (level^2).
_LEVEL = 8


class State(eqx.Module):
    """What flows through the simulator's pipeline; a stage fills or transforms some fields.

    Fields a stage has not filled yet are None.

    Attributes:
        times: (T,) the frame times, seconds.
        background: (E,) the untouched skin's conductivity on the simulation mesh, S/sq.
        stimulus: (T, E) the touches' dsigma/sigma (None without touches).
        response: (T, E) the skin's dsigma/sigma after its memory (the stimulus without
            memory).
        conductivity: (T, E) the sheet conductivity of every frame, S/sq.
        contact_impedance: (T, L) the contact impedance of every frame, ohm m.
        reference_contact_impedance: (L,) the contact impedance of the reference, ohm m.
        frames: (T, M) the readings, volts.
        reference: (M,) the reference frame's readings, volts.
        electrode: (T, D, L) the electrode potentials of every frame and drive, volts, kept
            only when the readout mixes them.
        reference_electrode: (D, L) the reference's electrode potentials, volts, likewise.
        lost: (M,) bool, the readings lost to open electrodes.
        solves: The forward solves run (distinct states, reference included).
    """

    times: jax.Array
    background: jax.Array
    stimulus: jax.Array | None = None
    response: jax.Array | None = None
    conductivity: jax.Array | None = None
    contact_impedance: jax.Array | None = None
    reference_contact_impedance: jax.Array | None = None
    frames: jax.Array | None = None
    reference: jax.Array | None = None
    electrode: jax.Array | None = None
    reference_electrode: jax.Array | None = None
    lost: np.ndarray | None = None
    solves: int = eqx.field(default=0, static=True)

    def replace(self, **changes: Any) -> State:
        """This state with the fields named in `changes` replaced."""
        return dataclasses.replace(self, **changes)


# --- Stages ---------------------------------------------------------------------------------


class Touches(eqx.Module):
    """The stage of the touches: their stimulus dsigma/sigma per frame and element.

    `diffeit.scene.stimulus` on the simulation mesh; the response is the stimulus until a
    `Memory` stage follows.

    Attributes:
        name: The stage's name, as `Simulation.stages` lists it (a class variable).
        mesh: The simulation `Mesh`.
        touches: The scene's `Touch`es.
        surface: The curved skin's surface (`Skin.surface`; centres are moved onto it), or
            None for a flat skin.
    """

    name: ClassVar[str] = "touches"
    mesh: Mesh = eqx.field(static=True)
    touches: tuple[Touch, ...]
    surface: tuple[str, float] | None = eqx.field(default=None, static=True)

    def __call__(self, state: State) -> State:
        """`state` with `stimulus` and `response` set to the touches' stimulus."""
        change = stimulus(self.mesh, self.touches, state.times, level=_LEVEL, surface=self.surface)
        return state.replace(stimulus=change, response=change)


class Memory(eqx.Module):
    """The stage of the skin's viscoelastic memory: the response to the stimulus.

    `diffeit.scene.memory_response` from a rested skin at the first frame time.

    Attributes:
        name: The stage's name, as `Simulation.stages` lists it (a class variable).
        parameters: The `MemoryParameters`.
    """

    name: ClassVar[str] = "memory"
    parameters: MemoryParameters

    def __call__(self, state: State) -> State:
        """`state` with `response` the memory's response to its stimulus (dsigma/sigma)."""
        return state.replace(response=memory_response(state.stimulus, state.times, self.parameters))


class Conductivity(eqx.Module):
    """The stage of the sheet conductivity: sigma = background (1 + response), per frame.

    In S/sq; the background alone in every frame without touches.

    Attributes:
        name: The stage's name, as `Simulation.stages` lists it (a class variable).
    """

    name: ClassVar[str] = "conductivity"

    def __call__(self, state: State) -> State:
        """`state` with `conductivity` (T, E) S/sq.

        Raises:
            ValueError: For a concrete response <= -1 somewhere (a conductivity <= 0).
        """
        if state.response is None:
            conductivity = jnp.broadcast_to(state.background, (len(state.times), len(state.background)))
        else:
            if is_concrete(state.response) and (lowest := float(jnp.min(state.response))) <= -1:
                raise ValueError(
                    f"touches and effects.memory: the skin's response reaches dsigma/sigma = {lowest:.4g} "
                    "(<= -1, a conductivity <= 0); lower the touches' amplitudes or the memory's fractions"
                )
            conductivity = state.background * (1 + state.response)
        return state.replace(conductivity=conductivity)


class ContactImpedance(eqx.Module):
    """The stage of the contact impedance per frame and electrode, ohm m.

    The skin's, drifting when declared (from t = 0), and open electrodes' multiplied by
    `OPEN_FACTOR`; the reference's is that at the first frame time.

    Attributes:
        name: The stage's name, as `Simulation.stages` lists it (a class variable).
        initial: (L,) the skin's contact impedance, ohm m.
        drift: The `ContactDrift`, or None.
        open_electrodes: The indices of the open electrodes (none: an empty tuple).
    """

    name: ClassVar[str] = "contact impedance"
    initial: jax.Array
    drift: ContactDrift | None
    open_electrodes: tuple[int, ...] = eqx.field(static=True)

    def __call__(self, state: State) -> State:
        """`state` with `contact_impedance` (T, L) and `reference_contact_impedance` (L,), ohm m."""
        times = jnp.concatenate([state.times[:1], state.times])
        if self.drift is None:
            z = jnp.broadcast_to(self.initial, (len(times), len(self.initial)))
        else:
            z = contact_impedance(self.initial, times, self.drift)
        if self.open_electrodes:
            z = open_contact_impedance(z, self.open_electrodes)
        return state.replace(reference_contact_impedance=z[0], contact_impedance=z[1:])


class Forward(eqx.Module):
    """The stage of the forward model: the readings of every frame and of the reference.

    One forward solve per distinct state: on concrete inputs, frames whose conductivity and
    contact impedance are equal bit for bit share one solve (a static scene costs one); traced
    inputs (under jax.grad or jit) solve every frame. Solves run in batches of 16 with a
    progress bar when there are many.

    Attributes:
        name: The stage's name, as `Simulation.stages` lists it (a class variable).
        model: The `ForwardModel` of the simulation mesh and the skin's protocol.
        progress: Show a progress bar over the batches of solves (when there are 8 or more).
        potentials: Keep the electrode potentials of every drive (`State.electrode`, volts)
            and form the readings from them with the protocol's weights: a readout that mixes
            needs them.
    """

    name: ClassVar[str] = "forward"
    model: ForwardModel
    progress: bool = eqx.field(default=True, static=True)
    potentials: bool = eqx.field(default=False, static=True)

    def __call__(self, state: State) -> State:
        """`state` with `frames` (T, M), `reference` (M,) (volts), `solves` and, with `potentials`, the potentials."""
        conductivity = jnp.concatenate([state.background[None], state.conductivity])
        z = jnp.concatenate([state.reference_contact_impedance[None], state.contact_impedance])
        if is_concrete(conductivity) and is_concrete(z):
            rows = np.concatenate([np.asarray(conductivity), np.asarray(z)], axis=1)
            _, first, inverse = np.unique(rows, axis=0, return_index=True, return_inverse=True)
            distinct = np.sort(first)
            where = np.argsort(np.argsort(first))[inverse.ravel()]
            voltages = self._solve(conductivity[distinct], z[distinct])[where]
            solves = len(distinct)
        else:
            voltages = self._solve(conductivity, z)
            solves = len(conductivity)
        if not self.potentials:
            return state.replace(reference=voltages[0], frames=voltages[1:], solves=solves)
        protocol = self.model.protocol
        readings = jnp.sum(jnp.asarray(protocol.measure, voltages.dtype) * voltages[:, protocol.drive_index], axis=-1)
        return state.replace(
            reference=readings[0],
            frames=readings[1:],
            reference_electrode=voltages[0],
            electrode=voltages[1:],
            solves=solves,
        )

    def _solve(self, conductivity: jax.Array, z: jax.Array) -> jax.Array:
        """(K, M) readings, or with `potentials` (K, D, L) electrode potentials, volts, of K states."""
        if self.potentials:
            measure = jax.vmap(lambda sigma, z: self.model.potentials(sigma, z).electrode)
        else:
            measure = jax.vmap(self.model.measure)
        count = len(conductivity)
        if count > _SOLVES_PER_BATCH:
            # The last batch padded with copies of the last state: every batch then has one shape,
            # and the solves compile once, not again for the remainder.
            padding = -count % _SOLVES_PER_BATCH
            conductivity = jnp.concatenate([conductivity, jnp.repeat(conductivity[-1:], padding, axis=0)])
            z = jnp.concatenate([z, jnp.repeat(z[-1:], padding, axis=0)])
        starts = range(0, len(conductivity), _SOLVES_PER_BATCH)
        bar = tqdm(
            starts, desc="forward solves", unit="batch", disable=True if len(starts) < 8 or not self.progress else None
        )
        return jnp.concatenate(
            [measure(conductivity[k : k + _SOLVES_PER_BATCH], z[k : k + _SOLVES_PER_BATCH]) for k in bar]
        )[:count]


class MixReadout(eqx.Module):
    """The stage of the mixing readout: frames and reference read from the electrode potentials.

    `diffeit.readout.Readout.readings` with unit gains (the gains are a stage of their own).

    Attributes:
        name: The stage's name, as `Simulation.stages` lists it (a class variable).
        protocol: The skin's `Protocol`.
        mixing: The `ReadoutMixing` effect.
    """

    name: ClassVar[str] = "readout mixing"
    protocol: Protocol = eqx.field(static=True)
    mixing: ReadoutMixing

    def __call__(self, state: State) -> State:
        """`state` with `frames` and `reference` (volts) read through the mixing readout."""
        readout = self.mixing.readout(self.protocol)
        frames = jax.vmap(lambda electrode: readout.readings(self.protocol, electrode))(state.electrode)
        reference = readout.readings(self.protocol, state.reference_electrode)
        return state.replace(frames=frames, reference=reference)


class ApplyGains(eqx.Module):
    """The stage of the reading gains: every reading multiplied by its gain.

    The frames' and the reference's alike; the gains are dimensionless.

    Attributes:
        name: The stage's name, as `Simulation.stages` lists it (a class variable).
        gains: The `ReadingGains` effect.
    """

    name: ClassVar[str] = "reading gains"
    gains: ReadingGains

    def __call__(self, state: State) -> State:
        """`state` with `frames` and `reference` multiplied by the gains."""
        gains = jnp.asarray(self.gains.gains, state.frames.dtype)
        return state.replace(frames=gains * state.frames, reference=gains * state.reference)


class AddDrift(eqx.Module):
    """The stage of the common-mode drift of all readings (`diffeit.scene.add_drift`).

    The frames drift at their times, the reference at the first frame time.

    Attributes:
        name: The stage's name, as `Simulation.stages` lists it (a class variable).
        drift: The `CommonModeDrift` effect.
    """

    name: ClassVar[str] = "common-mode drift"
    drift: CommonModeDrift

    def __call__(self, state: State) -> State:
        """`state` with the drift applied to `frames` and `reference` (volts)."""
        frames = add_drift(state.frames, state.times, self.drift)
        reference = add_drift(state.reference[None], state.times[:1], self.drift)[0]
        return state.replace(frames=frames, reference=reference)


class AddNoise(eqx.Module):
    """The stage of the measurement noise on every reading of the frames and of the reference.

    Independent Gaussian draws from `jax.random.key(seed)`, their scale set by the noise-free
    reference (`diffeit.scene.add_noise`).

    Attributes:
        name: The stage's name, as `Simulation.stages` lists it (a class variable).
        noise: The `MeasurementNoise` effect (its level and seed).
    """

    name: ClassVar[str] = "noise"
    noise: MeasurementNoise

    def __call__(self, state: State) -> State:
        """`state` with noise added to `frames` and `reference` (volts)."""
        frame_key, reference_key = jax.random.split(jax.random.key(self.noise.seed))
        frames = add_noise(state.frames, state.reference, self.noise.noise, frame_key)
        reference = add_noise(state.reference[None], state.reference, self.noise.noise, reference_key)[0]
        return state.replace(frames=frames, reference=reference)


class LostReadings(eqx.Module):
    """The stage of the readings lost to open electrodes: set to the effect's `fill`, volts.

    A reading is lost when it weights an open electrode or its drive sends current through
    one.

    Attributes:
        name: The stage's name, as `Simulation.stages` lists it (a class variable).
        protocol: The skin's `Protocol`.
        open_electrodes: The `OpenElectrodes` effect (the electrodes and the fill value).
    """

    name: ClassVar[str] = "lost readings"
    protocol: Protocol = eqx.field(static=True)
    open_electrodes: OpenElectrodes

    def __call__(self, state: State) -> State:
        """`state` with the lost readings of `frames` and `reference` filled, and `lost` (M,)."""
        lost = lost_readings(self.protocol, self.open_electrodes.electrodes)
        fill = jnp.asarray(self.open_electrodes.fill, dtype=state.frames.dtype)
        return state.replace(
            frames=jnp.where(lost, fill, state.frames), reference=jnp.where(lost, fill, state.reference), lost=lost
        )


Stage = (
    Touches
    | Memory
    | Conductivity
    | ContactImpedance
    | Forward
    | MixReadout
    | ApplyGains
    | AddDrift
    | AddNoise
    | LostReadings
)
"""One stage of the simulator's `pipeline`: an equinox Module, a pure function `State -> State`."""


def pipeline(scene: Scene, *, progress: bool = True) -> tuple[Stage, ...]:
    """The stages that simulate a scene, in order: only those its touches and effects call for.

    Touches, memory, conductivity, contact impedance, the forward solves, then the instrument:
    readout mixing, reading gains, noise, common-mode drift, lost readings
    (docs/science.md#simulation-order). `simulate` runs them.

    Arguments:
        scene: The `Scene`.
        progress: Show a progress bar over the forward solves of long scenes.

    Returns:
        The stages, a tuple of `Stage`s.
    """
    mesh = scene.simulation_mesh()
    skin = scene.skin
    stages: list[Stage] = []
    if scene.touches:
        stages.append(Touches(mesh, scene.touches, skin.surface))
        memory = scene.effect("memory")
        if memory is not None:
            stages.append(Memory(memory))
    stages.append(Conductivity())
    opened = scene.effect("open_electrode")
    stages.append(
        ContactImpedance(
            skin.contact_impedances(), scene.effect("contact_drift"), () if opened is None else opened.electrodes
        )
    )
    model = ForwardModel(mesh, skin.make_protocol(), skin.contact_impedances(), drive_current=skin.drive_current)
    mixing = scene.effect("readout_mixing")
    stages.append(Forward(model, progress, potentials=mixing is not None))
    # The board's order: mixing of the potentials, then each reading's gain (then |.| on a
    # board of magnitudes: the simulator's readings are signed), then noise, whose scale is the
    # reference as the board reads it.
    if mixing is not None:
        stages.append(MixReadout(model.protocol, mixing))
    gains = scene.effect("reading_gains")
    if gains is not None:
        stages.append(ApplyGains(gains))
    # Noise before drift: its scale is the percentage of RMS(V_ref) of the drift-free reference.
    noise = scene.effect("noise")
    if noise is not None:
        stages.append(AddNoise(noise))
    drift = scene.effect("common_mode_drift")
    if drift is not None:
        stages.append(AddDrift(drift))
    if opened is not None:
        stages.append(LostReadings(model.protocol, opened))
    return tuple(stages)


# --- Simulation -----------------------------------------------------------------------------


class Simulation(eqx.Module):
    """A simulated scene: what a recording would hold, with the ground truth.

    Arrays stay JAX arrays, so gradients flow through `simulate`; `save` writes a frames file
    of `diffeit.io` and `read_simulation` reads it back.

    Attributes:
        scene: The `Scene` simulated.
        mesh: The simulation `Mesh`.
        protocol: The skin's `Protocol`.
        times: (T,) the frame times, seconds.
        frames: (T, M) the readings, volts, in the protocol's order and sign.
        reference: (M,) the untouched skin's readings at the first frame time, volts.
        truth: (T, E) the true sheet conductivity per frame on `mesh`, S/sq; `truth_on`
            interpolates it onto a reconstruction mesh.
        lost: (M,) bool, the readings lost to open electrodes (None without them).
        stages: The names of the stages run, in order.
        solves: The number of forward solves run.
    """

    scene: Scene
    mesh: Mesh = eqx.field(static=True)
    protocol: Protocol = eqx.field(static=True)
    times: jax.Array
    frames: jax.Array
    reference: jax.Array
    truth: jax.Array
    lost: np.ndarray | None
    stages: tuple[str, ...] = eqx.field(static=True)
    solves: int = eqx.field(static=True)

    def truth_on(self, mesh: Mesh) -> np.ndarray:
        """The true conductivity on another mesh of the same skin, conservatively interpolated.

        `diffeit.mesh.interpolate`: the area-weighted means over the overlaps.

        Arguments:
            mesh: The target `Mesh` (a reconstruction mesh), E' elements.

        Returns:
            (T, E') the true conductivity, S/sq.

        Raises:
            ValueError: For a mesh with elements outside the simulation mesh.
        """
        return interpolate(np.asarray(self.truth), self.mesh, mesh)

    def truth_change_on(self, mesh: Mesh) -> np.ndarray:
        """The true conductivity change from the untouched skin, on another mesh of the same skin.

        The truth less the background, conservatively interpolated (`truth_on`).

        Arguments:
            mesh: The target `Mesh` (a reconstruction mesh), E' elements.

        Returns:
            (T, E') dsigma, S/sq.

        Raises:
            ValueError: For a mesh with elements outside the simulation mesh.
        """
        background = np.asarray(self.scene.background.values_on(self.mesh, level=_LEVEL))
        return interpolate(np.asarray(self.truth) - background, self.mesh, mesh)

    def to_recording(self) -> io.Recording:
        """The simulation as a `diffeit.io.Recording`, what `save` writes.

        Frames, times, reference, the simulation mesh with the truth as its images
        ("conductivity", S/sq), the reconstruction mesh's geometry, and the scene, the stages,
        the solves and the lost readings in the provenance metadata.

        Returns:
            The `diffeit.io.Recording`.
        """
        skin = self.scene.skin
        metadata = {
            "scene": self.scene.to_dict(),
            "images": "ground truth: the true sheet conductivity on the simulation mesh",
            "stages": list(self.stages),
            "solves": self.solves,
            "lost_readings": [] if self.lost is None else np.flatnonzero(self.lost).tolist(),
        }
        return io.Recording(
            frames=np.asarray(self.frames),
            times=np.asarray(self.times),
            protocol=self.protocol,
            reference=np.asarray(self.reference),
            mesh=self.mesh,
            # diffeit.io names flat generators only: a curved skin's file holds its mesh alone.
            geometry=skin.geometry_with_h(skin.h),
            provenance={"source": f"diffeit simulate {self.scene.name}".rstrip(), "metadata": metadata},
            images=np.asarray(self.truth),
            image_quantity="conductivity",
        )

    def save(self, path: str | FilePath, *, overwrite: bool = False) -> FilePath:
        """Write the simulation to a new frames file (`diffeit.io.write_frames`).

        Arguments:
            path: The file to write.
            overwrite: Replace an existing file at `path`.

        Returns:
            `path`, as a `Path`.

        Raises:
            FileExistsError: For an existing `path` without `overwrite=True`.
            FileNotFoundError: When the folder of `path` does not exist.
        """
        return io.write_frames(path, self.to_recording(), overwrite=overwrite)


def read_simulation(path: str | FilePath) -> Simulation:
    """Read back a `Simulation` saved by `Simulation.save`, identically.

    Arguments:
        path: The frames file.

    Returns:
        The `Simulation`.

    Raises:
        FileNotFoundError: For a missing file.
        ValueError: For a file `diffeit.io.read_frames` refuses, or a frames file that is not
            a simulation (no scene, truth or mesh).
    """
    recording = io.read_frames(path)
    metadata = recording.provenance.get("metadata", {})
    if "scene" not in metadata or recording.images is None or recording.mesh is None:
        raise ValueError(f"{path} is a frames file but not a simulation (no scene, truth or mesh)")
    lost = None
    if metadata["scene"].get("effects", {}).get("open_electrode") is not None:
        lost = np.zeros(recording.n_measurements, dtype=bool)
        lost[metadata["lost_readings"]] = True
    return Simulation(
        scene=Scene.from_dict(metadata["scene"]),
        mesh=recording.mesh,
        protocol=recording.protocol,
        times=jnp.asarray(recording.times),
        frames=jnp.asarray(recording.frames),
        reference=jnp.asarray(recording.reference),
        truth=jnp.asarray(recording.images),
        lost=lost,
        stages=tuple(metadata["stages"]),
        solves=int(metadata["solves"]),
    )


def simulate(scene: Scene, *, progress: bool = True) -> Simulation:
    """Simulate a scene: the frames a skin would record, with the ground truth.

    Builds the scene's `pipeline` (only the stages its touches and effects call for) and runs
    the stages in order: touches, memory, conductivity, contact impedance, one forward solve
    per distinct state, then the instrument (readout mixing, reading gains, noise, common-mode
    drift, lost readings). The reference frame is the untouched skin at the first frame time,
    measured like a frame.
    Differentiable in every continuous parameter of the scene (a `Scene` is a pytree):
    `jax.grad(lambda s: loss(simulate(s).frames))(scene)`. The order and its reasons are in
    docs/science.md#simulation-order.

    Arguments:
        scene: The `Scene` to simulate.
        progress: Show a progress bar over the forward solves of long scenes.

    Returns:
        The `Simulation`: frames (T, M) and reference (M,) in volts, times in seconds, the true
        conductivity (T, E) in S/sq on the simulation mesh.

    Raises:
        ValueError: For a `scene` that is not a `Scene`.
    """
    if not isinstance(scene, Scene):
        raise ValueError(f"simulate needs a diffeit.Scene; got {type(scene).__name__}")
    stages = pipeline(scene, progress=progress)
    forward = _forward(stages)
    mesh = forward.model.mesh
    state = State(times=jnp.asarray(scene.times), background=scene.background.values_on(mesh, level=_LEVEL))
    for stage in stages:
        state = stage(state)
    return Simulation(
        scene=scene,
        mesh=mesh,
        protocol=forward.model.protocol,
        times=state.times,
        frames=state.frames,
        reference=state.reference,
        truth=state.conductivity,
        lost=state.lost,
        stages=tuple(stage.name for stage in stages),
        solves=state.solves,
    )


def _forward(stages: Sequence[Stage]) -> Forward:
    return next(stage for stage in stages if isinstance(stage, Forward))
