"""The frame formats of hw and its streaming parsers: round trips, every rejection kind, the
resynchronisation rule, and fuzzing with hypothesis."""

import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import hw
from diffeit.protocol import adjacent, opposite, skip
from hw.frame import HEADER_SIZE, LAYOUT_ADJACENT_FULL, LAYOUT_DECLARED, LAYOUT_OPPOSITE, SYNC

RNG = np.random.default_rng(11)
FRAMES = RNG.normal(scale=0.01, size=(12, 208))  # volts
FLOAT32 = FRAMES.astype(np.float32).astype(np.float64)  # what float32 frames carry


def _stream(frames=FRAMES, first_counter=0, **options) -> list[bytes]:
    return [
        hw.encode_frame(values, counter=(first_counter + i) % 2**32, device_time=0.01 * i, **options)
        for i, values in enumerate(frames)
    ]


def _feed_in_pieces(parser, data: bytes, cuts) -> list[hw.Frame]:
    frames, start = [], 0
    for cut in [*sorted(cuts), len(data)]:
        frames += parser.feed(data[start:cut])
        start = cut
    return frames


def test_binary_frames_round_trip_in_any_pieces():
    data = b"".join(_stream())
    assert len(data) == 12 * (HEADER_SIZE + 4 * 208 + 4)  # 864 bytes a frame
    for cuts in ([], list(range(1, len(data), 1)), list(RNG.integers(0, len(data), 40))):
        parser = hw.BinaryParser(adjacent(16))
        frames = _feed_in_pieces(parser, data, list(cuts))
        assert [f.counter for f in frames] == list(range(12))
        np.testing.assert_array_equal([f.values for f in frames], FLOAT32)
        assert [f.device_time for f in frames] == pytest.approx(0.01 * np.arange(12))
        assert parser.finish() == hw.DropStatistics(frames=12)


def test_integer_values_with_a_scale():
    scale = 1e-5  # volts per count
    data = b"".join(_stream(value_type="int16", scale=scale))
    frames = hw.BinaryParser().feed(data)
    np.testing.assert_allclose([f.values for f in frames], FRAMES, atol=scale / 2 + 1e-12)
    with pytest.raises(ValueError, match="int16 holds"):
        hw.encode_frame(np.full(208, 1.0), counter=0, device_time=0, value_type="int16", scale=scale)


@pytest.mark.parametrize(
    ("values", "options", "message"),
    [
        (np.full(207, 1.0), {}, "has 208 values; got 207"),
        (np.r_[np.nan, np.ones(207)], {}, "NaN or inf at \\[0\\]"),
        (np.ones(208), {"value_type": "float16"}, "value_type must be one of"),
        (np.ones(208), {"scale": 0.0}, "scale must be finite and non-zero"),
        (np.ones(208), {"scale": 1e-50}, "scale must be finite and non-zero in float32"),
        (np.full(208, 1e30), {"scale": 1e-10}, "overflow float32"),
        (np.ones(208), {"counter": 2**32}, "counter must be in"),
        (np.ones(192), {"layout": 9}, "unknown layout id 9"),
    ],
)
def test_encoding_refuses_bad_input(values, options, message):
    with pytest.raises(ValueError, match=message):
        hw.encode_frame(values, **{"counter": 0, "device_time": 0.0, **options})


def test_layouts_map_to_diffeit_protocols():
    assert hw.layout_protocol(LAYOUT_DECLARED, 16) is None
    assert hw.layout_protocol(LAYOUT_ADJACENT_FULL, 16).n_measurements == 256
    assert hw.layout_protocol(LAYOUT_OPPOSITE, 16).n_measurements == 192
    values = RNG.normal(size=192)
    data = hw.encode_frame(values, counter=0, device_time=0, layout=LAYOUT_OPPOSITE)
    assert hw.BinaryParser(opposite(16)).feed(data)[0].n_values == 192
    parser = hw.BinaryParser(adjacent(16))  # an opposite frame is not an adjacent one
    assert parser.feed(data) == [] and parser.statistics.length == 1


def test_layout_of_names_each_protocol_and_declares_the_rest():
    assert hw.layout_of(adjacent(16)) == hw.frame.LAYOUT_ADJACENT
    assert hw.layout_of(adjacent(16, measure_driven=True)) == LAYOUT_ADJACENT_FULL
    assert hw.layout_of(opposite(16)) == LAYOUT_OPPOSITE
    assert hw.layout_of(skip(16, 3)) == LAYOUT_DECLARED
    assert hw.layout_of(adjacent(16, rotate_measurements=True)) == LAYOUT_DECLARED  # same pairs, other order
    assert not hw.layout_matches(hw.frame.LAYOUT_ADJACENT, 8, adjacent(16))
    assert not hw.layout_matches(LAYOUT_DECLARED, 16, adjacent(16))
    assert not hw.layout_matches(99, 16, adjacent(16))


def test_garbage_before_between_and_after_frames_is_discarded():
    parts = _stream()
    garbage = [b"boot v1.2\r\n", SYNC[:3], bytes(RNG.integers(0, 256, 500, dtype=np.uint8)), SYNC + b"\x01"]
    data = b"".join(garbage[i % 4] + part for i, part in enumerate(parts)) + b"\xa5\x5a"
    parser = hw.BinaryParser()
    frames = _feed_in_pieces(parser, data, list(RNG.integers(0, len(data), 30)))
    assert [f.counter for f in frames] == list(range(12))
    statistics = parser.finish()
    assert statistics.frames == 12 and statistics.missing_frames == 0
    assert statistics.discarded_bytes == len(data) - sum(map(len, parts))


def _damaged(part: bytes, offset: int, kind: str) -> bytes:
    if kind == "flip":
        damaged = bytearray(part)
        damaged[offset] ^= 0x10
        return bytes(damaged)
    if kind == "drop":
        return part[:offset] + part[offset + 3 :]
    return part[:offset]  # truncated


@pytest.mark.parametrize("kind", ["flip", "drop", "truncate"])
@pytest.mark.parametrize(
    ("offset", "rejection"), [(1, None), (10, "header"), (26, "header"), (400, "crc"), (862, "crc")]
)
def test_a_damaged_frame_costs_no_other_frame(kind, offset, rejection):
    """The resynchronisation rule: frame 5 damaged at `offset`; every other frame arrives; the
    damage is rejected as the rule says (a damaged sync marker: discarded, seen as a gap)."""
    parts = _stream()
    parts[5] = _damaged(parts[5], offset, kind)
    parser = hw.BinaryParser()
    frames = parser.feed(b"".join(parts))
    assert [f.counter for f in frames] == [0, 1, 2, 3, 4, 6, 7, 8, 9, 10, 11]
    np.testing.assert_array_equal([f.values for f in frames], np.delete(FLOAT32, 5, axis=0))
    statistics = parser.finish()
    assert (statistics.missing_frames, statistics.gaps) == (1, 1)
    assert statistics.rejected == (rejection is not None)
    if rejection:
        assert getattr(statistics, rejection) == 1


def test_a_corrupted_length_field_is_caught_by_the_header_crc():
    parts = _stream()
    damaged = bytearray(parts[3])
    damaged[8:10] = (4000).to_bytes(2, "little")  # claims 4000 values: 16 kB the parser would wait for
    parts[3] = bytes(damaged)
    parser = hw.BinaryParser()
    assert [f.counter for f in parser.feed(b"".join(parts[:5]))] == [0, 1, 2, 4]
    assert parser.statistics.header == 1


def test_counter_gaps_duplicates_and_restarts():
    parts = _stream(first_counter=2**32 - 2)  # counters wrap: ..., 2**32 - 1, 0, 1, ...
    parser = hw.BinaryParser()
    frames = parser.feed(b"".join(parts[:3] + parts[5:7] + [parts[6]]))
    assert [f.counter for f in frames] == [2**32 - 2, 2**32 - 1, 0, 3, 4]
    statistics = parser.statistics
    assert (statistics.missing_frames, statistics.gaps, statistics.counter) == (2, 1, 1)
    stale = hw.encode_frame(FRAMES[0], counter=1, device_time=0)  # behind 4, not a restart
    restart = hw.encode_frame(FRAMES[0], counter=0, device_time=0)  # the device was reset
    frames = parser.feed(stale + restart)
    assert [f.counter for f in frames] == [0]
    assert (parser.statistics.counter, parser.statistics.restarts) == (2, 1)


def test_a_reset_whose_first_frame_is_lost_restarts_the_count():
    """Counters 0..99, then the device resets and its frame 0 is lost: 1..50 are a new start
    (more than 16 behind), not 50 stale frames. A counter 16 behind is stale; a jump of more
    than 2**24 ahead restarts, one of 2**24 is a gap."""
    parser = hw.BinaryParser()
    parser.feed(b"".join(_stream(np.ones((100, 208)))))
    frames = parser.feed(b"".join(_stream(np.ones((50, 208)), first_counter=1)))
    assert [f.counter for f in frames] == list(range(1, 51))
    assert (parser.statistics.counter, parser.statistics.restarts, parser.statistics.missing_frames) == (0, 1, 0)
    parser.feed(b"".join(_stream(np.ones((1, 208)), first_counter=34)))  # 50 -> 34: 16 behind, stale
    assert (parser.statistics.counter, parser.statistics.restarts, parser.statistics.missing_frames) == (1, 1, 0)
    parser.feed(b"".join(_stream(np.ones((1, 208)), first_counter=50 + 2**24 + 1)))  # days ahead
    assert (parser.statistics.restarts, parser.statistics.missing_frames) == (2, 0)
    parser.feed(b"".join(_stream(np.ones((1, 208)), first_counter=50 + 2**24 + 1 + 2**24)))  # a gap
    assert (parser.statistics.restarts, parser.statistics.missing_frames) == (2, 2**24 - 1)


def test_frames_of_another_layout_or_with_nan_are_rejected_whole():
    parser = hw.BinaryParser()  # the first frame fixes 208 adjacent values
    full = hw.encode_frame(np.ones(256), counter=1, device_time=0, layout=LAYOUT_ADJACENT_FULL)
    nan = bytearray(hw.encode_frame(np.ones(208), counter=2, device_time=0))
    nan[HEADER_SIZE : HEADER_SIZE + 4] = np.float32(np.nan).tobytes()  # a device reporting NaN, with a valid CRC
    nan[-4:] = zlib.crc32(bytes(nan[:-4])).to_bytes(4, "little")
    frames = parser.feed(_stream()[0] + full + bytes(nan) + _stream(first_counter=3)[0])
    assert [f.counter for f in frames] == [0, 3]
    assert (parser.statistics.length, parser.statistics.non_finite, parser.statistics.missing_frames) == (1, 1, 2)


def test_reset_counts_the_partial_frame_and_keeps_the_counter():
    parts = _stream()
    parser = hw.BinaryParser()
    assert len(parser.feed(parts[0] + parts[1][:500])) == 1
    parser.reset()  # the device vanished mid-frame
    assert [f.counter for f in parser.feed(parts[4])] == [4]
    statistics = parser.statistics
    assert (statistics.truncated, statistics.missing_frames) == (1, 3)
    assert statistics.discarded_bytes == 500


def test_feed_takes_bytes_only():
    with pytest.raises(TypeError, match="feed takes bytes"):
        hw.BinaryParser().feed("text")
    with pytest.raises(ValueError, match="declare the layout"):
        hw.TextParser(None)


def test_text_lines_with_labels_round_trip():
    lines = [hw.encode_text_line(values, "frame" if i % 2 else None) for i, values in enumerate(FRAMES)]
    data = b"\r\n".join(line.rstrip(b"\n") for line in lines) + b"\r\n"
    parser = hw.TextParser(adjacent(16))
    frames = _feed_in_pieces(parser, data, list(RNG.integers(0, len(data), 50)))
    np.testing.assert_array_equal([f.values for f in frames], FRAMES)  # shortest round-trip decimals
    assert [f.label for f in frames[:2]] == [None, "frame"]
    assert parser.finish() == hw.DropStatistics(frames=12)


def test_text_rejections_by_kind():
    good = hw.encode_text_line(FRAMES[0])
    lines = [
        b"magnitudes: " + b" , ".join(b"1.5" for _ in range(208)) + b" ,\n",  # OpenEIT style: accepted
        good[:-40] + b"\n",  # cut short: length
        good.replace(b",", b",x", 1),  # malformed
        b"\xff\xfe" + good,  # not ASCII: malformed
        good.replace(good.split(b",")[3], b"nan"),  # non-finite
        b"\n   \n",  # blank lines: skipped, not counted
        b"9" * 6000 + b"\n",  # longer than the limit below
        good,
        good[:100],  # the stream ends mid-line: truncated
    ]
    parser = hw.TextParser(208, max_line_bytes=5000)
    frames = parser.feed(b"".join(lines))
    assert len(frames) == 2 and frames[0].label == "magnitudes"
    np.testing.assert_array_equal(frames[0].values, np.full(208, 1.5))
    statistics = parser.finish()
    assert (statistics.length, statistics.malformed, statistics.non_finite, statistics.truncated) == (1, 3, 1, 1)


def test_a_reset_ends_a_long_line():
    """A reconnection in the middle of an over-long line: the next line is a line of its own."""
    parser = hw.TextParser(4, max_line_bytes=10)
    assert parser.feed(b"9" * 30) == []
    parser.reset()
    frames = parser.feed(b"1,2,3,4\n5,6,7,8\n")
    assert [f.values.tolist() for f in frames] == [[1, 2, 3, 4], [5, 6, 7, 8]]
    assert parser.statistics.malformed == 1


def test_a_frame_whose_values_disagree_with_its_layout_is_rejected():
    """Header: adjacent, 16 electrodes (208 values), but 100 values, CRCs valid: `length`, with
    or without a declared protocol, so a recorder never sees it."""
    frame = hw.encode_frame(np.ones(100), counter=0, device_time=0, layout=hw.frame.LAYOUT_DECLARED)
    header = bytearray(frame[: HEADER_SIZE - 2])
    header[len(SYNC) + 2] = hw.frame.LAYOUT_ADJACENT  # layout id, then the electrode count
    header[len(SYNC) + 3] = 16
    body = bytes(header) + hw.frame.header_crc(bytes(header)).to_bytes(2, "little") + frame[HEADER_SIZE:-4]
    forged = body + zlib.crc32(body).to_bytes(4, "little")
    for protocol in (adjacent(16), None):
        parser = hw.BinaryParser(protocol)
        assert parser.feed(forged) == [] and parser.statistics.length == 1


def test_every_flipped_bit_and_every_cut_in_a_frame_is_caught():
    """The header's CRC-16 and the frame's CRC-32 catch any one flipped bit: frame 1 of 3,
    damaged at each bit in turn, is never delivered, and is counted (`header`, `crc`; a
    damaged sync marker: discarded bytes); a frame cut anywhere costs no other frame."""
    values = np.arange(1.0, 9.0)  # 8 values, declared by the host: 64-byte frames
    parts = [
        hw.encode_frame(values * (i + 1), counter=i, device_time=0.01 * i, layout=LAYOUT_DECLARED) for i in range(3)
    ]
    damaged_streams = []
    for offset in range(len(parts[1])):
        for bit in range(8):
            damaged = bytearray(parts[1])
            damaged[offset] ^= 1 << bit
            damaged_streams.append((offset, bytes(damaged)))
    damaged_streams += [(len(SYNC), parts[1][:cut]) for cut in range(len(SYNC), len(parts[1]))]
    for offset, damaged in damaged_streams:
        parser = hw.BinaryParser()
        frames = parser.feed(parts[0] + damaged + parts[2])
        assert [f.counter for f in frames] == [0, 2]
        np.testing.assert_array_equal(frames[1].values, 3 * values)
        statistics = parser.finish()
        assert statistics.missing_frames == 1
        assert statistics.header + statistics.crc == (offset >= len(SYNC))


# -- fuzzing ----------------------------------------------------------------------------------

STREAM = _stream()
FUZZ_FRAMES = {f.counter: f.values for f in hw.BinaryParser().feed(b"".join(STREAM))}


@st.composite
def damaged_streams(draw):
    """The 12 frames with random garbage between them, random damage (bit flips, dropped and
    inserted bytes, cuts) and random read boundaries."""
    data = bytearray()
    for part in STREAM:
        data += draw(st.binary(max_size=20)) + part
    for _ in range(draw(st.integers(0, 6))):
        position = draw(st.integers(0, len(data) - 1))
        action = draw(st.sampled_from(["flip", "drop", "insert"]))
        if action == "flip":
            data[position] ^= 1 << draw(st.integers(0, 7))
        elif action == "drop":
            del data[position : position + draw(st.integers(1, 50))]
        else:
            data[position:position] = draw(st.binary(min_size=1, max_size=30)) + draw(st.sampled_from([b"", SYNC]))
    cuts = draw(st.lists(st.integers(0, len(data)), max_size=20))
    return bytes(data), cuts


@settings(max_examples=150, deadline=None, derandomize=True)
@given(damaged_streams())
def test_fuzzed_binary_streams_never_yield_a_wrong_frame(stream):
    data, cuts = stream
    parser = hw.BinaryParser()
    frames = _feed_in_pieces(parser, data, cuts)
    counters = [f.counter for f in frames]
    assert counters == sorted(set(counters))  # in order, no repeats
    for frame in frames:
        np.testing.assert_array_equal(frame.values, FUZZ_FRAMES[frame.counter])
    statistics = parser.finish()
    assert statistics.frames == len(frames)
    if frames:  # every frame between the first and the last accepted one is accounted for
        assert statistics.missing_frames == counters[-1] - counters[0] + 1 - len(frames)


@settings(max_examples=100, deadline=None, derandomize=True)
@given(st.binary(max_size=3000), st.lists(st.integers(0, 3000), max_size=10))
def test_random_bytes_are_never_frames(data, cuts):
    for parser in (hw.BinaryParser(), hw.TextParser(4, max_line_bytes=200)):
        frames = _feed_in_pieces(parser, data, [cut for cut in cuts if cut <= len(data)])
        statistics = parser.finish()
        assert statistics.discarded_bytes <= len(data)
        if isinstance(parser, hw.BinaryParser):
            assert frames == []  # two CRCs: random bytes pass with probability ~2**-48
        for frame in frames:  # text: any four finite numbers on a line are a frame
            assert frame.n_values == 4 and np.all(np.isfinite(frame.values))


def test_hw_depends_on_diffeit_io_and_protocols_only():
    import ast
    from pathlib import Path

    for source in Path(hw.__file__).parent.glob("*.py"):
        for node in ast.walk(ast.parse(source.read_text())):
            names = [node.module or ""] if isinstance(node, ast.ImportFrom) and node.level == 0 else []
            names += [alias.name for alias in node.names] if isinstance(node, ast.Import) else []
            for name in names:
                if name.startswith("diffeit"):
                    assert name in ("diffeit.io", "diffeit.protocol"), f"{source.name} imports {name}"
