import numpy as np
import pytest

import diffeit as de


def test_adjacent_order_and_sign_follow_eidors():
    protocol = de.protocol.adjacent(16)
    assert (protocol.n_drives, protocol.n_measurements, protocol.n_electrodes) == (16, 208, 16)
    row = 0
    for k in range(16):
        expected_drive = np.zeros(16)
        expected_drive[(k + 1) % 16], expected_drive[k] = 1.0, -1.0  # in at k+1, out at k
        np.testing.assert_array_equal(protocol.drive[k], expected_drive)
        for m in range(16):
            if {m, (m + 1) % 16} & {k, (k + 1) % 16}:
                continue
            expected = np.zeros(16)
            expected[m], expected[(m + 1) % 16] = 1.0, -1.0  # U_m - U_(m+1)
            np.testing.assert_array_equal(protocol.measure[row], expected)
            assert protocol.drive_index[row] == k
            row += 1
    assert row == 208
    # Drive 0 measures pairs (2,3) .. (14,15); drive 15 (in at 0, out at 15) pairs (1,2) .. (13,14).
    assert np.flatnonzero(protocol.measure[0] == 1)[0] == 2
    assert np.flatnonzero(protocol.measure[207] == 1)[0] == 13


def test_adjacent_is_a_general_protocol_with_distinct_patterns():
    protocol = de.protocol.adjacent(8)
    rebuilt = de.Protocol(protocol.drive, [protocol.measure[protocol.drive_index == k] for k in range(8)])
    np.testing.assert_array_equal(rebuilt.measure, protocol.measure)
    np.testing.assert_array_equal(rebuilt.drive_index, protocol.drive_index)
    assert protocol.measure_patterns.shape == (8, 8)  # one per electrode pair
    np.testing.assert_array_equal(protocol.measure_patterns[protocol.pattern_index], protocol.measure)


def test_protocol_accepts_a_dense_measurement_array():
    drive = np.array([[1.0, -1.0, 0.0, 0.0], [0.0, 1.0, -1.0, 0.0]])
    measure = np.array([[[0.0, 0.0, 1.0, -1.0]], [[1.0, 0.0, 0.0, -1.0]]])
    protocol = de.Protocol(drive, measure)
    assert protocol.n_measurements == 2
    np.testing.assert_array_equal(protocol.drive_index, [0, 1])


@pytest.mark.parametrize(
    ("drive", "measure", "message"),
    [
        (np.array([[1.0, 0.0, 0.0, 0.0]]), [np.eye(4)[:1]], "do not sum to zero"),
        (np.array([[1.0, -1.0, 0.0, 0.0]]), [np.eye(3)], r"shape \(M, 4\)"),
        (np.array([[1.0, -1.0, 0.0, 0.0]]), [np.eye(4), np.eye(4)], "readings for 2 drives"),
        (np.array([[np.nan, -1.0, 0.0, 0.0]]), [np.eye(4)], "non-finite"),
        (np.array([1.0, -1.0]), [np.eye(2)], "n_drives, n_electrodes"),
    ],
)
def test_bad_protocols_are_refused(drive, measure, message):
    with pytest.raises(ValueError, match=message):
        de.Protocol(drive, measure)


def test_protocol_and_mesh_must_agree(small_disc):
    with pytest.raises(ValueError, match="addresses 8 electrodes; the mesh has 16"):
        de.ForwardModel(small_disc, de.protocol.adjacent(8))


def _pair(n, a, b, first=1.0, second=-1.0):
    row = np.zeros(n)
    row[a % n], row[b % n] = first, second
    return row


@pytest.mark.parametrize("n", [4, 5, 8, 16])
@pytest.mark.parametrize("options", [{}, {"measure_driven": True}, {"rotate_measurements": True}])
def test_skip_zero_is_adjacent(n, options):
    skip, adjacent = de.protocol.skip(n, 0, **options), de.protocol.adjacent(n, **options)
    np.testing.assert_array_equal(skip.drive, adjacent.drive)
    np.testing.assert_array_equal(skip.measure, adjacent.measure)
    np.testing.assert_array_equal(skip.drive_index, adjacent.drive_index)


def test_skip_order_and_sign_follow_eidors():
    """skip(16, 3): drive i is -1 at i, +1 at i+4; readings U_m - U_(m+4), m from 0, off the driven pair."""
    protocol = de.protocol.skip(16, 3)
    row = 0
    for i in range(16):
        np.testing.assert_array_equal(protocol.drive[i], _pair(16, i + 4, i))
        for m in range(16):
            if {m, (m + 4) % 16} & {i, (i + 4) % 16}:
                continue
            np.testing.assert_array_equal(protocol.measure[row], _pair(16, m, m + 4))
            assert protocol.drive_index[row] == i
            row += 1
    assert row == protocol.n_measurements == 208


def test_opposite_follows_eidors():
    """EIDORS '{op}' is [0, n/2] with amplitudes [-1, 1]: -1 at i, +1 at i+n/2; adjacent readings."""
    protocol = de.protocol.opposite(16)
    for i in range(16):
        np.testing.assert_array_equal(protocol.drive[i], _pair(16, i + 8, i))
    np.testing.assert_array_equal(protocol.drive[8:], -protocol.drive[:8])  # both halves kept, as EIDORS does
    first = protocol.measure[protocol.drive_index == 0]
    starts = [int(np.flatnonzero(row == 1)[0]) for row in first]
    assert starts == [1, 2, 3, 4, 5, 6, 9, 10, 11, 12, 13, 14]  # pairs touching 0 or 8 skipped
    np.testing.assert_array_equal(first, [_pair(16, m, m + 1) for m in starts])


def test_rotated_measurements_start_at_the_drive():
    standard = de.protocol.adjacent(16)
    rotated = de.protocol.adjacent(16, rotate_measurements=True)
    for k in range(16):
        starts = [int(np.flatnonzero(row == 1)[0]) for row in rotated.measure[rotated.drive_index == k]]
        assert starts == [(k + 2 + j) % 16 for j in range(13)]  # k+2, ..., k-2: the first pair off k, k+1
        np.testing.assert_array_equal(rotated.drive[k], standard.drive[k])
    # Drives 0 and 1 coincide: the pairs that wrap round are skipped anyway.
    np.testing.assert_array_equal(rotated.measure[:26], standard.measure[:26])
    assert not np.array_equal(rotated.measure[26:39], standard.measure[26:39])


def test_measure_driven_keeps_every_pair_in_order():
    protocol = de.protocol.adjacent(16, measure_driven=True)
    expected = np.stack([_pair(16, m, m + 1) for m in range(16)])
    for k in range(16):
        np.testing.assert_array_equal(protocol.measure[16 * k : 16 * (k + 1)], expected)


@pytest.mark.parametrize(
    ("build", "count"),
    [
        (lambda: de.protocol.adjacent(16), 208),
        (lambda: de.protocol.adjacent(16, rotate_measurements=True), 208),
        (lambda: de.protocol.opposite(16), 192),
        (lambda: de.protocol.opposite(8), 32),
        (lambda: de.protocol.opposite(6), 12),
        (lambda: de.protocol.skip(16, 1), 208),
        (lambda: de.protocol.skip(16, 4), 208),
        (lambda: de.protocol.skip(16, 7), 224),  # k = n/2 - 1: the two pairs touching both driven electrodes coincide
        (lambda: de.protocol.skip(16, 14), 208),
        (lambda: de.protocol.skip(32, 4), 928),
        (lambda: de.protocol.skip(4, 1), 8),
        (lambda: de.protocol.adjacent(16, measure_driven=True), 256),
        (lambda: de.protocol.opposite(16, measure_driven=True), 256),
        (lambda: de.protocol.skip(16, 7, measure_driven=True, rotate_measurements=True), 256),
        (lambda: de.protocol.adjacent(3, measure_driven=True), 9),
        (lambda: de.protocol.opposite(2, measure_driven=True), 4),
    ],
)
def test_measurement_counts(build, count):
    assert build().n_measurements == count


def test_multi_electrode_drives_and_reference_readings_are_accepted():
    """Kuopio-challenge style, 32 electrodes: current into one electrode and out of all others,
    trigonometric patterns, every electrode read against electrode 0."""
    n = 32
    eye, angles = np.eye(n), 2 * np.pi * np.arange(n) / n
    one_to_all = eye[0] - (1 - eye[0]) / (n - 1)
    drive = np.stack([one_to_all, np.cos(angles), np.sin(3 * angles)])
    reference = eye[1:] - eye[0]  # U_l - U_0, l = 1..31
    protocol = de.Protocol(drive, [reference] * 3)
    assert (protocol.n_drives, protocol.n_measurements, protocol.measure_patterns.shape) == (3, 93, (31, 32))


def test_reference_readings_agree_with_adjacent_ones(small_disc, rough_conductivity):
    """Under a trigonometric drive, U_l - U_0 = -sum_(m<l) (U_m - U_(m+1)): readings of a general
    protocol are the same potentials read differently."""
    eye = np.eye(16)
    drive = np.cos(2 * np.pi * np.arange(16) / 16)[None] + eye[3] - eye[11]
    adjacent_pairs = eye - np.roll(eye, 1, axis=1)
    protocol = de.Protocol(drive, [np.concatenate([eye[1:] - eye[0], adjacent_pairs])])
    voltages = np.asarray(de.ForwardModel(small_disc, protocol).measure(rough_conductivity))
    np.testing.assert_allclose(
        voltages[:15], -np.cumsum(voltages[15:30]), rtol=1e-10, atol=1e-12 * np.abs(voltages).max()
    )


@pytest.mark.parametrize(
    ("drive", "measure", "message"),
    [
        (
            np.array([[1.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]]),
            [np.eye(4), np.eye(4)],
            r"drive patterns \[1\] are all zero",
        ),
        (
            np.array([[1.0, -1.0, 0.0, 0.0]]),
            [np.array([[1.0, -1, 0, 0], [0, 0, 0, 0]])],
            r"measurements \[1\] of drive 0 are all zero",
        ),
        (np.array([[0.0]]), [np.ones((1, 1))], "at least 2 electrodes"),
        (np.array([[1.0, -1.0, 0.0, 0.0]]), [np.eye(5)], r"shape \(M, 4\), one weight per electrode"),
        (np.array([[1.0, -1.0, 0.0], [2.0, 0.0, 0.0]]), [np.eye(3), np.eye(3)], r"drive patterns \[1\] do not sum"),
        (np.array([[1.0, -1.0]]), [np.zeros((0, 2))], "no measurements"),
    ],
)
def test_more_bad_protocols_are_refused(drive, measure, message):
    with pytest.raises(ValueError, match=message):
        de.Protocol(drive, measure)


@pytest.mark.parametrize(
    ("build", "message"),
    [
        (lambda: de.protocol.skip(16, 15), r"skip k must be in 0\.\.14"),
        (lambda: de.protocol.skip(16, -1), r"skip k must be in 0\.\.14"),
        (lambda: de.protocol.opposite(15), "even number of electrodes"),
        (lambda: de.protocol.opposite(4), "leaves drive 0 no reading off the driven electrodes"),
        (lambda: de.protocol.adjacent(3), "leaves drive 0 no reading"),
        (lambda: de.protocol.adjacent(1), "at least 2 electrodes"),
        (lambda: de.protocol.skip(1, 0, measure_driven=True), "at least 2 electrodes"),
    ],
)
def test_bad_builder_arguments_are_refused(build, message):
    with pytest.raises(ValueError, match=message):
        build()


def test_select_keeps_the_chosen_readings_in_order_and_refuses_none():
    protocol = de.protocol.adjacent(16)
    mask = np.arange(208) % 3 != 0
    chosen = protocol.select(mask)
    np.testing.assert_array_equal(chosen.measure, protocol.measure[mask])
    np.testing.assert_array_equal(chosen.drive_index, protocol.drive_index[mask])
    np.testing.assert_array_equal(chosen.drive, protocol.drive)
    np.testing.assert_array_equal(protocol.select(np.flatnonzero(mask)).measure, chosen.measure)
    with pytest.raises(ValueError, match="no readings"):
        protocol.select(np.zeros(208, bool))
    with pytest.raises(ValueError, match="shape"):
        protocol.select(np.ones(200, bool))
    with pytest.raises(ValueError, match="indices"):
        protocol.select([0, 208])


def test_relabel_moves_the_electrodes_and_keeps_the_readings():
    protocol = de.protocol.adjacent(16)
    rotated = protocol.relabel((np.arange(16) + 1) % 16)
    # Instrument drive 0 (into electrode 1, out of 0) now enters the sheet at 2 and leaves at 1.
    assert rotated.drive[0, 2] == 1 and rotated.drive[0, 1] == -1
    np.testing.assert_array_equal(np.roll(protocol.measure, 1, axis=1), rotated.measure)
    reversed_twice = protocol.relabel((-np.arange(16)) % 16).relabel((-np.arange(16)) % 16)
    assert reversed_twice == protocol
    with pytest.raises(ValueError, match="permutation"):
        protocol.relabel(np.zeros(16, int))
