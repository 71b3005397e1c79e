"""Conservative interpolation of element fields between meshes by exact overlap areas."""

import numpy as np
import pytest

import diffeit as de


@pytest.fixture(scope="module")
def fine():
    return de.mesh.rectangle(2.0, 1.0, 16, electrode_width=0.1, h=0.05)


@pytest.fixture(scope="module")
def coarse():
    return de.mesh.rectangle(2.0, 1.0, 16, electrode_width=0.1, h=0.2)


def _split_square(diagonal: str, offset=(0.0, 0.0)) -> de.Mesh:
    """The unit square as two triangles, cut along one diagonal."""
    nodes = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=float) + offset
    triangles = [[0, 1, 2], [0, 2, 3]] if diagonal == "rising" else [[0, 1, 3], [1, 2, 3]]
    return de.Mesh.from_arrays(nodes, triangles, [[0, 1], [2, 3]])


@pytest.mark.parametrize("offset", [(0.0, 0.0), (1e3, -2e3)])
def test_overlap_areas_of_the_two_diagonal_splits_of_a_square(offset):
    rising, falling = _split_square("rising", offset), _split_square("falling", offset)
    areas = de.mesh.overlap_areas(rising, falling).toarray()
    np.testing.assert_allclose(areas, np.full((2, 2), 0.25), rtol=1e-12)
    np.testing.assert_allclose(de.mesh.remap_matrix(rising, falling).toarray(), np.full((2, 2), 0.5), rtol=1e-12)
    np.testing.assert_allclose(de.mesh.interpolate([1.0, 3.0], rising, falling), [2.0, 2.0], rtol=1e-12)


def test_a_mesh_onto_itself_is_the_identity(coarse):
    weights = de.mesh.remap_matrix(coarse, coarse)
    np.testing.assert_allclose(weights.toarray(), np.eye(coarse.n_elements), atol=1e-12)
    assert weights.nnz == coarse.n_elements  # neighbours that share an edge do not overlap
    np.testing.assert_allclose(de.mesh.overlap_areas(coarse, coarse).diagonal(), coarse.element_areas, rtol=1e-12)
    field = np.random.default_rng(0).normal(size=coarse.n_elements)
    np.testing.assert_allclose(de.mesh.interpolate(field, coarse, coarse), field, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("direction", ["fine to coarse", "coarse to fine"])
def test_overlaps_sum_to_element_areas_and_integrals_are_conserved(fine, coarse, direction):
    source, target = (fine, coarse) if direction == "fine to coarse" else (coarse, fine)
    areas = de.mesh.overlap_areas(source, target)
    assert areas.shape == (target.n_elements, source.n_elements)
    np.testing.assert_allclose(areas.sum(axis=1), target.element_areas, rtol=1e-12)
    np.testing.assert_allclose(areas.sum(axis=0), source.element_areas, rtol=1e-12)
    assert areas.nnz < 20 * max(source.n_elements, target.n_elements)  # local, not all pairs
    field = np.exp(np.random.default_rng(1).normal(0.0, 1.0, source.n_elements))
    moved = de.mesh.interpolate(field, source, target)
    np.testing.assert_allclose(moved @ target.element_areas, field @ source.element_areas, rtol=1e-12)
    np.testing.assert_allclose(de.mesh.interpolate(np.full(source.n_elements, 3.7), source, target), 3.7, rtol=1e-13)
    assert field.min() <= moved.min() and moved.max() <= field.max()  # a mean never overshoots


def test_discs_of_different_h_preserve_constants_on_their_different_polygons():
    fine, coarse = de.mesh.disc(h=0.05), de.mesh.disc(h=0.2)
    areas = de.mesh.overlap_areas(fine, coarse)
    covered = areas.sum(axis=1) / coarse.element_areas
    # Inscribed polygons with different vertices: rim elements are covered only in part.
    assert covered.min() < 1 - 1e-4 and np.all(covered <= 1 + 1e-12)
    assert np.median(covered) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(de.mesh.interpolate(np.full(fine.n_elements, 2.5), fine, coarse), 2.5, rtol=1e-13)


def _quadratic_means(mesh: de.Mesh) -> np.ndarray:
    """Exact element means of x^2 + y: the edge-midpoint rule integrates quadratics exactly."""
    corners = mesh.nodes[mesh.triangles]
    midpoints = 0.5 * (corners + np.roll(corners, 1, axis=1))
    return np.mean(midpoints[..., 0] ** 2 + midpoints[..., 1], axis=1)


def test_a_smooth_field_moved_from_finer_meshes_converges_to_the_coarse_means(coarse):
    errors = []
    for h in (0.1, 0.05, 0.025):
        source = de.mesh.rectangle(2.0, 1.0, 16, electrode_width=0.1, h=h, electrode_h=h)
        moved = de.mesh.interpolate(_quadratic_means(source), source, coarse)
        errors.append(np.abs(moved - _quadratic_means(coarse)).max())
    errors = np.array(errors)
    assert np.all(errors[1:] < 0.7 * errors[:-1]), errors
    assert errors[-1] < 0.02  # the field spans 1.5 over the rectangle


def test_a_batch_equals_frame_by_frame(fine, coarse):
    frames = np.random.default_rng(2).normal(size=(4, fine.n_elements))
    batch = de.mesh.interpolate(frames, fine, coarse)
    assert batch.shape == (4, coarse.n_elements)
    for frame, moved in zip(frames, batch, strict=True):
        np.testing.assert_allclose(moved, de.mesh.interpolate(frame, fine, coarse), rtol=1e-14, atol=1e-15)
    complex_field = frames[0] + 1j * frames[1]
    np.testing.assert_allclose(de.mesh.interpolate(complex_field, fine, coarse), batch[0] + 1j * batch[1], rtol=1e-14)


def test_target_elements_outside_the_source_are_refused_or_filled_by_the_nearest():
    source = de.mesh.rectangle(1.0, 1.0, 4, electrode_width=0.2, h=0.25)
    target = de.mesh.rectangle(3.0, 3.0, 4, electrode_width=0.2, h=0.5)
    with pytest.raises(ValueError, match=r"target element\(s\) \[.*overlap no source element.*uncovered='nearest'"):
        de.mesh.interpolate(np.ones(source.n_elements), source, target)
    field = source.element_centroids[:, 0]
    moved = de.mesh.interpolate(field, source, target, uncovered="nearest")
    areas = de.mesh.overlap_areas(source, target)
    covered = areas.sum(axis=1) > 0
    assert np.any(~covered) and np.any(covered)
    # Covered elements, even in part, take the mean over their covered part.
    np.testing.assert_allclose(moved[covered], (areas @ field)[covered] / areas.sum(axis=1)[covered], rtol=1e-13)
    weights = de.mesh.remap_matrix(source, target, uncovered="nearest")
    np.testing.assert_allclose(weights.sum(axis=1), 1.0, rtol=1e-13)
    for t in np.flatnonzero(~covered):
        (chosen,) = weights[[t]].indices  # one source element, weight 1
        distance = np.linalg.norm(source.element_centroids - target.element_centroids[t], axis=1)
        assert distance[chosen] == pytest.approx(distance.min(), rel=1e-12)
        assert moved[t] == field[chosen]


@pytest.mark.parametrize(
    ("field", "message"),
    [
        (np.ones(5), r"shape \(E_source,\) or \(T, E_source\)"),
        (np.ones((2, 3, 4)), r"shape \(E_source,\) or \(T, E_source\)"),
        ("nan at 3", r"not finite on source element\(s\) \[3\]"),
        (np.array(["a"]), "must hold numbers"),
    ],
)
def test_bad_fields_are_refused(coarse, field, message):
    if isinstance(field, str):
        field = np.ones((2, coarse.n_elements))
        field[1, 3] = np.nan
    with pytest.raises(ValueError, match=message):
        de.mesh.interpolate(field, coarse, coarse)


def test_bad_arguments_are_refused(coarse):
    with pytest.raises(ValueError, match="uncovered must be 'raise' or 'nearest'"):
        de.mesh.remap_matrix(coarse, coarse, uncovered="zero")
    with pytest.raises(TypeError, match="target must be a diffeit Mesh"):
        de.mesh.overlap_areas(coarse, coarse.nodes)


def test_remap_of_32k_onto_3k_triangles_is_exact():
    fine, coarse = de.mesh.disc(h=0.0155, electrode_h=0.0155), de.mesh.disc(h=0.05, electrode_h=0.05)
    assert fine.n_elements > 30_000 and coarse.n_elements > 2_900
    weights = de.mesh.remap_matrix(fine, coarse)
    np.testing.assert_allclose(weights.sum(axis=1), 1.0, rtol=1e-12)
    areas = de.mesh.overlap_areas(fine, coarse)
    np.testing.assert_allclose(areas.sum(), min(fine.element_areas.sum(), coarse.element_areas.sum()), rtol=1e-3)
