"""Generic CSV frames: one frame a row."""

from __future__ import annotations

import csv
import io
import math
import os
from pathlib import Path

import numpy as np

from .._messages import name_indices
from ..protocol import Protocol, adjacent
from ._recording import Recording


def checked_text(path: Path) -> str:
    """The text of a file of text rows: UTF-8 (a byte-order mark skipped), every line ended.

    Raises:
        ValueError: Naming the file and line, for bytes that are not UTF-8 (not a text file?)
            and for a last line without its newline (the file cut short, or its writer left the
            newline out).
    """
    data = path.read_bytes()
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as error:
        line = data[: error.start].count(b"\n") + 1
        raise ValueError(f"{path}: line {line} is not UTF-8 text (byte {error.start}): not a CSV file?") from None
    if text and not text.endswith(("\n", "\r")):
        raise ValueError(
            f"{path}: line {len(text.splitlines())}, the last, does not end in a newline: the file is cut short, or "
            "its writer left the newline out (add it if the last row is whole)"
        )
    return text


def read_csv(
    path: str | os.PathLike,
    protocol: Protocol | None = None,
    *,
    time_column: int | str | None = None,
    frame_rate: float = 1.0,
    delimiter: str = ",",
    voltage_unit: str = "V",
    header: bool | None = None,
) -> Recording:
    """Frames from a CSV file: one frame a row, one reading a column.

    An optional first row of column names and an optional column of times; the other columns
    are the readings, in the protocol's order and sign. A UTF-8 byte-order mark (Excel's "CSV
    UTF-8") is skipped. A CSV file carries no checksum: what the reader can and cannot detect
    is in docs/tutorials/real-recordings.md#what-the-readers-check.

    Arguments:
        path: The CSV file.
        protocol: The protocol of the readings; None chooses it from the number of reading
            columns: n(n-3) is `adjacent(n)` (208: 16 electrodes, EIDORS's order), n * n the
            full layout `adjacent(n, measure_driven=True)` (256;
            `diffeit.protocol.from_full_layout` drops the driven pairs).
        time_column: The name (or number, from 0) of a column of times, seconds; None: frame
            t is at t / `frame_rate` seconds.
        frame_rate: Frames per second, without a time column.
        delimiter: The field separator.
        voltage_unit: The unit of the readings (see `Recording`).
        header: Whether the first row holds column names; None decides: a first row that holds
            no number, or whose fields number the columns 0, 1, 2, ... or 1, 2, 3, ... (as pandas
            writes them; after one name, `t,0,1,2,...`), is a header, and any other first row
            is read as readings (pass `header=True` for other headers).

    Returns:
        The `Recording`, with `provenance["metadata"]` naming the file, the time column and
        the column names.

    Raises:
        FileNotFoundError: For a missing file.
        ValueError: Naming the file, row and column for rows of another length, non-numbers,
            non-finite values, an unknown time column, readings that fit no protocol (or not
            the one given); naming the file for text that is not UTF-8 or not CSV (a field over
            the csv module's limit, 128 kB), and a last row without its newline (a file cut
            short); and for a frame rate that is not positive.
    """
    path = Path(path)
    if not math.isfinite(frame_rate) or frame_rate <= 0:
        raise ValueError(f"frame_rate must be positive (frames per second); got {frame_rate}")
    if not path.exists():
        raise FileNotFoundError(f"no such CSV file: {path}")
    text = checked_text(path)
    reader = csv.reader(io.StringIO(text, newline=""), delimiter=delimiter)
    try:
        rows = [(number, row) for number, row in enumerate(reader, start=1) if row]
    except csv.Error as error:
        raise ValueError(f"{path}: line {reader.line_num} is not CSV: {error}") from None
    if header is None:
        header = bool(rows) and _is_header(rows[0][1])
    if header and rows:
        names, rows = [name.strip() for name in rows[0][1]], rows[1:]
    else:
        names = None
    if not rows:
        raise ValueError(f"{path} holds no rows of values")
    width = len(rows[0][1])
    uneven = [number for number, row in rows if len(row) != width]
    if uneven:
        raise ValueError(f"{path}: rows {name_indices(np.array(uneven))} do not have {width} columns as the first")
    values = np.empty((len(rows), width))
    for index, (number, row) in enumerate(rows):
        try:
            values[index] = [float(item) for item in row]
        except ValueError:
            column = next(c for c, item in enumerate(row) if not _numeric([item]))
            raise ValueError(f"{path}: row {number}, column {column} is not a number: {row[column]!r}") from None
    if not np.all(np.isfinite(values)):
        bad = np.flatnonzero(~np.all(np.isfinite(values), axis=1))
        raise ValueError(f"{path}: rows {name_indices(np.array([rows[i][0] for i in bad]))} hold non-finite values")
    if time_column is not None:
        if isinstance(time_column, str):
            if names is None or time_column not in names:
                raise ValueError(f"{path} has no column named {time_column!r}; columns: {names}")
            time_column = names.index(time_column)
        if not -width <= time_column < width:
            raise ValueError(f"{path} has {width} columns; no time column {time_column}")
        times = values[:, time_column]
        values = np.delete(values, time_column, axis=1)
    else:
        times = np.arange(len(values)) / frame_rate
    if protocol is None:
        protocol = _protocol_of(values.shape[1], path)
    if values.shape[1] != protocol.n_measurements:
        raise ValueError(f"{path} holds {values.shape[1]} readings a row; the protocol has {protocol.n_measurements}")
    return Recording(
        frames=values,
        times=times,
        protocol=protocol,
        provenance={
            "source": f"CSV file {path.name}",
            "metadata": {"file": str(path), "time_column": time_column, "columns": names},
        },
        voltage_unit=voltage_unit,
    )


def _protocol_of(n_readings: int, path: Path) -> Protocol:
    for n in range(4, 129):
        if n * (n - 3) == n_readings:
            return adjacent(n)
        if n * n == n_readings:
            return adjacent(n, measure_driven=True)
    raise ValueError(
        f"{path} holds {n_readings} readings a row: not n(n-3) (adjacent) nor n * n (the full adjacent layout); "
        "pass the protocol"
    )


def _is_header(items: list[str]) -> bool:
    """Whether a first row names the columns (`read_csv`'s rule): no number among its fields,
    or fields that number the columns, perhaps after one name."""
    if not any(_numeric([item]) for item in items):
        return True
    counted = items if _numeric(items[:1]) else items[1:]
    return _numeric(counted) and _numbers_columns(counted)


def _numbers_columns(items: list[str]) -> bool:
    """Whether a row of numbers counts the columns, 0.. or 1.. (a header of column indices); a
    frame of 8 readings or more never does."""
    values = np.array([float(item) for item in items])
    return len(values) >= 8 and any(np.array_equal(values, np.arange(len(values)) + first) for first in (0, 1))


def _numeric(items: list[str]) -> bool:
    try:
        [float(item) for item in items]
    except ValueError:
        return False
    return True
