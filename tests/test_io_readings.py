"""What a reading is (signed or a magnitude), complex EIDORS frames and readings on driven
electrodes: the IIRC 2006 tank, the Montreal 1995 magnitudes, OpenEIT logs, the frames file."""

import re
from pathlib import Path

import h5py
import numpy as np
import pytest
import scipy.io

from diffeit.io import Recording, append_frames, read_eidors_mat, read_frames, read_openeit, write_frames
from diffeit.protocol import adjacent, from_full_layout, to_full_layout

DATA = Path(__file__).parent / "data"
IIRC = DATA / "iirc_data_2006.mat"
MONTREAL = DATA / "montreal_data_1995.mat"


@pytest.fixture(scope="module")
def raw() -> dict[str, np.ndarray]:
    return scipy.io.loadmat(IIRC)


def _driven_positions(n: int = 16) -> np.ndarray:
    """Value n * k + m of the full layout where pair (m, m+1) touches electrode k or k+1."""
    return np.array(sorted(n * k + (k + d) % n for k in range(n) for d in (-1, 0, 1)))


def _same_protocol(a, b) -> None:
    for name in ("drive", "measure", "drive_index"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


# ---------------------------------------------------------------------------------------------
# The IIRC 2006 tank: complex frames with every driven-pair reading measured


def test_iirc_keeps_the_driven_readings_and_reads_the_in_phase_part(raw):
    assert raw["v_rotate"].shape == (256, 100) and raw["v_rotate"].dtype == np.complex64
    recording = read_eidors_mat(IIRC, "v_rotate", reference="v_reference", frame_rate=10.0)
    assert recording.frames.shape == (100, 256) and recording.reference.shape == (256,)
    _same_protocol(recording.protocol, adjacent(16, measure_driven=True))
    # Reading 16 k + m (drive k, pair (m, m+1)) is the file's row 16 k + m, frame t its column t.
    rotate, reference = raw["v_rotate"], raw["v_reference"][:, 0]
    for t, k, m in ((0, 0, 0), (0, 0, 1), (7, 3, 9), (99, 15, 14), (42, 11, 12)):
        assert recording.frames[t, 16 * k + m] == np.float64(rotate[16 * k + m, t].real)
        assert recording.reference[16 * k + m] == np.float64(reference[16 * k + m].real)
    np.testing.assert_array_equal(recording.frames, rotate.real.T.astype(np.float64))
    np.testing.assert_array_equal(recording.reference, reference.real.astype(np.float64))
    # The in-phase readings of each drive change sign: signed, decided from the values.
    assert recording.readings == "signed" and recording.voltage_unit == "arbitrary"
    assert np.all((recording.frames < 0).sum(axis=1) == 224) and np.all((recording.frames > 0).sum(axis=1) == 32)
    metadata = recording.provenance["metadata"]
    assert metadata["complex_part"] == "real" and metadata["driven_readings"] == "kept"
    assert metadata["driven_pair_values"] == "non-zero" and metadata["orientation"] == "columns are frames"
    np.testing.assert_allclose(recording.times[:3], [0.0, 0.1, 0.2])


def test_iirc_magnitudes(raw):
    recording = read_eidors_mat(IIRC, "v_rotate", reference="v_reference", complex_part="magnitude")
    assert recording.readings == "magnitude" and recording.provenance["metadata"]["complex_part"] == "magnitude"
    np.testing.assert_array_equal(recording.frames, np.abs(raw["v_rotate"]).T.astype(np.float64))
    np.testing.assert_array_equal(recording.reference, np.abs(raw["v_reference"][:, 0]).astype(np.float64))
    # The quadrature part is about a fifth of the in-phase part, so the magnitudes differ from it.
    assert 1.0 < np.abs(recording.frames[0, 16 * 2 + 5]) / abs(raw["v_rotate"][37, 0].real) < 1.1
    # Explicit readings override the rule; the values must fit them.
    signed = read_eidors_mat(IIRC, "v_rotate", complex_part="magnitude", readings="signed")
    assert signed.readings == "signed"
    with pytest.raises(ValueError, match=r"iirc_data_2006\.mat, variable 'v_rotate': frames hold negative values"):
        read_eidors_mat(IIRC, "v_rotate", readings="magnitude")


def test_iirc_driven_readings_dropped(raw):
    kept = read_eidors_mat(IIRC, "v_rotate", reference="v_reference")
    dropped = read_eidors_mat(IIRC, "v_rotate", reference="v_reference", driven_readings="drop")
    assert dropped.frames.shape == (100, 208) and dropped.reference.shape == (208,)
    _same_protocol(dropped.protocol, adjacent(16))
    measured = np.setdiff1d(np.arange(256), _driven_positions())
    np.testing.assert_array_equal(dropped.frames, raw["v_rotate"][measured].real.T.astype(np.float64))
    np.testing.assert_array_equal(dropped.reference, raw["v_reference"][measured, 0].real.astype(np.float64))
    np.testing.assert_array_equal(dropped.frames, from_full_layout(kept.frames))
    # Drive 0 reads pairs 2..14: the file's rows 2, 3, ...
    assert dropped.frames[0, 0] == np.float64(raw["v_rotate"][2, 0].real)
    assert dropped.provenance["metadata"]["driven_readings"] == "dropped"
    # strict refuses dropping measured readings.
    with pytest.raises(ValueError, match="strict=True refuses them"):
        read_eidors_mat(IIRC, "v_rotate", driven_readings="drop", strict=True)


def test_iirc_every_variable():
    recordings = read_eidors_mat(IIRC)
    assert sorted(recordings) == ["v_reference", "v_rotate"]  # "description" is text, not frames
    assert {name: r.n_frames for name, r in recordings.items()} == {"v_reference": 1, "v_rotate": 100}
    assert {r.protocol.n_measurements for r in recordings.values()} == {256}


def test_driven_readings_follow_the_reference_and_keep_refuses_what_is_not_there(tmp_path):
    rng = np.random.default_rng(11)
    short = rng.uniform(1, 2, size=(3, 208))
    measured = np.asarray(to_full_layout(short))
    measured[:, _driven_positions()] = rng.uniform(5, 6, size=(3, 48))
    path = tmp_path / "frames.mat"
    variables = {"full": measured.T, "zeros": to_full_layout(short[:1]).T, "short": short.T, "short_one": short[:1].T}
    scipy.io.savemat(path, variables)
    assert read_eidors_mat(path, "full").protocol.n_measurements == 256
    # A reference without driven readings: the frames drop theirs, one protocol for both.
    for reference in ("zeros", "short_one"):
        recording = read_eidors_mat(path, "full", reference=reference)
        assert recording.protocol.n_measurements == 208
        assert recording.provenance["metadata"]["driven_readings"] == "dropped"
        np.testing.assert_array_equal(recording.frames, short)
        with pytest.raises(ValueError, match=f"the reference '{reference}' hold"):
            read_eidors_mat(path, "full", reference=reference, driven_readings="keep")
    with pytest.raises(ValueError, match="zeros on every driven pair: nothing was measured"):
        read_eidors_mat(MONTREAL, "zc_demo3", driven_readings="keep")
    with pytest.raises(ValueError, match="the frames hold 208 values, no driven-pair readings to keep"):
        read_eidors_mat(path, "short", driven_readings="keep")
    assert read_eidors_mat(path, "short").provenance["metadata"]["driven_readings"] == "absent"


def test_complex_frames_and_keyword_refusals(tmp_path):
    frames = to_full_layout(np.ones((2, 208))).astype(np.complex128) * (1 - 2j)
    bad = frames.copy()
    bad[1, 7] = complex(1.0, np.inf)  # the quadrature part is not read, but a file with inf is refused
    path = tmp_path / "complex.mat"
    scipy.io.savemat(path, {"frames": frames.T, "bad": bad.T})
    recording = read_eidors_mat(path, "frames")
    np.testing.assert_array_equal(recording.frames, 1.0)
    assert recording.readings == "magnitude"  # all in-phase values >= 0: no sign to go by
    np.testing.assert_allclose(read_eidors_mat(path, "frames", complex_part="magnitude").frames, np.sqrt(5))
    with pytest.raises(ValueError, match=r"'bad': frames \[1\] hold non-finite values"):
        read_eidors_mat(path, "bad")
    for keyword, value in (("complex_part", "imag"), ("driven_readings", "all"), ("readings", "abs")):
        with pytest.raises(ValueError, match=f"{keyword} must be one of"):
            read_eidors_mat(path, "frames", **{keyword: value})


def test_montreal_reads_as_magnitudes_unless_told():
    recording = read_eidors_mat(MONTREAL, "zc_demo3", reference="zc_h_demo3")
    assert recording.readings == "magnitude"
    assert read_eidors_mat(MONTREAL, "zc_demo3", readings="signed").readings == "signed"


# ---------------------------------------------------------------------------------------------
# Damaged .mat files: refused as a whole, never read in part (or, in scipy, a crash)


def _sound_mat(path: Path, compressed: bool) -> np.ndarray:
    """A v5 file as MATLAB saves one: frames, a reference, and a cell array and a struct that
    are not frames (never read). The frames (T, 208)."""
    frames = np.random.default_rng(5).uniform(1, 2, size=(2, 208))
    variables = {"frames": frames.T, "reference": frames[:1].T, "notes": np.array([[1.0, "a"]], dtype=object)}
    scipy.io.savemat(path, {**variables, "model": {"n": 16}}, do_compression=compressed)
    return frames


def _changed(path: Path, offset: int, value: bytes) -> Path:
    data = bytearray(path.read_bytes())
    data[offset : offset + len(value)] = value
    damaged = path.with_name("damaged.mat")
    damaged.write_bytes(bytes(data))
    return damaged


def test_a_compressed_mat_file_cut_or_changed_anywhere_is_refused_or_read_whole(tmp_path):
    """MATLAB's default (v7) compresses each variable with a checksum: a cut or a flipped bit
    anywhere is refused (naming the file) or changes nothing that is read (the header's text)."""
    frames = _sound_mat(tmp_path / "sound.mat", compressed=True)
    data = (tmp_path / "sound.mat").read_bytes()
    rng = np.random.default_rng(6)
    path = tmp_path / "damaged.mat"
    damaged = [data[:cut] for cut in rng.integers(0, len(data), 40)]
    for offset, bit in zip(rng.integers(0, len(data), 80), rng.integers(0, 8, 80), strict=True):
        flipped = bytearray(data)
        flipped[offset] ^= 1 << bit
        damaged.append(bytes(flipped))
    for content in damaged:
        path.write_bytes(content)
        try:
            recording = read_eidors_mat(path, "frames", reference="reference")
        except ValueError as error:
            assert str(path) in str(error)
        else:
            np.testing.assert_array_equal(recording.frames, frames)
            np.testing.assert_array_equal(recording.reference, frames[0])


# The uncompressed file ('-v6', scipy's default): "frames" at byte 128, its real values' tag at
# 184 (after its 8-byte tag, array flags, dimensions and name, 16 bytes each).
@pytest.mark.parametrize(
    ("offset", "value", "message"),
    [
        (184, b"\x19", r"'frames', 208x2\) has no real values of that size \(data type 25"),  # scipy: a segfault
        (184, b"\x0e", r"has no real values of that size \(data type 14"),  # an miMATRIX: a segfault too
        (168, b"\x07", r"has no name \(miINT8 characters\)"),
        (152, b"\x09", r"has no dimensions"),
        (132, b"\xff\xff", "cut short: the variable at byte 128 claims"),
        (128, b"\x0d", "has data type 13, neither miMATRIX nor miCOMPRESSED"),
        (125, b"\x02", r"a MATLAB v7\.3 file \(HDF5\)"),
        (126, b"XX", "not a MATLAB file: bytes 124-127"),
    ],
)
def test_a_mat_file_of_damaged_structure_is_refused(tmp_path, offset, value, message):
    _sound_mat(tmp_path / "sound.mat", compressed=False)
    damaged = _changed(tmp_path / "sound.mat", offset, value)
    with pytest.raises(ValueError, match=re.escape(str(damaged)) + ".*" + message):
        read_eidors_mat(damaged, "frames")


def test_other_damaged_mat_files_are_refused_naming_the_file(tmp_path):
    frames = _sound_mat(tmp_path / "sound.mat", compressed=False)
    data = (tmp_path / "sound.mat").read_bytes()
    # Variables other than numeric arrays are named, never read: a cell array whose dimensions
    # are damaged (scipy allocated 2**28 cells, a hang) costs nothing.
    notes = data.index(b"notes") - 48  # its tag: then flags, dimensions and the name's tag, 16, 16, 8 bytes
    assert data[notes : notes + 4] == b"\x0e\x00\x00\x00"
    huge = _changed(tmp_path / "sound.mat", notes + 35, b"\x10")  # the high byte of its first dimension
    np.testing.assert_array_equal(read_eidors_mat(huge, "frames").frames, frames)
    for name, kind in (("notes", "a cell array"), ("model", "a struct")):
        with pytest.raises(ValueError, match=f"variable '{name}' is {kind}, not frames"):
            read_eidors_mat(huge, name)
    cases = {
        "cut.mat": data[: len(data) - 3],  # within the last variable
        "twice.mat": data + data[128:],
        "empty.mat": b"",
        "text.mat": b"frames = [1 2 3]\n",
        "picture.mat": b"\x89PNG\r\n\x1a\n" + bytes(range(256)),
    }
    messages = {
        "cut.mat": "cut short: the variable at byte",
        "twice.mat": "two variables are named 'frames'",
        "empty.mat": "is not a MATLAB file: 0 bytes",
        "text.mat": "cut short or not a MATLAB file: 17 bytes",
        "picture.mat": "not a MATLAB file: bytes 124-127",
    }
    for name, content in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ValueError, match=re.escape(str(tmp_path / name)) + ".*" + messages[name]):
            read_eidors_mat(tmp_path / name, "frames")
    with h5py.File(tmp_path / "frames.h5", "w") as file:
        file["frames"] = frames
    with pytest.raises(ValueError, match=r"frames\.h5: not a MATLAB file"):
        read_eidors_mat(tmp_path / "frames.h5")
    with pytest.raises(FileNotFoundError, match=r"no such \.mat file"):
        read_eidors_mat(tmp_path / "missing.mat")


def test_a_compressed_variable_damaged_or_cut_is_refused(tmp_path):
    _sound_mat(tmp_path / "sound.mat", compressed=True)
    data = (tmp_path / "sound.mat").read_bytes()
    start, size = 136, int.from_bytes(data[132:136], "little")  # the zlib stream of the first variable
    changed = _changed(tmp_path / "sound.mat", start + size // 2, bytes([data[start + size // 2] ^ 0x01]))
    with pytest.raises(ValueError, match=r"damaged\.mat: the variable at byte 128 is compressed and damaged"):
        read_eidors_mat(changed, "frames")
    # The stream's length shortened by 2: its end is missing, and the next variable's tag
    # starts within it.
    shorter = _changed(tmp_path / "sound.mat", 132, (size - 2).to_bytes(4, "little"))
    with pytest.raises(ValueError, match="the variable at byte 128 is compressed and cut short"):
        read_eidors_mat(shorter, "frames")


# ---------------------------------------------------------------------------------------------
# Recording, the frames file, OpenEIT


def test_recording_refuses_negative_magnitudes_and_unknown_readings():
    protocol = adjacent(8)
    frames = np.ones((3, 40))
    assert Recording(frames=frames, times=[0, 1, 2], protocol=protocol).readings == "signed"
    assert Recording(frames=frames, times=[0, 1, 2], protocol=protocol, readings="magnitude").readings == "magnitude"
    frames[2, 5] = -1e-3
    with pytest.raises(ValueError, match=r'frames hold negative values in frame\(s\) \[2\] but readings="magnitude"'):
        Recording(frames=frames, times=[0, 1, 2], protocol=protocol, readings="magnitude")
    with pytest.raises(ValueError, match=r'reference hold negative values in entries \[3\] but readings="magnitude"'):
        Recording(frames=np.ones((1, 40)), times=[0], protocol=protocol, reference=-np.eye(40)[3], readings="magnitude")
    with pytest.raises(ValueError, match=r"readings must be one of \('signed', 'magnitude'\); got 'absolute'"):
        Recording(frames=np.ones((1, 40)), times=[0], protocol=protocol, readings="absolute")


def test_frames_file_keeps_the_readings(tmp_path):
    magnitudes = read_eidors_mat(MONTREAL, "zc_demo4", reference="zc_h_demo4")
    path = write_frames(tmp_path / "magnitudes.h5", magnitudes)
    back = read_frames(path)
    assert back.readings == "magnitude"
    np.testing.assert_array_equal(back.frames, magnitudes.frames)
    with h5py.File(path) as file:
        assert file["frames"].attrs["readings"] == b"magnitude"
    # Appending to a file of magnitudes: negative values are refused, the file left as it was.
    with pytest.raises(ValueError, match="holds magnitudes"):
        append_frames(path, -np.ones(208), 10.0)
    assert append_frames(path, np.ones(208), 10.0) == 34
    signed = read_eidors_mat(IIRC, "v_reference")
    assert read_frames(write_frames(tmp_path / "signed.h5", signed)).readings == "signed"
    # A file written before the attribute existed reads as signed.
    older = tmp_path / "older.h5"
    write_frames(older, signed)
    with h5py.File(older, "r+") as file:
        del file["frames"].attrs["readings"]
    assert read_frames(older).readings == "signed"
    with h5py.File(older, "r+") as file:
        file["frames"].attrs["readings"] = "phase"
    with pytest.raises(ValueError, match=r"older\.h5: readings must be one of"):
        read_frames(older)


def test_openeit_logs_are_magnitudes(tmp_path):
    frames = np.round(np.random.default_rng(4).uniform(150, 350, size=(2, 192)), 4)
    log = tmp_path / "openeit.txt"
    log.write_text("".join("magnitudes: " + " , ".join(f"{v:.4f}" for v in row) + " ,\n" for row in frames))
    recording = read_openeit(log)
    assert recording.readings == "magnitude"
    np.testing.assert_array_equal(recording.frames, frames)
    log.write_text(log.read_text() + "magnitudes: " + " , ".join(["-1.0"] * 192) + "\n")
    with pytest.raises(ValueError, match=r"lines \[3\] hold negative values; OpenEIT prints magnitudes"):
        read_openeit(log)
