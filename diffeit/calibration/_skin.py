"""`SkinCalibration`, the model of one skin and board that `calibrate` fits, and its file:
`SkinCalibration.save` writes it (HDF5, schema `SCHEMA`, version `SCHEMA_VERSION`) and `load`
reads it back, refusing what it stores out of range; with the electrodes' places along the
boundary (`_boundary_loop`, `_electrode_centres`).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
from pathlib import Path
from typing import Any

import equinox as eqx
import h5py
import numpy as np
from numpy.typing import ArrayLike

from ..forward import ForwardModel
from ..inverse import CONTACT_IMPEDANCE_SPREAD
from ..io import Recording, create_checked, read_attributes, read_checked, write_atomically, write_attributes
from ..memory import MemoryParameters
from ..mesh import Mesh
from ..protocol import Protocol
from ..readout import Readout
from ._maps import PositionMap, SizeMap, _in_mesh_frame, _terms
from ._reference import ReferenceCalibration

# The labels' frame: ln scale, angle (rad), offset x and y (m), handedness (+1, or -1: mirrored).
_IDENTITY_FRAME = np.array([0.0, 0.0, 0.0, 0.0, 1.0])


# The ringing a further touch must rise above: this quantile of the relative heights of the
# further hills in the presses' images (a press with none counts 0), at most the cap (a second
# touch half as deep as the first is always read).
_RINGING_QUANTILE, _RINGING_CAP = 0.95, 0.5


class SkinCalibration(eqx.Module):
    """The model of one skin and board, fitted to a calibration session by `calibrate`.

    Attributes:
        model: The calibrated `ForwardModel`: the readings used, in the orientation found,
            the readout's mixing folded into its reading weights, the fitted contact
            impedances, in the recording's voltage unit at `conductivity`.
        conductivity: sigma_h, the fitted level, S/sq in the recording's voltage unit.
        background_map: (E,) the sheet's conductivity fitted to the reference (or by the
            presses) on the mesh's elements, S/sq in the same unit (package docstring,
            "Background map"), or None: the
            sheet is taken uniform at `conductivity`. `background` is the one imaged at.
        contact_impedance: (L,) ohm m, in the same unit.
        electrode_centres: (L,) the electrodes' centres as arc length along the boundary, m,
            counter-clockwise from the first node of the mesh's electrode 0: the mesh's, moved
            by the fitted shifts when "electrode_positions" was fitted.
        readout: The fitted `diffeit.readout.Readout` on the readings used (its gains: the
            drive and channel gains that `signed` divides by, times a gain per reading when
            the presses fitted "reading_gains"; a reference cannot tell a reading's gain from
            the model's error there).
        used: (M,) bool, the recording's readings that are imaged.
        reading_sign: (M,) +-1, what a recorded reading is multiplied by to match the model.
        standard_errors: Group -> (n,) standard errors of the fitted parameters, as `values`
            (those the presses fit raised to their spread over the held-out folds where that
            is larger: `_with_fold_spread`).
        values: Group -> (n,) the fitted parameters: "level" (ln c: `conductivity` is the
            first stage's over c), "contact_impedance" (ln of each z / (c z_first), z_first
            the first stage's), "mixing" (source, sink, offsets), "drive_gains" and
            "channel_gains" (ln g), "electrode_positions" (the centres' shifts, m along the
            boundary), "electrode_widths" (the change of each electrode's length, m),
            "background" (the background map's coefficients).
        undetermined: Names of the fitted parameters the data did not determine.
        fitted: "reference" and "presses" -> the groups each determined.
        misfit: ||v - V|| / ||v|| of the refined model, and
            `correlation` (Pearson) on the readings used.
        position_map: The `PositionMap` fitted on labelled presses, or None.
        press_errors: (K,) distances, m, between mapped and labelled press positions, each
            press held out: of the presses' fit and the position map when the presses' fit
            is kept (five folds), of the position map alone otherwise (leave-one-out; with
            fewer than 20 presses always); NaN for a press no touch was read at, or left out
            as damaged; None without presses.
        press_positions: (K, 2), or (K, 3) on a curved skin, where each press was read, m,
            through the position map (NaN for a press no touch was read at, or left out as
            damaged), or None.
        noise: (M_used,) the standard deviation of one reading, in the units of `signed`, from
            the spread of the reference frames (None with fewer than 6): `diffeit.touches`
            tests each frame's differences against it.
        noise_frames: How many reference frames `noise` was estimated from.
        polarity: -1 when the presses lower the conductivity, +1 when they raise it; None
            without presses (`diffeit.touches` then reads it from the images).
        memory: The skin's `diffeit.memory.MemoryParameters` fitted to presses held over
            several frames (each free field also in `values["memory.NAME"]`, its standard
            error in `standard_errors["memory.NAME"]`), or None.
        hyperparameter: The one-step hyperparameter the presses were imaged at (images to be
            read through the position map are best made at it), or None.
        first_stage: The `ReferenceCalibration` the refinement started from (orientation,
            masked readings).
        warnings: What the calibration warns about, in words.
        protocol: The recording's protocol; `readings` its kind ("signed" or "magnitude").
        ringing: How high the further hills of the presses' images stand beside each one's
            highest, a fraction of its peak (the `_RINGING_QUANTILE` quantile over the
            presses, at most `_RINGING_CAP`): `diffeit.touches` reports a further touch only
            above it (a single press is one touch). None without a position map.
        size_map: The `SizeMap` that `diffeit.touches` reads touches' radii and depths
            through, fitted on labelled presses (20 or more on a flat skin: the labels' frame
            gives their radius in the mesh's), or None.
        reference: (M,) the mean of the reference frames the model was fitted to, as recorded
            (the mean of `noise_frames` frames), or None (a file written before it was kept):
            `diffeit.reconstruct` images a recording without untouched first frames against
            it (`calibrated_reference_frames`).
        contact_impedance_spread: The one-step contact spread the presses were imaged at
            (`diffeit.inverse.LinearisedProblem`; 0 in files written before it was kept, whose
            presses were imaged with the contacts held), as `hyperparameter`; None without.
    """

    model: ForwardModel
    conductivity: float
    background_map: np.ndarray | None
    contact_impedance: np.ndarray
    electrode_centres: np.ndarray
    readout: Readout
    used: np.ndarray
    reading_sign: np.ndarray
    standard_errors: dict[str, np.ndarray]
    values: dict[str, np.ndarray]
    undetermined: tuple[str, ...]
    fitted: dict[str, tuple[str, ...]]
    misfit: float
    correlation: float
    position_map: PositionMap | None
    press_errors: np.ndarray | None
    press_positions: np.ndarray | None
    hyperparameter: float | None
    noise: np.ndarray | None
    noise_frames: int
    polarity: int | None
    memory: MemoryParameters | None
    first_stage: ReferenceCalibration
    warnings: tuple[str, ...]
    protocol: Protocol = eqx.field(static=True)
    readings: str = eqx.field(static=True)
    ringing: float | None = None
    size_map: SizeMap | None = None
    reference: np.ndarray | None = None
    contact_impedance_spread: float | None = None

    @property
    def imaging_spread(self) -> float:
        """The contact spread its one-step images are made at: its own once it holds one (its
        presses were imaged at it, and a position map fitted on them), else
        `diffeit.reconstruct`'s default, `diffeit.inverse.CONTACT_IMPEDANCE_SPREAD`."""
        spread = self.contact_impedance_spread
        return CONTACT_IMPEDANCE_SPREAD if spread is None else spread

    @property
    def driven_readings(self) -> str:
        """ "none", "kept" or "dropped": the first stage's choice of the readings on driven electrodes."""
        return self.first_stage.driven_readings

    @property
    def background(self) -> float | np.ndarray:
        """The conductivity the model images at, S/sq in the recording's unit: the background
        map (E,) when one was fitted, else the level."""
        return self.conductivity if self.background_map is None else self.background_map

    def signed(self, frames: np.ndarray) -> np.ndarray:
        """(..., M_used): recorded frames (..., M) in the calibrated model's order, sign and
        gain: what the calibrated model's `measure` predicts."""
        frames = np.asarray(frames, np.float64)
        if frames.shape[-1] != self.protocol.n_measurements:
            raise ValueError(
                f"frames have {frames.shape[-1]} readings; this calibration's protocol has "
                f"{self.protocol.n_measurements}"
            )
        return (frames * self.reading_sign)[..., self.used] / np.asarray(self.readout.gains)

    def summary(self) -> dict[str, Any]:
        """The calibration in JSON-serialisable form, for provenance."""
        first = self.first_stage.summary()
        return {
            **first,
            "conductivity": self.conductivity,
            "contact_impedance": float(np.mean(self.contact_impedance)),
            "contact_impedance_per_electrode": [float(z) for z in self.contact_impedance],
            "misfit": self.misfit,
            "correlation": self.correlation,
            "first_stage_misfit": first["misfit"],
            "first_stage_correlation": first["correlation"],
            "mixing": [float(w) for w in self.values["mixing"]],
            "background_map_range": None
            if self.background_map is None
            else [float(self.background_map.min()), float(self.background_map.max())],
            "undetermined": list(self.undetermined),
            "position_map_degree": None if self.position_map is None else self.position_map.degree,
            "size_map_degrees": None
            if self.size_map is None
            else {"radius": self.size_map.radius_degree, "depth": self.size_map.depth_degree},
            "press_error_median": None if self.press_errors is None else float(np.median(self.press_errors)),
            "warnings": list(self.warnings),
        }

    def lines(self) -> list[str]:
        """The calibration's report, a line per finding."""
        first = self.first_stage
        mixing = self.values["mixing"]
        gains = np.exp(np.concatenate([self.values["drive_gains"], self.values["channel_gains"]]))
        lines = [
            f"readings used: {int(self.used.sum())} of {len(self.used)} ({first.orientation})",
            f"model against reference: misfit {first.misfit:.1%} -> {self.misfit:.1%}, "
            f"correlation {first.correlation:.3f} -> {self.correlation:.3f}",
            f"level sigma_h: {self.conductivity:.4g} S/sq (in the recording's unit)",
            "background: uniform at the level"
            if self.background_map is None
            else f"background map: {self.background_map.min():.4g} to {self.background_map.max():.4g} S/sq",
            "contact impedance per electrode, ohm m: " + " ".join(f"{z:.3g}" for z in self.contact_impedance),
            f"readout mixing: source {mixing[0]:+.3f} +- {self.standard_errors['mixing'][0]:.3f}, "
            f"sink {mixing[1]:+.3f} +- {self.standard_errors['mixing'][1]:.3f}, largest offset weight "
            f"{np.max(np.abs(mixing[2:])):.3f}",
            f"drive and channel gains: {gains.min():.3f} to {gains.max():.3f}",
            f"fitted from the reference: {', '.join(self.fitted['reference'])}; from the presses: "
            + (", ".join(self.fitted["presses"]) or "nothing"),
            self._positions_line(),
        ]
        if self.undetermined:
            lines.append(f"not determined by the data ({len(self.undetermined)}): " + ", ".join(self.undetermined))
        if "label_frame" in self.values:
            scale, angle, x, y, *handedness = self.values["label_frame"]  # files of versions 1 to 4: 4 values
            mirrored = ", mirrored (y -> -y first)" if handedness and handedness[0] < 0 else ""
            lines.append(
                f"labels' frame onto the mesh's: scale {math.exp(scale):.4g}, rotation {math.degrees(angle):+.1f} deg, "
                f"offset ({x:+.4g}, {y:+.4g}) m{mirrored}"
            )
        memory = [name.split(".", 1)[1] for name in self.values if name.startswith("memory.")]
        if memory:
            lines.append(
                "memory: "
                + ", ".join(
                    f"{name} {self.values['memory.' + name][0]:.3g} +- {self.standard_errors['memory.' + name][0]:.2g}"
                    for name in memory
                )
            )
        if self.position_map is not None:
            errors = ", ".join(f"{degree}: {1e3 * error:.1f} mm" for degree, error in self.position_map.errors.items())
            lines.append(
                f"position map: degree {self.position_map.degree} (leave-one-out median error by degree: {errors})"
            )
        if self.ringing is not None:
            lines.append(f"ringing: a further touch stands above {self.ringing:.2f} of the highest's peak")
        if self.size_map is not None:
            lines.append(self._sizes_line())
        lines.extend(f"warning: {note}" for note in self.warnings)
        return lines

    def _sizes_line(self) -> str:
        """The size map's line of the report: each gain's range and, by degree, its
        leave-one-out median factor off the presses'."""
        sizes, parts = self.size_map, []
        for row, (name, degree) in enumerate((("radius", sizes.radius_degree), ("depth", sizes.depth_degree))):
            low, high = np.exp(sizes.limits[row])
            off = ", ".join(f"{key}: {math.exp(error):.2f}x" for key, error in sizes.errors[name].items())
            parts.append(
                f"{name} x{low:.2f} to x{high:.2f}, degree {degree} (leave-one-out median off by degree: {off})"
            )
        return "size map (touches' radius and depth as the presses'): " + "; ".join(parts)

    def in_mesh_frame(self, points: ArrayLike) -> np.ndarray:
        """Points in the labels' frame (`diffeit.touches`' positions, the presses' labels) taken
        into the mesh's frame, to draw them on the mesh.

        Arguments:
            points: (..., D) positions, m; NaN stays NaN.

        Returns:
            (..., D) the positions in the mesh's frame, m: moved by the labels' frame
            (`values["label_frame"]`) on a flat skin calibrated with presses, else a copy.
        """
        points = np.array(points, np.float64)
        if "label_frame" not in self.values or points.shape[-1] != 2:
            return points
        frame = np.asarray(self.values["label_frame"], np.float64)
        return _in_mesh_frame(points, frame if len(frame) == 5 else np.append(frame, 1.0))  # versions 1-4: unmirrored

    @property
    def electrode_points(self) -> np.ndarray:
        """(L, D) each electrode's centre, m: `electrode_centres` taken onto the boundary (NaN
        for an electrode on another boundary loop)."""
        loop, arcs = _boundary_loop(self.model.mesh)
        points = self.model.mesh.nodes[loop]
        return np.stack([np.interp(self.electrode_centres, arcs, axis) for axis in points.T], axis=1)

    @property
    def electrode_lengths(self) -> np.ndarray:
        """(L,) each electrode's length along the boundary, m: the mesh's, changed by the
        fitted widths when "electrode_widths" was fitted."""
        lengths = np.asarray(self.model.system.electrode_lengths)
        shift = self.model.electrode_shift
        return lengths if shift is None else lengths + np.asarray(shift[:, 1] - shift[:, 0])

    def _positions_line(self) -> str:
        fitted = set(itertools.chain(*self.fitted.values()))
        if "electrode_positions" not in fitted:
            line = "electrode positions: the mesh's (not fitted)"
        else:
            shift, error = 1e3 * self.values["electrode_positions"], 1e3 * self.standard_errors["electrode_positions"]
            line = (
                f"electrode positions: moved {shift.min():+.2f} to {shift.max():+.2f} mm along the boundary "
                f"(standard errors {error.min():.2f} to {error.max():.2f} mm)"
            )
        if "electrode_widths" in fitted:
            width, error = 1e3 * self.values["electrode_widths"], 1e3 * self.standard_errors["electrode_widths"]
            line += (
                f"; widths changed {width.min():+.2f} to {width.max():+.2f} mm "
                f"(standard errors {error.min():.2f} to {error.max():.2f} mm)"
            )
        return line

    def save(self, path: str | Path, *, overwrite: bool = False) -> Path:
        """Write the calibration to an HDF5 file (schema "diffeit.calibration"), atomically and
        checksummed; `load` reads it.

        Arguments:
            path: The file to write (by convention `SKIN.cal.h5`).
            overwrite: Replace an existing file.

        Returns:
            The path written.
        """
        return _save(self, Path(path), overwrite)


def _boundary_loop(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """The boundary loop through the first node of electrode 0, counter-clockwise from it: its
    nodes, closed (n + 1,: the first again at the end), and their arc lengths from it (n + 1,), m."""
    following = dict(mesh.boundary_edges.tolist())
    start = int(mesh.electrodes[0][0])
    loop = [start]
    while loop[-1] != start or len(loop) == 1:
        loop.append(following[loop[-1]])
    loop = np.array(loop)
    steps = np.linalg.norm(np.diff(mesh.nodes[loop], axis=0), axis=1)
    return loop, np.concatenate([[0.0], np.cumsum(steps)])


def _electrode_centres(mesh: Mesh, shift: np.ndarray | None = None) -> np.ndarray:
    """(L,) each electrode's midpoint as arc length along its boundary, m, counter-clockwise
    from the first node of electrode 0 (NaN for an electrode on another boundary loop), moved
    by `shift` (L,), m."""
    loop, arcs = _boundary_loop(mesh)
    arc = float(arcs[-1])
    position = dict(zip(loop[:-1].tolist(), arcs[:-1].tolist(), strict=True))
    centres = []
    for nodes in mesh.electrodes:
        if int(nodes[0]) not in position:
            centres.append(math.nan)
            continue
        first = position[int(nodes[0])]
        length = np.sum(np.linalg.norm(np.diff(mesh.nodes[nodes], axis=0), axis=1))
        centres.append(first + 0.5 * length)
    return (np.array(centres) + (0.0 if shift is None else shift)) % arc


# ---------------------------------------------------------------------------------------------
# Files


SCHEMA = "diffeit.calibration"


# Version 2: the electrodes' positions (model/electrode_shift, electrode_margin); version 3: the
# background map (background_map), which a reader of version 2 would ignore; version 4: polarity 0
# for a calibration without presses (none known), which a reader of version 3 would refuse to read
# touches with; version 5: the labels' frame's handedness (values/label_frame's fifth value), which
# a reader of version 4 would fail on, and a curved skin's position maps (coefficients (n_terms, 3)),
# which it would apply without taking the touches back onto the surface; version 6: the size map
# (size_map), without which a reader of version 5 would read touches' radii and depths other than
# the calibration's. Versions 1 to 5 read (their -1 without presses stays -1). The reference
# (reference) came within version 6, optional: a reader without it images every recording
# against the recording's own first frames, as a calibration without it does. Version 7: the
# position map's region and slope (position_map/region, position_map/slope), without which a
# reader of version 6 would extrapolate its polynomial beyond the presses; a map read from
# versions 1 to 6 has none, and is evaluated everywhere as it was. The contact spread the presses
# were imaged at (contact_impedance_spread) came within version 7, optional: a file without it had
# them imaged with the contacts held, and is read so.
SCHEMA_VERSION = 7


def _save(calibration: SkinCalibration, path: Path, overwrite: bool) -> Path:
    """Write `calibration` (see `SkinCalibration.save`)."""
    model = calibration.model
    mesh = model.mesh
    arrays = {
        "mesh/nodes": mesh.nodes,
        "mesh/triangles": mesh.triangles,
        "mesh/electrode_nodes": np.concatenate(mesh.electrodes),
        "mesh/electrode_offsets": np.cumsum([0, *(len(e) for e in mesh.electrodes)]),
        "protocol/drive": calibration.protocol.drive,
        "protocol/measure": calibration.protocol.measure,
        "protocol/drive_index": calibration.protocol.drive_index,
        "model/measure": model.protocol.measure,
        "contact_impedance": calibration.contact_impedance,
        "used": calibration.used.astype(np.int8),
        "reading_sign": calibration.reading_sign,
        "readout/gains": np.asarray(calibration.readout.gains),
        "readout/weights": np.concatenate(
            [
                np.atleast_1d(calibration.readout.source),
                np.atleast_1d(calibration.readout.sink),
                calibration.readout.offsets,
            ]
        ),
        **{f"values/{name}": value for name, value in calibration.values.items()},
        **{f"standard_errors/{name}": value for name, value in calibration.standard_errors.items()},
    }
    if model.electrode_shift is not None:
        arrays["model/electrode_shift"] = np.asarray(model.electrode_shift)
    if calibration.noise is not None:
        arrays["noise"] = calibration.noise
    if calibration.reference is not None:
        arrays["reference"] = calibration.reference
    if calibration.background_map is not None:
        arrays["background_map"] = calibration.background_map
    if calibration.position_map is not None:
        arrays["position_map/coefficients"] = calibration.position_map.coefficients
        if calibration.position_map.region is not None:
            arrays["position_map/region"] = calibration.position_map.region
            arrays["position_map/slope"] = calibration.position_map.slope
    if calibration.size_map is not None:
        arrays["size_map/radius_coefficients"] = calibration.size_map.radius_coefficients
        arrays["size_map/depth_coefficients"] = calibration.size_map.depth_coefficients
        arrays["size_map/limits"] = calibration.size_map.limits
    if calibration.press_errors is not None:
        arrays["press_errors"] = calibration.press_errors
        arrays["press_positions"] = calibration.press_positions
    attributes = {
        "schema": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "readings": calibration.readings,
        "drive_current": model.drive_current,
        "electrode_margin": getattr(model.system, "electrode_margin", 0.0),
        "conductivity": calibration.conductivity,
        "misfit": calibration.misfit,
        "correlation": calibration.correlation,
        "hyperparameter": -1.0 if calibration.hyperparameter is None else calibration.hyperparameter,
        "noise_frames": calibration.noise_frames,
        "polarity": 0 if calibration.polarity is None else calibration.polarity,  # 0: none
        "ringing": -1.0 if calibration.ringing is None else calibration.ringing,
        "contact_impedance_spread": -1.0
        if calibration.contact_impedance_spread is None
        else calibration.contact_impedance_spread,
        "json": json.dumps(
            {
                "undetermined": list(calibration.undetermined),
                "fitted": {source: list(groups) for source, groups in calibration.fitted.items()},
                "memory": None
                if calibration.memory is None
                else {
                    field.name: float(getattr(calibration.memory, field.name))
                    for field in dataclasses.fields(calibration.memory)
                },
                "warnings": list(calibration.warnings),
                "first_stage": calibration.first_stage.summary(),
                "position_map": None
                if calibration.position_map is None
                else {
                    "degree": calibration.position_map.degree,
                    "length": calibration.position_map.length,
                    "errors": calibration.position_map.errors,
                },
                "size_map": None
                if calibration.size_map is None
                else {
                    "radius_degree": calibration.size_map.radius_degree,
                    "depth_degree": calibration.size_map.depth_degree,
                    "length": calibration.size_map.length,
                    "errors": calibration.size_map.errors,
                },
            }
        ),
    }

    def write(file: h5py.File) -> None:
        write_attributes(file, attributes)
        for name, value in arrays.items():
            create_checked(file, name, np.asarray(value))

    return write_atomically(path, write, overwrite=overwrite)


def load(path: str | Path, *, recording: Recording | None = None) -> SkinCalibration:
    """Read a calibration written by `SkinCalibration.save`.

    Arguments:
        path: The file.
        recording: When given, the calibration must be for its protocol (and its mesh, when
            it brings one): a `ValueError` otherwise.

    Returns:
        The `SkinCalibration` (its first stage restored as far as the file keeps it: the
        orientation, masks and fit figures are in `first_stage_summary` of `summary()`).

    Raises:
        ValueError: For a file that is not a calibration, is damaged, has another schema or
            a newer version, or is for another protocol or mesh than `recording`'s.
    """
    path = Path(path)

    def read(file: h5py.File) -> tuple[dict, dict]:
        stored = read_attributes(file)
        schema = stored.get("schema")
        if schema != SCHEMA:
            raise ValueError(f"{path} is not a diffeit calibration (schema {schema!r}, expected {SCHEMA!r})")
        version = int(stored.get("schema_version", -1))
        if version > SCHEMA_VERSION:
            raise ValueError(
                f"{path} is a calibration of schema version {version}, newer than this diffeit reads "
                f"({SCHEMA_VERSION}): update diffeit"
            )
        if version < 1:
            raise ValueError(
                f"{path} has calibration schema version {version}; this diffeit reads 1 to {SCHEMA_VERSION}"
            )
        arrays: dict[str, np.ndarray] = {}
        file.visititems(
            lambda name, item: arrays.__setitem__(name, item[()]) if isinstance(item, h5py.Dataset) else None
        )
        return arrays, stored

    arrays, attributes = read_checked(path, read, what="calibration file")
    try:
        return _from_stored(arrays, attributes, recording, path)
    except (KeyError, ValueError, TypeError, json.JSONDecodeError) as error:
        if isinstance(error, ValueError) and str(error).startswith(str(path)):
            raise
        raise ValueError(f"{path} is not a readable diffeit calibration: {error}") from error


# What each stored number may be: a file edited by hand or written by a faulty program is
# refused by name rather than read as other numbers (a NaN ringing had read as the default).
# Name -> (smallest, largest, the value that stands for "none" or None).
_STORED_NUMBERS = {
    "conductivity": (0.0, math.inf, None),
    "drive_current": (-math.inf, math.inf, None),  # A; not 0 either
    "electrode_margin": (0.0, math.inf, None),
    "misfit": (0.0, math.inf, None),
    "correlation": (-1.0, 1.0, None),
    "hyperparameter": (0.0, math.inf, -1.0),
    "noise_frames": (0.0, math.inf, None),
    "ringing": (0.0, _RINGING_CAP, -1.0),
    "contact_impedance_spread": (0.0, math.inf, -1.0),
}


# Arrays -> what their values must be besides finite: "positive", "non-negative", "nonzero" or
# "" (anything).
_STORED_ARRAYS = {
    "contact_impedance": "positive",
    "background_map": "positive",
    "readout/gains": "nonzero",
    "readout/weights": "",
    "noise": "non-negative",
    "reference": "",
    "model/electrode_shift": "",
    "position_map/coefficients": "",
    "position_map/region": "",
    "position_map/slope": "",
    "values/label_frame": "",
    "size_map/radius_coefficients": "",
    "size_map/depth_coefficients": "",
    "size_map/limits": "",
}


def _check_stored(arrays: dict, attributes: dict) -> None:
    """ValueError naming a stored number or array out of its range (`_STORED_NUMBERS`,
    `_STORED_ARRAYS`): NaN, infinite, of the wrong sign, a reading sign other than +-1, or a
    polarity other than -1, 0 (none) or +1."""
    for name, (low, high, none) in _STORED_NUMBERS.items():
        if name not in attributes:
            continue
        value = float(attributes[name])
        if value != none and not (math.isfinite(value) and low <= value <= high):
            raise ValueError(f"its {name} is {value!r}, not a finite number in [{low:g}, {high:g}]")
    for name in ("conductivity", "drive_current"):
        if float(attributes[name]) == 0:
            raise ValueError(f"its {name} is 0")
    polarity = float(attributes.get("polarity", 0))
    if polarity not in (-1, 0, 1):
        raise ValueError(f"its polarity is {polarity:g}, not -1, +1 or 0 (none)")
    for name, kind in _STORED_ARRAYS.items():
        if name not in arrays:
            continue
        values = np.asarray(arrays[name], float)
        if not np.all(np.isfinite(values)):
            raise ValueError(f"its {name} holds values that are not finite")
        wrong = {"positive": values <= 0, "non-negative": values < 0, "nonzero": values == 0}.get(kind, False)
        if np.any(wrong):
            raise ValueError(f"its {name} holds values that are not {kind}")
    if not np.all(np.abs(np.asarray(arrays["reading_sign"], float)) == 1):
        raise ValueError("its reading_sign holds values other than +-1")
    if ("position_map/region" in arrays) != ("position_map/slope" in arrays) or (
        "position_map/region" in arrays
        and (
            np.ndim(arrays["position_map/region"]) != 2
            or np.shape(arrays["position_map/region"])[0] < 2
            or np.shape(arrays["position_map/region"])[1] != 2
            or np.shape(arrays["position_map/slope"]) not in ((1, 2), (3, 2), (1, 3))
        )
    ):
        raise ValueError(
            "its position_map/region and slope are not a region (H, 2) and a shift (1, D) or affine slope (3, 2)"
        )
    frame = np.asarray(arrays.get("values/label_frame", _IDENTITY_FRAME), float)
    if frame.shape not in ((4,), (5,)) or (len(frame) == 5 and abs(frame[4]) != 1):
        raise ValueError(
            "its values/label_frame is not a labels' frame (ln scale, angle, offset x and y, handedness +-1)"
        )


def _stored_size_map(sizes: dict, arrays: dict, dimension: int) -> SizeMap:
    """The `SizeMap` a file keeps; ValueError naming what does not fit together."""
    length = float(sizes["length"])
    if not (math.isfinite(length) and length > 0):
        raise ValueError(f"its size map's length is {length!r}, not a positive number")
    limits = np.asarray(arrays["size_map/limits"], np.float64)
    if limits.shape != (2, 2) or np.any(limits[:, 0] > limits[:, 1]):
        raise ValueError("its size_map/limits is not two ranges (smallest, largest ln gain)")
    for name in ("radius", "depth"):
        degree, coefficients = sizes[f"{name}_degree"], arrays[f"size_map/{name}_coefficients"]
        terms = 0 if degree is None else _terms(np.zeros((1, dimension)), int(degree)).shape[1]
        if np.shape(coefficients) != (terms,):
            raise ValueError(
                f"its size_map/{name}_coefficients has shape {np.shape(coefficients)}; "
                f"degree {degree} has {terms} terms"
            )
    return SizeMap(
        *(None if sizes[f"{name}_degree"] is None else int(sizes[f"{name}_degree"]) for name in ("radius", "depth")),
        arrays["size_map/radius_coefficients"],
        arrays["size_map/depth_coefficients"],
        limits,
        length,
        sizes["errors"],
    )


def _stored_reference(arrays: dict, protocol: Protocol) -> np.ndarray | None:
    """The reference a file keeps (none before it was kept); ValueError for one that is not one
    frame of the protocol's readings."""
    reference = arrays.get("reference")
    if reference is not None and np.shape(reference) != (protocol.n_measurements,):
        raise ValueError(
            f"its reference has shape {np.shape(reference)}; the protocol's frames have {protocol.n_measurements} "
            "readings"
        )
    return reference


def _from_stored(arrays: dict, attributes: dict, recording: Recording | None, path: Path) -> SkinCalibration:
    _check_stored(arrays, attributes)
    offsets = arrays["mesh/electrode_offsets"]
    nodes = arrays["mesh/electrode_nodes"]
    mesh = Mesh(arrays["mesh/nodes"], arrays["mesh/triangles"], [nodes[a:b] for a, b in itertools.pairwise(offsets)])
    drive, drive_index = arrays["protocol/drive"], arrays["protocol/drive_index"]
    protocol = Protocol(drive, [arrays["protocol/measure"][drive_index == d] for d in range(len(drive))])
    if recording is not None:
        if recording.protocol != protocol:
            raise ValueError(f"{path} calibrates another protocol than the recording's")
        if recording.mesh is not None and recording.mesh != mesh:
            raise ValueError(f"{path} calibrates another mesh than the recording's")
    used = arrays["used"].astype(bool)
    measure = arrays["model/measure"]
    selected = protocol.select(used)
    model_protocol = Protocol(selected.drive, [measure[selected.drive_index == d] for d in range(selected.n_drives)])
    moved = {}
    if "model/electrode_shift" in arrays:
        moved = {
            "electrode_shift": arrays["model/electrode_shift"],
            "electrode_margin": float(attributes["electrode_margin"]),
        }
    model = ForwardModel(
        mesh, model_protocol, arrays["contact_impedance"], drive_current=float(attributes["drive_current"]), **moved
    )
    weights = arrays["readout/weights"]
    readout = Readout(selected, source=weights[0], sink=weights[1], offsets=weights[2:], gains=arrays["readout/gains"])
    stored = json.loads(attributes["json"])
    mapping = stored["position_map"]
    position_map = None
    if mapping is not None:
        position_map = PositionMap(
            mapping["degree"],
            arrays.get("position_map/coefficients", np.zeros((0, mesh.nodes.shape[1]))),
            mapping["length"],
            mapping["errors"],
            mesh if mesh.nodes.shape[1] == 3 else None,  # a curved skin's map takes touches onto it
            region=arrays.get("position_map/region"),  # none before version 7
            slope=arrays.get("position_map/slope"),
        )
    values = {name.split("/", 1)[1]: value for name, value in arrays.items() if name.startswith("values/")}
    errors = {name.split("/", 1)[1]: value for name, value in arrays.items() if name.startswith("standard_errors/")}
    if position_map is not None and "label_frame" in values and mesh.nodes.shape[1] == 2:
        frame = np.asarray(values["label_frame"], np.float64)
        position_map = position_map.held_to(mesh, frame if len(frame) == 5 else np.append(frame, 1.0))  # versions 1-4
    sizes = stored.get("size_map")  # none before version 6
    size_map = None if sizes is None else _stored_size_map(sizes, arrays, mesh.nodes.shape[1])
    first = stored["first_stage"]
    first_stage = ReferenceCalibration(
        model=model,
        conductivity=float(first["conductivity"]),
        contact_impedance=np.asarray(first["contact_impedance_per_electrode"]),
        used=used,
        reading_sign=arrays["reading_sign"],
        orientation=first["orientation"],
        orientations=first["orientations_misfit"],
        misfit=float(first["misfit"]),
        correlation=float(first["correlation"]),
        masked={reason: tuple(indices) for reason, indices in first["masked"].items()},
        broken_electrodes=tuple(first["broken_electrodes"]),
        driven_readings=first["driven_readings"],
        warnings=tuple(first["warnings"]),
    )
    hyperparameter = float(attributes["hyperparameter"])
    ringing = float(attributes.get("ringing", -1.0))  # none before it was kept
    # Kept within version 7: before, the presses were imaged with the contacts held.
    spread = float(attributes.get("contact_impedance_spread", -1.0 if hyperparameter < 0 else 0.0))
    return SkinCalibration(
        model=model,
        conductivity=float(attributes["conductivity"]),
        background_map=arrays.get("background_map"),
        contact_impedance=arrays["contact_impedance"],
        electrode_centres=_electrode_centres(
            mesh, None if model.electrode_shift is None else np.asarray(model.electrode_shift).mean(axis=1)
        ),
        readout=readout,
        used=used,
        reading_sign=arrays["reading_sign"],
        standard_errors=errors,
        values=values,
        undetermined=tuple(stored["undetermined"]),
        fitted={source: tuple(groups) for source, groups in stored["fitted"].items()},
        misfit=float(attributes["misfit"]),
        correlation=float(attributes["correlation"]),
        position_map=position_map,
        press_errors=arrays.get("press_errors"),
        press_positions=arrays.get("press_positions"),
        noise=arrays.get("noise"),
        noise_frames=int(attributes["noise_frames"]),
        polarity=int(attributes["polarity"]) or None,
        memory=None if stored["memory"] is None else MemoryParameters(**stored["memory"]),
        hyperparameter=None if hyperparameter < 0 else hyperparameter,
        first_stage=first_stage,
        warnings=tuple(stored["warnings"]),
        protocol=protocol,
        readings=str(attributes["readings"]),
        ringing=None if ringing < 0 else ringing,
        size_map=size_map,
        reference=_stored_reference(arrays, protocol),
        contact_impedance_spread=None if spread < 0 else spread,
    )
