"""The frames file: `Recording`s in HDF5 (schema in the docstring of `diffeit.io`)."""

from __future__ import annotations

import contextlib
import datetime
import importlib.metadata
import itertools
import json
import os
import time
import uuid
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from numpy.typing import ArrayLike

from ..mesh import Mesh
from ..protocol import Protocol
from ._recording import Recording

SCHEMA = "diffeit.frames"
SCHEMA_VERSION = 1
# Rows per HDF5 chunk of `frames` and `times`: about 100 kB for 208 readings, so appending one
# frame at a time touches one chunk and reading a few frames reads little.
_CHUNK_ROWS = 64
# Seconds a reader waits while another process holds a file's lock.
_LOCK_WAIT = 5.0
# HDF5 file format 1.10 or later: what single-writer/multiple-reader (SWMR) mode needs, so a
# recorder can append while a viewer reads.
_LIBVER = "v110"


def write_frames(path: str | os.PathLike, recording: Recording, *, overwrite: bool = False) -> Path:
    """Write `recording` to a new frames file at `path` (HDF5) and return the path.

    Refuses an existing file (`FileExistsError`) unless `overwrite=True`: nothing recorded is
    lost by accident. The file is written under a temporary name beside `path` and renamed
    when complete, so an interrupted write leaves no half-written file at `path` (and, with
    `overwrite=True`, the old file intact). Fills in `provenance["created_utc"]` (now) and
    `provenance["diffeit_version"]` when the recording has none.
    """
    if not isinstance(recording, Recording):
        raise ValueError(f"write_frames needs a diffeit.io.Recording; got {type(recording).__name__}")
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it")
    if not path.parent.is_dir():
        raise FileNotFoundError(f"the folder of {path} does not exist")
    metadata = _metadata_json(recording.provenance.get("metadata", {}))  # fail before creating anything
    # Not tempfile.mkstemp: its files are private (mode 0600); h5py creates with the umask's mode.
    temporary = path.with_name(f".{path.name}.{uuid.uuid4().hex[:12]}.partial")
    try:
        with h5py.File(temporary, "x", libver=_LIBVER) as file:
            _write(file, recording, metadata)
        _publish(temporary, path, overwrite)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(temporary)
    return path


def read_frames(path: str | os.PathLike) -> Recording:
    """Read a frames file written by `write_frames` (and perhaps grown by `append_frames`).

    Raises `FileNotFoundError` for a missing file and `ValueError` naming the file and the
    problem for anything else: not HDF5, not a frames file, a newer schema version, missing
    datasets, shapes that disagree (frames wider or narrower than the protocol's readings,
    times not one per frame, images not one per frame and element), non-finite values.
    """
    path = Path(path)
    with _open(path, "r") as file:
        try:
            return _read(file)
        except (KeyError, ValueError, TypeError) as error:
            raise ValueError(f"{path}: {_message(error)}") from None


def append_frames(path: str | os.PathLike, frames: ArrayLike, times: ArrayLike) -> int:
    """Append frames (k, n_meas) (or one frame (n_meas,)) and their times (k,) in seconds to
    the frames file at `path`; returns the number of frames the file now holds.

    The file must hold no images (they would no longer match the frames). Frames and times
    are checked for shape and finiteness, and frames of a file of magnitudes (frames attribute
    readings = "magnitude") for negative values, first (`ValueError`); the file is unchanged then.
    """
    path = Path(path)
    frames = np.array(frames, dtype=np.float64)
    frames = frames[None] if frames.ndim == 1 else frames
    times = np.atleast_1d(np.array(times, dtype=np.float64))
    with _open(path, "r+") as file:
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
        if stored.attrs.get("readings") == "magnitude" and np.any(frames < 0):
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
            file["committed_frames"][()] = n_new
    return n_new


# ---------------------------------------------------------------------------------------------


def _write(file: h5py.File, recording: Recording, metadata: str) -> None:
    provenance = recording.provenance
    file.attrs["schema"] = SCHEMA
    file.attrs["schema_version"] = SCHEMA_VERSION
    file.attrs["diffeit_version"] = provenance.get("diffeit_version", importlib.metadata.version("diffeit"))
    file.attrs["created_utc"] = provenance.get("created_utc", _now())
    file.attrs["source"] = provenance.get("source", "")
    file.attrs["metadata"] = metadata

    n_meas = recording.n_measurements
    frames = file.create_dataset("frames", data=recording.frames, maxshape=(None, n_meas), chunks=(_CHUNK_ROWS, n_meas))
    frames.attrs["units"] = recording.voltage_unit
    frames.attrs["readings"] = recording.readings
    times = file.create_dataset("times", data=recording.times, maxshape=(None,), chunks=(_CHUNK_ROWS,))
    times.attrs["units"] = "s"
    if recording.reference is not None:
        reference = file.create_dataset("reference", data=recording.reference)
        reference.attrs["units"] = recording.voltage_unit

    protocol = file.create_group("protocol")
    protocol.attrs["drive_units"] = "multiples of the model's drive current, positive into the sheet"
    protocol.create_dataset("drive", data=recording.protocol.drive)
    protocol.create_dataset("measure", data=recording.protocol.measure)
    protocol.create_dataset("drive_index", data=recording.protocol.drive_index.astype(np.int64))

    if recording.mesh is not None:
        mesh = file.create_group("mesh")
        nodes = mesh.create_dataset("nodes", data=recording.mesh.nodes)
        nodes.attrs["units"] = "m"
        mesh.create_dataset("triangles", data=recording.mesh.triangles.astype(np.int64))
        chains = recording.mesh.electrodes
        mesh.create_dataset("electrode_nodes", data=np.concatenate(chains).astype(np.int64))
        mesh.create_dataset("electrode_offsets", data=np.cumsum([0, *map(len, chains)]).astype(np.int64))
    if recording.geometry is not None:
        geometry = file.create_group("geometry")
        geometry.attrs["units"] = "m"
        for key, value in recording.geometry.items():
            if value is not None:  # every generator's None default; HDF5 attributes cannot hold None
                geometry.attrs[key] = value
    if recording.images is not None:
        images = file.create_dataset("images", data=recording.images)
        images.attrs["units"] = "S/sq"
        images.attrs["quantity"] = recording.image_quantity


def _read(file: h5py.File) -> Recording:
    _check_schema(file)
    provenance: dict[str, Any] = {
        key: str(file.attrs[key]) for key in ("source", "created_utc", "diffeit_version") if key in file.attrs
    }
    if "metadata" in file.attrs:
        try:
            provenance["metadata"] = json.loads(file.attrs["metadata"])
        except json.JSONDecodeError as error:
            raise ValueError(f"the 'metadata' attribute is not valid JSON: {error}") from None
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
        attrs = file["geometry"].attrs
        geometry = {key: _python(attrs[key]) for key in attrs if key != "units"}
    images, quantity = None, None
    if "images" in file:
        images = _dataset(file, "images")[()]
        quantity = str(file["images"].attrs.get("quantity", "conductivity change"))
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
        voltage_unit=str(frames_dataset.attrs.get("units", "V")),
        readings=str(frames_dataset.attrs.get("readings", "signed")),  # files written before the attribute: signed
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
    schema = file.attrs.get("schema")
    if schema != SCHEMA:
        raise ValueError(f"not a diffeit frames file (attribute 'schema' is {schema!r}, expected {SCHEMA!r})")
    version = int(file.attrs.get("schema_version", 0))
    if not 1 <= version <= SCHEMA_VERSION:
        raise ValueError(
            f"schema version {version}; this diffeit reads versions 1..{SCHEMA_VERSION} (a newer diffeit wrote it?)"
        )


def _committed_frames(file: h5py.File) -> int | None:
    """The committed frame count of a recorder's file, None when the file has none."""
    if "committed_frames" not in file:
        return None
    value = _dataset(file, "committed_frames")[()]
    if np.ndim(value) != 0 or not np.issubdtype(np.asarray(value).dtype, np.integer) or value < 0:
        raise ValueError(f"committed_frames must be a non-negative integer; got {value!r}")
    return int(value)


def _dataset(file: h5py.File, name: str) -> h5py.Dataset:
    if name not in file:
        raise ValueError(f"the dataset {name!r} is missing")
    dataset = file[name]
    if not isinstance(dataset, h5py.Dataset):
        raise ValueError(f"{name!r} is not a dataset")
    return dataset


@contextlib.contextmanager
def _open(path: Path, mode: str):
    if not path.exists():
        raise FileNotFoundError(f"no such frames file: {path}")
    try:
        file = _open_locked(path, mode)
    except OSError as error:
        if mode != "r":
            if "already open for write" in str(error):
                raise ValueError(
                    f"{path} is marked open for writing: a recorder is still writing it, or was killed before it "
                    "closed the file. Its frames read as they are (read_frames); to append, first clear the mark "
                    f"with `h5clear -s {path}` (Debian package hdf5-tools)"
                ) from None
            raise ValueError(f"{path} is not a writable HDF5 file ({error})") from None
        try:
            # A file a recorder is writing, or was writing when it was killed, is marked open
            # for writing; single-writer/multiple-reader access reads it all the same.
            file = _open_locked(path, "r", swmr=True)
        except OSError:
            raise ValueError(f"{path} is not a readable HDF5 file ({error})") from None
    with file:
        yield file


def _open_locked(path: Path, mode: str, **options: Any) -> h5py.File:
    """h5py.File, waiting up to _LOCK_WAIT seconds while another process holds the file's lock
    (a recorder creating the file, or reopening it as it closes)."""
    deadline = time.monotonic() + _LOCK_WAIT
    while True:
        try:
            return h5py.File(path, mode, **options)
        except BlockingIOError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.02)


def _publish(temporary: Path, path: Path, overwrite: bool) -> None:
    """Move the finished file into place; without `overwrite`, never replace a file that
    appeared meanwhile (a hard link fails when the name exists)."""
    if overwrite:
        os.replace(temporary, path)
        return
    try:
        os.link(temporary, path)
    except FileExistsError:
        raise FileExistsError(f"{path} exists; pass overwrite=True to replace it") from None
    except OSError:  # file systems without hard links
        if path.exists():
            raise FileExistsError(f"{path} exists; pass overwrite=True to replace it") from None
        os.replace(temporary, path)


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
