import itertools

import jax.numpy as jnp
import numpy as np
import pytest
import skfem
from hypothesis import given, settings
from hypothesis import strategies as st

import diffeit as de


def test_disc_puts_electrode_ends_on_the_circle_at_their_angles():
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.1, first_electrode_angle=0.3)
    assert mesh.n_electrodes == 16
    for k, chain in enumerate(mesh.electrodes):
        ends = mesh.nodes[chain[[0, -1]]]
        np.testing.assert_allclose(np.linalg.norm(ends, axis=1), 1.0, atol=1e-14)
        angles = np.arctan2(ends[:, 1], ends[:, 0])
        centre = 0.3 + 2 * np.pi * k / 16
        expected = np.angle(np.exp(1j * (centre + np.array([-0.1, 0.1]))))
        np.testing.assert_allclose(angles, expected, atol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(mesh.nodes[chain], axis=1), 1.0, atol=1e-14)
    boundary = np.unique(mesh.boundary_edges)
    np.testing.assert_allclose(np.linalg.norm(mesh.nodes[boundary], axis=1), 1.0, atol=1e-14)
    assert np.all(mesh.element_areas > 0)


def test_disc_element_count_follows_h_and_refines_near_electrodes():
    counts = [de.mesh.disc(h=h, electrode_h=h).n_elements for h in (0.2, 0.1, 0.05)]
    ratios = np.array(counts[1:]) / np.array(counts[:-1])
    assert np.all((ratios > 3.0) & (ratios < 5.0)), counts  # ~4x per halving of h
    uniform = de.mesh.disc(h=0.1, electrode_h=0.1)
    refined = de.mesh.disc(h=0.1, electrode_h=0.025)
    assert refined.n_elements > uniform.n_elements
    radius = np.linalg.norm(refined.element_centroids, axis=1)
    rim, centre = refined.element_areas[radius > 0.95].mean(), refined.element_areas[radius < 0.5].mean()
    assert rim < 0.25 * centre
    assert all(len(chain) >= 9 for chain in refined.electrodes)  # width 0.2 at spacing 0.025


@pytest.mark.parametrize(("n_electrodes", "radius", "width"), [(16, 0.08, 0.2 * 0.08), (32, 0.1, np.pi * 0.1 / 32)])
def test_a_disc_in_metres_gets_the_unit_discs_defaults_scaled(n_electrodes, radius, width):
    """A skin described by its radius alone ({"kind": "disc", "radius": 0.08}: 80 mm) gets
    electrodes 0.2 of the radius wide (half the spacing for 32, where 0.2 leaves no gaps) and
    elements 0.1 of it: with the unit disc's absolute defaults the 80 mm disc's electrodes did
    not fit its rim, and h = 0.1 m made a sheet of a few dozen triangles."""
    mesh = de.io.mesh_from_geometry({"kind": "disc", "radius": radius, "n_electrodes": n_electrodes})
    unit = de.mesh.disc(n_electrodes, electrode_width=width / radius, h=0.1)
    assert abs(mesh.n_elements - unit.n_elements) < 0.05 * unit.n_elements
    for chain in mesh.electrodes:
        ends = mesh.nodes[chain[[0, -1]]]
        np.testing.assert_allclose(np.linalg.norm(ends, axis=1), radius, rtol=1e-12)
        angle = np.angle(np.exp(1j * np.diff(np.arctan2(ends[:, 1], ends[:, 0]))))
        np.testing.assert_allclose(radius * angle, width, rtol=1e-12)
    edges = np.linalg.norm(np.diff(mesh.nodes[mesh.triangles[:, [0, 1, 2, 0]]], axis=1), axis=2)
    assert 0.05 * radius < np.median(edges) < 0.15 * radius


def test_disc_aligns_elements_to_interior_circles():
    mesh = de.mesh.disc(h=0.1, interior_circles=(0.5,))
    radius = np.linalg.norm(mesh.nodes[mesh.triangles], axis=2)  # (E, 3)
    inside = np.all(radius <= 0.5 + 1e-12, axis=1)
    outside = np.all(radius >= 0.5 - 1e-12, axis=1)
    assert np.all(inside | outside)
    # The inscribed polygon of the circle has area close to pi r^2.
    assert abs(mesh.element_areas[inside].sum() - np.pi * 0.25) < 0.01


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"n_electrodes": 32, "electrode_width": 0.2}, "do not fit"),
        ({"h": -1.0}, "must be positive"),
        ({"electrode_h": 0.5, "h": 0.1}, "electrode_h"),
        ({"interior_circles": (1.2,)}, "strictly inside"),
    ],
)
def test_disc_refuses_impossible_layouts(kwargs, message):
    with pytest.raises(ValueError, match=message):
        de.mesh.disc(**kwargs)


def _square():
    """The unit square from scikit-fem, 4 electrodes: one chain of boundary nodes per side."""
    skmesh = skfem.MeshTri().refined(3)
    nodes, triangles = skmesh.p.T, skmesh.t.T
    electrodes = []
    for axis, value in [(1, 0.0), (0, 1.0), (1, 1.0), (0, 0.0)]:
        on_side = np.flatnonzero(np.isclose(nodes[:, axis], value))
        along = nodes[on_side, 1 - axis]
        chain = on_side[np.argsort(along)]
        middle = (along[np.argsort(along)] > 0.3) & (along[np.argsort(along)] < 0.7)
        electrodes.append(chain[middle])
    return nodes, triangles, electrodes


def test_from_arrays_reorients_clockwise_triangles():
    nodes, triangles, electrodes = _square()
    flipped = triangles.copy()
    flipped[::2] = flipped[::2, [0, 2, 1]]  # half of them clockwise
    a = de.Mesh.from_arrays(nodes, triangles, electrodes)
    b = de.Mesh.from_arrays(nodes, flipped, electrodes)
    np.testing.assert_allclose(a.element_areas, b.element_areas)
    assert np.all(b.element_areas > 0)
    np.testing.assert_allclose(a.element_areas.sum(), 1.0)
    protocol = de.protocol.adjacent(4)
    sigma = jnp.linspace(0.5, 2.0, a.n_elements)
    np.testing.assert_allclose(
        de.ForwardModel(a, protocol).measure(sigma), de.ForwardModel(b, protocol).measure(sigma), rtol=1e-12
    )


@settings(max_examples=15, deadline=None)
@given(flips=st.lists(st.booleans(), min_size=128, max_size=128), seed=st.integers(0, 2**31 - 1))
def test_any_mix_of_orientations_gives_the_same_mesh_and_voltages(flips, seed):
    nodes, triangles, electrodes = _square()
    mixed = np.where(np.array(flips)[:, None], triangles[:, [0, 2, 1]], triangles)
    reference, mesh = de.Mesh.from_arrays(nodes, triangles, electrodes), de.Mesh.from_arrays(nodes, mixed, electrodes)
    np.testing.assert_allclose(mesh.element_areas, reference.element_areas, rtol=1e-15)
    np.testing.assert_array_equal(np.sort(mesh.boundary_edges, axis=0), np.sort(reference.boundary_edges, axis=0))
    sigma = jnp.asarray(np.random.default_rng(seed).uniform(0.1, 10.0, mesh.n_elements))
    protocol = de.protocol.adjacent(4)
    np.testing.assert_allclose(
        de.ForwardModel(mesh, protocol).measure(sigma), de.ForwardModel(reference, protocol).measure(sigma), rtol=1e-11
    )


def test_from_arrays_refuses_bad_meshes_naming_the_problem():
    nodes, triangles, electrodes = _square()
    degenerate = triangles.copy()
    degenerate[5] = [degenerate[5, 0], degenerate[5, 0], degenerate[5, 1]]
    with pytest.raises(ValueError, match=r"degenerate triangles .*\[5\]"):
        de.Mesh.from_arrays(nodes, degenerate, electrodes)
    collinear = np.vstack([nodes, [[0.25, 0.25], [0.5, 0.5], [0.75, 0.75]]])
    flat = np.vstack([triangles, [len(nodes), len(nodes) + 1, len(nodes) + 2]])
    with pytest.raises(ValueError, match=rf"degenerate triangles .*\[{len(triangles)}\]"):
        de.Mesh.from_arrays(collinear, flat, electrodes)
    with pytest.raises(ValueError, match="index nodes outside"):
        de.Mesh.from_arrays(nodes, triangles + 1000, electrodes)
    with pytest.raises(ValueError, match="belong to no triangle"):
        de.Mesh.from_arrays(np.vstack([nodes, [[3.0, 3.0]]]), triangles, electrodes)
    interior = int(np.flatnonzero(np.all(np.abs(nodes - 0.5) < 0.3, axis=1))[0])
    with pytest.raises(ValueError, match=rf"electrode 1: nodes \[{interior}\] are not on the boundary"):
        de.Mesh.from_arrays(nodes, triangles, [electrodes[0], [*electrodes[1], interior]])
    with pytest.raises(ValueError, match="electrodes 0 and 1 overlap"):
        de.Mesh.from_arrays(nodes, triangles, [electrodes[0], electrodes[0][1:]])
    with pytest.raises(ValueError, match="electrode 2 has 1 node"):
        de.Mesh.from_arrays(nodes, triangles, [electrodes[0], electrodes[1], electrodes[2][:1]])
    with pytest.raises(ValueError, match="do not form one contiguous piece of the boundary"):
        de.Mesh.from_arrays(nodes, triangles, [electrodes[0][::2]])
    with pytest.raises(ValueError, match="non-finite"):
        de.Mesh.from_arrays(np.where(np.arange(len(nodes))[:, None] == 3, np.nan, nodes), triangles, electrodes)


def test_electrode_nodes_in_any_order_are_ordered_along_the_boundary():
    nodes, triangles, electrodes = _square()
    mesh = de.Mesh.from_arrays(nodes, triangles, electrodes)
    shuffled = [np.random.default_rng(k).permutation(e) for k, e in enumerate(electrodes)]
    reordered = de.Mesh.from_arrays(nodes, triangles, shuffled)
    reversed_ = de.Mesh.from_arrays(nodes, triangles, [e[::-1] for e in electrodes])
    for a, b, c in zip(mesh.electrodes, reordered.electrodes, reversed_.electrodes, strict=True):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)
        # Each step is a boundary edge in its counter-clockwise direction.
        steps = {tuple(edge) for edge in mesh.boundary_edges.tolist()}
        assert all((int(p), int(q)) in steps for p, q in itertools.pairwise(a))
    # The bottom side's electrode runs in +x: counter-clockwise around the square.
    assert np.all(np.diff(mesh.nodes[mesh.electrodes[0], 0]) > 0)


def test_from_arrays_refuses_disconnected_meshes():
    nodes = np.array([[0, 0], [1, 0], [0, 1], [5, 5], [6, 5], [5, 6]], dtype=float)
    triangles = np.array([[0, 1, 2], [3, 4, 5]])
    with pytest.raises(ValueError, match="2 disconnected pieces"):
        de.Mesh.from_arrays(nodes, triangles, [[0, 1], [3, 4]])


def test_mesh_is_immutable(small_disc):
    with pytest.raises(AttributeError):
        small_disc.nodes = small_disc.nodes
    with pytest.raises(ValueError, match="read-only"):
        small_disc.nodes[0, 0] = 1.0


def test_disc_fraction_integrates_the_disc_area():
    mesh = de.mesh.disc(h=0.05)
    fraction = de.mesh.disc_fraction(mesh, (0.3, -0.2), 0.25)
    assert np.all((fraction >= 0) & (fraction <= 1))
    np.testing.assert_allclose(fraction @ mesh.element_areas, np.pi * 0.25**2, rtol=2e-3)


@pytest.mark.parametrize("surface", [False, True], ids=["flat", "dome"])
def test_exact_disc_fractions_are_what_sampling_tends_to_and_move_smoothly(surface):
    """`level=None`: the exact area, which the midpoint rule approaches as O(1/level) (measured:
    5.5e-4 at level 100), 1 on a disc holding the whole mesh, the disc's area on the flat mesh to
    rounding, and a footprint that moves smoothly with its centre (sampled, it moves in steps of
    1/level^2)."""
    mesh = de.mesh.sphere_cap(1.0, 1.0, 8, 0.2) if surface else de.mesh.disc(h=0.1)
    rng = np.random.default_rng(3)
    centres = mesh.element_centroids[rng.choice(mesh.n_elements, 5, replace=False)]
    radii = np.array([0.05, 0.1, 0.2, 0.3, 2.0])
    exact = de.mesh.disc_fractions(mesh, centres, radii, level=None).toarray()
    # The disc holding the mesh is left out of the fine sampling (its 1 is checked exactly below).
    fine = de.mesh.disc_fractions(mesh, centres[:-1], radii[:-1], level=100).toarray()
    assert np.abs(exact[:, :-1] - fine).max() < 1e-3
    assert np.abs(exact - de.mesh.disc_fractions(mesh, centres, radii).toarray()).max() > 5e-3  # level 8 differs
    np.testing.assert_allclose(exact[:, -1], 1.0, atol=1e-12)
    step = 1e-7 * np.eye(mesh.nodes.shape[1])[0]
    moved = de.mesh.disc_fractions(mesh, centres + step, radii, level=None).toarray()
    assert 0 < np.abs(moved - exact).max() < 1e-5
    if not surface:
        inside = de.mesh.disc_fraction(mesh, (0.3, -0.2), 0.25, level=None)
        np.testing.assert_allclose(inside @ mesh.element_areas, np.pi * 0.25**2, rtol=1e-12)


@pytest.mark.parametrize("surface", [False, True], ids=["flat", "dome"])
def test_disc_fractions_equal_testing_every_triangles_sample_points(surface):
    """The batched fractions sample only the triangles near each disc; testing every triangle's
    sample points against each disc gives the same numbers."""
    mesh = de.mesh.sphere_cap(1.0, 1.0, 8, 0.2) if surface else de.mesh.disc(h=0.1)
    rng = np.random.default_rng(3)
    centres = mesh.element_centroids[rng.choice(mesh.n_elements, 5, replace=False)]
    radii = np.array([0.05, 0.1, 0.2, 0.3, 2.0])
    samples = de.mesh.element_sample_points(mesh)
    every = np.stack(
        [(np.linalg.norm(samples - c, axis=2) < r).mean(axis=1) for c, r in zip(centres, radii, strict=True)], axis=1
    )
    fractions = de.mesh.disc_fractions(mesh, centres, radii)
    np.testing.assert_array_equal(fractions.toarray(), every)
    assert np.all(fractions.toarray()[:, -1] == 1)  # a disc holding the whole mesh
    np.testing.assert_array_equal(de.mesh.disc_fraction(mesh, centres[1], 0.1), every[:, 1])
    assert de.mesh.disc_fractions(mesh, centres[:0], 0.1).shape == (mesh.n_elements, 0)
    with pytest.raises(ValueError, match="radius must be positive"):
        de.mesh.disc_fractions(mesh, centres, -1.0)
    with pytest.raises(ValueError, match="centres must have shape"):
        de.mesh.disc_fractions(mesh, centres[:, :1], 0.1)


def test_locate_finds_the_element_holding_each_point(small_disc):
    """Every centroid is in its own element; a point off the sheet is in none (-1)."""
    found = de.mesh.locate(small_disc, small_disc.element_centroids)
    np.testing.assert_array_equal(found, np.arange(small_disc.n_elements))
    assert de.mesh.locate(small_disc, [2.0, 0.0]) == -1 and de.mesh.locate(small_disc, [2.0, 0.0]).shape == ()


def test_onto_sheet_takes_points_off_a_sheet_to_the_nearest_point_of_its_outline():
    """On a 2 x 1 rectangle: a point beyond a side goes straight onto it, one beyond a corner to
    the corner; points on the sheet and NaN stay as they are, bit for bit, in any batch shape."""
    sheet = de.mesh.rectangle(2.0, 1.0, 8, h=0.25)
    points = np.array([[[3.0, 0.2], [0.4, -0.9]], [[-1.5, 0.75], [0.3, 0.1]], [[np.nan, np.nan], [-0.99, 0.49]]])
    held = de.mesh.onto_sheet(sheet, points)
    assert held.shape == points.shape
    np.testing.assert_allclose(held[0], [[1.0, 0.2], [0.4, -0.5]], atol=1e-12)
    np.testing.assert_allclose(held[1, 0], [-1.0, 0.5], atol=1e-12)
    np.testing.assert_array_equal(held[1, 1], points[1, 1])
    np.testing.assert_array_equal(held[2], points[2])
    with pytest.raises(ValueError, match="onto_sheet"):
        de.mesh.onto_sheet(de.mesh.sphere_cap(1.0, 0.8, 8, h=0.3), np.zeros((1, 2)))
