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
every group; the Jacobian in closed form from the electrode potentials and their adjoint
derivatives in the contact impedances and the electrodes' ends) refines the level (a factor c
with the voltage unit) and the groups `reference_groups` names, against the reference's
readings in use (by default `REFERENCE_GROUPS`, the contact impedances and the mixing, where
20 or more labelled presses fit the positions or a background map is fitted, and
`REFERENCE_ONLY_GROUPS`, the electrode positions too, otherwise):

- "contact_impedance": one per electrode, ln z, prior standard deviation 1 (the default);
- "mixing": the readout's (`diffeit.readout.Readout`: source, sink and offset weights), prior
  standard deviation 0.3 of the pair's weight. From a reference (the default) only the
  source electrode's and the far electrode's weights, started from the best of a grid of
  the two: a magnitude board's readings flip sign along the way, where small steps from no
  mixing stop short. Not fitted (with a warning) to a reference the first stage's model
  correlates with under 0.5, nor are the electrodes' positions and widths: what the model
  lacks is then something else, gains per reading or the wiring, that they would only mask;
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
  leave-one-out cross-validation on the presses (`PositionMap`): a degree replaces a lower one
  only when its held-out distances are lower in the median and smaller by a one-sided
  signed-rank test at 10%. `diffeit.touches` applies it.
  With the labels' frame found (20 presses or more, on a flat skin), a touch the polynomial
  takes off the skin (it extrapolates beyond the presses) is taken to the nearest point of the
  skin's outline in that frame: a rim hill beside a press had been placed 1.2 radii from the
  centre. The polynomial is trusted within the presses alone (their read positions' convex
  hull); beyond, a touch takes the labels' frame (else the presses' shift or affine fit; on a
  curved skin, no global move) and the nearest press's correction, fading with its distance
  (`PositionMap`).
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
through a position map fitted again, land significantly closer to their labels
(leave-one-out), both more often and by more (a one-sided sign test and a one-sided Wilcoxon
signed-rank test of the differences, each at 5%); its press errors are then those
leave-one-out ones. (A map the presses fit
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

from ._calibrate import PRESS_GROUP_CHOICES as PRESS_GROUP_CHOICES
from ._calibrate import calibrate as calibrate
from ._calibrate import default_mesh as default_mesh
from ._frames import REFERENCE_FRAMES as REFERENCE_FRAMES
from ._frames import LiveDrift as LiveDrift
from ._frames import LiveLost as LiveLost
from ._frames import calibrated_reference_frames as calibrated_reference_frames
from ._frames import damaged_frames as damaged_frames
from ._frames import drift_corrected as drift_corrected
from ._frames import drift_note as drift_note
from ._frames import glitched_frames as glitched_frames
from ._frames import held_lost_readings as held_lost_readings
from ._frames import lost_electrodes as lost_electrodes
from ._frames import lost_note as lost_note
from ._frames import reading_spread as reading_spread
from ._frames import reference_frames as reference_frames
from ._frames import untouched_run as untouched_run
from ._maps import PositionMap as PositionMap
from ._maps import SizeMap as SizeMap
from ._presses import auto_hyperparameter as auto_hyperparameter
from ._reference import CalibrationWarning as CalibrationWarning
from ._reference import DrivenReadings as DrivenReadings
from ._reference import ReferenceCalibration as ReferenceCalibration
from ._reference import auto_difference as auto_difference
from ._reference import calibrate_to_reference as calibrate_to_reference
from ._refine import PRIORS as PRIORS
from ._refine import REFERENCE_GROUPS as REFERENCE_GROUPS
from ._refine import REFERENCE_ONLY_GROUPS as REFERENCE_ONLY_GROUPS
from ._refine import refine_to_reference as refine_to_reference
from ._skin import SCHEMA as SCHEMA
from ._skin import SCHEMA_VERSION as SCHEMA_VERSION
from ._skin import SkinCalibration as SkinCalibration
from ._skin import load as load
