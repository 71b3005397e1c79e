"""Drive and measurement protocols: which currents are applied and which voltages are read.

Builders: `adjacent`, `skip`, `opposite` (EIDORS's conventions), and `Protocol(drive, measure)`
for anything else (multi-electrode and trigonometric current patterns, readings against a
common reference electrode). Conversions between the layouts other tools and hardware use:
`Conversion` / `convert` between any two protocols, `to_full_layout` / `from_full_layout` for
the 16 x 16 layout with zeros, and `from_pyeit` for pyEIT's protocols.
"""

from __future__ import annotations

import functools
import operator
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, TypeAlias

import jax
import jax.numpy as jnp
import numpy as np
from numpy.typing import ArrayLike

from ._arrays import StaticData, fingerprint, readonly
from ._messages import name_indices


@dataclass(init=False, eq=False)
class Protocol(StaticData):
    """Current patterns and the voltage readings taken under each.

    Any current pattern is allowed: a pair of electrodes, current into one electrode and out of
    several, trigonometric patterns; `adjacent`, `skip` and `opposite` build the usual ones. A
    reading with weights m is `sum_l m_l U_l`, U the electrode potentials (volts):
    `U_m - U_(m+1)` has weights +1 at m and -1 at m+1, a reading against a common reference
    electrode r has +1 at m and -1 at r. Measurements are ordered drive by drive, then in the
    given order within a drive, and stored flat. A protocol is static data for JAX (a pytree
    without leaves); protocols compare and hash by content.

    Arguments:
        drive: (n_drives, L) current pattern per drive, in units of the model's drive current:
            entry l is the current entering the sheet through electrode l (positive in). Each
            row must sum to zero and must not be all zero.
        measure: The readings of each drive, weights per electrode: an (n_drives, M, L) array
            or a sequence of n_drives arrays of shape (M_k, L). A row must not be all zero.

    Attributes:
        drive: (n_drives, L) the current patterns, read-only.
        measure: (n_measurements, L) the weights of every reading, drive by drive, read-only.
        drive_index: (n_measurements,) the drive each reading belongs to.
        measure_patterns: (P, L) the distinct rows of `measure`.
        pattern_index: (n_measurements,) the row of `measure_patterns` each reading uses.
        fingerprint: A digest of the content, for hashing and comparing.

    Raises:
        ValueError: Naming the offending rows, for a drive that is not (n_drives, L) with
            L >= 2, non-finite values, an all-zero drive or reading, a drive that does not sum
            to zero, readings for another number of drives or electrodes, or no readings at
            all.
    """

    drive: np.ndarray
    measure: np.ndarray
    drive_index: np.ndarray
    measure_patterns: np.ndarray = field(repr=False)
    pattern_index: np.ndarray = field(repr=False)
    fingerprint: bytes = field(repr=False)

    def __init__(self, drive: np.ndarray, measure: np.ndarray | Sequence[np.ndarray]) -> None:
        drive = np.array(drive, dtype=np.float64)
        if drive.ndim != 2 or drive.shape[0] == 0:
            raise ValueError(f"drive must have shape (n_drives, n_electrodes); got {drive.shape}")
        n_drives, n_electrodes = drive.shape
        if n_electrodes < 2:
            raise ValueError(f"a protocol needs at least 2 electrodes; drive addresses {n_electrodes}")
        if not np.all(np.isfinite(drive)):
            raise ValueError("drive patterns hold non-finite values")
        silent = np.flatnonzero(~np.any(drive, axis=1))
        if len(silent):
            raise ValueError(f"drive patterns {name_indices(silent)} are all zero: every drive must apply current")
        unbalanced = np.flatnonzero(np.abs(drive.sum(axis=1)) > 1e-12 * np.abs(drive).sum(axis=1).clip(1))
        if len(unbalanced):
            raise ValueError(f"drive patterns {name_indices(unbalanced)} do not sum to zero: current must be conserved")
        per_drive = [np.array(m, dtype=np.float64) for m in measure]
        if len(per_drive) != n_drives:
            raise ValueError(f"measure gives readings for {len(per_drive)} drives; drive has {n_drives}")
        for k, m in enumerate(per_drive):
            if m.ndim != 2 or m.shape[1] != n_electrodes:
                raise ValueError(
                    f"measurements of drive {k} must have shape (M, {n_electrodes}), one weight per electrode "
                    f"the drive addresses; got {m.shape}"
                )
            if not np.all(np.isfinite(m)):
                raise ValueError(f"measurements of drive {k} hold non-finite values")
            empty = np.flatnonzero(~np.any(m, axis=1))
            if len(empty):
                raise ValueError(f"measurements {name_indices(empty)} of drive {k} are all zero: they read nothing")
        flat = np.concatenate(per_drive) + 0.0  # + 0.0 turns -0.0 into 0.0 for np.unique
        if len(flat) == 0:
            raise ValueError("the protocol has no measurements")
        drive_index = np.repeat(np.arange(n_drives), [len(m) for m in per_drive])
        patterns, pattern_index = np.unique(flat, axis=0, return_inverse=True)
        self.drive = readonly(drive)
        self.measure = readonly(flat)
        self.drive_index = readonly(drive_index)
        self.measure_patterns = readonly(patterns)
        self.pattern_index = readonly(pattern_index.ravel())
        self.fingerprint = fingerprint(drive, flat, drive_index)

    @property
    def n_electrodes(self) -> int:
        """L, the number of electrodes the protocol addresses."""
        return self.drive.shape[1]

    @property
    def n_drives(self) -> int:
        """The number of drives (current patterns)."""
        return self.drive.shape[0]

    @property
    def n_measurements(self) -> int:
        """M, the number of readings over all drives: the length of a frame."""
        return self.measure.shape[0]

    def __repr__(self) -> str:
        return (
            f"Protocol(n_electrodes={self.n_electrodes}, n_drives={self.n_drives}, "
            f"n_measurements={self.n_measurements})"
        )

    def select(self, readings: ArrayLike) -> Protocol:
        """The protocol of some of this protocol's readings: masking broken channels.

        The readings kept stay in this protocol's order. Drives keep their index; a drive left
        without readings keeps its pattern and reads nothing.

        Arguments:
            readings: The readings to keep: a boolean mask (n_measurements,) or indices.

        Returns:
            The new `Protocol`.

        Raises:
            ValueError: For a mask of another shape, indices outside 0..n_measurements-1, or
                no reading kept.
        """
        keep = np.zeros(self.n_measurements, dtype=bool)
        chosen = np.asarray(readings)
        if chosen.dtype == bool:
            if chosen.shape != keep.shape:
                raise ValueError(f"a reading mask has shape ({self.n_measurements},); got {chosen.shape}")
            keep = chosen
        else:
            if chosen.size and (chosen.min() < 0 or chosen.max() >= self.n_measurements):
                raise ValueError(f"reading indices must be in 0..{self.n_measurements - 1}")
            keep[chosen.astype(int)] = True
        if not keep.any():
            raise ValueError("no readings are left: a protocol needs at least one")
        return Protocol(self.drive, [self.measure[keep & (self.drive_index == k)] for k in range(self.n_drives)])

    def relabel(self, position: ArrayLike) -> Protocol:
        """The same drives and readings with the electrodes numbered otherwise.

        Electrode l of this protocol becomes electrode `position[l]` of the sheet: for an
        instrument whose electrodes are numbered the other way round (`position[l] = -l mod L`)
        or from another first electrode (`position[l] = l + 1 mod L`). The order and sign of
        the readings are kept.

        Arguments:
            position: (L,) the sheet's electrode of each of this protocol's electrodes, a
                permutation of 0..L-1.

        Returns:
            The relabelled `Protocol`.

        Raises:
            ValueError: For a position that is not a permutation of 0..L-1.
        """
        position = np.asarray(position)
        if sorted(position.tolist()) != list(range(self.n_electrodes)):
            raise ValueError(f"position must be a permutation of 0..{self.n_electrodes - 1}; got {position}")
        order = np.argsort(position)  # sheet electrode j is this protocol's electrode order[j]
        per_drive = [self.measure[self.drive_index == k][:, order] for k in range(self.n_drives)]
        return Protocol(self.drive[:, order], per_drive)


# ---------------------------------------------------------------------------------------------
# Pair protocols (EIDORS's mk_stim_patterns conventions)


def skip(n_electrodes: int, k: int, *, measure_driven: bool = False, rotate_measurements: bool = False) -> Protocol:
    """Skip-k drive and skip-k measurement: pairs k electrodes apart, k = 0 is adjacent.

    Drive i (i = 0..n-1): the current enters through electrode i+k+1 and leaves through
    electrode i (pattern -1 at i, +1 at i+k+1; indices mod n). Under each drive, the pairs
    (m, m+k+1) give U_m - U_(m+k+1), m in increasing order starting at 0, or at i with
    `rotate_measurements=True` (m = i, i+1, ..., i-1). Pairs that touch a driven electrode are
    skipped unless `measure_driven=True`. The order and sign are EIDORS's
    `mk_stim_patterns(n, 1, [0, k+1], [0, k+1], options, 1)` with options 'no_meas_current' /
    'meas_current' and 'no_rotate_meas' / 'rotate_meas'.

    Counts: n(n-3) measurements (16 electrodes: 208), except for k = n/2 - 1, where the two
    readings that touch both driven electrodes coincide, n(n-2) (16 electrodes, skip 7: 224);
    with `measure_driven=True` always n * n (256).

    Arguments:
        n_electrodes: n, the number of electrodes (>= 4 without `measure_driven`).
        k: The skip, in 0..n-2: the pairs are k + 1 electrodes apart.
        measure_driven: Keep the readings on driven electrodes (EIDORS 'meas_current').
        rotate_measurements: Start drive i's readings at m = i (EIDORS 'rotate_meas').

    Returns:
        The `Protocol`.

    Raises:
        ValueError: For fewer than 2 electrodes, k outside 0..n-2, or a drive left with no
            reading off its driven electrodes (too few electrodes without `measure_driven`).
        TypeError: For an `n_electrodes` or `k` that is not an integer.
    """
    n = _electrode_count(n_electrodes)
    if not 0 <= operator.index(k) <= n - 2:
        raise ValueError(f"skip k must be in 0..{n - 2} for {n} electrodes (pairs k+1 apart); got {k}")
    return _pair_protocol(n, k + 1, k + 1, measure_driven, rotate_measurements, f"skip {k}")


def adjacent(n_electrodes: int = 16, *, measure_driven: bool = False, rotate_measurements: bool = False) -> Protocol:
    """Adjacent drive, adjacent measurement, no measurement on a driven electrode: `skip(n, 0)`.

    Drive k (k = 0..n-1): the current enters through electrode k+1 and leaves through
    electrode k (indices mod n). Under each drive, the pairs (m, m+1) for m = 0..n-1 in
    increasing order, skipping every pair that touches electrode k or k+1, give U_m - U_(m+1).
    For 16 electrodes: 16 x 13 = 208 measurements, exactly the order and sign of EIDORS's
    `mk_stim_patterns(16, 1, '{ad}', '{ad}', {'no_meas_current'}, 1)`.

    Arguments:
        n_electrodes: n, the number of electrodes (>= 4 without `measure_driven`).
        measure_driven: Keep the pairs on driven electrodes (EIDORS 'meas_current': n * n
            readings, the full 16 x 16 layout, see `to_full_layout`).
        rotate_measurements: Start drive k's pairs at m = k (EIDORS 'rotate_meas').

    Returns:
        The `Protocol`.

    Raises:
        ValueError: For fewer than 2 electrodes, or fewer than 4 without `measure_driven`.
        TypeError: For an `n_electrodes` that is not an integer.
    """
    return skip(n_electrodes, 0, measure_driven=measure_driven, rotate_measurements=rotate_measurements)


def opposite(n_electrodes: int = 16, *, measure_driven: bool = False, rotate_measurements: bool = False) -> Protocol:
    """Opposite drive, adjacent measurement.

    Drive i (i = 0..n-1, n even): the current enters through electrode i+n/2 and leaves
    through electrode i (pattern -1 at i, +1 at i+n/2). Drive i+n/2 is drive i negated; both
    are kept, as EIDORS does. Measurements as in `adjacent`: U_m - U_(m+1), m from 0 (or from i
    with `rotate_measurements=True`), skipping pairs that touch a driven electrode unless
    `measure_driven=True`. The order and sign are EIDORS's
    `mk_stim_patterns(n, 1, '{op}', '{ad}', {'no_meas_current'}, 1)`.

    Counts: n(n-4) measurements (16 electrodes: 192); with `measure_driven=True` n * n (256).

    Arguments:
        n_electrodes: n, the number of electrodes, even (>= 6 without `measure_driven`).
        measure_driven: Keep the pairs on driven electrodes (EIDORS 'meas_current').
        rotate_measurements: Start drive i's pairs at m = i (EIDORS 'rotate_meas').

    Returns:
        The `Protocol`.

    Raises:
        ValueError: For an odd number of electrodes, fewer than 2, or fewer than 6 without
            `measure_driven`.
        TypeError: For an `n_electrodes` that is not an integer.
    """
    n = _electrode_count(n_electrodes)
    if n % 2:
        raise ValueError(f"an opposite protocol needs an even number of electrodes; got {n}")
    return _pair_protocol(n, n // 2, 1, measure_driven, rotate_measurements, "an opposite protocol")


def _electrode_count(n_electrodes: int) -> int:
    n = operator.index(n_electrodes)
    if n < 2:
        raise ValueError(f"a protocol needs at least 2 electrodes; got {n}")
    return n


def _pair_protocol(
    n: int, drive_step: int, measure_step: int, measure_driven: bool, rotate_measurements: bool, name: str
) -> Protocol:
    """Drive i: -1 at i, +1 at i+drive_step; readings U_m - U_(m+measure_step)."""
    eye = np.eye(n)
    drive = np.roll(eye, drive_step, axis=1) - eye  # row i: +1 at i+drive_step, -1 at i
    pairs = eye - np.roll(eye, measure_step, axis=1)  # row m: +1 at m, -1 at m+measure_step
    measure = []
    for i in range(n):
        m = (np.arange(n) + (i if rotate_measurements else 0)) % n
        if not measure_driven:
            driven = drive[i] != 0
            m = m[~(driven[m] | driven[(m + measure_step) % n])]
            if len(m) == 0:
                raise ValueError(
                    f"{name} on {n} electrodes leaves drive {i} no reading off the driven electrodes; "
                    "use more electrodes or measure_driven=True"
                )
        measure.append(pairs[m])
    return Protocol(drive, measure)


# ---------------------------------------------------------------------------------------------
# Conversions between protocols

Frames: TypeAlias = np.ndarray | jax.Array
"""Frames of readings, volts: (n_measurements,) for one frame or (T, n_measurements) for a batch.

A JAX array in gives a JAX array out (jit and vmap work), anything else a NumPy array."""


@dataclass(init=False, eq=False)
class Conversion(StaticData):
    """Maps frames recorded under one protocol onto the order and sign of another.

    Build it once, then call it: `conversion(frames)` maps frames (..., n_source) voltages, a
    NumPy or JAX array (one frame or a batch), to (..., n_target), one gather.
    Under `jax.jit` the map is static data; conversions compare and hash by content.

    Each target reading (drive d, weights w) takes the value of a source reading with the same
    drive and the same weights; a negated drive or negated weights negate the value, both
    negated give the same value (potentials are linear in the current). Patterns match to a
    relative 1e-9 of their largest entry; nothing else matches (no rescaling, and weights that
    differ by a constant are different readings even though the model's potentials sum to
    zero: hardware reads against its own ground).

    Several source readings can match one target reading (duplicates, or opposite drives,
    where drive i+n/2 is drive i negated). The choice is deterministic: first a match with the
    same drive over a negated one, then the same weights over negated ones, then the first in
    source order.

    Arguments:
        source: The `Protocol` the frames were recorded under.
        target: The `Protocol` whose order and sign the frames are mapped to (as many
            electrodes as `source`).
        fill: The value, volts, of target readings that no source reading matches (for
            example 0.0 for the zeros of the 16 x 16 layout); None: refuse them.

    Attributes:
        source: The source `Protocol`.
        target: The target `Protocol`.
        fill: The fill value, a float, or None.
        index: (n_target,) the source reading each target reading takes (0 where none).
        sign: (n_target,) +1 or -1, the sign each target reading takes it with.
        missing: (n_target,) bool, True where `fill` is used.
        fingerprint: A digest of the content, for hashing and comparing.

    Raises:
        ValueError: For protocols on different numbers of electrodes, or, without `fill`,
            target readings that no source reading matches (naming them).
    """

    source: Protocol
    target: Protocol
    fill: float | None
    index: np.ndarray = field(repr=False)
    sign: np.ndarray = field(repr=False)
    missing: np.ndarray = field(repr=False)
    fingerprint: bytes = field(repr=False)

    def __init__(self, source: Protocol, target: Protocol, *, fill: float | None = None) -> None:
        if source.n_electrodes != target.n_electrodes:
            raise ValueError(
                f"the source protocol addresses {source.n_electrodes} electrodes; the target {target.n_electrodes}"
            )
        drives = _signed_matches(target.drive, source.drive)  # (target drives, source drives)
        patterns = _signed_matches(target.measure_patterns, source.measure_patterns)
        drive_sign = drives[target.drive_index][:, source.drive_index]  # (n_target, n_source)
        weight_sign = patterns[target.pattern_index][:, source.pattern_index]
        # Rank of each candidate, lowest preferred: 0 same drive and weights, 1 negated weights,
        # 2 negated drive, 3 both negated, 4 no match; argmin takes the first in source order.
        rank = np.where((drive_sign != 0) & (weight_sign != 0), 2 * (drive_sign < 0) + (weight_sign < 0), 4)
        index = np.argmin(rank, axis=1)
        rows = np.arange(target.n_measurements)
        missing = rank[rows, index] == 4
        if missing.any() and fill is None:
            first = np.flatnonzero(missing)[0]
            raise ValueError(
                f"{np.count_nonzero(missing)} target reading(s) {name_indices(np.flatnonzero(missing))} have no "
                f"match in the source protocol (the first: drive {_nonzero(target.drive[target.drive_index[first]])}, "
                f"weights {_nonzero(target.measure[first])}, as electrode: value); pass fill=0.0 to fill them"
            )
        sign = drive_sign[rows, index] * weight_sign[rows, index]
        self.source = source
        self.target = target
        self.fill = None if fill is None else float(fill)
        self.index = readonly(np.where(missing, 0, index))
        self.sign = readonly(np.where(missing, 1, sign).astype(np.float64))
        self.missing = readonly(missing)
        self.fingerprint = fingerprint(source.fingerprint, target.fingerprint, repr(self.fill).encode())

    def __call__(self, frames: ArrayLike | jax.Array) -> Frames:
        """Map frames recorded under the source protocol to the target's order and sign.

        Arguments:
            frames: (..., n_source) readings, volts: one frame or a batch; a JAX array stays
                one (jit, vmap, grad), anything else becomes a NumPy array. Integers become
                floats; complex frames stay complex.

        Returns:
            (..., n_target) the readings of the target protocol, volts.

        Raises:
            ValueError: For frames whose last axis is not n_source long.
        """
        xp = jnp if isinstance(frames, jax.Array) else np
        frames = xp.asarray(frames)
        if not xp.issubdtype(frames.dtype, xp.inexact):  # complex (admittivity) frames stay complex
            frames = frames.astype(float)
        if frames.ndim == 0 or frames.shape[-1] != self.source.n_measurements:
            raise ValueError(
                f"frames have shape {frames.shape}; expected (..., {self.source.n_measurements}), "
                "one value per reading of the source protocol"
            )
        values = frames[..., self.index] * xp.asarray(self.sign, frames.dtype)
        if self.missing.any():
            values = xp.where(self.missing, xp.asarray(self.fill, frames.dtype), values)
        return values


def convert(frames: ArrayLike | jax.Array, source: Protocol, target: Protocol, *, fill: float | None = None) -> Frames:
    """Frames recorded under one protocol, in the order and sign of another.

    A shorthand for `Conversion(source, target, fill=fill)(frames)`; build the `Conversion`
    once to convert many batches. The matching rules are `Conversion`'s.

    Arguments:
        frames: (..., n_source) readings, volts (a NumPy or JAX array).
        source: The `Protocol` the frames were recorded under.
        target: The `Protocol` to convert to.
        fill: The value, volts, of target readings without a match; None: refuse them.

    Returns:
        (..., n_target) readings, volts; a JAX array for a JAX array in.

    Raises:
        ValueError: As `Conversion` and `Conversion.__call__`.
    """
    return Conversion(source, target, fill=fill)(frames)


def _nonzero(row: np.ndarray) -> dict[int, float]:
    """{electrode: value} of a pattern's nonzero entries, for an error message."""
    return {int(l): float(row[l]) for l in np.flatnonzero(row)}


def _signed_matches(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(A, B) int8: +1 where row i of `a` equals row j of `b`, -1 where it equals its negation."""
    scale = np.maximum(np.abs(a).max(axis=1)[:, None], np.abs(b).max(axis=1)[None, :])
    tolerance = 1e-9 * scale  # rows are never all zero (Protocol refuses them), so scale > 0
    same = np.abs(a[:, None, :] - b[None, :, :]).max(axis=2) <= tolerance
    negated = np.abs(a[:, None, :] + b[None, :, :]).max(axis=2) <= tolerance
    return same.astype(np.int8) - negated.astype(np.int8)


# ---------------------------------------------------------------------------------------------
# The layouts of other tools and hardware


def to_full_layout(frames: ArrayLike | jax.Array, n_electrodes: int = 16) -> Frames:
    """Adjacent frames (..., n(n-3)) to the full n x n layout with zeros (..., n * n).

    The full layout, which EIDORS data sets and many adjacent-drive systems store (16
    electrodes: 256 values), is `adjacent(n, measure_driven=True)`: value 16 * k + m (in
    general n * k + m) is drive k (in at k+1, out at k), pair (m, m+1), U_m - U_(m+1), for
    every m, 0 where the pair touches electrode k or k+1. This fills those n(n-3) -> n * n
    places with 0.

    Arguments:
        frames: (..., n(n-3)) readings of `adjacent(n)`, volts.
        n_electrodes: n, at least 4.

    Returns:
        (..., n * n) readings, volts; a JAX array for a JAX array in.

    Raises:
        ValueError: For frames whose last axis is not n(n-3) long, or fewer than 4 electrodes.
    """
    return _full_layout_conversions(n_electrodes)[0](frames)


def from_full_layout(frames: ArrayLike | jax.Array, n_electrodes: int = 16) -> Frames:
    """Frames in the full n x n layout (..., n * n) to `adjacent(n)` (..., n(n-3)).

    Drops the 3n values on pairs that touch a driven electrode, whatever they hold (zeros in
    EIDORS data, a contact-impedance-dominated reading from hardware that measures them). See
    `to_full_layout` for the layout.

    Arguments:
        frames: (..., n * n) readings in the full layout, volts.
        n_electrodes: n, at least 4.

    Returns:
        (..., n(n-3)) readings of `adjacent(n)`, volts; a JAX array for a JAX array in.

    Raises:
        ValueError: For frames whose last axis is not n * n long, or fewer than 4 electrodes.
    """
    return _full_layout_conversions(n_electrodes)[1](frames)


@functools.cache
def _full_layout_conversions(n_electrodes: int) -> tuple[Conversion, Conversion]:
    standard, full = adjacent(n_electrodes), adjacent(n_electrodes, measure_driven=True)
    return Conversion(standard, full, fill=0.0), Conversion(full, standard)


def from_pyeit(
    protocol_or_ex_mat: Any, meas_mat: np.ndarray | None = None, *, n_electrodes: int | None = None
) -> Protocol:
    """The diffeit `Protocol` of a pyEIT protocol, reading for reading, in pyEIT's order and sign.

    Frames pyEIT simulates or records under it (`EITForward.solve_eit`, drive by drive, the
    rows of `meas_mat` in order) then convert to any diffeit protocol with `convert`.

    pyEIT's conventions (pyEIT 1.2.4): `ex_mat` row [a, b] drives current into electrode a and
    out of electrode b (`create` gives drive i = [i, i + dist_exc], the negation of diffeit's
    -1 at i, +1 at i+dist); `meas_mat[i]` row [p, q] reads U_p - U_q (`create` gives
    [m + step_meas, m]: U_(m+1) - U_m, the negation of diffeit's). The two signs cancel: a
    pyEIT adjacent frame equals diffeit's value for value. Parser 'std' orders the pairs from
    m = 0 as diffeit does; 'rotate_meas' (or 'fmmu') starts at m = a, as
    `rotate_measurements=True`; 'meas_current' keeps the pairs on driven electrodes
    (`measure_driven=True`). pyEIT's `ex_mat` and `meas_mat` are electrode numbers (its
    "local" indices), which is what diffeit's electrodes are.

    Arguments:
        protocol_or_ex_mat: A pyEIT protocol (an object with `ex_mat` and `meas_mat`, as
            `pyeit.eit.protocol.create` returns), or its `ex_mat`: (n_exc, 2) integer rows
            [in, out].
        meas_mat: With an `ex_mat`: (n_exc, n_meas, 2) integer rows [p, q] per drive.
        n_electrodes: L; default the largest electrode number used + 1 (as pyEIT's `n_el`).

    Returns:
        The `Protocol`, reading for reading in pyEIT's order and sign.

    Raises:
        ValueError: For a first argument without `ex_mat` and `meas_mat` when `meas_mat` is
            not given, matrices of the wrong shape, non-integer entries, or electrode numbers
            outside 0..n_electrodes-1 (and as `Protocol`).
    """
    if meas_mat is not None:
        ex_mat = protocol_or_ex_mat
    elif hasattr(protocol_or_ex_mat, "ex_mat") and hasattr(protocol_or_ex_mat, "meas_mat"):
        ex_mat, meas_mat = protocol_or_ex_mat.ex_mat, protocol_or_ex_mat.meas_mat
    else:
        raise ValueError("pass a pyEIT protocol (with ex_mat and meas_mat) or both ex_mat and meas_mat")
    ex_mat = np.asarray(ex_mat)
    meas_mat = np.asarray(meas_mat)
    if ex_mat.ndim != 2 or ex_mat.shape[1] != 2:
        raise ValueError(f"ex_mat must have shape (n_exc, 2), rows [in, out]; got {ex_mat.shape}")
    if meas_mat.ndim != 3 or meas_mat.shape[0] != len(ex_mat) or meas_mat.shape[2] != 2:
        raise ValueError(f"meas_mat must have shape ({len(ex_mat)}, n_meas, 2), rows [p, q]; got {meas_mat.shape}")
    if not (np.issubdtype(ex_mat.dtype, np.integer) and np.issubdtype(meas_mat.dtype, np.integer)):
        raise ValueError("ex_mat and meas_mat must hold electrode numbers (integers)")
    used = max(ex_mat.max(), meas_mat.max()) + 1
    n = int(used) if n_electrodes is None else operator.index(n_electrodes)
    if min(ex_mat.min(), meas_mat.min()) < 0 or used > n:
        raise ValueError(f"ex_mat and meas_mat must hold electrode numbers in 0..{n - 1}")
    eye = np.eye(n)
    return Protocol(eye[ex_mat[:, 0]] - eye[ex_mat[:, 1]], eye[meas_mat[..., 0]] - eye[meas_mat[..., 1]])
