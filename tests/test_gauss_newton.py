"""Gauss-Newton: absolute imaging of the issue's scene against pyEIT's reported figures, hard
cases, batches, difference imaging, joint contact impedance."""

import jax.numpy as jnp
import numpy as np
import pytest
from helpers import noisy

import diffeit as de
from diffeit.inverse import AbsoluteGaussNewton, GaussNewton, OneStep
from diffeit.results import RESULTS, SolverError, names

CENTRE, RADIUS, CONTRAST, BACKGROUND = (0.5, 0.0), 0.2, 10.0, 2.0
STOPS = (RESULTS.successful, RESULTS.max_iterations_reached, RESULTS.line_search_failed)


def _assert_sound(solution, background=None) -> None:
    """Finite, positive (the conductivity: `value`, or `background` + `value` for difference
    imaging), a never-rising objective, and a known stop."""
    conductivity = solution.value if background is None else background + solution.value
    assert np.all(np.isfinite(conductivity)) and np.all(conductivity > 0)
    stats = solution.stats
    histories = [stats["history"]] if np.ndim(stats["iterations"]) == 0 else list(stats["history"])
    known = np.any([np.atleast_1d(solution.result == stop) for stop in STOPS], axis=0)
    assert len(known) == len(histories) and np.all(known)
    for history in histories:
        assert np.all(np.isfinite(history)) and np.all(np.diff(history) <= 0), history


@pytest.fixture(scope="module")
def scene():
    """The issue's scene, absolute: data on 8,864 triangles, reconstruction on about 2,800,
    1% noise."""
    protocol = de.protocol.adjacent(16)
    fine = de.mesh.disc(16, electrode_width=0.2, h=0.03)
    inclusion = BACKGROUND * (1 + (CONTRAST - 1) * de.mesh.disc_fraction(fine, CENTRE, RADIUS))
    voltages = noisy(np.asarray(de.ForwardModel(fine, protocol).measure(jnp.asarray(inclusion))), 1.0, 0)
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.054)
    return de.ForwardModel(mesh, protocol), voltages, de.mesh.interpolate(inclusion, fine, mesh)


@pytest.mark.slow
def test_absolute_gauss_newton_finds_the_inclusion_and_the_background(scene):
    """pyEIT 1.2.4's 20-iteration gn() on this scene (the issue): position error 0.016,
    correlation 0.82, peak 3.8-4.7 of a true 10 (38-47%). Measured here: 0.007, 0.92, 62% of
    the peak, the background within 1%, stopped by the discrepancy principle."""
    model, voltages, truth = scene
    solution = AbsoluteGaussNewton(model, "laplace", 1e-2, noise=1.0).solve(voltages)
    _assert_sound(solution)
    assert solution.result == RESULTS.successful and solution.stats["reached_discrepancy"]
    mesh = model.mesh
    conductivity = solution.value
    outside = de.mesh.disc_fraction(mesh, CENTRE, RADIUS + 0.15) == 0
    background = np.average(conductivity[outside], weights=mesh.element_areas[outside])
    assert background == pytest.approx(BACKGROUND, rel=0.02)
    change = conductivity - background
    assert de.metrics.position_error(mesh, change, CENTRE) < 0.016
    assert de.metrics.correlation(mesh, truth, conductivity) > 0.82
    assert conductivity.max() / (CONTRAST * BACKGROUND) > 0.55  # pyEIT: at most 0.47
    # The start was the best homogeneous conductivity: near the background, below the mean.
    assert 0.9 * BACKGROUND < solution.stats["reference"][0] < 1.3 * BACKGROUND


@pytest.mark.parametrize("contrast", [1e-3, 1e3])
@pytest.mark.parametrize(
    "hyperparameter", [pytest.param(1e-8, marks=pytest.mark.slow), 1e-2, pytest.param(1e3, marks=pytest.mark.slow)]
)
def test_hard_contrasts_and_hyperparameters(contrast, hyperparameter):
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.1)
    fine = de.mesh.disc(16, electrode_width=0.2, h=0.07)
    protocol = de.protocol.adjacent(16)
    truth = 1 + (contrast - 1) * de.mesh.disc_fraction(fine, (0.3, 0.2), 0.3)
    voltages = np.asarray(de.ForwardModel(fine, protocol).measure(jnp.asarray(truth)))
    solver = AbsoluteGaussNewton(de.ForwardModel(mesh, protocol), "laplace", hyperparameter)
    solution = solver.solve(voltages, throw=False)
    _assert_sound(solution)
    stats = solution.stats
    assert stats["iterations"] >= 1 and len(stats["history"]) == stats["iterations"] + 1
    if hyperparameter == 1e3:  # regularised to the homogeneous start
        np.testing.assert_allclose(solution.value, stats["reference"], rtol=1e-3)


def test_float32_data_give_float32_results():
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.1)
    model = de.ForwardModel(mesh, de.protocol.adjacent(16))
    voltages = np.asarray(model.measure(jnp.asarray(1 + de.mesh.disc_fraction(mesh, (0.2, -0.3), 0.3))))
    solution = AbsoluteGaussNewton(model, "noser", 0.05).solve(voltages.astype(np.float32))
    _assert_sound(solution)
    assert solution.value.dtype == np.float32


@pytest.mark.slow
def test_a_batch_runs_every_frame_on_its_own_schedule():
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.1)
    model = de.ForwardModel(mesh, de.protocol.adjacent(16))
    frames = np.stack(
        [
            np.asarray(model.measure(jnp.asarray(1 + c * de.mesh.disc_fraction(mesh, (0.3, 0.2), 0.3))))
            for c in (0.0, 1.0, -0.5)
        ]
    )
    solver = AbsoluteGaussNewton(model, "laplace", 1e-2, noise=0.5)
    batch = solver.solve(frames)
    _assert_sound(batch)
    stats = batch.stats
    assert batch.value.shape == (3, mesh.n_elements) and len(stats["history"]) == 3
    assert stats["reached_discrepancy"][0] and stats["iterations"][0] == 0  # homogeneous: the start fits
    for k in range(3):
        alone = solver.solve(frames[k])
        np.testing.assert_allclose(batch.value[k], alone.value, rtol=1e-9)
        assert (batch.result == alone.result)[k]
        assert stats["reached_discrepancy"][k] == alone.stats["reached_discrepancy"]
        assert stats["iterations"][k] == alone.stats["iterations"]


def test_one_difference_step_is_the_one_step_reconstruction():
    """At a tiny contrast the first Gauss-Newton step from the background, with the same prior
    and hyperparameter, is OneStep's image (x = ln(sigma / background) = dsigma / background to
    first order): the two solvers share their normalisation."""
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.1)
    model = de.ForwardModel(mesh, de.protocol.adjacent(16))
    background = 2.0
    change = 1 + 1e-3 * de.mesh.disc_fraction(mesh, (0.3, 0.3), 0.2)
    dv = np.asarray(model.measure(jnp.asarray(background * change)) - model.measure(jnp.full(mesh.n_elements, 2.0)))
    solver = GaussNewton(model, "laplace", 0.05, background=background, max_iterations=1)
    step = solver.solve(dv, throw=False)
    assert step.stats["iterations"] == 1 and step.result == RESULTS.max_iterations_reached
    with pytest.raises(SolverError, match="Gauss-Newton: the iteration limit was reached"):
        solver.solve(dv)
    linear = np.asarray(OneStep(model, "laplace", 0.05, background=background).solve(dv).value) / background
    np.testing.assert_allclose(np.log1p(step.value / background), linear, atol=1e-8 * np.abs(linear).max())
    # Built without a model and bound to one, as `diffeit.reconstruct` does: the same step.
    bound = GaussNewton(prior="laplace", hyperparameter=0.05, max_iterations=1).bound(model, background)
    np.testing.assert_array_equal(bound.solve(dv, throw=False).value, step.value)


@pytest.mark.slow
def test_difference_imaging_of_a_strong_touch(scene):
    model, _, _ = scene
    mesh = model.mesh
    touch = 1 - 0.7 * de.mesh.disc_fraction(mesh, (-0.3, 0.4), 0.2)
    reference = model.measure(jnp.ones(mesh.n_elements))
    dv = noisy(np.asarray(model.measure(jnp.asarray(touch)) - reference), 0.1, 1)
    solution = GaussNewton(model, "laplace", 1e-2).solve(dv)
    _assert_sound(solution, background=1.0)
    change = solution.value
    assert de.metrics.peak(change) < 0
    assert de.metrics.position_error(mesh, change, (-0.3, 0.4)) < 0.05
    # The linearised image overshoots to a negative conductivity (measured: -1.03 S/sq on a
    # background of 1); the nonlinear one stays positive and nearer the true -0.7 (-0.63).
    linear = np.asarray(OneStep(model, "laplace", 1e-2).solve(dv).value)
    assert abs(change.min() + 0.7) < abs(linear.min() + 0.7)
    assert -0.8 < change.min() < -0.5


@pytest.mark.slow
def test_joint_contact_impedance_estimation():
    """With readings on driven electrodes (which depend on z most), per-electrode contact
    impedances spread by a factor e^0.4 are recovered alongside the conductivity."""
    protocol = de.protocol.adjacent(16, measure_driven=True)
    z_true = np.exp(np.random.default_rng(0).normal(np.log(0.02), 0.4, 16))
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.1)
    truth = 1 + 2 * de.mesh.disc_fraction(mesh, (-0.3, 0.2), 0.3)
    voltages = np.asarray(de.ForwardModel(mesh, protocol, jnp.asarray(z_true)).measure(jnp.asarray(truth)))
    model = de.ForwardModel(mesh, protocol, contact_impedance=0.02)
    joint = AbsoluteGaussNewton(model, "laplace", 1e-3, estimate_contact_impedance=True, max_iterations=30)
    joint = joint.solve(voltages)
    fixed = AbsoluteGaussNewton(model, "laplace", 1e-3, max_iterations=30).solve(voltages)
    _assert_sound(joint)
    assert joint.stats["misfit"] < 0.8 * fixed.stats["misfit"]  # measured 0.0013 against 0.0017
    contact_impedance = joint.stats["contact_impedance"]
    assert np.corrcoef(contact_impedance, z_true)[0, 1] > 0.9
    assert np.median(np.abs(contact_impedance / z_true - 1)) < 0.2
    np.testing.assert_array_equal(fixed.stats["contact_impedance"], 0.02)  # not estimated: the model's


def test_a_frame_equal_to_the_reference_is_fitted_at_once(small_model):
    """A zero difference (an untouched frame of noise-free data) is fitted by the start to
    rounding: successful in no steps, not a line search that cannot lower 1e-30."""
    touched = np.asarray(small_model.measure(1 + 0.5 * de.mesh.disc_fraction(small_model.mesh, (0.3, 0.2), 0.3)))
    untouched = np.asarray(small_model.measure(jnp.ones(small_model.n_elements)))
    solution = GaussNewton(small_model, "laplace", 0.05).solve(np.stack([0 * untouched, touched - untouched]))
    assert names(solution.result) == ["successful", "successful"]
    assert solution.stats["iterations"][0] == 0 and solution.stats["iterations"][1] > 0
    np.testing.assert_array_equal(solution.value[0], 0.0)


def test_bad_input_is_refused():
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.15)
    model = de.ForwardModel(mesh, de.protocol.adjacent(16))
    voltages = np.asarray(model.measure(jnp.ones(mesh.n_elements)))
    with pytest.raises(ValueError, match="hyperparameter must be finite and positive"):
        GaussNewton(model, "laplace", -1.0)
    with pytest.raises(ValueError, match=r"expected \(208,\)"):
        AbsoluteGaussNewton(model).solve(voltages[:100])
    with pytest.raises(ValueError, match=r"not finite \(NaN or inf\) in frame\(s\) \[0\]"):
        AbsoluteGaussNewton(model).solve(np.where(np.arange(208) == 3, np.nan, voltages))
    with pytest.raises(ValueError, match="do not correlate positively"):
        AbsoluteGaussNewton(model).solve(-voltages)
    with pytest.raises(ValueError, match="conductivity must be finite and positive"):
        GaussNewton(model, background=0.0)
    with pytest.raises(ValueError, match="conductivity must be finite and positive"):
        AbsoluteGaussNewton(model, initial=-1.0)
    with pytest.raises(ValueError, match="has no model"):
        GaussNewton().solve(voltages)
