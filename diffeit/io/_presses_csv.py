"""Labelled presses from a CSV file: one press a row."""

from __future__ import annotations

import csv
import io
import math
import os
from pathlib import Path

from ._csv import checked_text
from ._presses import Presses

# The columns: where, how wide, and either an instant or a hold's start and end.
PLACE_COLUMNS = ("x_m", "y_m", "radius_m")
INSTANT_COLUMNS = ("time_s",)
HOLD_COLUMNS = ("start_s", "end_s")


def read_presses(path: str | os.PathLike) -> Presses:
    """Labelled presses (`Presses`) from a CSV file, strictly: one header row, then one press a row.

    The header names the columns `x_m,y_m,radius_m,time_s` (the instant each press is held) or
    `x_m,y_m,radius_m,start_s,end_s` (each hold's start and end), in any order, and a `z_m`
    column too for points on a curved skin; other columns (a label, a force) are ignored.
    Metres and seconds on the recording's clock. A UTF-8 byte-order mark is skipped and blank
    lines are ignored.

    Arguments:
        path: The CSV file.

    Returns:
        The `Presses`, one per row, in the file's order.

    Raises:
        FileNotFoundError: For a missing file.
        ValueError: Naming the file (and line) for text that is not UTF-8 or not CSV, a last
            line without its newline (a file cut short), a missing column (or both `time_s` and
            `start_s`/`end_s`), a row of another length than the header, a value that is not a
            number or is not finite (NaN, inf), a radius that is not positive, a hold that ends
            before it starts, and a file with no presses.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no such presses file: {path}")
    text = checked_text(path)
    reader = csv.reader(io.StringIO(text, newline=""))
    try:
        rows = [(reader.line_num, row) for row in reader if any(item.strip() for item in row)]
    except csv.Error as error:
        raise ValueError(f"{path}: line {reader.line_num} is not CSV: {error}") from None
    if not rows:
        raise ValueError(f"{path} is empty: expected a header row ({','.join(PLACE_COLUMNS + INSTANT_COLUMNS)})")
    header_line, names = rows[0][0], [name.strip() for name in rows[0][1]]
    times = _time_columns(names, path, header_line)
    place = (*PLACE_COLUMNS[:2], "z_m", PLACE_COLUMNS[2]) if "z_m" in names else PLACE_COLUMNS
    repeated = sorted({name for name in names if names.count(name) > 1} & set(place + times))
    if repeated:
        raise ValueError(f"{path}: line {header_line} (the header) names column(s) {repeated} more than once")
    wanted = [names.index(name) for name in place + times]
    radius = len(place) - 1  # the radius's place among the numbers of a row
    values = []
    for line, row in rows[1:]:
        if len(row) != len(names):
            raise ValueError(f"{path}: line {line} has {len(row)} columns; the header has {len(names)}")
        numbers = []
        for column in wanted:
            try:
                number = float(row[column])
            except ValueError:
                raise ValueError(
                    f"{path}: line {line}, column {names[column]} is not a number: {row[column]!r}"
                ) from None
            if not math.isfinite(number):
                raise ValueError(f"{path}: line {line}, column {names[column]} is not finite: {row[column]!r}")
            numbers.append(number)
        if numbers[radius] <= 0:
            raise ValueError(f"{path}: line {line}: radius_m must be positive, metres; got {row[wanted[radius]]!r}")
        if len(times) == 2 and numbers[-1] < numbers[-2]:
            raise ValueError(
                f"{path}: line {line}: the hold ends (end_s {numbers[-1]:g}) before it starts ({numbers[-2]:g})"
            )
        values.append(numbers)
    if not values:
        raise ValueError(f"{path} holds a header but no presses")
    return Presses(
        [row[:radius] for row in values],
        [row[radius] for row in values],
        [row[radius + 1 :] if len(times) == 2 else row[radius + 1] for row in values],
    )


def _time_columns(names: list[str], path: Path, line: int) -> tuple[str, ...]:
    """The time columns `names` holds (`INSTANT_COLUMNS` or `HOLD_COLUMNS`); ValueError naming
    what is missing or ambiguous."""
    missing = [name for name in PLACE_COLUMNS if name not in names]
    instant = all(name in names for name in INSTANT_COLUMNS)
    hold = [name for name in HOLD_COLUMNS if name in names]
    if instant and hold:
        raise ValueError(
            f"{path}: line {line} (the header) has both time_s and {'/'.join(hold)}: give one or the other"
        )
    if not instant and len(hold) == 1:
        missing += [name for name in HOLD_COLUMNS if name not in names]
    elif not instant and not hold:
        missing.append("time_s (or start_s and end_s)")
    if missing:
        raise ValueError(
            f"{path}: line {line} (the header) lacks column(s) {', '.join(missing)}; it names {names}. Expected "
            f"{','.join(PLACE_COLUMNS + INSTANT_COLUMNS)} or {','.join(PLACE_COLUMNS + HOLD_COLUMNS)}"
        )
    return INSTANT_COLUMNS if instant else HOLD_COLUMNS
