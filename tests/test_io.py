"""The frames file (HDF5) and the EIDORS .mat reader of diffeit.io."""

from pathlib import Path

import h5py
import numpy as np
import pytest
import scipy.io

import diffeit as de
from diffeit.io import Recording, append_frames, mesh_from_geometry, read_eidors_mat, read_frames, write_frames
from diffeit.protocol import adjacent, to_full_layout

MONTREAL = Path(__file__).parent / "data" / "montreal_data_1995.mat"
GEOMETRY = {"kind": "disc", "n_electrodes": 8, "electrode_width": 0.3, "h": 0.5, "radius": 1.5}


@pytest.fixture(scope="module")
def mesh() -> de.Mesh:
    return mesh_from_geometry(GEOMETRY)


def _trigonometric_protocol() -> de.Protocol:
    """Not a pair protocol: cosine current patterns, readings against electrode 0, a different
    number of readings per drive."""
    angles = 2 * np.pi * np.arange(8) / 8
    drive = np.stack([np.cos(k * angles) for k in (1, 2, 3)])
    eye = np.eye(8)
    measure = [eye[1:] - eye[0], eye[[2, 4, 6]] - eye[0], eye[[3, 5]] - eye[0]]
    return de.Protocol(drive, measure)


def _recording(mesh: de.Mesh, n_frames: int = 4, **changes) -> Recording:
    protocol = _trigonometric_protocol()
    rng = np.random.default_rng(7)
    fields = {
        "frames": rng.normal(size=(n_frames, protocol.n_measurements)),
        "times": 0.1 * np.arange(n_frames),
        "protocol": protocol,
        "reference": rng.normal(size=protocol.n_measurements),
        "mesh": mesh,
        "geometry": GEOMETRY,
        "provenance": {
            "source": "test: seeded normal frames",
            "created_utc": "2026-11-22T10:00:00+00:00",
            "metadata": {"operator": "me", "skin": {"layers": [1, 2]}, "gain": np.float64(2.5)},
        },
        "images": rng.normal(size=(n_frames, mesh.n_elements)),
        "image_quantity": "conductivity change",
    }
    return Recording(**{**fields, **changes})


def test_every_field_survives_a_round_trip(tmp_path, mesh):
    recording = _recording(mesh)
    path = write_frames(tmp_path / "frames.h5", recording)
    back = read_frames(path)
    np.testing.assert_array_equal(back.frames, recording.frames)
    np.testing.assert_array_equal(back.times, recording.times)
    np.testing.assert_array_equal(back.reference, recording.reference)
    np.testing.assert_array_equal(back.images, recording.images)
    assert back.image_quantity == "conductivity change"
    assert back.voltage_unit == "V"
    for name in ("drive", "measure", "drive_index"):
        np.testing.assert_array_equal(getattr(back.protocol, name), getattr(recording.protocol, name))
    assert back.protocol.drive_index.tolist() == [0] * 7 + [1] * 3 + [2] * 2
    np.testing.assert_array_equal(back.mesh.nodes, mesh.nodes)
    np.testing.assert_array_equal(back.mesh.triangles, mesh.triangles)
    assert len(back.mesh.electrodes) == 8
    for a, b in zip(back.mesh.electrodes, mesh.electrodes, strict=True):
        np.testing.assert_array_equal(a, b)
    assert back.geometry == GEOMETRY
    assert back.provenance == {
        "source": "test: seeded normal frames",
        "created_utc": "2026-11-22T10:00:00+00:00",
        "diffeit_version": de.__version__,
        "metadata": {"operator": "me", "skin": {"layers": [1, 2]}, "gain": 2.5},
    }
    # The units and schema attributes a reader without diffeit relies on: fixed-length UTF-8
    # strings (bytes in h5py), in the object headers their checksums cover.
    with h5py.File(path) as file:
        assert file.attrs["schema"] == b"diffeit.frames" and file.attrs["schema_version"] == 2
        assert file["frames"].attrs["units"] == b"V" and file["times"].attrs["units"] == b"s"
        assert file["mesh/nodes"].attrs["units"] == b"m" and file["images"].attrs["units"] == b"S/sq"
        strings = [file.attrs[name] for name in file.attrs] + [
            file["frames"].attrs[name] for name in file["frames"].attrs
        ]
        assert not any(isinstance(value, str) for value in strings)  # none in the unchecked global heap
        assert file["frames"].maxshape == (None, 12) and file["frames"].chunks is not None


def test_minimal_recording_and_creation_stamp(tmp_path):
    recording = Recording(frames=np.ones((2, 208)), times=[0.0, 0.5], protocol=adjacent(16))
    back = read_frames(write_frames(tmp_path / "f.h5", recording))
    assert back.mesh is None and back.geometry is None and back.reference is None and back.images is None
    assert back.provenance["source"] == "" and back.provenance["metadata"] == {}
    assert back.provenance["created_utc"].endswith("+00:00")  # stamped at write time, UTC
    np.testing.assert_array_equal(back.frames, 1.0)


def test_geometry_describes_the_generated_mesh(mesh):
    reference = de.mesh.disc(8, electrode_width=0.3, h=0.5, radius=1.5)
    np.testing.assert_array_equal(mesh.nodes, reference.nodes)
    recording = Recording(frames=np.zeros((1, 40)), times=[0.0], protocol=adjacent(8), geometry=GEOMETRY)
    assert recording.resolve_mesh().n_elements == reference.n_elements
    with pytest.raises(ValueError, match=r"does not fit diffeit\.mesh\.disc"):
        mesh_from_geometry({"kind": "disc", "sides": 3})
    with pytest.raises(ValueError, match="geometry kind must be one of"):
        mesh_from_geometry({"kind": "sphere"})
    with pytest.raises(ValueError, match="neither a mesh nor a geometry"):
        Recording(frames=np.zeros((1, 40)), times=[0.0], protocol=adjacent(8)).resolve_mesh()


def test_append_grows_frames_and_times(tmp_path):
    path = tmp_path / "live.h5"
    empty = Recording(frames=np.zeros((0, 208)), times=[], protocol=adjacent(16), reference=np.ones(208))
    write_frames(path, empty)
    rng = np.random.default_rng(3)
    first, batch = rng.normal(size=208), rng.normal(size=(70, 208))  # 71 frames: more than one chunk
    assert append_frames(path, first, 0.0) == 1
    assert append_frames(path, batch, 0.1 * np.arange(1, 71)) == 71
    back = read_frames(path)
    np.testing.assert_array_equal(back.frames, np.vstack([first, batch]))
    np.testing.assert_allclose(back.times, 0.1 * np.arange(71))
    np.testing.assert_array_equal(back.reference, 1.0)
    with pytest.raises(ValueError, match=r"shape \(2, 207\); .* frames of 208 readings"):
        append_frames(path, np.zeros((2, 207)), [1.0, 2.0])
    with pytest.raises(ValueError, match="one per appended frame"):
        append_frames(path, np.zeros((2, 208)), [1.0])
    with pytest.raises(ValueError, match="non-finite"):
        append_frames(path, np.full((1, 208), np.nan), [1.0])
    assert read_frames(path).n_frames == 71  # refused appends leave the file as it was


def test_append_refuses_a_file_with_images(tmp_path, mesh):
    path = write_frames(tmp_path / "images.h5", _recording(mesh))
    with pytest.raises(ValueError, match="holds images"):
        append_frames(path, np.zeros(12), 1.0)


def test_writing_never_replaces_a_file_unless_asked(tmp_path, mesh):
    path = tmp_path / "take.h5"
    first = _recording(mesh)
    write_frames(path, first)
    second = _recording(mesh, frames=first.frames + 1.0)
    with pytest.raises(FileExistsError, match="overwrite=True"):
        write_frames(path, second)
    np.testing.assert_array_equal(read_frames(path).frames, first.frames)
    write_frames(path, second, overwrite=True)
    np.testing.assert_array_equal(read_frames(path).frames, second.frames)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["take.h5"]  # no temporary files left


def _edit(path: Path, change) -> Path:
    with h5py.File(path, "r+") as file:
        change(file)
    return path


def _replace(name, values):
    def change(file):
        del file[name]
        file[name] = values

    return change


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda f: f.__delitem__("frames"), "the dataset 'frames' is missing"),
        (lambda f: f.__delitem__("protocol/measure"), "the dataset 'protocol/measure' is missing"),
        (_replace("frames", np.zeros((4, 11))), r"frames have shape \(4, 11\); the protocol has 12 readings"),
        (_replace("times", np.zeros(3)), r"times has shape \(3,\); expected \(4,\)"),
        (_replace("reference", np.zeros(13)), r"reference has shape \(13,\)"),
        (_replace("images", np.zeros((4, 5))), r"images has shape \(4, 5\)"),
        (_replace("frames", np.where(np.eye(4, 12) > 0, np.nan, 0.0)), r"frames hold non-finite .* frame\(s\) \[0, 1"),
        (_replace("times", [0.0, np.inf, 1.0, 2.0]), "times hold non-finite"),
        (_replace("mesh/nodes", np.full((1, 2), np.nan)), "nodes \\[0\\] have non-finite coordinates"),
        (_replace("mesh/electrode_offsets", [0, 5]), "electrode_offsets must rise from 0"),
        (_replace("protocol/drive_index", np.zeros(12, dtype=int) + 3), "drive_index must run"),
        (lambda f: f.attrs.__setitem__("schema", "other"), "not a diffeit frames file"),
        (lambda f: f.attrs.__setitem__("schema_version", 3), "schema version 3"),
        (lambda f: f.attrs.__setitem__("metadata", "{oops"), "not valid JSON"),
    ],
    ids=[
        "no-frames",
        "no-measure",
        "frames-width",
        "times-length",
        "reference-length",
        "images-shape",
        "frames-nan",
        "times-inf",
        "nodes-nan",
        "offsets",
        "drive-index",
        "schema",
        "schema-version",
        "metadata-json",
    ],
)
def test_reading_names_the_problem_and_the_file(tmp_path, mesh, change, message):
    path = _edit(write_frames(tmp_path / "bad.h5", _recording(mesh)), change)
    with pytest.raises(ValueError, match=message) as raised:
        read_frames(path)
    assert str(path) in str(raised.value)


def test_reading_files_that_are_not_frames_files(tmp_path):
    text = tmp_path / "notes.h5"
    text.write_text("not hdf5")
    with pytest.raises(ValueError, match=r"notes\.h5 is not a diffeit frames file: it is not HDF5 \(a text file\)"):
        read_frames(text)
    with pytest.raises(FileNotFoundError, match="no such diffeit frames file"):
        read_frames(tmp_path / "missing.h5")


def test_recording_validates_what_it_is_given(mesh):
    protocol = adjacent(8)
    with pytest.raises(ValueError, match=r"frames has shape \(2, 41\); expected \(T, 40\)"):
        Recording(frames=np.zeros((2, 41)), times=[0, 1], protocol=protocol)
    with pytest.raises(ValueError, match=r"frames hold non-finite values \(NaN or inf\) in frame\(s\) \[1\]"):
        Recording(frames=[np.zeros(40), np.full(40, np.inf)], times=[0, 1], protocol=protocol)
    with pytest.raises(ValueError, match="images need the mesh"):
        Recording(frames=np.zeros((1, 40)), times=[0], protocol=protocol, images=np.zeros((1, 3)))
    with pytest.raises(ValueError, match="the mesh has 8 electrodes; the protocol addresses 16"):
        Recording(frames=np.zeros((1, 208)), times=[0], protocol=adjacent(16), mesh=mesh)
    with pytest.raises(ValueError, match=r"provenance keys \['user'\] are not part of the schema"):
        Recording(frames=np.zeros((1, 40)), times=[0], protocol=protocol, provenance={"user": "me"})
    recording = Recording(frames=np.zeros((1, 40)), times=[0], protocol=protocol)
    with pytest.raises(ValueError):
        recording.frames[0, 0] = 1.0  # read-only


def test_metadata_must_be_json(tmp_path):
    recording = Recording(
        frames=np.zeros((1, 40)), times=[0], protocol=adjacent(8), provenance={"metadata": {"f": object()}}
    )
    with pytest.raises(ValueError, match="JSON-serialisable"):
        write_frames(tmp_path / "f.h5", recording)
    assert not any(tmp_path.iterdir())


def test_differences_against_the_reference_or_a_frame():
    frames = np.array([[1.0, 2.0], [3.0, 6.0]])
    protocol = de.Protocol([[-1, 1, 0]], [[[0, 1, -1], [1, 0, -1]]])
    recording = Recording(frames=frames, times=[0, 1], protocol=protocol, reference=[1.0, 4.0])
    np.testing.assert_array_equal(recording.difference(), [[0.0, -2.0], [2.0, 2.0]])
    np.testing.assert_array_equal(recording.difference(relative=True), [[0.0, -0.5], [2.0, 0.5]])
    np.testing.assert_array_equal(recording.difference(reference_frame=0), [[0.0, 0.0], [2.0, 4.0]])
    with pytest.raises(ValueError, match="out of range"):
        recording.difference(reference_frame=2)
    with pytest.raises(ValueError, match="no reference frame"):
        Recording(frames=frames, times=[0, 1], protocol=protocol).difference()


# ---------------------------------------------------------------------------------------------
# EIDORS .mat files


def _driven_positions(n: int = 16) -> np.ndarray:
    """Value n * k + m of the full layout where pair (m, m+1) touches electrode k or k+1."""
    return np.array(sorted(n * k + (k + d) % n for k in range(n) for d in (-1, 0, 1)))


def test_montreal_frames_are_columns_with_zeros_on_driven_pairs():
    raw = scipy.io.loadmat(MONTREAL)
    assert raw["zc_demo3"].shape == (256, 99) and raw["zc_h_demo3"].shape == (256, 1)
    driven = _driven_positions()
    assert driven[:6].tolist() == [0, 1, 15, 16, 17, 18]
    zero_rows = np.flatnonzero(np.all(raw["zc_demo3"] == 0, axis=1))
    np.testing.assert_array_equal(zero_rows, driven)  # zeros exactly on the driven pairs, nowhere else

    recording = read_eidors_mat(MONTREAL, "zc_demo3", reference="zc_h_demo3", frame_rate=7.0)
    assert recording.frames.shape == (99, 208) and recording.reference.shape == (208,)
    measured = np.setdiff1d(np.arange(256), driven)
    np.testing.assert_array_equal(recording.frames, raw["zc_demo3"][measured].T)
    np.testing.assert_array_equal(recording.reference, raw["zc_h_demo3"][measured, 0])
    # Drive 0 reads pairs 2..14 first: the raw file's values 2, 3, 4, ...
    assert recording.frames[0, :4].tolist() == [4735.0, 6184.0, 14249.0, 7895.0]
    assert recording.reference[:3].tolist() == [4752.0, 5768.0, 14738.0]
    np.testing.assert_allclose(recording.times[:3], [0.0, 1 / 7, 2 / 7])
    assert recording.protocol.n_measurements == 208 and recording.voltage_unit == "arbitrary"
    # ADC magnitudes, never negative (the readme: "absolute value of measured signal").
    assert recording.readings == "magnitude"
    metadata = recording.provenance["metadata"]
    assert metadata["orientation"] == "columns are frames" and metadata["driven_pair_values"] == "zero"
    assert metadata["driven_readings"] == "dropped" and metadata["complex_part"] is None


def test_montreal_every_variable_and_the_driven_pair_decision():
    recordings = read_eidors_mat(MONTREAL)
    assert "ecg_breathhold" not in recordings  # 544 values: not frames
    assert {name: r.n_frames for name, r in recordings.items()} == {
        "zc_h_demo3": 1,
        "zc_demo3": 99,
        "zc_demo4": 33,
        "zc_h_demo4": 1,
        "zc_resp": 34,
        "zc_h_stomach_pre": 1,
        "zc_respsc2": 19,
        "zc_breathhold": 34,
        "zc_stomach_0_5_60min": 13,
    }
    assert {r.readings for r in recordings.values()} == {"magnitude"}
    # The stomach frames record a value on every driven pair: kept (256 readings); dropped when
    # asked, and said so; strict refuses dropping them.
    raw = scipy.io.loadmat(MONTREAL)["zc_stomach_0_5_60min"]
    stomach = recordings["zc_stomach_0_5_60min"]
    assert stomach.provenance["metadata"]["driven_pair_values"] == "non-zero"
    assert stomach.provenance["metadata"]["driven_readings"] == "kept"
    np.testing.assert_array_equal(stomach.frames, raw.T)
    assert stomach.protocol.n_measurements == 256
    dropped = read_eidors_mat(MONTREAL, "zc_stomach_0_5_60min", driven_readings="drop")
    assert dropped.provenance["metadata"]["driven_readings"] == "dropped"
    np.testing.assert_array_equal(dropped.frames, raw[np.setdiff1d(np.arange(256), _driven_positions())].T)
    with pytest.raises(ValueError, match=r"in frames \[0, 1, .* \(strict=True refuses them"):
        read_eidors_mat(MONTREAL, "zc_stomach_0_5_60min", driven_readings="drop", strict=True)
    # Against a reference with zeros on the driven pairs, the frames drop theirs too: one protocol.
    against = read_eidors_mat(MONTREAL, "zc_stomach_0_5_60min", reference="zc_h_demo3")
    assert against.protocol.n_measurements == 208 and against.reference.shape == (208,)


def test_eidors_orientations_and_208_value_frames(tmp_path):
    rng = np.random.default_rng(5)
    adjacent_frames = rng.uniform(1, 2, size=(5, 208))
    full = np.asarray(to_full_layout(adjacent_frames))
    path = tmp_path / "frames.mat"
    scipy.io.savemat(path, {"rows": full, "short": adjacent_frames.T, "one": full[0], "ref": full[:1].T})
    recordings = read_eidors_mat(path, reference="ref")
    for name, frames in (("rows", adjacent_frames), ("short", adjacent_frames), ("one", adjacent_frames[:1])):
        np.testing.assert_array_equal(recordings[name].frames, frames)
        np.testing.assert_array_equal(recordings[name].reference, adjacent_frames[0])
    assert recordings["rows"].provenance["metadata"]["orientation"] == "rows are frames"
    assert recordings["short"].provenance["metadata"]["layout"] == "adjacent, 208 values"


def test_eidors_refusals(tmp_path):
    rng = np.random.default_rng(6)
    full = np.asarray(to_full_layout(rng.uniform(1, 2, size=(3, 208))))
    rotated = np.roll(full.reshape(3, 16, 16), 5, axis=2).reshape(3, 256)  # zeros off the driven pairs
    path = tmp_path / "bad.mat"
    variables = {"rotated": rotated.T, "full": full.T, "odd": np.ones((3, 100)), "nan": np.full((256, 1), np.nan)}
    scipy.io.savemat(path, variables)
    with pytest.raises(ValueError, match="not in the 16 x 16 adjacent layout"):
        read_eidors_mat(path, "rotated")
    with pytest.raises(ValueError, match=r"'odd': has shape \(3, 100\)"):
        read_eidors_mat(path, "odd")
    with pytest.raises(ValueError, match="non-finite"):
        read_eidors_mat(path, "nan")
    with pytest.raises(ValueError, match=r"has no variable 'zc'; it has rotated \(256, 3\)"):
        read_eidors_mat(path, "zc")
    with pytest.raises(ValueError, match="holds 3 frames; a reference is one frame"):
        read_eidors_mat(path, "full", reference="full")
    with pytest.raises(ValueError, match="frame_rate must be positive"):
        read_eidors_mat(MONTREAL, "zc_demo3", frame_rate=0)
    with pytest.raises(FileNotFoundError):
        read_eidors_mat(tmp_path / "missing.mat")


def test_eidors_recording_round_trips_through_the_frames_file(tmp_path):
    recording = read_eidors_mat(MONTREAL, "zc_demo4", reference="zc_h_demo4", frame_rate=7.0)
    back = read_frames(write_frames(tmp_path / "demo4.h5", recording))
    np.testing.assert_array_equal(back.frames, recording.frames)
    np.testing.assert_array_equal(back.reference, recording.reference)
    assert back.voltage_unit == "arbitrary"
    assert back.provenance["metadata"]["variable"] == "zc_demo4"


def test_io_is_a_leaf():
    """diffeit.io uses only the data modules: the hardware module can depend on it alone."""
    import ast

    allowed = {"protocol", "mesh", "_arrays", "_messages"}
    for source in (Path(de.__file__).parent / "io").glob("*.py"):
        for node in ast.walk(ast.parse(source.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level == 2:
                assert (node.module or "").split(".")[0] in allowed, f"{source.name} imports ..{node.module}"
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                assert not node.module.startswith("diffeit"), f"{source.name} imports {node.module}"
            elif isinstance(node, ast.Import):
                assert not any(alias.name.startswith("diffeit") for alias in node.names), source.name
