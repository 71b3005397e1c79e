"""`diffeit acquire`, `diffeit live` and `diffeit emulate` against the emulator's pty."""

import json
import threading
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest

import diffeit as de
import hw
from diffeit.cli import main
from diffeit.cli._hardware import _LiveViewer
from diffeit.cli._model import ModelSettings
from diffeit.io import read_frames
from diffeit.protocol import adjacent

SCENE = Path(de.__file__).parent / "scene" / "examples" / "single_touch.toml"


@pytest.fixture(scope="module")
def touch() -> np.ndarray:
    """Frames of a simulated press, the reference first (volts)."""
    simulation = de.simulate(de.Scene.from_toml(SCENE), progress=False)
    return np.concatenate([np.asarray(simulation.reference)[None], np.asarray(simulation.frames)])


def test_acquire_records_what_arrives_and_reports_the_drops(tmp_path, touch, capsys):
    frames = np.tile(touch, (4, 1))  # 104 frames
    faults = hw.FaultRates(bit_flip=0.05, truncated=0.05, seed=2)
    emulator = hw.Emulator(frames, frame_rate=200.0, faults=faults).start()
    output = tmp_path / "run.h5"
    status = main(["acquire", "--port", emulator.port, "-o", str(output), "--reconnect-timeout", "0.3"])
    assert status == 0 and emulator.wait(5)
    recording = read_frames(output)
    lost = set(emulator.lost_frames)
    kept = [i for i in range(len(frames)) if i not in lost]
    assert len(lost) > 0 and recording.n_frames == len(kept)
    np.testing.assert_array_equal(recording.frames, frames[kept].astype(np.float32))
    np.testing.assert_array_equal(recording.protocol.measure, adjacent(16).measure)
    statistics = recording.provenance["metadata"]["drop_statistics"]
    assert statistics["frames"] == len(kept)
    assert statistics["missing_frames"] == kept[-1] - kept[0] + 1 - len(kept)  # gaps between arrived frames
    report = capsys.readouterr().out
    assert f"{len(kept)} frames recorded in {output}" in report and "did not come back" in report
    assert main(["acquire", "--port", emulator.port, "-o", str(output)]) == 2  # never overwrites unasked
    assert "exists; pass --overwrite" in capsys.readouterr().err


def test_acquire_counts_what_it_recorded_and_checks_the_folder_first(tmp_path, touch, capsys):
    """--frames 5 from a fast device: the report and the stored statistics count the 5 frames
    recorded, not frames parsed beyond them; a missing folder is refused before reading."""
    emulator = hw.Emulator(touch, frame_rate=1e5).start()
    output = tmp_path / "five.h5"
    assert main(["acquire", "--port", emulator.port, "-o", str(output), "--frames", "5"]) == 0
    emulator.stop()
    assert read_frames(output).n_frames == 5
    assert read_frames(output).provenance["metadata"]["drop_statistics"]["frames"] == 5
    assert "5 frames recorded" in capsys.readouterr().out
    status = main(["acquire", "--port", "/dev/null", "-o", str(tmp_path / "no" / "run.h5")])
    assert status == 2 and f"the folder {tmp_path / 'no'} does not exist" in capsys.readouterr().err


def test_live_reconstructs_batches_and_saves_a_png_without_display(tmp_path, touch, capsys):
    emulator = hw.Emulator(touch, frame_rate=100.0, text=True, label="v").start()
    png = tmp_path / "live.png"
    status = main(
        ["live", "--port", emulator.port, "--text", "--protocol", "adjacent", "--frames", "21", "--batch", "5",
         "--h", "0.15", "--png", str(png)]
    )  # fmt: skip
    emulator.stop()
    assert status == 0
    assert "20 frames reconstructed, 0 rejected; the latest image is in" in capsys.readouterr().out
    image = matplotlib.image.imread(png)
    assert image.shape[2] == 4 and np.ptp(image[..., :3]) > 0.5  # a coloured image, not a blank canvas


def test_live_images_the_calibrated_relative_change(tmp_path, touch, capsys):
    """The viewer calibrates the model to the reference frame (the scene's 0.01 S/sq skin in
    volts) and shows dsigma/sigma: the press as a drop of tens of percent, the untouched skin
    near zero, on a colour scale that does not follow the frame."""
    scene = de.Scene.from_toml(SCENE)
    settings = ModelSettings(h=0.15, hyperparameter="auto")
    viewer = _LiveViewer(adjacent(16), settings, str(tmp_path / "live.png"), touch[:2], colour_limit=0.4)
    report = capsys.readouterr().out
    assert "calibrated to the reference" in report and "orientation as recorded" in report
    assert viewer.calibration.correlation > 0.99
    assert viewer.calibration.conductivity == pytest.approx(scene.background.conductivity, rel=0.1)
    differences = viewer.calibration.signed(touch) - viewer.reference
    images = np.asarray(viewer.solver.solve(differences).value) / viewer.calibration.conductivity
    pressed = np.argmax(np.abs(images).max(axis=1))
    assert -1.0 < images[pressed].min() < -0.05  # a relative drop, not S/sq or volts
    # The untouched skin: only the reading noise (0.5%, against a reference of 2 frames).
    assert np.abs(images[0]).max() < 0.2 * np.abs(images[pressed]).max()
    assert viewer.show([hw.Frame(values=touch[pressed]), hw.Frame(values=touch[0])]) == 2
    collection = viewer.axes.collections[0]
    assert collection.get_clim() == (-0.4, 0.4)  # the stated, steady scale, whatever the frame holds
    assert "colour -0.4 to +0.4" in viewer.axes.get_title()


def test_live_counts_images_that_are_not_finite_and_exits_1(tmp_path, touch, capsys):
    """A frame of readings near the float64 limit overflows the one-step image: the run goes on,
    the image is not drawn, the PNG's title and stderr count it, and the exit status is 1."""
    frames = touch[:9].copy()
    frames[4] = 1e308  # imaged frame 3: the first frame is the reference
    emulator = hw.Emulator(frames, frame_rate=100.0, text=True, label="v").start()
    png = tmp_path / "live.png"
    status = main(
        ["live", "--port", emulator.port, "--text", "--protocol", "adjacent", "--frames", "9", "--batch", "4",
         "--h", "0.15", "--png", str(png)]
    )  # fmt: skip
    emulator.stop()
    assert status == 1
    captured = capsys.readouterr()
    assert "8 frames reconstructed" in captured.out
    assert "diffeit live: 1 of 8 images not finite, imaged frames [3]" in captured.err
    assert png.exists()
    settings = ModelSettings(h=0.15, hyperparameter="auto")
    viewer = _LiveViewer(adjacent(16), settings, str(tmp_path / "viewer.png"), touch[:1])
    assert viewer.show([hw.Frame(values=touch[1]), hw.Frame(values=frames[4])]) == 2
    assert viewer.nonfinite == [1] and not viewer.axes.collections  # the last image, not drawn
    assert "not finite: not drawn\n1 of 2 images not finite" in viewer.axes.get_title()


def test_emulate_streams_the_scene_reference_first(tmp_path, touch, capsys):
    port, log = tmp_path / "ttyEIT", tmp_path / "faults.json"
    arguments = ["emulate", str(SCENE), "--port", str(port), "--frame-rate", "100", "--wait", "30"]
    arguments += ["--faults", "stall=0.2", "--log", str(log)]
    thread = threading.Thread(target=main, args=(arguments,))
    thread.start()
    with hw.SerialSource(str(port), open_timeout=60, reconnect_timeout=0.3) as source:
        arrived = []
        with pytest.raises(hw.DeviceLost):
            arrived.extend(source.frames())
    thread.join()
    np.testing.assert_allclose([f.values for f in arrived], touch.astype(np.float32), rtol=1e-6)
    assert [f.counter for f in arrived] == list(range(len(touch)))
    stalls = json.loads(log.read_text())
    assert stalls and {fault["kind"] for fault in stalls} == {"stall"}
    assert f"done: {len(touch)} frames sent intact; stall {len(stalls)}" in capsys.readouterr().out
    assert main(["emulate", str(SCENE), "--faults", "flip=0.1"]) == 2
