"""Image metrics on hand-made images with known answers (a disc, two discs, a ring, a cone, a
disc with a ringing halo), on elements and on pixels; rendering; validation."""

import matplotlib.tri
import numpy as np
import pytest

import diffeit as de
from diffeit import metrics
from diffeit.render import pixel_grid, render


@pytest.fixture(scope="module")
def mesh() -> de.Mesh:
    return de.mesh.disc(16, electrode_width=0.2, h=0.05)  # 3,272 triangles on the unit disc


def _distance(mesh, centre):
    return np.linalg.norm(mesh.element_centroids - np.asarray(centre), axis=1)


def _cone(mesh, centre=(0.2, 0.1), radius=0.4, height=-0.02):
    """height (1 - |x - centre| / radius)+ at the element centroids: its half-amplitude set is the
    disc of radius radius / 2 about centre, up to the elements' resolution."""
    return height * np.maximum(0.0, 1 - _distance(mesh, centre) / radius)


def test_a_disc(mesh):
    """A touch of -0.003 S/sq in a disc r = 0.2 at (0.5, 0): peak, size, position, shape."""
    image = -0.003 * de.mesh.disc_fraction(mesh, (0.5, 0.0), 0.2)
    assert metrics.peak(image) == -0.003
    chosen = metrics.half_amplitude_set(image)
    assert np.all(image[chosen] <= -0.0015) and np.all(image[~chosen] > -0.0015)
    assert metrics.reconstructed_area(mesh, image) == pytest.approx(np.pi * 0.2**2, rel=0.03)
    assert metrics.equivalent_radius(mesh, image) == pytest.approx(0.2, rel=0.015)
    assert metrics.position_error(mesh, image, (0.5, 0.0)) < 0.01
    assert metrics.position_error(mesh, image, (0.5, 0.3)) == pytest.approx(0.3, abs=0.01)
    assert metrics.shape_deformation(mesh, image) < 0.06  # 0 for a perfect disc; measured 0.036
    assert metrics.count_artifacts(mesh, image, (0.5, 0.0)) == 0
    assert metrics.integral(mesh, image) == pytest.approx(-0.003 * np.pi * 0.2**2, rel=0.01)
    assert metrics.correlation(mesh, image, 5 * image) == pytest.approx(1.0)
    assert metrics.correlation(mesh, image, -image) == pytest.approx(-1.0)


def test_transition_width_of_a_sharp_and_a_linear_edge(mesh):
    """A sharp disc's edge blurs over only the elements its boundary cuts; a linear ramp from the
    peak at r = 0.1 to zero at r = 0.3 has 80% of its 0.2 m ramp between 10% and 90%."""
    perimeter = 2 * np.pi * 0.2
    sharp = -0.003 * de.mesh.disc_fraction(mesh, (0.0, 0.0), 0.2)
    assert metrics.transition_width(mesh, sharp, perimeter) < 0.06  # about one element (h = 0.05)
    radius = np.linalg.norm(mesh.element_centroids, axis=1)
    ramp = -np.clip((0.3 - radius) / 0.2, 0.0, 1.0)
    # The band 0.12 < r < 0.28 has area pi (0.28^2 - 0.12^2); over the mid-ramp circle 2 pi 0.2.
    expected = np.pi * (0.28**2 - 0.12**2) / (2 * np.pi * 0.2)
    assert metrics.transition_width(mesh, ramp, 2 * np.pi * 0.2) == pytest.approx(expected, rel=0.1)
    with pytest.raises(ValueError, match="edge_length"):
        metrics.transition_width(mesh, ramp, 0.0)


def test_a_cone_and_its_cross_section(mesh):
    """A cone of height -0.02 and base radius 0.4: the half-amplitude set is the disc r = 0.2,
    and the cross-section through the peak is the cone's profile."""
    image = _cone(mesh)
    assert metrics.equivalent_radius(mesh, image) == pytest.approx(0.2, rel=0.02)
    assert metrics.position_error(mesh, image, (0.2, 0.1)) < 0.005
    np.testing.assert_allclose(metrics.half_amplitude_centroid(mesh, image), [0.2, 0.1], atol=0.005)
    section = metrics.cross_section(mesh, image)
    peak_centre = mesh.element_centroids[np.argmax(np.abs(image))]
    np.testing.assert_allclose(section.points, peak_centre + section.distance[:, None] * [1.0, 0.0], atol=1e-12)
    assert np.all(np.linalg.norm(section.points, axis=1) <= 1.0) and np.ptp(section.distance) > 1.9  # a chord
    # The samples span the line's chord of the bounding box: nearly all 201 land in the disc.
    assert len(section.values) > 190 and np.diff(section.distance) == pytest.approx(0.01, rel=0.02)
    # The line samples the peak's element: its lowest samples lie in it, within its reach (h = 0.05).
    assert section.values.min() == image.min()
    assert section.distance[np.argmin(section.values)] == pytest.approx(0.0, abs=0.04)
    # Each sample is the value of the element containing it: within the cone's slope times the
    # element's reach of the exact profile.
    exact = -0.02 * np.maximum(0.0, 1 - np.linalg.norm(section.points - [0.2, 0.1], axis=1) / 0.4)
    assert np.max(np.abs(section.values - exact)) < 0.02 * 0.06 / 0.4
    vertical = metrics.cross_section(mesh, image, through=(0.2, 0.1), direction=(0.0, 2.0), n_points=11)
    assert np.allclose(vertical.points[:, 0], 0.2) and len(vertical.values) <= 11


def test_a_ring(mesh):
    """An annulus 0.3 < |x| < 0.6: one component whose centroid is the centre (a hole, 0 m
    error), area pi (0.6^2 - 0.3^2) and shape deformation 1/3 (the disc of equal area has radius
    sqrt(0.27); the annulus beyond it is pi (0.36 - 0.27), a third of the area)."""
    radius = _distance(mesh, (0.0, 0.0))
    image = 0.5 * ((radius > 0.3) & (radius < 0.6))
    assert metrics.amplitude_components(mesh, image).count == 1
    assert metrics.reconstructed_area(mesh, image) == pytest.approx(np.pi * 0.27, rel=0.01)
    assert metrics.position_error(mesh, image, (0.0, 0.0)) < 0.005
    assert metrics.shape_deformation(mesh, image) == pytest.approx(1 / 3, abs=0.01)


def test_two_discs_are_matched_to_their_targets(mesh):
    big, small = ((0.5, 0.0), 0.2), ((-0.3, 0.4), 0.15)
    image = -0.3 * (de.mesh.disc_fraction(mesh, *big) + de.mesh.disc_fraction(mesh, *small))
    components = metrics.amplitude_components(mesh, image)
    assert components.count == 2 and components.areas[0] > components.areas[1]  # by decreasing area
    assert set(np.unique(components.labels)) == {-1, 0, 1}
    figures = metrics.target_figures(mesh, image, [small[0], big[0]])  # the order of the centres given
    assert figures.n_artifacts == 0 and np.all(figures.matched)
    np.testing.assert_array_equal(figures.component, [1, 0])
    np.testing.assert_allclose(figures.equivalent_radius, [0.15, 0.2], rtol=0.02)
    np.testing.assert_allclose(figures.peak, [-0.3, -0.3])
    np.testing.assert_allclose(figures.centroid, [small[0], big[0]], atol=0.01)
    assert np.all(figures.position_error < 0.01) and np.all(figures.shape_deformation < 0.08)
    # One target named: the other disc is an artifact. A third, far from both: unmatched, NaN.
    assert metrics.count_artifacts(mesh, image, big[0]) == 1
    three = metrics.target_figures(mesh, image, [big[0], small[0], (-0.5, -0.5)])
    np.testing.assert_array_equal(three.matched, [True, True, False])
    assert np.isnan(three.peak[2]) and np.isnan(three.centroid[2]).all() and three.n_artifacts == 0
    # A match must lie within max_distance: the small disc is 0.2 m from (-0.3, 0.6).
    gated = metrics.target_figures(mesh, image, [big[0], (-0.3, 0.6)], max_distance=0.1)
    np.testing.assert_array_equal(gated.matched, [True, False])
    assert gated.n_artifacts == 1


def test_gating_comes_before_the_assignment(mesh):
    """Discs at (0, 0) and (0.3, 0); targets (0.1, 0) and (-0.9, 0), max_distance 0.15. The
    cheapest assignment overall pairs (0.1, 0) with the far disc (0.2 m, gated away); the match
    within reach, (0.1, 0) with the disc at the origin (0.1 m), must win instead."""
    image = -(de.mesh.disc_fraction(mesh, (0.0, 0.0), 0.08) + de.mesh.disc_fraction(mesh, (0.3, 0.0), 0.08))
    figures = metrics.target_figures(mesh, image, [(0.1, 0.0), (-0.9, 0.0)], max_distance=0.15)
    np.testing.assert_array_equal(figures.matched, [True, False])
    assert figures.position_error[0] == pytest.approx(0.1, abs=0.01) and figures.n_artifacts == 1


def test_components_connect_through_edges_not_corners():
    """Two pixels touching at a corner are two components; sharing an edge, one."""
    mesh = de.mesh.rectangle(1.0, 1.0, 16, electrode_width=0.05, h=0.2)
    grid = pixel_grid(mesh, 4)
    image = np.zeros((4, 4))
    image[1, 1] = image[2, 2] = 1.0
    assert metrics.amplitude_components(grid, image).count == 2
    image[1, 2] = 1.0
    components = metrics.amplitude_components(grid, image)
    assert components.count == 1 and components.areas[0] == pytest.approx(3 / 16)


def test_the_half_amplitude_set_is_on_the_peaks_side(mesh):
    """A negative peak with a positive lobe of 90% of its magnitude: only the negative side."""
    image = _cone(mesh, (0.4, 0.0), 0.3, height=-1.0) + _cone(mesh, (-0.4, 0.0), 0.3, height=0.9)
    chosen = metrics.half_amplitude_set(image)
    assert np.all(image[chosen] <= 0.5 * image.min()) and np.all(mesh.element_centroids[chosen, 0] > 0)
    assert metrics.peak(image) == pytest.approx(image.min())
    assert metrics.count_artifacts(mesh, image, (0.4, 0.0)) == 0
    quarter = metrics.amplitude_set(image, 0.25)
    assert np.all(quarter >= chosen) and quarter.sum() > chosen.sum()


def test_greit_figures_of_a_perfect_image_and_of_a_ringing_one(mesh):
    """Truth itself: AR 1, PE 0, RES sqrt(A_q / A_0), SD 0, RNG 0. The same disc with a halo of
    -10% in 0.25 < |x - c| < 0.35: AR drops by the halo's integral, RNG is the halo's integral
    over the disc's, 0.1 (0.35^2 - 0.25^2) / 0.2^2 = 0.15."""
    centre = (0.5, 0.0)
    truth = de.mesh.disc_fraction(mesh, centre, 0.2)
    perfect = metrics.greit_figures(mesh, truth, centre, truth)
    assert perfect.amplitude_response == pytest.approx(1.0)
    assert abs(perfect.radial_position_error) < 0.005 and perfect.ringing == 0
    area = mesh.element_areas[truth >= 0.25].sum()
    assert perfect.resolution == pytest.approx(np.sqrt(area / mesh.element_areas.sum()))
    assert perfect.shape_deformation < 0.06
    distance = _distance(mesh, centre)
    halo = -0.1 * ((distance > 0.25) & (distance < 0.35))
    ringing = metrics.greit_figures(mesh, truth + halo, centre, truth)
    assert ringing.ringing == pytest.approx(0.15, rel=0.05)  # measured 0.155
    assert ringing.amplitude_response == pytest.approx(1 - 0.15, rel=0.01)
    # Pulled towards the middle by 0.1 m: PE = +0.1 (Adler et al.'s sign).
    inward = metrics.greit_figures(mesh, de.mesh.disc_fraction(mesh, (0.4, 0.0), 0.2), centre, truth)
    assert inward.radial_position_error == pytest.approx(0.1, abs=0.01)


def test_metrics_on_pixels_agree_with_elements(mesh):
    image = _cone(mesh)
    grid = pixel_grid(mesh, 64)
    pixels = grid.render(image)
    assert pixels.shape == (64, 64) and np.all(np.isnan(pixels[~grid.mask])) and np.all(np.isfinite(pixels[grid.mask]))
    assert metrics.equivalent_radius(grid, pixels) == pytest.approx(metrics.equivalent_radius(mesh, image), rel=0.03)
    assert metrics.position_error(grid, pixels, (0.2, 0.1)) < 0.01
    assert metrics.shape_deformation(grid, pixels) < 0.05
    assert metrics.integral(grid, pixels) == pytest.approx(metrics.integral(mesh, image), rel=1e-3)
    assert metrics.peak(pixels[grid.mask]) == pytest.approx(metrics.peak(image), rel=0.05)
    section = metrics.cross_section(grid, pixels)
    assert section.distance[np.argmin(section.values)] == pytest.approx(0.0, abs=0.04)


def test_render_is_an_exact_area_weighted_mean(mesh):
    """Constants stay constant; with every overlapping pixel kept the integral is conserved to
    rounding; a batch renders frame by frame; the grid is GREIT's."""
    grid = pixel_grid(mesh, (20, 30), min_coverage=0.0)
    assert grid.shape == (20, 30) and grid.pixel_centres.shape == (20, 30, 2)
    np.testing.assert_allclose(grid.render(np.full(mesh.n_elements, 0.01))[grid.mask], 0.01, rtol=1e-12)
    image = np.random.default_rng(0).standard_normal(mesh.n_elements)
    pixels = grid.render(image)
    assert np.nansum(pixels * grid.pixel_areas) == pytest.approx(mesh.element_areas @ image, rel=1e-10, abs=1e-12)
    assert grid.pixel_areas.sum() == pytest.approx(mesh.element_areas.sum(), rel=1e-12)
    batch = grid.render(np.stack([image, 2 * image]))
    assert batch.shape == (2, 20, 30)
    np.testing.assert_allclose(batch[1], 2 * pixels, equal_nan=True)
    np.testing.assert_allclose(render(mesh, image, grid=(20, 30), min_coverage=0.0), pixels, equal_nan=True)
    # A pixel whose four corners lie in one triangle lies wholly in it: it takes its value.
    coarse = de.mesh.disc(16, electrode_width=0.2, h=0.3)
    coarse_grid = pixel_grid(coarse, 50)
    values = np.arange(coarse.n_elements, dtype=float)
    finder = matplotlib.tri.Triangulation(*coarse.nodes.T, coarse.triangles).get_trifinder()
    x, y = np.meshgrid(coarse_grid.x_edges, coarse_grid.y_edges)
    corner = finder(x, y)
    owner = corner[:-1, :-1]
    whole = (owner >= 0) & (owner == corner[1:, :-1]) & (owner == corner[:-1, 1:]) & (owner == corner[1:, 1:])
    assert whole.sum() > 500
    np.testing.assert_allclose(coarse_grid.render(values)[whole], values[owner[whole]], rtol=1e-12)


def test_pixels_back_to_elements_conserve_the_integral(mesh):
    """`to_elements` is the area-weighted adjoint of `render`: constants stay constant, the
    integral over the covered area is conserved, a batch maps frame by frame, and an element
    under pixels of one value takes that value."""
    grid = pixel_grid(mesh, (20, 30), min_coverage=0.0)
    np.testing.assert_allclose(grid.to_elements(np.full(grid.shape, 0.01)), 0.01, rtol=1e-12)
    pixels = np.where(grid.mask, np.random.default_rng(2).standard_normal(grid.shape), np.nan)
    elements = grid.to_elements(pixels)
    assert elements.shape == (mesh.n_elements,)
    assert mesh.element_areas @ elements == pytest.approx(np.nansum(pixels * grid.pixel_areas), rel=1e-10)
    np.testing.assert_allclose(grid.to_elements(np.stack([pixels, -pixels]))[1], -elements, rtol=1e-12)
    smooth = mesh.element_centroids[:, 0] + 2 * mesh.element_centroids[:, 1]
    back = grid.to_elements(grid.render(smooth))
    inner = np.linalg.norm(mesh.element_centroids, axis=1) < 0.8 * np.linalg.norm(mesh.nodes, axis=1).max()
    np.testing.assert_allclose(back[inner], smooth[inner], atol=0.15)
    with pytest.raises(ValueError, match=r"pixel image has shape \(20, 29\)"):
        grid.to_elements(pixels[:, :-1])
    with pytest.raises(ValueError, match="pixel image is not finite"):
        grid.to_elements(np.where(grid.mask, np.inf, 0.0))


def test_the_pixel_grid_is_greits():
    model = de.ForwardModel(de.mesh.disc(16, electrode_width=0.2, h=0.15), de.protocol.adjacent(16), 0.01)
    greit = de.inverse.GREIT(model, grid=16, n_targets=20)
    grid = pixel_grid(model.mesh, 16)
    np.testing.assert_array_equal(grid.mask, greit.grid.mask)
    np.testing.assert_allclose(grid.pixel_areas, greit.grid.pixel_areas, rtol=1e-12)
    np.testing.assert_allclose(grid.pixel_centres, greit.grid.pixel_centres, rtol=1e-12)
    values = np.random.default_rng(1).standard_normal(model.n_elements)
    np.testing.assert_allclose(grid.render(values)[grid.mask], greit.grid.render(values)[grid.mask], rtol=1e-12)


def test_bad_images_are_refused(mesh):
    image = _cone(mesh)
    with pytest.raises(ValueError, match=rf"shape \(10,\); expected \({mesh.n_elements},\)"):
        metrics.position_error(mesh, image[:10], (0, 0))
    with pytest.raises(ValueError, match="not finite"):
        metrics.reconstructed_area(mesh, np.where(np.arange(mesh.n_elements) == 3, np.nan, image))
    with pytest.raises(ValueError, match=r"all zero.*no half-amplitude set"):
        metrics.half_amplitude_centroid(mesh, np.zeros(mesh.n_elements))
    with pytest.raises(ValueError, match="all zero"):
        metrics.peak(np.zeros(3))
    with pytest.raises(ValueError, match="empty"):
        metrics.peak(np.zeros(0))
    with pytest.raises(ValueError, match=r"centres must be one point \(x, y\) or a list"):
        metrics.target_figures(mesh, image, [(0, 0, 0)])
    with pytest.raises(ValueError, match=r"centre must be one point \(x, y\); got 2 points"):
        metrics.position_error(mesh, image, [(0.5, 0.0), (0.0, 0.0)])
    with pytest.raises(ValueError, match=r"through must be one point"):
        metrics.cross_section(mesh, image, through=[(0.5, 0.0), (0.0, 0.0)])
    with pytest.raises(ValueError, match="centre must be finite"):
        metrics.position_error(mesh, image, (np.nan, 0))
    with pytest.raises(ValueError, match=r"fraction of the peak must be in \(0, 1\]"):
        metrics.amplitude_set(image, 0.0)
    with pytest.raises(ValueError, match="max_distance must be positive"):
        metrics.target_figures(mesh, image, (0, 0), max_distance=0)
    with pytest.raises(ValueError, match="truth has shape"):
        metrics.correlation(mesh, image[:-1], image)
    with pytest.raises(ValueError, match="constant image"):
        metrics.correlation(mesh, image, np.ones(mesh.n_elements))
    with pytest.raises(ValueError, match="truth integrates to 0"):
        metrics.greit_figures(mesh, image, (0, 0), np.zeros(mesh.n_elements))
    radius = _distance(mesh, (0.0, 0.0))  # a ring whose equal-area disc holds an opposite-sign core
    ring = 1.0 * ((radius > 0.5) & (radius < 0.6)) - 0.2 * (radius < 0.3)
    with pytest.raises(ValueError, match="ringing is undefined"):
        metrics.greit_figures(mesh, ring, (0, 0), 1.0 * ((radius > 0.5) & (radius < 0.6)))
    with pytest.raises(ValueError, match="direction must be a finite non-zero"):
        metrics.cross_section(mesh, image, direction=(0, 0))
    with pytest.raises(ValueError, match="misses the domain"):
        metrics.cross_section(mesh, image, through=(5.0, 5.0))
    with pytest.raises(ValueError, match=r"geometry must be a diffeit\.Mesh or a diffeit\.render\.PixelGrid"):
        metrics.reconstructed_area(object(), image)
    grid = pixel_grid(mesh, 8)
    with pytest.raises(ValueError, match=r"expected \(8, 8\), one value a pixel"):
        metrics.reconstructed_area(grid, np.ones((8, 9)))
    with pytest.raises(ValueError, match="element image has shape"):
        grid.render(image[:-1])
    with pytest.raises(ValueError, match="element image is not finite"):
        grid.render(np.full(mesh.n_elements, np.inf))
    with pytest.raises(ValueError, match="grid must be a positive integer"):
        pixel_grid(mesh, 0)
    with pytest.raises(ValueError, match="min_coverage"):
        pixel_grid(mesh, 8, min_coverage=1.0)
