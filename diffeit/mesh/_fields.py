"""Element fields defined by geometry: sample points inside each triangle, distances to
segments, what fraction of each triangle a shape covers, and which triangle holds a point."""

from __future__ import annotations

import functools

import matplotlib.tri
import numpy as np
import scipy.sparse
import scipy.spatial
from numpy.typing import ArrayLike

from ._mesh import Mesh, require_flat


def locate(mesh: Mesh, points: ArrayLike) -> np.ndarray:
    """The element holding each point.

    Uses matplotlib's trapezoid-map locator, built once per mesh.

    Arguments:
        mesh: The sheet.
        points: (P, 2) positions in metres (or (2,) for one).

    Returns:
        (P,) (or a scalar for one point) int: the index of the triangle containing each point,
        -1 for a point off the mesh. A point on an edge goes to one of its triangles.

    Raises:
        ValueError: For a surface mesh (a curved skin): the locator is planar.
    """
    require_flat(mesh, "locate (point location)")
    positions = np.asarray(points, dtype=float)
    found = _finder(mesh)(*np.atleast_2d(positions).T)
    return np.asarray(found, dtype=int).reshape(positions.shape[:-1])


def onto_surface(mesh: Mesh, point: ArrayLike, elements: ArrayLike | None = None) -> np.ndarray:
    """Points near a curved skin taken onto it: each projected onto the plane of the element
    (among `elements`) whose centroid is nearest.

    A weighted mean of element centroids (a touch's or an image's centroid) lies inside the
    surface's chord; its projection lies on the surface to within that element's own flatness.
    On a flat sheet the points are returned as they are.

    Arguments:
        mesh: The sheet.
        point: (..., D) points, m, D the mesh's dimension; a point with a NaN stays NaN.
        elements: The elements to project onto (indices); None for all.

    Returns:
        (..., D) the points on the surface, m.

    Raises:
        ValueError: For points of another dimension than the mesh's.
    """
    point = np.asarray(point, dtype=float)
    _check_dimension(mesh, point)
    if mesh.nodes.shape[1] == 2:
        return point
    points = point.reshape(-1, 3)
    finite = np.all(np.isfinite(points), axis=1)
    nearest, _, normal = nearest_element(mesh, points[finite], elements)
    height = np.einsum("pd,pd->p", points[finite] - mesh.element_centroids[nearest], normal)
    projected = np.full_like(points, np.nan)
    projected[finite] = points[finite] - height[:, None] * normal
    return projected.reshape(point.shape)


def nearest_element(
    mesh: Mesh, points: ArrayLike, elements: ArrayLike | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The element (among `elements`) whose centroid is nearest each point, how far that
    centroid is, and the element's unit normal.

    Arguments:
        mesh: The sheet.
        points: (P, D) finite points, m, D the mesh's dimension (built once per mesh, the
            centroids' k-d tree of all its elements is shared by later calls).
        elements: The elements to choose among (indices); None for all.

    Returns:
        (P,) int the elements, (P,) the distances to their centroids, m, and (P, 3) their unit
        normals (b - a) x (c - a) / |...| (corners a, b, c as the mesh winds them; (P, 0) on a
        flat sheet, which has no normal in its own coordinates).

    Raises:
        ValueError: For points of another dimension than the mesh's.
    """
    points = np.asarray(points, dtype=float)
    _check_dimension(mesh, points)
    if elements is None:
        distance, nearest = _centroid_tree(mesh).query(points)
    else:
        elements = np.asarray(elements)
        distance, index = scipy.spatial.cKDTree(mesh.element_centroids[elements]).query(points)
        nearest = elements[index]
    nearest = np.asarray(nearest, dtype=int)
    if mesh.nodes.shape[1] == 2:
        return nearest, np.asarray(distance), np.zeros((len(nearest), 0))
    a, b, c = (mesh.nodes[mesh.triangles[nearest, corner]] for corner in range(3))
    normal = np.cross(b - a, c - a)
    return nearest, np.asarray(distance), normal / np.linalg.norm(normal, axis=1, keepdims=True)


def _check_dimension(mesh: Mesh, point: np.ndarray) -> None:
    """ValueError for points (..., D) of another dimension D than the mesh's."""
    if point.ndim == 0 or point.shape[-1] != mesh.nodes.shape[1]:
        raise ValueError(f"a point of this mesh has {mesh.nodes.shape[1]} coordinates; got shape {point.shape}")


def surface_distance(mesh: Mesh, start: ArrayLike, stop: ArrayLike) -> np.ndarray:
    """The distance along the sheet between points on it, m.

    On a flat sheet the straight line. On a curved skin the arc of a circle over the chord c
    whose curvature k is the surface's normal curvature along the chord, (2 / k) asin(k c / 2),
    with k = |(n_b - n_a) . (b - a)| / c^2 from the unit normals n_a, n_b of the elements whose
    centroids are nearest the two points (each turned to the side of the normal nearest the
    chord's midpoint: a mesh's triangles may be wound either way). On a sphere this is the
    great circle; on a cylinder, in any direction, the helix along it to fourth order in k c
    (2.5% short for points 2 rad apart round the axis). Points in one element (equal normals)
    are a chord apart: within that triangle's own flatness.

    Arguments:
        mesh: The sheet.
        start: (..., D) points on it, m, D the mesh's dimension.
        stop: (..., D) points on it, m (broadcast with `start`).

    Returns:
        (...) the distances, m; NaN where a point holds a NaN.

    Raises:
        ValueError: For points of another dimension than the mesh's.
    """
    start, stop = np.broadcast_arrays(np.asarray(start, dtype=float), np.asarray(stop, dtype=float))
    _check_dimension(mesh, start)
    chord = stop - start
    length = np.linalg.norm(chord, axis=-1)
    if mesh.nodes.shape[1] == 2:
        return length
    finite = np.all(np.isfinite(chord), axis=-1)
    middle, first, last = (nearest_element(mesh, points[finite])[2] for points in (0.5 * (start + stop), start, stop))
    first *= np.sign(np.sum(first * middle, axis=1, keepdims=True) + 1e-300)
    last *= np.sign(np.sum(last * middle, axis=1, keepdims=True) + 1e-300)
    along = length[finite]
    bend = np.abs(np.sum((last - first) * chord[finite], axis=1)) / np.maximum(along, 1e-300)  # k c
    arc = along * np.ones_like(bend)
    curved = bend > 1e-8
    arc[curved] = 2.0 * along[curved] * np.arcsin(np.minimum(0.5 * bend[curved], 1.0)) / bend[curved]
    distance = np.full(length.shape, np.nan)
    distance[finite] = arc
    return distance


@functools.lru_cache(maxsize=16)
def _finder(mesh: Mesh) -> matplotlib.tri.TriFinder:
    """matplotlib's trapezoid-map point locator of `mesh`, built once per mesh (by content)."""
    return matplotlib.tri.Triangulation(mesh.nodes[:, 0], mesh.nodes[:, 1], mesh.triangles).get_trifinder()


def barycentric_samples(level: int) -> np.ndarray:
    """Barycentric coordinates of the centroids of the level^2 congruent sub-triangles of a triangle.

    Arguments:
        level: The subdivision of each side, a positive integer.

    Returns:
        (level^2, 3) the coordinates, each row summing to 1.
    """
    points = []
    for i in range(level):
        for j in range(level - i):
            points.append([(i + 1 / 3) / level, (j + 1 / 3) / level])  # upward sub-triangles
            if i + j < level - 1:
                points.append([(i + 2 / 3) / level, (j + 2 / 3) / level])  # downward ones
    points = np.array(points)
    return np.column_stack([1 - points.sum(axis=1), points])


@functools.lru_cache(maxsize=16)
def element_sample_points(mesh: Mesh, level: int = 8) -> np.ndarray:
    """Sample points in every triangle: the centroids of its level^2 congruent sub-triangles.

    Each point stands for 1/S of its triangle's area (S = level^2): averages over them are the
    midpoint rule on the sub-triangles. Computed once per mesh (by content) and level.

    Arguments:
        mesh: The mesh.
        level: The subdivision of each side, a positive integer.

    Returns:
        (E, S, d) the points, metres, d = 2 for a flat mesh and 3 for a surface mesh ((N, 3)
        nodes); read-only.
    """
    points = np.einsum("sk,ekx->esx", barycentric_samples(level), mesh.nodes[mesh.triangles])
    points.flags.writeable = False
    return points


def _from_segments(points: np.ndarray, starts: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """(P, K, 2) each point (P, 2) less its nearest point on each segment (K of `starts`,
    `stops`)."""
    direction = stops - starts
    relative = points[:, None] - starts[None]
    t = np.clip(np.sum(relative * direction, axis=2) / np.sum(direction**2, axis=1), 0.0, 1.0)
    return relative - t[..., None] * direction


def distance_to_segments(points: np.ndarray, starts: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """The distance from each point to the nearest of a set of segments.

    Arguments:
        points: (P, 2) the points.
        starts: (K, 2) the start of each segment, in the points' units.
        stops: (K, 2) the end of each segment.

    Returns:
        (P,) the distances, in the points' units; inf when there is no segment.
    """
    return np.min(np.linalg.norm(_from_segments(points, starts, stops), axis=2), axis=1, initial=np.inf)


def onto_sheet(mesh: Mesh, points: ArrayLike) -> np.ndarray:
    """Points of the plane held to a flat sheet: each off it taken to the nearest point of its
    boundary (outer or a hole's), the others and NaN unchanged.

    Arguments:
        mesh: The flat sheet.
        points: (..., 2) positions, m.

    Returns:
        (..., 2) the positions, m, on the sheet.

    Raises:
        ValueError: For a surface mesh (a curved skin; `onto_surface` takes points onto it).
    """
    require_flat(mesh, "onto_sheet")
    positions = np.array(points, dtype=float)
    flat = positions.reshape(-1, 2)
    finite = np.flatnonzero(np.all(np.isfinite(flat), axis=1))
    off = finite[locate(mesh, flat[finite]) < 0] if len(finite) else finite
    if len(off):
        starts, stops = mesh.nodes[mesh.boundary_edges[:, 0]], mesh.nodes[mesh.boundary_edges[:, 1]]
        offsets = _from_segments(flat[off], starts, stops)
        nearest = np.argmin(np.sum(offsets**2, axis=2), axis=1)
        flat[off] -= offsets[np.arange(len(off)), nearest]
    return flat.reshape(positions.shape)


def disc_fraction(mesh: Mesh, centre: tuple[float, float], radius: float, level: int | None = 8) -> np.ndarray:
    """(E,) fraction of each triangle's area inside the disc |x - centre| < radius.

    With `level`, the midpoint rule on `level`^2 equal sub-triangles: exact for triangles
    wholly inside or outside, error O(1/level) of the area of a triangle the circle cuts, and
    a staircase in the centre and the radius. With `level=None`, the exact area (piecewise
    smooth in the centre and the radius: what a derivative of the footprint needs). For many
    discs at once, `disc_fractions`.

    Arguments:
        mesh: The mesh.
        centre: (x, y), metres.
        radius: Metres, positive.
        level: The subdivision of each side, a positive integer, or None for exact areas.

    Returns:
        (E,) fractions in [0, 1].

    Raises:
        ValueError: For a radius that is not positive.
    """
    return disc_fractions(mesh, np.asarray(centre, dtype=float)[None], radius, level)[:, [0]].toarray().ravel()


def disc_fractions(mesh: Mesh, centres: ArrayLike, radius: ArrayLike, level: int | None = 8) -> scipy.sparse.csc_array:
    """The fraction of each triangle's area inside each of K discs, as `disc_fraction`.

    Only the triangles whose centroid lies within a radius and the largest triangle's reach of
    a disc's centre are computed: no other triangle comes within a radius of the centre, so
    the result is the same as computing every triangle.

    Arguments:
        mesh: The mesh.
        centres: (K, d) the discs' centres, metres, d the mesh's dimension (3 on a surface
            mesh: the disc is then the ball of the radius about the centre, and each triangle's
            part inside it is the disc where the ball cuts the triangle's plane).
        radius: Scalar or (K,), metres, positive.
        level: The subdivision of each side, a positive integer (the midpoint rule), or None
            (exact areas).

    Returns:
        (E, K) sparse fractions in [0, 1].

    Raises:
        ValueError: For a radius that is not positive, or centres not of shape (K, d).
    """
    centres = np.asarray(centres, dtype=float)
    if centres.ndim != 2 or centres.shape[1] != mesh.nodes.shape[1]:
        raise ValueError(f"centres must have shape (K, {mesh.nodes.shape[1]}); got {centres.shape}")
    radii = np.broadcast_to(np.asarray(radius, dtype=float), (len(centres),))
    if np.any(~(radii > 0)):
        raise ValueError(f"radius must be positive; got {radius}")
    near = _centroid_tree(mesh).query_ball_point(centres, radii + _largest_reach(mesh))
    disc = np.repeat(np.arange(len(centres)), [len(n) for n in near])
    element = np.concatenate([np.zeros(0, int), *(np.asarray(n, dtype=int) for n in near)])
    if level is None:
        fraction = _exact_disc_fractions(mesh.nodes[mesh.triangles[element]] - centres[disc][:, None], radii[disc])
    else:
        offsets = element_sample_points(mesh, level)[element] - centres[disc][:, None]
        fraction = (np.einsum("psx,psx->ps", offsets, offsets) < radii[disc][:, None] ** 2).mean(axis=1)
    kept = fraction > 0
    return scipy.sparse.csc_array((fraction[kept], (element[kept], disc[kept])), shape=(mesh.n_elements, len(centres)))


def _exact_disc_fractions(corners: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """(P,) the fraction of each triangle inside a disc about the origin: corners (P, 3, d)
    relative to the disc's centre, m, radii (P,), m.

    The area is the signed sum, over the triangle's sides, of the disc's part of the triangle
    the side makes with the centre: a circular sector where the side runs outside the circle,
    a straight triangle where inside. In 3D each triangle is first taken into its own plane: the
    ball cuts it in a disc about the centre's projection, of radius sqrt(r^2 - distance^2)."""
    if corners.shape[2] == 3:
        first, second = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
        normal = np.cross(first, second)
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        across = np.einsum("px,px->p", corners[:, 0], normal)
        along = first / np.linalg.norm(first, axis=1, keepdims=True)
        axes = np.stack([along, np.cross(normal, along)], axis=1)  # (P, 2, 3) the plane's directions
        corners = np.einsum("pcx,pax->pca", corners - across[:, None, None] * normal[:, None], axes)
        radii_squared = radii**2 - across**2
    else:
        radii_squared = radii**2
    r2 = np.maximum(radii_squared, 0.0)[:, None]
    start, side = corners, np.roll(corners, -1, axis=1) - corners
    a = np.einsum("psx,psx->ps", side, side)
    b = np.einsum("psx,psx->ps", start, side)
    c = np.einsum("psx,psx->ps", start, start) - r2
    discriminant = b * b - a * c
    root = np.sqrt(np.maximum(discriminant, 0.0))
    crosses = discriminant > 0  # the side's line cuts the circle: its chord's ends, clipped to the side
    enter = np.where(crosses, np.clip((-b - root) / a, 0.0, 1.0), 1.0)[..., None]
    leave = np.where(crosses, np.clip((-b + root) / a, 0.0, 1.0), 1.0)[..., None]
    inside_from, inside_to = start + enter * side, start + leave * side

    def cross(p: np.ndarray, q: np.ndarray) -> np.ndarray:
        return p[..., 0] * q[..., 1] - p[..., 1] * q[..., 0]

    def sector(p: np.ndarray, q: np.ndarray) -> np.ndarray:
        return 0.5 * r2 * np.arctan2(cross(p, q), np.einsum("psx,psx->ps", p, q))

    area = sector(start, inside_from) + 0.5 * cross(inside_from, inside_to) + sector(inside_to, start + side)
    whole = 0.5 * cross(side[:, 0], -side[:, 2])
    fraction = np.clip(np.sum(area, axis=1) / whole, 0.0, 1.0)
    return np.where(radii_squared > 0, fraction, 0.0)


@functools.lru_cache(maxsize=16)
def _largest_reach(mesh: Mesh) -> float:
    """The largest distance, m, from a triangle's centroid to one of its corners."""
    return float(np.max(np.linalg.norm(mesh.nodes[mesh.triangles] - mesh.element_centroids[:, None], axis=2)))


@functools.lru_cache(maxsize=16)
def _centroid_tree(mesh: Mesh) -> scipy.spatial.cKDTree:
    """A k-d tree of the element centroids, built once per mesh (by content)."""
    return scipy.spatial.cKDTree(mesh.element_centroids)
