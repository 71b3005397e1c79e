"""The frames file: `Recording`s in HDF5 (schema in the docstring of `diffeit.io`)."""

from __future__ import annotations

import datetime
import importlib.metadata
import itertools
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from numpy.typing import ArrayLike

from ..mesh import Mesh
from ..protocol import Protocol
from ._checked import (
    create_checked,
    open_checked,
    read_attributes,
    read_checked,
    write_atomically,
    write_attributes,
)
from ._recording import Recording

SCHEMA = "diffeit.frames"
# Version 2: every dataset checksummed, committed_frames of shape (1,). Version 1 files read,
# with a NoChecksumWarning.
SCHEMA_VERSION = 2
# Rows per HDF5 chunk of `frames` and `times`: about 100 kB for 208 readings, so appending one
# frame at a time touches one chunk and reading a few frames reads little.
CHUNK_ROWS = 64
_WHAT = "diffeit frames file"


def write_frames(path: str | os.PathLike, recording: Recording, *, overwrite: bool = False) -> Path:
    """Write a recording to a new frames file (HDF5) and return its path.

    Refuses an existing file unless `overwrite=True`: nothing recorded is lost by accident.
    The file is written under a temporary name beside `path` and renamed when complete
    (`write_atomically`), so an interrupted write leaves no half-written file at `path` (and,
    with `overwrite=True`, the old file intact). Fills in `provenance["created_utc"]` (now)
    and `provenance["diffeit_version"]` when the recording has none. The layout is in the
    docstring of `diffeit.io` and docs/conventions.md#the-frames-file.

    Arguments:
        path: The file to write.
        recording: The `Recording` to write.
        overwrite: Replace an existing file at `path`.

    Returns:
        `path`, as a `Path`.

    Raises:
        ValueError: For a `recording` that is not a `Recording`, or provenance metadata that
            is not JSON-serialisable (before anything is created).
        FileExistsError: For an existing `path` without `overwrite=True`.
        FileNotFoundError: When the folder of `path` does not exist.
    """
    if not isinstance(recording, Recording):
        raise ValueError(f"write_frames needs a diffeit.io.Recording; got {type(recording).__name__}")
    metadata = _metadata_json(recording.provenance.get("metadata", {}))  # fail before creating anything
    return write_atomically(path, lambda file: _write(file, recording, metadata), overwrite=overwrite)


def read_frames(path: str | os.PathLike) -> Recording:
    """Read a frames file written by `write_frames` (and perhaps grown by `append_frames`).

    Returns the file's data as written: all of it, or, of a file a recorder is writing (or
    was writing when it was killed), the frames it committed. Every dataset's checksum is
    verified, and damage is refused promptly, never read as data (`open_checked`).

    Arguments:
        path: The frames file.

    Returns:
        The `Recording`.

    Raises:
        FileNotFoundError: For a missing file.
        ValueError: Naming the file and the problem, for anything else: empty, not HDF5,
            truncated, altered bytes (a failed checksum), not a frames file, a newer schema
            version, missing datasets, wrong dtypes, shapes that disagree (frames wider or
            narrower than the protocol's readings, times not one per frame, images not one
            per frame and element), non-finite values.

    Warns:
        diffeit.io.NoChecksumWarning: For a file written before diffeit stored checksums
            (schema version 1).
    """
    path = Path(path)

    def read(file: h5py.File) -> Recording:
        try:
            return _read(file)
        except (KeyError, ValueError, TypeError) as error:
            raise ValueError(f"{path}: {_message(error)}") from None

    return read_checked(path, read, what=_WHAT)


def append_frames(path: str | os.PathLike, frames: ArrayLike, times: ArrayLike) -> int:
    """Append frames and their times to a frames file; return how many frames it now holds.

    Frames and times are checked first (shape, finiteness, and, for a file of magnitudes,
    whose frames attribute `readings` is "magnitude", no negative values); the file is
    unchanged when they fail. The file must hold no images: they would no longer match the
    frames.

    Arguments:
        path: A frames file written by `write_frames`.
        frames: (k, n_meas) frames, or one frame (n_meas,), in the file's units, protocol
            order and sign.
        times: (k,) their times, seconds.

    Returns:
        The number of frames the file holds after appending.

    Raises:
        FileNotFoundError: For a missing file.
        ValueError: For a file that is damaged or not a frames file, one marked open for
            writing (a recorder holds it, or was killed before closing it), one that holds
            images or uncommitted rows of an interrupted recorder; and for frames or times of
            the wrong shape, not finite, or negative for a file of magnitudes.
    """
    path = Path(path)
    frames = np.array(frames, dtype=np.float64)
    frames = frames[None] if frames.ndim == 1 else frames
    times = np.atleast_1d(np.array(times, dtype=np.float64))
    with open_checked(path, "r+", what=_WHAT) as file:
        try:
            _check_schema(file)
            stored, stored_times = _dataset(file, "frames"), _dataset(file, "times")
        except (KeyError, ValueError) as error:
            raise ValueError(f"{path}: {_message(error)}") from None
        if "images" in file:
            raise ValueError(f"{path} holds images of its frames; appending frames would leave them behind")
        n_old, n_meas = stored.shape
        if frames.ndim != 2 or frames.shape[1] != n_meas:
            raise ValueError(f"frames to append have shape {frames.shape}; {path} holds frames of {n_meas} readings")
        if times.shape != (len(frames),):
            raise ValueError(f"times have shape {times.shape}; expected ({len(frames)},), one per appended frame")
        if not (np.all(np.isfinite(frames)) and np.all(np.isfinite(times))):
            raise ValueError("frames or times to append hold non-finite values (NaN or inf)")
        if read_attributes(stored).get("readings") == "magnitude" and np.any(frames < 0):
            raise ValueError(
                f'{path} holds magnitudes (readings="magnitude"); the frames to append hold negative values'
            )
        if stored_times.shape != (n_old,):
            raise ValueError(f"{path}: times have shape {stored_times.shape}; frames {stored.shape}")
        committed = _committed_frames(file)
        if committed is not None and committed != n_old:
            raise ValueError(
                f"{path} holds {n_old} frame rows of which {committed} are committed (a recorder was interrupted); "
                "read it with read_frames and write a new file"
            )
        n_new = n_old + len(frames)
        stored.resize(n_new, axis=0)
        stored_times.resize(n_new, axis=0)
        stored[n_old:] = frames
        stored_times[n_old:] = times
        if committed is not None:
            file["committed_frames"][...] = n_new
    return n_new


# ---------------------------------------------------------------------------------------------


def _write(file: h5py.File, recording: Recording, metadata: str) -> None:
    provenance = recording.provenance
    write_attributes(
        file,
        {
            "schema": SCHEMA,
            "schema_version": SCHEMA_VERSION,
            "diffeit_version": provenance.get("diffeit_version", importlib.metadata.version("diffeit")),
            "created_utc": provenance.get("created_utc", _now()),
            "source": provenance.get("source", ""),
            "metadata": metadata,
        },
    )

    n_meas = recording.n_measurements
    frames = create_checked(file, "frames", recording.frames, maxshape=(None, n_meas), chunks=(CHUNK_ROWS, n_meas))
    write_attributes(frames, {"units": recording.voltage_unit, "readings": recording.readings})
    times = create_checked(file, "times", recording.times, maxshape=(None,), chunks=(CHUNK_ROWS,))
    write_attributes(times, {"units": "s"})
    if recording.reference is not None:
        reference = create_checked(file, "reference", recording.reference)
        write_attributes(reference, {"units": recording.voltage_unit})

    protocol = file.create_group("protocol")
    write_attributes(protocol, {"drive_units": "multiples of the model's drive current, positive into the sheet"})
    create_checked(protocol, "drive", recording.protocol.drive)
    create_checked(protocol, "measure", recording.protocol.measure)
    create_checked(protocol, "drive_index", recording.protocol.drive_index.astype(np.int64))

    if recording.mesh is not None:
        mesh = file.create_group("mesh")
        nodes = create_checked(mesh, "nodes", recording.mesh.nodes)
        write_attributes(nodes, {"units": "m"})
        create_checked(mesh, "triangles", recording.mesh.triangles.astype(np.int64))
        chains = recording.mesh.electrodes
        create_checked(mesh, "electrode_nodes", np.concatenate(chains).astype(np.int64))
        create_checked(mesh, "electrode_offsets", np.cumsum([0, *map(len, chains)]).astype(np.int64))
    if recording.geometry is not None:
        geometry = file.create_group("geometry")
        # None is every generator's default; HDF5 attributes cannot hold it.
        given = {key: value for key, value in recording.geometry.items() if value is not None}
        write_attributes(geometry, {"units": "m", **given})
    if recording.images is not None:
        images = create_checked(file, "images", recording.images)
        write_attributes(images, {"units": "S/sq", "quantity": recording.image_quantity})


def _read(file: h5py.File) -> Recording:
    _check_schema(file)
    attributes = read_attributes(file)
    provenance: dict[str, Any] = {
        key: str(attributes[key]) for key in ("source", "created_utc", "diffeit_version") if key in attributes
    }
    if "metadata" in attributes:
        try:
            provenance["metadata"] = json.loads(attributes["metadata"])
        except json.JSONDecodeError as error:
            raise ValueError(f"the 'metadata' attribute is not valid JSON: {error}") from None
    statistics = drop_statistics(file)
    if statistics is not None:  # in the metadata, beside what the recorder stored at the start
        provenance.setdefault("metadata", {})["drop_statistics"] = statistics
    drive = _dataset(file, "protocol/drive")[()]
    measure = _dataset(file, "protocol/measure")[()]
    drive_index = _dataset(file, "protocol/drive_index")[()]
    protocol = _protocol(drive, measure, drive_index)
    # A recorder may be appending (SWMR): the committed count first, then the datasets, refreshed,
    # hold at least the rows it counts (the recorder flushes the rows before the count).
    committed = _committed_frames(file)
    frames_dataset = _dataset(file, "frames")
    times_dataset = _dataset(file, "times")
    if file.swmr_mode:
        frames_dataset.refresh()
        times_dataset.refresh()
    frames = frames_dataset[()] if committed is None else frames_dataset[:committed]
    times = times_dataset[()] if committed is None else times_dataset[:committed]
    if committed is not None and not (committed <= len(frames_dataset) and committed <= len(times_dataset)):
        raise ValueError(
            f"committed_frames is {committed} but frames hold {len(frames_dataset)} rows and times {len(times_dataset)}"
        )
    if frames.ndim != 2 or frames.shape[1] != protocol.n_measurements:
        raise ValueError(
            f"frames have shape {frames.shape}; the protocol has {protocol.n_measurements} readings, "
            f"so frames must be (T, {protocol.n_measurements})"
        )
    mesh = None
    if "mesh" in file:
        nodes = _dataset(file, "mesh/nodes")[()]
        triangles = _dataset(file, "mesh/triangles")[()]
        electrode_nodes = _dataset(file, "mesh/electrode_nodes")[()]
        offsets = _dataset(file, "mesh/electrode_offsets")[()]
        if (
            offsets.ndim != 1
            or len(offsets) < 2
            or offsets[0] != 0
            or offsets[-1] != len(electrode_nodes)
            or np.any(np.diff(offsets) < 0)
        ):
            raise ValueError(
                f"mesh/electrode_offsets must rise from 0 to len(electrode_nodes) = {len(electrode_nodes)}; "
                f"got {offsets.tolist()}"
            )
        chains = [electrode_nodes[a:b] for a, b in itertools.pairwise(offsets)]
        mesh = Mesh.from_arrays(nodes, triangles, chains)
    geometry = None
    if "geometry" in file:
        attrs = read_attributes(file["geometry"])
        geometry = {key: _python(value) for key, value in attrs.items() if key != "units"}
    images, quantity = None, None
    if "images" in file:
        images = _dataset(file, "images")[()]
        quantity = str(read_attributes(file["images"]).get("quantity", "conductivity change"))
    return Recording(
        frames=frames,
        times=times,
        protocol=protocol,
        reference=_dataset(file, "reference")[()] if "reference" in file else None,
        mesh=mesh,
        geometry=geometry,
        provenance=provenance,
        images=images,
        image_quantity=quantity,
        voltage_unit=str(read_attributes(frames_dataset).get("units", "V")),
        # Files written before the attribute: signed.
        readings=str(read_attributes(frames_dataset).get("readings", "signed")),
    )


def _protocol(drive: np.ndarray, measure: np.ndarray, drive_index: np.ndarray) -> Protocol:
    if drive.ndim != 2 or measure.ndim != 2 or drive_index.shape != (len(measure),):
        raise ValueError(
            f"protocol datasets disagree: drive {drive.shape} (n_drives, L), measure {measure.shape} "
            f"(n_meas, L), drive_index {drive_index.shape} (n_meas,)"
        )
    if len(drive_index) and (np.any(np.diff(drive_index) < 0) or drive_index[0] < 0 or drive_index[-1] >= len(drive)):
        raise ValueError(f"protocol/drive_index must run drive by drive through 0..{len(drive) - 1}")
    return Protocol(drive, [measure[drive_index == k] for k in range(len(drive))])


def _check_schema(file: h5py.File) -> None:
    attributes = read_attributes(file)
    schema = attributes.get("schema")
    if schema != SCHEMA:
        raise ValueError(f"not a diffeit frames file (attribute 'schema' is {schema!r}, expected {SCHEMA!r})")
    version = int(attributes.get("schema_version", 0))
    if not 1 <= version <= SCHEMA_VERSION:
        raise ValueError(
            f"schema version {version}; this diffeit reads versions 1..{SCHEMA_VERSION} (a newer diffeit wrote it?)"
        )


def _committed_frames(file: h5py.File) -> int | None:
    """The committed frame count of a recorder's file, None when the file has none."""
    if "committed_frames" not in file:
        return None
    value = np.asarray(_dataset(file, "committed_frames")[()])
    # () in schema version 1, (1,) since: a chunked dataset can carry a checksum.
    if value.shape not in ((), (1,)) or not np.issubdtype(value.dtype, np.integer) or value.ravel()[0] < 0:
        raise ValueError(f"committed_frames must be one non-negative integer; got {value!r}")
    return int(value.ravel()[0])


# The dtype each dataset must have: numbers of a kind, so that strings, compound types or a
# float where an index belongs are refused by name instead of failing somewhere later.
_KINDS = {
    "frames": np.floating,
    "times": np.floating,
    "reference": np.floating,
    "images": np.floating,
    "protocol/drive": np.number,
    "protocol/measure": np.number,
    "protocol/drive_index": np.integer,
    "mesh/nodes": np.floating,
    "mesh/triangles": np.integer,
    "mesh/electrode_nodes": np.integer,
    "mesh/electrode_offsets": np.integer,
    "committed_frames": np.integer,
}


def drop_statistics(file: h5py.File) -> dict[str, int] | None:
    """A recorder's latest drop statistics (`/acquisition/drops`, hw.DropStatistics's fields)
    in an open frames file, by kind; None in a file without them.

    Arguments:
        file: The open file (read while a recorder may still write it: SWMR is refreshed).

    Returns:
        Kind -> count, or None.

    Raises:
        ValueError: For a drops dataset that is not one integer per kind.
    """
    if "acquisition/drops" not in file:
        return None
    drops = _dataset(file, "acquisition/drops")
    if file.swmr_mode:
        drops.refresh()
    kinds = [str(kind) for kind in read_attributes(drops)["kinds"]]
    return {kind: int(value) for kind, value in zip(kinds, drops[()], strict=True)}


def _dataset(file: h5py.File, name: str) -> h5py.Dataset:
    if name not in file:
        raise ValueError(f"the dataset {name!r} is missing")
    dataset = file[name]
    if not isinstance(dataset, h5py.Dataset):
        raise ValueError(f"{name!r} is not a dataset")
    kind = _KINDS.get(name)
    if kind is not None and not np.issubdtype(dataset.dtype, kind):
        expected = {np.floating: "floating-point numbers", np.integer: "integers", np.number: "numbers"}[kind]
        raise ValueError(f"the dataset {name!r} holds {dataset.dtype}; it must hold {expected}")
    return dataset


def _metadata_json(metadata: Mapping[str, Any]) -> str:
    try:
        return json.dumps(metadata, default=_jsonable)
    except (TypeError, ValueError) as error:
        raise ValueError(f"provenance metadata must be JSON-serialisable: {error}") from None


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} {value!r} is not JSON-serialisable")


def _python(value: Any) -> Any:
    """An HDF5 attribute as a Python value: numpy scalars to int/float/bool/str, arrays kept."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, bytes):
        return value.decode()
    return value


def _now() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


def _message(error: Exception) -> str:
    # KeyError's str() adds quotes; the others are already sentences.
    return error.args[0] if isinstance(error, KeyError) and error.args else str(error)
