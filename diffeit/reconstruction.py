"""From a recording to images in one call (`reconstruct`), and the calibration of the model to
the recording's reference that it rests on (`calibrate_to_reference`).

## Calibration

A real instrument's reference frame v (a homogeneous tank, an untouched skin) is compared with
the model V(sigma, z) before anything is imaged. The model's voltages scale as
V(sigma, z) = V(1, z sigma) / sigma, so one factor c with v ~ c V(sigma_0, z_0) fixes the
conductivity level sigma_h = sigma_0 / c together with an unknown voltage unit (ADC counts):
the contact impedance moves with it (z_h = c z_0), keeping the contact length z sigma (m) of
the nominal model. c is a closed-form least-squares fit. In order:

1. **Broken readings** in the reference: exactly zero, or saturated (the largest magnitude,
   held by two or more readings whose model magnitudes differ: a clipped rail).
2. **Orientation.** The misfit ||v - c V|| / ||v|| is computed for the electrodes as recorded,
   numbered the other way round, and with the first electrode one on or one back, each with
   either sign of c (the drive's sign flipped; not for magnitudes). An alternative is adopted,
   with a warning naming it, when it at least halves the misfit as recorded; a symmetric sheet
   (a uniform disc) cannot tell rotations apart, and then the recording's own order stays.
3. **Magnitudes** (`readings="magnitude"`, boards that report |V|): each reading takes the sign
   of the model's reading, so that d|V| = sign(V) dV. Readings whose model value is under 5% of
   the model's RMS reading have an uncertain sign (a small model error flips it) and are masked.
4. **Readings on driven electrodes** (EIDORS 'meas_current') are dominated by the contact
   impedance: with them, a common factor of the contact impedance is fitted too (a 1-D search
   in log z). `driven_readings="auto"` keeps them when the fitted model reproduces them about
   as well as the others (relative misfit at most twice theirs, or 5%) once they have
   determined one contact impedance per electrode (Levenberg-Marquardt on ln z, from the
   common factor), and otherwise drops them with a warning; "keep" and "drop" force the
   choice.
5. **Outliers:** a reading whose residual exceeds both six robust standard deviations of the
   residuals (1.4826 MAD) and half the model's reading (or half of 10% of the RMS reading,
   when that is larger) is masked: a broken channel is off by a factor, a model's error by a
   few percent. An electrode with half or more of the readings it takes part in (driving or
   measuring) masked is broken, worst first: every reading that uses it is masked.

The result reports the relative misfit and the Pearson correlation between v and the
calibrated model on the readings used, and warns (`CalibrationWarning`) when the correlation
is under 0.9: the model does not reproduce the reference, whatever the images show.

Per-reading or per-channel gains are not fitted (the real tanks do not support them:
docs/tutorials/calibration.md). Normalised differences (`difference="normalised"`) divide by
the reference reading by reading, which is a gain per reading.

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
- "auto" (the default): "calibrated" when the calibrated model reproduces the reference
  (correlation at least 0.9), else "normalised": then the reference is not what the model
  predicts, and gains per reading are the explanation left (measured on the real tanks:
  docs/tutorials/real-recordings.md#which-differences).

## Hyperparameter "auto"

The corner of the L-curve of the calibrated, normalised one-step problem, from all frames at
once (`diffeit.inverse.select_hyperparameter(..., "lcurve")`); when the corner sits at an end
of the candidates, the noise figure 0.5 instead. Gauss-Newton iterates to the regularised
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
from collections.abc import Mapping
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from ._messages import name_indices
from .fit import background as fit_background
from .forward import ForwardModel
from .inverse import (
    GREIT,
    AbsoluteGaussNewton,
    AbstractSolver,
    GaussNewton,
    LinearisedProblem,
    OneStep,
    TotalVariation,
    select_hyperparameter,
)
from .io import Recording, mesh_from_geometry
from .mesh import Mesh, disc
from .protocol import Protocol
from .results import RESULTS, failed, names, throw_if_failed

Method = Literal["one_step", "gauss_newton", "total_variation", "greit"]
Difference = Literal["auto", "calibrated", "normalised"]
DrivenReadings = Literal["auto", "keep", "drop"]
METHODS = ("one_step", "gauss_newton", "total_variation", "greit")
SELECTION_METHODS = ("auto", "gcv", "lcurve", "noise_figure")

# A recording without a reference is calibrated on the mean of at most this many first frames.
REFERENCE_FRAMES = 5
# Adopt another orientation when it cuts the misfit as recorded by at least this factor.
_ORIENTATION_GAIN = 2.0
# A magnitude's sign is uncertain where the model's reading is under this fraction of its RMS.
_UNCERTAIN_SIGN = 0.05
# Outliers: a residual above this many robust standard deviations and above this fraction of the
# model's reading (itself at least the floor times the RMS reading): off by a factor, not by model error.
_OUTLIER_DEVIATIONS, _OUTLIER_RELATIVE, _OUTLIER_FLOOR = 6.0, 0.5, 0.1
# An electrode is broken when at least this fraction of the readings that use it are masked.
_BROKEN_ELECTRODE = 0.5
# Driven readings stay when their relative misfit is at most this factor times the others' (or the floor).
_DRIVEN_FACTOR, _DRIVEN_FLOOR = 2.0, 0.05
# Normalised differences mask readings whose gain V_ref / V_model is this many times off the median.
_LARGEST_GAIN = 30.0
# Gauss-Newton's "auto" hyperparameter over the one-step's (module docstring, "Hyperparameter").
_GAUSS_NEWTON_FACTOR = 4.0
# The model does not reproduce the reference below this correlation.
_LEAST_CORRELATION = 0.9
# Contact impedance factors searched (log-spaced) before a golden-section refinement, and the
# most Levenberg-Marquardt steps of the per-electrode fit that follows.
_CONTACT_GRID = np.logspace(-3, 3, 25)
_CONTACT_STEPS = 20
# The solver each method names, and GREIT's design when its hyperparameter is "auto".
_METHOD_SOLVERS = {"one_step": OneStep, "gauss_newton": GaussNewton, "total_variation": TotalVariation, "greit": GREIT}
_GREIT_NOISE_FIGURE = 0.5
# Frames per solve: one-step and GREIT in batches (one product and one progress step each), total
# variation frame by frame (a progress step each), Gauss-Newton (and any other solver) all at once.
_CHUNKS = {OneStep: 256, GREIT: 256, TotalVariation: 1}


class CalibrationWarning(UserWarning):
    """The model does not reproduce a recording's reference well, or the calibration changed
    how the recording is read (orientation, masked readings): the images may mislead."""


class ReferenceCalibration(eqx.Module):
    """The model calibrated to a recording's reference (module docstring, "Calibration").

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
    module docstring ("Calibration"); docs/tutorials/calibration.md shows it at work.

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
        masked["uncertain sign"] = np.abs(nominal) < _UNCERTAIN_SIGN * _rms(nominal)
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
    broken electrodes (module docstring, step 5); records them in `masked`."""
    residual = data - voltages
    deviation = 1.4826 * np.median(np.abs(residual[used] - np.median(residual[used])))
    floor = np.maximum(np.abs(voltages), _OUTLIER_FLOOR * _rms(voltages[used]))
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
    calibrated = _with(model, protocol.select(used), contact_impedance)
    voltages = np.asarray(calibrated.measure(jnp.full(model.n_elements, conductivity)))
    data = (sign * v)[used]
    misfit = _relative(data - voltages, data)
    correlation = float(np.corrcoef(data, voltages)[0, 1]) if len(data) > 1 else 1.0
    notes = list(notes)
    if correlation < _LEAST_CORRELATION:
        notes.insert(
            0,
            f"the model does not reproduce the reference (correlation {correlation:.2f}, misfit {misfit:.0%}): "
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
    return np.asarray(_with(model, protocol, contact_impedance).measure(jnp.full(model.n_elements, background)))


def _with(model: ForwardModel, protocol: Protocol, contact_impedance: np.ndarray) -> ForwardModel:
    """`model` under another protocol and contact impedance (same mesh, drive current and solver)."""
    return ForwardModel(model.mesh, protocol, contact_impedance, drive_current=model.drive_current, solver=model.solver)


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


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(values))))


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
    """The common factor f of the contact impedances minimising min_c ||data - c V(z0 f)|| on `used`."""
    uniform = _with(model, protocol, z0)
    sigma = jnp.full(model.n_elements, background)
    measure = jax.vmap(lambda factor: uniform.measure(sigma, jnp.asarray(z0) * factor))

    def misfits(factors: np.ndarray) -> np.ndarray:
        voltages = np.asarray(measure(jnp.asarray(factors)))[:, used]
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


def _electrode_contact_impedances(
    model: ForwardModel, protocol: Protocol, data: np.ndarray, used: np.ndarray, background: float, start: np.ndarray
) -> tuple[np.ndarray, float]:
    """One contact impedance per electrode (ohm m, at `background`) and the scale c minimising
    ||data - c V(z)|| on `used`, from `start`: Levenberg-Marquardt on ln z, c in closed form at
    every step. The readings on driven electrodes determine each z; a weak pull (1% of the
    curvature's mean) towards `start` keeps an electrode they do not see where it was."""
    uniform = _with(model, protocol, start)
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


def reconstruct(
    recording: Recording,
    *,
    method: Method | None = None,
    solver: AbstractSolver | None = None,
    prior: str | None = None,
    hyperparameter: float | str | None = None,
    calibrate: bool = True,
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

    The reference is the recording's, its frame `reference_frame`, or the mean of its first
    `REFERENCE_FRAMES` frames when it has none. The model (the sheet `mesh`, else
    `default_mesh(recording, h)`; the recording's protocol; `contact_impedance` at
    `background`) is calibrated to it by `calibrate_to_reference` (level, orientation, signs of
    magnitudes, driven readings, broken channels; its warnings are issued as
    `CalibrationWarning`), and optionally a smooth background map is fitted to it
    (`diffeit.fit.background`). The frames' differences (module docstring, "Which
    differences") are then imaged at that state by the solver: a solver object's settings
    bound to the calibrated model and background (`solver.bound(model, background)`), or the
    solver a `method` names. The choices and their measurements on real tanks are in
    docs/tutorials/real-recordings.md.

    Arguments:
        recording: The frames, with their protocol (and reference, mesh or geometry).
        method: A shorthand for a solver: "one_step" (`OneStep` with `prior`, the default),
            "gauss_newton" (`GaussNewton` with `prior`), "total_variation" (`TotalVariation`)
            or "greit" (`GREIT`, 32 x 32 pixels, designed for noise figure 0.5 when the
            hyperparameter is "auto"). Not together with `solver`.
        solver: A solver object (`OneStep`, `GaussNewton`, `TotalVariation`, `GREIT`; built
            with or without a model): its settings are used, on the calibrated model and
            background. Not a normalised `OneStep` (use `difference="normalised"`) nor
            `AbsoluteGaussNewton`.
        prior: The prior of "one_step" and "gauss_newton" (default "noser"); a solver object
            brings its own.
        hyperparameter: Unit-free, or "auto" (module docstring), or a method of
            `diffeit.inverse.select_hyperparameter` ("gcv", "lcurve", "noise_figure"),
            chosen from all frames at once. None: "auto" for a `method`, the solver's own
            for a solver object (a value or rule given replaces it).
        calibrate: Calibrate the model to the reference (False keeps the nominal model,
            signing magnitudes only).
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
        provenance's metadata holds the calibration (`ReferenceCalibration.summary`), the
        method, prior, hyperparameter and how it was chosen (with what each selection method
        gives and its code's name), every option, and the outcome: "results", the name of
        each frame's `diffeit.results.RESULTS` code (the solver's; `nonfinite` for an image
        that is not finite, which is then zero), "frames_failed", how many are not
        "successful", and the background map's code in `["background_map"]["result"]`.

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
    shorthand = solver is None
    solver, method = _unbound_solver(method, solver, prior, max_iterations)
    if shorthand:
        prior = "noser" if prior is None else prior
        hyperparameter = "auto" if hyperparameter is None else hyperparameter
    else:
        prior = getattr(solver, "prior", None)
    mesh = default_mesh(recording, h) if mesh is None else mesh
    if recording.reference is not None or reference_frame is not None:
        reference = recording.reference_values(reference_frame)
        reference_source = "recording" if reference_frame is None else f"frame {reference_frame}"
    else:
        count = min(REFERENCE_FRAMES, recording.n_frames)
        reference = recording.frames[:count].mean(axis=0)
        reference_source = f"mean of the first {count} frames"
    nominal = ForwardModel(mesh, recording.protocol, contact_impedance=contact_impedance)
    calibration = calibrate_to_reference(
        nominal,
        reference,
        readings=recording.readings,
        background=background,
        driven_readings=driven_readings,
        fit=calibrate,
    )
    for note in calibration.warnings:
        warnings.warn(note, CalibrationWarning, stacklevel=2)
    model = calibration.model
    level = calibration.conductivity
    frames = calibration.signed(recording.frames)
    signed_reference = calibration.signed(reference)
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
        model, level = _with(model, model.protocol, fitted.contact_impedance), fitted.conductivity
        map_summary = {
            "misfit": fitted.misfit,
            "hyperparameter": fitted.hyperparameter,
            "result": names(fitted.result)[0],
            "range": [float(level.min()), float(level.max())],
        }
    dv = frames - signed_reference
    if difference == "auto":
        difference = "calibrated" if calibration.correlation >= _LEAST_CORRELATION else "normalised"
    unsafe: list[int] = []
    if difference == "normalised":
        model, dv, unsafe = _normalised(model, dv, signed_reference, level, calibration)
    value, choice = _hyperparameter_of(solver, model, dv, hyperparameter, "noser" if prior is None else prior, level)
    if isinstance(solver, GREIT) and hyperparameter == "auto":
        solver = solver.bound(model, level, noise_figure=_GREIT_NOISE_FIGURE)
    else:
        solver = solver.bound(model, level, hyperparameter=value)
    images, codes = _images(solver, dv, progress)
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
        "max_iterations": max_iterations if shorthand else getattr(solver, "max_iterations", None),
        "results": names(codes),
        "frames_failed": int(failed(codes).sum()),
        "difference": difference,
        "unsafe_ratio_readings": unsafe,
        "reference": reference_source,
        "calibrated": bool(calibrate),
        "calibration": calibration.summary(),
        "background_map": map_summary,
        "background": background,
        "contact_impedance": contact_impedance,
        "readings": recording.readings,
        "input_source": recording.provenance.get("source", ""),
        "seconds": round(time.perf_counter() - start, 3),
    }
    return dataclasses.replace(
        recording,
        reference=reference if recording.reference is None else recording.reference,  # the recorded one is kept
        mesh=mesh,
        images=images,
        image_quantity="relative conductivity change" if relative else "conductivity change",
        provenance={"source": f"diffeit.reconstruct ({method})", "metadata": metadata},
    )


def _normalised(model, dv, reference, level, calibration) -> tuple[ForwardModel, np.ndarray, list[int]]:
    """The model and data of normalised differences: dV / V_ref times the calibrated model's
    voltages V_h, a gain g = V_ref / V_h per reading. Readings whose gain is not positive or is
    more than `_LARGEST_GAIN` times off the median gain, or where V_ref or V_h is under 5% of
    its RMS, are masked (their indices in the recording returned): there the ratio would blow
    up, flip a sign or divide noise by noise."""
    voltages = np.asarray(model.measure(jnp.broadcast_to(jnp.asarray(level), (model.n_elements,))))
    gain = reference / voltages
    positive = gain > 0
    # A ratio of two near-zero numbers says nothing: such readings go too, whatever their ratio.
    small = (np.abs(voltages) < _UNCERTAIN_SIGN * _rms(voltages)) | (
        np.abs(reference) < _UNCERTAIN_SIGN * _rms(reference)
    )
    off = np.abs(np.log(np.where(positive, gain, 1.0) / np.median(gain[positive]))) > np.log(_LARGEST_GAIN)
    safe = positive & ~off & ~small
    if not safe.any():
        raise ValueError("no reading of the reference has the model's sign: normalised differences are meaningless")
    unsafe = np.flatnonzero(calibration.used)[~safe].tolist()
    if unsafe:
        warnings.warn(
            f"normalised differences: readings {name_indices(np.array(unsafe))} masked, their reference is near zero "
            f"or disagrees with the model in sign or by more than a factor of {_LARGEST_GAIN:g}",
            CalibrationWarning,
            stacklevel=3,
        )
        model = _with(model, model.protocol.select(safe), model.contact_impedance)
    return model, (dv / gain)[:, safe], unsafe


def _hyperparameter(model, dv, hyperparameter, prior, level) -> tuple[float, dict[str, Any]]:
    """The value and how it was chosen: the rule, and the value of each selection method
    evaluated (one linearisation shared between them)."""
    if not isinstance(hyperparameter, str):
        return float(hyperparameter), {"rule": "given"}
    problem = LinearisedProblem(model, prior, level)

    def select(name: str) -> dict[str, Any]:
        selection = select_hyperparameter(model, dv, name, prior=prior, background=level, throw=False, problem=problem)
        return {
            "value": float(selection.value),
            "at_boundary": bool(selection.result != RESULTS.successful),
            "result": names(selection.result)[0],
        }

    if hyperparameter != "auto":
        chosen = select(hyperparameter)
        return chosen["value"], {hyperparameter: chosen, "rule": "given method", "method": hyperparameter}
    choice = {"lcurve": select("lcurve"), "rule": "auto"}
    rule = "lcurve" if not choice["lcurve"]["at_boundary"] else "noise_figure"
    if rule == "noise_figure":
        choice["noise_figure"] = select("noise_figure")
    return choice[rule]["value"], {**choice, "method": rule}


def _unbound_solver(
    method: str | None, solver: AbstractSolver | None, prior: str | None, max_iterations: int | None
) -> tuple[AbstractSolver, str]:
    """The solver `reconstruct` binds to the calibrated model (the one `method` names, or
    `solver`) and the method's name for the metadata, after checking the options."""
    if solver is not None:
        if method is not None:
            raise ValueError("give a method or a solver, not both")
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
        return OneStep(prior=prior), method
    if method == "gauss_newton":
        return GaussNewton(prior=prior, **limit), method
    if method == "total_variation":
        return TotalVariation(**limit), method
    return GREIT(), method


def _hyperparameter_of(
    solver: AbstractSolver, model, dv, hyperparameter, prior, level
) -> tuple[float | None, dict[str, Any]]:
    """The hyperparameter to bind `solver` with (None: the solver's own, or GREIT's design for a
    noise figure) and how it was chosen (module docstring, "Hyperparameter")."""
    if hyperparameter is None:
        return None, {"rule": "the solver's own"}
    if isinstance(solver, GREIT) and hyperparameter == "auto":
        return None, {"rule": f"GREIT designed for noise figure {_GREIT_NOISE_FIGURE}", "method": "noise_figure"}
    value, choice = _hyperparameter(model, dv, hyperparameter, prior, level)
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
