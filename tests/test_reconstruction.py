"""`diffeit.reconstruct`: calibration to the reference (level, orientation, magnitudes, driven
readings, broken channels), the automatic hyperparameter, and what it returns."""

import warnings

import jax
import numpy as np
import pytest

import diffeit as de
from diffeit.calibration import CalibrationWarning, calibrate_to_reference
from diffeit.calibration._reference import _driven, _uses
from diffeit.results import SolverError

jax.config.update("jax_enable_x64", True)

CENTRE = np.array([0.4, 0.25])
RADIUS = 0.25
# Electrodes off their even spacing: no rotation or mirror maps the sheet onto itself.
ANGLES = 2 * np.pi * np.arange(16) / 16 + np.random.default_rng(3).uniform(-0.08, 0.08, 16)


def _opposite_skip_three() -> de.Protocol:
    """Opposite drive, pairs (m, m+4) read: the pairs mirrored across the drive's axis read zero
    on a uniform disc."""
    drive = np.zeros((16, 16))
    readings = []
    for i in range(16):
        drive[i, [i, (i + 8) % 16]] = -1.0, 1.0
        pairs = [m for m in range(16) if not {m, (m + 4) % 16} & {i, (i + 8) % 16}]
        weights = np.zeros((len(pairs), 16))
        weights[np.arange(len(pairs)), pairs] = 1.0
        weights[np.arange(len(pairs)), (np.array(pairs) + 4) % 16] = -1.0
        readings.append(weights)
    return de.Protocol(drive, readings)


def _touch(mesh: de.Mesh, level: float, contrast: float = -0.5) -> np.ndarray:
    inside = np.linalg.norm(mesh.element_centroids - CENTRE, axis=1) < RADIUS
    return level * (1 + contrast * inside)


def _recording(
    protocol: de.Protocol,
    *,
    level: float = 0.01,
    contact_impedance: float | np.ndarray = 0.01,
    truth_protocol: de.Protocol | None = None,
    angles: np.ndarray | None = None,
    noise: float = 0.002,
    sign: float = 1.0,
    magnitude: bool = False,
    unit: float = 1.0,
) -> de.io.Recording:
    """A reference and 4 frames of a touch, simulated on a fine disc under `truth_protocol`
    (the instrument's readings as they really are) and recorded as `protocol`."""
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.06, electrode_angles=angles)
    model = de.ForwardModel(mesh, truth_protocol or protocol, contact_impedance=contact_impedance)
    reference = np.asarray(model.measure(np.full(mesh.n_elements, level)))
    touched = np.asarray(model.measure(_touch(mesh, level)))
    frames = np.stack([reference, touched, 0.5 * (reference + touched), touched])
    rng = np.random.default_rng(0)
    scale = noise * np.sqrt(np.mean(reference**2))
    frames = frames + rng.normal(0, scale, frames.shape)
    reference = reference + rng.normal(0, scale, reference.shape)
    frames, reference = sign * unit * frames, sign * unit * reference
    if magnitude:
        frames, reference = np.abs(frames), np.abs(reference)
    return de.io.Recording(
        frames=frames,
        times=np.arange(4.0),
        protocol=protocol,
        reference=reference,
        voltage_unit="V" if unit == 1.0 else "arbitrary",
        readings="magnitude" if magnitude else "signed",
    )


def _reconstruct(recording, angles=None, **options):
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.1, electrode_angles=angles)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = de.reconstruct(recording, mesh=mesh, progress=False, **options)
    return result, [str(w.message) for w in caught if issubclass(w.category, CalibrationWarning)]


@pytest.fixture(scope="module")
def adjacent_recording() -> de.io.Recording:
    """`_recording` of the adjacent protocol with its defaults, which several tests read (each
    copies what it changes): simulated once on the fine disc."""
    return _recording(de.protocol.adjacent(16))


@pytest.fixture(scope="module")
def imaged_with_the_defaults(adjacent_recording):
    """`adjacent_recording` imaged with every default, and its calibration warnings: the first
    test's result, and the one-step image Gauss-Newton's automatic hyperparameter is compared with."""
    return _reconstruct(adjacent_recording)


@pytest.fixture(scope="module")
def counts_and_one_step():
    """A recording in arbitrary units (x250) and its one-step image at hyperparameter 0.05, which
    each nonlinear method's image is compared with."""
    recording = _recording(de.protocol.adjacent(16), unit=250.0)
    return recording, _reconstruct(recording, hyperparameter=0.05)[0]


def _position_error(result, frame: int = 1) -> float:
    image = result.images[frame]
    return float(np.linalg.norm(de.metrics.half_amplitude_centroid(result.mesh, -image) - CENTRE))


def test_a_recording_in_volts_images_the_touch_at_its_place_and_says_what_it_chose(imaged_with_the_defaults):
    result, caught = imaged_with_the_defaults
    metadata = result.provenance["metadata"]
    calibration = metadata["calibration"]
    assert caught == []
    assert calibration["orientation"] == "as recorded"
    assert calibration["correlation"] > 0.999 and calibration["misfit"] < 0.02
    assert calibration["conductivity"] == pytest.approx(0.01, rel=0.05)  # the level in S/sq
    assert result.image_quantity == "conductivity change"
    assert result.images.shape == (4, result.mesh.n_elements)
    assert _position_error(result) < 0.12
    assert result.images[1].min() < -0.1 * 0.01 * 0.5  # S/sq: a drop of the right sign and size
    assert np.abs(result.images[0]).max() < 0.2 * np.abs(result.images[1]).max()  # the reference frame is calm
    choice = metadata["hyperparameter_choice"]
    assert (
        choice["method"] in ("lcurve", "noise_figure")
        and metadata["hyperparameter"] == choice[choice["method"]]["value"]
    )
    assert metadata["difference"] == "calibrated"


def test_an_arbitrary_voltage_unit_gives_the_same_relative_image(adjacent_recording):
    volts, _ = _reconstruct(adjacent_recording, hyperparameter=0.05)
    counts, _ = _reconstruct(_recording(de.protocol.adjacent(16), unit=3.7e4), hyperparameter=0.05)
    assert counts.image_quantity == "relative conductivity change"
    level = volts.provenance["metadata"]["calibration"]["conductivity"]
    np.testing.assert_allclose(counts.images, volts.images / level, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize(
    ("position", "expected"),
    [
        ((-np.arange(16)) % 16, "the electrodes numbered the other way round"),
        ((np.arange(16) + 1) % 16, "the first electrode one on"),
        (np.arange(16), "the drive's sign flipped"),
    ],
)
def test_a_wrong_electrode_order_or_drive_sign_is_found_named_and_undone(position, expected):
    protocol = de.protocol.adjacent(16)
    sign = -1.0 if "sign" in expected else 1.0
    recording = _recording(protocol, truth_protocol=protocol.relabel(position), angles=ANGLES, sign=sign)
    result, caught = _reconstruct(recording, angles=ANGLES)
    calibration = result.provenance["metadata"]["calibration"]
    assert calibration["orientation"] == expected
    misfits = calibration["orientations_misfit"]
    assert misfits[expected] < 0.5 * misfits["as recorded"] and calibration["correlation"] > 0.99
    assert any(expected in message for message in caught)
    assert _position_error(result) < 0.12  # imaged as if the instrument had been set up right


def test_a_symmetric_disc_keeps_the_recorded_order_when_rotations_fit_alike():
    protocol = de.protocol.adjacent(16)
    result, caught = _reconstruct(_recording(protocol, truth_protocol=protocol.relabel((np.arange(16) + 1) % 16)))
    assert result.provenance["metadata"]["calibration"]["orientation"] == "as recorded"
    assert caught == []


@pytest.mark.parametrize("protocol", [de.protocol.opposite(16), _opposite_skip_three()], ids=["openeit", "skip3"])
def test_magnitudes_take_the_models_signs_and_beat_treating_them_as_signed(protocol):
    """An OpenEIT-class board (opposition drive, 192 readings) and one reading pairs four apart,
    magnitudes only. Treated as signed values, OpenEIT's magnitudes still image (its drive i+8
    is drive i negated, so every reading comes with both signs) but less well; pairs four apart
    do not image at all."""
    magnitudes = _recording(protocol, magnitude=True, noise=0.001)
    restored, _ = _reconstruct(magnitudes, hyperparameter=0.05)
    as_signed, _ = _reconstruct(
        de.io.Recording(
            frames=magnitudes.frames, times=magnitudes.times, protocol=protocol, reference=magnitudes.reference
        ),
        hyperparameter=0.05,
        calibrate=False,
        background=0.01,
        difference="calibrated",
    )
    truth, _ = _reconstruct(_recording(protocol, noise=0.001), hyperparameter=0.05)
    assert _position_error(restored) < 0.05
    assert _position_error(restored) < 0.5 * _position_error(as_signed)
    correlation = np.corrcoef(restored.images[1], truth.images[1])[0, 1]
    assert correlation > 0.97 and correlation > np.corrcoef(as_signed.images[1], truth.images[1])[0, 1] + 0.005


def test_magnitudes_whose_sign_the_model_leaves_open_are_reported_and_masked():
    protocol = _opposite_skip_three()
    result, caught = _reconstruct(_recording(protocol, magnitude=True), hyperparameter=0.05)
    uncertain = result.provenance["metadata"]["calibration"]["masked"]["uncertain sign"]
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.1)
    model = np.asarray(de.ForwardModel(mesh, protocol).measure(np.ones(mesh.n_elements)))
    np.testing.assert_array_equal(uncertain, np.flatnonzero(np.abs(model) < 0.05 * np.sqrt(np.mean(model**2))))
    assert len(uncertain) >= 16  # a mirrored pair per drive
    assert any("uncertain sign" in message for message in caught)


def test_readings_on_driven_electrodes_are_kept_through_a_fitted_contact_impedance_or_dropped():
    protocol = de.protocol.adjacent(16, measure_driven=True)
    truth = 2.0 * np.exp(np.random.default_rng(4).normal(0, 0.4, 16))  # ohm m, one per electrode
    recording = _recording(protocol, contact_impedance=truth, noise=0.0005)
    kept, _ = _reconstruct(recording, hyperparameter=0.05)
    calibration = kept.provenance["metadata"]["calibration"]
    assert calibration["driven_readings"] == "kept" and calibration["readings_used"] == 256
    # The level and the contact impedances fitted: the model's nominal 0.01 ohm m was 200x off.
    # Their level to 30% (the data's finer mesh resolves the current crowding under the
    # electrodes better), their pattern over the electrodes to 25% (the smallest, which the
    # readings see least, are the furthest off).
    fitted = np.array(calibration["contact_impedance_per_electrode"])
    level, true_level = np.exp(np.mean(np.log(fitted))), np.exp(np.mean(np.log(truth)))
    assert level == pytest.approx(true_level, rel=0.3)
    np.testing.assert_allclose(fitted / level, truth / true_level, rtol=0.25)
    assert np.corrcoef(np.log(fitted), np.log(truth))[0, 1] > 0.95
    assert calibration["correlation"] > 0.999
    dropped, _ = _reconstruct(recording, hyperparameter=0.05, driven_readings="drop")
    assert dropped.provenance["metadata"]["calibration"]["readings_used"] == 208
    assert _position_error(kept) < 0.12 and _position_error(dropped) < 0.12

    # Driven readings the model cannot reproduce (another instrument's convention) are dropped.
    mangled = np.array(recording.frames)
    driven = np.flatnonzero(_driven(protocol))
    mangled[:, driven] = np.roll(mangled[:, driven], 1, axis=1)
    reference = np.array(recording.reference)
    reference[driven] = np.roll(reference[driven], 1)
    auto, caught = _reconstruct(
        de.io.Recording(frames=mangled, times=recording.times, protocol=protocol, reference=reference),
        hyperparameter=0.05,
    )
    assert auto.provenance["metadata"]["calibration"]["driven_readings"] == "dropped"
    assert any("driven electrodes dropped" in message for message in caught)


def test_broken_readings_and_a_broken_electrode_are_masked_and_reported(adjacent_recording):
    protocol, recording = adjacent_recording.protocol, adjacent_recording
    frames, reference = np.array(recording.frames), np.array(recording.reference)
    largest = np.abs(reference).max()
    reference[10] = 0.0  # a dead channel
    reference[[40, 41]] = frames[:, [40, 41]] = 50 * largest  # a saturated rail
    reference[100] *= 4.0  # a wrong gain
    electrode = 7
    uses = _uses(protocol, np.arange(16) == electrode)
    noise = np.random.default_rng(5).normal(0, largest, (5, uses.sum()))
    reference[uses], frames[:, uses] = noise[0], noise[1:]  # a loose electrode
    result, caught = _reconstruct(
        de.io.Recording(frames=frames, times=recording.times, protocol=protocol, reference=reference)
    )
    calibration = result.provenance["metadata"]["calibration"]
    masked = calibration["masked"]
    assert 10 in masked["zero"] and masked["saturated"] == [40, 41]
    assert 100 in masked["outlier"]
    assert calibration["broken_electrodes"] == [electrode]
    lost = set().union(*map(set, masked.values()))
    assert set(np.flatnonzero(uses)) <= lost
    assert calibration["readings_used"] == 208 - len(lost) and calibration["readings_used"] > 120
    assert any("masked readings" in message for message in caught)
    assert calibration["correlation"] > 0.99
    assert _position_error(result) < 0.15


def test_reading_by_reading_ratios_blow_up_where_the_default_does_not():
    """Pairs mirrored across the drive's axis read near zero: dividing by the reference reading by reading
    amplifies their noise; the default scales by the calibrated model, and normalised
    differences in `reconstruct` mask the readings whose ratio would blow up."""
    protocol = _opposite_skip_three()
    recording = _recording(protocol, noise=0.002)
    calibrated, _ = _reconstruct(recording, hyperparameter=0.05)
    normalised, caught = _reconstruct(recording, hyperparameter=0.05, difference="normalised")
    assert calibrated.provenance["metadata"]["difference"] == "calibrated"
    assert _position_error(calibrated) < 0.12 and _position_error(normalised) < 0.12
    assert len(normalised.provenance["metadata"]["unsafe_ratio_readings"]) >= 16
    assert any("normalised differences" in message for message in caught)

    model = de.ForwardModel(calibrated.mesh, protocol)
    plain = de.inverse.OneStep(
        model, hyperparameter=0.05, background=0.01, normalised=True, reference=recording.reference
    )
    ratios = np.asarray(plain.solve(recording.difference()).value)

    error = np.linalg.norm(de.metrics.half_amplitude_centroid(calibrated.mesh, -ratios[1]) - CENTRE)
    assert error > 0.3 > 0.12 > _position_error(calibrated)  # the ratios of near-zero readings lose the touch


def test_bad_input_is_refused_or_warned_about(adjacent_recording):
    recording = adjacent_recording
    with pytest.raises(ValueError, match="method"):
        de.reconstruct(recording, method="magic")
    with pytest.raises(ValueError, match="hyperparameter"):
        de.reconstruct(recording, hyperparameter="largest")
    with pytest.raises(ValueError, match="hyperparameter"):
        de.reconstruct(recording, hyperparameter=-1.0)
    with pytest.raises(ValueError, match="difference"):
        de.reconstruct(recording, difference="ratio")
    with pytest.raises(ValueError, match="no frames"):
        de.reconstruct(de.io.Recording(frames=np.zeros((0, 208)), times=[], protocol=de.protocol.adjacent(16)))
    mesh = de.mesh.disc(16, h=0.1)
    model = de.ForwardModel(mesh, de.protocol.adjacent(16))
    with pytest.raises(ValueError, match="non-finite"):
        calibrate_to_reference(model, np.full(208, np.nan))
    with pytest.raises(ValueError, match="shape"):
        calibrate_to_reference(model, np.ones(200))
    with pytest.raises(ValueError, match="negative"):
        calibrate_to_reference(model, -np.ones(208), readings="magnitude")
    with pytest.raises(ValueError, match="zero or saturated"):
        calibrate_to_reference(model, np.zeros(208))
    with pytest.raises(ValueError, match="does not correlate positively"):
        calibrate_to_reference(model, np.random.default_rng(1).normal(size=208) - 1.0)
    # A reference the model reproduces badly (a gain per reading): imaged, but loudly.
    gains = np.exp(np.random.default_rng(2).normal(0, 0.8, 208))
    skewed = de.io.Recording(
        frames=recording.frames * gains,
        times=recording.times,
        protocol=recording.protocol,
        reference=recording.reference * gains,
    )
    result, caught = _reconstruct(skewed)
    assert result.provenance["metadata"]["calibration"]["correlation"] < 0.9
    assert any("does not reproduce the reference" in message for message in caught)
    assert result.provenance["metadata"]["difference"] == "normalised"  # the gains cancel reading by reading
    assert _position_error(result) < 0.12


def test_a_recording_without_reference_is_calibrated_on_its_first_frames(adjacent_recording):
    """Its 4 frames, too few to test for a touch by their own noise, are an untouched frame and
    3 touched ones: the model calibrated on them sees the touch in the second
    (`untouched_run`), and the reference is the first alone (it was the mean of all 4)."""
    recording = adjacent_recording
    without = de.io.Recording(frames=recording.frames, times=recording.times, protocol=recording.protocol)
    result, _ = _reconstruct(without, hyperparameter=0.05)
    expected = "mean of the first 4 frames: the first 1 of them, the model sees a touch in the next"
    assert result.provenance["metadata"]["reference"] == expected
    np.testing.assert_allclose(result.reference, recording.frames[0])


@pytest.mark.parametrize("method", ["gauss_newton", "total_variation", "greit"])
def test_the_nonlinear_methods_run_at_the_calibrated_state(counts_and_one_step, method):
    recording, one_step = counts_and_one_step
    result, _ = _reconstruct(recording, hyperparameter=0.05, method=method)
    assert result.provenance["metadata"]["method"] == method
    assert result.provenance["metadata"]["results"] == ["successful"] * 4  # each frame's solver converged
    assert result.provenance["metadata"]["frames_failed"] == 0
    assert _position_error(result) < 0.12
    assert np.corrcoef(result.images[1], one_step.images[1])[0, 1] > 0.7


def test_a_background_map_fitted_to_the_reference_images_on_a_non_uniform_skin():
    """Left half 0.01 S/sq, right half 0.004 (the touch's side): with `background_map` the
    fitted map tells the regions apart and explains the reference the uniform level cannot."""
    protocol = de.protocol.adjacent(16)
    fine = de.mesh.disc(16, electrode_width=0.2, h=0.06)
    model = de.ForwardModel(fine, protocol)
    background = np.where(fine.element_centroids[:, 0] < 0, 0.01, 0.004)
    touched = background * np.where(np.linalg.norm(fine.element_centroids - CENTRE, axis=1) < RADIUS, 0.5, 1.0)
    reference, frame = (np.asarray(model.measure(s)) for s in (background, touched))
    recording = de.io.Recording(
        frames=np.stack([reference, frame]), times=[0.0, 1.0], protocol=protocol, reference=reference
    )
    uniform, _ = _reconstruct(recording, hyperparameter=0.05)
    mapped, _ = _reconstruct(recording, hyperparameter=0.05, background_map=True)
    summary = mapped.provenance["metadata"]["background_map"]
    assert uniform.provenance["metadata"]["background_map"] is None
    # The coarse sheet's own error stops the map's misfit above the noise: recorded, not raised.
    assert summary["result"] == "selection_at_boundary"
    assert summary["misfit"] < 0.3 * uniform.provenance["metadata"]["calibration"]["misfit"]
    low, high = summary["range"]
    assert 1.8 < high / low < 4.0  # the true ratio is 2.5; a smooth map rounds the step
    assert _position_error(mapped) < 0.12


def test_a_32_electrode_tank_with_its_own_patterns_is_imaged_with_the_defaults():
    """76 current injections between electrode pairs at several spacings, each read on every
    free adjacent pair against the next-but-one (an instrument's own pattern, some readings near
    zero), in device units with 1% noise: the defaults image the target where it is."""
    n = 32
    rng = np.random.default_rng(7)
    pairs = [(i, (i + step) % n) for step in (1, 3, 5, 16) for i in range(0, n, 1 if step == 16 else 2)][:76]
    drive = np.zeros((len(pairs), n))
    readings = []
    for k, (a, b) in enumerate(pairs):
        drive[k, [a, b]] = -1.0, 1.0
        free = [m for m in range(n) if not {m, (m + 2) % n} & {a, b}]
        weights = np.zeros((len(free), n))
        weights[np.arange(len(free)), free] = 1.0
        weights[np.arange(len(free)), (np.array(free) + 2) % n] = -1.0
        readings.append(weights)
    protocol = de.Protocol(drive, readings)
    assert protocol.n_drives == 76
    fine = de.mesh.disc(n, electrode_width=0.08, h=0.06)
    model = de.ForwardModel(fine, protocol)
    reference = np.asarray(model.measure(np.full(fine.n_elements, 2.0)))
    frame = np.asarray(model.measure(_touch(fine, 2.0)))
    scale = 0.01 * np.sqrt(np.mean(reference**2))
    frames = np.stack([reference, frame]) + rng.normal(0, scale, (2, len(reference)))
    recording = de.io.Recording(
        frames=4096 * frames,
        times=[0.0, 1.0],
        protocol=protocol,
        reference=4096 * (reference + rng.normal(0, scale, len(reference))),
        voltage_unit="arbitrary",
    )
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        result = de.reconstruct(recording, mesh=de.mesh.disc(n, electrode_width=0.08, h=0.1), progress=False)
    metadata = result.provenance["metadata"]
    assert metadata["calibration"]["correlation"] > 0.99 and metadata["difference"] == "calibrated"
    assert result.image_quantity == "relative conductivity change"
    assert _position_error(result) < 0.12
    assert -1.0 < result.images[1].min() < -0.1  # dsigma / sigma of a -50% target, blurred


def test_gauss_newtons_automatic_hyperparameter_is_four_times_the_one_steps(
    adjacent_recording, imaged_with_the_defaults
):
    one_step, _ = imaged_with_the_defaults
    nonlinear, _ = _reconstruct(adjacent_recording, method="gauss_newton")
    choice = nonlinear.provenance["metadata"]["hyperparameter_choice"]
    assert choice["gauss_newton_factor"] == 4.0
    assert nonlinear.provenance["metadata"]["hyperparameter"] == pytest.approx(
        4.0 * one_step.provenance["metadata"]["hyperparameter"]
    )
    assert _position_error(nonlinear) < 0.12


def _coarse_touch(noise: float = 0.002) -> tuple[de.io.Recording, de.Mesh]:
    """An untouched and a touched frame (noise `noise` of the RMS reading, seeded; the
    reference noise-free), simulated on a coarse disc, and the coarser sheet to image them on:
    quick to solve."""
    protocol = de.protocol.adjacent(16)
    truth = de.mesh.disc(16, electrode_width=0.2, h=0.12)
    model = de.ForwardModel(truth, protocol)
    reference = np.asarray(model.measure(np.full(truth.n_elements, 0.01)))
    frames = np.stack([reference, np.asarray(model.measure(_touch(truth, 0.01)))])
    frames = frames + np.random.default_rng(0).normal(0, noise * np.sqrt(np.mean(reference**2)), frames.shape)
    recording = de.io.Recording(frames=frames, times=[0.0, 1.0], protocol=protocol, reference=reference)
    return recording, de.mesh.disc(16, electrode_width=0.2, h=0.2)


def test_a_frame_whose_gauss_newton_stops_at_its_iteration_limit_raises_or_is_marked():
    """Capped at 5 steps, Gauss-Newton converges on the untouched frame (3 steps) but not on
    the touch (7): throw=True names frame 1, throw=False marks it, uncapped both converge."""
    recording, mesh = _coarse_touch()
    options = {"method": "gauss_newton", "mesh": mesh, "hyperparameter": 0.2, "progress": False}
    message = r"gauss_newton reconstruction \(frames \[1\]\): the iteration limit was reached"
    with pytest.raises(SolverError, match=message):
        de.reconstruct(recording, max_iterations=5, **options)
    capped = de.reconstruct(recording, max_iterations=5, throw=False, **options)
    metadata = capped.provenance["metadata"]
    assert metadata["results"] == ["successful", "max_iterations_reached"] and metadata["frames_failed"] == 1
    assert metadata["max_iterations"] == 5 and np.all(np.isfinite(capped.images))
    converged = de.reconstruct(recording, **options).provenance["metadata"]
    assert converged["results"] == ["successful", "successful"] and converged["frames_failed"] == 0


def test_total_variation_gives_each_frame_its_code():
    """One iteration: the frame equal to the reference starts at its minimiser, the touch does not."""
    recording, mesh = _coarse_touch(noise=0.0)
    result = de.reconstruct(
        recording,
        method="total_variation",
        mesh=mesh,
        hyperparameter=0.1,
        max_iterations=1,
        throw=False,
        progress=False,
    )
    assert result.provenance["metadata"]["results"] == ["successful", "max_iterations_reached"]


@pytest.mark.filterwarnings("error::RuntimeWarning")  # a frame of 1e308 V is marked, no overflow warned of
def test_a_direct_method_marks_a_non_finite_image_and_a_selection_at_its_boundary_does_not_raise():
    recording, mesh = _coarse_touch()
    overflowing = de.io.Recording(
        frames=np.stack([recording.frames[1], np.full(recording.protocol.n_measurements, 1e308)]),
        times=[0.0, 1.0],
        protocol=recording.protocol,
        reference=recording.reference,
    )
    options = {"mesh": mesh, "hyperparameter": 0.1, "progress": False}
    with pytest.raises(SolverError, match=r"one_step reconstruction \(frames \[1\]\): a non-finite value"):
        de.reconstruct(overflowing, **options)
    result = de.reconstruct(overflowing, throw=False, **options)
    assert result.provenance["metadata"]["results"] == ["successful", "nonfinite"]
    np.testing.assert_array_equal(result.images[1], 0.0)  # a Recording holds finite images only
    assert np.abs(result.images[0]).max() > 0
    # GCV on noise-free differences chooses its smallest candidate: kept in the metadata, not raised.
    # (Uncalibrated: a model refined to the reference absorbs the coarser mesh's error in its
    # contacts and mixing, and that error then reads as noise.)
    noiseless, mesh = _coarse_touch(noise=0.0)
    options = {"mesh": mesh, "hyperparameter": "gcv", "calibrate": False, "background": 0.01, "progress": False}
    choice = de.reconstruct(noiseless, **options).provenance["metadata"]
    assert choice["hyperparameter_choice"]["gcv"]["result"] == "selection_at_boundary"
    assert choice["results"] == ["successful", "successful"]
    with pytest.raises(ValueError, match="max_iterations applies to gauss_newton and total_variation"):
        de.reconstruct(noiseless, mesh=mesh, max_iterations=5, progress=False)
    with pytest.raises(ValueError, match="max_iterations must be a positive integer"):
        de.reconstruct(noiseless, mesh=mesh, method="gauss_newton", max_iterations=0, progress=False)


def test_a_solver_object_is_bound_to_the_calibrated_model_with_its_own_settings():
    """`solver=` takes any difference solver, built without a model (or on another one): its
    settings, the calibrated model and level. The method's shorthand gives the same images
    (its contacts free to drift, `CONTACT_IMPEDANCE_SPREAD`); a solver's own spread is kept."""
    recording, mesh = _coarse_touch()
    options = {"mesh": mesh, "progress": False}
    spread = de.inverse.CONTACT_IMPEDANCE_SPREAD
    shorthand = de.reconstruct(recording, method="one_step", prior="laplace", hyperparameter=0.05, **options)
    assert shorthand.provenance["metadata"]["contact_impedance_spread"] == spread
    solver = de.inverse.OneStep(prior="laplace", hyperparameter=0.05, contact_impedance_spread=spread)
    unbound = de.reconstruct(recording, solver=solver, **options)
    np.testing.assert_allclose(unbound.images, shorthand.images, rtol=1e-10, atol=1e-15)
    held = de.reconstruct(recording, solver=de.inverse.OneStep(prior="laplace", hyperparameter=0.05), **options)
    assert held.provenance["metadata"]["contact_impedance_spread"] == 0.0
    assert not np.allclose(held.images, shorthand.images, rtol=1e-6, atol=0)
    metadata = unbound.provenance["metadata"]
    assert metadata["method"] == "one_step" and metadata["prior"] == repr(de.inverse.Laplace())
    assert metadata["hyperparameter"] == 0.05 and metadata["hyperparameter_choice"] == {"rule": "the solver's own"}
    # Built on another model: re-bound; a hyperparameter given to reconstruct replaces the solver's.
    other = de.ForwardModel(de.mesh.disc(16, h=0.3), recording.protocol)
    solver = de.inverse.OneStep(other, "laplace", 0.3, contact_impedance_spread=spread)
    bound = de.reconstruct(recording, solver=solver, hyperparameter=0.05, **options)
    np.testing.assert_allclose(bound.images, shorthand.images, rtol=1e-10, atol=1e-15)
    # An iterative solver's own limit, and its codes.
    capped = de.reconstruct(
        _coarse_touch(noise=0.0)[0],
        solver=de.inverse.TotalVariation(hyperparameter=0.1, max_iterations=1),
        throw=False,
        **options,
    )
    assert capped.provenance["metadata"]["max_iterations"] == 1
    assert capped.provenance["metadata"]["results"] == ["successful", "max_iterations_reached"]
    # "auto" with a Gauss-Newton object: the selection, times four, as for the shorthand.
    automatic = de.reconstruct(
        recording, solver=de.inverse.GaussNewton(max_iterations=30), hyperparameter="auto", **options
    )
    assert automatic.provenance["metadata"]["hyperparameter_choice"]["gauss_newton_factor"] == 4.0


def test_a_solver_object_that_does_not_fit_is_refused():
    recording, mesh = _coarse_touch()
    options = {"mesh": mesh, "progress": False}
    with pytest.raises(ValueError, match="not both"):
        de.reconstruct(recording, method="greit", solver=de.inverse.GREIT(), **options)
    with pytest.raises(ValueError, match="settings of the solver object"):
        de.reconstruct(recording, solver=de.inverse.OneStep(), prior="laplace", **options)
    with pytest.raises(ValueError, match="settings of the solver object"):
        de.reconstruct(recording, solver=de.inverse.TotalVariation(), max_iterations=3, **options)
    with pytest.raises(ValueError, match="difference solver"):
        de.reconstruct(recording, solver=de.inverse.AbsoluteGaussNewton(), **options)
    with pytest.raises(ValueError, match="difference solver"):
        de.reconstruct(recording, solver="one_step", **options)
    model = de.ForwardModel(mesh, recording.protocol)
    normalised = de.inverse.OneStep(model, normalised=True, reference=recording.reference)
    with pytest.raises(ValueError, match="normalised differences itself"):
        de.reconstruct(recording, solver=normalised, **options)
