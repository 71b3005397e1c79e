"""OpenEIT text logs: `magnitudes:` lines of the opposition protocol."""

from __future__ import annotations

import collections
import math
import os
from pathlib import Path

import numpy as np

from .._messages import name_indices
from ..protocol import opposite
from ._recording import Recording

# Values per line of OpenEIT's opposition layouts (firmware lookup tables), by electrode count.
OPENEIT_ELECTRODES = {32: 8, 192: 16, 896: 32}


def read_openeit(
    path: str | os.PathLike,
    *,
    n_electrodes: int | None = None,
    frame_rate: float = 1.0,
    skip_malformed: bool = False,
) -> Recording:
    """Frames from an OpenEIT text log (what its dashboard records from the serial port).

    Each frame is one line `magnitudes: v1 , v2 , ... ,` (the label and a trailing comma
    optional); lines without a comma (the firmware's messages such as "mode 3: imaging") and
    blank lines are skipped. OpenEIT's imaging firmware drives opposite electrodes, and its
    frames are `opposite(n)`'s readings value for value (16 electrodes: 192 values; 8: 32;
    32: 896). The board prints magnitudes, so the sign of each reading is lost: the recording
    has `readings="magnitude"` (a reconstruction restores the signs from the calibrated
    model's predicted readings) and `voltage_unit="arbitrary"`. The layout, and what the
    reader can and cannot detect of a damaged log, are in
    docs/tutorials/real-recordings.md#what-the-readers-check.

    Arguments:
        path: The log file.
        n_electrodes: 8, 16 or 32; None chooses from the number of values per line.
        frame_rate: Frames per second (logs carry no times: the t-th line of values is at
            t / frame_rate s).
        skip_malformed: Drop lines of another length or with non-numbers, and a last line
            without its newline, instead of refusing the file (their line numbers go in
            `provenance["metadata"]["skipped_lines"]`). Each dropped line keeps its place in
            time: the frames after it keep theirs (labelled presses timed by the frame
            count stay on their frames).

    Returns:
        The `Recording` under `opposite(n_electrodes)`.

    Raises:
        FileNotFoundError: For a missing file.
        ValueError: Naming the file and the lines, for an empty log, malformed lines (unless
            skipped), non-finite or negative values, an unknown layout, a last line of values
            without its newline (unless skipped: the log was cut short, or is still being
            written); and for a frame rate that is not positive.
    """
    path = Path(path)
    if not math.isfinite(frame_rate) or frame_rate <= 0:
        raise ValueError(f"frame_rate must be positive (frames per second); got {frame_rate}")
    if not path.exists():
        raise FileNotFoundError(f"no such OpenEIT log: {path}")
    rows: list[tuple[int, list[float] | None]] = []  # (line number from 1, values or None if unreadable)
    cut: list[int] = []  # a last line of values without its newline
    with path.open("r", encoding="ascii", errors="replace") as file:
        for number, line in enumerate(file, start=1):
            if "," not in line:  # the firmware's messages ("mode 3: imaging") and blank lines
                continue
            if not line.endswith("\n"):
                cut.append(number)
                continue
            numbers = line.split(":", 1)[-1]
            items = [item.strip() for item in numbers.split(",")]
            if items and not items[-1]:
                items.pop()
            try:
                rows.append((number, [float(item) for item in items]))
            except ValueError:
                rows.append((number, None))
    if cut and not skip_malformed:
        raise ValueError(
            f"{path}: line {cut[0]}, the last, does not end in a newline: the log is cut short (or still being "
            "written); pass skip_malformed=True to drop it"
        )
    if not rows:
        raise ValueError(f"{path} holds no lines of values: not an OpenEIT log?")
    if n_electrodes is None:
        counts = collections.Counter(len(values) for _, values in rows if values is not None)
        known = [count for count, _ in counts.most_common() if count in OPENEIT_ELECTRODES]
        if not known:
            raise ValueError(
                f"{path}: lines hold {sorted(counts)} values; OpenEIT's opposition layouts have "
                f"{sorted(OPENEIT_ELECTRODES)} (8, 16, 32 electrodes): pass n_electrodes"
            )
        n_electrodes = OPENEIT_ELECTRODES[known[0]]
    protocol = opposite(n_electrodes)
    n_values = protocol.n_measurements
    bad = [number for number, values in rows if values is None or len(values) != n_values]
    if bad and not skip_malformed:
        raise ValueError(
            f"{path}: lines {name_indices(np.array(bad))} are not {n_values} numbers (the {n_electrodes}-electrode "
            "opposition layout); pass skip_malformed=True to drop them"
        )
    skipped = set(bad)
    slots = [slot for slot, (number, _) in enumerate(rows) if number not in skipped]  # each line of values, a frame
    kept = [rows[slot] for slot in slots]
    if not kept:
        raise ValueError(f"{path}: no line holds {n_values} values")
    frames = np.array([values for _, values in kept])
    if not np.all(np.isfinite(frames)):
        lines = [number for (number, _), row in zip(kept, frames, strict=True) if not np.all(np.isfinite(row))]
        raise ValueError(f"{path}: lines {name_indices(np.array(lines))} hold non-finite values")
    if np.any(frames < 0):
        lines = [number for (number, _), row in zip(kept, frames, strict=True) if np.any(row < 0)]
        raise ValueError(
            f"{path}: lines {name_indices(np.array(lines))} hold negative values; OpenEIT prints magnitudes"
        )
    return Recording(
        frames=frames,
        times=np.array(slots, np.float64) / frame_rate,
        protocol=protocol,
        provenance={
            "source": f"OpenEIT text log {path.name}",
            "metadata": {
                "file": str(path),
                "layout": f"OpenEIT opposition, {n_electrodes} electrodes, {n_values} values (diffeit opposite)",
                "values": "magnitudes: the sign of each reading is lost",
                "frame_rate": frame_rate,
                "skipped_lines": bad + cut,
            },
        },
        voltage_unit="arbitrary",
        readings="magnitude",
    )
