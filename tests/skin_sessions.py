"""A simulated calibration session of a skin and its board, for the tests of calibration
(tests/test_calibration.py), of `diffeit calibrate` (tests/test_cli_calibrate.py) and of
`diffeit live --calibration` (tests/test_cli_live_touches.py).

`skin_session(seed, board, ...)` builds one; `gains_board` and `mixing_board` are the boards
(`Readout`s) the tests read their skins with. `calibrated_session(tmp_path_factory)` is one
session written to files and calibrated by `diffeit calibrate`, made once per run and shared by
the CLI tests (`once_per_run`: pytest-xdist's processes share it)."""

from __future__ import annotations

import csv
import dataclasses
import fcntl
import functools
import os
import pickle
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TypeVar

import jax.numpy as jnp
import numpy as np

import diffeit as de
from diffeit.cli import main
from diffeit.readout import Readout

PROTOCOL = de.protocol.adjacent(16)
RADIUS, DROP = 0.15, 0.3  # every press: a disc of this radius (m) where dsigma/sigma = -DROP
UNTOUCHED = 10  # untouched frames a session begins with
PERIOD = 0.1  # s from one frame to the next


def gains_board(rng: np.random.Generator) -> Readout:
    """Gains per drive and per measuring channel of up to 25%."""
    drive, channel = np.exp(rng.uniform(-0.25, 0.25, (2, 16)))
    return Readout(PROTOCOL, gains=drive[PROTOCOL.drive_index] * channel[PROTOCOL.pattern_index])


def mixing_board(rng: np.random.Generator) -> Readout:
    """0.2 of the source electrode's potential and 0.1 of the far electrode's mixed in."""
    return Readout(PROTOCOL, source=0.2, offsets=0.1 * np.eye(16)[8])


@dataclasses.dataclass(frozen=True)
class SkinSession:
    """A simulated session (see `skin_session`) and the skin and board that gave it.

    Attributes:
        recording: The session's frames, in the board's unit ("arbitrary"), with the mesh.
        presses: The labelled presses (the mesh's frame), or None for a session without any.
        readout: The board.
        truth: The skin's model: the reconstruction's mesh, contact impedances of its own.
        noise: The standard deviation of the noise on every reading, in the board's unit.
    """

    recording: de.io.Recording
    presses: de.io.Presses | None
    readout: Readout
    truth: de.ForwardModel
    noise: float

    @property
    def mesh(self) -> de.Mesh:
        return self.truth.mesh

    def clean(self, sigma: np.ndarray) -> np.ndarray:
        """(M,) the board's noiseless readings of the skin at conductivity `sigma` (E,), S/sq."""
        return _readings(self.truth, self.readout, sigma)

    def pressed(self, centre: Sequence[float]) -> np.ndarray:
        """(E,) the skin's conductivity (S/sq) under one press at `centre` (m)."""
        return _pressed(self.mesh, centre)

    def frames(self, sigmas: Sequence[np.ndarray], seed: int) -> np.ndarray:
        """(T, M) the board's noisy frames of the conductivities `sigmas` (T of (E,)), seeded."""
        return _noisy([self.clean(sigma) for sigma in sigmas], self.noise, np.random.default_rng(seed))


def _readings(truth: de.ForwardModel, readout: Readout, sigma: np.ndarray) -> np.ndarray:
    return 1e3 * np.asarray(readout.readings(PROTOCOL, truth.potentials(jnp.asarray(sigma)).electrode))


def _pressed(mesh: de.Mesh, centre: Sequence[float]) -> np.ndarray:
    return 1 - DROP * de.mesh.disc_fraction(mesh, tuple(centre), RADIUS)


def _noisy(clean: list[np.ndarray], noise: float, rng: np.random.Generator) -> np.ndarray:
    return np.array(clean) + noise * rng.standard_normal((len(clean), len(clean[0])))


def skin_session(
    seed: int,
    board: Callable[[np.random.Generator], Readout],
    *,
    n_presses: int = 30,
    noise: float = 1e-3,
    untouched_between: bool = True,
    noise_seed: int | None = None,
    mesh: de.Mesh | None = None,
    sheet: Callable[[np.ndarray], np.ndarray] | None = None,
) -> SkinSession:
    """A calibration session of a coarse simulated skin, read by a board with noise.

    The skin is a disc of radius 1 m (16 electrodes 0.2 m wide, mesh size h = 0.1 m: its model is
    the reconstruction's) of conductivity 1 S/sq, with contact impedances 0.01 * exp(U(-0.55,
    0.55)) each (spread 3x), on the adjacent protocol. The board, `board(rng)`, takes its readings
    of the electrodes' potentials (V) and gives them times 1e3, in its own unit ("arbitrary");
    every reading gets Gaussian noise of standard deviation `noise` times the RMS untouched
    reading. A frame every 0.1 s: 10 untouched frames, then `n_presses` presses (discs of radius
    0.15 m, dsigma/sigma = -0.3) centred uniformly over the disc of radius 0.6 m, each followed by
    an untouched frame when `untouched_between`. One
    generator, `np.random.default_rng(seed)`, draws the contact impedances, then the board, the
    centres and the noise (the noise from `np.random.default_rng(noise_seed)` when given).
    With `mesh` (a curved skin), the skin is that mesh, and the presses are centred at the
    centroids of triangles drawn uniformly among those within 0.6 of the skin's size (its
    farthest node from the nodes' mean) of the nodes' mean. With `sheet`, the untouched skin's
    conductivity is `sheet(centroids)` (E,) S/sq instead of 1, and a press lowers it by the
    same fraction.

    Arguments:
        seed: Seeds the session's generator.
        board: Makes the board's `Readout` from the generator (`gains_board`, `mixing_board`).
        n_presses: How many presses; 0 for untouched frames only.
        noise: The noise's standard deviation, as a fraction of the RMS untouched reading.
        untouched_between: Whether an untouched frame follows each press.
        noise_seed: Seeds the noise's own generator; None draws it from the session's.
        mesh: The skin's mesh, for one other than the disc.
        sheet: The untouched conductivity, S/sq, as a function of the elements' centroids.

    Returns:
        A `SkinSession`: the recording, its presses (one instant each, at its pressed frame;
        None without presses), the board, the skin's model and the noise in the board's unit.
    """
    rng = np.random.default_rng(seed)
    disc = mesh is None
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.1) if disc else mesh
    truth = de.ForwardModel(mesh, PROTOCOL, contact_impedance=0.01 * np.exp(rng.uniform(-0.55, 0.55, 16)))
    readout = board(rng)
    untouched = np.ones(mesh.n_elements) if sheet is None else np.asarray(sheet(mesh.element_centroids), float)
    reference = _readings(truth, readout, untouched)
    if disc:
        angles = rng.uniform(0, 2 * np.pi, n_presses)
        radii = 0.6 * np.sqrt(rng.uniform(0, 1, n_presses))
        centres = np.stack([radii * np.cos(angles), radii * np.sin(angles)], axis=1)
    else:
        middle = mesh.nodes.mean(axis=0)
        size = np.max(np.linalg.norm(mesh.nodes - middle, axis=1))
        inner = np.flatnonzero(np.linalg.norm(mesh.element_centroids - middle, axis=1) < 0.6 * size)
        centres = mesh.element_centroids[rng.choice(inner, n_presses, replace=False)]
    clean = [reference] * UNTOUCHED
    for centre in centres:
        clean.append(_readings(truth, readout, untouched * _pressed(mesh, centre)))
        if untouched_between:
            clean.append(reference)
    std = noise * np.sqrt(np.mean(reference**2))
    frames = _noisy(clean, std, rng if noise_seed is None else np.random.default_rng(noise_seed))
    times = PERIOD * np.arange(len(frames))
    recording = de.io.Recording(frames=frames, times=times, protocol=PROTOCOL, mesh=mesh, voltage_unit="arbitrary")
    step = 2 if untouched_between else 1  # from one pressed frame to the next
    presses = de.io.Presses(centres, RADIUS, times[UNTOUCHED::step]) if n_presses else None
    return SkinSession(recording, presses, readout, truth, std)


@dataclasses.dataclass(frozen=True)
class CalibratedSession:
    """A session's files and their calibration by `diffeit calibrate` (see `calibrated_session`).

    Attributes:
        skin: The session.
        path: The session file (`diffeit.io.write_frames`).
        presses: The presses' CSV file (x_m, y_m, radius_m, time_s, label).
        status: `diffeit calibrate`'s exit status.
        calibration: The calibration file it wrote (and its figure beside it, .png).
    """

    skin: SkinSession
    path: Path
    presses: Path
    status: int
    calibration: Path


Value = TypeVar("Value")


def once_per_run(tmp_path_factory, name: str, compute: Callable[[Path], Value]) -> Value:
    """`compute(folder)`, once per test run: the first of pytest-xdist's processes to ask computes
    it, under a lock, and the others wait for it and read it back (pickled: the value must
    pickle). `folder`, shared by the processes, is where `compute` may write files. The suite's
    slowest fixtures (calibrations of about 15 s) had been computed in each process."""
    if os.environ.get("PYTEST_XDIST_WORKER") is None:  # one process: its own temporary folder
        return _computed(tmp_path_factory.getbasetemp(), name, compute)
    root = tmp_path_factory.getbasetemp().parent  # the run's folder, above each process's own
    with open(root / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        return _computed(root, name, compute)


@functools.cache
def _computed(root: Path, name: str, compute: Callable[[Path], Value]) -> Value:
    stored = root / f"{name}.pickle"
    if stored.exists():
        return pickle.loads(stored.read_bytes())
    folder = root / name
    folder.mkdir(exist_ok=True)  # a computation that raised before may have left it
    value = compute(folder)
    partial = stored.with_suffix(".partial")
    partial.write_bytes(pickle.dumps(value))
    partial.replace(stored)
    return value


def calibrated_session(tmp_path_factory) -> CalibratedSession:
    """The session of a board with drive and channel gains up to 25% (`gains_board`), contact
    impedances spread 3x, 0.1% noise: 10 untouched frames, then 30 presses at known places, one
    after another (`skin_session(4, gains_board, untouched_between=False)`), written to a session
    file and a presses CSV and calibrated by `diffeit calibrate SESSION.h5 --presses PRESSES.csv
    -o SKIN.cal.h5`. Made once per run (`once_per_run`): a calibration takes about 15 s, and the
    CLI tests (tests/test_cli_calibrate.py, tests/test_cli_live_touches.py) share this one."""
    return once_per_run(tmp_path_factory, "calibrated_session", _calibrated_session)


def _calibrated_session(folder: Path) -> CalibratedSession:
    skin = skin_session(4, gains_board, untouched_between=False)
    recording, centres, times = skin.recording, skin.presses.centres, skin.recording.times
    path = de.io.write_frames(folder / "session.h5", recording)
    presses = folder / "presses.csv"
    with open(presses, "w", newline="") as file:
        writer = csv.writer(file, lineterminator="\n")
        writer.writerow(["x_m", "y_m", "radius_m", "time_s", "label"])
        for k, ((x, y), t) in enumerate(zip(centres, times[UNTOUCHED:], strict=True)):
            writer.writerow([repr(float(x)), repr(float(y)), RADIUS, repr(float(t)), f"press {k}"])
    output = folder / "skin.cal.h5"
    status = main(["calibrate", str(path), "--presses", str(presses), "-o", str(output)])
    return CalibratedSession(skin, path, presses, status, output)
