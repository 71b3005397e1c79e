"""`diffeit simulate`: a scene file to a frames file, which `diffeit reconstruct` then images."""

import numpy as np
import pytest

import diffeit as de
from diffeit.cli import main

SCENE = """
name = "cli touch"
frame_rate = 4.0
duration = 1.0
[skin]
h = 0.25
[background]
conductivity = "0.01 S/sq"
[[touches]]
centre = [0.4, 0.0]
radius = 0.3
amplitude = -0.4
envelope = { kind = "press", start = 0.5, hold = 1.0 }
[effects.noise]
level = "low"
"""


@pytest.mark.slow
def test_simulate_then_reconstruct(tmp_path, capsys):
    scene = tmp_path / "scene.toml"
    scene.write_text(SCENE)
    frames = tmp_path / "frames.h5"
    assert main(["simulate", str(scene), "-o", str(frames), "--plot", str(tmp_path / "truth.png")]) == 0
    out = capsys.readouterr().out
    assert "4 frames at 4 Hz" in out and "2 forward solves" in out
    assert (tmp_path / "truth.png").stat().st_size > 10_000
    simulation = de.scene.read_simulation(frames)
    assert simulation.scene.name == "cli touch" and simulation.frames.shape == (4, 208)

    assert main(["reconstruct", str(frames), "-o", str(tmp_path / "images"), "--prior", "laplace"]) == 0
    images = de.io.read_frames(tmp_path / "images.h5")
    # Reconstructed on the coarse mesh of the scene's skin, with its background of 0.01 S/sq.
    assert images.mesh.n_elements == simulation.scene.reconstruction_mesh().n_elements < simulation.mesh.n_elements
    metadata = images.provenance["metadata"]
    assert metadata["background"] == 0.01 and metadata["input"] == str(frames)
    assert metadata["calibration"]["correlation"] > 0.99 and metadata["difference"] == "calibrated"
    # The scene's level, to the coarser mesh's error: the refinement trades the level with the
    # contacts and the source's mixing weight (measured 0.0094; the level alone 0.0096).
    assert metadata["calibration"]["conductivity"] == pytest.approx(0.01, rel=0.08)
    assert images.image_quantity == "conductivity change"
    pressed = images.images[3]
    peak = pressed[np.argmax(np.abs(pressed))]
    assert -0.01 < peak < -0.001  # a conductivity drop of the order of 0.4 x 0.01 S/sq
    assert de.metrics.position_error(images.mesh, pressed, (0.4, 0.0)) < 0.15


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (SCENE.replace('"0.01 S/sq"', '"0.01 m"'), "background.conductivity"),
        (SCENE + "[effects.vibration]\n", "effects.vibration"),
    ],
)
def test_simulate_names_bad_fields(tmp_path, capsys, text, message):
    scene = tmp_path / "scene.toml"
    scene.write_text(text)
    assert main(["simulate", str(scene), "-o", str(tmp_path / "frames.h5")]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "frames.h5").exists()


def test_simulate_refuses_to_overwrite(tmp_path, capsys):
    (tmp_path / "frames.h5").write_bytes(b"recorded")
    assert main(["simulate", "single_touch", "-o", str(tmp_path / "frames.h5")]) == 2
    assert "exists" in capsys.readouterr().err
    assert (tmp_path / "frames.h5").read_bytes() == b"recorded"
