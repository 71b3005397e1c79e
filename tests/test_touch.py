"""diffeit.touch: touches read from images (where, how large, how deep, how hard)."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

import diffeit as de
from diffeit.scene import FoamStack, pressure_to_change

MESH = de.mesh.disc(16, electrode_width=0.2, h=0.05)


def disc_image(centre, radius, depth):
    return depth * np.asarray(de.mesh.disc_fraction(MESH, tuple(centre), radius))


def test_two_separate_touches_are_read_where_they_are_with_their_size_and_depth():
    image = disc_image((0.4, 0.1), 0.2, -0.3) + disc_image((-0.3, -0.3), 0.15, -0.2)
    found = de.touch.read(MESH, image)
    assert found.count.tolist() == [2]
    np.testing.assert_allclose(found.position[0, 0], (0.4, 0.1), atol=0.02)
    np.testing.assert_allclose(found.position[0, 1], (-0.3, -0.3), atol=0.02)
    np.testing.assert_allclose(found.radius[0, :2], (0.2, 0.15), rtol=0.15)
    np.testing.assert_allclose(found.depth[0, :2], (-0.3, -0.2), rtol=1e-6)
    assert np.all(np.isnan(found.position[0, 2:]))


def test_an_untouched_frame_has_no_touch_and_a_touch_stands_out_of_noise():
    rng = np.random.default_rng(0)
    noise = 0.01 * rng.standard_normal((20, MESH.n_elements))
    assert de.touch.read(MESH, noise).count.tolist() == [0] * 20
    touched = noise + disc_image((0.2, 0.2), 0.2, -0.3)
    assert np.all(de.touch.read(MESH, touched).count == 1)


def test_touches_whose_valley_stays_above_half_the_lower_peak_merge():
    overlapping = disc_image((0.1, 0.0), 0.2, -0.3) + disc_image((-0.1, 0.0), 0.2, -0.3)
    assert de.touch.read(MESH, overlapping).count.tolist() == [1]
    apart = disc_image((0.5, 0.0), 0.15, -0.3) + disc_image((-0.5, 0.0), 0.15, -0.3)
    assert de.touch.read(MESH, apart).count.tolist() == [2]


def test_pressures_invert_the_foam_stacks_map_and_the_count_is_capped():
    stack = FoamStack()
    pressures = np.array([10.0, 60.0])
    depths = np.asarray(pressure_to_change(pressures, stack))
    image = disc_image((0.5, 0.0), 0.15, depths[0]) + disc_image((-0.5, 0.0), 0.15, depths[1])
    found = de.touch.read(MESH, image, stack=stack)
    np.testing.assert_allclose(np.sort(found.pressure[0, :2]), pressures, rtol=1e-6)
    assert de.touch.read(MESH, image, max_touches=1).count.tolist() == [1]
    # A further touch counts only from `relative` of the highest's peak up (a calibration's ringing).
    shallower = float(np.min(np.abs(depths)) / np.max(np.abs(depths)))
    assert de.touch.read(MESH, image, relative=0.9 * shallower).count.tolist() == [2]
    assert de.touch.read(MESH, image, relative=min(1.1 * shallower, 0.99)).count.tolist() == [1]


def test_bad_images_and_options_are_refused():
    with pytest.raises(ValueError, match="images have shape"):
        de.touch.read(MESH, np.zeros(5))
    with pytest.raises(ValueError, match="non-finite"):
        de.touch.read(MESH, np.full(MESH.n_elements, np.nan))
    with pytest.raises(ValueError, match="polarity"):
        de.touch.read(MESH, np.zeros(MESH.n_elements), polarity=0)
    with pytest.raises(ValueError, match="relative must be"):
        de.touch.read(MESH, np.zeros(MESH.n_elements), relative=1.0)
    with pytest.raises(ValueError, match="reconstructed recording"):
        de.touches(de.io.Recording(frames=np.ones((1, 208)), times=[0.0], protocol=de.protocol.adjacent(16)))


def test_the_polarity_of_images_is_the_sign_their_touches_stand_out_with():
    rng = np.random.default_rng(1)
    centres = rng.uniform(-0.5, 0.5, (5, 2))
    # Each press with ringing of the other sign, 40% of its depth, and noise; one frame untouched.
    images = np.array([disc_image(c, 0.15, -0.3) + disc_image(-c, 0.3, 0.12) for c in centres])
    images = np.concatenate([images, np.zeros((1, MESH.n_elements))]) + 0.01 * rng.standard_normal((6, MESH.n_elements))
    assert de.touch.polarity_of(images) == -1
    assert de.touch.polarity_of(-images) == 1
    assert de.touch.polarity_of(np.zeros((0, MESH.n_elements))) == -1
    with pytest.raises(ValueError, match="non-finite"):
        de.touch.polarity_of(np.where(images < -0.2, np.nan, images))
    with pytest.raises(ValueError, match="expected \\(T, E\\)"):
        de.touch.polarity_of(images[None])


def test_a_clean_images_ringing_is_no_touch_but_a_light_touch_beside_a_hard_one_is():
    """A further hill needs a tenth of the highest one's peak: one press imaged by one step at
    0.01% noise rings near the rim at 6.5% of its peak (measured), which the noise floors alone
    read as two more touches; a touch of 5 kPa beside one of 60 kPa (a sixth of its depth)
    stays."""
    model = de.ForwardModel(de.mesh.disc(16, electrode_width=0.2, h=0.08), de.protocol.adjacent(16), 0.01)
    mesh = model.mesh
    sigma = np.ones(mesh.n_elements)
    pressed = sigma * (1 - 0.3 * np.asarray(de.mesh.disc_fraction(mesh, (0.3, 0.2), 0.15)))
    v0, v1 = (np.asarray(model.measure(np.asarray(s))) for s in (sigma, pressed))
    noise = 1e-4 * np.sqrt(np.mean(v0**2)) * np.random.default_rng(0).standard_normal((9, len(v0)))
    frames = np.vstack([np.tile(v0, (8, 1)), v1]) + noise
    recording = de.io.Recording(frames=frames, times=np.arange(9.0), protocol=model.protocol, mesh=mesh)
    found = de.touches(de.reconstruct(recording, progress=False))
    assert found.count.tolist() == [0] * 8 + [1]
    np.testing.assert_allclose(found.position[8, 0], (0.3, 0.2), atol=0.01)
    depths = np.asarray(pressure_to_change(np.array([5.0, 60.0]), FoamStack()))
    image = disc_image((0.5, 0.0), 0.15, depths[0]) + disc_image((-0.5, 0.0), 0.15, depths[1])
    assert de.touch.read(MESH, image).count.tolist() == [2]


def test_hills_divided_by_the_images_noise_leave_a_noisy_rims_narrow_hill_out():
    """A press's broad hill in the middle, and at the rim, where the image's noise is 50 times
    the middle's (seeded), a narrow hill higher than the press's: on the image itself the rim's
    hill is the first touch; on the image divided by its noise the press is the one touch, read
    on the image (its centre and depth)."""
    centroids = MESH.element_centroids
    at_rim = np.linalg.norm(centroids, axis=1) > 0.9
    noise = np.where(at_rim, 0.1, 0.002)
    image = disc_image((0.2, 0.1), 0.25, -0.3) + noise * np.random.default_rng(0).standard_normal(MESH.n_elements)
    rim = np.flatnonzero(at_rim)[0]
    image[rim] = -0.4
    plain = de.touch.read(MESH, image)
    assert plain.count[0] >= 2
    np.testing.assert_allclose(plain.position[0, 0], centroids[rim], atol=1e-12)
    divided = de.touch.read(MESH, image, image_noise=noise)
    assert divided.count.tolist() == [1]
    np.testing.assert_allclose(divided.position[0, 0], (0.2, 0.1), atol=0.03)
    assert -0.31 < divided.depth[0, 0] < -0.29
    # A noise alike everywhere changes nothing.
    same = de.touch.read(MESH, image, image_noise=np.full(MESH.n_elements, 0.02))
    np.testing.assert_array_equal(same.position, plain.position)
    for bad in (np.ones(3), np.zeros(MESH.n_elements), np.full(MESH.n_elements, np.nan)):
        with pytest.raises(ValueError, match="image_noise must hold"):
            de.touch.read(MESH, image, image_noise=bad)


def test_an_images_noise_is_its_reconstruction_of_the_readings_noise():
    """`image_noise` is the standard deviation of R n / sigma over noise draws n of the given
    spread (checked on 20000 seeded draws, to their sampling error)."""
    rng = np.random.default_rng(3)
    matrix, spread, background = rng.standard_normal((7, 5)), rng.uniform(0.5, 2.0, 5), rng.uniform(1.0, 2.0, 7)
    draws = (spread * rng.standard_normal((20000, 5))) @ matrix.T / background
    np.testing.assert_allclose(de.touch.image_noise(matrix, spread, background), draws.std(axis=0), rtol=0.03)
    with pytest.raises(ValueError, match="reading_noise must hold 5"):
        de.touch.image_noise(matrix, spread[:4], background)


def _bump(centre: int, height: float, readings: int = 60) -> np.ndarray:
    """A touch on a line of readings that are their own image: a bump of width 3 at `centre`."""
    return height * np.exp(-0.5 * ((np.arange(readings) - centre) / 3.0) ** 2)


def _anchors_of(
    clean: list[np.ndarray], seed: int, damaged: tuple[int, ...] = (), batch: int | None = None
) -> tuple[np.ndarray, list[list[int]]]:
    """`_rest_anchors` of the frames `clean` (T, 60) with unit noise, after 20 reference frames at
    0, each reading its own image (a touch positive); the frames `damaged` replaced by a glitch
    (every reading 50) and marked damaged. All at once, or `batch` frames at a time, the state
    carried (as `diffeit live` reads them). Each frame's anchor (-1: the reference) and each
    anchor's frames."""
    from diffeit.touch import _Anchoring, _rest_anchors, _VoltageTest

    frames = np.array(clean) + np.random.default_rng(seed).standard_normal((len(clean), 60))
    frames[list(damaged)] = 50.0
    marked = np.isin(np.arange(len(frames)), damaged)
    test = _VoltageTest(frames, np.zeros(60), np.ones(60), 20, 20, None)
    state = _Anchoring.at_reference(test, 60, ())
    anchor_of, anchors = [], []
    size = batch or len(frames)
    for start in range(0, len(frames), size):
        part = slice(start, start + size)
        which, made, _, state = _rest_anchors(
            test._replace(frames=frames[part]), frames[part], (), de.touch.DETECTION, marked[part], state
        )
        # Index 0 is the anchor in force at the batch's start: the last one made, or the reference.
        anchor_of += (which - 1 + len(anchors)).tolist()
        anchors += [anchor.frames.tolist() for anchor in made[1:]]
    return np.array(anchor_of), anchors


def test_rest_anchors_follow_what_presses_leave_and_keep_a_rest_level_that_did_not_move():
    rest = np.zeros(60)
    # Each press leaves 0.45 of itself: its touch is read against the rest just before it.
    frames = [rest] * 3
    for centre in (15, 40, 25):
        frames += [rest + _bump(centre, 12.0)] * 3
        rest = rest + 0.45 * _bump(centre, 12.0)
        frames += [rest] * 4
    anchor_of, anchors = _anchors_of(frames, seed=0)
    assert anchors == [[6, 7, 8, 9], [13, 14, 15, 16]]
    np.testing.assert_array_equal(anchor_of, [-1] * 6 + [0] * 7 + [1] * 11)
    # Read 4 frames at a time: the same anchors, each from its onset on; the rest frames of an
    # earlier batch (6, 7; 13 to 15) keep the anchor they were read against.
    anchor_of, anchors = _anchors_of(frames, seed=0, batch=4)
    assert anchors == [[6, 7, 8, 9], [13, 14, 15, 16]]
    np.testing.assert_array_equal(anchor_of, [-1] * 8 + [0] * 8 + [1] * 8)
    # Damaged frames in a press's hold and at rest are passed over: the same anchors, less them.
    anchor_of, anchors = _anchors_of(frames, seed=0, damaged=(11, 14))
    assert anchors == [[6, 7, 8, 9], [13, 15, 16]]
    # A press held while it relaxes by 20% stays held: the frames after it are no rest.
    relaxing = [np.zeros(60)] * 3 + [_bump(20, 12.0) * (1 - 0.02 * k) for k in range(10)] + [_bump(45, 12.0)] * 2
    anchor_of, anchors = _anchors_of(relaxing, seed=1)
    assert anchors == [] and np.all(anchor_of == -1)
    # Weak presses where a strong one was, an untouched frame among them: each stands out of the
    # reference's noise but not its step, and is that press scaled down, yet the untouched frame
    # shows the rest level did not move. (Taking them as rest anchored on frames 7 to 11.)
    untouched = np.zeros(60)
    weak = [untouched] * 3 + [_bump(20, 12.0), untouched] + [_bump(20, 4.0)] * 3 + [untouched]
    weak += [_bump(20, 4.0)] * 3 + [_bump(45, 12.0)]
    anchor_of, anchors = _anchors_of(weak, seed=2)
    assert anchors == [] and np.all(anchor_of == -1)
    # A faint press held where a strong one was, after a rest back at the reference's level: its
    # onset stands within the noise of a step, so nothing tells it from what the strong one left
    # but the rest before it, where the strong one had left nothing. (Read as its remains, it
    # anchored on its own frames, on seeds 0, 1 and 3.)
    later = [untouched] * 3 + [_bump(20, 12.0)] * 3 + [untouched] * 4 + [_bump(20, 5.0)] * 6 + [_bump(45, 12.0)]
    for seed in range(4):
        anchor_of, anchors = _anchors_of(later, seed=seed)
        assert anchors == [] and np.all(anchor_of == -1), (seed, anchors)
    # A weak press elsewhere right after a strong one, no step out of the noise: its multiple of
    # the strong press is within its errors of 0, so it is no remains of it. (Taking it as
    # such anchored on it.)
    elsewhere = [untouched] * 3 + [_bump(20, 12.0)] * 2 + [_bump(45, 4.5)] * 5 + [_bump(30, 12.0)]
    anchor_of, anchors = _anchors_of(elsewhere, seed=3)
    assert anchors == [] and np.all(anchor_of == -1)
    # Two faint presses beside a deep one, one after another with no rest between: each passes
    # for what the deep one left, but two frames are too few to tell a rest level by. (With two
    # enough, they anchored every frame after them.)
    faint = [untouched] * 3 + [_bump(20, 12.0), _bump(22, 5.0), _bump(26, 5.0)] + [_bump(40, 12.0)] * 2
    for seed in range(4):
        anchor_of, anchors = _anchors_of(faint, seed=seed)
        assert anchors == [] and np.all(anchor_of == -1)
    # Three faint presses one after another after a deep one, each a little of the deep one's
    # pattern (a press near the middle moves the readings' common level) and a wide change of its
    # own: their steps stay within the noise, and each passed for what the deep one left. The
    # deep one explains under a tenth of each and leaves the rest standing out of the noise:
    # they are presses. (Taken as a rest, they anchored every frame after them.)
    wide = [2.0 * np.exp(-0.5 * ((np.arange(60) - centre) / 10.0) ** 2) for centre in (35, 38, 41)]
    row = [untouched] * 3 + [_bump(20, 12.0)] + [0.12 * _bump(20, 12.0) + change for change in wide]
    for seed in range(4):
        anchor_of, anchors = _anchors_of(row + [_bump(50, 12.0)] * 2, seed=seed)
        assert anchors == [] and np.all(anchor_of == -1)
    # A faint press elsewhere, held after the rest where a strong one left 0.45 of itself: its
    # step from one frame stands within the noise, its departure from the rest frames before it
    # does not. An onset, and those rest frames its anchor. (By steps alone, on seeds 2, 3 and 5
    # it passed for what the strong one left, and was read against the reference.)
    left = 0.45 * _bump(20, 12.0)
    faint_after_rest = [untouched] * 3 + [_bump(20, 12.0)] * 3 + [left] * 5 + [left + _bump(45, 5.0)] * 4
    for seed in range(6):
        anchor_of, anchors = _anchors_of(faint_after_rest, seed=seed)
        assert anchors == [[6, 7, 8, 9, 10]], (seed, anchors)
        np.testing.assert_array_equal(anchor_of, [-1] * 6 + [0] * 9)
    # Three presses one after another beside a deep one, no rest between, each passing for what
    # it left: they are not alike (their steps stand out of the noise), so no rest level. (Taken
    # as one, they anchored the frames after them on 6 of these 8 seeds.)
    beside = [untouched] * 3 + [_bump(20, 12.0)] + [_bump(c, 6.0) for c in (16, 22, 18)] + [_bump(45, 12.0)] * 2
    for seed in range(8):
        anchor_of, anchors = _anchors_of(beside, seed=seed)
        assert anchors == [] and np.all(anchor_of == -1), (seed, anchors)
    # Presses of one frame each, two frames of rest between, each leaving 0.45 of itself: the two
    # frames are what the press left, and they stay through the next onset, a rest level. Each
    # press is read against the rest just before it. (With three rest frames needed, every press
    # was read against the reference and all that the presses before it had left.)
    rest, quick = np.zeros(60), [untouched] * 3
    for centre in (15, 40, 25, 50, 8):
        quick += [rest + _bump(centre, 12.0)]
        rest = rest + 0.45 * _bump(centre, 12.0)
        quick += [rest] * 2
    for seed in range(4):
        anchor_of, anchors = _anchors_of(quick, seed=seed)
        assert anchors[:3] == [[4, 5], [7, 8], [10, 11]], (seed, anchors)
        np.testing.assert_array_equal(anchor_of[6:13:3], [0, 1, 2])
    # Presses of one frame each, one frame of rest between, on a rest level that drifts (0.4 a
    # frame along a wide pattern: a contact's impedance creeping): each frame just after a
    # press, the press gone from it in full, is the rest. Once three to five such frames, alike,
    # stand out of the reference's noise, the anchor is their mean, and from then on it follows
    # the last five at each onset. (Without, every frame was read against the reference, the drift
    # growing in each; a skin with memory, whose presses leave half of themselves, is not so
    # followed: above.)
    wide = np.exp(-0.5 * ((np.arange(60) - 30) / 15.0) ** 2)
    drifting, t = [untouched] * 3, 3
    for centre in (10, 45, 25, 52, 5, 38, 18, 48, 12, 33, 57, 22):
        drifting += [0.4 * t * wide + _bump(centre, 12.0), 0.4 * (t + 1) * wide]
        t += 2
    for seed in range(4):
        anchor_of, anchors = _anchors_of(drifting, seed=seed)
        assert len(anchors) >= 3 and all(len(frames) >= 3 for frames in anchors), (seed, anchors)
        assert all(frame % 2 == 0 for frames in anchors for frame in frames)  # the rest frames alone
        # The last presses are read against rest frames at most 12 frames before them.
        assert all(0 < 25 - max(anchors[a]) <= 12 for a in anchor_of[-4:]), (seed, anchors, anchor_of[-4:])


def _magnitude_board(touches: tuple, duration: float, seed: int) -> tuple[de.io.Recording, de.io.Recording]:
    """A skin of radius 80 mm on an opposition-drive board of magnitudes, its readout mixing
    potentials in, gains per reading, medium noise (drawn with `seed`), 10 frames a second for
    `duration` s with `touches`: the recording and its images by `diffeit.reconstruct`'s
    defaults (no calibration)."""
    from diffeit.scene import MeasurementNoise, Noise, ReadingGains, ReadoutMixing, Scene, Skin

    radius = 0.08
    geometry = {"kind": "disc", "radius": radius, "n_electrodes": 16, "electrode_width": 0.15 * radius}
    skin = Skin(geometry=geometry, h=0.1 * radius, protocol="opposite")
    effects = (
        ReadoutMixing.random(16, 0.3, seed=seed),
        ReadingGains.random(192, 0.2, seed=seed),
        MeasurementNoise(Noise.level("medium"), seed=seed),
    )
    scene = Scene(skin=skin, touches=touches, frame_rate=10.0, duration=duration, effects=effects)
    simulated = de.simulate(scene).to_recording()
    recording = de.io.Recording(
        frames=np.abs(np.asarray(simulated.frames)),
        times=simulated.times,
        protocol=simulated.protocol,
        geometry={**geometry, "h": skin.h},
        readings="magnitude",
    )
    return recording, de.reconstruct(recording, progress=False, throw=False)


def test_presses_one_after_another_on_a_magnitude_board_read_as_against_the_reference():
    # The board of `_magnitude_board`; 80 presses one after another, no rest between, imaged
    # without a calibration. A weak press beside the one before it is, in its voltages, nearly
    # that press scaled down: its image, whose peak stands higher than that scale of the press's,
    # tells it from what a press leaves. (Told by the voltages alone, 12 of the 100 frames read
    # other touches: anchored on presses.)
    from diffeit.scene import Disc, Press, Touch

    radius, step = 0.08, 0.1
    rng = np.random.default_rng(0)
    angle, distance = rng.uniform(0, 2 * np.pi, 80), 0.8 * radius * np.sqrt(rng.uniform(0, 1, 80))
    centres = np.stack([distance * np.cos(angle), distance * np.sin(angle)], axis=1)
    starts = (20 + np.arange(80)) * step - 0.5 * step
    touches = tuple(
        Touch(Disc(tuple(c), 0.01), -0.3, Press(start=s, hold=step)) for c, s in zip(centres, starts, strict=True)
    )
    recording, images = _magnitude_board(touches, 100 * step, seed=0)
    found, against_reference = de.touches(images), de.touches(images, baseline="reference")
    np.testing.assert_array_equal(found.count, against_reference.count)
    np.testing.assert_array_equal(found.position, against_reference.position)
    # One untouched frame before the presses: the reference, with no noise to test frames
    # against. Each frame's differences are tested against their own noise, off the subspace a
    # conductivity change reaches (`subspace_statistic`, kept by `diffeit.reconstruct`), beside
    # the image's hills: 78 of the 80 presses are read, each as one touch (by the image's hills
    # alone, 37; a further hill held to the lower bar of a frame tested against known noise, 24
    # of them read as 2 to 4 touches).
    first = np.arange(19, 100)
    short = dataclasses.replace(recording, frames=recording.frames[first], times=recording.times[first])
    images = de.reconstruct(short, progress=False, throw=False)
    assert images.provenance["metadata"]["reading_noise"] is None
    found = de.touches(images)
    assert found.count[0] == 0 and np.sum(found.count[1:] >= 1) >= 76, np.sum(found.count[1:] >= 1)
    assert np.all(found.count <= 1)
    metadata = {**images.provenance["metadata"], "touch_statistic": [1.0, 2.0]}
    with pytest.raises(ValueError, match="touch_statistic"):
        de.touches(dataclasses.replace(images, provenance={**images.provenance, "metadata": metadata}))


def test_a_touch_sliding_across_a_magnitude_boards_skin_reads_as_against_the_reference():
    # The board of `_magnitude_board` (another seed), a finger sliding across it three times at
    # one radius a second, a rest between. Towards the middle the touch fades frame by frame, and
    # its voltages are nearly the frame before scaled down, but its image's hill has left the
    # place of the touch's highest frame: the touch moved on, it is not what that frame left, and
    # no anchor moves. (Read as what it left, its frames became a rest anchor: 54 of the 77
    # frames were read against a touch, and 3 of the 27 frames of the slides read none.)
    from diffeit.scene import Disc, Path, Press, Touch

    radius, seed = 0.08, 3
    rng = np.random.default_rng(seed)
    touches, start = [], 2.0
    for _ in range(3):
        begin, end = rng.uniform(-0.6, 0.6, (2, 2)) * radius
        duration = np.linalg.norm(end - begin) / radius  # one radius a second
        path = Path([start + 0.1, start + 0.1 + duration], [begin, end])
        touches.append(Touch(Disc(path, 0.01), -0.3, Press(start=start, ramp_in=0.1, hold=duration + 0.1)))
        start += duration + 1.2
    recording, images = _magnitude_board(tuple(touches), start, seed)
    found, against_reference = de.touches(images), de.touches(images, baseline="reference")
    assert np.all(found.anchor == -1)
    np.testing.assert_array_equal(found.count, against_reference.count)
    np.testing.assert_array_equal(found.position, against_reference.position)
    times = np.asarray(recording.times)
    sliding = np.zeros(len(times), bool)
    for touch in touches:
        sliding |= (times > touch.envelope.start) & (times < touch.envelope.start + 0.1 + touch.envelope.hold)
    np.testing.assert_array_equal(found.count > 0, sliding)  # a touch on every frame of the slides alone


@pytest.mark.parametrize("noise", ["a fraction of each reading", "alike on every reading"])
def test_with_no_noise_known_untouched_frames_read_no_touch_whatever_the_noise_is_like(noise):
    """A reference of one frame, no calibration: frames are tested against their own noise off
    the subspace a conductivity change reaches (`subspace_statistic`). Noise that is a fraction
    of each reading (0.1%) lies mostly on the largest readings, where that subspace is: tested on
    the differences as they are, an untouched frame stood 12.8 out and read a touch. Relative to
    the model's readings it is alike on every reading; the smaller of the two tells."""
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.12)
    model = de.ForwardModel(mesh, de.protocol.adjacent(16))
    untouched = np.asarray(model.measure(jnp.ones(mesh.n_elements)))
    places = [(0.3 * np.cos(angle), 0.3 * np.sin(angle)) for angle in np.linspace(0, 6, 8)]
    pressed = [np.asarray(model.measure(jnp.asarray(1 - 0.3 * de.mesh.disc_fraction(mesh, p, 0.2)))) for p in places]
    clean = np.array([untouched] * 3 + pressed)
    size = clean if noise == "a fraction of each reading" else np.sqrt(np.mean(untouched**2))
    frames = clean + 1e-3 * size * np.random.default_rng(0).standard_normal(clean.shape)
    recording = de.io.Recording(
        frames=frames[1:], times=0.1 * np.arange(10), protocol=model.protocol, mesh=mesh, reference=frames[0]
    )
    images = de.reconstruct(recording, progress=False)
    statistic = np.asarray(images.provenance["metadata"]["touch_statistic"])
    assert np.all(statistic[:2] < 3) and np.all(statistic[2:] > 50), statistic
    found = de.touches(images)
    assert found.count.tolist() == [0, 0] + [1] * 8
    distance = np.linalg.norm(found.position[2:, 0] - np.array(places), axis=1)
    assert np.max(distance) < 0.15, distance
    calibration = de.calibrate(recording)
    for bad, match in ((statistic[:, None], "differences must be"), (np.full((2, 208), np.nan), "NaN")):
        with pytest.raises(ValueError, match=match):
            de.touch.subspace_statistic(bad, calibration)
