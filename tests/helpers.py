"""Helpers shared by the test modules."""

import numpy as np


def noisy(clean: np.ndarray, percent: float, seed: int, reference: np.ndarray | None = None) -> np.ndarray:
    """`clean` plus the project's noise: independent Gaussian noise of standard deviation
    p/100 RMS(reference) on every reading (RMS(clean) when no reference is given), seeded."""
    scale = np.sqrt(np.mean((clean if reference is None else reference) ** 2))
    return clean + percent / 100 * scale * np.random.default_rng(seed).standard_normal(np.shape(clean))
