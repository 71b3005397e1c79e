"""Sound sample files of the formats diffeit reads, each written by the project's own code, and
the public reader of each: for tests that damage a file (cut it, flip bits, ...) and check that
reading it raises `ValueError` / `FileNotFoundError` or gives the file's data, promptly.

For each kind in `KINDS`:

- `write_<kind>(folder) -> Path` writes one small sound file into `folder` (fast: no mesh);
- `read_<kind>(path)` reads a file with the public reader and returns its data as plain values
  (dicts of arrays, numbers and strings; `same(a, b)` compares two), or raises `ValueError`
  (naming the file) or `FileNotFoundError`, within a second whatever the damage.

What a damaged file can read as, when reading it raises nothing (`DAMAGE_READS_AS`):

- "whole": the sound file's data. Every cut and every changed byte that matters is detected
  (checksums: HDF5's Fletcher-32 of every dataset and its metadata checksums, zlib's Adler-32
  of each compressed MAT variable, the .npz archive's CRC-32 of each member); the bytes that
  do not matter (a MAT header's text, a zip entry's time stamp) change nothing read.
- "frames": some of the sound frames, each value for value, by counter (serial streams: both
  CRCs of every binary frame; a damaged frame is dropped and counted, never raised).
- "as written": what the damaged bytes now say. These formats carry no checksum: a digit
  changed to another digit reads as another number (uncompressed MAT values, text), and a file
  cut at the end of a line (a variable) reads as the lines (variables) before the cut; a cut
  within a line is refused. A scene's keys cut off take their defaults.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import scipy.io

import diffeit as de
import hw
from diffeit import correction

KINDS = (
    "frames",
    "recorder",
    "fit",
    "eidors_mat",
    "eidors_mat_uncompressed",
    "openeit",
    "csv",
    "scene",
    "correction",
    "skin_calibration",
    "serial",
)
DAMAGE_READS_AS = {
    "frames": "whole",
    "recorder": "whole",
    "fit": "whole",
    "eidors_mat": "whole",
    "eidors_mat_uncompressed": "as written",
    "openeit": "as written",
    "csv": "as written",
    "scene": "as written",
    "correction": "whole",
    "skin_calibration": "whole",
    "serial": "frames",
}
_RNG_SEED = 30


def _frames(n_frames: int, n_values: int, low: float = -1.0, high: float = 1.0) -> np.ndarray:
    return np.random.default_rng(_RNG_SEED).uniform(low, high, size=(n_frames, n_values))


# -- EIDORS .mat ------------------------------------------------------------------------------


def _write_mat(path: Path, compressed: bool) -> Path:
    """Frames (208, 2) and a reference (208, 1), columns are frames, as EIDORS saves them."""
    frames = _frames(2, 208)
    scipy.io.savemat(path, {"frames": frames.T, "reference": frames[:1].T}, do_compression=compressed)
    return path


def write_eidors_mat(folder: Path) -> Path:
    """A compressed v5 file, MATLAB's default since v7."""
    return _write_mat(Path(folder) / "frames.mat", compressed=True)


def write_eidors_mat_uncompressed(folder: Path) -> Path:
    """An uncompressed v5 file (MATLAB '-v6', scipy's default): no checksum of its values."""
    return _write_mat(Path(folder) / "frames_v6.mat", compressed=False)


def read_eidors_mat(path: Path) -> dict[str, Any]:
    """With the reference, so a file cut at the end of its first variable lacks the second."""
    recording = de.io.read_eidors_mat(path, "frames", reference="reference")
    return {"frames": recording.frames, "reference": recording.reference}


read_eidors_mat_uncompressed = read_eidors_mat


# -- text frames ------------------------------------------------------------------------------


def write_openeit(folder: Path) -> Path:
    """An OpenEIT dashboard log: firmware messages, then 3 frames of 8 electrodes (32 values)."""
    lines = [
        "magnitudes: " + "".join(f"{value:13.4f} , " for value in row) + "\n" for row in _frames(3, 32, 150.0, 350.0)
    ]
    path = Path(folder) / "openeit.txt"
    path.write_text("OpenEIT\nmode 3: imaging\n\n" + "".join(lines))
    return path


def read_openeit(path: Path) -> dict[str, Any]:
    recording = de.io.read_openeit(path)
    return {"frames": recording.frames, "n_electrodes": recording.protocol.n_electrodes}


def write_csv(folder: Path) -> Path:
    """3 frames of `adjacent(8)` (40 readings), one a row, by numpy's writer (round-tripping digits)."""
    path = Path(folder) / "frames.csv"
    np.savetxt(path, _frames(3, 40), delimiter=",", fmt="%.17g")
    return path


def read_csv(path: Path) -> dict[str, Any]:
    recording = de.io.read_csv(path)
    return {"frames": recording.frames, "times": recording.times, "n_electrodes": recording.protocol.n_electrodes}


# -- scene, calibration -----------------------------------------------------------------------


def write_scene(folder: Path) -> Path:
    """The example "single_touch" on coarse meshes (h = 0.25 m both), saved by `Scene.to_toml`.

    Reading a scene meshes its skin (a touch must lie on it), so a coarse mesh keeps a damaged
    file whose skin grew (a radius of 1.0 read as 9.0) quick to read."""
    scene = de.scene.example("single_touch")
    scene = dataclasses.replace(scene, skin=dataclasses.replace(scene.skin, h=0.25, simulation_h=0.25))
    return scene.to_toml(Path(folder) / "scene.toml", overwrite=True)


def read_scene(path: Path) -> dict[str, Any]:
    return de.scene.Scene.from_toml(path).to_dict()


def write_correction(folder: Path) -> Path:
    """A small calibration made by hand (4 positions, 1 x 2 x 1 settings), by `Calibration.save`."""
    rng = np.random.default_rng(_RNG_SEED)
    settings = correction.CalibrationSettings("noser", 0.05, (0.01,), (-0.4, -0.6), (0.2,), 0.5, 2, 0, 10, 20)
    positions = np.array([[0.0, 0.0], [0.5, 0.0], [0.0, 0.5], [-0.4, -0.3]])
    tables = [rng.uniform(0.5, 2.0, (1, 2, 1, 4)) for _ in range(2)]
    factors = [rng.uniform(0.5, 2.0, 4) for _ in range(2)]
    calibration = correction.Calibration(positions, *factors, *tables, settings, 0.9 * positions)
    return calibration.save(Path(folder) / "calibration.npz")


def read_correction(path: Path) -> dict[str, Any]:
    calibration = correction.load(path)
    arrays = ("positions", "image_positions", "intensity_factor", "size_factor", "intensity_table", "size_table")
    return {name: np.asarray(getattr(calibration, name)) for name in arrays} | {
        "settings": dataclasses.asdict(calibration.settings)
    }


def write_skin_calibration(folder: Path) -> Path:
    """A skin's calibration (`de.calibrate` on ten reference frames of a coarse disc, with its
    electrode positions fitted), saved by `SkinCalibration.save`."""
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.4)
    protocol = de.protocol.adjacent(16)
    clean = np.asarray(de.ForwardModel(mesh, protocol, 0.02).measure(np.ones(mesh.n_elements)))
    rng = np.random.default_rng(_RNG_SEED)
    frames = clean * (1 + 1e-3 * rng.standard_normal((10, clean.size)))
    recording = de.io.Recording(frames=frames, times=0.1 * np.arange(10), protocol=protocol, mesh=mesh)
    calibration = de.calibrate(recording, reference_groups=("contact_impedance", "electrode_positions"))
    return calibration.save(Path(folder) / "skin.cal.h5")


def read_skin_calibration(path: Path) -> dict[str, Any]:
    calibration = de.calibration.load(path)
    sigma = np.full(calibration.model.n_elements, calibration.conductivity)
    return {
        "values": calibration.values,
        "standard_errors": calibration.standard_errors,
        "lines": calibration.lines(),
        "voltages": np.asarray(calibration.model.measure(sigma)),
        "noise": calibration.noise,
    }


# -- serial stream ----------------------------------------------------------------------------


def write_serial(folder: Path) -> Path:
    """The bytes a board (or `hw.Emulator`, which encodes its frames so) sends: 4 binary frames
    of `adjacent(8)`, float32, counters 0..3, 100 frames/s."""
    stream = b"".join(
        hw.encode_frame(values, counter=i, device_time=i / 100.0, layout=hw.frame.LAYOUT_ADJACENT, n_electrodes=8)
        for i, values in enumerate(_frames(4, 40))
    )
    path = Path(folder) / "stream.bin"
    path.write_bytes(stream)
    return path


def read_serial(path: Path) -> dict[int, np.ndarray]:
    """The frames `hw.BinaryParser` delivers from the stream, by counter (damage is dropped and
    counted in its statistics, never raised)."""
    parser = hw.BinaryParser()
    frames = {frame.counter: frame.values for frame in parser.feed(Path(path).read_bytes())}
    parser.finish()
    return frames


# -- HDF5: a frames file, a recorder's file its killed recorder left open, a joint fit ---------


def _small_recording():
    """A frames file's worth: 5 frames of a 16-electrode sheet with its mesh, reference and images."""
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.4)
    protocol = de.protocol.adjacent(16)
    rng = np.random.default_rng(3)
    return de.io.Recording(
        frames=rng.normal(size=(5, protocol.n_measurements)),
        times=np.arange(5) * 0.1,
        protocol=protocol,
        reference=rng.normal(size=protocol.n_measurements),
        mesh=mesh,
        provenance={"source": "tests", "metadata": {"operator": "me"}},
        images=rng.normal(size=(5, mesh.n_elements)),
        image_quantity="conductivity change",
    )


def write_frames(folder: Path) -> Path:
    return de.io.write_frames(folder / "frames.h5", _small_recording())


def read_frames(path: Path) -> object:
    return de.io.read_frames(path)


def write_recorder(folder: Path) -> Path:
    """A copy of a recorder's file taken while the recorder held it open: marked open for
    writing in SWMR mode, as a killed recorder leaves its file."""
    import shutil

    protocol = de.protocol.adjacent(16)
    rng = np.random.default_rng(4)
    with hw.Recorder(folder / "recording.h5", protocol) as recorder:
        for _ in range(3):
            recorder.append([hw.Frame(rng.normal(size=protocol.n_measurements), counter=k) for k in range(20)])
        shutil.copyfile(folder / "recording.h5", folder / "killed.h5")
    return folder / "killed.h5"


def read_recorder(path: Path) -> object:
    return list(hw.read_recorded_frames(path)), hw.recorded_statistics(path)


def write_fit(folder: Path) -> Path:
    """A joint fit of five frames on a coarse disc, made by hand (as `write_correction`'s
    calibration: `de.fit.joint` compiles its start and optimiser for seconds, and writes the
    same datasets) and saved by `JointFit.save`: small, but every dataset."""
    from diffeit.fit._memory import DEFAULT_FREE, memory_to_unconstrained
    from diffeit.fit._optimise import History
    from diffeit.results import RESULTS

    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.4)
    rng = np.random.default_rng(_RNG_SEED)
    times = np.array([0.0, 0.5, 1.0, 1.5, 2.5])
    near = np.linalg.norm(mesh.element_centroids - np.array([0.3, 0.2]), axis=1) < 0.4
    stimulus = np.outer([0.0, -0.3, -0.28, -0.05, -0.02], near)
    background = rng.uniform(0.009, 0.011, mesh.n_elements)
    contact_impedance = rng.uniform(0.009, 0.011, 16)
    memory = de.scene.over_foam()
    fit = de.fit.JointFit(
        background=background,
        contact_impedance=contact_impedance,
        memory=memory,
        stimulus=stimulus,
        response=np.asarray(de.scene.memory_response(stimulus, times, memory)),
        times=times,
        misfit=0.0042,
        history=History(np.array([37.2, 21.5, 18.9]), np.array([4.1, 2.3, 1.7])),
        result=RESULTS.max_iterations_reached,
        parameters=de.fit.JointParameters(
            np.log(background), np.log(contact_impedance), memory_to_unconstrained(memory, DEFAULT_FREE), stimulus
        ),
        settings=de.fit.JointSettings(
            ("background", "contact_impedance", "memory", "stimulus"),
            DEFAULT_FREE,
            de.fit.JointPriors(),
            2.1e-5,
            memory,
            np.log(contact_impedance),
        ),
    )
    return fit.save(folder / "fit.fit.h5")


def read_fit(path: Path) -> object:
    return de.fit.load(path)


# -- comparing --------------------------------------------------------------------------------


def same(a: Any, b: Any) -> bool:
    """Whether two results of a `read_<kind>` are equal, arrays value for value."""
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[key], b[key]) for key in a)
    if isinstance(a, list | tuple):
        return isinstance(b, list | tuple) and len(a) == len(b) and all(map(same, a, b))
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.array_equal(a, b)
    return a == b


WRITERS: dict[str, Callable[[Path], Path]] = {kind: globals()[f"write_{kind}"] for kind in KINDS}
READERS: dict[str, Callable[[Path], Any]] = {kind: globals()[f"read_{kind}"] for kind in KINDS}
