"""Figures of merit of element-wise images (conventions of DESIGN.md)."""

from __future__ import annotations

import numpy as np

from .mesh import Mesh


def half_amplitude_set(image: np.ndarray) -> np.ndarray:
    """(E,) boolean: elements at or beyond half the peak, on the peak's side.

    The peak is the value of largest magnitude; for a negative peak the set is the elements
    with image <= peak / 2.
    """
    image = np.asarray(image, dtype=float)
    peak = image[np.argmax(np.abs(image))]
    return image * np.sign(peak) >= 0.5 * np.abs(peak)


def half_amplitude_centroid(mesh: Mesh, image: np.ndarray) -> np.ndarray:
    """(2,) the area-weighted centroid (m) of the half-amplitude set of `image` (E,)."""
    chosen = half_amplitude_set(image)
    areas = mesh.element_areas[chosen]
    return areas @ mesh.element_centroids[chosen] / areas.sum()


def position_error(mesh: Mesh, image: np.ndarray, centre: tuple[float, float]) -> float:
    """Distance (m) from `centre` to the area-weighted centroid of the half-amplitude set."""
    return float(np.linalg.norm(half_amplitude_centroid(mesh, image) - np.asarray(centre, dtype=float)))


def correlation(mesh: Mesh, truth: np.ndarray, image: np.ndarray) -> float:
    """Area-weighted Pearson correlation of two element-wise images on `mesh`."""
    weights = mesh.element_areas / mesh.element_areas.sum()
    a = np.asarray(truth, float) - weights @ truth
    b = np.asarray(image, float) - weights @ image
    return float((weights @ (a * b)) / np.sqrt((weights @ a**2) * (weights @ b**2)))
