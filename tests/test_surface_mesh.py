"""Skins on curved surfaces: meshes with (N, 3) nodes carry the same 2D complete electrode
model on a surface in space."""

import jax
import numpy as np
import pytest

import diffeit as de
from diffeit.assembly import CompleteElectrodeSystem, basis_gradients


def _relative(a, b) -> float:
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / np.linalg.norm(np.asarray(b)))


def _rotation(seed: int) -> np.ndarray:
    """A random 3 x 3 rotation matrix (determinant +1)."""
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _in_3d(nodes: np.ndarray) -> np.ndarray:
    return np.column_stack([nodes, np.zeros(len(nodes))])


def _rough_conductivity(n_elements: int, seed: int = 0) -> np.ndarray:
    return np.exp(0.5 * np.random.default_rng(seed).normal(size=n_elements))


def _assert_same_physics(flat: de.Mesh, surface: de.Mesh, tolerance: float = 1e-12) -> None:
    """Voltages, the fast Jacobians and jacrev of the surface's model equal the flat one's."""
    protocol = de.protocol.adjacent(flat.n_electrodes)
    flat_model, surface_model = de.ForwardModel(flat, protocol), de.ForwardModel(surface, protocol)
    sigma = _rough_conductivity(flat.n_elements)
    assert _relative(surface_model.measure(sigma), flat_model.measure(sigma)) < tolerance
    expected = flat_model.jacobian(sigma)
    assert _relative(surface_model.jacobian(sigma), expected) < tolerance
    assert _relative(jax.jacrev(surface_model.measure)(sigma), expected) < tolerance
    log_jacobian = surface_model.jacobian(sigma, wrt="log_conductivity")
    assert _relative(log_jacobian, flat_model.jacobian(sigma, wrt="log_conductivity")) < tolerance
    # Looser: even on one flat mesh, the fast path and jacrev agree in z to only about 3e-13.
    z_jacobian = surface_model.jacobian(sigma, wrt="contact_impedance")
    assert _relative(z_jacobian, flat_model.jacobian(sigma, wrt="contact_impedance")) < 10 * tolerance
    # Point electrodes, and electrodes moved along the boundary (by arc length, which the
    # surface keeps), see the same sheet.
    for options in ({"electrode_model": "point"}, {"electrode_shift": np.linspace(-0.04, 0.04, flat.n_electrodes)}):
        expected = de.ForwardModel(flat, protocol, **options).measure(sigma)
        assert _relative(de.ForwardModel(surface, protocol, **options).measure(sigma), expected) < tolerance


def test_a_flat_mesh_given_in_3d_is_the_same_mesh_whatever_its_rotation_and_triangle_order():
    flat = de.mesh.rectangle(1.0, 0.6, 8, h=0.2)
    rng = np.random.default_rng(1)
    triangles = flat.triangles.copy()
    flips = rng.random(len(triangles)) < 0.5
    flips[0] = False  # the first triangle sets the orientation
    triangles[flips] = triangles[flips][:, [0, 2, 1]]
    rotation = _rotation(2)
    surface = de.Mesh(_in_3d(flat.nodes) @ rotation.T, triangles, flat.electrodes)

    assert surface.nodes.shape == (flat.n_nodes, 3)
    np.testing.assert_array_equal(surface.triangles, flat.triangles)
    np.testing.assert_array_equal(surface.boundary_edges, flat.boundary_edges)
    for chain, expected in zip(surface.electrodes, flat.electrodes, strict=True):
        np.testing.assert_array_equal(chain, expected)
    np.testing.assert_allclose(surface.element_areas, flat.element_areas, rtol=1e-13)
    # The gradients within each triangle's plane are the flat ones, rotated.
    gradients = np.concatenate([basis_gradients(flat), np.zeros((flat.n_elements, 1, 3))], axis=1)
    np.testing.assert_allclose(
        basis_gradients(surface), np.einsum("yx,exk->eyk", rotation, gradients), atol=1e-12 * np.abs(gradients).max()
    )
    _assert_same_physics(flat, surface)


def test_basis_gradients_in_the_z_plane_are_the_2d_ones_with_a_zero_z_component():
    flat = de.mesh.rectangle(1.0, 0.6, 6, h=0.3)
    surface = de.Mesh(_in_3d(flat.nodes), flat.triangles, flat.electrodes)
    gradients = basis_gradients(surface)
    np.testing.assert_allclose(gradients[:, :2], basis_gradients(flat), rtol=1e-14, atol=1e-14)
    np.testing.assert_array_equal(gradients[:, 2], 0.0)
    # Each basis function's gradient is orthogonal to the opposite edge and sums to zero.
    np.testing.assert_allclose(gradients.sum(axis=2), 0.0, atol=1e-12)


def _grid_sheet(nx: int = 9, ny: int = 5, width: float = 2.0, height: float = 1.0):
    """A structured flat sheet: nodes (nx ny, 2) on a grid, two triangles per cell, and
    eight electrodes of one boundary edge each, every third edge round the boundary."""
    x, y = np.linspace(-width / 2, width / 2, nx), np.linspace(-height / 2, height / 2, ny)
    nodes = np.stack(np.meshgrid(x, y, indexing="ij"), axis=-1).reshape(-1, 2)
    index = np.arange(nx * ny).reshape(nx, ny)
    a, b, c, d = index[:-1, :-1], index[1:, :-1], index[1:, 1:], index[:-1, 1:]
    triangles = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    loop = np.concatenate([index[:, 0], index[-1, 1:], index[-2::-1, -1], index[0, -2:0:-1]])
    electrodes = [loop[k : k + 2] for k in range(0, len(loop), 3)]
    return nodes, triangles, electrodes


def _folded(nodes: np.ndarray, fold_lines: list[float], turns: list[float]) -> np.ndarray:
    """(N, 3) the flat sheet bent along the lines x = fold_lines by the angles `turns`
    (radians): x follows a polyline of unit speed in the x-z plane, so lengths are kept."""
    x = nodes[:, 0]
    breaks = np.concatenate([[x.min()], fold_lines, [x.max()]])
    headings = np.concatenate([[0.0], np.cumsum(turns)])
    travelled = np.clip(x[:, None] - breaks[None, :-1], 0.0, np.diff(breaks)[None])  # (N, pieces)
    return np.column_stack([breaks[0] + travelled @ np.cos(headings), nodes[:, 1], travelled @ np.sin(headings)])


def test_a_sheet_folded_along_mesh_edges_has_the_flat_sheets_voltages_and_jacobian():
    nodes, triangles, electrodes = _grid_sheet()
    flat = de.Mesh(nodes, triangles, electrodes)
    bent = _folded(nodes, fold_lines=[-0.5, 0.25], turns=[1.0, -2.0])
    assert np.ptp(bent[:, 2]) > 0.3  # the first piece lies in z = 0, the others leave it
    folded = de.Mesh(bent @ _rotation(3).T, triangles, electrodes)
    np.testing.assert_allclose(folded.element_areas, flat.element_areas, rtol=1e-13)
    _assert_same_physics(flat, folded)


def test_distances_along_a_folded_sheet_and_its_smoothness_prior_are_the_flat_sheets():
    """The Matern prior's distances between neighbouring centroids are taken along the sheet
    (across the shared edge, unfolded): a sheet folded along mesh edges keeps them, and its
    one-step image equals the flat sheet's. The straight chords through the folds are shorter."""
    nodes, triangles, electrodes = _grid_sheet()
    flat = de.Mesh(nodes, triangles, electrodes)
    folded = de.Mesh(_folded(nodes, fold_lines=[-0.5, 0.25], turns=[1.0, -2.0]) @ _rotation(3).T, triangles, electrodes)
    first, second, _ = de.mesh.element_adjacency(flat)
    chords = np.linalg.norm(flat.element_centroids[first] - flat.element_centroids[second], axis=1)
    np.testing.assert_allclose(de.mesh.centroid_distances(flat), chords, rtol=1e-14)
    np.testing.assert_allclose(de.mesh.centroid_distances(folded), chords, rtol=1e-13)
    through = np.linalg.norm(folded.element_centroids[first] - folded.element_centroids[second], axis=1)
    assert np.max(1 - through / chords) > 0.05  # pairs across a fold
    protocol = de.protocol.adjacent(flat.n_electrodes)
    sigma = _rough_conductivity(flat.n_elements)
    difference = de.ForwardModel(flat, protocol).measure(sigma * 1.1) - de.ForwardModel(flat, protocol).measure(sigma)
    images = [
        np.asarray(
            de.inverse.OneStep(de.ForwardModel(mesh, protocol), de.inverse.Matern(0.5), 1e-2, background=sigma)
            .solve(difference)
            .value
        )
        for mesh in (flat, folded)
    ]
    assert _relative(images[1], images[0]) < 1e-10


def test_centroid_distances_on_a_dome_exceed_the_chords_by_the_bend():
    """On a sphere cap each unfolded distance is at least the chord, and longer by about the
    angle between the two triangles' planes squared, over 8, of it (d theta^2 / 8 for a path
    bent by theta in the middle)."""
    dome = de.mesh.sphere_cap(1.0, 1.0, 8, 0.15)
    first, second, _ = de.mesh.element_adjacency(dome)
    chords = np.linalg.norm(dome.element_centroids[first] - dome.element_centroids[second], axis=1)
    along = de.mesh.centroid_distances(dome)
    corners = dome.nodes[dome.triangles]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    bend = np.arccos(np.clip(np.sum(normals[first] * normals[second], axis=1), -1, 1))
    assert np.all(along >= chords * (1 - 1e-14)) and np.max(along / chords - 1) > 1e-4
    np.testing.assert_allclose(along / chords - 1, bend**2 / 8, rtol=0.6, atol=1e-6)


def test_a_cylinder_patch_converges_to_the_flat_rectangle_it_unrolls_to():
    # Same parameter mesh, rolled and flat: the difference is the chords' error alone, second order.
    radius, length, angle, n_electrodes = 0.5, 1.0, 2.0, 8
    protocol = de.protocol.adjacent(n_electrodes)
    errors = []
    for h in (0.2, 0.1, 0.05):
        patch = de.mesh.cylinder_patch(radius, length, angle, n_electrodes, h)
        flat = de.mesh.rectangle(radius * angle, length, n_electrodes, h=h)
        np.testing.assert_array_equal(patch.triangles, flat.triangles)
        np.testing.assert_allclose(np.hypot(patch.nodes[:, 0], patch.nodes[:, 1]), radius, rtol=1e-14)
        assert np.all(np.abs(np.arctan2(patch.nodes[:, 1], patch.nodes[:, 0])) <= angle / 2 + 1e-12)
        corners = patch.nodes[patch.triangles]
        normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        assert np.all(np.sum(normals[:, :2] * corners.mean(axis=1)[:, :2], axis=1) > 0)  # away from the axis
        width = 2 * (radius * angle + length) / (2 * n_electrodes)  # half the spacing
        lengths = CompleteElectrodeSystem.from_mesh(patch).electrode_lengths
        assert np.all((lengths <= width * (1 + 1e-12)) & (lengths >= width * (1 - (h / 2 / radius) ** 2 / 24)))
        voltages = de.ForwardModel(patch, protocol).measure(np.ones(patch.n_elements))
        expected = de.ForwardModel(flat, protocol).measure(np.ones(flat.n_elements))
        errors.append(_relative(voltages, expected))
    print("cylinder patch vs unrolled rectangle, h = 0.2, 0.1, 0.05: relative voltage errors", errors)
    assert errors[0] < 0.02
    assert errors[0] / errors[1] > 3 and errors[1] / errors[2] > 3, errors


def test_on_a_curved_surface_the_fast_jacobian_equals_jacrev():
    cap = de.mesh.sphere_cap(1.0, 1.2, 8, h=0.3)
    model = de.ForwardModel(cap, de.protocol.adjacent(8))
    sigma = _rough_conductivity(cap.n_elements)
    assert _relative(model.jacobian(sigma), jax.jacrev(model.measure)(sigma)) < 1e-12


def test_a_sphere_cap_lies_on_the_sphere_with_electrodes_of_the_asked_width():
    radius, polar_angle, n_electrodes, width = 0.01, 1.2, 6, 0.004
    cap = de.mesh.sphere_cap(radius, polar_angle, n_electrodes, h=0.002, electrode_width=width)
    np.testing.assert_allclose(np.linalg.norm(cap.nodes, axis=1), radius, rtol=1e-14)
    polar = np.arccos(np.clip(cap.nodes[:, 2] / radius, -1, 1))
    assert polar.max() <= polar_angle + 1e-12
    np.testing.assert_allclose(polar[np.unique(cap.boundary_edges)], polar_angle, rtol=1e-12)
    cap_area = 2 * np.pi * radius**2 * (1 - np.cos(polar_angle))
    assert 0.97 * cap_area < cap.element_areas.sum() < cap_area
    # Normals point away from the centre; electrodes go counter-clockwise seen from +z.
    corners = cap.nodes[cap.triangles]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    assert np.all(np.sum(normals * corners.mean(axis=1), axis=1) > 0)
    centres = np.array([cap.nodes[chain].mean(axis=0) for chain in cap.electrodes])
    offsets = np.arctan2(centres[:, 1], centres[:, 0]) - 2 * np.pi * np.arange(n_electrodes) / n_electrodes
    np.testing.assert_allclose(np.angle(np.exp(1j * offsets)), 0.0, atol=1e-9)
    lengths = CompleteElectrodeSystem.from_mesh(cap).electrode_lengths
    assert np.all((lengths <= width) & (lengths > 0.995 * width)), lengths


def test_sphere_cap_voltages_converge_under_refinement():
    protocol = de.protocol.adjacent(8)
    voltages = []
    for h in (0.4, 0.2, 0.1):
        cap = de.mesh.sphere_cap(1.0, 1.0, 8, h)
        voltages.append(de.ForwardModel(cap, protocol).measure(np.ones(cap.n_elements)))
    errors = [_relative(v, voltages[-1]) for v in voltages[:-1]]
    print("sphere cap, h = 0.4, 0.2 against h = 0.1: relative voltage errors", errors)
    assert errors[1] < errors[0] / 2.5 and errors[1] < 0.02, errors


def _moebius_strip(n: int = 12, half_width: float = 0.3):
    """A Moebius strip: n quads round a unit circle, the last joined to the first with a half twist."""
    u = 2 * np.pi * np.arange(n) / n
    rows = []
    for v in (-half_width, half_width):
        ring = 1 + v * np.cos(u / 2)
        rows.append(np.stack([ring * np.cos(u), ring * np.sin(u), v * np.sin(u / 2)], axis=1))
    nodes = np.concatenate(rows)  # bottom row 0 .. n-1, top row n .. 2n-1
    bottom, top = np.arange(n), n + np.arange(n)
    next_bottom, next_top = np.roll(bottom, -1), np.roll(top, -1)
    next_bottom[-1], next_top[-1] = top[0], bottom[0]  # the half twist swaps the rows
    triangles = np.concatenate([np.stack([bottom, next_bottom, next_top], 1), np.stack([bottom, next_top, top], 1)])
    return nodes, triangles, [bottom[:2]]


def _octahedron():
    nodes = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=float)
    triangles = [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]
    return nodes, np.array(triangles), [[0, 2]]


def _three_triangles_on_one_edge():
    nodes = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0, 1]], dtype=float)
    return nodes, np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]]), [[0, 2]]


def _zero_area_triangle():
    nodes = np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2], [0, 1, 0]], dtype=float)
    return nodes, np.array([[0, 1, 3], [0, 1, 2]]), [[0, 3]]


def _interior_electrode():
    patch = de.mesh.cylinder_patch(0.5, 1.0, 2.0, 4, h=0.3)
    interior = np.setdiff1d(np.arange(patch.n_nodes), patch.boundary_edges)[:2]
    return patch.nodes, patch.triangles, [*patch.electrodes[:3], interior]


@pytest.mark.parametrize(
    ("surface", "message"),
    [
        (_zero_area_triangle, r"degenerate triangles \(zero area or repeated vertices\): \[1\]"),
        (_three_triangles_on_one_edge, "non-manifold mesh: the edge between nodes 0 and 1 is shared by 3 triangles"),
        (_octahedron, "closed surface"),
        (_moebius_strip, "non-orientable"),
        (_interior_electrode, "electrode 3: nodes .* are not on the boundary"),
    ],
)
def test_bad_surfaces_are_refused_by_name(surface, message):
    nodes, triangles, electrodes = surface()
    with pytest.raises(ValueError, match=message):
        de.Mesh(nodes, triangles, electrodes)


def test_a_curved_surface_is_oriented_consistently_whatever_the_input_orientation():
    patch = de.mesh.cylinder_patch(0.5, 1.0, 2.0, 8, h=0.2)
    triangles = patch.triangles.copy()
    flips = np.random.default_rng(4).random(len(triangles)) < 0.5
    flips[0] = False
    triangles[flips] = triangles[flips][:, [0, 2, 1]]
    reoriented = de.Mesh(patch.nodes, triangles, patch.electrodes)
    np.testing.assert_array_equal(reoriented.triangles, patch.triangles)
    # Every interior edge is traversed once each way; reversing the first triangle reverses all.
    directed = reoriented.triangles[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2)
    assert len({tuple(edge) for edge in directed.tolist()}) == len(directed)
    flipped_first = de.Mesh(patch.nodes, patch.triangles[:, [0, 2, 1]], patch.electrodes)
    reversed_edges = {(b, a) for a, b in patch.boundary_edges.tolist()}
    assert {tuple(edge) for edge in flipped_first.boundary_edges.tolist()} == reversed_edges
    np.testing.assert_array_equal(flipped_first.electrodes[0], patch.electrodes[0][::-1])


def test_flat_and_3d_meshes_differ_and_3d_meshes_refuse_scikit_fem():
    flat = de.mesh.rectangle(1.0, 0.6, 6, h=0.3)
    surface = de.Mesh(_in_3d(flat.nodes), flat.triangles, flat.electrodes)
    assert surface != flat
    assert surface == de.Mesh(_in_3d(flat.nodes), flat.triangles, flat.electrodes)
    assert hash(surface) == hash(de.Mesh(_in_3d(flat.nodes), flat.triangles, flat.electrodes))
    assert surface.element_centroids.shape == (flat.n_elements, 3)
    with pytest.raises(ValueError, match="to_skfem needs a flat mesh"):
        surface.to_skfem()
    with pytest.raises(ValueError, match=r"\(N, 2\) or, for a surface in 3D, \(N, 3\)"):
        de.Mesh(np.zeros((3, 4)), [[0, 1, 2]], [[0, 1]])


@pytest.mark.parametrize(
    ("generator", "kwargs", "message"),
    [
        (de.mesh.cylinder_patch, {"radius": 0.5, "length": 1.0, "angle": 2 * np.pi}, "angle must lie in"),
        (de.mesh.cylinder_patch, {"radius": -0.5, "length": 1.0, "angle": 1.0}, "must be positive"),
        (de.mesh.sphere_cap, {"radius": 1.0, "polar_angle": np.pi}, "polar_angle must lie in"),
        (de.mesh.sphere_cap, {"radius": 1.0, "polar_angle": 0.5, "electrode_width": 0.4}, "do not fit"),
    ],
)
def test_surface_generators_refuse_impossible_shapes(generator, kwargs, message):
    with pytest.raises(ValueError, match=message):
        generator(n_electrodes=8, h=0.2, **kwargs)


def test_what_works_in_the_plane_refuses_a_curved_skin_by_name():
    """Point location, pixel grids (GREIT, rendering) and mesh-to-mesh interpolation would read
    a surface's first two coordinates as a plane: they refuse it."""
    cap = de.mesh.sphere_cap(1.0, 1.0, 16, h=0.4)
    message = "works on flat meshes"
    with pytest.raises(ValueError, match=message):
        de.mesh.locate(cap, [0.0, 0.0])
    with pytest.raises(ValueError, match=message):
        de.render.pixel_grid(cap, 16)
    with pytest.raises(ValueError, match=message):
        de.mesh.interpolate(np.ones(cap.n_elements), cap, cap)
    with pytest.raises(ValueError, match=message):
        de.inverse.GREIT(de.ForwardModel(cap, de.protocol.adjacent(16)))


def test_onto_surface_projects_onto_the_nearest_elements_plane():
    """On a flat sheet turned in 3D every element's plane is the sheet's: a point off it comes
    back with its height removed and its place kept; a flat mesh keeps the point; another
    dimension is refused."""
    flat = de.mesh.rectangle(1.0, 0.6, 8, h=0.2)
    rotation = _rotation(3)
    surface = de.Mesh(_in_3d(flat.nodes) @ rotation.T, flat.triangles, flat.electrodes)
    above = rotation @ np.array([0.3, 0.2, 0.05])
    np.testing.assert_allclose(de.mesh.onto_surface(surface, above), rotation @ np.array([0.3, 0.2, 0.0]), atol=1e-12)
    np.testing.assert_array_equal(de.mesh.onto_surface(flat, [0.3, 0.2]), [0.3, 0.2])
    with pytest.raises(ValueError, match="a point of this mesh has 3 coordinates"):
        de.mesh.onto_surface(surface, [0.3, 0.2])


def test_nearest_element_gives_the_element_its_centroids_distance_and_its_normal():
    """Against a brute-force search over the centroids: the element, the distance to its
    centroid, and the unit normal of its winding; among a subset of the elements, one of them;
    on a flat sheet no normal."""
    cap = de.mesh.sphere_cap(1.0, 1.0, 16, h=0.2)
    points = np.random.default_rng(0).normal(size=(20, 3)) * 0.5 + [0.0, 0.0, 0.8]
    element, distance, normal = de.mesh.nearest_element(cap, points)
    gaps = np.linalg.norm(points[:, None] - cap.element_centroids[None], axis=2)
    np.testing.assert_array_equal(element, np.argmin(gaps, axis=1))
    np.testing.assert_allclose(distance, np.min(gaps, axis=1))
    a, b, c = (cap.nodes[cap.triangles[element, corner]] for corner in range(3))
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0)
    np.testing.assert_allclose(np.einsum("pd,pd->p", normal, b - a), 0.0, atol=1e-12)
    assert np.all(np.einsum("pd,pd->p", normal, np.cross(b - a, c - a)) > 0)
    subset = np.arange(0, cap.n_elements, 3)
    np.testing.assert_array_equal(
        de.mesh.nearest_element(cap, points, subset)[0], subset[np.argmin(gaps[:, subset], axis=1)]
    )
    flat = de.mesh.disc(8, h=0.3)
    found, _, none = de.mesh.nearest_element(flat, np.array([[0.1, 0.2]]))
    assert none.shape == (1, 0) and found[0] == np.argmin(np.linalg.norm(flat.element_centroids - [0.1, 0.2], axis=1))


def test_the_noise_figure_targets_the_middle_of_a_domes_surface():
    """The noise figure's small target sits at the area-weighted mean of the centroids, which on
    a dome lies inside it (0.25 m below the apex here): it is taken onto the surface, where its
    disc covers elements (it covered none, and the hyperparameter choice failed)."""
    cap = de.mesh.sphere_cap(1.15, np.deg2rad(60.0), 16, h=0.15, electrode_width=0.2)
    model = de.ForwardModel(cap, de.protocol.adjacent(16), contact_impedance=0.01)
    pressed = 1 - 0.3 * de.mesh.disc_fraction(cap, tuple(cap.element_centroids[0]), 0.2)
    dv = np.asarray(model.measure(jax.numpy.asarray(pressed))) - np.asarray(
        model.measure(jax.numpy.ones(cap.n_elements))
    )
    selection = de.inverse.select_hyperparameter(model, dv[None], "noise_figure")
    assert selection.target == 0.5 and np.isfinite(selection.value) and selection.value > 0
    figure = np.interp(np.log(selection.value), np.log(selection.candidates), selection.criterion)
    assert figure == pytest.approx(0.5, rel=0.2)  # the crossing, between the candidates around it


def test_distances_along_a_surface_are_great_circles_on_a_dome_and_helices_on_a_forearm():
    """`surface_distance` between points on a dome of radius 1 (taken onto its mesh) is the
    great circle to the mesh's flatness, also for points 2 rad apart (the chord is 16% short);
    on a 40 mm cylinder, the helix along it within 0.3% (2.6% short at 2 rad round the axis,
    as documented); on a flat sheet the straight line; NaN stays NaN."""
    cap = de.mesh.sphere_cap(1.0, 1.2, 16, h=0.05)

    def on_sphere(polar: float, azimuth: float) -> np.ndarray:
        return np.array([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)])

    pairs = [((0.2, 0.0), (0.9, 2.0)), ((0.5, 1.0), (0.6, 1.2)), ((1.0, 0.0), (1.0, 3.0))]
    starts = de.mesh.onto_surface(cap, np.array([on_sphere(*a) for a, _ in pairs]))
    stops = de.mesh.onto_surface(cap, np.array([on_sphere(*b) for _, b in pairs]))
    great = np.array([np.arccos(on_sphere(*a) @ on_sphere(*b)) for a, b in pairs])
    np.testing.assert_allclose(de.mesh.surface_distance(cap, starts, stops), great, rtol=2e-3)
    assert np.linalg.norm(stops[2] - starts[2]) < 0.85 * great[2]
    rho = 0.04
    patch = de.mesh.cylinder_patch(rho, 0.15, np.radians(150), 16, 0.003)
    turns = np.array([[1.0, 0.0], [1.0, 0.05], [0.3, 0.02], [2.0, 0.06]])  # (angle round the axis, rad; along it, m)
    starts = np.column_stack([rho * np.cos(-turns[:, 0] / 2), rho * np.sin(-turns[:, 0] / 2), np.zeros(4)])
    stops = np.column_stack([rho * np.cos(turns[:, 0] / 2), rho * np.sin(turns[:, 0] / 2), turns[:, 1]])
    distance = de.mesh.surface_distance(patch, de.mesh.onto_surface(patch, starts), de.mesh.onto_surface(patch, stops))
    helix = np.hypot(rho * turns[:, 0], turns[:, 1])
    np.testing.assert_allclose(distance[:3], helix[:3], rtol=3e-3)
    assert 0.97 * helix[3] < distance[3] < helix[3]
    flat = de.mesh.disc(8, h=0.3)
    np.testing.assert_allclose(de.mesh.surface_distance(flat, [0.1, 0.2], [0.4, -0.2]), 0.5)
    assert np.isnan(de.mesh.surface_distance(cap, np.full(3, np.nan), on_sphere(0.2, 0.0)))
    with pytest.raises(ValueError, match="3 coordinates"):
        de.mesh.surface_distance(cap, [0.1, 0.2], [0.3, 0.4])
