"""Drive and measurement protocols: which currents are applied and which voltages are read."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import jax
import numpy as np

from ._arrays import readonly


@dataclass(frozen=True, eq=False)
class Protocol:
    """Current patterns and the voltage readings taken under each.

    `Protocol(drive, measure)`:

    - `drive`: (n_drives, L) current pattern per drive, in units of the model's drive current:
      entry l is the current entering the sheet through electrode l (positive in). Each row
      must sum to zero.
    - `measure`: the readings of each drive, either an (n_drives, M, L) array or a sequence of
      n_drives arrays of shape (M_k, L). A reading with weights m is `sum_l m_l U_l`, U the
      electrode potentials; `U_m - U_(m+1)` has weights +1 at m and -1 at m+1.

    Measurements are ordered drive by drive, then in the given order within a drive, and
    stored flat: `measure` (n_measurements, L) with `drive_index` (n_measurements,) naming the
    drive each belongs to. A protocol is static data for JAX (a pytree without leaves).
    """

    drive: np.ndarray
    measure: np.ndarray
    drive_index: np.ndarray = field(init=False)
    measure_patterns: np.ndarray = field(init=False, repr=False)
    """(P, L) the distinct rows of `measure`."""
    pattern_index: np.ndarray = field(init=False, repr=False)
    """(n_measurements,) row of `measure_patterns` each measurement uses."""

    def __init__(self, drive: np.ndarray, measure: np.ndarray | Sequence[np.ndarray]) -> None:
        drive = np.array(drive, dtype=np.float64)
        if drive.ndim != 2 or drive.shape[0] == 0:
            raise ValueError(f"drive must have shape (n_drives, n_electrodes); got {drive.shape}")
        n_drives, n_electrodes = drive.shape
        if not np.all(np.isfinite(drive)):
            raise ValueError("drive patterns hold non-finite values")
        unbalanced = np.flatnonzero(np.abs(drive.sum(axis=1)) > 1e-12 * np.abs(drive).sum(axis=1).clip(1))
        if len(unbalanced):
            raise ValueError(f"drive patterns {unbalanced.tolist()} do not sum to zero: current must be conserved")
        per_drive = [np.array(m, dtype=np.float64) for m in measure]
        if len(per_drive) != n_drives:
            raise ValueError(f"measure gives readings for {len(per_drive)} drives; drive has {n_drives}")
        for k, m in enumerate(per_drive):
            if m.ndim != 2 or m.shape[1] != n_electrodes:
                raise ValueError(f"measurements of drive {k} must have shape (M, {n_electrodes}); got {m.shape}")
            if not np.all(np.isfinite(m)):
                raise ValueError(f"measurements of drive {k} hold non-finite values")
        flat = np.concatenate(per_drive) + 0.0  # + 0.0 turns -0.0 into 0.0 for np.unique
        if len(flat) == 0:
            raise ValueError("the protocol has no measurements")
        drive_index = np.repeat(np.arange(n_drives), [len(m) for m in per_drive])
        patterns, pattern_index = np.unique(flat, axis=0, return_inverse=True)
        object.__setattr__(self, "drive", readonly(drive))
        object.__setattr__(self, "measure", readonly(flat))
        object.__setattr__(self, "drive_index", readonly(drive_index))
        object.__setattr__(self, "measure_patterns", readonly(patterns))
        object.__setattr__(self, "pattern_index", readonly(pattern_index.ravel()))

    @property
    def n_electrodes(self) -> int:
        return self.drive.shape[1]

    @property
    def n_drives(self) -> int:
        return self.drive.shape[0]

    @property
    def n_measurements(self) -> int:
        return self.measure.shape[0]

    def __repr__(self) -> str:
        return (
            f"Protocol(n_electrodes={self.n_electrodes}, n_drives={self.n_drives}, "
            f"n_measurements={self.n_measurements})"
        )


jax.tree_util.register_static(Protocol)


def adjacent(n_electrodes: int = 16) -> Protocol:
    """Adjacent drive, adjacent measurement, no measurement on a driven electrode.

    Drive k (k = 0..n-1): the current enters through electrode k+1 and leaves through
    electrode k (indices mod n). Under each drive, the pairs (m, m+1) for m = 0..n-1 in
    increasing order, skipping every pair that touches electrode k or k+1, give U_m - U_(m+1).
    For 16 electrodes: 16 x 13 = 208 measurements, exactly the order and sign of EIDORS's
    `mk_stim_patterns(16, 1, '{ad}', '{ad}', {'no_meas_current'}, 1)`.
    """
    if n_electrodes < 4:
        raise ValueError(f"an adjacent protocol needs at least 4 electrodes; got {n_electrodes}")
    eye = np.eye(n_electrodes)
    pairs = eye - np.roll(eye, 1, axis=1)  # row m: +1 at m, -1 at m+1
    drive = np.roll(eye, 1, axis=1) - eye  # row k: +1 at k+1, -1 at k
    measure = []
    for k in range(n_electrodes):
        driven = {k, (k + 1) % n_electrodes}
        keep = [m for m in range(n_electrodes) if not driven & {m, (m + 1) % n_electrodes}]
        measure.append(pairs[keep])
    return Protocol(drive, measure)
