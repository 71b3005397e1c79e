"""From a recording to images in one call (`reconstruct`), and the calibration of the model to
the recording's reference that it rests on (`calibrate_to_reference`).

## Which differences

- "calibrated": dV = V - V_ref in the recording's units, signed as in step 3, against the
  Jacobian of the calibrated model, whose level absorbed the unit. One factor for all
  readings: nothing is divided by a reading that sits near zero.
- "normalised": dV / V_ref times the calibrated model's voltages V_h, reading by reading: a
  gain g = V_ref / V_h per reading, which cancels an instrument's per-channel gains but blows
  up where V_ref is near zero or has the other sign. Readings whose g is not positive or is
  more than 30 times off the median g, or where V_ref or V_h is under 5% of its RMS, are
  masked (and reported): the Montreal gains span 12x, a reference reading near zero makes
  hundreds.
- "auto" (the default): with a skin calibration given (`calibration=`, `diffeit.calibrate`),
  "calibrated" when its model follows the reference at all (correlation at least 0.5): the
  calibration fitted what its session determines, and on a simulated skin the gains per reading
  barely moved the touches while a ratio per reading carried the model's error into the data
  (docs/tutorials/calibration.md); on a real skin whose model correlated 0.77 with its
  reference, calibrated differences placed presses at 20 mm, normalised ones at 28.5 mm. Below
  0.5 (the Montreal tank, -0.48) "normalised": the rod's path spread 0.7% of its radius against
  2.7% with calibrated differences. Without one (the model calibrated and refined here),
  "calibrated" when it reproduces the reference (correlation at least 0.9), else "normalised":
  then the reference is not what the model predicts, and gains per reading are the
  explanation left (measured on the real tanks:
  docs/tutorials/real-recordings.md#which-differences).

## Hyperparameter "auto"

The corner of the L-curve of the calibrated, normalised one-step problem, from all frames at
once (`diffeit.inverse.select_hyperparameter(..., "lcurve")`) but damaged ones: a frame whose
differences' norm exceeds half the reference's, or whose readings are the reference's moved
one or two places along (`_readings_moved`), is a board's glitch (a frame of zeros, one at
another gain, a reading lost or gained in its stream), not a touch, and alone it would place
the corner (one such frame among 70 of a simulated skin took the median press error from 0.04
to 0.15 of the radius); they are listed in the choice as "frames_left_out" and imaged as
they are. A named selection method leaves them out too. When the corner sits within a decade
of an end of the candidates, the noise figure 0.5 instead
(`diffeit.calibration.auto_hyperparameter`). Gauss-Newton iterates to the regularised
minimiser and fits more of the noise than one linear step: its "auto" is 4 times the
one-step's value. Total variation keeps the one-step's value; GREIT is designed for noise
figure 0.5. How the rules were chosen, measured on the real tanks:
docs/tutorials/real-recordings.md#the-hyperparameter-auto.

## Solvers

`reconstruct` images with a solver object of `diffeit.inverse` (`OneStep`, `GaussNewton`,
`TotalVariation`, `GREIT`), built with or without a model: it builds the calibrated model
itself and binds the solver to it and to the calibrated background (`solver.bound(model,
background, hyperparameter=...)`). The `method` strings are shorthands for solvers with their
defaults.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from typing import Any, Literal

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from ._arrays import uncertain_sign
from ._messages import name_indices
from ._threads import host_algebra
from .calibration import (
    CalibrationWarning,
    DrivenReadings,
    SkinCalibration,
    auto_difference,
    auto_hyperparameter,
    calibrate_to_reference,
    calibrated_reference_frames,
    default_mesh,
    drift_corrected,
    drift_note,
    glitched_frames,
    held_lost_readings,
    lost_note,
    reading_spread,
    reference_frames,
    refine_to_reference,
    untouched_run,
)
from .fit import JointImaging
from .fit import background as fit_background
from .forward import ForwardModel
from .inverse import (
    CONTACT_IMPEDANCE_SPREAD,
    GREIT,
    AbsoluteGaussNewton,
    AbstractSolver,
    GaussNewton,
    LinearisedProblem,
    OneStep,
    TotalVariation,
)
from .io import Recording
from .mesh import Mesh
from .results import RESULTS, failed, names, throw_if_failed
from .touch import _one_step_noise, reading_projection, subspace_statistic

Method = Literal["one_step", "gauss_newton", "total_variation", "greit"]
Difference = Literal["auto", "calibrated", "normalised"]
METHODS = ("one_step", "gauss_newton", "total_variation", "greit")
SELECTION_METHODS = ("auto", "gcv", "lcurve", "noise_figure")

# Normalised differences mask readings whose gain V_ref / V_model is this many times off the median.
_LARGEST_GAIN = 30.0
# Gauss-Newton's "auto" hyperparameter over the one-step's (module docstring, "Hyperparameter").
_GAUSS_NEWTON_FACTOR = 4.0
# The solver each method names, and GREIT's design when its hyperparameter is "auto".
_METHOD_SOLVERS = {"one_step": OneStep, "gauss_newton": GaussNewton, "total_variation": TotalVariation, "greit": GREIT}
_GREIT_NOISE_FIGURE = 0.5
# Frames per solve: one-step and GREIT in batches (one product and one progress step each), total
# variation frame by frame (a progress step each), Gauss-Newton (and any other solver) all at once.
_CHUNKS = {OneStep: 256, GREIT: 256, TotalVariation: 1}


@host_algebra
def reconstruct(
    recording: Recording,
    *,
    method: Method | None = None,
    solver: AbstractSolver | None = None,
    prior: str | None = None,
    hyperparameter: float | str | None = None,
    calibrate: bool = True,
    calibration: SkinCalibration | None = None,
    mesh: Mesh | None = None,
    h: float | None = None,
    reference_frame: int | None = None,
    difference: Difference = "auto",
    driven_readings: DrivenReadings = "auto",
    background_map: bool = False,
    background: float = 1.0,
    contact_impedance: float = 0.01,
    max_iterations: int | None = None,
    progress: bool = True,
    throw: bool = True,
) -> Recording:
    """Image every frame of a recording against its reference: recorded frames to images in one call.

    The reference is the recording's, its frame `reference_frame`, or, when it has none, the
    mean of its first frames up to the first that looks touched, however few (where its first
    frame or two look touched, as a board's first frames after it connects may, the untouched
    run after them; `reference_frames`; with a `calibration`, unless one of them looks touched
    against the calibration's reference: then the frames within its noise, or that reference,
    `calibrated_reference_frames`). Their spread, from 6 frames or more, is kept in the
    provenance as "reading_noise", the noise `diffeit.touches` tests frames against without a
    calibration, with the calibrated model's projection of raw differences onto where a touch
    puts them ("touch_projection", `diffeit.touch.reading_projection`); with it, or with a
    calibration's noise, one-step images keep each element's noise as "image_noise"
    (`diffeit.touch.image_noise`), on which `diffeit.touches` finds the hills. Without either,
    how far each frame stands out of its own noise is kept as
    "touch_statistic" (`diffeit.touch.subspace_statistic`, at the calibrated model), on which
    `diffeit.touches` tells touched frames. An electrode lost during the recording (half the
    readings on it broken from some frame on, the others not: `lost_electrodes`) is warned of,
    and the readings on it are masked in every frame ("lost_electrodes", "lost_frames" and
    "lost_readings" in the provenance; `diffeit.touches` leaves them out); without that, each
    frame after it went would be a glitch, read as no touch. Where the frames drift beyond the
    reference's jitter, every frame is divided by its common gain against the reference
    (`drift_corrected`), the gains kept as "frame_gains", their range warned of, and the
    returned recording's frames the corrected ones. The model
    (the sheet `mesh`, else `default_mesh(recording, h)`; the recording's protocol;
    `contact_impedance` at `background`) is calibrated to it by `calibrate_to_reference` (level, orientation, signs of
    magnitudes, driven readings, broken channels; its warnings are issued as
    `CalibrationWarning`) and refined as `diffeit.calibrate` refines a session without presses
    (a contact impedance per electrode, the readout's source and far mixing weights), or instead
    a smooth background map is fitted to it (`diffeit.fit.background`, which fits the level and
    contacts its own way). The frames' differences (module docstring, "Which differences") are
    then imaged at that state by the solver: a solver object's settings bound to the calibrated
    model and background (`solver.bound(model, background)`), or the solver a `method` names.
    The choices and their measurements on real tanks are in docs/tutorials/real-recordings.md.

    Arguments:
        recording: The frames, with their protocol (and reference, mesh or geometry).
        method: A shorthand for a solver: "one_step" (`OneStep` with `prior`, the default,
            each electrode's contact impedance free to change between the reference and a
            frame with the prior spread `diffeit.inverse.CONTACT_IMPEDANCE_SPREAD` in ln z,
            so that a contact's drift is not imaged; a `OneStep` solver object brings its own,
            0 unless given),
            "gauss_newton" (`GaussNewton` with `prior`), "total_variation" (`TotalVariation`)
            or "greit" (`GREIT`, 32 x 32 pixels, designed for noise figure 0.5 when the
            hyperparameter is "auto"). Not together with `solver`.
        solver: A solver object (`OneStep`, `GaussNewton`, `TotalVariation`, `GREIT`; built
            with or without a model): its settings are used, on the calibrated model and
            background. Not a normalised `OneStep` (use `difference="normalised"`),
            `AbsoluteGaussNewton` nor the joint fit's `diffeit.fit.JointImaging` (call its
            `solve` on the recording's frames, or `diffeit fit`).
        prior: The prior of "one_step" and "gauss_newton" (default "noser"); a solver object
            brings its own.
        hyperparameter: Unit-free, or "auto" (module docstring), or a method of
            `diffeit.inverse.select_hyperparameter` ("gcv", "lcurve", "noise_figure"),
            chosen from all frames at once but damaged ones (module docstring). None: "auto"
            for a `method`, the solver's own for a solver object (a value or rule given
            replaces it).
        calibrate: Calibrate and refine the model to the reference (`diffeit.calibrate`
            without presses); False keeps the nominal model, signing magnitudes only.
        calibration: A `diffeit.calibration.SkinCalibration` of this skin and board (from
            `diffeit.calibrate`): images at its model, mesh and gains; with a position map
            from labelled presses, one-step images at the contact spread the map was fitted
            at and by default at its hyperparameter (without one, where the presses'
            cross-validation chose no map, the hyperparameter is chosen from the recording's
            own frames as usual: measured on
            `benchmarks/calibration.py`'s skins, the presses' choice then read test presses
            worse in four of five sessions, by up to 1.2 mm).
        mesh: The sheet to image on; None for `default_mesh(recording, h)`.
        h: Element size of the default mesh, m.
        reference_frame: Image against this frame instead of the recording's reference.
        difference: "auto", "calibrated" or "normalised" (module docstring).
        driven_readings: "auto", "keep" or "drop" the readings on driven electrodes.
        background_map: Fit a smooth background map (and, with driven readings kept, one
            contact impedance per electrode) to the reference and image at that map;
            relative images are then dsigma over the map.
        background: The nominal background conductivity, S/sq.
        contact_impedance: The nominal contact impedance, ohm m.
        max_iterations: The iteration limit of "gauss_newton" and "total_variation" (None:
            theirs, 20 and 100); a solver object brings its own.
        progress: Show progress bars.
        throw: Raise for a frame that failed (True), or record its code (False).

    Returns:
        The recording with `mesh`, `images` (T, E) and `image_quantity` filled in; its frames
        and reference as recorded (a recording without one gets the reference it was imaged
        against). With volts (`voltage_unit="V"`) the images are conductivity changes dsigma,
        S/sq; in any other unit relative changes dsigma / sigma_h (unit-free). The
        provenance's metadata holds the calibration (its `summary()`), the
        method, prior, hyperparameter and how it was chosen (with what each selection method
        gives and its code's name), every option, and the outcome: "results", the name of
        each frame's `diffeit.results.RESULTS` code (the solver's; `nonfinite` for an image
        that is not finite, which is then zero), "frames_failed", how many are not
        "successful", "damaged_frames", the frames whose differences exceed half the
        reference or whose readings are moved along (imaged as they are; `diffeit.touches`
        reads no touch on them), and the
        background map's code in `["background_map"]["result"]`.

    Raises:
        ValueError: For a recording without frames, a bad option, or a reference the model
            cannot be calibrated on.
        diffeit.results.SolverError: With `throw=True`, for a frame that failed or a background
            map whose fit failed (a selection at an end of its candidates, of the
            hyperparameter or of the map, never raises: its code is in the metadata).
    """
    start = time.perf_counter()
    if not isinstance(recording, Recording):
        raise ValueError(f"reconstruct takes a diffeit.io.Recording; got {type(recording).__name__}")
    if recording.n_frames == 0:
        raise ValueError("the recording holds no frames")
    if difference not in ("auto", "calibrated", "normalised"):
        raise ValueError(f'difference must be "auto", "calibrated" or "normalised"; got {difference!r}')
    if isinstance(hyperparameter, str) and hyperparameter not in SELECTION_METHODS:
        raise ValueError(
            f"hyperparameter must be a positive number or one of {SELECTION_METHODS}; got {hyperparameter!r}"
        )
    numeric = hyperparameter is not None and not isinstance(hyperparameter, str)
    if numeric and not (math.isfinite(hyperparameter) and hyperparameter > 0):
        raise ValueError(f"hyperparameter must be finite and positive; got {hyperparameter}")
    given = calibration is not None
    shorthand = solver is None
    # A position map was fitted on one-step images made at its calibration's contact spread.
    spread = calibration.contact_impedance_spread if _maps_positions(calibration) else CONTACT_IMPEDANCE_SPREAD
    solver, method = _unbound_solver(method, solver, prior, max_iterations, spread)
    if shorthand:
        prior = "noser" if prior is None else prior
        hyperparameter = "auto" if hyperparameter is None else hyperparameter
    else:
        prior = getattr(solver, "prior", None)
    if calibration is not None:
        _check_calibration(calibration, recording, mesh, h)
        mesh = calibration.model.mesh
    mesh = default_mesh(recording, h) if mesh is None else mesh
    # Electrodes lost during the recording (come off the skin, a connector come loose): the
    # readings on them hold their values from before, and are masked below.
    recorded = recording
    recording, lost, lost_frames, lost_readings = held_lost_readings(recording)
    reference_set, reference_source, averaged = _reference_set(recording, reference_frame, calibration)
    reference = reference_set.mean(axis=0)
    # The readings' spread over the reference frames, when the reference is the mean of enough of
    # the recording's own frames: `diffeit.touches` tests frames against it without a calibration.
    from_frames = recording.reference is None and reference_frame is None
    spread = reading_spread(reference_set) if from_frames else None
    frame_gains = None
    if spread is not None:  # a drift's common gain out of every frame (`drift_corrected`)
        recording, frame_gains = drift_corrected(recording, reference_set, ~lost_readings)
        if frame_gains is not None:  # the reference frames, and their spread, without the drift
            reference_set, reference_source, averaged = _reference_set(recording, reference_frame, calibration)
            reference = reference_set.mean(axis=0)
            spread = reading_spread(reference_set)
    if calibration is None:
        nominal = ForwardModel(mesh, recording.protocol, contact_impedance=contact_impedance)

        def calibrated(frames: np.ndarray) -> Any:
            first = calibrate_to_reference(
                nominal,
                frames,
                readings=recording.readings,
                background=background,
                driven_readings=driven_readings,
                fit=calibrate,
            )
            # The map fits the level and contacts its own way.
            return refine_to_reference(first, frames, recording) if calibrate and not background_map else first

        calibration = calibrated(reference_set)
        # Too few frames to measure the noise on: the model tells a faint press among them.
        count = untouched_run(reference_set, calibration) if from_frames and spread is None else len(reference_set)
        if count < len(reference_set):
            reference_set, averaged = reference_set[:count], count
            reference_source = f"{reference_source}: the first {count} of them, the model sees a touch in the next"
            reference = reference_set.mean(axis=0)
            calibration = calibrated(reference_set)
    notes = calibration.warnings if frame_gains is None else (*calibration.warnings, drift_note(frame_gains))
    for note in notes:
        warnings.warn(note, CalibrationWarning, stacklevel=2)
    model = calibration.model
    level = calibration.background  # the level, or a calibration's background map (E,)
    frames = calibration.signed(recording.frames)
    signed_reference = calibration.signed(reference)
    if shorthand and method == "one_step" and hyperparameter == "auto" and _maps_positions(calibration):
        hyperparameter = calibration.hyperparameter  # the position map was fitted on images made at it
    map_summary = None
    if background_map:
        fitted = fit_background(
            model,
            signed_reference,
            estimate_contact_impedance=calibration.driven_readings == "kept",
            progress=progress,
            throw=False,
        )
        # At the boundary the misfit levelled off (the model's own error): the map is the selection's
        # best, as a hyperparameter at an end of its candidates is; a failed solve is no map.
        if throw and bool(fitted.result != RESULTS.selection_at_boundary):
            throw_if_failed(fitted, fitted.result, "the background map's fit (diffeit.fit.background)")
        model, level = model.replace(contact_impedance=fitted.contact_impedance), fitted.conductivity
        map_summary = {
            "misfit": fitted.misfit,
            "hyperparameter": fitted.hyperparameter,
            "result": names(fitted.result)[0],
            "range": [float(level.min()), float(level.max())],
        }
    differences = frames - signed_reference
    readings = np.flatnonzero(calibration.used)  # the recording's index of each reading imaged
    lost_readings &= calibration.used  # the readings imaged that are on a lost electrode: masked
    on_lost = lost_readings[calibration.used]
    if lost:
        warnings.warn(
            f"{lost_note(lost, lost_frames, 'recording')}: the {int(on_lost.sum())} readings on them are masked in "
            "every frame",
            CalibrationWarning,
            stacklevel=2,
        )
        model = model.replace(protocol=model.protocol.select(~on_lost))
    dv, signed_reference, readings = differences[:, ~on_lost], signed_reference[~on_lost], readings[~on_lost]
    # Damaged frames are imaged as they are, but a selection over every frame is theirs alone.
    damaged = glitched_frames(dv, signed_reference, recording.frames[:, ~lost_readings], reference[~lost_readings])
    # The readings' noise in the calibration's units: its own, else the reference frames' spread
    # (a lost electrode's readings with none: no test looks at them).
    noise = _reading_noise(calibration, reference_set if spread is not None else None)
    noise = None if noise is None else np.where(on_lost, 0.0, noise)
    # Without it, how far each frame stands out of its own noise, for `diffeit.touches`; with it
    # and no calibration given, where this model puts a touch, for `diffeit.touches`' voltage test.
    statistic = None if noise is not None else subspace_statistic(differences, calibration)
    projection = None if given or noise is None else reading_projection(calibration, noise)
    noise = None if noise is None else noise[~on_lost]
    difference, difference_reason = (
        (difference, "given") if difference != "auto" else auto_difference(calibration, given=given)
    )
    unsafe: list[int] = []
    if difference == "normalised":
        model, dv, unsafe, noise = _normalised(model, dv, signed_reference, level, readings, noise)
    # A one-step solver images with the linearisation the hyperparameter is chosen on: built once.
    problem = (
        LinearisedProblem(model, solver.prior, level, contact_impedance_spread=solver.contact_impedance_spread)
        if isinstance(solver, OneStep)
        else None
    )
    chosen_on = dv[~damaged] if (~damaged).any() else dv
    value, choice = _hyperparameter_of(
        solver, model, chosen_on, hyperparameter, "noser" if prior is None else prior, level, problem
    )
    if damaged.any() and (~damaged).any() and choice.get("rule") in ("auto", "given method"):
        choice = {**choice, "frames_left_out": np.flatnonzero(damaged).tolist()}
    if isinstance(solver, GREIT) and hyperparameter == "auto":
        solver = solver.bound(model, level, noise_figure=_GREIT_NOISE_FIGURE)
    elif problem is not None:
        solver = OneStep(
            model,
            solver.prior,
            solver.hyperparameter if value is None else value,
            level,
            contact_impedance_spread=solver.contact_impedance_spread,
            problem=problem,
        )
    else:
        solver = solver.bound(model, level, hyperparameter=value)
    images, codes = _images(solver, dv, progress)
    # Each element's noise in the one-step images, for `diffeit.touches`.
    element_noise = _one_step_noise(solver, noise, level) if isinstance(solver, OneStep) else None
    value = solver.hyperparameter
    codes = _nonfinite_marked(codes, images)
    if throw:
        throw_if_failed(images, codes, f"{method} reconstruction")
    images = np.where(np.isfinite(images).all(axis=1, keepdims=True), images, 0.0)  # a Recording's are finite
    relative = recording.voltage_unit != "V"
    if relative:
        images = images / level
    metadata = {
        "method": method,
        "prior": prior if prior is None or isinstance(prior, str) else repr(prior),
        "hyperparameter": value,
        "hyperparameter_choice": choice,
        # One-step images: each contact's prior spread in ln z (0: the contacts held).
        "contact_impedance_spread": solver.contact_impedance_spread if isinstance(solver, OneStep) else None,
        "max_iterations": max_iterations if shorthand else getattr(solver, "max_iterations", None),
        "results": names(codes),
        "frames_failed": int(failed(codes).sum()),
        # Frames whose differences exceed half the reference: a glitch; `diffeit.touches` reads none.
        "damaged_frames": np.flatnonzero(damaged).tolist(),
        # Electrodes lost during the recording, the frames they were lost in, and the readings on
        # them (the recording's indices), masked in every frame; `diffeit.touches` leaves them out.
        "lost_electrodes": list(lost),
        "lost_frames": np.flatnonzero(lost_frames).tolist(),
        "lost_readings": np.flatnonzero(lost_readings).tolist(),
        "difference": difference,
        "difference_reason": difference_reason,
        "unsafe_ratio_readings": unsafe,
        "reference": reference_source,
        # How many frames the reference is the mean of; None for the recording's own (unknown).
        "reference_frames": None if recording.reference is not None and reference_frame is None else averaged,
        "noise_frames": 0 if spread is None else len(reference_set),
        "reading_noise": None if spread is None else spread.tolist(),
        "image_noise": None if element_noise is None else element_noise.tolist(),
        "touch_statistic": None if statistic is None else statistic.tolist(),
        "touch_projection": None if projection is None else projection.tolist(),
        "frame_gains": None if frame_gains is None else frame_gains.tolist(),
        "calibrated": bool(calibrate) or given,
        "calibration": calibration.summary(),
        "background_map": map_summary,
        "background": background,
        "contact_impedance": contact_impedance,
        "readings": recording.readings,
        "input_source": recording.provenance.get("source", ""),
        "seconds": round(time.perf_counter() - start, 3),
    }
    if lost:  # the frames as recorded (divided by the drift's gains where taken out)
        frames = recorded.frames if frame_gains is None else recorded.frames / frame_gains[:, None]
        recording = dataclasses.replace(recording, frames=frames)
    return dataclasses.replace(
        recording,
        reference=reference if recording.reference is None else recording.reference,  # the recorded one is kept
        mesh=mesh,
        images=images,
        image_quantity="relative conductivity change" if relative else "conductivity change",
        provenance={"source": f"diffeit.reconstruct ({method})", "metadata": metadata},
    )


def _reference_set(
    recording: Recording, reference_frame: int | None, calibration: SkinCalibration | None
) -> tuple[np.ndarray, str, int]:
    """(R, M) the frames a recording is imaged against, as recorded; their description; how many
    frames their mean stands for: `reference_frames`, or with a calibration given and no
    reference named, `calibrated_reference_frames`."""
    if calibration is None or recording.reference is not None or reference_frame is not None:
        frames, source = reference_frames(recording, reference_frame)
        return frames, source, len(frames)
    return calibrated_reference_frames(recording, calibration)


def _reading_noise(calibration: Any, reference_set: np.ndarray | None) -> np.ndarray | None:
    """The readings' noise in the units of `calibration.signed`: the calibration's own (a
    `SkinCalibration` from 6 or more reference frames), else the spread of the
    `reference_set` (R, M) when it holds 6 or more frames; None without either."""
    noise = getattr(calibration, "noise", None)
    if noise is None and reference_set is not None:
        noise = reading_spread(calibration.signed(reference_set))
    return noise


def _check_calibration(calibration: SkinCalibration, recording: Recording, mesh: Mesh | None, h: float | None) -> None:
    """ValueError for a calibration that is not one, or is for another protocol or kind of
    reading than the recording's, or given with a mesh of its own."""
    if not isinstance(calibration, SkinCalibration):
        raise ValueError(f"calibration must be a diffeit.calibration.SkinCalibration; got {type(calibration).__name__}")
    if calibration.protocol != recording.protocol:
        raise ValueError("the calibration is for another protocol than the recording's")
    if calibration.readings != recording.readings:
        raise ValueError(
            f"the calibration is for {calibration.readings} readings; the recording's are {recording.readings}"
        )
    # A recording with a geometry is imaged on that geometry's mesh (a simulation's mesh is finer):
    # only a recording that brings the mesh it is imaged on must match the calibration's.
    if recording.geometry is None and recording.mesh is not None and recording.mesh != calibration.model.mesh:
        raise ValueError("the calibration is for another mesh than the recording's")
    if mesh is not None or h is not None:
        raise ValueError("a calibration brings its mesh: give no mesh or h with it")


def _normalised(
    model, dv, reference, level, readings: np.ndarray, noise: np.ndarray | None
) -> tuple[ForwardModel, np.ndarray, list[int], np.ndarray | None]:
    """The model and data of normalised differences: dV / V_ref times the calibrated model's
    voltages V_h, a gain g = V_ref / V_h per reading. Readings whose gain is not positive or is
    more than `_LARGEST_GAIN` times off the median gain, or where V_ref or V_h is under 5% of
    its RMS, are masked (their indices in the recording returned): there the ratio would blow
    up, flip a sign or divide noise by noise. The readings' `noise` (or None) as the data's;
    `readings` the recording's index of each."""
    voltages = np.asarray(model.measure(jnp.broadcast_to(jnp.asarray(level), (model.n_elements,))))
    gain = reference / voltages
    positive = gain > 0
    # A ratio of two near-zero numbers says nothing: such readings go too, whatever their ratio.
    small = uncertain_sign(voltages) | uncertain_sign(reference)
    off = np.abs(np.log(np.where(positive, gain, 1.0) / np.median(gain[positive]))) > np.log(_LARGEST_GAIN)
    safe = positive & ~off & ~small
    if not safe.any():
        raise ValueError("no reading of the reference has the model's sign: normalised differences are meaningless")
    unsafe = readings[~safe].tolist()
    if unsafe:
        warnings.warn(
            f"normalised differences: readings {name_indices(np.array(unsafe))} masked, their reference is near zero "
            f"or disagrees with the model in sign or by more than a factor of {_LARGEST_GAIN:g}",
            CalibrationWarning,
            stacklevel=3,
        )
        model = model.replace(protocol=model.protocol.select(safe))
    return model, (dv / gain)[:, safe], unsafe, None if noise is None else (noise / gain)[safe]


def _hyperparameter(model, dv, hyperparameter, prior, level, problem) -> tuple[float, dict[str, Any]]:
    """The value and how it was chosen (`diffeit.calibration.auto_hyperparameter`, on `problem`
    when one is built)."""
    if not isinstance(hyperparameter, str):
        return float(hyperparameter), {"rule": "given"}
    return auto_hyperparameter(model, dv, prior, level, hyperparameter, problem=problem)


def _unbound_solver(
    method: str | None,
    solver: AbstractSolver | None,
    prior: str | None,
    max_iterations: int | None,
    contact_impedance_spread: float,
) -> tuple[AbstractSolver, str]:
    """The solver `reconstruct` binds to the calibrated model (the one `method` names, or
    `solver`) and the method's name for the metadata, after checking the options; "one_step"
    images at `contact_impedance_spread`."""
    if solver is not None:
        if method is not None:
            raise ValueError("give a method or a solver, not both")
        if isinstance(solver, JointImaging):
            raise ValueError(
                "reconstruct images differences on a model it calibrates, while the joint fit (JointImaging) fits its "
                "own background, contact impedances and memory to the readings over time: call "
                "solver.solve(recording.frames) on a JointImaging with times=recording.times, or run diffeit fit"
            )
        if not isinstance(solver, AbstractSolver) or isinstance(solver, AbsoluteGaussNewton):
            raise ValueError(
                "solver must be a difference solver of diffeit.inverse (OneStep, GaussNewton, TotalVariation, "
                f"GREIT); got {type(solver).__name__}"
            )
        if isinstance(solver, OneStep) and solver.normalised:
            raise ValueError(
                'reconstruct forms normalised differences itself (difference="normalised"): pass a OneStep with '
                "normalised=False"
            )
        if prior is not None or max_iterations is not None:
            raise ValueError("prior and max_iterations are settings of the solver object: set them there")
        names = [name for name, kind in _METHOD_SOLVERS.items() if type(solver) is kind]
        return solver, names[0] if names else type(solver).__name__
    method = "one_step" if method is None else method
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}; got {method!r}")
    if max_iterations is not None:
        if method not in ("gauss_newton", "total_variation"):
            raise ValueError(f"max_iterations applies to gauss_newton and total_variation, not {method}")
        if int(max_iterations) != max_iterations or max_iterations < 1:
            raise ValueError(f"max_iterations must be a positive integer; got {max_iterations}")
    limit = {} if max_iterations is None else {"max_iterations": int(max_iterations)}
    prior = "noser" if prior is None else prior
    if method == "one_step":
        return OneStep(prior=prior, contact_impedance_spread=contact_impedance_spread), method
    if method == "gauss_newton":
        return GaussNewton(prior=prior, **limit), method
    if method == "total_variation":
        return TotalVariation(**limit), method
    return GREIT(), method


def _maps_positions(calibration: Any) -> bool:
    """Whether `calibration` holds a position map that moves the positions read (one fitted
    on images made at its `hyperparameter`)."""
    mapping = getattr(calibration, "position_map", None)
    return (
        getattr(calibration, "hyperparameter", None) is not None and mapping is not None and mapping.degree is not None
    )


def _hyperparameter_of(
    solver: AbstractSolver, model, dv, hyperparameter, prior, level, problem: LinearisedProblem | None
) -> tuple[float | None, dict[str, Any]]:
    """The hyperparameter to bind `solver` with (None: the solver's own, or GREIT's design for a
    noise figure) and how it was chosen (module docstring, "Hyperparameter"), a selection on
    `problem` when one is built."""
    if hyperparameter is None:
        return None, {"rule": "the solver's own"}
    if isinstance(solver, GREIT) and hyperparameter == "auto":
        return None, {"rule": f"GREIT designed for noise figure {_GREIT_NOISE_FIGURE}", "method": "noise_figure"}
    value, choice = _hyperparameter(model, dv, hyperparameter, prior, level, problem)
    if isinstance(solver, GaussNewton) and hyperparameter == "auto":
        value, choice = _GAUSS_NEWTON_FACTOR * value, {**choice, "gauss_newton_factor": _GAUSS_NEWTON_FACTOR}
    return value, choice


def _images(solver: AbstractSolver, dv: np.ndarray, progress: bool) -> tuple[np.ndarray, RESULTS]:
    """(T, E) conductivity changes, S/sq, of the frames' differences `dv` by the bound
    `solver`, and the solver's code of each frame; in chunks of frames (`_CHUNKS`), a progress
    step each."""
    size = next((size for kind, size in _CHUNKS.items() if isinstance(solver, kind)), len(dv))
    starts = range(0, len(dv), size)
    unit = "frame" if size == 1 else "batch"
    bar = tqdm(starts, desc="reconstructing", unit=unit, disable=not progress or len(starts) < 2)
    solutions = [solver.solve(dv[i : i + size], throw=False) for i in bar]
    images = np.concatenate([np.asarray(solution.value) for solution in solutions])
    codes = jax.tree_util.tree_map(
        lambda *chunks: np.concatenate([np.asarray(chunk) for chunk in chunks]), *(s.result for s in solutions)
    )
    return images, codes


def _nonfinite_marked(codes: RESULTS, images: np.ndarray) -> RESULTS:
    """One code per frame of `images` (T, E): `codes` (one per frame, or one for all), with
    `RESULTS.nonfinite` where the image holds NaN or inf."""
    finite = np.all(np.isfinite(images), axis=1)
    codes = jax.tree_util.tree_map(lambda code: np.broadcast_to(code, finite.shape), codes)
    return jax.vmap(lambda ok, code: RESULTS.where(ok, code, RESULTS.nonfinite))(finite, codes)
