"""The presses' fit (`_fit_presses`; the package's docstring, "Presses"): the readout's mixing and
the presses' depths by Gauss-Newton on their bilinear model (`_BilinearPresses`), and, as asked
(`_PressGroups`), the gains per reading, the electrodes' positions, the background map and the
labels' frame the presses are placed in (`_moved`).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Mapping
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._arrays import per_element, rms
from .._threads import host_algebra
from ..forward import ForwardModel
from ..io import Presses, Recording
from ..mesh import Mesh
from ..readout import Readout, roles
from ._maps import _in_mesh_frame, _spread
from ._presses import _press_patterns
from ._reference import _contact_factor, _relative, _scale
from ._refine import _UNDETERMINED, _every_electrode, _position_prior, _ReadoutFit
from ._skin import SkinCalibration, _electrode_centres

# Gauss-Newton steps of the electrode positions on the presses, with the mixing and depths,
# each followed by the mixing's own fit: at most this many, until no electrode moves by this
# fraction of the positions' prior standard deviation; a step that does not decrease the
# presses' objective is halved, at most this many times, and then the fit stops there.
_POSITION_ROUNDS, _POSITION_STEP, _POSITION_HALVINGS = 10, 0.01, 5


# Gains per reading from the presses: rounds in turn with the weights and depths, until no ln g
# moves by the step.
_GAIN_ROUNDS, _GAIN_STEP = 30, 1e-6


# The central differences of the frame's refinement: this fraction of its `_frame_steps`.
_FRAME_DELTA = 0.2


# Gauss-Newton steps of the presses' depths and the readout's mixing, and the step (largest
# change of a weight) they stop at: 4 to 6 steps reach it.
_PRESS_ROUNDS, _PRESS_STEP = 30, 1e-6


# Halvings of a step that does not decrease the presses' objective before the fit stops there.
_PRESS_HALVINGS = 20


# A magnitude's sign follows the presses' differences where their projection on its predicted
# changes exceeds this many standard errors (`_signs`).
_SIGN_ERRORS = 3.0


# The prior standard deviation of each of the background map's coefficients (ln sigma, on
# terms of unit size over the sheet: package docstring, "Background map").
_SHEET_PRIOR = 0.3


def _skin_size(mesh: Mesh) -> float:
    """The skin's size, m: its farthest node from the nodes' mean."""
    return float(np.max(np.linalg.norm(mesh.nodes - mesh.nodes.mean(axis=0), axis=1)))


@host_algebra
def _frame_steps(mesh: Mesh) -> np.ndarray:
    """(4,) the scale of a change of the labels' frame (ln scale, angle, offset x and y): the
    search's first steps, and the prior standard deviations of the frame's refinement about
    it (`_fit_presses`)."""
    size = _skin_size(mesh)
    return np.array([0.05, math.radians(3.0), 0.03 * size, 0.03 * size])


class _PressGroups(NamedTuple):
    """What the presses fit besides the readout's mixing, by their priors: the electrode
    positions' (prior standard deviation and margin, m), the gains per reading's (prior
    standard deviation of a gain's relative change), the background map's (prior standard
    deviation of each coefficient of ln sigma); None for a group not fitted; and whether the
    labels' frame is refined with them (prior `_frame_steps` about the start `_label_frame`
    chose)."""

    positions: tuple[float, float] | None = None
    gains: float | None = None
    sheet: float | None = None
    frame: bool = False

    @classmethod
    def of(cls, model: ForwardModel, priors: Mapping[str, float], groups: tuple[str, ...]) -> _PressGroups:
        """The groups' priors; on a flat sheet the labels' frame is refined with them (with the
        mixing alone too: it was a Nelder-Mead search of mixing fits before). With the
        positions the two are nearly one: a shift of the electrodes along the boundary by a first
        harmonic of their angle, and a shift of the labels, explain the presses alike (a
        conformal map of the disc onto itself moves both so, to first order). Held at the
        frame its search found with the electrodes unmoved, the positions took up that
        search's error (measured on seed 0 of the calibration benchmark without noise: the
        frame 1.5 mm off and every electrode a first harmonic of 1.6 degrees off; refined,
        0.06 mm and 0.45 degrees)."""
        flat = model.mesh.nodes.shape[1] == 2
        return cls(
            _position_prior(model, priors["electrode_positions"]) if "electrode_positions" in groups else None,
            priors["reading_gains"] if "reading_gains" in groups else None,
            _SHEET_PRIOR if "background_map" in groups else None,
            flat,
        )


class _ContradictsReference(Exception):
    """A presses' fit whose mixing makes the model's reference readings anti-correlate with the
    recorded ones: no positive level explains the reference under it."""


_CONTRADICTS = "its mixing makes the model's reference readings anti-correlate with the recorded ones"


def _fit_presses(
    calibration: SkinCalibration,
    recording: Recording,
    presses: Presses,
    frame: np.ndarray | None,
    reference: np.ndarray,
    prior: float,
    polarity: int,
    start: _PressState,
    free: _PressGroups | None = None,
    train: np.ndarray | None = None,
    refit_contacts: bool = False,
    *,
    changes: np.ndarray,
    rounds: int = _POSITION_ROUNDS,
) -> tuple[SkinCalibration, float, _PressState]:
    """`calibration` with the readout's mixing fitted to the presses (package docstring,
    "Presses"), the relative misfit of the presses' differences, and where the fit ended (the
    held-out folds start there: `_held_out_errors`); the labelled `presses` in
    the labels' `frame` (`_moved`; None: the mesh's); with `free`, the groups it names too
    (`_PressGroups`: electrode positions, gains per reading, background map, the frame itself;
    None: the mixing alone); with `train` (K,) bool, to those presses alone (the others'
    potentials are computed all the same: the compiled programs are those of all K presses).
    The fit starts from `start` (`_PressState`): the calibration's model's response
    (`_ElectrodeResponse.of_calibration`, with the margin of `free.positions` when they are
    fitted), or where another fit of the same groups ended; the priors stay those about the
    calibration's model and `frame` either way. It takes at most `rounds` Gauss-Newton steps.

    Each press k is a disc of the labelled centre and radius and an unknown depth a_k, a
    relative change of the sheet's conductivity sigma under it; its differences are linearised
    at sigma, dv_k = a_k s * ((W + X) dU_k), dU_k the electrode potentials' change under the
    press's pattern, s the readings' signs (for magnitudes, the presses' where they decide
    them, else the mixed reference readings'; `_signs`). X is linear in the mixing weights:
    the weights, with their prior, and the depths are solved together (`_mixing_and_depths`),
    from the reference's weights. The positions, and the background map (sigma = sigma_0
    exp(terms @ c), the terms of the reference's map, `_sheet_terms`, sigma_0 the
    calibration's), take Gauss-Newton steps with the weights and depths on the same
    differences (their derivative by `jax.jacfwd` through the forward model), with their
    priors, each followed by the weights' and depths' own fit. With gains per reading, each
    reading also gets a gain of its own, fitted with the weights and depths
    (`_mixing_depths_and_gains`) and multiplied into the readout's gains. With `free.frame`,
    the labels' frame (its scale, angle and offset; prior `_frame_steps` about `frame`) steps
    with the weights and depths (and the positions and the map), its derivative by central
    differences of the presses' footprints (`_FRAME_DELTA` of those steps): a search of mixing
    fits alone, at the reference's electrodes and uniform sheet, settled degrees off
    (docs/tutorials/calibration.md). The fitted mixing changes the reference's readings: the
    level (and unit) is fitted again to them, and with `refit_contacts` (the fit to be kept,
    not the frame's start's nor the held-out folds') the contact impedances' common factor with
    it (`_contact_factor`). `changes` are the presses' differences (`_fitted_changes`), computed
    once by `calibrate` for all its fits of the same presses (the frame's start, each set of
    groups and its held-out folds)."""
    first = calibration.first_stage
    protocol = first.model.protocol
    gains = np.asarray(calibration.readout.gains)
    free = _PressGroups() if free is None else free
    positions, gains_prior = free.positions, free.gains
    response = start.response
    every, sigma = response.every, np.asarray(response.sigma)
    level = calibration.conductivity

    def fractions_at(frame: np.ndarray | None) -> np.ndarray:
        """(K, E) each press's footprint in the labels' `frame`, a fraction of the sheet's conductivity."""
        return polarity * _press_patterns(every.mesh, _moved(presses, frame))

    terms = _sheet_terms(every.mesh) if free.sheet is not None else np.zeros((every.n_elements, 0))
    coefficients = np.zeros(terms.shape[1]) if start.coefficients is None else start.coefficients
    steps = _frame_steps(every.mesh) if free.frame and frame is not None else np.zeros(0)
    turn = np.zeros(len(steps)) if start.turn is None else start.turn  # the frame's move from `frame`
    fractions = fractions_at(frame + np.r_[turn, 0.0] if len(steps) else frame)
    source, sink, offset = roles(protocol)
    fixed = _ReadoutFit.of(first.model, level, calibration.contact_impedance, False).pair_offsets
    basis = np.concatenate([source[None], sink[None], offset[~fixed]])  # (p, M, L)
    drive = protocol.drive_index
    weights = np.asarray(protocol.measure)
    signed_reference = first.signed(np.atleast_2d(reference).mean(axis=0)) / gains
    keep = np.ones(presses.n_presses, bool) if train is None else np.asarray(train, bool)
    differences = changes[keep]
    magnitude = recording.readings == "magnitude"
    if magnitude:
        differences = differences * first.reading_sign[first.used]  # back to |V| differences
    data = signed_reference * (first.reading_sign[first.used] if magnitude else 1.0)  # |V| for magnitudes
    # From the reference's mixing: from none, the fit of magnitudes' signs can end in another basin.
    readout = calibration.readout
    mixing = np.concatenate([[float(readout.source), float(readout.sink)], np.asarray(readout.offsets)[~fixed]])
    mixing = mixing if start.mixing is None else start.mixing
    full_weights = jnp.asarray(np.concatenate([weights[None], basis]))  # (1 + p, M, L)
    drive_onehot = jnp.asarray(np.eye(protocol.n_drives)[drive])  # (M, drives)
    # The groups that move, in this order: the electrodes' shifts, the map's coefficients, the frame's steps.
    shifts = 0 if positions is None else protocol.n_electrodes
    precision = np.concatenate(
        [
            np.full(shifts, 0.0 if positions is None else positions[0] ** -2.0),
            np.full(len(coefficients), 0.0 if free.sheet is None else free.sheet**-2.0),
            steps**-2.0,
        ]
    )
    joint_errors = None
    log_gain, gain_errors = np.zeros(differences.shape[1]), np.zeros(differences.shape[1])
    log_gain = log_gain if start.log_gain is None else start.log_gain

    def linearised(response: _ElectrodeResponse, fractions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each press's readings at unit depth without mixing (K, M) under its footprint
        `fractions` (K, E), their derivative in the weights (K, M, p), and each reading's
        drive's reference potentials (M, L)."""
        changes = response.changes(np.asarray(response.sigma) * fractions[keep])  # (K, drives, L)
        base = np.einsum("ml,kml->km", weights, changes[:, drive])
        return base, np.einsum("pml,kml->kmp", basis, changes[:, drive]), response.potentials[drive]

    def objective(at: tuple, mixing: np.ndarray, depth: np.ndarray, values: np.ndarray, scale: np.ndarray) -> float:
        residual, _ = _BilinearPresses(scaled, *at[:2], basis, weights, at[2], magnitude).residual(mixing, depth)
        return float(np.sum((residual / scale) ** 2) + np.sum(mixing**2) / prior**2 + values**2 @ precision)

    def along_frame(response: _ElectrodeResponse, turn: np.ndarray, mixing: np.ndarray) -> np.ndarray:
        """(K, M, 4) the mixed readings' derivative at unit depth in the frame's scale, angle and offset."""
        columns = []
        for i, delta in enumerate(steps * _FRAME_DELTA):
            ahead = np.r_[turn, 0.0] + frame + delta * np.eye(5)[i]
            behind = ahead - 2 * delta * np.eye(5)[i]
            base, per_weight, _ = linearised(response, (fractions_at(ahead) - fractions_at(behind)) / (2 * delta))
            columns.append(base + per_weight @ mixing)
        return np.stack(columns, axis=2)

    at = linearised(response, fractions)
    converged = not len(precision)
    for position_round in itertools.count():
        # Only the presses: a mixing fitted to the reference as well bends to the model's own
        # errors there (measured: touches placed 5 times worse; docs/tutorials/calibration.md).
        linear = _BilinearPresses(differences, *at[:2], basis, weights, at[2], magnitude)
        fit = _mixing_depths_and_gains(linear, mixing, prior, gains_prior, log_gain)
        mixing, depth, sign, curvature, residual, last_step, log_gain, gain_errors = fit
        if converged or position_round == rounds:
            break
        # A Gauss-Newton step of the positions (each electrode's ends moved together: its width
        # stays the reference's), the map, and the weights and depths together: in turn, the
        # weights held, the steps traded one for the other and stopped degrees off (measured on
        # the calibration benchmark's skins; docs/tutorials/calibration.md).
        scaled = differences / np.exp(log_gain)
        ends = np.zeros((0, 2)) if positions is None else np.asarray(every.electrode_shift)
        values = np.concatenate([ends.mean(axis=1), coefficients, turn])
        mixed = jnp.asarray(np.concatenate([[1.0], mixing]))
        along = []
        if shifts or len(coefficients):
            jacobian = _press_readings_jacobian(
                every,
                jnp.asarray(sigma),
                jnp.asarray(fractions),
                jnp.asarray(terms),
                full_weights,
                mixed,
                drive_onehot,
                positions is not None,
            )
            along.append(np.asarray(jacobian)[keep])
        if len(steps):
            along.append(along_frame(response, turn, mixing))
        along = np.concatenate(along, axis=2)
        design = depth[:, None, None] * sign[None, :, None] * np.concatenate([at[1], along], axis=2)
        predicted = sign * linear.unsigned(mixing)
        scale = _residual_scale(residual, scaled)
        step, depth_step, joint = _step_with_depths(
            predicted,
            design,
            residual,
            scale,
            np.concatenate([mixing, values]),
            np.r_[np.full(len(mixing), prior**-2.0), precision],
        )
        joint_errors = np.sqrt(np.diag(np.linalg.inv(joint))[len(mixing) :])
        before = objective(at, mixing, depth, values, scale)
        converged = True
        for _ in range(_POSITION_HALVINGS):
            change = step[len(mixing) :].copy()
            trial = every
            if positions is not None:
                moved = np.clip(ends + change[:shifts, None], *(0.999 * np.array([-1, 1]) * positions[1]))
                trial = eqx.tree_at(lambda m: m.electrode_shift, every, jnp.asarray(moved))
                change[:shifts] = moved.mean(axis=1) - ends.mean(axis=1)
            trial_sigma = sigma * np.exp(terms @ change[shifts : shifts + len(coefficients)])
            trial_turn = turn + change[shifts + len(coefficients) :]
            trial_fractions = fractions_at(frame + np.r_[trial_turn, 0.0]) if len(steps) else fractions
            trial_response = _ElectrodeResponse.of(trial, jnp.asarray(trial_sigma))
            trial_at = linearised(trial_response, trial_fractions)
            if objective(trial_at, mixing + step[: len(mixing)], depth + depth_step, values + change, scale) <= before:
                every, sigma, response, at = trial, trial_sigma, trial_response, trial_at
                fractions, turn = trial_fractions, trial_turn
                mixing = mixing + step[: len(mixing)]
                coefficients = coefficients + change[shifts : shifts + len(coefficients)]
                converged = np.all(np.abs(change) < _POSITION_STEP * np.sqrt(1.0 / precision))
                break
            step, depth_step = step / 2, depth_step / 2
    unchanged = response.potentials
    errors = np.sqrt(np.diag(np.linalg.inv(curvature)))
    values = np.zeros(2 + protocol.n_electrodes)
    spread = np.zeros_like(values)
    weighed = np.concatenate([[True, True], ~fixed])
    values[weighed], spread[weighed] = mixing, errors
    readout = Readout(protocol, values[0], values[1], values[2:], gains * np.exp(log_gain))
    mixed = weights + np.asarray(readout.mixing(protocol))
    # The readings' signs are the fit's (`_signs`: the presses' where they decide them); the frames take them.
    readings = np.sum(mixed * unchanged[drive], axis=1)
    data = data * sign / np.exp(log_gain)
    if not readings @ data > 0:
        raise _ContradictsReference(_CONTRADICTS)
    # The mixing (and the gains) change the reference's readings, most those of the source
    # electrode's potential, which its contact's drop dominates: the contact impedances' common
    # factor is fitted again with the level (and unit). With the level alone the reference was
    # matched by scaling the whole model, the presses' differences with it: on the calibration
    # benchmark's skins `de.touches(method="fit")` then read presses 1.09 to 1.34 times as strong
    # as they were (0.87 to 0.96 with the factor; the true model 0.92 on the first).
    folded = readout.folded(protocol)
    contact_factor = 1.0
    if refit_contacts:
        everything = np.ones(len(data), bool)
        contact_factor = _contact_factor(every, folded, data, everything, sigma, calibration.contact_impedance)
        refitted = every.replace(protocol=folded, contact_impedance=calibration.contact_impedance * contact_factor)
        readings = np.asarray(refitted.measure(jnp.asarray(sigma)))
    factor = _scale(readings, data)
    contact = calibration.contact_impedance * contact_factor * factor
    fitted_model = every.replace(protocol=folded, contact_impedance=contact)
    reading_sign = first.reading_sign.copy()
    if magnitude:
        reading_sign[first.used] = sign
    undetermined = tuple(f"mixing[{i}]" for i in np.flatnonzero(weighed) if spread[i] > _UNDETERMINED * prior)
    misfit = _relative(data - factor * readings, data)
    # As the reference's refinement keeps them: with c = exp(values["level"]), the level is sigma_first / c
    # and the contacts z_first exp(values["contact_impedance"]) c.
    values_by_group = {
        **calibration.values,
        "level": calibration.values["level"] + math.log(factor),
        "contact_impedance": calibration.values["contact_impedance"] + math.log(contact_factor),
        "mixing": values,
        "press_depths": depth,
    }
    errors_by_group = {**calibration.standard_errors, "mixing": spread, "press_depths": np.full(len(depth), np.nan)}
    groups = ("mixing", "press depths")
    if gains_prior is not None:
        values_by_group["reading_gains"], errors_by_group["reading_gains"] = log_gain, gain_errors
        undetermined += tuple(f"reading_gains[{i}]" for i in np.flatnonzero(gain_errors > _UNDETERMINED * gains_prior))
        groups = ("mixing", "reading_gains", "press depths")
    centres, background_map = calibration.electrode_centres, calibration.background_map
    if positions is not None and joint_errors is not None:
        shift = np.asarray(every.electrode_shift).mean(axis=1)
        position_errors = joint_errors[: protocol.n_electrodes]
        values_by_group["electrode_positions"], errors_by_group["electrode_positions"] = shift, position_errors
        undetermined += tuple(
            f"electrode_positions[{i}]" for i in np.flatnonzero(position_errors > _UNDETERMINED * positions[0])
        )
        groups = (*groups[:-1], "electrode_positions", "press depths")
        centres = _electrode_centres(every.mesh, shift)
    if len(steps) and joint_errors is not None:
        values_by_group["label_frame"] = frame + np.r_[turn, 0.0]
        errors_by_group["label_frame"] = np.r_[joint_errors[len(joint_errors) - len(steps) :], 0.0]
        joint_errors = joint_errors[: len(joint_errors) - len(steps)]
    if free.sheet is not None and joint_errors is not None:
        sheet_errors = joint_errors[-len(coefficients) :]
        values_by_group["background"], errors_by_group["background"] = coefficients, sheet_errors
        undetermined += tuple(f"background[{i}]" for i in np.flatnonzero(sheet_errors > _UNDETERMINED * free.sheet))
        groups = (*groups[:-1], "background_map", "press depths")
        background_map = sigma / factor  # c V(sigma, z) = V(sigma / c, c z), as the level
    fitted = eqx.tree_at(
        lambda c: (
            c.model,
            c.conductivity,
            c.background_map,
            c.contact_impedance,
            c.readout,
            c.reading_sign,
            c.electrode_centres,
            c.values,
            c.standard_errors,
            c.undetermined,
            c.fitted,
            c.misfit,
            c.correlation,
            c.warnings,
            c.noise,
        ),
        calibration,
        (
            fitted_model,
            level / factor,
            background_map,
            contact,
            readout,
            reading_sign,
            centres,
            values_by_group,
            errors_by_group,
            tuple(
                name
                for name in calibration.undetermined
                if not name.startswith("mixing")
                and not (positions is not None and name.startswith("electrode"))
                and not (free.sheet is not None and name.startswith("background"))
            )
            + undetermined,
            {**calibration.fitted, "presses": groups},
            misfit,
            float(np.corrcoef(data, readings)[0, 1]),
            calibration.warnings
            + (
                (f"the presses' mixing fit did not converge: its last step moved a weight by {last_step:.2g}",)
                if last_step >= _PRESS_STEP
                else ()
            ),
            None if calibration.noise is None else calibration.noise / np.exp(log_gain),
        ),
        is_leaf=lambda node: node is None,
    )
    end = _PressState(response, mixing, coefficients, turn, log_gain)
    return fitted, _relative(residual.ravel(), (differences / np.exp(log_gain)).ravel()), end


class _PressState(NamedTuple):
    """Where a presses' fit (`_fit_presses`) starts or ended: the electrode response there
    (`_ElectrodeResponse`: the electrodes' positions and the sheet, with its map), the mixing
    weights free in the fit, the map's coefficients (the sheet's ln sigma from the
    calibration's), the labels' frame's move from the frame it was given, and each reading's ln
    gain; None for the calibration's mixing and no map, move or gains."""

    response: _ElectrodeResponse
    mixing: np.ndarray | None = None
    coefficients: np.ndarray | None = None
    turn: np.ndarray | None = None
    log_gain: np.ndarray | None = None


class _BilinearPresses(NamedTuple):
    """The presses' linearised model (`_fit_presses`), bilinear in the readout's p mixing
    weights m and the presses' depths a_k: dv_k = a_k s * (base_k + columns_k m), s the
    readings' signs (for magnitudes `_signs`': the presses' where they decide them, else the
    mixed reference readings').

    Attributes:
        differences: (K, M) the presses' differences.
        base: (K, M) each press's readings at unit depth without mixing.
        columns: (K, M, p) their derivative in the p mixing weights.
        basis: (p, M, L) the weights' reading weights; `weights` (M, L) the protocol's.
        potentials: (M, L) the reference's electrode potentials of each reading's drive.
        magnitude: Whether the readings are magnitudes.
    """

    differences: np.ndarray
    base: np.ndarray
    columns: np.ndarray
    basis: np.ndarray
    weights: np.ndarray
    potentials: np.ndarray
    magnitude: bool

    def mixed(self, mixing: np.ndarray) -> np.ndarray:
        """(M, L) the reading weights with the mixing weights `mixing` (p,)."""
        return self.weights + np.einsum("p,pml->ml", mixing, self.basis)

    def unsigned(self, mixing: np.ndarray) -> np.ndarray:
        """(K, M) each press's readings at unit depth with the weights `mixing`, before their signs."""
        return self.base + self.columns @ mixing

    def residual(self, mixing: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(K, M) the differences less the model's at `mixing` (p,) and `depth` (K,), and the
        readings' signs (M,) it takes."""
        unsigned = self.unsigned(mixing)
        sign = _signs(self.mixed(mixing), self.potentials, self.magnitude, depth[:, None] * unsigned, self.differences)
        return self.differences - depth[:, None] * sign * unsigned, sign


def _mixing_depths_and_gains(
    presses: _BilinearPresses,
    mixing: np.ndarray,
    prior: float,
    gains_prior: float | None,
    log_gain: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, np.ndarray, np.ndarray]:
    """`_mixing_and_depths` on the differences divided by each reading's gain exp(`log_gain`)
    (M,), and with `gains_prior` (the prior standard deviation of a gain's relative change;
    None: the gains as given) the gains fitted in turn: given the weights and depths, each
    reading's gain g_m minimises sum_k (dv_km - g_m p_km)^2 / s_k^2 + (g_m - 1)^2 / prior^2 (p
    the predicted differences, s_k press k's residual scale, `_residual_scale`), in closed
    form; the gains' geometric mean is held at 1 (a common factor is the depths'). Until no
    ln g moves by `_GAIN_STEP`, at most `_GAIN_ROUNDS` rounds.

    Returns:
        As `_mixing_and_depths` (the residual that of the divided differences), then ln g (M,)
        and its standard errors (zero for gains not fitted).
    """
    errors, step = np.zeros_like(log_gain), math.inf
    rounds = 0 if gains_prior is None else _GAIN_ROUNDS
    for done in itertools.count():
        scaled = presses._replace(differences=presses.differences / np.exp(log_gain))
        mixing, depth, sign, curvature, residual, last_step = _mixing_and_depths(scaled, mixing, prior)
        # The weights and depths returned are those of the last gains.
        if done == rounds or step < _GAIN_STEP:
            return mixing, depth, sign, curvature, residual, last_step, log_gain, errors
        predicted = depth[:, None] * sign * presses.unsigned(mixing)  # (K, M)
        variance = _residual_scale(residual, scaled.differences) ** 2  # (K, 1)
        power = np.sum(predicted**2 / variance, axis=0) + gains_prior**-2.0
        weighed = np.sum(predicted * presses.differences / variance, axis=0)
        gain = np.maximum((weighed + gains_prior**-2.0) / power, 1e-3)
        moved = np.log(gain) - np.log(gain).mean()
        errors = np.sqrt(1.0 / power) / gain
        step, log_gain = float(np.max(np.abs(moved - log_gain))), moved


def _mixing_and_depths(
    presses: _BilinearPresses, mixing: np.ndarray, prior: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """The presses' mixing weights and depths (`_fit_presses`): Gauss-Newton on the bilinear
    model of `presses`, the weights m with their prior, from `mixing` and each depth's
    projection there.

    The depths are eliminated from each step (the Schur complement of their diagonal block),
    so a step costs what one of alternating the depths and the weights does; alternating
    converged linearly, its steps shrinking about 3% a round, and stopped far from the optimum.
    The residual's RMS weighs the data, updated every step.

    Arguments:
        presses: The linearised presses.
        mixing: (p,) the start.
        prior: The weights' prior standard deviation.

    Returns:
        The weights (p,), the depths (K,), the signs (M,), the weights' curvature (p, p) with
        the depths unknown (its inverse their covariance), the residual (K, M) and the last
        step's largest change of a weight (converged below `_PRESS_STEP`).
    """
    differences = presses.differences

    def objective(mixing: np.ndarray, depth: np.ndarray, scale: np.ndarray) -> float:
        residual, _ = presses.residual(mixing, depth)
        return float(np.sum((residual / scale) ** 2) + np.sum(mixing**2) / prior**2)

    depth = None
    precision = np.full(len(mixing), prior**-2.0)
    for _ in range(_PRESS_ROUNDS):
        unsigned = presses.unsigned(mixing)  # (K, M), at unit depth
        if depth is None:
            predicted = _signs(presses.mixed(mixing), presses.potentials, presses.magnitude) * unsigned
            depth = np.sum(predicted * differences, axis=1) / np.maximum(np.sum(predicted**2, axis=1), 1e-300)
        residual, sign = presses.residual(mixing, depth)
        predicted = sign * unsigned
        along = depth[:, None, None] * sign[None, :, None] * presses.columns  # d dv / d m
        scale = _residual_scale(residual, differences)
        step, depth_step, curvature = _step_with_depths(predicted, along, residual, scale, mixing, precision)
        # The model is bilinear and the signs of magnitudes follow the weights: a full step can
        # overshoot into another basin (measured: 3 of 5 folds of 40 presses ended there, their
        # misfit 0.9 against 0.6). Halved until the objective, at this step's scale, decreases;
        # where no halving does, the fit stops there (taking the full step instead placed
        # held-out presses worse on a benchmark skin: 2.9 against 2.6 mm).
        start = objective(mixing, depth, scale)
        for _ in range(_PRESS_HALVINGS):
            if objective(mixing + step, depth + depth_step, scale) <= start:
                break
            step, depth_step = step / 2, depth_step / 2
        else:
            step, depth_step = np.zeros_like(step), np.zeros_like(depth_step)
        mixing = mixing + step
        depth = depth + depth_step
        if np.max(np.abs(step)) < _PRESS_STEP:
            break
    residual, sign = presses.residual(mixing, depth)
    return mixing, depth, sign, curvature, residual, float(np.max(np.abs(step)))


def _step_with_depths(
    predicted: np.ndarray,
    along: np.ndarray,
    residual: np.ndarray,
    scale: np.ndarray,
    values: np.ndarray,
    precision: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A Gauss-Newton step of n parameters and of the presses' depths together, the depths
    eliminated (the Schur complement of their diagonal block: each depth moves one press's
    readings only).

    Arguments:
        predicted: (K, M) each press's readings at unit depth (the depths' derivative).
        along: (K, M, n) the readings' derivative in the parameters.
        residual: (K, M) the differences less the model's.
        scale: (K, 1) each press's residual scale, which weighs its differences (`_residual_scale`).
        values: (n,) the parameters, their prior mean zero.
        precision: (n,) their prior's inverse variances.

    Returns:
        The parameters' step (n,), the depths' (K,), and the parameters' curvature (n, n) with
        the depths unknown (its inverse their covariance).
    """
    predicted, along, residual = predicted / scale, along / scale[..., None], residual / scale  # whitened
    power = np.maximum(np.sum(predicted**2, axis=1), 1e-300)
    flat = along.reshape(-1, along.shape[-1])
    coupling = np.einsum("km,kmn->kn", predicted, along)
    on_depth = np.sum(predicted * residual, axis=1)
    schur = flat.T @ flat - coupling.T @ (coupling / power[:, None])
    curvature = schur + np.diag(precision)
    gradient = flat.T @ residual.ravel() - coupling.T @ (on_depth / power) - values * precision
    step = np.linalg.solve(curvature, gradient)
    return step, (on_depth - coupling @ step) / power, curvature


def _residual_scale(residual: np.ndarray, data: np.ndarray) -> np.ndarray:
    """(K, 1) each press's residual RMS, which weighs its differences: at least the median
    press's (no press weighs more than a typical one) and 1e-12 of the data's RMS (a noise-free
    fit stays finite). A press the linearised disc model misses (one on an electrode, whose
    response is the least linear) weighs less: weighed alike, the few such presses, their
    residuals ten times the median's, pulled the positions fit their way (measured on a
    noise-free benchmark skin with the true electrode positions)."""
    per_press = np.sqrt(np.mean(residual**2, axis=1))
    return np.maximum(per_press, max(float(np.median(per_press)), 1e-12 * rms(data)))[:, None]


@dataclasses.dataclass(frozen=True)
class _ElectrodeResponse:
    """A model reading every electrode's potential (`_every_electrode`), the conductivity
    `sigma` (E,), S/sq, and there the electrode potentials (drives, L), V, and their Jacobian
    (drives * L, E), the fast adjoint path. Every press fit of the frame's starts, and of the
    held-out folds, starts from one calibration's model: they share one response."""

    every: ForwardModel
    sigma: jax.Array
    potentials: np.ndarray
    jacobian: np.ndarray

    @classmethod
    def of(cls, every: ForwardModel, sigma: jax.Array) -> _ElectrodeResponse:
        return cls(every, sigma, np.asarray(every.potentials(sigma).electrode), np.asarray(every.jacobian(sigma)))

    @classmethod
    def of_calibration(cls, calibration: SkinCalibration, margin: float | None) -> _ElectrodeResponse:
        """At the calibration's level and contact impedance, its electrodes free to move by
        `margin`, m (None: as they are)."""
        protocol = calibration.first_stage.model.protocol
        model = calibration.model.replace(
            protocol=protocol, contact_impedance=calibration.contact_impedance, electrode_margin=margin
        )
        every = model.replace(protocol=_every_electrode(protocol))
        return cls.of(every, per_element(calibration.background, model.n_elements))

    def changes(self, patterns: jax.Array) -> np.ndarray:
        """(K, drives, L) the electrode potentials' derivative along each conductivity change (K, E)."""
        return (np.asarray(patterns) @ self.jacobian.T).reshape(len(patterns), self.every.protocol.n_drives, -1)


@eqx.filter_jit
def _press_readings_jacobian(
    every: ForwardModel,
    sigma: jax.Array,
    fractions: jax.Array,
    terms: jax.Array,
    weights: jax.Array,
    mixing: jax.Array,
    drive_onehot: jax.Array,
    positions: bool,
) -> jax.Array:
    """(K, M, L + n) the derivative of each press's linearised readings at unit depth,
    sum_l W_ml dU_k[drive of m, l], in a move of each electrode (both its ends), m (with
    `positions`; (K, M, n) without, the map fitted alone), and in the
    n coefficients c of the sheet's conductivity sigma exp(`terms` @ c), `terms` (E, n): W the
    reading weights `weights` (1 + p, M, L) combined by `mixing` (1 + p,), `drive_onehot` (M,
    drives) each reading's drive, `every` the model reading every electrode
    (`_every_electrode`), each press's pattern its `fractions` (K, E) of the sheet's
    conductivity (a press changes it by a fraction of its own).

    The readings' Jacobian in the conductivity is W spread over the drives times the electrode
    potentials' (a plain matrix product: gathering the potentials per reading is ten times
    slower under `jax.jacfwd`)."""
    combined = jnp.einsum("p,pml->ml", mixing, weights)
    spread = (drive_onehot[:, :, None] * combined[:, None, :]).reshape(len(combined), -1)  # (M, drives * L)
    n_electrodes = every.protocol.n_electrodes

    def readings(move: jax.Array | None, coefficients: jax.Array) -> jax.Array:
        moved = every if move is None else eqx.tree_at(lambda m: m.electrode_shift, every, every.electrode_shift + move)
        conductivity = sigma * jnp.exp(terms @ coefficients)
        # The presses first: (K, E) @ (E, drives * L) then @ (drives * L, M) is a quarter of the
        # work of weighing the (drives * L, E) Jacobian by `spread` first, in every tangent.
        return ((fractions * conductivity) @ moved.jacobian(conductivity).T) @ spread.T

    if not positions:
        return jax.jacfwd(lambda c: readings(None, c))(jnp.zeros(terms.shape[1]))
    parameters = jnp.zeros(n_electrodes + terms.shape[1])
    return jax.jacfwd(lambda p: readings(p[:n_electrodes, None], p[n_electrodes:]))(parameters)


def _signs(
    weights: np.ndarray,
    potentials: np.ndarray,
    magnitude: bool,
    changes: np.ndarray | None = None,
    differences: np.ndarray | None = None,
) -> np.ndarray:
    """(M,) the sign of each reading `sum_l weights * potentials` for magnitudes (d|V| = sign dV), else 1.

    With the presses' predicted `changes` (K, M) of the signed readings and their recorded
    `differences` (K, M) of the magnitudes, a reading whose recorded changes follow its
    predicted ones in one sense, by more than `_SIGN_ERRORS` standard errors of their
    projection, takes that sense: the model's sign of a reading near zero is what its errors
    flip first (measured: on the calibration benchmark's skins without noise, 8 of 192 signs
    the presses contradicted held the positions fit degrees off)."""
    if not magnitude:
        return np.ones(len(weights))
    sign = np.where(np.sum(weights * potentials, axis=1) < 0, -1.0, 1.0)
    if changes is None:
        return sign
    projection = np.sum(changes * differences, axis=0)
    residual = differences - np.where(projection < 0, -1.0, 1.0) * changes
    error = rms(residual) * np.sqrt(np.sum(changes**2, axis=0))
    return np.where(np.abs(projection) > _SIGN_ERRORS * error, np.sign(projection), sign)


def _moved(presses: Presses, frame: np.ndarray | None) -> Presses:
    """The presses in the mesh's frame under `frame` (ln scale, angle, offset, handedness: the
    labels' y negated when it is -1, then scaled, turned by the angle and offset); None: they
    are in it (a curved skin's)."""
    if frame is None:
        return presses
    return Presses(_in_mesh_frame(presses.centres, frame), presses.radius * math.exp(frame[0]), presses.times)


def _sheet_terms(mesh: Mesh) -> np.ndarray:
    """(E, n) the background map's terms on the elements: the monomials of degree 1 and 2 in the
    centroids' coordinates (taken from their mean, in units of their RMS distance from it), each
    less its area-weighted mean, so that the map's coefficients leave the level alone."""
    centroids = mesh.element_centroids
    points = (centroids - centroids.mean(axis=0)) / _spread(centroids)
    dimensions = range(points.shape[1])
    terms = [points[:, i] for i in dimensions]
    terms += [points[:, i] * points[:, j] for i, j in itertools.combinations_with_replacement(dimensions, 2)]
    terms = np.stack(terms, axis=1)
    areas = mesh.element_areas
    return terms - (areas @ terms) / areas.sum()
