"""The first stage of a calibration, `calibrate_to_reference` (a `ReferenceCalibration`): the
level with the voltage unit, the orientation, the signs of magnitudes, the readings on driven
electrodes and the outliers, fitted to a recording's reference frame (the package's docstring,
"First stage"); with the model's helpers the later stages share (`_scale`, `_relative`,
`_contact_factor`, `_batched_readings`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._arrays import per_element, rms, uncertain_sign
from .._messages import name_indices
from .._threads import host_algebra
from ..forward import ForwardModel
from ..protocol import Protocol

DrivenReadings = Literal["auto", "keep", "drop"]


# Adopt another orientation when it cuts the misfit as recorded by at least this factor.
_ORIENTATION_GAIN = 2.0


# Outliers: a residual above this many robust standard deviations and above this fraction of the
# model's reading (itself at least the floor times the RMS reading): off by a factor, not by model error.
_OUTLIER_DEVIATIONS, _OUTLIER_RELATIVE, _OUTLIER_FLOOR = 6.0, 0.5, 0.1


# An electrode is broken when at least this fraction of the readings that use it are masked.
_BROKEN_ELECTRODE = 0.5


# Driven readings stay when their relative misfit is at most this factor times the others' (or the floor).
_DRIVEN_FACTOR, _DRIVEN_FLOOR = 2.0, 0.05


# The model does not reproduce the reference below this correlation (the warning begins so).
_LEAST_CORRELATION = 0.9


# `diffeit.reconstruct` images a skin calibration's calibrated differences when its model
# correlates with the reference at least this well (else normalised ones): a presses' fit that
# takes a model below it is refused, its presses having been read at calibrated differences.
_SKIN_LEAST_CORRELATION = 0.5


_NOT_REPRODUCED = "the model does not reproduce the reference"


# Contact impedance factors searched (log-spaced) before a golden-section refinement, and the
# most Levenberg-Marquardt steps of the per-electrode fit that follows.
_CONTACT_GRID = np.logspace(-3, 3, 25)


_CONTACT_STEPS = 20


class CalibrationWarning(UserWarning):
    """The model does not reproduce a recording's reference well, or the calibration changed
    how the recording is read (orientation, masked readings): the images may mislead."""


class ReferenceCalibration(eqx.Module):
    """The model calibrated to a recording's reference (package docstring, "First stage").

    - `model`: the calibrated `ForwardModel`: the orientation's protocol restricted to the
      readings used, with the fitted contact impedance `contact_impedance` (ohm m, per electrode).
    - `conductivity`: sigma_h, the fitted level, S/sq in the recording's voltage unit (with an
      arbitrary unit, only its ratio to the contact impedance is physical).
    - `used`: (M,) bool, the recording's readings that are imaged.
    - `reading_sign`: (M,) +-1, what a recorded reading is multiplied by to match the model: the
      drive's sign, times the model's sign for magnitudes.
    - `orientation`: "as recorded", or the alternative adopted (see `orientations`, the misfit
      of each alternative tried).
    - `misfit`: ||v - V|| / ||v|| and `correlation` (Pearson) on the readings used.
    - `masked`: reason -> reading indices ("zero", "saturated", "uncertain sign",
      "driven electrode", "outlier", "broken electrode"); `broken_electrodes`.
    - `driven_readings`: "none" (the protocol reads no driven electrode), "kept" or "dropped".
    - `warnings`: what the calibration warns about, in words.
    """

    model: ForwardModel
    conductivity: float
    contact_impedance: np.ndarray
    used: np.ndarray
    reading_sign: np.ndarray
    orientation: str = eqx.field(static=True)
    orientations: dict[str, float]
    misfit: float
    correlation: float
    masked: dict[str, tuple[int, ...]]
    broken_electrodes: tuple[int, ...]
    driven_readings: str = eqx.field(static=True)
    warnings: tuple[str, ...]

    def signed(self, frames: np.ndarray) -> np.ndarray:
        """(..., M_used): recorded frames (..., M) in the calibrated model's order and sign."""
        return (np.asarray(frames, np.float64) * self.reading_sign)[..., self.used]

    @property
    def background(self) -> float:
        """The conductivity the model images at, S/sq: the level (as `SkinCalibration.background`)."""
        return self.conductivity

    def summary(self) -> dict[str, Any]:
        """The calibration in JSON-serialisable form, for provenance."""
        return {
            "orientation": self.orientation,
            "orientations_misfit": {name: round(value, 6) for name, value in self.orientations.items()},
            "conductivity": self.conductivity,
            "contact_impedance": float(np.mean(self.contact_impedance)),
            "contact_impedance_per_electrode": [float(z) for z in self.contact_impedance],
            "misfit": self.misfit,
            "correlation": self.correlation,
            "readings_used": int(self.used.sum()),
            "masked": {reason: list(indices) for reason, indices in self.masked.items()},
            "broken_electrodes": list(self.broken_electrodes),
            "driven_readings": self.driven_readings,
            "warnings": list(self.warnings),
        }


@host_algebra
def calibrate_to_reference(
    model: ForwardModel,
    reference: np.ndarray,
    *,
    readings: str = "signed",
    background: float = 1.0,
    driven_readings: DrivenReadings = "auto",
    fit: bool = True,
) -> ReferenceCalibration:
    """Calibrate a model to a recording's reference frame.

    Fits the conductivity level (with the voltage unit), the orientation, the signs of
    magnitudes, the readings on driven electrodes and the broken channels, in the order of the
    package docstring ("First stage"); docs/tutorials/calibration.md shows it at work.

    Arguments:
        model: The nominal model: the sheet's mesh, the recording's protocol, the nominal
            contact impedance.
        reference: The reference frame (M,), or several untouched frames (T, M) whose mean is
            used, in the recording's units.
        readings: "signed" or "magnitude" (the recording's).
        background: sigma_0, S/sq: the nominal level whose contact length z_0 sigma_0 the fit
            keeps.
        driven_readings: "auto", "keep" or "drop" the readings on driven electrodes.
        fit: False keeps the nominal model as it is (level, contact impedance, orientation,
            every reading), signing magnitudes only.

    Returns:
        The `ReferenceCalibration`.

    Raises:
        ValueError: For a reference of the wrong shape or with non-finite values, an unknown
            option, or a reference left without readings.
    """
    v = _reference_mean(reference, model.n_measurements)
    if readings not in ("signed", "magnitude"):
        raise ValueError(f'readings must be "signed" or "magnitude"; got {readings!r}')
    if driven_readings not in ("auto", "keep", "drop"):
        raise ValueError(f'driven_readings must be "auto", "keep" or "drop"; got {driven_readings!r}')
    if not (math.isfinite(background) and background > 0):
        raise ValueError(f"background must be a positive conductivity, S/sq; got {background}")
    protocol = model.protocol
    magnitude = readings == "magnitude"
    if magnitude and np.any(v < 0):
        raise ValueError(
            f"readings are magnitudes, yet the reference is negative at {name_indices(np.flatnonzero(v < 0))}"
        )
    z0 = np.broadcast_to(np.asarray(model.contact_impedance, np.float64), (protocol.n_electrodes,))
    driven = _driven(protocol)
    masked: dict[str, np.ndarray] = {}
    notes: list[str] = []
    if not fit:
        nominal = _voltages(model, protocol, background, z0)
        sign = np.sign(nominal) if magnitude else np.ones_like(v)
        sign[sign == 0] = 1.0
        used = np.ones(len(v), bool)
        return _calibration(model, protocol, used, sign, 1.0, 1.0, background, z0, v, masked, "as recorded", {}, [])

    masked["zero"] = np.abs(v) <= 1e-12 * np.max(np.abs(v))
    masked["saturated"] = _saturated(model, v, background, z0)
    usable = ~(masked["zero"] | masked["saturated"])
    if not usable.any():
        raise ValueError("every reading of the reference is zero or saturated: nothing to calibrate on")

    orientations, choice = _orientation(model, protocol, v, usable & ~driven, magnitude, background, z0)
    protocol, orientation_sign, orientation = choice
    if orientation != "as recorded":
        notes.append(
            f"the reference fits the model {orientations['as recorded'] / orientations[orientation]:.1f}x better "
            f"with {orientation}: check the electrode order and the drive's sign; imaging as if so"
        )
    nominal = _voltages(model, protocol, background, z0)
    if magnitude:
        sign = np.where(nominal < 0, -1.0, 1.0)
        masked["uncertain sign"] = uncertain_sign(nominal)
    else:
        sign = np.full(len(v), orientation_sign)
    signed = sign * v

    none = np.zeros(len(v), bool)
    masked["outlier"], masked["broken electrode"] = none, none
    # First the readings off the driven electrodes, which the contact impedance barely moves.
    used = usable & ~masked.get("uncertain sign", none) & ~driven
    for _ in range(2):  # fit, mask outliers and broken electrodes, refit
        voltages = _voltages(model, protocol, background, z0)
        scale = _scale(voltages[used], signed[used])
        used = _mask_outliers(protocol, signed, scale * voltages, used, usable, masked)
    factor = 1.0
    if driven.any() and driven_readings == "drop":
        masked["driven electrode"] = driven & usable
    elif driven.any():
        with_driven = used | (driven & usable)
        factor = _contact_factor(model, protocol, signed, with_driven, background, z0)
        voltages = _voltages(model, protocol, background, z0 * factor)
        # Driven readings of another sign than the model's spoil the level itself: a misfit of 100%.
        misfit_driven, contact = 1.0, z0 * factor
        if voltages[with_driven] @ signed[with_driven] > 0:
            contact, scale_driven = _electrode_contact_impedances(
                model, protocol, signed, with_driven, background, contact
            )
            voltages = _voltages(model, protocol, background, contact)
            misfit_driven = _relative(
                signed[driven & usable] - scale_driven * voltages[driven & usable], signed[driven & usable]
            )
        # Against the others' misfit without them: a fit the driven readings spoil misfits both.
        misfit_others = _relative(signed[used] - scale * _voltages(model, protocol, background, z0)[used], signed[used])
        if driven_readings == "auto" and misfit_driven > max(_DRIVEN_FACTOR * misfit_others, _DRIVEN_FLOOR):
            notes.append(
                f"readings on driven electrodes dropped: the model with fitted contact impedances misses them by "
                f"{misfit_driven:.0%}, the others by {misfit_others:.0%}"
            )
            masked["driven electrode"] = driven & usable
            factor = 1.0
        elif misfit_driven < 1.0 or driven_readings == "keep":
            scale, factor = (scale_driven, contact / z0) if misfit_driven < 1.0 else (scale, factor)
            used = _mask_outliers(protocol, signed, scale * voltages, with_driven, usable, masked)
    masked = {reason: mask & ~_earlier(masked, reason) for reason, mask in masked.items()}
    lost = {reason: mask for reason, mask in masked.items() if mask.any() and reason != "driven electrode"}
    if lost:
        notes.append(
            "masked readings: "
            + "; ".join(f"{reason} {name_indices(np.flatnonzero(mask))}" for reason, mask in lost.items())
        )
    return _calibration(
        model, protocol, used, sign, scale, factor, background, z0, v, masked, orientation, orientations, notes
    )


def _mask_outliers(protocol, data, voltages, used, usable, masked) -> np.ndarray:
    """`used` less the outliers of `data` against the model's `voltages` and the readings of
    broken electrodes (package docstring, step 5); records them in `masked`."""
    residual = data - voltages
    deviation = 1.4826 * np.median(np.abs(residual[used] - np.median(residual[used])))
    floor = np.maximum(np.abs(voltages), _OUTLIER_FLOOR * rms(voltages[used]))
    outlier = (
        used & (np.abs(residual) > _OUTLIER_DEVIATIONS * deviation) & (np.abs(residual) > _OUTLIER_RELATIVE * floor)
    )
    masked["outlier"] = masked["outlier"] | outlier
    broken = _uses(protocol, _broken_electrodes(protocol, ~usable | masked["outlier"]))
    masked["broken electrode"] = masked["broken electrode"] | (broken & usable & ~masked["outlier"])
    used = used & ~masked["outlier"] & ~masked["broken electrode"]
    if not used.any():
        raise ValueError("every reading of the reference is broken or an outlier: nothing to calibrate on")
    return used


def _calibration(
    model, protocol, used, sign, scale, factor, background, z0, v, masked, orientation, orientations, notes
):
    """Assemble the `ReferenceCalibration` of a fitted scale c and contact factor."""
    contact_impedance = z0 * factor * scale
    conductivity = background / scale
    calibrated = model.replace(protocol=protocol.select(used), contact_impedance=contact_impedance)
    voltages = np.asarray(calibrated.measure(jnp.full(model.n_elements, conductivity)))
    data = (sign * v)[used]
    misfit = _relative(data - voltages, data)
    correlation = float(np.corrcoef(data, voltages)[0, 1]) if len(data) > 1 else 1.0
    notes = list(notes)
    if correlation < _LEAST_CORRELATION:
        notes.insert(
            0,
            f"{_NOT_REPRODUCED} (correlation {correlation:.2f}, misfit {misfit:.0%}): "
            "check the protocol (electrode order, first electrode, drive sign), the sheet's geometry and the "
            "instrument's gains",
        )
    electrodes = np.flatnonzero(
        _broken_electrodes(protocol, ~used & ~masked.get("driven electrode", np.zeros_like(used)))
    )
    return ReferenceCalibration(
        model=calibrated,
        conductivity=float(conductivity),
        contact_impedance=np.asarray(contact_impedance),
        used=used,
        reading_sign=sign,
        orientation=orientation,
        orientations=dict(orientations),
        misfit=float(misfit),
        correlation=correlation,
        masked={reason: tuple(np.flatnonzero(mask).tolist()) for reason, mask in masked.items() if mask.any()},
        broken_electrodes=tuple(electrodes.tolist()),
        driven_readings="none"
        if not _driven(protocol).any()
        else ("kept" if (used & _driven(protocol)).any() else "dropped"),
        warnings=tuple(notes),
    )


def _saturated(model: ForwardModel, v: np.ndarray, background: float, z0: np.ndarray) -> np.ndarray:
    """(M,) bool: readings at the largest magnitude when two or more share it (a clipped rail),
    unless the model gives them equal magnitudes too (a symmetric sheet without noise)."""
    peak = np.abs(v) == np.max(np.abs(v))
    if np.count_nonzero(peak) < 2:
        return np.zeros(len(v), bool)
    expected = np.abs(_voltages(model, model.protocol, background, z0))
    return peak if np.ptp(expected[peak]) > 1e-6 * np.max(expected) else np.zeros(len(v), bool)


def _reference_mean(reference: np.ndarray, n_measurements: int) -> np.ndarray:
    array = np.asarray(reference, np.float64)
    if array.ndim not in (1, 2) or array.shape[-1] != n_measurements:
        raise ValueError(
            f"the reference has shape {array.shape}; expected ({n_measurements},) or (T, {n_measurements})"
        )
    if not np.all(np.isfinite(array)):
        raise ValueError("the reference holds non-finite values (NaN or inf): it cannot calibrate the model")
    return np.atleast_2d(array).mean(axis=0)


def _voltages(model: ForwardModel, protocol: Protocol, background: float, contact_impedance: np.ndarray) -> np.ndarray:
    """(M,) the voltages of a uniform sheet of `background` S/sq under `protocol`."""
    uniform = model.replace(protocol=protocol, contact_impedance=contact_impedance)
    return np.asarray(uniform.measure(jnp.full(model.n_elements, background)))


def auto_difference(calibration: Any, *, given: bool) -> tuple[Literal["calibrated", "normalised"], str]:
    """The differences `diffeit.reconstruct` images with `difference="auto"`, and why.

    With a skin calibration given (`given`), "calibrated" when its model follows the reference
    at all (correlation at least 0.5): the calibration fitted what its session determines, and
    a ratio per reading would carry the model's remaining error into every difference.
    Otherwise "calibrated" when the calibrated model reproduces the reference (correlation at
    least 0.9), else "normalised": gains per reading are the explanation left.

    Arguments:
        calibration: A `ReferenceCalibration` or `SkinCalibration` (its `correlation` with
            the reference, as fitted).
        given: Whether it is a skin calibration the user gave (`diffeit.calibrate`'s), rather
            than the reference's own.

    Returns:
        "calibrated" or "normalised", and the reason (for the images' provenance).
    """
    if given and calibration.correlation >= _SKIN_LEAST_CORRELATION:
        return "calibrated", (
            f"a skin calibration whose model follows the reference (correlation {calibration.correlation:.3f}): a "
            "ratio per reading would carry the model's remaining error into every difference"
        )
    if calibration.correlation >= _LEAST_CORRELATION:
        return (
            "calibrated",
            f"the calibrated model reproduces the reference (correlation {calibration.correlation:.3f})",
        )
    return "normalised", (
        f"the calibrated model does not reproduce the reference (correlation {calibration.correlation:.3f} < "
        f"{_LEAST_CORRELATION}): gains per reading are the explanation left"
    )


def _scale(voltages: np.ndarray, data: np.ndarray) -> float:
    """c > 0 minimising ||data - c V||; raises `ValueError` when the data do not correlate
    positively with the model's voltages (no positive level explains them)."""
    scale = float(voltages @ data / (voltages @ voltages))
    if not scale > 0:
        raise ValueError(
            "the reference does not correlate positively with the model's voltages in any orientation tried: "
            "check the protocol (its order and sign, diffeit.protocol.convert) and the reference frame"
        )
    return scale


def _relative(residual: np.ndarray, data: np.ndarray) -> float:
    return float(np.linalg.norm(residual) / max(np.linalg.norm(data), 1e-300)) if len(data) else 0.0


def _driven(protocol: Protocol) -> np.ndarray:
    """(M,) bool: readings that use an electrode their drive applies current through."""
    return np.any((protocol.measure != 0) & (protocol.drive[protocol.drive_index] != 0), axis=1)


def _uses(protocol: Protocol, electrodes: np.ndarray) -> np.ndarray:
    """(M,) bool: readings that drive or measure through any electrode in the mask `electrodes`."""
    involved = (protocol.measure != 0) | (protocol.drive[protocol.drive_index] != 0)
    return np.any(involved & electrodes, axis=1)


def _broken_electrodes(protocol: Protocol, bad: np.ndarray) -> np.ndarray:
    """(L,) bool: broken electrodes, those with at least half of the readings that use them in
    `bad`. Worst first: the readings a broken electrode spoils no longer count against its
    neighbours, which share many of them."""
    involved = (protocol.measure != 0) | (protocol.drive[protocol.drive_index] != 0)
    broken = np.zeros(protocol.n_electrodes, bool)
    while True:
        counted = involved & ~np.any(involved & broken, axis=1, keepdims=True)
        counts = counted.sum(axis=0)
        fraction = (counted & bad[:, None]).sum(axis=0) / np.maximum(counts, 1)
        fraction[broken | (counts == 0)] = 0.0
        worst = int(np.argmax(fraction))
        if fraction[worst] < _BROKEN_ELECTRODE:
            return broken
        broken[worst] = True


def _earlier(masked: Mapping[str, np.ndarray], reason: str) -> np.ndarray:
    """Readings masked for a reason listed before `reason`: each reading is reported once."""
    before = np.zeros(len(next(iter(masked.values()))), bool)
    for name, mask in masked.items():
        if name == reason:
            return before
        before = before | mask
    return before


def _orientation(model, protocol, v, usable, magnitude, background, z0):
    """The misfit of each orientation, and the one adopted: (protocol, sign, name)."""
    n = protocol.n_electrodes
    labels = np.arange(n)
    relabellings = {
        "as recorded": labels,
        "the electrodes numbered the other way round": (-labels) % n,
        "the first electrode one on": (labels + 1) % n,
        "the first electrode one back": (labels - 1) % n,
    }
    misfits: dict[str, float] = {}
    candidates: dict[str, tuple[Protocol, float]] = {}
    data = v[usable]
    for name, position in relabellings.items():
        relabelled = protocol if name == "as recorded" else protocol.relabel(position)
        voltages = _voltages(model, relabelled, background, z0)[usable]
        if magnitude:
            voltages = np.abs(voltages)
        projection = float(voltages @ data / (voltages @ voltages))
        for sign, label in ((1.0, name), (-1.0, "the drive's sign flipped" if name == "as recorded" else None)):
            if label is None:
                label = f"{name}, the drive's sign flipped"
            if magnitude and sign < 0:
                continue
            scale = max(sign * projection, 0.0)
            misfits[label] = _relative(data - sign * scale * voltages, data)
            candidates[label] = (relabelled, sign)
    best = min(misfits, key=misfits.get)
    if misfits[best] * _ORIENTATION_GAIN > misfits["as recorded"]:
        best = "as recorded"
    return misfits, (*candidates[best], best)


def _contact_factor(model, protocol, data, used, background, z0) -> float:
    """The common factor f of the contact impedances minimising min_c ||data - c V(z0 f)|| on
    `used`, V at the conductivity `background` (S/sq, one value or one per element)."""
    uniform = model.replace(protocol=protocol, contact_impedance=z0)
    sigma = jnp.asarray(per_element(background, model.n_elements))

    def misfits(factors: np.ndarray) -> np.ndarray:
        contact = jnp.asarray(z0)[None] * jnp.asarray(factors)[:, None]
        voltages = np.asarray(_batched_readings(uniform, jnp.broadcast_to(sigma, (len(factors), len(sigma))), contact))
        voltages = voltages[:, used]
        scales = np.maximum(np.sum(voltages * data[used], axis=1) / np.sum(voltages**2, axis=1), 0.0)
        return np.linalg.norm(data[used] - scales[:, None] * voltages, axis=1)

    grid = misfits(_CONTACT_GRID)
    best = int(np.argmin(grid))
    low, high = np.log(_CONTACT_GRID[max(best - 1, 0)]), np.log(_CONTACT_GRID[min(best + 1, len(grid) - 1)])
    ratio = (math.sqrt(5) - 1) / 2
    for _ in range(12):  # golden section in log f
        a, b = high - ratio * (high - low), low + ratio * (high - low)
        left, right = misfits(np.exp([a, b]))
        low, high = (low, b) if left <= right else (a, high)
    return float(np.exp(0.5 * (low + high)))


@eqx.filter_jit
def _batched_readings(model: ForwardModel, conductivities: jax.Array, contact_impedances: jax.Array) -> jax.Array:
    """(K, M) `model`'s readings at each of K conductivities (K, E), S/sq, with each of K contact
    impedances (K, L), ohm m. Compiled once per model's shape and K: an unjitted `jax.vmap`
    traced the batched model again on every call (0.1 s a call; 2.7 s of a first 20-press
    calibration's 22, in the contact factor's search)."""
    return jax.vmap(model.measure)(conductivities, contact_impedances)


def _electrode_contact_impedances(
    model: ForwardModel, protocol: Protocol, data: np.ndarray, used: np.ndarray, background: float, start: np.ndarray
) -> tuple[np.ndarray, float]:
    """One contact impedance per electrode (ohm m, at `background`) and the scale c minimising
    ||data - c V(z)|| on `used`, from `start`: Levenberg-Marquardt on ln z, c in closed form at
    every step. The readings on driven electrodes determine each z; a weak pull (1% of the
    curvature's mean) towards `start` keeps an electrode they do not see where it was."""
    uniform = model.replace(protocol=protocol, contact_impedance=start)
    sigma = jnp.full(model.n_elements, background)
    log_z, anchor = np.log(start), np.log(start)

    def evaluate(log_z: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
        z = jnp.asarray(np.exp(log_z))
        voltages = np.asarray(uniform.measure(sigma, z))[used]
        slope = np.asarray(uniform.jacobian(sigma, z, wrt="contact_impedance"))[used] * np.exp(log_z)
        scale = float(voltages @ data[used] / (voltages @ voltages))
        return voltages, slope, scale, float(np.sum((data[used] - scale * voltages) ** 2))

    voltages, slope, scale, cost = evaluate(log_z)
    damping = 1e-3
    for _ in range(_CONTACT_STEPS):
        design = scale * slope
        curvature = design.T @ design
        pull = 0.01 * np.trace(curvature) / len(curvature)
        gradient = design.T @ (data[used] - scale * voltages) - pull * (log_z - anchor)
        step = np.linalg.solve(
            curvature + (pull + damping * np.trace(curvature) / len(curvature)) * np.eye(len(log_z)), gradient
        )
        trial = evaluate(log_z + step)
        if trial[3] < cost:
            log_z, (voltages, slope, scale, cost) = log_z + step, trial
            damping = max(damping / 10, 1e-6)
            if np.max(np.abs(step)) < 1e-4:
                break
        else:
            damping *= 10
    return np.exp(log_z), scale
