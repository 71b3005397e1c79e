"""Acquisition over a serial port (pyserial): frames with host timestamps, reconnection."""

from __future__ import annotations

import collections
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from typing import Any

import serial

from .frame import Frame, host_time
from .parser import AbstractParser, BinaryParser, DropStatistics


class DeviceLost(ConnectionError):
    """The device disappeared and did not come back within the reconnection timeout."""


class SerialSource:
    """Frames from a device on a serial port.

    `SerialSource(port, parser=None, *, baudrate=115200, read_timeout=0.05,
    reconnect_timeout=5.0, reconnect_interval=0.1, open_timeout=0.0, **serial_options)`

    - `port`: a device name (`/dev/ttyACM0`, `COM3`) or a pyserial URL (`socket://host:port`,
      `rfc2217://...`, `loop://`): opened with `serial.serial_for_url`.
    - `parser`: a `hw.BinaryParser` (default) or `hw.TextParser` (text lines need their
      layout declared).
    - `baudrate`: bits per second (USB CDC devices ignore it); `read_timeout`: seconds one read
      waits for bytes (how quickly `stop()` and `duration` take effect).
    - `reconnect_timeout`: when the port fails (the device unplugged, reset, or the emulator
      disconnecting), the partial frame is dropped (counted `truncated`) and the port reopened
      every `reconnect_interval` seconds for up to this many seconds; then `DeviceLost`. 0
      disables reconnection.
    - `open_timeout`: seconds to keep trying the first open (0: one try, `ConnectionError`).
    - `serial_options`: passed on to pyserial (bytesize, parity, rtscts, ...).

    `frames(max_frames=None, duration=None)` iterates over frames as they arrive, each with
    `host_time` (seconds since the Unix epoch when the read that completed it returned, on
    `hw.frame.host_time`'s clock, which never steps back);
    `run(callback, ...)` calls `callback(frame)` for each. Both end after `max_frames` frames,
    `duration` seconds or `stop()` (from another thread or the callback), and raise `DeviceLost`
    when the device is gone for good. Frames already parsed when an iteration ends are kept for
    the next one: none is lost. `statistics` is the parser's `DropStatistics` with `reconnects`
    (its `frames`: those delivered).
    Use as a context manager, or call `close()`.
    """

    def __init__(
        self,
        port: str,
        parser: AbstractParser | None = None,
        *,
        baudrate: int = 115200,
        read_timeout: float = 0.05,
        reconnect_timeout: float = 5.0,
        reconnect_interval: float = 0.1,
        open_timeout: float = 0.0,
        **serial_options: Any,
    ) -> None:
        if parser is not None and not isinstance(parser, AbstractParser):
            raise ValueError(f"parser must be a hw.BinaryParser or hw.TextParser; got {type(parser).__name__}")
        for name, value in (
            ("read_timeout", read_timeout),
            ("reconnect_timeout", reconnect_timeout),
            ("reconnect_interval", reconnect_interval),
            ("open_timeout", open_timeout),
        ):
            if not value >= 0:
                raise ValueError(f"{name} must be >= 0 seconds; got {value}")
        self.port = str(port)
        self.parser = parser if parser is not None else BinaryParser()
        self.baudrate = baudrate
        self.read_timeout = read_timeout
        self.reconnect_timeout = reconnect_timeout
        self.reconnect_interval = reconnect_interval
        self.serial_options = serial_options
        self._reconnects = 0
        self._pending: collections.deque[Frame] = collections.deque()
        self._stopping = False
        self._last_error: Exception | None = None
        self._serial = self._open_within(open_timeout)
        if self._serial is None:
            raise ConnectionError(f"cannot open serial port {self.port} ({self._last_error})")

    @property
    def description(self) -> dict[str, Any]:
        """What to store with a recording: the port and its settings."""
        return {
            "port": self.port,
            "baudrate": self.baudrate,
            "parser": type(self.parser).__name__,
            **{key: str(value) for key, value in self.serial_options.items()},
        }

    @property
    def statistics(self) -> DropStatistics:
        """The parser's statistics with `reconnects`; `frames` counts the frames delivered (those
        parsed but still waiting for the next iteration are not yet counted)."""
        parsed = self.parser.statistics
        return replace(parsed, frames=parsed.frames - len(self._pending), reconnects=self._reconnects)

    def frames(self, *, max_frames: int | None = None, duration: float | None = None) -> Iterator[Frame]:
        """Frames as they arrive (see the class docstring)."""
        self._stopping = False
        deadline = None if duration is None else time.monotonic() + duration
        delivered = 0
        while not self._stopping and (max_frames is None or delivered < max_frames):
            if self._pending:
                delivered += 1
                yield self._pending.popleft()
                continue
            if deadline is not None and time.monotonic() >= deadline:
                return
            try:
                if self._serial is None:  # closed, or lost earlier
                    raise serial.SerialException(f"{self.port} is not open")
                data = self._serial.read(max(1, self._serial.in_waiting))
            except (serial.SerialException, OSError):
                self._reconnect()
                continue
            if data:
                read_at = host_time()
                self._pending.extend(replace(frame, host_time=read_at) for frame in self.parser.feed(data))

    def run(
        self, callback: Callable[[Frame], object], *, max_frames: int | None = None, duration: float | None = None
    ) -> DropStatistics:
        """Call `callback(frame)` for each frame as it arrives; the statistics at the end."""
        for frame in self.frames(max_frames=max_frames, duration=duration):
            callback(frame)
        return self.statistics

    def stop(self) -> None:
        """End the running iteration after the current read (safe from another thread)."""
        self._stopping = True

    def close(self) -> None:
        if self._serial is not None:
            self._serial.close()
            self._serial = None

    def __enter__(self) -> SerialSource:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def _reconnect(self) -> None:
        self.parser.reset()
        self.close()
        self._serial = self._open_within(self.reconnect_timeout) if self.reconnect_timeout > 0 else None
        if self._serial is None and self._stopping:  # stop() while reconnecting: end, not DeviceLost
            return
        if self._serial is None:
            reason = f" ({self._last_error})" if self.reconnect_timeout > 0 else " (reconnection disabled)"
            raise DeviceLost(f"{self.port} disappeared and did not come back within {self.reconnect_timeout} s{reason}")
        self._reconnects += 1

    def _open_within(self, timeout: float) -> serial.SerialBase | None:
        deadline = time.monotonic() + timeout
        while True:
            try:
                return serial.serial_for_url(
                    self.port, baudrate=self.baudrate, timeout=self.read_timeout, **self.serial_options
                )
            except (serial.SerialException, OSError, ValueError) as error:
                self._last_error = error
            if time.monotonic() + self.reconnect_interval > deadline or self._stopping:
                return None
            time.sleep(self.reconnect_interval)
