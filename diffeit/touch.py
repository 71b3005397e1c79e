"""From images to touches: where the skin was touched, how large the contact was and how hard.

`touches(recording)` (`diffeit.touches`) reads every image of a reconstructed recording (`diffeit.reconstruct`);
`read(mesh, images)` is the same on bare arrays.

## The rule

A touch lowers the sheet's conductivity (`polarity=-1`; +1 for a sheet whose conductivity a
touch raises, or a conductive object in a tank): in each image a = polarity * change, the
touches are the hills of a. Where no one says which (no `polarity`, no calibration from labelled
presses), `touches` reads it from the images (`polarity_of`): the sign of the median, over the
touched frames, of each image's largest change. A touch is a hill well above its image's
ringing and noise, so a skin's touches vote for their own sign.

1. **Is the frame touched?** With a calibration that knows the readings' noise (from its
   reference frames), a frame is touched when its differences dv (in the calibrated model's
   units) stand out of that noise where a touch puts them: z > `detection` (default 5), z the
   standardised sum of the squared projections of the whitened differences dv_m / s_m /
   sqrt(1 + 1/n) on the k leading left singular vectors of the whitened Jacobian J_me / s_m
   (singular values above `_SUBSPACE_CUT` of the largest), each term taken as F(1, n - 1) for an
   untouched frame (s_m estimated from n reference frames, dv against their mean). A touch's
   differences lie in that subspace, the noise spreads over all M readings: on the calibration
   benchmark's skins (192 magnitudes, k about 45) the sum over every reading missed 7 of 60
   presses on one skin, the subspace none, its untouched frames staying under z = 2.8. Without
   a calibration, the same test runs on the raw readings when the images' recording says their
   noise and where a touch puts them: `diffeit.reconstruct`, imaging at the model it calibrated
   to the reference of 6 or more of the recording's frames, keeps their spread
   ("reading_noise") and that model's projection of raw differences onto the whitened subspace
   ("touch_projection", `reading_projection`) in the provenance (on the same skins, the sum
   over every raw reading had missed 2, 3 and 11 of 60 presses on three of five; a recording
   without the projection is tested that way). With
   a calibration that knows no noise (fewer than 6 reference frames), the differences inside the
   subspace a conductivity change reaches are compared with those outside it, where only noise
   is (`touched`): the ratio of their mean squares is about 1 for an untouched frame, and a
   frame is touched when it exceeds 1 by `detection` of its standard deviations. Without a
   calibration, and no noise kept, `diffeit.reconstruct` keeps that statistic, made at the model
   it calibrated to the reference (`subspace_statistic`, "touch_statistic"), and a frame is
   touched when it is, or when its image has a hill above `threshold` (each finds presses the
   other misses: on a magnitude board with one untouched frame before 80 presses one after
   another, 78 read where the hills alone read 37; on an adjacent board the statistic alone
   missed 4 of 30 the hills read). A touched frame reports its strongest hill however low, and
   the others above `LOW` (3) robust standard deviations of its image where the noise is known,
   above `threshold` where it is not (`LOW` read a single press as 2 to 4 touches in 24 of those
   80 frames); an untouched frame reports none. Without either, a hill counts when its peak
   exceeds `threshold` (default 6) robust standard deviations of the image: sigma_t = 1.4826 *
   MAD of a over the elements (a touch covers few of them, so this is the image's noise and
   artefacts).
2. **Hills.** The local maxima of a (at least every element sharing an edge), highest
   first, each further one at least `RELATIVE` (0.1) of the highest one's peak (a one-step
   image rings at a fraction of its touch's peak whatever the noise), or, with a calibration
   from labelled presses, at least its `ringing` when that is more: how high the further
   hills of its own single presses' images stood (the model's errors ring too, and more than
   the noise; on the calibration benchmark's skins single presses were read as two or more
   touches at 11 of 120 test presses with 0.1 alone, at 3 with the ringing). Each claims the
   connected elements at or above half its peak (its half-amplitude set). A maximum whose
   half-amplitude set reaches a set already claimed is the same touch (two maxima whose valley
   stays above half the lower peak merge); otherwise it is a touch of its own, up to
   `max_touches`.
   **On the image divided by its noise**, where `diffeit.reconstruct` knew the readings' noise
   (a calibration's, or the spread of 6 or more reference frames) and made one-step images: it
   keeps each element's noise in the provenance ("image_noise", `image_noise`: its standard
   deviation sqrt(sum_m (R_em s_m)^2) / sigma_e, R the one-step matrix), and the maxima, their
   order, the floors of step 1 and the merging are those of a / image_noise, and each hill is
   then read (step 3) on a itself, from its highest element. Near the electrodes a one-step
   image follows the readings closely, their noise and the model's errors with them: on the
   calibration benchmark's skins calibrated from their reference alone, the hills of a alone
   read single presses as one touch at 17, 16 and 25 of 60 (narrow hills at the rim beside
   each press, now and then above it) and 27 of 180 presses more than 15 mm off; divided by
   the image's noise, at 45, 50 and 59 of 60, and 4 of 180. A further hill's `RELATIVE` and
   `ringing` are still fractions of the highest one's peak in a.
3. **Readout.** Position: the centroid of the half-amplitude set, weighted by a times area,
   m, mapped by the calibration's `PositionMap` when there is one; radius: sqrt(area / pi) of
   the set, m; depth: the peak relative change (negative for a press with polarity -1); both
   times the gains of the calibration's `SizeMap` at the position read, when it has one (an
   image blurs a touch: it reads a press about twice as wide and a fifth as deep; the gains,
   fitted on labelled presses, read touches like them at their radius and depth); pressure,
   kPa, from the depth through a foam stack's map (`diffeit.scene.pressure_to_change`) when one
   is given.

## Rest anchors (`baseline="rest"`, the default)

A skin with memory keeps part of each touch after its release (the `diffeit.memory` presets
keep 46-49% of the peak just after it), and the parts add up over a session: against the
recording's reference, every later frame holds the ghosts of the touches before it. On a
simulated skin with the preset `over_foam` (80 mm radius, magnitudes, medium noise), pressed for
0.5 s once a second, every frame between presses stood out of the noise from the first presses
on, and 40 presses read 12.2 and 10.0 mm off (median, two seeds) from the reference alone, 11.6
and 9.1 mm after 50 labelled presses. Where the readings' noise is known (the voltage test's),
each touch is read against the rest just before it instead, frame by frame:

1. **Onsets.** A step from one frame to the next brings a touch when it stands out of the
   noise (the voltage test's z > `detection`, the step's variance 2 s^2) and grows a touch's
   hill (its image's largest value, a touch positive, is positive), or when what is left of it
   once the least-squares multiple of the touch held since the last onset is taken out stands
   out of the noise and grows one (a touch moved, or one added beside a deeper one: the
   voltages of nearby touches differ little, their images do). The touch pressed deeper,
   relaxed or released, or another released, is no onset. A frame's departure from the mean of
   the rest frames before it (at least 3, the last 5; its variance (1 + 1/n) s^2) is an onset
   by the same tests: a faint press held after what a touch left steps within the noise from
   one frame to the next, and was read as that touch's remains (on the benchmark's skin below,
   seed 0, two presses read 53-66 mm off, at the press before them, and 24 of 200 held frames
   were said remains; 15 now, of three faint presses near the middle not found).
2. **Held or left.** A touched frame (against its anchor, or against the one or two rest
   frames before the last onset where they are alike, stand out of the anchor's noise and
   step 3 did not take them for the anchor: after a missed rest, every later frame had been
   measured against all that the touches since the anchor left, and no later rest was taken)
   holds a touch unless it is the highest frame since the last onset scaled down, with
   nothing else in it: the least-squares multiple of that frame's whitened differences in its
   own lies more than `SIGNIFICANCE` (2) standard errors (the readings' noise gives them) above
   0 and below `HELD` (0.7; below `HELD` alone where the frame dropped along the touch from the
   one before by more than 2 standard errors: a release, which a held touch's relaxing is far
   too slow for; a press of one frame leaves over half of itself on the memory presets, within
   the noise of `HELD` against one frame of rest, and pressed once every 2 frames, the presses
   read 28 mm off), its image's peak is below `HELD` of the highest frame's, that multiple of
   the highest frame explains at least `EXPLAINED` (a tenth) of the frame's whitened change or
   leaves the rest within the noise (the voltage test's z at most `detection`), and its image
   less that multiple of the highest's has no value above `THRESHOLD` robust standard
   deviations. That is what the touch left where it was, when its image stands where the
   highest frame's did (its highest value within that image's half height, or its value at
   that image's peak at least half its own highest; or no hill of it stands above `LOW` robust
   standard deviations). Elsewhere, the touch moved on: a touch sliding towards the middle
   fades frame by frame, its voltages nearly the frame before scaled down, but its hill moves.
   Such a frame is no part of a rest level of three frames or more (step 3), yet ends no run of
   rest frames as a held one does (after presses one after another beside a deep one, the one
   or two frames left in the run then passed for a rest level), and `Touches.remains` leaves it
   out. Without the place, a slide's frames had passed for what it left and anchored the frames
   after them (`benchmarks/slides.py`: of its 16 sessions, seed 3 at 0.3 radius a second read 80
   frames against such an anchor, 9 of 52 untouched frames touched, 5 more of the slides' 71
   frames missed; with slides drawn in a square, 4 of 16 sessions, 6-13 of 23-97 frames missed
   and 15-31 of 52 untouched frames touched; now every session reads as against the reference).
   Faint presses near the middle, one after another, move the
   readings' common level and little else: each was a significant multiple of a deeper press
   before them, though that multiple explained 1-3% of its change (on a skin with memory, what
   a press left: 59% in the median, 5% at least), and three of them in a row anchored the frames
   after them. A held touch that relaxes by less than 30% stays held (the presets
   lose 6% and 11% over a 5 s hold), and so does a weak touch elsewhere: a multiple within its
   errors of 0, or a hill of its own. The image matters beside the voltages: a weak press
   beside a stronger one is, in its voltages, nearly the stronger scaled down, but its image's
   peak stands higher than that.
3. **Anchors.** At an onset, the frames since the last one that held a touch are at rest.
   When they are at least 3, alike (each step between them within the noise: what a memory
   leaves changes slowly), and each of the last 5 of them stands out of the noise against
   the anchor in force, and so does their mean (the rest level moved), that mean is the new
   anchor, for them and the frames after; else the anchor stays. A skin back at its reference
   keeps the reference, the mean of more frames; a rest frame within the noise of the anchor
   shows the level has not moved (a weak press between untouched frames, not held, would
   otherwise move it). One or two frames between touches one after another are a rest level
   only where each is what the last touch left, alike, and that touch scaled down in full (the
   highest value of their image within the touch's half height, their whitened change less
   its multiple of the touch's within the noise), and the onset after them keeps them (their
   multiple in its step is not below -`RELEASED`, a half, by `SIGNIFICANCE` standard errors):
   what a touch leaves stays through the next onset, a faint press is released at it. Taken
   as a rest level on step 2 alone they had anchored faint presses (on the calibration
   benchmark's skin, 110 presses of one frame each with no rest between, two faint presses
   after a deeper one became the anchor of the 60 presses after them: 9 of them missed; without
   a calibration, 20 of 100 frames read other touches), and refused, a skin with memory pressed
   once every 3 frames read every press against all that the presses before it left (25 and
   26 mm off from the reference alone on the rest anchors benchmark's two seeds; 5.4 and 4.0
   mm now; pressed once every 2 frames, 28 and 31 mm before, 5.9 and 4.9 mm now). The cost:
   presses one after another with no rest at all, on a skin without memory, where a press
   beside the one before and fainter passes for what it left (benchmarks/session_layouts.py,
   "back to back", seed 0: 6 and 10 of 60 presses missed without a calibration and from the
   reference alone, none before; seed 1: 3 from the reference alone; 10 and 15 on seed 0
   while three such presses in a row, not alike, made an anchor).
   A rest level that drifts (a contact's impedance creeping, a sheet drying) moves away from
   the anchor with one frame of rest between presses, which none of the above takes: every
   untouched frame then read a touch. The frame just after a held touch, the touch gone from
   it nearly in full (its multiple in the step below -3/4, the midpoint of a full release and
   the `RELEASED` half a memory keeps, by `SIGNIFICANCE` standard errors), neither held nor what
   the touch left, is a rest across touches. When the last five such frames (at least 3) are
   alike, each stands out of the anchor's noise and so does their mean, that mean is the
   anchor; from then on the rest level drifts: at each onset the anchor is the mean of the last
   five, and step 2 measures against the last rest. On the contact drift benchmark's sessions
   (contacts drifting by up to 35%, one untouched frame after each press, read from the
   reference alone) the untouched frames read touched fell from 40, 17, 27 and 20 of 60 to 4,
   3, 23 and 6 (four seeds, presses within 0.8 of the radius) and from 60, 60, 27 and 60 to 11,
   8, 23 and 3 (at the rim); the presses read 4.7, 3.8, 2.8 and 3.9 mm off before, 5.7, 4.3,
   2.9 and 4.7 mm now (9 misses before, 3 now; at the rim alike or closer). A mean of five
   frames is noisier than the reference's. Sessions whose rest holds still, and the skins with
   memory of the rest anchors benchmark, read as before.
4. **Reading.** Each frame is read against its anchor: its differences (the voltage test,
   with the anchor's number of frames; the discs' fit) and its image (one-step images are
   linear in the differences, and the anchor's image is the mean of its frames' images;
   Gauss-Newton's nearly so). `Touches.anchor` says which frames each frame's anchor holds,
   and `Touches.remains` which frames step 2 took for what the last touch left (against the
   anchor in force then): their touches stand where it was, and `Touches.lines` says so.
   After the last touch of a recording, or where the rest before an onset did not move the
   anchor, no anchor takes the remains in, and they read as touches.

On the skin above (`benchmarks/rest_anchors.py`), from the reference alone: 3.6 and 4.6 mm, 34
and 32 of 200 frames between presses touched where all 200 had been (17 and 17 of them said
remains), 3 and 0 of 40 presses (weak, near the middle) not found where none had been; after
50 labelled presses, 3.4 and 5.1 mm (3 and 0 presses not found; 3.2 and 5.9 while the
calibration read a press against the frames just before it whatever they held, and 4.3 and
5.2 against the reference).
Reading each press against the 3 frames before it, its start known, gave 5.5 mm from the
reference alone and 4.0 mm after the presses on the first seed (with a calibration that read
its presses against the reference). On the same skin without memory no anchor moved: every frame read as against the
reference. A touch whose start stays within the noise frame by frame brings no onset: it is
read against the anchor in force.
`baseline="reference"` reads every frame against the recording's reference. `LiveTouches`
carries the anchors through a stream a batch at a time (`diffeit live --touches`).

## Refinement by the model (`method="fit"`)

The image is a regularised, blurred picture of a touch: its half-amplitude set is wider and
its peak shallower than the contact. With a calibration, `touches(recording, calibration,
method="fit")` takes the image method's touches of each touched frame as a start (their
positions in the mesh's frame, before the position map) and fits K discs to the frame's
differences dv = `calibration.signed(frame) - calibration.signed(reference)` (the calibrated
model's unit) through the calibrated forward model V:

    dv(theta) = V(sigma_h (1 + sum_k depth_k f_k)) - V(sigma_h),

sigma_h the calibrated level, f_k the fraction of each element under disc k: the smooth disc
footprint of `diffeit.scene.shape_fraction` (an erf edge of the mesh's default edge width at
`FIT_LEVEL`^2 sample points per element, about half an element), differentiable in its centre
and radius (m, where the edge weight is 1/2). The centre moves in a plane through the image
method's touch: (u, v) along the axes on a flat sheet; on a curved skin along two orthonormal
directions of the element nearest the touch, the footprint the part of the surface within the
radius of the centre (3D chord, as `diffeit.scene.Disc`), and the fitted centre taken onto the
surface (`diffeit.mesh.onto_surface`). Each disc is fitted as (u, v, radius, strength = depth
radius^2): for a small disc the data fix the strength (the change it makes far off) much better
than depth and radius apart, and depth = 0 is strength = 0.

Levenberg-Marquardt on the residual weighted by the calibration's per-reading noise
(unweighted when it knows none), the Jacobian by the chain rule: forward differentiation
(`jax.jacfwd`) of each footprint in its disc's geometry, times the model's conductivity
Jacobian (the adjoint path, whose cost does not grow with K), compiled once per model and K.
The centre and radius of a disc whose strength is not significant at the current step are
held (they are not determined; free, they wander). It stops when the Gauss-Newton step's
predicted decrease of chi^2, or the last step's actual one, is below `_FIT_TOLERANCE` (in
units of the noise variance: a step of a small fraction of a standard error), after
`_FIT_STEPS` steps at most.

The covariance is (J^T W J)^-1 (W the inverse noise variances), scaled by the residual's chi^2
per degree of freedom when it exceeds 1 (a model that does not explain the frame to its noise
is not trusted beyond its misfit; without the noise, by that ratio always); the depth's
standard error follows from the strength's and the radius's. A disc whose strength is not
significant (|strength| < `SIGNIFICANCE` = 2 standard errors, or not determined) is dropped,
the least significant first, and the others refitted; the last disc is kept, however weak (the
frame stood out of its noise, so a touch is there: with a model that does not explain the
frames to their noise, a magnitude board's, the single disc of half the benchmark's presses was
insignificant and dropped, although it placed the touch better than the image). The fitted centres, and their standard
errors through the map's local Jacobian, are then mapped by the calibration's position map;
radii stay in the mesh's frame (as the image method's). The discs are reported deepest first.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg
import scipy.sparse
from numpy.typing import ArrayLike

from ._arrays import per_element
from ._threads import host_algebra
from .forward import ForwardModel
from .io import Recording
from .mesh import Mesh, nearest_element, onto_surface
from .scene import Disc, FoamStack, shape_fraction

# A hill counts when its peak exceeds this many robust standard deviations of the image; in a
# frame the voltage test finds touched, a further hill needs LOW of them.
THRESHOLD, LOW = 6.0, 3.0
# A further hill needs at least this fraction of the highest one's peak: a one-step image rings
# at a fraction of its touch's peak whatever the noise (measured 6.5% near the rim for one press
# at 0.01% noise, which the noise floors alone read as three touches).
RELATIVE = 0.1
# The voltage test's statistic z above which a frame is touched.
DETECTION = 5.0
# The voltage test keeps the differences along the calibrated Jacobian's left singular vectors
# (whitened by the readings' noise where it is known) whose singular values exceed this fraction
# of the largest: what a conductivity change makes. Without the noise, it compares them with the
# rest (what noise makes), when the rest keeps at least _LEAST_REST dimensions.
_SUBSPACE_CUT, _LEAST_REST = 0.1, 10
# Without the noise, differences are also tested relative to the model's readings, each taken as
# at least this fraction of their RMS (a reading near zero would blow up).
_UNCERTAIN_READING = 0.05
# method="fit": the disc footprint's sample points per element are FIT_LEVEL^2 (its edge width
# is the mesh's default at that level, `diffeit.scene.shape_fraction`).
FIT_LEVEL = 4
# A fitted disc counts when its strength (depth radius^2) is at least this many standard errors.
SIGNIFICANCE = 2.0
# Levenberg-Marquardt: at most this many steps; stop when a step's predicted decrease of chi^2
# (in units of the noise variance) is below the tolerance.
_FIT_STEPS = 30
_FIT_TOLERANCE = 1e-2
METHODS = ("image", "fit")
# baseline="rest" (module docstring, "Rest anchors"): a touched frame that is the highest one
# since the last onset scaled below HELD, and nothing else, is what that touch left; an anchor is
# the mean of the last _ANCHOR_FRAMES rest frames of a run of at least _LEAST_REST_FRAMES.
HELD = 0.7
_ANCHOR_FRAMES, _LEAST_REST_FRAMES = 5, 3
# What a touch left is that touch scaled down: the scaled touch explains at least this share of
# the frame's whitened change from its anchor, or what it does not explain is within the noise.
EXPLAINED = 0.1
BASELINES = ("rest", "reference")
# One or two frames of what a touch left are a rest level (step 3) where the next onset releases
# less than this share of them.
RELEASED = 0.5
# What `Touches.lines` (and `diffeit live`) say of a damaged frame.
DAMAGED_LINE = (
    "damaged frame (a board's glitch: its differences exceed half the reference, or its readings are moved along): "
    "not read"
)
# What `Touches.lines` (and `diffeit live`) add to a touch of a frame of `Touches.remains`.
REMAINS_NOTE = "(likely what the last touch left)"


class Touches(eqx.Module):
    """The touches of each frame, at most `max_touches`, strongest first.

    Attributes:
        count: (T,) int, the touches found in each frame.
        position: (T, K, D) centres, m, in the skin's frame (the labels' frame after a
            calibration's position map); NaN where a frame has fewer than K touches. D is
            the mesh's: 2 on a flat sheet, 3 on a curved skin (points on its surface).
        radius: (T, K) contact radius, m: sqrt(area / pi) of the half-amplitude set (times
            the calibration's size map's gain, when it has one).
        depth: (T, K) the peak relative conductivity change dsigma / sigma (negative for a
            touch that lowers it; times the size map's gain, when there is one).
        pressure: (T, K) kPa through the given foam stack's map, or None.
        noise: (T,) the robust standard deviation of each image, in relative change.
        standard_errors: With `method="fit"`, (T, K, 4) the standard errors of the centre's
            two coordinates (m: x, y in the frame of `position` on a flat sheet; on a curved
            skin along two orthonormal directions of the surface at the image's touch, at the
            mapped touch where a position map moved it), radius
            (m) and depth (relative change) of each fitted disc, NaN where there is none; None
            for the image method.
        misfit: With `method="fit"`, (T,) ||dv - dv(theta)|| / ||dv|| of each fitted frame's
            differences (NaN for a frame not fitted, 1 where every disc was dropped); None for
            the image method.
        damaged: (T,) bool, the frames `diffeit.reconstruct` found damaged (their differences
            larger than half the reference: a board's glitch, not a touch), read as no touch;
            None where the images' recording does not say.
        anchor: (T, 2) int, with `baseline="rest"`, the first and last frame of the rest
            frames each frame was read against (module docstring, "Rest anchors": their mean;
            a damaged frame among them is left out of it); -1, -1 where it was read against the
            recording's reference. None where every frame was read against the reference
            (`baseline="reference"`, or no readings' noise to find anchors with).
        remains: (T,) bool, with `anchor`, the frames whose change from their anchor is likely
            what the last touch left, not a touch of their own (module docstring, "Rest
            anchors", step 2: a skin with memory keeps part of a press after its release, where
            it was, fading); `lines` says so of their touches. None without `anchor`.
    """

    count: np.ndarray
    position: np.ndarray
    radius: np.ndarray
    depth: np.ndarray
    pressure: np.ndarray | None
    noise: np.ndarray
    standard_errors: np.ndarray | None = None
    misfit: np.ndarray | None = None
    damaged: np.ndarray | None = None
    anchor: np.ndarray | None = None
    remains: np.ndarray | None = None

    def lines(self, frame: int) -> list[str]:
        """One frame's touches as text, a line each.

        Each line gives the position in mm, the radius in mm, the depth (and the pressure,
        kPa); with standard errors (`method="fit"`), each followed by +- its error.

        Arguments:
            frame: The frame's index.

        Returns:
            One line per touch of the frame (none for an untouched frame; one saying so for a
            damaged frame), each ending "(likely what the last touch left)" for a frame of
            `remains`.
        """
        if self.damaged is not None and self.damaged[frame]:
            return [DAMAGED_LINE]
        lines = []
        for k in range(int(self.count[frame])):
            x, y, *z = 1e3 * self.position[frame, k]
            if self.standard_errors is None:
                point = ", ".join(f"{value:+.1f}" for value in (x, y, *z))
                line = f"touch {k}: ({point}) mm, radius {1e3 * self.radius[frame, k]:.1f} mm, "
                line += f"depth {self.depth[frame, k]:+.3f}"
            else:
                ex, ey, er, ed = self.standard_errors[frame, k] * [1e3, 1e3, 1e3, 1.0]
                line = f"touch {k}: ({x:+.1f} +- {ex:.1f}, {y:+.1f} +- {ey:.1f}) mm, "
                line += f"radius {1e3 * self.radius[frame, k]:.1f} +- {er:.1f} mm, "
                line += f"depth {self.depth[frame, k]:+.3f} +- {ed:.3f}"
            if self.pressure is not None:
                line += f", {self.pressure[frame, k]:.1f} kPa"
            if self.remains is not None and self.remains[frame]:
                line += f" {REMAINS_NOTE}"
            lines.append(line)
        return lines


@host_algebra
def touches(
    recording: Recording,
    calibration: Any = None,
    *,
    max_touches: int = 6,
    threshold: float = THRESHOLD,
    detection: float = DETECTION,
    polarity: int | None = None,
    stack: FoamStack | None = None,
    method: str = "image",
    baseline: str = "rest",
) -> Touches:
    """The touches of every image of a reconstructed recording.

    Read from the images by the rule of the module docstring ("The rule"); with
    `method="fit"`, refined by fitting discs to the frames' voltages (module docstring,
    "Refinement by the model"). When the recording has a reference, frames are tested against
    the readings' noise (`touched`): the calibration's, else the reference frames' spread that
    `diffeit.reconstruct` kept in the recording's provenance.

    Arguments:
        recording: A recording with images (`diffeit.reconstruct`'s result), relative changes
            or conductivity changes (then divided by the calibrated level in its provenance).
        calibration: A `diffeit.calibration.SkinCalibration` whose position map (from labelled
            presses) maps the positions into the labels' frame, and whose `ringing` (from
            them too) a further touch's peak must reach beside the highest's; None reads them
            in the mesh's.
        max_touches: The most touches reported per frame.
        threshold: Without the voltage test, a touch's peak must exceed this many robust
            standard deviations of its image.
        detection: With it, the voltage test's z above which a frame is touched.
        polarity: -1 when a touch lowers the conductivity, +1 when it raises it; None: the
            calibration's (found from its presses), else read from the images (`polarity_of`
            of the touched frames).
        stack: The skin's foam stack (`diffeit.scene.FoamStack`): pressures are then read
            from the depths.
        method: "image" reads the touches from the images; "fit" starts there and fits
            discs (centre, radius, depth) to each touched frame's voltage differences through
            the calibration's model, with standard errors (it needs the calibration, and the
            recording's reference).
        baseline: "rest" reads each touch against the rest frames before it where a skin's
            rest level moved (module docstring, "Rest anchors"; it needs the readings' noise,
            and reads against the reference without it); "reference" reads every frame
            against the recording's reference.

    Returns:
        The `Touches`.

    Raises:
        ValueError: For an unknown method or baseline, a recording without images (or with
            conductivity changes but no calibrated level in its provenance), images that are
            not finite, a bad option (`max_touches` not a positive integer, `threshold` not
            positive, `polarity` not -1 or +1); for `method="fit"` without a calibration,
            without the recording's reference; for a position map on a curved skin; for a
            "reading_noise" in the recording's provenance that is not one finite value per
            reading, or an "image_noise" that is not one finite positive value per element.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}; got {method!r}")
    if baseline not in BASELINES:
        raise ValueError(f"baseline must be one of {BASELINES}; got {baseline!r}")
    if method == "fit" and calibration is None:
        raise ValueError(
            'method="fit" needs a calibration (diffeit.calibrate): it fits discs to the voltages '
            "through the calibrated forward model"
        )
    if not isinstance(recording, Recording) or recording.images is None or recording.mesh is None:
        raise ValueError("touches reads a reconstructed recording (diffeit.reconstruct's result, with images)")
    images = np.asarray(recording.images, np.float64)
    if recording.image_quantity == "conductivity change":
        level = recording.provenance.get("metadata", {}).get("calibration", {}).get("conductivity")
        if level is None:
            raise ValueError("the recording's images are conductivity changes without the level they are relative to")
        images = images / level
    mapping = None if calibration is None else calibration.position_map
    if mapping is not None and mapping.degree is None:
        mapping = None  # the identity: nothing to apply
    if method == "fit" and recording.reference is None:
        raise ValueError('method="fit" fits the differences from the recording\'s reference; it has none')
    test = None if recording.reference is None else _voltage_test(recording, calibration)
    if test is not None:
        frames_touched = test.statistic(test.frames - test.reference, 1 + 1 / test.reference_frames) > detection
    elif recording.reference is not None:  # the calibration's subspace test where it knows no noise
        frames_touched = touched(recording.frames, recording.reference, calibration, detection=detection)
    else:
        frames_touched = None
    # `diffeit.reconstruct`'s subspace test, made with its own calibration where nothing knew the noise.
    from_reconstruct = _subspace_tested(recording, detection) if frames_touched is None else None
    frames_touched = from_reconstruct if frames_touched is None else frames_touched
    if polarity is None:
        polarity = None if calibration is None else calibration.polarity
    damaged = _damaged_frames(recording)
    intact = np.ones(len(images), bool) if damaged is None else ~damaged
    if polarity is None:
        polarity = polarity_of(images[intact] if frames_touched is None else images[frames_touched & intact])
    element_noise = _images_noise(recording)
    if from_reconstruct is not None:  # or a hill above `threshold` (each misses what the other finds)
        hills = read(recording.mesh, images, max_touches=1, threshold=threshold, polarity=polarity)
        frames_touched = from_reconstruct | (hills.count > 0)
    # The discs' fit reads the calibrated model's signed differences (the test's may be raw).
    signed = ()
    if method == "fit":
        signed = (calibration.signed(recording.frames) - calibration.signed(recording.reference),)
    spans = None
    if baseline == "rest" and test is not None:
        scores = polarity * images if element_noise is None else polarity * images / element_noise
        start = _Anchoring.at_reference(test, images.shape[1], tuple(values.shape[1] for values in (images, *signed)))
        anchor_of, anchors, left_behind, _ = _rest_anchors(test, scores, (images, *signed), detection, ~intact, start)
        images = _against(images, 2, anchor_of, anchors)
        signed = tuple(_against(values, 3, anchor_of, anchors) for values in signed)
        frames_touched, spans = _against_anchors_tested(test, anchor_of, anchors, detection)
    found = read(
        recording.mesh,
        images,
        max_touches=max_touches,
        threshold=threshold,
        polarity=polarity,
        position_map=mapping if method == "image" else None,
        size_map=getattr(calibration, "size_map", None) if method == "image" else None,
        stack=stack if method == "image" else None,
        touched=frames_touched,
        relative=relative_floor(calibration),
        image_noise=element_noise,
        # A frame told touched with no noise known (its own, `subspace_statistic`): a further hill
        # needs what a hill of an untested frame does (with `LOW`, single presses read as up to 5).
        further=LOW if test is not None else threshold,
    )
    if damaged is not None:  # read as no touch
        found = Touches(
            np.where(damaged, 0, found.count),
            np.where(damaged[:, None, None], np.nan, found.position),
            np.where(damaged[:, None], np.nan, found.radius),
            np.where(damaged[:, None], np.nan, found.depth),
            None if found.pressure is None else np.where(damaged[:, None], np.nan, found.pressure),
            found.noise,
            damaged=damaged,
        )
    if method == "fit":
        found = _refined(calibration, signed[0], found, mapping, stack, _lost_readings(recording)[calibration.used])
    if spans is not None:
        found = eqx.tree_at(
            lambda t: (t.anchor, t.remains), found, (spans, left_behind), is_leaf=lambda node: node is None
        )
    return found


class LiveTouches(eqx.Module):
    """Touches read from a stream one batch of frames at a time (`diffeit live --touches`), the
    future unknown: `touches`'s rule, its voltage test and rest anchors carried from batch to
    batch.

    With a calibration that knows its readings' noise, each frame is read against the rest
    anchor in force (module docstring, "Rest anchors"): an anchor moves at an onset as
    `touches` moves it, and is that of the frames from the onset on; the rest frames before
    it, already shown, were read against the anchor before (`touches` reads them against the
    new one): what the last touch left stands in them, and `step` says which they are (step
    2). Without that noise, each frame is read against the reference, tested by `touched` (or
    not at all without a calibration).

    The polarity is the calibration's (from its presses), else the first batch with touched
    frames tells it (`polarity_of`) and it is kept; until then each batch's own.

    Attributes:
        mesh: The sheet the images are on.
        calibration: The `diffeit.calibration.SkinCalibration`, or None.
        reference: (M,) the reference, as recorded.
        reference_frames: How many frames it is the mean of.
        subspace: The calibration's `touch_subspace` (None without its noise).
        image_noise: (E,) the images' noise (`image_noise`), or None.
        polarity: The touches' polarity, once known; None before.
        anchoring: The rest anchors' state after the frames read; None before the polarity is
            known, or without the calibration's noise.
        frame: The frames read so far (their indices in `Touches.anchor` count from the first).
    """

    mesh: Mesh
    calibration: Any
    reference: np.ndarray
    reference_frames: int
    subspace: np.ndarray | None
    image_noise: np.ndarray | None
    polarity: int | None = None
    anchoring: _Anchoring | None = None
    frame: int = 0

    @classmethod
    def of(
        cls, mesh: Mesh, calibration: Any, reference: ArrayLike, reference_frames: int, image_noise: ArrayLike | None
    ) -> LiveTouches:
        """The touches of a stream imaged on `mesh` against the mean `reference` (M,) of
        `reference_frames` frames, as recorded, with a `calibration` (or None) and the images'
        noise `image_noise` (E,) (or None). The calibration's touch subspace is computed here,
        once for every batch."""
        noise = getattr(calibration, "noise", None)
        return cls(
            mesh,
            calibration,
            np.asarray(reference, np.float64),
            int(reference_frames),
            None if noise is None else touch_subspace(calibration),
            None if image_noise is None else np.asarray(image_noise, np.float64),
            getattr(calibration, "polarity", None),
        )

    def step(
        self, frames: ArrayLike, images: ArrayLike, readable: ArrayLike
    ) -> tuple[Touches, np.ndarray, LiveTouches]:
        """The touches of a batch.

        Arguments:
            frames: (B, M) the batch's frames, as recorded (drift taken out).
            images: (B, E) their images, relative changes.
            readable: (B,) bool, the frames to read: their images finite, the frames not
                damaged (a board's glitch). The others are not read, and the anchors pass
                them over.

        Returns:
            The `Touches` of the batch's readable frames (in order), (B,) bool the frames that
            are what the last touch left (by the rule: a weak press beside the last one, with
            no release between, can look the same), and the state after the batch.
        """
        frames = np.atleast_2d(np.asarray(frames, np.float64))
        images = np.atleast_2d(np.asarray(images, np.float64))
        readable = np.asarray(readable, bool)
        skin, state, polarity = self.calibration, self, self.polarity
        frames_touched = None  # against the reference: to tell the polarity, or where no anchors are kept
        if polarity is None or self.subspace is None:
            frames_touched = touched(
                frames[readable], self.reference, skin, reference_frames=self.reference_frames, subspace=self.subspace
            )
        if polarity is None:
            polarity = polarity_of(images[readable] if frames_touched is None else images[readable][frames_touched])
            if frames_touched is not None and frames_touched.any():  # touched frames told it: kept
                state = eqx.tree_at(lambda live: live.polarity, state, polarity, is_leaf=lambda node: node is None)
        left_behind, spans = np.zeros(len(frames), bool), None
        if state.polarity is not None and self.subspace is not None:
            test = _VoltageTest(
                skin.signed(frames),
                skin.signed(self.reference),
                skin.noise,
                skin.noise_frames,
                self.reference_frames,
                self.subspace,
            )
            start = self.anchoring
            if start is None:
                start = _Anchoring.at_reference(test, images.shape[1], (images.shape[1],))._replace(frame=self.frame)
            images = np.where(readable[:, None], images, 0.0)  # a frame not read is passed over
            scores = polarity * images if self.image_noise is None else polarity * images / self.image_noise
            anchor_of, anchors, left_behind, anchoring = _rest_anchors(
                test, scores, (images,), DETECTION, ~readable, start
            )
            images = _against(images, 2, anchor_of, anchors)
            frames_touched, spans = _against_anchors_tested(test, anchor_of, anchors, DETECTION)
            frames_touched, spans = frames_touched[readable], spans[readable]
            state = eqx.tree_at(lambda live: live.anchoring, state, anchoring, is_leaf=lambda node: node is None)
        found = read(
            self.mesh,
            images[readable],
            polarity=polarity,
            position_map=None if skin is None else skin.position_map,
            size_map=getattr(skin, "size_map", None),
            touched=frames_touched,
            relative=relative_floor(skin),
            image_noise=self.image_noise,
        )
        if spans is not None:
            marks = (spans, left_behind[readable])
            found = eqx.tree_at(lambda t: (t.anchor, t.remains), found, marks, is_leaf=lambda node: node is None)
        return found, left_behind, eqx.tree_at(lambda live: live.frame, state, self.frame + len(frames))


def relative_floor(calibration: Any) -> float:
    """The fraction of a frame's highest peak a further touch's must reach (module docstring,
    "The rule", step 2): `RELATIVE`, or the `ringing` of `calibration` (a
    `diffeit.calibration.SkinCalibration` from labelled presses, or None) where that is higher."""
    return max(RELATIVE, getattr(calibration, "ringing", None) or 0.0)


def image_noise(matrix: ArrayLike, reading_noise: ArrayLike, background: float | ArrayLike) -> np.ndarray:
    """(E,) each element's noise standard deviation in a one-step image, in relative change:
    sqrt(sum_m (R_em s_m)^2) / sigma_e, R the reconstruction matrix (E, M; `OneStep.matrix`,
    S/sq per unit of the readings), s the readings' independent noise (M,, their unit) and
    sigma the background (S/sq, scalar or (E,)).

    Near the electrodes a one-step image follows the readings most closely, and their noise and
    the model's errors there stand in it as narrow hills at the rim: `read` with it finds the
    hills on the image divided by it (module docstring, "The rule", step 2).

    Raises:
        ValueError: For a `reading_noise` that is not one finite value per column of `matrix`.
    """
    matrix = np.asarray(matrix, np.float64)
    reading_noise = np.asarray(reading_noise, np.float64)
    if reading_noise.shape != matrix.shape[1:] or not np.all(np.isfinite(reading_noise)):
        raise ValueError(
            f"reading_noise must hold {matrix.shape[1]} finite values, one per reading; got shape {reading_noise.shape}"
        )
    return np.sqrt(np.sum((matrix * reading_noise) ** 2, axis=1)) / np.asarray(background, np.float64)


def _one_step_noise(solver: Any, noise: np.ndarray | None, level: float | np.ndarray) -> np.ndarray | None:
    """`image_noise` of a one-step `solver`'s images (its `matrix`) for the readings' `noise` at
    `level` (S/sq), or None without a noise or where it is not finite and positive in every
    element."""
    if noise is None:
        return None
    values = image_noise(np.asarray(solver.matrix), noise, level)
    return values if np.all(np.isfinite(values) & (values > 0)) else None


def _images_noise(recording: Recording) -> np.ndarray | None:
    """The "image_noise" `diffeit.reconstruct` kept in the recording's provenance (its one-step
    images' `image_noise`, where it knew the readings' noise), or None.

    Raises:
        ValueError: For one that is not one finite positive value per element.
    """
    values = recording.provenance.get("metadata", {}).get("image_noise")
    if values is None:
        return None
    return _checked_element_noise(values, recording.mesh, "the recording's image_noise (provenance)")


def _damaged_frames(recording: Recording) -> np.ndarray | None:
    """(T,) bool, the frames `diffeit.reconstruct` found damaged ("damaged_frames" in the
    recording's provenance), or None where it does not say.

    Raises:
        ValueError: For "damaged_frames" that are not indices of the recording's frames.
    """
    listed = recording.provenance.get("metadata", {}).get("damaged_frames")
    if listed is None:
        return None
    listed = np.asarray(listed)
    n_frames = len(np.atleast_2d(recording.images))
    indices = listed.ndim == 1 and (not listed.size or listed.dtype.kind in "iu")
    if not indices or (listed.size and (listed.min() < 0 or listed.max() >= n_frames)):
        raise ValueError(f"the recording's damaged_frames (provenance) must be indices of its {n_frames} frames")
    damaged = np.zeros(n_frames, bool)
    damaged[listed.astype(int)] = True
    return damaged


def _checked_element_noise(values: ArrayLike, mesh: Mesh, name: str) -> np.ndarray:
    """`values` as float64, or a ValueError naming them (`name`) when they are not one finite
    positive value per element of `mesh`."""
    values = np.asarray(values, np.float64)
    if values.shape != (mesh.n_elements,) or not np.all(np.isfinite(values) & (values > 0)):
        raise ValueError(
            f"{name} must hold {mesh.n_elements} finite positive values, one per element; got shape {values.shape}"
        )
    return values


def touched(
    frames: ArrayLike,
    reference: ArrayLike,
    calibration: Any,
    *,
    detection: float = DETECTION,
    reference_frames: int | None = None,
    subspace: np.ndarray | None = None,
) -> np.ndarray | None:
    """Which frames stand out of the calibration's noise: the voltage test.

    The standardised sum of the squared whitened differences dv_m / s_m / sqrt(1 + 1/R)
    projected on the subspace a conductivity change reaches, each term taken as F(1, n - 1) for
    an untouched frame (module docstring, "The rule", step 1).

    Without the calibration's noise (a reference of fewer than 6 frames), each frame's
    differences in the subspace a conductivity change reaches are compared with those outside
    it (`_subspace_test`).

    Arguments:
        frames: (T, M) recorded frames.
        reference: (M,) the reference they are differences from, as recorded.
        calibration: A `diffeit.calibration.SkinCalibration`.
        detection: The statistic z above which a frame is touched.
        reference_frames: How many frames the reference is the mean of; None: the
            calibration's own reference frames (`noise_frames`).
        subspace: The calibration's `touch_subspace`, computed once by a caller that tests
            many batches (`diffeit live`); None computes it.

    Returns:
        (T,) bool, or None without a calibration (or with too few readings for the subspace
        test).
    """
    if calibration is None:
        return None
    dv = calibration.signed(np.atleast_2d(frames)) - calibration.signed(reference)
    noise = getattr(calibration, "noise", None)
    if noise is None:
        return _subspace_test(dv, calibration, detection)
    # Each reading's variance s^2 is estimated from n frames; an untouched frame's difference from
    # a reference of R frames has variance s^2 (1 + 1/R): (dv / s)^2 / (1 + 1/R) is F(1, n - 1).
    n = calibration.noise_frames
    averaged = n if reference_frames is None else reference_frames
    subspace = touch_subspace(calibration) if subspace is None else subspace
    return _noise_test(dv, noise, n, averaged, detection, subspace)


class _VoltageTest(NamedTuple):
    """A recording's frames and reference in the unit of their readings' noise, for the voltage
    test (`touched`)."""

    frames: np.ndarray  # (T, M)
    reference: np.ndarray  # (M,)
    noise: np.ndarray  # (M,) each reading's standard deviation
    noise_frames: int  # the frames it is estimated from
    reference_frames: int  # the frames the reference is the mean of
    subspace: np.ndarray | None  # `touch_subspace`, or None: every reading

    def whitened(self, dv: np.ndarray) -> np.ndarray:
        """(T, k) differences `dv` (T, M) or (M,) whitened and projected (`_whitened`)."""
        return _whitened(dv, self.noise, self.subspace)

    def statistic(self, dv: np.ndarray, variance: float | np.ndarray) -> np.ndarray:
        """(T,) `_statistic` of differences `dv` (T, M) of variance `variance` s^2 (a number, or
        (T, 1): each difference's own)."""
        return _statistic(dv, self.noise, self.noise_frames, variance, self.subspace)


def _subspace_tested(recording: Recording, detection: float) -> np.ndarray | None:
    """(T,) bool, the frames whose "touch_statistic" in the recording's provenance
    (`diffeit.reconstruct`'s `subspace_statistic`, made where the readings' noise is unknown)
    exceeds `detection`; None without one.

    Raises:
        ValueError: For a statistic that is not one value per frame.
    """
    statistic = recording.provenance.get("metadata", {}).get("touch_statistic")
    if statistic is None:
        return None
    statistic = np.asarray(statistic, np.float64)
    if statistic.shape != (recording.n_frames,) or np.isnan(statistic).any():
        raise ValueError(
            f"the recording's touch_statistic (provenance) must hold {recording.n_frames} values, one per frame, "
            f"none NaN; got shape {statistic.shape}"
        )
    return statistic > detection


def _voltage_test(recording: Recording, calibration: Any) -> _VoltageTest | None:
    """The voltage test of a recording with a reference: against the calibration's noise when it
    knows it (its signed readings, in the touch subspace), else against the reference frames'
    spread kept by `diffeit.reconstruct` (raw readings: a difference of magnitudes is as noisy
    as the signed difference); None without either.

    Raises:
        ValueError: For a "reading_noise" in the provenance that is not one finite value per
            reading.
    """
    metadata = recording.provenance.get("metadata", {})
    spread = metadata.get("reading_noise")
    lost = _lost_readings(recording)
    if getattr(calibration, "noise", None) is None:
        if spread is None:
            return None
        frames = np.atleast_2d(np.asarray(recording.frames, np.float64))
        spread = np.asarray(spread, np.float64)
        if spread.shape != frames.shape[1:] or not np.all(np.isfinite(spread)):
            raise ValueError(
                f"the recording's reading_noise (provenance) must hold {frames.shape[1]} finite values, one per "
                f"reading; got shape {spread.shape}"
            )
        spread = np.where(lost, 0.0, spread)  # zero: left out
        reference = np.asarray(recording.reference, np.float64)
        counts = metadata["noise_frames"], metadata["reference_frames"]
        projection = metadata.get("touch_projection")
        if projection is None:  # a recording imaged before it was kept: every raw reading
            return _VoltageTest(frames, reference, spread, *counts, None)
        projection = np.asarray(projection, np.float64)
        if projection.ndim != 2 or projection.shape[0] != frames.shape[1] or not np.all(np.isfinite(projection)):
            raise ValueError(
                f"the recording's touch_projection (provenance) must be ({frames.shape[1]}, k) finite values, a row "
                f"per reading; got shape {projection.shape}"
            )
        # `reading_projection` whitens in the model's units: the raw differences enter as they are.
        return _VoltageTest(frames, reference, np.ones(frames.shape[1]), *counts, projection)
    averaged = metadata.get("reference_frames") or calibration.noise_frames  # the reference's own frames, where known
    noise = np.where(lost[calibration.used], 0.0, calibration.noise)  # zero: left out
    return _VoltageTest(
        calibration.signed(np.atleast_2d(recording.frames)),
        calibration.signed(recording.reference),
        noise,
        calibration.noise_frames,
        averaged,
        _whitened_subspace(calibration, noise),
    )


def _lost_readings(recording: Recording) -> np.ndarray:
    """(M,) bool, the readings on the electrodes `diffeit.reconstruct` found lost during the
    recording ("lost_readings" in the provenance): no test or fit looks at them.

    Raises:
        ValueError: For indices that are not readings of the recording.
    """
    indices = np.asarray(recording.provenance.get("metadata", {}).get("lost_readings") or [], int)
    readings = recording.frames.shape[-1]
    if indices.size and (indices.ndim != 1 or indices.min() < 0 or indices.max() >= readings):
        raise ValueError(f"the recording's lost_readings (provenance) must be indices of its {readings} readings")
    lost = np.zeros(readings, bool)
    lost[indices] = True
    return lost


class _RestFrame(NamedTuple):
    """A frame `_rest_anchors` keeps (`_Anchoring.rest`, `_Anchoring.across`)."""

    index: int
    differences: np.ndarray  # (M,) against the reference
    scores: np.ndarray  # (E,) its image
    values: tuple[np.ndarray, ...]  # each of the values read against the anchors
    standing: bool  # it stood out of the noise of the anchor then in force
    left_behind: bool  # step 2 took it for what the last touch left
    moved_on: bool  # and it was that touch moved on


_RestFrames = tuple[_RestFrame, ...]


class _Anchor(NamedTuple):
    """An anchor (module docstring, "Rest anchors"): the frames whose mean it is (none for the
    recording's reference), how many frames its mean is of (the reference's for the reference),
    and the means over them of the differences, the scores and each of the values read against
    it (`_rest_anchors`; zeros for the reference)."""

    frames: np.ndarray
    count: int
    means: tuple[np.ndarray, ...]


class _Anchoring(NamedTuple):
    """The rest anchors' state between two frames: the anchor in force and what the rule needs
    of the frames before the next one. `diffeit.touches` carries it through a recording,
    `diffeit live` from one batch to the next."""

    frame: int  # the next frame's index
    anchor: _Anchor
    previous: tuple[np.ndarray, np.ndarray] | None  # the last frame's differences and scores; None after a damaged one
    # The highest frame since the last onset, against the level: differences, whitened, scores.
    peak: tuple[np.ndarray, np.ndarray, np.ndarray] | None
    rest_start: int  # the first frame after the last that held a touch
    rest: _RestFrames  # the last _ANCHOR_FRAMES intact frames since
    # What step 2 measures against: the anchor, or the one or two rest frames before the last
    # onset where they were alike and stood out of its noise, and it did not move to them.
    level: _Anchor
    # The last _ANCHOR_FRAMES frames that a touch left in full, at once (step 3); and whether the
    # anchor follows them (a rest level that drifts).
    across: _RestFrames
    drifting: bool

    @classmethod
    def at_reference(cls, test: _VoltageTest, elements: int, widths: tuple[int, ...]) -> _Anchoring:
        """Before the first frame: the recording's reference (its `test`'s), images of
        `elements` elements, values of `widths` columns each."""
        zeros = (np.zeros(test.frames.shape[1]), np.zeros(elements), *(np.zeros(width) for width in widths))
        reference = _Anchor(np.zeros(0, int), test.reference_frames, zeros)
        return cls(0, reference, None, None, 0, (), reference, (), False)


def _rest_anchors(
    test: _VoltageTest,
    scores: np.ndarray,
    values: tuple[np.ndarray, ...],
    detection: float,
    damaged: np.ndarray,
    state: _Anchoring,
) -> tuple[np.ndarray, list[_Anchor], np.ndarray, _Anchoring]:
    """Each frame's anchor (module docstring, "Rest anchors"), from `state` on.

    Arguments:
        test: The frames' voltage test.
        scores: (T, E) their images, a touch positive (divided by the images' noise where
            known): linear in the frames, as the differences `test` reads.
        values: Arrays (T, X) to be read against the anchors (each anchor keeps their mean over
            its frames).
        detection: The voltage test's z above which a difference stands out of the noise.
        damaged: (T,) bool, damaged frames: passed over (each keeps the anchor in force, is
            in no anchor, and no step to or from it is an onset).
        state: The state after the frames before these (`_Anchoring.at_reference` before the
            first).

    Returns:
        (T,) each frame's anchor, an index into the anchors: the state's anchor first, then
        those these frames set (a new anchor is also that of the frames since the last that
        held a touch among these: `LiveTouches`, which has shown the frames before, reads
        only the frames after against it); the anchors; (T,) bool, the frames that are what
        the last touch left (they stand out of their anchor's noise and are that touch scaled
        down, step 2); and the state after them.
    """
    dv = test.frames - test.reference
    first, anchor, previous, peak, rest_start, rest, level, across, drifting = state
    anchors = [anchor]
    anchor_of = np.zeros(len(dv), int)
    held, left_behind, moved_on = (np.zeros(len(dv), bool) for _ in range(3))
    # A frame less the one before (variance 2 s^2); the first against the state's last frame.
    before = dv[:1] if previous is None else previous[0][None]
    steps = test.statistic(np.diff(np.concatenate([before, dv]), axis=0), 2.0)
    for i in range(len(dv)):
        if damaged[i]:
            anchor_of[i], previous = len(anchors) - 1, None
            continue
        step = None if previous is None or steps[i] <= detection else (dv[i] - previous[0], scores[i] - previous[1])
        onset = step is not None and _onset(test, *step, peak, detection)
        if not onset and peak is not None:
            onset = _departs_from_rest(test, dv[i], scores[i], rest, peak, detection)
        if onset:
            window = rest[-_ANCHOR_FRAMES:]
            # A touch that moved on is no rest level (step 2).
            moved = None if any(frame.moved_on for frame in window) else _moved_anchor(test, window, anchor, detection)
            few = moved is None and len(rest) < _LEAST_REST_FRAMES
            short = _moved_anchor(test, rest, anchor, detection, least=1) if few else None
            if short is not None and step is not None and _remains_kept(test, rest, step[0], level, peak, detection):
                moved = short
            if moved is None and few:
                moved = _moved_anchor(test, across, anchor, detection, settled=not drifting)
                drifting = drifting or moved is not None
            if moved is not None:
                anchor, across = moved, across if drifting else ()
                anchors.append(anchor)
                anchor_of[max(rest_start - first, 0) : i] = len(anchors) - 1
            # A drifting level is the last rest's; the anchor, the mean of five, lags it.
            level = anchor if (moved is not None and not drifting) or short is None else short
            peak = None  # what is held is now measured against this onset's touches
        anchor_of[i] = len(anchors) - 1
        prior = None if previous is None else previous[0]
        previous = dv[i], scores[i]
        # Just after a held touch: the touch gone, nearer in full than the half a memory keeps
        # (its multiple in the step below -3/4 by 2 standard errors).
        released = first + i == rest_start and prior is not None and peak is not None
        if released:
            drop, drop_error = _step_multiple(test, dv[i] - prior, peak[1])
            released = drop + SIGNIFICANCE * drop_error < -(1.0 + RELEASED) / 2
        standing = bool(test.statistic(dv[i] - anchor.means[0], 1 + 1 / anchor.count)[0] > detection)
        base_dv, base_scores = level.means[:2]
        raised = bool(test.statistic(dv[i] - base_dv, 1 + 1 / level.count)[0] > detection)
        if not raised:
            # Back at the level step 2 measures against: the last touch left nothing, and a faint
            # press after it (its onset within the noise of a step) is no part of it. Before, such
            # a press was read as what the last one left, and its frames became an anchor that hid it (a
            # benchmark skin of 500 presses held 1 s, 10 frames of rest between: 29 of 450 missed).
            peak = None
        if raised:
            here, along = scores[i] - base_scores, test.whitened(dv[i] - base_dv)[0]
            if peak is None or here.max() > peak[2].max():
                peak = dv[i] - base_dv, along, here
            # What a touch left where it was is it scaled down, significantly above 0 and below
            # HELD (the scale's standard error from the readings' noise), in its voltages and in
            # its image's peak, and nothing else stands out.
            touch = peak[1]
            scale = (along @ touch) / (touch @ touch)
            error = np.sqrt((1 + 1 / level.count) / (touch @ touch))
            left = here - scale * peak[2]
            # A frame that dropped along the touch from the one before, significantly, was released
            # (a held touch relaxes far slower): below HELD it is what the touch left.
            dropped = False
            if prior is not None:
                drop, drop_error = _step_multiple(test, dv[i] - prior, touch)
                dropped = drop < -SIGNIFICANCE * drop_error
            ceiling = HELD if dropped else HELD - SIGNIFICANCE * error
            remains = SIGNIFICANCE * error < scale < ceiling and here.max() < HELD * peak[2].max()
            # Its pattern explains a share of the frame's change, or what it leaves is noise: faint
            # presses near the middle, one after another, passed for what a deeper one left.
            alike = scale**2 * (touch @ touch) >= EXPLAINED * (along @ along)
            alike = alike or _unexplained(test, along, touch, 1 + 1 / level.count) <= detection
            left_behind[i] = here.max() > 0 and remains and alike and left.max() <= THRESHOLD * _robust_std(left)
            held[i] = here.max() > 0 and not left_behind[i]
            # Passing for it but standing elsewhere, the touch moved on (a touch sliding towards the
            # middle): no part of a rest level of three frames or more, nor said to be what it
            # left. It ends no run of rest frames as a held frame would (the one or two after it
            # then passed for a rest level), and `_remains_kept` places one or two itself.
            moved_on[i] = left_behind[i] and not _where_it_was(here, peak[2])
        if held[i]:
            rest_start, rest = first + i + 1, ()
        else:
            frame = _RestFrame(
                first + i,
                dv[i],
                scores[i],
                tuple(value[i] for value in values),
                standing,
                left_behind[i],
                moved_on[i],
            )
            rest = (*rest, frame)[-_ANCHOR_FRAMES:]
            if released and not left_behind[i]:
                across = (*across, frame)[-_ANCHOR_FRAMES:]
    state = _Anchoring(first + len(dv), anchor, previous, peak, rest_start, rest, level, across, drifting)
    return anchor_of, anchors, left_behind & ~moved_on, state


def _where_it_was(image: np.ndarray, highest: np.ndarray) -> bool:
    """Whether a frame's `image` (E,) stands where its touch's `highest` frame's image (E,) did,
    as what the touch left does (step 2): its highest value within the highest frame's half
    height, or its value at the highest frame's peak at least half its own highest; or it has no
    hill above `LOW` robust standard deviations to place it by (the faint remains of a memory,
    whose peak the noise moves). A touch sliding towards the middle fades frame by frame, its
    voltages nearly the frame before scaled down, but its hill moves on."""
    if image.max() <= LOW * _robust_std(image):
        return True
    return bool(highest[np.argmax(image)] >= 0.5 * highest.max() or image[np.argmax(highest)] >= 0.5 * image.max())


def _step_multiple(test: _VoltageTest, step: np.ndarray, direction: np.ndarray) -> tuple[float, float]:
    """The least-squares multiple of a whitened `direction` (k,) in a `step` (M,) between two
    frames, and its standard error (the step's variance 2 s^2)."""
    size = float(direction @ direction)
    return float(test.whitened(step)[0] @ direction) / size, float(np.sqrt(2.0 / size))


def _unexplained(test: _VoltageTest, change: np.ndarray, touch: np.ndarray, variance: float) -> float:
    """The voltage test's statistic of a whitened `change` (k,; variance `variance` s^2) less its
    least-squares multiple of a whitened `touch` (k,)."""
    scale = (change @ touch) / (touch @ touch)
    return float(_standardised((change - scale * touch)[None] / np.sqrt(variance), test.noise_frames)[0])


def _moved_anchor(
    test: _VoltageTest,
    window: _RestFrames,
    anchor: _Anchor,
    detection: float,
    least: int = _LEAST_REST_FRAMES,
    settled: bool = True,
) -> _Anchor | None:
    """The anchor the rest frames `window` (`_Anchoring.rest`'s last) make at an onset, or None
    where they are no rest level moved from `anchor`'s: fewer than `least` of them, a step
    between two of them out of the noise (presses one after another that passed for what the
    one before left), one within the anchor's noise (it is at the anchor's level), or their
    mean within it. Not `settled`, a level known to drift, the last two are not asked: the
    frames need only be alike."""
    if len(window) < least or (settled and not all(frame.standing for frame in window)):
        return None
    steps = np.diff(np.stack([frame.differences for frame in window]), axis=0)
    if len(steps) and np.any(test.statistic(steps, 2.0) > detection):
        return None
    columns = zip(*(frame.values for frame in window), strict=True)
    means = (
        np.stack([frame.differences for frame in window]).mean(axis=0),
        np.stack([frame.scores for frame in window]).mean(axis=0),
        *(np.stack(values).mean(axis=0) for values in columns),
    )
    if settled and test.statistic(means[0] - anchor.means[0], 1 / len(window) + 1 / anchor.count)[0] <= detection:
        return None
    return _Anchor(np.array([frame.index for frame in window]), len(window), means)


def _against(values: np.ndarray, which: int, anchor_of: np.ndarray, anchors: list[_Anchor]) -> np.ndarray:
    """(T, X) the rows of `values` less their anchor's mean of them, its `which`th
    (`_rest_anchors`: 0 the differences, 1 the scores, then the values)."""
    return values - np.stack([anchor.means[which] for anchor in anchors])[anchor_of]


def _against_anchors_tested(
    test: _VoltageTest, anchor_of: np.ndarray, anchors: list[_Anchor], detection: float
) -> tuple[np.ndarray, np.ndarray]:
    """(T,) bool, the frames whose differences from their anchor stand out of its noise (the
    voltage test, with the anchor's number of frames), and (T, 2) the first and last frame of
    each frame's anchor (-1, -1: the recording's reference; `Touches.anchor`)."""
    counts = np.array([anchor.count for anchor in anchors])[anchor_of]
    dv = _against(test.frames - test.reference, 0, anchor_of, anchors)
    frames_touched = test.statistic(dv, (1 + 1 / counts)[:, None]) > detection
    spans = np.array([anchor.frames[[0, -1]] if len(anchor.frames) else [-1, -1] for anchor in anchors])
    return frames_touched, spans[anchor_of]


def _remains_kept(
    test: _VoltageTest,
    rest: _RestFrames,
    step: np.ndarray,
    level: _Anchor,
    peak: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    detection: float,
) -> bool:
    """Whether one or two rest frames (`_Anchoring.rest`, fewer than `_LEAST_REST_FRAMES`) are a
    rest level an onset's `step` (M,; from the last of them) is read against (module docstring,
    "Rest anchors", step 3; `_moved_anchor` asks the rest): each is what the last touch
    (`peak`) left, their mean change from the `level` step 2 measured them against
    (`_Anchoring.level`) is that touch scaled down in full (its image's highest value within
    the touch's half height; its whitened change less the least-squares multiple of the
    touch's within the noise), and the onset keeps it: the multiple of that change in the
    step's whitened differences (variance 2 s^2) is not below -`RELEASED` by `SIGNIFICANCE`
    standard errors."""
    if peak is None or not 0 < len(rest) < _LEAST_REST_FRAMES or not all(frame.left_behind for frame in rest):
        return False
    image = np.mean([frame.scores for frame in rest], axis=0) - level.means[1]
    if peak[2][np.argmax(image)] < 0.5 * peak[2].max():
        return False
    change = test.whitened(np.mean([frame.differences for frame in rest], axis=0) - level.means[0])[0]
    if _unexplained(test, change, peak[1], 1 / len(rest) + 1 / level.count) > detection:
        return False
    along, error = _step_multiple(test, step, change)
    return along + SIGNIFICANCE * error >= -RELEASED


def _departs_from_rest(
    test: _VoltageTest,
    dv: np.ndarray,
    scores: np.ndarray,
    rest: _RestFrames,
    peak: tuple[np.ndarray, np.ndarray, np.ndarray],
    detection: float,
) -> bool:
    """Whether a frame (differences `dv` (M,), image `scores` (E,)) brings a touch against the
    rest frames before it (`_Anchoring.rest`, at least `_LEAST_REST_FRAMES`): its departure from
    their mean is an onset (`_onset`, the departure's variance (1 + 1/n) s^2). A faint press
    after what a touch left steps out of the noise from their mean where its step from one
    frame (variance 2 s^2) does not, and without an onset it is read against the last touch's
    peak: as what that touch left (on the rest anchors benchmark's skin, 4 of 40 presses missed
    or read at the press before)."""
    if len(rest) < _LEAST_REST_FRAMES:
        return False
    variance = 1 + 1 / len(rest)
    departure = dv - np.mean([frame.differences for frame in rest], axis=0)
    if test.statistic(departure, variance)[0] <= detection:
        return False
    image = scores - np.mean([frame.scores for frame in rest], axis=0)
    return _onset(test, departure, image, peak, detection, variance)


def _onset(
    test: _VoltageTest,
    step: np.ndarray,
    step_image: np.ndarray,
    peak: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    detection: float,
    variance: float = 2.0,
) -> bool:
    """Whether a step between two frames that stands out of the noise (differences `step`
    (M,), image `step_image` (E,), a touch positive) brought a touch: when it grew a touch's
    hill (its image's largest value is positive), or when what is left of it once the
    least-squares multiple of the touch held since the last onset is taken out (`peak`, the
    differences, their whitened values and the image of its highest frame) stands out of the
    noise and grew one (a touch moved, or one added beside a deeper one; not that touch pressed
    deeper, relaxed or released, nor another released). `variance`: the step's, in s^2 (two
    frames': 2)."""
    if step_image.max() > -step_image.min():
        return True
    if peak is None:
        return False
    differences, touch, image = peak
    along = test.whitened(step)[0]
    scale = (along @ touch) / (touch @ touch)
    left = step_image - scale * image
    return bool(test.statistic(step - scale * differences, variance)[0] > detection and left.max() > -left.min())


def touch_subspace(calibration: Any) -> np.ndarray:
    """(M', k) where a conductivity change puts a frame's whitened differences: the left
    singular vectors of the calibrated model's Jacobian, each reading divided by its noise (the
    calibration's; M' the readings whose noise is not zero), whose singular values exceed
    `_SUBSPACE_CUT` of the largest. The voltage test (`touched`) sums the squared projections on
    them.

    Raises:
        ValueError: For a calibration that knows no noise (fewer than 6 reference frames).
    """
    noise = getattr(calibration, "noise", None)
    if noise is None:
        raise ValueError("the calibration knows no readings' noise (fewer than 6 reference frames): no subspace")
    return _whitened_subspace(calibration, noise)


def _whitened_subspace(calibration: Any, noise: np.ndarray) -> np.ndarray:
    """`touch_subspace` for the readings' `noise` (M_used,, in the units of `calibration.signed`)."""
    kept = noise > 0
    return _leading_subspace(_calibrated_jacobian(calibration)[kept] / noise[kept, None])


def _leading_subspace(jacobian: np.ndarray) -> np.ndarray:
    """(M, k) the left singular vectors of `jacobian` (M, E) whose singular values exceed
    `_SUBSPACE_CUT` of the largest. From the M x M Gram matrix, cheaper than an SVD while the
    readings are fewer than the elements: its eigenvalues are the squared singular values, and
    the cut at 0.1 of the largest is far above their rounding."""
    squared, basis = scipy.linalg.eigh(jacobian @ jacobian.T)
    return basis[:, squared > _SUBSPACE_CUT**2 * squared[-1]]


def _noise_test(
    dv: np.ndarray, noise: np.ndarray, n: int, averaged: int, detection: float, subspace: np.ndarray | None = None
) -> np.ndarray:
    """(T,) whether the standardised sum of the squared whitened differences w_m = dv_m / s_m /
    sqrt(1 + 1 / averaged) exceeds `detection` (`_statistic` of a frame against a reference of
    `averaged` frames)."""
    return _statistic(dv, noise, n, 1 + 1 / averaged, subspace) > detection


def _statistic(
    dv: np.ndarray, noise: np.ndarray, n: int, variance: float | np.ndarray, subspace: np.ndarray | None = None
) -> np.ndarray:
    """(T,) the standardised sum of the squared whitened differences w_m = dv_m / s_m /
    sqrt(variance): each term F(1, n - 1) for differences of untouched frames, `noise` s (M,)
    estimated from n frames and each difference's variance `variance` s^2 (1 + 1/R for a frame
    against the mean of R frames; a number, or (T, 1) one per difference). With a `subspace`
    (`touch_subspace`), the terms are w's projections on it (the F moments, a linear
    combination of t variables being nearer the normal, are conservative); without, the w_m
    themselves. A reading whose spread is zero (a
    constant channel) is left out."""
    return _standardised(_whitened(dv, noise, subspace) / np.sqrt(variance), n)


def _standardised(whitened: np.ndarray, n: int) -> np.ndarray:
    """(T,) `_statistic` of differences already whitened and divided by the square root of
    their variance factor, (T, k), the noise estimated from `n` frames."""
    freedom = n - 1
    mean = freedom / (freedom - 2)
    spread = 2 * freedom**2 * (freedom - 1) / ((freedom - 2) ** 2 * (freedom - 4))
    terms = whitened.shape[1]
    return (np.sum(whitened**2, axis=1) - terms * mean) / np.sqrt(terms * spread)


def _whitened(dv: ArrayLike, noise: np.ndarray, subspace: np.ndarray | None) -> np.ndarray:
    """(T, k) differences `dv` (T, M) or (M,) divided by the readings' `noise` (M,; a reading
    whose spread is zero left out), projected on `subspace` (M', k) when given."""
    kept = noise > 0
    whitened = np.atleast_2d(dv)[:, kept] / noise[kept]
    return whitened if subspace is None else whitened @ subspace


def reading_projection(calibration: Any, noise: np.ndarray) -> np.ndarray:
    """(M, k) the voltage test's projection of a frame's differences as recorded (M readings,
    raw) onto `touch_subspace`: row m is reading m's factor into the calibrated model's units
    (its sign and gain, `calibration.signed`) over its `noise` s_m (M_used,, those units) times
    the subspace's row, zero for a reading not used or whose noise is zero. `diffeit.reconstruct`
    keeps it where no calibration is given, so that `touches` tests the raw differences as the
    calibrated ones (`_voltage_test`)."""
    kept = noise > 0
    basis = _whitened_subspace(calibration, noise)
    readings = len(calibration.used)  # the recording's, used or not
    factor = calibration.signed(np.ones(readings))  # sign / gain per reading used
    projection = np.zeros((readings, basis.shape[1]))
    projection[np.flatnonzero(calibration.used)[kept]] = (factor[kept] / noise[kept])[:, None] * basis
    return projection


def _calibrated_jacobian(calibration: Any) -> np.ndarray:
    """(M, E) the calibrated model's Jacobian at its background, in the units of `signed`."""
    model = calibration.model
    return np.asarray(model.jacobian(per_element(calibration.background, model.n_elements)))


def _subspace_test(dv: np.ndarray, calibration: Any, detection: float) -> np.ndarray | None:
    """(T,) which frames' differences `dv` (T, M) stand out of their own noise (`subspace_statistic`
    above `detection`), or None when the readings are too few to tell."""
    statistic = subspace_statistic(dv, calibration)
    return None if statistic is None else statistic > detection


def subspace_statistic(dv: np.ndarray, calibration: Any) -> np.ndarray | None:
    """(T,) how far each frame's differences `dv` (T, M; in the units of `calibration.signed`)
    stand out of their own noise, or None when the readings are too few to tell: the test of a
    frame where the readings' noise is unknown.

    The calibrated Jacobian's left singular vectors split the readings' space: the k whose
    singular values exceed `_SUBSPACE_CUT` of the largest hold what a conductivity change
    makes, the M - k others little more than noise. For an untouched frame with noise alike on
    every reading, F = (|U_k^T dv|^2 / k) / (|dv - U_k U_k^T dv|^2 / (M - k)) is F(k, M - k)
    distributed, about 1 with standard deviation sqrt(2 / k + 2 / (M - k)); the statistic is
    (F - 1) over that, and a frame is touched when it exceeds `detection`. On simulated
    magnitude skins (192 readings, k about 45, medium noise) untouched frames reached F = 1.8 at
    most, pressed ones 2.4 at least. A board's noise may instead be a fraction of each reading
    (the leading subspace, on the largest readings, then holds more of it: an untouched frame
    of an adjacent board with 0.1% noise per reading stood 12.8 out): the statistic is the
    smaller of the two, on the differences as they are and on them relative to the model's
    readings (each at least 5% of their RMS).

    Raises:
        ValueError: For differences that are not (T, M) with M the calibrated model's readings,
            or not finite.
    """
    model = calibration.model
    dv = np.asarray(dv, np.float64)
    if dv.ndim != 2 or dv.shape[1] != model.protocol.n_measurements:
        raise ValueError(
            f"differences must be (T, {model.protocol.n_measurements}), the calibrated model's readings; "
            f"got shape {dv.shape}"
        )
    if not np.all(np.isfinite(dv)):
        raise ValueError("the differences hold NaN or infinite values")
    jacobian = _calibrated_jacobian(calibration)
    readings = np.abs(np.asarray(model.measure(per_element(calibration.background, model.n_elements))))
    scale = np.maximum(readings, _UNCERTAIN_READING * np.sqrt(np.mean(readings**2)))
    # Differences beyond float range (a damaged frame, imaged as non-finite) stand at NaN: no touch.
    with np.errstate(over="ignore", invalid="ignore"):
        statistics = [_split_statistic(dv, jacobian), _split_statistic(dv / scale, jacobian / scale[:, None])]
    found = [statistic for statistic in statistics if statistic is not None]
    return np.min(found, axis=0) if found else None


def _split_statistic(dv: np.ndarray, jacobian: np.ndarray) -> np.ndarray | None:
    """(T,) `subspace_statistic` of `dv` (T, M) for noise alike on every reading, the subspace
    that of `jacobian` (M, E); None with fewer than `_LEAST_REST` readings outside it."""
    basis = _leading_subspace(jacobian)
    k = basis.shape[1]
    rest = dv.shape[1] - k
    if rest < _LEAST_REST:
        return None
    inside = np.sum((dv @ basis) ** 2, axis=1)
    outside = np.maximum(np.sum(dv**2, axis=1) - inside, np.finfo(float).tiny)
    ratio = (inside / k) / (outside / rest)
    return (ratio - 1) / np.sqrt(2 / k + 2 / rest)


@host_algebra
def read(
    mesh: Mesh,
    images: ArrayLike,
    *,
    max_touches: int = 6,
    threshold: float = THRESHOLD,
    polarity: int = -1,
    position_map: Any = None,
    size_map: Any = None,
    stack: FoamStack | None = None,
    touched: np.ndarray | None = None,
    relative: float = RELATIVE,
    image_noise: ArrayLike | None = None,
    further: float = LOW,
) -> Touches:
    """The touches of relative-change images on a mesh (module docstring, "The rule").

    Arguments:
        mesh: The sheet the images are on.
        images: (T, E) or (E,) relative conductivity changes dsigma / sigma per element.
        max_touches: The most touches reported per frame.
        threshold: A touch's peak must exceed this many robust standard deviations of its image.
        polarity: -1 when a touch lowers the conductivity, +1 when it raises it.
        position_map: A callable from (..., D) read positions to the labels' frame
            (`diffeit.calibration.PositionMap`), or None.
        size_map: A callable from read positions (..., D), radii and depths (...) to the
            radii and depths reported (`diffeit.calibration.SizeMap`), or None.
        stack: A foam stack whose map gives pressures from depths, or None.
        touched: (T,) bool, which frames are touched (a test on the voltages, module
            docstring): a touched frame reports its strongest hill and the others above
            `further` robust standard deviations, an untouched one none; None applies
            `threshold` alone.
        relative: A further touch's peak must be at least this fraction of the highest's, in
            [0, 1).
        image_noise: (E,) each element's noise standard deviation in relative change
            (`image_noise`): the hills are then found, ordered and thresholded on the image
            divided by it (module docstring, "The rule", step 2), their sets, positions, radii
            and depths read on the image itself; None: found on the image.
        further: In a frame `touched` marks, the robust standard deviations a hill after the
            strongest must exceed.

    Returns:
        The `Touches` (T = 1 for one image).

    Raises:
        ValueError: For images of the wrong shape or not finite, a `max_touches` that is not a
            positive integer, a `polarity` other than -1 and +1, a `threshold` that is not
            positive, a `relative` outside [0, 1), `touched` not one per image, or an
            `image_noise` that is not one finite positive value per element.
    """
    images = np.atleast_2d(np.asarray(images, np.float64))
    if images.ndim != 2 or images.shape[1] != mesh.n_elements:
        raise ValueError(f"images have shape {images.shape}; expected (T, {mesh.n_elements}), one value per element")
    if not np.all(np.isfinite(images)):
        raise ValueError("images hold non-finite values (NaN or inf): no touches can be read")
    if int(max_touches) != max_touches or max_touches < 1:
        raise ValueError(f"max_touches must be a positive integer; got {max_touches}")
    if polarity not in (-1, 1):
        raise ValueError(f"polarity must be -1 (a touch lowers the conductivity) or +1; got {polarity}")
    if not (np.isfinite(threshold) and threshold > 0):
        raise ValueError(f"threshold must be a positive number of standard deviations; got {threshold}")
    if not 0 <= relative < 1:
        raise ValueError(f"relative must be a fraction of the highest peak in [0, 1); got {relative}")
    if not (np.isfinite(further) and further > 0):
        raise ValueError(f"further must be a positive number of standard deviations; got {further}")
    if image_noise is not None:
        image_noise = _checked_element_noise(image_noise, mesh, "image_noise")
    count = np.zeros(len(images), int)
    position = np.full((len(images), max_touches, mesh.nodes.shape[1]), np.nan)
    radius = np.full((len(images), max_touches), np.nan)
    depth = np.full((len(images), max_touches), np.nan)
    noise = np.zeros(len(images))
    if touched is not None and np.shape(touched) != (len(images),):
        raise ValueError(f"touched has shape {np.shape(touched)}; expected ({len(images)},), one per image")
    for t, image in enumerate(images):
        if touched is None:
            hills, noise[t] = _hills(mesh, polarity * image, max_touches, threshold, relative, image_noise)
        elif touched[t]:
            found = _hills(mesh, polarity * image, max_touches, further, relative, image_noise, strongest=True)
            hills, noise[t] = found
        else:
            hills, noise[t] = [], _robust_std(polarity * image)
        count[t] = len(hills)
        for k, (centre, size, peak) in enumerate(hills):
            position[t, k], radius[t, k], depth[t, k] = centre, size, polarity * peak
    if size_map is not None:
        radius, depth = size_map(position, radius, depth)
    if position_map is not None:
        position = position_map(position)
    pressure = None if stack is None else _pressure(depth, stack)
    return Touches(count, position, radius, depth, pressure, noise)


def polarity_of(images: ArrayLike) -> int:
    """Whether the touches of `images` lower the conductivity (-1) or raise it (+1): the sign
    of the median, over the images (T, E), of each image's value of largest magnitude; -1 for
    no images or a median of zero.

    Pass the touched frames' images: an untouched image's largest value is noise of either
    sign.

    Raises:
        ValueError: For images that are not (T, E) or (E,), or not finite.
    """
    images = np.atleast_2d(np.asarray(images, np.float64))
    if images.ndim != 2:
        raise ValueError(f"images have shape {images.shape}; expected (T, E) or (E,), one value per element")
    if not np.all(np.isfinite(images)):
        raise ValueError("images hold non-finite values (NaN or inf): no polarity can be read")
    if images.size == 0:
        return -1
    extremes = images[np.arange(len(images)), np.argmax(np.abs(images), axis=1)]
    return 1 if np.median(extremes) > 0 else -1


def _robust_std(values: np.ndarray) -> float:
    return 1.4826 * float(np.median(np.abs(values - np.median(values))))


def _hills(
    mesh: Mesh,
    values: np.ndarray,
    max_touches: int,
    threshold: float,
    relative: float,
    image_noise: np.ndarray | None = None,
    strongest: bool = False,
) -> tuple[list, float]:
    """The touches of one image `values` (a touch positive): (centre, radius, peak) each, a
    further one at least `relative` of the highest's peak, and the image's robust standard
    deviation; with `strongest`, the highest hill counts whatever its height (when it is
    positive). With `image_noise` (E,), the hills are those of values / image_noise (found,
    ordered, thresholded and merged there), each read on `values` from its highest element."""
    noise = _robust_std(values)
    scores = values if image_noise is None else values / image_noise
    adjacency = _adjacency(mesh)
    neighbour_max = _neighbour_max(adjacency, scores)
    floor = threshold * (noise if image_noise is None else _robust_std(scores))
    if strongest:
        floor = min(floor, float(np.max(scores)))
    maxima = np.flatnonzero((scores >= neighbour_max) & (scores > 0) & (scores >= floor))
    claimed = np.zeros(len(values), bool)
    areas, centroids = mesh.element_areas, mesh.element_centroids
    hills = []
    for element in maxima[np.argsort(-scores[maxima])]:
        if image_noise is None and hills and values[element] < relative * hills[0][2]:
            break  # ringing of the highest hill; every later maximum is lower still
        if len(hills) == max_touches:
            break
        if claimed[element]:
            continue
        order = _connected(adjacency, scores >= 0.5 * scores[element], element)
        if claimed[order].any():
            claimed[order] = True
            continue
        claimed[order] = True
        if image_noise is not None:  # the touch on the image, from its highest element
            element = order[np.argmax(values[order])]
            order = _connected(adjacency, values >= 0.5 * values[element], element)
            if hills and values[element] < relative * hills[0][2]:
                continue  # ringing of the highest hill
        peak = values[element]
        weight = values[order] * areas[order]
        centre = weight @ centroids[order] / weight.sum()
        centre = onto_surface(mesh, centre, order)  # on a curved skin, onto it
        hills.append((centre, float(np.sqrt(areas[order].sum() / np.pi)), float(peak)))
    return hills, noise


def _connected(adjacency: scipy.sparse.csr_matrix, keep: np.ndarray, element: int) -> np.ndarray:
    """The elements of `keep` connected to `element` through edges between elements of `keep`,
    breadth first from it (a walk over the set alone: a hill's set is a few dozen elements)."""
    starts, neighbours = adjacency.indptr, adjacency.indices
    found, order = {element}, [element]
    for current in order:
        for neighbour in neighbours[starts[current] : starts[current + 1]].tolist():
            if keep[neighbour] and neighbour not in found:
                found.add(neighbour)
                order.append(neighbour)
    return np.array(order)


def _neighbour_max(adjacency: scipy.sparse.csr_matrix, values: np.ndarray) -> np.ndarray:
    """(E,) the largest value among each element's edge neighbours."""
    rows = np.repeat(np.arange(adjacency.shape[0]), np.diff(adjacency.indptr))
    result = np.full(len(values), -np.inf)
    np.maximum.at(result, rows, values[adjacency.indices])
    return result


@functools.lru_cache(maxsize=16)
def _adjacency(mesh: Mesh) -> scipy.sparse.csr_matrix:
    """(E, E) the elements sharing an edge."""
    edges = np.sort(mesh.triangles[:, [[0, 1], [1, 2], [2, 0]]], axis=2).reshape(-1, 2)
    owner = np.repeat(np.arange(mesh.n_elements), 3)
    key = edges[:, 0] * mesh.n_nodes + edges[:, 1]
    order = np.argsort(key, kind="stable")
    shared = np.flatnonzero(key[order][1:] == key[order][:-1])
    a, b = owner[order][shared], owner[order][shared + 1]
    matrix = scipy.sparse.coo_matrix((np.ones(len(a)), (a, b)), shape=(mesh.n_elements,) * 2)
    return (matrix + matrix.T).tocsr()


def _pressure(depth: np.ndarray, stack: FoamStack) -> np.ndarray:
    """kPa from relative changes dsigma / sigma through the stack's bilinear map (the inverse
    of `diffeit.scene.pressure_to_change`); 0 for a depth that is not a decrease."""
    x = np.maximum(-depth / (1.0 + depth), 0.0)
    knee = float(stack.knee) * float(stack.sensitivity)
    below = x / float(stack.sensitivity)
    above = float(stack.knee) + (x - knee) / float(stack.sensitivity_above)
    return np.where(x <= knee, below, above)


# --- method="fit": discs fitted to the voltages ----------------------------------------------


class _DiscFit(eqx.Module):
    """What the predicted differences of K discs depend on besides their parameters (module
    docstring, "Refinement by the model")."""

    model: ForwardModel
    level: jax.Array  # (E,) the calibrated background, S/sq: the level, or the background map
    base: jax.Array  # (M,) the readings at the background

    @classmethod
    def of(cls, model: ForwardModel, background: float | np.ndarray) -> _DiscFit:
        sigma = per_element(background, model.n_elements)
        return cls(model, sigma, model.measure(sigma))


def _disc_fraction(fit: _DiscFit, disc: jax.Array, plane: jax.Array) -> jax.Array:
    """(E,) the fraction of each element under the disc (u, v, radius), m, centred at u, v in
    the plane (3, D) (its origin and two orthonormal directions): the smooth disc footprint of
    `diffeit.scene.shape_fraction` (an erf edge of the mesh's default width)."""
    return shape_fraction(fit.model.mesh, Disc(_in_plane(disc, plane), disc[2]), level=FIT_LEVEL)


def _in_plane(theta: Any, planes: Any) -> Any:
    """(..., D) the points at (u, v) = theta[..., :2] in `planes` (..., 3, D): origin + u first
    direction + v second (NumPy or JAX)."""
    return planes[..., 0, :] + theta[..., :1] * planes[..., 1, :] + theta[..., 1:2] * planes[..., 2, :]


def _change(fit: _DiscFit, theta: jax.Array, planes: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The relative conductivity change sum_k depth_k f_k (E,) of discs `theta` (K, 4), rows
    (u, v, radius, strength) in m, m, m and m^2 (u, v in each disc's plane of `planes` (K, 3,
    D); strength = depth radius^2: the data determine it far better than the depth of a small
    disc), and its derivatives (4K, E), row-major in theta: forward differentiation
    (`jax.jacfwd`) of each disc's footprint in its own three geometric parameters (not of every
    disc in all 4K)."""
    slopes, fractions = jax.vmap(jax.jacfwd(lambda disc, plane: (_disc_fraction(fit, disc, plane),) * 2, has_aux=True))(
        theta[:, :3], planes
    )  # (K, E, 3) and (K, E)
    radius, strength = theta[:, 2], theta[:, 3]
    depth = strength / radius**2
    tangents = jnp.stack(
        [
            depth[:, None] * slopes[..., 0],
            depth[:, None] * slopes[..., 1],
            depth[:, None] * slopes[..., 2] - (2 * strength / radius**3)[:, None] * fractions,
            fractions / radius[:, None] ** 2,
        ],
        axis=1,
    ).reshape(-1, fractions.shape[1])
    return depth @ fractions, tangents


@eqx.filter_jit
def _disc_readings(fit: _DiscFit, theta: jax.Array, planes: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The differences dv(theta) (M,) of discs `theta` (K, 4) in their `planes` (K, 3, D)
    (`_change`) through the model, their (M, 4K) Jacobian (the model's conductivity Jacobian,
    by the adjoint path, times the 4K conductivity changes of `_change`: its cost does not grow
    with K, as tangent solves would), and the least relative conductivity min(1 + change).
    Compiled once per model and K."""
    change, tangents = _change(fit, theta, planes)
    # The conductivity is kept positive (the fit rejects steps where 1 + change < 0.02 anyway,
    # so the clamp never reaches an accepted step's Jacobian).
    sigma = fit.level * jnp.maximum(1.0 + change, 1e-2)
    readings, jacobian = fit.model.measure_and_jacobian(sigma)
    return readings - fit.base, jacobian @ (fit.level * tangents).T, jnp.min(1.0 + change)


def _refined(
    calibration: Any, dv: np.ndarray, found: Touches, mapping: Any, stack: FoamStack | None, lost: np.ndarray
) -> Touches:
    """The image method's touches `found` (in the mesh's frame) refined by fitting discs to
    each touched frame's differences `dv` (T, M; module docstring, "Refinement by the model"),
    the readings `lost` (M,) bool (on a lost electrode) weighing nothing."""
    model = calibration.model
    fit = _DiscFit.of(model, calibration.background)
    noise = getattr(calibration, "noise", None)
    weights = None
    # Where most readings have no measured spread (a noise-free simulation's identical reference
    # frames) there is no noise to weigh by: unweighted, as without one (infinite weights had
    # failed the solve).
    if noise is not None and np.median(noise) > 0:
        noise = np.asarray(noise, np.float64)
        # A reading of no measured spread would take all the weight: floored at 1e-3 of the median.
        weights = 1.0 / np.maximum(noise, 1e-3 * np.median(noise))
    noise_known = weights is not None
    if lost.any():
        weights = np.where(lost, 0.0, 1.0 if weights is None else weights)
        dv = np.where(lost, 0.0, dv)
    nodes = model.mesh.nodes
    middle = nodes.mean(axis=0)
    size = float(np.max(np.linalg.norm(nodes - middle, axis=1)))
    # No disc narrower than its footprint's edge (the scene's default edge width at FIT_LEVEL).
    width = 2.0 * float(np.sqrt(np.max(model.mesh.element_areas))) / FIT_LEVEL
    limits = (middle, size, width)
    count = np.zeros_like(found.count)
    position = np.full_like(found.position, np.nan)
    radius, depth = np.full_like(found.radius, np.nan), np.full_like(found.depth, np.nan)
    errors = np.full((*found.radius.shape, 4), np.nan)
    covariances = np.full((*found.radius.shape, 2, 2), np.nan)
    axes = np.full((*found.radius.shape, 2, nodes.shape[1]), np.nan)  # the directions the centres' errors are along
    misfit = np.full(len(dv), np.nan)
    for t in np.flatnonzero(found.count > 0):
        k = int(found.count[t])
        planes = np.stack([_tangent_plane(model.mesh, point) for point in found.position[t, :k]])
        start = np.column_stack(
            [
                np.zeros((k, 2)),
                np.clip(found.radius[t, :k], width, 0.5 * size),
                np.clip(found.depth[t, :k], -0.9, 10.0),
            ]
        )
        theta, planes, covariance, misfit[t] = _fit_discs(fit, dv[t], weights, noise_known, start, planes, limits)
        count[t] = len(theta)
        if not len(theta):
            continue
        order = np.argsort(-np.abs(theta[:, 3]))
        n = len(theta)
        blocks = covariance.reshape(n, 4, n, 4)[order, :, order, :]  # (n, 4, 4): each disc's own block
        position[t, :n] = [onto_surface(model.mesh, centre) for centre in _in_plane(theta[order], planes[order])]
        radius[t, :n], depth[t, :n] = theta[order, 2], theta[order, 3]
        with np.errstate(invalid="ignore"):
            errors[t, :n] = np.sqrt(np.einsum("kii->ki", blocks))
        covariances[t, :n] = blocks[:, :2, :2]
        axes[t, :n] = planes[order, 1:]
    if mapping is not None:
        mapped = mapping(position)
        errors[..., :2] = _mapped_errors(mapping, model.mesh, position, mapped, covariances, axes)
        position = mapped
    pressure = None if stack is None else _pressure(depth, stack)
    return Touches(count, position, radius, depth, pressure, found.noise, errors, misfit, found.damaged)


def _tangent_plane(mesh: Mesh, point: np.ndarray) -> np.ndarray:
    """(3, D) `point` and two orthonormal directions of the sheet there: the plane of the
    element whose centroid is nearest on a curved skin, the axes on a flat one."""
    if mesh.nodes.shape[1] == 2:
        return np.vstack([point, np.eye(2)])
    element, _, normal = nearest_element(mesh, point[None])
    corners = mesh.nodes[mesh.triangles[element[0]]]
    first = corners[1] - corners[0]
    first /= np.linalg.norm(first)
    return np.vstack([point, first, np.cross(normal[0], first)])


def _fit_discs(
    fit: _DiscFit,
    dv: np.ndarray,
    weights: np.ndarray | None,
    noise_known: bool,
    start: np.ndarray,
    planes: np.ndarray,
    limits: tuple,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Discs (K', 4) fitted to one frame's differences `dv` (M,) (each reading weighed by
    `weights`, 1 / its noise where `noise_known`) from `start` (K, 4), rows
    (u, v, radius, depth), u and v in each disc's plane of `planes` (K, 3, D), the
    insignificant dropped one at a time, never the last (module docstring); the planes (K', 3, D) of those
    kept, their (4K', 4K') covariance and the relative residual ||dv - dv(theta)|| / ||dv||."""
    theta = start.copy()
    theta[:, 3] *= theta[:, 2] ** 2  # fitted as (u, v, radius, strength = depth radius^2)
    scale = np.ones(len(dv)) if weights is None else weights
    norm = float(np.linalg.norm(dv)) or 1.0
    while True:
        theta, curvature, residual = _levenberg_marquardt(fit, dv, scale, noise_known, theta, planes, limits)
        covariance = _covariance(curvature, residual, noise_known)
        significance = _significance(theta, covariance)
        # The last disc stays: the frame stood out of the noise (a touch is there), and its
        # standard errors say how well the fit places it.
        if len(theta) == 1 or np.all(significance >= SIGNIFICANCE):
            natural, covariance = _natural(theta, covariance)
            return natural, planes, covariance, float(np.linalg.norm(residual / scale)) / norm
        weakest = int(np.argmin(significance))
        theta, planes = np.delete(theta, weakest, axis=0), np.delete(planes, weakest, axis=0)


def _covariance(curvature: np.ndarray, residual: np.ndarray, noise_known: bool) -> np.ndarray:
    """(P, P) the parameters' covariance from the curvature J^T W^2 J and the weighted
    residual (M,): its inverse times chi^2 per degree of freedom (at least 1 when the weights
    are 1 / noise). A parameter the data do not determine gets a huge variance (the inverse of
    the curvature scaled to unit diagonal, with a 1e-10 ridge), not NaN."""
    freedom = max(len(residual) - len(curvature), 1)
    chi2 = float(residual @ residual) / freedom
    factor = max(chi2, 1.0) if noise_known else chi2
    diagonal = np.sqrt(np.diag(curvature))
    unit = np.where(diagonal > 0, diagonal, 1e-300)
    scaled = curvature / np.outer(unit, unit) + 1e-10 * np.eye(len(curvature))
    return factor * np.linalg.inv(scaled) / np.outer(unit, unit)


def _significance(theta: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """(K,) |strength| / its standard error for discs (K, 4) (x, y, radius, strength).

    depth = 0 is strength = 0; the strength's standard error is far smaller than the depth's
    where the radius is poorly determined (depth and radius trade off at a fixed strength)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        significance = np.abs(theta[:, 3]) / np.sqrt(np.diag(covariance)[3::4])
    return np.where(np.isnan(significance), 0.0, significance)  # an exact fit: inf, significant


def _natural(theta: np.ndarray, covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Discs (K, 4) as (x, y, radius, depth) from (x, y, radius, strength), and their
    covariance (4K, 4K) through the transformation's Jacobian (depth = strength / radius^2)."""
    radius, strength = theta[:, 2], theta[:, 3]
    natural = theta.copy()
    natural[:, 3] = strength / radius**2
    blocks = np.zeros((len(theta), 4, 4))
    blocks[:] = np.eye(4)
    blocks[:, 3, 2] = -2 * strength / radius**3
    blocks[:, 3, 3] = 1 / radius**2
    jacobian = scipy.linalg.block_diag(*blocks)
    return natural, jacobian @ covariance @ jacobian.T


def _levenberg_marquardt(
    fit: _DiscFit,
    dv: np.ndarray,
    weights: np.ndarray,
    noise_known: bool,
    theta: np.ndarray,
    planes: np.ndarray,
    limits: tuple,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The discs (K, 4) (u, v, radius, strength; u, v in their `planes` (K, 3, D)) minimising
    ||weights (dv - dv(theta))||^2 from `theta`, the Gauss-Newton curvature J^T W^2 J there
    and the weighted residual. With `noise_known` (weights 1 / noise) chi^2 is in units of
    the noise variance, else of the residual's. The centre and radius of a disc whose strength
    is not significant at the current step are held (they are not determined: free, they wander
    and cost steps); the strength is always fitted."""
    middle, size, width = limits

    def evaluate(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, float] | None:
        centres = _in_plane(theta, planes)
        radii, depths = theta[:, 2], theta[:, 3] / theta[:, 2] ** 2
        if (
            np.any(np.linalg.norm(centres - middle, axis=1) > size)
            or np.any(radii < 0.25 * width)
            or np.any(radii > size)
            or np.any(depths <= -0.98)
        ):
            return None
        predicted, jacobian, lowest = _disc_readings(fit, jnp.asarray(theta), jnp.asarray(planes))
        if float(lowest) < 0.02:
            return None
        residual = weights * (dv - np.asarray(predicted))
        return residual, weights[:, None] * np.asarray(jacobian), float(residual @ residual)

    state = evaluate(theta)
    if state is None:  # a start outside the limits: moved into them (the planes' origins are on the sheet)
        theta = theta.copy()
        theta[:, :2] = 0.0
        theta[:, 2] = np.clip(theta[:, 2], width, 0.5 * size)
        theta[:, 3] = np.clip(theta[:, 3] / theta[:, 2] ** 2, -0.5 / len(theta), 10.0) * theta[:, 2] ** 2
        state = evaluate(theta)
        if state is None:
            raise ValueError("the image's touches give no start the disc fit can evaluate")
    residual, design, cost = state
    damping = 1e-3
    for _ in range(_FIT_STEPS):
        curvature = design.T @ design
        gradient = design.T @ residual
        significant = _significance(theta, _covariance(curvature, residual, noise_known)) >= SIGNIFICANCE
        free = np.column_stack([np.repeat(significant[:, None], 3, axis=1), np.ones(len(theta), bool)]).ravel()
        block, pull = curvature[np.ix_(free, free)], gradient[free]
        diagonal = np.maximum(np.diag(block), 1e-12 * np.max(np.diag(block)))
        # chi^2's unit: the noise's variance, or the residual's per degree of freedom where that
        # is larger (the model's own error, which `_covariance` scales the errors by too: a
        # step far below it moves the discs far less than their errors; on a noise-free frame
        # weighed by rounding's spread the steps had run until the damping gave out).
        variance = max(cost / max(len(dv) - theta.size, 1), 1.0 if noise_known else 1e-300)
        # Converged when even the Gauss-Newton step would lower chi^2 by less than the tolerance.
        newton = np.linalg.lstsq(block, pull, rcond=None)[0]
        if (newton @ pull) / variance < _FIT_TOLERANCE:
            break
        accepted = False
        while damping < 1e10 and not accepted:
            step = np.zeros(theta.size)
            step[free] = np.linalg.solve(block + damping * np.diag(diagonal), pull)
            trial = evaluate(theta + step.reshape(theta.shape))
            accepted = trial is not None and trial[2] < cost
            if accepted:
                decrease = cost - trial[2]
                theta, (residual, design, cost) = theta + step.reshape(theta.shape), trial
                damping = max(damping / 10, 1e-7)
            else:
                damping *= 10
        # ... or when a step lowered it by less (a flat valley the steps zigzag along).
        if not accepted or decrease / variance < _FIT_TOLERANCE:
            break
    return theta, design.T @ design, residual


def _mapped_errors(
    mapping: Any, mesh: Mesh, position: np.ndarray, mapped: np.ndarray, covariances: np.ndarray, axes: np.ndarray
) -> np.ndarray:
    """(..., 2) the standard errors of the positions (..., D) (mesh frame, m) after the map
    (`mapped`, the map of `position`), along the sheet's directions there (`_tangent_plane`:
    the axes on a flat sheet), from their covariances (..., 2, 2) along `axes` (..., 2, D)
    through the map's local Jacobian (central differences)."""
    step = 1e-6
    columns = [
        (mapping(position + step * unit) - mapping(position - step * unit)) / (2 * step)
        for unit in np.eye(position.shape[-1])
    ]
    jacobian = np.stack(columns, axis=-1) @ np.swapaxes(axes, -1, -2)  # (..., D, 2): along the axes
    after = np.full_like(axes, np.nan)
    placed = np.all(np.isfinite(mapped), axis=-1)
    after[placed] = [_tangent_plane(mesh, point)[1:] for point in mapped[placed]]
    along = after @ jacobian  # (..., 2, 2)
    covariance = along @ covariances @ np.swapaxes(along, -1, -2)
    with np.errstate(invalid="ignore"):
        return np.sqrt(np.diagonal(covariance, axis1=-2, axis2=-1))
