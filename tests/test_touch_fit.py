"""diffeit.touch, method="fit": discs fitted to the voltages through the calibrated model,
started from the image method's touches, with standard errors."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import diffeit as de
from diffeit.calibration import PositionMap
from diffeit.scene import Disc, FoamStack, shape_fraction
from diffeit.touch import FIT_LEVEL

PROTOCOL = de.protocol.adjacent(16)


def calibrated(mesh: de.Mesh) -> de.calibration.SkinCalibration:
    """`mesh` with contact impedances spread, calibrated on 10 untouched frames with noise of
    1e-3 of the RMS reading (the calibration knows it)."""
    rng = np.random.default_rng(7)
    truth = de.ForwardModel(mesh, PROTOCOL, contact_impedance=0.01 * np.exp(rng.uniform(-0.5, 0.5, 16)))
    reference = 1e3 * np.asarray(truth.measure(jnp.ones(mesh.n_elements)))
    frames = reference + 1e-3 * np.sqrt(np.mean(reference**2)) * rng.standard_normal((10, len(reference)))
    recording = de.io.Recording(
        frames=frames, times=np.arange(10.0), protocol=PROTOCOL, mesh=mesh, voltage_unit="arbitrary"
    )
    return de.calibrate(recording)


@pytest.fixture(scope="module")
def calibration():
    """A coarse skin (about 900 triangles), `calibrated`."""
    return calibrated(de.mesh.disc(16, electrode_width=0.2, h=0.1))


def recorded(calibration, signed: np.ndarray) -> np.ndarray:
    """Recorded frames (..., M) whose `calibration.signed` is `signed` (..., M_used)."""
    frames = np.ones((*signed.shape[:-1], PROTOCOL.n_measurements))
    frames[..., calibration.used] = signed * np.asarray(calibration.readout.gains)
    return frames * calibration.reading_sign


def session(calibration, presses, seed: int):
    """A reconstructed recording of one frame per press (a list of discs (centre, radius,
    depth) each), simulated with the calibrated model itself (the fit's own smooth disc),
    with the calibration's noise."""
    rng = np.random.default_rng(seed)
    model, level = calibration.model, calibration.conductivity
    mesh = model.mesh
    base = np.asarray(model.measure(jnp.full(mesh.n_elements, level)))
    frames = []
    for discs in presses:
        change = sum(
            depth * np.asarray(shape_fraction(mesh, Disc(jnp.asarray(centre), radius), level=FIT_LEVEL))
            for centre, radius, depth in discs
        )
        voltages = np.asarray(model.measure(jnp.asarray(level * (1 + change))))
        frames.append(voltages + calibration.noise * rng.standard_normal(len(voltages)))
    recording = de.io.Recording(
        frames=recorded(calibration, np.array(frames)),
        times=np.arange(float(len(frames))),
        protocol=PROTOCOL,
        mesh=mesh,
        reference=recorded(calibration, base),
        voltage_unit="arbitrary",
    )
    return de.reconstruct(recording, calibration=calibration, difference="calibrated", progress=False)


SINGLE = [
    ((0.35, 0.2), 0.16, -0.3),
    ((-0.45, 0.1), 0.14, -0.35),
    ((0.05, -0.4), 0.18, -0.25),
    ((-0.25, -0.3), 0.15, -0.3),
]


@pytest.fixture(scope="module")
def single(calibration):
    return session(calibration, [[press] for press in SINGLE], seed=1)


def test_a_fitted_disc_is_where_the_simulated_one_was_closer_than_the_image_says(calibration, single):
    image = de.touches(single, calibration)
    fitted = de.touches(single, calibration, method="fit")
    assert image.standard_errors is None and image.misfit is None
    assert fitted.count.tolist() == [1] * len(SINGLE)
    truth = np.array([[*centre, radius, depth] for centre, radius, depth in SINGLE])
    found = np.concatenate([fitted.position[:, 0], fitted.radius[:, :1], fitted.depth[:, :1]], axis=1)
    errors = fitted.standard_errors[:, 0]
    distance = np.linalg.norm(found[:, :2] - truth[:, :2], axis=1)
    assert np.all(distance < 0.008), distance  # metres, on a disc of radius 1 m: 2 to 3 standard errors
    assert np.all(distance < np.linalg.norm(image.position[:, 0] - truth[:, :2], axis=1))
    np.testing.assert_allclose(found[:, 2], truth[:, 2], rtol=0.3)
    assert np.all(np.isfinite(errors)) and np.all(errors > 0)
    assert np.all(np.abs(found - truth) < 3 * errors), (found - truth) / errors
    assert np.all(fitted.misfit < 0.3)
    np.testing.assert_array_equal(fitted.noise, image.noise)
    assert "+-" in fitted.lines(0)[0]


def test_on_a_forearm_the_fitted_discs_are_points_on_its_surface_near_the_simulated_ones():
    """A cylinder patch (a 40 mm forearm, 784 triangles): the discs' centres move in the
    surface's tangent plane at the image's touch and come back onto the surface, within three
    of their standard errors of the simulated centres, closer than the image's touches
    (measured 0.3 and 0.1 mm off, standard errors 0.1-0.2 mm; the image's 1.3 and 0.8 mm)."""
    rho = 0.04
    calibration = calibrated(de.mesh.cylinder_patch(rho, 0.15, np.radians(150), 16, 0.008))
    presses = [((rho * np.cos(a), rho * np.sin(a), z), 0.012, -0.3) for a, z in ((0.3, 0.02), (-0.6, -0.03))]
    images = session(calibration, [[press] for press in presses], seed=3)
    image = de.touches(images, calibration)
    fitted = de.touches(images, calibration, method="fit")
    assert fitted.count.tolist() == [1, 1] and fitted.position.shape == (2, 6, 3)
    points = fitted.position[:, 0]
    np.testing.assert_allclose(np.hypot(points[:, 0], points[:, 1]), rho, rtol=0.01)  # the mesh's chords
    centres = np.array([centre for centre, _, _ in presses])
    distance = np.linalg.norm(points - centres, axis=1)
    assert np.all(distance < np.linalg.norm(image.position[:, 0] - centres, axis=1)), distance
    errors = fitted.standard_errors[:, 0]
    assert np.all(np.isfinite(errors)) and np.all(errors > 0)
    assert np.all(distance < 3 * np.linalg.norm(errors[:, :2], axis=1)), (distance, errors)
    np.testing.assert_allclose(fitted.radius[:, 0], 0.012, rtol=0.3)
    np.testing.assert_allclose(fitted.depth[:, 0], -0.3, rtol=0.3)
    # A position map that turns the forearm about its axis by 0.2 rad (fitted on points of the
    # surface): the centres turn with it and stay on the surface (to its chords, 0.2 mm), and
    # their errors' size (the trace of their covariance, whatever the axes) is kept.
    turn = np.array([[np.cos(0.2), -np.sin(0.2), 0.0], [np.sin(0.2), np.cos(0.2), 0.0], [0.0, 0.0, 1.0]])
    on = calibration.model.mesh.element_centroids[::25]
    with pytest.raises(ValueError, match="needs the skin's"):
        PositionMap.fit(on, on @ turn.T)
    mapping = PositionMap.fit(on, on @ turn.T, calibration.model.mesh)
    assert mapping.degree is not None and mapping.errors[str(mapping.degree)] < 5e-4
    mapped = eqx.tree_at(lambda c: c.position_map, calibration, mapping, is_leaf=lambda x: x is None)
    moved = de.touches(images, mapped, method="fit")
    np.testing.assert_allclose(moved.position[:, 0], points @ turn.T, atol=5e-4)
    np.testing.assert_allclose(np.hypot(moved.position[:, 0, 0], moved.position[:, 0, 1]), rho, rtol=0.01)
    sizes = [np.linalg.norm(e[:, 0, :2], axis=1) for e in (moved.standard_errors, fitted.standard_errors)]
    np.testing.assert_allclose(*sizes, rtol=0.05)


def test_two_separated_discs_are_both_recovered(calibration):
    presses = [((0.45, 0.15), 0.17, -0.3), ((-0.35, -0.35), 0.17, -0.3)]
    images = session(calibration, [presses], seed=2)
    fitted = de.touches(images, calibration, method="fit")
    assert fitted.count.tolist() == [2]
    for centre, radius, depth in presses:
        k = int(np.argmin(np.linalg.norm(fitted.position[0, :2] - centre, axis=1)))
        assert np.linalg.norm(fitted.position[0, k] - centre) < 0.01
        np.testing.assert_allclose(fitted.radius[0, k], radius, rtol=0.3)
        np.testing.assert_allclose(fitted.depth[0, k], depth, rtol=0.3)
    assert np.all(np.isnan(fitted.standard_errors[0, 2:]))


def test_the_position_map_moves_the_fitted_centres_and_their_errors(calibration, single):
    # A map that scales by 2 and shifts: positions mapped, position errors doubled.
    read = np.random.default_rng(0).uniform(-0.7, 0.7, (12, 2))
    mapping = PositionMap.fit(read, 2.0 * read + np.array([0.1, -0.2]))
    mapped = eqx.tree_at(lambda c: c.position_map, calibration, mapping, is_leaf=lambda x: x is None)
    plain = de.touches(single, calibration, method="fit")
    moved = de.touches(single, mapped, method="fit", stack=FoamStack())
    np.testing.assert_allclose(moved.position, 2.0 * plain.position + [0.1, -0.2], atol=1e-9)
    np.testing.assert_allclose(moved.standard_errors[..., :2], 2.0 * plain.standard_errors[..., :2], rtol=1e-6)
    np.testing.assert_allclose(moved.radius, plain.radius)
    assert moved.pressure is not None and np.all(moved.pressure[:, 0] > 0)


def test_a_touched_frames_last_disc_stays_however_weak(calibration, single, monkeypatch):
    """Every disc held insignificant (the threshold raised to 1e9 standard errors, as a model
    that misses a board's frames by far more than their noise makes it): a frame the voltage
    test found touched keeps its one disc, its centre held where the image put it (an
    insignificant disc's centre is not fitted). On the calibration benchmark's magnitude skins
    the single disc of 18-20 of 40 presses was dropped so, and those presses read as misses."""
    monkeypatch.setattr(de.touch, "SIGNIFICANCE", 1e9)
    image = de.touches(single, calibration)
    fitted = de.touches(single, calibration, method="fit")
    assert fitted.count.tolist() == [1] * len(SINGLE)
    np.testing.assert_allclose(fitted.position[:, 0], image.position[:, 0], atol=1e-12)
    assert np.all(np.isfinite(fitted.depth[:, 0])) and np.all(fitted.depth[:, 0] < 0)


def test_without_the_noise_the_errors_come_from_the_residual(calibration, single):
    unknown = eqx.tree_at(lambda c: c.noise, calibration, None)
    fitted = de.touches(single, unknown, method="fit", threshold=4.0)
    seen = fitted.count > 0
    assert seen.sum() >= 3
    errors = fitted.standard_errors[seen, 0]
    assert np.all(np.isfinite(errors)) and np.all(errors > 0)
    truth = np.array([centre for centre, _, _ in SINGLE])[seen]
    assert np.all(np.linalg.norm(fitted.position[seen, 0] - truth, axis=1) < 0.01)


def test_the_fit_needs_a_calibration_and_a_known_method(single):
    with pytest.raises(ValueError, match="needs a calibration"):
        de.touches(single, method="fit")
    with pytest.raises(ValueError, match="method must be one of"):
        de.touches(single, method="model")


def test_the_disc_fits_jacobian_matches_finite_differences_of_its_readings():
    """The disc fit's (M, 4K) Jacobian (the footprints' forward derivative times the model's
    adjoint conductivity Jacobian) against central differences of its readings, two discs."""
    from diffeit import touch as touch_module

    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.15)
    model = de.ForwardModel(mesh, de.protocol.adjacent(16), 0.01)
    fit = touch_module._DiscFit.of(model, 2.0)
    planes = jnp.asarray([[[0.3, 0.1], [1.0, 0.0], [0.0, 1.0]], [[-0.4, -0.2], [0.0, 1.0], [-1.0, 0.0]]])
    theta = jnp.asarray([[0.02, -0.03, 0.25, -0.3 * 0.25**2], [0.0, 0.05, 0.3, -0.2 * 0.3**2]])
    _, jacobian, _ = touch_module._disc_readings(fit, theta, planes)
    step = 1e-6
    columns = []
    for index in range(theta.size):
        unit = jnp.zeros(theta.size).at[index].set(step).reshape(theta.shape)
        above = np.asarray(touch_module._disc_readings(fit, theta + unit, planes)[0])
        below = np.asarray(touch_module._disc_readings(fit, theta - unit, planes)[0])
        columns.append((above - below) / (2 * step))
    np.testing.assert_allclose(
        np.asarray(jacobian), np.stack(columns, axis=1), rtol=0, atol=1e-6 * np.abs(jacobian).max()
    )


def test_without_presses_the_touches_polarity_is_the_one_their_images_show(calibration, single):
    """A calibration from the reference alone knows no polarity: raised and lowered presses
    are both read where they are, with the sign of their change, by either method."""
    assert calibration.polarity is None
    raised = session(calibration, [[(centre, radius, -depth)] for centre, radius, depth in SINGLE], seed=4)
    truth = np.array([centre for centre, _, _ in SINGLE])
    for images, sign in ((raised, 1), (single, -1)):
        for method in ("image", "fit"):
            found = de.touches(images, calibration, method=method)
            assert np.all(found.count >= 1) and np.all(np.sign(found.depth[:, 0]) == sign)
            assert np.all(np.linalg.norm(found.position[:, 0] - truth, axis=1) < 0.1)
    # Told the wrong sign, the image method reads the raised presses' ringing instead.
    wrong = de.touches(raised, calibration, polarity=-1)
    assert np.median(np.linalg.norm(wrong.position[:, 0] - truth, axis=1)) > 0.2


def test_the_voltage_test_looks_where_a_touch_puts_the_differences(calibration):
    """Weak presses (-10% over discs of radius 0.1 at the calibration's noise) and untouched
    frames: tested in the whitened Jacobian's leading subspace (31 of 208 readings' dimensions)
    every press is found and no untouched frame (measured z: presses 6.7 to 134, untouched under
    1.1); the sum over every reading misses presses (the centre's and another: z 0.8 and 2.6)."""
    from diffeit.touch import _noise_test, touch_subspace, touched

    rng = np.random.default_rng(11)
    model, level = calibration.model, calibration.conductivity
    mesh = model.mesh
    base = np.asarray(model.measure(jnp.full(mesh.n_elements, level)))
    centres = [(0.0, 0.0), (0.3, 0.2), (-0.5, 0.3), (0.1, -0.6), (-0.2, -0.2), (0.6, -0.1)]
    pressed = np.array(
        [
            np.asarray(model.measure(jnp.asarray(level * (1 - 0.1 * np.asarray(de.mesh.disc_fraction(mesh, c, 0.1))))))
            for c in centres
        ]
    )
    clean = np.concatenate([pressed, np.repeat(base[None], 40, axis=0)])
    frames = recorded(calibration, clean + calibration.noise * rng.standard_normal(clean.shape))
    reference = recorded(calibration, base)
    found = touched(frames, reference, calibration, reference_frames=10**6)
    assert found[: len(centres)].all() and not found[len(centres) :].any()
    subspace = touch_subspace(calibration)  # what `diffeit live` computes once for every batch
    assert subspace.shape == (208, 31) and np.allclose(subspace.T @ subspace, np.eye(31))
    again = touched(frames, reference, calibration, reference_frames=10**6, subspace=subspace)
    np.testing.assert_array_equal(again, found)
    dv = calibration.signed(frames) - calibration.signed(reference)
    everywhere = _noise_test(dv, calibration.noise, calibration.noise_frames, 10**6, de.touch.DETECTION)
    assert not everywhere[: len(centres)].all() and not everywhere[len(centres) :].any()
