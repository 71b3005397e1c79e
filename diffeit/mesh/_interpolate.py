"""Conservative interpolation of element-wise fields between two triangle meshes.

A piecewise-constant field moves from a source mesh to a target mesh by exact overlap areas:
the value on target element t is the area-weighted mean of the source values over the part of
t that the source mesh covers,

    g_t = sum_s A_ts f_s / sum_s A_ts,    A_ts = area(target t ∩ source s)  (m^2).

Constants are preserved exactly. Where both meshes cover the same region, sum_s A_ts is the area
of t and sum_t A_ts the area of s, so the integral sum_t area_t g_t equals sum_s area_s f_s (to
rounding). Where the regions differ (disc meshes at two values of h inscribe slightly different
polygons in the circle), a partly covered target element averages over its covered part, and
the integral over the uncovered slivers is lost or gained.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import scipy.sparse
from numpy.typing import ArrayLike
from scipy.spatial import cKDTree

from .._messages import name_indices
from ._mesh import Mesh, require_flat

# Candidate pairs clipped per batch: bounds the temporaries to a few tens of MB.
_PAIRS_PER_BATCH = 1 << 16
# Overlaps below this fraction of the smaller triangle are rounding (triangles that only touch).
_NEGLIGIBLE_OVERLAP = 1e-14


def overlap_areas(source: Mesh, target: Mesh) -> scipy.sparse.csr_array:
    """The areas of the intersections of every target triangle with every source triangle.

    Row t sums to the area of t where the source mesh covers t; column s sums to the area of s
    where the target covers s. Exact up to rounding: the intersections of the (convex) triangles
    are clipped polygons (Sutherland-Hodgman), and candidate pairs come from a k-d tree of
    centroids, so the cost grows with the number of overlapping pairs, not all pairs.

    Arguments:
        source: The source mesh (metres).
        target: The target mesh, in the same frame.

    Returns:
        Sparse (target.n_elements, source.n_elements) A_ts, m^2.

    Raises:
        TypeError: For a source or target that is not a `Mesh`.
        ValueError: For a surface mesh (a curved skin): the clipping is planar.
    """
    _check_mesh(source, "source")
    _check_mesh(target, "target")
    require_flat(source, "overlap_areas (mesh-to-mesh interpolation)")
    require_flat(target, "overlap_areas (mesh-to-mesh interpolation)")
    target_index, source_index = _candidate_pairs(source, target)
    corners_t, corners_s = target.nodes[target.triangles], source.nodes[source.triangles]
    areas = np.empty(len(target_index))
    for start in range(0, len(target_index), _PAIRS_PER_BATCH):
        batch = slice(start, start + _PAIRS_PER_BATCH)
        areas[batch] = triangle_intersection_areas(corners_t[target_index[batch]], corners_s[source_index[batch]])
    smaller = np.minimum(target.element_areas[target_index], source.element_areas[source_index])
    kept = areas > _NEGLIGIBLE_OVERLAP * smaller
    return scipy.sparse.csr_array(
        (areas[kept], (target_index[kept], source_index[kept])), shape=(target.n_elements, source.n_elements)
    )


def remap_matrix(
    source: Mesh, target: Mesh, *, uncovered: Literal["raise", "nearest"] = "raise"
) -> scipy.sparse.csr_array:
    """The sparse matrix R of conservative interpolation from one mesh to another.

    `R @ f` is the conservative interpolation of element field f from `source` to `target`
    (see the module docstring): R_ts = A_ts / sum_s' A_ts', so every row sums to 1. Build it
    once and apply it to many fields: `R @ f` for (E_source,), `(R @ F.T).T` for a batch
    (T, E_source).

    Arguments:
        source: The source mesh (metres).
        target: The target mesh, in the same frame.
        uncovered: What to do with target elements that overlap no source element at all:
            "raise" (default) raises a `ValueError` naming them; "nearest" gives each the value
            of the source element whose centroid is nearest its centroid (not conservative).

    Returns:
        Sparse (target.n_elements, source.n_elements) R, unit-free.

    Raises:
        ValueError: For an unknown `uncovered`, or uncovered target elements with
            `uncovered="raise"`.
        TypeError: For a source or target that is not a `Mesh`.
    """
    if uncovered not in ("raise", "nearest"):
        raise ValueError(f"uncovered must be 'raise' or 'nearest'; got {uncovered!r}")
    overlap = overlap_areas(source, target)
    covered = overlap.sum(axis=1)
    empty = np.flatnonzero(covered <= 0)
    if len(empty) and uncovered == "raise":
        raise ValueError(
            f"{len(empty)} target element(s) {name_indices(empty)} overlap no source element: the meshes "
            "cover different regions; pass uncovered='nearest' to fill them from the nearest source element"
        )
    weights = scipy.sparse.diags_array(1.0 / np.where(covered > 0, covered, 1.0)) @ overlap
    if len(empty):
        _, nearest = cKDTree(source.element_centroids).query(target.element_centroids[empty])
        fill = scipy.sparse.csr_array(
            (np.ones(len(empty)), (empty, nearest)), shape=(target.n_elements, source.n_elements)
        )
        weights = weights + fill
    return scipy.sparse.csr_array(weights)


def interpolate(
    field: ArrayLike, source: Mesh, target: Mesh, *, uncovered: Literal["raise", "nearest"] = "raise"
) -> np.ndarray:
    """Conservative interpolation of a piecewise-constant element field from one mesh to another.

    The area-weighted mean over each target element's overlap with the source mesh (see
    `remap_matrix`, which this applies; build that once to move many fields).

    Arguments:
        field: (E_source,) values per source element (conductivity in S/sq, a change of it,
            ...), or a batch (T, E_source); real or complex, finite.
        source: The source mesh (metres).
        target: The target mesh, in the same frame.
        uncovered: "raise" or "nearest", for target elements outside the source mesh (see
            `remap_matrix`).

    Returns:
        (E_target,) or (T, E_target), matching `field`, in its unit (float64 or complex).

    Raises:
        ValueError: For a field that is not numbers, of the wrong shape, or not finite; and as
            `remap_matrix`.
        TypeError: For a source or target that is not a `Mesh`.
    """
    _check_mesh(source, "source")
    _check_mesh(target, "target")
    field = np.asarray(field)
    if not (np.issubdtype(field.dtype, np.number) and not np.issubdtype(field.dtype, np.bool_)):
        raise ValueError(f"field must hold numbers; got dtype {field.dtype}")
    if field.ndim not in (1, 2) or field.shape[-1] != source.n_elements:
        raise ValueError(
            f"field must have shape (E_source,) or (T, E_source) with E_source = {source.n_elements}, "
            f"one value per source element; got {field.shape}"
        )
    bad = ~np.isfinite(field)
    if np.any(bad):
        where = np.flatnonzero(bad.any(axis=0) if field.ndim == 2 else bad)
        raise ValueError(f"field is not finite on source element(s) {name_indices(where)}")
    if not np.iscomplexobj(field):
        field = field.astype(np.float64)
    weights = remap_matrix(source, target, uncovered=uncovered)
    return weights @ field if field.ndim == 1 else (weights @ field.T).T


def _check_mesh(mesh, name: str) -> None:
    if not isinstance(mesh, Mesh):
        raise TypeError(f"{name} must be a diffeit Mesh; got {type(mesh).__name__}")


def _candidate_pairs(source: Mesh, target: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """(target, source) element index pairs whose bounding boxes overlap: a superset of the
    overlapping pairs, found without looking at all pairs."""
    corners_t, corners_s = target.nodes[target.triangles], source.nodes[source.triangles]
    centroids_t, centroids_s = corners_t.mean(axis=1), corners_s.mean(axis=1)
    # Each triangle lies in the ball about its centroid through its farthest corner, so two that
    # overlap have centroids at most the sum of those radii apart.
    radius_t = np.linalg.norm(corners_t - centroids_t[:, None], axis=2).max(axis=1)
    radius_s = np.linalg.norm(corners_s - centroids_s[:, None], axis=2).max(axis=1)
    neighbours = cKDTree(centroids_s).query_ball_point(centroids_t, radius_t + radius_s.max() * (1 + 1e-9))
    counts = np.fromiter(map(len, neighbours), dtype=np.int64, count=len(neighbours))
    target_index = np.repeat(np.arange(target.n_elements), counts)
    source_index = np.fromiter((s for near in neighbours for s in near), dtype=np.int64, count=int(counts.sum()))
    low_t, high_t = corners_t.min(axis=1), corners_t.max(axis=1)
    low_s, high_s = corners_s.min(axis=1), corners_s.max(axis=1)
    boxes_meet = np.all(
        (low_t[target_index] <= high_s[source_index]) & (low_s[source_index] <= high_t[target_index]), axis=1
    )
    return target_index[boxes_meet], source_index[boxes_meet]


def triangle_intersection_areas(clip: np.ndarray, subject: np.ndarray) -> np.ndarray:
    """The areas of the intersections of pairs of triangles.

    Sutherland-Hodgman clipping of subject by the three edges of clip, all pairs at once, on
    polygons padded to a common vertex count.

    Arguments:
        clip: (M, 3, 2) counter-clockwise triangles.
        subject: (M, 3, 2) counter-clockwise triangles, in the same units.

    Returns:
        (M,) the area of clip[m] ∩ subject[m], in the units squared.
    """
    # Coordinates relative to a clip corner keep the cross products accurate far from the origin.
    origin = clip[:, :1]
    clip, polygon = clip - origin, subject - origin
    count = np.full(len(clip), 3)
    for k in range(3):
        start, edge = clip[:, k], clip[:, (k + 1) % 3] - clip[:, k]
        # Twice the signed distance times the edge length; >= 0 on the inner (left) side.
        side = edge[:, None, 0] * (polygon[..., 1] - start[:, None, 1]) - edge[:, None, 1] * (
            polygon[..., 0] - start[:, None, 0]
        )
        slots = np.arange(polygon.shape[1])[None]
        following = np.where(slots + 1 < count[:, None], slots + 1, 0)
        side_next = np.take_along_axis(side, following, axis=1)
        vertex_next = np.take_along_axis(polygon, following[..., None], axis=1)
        valid = slots < count[:, None]
        inside, inside_next = side >= 0, side_next >= 0
        crossing = valid & (inside != inside_next)
        t = side / np.where(crossing, side - side_next, 1.0)
        cut = polygon + t[..., None] * (vertex_next - polygon)
        # Each vertex emits itself when inside, then the crossing point when the edge to the next
        # vertex crosses the clip line; compact the emitted points to the front of each row.
        emitted = np.stack([valid & inside, crossing], axis=2).reshape(len(clip), -1)
        points = np.stack([polygon, cut], axis=2).reshape(len(clip), -1, 2)
        count = emitted.sum(axis=1)
        width = max(int(count.max(initial=0)), 1)
        order = np.argsort(~emitted, axis=1, kind="stable")[:, :width]
        polygon = np.take_along_axis(points, order[..., None], axis=1)
    slots = np.arange(polygon.shape[1])[None]
    following = np.where(slots + 1 < count[:, None], slots + 1, 0)
    vertex_next = np.take_along_axis(polygon, following[..., None], axis=1)
    cross = polygon[..., 0] * vertex_next[..., 1] - vertex_next[..., 0] * polygon[..., 1]
    return 0.5 * np.sum(np.where(slots < count[:, None], cross, 0.0), axis=1)


def pixel_overlaps(mesh: Mesh, x_edges: np.ndarray, y_edges: np.ndarray) -> scipy.sparse.csr_array:
    """The area of every pixel of a grid inside every triangle of a mesh.

    Exact up to rounding: each pixel as two triangles, clipped against each element.

    Arguments:
        mesh: The mesh.
        x_edges: (n_columns + 1,) equally spaced pixel edges in x, metres, increasing.
        y_edges: (n_rows + 1,) equally spaced pixel edges in y, metres, increasing.

    Returns:
        Sparse (n_rows * n_columns, E): the area, m^2, of pixel p (row-major, row 0 at the
        smallest y) inside triangle e.

    Raises:
        ValueError: For a surface mesh (a curved skin).
    """
    require_flat(mesh, "pixel_overlaps (a pixel grid)")
    corners = mesh.nodes[mesh.triangles]  # (E, 3, 2), counter-clockwise
    n_columns, n_rows = len(x_edges) - 1, len(y_edges) - 1
    dx, dy = x_edges[1] - x_edges[0], y_edges[1] - y_edges[0]
    low, high = corners.min(axis=1), corners.max(axis=1)
    first_column = np.clip(np.floor((low[:, 0] - x_edges[0]) / dx).astype(int), 0, n_columns - 1)
    last_column = np.clip(np.floor((high[:, 0] - x_edges[0]) / dx).astype(int), 0, n_columns - 1)
    first_row = np.clip(np.floor((low[:, 1] - y_edges[0]) / dy).astype(int), 0, n_rows - 1)
    last_row = np.clip(np.floor((high[:, 1] - y_edges[0]) / dy).astype(int), 0, n_rows - 1)
    # Every (element, pixel) pair whose bounding boxes meet: a superset of the overlapping pairs.
    widths = last_column - first_column + 1
    counts = widths * (last_row - first_row + 1)
    element = np.repeat(np.arange(mesh.n_elements), counts)
    local = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    column = first_column[element] + local % widths[element]
    row = first_row[element] + local // widths[element]
    areas = np.empty(len(element))
    for start in range(0, len(element), _PAIRS_PER_BATCH):
        batch = slice(start, start + _PAIRS_PER_BATCH)
        x0, x1 = x_edges[column[batch]], x_edges[column[batch] + 1]
        y0, y1 = y_edges[row[batch]], y_edges[row[batch] + 1]
        lower = np.stack([np.stack([x0, y0], -1), np.stack([x1, y0], -1), np.stack([x1, y1], -1)], 1)
        upper = np.stack([np.stack([x0, y0], -1), np.stack([x1, y1], -1), np.stack([x0, y1], -1)], 1)
        subject = corners[element[batch]]
        areas[batch] = triangle_intersection_areas(lower, subject) + triangle_intersection_areas(upper, subject)
    kept = areas > 0
    pixel = row * n_columns + column
    return scipy.sparse.csr_array(
        (areas[kept], (pixel[kept], element[kept])), shape=(n_rows * n_columns, mesh.n_elements)
    )
