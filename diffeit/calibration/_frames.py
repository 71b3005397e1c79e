"""The frames a calibration stands on: a recording's untouched reference frames (`reference_frames`,
`calibrated_reference_frames`), the frames a board damaged (`damaged_frames`, `glitched_frames`), the
electrodes lost during a recording (`lost_electrodes`), and the
common gain's drift taken out of a recording (`drift_corrected`) or of a stream (`LiveDrift`),
the rests told from the presses by their gains.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from typing import NamedTuple

import equinox as eqx
import numpy as np
import scipy.stats
from numpy.typing import ArrayLike

from .._arrays import frame_period
from .._messages import name_indices
from .._threads import host_algebra
from ..io import Presses, Recording
from ..protocol import Protocol
from ..touch import DETECTION, _noise_test, _statistic, subspace_statistic, touch_subspace
from ._reference import _broken_electrodes, _uses
from ._skin import SkinCalibration

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


# A frame whose readings, moved up to _MOVED_PLACES places along from some reading on, lie within
# _MOVED_FIT of its distance from the frames about it is damaged (`_readings_moved`).
_MOVED_PLACES, _MOVED_FIT = 2, 0.5


# An electrode is lost in a frame when half the readings on it changed by more than
# _LARGEST_CHANGE of their reference (`_broken_electrodes`), and at most _STRAY_SHARE of the
# readings on no lost electrode did (else the whole frame is a glitch); lost from the recording
# when so in at least _LOST_FRAMES frames (one frame so is a damaged frame). A press changes a
# reading by a few percent: a connector or electrode come loose sends those readings to zero,
# saturation or noise.
_STRAY_SHARE, _LOST_FRAMES = 0.1, 3
# ... and when at least this share of the readings are on none of the frame's lost electrodes.
_LEAST_LEFT = 0.25


# A recording's first frames that look touched are left out of its reference when they are at
# most this many (a board's first frames after it connects; `reference_frames`).
_LEADING_DAMAGED = 2


_DRIFT_DETECTION = 5.0  # z of a frame untouched but for its common gain (`drift_corrected`)


_DRIFT_WINDOW = 9  # untouched frames in the running median of their gains (`drift_corrected`)


_GAIN_STEP = 3.0  # standard errors of a step in the gains that cuts a run of untouched frames (`_gain_steps`)


# Runs of untouched frames shorter than this among touched ones are rests only when their gains
# stand apart from the presses beside them as a rest's do, where a press moves the gain by more
# than this many times a gain's noise (`_rests_not_presses`).
_LONG_REST, _PRESS_PART = 5, 4.0


_LEAST_NEAR = 3  # touched frames near untouched ones that tell a press's part of the common gain (`drift_corrected`)


_DRIFT_CHANCE = 1e-6  # the chance that the reference's own jitter passes for a drift (`drift_corrected`)


_ROUND_OFF = 1e-12  # a reading's spread under this fraction of its value is round-off, not noise (`drift_corrected`)


_LIVE_DRIFT_ERRORS = 3.0  # a stream's running gain is taken out beyond this many standard errors from 1 (`LiveDrift`)


# A stream's untouched frames join its drift's gains in pieces: a piece of at least _LIVE_SETTLED
# frames whose mean gain lies within _GAIN_STEP standard errors of the gains' trend, or of
# _LIVE_PIECE frames whose mean shows no touch's pattern (the trend's new level), once the gains
# hold _LIVE_TREND frames (before, every untouched frame joins them: no trend to stand off).
_LIVE_SETTLED, _LIVE_PIECE, _LIVE_TREND = 3, 2 * _DRIFT_WINDOW, 3
# A stream's trend is the median of its latest _DRIFT_WINDOW joined gains moved along the slope of
# the latest _LIVE_SLOPE (`LiveDrift`): a touch's step in the gain stands off a trend a few frames
# on from them only when its slope is known to a fraction of a gain's noise over those frames.
_LIVE_SLOPE = 3 * _DRIFT_WINDOW
# A piece that showed a touch's pattern shows it until the z of its latest frames' mean falls to
# this (a faint touch's z wavers about `_DRIFT_DETECTION`; `LiveDrift`).
_LIVE_GONE = 3.0
# With fewer reference frames than this, a stream's untouched frames join its gains at once: the
# reference's own noise hides a faint touch's pattern, and its jitter, from so few frames, is
# too uncertain to tell a touch's step (6 frames: a stream ran 2.8% astray, its gains' slope
# tilted by a touch's frames that joined them).
_LIVE_REFERENCE = 10


# A block of frames differs from the untouched frames before it beyond this many robust spreads of
# their noise (`_unchanged`).
_CHANGE_SPREADS = 6.0


# The fewest reference frames whose spread gives the readings' noise (the touch test needs 5 degrees of freedom).
_NOISE_FRAMES = 6


def reading_spread(frames: np.ndarray) -> np.ndarray | None:
    """Each reading's noise, from its spread over untouched frames.

    Arguments:
        frames: (N, M) untouched frames (the reference frames), in any one unit.

    Returns:
        (M,) each reading's sample standard deviation over the frames, in their unit; None for
        fewer than `_NOISE_FRAMES` (6) frames, too few to test a touch against (its test needs
        5 degrees of freedom).

    Raises:
        ValueError: For frames that are not (N, M), or hold NaN or inf.
    """
    frames = _checked_frames(frames, name="frames")
    return np.std(frames, axis=0, ddof=1) if len(frames) >= _NOISE_FRAMES else None


def reference_frames(
    recording: Recording,
    reference_frame: int | None = None,
    presses: Presses | None = None,
    *,
    every_frame: bool = False,
    run_frames: int | None = None,
) -> tuple[np.ndarray, str]:
    """The frames a recording's model is calibrated on, and where they come from.

    The recording's reference; else its frame `reference_frame`; else, with presses, the
    frames before the first press, chosen among them as a session's below when they are more
    than `REFERENCE_FRAMES` (the presses labelled may be some of the session's, the others
    kept to test on, and some of those may come first: a faint press held several frames
    passes `_untouched` frame by frame), else those not damaged; or, when no frame comes before
    it, those outside every hold that look untouched (`_untouched`, when more than
    `REFERENCE_FRAMES`); else
    the recording's first frames up to the first that looks touched (`_untouched`, among the
    first `_SESSION_FRAMES`, for more than `REFERENCE_FRAMES` frames), however few; when its
    first `_LEADING_DAMAGED` frames or fewer look touched (damaged), the untouched run after
    them; when more do, those (the untouched trend is the frames' median, and most of such a
    recording is one long press); the first `REFERENCE_FRAMES` when the recording holds no
    more (`every_frame`: every frame of the first `_SESSION_FRAMES` that looks untouched and
    lies within the noise of the first untouched run, `_within_noise_of`). A
    frame that looks damaged (`damaged_frames`: a frame of zeros, one at another gain) is never one
    of them, of 3 frames or more.

    Arguments:
        recording: The recording.
        reference_frame: A frame to use instead of the recording's reference.
        presses: The session's labelled presses, if any.
        every_frame: Without a reference, take every frame of the first ones (or of those
            before the first press) that looks untouched (a session; `_within_noise_of`), not
            just the first run.
        run_frames: The first run's frames are at most this many (`untouched_run`: a model
            saw a touch in the next); None: as the frames alone tell.

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
        if before.sum() > REFERENCE_FRAMES:
            # Presses not labelled (kept to test on) may come before the first labelled one.
            frames, times = recording.frames[before][:_SESSION_FRAMES], recording.times[before][:_SESSION_FRAMES]
            kept, _ = _leading_untouched(frames, times, every_frame, run_frames)
            if len(kept) == len(frames):
                return kept, f"the {len(frames)} frames before the first press"
            return kept, f"the {len(kept)} frames before the first press that look untouched (of {len(frames)})"
        if before.any():
            frames, times = recording.frames[before][:run_frames], recording.times[before][:run_frames]
            return _looking_untouched(frames, times, "before the first press")
        pressed = np.zeros(recording.n_frames, bool)
        for frames in presses.frames(recording.times):
            pressed[frames] = True
        if (~pressed).any():
            return _looking_untouched(recording.frames[~pressed], recording.times[~pressed], "outside the presses")
    if recording.n_frames > REFERENCE_FRAMES:
        session, session_times = recording.frames[:_SESSION_FRAMES], recording.times[:_SESSION_FRAMES]
        return _leading_untouched(session, session_times, every_frame, run_frames)
    whole = ~damaged_frames(recording.frames)
    if whole.all():
        return recording.frames, f"mean of the first {recording.n_frames} frames"
    kept = np.flatnonzero(whole)
    return recording.frames[kept], f"mean of frames {name_indices(kept)} (the others look damaged)"


def _leading_untouched(
    session: np.ndarray, session_times: np.ndarray, every_frame: bool, run_frames: int | None
) -> tuple[np.ndarray, str]:
    """`reference_frames` of a recording's leading frames `session` (T, M; more than
    `REFERENCE_FRAMES`) recorded at `session_times` (T,), without a reference: the first
    untouched run up to its first change (and of at most `run_frames` frames, or None), or
    with `every_frame` every frame that lies within its noise; and their description."""
    still = _untouched(session, session_times)
    # Only the first run, up to its first change (`_unchanged`): a light press can pass for
    # untouched frame by frame. A run shorter than `REFERENCE_FRAMES` is kept as it is: the
    # first frames beyond it had put a press into the reference of a session with one
    # untouched frame before its presses, and every untouched frame after them then read as
    # touched.
    first = int(np.argmax(still))  # `_untouched` passes some frames, the first ones when too few pass
    run = still[first:]
    end = first + (len(run) if run.all() else int(np.argmin(run)))
    unchanged, changed = _unchanged(session[first:end])
    end = first + (unchanged if run_frames is None else min(unchanged, run_frames))
    if every_frame:
        still[end : first + changed] = False  # the change's own frames: one may pass `_within_noise_of`
        leading = slice(first, end) if first <= _LEADING_DAMAGED else slice(0, first)
        kept = _within_noise_of(session, session_times, still, leading)
        return session[kept], f"the {int(kept.sum())} untouched frames of the first ones"
    if first == 0:
        return session[:end], f"mean of the first {end} frames (up to the first that looks touched)"
    if first <= _LEADING_DAMAGED:
        # A board's first frame or two after it connects can be damaged: left out.
        return session[first:end], (
            f"mean of frames {first} to {end - 1} (the first that look untouched; those before them look touched)"
        )
    # More leading frames than a glitch that look touched: the rest of the recording is most of
    # it one long press (the untouched trend `_untouched` starts from is the frames' median),
    # and the leading run is its reference.
    return session[:first], f"mean of the first {first} frames (up to the first of a long press)"


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
    Where the calibration knows no noise and the own frames are too few to measure it on, those
    up to the first the calibrated model sees touched (`untouched_run`).

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
        count = untouched_run(own, calibration) if len(own) < _NOISE_FRAMES else len(own)
        if count < len(own):
            seen = f"{source}: the first {count} of them, the calibrated model sees a touch in the next"
            return own[:count], seen, count
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
    quiet = ~damaged_frames(session) & (statistic(session, stored, 1.0 + 1.0 / count) <= DETECTION)
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


def untouched_run(frames: np.ndarray, calibration: SkinCalibration) -> int:
    """How many of a recording's first untouched frames `frames` (R, M; as recorded) come before
    the first the calibrated model sees touched: each frame's difference from the mean of
    those before it tested in the touch subspace against its own noise
    (`diffeit.touch.subspace_statistic` above `DETECTION`); R when the readings are too few to
    tell.

    For frames too few to measure the readings' noise on (fewer than `_NOISE_FRAMES`): in a
    session of one untouched frame, then presses one after another, every step between frames
    is a press, and the frames alone cannot tell faint presses from noise. On a benchmark skin
    the first run took 4 frames, 3 of them presses, and a calibration from them missed 18 of
    60 presses.

    Raises:
        ValueError: For frames that are not (R, M), or hold NaN or inf.
    """
    frames = _checked_frames(frames, name="frames")
    signed = calibration.signed(frames)
    for count in range(1, len(frames)):
        statistic = subspace_statistic((signed[count] - signed[:count].mean(axis=0))[None], calibration)
        if statistic is None:
            return len(frames)
        if statistic[0] > DETECTION:
            return count
    return len(frames)


def _looking_untouched(frames: np.ndarray, times: np.ndarray, where: str) -> tuple[np.ndarray, str]:
    """Those of `frames` (T, M), recorded at `times` (T,), that look untouched (`_untouched`,
    when there are more than `REFERENCE_FRAMES`; else those not damaged, `damaged_frames`), and
    their description, the frames `where` they are."""
    still = _untouched(frames, times) if len(frames) > REFERENCE_FRAMES else ~damaged_frames(frames)
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
    pass. A damaged frame (`damaged_frames`) is never untouched: with its gain taken out, a frame of
    zeros stood on the trend, and a reference holding one read no press of a session."""
    factor = 1.0 + 5.0 / math.sqrt(2.0 * frames.shape[1])
    design = _time_line(times)
    whole = ~damaged_frames(frames)

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


def _unchanged(run: np.ndarray) -> tuple[int, int]:
    """How many of the frames of a `run` (n, M) that each look untouched (`_untouched`) come
    before its first change (the first frame j from which a block of L = 2, 4, 8, ... frames
    differs from the frames before it beyond their noise), and the end of that change (the
    last end of a block from it that differs; both n: no change).

    `_untouched` tests one frame at a time against a noise it measures on the frames it passes:
    a faint press held several frames passes, and the noise it sets lets the next pass. On the
    calibration benchmark's skin pressed 1 s in every 2 (10 frames each), the run of untouched
    frames took in the first two presses (60 frames, 20 of them untouched): the reference held
    them, the noise it gave was too high, and 39 of 200 presses went unread. A held press
    differs from the frames before it in its mean, whose noise shrinks with L.

    The statistic of the block [j, j + L) is D = |b - g a|^2 / (1/L + 1/j), b its mean, a the
    mean of the frames before it, g the least-squares gain of a in b (a drift's common gain is
    not a change). Unchanged, D has the mean and spread of half a step's squared norm from one
    frame to the next, |f_t - f_(t-1)|^2 / 2 (both sum_m sigma_m^2 and 2 sum_m sigma_m^4): the
    steps inside the run measure them (their median and robust spread; a press's two steps are
    few among them): a change is D beyond `_change_limit`; a block of
    one frame is no change (an outlier among untouched frames). The run ends where the first
    block that changed splits most (the largest D of [k, its end) over its frames k: the
    change's likelihood), not at the block's start, which may lie before the change."""
    n = len(run)
    limit = _change_limit(run) if n >= 4 else None
    if limit is None:
        return n, n
    sums = np.concatenate([np.zeros((1, run.shape[1])), np.cumsum(run, axis=0)])

    def statistic(starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
        block = (sums[ends] - sums[starts]) / (ends - starts)[:, None]
        before = sums[starts] / starts[:, None]
        gain = np.sum(block * before, axis=1) / np.maximum(np.sum(before * before, axis=1), 1e-300)
        return np.sum((block - gain[:, None] * before) ** 2, axis=1) / (1.0 / (ends - starts) + 1.0 / starts)

    first = None  # the first block that changed: (its start, its end)
    for length in 2 ** np.arange(1, int(np.log2(n - 1)) + 1):
        starts = np.arange(1, n - length + 1)
        changed = starts[statistic(starts, starts + length) > limit]
        if len(changed) and (first is None or changed[0] < first[0]):
            first = int(changed[0]), int(changed[0] + length)
    if first is None:
        return n, n
    splits = np.arange(*first)
    split = int(splits[np.argmax(statistic(splits, np.full(len(splits), first[1])))])
    # The change lasts while the frames from it still differ: a faint press's last frames pass
    # one by one, and alone, no block test can tell them.
    ends = np.arange(first[1], n + 1)
    lasting = ends[statistic(np.full(len(ends), split), ends) > limit]
    return split, int(lasting.max()) if len(lasting) else first[1]


def _change_limit(frames: np.ndarray) -> float | None:
    """The statistic D of `_unchanged` beyond which a block of `frames` (n, M; n >= 2, in order,
    most of them untouched or held) changed: the median of half their steps' squared norms,
    |f_t - f_(t-1)|^2 / 2, plus `_CHANGE_SPREADS` of their robust spread, at least sqrt(2 / M)
    of that median (the spread of a sum of M squared normal terms, sqrt(2 sum sigma^4), is at
    least that share of its mean: of 9 steps between 10 untouched frames of 208 readings, the
    robust spread came out 0.035 of the median, and a block of them passed for a change); None
    when the steps are identical to round-off (no noise to tell a change by)."""
    half_steps = 0.5 * np.sum(np.diff(frames, axis=0) ** 2, axis=1)
    level = float(np.median(half_steps))
    spread = 1.4826 * float(np.median(np.abs(half_steps - level)))
    if spread <= _ROUND_OFF * level:
        return None
    return level + _CHANGE_SPREADS * max(spread, level * math.sqrt(2.0 / frames.shape[1]))


def _changed_blocks(residuals: np.ndarray, kept: np.ndarray, count: int, limit: float) -> np.ndarray:
    """(T,) bool: the frames of the blocks of L = 2, 4, 8, ... successive frames `kept` ((T,)
    bool) whose mean residual (`residuals` (T, M), each frame less the untouched trend, its
    gain taken out) has D = |mean|^2 / (1/L + 1/`count`) beyond `limit` (`_change_limit`; the
    trend estimated from `count` frames)."""
    sums = np.concatenate([np.zeros((1, residuals.shape[1])), np.cumsum(np.where(kept[:, None], residuals, 0.0), 0)])
    runs = np.concatenate([[0], np.cumsum(kept)])
    changed = np.zeros(len(kept), bool)
    length = 2
    while length <= len(kept):
        starts = np.arange(len(kept) - length + 1)
        whole = starts[runs[starts + length] - runs[starts] == length]
        mean = (sums[whole + length] - sums[whole]) / length
        for start in whole[np.sum(mean**2, axis=1) / (1.0 / length + 1.0 / count) > limit]:
            changed[start : start + length] = True
        length *= 2
    return changed


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
    drifts is followed outwards from the run. A faint press held several frames passes frame
    by frame, but not in its frames' mean: the blocks of kept frames outside the run whose mean
    differs from the trend (`_changed_blocks`, at the run's `_change_limit`) are left out (on
    that skin pressed 1 s in every 2, 10 frames each, 150 frames had been kept, 40 of them
    presses; 78 now, none of them)."""
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
    # A faint press held several frames passes frame by frame; its frames' mean does not.
    limit = _change_limit(frames[run])
    if limit is None:
        return kept
    gains = np.sum(frames * trend, axis=1) / np.maximum(np.sum(trend * trend, axis=1), 1e-300)
    changed = _changed_blocks(frames - gains[:, None] * trend, kept & ~run, int(kept.sum()), limit)
    return kept & ~changed if (kept & ~changed).sum() >= 3 else kept


def damaged_frames(frames: np.ndarray) -> np.ndarray:
    """The frames a board damaged, told from the frames about them.

    A frame is damaged when its change from the frames about it (`_change_from_about`)
    exceeds `_LARGEST_CHANGE` (half their size), or when its readings are theirs moved one or
    two places along (`_readings_moved`): a board's glitch (a frame of zeros, one at another
    gain, a stream that lost a reading), not a touch, and not a drift over so few frames.

    Arguments:
        frames: (T, M) frames in time order, as recorded.

    Returns:
        (T,) bool, True for a damaged frame; none of fewer than 3 frames (nothing to tell
        which is damaged), nor of frames that all look so.

    Raises:
        ValueError: For frames that are not (T, M).
    """
    frames = _checked_frames(frames, name="frames", finite=False)
    if len(frames) < 3:
        return np.zeros(len(frames), bool)
    about = _about(frames)
    damaged = (_change_from(frames, about) > _LARGEST_CHANGE) | _readings_moved(frames, about)
    return np.zeros(len(frames), bool) if damaged.all() else damaged


def held_lost_readings(recording: Recording) -> tuple[Recording, tuple[int, ...], np.ndarray, np.ndarray]:
    """A recording whose electrodes lost during it (`lost_electrodes`, against its reference or
    the median of its first 3 frames) hold their readings' values from before in every frame
    they are lost in, so that they move neither the choice of the reference frames nor the
    drift's gains, and no frame after they went is a glitch; and the lost electrodes, the
    frames they are lost in (T,) and the readings on them (M,), as `lost_electrodes`."""
    frames = recording.frames
    before = recording.reference if recording.reference is not None else np.median(frames[:3], axis=0)
    lost, lost_frames, lost_readings = lost_electrodes(frames - before, before, recording.protocol)
    if lost:
        held = np.where(lost_frames[:, None] & lost_readings, before, frames)
        recording = dataclasses.replace(recording, frames=held)
    return recording, lost, lost_frames, lost_readings


def lost_note(lost: tuple[int, ...], lost_frames: np.ndarray, during: str) -> str:
    """The electrodes `lost` during a `during` ("recording", "session") and the frames they are
    lost in, (T,) bool (`lost_electrodes`), in words: a warning's start."""
    return (
        f"electrode(s) {name_indices(np.array(lost))} lost during the {during} (half their readings changed by "
        f"more than half, in {int(lost_frames.sum())} frames from frame {int(np.argmax(lost_frames))} on)"
    )


def lost_electrodes(
    differences: np.ndarray, reference: np.ndarray, protocol: Protocol
) -> tuple[tuple[int, ...], np.ndarray, np.ndarray]:
    """The electrodes lost during a recording (an electrode come off the skin, a connector come
    loose): the readings on them broken from some frame on, the others not.

    A reading is broken in a frame when it changed by more than half of its reference (of half
    the RMS reference, where the reading is smaller), or is not finite. In each frame the
    electrodes half of whose readings (driven or measuring) are broken are found worst first, as
    the reference's broken electrodes are (a lost electrode's readings are its neighbours' too);
    they are lost there when a quarter of the readings or more are on none of them and at most
    a tenth of those are broken (else the frame is a glitch as a whole: `glitched_frames`), and
    lost from the recording when so in at least 3 frames (one frame so is a damaged frame).

    Arguments:
        differences: (T, M) the frames' differences from `reference`, in its unit.
        reference: (M,) the reference.
        protocol: The readings' protocol (M readings).

    Returns:
        The lost electrodes (indices, ascending); (T,) bool, the frames they are lost in; and
        (M,) bool, the readings on them (driven or measuring).

    Raises:
        ValueError: For arrays whose shapes do not fit together as above.
    """
    reference = np.asarray(reference, np.float64)
    differences = _checked_frames(differences, protocol.n_measurements, "differences", finite=False)
    if reference.shape != (protocol.n_measurements,):
        raise ValueError(
            f"lost_electrodes takes the differences' reference of shape ({protocol.n_measurements},), one value per "
            f"reading of the protocol; got {reference.shape}"
        )
    lost_in = _lost_in(differences, reference, protocol)
    lost = lost_in.sum(axis=0) >= _LOST_FRAMES
    return tuple(int(e) for e in np.flatnonzero(lost)), lost_in[:, lost].any(axis=1), _uses(protocol, lost)


def _lost_in(differences: np.ndarray, reference: np.ndarray, protocol: Protocol) -> np.ndarray:
    """(T, E) bool, the electrodes off in each frame of `differences` (T, M) from `reference`
    (M,) (`lost_electrodes`: half their readings broken, and the readings on none of them not)."""
    scale = np.maximum(np.abs(reference), _LARGEST_CHANGE * np.sqrt(np.mean(reference**2)))
    with np.errstate(invalid="ignore", over="ignore"):
        broken = ~np.isfinite(differences) | (np.abs(differences) > _LARGEST_CHANGE * scale)
    lost_in = np.zeros((len(differences), protocol.n_electrodes), bool)
    for frame in np.flatnonzero(broken.sum(axis=1) > 0):
        electrodes = _broken_electrodes(protocol, broken[frame])
        on_them = _uses(protocol, electrodes)
        # Lost electrodes leave most readings; the rest broken too is a glitch of the whole frame.
        few = np.sum(~on_them) >= _LEAST_LEFT * protocol.n_measurements
        if electrodes.any() and few and np.sum(broken[frame] & ~on_them) <= _STRAY_SHARE * np.sum(~on_them):
            lost_in[frame] = electrodes
    return lost_in


class LiveLost(eqx.Module):
    """A stream's lost electrodes (`diffeit live`): `lost_electrodes` for frames that come one
    batch at a time.

    In each frame the electrodes off in it (`lost_electrodes`' test of one frame against the
    reference) have their readings (driven or measuring) held; an electrode off in
    `_LOST_FRAMES` frames is lost, and its readings are held in every frame after, as
    `diffeit.reconstruct` masks them in every frame. A held reading takes the reference's value
    times the frame's common gain over the readings not held (its least-squares multiple of the
    reference there): it follows a drift as the others do, and reads no change of its own, so
    that neither a drift's gain nor a test of the frame for a touch reads the loss. An image
    should not take the held readings for data (no change there pulls the image towards none by
    the electrode, and a press elsewhere then rings beside it): `diffeit live` images from the
    readings not `on_lost` alone once an electrode is lost.

    Attributes:
        reference: (M,) the stream's reference, as recorded.
        protocol: Its readings' protocol.
        frames_off: (E,) how many frames each electrode has been off in.
        first_off: (E,) the first frame each electrode was off in (counted from 0 among the
            frames stepped), -1 for one never off.
        frames_seen: How many frames have been stepped.
    """

    reference: np.ndarray
    protocol: Protocol
    frames_off: np.ndarray
    first_off: np.ndarray
    frames_seen: int

    @classmethod
    def of(cls, reference: ArrayLike, protocol: Protocol) -> LiveLost:
        """No electrode lost yet, against `reference` (M,), as recorded, of `protocol`.

        Raises:
            ValueError: For a reference that is not M finite values.
        """
        reference = np.asarray(reference, np.float64)
        if reference.shape != (protocol.n_measurements,) or not np.all(np.isfinite(reference)):
            raise ValueError(
                f"the reference must be {protocol.n_measurements} finite readings, the protocol's; got shape "
                f"{reference.shape}"
            )
        return cls(reference, protocol, np.zeros(protocol.n_electrodes, int), np.full(protocol.n_electrodes, -1), 0)

    @property
    def lost(self) -> tuple[int, ...]:
        """The electrodes lost so far (ascending)."""
        return tuple(int(e) for e in np.flatnonzero(self.frames_off >= _LOST_FRAMES))

    @property
    def on_lost(self) -> np.ndarray:
        """(M,) bool, the readings on the electrodes lost so far (driven or measuring)."""
        return _uses(self.protocol, self.frames_off >= _LOST_FRAMES)

    def step(self, frames: ArrayLike) -> tuple[np.ndarray, np.ndarray, LiveLost]:
        """The frames (B, M), as recorded, with the readings on the electrodes off in them, or
        lost before, held (class docstring); (B, E) bool, the electrodes held in each; and the
        state after them.

        Raises:
            ValueError: For frames that are not (B, M) with the reference's M readings.
        """
        frames = np.atleast_2d(np.asarray(frames, np.float64))
        if frames.ndim != 2 or frames.shape[1] != len(self.reference):
            raise ValueError(f"frames must be (B, {len(self.reference)}), the reference's readings; got {frames.shape}")
        off_in = _lost_in(frames - self.reference, self.reference, self.protocol)
        # An electrode lost within the batch is held from its own frame on.
        off_so_far = self.frames_off + np.cumsum(off_in, axis=0)
        held_electrodes = off_in | (off_so_far >= _LOST_FRAMES)
        held = frames.copy()
        for k in np.flatnonzero(held_electrodes.any(axis=1)):
            on_them = _uses(self.protocol, held_electrodes[k])
            rest = self.reference[~on_them]
            gain = frames[k, ~on_them] @ rest / (rest @ rest) if rest @ rest > 0 else 1.0
            held[k, on_them] = gain * self.reference[on_them]
        first = (self.first_off < 0) & off_in.any(axis=0)
        first_off = np.where(first, self.frames_seen + np.argmax(off_in, axis=0), self.first_off)
        after = eqx.tree_at(
            lambda lost: (lost.frames_off, lost.first_off, lost.frames_seen),
            self,
            (off_so_far[-1], first_off, self.frames_seen + len(frames)),
        )
        return held, held_electrodes, after


def glitched_frames(
    differences: np.ndarray, reference: np.ndarray, frames: np.ndarray, recorded: np.ndarray
) -> np.ndarray:
    """The frames that are a board's glitch, not a touch, told against their reference.

    What `diffeit.reconstruct` lists as "damaged_frames" and `diffeit live` leaves unread: frames
    whose differences exceed half the reference's size (`_LARGEST_CHANGE`), or whose readings
    are the reference's moved one or two places along (`_readings_moved`).

    Arguments:
        differences: (T, M') the frames' differences from `reference`, in its unit.
        reference: (M') the reference they are differences from.
        frames: (T, M) the frames as recorded.
        recorded: (M,) the reference as recorded.

    Returns:
        (T,) bool, True for a glitch.

    Raises:
        ValueError: For arrays whose shapes do not fit together as above.
    """
    differences = _checked_frames(differences, len(np.atleast_1d(reference)), "differences", finite=False)
    frames = _checked_frames(frames, len(np.atleast_1d(recorded)), "frames", finite=False)
    if len(frames) != len(differences) or np.ndim(reference) != 1 or np.ndim(recorded) != 1:
        raise ValueError(
            f"glitched_frames takes (T, M') differences with their (M',) reference and (T, M) frames with their (M,) "
            f"recorded reference; got {differences.shape}, {np.shape(reference)}, {frames.shape}, {np.shape(recorded)}"
        )
    with np.errstate(over="ignore"):  # readings beyond float range: a norm of inf, large
        large = np.linalg.norm(differences, axis=1) > _LARGEST_CHANGE * np.linalg.norm(reference)
    moved = np.zeros_like(large)
    moved[~large] = _readings_moved(frames[~large], recorded)
    return large | moved


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
def drift_corrected(
    recording: Recording, reference_set: np.ndarray, readings: np.ndarray | None = None
) -> tuple[Recording, np.ndarray | None]:
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
    them). A touch held near the middle, or what a skin's memory leaves after a press, moves the
    common part and little else, and passes frame by frame; its pattern stands out of the noise
    of the mean of its frames between steps of the gain, where a drift leaves none
    (`_DriftReference.untouched_together`: on the slides benchmark, slow slides through the
    middle had been divided by their own gains, and 41 to 72 of their frames missed); when
    every run shows a pattern, it is the reference's, and the frames untouched frame by frame
    are kept. The gains are the running median of the c_t of the untouched frames left over
    `_DRIFT_WINDOW` of them, interpolated in time to the others (the nearest one's beyond
    them): a touch moves the readings' common part too, and one that moves little else passes
    for untouched (its own c_t took its touch out of 6 of 60 presses' frames on a benchmark
    skin, which were then missed). Touched frames before the first frame untouched frame by
    frame, or after the last, and more than half `_DRIFT_WINDOW` frame steps from it (presses
    one after another, which the untouched frames' gains no longer follow), take their own c_t
    instead, less a press's typical part of it (the median, over the touched frames near
    untouched ones, of their c_t less the untouched frames' gain there), in a running median
    over `_DRIFT_WINDOW` of them (on a benchmark skin whose gain grew 5% under 60 presses one
    after another, the test presses were read 19.5 mm off with the nearest untouched gain held,
    4.6 mm so). Between untouched frames the gains are interpolated instead: a press held there
    is one press, whose own gain a running median follows (on designed memory sessions, 11 of
    12 took presses held 1 to 4 s, each its own depth, for a drift of 0.8% to 1.8%, and divided
    them by it). Gains are taken out only when the untouched frames' c_t spread beyond
    the reference frames' own jitter from one frame to the next, or the far touched frames'
    gains beyond the uncertainty of their running median and typical part (F tests at chance
    `_DRIFT_CHANCE`): estimated from the frames, each gain is as noisy as the readings' common
    part, and without drift dividing by them only adds that noise.

    Arguments:
        recording: The recording (frames as recorded).
        reference_set: (N, M) the frames its reference is the mean of (`reference_frames`).
        readings: (M,) bool, the readings the gains are estimated from (None: every one; a lost
            electrode's are left out, `lost_electrodes`); every reading is divided by them.

    Returns:
        The recording, its frames divided by the gains, and the gains; or the recording and
        None (too few reference frames, or no drift beyond their jitter).

    Raises:
        ValueError: For reference frames that are not (N, M) finite readings of the
            recording's M, or, with a drift to take out, times that go backwards.
    """
    reference_set = _checked_frames(reference_set, recording.frames.shape[1])
    readings = np.ones(reference_set.shape[1], bool) if readings is None else np.asarray(readings, bool)
    if readings.shape != reference_set.shape[1:] or not readings.any():
        raise ValueError(f"readings must be a ({reference_set.shape[1]},) mask keeping a reading; got {readings.shape}")
    drift = _DriftReference.of(reference_set[:, readings])
    if drift is None or recording.n_frames == 0:
        return recording, None
    frames = recording.frames[:, readings]
    common = drift.gains(frames)
    ordered = not np.any(np.diff(recording.times) < 0)
    still = drift.untouched(frames, common)
    rests = still
    if ordered:
        still = _rests_not_presses(recording.times, common, still, drift.jitter)
        rests = drift.untouched_together(frames, common, still)
        # A pattern in every run is the reference's own (one with presses in it, taken from a
        # session of presses one after another): the frames untouched frame by frame are all
        # there is to follow (without them, a benchmark skin's session missed 15 of 60 presses, 10 with).
        rests = rests if rests.any() else still
    gains = np.ones_like(common)
    if rests.any() and ordered:
        # A running median over the untouched frames: a touch that moves the readings' common
        # part alone passes for untouched, and its own gain would take the touch out of its frame.
        smooth = scipy.ndimage.median_filter(common[rests], size=_DRIFT_WINDOW, mode="nearest")
        gains = np.interp(recording.times, recording.times[rests], smooth)
    # No drift beyond the reference frames' own jitter, no correction: dividing by noisy gains
    # cost a benchmark skin's nominal pipeline 4 of the 60 presses it had read.
    drifts = rests.any() and _departs(common[rests] - 1.0, drift.jitter, 1, drift.frames - 1)
    far = _beyond_untouched(recording.times, still) if ordered and still.any() else np.zeros_like(still)
    near = ~still & ~far
    # Touches between untouched frames take the gains interpolated across them: a drift is slow,
    # and a press held there is one press, whose own gain a running median would follow.
    far &= _outside_untouched(still)
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
    edges = _runs(still)
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


def _runs(marked: np.ndarray) -> np.ndarray:
    """(R, 2) the first frame and the end (exclusive) of each run of frames `marked` (T,) bool."""
    return np.flatnonzero(np.diff(np.r_[0, marked.astype(int), 0])).reshape(-1, 2)


def _gain_steps(
    gains: np.ndarray, jitter: float, first: int, last: int, step: float = _GAIN_STEP
) -> list[tuple[int, int]]:
    """The frames `first` to `last` (exclusive) cut where their `gains` (T,) step: before each
    frame where the mean gain of the up to `_DRIFT_WINDOW` // 2 frames from it less that of as
    many before it is largest within as many frames either side and exceeds `step` of
    its standard error (`jitter` the variance of one gain), the run's steady drift taken out (the
    median slope of these differences: a touch steps the gain at a few frames alone). A held
    touch steps the gain at its start and its end; a drift moves it slowly, a fraction of a
    step over so few frames, yet a steep one (3% over 14 s) cut a held touch in two without it,
    and a cut too many leaves pieces too short to show a touch's pattern."""
    width = max(_DRIFT_WINDOW // 2, 1)
    sums = np.r_[0.0, np.cumsum(gains[first:last])]
    count = last - first
    at = np.arange(1, count)
    before, after = np.minimum(at, width), np.minimum(count - at, width)
    difference = (sums[at + after] - sums[at]) / after - (sums[at] - sums[at - before]) / before
    # A steady drift's slope s moves the means' difference by s (before + after) / 2.
    span = 0.5 * (before + after)
    difference -= np.median(difference / span) * span if len(at) else 0.0
    size = np.abs(difference) / np.sqrt(jitter * (1 / before + 1 / after))
    peaks = [k for k in range(len(at)) if size[k] > step and size[k] == size[max(k - width, 0) : k + width + 1].max()]
    cuts = [first, *(first + int(at[k]) for k in peaks), last]
    return list(itertools.pairwise(cuts))


def _trend_at(times: np.ndarray, gains: np.ndarray, time: float) -> float:
    """The gain at `time` of gains (n,) at `times` (n,): their median moved to `time` along their
    Theil-Sen slope (`_slope`), robust to a touch among them that passed for untouched; a median
    alone lags a steady drift by half their span."""
    return float(np.median(gains)) + _slope(times, gains) * (time - float(np.median(times)))


def _slope(times: np.ndarray, gains: np.ndarray) -> float:
    """The Theil-Sen slope, 1/s, of gains (n,) at `times` (n,): the median of the slopes between
    pairs of them (0 for none)."""
    first, second = np.triu_indices(len(gains), k=1)
    apart = times[second] - times[first]
    slopes = (gains[second] - gains[first])[apart != 0] / apart[apart != 0]
    return float(np.median(slopes)) if len(slopes) else 0.0


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


def _outside_untouched(still: np.ndarray) -> np.ndarray:
    """(T,) the frames before the first frame `still` (T,) bool and after the last."""
    marked = np.flatnonzero(still)
    frame = np.arange(len(still))
    return (frame < marked[0]) | (frame > marked[-1]) if len(marked) else np.ones_like(still)


def _time_to_nearest(times: np.ndarray, marked: np.ndarray) -> np.ndarray:
    """(T,) the time, s, from each of `times` (T,), in order, to the nearest frame `marked`
    ((T,) bool, some true)."""
    at = times[marked]
    after = np.clip(np.searchsorted(at, times), 1, len(at)) - 1
    return np.minimum(np.abs(times - at[after]), np.abs(times - at[np.minimum(after + 1, len(at) - 1)]))


def _checked_frames(
    frames: ArrayLike, readings: int | None = None, name: str = "reference_set", finite: bool = True
) -> np.ndarray:
    """`frames` as (N, `readings`) float64 frames (None: any number of readings), finite where
    `finite` (a board's glitch may hold infinities its test must see), or a ValueError naming
    the problem by `name`."""
    frames = np.asarray(frames, np.float64)
    if frames.ndim != 2 or readings not in (None, frames.shape[1]):
        expected = "M" if readings is None else readings
        raise ValueError(f"{name} must be (N, {expected}) frames of the recording's readings; got shape {frames.shape}")
    if finite and not np.all(np.isfinite(frames)):
        raise ValueError(f"{name} holds non-finite values (NaN or inf)")
    return frames


class _DriftReference(NamedTuple):
    """What tells a frame's common gain against a reference (`drift_corrected`, `LiveDrift`):
    the reference (M,), the mean of `frames` frames, their noise (M,), the readings whose noise
    is above round-off (`kept`) and their weights (the reference over the noise squared), and
    `jitter`, the variance of one frame's gain (a sixth of the mean square of the successive
    reference frames' gains' second differences: blind to a steady drift among the reference
    frames themselves), each frame's gain taken against the reference and weights of the others."""

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
        steadied = reference_set / np.where(own > 0, own, 1.0)[:, None]
        noise = steadied.std(axis=0, ddof=1)
        # A spread at round-off (a noise-free simulation's) is no noise: gains tested against it
        # found a drift of 0% and divided the frames by it.
        kept = noise > _ROUND_OFF * np.abs(reference)
        if not kept.any():
            return None
        # Against weights from the frames themselves, a frame weighs most the readings whose
        # noise it happened to make small, and its gain looks steadier than a later frame's:
        # with 6 reference frames of 192 readings, later frames' gains spread 1.4 times as far
        # as the reference frames' on the median, 3.4 times at the 90th percentile (0.99 and
        # 1.6 times, each left out of its own reference, their jitter from second differences).
        # For each frame, the other frames' mean and (their own gains taken out) variance, (N, M').
        count = len(reference_set)
        others = (reference_set.sum(axis=0) - reference_set)[:, kept] / (count - 1)
        centred = (steadied - steadied.mean(axis=0))[:, kept]
        variance = np.sum(centred**2, axis=0) - centred**2 - (centred.sum(axis=0) - centred) ** 2 / (count - 1)
        variance /= count - 2
        # A reading that varied in one frame alone takes, left out of the others, the noise of all.
        variance = np.where(variance > (_ROUND_OFF * others) ** 2, variance, noise[kept] ** 2)
        gains = np.sum(reference_set[:, kept] * others / variance, axis=1) / np.sum(others**2 / variance, axis=1)
        # Second differences: a steady drift among the reference frames cancels (in the first,
        # a drift of 9 times the noise a frame passed for jitter, and a stream took it for none).
        jitter = float(np.mean(np.diff(gains, 2) ** 2) / 6)
        return cls(reference, noise, len(reference_set), kept, reference[kept] / noise[kept] ** 2, jitter)

    def gains(self, frames: np.ndarray) -> np.ndarray:
        """(T,) each frame's least-squares multiple of the reference, the readings weighed by their noise."""
        return frames[:, self.kept] @ self.weighed / (self.reference[self.kept] @ self.weighed)

    def untouched_together(self, frames: np.ndarray, gains: np.ndarray, still: np.ndarray) -> np.ndarray:
        """(T,) the frames `still` (T,) bool, in order, less those a touch holds together. Each
        run of them is cut where its gains step (`_gain_steps`), and a piece of two frames or
        more is left out where the mean of its frames, each less its gain times the reference,
        stands out of the noise (z > `_DRIFT_DETECTION`, its variance 1/n + 1/N of the readings'
        for n frames against N reference frames). A touch near the middle moves the readings'
        common gain and little else, and frame by frame it passes for untouched; held, its
        pattern stands out of the noise of their mean, as what a skin's memory leaves does,
        where a drift's gain leaves none."""
        kept = still.copy()
        edges = _runs(still)
        for first, last in edges[edges[:, 1] - edges[:, 0] > 1]:
            for start, end in _gain_steps(gains, self.jitter, first, last):
                if end - start < 2:
                    continue
                left = np.mean(frames[start:end] - gains[start:end, None] * self.reference, axis=0)
                kept[start:end] = self.pattern(left, end - start) <= _DRIFT_DETECTION
        return kept

    def pattern(self, left: np.ndarray, count: int) -> float:
        """How far `left` (M,), the mean of `count` frames each less its gain times the
        reference, stands out of the noise: `_statistic` of it, its variance 1/n + 1/N of the
        readings' for n frames against N reference frames (a touch's pattern, where a drift's
        gain leaves none)."""
        return float(_statistic(left[None], self.noise, self.frames, 1 / count + 1 / self.frames)[0])

    def untouched(self, frames: np.ndarray, gains: np.ndarray) -> np.ndarray:
        """(T,) whether frame - gain * reference stands within the reference frames' noise
        (`diffeit.touch`'s test of differences against it, at z = `_DRIFT_DETECTION`)."""
        left = frames - gains[:, None] * self.reference
        return ~_noise_test(left, self.noise, self.frames, self.frames, _DRIFT_DETECTION)


class _Piece(NamedTuple):
    """A stream's untouched frames not yet joined to its drift's gains (`LiveDrift`): the
    latest `_LIVE_SLOPE` frames' `times` (n,) s and `gains` (n,), their `count`, the sums of
    all their times and gains, the latest `_LIVE_PIECE` frames each less its gain times the
    reference (`left`, (k, M)), and whether their mean shows a touch's pattern (`touched`)."""

    times: np.ndarray
    gains: np.ndarray
    count: int
    time_sum: float
    gain_sum: float
    left: np.ndarray
    touched: bool

    @classmethod
    def of(cls, time: float, gain: float, left: np.ndarray) -> _Piece:
        """A piece of one frame at `time` of `gain`, `left` (M,) the frame less its gain times the reference."""
        return cls(np.array([time]), np.array([gain]), 1, time, gain, left[None], False)

    def joined(self, time: float, gain: float, left: np.ndarray) -> _Piece:
        """The piece with a frame at `time` of `gain`, `left` (M,) as `of`'s."""
        return self._replace(
            times=np.append(self.times, time)[-_LIVE_SLOPE:],
            gains=np.append(self.gains, gain)[-_LIVE_SLOPE:],
            count=self.count + 1,
            time_sum=self.time_sum + time,
            gain_sum=self.gain_sum + gain,
            left=np.concatenate([self.left, left[None]])[-_LIVE_PIECE:],
        )

    def split(self, first: int) -> tuple[_Piece, _Piece]:
        """The piece before its frame `first` and from it on, counted among its latest
        `_LIVE_SLOPE` (the latter within its latest `_LIVE_PIECE`); neither `touched` yet."""
        times, gains = self.times[first:], self.gains[first:]
        kept = len(gains)
        after = _Piece(times, gains, kept, float(times.sum()), float(gains.sum()), self.left[-kept:], False)
        before = _Piece(
            self.times[:first],
            self.gains[:first],
            self.count - kept,
            self.time_sum - after.time_sum,
            self.gain_sum - after.gain_sum,
            self.left[:-kept],
            False,
        )
        return before, after


class _Stream(NamedTuple):
    """`LiveDrift`'s state while it steps through a batch (its fields, and the rules of its
    docstring): a NamedTuple, cheap to replace frame by frame."""

    reference: _DriftReference
    times: np.ndarray
    recent: np.ndarray
    piece: _Piece | None

    def after(self, time: float, gain: float, left: np.ndarray) -> _Stream:
        """The stream after an untouched frame at `time` of `gain`, `left` (M,) the frame less
        its gain times the reference (`LiveDrift`'s pieces)."""
        piece = self.piece
        if piece is None:
            return self._settling(_Piece.of(time, gain, left))
        # The frame continues the piece when within `_GAIN_STEP` standard errors of its trend, or
        # when the piece is neither settled nor a touch (a frame of noise, or a level the gains'
        # trend lost: closed, it would be lost, and the gains would follow the trend they lost).
        stepped = self._off(piece.times, piece.gains, time, gain, least=_LIVE_TREND) > _GAIN_STEP
        settled = stepped and self._settled(piece)
        if not stepped or not (piece.touched or settled):
            return self._settling(self._tested(piece.joined(time, gain, left)))
        # Closed by a frame that steps off it, the piece joins the gains when settled, its last
        # frame too: a rest frame and a touch's first, closed by the touch's second, had settled
        # on their mean, and the touch's frame tilted the trend's slope.
        settled = settled and self._off(self.times, self.recent, piece.times[-1], piece.gains[-1]) <= _GAIN_STEP
        return (self._joined(piece) if settled else self)._settling(_Piece.of(time, gain, left))

    def _settling(self, piece: _Piece) -> _Stream:
        """The stream with `piece` open, joined to the gains when it is settled or of
        `_LIVE_PIECE` frames with no touch's pattern."""
        if len(self.recent) < _LIVE_TREND or self.reference.frames < _LIVE_REFERENCE:
            return self._joined(piece)
        cuts = (
            []
            if piece.touched
            else _gain_steps(piece.gains, self.reference.jitter, 0, len(piece.gains), _DRIFT_DETECTION)
        )
        if len(cuts) > 1:
            # Two levels, not one (a touch that began on frames the trend had lost, its pattern
            # diluted by theirs, and the mean between them settled). The piece goes on from the
            # last step; the frames before it join the gains when settled, or when, with no
            # touch's pattern, they lie nearer the trend than the frames after (a level the trend
            # lost, then a touch); else they are left out.
            before, after = (self._tested(part) for part in piece.split(cuts[-1][0]))
            trend = self._trend(self.times, self.recent, after.time_sum / after.count)[0]
            nearer = abs(before.gain_sum / before.count - trend) < abs(after.gain_sum / after.count - trend)
            lost = before.count >= _LIVE_SETTLED and not before.touched and nearer
            return (self._joined(before) if self._settled(before) or lost else self)._settling(after)
        if piece.count >= _LIVE_SETTLED and self._settled(piece):
            return self._joined(piece)
        if piece.count >= _LIVE_PIECE and not piece.touched:
            # A new level: the gains before it would tilt the trend's slope across the step.
            return self._joined(piece, anew=True)
        return self._replace(piece=piece)

    def _joined(self, piece: _Piece, anew: bool = False) -> _Stream:
        """The stream with `piece`'s frames joined to the gains (`anew`: in their place), and no piece open."""
        times = piece.times if anew else np.append(self.times, piece.times)[-_LIVE_SLOPE:]
        recent = piece.gains if anew else np.append(self.recent, piece.gains)[-_LIVE_SLOPE:]
        return self._replace(times=times, recent=recent, piece=None)

    def _settled(self, piece: _Piece) -> bool:
        """Whether `piece` shows no touch's pattern and its mean gain lies within `_GAIN_STEP`
        standard errors of the gains' trend."""
        count = piece.count
        return (
            not piece.touched
            and self._off(self.times, self.recent, piece.time_sum / count, piece.gain_sum / count, count) <= _GAIN_STEP
        )

    def _tested(self, piece: _Piece) -> _Piece:
        """The piece, `touched` once the mean of its latest `_LIVE_PIECE` frames, each less its
        gain times the reference, stands out of the noise (`_DriftReference.pattern` above
        `_DRIFT_DETECTION`), and until its z falls to `_LIVE_GONE`: a touch held, or what a
        skin's memory leaves, until it is gone."""
        if len(piece.left) < 2:
            return piece
        statistic = self.reference.pattern(piece.left.mean(axis=0), len(piece.left))
        return piece._replace(touched=statistic > (_LIVE_GONE if piece.touched else _DRIFT_DETECTION))

    def _off(
        self,
        times: np.ndarray,
        gains: np.ndarray,
        time: float | np.ndarray,
        gain: float | np.ndarray,
        frames: int = 1,
        least: int = 2,
    ) -> float | np.ndarray:
        """How many standard errors `gain`, the mean gain of `frames` frames whose mean time is
        `time` (or such gains at such times, arrays), stands off the trend of `gains` at `times`
        (`_trend`): its uncertainty and the frames' own jitter."""
        trend, variance = self._trend(times, gains, time, least)
        return np.abs(gain - trend) / np.sqrt(self.reference.jitter * (1 / frames + variance))

    def _trend(
        self, times: np.ndarray, gains: np.ndarray, time: float | np.ndarray, least: int = 2
    ) -> tuple[float | np.ndarray, float | np.ndarray]:
        """The trend at `time` (or times) of `gains` (n,) at `times` (n,), joined or a piece's, and its
        variance over a gain's jitter: the median of the latest `_DRIFT_WINDOW` moved to `time`
        along the Theil-Sen slope of all (`_slope`), where it stands beyond `_LIVE_DRIFT_ERRORS`
        of its standard errors of 0 (a slope of noise, carried across a touch, moved a steady
        skin's gains, and those of the first frames after the reference went 0.3% astray along
        a slope of three), its variance a median's, pi / 2 / n, and the slope's as a
        least-squares slope's. The reference's gain, 1, before any gain (its variance 1 / N).
        Of fewer than `least` gains, their mean: the joined gains take a slope from two on (a
        steep drift just after the reference), a piece from `_LIVE_TREND` (a slope between a
        rest and a touch's first frame would carry any frame)."""
        if not len(gains):
            return 1.0, 1 / self.reference.frames
        if len(gains) < least:
            return float(np.mean(gains)), 1 / len(gains)
        latest = min(len(gains), _DRIFT_WINDOW)
        spread = float(np.sum((times - times.mean()) ** 2))
        at = float(np.median(times[-latest:]))
        moved = (time - at) ** 2 / spread if spread > 0 else 0.0
        slope = _slope(times, gains) if spread > 0 else 0.0
        if abs(slope) <= _LIVE_DRIFT_ERRORS * math.sqrt(self.reference.jitter / spread if spread > 0 else 0.0):
            slope = 0.0
        return float(np.median(gains[-latest:])) + slope * (time - at), np.pi / 2 / latest + moved

    def gain_at(self, time: float) -> float:
        """The gain at `time` from the joined untouched frames' gains (`LiveDrift`)."""
        if not len(self.recent):
            return 1.0
        trend = self._trend(self.times, self.recent, time)[0]
        latest = self.recent[-_DRIFT_WINDOW:]
        # The trend is the latest gains' median where `_trend` finds no slope beyond its errors.
        level = float(np.median(latest))
        still = trend == level and abs(level - 1.0) <= _LIVE_DRIFT_ERRORS * 1.25 * math.sqrt(
            self.reference.jitter / len(latest)
        )
        return 1.0 if still else trend


class LiveDrift(eqx.Module):
    """A stream's drift, followed frame by frame (`diffeit live`): `drift_corrected` for frames
    that come one batch at a time, the future unknown.

    Each frame's common gain against the reference and its test for a touch are
    `drift_corrected`'s. The gain a frame is divided by is the trend of the untouched frames'
    gains joined so far (`_trend`): the median of the latest `_DRIFT_WINDOW`, moved to the
    frame's time along the Theil-Sen slope of the latest `_LIVE_SLOPE` where that slope stands
    beyond `_LIVE_DRIFT_ERRORS` of its standard errors (a median alone lags a steady drift by
    half its window, and the frames then looked touched). It is taken as 1 while no slope does
    and the median stands within `_LIVE_DRIFT_ERRORS` of its standard errors of 1 (1.25
    sqrt(jitter / n) for n gains), so that a steady skin's frames are not divided by noise. A
    frame that looks touched gets the trend at its time too.

    A touch held near the middle moves the readings' common gain and little else, and frame by
    frame passes for untouched: when each such frame joined the gains as it came, the stream
    divided the touch out from about its fourth frame (29 to 93 of a slow slide's frames on
    the slides benchmark's skins). So untouched frames join the gains in pieces, a few frames late:

    - A frame continues the open piece when it lies within `_GAIN_STEP` standard errors of the
      piece's trend (that trend's uncertainty and the frame's own jitter; a piece of fewer than
      `_LIVE_TREND` frames takes no slope), or when the piece has neither settled nor shown a
      touch (closed, a level the gains' trend lost would be dropped, and the gains would keep
      the trend they lost). Else the piece closes, and joins the gains when settled, its last
      frame too.
    - A piece has settled when its mean gain lies within `_GAIN_STEP` standard errors of the
      gains' trend and it shows no touch's pattern: the mean of its latest `_LIVE_PIECE` frames,
      each less its gain times the reference, stands within the noise (z <= `_DRIFT_DETECTION`,
      as `drift_corrected` tells a touch held; once above, until it falls to `_LIVE_GONE`). It
      joins once it holds `_LIVE_SETTLED` frames.
    - A piece whose gains step (`_gain_steps` at `_DRIFT_DETECTION` standard errors) is two: the
      frames before the last step join when settled, or when they show no pattern and lie
      nearer the trend than the frames after (a level the trend lost, then a touch); the piece
      goes on from the step.
    - A piece of `_LIVE_PIECE` frames with no touch's pattern is the gains' new level, in their
      place (a gain that stepped: a board's, or a drift the trend lost under a long touch).

    Any other piece is a touch, or frames of noise, and never joins. While the gains hold fewer
    than `_LIVE_TREND` frames, every untouched frame joins them at once: there is no trend to
    stand off; and so it does with fewer than `_LIVE_REFERENCE` reference frames, whose own
    noise hides a faint touch's pattern (with 6, a faint central touch's frames were held back
    in 27% of cases, and one stream of 16 ran 2.8% astray). Under a touch, the drift is
    followed only along the slope the gains had before it: after a touch held 15 s under a
    drift of 1% over 22 s, the first rest frames' gains were up to 1% off.

    Attributes:
        reference: What tells a frame's gain and touch (the reference frames'; `of`).
        times: (n,) the latest joined untouched frames' times, s, n at most `_LIVE_SLOPE`.
        recent: (n,) their gains.
        piece: The untouched frames since, not yet joined, or None.
    """

    reference: _DriftReference
    times: np.ndarray
    recent: np.ndarray
    piece: _Piece | None = None

    @classmethod
    def of(cls, reference_set: ArrayLike) -> LiveDrift | None:
        """The drift of a stream whose reference is the mean of `reference_set` (N, M), as
        streamed; None for fewer than 6 frames (no noise to tell untouched frames by).

        Raises:
            ValueError: For reference frames that are not (N, M) finite values.
        """
        reference = _DriftReference.of(_checked_frames(reference_set))
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
        stream, gains = _Stream(self.reference, self.times, self.recent, self.piece), np.ones(len(frames))
        for t in range(len(frames)):
            if still[t]:
                stream = stream.after(times[t], common[t], frames[t] - common[t] * self.reference.reference)
            gains[t] = stream.gain_at(times[t])
        drift = dataclasses.replace(self, times=stream.times, recent=stream.recent, piece=stream.piece)
        return frames / gains[:, None], gains, drift


def drift_note(gains: np.ndarray) -> str:
    """The warning that a recording's frames were divided by their drifting common gains.

    Arguments:
        gains: (T,) each frame's common gain, as `drift_corrected` returns them.

    Returns:
        The sentence, with the gains' range, that `calibrate` and `diffeit.reconstruct` warn.

    Raises:
        ValueError: For gains that are empty or not finite.
    """
    gains = np.asarray(gains, np.float64)
    if gains.size == 0:
        raise ValueError("drift_note takes the frames' common gains; got none")
    if not np.all(np.isfinite(gains)):
        raise ValueError("drift_note takes the frames' common gains; some are not finite (NaN or inf)")
    low, high = float(np.min(gains)), float(np.max(gains))
    return (
        f"the frames' common gain drifts over the recording, from {low:.4g} to {high:.4g} times the reference's "
        f"({100 * (high - low):.2g}%): each frame is divided by it (diffeit.calibration.drift_corrected)"
    )
