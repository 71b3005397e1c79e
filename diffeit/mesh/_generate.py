"""Mesh generators: skins whose electrode ends are mesh vertices (Shewchuk's `triangle`)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import triangle

from ._mesh import Mesh, _signed_areas

# triangle's mean element area is about 0.65 of the area bound it is given: this factor makes
# the mean edge length about the requested h.
_AREA_PER_H_SQUARED = 0.65
# Element size grows by this much per metre of distance from the nearest electrode.
_GRADING = 0.5


def disc(
    n_electrodes: int = 16,
    electrode_width: float = 0.2,
    h: float = 0.1,
    *,
    radius: float = 1.0,
    electrode_h: float | None = None,
    first_electrode_angle: float = 0.0,
    interior_circles: Sequence[float] = (),
) -> Mesh:
    """A disc skin with `n_electrodes` equally spaced electrodes on its rim.

    Electrode k is centred at angle `first_electrode_angle + 2 pi k / n_electrodes` (radians,
    counter-clockwise from the x axis); both ends of every electrode are mesh vertices on the
    circle. The boundary is the inscribed polygon through its vertices.

    **Arguments:**

    - `n_electrodes`: number of electrodes.
    - `electrode_width`: arc length of each electrode, in metres.
    - `h`: target element edge length away from the electrodes, in metres.
    - `radius`: disc radius in metres.
    - `electrode_h`: element edge length at the electrodes (default `h / 2`); the size grows
      linearly with the distance from the nearest electrode up to `h`.
    - `first_electrode_angle`: centre angle of electrode 0, radians.
    - `interior_circles`: radii of concentric circles that element edges follow (for
      inclusions whose boundary the mesh must resolve).
    """
    if n_electrodes < 2:
        raise ValueError(f"a disc needs at least 2 electrodes; got {n_electrodes}")
    if not 0 < electrode_width * n_electrodes < 2 * np.pi * radius:
        raise ValueError(
            f"{n_electrodes} electrodes of width {electrode_width} do not fit on a rim of "
            f"length {2 * np.pi * radius:.4g} with gaps between them"
        )
    if h <= 0 or radius <= 0:
        raise ValueError(f"h and radius must be positive; got h={h}, radius={radius}")
    electrode_h = h / 2 if electrode_h is None else electrode_h
    if not 0 < electrode_h <= h:
        raise ValueError(f"electrode_h must lie in (0, h]; got {electrode_h} with h={h}")
    for r in interior_circles:
        if not 0 < r < radius:
            raise ValueError(f"interior circle radius {r} must lie strictly inside (0, {radius})")

    half_angle = electrode_width / (2 * radius)
    centres = first_electrode_angle + 2 * np.pi * np.arange(n_electrodes) / n_electrodes
    electrode_ends = np.stack([centres - half_angle, centres + half_angle], axis=1)

    def size(distance: np.ndarray) -> np.ndarray:
        return np.minimum(h, electrode_h + _GRADING * distance)

    # The rim, electrode by electrode then the gap after it, as angles.
    angles, electrode_indices = [], []
    for k in range(n_electrodes):
        start, stop = electrode_ends[k]
        arc = _graded_points(0.0, stop - start, lambda s: np.full_like(s, electrode_h / radius))
        electrode_indices.append(sum(map(len, angles)) + np.arange(len(arc)))
        angles.append(start + arc)
        gap_stop = electrode_ends[(k + 1) % n_electrodes, 0] + (2 * np.pi if k == n_electrodes - 1 else 0)
        gap = stop - gap_stop

        def gap_size(s: np.ndarray, gap: float = -gap) -> np.ndarray:
            return size(radius * np.minimum(s, gap - s)) / radius

        angles.append(stop + _graded_points(0.0, -gap, gap_size)[1:-1])
    rim_angles = np.concatenate(angles)
    vertices = [radius * np.stack([np.cos(rim_angles), np.sin(rim_angles)], axis=1)]
    segments = [_closed_loop(0, len(rim_angles))]
    offset = len(rim_angles)
    for r in interior_circles:
        n = max(8, int(np.ceil(2 * np.pi * r / size(radius - r))))
        theta = 2 * np.pi * np.arange(n) / n
        vertices.append(r * np.stack([np.cos(theta), np.sin(theta)], axis=1))
        segments.append(_closed_loop(offset, n))
        offset += n
    vertices = np.concatenate(vertices)

    ends_xy = radius * np.stack([np.cos(electrode_ends.ravel()), np.sin(electrode_ends.ravel())], axis=1)

    def target_size(points: np.ndarray) -> np.ndarray:
        # Distance to the nearest electrode, measured to its ends and (radially) to the rim.
        to_ends = np.min(np.linalg.norm(points[:, None, :] - ends_xy[None], axis=2), axis=1)
        angle = np.arctan2(points[:, 1], points[:, 0])
        on_electrode = np.any(np.abs(np.angle(np.exp(1j * (angle[:, None] - centres[None])))) <= half_angle, axis=1)
        to_rim = radius - np.linalg.norm(points, axis=1)
        return size(np.where(on_electrode, np.minimum(to_rim, to_ends), to_ends))

    nodes, triangles = _triangulate(vertices, np.concatenate(segments), h, target_size)
    return Mesh(nodes, triangles, tuple(electrode_indices))


def _closed_loop(offset: int, n: int) -> np.ndarray:
    index = offset + np.arange(n)
    return np.stack([index, np.roll(index, -1)], axis=1)


def _graded_points(start: float, stop: float, spacing: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """Points from `start` to `stop` (both included) whose local spacing follows `spacing(s)`."""
    s = np.linspace(start, stop, 2001)
    density = 1.0 / spacing(s)
    cumulative = np.concatenate([[0.0], np.cumsum(0.5 * (density[1:] + density[:-1]) * np.diff(s))])
    n = max(1, int(np.ceil(cumulative[-1] - 1e-9)))
    return np.interp(np.linspace(0.0, cumulative[-1], n + 1), cumulative, s)


def _triangulate(
    vertices: np.ndarray,
    segments: np.ndarray,
    h: float,
    target_size: Callable[[np.ndarray], np.ndarray],
) -> tuple[np.ndarray, np.ndarray]:
    """Quality triangulation (minimum angle 30 degrees) that keeps the given vertices first
    and never splits a segment ('Y'), refined until element areas follow `target_size`."""
    mesh = triangle.triangulate(
        {"vertices": vertices, "segments": segments}, f"pq30Ya{_AREA_PER_H_SQUARED * h * h:.17g}"
    )
    for _ in range(4):
        centroids = mesh["vertices"][mesh["triangles"]].mean(axis=1)
        bound = _AREA_PER_H_SQUARED * target_size(centroids) ** 2
        area = np.abs(_signed_areas(mesh["vertices"], mesh["triangles"]))
        if np.all(area <= 1.5 * bound):
            break
        mesh = triangle.triangulate({**mesh, "triangle_max_area": bound}, "rpq30Ya")
    if not np.allclose(mesh["vertices"][: len(vertices)], vertices):
        raise RuntimeError("triangle reordered the input vertices; electrode indices would be wrong")
    return mesh["vertices"], mesh["triangles"]
