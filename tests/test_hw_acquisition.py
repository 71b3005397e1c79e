"""Acquisition end to end through a real pseudo-terminal: the emulator injects faults and logs
them, hw.SerialSource reads it as a serial port, hw.Recorder writes what arrives; every frame is
accounted for."""

import os
import signal
import socket
import subprocess
import sys
import termios
import threading
import time

import numpy as np
import pytest

import hw
from diffeit.io import append_frames, read_frames
from diffeit.protocol import adjacent
from hw.frame import HEADER_SIZE, SYNC

RNG = np.random.default_rng(5)
FAULTS = {"bit_flip": 0.03, "dropped_bytes": 0.03, "truncated": 0.03, "stall": 0.03, "disconnect": 0.01}


def _acquire(emulator: hw.Emulator, source: hw.SerialSource, recorder: hw.Recorder | None = None) -> list[hw.Frame]:
    """Every frame until the emulator is done and its port gone for good."""
    arrived = []
    try:
        for frame in source.frames():
            arrived.append(frame)
            if recorder is not None:
                recorder.append(frame, source.statistics)
    except hw.DeviceLost:
        pass
    assert emulator.wait(timeout=10)
    return arrived


def _expected_rejections(log: tuple[hw.Fault, ...]) -> dict[str, int]:
    """The parser's rejections of the logged faults under its resynchronisation rule: a fault in
    the sync marker leaves nothing to reject; one in the rest of the header is `header`; one
    in the values or the CRC is `crc`; a frame cut off by a disconnection is `truncated`."""
    expected = {"header": 0, "crc": 0, "truncated": 0}
    for fault in log:
        if fault.kind in ("stall", "not_sent") or fault.offset < len(SYNC):
            continue
        if fault.kind == "disconnect":
            expected["truncated"] += 1
        else:
            expected["header" if fault.offset < HEADER_SIZE else "crc"] += 1
    return expected


def _check_run(frames: np.ndarray, emulator: hw.Emulator, arrived: list[hw.Frame], statistics: hw.DropStatistics):
    counters = [frame.counter for frame in arrived]
    assert counters == sorted(set(counters)), "frames arrive in order, each once"
    assert set(counters) == set(range(len(frames))) - set(emulator.lost_frames), "every intact frame arrives"
    np.testing.assert_array_equal([f.values for f in arrived], frames[counters].astype(np.float32))
    stalled = {fault.frame for fault in emulator.log if fault.kind == "stall"}
    assert stalled and stalled <= set(counters), "a stalled frame arrives whole"
    kinds = {fault.kind for fault in emulator.log}
    assert {"bit_flip", "dropped_bytes", "truncated", "disconnect"} <= kinds
    assert statistics.frames == len(arrived)
    assert statistics.missing_frames == counters[-1] - counters[0] + 1 - len(arrived)
    rejected = {kind: getattr(statistics, kind) for kind in ("header", "crc", "truncated")}
    assert rejected == _expected_rejections(emulator.log)
    assert statistics.rejected == sum(rejected.values())
    assert statistics.reconnects == sum(fault.kind == "disconnect" for fault in emulator.log)
    host_times = np.array([frame.host_time for frame in arrived])
    assert np.all(np.diff(host_times) >= 0)


@pytest.mark.slow
# Real time: 10 s streams about 30 faults of each kind and a few disconnections (the same
# assertions as 3 s, over more of their interplay; 30 s took 40 s and checked nothing more).
@pytest.mark.parametrize("seconds", [pytest.param(3, id="3s"), pytest.param(10, id="10s", marks=pytest.mark.slow)])
def test_every_frame_is_accounted_for_and_recorded(tmp_path, seconds):
    """100 frames/s with faults: intact frames arrive in order, damaged ones are rejected and
    counted as the rule says, missing ones are in the fault log, the recording holds exactly
    the frames that arrived."""
    frames = RNG.normal(scale=0.01, size=(100 * seconds, 208))
    faults = hw.FaultRates(**FAULTS, disconnect_seconds=0.2, seed=seconds)
    emulator = hw.Emulator(frames, frame_rate=100.0, faults=faults).start()
    with hw.SerialSource(emulator.port, hw.BinaryParser(adjacent(16)), reconnect_timeout=0.6) as source:
        with hw.Recorder(tmp_path / "run.h5", adjacent(16), metadata=source.description) as recorder:
            arrived = _acquire(emulator, source, recorder)
        statistics = source.statistics
    _check_run(frames, emulator, arrived, statistics)
    recording = read_frames(tmp_path / "run.h5")
    np.testing.assert_array_equal(recording.frames, [frame.values for frame in arrived])
    back = list(hw.read_recorded_frames(tmp_path / "run.h5"))
    assert [f.counter for f in back] == [f.counter for f in arrived]
    assert [f.host_time for f in back] == pytest.approx([f.host_time for f in arrived], abs=1e-6)
    assert [f.device_time for f in back] == pytest.approx([f.counter / 100 for f in arrived])
    assert hw.recorded_statistics(tmp_path / "run.h5") == statistics
    assert recording.provenance["metadata"]["drop_statistics"] == statistics.as_dict()
    assert recording.provenance["metadata"]["port"] == emulator.port


def test_the_emulator_waits_for_the_hosts_flush_after_opening():
    """pyserial's open() flushes the input queue after configuring the port; the emulator must
    not send before that flush, or the first frame (after each reconnection) would be discarded
    unlogged. A slow host that flushes 0.3 s after opening still receives frame 0."""
    frames = RNG.normal(scale=0.01, size=(3, 208))
    emulator = hw.Emulator(frames, frame_rate=100.0).start()
    descriptor = os.open(emulator.port, os.O_RDWR | os.O_NOCTTY)
    try:
        time.sleep(0.3)
        termios.tcflush(descriptor, termios.TCIFLUSH)
        parser, arrived = hw.BinaryParser(adjacent(16)), []
        while len(arrived) < 3:
            arrived += parser.feed(os.read(descriptor, 4096))
    finally:
        os.close(descriptor)
    assert emulator.wait(timeout=10)
    assert [frame.counter for frame in arrived] == [0, 1, 2] and emulator.log == ()


def test_text_lines_through_the_port_with_the_callback_api():
    frames = RNG.normal(size=(40, 256))
    emulator = hw.Emulator(frames, frame_rate=200.0, text=True, label="frame").start()
    source = hw.SerialSource(emulator.port, hw.TextParser(adjacent(16, measure_driven=True)), reconnect_timeout=0)
    arrived = []
    statistics = source.run(arrived.append, max_frames=40)
    source.close()
    assert emulator.wait(timeout=10) and emulator.log == ()
    np.testing.assert_array_equal([f.values for f in arrived], frames)  # decimal text round-trips exactly
    assert {f.label for f in arrived} == {"frame"} and statistics == hw.DropStatistics(frames=40)


@pytest.mark.slow
def test_the_recorder_killed_mid_run_leaves_every_frame_it_wrote(tmp_path):
    frames = RNG.normal(scale=0.01, size=(2000, 208))
    emulator = hw.Emulator(frames, frame_rate=100.0, host_timeout=60.0).start()
    script = (
        "import sys, hw\n"
        "from diffeit.protocol import adjacent\n"
        "source = hw.SerialSource(sys.argv[1], reconnect_timeout=0)\n"
        "with hw.Recorder(sys.argv[2], adjacent(16), metadata=source.description) as recorder:\n"
        "    for frame in source.frames():\n"
        "        recorder.append(frame, source.statistics)\n"
        "        print(frame.counter, flush=True)\n"
    )
    path = tmp_path / "killed.h5"
    recorder = subprocess.Popen(
        [sys.executable, "-c", script, emulator.port, str(path)], stdout=subprocess.PIPE, text=True
    )
    written = [int(recorder.stdout.readline()) for _ in range(60)]
    os.kill(recorder.pid, signal.SIGKILL)
    written += [int(line) for line in recorder.stdout.read().split()]
    recorder.wait()
    emulator.stop()
    back = list(hw.read_recorded_frames(path))
    counters = [frame.counter for frame in back]
    assert counters[: len(written)] == written == list(range(len(written)))
    assert len(counters) <= len(written) + 1  # at most the frame in flight besides
    np.testing.assert_array_equal([f.values for f in back], frames[counters].astype(np.float32))
    assert read_frames(path).n_frames == len(back)
    # Appending says why it cannot, and how to clear the writer's mark.
    with pytest.raises(ValueError, match=r"marked open for writing.*h5clear -s"):
        append_frames(path, frames[:1], [100.0])
    assert read_frames(path).n_frames == len(back)


@pytest.mark.slow
def test_a_recording_reads_consistently_while_it_is_written(tmp_path):
    """A reader polling the file while a recorder appends: every read is a prefix of the frames,
    none fails on rows counted but not yet visible, and the recorder closes cleanly."""
    path = tmp_path / "live.h5"
    script = (
        "import sys, numpy as np, hw\n"
        "from diffeit.protocol import adjacent\n"
        "with hw.Recorder(sys.argv[1], adjacent(16), durable=False) as recorder:\n"
        "    print('ready', flush=True)\n"
        "    for i in range(1500):\n"
        "        recorder.append(hw.Frame(np.full(208, float(i)), counter=i, device_time=i / 100))\n"
    )
    writer = subprocess.Popen(
        [sys.executable, "-W", "error", "-c", script, str(path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert writer.stdout.readline() == "ready\n"
    lengths = []
    while writer.poll() is None:
        frames = read_frames(path).frames
        np.testing.assert_array_equal(frames[:, 0], np.arange(len(frames)))
        lengths.append(len(frames))
    assert writer.wait() == 0, writer.stderr.read()
    assert len(lengths) > 3 and lengths == sorted(lengths)
    assert read_frames(path).n_frames == 1500 and hw.recorded_statistics(path).frames == 0


def _serve(data: bytes) -> int:
    """A TCP port that sends `data` to its first client and hangs up."""
    server = socket.create_server(("127.0.0.1", 0))

    def send() -> None:
        connection, _ = server.accept()
        time.sleep(0.3)  # pyserial's socket:// discards what arrived before its open returned
        connection.sendall(data)
        connection.close()
        server.close()

    threading.Thread(target=send, daemon=True).start()
    return server.getsockname()[1]


def test_urls_max_frames_and_a_device_that_does_not_come_back():
    frames = RNG.normal(size=(10, 208))
    data = b"".join(hw.encode_frame(v, counter=i, device_time=i) for i, v in enumerate(frames))
    port = _serve(data)
    with hw.SerialSource(f"socket://127.0.0.1:{port}", reconnect_timeout=0) as source:
        first = list(source.frames(max_frames=3))
        rest = list(source.frames(max_frames=7))  # parsed together with the first: kept, not lost
        assert [f.counter for f in first + rest] == list(range(10))
        with pytest.raises(hw.DeviceLost, match="did not come back within 0"):
            next(source.frames())


def test_source_and_emulator_refuse_bad_arguments(tmp_path):
    with pytest.raises(ConnectionError, match="cannot open serial port"):
        hw.SerialSource(str(tmp_path / "no-such-port"))
    with pytest.raises(ValueError, match="read_timeout must be >= 0"):
        hw.SerialSource("loop://", read_timeout=-1)
    with pytest.raises(ValueError, match="frames must have shape"):
        hw.Emulator(np.ones(208))
    with pytest.raises(ValueError, match="summing to at most 1"):
        hw.FaultRates(bit_flip=0.7, truncated=0.7)
    with pytest.raises(ValueError, match="records 208-value frames"), hw.Recorder(tmp_path / "r.h5", adjacent(16)) as r:
        r.append(hw.Frame(np.ones(256)))
    assert read_frames(tmp_path / "r.h5").n_frames == 0
    with pytest.raises(FileExistsError):
        hw.Recorder(tmp_path / "r.h5", adjacent(16))
    with pytest.raises(ValueError, match=r"protocol must be a diffeit\.protocol\.Protocol; got int"):
        hw.Recorder(tmp_path / "other.h5", 208)


def test_fault_plans_are_seeded():
    rates = hw.FaultRates(**FAULTS, seed=3)
    plan = hw.plan_faults([864] * 1000, rates)
    assert plan == hw.plan_faults([864] * 1000, rates)
    counts = {kind: sum(f.kind == kind for f in plan) for kind in FAULTS}
    assert 15 <= counts["bit_flip"] <= 45 and 2 <= counts["disconnect"] <= 20
    assert all(0 <= f.offset < 864 and (f.kind != "dropped_bytes" or 1 <= f.size <= 16) for f in plan)


def test_a_wall_clock_set_back_mid_recording_does_not_send_the_times_back(tmp_path, monkeypatch):
    """Host times come from the monotonic clock: an NTP step back of the wall clock while frames
    arrive leaves the recorded times in order (the calibration and the memory fit read them so)."""
    values = ", ".join(["1.5"] * 208)
    with (
        hw.SerialSource("loop://", hw.TextParser(208), read_timeout=0.01) as source,
        hw.Recorder(tmp_path / "run.h5", adjacent(16)) as recorder,
    ):
        source._serial.write(f"{values}\n".encode())
        recorder.append(next(source.frames()))
        monkeypatch.setattr(time, "time", lambda: 1e9)  # 2001: set back by decades
        source._serial.write(f"{values}\n".encode())
        recorder.append(next(source.frames()))
        recorder.append(hw.Frame(np.full(208, 1.5)))  # no host time: the recorder's own clock
    times = read_frames(tmp_path / "run.h5").times
    assert len(times) == 3 and np.all(np.diff(times) >= 0) and times[-1] < 60
