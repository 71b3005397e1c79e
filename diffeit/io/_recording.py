"""`Recording`: frames with their protocol, sheet, times and provenance, in memory."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import equinox as eqx
import numpy as np
from numpy.typing import ArrayLike

from .._arrays import readonly
from .._messages import name_indices
from ..mesh import Mesh, cylinder_patch, disc, polygon, rectangle, sphere_cap
from ..protocol import Protocol

PROVENANCE_KEYS = ("source", "created_utc", "diffeit_version", "metadata")
# The generators a geometry description may name; their keyword arguments are its other entries.
_GENERATORS = {
    "disc": disc,
    "rectangle": rectangle,
    "polygon": polygon,
    "cylinder_patch": cylinder_patch,
    "sphere_cap": sphere_cap,
}
GEOMETRY_KINDS = tuple(_GENERATORS)
# What a reading is: a signed voltage, or its magnitude |V| from instruments that lose the sign.
READINGS = ("signed", "magnitude")


class Recording(eqx.Module):
    """Frames of boundary voltages, simulated, recorded or reconstructed, with what they need.

    Built from keyword arguments named as the attributes. Arrays are stored as read-only
    float64 copies; construction checks shapes and finiteness. A recording is an
    `equinox.Module`: the arrays, geometry and provenance are its leaves; protocol, mesh,
    image_quantity, voltage_unit and readings are static fields. `write_frames` and
    `read_frames` store it (docs/conventions.md#the-frames-file).

    Attributes:
        frames: (T, n_meas) voltages, one row per frame, in `protocol`'s order and sign; T may
            be 0 (a recording that frames will be appended to).
        times: (T,) seconds, the acquisition (or simulation) time of each frame.
        protocol: The `diffeit.protocol.Protocol` the frames were taken under.
        reference: (n_meas,) the reference frame of difference imaging (a homogeneous tank,
            the untouched skin), or None.
        mesh: The sheet's `Mesh`, or None; it must have the protocol's number of electrodes.
        geometry: A description of the sheet for a mesh generator, or None: `{"kind": "disc",
            ...}` with the keyword arguments of `diffeit.mesh.disc` (likewise "rectangle",
            "polygon"), for example `{"kind": "disc", "n_electrodes": 16, "electrode_width":
            0.2, "h": 0.05, "radius": 1.0}` (lengths in metres). See `resolve_mesh`.
        provenance: `source` (str, what made the frames), `created_utc` (ISO 8601 UTC, when),
            `diffeit_version` (str), `metadata` (a JSON-serialisable dict, free-form); all
            optional, no other keys; `write_frames` fills in `created_utc` and
            `diffeit_version` when absent.
        images: (T, E) element-wise images of the frames on `mesh` (E = mesh.n_elements),
            S/sq, or None. A recording with images needs its mesh.
        image_quantity: What `images` hold: "conductivity change" (difference imaging,
            against the reference) or "conductivity"; None without images.
        voltage_unit: The unit of `frames` and `reference`: "V" (volts, the default) for
            diffeit's simulations and calibrated hardware, "arbitrary" for data in device
            units (EIDORS files, ADC counts).
        readings: What a value of `frames` and `reference` is: "signed" (default), the reading
            in `protocol`'s sign; or "magnitude", its absolute value |V|, from instruments that
            report magnitudes and lose the sign (OpenEIT-class boards, the Montreal 1995 EIDORS
            set), never negative. A reconstruction restores the signs from a calibrated model.

    Raises:
        ValueError: Naming the problem, for a protocol or mesh of the wrong type, a mesh
            whose electrodes the protocol does not address, arrays of the wrong shape or not
            finite, an unknown geometry kind, provenance keys outside the schema or of the
            wrong type, images without a mesh or without `image_quantity` (or the quantity
            without images), an empty `voltage_unit`, an unknown `readings`, or negative
            values with `readings="magnitude"`.
    """

    frames: np.ndarray
    times: np.ndarray
    protocol: Protocol = eqx.field(static=True)
    reference: np.ndarray | None
    mesh: Mesh | None = eqx.field(static=True)
    geometry: dict[str, Any] | None
    provenance: dict[str, Any]
    images: np.ndarray | None
    image_quantity: str | None = eqx.field(static=True)
    voltage_unit: str = eqx.field(static=True)
    readings: str = eqx.field(static=True)

    def __init__(
        self,
        *,
        frames: ArrayLike,
        times: ArrayLike,
        protocol: Protocol,
        reference: ArrayLike | None = None,
        mesh: Mesh | None = None,
        geometry: Mapping[str, Any] | None = None,
        provenance: Mapping[str, Any] | None = None,
        images: ArrayLike | None = None,
        image_quantity: str | None = None,
        voltage_unit: str = "V",
        readings: str = "signed",
    ) -> None:
        if not isinstance(protocol, Protocol):
            raise ValueError(f"protocol must be a diffeit.protocol.Protocol; got {type(protocol).__name__}")
        n_meas = protocol.n_measurements
        frames = _finite_array("frames", frames, (None, n_meas), f"(T, {n_meas}): one value per reading")
        n_frames = len(frames)
        times = _finite_array("times", times, (n_frames,), f"({n_frames},): one time per frame, seconds")
        if reference is not None:
            reference = _finite_array("reference", reference, (n_meas,), f"({n_meas},): one frame")
        if mesh is not None:
            if not isinstance(mesh, Mesh):
                raise ValueError(f"mesh must be a diffeit Mesh; got {type(mesh).__name__}")
            if mesh.n_electrodes != protocol.n_electrodes:
                raise ValueError(
                    f"the mesh has {mesh.n_electrodes} electrodes; the protocol addresses {protocol.n_electrodes}"
                )
        geometry = None if geometry is None else _checked_geometry(geometry)
        provenance = _checked_provenance({} if provenance is None else provenance)
        if images is not None:
            if mesh is None:
                raise ValueError("images need the mesh they live on: pass mesh=")
            n_elements = mesh.n_elements
            images = _finite_array("images", images, (n_frames, n_elements), f"({n_frames}, {n_elements})")
            if not isinstance(image_quantity, str) or not image_quantity:
                raise ValueError('images need image_quantity, e.g. "conductivity change" or "conductivity"')
        elif image_quantity is not None:
            raise ValueError("image_quantity is given without images")
        if not isinstance(voltage_unit, str) or not voltage_unit:
            raise ValueError(f'voltage_unit must be a non-empty string such as "V"; got {voltage_unit!r}')
        if not isinstance(readings, str) or readings not in READINGS:
            raise ValueError(f"readings must be one of {READINGS}; got {readings!r}")
        if readings == "magnitude":
            _check_magnitudes("frames", frames)
            if reference is not None:
                _check_magnitudes("reference", reference)
        self.frames = frames
        self.times = times
        self.protocol = protocol
        self.reference = reference
        self.mesh = mesh
        self.geometry = geometry
        self.provenance = provenance
        self.images = images
        self.image_quantity = image_quantity
        self.voltage_unit = voltage_unit
        self.readings = readings

    @property
    def n_frames(self) -> int:
        """T, the number of frames."""
        return self.frames.shape[0]

    @property
    def n_measurements(self) -> int:
        """n_meas, the number of readings a frame."""
        return self.frames.shape[1]

    def difference(self, *, reference_frame: int | None = None, relative: bool = False) -> np.ndarray:
        """The frames minus the reference, absolute or relative.

        Arguments:
            reference_frame: The index of the frame to use as the reference; None uses
                `reference`.
            relative: Return the relative (normalised) difference (V - V_ref) / V_ref,
                unit-free, instead of V - V_ref in `voltage_unit`.

        Returns:
            (T, n_meas) differences.

        Raises:
            ValueError: When there is no reference, the reference frame is out of range, or
                (relative) the reference has zero entries.
        """
        reference = self.reference_values(reference_frame)
        difference = self.frames - reference
        if not relative:
            return difference
        zero = np.flatnonzero(reference == 0)
        if len(zero):
            raise ValueError(f"the reference is zero at readings {name_indices(zero)}: no relative difference")
        return difference / reference

    def reference_values(self, reference_frame: int | None = None) -> np.ndarray:
        """The reference frame of difference imaging.

        Arguments:
            reference_frame: The index of the frame to use; None uses `reference`.

        Returns:
            (n_meas,) the reference, in `voltage_unit`.

        Raises:
            ValueError: When there is no reference or the frame is out of range.
        """
        if reference_frame is None:
            if self.reference is None:
                raise ValueError("the recording has no reference frame; name one of its frames as the reference")
            return self.reference
        if not -self.n_frames <= reference_frame < self.n_frames:
            raise ValueError(f"reference frame {reference_frame} is out of range: the recording has {self.n_frames}")
        return self.frames[reference_frame]

    def resolve_mesh(self) -> Mesh:
        """The sheet's mesh: `mesh` when present, else generated from `geometry`.

        Returns:
            The `Mesh`.

        Raises:
            ValueError: When the recording has neither, or the geometry does not fit its
                generator.
        """
        if self.mesh is not None:
            return self.mesh
        if self.geometry is None:
            raise ValueError("the recording has neither a mesh nor a geometry description of its sheet")
        return mesh_from_geometry(self.geometry)


def mesh_from_geometry(geometry: Mapping[str, Any]) -> Mesh:
    """The mesh a geometry description names.

    `{"kind": "disc", **keywords}` calls `diffeit.mesh.disc(**keywords)`; likewise
    "rectangle", "polygon", and the curved skins "cylinder_patch" and "sphere_cap". A frames
    file's geometry is such a description.

    Arguments:
        geometry: A mapping of "kind" and that generator's keyword arguments (lengths in
            metres, angles in radians), e.g. `{"kind": "disc", "h": 0.05}`.

    Returns:
        The generator's `diffeit.mesh.Mesh`.

    Raises:
        ValueError: For a geometry that is not a mapping, an unknown kind, a
            keyword the generator does not take, and from the generator for values it refuses.
    """
    geometry = _checked_geometry(geometry)
    keywords = {k: v for k, v in geometry.items() if k != "kind"}
    generator = _GENERATORS[geometry["kind"]]
    try:
        return generator(**keywords)
    except TypeError as error:  # an unknown keyword: say which generator refused what
        raise ValueError(f"geometry {dict(geometry)} does not fit diffeit.mesh.{geometry['kind']}: {error}") from None


def _finite_array(name: str, values: Any, shape: tuple[int | None, ...], expected: str) -> np.ndarray:
    """A read-only float64 copy of `values`, checked for shape (None: any length) and finiteness."""
    try:
        array = np.array(values, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{name} must be an array of numbers: {error}") from None
    if array.ndim != len(shape) or any(n is not None and n != m for n, m in zip(shape, array.shape, strict=True)):
        raise ValueError(f"{name} has shape {array.shape}; expected {expected}")
    if not np.all(np.isfinite(array)):
        rows = np.flatnonzero(~np.isfinite(array).reshape(len(array), -1).all(axis=1))
        where = f"frame(s) {name_indices(rows)}" if array.ndim == 2 else f"entries {name_indices(rows)}"
        raise ValueError(f"{name} hold non-finite values (NaN or inf) in {where}")
    return readonly(array)


def _check_magnitudes(name: str, values: np.ndarray) -> None:
    """Refuse negative values in frames or a reference of magnitudes."""
    negative = values < 0
    if np.any(negative):
        where = (
            f"frame(s) {name_indices(np.flatnonzero(negative.any(axis=1)))}"
            if values.ndim == 2
            else f"entries {name_indices(np.flatnonzero(negative))}"
        )
        raise ValueError(
            f'{name} hold negative values in {where} but readings="magnitude" (|V|, never negative); '
            'signed readings need readings="signed"'
        )


def _checked_geometry(geometry: Mapping[str, Any]) -> dict[str, Any]:
    if not isinstance(geometry, Mapping):
        raise ValueError(f"geometry must be a dict such as {{'kind': 'disc', 'h': 0.05}}; got {geometry!r}")
    kind = geometry.get("kind")
    if kind not in GEOMETRY_KINDS:
        raise ValueError(f"geometry kind must be one of {GEOMETRY_KINDS}; got {kind!r}")
    return dict(geometry)


def _checked_provenance(provenance: Mapping[str, Any]) -> dict[str, Any]:
    if not isinstance(provenance, Mapping):
        raise ValueError(f"provenance must be a dict with keys among {PROVENANCE_KEYS}; got {provenance!r}")
    unknown = sorted(set(provenance) - set(PROVENANCE_KEYS))
    if unknown:
        raise ValueError(
            f"provenance keys {unknown} are not part of the schema (keys: {PROVENANCE_KEYS}); "
            "put free-form entries under 'metadata'"
        )
    for key in ("source", "created_utc", "diffeit_version"):
        if key in provenance and not isinstance(provenance[key], str):
            raise ValueError(f"provenance {key!r} must be a string; got {provenance[key]!r}")
    if "metadata" in provenance and not isinstance(provenance["metadata"], Mapping):
        raise ValueError(f"provenance 'metadata' must be a dict; got {provenance['metadata']!r}")
    return dict(provenance)
