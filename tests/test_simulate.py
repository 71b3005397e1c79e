"""The simulator: only the declared stages run, each effect changes only what it should, output
round-trips through the frames file, and gradients flow through the whole pipeline."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffeit as de
from diffeit.scene import (
    CommonModeDrift,
    ContactDrift,
    Disc,
    ElectrodePositionError,
    MeasurementNoise,
    MemoryParameters,
    Noise,
    OpenElectrodes,
    Press,
    Scene,
    Skin,
    Touch,
    _simulate,
)

SKIN = Skin(h=0.2, simulation_h=0.12)
TOUCH = Touch(Disc([0.4, 0.1], 0.25), -0.3, Press(start=0.2, hold=0.5))


def scene_with(*effects, touches=(TOUCH,), duration=1.0) -> Scene:
    return Scene(skin=SKIN, touches=touches, frame_rate=10.0, duration=duration, effects=effects)


@pytest.fixture(scope="module")
def plain():
    return de.simulate(scene_with())


def test_plain_scene_is_exact_forward_voltages(plain):
    """Without effects: touches, conductivity, contact impedance, forward; one solve per state."""
    assert plain.stages == ("touches", "conductivity", "contact impedance", "forward")
    assert plain.solves == 2  # the untouched skin (reference and frames 0, 1, 7, 8, 9) and the press
    assert plain.frames.shape == (10, 208) and plain.truth.shape == (10, plain.mesh.n_elements)
    model = de.ForwardModel(plain.mesh, de.protocol.adjacent(16), contact_impedance=0.01)
    background = np.full(plain.mesh.n_elements, 0.01)
    np.testing.assert_array_equal(np.asarray(plain.truth[0]), background)
    np.testing.assert_allclose(np.asarray(plain.reference), np.asarray(model.measure(background)), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(plain.frames[4]), np.asarray(model.measure(plain.truth[4])), rtol=1e-12)
    untouched = [0, 1, 7, 8, 9]
    np.testing.assert_array_equal(np.asarray(plain.frames)[untouched], np.tile(plain.reference, (5, 1)))
    # The press: about -0.3 under the footprint, 0 far from it.
    change = np.asarray(plain.truth[4]) / 0.01 - 1
    distance = np.linalg.norm(plain.mesh.element_centroids - [0.4, 0.1], axis=1)
    assert np.all(np.abs(change[distance < 0.05] + 0.3) < 1e-5)  # the edge's tail, five widths away
    assert np.all(np.abs(change[distance > 0.6]) < 1e-12)


def test_static_scene_costs_one_solve():
    static = de.simulate(scene_with(touches=()))
    assert static.stages == ("conductivity", "contact impedance", "forward")
    assert static.solves == 1
    np.testing.assert_array_equal(np.asarray(static.frames), np.tile(static.reference, (10, 1)))


def test_undeclared_stages_never_run(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("an undeclared stage ran")

    for name in ("memory_response", "add_noise", "add_drift", "contact_impedance", "open_contact_impedance"):
        monkeypatch.setattr(_simulate, name, refuse)
    monkeypatch.setattr(_simulate, "stimulus", refuse)
    calls = []
    original = _simulate.Forward._solve
    monkeypatch.setattr(_simulate.Forward, "_solve", lambda self, s, z: calls.append(len(s)) or original(self, s, z))
    simulation = de.simulate(scene_with(touches=()))
    assert calls == [1]
    assert simulation.solves == 1


def test_declared_stages_run_once_each(monkeypatch):
    counts = {}

    def counting(name):
        original = getattr(_simulate, name)

        def wrapper(*args, **kwargs):
            counts[name] = counts.get(name, 0) + 1
            return original(*args, **kwargs)

        monkeypatch.setattr(_simulate, name, wrapper)

    for name in ("stimulus", "memory_response", "add_noise", "add_drift", "contact_impedance"):
        counting(name)
    scene = scene_with(
        MemoryParameters(), MeasurementNoise(Noise.percent(0.5)), CommonModeDrift(offset=1e-3), ContactDrift(0.01)
    )
    simulation = de.simulate(scene)
    assert simulation.stages == (
        "touches",
        "memory",
        "conductivity",
        "contact impedance",
        "forward",
        "noise",
        "common-mode drift",
    )
    # Noise and drift act on the frames and, separately, the reference.
    assert counts == {"stimulus": 1, "memory_response": 1, "contact_impedance": 1, "add_drift": 2, "add_noise": 2}
    # Drifting contacts: every frame differs from every other; frame 0 is the reference's state.
    assert simulation.solves == 10


# Each effect with parameters that do nothing: bit-identical to the scene without it.
NEUTRAL = [
    MemoryParameters(
        fast_fraction=0.0, slow_fraction=0.0, relaxation=0.0, first_cycle_offset=0.0, fatigue_limit=0.0, gain=1.0
    ),
    MeasurementNoise(Noise.percent(0.0)),
    CommonModeDrift(),
    ContactDrift(0.0),
]


@pytest.mark.parametrize("effect", NEUTRAL, ids=lambda e: type(e).__name__)
def test_a_neutral_effect_changes_nothing(plain, effect):
    simulation = de.simulate(scene_with(effect))
    np.testing.assert_array_equal(np.asarray(simulation.frames), np.asarray(plain.frames))
    np.testing.assert_array_equal(np.asarray(simulation.reference), np.asarray(plain.reference))
    np.testing.assert_array_equal(np.asarray(simulation.truth), np.asarray(plain.truth))


def test_each_effect_changes_only_its_part(plain):
    """Instrument effects leave the truth bit for bit; the memory changes the truth."""
    frames, truth = np.asarray(plain.frames), np.asarray(plain.truth)
    for effect in (
        MeasurementNoise(Noise.percent(0.5)),
        CommonModeDrift(offset=1e-3),
        ContactDrift(0.05),
        OpenElectrodes((5,)),
    ):
        simulation = de.simulate(scene_with(effect))
        np.testing.assert_array_equal(np.asarray(simulation.truth), truth)
        assert not np.array_equal(np.asarray(simulation.frames), frames)
    memory = de.simulate(scene_with(MemoryParameters()))
    assert not np.array_equal(np.asarray(memory.truth), truth)
    # Before the first press the skin is untouched, memory or not.
    np.testing.assert_array_equal(np.asarray(memory.frames[:2]), frames[:2])
    # Common-mode drift adds exactly its offset.
    drift = de.simulate(scene_with(CommonModeDrift(offset=1e-3)))
    np.testing.assert_allclose(np.asarray(drift.frames) - frames, 1e-3, rtol=1e-9)


def test_memory_truth_is_the_integrated_response(plain):
    parameters = de.scene.bare_skin()
    simulation = de.simulate(scene_with(parameters))
    stimulus = np.asarray(plain.truth) / 0.01 - 1
    response = np.asarray(de.scene.memory_response(stimulus, plain.times, parameters))
    np.testing.assert_allclose(np.asarray(simulation.truth), 0.01 * (1 + response), rtol=1e-12)
    # After release the skin has not recovered: a residual change of the touch's sign.
    assert np.all(response[8][stimulus[4] < -0.29] < -0.01)


def test_more_states_than_a_batch_of_solves_are_each_solved_once():
    """Memory makes every frame from the press on a state of its own: 2.5 s at 10 Hz is 24
    states (the reference and the two frames before the press one), two batches of 16 solves,
    the second padded (one shape, one compilation); every frame is its own state's voltages."""
    simulation = de.simulate(scene_with(de.scene.bare_skin(), duration=2.5), progress=False)
    assert simulation.solves == 24 and simulation.frames.shape == (25, 208)
    model = de.ForwardModel(simulation.mesh, de.protocol.adjacent(16), contact_impedance=0.01)
    expected = jax.vmap(model.measure)(simulation.truth)
    np.testing.assert_allclose(np.asarray(simulation.frames), np.asarray(expected), rtol=1e-12)


def test_noise_has_the_declared_level():
    static = scene_with(touches=(), duration=20.0)
    exact = de.simulate(static)
    rms = float(np.sqrt(np.mean(np.asarray(exact.reference) ** 2)))
    for noise, std in ((Noise.percent(2.0), 0.02 * rms), (Noise.snr_db(40.0), 0.01 * rms), (Noise.volts(1e-5), 1e-5)):
        noisy = de.simulate(static.replace(effects=(MeasurementNoise(noise, seed=11),)))
        residual = np.asarray(noisy.frames) - np.asarray(exact.frames)
        # 200 x 208 samples: the sample standard deviation is within 0.5% (3 sigma: 3 / sqrt(2 n)).
        assert residual.std() == pytest.approx(std, rel=0.005)
        assert abs(residual.mean()) < 3 * std / np.sqrt(residual.size)
        reference_residual = np.asarray(noisy.reference) - np.asarray(exact.reference)
        assert 0.7 * std < reference_residual.std() < 1.3 * std
        assert not np.allclose(reference_residual, residual[0])
    # The level is relative to the drift-free reference: a common-mode offset of 50 mV (12x the
    # readings' RMS) adds the same noise, not 12x more.
    offset = static.replace(effects=(MeasurementNoise(Noise.percent(2.0), seed=11), CommonModeDrift(offset=0.05)))
    residual = np.asarray(de.simulate(offset).frames) - np.asarray(exact.frames) - 0.05
    assert residual.std() == pytest.approx(0.02 * rms, rel=0.005)
    # Seeded: the same seed draws the same noise, another seed other noise.
    first = de.simulate(static.replace(effects=(MeasurementNoise(Noise.volts(1e-5), seed=11),)))
    other = de.simulate(static.replace(effects=(MeasurementNoise(Noise.volts(1e-5), seed=12),)))
    np.testing.assert_array_equal(np.asarray(first.frames), np.asarray(noisy.frames))
    assert not np.allclose(np.asarray(other.frames), np.asarray(noisy.frames))


def test_memory_that_takes_the_conductivity_to_zero_is_refused():
    """A touch of -0.96 over foam: recovery overshoots below -1, which no sheet can do."""
    deep = scene_with(de.scene.over_foam(), touches=(Touch(Disc([0.0, 0.0], 0.3), -0.96, Press(0.1, hold=0.3)),))
    with pytest.raises(ValueError, match=r"touches and effects\.memory: .* = -1\.008 \(<= -1"):
        de.simulate(deep, progress=False)


def test_open_electrode_loses_its_readings(plain):
    simulation = de.simulate(scene_with(OpenElectrodes((5,), fill=0.0)))
    assert simulation.lost.sum() == 52
    assert np.all(np.asarray(simulation.frames)[:, simulation.lost] == 0)
    assert np.all(np.asarray(simulation.frames)[:, ~simulation.lost] != 0)
    # The open electrode carries no current: the readings it does not touch change too.
    kept = ~simulation.lost
    assert not np.allclose(np.asarray(simulation.frames)[:, kept], np.asarray(plain.frames)[:, kept])


def test_data_come_from_a_finer_mesh_and_truth_interpolates(plain):
    reconstruction = plain.scene.reconstruction_mesh()
    assert plain.mesh.n_elements > 2 * reconstruction.n_elements
    coarse = plain.truth_on(reconstruction)
    assert coarse.shape == (10, reconstruction.n_elements)
    np.testing.assert_allclose(coarse[0], 0.01, rtol=1e-12)
    # Conservative: the integral of the change (zero near the rim, where the two inscribed
    # polygons differ) is kept.
    change = plain.truth_change_on(reconstruction)
    fine_change = np.asarray(plain.truth) - 0.01
    np.testing.assert_allclose(change @ reconstruction.element_areas, fine_change @ plain.mesh.element_areas, rtol=1e-9)
    np.testing.assert_allclose(change[0], 0.0, atol=1e-15)
    assert change[4].min() < -0.002


def test_electrode_position_error_changes_the_data_not_the_truth_mesh_size(plain):
    moved = de.simulate(scene_with(ElectrodePositionError.random(16, 0.02, seed=1)))
    assert not np.allclose(np.asarray(moved.reference), np.asarray(plain.reference), rtol=1e-3)
    # A difference frame hardly notices: the change under the touch stays within 10%.
    dv_plain = np.asarray(plain.frames[4] - plain.reference)
    dv_moved = np.asarray(moved.frames[4] - moved.reference)
    assert np.linalg.norm(dv_moved - dv_plain) < 0.1 * np.linalg.norm(dv_plain)


def test_simulation_round_trips_through_the_frames_file(tmp_path):
    scene = scene_with(MemoryParameters(), MeasurementNoise(Noise.level("medium"), seed=5), OpenElectrodes((2,)))
    simulation = de.simulate(scene)
    path = simulation.save(tmp_path / "frames.h5")
    again = de.scene.read_simulation(path)
    for name in ("times", "frames", "reference", "truth"):
        np.testing.assert_array_equal(np.asarray(getattr(again, name)), np.asarray(getattr(simulation, name)))
    np.testing.assert_array_equal(again.lost, simulation.lost)
    np.testing.assert_array_equal(again.mesh.nodes, simulation.mesh.nodes)
    assert again.scene.to_dict() == scene.to_dict()
    assert (again.stages, again.solves) == (simulation.stages, simulation.solves)
    # A plain reader sees a recording: the reconstruction mesh is its geometry.
    recording = de.io.read_frames(path)
    assert recording.geometry["h"] == 0.2 and recording.image_quantity == "conductivity"
    with pytest.raises(FileExistsError):
        simulation.save(path)


@pytest.mark.slow
def test_gradients_flow_through_the_simulator():
    """d/dparameter of a loss on the frames, against central differences."""
    scene = scene_with(MemoryParameters(), CommonModeDrift(offset=1e-4), duration=0.6)

    def loss(scene):
        simulation = de.simulate(scene, progress=False)
        return jnp.sum((simulation.frames - simulation.reference) ** 2) * 1e6

    gradient = jax.grad(loss)(scene)

    def moved(path, step):
        leaves, tree = jax.tree_util.tree_flatten_with_path(scene)
        values = [leaf + step if jax.tree_util.keystr(p) == path else leaf for p, leaf in leaves]
        return jax.tree_util.tree_unflatten(tree, values)

    paths = {jax.tree_util.keystr(p): g for p, g in jax.tree_util.tree_flatten_with_path(gradient)[0]}
    checks = {
        ".touches[0].shape.centre": np.array([1e-4, 0.0]),
        ".touches[0].shape.radius": 1e-4,
        ".touches[0].amplitude": 1e-4,
        ".background.conductivity": 1e-6,
        ".skin.contact_impedance": 1e-5,
        ".effects[0].slow_fraction": 1e-4,
    }
    for path, step in checks.items():
        step = np.asarray(step)
        derivative = float(np.sum(np.asarray(paths[path]) * step / np.linalg.norm(step)))
        fd = (float(loss(moved(path, step))) - float(loss(moved(path, -step)))) / (2 * np.linalg.norm(step))
        assert derivative == pytest.approx(fd, rel=2e-4, abs=1e-9), path
        assert derivative != 0, path
