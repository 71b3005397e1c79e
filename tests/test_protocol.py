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
