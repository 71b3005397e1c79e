"""The background map (the package's docstring, "Background map"): a smooth map of ln sigma fitted
to the reference at the calibrated model (`_background_fitted`, `_SheetFit`), kept where the
presses, read at it, land closer to their labels (`_with_background_map`).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._arrays import rms
from ..forward import ForwardModel
from ..io import Presses, Recording
from ._held_out import _median_read, _with_position_map
from ._paired import _SIGNIFICANCE, _closer, _signed_rank
from ._press_fit import _SHEET_PRIOR, _sheet_terms
from ._presses import _read_presses
from ._reference import _relative
from ._refine import _REFINE_ROUNDS, _UNDETERMINED, PRIORS, _levenberg_marquardt, _with_warnings
from ._skin import SkinCalibration


def _with_background_map(
    calibration: SkinCalibration,
    recording: Recording,
    presses: Presses | None,
    reference: np.ndarray,
    required: bool = True,
) -> SkinCalibration:
    """`calibration` with a background map fitted to the reference frames (package docstring,
    "Background map"). With `presses`, they are read at the map through a position map fitted
    again; unless `required`, the map is kept only when their leave-one-out errors are
    significantly smaller than those of `calibration` read the same way, both more often and
    by more (a one-sided sign test, `_closer`, and signed-rank test, `_signed_rank`, each at
    `_SIGNIFICANCE`), else `calibration` is returned with a note.

    A map changes every image: on the benchmark skins, maps the presses read closer by one test
    and not the other read the test presses farther. Presses held 1 s, 50 of 110 labelled at
    random (`benchmarks/session_layouts.py`, seed 1): 32 closer and 18 farther by 0.1 mm in the
    median (sign test p = 0.03, signed-rank 0.11), and of the 60 test presses 2 went unread and 5
    more read 20-110 mm off (the median 4.6 mm against 3.7 without it). Contacts drifting
    (`benchmarks/contact_drift.py`, seed 2): 31 closer and 19 farther (sign test p = 0.06,
    signed-rank under 0.05), the test presses' median 3.3 mm against 2.5 without it."""
    mapped = _background_fitted(calibration, reference)
    if mapped.background_map is None or presses is None:
        return mapped
    hyperparameter, polarity = calibration.hyperparameter, calibration.polarity
    found, further, chosen, polarity = _read_presses(mapped, recording, presses, reference, hyperparameter, polarity)
    mapped = _with_position_map(mapped, presses, found, further, chosen, polarity)
    if required:
        return mapped
    found, further, chosen, polarity = _read_presses(calibration, recording, presses, reference, chosen, polarity)
    uniform = _with_position_map(calibration, presses, found, further, chosen, polarity)
    ours, theirs = mapped.press_errors, uniform.press_errors
    closer, farther, often = _closer(ours, theirs)
    significance = max(often, _signed_rank(ours, theirs))
    if significance < _SIGNIFICANCE:
        return mapped
    sheet = mapped.background_map
    note = (
        f"the background map ({sheet.min():.4g} to {sheet.max():.4g} S/sq) is not kept: it reads {closer} presses "
        f"closer and {farther} farther (leave-one-out; median {1e3 * _median_read(ours):.1f} mm against "
        f"{1e3 * _median_read(theirs):.1f} mm without), not significantly closer (the larger of the "
        f"sign test's and the signed-rank test's p = {significance:.2f})"
    )
    return _with_warnings(calibration, note)


def _background_fitted(calibration: SkinCalibration, reference: np.ndarray) -> SkinCalibration:
    """`calibration` with its level and a smooth map of ln sigma fitted to the mean `reference`
    (package docstring, "Background map") with each contact impedance (ln z, the reference's
    prior about the calibration's), the readout and gains held; the
    calibration itself, with a note, when the data determine none of the map's terms."""
    data = calibration.signed(np.atleast_2d(reference).mean(axis=0))
    fit = _SheetFit.of(calibration.model, calibration.conductivity, calibration.contact_impedance)
    n, electrodes = fit.terms.shape[1], len(fit.contact_impedance)
    spread = np.r_[1.0, np.full(electrodes, PRIORS["contact_impedance"]), np.full(n, _SHEET_PRIOR)]
    fixed = np.zeros(len(spread), bool)
    scale = max(calibration.misfit, 1e-4) * rms(data)
    theta = np.zeros(len(spread))
    for _ in range(_REFINE_ROUNDS):
        theta, curvature = _levenberg_marquardt(fit, theta, data, scale, spread, fixed)
        residual = data - np.asarray(fit.readings(jnp.asarray(theta)))
        scale = max(float(np.sqrt(np.sum(residual**2) / max(len(data) - len(theta), 1))), 1e-9 * rms(data))
    all_errors = np.sqrt(np.diag(np.linalg.inv(curvature)))
    errors = all_errors[1 + electrodes :]
    if np.all(errors > _UNDETERMINED * _SHEET_PRIOR):
        note = "no background map: the reference determines none of its terms"
        return _with_warnings(calibration, note)
    # c V(sigma, z) = V(sigma / c, c z): the fitted factor moves the level and the contacts.
    factor = math.exp(theta[0])
    level = calibration.conductivity / factor
    contact = np.asarray(calibration.contact_impedance) * np.exp(theta[1 : 1 + electrodes]) * factor
    sheet = level * np.exp(np.asarray(fit.terms) @ theta[1 + electrodes :])
    fitted = np.asarray(fit.readings(jnp.asarray(theta)))
    undetermined = tuple(f"background[{i}]" for i in np.flatnonzero(errors > _UNDETERMINED * _SHEET_PRIOR))
    # The level's ln c and the contacts' ln z (from the first stage's) moved with the map; the
    # contacts' errors are the joint fit's.
    moved_values = {
        "level": calibration.values["level"] + theta[0],
        "contact_impedance": calibration.values["contact_impedance"] + theta[1 : 1 + electrodes],
    }
    moved_errors = {"contact_impedance": all_errors[1 : 1 + electrodes]}
    return eqx.tree_at(
        lambda c: (
            c.model,
            c.conductivity,
            c.background_map,
            c.contact_impedance,
            c.values,
            c.standard_errors,
            c.undetermined,
            c.fitted,
            c.misfit,
            c.correlation,
        ),
        calibration,
        (
            calibration.model.replace(contact_impedance=contact),
            float(level),
            sheet,
            contact,
            {**calibration.values, **moved_values, "background": theta[1 + electrodes :]},
            {**calibration.standard_errors, **moved_errors, "background": errors},
            (*calibration.undetermined, *undetermined),
            {**calibration.fitted, "reference": (*calibration.fitted["reference"], "background_map")},
            _relative(data - fitted, data),
            float(np.corrcoef(data, fitted)[0, 1]),
        ),
        is_leaf=lambda node: node is None,
    )


class _SheetFit(eqx.Module):
    """The calibrated model's readings of a smooth sheet: theta = (ln c, ln f (L,), the
    coefficients of ln sigma's terms), the readings c V(sigma_h exp(terms @ coefficients), z f)
    (as `_ReadoutFit`, for `_levenberg_marquardt`)."""

    model: ForwardModel
    conductivity: jax.Array
    contact_impedance: jax.Array
    terms: jax.Array

    @classmethod
    def of(cls, model: ForwardModel, level: float, contact_impedance: np.ndarray) -> _SheetFit:
        return cls(
            model,
            jnp.asarray(level, float),
            jnp.asarray(contact_impedance, float),
            jnp.asarray(_sheet_terms(model.mesh)),
        )

    def readings(self, theta: jax.Array) -> jax.Array:
        """(M,) the readings at `theta`, signed."""
        return _sheet_readings(self, theta)

    def jacobian(self, theta: jax.Array, free: np.ndarray) -> np.ndarray:
        """(M, n) the derivative of `readings` at `theta` (every parameter is free)."""
        return np.asarray(_sheet_jacobian(self, theta))


def _sheet_at(fit: _SheetFit, theta: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The sheet's conductivity (E,), S/sq, and the contact impedances (L,), ohm m, at `theta`."""
    electrodes = len(fit.contact_impedance)
    sigma = fit.conductivity * jnp.exp(fit.terms @ theta[1 + electrodes :])
    return sigma, fit.contact_impedance * jnp.exp(theta[1 : 1 + electrodes])


@eqx.filter_jit
def _sheet_readings(fit: _SheetFit, theta: jax.Array) -> jax.Array:
    return jnp.exp(theta[0]) * fit.model.measure(*_sheet_at(fit, theta))


@eqx.filter_jit
def _sheet_jacobian(fit: _SheetFit, theta: jax.Array) -> jax.Array:
    """(M, 1 + L + n) the derivative of `_sheet_readings` by the adjoint path: d/d ln c the
    readings, d/d ln f_l = dV/dz_l z_l, d/d coefficients = dV/d(ln sigma) @ terms (`jax.jacfwd`
    through the solves took three times as long with the contact impedances free)."""
    sigma, contact = _sheet_at(fit, theta)
    readings, along_sigma = fit.model.measure_and_jacobian(sigma, contact)  # one set of solves for both
    along_contact = fit.model.jacobian(sigma, contact, wrt="contact_impedance") * contact
    along_sheet = (along_sigma * sigma) @ fit.terms
    return jnp.exp(theta[0]) * jnp.concatenate([readings[:, None], along_contact, along_sheet], axis=1)
