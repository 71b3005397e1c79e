"""diffeit.fit.correct_memory and diffeit.fit.memory: the exact causal inverse of the memory model,
its dead band for noise, and the fit of the memory parameters and the memoryless stimulus from
images (three presses at one place, and presses with varied holds and gaps)."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffeit as de
from diffeit.fit import MemoryFit, correct_memory, correct_memory_step, memory
from diffeit.fit._memory import (
    DEFAULT_FREE,
    MemoryObjective,
    memory_from_unconstrained,
    memory_to_unconstrained,
    noise_level,
)
from diffeit.results import RESULTS, SolverError
from diffeit.scene import (
    Disc,
    MemoryParameters,
    Press,
    Touch,
    bare_skin,
    initial_state,
    integrate_memory,
    memory_response,
    over_foam,
    stimulus,
)

# A skin of our own, between the presets: faster and weaker fast mode, stronger slow mode.
TRUTH = MemoryParameters(fast_fraction=0.25, fast_time=0.8, slow_fraction=0.35, slow_time=6.0, relaxation=0.2)
FITTED = ("fast_fraction", "fast_time", "slow_fraction", "slow_time", "relaxation")
# Three presses at one place (start, hold; seconds), then holds and gaps of 0.6 to 6 s.
THREE = [(1.0, 2.0), (7.0, 2.0), (13.0, 2.0)]
VARIED = [(19.0, 0.6), (22.0, 6.0), (33.0, 1.0)]
DEPTH = -0.3  # dsigma/sigma at the centre of the press
STRONG = MemoryParameters(fast_fraction=0.45, slow_fraction=0.45, first_cycle_offset=0.2, fatigue_rate=5.0)
PARAMETER_SETS = {"bare_skin": bare_skin(), "over_foam": over_foam(), "truth": TRUTH, "strong": STRONG}


def random_presses(times: np.ndarray, n_elements: int, seed: int) -> np.ndarray:
    """(T, E) presses of random depth (mostly touches, some increases), hold and gap per element."""
    rng = np.random.default_rng(seed)
    result = np.zeros((times.size, n_elements))
    for element in range(n_elements):
        frame = 0
        while frame < times.size:
            frame += int(rng.integers(2, 30))
            hold = int(rng.integers(1, 40))
            result[frame : frame + hold, element] = rng.uniform(-0.6, 0.3)
            frame += hold
    return result


@pytest.fixture(scope="module")
def random_scene():
    rng = np.random.default_rng(3)
    times = np.cumsum(rng.uniform(0.05, 0.3, 300))
    return times, random_presses(times, 24, seed=4)


def touch_scene(mesh: de.Mesh, rate: float, duration: float, presses=THREE + VARIED):
    """(times, stimulus (T, E), responses (T, E)): presses of one disc at one place on `mesh`."""
    times = np.arange(0.0, duration, 1 / rate)
    touches = [
        Touch(shape=Disc(centre=[0.4, 0.1], radius=0.35), amplitude=DEPTH, envelope=Press(start=start, hold=hold))
        for start, hold in presses
    ]
    truth = np.asarray(stimulus(mesh, touches, times))
    return times, truth, np.asarray(memory_response(truth, times, TRUTH))


@pytest.fixture(scope="module")
def small_scene():
    return touch_scene(de.mesh.disc(16, electrode_width=0.2, h=0.25), rate=5.0, duration=40.0)


@pytest.fixture(scope="module")
def medium_images(small_scene):
    """The small scene's images with medium noise: 2% of the press depth per element and frame."""
    _, _, clean = small_scene
    return clean + 0.02 * abs(DEPTH) * np.random.default_rng(11).standard_normal(clean.shape)


def relative_errors(fitted: MemoryParameters) -> dict[str, float]:
    return {name: float(getattr(fitted, name) / getattr(TRUTH, name) - 1) for name in FITTED}


def touch_peaks(times, truth, values) -> np.ndarray:
    """The peak of each of the three presses at one place: the most negative mean over the
    elements more than half pressed, over the press's frames."""
    core = truth.min(axis=0) < DEPTH / 2
    return np.array([values[(times >= s) & (times < s + h)][:, core].mean(axis=1).min() for s, h in THREE])


def ghost_energy(times, truth, values) -> float:
    """Sum of squares in the frames between presses (the true stimulus 0 everywhere)."""
    between = np.all(truth == 0, axis=1) & (times > THREE[0][0])
    return float(np.sum(np.asarray(values)[between] ** 2))


# --- correct_memory -------------------------------------------------------------------------------


@pytest.mark.parametrize("name", PARAMETER_SETS)
def test_correct_memory_recovers_simulated_stimuli_to_rounding(random_scene, name):
    times, truth = random_scene
    parameters = PARAMETER_SETS[name]
    responses = memory_response(truth, times, parameters)
    recovered = correct_memory(responses, times, parameters)
    np.testing.assert_allclose(recovered, truth, rtol=0, atol=1e-12)
    np.testing.assert_allclose(memory_response(recovered, times, parameters), responses, rtol=0, atol=1e-13)


def test_correct_memory_with_per_element_parameters(random_scene):
    times, truth = random_scene
    mixed = MemoryParameters(
        fast_time=np.linspace(0.3, 2.0, truth.shape[1]), relaxation=np.linspace(0.0, 0.5, truth.shape[1])
    )
    responses = memory_response(truth, times, mixed)
    np.testing.assert_allclose(correct_memory(responses, times, mixed), truth, rtol=0, atol=1e-12)


def test_the_response_of_the_correction_is_the_image_or_its_nearest_reachable_value(random_scene):
    """memory_response(correct_memory(r)) == r wherever the model can produce r; inside the jump of
    a new extreme of the other sign the stimulus is the knot."""
    times, truth = random_scene
    images = np.asarray(memory_response(truth, times, over_foam()))
    images = images + 0.01 * np.random.default_rng(5).standard_normal(images.shape)
    corrected = np.asarray(correct_memory(images, times, over_foam()))
    back = np.asarray(memory_response(corrected, times, over_foam()))
    exact = np.abs(back - images) < 1e-12
    assert exact.mean() > 0.8
    previous = np.abs(np.concatenate([np.zeros((1, truth.shape[1])), corrected[:-1]]))
    extreme = np.maximum.accumulate(np.concatenate([np.zeros((1, truth.shape[1])), np.abs(corrected[:-1])]))
    magnitude = np.abs(corrected)
    at_knot = np.isclose(magnitude, previous, rtol=0, atol=1e-12) | np.isclose(magnitude, extreme, rtol=0, atol=1e-12)
    assert np.all(at_knot[~exact])


def test_correct_memory_degrades_gracefully_with_noise(small_scene, capsys):
    """The exact inverse reads noise as a chattering load, which the hysteresis pumps into a drift;
    the dead band at 3 noise levels keeps the stimulus error below the noise level."""
    times, truth, clean = small_scene
    rows = []
    for level in (0.005, 0.02, 0.05):
        sigma = level * abs(DEPTH)
        images = clean + sigma * np.random.default_rng(7).standard_normal(clean.shape)
        exact = np.asarray(correct_memory(images, times, TRUTH))
        banded = np.asarray(correct_memory(images, times, TRUTH, tolerance=3 * sigma))
        rms = [float(np.sqrt(np.mean((x - truth) ** 2))) / sigma for x in (exact, banded)]
        rows.append((level, *rms))
        assert rms[1] < 1.0
        assert rms[0] > 2 * rms[1]
    with capsys.disabled():
        print("\nnoise (of the peak) | stimulus rms error / noise: exact | dead band 3 sigma")
        for level, exact, banded in rows:
            print(f"{level:18.1%} | {exact:30.2f} | {banded:.2f}")


def test_correct_memory_step_frame_by_frame_and_from_a_state(random_scene):
    times, truth = random_scene
    responses = memory_response(truth, times, TRUTH)
    whole = np.asarray(correct_memory(responses, times, TRUTH))
    step = jax.jit(correct_memory_step)
    state = initial_state(truth.shape[1], time=times[0])
    frames = []
    for image, time in zip(responses, times, strict=True):
        value, state = step(state, image, time, TRUTH)
        frames.append(value)
    np.testing.assert_allclose(np.stack(frames), whole, rtol=0, atol=1e-14)
    # A recording continued from the skin's state: the second half alone.
    _, middle = integrate_memory(truth[:150], times[:150], TRUTH)
    second = correct_memory(responses[150:], times[150:], TRUTH, state=middle)
    np.testing.assert_allclose(second, truth[150:], rtol=0, atol=1e-12)


def test_correct_memory_under_jit_vmap_and_grad(random_scene):
    times, truth = random_scene
    responses = memory_response(truth, times, TRUTH)
    batch = jax.tree.map(lambda *v: jnp.stack(v), TRUTH, bare_skin())
    batched = jax.vmap(lambda p: correct_memory(responses, times, p))(batch)
    np.testing.assert_allclose(batched[0], truth, atol=1e-12)
    np.testing.assert_allclose(batched[1], correct_memory(responses, times, bare_skin()), atol=1e-14)

    def total(slow_time):
        return jnp.sum(correct_memory(responses, times, dataclasses.replace(TRUTH, slow_time=slow_time)) ** 2)

    # Away from the truth, where a held stimulus sits on a knot (a kink of the inverse).
    gradient = jax.jit(jax.grad(total))(4.0)
    step = 1e-6
    central = (total(4.0 + step) - total(4.0 - step)) / (2 * step)
    np.testing.assert_allclose(gradient, central, rtol=1e-5)


def test_correct_memory_refuses_bad_input(random_scene):
    times, truth = random_scene
    images = np.asarray(memory_response(truth, times, TRUTH))
    broken = images.copy()
    broken[5, 2] = np.nan
    with pytest.raises(ValueError, match="finite; frame 5"):
        correct_memory(broken, times, TRUTH)
    with pytest.raises(ValueError, match=r"times must increase: times\[3\]"):
        correct_memory(images, np.concatenate([times[:3], times[2:-1]]), TRUTH)
    with pytest.raises(ValueError, match="same length"):
        correct_memory(images, times[:-1], TRUTH)
    with pytest.raises(ValueError, match=r"shape \(T, E\)"):
        correct_memory(images[:, 0], times, TRUTH)
    with pytest.raises(ValueError, match="fast_fraction \\+ slow_fraction < 1"):
        correct_memory(images, times, MemoryParameters(fast_fraction=0.5, slow_fraction=0.5))
    with pytest.raises(ValueError, match="tolerance"):
        correct_memory(images, times, TRUTH, tolerance=-0.1)
    with pytest.raises(ValueError, match=r"before state\.time"):
        correct_memory(images, times, TRUTH, state=initial_state(truth.shape[1], time=times[0] + 1))


# --- memory ---------------------------------------------------------------------------------------


def test_unconstrained_round_trip():
    names = (*FITTED, "fatigue_rate", "first_cycle_offset")
    back = memory_from_unconstrained(memory_to_unconstrained(TRUTH, names), over_foam())
    for name in names:
        np.testing.assert_allclose(getattr(back, name), getattr(TRUTH, name), rtol=1e-12)
    assert back.gain == over_foam().gain


def test_memory_objective_gradient_matches_central_differences(small_scene):
    times, truth, clean = small_scene
    chosen = np.flatnonzero(truth.min(axis=0) < DEPTH / 2)[:5]
    segments = np.cumsum(np.concatenate([[0], np.any(np.diff(truth[:, chosen], axis=0) != 0, axis=1)]))
    segments = np.broadcast_to(segments[:, None], (times.size, chosen.size))
    weights = jnp.full(chosen.size, 1e3)
    # Rests at zero, presses ever deeper: away from the knots of the response (a level equal in
    # size to the largest so far), where it has kinks.
    signs = np.zeros((segments.max() + 1, chosen.size))
    signs[1::2] = -1.0
    objective = MemoryObjective(
        jnp.asarray(clean[:, chosen]), times, weights, jnp.asarray(segments), jnp.asarray(signs), over_foam()
    )
    levels = np.zeros(signs.shape)
    levels[1::2] = np.log(0.25 + 0.01 * np.arange(levels[1::2].shape[0]))[:, None]
    unknowns = (memory_to_unconstrained(over_foam(), DEFAULT_FREE), jnp.asarray(levels))
    gradient = jax.grad(objective)(unknowns)
    step = 1e-6
    for name in DEFAULT_FREE:

        def along(value, name=name):
            return objective(({**unknowns[0], name: value}, unknowns[1]))

        value = unknowns[0][name]
        central = (along(value + step) - along(value - step)) / (2 * step)
        np.testing.assert_allclose(gradient[0][name], central, rtol=1e-5, err_msg=name)
    for index in [(1, 0), (1, 2), (3, 4), (5, 1)]:
        shifted = [unknowns[1].at[index].add(sign * step) for sign in (1, -1)]
        central = (objective((unknowns[0], shifted[0])) - objective((unknowns[0], shifted[1]))) / (2 * step)
        np.testing.assert_allclose(gradient[1][index], central, rtol=1e-5, err_msg=str(index))


def check_memory_criteria(times, truth, images, fit: MemoryFit, parameter_tolerance: float) -> None:
    errors = relative_errors(fit.memory)
    assert max(abs(e) for e in errors.values()) < parameter_tolerance, errors
    peaks = touch_peaks(times, truth, np.asarray(fit.stimulus))
    np.testing.assert_allclose(peaks[1:] / peaks[0], 1, atol=0.1)
    assert ghost_energy(times, truth, images) >= 5 * ghost_energy(times, truth, fit.stimulus)


def test_memory_fit_noise_free(small_scene):
    times, truth, clean = small_scene
    # A fixed field given per element (the truth's value) is used on the elements fitted.
    initial = dataclasses.replace(over_foam(), first_cycle_offset=np.full(clean.shape[1], TRUTH.first_cycle_offset))
    fit = memory(clean, times, initial=initial, progress=False)
    assert fit.result == RESULTS.successful
    check_memory_criteria(times, truth, clean, fit, parameter_tolerance=1e-3)
    np.testing.assert_allclose(fit.stimulus, truth, atol=1e-3)
    assert fit.misfit < 1e-4
    assert fit.stimulus.shape == fit.response.shape == clean.shape
    assert fit.memory.gain == 1.0 and fit.memory.fatigue_rate == over_foam().fatigue_rate
    assert fit.history.objective.shape == fit.history.gradient_norm.shape
    assert fit.elements.sum() > 20 and not fit.elements[truth.min(axis=0) == 0].any()


def test_memory_fit_uses_the_strongest_elements_up_to_max_elements(small_scene, medium_images):
    times, _, _ = small_scene
    images = medium_images
    fit = memory(images, times, rounds=1, max_elements=8, progress=False)
    assert fit.elements.sum() <= 8
    strength = np.abs(images).max(axis=0) / fit.noise
    weakest_used = strength[fit.elements].min()
    # Only the strongest are candidates (a few may be left out as outliers after the round).
    assert np.sum(strength > weakest_used) < 8
    assert all(abs(e) < 0.3 for e in relative_errors(fit.memory).values())
    with pytest.raises(ValueError, match="max_elements"):
        memory(images, times, max_elements=0, progress=False)


def test_memory_fit_with_medium_noise(small_scene, medium_images):
    """Medium noise: 2% of the press depth per element and frame (one-step images of a scene's
    "medium" noise carry more, spatially correlated: the joint fit handles those)."""
    times, truth, _ = small_scene
    images = medium_images
    fit = memory(images, times, rounds=1, progress=False)
    check_memory_criteria(times, truth, images, fit, parameter_tolerance=0.2)
    np.testing.assert_allclose(np.median(fit.noise), 0.02 * abs(DEPTH), rtol=0.1)


@pytest.mark.slow
def test_memory_fit_degrades_with_noise_on_a_larger_problem(capsys):
    """10 frames/s on a finer mesh: low and medium noise meet the criteria, and the table reports
    them. Of the 404 elements about 60 rise above the noise threshold; the 40 strongest fit the
    parameters (`max_elements`, as on fine meshes: the fits then share one compiled program, and
    take 40-700 L-BFGS steps where all of them took 500-1000), and every element is corrected."""
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.15)
    times, truth, clean = touch_scene(mesh, rate=10.0, duration=40.0)
    rows = []
    for level in (0.005, 0.02):
        images = clean + level * abs(DEPTH) * np.random.default_rng(13).standard_normal(clean.shape)
        fit = memory(images, times, max_elements=40, progress=False, throw=False)
        assert fit.result == RESULTS.successful
        check_memory_criteria(times, truth, images, fit, parameter_tolerance=0.2)
        peaks = touch_peaks(times, truth, np.asarray(fit.stimulus))
        ghosts = ghost_energy(times, truth, images) / ghost_energy(times, truth, fit.stimulus)
        rows.append((level, relative_errors(fit.memory), peaks[1:] / peaks[0], ghosts))
    with capsys.disabled():
        print("\nnoise | " + " | ".join(FITTED) + " | peaks 2, 3 / peak 1 | ghost energy before / after")
        for level, errors, ratios, ghosts in rows:
            print(
                f"{level:.1%} | "
                + " | ".join(f"{errors[name]:+.1%}" for name in FITTED)
                + f" | {ratios[0]:.3f}, {ratios[1]:.3f} | {ghosts:.0f}"
            )


def test_noise_level_is_robust_to_steps():
    rng = np.random.default_rng(17)
    steps = np.repeat([0.0, -0.3, 0.0, -0.2], 50)[:, None] * np.ones((1, 30))
    estimate = noise_level(steps + 0.01 * rng.standard_normal(steps.shape))
    np.testing.assert_allclose(np.median(estimate), 0.01, rtol=0.1)


def test_memory_fit_that_does_not_converge_says_so(small_scene, medium_images):
    """The medium-noise fit's problem (the same images, one round) cut short at 3 L-BFGS steps:
    its shapes are those of test_memory_fit_with_medium_noise, so the two share one compiled
    program (measured: 7 s of compilation otherwise, for a run of 0.07 s)."""
    times, _, _ = small_scene
    fit = memory(medium_images, times, max_steps=3, rounds=1, throw=False, progress=False)
    assert fit.result == RESULTS.max_iterations_reached
    with pytest.raises(SolverError, match="memory fit"):
        memory(medium_images, times, max_steps=3, rounds=1, progress=False)


def test_memory_fit_refuses_bad_input(small_scene):
    times, _, clean = small_scene
    broken = clean.copy()
    broken[4, 7] = np.inf
    with pytest.raises(ValueError, match="finite; frame 4"):
        memory(broken, times)
    with pytest.raises(ValueError, match="times must increase"):
        memory(clean, times[::-1])
    with pytest.raises(ValueError, match="same length"):
        memory(clean[:-2], times)
    with pytest.raises(ValueError, match=r"MemoryParameters\.slow_time is a time constant"):
        memory(clean, times, initial=MemoryParameters(slow_time=-1.0))
    with pytest.raises(ValueError, match=r"MemoryParameters\.relaxation is a fraction"):
        memory(clean, times, initial=eqx.tree_at(lambda p: p.relaxation, over_foam(), 1.5))
    with pytest.raises(ValueError, match=r"initial\.relaxation = 0\.0 is on the boundary"):
        memory(clean, times, initial=MemoryParameters(relaxation=0.0))
    with pytest.raises(ValueError, match="gain trades exactly"):
        memory(clean, times, free=("gain", "fast_time"))
    with pytest.raises(ValueError, match="unknown names"):
        memory(clean, times, free=("fast_time", "speed"))
    with pytest.raises(ValueError, match="fitted together"):
        memory(clean, times, free=("fast_fraction",))
    with pytest.raises(ValueError, match="must be a scalar"):
        memory(clean, times, initial=MemoryParameters(fast_time=np.full(clean.shape[1], 1.0)))
    with pytest.raises(ValueError, match="no element's images exceed"):
        memory(np.zeros_like(clean), times)
    with pytest.raises(ValueError, match="jump"):
        memory(clean, times, jump=1.5)
