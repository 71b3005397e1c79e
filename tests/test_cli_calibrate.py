"""`diffeit calibrate SESSION.h5 --presses PRESSES.csv -o SKIN.cal.h5`, `diffeit reconstruct
--calibration SKIN.cal.h5 --touches`, and `diffeit.io.read_presses`."""

import csv

import equinox as eqx
import numpy as np
import pytest
from skin_sessions import calibrated_session

import diffeit as de
from diffeit.cli import main
from diffeit.cli._calibrate import _calibration_figure


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """A session file and its presses CSV (tests/skin_sessions.py's `calibrated_session`): a board
    with drive and channel gains up to 25%, contact impedances spread 3x, 0.1% noise; 10
    untouched frames, then 30 presses (radius 0.15, dsigma/sigma = -0.3) at known places, one
    after another."""
    shared = calibrated_session(tmp_path_factory)
    return shared.path, shared.presses, shared.skin.presses.centres


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """`diffeit calibrate SESSION.h5 --presses PRESSES.csv -o SKIN.cal.h5` run on the session once
    per test process, shared with tests/test_cli_live_touches.py: its exit status and output."""
    shared = calibrated_session(tmp_path_factory)
    return shared.status, shared.calibration


def test_calibrate_writes_a_calibration_file_and_its_figure(session, calibrated, capsys):
    path, _, _ = session
    status, output = calibrated
    assert status == 0
    skin = de.calibration.load(output, recording=de.io.read_frames(path))
    assert skin.position_map is not None and skin.press_errors is not None
    assert np.nanmedian(skin.press_errors) < 0.1
    assert output.with_suffix(".png").stat().st_size > 10_000  # skin.cal.png, beside it
    # An existing output is refused, with the other commands' one-line error.
    assert main(["calibrate", str(path), "-o", str(output)]) == 2
    assert "diffeit calibrate: error:" in capsys.readouterr().err


def test_the_figure_names_the_mixing_weights_and_says_which_groups_were_not_fitted(session, calibrated):
    """The mixing panel's ticks name each weight (the source's, the sink's, then offset j's), a
    panel of gains not fitted is titled so, and the presses' panel has its units."""
    path, presses_file, _ = session
    skin = de.calibration.load(calibrated[1], recording=de.io.read_frames(path))
    figure = _calibration_figure(skin, de.io.read_presses(presses_file))
    mixing, gains, presses = figure.axes[1:4]
    names = [label.get_text() for label in mixing.get_xticklabels()]
    assert names == ["source", "sink", *map(str, range(16))]
    # Drive and channel gains are fitted on request only (`diffeit.calibration.REFERENCE_GROUPS`).
    assert skin.fitted["reference"] == ("level", "contact_impedance", "mixing")
    assert gains.get_title() == "drive and channel gains (not fitted: 1)"
    requested = eqx.tree_at(lambda c: c.fitted, skin, {"reference": ("level", "drive_gains")})
    assert [axes.get_title() for axes in _calibration_figure(requested, None).axes[1:3]] == [
        "readout mixing weights (not fitted)",
        "drive and channel gains",
    ]
    assert (presses.get_xlabel(), presses.get_ylabel()) == ("x (m)", "y (m)")


def test_calibrate_fits_a_background_map_on_request_and_draws_it(session, tmp_path):
    """`--background-map yes` on the session's untouched frames alone (no presses: the default
    fits none): the file holds the map and the figure colours the mesh by it (looked at)."""
    path, _, _ = session
    output = tmp_path / "skin.cal.h5"
    assert main(["calibrate", str(path), "--background-map", "yes", "-o", str(output)]) == 0
    skin = de.calibration.load(output)
    assert skin.background_map is not None and "background_map" in skin.fitted["reference"]
    assert skin.background_map.shape == (skin.model.mesh.n_elements,)
    assert output.with_suffix(".png").stat().st_size > 10_000


def test_reconstruct_with_the_calibration_places_the_touches_at_the_presses(session, calibrated, tmp_path, capsys):
    path, _, centres = session
    _, calibration = calibrated
    out = tmp_path / "images"
    capsys.readouterr()
    arguments = ["reconstruct", str(path), "-o", str(out), "--calibration", str(calibration), "--touches"]
    assert main(arguments) == 0
    printed = capsys.readouterr().out
    assert "frame 10 (t = 1.000 s): touch 0:" in printed
    with open(tmp_path / "images.touches.csv", newline="") as file:
        rows = list(csv.DictReader(file))
    first = {int(row["frame"]): row for row in reversed(rows) if row["touch"] == "0"}  # each frame's strongest
    assert set(range(10, 40)) <= set(first)
    found = np.array([[float(first[t]["x_m"]), float(first[t]["y_m"])] for t in range(10, 40)])
    errors = np.linalg.norm(found - centres, axis=1)
    assert np.median(errors) < 0.1, np.median(errors)
    assert all(float(row["radius_m"]) > 0 and float(row["depth"]) < 0 for row in rows)
    metadata = de.io.read_frames(tmp_path / "images.h5").provenance["metadata"]
    assert metadata["calibrated"]


def test_a_hold_labelled_at_frame_times_holds_them_to_rounding():
    """A hold labelled 3.8 s to 4.0 s holds the frames a clock stamped a rounding before 3.8 s
    and after 4.0 s (times summed frame by frame, labels written from frame numbers); a frame a
    period away does not."""
    times = 0.1 * np.arange(60)
    times[38], times[40] = np.nextafter(3.8, 0.0), np.nextafter(4.0, 5.0)
    presses = de.io.Presses(np.zeros((2, 2)), 0.01, np.array([[3.8, 4.0], [3.85, 3.95]]))
    held, inner = presses.frames(times)
    np.testing.assert_array_equal(held, [38, 39, 40])
    np.testing.assert_array_equal(inner, [39])


def test_read_presses_reads_instants_and_holds(tmp_path):
    instants = tmp_path / "instants.csv"
    instants.write_text("\ufeffx_m,y_m,radius_m,time_s\n0.1,-0.2,0.05,1.5\n\n0,0.3,0.1,2\n")
    presses = de.io.read_presses(instants)
    np.testing.assert_array_equal(presses.centres, [[0.1, -0.2], [0.0, 0.3]])
    np.testing.assert_array_equal(presses.radius, [0.05, 0.1])
    np.testing.assert_array_equal(presses.times, [[1.5, 1.5], [2.0, 2.0]])
    holds = tmp_path / "holds.csv"
    holds.write_text("end_s,start_s,x_m,y_m,radius_m\r\n2.0,1.0,0,0,0.1\r\n")
    np.testing.assert_array_equal(de.io.read_presses(holds).times, [[1.0, 2.0]])
    on_a_surface = tmp_path / "surface.csv"
    on_a_surface.write_text("z_m,x_m,y_m,radius_m,start_s,end_s\n0.9,0.1,-0.2,0.05,1,3\n")
    presses = de.io.read_presses(on_a_surface)
    np.testing.assert_array_equal(presses.centres, [[0.1, -0.2, 0.9]])
    np.testing.assert_array_equal(presses.radius, [0.05])
    np.testing.assert_array_equal(presses.times, [[1.0, 3.0]])


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("x_m,y_m,time_s\n0,0,1\n", r"line 1 \(the header\) lacks column\(s\) radius_m"),
        ("x_m,y_m,radius_m\n0,0,0.1\n", r"lacks column\(s\) time_s \(or start_s and end_s\)"),
        ("x_m,y_m,radius_m,start_s\n0,0,0.1,1\n", r"lacks column\(s\) end_s"),
        ("x_m,y_m,radius_m,time_s,start_s,end_s\n0,0,0.1,1,1,2\n", "both time_s and start_s/end_s"),
        ("x_m,y_m,radius_m,time_s\n0,0,0.1,1\n0,zero,0.1,2\n", r"line 3, column y_m is not a number: 'zero'"),
        ("x_m,y_m,radius_m,time_s\n0,nan,0.1,1\n", "line 2, column y_m is not finite: 'nan'"),
        ("x_m,y_m,radius_m,time_s\n0,0,inf,1\n", "line 2, column radius_m is not finite"),
        ("x_m,y_m,radius_m,time_s\n0,0,0.1,1\n0,0,0.1", "line 3, the last, does not end in a newline"),
        ("x_m,y_m,radius_m,time_s\n0,0,0.1\n", "line 2 has 3 columns; the header has 4"),
        ("x_m,y_m,radius_m,time_s\n0,0,0,1\n", "line 2: radius_m must be positive"),
        ("x_m,y_m,radius_m,start_s,end_s\n0,0,0.1,2,1\n", "line 2: the hold ends"),
        ("x_m,y_m,z_m,radius_m,start_s,end_s\n0,0,1,0.1,2,1\n", "line 2: the hold ends"),
        ("x_m,y_m,z_m,radius_m,time_s\n0,0,1,-0.1,2\n", "line 2: radius_m must be positive"),
        ("x_m,y_m,z_m,radius_m,time_s\n0,0,z,0.1,2\n", "line 2, column z_m is not a number: 'z'"),
        ("x_m,y_m,radius_m,time_s\n", "holds a header but no presses"),
        ("", "is empty"),
    ],
)
def test_read_presses_refuses_bad_files_naming_the_file_and_line(tmp_path, text, message):
    path = tmp_path / "presses.csv"
    path.write_text(text)
    with pytest.raises(ValueError, match=message) as raised:
        de.io.read_presses(path)
    assert str(path) in str(raised.value)


def test_read_presses_refuses_text_that_is_not_utf8_and_a_missing_file(tmp_path):
    path = tmp_path / "presses.csv"
    path.write_bytes(b"x_m,y_m,radius_m,time_s\n\xff\xfe,0,0.1,1\n")
    with pytest.raises(ValueError, match="line 2 is not UTF-8"):
        de.io.read_presses(path)
    with pytest.raises(FileNotFoundError, match="no such presses file"):
        de.io.read_presses(tmp_path / "missing.csv")


def test_calibrate_reports_bad_presses_in_one_line(session, tmp_path, capsys):
    path, _, _ = session
    presses = tmp_path / "bad.csv"
    presses.write_text("x_m,y_m,radius_m\n0,0,0.1\n")
    assert main(["calibrate", str(path), "--presses", str(presses), "-o", str(tmp_path / "skin.cal.h5")]) == 2
    error = capsys.readouterr().err
    assert error.startswith("diffeit calibrate: error:") and "lacks column(s) time_s" in error
    assert not (tmp_path / "skin.cal.h5").exists()
