"""A device emulator: streams given frames over a pseudo-terminal, with faults and their log.

`Emulator(frames, frame_rate=100.0, ...)` encodes every frame up front (binary frames of
`hw.frame`, or text lines), opens a pseudo-terminal in raw mode and links `emulator.port` (a
path that stays the same across disconnections) to its serial end. `start()` streams from a
thread: it waits for a host to open the port, then sends frame i at i / frame_rate seconds
(later, never earlier, when it falls behind). Any serial client reads it as a real port:
`serial.Serial(emulator.port)` or `hw.SerialSource(emulator.port)`.

Faults (`FaultRates`, drawn up front from a seed by `plan_faults`, at most one per frame):

- `bit_flip`: one bit of one byte of the frame inverted.
- `dropped_bytes`: 1..`max_dropped_bytes` consecutive bytes of the frame never sent.
- `truncated`: the frame cut off after `offset` bytes; the rest never sent.
- `stall`: the frame's first `offset` bytes, a pause of `stall_seconds`, then the rest: the
  frame arrives intact, late and in two pieces.
- `disconnect`: the frame's first `offset` bytes, then the pseudo-terminal closes (a host
  reading it sees the device vanish), `disconnect_seconds` later a new one appears at the same
  `port`; the emulator waits for the host to reopen it and goes on with the next frame (the
  frames due meanwhile are sent late, not lost).

Every fault that hit a frame loses that frame, except a stall. `log` is the ground truth: the
`Fault`s injected, in order, and a `not_sent` entry for each frame never sent because the host
closed the port or never came back (`host_timeout`) or `stop()` was called. Before a
disconnection and at the end, the emulator waits until the host has read every byte already
sent, so no intact frame is lost in the pseudo-terminal's buffer. After the host opens the port
the emulator waits until the host has flushed its input queue, as pyserial's `open()` does once
it has configured the port (the pseudo-terminal's packet mode reports the flush), so that the
flush cannot discard a frame; a client that never flushes is served after `_OPEN_FLUSH_WAIT`
seconds.
"""

from __future__ import annotations

import fcntl
import os
import select
import struct
import tempfile
import termios
import threading
import time
import tty
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from .frame import LAYOUT_ADJACENT, encode_frame, encode_text_line

FAULT_KINDS = ("bit_flip", "dropped_bytes", "truncated", "stall", "disconnect")
# How long the emulator waits for the host to read what was sent, before a disconnection or at
# the end (seconds).
_DRAIN_TIMEOUT = 5.0
_DRAIN_SETTLE = 0.05
# How long the emulator waits, after a host opened the port, for the host to flush its input
# queue (seconds); pyserial flushes within milliseconds on an idle machine.
_OPEN_FLUSH_WAIT = 2.0


@dataclass(frozen=True)
class FaultRates:
    """Probability per frame of each fault (their sum at most 1; at most one fault a frame),
    and the faults' sizes: `stall_seconds`, `disconnect_seconds` in seconds,
    `max_dropped_bytes` bytes. `seed` fixes which frames are hit and where."""

    bit_flip: float = 0.0
    dropped_bytes: float = 0.0
    truncated: float = 0.0
    stall: float = 0.0
    disconnect: float = 0.0
    stall_seconds: float = 0.05
    disconnect_seconds: float = 0.2
    max_dropped_bytes: int = 16
    seed: int = 0

    def __post_init__(self) -> None:
        rates = [getattr(self, kind) for kind in FAULT_KINDS]
        if not all(0 <= rate <= 1 for rate in rates) or sum(rates) > 1:
            named = dict(zip(FAULT_KINDS, rates, strict=True))
            raise ValueError(f"fault rates must be probabilities summing to at most 1; got {named}")
        if self.stall_seconds < 0 or self.disconnect_seconds < 0 or self.max_dropped_bytes < 1:
            raise ValueError("stall_seconds and disconnect_seconds must be >= 0 and max_dropped_bytes >= 1")


@dataclass(frozen=True)
class Fault:
    """One entry of the ground-truth log.

    - `frame`: index of the frame hit (into the frames given; its counter is
      `counter_start + frame`).
    - `kind`: one of `FAULT_KINDS`, or `not_sent`.
    - `offset`: the byte of the frame's encoding where the fault hits (`bit_flip`: the byte
      flipped; `dropped_bytes`: the first byte dropped; `truncated`, `stall`, `disconnect`:
      bytes sent before it).
    - `size`: `bit_flip`: the bit (0..7); `dropped_bytes`: bytes dropped; else 0.
    - `seconds`: a stall's or disconnection's duration.
    """

    frame: int
    kind: str
    offset: int = 0
    size: int = 0
    seconds: float = 0.0

    @property
    def loses_frame(self) -> bool:
        return self.kind != "stall"


def plan_faults(frame_sizes: ArrayLike, rates: FaultRates) -> tuple[Fault, ...]:
    """The faults for frames of `frame_sizes` bytes: each frame draws at most one fault with
    the probabilities of `rates`, seeded by `rates.seed` (the same plan every time)."""
    sizes = np.asarray(frame_sizes, dtype=int)
    rng = np.random.default_rng(rates.seed)
    bounds = np.cumsum([getattr(rates, kind) for kind in FAULT_KINDS])
    draws = rng.random(len(sizes))
    plan = []
    for frame, (draw, size) in enumerate(zip(draws, sizes, strict=True)):
        chosen = int(np.searchsorted(bounds, draw, side="right"))
        if chosen == len(FAULT_KINDS):
            continue
        kind = FAULT_KINDS[chosen]
        offset = int(rng.integers(0, size))
        if kind == "bit_flip":
            plan.append(Fault(frame, kind, offset, int(rng.integers(0, 8))))
        elif kind == "dropped_bytes":
            most = min(rates.max_dropped_bytes, size - offset)
            plan.append(Fault(frame, kind, offset, int(rng.integers(1, most + 1))))
        elif kind == "stall":
            plan.append(Fault(frame, kind, offset, seconds=rates.stall_seconds))
        elif kind == "disconnect":
            plan.append(Fault(frame, kind, offset, seconds=rates.disconnect_seconds))
        else:
            plan.append(Fault(frame, kind, offset))
    return tuple(plan)


class Emulator:
    """Streams `frames` (T, N) volts over a pseudo-terminal (see the module docstring).

    - `frame_rate`: frames per second.
    - `text`: send text lines (`label: v1,v2,...`) instead of binary frames.
    - `faults`: a `FaultRates`, or None for none.
    - `port`: the path to link to the pseudo-terminal (default: a fresh temporary folder's
      `ttyEIT`); it must not exist.
    - `counter_start`, `layout`, `n_electrodes`, `value_type`, `scale`: binary frames'
      fields (`hw.frame.encode_frame`); frame i has counter `counter_start + i` and device time
      i / frame_rate seconds. `label`: text lines' label.
    - `host_timeout`: seconds to wait for the host to open (or reopen) the port before giving
      up and logging the remaining frames as `not_sent`.
    """

    def __init__(
        self,
        frames: ArrayLike,
        *,
        frame_rate: float = 100.0,
        text: bool = False,
        faults: FaultRates | None = None,
        port: str | os.PathLike | None = None,
        counter_start: int = 0,
        layout: int = LAYOUT_ADJACENT,
        n_electrodes: int = 16,
        value_type: str = "float32",
        scale: float = 1.0,
        label: str | None = None,
        host_timeout: float = 10.0,
    ) -> None:
        frames = np.asarray(frames, dtype=np.float64)
        if frames.ndim != 2 or len(frames) == 0:
            raise ValueError(f"frames must have shape (T, N) with T >= 1; got {frames.shape}")
        if not (np.isfinite(frame_rate) and frame_rate > 0):
            raise ValueError(f"frame_rate must be positive (frames per second); got {frame_rate}")
        if text:
            self._encoded = [encode_text_line(values, label) for values in frames]
        else:
            self._encoded = [
                encode_frame(
                    values, counter=(counter_start + i) % 2**32, device_time=i / frame_rate, layout=layout,
                    n_electrodes=n_electrodes, value_type=value_type, scale=scale,
                )
                for i, values in enumerate(frames)
            ]  # fmt: skip
        self.frame_rate = float(frame_rate)
        self.n_frames = len(frames)
        self.plan = plan_faults([len(data) for data in self._encoded], faults) if faults is not None else ()
        if port is None:
            self._folder = tempfile.mkdtemp(prefix="diffeit-emulator-")
            port = Path(self._folder) / "ttyEIT"
        else:
            self._folder = None
        self.port = str(port)
        if os.path.lexists(self.port):
            raise ValueError(f"the emulator's port path {self.port} exists; choose another")
        self.host_timeout = host_timeout
        self._log: list[Fault] = []
        self._stop = threading.Event()
        self._master: int | None = None
        self._serial_end: str | None = None
        self._thread = threading.Thread(target=self._run, name="diffeit-emulator", daemon=True)

    # -- control ----------------------------------------------------------------------------

    def start(self) -> Emulator:
        """Open the pseudo-terminal at `port` and start streaming from a thread."""
        self._open_terminal()
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop streaming (frames not yet sent are logged `not_sent`) and wait for the thread."""
        self._stop.set()
        self.wait()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until every frame was handled; whether it finished within `timeout` s."""
        if self._thread.ident is None:  # never started
            return True
        self._thread.join(timeout)
        return not self._thread.is_alive()

    def __enter__(self) -> Emulator:
        return self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.stop()

    @property
    def log(self) -> tuple[Fault, ...]:
        """The ground truth so far: faults injected and frames not sent, in order."""
        return tuple(self._log)

    @property
    def lost_frames(self) -> tuple[int, ...]:
        """Indices of the frames the log says were damaged or not sent."""
        return tuple(sorted({fault.frame for fault in self._log if fault.loses_frame}))

    # -- streaming --------------------------------------------------------------------------

    def _run(self) -> None:
        faults = {fault.frame: fault for fault in self.plan}
        frame = 0
        try:
            if not self._wait_for_host():
                return
            due = time.monotonic()
            for frame, data in enumerate(self._encoded):
                if self._stop.wait(max(0.0, due - time.monotonic())):
                    return
                if not self._send(data, faults.get(frame)):
                    return
                due = max(due + 1 / self.frame_rate, time.monotonic() - 1 / self.frame_rate)
            frame = self.n_frames
            self._drain()
        finally:
            logged = {fault.frame for fault in self._log}  # a disconnected frame is logged already
            self._log.extend(Fault(index, "not_sent") for index in range(frame, self.n_frames) if index not in logged)
            self._close_terminal()
            if self._folder is not None:
                os.rmdir(self._folder)

    def _send(self, data: bytes, fault: Fault | None) -> bool:
        """Send one frame as `fault` says; False when the host is gone (the frame not sent)."""
        if fault is None:
            return self._write(data)
        offset = fault.offset
        if fault.kind == "bit_flip":
            damaged = bytearray(data)
            damaged[offset] ^= 1 << fault.size
            sent = self._write(bytes(damaged))
        elif fault.kind == "dropped_bytes":
            sent = self._write(data[:offset] + data[offset + fault.size :])
        elif fault.kind == "truncated":
            sent = self._write(data[:offset])
        elif fault.kind == "stall":
            sent = self._write(data[:offset]) and not self._stop.wait(fault.seconds) and self._write(data[offset:])
        else:  # disconnect
            if not (self._write(data[:offset]) and self._drain()):
                return False
            self._log.append(fault)
            self._close_terminal()
            if self._stop.wait(fault.seconds):
                return False
            self._open_terminal()
            return self._wait_for_host()
        if sent:
            self._log.append(fault)
        return sent

    def _write(self, data: bytes) -> bool:
        view = memoryview(data)
        poller = select.poll()
        poller.register(self._master, select.POLLOUT)
        while view:
            if self._stop.is_set():
                return False
            events = dict(poller.poll(100)).get(self._master, 0)
            if events & select.POLLHUP:  # the host closed the port
                return False
            if events & select.POLLOUT:
                try:
                    view = view[os.write(self._master, view) :]
                except BlockingIOError:
                    continue
        return True

    def _host_connected(self) -> bool:
        poller = select.poll()
        poller.register(self._master, select.POLLOUT)
        return not dict(poller.poll(0)).get(self._master, 0) & select.POLLHUP

    def _wait_for_host(self) -> bool:
        """Wait until a host has opened the port and flushed its input queue; False if none
        came within `host_timeout` or `stop()` was called."""
        deadline = time.monotonic() + self.host_timeout
        while not self._host_connected():
            if time.monotonic() > deadline or self._stop.wait(0.01):
                return False
        flush_deadline = time.monotonic() + _OPEN_FLUSH_WAIT
        while not self._host_flushed():
            if time.monotonic() > flush_deadline:
                return True
            if self._stop.wait(0.002):
                return False
        return True

    def _host_flushed(self) -> bool:
        """Whether the host flushed its input queue since the last call (a packet-mode status
        byte with TIOCPKT_FLUSHREAD; the host never writes, so no data packet comes)."""
        try:
            status = os.read(self._master, 64)
        except (BlockingIOError, OSError):  # nothing to report, or no host holds the port
            return False
        return bool(status) and bool(status[0] & termios.TIOCPKT_FLUSHREAD)

    def _drain(self) -> bool:
        """Wait until the host has read every byte sent; False if it went away first."""
        try:
            # Our own descriptor of the serial end shares its input queue with the host's.
            probe = os.open(self._serial_end, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        except OSError:
            return False
        try:
            # The kernel moves written bytes into the input queue asynchronously: an empty queue
            # counts only once it has stayed empty for _DRAIN_SETTLE seconds.
            deadline = time.monotonic() + _DRAIN_TIMEOUT
            empty_since = None
            while True:
                now = time.monotonic()
                if struct.unpack("i", fcntl.ioctl(probe, termios.TIOCINQ, b"\0" * 4))[0]:
                    empty_since = None
                elif empty_since is None:
                    empty_since = now
                elif now - empty_since >= _DRAIN_SETTLE:
                    return True
                if now > deadline or self._stop.wait(0.005):
                    return False
        finally:
            os.close(probe)

    def _open_terminal(self) -> None:
        master, serial_end = os.openpty()
        tty.setraw(serial_end)  # no echo, no line editing, no CR/LF translation: bytes as sent
        self._serial_end = os.ttyname(serial_end)
        os.close(serial_end)  # so that polling the master tells whether a host holds it open
        os.set_blocking(master, False)
        # Packet mode: the master reads a status byte when the host flushes its input queue.
        fcntl.ioctl(master, termios.TIOCPKT, struct.pack("i", 1))
        self._master = master
        temporary = f"{self.port}.{os.getpid()}.link"
        os.symlink(self._serial_end, temporary)
        os.replace(temporary, self.port)

    def _close_terminal(self) -> None:
        if self._master is not None:
            if os.path.islink(self.port):
                os.unlink(self.port)
            os.close(self._master)
            self._master = None
