"""The joint fit: background map, contact impedances, memory parameters and per-frame stimulus
images together, every frame's misfit through the forward model with the memory model in the loop.

Frame k is measured from sigma_k = b (1 + r_k), r = memory_response(a, times, p): b the
background map, a the memoryless stimulus, r the response, p the memory parameters, and one
contact impedance per electrode shared by all frames. `JointProblem` is the objective J (misfit
plus the priors of `JointPriors`), `joint` minimises it by L-BFGS from a start taken from the
data (`_initial_values`). The objective, its priors, the unknowns' transforms, the
preconditioner and the initialisation, with the measurements behind each choice, are in
docs/science.md#joint-fit; what the data determine is in
docs/tutorials/fitting.md#identifiability.
"""

from __future__ import annotations

import dataclasses
import json
import os
import warnings
from collections.abc import Callable, Collection, Mapping
from functools import partial
from pathlib import Path
from typing import Any

import equinox as eqx
import h5py
import jax
import jax.numpy as jnp
import numpy as np

from .._arrays import concrete_floats, readonly
from .._precision import ensure_float64
from ..forward import ForwardModel
from ..inverse import AbstractSolver, OneStep, Solution
from ..inverse.linearised import check_frames
from ..inverse.solution import finished, model_of
from ..io import create_checked, read_attributes, read_checked, write_atomically, write_attributes
from ..memory import MemoryParameters, memory_response, over_foam
from ..mesh import centroid_distances, element_adjacency
from ..results import RESULTS, messages, names, throw_if_failed
from ._background import background as fit_background
from ._memory import (
    DEFAULT_FREE,
    MEMORY_FIELDS,
    check_times,
    correct_memory,
    memory_from_unconstrained,
    memory_to_unconstrained,
    reported_memory,
)
from ._memory import memory as fit_memory
from ._optimise import History, Minimum, minimise

GROUPS = ("background", "contact_impedance", "memory", "stimulus")
# The noise, percent of the RMS of the reference, when neither the caller nor the background fit
# gives it: diffeit's "medium", the order of a skin readout's noise at rest.
DEFAULT_NOISE = 0.5
# The smooth floor of 1 + response, and how far (in ln) a trial step may take a conductivity
# from the median background or a contact impedance from 1 ohm m (docs/science.md#joint-fit).
_FLOOR = 0.01
_CONTRAST = 15.0
_CONTRAST_Z = 30.0
# Added to every curvature of `JointProblem.scales`: an unknown the objective does not see at all
# keeps a finite unit.
_TINY_CURVATURE = 1e-12
# The initial one-step images' hyperparameter per unit of noise fraction, the least
# hyperparameter of the images the memory parameters start from, and the soft threshold of
# image-derived stimuli in units of their median |a| (docs/science.md#joint-fit, Initialisation).
_IMAGE_REGULARISATION = 20.0
_MEMORY_IMAGE_REGULARISATION = 0.3
_THRESHOLD = 3.0
# Time constants within this factor of each other are one mode split in two; a mode with a
# smaller fraction is one the images did not show (docs/science.md#joint-fit, Initialisation).
_MERGED = 2.0
_LEAST_FRACTION = 0.05
_SCHEMA = "diffeit.joint_fit"
# Version 2: the stimulus priors charge changes (version 1 files were fitted with per-frame ones).
_SCHEMA_VERSION = 2


class JointPriors(eqx.Module):
    """The weights of the joint fit's priors, in units of one frame's misfit at the noise level.

    Each weight multiplies one prior term of the objective J of `joint` (the terms and the
    symbols are in docs/science.md#joint-fit). Every field is a number >= 0.

    Attributes:
        background: w_b, smoothness of ln b (its Dirichlet energy, dimensionless).
        stimulus: w_a, sparsity of the stimulus in every frame: the cost per frame of a unit
            stimulus over the sheet. Default 0: it charges a held touch for every frame it
            lasts and so biases the memory.
        stimulus_variation: w_v, the changes' total variation in space (compact presses).
        stimulus_change: w_t, sparsity of the stimulus' changes from frame to frame (presses,
            releases): the cost of a unit change over the sheet.
        memory: w_p, the pull of each free memory parameter (unconstrained) to its start: a
            deviation of 1/sqrt(w_p) costs one frame's misfit.
        contact_impedance: w_z, the pull of ln z to its start, likewise.
        smoothing: eps of the smoothed |x| (dsigma/sigma, > 0): the sparsity terms are quadratic
            below it, which keeps the objective smooth for L-BFGS.
        change_scale: c of the temporal term's psi (dsigma/sigma, >= 0; 0 makes it the total
            variation in time): changes larger than c cost only logarithmically more.

    Raises:
        ValueError: For a weight that is not a finite number >= 0, or a smoothing of 0.
    """

    background: float = eqx.field(default=0.1, static=True)
    stimulus: float = eqx.field(default=0.0, static=True)
    stimulus_variation: float = eqx.field(default=2.0, static=True)
    stimulus_change: float = eqx.field(default=200.0, static=True)
    memory: float = eqx.field(default=0.1, static=True)
    contact_impedance: float = eqx.field(default=1.0, static=True)
    smoothing: float = eqx.field(default=0.005, static=True)
    change_scale: float = eqx.field(default=0.02, static=True)

    def __check_init__(self) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, bool) or not (isinstance(value, int | float) and np.isfinite(value) and value >= 0):
                raise ValueError(f"JointPriors.{field.name} must be a finite number >= 0; got {value!r}")
        if self.smoothing <= 0:
            raise ValueError(f"JointPriors.smoothing must be positive (dsigma/sigma); got {self.smoothing}")


class JointParameters(eqx.Module):
    """The joint fit's unknowns in the unconstrained space the optimiser works in.

    Attributes:
        log_background: (E,) ln of the background conductivity in S/sq.
        log_contact_impedance: (L,) ln of the contact impedance in ohm m.
        memory: The free memory parameters, unconstrained (`diffeit.fit.memory`'s transform),
            by field name.
        stimulus: (T, E) the memoryless stimulus dsigma/sigma (unconstrained as it is).
    """

    log_background: jax.Array
    log_contact_impedance: jax.Array
    memory: dict[str, jax.Array]
    stimulus: jax.Array

    def group(self, name: str) -> Any:
        """The unknowns of one group.

        Arguments:
            name: One of `GROUPS`: "background", "contact_impedance", "memory" or "stimulus".

        Returns:
            The group's field: `log_background`, `log_contact_impedance`, `memory` or
            `stimulus`.

        Raises:
            KeyError: For a name not in `GROUPS`.
        """
        return getattr(self, _FIELDS[name])

    def with_groups(self, groups: Mapping[str, Any]) -> JointParameters:
        """These parameters with some groups replaced.

        Arguments:
            groups: New values by group name (of `GROUPS`), each of its field's structure.

        Returns:
            The new `JointParameters`; the groups not named keep their values.

        Raises:
            KeyError: For a name not in `GROUPS`.
        """
        return dataclasses.replace(self, **{_FIELDS[name]: value for name, value in groups.items()})


_FIELDS = {
    "background": "log_background",
    "contact_impedance": "log_contact_impedance",
    "memory": "memory",
    "stimulus": "stimulus",
}


class JointSettings(eqx.Module):
    """What defines the joint fit's objective besides the data, kept to resume a fit.

    Attributes:
        free: The groups of `GROUPS` fitted.
        memory_free: The memory fields fitted when "memory" is free.
        priors: `JointPriors`.
        data_scale: s, volts (the noise standard deviation the misfit is measured in), a
            scalar array.
        memory_centre: The memory prior's centre (`MemoryParameters`; the fixed fields'
            values), its fields arrays.
        log_contact_impedance_centre: (L,) the contact prior's centre, ln(ohm m).
    """

    free: tuple[str, ...] = eqx.field(static=True)
    memory_free: tuple[str, ...] = eqx.field(static=True)
    priors: JointPriors
    data_scale: jax.Array
    memory_centre: MemoryParameters
    log_contact_impedance_centre: jax.Array

    def __init__(
        self,
        free: Collection[str],
        memory_free: Collection[str],
        priors: JointPriors,
        data_scale: float | jax.Array,
        memory_centre: MemoryParameters,
        log_contact_impedance_centre: jax.Array,
    ) -> None:
        self.free = tuple(free)
        self.memory_free = tuple(memory_free)
        self.priors = priors
        # Arrays, not Python floats: a float is static to jit and would be compiled into the
        # fit's programs, so that every fit of other data or from another start compiled again.
        self.data_scale = jnp.asarray(data_scale, float)
        self.memory_centre = jax.tree_util.tree_map(lambda value: jnp.asarray(value, float), memory_centre)
        self.log_contact_impedance_centre = jnp.asarray(log_contact_impedance_centre)

    @property
    def memory_fitted(self) -> tuple[str, ...]:
        """The memory fields the fit moves: `memory_free`, or none when "memory" is not free."""
        return self.memory_free if "memory" in self.free else ()


@dataclasses.dataclass(frozen=True)
class JointProgress:
    """A joint fit while it runs, as `joint` hands it to its `on_step`.

    Attributes:
        steps: The accepted steps so far, a resumed fit's earlier ones included (its history's
            length less one).
        objective: J at the current iterate (in units of one frame's misfit at the noise
            level).
        fit: Builds the `JointFit` of the current iterate, its `result`
            `RESULTS.max_iterations_reached` (unfinished): what `JointFit.save` writes as a
            checkpoint, and `joint(..., initial=load(path))` resumes. Built when called, for
            about the cost of one objective evaluation.
    """

    steps: int
    objective: float
    fit: Callable[[], JointFit]


class JointFit(eqx.Module):
    """The result of `joint`: the fitted skin, the stimulus of every frame, and what resuming needs.

    `save(path)` writes the fit to an HDF5 file; `diffeit.fit.load(path)` reads it back, and
    `joint(..., initial=fit)` resumes from it.

    Attributes:
        background: (E,) background conductivity b, S/sq.
        contact_impedance: (L,) contact impedance per electrode, ohm m.
        memory: The memory parameters (`diffeit.memory.MemoryParameters`); with both modes
            fitted, the quicker one is named fast (`diffeit.fit.ordered_modes`).
        stimulus: (T, E) the memoryless stimulus dsigma/sigma per frame (touches < 0).
        response: (T, E) the skin's response dsigma/sigma, the memory model applied to the
            stimulus: frame k's conductivity is background * (1 + response[k]).
        times: (T,) the frame times, seconds.
        misfit: The relative misfit ||V - v|| / ||v|| over all frames and readings.
        history: `History`: objective and gradient norm per accepted step (a resumed fit
            continues the history of the fit it started from).
        result: `RESULTS.successful`, `max_iterations_reached`, `stalled` or `nonfinite`.
        parameters: `JointParameters`, the unconstrained unknowns, what a resumed fit starts
            from.
        settings: `JointSettings`, what defines the objective besides the data (kept to resume).
    """

    background: jax.Array
    contact_impedance: jax.Array
    memory: MemoryParameters
    stimulus: jax.Array
    response: jax.Array
    times: jax.Array
    misfit: float
    history: History
    result: RESULTS
    parameters: JointParameters
    settings: JointSettings

    def save(self, path: str | os.PathLike, *, overwrite: bool = False) -> Path:
        """Write the fit to `path` (HDF5, schema "diffeit.joint_fit") and return the path.

        The file is written under a temporary name and renamed when complete, so an interrupted
        save leaves the old file (or none) at `path`. Every dataset carries a checksum
        (`diffeit.io`). Datasets: `background`, `contact_impedance`, `stimulus`, `response`, `times`,
        `memory/<field>`, `history/objective`, `history/gradient_norm`, and what resuming needs:
        `parameters/...` (the unconstrained unknowns), `settings/memory_centre/<field>` and
        `settings/log_contact_impedance_centre`. Attributes: schema, schema_version, result
        (its name), misfit, free, memory_free, priors (JSON), data_scale (volts).

        Arguments:
            path: The file to write.
            overwrite: Replace an existing file (True), or refuse it (False).

        Returns:
            The path written, as a `Path`.

        Raises:
            FileExistsError: For an existing file without `overwrite=True`.
            FileNotFoundError: When the folder of `path` does not exist.
        """
        settings, parameters = self.settings, self.parameters

        def write(file: h5py.File) -> None:
            write_attributes(
                file,
                {
                    "schema": _SCHEMA,
                    "schema_version": _SCHEMA_VERSION,
                    "result": names(self.result)[0],
                    "misfit": self.misfit,
                    "free": json.dumps(list(settings.free)),
                    "memory_free": json.dumps(list(settings.memory_free)),
                    "priors": json.dumps(dataclasses.asdict(settings.priors)),
                    "data_scale": float(settings.data_scale),
                },
            )
            for name in ("background", "contact_impedance", "stimulus", "response", "times"):
                create_checked(file, name, np.asarray(getattr(self, name)))
            _write_memory(file.create_group("memory"), self.memory)
            create_checked(file, "history/objective", self.history.objective)
            create_checked(file, "history/gradient_norm", self.history.gradient_norm)
            for name in ("log_background", "log_contact_impedance", "stimulus"):
                create_checked(file, f"parameters/{name}", np.asarray(getattr(parameters, name)))
            group = file.create_group("parameters/memory")
            for name, value in parameters.memory.items():
                create_checked(group, name, np.asarray(value))
            _write_memory(file.create_group("settings/memory_centre"), settings.memory_centre)
            create_checked(
                file, "settings/log_contact_impedance_centre", np.asarray(settings.log_contact_impedance_centre)
            )

        return write_atomically(path, write, overwrite=overwrite)


def load(path: str | os.PathLike) -> JointFit:
    """Read back a `JointFit` written by `JointFit.save`.

    To inspect a fit, or to resume it with `joint(..., initial=fit)`. A fit saved before diffeit
    stored checksums reads with a `diffeit.io.NoChecksumWarning`.

    Arguments:
        path: The file `JointFit.save` wrote.

    Returns:
        The `JointFit`.

    Raises:
        FileNotFoundError: For a missing file.
        ValueError: Naming the file, for anything but a sound joint fit: empty, not HDF5,
            truncated, altered bytes (a failed checksum), another schema or version, missing or
            non-numeric datasets.

    Warns:
        diffeit.PrecisionWarning: When loading turns on `jax_enable_x64`: the fit's float64
            numbers are returned as they are, never rounded to float32.
    """
    path = Path(path)
    ensure_float64()

    def read(file: h5py.File) -> JointFit:
        try:
            return _read_fit(file, path)
        except (KeyError, TypeError, json.JSONDecodeError) as error:
            raise ValueError(f"{path} is not a complete joint fit: {error}") from None

    return read_checked(path, read, what="joint fit")


def _read_fit(file: h5py.File, path: Path) -> JointFit:
    attributes = read_attributes(file)
    schema = attributes.get("schema")
    if schema != _SCHEMA:
        raise ValueError(f"{path} is not a joint fit (schema {schema!r}, not {_SCHEMA!r})")
    version = int(attributes["schema_version"])
    if version != _SCHEMA_VERSION:
        older = " (its priors were charged per frame and mean otherwise now: fit again)" if version < 2 else ""
        newer = " (a newer diffeit wrote it?)" if version > _SCHEMA_VERSION else ""
        raise ValueError(f"{path} has schema version {version}; this diffeit reads {_SCHEMA_VERSION}{older}{newer}")

    def values(name: str) -> np.ndarray:
        if not isinstance(file.get(name), h5py.Dataset):
            raise ValueError(f"{path} is not a complete joint fit: the dataset {name!r} is missing")
        if not np.issubdtype(file[name].dtype, np.number):
            raise ValueError(f"{path}: the dataset {name!r} holds {file[name].dtype}, not numbers")
        return file[name][()]

    def array(name: str) -> jax.Array:
        return jnp.asarray(values(name))

    def memory(group: str) -> MemoryParameters:
        read = {name: values(f"{group}/{name}") for name in MEMORY_FIELDS}
        return MemoryParameters(**{name: float(v) if np.ndim(v) == 0 else jnp.asarray(v) for name, v in read.items()})

    result = str(attributes["result"])
    if result not in RESULTS._name_to_item:
        raise ValueError(f"{path}: result {result!r} is not a diffeit.results.RESULTS code")
    if not isinstance(file.get("parameters/memory"), h5py.Group):
        raise ValueError(f"{path} is not a complete joint fit: the group 'parameters/memory' is missing")
    settings = JointSettings(
        free=tuple(json.loads(attributes["free"])),
        memory_free=tuple(json.loads(attributes["memory_free"])),
        priors=JointPriors(**json.loads(attributes["priors"])),
        data_scale=float(attributes["data_scale"]),
        memory_centre=memory("settings/memory_centre"),
        log_contact_impedance_centre=array("settings/log_contact_impedance_centre"),
    )
    parameters = JointParameters(
        log_background=array("parameters/log_background"),
        log_contact_impedance=array("parameters/log_contact_impedance"),
        memory={name: array(f"parameters/memory/{name}") for name in file["parameters/memory"]},
        stimulus=array("parameters/stimulus"),
    )
    return JointFit(
        background=array("background"),
        contact_impedance=array("contact_impedance"),
        memory=memory("memory"),
        stimulus=array("stimulus"),
        response=array("response"),
        times=array("times"),
        misfit=float(attributes["misfit"]),
        history=History(values("history/objective"), values("history/gradient_norm")),
        result=getattr(RESULTS, result),
        parameters=parameters,
        settings=settings,
    )


def _write_memory(group: h5py.Group, memory: MemoryParameters) -> None:
    for name in MEMORY_FIELDS:
        create_checked(group, name, np.asarray(getattr(memory, name), dtype=float))


# --- The objective --------------------------------------------------------------------------------


def _log_floored(x: jax.Array) -> jax.Array:
    """ln f(x) for the smooth floor f(x) = _FLOOR softplus(x / _FLOOR): ln x to rounding above
    x = 0.2, ln _FLOOR + x / _FLOOR far below 0; finite and differentiable everywhere."""
    u = x / _FLOOR
    # softplus(u) underflows below u = -745; below -30, ln softplus(u) = u to rounding.
    return jnp.log(_FLOOR) + jnp.where(u > -30.0, jnp.log(jax.nn.softplus(jnp.maximum(u, -30.0))), u)


def _few_changes(size: jax.Array, scale: float) -> jax.Array:
    """scale ln(1 + size / scale): |x| for small changes, growing only logarithmically beyond
    `scale`, so that one large change costs less than the same change in several steps (0: |x|)."""
    return size if scale == 0 else scale * jnp.log1p(size / scale)


def _smoothed_abs(x: jax.Array, eps: float) -> jax.Array:
    return jnp.sqrt(x * x + eps * eps) - eps


class _OfGroups(eqx.Module):
    """J as a function of the free groups alone (the others held at `start`): a Module, not a
    closure, so that the next fit of the same shapes reuses the compiled optimiser step."""

    problem: JointProblem
    start: JointParameters

    def __call__(self, groups: Mapping[str, Any]) -> jax.Array:
        return self.problem(self.start.with_groups(groups))


class JointProblem(eqx.Module):
    """The joint fit's objective J as a function of `JointParameters`.

    `problem(parameters)` is J (docs/science.md#joint-fit), in units of one frame's misfit at
    the noise level; `problem.terms(parameters)` its parts by name (the misfit and each prior);
    `problem.state(parameters)` the background, contact impedance, memory and response;
    `problem.voltages(parameters)` the frames' readings. All are pure JAX (jit, grad). The
    constructor takes the data as they are: `joint` checks them.

    Arguments:
        model: The `ForwardModel` of the fit's mesh and protocol.
        frames: (T, M) the recorded readings, volts.
        times: (T,) the frame times, seconds.
        settings: The `JointSettings`: free groups, priors, data scale and prior centres.

    Attributes:
        model: The forward model.
        frames: (T, M) the readings, volts.
        times: (T,) the frame times, seconds.
        settings: The `JointSettings`.
        area_fractions: (E,) each element's share A_e / A of the sheet's area.
        neighbours: (first, second), two (P,) index arrays: the P pairs of elements that share
            an edge.
        edge_weights: (P,) l_ij / d_ij, the shared edge's length over the distance of the
            centroids along the sheet (`diffeit.mesh.centroid_distances`; the background
            prior's weights).
        edge_lengths: (P,) l_ij / sqrt(A), the shared edge's length relative to the sheet's
            size (the total variation's weights).
    """

    model: ForwardModel
    frames: jax.Array
    times: jax.Array
    settings: JointSettings
    area_fractions: jax.Array
    neighbours: tuple[jax.Array, jax.Array]
    edge_weights: jax.Array
    edge_lengths: jax.Array

    def __init__(self, model: ForwardModel, frames: jax.Array, times: jax.Array, settings: JointSettings) -> None:
        self.model = model
        self.frames = jnp.asarray(frames)
        self.times = jnp.asarray(times)
        self.settings = settings
        mesh = model.mesh
        area = mesh.element_areas.sum()
        self.area_fractions = jnp.asarray(mesh.element_areas / area)
        first, second, lengths = element_adjacency(mesh)
        self.neighbours = (jnp.asarray(first), jnp.asarray(second))
        self.edge_weights = jnp.asarray(lengths / centroid_distances(mesh))
        self.edge_lengths = jnp.asarray(lengths / np.sqrt(area))

    def _response(self, parameters: JointParameters) -> tuple[MemoryParameters, jax.Array]:
        memory = memory_from_unconstrained(parameters.memory, self.settings.memory_centre)
        return memory, memory_response(parameters.stimulus, self.times, memory)

    def state(self, parameters: JointParameters) -> tuple[jax.Array, jax.Array, MemoryParameters, jax.Array]:
        """The skin the unknowns describe.

        Arguments:
            parameters: The `JointParameters`.

        Returns:
            (background, contact impedance, memory, response): (E,) S/sq, (L,) ohm m, the
            `MemoryParameters` (the free fields from `parameters`, the others the memory
            prior's centre) and (T, E) dsigma/sigma.
        """
        memory, response = self._response(parameters)
        return jnp.exp(parameters.log_background), jnp.exp(parameters.log_contact_impedance), memory, response

    def log_conductivity(self, parameters: JointParameters) -> jax.Array:
        """The log conductivity of every frame: ln b + ln(1 + r).

        1 + r enters through a smooth floor at 0.01, and the result is held within a factor
        e^15 of the median background (docs/science.md#joint-fit), so every trial step is
        solvable.

        Arguments:
            parameters: The `JointParameters`.

        Returns:
            (T, E) ln sigma, ln(S/sq).
        """
        log_sigma = parameters.log_background + _log_floored(1 + self._response(parameters)[1])
        middle = jax.lax.stop_gradient(jnp.median(parameters.log_background))
        return jnp.clip(log_sigma, middle - _CONTRAST, middle + _CONTRAST)

    def voltages(self, parameters: JointParameters) -> jax.Array:
        """The model's readings of every frame.

        The contact impedance is held within a factor e^30 of 1 ohm m.

        Arguments:
            parameters: The `JointParameters`.

        Returns:
            (T, M) readings, volts.
        """
        sigma = jnp.exp(self.log_conductivity(parameters))
        z = jnp.exp(jnp.clip(parameters.log_contact_impedance, -_CONTRAST_Z, _CONTRAST_Z))
        return jax.vmap(self.model.measure, in_axes=(0, None))(sigma, z)

    def terms(self, parameters: JointParameters) -> dict[str, jax.Array]:
        """The misfit and each prior term of J, by name; their sum is J.

        Arguments:
            parameters: The `JointParameters`.

        Returns:
            Scalars by name, in units of one frame's misfit at the noise level: "misfit",
            "background", "stimulus", "stimulus_variation", "stimulus_change", "memory" and
            "contact_impedance" (the weights of `JointPriors` included).
        """
        settings, priors = self.settings, self.settings.priors
        residual = (self.voltages(parameters) - self.frames) / settings.data_scale
        first, second = self.neighbours
        log_b = parameters.log_background
        stimulus = parameters.stimulus
        change = jnp.diff(stimulus, axis=0, prepend=jnp.zeros_like(stimulus[:1]))
        jumps = change[:, first] - change[:, second]
        centre = memory_to_unconstrained(settings.memory_centre, parameters.memory)
        memory = [jnp.mean((value - centre[name]) ** 2) for name, value in parameters.memory.items()]
        contact = jnp.mean((parameters.log_contact_impedance - settings.log_contact_impedance_centre) ** 2)
        eps = priors.smoothing
        return {
            "misfit": jnp.sum(residual**2) / self.frames.shape[1],
            "background": priors.background * jnp.sum(self.edge_weights * (log_b[first] - log_b[second]) ** 2),
            "stimulus": priors.stimulus * jnp.sum(self.area_fractions * _smoothed_abs(stimulus, eps)),
            "stimulus_variation": priors.stimulus_variation * jnp.sum(self.edge_lengths * _smoothed_abs(jumps, eps)),
            "stimulus_change": priors.stimulus_change
            * jnp.sum(self.area_fractions * _few_changes(_smoothed_abs(change, eps), priors.change_scale)),
            "memory": priors.memory * sum(memory, start=jnp.zeros(())),
            "contact_impedance": priors.contact_impedance * contact,
        }

    def __call__(self, parameters: JointParameters) -> jax.Array:
        """J at `parameters`: the sum of `terms`, a scalar."""
        return sum(self.terms(parameters).values(), start=jnp.zeros(()))

    def scales(self, parameters: JointParameters) -> JointParameters:
        """The optimiser's unit of each unknown: 1 / sqrt of the objective's curvature there.

        The curvature at `parameters` (docs/science.md#joint-fit) is the misfit's Gauss-Newton
        diagonal from the Jacobian at the frames' mean conductivity, plus the priors' curvature
        (the sparsity terms' largest, at zero): a diagonal preconditioner.

        Arguments:
            parameters: The `JointParameters` (the start).

        Returns:
            The units, as `JointParameters` of the same structure.
        """
        settings, priors = self.settings, self.settings.priors
        n_frames, n_readings = self.frames.shape
        weight = 2 / (n_readings * settings.data_scale**2)
        log_sigma = self.log_conductivity(parameters)
        sigma = jnp.exp(jnp.mean(log_sigma, axis=0))
        z = jnp.exp(parameters.log_contact_impedance)
        jacobian = self.model.jacobian(sigma, z, wrt="log_conductivity")  # (M, E)
        sensitivity = weight * jnp.sum(jacobian**2, axis=0)  # (E,), per frame
        background = n_frames * sensitivity + 2 * priors.background * self._per_element(self.edge_weights)
        # a_k enters two changes (c_k and c_(k+1)), and each change's variation over every edge
        # of its element: hence 2 and 2 x 2.
        sparsity = (priors.stimulus + 2 * priors.stimulus_change) * self.area_fractions
        sparsity = (sparsity + 4 * priors.stimulus_variation * self._per_element(self.edge_lengths)) / priors.smoothing
        stimulus = jnp.broadcast_to(sensitivity + sparsity, parameters.stimulus.shape)
        contact_jacobian = self.model.jacobian(sigma, z, wrt="contact_impedance") * z  # (M, L)
        contact = n_frames * weight * jnp.sum(contact_jacobian**2, axis=0) + 2 * priors.contact_impedance / len(z)
        memory = {}
        for name, value in parameters.memory.items():
            # Elements are independent in the memory model: a tangent of ones gives every
            # element's derivative of ln sigma, for a shared field and for a per-element one.
            tangent = {other: jnp.zeros_like(v) for other, v in parameters.memory.items()}
            tangent[name] = jnp.ones_like(value)
            _, derivative = jax.jvp(
                lambda values: self.log_conductivity(dataclasses.replace(parameters, memory=values)),
                (dict(parameters.memory),),
                (tangent,),
            )  # (T, E)
            if jnp.size(value) == 1:
                curvature = weight * jnp.sum((derivative @ jacobian.T) ** 2)
            else:
                curvature = jnp.sum(derivative**2, axis=0) * sensitivity
            memory[name] = jnp.broadcast_to(curvature + 2 * priors.memory / jnp.size(value), jnp.shape(value))
        curvatures = JointParameters(background, contact, memory, stimulus)
        return jax.tree_util.tree_map(lambda c: 1 / jnp.sqrt(c + _TINY_CURVATURE), curvatures)

    def _per_element(self, edge_values: jax.Array) -> jax.Array:
        """(E,) the sum of `edge_values` over each element's edges shared with a neighbour."""
        first, second = self.neighbours
        return jnp.zeros(self.area_fractions.shape).at[first].add(edge_values).at[second].add(edge_values)


# --- The fit ----------------------------------------------------------------------------------------


def joint(
    model: ForwardModel,
    frames: jax.Array | np.ndarray,
    times: jax.Array | np.ndarray,
    *,
    reference_frames: int = 1,
    free: Collection[str] | None = None,
    memory_free: Collection[str] | None = None,
    priors: JointPriors | None = None,
    noise: float | None = None,
    initial: JointFit | Mapping[str, Any] | None = None,
    max_steps: int = 500,
    rtol: float = 1e-4,
    atol: float = 1e-2,
    progress: bool = True,
    throw: bool = True,
    on_step: Callable[[JointProgress], None] | None = None,
) -> JointFit:
    """Fit background, contact impedances, memory parameters and stimulus to `frames` jointly.

    Every frame's misfit is taken through `model` with the memory model in the loop: frame k is
    measured from sigma_k = background * (1 + response[k]), the response the memory model's
    answer to the memoryless stimulus. The objective (misfit in units of the readings' noise,
    plus the priors of `JointPriors`) is minimised by L-BFGS, jitted, one step at a time with a
    progress bar, from a start taken from the data (`background`, one-step images, `memory`) or
    given. The objective and the start are in docs/science.md#joint-fit; what the data
    determine in docs/tutorials/fitting.md#identifiability.

    `free`, `memory_free`, `priors` and `noise` left None take a resumed fit's settings, else
    the defaults below; a resumed fit keeps its prior centres. Resumed from a checkpoint, the
    fit goes on from there with its L-BFGS memory rebuilt (the next steps differ from the
    uninterrupted fit's, the minimum agrees to the tolerances).

    Arguments:
        model: The forward model of the fit's mesh; its contact impedance is the start unless
            `initial` gives one.
        frames: (T, M) readings, volts.
        times: (T,) frame times, seconds, increasing.
        reference_frames: How many of the first frames are untouched (>= 1).
        free: The groups fitted, of "background", "contact_impedance", "memory", "stimulus"
            (default all); the others stay at their initial values.
        memory_free: The memory fields fitted when "memory" is free (default `memory`'s: the
            fractions, the time constants and the relaxation). Never the gain; the two
            fractions together or not at all.
        priors: `JointPriors` (default `JointPriors()`).
        noise: The readings' noise standard deviation, percent of the RMS of the mean reference
            frame: the data scale of the misfit, which sets the balance of misfit and priors.
            Default: the background fit's estimate when it runs, else 0.5 (diffeit's "medium").
        initial: The start. None: from the data; a mapping with any of "background" (E,) S/sq,
            "contact_impedance" (L,) or scalar ohm m, "memory" (`MemoryParameters`) and
            "stimulus" (T, E) dsigma/sigma (the parts not given come from the data); or a
            `JointFit` of the same frames and times, to resume from (L-BFGS starts afresh
            there).
        max_steps: L-BFGS steps, rejected trial steps included.
        rtol: With `atol`: the fit stops when three accepted steps in a row each lower the
            objective by less than atol + rtol |J| (by default 1% of a frame's misfit at the
            noise level, about 1e-4 of J).
        atol: See `rtol`; in units of one frame's misfit at the noise level.
        progress: Show a tqdm progress bar.
        throw: Raise for a result other than `RESULTS.successful` (True), or return it in
            `result` (False).
        on_step: Called with a `JointProgress` when the optimisation starts (after the
            initialisation) and after every accepted step; its `fit()` is the fit so far, to
            save as a checkpoint. What it raises stops the fit and propagates: the way to stop
            at a step with the state saved (`diffeit fit` saves every few steps, and on Ctrl-C
            at the next step). A `KeyboardInterrupt` raised at any moment may arrive inside the
            forward model's host solve, where XLA reports it as a runtime error: keep the last
            progress and save it when that happens, or stop from `on_step`.

    Returns:
        The `JointFit`; resumed, its history continues the one it started from.

    Raises:
        ValueError: For frames that are not finite or not (T, M), times that do not increase
            or are not one per frame, `reference_frames` out of range, unknown groups or
            fields, initial values of the wrong shape or out of range, and invalid memory
            parameters.
        diffeit.results.SolverError: With `throw=True`, for a result other than
            `RESULTS.successful`.
    """
    frames = check_frames(frames, model.n_measurements, "frames")
    if frames.ndim != 2:
        raise ValueError(f"frames must have shape (T, {model.n_measurements}), one row per frame; got {frames.shape}")
    times = check_times(times, frames.shape[0])
    if isinstance(reference_frames, bool) or not (
        isinstance(reference_frames, int) and 1 <= reference_frames <= frames.shape[0]
    ):
        raise ValueError(f"reference_frames must be an integer in 1..{frames.shape[0]}; got {reference_frames!r}")
    if initial is not None and not isinstance(initial, JointFit | Mapping):
        raise ValueError(f"initial must be a JointFit, a mapping of its parts or None; got {type(initial).__name__}")
    resumed = initial if isinstance(initial, JointFit) else None
    before = None if resumed is None else resumed.settings
    free = _checked_names(_setting(free, before, "free", GROUPS), GROUPS, "free")
    memory_free = _checked_memory_free(_setting(memory_free, before, "memory_free", DEFAULT_FREE))
    priors = _checked_priors(_setting(priors, before, "priors", JointPriors()))
    _checked_noise(noise)
    rms = float(jnp.sqrt(jnp.mean(jnp.mean(frames[:reference_frames], axis=0) ** 2)))

    if resumed is not None:
        start = _resumed_start(resumed, model, times)
        data_scale = before.data_scale if noise is None else noise / 100 * rms
        centres = (before.memory_centre, before.log_contact_impedance_centre)
        memory_start = resumed.memory
    else:
        values = _initial_values(model, frames, times, reference_frames, initial or {}, noise, rms, progress)
        background, z, memory, stimulus, data_scale = values
        start = JointParameters(jnp.log(background), jnp.log(z), {}, stimulus)
        centres = (memory, jnp.log(z))
        memory_start = memory
    settings = JointSettings(free, memory_free, priors, data_scale, *centres)
    unconstrained = memory_to_unconstrained(memory_start, settings.memory_fitted)
    if resumed is not None:
        unconstrained |= {name: v for name, v in resumed.parameters.memory.items() if name in unconstrained}
    start = dataclasses.replace(start, memory=unconstrained)

    problem = JointProblem(model, frames, times, settings)
    scales = eqx.filter_jit(problem.scales)(start)
    earlier = 0 if resumed is None else len(resumed.history.objective) - 1

    def report(so_far: Minimum) -> None:
        steps = earlier + len(so_far.objective) - 1
        on_step(JointProgress(steps, float(so_far.objective[-1]), partial(_joint_fit, problem, start, resumed, so_far)))

    minimum = minimise(
        _OfGroups(problem, start),
        {name: start.group(name) for name in free},
        units={name: scales.group(name) for name in free},
        max_steps=max_steps,
        rtol=rtol,
        atol=atol,
        progress=progress,
        description="joint fit",
        on_step=None if on_step is None else report,
    )
    fit = _joint_fit(problem, start, resumed, minimum)
    return throw_if_failed(fit, fit.result, "joint fit") if throw else fit


class JointImaging(AbstractSolver):
    """The joint fit as a reconstruction: readings over time in, every frame's conductivity change out.

    A solver of `diffeit.inverse`'s interface (`AbstractSolver`) for `joint`: the fit's settings
    live on the object, and `solve(readings)` fits background, contact impedances, memory
    parameters and stimulus to the (T, M) readings of T frames, then returns every frame's
    conductivity change from the fitted background, dsigma_k = sigma_k - b = b r_k in S/sq per
    element: what the difference solvers (`OneStep`, `GaussNewton`, ...) estimate from
    V_k - V_ref, the skin's memory included (docs/science.md#joint-fit). The memoryless
    stimulus, the same change without the memory's ghosts, is in `stats`. Unlike the difference
    solvers it takes absolute readings (the reference frames first) and needs each frame's time,
    which is a setting: `times`, one per frame, or a frame interval for readings of any length.

    Arguments:
        model: The forward model of the fit's mesh and protocol (its contact impedance is the
            start unless `initial` gives one); None for an unbound solver (see `bound`).
        times: The frame times: (T,) seconds, increasing, one per frame of the readings `solve`
            takes; or a frame interval in seconds (> 0), frame k at k * times.
        reference_frames: How many of the first frames are untouched (>= 1), as `joint`'s.
        free: The groups fitted (`joint`'s; None for all).
        memory_free: The memory fields fitted (`joint`'s; None for its default).
        priors: `JointPriors` (None for `JointPriors()`).
        noise: The readings' noise, percent of the RMS of the mean reference frame, or None
            (as `joint`'s).
        initial: The start, as `joint`'s mapping: any of "background" ((E,) or scalar, S/sq),
            "contact_impedance" ((L,) or scalar, ohm m), "memory" (`MemoryParameters`) and
            "stimulus" ((T, E), dsigma/sigma); None, or the parts not given: from the data.
        max_steps: L-BFGS steps, as `joint`'s.
        rtol: As `joint`'s.
        atol: As `joint`'s.
        progress: Show the fit's progress bars.

    Attributes:
        model: The forward model (None when unbound).
        times: The frame times, a read-only (T,) array in seconds, or the frame interval, a
            float.
        reference_frames: As given (static).
        free: The groups fitted, in the order of `GROUPS` (static).
        memory_free: The memory fields fitted (static).
        priors: The `JointPriors`.
        noise: As given (static).
        initial: The start's parts by name, or None.
        max_steps: As given (static).
        rtol: As given (static).
        atol: As given (static).
        progress: As given (static).

    Raises:
        ValueError: For times that are neither an increasing finite (T,) array nor a positive
            interval, `reference_frames` not an integer >= 1, unknown groups or fields, priors
            that are not a `JointPriors`, a noise that is not positive, or `initial` with
            unknown parts.
    """

    model: ForwardModel | None
    times: float | np.ndarray = eqx.field(repr=False)
    reference_frames: int = eqx.field(static=True)
    free: tuple[str, ...] = eqx.field(static=True)
    memory_free: tuple[str, ...] = eqx.field(static=True)
    priors: JointPriors
    noise: float | None = eqx.field(static=True)
    initial: dict[str, Any] | None = eqx.field(repr=False)
    max_steps: int = eqx.field(static=True)
    rtol: float = eqx.field(static=True)
    atol: float = eqx.field(static=True)
    progress: bool = eqx.field(static=True)

    def __init__(
        self,
        model: ForwardModel | None = None,
        times: float | jax.Array | np.ndarray | None = None,
        *,
        reference_frames: int = 1,
        free: Collection[str] | None = None,
        memory_free: Collection[str] | None = None,
        priors: JointPriors | None = None,
        noise: float | None = None,
        initial: Mapping[str, Any] | None = None,
        max_steps: int = 500,
        rtol: float = 1e-4,
        atol: float = 1e-2,
        progress: bool = True,
    ) -> None:
        self.model = model
        self.times = _checked_frame_times(times)
        if isinstance(reference_frames, bool) or not (isinstance(reference_frames, int) and reference_frames >= 1):
            raise ValueError(f"reference_frames must be an integer >= 1; got {reference_frames!r}")
        self.reference_frames = reference_frames
        self.free = GROUPS if free is None else _checked_names(free, GROUPS, "free")
        self.memory_free = _checked_memory_free(DEFAULT_FREE if memory_free is None else memory_free)
        self.priors = _checked_priors(JointPriors() if priors is None else priors)
        self.noise = _checked_noise(noise)
        if initial is not None:
            if not isinstance(initial, Mapping):
                kind = type(initial).__name__
                raise ValueError(f"initial must be a mapping of the start's parts or None; got {kind}")
            unknown = sorted(set(initial) - set(GROUPS))
            if unknown:
                raise ValueError(f"initial: unknown parts {unknown}; parts are {list(GROUPS)}")
            initial = dict(initial)
        self.initial = initial
        self.max_steps = int(max_steps)
        self.rtol = float(rtol)
        self.atol = float(atol)
        self.progress = bool(progress)

    def bound(
        self, model: ForwardModel, background: float | np.ndarray | None = None, *, hyperparameter: float | None = None
    ) -> JointImaging:
        """This solver's settings on another model (see `AbstractSolver.bound`).

        Arguments:
            model: The forward model to fit on.
            background: The fit's start background (`initial["background"]`), S/sq, scalar or
                (E,); None keeps this solver's start (fitted to the reference frames when it
                gives none).
            hyperparameter: Must be None: the joint fit has no hyperparameter (its balance of
                misfit and priors is set by `priors` and `noise`).

        Returns:
            A new `JointImaging` with these settings on `model`.

        Raises:
            ValueError: For a hyperparameter other than None.
        """
        if hyperparameter is not None:
            raise ValueError(
                "JointImaging has no hyperparameter: the joint fit's balance of misfit and priors is set by priors= "
                f"(JointPriors, in units of one frame's misfit at the noise level) and noise=; got {hyperparameter!r}"
            )
        initial = self.initial if background is None else {**(self.initial or {}), "background": background}
        return JointImaging(
            model,
            self.times,
            reference_frames=self.reference_frames,
            free=self.free,
            memory_free=self.memory_free,
            priors=self.priors,
            noise=self.noise,
            initial=initial,
            max_steps=self.max_steps,
            rtol=self.rtol,
            atol=self.atol,
            progress=self.progress,
        )

    def solve(self, data: jax.Array | np.ndarray, *, throw: bool = True) -> Solution:
        """Fit the readings of T frames jointly and image every frame.

        Runs `joint(model, data, times, ...)` with this solver's settings.

        Arguments:
            data: The readings v of T frames, (T, M), volts (absolute readings, not
                differences), the `reference_frames` untouched ones first.
            throw: Raise when the fit does not succeed (True), or return its code (False).

        Returns:
            The `Solution`: `value` (T, E) the conductivity change of every frame from the
            fitted background, sigma_k - b = b r_k, S/sq (`JointFit.background` times
            `JointFit.response`, the memory's ghosts included); `result` the fit's code, one
            per frame (the frames are fitted together: all succeed or fail alike). `stats`:
            "fit" the `JointFit`, "stimulus" (T, E) the memoryless stimulus as a conductivity
            change b a, S/sq (`JointFit.background` times `JointFit.stimulus`), "background"
            (E,) b, S/sq, "contact_impedance" (L,) ohm m, "memory" the `MemoryParameters`,
            "misfit" the relative misfit over all frames and "steps" the accepted steps.

        Raises:
            ValueError: For an unbound solver, readings that are not (T, M) or not finite,
                `times` that are not one per frame, and what `joint` refuses (for example
                `reference_frames` beyond T or an `initial` of the wrong shape).
            diffeit.results.SolverError: With `throw=True`, for a fit whose result is not
                `RESULTS.successful` (its iterate is lost: pass throw=False to keep it).
        """
        model = model_of(self)
        if np.ndim(data) != 2:
            raise ValueError(
                f"JointImaging.solve takes the readings of T frames, (T, {model.n_measurements}); got shape "
                f"{np.shape(data)}"
            )
        n_frames = np.shape(data)[0]
        if isinstance(self.times, float):
            times = self.times * np.arange(n_frames)
        elif len(self.times) != n_frames:
            raise ValueError(
                f"JointImaging.times holds {len(self.times)} frame times and the readings {n_frames} frames: give "
                "one time per frame, or a frame interval (seconds)"
            )
        else:
            times = self.times
        fit = joint(
            model,
            data,
            times,
            reference_frames=self.reference_frames,
            free=self.free,
            memory_free=self.memory_free,
            priors=self.priors,
            noise=self.noise,
            initial=self.initial,
            max_steps=self.max_steps,
            rtol=self.rtol,
            atol=self.atol,
            progress=self.progress,
            throw=False,
        )
        background = fit.background[None]
        stats = {
            "fit": fit,
            "stimulus": background * fit.stimulus,
            "background": fit.background,
            "contact_impedance": fit.contact_impedance,
            "memory": fit.memory,
            "misfit": fit.misfit,
            "steps": len(fit.history.objective) - 1,
        }
        result = jax.tree_util.tree_map(lambda code: jnp.broadcast_to(code, (n_frames,)), fit.result)
        return finished(background * fit.response, result, stats, "joint fit", throw)


def _checked_frame_times(times: Any) -> float | np.ndarray:
    """`JointImaging.times` checked: a frame interval (a float, seconds) or (T,) frame times (a
    read-only array)."""
    if times is None:
        raise ValueError("JointImaging needs the frame times: times=(T,) seconds, or a frame interval in seconds")
    if isinstance(times, bool):
        raise ValueError(f"times must be frame times (T,) or a frame interval, seconds; got {times!r}")
    array = np.asarray(times, dtype=float)
    if array.ndim == 0:
        if not (np.isfinite(array) and array > 0):
            raise ValueError(f"a frame interval must be finite and positive (seconds); got {float(array)}")
        return float(array)
    return readonly(np.asarray(check_times(array, array.shape[0])))


def _joint_fit(problem: JointProblem, start: JointParameters, resumed: JointFit | None, minimum: Minimum) -> JointFit:
    """The `JointFit` of `minimum` (the free groups' values) from `start`, its history continuing
    `resumed`'s when there is one."""
    parameters = start.with_groups(minimum.value)
    history = History(minimum.objective, minimum.gradient_norm)
    if resumed is not None:
        history = History(
            np.concatenate([resumed.history.objective, history.objective[1:]]),
            np.concatenate([resumed.history.gradient_norm, history.gradient_norm[1:]]),
        )
    background, z, memory, response = problem.state(parameters)
    voltages = problem.voltages(parameters)
    return JointFit(
        background=background,
        contact_impedance=z,
        # Reported in mode order; the unknowns keep the optimiser's labelling, so that a resumed
        # fit continues from exactly where this one stopped.
        memory=reported_memory(
            MemoryParameters(**{name: getattr(memory, name) for name in MEMORY_FIELDS}),
            problem.settings.memory_fitted,
        ),
        stimulus=parameters.stimulus,
        response=response,
        times=problem.times,
        misfit=float(jnp.linalg.norm(voltages - problem.frames) / jnp.linalg.norm(problem.frames)),
        history=history,
        result=minimum.result,
        parameters=parameters,
        settings=problem.settings,
    )


def _checked_priors(priors: Any) -> JointPriors:
    if not isinstance(priors, JointPriors):
        raise ValueError(f"priors must be a JointPriors; got {type(priors).__name__}")
    return priors


def _checked_noise(noise: Any) -> float | None:
    if noise is not None and (isinstance(noise, bool) or not (isinstance(noise, int | float) and noise > 0)):
        raise ValueError(f"noise must be a positive number (percent of the RMS of the reference); got {noise!r}")
    return noise


def _setting(value: Any, before: JointSettings | None, name: str, default: Any) -> Any:
    """`value`, or when None the resumed fit's setting `name`, or `default`."""
    if value is not None:
        return value
    return default if before is None else getattr(before, name)


def _checked_names(names: Collection[str], known: tuple[str, ...], what: str) -> tuple[str, ...]:
    names = (names,) if isinstance(names, str) else tuple(names)
    unknown = sorted(set(names) - set(known))
    if unknown:
        raise ValueError(f"{what}: unknown names {unknown}; known: {list(known)}")
    return tuple(name for name in known if name in names)


def _checked_memory_free(names: Collection[str]) -> tuple[str, ...]:
    names = _checked_names(names, MEMORY_FIELDS, "memory_free")
    if "gain" in names:
        raise ValueError("memory_free: the gain trades exactly with the stimulus' amplitude; it cannot be fitted")
    if ("fast_fraction" in names) != ("slow_fraction" in names):
        raise ValueError(
            "memory_free: fast_fraction and slow_fraction are fitted together (their sum stays below 1): "
            "free both or neither"
        )
    return names


def _checked_memory(memory: Any, n_elements: int) -> MemoryParameters:
    """`memory` built again, so that its checks run (a Module changed by `eqx.tree_at` skipped
    them), with every field a number or one value per element."""
    if not isinstance(memory, MemoryParameters):
        raise ValueError(f"the initial memory must be a MemoryParameters; got {type(memory).__name__}")
    values = {}
    for name in MEMORY_FIELDS:
        array = concrete_floats(getattr(memory, name), f"MemoryParameters.{name}")
        if array is None:
            raise ValueError(f"the initial memory must hold values, not traced arrays (MemoryParameters.{name})")
        if array.shape not in ((), (1,), (n_elements,)):
            raise ValueError(
                f"MemoryParameters.{name} has shape {array.shape}: give a number or one value per element "
                f"({n_elements},)"
            )
        values[name] = float(array) if array.shape == () else jnp.asarray(array)
    return MemoryParameters(**values)


def _initial_values(
    model: ForwardModel,
    frames: jax.Array,
    times: jax.Array,
    reference_frames: int,
    initial: Mapping[str, Any],
    noise: float | None,
    rms: float,
    progress: bool,
) -> tuple[jax.Array, jax.Array, MemoryParameters, jax.Array, float]:
    """(background, contact impedance, memory, stimulus, data scale): the parts `initial` gives,
    checked, and the others from the data (docs/science.md#joint-fit, Initialisation)."""
    unknown = sorted(set(initial) - set(GROUPS))
    if unknown:
        raise ValueError(f"initial: unknown parts {unknown}; parts are {list(GROUPS)}")
    n_frames, n_elements = frames.shape[0], model.n_elements
    given = initial.get("memory")
    memory = None if given is None else _checked_memory(given, n_elements)
    stimulus = initial.get("stimulus")
    if stimulus is not None:
        stimulus = np.asarray(stimulus, dtype=float)
        if stimulus.shape != (n_frames, n_elements):
            raise ValueError(f"initial stimulus has shape {stimulus.shape}; expected ({n_frames}, {n_elements})")
        if not np.all(np.isfinite(stimulus)):
            raise ValueError("initial stimulus must be finite (dsigma/sigma)")
    z = _positive(
        initial.get("contact_impedance", model.contact_impedance),
        (model.mesh.n_electrodes,),
        "initial contact_impedance",
        "ohm m",
    )
    background = initial.get("background")
    estimated_noise = None
    if background is None:
        found = fit_background(
            eqx.tree_at(lambda m: m.contact_impedance, model, z),
            frames[:reference_frames],
            noise=noise,
            progress=progress,
            throw=False,
        )
        # At the boundary its misfit levelled off at the model's own error: a map all the same.
        if bool(found.result != RESULTS.selection_at_boundary):
            _warn_if_failed(found.result, "the starting background fit (diffeit.fit.background)")
        background = found.conductivity
        if np.isfinite(found.noise) and found.noise > 0:
            estimated_noise = found.noise
    background = _positive(background, (n_elements,), "initial background", "S/sq")
    if noise is not None:
        data_scale = noise / 100 * rms
    else:
        data_scale = DEFAULT_NOISE / 100 * rms if estimated_noise is None else float(estimated_noise)
    if memory is None or stimulus is None:
        sharp = _IMAGE_REGULARISATION * data_scale / rms
        images, image_noise = _one_step_images(model, frames, reference_frames, background, z, data_scale, sharp)
        if memory is None:
            if sharp >= _MEMORY_IMAGE_REGULARISATION:  # the images are calm enough already
                calm, calm_noise = images, image_noise
            else:
                calm, calm_noise = _one_step_images(
                    model, frames, reference_frames, background, z, data_scale, _MEMORY_IMAGE_REGULARISATION
                )
            try:
                found = fit_memory(calm, times, noise=calm_noise, progress=progress, throw=False)
                _warn_if_failed(found.result, "the starting memory fit (diffeit.fit.memory)")
                memory = _modes_apart(_determined(found.memory, float(times[-1] - times[0])), over_foam())
            except ValueError:  # no element rises above the images' noise: nothing to fit p to
                memory = over_foam()
        if stimulus is None:
            derived = correct_memory(images, times, memory)
            threshold = _THRESHOLD * float(jnp.median(jnp.abs(derived)))
            stimulus = jnp.minimum(derived + threshold, 0.0)
    return background, z, memory, jnp.asarray(stimulus), data_scale


def _warn_if_failed(result: RESULTS, what: str) -> None:
    """A warning when a fit that gives the joint fit its start fell short: the joint fit goes on
    from its last iterate, which only costs steps, but the user hears of it."""
    if bool(result != RESULTS.successful):
        warnings.warn(f"{what} ended: {messages(result)[0]}; the joint fit starts from its last iterate", stacklevel=4)


def _determined(memory: MemoryParameters, duration: float) -> MemoryParameters:
    """`memory`, or over_foam when a mode carries less than `_LEAST_FRACTION` of the response or
    decays slower than the recording's `duration` (seconds) lasts (docs/science.md#joint-fit,
    Initialisation)."""
    fractions = (float(memory.fast_fraction), float(memory.slow_fraction))
    times = (float(memory.fast_time), float(memory.slow_time))
    if min(fractions) < _LEAST_FRACTION or max(times) > duration:
        return over_foam()
    return memory


def _modes_apart(memory: MemoryParameters, preset: MemoryParameters) -> MemoryParameters:
    """`memory` with its two time constants set apart by `preset`'s ratio around their geometric
    mean when they are within a factor `_MERGED` of each other (docs/science.md#joint-fit, Initialisation)."""
    fast, slow = float(memory.fast_time), float(memory.slow_time)
    if max(fast, slow) >= _MERGED * min(fast, slow):
        return memory
    middle, half_ratio = np.sqrt(fast * slow), np.sqrt(float(preset.slow_time) / float(preset.fast_time))
    return dataclasses.replace(memory, fast_time=middle / half_ratio, slow_time=middle * half_ratio)


def _positive(value: Any, shape: tuple[int, ...], what: str, unit: str) -> jax.Array:
    array = np.asarray(value, dtype=float)
    if array.shape not in ((), shape):
        raise ValueError(f"{what} has shape {array.shape}; expected {shape} or a scalar")
    if not np.all(np.isfinite(array) & (array > 0)):
        raise ValueError(f"{what} must be finite and positive ({unit})")
    return jnp.asarray(np.broadcast_to(array, shape))


def _one_step_images(
    model: ForwardModel,
    frames: jax.Array,
    reference_frames: int,
    background: jax.Array,
    z: jax.Array,
    data_scale: float,
    hyperparameter: float,
) -> tuple[jax.Array, np.ndarray]:
    """(T, E) relative-change images dsigma/sigma of every frame against the mean reference frame
    (`OneStep`, NOSER prior, `hyperparameter`), and (E,) their noise standard deviation: the
    readings' noise `data_scale` (volts) through the reconstruction matrix, the reference's
    included."""
    fitted = eqx.tree_at(lambda m: m.contact_impedance, model, z)
    one_step = OneStep(fitted, "noser", hyperparameter, np.asarray(background))
    reference = jnp.mean(frames[:reference_frames], axis=0)
    images = one_step.solve(frames - reference).value / background
    gain = np.linalg.norm(np.asarray(one_step.matrix), axis=1) / np.asarray(background)
    return images, data_scale * np.sqrt(1 + 1 / reference_frames) * gain


def _resumed_start(fit: JointFit, model: ForwardModel, times: jax.Array) -> JointParameters:
    """The unknowns of `fit` (memory filled in by the caller), checked against this model and
    these frames."""
    parameters = fit.parameters
    expected = {
        "log_background": (model.n_elements,),
        "log_contact_impedance": (model.mesh.n_electrodes,),
        "stimulus": (len(times), model.n_elements),
    }
    for name, shape in expected.items():
        if getattr(parameters, name).shape != shape:
            raise ValueError(
                f"the fit to resume has {name} of shape {getattr(parameters, name).shape}; this model and "
                f"these frames need {shape}"
            )
    if not np.array_equal(np.asarray(fit.times), np.asarray(times)):
        raise ValueError("the fit to resume was made with other frame times")
    return dataclasses.replace(parameters, memory={})
