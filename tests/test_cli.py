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
    printed = capsys.readouterr().out
    assert "3 frames" in printed and "wrote" in printed
    assert "correlation 1.000" in printed and "calibrated differences" in printed
    strip = matplotlib.image.imread(tmp_path / "out.png")
    assert strip.shape[1] > 3 * strip.shape[0] / 2  # three panels side by side
    out = read_frames(tmp_path / "out.h5")
    mesh = out.mesh
    assert mesh.n_elements == de.mesh.disc(16, electrode_width=0.2, h=0.15).n_elements  # built from the geometry
    assert out.images.shape == (3, mesh.n_elements) and out.image_quantity == "conductivity change"  # volts
    np.testing.assert_array_equal(out.frames, simulated.frames)
    np.testing.assert_array_equal(out.reference, simulated.reference)
    metadata = out.provenance["metadata"]
    assert metadata["input"] == str(frames) and metadata["method"] == "one_step" and metadata["prior"] == "noser"
    # The defaults of diffeit.reconstruct: calibrated to the reference, the hyperparameter chosen from the frames.
    assert metadata["calibrated"] and metadata["difference"] == "calibrated"
    assert metadata["calibration"]["correlation"] > 0.999 and metadata["calibration"]["misfit"] < 1e-6
    assert metadata["calibration"]["orientation"] == "as recorded"
    assert metadata["calibration"]["conductivity"] == pytest.approx(BACKGROUND)
    assert metadata["hyperparameter_choice"]["method"] in ("lcurve", "noise_figure")
    assert f"hyperparameter {metadata['hyperparameter']:.3g} (auto: " in printed
    assert metadata["results"] == ["successful"] * 3 and metadata["frames_failed"] == 0  # every frame's code
    for image, touch in zip(out.images, TOUCHES, strict=True):
        assert image[np.argmax(np.abs(image))] < 0  # a touch lowers the conductivity
        error = np.linalg.norm(_centroid(mesh, image) - touch)
        assert error < 0.1, f"touch at {touch} imaged {error:.3f} m away"  # half the touch radius
    peak = out.images.flat[np.argmax(np.abs(out.images))]
    assert f"conductivity change: peak {peak:.3e} S/sq" in printed


def test_options_reach_reconstruct(tmp_path, simulated, capsys):
    frames = write_frames(tmp_path / "touches.h5", simulated)
    arguments = ["reconstruct", str(frames), "-o", str(tmp_path / "out"), "--hyperparameter", "0.3"]
    arguments += ["--no-calibrate", "--difference", "normalised", "--prior", "laplace", "--h", "0.2"]
    arguments += ["--contact-impedance", "0.02", "--driven-readings", "drop"]
    assert main(arguments) == 0
    assert "hyperparameter 0.3 (given)" in capsys.readouterr().out
    out = read_frames(tmp_path / "out.h5")
    metadata = out.provenance["metadata"]
    assert metadata["hyperparameter"] == 0.3 and metadata["hyperparameter_choice"] == {"rule": "given"}
    assert not metadata["calibrated"] and metadata["difference"] == "normalised" and metadata["prior"] == "laplace"
    assert metadata["contact_impedance"] == 0.02 and metadata["background"] == 1.0
    assert out.mesh.n_elements == de.mesh.disc(16, electrode_width=0.2, h=0.2).n_elements  # the geometry at --h
    arguments = ["reconstruct", str(frames), "-o", str(tmp_path / "mapped"), "--background-map", "--h", "0.2"]
    assert main(arguments) == 0
    summary = read_frames(tmp_path / "mapped.h5").provenance["metadata"]["background_map"]
    assert 0 <= summary["misfit"] < 0.05 and summary["range"][0] <= summary["range"][1]


def test_frames_that_did_not_converge_are_written_named_and_exit_1(tmp_path, simulated, capsys):
    """Gauss-Newton capped at one step converges on no touch: the files are written with every
    frame's code, stderr counts and names the frames, the exit status is 1."""
    frames = write_frames(tmp_path / "touches.h5", simulated)
    arguments = ["reconstruct", str(frames), "-o", str(tmp_path / "capped"), "--method", "gauss_newton"]
    arguments += ["--max-iterations", "1", "--hyperparameter", "0.2", "--h", "0.2"]
    assert main(arguments) == 1
    captured = capsys.readouterr()
    assert "3 of 3 frames failed: [0, 1, 2] max_iterations_reached (the iteration limit was reached" in captured.err
    assert "their codes in capped.h5" in captured.err and "wrote" in captured.out
    out = read_frames(tmp_path / "capped.h5")
    metadata = out.provenance["metadata"]
    assert metadata["results"] == ["max_iterations_reached"] * 3 and metadata["frames_failed"] == 3
    assert metadata["max_iterations"] == 1 and out.images.shape == (3, out.mesh.n_elements)
    assert (tmp_path / "capped.png").exists()
    # GCV on noise-free differences ends at its smallest candidate: a note, not a failure.
    arguments = ["reconstruct", str(frames), "-o", str(tmp_path / "gcv"), "--hyperparameter", "gcv", "--h", "0.2"]
    arguments += ["--no-calibrate"]  # a model refined to the reference reads the coarser mesh's error as noise
    assert main(arguments) == 0
    assert "that gcv chose is at an end of its candidates" in capsys.readouterr().err
    choice = read_frames(tmp_path / "gcv.h5").provenance["metadata"]["hyperparameter_choice"]
    assert choice["gcv"]["result"] == "selection_at_boundary"
    # An iteration limit for a direct method is a bad option.
    assert main(["reconstruct", str(frames), "-o", str(tmp_path / "x"), "--max-iterations", "5"]) == 2
    assert "max_iterations applies to gauss_newton and total_variation" in capsys.readouterr().err


def test_reference_frame_option_and_a_file_without_reference(tmp_path, simulated, capsys):
    without = write_frames(tmp_path / "plain.h5", Recording(**{**_fields(simulated), "reference": None}))
    assert main(["reconstruct", str(without), "-o", str(tmp_path / "a")]) == 0
    # Without a reference, the first frames up to the first the model calibrated on them sees
    # touched (too few to test by their own noise): here the first alone, the next a touch elsewhere.
    metadata = read_frames(tmp_path / "a.h5").provenance["metadata"]
    expected = "mean of the first 3 frames: the first 1 of them, the model sees a touch in the next"
    assert metadata["reference"] == expected
    np.testing.assert_allclose(read_frames(tmp_path / "a.h5").reference, simulated.frames[0])
    assert main(["reconstruct", str(without), "-o", str(tmp_path / "b"), "--reference-frame", "0"]) == 0
    out = read_frames(tmp_path / "b.h5")
    assert out.provenance["metadata"]["reference"] == "frame 0"
    np.testing.assert_array_equal(out.images[0], 0.0)  # frame 0 against itself
    assert np.abs(out.images[1]).max() > 0


def _fields(recording: Recording) -> dict:
    names = ("frames", "times", "protocol", "reference", "mesh", "geometry", "provenance")
    return {name: getattr(recording, name) for name in names}


def test_bad_inputs_exit_with_a_clear_message(tmp_path, simulated, capsys):
    text = tmp_path / "notes.h5"
    text.write_text("not a frames file")
    assert main(["reconstruct", str(text), "-o", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("diffeit reconstruct: error:")
    assert f"{text} is not a diffeit frames file: it is not HDF5" in err
    assert main(["reconstruct", str(tmp_path / "missing.h5"), "-o", str(tmp_path / "x")]) == 2
    assert "no such diffeit frames file" in capsys.readouterr().err
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
    message = "--hyperparameter must be a number or auto or gcv or lcurve or noise_figure; got 'large'"
    assert message in capsys.readouterr().err
    assert main(["reconstruct", str(frames), "-o", str(tmp_path / "z"), "--hyperparameter", "-1"]) == 2
    assert "hyperparameter must be finite and positive" in capsys.readouterr().err
    assert main(["reconstruct", str(frames), "-o", str(tmp_path / "z"), "--reference-frame", "7"]) == 2
    assert capsys.readouterr().err.startswith("diffeit reconstruct: error:")
    assert not (tmp_path / "z.png").exists() and not (tmp_path / "z.h5").exists()


def test_reconstruct_an_eidors_mat_file_with_the_defaults(tmp_path, capsys):
    arguments = ["reconstruct", str(MONTREAL), "-o", str(tmp_path / "rod.png"), "--variable", "zc_demo3"]
    arguments += ["--reference-variable", "zc_h_demo3", "--h", "0.15", "--frame-rate", "7"]
    assert main(arguments) == 0
    printed = capsys.readouterr().out
    # The Montreal reference does not look like the model's (gains per channel): the user is told.
    assert "warning: the model does not reproduce the reference (correlation -0.48" in printed
    assert "correlation -0.478" in printed.split("calibration:")[1] and "normalised differences" in printed
    out = read_frames(tmp_path / "rod.h5")
    assert out.images.shape == (99, out.mesh.n_elements) and out.voltage_unit == "arbitrary"
    assert out.mesh.n_elements == de.mesh.disc(16, electrode_width=np.pi / 16, h=0.15).n_elements  # default disc
    assert out.image_quantity == "relative conductivity change" and out.readings == "magnitude"
    assert out.times[-1] == pytest.approx(98 / 7)
    peak = out.images.flat[np.argmax(np.abs(out.images))]
    assert f"relative conductivity change: peak {peak:.3e}\n" in printed
    # The rod is non-conductive: every frame's strongest change is a decrease.
    assert np.all(out.images.min(axis=1) < -out.images.max(axis=1))
    metadata = out.provenance["metadata"]
    assert metadata["hyperparameter_choice"]["method"] in ("lcurve", "noise_figure")
    assert metadata["difference"] == "normalised" and metadata["input"] == str(MONTREAL)
    assert metadata["variable"] == "zc_demo3" and metadata["reference_variable"] == "zc_h_demo3"
    assert metadata["calibration"]["correlation"] == pytest.approx(-0.48, abs=0.01)
    assert any("does not reproduce the reference" in note for note in metadata["warnings"])
    assert metadata["calibration"]["warnings"]  # the calibration's own record
