"""The maps fitted on labelled presses that `diffeit.touches` reads touches through: `PositionMap`
(read positions onto the labels) and `SizeMap` (read radii and depths onto the presses'), each
of a degree chosen by leave-one-out cross-validation, and the labels' frame's similarity
(`_in_mesh_frame`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import equinox as eqx
import numpy as np
import scipy.spatial

from ..mesh import Mesh, onto_sheet, onto_surface, surface_distance
from ._paired import _signed_rank

# A press read tells about the skin within this fraction of its radius (`_coverage`).
_COVERED_RADII = 0.3


# Degrees of the position map tried by cross-validation (None: no map).
_MAP_DEGREES = (None, 0, 1, 2, 3)
# A degree replaces a lower one when its held-out errors are smaller at this one-sided significance
# (`_chosen_degree`).
_DEGREE_SIGNIFICANCE = 0.1


# On a curved skin the monomials in x, y and z are nearly dependent (x^2 + y^2 + z^2 is constant
# on a sphere, to the mesh's flatness): the least squares drop directions this much weaker.
_MAP_RCOND = 1e-8


class PositionMap(eqx.Module):
    """A smooth map from touch positions read from images (the mesh's frame) to the labels'.

    The read position plus a displacement polynomial in the coordinates of total degree
    `degree`, fitted by least squares on labelled presses, the degree chosen by leave-one-out
    cross-validation (degree 0 shifts, 1 is affine: the labels' orientation, scale and offset;
    `degree=None` is the identity). On a curved skin the polynomial is in x, y and z and each
    displaced point is taken back onto the surface (`diffeit.mesh.onto_surface`): an affine
    map then turns, stretches and shifts touches along it. On a flat skin whose labels' frame
    is known (`held_to`), a point the polynomial takes off the skin (it extrapolates beyond the
    presses it was fitted on) is taken to the nearest point of the skin's outline in that frame.

    The polynomial is trusted only within the presses (`region`, their read positions' convex
    hull; on a curved skin in the plane of its mesh's two widest directions, `_chart`). It is
    the skin's global map (the labels' frame, held with `held_to`; else the presses' shift or
    affine fit, `slope`; on a curved skin, whose labels are in the mesh's frame, none) plus a
    local correction, the images' own bias; beyond the region a point takes the global map and
    the nearest point's local correction, fading as exp(-(d / l)^2) with its distance d from
    the region, l a quarter of `length`: what the presses taught about the images' bias holds
    near them, and the global map beyond. Extrapolated as a polynomial, the map had read
    touches 42 mm off (degree 3; 8 mm at degree 1) against 3.7 mm unmapped on simulated skins
    whose calibration presses lay in half of them alone, a robot's raster cut short.

    Attributes:
        degree: The polynomial's degree, or None for the identity.
        coefficients: (n_terms, D) the displacement polynomial's coefficients, on positions
            and displacements divided by `length`.
        length: The length, m, positions are divided by (the presses' spread).
        errors: Degree (str; "none" for the identity) -> the median leave-one-out distance, m,
            between mapped and labelled positions (on a curved skin along it:
            `diffeit.mesh.surface_distance`).
        surface: The curved skin's mesh the mapped points are taken onto; None on a flat one.
        sheet: The flat skin's mesh whose outline, in the labels' frame `frame`, holds the
            mapped points; None: they are not held.
        frame: (5,) the labels' frame onto the mesh's (`SkinCalibration.values["label_frame"]`:
            ln scale, angle (rad), offset x and y (m), handedness), with `sheet`; else None.
        region: (H, 2) the convex hull of the presses' read positions, m, counter-clockwise
            (two points where they lie on a line; on a curved skin in its chart's plane),
            within which the polynomial is evaluated; None where it is evaluated everywhere
            (maps read from files of schema version 6 or older).
        slope: (1, D) or (1 + D, D) the coefficients (as `coefficients`) of the global map's
            displacement where the labels' frame is not held: the presses' shift (degree 0)
            or affine fit (degree 1 and above) on a flat skin, zero on a curved one; with
            `region`.
    """

    degree: int | None = eqx.field(static=True)
    coefficients: np.ndarray
    length: float
    errors: dict[str, float]
    surface: Mesh | None = None
    sheet: Mesh | None = None
    frame: np.ndarray | None = None
    region: np.ndarray | None = None
    slope: np.ndarray | None = None

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """(..., D) the labels'-frame positions, m, of positions `points` (..., D) read in the
        mesh's frame; NaN stays NaN."""
        points = np.asarray(points, np.float64)
        if self.degree is None:
            return self.within(points)
        if self.region is None:
            moved = points + self._displacement(points)
            return self.within(moved) if self.surface is None else onto_surface(self.surface, moved)
        if self.surface is None:
            nearest = _nearest_in(self.region, points)
            distance = np.linalg.norm(points - nearest, axis=-1, keepdims=True)
        else:
            origin, axes = _chart(self.surface)
            charted = (points - origin) @ axes.T
            on_chart = _nearest_in(self.region, charted)
            distance = np.linalg.norm(charted - on_chart, axis=-1, keepdims=True)
            nearest = np.where(distance > 0, onto_surface(self.surface, origin + on_chart @ axes), points)
        local = self._displacement(nearest) - self._global_displacement(nearest)
        fade = np.exp(-((distance / (0.25 * self.length)) ** 2))
        moved = points + self._global_displacement(points) + fade * local
        return self.within(moved) if self.surface is None else onto_surface(self.surface, moved)

    def _displacement(self, points: np.ndarray) -> np.ndarray:
        """(..., D) the polynomial's displacement, m, at `points` (..., D) in the mesh's frame."""
        return _terms(points / self.length, self.degree) @ self.coefficients * self.length

    def _global_displacement(self, points: np.ndarray) -> np.ndarray:
        """(..., D) the displacement, m, of the labels' frame at `points` (..., D) in the mesh's
        frame; `slope`'s where the frame is not held."""
        if self.frame is None:
            return _terms(points / self.length, 1 if len(self.slope) > 1 else 0) @ self.slope * self.length
        scale, rotation = _similarity_of(self.frame)
        return (points - self.frame[2:4]) @ rotation / scale * [1.0, self.frame[4]] - points

    def held_to(self, sheet: Mesh, frame: np.ndarray) -> PositionMap:
        """This map, its points held to the flat skin `sheet`, seen in the labels' frame `frame`
        (as `frame`)."""
        return dataclasses.replace(self, sheet=sheet, frame=np.asarray(frame, np.float64))

    def within(self, points: np.ndarray) -> np.ndarray:
        """(..., 2) labels'-frame positions `points`, m, each off the skin taken to the nearest
        point of its outline (`diffeit.mesh.onto_sheet` in the mesh's frame: the labels' frame
        is a similarity of it); a copy of them when the map holds no sheet."""
        points = np.array(points, np.float64)
        if self.sheet is None or self.frame is None:
            return points
        scale, rotation = _similarity_of(self.frame)
        offset, mirror = self.frame[2:4], [1.0, self.frame[4]]
        in_mesh = _in_mesh_frame(points, self.frame)
        on_mesh = onto_sheet(self.sheet, in_mesh)
        moved = np.any(on_mesh != in_mesh, axis=-1)  # the others stay bit for bit
        points[moved] = (on_mesh[moved] - offset) @ rotation / scale * mirror
        return points

    @classmethod
    def fit(cls, read: np.ndarray, labelled: np.ndarray, mesh: Mesh | None = None) -> PositionMap:
        """The map from `read` (K, D) to `labelled` (K, D) positions, m, on the sheet `mesh`
        (needed for points on a curved skin, D = 3, which the map takes back onto it).

        Its degree is chosen by leave-one-out cross-validation among those that K presses
        determine with two to spare: a degree replaces a lower one when its distances are lower
        in the median and smaller by a signed-rank test (`_chosen_degree`).

        Raises:
            ValueError: For points on a curved skin without its `mesh`.
        """
        read, labelled = np.asarray(read, np.float64), np.asarray(labelled, np.float64)
        surface = None
        if read.shape[1] == 3:
            if mesh is None or mesh.nodes.shape[1] != 3:
                raise ValueError("a position map of points on a curved skin needs the skin's (surface) mesh")
            surface = mesh
        degree, errors = _chosen_degree(
            read,
            lambda degree: _leave_one_out_errors(read, labelled, degree, surface),
        )
        length = _spread(labelled)
        coefficients = np.zeros((0, read.shape[1]))
        region = slope = None
        if degree is not None:
            shift = (labelled - read) / length
            coefficients, *_ = np.linalg.lstsq(_terms(read / length, degree), shift, rcond=_MAP_RCOND)
            if surface is None:
                region = _hull(read)
                slope, *_ = np.linalg.lstsq(_terms(read / length, min(degree, 1)), shift, rcond=_MAP_RCOND)
            else:
                origin, axes = _chart(surface)
                region, slope = _hull((read - origin) @ axes.T), np.zeros((1, 3))
        return cls(degree, coefficients, length, errors, surface, region=region, slope=slope)


class SizeMap(eqx.Module):
    """Gains, smooth over the sheet, on the radius and the depth of touches read from images,
    fitted on labelled presses.

    A one-step image blurs a touch: it reads a press wider and shallower than it is, by factors
    that vary over the sheet (on the calibration benchmark's skins, presses of radius 10 mm and
    depth -0.3 read 1.6 to 3.1 times as wide and 0.11 to 0.43 times as deep, 10th to 90th
    percentile). ln(labelled radius / read radius) and ln(model depth / read depth) are each a
    polynomial in the read position (positions divided by `length`, as `PositionMap`'s), its
    degree chosen by leave-one-out cross-validation as `PositionMap`'s (None: a gain of 1); the
    model depth is the press's depth under its labelled disc at the calibrated model. A touch
    like the presses then reads at their radius and depth; one of another size in proportion.
    Beyond the presses the polynomial is not trusted: each ln gain stays within the range it
    takes at them.

    Attributes:
        radius_degree: The radius gain's polynomial degree, or None for a gain of 1.
        depth_degree: The depth gain's, or None.
        radius_coefficients: (n_terms,) the radius gain's polynomial coefficients (ln gain).
        depth_coefficients: (n_terms,) the depth gain's.
        limits: (2, 2) the smallest and largest ln gain of radius (row 0) and depth (row 1) at
            the presses.
        length: The length, m, positions are divided by (the presses' spread).
        errors: "radius" and "depth" -> degree (str; "none" for a gain of 1) -> the median
            leave-one-out |ln(read x gain / press's)|.
    """

    radius_degree: int | None = eqx.field(static=True)
    depth_degree: int | None = eqx.field(static=True)
    radius_coefficients: np.ndarray
    depth_coefficients: np.ndarray
    limits: np.ndarray
    length: float
    errors: dict[str, dict[str, float]]

    def __call__(self, points: np.ndarray, radius: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The radii and depths (...) of touches read at positions `points` (..., D), m in the
        mesh's frame, with their gains; NaN stays NaN."""
        scaled = np.asarray(points, np.float64) / self.length
        gains = [
            np.exp(np.clip(_terms(scaled, degree) @ coefficients, *limits)) if degree is not None else 1.0
            for degree, coefficients, limits in (
                (self.radius_degree, self.radius_coefficients, self.limits[0]),
                (self.depth_degree, self.depth_coefficients, self.limits[1]),
            )
        ]
        return np.asarray(radius) * gains[0], np.asarray(depth) * gains[1]

    @classmethod
    def fit(
        cls,
        read_positions: np.ndarray,
        read_radius: np.ndarray,
        read_depth: np.ndarray,
        radius: np.ndarray,
        depth: np.ndarray,
    ) -> SizeMap:
        """The gains that take the radii and depths (K,) read at `read_positions` (K, D), m, to
        the presses' `radius` (K,) and `depth` (K,) (presses read at no position, or whose read
        and press's values differ in sign, are left out).

        Raises:
            ValueError: For fewer than 3 presses left.
        """
        read_positions = np.asarray(read_positions, np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            targets = {
                "radius": np.log(np.asarray(radius, np.float64) / read_radius),
                "depth": np.log(np.asarray(depth, np.float64) / read_depth),
            }
        seen = np.all(np.isfinite(read_positions), axis=1)
        if seen.sum() < 3:
            raise ValueError(f"a size map needs 3 presses read or more; {int(seen.sum())} were")
        length = _spread(read_positions[seen])
        degrees, coefficients, limits, errors = {}, {}, [], {}
        for name, target in targets.items():
            kept = seen & np.isfinite(target)
            if kept.sum() < 3:
                raise ValueError(f"a size map needs 3 presses whose {name} was read or more; {int(kept.sum())} were")
            points, target = read_positions[kept] / length, target[kept]

            def held_out(degree: int | None, points: np.ndarray = points, target: np.ndarray = target) -> np.ndarray:
                residuals = target if degree is None else _held_out_residuals(_terms(points, degree), target)
                return np.abs(residuals)

            degrees[name], errors[name] = _chosen_degree(points, held_out)
            coefficients[name] = np.zeros(0)
            fitted = np.zeros(len(target))
            if degrees[name] is not None:
                terms = _terms(points, degrees[name])
                coefficients[name] = np.linalg.lstsq(terms, target, rcond=_MAP_RCOND)[0]
                fitted = terms @ coefficients[name]
            limits.append([fitted.min(), fitted.max()])
        return cls(
            degrees["radius"],
            degrees["depth"],
            coefficients["radius"],
            coefficients["depth"],
            np.array(limits),
            length,
            errors,
        )


def _chosen_degree(
    points: np.ndarray, held_out: Callable[[int | None], np.ndarray]
) -> tuple[int | None, dict[str, float]]:
    """The polynomial degree (None: no polynomial) of a map of `points` (K, D) chosen by
    cross-validation, and each degree's median held-out error ("none" for None).

    Among the degrees K points determine with two to spare, a degree replaces the one chosen
    below it when its held-out errors `held_out(degree)` (K,) are lower in the median and
    smaller by a one-sided signed-rank test at `_DEGREE_SIGNIFICANCE` (`_paired._signed_rank`).
    A median alone swings on differences of 0.1 mm. On the calibration benchmark's sessions
    (five seeds, 25, 50 and 100 presses) and three laid in rows (`benchmarks/session_layouts.py`),
    the test presses read 2.92 and 4.86 mm off on average with the lowest median's degree, 2.90
    and 4.26 mm so, and 2.96 and 4.26 mm needing a sign test at 5% as well (each map fitted to
    the same calibration's presses)."""
    chosen = held_out(None)
    errors, degree = {"none": float(np.median(chosen))}, None
    for candidate in _MAP_DEGREES[1:]:
        if len(points) < _terms(points[:1], candidate).shape[1] + 2:
            break
        trial = held_out(candidate)
        errors[str(candidate)] = float(np.median(trial))
        if np.median(trial) < np.median(chosen) and _signed_rank(trial, chosen) < _DEGREE_SIGNIFICANCE:
            degree, chosen = candidate, trial
    return degree, errors


def _held_out_residuals(terms: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """The residuals (K, ...) of each of `targets` (K, ...) left out of the least-squares fit
    on `terms` (K, n_terms), through the fit's hat matrix."""
    coefficients, *_ = np.linalg.lstsq(terms, targets, rcond=None)
    hat = np.einsum("ij,ji->i", terms, np.linalg.pinv(terms))
    leverage = np.maximum(1.0 - hat, 1e-9).reshape((-1,) + (1,) * (targets.ndim - 1))
    return (targets - terms @ coefficients) / leverage


def _chart(surface: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """The plane a curved skin's presses are bounded in: its mesh's nodes' mean (3,) and two
    directions (2, 3) across the one they spread least along (a forearm's patch or a cap seen
    from above: one point of the plane to each point of the skin).

    The in-plane directions are made from that normal alone, each sign fixed: a dome spreads
    alike along every direction across it, where the singular vectors are any pair, and a file's
    region must meet the same chart on another machine."""
    origin = surface.nodes.mean(axis=0)
    normal = np.linalg.svd(surface.nodes - origin, full_matrices=False)[2][2]
    # The first clearly large component sets the sign, the first clearly small one the first
    # direction (|normal| = 1: one of each exists), away from ties that rounding could break.
    normal = normal * np.sign(normal[np.flatnonzero(np.abs(normal) > 0.5)[0]])
    first = np.eye(3)[np.flatnonzero(np.abs(normal) < 0.6)[0]]
    first = first - (first @ normal) * normal
    first = first / np.linalg.norm(first)
    return origin, np.stack([first, np.cross(normal, first)])


def _hull(points: np.ndarray) -> np.ndarray:
    """(H, 2) the convex hull of `points` (K, 2), counter-clockwise; the two extreme points
    along their line where they lie on one."""
    try:
        return points[scipy.spatial.ConvexHull(points).vertices]
    except scipy.spatial.QhullError:
        direction = np.linalg.svd(points - points.mean(axis=0))[2][0]
        along = (points - points.mean(axis=0)) @ direction
        return points[[np.argmin(along), np.argmax(along)]]


def _nearest_in(region: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(..., 2) each of `points` (..., 2) within the convex polygon `region` (H, 2),
    counter-clockwise (H = 2: a segment), else the nearest point of its outline; NaN stays NaN."""
    flat = points.reshape(-1, 2)
    edges = np.roll(region, -1, axis=0) - region  # (H, 2), from each vertex to the next
    relative = flat[:, None, :] - region[None]  # (P, H, 2)
    inside = np.all(edges[:, 0] * relative[..., 1] - edges[:, 1] * relative[..., 0] >= 0, axis=1)
    inside &= len(region) > 2
    along = np.clip(np.sum(relative * edges, axis=-1) / np.maximum(np.sum(edges**2, axis=-1), 1e-300), 0.0, 1.0)
    feet = region + along[..., None] * edges  # (P, H, 2) the nearest point of each edge
    nearest = np.argmin(np.nan_to_num(np.sum((flat[:, None] - feet) ** 2, axis=-1), nan=np.inf), axis=1)
    outline = feet[np.arange(len(flat)), nearest]
    return np.where(inside[:, None], flat, outline).reshape(points.shape)


def _coverage(mesh: Mesh, points: np.ndarray) -> float:
    """The fraction of the skin `mesh`'s area (its elements, by centroid) within
    `_COVERED_RADII` of its equivalent radius (that of a disc of its area) of some point of
    `points` (K, D), m: how much of the skin presses read there tell about."""
    reach = _COVERED_RADII * math.sqrt(mesh.element_areas.sum() / math.pi)
    centroids = mesh.nodes[mesh.triangles].mean(axis=1)
    near = scipy.spatial.cKDTree(points).query(centroids, distance_upper_bound=reach)[0] < reach
    return float(mesh.element_areas[near].sum() / mesh.element_areas.sum())


def _spread(points: np.ndarray) -> float:
    """The RMS distance, m, of `points` (K, D) from their mean (at least 1 um)."""
    return float(max(np.sqrt(np.mean(np.sum((points - points.mean(0)) ** 2, axis=1))), 1e-6))


def _terms(points: np.ndarray, degree: int) -> np.ndarray:
    """(..., n_terms) the monomials of total degree at most `degree` in the coordinates of
    positions (..., 2) (x^i y^j) or (..., 3) (x^i y^j z^k), by total degree."""
    if points.shape[-1] == 2:
        powers = [(i, total - i) for total in range(degree + 1) for i in range(total + 1)]
    else:
        powers = [
            (i, j, total - i - j) for total in range(degree + 1) for i in range(total + 1) for j in range(total - i + 1)
        ]
    return np.stack([np.prod(points ** np.array(power), axis=-1) for power in powers], axis=-1)


def _similarity_of(frame: np.ndarray) -> tuple[float, np.ndarray]:
    """The scale and the rotation (2, 2) of the labels' frame `frame` (`_moved`)."""
    angle = frame[1]
    return math.exp(frame[0]), np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])


def _in_mesh_frame(points: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """(..., 2) labels'-frame `points` in the mesh's frame under `frame` (`_moved`)."""
    scale, rotation = _similarity_of(frame)
    return scale * (points * [1.0, frame[4]]) @ rotation.T + frame[2:4]


def _leave_one_out_errors(
    read: np.ndarray, labelled: np.ndarray, degree: int | None, surface: Mesh | None = None
) -> np.ndarray:
    """(K,) the distance, m, between each labelled position and the map of degree `degree`
    fitted without it (on a curved skin's `surface`, refitted without each in turn, taken onto
    it, and the distance along it: `diffeit.mesh.surface_distance`; on a flat sheet through the
    fit's hat matrix)."""
    if degree is None:
        return np.linalg.norm(read - labelled, axis=1) if surface is None else surface_distance(surface, read, labelled)
    length = _spread(labelled)
    terms = _terms(read / length, degree)
    shift = (labelled - read) / length
    if surface is not None:
        mapped = np.empty_like(read)
        for k in range(len(read)):
            others = np.arange(len(read)) != k
            coefficients, *_ = np.linalg.lstsq(terms[others], shift[others], rcond=_MAP_RCOND)
            mapped[k] = read[k] + terms[k] @ coefficients * length
        return surface_distance(surface, onto_surface(surface, mapped), labelled)
    return np.linalg.norm(_held_out_residuals(terms, shift), axis=1) * length
