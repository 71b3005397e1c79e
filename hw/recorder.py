"""The recorder: frames appended to a diffeit frames file as they arrive, safe against kills.

`Recorder(path, protocol, ...)` creates a frames file (`diffeit.io.write_frames`, no frames
yet), adds the `/acquisition` group and switches the file to single-writer/multiple-reader
(SWMR) mode. `append(frames, statistics)` writes each batch in this order: the rows of
`/frames`, `/times`, `/acquisition/counter` and `/acquisition/device_time`; a flush and an
fsync; then `/committed_frames` and `/acquisition/drops`; a flush and an fsync. Readers take the
first `/committed_frames` rows only, so a kill or a power cut at any instant loses at most the
batch being written (the recorder of `diffeit acquire` writes one frame a batch), and never
yields a half-written row. The file stays readable meanwhile and afterwards:
`diffeit.io.read_frames` (a `Recording`) and `read_recorded_frames` (`hw.Frame`s with counters
and timestamps). `close()` leaves SWMR mode. `read_frames` reports the committed drop
statistics in the provenance metadata (`drop_statistics`).

Additions to the frames file (all under `/acquisition`, written by the recorder only):

```
counter        (T,) int64: each frame's device counter, -1 for text lines (no counter)
device_time    (T,) float64: seconds on the device's clock, NaN for text lines (none)
drops          (K,) int64: the latest DropStatistics, attribute kinds (K,) names its entries
```
`/times` holds host times in seconds since `host_time_origin` (seconds since the Unix epoch,
in the provenance metadata): the recorder's start.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from diffeit.io import (
    CHUNK_ROWS,
    Recording,
    create_checked,
    drop_statistics,
    read_checked,
    read_frames,
    write_attributes,
    write_frames,
)
from diffeit.protocol import Protocol

from .frame import Frame, host_time
from .parser import DropStatistics

_KINDS = tuple(field.name for field in dataclasses.fields(DropStatistics))
_WHAT = "recorder's frames file"


class Recorder:
    """Appends frames under `protocol` to a new frames file at `path` (see the module docstring).

    - `metadata`: JSON-serialisable facts about the device and the run (port, baud rate,
      firmware, operator); stored in the provenance metadata with `host_time_origin`.
    - `source`: the provenance source line.
    - `reference`: (n_meas,) a reference frame, volts, or None.
    - `geometry`: the sheet, as `diffeit.io.Recording` takes it, or None.
    - `voltage_unit`: "V" (default) or "arbitrary" for devices reporting raw units.
    - `overwrite`: replace an existing file (default: refuse, `FileExistsError`).
    - `durable`: fsync after every batch (default), so a power cut loses at most that batch;
      False only flushes to the operating system (a killed process still loses nothing more).

    Use as a context manager (closes on exit, also after an exception).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        protocol: Protocol,
        *,
        metadata: Mapping[str, Any] | None = None,
        source: str = "hw.Recorder",
        reference: np.ndarray | None = None,
        geometry: Mapping[str, Any] | None = None,
        voltage_unit: str = "V",
        overwrite: bool = False,
        durable: bool = True,
    ) -> None:
        if not isinstance(protocol, Protocol):
            raise ValueError(f"protocol must be a diffeit.protocol.Protocol; got {type(protocol).__name__}")
        self.path = Path(path)
        self.protocol = protocol
        self.durable = durable
        self.host_time_origin = host_time()
        self._metadata = {**(metadata or {}), "host_time_origin": self.host_time_origin, "recorder": "hw.Recorder"}
        n_meas = protocol.n_measurements
        write_frames(
            self.path,
            Recording(
                frames=np.empty((0, n_meas)),
                times=np.empty(0),
                protocol=protocol,
                reference=reference,
                geometry=geometry,
                provenance={"source": source, "metadata": self._metadata},
                voltage_unit=voltage_unit,
            ),
            overwrite=overwrite,
        )
        self._file = h5py.File(self.path, "r+", libver="v110")
        acquisition = self._file.create_group("acquisition")
        for name, dtype in (("counter", np.int64), ("device_time", np.float64)):
            create_checked(acquisition, name, np.empty(0, dtype), maxshape=(None,), chunks=(CHUNK_ROWS,))
        write_attributes(acquisition["device_time"], {"units": "s"})
        drops = create_checked(acquisition, "drops", np.zeros(len(_KINDS), dtype=np.int64))
        write_attributes(drops, {"kinds": list(_KINDS)})
        # (1,), not a scalar: a chunked dataset carries a checksum, and SWMR readers see it change.
        create_checked(self._file, "committed_frames", np.zeros(1, dtype=np.int64))
        self._file.swmr_mode = True  # from here on: appends only, readable at every instant
        self._statistics = DropStatistics()
        self.n_frames = 0

    def append(self, frames: Frame | Sequence[Frame], statistics: DropStatistics | None = None) -> int:
        """Append a frame or a batch of frames (values in the recorder's protocol, volts) and,
        optionally, the source's latest statistics; returns the frames the file now holds.

        Raises `ValueError` for frames of another length or with non-finite values (the file
        is unchanged then), and for a closed recorder.
        """
        if self._file is None:
            raise ValueError(f"the recorder of {self.path} is closed")
        batch = [frames] if isinstance(frames, Frame) else list(frames)
        n_meas = self.protocol.n_measurements
        for frame in batch:
            if frame.n_values != n_meas:
                raise ValueError(f"a frame of {frame.n_values} values; {self.path} records {n_meas}-value frames")
            if not np.all(np.isfinite(frame.values)):
                raise ValueError("a frame holds non-finite values (NaN or inf); nothing was written")
        if statistics is not None:
            self._statistics = statistics
        if batch:
            now = host_time()
            host_times = [now if f.host_time is None else f.host_time for f in batch]
            device_times = [np.nan if f.device_time is None else f.device_time for f in batch]
            rows = {
                "frames": np.array([frame.values for frame in batch]),
                "times": np.array(host_times) - self.host_time_origin,
                "acquisition/counter": np.array([-1 if f.counter is None else f.counter for f in batch]),
                "acquisition/device_time": np.array(device_times),
            }
            start, end = self.n_frames, self.n_frames + len(batch)
            for name, values in rows.items():
                dataset = self._file[name]
                dataset.resize(end, axis=0)
                dataset[start:end] = values
            self._sync()
            self.n_frames = end
        self._file["committed_frames"][...] = self.n_frames
        self._file["acquisition/drops"][:] = [getattr(self._statistics, kind) for kind in _KINDS]
        self._sync()
        return self.n_frames

    def close(self) -> None:
        """Close the file, which leaves SWMR mode.

        The statistics are stored by `append`; nothing is written after the close, when a
        reader polling the file could hold its lock.
        """
        if self._file is None:
            return
        self._file.close()
        self._file = None

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def _sync(self) -> None:
        self._file.flush()
        if self.durable:
            os.fsync(self._file.id.get_vfd_handle())


def read_recorded_frames(path: str | os.PathLike) -> Iterator[Frame]:
    """The frames of a recorder's file as `hw.Frame`s (values, counter, device_time,
    host_time in seconds since the Unix epoch), in the order they arrived; also from a file
    whose recorder is still running or was killed (its committed frames)."""
    recording = read_frames(path)
    counters, device_times = _acquisition(path, recording.n_frames)
    origin = float(recording.provenance.get("metadata", {}).get("host_time_origin", 0.0))
    for values, time_, counter, device_time in zip(
        recording.frames, recording.times, counters, device_times, strict=True
    ):
        yield Frame(
            values,
            counter=None if counter < 0 else int(counter),
            device_time=None if np.isnan(device_time) else float(device_time),
            host_time=origin + float(time_),
        )


def recorded_statistics(path: str | os.PathLike) -> DropStatistics:
    """The drop statistics a recorder's file holds (the latest it committed)."""

    def read(file: h5py.File) -> DropStatistics:
        _acquisition_group(file, path)  # refuses a file hw.Recorder did not write, by name
        statistics = drop_statistics(file)
        if statistics is None:
            raise ValueError(f"{path}: /acquisition holds no drop statistics (/acquisition/drops)")
        return DropStatistics(**statistics)

    return read_checked(path, read, what=_WHAT, warn_unchecked=False)


def _acquisition(path: str | os.PathLike, n_frames: int) -> tuple[np.ndarray, np.ndarray]:
    def read(file: h5py.File) -> tuple[np.ndarray, np.ndarray]:
        acquisition = _acquisition_group(file, path)
        return acquisition["counter"][:n_frames], acquisition["device_time"][:n_frames]

    counters, device_times = read_checked(path, read, what=_WHAT, warn_unchecked=False)
    if len(counters) != n_frames or len(device_times) != n_frames:
        raise ValueError(f"{path}: /acquisition holds fewer rows than the {n_frames} committed frames")
    return counters, device_times


def _acquisition_group(file: h5py.File, path: str | os.PathLike) -> h5py.Group:
    if "acquisition" not in file:
        raise ValueError(f"{path} was not written by hw.Recorder (it has no /acquisition group)")
    return file["acquisition"]
