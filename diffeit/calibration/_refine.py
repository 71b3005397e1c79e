"""The refinement to the reference (the package's docstring, "Refinement"): one regularised
Levenberg-Marquardt fit of the level and the groups `reference_groups` names (`PRIORS`,
`REFERENCE_GROUPS`, `REFERENCE_ONLY_GROUPS`), with the readout's closed-form Jacobian
(`_ReadoutFit`), the standard errors and the electrodes' positions and widths along the boundary.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._arrays import rms
from ..forward import ForwardModel
from ..io import Recording
from ..protocol import Protocol
from ..readout import Readout, roles
from ._frames import reading_spread
from ._reference import _LEAST_CORRELATION, _NOT_REPRODUCED, ReferenceCalibration, _relative
from ._skin import SkinCalibration, _electrode_centres

# Prior standard deviations of the refined groups (package docstring, "Refinement").
PRIORS = {
    "contact_impedance": 1.0,
    "mixing": 0.3,
    "drive_gains": 0.5,
    "channel_gains": 0.5,
    "electrode_positions": 0.1,
    "electrode_widths": 0.2,
    "reading_gains": 0.2,
}


# Electrodes may move this many prior standard deviations, and at most this fraction of the
# narrowest gap between two electrodes (they never meet).
_POSITION_REACH, _POSITION_GAP = 3.0, 0.45


# The groups fitted to the reference before presses enough to fit every mixing weight and the
# electrode positions, or a background map (docs/tutorials/calibration.md).
REFERENCE_GROUPS = ("contact_impedance", "mixing")
# ... and otherwise, the electrode positions too: on the calibration benchmark's skins (8
# seeds) their RMS error went from 2.2-3.2 to 1.0-1.4 degrees and the touches read from 1.44 to
# 1.10 times the true model's median error; with presses, the positions fitted to the reference
# took up a sheet's gradient that the background map would have (30 presses: 13.0 against 10.1 mm).
REFERENCE_ONLY_GROUPS = (*REFERENCE_GROUPS, "electrode_positions")


# A parameter whose standard error exceeds this fraction of its prior's is not determined by the data.
_UNDETERMINED = 0.7


# Levenberg-Marquardt steps of the refinement, and the rounds that re-estimate the misfit's scale.
_REFINE_STEPS, _REFINE_ROUNDS = 25, 2


# The refinement stops when no parameter moves by more than this fraction of its prior's spread.
_REFINE_TOLERANCE = 1e-3


# The grid of the source's and far electrode's mixing weights the refinement starts from: -reach to reach.
_MIXING_REACH, _MIXING_GRID = 0.5, 41


# Mixing and the electrodes' geometry are fitted to a reference the first stage's model correlates
# with at least this well: they would explain the rest of what it lacks, wrongly.
_MASKING_LEAST_CORRELATION = 0.5
_MASKING_GROUPS = ("mixing", "electrode_positions", "electrode_widths")


def _with_warnings(calibration: Any, *notes: str) -> Any:
    """`calibration` with `notes` added to its warnings."""
    return eqx.tree_at(lambda c: c.warnings, calibration, (*calibration.warnings, *notes))


def refine_to_reference(
    first: ReferenceCalibration,
    reference: np.ndarray,
    recording: Recording,
    priors: Mapping[str, float] | None = None,
    groups: tuple[str, ...] = REFERENCE_ONLY_GROUPS,
) -> SkinCalibration:
    """The second stage of a calibration from the reference: the first stage refined on its frames.

    One regularised least-squares fit (package docstring, "Refinement") of the level and the
    parameter `groups`, with their standard errors and a report of what the frames left
    undetermined; without mixing and the electrodes' positions and widths (and a warning noted)
    when the first stage's model correlates with the reference under 0.5. What `calibrate`
    does without presses, and `diffeit.reconstruct` with no calibration given.

    Arguments:
        first: The first stage (`calibrate_to_reference`).
        reference: (N, M) or (M,) the reference frames, as recorded.
        recording: The recording they come from (its protocol and kind of readings).
        priors: Prior standard deviations by group; None for `PRIORS`.
        groups: The groups of `PRIORS` fitted (by default those of a reference without presses).

    Returns:
        The `SkinCalibration` (no presses: no position map, no polarity).
    """
    priors = PRIORS if priors is None else priors
    masking = [group for group in groups if group in _MASKING_GROUPS]
    if masking and first.correlation < _MASKING_LEAST_CORRELATION:
        # A reference the nominal model does not follow at all (the Montreal tank's, its channel
        # gains spanning 12x) is explained by mixing or moved electrodes only in part, and
        # wrongly: fitted there, they mislead the images.
        others = tuple(group for group in groups if group not in _MASKING_GROUPS)
        calibration = _refine(first, reference, priors, recording, others)
        note = (
            f"{' and '.join(masking)} not fitted to the reference: the nominal model correlates with it at "
            f"{first.correlation:.3f} (< {_MASKING_LEAST_CORRELATION}), so it departs from the model in ways they "
            "would only mask (gains per reading, the wiring)"
        )
        return _with_warnings(calibration, note)
    return _refine(first, reference, priors, recording, groups)


def _refine(
    first: ReferenceCalibration,
    reference: np.ndarray,
    priors: Mapping[str, float],
    recording: Recording,
    groups: tuple[str, ...],
) -> SkinCalibration:
    """The refinement (package docstring): regularised Levenberg-Marquardt from the first stage,
    of the level and the parameter `groups` (the others stay nominal)."""
    model = first.model
    protocol = model.protocol
    frames = np.atleast_2d(np.asarray(reference, np.float64))
    magnitude = recording.readings == "magnitude"
    data = first.signed(frames.mean(axis=0)) * (first.reading_sign[first.used] if magnitude else 1.0)
    n = protocol.n_electrodes
    position_prior, margin = _position_prior(model, priors["electrode_positions"])
    width_prior = priors["electrode_widths"] * float(np.mean(model.system.electrode_lengths))
    prior = dict(priors, electrode_positions=position_prior, electrode_widths=width_prior)
    moves = "electrode_positions" in groups or "electrode_widths" in groups
    if moves:
        model = model.replace(protocol=protocol, electrode_margin=margin)
    fit = _ReadoutFit.of(model, first.conductivity, first.contact_impedance, magnitude)
    sizes = {
        "level": 1,
        "contact_impedance": n,
        "mixing": 2 + n,
        "drive_gains": protocol.n_drives,
        "channel_gains": len(protocol.measure_patterns),
        "electrode_positions": n,
        "electrode_widths": n,
    }
    spread = np.concatenate([np.full(size, 1.0 if name == "level" else prior[name]) for name, size in sizes.items()])
    fixed = np.concatenate([np.full(size, name != "level" and name not in groups) for name, size in sizes.items()])
    fixed[3 + n : 3 + 2 * n][fit.pair_offsets] = True  # offsets on the measuring pair are its gain
    theta = np.zeros(len(spread))
    if "mixing" in groups:
        # A reference determines the source's and the far electrode's weights, from the grid's
        # best; left free, the other weights trade with them and with the sheet the model
        # lacks (docs/tutorials/calibration.md). Presses fit them all.
        theta[1 + n], theta[3 + n + n // 2] = _mixing_start(fit, data)
        held = np.ones(2 + n, bool)
        held[[0, 2 + n // 2]] = False
        fixed[1 + n : 3 + 2 * n] |= held
    scale = max(first.misfit, 1e-4) * rms(data)
    for _ in range(_REFINE_ROUNDS):
        theta, curvature = _levenberg_marquardt(fit, theta, data, scale, spread, fixed)
        residual = data - np.asarray(fit.readings(jnp.asarray(theta)))
        free = int(np.count_nonzero(~fixed))
        scale = max(float(np.sqrt(np.sum(residual**2) / max(len(data) - free, 1))), 1e-9 * rms(data))
    values = dict(zip(sizes, np.split(theta, np.cumsum(list(sizes.values()))[:-1]), strict=True))
    covariance = np.zeros((len(theta), len(theta)))
    covariance[np.ix_(~fixed, ~fixed)] = np.linalg.inv(curvature[np.ix_(~fixed, ~fixed)])
    errors = dict(zip(sizes, np.split(np.sqrt(np.diag(covariance)), np.cumsum(list(sizes.values()))[:-1]), strict=True))
    # Centres and widths in metres, through the bounding map of the electrodes' ends.
    ends = _electrode_ends(values["electrode_positions"], values["electrode_widths"], margin)
    values["electrode_positions"], values["electrode_widths"] = ends.mean(axis=1), ends[:, 1] - ends[:, 0]
    errors["electrode_positions"], errors["electrode_widths"] = _electrode_end_errors(
        covariance[-2 * n :, -2 * n :], ends, margin
    )
    names = [f"{name}[{i}]" if size > 1 else name for name, size in sizes.items() for i in range(size)]
    undetermined = tuple(
        name
        for name, error, prior, off in zip(names, np.sqrt(np.diag(covariance)), spread, fixed, strict=True)
        if not off and name != "level" and error > _UNDETERMINED * prior
    )
    fitted = np.asarray(fit.readings(jnp.asarray(theta)))
    misfit = _relative(data - fitted, data)
    correlation = float(np.corrcoef(data, fitted)[0, 1]) if len(data) > 1 else 1.0
    reading_sign = first.reading_sign.copy()
    if magnitude:  # the signs of the refined model's readings
        reading_sign[first.used] = fit.signs(jnp.asarray(theta))
    # The first stage's warning that its model misses the reference goes when the refined one does not.
    notes = [n for n in first.warnings if correlation < _LEAST_CORRELATION or not n.startswith(_NOT_REPRODUCED)]
    structured = np.exp(values["drive_gains"][protocol.drive_index] + values["channel_gains"][protocol.pattern_index])
    level = first.conductivity / math.exp(values["level"][0])
    contact = first.contact_impedance * np.exp(values["contact_impedance"]) * math.exp(values["level"][0])
    readout = Readout(
        protocol,
        source=values["mixing"][0],
        sink=values["mixing"][1],
        offsets=values["mixing"][2:],
        gains=structured,
    )
    if moves:
        model = eqx.tree_at(lambda m: m.electrode_shift, model, jnp.asarray(ends))
    calibrated = model.replace(protocol=readout.folded(protocol), contact_impedance=contact)
    spread = reading_spread(frames)
    return SkinCalibration(
        model=calibrated,
        conductivity=float(level),
        background_map=None,
        contact_impedance=np.asarray(contact),
        electrode_centres=_electrode_centres(model.mesh, values["electrode_positions"]),
        readout=readout,
        used=first.used,
        reading_sign=reading_sign,
        standard_errors=errors,
        values=values,
        undetermined=undetermined,
        fitted={"reference": ("level", *groups), "presses": ()},
        misfit=float(misfit),
        correlation=correlation,
        position_map=None,
        press_errors=None,
        press_positions=None,
        hyperparameter=None,
        noise=None if spread is None else np.abs(first.signed(spread)) / structured,
        noise_frames=len(frames),
        polarity=None,
        memory=None,
        first_stage=first,
        warnings=tuple(notes),
        protocol=recording.protocol,
        readings=recording.readings,
        reference=frames.mean(axis=0),
    )


def _mixing_start(fit: _ReadoutFit, data: np.ndarray) -> tuple[float, float]:
    """The source's and the far electrode's mixing weights, on a grid, that best explain the
    reference `data` (M,) up to one scale, the model's potentials as they are.

    A magnitude board's readings are not smooth in the weights where the mixing flips a
    reading's sign, and from no mixing Levenberg-Marquardt stops short of weights that flip
    many (a source weight of 0.19 came out 0.04): the search over the grid does not.
    """
    protocol = fit.model.protocol
    electrode = np.asarray(fit.model.potentials(fit.conductivity, fit.contact_impedance).electrode)
    potentials = electrode[protocol.drive_index]

    def readings(weights: np.ndarray) -> np.ndarray:
        return np.sum(weights * potentials, axis=-1)

    nominal = readings(np.asarray(protocol.measure))
    source = readings(np.asarray(fit.source))
    far = readings(np.asarray(fit.offset[protocol.n_electrodes // 2]))
    grid = np.linspace(-_MIXING_REACH, _MIXING_REACH, _MIXING_GRID)
    a, b = (values.ravel() for values in np.meshgrid(grid, grid, indexing="ij"))
    candidates = nominal + a[:, None] * source + b[:, None] * far
    if fit.magnitude:
        candidates = np.abs(candidates)
    scale = candidates @ data / np.maximum(np.sum(candidates**2, axis=1), np.finfo(float).tiny)
    misfit = np.sum((data - scale[:, None] * candidates) ** 2, axis=1)
    best = int(np.argmin(np.where(scale > 0, misfit, np.inf)))
    return float(a[best]), float(b[best])


class _ReadoutFit(eqx.Module):
    """The refined model's readings as a function of the refined parameters (package docstring)."""

    model: ForwardModel
    every: ForwardModel  # the same model reading every electrode's potential (`_every_electrode`)
    conductivity: jax.Array
    contact_impedance: jax.Array
    source: jax.Array
    sink: jax.Array
    offset: jax.Array
    pair_offsets: np.ndarray
    magnitude: bool = eqx.field(static=True)

    @classmethod
    def of(cls, model: ForwardModel, level: float, contact_impedance: np.ndarray, magnitude: bool) -> _ReadoutFit:
        source, sink, offset = roles(model.protocol)
        # An offset j every reading measures through is the pair's own weight: a channel gain.
        on_pair = np.all(np.sum(offset * (model.protocol.measure != 0), axis=2) > 0, axis=1)
        return cls(
            model,
            model.replace(protocol=_every_electrode(model.protocol)),
            jnp.full(model.n_elements, level),
            jnp.asarray(contact_impedance, float),
            jnp.asarray(source),
            jnp.asarray(sink),
            jnp.asarray(offset),
            on_pair,
            magnitude,
        )

    @property
    def placed(self) -> jax.Array:
        """(2 + L, M, L) the reading weights each mixing weight places: the source's, the
        sink's, then each electrode's offset."""
        return jnp.concatenate([self.source[None], self.sink[None], self.offset])

    def readings(self, theta: jax.Array) -> jax.Array:
        """(M,) the readings at `theta`: signed, or magnitudes for a board that reports them."""
        return _readings(self, theta)

    def signs(self, theta: jax.Array) -> np.ndarray:
        """(M,) +-1, the signs of the signed readings at `theta`."""
        signed = _ReadoutFit(*[getattr(self, field.name) for field in dataclasses.fields(self)][:-1], False)
        return np.where(np.asarray(_readings(signed, theta)) < 0, -1.0, 1.0)

    def jacobian(self, theta: jax.Array, free: np.ndarray) -> np.ndarray:
        """(M, n) the derivative of `readings` at `theta` (n,), in the parameters where `free`
        (n,) is True (zero in the others: held, they are not differentiated).

        In closed form from the electrode potentials and their adjoint derivatives in the
        contact impedances and the electrodes' ends (`_readout_jacobian`: one solve per
        electrode, against one per parameter and drive by forward differentiation, 8 times
        slower on a 32-electrode tank)."""
        design = np.array(_readout_jacobian(self, theta))
        design[:, ~free] = 0.0
        return design


@eqx.filter_jit
def _readings(fit: _ReadoutFit, theta: jax.Array) -> jax.Array:
    model, z, weights, gain = _readout_at(fit, fit.model, theta)
    electrode = model.potentials(fit.conductivity, z).electrode
    readings = gain * jnp.sum(weights * electrode[model.protocol.drive_index], axis=-1)
    # A magnitude board is fitted in magnitudes: a reading whose sign the nominal model had wrong still fits.
    return jnp.abs(readings) if fit.magnitude else readings


def _readout_at(
    fit: _ReadoutFit, model: ForwardModel, theta: jax.Array
) -> tuple[ForwardModel, jax.Array, jax.Array, jax.Array]:
    """At the refined parameters `theta` (their layout: `_refine`'s groups in order): `model`
    with the fitted electrode ends (when it lets them move), the contact impedances (L,), ohm m,
    the reading weights with the mixing (M, L), and each reading's gain (M,)."""
    protocol = fit.model.protocol
    n, drives = protocol.n_electrodes, protocol.n_drives
    log_c, log_z = theta[0], theta[1 : 1 + n]
    mixing = theta[1 + n : 3 + 2 * n]
    log_drive = theta[3 + 2 * n : 3 + 2 * n + drives]
    log_channel = theta[3 + 2 * n + drives : -2 * n]
    if model.electrode_shift is not None:  # positions or widths fitted: the ends' bounded shifts, m
        ends = _electrode_ends(theta[-2 * n : -n], theta[-n:], model.system.electrode_margin)
        model = eqx.tree_at(lambda m: m.electrode_shift, model, ends)
    weights = jnp.asarray(protocol.measure) + jnp.einsum("j,jml->ml", mixing, fit.placed)
    gain = jnp.exp(log_c + log_drive[protocol.drive_index] + log_channel[protocol.pattern_index])
    return model, fit.contact_impedance * jnp.exp(log_z), weights, gain


@eqx.filter_jit
def _readout_jacobian(fit: _ReadoutFit, theta: jax.Array) -> jax.Array:
    """(M, n) the derivative of `_readings` at `theta`, in closed form. Reading m of drive d(m)
    is s_m = G_m sum_l W'_ml U_d(m)l with G_m the gains' product exp(ln c + ln g_d + ln g_p)
    and W' the weights with the mixing: d s / d ln c = s, d s / d ln g = s where the gain
    applies, d s / d weight = G (the potential it weighs), d s / d ln z_k = G W' dU/dz_k z_k
    and d s / d (centre, width)_k = G W' dU/d ends_k d ends_k / d (centre, width)_k (the
    adjoint Jacobians of the model reading every electrode; the position columns are zero
    for a model whose electrodes do not move); a magnitude board's |s| takes sign(s)."""
    protocol = fit.model.protocol
    n, drives = protocol.n_electrodes, protocol.n_drives
    every, z, weights, gain = _readout_at(fit, fit.every, theta)
    potentials = every.measure(fit.conductivity, z).reshape(drives, n)[protocol.drive_index]  # (M, L)
    # (M, L, L): dU_d(m)l / dz_k of every electrode l, by k.
    along_z = every.jacobian(fit.conductivity, z, wrt="contact_impedance").reshape(drives, n, n)[protocol.drive_index]
    signed = gain * jnp.sum(weights * potentials, axis=-1)
    moves = jnp.zeros((len(signed), 2 * n), signed.dtype)
    if every.electrode_shift is not None:
        # (M, L, 2): dU_d(m)l / d ends_k, by electrode k and its start and end, weighed by W'.
        along_ends = every.jacobian(fit.conductivity, z, wrt="electrode_shift").reshape(drives, n, n, 2)
        along_ends = jnp.einsum("ml,mlks->mks", weights, along_ends[protocol.drive_index])
        # Electrode k's ends depend on its own centre and width alone: one tangent for each.
        bounded = functools.partial(_electrode_ends, margin=every.system.electrode_margin)
        centre, width = theta[-2 * n : -n], theta[-n:]
        by_centre = jax.jvp(bounded, (centre, width), (jnp.ones(n), jnp.zeros(n)))[1]
        by_width = jax.jvp(bounded, (centre, width), (jnp.zeros(n), jnp.ones(n)))[1]
        moves = gain[:, None] * jnp.concatenate(
            [jnp.sum(along_ends * by_centre, axis=-1), jnp.sum(along_ends * by_width, axis=-1)], axis=1
        )
    columns = [
        signed[:, None],
        gain[:, None] * jnp.einsum("ml,mlk->mk", weights, along_z) * z,
        gain[:, None] * jnp.einsum("jml,ml->mj", fit.placed, potentials),
        signed[:, None] * jax.nn.one_hot(protocol.drive_index, drives, dtype=signed.dtype),
        signed[:, None] * jax.nn.one_hot(protocol.pattern_index, len(protocol.measure_patterns), dtype=signed.dtype),
        moves,
    ]
    design = jnp.concatenate(columns, axis=1)
    return jnp.sign(signed)[:, None] * design if fit.magnitude else design


def _levenberg_marquardt(
    fit: _ReadoutFit, start: np.ndarray, data: np.ndarray, scale: float, spread: np.ndarray, fixed: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The minimiser of ||data - V(theta)||^2 / scale^2 + ||theta / spread||^2 over the free
    parameters, and the curvature (Gauss-Newton Hessian with the prior) there."""
    theta = start.copy()
    precision = 1.0 / spread**2

    def misfit(theta: np.ndarray) -> tuple[float, np.ndarray]:
        """The cost at `theta` and its scaled residual (which the next step starts from)."""
        residual = (data - np.asarray(fit.readings(jnp.asarray(theta)))) / scale
        return float(np.sum(residual**2) + np.sum(precision * theta**2)), residual

    (cost, residual), damping = misfit(theta), 1e-3
    free = ~fixed
    design = fit.jacobian(jnp.asarray(theta), free) / scale
    for _ in range(_REFINE_STEPS):
        curvature = design.T @ design + np.diag(precision)
        gradient = design.T @ residual - precision * theta
        while True:
            block = curvature[np.ix_(free, free)]
            step = np.zeros_like(theta)
            step[free] = np.linalg.solve(block + damping * np.diag(np.diag(block)), gradient[free])
            trial, trial_residual = misfit(theta + step)
            if trial <= cost:
                theta, cost, residual, damping = theta + step, trial, trial_residual, max(damping / 10, 1e-9)
                break
            damping *= 10
            if damping > 1e8:
                break
        # The curvature is wanted at the minimiser, so the Jacobian follows every accepted step.
        design = fit.jacobian(jnp.asarray(theta), free) / scale
        if damping > 1e8 or np.max(np.abs(step) / spread) < _REFINE_TOLERANCE:
            break
    return theta, design.T @ design + np.diag(precision)


def _electrode_ends(centre: Any, width: Any, margin: float) -> Any:
    """(L, 2) how far each electrode's start and end lie from the mesh's, m, for unbounded
    centre shifts and width changes (L,), m: each end bounded smoothly by `margin`. The map is
    1-Lipschitz, so an electrode keeps some length while its width change exceeds minus its
    length (the width prior keeps it well above)."""
    xp = jnp if isinstance(centre, jax.Array) or isinstance(width, jax.Array) else np
    return margin * xp.tanh(xp.stack([centre - width / 2, centre + width / 2], axis=1) / margin)


def _electrode_end_errors(covariance: np.ndarray, ends: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """The standard errors of the electrodes' centre shifts and width changes, m, from the
    covariance (2L, 2L) of the unbounded centres and widths, through the bounding map's slope
    at the `ends` (L, 2) (first order)."""
    n = len(ends)
    slope = 1 - (ends / margin) ** 2  # d end / d (unbounded end)
    # (centre, width) of the bounded ends per electrode, by the unbounded (centre, width).
    to_ends = np.array([[1.0, -0.5], [1.0, 0.5]])
    to_result = np.array([[0.5, 0.5], [-1.0, 1.0]])
    centre_errors, width_errors = np.zeros(n), np.zeros(n)
    for i in range(n):
        jacobian = to_result @ np.diag(slope[i]) @ to_ends
        block = covariance[np.ix_([i, n + i], [i, n + i])]
        variance = np.diag(jacobian @ block @ jacobian.T)
        centre_errors[i], width_errors[i] = np.sqrt(np.maximum(variance, 0.0))
    return centre_errors, width_errors


def _position_prior(model: ForwardModel, fraction: float) -> tuple[float, float]:
    """The electrode positions' prior standard deviation, m (`fraction` of the mean spacing
    between electrodes), and how far they may move (package docstring)."""
    spacing, gap = _electrode_spacing(model)
    return fraction * spacing, min(_POSITION_REACH * fraction * spacing, _POSITION_GAP * gap)


def _electrode_spacing(model: ForwardModel) -> tuple[float, float]:
    """The mean distance between neighbouring electrode centres along the boundary, and the
    narrowest gap between two electrodes, m (electrodes on the outer boundary loop)."""
    centres = _electrode_centres(model.mesh)
    lengths = model.system.electrode_lengths
    perimeter = float(
        np.sum(np.linalg.norm(np.diff(model.mesh.nodes[model.mesh.boundary_edges], axis=1)[:, 0], axis=1))
    )
    order = np.argsort(centres)
    between = np.diff(np.append(centres[order], centres[order[0]] + perimeter))
    gaps = between - (lengths[order] + np.roll(lengths[order], -1)) / 2
    return float(np.mean(between)), float(np.min(gaps))


def _every_electrode(protocol: Protocol) -> Protocol:
    """`protocol`'s drives, each reading every electrode's potential (drives x L readings)."""
    return Protocol(protocol.drive, [np.eye(protocol.n_electrodes)] * protocol.n_drives)
