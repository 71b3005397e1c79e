"""The memory effect: exact integration, the dissertation's figures, switching off, gradients, checks."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffeit  # noqa: F401  (turns on float64)
from diffeit.memory import (
    MemoryParameters,
    advance,
    apply_stimulus,
    bare_skin,
    initial_state,
    integrate_memory,
    memory_response,
    over_foam,
    read_response,
)

# Parameters away from the presets, so that no term hides behind a round default.
CUSTOM = MemoryParameters(
    gain=1.3,
    fast_fraction=0.2,
    fast_time=0.7,
    slow_fraction=0.45,
    slow_time=6.0,
    relaxation=0.35,
    first_cycle_offset=0.08,
    fatigue_limit=0.5,
    fatigue_rate=0.9,
    fatigue_recovery_time=40.0,
)
PRESETS = {"bare_skin": bare_skin(), "over_foam": over_foam(), "custom": CUSTOM}
REFERENCE_PRESS = -0.3  # the calibration press of the presets: dsigma/sigma, held 5 s
REFERENCE_HOLD = 5.0


def analytic_response(t: np.ndarray, p: MemoryParameters, presses: list[tuple[float, float, float]]) -> np.ndarray:
    """The model's closed form (module docstring) at arbitrary times `t` (s) for rectangular
    presses (height, start, hold), in order and apart, on a rested virgin skin. Each segment is
    evaluated directly from its start; nothing is stepped frame by frame."""
    t = np.asarray(t, dtype=float)
    response = np.zeros_like(t)
    taus = np.array([p.fast_time, p.slow_time])
    fractions = np.array([p.fast_fraction, p.slow_fraction])
    fatigue, modes, extreme, released = 0.0, np.zeros(2), 0.0, None
    next_starts = [start for _, start, _ in presses[1:]] + [np.inf]
    for (height, start, hold), next_start in zip(presses, next_starts, strict=True):
        if released is not None:  # recovery since the last release, stimulus zero
            modes = modes * np.exp(-(start - released) / taus)
            fatigue = fatigue * np.exp(-(start - released) / p.fatigue_recovery_time)
        sensitivity = 1 - fatigue
        extreme = height if abs(height) > abs(extreme) else extreme
        loaded = modes + sensitivity * height
        relaxed = (1 - p.relaxation) * sensitivity * height
        drive = p.fatigue_rate * abs(height) * p.fatigue_recovery_time
        fatigue_target = p.fatigue_limit * drive / (1 + drive)
        rate = (1 + drive) / p.fatigue_recovery_time

        held = (t >= start) & (t < start + hold)
        mode_values = relaxed + (loaded - relaxed) * np.exp(-(t[held, None] - start) / taus)
        elastic = (1 - fractions.sum()) * sensitivity * height
        response[held] = p.gain * (elastic + mode_values @ fractions) + p.first_cycle_offset * extreme

        released = start + hold
        modes = relaxed + (loaded - relaxed) * np.exp(-hold / taus)
        fatigue = fatigue_target + (fatigue - fatigue_target) * np.exp(-rate * hold)
        after = (t >= released) & (t < next_start)
        mode_values = modes * np.exp(-(t[after, None] - released) / taus)
        response[after] = p.gain * mode_values @ fractions + p.first_cycle_offset * extreme
    return response


def press_stimulus(t: np.ndarray, presses: list[tuple[float, float, float]]) -> np.ndarray:
    stimulus = np.zeros_like(t)
    for height, start, hold in presses:
        stimulus[(t >= start) & (t < start + hold)] = height
    return stimulus


def irregular_times(rng: np.random.Generator, end: float, n: int, events: list[float]) -> np.ndarray:
    """n random frame times in [0, end] plus the event times (where the held stimulus changes)."""
    return np.unique(np.concatenate([[0.0], rng.uniform(0, end, n), events]))


TWO_PRESSES = [(-0.3, 1.0, 3.0), (-0.5, 12.0, 2.5)]  # the second deeper: the offset grows again


@pytest.mark.parametrize("name", PRESETS)
def test_integrator_matches_the_analytic_press_response(name):
    p = PRESETS[name]
    events = [edge for _, start, hold in TWO_PRESSES for edge in (start, start + hold)]
    for times in (np.arange(0, 40.0, 0.25), irregular_times(np.random.default_rng(3), 40.0, 300, events)):
        scales = np.array([0.2, 1.0, 1.6])  # three elements pressed to different depths
        presses = [[(height * scale, start, hold) for height, start, hold in TWO_PRESSES] for scale in scales]
        stimulus = np.stack([press_stimulus(times, pressed) for pressed in presses], axis=1)
        response = np.asarray(memory_response(stimulus, times, p))
        expected = np.stack([analytic_response(times, p, pressed) for pressed in presses], axis=1)
        np.testing.assert_allclose(response, expected, rtol=0, atol=1e-10)
        assert np.min(expected) < -0.5  # the comparison covers the presses, not only the rest


def test_responses_do_not_depend_on_the_frame_rate():
    # A staircase with a partial release, a reloading, a sign change and long rests; its steps
    # lie on the coarse grid, so every grid holds it exactly.
    coarse = np.arange(0.0, 60.0, 0.5)
    levels = {1.0: -0.2, 2.5: -0.45, 6.0: -0.15, 7.0: -0.6, 9.0: 0.0, 20.0: 0.1, 21.0: -0.3, 23.5: 0.0}
    edges = np.array(sorted(levels))

    def stimulus_at(t: np.ndarray) -> np.ndarray:
        index = np.searchsorted(edges, t, side="right") - 1
        return np.where(index >= 0, np.array([levels[e] for e in edges])[np.maximum(index, 0)], 0.0)[:, None]

    rng = np.random.default_rng(7)
    fine = np.unique(np.concatenate([coarse, np.arange(0.0, 60.0, 0.05), rng.uniform(0, 60, 500)]))
    for p in PRESETS.values():
        on_coarse = np.asarray(memory_response(stimulus_at(coarse), coarse, p))
        on_fine = np.asarray(memory_response(stimulus_at(fine), fine, p))
        shared = np.isin(fine, coarse)
        assert np.count_nonzero(shared) == len(coarse)
        np.testing.assert_allclose(on_fine[shared], on_coarse, rtol=0, atol=1e-13)

        # Continuing from a returned state gives the same frames as one run.
        first, state = integrate_memory(stimulus_at(fine[:400]), fine[:400], p)
        second = memory_response(stimulus_at(fine[400:]), fine[400:], p, state)
        np.testing.assert_allclose(np.concatenate([first, second]), on_fine, rtol=0, atol=1e-15)


def reference_press(p: MemoryParameters, step: float = 0.01, tail: float = 40.0) -> tuple[np.ndarray, np.ndarray]:
    """Times after release (s) and the change as a fraction of the peak, for the reference press
    on a preconditioned, rested skin, measured from the baseline before the press."""
    times = np.arange(0.0, REFERENCE_HOLD + tail, step)
    stimulus = np.where(times < REFERENCE_HOLD - step / 2, REFERENCE_PRESS, 0.0)[:, None]
    state = initial_state(1, preconditioned=REFERENCE_PRESS)
    response = np.asarray(memory_response(stimulus, times, p, state))[:, 0]
    change = response - p.first_cycle_offset * REFERENCE_PRESS
    after = times >= REFERENCE_HOLD - step / 2
    return times[after] - times[after][0], change[after] / change[0]


def recovery_time(p: MemoryParameters, fraction: float = 0.1) -> float:
    """Seconds from release until the change falls to `fraction` of the peak (interpolated)."""
    since_release, relative = reference_press(p)
    below = int(np.flatnonzero(relative <= fraction)[0])
    return float(np.interp(fraction, relative[[below, below - 1]], since_release[[below, below - 1]]))


def second_press_ratio(p: MemoryParameters, gap: float) -> float:
    """The change read by a reference press `gap` seconds after the release of another, over
    the change read by the first on a rested (preconditioned) skin."""
    hold = REFERENCE_HOLD
    times = np.array([0.0, hold, hold + gap, hold + gap])  # the last two: just before, at the press
    stimulus = np.array([REFERENCE_PRESS, 0.0, 0.0, REFERENCE_PRESS])[:, None]
    state = initial_state(1, time=-1000.0, preconditioned=REFERENCE_PRESS)
    response = np.asarray(memory_response(stimulus, times, state=state, parameters=p))[:, 0]
    return (response[3] - response[2]) / (response[0] - p.first_cycle_offset * REFERENCE_PRESS)


def test_presets_recover_to_ten_percent_as_measured():
    # The dissertation: about 4 s for the bare skin, 7-8 s over foam.
    assert recovery_time(bare_skin()) == pytest.approx(4.0, abs=0.1)
    assert 7.0 <= recovery_time(over_foam()) <= 8.0
    assert recovery_time(over_foam()) == pytest.approx(7.5, abs=0.1)
    for p in (bare_skin(), over_foam()):
        _, relative = reference_press(p)
        assert 0.3 < relative[0] < 0.6  # the instant drop leaves part of the change
        assert np.all(np.diff(relative) <= 0) and relative[-1] < 0.01  # recovery is monotone, to baseline


def test_presets_lose_a_quarter_of_their_gain_after_a_30_s_gap():
    for p in (bare_skin(), over_foam()):
        assert second_press_ratio(p, 30.0) == pytest.approx(0.75, abs=0.01)
        assert second_press_ratio(p, 300.0) > 0.98  # tests 5 minutes apart are safe


def test_presets_relax_while_held():
    for p in (bare_skin(), over_foam()):
        times = np.linspace(0.0, REFERENCE_HOLD, 51)
        state = initial_state(1, preconditioned=REFERENCE_PRESS)
        response = np.asarray(memory_response(np.full((51, 1), REFERENCE_PRESS), times, p, state))[:, 0]
        change = response - p.first_cycle_offset * REFERENCE_PRESS
        assert change[0] == pytest.approx(p.gain * REFERENCE_PRESS, rel=1e-14)  # instant rise to the full change
        assert np.all(np.diff(np.abs(change)) < 0)  # relaxation while held
        assert 0.85 < change[-1] / change[0] < 0.97


@pytest.mark.parametrize("name", PRESETS)
def test_first_cycle_offset_stays(name):
    p = PRESETS[name]
    times = np.array([0.0, 1.0, 6.0, 600.0, 3600.0, 3605.0, 7200.0])
    stimulus = np.array([0.0, -0.3, 0.0, 0.0, -0.3, 0.0, 0.0])[:, None]
    response = np.asarray(memory_response(stimulus, times, p))[:, 0]
    offset = p.first_cycle_offset * -0.3
    np.testing.assert_allclose(response[[3, 6]], offset, rtol=1e-12)  # after 10 min and after 1 h
    first_change, later_change = response[1] - response[0], response[4] - response[3]
    np.testing.assert_allclose(first_change - later_change, offset, rtol=1e-6)  # the first touch reads larger
    assert offset < 0


def test_zero_stimulus_gives_exactly_zero():
    times = np.sort(np.random.default_rng(0).uniform(0, 100, 50))
    for p in PRESETS.values():
        response, state = integrate_memory(np.zeros((50, 4)), times, p)
        assert np.array_equal(response, np.zeros((50, 4)))
        for field in ("stimulus", "fast", "slow", "extreme", "fatigue"):
            assert np.array_equal(getattr(state, field), np.zeros(4))


def test_without_memory_the_response_is_gain_times_stimulus_bit_for_bit():
    rng = np.random.default_rng(1)
    times = np.sort(rng.uniform(0, 50, 200))
    stimulus = rng.uniform(-0.8, 0.2, (200, 6)) * (rng.uniform(size=(200, 6)) < 0.7)
    off = MemoryParameters(
        gain=1.7, fast_fraction=0.0, slow_fraction=0.0, relaxation=0.0, first_cycle_offset=0.0, fatigue_limit=0.0
    )
    expected = 1.7 * stimulus
    assert np.array_equal(memory_response(stimulus, times, off), expected)
    assert np.array_equal(jax.jit(memory_response)(stimulus, times, off), expected)


def test_each_effect_changes_only_its_part():
    rng = np.random.default_rng(2)
    times = np.cumsum(rng.uniform(0.05, 2.0, 120))
    stimulus = np.repeat(rng.uniform(-0.6, 0.0, (12, 3)) * (rng.uniform(size=(12, 3)) < 0.6), 10, axis=0)
    base = dataclasses.replace(CUSTOM, first_cycle_offset=0.0)
    with_offset = np.asarray(memory_response(stimulus, times, CUSTOM))
    without = np.asarray(memory_response(stimulus, times, base))
    # The offset adds mu times the running extreme (the stimulus of largest magnitude so far) and nothing else.
    running, extreme = np.zeros_like(stimulus), np.zeros(3)
    for k, row in enumerate(stimulus):
        extreme = np.where(np.abs(row) > np.abs(extreme), row, extreme)
        running[k] = extreme
    np.testing.assert_allclose(with_offset - without, CUSTOM.first_cycle_offset * running, rtol=0, atol=1e-15)
    # Without fatigue the model is positively homogeneous: twice the stimulus, twice the response.
    unfatigued = dataclasses.replace(CUSTOM, fatigue_limit=0.0)
    np.testing.assert_allclose(
        memory_response(2 * stimulus, times, unfatigued), 2 * memory_response(stimulus, times, unfatigued), atol=1e-15
    )


def test_gradients_match_finite_differences():
    events = [edge for _, start, hold in TWO_PRESSES for edge in (start, start + hold)]
    times = irregular_times(np.random.default_rng(5), 30.0, 80, events)
    stimulus = np.stack([press_stimulus(times, TWO_PRESSES), 0.5 * press_stimulus(times, TWO_PRESSES)], axis=1)
    weights = np.random.default_rng(6).normal(size=stimulus.shape)

    def objective(p: MemoryParameters, depth: float = 1.0) -> jax.Array:
        return jnp.sum(weights * memory_response(depth * stimulus, times, p))

    gradient = jax.jit(jax.grad(objective))(CUSTOM)
    objective = jax.jit(objective)  # one compilation for all the finite differences
    for field in dataclasses.fields(MemoryParameters):
        value = getattr(CUSTOM, field.name)
        step = 1e-6 * max(abs(value), 1.0)
        up = float(objective(dataclasses.replace(CUSTOM, **{field.name: value + step})))
        down = float(objective(dataclasses.replace(CUSTOM, **{field.name: value - step})))
        derivative = float(getattr(gradient, field.name))
        assert derivative == pytest.approx((up - down) / (2 * step), rel=1e-6, abs=1e-9), field.name
        assert abs(derivative) > 1e-4, field.name  # every parameter matters in this scene
    depth_gradient = jax.grad(objective, argnums=1)(CUSTOM, 1.0)
    finite = (float(objective(CUSTOM, 1.0 + 1e-6)) - float(objective(CUSTOM, 1.0 - 1e-6))) / 2e-6
    assert float(depth_gradient) == pytest.approx(finite, rel=1e-6)


def test_vmap_over_parameters_and_per_element_parameters():
    times = np.arange(0.0, 20.0, 0.1)
    stimulus = np.tile(press_stimulus(times, [(-0.3, 1.0, 5.0)])[:, None], (1, 2))
    batch = jax.tree.map(lambda *leaves: jnp.stack([jnp.asarray(x, float) for x in leaves]), bare_skin(), over_foam())
    batched = jax.vmap(memory_response, in_axes=(None, None, 0))(stimulus, times, batch)
    for index, p in enumerate((bare_skin(), over_foam())):
        np.testing.assert_allclose(batched[index], memory_response(stimulus, times, p), rtol=0, atol=1e-15)
    # One value per element: element 0 a bare skin, element 1 over foam.
    mixed = jax.tree.map(lambda *leaves: np.array(leaves, float), bare_skin(), over_foam())
    mixed = MemoryParameters(**{f.name: getattr(mixed, f.name) for f in dataclasses.fields(mixed)})
    per_element = memory_response(stimulus, times, mixed)
    np.testing.assert_allclose(per_element[:, 0], batched[0, :, 0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(per_element[:, 1], batched[1, :, 1], rtol=0, atol=1e-15)


def test_float32_is_kept_and_close():
    times = np.arange(0.0, 30.0, 0.1)
    stimulus = press_stimulus(times, TWO_PRESSES)[:, None]
    single = memory_response(stimulus.astype(np.float32), times, over_foam())
    assert single.dtype == np.float32
    np.testing.assert_allclose(single, memory_response(stimulus, times, over_foam()), rtol=0, atol=1e-6)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("fast_time", -1.0),
        ("slow_time", 0.0),
        ("fatigue_recovery_time", -100.0),
        ("fast_fraction", 1.2),
        ("slow_fraction", -0.1),
        ("relaxation", 1.5),
        ("first_cycle_offset", -0.01),
        ("fatigue_limit", 2.0),
        ("fatigue_rate", -1.0),
        ("gain", 0.0),
        ("slow_time", float("nan")),
        ("fast_time", np.array([1.0, -2.0])),
        ("relaxation", "a lot"),
    ],
)
def test_bad_parameters_name_the_field(field, value):
    with pytest.raises(ValueError, match=rf"MemoryParameters\.{field}\b"):
        MemoryParameters(**{field: value})


def test_bad_fraction_sum_and_bad_frames():
    with pytest.raises(ValueError, match=r"fast_fraction \+ MemoryParameters\.slow_fraction"):
        MemoryParameters(fast_fraction=0.6, slow_fraction=0.5)
    with pytest.raises(ValueError, match=r"times\[2\] < times\[1\]"):
        memory_response(np.zeros((3, 2)), np.array([0.0, 2.0, 1.0]), over_foam())
    with pytest.raises(ValueError, match=r"before state\.time"):
        memory_response(np.zeros((2, 2)), np.array([0.0, 1.0]), over_foam(), initial_state(2, time=5.0))
    with pytest.raises(ValueError, match="shape"):
        memory_response(np.zeros((3, 2)), np.array([0.0, 1.0]), over_foam())
    with pytest.raises(ValueError, match="finite"):
        memory_response(np.full((2, 2), np.nan), np.array([0.0, 1.0]), over_foam())
    # Traced parameters are not checked (no values to check): construction under jit works.
    assert jax.jit(lambda tau: MemoryParameters(fast_time=tau).fast_time)(-1.0) == -1.0


@pytest.mark.slow
def test_gradient_is_finite_for_the_tiny_tails_of_smooth_edges():
    """A smooth-edged touch leaves stimuli of 1e-200 far from it; the loading weight a_prev / a_k
    must not overflow its derivative there (it did: NaN gradients through the simulator)."""
    times = jnp.arange(4) * 0.1

    def total(amplitude):
        stimulus = jnp.array([0.0, 1e-200, 2e-200, 0.0])[:, None] * amplitude
        return memory_response(stimulus, times, MemoryParameters()).sum()

    gradient = float(jax.grad(total)(-0.3))
    assert np.isfinite(gradient) and abs(gradient) < 1e-190


@pytest.mark.parametrize("previous", [-0.3, 0.2])
def test_the_response_is_continuous_in_the_new_stimulus_across_zero(previous):
    """After a held load a_prev, the response to the next frame's stimulus a_k has no jump: not at
    zero and not at -a_prev (a load of the other sign starts afresh from zero), on a fatigued,
    first-cycled skin. A jump would stall every gradient fit of noisy stimuli."""
    parameters = MemoryParameters()
    # A deeper first press, then a_prev held: the largest stimulus seen is beyond +-a_prev.
    state = advance(apply_stimulus(initial_state(1), jnp.array([2 * previous])), parameters, 1.0)
    state = advance(apply_stimulus(state, jnp.array([previous])), parameters, 2.5)
    assert float(state.fatigue[0]) > 0.05
    # Stay below the largest stimulus seen: a new extreme of the other sign moves the offset.
    stimuli = jnp.linspace(-1.9 * abs(previous), 1.9 * abs(previous), 4001)
    responses = jax.vmap(lambda a: read_response(apply_stimulus(state, a[None]), parameters)[0])(stimuli)
    steps = np.abs(np.diff(np.asarray(responses)))
    slope = float(parameters.gain) + float(parameters.first_cycle_offset)
    assert steps.max() <= 1.01 * slope * float(stimuli[1] - stimuli[0])
    assert np.all(np.diff(np.asarray(responses)) > 0)  # increasing: the correction inverts it
