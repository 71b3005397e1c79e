"""Polygon and rectangle skins: geometry, electrode placement, refusals, exchange with scikit-fem."""

import numpy as np
import pytest
import skfem
from skfem.helpers import dot, grad

import diffeit as de
from diffeit.assembly import CompleteElectrodeSystem

L_SHAPE = np.array([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], dtype=float)  # perimeter 8, area 3
HEXAGON = np.stack([np.cos(np.pi / 3 * np.arange(6)), np.sin(np.pi / 3 * np.arange(6))], axis=1)


def _shoelace(vertices: np.ndarray) -> float:
    following = np.roll(vertices, -1, axis=0)
    return 0.5 * float(np.sum(vertices[:, 0] * following[:, 1] - following[:, 0] * vertices[:, 1]))


def _arc_length(points: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Arc length of boundary points counter-clockwise from corner 0 of a counter-clockwise
    polygon; asserts each point lies on an edge."""
    starts, stops = corners, np.roll(corners, -1, axis=0)
    lengths = np.linalg.norm(stops - starts, axis=1)
    offsets = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
    arcs = []
    for point in points:
        along = np.sum((point - starts) * (stops - starts), axis=1) / lengths
        edge, offset = stops - starts, point - starts
        across = np.abs(edge[:, 0] * offset[:, 1] - edge[:, 1] * offset[:, 0]) / lengths
        on_edge = np.flatnonzero((across < 1e-12) & (along >= -1e-12) & (along <= lengths + 1e-12))
        assert len(on_edge), f"{point} is not on the boundary"
        arcs.append(offsets[on_edge[0]] + along[on_edge[0]])
    return np.array(arcs)


def _electrode_arcs(mesh: de.Mesh, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(L,) arc lengths of the electrode starts and (L,) electrode lengths along their chains."""
    starts = _arc_length(np.array([mesh.nodes[chain[0]] for chain in mesh.electrodes]), corners)
    lengths = np.array([np.linalg.norm(np.diff(mesh.nodes[chain], axis=0), axis=1).sum() for chain in mesh.electrodes])
    return starts, lengths


def _check_boundary_on_polygon(mesh: de.Mesh, corners: np.ndarray) -> None:
    boundary = np.unique(mesh.boundary_edges)
    _arc_length(mesh.nodes[boundary], corners)  # asserts
    for corner in corners:  # every corner is a mesh vertex
        assert np.min(np.linalg.norm(mesh.nodes - corner, axis=1)) == 0.0


def test_square_gets_four_symmetric_electrodes_per_side():
    mesh = de.mesh.rectangle()  # 1 m x 1 m, 16 electrodes of width 1/8, vertex 0 bottom left
    corners = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]])
    assert mesh.n_electrodes == 16
    np.testing.assert_allclose(mesh.element_areas.sum(), 1.0, rtol=1e-12)
    _check_boundary_on_polygon(mesh, corners)
    starts, lengths = _electrode_arcs(mesh, corners)
    np.testing.assert_allclose(lengths, 0.125, rtol=1e-12)
    np.testing.assert_allclose(starts + 0.0625, 0.125 + 0.25 * np.arange(16), atol=1e-12)
    centres = np.array([mesh.nodes[chain[[0, -1]]].mean(axis=0) for chain in mesh.electrodes])
    np.testing.assert_allclose(centres[:4], np.column_stack([[-0.375, -0.125, 0.125, 0.375], np.full(4, -0.5)]))
    # Each side is the previous one turned by 90 degrees about the centre.
    turned = centres[:4] @ np.array([[0.0, 1.0], [-1.0, 0.0]])
    for side in range(1, 4):
        np.testing.assert_allclose(centres[4 * side : 4 * side + 4], turned, atol=1e-15)
        turned = turned @ np.array([[0.0, 1.0], [-1.0, 0.0]])


def test_rectangle_at_requested_centres_and_sizes():
    centres = np.array([0.3, 1.0, 1.75, 2.5, 3.2, 4.0, 5.1, 5.7])  # perimeter 6
    mesh = de.mesh.rectangle(2.0, 1.0, 8, electrode_width=0.2, h=0.2, electrode_centres=centres, electrode_h=0.04)
    corners = np.array([[-1.0, -0.5], [1.0, -0.5], [1.0, 0.5], [-1.0, 0.5]])
    np.testing.assert_allclose(mesh.element_areas.sum(), 2.0, rtol=1e-12)
    _check_boundary_on_polygon(mesh, corners)
    starts, lengths = _electrode_arcs(mesh, corners)
    np.testing.assert_allclose(lengths, 0.2, rtol=1e-12)
    np.testing.assert_allclose(starts + 0.1, centres, atol=1e-12)
    assert all(len(chain) >= 6 for chain in mesh.electrodes)  # 0.2 m at 0.04 m spacing
    # Elements grow away from the electrodes up to h.
    near = mesh.element_areas[np.min(np.abs(np.abs(mesh.element_centroids) - [1.0, 0.5]), axis=1) < 0.05]
    assert near.mean() < 0.25 * mesh.element_areas.max()


def test_l_shape_with_electrodes_around_its_corners():
    # Centres every 0.5 m from vertex 0: six electrodes sit on corners, the reflex one included,
    # and electrode 0 wraps around vertex 0.
    mesh = de.mesh.polygon(L_SHAPE, 16, electrode_width=0.2, h=0.2, electrode_centres=0.5 * np.arange(16))
    np.testing.assert_allclose(mesh.element_areas.sum(), 3.0, rtol=1e-12)
    _check_boundary_on_polygon(mesh, L_SHAPE)
    starts, lengths = _electrode_arcs(mesh, L_SHAPE)
    np.testing.assert_allclose(lengths, 0.2, rtol=1e-12)
    np.testing.assert_allclose(np.mod(starts + 0.1, 8.0), 0.5 * np.arange(16), atol=1e-12)
    corner_arcs = {0: 0.0, 4: 2.0, 6: 3.0, 8: 4.0, 10: 5.0, 12: 6.0}
    for k, chain in enumerate(mesh.electrodes):
        has_corner = [np.any(np.all(mesh.nodes[chain] == corner, axis=1)) for corner in L_SHAPE]
        assert sum(has_corner) == (1 if k in corner_arcs else 0)
    np.testing.assert_array_equal(mesh.nodes[mesh.electrodes[0][1]], [0.0, 0.0])  # vertex 0, mid-electrode
    np.testing.assert_array_equal(mesh.nodes[mesh.electrodes[8][1]], [1.0, 1.0])  # the reflex corner


def test_clockwise_vertices_are_reversed_about_vertex_zero():
    counter = de.mesh.polygon(HEXAGON, 12, h=0.15)
    clockwise = de.mesh.polygon(HEXAGON[[0, 5, 4, 3, 2, 1]], 12, h=0.15)
    np.testing.assert_array_equal(clockwise.nodes, counter.nodes)
    np.testing.assert_array_equal(clockwise.triangles, counter.triangles)
    for a, b in zip(counter.electrodes, clockwise.electrodes, strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(counter.element_areas.sum(), _shoelace(HEXAGON), rtol=1e-12)
    # Electrode 0 is the first counter-clockwise from vertex 0; the default width is half the
    # spacing, the centres half a spacing after vertex 0.
    starts, lengths = _electrode_arcs(counter, HEXAGON)
    np.testing.assert_allclose(lengths, 0.25, rtol=1e-12)
    np.testing.assert_allclose(starts + 0.125, 0.25 + 0.5 * np.arange(12), atol=1e-12)
    assert np.all(np.diff(starts) > 0)


def test_arbitrary_polygon_electrode_count_and_default_sizes():
    rng = np.random.default_rng(3)
    angles = np.sort(rng.uniform(0, 2 * np.pi, 9))
    star = (1.0 + 0.4 * rng.uniform(-1, 1, 9))[:, None] * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    mesh = de.mesh.polygon(star, 10)
    np.testing.assert_allclose(mesh.element_areas.sum(), _shoelace(star), rtol=1e-12)
    _check_boundary_on_polygon(mesh, star)
    perimeter = np.linalg.norm(np.roll(star, -1, axis=0) - star, axis=1).sum()
    starts, lengths = _electrode_arcs(mesh, star)
    np.testing.assert_allclose(lengths, perimeter / 20, rtol=1e-12)
    np.testing.assert_allclose(starts + perimeter / 40, perimeter * (np.arange(10) + 0.5) / 10, atol=1e-12)


def test_element_count_follows_h():
    meshes = [de.mesh.rectangle(h=h, electrode_h=h) for h in (0.1, 0.05, 0.025)]
    counts = np.array([mesh.n_elements for mesh in meshes])
    assert np.all((counts[1:] / counts[:-1] > 3.0) & (counts[1:] / counts[:-1] < 5.0)), counts
    for h, mesh in zip((0.1, 0.05, 0.025), meshes, strict=True):
        corners = mesh.nodes[mesh.triangles]
        edges = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2)
        assert 0.7 * h < edges.mean() < 1.3 * h


def test_an_end_next_to_a_corner_snaps_onto_it():
    mesh = de.mesh.rectangle(electrode_centres=[0.0625 + 1e-12, 1.5, 2.5, 3.5], n_electrodes=4, electrode_width=0.125)
    np.testing.assert_array_equal(mesh.nodes[mesh.electrodes[0][0]], [-0.5, -0.5])
    assert np.min(np.linalg.norm(np.diff(mesh.nodes[np.unique(mesh.boundary_edges)], axis=0), axis=1)) > 1e-3


@pytest.mark.parametrize(
    ("vertices", "kwargs", "message"),
    [
        ([[0, 0], [1, 0]], {}, "at least 3 vertices; got 2"),
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], {}, r"shape \(n, 2\)"),
        ([[0, 0], [1, np.nan], [0, 1]], {}, r"vertices \[1\] are not finite"),
        ([[0, 0], [1, 0], [1, 1], [0, 1], [0, 0]], {}, "vertices 0 and 4 repeat the same point.*closing vertex"),
        ([[0, 0], [1, 0], [1, 1], [1, 0], [0, 1]], {}, "vertices 1 and 3 repeat"),
        ([[0, 0], [1, 1], [1, 0], [0, 1]], {}, r"intersects itself: edge 0 \(vertices 0-1\) and edge 2"),
        ([[0, 0], [2, 0], [1, 0], [1, 1]], {}, "intersects itself: edge 0 .* and edge 1"),
        ([[0, 0], [2, 0], [2, 2], [1, 0.0], [0, 2]], {}, "intersects itself"),  # a vertex on another edge
        (L_SHAPE, {"electrode_width": 0.6}, "16 electrodes of width 0.6 do not fit"),
        (L_SHAPE, {"h": -0.1}, "must be positive"),
        (L_SHAPE, {"electrode_width": 0.0}, "must be positive"),
        (L_SHAPE, {"h": 0.1, "electrode_h": 0.2}, r"electrode_h must lie in \(0, h\]"),
        (L_SHAPE, {"n_electrodes": 1}, "at least 2 electrodes"),
        (L_SHAPE, {"electrode_centres": [1.0, 2.0, 3.0]}, r"one arc length per electrode, shape \(16,\)"),
        (L_SHAPE, {"n_electrodes": 3, "electrode_centres": [1.0, 3.0, 2.0]}, "increase strictly"),
        (L_SHAPE, {"n_electrodes": 3, "electrode_centres": [1.0, 3.0, 8.0]}, r"must lie in \[0, 8\)"),
        (
            L_SHAPE,
            {"n_electrodes": 3, "electrode_width": 0.5, "electrode_centres": [1.0, 1.4, 5.0]},
            "electrodes 0 and 1 overlap",
        ),
        (
            L_SHAPE,
            {"n_electrodes": 3, "electrode_width": 0.5, "electrode_centres": [0.1, 4.0, 7.7]},
            "electrodes 2 and 0 overlap",  # across vertex 0
        ),
    ],
)
def test_polygon_refuses_bad_inputs_naming_the_problem(vertices, kwargs, message):
    with pytest.raises(ValueError, match=message):
        de.mesh.polygon(vertices, **kwargs)


def test_rectangle_refuses_non_positive_sides():
    with pytest.raises(ValueError, match="width and height must be positive"):
        de.mesh.rectangle(0.0, 1.0)
    with pytest.raises(ValueError, match="do not fit"):
        de.mesh.rectangle(0.1, 0.1, electrode_width=0.05)


@pytest.mark.parametrize(
    "mesh",
    [
        de.mesh.rectangle(2.0, 1.0, 16, electrode_width=0.15, h=0.15),
        de.mesh.polygon(L_SHAPE, 16, electrode_width=0.2, h=0.2, electrode_centres=0.5 * np.arange(16)),
    ],
    ids=["rectangle", "l_shape"],
)
def test_to_skfem_assembles_the_same_stiffness_as_diffeit(mesh):
    skmesh = mesh.to_skfem()
    assert isinstance(skmesh, skfem.MeshTri)
    np.testing.assert_array_equal(skmesh.p, mesh.nodes.T)
    np.testing.assert_array_equal(skmesh.t, mesh.triangles.T)
    sigma = np.exp(np.random.default_rng(5).normal(0.0, 0.5, mesh.n_elements))

    @skfem.BilinearForm
    def laplace(u, v, w):
        return w.sigma * dot(grad(u), grad(v))

    basis = skfem.Basis(skmesh, skfem.ElementTriP1())
    reference = skfem.asm(laplace, basis, sigma=basis.with_element(skfem.ElementTriP0()).interpolate(sigma))

    system = CompleteElectrodeSystem.from_mesh(mesh)
    rows, cols = np.repeat(mesh.triangles, 3, axis=1).ravel(), np.tile(mesh.triangles, 3).ravel()
    values = (sigma[:, None] * system.unit_stiffness).ravel()
    ours = np.zeros((mesh.n_nodes, mesh.n_nodes))
    np.add.at(ours, (rows, cols), values)
    np.testing.assert_allclose(ours, reference.toarray(), atol=1e-12 * np.abs(ours).max())
    u = np.random.default_rng(6).normal(size=mesh.n_nodes)
    np.testing.assert_allclose(u @ ours @ u, u @ reference @ u, rtol=1e-12)


def test_skfem_round_trip_keeps_electrodes_as_named_boundaries():
    mesh = de.mesh.polygon(HEXAGON, 12, h=0.2)
    skmesh = mesh.to_skfem()
    assert sorted(skmesh.boundaries) == sorted(f"electrode_{k}" for k in range(12))

    @skfem.Functional
    def length(w):
        return 1.0 + 0.0 * w.x[0]

    for k in range(12):
        facet_basis = skfem.FacetBasis(skmesh, skfem.ElementTriP1(), facets=f"electrode_{k}")
        np.testing.assert_allclose(length.assemble(facet_basis), 0.25, rtol=1e-12)
    back = de.Mesh.from_skfem(skmesh)
    np.testing.assert_array_equal(back.nodes, mesh.nodes)
    np.testing.assert_array_equal(back.triangles, mesh.triangles)
    for a, b in zip(back.electrodes, mesh.electrodes, strict=True):
        np.testing.assert_array_equal(a, b)


def test_from_skfem_with_explicit_electrodes_and_refusals():
    skmesh = skfem.MeshTri().refined(2)  # unit square, mixed orientations after sorting
    bottom = np.flatnonzero(np.isclose(skmesh.p[1], 0.0) & (skmesh.p[0] < 0.6))
    top = np.flatnonzero(np.isclose(skmesh.p[1], 1.0) & (skmesh.p[0] > 0.4))
    mesh = de.Mesh.from_skfem(skmesh, [bottom, top])
    assert mesh.n_electrodes == 2
    np.testing.assert_allclose(mesh.element_areas.sum(), 1.0, rtol=1e-12)
    with pytest.raises(ValueError, match="no boundaries named electrode_0"):
        de.Mesh.from_skfem(skmesh)
    with pytest.raises(ValueError, match="2D triangle mesh"):
        de.Mesh.from_skfem(skfem.MeshQuad(), [[0, 1]])
