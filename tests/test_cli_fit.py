"""`diffeit fit`: the joint fit of a simulated frames file (two presses at one place on a skin
with memory, simulated on a finer mesh with noise), its corrected images, saved fit and figure;
a capped fit that does not converge; bad input; and `diffeit live --memory` with a saved fit."""

import dataclasses
from types import SimpleNamespace

import matplotlib.image
import numpy as np
import pytest

import diffeit as de
import hw
from diffeit import fit
from diffeit.cli import main
from diffeit.cli._fit import IMAGE_QUANTITY, NOT_CONVERGED
from diffeit.cli._hardware import DEAD_BAND, _LiveViewer
from diffeit.cli._model import ModelSettings
from diffeit.io import Recording, read_frames, write_frames
from diffeit.results import RESULTS
from diffeit.scene import Disc, MeasurementNoise, Noise, Press, Scene, Skin, Touch, over_foam, simulate

CENTRE, RADIUS, AMPLITUDE = (0.4, -0.1), 0.35, -0.4
PRESSES = ((1.0, 1.5), (4.5, 1.0))  # (start, hold), seconds
RATE, DURATION = 2.0, 8.0  # 16 frames: the first two untouched
GEOMETRY = {"kind": "disc", "n_electrodes": 16, "electrode_width": 0.2, "h": 0.25}


@pytest.fixture(scope="module")
def scene() -> Scene:
    touches = tuple(Touch(Disc(CENTRE, RADIUS), AMPLITUDE, Press(start=s, hold=h)) for s, h in PRESSES)
    return Scene(
        skin=Skin(h=0.25),  # simulated at h / 2
        touches=touches,
        frame_rate=RATE,
        duration=DURATION,
        effects=(over_foam(), MeasurementNoise(Noise.level("medium"), seed=11)),
    )


@pytest.fixture(scope="module")
def frames_file(scene, tmp_path_factory):
    path = tmp_path_factory.mktemp("fit") / "memory.h5"
    simulate(scene, progress=False).save(path)
    return path


def _gaps(scene: Scene, mesh: de.Mesh) -> tuple[np.ndarray, np.ndarray]:
    """Boolean (T,) masks: the frames between and after the presses (no touch, but the skin
    still recovering), and the frames pressed."""
    truth = np.asarray(de.scene.stimulus(mesh, scene.touches, scene.times))
    pressed = np.abs(truth).max(axis=1) > 0.5 * abs(AMPLITUDE)
    untouched = np.abs(truth).max(axis=1) == 0
    return untouched & (np.cumsum(pressed) > 0), pressed


def _energy(mesh: de.Mesh, images: np.ndarray) -> float:
    return float(np.sum(images**2 @ mesh.element_areas))


@pytest.mark.slow
def test_fit_writes_the_stimulus_the_fit_and_a_figure(scene, frames_file, tmp_path, capsys):
    out = tmp_path / "skin"
    assert main(["fit", str(frames_file), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert " s, converged\n" in printed and "misfit" in printed

    corrected = read_frames(tmp_path / "skin.h5")
    mesh = corrected.mesh
    n_frames = len(scene.times)
    assert mesh.n_elements == scene.reconstruction_mesh().n_elements
    assert corrected.images.shape == (n_frames, mesh.n_elements)
    assert corrected.image_quantity == IMAGE_QUANTITY
    np.testing.assert_array_equal(corrected.frames, read_frames(frames_file).frames)

    saved = fit.load(tmp_path / "skin.fit.h5")
    assert saved.result == RESULTS.successful
    np.testing.assert_allclose(corrected.images, saved.stimulus)
    assert saved.background.shape == (mesh.n_elements,) and saved.contact_impedance.shape == (16,)
    assert abs(np.median(saved.background) / 0.01 - 1) < 0.1  # the scene's uniform 0.01 S/sq
    assert corrected.provenance["metadata"]["misfit"] == pytest.approx(saved.misfit)
    # The memory parameters' standard errors: printed, and kept in the provenance.
    errors = corrected.provenance["metadata"]["memory_relative_error"]
    assert set(errors) == set(saved.settings.memory_fitted)
    assert all(0 < value < np.inf for value in errors.values())
    assert f"slow_time {float(saved.memory.slow_time):.3g} +- {errors['slow_time']:.0%}" in printed

    # Between the presses the stimulus is near zero: the memory explains the recovering skin.
    gaps, pressed = _gaps(scene, mesh)
    stimulus = np.asarray(saved.stimulus)
    peak = np.abs(stimulus[pressed]).max()
    assert np.abs(stimulus[gaps]).max() < 0.25 * peak
    before = _plain_images(saved, mesh, read_frames(frames_file))
    assert _energy(mesh, before[gaps]) > 5 * _energy(mesh, stimulus[gaps])

    figure = matplotlib.image.imread(tmp_path / "skin.png")
    assert figure.shape[0] > 600 and figure.shape[1] > 900 and np.ptp(figure[..., :3]) > 0.5


def _plain_images(saved, mesh, recording) -> np.ndarray:
    from diffeit.cli._fit import fitted_one_step

    solver = fitted_one_step(saved, mesh, recording.protocol, ModelSettings())
    return np.asarray(solver.reconstruct(recording.frames - recording.frames[0])) / np.asarray(saved.background)


@pytest.mark.slow
def test_a_capped_fit_says_it_did_not_converge(frames_file, tmp_path, capsys):
    """--max-steps 2: exit status 1 (NOT_CONVERGED), the reason on stderr, and the files of the
    last iterate written (to resume from)."""
    out = tmp_path / "capped"
    status = main(["fit", str(frames_file), "-o", str(out), "--max-steps", "2", "--free", "memory", "stimulus"])
    captured = capsys.readouterr()
    assert status == NOT_CONVERGED == 1
    assert "did not converge" in captured.out and "did not converge" in captured.err
    assert "--resume" in captured.err
    saved = fit.load(tmp_path / "capped.fit.h5")
    assert saved.result == RESULTS.max_iterations_reached
    assert saved.settings.free == ("memory", "stimulus")
    assert len(saved.history.objective) <= 3
    assert (tmp_path / "capped.png").exists() and read_frames(tmp_path / "capped.h5").images is not None


def test_bad_input_exits_2_with_a_message_and_writes_nothing(tmp_path, capsys):
    protocol = de.protocol.adjacent(16)
    recording = Recording(
        frames=np.ones((4, protocol.n_measurements)), times=np.arange(4.0), protocol=protocol, geometry=GEOMETRY
    )
    frames_file = write_frames(tmp_path / "frames.h5", recording)
    out = tmp_path / "bad"
    assert main(["fit", str(frames_file), "-o", str(out), "--free", "gain"]) == 2
    assert "free: unknown names ['gain']" in capsys.readouterr().err
    assert main(["fit", str(frames_file), "-o", str(out), "--reference-frames", "0"]) == 2
    assert "reference_frames" in capsys.readouterr().err
    assert main(["fit", str(tmp_path / "missing.h5"), "-o", str(out)]) == 2
    assert "missing.h5" in capsys.readouterr().err
    counts = write_frames(tmp_path / "counts.h5", dataclasses.replace(recording, voltage_unit="arbitrary"))
    assert main(["fit", str(counts), "-o", str(out)]) == 2
    assert "needs volts" in capsys.readouterr().err
    (tmp_path / "bad.png").write_bytes(b"kept")
    assert main(["fit", str(frames_file), "-o", str(out)]) == 2
    assert "exists; pass --overwrite" in capsys.readouterr().err
    assert (tmp_path / "bad.png").read_bytes() == b"kept"
    assert not (tmp_path / "bad.h5").exists() and not (tmp_path / "bad.fit.h5").exists()


# --- diffeit live --memory -------------------------------------------------------------------


def test_live_memory_corrects_frame_by_frame_across_batches(scene, tmp_path):
    """The live viewer's correction of batches of 3 frames equals `correct_memory` of all the
    frames at once (the memory state carries over from batch to batch), with a dead band of 3
    standard deviations of the image noise the fit's data scale implies."""
    simulation = simulate(scene, progress=False)
    frames, times = np.asarray(simulation.frames), np.asarray(simulation.times)
    settings = ModelSettings(h=0.25)
    mesh = settings.unit_disc(16)
    # The parts of a JointFit the viewer reads: the skin's true values, and the noise level.
    known = SimpleNamespace(
        background=np.full(mesh.n_elements, 0.01),
        contact_impedance=np.full(16, 0.01),
        memory=over_foam(),
        settings=SimpleNamespace(data_scale=0.005 * np.sqrt(np.mean(frames[0] ** 2))),
    )
    reference = np.asarray(simulation.reference)
    viewer = _LiveViewer(de.protocol.adjacent(16), settings, str(tmp_path / "live.png"), reference[None], known)
    incoming = [hw.Frame(values=values, host_time=1000.0 + t) for values, t in zip(frames, times, strict=True)]
    batches = [incoming[i : i + 3] for i in range(0, len(incoming), 3)]
    shown = np.concatenate([viewer._corrected(_relative_images(viewer, batch, reference), batch) for batch in batches])

    images = _relative_images(viewer, incoming, reference)
    expected = fit.correct_memory(images, 1000.0 + times, known.memory, tolerance=viewer.tolerance)
    np.testing.assert_allclose(shown, expected, atol=1e-12)
    noise = np.linalg.norm(np.asarray(viewer.solver.matrix), axis=1) * known.settings.data_scale / 0.01
    np.testing.assert_allclose(viewer.tolerance, DEAD_BAND * noise)
    # Between the presses the corrected images are quieter than the plain ones (measured: 0.72 of
    # the energy; the dead band keeps part of a release's small edge changes), the presses as strong.
    gaps, pressed = _gaps(scene, mesh)
    assert _energy(mesh, shown[gaps]) < 0.8 * _energy(mesh, images[gaps])
    assert _energy(mesh, shown[pressed]) > 0.8 * _energy(mesh, images[pressed])


def _relative_images(viewer: _LiveViewer, batch: list, reference: np.ndarray) -> np.ndarray:
    differences = np.array([frame.values for frame in batch]) - reference
    return np.asarray(viewer.solver.reconstruct(differences)) / np.asarray(viewer.fit.background)


@pytest.mark.slow
def test_live_memory_with_the_emulator(scene, tmp_path, capsys):
    """A fit saved by `JointFit.save` (from given parts, no steps), applied by `diffeit live
    --memory` to frames streamed by the emulator."""
    settings = ModelSettings(h=0.25)
    mesh = settings.unit_disc(16)
    model = settings.model(mesh, de.protocol.adjacent(16))
    simulation = simulate(scene, progress=False)
    frames = np.asarray(simulation.frames)
    initial = {
        "background": 0.01,
        "contact_impedance": 0.01,
        "memory": over_foam(),
        "stimulus": np.zeros((len(frames), mesh.n_elements)),
    }
    found = fit.joint(model, frames, simulation.times, initial=initial, max_steps=0, progress=False, throw=False)
    path = found.save(tmp_path / "skin.fit.h5")
    frames = np.concatenate([np.asarray(simulation.reference)[None], frames])
    png = tmp_path / "live.png"

    def live(frames: np.ndarray, *options: str) -> int:
        emulator = hw.Emulator(frames, frame_rate=50.0, text=True).start()
        arguments = ["live", "--port", emulator.port, "--text", "--protocol", "adjacent", "--frames", str(len(frames))]
        try:
            return main([*arguments, "--png", str(png), *options])
        finally:
            emulator.stop()

    assert live(frames, "--batch", "4", "--h", "0.25", "--memory", str(path)) == 0
    assert f"{len(frames) - 1} frames reconstructed and corrected for memory" in capsys.readouterr().out
    assert np.ptp(matplotlib.image.imread(png)[..., :3]) > 0.5
    # A fit made on another mesh is refused, naming the meshes; a missing fit file too.
    assert live(frames[:3], "--h", "0.2", "--memory", str(path)) == 2
    assert "the fit was made on a mesh of" in capsys.readouterr().err
    assert live(frames[:3], "--memory", str(tmp_path / "none.fit.h5")) == 2
    assert "none.fit.h5" in capsys.readouterr().err
