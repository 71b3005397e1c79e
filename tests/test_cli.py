"""`diffeit reconstruct`: a frames file in, an image strip and an images file out."""

from pathlib import Path

import jax.numpy as jnp
import matplotlib.image
import numpy as np
import pytest

import diffeit as de
from diffeit.cli import main
from diffeit.io import Recording, read_frames, write_frames

MONTREAL = Path(__file__).parent / "data" / "montreal_data_1995.mat"
GEOMETRY = {"kind": "disc", "n_electrodes": 16, "electrode_width": 0.2, "h": 0.15}
BACKGROUND = 1.0  # S/sq
TOUCHES = [(0.5, 0.0), (0.0, 0.5), (-0.4, -0.3)]  # m: one touch per frame, radius 0.2, -30%


@pytest.fixture(scope="module")
def simulated() -> Recording:
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.15)
    model = de.ForwardModel(mesh, de.protocol.adjacent(16), contact_impedance=0.01)
    reference = model.measure(jnp.full(mesh.n_elements, BACKGROUND))
    frames = [model.measure(BACKGROUND * (1 - 0.3 * de.mesh.disc_fraction(mesh, c, 0.2))) for c in TOUCHES]
    return Recording(
        frames=np.asarray(frames),
        times=[0.0, 0.1, 0.2],
        protocol=model.protocol,
        reference=np.asarray(reference),
        geometry=GEOMETRY,
        provenance={"source": "tests/test_cli.py: three touches"},
    )


def _centroid(mesh: de.Mesh, image: np.ndarray) -> np.ndarray:
    chosen = de.metrics.half_amplitude_set(image)
    areas = mesh.element_areas[chosen]
    return areas @ mesh.element_centroids[chosen] / areas.sum()


def test_reconstruct_images_every_frame_of_a_frames_file(tmp_path, simulated, capsys):
    frames = write_frames(tmp_path / "touches.h5", simulated)
    assert main(["reconstruct", str(frames), "-o", str(tmp_path / "out"), "--background", "1.0"]) == 0
    assert "wrote" in capsys.readouterr().out
    strip = matplotlib.image.imread(tmp_path / "out.png")
    assert strip.shape[1] > 3 * strip.shape[0] / 2  # three panels side by side
    out = read_frames(tmp_path / "out.h5")
    mesh = out.mesh
    assert mesh.n_elements == de.mesh.disc(16, electrode_width=0.2, h=0.15).n_elements  # built from the geometry
    assert out.images.shape == (3, mesh.n_elements) and out.image_quantity == "conductivity change"
    np.testing.assert_array_equal(out.frames, simulated.frames)
    np.testing.assert_array_equal(out.reference, simulated.reference)
    assert out.provenance["metadata"]["hyperparameter"] == 0.1
    for image, touch in zip(out.images, TOUCHES, strict=True):
        assert image[np.argmax(np.abs(image))] < 0  # a touch lowers the conductivity
        error = np.linalg.norm(_centroid(mesh, image) - touch)
        assert error < 0.1, f"touch at {touch} imaged {error:.3f} m away"  # half the touch radius


def test_reference_frame_option_and_a_file_without_reference(tmp_path, simulated, capsys):
    without = write_frames(tmp_path / "plain.h5", Recording(**{**_fields(simulated), "reference": None}))
    assert main(["reconstruct", str(without), "-o", str(tmp_path / "a")]) == 2
    assert "has no reference frame; choose one with --reference-frame K" in capsys.readouterr().err
    assert main(["reconstruct", str(without), "-o", str(tmp_path / "b"), "--reference-frame", "0"]) == 0
    images = read_frames(tmp_path / "b.h5").images
    np.testing.assert_array_equal(images[0], 0.0)  # frame 0 against itself
    assert np.abs(images[1]).max() > 0


def _fields(recording: Recording) -> dict:
    names = ("frames", "times", "protocol", "reference", "mesh", "geometry", "provenance")
    return {name: getattr(recording, name) for name in names}


def test_bad_inputs_exit_with_a_clear_message(tmp_path, simulated, capsys):
    text = tmp_path / "notes.h5"
    text.write_text("not a frames file")
    assert main(["reconstruct", str(text), "-o", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("diffeit reconstruct: error:") and f"{text} is not a readable HDF5 file" in err
    assert main(["reconstruct", str(tmp_path / "missing.h5"), "-o", str(tmp_path / "x")]) == 2
    assert "no such frames file" in capsys.readouterr().err
    assert main(["reconstruct", str(MONTREAL), "-o", str(tmp_path / "x")]) == 2
    assert "name the frames with --variable" in capsys.readouterr().err
    frames = write_frames(tmp_path / "touches.h5", simulated)
    (tmp_path / "taken.png").write_bytes(b"a figure someone made")
    assert main(["reconstruct", str(frames), "-o", str(tmp_path / "taken")]) == 2
    assert "taken.png exists; pass --overwrite" in capsys.readouterr().err
    assert (tmp_path / "taken.png").read_bytes() == b"a figure someone made"
    assert main(["reconstruct", str(frames), "-o", str(tmp_path / "y"), "--prior", "magic"]) == 2
    assert "unknown prior 'magic'" in capsys.readouterr().err
    assert main(["reconstruct", str(frames), "-o", str(tmp_path / "z"), "--hyperparameter", "large"]) == 2
    assert "--hyperparameter must be a number or gcv or lcurve; got 'large'" in capsys.readouterr().err


@pytest.mark.slow
def test_reconstruct_an_eidors_mat_file(tmp_path):
    arguments = ["reconstruct", str(MONTREAL), "-o", str(tmp_path / "rod.png"), "--variable", "zc_demo3"]
    arguments += ["--reference-variable", "zc_h_demo3", "--difference", "relative", "--h", "0.15", "--frame-rate", "7"]
    arguments += ["--hyperparameter", "lcurve"]  # chosen from the data (about 1 here; 0.1 breaks the rod up)
    assert main(arguments) == 0
    out = read_frames(tmp_path / "rod.h5")
    assert out.images.shape == (99, out.mesh.n_elements) and out.voltage_unit == "arbitrary"
    assert out.times[-1] == pytest.approx(98 / 7)
    # The rod is non-conductive: every frame's strongest change is a decrease.
    assert np.all(out.images.min(axis=1) < -out.images.max(axis=1))
    metadata = out.provenance["metadata"]
    assert metadata["hyperparameter_choice"] == "lcurve" and 0.3 < metadata["hyperparameter"] < 3
