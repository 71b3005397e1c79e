"""`diffeit live --calibration SKIN.cal.h5 --touches` against the emulator's pty: images at the
calibration's model, and each frame's touches printed through its position map."""

import dataclasses
import re

import jax.numpy as jnp
import numpy as np
import pytest
from skin_sessions import calibrated_session

import diffeit as de
import hw
from diffeit.cli import main

# Where the live stream presses (the labels' frame is the mesh's here).
PLACES = np.array([[0.35, 0.2], [-0.3, -0.35]])


@pytest.fixture(scope="module")
def skin(tmp_path_factory):
    """A calibration session of one board (tests/skin_sessions.py's `calibrated_session`, shared
    with tests/test_cli_calibrate.py: one calibration per test process): drive and channel gains
    up to 25%, contact impedances spread 3x, 0.1% noise; 10 untouched frames, then 30 labelled
    presses; calibrated by `diffeit calibrate`. Returns the calibration file's path, a function
    giving the board's noisy frames of conductivities (T of (E,)) and a seed, one giving the
    conductivity (E,) under a press at a centre, and the mesh."""
    shared = calibrated_session(tmp_path_factory)
    assert shared.status == 0
    calibration = de.calibration.load(shared.calibration)
    assert calibration.position_map is not None and calibration.noise is not None
    return shared.calibration, shared.skin.frames, shared.skin.pressed, shared.skin.mesh


def _live(port, *options):
    return main(["live", "--port", port, "--protocol", "adjacent", "--batch", "4", *options])


def _streamed(frames, capsys, *options):
    """`live` (`options`) on `frames` streamed by the emulator, which must end well: what it
    printed, and each frame imaged's line (frame index -> the text after its time)."""
    emulator = hw.Emulator(frames, frame_rate=100.0).start()
    status = _live(emulator.port, *options)
    emulator.stop()
    assert status == 0
    printed = capsys.readouterr().out
    return printed, {int(m[1]): m[2] for m in re.finditer(r"^frame (\d+) \(t = [\d.]+ s\): (.*)$", printed, re.M)}


def test_live_prints_the_touches_at_the_calibrations_model(skin, tmp_path, capsys):
    path, board, pressed, mesh = skin
    untouched = np.ones(mesh.n_elements)
    # The reference frame, then: untouched, a press at each place (held 3 frames), untouched. One reference
    # frame (the default): the voltage test must take its noise into the differences to pass untouched frames.
    sigmas = [untouched] * 3 + [pressed(PLACES[0])] * 3 + [pressed(PLACES[1])] * 3 + [untouched]
    png = tmp_path / "live.png"
    printed, lines = _streamed(
        board(sigmas, 2), capsys, "--frames", "10", "--calibration", str(path), "--touches", "--png", str(png)
    )
    assert "imaging at the calibration's model" in printed and "(the calibration's)" in printed
    assert "calibrated to the reference" not in printed  # its own reference calibration is skipped
    assert "done: 9 frames reconstructed" in printed and png.exists()
    assert sorted(lines) == list(range(9))
    for frame in (0, 1, 8):  # untouched: the voltage test finds no touch
        assert lines[frame].endswith("no touch"), lines[frame]
    pattern = r"touch 0: \(([+-][\d.]+), ([+-][\d.]+)\) mm, radius ([\d.]+) mm, depth ([+-][\d.]+)"
    for frames, place in ((range(2, 5), PLACES[0]), (range(5, 8), PLACES[1])):
        for frame in frames:
            found = re.search(pattern, lines[frame])
            assert found, lines[frame]
            position = 1e-3 * np.array([float(found[1]), float(found[2])])
            assert np.linalg.norm(position - place) < 0.1, (lines[frame], place)
            assert float(found[3]) > 0 and float(found[4]) < 0  # a press lowers the conductivity
            assert "touch 1" not in lines[frame], lines[frame]  # one press, one touch: above the ringing alone


def test_live_says_a_reference_frame_that_looks_touched_against_the_calibrations(skin, tmp_path, capsys):
    """A stream begun with a finger on the skin: its reference frame stands out of the
    calibration's reference, and live says so; begun untouched, it says nothing."""
    path, board, pressed, mesh = skin
    untouched = np.ones(mesh.n_elements)
    options = ("--frames", "4", "--calibration", str(path), "--touches", "--png", str(tmp_path / "live.png"))
    for first, said in ((pressed(PLACES[0]), True), (untouched, False)):
        emulator = hw.Emulator(board([first, *[untouched] * 3], 5), frame_rate=100.0).start()
        status = _live(emulator.port, *options)
        emulator.stop()
        assert status == 0
        error = capsys.readouterr().err
        assert ("reference frame(s) [0] look touched against the calibration's reference" in error) is said, error


def test_live_does_not_read_a_frame_the_board_garbled(skin, tmp_path, capsys):
    """A frame of zeros in the middle of a press (a board's glitch), and one whose readings the
    stream moved one place along: said damaged and not read, as `diffeit.touches` does; the
    press's other frames read where it is, and the frame after the press no touch (the glitches
    are no rest anchor)."""
    path, board, pressed, mesh = skin
    untouched = np.ones(mesh.n_elements)
    sigmas = [untouched] * 2 + [pressed(PLACES[0])] * 5 + [untouched] * 2
    frames = board(sigmas, 5)
    frames[4] = 0.0
    frames[6] = np.roll(frames[6], 1)
    options = ("--frames", "9", "--calibration", str(path), "--touches", "--png", str(tmp_path / "l.png"))
    _, lines = _streamed(frames, capsys, *options)
    assert sorted(lines) == list(range(8))
    for frame in (3, 5):
        assert lines[frame].endswith("its readings are moved along): not read"), lines[frame]
    for frame in (1, 2, 4):
        found = re.search(r"touch 0: \(([+-][\d.]+), ([+-][\d.]+)\) mm", lines[frame])
        assert found, lines[frame]
        assert np.linalg.norm(1e-3 * np.array([float(found[1]), float(found[2])]) - PLACES[0]) < 0.1, lines[frame]
    assert lines[0].endswith("no touch") and lines[7].endswith("no touch"), (lines[0], lines[7])


@pytest.mark.parametrize("first", ["as read", "zeros"])
def test_live_follows_a_drifting_skin_with_enough_reference_frames(skin, tmp_path, capsys, first):
    """A stream whose readings grow 2% (20 times the board's noise) from its first frame to its
    last, 8 reference frames: the drift is taken out frame by frame, so the untouched frames
    after them read no touch and each press one touch where it was; the summary gives the
    gains taken out. (Against the fixed reference every one of those untouched frames read as
    touched.) A first frame of zeros (a board's glitch as it connects) is left out of the
    reference, and said so."""
    path, board, pressed, mesh = skin
    untouched = np.ones(mesh.n_elements)
    sigmas = [untouched] * 14 + [pressed(PLACES[0])] * 3 + [untouched] * 6 + [pressed(PLACES[1])] * 3 + [untouched] * 6
    frames = board(sigmas, 3) * (1 + 0.02 * np.linspace(0, 1, len(sigmas)))[:, None]
    if first == "zeros":
        frames[0] = 0.0
    options = ("--frames", str(len(sigmas)), "--reference-frames", "8", "--calibration", str(path), "--touches")
    printed, lines = _streamed(frames, capsys, *options, "--png", str(tmp_path / "live.png"))
    assert sorted(lines) == list(range(len(sigmas) - 8))
    for frame in (*range(6), *range(9, 15), *range(18, 24)):
        assert lines[frame].endswith("no touch"), (frame, lines[frame])
    pattern = r"touch 0: \(([+-][\d.]+), ([+-][\d.]+)\) mm"
    for frames_pressed, place in ((range(6, 9), PLACES[0]), (range(15, 18), PLACES[1])):
        for frame in frames_pressed:
            found = re.search(pattern, lines[frame])
            assert found and "touch 1" not in lines[frame], lines[frame]
            assert np.linalg.norm(1e-3 * np.array([float(found[1]), float(found[2])]) - place) < 0.1, lines[frame]
    assert ("reference frame(s) [0] left out" in printed) == (first == "zeros")
    gains = re.search(r"the common gain drifted, taken out: ([\d.]+) to ([\d.]+)$", printed, re.M)
    # Against the reference (the mean of the first 8 frames, its gain 1 + 0.02 * 3.5 / 31, or of
    # frames 1 to 7, 1 + 0.02 * 4 / 31): the first imaged frame's gain, and the last's.
    drift = (1 + 0.02 * np.array([8, 31]) / 31) / (1 + 0.02 * (3.5 if first == "as read" else 4.0) / 31)
    assert gains, printed[-300:]
    np.testing.assert_allclose([float(gains[1]), float(gains[2])], drift, atol=5e-4)


def test_live_refuses_a_calibration_for_another_protocol_or_readings(skin, tmp_path, capsys):
    path = skin[0]
    # Binary frames of the full 16 x 16 layout: the stream's protocol, known at its first frame, is not the
    # calibration's.
    full = de.protocol.adjacent(16, measure_driven=True)
    emulator = hw.Emulator(np.ones((3, full.n_measurements)), frame_rate=100.0, layout=hw.LAYOUT_ADJACENT_FULL)
    emulator.start()
    status = main(["live", "--port", emulator.port, "--calibration", str(path), "--png", str(tmp_path / "a.png")])
    emulator.stop()
    assert status == 2
    err = capsys.readouterr().err
    assert "diffeit live: error: the calibration is for another protocol than the frames' (16 electrodes and 208" in err
    # Declared on the command line: refused before the device is opened.
    assert main(["live", "--port", "/dev/null", "--protocol", "opposite", "--calibration", str(path)]) == 2
    assert "diffeit live: error: the calibration is for another protocol" in capsys.readouterr().err
    # A calibration of magnitudes: a device streams signed readings.
    magnitudes = dataclasses.replace(de.calibration.load(path), readings="magnitude")
    other = magnitudes.save(tmp_path / "magnitudes.cal.h5")
    assert main(["live", "--port", "/dev/null", "--text", "--calibration", str(other)]) == 2
    assert "the calibration is for magnitude readings; the device's frames are signed" in capsys.readouterr().err
    # Options the calibration's model replaces, and --memory, are refused too.
    assert main(["live", "--port", "/dev/null", "--calibration", str(path), "--h", "0.1"]) == 2
    assert "brings its model (mesh, level, contact impedances): give no --h" in capsys.readouterr().err
    assert main(["live", "--port", "/dev/null", "--calibration", str(path), "--memory", "fit.h5"]) == 2
    assert "--calibration and --memory each bring a model" in capsys.readouterr().err


def test_live_without_a_calibration_reads_one_touch_a_press_against_its_reference_frames(tmp_path, capsys):
    """Without a calibration, 8 reference frames give the readings' noise: untouched frames read
    no touch, and a press one touch where it was (the hills found on the image divided by its
    noise, as `diffeit.touches` finds them). A skin of its own: a unit disc at 0.1% noise."""
    model = de.ForwardModel(de.mesh.disc(16, electrode_width=0.2, h=0.06), de.protocol.adjacent(16), 0.01)
    mesh = model.mesh
    untouched = np.ones(mesh.n_elements)
    pressed = 1 - 0.3 * np.asarray(de.mesh.disc_fraction(mesh, tuple(PLACES[0]), 0.15))
    clean = [np.asarray(model.measure(jnp.asarray(sigma))) for sigma in (untouched, pressed)]
    frames = np.array([clean[0]] * 11 + [clean[1]] * 3 + [clean[0]] * 3)
    frames = frames + 1e-3 * np.sqrt(np.mean(clean[0] ** 2)) * np.random.default_rng(5).standard_normal(frames.shape)
    options = ("--frames", str(len(frames)), "--reference-frames", "8", "--touches", "--png", str(tmp_path / "l.png"))
    _, lines = _streamed(frames, capsys, *options)
    assert sorted(lines) == list(range(9))
    for frame in (0, 1, 2, 6, 7, 8):
        assert lines[frame].endswith("no touch"), (frame, lines[frame])
    for frame in (3, 4, 5):
        found = re.search(r"touch 0: \(([+-][\d.]+), ([+-][\d.]+)\) mm", lines[frame])
        assert found and "touch 1" not in lines[frame], lines[frame]
        assert np.linalg.norm(1e-3 * np.array([float(found[1]), float(found[2])]) - PLACES[0]) < 0.1, lines[frame]


def test_live_reads_a_skin_that_keeps_part_of_each_press_against_the_rest_before_each(skin, tmp_path, capsys):
    """Each press (held 3 frames) leaves 0.4 of its change for good, then 4 frames at rest: live
    carries the rest anchors from batch to batch (`diffeit.touch.LiveTouches`), so each press
    reads one touch where it was, against the rest before it, and a frame at rest at most what
    the last press left, said so. (Against the reference frame, 9 of the 15 pressed frames read
    a second touch: the earlier presses' remains.)"""
    path, board, pressed, mesh = skin
    places = np.array([[0.35, 0.2], [-0.3, -0.35], [0.0, 0.45], [-0.4, 0.1], [0.3, -0.3]])
    rest = np.ones(mesh.n_elements)
    sigmas, held = [rest] * 4, []
    for place in places:
        press = pressed(place)
        held.append(range(len(sigmas) - 1, len(sigmas) + 2))  # printed frames count from the second
        sigmas += [rest * press] * 3
        rest = rest * (1 - 0.4 * (1 - press))
        sigmas += [rest] * 4
    options = ("--frames", str(len(sigmas)), "--calibration", str(path), "--touches", "--png", str(tmp_path / "l.png"))
    printed, lines = _streamed(board(sigmas, 4), capsys, *options)
    assert sorted(lines) == list(range(len(sigmas) - 1))
    pattern = r"touch 0: \(([+-][\d.]+), ([+-][\d.]+)\) mm"
    for frames, place in zip(held, places, strict=True):
        for frame in frames:
            found = re.search(pattern, lines[frame])
            assert found, (frame, lines[frame])
            assert np.linalg.norm(1e-3 * np.array([float(found[1]), float(found[2])]) - place) < 0.1, lines[frame]
    # A hill at the rim beside a press, now and then, reads as a second touch (measured: 1 of 15),
    # on the skin: the position map holds what it maps to the skin's outline (it had put one at
    # (930, -785) mm on this unit disc).
    assert sum("touch 1" in lines[frame] for frames in held for frame in frames) <= 2
    every = re.findall(r"touch \d: \(([+-][\d.]+), ([+-][\d.]+)\) mm", printed)
    assert np.max(np.linalg.norm(np.array(every, float), axis=1)) < 1050.0, every
    # At rest, a touch read is what the last press left, where it was, and says so (measured:
    # all 20 frames at rest said so, 14 with a touch).
    flagged = 0
    for frames, place in zip(held, places, strict=True):
        for frame in range(frames[-1] + 1, frames[-1] + 5):
            flagged += lines[frame].endswith("(likely what the last touch left)")
            found = re.search(pattern, lines[frame])
            if found:
                assert lines[frame].endswith("(likely what the last touch left)"), lines[frame]
                assert np.linalg.norm(1e-3 * np.array([float(found[1]), float(found[2])]) - place) < 0.1, lines[frame]
    assert flagged >= 15, flagged


def test_live_holds_the_readings_of_an_electrode_that_comes_off(skin, tmp_path, capsys):
    """Electrode 5 comes off half way through a stream (the readings on it read zero, those of
    the drives through it saturate at ten times the largest reading): live warns of it at the
    third frame it is off in, holds the readings on it from its first, images from the others
    alone from then on, and the frames after read as before: untouched ones no touch, each press
    one touch where it was. (Unheld, every frame after it was taken for a board's glitch and not
    read; held but imaged from every reading, each press read a second touch by electrode 5.)"""
    path, board, pressed, mesh = skin
    protocol = de.protocol.adjacent(16)  # the stream's (the calibration's folds its readout's mixing in)
    untouched = np.ones(mesh.n_elements)
    a, b = pressed(PLACES[0]), pressed(PLACES[1])
    sigmas = [untouched] * 10 + [a] * 3 + [untouched] * 5 + [b] * 3 + [untouched] * 2 + [a] * 3 + [untouched] * 2
    frames = board(sigmas, 6)
    through = protocol.drive[protocol.drive_index, 5] != 0
    off = 15  # from the third untouched frame after the first press (printed frame 7)
    frames[off:, (protocol.measure[:, 5] != 0) | through] = 0.0
    frames[off:, through] = 10 * np.abs(frames).max()
    options = ("--frames", str(len(sigmas)), "--reference-frames", "8", "--calibration", str(path), "--touches")
    printed, lines = _streamed(frames, capsys, *options, "--png", str(tmp_path / "live.png"))
    assert sorted(lines) == list(range(len(sigmas) - 8))
    assert re.search(r"^warning: electrode\(s\) \[5\] lost, off from frame\(s\) \[7\]", printed, re.M), printed[-2000:]
    assert all(lines[frame].endswith("(electrode(s) [5] off: the readings on them held)") for frame in range(7, 20))
    assert not any("off:" in lines[frame] for frame in range(7))
    pattern = r"touch 0: \(([+-][\d.]+), ([+-][\d.]+)\) mm"
    for frame in (0, 1, 5, 6, 7, 8, 9, 13, 14, 18, 19):
        assert re.search(r"no touch( \(electrode.*held\))?$", lines[frame]), (frame, lines[frame])
    for pressed_frames, place in ((range(2, 5), PLACES[0]), (range(10, 13), PLACES[1]), (range(15, 18), PLACES[0])):
        for frame in pressed_frames:
            found = re.search(pattern, lines[frame])
            assert found and "touch 1" not in lines[frame], (frame, lines[frame])
            assert np.linalg.norm(1e-3 * np.array([float(found[1]), float(found[2])]) - place) < 0.1, lines[frame]
    assert "readings held on electrodes off in 13 frames (electrode(s) [5] lost, off from frame(s) [7])" in printed
