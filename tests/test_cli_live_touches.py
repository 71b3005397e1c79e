"""`diffeit live --calibration SKIN.cal.h5 --touches` against the emulator's pty: images at the
calibration's model, and each frame's touches printed through its position map."""

import dataclasses
import re

import jax.numpy as jnp
import numpy as np
import pytest

import diffeit as de
import hw
from diffeit.cli import main
from diffeit.readout import Readout

PROTOCOL = de.protocol.adjacent(16)
# Where the live stream presses (the labels' frame is the mesh's here), and the press's size.
PLACES = np.array([[0.35, 0.2], [-0.3, -0.35]])
RADIUS, DROP = 0.15, 0.3


@pytest.fixture(scope="module")
def skin(tmp_path_factory):
    """A small calibration session of one board (tests/test_cli_calibrate.py's, smaller): drive
    and channel gains up to 25%, contact impedances spread 3x, 0.1% noise; 10 untouched frames,
    then 12 labelled presses; calibrated with `de.calibrate` and saved. Returns the path and a
    function giving the board's noisy frames of a conductivity (E,) or (T, E)."""
    rng = np.random.default_rng(7)
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.1)
    truth = de.ForwardModel(mesh, PROTOCOL, contact_impedance=0.01 * np.exp(rng.uniform(-0.55, 0.55, 16)))
    gains = (
        np.exp(rng.uniform(-0.25, 0.25, 16))[PROTOCOL.drive_index]
        * np.exp(rng.uniform(-0.25, 0.25, 16))[PROTOCOL.pattern_index]
    )
    readout = Readout(PROTOCOL, gains=gains)

    def clean(sigma):
        return 1e3 * np.asarray(readout.readings(PROTOCOL, truth.potentials(jnp.asarray(sigma)).electrode))

    reference = clean(np.ones(mesh.n_elements))
    noise = 1e-3 * np.sqrt(np.mean(reference**2))

    def board(sigmas, seed):
        noisy = np.random.default_rng(seed)
        return np.array([clean(sigma) + noise * noisy.standard_normal(len(reference)) for sigma in sigmas])

    def pressed(centre):
        return 1 - DROP * de.mesh.disc_fraction(mesh, tuple(centre), RADIUS)

    angles = rng.uniform(0, 2 * np.pi, 12)
    radii = 0.6 * np.sqrt(rng.uniform(0, 1, 12))
    centres = np.stack([radii * np.cos(angles), radii * np.sin(angles)], axis=1)
    sigmas = [np.ones(mesh.n_elements)] * 10 + [pressed(c) for c in centres]
    times = 0.1 * np.arange(len(sigmas))
    recording = de.io.Recording(
        frames=board(sigmas, 1), times=times, protocol=PROTOCOL, mesh=mesh, voltage_unit="arbitrary"
    )
    presses = de.io.Presses(centres, RADIUS, times[10:])
    calibration = de.calibrate(recording, presses)
    assert calibration.position_map is not None and calibration.noise is not None
    path = calibration.save(tmp_path_factory.mktemp("skin") / "skin.cal.h5")
    return path, board, pressed, mesh


def _live(port, *options):
    return main(["live", "--port", port, "--protocol", "adjacent", "--batch", "4", *options])


def test_live_prints_the_touches_at_the_calibrations_model(skin, tmp_path, capsys):
    path, board, pressed, mesh = skin
    untouched = np.ones(mesh.n_elements)
    # The reference frame, then: untouched, a press at each place (held 3 frames), untouched. One reference
    # frame (the default): the voltage test must take its noise into the differences to pass untouched frames.
    sigmas = [untouched] * 3 + [pressed(PLACES[0])] * 3 + [pressed(PLACES[1])] * 3 + [untouched]
    emulator = hw.Emulator(board(sigmas, 2), frame_rate=100.0).start()
    png = tmp_path / "live.png"
    status = _live(emulator.port, "--frames", "10", "--calibration", str(path), "--touches", "--png", str(png))
    emulator.stop()
    assert status == 0
    printed = capsys.readouterr().out
    assert "imaging at the calibration's model" in printed and "(the calibration's)" in printed
    assert "calibrated to the reference" not in printed  # its own reference calibration is skipped
    assert "done: 9 frames reconstructed" in printed and png.exists()
    lines = {int(m[1]): m[2] for m in re.finditer(r"^frame (\d+) \(t = [\d.]+ s\): (.*)$", printed, re.M)}
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
