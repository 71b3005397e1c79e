"""GREIT: position error and amplitude on a pixel grid, uniformity over the domain, batches,
validation, noise figure, and the linearised training against the nonlinear one."""

import jax.numpy as jnp
import numpy as np
import pytest

import diffeit as de
from diffeit.inverse.greit import GREIT
from diffeit.render import pixel_grid

NOISE_PERCENT = 1.0
TARGET_RADIUS = 0.2  # m, on the unit disc
CONTRAST = 10.0  # sigma_target / sigma_background
# Measured with the default settings (hyperparameter 0.3, 500 targets, blur 0.15) on these
# meshes, seeds 0-2: position errors 0.004-0.020 m at every position below, spread over the
# positions 0.014-0.015 m; image integrals 0.195-0.227 (the linearised 9 * pi 0.2^2 = 1.13 is
# shrunk by the nonlinear response of a 10x disc, 2 * 9 / 11 / 9). Thresholds allow 2-3x.
POSITION_ERROR_LIMIT = 0.05
POSITION_ERROR_SPREAD_LIMIT = 0.035
INTEGRAL_RANGE = (0.15, 0.28)
POSITIONS = [(0.0, 0.0), (0.25, 0.0), (0.5, 0.0), (0.7, 0.0), (0.0, 0.5), (-0.35, -0.35), (0.35, -0.6)]


@pytest.fixture(scope="module")
def model() -> de.ForwardModel:
    """The training (reconstruction) model: coarser than the data's."""
    return de.ForwardModel(de.mesh.disc(16, electrode_width=0.2, h=0.08), de.protocol.adjacent(16), 0.01)


@pytest.fixture(scope="module")
def data_model() -> de.ForwardModel:
    return de.ForwardModel(de.mesh.disc(16, electrode_width=0.2, h=0.05), de.protocol.adjacent(16), 0.01)


@pytest.fixture(scope="module")
def rec(model) -> GREIT:
    return GREIT(model)


@pytest.fixture(scope="module")
def simulate(data_model):
    """dV (volts) of a disc target on the finer data mesh, with the README's p% noise, seeded."""
    mesh = data_model.mesh
    reference = np.asarray(data_model.measure(jnp.ones(mesh.n_elements)))
    noise_std = NOISE_PERCENT / 100 * np.sqrt(np.mean(reference**2))

    def run(centre, contrast=CONTRAST, seed=0):
        sigma = 1 + (contrast - 1) * de.mesh.disc_fraction(mesh, centre, TARGET_RADIUS)
        difference = np.asarray(data_model.measure(jnp.asarray(sigma))) - reference
        return difference + noise_std * np.random.default_rng(seed).standard_normal(difference.shape)

    return run


def test_grid_mask_and_areas(rec, model):
    grid = rec.grid
    assert rec.shape == grid.shape == (32, 32) and rec.matrix.shape == (32 * 32, model.n_measurements)
    centres = grid.pixel_centres
    assert np.all(np.diff(centres[..., 0], axis=1) > 0) and np.all(np.diff(centres[..., 1], axis=0) > 0)
    x_min, x_max, y_min, y_max = grid.extent
    assert np.allclose(centres[0, 0], [x_min + (x_max - x_min) / 64, y_min + (y_max - y_min) / 64])  # row 0: bottom
    # Pixels wholly inside the disc are wholly covered; the image covers the disc to within its rim.
    pixel_area = (x_max - x_min) * (y_max - y_min) / 32**2
    assert np.all(grid.pixel_areas <= pixel_area * (1 + 1e-9))
    assert np.allclose(grid.pixel_areas[np.linalg.norm(centres, axis=2) < 0.9], pixel_area, rtol=1e-6)
    assert grid.pixel_areas.sum() == pytest.approx(model.mesh.element_areas.sum(), rel=0.02)
    assert np.all(grid.pixel_areas[~grid.mask] == 0) and np.all(np.asarray(rec.matrix)[~grid.mask.ravel()] == 0)
    # A constant element field is that constant on every image pixel (the weights sum to 1).
    ones = grid.render(np.ones(model.n_elements))
    assert np.allclose(ones[grid.mask], 1) and np.all(np.isnan(ones[~grid.mask]))
    assert len(rec.target_centres) == 500 and np.all(np.linalg.norm(rec.target_centres, axis=1) < 0.95)


def test_target_at_half_radius(rec, simulate):
    image = np.asarray(rec.solve(simulate((0.5, 0.0))).stats["pixels"])
    assert image.shape == rec.shape and np.all(np.isfinite(image)) and np.all(image[~rec.grid.mask] == 0)
    error = de.metrics.position_error(rec.grid, image, (0.5, 0.0))
    assert error < POSITION_ERROR_LIMIT, error  # measured 0.010
    peak = np.unravel_index(np.argmax(np.abs(image)), image.shape)
    assert de.metrics.peak(image) == image[peak] > 0  # more conductive: a positive change
    assert np.linalg.norm(rec.grid.pixel_centres[peak] - [0.5, 0.0]) < 0.1
    # A less conductive target images with the opposite sign, at the same place.
    darker = np.asarray(rec.solve(simulate((0.5, 0.0), contrast=0.3)).stats["pixels"])
    assert de.metrics.peak(darker) < 0
    assert de.metrics.position_error(rec.grid, darker, (0.5, 0.0)) < POSITION_ERROR_LIMIT


def test_uniform_over_positions(rec, model, simulate):
    """GREIT's aim: the same position error and amplitude response everywhere, centre and rim.
    The metrics of diffeit.metrics apply on GREIT's grid, which `pixel_grid` builds alike."""
    grid = pixel_grid(model.mesh, rec.shape)
    np.testing.assert_array_equal(grid.mask, rec.grid.mask)
    assert abs(grid.element_to_pixel - rec.grid.element_to_pixel).max() == 0
    images = [np.asarray(rec.solve(simulate(c, seed=i)).stats["pixels"]) for i, c in enumerate(POSITIONS)]
    errors = np.array([de.metrics.position_error(grid, image, c) for image, c in zip(images, POSITIONS, strict=True)])
    assert np.all(errors < POSITION_ERROR_LIMIT), errors
    assert np.ptp(errors) < POSITION_ERROR_SPREAD_LIMIT, errors
    integrals = np.array([de.metrics.integral(grid, image) for image in images])  # S/sq m^2
    assert np.all((INTEGRAL_RANGE[0] < integrals) & (integrals < INTEGRAL_RANGE[1])), integrals
    assert integrals.max() / integrals.min() < 1.3, integrals


def test_batch_equals_frames(rec, simulate):
    frames = np.stack([simulate(c, seed=i) for i, c in enumerate(POSITIONS[:3])])
    solution = rec.solve(frames)
    batch = np.asarray(solution.stats["pixels"])
    assert batch.shape == (3, *rec.shape) and de.results.names(solution.result) == ["successful"] * 3
    # The value is on the mesh's elements: the pixels averaged onto them by their overlap areas.
    np.testing.assert_allclose(solution.value, rec.grid.to_elements(batch), rtol=1e-10, atol=1e-12)
    for frame, image, elements in zip(frames, batch, solution.value, strict=True):
        alone = rec.solve(frame)
        np.testing.assert_allclose(image, np.asarray(alone.stats["pixels"]), rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(elements, np.asarray(alone.value), rtol=1e-12, atol=1e-15)


def test_jit_and_vmap_give_the_eager_images(rec, simulate):
    """GREIT reconstructs under jit and vmap, as OneStep does: the same images, in the input's
    dtype (float32 in, float32 out)."""
    import jax

    frames = jnp.asarray(np.stack([simulate(c, seed=i) for i, c in enumerate(POSITIONS[:3])]))
    eager = rec.solve(frames)
    for solution in (jax.jit(rec.solve)(frames), jax.vmap(rec.solve)(frames)):
        for name in ("value", "pixels"):
            got, expected = (x.value if name == "value" else x.stats["pixels"] for x in (solution, eager))
            np.testing.assert_allclose(np.asarray(got), np.asarray(expected), rtol=1e-12, atol=1e-15)
    single = rec.solve(frames[0].astype(jnp.float32))
    assert single.value.dtype == single.stats["pixels"].dtype == jnp.float32
    pixels = np.asarray(eager.stats["pixels"][0])
    np.testing.assert_allclose(np.asarray(single.stats["pixels"]), pixels, rtol=0, atol=1e-5 * np.abs(pixels).max())


def test_bad_voltages_are_refused(rec, model):
    n = model.n_measurements
    with pytest.raises(ValueError, match=r"shape \(207,\)"):
        rec.solve(np.zeros(n - 1))
    with pytest.raises(ValueError, match="expected"):
        rec.solve(np.zeros((2, 3, n)))
    frames = np.zeros((4, n))
    frames[1, 5], frames[3, 0] = np.nan, np.inf
    with pytest.raises(ValueError, match=r"frame\(s\) \[1, 3\]"):
        rec.solve(frames)
    with pytest.raises(ValueError, match=r"frame\(s\) \[0\]"):
        rec.solve(np.full(n, np.nan))
    with pytest.raises(ValueError, match="shape"):
        de.metrics.position_error(rec.grid, np.zeros((3, 3)), (0, 0))


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"hyperparameter": 0.0}, "hyperparameter must be finite and positive"),
        ({"hyperparameter": np.nan}, "hyperparameter must be finite and positive"),
        ({"hyperparameter": 0.1, "noise_figure": 0.5}, "not both"),
        ({"noise_figure": -1.0}, "noise_figure must be finite and positive"),
        ({"grid": 1}, "grid must be"),
        ({"grid": (32, 32, 2)}, "grid must be"),
        ({"target_radius": 0.0}, "target_radius"),
        ({"blur": 1.5}, "blur"),
        ({"n_targets": 0}, "n_targets"),
        ({"training": "exact"}, "training must be"),
        ({"contrast": -1.0}, "contrast"),
        ({"background": -1.0}, "background"),
        ({"background": np.ones(3)}, "background has shape"),
        ({"target_radius": 0.99}, "could not place"),
    ],
)
def test_bad_settings_are_refused(model, options, message):
    with pytest.raises(ValueError, match=message):
        GREIT(model, **options)


def test_finite_for_extreme_hyperparameters(model, simulate):
    difference = simulate((0.5, 0.0))
    for hyperparameter in (1e-8, 1e-4, 1e-1, 1e3):
        rec = GREIT(model, hyperparameter=hyperparameter, n_targets=200)
        assert np.all(np.isfinite(np.asarray(rec.matrix))), hyperparameter
        image = np.asarray(rec.solve(difference).stats["pixels"])
        assert np.all(np.isfinite(image)) and np.any(image != 0), hyperparameter
        assert np.isfinite(rec.noise_figure) and rec.noise_figure > 0


def test_noise_figure_chooses_the_hyperparameter(model, rec):
    assert rec.hyperparameter == 0.3 and rec.noise_figure == pytest.approx(0.873, rel=0.02)
    chosen = GREIT(model, noise_figure=0.5)
    assert chosen.noise_figure == pytest.approx(0.5, rel=1e-6)
    assert chosen.hyperparameter == pytest.approx(0.72, rel=0.02)  # more regularised than the default
    same = GREIT(model, hyperparameter=chosen.hyperparameter)
    np.testing.assert_allclose(np.asarray(same.matrix), np.asarray(chosen.matrix))
    with pytest.raises(ValueError, match="out of reach"):
        GREIT(model, noise_figure=0.1)  # the smallest on this disc is about 0.28


@pytest.mark.slow
def test_unit_free_in_the_drive_current(model, simulate):
    """Voltages scale with the drive current; the normalised problem, hence the image, does not."""
    strong = de.ForwardModel(model.mesh, model.protocol, 0.01, drive_current=1.0)
    difference = simulate((0.0, 0.5))
    image = np.asarray(GREIT(model, n_targets=200).solve(difference).stats["pixels"])
    scaled = np.asarray(GREIT(strong, n_targets=200).solve(difference * 1e3).stats["pixels"])
    np.testing.assert_allclose(scaled, image, rtol=1e-8, atol=1e-10 * np.abs(image).max())


@pytest.mark.slow
def test_nonlinear_training_matches_linearised_for_small_contrast(small_model):
    options = {"n_targets": 50, "grid": 12}
    linearised = np.asarray(GREIT(small_model, **options).matrix)
    nonlinear = np.asarray(GREIT(small_model, training="nonlinear", contrast=1e-3, **options).matrix)
    assert np.linalg.norm(nonlinear - linearised) / np.linalg.norm(linearised) < 2e-3


def test_rectangle_with_rectangular_grid():
    mesh = de.mesh.rectangle(2.0, 1.0, 16, electrode_width=0.15, h=0.15)
    model = de.ForwardModel(mesh, de.protocol.adjacent(16), 0.01)
    rec = GREIT(model, grid=(12, 24), n_targets=200, background=0.01)
    assert rec.shape == (12, 24) and np.all(rec.grid.mask)  # the grid is the rectangle itself
    assert rec.grid.pixel_areas.sum() == pytest.approx(2.0, rel=1e-9)
    centre = (0.4, 0.1)
    sigma = 0.01 * (1 - 0.5 * de.mesh.disc_fraction(mesh, centre, 0.15))
    image = np.asarray(
        rec.solve(model.measure(jnp.asarray(sigma)) - model.measure(jnp.full(mesh.n_elements, 0.01))).stats["pixels"]
    )
    assert de.metrics.peak(image) < 0
    assert de.metrics.position_error(rec.grid, image, centre) < 0.1


def test_a_design_for_a_noise_figure_is_kept_when_bound(model):
    """Built without a model, GREIT keeps its design (a noise figure, or a hyperparameter) and
    trains on the model it is bound to, as `diffeit.reconstruct` binds it."""
    settings = GREIT(noise_figure=0.5, n_targets=200, grid=16)
    assert settings.model is None and settings.shape == (16, 16) and settings.hyperparameter is None
    with pytest.raises(ValueError, match="has no model"):
        settings.solve(np.zeros(model.n_measurements))
    bound = settings.bound(model, 2.0)
    assert bound.noise_figure == pytest.approx(0.5, rel=1e-6) and bound.shape == (16, 16)
    np.testing.assert_allclose(bound.problem.background, 2.0)
    fixed = bound.bound(model, hyperparameter=0.3)
    assert fixed.hyperparameter == 0.3 and not fixed.by_noise_figure
    assert fixed.bound(model).hyperparameter == 0.3
