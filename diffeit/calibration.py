"""Calibrating the model of a real skin and board: `calibrate` (a `SkinCalibration`) and its
first stage, `calibrate_to_reference` (a `ReferenceCalibration`).

A nominal model (the sheet's mesh, the protocol, a contact impedance) reproduces a real board's
reference frame only roughly: the board's voltage unit, the contacts, the readout and the gains
differ. `calibrate` fits what the reference frames determine, in two stages, and with labelled
presses maps the reconstructed touch positions onto the labels.

## First stage (`calibrate_to_reference`)

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

The first stage fits no gains; the refinement below can.

## Refinement (`calibrate`)

After the first stage, one regularised least-squares fit (Levenberg-Marquardt, priors on
every group; the Jacobian in closed form from the electrode potentials and the contact
impedances' adjoint derivative, the electrode positions' and widths' columns by `jax.jacfwd`
through the forward model) refines the level (a factor c
with the voltage unit) and the groups `reference_groups` names, against the reference's
readings in use:

- "contact_impedance": one per electrode, ln z, prior standard deviation 1 (the default);
- "mixing": the readout's (`diffeit.readout.Readout`: source, sink and offset weights), prior
  standard deviation 0.3 of the pair's weight. From a reference (the default) only the
  source electrode's and the far electrode's weights, started from the best of a grid of
  the two: a magnitude board's readings flip sign along the way, where small steps from no
  mixing stop short. Not fitted (with a warning) to a reference the first stage's model
  correlates with under 0.5: what the model lacks is then something else, gains per reading
  or the wiring, that mixing would only mask;
- "drive_gains", "channel_gains": ln g per drive and per measuring channel, prior 0.5;
- "electrode_positions": how far each electrode's centre lies from the mesh's, along the
  boundary, prior standard deviation 0.1 of the mean spacing between electrode centres
  (`diffeit.ForwardModel`'s `electrode_shift`: the electrode terms are integrals over the part
  of each boundary edge an electrode covers, differentiable in its ends);
- "electrode_widths": how much longer each electrode is than the mesh's, prior standard
  deviation 0.2 of the mean electrode length. Each end of an electrode moves by its centre's
  shift plus or minus half its width change, bounded, smoothly, by three prior standard
  deviations of the positions and 0.45 of the narrowest gap between electrodes. Widths show
  mostly in the readings of driven electrodes and near them, where they trade with the
  contact impedance: the report names those the data do not determine.

Each fitted parameter comes with a standard error from the posterior covariance (the misfit's
scale estimated from the residual); one whose standard error is over 70% of its prior's is
reported as not determined. Measured in docs/tutorials/calibration.md: on a simulated skin
with mixing, the reference's two weights brought the touches from 47 mm to 6 mm; the other
weights, left free, traded with the sheet the model lacks.

## Presses

With labelled presses (`diffeit.io.Presses`), these fits follow. A press one of whose frames
a board garbled (its change from the frames about it over 0.15 of their norm and over 10 times
the presses' median: readings one place out of order change a frame by 0.26 to 0.6, a press by
about 0.01, a deep one by 0.1) is left out first, with a warning: one such press had cost a
session its fit. So is a press timed at an instant no frame lies within 3/4 of a frame's period
of (a frame lost: the nearest frame is the rest's, or another press's).

Each press's change is its frames' mean less the rest before it: the reference frames' mean, or
the rest frames just before the press where their mean stands out of the reference's noise (the
voltage test of `diffeit.touch` over every reading, z = 5), as `diffeit.touches` reads a touch
against the rest before it. What earlier presses left on a skin with memory is then not read
as this press's: a press's disc does not explain it, and the fits below bent the readout's
mixing and the contact impedances to it (`_press_changes`). A rest frame is one no press
changes: within the noise of the quietest frame since the previous labelled press, and not
moved from it towards this press (`_rests`). Presses not labelled, a press's onset before its
labelled instant, and a frame a board garbled are then no rest.

- **Polarity**: whether a press lowers the conductivity (-1) or raises it, from the sign of
  the presses' images.
- **The labels' frame** (scale, rotation, offset against the mesh's, and whether it is
  mirrored), the one whose discs explain the presses' differences best: it starts from the
  best (a mixing fit each) of the mesh's own frame and the similarities, turning and mirrored,
  that map the labels onto the positions read (`_label_frame`), and every presses' fit refines
  its scale, angle and offset with its other groups, by Gauss-Newton (below). Before, a
  Nelder-Mead search on the misfit of 80 mixing fits came first: 60% of a calibration of 8
  presses, and the calibration benchmark's skins read their test presses alike without it
  (docs/tutorials/calibration.md). A mirrored frame is a skin whose electrodes are numbered
  clockwise in the labels' axes (an indenter's or an image's y axis pointing the other way).
  On a curved skin the labels are points on its surface in the mesh's frame, and no frame is
  fitted.
- **The readout's mixing**, from the presses' differences: each press is a disc of the
  labelled centre and radius with an unknown depth, linearised at the calibrated level; the
  mixing enters linearly, and the depths and the mixing weights (with their prior) are solved
  together by Gauss-Newton (`_mixing_and_depths`), from the reference's weights. On magnitudes,
  a reading whose recorded changes follow its predicted ones in one sense beyond three standard
  errors takes that sign, the model's sign elsewhere (`_signs`): the presses, not the model,
  tell the sign of a reading near zero, and the frames are signed with them. The level is
  fitted again to the reference under the new mixing, and for the fit that is kept the contact
  impedances' common factor with it: the source electrode's potential, which the mixing adds
  to every reading of its drive, is mostly its contact's drop, and a level alone matched the
  reference by scaling the whole model, its response to a touch with it (touches read 1.09 to
  1.34 times as strong as they were on the calibration benchmark's skins; 0.87 to 0.96 with
  the factor).
  A board whose readings mix in its source electrode's potential moves every image's touch;
  the presses determine the weights where the reference does not.
- **Gains per reading** (with `press_groups=("mixing", "reading_gains")`): a gain of its own
  for each reading, prior standard deviation 0.2 of its relative change, fitted in turn with
  the weights and depths (closed form per reading given them; their geometric mean held at 1,
  a common factor being the depths'), and multiplied into the readout's gains. A reference
  cannot tell a reading's gain from the model's error there; the presses' differences can.
- **Electrode positions and a background map**, with the mixing: Gauss-Newton steps of the
  positions, of the coefficients of a smooth map of the sheet's ln sigma (the terms of the
  background map below, prior standard deviation 0.3 each), the weights and the depths
  together on the same differences (the derivative in the positions and the coefficients by
  `jax.jacfwd` through the forward model; a press lowers the sheet by a fraction of its own
  conductivity, so its pattern follows the map), and, with the map, of the labels' frame's
  scale, angle and offset (their derivative by central differences of the presses'
  footprints, prior standard deviations the search's first steps about the frame it found:
  searched on mixing fits at the reference's electrodes and uniform sheet, the frame took up
  the sheet's step), with their priors, a step halved until the presses' objective decreases,
  each followed by the mixing's own fit. A press's response
  measures the sheet where it is: fitted with a uniform sheet, a sheet 30% more conductive on
  one side moved the electrodes instead, up to 3 degrees off (docs/tutorials/calibration.md).
  By default (`press_groups=None`) the mixing alone and the mixing with the positions are both
  fitted (the map on request: on the benchmark's skins it placed the electrodes closer but
  read the test presses no closer), and the fuller set goes on to be compared with the
  reference's calibration unless the mixing alone reads significantly more of the held-out
  presses (below) closer (`_fullest_unless_beaten`). A
  fit that takes the model's correlation with the reference under 0.5, where
  `diffeit.reconstruct` would image normalised differences rather than the calibrated ones the
  presses were read at, is refused by name.
- **Held-out presses decide** whether the presses' fit is kept: the presses in five folds, each
  fold read at the mixing (and positions) fitted to the other four, through a position map fitted
  on those (each fold's fit starts where the fit of all the presses ended and takes at most two
  Gauss-Newton steps: a third less time, the same choices on the calibration benchmark). When
  the reference's calibration with a position map fitted on the same four folds reads
  significantly more of the presses closer than farther (a one-sided sign test, p < 0.05), the
  presses' fit made unseen presses worse: the reference's calibration is kept instead, with a
  warning giving both (`_kept_if_it_generalises`). Short of that the physical fit is kept.
  Kept, its press errors are these held-out ones. With fewer than 20 presses (folds under
  four) nothing can show it: the reference's calibration is kept, with a warning (with 10,
  folds of two passed fits that read the benchmark's test presses worse), and the presses'
  fit is not made unless the memory is fitted, which needs the labels' frame it finds. The
  presses' mixing fits every weight to a linearised disc model; a board or sheet the model
  does not capture can pull it anywhere, and only presses it did not see show it (measured
  in docs/tutorials/calibration.md).
- **A position map**: each press's frames are imaged at the calibrated model, its touch read
  (`diffeit.touch.read`), and a smooth map from read positions to labelled ones fitted: the
  read position plus a polynomial displacement of degree 0 (a shift), 1 (affine: the skin's
  orientation, scale and offset against the labels' frame), 2 or 3, or none, chosen by
  leave-one-out cross-validation on the presses (`PositionMap`). `diffeit.touches` applies it.
  With the labels' frame found (20 presses or more, on a flat skin), a touch the polynomial
  takes off the skin (it extrapolates beyond the presses) is taken to the nearest point of the
  skin's outline in that frame: a rim hill beside a press had been placed 1.2 radii from the
  centre.
  How high the further hills of the presses' images stand beside each one's highest (95% of
  the presses' below it) is the calibration's `ringing`, above which alone `diffeit.touches`
  reads a further touch: a single press is one touch.
  On a curved skin the polynomial is in x, y and z and the displaced touches are taken back
  onto the surface.
- **A size map** (`SizeMap`), with the labels' frame found (20 presses or more on a flat skin)
  or on a curved skin: gains on the radius and depth a touch reads at, smooth over the sheet,
  that take each press's to its labelled radius and its depth under its labelled disc at the
  calibrated model (a one-step image reads a press about twice as wide and a fifth as deep,
  more so in the sheet's middle). `diffeit.touches` reads through it.
- **Memory**, when every press is held over several frames: the skin's memory parameters
  fitted to the session's readings with the presses' holds known, each press's signature
  learned from its own frames, and its depth and how its readings bend with it from the
  calibrated model (`diffeit.fit.memory_from_press_readings`).

## Background map

A sheet whose conductivity varies (thickness, filler, a seam) images touches where its
sensitivity is not the uniform model's. The calibration can fit a smooth map of ln sigma to
the mean reference at the calibrated model, its readout and gains held and its contact
impedances fitted with it (held, they had taken up the sheet's gradient at the uniform sheet:
57x apart on a test skin whose truth is 3x, 3.6x fitted with the map): the level
times exp of the monomials of degree 1 and 2 in the elements' centroids (five coefficients on a
flat sheet, nine on a curved one, each less its area-weighted mean, prior standard deviation
0.3), by the refinement's Levenberg-Marquardt, with standard errors (a map none of whose terms
the data determine is not made). The calibration then images at it
(`SkinCalibration.background`). (`diffeit.fit.background`'s map of every element, its
hyperparameter by the discrepancy principle, spanned four decades on simulated skins whose
readout the model misses: a few smooth terms are what a reference can carry.)

A reference alone cannot tell a non-uniform sheet from the model's other errors (mixing,
positions, gains), which a map absorbs as readily; so by default the map is fitted only with
at least 20 labelled presses, to the reference, and kept only when the presses, read at it
through a position map fitted again, land closer to their labels (leave-one-out) at
significantly more presses than farther (a one-sided sign test at 5%: with 30 presses, at
least 20 of them); its press errors are then those leave-one-out ones. (A map the presses fit
with the electrode positions, when `press_groups` names it, is judged with the rest of their
fit, on held-out presses: above.)
`calibrate(..., background_map=True)` fits and keeps it in any case (the reference's map
where the presses' fit kept has none); `background_map=False` fits none (and refuses a
`press_groups` that names it).

The calibrated `ForwardModel` folds the mixing into its protocol's reading weights and carries
the fitted electrode positions (its `electrode_shift`); gains divide the recorded frames
(`SkinCalibration.signed`). The readings' noise, from the spread of the reference frames, is kept for the touch
detection of `diffeit.touches`.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Literal, NamedTuple

import equinox as eqx
import h5py
import jax
import jax.numpy as jnp
import numpy as np
import scipy.ndimage
import scipy.stats
from numpy.typing import ArrayLike

from ._arrays import frame_period, per_element
from ._messages import name_indices
from ._threads import host_algebra
from .fit import memory_from_press_readings
from .forward import ForwardModel
from .inverse import LinearisedProblem, OneStep, select_hyperparameter
from .inverse.hyperparameter import DEFAULT_CANDIDATES
from .io import (
    Presses,
    Recording,
    create_checked,
    mesh_from_geometry,
    read_attributes,
    read_checked,
    write_atomically,
    write_attributes,
)
from .memory import MemoryParameters
from .mesh import Mesh, disc, disc_fractions, onto_sheet, onto_surface, surface_distance
from .protocol import Protocol
from .readout import Readout, roles
from .results import RESULTS, failed, names
from .touch import (
    DETECTION,
    SIGNIFICANCE,
    _noise_test,
    _one_step_noise,
    _statistic,
    _whitened,
    polarity_of,
    read,
    subspace_statistic,
    touch_subspace,
)

DrivenReadings = Literal["auto", "keep", "drop"]

# A recording without a reference is calibrated on the mean of at most this many first frames;
# a session without presses on those of its first _SESSION_FRAMES that look untouched.
REFERENCE_FRAMES, _SESSION_FRAMES = 5, 200
# `_within_noise_of` follows the untouched trend out from the first run in at most this many passes.
_TREND_PASSES = 6
# A frame whose difference from the frames about it (`_DAMAGE_REACH` each side) exceeds this
# fraction of their norm is damaged, not touched (a board's glitch: a frame of zeros, one at
# another gain, readings out of order): never a reference frame; `diffeit.reconstruct` chooses
# the "auto" hyperparameter without a frame whose differences exceed it, and `diffeit.touches`
# reads no touch there (a press changes the readings by a few percent).
_LARGEST_CHANGE, _DAMAGE_REACH = 0.5, 4
# A labelled press whose frame changes more than this, and more than this factor times the
# presses' median change, is a glitch (`_presses_left_out`): readings one place out of order
# changed a frame by 0.26 of its norm (adjacent drive) to 0.6 (opposition); the presses of the
# tests' and the benchmark's skins by at most 0.006 and 0.019, deep ones (-0.8, up to 16 mm) by
# 0.105, 5.3 times their median.
_GLITCH_CHANGE, _GLITCH_FACTOR = 0.15, 10.0
# A frame whose readings, moved up to _MOVED_PLACES places along from some reading on, lie within
# _MOVED_FIT of its distance from the frames about it is damaged (`_readings_moved`).
_MOVED_PLACES, _MOVED_FIT = 2, 0.5
# A labelled press timed at an instant no frame lies within this fraction of the frames' median
# period of lost its frame (`_presses_left_out`): the nearest is the rest's or another press's.
# Not a half: frames' times jitter, and labels may be timed at a press's onset.
_LOST_FRAME = 0.75
# A recording's first frames that look touched are left out of its reference when they are at
# most this many (a board's first frames after it connects; `reference_frames`).
_LEADING_DAMAGED = 2
_DRIFT_DETECTION = 5.0  # z of a frame untouched but for its common gain (`drift_corrected`)
_DRIFT_WINDOW = 9  # untouched frames in the running median of their gains (`drift_corrected`)
# Runs of untouched frames shorter than this among touched ones are rests only when their gains
# stand apart from the presses beside them as a rest's do, where a press moves the gain by more
# than this many times a gain's noise (`_rests_not_presses`).
_LONG_REST, _PRESS_PART = 5, 4.0
_LEAST_NEAR = 3  # touched frames near untouched ones that tell a press's part of the common gain (`drift_corrected`)
_DRIFT_CHANCE = 1e-6  # the chance that the reference's own jitter passes for a drift (`drift_corrected`)
_ROUND_OFF = 1e-12  # a reading's spread under this fraction of its value is round-off, not noise (`drift_corrected`)
_LIVE_DRIFT_ERRORS = 3.0  # a stream's running gain is taken out beyond this many standard errors from 1 (`LiveDrift`)
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
# The model does not reproduce the reference below this correlation (the warning begins so).
_LEAST_CORRELATION = 0.9
_NOT_REPRODUCED = "the model does not reproduce the reference"
# Contact impedance factors searched (log-spaced) before a golden-section refinement, and the
# most Levenberg-Marquardt steps of the per-electrode fit that follows.
_CONTACT_GRID = np.logspace(-3, 3, 25)
_CONTACT_STEPS = 20


class CalibrationWarning(UserWarning):
    """The model does not reproduce a recording's reference well, or the calibration changed
    how the recording is read (orientation, masked readings): the images may mislead."""


class ReferenceCalibration(eqx.Module):
    """The model calibrated to a recording's reference (module docstring, "First stage").

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
    module docstring ("First stage"); docs/tutorials/calibration.md shows it at work.

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
    return np.asarray(_with(model, protocol, contact_impedance).measure(jnp.full(model.n_elements, background)))


def _with(
    model: ForwardModel, protocol: Protocol, contact_impedance: np.ndarray, margin: float | None = None
) -> ForwardModel:
    """`model` under another protocol and contact impedance (same mesh, electrodes, drive
    current and solver); with `margin`, its electrodes free to move that far, m, from where
    they are."""
    moved = {}
    if model.electrode_shift is not None or margin is not None:
        moved = {
            "electrode_shift": model.electrode_shift,
            "electrode_margin": model.system.electrode_margin if margin is None else margin,
        }
    return ForwardModel(
        model.mesh, protocol, contact_impedance, drive_current=model.drive_current, solver=model.solver, **moved
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
    """The common factor f of the contact impedances minimising min_c ||data - c V(z0 f)|| on
    `used`, V at the conductivity `background` (S/sq, one value or one per element)."""
    uniform = _with(model, protocol, z0)
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


# ---------------------------------------------------------------------------------------------
# The refinement and the skin's calibration

# Prior standard deviations of the refined groups (module docstring, "Refinement").
PRIORS = {
    "contact_impedance": 1.0,
    "mixing": 0.3,
    "drive_gains": 0.5,
    "channel_gains": 0.5,
    "electrode_positions": 0.1,
    "electrode_widths": 0.2,
    "reading_gains": 0.2,
}
# Gauss-Newton steps of the electrode positions on the presses, with the mixing and depths,
# each followed by the mixing's own fit: at most this many, until no electrode moves by this
# fraction of the positions' prior standard deviation; a step that does not decrease the
# presses' objective is halved, at most this many times, and then the fit stops there.
_POSITION_ROUNDS, _POSITION_STEP, _POSITION_HALVINGS = 10, 0.01, 5
# Gains per reading from the presses: rounds in turn with the weights and depths, until no ln g
# moves by the step.
_GAIN_ROUNDS, _GAIN_STEP = 30, 1e-6
# Electrodes may move this many prior standard deviations, and at most this fraction of the
# narrowest gap between two electrodes (they never meet).
_POSITION_REACH, _POSITION_GAP = 3.0, 0.45
# The groups a reference alone determines well enough to image with (docs/tutorials/calibration.md).
REFERENCE_GROUPS = ("contact_impedance", "mixing")
# The groups fitted to the presses' differences by default, each set in turn, the last kept unless an
# earlier one reads the held-out presses significantly closer (`_fullest_unless_beaten`), and those
# that can be.
PRESS_GROUP_CHOICES = (("mixing",), ("mixing", "electrode_positions"))
_PRESS_GROUPS_POSSIBLE = ("mixing", "electrode_positions", "reading_gains", "background_map")
# The fewest reference frames whose spread gives the readings' noise (the touch test needs 5 degrees of freedom).
_NOISE_FRAMES = 6
# An L-curve corner within this factor of an end of the candidates counts as at the end.
_CORNER_MARGIN = 10.0
# Presses read a median of this fraction of the skin's size or more from their labels are
# warned of (`_far_from_labels_noted`).
_FAR_FROM_LABELS = 0.25
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
# The central differences of the frame's refinement: this fraction of its `_frame_steps`.
_FRAME_DELTA = 0.2
# The labels' frame: ln scale, angle (rad), offset x and y (m), handedness (+1, or -1: mirrored).
_IDENTITY_FRAME = np.array([0.0, 0.0, 0.0, 0.0, 1.0])
# The presses' fit is judged on presses it did not see: every fifth press held out in turn, with
# at least this many presses (fewer cannot show it: the reference's calibration is kept). With
# 10, folds of two passed fits that read the benchmark's test presses worse in both such cases.
_HELD_OUT_FOLDS, _LEAST_HELD_OUT = 5, 20
# The Gauss-Newton steps of each fold's fit, from where the fit of all the presses ended
# (`_held_out_errors`).
_FOLD_ROUNDS = 2
# Gauss-Newton steps of the presses' depths and the readout's mixing, and the step (largest
# change of a weight) they stop at: 4 to 6 steps reach it.
_PRESS_ROUNDS, _PRESS_STEP = 30, 1e-6
# Halvings of a step that does not decrease the presses' objective before the fit stops there.
_PRESS_HALVINGS = 20
# A press is read against the rest frames before it, not the reference, where their mean stands
# out of the reference's noise at this z (`_press_changes`; the voltage test's), and a frame is
# one of those rests when it stands within it of the quietest before the press (`_rests`) and
# has moved from that one towards the press by at most `_REST_TOWARD` standard deviations.
_REST_MOVED, _REST_TOWARD = 5.0, 3.0
# A magnitude's sign follows the presses' differences where their projection on its predicted
# changes exceeds this many standard errors (`_signs`).
_SIGN_ERRORS = 3.0
# A parameter whose standard error exceeds this fraction of its prior's is not determined by the data.
_UNDETERMINED = 0.7
# Levenberg-Marquardt steps of the refinement, and the rounds that re-estimate the misfit's scale.
_REFINE_STEPS, _REFINE_ROUNDS = 25, 2
# The refinement stops when no parameter moves by more than this fraction of its prior's spread.
_REFINE_TOLERANCE = 1e-3
# The grid of the source's and far electrode's mixing weights the refinement starts from: -reach to reach.
_MIXING_REACH, _MIXING_GRID = 0.5, 41
# Mixing is fitted to a reference the first stage's model correlates with at least this well.
_MIXING_LEAST_CORRELATION = 0.5
# `diffeit.reconstruct` images a skin calibration's calibrated differences when its model
# correlates with the reference at least this well (else normalised ones): a presses' fit that
# takes a model below it is refused, its presses having been read at calibrated differences.
_SKIN_LEAST_CORRELATION = 0.5
# The prior standard deviation of each of the background map's coefficients (ln sigma, on
# terms of unit size over the sheet: module docstring, "Background map").
_SHEET_PRIOR = 0.3
# Kept by default when the presses are read closer with it at more presses than farther, at
# this one-sided significance (a sign test).
_SHEET_SIGNIFICANCE = 0.05
# The ringing a further touch must rise above: this quantile of the relative heights of the
# further hills in the presses' images (a press with none counts 0), at most the cap (a second
# touch half as deep as the first is always read).
_RINGING_QUANTILE, _RINGING_CAP = 0.95, 0.5
# Degrees of the position map tried by cross-validation (None: no map).
_MAP_DEGREES = (None, 0, 1, 2, 3)
# On a curved skin the monomials in x, y and z are nearly dependent (x^2 + y^2 + z^2 is constant
# on a sphere, to the mesh's flatness): the least squares drop directions this much weaker.
_MAP_RCOND = 1e-8


class PositionMap(eqx.Module):
    """A smooth map from touch positions read from images (the mesh's frame) to the labels'.

    The read position plus a displacement polynomial in the coordinates of total degree
    `degree`, fitted by least squares on labelled presses, the degree chosen by leave-one-out
    cross-validation (degree 0 shifts, 1 is affine: the labels' orientation, scale and offset;
    `degree=None` is the identity). On a curved skin the polynomial is in x, y and z and each
    displaced point is taken back onto the surface (`diffeit.mesh.onto_surface`): an affine
    map then turns, stretches and shifts touches along it. On a flat skin whose labels' frame
    is known (`held_to`), a point the polynomial takes off the skin (it extrapolates beyond the
    presses it was fitted on) is taken to the nearest point of the skin's outline in that frame.

    Attributes:
        degree: The polynomial's degree, or None for the identity.
        coefficients: (n_terms, D) the displacement polynomial's coefficients, on positions
            and displacements divided by `length`.
        length: The length, m, positions are divided by (the presses' spread).
        errors: Degree (str; "none" for the identity) -> the median leave-one-out distance, m,
            between mapped and labelled positions (on a curved skin along it:
            `diffeit.mesh.surface_distance`).
        surface: The curved skin's mesh the mapped points are taken onto; None on a flat one.
        sheet: The flat skin's mesh whose outline, in the labels' frame `frame`, holds the
            mapped points; None: they are not held.
        frame: (5,) the labels' frame onto the mesh's (`SkinCalibration.values["label_frame"]`:
            ln scale, angle (rad), offset x and y (m), handedness), with `sheet`; else None.
    """

    degree: int | None = eqx.field(static=True)
    coefficients: np.ndarray
    length: float
    errors: dict[str, float]
    surface: Mesh | None = None
    sheet: Mesh | None = None
    frame: np.ndarray | None = None

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """(..., D) the labels'-frame positions, m, of positions `points` (..., D) read in the
        mesh's frame; NaN stays NaN."""
        points = np.asarray(points, np.float64)
        if self.degree is None:
            return self.within(points)
        moved = points + _terms(points / self.length, self.degree) @ self.coefficients * self.length
        return self.within(moved) if self.surface is None else onto_surface(self.surface, moved)

    def held_to(self, sheet: Mesh, frame: np.ndarray) -> PositionMap:
        """This map, its points held to the flat skin `sheet`, seen in the labels' frame `frame`
        (as `frame`)."""
        return dataclasses.replace(self, sheet=sheet, frame=np.asarray(frame, np.float64))

    def within(self, points: np.ndarray) -> np.ndarray:
        """(..., 2) labels'-frame positions `points`, m, each off the skin taken to the nearest
        point of its outline (`diffeit.mesh.onto_sheet` in the mesh's frame: the labels' frame
        is a similarity of it); a copy of them when the map holds no sheet."""
        points = np.array(points, np.float64)
        if self.sheet is None or self.frame is None:
            return points
        scale, rotation = _similarity_of(self.frame)
        offset, mirror = self.frame[2:4], [1.0, self.frame[4]]
        in_mesh = _in_mesh_frame(points, self.frame)
        on_mesh = onto_sheet(self.sheet, in_mesh)
        moved = np.any(on_mesh != in_mesh, axis=-1)  # the others stay bit for bit
        points[moved] = (on_mesh[moved] - offset) @ rotation / scale * mirror
        return points

    @classmethod
    def fit(cls, read: np.ndarray, labelled: np.ndarray, mesh: Mesh | None = None) -> PositionMap:
        """The map from `read` (K, D) to `labelled` (K, D) positions, m, on the sheet `mesh`
        (needed for points on a curved skin, D = 3, which the map takes back onto it).

        Its degree is chosen by leave-one-out cross-validation among those that K presses
        determine with two to spare: a degree replaces a lower one when its median distance is
        lower.

        Raises:
            ValueError: For points on a curved skin without its `mesh`.
        """
        read, labelled = np.asarray(read, np.float64), np.asarray(labelled, np.float64)
        surface = None
        if read.shape[1] == 3:
            if mesh is None or mesh.nodes.shape[1] != 3:
                raise ValueError("a position map of points on a curved skin needs the skin's (surface) mesh")
            surface = mesh
        degree, errors = _chosen_degree(
            read,
            lambda degree: float(np.median(_leave_one_out_errors(read, labelled, degree, surface))),
        )
        length = _spread(labelled)
        coefficients = np.zeros((0, read.shape[1]))
        if degree is not None:
            shift = (labelled - read) / length
            coefficients, *_ = np.linalg.lstsq(_terms(read / length, degree), shift, rcond=_MAP_RCOND)
        return cls(degree, coefficients, length, errors, surface)


class SizeMap(eqx.Module):
    """Gains, smooth over the sheet, on the radius and the depth of touches read from images,
    fitted on labelled presses.

    A one-step image blurs a touch: it reads a press wider and shallower than it is, by factors
    that vary over the sheet (on the calibration benchmark's skins, presses of radius 10 mm and
    depth -0.3 read 1.6 to 3.1 times as wide and 0.11 to 0.43 times as deep, 10th to 90th
    percentile). ln(labelled radius / read radius) and ln(model depth / read depth) are each a
    polynomial in the read position (positions divided by `length`, as `PositionMap`'s), its
    degree chosen by leave-one-out cross-validation as `PositionMap`'s (None: a gain of 1); the
    model depth is the press's depth under its labelled disc at the calibrated model. A touch
    like the presses then reads at their radius and depth; one of another size in proportion.
    Beyond the presses the polynomial is not trusted: each ln gain stays within the range it
    takes at them.

    Attributes:
        radius_degree: The radius gain's polynomial degree, or None for a gain of 1.
        depth_degree: The depth gain's, or None.
        radius_coefficients: (n_terms,) the radius gain's polynomial coefficients (ln gain).
        depth_coefficients: (n_terms,) the depth gain's.
        limits: (2, 2) the smallest and largest ln gain of radius (row 0) and depth (row 1) at
            the presses.
        length: The length, m, positions are divided by (the presses' spread).
        errors: "radius" and "depth" -> degree (str; "none" for a gain of 1) -> the median
            leave-one-out |ln(read x gain / press's)|.
    """

    radius_degree: int | None = eqx.field(static=True)
    depth_degree: int | None = eqx.field(static=True)
    radius_coefficients: np.ndarray
    depth_coefficients: np.ndarray
    limits: np.ndarray
    length: float
    errors: dict[str, dict[str, float]]

    def __call__(self, points: np.ndarray, radius: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The radii and depths (...) of touches read at positions `points` (..., D), m in the
        mesh's frame, with their gains; NaN stays NaN."""
        scaled = np.asarray(points, np.float64) / self.length
        gains = [
            np.exp(np.clip(_terms(scaled, degree) @ coefficients, *limits)) if degree is not None else 1.0
            for degree, coefficients, limits in (
                (self.radius_degree, self.radius_coefficients, self.limits[0]),
                (self.depth_degree, self.depth_coefficients, self.limits[1]),
            )
        ]
        return np.asarray(radius) * gains[0], np.asarray(depth) * gains[1]

    @classmethod
    def fit(
        cls,
        read_positions: np.ndarray,
        read_radius: np.ndarray,
        read_depth: np.ndarray,
        radius: np.ndarray,
        depth: np.ndarray,
    ) -> SizeMap:
        """The gains that take the radii and depths (K,) read at `read_positions` (K, D), m, to
        the presses' `radius` (K,) and `depth` (K,) (presses read at no position, or whose read
        and press's values differ in sign, are left out).

        Raises:
            ValueError: For fewer than 3 presses left.
        """
        read_positions = np.asarray(read_positions, np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            targets = {
                "radius": np.log(np.asarray(radius, np.float64) / read_radius),
                "depth": np.log(np.asarray(depth, np.float64) / read_depth),
            }
        seen = np.all(np.isfinite(read_positions), axis=1)
        if seen.sum() < 3:
            raise ValueError(f"a size map needs 3 presses read or more; {int(seen.sum())} were")
        length = _spread(read_positions[seen])
        degrees, coefficients, limits, errors = {}, {}, [], {}
        for name, target in targets.items():
            kept = seen & np.isfinite(target)
            if kept.sum() < 3:
                raise ValueError(f"a size map needs 3 presses whose {name} was read or more; {int(kept.sum())} were")
            points, target = read_positions[kept] / length, target[kept]

            def held_out(degree: int | None, points: np.ndarray = points, target: np.ndarray = target) -> float:
                residuals = target if degree is None else _held_out_residuals(_terms(points, degree), target)
                return float(np.median(np.abs(residuals)))

            degrees[name], errors[name] = _chosen_degree(points, held_out)
            coefficients[name] = np.zeros(0)
            fitted = np.zeros(len(target))
            if degrees[name] is not None:
                terms = _terms(points, degrees[name])
                coefficients[name] = np.linalg.lstsq(terms, target, rcond=_MAP_RCOND)[0]
                fitted = terms @ coefficients[name]
            limits.append([fitted.min(), fitted.max()])
        return cls(
            degrees["radius"],
            degrees["depth"],
            coefficients["radius"],
            coefficients["depth"],
            np.array(limits),
            length,
            errors,
        )


def _chosen_degree(points: np.ndarray, held_out: Callable[[int | None], float]) -> tuple[int | None, dict[str, float]]:
    """The polynomial degree (None: no polynomial) of a map of `points` (K, D) chosen by
    cross-validation: among the degrees K points determine with two to spare, a degree
    replaces a lower one when its held-out median error `held_out(degree)` is lower; and each
    degree's error ("none" for None)."""
    errors = {"none": held_out(None)}
    degree = None
    for candidate in _MAP_DEGREES[1:]:
        if len(points) < _terms(points[:1], candidate).shape[1] + 2:
            break
        errors[str(candidate)] = held_out(candidate)
        if errors[str(candidate)] < errors["none" if degree is None else str(degree)]:
            degree = candidate
    return degree, errors


def _held_out_residuals(terms: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """The residuals (K, ...) of each of `targets` (K, ...) left out of the least-squares fit
    on `terms` (K, n_terms), through the fit's hat matrix."""
    coefficients, *_ = np.linalg.lstsq(terms, targets, rcond=None)
    hat = np.einsum("ij,ji->i", terms, np.linalg.pinv(terms))
    leverage = np.maximum(1.0 - hat, 1e-9).reshape((-1,) + (1,) * (targets.ndim - 1))
    return (targets - terms @ coefficients) / leverage


def _spread(points: np.ndarray) -> float:
    """The RMS distance, m, of `points` (K, D) from their mean (at least 1 um)."""
    return float(max(np.sqrt(np.mean(np.sum((points - points.mean(0)) ** 2, axis=1))), 1e-6))


def _terms(points: np.ndarray, degree: int) -> np.ndarray:
    """(..., n_terms) the monomials of total degree at most `degree` in the coordinates of
    positions (..., 2) (x^i y^j) or (..., 3) (x^i y^j z^k), by total degree."""
    if points.shape[-1] == 2:
        powers = [(i, total - i) for total in range(degree + 1) for i in range(total + 1)]
    else:
        powers = [
            (i, j, total - i - j) for total in range(degree + 1) for i in range(total + 1) for j in range(total - i + 1)
        ]
    return np.stack([np.prod(points ** np.array(power), axis=-1) for power in powers], axis=-1)


class SkinCalibration(eqx.Module):
    """The model of one skin and board, fitted to a calibration session by `calibrate`.

    Attributes:
        model: The calibrated `ForwardModel`: the readings used, in the orientation found,
            the readout's mixing folded into its reading weights, the fitted contact
            impedances, in the recording's voltage unit at `conductivity`.
        conductivity: sigma_h, the fitted level, S/sq in the recording's voltage unit.
        background_map: (E,) the sheet's conductivity fitted to the reference (or by the
            presses) on the mesh's elements, S/sq in the same unit (module docstring,
            "Background map"), or None: the
            sheet is taken uniform at `conductivity`. `background` is the one imaged at.
        contact_impedance: (L,) ohm m, in the same unit.
        electrode_centres: (L,) the electrodes' centres as arc length along the boundary, m,
            counter-clockwise from the first node of the mesh's electrode 0: the mesh's, moved
            by the fitted shifts when "electrode_positions" was fitted.
        readout: The fitted `diffeit.readout.Readout` on the readings used (its gains: the
            drive and channel gains that `signed` divides by, times a gain per reading when
            the presses fitted "reading_gains"; a reference cannot tell a reading's gain from
            the model's error there).
        used: (M,) bool, the recording's readings that are imaged.
        reading_sign: (M,) +-1, what a recorded reading is multiplied by to match the model.
        standard_errors: Group -> (n,) standard errors of the fitted parameters, as `values`
            (those the presses fit raised to their spread over the held-out folds where that
            is larger: `_with_fold_spread`).
        values: Group -> (n,) the fitted parameters: "level" (ln c: `conductivity` is the
            first stage's over c), "contact_impedance" (ln of each z / (c z_first), z_first
            the first stage's), "mixing" (source, sink, offsets), "drive_gains" and
            "channel_gains" (ln g), "electrode_positions" (the centres' shifts, m along the
            boundary), "electrode_widths" (the change of each electrode's length, m),
            "background" (the background map's coefficients).
        undetermined: Names of the fitted parameters the data did not determine.
        fitted: "reference" and "presses" -> the groups each determined.
        misfit: ||v - V|| / ||v|| of the refined model, and
            `correlation` (Pearson) on the readings used.
        position_map: The `PositionMap` fitted on labelled presses, or None.
        press_errors: (K,) distances, m, between mapped and labelled press positions, each
            press held out: of the presses' fit and the position map when the presses' fit
            is kept (five folds), of the position map alone otherwise (leave-one-out; with
            fewer than 20 presses always); NaN for a press no touch was read at, or left out
            as damaged; None without presses.
        press_positions: (K, 2), or (K, 3) on a curved skin, where each press was read, m,
            through the position map (NaN for a press no touch was read at, or left out as
            damaged), or None.
        noise: (M_used,) the standard deviation of one reading, in the units of `signed`, from
            the spread of the reference frames (None with fewer than 6): `diffeit.touches`
            tests each frame's differences against it.
        noise_frames: How many reference frames `noise` was estimated from.
        polarity: -1 when the presses lower the conductivity, +1 when they raise it; None
            without presses (`diffeit.touches` then reads it from the images).
        memory: The skin's `diffeit.memory.MemoryParameters` fitted to presses held over
            several frames (each free field also in `values["memory.NAME"]`, its standard
            error in `standard_errors["memory.NAME"]`), or None.
        hyperparameter: The one-step hyperparameter the presses were imaged at (images to be
            read through the position map are best made at it), or None.
        first_stage: The `ReferenceCalibration` the refinement started from (orientation,
            masked readings).
        warnings: What the calibration warns about, in words.
        protocol: The recording's protocol; `readings` its kind ("signed" or "magnitude").
        ringing: How high the further hills of the presses' images stand beside each one's
            highest, a fraction of its peak (the `_RINGING_QUANTILE` quantile over the
            presses, at most `_RINGING_CAP`): `diffeit.touches` reports a further touch only
            above it (a single press is one touch). None without a position map.
        size_map: The `SizeMap` that `diffeit.touches` reads touches' radii and depths
            through, fitted on labelled presses (20 or more on a flat skin: the labels' frame
            gives their radius in the mesh's), or None.
        reference: (M,) the mean of the reference frames the model was fitted to, as recorded
            (the mean of `noise_frames` frames), or None (a file written before it was kept):
            `diffeit.reconstruct` images a recording without untouched first frames against
            it (`calibrated_reference_frames`).
    """

    model: ForwardModel
    conductivity: float
    background_map: np.ndarray | None
    contact_impedance: np.ndarray
    electrode_centres: np.ndarray
    readout: Readout
    used: np.ndarray
    reading_sign: np.ndarray
    standard_errors: dict[str, np.ndarray]
    values: dict[str, np.ndarray]
    undetermined: tuple[str, ...]
    fitted: dict[str, tuple[str, ...]]
    misfit: float
    correlation: float
    position_map: PositionMap | None
    press_errors: np.ndarray | None
    press_positions: np.ndarray | None
    hyperparameter: float | None
    noise: np.ndarray | None
    noise_frames: int
    polarity: int | None
    memory: MemoryParameters | None
    first_stage: ReferenceCalibration
    warnings: tuple[str, ...]
    protocol: Protocol = eqx.field(static=True)
    readings: str = eqx.field(static=True)
    ringing: float | None = None
    size_map: SizeMap | None = None
    reference: np.ndarray | None = None

    @property
    def driven_readings(self) -> str:
        """ "none", "kept" or "dropped": the first stage's choice of the readings on driven electrodes."""
        return self.first_stage.driven_readings

    @property
    def background(self) -> float | np.ndarray:
        """The conductivity the model images at, S/sq in the recording's unit: the background
        map (E,) when one was fitted, else the level."""
        return self.conductivity if self.background_map is None else self.background_map

    def signed(self, frames: np.ndarray) -> np.ndarray:
        """(..., M_used): recorded frames (..., M) in the calibrated model's order, sign and
        gain: what the calibrated model's `measure` predicts."""
        frames = np.asarray(frames, np.float64)
        if frames.shape[-1] != self.protocol.n_measurements:
            raise ValueError(
                f"frames have {frames.shape[-1]} readings; this calibration's protocol has "
                f"{self.protocol.n_measurements}"
            )
        return (frames * self.reading_sign)[..., self.used] / np.asarray(self.readout.gains)

    def summary(self) -> dict[str, Any]:
        """The calibration in JSON-serialisable form, for provenance."""
        first = self.first_stage.summary()
        return {
            **first,
            "conductivity": self.conductivity,
            "contact_impedance": float(np.mean(self.contact_impedance)),
            "contact_impedance_per_electrode": [float(z) for z in self.contact_impedance],
            "misfit": self.misfit,
            "correlation": self.correlation,
            "first_stage_misfit": first["misfit"],
            "first_stage_correlation": first["correlation"],
            "mixing": [float(w) for w in self.values["mixing"]],
            "background_map_range": None
            if self.background_map is None
            else [float(self.background_map.min()), float(self.background_map.max())],
            "undetermined": list(self.undetermined),
            "position_map_degree": None if self.position_map is None else self.position_map.degree,
            "size_map_degrees": None
            if self.size_map is None
            else {"radius": self.size_map.radius_degree, "depth": self.size_map.depth_degree},
            "press_error_median": None if self.press_errors is None else float(np.median(self.press_errors)),
            "warnings": list(self.warnings),
        }

    def lines(self) -> list[str]:
        """The calibration's report, a line per finding."""
        first = self.first_stage
        mixing = self.values["mixing"]
        gains = np.exp(np.concatenate([self.values["drive_gains"], self.values["channel_gains"]]))
        lines = [
            f"readings used: {int(self.used.sum())} of {len(self.used)} ({first.orientation})",
            f"model against reference: misfit {first.misfit:.1%} -> {self.misfit:.1%}, "
            f"correlation {first.correlation:.3f} -> {self.correlation:.3f}",
            f"level sigma_h: {self.conductivity:.4g} S/sq (in the recording's unit)",
            "background: uniform at the level"
            if self.background_map is None
            else f"background map: {self.background_map.min():.4g} to {self.background_map.max():.4g} S/sq",
            "contact impedance per electrode, ohm m: " + " ".join(f"{z:.3g}" for z in self.contact_impedance),
            f"readout mixing: source {mixing[0]:+.3f} +- {self.standard_errors['mixing'][0]:.3f}, "
            f"sink {mixing[1]:+.3f} +- {self.standard_errors['mixing'][1]:.3f}, largest offset weight "
            f"{np.max(np.abs(mixing[2:])):.3f}",
            f"drive and channel gains: {gains.min():.3f} to {gains.max():.3f}",
            f"fitted from the reference: {', '.join(self.fitted['reference'])}; from the presses: "
            + (", ".join(self.fitted["presses"]) or "nothing"),
            self._positions_line(),
        ]
        if self.undetermined:
            lines.append(f"not determined by the data ({len(self.undetermined)}): " + ", ".join(self.undetermined))
        if "label_frame" in self.values:
            scale, angle, x, y, *handedness = self.values["label_frame"]  # files of versions 1 to 4: 4 values
            mirrored = ", mirrored (y -> -y first)" if handedness and handedness[0] < 0 else ""
            lines.append(
                f"labels' frame onto the mesh's: scale {math.exp(scale):.4g}, rotation {math.degrees(angle):+.1f} deg, "
                f"offset ({x:+.4g}, {y:+.4g}) m{mirrored}"
            )
        memory = [name.split(".", 1)[1] for name in self.values if name.startswith("memory.")]
        if memory:
            lines.append(
                "memory: "
                + ", ".join(
                    f"{name} {self.values['memory.' + name][0]:.3g} +- {self.standard_errors['memory.' + name][0]:.2g}"
                    for name in memory
                )
            )
        if self.position_map is not None:
            errors = ", ".join(f"{degree}: {1e3 * error:.1f} mm" for degree, error in self.position_map.errors.items())
            lines.append(
                f"position map: degree {self.position_map.degree} (leave-one-out median error by degree: {errors})"
            )
        if self.ringing is not None:
            lines.append(f"ringing: a further touch stands above {self.ringing:.2f} of the highest's peak")
        if self.size_map is not None:
            lines.append(self._sizes_line())
        lines.extend(f"warning: {note}" for note in self.warnings)
        return lines

    def _sizes_line(self) -> str:
        """The size map's line of the report: each gain's range and, by degree, its
        leave-one-out median factor off the presses'."""
        sizes, parts = self.size_map, []
        for row, (name, degree) in enumerate((("radius", sizes.radius_degree), ("depth", sizes.depth_degree))):
            low, high = np.exp(sizes.limits[row])
            off = ", ".join(f"{key}: {math.exp(error):.2f}x" for key, error in sizes.errors[name].items())
            parts.append(
                f"{name} x{low:.2f} to x{high:.2f}, degree {degree} (leave-one-out median off by degree: {off})"
            )
        return "size map (touches' radius and depth as the presses'): " + "; ".join(parts)

    def in_mesh_frame(self, points: ArrayLike) -> np.ndarray:
        """Points in the labels' frame (`diffeit.touches`' positions, the presses' labels) taken
        into the mesh's frame, to draw them on the mesh.

        Arguments:
            points: (..., D) positions, m; NaN stays NaN.

        Returns:
            (..., D) the positions in the mesh's frame, m: moved by the labels' frame
            (`values["label_frame"]`) on a flat skin calibrated with presses, else a copy.
        """
        points = np.array(points, np.float64)
        if "label_frame" not in self.values or points.shape[-1] != 2:
            return points
        frame = np.asarray(self.values["label_frame"], np.float64)
        return _in_mesh_frame(points, frame if len(frame) == 5 else np.append(frame, 1.0))  # versions 1-4: unmirrored

    @property
    def electrode_points(self) -> np.ndarray:
        """(L, D) each electrode's centre, m: `electrode_centres` taken onto the boundary (NaN
        for an electrode on another boundary loop)."""
        loop, arcs = _boundary_loop(self.model.mesh)
        points = self.model.mesh.nodes[loop]
        return np.stack([np.interp(self.electrode_centres, arcs, axis) for axis in points.T], axis=1)

    @property
    def electrode_lengths(self) -> np.ndarray:
        """(L,) each electrode's length along the boundary, m: the mesh's, changed by the
        fitted widths when "electrode_widths" was fitted."""
        lengths = np.asarray(self.model.system.electrode_lengths)
        shift = self.model.electrode_shift
        return lengths if shift is None else lengths + np.asarray(shift[:, 1] - shift[:, 0])

    def _positions_line(self) -> str:
        fitted = set(itertools.chain(*self.fitted.values()))
        if "electrode_positions" not in fitted:
            line = "electrode positions: the mesh's (not fitted)"
        else:
            shift, error = 1e3 * self.values["electrode_positions"], 1e3 * self.standard_errors["electrode_positions"]
            line = (
                f"electrode positions: moved {shift.min():+.2f} to {shift.max():+.2f} mm along the boundary "
                f"(standard errors {error.min():.2f} to {error.max():.2f} mm)"
            )
        if "electrode_widths" in fitted:
            width, error = 1e3 * self.values["electrode_widths"], 1e3 * self.standard_errors["electrode_widths"]
            line += (
                f"; widths changed {width.min():+.2f} to {width.max():+.2f} mm "
                f"(standard errors {error.min():.2f} to {error.max():.2f} mm)"
            )
        return line

    def save(self, path: str | Path, *, overwrite: bool = False) -> Path:
        """Write the calibration to an HDF5 file (schema "diffeit.calibration"), atomically and
        checksummed; `load` reads it.

        Arguments:
            path: The file to write (by convention `SKIN.cal.h5`).
            overwrite: Replace an existing file.

        Returns:
            The path written.
        """
        return _save(self, Path(path), overwrite)


def reference_frames(
    recording: Recording,
    reference_frame: int | None = None,
    presses: Presses | None = None,
    *,
    every_frame: bool = False,
) -> tuple[np.ndarray, str]:
    """The frames a recording's model is calibrated on, and where they come from.

    The recording's reference; else its frame `reference_frame`; else, with presses, the
    frames before the first press (or, when there are none, those outside every hold) that
    look untouched (`_untouched`, when more than `REFERENCE_FRAMES`: the presses labelled may
    be some of the session's, the others kept to test on); else
    the recording's first frames up to the first that looks touched (`_untouched`, among the
    first `_SESSION_FRAMES`, for more than `REFERENCE_FRAMES` frames), however few; when its
    first `_LEADING_DAMAGED` frames or fewer look touched (damaged), the untouched run after
    them; when more do, those (the untouched trend is the frames' median, and most of such a
    recording is one long press); the first `REFERENCE_FRAMES` when the recording holds no
    more (`every_frame`: every frame of the first `_SESSION_FRAMES` that looks untouched and
    lies within the noise of the first untouched run, `_within_noise_of`). A
    frame that looks damaged (`_damaged`: a frame of zeros, one at another gain) is never one
    of them, of 3 frames or more.

    Arguments:
        recording: The recording.
        reference_frame: A frame to use instead of the recording's reference.
        presses: The session's labelled presses, if any.
        every_frame: Without a reference or presses, take every frame of the first ones that
            looks untouched (a session; `_within_noise_of`), not just the first run.

    Returns:
        (T, M) the reference frames, and a description of them.
    """
    if recording.reference is not None or reference_frame is not None:
        source = "recording" if reference_frame is None else f"frame {reference_frame}"
        return np.atleast_2d(recording.reference_values(reference_frame)), source
    if presses is not None:
        # The labelled presses may be some of the session's (the rest kept to test on): the
        # frames outside them are the untouched ones among them.
        before = recording.times < presses.times[:, 0].min()
        if before.any():
            return _looking_untouched(recording.frames[before], recording.times[before], "before the first press")
        pressed = np.zeros(recording.n_frames, bool)
        for frames in presses.frames(recording.times):
            pressed[frames] = True
        if (~pressed).any():
            return _looking_untouched(recording.frames[~pressed], recording.times[~pressed], "outside the presses")
    if recording.n_frames > REFERENCE_FRAMES:
        session, session_times = recording.frames[:_SESSION_FRAMES], recording.times[:_SESSION_FRAMES]
        still = _untouched(session, session_times)
        # Only the first run: a light press later on can pass for untouched. A run shorter than
        # `REFERENCE_FRAMES` is kept as it is: the first frames beyond it had put a press into the
        # reference of a session with one untouched frame before its presses, and every
        # untouched frame after them then read as touched.
        first = int(np.argmax(still))  # `_untouched` passes some frames, the first ones when too few pass
        run = still[first:]
        end = first + (len(run) if run.all() else int(np.argmin(run)))
        if every_frame:
            leading = slice(first, end) if first <= _LEADING_DAMAGED else slice(0, first)
            kept = _within_noise_of(session, session_times, still, leading)
            return session[kept], f"the {int(kept.sum())} untouched frames of the first ones"
        if first == 0:
            return recording.frames[:end], f"mean of the first {end} frames (up to the first that looks touched)"
        if first <= _LEADING_DAMAGED:
            # A board's first frame or two after it connects can be damaged: left out.
            return recording.frames[first:end], (
                f"mean of frames {first} to {end - 1} (the first that look untouched; those before them look touched)"
            )
        # More leading frames than a glitch that look touched: the rest of the recording is most of
        # it one long press (the untouched trend `_untouched` starts from is the frames' median),
        # and the leading run is its reference.
        return recording.frames[:first], f"mean of the first {first} frames (up to the first of a long press)"
    whole = ~_damaged(recording.frames)
    if whole.all():
        return recording.frames, f"mean of the first {recording.n_frames} frames"
    kept = np.flatnonzero(whole)
    return recording.frames[kept], f"mean of frames {name_indices(kept)} (the others look damaged)"


def calibrated_reference_frames(recording: Recording, calibration: SkinCalibration) -> tuple[np.ndarray, str, int]:
    """The reference frames of a recording without a reference, imaged at a calibration of its
    skin: its own first untouched frames (`reference_frames`), unless one of them looks touched
    against the calibration's reference.

    A recording may start pressed: a test recording cut from a session, or one begun with a
    finger on the skin. Its own first frames then hold a press, and every frame is imaged
    against it (simulated, 60 single-frame presses with no rest: 9 of them missed). Where the
    calibration keeps its reference and the readings' noise, each of the recording's own first
    untouched frames is tested against that reference in the touch subspace (the statistic of
    `diffeit.touch.touched`; not their mean, in which a press among rests is diluted). Where one
    stands out:
    1. the others, when they are `REFERENCE_FRAMES` or more (a faint press the first frames'
       own test let pass: on a benchmark skin 3 of the first 26 frames);
    2. else the frames of the first `_SESSION_FRAMES` (not damaged) that lie within the noise of
       the calibration's reference, when there are any;
    3. else, where every frame differs from it: a skin that drifted since its calibration (a
       hydrogel dries, contacts change) still rests, and its frames at rest agree with each
       other: the own frames are kept when they are two or more and each lies within the noise
       of their mean;
    4. else the calibration's reference (the mean of its `noise_frames` frames).

    Arguments:
        recording: The recording (no reference of its own).
        calibration: The skin's calibration.

    Returns:
        (R, M) the reference frames, as recorded; a description of them; how many frames their
        mean stands for (R, or the calibration's `noise_frames` for its reference).
    """
    own, source = reference_frames(recording)
    stored, noise = calibration.reference, calibration.noise
    if stored is None or noise is None:
        return own, source, len(own)
    subspace = touch_subspace(calibration)
    count = calibration.noise_frames

    def statistic(frames: np.ndarray, against: np.ndarray, variance: float) -> np.ndarray:
        return _statistic(calibration.signed(frames) - calibration.signed(against), noise, count, variance, subspace)

    touched = statistic(own, stored, 1.0 + 1.0 / count) > DETECTION
    if not touched.any():
        return own, source, len(own)
    if np.sum(~touched) >= REFERENCE_FRAMES:
        return (
            own[~touched],
            f"{source}, but {int(touched.sum())} that look touched against the calibration's reference",
            int(np.sum(~touched)),
        )
    session = recording.frames[:_SESSION_FRAMES]
    quiet = ~_damaged(session) & (statistic(session, stored, 1.0 + 1.0 / count) <= DETECTION)
    if quiet.any():
        return (
            session[quiet],
            (
                f"the {int(quiet.sum())} frames of the first ones within the noise of the calibration's reference "
                f"(the recording's own, {source}, look touched against it)"
            ),
            int(quiet.sum()),
        )
    if len(own) >= 2 and np.all(statistic(own, own.mean(axis=0), 1.0 - 1.0 / len(own)) <= DETECTION):
        return own, f"{source}: every frame differs from the calibration's reference (a drift since)", len(own)
    return (
        stored[None],
        (
            f"the calibration's reference (the recording's own, {source}, look touched against it and differ from "
            "each other, and no frame lies within its noise)"
        ),
        count,
    )


def _looking_untouched(frames: np.ndarray, times: np.ndarray, where: str) -> tuple[np.ndarray, str]:
    """Those of `frames` (T, M), recorded at `times` (T,), that look untouched (`_untouched`,
    when there are more than `REFERENCE_FRAMES`; else those not damaged, `_damaged`), and
    their description, the frames `where` they are."""
    still = _untouched(frames, times) if len(frames) > REFERENCE_FRAMES else ~_damaged(frames)
    if still.all():
        return frames, f"the {len(frames)} frames {where}"
    return frames[still], f"the {int(still.sum())} frames {where} that look untouched (of {len(frames)})"


def _untouched(frames: np.ndarray, times: np.ndarray) -> np.ndarray:
    """(T,) bool, the frames (T, M) recorded at `times` (T,) that look untouched. Noise alone
    puts a frame at a distance from the untouched frames' trend that varies by about
    1 / sqrt(2 M) of itself (M readings); a frame further than (1 + 5 / sqrt(2 M)) times the
    median distance is touched. A skin drifts (a hydrogel dries, a board warms), so the
    distance is measured after the frame's own common gain against the trend is taken out, and
    the trend is each reading's straight line in time (seconds, not frame numbers: a test
    recording joins a session's first frames to its later ones), least squares over the frames
    kept. From the frames' median, a drift of 2% over a simulated session put the first frames
    among the touched ones, leaving a reference of 5 frames and no noise to test frames
    against; a line alone did so for a drift that levels off (5% with a 5 s time constant:
    single presses on a benchmark skin then read 41 mm off from the reference alone, 5 mm with
    the gain taken out). Three times: first against the frames' median (robust to the touched
    ones), then against the line through those kept; the first `REFERENCE_FRAMES` when fewer
    pass. A damaged frame (`_damaged`) is never untouched: with its gain taken out, a frame of
    zeros stood on the trend, and a reference holding one read no press of a session."""
    factor = 1.0 + 5.0 / math.sqrt(2.0 * frames.shape[1])
    design = _time_line(times)
    whole = ~_damaged(frames)

    def near(trend: np.ndarray, still: np.ndarray) -> np.ndarray:
        distance = _off_trend(frames, trend)
        return whole & (distance <= factor * np.median(distance[still]))

    still = near(np.median(frames[whole], axis=0), whole)
    for _ in range(2):
        if still.sum() < 3:  # no line through fewer
            break
        still = near(design @ np.linalg.lstsq(design[still], frames[still], rcond=None)[0], still)
    if still.sum() < REFERENCE_FRAMES:
        still = whole & (np.cumsum(whole) <= REFERENCE_FRAMES)
    return still


def _time_line(times: np.ndarray) -> np.ndarray:
    """(T, 2) the design of a straight line in time through frames at `times` (T,): ones, and
    the times about their mean over their largest distance from it."""
    time = np.asarray(times, np.float64) - np.mean(times)
    time = time / max(float(np.max(np.abs(time))), 1e-300)
    return np.column_stack([np.ones_like(time), time])


def _off_trend(frames: np.ndarray, trend: np.ndarray) -> np.ndarray:
    """(T,) each frame's (T, M) distance from the `trend` ((T, M) or (M,)) once the frame's own
    common gain against it is taken out (a drift's)."""
    trend = np.broadcast_to(trend, frames.shape)
    gains = np.sum(frames * trend, axis=1) / np.maximum(np.sum(trend * trend, axis=1), 1e-300)
    return np.linalg.norm(frames - gains[:, None] * trend, axis=1)


def _within_noise_of(frames: np.ndarray, times: np.ndarray, still: np.ndarray, leading: slice) -> np.ndarray:
    """(T,) bool: those of the frames (T, M) of the untouched run `leading` and of `still`
    (`_untouched`) that lie within the noise of the untouched trend through them, the noise
    measured on the run alone (3 frames or more; with fewer, or fewer than 3 passing, the run).

    `_untouched` measures the noise on the frames it passes: when most of a session's frames
    are presses (one after another, no rest between them), faint ones pass, and the noise they
    set lets more pass. On the calibration benchmark's skin, a session of 20 untouched frames
    then 110 presses back to back gave 60 "untouched" frames, 40 of them faint presses, and a
    calibration from them missed 15 of 60 presses (none now). The run's noise is the median
    distance of its frames from their mean, squared, over (1 - 1/n) (sigma^2 M, a faint press
    ending the run left out); a frame passes when its distance from the trend, its common gain
    taken out (as `_untouched`), is within (1 + 5 / sqrt(2 M)) times that of an untouched frame
    from a mean of the frames kept. The trend is the run's mean, then each reading's straight
    line in time through the frames kept once some lie outside the run: a rest level that
    drifts is followed outwards from the run."""
    run = np.zeros(len(frames), bool)
    run[leading] = True
    n = int(run.sum())
    if n < 3:
        return run
    variance = float(np.median(np.sum((frames[run] - frames[run].mean(axis=0)) ** 2, axis=1))) / (1.0 - 1.0 / n)
    factor = 1.0 + 5.0 / math.sqrt(2.0 * frames.shape[1])
    candidates = still | run
    line = _time_line(times)
    kept = run
    for _ in range(_TREND_PASSES):
        design = line if (kept & ~run).any() else line[:, :1]
        trend = design @ np.linalg.lstsq(design[kept], frames[kept], rcond=None)[0]
        distance = _off_trend(frames, trend)
        passed = candidates & (distance**2 <= factor**2 * variance * (1.0 + 1.0 / kept.sum()))
        if passed.sum() < 3:
            return run
        if np.array_equal(passed, kept):
            break
        kept = passed
    return kept


def _damaged(frames: np.ndarray) -> np.ndarray:
    """(T,) bool, the frames (T, M), in time order, whose change from the frames about them
    (`_change_from_about`) exceeds `_LARGEST_CHANGE`, or whose readings are theirs moved along
    (`_readings_moved`): a board's glitch (a frame of zeros, one at another gain, readings out
    of place), not a touch, and not a drift over so few frames.
    None of fewer than 3 frames (nothing to tell which is damaged), nor of frames that all
    look so."""
    if len(frames) < 3:
        return np.zeros(len(frames), bool)
    about = _about(frames)
    damaged = (_change_from(frames, about) > _LARGEST_CHANGE) | _readings_moved(frames, about)
    return np.zeros(len(frames), bool) if damaged.all() else damaged


def _glitched(differences: np.ndarray, reference: np.ndarray, frames: np.ndarray, recorded: np.ndarray) -> np.ndarray:
    """(T,) bool, the frames that are a board's glitch, not a touch (`diffeit.reconstruct` and
    `diffeit live`): their `differences` (T, M') exceed `_LARGEST_CHANGE` of the `reference`
    (M') they are from, or their readings as recorded, `frames` (T, M), are the `recorded`
    reference's (M,) moved along (`_readings_moved`)."""
    large = np.linalg.norm(differences, axis=1) > _LARGEST_CHANGE * np.linalg.norm(reference)
    return large | _readings_moved(frames, recorded)


def _readings_moved(frames: np.ndarray, about: np.ndarray) -> np.ndarray:
    """(T,) bool, the frames (T, M) whose readings are those of `about` ((T, M) or (M,)) moved
    one or two places along, from some reading on to the frame's end or from its start up to
    some reading: a board's stream that lost or gained a reading within a frame puts every
    reading after it in its neighbour's place. A frame is so when the readings moved fit it
    within `_MOVED_FIT` of its distance from `about` as they are. Neighbouring readings differ by
    far more than a press changes them (one place along changes a frame by 0.26 of its norm on an
    opposition board of magnitudes, 0.48 on an adjacent one; a press by a few percent), so a
    touched frame fits no moved readings; under adjacent drive a whole frame one place along
    changes it by less than `_LARGEST_CHANGE`, and was imaged as a touch."""
    frames = np.asarray(frames, np.float64)
    about = np.broadcast_to(np.asarray(about, np.float64), frames.shape)

    def running(squares: np.ndarray) -> np.ndarray:  # (T, M + 1): the sums over readings before j
        return np.concatenate([np.zeros((len(squares), 1)), np.cumsum(squares, axis=1)], axis=1)

    before = running((frames - about) ** 2)
    total = before[:, -1]
    best = total
    for places in (k for k in range(-_MOVED_PLACES, _MOVED_PLACES + 1) if k):
        moved_before = running((frames - np.roll(about, places, axis=1)) ** 2)
        # Moved from reading j on (j = 0: the whole frame), or up to reading j.
        from_j = before + (moved_before[:, -1:] - moved_before)
        up_to_j = moved_before + (total[:, None] - before)
        best = np.minimum(best, np.minimum(from_j.min(axis=1), up_to_j.min(axis=1)))
    return best < _MOVED_FIT**2 * total


def _change_from_about(frames: np.ndarray) -> np.ndarray:
    """(T,) each frame's (T, M, in time order; at least 3) distance from the median of the
    frames about it (`_about`), a fraction of that median's norm."""
    return _change_from(frames, _about(frames))


def _about(frames: np.ndarray) -> np.ndarray:
    """(T, M) the median of the frames (T, M, in time order) about each one (`_DAMAGE_REACH`
    each side; all of them, up to 9)."""
    if len(frames) <= 2 * _DAMAGE_REACH + 1:
        return np.broadcast_to(np.median(frames, axis=0), frames.shape)
    return scipy.ndimage.median_filter(frames, size=(2 * _DAMAGE_REACH + 1, 1), mode="reflect")


def _change_from(frames: np.ndarray, about: np.ndarray) -> np.ndarray:
    """(T,) each frame's (T, M) distance from `about` (T, M), a fraction of its norm."""
    return np.linalg.norm(frames - about, axis=1) / np.maximum(np.linalg.norm(about, axis=1), 1e-300)


@host_algebra
def drift_corrected(recording: Recording, reference_set: np.ndarray) -> tuple[Recording, np.ndarray | None]:
    """The recording with each frame divided by its common gain against the reference, and
    the gains (T,); the recording as it is and None when `reference_set` holds fewer than
    `_NOISE_FRAMES` frames, or ones identical to round-off (no noise to tell untouched frames by).

    A skin drifts: a hydrogel dries, a sheet and a board warm, and every reading moves with a
    common gain g(t). Untouched, the differences are then g(t) - 1 times the reference, far
    above the noise over a session, and every frame looks touched. Each frame's gain c_t is its
    least-squares multiple of the reference (the readings weighed by their noise); a frame is
    untouched when what is left, frame - c_t reference, stands within the reference frames'
    noise (`diffeit.touch`'s test of differences against a reference's noise, at z = 5), and its
    gain does not mark it as a press that moved the common part alone (`_rests_not_presses`:
    among presses one after another, those were all the untouched frames, and the drift followed
    them). The gains are the running median of the untouched frames' c_t over `_DRIFT_WINDOW` of
    them, interpolated in time to the touched frames (the nearest one's beyond them): a touch
    moves the readings' common part too, and one that moves little else passes for untouched
    (its own c_t took its touch out of 6 of 60 presses' frames on a benchmark skin, which were
    then missed). Touched frames more than half `_DRIFT_WINDOW` frame steps from every untouched
    one (presses one after another, which the untouched frames' gains no longer follow) take
    their own c_t instead, less a press's typical part of it (the median, over the touched
    frames near untouched ones, of their c_t less the untouched frames' gain there), in a
    running median over `_DRIFT_WINDOW` of them (on a benchmark skin whose gain grew 5% under 60
    presses one after another, the test presses were read 19.5 mm off with the nearest untouched
    gain held, 4.6 mm so). Gains are taken out only when the untouched frames' c_t spread beyond
    the reference frames' own jitter from one frame to the next, or the far touched frames'
    gains beyond the uncertainty of their running median and typical part (F tests at chance
    `_DRIFT_CHANCE`): estimated from the frames, each gain is as noisy as the readings' common
    part, and without drift dividing by them only adds that noise.

    Arguments:
        recording: The recording (frames as recorded).
        reference_set: (N, M) the frames its reference is the mean of (`reference_frames`).

    Returns:
        The recording, its frames divided by the gains, and the gains; or the recording and
        None (too few reference frames, or no drift beyond their jitter).

    Raises:
        ValueError: For reference frames that are not (N, M) finite readings of the
            recording's M, or, with a drift to take out, times that go backwards.
    """
    reference_set = _checked_reference_set(reference_set, recording.frames.shape[1])
    drift = _DriftReference.of(reference_set)
    if drift is None or recording.n_frames == 0:
        return recording, None
    common = drift.gains(recording.frames)
    ordered = not np.any(np.diff(recording.times) < 0)
    still = drift.untouched(recording.frames, common)
    if ordered:
        still = _rests_not_presses(recording.times, common, still, drift.jitter)
    gains = np.ones_like(common)
    if still.any() and ordered:
        # A running median over the untouched frames: a touch that moves the readings' common
        # part alone passes for untouched, and its own gain would take the touch out of its frame.
        smooth = scipy.ndimage.median_filter(common[still], size=_DRIFT_WINDOW, mode="nearest")
        gains = np.interp(recording.times, recording.times[still], smooth)
    # No drift beyond the reference frames' own jitter, no correction: dividing by noisy gains
    # cost a benchmark skin's nominal pipeline 4 of the 60 presses it had read.
    drifts = still.any() and _departs(common[still] - 1.0, drift.jitter, 1, drift.frames - 1)
    far = _beyond_untouched(recording.times, still) if ordered and still.any() else np.zeros_like(still)
    near = ~still & ~far
    if far.sum() > _DRIFT_WINDOW and near.sum() >= _LEAST_NEAR:
        # Presses one after another: their own gains less a press's typical part of it (the
        # median of the touched frames near untouched ones, less the untouched frames' gains
        # there), in a running median over `_DRIFT_WINDOW` of them. A lowered conductivity raises
        # a frame's common gain a little (a benchmark skin's presses of 10 mm at -30%: 0.39% +-
        # 0.08%); the running median takes one press's departure from the typical out of it.
        typical = float(np.median(common[near] - gains[near]))
        gains[far] = scipy.ndimage.median_filter(common[far] - typical, size=_DRIFT_WINDOW, mode="nearest")
        departure = common[far] - gains[far]
        varying = (1.4826 * np.median(np.abs(departure - np.median(departure)))) ** 2
        # Their level is as uncertain as the running median's and the typical part's medians.
        uncertainty = varying * np.pi / 2 * (1 / _DRIFT_WINDOW + 1 / near.sum())
        drifts = drifts or _departs(gains[far] - 1.0, uncertainty, far.sum(), far.sum() - 1)
    if not drifts:
        return recording, None
    if not ordered:
        backwards = np.flatnonzero(np.diff(recording.times) < 0)
        raise ValueError(
            f"the recording's times go backwards at frame {backwards[0] + 1}: its drift's gains cannot be "
            "interpolated in time"
        )
    return dataclasses.replace(recording, frames=recording.frames / gains[:, None]), gains


def _rests_not_presses(times: np.ndarray, gains: np.ndarray, still: np.ndarray, jitter: float) -> np.ndarray:
    """(T,) the frames `still` (T,) bool, at `times` (T,) in order, that are at rest, by their
    gains (T,): those of long runs (`_LONG_REST` frames or more), and those of the short runs
    among touched frames (and of the long runs next to a touched frame) whose gains stand nearer
    a rest's than a press's against the presses beside them.

    A press near the middle moves the readings' common part and little else, and its frame
    minus its gain times the reference passes for untouched (25 of 110 presses on the
    calibration benchmark's skin, 10 mm at -30%, each raising the gain 0.35%). Between rest
    frames a running median outvotes them; with presses one after another and no rest between,
    they were all the untouched frames after the reference, the drift followed them, and every
    frame was divided by the presses' typical gain (9 of 60 presses then missed).

    A press's part of the gain, p, is the median, over the touched frames within
    `_DRIFT_WINDOW` frame steps of a long run, of their gain less the rest's there (`_trend_at`
    of the `_DRIFT_WINDOW` long runs' frames nearest in time: a drift moves on from a run's
    end). Against the mean gain of the nearest touched frames before and after it, a rest's
    gain stands about -p off, a press's about 0 (a drift moves both alike): a short run's frame
    is a press when its gain less theirs lies nearer 0 than -p. When p is unknown (fewer than
    `_LEAST_NEAR` such frames: no long run, or a gap in time after it) or within
    `_PRESS_PART` times a gain's noise (sqrt(`jitter`)) of 0, every frame `still` is kept: a
    press that moves the gain by so little moves no drift."""
    touched = np.flatnonzero(~still)
    edges = np.flatnonzero(np.diff(np.r_[0, still.astype(int), 0])).reshape(-1, 2)
    long = np.zeros_like(still)
    for first, last in edges[edges[:, 1] - edges[:, 0] >= _LONG_REST]:
        long[first:last] = True
    if not len(touched) or not long.any():
        return still
    step = frame_period(times)
    near = touched[_time_to_nearest(times, long)[touched] <= (_DRIFT_WINDOW + 0.5) * step]
    if len(near) < _LEAST_NEAR:
        return still
    rest = np.flatnonzero(long)
    levels = []
    for t in near:
        nearest = rest[np.argsort(np.abs(times[rest] - times[t]), kind="stable")[:_DRIFT_WINDOW]]
        levels.append(_trend_at(times[nearest], gains[nearest], times[t]))
    part = float(np.median(gains[near] - np.asarray(levels)))
    if abs(part) <= _PRESS_PART * math.sqrt(jitter):
        return still
    # The short runs' frames after the first touch, and the long runs' frames next to a touch
    # (a press that passes for untouched, just before or after a run, joins it).
    edge = np.zeros_like(still)
    edge[touched[touched > 0] - 1] = edge[touched[touched < len(still) - 1] + 1] = True
    frames = np.flatnonzero(still & ((~long & (np.arange(len(still)) > touched[0])) | (long & edge)))
    before = touched[np.maximum(np.searchsorted(touched, frames) - 1, 0)]
    following = touched[np.minimum(np.searchsorted(touched, frames), len(touched) - 1)]
    beside = np.select(
        [(before < frames) & (following > frames), before < frames],
        [0.5 * (gains[before] + gains[following]), gains[before]],
        gains[following],
    )
    offset = gains[frames] - beside
    kept = still.copy()
    kept[frames[np.abs(offset) < np.abs(offset + part)]] = False
    return kept


def _trend_at(times: np.ndarray, gains: np.ndarray, time: float) -> float:
    """The gain at `time` of gains (n,) at `times` (n,): their median moved to `time` along their
    Theil-Sen slope (the median of the slopes between pairs of them), robust to a touch among
    them that passed for untouched; a median alone lags a steady drift by half their span."""
    first, second = np.triu_indices(len(gains), k=1)
    apart = times[second] - times[first]
    slopes = (gains[second] - gains[first])[apart != 0] / apart[apart != 0]
    slope = float(np.median(slopes)) if len(slopes) else 0.0
    return float(np.median(gains)) + slope * (time - float(np.median(times)))


def _departs(deviations: np.ndarray, variance: float, run: int, freedom: int) -> bool:
    """Whether gains' `deviations` from 1 (n,) stand beyond their noise `variance`, estimated
    with `freedom` degrees: an F test at chance `_DRIFT_CHANCE` on their robust mean square (the
    median square over 0.455, chi-square's median with one degree of freedom), `run` successive
    deviations counted as one (a running median's)."""
    spread = np.median(deviations**2) / 0.455
    return bool(spread > variance * scipy.stats.f.isf(_DRIFT_CHANCE, max(len(deviations) // run, 1), max(freedom, 1)))


def _beyond_untouched(times: np.ndarray, still: np.ndarray) -> np.ndarray:
    """(T,) the touched frames more than half `_DRIFT_WINDOW` frame steps from every untouched
    frame (`still`, (T,) bool, some true): presses one after another with no untouched frame
    between them, whose drift the untouched frames' gains no longer follow."""
    step = frame_period(times)
    return ~still & (_time_to_nearest(times, still) > (_DRIFT_WINDOW // 2 + 0.5) * step)


def _time_to_nearest(times: np.ndarray, marked: np.ndarray) -> np.ndarray:
    """(T,) the time, s, from each of `times` (T,), in order, to the nearest frame `marked`
    ((T,) bool, some true)."""
    at = times[marked]
    after = np.clip(np.searchsorted(at, times), 1, len(at)) - 1
    return np.minimum(np.abs(times - at[after]), np.abs(times - at[np.minimum(after + 1, len(at) - 1)]))


def _checked_reference_set(reference_set: ArrayLike, readings: int | None = None) -> np.ndarray:
    """`reference_set` as (N, `readings`) finite float64 frames (None: any number of readings),
    or a ValueError naming the problem."""
    reference_set = np.asarray(reference_set, np.float64)
    if reference_set.ndim != 2 or readings not in (None, reference_set.shape[1]):
        expected = "M" if readings is None else readings
        raise ValueError(
            f"reference_set must be (N, {expected}) frames of the recording's readings; got shape {reference_set.shape}"
        )
    if not np.all(np.isfinite(reference_set)):
        raise ValueError("reference_set holds non-finite values (NaN or inf)")
    return reference_set


class _DriftReference(NamedTuple):
    """What tells a frame's common gain against a reference (`drift_corrected`, `LiveDrift`):
    the reference (M,), the mean of `frames` frames, their noise (M,), the readings whose noise
    is above round-off (`kept`) and their weights (the reference over the noise squared), and
    `jitter`, the variance of one frame's gain (half the mean square of successive reference
    frames' gains' differences: blind to a slow drift among the reference frames themselves)."""

    reference: np.ndarray
    noise: np.ndarray
    frames: int
    kept: np.ndarray
    weighed: np.ndarray
    jitter: float

    @classmethod
    def of(cls, reference_set: np.ndarray) -> _DriftReference | None:
        """From the (N, M) reference frames; None for fewer than `_NOISE_FRAMES`, or frames
        identical to round-off (no noise to weigh or test by)."""
        if len(reference_set) < _NOISE_FRAMES:
            return None
        # The noise with each frame's own gain taken out first: the reference frames may drift too.
        reference = reference_set.mean(axis=0)
        norm = reference @ reference
        own = reference_set @ reference / norm if norm > 0 else np.ones(len(reference_set))
        noise = (reference_set / np.where(own > 0, own, 1.0)[:, None]).std(axis=0, ddof=1)
        # A spread at round-off (a noise-free simulation's) is no noise: gains tested against it
        # found a drift of 0% and divided the frames by it.
        kept = noise > _ROUND_OFF * np.abs(reference)
        if not kept.any():
            return None
        weighed = reference[kept] / noise[kept] ** 2
        gains = reference_set[:, kept] @ weighed / (reference[kept] @ weighed)
        return cls(reference, noise, len(reference_set), kept, weighed, float(0.5 * np.mean(np.diff(gains) ** 2)))

    def gains(self, frames: np.ndarray) -> np.ndarray:
        """(T,) each frame's least-squares multiple of the reference, the readings weighed by their noise."""
        return frames[:, self.kept] @ self.weighed / (self.reference[self.kept] @ self.weighed)

    def untouched(self, frames: np.ndarray, gains: np.ndarray) -> np.ndarray:
        """(T,) whether frame - gain * reference stands within the reference frames' noise
        (`diffeit.touch`'s test of differences against it, at z = `_DRIFT_DETECTION`)."""
        left = frames - gains[:, None] * self.reference
        return ~_noise_test(left, self.noise, self.frames, self.frames, _DRIFT_DETECTION)


class LiveDrift(eqx.Module):
    """A stream's drift, followed frame by frame (`diffeit live`): `drift_corrected` for frames
    that come one batch at a time, the future unknown.

    Each frame's common gain against the reference and its test for a touch are
    `drift_corrected`'s. The gain a frame is divided by comes from the latest `_DRIFT_WINDOW`
    untouched frames' gains (itself included when it is untouched): their median, moved to the
    frame's time along their Theil-Sen slope (the median of the slopes between pairs of them:
    a median alone lags a steady drift by half the window, and the frames then looked touched);
    robust, as the offline running median, to a touch that passes for untouched. It is taken
    as 1 while the median stands within `_LIVE_DRIFT_ERRORS` of its standard errors of 1
    (1.25 sqrt(jitter / n) for n gains), so that a steady skin's frames are not divided by
    noise. A frame that looks touched gets the untouched frames' gain at its time.

    Attributes:
        reference: What tells a frame's gain and touch (the reference frames'; `of`).
        times: (n,) the latest untouched frames' times, s, n at most `_DRIFT_WINDOW`.
        recent: (n,) their gains.
    """

    reference: _DriftReference
    times: np.ndarray
    recent: np.ndarray

    @classmethod
    def of(cls, reference_set: ArrayLike) -> LiveDrift | None:
        """The drift of a stream whose reference is the mean of `reference_set` (N, M), as
        streamed; None for fewer than 6 frames (no noise to tell untouched frames by).

        Raises:
            ValueError: For reference frames that are not (N, M) finite values.
        """
        reference = _DriftReference.of(_checked_reference_set(reference_set))
        return None if reference is None else cls(reference, np.zeros(0), np.zeros(0))

    def step(self, frames: ArrayLike, times: ArrayLike) -> tuple[np.ndarray, np.ndarray, LiveDrift]:
        """The frames (B, M), taken at `times` (B,) s, divided by their gains; the gains (B,);
        and the drift after them.

        Raises:
            ValueError: For frames that are not (B, M) with the reference's M readings, or
                times that are not (B,) finite.
        """
        frames = np.atleast_2d(np.asarray(frames, np.float64))
        times = np.atleast_1d(np.asarray(times, np.float64))
        if frames.ndim != 2 or frames.shape[1] != len(self.reference.reference):
            raise ValueError(
                f"frames must be (B, {len(self.reference.reference)}), the reference's readings; got {frames.shape}"
            )
        if times.shape != (len(frames),) or not np.all(np.isfinite(times)):
            raise ValueError(f"times must be {len(frames)} finite values, one per frame; got shape {times.shape}")
        common = self.reference.gains(frames)
        # A frame that is not finite (reported by its caller) must not poison the gains to come.
        still = self.reference.untouched(frames, common) & np.all(np.isfinite(frames), axis=1)
        kept_times, recent, gains = self.times, self.recent, np.ones(len(frames))
        for t in range(len(frames)):
            if still[t]:
                kept_times = np.append(kept_times, times[t])[-_DRIFT_WINDOW:]
                recent = np.append(recent, common[t])[-_DRIFT_WINDOW:]
            gains[t] = self._gain_at(kept_times, recent, times[t])
        return frames / gains[:, None], gains, eqx.tree_at(lambda d: (d.times, d.recent), self, (kept_times, recent))

    def _gain_at(self, times: np.ndarray, gains: np.ndarray, time: float) -> float:
        """The gain at `time` from untouched frames' `gains` at `times` (class docstring)."""
        if not len(gains):
            return 1.0
        median = float(np.median(gains))
        if abs(median - 1.0) <= _LIVE_DRIFT_ERRORS * 1.25 * math.sqrt(self.reference.jitter / len(gains)):
            return 1.0
        return _trend_at(times, gains, time)


def _drift_note(gains: np.ndarray) -> str:
    """The warning that a recording's frames were divided by their drifting common gains (T,)."""
    low, high = float(np.min(gains)), float(np.max(gains))
    return (
        f"the frames' common gain drifts over the recording, from {low:.4g} to {high:.4g} times the reference's "
        f"({100 * (high - low):.2g}%): each frame is divided by it (diffeit.calibration.drift_corrected)"
    )


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


def _skin_size(mesh: Mesh) -> float:
    """The skin's size, m: its farthest node from the nodes' mean."""
    return float(np.max(np.linalg.norm(mesh.nodes - mesh.nodes.mean(axis=0), axis=1)))


def _with_warnings(calibration: Any, *notes: str) -> Any:
    """`calibration` with `notes` added to its warnings."""
    return eqx.tree_at(lambda c: c.warnings, calibration, (*calibration.warnings, *notes))


@host_algebra
def _frame_steps(mesh: Mesh) -> np.ndarray:
    """(4,) the scale of a change of the labels' frame (ln scale, angle, offset x and y): the
    search's first steps, and the prior standard deviations of the frame's refinement about
    it (`_fit_presses`)."""
    size = _skin_size(mesh)
    return np.array([0.05, math.radians(3.0), 0.03 * size, 0.03 * size])


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
    reference_groups: tuple[str, ...] = REFERENCE_GROUPS,
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
    channels), then the refinement (module docstring): contact impedance per electrode, the
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
            is); the default, the contact impedances and the mixing's source and far
            electrode weights, is what a reference determines on a skin whose electrode
            positions and sheet the model does not know (measured in
            docs/tutorials/calibration.md). Mixing is not fitted (a warning says so) to a
            reference the first stage's model correlates with under 0.5. The presses fit
            every mixing weight.
        press_groups: The groups fitted to the presses' differences: "mixing" (always),
            "electrode_positions", "background_map" (module docstring) and "reading_gains" (a
            gain per reading, prior standard deviation 0.2 of its relative change). None: each
            set of `PRESS_GROUP_CHOICES` (the mixing; the mixing and the positions) in turn,
            the positions kept unless the mixing alone reads significantly more of the
            held-out presses closer (a sign test; measured in docs/tutorials/calibration.md).
        hyperparameter: The one-step hyperparameter the presses are imaged at; None chooses
            it from the presses' frames (`auto_hyperparameter`).
        memory: With presses held over at least `_HELD_FRAMES` frames each, fit the skin's
            memory to the session's readings, the presses' holds known
            (`diffeit.fit.memory_from_press_readings`).
        background_map: Fit a smooth map of the sheet's conductivity (module docstring,
            "Background map"). None: with at least 20 labelled presses, the presses' map when
            `press_groups` names it and their fit is kept, else the reference's, kept when it
            reads significantly more of them closer to their labels than farther
            (leave-one-out); without, not fitted (a reference alone cannot tell a non-uniform
            sheet from the model's other errors); True: fitted and kept; False: not fitted.

    Returns:
        The `SkinCalibration`.

    Raises:
        ValueError: For a recording without frames, presses outside the skin or outside the
            recording's time, presses that are all left out or whose times look off the
            recording's clock (`_presses_unseen`), an unknown prior group,
            `press_groups` without "mixing" or with a group the presses cannot fit (or
            "background_map" with `background_map=False`),
            a `background_map` other than None, True or False, a reference the model
            cannot be calibrated on.
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
    reference, _ = reference_frames(recording, reference_frame, presses, every_frame=True)
    as_recorded = recording, reference  # the memory's fit takes any common gain out itself
    recording, gains = drift_corrected(recording, reference)
    if gains is not None:  # the reference frames, and their spread, without the drift
        reference, _ = reference_frames(recording, reference_frame, presses, every_frame=True)
    nominal = ForwardModel(mesh, recording.protocol, contact_impedance=contact_impedance)
    first = calibrate_to_reference(
        nominal, reference, readings=recording.readings, background=background, driven_readings=driven_readings
    )
    if gains is not None:  # said with every later stage's warnings
        first = _with_warnings(first, _drift_note(gains))
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
    calibration = _refine_to_reference(first, reference, recording, priors, tuple(reference_groups))
    if presses is None:
        return _with_background_map(calibration, recording, None, reference) if background_map else calibration
    left_out, notes = _presses_left_out(presses, recording)
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


def _presses_left_out(presses: Presses, recording: Recording) -> tuple[np.ndarray, tuple[str, ...]]:
    """(K,) bool, the presses the calibration leaves out, and why, in words: those one of whose
    frames looks damaged, its change from the frames about it (`_change_from_about`, over the
    whole recording) over `_GLITCH_CHANGE` and over `_GLITCH_FACTOR` times the presses' median
    (a skin whose every press changes its readings that much has none left out: a board's
    glitch on one press's frame, its readings one place out of order, had cost a session its
    presses' fit, and a press changes the readings by a few percent); and those timed at an
    instant no frame lies within `_LOST_FRAME` of the frames' median period of (a frame
    missing: the nearest one is another's, or the rest's)."""
    frames, times = presses.frames(recording.times), recording.times
    left_out, notes = np.zeros(len(frames), bool), []
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
    if left_out.all():
        raise ValueError(f"every labelled press is left out: {'; '.join(notes)}")
    return left_out, tuple(notes)


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
    """ValueError for presses outside the recording's time, far outside the skin, or of another
    dimension than the mesh's."""
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
        spread = np.linalg.norm(metres - metres.mean(axis=0), axis=1).max()
        millimetres = 0.05 * size < spread and np.all(np.linalg.norm(metres - middle, axis=1) <= 1.5 * size)
        raise ValueError(
            f"press(es) {name_indices(np.flatnonzero(outside))} are outside the skin: more than 1.5 times its "
            f"radius ({size:.3g} m) from its centre (centres are in metres, about the mesh's centre)"
            + ("; in millimetres they lie on the skin: give their centres and radius in metres" if millimetres else "")
        )


def _refine_to_reference(
    first: ReferenceCalibration,
    reference: np.ndarray,
    recording: Recording,
    priors: Mapping[str, float] | None = None,
    groups: tuple[str, ...] = REFERENCE_GROUPS,
) -> SkinCalibration:
    """The refinement of a first stage on its reference frames (module docstring): the level
    and the parameter `groups`, without mixing (and a warning noted) when the first stage's
    model correlates with the reference under 0.5.

    Arguments:
        first: The first stage (`calibrate_to_reference`).
        reference: (N, M) or (M,) the reference frames, as recorded.
        recording: The recording they come from (its protocol and kind of readings).
        priors: Prior standard deviations by group; None for `PRIORS`.
        groups: The groups of `PRIORS` fitted.

    Returns:
        The `SkinCalibration` (no presses: no position map, no polarity).
    """
    priors = PRIORS if priors is None else priors
    if "mixing" in groups and first.correlation < _MIXING_LEAST_CORRELATION:
        # A reference the nominal model does not follow at all (the Montreal tank's, its channel
        # gains spanning 12x) is explained by mixing only in part, and wrongly: fitted there, it
        # misleads the images.
        others = tuple(group for group in groups if group != "mixing")
        calibration = _refine(first, reference, priors, recording, others)
        note = (
            f"the readout's mixing was not fitted to the reference: the nominal model correlates with it at "
            f"{first.correlation:.3f} (< {_MIXING_LEAST_CORRELATION}), so it departs from the model in ways mixing "
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
    """The refinement (module docstring): regularised Levenberg-Marquardt from the first stage,
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
        model = _with(model, protocol, model.contact_impedance, margin)
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
    scale = max(first.misfit, 1e-4) * _rms(data)
    for _ in range(_REFINE_ROUNDS):
        theta, curvature = _levenberg_marquardt(fit, theta, data, scale, spread, fixed)
        residual = data - np.asarray(fit.readings(jnp.asarray(theta)))
        free = int(np.count_nonzero(~fixed))
        scale = max(float(np.sqrt(np.sum(residual**2) / max(len(data) - free, 1))), 1e-9 * _rms(data))
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
    calibrated = _with(model, readout.folded(protocol), contact)
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
        noise=np.abs(first.signed(frames.std(axis=0, ddof=1))) / structured if len(frames) >= _NOISE_FRAMES else None,
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
    """The refined model's readings as a function of the refined parameters (module docstring)."""

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
            _with(model, _every_electrode(model.protocol), model.contact_impedance),
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

        The level, contact impedances, mixing weights and gains in closed form from the
        electrode potentials and their adjoint derivative in the contact impedances
        (`_readout_jacobian`: one solve per electrode, against one per parameter and drive
        by forward differentiation, 8 times slower on a 32-electrode tank); the electrode
        positions and widths by `jax.jacfwd`."""
        n = self.model.protocol.n_electrodes
        moves = free.copy()
        moves[: -2 * n] = False
        if np.any(free & ~moves):
            design = np.array(_readout_jacobian(self, theta))
        else:
            design = np.zeros((self.model.n_measurements, len(theta)))
        if np.any(moves):
            index = np.flatnonzero(moves)
            design[:, index] = np.asarray(_readings_jacobian(self, theta, jnp.asarray(index)))
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
    """(M, n) the derivative of `_readings` at `theta` in every parameter but the electrode
    positions and widths (zero there), in closed form. Reading m of drive d(m) is
    s_m = G_m sum_l W'_ml U_d(m)l with G_m the gains' product exp(ln c + ln g_d + ln g_p) and
    W' the weights with the mixing: d s / d ln c = s, d s / d ln g = s where the gain applies,
    d s / d weight = G (the potential it weighs), d s / d ln z_k = G W' dU/dz_k z_k (the
    contact impedances' adjoint Jacobian of the model reading every electrode); a magnitude
    board's |s| takes sign(s)."""
    protocol = fit.model.protocol
    n, drives = protocol.n_electrodes, protocol.n_drives
    every, z, weights, gain = _readout_at(fit, fit.every, theta)
    potentials = every.measure(fit.conductivity, z).reshape(drives, n)[protocol.drive_index]  # (M, L)
    # (M, L, L): dU_d(m)l / dz_k of every electrode l, by k.
    along_z = every.jacobian(fit.conductivity, z, wrt="contact_impedance").reshape(drives, n, n)[protocol.drive_index]
    signed = gain * jnp.sum(weights * potentials, axis=-1)
    columns = [
        signed[:, None],
        gain[:, None] * jnp.einsum("ml,mlk->mk", weights, along_z) * z,
        gain[:, None] * jnp.einsum("jml,ml->mj", fit.placed, potentials),
        signed[:, None] * jax.nn.one_hot(protocol.drive_index, drives, dtype=signed.dtype),
        signed[:, None] * jax.nn.one_hot(protocol.pattern_index, len(protocol.measure_patterns), dtype=signed.dtype),
        jnp.zeros((len(signed), 2 * n), signed.dtype),
    ]
    design = jnp.concatenate(columns, axis=1)
    return jnp.sign(signed)[:, None] * design if fit.magnitude else design


@eqx.filter_jit
def _readings_jacobian(fit: _ReadoutFit, theta: jax.Array, index: jax.Array) -> jax.Array:
    return jax.jacfwd(lambda part: _readings(fit, theta.at[index].set(part)))(theta[index])


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
    between electrodes), and how far they may move (module docstring)."""
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


def _boundary_loop(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """The boundary loop through the first node of electrode 0, counter-clockwise from it: its
    nodes, closed (n + 1,: the first again at the end), and their arc lengths from it (n + 1,), m."""
    following = dict(mesh.boundary_edges.tolist())
    start = int(mesh.electrodes[0][0])
    loop = [start]
    while loop[-1] != start or len(loop) == 1:
        loop.append(following[loop[-1]])
    loop = np.array(loop)
    steps = np.linalg.norm(np.diff(mesh.nodes[loop], axis=0), axis=1)
    return loop, np.concatenate([[0.0], np.cumsum(steps)])


def _electrode_centres(mesh: Mesh, shift: np.ndarray | None = None) -> np.ndarray:
    """(L,) each electrode's midpoint as arc length along its boundary, m, counter-clockwise
    from the first node of electrode 0 (NaN for an electrode on another boundary loop), moved
    by `shift` (L,), m."""
    loop, arcs = _boundary_loop(mesh)
    arc = float(arcs[-1])
    position = dict(zip(loop[:-1].tolist(), arcs[:-1].tolist(), strict=True))
    centres = []
    for nodes in mesh.electrodes:
        if int(nodes[0]) not in position:
            centres.append(math.nan)
            continue
        first = position[int(nodes[0])]
        length = np.sum(np.linalg.norm(np.diff(mesh.nodes[nodes], axis=0), axis=1))
        centres.append(first + 0.5 * length)
    return (np.array(centres) + (0.0 if shift is None else shift)) % arc


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
    """The labels' frame (ln scale, angle, offset, handedness; `_moved`; module docstring,
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

    starts = [_IDENTITY_FRAME, *(_frame_from_reads(read_positions, presses, mirror) for mirror in (False, True))]
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
    """`calibration` with the readout's mixing fitted to the presses (module docstring,
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
        refitted = _with(every, folded, calibration.contact_impedance * contact_factor)
        readings = np.asarray(refitted.measure(jnp.asarray(sigma)))
    factor = _scale(readings, data)
    contact = calibration.contact_impedance * contact_factor * factor
    fitted_model = _with(every, folded, contact)
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
    return np.maximum(per_press, max(float(np.median(per_press)), 1e-12 * _rms(data)))[:, None]


def _press_patterns(mesh: Mesh, presses: Presses) -> np.ndarray:
    """(K, E) the fraction of each element inside each press's disc (its footprint), exact:
    the frame's central differences (`_FRAME_DELTA`) differentiate it, and a sampled footprint
    moves in steps (docs/tutorials/calibration.md: fewer trial steps, the same errors)."""
    return disc_fractions(mesh, presses.centres, presses.radius, level=None).T.toarray()


def _every_electrode(protocol: Protocol) -> Protocol:
    """`protocol`'s drives, each reading every electrode's potential (drives x L readings)."""
    return Protocol(protocol.drive, [np.eye(protocol.n_electrodes)] * protocol.n_drives)


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
        model = _with(calibration.model, protocol, calibration.contact_impedance, margin)
        every = _with(model, _every_electrode(protocol), calibration.contact_impedance)
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
    error = _rms(residual) * np.sqrt(np.sum(changes**2, axis=0))
    return np.where(np.abs(projection) > _SIGN_ERRORS * error, np.sign(projection), sign)


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
    problem = LinearisedProblem(calibration.model, "noser", level)
    if hyperparameter is None:
        hyperparameter, _ = auto_hyperparameter(calibration.model, dv, "noser", level, problem=problem)
    solver = OneStep(calibration.model, problem.prior, hyperparameter, level, problem=problem)
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


def _frame_from_reads(read_positions: np.ndarray, presses: Presses, mirror: bool) -> np.ndarray:
    """(5,) the frame (`_moved`) of the similarity, mirrored (y -> -y first) when `mirror`, that
    best maps the presses' labelled centres onto the positions read (Umeyama's least squares,
    once more without the presses read more than three robust deviations off; NaN reads left
    out); the identity with fewer than 3 reads."""
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
    return np.array([math.log(scale), math.atan2(rotation[1, 0], rotation[0, 0]), *offset, handedness])


def _moved(presses: Presses, frame: np.ndarray | None) -> Presses:
    """The presses in the mesh's frame under `frame` (ln scale, angle, offset, handedness: the
    labels' y negated when it is -1, then scaled, turned by the angle and offset); None: they
    are in it (a curved skin's)."""
    if frame is None:
        return presses
    return Presses(_in_mesh_frame(presses.centres, frame), presses.radius * math.exp(frame[0]), presses.times)


def _similarity_of(frame: np.ndarray) -> tuple[float, np.ndarray]:
    """The scale and the rotation (2, 2) of the labels' frame `frame` (`_moved`)."""
    angle = frame[1]
    return math.exp(frame[0]), np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])


def _in_mesh_frame(points: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """(..., 2) labels'-frame `points` in the mesh's frame under `frame` (`_moved`)."""
    scale, rotation = _similarity_of(frame)
    return scale * (points * [1.0, frame[4]]) @ rotation.T + frame[2:4]


def _similarity(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Scale s, rotation R (2, 2) and offset t minimising ||target - (s R source + t)||."""
    mean_source, mean_target = source.mean(axis=0), target.mean(axis=0)
    a, b = source - mean_source, target - mean_target
    u, singular, vt = np.linalg.svd(b.T @ a)
    flip = np.diag([1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ flip @ vt
    scale = float(np.trace(np.diag(singular) @ flip) / max(np.sum(a**2), 1e-300))
    return scale, rotation, mean_target - scale * rotation @ mean_source


def _with_position_map(
    calibration: SkinCalibration,
    presses: Presses,
    found: Any,
    further: np.ndarray,
    hyperparameter: float,
    polarity: int,
) -> SkinCalibration:
    """`calibration` with the position map fitted on the presses' touches `found`, and the
    ringing from their images' further hills `further` (`_read_presses`; module docstring,
    "Presses")."""
    seen = found.count > 0
    notes = list(calibration.warnings)
    if not seen.all():
        notes.append(f"no touch read at press(es) {name_indices(np.flatnonzero(~seen))}: left out of the position map")
    if seen.sum() < 3:
        notes.append("fewer than 3 presses read: no position map")
        return eqx.tree_at(
            lambda c: (c.warnings, c.polarity), calibration, (tuple(notes), polarity), is_leaf=lambda node: node is None
        )
    read_positions, labelled = found.position[seen, 0], presses.centres[seen]
    mapping = PositionMap.fit(read_positions, labelled, calibration.model.mesh)
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
            c.polarity,
            c.ringing,
        ),
        calibration,
        (mapping, errors, mapping(found.position[:, 0]), tuple(notes), hyperparameter, polarity, ringing),
        is_leaf=lambda node: node is None,
    )


def _leave_one_out_errors(
    read: np.ndarray, labelled: np.ndarray, degree: int | None, surface: Mesh | None = None
) -> np.ndarray:
    """(K,) the distance, m, between each labelled position and the map of degree `degree`
    fitted without it (on a curved skin's `surface`, refitted without each in turn, taken onto
    it, and the distance along it: `diffeit.mesh.surface_distance`; on a flat sheet through the
    fit's hat matrix)."""
    if degree is None:
        return np.linalg.norm(read - labelled, axis=1) if surface is None else surface_distance(surface, read, labelled)
    length = _spread(labelled)
    terms = _terms(read / length, degree)
    shift = (labelled - read) / length
    if surface is not None:
        mapped = np.empty_like(read)
        for k in range(len(read)):
            others = np.arange(len(read)) != k
            coefficients, *_ = np.linalg.lstsq(terms[others], shift[others], rcond=_MAP_RCOND)
            mapped[k] = read[k] + terms[k] @ coefficients * length
        return surface_distance(surface, onto_surface(surface, mapped), labelled)
    return np.linalg.norm(_held_out_residuals(terms, shift), axis=1) * length


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
    farther (a one-sided sign test at `_SHEET_SIGNIFICANCE`): then the closest of those. As
    for the reference's calibration (`_kept_if_it_generalises`), the physical fit is kept short
    of evidence against it: at 50 presses the sets' held-out medians chose the better set of
    test presses about as often as not (docs/tutorials/calibration.md), and the mixing alone,
    with the electrodes where the mesh has them, took up their error (a weight 0.104 off on
    the calibration benchmark's seed 2 with 50 presses, against 0.010 with the positions)."""
    fullest = made[-1]
    if fullest.held_out is None:
        return fullest
    beaten_by = [fit for fit in made[:-1] if _closer(fit.held_out, fullest.held_out)[2] < _SHEET_SIGNIFICANCE]
    return min(beaten_by, key=lambda fit: _median_read(fit.held_out)) if beaten_by else fullest


def _kept_if_it_generalises(
    fitted: SkinCalibration, reference_only: SkinCalibration, held_out: np.ndarray | None, theirs: np.ndarray
) -> SkinCalibration:
    """`fitted` (the presses' fit) with its held-out press errors `held_out` as `press_errors`,
    unless the calibration from the reference alone with a position map (`reference_only`),
    held out in the same folds (`theirs`, `_map_held_out_errors`), reads significantly more of
    the presses closer than farther (a one-sided sign test at `_SHEET_SIGNIFICANCE`): then that
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
    if significance >= _SHEET_SIGNIFICANCE:
        return eqx.tree_at(lambda c: c.press_errors, fitted, held_out)
    note = (
        f"{_not_kept(fitted.fitted['presses'])}presses it did not see were read {1e3 * _median_read(held_out):.1f} mm "
        f"off (median) against {1e3 * _median_read(theirs):.1f} mm with the reference's calibration and a position "
        f"map, which read {closer} of them closer and {farther} farther (sign test p = {significance:.2g})"
    )
    return _with_warnings(reference_only, note)


def _with_background_map(
    calibration: SkinCalibration,
    recording: Recording,
    presses: Presses | None,
    reference: np.ndarray,
    required: bool = True,
) -> SkinCalibration:
    """`calibration` with a background map fitted to the reference frames (module docstring,
    "Background map"). With `presses`, they are read at the map through a position map fitted
    again; unless `required`, the map is kept only when their leave-one-out errors are smaller
    than those of `calibration` read the same way at significantly more presses than they are
    larger (a one-sided sign test at `_SHEET_SIGNIFICANCE`), else `calibration` is returned
    with a note."""
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
    closer, farther, significance = _closer(ours, theirs)
    if significance < _SHEET_SIGNIFICANCE:
        return mapped
    sheet = mapped.background_map
    note = (
        f"the background map ({sheet.min():.4g} to {sheet.max():.4g} S/sq) is not kept: it reads {closer} presses "
        f"closer and {farther} farther (leave-one-out; median {1e3 * _median_read(ours):.1f} mm against "
        f"{1e3 * _median_read(theirs):.1f} mm without), not significantly better (sign test p = {significance:.2f})"
    )
    return _with_warnings(calibration, note)


def _closer(ours: np.ndarray, theirs: np.ndarray) -> tuple[int, int, float]:
    """At how many presses the errors `ours` (K,) are smaller than `theirs` (K,), and larger (a
    press not read, NaN, the largest), and the one-sided sign test's p-value that ours are
    smaller more often than not."""
    ours, theirs = np.where(np.isnan(ours), np.inf, ours), np.where(np.isnan(theirs), np.inf, theirs)
    closer, farther = int(np.sum(ours < theirs)), int(np.sum(ours > theirs))
    significance = scipy.stats.binomtest(closer, closer + farther, alternative="greater").pvalue if closer else 1.0
    return closer, farther, float(significance)


def _background_fitted(calibration: SkinCalibration, reference: np.ndarray) -> SkinCalibration:
    """`calibration` with its level and a smooth map of ln sigma fitted to the mean `reference`
    (module docstring, "Background map") with each contact impedance (ln z, the reference's
    prior about the calibration's), the readout and gains held; the
    calibration itself, with a note, when the data determine none of the map's terms."""
    data = calibration.signed(np.atleast_2d(reference).mean(axis=0))
    fit = _SheetFit.of(calibration.model, calibration.conductivity, calibration.contact_impedance)
    n, electrodes = fit.terms.shape[1], len(fit.contact_impedance)
    spread = np.r_[1.0, np.full(electrodes, PRIORS["contact_impedance"]), np.full(n, _SHEET_PRIOR)]
    fixed = np.zeros(len(spread), bool)
    scale = max(calibration.misfit, 1e-4) * _rms(data)
    theta = np.zeros(len(spread))
    for _ in range(_REFINE_ROUNDS):
        theta, curvature = _levenberg_marquardt(fit, theta, data, scale, spread, fixed)
        residual = data - np.asarray(fit.readings(jnp.asarray(theta)))
        scale = max(float(np.sqrt(np.sum(residual**2) / max(len(data) - len(theta), 1))), 1e-9 * _rms(data))
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
            _with(calibration.model, calibration.model.protocol, contact),
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


# ---------------------------------------------------------------------------------------------
# Files

SCHEMA = "diffeit.calibration"
# Version 2: the electrodes' positions (model/electrode_shift, electrode_margin); version 3: the
# background map (background_map), which a reader of version 2 would ignore; version 4: polarity 0
# for a calibration without presses (none known), which a reader of version 3 would refuse to read
# touches with; version 5: the labels' frame's handedness (values/label_frame's fifth value), which
# a reader of version 4 would fail on, and a curved skin's position maps (coefficients (n_terms, 3)),
# which it would apply without taking the touches back onto the surface; version 6: the size map
# (size_map), without which a reader of version 5 would read touches' radii and depths other than
# the calibration's. Versions 1 to 5 read (their -1 without presses stays -1). The reference
# (reference) came within version 6, optional: a reader without it images every recording
# against the recording's own first frames, as a calibration without it does.
SCHEMA_VERSION = 6


def _save(calibration: SkinCalibration, path: Path, overwrite: bool) -> Path:
    """Write `calibration` (see `SkinCalibration.save`)."""
    model = calibration.model
    mesh = model.mesh
    arrays = {
        "mesh/nodes": mesh.nodes,
        "mesh/triangles": mesh.triangles,
        "mesh/electrode_nodes": np.concatenate(mesh.electrodes),
        "mesh/electrode_offsets": np.cumsum([0, *(len(e) for e in mesh.electrodes)]),
        "protocol/drive": calibration.protocol.drive,
        "protocol/measure": calibration.protocol.measure,
        "protocol/drive_index": calibration.protocol.drive_index,
        "model/measure": model.protocol.measure,
        "contact_impedance": calibration.contact_impedance,
        "used": calibration.used.astype(np.int8),
        "reading_sign": calibration.reading_sign,
        "readout/gains": np.asarray(calibration.readout.gains),
        "readout/weights": np.concatenate(
            [
                np.atleast_1d(calibration.readout.source),
                np.atleast_1d(calibration.readout.sink),
                calibration.readout.offsets,
            ]
        ),
        **{f"values/{name}": value for name, value in calibration.values.items()},
        **{f"standard_errors/{name}": value for name, value in calibration.standard_errors.items()},
    }
    if model.electrode_shift is not None:
        arrays["model/electrode_shift"] = np.asarray(model.electrode_shift)
    if calibration.noise is not None:
        arrays["noise"] = calibration.noise
    if calibration.reference is not None:
        arrays["reference"] = calibration.reference
    if calibration.background_map is not None:
        arrays["background_map"] = calibration.background_map
    if calibration.position_map is not None:
        arrays["position_map/coefficients"] = calibration.position_map.coefficients
    if calibration.size_map is not None:
        arrays["size_map/radius_coefficients"] = calibration.size_map.radius_coefficients
        arrays["size_map/depth_coefficients"] = calibration.size_map.depth_coefficients
        arrays["size_map/limits"] = calibration.size_map.limits
    if calibration.press_errors is not None:
        arrays["press_errors"] = calibration.press_errors
        arrays["press_positions"] = calibration.press_positions
    attributes = {
        "schema": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "readings": calibration.readings,
        "drive_current": model.drive_current,
        "electrode_margin": getattr(model.system, "electrode_margin", 0.0),
        "conductivity": calibration.conductivity,
        "misfit": calibration.misfit,
        "correlation": calibration.correlation,
        "hyperparameter": -1.0 if calibration.hyperparameter is None else calibration.hyperparameter,
        "noise_frames": calibration.noise_frames,
        "polarity": 0 if calibration.polarity is None else calibration.polarity,  # 0: none
        "ringing": -1.0 if calibration.ringing is None else calibration.ringing,
        "json": json.dumps(
            {
                "undetermined": list(calibration.undetermined),
                "fitted": {source: list(groups) for source, groups in calibration.fitted.items()},
                "memory": None
                if calibration.memory is None
                else {
                    field.name: float(getattr(calibration.memory, field.name))
                    for field in dataclasses.fields(calibration.memory)
                },
                "warnings": list(calibration.warnings),
                "first_stage": calibration.first_stage.summary(),
                "position_map": None
                if calibration.position_map is None
                else {
                    "degree": calibration.position_map.degree,
                    "length": calibration.position_map.length,
                    "errors": calibration.position_map.errors,
                },
                "size_map": None
                if calibration.size_map is None
                else {
                    "radius_degree": calibration.size_map.radius_degree,
                    "depth_degree": calibration.size_map.depth_degree,
                    "length": calibration.size_map.length,
                    "errors": calibration.size_map.errors,
                },
            }
        ),
    }

    def write(file: h5py.File) -> None:
        write_attributes(file, attributes)
        for name, value in arrays.items():
            create_checked(file, name, np.asarray(value))

    return write_atomically(path, write, overwrite=overwrite)


def load(path: str | Path, *, recording: Recording | None = None) -> SkinCalibration:
    """Read a calibration written by `SkinCalibration.save`.

    Arguments:
        path: The file.
        recording: When given, the calibration must be for its protocol (and its mesh, when
            it brings one): a `ValueError` otherwise.

    Returns:
        The `SkinCalibration` (its first stage restored as far as the file keeps it: the
        orientation, masks and fit figures are in `first_stage_summary` of `summary()`).

    Raises:
        ValueError: For a file that is not a calibration, is damaged, has another schema or
            a newer version, or is for another protocol or mesh than `recording`'s.
    """
    path = Path(path)

    def read(file: h5py.File) -> tuple[dict, dict]:
        stored = read_attributes(file)
        schema = stored.get("schema")
        if schema != SCHEMA:
            raise ValueError(f"{path} is not a diffeit calibration (schema {schema!r}, expected {SCHEMA!r})")
        version = int(stored.get("schema_version", -1))
        if version > SCHEMA_VERSION:
            raise ValueError(
                f"{path} is a calibration of schema version {version}, newer than this diffeit reads "
                f"({SCHEMA_VERSION}): update diffeit"
            )
        if version < 1:
            raise ValueError(
                f"{path} has calibration schema version {version}; this diffeit reads 1 to {SCHEMA_VERSION}"
            )
        arrays: dict[str, np.ndarray] = {}
        file.visititems(
            lambda name, item: arrays.__setitem__(name, item[()]) if isinstance(item, h5py.Dataset) else None
        )
        return arrays, stored

    arrays, attributes = read_checked(path, read, what="calibration file")
    try:
        return _from_stored(arrays, attributes, recording, path)
    except (KeyError, ValueError, TypeError, json.JSONDecodeError) as error:
        if isinstance(error, ValueError) and str(error).startswith(str(path)):
            raise
        raise ValueError(f"{path} is not a readable diffeit calibration: {error}") from error


# What each stored number may be: a file edited by hand or written by a faulty program is
# refused by name rather than read as other numbers (a NaN ringing had read as the default).
# Name -> (smallest, largest, the value that stands for "none" or None).
_STORED_NUMBERS = {
    "conductivity": (0.0, math.inf, None),
    "drive_current": (-math.inf, math.inf, None),  # A; not 0 either
    "electrode_margin": (0.0, math.inf, None),
    "misfit": (0.0, math.inf, None),
    "correlation": (-1.0, 1.0, None),
    "hyperparameter": (0.0, math.inf, -1.0),
    "noise_frames": (0.0, math.inf, None),
    "ringing": (0.0, _RINGING_CAP, -1.0),
}
# Arrays -> what their values must be besides finite: "positive", "non-negative", "nonzero" or
# "" (anything).
_STORED_ARRAYS = {
    "contact_impedance": "positive",
    "background_map": "positive",
    "readout/gains": "nonzero",
    "readout/weights": "",
    "noise": "non-negative",
    "reference": "",
    "model/electrode_shift": "",
    "position_map/coefficients": "",
    "values/label_frame": "",
    "size_map/radius_coefficients": "",
    "size_map/depth_coefficients": "",
    "size_map/limits": "",
}


def _check_stored(arrays: dict, attributes: dict) -> None:
    """ValueError naming a stored number or array out of its range (`_STORED_NUMBERS`,
    `_STORED_ARRAYS`): NaN, infinite, of the wrong sign, a reading sign other than +-1, or a
    polarity other than -1, 0 (none) or +1."""
    for name, (low, high, none) in _STORED_NUMBERS.items():
        if name not in attributes:
            continue
        value = float(attributes[name])
        if value != none and not (math.isfinite(value) and low <= value <= high):
            raise ValueError(f"its {name} is {value!r}, not a finite number in [{low:g}, {high:g}]")
    for name in ("conductivity", "drive_current"):
        if float(attributes[name]) == 0:
            raise ValueError(f"its {name} is 0")
    polarity = float(attributes.get("polarity", 0))
    if polarity not in (-1, 0, 1):
        raise ValueError(f"its polarity is {polarity:g}, not -1, +1 or 0 (none)")
    for name, kind in _STORED_ARRAYS.items():
        if name not in arrays:
            continue
        values = np.asarray(arrays[name], float)
        if not np.all(np.isfinite(values)):
            raise ValueError(f"its {name} holds values that are not finite")
        wrong = {"positive": values <= 0, "non-negative": values < 0, "nonzero": values == 0}.get(kind, False)
        if np.any(wrong):
            raise ValueError(f"its {name} holds values that are not {kind}")
    if not np.all(np.abs(np.asarray(arrays["reading_sign"], float)) == 1):
        raise ValueError("its reading_sign holds values other than +-1")
    frame = np.asarray(arrays.get("values/label_frame", _IDENTITY_FRAME), float)
    if frame.shape not in ((4,), (5,)) or (len(frame) == 5 and abs(frame[4]) != 1):
        raise ValueError(
            "its values/label_frame is not a labels' frame (ln scale, angle, offset x and y, handedness +-1)"
        )


def _stored_size_map(sizes: dict, arrays: dict, dimension: int) -> SizeMap:
    """The `SizeMap` a file keeps; ValueError naming what does not fit together."""
    length = float(sizes["length"])
    if not (math.isfinite(length) and length > 0):
        raise ValueError(f"its size map's length is {length!r}, not a positive number")
    limits = np.asarray(arrays["size_map/limits"], np.float64)
    if limits.shape != (2, 2) or np.any(limits[:, 0] > limits[:, 1]):
        raise ValueError("its size_map/limits is not two ranges (smallest, largest ln gain)")
    for name in ("radius", "depth"):
        degree, coefficients = sizes[f"{name}_degree"], arrays[f"size_map/{name}_coefficients"]
        terms = 0 if degree is None else _terms(np.zeros((1, dimension)), int(degree)).shape[1]
        if np.shape(coefficients) != (terms,):
            raise ValueError(
                f"its size_map/{name}_coefficients has shape {np.shape(coefficients)}; "
                f"degree {degree} has {terms} terms"
            )
    return SizeMap(
        *(None if sizes[f"{name}_degree"] is None else int(sizes[f"{name}_degree"]) for name in ("radius", "depth")),
        arrays["size_map/radius_coefficients"],
        arrays["size_map/depth_coefficients"],
        limits,
        length,
        sizes["errors"],
    )


def _stored_reference(arrays: dict, protocol: Protocol) -> np.ndarray | None:
    """The reference a file keeps (none before it was kept); ValueError for one that is not one
    frame of the protocol's readings."""
    reference = arrays.get("reference")
    if reference is not None and np.shape(reference) != (protocol.n_measurements,):
        raise ValueError(
            f"its reference has shape {np.shape(reference)}; the protocol's frames have {protocol.n_measurements} "
            "readings"
        )
    return reference


def _from_stored(arrays: dict, attributes: dict, recording: Recording | None, path: Path) -> SkinCalibration:
    _check_stored(arrays, attributes)
    offsets = arrays["mesh/electrode_offsets"]
    nodes = arrays["mesh/electrode_nodes"]
    mesh = Mesh(arrays["mesh/nodes"], arrays["mesh/triangles"], [nodes[a:b] for a, b in itertools.pairwise(offsets)])
    drive, drive_index = arrays["protocol/drive"], arrays["protocol/drive_index"]
    protocol = Protocol(drive, [arrays["protocol/measure"][drive_index == d] for d in range(len(drive))])
    if recording is not None:
        if recording.protocol != protocol:
            raise ValueError(f"{path} calibrates another protocol than the recording's")
        if recording.mesh is not None and recording.mesh != mesh:
            raise ValueError(f"{path} calibrates another mesh than the recording's")
    used = arrays["used"].astype(bool)
    measure = arrays["model/measure"]
    selected = protocol.select(used)
    model_protocol = Protocol(selected.drive, [measure[selected.drive_index == d] for d in range(selected.n_drives)])
    moved = {}
    if "model/electrode_shift" in arrays:
        moved = {
            "electrode_shift": arrays["model/electrode_shift"],
            "electrode_margin": float(attributes["electrode_margin"]),
        }
    model = ForwardModel(
        mesh, model_protocol, arrays["contact_impedance"], drive_current=float(attributes["drive_current"]), **moved
    )
    weights = arrays["readout/weights"]
    readout = Readout(selected, source=weights[0], sink=weights[1], offsets=weights[2:], gains=arrays["readout/gains"])
    stored = json.loads(attributes["json"])
    mapping = stored["position_map"]
    position_map = None
    if mapping is not None:
        position_map = PositionMap(
            mapping["degree"],
            arrays.get("position_map/coefficients", np.zeros((0, mesh.nodes.shape[1]))),
            mapping["length"],
            mapping["errors"],
            mesh if mesh.nodes.shape[1] == 3 else None,  # a curved skin's map takes touches onto it
        )
    values = {name.split("/", 1)[1]: value for name, value in arrays.items() if name.startswith("values/")}
    errors = {name.split("/", 1)[1]: value for name, value in arrays.items() if name.startswith("standard_errors/")}
    if position_map is not None and "label_frame" in values and mesh.nodes.shape[1] == 2:
        frame = np.asarray(values["label_frame"], np.float64)
        position_map = position_map.held_to(mesh, frame if len(frame) == 5 else np.append(frame, 1.0))  # versions 1-4
    sizes = stored.get("size_map")  # none before version 6
    size_map = None if sizes is None else _stored_size_map(sizes, arrays, mesh.nodes.shape[1])
    first = stored["first_stage"]
    first_stage = ReferenceCalibration(
        model=model,
        conductivity=float(first["conductivity"]),
        contact_impedance=np.asarray(first["contact_impedance_per_electrode"]),
        used=used,
        reading_sign=arrays["reading_sign"],
        orientation=first["orientation"],
        orientations=first["orientations_misfit"],
        misfit=float(first["misfit"]),
        correlation=float(first["correlation"]),
        masked={reason: tuple(indices) for reason, indices in first["masked"].items()},
        broken_electrodes=tuple(first["broken_electrodes"]),
        driven_readings=first["driven_readings"],
        warnings=tuple(first["warnings"]),
    )
    hyperparameter = float(attributes["hyperparameter"])
    ringing = float(attributes.get("ringing", -1.0))  # none before it was kept
    return SkinCalibration(
        model=model,
        conductivity=float(attributes["conductivity"]),
        background_map=arrays.get("background_map"),
        contact_impedance=arrays["contact_impedance"],
        electrode_centres=_electrode_centres(
            mesh, None if model.electrode_shift is None else np.asarray(model.electrode_shift).mean(axis=1)
        ),
        readout=readout,
        used=used,
        reading_sign=arrays["reading_sign"],
        standard_errors=errors,
        values=values,
        undetermined=tuple(stored["undetermined"]),
        fitted={source: tuple(groups) for source, groups in stored["fitted"].items()},
        misfit=float(attributes["misfit"]),
        correlation=float(attributes["correlation"]),
        position_map=position_map,
        press_errors=arrays.get("press_errors"),
        press_positions=arrays.get("press_positions"),
        noise=arrays.get("noise"),
        noise_frames=int(attributes["noise_frames"]),
        polarity=int(attributes["polarity"]) or None,
        memory=None if stored["memory"] is None else MemoryParameters(**stored["memory"]),
        hyperparameter=None if hyperparameter < 0 else hyperparameter,
        first_stage=first_stage,
        warnings=tuple(stored["warnings"]),
        protocol=protocol,
        readings=str(attributes["readings"]),
        ringing=None if ringing < 0 else ringing,
        size_map=size_map,
        reference=_stored_reference(arrays, protocol),
    )
