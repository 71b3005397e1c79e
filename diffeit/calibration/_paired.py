"""Paired tests of press errors: whether one calibration's (or map's) errors at the same presses
are smaller than another's, how often (`_closer`, a sign test) and by how much (`_signed_rank`),
each one-sided.
"""

from __future__ import annotations

import numpy as np
import scipy.stats

# A choice is kept when the presses are read closer with it at this one-sided significance.
_SIGNIFICANCE = 0.05


def _closer(ours: np.ndarray, theirs: np.ndarray) -> tuple[int, int, float]:
    """At how many presses the errors `ours` (K,) are smaller than `theirs` (K,), and larger (a
    press not read, NaN, the largest), and the one-sided sign test's p-value that ours are
    smaller more often than not."""
    ours, theirs = np.where(np.isnan(ours), np.inf, ours), np.where(np.isnan(theirs), np.inf, theirs)
    closer, farther = int(np.sum(ours < theirs)), int(np.sum(ours > theirs))
    significance = scipy.stats.binomtest(closer, closer + farther, alternative="greater").pvalue if closer else 1.0
    return closer, farther, float(significance)


def _signed_rank(ours: np.ndarray, theirs: np.ndarray) -> float:
    """The one-sided Wilcoxon signed-rank test's p-value that the errors `ours` (K,) are smaller
    than `theirs` (K,): how much closer counts, where the sign test (`_closer`) counts how
    often. A press not read (NaN) counts as twice the largest error read."""
    read = np.concatenate([ours[~np.isnan(ours)], theirs[~np.isnan(theirs)]])
    worst = 2.0 * float(read.max()) if len(read) else 1.0
    difference = np.where(np.isnan(ours), worst, ours) - np.where(np.isnan(theirs), worst, theirs)
    if not np.any(difference < 0):
        return 1.0
    return float(scipy.stats.wilcoxon(difference, zero_method="wilcox", alternative="less").pvalue)
