import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffeit as de
from diffeit.protocol import Conversion, adjacent, convert, from_full_layout, from_pyeit, opposite, skip, to_full_layout


def _frames(n_measurements, batch=(), seed=0):
    return np.random.default_rng(seed).normal(size=(*batch, n_measurements))


def _touches_driven(k, m, n=16):
    return bool({m, (m + 1) % n} & {k, (k + 1) % n})


def test_full_layout_places_values_at_16_drive_plus_pair():
    frames = _frames(208)
    full = to_full_layout(frames)
    assert full.shape == (256,)
    reading = 0
    for k in range(16):
        for m in range(16):
            if _touches_driven(k, m):
                assert full[16 * k + m] == 0.0
            else:
                assert full[16 * k + m] == frames[reading]
                reading += 1
    assert np.count_nonzero(full == 0.0) == 48


def test_full_layout_round_trip():
    frames = _frames(208, (5,))
    np.testing.assert_array_equal(from_full_layout(to_full_layout(frames)), frames)
    full = to_full_layout(frames)
    full[:, full[0] == 0] = 7.0  # what the driven pairs hold is dropped
    np.testing.assert_array_equal(from_full_layout(full), frames)
    np.testing.assert_array_equal(to_full_layout(_frames(5 * 8, (2,)), n_electrodes=8).shape, (2, 64))


def test_rotated_standard_round_trip():
    standard, rotated = adjacent(16), adjacent(16, rotate_measurements=True)
    frames = _frames(208, (3,))
    to_standard = Conversion(rotated, standard)
    back = Conversion(standard, rotated)
    assert not np.array_equal(to_standard.index, np.arange(208))  # a real permutation, no signs
    np.testing.assert_array_equal(np.sort(to_standard.index), np.arange(208))
    np.testing.assert_array_equal(to_standard.sign, 1.0)
    np.testing.assert_array_equal(back(to_standard(frames)), frames)
    # Reading by reading: same drive, same weights.
    np.testing.assert_array_equal(rotated.measure[to_standard.index], standard.measure)
    np.testing.assert_array_equal(rotated.drive_index[to_standard.index], standard.drive_index)


def test_negated_weights_or_drive_negate_the_value_and_both_keep_it():
    protocol = adjacent(8)
    per_drive = [protocol.measure[protocol.drive_index == k] for k in range(8)]
    weights_flipped = de.Protocol(protocol.drive, [-m for m in per_drive])
    drive_flipped = de.Protocol(-protocol.drive, per_drive)
    both_flipped = de.Protocol(-protocol.drive, [-m for m in per_drive])
    frames = _frames(protocol.n_measurements, (4,))
    np.testing.assert_array_equal(convert(frames, protocol, weights_flipped), -frames)
    np.testing.assert_array_equal(convert(frames, protocol, drive_flipped), -frames)
    np.testing.assert_array_equal(convert(frames, protocol, both_flipped), frames)
    np.testing.assert_array_equal(
        convert(convert(frames, protocol, weights_flipped), weights_flipped, protocol), frames
    )


def test_batch_conversion_equals_per_frame_in_numpy_and_jax():
    conversion = Conversion(adjacent(16), adjacent(16, measure_driven=True, rotate_measurements=True), fill=0.0)
    frames = _frames(208, (1000,))
    batch = conversion(frames)
    assert isinstance(batch, np.ndarray) and batch.shape == (1000, 256)
    np.testing.assert_array_equal(batch[17], conversion(frames[17]))
    np.testing.assert_array_equal(np.asarray(conversion(jnp.asarray(frames))), batch)
    np.testing.assert_array_equal(np.asarray(jax.jit(conversion)(jnp.asarray(frames))), batch)
    np.testing.assert_array_equal(np.asarray(jax.vmap(conversion)(jnp.asarray(frames))), batch)
    assert conversion(np.arange(208)).dtype == np.float64  # integer counts become floats
    np.testing.assert_array_equal(conversion(frames * (1 - 2j)), batch * (1 - 2j))  # complex frames stay complex


def test_duplicate_matches_are_resolved_in_a_documented_order():
    protocol = opposite(16)  # drive i+8 is drive i negated: every reading has a second, negated-drive match
    identity = Conversion(protocol, protocol)
    np.testing.assert_array_equal(identity.index, np.arange(192))
    np.testing.assert_array_equal(identity.sign, 1.0)
    # Only drives 0..7 recorded: drives 8..15 come from their negations.
    half = de.Protocol(protocol.drive[:8], [protocol.measure[protocol.drive_index == k] for k in range(8)])
    from_half = Conversion(half, protocol)
    np.testing.assert_array_equal(from_half.index, np.tile(np.arange(96), 2))
    np.testing.assert_array_equal(from_half.sign, np.repeat([1.0, -1.0], 96))
    # Same drive with negated weights beats negated drive with the same weights; then source order.
    eye = np.eye(4)
    drive = np.stack([eye[1] - eye[0], eye[0] - eye[1]])
    source = de.Protocol(drive, [eye[[3, 3]] - eye[[2, 2]], eye[[2]] - eye[[3]]])
    target = de.Protocol(drive[:1], [eye[[2]] - eye[[3]]])
    conversion = Conversion(source, target)
    assert (conversion.index.tolist(), conversion.sign.tolist()) == ([0], [-1.0])


def test_unmatched_readings_are_named_or_filled():
    named = r"48 target reading\(s\) \[0, 1, 15, 16, .*drive \{0: -1.0, 1: 1.0\}, weights \{0: 1.0, 1: -1.0\}"
    with pytest.raises(ValueError, match=named + ".*pass fill=0.0"):
        Conversion(adjacent(16), adjacent(16, measure_driven=True))
    filled = convert(_frames(208), adjacent(16), adjacent(16, measure_driven=True), fill=np.nan)
    assert np.count_nonzero(np.isnan(filled)) == 48
    with pytest.raises(ValueError, match="have no match"):
        Conversion(adjacent(16), skip(16, 4))


def test_conversion_inputs_are_checked():
    with pytest.raises(ValueError, match="addresses 16 electrodes; the target 8"):
        Conversion(adjacent(16), adjacent(8))
    with pytest.raises(ValueError, match=r"shape \(208,\); expected \(\.\.\., 256\)"):
        from_full_layout(_frames(208))
    with pytest.raises(ValueError, match=r"expected \(\.\.\., 208\)"):
        to_full_layout(np.float64(1.0))


def _pyeit_protocols():
    from pyeit.eit import protocol

    cases = [
        (1, 1, "std", adjacent(16)),
        (1, 1, "rotate_meas", adjacent(16, rotate_measurements=True)),
        (1, 1, ["meas_current"], adjacent(16, measure_driven=True)),
        (1, 1, ["rotate_meas", "meas_current"], adjacent(16, measure_driven=True, rotate_measurements=True)),
        (4, 4, "std", skip(16, 3)),
        (8, 1, "std", opposite(16)),
    ]
    return [(protocol.create(16, dist, step, parser), target) for dist, step, parser, target in cases]


def test_from_pyeit_reads_ex_mat_and_meas_mat_reading_by_reading():
    for pyeit_protocol, _ in _pyeit_protocols():
        converted = from_pyeit(pyeit_protocol)
        ex_mat, meas_mat = pyeit_protocol.ex_mat, pyeit_protocol.meas_mat
        assert converted.n_measurements == pyeit_protocol.n_meas_tot
        for i, (a, b) in enumerate(ex_mat):  # current in at a, out at b
            assert converted.drive[i, a] == 1.0 and converted.drive[i, b] == -1.0
            assert np.count_nonzero(converted.drive[i]) == 2
        for j, (p, q) in enumerate(meas_mat.reshape(-1, 2)):  # U_p - U_q, drive by drive
            assert converted.measure[j, p] == 1.0 and converted.measure[j, q] == -1.0
            assert converted.drive_index[j] == j // pyeit_protocol.n_meas
        same = from_pyeit(ex_mat, meas_mat)
        np.testing.assert_array_equal(same.measure, converted.measure)


def test_pyeit_frames_match_diffeit_order_and_sign():
    """pyEIT negates both the drive and the readings, so its adjacent frames ('std': pairs from
    0; 'rotate_meas': from the drive's first electrode) are diffeit's value for value."""
    for pyeit_protocol, target in _pyeit_protocols():
        conversion = Conversion(from_pyeit(pyeit_protocol), target)
        if target.drive[8, 0] == 0.0:  # adjacent and skip: drive and readings negated, the identity
            np.testing.assert_array_equal(conversion.index, np.arange(target.n_measurements))
            np.testing.assert_array_equal(conversion.sign, 1.0)
        else:  # opposite: pyEIT's drive i + 8 is diffeit's drive i exactly, its readings negated
            np.testing.assert_array_equal(conversion.index, (np.arange(192) + 96) % 192)
            np.testing.assert_array_equal(conversion.sign, -1.0)


def test_from_pyeit_refuses_bad_input():
    with pytest.raises(ValueError, match="ex_mat and meas_mat"):
        from_pyeit(np.array([[0, 1]]))
    with pytest.raises(ValueError, match=r"ex_mat must have shape \(n_exc, 2\)"):
        from_pyeit(np.array([0, 1, 2]), np.zeros((1, 1, 2), dtype=int))
    with pytest.raises(ValueError, match=r"meas_mat must have shape \(1, n_meas, 2\)"):
        from_pyeit(np.array([[0, 1]]), np.zeros((2, 1, 2), dtype=int))
    with pytest.raises(ValueError, match=r"electrode numbers in 0\.\.3"):
        from_pyeit(np.array([[0, 1]]), np.array([[[2, 4]]]), n_electrodes=4)
    with pytest.raises(ValueError, match="all zero"):
        from_pyeit(np.array([[0, 0]]), np.array([[[2, 3]]]))


# Physics: the same conductivity simulated under two protocols, one converted onto the other.


def test_converted_simulations_equal_direct_ones(small_disc, rough_conductivity):
    protocols = {
        "standard": adjacent(16),
        "rotated": adjacent(16, rotate_measurements=True),
        "full": adjacent(16, measure_driven=True),
        "opposite": opposite(16),
    }
    v = {name: np.asarray(de.ForwardModel(small_disc, p).measure(rough_conductivity)) for name, p in protocols.items()}
    scale = np.abs(v["full"]).max()
    np.testing.assert_allclose(convert(v["rotated"], protocols["rotated"], protocols["standard"]), v["standard"])
    np.testing.assert_allclose(from_full_layout(v["full"]), v["standard"], rtol=1e-12, atol=1e-14 * scale)
    # Opposite drives i + 8 are drives i negated: recorded halves give the whole, negated.
    half = de.Protocol(protocols["opposite"].drive[:8], list(np.split(protocols["opposite"].measure[:96], 8)))
    v_half = np.asarray(de.ForwardModel(small_disc, half).measure(rough_conductivity))
    np.testing.assert_allclose(
        convert(v_half, half, protocols["opposite"]), v["opposite"], rtol=1e-9, atol=1e-12 * scale
    )


@pytest.mark.slow
def test_pyeit_protocols_simulated_in_diffeit_convert_exactly(small_disc, rough_conductivity):
    """diffeit simulating pyEIT's protocols as pyEIT defines them: converted, they equal diffeit's."""
    for pyeit_protocol, target in _pyeit_protocols()[4:]:  # skip 3 and opposite: both sign paths
        source = from_pyeit(pyeit_protocol)
        v_source = de.ForwardModel(small_disc, source).measure(rough_conductivity)
        v_target = np.asarray(de.ForwardModel(small_disc, target).measure(rough_conductivity))
        np.testing.assert_allclose(
            convert(np.asarray(v_source), source, target), v_target, rtol=1e-9, atol=1e-12 * np.abs(v_target).max()
        )


def test_pyeit_forward_agrees_in_sign_and_order():
    """pyEIT's own (point-electrode) forward model on its own disc, converted to diffeit order,
    has the shape of diffeit's adjacent voltages: a wrong sign would give correlation -1, a wrong
    order far less than 1."""
    from pyeit import mesh as pyeit_mesh
    from pyeit.eit import fem as pyeit_fem

    mesh = pyeit_mesh.create(16, h0=0.15)
    disc = de.mesh.disc(16, electrode_width=0.2, h=0.15)
    for pyeit_protocol, target in _pyeit_protocols()[:2]:
        frames = pyeit_fem.EITForward(mesh, pyeit_protocol).solve_eit()
        converted = convert(frames, from_pyeit(pyeit_protocol), target)
        expected = np.asarray(de.ForwardModel(disc, target).measure(np.ones(disc.n_elements)))
        assert np.corrcoef(converted, expected)[0, 1] > 0.99
