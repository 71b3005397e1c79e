"""Streaming parsers: bytes in, whole checked frames out, every drop counted by kind.

`BinaryParser` reads the binary frames of `hw.frame`; `TextParser` reads text lines. Both
take bytes in any pieces (`feed(data) -> list[Frame]`), never return a partial frame, and keep
`statistics` (a `DropStatistics`). `reset()` drops a partial frame after the device
disappeared (counted as truncated) and keeps the counter, so frames lost across a reconnection
are counted as missing. The only exceptions they raise are `ValueError` for bad arguments and
`TypeError` for data that is not bytes.

**Resynchronisation rule (binary).** The parser searches for the sync marker; bytes before it
are discarded. At a marker it waits for the 28-byte header and checks the header CRC, the
version and the header's values (value type, 1..4096 values, finite non-zero scale); then it
waits for the whole frame (its length from the checked header) and checks the frame CRC. When
any of these checks fails, the candidate is rejected and the search resumes **one byte after
the rejected marker**, over bytes already received: nothing that follows a damaged frame is
skipped on its behalf. A frame whose CRC holds but whose layout differs from the expected one
(`length`), whose values are not finite (`non_finite`) or whose counter repeats or is up to 16
behind the last (`counter`, a stale frame) is rejected whole: its CRC vouches for its
boundaries, and the search resumes after it. A counter of 0, more than 16 behind or more than
2**24 ahead is a device reset (`restarts`), accepted as a new start.

Consequences, exactly:

- A damaged frame never costs an intact one. A corrupted length field fails the header CRC
  before any byte is waited for or skipped; a frame cut short (dropped bytes, truncation) makes
  the parser wait for bytes of the next frame, fail the frame CRC, and then find the next frame
  inside the bytes it already holds.
- A damaged frame is either rejected and counted by kind (`header`: a fault in bytes 4..27;
  `crc`: a fault in the values or the CRC; `truncated`: cut off by `reset` or `finish`), or, when
  the fault hit its sync marker, never seen as a frame: its bytes are discarded. Either way the
  next accepted frame's counter shows the gap (`missing_frames`).
- The intact frame after a damaged one is delivered as soon as its last byte arrives, except
  that a frame cut short with an intact header delays it until the damaged frame's claimed
  length has arrived (at most one frame's worth of bytes).
- The wrong frame is accepted only if damage leaves both CRCs valid: about once in 2**32
  damaged frames.

**Text lines.** A line is complete at its newline; blank lines are skipped; a line that is not
ASCII or holds a non-number (`malformed`), has another number of values than declared
(`length`) or a non-finite value (`non_finite`) is rejected. A line longer than `max_line_bytes`
is rejected (`malformed`) and its bytes up to the next newline discarded. Text has no counter:
lines that never arrive cannot be counted.
"""

from __future__ import annotations

import abc
import functools
import math
import zlib
from dataclasses import asdict, dataclass, replace

import numpy as np

from diffeit.protocol import Protocol

from .frame import (
    _FRAME_CRC,
    _HEADER,
    _HEADER_CRC,
    CRC_SIZE,
    HEADER_SIZE,
    LAYOUT_DECLARED,
    MAX_VALUES,
    SYNC,
    VALUE_TYPES,
    VERSION,
    Frame,
    header_crc,
    layout_matches,
    layout_protocol,
)

_COUNTER_MODULUS = 2**32
# A counter at most this far behind the last accepted one is a stale frame (rejected, `counter`);
# farther back, or further ahead than _MAX_GAP (a loss of days of frames is no gap), the device
# restarted its numbering: accepted, counted in `restarts`. A counter of 0 always restarts.
_STALE_WINDOW = 16
_MAX_GAP = 2**24


@dataclass(frozen=True)
class DropStatistics:
    """What a parser accepted and what it dropped, by kind.

    - `frames`: frames accepted.
    - `discarded_bytes`: bytes that are in no accepted frame (garbage, damaged and rejected
      frames; not blank text lines), not counting bytes still held for a frame in progress.
    - rejected frames (binary) or lines (text), by kind: `header` (header CRC or impossible
      header values), `version` (a newer frame version), `crc` (frame CRC), `length` (another
      layout or number of values than expected, or than its layout has), `non_finite` (NaN or
      inf values), `counter` (a counter that repeats, or up to 16 behind the last: a stale
      frame), `malformed` (a text line that is not ASCII numbers, or too long), `truncated` (a
      frame cut off by a disconnection or the end).
    - `missing_frames`: frames the device numbered that were not accepted (sum of the counter
      jumps between accepted frames), `gaps`: how many jumps; `restarts`: the counter went back
      to 0, more than 16 back, or more than 2**24 ahead (a device reset, its first frames
      perhaps lost), accepted as a new start.
    - `reconnects`: times the port was reopened (set by `hw.SerialSource`).
    """

    frames: int = 0
    discarded_bytes: int = 0
    header: int = 0
    version: int = 0
    crc: int = 0
    length: int = 0
    non_finite: int = 0
    counter: int = 0
    malformed: int = 0
    truncated: int = 0
    missing_frames: int = 0
    gaps: int = 0
    restarts: int = 0
    reconnects: int = 0

    REJECTION_KINDS = ("header", "version", "crc", "length", "non_finite", "counter", "malformed", "truncated")

    @property
    def rejected(self) -> int:
        """Frames (or lines) rejected, all kinds together."""
        return sum(getattr(self, kind) for kind in self.REJECTION_KINDS)

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class AbstractParser(abc.ABC):
    """Bytes in, checked frames out. Subclasses: `BinaryParser`, `TextParser`."""

    def __init__(self) -> None:
        self._buffer = bytearray()
        self._bytes_fed = 0
        self._bytes_accepted = 0
        self._counts = DropStatistics()

    @abc.abstractmethod
    def _parse(self) -> list[Frame]:
        """Frames from the front of `_buffer`, consuming what they and the garbage took."""

    @abc.abstractmethod
    def _holds_partial_frame(self) -> bool:
        """Whether the buffer holds the beginning of a frame."""

    def feed(self, data: bytes | bytearray | memoryview) -> list[Frame]:
        """The frames completed by `data` (possibly none), in arrival order."""
        if not isinstance(data, bytes | bytearray | memoryview):
            raise TypeError(f"feed takes bytes; got {type(data).__name__}")
        self._buffer += data
        self._bytes_fed += len(data)
        return self._parse()

    def reset(self) -> None:
        """Forget a partial frame (the device went away mid-frame: counted as `truncated`);
        keep the counter, so frames lost meanwhile show as missing."""
        if self._holds_partial_frame():
            self._count(truncated=1)
        self._buffer.clear()

    def finish(self) -> DropStatistics:
        """End of the stream: count a partial frame as truncated; the final statistics."""
        self.reset()
        return self.statistics

    @property
    def statistics(self) -> DropStatistics:
        return replace(self._counts, discarded_bytes=self._bytes_fed - self._bytes_accepted - len(self._buffer))

    def _count(self, **increments: int) -> None:
        self._counts = replace(self._counts, **{k: getattr(self._counts, k) + v for k, v in increments.items()})

    def _accept(self, frame: Frame, size: int) -> Frame:
        self._bytes_accepted += size
        self._count(frames=1)
        return frame


class BinaryParser(AbstractParser):
    """Parser of binary frames (`hw.frame`), resynchronising as the module docstring says.

    `protocol`: the protocol frames must have (a layout id 0 frame is taken to be in it, a
    frame of another layout is rejected as `length`). Without one, the first accepted frame
    fixes the layout (layout id, electrodes, number of values) and later frames must match it:
    a recording never mixes frame lengths.
    """

    def __init__(self, protocol: Protocol | None = None) -> None:
        super().__init__()
        if protocol is not None and not isinstance(protocol, Protocol):
            raise ValueError(f"protocol must be a diffeit Protocol or None; got {type(protocol).__name__}")
        self.protocol = protocol
        self._layout: tuple[int, int, int] | None = None  # (layout id, electrodes, values) once fixed
        self._last_counter: int | None = None
        self._matching: dict[tuple[int, int], bool] = {}  # layouts checked against `protocol`

    def _holds_partial_frame(self) -> bool:
        return self._buffer.startswith(SYNC)

    def _matches(self, layout: int, n_electrodes: int) -> bool:
        """`hw.layout_matches` for `protocol`, once per layout: it builds a protocol each time."""
        key = (layout, n_electrodes)
        if key not in self._matching:
            self._matching[key] = layout_matches(layout, n_electrodes, self.protocol)
        return self._matching[key]

    def _parse(self) -> list[Frame]:
        buffer, frames, position = self._buffer, [], 0
        while True:
            start = buffer.find(SYNC, position)
            if start < 0:
                # Keep a tail that may be the beginning of a marker split across reads.
                position = max(position, len(buffer) - len(SYNC) + 1)
                break
            position = start
            if len(buffer) - start < HEADER_SIZE:
                break
            header = bytes(buffer[start : start + HEADER_SIZE])
            version, code, layout, n_electrodes, n_values, counter, device_us, scale = _HEADER.unpack_from(
                header, len(SYNC)
            )
            if _HEADER_CRC.unpack_from(header, HEADER_SIZE - 2)[0] != header_crc(header[: HEADER_SIZE - 2]):
                self._count(header=1)
                position = start + 1
                continue
            if version != VERSION:
                self._count(version=1)
                position = start + 1
                continue
            if code not in VALUE_TYPES or not 1 <= n_values <= MAX_VALUES or not (math.isfinite(scale) and scale):
                self._count(header=1)
                position = start + 1
                continue
            dtype = VALUE_TYPES[code]
            end = start + HEADER_SIZE + n_values * dtype.itemsize
            if len(buffer) < end + CRC_SIZE:
                break
            if _FRAME_CRC.unpack_from(buffer, end)[0] != zlib.crc32(buffer[start:end]):
                self._count(crc=1)
                position = start + 1
                continue
            position = end + CRC_SIZE  # the CRC vouches for the frame's extent
            # A copy: a view would pin the buffer, which must stay resizable.
            values = np.frombuffer(bytes(buffer[start + HEADER_SIZE : end]), dtype).astype(np.float64) * scale
            rejection = self._check(layout, n_electrodes, n_values, values, counter)
            if rejection:
                self._count(**{rejection: 1})
                continue
            values.setflags(write=False)
            frame = Frame(values, counter, device_us / 1e6, layout, n_electrodes)
            frames.append(self._accept(frame, position - start))
        del buffer[:position]
        return frames

    def _check(self, layout: int, n_electrodes: int, n_values: int, values: np.ndarray, counter: int) -> str | None:
        """The rejection kind of a frame whose CRC holds, or None; updates layout and counter."""
        shape = (layout, n_electrodes, n_values)
        if self.protocol is not None:
            if layout == LAYOUT_DECLARED:
                if n_values != self.protocol.n_measurements:
                    return "length"
            elif n_values != self.protocol.n_measurements or not self._matches(layout, n_electrodes):
                return "length"
        elif self._layout is not None and shape != self._layout:
            return "length"
        elif layout != LAYOUT_DECLARED and _layout_size(layout, n_electrodes) != n_values:
            return "length"  # the values disagree with the layout the frame declares
        if not np.all(np.isfinite(values)):
            return "non_finite"
        if self._last_counter is not None:
            step = (counter - self._last_counter) % _COUNTER_MODULUS
            behind = (self._last_counter - counter) % _COUNTER_MODULUS
            if step == 0:
                return "counter"
            if step > _MAX_GAP:
                if counter != 0 and behind <= _STALE_WINDOW:
                    return "counter"
                self._count(restarts=1)
            elif step > 1:
                self._count(missing_frames=step - 1, gaps=1)
        self._layout = shape
        self._last_counter = counter
        return None


@functools.lru_cache(maxsize=64)
def _layout_size(layout: int, n_electrodes: int) -> int | None:
    """Values in a frame of this layout, None for a layout id or electrode count that cannot be."""
    try:
        protocol = layout_protocol(layout, n_electrodes)
    except ValueError:
        return None
    return None if protocol is None else protocol.n_measurements


class TextParser(AbstractParser):
    """Parser of text lines `[label:] v1, v2, ..., vN` whose N values are the readings of the
    declared `protocol` (or, given an int, of `n_values` readings).

    `max_line_bytes` bounds a line (default 64 kB, room for 4096 values of 15 characters):
    longer lines are rejected (`malformed`).
    """

    def __init__(self, protocol: Protocol | int, *, max_line_bytes: int = 65536) -> None:
        super().__init__()
        if isinstance(protocol, Protocol):
            n_values = protocol.n_measurements
        elif isinstance(protocol, int) and not isinstance(protocol, bool) and protocol > 0:
            n_values, protocol = protocol, None
        else:
            raise ValueError(f"declare the layout: a diffeit Protocol or a number of values; got {protocol!r}")
        self.protocol = protocol
        self.n_values = n_values
        self.max_line_bytes = max_line_bytes
        self._skipping_long_line = False

    def _holds_partial_frame(self) -> bool:
        return bool(self._buffer.strip()) and not self._skipping_long_line

    def reset(self) -> None:
        super().reset()
        self._skipping_long_line = False  # the long line ended with the connection

    def _parse(self) -> list[Frame]:
        buffer, frames, position = self._buffer, [], 0
        while True:
            end = buffer.find(b"\n", position)
            if end < 0:
                if len(buffer) - position > self.max_line_bytes and not self._skipping_long_line:
                    self._count(malformed=1)
                    self._skipping_long_line = True
                if self._skipping_long_line:
                    position = len(buffer)
                break
            line, start, position = bytes(buffer[position:end]), position, end + 1
            if self._skipping_long_line:
                self._skipping_long_line = False
                continue
            if len(line) > self.max_line_bytes:
                self._count(malformed=1)
                continue
            parsed = self._line(line)
            if isinstance(parsed, Frame):
                frames.append(self._accept(parsed, position - start))
            elif parsed:
                self._count(**{parsed: 1})
            else:  # a blank line separates frames, as many boards print one
                self._bytes_accepted += position - start
        del buffer[:position]
        return frames

    def _line(self, line: bytes) -> Frame | str | None:
        """The frame of one line, or the kind of its rejection, or None for a blank line."""
        try:
            text = line.decode("ascii").strip()
        except UnicodeDecodeError:
            return "malformed"
        if not text:
            return None
        label, colon, numbers = text.partition(":")
        if not colon:
            label, numbers = None, text
        items = [item.strip() for item in numbers.split(",")]
        if items and not items[-1]:
            items.pop()  # one trailing comma, as OpenEIT prints
        try:
            values = np.array([float(item) for item in items], dtype=np.float64)
        except ValueError:
            return "malformed"
        if len(values) != self.n_values:
            return "length"
        if not np.all(np.isfinite(values)):
            return "non_finite"
        values.setflags(write=False)
        return Frame(values, label=label.strip() if label is not None else None)
