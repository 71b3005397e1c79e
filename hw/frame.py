"""The frame formats a board sends: diffeit binary frames and plain text lines.

**Binary frame, version 1** (boards we control). Little-endian, a 28-byte header, the values,
a 4-byte CRC:

```
offset  size  field
0       4     sync marker A5 5A E1 70 (never valid ASCII, so text chatter cannot fake it)
4       1     version = 1
5       1     value type: 0 float32, 1 int16, 2 int32
6       1     layout id: 0 declared by the host, 1 adjacent, 2 adjacent with driven pairs
              (the full n x n layout with zeros), 3 opposite (see `layout_protocol`)
7       1     number of electrodes n (0 with layout 0)
8       2     number of values N (uint16), 1..4096
10      4     frame counter (uint32): +1 per frame the device measures, wraps at 2**32
14      8     device timestamp (uint64), microseconds on the device's clock
22      4     scale (float32): volts per stored unit; value in volts = stored * scale
26      2     header CRC: CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF) of bytes 0..25
28      N*s   the values, s = 4, 2 or 4 bytes by the value type, in the layout's order and sign
28+N*s  4     frame CRC: CRC-32 (zlib, IEEE 802.3) of every byte before it, header included
```

A 208-value float32 frame is 864 bytes (86 kB/s at 100 frames/s: a USB CDC port, or int16
values, 448 bytes, over a UART at 921600 baud). The header CRC protects the length field on its
own, so a corrupted length is caught before the parser waits for, or skips, any bytes on its
behalf (the resynchronisation rule in `hw.parser`).

**Text lines** (simple boards): `[label:] v1, v2, ..., vN` and a newline (CR LF accepted), the
values decimal numbers separated by commas (spaces and one trailing comma allowed), an optional
label before the first colon (OpenEIT prints `magnitudes:`). The host declares the layout: the
protocol whose readings the N values are, typically 208 (`adjacent(16)`) or 256 (the full
16 x 16 layout, `adjacent(16, measure_driven=True)`). Text lines carry no counter, timestamp or
checksum: a line of the wrong length or with a non-number is rejected, but a corrupted digit is
not detectable.
"""

from __future__ import annotations

import binascii
import math
import struct
import time
import zlib
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from diffeit.protocol import Protocol, adjacent, opposite

SYNC = b"\xa5\x5a\xe1\x70"
VERSION = 1
HEADER_SIZE = 28
CRC_SIZE = 4
MAX_VALUES = 4096
# struct of the header after the sync marker, up to (not including) the header CRC
_HEADER = struct.Struct("<BBBBHIQf")
_HEADER_CRC = struct.Struct("<H")
_FRAME_CRC = struct.Struct("<I")

# The Unix time at the monotonic clock's zero, taken once: host times are this plus the
# monotonic clock, so a recording's times never step back when the wall clock is set back (NTP).
_UNIX_AT_MONOTONIC_ZERO = time.time() - time.monotonic()


def host_time() -> float:
    """Now, seconds since the Unix epoch, from the monotonic clock: never earlier than before."""
    return _UNIX_AT_MONOTONIC_ZERO + time.monotonic()


LAYOUT_DECLARED = 0
LAYOUT_ADJACENT = 1
LAYOUT_ADJACENT_FULL = 2
LAYOUT_OPPOSITE = 3
LAYOUT_NAMES = {
    LAYOUT_DECLARED: "declared by the host",
    LAYOUT_ADJACENT: "adjacent",
    LAYOUT_ADJACENT_FULL: "adjacent with driven pairs (n x n)",
    LAYOUT_OPPOSITE: "opposite",
}

VALUE_TYPES = {0: np.dtype("<f4"), 1: np.dtype("<i2"), 2: np.dtype("<i4")}
VALUE_TYPE_NAMES = {"float32": 0, "int16": 1, "int32": 2}


@dataclass(frozen=True, eq=False)
class Frame:
    """One frame as it arrived.

    - `values`: (N,) float64 voltages in volts (stored value * scale), read-only, in the
      layout's order and sign.
    - `counter`: the device's frame counter (binary frames), None for text lines.
    - `device_time`: seconds on the device's clock (binary frames), None for text lines.
    - `layout`, `n_electrodes`: the layout id and electrode count the frame declares (text
      lines: `LAYOUT_DECLARED`, 0).
    - `label`: a text line's label (before the colon), else None.
    - `host_time`: seconds since the Unix epoch when the host read the frame's last byte (set
      by `hw.SerialSource`), else None.
    """

    values: np.ndarray
    counter: int | None = None
    device_time: float | None = None
    layout: int = LAYOUT_DECLARED
    n_electrodes: int = 0
    label: str | None = None
    host_time: float | None = None

    @property
    def n_values(self) -> int:
        return len(self.values)


def layout_protocol(layout: int, n_electrodes: int) -> Protocol | None:
    """The diffeit protocol of a layout id: 1 `adjacent(n)` (n(n-3) values, EIDORS's order and
    sign), 2 `adjacent(n, measure_driven=True)` (the full n x n layout), 3 `opposite(n)`
    (n(n-4) values); 0 (declared by the host) gives None. Unknown ids raise `ValueError`."""
    if layout == LAYOUT_DECLARED:
        return None
    if layout == LAYOUT_ADJACENT:
        return adjacent(n_electrodes)
    if layout == LAYOUT_ADJACENT_FULL:
        return adjacent(n_electrodes, measure_driven=True)
    if layout == LAYOUT_OPPOSITE:
        return opposite(n_electrodes)
    raise ValueError(f"unknown layout id {layout}; known: {LAYOUT_NAMES}")


def layout_matches(layout: int, n_electrodes: int, protocol: Protocol) -> bool:
    """Whether layout id `layout` with `n_electrodes` names exactly `protocol` (same drive and
    measurement pairs, same order); False for `LAYOUT_DECLARED`, unknown ids and electrode
    counts the layout cannot have."""
    try:
        declared = layout_protocol(layout, n_electrodes)
    except ValueError:
        return False
    return (
        declared is not None
        and declared.n_measurements == protocol.n_measurements
        and np.array_equal(declared.drive, protocol.drive)
        and np.array_equal(declared.measure, protocol.measure)
    )


def layout_of(protocol: Protocol) -> int:
    """The layout id that names `protocol`, or `LAYOUT_DECLARED` when no id does (the host
    then declares the protocol to the parser)."""
    known = (LAYOUT_ADJACENT, LAYOUT_OPPOSITE, LAYOUT_ADJACENT_FULL)
    return next((code for code in known if layout_matches(code, protocol.n_electrodes, protocol)), LAYOUT_DECLARED)


def encode_frame(
    values: ArrayLike,
    *,
    counter: int,
    device_time: float,
    layout: int = LAYOUT_ADJACENT,
    n_electrodes: int = 16,
    value_type: str = "float32",
    scale: float = 1.0,
) -> bytes:
    """One binary frame (format above) of `values` (N,) in volts.

    `device_time` in seconds (stored in whole microseconds), `counter` in 0..2**32-1, `scale`
    in volts per stored unit: float32 stores values / scale, int16 and int32 store
    round(values / scale), which must fit the type. Raises `ValueError` for non-finite values,
    a count outside 1..4096 or one that disagrees with the layout, values that overflow the
    type.
    """
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 1 or not 1 <= len(values) <= MAX_VALUES:
        raise ValueError(f"a frame holds 1..{MAX_VALUES} values in one row; got shape {values.shape}")
    if not np.all(np.isfinite(values)):
        raise ValueError(f"frame values hold NaN or inf at {np.flatnonzero(~np.isfinite(values))[:10].tolist()}")
    if value_type not in VALUE_TYPE_NAMES:
        raise ValueError(f"value_type must be one of {list(VALUE_TYPE_NAMES)}; got {value_type!r}")
    if not (math.isfinite(scale) and np.isfinite(np.float32(scale)) and np.float32(scale) != 0):
        raise ValueError(f"scale must be finite and non-zero in float32 (volts per stored unit); got {scale}")
    if not 0 <= counter < 2**32:
        raise ValueError(f"counter must be in 0..2**32-1; got {counter}")
    if not (math.isfinite(device_time) and 0 <= device_time < 2**64 / 1e6):
        raise ValueError(f"device_time must be a non-negative number of seconds; got {device_time}")
    protocol = layout_protocol(layout, n_electrodes)
    if protocol is not None and protocol.n_measurements != len(values):
        raise ValueError(
            f"layout {LAYOUT_NAMES[layout]!r} on {n_electrodes} electrodes has {protocol.n_measurements} values; "
            f"got {len(values)}"
        )
    code = VALUE_TYPE_NAMES[value_type]
    dtype = VALUE_TYPES[code]
    stored = values / scale
    if dtype.kind == "i":
        stored = np.round(stored)
        limits = np.iinfo(dtype)
        if stored.min() < limits.min or stored.max() > limits.max:
            span = f"{stored.min():.0f}..{stored.max():.0f}"
            raise ValueError(f"values / scale span {span}; {value_type} holds {limits.min}..{limits.max}")
    header = SYNC + _HEADER.pack(
        VERSION, code, layout, 0 if protocol is None else n_electrodes, len(values), counter,
        round(device_time * 1e6), scale,
    )  # fmt: skip
    with np.errstate(over="ignore"):
        stored = stored.astype(dtype)
    if not np.all(np.isfinite(stored)):  # float32 overflow
        raise ValueError(f"values / scale overflow {value_type} (scale {scale} V per unit is too small)")
    body = header + _HEADER_CRC.pack(header_crc(header)) + stored.tobytes()
    return body + _FRAME_CRC.pack(zlib.crc32(body))


def header_crc(header: bytes) -> int:
    """CRC-16/CCITT-FALSE of the first 26 header bytes."""
    return binascii.crc_hqx(header, 0xFFFF)


def encode_text_line(values: ArrayLike, label: str | None = None) -> bytes:
    """One text line `label: v1,v2,...\\n` of `values` (N,) in volts, each written as Python's
    shortest round-tripping decimal (so parsing gives the same float64 back)."""
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 1 or len(values) == 0:
        raise ValueError(f"a text line holds one row of values; got shape {values.shape}")
    if not np.all(np.isfinite(values)):
        raise ValueError("text line values hold NaN or inf")
    if label is not None and (":" in label or "\n" in label or "," in label):
        raise ValueError(f"a label cannot hold ':', ',' or a newline; got {label!r}")
    text = ",".join(repr(float(value)) for value in values)
    return (f"{label}: {text}\n" if label is not None else f"{text}\n").encode("ascii")
