"""diffeit.mesh.read: meshes from standard mesh files (gmsh, STL, OBJ, VTU through meshio), and
surface meshes in the frames file."""

import re
import time

import meshio
import numpy as np
import pytest

import diffeit as de


@pytest.fixture(scope="module")
def patch() -> de.Mesh:
    return de.mesh.cylinder_patch(0.05, 0.1, 2.0, 8, h=0.02)


@pytest.fixture(scope="module")
def voltages(patch):
    """The patch's model and its voltages at a rough conductivity."""
    sigma = np.exp(0.5 * np.random.default_rng(0).normal(size=patch.n_elements))
    model = de.ForwardModel(patch, de.protocol.adjacent(patch.n_electrodes))
    return sigma, np.asarray(model.measure(sigma))


def _same_voltages(mesh: de.Mesh, voltages) -> None:
    sigma, expected = voltages
    measured = de.ForwardModel(mesh, de.protocol.adjacent(mesh.n_electrodes)).measure(sigma)
    np.testing.assert_allclose(measured, expected, rtol=0, atol=1e-12 * np.abs(expected).max())


# (file name, meshio.write keyword arguments): formats that keep the node numbering.
NUMBERED = [
    ("patch.vtu", {}),
    ("patch22.msh", {"file_format": "gmsh22", "binary": False}),
    ("patch41.msh", {"file_format": "gmsh", "binary": False}),
    ("patch41-binary.msh", {"file_format": "gmsh", "binary": True}),
    ("patch.obj", {}),
]


@pytest.mark.parametrize(("name", "options"), NUMBERED, ids=[name for name, _ in NUMBERED])
def test_formats_that_keep_the_numbering_read_back_the_same_mesh(tmp_path, patch, voltages, name, options):
    path = tmp_path / name
    meshio.write_points_cells(path, patch.nodes, [("triangle", patch.triangles)], **options)
    mesh = de.mesh.read(path, electrodes=patch.electrodes)
    assert mesh.nodes.shape == (patch.n_nodes, 3)
    np.testing.assert_array_equal(mesh.nodes, patch.nodes)
    np.testing.assert_array_equal(mesh.triangles, patch.triangles)
    assert mesh == patch
    _same_voltages(mesh, voltages)


def _by_coordinates(original: de.Mesh, nodes_as=np.float64):
    """An electrode finder: the original's electrodes, looked up by their nodes' coordinates
    (rounded to `nodes_as`, as the file stores them)."""
    original_nodes = original.nodes.astype(nodes_as)

    def find(nodes, boundary_edges):
        assert boundary_edges.shape[1] == 2 and np.isin(boundary_edges, np.arange(len(nodes))).all()
        keys = {tuple(point): index for index, point in enumerate(nodes.tolist())}
        return [
            np.array([keys[tuple(original_nodes[node].tolist())] for node in chain]) for chain in original.electrodes
        ]

    return find


@pytest.mark.parametrize("binary", [False, True], ids=["ascii", "binary"])
def test_stl_facets_are_merged_into_one_surface(tmp_path, patch, voltages, binary):
    path = tmp_path / "patch.stl"
    meshio.write_points_cells(path, patch.nodes, [("triangle", patch.triangles)], binary=binary)
    mesh = de.mesh.read(path, electrodes=_by_coordinates(patch, np.float32 if binary else np.float64))
    assert (mesh.n_nodes, mesh.n_elements, mesh.n_electrodes) == (patch.n_nodes, patch.n_elements, patch.n_electrodes)
    # The same triangles, up to the numbering of the merged vertices.
    expected = patch.nodes.astype(np.float32) if binary else patch.nodes
    order = np.lexsort(mesh.nodes.T)
    np.testing.assert_array_equal(mesh.nodes[order], expected[np.lexsort(expected.T)])
    renumber = np.empty(mesh.n_nodes, dtype=np.int64)
    renumber[order] = np.lexsort(expected.T)  # mesh node -> original node
    assert sorted(map(tuple, np.sort(renumber[mesh.triangles], axis=1))) == sorted(
        map(tuple, np.sort(patch.triangles, axis=1))
    )
    if binary:
        # STL stores float32: the geometry moves by 1e-7 relative, and the voltages with it.
        sigma, expected_voltages = voltages
        measured = de.ForwardModel(mesh, de.protocol.adjacent(8)).measure(sigma)
        np.testing.assert_allclose(measured, expected_voltages, rtol=0, atol=1e-5 * np.abs(expected_voltages).max())
    else:
        _same_voltages(mesh, voltages)


def test_the_finder_gets_the_boundary_edges_the_mesh_will_have(tmp_path, patch):
    seen = {}

    def find(nodes, boundary_edges):
        seen["nodes"], seen["edges"] = nodes, boundary_edges
        return _by_coordinates(patch)(nodes, boundary_edges)

    path = tmp_path / "patch.stl"
    meshio.write_points_cells(path, patch.nodes, [("triangle", patch.triangles)])
    mesh = de.mesh.read(path, electrodes=find)
    np.testing.assert_array_equal(seen["nodes"], mesh.nodes)
    np.testing.assert_array_equal(seen["edges"], mesh.boundary_edges)


def test_a_flat_mesh_written_with_z_zero_reads_back_flat(tmp_path):
    disc = de.mesh.disc(8, 0.2, 0.3)
    path = tmp_path / "disc.vtu"
    meshio.write_points_cells(
        path, np.column_stack([disc.nodes, np.zeros(disc.n_nodes)]), [("triangle", disc.triangles)]
    )
    mesh = de.mesh.read(path, electrodes=disc.electrodes)
    assert mesh.nodes.shape == (disc.n_nodes, 2)
    assert mesh == disc


def test_unused_nodes_and_other_cells_are_dropped_and_the_electrodes_renumbered(tmp_path, patch, voltages):
    # Two stray nodes in front and one in the middle, boundary lines and a vertex cell beside the triangles.
    stray = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    middle = patch.n_nodes // 2
    nodes = np.concatenate([stray, patch.nodes[:middle], [[7.0, 8.0, 9.0]], patch.nodes[middle:]])
    to_file = np.arange(patch.n_nodes) + 2 + (np.arange(patch.n_nodes) >= middle)
    cells = [
        ("vertex", np.array([[0]])),
        ("line", to_file[patch.boundary_edges]),
        ("triangle", to_file[patch.triangles]),
    ]
    path = tmp_path / "stray.msh"
    meshio.write_points_cells(path, nodes, cells, file_format="gmsh22", binary=False)
    mesh = de.mesh.read(path, electrodes=[to_file[chain] for chain in patch.electrodes])
    assert mesh == patch
    _same_voltages(mesh, voltages)
    with pytest.raises(ValueError, match=r"stray\.msh: electrode 1: nodes \[0\] belong to no triangle"):
        de.mesh.read(path, electrodes=[to_file[patch.electrodes[0]], [0, *to_file[patch.electrodes[1]]]])
    with pytest.raises(ValueError, match=r"stray\.msh: electrode 0: nodes \[999\] are outside the file's"):
        de.mesh.read(path, electrodes=[[999, 3]])


def test_a_surface_mesh_survives_the_frames_file(tmp_path):
    cap = de.mesh.sphere_cap(0.02, 1.2, 8, h=0.006)
    protocol = de.protocol.adjacent(8)
    frames = np.random.default_rng(1).normal(size=(3, protocol.n_measurements))
    recording = de.io.Recording(frames=frames, times=[0.0, 0.1, 0.2], protocol=protocol, mesh=cap)
    back = de.io.read_frames(de.io.write_frames(tmp_path / "cap.h5", recording))
    assert back.mesh.nodes.shape == (cap.n_nodes, 3)
    assert back.mesh == cap
    np.testing.assert_array_equal(back.mesh.nodes, cap.nodes)
    np.testing.assert_array_equal(back.frames, frames)


def _truncated_vtu(path, patch):
    meshio.write_points_cells(path, patch.nodes, [("triangle", patch.triangles)])
    content = path.read_bytes()
    path.write_bytes(content[: len(content) // 2])


BAD = {
    "not a mesh": ("notes.msh", lambda path, patch: path.write_text("shopping list\n- milk\n- eggs\n")),
    "not a mesh, as VTU": ("notes.vtu", lambda path, patch: path.write_text("shopping list\n- milk\n")),
    "unknown extension": ("notes.txt", lambda path, patch: path.write_text("shopping list\n")),
    "truncated VTU": ("cut.vtu", _truncated_vtu),
    "only lines": (
        "lines.vtu",
        lambda path, patch: meshio.write_points_cells(path, patch.nodes, [("line", patch.boundary_edges)]),
    ),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_files_are_refused_naming_the_file(tmp_path, patch, case):
    name, make = BAD[case]
    path = tmp_path / name
    make(path, patch)
    start = time.perf_counter()
    with pytest.raises(ValueError, match=re.escape(str(path))) as raised:
        de.mesh.read(path, electrodes=patch.electrodes)
    assert time.perf_counter() - start < 2.0
    if case == "only lines":
        assert "no triangle cells" in str(raised.value) and f"line x {len(patch.boundary_edges)}" in str(raised.value)


def test_a_missing_file_is_not_found(tmp_path, patch):
    with pytest.raises(FileNotFoundError, match=r"missing\.vtu"):
        de.mesh.read(tmp_path / "missing.vtu", electrodes=patch.electrodes)


def test_an_unusable_mesh_is_refused_naming_the_file(tmp_path, patch):
    # Electrodes off the boundary: the Mesh's refusal, with the file's name in front.
    path = tmp_path / "patch.vtu"
    meshio.write_points_cells(path, patch.nodes, [("triangle", patch.triangles)])
    interior = np.setdiff1d(np.arange(patch.n_nodes), patch.boundary_edges)[:2]
    with pytest.raises(ValueError, match=r"patch\.vtu: electrode 0: nodes .* are not on the boundary"):
        de.mesh.read(path, electrodes=[interior])
