"""Mesh generators: disc and polygonal skins whose electrode ends are mesh vertices (Shewchuk's
`triangle`)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import triangle

from .._messages import name_indices
from ._fields import distance_to_segments
from ._mesh import Mesh, _signed_areas

# triangle's mean element area is about 0.65 of the area bound it is given: this factor makes
# the mean edge length about the requested h.
_AREA_PER_H_SQUARED = 0.65
# Element size grows by this much per metre of distance from the nearest electrode.
_GRADING = 0.5
# Vertices closer than this fraction of the polygon's extent count as one point.
_POLYGON_TOLERANCE = 1e-12
# Electrode ends this close to a corner (as a fraction of the perimeter) move onto it: no slivers.
_CORNER_SNAP = 1e-9


def disc(
    n_electrodes: int = 16,
    electrode_width: float | None = None,
    h: float | None = None,
    *,
    radius: float = 1.0,
    electrode_h: float | None = None,
    first_electrode_angle: float = 0.0,
    electrode_angles: Sequence[float] | np.ndarray | None = None,
    interior_circles: Sequence[float] = (),
) -> Mesh:
    """A disc skin centred at the origin, with electrodes on its rim.

    Electrode k is centred at angle `first_electrode_angle + 2 pi k / n_electrodes` (radians,
    counter-clockwise from the x axis), or at `electrode_angles[k]`; both ends of every
    electrode are mesh vertices on the circle. The boundary is the inscribed polygon through
    its vertices. The element size grows linearly with the distance from the nearest electrode,
    from `electrode_h` there up to `h`.

    Arguments:
        n_electrodes: The number of electrodes, at least 2.
        electrode_width: The arc length of each electrode, m; default 0.2 times the radius,
            or half the spacing between electrodes where that leaves no gaps (32 or more).
        h: The target element edge length away from the electrodes, m; default 0.1 times
            the radius (a skin of radius 80 mm gets about 900 triangles, as the unit disc does).
        radius: The disc's radius, m.
        electrode_h: The element edge length at the electrodes, m, in (0, h]; default `h / 2`.
        first_electrode_angle: The centre angle of electrode 0, radians.
        electrode_angles: (n_electrodes,) the centre angle of every electrode (radians,
            increasing, within one turn, electrodes not overlapping), in place of the equal
            spacing: displaced electrodes.
        interior_circles: Radii (m, in (0, radius)) of concentric circles that element edges
            follow (for inclusions whose boundary the mesh must resolve).

    Returns:
        The `Mesh`, its electrodes numbered counter-clockwise.

    Raises:
        ValueError: For fewer than 2 electrodes, a non-positive electrode width or electrodes
            that do not fit on the rim with gaps between them, a non-positive `h` or
            `radius`, an `electrode_h` outside (0, h], an interior circle outside
            (0, radius), or electrode angles of the wrong count, not finite, out of order or
            overlapping.
    """
    if n_electrodes < 2:
        raise ValueError(f"a disc needs at least 2 electrodes; got {n_electrodes}")
    if radius <= 0:
        raise ValueError(f"radius must be positive; got {radius}")
    # Scaled with the radius: a skin described in metres gets the unit disc's mesh, scaled.
    if electrode_width is None:
        electrode_width = radius * (0.2 if 0.2 * n_electrodes < 2 * np.pi else np.pi / n_electrodes)
    h = 0.1 * radius if h is None else h
    if not 0 < electrode_width * n_electrodes < 2 * np.pi * radius:
        raise ValueError(
            f"{n_electrodes} electrodes of width {electrode_width} do not fit on a rim of "
            f"length {2 * np.pi * radius:.4g} with gaps between them"
        )
    if h <= 0:
        raise ValueError(f"h must be positive; got h={h}")
    electrode_h, size = _element_size(h, electrode_h)
    for r in interior_circles:
        if not 0 < r < radius:
            raise ValueError(f"interior circle radius {r} must lie strictly inside (0, {radius})")

    half_angle = electrode_width / (2 * radius)
    if electrode_angles is None:
        centres = first_electrode_angle + 2 * np.pi * np.arange(n_electrodes) / n_electrodes
    else:
        centres = _checked_angles(electrode_angles, n_electrodes, 2 * half_angle)
    electrode_ends = np.stack([centres - half_angle, centres + half_angle], axis=1)

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


def _checked_angles(angles, n_electrodes: int, width_angle: float) -> np.ndarray:
    angles = np.asarray(angles, dtype=np.float64)
    if angles.shape != (n_electrodes,) or not np.all(np.isfinite(angles)):
        raise ValueError(
            f"electrode_angles must hold one finite angle (radians) per electrode, shape ({n_electrodes},); "
            f"got {angles.tolist()}"
        )
    gaps = np.diff(np.append(angles, angles[0] + 2 * np.pi))
    if np.any(gaps <= width_angle):
        k = int(np.argmax(gaps <= width_angle))
        raise ValueError(
            f"electrode_angles: electrodes {k} and {(k + 1) % n_electrodes} overlap or are out of order "
            f"(centres {gaps[k]:.4g} rad apart; each electrode spans {width_angle:.4g} rad)"
        )
    return angles


def polygon(
    vertices: np.ndarray | Sequence[Sequence[float]],
    n_electrodes: int = 16,
    electrode_width: float | None = None,
    h: float | None = None,
    *,
    electrode_centres: Sequence[float] | np.ndarray | None = None,
    electrode_h: float | None = None,
) -> Mesh:
    """A polygonal skin with electrodes on its boundary, placed by arc length.

    Positions on the boundary are arc lengths s in metres, measured counter-clockwise from
    vertex 0, in [0, P) for a perimeter P. By default the electrodes are spread evenly: electrode
    k is centred at s = (k + 1/2) P / n_electrodes, so the first centre is half a spacing after
    vertex 0 and a square with 16 electrodes gets 4 per side, placed symmetrically. Electrode 0 is
    the first electrode counter-clockwise from vertex 0, and the order follows the boundary, as
    the `Mesh` convention requires.

    Both ends of every electrode are mesh vertices on the boundary, and no boundary segment is
    split by the mesher, so each electrode covers exactly its arc length. An electrode may pass
    around a corner (its node chain then includes the corner). An end that lands within 1e-9 P
    of a corner is moved onto the corner, which avoids slivers.

    Arguments:
        vertices: (n, 2) corners, m, n >= 3, in either orientation (clockwise input is reversed
            about vertex 0, so vertex 0 stays the origin of the arc length). Do not repeat
            vertex 0 at the end: the polygon closes itself.
        n_electrodes: The number of electrodes, at least 2.
        electrode_width: The arc length of each electrode, m; default half the smallest
            distance between neighbouring centres (half the spacing when evenly placed).
        h: The target element edge length away from the electrodes, m; default P / 64.
        electrode_centres: (n_electrodes,) the arc lengths of the electrode centres, m,
            strictly increasing in [0, P); an electrode centred near vertex 0 may extend past
            it.
        electrode_h: The element edge length at the electrodes, m, in (0, h]; default `h / 2`.
            The size grows linearly with the distance from the nearest electrode up to `h`.

    Returns:
        The `Mesh`, its electrodes numbered counter-clockwise from vertex 0.

    Raises:
        ValueError: Naming the problem: vertices not (n, 2) or not finite, fewer than 3
            vertices, repeated vertices, a self-intersecting polygon, fewer than 2 electrodes,
            non-positive sizes, an `electrode_h` outside (0, h], centres of the wrong count,
            outside [0, P) or out of order, electrodes that overlap or do not fit on the
            boundary.
    """
    corners = _counter_clockwise(_checked_polygon(vertices))
    edges = np.roll(corners, -1, axis=0) - corners
    edge_lengths = np.linalg.norm(edges, axis=1)
    corner_arcs = np.concatenate([[0.0], np.cumsum(edge_lengths)[:-1]])
    perimeter = float(edge_lengths.sum())

    centres = _electrode_centres(n_electrodes, electrode_centres, perimeter)
    spacing = np.diff(centres, append=centres[0] + perimeter)
    if electrode_width is None:
        electrode_width = 0.5 * float(spacing.min())
    h = perimeter / 64 if h is None else h
    if electrode_width <= 0 or h <= 0:
        raise ValueError(f"electrode_width and h must be positive; got electrode_width={electrode_width}, h={h}")
    electrode_h, size = _element_size(h, electrode_h)
    if electrode_width * n_electrodes >= perimeter:
        raise ValueError(
            f"{n_electrodes} electrodes of width {electrode_width} do not fit on a boundary of "
            f"length {perimeter:.4g} with gaps between them"
        )
    overlapping = np.flatnonzero(spacing <= electrode_width)
    if len(overlapping):
        k = int(overlapping[0])
        raise ValueError(
            f"electrodes {k} and {(k + 1) % n_electrodes} overlap: their centres are {spacing[k]:.4g} apart "
            f"along the boundary, not more than the electrode width {electrode_width}"
        )

    # Electrode k covers the arc lengths [starts[k], starts[k] + lengths[k]] modulo the perimeter.
    ends = np.mod(centres[:, None] + np.array([-0.5, 0.5]) * electrode_width, perimeter)
    ends = _snap_to_corners(ends, corner_arcs, perimeter)
    starts, lengths = ends[:, 0], np.mod(ends[:, 1] - ends[:, 0], perimeter)

    def along(s: np.ndarray) -> np.ndarray:
        """(M, K) arc length from s forward to the start of each electrode (0 inside it)."""
        return np.mod(np.asarray(s)[:, None] - starts[None], perimeter)

    def arc_distance(s: np.ndarray) -> np.ndarray:
        """Distance along the boundary to the nearest electrode (0 on an electrode)."""
        past = along(s) - lengths[None]
        return np.min(np.where(past <= 0, 0.0, np.minimum(past, perimeter - past - lengths[None])), axis=1)

    def position(s: np.ndarray) -> np.ndarray:
        edge = np.searchsorted(corner_arcs, s, side="right") - 1
        # At a corner (s equal to its arc length) this is the corner itself, exactly.
        return corners[edge] + ((s - corner_arcs[edge]) / edge_lengths[edge])[:, None] * edges[edge]

    # The boundary, piece by piece between consecutive corners and electrode ends: each piece is
    # straight and lies on one electrode or in one gap.
    breaks = np.unique(np.concatenate([corner_arcs, ends.ravel()]))
    piece_ends = np.append(breaks[1:], perimeter)
    arcs = [
        _graded_points(start, stop, lambda s: size(arc_distance(s)))[:-1]
        for start, stop in zip(breaks, piece_ends, strict=True)
    ]
    arc = np.concatenate(arcs)
    on_electrode = along(arc) <= lengths[None] + 1e-12 * perimeter
    electrodes = tuple(np.flatnonzero(on_electrode[:, k]) for k in range(n_electrodes))

    middles = 0.5 * (breaks + piece_ends)
    electrode_pieces = np.any(along(middles) < lengths[None], axis=1)
    piece_starts = position(breaks[electrode_pieces])
    piece_stops = position(np.mod(piece_ends[electrode_pieces], perimeter))

    def target_size(points: np.ndarray) -> np.ndarray:
        return size(distance_to_segments(points, piece_starts, piece_stops))

    nodes, triangles = _triangulate(position(arc), _closed_loop(0, len(arc)), h, target_size)
    return Mesh(nodes, triangles, electrodes)


def rectangle(
    width: float = 1.0,
    height: float = 1.0,
    n_electrodes: int = 16,
    electrode_width: float | None = None,
    h: float | None = None,
    *,
    electrode_centres: Sequence[float] | np.ndarray | None = None,
    electrode_h: float | None = None,
) -> Mesh:
    """A rectangular skin centred at the origin, with electrodes on its boundary.

    `polygon` with vertex 0 at the bottom-left corner (-width/2, -height/2) and the arc length
    running counter-clockwise (along the bottom side first). With the default even placement a
    square gets n_electrodes / 4 electrodes per side, symmetric about the middle of each side.

    Arguments:
        width: The extent along x, m.
        height: The extent along y, m.
        n_electrodes: The number of electrodes, at least 2.
        electrode_width: The arc length of each electrode, m; default half the spacing.
        h: The target element edge length away from the electrodes, m; default perimeter / 64.
        electrode_centres: (n_electrodes,) the arc lengths of the electrode centres, m, from
            the bottom-left corner, as in `polygon`.
        electrode_h: The element edge length at the electrodes, m; default `h / 2`.

    Returns:
        The `Mesh`.

    Raises:
        ValueError: For a non-positive width or height, and as `polygon`.
    """
    if not (width > 0 and height > 0):
        raise ValueError(f"width and height must be positive; got width={width}, height={height}")
    corners = 0.5 * np.array([[-width, -height], [width, -height], [width, height], [-width, height]])
    return polygon(
        corners,
        n_electrodes,
        electrode_width,
        h,
        electrode_centres=electrode_centres,
        electrode_h=electrode_h,
    )


def _element_size(h: float, electrode_h: float | None) -> tuple[float, Callable[[np.ndarray], np.ndarray]]:
    """The electrode element size (default h / 2) and the size as a function of the distance
    (metres) from the nearest electrode: electrode_h there, growing linearly up to h."""
    electrode_h = h / 2 if electrode_h is None else electrode_h
    if not 0 < electrode_h <= h:
        raise ValueError(f"electrode_h must lie in (0, h]; got {electrode_h} with h={h}")

    def size(distance: np.ndarray) -> np.ndarray:
        return np.minimum(h, electrode_h + _GRADING * distance)

    return electrode_h, size


def _checked_polygon(vertices) -> np.ndarray:
    """(n, 2) float vertices of a simple polygon, in the caller's order and numbering."""
    vertices = np.asarray(vertices, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 2:
        raise ValueError(f"vertices must have shape (n, 2); got {vertices.shape}")
    if not np.all(np.isfinite(vertices)):
        raise ValueError(f"vertices {name_indices(np.flatnonzero(~np.isfinite(vertices).all(axis=1)))} are not finite")
    n = len(vertices)
    if n < 3:
        raise ValueError(f"a polygon needs at least 3 vertices; got {n}")
    scale = float(np.ptp(vertices, axis=0).max())
    distance = np.linalg.norm(vertices[:, None] - vertices[None], axis=2)
    i, j = np.nonzero(np.triu(distance <= _POLYGON_TOLERANCE * scale, k=1))
    if len(i):
        hint = "; leave out the closing vertex, the polygon closes itself" if (i[0], j[0]) == (0, n - 1) else ""
        raise ValueError(f"vertices {i[0]} and {j[0]} repeat the same point {vertices[i[0]].tolist()}{hint}")
    crossing = _crossing_edges(vertices, _POLYGON_TOLERANCE * scale**2)
    if crossing is not None:
        i, j = crossing
        raise ValueError(
            f"the polygon intersects itself: edge {i} (vertices {i}-{(i + 1) % n}) and edge {j} "
            f"(vertices {j}-{(j + 1) % n}) meet"
        )
    return vertices


def _counter_clockwise(vertices: np.ndarray) -> np.ndarray:
    """The vertices counter-clockwise, reversed about vertex 0 when they run clockwise."""
    following = np.roll(vertices, -1, axis=0)
    twice_area = np.sum(vertices[:, 0] * following[:, 1] - following[:, 0] * vertices[:, 1])
    return vertices if twice_area > 0 else vertices[np.r_[0, len(vertices) - 1 : 0 : -1]]


def _crossing_edges(vertices: np.ndarray, tolerance: float) -> tuple[int, int] | None:
    """The first pair of edges (i, j), i < j, of a closed polygon that touch or cross other
    than at the vertex two neighbouring edges share; None for a simple polygon."""
    n = len(vertices)
    a, b = vertices, np.roll(vertices, -1, axis=0)  # edge i runs from a[i] to b[i]

    def orientation(p, q, r):
        value = (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0])
        return np.where(np.abs(value) <= tolerance, 0, np.sign(value))

    def within_box(p, q, r):  # r inside the bounding box of segment pq (used when collinear)
        low, high = np.minimum(p, q) - np.sqrt(tolerance), np.maximum(p, q) + np.sqrt(tolerance)
        return np.all((r >= low) & (r <= high), axis=-1)

    i, j = np.triu_indices(n, k=1)
    p, q, r, s = a[i], b[i], a[j], b[j]
    o1, o2, o3, o4 = orientation(p, q, r), orientation(p, q, s), orientation(r, s, p), orientation(r, s, q)
    meet = (o1 * o2 < 0) & (o3 * o4 < 0)
    meet |= ((o1 == 0) & within_box(p, q, r)) | ((o2 == 0) & within_box(p, q, s))
    meet |= ((o3 == 0) & within_box(r, s, p)) | ((o4 == 0) & within_box(r, s, q))
    # Neighbouring edges always share a vertex; they overlap only when the second folds back
    # along the first.
    neighbours = (j == i + 1) | ((i == 0) & (j == n - 1))
    first = np.where((i == 0) & (j == n - 1), j, i)
    second = np.where((i == 0) & (j == n - 1), i, j)
    edge = b - a
    turn = edge[first, 0] * edge[second, 1] - edge[first, 1] * edge[second, 0]
    folds_back = (np.abs(turn) <= tolerance) & (np.sum(edge[first] * edge[second], axis=1) < 0)
    meet = np.where(neighbours, folds_back, meet)
    hits = np.flatnonzero(meet)
    return (int(i[hits[0]]), int(j[hits[0]])) if len(hits) else None


def _electrode_centres(n_electrodes: int, centres, perimeter: float) -> np.ndarray:
    if n_electrodes < 2:
        raise ValueError(f"a skin needs at least 2 electrodes; got {n_electrodes}")
    if centres is None:
        return (np.arange(n_electrodes) + 0.5) * perimeter / n_electrodes
    centres = np.asarray(centres, dtype=np.float64)
    if centres.shape != (n_electrodes,):
        raise ValueError(
            f"electrode_centres must hold one arc length per electrode, shape ({n_electrodes},); got {centres.shape}"
        )
    if not np.all(np.isfinite(centres) & (centres >= 0) & (centres < perimeter)):
        raise ValueError(f"electrode_centres must lie in [0, {perimeter:.6g}), the perimeter; got {centres.tolist()}")
    if np.any(np.diff(centres) <= 0):
        raise ValueError(
            "electrode_centres must increase strictly: electrode k is the k-th counter-clockwise from vertex 0"
        )
    return centres


def _snap_to_corners(arcs: np.ndarray, corner_arcs: np.ndarray, perimeter: float) -> np.ndarray:
    """`arcs` with those within `_CORNER_SNAP` of the perimeter of a corner replaced by the corner's."""
    offset = np.mod(arcs[..., None] - corner_arcs, perimeter)
    distance = np.minimum(offset, perimeter - offset)
    nearest = np.argmin(distance, axis=-1)
    close = np.take_along_axis(distance, nearest[..., None], axis=-1)[..., 0] <= _CORNER_SNAP * perimeter
    return np.where(close, corner_arcs[nearest], arcs)


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
