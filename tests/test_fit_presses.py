"""diffeit.fit.memory_from_presses: the memory fit of a labelled calibration session (known
footprints and hold windows, unknown depths), its standard errors and its checks."""

import numpy as np
import pytest

import diffeit as de
from diffeit.fit import memory_from_press_readings, memory_from_presses
from diffeit.fit._presses import PressMemoryFit
from diffeit.memory import MemoryParameters, memory_response
from diffeit.results import RESULTS

# A skin of our own, between the presets (the fit starts from over_foam).
TRUTH = MemoryParameters(fast_fraction=0.25, fast_time=0.8, slow_fraction=0.35, slow_time=6.0, relaxation=0.2)
FREE = ("fast_fraction", "fast_time", "slow_fraction", "slow_time", "relaxation")
# Four presses (centre m, radius m, start s, hold s) of holds 1-4 s at different places, 10 Hz.
PRESSES = [
    ((-0.4, 0.3), 0.3, 1.0, 1.0),
    ((0.4, 0.2), 0.3, 9.0, 2.0),
    ((0.0, -0.4), 0.3, 18.0, 3.0),
    ((-0.2, -0.1), 0.25, 28.0, 4.0),
]
DEPTHS = np.array([-0.3, -0.2, -0.25, -0.15])  # dsigma/sigma at full cover
TIMES = np.arange(400) * 0.1  # seconds
NOISE = 0.01  # of the peak change, per element and frame
SEEDS = 10


@pytest.fixture(scope="module")
def session():
    """The footprints (K, E), windows (K, 2) and noise-free images (T, E) of the session."""
    mesh = de.mesh.disc(16, h=0.15)
    patterns = np.stack([de.mesh.disc_fraction(mesh, centre, radius) for centre, radius, _, _ in PRESSES])
    windows = np.array([[start, start + hold] for _, _, start, hold in PRESSES])
    held = (TIMES[:, None] >= windows[:, 0]) & (TIMES[:, None] <= windows[:, 1])
    clean = np.asarray(memory_response((held * DEPTHS) @ patterns, TIMES, TRUTH))
    return patterns, windows, clean


def noisy(clean: np.ndarray, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return clean + NOISE * np.abs(clean).max() * rng.standard_normal(clean.shape)


def deviations(fit: PressMemoryFit) -> np.ndarray:
    """(5 + K,) |fit - truth| / standard error of each memory parameter, then each depth."""
    memory = [abs(float(getattr(fit.memory, n)) - getattr(TRUTH, n)) / fit.standard_errors[n] for n in FREE]
    depths = np.abs(fit.depths - DEPTHS) / fit.standard_errors["depths"]
    return np.concatenate([memory, depths])


def test_fit_recovers_the_truth_within_its_errors(session):
    patterns, windows, clean = session
    images = noisy(clean, 0)
    fit = memory_from_presses(images, TIMES, patterns, windows)
    assert isinstance(fit, PressMemoryFit)
    assert fit.result == RESULTS.successful
    assert fit.depths.shape == (len(PRESSES),)
    assert set(fit.standard_errors) == {*FREE, "depths"}
    assert np.all(deviations(fit) <= 3)
    for name in FREE:
        assert float(getattr(fit.memory, name)) == pytest.approx(getattr(TRUTH, name), rel=0.05), name
        assert 0 < fit.standard_errors[name] < 0.05 * getattr(TRUTH, name), name
    np.testing.assert_allclose(fit.depths, DEPTHS, rtol=0.01)
    # Fields not fitted keep the initial (over_foam) values; the noise estimate is right.
    assert float(fit.memory.gain) == 1.0 and float(fit.memory.first_cycle_offset) == 0.05
    assert 0.9 < fit.reduced_chi_square < 1.1
    # The misfit is the noise's (mostly that of the untouched elements, 1% of the peak each).
    assert fit.misfit == pytest.approx(np.linalg.norm(images - clean) / np.linalg.norm(images), rel=0.01)
    np.testing.assert_allclose(fit.response, clean, atol=0.2 * NOISE * np.abs(clean).max())


def test_errors_cover_the_truth_over_noise_seeds(session):
    """Over 10 noise seeds, |fit - truth| <= 2 standard errors for >= 80% of (parameter x seed)
    (95% for a Gaussian error; measured: 0.92 of all 90, 0.88 of the 50 memory ones, 0.975 of the
    40 depths)."""
    patterns, windows, clean = session
    within = np.array(
        [deviations(memory_from_presses(noisy(clean, seed), TIMES, patterns, windows)) <= 2 for seed in range(SEEDS)]
    )
    assert within.mean() >= 0.8
    assert within[:, : len(FREE)].mean() >= 0.8


def test_noise_given_and_fields_held(session):
    """A known noise level and a smaller free set (the relaxation held at its truth)."""
    patterns, windows, clean = session
    sigma = NOISE * np.abs(clean).max()
    free = ("fast_fraction", "fast_time", "slow_fraction", "slow_time")
    initial = MemoryParameters(relaxation=0.2)
    fit = memory_from_presses(noisy(clean, 1), TIMES, patterns, windows, initial=initial, free=free, noise=sigma)
    assert set(fit.standard_errors) == {*free, "depths"}
    assert float(fit.memory.relaxation) == 0.2
    for name in free:
        assert abs(float(getattr(fit.memory, name)) - getattr(TRUTH, name)) <= 3 * fit.standard_errors[name], name


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda p, w, y: (p[:, :-1], w, y), "patterns must have shape"),
        (lambda p, w, y: (p[0], w, y), "patterns must have shape"),
        (lambda p, w, y: (p * 2, w, y), r"\[0, 1\]"),
        (lambda p, w, y: (np.concatenate([p, 0 * p[:1]]), np.concatenate([w, w[:1]]), y), "cover no element"),
        (lambda p, w, y: (p, w[:-1], y), "windows must have shape"),
        (lambda p, w, y: (p, w[:, :1], y), "windows must have shape"),
        (lambda p, w, y: (p, w[:, ::-1], y), "end before they start"),
        (lambda p, w, y: (p, w + 20.0, y), "outside the times"),
        (lambda p, w, y: (p, w - 1.5, y), "outside the times"),
        (lambda p, w, y: (p, np.stack([w[:, 0] + 0.02, w[:, 0] + 0.03], axis=1), y), "hold no frame"),
        (lambda p, w, y: (p, w * np.nan, y), "finite"),
        (lambda p, w, y: (p, w, y[:, :-1]), "patterns must have shape"),
    ],
)
def test_mismatched_inputs_raise(session, change, message):
    patterns, windows, clean = session
    patterns, windows, images = change(patterns, windows, clean)
    with pytest.raises(ValueError, match=message):
        memory_from_presses(images, TIMES, patterns, windows)


def test_gain_is_not_fitted(session):
    patterns, windows, clean = session
    with pytest.raises(ValueError, match="gain"):
        memory_from_presses(clean, TIMES, patterns, windows, free=("gain",))


def test_modes_started_in_the_other_order_are_reported_quicker_first(session):
    """Started with the mode labels exchanged, the fit reports the quicker mode as fast, with the
    errors exchanged alike: the same fit as from over_foam."""
    patterns, windows, clean = session
    images = noisy(clean, 0)
    swapped = MemoryParameters(fast_fraction=0.3, fast_time=7.0, slow_fraction=0.3, slow_time=1.0)
    plain = memory_from_presses(images, TIMES, patterns, windows)
    fit = memory_from_presses(images, TIMES, patterns, windows, initial=swapped)
    for name in FREE:
        assert float(getattr(fit.memory, name)) == pytest.approx(float(getattr(plain.memory, name)), rel=1e-5)
        assert fit.standard_errors[name] == pytest.approx(plain.standard_errors[name], rel=1e-4)


# --- memory_from_press_readings: the same session read as readings ---------------------------------

N_READINGS = 40


def press_readings(session, seed: int, noise: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """(T, M) readings of the session's presses: each press's own response (a skin rested at the
    first frame, pressed alone), bent as r / (1 + b r), times a signature of its own, a lasting
    step of its own from its start and an offset; noise `noise` of the largest reading. And the
    bends (K,)."""
    _, windows, _ = session
    rng = np.random.default_rng(100 + seed)
    held = (TIMES[:, None] >= windows[:, 0]) & (TIMES[:, None] <= windows[:, 1])
    response = np.asarray(memory_response(held * DEPTHS, TIMES, TRUTH))
    bends = rng.uniform(0.3, 0.6, len(PRESSES))
    signatures, steps = rng.standard_normal((2, len(PRESSES), N_READINGS))
    started = np.cumsum(held, axis=0) > 0
    clean = rng.standard_normal(N_READINGS) + (response / (1 + bends * response)) @ signatures + 0.01 * started @ steps
    return clean + noise * np.abs(clean).max() * rng.standard_normal(clean.shape), bends


def test_readings_give_the_memory_within_its_errors_over_noise_seeds(session):
    """Over 10 noise seeds, |fit - truth| <= 2 standard errors for >= 90% of the 50 (measured: 48
    of 50), the errors neither far too small nor far too large (the deviations' RMS in standard
    errors, measured 0.98), and the noise estimated per reading (measured: 0.98 of the truth)."""
    _, windows, _ = session
    deviations, noises = [], []
    for seed in range(SEEDS):
        readings, bends = press_readings(session, seed)
        fit = memory_from_press_readings(readings, TIMES, windows, DEPTHS, bends=bends)
        assert fit.result == RESULTS.successful
        assert set(fit.standard_errors) == set(FREE)
        deviations.append([(float(getattr(fit.memory, n)) - getattr(TRUTH, n)) / fit.standard_errors[n] for n in FREE])
        noises.append(fit.noise / (0.01 * np.abs(readings).max()))
    deviations = np.array(deviations)
    assert np.mean(np.abs(deviations) <= 2) >= 0.9
    assert 0.7 < np.sqrt(np.mean(deviations**2)) < 1.4
    assert np.mean(noises) == pytest.approx(1.0, abs=0.05)


def test_readings_without_their_bends_or_steps_mislead_the_fit(session):
    """The readings' bend and each press's lasting step are what the fit must know: read as if
    linear, the slow fraction lies many standard errors off (a check that the test's readings need
    what the fit models; measured: 0.15 standard errors off with the bends, 13 without)."""
    _, windows, _ = session
    readings, bends = press_readings(session, 0, noise=0.002)
    bent = memory_from_press_readings(readings, TIMES, windows, DEPTHS, bends=bends)
    linear = memory_from_press_readings(readings, TIMES, windows, DEPTHS)
    assert abs(float(bent.memory.slow_fraction) - TRUTH.slow_fraction) < 3 * bent.standard_errors["slow_fraction"]
    assert abs(float(linear.memory.slow_fraction) - TRUTH.slow_fraction) > 5 * linear.standard_errors["slow_fraction"]


FOUR_QUICK = np.array([[0.0, 0.1], [0.2, 0.3], [0.4, 0.5], [0.6, 0.7]])


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda y, t, w, d, b: (y[:, :, None], t, w, d, b), r"readings must have shape \(T, E\)"),
        (lambda y, t, w, d, b: (y * np.nan, t, w, d, b), "readings must be finite"),
        (lambda y, t, w, d, b: (y[:10], t[:10], FOUR_QUICK, d, b), "needs more than 10 frames; got 10"),
        (lambda y, t, w, d, b: (y, t, w, d * 0, b), "depths must be"),
        (lambda y, t, w, d, b: (y, t, w, d, b[:-1]), "bends must be"),
        (lambda y, t, w, d, b: (y, t, w, d, 0 * b + 4), r"1 \+ b d > 0"),
        (lambda y, t, w, d, b: (y, t, w[:-1], d, b), "windows must have shape"),
        (lambda y, t, w, d, b: (y, t, w + 60.0, d, b), "outside the times"),
    ],
)
def test_readings_fit_refuses_what_does_not_match(session, change, message):
    _, windows, _ = session
    readings, bends = press_readings(session, 0)
    readings, times, windows, depths, bends = change(readings, TIMES, windows, DEPTHS, bends)
    with pytest.raises(ValueError, match=message):
        memory_from_press_readings(readings, times, windows, depths, bends=bends)
