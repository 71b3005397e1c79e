"""The labelled presses read: each press's change against the rest before it (`_press_changes`,
`_rests`), its touch read from its one-step image as `diffeit.touches` reads one (`_read_presses`,
at `auto_hyperparameter`'s hyperparameter), its depth under its labelled disc at the calibrated
model (`_press_depths`), and the skin's memory fitted to presses held over several frames
(`_with_memory`).
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._arrays import frame_period
from ..fit import memory_from_press_readings
from ..forward import ForwardModel
from ..inverse import LinearisedProblem, OneStep, select_hyperparameter
from ..inverse.hyperparameter import DEFAULT_CANDIDATES
from ..io import Presses, Recording
from ..mesh import Mesh, disc_fractions
from ..results import RESULTS, failed, names
from ..touch import DETECTION, _one_step_noise, _statistic, _whitened, polarity_of, read
from ._reference import _batched_readings
from ._skin import SkinCalibration

# An L-curve corner within this factor of an end of the candidates counts as at the end.
_CORNER_MARGIN = 10.0


# A memory fit needs every press held over at least this many frames.
_HELD_FRAMES = 3


# A step of the readings this many frame periods or more from every labelled hold is a press not
# labelled (`_unlabelled_steps`): a press's ramp and its release lie within it.
_LABELLED_MARGIN = 2.5


# The memory fit's press depths: a press fainter than this (dsigma/sigma) keeps it, and a bend
# takes the model's readings under a press to within this factor (and its inverse) of their
# linear part, and no press lowers the conductivity by more than `_DEEPEST` of itself
# (`_depths_and_bends`).
_FAINTEST, _BEND_RATIO, _DEEPEST = 1e-3, 0.2, 0.9


# A press is read against the rest frames before it, not the reference, where their mean stands
# out of the reference's noise at this z (`_press_changes`; the voltage test's), and a frame is
# one of those rests when it stands within it of the quietest before the press (`_rests`) and
# has moved from that one towards the press by at most `_REST_TOWARD` standard deviations.
_REST_MOVED, _REST_TOWARD = 5.0, 3.0


def _press_patterns(mesh: Mesh, presses: Presses) -> np.ndarray:
    """(K, E) the fraction of each element inside each press's disc (its footprint), exact:
    the frame's central differences (`_FRAME_DELTA`) differentiate it, and a sampled footprint
    moves in steps (docs/tutorials/calibration.md: fewer trial steps, the same errors)."""
    return disc_fractions(mesh, presses.centres, presses.radius, level=None).T.toarray()


def auto_hyperparameter(
    model: ForwardModel,
    dv: np.ndarray,
    prior: Any,
    level: float | np.ndarray,
    rule: str = "auto",
    problem: LinearisedProblem | None = None,
) -> tuple[float, dict[str, Any]]:
    """The one-step hyperparameter for differences `dv` (T, M), and how it was chosen.

    "auto": the L-curve's corner, or the noise figure 0.5 when the corner sits within a decade
    of an end of the candidates (`diffeit.inverse.hyperparameter.DEFAULT_CANDIDATES`): a corner there is the
    curve's end, not a corner. A method of `diffeit.inverse.select_hyperparameter` ("gcv",
    "lcurve", "noise_figure") is used as given.

    Arguments:
        model: The calibrated model.
        dv: (T, M) or (M,) differences in the model's units.
        prior: The one-step prior (a name or a `diffeit.inverse` prior).
        level: The background conductivity the problem is linearised at, S/sq.
        rule: "auto" or a selection method's name.
        problem: The `LinearisedProblem` of `model` at `prior` and `level` when already
            built (the solver that images with the value can share it); None builds it.

    Returns:
        The value, and how it was chosen: the rule, and the value and code of each selection
        method evaluated (one linearisation shared between them).
    """
    problem = LinearisedProblem(model, prior, level) if problem is None else problem

    def select(name: str) -> dict[str, Any]:
        selection = select_hyperparameter(model, dv, name, prior=prior, background=level, throw=False, problem=problem)
        value = float(selection.value)
        # A corner within a decade of an end is the curve's end, not a corner: no regularisation to speak of.
        near_end = not DEFAULT_CANDIDATES[0] * _CORNER_MARGIN <= value <= DEFAULT_CANDIDATES[-1] / _CORNER_MARGIN
        return {
            "value": value,
            "at_boundary": bool(selection.result != RESULTS.successful) or near_end,
            "result": names(selection.result)[0],
        }

    if rule != "auto":
        chosen = select(rule)
        return chosen["value"], {rule: chosen, "rule": "given method", "method": rule}
    choice = {"lcurve": select("lcurve"), "rule": "auto"}
    method = "lcurve" if not choice["lcurve"]["at_boundary"] else "noise_figure"
    if method == "noise_figure":
        choice["noise_figure"] = select("noise_figure")
    return choice[method]["value"], {**choice, "method": method}


def _held(presses: Presses, times: np.ndarray) -> bool:
    """Whether every press is held over at least `_HELD_FRAMES` frames (a memory fit needs the holds)."""
    return all(len(chosen) >= _HELD_FRAMES for chosen in presses.frames(times)) and bool(
        np.all(presses.times[:, 1] > presses.times[:, 0])
    )


def _unlabelled_steps(calibration: SkinCalibration, recording: Recording, presses: Presses) -> np.ndarray:
    """The frames whose readings step out of their noise from the frame before, and whose pair
    (the frame and the next) stands out of the pair before them (the voltage test of each,
    variances 2 s^2 and s^2, at `diffeit.touch.DETECTION`: a press's onset or release holds,
    a noisy frame does not: with the noise from 10 frames, one step in 830 of a designed
    session stood at 6.2), farther than `_LABELLED_MARGIN` frame periods from every labelled
    press's hold: the onsets and releases of presses the labels do not hold. The memory's fit
    explains the session's readings by the labelled presses alone: on a simulated session with
    memory whose every other press was not labelled it did not converge (every press labelled:
    fitted). None where the calibration knows no noise."""
    noise = calibration.noise
    if noise is None or recording.n_frames < 4:
        return np.zeros(0, int)
    signed, count = calibration.signed(recording.frames), calibration.noise_frames
    steps = np.diff(signed, axis=0)[1:-1]  # into frames 2 to T - 2
    pairs = 0.5 * (signed[2:-1] + signed[3:]) - 0.5 * (signed[:-3] + signed[1:-2])
    stands_out = (_statistic(steps, noise, count, 2.0) > DETECTION) & (_statistic(pairs, noise, count, 1.0) > DETECTION)
    times = recording.times[2:-1]
    margin = _LABELLED_MARGIN * frame_period(recording.times)
    held = np.zeros(len(times), bool)
    for start, end in presses.times:
        held |= (times >= start - margin) & (times <= end + margin)
    return 2 + np.flatnonzero(stands_out & ~held)


def _with_memory(
    calibration: SkinCalibration, recording: Recording, reference: np.ndarray, presses: Presses
) -> SkinCalibration:
    """`calibration` with the skin's memory fitted to the session's readings, the presses' holds
    known (`diffeit.fit.memory_from_press_readings`); their depths and bends from the
    calibrated model (`_depths_and_bends`)."""
    at_rest = calibration.signed(np.atleast_2d(reference).mean(axis=0))
    dv, depths, bends = _press_depths(calibration, recording, reference, presses)
    # Each frame's part along the reference is dropped: a common gain cannot move the fit, neither
    # a drift nor the part of the skin's lasting changes that `drift_corrected` took for one (on a
    # simulated skin with memory, a 1% drift found in every session biased the relaxation by 2
    # standard errors).
    direction = at_rest / np.linalg.norm(at_rest)
    dv = dv - np.outer(dv @ direction, direction)
    fit = memory_from_press_readings(dv, recording.times, presses.times, depths, bends=bends, throw=False)
    notes = list(calibration.warnings)
    if failed(fit.result).any():
        notes.append(f"the memory fit to the presses did not converge ({names(fit.result)[0]}): no memory")
        return eqx.tree_at(lambda c: c.warnings, calibration, tuple(notes))
    values = {f"memory.{name}": np.atleast_1d(float(getattr(fit.memory, name))) for name in fit.standard_errors}
    errors = {f"memory.{name}": np.atleast_1d(float(error)) for name, error in fit.standard_errors.items()}
    # A field at a bound of its range (a time constant of 0, a fraction of 0 or 1) has no finite error.
    unsure = tuple(name for name, error in errors.items() if not np.isfinite(error[0]))
    if unsure:
        notes.append(
            f"the presses did not determine the memory ({', '.join(unsure)} without a finite standard error, "
            "a field at a bound of its range): presses held for longer than the memory's time constants, with rests "
            "as long between them, determine it"
        )
    return eqx.tree_at(
        lambda c: (c.memory, c.values, c.standard_errors, c.fitted, c.undetermined, c.warnings),
        calibration,
        (
            fit.memory,
            {**calibration.values, **values},
            {**calibration.standard_errors, **errors},
            {**calibration.fitted, "presses": (*calibration.fitted["presses"], "memory")},
            (*calibration.undetermined, *unsure),
            tuple(notes),
        ),
        is_leaf=lambda node: node is None,
    )


def _press_depths(
    calibration: SkinCalibration, recording: Recording, reference: np.ndarray, presses: Presses
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The signed differences dv (T, M_used) of the recording's frames from the reference
    frames' mean, and each press's depth and bend (K,) under its disc (`presses` in the mesh's
    frame) at the calibrated model (`_depths_and_bends`)."""
    dv = calibration.signed(recording.frames) - calibration.signed(np.atleast_2d(reference).mean(axis=0))
    patterns = _press_patterns(calibration.model.mesh, presses)
    held = _held_frames(presses, recording.times)
    noise = calibration.noise
    before = _before(held) if noise is None else _rests(dv, 0.0, held, noise, calibration.noise_frames)
    depths, bends = _depths_and_bends(calibration.model, calibration.background, patterns, dv, held, before)
    return dv, depths, bends


def _held_frames(presses: Presses, times: np.ndarray) -> np.ndarray:
    """(T, K) bool, the frames (at `times`) each press holds."""
    return np.stack([np.isin(np.arange(len(times)), chosen) for chosen in presses.frames(times)], 1)


def _held_means(values: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """(K, M) the mean of the rows of `values` (T, M) that each column of `frames` (T, K, bool)
    marks; zero for a column that marks none."""
    return (frames.T @ values) / np.maximum(frames.sum(axis=0), 1)[:, None]


def _before(held: np.ndarray) -> np.ndarray:
    """(T, K) the frames just before each press (`held` (T, K)): of the run of frames no press
    holds up to its first held frame, the last `_HELD_FRAMES` at most (none for a press that
    follows another's hold at once). Without the readings' noise to tell a rest by
    (`_rests`)."""
    free = ~held.any(axis=1)
    before = np.zeros_like(held)
    for press, column in enumerate(held.T):
        frame = int(np.argmax(column)) - 1
        while frame >= 0 and free[frame] and before[:, press].sum() < _HELD_FRAMES:
            before[frame, press] = True
            frame -= 1
    return before


def _rests(
    signed: np.ndarray, at_rest: np.ndarray, held: np.ndarray, noise: np.ndarray, noise_frames: int
) -> np.ndarray:
    """(T, K) the rest frames before each press (`held` (T, K)) in `signed` (T, M): of the run of
    frames no labelled press holds up to its first held frame, those that stand within the
    readings' `noise` (M,; from `noise_frames` frames) of the run's quietest frame (the least
    changed from `at_rest` (M,)), by the voltage test's statistic at `_REST_MOVED`, and have
    not moved from it towards the press (their whitened change along the press's, in standard
    deviations, at most `_REST_TOWARD`: a faint press's onset passes the test over every
    reading); the last `_HELD_FRAMES` of them.

    A frame a press changes is no rest. The labelled presses may be some of the session's: of
    a random 50 of 110 on the calibration benchmark's skin, 19 had been read against other
    presses (the last frames before them, labelled or not). A press labelled at an instant is
    often held over the frames about it: its onset had been its rest (presses held 5 frames
    read 4.7 mm off, 4 of 40 missed; now 2.8 mm, 3.1 labelled with their holds). A frame a
    board garbled stands apart too. What a skin's memory leaves is alike from frame to frame."""
    free = ~held.any(axis=1)
    changed = _statistic(signed - at_rest, noise, noise_frames, 1.0 + 1.0 / noise_frames)
    rests = np.zeros_like(held)
    for press, column in enumerate(held.T):
        end = start = int(np.argmax(column))
        while start > 0 and free[start - 1]:
            start -= 1
        if start == end:
            continue
        run = np.arange(start, end)
        quietest = signed[run[np.argmin(changed[run])]]
        alike = _statistic(signed[run] - quietest, noise, noise_frames, 2.0) <= _REST_MOVED
        # A press's onset, too faint for the test over every reading, shows along its change.
        toward = _whitened(signed[column].mean(axis=0) - quietest, noise, None)[0]
        toward /= max(float(np.linalg.norm(toward)), 1e-300)
        along = _whitened(signed[run] - quietest, noise, None) @ toward / np.sqrt(2.0 * (1.0 + 1.0 / noise_frames))
        rests[run[alike & (along <= _REST_TOWARD)][-_HELD_FRAMES:], press] = True
    return rests


def _fitted_changes(
    calibration: SkinCalibration, recording: Recording, presses: Presses, reference: np.ndarray
) -> np.ndarray:
    """(K, M_used) the presses' differences `_fit_presses` fits: `_press_changes` of the
    recording's frames in the first stage's signs, divided by the calibration's gains."""
    first, gains = calibration.first_stage, np.asarray(calibration.readout.gains)
    return _press_changes(
        first.signed(recording.frames) / gains,
        first.signed(np.atleast_2d(reference).mean(axis=0)) / gains,
        presses,
        recording.times,
        calibration.noise,
        calibration.noise_frames,
    )


def _press_changes(
    signed: np.ndarray,
    at_rest: np.ndarray,
    presses: Presses,
    times: np.ndarray,
    noise: np.ndarray | None,
    noise_frames: int,
) -> np.ndarray:
    """(K, M) each press's change in the readings: the mean of its frames in `signed` (T, M;
    at `times`) less the rest before it. That rest is the reference frames' mean `at_rest`
    (M,), or the mean of the rest frames before the press (`_rests`) where it has moved from
    the reference beyond the readings' `noise` (M,; from `noise_frames` reference frames): its
    standardised sum of squared whitened differences (`diffeit.touch`'s voltage test, each term
    F(1, n - 1) for noise alone, over every reading) exceeds `_REST_MOVED`. What earlier
    presses left there (a skin's memory) is then not read as this press's: a press's disc does
    not explain it, and the presses' fit had bent the readout's mixing and the contact
    impedances to it. Without the noise, the reference."""
    held = _held_frames(presses, times)
    changes = _held_means(signed, held) - at_rest
    if noise is None:
        return changes
    before = _rests(signed, at_rest, held, noise, noise_frames)
    count = before.sum(axis=0)
    rests = _held_means(signed, before) - at_rest
    variance = (1.0 / np.maximum(count, 1) + 1.0 / noise_frames)[:, None]
    moved = (count > 0) & (_statistic(rests, noise, noise_frames, variance) > _REST_MOVED)
    return changes - np.where(moved[:, None], rests, 0.0)


def _depths_and_bends(
    model: ForwardModel,
    background: float | np.ndarray,
    patterns: np.ndarray,
    dv: np.ndarray,
    held: np.ndarray,
    before: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Each press's depth (K,) dsigma/sigma and bend (K,) b, from the readings `dv` (T, M) at
    `model`: its held frames' mean (`held` (T, K)) less that of the frames just before it
    (`before` (T, K); the reference's, 0, where none), so that what earlier presses left of the
    skin's memory is not read as this one's depth (on a skin pressed once a second, their
    lasting changes had read the presses of -0.3 as -0.7 to -2.6). With s = J p the linear
    readings of footprint p and the model's readings under depth a, s.dv(a) / (a s.s) =
    1 / (1 + b a). The linear amplitude a_lin = d / (1 + b d) gives the depth, b taken at it
    (twice: b changes slowly with the depth); no deeper than -`_DEEPEST` (a conductivity > 0)."""
    sigma = jnp.broadcast_to(jnp.asarray(background, float), (model.mesh.n_elements,))
    at_rest = np.asarray(model.measure(sigma))
    linear = np.asarray(model.jacobian(sigma, wrt="log_conductivity")) @ patterns.T  # (M, K)
    norms = np.maximum(np.sum(linear**2, axis=0), np.finfo(float).tiny)
    change = _held_means(dv, held) - _held_means(dv, before)
    amplitude = np.sum(linear * change.T, axis=0) / norms
    # A press too faint to read keeps a small depth of the presses' sign: its column stays a time course.
    sign = np.sign(np.median(amplitude)) or -1.0
    amplitude = np.where(np.abs(amplitude) < _FAINTEST, sign * _FAINTEST, amplitude)
    depths, bends = np.maximum(amplitude, -_DEEPEST), np.zeros_like(amplitude)
    for _ in range(2):
        pressed = sigma * (1 + jnp.asarray(depths[:, None] * patterns))
        contact = jnp.broadcast_to(model.contact_impedance, (len(depths), *model.contact_impedance.shape))
        readings = np.asarray(_batched_readings(model, pressed, contact)) - at_rest  # (K, M)
        ratio = np.sum(linear.T * readings, axis=1) / (depths * norms)
        bends = (1 / np.clip(ratio, _BEND_RATIO, 1 / _BEND_RATIO) - 1) / depths
        depths = np.maximum(amplitude / np.maximum(1 - bends * amplitude, _BEND_RATIO), -_DEEPEST)
    return depths, bends


def _read_presses(
    calibration: SkinCalibration,
    recording: Recording,
    presses: Presses,
    reference: np.ndarray,
    hyperparameter: float | None,
    polarity: int | None,
) -> tuple[Any, np.ndarray, float, int]:
    """Each press's touch read from its one-step image at the calibrated model: the `Touches`
    (its strongest hill, read however low: a press is known to be there), how high its image's
    highest further hill stands beside it (K,; 0 for none), the hyperparameter (None:
    `auto_hyperparameter` on the presses), and the touches' polarity (None: the sign of the
    presses' median extreme change). Each press is imaged from its change against the rest
    before it (`_press_changes`)."""
    signed_reference = calibration.signed(np.atleast_2d(reference).mean(axis=0))
    dv = _press_changes(
        calibration.signed(recording.frames),
        signed_reference,
        presses,
        recording.times,
        calibration.noise,
        calibration.noise_frames,
    )
    level = calibration.background
    problem = LinearisedProblem(calibration.model, "noser", level, contact_impedance_spread=calibration.imaging_spread)
    if hyperparameter is None:
        hyperparameter, _ = auto_hyperparameter(calibration.model, dv, "noser", level, problem=problem)
    solver = OneStep(
        calibration.model,
        problem.prior,
        hyperparameter,
        level,
        contact_impedance_spread=problem.contact_impedance_spread,
        problem=problem,
    )
    images = np.asarray(solver.solve(dv, throw=True).value) / level
    if polarity is None:
        polarity = polarity_of(images)
    # Each press's touch as `diffeit.touches` finds it: on the image divided by its noise, where known.
    mesh, touched = calibration.model.mesh, np.ones(len(images), bool)
    noise = _one_step_noise(solver, calibration.noise, level)
    found = read(mesh, images, max_touches=1, polarity=polarity, touched=touched, image_noise=noise)
    # The ringing (`_with_position_map`): the further hills read on the image itself, however
    # low beside the highest (the model's errors ring in proportion to a touch, whatever the noise).
    rung = read(mesh, images, max_touches=2, polarity=polarity, touched=touched, relative=0.0)
    further = np.where(rung.count > 1, rung.depth[:, 1] / rung.depth[:, 0], 0.0)
    return found, further, float(hyperparameter), polarity
