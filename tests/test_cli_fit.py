"""`diffeit fit`: the joint fit of a simulated frames file (a press on a skin with memory,
simulated on a finer mesh with noise), its corrected images, saved fit and figure;
a capped fit that does not converge; a fit killed mid-run and resumed from its checkpoint; bad
input; and `diffeit live --memory` with a saved fit."""

import concurrent.futures
import contextlib
import dataclasses
import io
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import jax
import matplotlib.image
import numpy as np
import pytest

import diffeit as de
import hw
from diffeit import fit
from diffeit.cli import main
from diffeit.cli._fit import CHECKPOINT_SUFFIX, FELL_SHORT, IMAGE_QUANTITY
from diffeit.cli._hardware import DEAD_BAND, _LiveViewer
from diffeit.cli._model import ModelSettings
from diffeit.io import Recording, read_frames, write_frames
from diffeit.results import RESULTS
from diffeit.scene import Disc, MeasurementNoise, Noise, Press, Scene, Skin, Touch, over_foam, simulate

# `diffeit fit` in a process of its own, to be killed.
FIT_COMMAND = (sys.executable, "-c", "import sys; from diffeit.cli import main; sys.exit(main())", "fit")

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
def simulation(scene):
    """The scene simulated once, for the frames file and the live viewer's tests."""
    return simulate(scene, progress=False)


@pytest.fixture(scope="module")
def small_scene(scene) -> Scene:
    """The scene's first press alone on a coarse skin: 8 frames (the press held from 1 s to
    2.5 s, then 3 frames recovering), 92 triangles."""
    return dataclasses.replace(scene, skin=Skin(h=0.4), duration=4.0)


@pytest.fixture(scope="module")
def small_frames_file(small_scene, tmp_path_factory):
    """`small_scene` simulated. Its fit takes about 100 steps of milliseconds each; the start
    (background and memory fits, compiling) most of the time."""
    path = tmp_path_factory.mktemp("fit") / "small.h5"
    simulate(small_scene, progress=False).save(path)
    return path


@pytest.fixture(scope="module")
def whole(small_frames_file, tmp_path_factory) -> SimpleNamespace:
    """`diffeit fit` of the small frames file run to its end, once for the tests that read it
    (what it writes, and the path the killed and resumed runs must follow): its exit status,
    what it printed, and its output name."""
    out = tmp_path_factory.mktemp("whole") / "skin"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        status = main(["fit", str(small_frames_file), "-o", str(out)])
    return SimpleNamespace(status=status, printed=printed.getvalue(), out=out)


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
def test_fit_writes_the_stimulus_the_fit_and_a_figure(small_scene, small_frames_file, whole):
    assert whole.status == 0
    printed, folder = whole.printed, whole.out.parent
    assert " s, converged\n" in printed and "misfit" in printed

    corrected = read_frames(folder / "skin.h5")
    mesh = corrected.mesh
    n_frames = len(small_scene.times)
    assert mesh.n_elements == small_scene.reconstruction_mesh().n_elements
    assert corrected.images.shape == (n_frames, mesh.n_elements)
    assert corrected.image_quantity == IMAGE_QUANTITY
    np.testing.assert_array_equal(corrected.frames, read_frames(small_frames_file).frames)

    saved = fit.load(folder / "skin.fit.h5")
    assert saved.result == RESULTS.successful
    np.testing.assert_allclose(corrected.images, saved.stimulus)
    assert saved.background.shape == (mesh.n_elements,) and saved.contact_impedance.shape == (16,)
    assert abs(np.median(saved.background) / 0.01 - 1) < 0.1  # the scene's uniform 0.01 S/sq
    assert corrected.provenance["metadata"]["misfit"] == pytest.approx(saved.misfit)
    assert corrected.provenance["metadata"]["result"] == "successful"
    assert corrected.provenance["metadata"]["failures"] == {}
    # The memory parameters' standard errors: printed, and kept in the provenance.
    errors = corrected.provenance["metadata"]["memory_relative_error"]
    assert set(errors) == set(saved.settings.memory_fitted)
    assert all(0 < value < np.inf for value in errors.values())
    assert f"slow_time {float(saved.memory.slow_time):.3g} +- {errors['slow_time']:.0%}" in printed

    # Between the presses the stimulus is near zero: the memory explains the recovering skin.
    gaps, pressed = _gaps(small_scene, mesh)
    stimulus = np.asarray(saved.stimulus)
    peak = np.abs(stimulus[pressed]).max()
    assert np.abs(stimulus[gaps]).max() < 0.25 * peak
    before = _plain_images(saved, mesh, read_frames(small_frames_file))
    assert _energy(mesh, before[gaps]) > 5 * _energy(mesh, stimulus[gaps])

    figure = matplotlib.image.imread(folder / "skin.png")
    assert figure.shape[0] > 600 and figure.shape[1] > 900 and np.ptp(figure[..., :3]) > 0.5


def _plain_images(saved, mesh, recording) -> np.ndarray:
    from diffeit.cli._fit import fitted_one_step

    solver = fitted_one_step(saved, mesh, recording.protocol, ModelSettings())
    return np.asarray(solver.solve(recording.frames - recording.frames[0]).value) / np.asarray(saved.background)


@pytest.mark.slow
def test_a_capped_fit_says_it_did_not_converge(small_frames_file, tmp_path, capsys, monkeypatch):
    """--max-steps 2: exit status 1 (FELL_SHORT), the reason on stderr, the result code's name in
    OUT.h5's provenance, and the files of the last iterate written (to resume from). A memory
    uncertainty that fails (made to, here) is said on stderr and kept in the provenance too."""

    def singular(*arguments):
        raise np.linalg.LinAlgError("Singular matrix")

    monkeypatch.setattr(fit, "memory_uncertainty", singular)
    out = tmp_path / "capped"
    status = main(["fit", str(small_frames_file), "-o", str(out), "--max-steps", "2", "--free", "memory", "stimulus"])
    captured = capsys.readouterr()
    assert status == FELL_SHORT == 1
    assert "did not converge" in captured.out and "did not converge" in captured.err
    assert "--resume" in captured.err
    assert "memory uncertainty failed: Singular matrix" in captured.err
    saved = fit.load(tmp_path / "capped.fit.h5")
    assert saved.result == RESULTS.max_iterations_reached
    assert saved.settings.free == ("memory", "stimulus")
    assert len(saved.history.objective) <= 3
    assert (tmp_path / "capped.png").exists()
    metadata = read_frames(tmp_path / "capped.h5").provenance["metadata"]
    assert metadata["result"] == "max_iterations_reached" and "iteration limit" in metadata["result_message"]
    assert metadata["failures"] == {"memory_uncertainty": "Singular matrix"}
    assert metadata["memory_relative_error"] == {}
    assert not (tmp_path / f"capped{CHECKPOINT_SUFFIX}").exists()


@pytest.mark.slow
def test_a_fit_killed_mid_run_goes_on_from_its_checkpoint(small_frames_file, whole, tmp_path, capsys):
    """A run SIGKILLed after its first checkpoint (every 5 accepted steps), in a process of its own;
    then resumed from it and stopped by SIGTERM (exit status 143, the checkpoint written at the next
    step), in this process, whose compiled programs it shares; then resumed to the end: the
    checkpoints hold the uninterrupted fit's path, and the end is where the uninterrupted fit ends,
    to what L-BFGS restarted twice without its history allows. The fit stops when three steps each
    lower J by less than 0.012 (its unit: one frame's misfit at the noise), along a valley
    where the memory parameters and the contact impedances are weakly determined (the memory's
    Cramer-Rao errors here 0.2 to 20 times its values). Measured here (killed at step 5, stopped
    at 11; at 10): J 0.007 apart (0.017), memory parameters within 3.6% (4.2%), stimulus within
    0.024 (0.029; peak 0.57), background within 1.0% (0.8%), contact impedances within 3.3%
    (2.3%), misfit within 0.06% (0.04%); over single restarts after 5, 20 and 50 steps: J within
    0.05, memory parameters within 7%, stimulus within 0.022, background within 1.1%, contact
    impedances within 6%."""
    frames = str(small_frames_file)
    out = tmp_path / "cut"
    checkpoint = tmp_path / f"cut{CHECKPOINT_SUFFIX}"
    arguments = [frames, "-o", str(out), "--checkpoint-every", "5"]
    command = [*FIT_COMMAND, *arguments]

    killed = subprocess.Popen(
        command,
        env=_compiling_environment(tmp_path / "compilation-cache"),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    _wait_for_a_new_file(killed, checkpoint, None)
    killed.kill()
    assert killed.wait() == -signal.SIGKILL
    first = fit.load(checkpoint)
    assert not (tmp_path / "cut.fit.h5").exists()
    assert whole.status == 0
    uninterrupted = fit.load(whole.out.parent / "skin.fit.h5")

    steps = len(first.history.objective) - 1
    assert first.result == RESULTS.max_iterations_reached and steps > 0 and steps % 5 == 0
    np.testing.assert_allclose(first.history.objective, uninterrupted.history.objective[: steps + 1], rtol=1e-9)

    # SIGTERM to this process once the resumed run writes its next checkpoint. The fit defers the
    # signal while it runs; the handler set here catches one that would come after it.
    late = []
    previous = signal.signal(signal.SIGTERM, lambda number, frame: late.append(number))
    capsys.readouterr()
    ended = threading.Event()
    try:
        with concurrent.futures.ThreadPoolExecutor(1) as pool:
            watcher = pool.submit(_signal_on_a_new_file, checkpoint, os.stat(checkpoint), signal.SIGTERM, ended)
            try:
                status = main(["fit", *arguments, "--resume", str(checkpoint)])
            finally:
                ended.set()
            assert watcher.result(), "the resumed run wrote no new checkpoint"
    finally:
        signal.signal(signal.SIGTERM, previous)
    stderr = capsys.readouterr().err
    second = fit.load(checkpoint)
    assert not late, "SIGTERM came after the fit had ended"

    assert status == 128 + signal.SIGTERM == 143, stderr
    later = len(second.history.objective) - 1
    assert f"stopped by SIGTERM; the fit at step {later} is in {checkpoint}" in stderr
    assert second.result == RESULTS.max_iterations_reached and later >= steps + 5
    np.testing.assert_array_equal(second.history.objective[: steps + 1], first.history.objective)

    assert main(["fit", frames, "-o", str(out), "--resume", str(checkpoint)]) == 0
    assert not checkpoint.exists()
    resumed = fit.load(tmp_path / "cut.fit.h5")
    assert resumed.result == RESULTS.successful
    np.testing.assert_array_equal(resumed.history.objective[: len(second.history.objective)], second.history.objective)
    assert abs(resumed.history.objective[-1] - uninterrupted.history.objective[-1]) < 0.1
    for name in resumed.settings.memory_fitted:
        assert float(getattr(resumed.memory, name)) == pytest.approx(
            float(getattr(uninterrupted.memory, name)), rel=0.1
        )
    np.testing.assert_allclose(resumed.stimulus, uninterrupted.stimulus, atol=0.05)
    np.testing.assert_allclose(resumed.background, uninterrupted.background, rtol=0.03)
    np.testing.assert_allclose(resumed.contact_impedance, uninterrupted.contact_impedance, rtol=0.1)
    assert resumed.misfit == pytest.approx(uninterrupted.misfit, rel=0.01)


def _compiling_environment(own_cache: Path) -> dict[str, str]:
    """This process's environment, with JAX's compilation cache shared when the tests keep one;
    else with the folder `own_cache`, which the processes started with it share."""
    cache = jax.config.jax_compilation_cache_dir or str(own_cache)
    return {**os.environ, "JAX_COMPILATION_CACHE_DIR": cache, "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0"}


def _wait_for_a_new_file(process: subprocess.Popen, path: Path, before: os.stat_result | None) -> None:
    """Poll until `path` exists and is another file than `before` (a checkpoint is renamed into
    place: a new inode); fails when `process` ends first, or after 5 minutes."""
    deadline = time.monotonic() + 300
    while True:
        try:
            now = os.stat(path)
        except FileNotFoundError:
            now = None
        if now is not None and (before is None or (now.st_ino, now.st_mtime_ns) != (before.st_ino, before.st_mtime_ns)):
            return
        assert process.poll() is None, f"the fit ended before a new checkpoint: {process.stderr.read()}"
        assert time.monotonic() < deadline, f"no new checkpoint {path} in 5 minutes"
        time.sleep(0.005)


def _signal_on_a_new_file(path: Path, before: os.stat_result, number: int, ended: threading.Event) -> bool:
    """Send signal `number` to this process once `path` is another file than `before`: True; False
    when `ended` is set first."""
    while not ended.is_set():
        with contextlib.suppress(FileNotFoundError):
            now = os.stat(path)
            if (now.st_ino, now.st_mtime_ns) != (before.st_ino, before.st_mtime_ns):
                os.kill(os.getpid(), number)
                return True
        time.sleep(0.005)
    return False


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


def test_live_memory_corrects_frame_by_frame_across_batches(scene, simulation, tmp_path):
    """The live viewer's correction of batches of 3 frames equals `correct_memory` of all the
    frames at once (the memory state carries over from batch to batch), with a dead band of 3
    standard deviations of the image noise the fit's data scale implies."""
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
    return np.asarray(viewer.solver.solve(differences).value) / np.asarray(viewer.fit.background)


@pytest.mark.slow
def test_live_memory_with_the_emulator(simulation, tmp_path, capsys):
    """A fit saved by `JointFit.save` (from given parts, no steps), applied by `diffeit live
    --memory` to frames streamed by the emulator."""
    settings = ModelSettings(h=0.25)
    mesh = settings.unit_disc(16)
    model = settings.model(mesh, de.protocol.adjacent(16))
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
