"""Element fields defined by geometry: what fraction of each triangle a shape covers."""

from __future__ import annotations

import numpy as np

from ._mesh import Mesh


def barycentric_samples(level: int) -> np.ndarray:
    """(S, 3) barycentric coordinates of the centroids of the level^2 congruent sub-triangles."""
    points = []
    for i in range(level):
        for j in range(level - i):
            points.append([(i + 1 / 3) / level, (j + 1 / 3) / level])  # upward sub-triangles
            if i + j < level - 1:
                points.append([(i + 2 / 3) / level, (j + 2 / 3) / level])  # downward ones
    points = np.array(points)
    return np.column_stack([1 - points.sum(axis=1), points])


def disc_fraction(mesh: Mesh, centre: tuple[float, float], radius: float, level: int = 8) -> np.ndarray:
    """(E,) fraction of each triangle's area inside the disc |x - centre| < radius.

    Midpoint rule on `level`^2 equal sub-triangles: exact for triangles wholly inside or
    outside, error O(1/level) of the area of a triangle the circle cuts.
    """
    if radius <= 0:
        raise ValueError(f"radius must be positive; got {radius}")
    weights = barycentric_samples(level)  # (S, 3)
    points = np.einsum("sk,ekx->esx", weights, mesh.nodes[mesh.triangles])
    inside = np.linalg.norm(points - np.asarray(centre, dtype=float), axis=2) < radius
    return inside.mean(axis=1)
