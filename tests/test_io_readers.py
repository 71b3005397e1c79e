"""Readers of other recordings in diffeit.io: OpenEIT text logs and generic CSV."""

import numpy as np
import pytest

from diffeit.io import read_csv, read_frames, read_openeit, write_frames
from diffeit.protocol import adjacent, from_pyeit, opposite

RNG = np.random.default_rng(3)


def _openeit_protocol(n: int):
    """OpenEIT's imaging protocol as its firmware tables list it: pyEIT's eit_scan_lines(n, n/2)
    drives [i, i + n/2] (current in at i) and readings [m + 1, m] (V(m+1) - V(m)) from m = 0,
    skipping pairs on a driven electrode."""
    ex_mat = np.array([[i, (i + n // 2) % n] for i in range(n)])
    meas_mat = np.array([[[(m + 1) % n, m] for m in range(n) if not {m, (m + 1) % n} & {a, b}] for a, b in ex_mat])
    return from_pyeit(ex_mat, meas_mat)


def test_openeit_layout_is_diffeits_opposite_value_for_value():
    openeit = _openeit_protocol(16)
    # The firmware's table, electrode = multiplexer channel / 2, rows (A+, A-, V+, V-): drive 0
    # reads (2,1), (3,2), ..., (7,6), (10,9), ..., (15,14); drive 2 starts with (1,0), (4,3).
    first = openeit.measure[:12]
    assert [(int(np.argmax(row)), int(np.argmin(row))) for row in first] == [
        (2, 1), (3, 2), (4, 3), (5, 4), (6, 5), (7, 6), (10, 9), (11, 10), (12, 11), (13, 12), (14, 13), (15, 14),
    ]  # fmt: skip
    drive_2 = openeit.measure[openeit.drive_index == 2][:2]
    assert [(int(np.argmax(row)), int(np.argmin(row))) for row in drive_2] == [(1, 0), (4, 3)]
    # Reading j: OpenEIT's drive and weights are diffeit's negated, so the voltage is the same.
    ours = opposite(16)
    np.testing.assert_array_equal(openeit.drive[openeit.drive_index], -ours.drive[ours.drive_index])
    np.testing.assert_array_equal(openeit.measure, -ours.measure)


def _openeit_line(values: np.ndarray) -> str:
    return "magnitudes: " + "".join(f"{value:13.4f} , " for value in values) + "\n"


def test_openeit_log_reads_as_opposite_frames(tmp_path):
    frames = np.round(RNG.uniform(150, 350, size=(3, 192)), 4)
    log = tmp_path / "openeit.txt"
    log.write_text("OpenEIT\nmode 3: imaging\n\n" + "".join(map(_openeit_line, frames)))
    recording = read_openeit(log, frame_rate=4.0)
    np.testing.assert_array_equal(recording.frames, frames)
    assert recording.protocol.n_measurements == 192
    np.testing.assert_array_equal(recording.protocol.drive, opposite(16).drive)
    np.testing.assert_array_equal(recording.protocol.measure, opposite(16).measure)
    np.testing.assert_array_equal(recording.times, [0.0, 0.25, 0.5])
    assert recording.voltage_unit == "arbitrary"
    assert recording.provenance["metadata"]["skipped_lines"] == []
    back = read_frames(write_frames(tmp_path / "openeit.h5", recording))
    np.testing.assert_array_equal(back.frames, frames)


def test_openeit_electrode_count_from_the_line_length_and_malformed_lines(tmp_path):
    log = tmp_path / "eight.txt"
    good = [_openeit_line(RNG.uniform(1, 2, 32)) for _ in range(4)]
    log.write_text(good[0] + good[1][:60] + "\n" + good[2] + "magnitudes: 1.0 , x ,\n" + good[3])
    with pytest.raises(ValueError, match=r"lines \[2, 4\] are not 32 numbers \(the 8-electrode"):
        read_openeit(log)
    recording = read_openeit(log, skip_malformed=True)
    assert recording.protocol.n_electrodes == 8 and recording.n_frames == 3
    assert recording.provenance["metadata"]["skipped_lines"] == [2, 4]
    # The frames keep their places in time: a line dropped leaves its frame's time empty.
    np.testing.assert_array_equal(recording.times, [0.0, 2.0, 4.0])
    (tmp_path / "odd.txt").write_text("magnitudes: 1, 2, 3\n")
    with pytest.raises(ValueError, match="lines hold \\[3\\] values; OpenEIT's opposition layouts have"):
        read_openeit(tmp_path / "odd.txt")
    (tmp_path / "empty.txt").write_text("OpenEIT\n\n")
    with pytest.raises(ValueError, match="holds no lines of values"):
        read_openeit(tmp_path / "empty.txt")
    with pytest.raises(FileNotFoundError):
        read_openeit(tmp_path / "missing.txt")


def test_csv_with_a_header_and_a_time_column(tmp_path):
    frames = RNG.normal(size=(4, 208))
    times = [0.0, 0.02, 0.05, 0.07]
    path = tmp_path / "frames.csv"
    lines = ["t," + ",".join(f"v{i}" for i in range(208))]
    lines += [f"{t}," + ",".join(repr(float(v)) for v in row) for t, row in zip(times, frames, strict=True)]
    path.write_text("\n".join(lines) + "\n")
    recording = read_csv(path, time_column="t")
    np.testing.assert_array_equal(recording.frames, frames)
    np.testing.assert_array_equal(recording.times, times)
    assert recording.protocol.n_measurements == 208
    np.testing.assert_array_equal(recording.protocol.measure, adjacent(16).measure)


def test_csv_without_header_full_layout_and_semicolons(tmp_path):
    frames = RNG.normal(size=(2, 256))
    path = tmp_path / "full.csv"
    path.write_text("".join(";".join(repr(float(v)) for v in row) + "\n" for row in frames))
    recording = read_csv(path, delimiter=";", frame_rate=10.0)
    np.testing.assert_array_equal(recording.frames, frames)
    np.testing.assert_array_equal(recording.times, [0.0, 0.1])
    np.testing.assert_array_equal(recording.protocol.measure, adjacent(16, measure_driven=True).measure)


def test_csv_headers_of_column_numbers_and_a_byte_order_mark(tmp_path):
    """pandas writes a header 0,1,...,207; Excel's "CSV UTF-8" starts with a byte-order mark:
    neither costs a frame nor adds one."""
    frames = RNG.normal(size=(3, 208))
    rows = [",".join(repr(float(v)) for v in row) for row in frames]
    numbered = tmp_path / "pandas.csv"
    numbered.write_text("\n".join([",".join(str(i) for i in range(208)), *rows]) + "\n")
    np.testing.assert_array_equal(read_csv(numbered).frames, frames)
    np.testing.assert_array_equal(read_csv(numbered, header=False).frames[1:], frames)  # when told otherwise
    marked = tmp_path / "excel.csv"
    marked.write_bytes(b"\xef\xbb\xbf" + ("\r\n".join(rows) + "\r\n").encode())
    np.testing.assert_array_equal(read_csv(marked).frames, frames)
    named = tmp_path / "named.csv"
    named.write_text("\n".join([",".join(f"v{i}" for i in range(208)), *rows]) + "\n")
    assert read_csv(named, header=True).provenance["metadata"]["columns"][:2] == ["v0", "v1"]


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("1,2,3\n4,5\n", "rows \\[2\\] do not have 3 columns"),
        ("1,2,3\n4,x,6\n", "row 2, column 1 is not a number: 'x'"),
        ("1,2,nan\n", "rows \\[1\\] hold non-finite values"),
        ("1,2,3\n", "holds 3 readings a row: not n\\(n-3\\)"),
        ("a,b\n", "holds no rows of values"),
    ],
)
def test_csv_refusals_name_the_row_and_column(tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        read_csv(path)


def test_csv_time_column_errors(tmp_path):
    path = tmp_path / "frames.csv"
    path.write_text(",".join(["0.1"] * 209) + "\n" + ",".join(["0.1"] * 209) + "\n")
    assert read_csv(path, time_column=0).n_measurements == 208
    with pytest.raises(ValueError, match="no column named 'time'"):
        read_csv(path, time_column="time")
    with pytest.raises(ValueError, match="holds 209 readings a row; the protocol has 208"):
        read_csv(path, adjacent(16))


# -- damaged text files -----------------------------------------------------------------------


def test_an_openeit_log_cut_within_a_line_is_refused(tmp_path):
    """A log cut within its last line: refused (a cut within a number would read as another
    number; a cut after 32 of 192 values as an 8-electrode frame), or dropped when told."""
    lines = [_openeit_line(values) for values in RNG.uniform(150, 350, size=(2, 192))]
    log = tmp_path / "cut.txt"
    for cut in (len(lines[1]) - 5, 12 + 32 * 16):  # within the last number; after 32 values
        log.write_text(lines[0] + lines[1][:cut])
        with pytest.raises(ValueError, match=r"cut\.txt: line 2, the last, does not end in a newline: the log is cut"):
            read_openeit(log)
        recording = read_openeit(log, skip_malformed=True)
        assert recording.n_frames == 1 and recording.provenance["metadata"]["skipped_lines"] == [2]
    log.write_text(lines[0][:200])
    with pytest.raises(ValueError, match="line 1, the last, does not end in a newline"):
        read_openeit(log)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"", "holds no lines of values"),
        (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR,\x00\x10\n", r"lines \[\d+\] are not 32 numbers"),
        (b"\x89HDF\r\n\x1a\n" + bytes(range(256)) + b"\n", "lines hold .* values; OpenEIT's opposition layouts"),
    ],
)
def test_openeit_refuses_files_of_another_kind_naming_the_file(tmp_path, content, message):
    path = tmp_path / "other.txt"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=r"other\.txt.*" + message):
        read_openeit(path, **({"n_electrodes": 8} if b"PNG" in content else {}))


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"1.5,2.5,3.5\n4.5,5.5,6.", r"line 2, the last, does not end in a newline: the file is cut short"),
        (b"\x89PNG\r\n\x1a\n\x00\x00", r"line 1 is not UTF-8 text \(byte 0\)"),
        (b"1,2\n" + b"x" * 200_000 + b"\n", "line 2 is not CSV: field larger than field limit"),
        (b"", "holds no rows of values"),
        # A row of readings with one damaged field is refused, not taken for a header.
        (b"0.5,0.2x5,0.7,0.1\n0.6,0.3,0.2,0.9\n", r"row 1, column 1 is not a number: '0\.2x5'"),
    ],
)
def test_csv_refuses_damaged_files_naming_the_file(tmp_path, content, message):
    path = tmp_path / "damaged.csv"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=r"damaged\.csv:? " + message):
        read_csv(path, adjacent(4))


def test_csv_headers_with_a_time_name_and_column_numbers(tmp_path):
    frames = RNG.normal(size=(2, 40))
    path = tmp_path / "numbered.csv"
    rows = ["t," + ",".join(str(i) for i in range(40))] + [
        f"{t}," + ",".join(repr(float(v)) for v in row) for t, row in enumerate(frames)
    ]
    path.write_text("\n".join(rows) + "\n")
    recording = read_csv(path, time_column="t")
    np.testing.assert_array_equal(recording.frames, frames)
    assert recording.protocol.n_electrodes == 8
