"""diffeit.fit.background: the background map of a skin with two regions (the dissertation's
Fig. 5.6) from untouched frames simulated on a finer mesh with noise, touches reconstructed
against it, the noise estimates, the objective's gradient, bad input and result codes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffeit as de
from diffeit import fit
from diffeit.fit._background import _Objective
from diffeit.inverse import OneStep
from diffeit.inverse.priors import Laplace
from diffeit.results import RESULTS, SolverError
from diffeit.scene import (
    Background,
    Disc,
    Ellipse,
    MeasurementNoise,
    Noise,
    Press,
    Region,
    Scene,
    Skin,
    Touch,
    simulate,
)

LOW, HIGH = 0.002, 0.01  # S/sq
# The 0.002 S/sq island; the rest of the disc is at 0.01.
ISLAND = Ellipse(centre=(0.45, 0.35), semi_axes=(0.75, 0.6), angle=0.5)
# Two identical touches, point-symmetric about the disc's centre (equivalent on a uniform skin):
# one in the island, one on the 0.01 S/sq part.
CENTRES = (np.array([0.42, 0.32]), np.array([-0.42, -0.32]))
RADIUS, AMPLITUDE = 0.2, -0.3


def _simulation(noise: str, seed: int, untouched: int, touched: int = 0, h: float = 0.1):
    """Frames at 10 Hz: `untouched` frames of the bare skin, then `touched` frames with both
    touches held; simulated at h / 2 (Skin's default), fitted at `h`."""
    start = untouched / 10 - 0.05
    touches = tuple(Touch(Disc(c, RADIUS), AMPLITUDE, Press(start=start, hold=100.0)) for c in CENTRES)
    scene = Scene(
        skin=Skin(h=h),
        background=Background(HIGH, (Region(ISLAND, LOW),)),
        touches=touches if touched else (),
        frame_rate=10.0,
        duration=(untouched + touched) / 10,
        effects=(MeasurementNoise(Noise.level(noise), seed=seed),),
    )
    simulation = simulate(scene, progress=False)
    skin = scene.skin
    model = de.ForwardModel(
        scene.reconstruction_mesh(), skin.make_protocol(), skin.contact_impedances(), drive_current=skin.drive_current
    )
    assert model.n_elements < simulation.mesh.n_elements / 3
    return model, np.asarray(simulation.frames)


def _region_means(mesh: de.Mesh, conductivity: np.ndarray) -> tuple[float, float]:
    """Area-weighted means over the elements at least 0.15 m inside the island and outside it."""
    distance = np.asarray(ISLAND.signed_distance(jnp.asarray(mesh.element_centroids)))
    areas = mesh.element_areas
    inside, outside = distance < -0.15, distance > 0.15
    return (
        float(np.average(conductivity[inside], weights=areas[inside])),
        float(np.average(conductivity[outside], weights=areas[outside])),
    )


def test_two_regions_from_untouched_frames():
    """Five untouched frames at medium noise (0.5%): the region means within 10% (measured:
    -2.0% and +0.5%), the noise level estimated from the frames' spread, lambda chosen by the
    discrepancy principle."""
    model, frames = _simulation("medium", seed=7, untouched=5, h=0.15)
    result = fit.background(model, frames, progress=False)
    assert result.result == RESULTS.successful
    low, high = _region_means(model.mesh, result.conductivity)
    print(f"region means: {low / LOW - 1:+.1%} (0.002 S/sq), {high / HIGH - 1:+.1%} (0.01 S/sq)")
    assert low == pytest.approx(LOW, rel=0.1)
    assert high == pytest.approx(HIGH, rel=0.1)
    rms = np.sqrt(np.mean(frames.mean(axis=0) ** 2))
    assert result.noise / rms == pytest.approx(0.005, rel=0.1)
    # The largest candidate meeting the noise level: the one before it did not.
    assert result.discrepancy[-1] <= 1 or np.min(result.discrepancy) <= 1
    assert 1e-3 < result.hyperparameter < 0.1
    assert np.all(np.diff(result.history.objective) <= 0)
    assert np.isnan(result.history.gradient_norm[0]) and 0 < result.history.gradient_norm[-1] < 1e-3
    assert result.gain is None and result.misfit < 0.01
    assert LOW < result.homogeneous < HIGH


@pytest.mark.slow
def test_touches_on_both_regions_agree_against_the_fitted_background():
    """Fig. 5.6: two identical touches (dsigma/sigma = -0.3), one on each region, at low noise
    (0.1%), fitting on h = 0.15 (404 triangles) from data on h = 0.075: the mesh of the test
    above, whose compiled background fit this one runs (on h = 0.1, 914 triangles, it took 8.5 s;
    3.6 s here). One-step images of the relative change dsigma / background, linearised at the
    fitted map, agree within 10% in peak and in integral over each touch's neighbourhood
    (measured: peak +4.3%, integral +1.9%; noise seed 2: +4.7%, +1.2%; on h = 0.1: -6%, -5%);
    against the best uniform background they disagree by about 60% (measured: +61%, +65%)."""
    untouched = 5
    model, frames = _simulation("low", seed=1, untouched=untouched, touched=5, h=0.15)
    reference = frames[:untouched]
    result = fit.background(model, reference, progress=False)
    assert result.result == RESULTS.successful
    low, high = _region_means(model.mesh, result.conductivity)
    assert low == pytest.approx(LOW, rel=0.1) and high == pytest.approx(HIGH, rel=0.1)
    change = frames[untouched:].mean(axis=0) - reference.mean(axis=0)
    mesh = model.mesh
    near = [de.mesh.disc_fraction(mesh, centre, 0.45) > 0.5 for centre in CENTRES]

    def disagreement(background):
        image = np.asarray(OneStep(model, "laplace", 0.03, background=background).solve(change).value) / background
        peaks = [de.metrics.peak(image[where]) for where in near]
        integrals = [mesh.element_areas[where] @ image[where] for where in near]
        return peaks[0] / peaks[1] - 1, integrals[0] / integrals[1] - 1

    fitted = disagreement(result.conductivity)
    uniform = disagreement(np.full(mesh.n_elements, result.homogeneous))
    print(
        f"touch on 0.002 S/sq vs on 0.01 S/sq: fitted background peak {fitted[0]:+.1%}, integral {fitted[1]:+.1%}; "
        f"uniform background peak {uniform[0]:+.1%}, integral {uniform[1]:+.1%}"
    )
    assert abs(fitted[0]) < 0.1 and abs(fitted[1]) < 0.1
    assert abs(uniform[0]) > 0.3 and abs(uniform[1]) > 0.3


@pytest.mark.slow
def test_gains_per_reading_are_fitted_with_their_prior():
    """Readings with gains of 1% spread: without gains the misfit levels off above the noise
    (`selection_at_boundary`); with `estimate_gain` the fit succeeds, the region means stay
    within 10% and the fitted gains follow the true ones (measured: correlation 0.51; the
    gains are determined by their prior and by reciprocity only)."""
    model, frames = _simulation("medium", seed=7, untouched=5)
    gains = np.exp(np.random.default_rng(8).normal(0, 0.01, model.n_measurements))
    frames = frames * gains
    plain = fit.background(model, frames, progress=False, throw=False)
    assert plain.result == RESULTS.selection_at_boundary
    result = fit.background(model, frames, estimate_gain=True, progress=False)
    assert result.result == RESULTS.successful
    low, high = _region_means(model.mesh, result.conductivity)
    correlation = np.corrcoef(np.log(result.gain), np.log(gains))[0, 1]
    print(f"with gains: region means {low / LOW - 1:+.1%}, {high / HIGH - 1:+.1%}; gain correlation {correlation:.2f}")
    assert low == pytest.approx(LOW, rel=0.1) and high == pytest.approx(HIGH, rel=0.1)
    assert correlation > 0.3
    assert abs(np.mean(np.log(result.gain))) < 0.005
    assert result.misfit < plain.misfit
    history = result.history
    assert np.all(np.diff(history.objective) <= 0) and len(history.objective) > 10
    assert np.all(np.isfinite(history.gradient_norm[-10:]))


def test_the_noise_is_estimated_from_one_frame_or_several(small_model):
    """One frame: from the readings reciprocity leaves redundant (104 of the 208 adjacent
    readings); several: from their spread; or given in percent of RMS(v)."""
    conductivity = 0.01 * np.exp(np.random.default_rng(1).normal(0, 0.3, small_model.n_elements))
    clean = np.asarray(small_model.measure(jnp.asarray(conductivity)))
    std = 0.005 * np.sqrt(np.mean(clean**2))
    frames = clean + np.random.default_rng(2).normal(0, std, (4, len(clean)))
    one = fit.background(small_model, frames[0], hyperparameter=0.01, progress=False)
    several = fit.background(small_model, frames, hyperparameter=0.01, progress=False)
    given = fit.background(small_model, frames, hyperparameter=0.01, noise=1.0, progress=False)
    assert one.noise == pytest.approx(std, rel=0.15)
    assert several.noise == pytest.approx(std, rel=0.1)
    assert given.noise == pytest.approx(0.01 * np.sqrt(np.mean(frames.mean(axis=0) ** 2)), rel=1e-12)
    assert one.candidates.tolist() == [0.01] and one.hyperparameter == 0.01


def test_the_objective_is_gauss_newtons_and_its_gradient_matches_central_differences(small_model):
    """Phi at the Gauss-Newton fit equals the last entry of its history, and jax.grad of Phi
    matches central differences in every group: ln(sigma), ln(z), ln(g)."""
    rng = np.random.default_rng(3)
    conductivity = 0.01 * np.exp(rng.normal(0, 0.3, small_model.n_elements))
    data = np.asarray(small_model.measure(jnp.asarray(conductivity))) * np.exp(rng.normal(0, 0.01, 208))
    result = fit.background(small_model, data, hyperparameter=0.01, estimate_contact_impedance=True, progress=False)
    objective = _Objective(small_model, Laplace(), data, result.homogeneous, 1.0)
    at_fit = {"s": jnp.log(result.conductivity), "w": jnp.log(result.contact_impedance)}
    assert float(objective.bind(0.01, 0.0)(at_fit)) == pytest.approx(result.history.objective[-1], rel=1e-9)

    function = objective.bind(0.01, 0.5)
    point = {
        "s": jnp.log(result.conductivity) + 0.2 * rng.normal(size=small_model.n_elements),
        "w": jnp.log(result.contact_impedance) + 0.3 * rng.normal(size=16),
        "gamma": 0.02 * rng.normal(size=208),
    }
    gradient = jax.grad(function)(point)
    # The forward solve is accurate to about 1e-10 (relative): smaller steps difference rounding.
    step = 1e-3
    for group in point:
        direction = {name: jnp.zeros_like(value) for name, value in point.items()}
        direction[group] = jnp.asarray(rng.normal(size=point[group].shape))

        def moved(sign, direction=direction):
            return float(function(jax.tree_util.tree_map(lambda y, d: y + sign * step * d, point, direction)))

        central = (moved(1) - moved(-1)) / (2 * step)
        analytic = float(jnp.vdot(gradient[group], direction[group]))
        assert analytic == pytest.approx(central, rel=1e-5), group


def test_contact_impedance_is_fitted_when_asked(small_model):
    rng = np.random.default_rng(4)
    z = 0.01 * np.exp(rng.normal(0, 0.3, 16))
    data = np.asarray(small_model.measure(jnp.full(small_model.n_elements, 0.01), jnp.asarray(z)))
    fixed = fit.background(small_model, data, hyperparameter=0.01, progress=False)
    joint = fit.background(small_model, data, hyperparameter=0.01, estimate_contact_impedance=True, progress=False)
    assert np.array_equal(fixed.contact_impedance, np.asarray(small_model.contact_impedance))
    assert joint.contact_impedance.shape == (16,) and np.all(joint.contact_impedance > 0)
    assert not np.allclose(joint.contact_impedance, 0.01)
    assert joint.misfit <= fixed.misfit


def test_a_fit_that_falls_short_says_so(small_model):
    """Gauss-Newton stopped after one step: `max_iterations_reached`; per-reading gains the
    model lacks hold the misfit above the noise: `selection_at_boundary`, the fit where the
    misfit levelled off. Both raise with throw=True."""
    rng = np.random.default_rng(5)
    conductivity = 0.01 * np.exp(rng.normal(0, 0.3, small_model.n_elements))
    clean = np.asarray(small_model.measure(jnp.asarray(conductivity)))
    frames = clean + rng.normal(0, 1e-4 * np.sqrt(np.mean(clean**2)), (3, len(clean)))
    capped = fit.background(small_model, frames, hyperparameter=1e-3, max_iterations=1, progress=False, throw=False)
    assert capped.result == RESULTS.max_iterations_reached
    with pytest.raises(SolverError, match="background fit"):
        fit.background(small_model, frames, hyperparameter=1e-3, max_iterations=1, progress=False)

    gained = frames * np.exp(rng.normal(0, 0.02, 208))
    levelled = fit.background(small_model, gained, progress=False, throw=False)
    assert levelled.result == RESULTS.selection_at_boundary
    assert np.min(levelled.discrepancy) > 1 and levelled.hyperparameter > 1e-6
    assert np.all(np.isfinite(levelled.conductivity)) and levelled.misfit < 0.05
    with pytest.raises(SolverError, match="background fit"):
        fit.background(small_model, gained, progress=False)


def test_bad_input_is_refused(small_model):
    frame = np.asarray(small_model.measure(jnp.full(small_model.n_elements, 0.01)))
    with pytest.raises(ValueError, match=r"reference frames have shape \(100,\); expected \(208,\)"):
        fit.background(small_model, frame[:100])
    with pytest.raises(ValueError, match=r"reference frames have shape \(2, 3, 208\)"):
        fit.background(small_model, np.ones((2, 3, 208)))
    with pytest.raises(ValueError, match=r"not finite \(NaN or inf\) in frame\(s\) \[1\]"):
        fit.background(small_model, np.stack([frame, np.where(np.arange(208) == 5, np.inf, frame)]))
    with pytest.raises(ValueError, match="the reference frames are identical"):
        fit.background(small_model, np.stack([frame, frame]))
    with pytest.raises(ValueError, match="do not correlate positively"):
        fit.background(small_model, -frame, hyperparameter=0.01)
    for option, value, message in (
        ("hyperparameter", -1.0, "hyperparameter must be finite and positive"),
        ("noise", 0.0, "noise is a percentage"),
        ("gain_spread", 0.0, "gain_spread must be finite and positive"),
        ("discrepancy_safety", np.nan, "discrepancy_safety must be finite and positive"),
        ("max_iterations", 0, "max_iterations must be >= 1"),
    ):
        with pytest.raises(ValueError, match=message):
            fit.background(small_model, frame, **{option: value})
    # One drive, its readings all independent: one frame holds no redundancy to estimate the noise.
    drive = np.zeros((1, 16))
    drive[0, :2] = 1, -1
    measure = [np.eye(16)[2:15] - np.eye(16, k=1)[2:15]]
    model = de.ForwardModel(small_model.mesh, de.protocol.Protocol(drive, measure))
    single = np.asarray(model.measure(jnp.full(model.n_elements, 0.01)))
    with pytest.raises(ValueError, match="too few to estimate the noise from"):
        fit.background(model, single)
    with pytest.raises(ValueError, match="too few to estimate the noise from"):
        fit.background(model, single, hyperparameter=0.01, estimate_gain=True)
    assert np.isnan(fit.background(model, single, hyperparameter=0.01, progress=False, throw=False).noise)
