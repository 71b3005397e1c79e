"""`calibrate`, the calibration of a skin and board from a calibration session, in its stages: the
reference frames, the first stage, the refinement, the presses' fits and maps, the background
map and the memory; with `default_mesh` and the checks of the labelled presses (those left out
as damaged or lost, those that show no touch, those outside the recording or the skin).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import equinox as eqx
import numpy as np

from .._arrays import frame_period
from .._messages import name_indices
from ..forward import ForwardModel
from ..io import Presses, Recording, mesh_from_geometry
from ..mesh import Mesh, disc
from ..touch import SIGNIFICANCE, _statistic, subspace_statistic, touch_subspace
from ._background import _with_background_map
from ._frames import (
    _NOISE_FRAMES,
    _change_from_about,
    drift_corrected,
    drift_note,
    held_lost_readings,
    lost_note,
    reference_frames,
    untouched_run,
)
from ._held_out import (
    _LEAST_HELD_OUT,
    _fullest_unless_beaten,
    _kept_if_it_generalises,
    _label_frame,
    _map_held_out_errors,
    _not_kept,
    _press_fit,
    _too_few_to_hold_out,
    _with_position_map,
)
from ._maps import SizeMap, _spread
from ._press_fit import _moved, _skin_size
from ._presses import (
    _fitted_changes,
    _held,
    _held_frames,
    _held_means,
    _press_depths,
    _read_presses,
    _unlabelled_steps,
    _with_memory,
)
from ._reference import DrivenReadings, calibrate_to_reference
from ._refine import PRIORS, REFERENCE_GROUPS, REFERENCE_ONLY_GROUPS, _with_warnings, refine_to_reference
from ._skin import SkinCalibration

# A labelled press whose frame changes more than this, and more than this factor times the
# presses' median change, is a glitch (`_presses_left_out`): readings one place out of order
# changed a frame by 0.26 of its norm (adjacent drive) to 0.6 (opposition); the presses of the
# tests' and the benchmark's skins by at most 0.006 and 0.019, deep ones (-0.8, up to 16 mm) by
# 0.105, 5.3 times their median.
_GLITCH_CHANGE, _GLITCH_FACTOR = 0.15, 10.0


# A labelled press timed at an instant no frame lies within this fraction of the frames' median
# period of lost its frame (`_presses_left_out`): the nearest is the rest's or another press's.
# Not a half: frames' times jitter, and labels may be timed at a press's onset.
_LOST_FRAME = 0.75


# The groups fitted to the presses' differences by default, each set in turn, the last kept unless an
# earlier one reads the held-out presses significantly closer (`_fullest_unless_beaten`), and those
# that can be.
PRESS_GROUP_CHOICES = (("mixing",), ("mixing", "electrode_positions"))


_PRESS_GROUPS_POSSIBLE = ("mixing", "electrode_positions", "reading_gains", "background_map")


# Presses read a median of this fraction of the skin's size or more from their labels are
# warned of (`_far_from_labels_noted`).
_FAR_FROM_LABELS = 0.25

# Three or more presses whose labels spread (RMS about their mean) less than this fraction of
# their mean radius (their footprints all overlap) are labelled at one place (`_check_presses`):
# fitted, their frame's scale was 0 and the position map sent every touch to their place.
_LEAST_LABEL_SPREAD = 0.5


def default_mesh(recording: Recording, h: float | None = None) -> Mesh:
    """The sheet a recording is imaged on.

    Its geometry (a simulation's geometry names the reconstruction mesh, coarser than the one
    it was simulated on), else its mesh, else a unit disc with the protocol's electrodes
    (width min(0.2, pi / L)).

    Arguments:
        recording: The recording.
        h: The element size, m, of the geometry's mesh or the default disc (default 0.08 for
            the disc); not for a recording that brings its mesh.

    Returns:
        The `diffeit.Mesh`.

    Raises:
        ValueError: For `h` given with a recording that brings its mesh.
    """
    if recording.geometry is not None:
        geometry = dict(recording.geometry)
        if h is not None:
            geometry["h"] = h
        return mesh_from_geometry(geometry)
    if recording.mesh is not None:
        if h is not None:
            raise ValueError("h applies to a recording's geometry or the default disc; this recording brings its mesh")
        return recording.mesh
    n = recording.protocol.n_electrodes
    return disc(n, electrode_width=min(0.2, math.pi / n), h=0.08 if h is None else h)


def calibrate(
    recording: Recording,
    presses: Presses | None = None,
    *,
    mesh: Mesh | None = None,
    h: float | None = None,
    reference_frame: int | None = None,
    background: float = 1.0,
    contact_impedance: float = 0.01,
    driven_readings: DrivenReadings = "auto",
    priors: Mapping[str, float] | None = None,
    reference_groups: tuple[str, ...] | None = None,
    press_groups: tuple[str, ...] | None = None,
    hyperparameter: float | None = None,
    memory: bool = True,
    background_map: bool | None = None,
) -> SkinCalibration:
    """Calibrate the model of a real skin and board from a calibration session.

    From the reference frames (`reference_frames`: without a reference or presses, the frames
    of the session's first 200 that look untouched; with 6 or more, a drift of the frames'
    common gain is first taken out, `drift_corrected`, and warned of): the first stage (`calibrate_to_reference`:
    level and voltage unit, orientation, signs of magnitudes, driven readings, broken
    channels), then the refinement (package docstring): contact impedance per electrode, the
    readout's mixing, drive and channel gains, electrode positions and widths (the groups
    `reference_groups` names), with standard errors. No gain per reading is fitted to the
    reference: it cannot tell one from the model's error at that reading (presses can:
    `press_groups`).
    With presses held over several frames, the skin's memory is fitted to the whole session's
    readings with the presses' holds known (`diffeit.fit.memory_from_press_readings`), unless
    the readings step out of their noise away from every labelled hold (presses the labels do
    not hold, `_unlabelled_steps`: a warning names where).
    With labelled `presses`: the readout's mixing, and the electrode positions (and gains per
    reading when `press_groups` names them), are fitted to the presses' differences, and kept
    unless the reference's calibration reads significantly more of the presses they did not see
    closer (five folds, at least 20 presses);
    each press is imaged at the calibrated model (`diffeit.inverse.OneStep`, NOSER prior), read
    as a touch (`diffeit.touch.read`), and a `PositionMap` from read to labelled positions is
    fitted, its degree chosen by cross-validation. A press one of whose frames looks damaged
    (a board's glitch), timed where a frame is missing (`_presses_left_out`), or whose frames
    show no touch (timed off them: `_presses_unseen`, whose warning names a shift of the labels'
    clock that would see more) is left out, its press error and position NaN, with a warning
    naming it.

    Arguments:
        recording: The session: untouched frames (or a reference) and, with presses, the
            pressed frames; its protocol and `readings` are the board's.
        presses: The labelled presses (`diffeit.io.Presses`), times on the recording's clock:
            all of the session's or some (the others kept to test on: each is read against
            the rest frames before it that no press changes, `_rests`).
        mesh: The sheet; None for `default_mesh(recording, h)`.
        h: Element size of the default mesh, m.
        reference_frame: Calibrate on this frame instead of the recording's reference.
        background: The nominal background conductivity, S/sq.
        contact_impedance: The nominal contact impedance, ohm m.
        driven_readings: "auto", "keep" or "drop" the readings on driven electrodes.
        priors: Prior standard deviations replacing those of `PRIORS` (by group name; the
            electrode positions' as a fraction of the mean spacing between electrodes).
        reference_groups: The groups of `PRIORS` fitted to the reference (the level always
            is). None: `REFERENCE_GROUPS`, the contact impedances and the mixing's source and
            far electrode weights, where the presses fit the electrode positions (20 presses
            or more, or `press_groups` naming them) or a background map is fitted (it takes the
            sheet's part that positions fitted to the reference would); otherwise
            `REFERENCE_ONLY_GROUPS`, the electrode positions too (measured in
            docs/tutorials/calibration.md). Mixing and the electrodes' positions and widths
            are not fitted (a warning says so) to a reference the first stage's model
            correlates with under 0.5.
        press_groups: The groups fitted to the presses' differences: "mixing" (always),
            "electrode_positions", "background_map" (package docstring) and "reading_gains" (a
            gain per reading, prior standard deviation 0.2 of its relative change). None: each
            set of `PRESS_GROUP_CHOICES` (the mixing; the mixing and the positions) in turn,
            the positions kept unless the mixing alone reads significantly more of the
            held-out presses closer (a sign test; measured in docs/tutorials/calibration.md).
        hyperparameter: The one-step hyperparameter the presses are imaged at; None chooses
            it from the presses' frames (`auto_hyperparameter`).
        memory: With presses held over at least `_HELD_FRAMES` frames each, fit the skin's
            memory to the session's readings, the presses' holds known
            (`diffeit.fit.memory_from_press_readings`).
        background_map: Fit a smooth map of the sheet's conductivity (package docstring,
            "Background map"). None: with at least 20 labelled presses, the presses' map when
            `press_groups` names it and their fit is kept, else the reference's, kept when it
            reads significantly more of them closer to their labels than farther
            (leave-one-out); without, not fitted (a reference alone cannot tell a non-uniform
            sheet from the model's other errors); True: fitted and kept; False: not fitted.

    Returns:
        The `SkinCalibration`.

    Raises:
        ValueError: For a recording without frames, presses outside the skin (labels in
            millimetres said so) or outside the recording's time, three or more presses
            labelled at one place (or with a radius in another unit), presses that
            are all left out or whose times look off the recording's clock
            (`_presses_unseen`), an unknown prior group, `press_groups` without "mixing" or
            with a group the presses cannot fit (or "background_map" with
            `background_map=False`), a `background_map` other than None, True or False, a
            reference the model cannot be calibrated on.
    """
    if not isinstance(recording, Recording):
        raise ValueError(f"calibrate takes a diffeit.io.Recording; got {type(recording).__name__}")
    if recording.n_frames == 0 and recording.reference is None:
        raise ValueError("the recording holds no frames and no reference: nothing to calibrate on")
    if presses is not None and not isinstance(presses, Presses):
        raise ValueError(f"presses must be a diffeit.io.Presses; got {type(presses).__name__}")
    if background_map is not None and not isinstance(background_map, bool):
        raise ValueError(f"background_map must be None (auto), True or False; got {background_map!r}")
    priors = {**PRIORS, **({} if priors is None else dict(priors))}
    unknown = set(priors) - set(PRIORS)
    if unknown:
        raise ValueError(f"unknown prior group(s) {sorted(unknown)}; the groups are {list(PRIORS)}")
    if not all(math.isfinite(value) and value > 0 for value in priors.values()):
        raise ValueError(f"prior standard deviations must be finite and positive; got {priors}")
    mesh = default_mesh(recording, h) if mesh is None else mesh
    if presses is not None:
        _check_presses(presses, recording, mesh)
    recording, lost, lost_frames, lost_readings = held_lost_readings(recording)
    lost_from = float(recording.times[np.argmax(lost_frames)]) if lost else None
    nominal = ForwardModel(mesh, recording.protocol, contact_impedance=contact_impedance)
    options = {"readings": recording.readings, "background": background, "driven_readings": driven_readings}
    run = _first_run(recording, reference_frame, presses, nominal, options)
    reference, _ = reference_frames(recording, reference_frame, presses, every_frame=True, run_frames=run)
    as_recorded = recording, reference  # the memory's fit takes any common gain out itself
    recording, gains = drift_corrected(recording, reference)
    if gains is not None:  # the reference frames, and their spread, without the drift
        reference, _ = reference_frames(recording, reference_frame, presses, every_frame=True, run_frames=run)
    first = calibrate_to_reference(nominal, reference, **options)
    if gains is not None:  # said with every later stage's warnings
        first = _with_warnings(first, drift_note(gains))
    if lost:
        first = _with_warnings(
            first,
            f"{lost_note(lost, lost_frames, 'session')}: the {int(lost_readings.sum())} readings on them hold their "
            "values from before, and the presses from then on are left out",
        )
    if reference_groups is None:
        # Positions fitted to the reference trade with the sheet's gradient, which a background
        # map takes; presses enough for their own fit place them better.
        enough = presses is not None and presses.n_presses >= _LEAST_HELD_OUT
        positions_by_presses = enough if press_groups is None else "electrode_positions" in press_groups
        mapped = background_map or (background_map is None and enough)
        reference_groups = REFERENCE_GROUPS if positions_by_presses or mapped else REFERENCE_ONLY_GROUPS
    unknown = set(reference_groups) - set(PRIORS)
    if unknown:
        raise ValueError(f"unknown reference group(s) {sorted(unknown)}; the groups are {list(PRIORS)}")
    possible = press_groups is None or ("mixing" in press_groups and set(press_groups) <= set(_PRESS_GROUPS_POSSIBLE))
    if not possible:
        raise ValueError(
            "press_groups must hold 'mixing' and may hold 'electrode_positions', 'reading_gains' and "
            f"'background_map'; got {press_groups}"
        )
    if background_map is False and press_groups is not None and "background_map" in press_groups:
        raise ValueError("press_groups names 'background_map' but background_map=False: fit the map or not")
    calibration = refine_to_reference(first, reference, recording, priors, tuple(reference_groups))
    if presses is None:
        return _with_background_map(calibration, recording, None, reference) if background_map else calibration
    left_out, notes = _presses_left_out(presses, recording, lost_from)
    unseen, unseen_notes = _presses_unseen(calibration, presses, recording, reference)
    left_out, notes = left_out | unseen, (*notes, *unseen_notes)
    if left_out.all():
        raise ValueError(f"every labelled press is left out: {'; '.join(notes)}")
    presses = presses.select(~left_out)
    with_memory = memory and _held(presses, recording.times)
    unlabelled = _unlabelled_steps(calibration, recording, presses) if with_memory else np.zeros(0, int)
    if len(unlabelled):
        with_memory = False
        note = (
            f"the memory is not fitted: the readings step out of their noise at frame(s) {name_indices(unlabelled)}, "
            "away from every labelled press's hold (presses not labelled, or left out): the memory's fit models "
            "the labelled presses alone; label every press of the session, or calibrate on the part whose presses "
            "are all labelled"
        )
        calibration = _with_warnings(calibration, note)
    found, further, chosen, polarity = _read_presses(calibration, recording, presses, reference, hyperparameter, None)
    reference_only = _with_position_map(calibration, presses, found, further, chosen, polarity)
    if presses.n_presses < _LEAST_HELD_OUT and not with_memory:
        # Nothing could show the presses' fit better: it is not made (the memory's needs its frame).
        calibration = _too_few_to_hold_out(reference_only, (*(press_groups or PRESS_GROUP_CHOICES[-1]), "press depths"))
        if background_map:
            calibration = _with_background_map(calibration, recording, presses, reference)
        calibration = _with_size_map(calibration, recording, presses, reference)
        return _far_from_labels_noted(_with_every_press(calibration, left_out, notes))
    # The presses' differences, the same for the frame's start, every set's fit and its folds.
    changes = _fitted_changes(calibration, recording, presses, reference)
    frame = _label_frame(
        calibration, recording, presses, reference, priors["mixing"], polarity, found.position[:, 0], changes
    )
    # Without held-out presses (the memory's fit needs the frame) nothing could choose: the first set.
    choices = PRESS_GROUP_CHOICES if presses.n_presses >= _LEAST_HELD_OUT else PRESS_GROUP_CHOICES[:1]
    fits = [
        _press_fit(
            calibration, recording, presses, reference, priors, polarity, frame, groups, hyperparameter, chosen, changes
        )
        for groups in ([press_groups] if press_groups is not None else choices)
    ]
    made = [fit for fit in fits if fit.calibration is not None]
    refused = tuple(f"{_not_kept((*fit.groups, 'press depths'))}{fit.refused}" for fit in fits if fit.refused)
    if not made:
        calibration = _with_warnings(reference_only, *refused)
    else:
        best = _fullest_unless_beaten(made)
        chosen = best.hyperparameter
        theirs = _map_held_out_errors(found.position[:, 0], presses.centres, mesh)
        calibration = _kept_if_it_generalises(best.calibration, reference_only, best.held_out, theirs)
        calibration = _with_warnings(calibration, *refused)
    if frame is not None and "label_frame" not in calibration.values:  # the search's, where no fit kept refined it
        calibration = eqx.tree_at(lambda c: c.values, calibration, {**calibration.values, "label_frame": frame})
    mapped_by_presses = "background_map" in calibration.fitted.get("presses", ())
    if not mapped_by_presses and (background_map or (background_map is None and presses.n_presses >= _LEAST_HELD_OUT)):
        calibration = _with_background_map(calibration, recording, presses, reference, required=bool(background_map))
    if with_memory:
        frame = calibration.values.get("label_frame")  # the presses' fit's, where it refined it
        calibration = _with_memory(calibration, *as_recorded, _moved(presses, frame))
    calibration = _with_size_map(_held_to_skin(calibration), recording, presses, reference)
    return _far_from_labels_noted(_with_every_press(calibration, left_out, notes))


def _first_run(
    recording: Recording,
    reference_frame: int | None,
    presses: Presses | None,
    nominal: ForwardModel,
    options: Mapping[str, object],
) -> int | None:
    """How many frames the first untouched run of a recording without a reference holds
    (`reference_frames`' `run_frames`), where it is too short to measure the noise on: those
    before the first that a model calibrated on the run sees touched (`untouched_run`); None
    where the frames alone tell (a reference given, the run long enough or of one frame)."""
    if recording.reference is not None or reference_frame is not None:
        return None
    run, _ = reference_frames(recording, None, presses)
    if not 1 < len(run) < _NOISE_FRAMES:
        return None
    calibration = refine_to_reference(calibrate_to_reference(nominal, run, **options), run, recording)
    count = untouched_run(run, calibration)
    return count if count < len(run) else None


def _presses_left_out(
    presses: Presses, recording: Recording, lost_from: float | None = None
) -> tuple[np.ndarray, tuple[str, ...]]:
    """(K,) bool, the presses the calibration leaves out, and why, in words: those held at or
    after `lost_from` (s; None: never), when an electrode was lost (its readings held at their
    values from before: the presses' differences miss them); those one of whose
    frames looks damaged, its change from the frames about it (`_change_from_about`, over the
    whole recording) over `_GLITCH_CHANGE` and over `_GLITCH_FACTOR` times the presses' median
    (a skin whose every press changes its readings that much has none left out: a board's
    glitch on one press's frame, its readings one place out of order, had cost a session its
    presses' fit, and a press changes the readings by a few percent); and those timed at an
    instant no frame lies within `_LOST_FRAME` of the frames' median period of (a frame
    missing: the nearest one is another's, or the rest's); and those whose every frame is
    another's, labelled elsewhere (`_frames_of_another`)."""
    frames, times = presses.frames(recording.times), recording.times
    left_out, notes = np.zeros(len(frames), bool), []
    if lost_from is not None:
        left_out = presses.times[:, 1] >= lost_from
        if left_out.any():
            notes.append(
                f"press(es) {name_indices(np.flatnonzero(left_out))} left out: held after an electrode was lost"
            )
    if recording.n_frames >= 3:
        change = _change_from_about(recording.frames)
        largest = np.array([change[chosen].max() for chosen in frames])
        damaged = (largest > _GLITCH_CHANGE) & (largest > _GLITCH_FACTOR * np.median(largest))
        if damaged.any():
            notes.append(
                f"press(es) {name_indices(np.flatnonzero(damaged))} left out: a frame of theirs looks damaged (it "
                "changes far more than the other presses do: a board's glitch)"
            )
        left_out |= damaged
    step = frame_period(times)
    if step > 0:  # else no period to tell a lost frame by (times of a coarse clock repeat)
        missing = np.array(
            [
                not np.any((times[chosen] >= start) & (times[chosen] <= end))
                and np.min(np.abs(times[chosen] - 0.5 * (start + end))) > _LOST_FRAME * step
                for chosen, (start, end) in zip(frames, presses.times, strict=True)
            ]
        )
        if missing.any():
            notes.append(
                f"press(es) {name_indices(np.flatnonzero(missing))} left out: no frame lies within 3/4 of a frame's "
                "period of their time (a frame missing; the nearest is another's)"
            )
        left_out |= missing
    shared = _frames_of_another(presses, frames)
    if shared.any():
        notes.append(
            f"press(es) {name_indices(np.flatnonzero(shared))} left out: each of their frames is also the frame of a "
            "press labelled elsewhere (their times overlap; which label the frame shows cannot be told)"
        )
    left_out |= shared
    if left_out.all():
        raise ValueError(f"every labelled press is left out: {'; '.join(notes)}")
    return left_out, tuple(notes)


def _frames_of_another(presses: Presses, frames: list[np.ndarray]) -> np.ndarray:
    """(K,) bool, the presses each of whose `frames` (`Presses.frames`) is also a frame of a
    press labelled elsewhere (centres farther apart than the larger radius): labels timed at
    another press's instant (five of 25 on a benchmark skin were kept, read 27 to 73 mm off,
    and the position map was refused). A frame shared at a hold's end is not one: the press
    has others of its own."""
    owners: dict[int, list[int]] = {}
    for k, chosen in enumerate(frames):
        for frame in chosen:
            owners.setdefault(int(frame), []).append(k)
    centres, radius = presses.centres, presses.radius

    def elsewhere(k: int, j: int) -> bool:
        return j != k and np.linalg.norm(centres[k] - centres[j]) > max(radius[k], radius[j])

    return np.array(
        [all(any(elsewhere(k, j) for j in owners[int(frame)]) for frame in chosen) for k, chosen in enumerate(frames)]
    )


def _presses_unseen(
    calibration: SkinCalibration, presses: Presses, recording: Recording, reference: np.ndarray
) -> tuple[np.ndarray, tuple[str, ...]]:
    """(K,) bool, the presses whose frames show no touch, and why, in words: their mean
    change from the `reference` frames' mean stands within the readings' own noise: no test
    of `diffeit.touch` exceeds `diffeit.touch.SIGNIFICANCE` (2, not the detection's 5: a faint
    press still tells where it was) at the reference's `calibration`, its `subspace_statistic`
    nor, where the calibration knows the noise, the voltage test on every reading (no model in
    it: the model may reproduce a real skin poorly) and on the touch subspace (presses near the
    middle of an 80 mm skin at medium noise stood at 4.0 to 4.8 on every reading, 7.9 to 9.7
    on the subspace; without the noise, at 2 to 5). None is unseen where no test can tell. A
    press timed off its frames (another clock, a lag) would put an untouched frame's position,
    wherever its image peaks, into the position map and its noise into the presses' fit: on a
    simulated session whose 50 labels each fell one frame after their presses' holds, the test
    presses were read 49 mm off (11 missed) with no word of why. When some are unseen, the
    note says how many a common shift of the labels' times by whole frames (within half the
    median spacing between presses) would see, and when that shift sees twice as many as the
    labels' own times and at least half of them, a ValueError says so: the labels are off the
    clock, and the few that pass by chance (at z 2) would fit a position map to noise (on the
    session above, 62 mm off).

    Raises:
        ValueError: For labels off the recording's clock, as above."""
    times = recording.times
    signed = calibration.signed(recording.frames)
    at_rest = calibration.signed(np.atleast_2d(reference)).mean(axis=0)
    noise, count = calibration.noise, calibration.noise_frames
    subspace = None if noise is None else touch_subspace(calibration)

    def seen(shifts: np.ndarray) -> np.ndarray:
        """(S, K) which presses show a touch with every press's time moved by each of `shifts`
        (S,), s: each test once over all of them (the subspace statistic's Jacobian is one)."""
        held = np.concatenate([_held_frames(presses, times - shift) for shift in shifts], axis=1)  # (T, S K)
        changes = _held_means(signed, held) - at_rest
        statistic = subspace_statistic(changes, calibration)
        touched = np.full(held.shape[1], noise is None) if statistic is None else statistic > SIGNIFICANCE
        if noise is not None:
            variance = (1.0 / held.sum(axis=0) + 1.0 / count)[:, None]
            for within in (None, subspace):
                touched |= _statistic(changes, noise, count, variance, within) > SIGNIFICANCE
        return touched.reshape(len(shifts), presses.n_presses)

    unseen = ~seen(np.zeros(1))[0]
    if not unseen.any():
        return unseen, ()
    note = (
        f"press(es) {name_indices(np.flatnonzero(unseen))} left out: their frames show no touch (their change "
        "from the reference stands within the readings' noise)"
    )
    step = frame_period(times)
    starts = np.sort(presses.times[:, 0])
    spacing = float(np.median(np.diff(starts))) if len(starts) >= 2 else 0.0
    reach = int(0.5 * spacing / step) if step > 0 else 0
    if reach > 0:  # the nearest shift that sees the most (farther, the labels fall on other presses)
        shifts = step * np.array([sign * k for k in range(1, reach + 1) for sign in (1, -1)])
        counts = seen(shifts).sum(axis=1)
        best = int(np.argmax(counts))
        shown = presses.n_presses - int(unseen.sum())
        if counts[best] > shown:
            note += (
                f"; with every press's time moved by {shifts[best]:+.3g} s, {counts[best]} of {presses.n_presses} "
                "would show one: are the presses' times on the recording's clock?"
            )
        if counts[best] >= max(2 * shown, 0.5 * presses.n_presses):
            # Off the clock: those that pass by chance would fit a position map to noise.
            raise ValueError(f"the labelled presses' times look off the recording's clock: {note}")
    return unseen, (note,)


def _with_every_press(calibration: SkinCalibration, left_out: np.ndarray, notes: tuple[str, ...]) -> SkinCalibration:
    """`calibration`, fitted on the presses not `left_out` (K,), with its press errors and
    positions for every press (NaN for those), and the `notes` saying why among its warnings."""
    if not left_out.any():
        return calibration
    errors = np.full(len(left_out), np.nan)
    positions = np.full((len(left_out), calibration.model.mesh.nodes.shape[1]), np.nan)
    if calibration.press_errors is not None:
        errors[~left_out], positions[~left_out] = calibration.press_errors, calibration.press_positions
    return eqx.tree_at(
        lambda c: (c.press_errors, c.press_positions, c.warnings),
        calibration,
        (errors, positions, (*calibration.warnings, *notes)),
        is_leaf=lambda node: node is None,
    )


def _far_from_labels_noted(calibration: SkinCalibration) -> SkinCalibration:
    """`calibration` with a warning when its presses are read a median `_FAR_FROM_LABELS` of
    the skin's size or more from their labels (`press_errors`): labels on another clock by a
    press or more, or in another frame than the search finds, fit a position map to nothing
    (each label one press late on the calibration benchmark's skin, held presses: 45 mm off,
    0.55 of its radius; on time, 4 mm)."""
    errors = calibration.press_errors
    if errors is None or not np.isfinite(errors).any():
        return calibration
    size = _skin_size(calibration.model.mesh)
    median = float(np.nanmedian(errors))
    if median < _FAR_FROM_LABELS * size:
        return calibration
    note = (
        f"the presses are read a median {1e3 * median:.3g} mm from their labels, {median / size:.2f} of the skin's "
        "size: are the presses' times on the recording's clock (each press's own frames), and their centres "
        "in one frame?"
    )
    return _with_warnings(calibration, note)


def _held_to_skin(calibration: SkinCalibration) -> SkinCalibration:
    """`calibration` with its position map holding touches to the skin in the labels' frame it
    found (`PositionMap.held_to`), and its presses' positions held so; as it is without a map,
    without that frame, or on a curved skin (whose map takes touches onto it)."""
    mapping, frame, mesh = calibration.position_map, calibration.values.get("label_frame"), calibration.model.mesh
    if mapping is None or frame is None or mesh.nodes.shape[1] != 2:
        return calibration
    held = mapping.held_to(mesh, frame)
    return eqx.tree_at(
        lambda c: (c.position_map, c.press_positions), calibration, (held, held.within(calibration.press_positions))
    )


def _with_size_map(
    calibration: SkinCalibration, recording: Recording, presses: Presses, reference: np.ndarray
) -> SkinCalibration:
    """`calibration` with the `SizeMap` fitted on the presses: each one's touch read as
    `diffeit.touches` reads it (`_read_presses`), against its labelled radius and its depth under
    its labelled disc at the calibrated model (`_press_depths`); as it is on a flat skin without
    the labels' frame (whose scale gives the labels' radius in the mesh's frame), or with fewer
    than 3 presses read; with a warning where fewer than 3 reads and depths agree in sign."""
    mesh, frame = calibration.model.mesh, calibration.values.get("label_frame")
    if mesh.nodes.shape[1] == 2 and frame is None:
        return calibration
    moved = _moved(presses, frame)
    found, _, _, _ = _read_presses(
        calibration, recording, presses, reference, calibration.hyperparameter, calibration.polarity
    )
    if np.sum(found.count > 0) < 3:
        return calibration
    _, depths, _ = _press_depths(calibration, recording, reference, moved)
    try:
        sizes = SizeMap.fit(found.position[:, 0], found.radius[:, 0], found.depth[:, 0], moved.radius, depths)
    except ValueError as error:  # reads of the other sign than the model's depths: said, and no map
        return _with_warnings(calibration, f"no size map: {error}")
    return eqx.tree_at(lambda c: c.size_map, calibration, sizes, is_leaf=lambda node: node is None)


def _check_presses(presses: Presses, recording: Recording, mesh: Mesh) -> None:
    """ValueError for presses outside the recording's time, far outside the skin, of another
    dimension than the mesh's, or (three or more) spread less than their radius (at one place,
    or a radius in another unit)."""
    if presses.centres.shape[1] != mesh.nodes.shape[1]:
        raise ValueError(
            f"presses have {presses.centres.shape[1]}-dimensional centres; the mesh's nodes have "
            f"{mesh.nodes.shape[1]} coordinates (a curved skin's presses are (K, 3) points on its surface, "
            "a flat skin's (K, 2))"
        )
    times = recording.times
    if len(times) == 0:
        raise ValueError("presses need the recording's frames; the recording holds none")
    step, first, last = frame_period(times), times.min(), times.max()
    late = (presses.times[:, 1] < first - step) | (presses.times[:, 0] > last + step)
    if late.any():
        raise ValueError(
            f"press(es) {name_indices(np.flatnonzero(late))} are outside the recording's time "
            f"({first:.3f} to {last:.3f} s)"
        )
    size, middle = _skin_size(mesh), mesh.nodes.mean(axis=0)
    outside = np.linalg.norm(presses.centres - middle, axis=1) > 1.5 * size
    if outside.any():
        # Labels in millimetres on a skin meshed in metres (a thousandth of them spread over
        # the skin and on it): said so, as the likeliest cause.
        metres = presses.centres / 1000
        reach = np.linalg.norm(metres - metres.mean(axis=0), axis=1).max()
        millimetres = 0.05 * size < reach and np.all(np.linalg.norm(metres - middle, axis=1) <= 1.5 * size)
        raise ValueError(
            f"press(es) {name_indices(np.flatnonzero(outside))} are outside the skin: more than 1.5 times its "
            f"radius ({size:.3g} m) from its centre (centres are in metres, about the mesh's centre)"
            + ("; in millimetres they lie on the skin: give their centres and radius in metres" if millimetres else "")
        )
    # In the labels' own units: their frame's scale against the mesh's is fitted.
    spread = _spread(presses.centres)
    if presses.n_presses >= 3 and spread < _LEAST_LABEL_SPREAD * np.mean(presses.radius):
        # No frame or position map is determined by them: fitted, every touch was read at their place.
        raise ValueError(
            f"the {presses.n_presses} presses' centres spread {spread:.3g} about their mean, under "
            f"{_LEAST_LABEL_SPREAD} of their mean radius ({np.mean(presses.radius):.3g}): labelled at one place, or "
            "the radius given in another unit than the centres (metres both); such labels cannot place touches: "
            "label presses spread over the skin, or calibrate from the reference alone (presses=None)"
        )
