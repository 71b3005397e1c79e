"""diffeit.calibration: the skin's model fitted to a calibration session, the position map
from labelled presses, and the calibration file."""

import h5py
import jax.numpy as jnp
import numpy as np
import pytest

import diffeit as de
from diffeit.calibration import PositionMap
from diffeit.readout import Readout

PROTOCOL = de.protocol.adjacent(16)


@pytest.fixture(scope="module")
def skin():
    """A coarse skin (its model is the reconstruction's) read by a board with drive and channel
    gains of up to 25%, contact impedances spread 3x, and 0.1% noise: 10 untouched frames, then
    30 presses (disc, radius 0.15, dsigma/sigma = -0.3) at known places."""
    rng = np.random.default_rng(4)
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.1)
    truth = de.ForwardModel(mesh, PROTOCOL, contact_impedance=0.01 * np.exp(rng.uniform(-0.55, 0.55, 16)))
    gains = np.exp(rng.uniform(-0.25, 0.25, 16))[PROTOCOL.drive_index] * np.exp(rng.uniform(-0.25, 0.25, 16))[
        PROTOCOL.pattern_index
    ]
    readout = Readout(PROTOCOL, gains=gains)

    def board(sigma):
        return 1e3 * np.asarray(readout.readings(PROTOCOL, truth.potentials(jnp.asarray(sigma)).electrode))

    reference = board(np.ones(mesh.n_elements))
    noise = 1e-3 * np.sqrt(np.mean(reference**2))
    angles = rng.uniform(0, 2 * np.pi, 30)
    radii = 0.6 * np.sqrt(rng.uniform(0, 1, 30))
    centres = np.stack([radii * np.cos(angles), radii * np.sin(angles)], axis=1)
    pressed = [board(1 - 0.3 * de.mesh.disc_fraction(mesh, tuple(c), 0.15)) for c in centres]
    frames = np.concatenate([np.tile(reference, (10, 1)), pressed]) + noise * rng.standard_normal((40, len(reference)))
    times = 0.1 * np.arange(40)
    recording = de.io.Recording(frames=frames, times=times, protocol=PROTOCOL, mesh=mesh, voltage_unit="arbitrary")
    presses = de.io.Presses(centres, 0.15, times[10:])
    return recording, presses, gains


@pytest.fixture(scope="module")
def calibrated(skin):
    recording, presses, _ = skin
    return de.calibrate(recording, presses)


def test_the_refinement_finds_the_boards_gains_and_reproduces_the_reference(skin, calibrated):
    _, _, gains = skin
    first = calibrated.first_stage
    assert first.correlation < 0.97  # the gains spoil the nominal model's fit
    assert calibrated.correlation > 0.999 and calibrated.misfit < 0.01
    fitted = np.asarray(calibrated.readout.gains)
    # Gains are found up to one common factor (the voltage unit's).
    ratio = fitted / gains
    assert np.std(np.log(ratio)) < 0.02, np.std(np.log(ratio))
    for group, values in calibrated.values.items():
        assert calibrated.standard_errors[group].shape == values.shape
        assert np.all(np.isfinite(calibrated.standard_errors[group]))


def test_calibrated_images_place_presses_better_than_the_first_stage(skin, calibrated):
    recording, presses, _ = skin
    held_out = de.io.Recording(
        frames=recording.frames[10:],
        times=recording.times[10:],
        protocol=PROTOCOL,
        reference=recording.frames[:10].mean(axis=0),
        mesh=recording.mesh,
        voltage_unit="arbitrary",
    )
    errors = {}
    for name, calibration in (("skin", calibrated), ("first stage", None)):
        images = de.reconstruct(held_out, calibration=calibration, difference="calibrated", progress=False)
        found = de.touches(images, calibration)
        assert np.all(found.count >= 1)
        errors[name] = np.median(np.linalg.norm(found.position[:, 0] - presses.centres, axis=1))
    assert errors["skin"] < 0.8 * errors["first stage"], errors
    assert errors["skin"] < 0.1, errors


def test_the_position_map_recovers_an_affine_frame_and_chooses_its_degree():
    rng = np.random.default_rng(0)
    read = rng.uniform(-0.7, 0.7, (25, 2))
    angle, scale, shift = np.deg2rad(10.0), 1.1, np.array([0.02, -0.01])
    rotation = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    labelled = scale * read @ rotation.T + shift
    mapping = PositionMap.fit(read, labelled)
    assert mapping.degree == 1
    assert np.max(np.abs(mapping(read) - labelled)) < 1e-12
    assert mapping.errors["1"] < 1e-12 < mapping.errors["none"]
    # Too few presses for an affine map with two to spare: a shift at most.
    assert PositionMap.fit(read[:4], labelled[:4]).degree in (None, 0)


def test_a_calibration_file_round_trips_and_refuses_other_data(skin, calibrated, tmp_path):
    recording, _, _ = skin
    path = calibrated.save(tmp_path / "skin.cal.h5")
    again = de.calibration.load(path, recording=recording)
    np.testing.assert_allclose(again.signed(recording.frames), calibrated.signed(recording.frames), rtol=1e-12)
    np.testing.assert_allclose(again.contact_impedance, calibrated.contact_impedance)
    assert again.position_map.degree == calibrated.position_map.degree
    np.testing.assert_allclose(again.position_map(recording.mesh.nodes), calibrated.position_map(recording.mesh.nodes))
    assert again.lines()[:3] == calibrated.lines()[:3]
    voltages = again.model.measure(jnp.full(again.model.n_elements, again.conductivity))
    np.testing.assert_allclose(voltages, calibrated.model.measure(jnp.full(again.model.n_elements, again.conductivity)))
    other = de.io.Recording(frames=np.ones((2, 192)), times=[0.0, 1.0], protocol=de.protocol.opposite(16))
    with pytest.raises(ValueError, match="another protocol"):
        de.calibration.load(path, recording=other)
    newer = tmp_path / "newer.cal.h5"
    newer.write_bytes(path.read_bytes())
    with h5py.File(newer, "r+") as file:
        file.attrs["schema_version"] = 99
    with pytest.raises(ValueError, match="newer than this diffeit reads"):
        de.calibration.load(newer)
    with pytest.raises(ValueError, match="another protocol"):
        de.reconstruct(other, calibration=calibrated)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda p: de.io.Presses(p.centres + 5.0, p.radius, p.times[:, 0]), "outside the skin"),
        (lambda p: de.io.Presses(p.centres, p.radius, p.times[:, 0] + 100.0), "outside the recording's time"),
    ],
)
def test_presses_the_recording_cannot_hold_are_refused(skin, change, message):
    recording, presses, _ = skin
    with pytest.raises(ValueError, match=message):
        de.calibrate(recording, change(presses))


def test_presses_check_their_shapes_and_values():
    with pytest.raises(ValueError, match="centres has shape"):
        de.io.Presses(np.zeros((3, 3)), 0.1, [0.0, 1.0, 2.0])
    with pytest.raises(ValueError, match=r"centres is not finite .* \[1\]"):
        de.io.Presses([[0, 0], [np.nan, 0]], 0.1, [0.0, 1.0])
    with pytest.raises(ValueError, match="times has shape"):
        de.io.Presses([[0, 0], [0.1, 0]], 0.1, [0.0, 1.0, 2.0])
    with pytest.raises(ValueError, match="ends before it starts"):
        de.io.Presses([[0, 0]], 0.1, [[1.0, 0.5]])
    with pytest.raises(ValueError, match="radius must be positive"):
        de.io.Presses([[0, 0]], 0.0, [1.0])
