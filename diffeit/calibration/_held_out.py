"""Which presses' fits the calibration keeps: the labels' frame found by the presses' fits
(`_label_frame`), each set of groups fitted (`_press_fit`) and judged on held-out presses
(`_held_out_errors`, `_fullest_unless_beaten`, `_kept_if_it_generalises`), and the position map
fitted on the presses' touches (`_with_position_map`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, NamedTuple

import equinox as eqx
import numpy as np

from .._messages import name_indices
from ..io import Presses, Recording
from ..mesh import Mesh, surface_distance
from ._maps import _COVERED_RADII, PositionMap, _coverage, _leave_one_out_errors
from ._paired import _SIGNIFICANCE, _closer
from ._press_fit import _CONTRADICTS, _ContradictsReference, _ElectrodeResponse, _fit_presses, _PressGroups, _PressState
from ._presses import _read_presses
from ._reference import _SKIN_LEAST_CORRELATION
from ._refine import _with_warnings
from ._skin import _IDENTITY_FRAME, _RINGING_CAP, _RINGING_QUANTILE, SkinCalibration

# The presses' fit is judged on presses it did not see: every fifth press held out in turn, with
# at least this many presses (fewer cannot show it: the reference's calibration is kept). With
# 10, folds of two passed fits that read the benchmark's test presses worse in both such cases.
_HELD_OUT_FOLDS, _LEAST_HELD_OUT = 5, 20


# The Gauss-Newton steps of each fold's fit, from where the fit of all the presses ended
# (`_held_out_errors`).
_FOLD_ROUNDS = 2


def _label_frame(
    calibration: SkinCalibration,
    recording: Recording,
    presses: Presses,
    reference: np.ndarray,
    prior: float,
    polarity: int,
    read_positions: np.ndarray,
    changes: np.ndarray,
) -> np.ndarray | None:
    """The labels' frame (ln scale, angle, offset, handedness; `_moved`; package docstring,
    "Presses") the presses' fits start from: of the mesh's own and the similarities, turning
    and mirrored, that map the labels onto the positions read, the one in which the readout's
    mixing fitted to the presses (their differences `changes`, `_fitted_changes`; the
    reference's model) explains them best; None on a curved skin, whose labels are in the
    mesh's frame. Each fit refines its scale, angle and offset with its other groups
    (`_PressGroups`), its handedness held."""
    mesh = calibration.model.mesh
    if mesh.nodes.shape[1] != 2:
        return None
    unmoved = _PressState(_ElectrodeResponse.of_calibration(calibration, None))

    def misfit(frame: np.ndarray) -> float:
        try:
            return _fit_presses(
                calibration, recording, presses, frame, reference, prior, polarity, unmoved, changes=changes
            )[1]
        except _ContradictsReference:
            return math.inf

    similar = (_frame_from_reads(read_positions, presses, mirror) for mirror in (False, True))
    starts = [_IDENTITY_FRAME, *(start for start in similar if start is not None)]
    return starts[int(np.argmin([misfit(start) for start in starts]))]


class _PressFit(NamedTuple):
    """One set of groups fitted to the presses: the calibration (with its position map; None
    when it is refused), its held-out press errors (None with too few presses), the
    hyperparameter the presses were read at, the groups, and why it was refused ("" if not)."""

    calibration: SkinCalibration | None
    held_out: np.ndarray | None
    hyperparameter: float
    groups: tuple[str, ...]
    refused: str = ""


def _press_fit(
    calibration: SkinCalibration,
    recording: Recording,
    presses: Presses,
    reference: np.ndarray,
    priors: Mapping[str, float],
    polarity: int,
    frame: np.ndarray | None,
    groups: tuple[str, ...],
    hyperparameter: float | None,
    chosen: float,
    changes: np.ndarray,
) -> _PressFit:
    """The presses' fit of `groups` in the labels' `frame` (`_fit_presses`, their differences
    `changes`), its presses read at
    it (at `hyperparameter`, or None: one chosen again from them) and a position map fitted, and
    its held-out errors (`_held_out_errors`); a refused fit carries `chosen`, the hyperparameter
    the reference's calibration read the presses at."""
    free = _PressGroups.of(calibration.model, priors, groups)
    # The fit starts from this model (the reference's calibration's), the held-out folds from the fit's end.
    response = _ElectrodeResponse.of_calibration(calibration, None if free.positions is None else free.positions[1])
    try:
        fitted, _, end = _fit_presses(
            calibration,
            recording,
            presses,
            frame,
            reference,
            priors["mixing"],
            polarity,
            _PressState(response),
            free,
            None,
            True,
            changes=changes,
        )
    except _ContradictsReference:
        return _PressFit(None, None, chosen, groups, _CONTRADICTS)
    if fitted.correlation < _SKIN_LEAST_CORRELATION <= calibration.correlation:
        refused = (
            f"it takes the model's correlation with the reference from {calibration.correlation:.3f} to "
            f"{fitted.correlation:.3f}, under the {_SKIN_LEAST_CORRELATION} at which the frames' calibrated "
            "differences are imaged"
        )
        return _PressFit(None, None, chosen, groups, refused)
    found, further, chosen, polarity = _read_presses(fitted, recording, presses, reference, hyperparameter, polarity)
    fitted = _with_position_map(fitted, presses, found, further, chosen, polarity)
    prior = priors["mixing"]
    held_out, folds = _held_out_errors(
        calibration, recording, presses, reference, prior, frame, free, chosen, polarity, end, changes
    )
    return _PressFit(_with_fold_spread(fitted, folds), held_out, chosen, groups)


# The presses' groups whose standard errors the held-out folds' spread checks: values' keys.
_FOLD_CHECKED = ("mixing", "electrode_positions", "background", "reading_gains")


def _with_fold_spread(calibration: SkinCalibration, folds: list[dict[str, np.ndarray]]) -> SkinCalibration:
    """`calibration` (the presses' fit of all of them) with the standard errors of each group of
    `_FOLD_CHECKED` it fitted raised by a common factor to the spread of the same fit over the
    held-out `folds` (each fold's `values`, every fold fitted), where that is larger.

    The Gauss-Newton errors take each reading's residual as independent noise; a model's own
    error repeats over a press's readings. The folds leave out a fifth of the presses each:
    their spread is the delete-a-group jackknife's variance, (g - 1) / g sum_i (theta_i -
    mean)^2, which counts a press as the independent unit. Its ratio to the Gauss-Newton
    variance is pooled over the group's parameters (g - 1 = 4 degrees of freedom each: one
    parameter's is too noisy to use alone). On the calibration benchmark, the labels' frame
    then held while the positions were fitted, the positions' errors stood 1.1 to 3.1 standard
    errors off (RMS; 1.6 to 4.5 before); the rest was the frame's bias, the same on every
    press, which no resampling of the presses sees. With the frame refined with them, 0.71 to
    1.24 (docs/tutorials/calibration.md)."""
    if len(folds) < _HELD_OUT_FOLDS:
        return calibration
    errors = dict(calibration.standard_errors)
    for group in _FOLD_CHECKED:
        if group not in errors or any(group not in fold for fold in folds):
            continue
        values = np.stack([np.asarray(fold[group], float) for fold in folds])
        spread = (len(folds) - 1) / len(folds) * np.sum((values - values.mean(axis=0)) ** 2, axis=0)
        error = np.asarray(errors[group], float)
        checked = np.isfinite(error) & (error > 0) & np.isfinite(spread)
        if checked.any():
            ratio = float(np.mean(spread[checked] / error[checked] ** 2))
            errors[group] = error * math.sqrt(max(ratio, 1.0))
    return eqx.tree_at(lambda c: c.standard_errors, calibration, errors)


def _frame_from_reads(read_positions: np.ndarray, presses: Presses, mirror: bool) -> np.ndarray | None:
    """(5,) the frame (`_moved`) of the similarity, mirrored (y -> -y first) when `mirror`, that
    best maps the presses' labelled centres onto the positions read (Umeyama's least squares,
    once more without the presses read more than three robust deviations off; NaN reads left
    out); the identity with fewer than 3 reads; None where no similarity maps them (labels at
    one place: its scale would be 0)."""
    seen = np.all(np.isfinite(read_positions), axis=1)
    if seen.sum() < 3:
        return _IDENTITY_FRAME
    handedness = -1.0 if mirror else 1.0
    labelled = presses.centres * [1.0, handedness]
    keep = seen.copy()
    for _ in range(2):
        scale, rotation, offset = _similarity(labelled[keep], read_positions[keep])
        moved = scale * labelled @ rotation.T + offset
        miss = np.linalg.norm(moved - read_positions, axis=1)
        deviation = 1.4826 * np.median(np.abs(miss[seen] - np.median(miss[seen])))
        keep = seen & (miss <= np.median(miss[seen]) + 3 * deviation)
        if keep.sum() < 3:
            keep = seen
    if not scale > 0:
        return None
    return np.array([math.log(scale), math.atan2(rotation[1, 0], rotation[0, 0]), *offset, handedness])


def _similarity(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Scale s, rotation R (2, 2) and offset t minimising ||target - (s R source + t)||."""
    mean_source, mean_target = source.mean(axis=0), target.mean(axis=0)
    a, b = source - mean_source, target - mean_target
    u, singular, vt = np.linalg.svd(b.T @ a)
    flip = np.diag([1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ flip @ vt
    scale = float(np.trace(np.diag(singular) @ flip) / max(np.sum(a**2), 1e-300))
    return scale, rotation, mean_target - scale * rotation @ mean_source


# With less of the skin near the presses read (`_coverage`), the calibration says so. On a
# benchmark skin, 50 presses anywhere within 0.8 of its radius lie near 92% of it, 25 near 71%,
# 10 near 55%; 50 in rows from the bottom up (a raster cut short) near 58%, 25 near 41%.
_LEAST_COVERAGE = 0.65


# How the notes `_with_position_map` adds begin.
_POSITION_MAP_NOTES = ("no touch read at press(es) ", "fewer than 3 presses read", "the presses read lie near ")


def _with_position_map(
    calibration: SkinCalibration,
    presses: Presses,
    found: Any,
    further: np.ndarray,
    hyperparameter: float,
    polarity: int,
) -> SkinCalibration:
    """`calibration` with the position map fitted on the presses' touches `found`, and the
    ringing from their images' further hills `further` (`_read_presses`; package docstring,
    "Presses"). The notes of a position map `calibration` already holds are replaced by this
    one's (a background map's calibration fits the map again)."""
    seen = found.count > 0
    notes = [note for note in calibration.warnings if not note.startswith(_POSITION_MAP_NOTES)]
    if not seen.all():
        notes.append(f"no touch read at press(es) {name_indices(np.flatnonzero(~seen))}: left out of the position map")
    if seen.sum() < 3:
        notes.append("fewer than 3 presses read: no position map")
        return eqx.tree_at(
            lambda c: (c.warnings, c.polarity), calibration, (tuple(notes), polarity), is_leaf=lambda node: node is None
        )
    read_positions, labelled = found.position[seen, 0], presses.centres[seen]
    mapping = PositionMap.fit(read_positions, labelled, calibration.model.mesh)
    coverage = _coverage(calibration.model.mesh, read_positions)
    if coverage < _LEAST_COVERAGE:
        notes.append(
            f"the presses read lie near {100 * coverage:.0f}% of the skin (within {_COVERED_RADII} of its radius): "
            "the position map corrects touches near them alone, and beyond them moves touches as a whole (the labels' "
            "frame, or the presses' affine fit); label presses all over the skin"
        )
    errors = np.full(presses.n_presses, np.nan)
    errors[seen] = _leave_one_out_errors(read_positions, labelled, mapping.degree, mapping.surface)
    ringing = min(float(np.quantile(further[seen], _RINGING_QUANTILE)), _RINGING_CAP)
    return eqx.tree_at(
        lambda c: (
            c.position_map,
            c.press_errors,
            c.press_positions,
            c.warnings,
            c.hyperparameter,
            c.contact_impedance_spread,
            c.polarity,
            c.ringing,
        ),
        calibration,
        (
            mapping,
            errors,
            mapping(found.position[:, 0]),
            tuple(notes),
            hyperparameter,
            calibration.imaging_spread,
            polarity,
            ringing,
        ),
        is_leaf=lambda node: node is None,
    )


def _held_out_errors(
    calibration: SkinCalibration,
    recording: Recording,
    presses: Presses,
    reference: np.ndarray,
    prior: float,
    frame: np.ndarray | None,
    free: _PressGroups,
    hyperparameter: float,
    polarity: int,
    start: _PressState,
    changes: np.ndarray,
) -> tuple[np.ndarray | None, list[dict[str, np.ndarray]]]:
    """(K,) each press's distance, m, from where it is read when the presses' fit (mixing, and
    what `free` names) and the position map are made without it: the presses
    in `_HELD_OUT_FOLDS` folds (every fifth), each fold read at the calibration fitted to the
    others, in the labels' frame `frame` found from all of them (the presses' differences
    `changes`: as `_fit_presses`). NaN for a press no touch was read at; None with fewer than
    `_LEAST_HELD_OUT` presses. And the `values` of each fold's fit (for `_with_fold_spread`).

    Each fold's fit starts where the fit of all the presses ended (`start`), a fifth of its
    presses away, and takes at most `_FOLD_ROUNDS` Gauss-Newton steps (the one-step jackknife
    takes one). On the calibration benchmark's sessions (25 to 100 presses) this read the test
    presses, kept the same sets and placed the electrodes exactly as folds fitted from the
    reference's calibration (up to `_POSITION_ROUNDS` steps each) did, and the positions'
    errors in their standard errors moved by at most 0.09 (RMS), in a third less time."""
    if presses.n_presses < _LEAST_HELD_OUT:
        return None, []
    fold = np.arange(presses.n_presses) % _HELD_OUT_FOLDS
    errors = np.full(presses.n_presses, np.nan)
    folds = []
    for k in range(_HELD_OUT_FOLDS):
        test = np.flatnonzero(fold == k)
        try:
            fitted, _, _ = _fit_presses(
                calibration,
                recording,
                presses,
                frame,
                reference,
                prior,
                polarity,
                start,
                free,
                fold != k,
                changes=changes,
                rounds=_FOLD_ROUNDS,
            )
        except _ContradictsReference:
            continue  # the fold's presses stay NaN: not read, the largest errors
        folds.append(fitted.values)
        found, _, _, _ = _read_presses(fitted, recording, presses, reference, hyperparameter, polarity)
        read = found.position[:, 0]
        seen = np.all(np.isfinite(read), axis=1)
        trained = seen & (fold != k)
        if trained.sum() < 3:
            continue
        mapping = PositionMap.fit(read[trained], presses.centres[trained], calibration.model.mesh)
        errors[test] = surface_distance(calibration.model.mesh, mapping(read[test]), presses.centres[test])
    return errors, folds


def _map_held_out_errors(read: np.ndarray, labelled: np.ndarray, mesh: Mesh) -> np.ndarray:
    """(K,) each press's distance, m, from its labelled position `labelled` (K, 2 or 3) of its
    read position `read` (K, 2 or 3; NaN: not read) mapped by a `PositionMap` fitted, its degree
    chosen, on the other folds' presses (the folds of `_held_out_errors`)."""
    fold = np.arange(len(read)) % _HELD_OUT_FOLDS
    seen = np.all(np.isfinite(read), axis=1)
    errors = np.full(len(read), np.nan)
    for k in range(_HELD_OUT_FOLDS):
        trained, test = seen & (fold != k), seen & (fold == k)
        if trained.sum() >= 3 and test.any():
            mapping = PositionMap.fit(read[trained], labelled[trained], mesh)
            errors[test] = surface_distance(mesh, mapping(read[test]), labelled[test])
    return errors


def _fullest_unless_beaten(made: list[_PressFit]) -> _PressFit:
    """Of the presses' fits `made` (in `PRESS_GROUP_CHOICES`' order, the fullest set last), the
    fullest, unless a smaller set reads significantly more of the held-out presses closer than
    farther (a one-sided sign test at `_SIGNIFICANCE`): then the closest of those. As
    for the reference's calibration (`_kept_if_it_generalises`), the physical fit is kept short
    of evidence against it: at 50 presses the sets' held-out medians chose the better set of
    test presses about as often as not (docs/tutorials/calibration.md), and the mixing alone,
    with the electrodes where the mesh has them, took up their error (a weight 0.104 off on
    the calibration benchmark's seed 2 with 50 presses, against 0.010 with the positions)."""
    fullest = made[-1]
    if fullest.held_out is None:
        return fullest
    beaten_by = [fit for fit in made[:-1] if _closer(fit.held_out, fullest.held_out)[2] < _SIGNIFICANCE]
    return min(beaten_by, key=lambda fit: _median_read(fit.held_out)) if beaten_by else fullest


def _kept_if_it_generalises(
    fitted: SkinCalibration, reference_only: SkinCalibration, held_out: np.ndarray | None, theirs: np.ndarray
) -> SkinCalibration:
    """`fitted` (the presses' fit) with its held-out press errors `held_out` as `press_errors`,
    unless the calibration from the reference alone with a position map (`reference_only`),
    held out in the same folds (`theirs`, `_map_held_out_errors`), reads significantly more of
    the presses closer than farther (a one-sided sign test at `_SIGNIFICANCE`): then that
    one, with a warning giving both. What the presses' fit adds is measured on presses it did
    not see; a board whose readout is not the model's mixing can make it worse, not better.
    Short of that the physical fit is kept. On the calibration benchmark's sessions (5 seeds,
    25, 50 and 100 presses) it read the test presses closer in 13 of 15; the rule before,
    against the reference's own leave-one-out median (its map's degree the one that made those
    errors smallest), refused it in 5, and in all 5 it read them closer. With too few presses
    to hold out (`held_out` None), `reference_only`, with a note."""
    if held_out is None:
        return _too_few_to_hold_out(reference_only, fitted.fitted["presses"])
    closer, farther, significance = _closer(theirs, held_out)
    if significance >= _SIGNIFICANCE:
        return eqx.tree_at(lambda c: c.press_errors, fitted, held_out)
    note = (
        f"{_not_kept(fitted.fitted['presses'])}presses it did not see were read {1e3 * _median_read(held_out):.1f} mm "
        f"off (median) against {1e3 * _median_read(theirs):.1f} mm with the reference's calibration and a position "
        f"map, which read {closer} of them closer and {farther} farther (sign test p = {significance:.2g})"
    )
    return _with_warnings(reference_only, note)


def _median_read(errors: np.ndarray | None) -> float:
    """The median of press errors, a press not read (NaN) counting as the largest; inf for none."""
    if errors is None:
        return math.inf
    return float(np.median(np.where(np.isnan(errors), np.inf, errors)))


def _too_few_to_hold_out(reference_only: SkinCalibration, groups: tuple[str, ...]) -> SkinCalibration:
    """`reference_only`, with the note that too few presses were given to keep the presses' fit of `groups`."""
    note = (
        f"{_not_kept(groups)}fewer than {_LEAST_HELD_OUT} presses cannot show that it reads presses it did not see "
        "better than the reference's calibration"
    )
    return _with_warnings(reference_only, note)


def _not_kept(groups: tuple[str, ...]) -> str:
    return f"the presses' fit ({', '.join(groups)}) is not kept: "
