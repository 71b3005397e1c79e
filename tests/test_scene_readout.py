"""The board's readout in scenes: readout mixing and reading gains. Neutral values change
nothing, a known mixing gives the readings of `diffeit.readout.Readout` of the forward model's
potentials, gains multiply exactly, the order is mixing, gains, noise, both effects round-trip
through TOML, bad values name the effect, and gradients flow through the weights and gains."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffeit as de
from diffeit.readout import Readout
from diffeit.scene import (
    Disc,
    MeasurementNoise,
    Noise,
    Press,
    ReadingGains,
    ReadoutMixing,
    Scene,
    Skin,
    Touch,
)

L = 8
SKIN = Skin(
    geometry={"kind": "disc", "n_electrodes": L, "electrode_width": 0.25, "radius": 1.0}, h=0.35, simulation_h=0.25
)
PROTOCOL = SKIN.make_protocol()
M = PROTOCOL.n_measurements
TOUCH = Touch(Disc([0.4, 0.1], 0.35), -0.3, Press(start=0.1, hold=0.2))
RNG = np.random.default_rng(5)
SOURCE, SINK = 0.04, -0.03
OFFSETS = RNG.uniform(-0.05, 0.05, L)
GAINS = RNG.uniform(0.8, 1.2, M)


def scene_with(*effects, duration=0.5) -> Scene:
    return Scene(skin=SKIN, touches=(TOUCH,), frame_rate=10.0, duration=duration, effects=effects)


@pytest.fixture(scope="module")
def plain():
    return de.simulate(scene_with(), progress=False)


@pytest.fixture(scope="module")
def mixed():
    return de.simulate(scene_with(ReadoutMixing(SOURCE, SINK, OFFSETS)), progress=False)


def test_zero_mixing_and_unit_gains_change_nothing(plain):
    neutral = de.simulate(scene_with(ReadoutMixing(0.0, 0.0, np.zeros(L)), ReadingGains(np.ones(M))), progress=False)
    assert neutral.stages == (*plain.stages, "readout mixing", "reading gains")
    assert neutral.solves == plain.solves
    scale = float(np.abs(np.asarray(plain.frames)).max())
    np.testing.assert_allclose(np.asarray(neutral.frames), np.asarray(plain.frames), rtol=0, atol=1e-12 * scale)
    np.testing.assert_allclose(np.asarray(neutral.reference), np.asarray(plain.reference), rtol=0, atol=1e-12 * scale)
    np.testing.assert_array_equal(np.asarray(neutral.truth), np.asarray(plain.truth))


def mixing_weights() -> np.ndarray:
    """(M, L) the mixing weights X of the readout's docstring, built here by hand."""
    x = np.zeros((M, L))
    for m in range(M):
        drive = PROTOCOL.drive[PROTOCOL.drive_index[m]]
        positive = int(np.flatnonzero(PROTOCOL.measure[m] == 1)[0])
        x[m, int(np.flatnonzero(drive == 1)[0])] += SOURCE
        x[m, int(np.flatnonzero(drive == -1)[0])] += SINK
        for j in range(L):
            x[m, (positive + j) % L] += OFFSETS[j]
    return x


def test_a_known_mixing_reads_the_forward_models_potentials_through_the_readout(plain, mixed):
    assert mixed.stages == (*plain.stages, "readout mixing")
    np.testing.assert_array_equal(np.asarray(mixed.truth), np.asarray(plain.truth))
    model = de.ForwardModel(mixed.mesh, PROTOCOL, SKIN.contact_impedances(), drive_current=SKIN.drive_current)
    readout = Readout(PROTOCOL, SOURCE, SINK, OFFSETS)
    np.testing.assert_allclose(np.asarray(readout.mixing(PROTOCOL)), mixing_weights(), rtol=0, atol=1e-15)
    weights = PROTOCOL.measure + mixing_weights()
    background = np.asarray(mixed.truth[0])
    conductivities = [background] + [np.asarray(sigma) for sigma in mixed.truth]
    expected = []
    for sigma in conductivities:
        potentials = np.asarray(model.potentials(sigma).electrode)
        readings = np.asarray(readout.readings(PROTOCOL, potentials))
        # The same by hand, from the potentials: sum_l (W + X)_ml U_(d(m), l).
        np.testing.assert_allclose(readings, np.sum(weights * potentials[PROTOCOL.drive_index], axis=1), rtol=1e-12)
        expected.append(readings)
    np.testing.assert_allclose(np.asarray(mixed.reference), expected[0], rtol=1e-12)
    np.testing.assert_allclose(np.asarray(mixed.frames), np.stack(expected[1:]), rtol=1e-12)
    assert not np.allclose(np.asarray(mixed.frames), np.asarray(plain.frames), rtol=1e-3)


def test_gains_multiply_each_reading_exactly(plain, mixed):
    gained = de.simulate(scene_with(ReadingGains(GAINS)), progress=False)
    assert gained.stages == (*plain.stages, "reading gains")
    np.testing.assert_array_equal(np.asarray(gained.frames), GAINS * np.asarray(plain.frames))
    np.testing.assert_array_equal(np.asarray(gained.reference), GAINS * np.asarray(plain.reference))
    # After the mixing: the gains multiply the mixed readings.
    both = de.simulate(scene_with(ReadingGains(GAINS), ReadoutMixing(SOURCE, SINK, OFFSETS)), progress=False)
    assert both.stages == (*plain.stages, "readout mixing", "reading gains")
    np.testing.assert_array_equal(np.asarray(both.frames), GAINS * np.asarray(mixed.frames))
    np.testing.assert_array_equal(np.asarray(both.reference), GAINS * np.asarray(mixed.reference))


def test_noise_comes_after_the_gains_relative_to_the_reference_the_board_reads(plain):
    """Gains of 2: the readings and the reference double, and so does percent noise."""
    noise = MeasurementNoise(Noise.percent(1.0), seed=3)
    noisy = de.simulate(scene_with(noise), progress=False)
    doubled = de.simulate(scene_with(noise, ReadingGains(np.full(M, 2.0))), progress=False)
    assert doubled.stages == (*plain.stages, "reading gains", "noise")
    np.testing.assert_allclose(
        np.asarray(doubled.frames) - 2 * np.asarray(plain.frames),
        2 * (np.asarray(noisy.frames) - np.asarray(plain.frames)),
        rtol=1e-9,
        atol=1e-15,
    )
    # Volts of noise do not scale with the gains: the noise is added after them.
    volts = MeasurementNoise(Noise.volts(1e-4), seed=3)
    residual = np.asarray(de.simulate(scene_with(volts), progress=False).frames) - np.asarray(plain.frames)
    gained = np.asarray(de.simulate(scene_with(volts, ReadingGains(np.full(M, 2.0))), progress=False).frames)
    np.testing.assert_allclose(gained - 2 * np.asarray(plain.frames), residual, rtol=1e-6, atol=1e-15)


def assert_same_effects(again: Scene, scene: Scene) -> None:
    assert jax.tree_util.tree_structure(again) == jax.tree_util.tree_structure(scene)
    for leaf, expected in zip(jax.tree_util.tree_leaves(again), jax.tree_util.tree_leaves(scene), strict=True):
        np.testing.assert_array_equal(np.asarray(leaf), np.asarray(expected))
    assert again.to_dict() == scene.to_dict()


def test_toml_round_trip_keeps_both_effects(tmp_path):
    scene = scene_with(ReadoutMixing(SOURCE, SINK, OFFSETS), ReadingGains(GAINS))
    again = Scene.from_toml(scene.to_toml(tmp_path / "scene.toml"))
    assert_same_effects(again, scene)
    np.testing.assert_array_equal(np.asarray(again.effect("readout_mixing").offsets), OFFSETS)
    np.testing.assert_array_equal(np.asarray(again.effect("reading_gains").gains), GAINS)
    assert float(again.effect("readout_mixing").source) == SOURCE
    # The random forms read as the classmethods draw them, and save as their values.
    text = "[effects.readout_mixing]\nlargest = 0.2\nseed = 4\n[effects.reading_gains]\nspread = 0.1\nseed = 6\n"
    drawn = Scene.from_toml_string(f"[skin]\nn_electrodes = {L}\nh = 0.35\nsimulation_h = 0.25\n{text}")
    expected = drawn.replace(effects=(ReadoutMixing.random(L, 0.2, seed=4), ReadingGains.random(M, 0.1, seed=6)))
    assert_same_effects(drawn, expected)
    assert_same_effects(Scene.from_toml_string(drawn.to_toml_string()), drawn)
    # Units of ratios: "5 %" is 0.05; source and sink default to 0.
    short = Scene.from_toml_string(
        f"[skin]\nn_electrodes = {L}\nh = 0.35\n[effects.readout_mixing]\noffsets = {['5 %'] + [0] * (L - 1)}\n"
    )
    mixing = short.effect("readout_mixing")
    assert (float(mixing.source), float(mixing.sink), float(mixing.offsets[0])) == (0.0, 0.0, 0.05)


def test_simulation_with_both_effects_round_trips_through_the_frames_file(tmp_path):
    scene = scene_with(ReadoutMixing(SOURCE, SINK, OFFSETS), ReadingGains(GAINS), duration=0.2)
    simulation = de.simulate(scene, progress=False)
    again = de.scene.read_simulation(simulation.save(tmp_path / "frames.h5"))
    np.testing.assert_array_equal(np.asarray(again.frames), np.asarray(simulation.frames))
    assert_same_effects(again.scene, scene)
    assert again.stages == simulation.stages


def test_random_draws_what_the_docstrings_say():
    mixing = ReadoutMixing.random(L, 0.3, seed=2)
    source, far = np.random.default_rng(2).uniform(0.0, 0.3, 2)
    assert (float(mixing.source), float(mixing.sink)) == (source, 0.0)
    expected = np.zeros(L)
    expected[L // 2] = far
    np.testing.assert_array_equal(np.asarray(mixing.offsets), expected)
    gains = np.asarray(ReadingGains.random(M, 0.2, seed=2).gains)
    np.testing.assert_array_equal(gains, np.random.default_rng(2).uniform(0.8, 1.2, M))
    assert gains.shape == (M,) and np.all((gains >= 0.8) & (gains < 1.2))
    np.testing.assert_array_equal(np.asarray(ReadingGains.random(M, 0.0).gains), np.ones(M))
    assert np.all(np.asarray(ReadoutMixing.random(L, 0.0).offsets) == 0)


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: scene_with(ReadoutMixing(0.0, 0.0, np.zeros(L - 1))), r"effects\.readout_mixing\.offsets has shape"),
        (lambda: scene_with(ReadingGains(np.ones(M + 1))), r"effects\.reading_gains\.gains has shape \(41,\)"),
        (lambda: ReadoutMixing(0.0, 0.0, [0.0, np.nan] + [0.0] * (L - 2)), r"effects\.readout_mixing\.offsets"),
        (lambda: ReadoutMixing(np.nan, 0.0, np.zeros(L)), r"effects\.readout_mixing\.source must be finite"),
        (lambda: ReadoutMixing(0.0, np.inf, np.zeros(L)), r"effects\.readout_mixing\.sink must be finite"),
        (lambda: ReadoutMixing([0.1, 0.2], 0.0, np.zeros(L)), r"effects\.readout_mixing\.source must be one number"),
        (lambda: ReadoutMixing(0.0, 0.0, 0.1), r"effects\.readout_mixing\.offsets must be one weight per electrode"),
        (lambda: ReadoutMixing(0.0, 0.0, "zero"), r"effects\.readout_mixing\.offsets must be a number"),
        (lambda: ReadingGains(np.r_[1.0, np.nan, np.ones(M - 2)]), r"effects\.reading_gains\.gains must be finite"),
        (lambda: ReadingGains(1.0), r"effects\.reading_gains\.gains must be one gain per reading"),
        (lambda: ReadoutMixing.random(L, -0.1), r"effects\.readout_mixing\.largest"),
        (lambda: ReadoutMixing.random(1), r"effects\.readout_mixing: n_electrodes"),
        (lambda: ReadingGains.random(M, 1.0), r"effects\.reading_gains\.spread"),
        (lambda: ReadingGains.random(M, float("nan")), r"effects\.reading_gains\.spread"),
    ],
)
def test_bad_values_name_the_effect(make, match):
    with pytest.raises(ValueError, match=match):
        make()


@pytest.mark.parametrize(
    ("effects", "match"),
    [
        ("[effects.readout_mixing]\noffsets = [0, 0, 0]\n", r"effects\.readout_mixing\.offsets has shape \(3,\)"),
        (f"[effects.readout_mixing]\noffsets = {[0.0] * L}\nlargest = 0.1\n", r"effects\.readout_mixing: give either"),
        ("[effects.readout_mixing]\nsource = 0.1\n", r"effects\.readout_mixing\.offsets is missing"),
        ("[effects.readout_mixing]\nsource = nan\noffsets = [0, 0, 0, 0, 0, 0, 0, 0]\n", r"readout_mixing\.source"),
        ("[effects.readout_mixing]\nlargest = 0.1\nseed = 1.5\n", r"effects\.readout_mixing\.seed must be an integer"),
        ("[effects.readout_mixing]\nlargest = 0.1\nscale = 1\n", r"effects\.readout_mixing: unknown keys \['scale'\]"),
        ("[effects.reading_gains]\ngains = [1, 1]\n", r"effects\.reading_gains\.gains has shape \(2,\)"),
        (f"[effects.reading_gains]\ngains = {[1.0] * (M - 1)} \n", r"effects\.reading_gains\.gains has shape"),
        (f"[effects.reading_gains]\ngains = {['nan'] + [1.0] * (M - 1)}\n", r"effects\.reading_gains\.gains"),
        ("[effects.reading_gains]\n", r"effects\.reading_gains: give either gains"),
        ("[effects.reading_gains]\nspread = 2\n", r"effects\.reading_gains\.spread must be in \[0, 1\)"),
        ('[effects.reading_gains]\nspread = "1 mV"\n', r"effects\.reading_gains\.spread"),
    ],
)
def test_bad_scene_files_name_the_effect(effects, match):
    text = f"[skin]\nn_electrodes = {L}\nh = 0.35\nsimulation_h = 0.25\n{effects}".replace("'nan'", "nan")
    with pytest.raises(ValueError, match=match):
        Scene.from_toml_string(text)


def test_gradients_through_the_mixing_and_gains_match_central_differences():
    scene = scene_with(ReadoutMixing(SOURCE, SINK, OFFSETS), ReadingGains(GAINS), duration=0.3)
    weights = np.random.default_rng(1).normal(size=(3, M))

    def loss(scene):
        simulation = de.simulate(scene, progress=False)
        return jnp.sum(weights * (simulation.frames - simulation.reference)) * 1e3 + jnp.sum(simulation.reference)

    gradient = jax.grad(loss)(scene)
    paths = {jax.tree_util.keystr(p): g for p, g in jax.tree_util.tree_flatten_with_path(gradient)[0]}

    def moved(path, step):
        leaves, tree = jax.tree_util.tree_flatten_with_path(scene)
        values = [leaf + step if jax.tree_util.keystr(p) == path else leaf for p, leaf in leaves]
        return jax.tree_util.tree_unflatten(tree, values)

    direction = np.random.default_rng(2)
    checks = {
        ".effects[0].source": np.asarray(1e-3),
        ".effects[0].sink": np.asarray(1e-3),
        ".effects[0].offsets": 1e-3 * direction.normal(size=L),
        ".effects[1].gains": 1e-3 * direction.normal(size=M),
    }
    for path, step in checks.items():
        derivative = float(np.sum(np.asarray(paths[path]) * step))
        fd = (float(loss(moved(path, step))) - float(loss(moved(path, -step)))) / 2
        assert np.all(np.isfinite(np.asarray(paths[path]))), path
        assert derivative != 0, path
        assert derivative == pytest.approx(fd, rel=1e-7, abs=1e-14), path
