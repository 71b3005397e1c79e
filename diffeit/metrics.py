"""Figures of merit of images: peak, half-amplitude set, size, position error, shape
deformation, artifacts, cross-sections, correlation, and GREIT's figures of merit.

An image is a conductivity change dsigma (S/sq, or any unit: values come back in the image's
unit) on a geometry of cells:

- a `diffeit.Mesh`: one value per element, shape (E,); or
- a `diffeit.render.PixelGrid`: one value per pixel, shape (n_rows, n_columns); only pixels in
  `grid.mask` count (values off the mask are ignored, so NaN there is fine).
  `pixel_grid(mesh, 32)` is the grid of `GREIT(model, grid=32)`.

Notation: cell k has area a_k (m^2; for a pixel its area inside the domain), centre c_k (m;
element centroid or pixel centre) and value x_k.

- Peak: p = x_k* with k* = argmax_k |x_k|, signed (a touch's conductivity drop gives p < 0).
- Amplitude set at fraction f, "on the peak's side": S_f = {k : sign(p) x_k >= f |p|}; the
  half-amplitude set is S = S_(1/2) (docs/science.md#figures-of-merit).
- Reconstructed size: area A = sum_(k in S) a_k (m^2) and equivalent radius r = sqrt(A / pi) (m).
- Centroid c = sum_(k in S) a_k c_k / A; position error |c - c_true| (m) (docs/science.md#figures-of-merit).
- Shape deformation SD = sum_(k in S) a_k (1 - phi_k) / A, phi_k the fraction of cell k inside
  the disc of radius r about c (for a pixel: of the whole pixel, also where it leaves the domain;
  weighted by a_k, its area inside): the part of S outside the circle of equal area centred on it
  (0 for a disc, 1 - 1/sqrt(2) ... for elongated sets; in [0, 1)).
- Components: the connected components of S, cells joined when they share an edge (a corner
  is not enough). Each has its own area, centroid and peak.
- Targets and artifacts: with K true centres, the components are matched to the targets by the
  assignment (Hungarian, `scipy.optimize.linear_sum_assignment`) that, among those with the
  most pairs at most `max_distance` apart, minimises the sum of distances target centre -
  component centroid; farther pairs are left unmatched; every unmatched component is an artifact.
- Correlation: Pearson, area-weighted (docs/science.md#figures-of-merit).

GREIT's figures (Adler et al. 2009, "GREIT: a unified approach to 2D linear EIT reconstruction
of lung images", Physiol. Meas. 30 S35) use the quarter-amplitude set by default: see
`greit_figures`.

Validation: a wrong shape, a non-finite value (in the mask) or an all-zero image (no peak, hence
no half-amplitude set) raises ValueError naming the problem.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import equinox as eqx
import numpy as np
import scipy.optimize
import scipy.sparse
import scipy.sparse.csgraph

from .mesh import Mesh, disc_fraction, element_adjacency, locate, onto_surface, surface_distance

if TYPE_CHECKING:
    from .render import PixelGrid

    Geometry = Mesh | PixelGrid

# Sub-samples per pixel side for the fraction of a pixel inside a disc (midpoint rule, as
# disc_fraction's 8^2 sub-triangles for elements).
_PIXEL_SAMPLES = 8


# --- Cells: the one view of meshes and pixel grids the metrics need ----------------------------


@dataclass(frozen=True)
class _Cells:
    """The cells of a geometry that carry values: areas (n,) m^2, centres (n, 2) m, the pairs of
    cells sharing an edge (first, second), and the values (n,) of one image."""

    areas: np.ndarray
    centres: np.ndarray
    first: np.ndarray
    second: np.ndarray
    values: np.ndarray


def _is_mesh(geometry) -> bool:
    if isinstance(geometry, Mesh):
        return True
    if all(hasattr(geometry, name) for name in ("mask", "pixel_areas", "pixel_centres", "x_edges", "y_edges")):
        return False
    raise ValueError(f"geometry must be a diffeit.Mesh or a diffeit.render.PixelGrid; got {type(geometry).__name__}")


def _cells(geometry: Geometry, image: np.ndarray, name: str = "image") -> _Cells:
    image = np.asarray(image, dtype=float)
    if _is_mesh(geometry):
        if image.shape != (geometry.n_elements,):
            raise ValueError(f"{name} has shape {image.shape}; expected ({geometry.n_elements},), one value an element")
        first, second, _ = element_adjacency(geometry)
        cells = _Cells(geometry.element_areas, geometry.element_centroids, first, second, image)
    else:
        if image.shape != geometry.mask.shape:
            raise ValueError(f"{name} has shape {image.shape}; expected {geometry.mask.shape}, one value a pixel")
        cells = _Cells(
            geometry.pixel_areas[geometry.mask],
            geometry.pixel_centres[geometry.mask],
            *_pixel_adjacency(geometry.mask),
            image[geometry.mask],
        )
    if not np.all(np.isfinite(cells.values)):
        raise ValueError(f"{name} is not finite (NaN or inf) at {np.count_nonzero(~np.isfinite(cells.values))} cells")
    return cells


def _pixel_adjacency(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of `mask` pixels sharing an edge, as indices into the pixels of `mask` (row-major)."""
    index = np.full(mask.shape, -1)
    index[mask] = np.arange(np.count_nonzero(mask))
    right = mask[:, :-1] & mask[:, 1:]
    up = mask[:-1, :] & mask[1:, :]
    first = np.concatenate([index[:, :-1][right], index[:-1, :][up]])
    second = np.concatenate([index[:, 1:][right], index[1:, :][up]])
    return first, second


def _disc_fraction(geometry: Geometry, centre: np.ndarray, radius: float) -> np.ndarray:
    """(n,) fraction of each cell inside the disc |x - centre| < radius (midpoint rule)."""
    if _is_mesh(geometry):
        return disc_fraction(geometry, tuple(centre), radius)
    offsets = (np.arange(_PIXEL_SAMPLES) + 0.5) / _PIXEL_SAMPLES - 0.5
    dx, dy = np.diff(geometry.x_edges[:2])[0], np.diff(geometry.y_edges[:2])[0]
    sub = np.stack(np.meshgrid(offsets * dx, offsets * dy), axis=-1).reshape(-1, 2)
    points = geometry.pixel_centres[geometry.mask][:, None, :] + sub[None]
    return np.mean(np.linalg.norm(points - centre, axis=2) < radius, axis=1)


def _point(dimension: int) -> str:
    """How a point of `dimension` coordinates is written in messages."""
    return "(x, y)" if dimension == 2 else "(x, y, z)"


def _checked_centres(centres, name: str = "centres", dimension: int = 2) -> np.ndarray:
    array = np.asarray(centres, dtype=float)
    if array.ndim == 1:
        array = array[None]
    if array.ndim != 2 or array.shape[1] != dimension or len(array) == 0:
        raise ValueError(
            f"{name} must be one point {_point(dimension)} or a list of them (K, {dimension}) in metres; "
            f"got shape {np.shape(centres)}"
        )
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} must be finite; got {array.tolist()}")
    return array


def _checked_point(point, name: str, dimension: int = 2) -> np.ndarray:
    """(D,) one point (x, y), or (x, y, z) with `dimension` 3, in metres."""
    array = _checked_centres(point, name, dimension)
    if len(array) != 1:
        raise ValueError(f"{name} must be one point {_point(dimension)}; got {len(array)} points")
    return array[0]


# --- Peak and amplitude sets (no geometry needed) ----------------------------------------------


def peak(image: np.ndarray) -> float:
    """The peak of an image: its signed value of largest magnitude.

    p = x_k* with k* = argmax_k |x_k|, signed: a touch's conductivity drop gives p < 0. No
    geometry is needed: pass `image[grid.mask]` for a rendered image (NaN off the mask).

    Arguments:
        image: Any array of values (an element image (E,), a GREIT image), in any unit.

    Returns:
        p, in the image's unit.

    Raises:
        ValueError: For an empty image, non-finite values, or an all-zero image (no peak).
    """
    values = _checked_values(image)
    return float(values.flat[np.argmax(np.abs(values))])


def _checked_values(image: np.ndarray) -> np.ndarray:
    values = np.asarray(image, dtype=float)
    if values.size == 0:
        raise ValueError("image is empty")
    if not np.all(np.isfinite(values)):
        raise ValueError(f"image is not finite (NaN or inf) at {np.count_nonzero(~np.isfinite(values))} values")
    if not np.any(values):
        raise ValueError("image is all zero: it has no peak, hence no half-amplitude set")
    return values


def amplitude_set(image: np.ndarray, fraction: float) -> np.ndarray:
    """The amplitude set S_f: the values at or beyond a fraction of the peak, on the peak's side.

    S_f = {k : sign(p) x_k >= f |p|}, p the `peak`: for a negative peak, the values <= f p.
    Never empty (it holds the peak). No geometry is needed: pass `image[grid.mask]` for a
    rendered image.

    Arguments:
        image: Any array of values, in any unit.
        fraction: f, in (0, 1].

    Returns:
        A boolean array of `image`'s shape, True in S_f.

    Raises:
        ValueError: For a fraction outside (0, 1], an empty image, non-finite values, or an
            all-zero image (no peak).
    """
    if not (np.isfinite(fraction) and 0 < fraction <= 1):
        raise ValueError(f"fraction of the peak must be in (0, 1]; got {fraction}")
    values = _checked_values(image)
    top = values.flat[np.argmax(np.abs(values))]
    return values * np.sign(top) >= fraction * np.abs(top)


def half_amplitude_set(image: np.ndarray) -> np.ndarray:
    """The half-amplitude set S: the values at or beyond half the peak, on the peak's side.

    `amplitude_set(image, 0.5)`: for a negative peak p, the values <= p / 2.

    Arguments:
        image: Any array of values, in any unit.

    Returns:
        A boolean array of `image`'s shape, True in S.

    Raises:
        ValueError: For an empty image, non-finite values, or an all-zero image (no peak).
    """
    return amplitude_set(image, 0.5)


def _cell_set(cells: _Cells, fraction: float) -> np.ndarray:
    return amplitude_set(cells.values, fraction)


# --- Size, position, shape of the whole set ----------------------------------------------------


def integral(geometry: Geometry, image: np.ndarray) -> float:
    """The image integrated over the domain: sum_k a_k x_k.

    Arguments:
        geometry: The cells: a `diffeit.Mesh`, or a `diffeit.render.PixelGrid` (pixels off its
            mask are ignored).
        image: One value per cell, (E,) on a mesh or (n_rows, n_columns) on a grid, in any
            unit (for example dsigma in S/sq).

    Returns:
        The integral, in the image's unit times m^2.

    Raises:
        ValueError: For another geometry, an image of the wrong shape, or non-finite values (in
            the mask).
    """
    cells = _cells(geometry, image)
    return float(cells.areas @ cells.values)


def reconstructed_area(geometry: Geometry, image: np.ndarray, fraction: float = 0.5) -> float:
    """The area of the amplitude set: A = sum_(k in S_f) a_k.

    Arguments:
        geometry: The cells: a `diffeit.Mesh`, or a `diffeit.render.PixelGrid` (pixels off its
            mask are ignored).
        image: One value per cell, (E,) on a mesh or (n_rows, n_columns) on a grid, in any
            unit (for example dsigma in S/sq).
        fraction: f of the amplitude set S_f, in (0, 1]; default 1/2, the half-amplitude set.

    Returns:
        A, m^2.

    Raises:
        ValueError: For another geometry, an image of the wrong shape, non-finite values (in
            the mask), an all-zero image (no peak), or a fraction outside (0, 1].
    """
    cells = _cells(geometry, image)
    return float(cells.areas[_cell_set(cells, fraction)].sum())


def equivalent_radius(geometry: Geometry, image: np.ndarray, fraction: float = 0.5) -> float:
    """The equivalent radius of the amplitude set: r = sqrt(A / pi), the radius of a disc of its area.

    Arguments:
        geometry: The cells: a `diffeit.Mesh`, or a `diffeit.render.PixelGrid` (pixels off its
            mask are ignored).
        image: One value per cell, (E,) on a mesh or (n_rows, n_columns) on a grid, in any
            unit (for example dsigma in S/sq).
        fraction: f of the amplitude set S_f, in (0, 1]; default 1/2, the half-amplitude set.

    Returns:
        r, m.

    Raises:
        ValueError: For another geometry, an image of the wrong shape, non-finite values (in
            the mask), an all-zero image (no peak), or a fraction outside (0, 1].
    """
    return float(np.sqrt(reconstructed_area(geometry, image, fraction) / np.pi))


def half_amplitude_centroid(geometry: Geometry, image: np.ndarray) -> np.ndarray:
    """The area-weighted centroid of the half-amplitude set: c = sum_(k in S) a_k c_k / A.

    Arguments:
        geometry: The cells: a `diffeit.Mesh`, or a `diffeit.render.PixelGrid` (pixels off its
            mask are ignored).
        image: One value per cell, (E,) on a mesh or (n_rows, n_columns) on a grid, in any
            unit (for example dsigma in S/sq).

    Returns:
        (D,) c, m: (x, y) on a flat sheet or a pixel grid, (x, y, z) on a curved skin (inside
        the surface's chord: `diffeit.mesh.onto_surface` takes it onto the surface).

    Raises:
        ValueError: For another geometry, an image of the wrong shape, non-finite values (in
            the mask), or an all-zero image (no peak).
    """
    cells = _cells(geometry, image)
    chosen = _cell_set(cells, 0.5)
    areas = cells.areas[chosen]
    return areas @ cells.centres[chosen] / areas.sum()


def position_error(geometry: Geometry, image: np.ndarray, centre: Sequence[float]) -> float:
    """The position error: the distance |c - centre| from the true centre to the half-amplitude centroid.

    A distance (>= 0), not GREIT's signed radial error (`greit_figures`).

    Arguments:
        geometry: The cells: a `diffeit.Mesh`, or a `diffeit.render.PixelGrid` (pixels off its
            mask are ignored).
        image: One value per cell, (E,) on a mesh or (n_rows, n_columns) on a grid, in any
            unit (for example dsigma in S/sq).
        centre: The true centre (x, y), m; on a curved skin (x, y, z), on its surface.

    On a curved skin the centroid (inside the surface's chord) is first taken onto the surface
    (`diffeit.mesh.onto_surface`), and the distance is measured along the surface
    (`diffeit.mesh.surface_distance`: the geodesic on a sphere, to fourth order in the chord
    over the radius of curvature elsewhere; the straight line is shorter by about
    d^2 / (24 rho^2) of it, 0.3% for 10 mm on a 40 mm forearm).

    Returns:
        |c - centre|, m.

    Raises:
        ValueError: For a centre that is not one finite point of the geometry's dimension,
            another geometry, an image of the wrong shape, non-finite values (in the mask), or
            an all-zero image.
    """
    dimension = geometry.nodes.shape[1] if _is_mesh(geometry) else 2
    true_centre = _checked_point(centre, "centre", dimension)
    found = half_amplitude_centroid(geometry, image)
    if dimension == 3:
        return float(surface_distance(geometry, onto_surface(geometry, found), true_centre))
    return float(np.linalg.norm(found - true_centre))


def transition_width(geometry: Geometry, image: np.ndarray, edge_length: float) -> float:
    """The edge blur of an image: the width of its transition from 10% to 90% of the peak.

    The area of the cells between 10% and 90% of the peak p (on the peak's side),
    sum_(k : 0.1 <= x_k / p <= 0.9) a_k, divided by the true edge's length. A sharp edge gives
    about one cell's width.

    Arguments:
        geometry: The cells: a `diffeit.Mesh`, or a `diffeit.render.PixelGrid` (pixels off its
            mask are ignored).
        image: One value per cell, (E,) on a mesh or (n_rows, n_columns) on a grid, in any
            unit (for example dsigma in S/sq).
        edge_length: The length of the true target's edge, m (2 pi r for a disc of radius r).

    Returns:
        The transition width, m.

    Raises:
        ValueError: For an edge length that is not positive, another geometry, an image of
            the wrong shape, non-finite values (in the mask), or an all-zero image.
    """
    if not (np.isfinite(edge_length) and edge_length > 0):
        raise ValueError(f"edge_length must be positive (m); got {edge_length}")
    cells = _cells(geometry, image)
    relative = cells.values / peak(cells.values)
    return float(cells.areas[(relative >= 0.1) & (relative <= 0.9)].sum() / edge_length)


def shape_deformation(geometry: Geometry, image: np.ndarray, fraction: float = 0.5) -> float:
    """The shape deformation of the amplitude set: the part of its area outside a disc of equal area.

    SD = sum_(k in S_f) a_k (1 - phi_k) / A, with phi_k the part of cell k inside the disc of
    area A centred on the set's centroid (midpoint rule; on a pixel grid, of the whole pixel,
    weighted by its area inside the domain). 0 for a disc up to the cells' resolution.

    Arguments:
        geometry: The cells: a `diffeit.Mesh`, or a `diffeit.render.PixelGrid` (pixels off its
            mask are ignored).
        image: One value per cell, (E,) on a mesh or (n_rows, n_columns) on a grid, in any
            unit (for example dsigma in S/sq).
        fraction: f of the amplitude set S_f, in (0, 1]; default 1/2, the half-amplitude set.

    Returns:
        SD, dimensionless, in [0, 1).

    Raises:
        ValueError: For another geometry, an image of the wrong shape, non-finite values (in
            the mask), an all-zero image (no peak), or a fraction outside (0, 1].
    """
    cells = _cells(geometry, image)
    chosen = _cell_set(cells, fraction)
    return _deformation(geometry, cells, chosen)


def _deformation(geometry: Geometry, cells: _Cells, chosen: np.ndarray) -> float:
    areas = cells.areas[chosen]
    area = areas.sum()
    centroid = areas @ cells.centres[chosen] / area
    inside = _disc_fraction(geometry, centroid, np.sqrt(area / np.pi))[chosen]
    return float(areas @ (1 - inside) / area)


# --- Components, targets, artifacts ------------------------------------------------------------


@dataclass(frozen=True)
class Components:
    """The connected components of an amplitude set (`amplitude_components`).

    Cells are joined when they share an edge (a corner is not enough). The K components are
    ordered by decreasing area.

    Attributes:
        labels: The image's shape: the component of each cell, -1 outside the set (and off a
            pixel grid's mask).
        areas: (K,) the area of each component, m^2.
        centroids: (K, D) the area-weighted centroid of each component, m ((x, y, z) inside
            the surface's chord on a curved skin).
        peaks: (K,) the signed value of largest magnitude in each component (the image's
            unit).
    """

    labels: np.ndarray
    areas: np.ndarray
    centroids: np.ndarray
    peaks: np.ndarray

    @property
    def count(self) -> int:
        """K, the number of components."""
        return len(self.areas)


def amplitude_components(geometry: Geometry, image: np.ndarray, fraction: float = 0.5) -> Components:
    """The connected components of the amplitude set S_f (the half-amplitude set by default).

    Arguments:
        geometry: The cells: a `diffeit.Mesh`, or a `diffeit.render.PixelGrid` (pixels off its
            mask are ignored).
        image: One value per cell, (E,) on a mesh or (n_rows, n_columns) on a grid, in any
            unit (for example dsigma in S/sq).
        fraction: f of the amplitude set S_f, in (0, 1]; default 1/2, the half-amplitude set.

    Returns:
        The `Components`, largest first.

    Raises:
        ValueError: For another geometry, an image of the wrong shape, non-finite values (in
            the mask), an all-zero image (no peak), or a fraction outside (0, 1].
    """
    cells = _cells(geometry, image)
    labels, _ = _components(cells, _cell_set(cells, fraction))
    return _summarise(geometry, cells, labels)


def _components(cells: _Cells, chosen: np.ndarray) -> tuple[np.ndarray, int]:
    """(n,) component of each chosen cell (-1 elsewhere), ordered by decreasing area."""
    both = chosen[cells.first] & chosen[cells.second]
    n = len(cells.values)
    graph = scipy.sparse.coo_array((np.ones(both.sum()), (cells.first[both], cells.second[both])), shape=(n, n))
    _, raw = scipy.sparse.csgraph.connected_components(graph, directed=False)
    # Unchosen cells are components of their own: keep only the labels of chosen cells.
    unique, relabelled = np.unique(raw[chosen], return_inverse=True)
    areas = np.bincount(relabelled, weights=cells.areas[chosen], minlength=len(unique))
    order = np.argsort(-areas, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    labels = np.full(n, -1)
    labels[chosen] = rank[relabelled]
    return labels, len(unique)


def _summarise(geometry: Geometry, cells: _Cells, labels: np.ndarray) -> Components:
    members = [labels == j for j in range(labels.max() + 1)]
    areas = np.array([cells.areas[m].sum() for m in members])
    dimension = cells.centres.shape[1]
    centroids = np.array([cells.areas[m] @ cells.centres[m] for m in members]).reshape(-1, dimension) / areas[:, None]
    peaks = np.array([cells.values[m][np.argmax(np.abs(cells.values[m]))] for m in members])
    return Components(labels=_to_image_shape(geometry, labels, -1), areas=areas, centroids=centroids, peaks=peaks)


def _to_image_shape(geometry: Geometry, values: np.ndarray, fill) -> np.ndarray:
    if _is_mesh(geometry):
        return values
    out = np.full(geometry.mask.shape, fill, dtype=values.dtype)
    out[geometry.mask] = values
    return out


class TargetFigures(eqx.Module):
    """Figures of merit per target of a multi-target image (`target_figures`).

    An equinox Module, as every result type. Arrays over the K targets, in the order of the
    centres given; a target that no component matched has `component` -1 and NaN in every
    other per-target figure (by definition, not by accident: test `matched`).

    Attributes:
        component: (K,) the index into `components` of each target's matched component.
        peak: (K,) the component's signed value of largest magnitude (the image's unit).
        area: (K,) the component's area, m^2.
        equivalent_radius: (K,) sqrt(area / pi), m.
        centroid: (K, 2) the component's area-weighted centroid, m.
        position_error: (K,) |centroid - centre|, m.
        shape_deformation: (K,) SD of the component alone (dimensionless; module docstring).
        n_artifacts: The number of components matched to no target.
        components: All `Components` of the amplitude set.
    """

    component: np.ndarray
    peak: np.ndarray
    area: np.ndarray
    equivalent_radius: np.ndarray
    centroid: np.ndarray
    position_error: np.ndarray
    shape_deformation: np.ndarray
    n_artifacts: int
    components: Components

    @property
    def matched(self) -> np.ndarray:
        """(K,) whether each target was matched to a component."""
        return self.component >= 0


def target_figures(
    geometry: Geometry,
    image: np.ndarray,
    centres: Sequence[Sequence[float]],
    *,
    max_distance: float = np.inf,
    fraction: float = 0.5,
) -> TargetFigures:
    """Match the components of the amplitude set to the true targets and measure each match.

    The components of S_f (the half-amplitude set by default) are assigned to the targets
    (Hungarian): among the assignments with the most pairs at most `max_distance` apart, the
    one of least summed distance centre - component centroid; farther pairs are no match, and
    every unmatched component is an artifact. The threshold is a fraction of the image's
    overall peak, so a much weaker target may have no component of its own.

    Arguments:
        geometry: The cells: a `diffeit.Mesh`, or a `diffeit.render.PixelGrid` (pixels off its
            mask are ignored).
        image: One value per cell, (E,) on a mesh or (n_rows, n_columns) on a grid, in any
            unit (for example dsigma in S/sq).
        centres: The true centres, (K, 2) m, or one (x, y).
        max_distance: The farthest a component's centroid may lie from its target, m
            (default: no limit).
        fraction: f of the amplitude set S_f, in (0, 1]; default 1/2, the half-amplitude set.

    Returns:
        The `TargetFigures`.

    Raises:
        ValueError: For centres that are not finite points (x, y), a max_distance that is not
            positive, another geometry, an image of the wrong shape, non-finite values (in the
            mask), an all-zero image, or a fraction outside (0, 1].
    """
    centres = _checked_centres(centres)
    if not max_distance > 0:
        raise ValueError(f"max_distance must be positive (metres); got {max_distance}")
    cells = _cells(geometry, image)
    chosen = _cell_set(cells, fraction)
    labels, _ = _components(cells, chosen)
    components = _summarise(geometry, cells, labels)
    distances = np.linalg.norm(centres[:, None, :] - components.centroids[None, :, :], axis=2)
    # Pairs beyond max_distance cost more than any set of allowed pairs, so the assignment first
    # maximises the number of matches within reach, then minimises their summed distance.
    allowed = distances <= max_distance
    forbidden = 1.0 + len(centres) * float(np.max(distances, where=allowed, initial=0.0))
    targets, matched = scipy.optimize.linear_sum_assignment(np.where(allowed, distances, forbidden))
    close = allowed[targets, matched]
    component = np.full(len(centres), -1)
    component[targets[close]] = matched[close]

    k = len(centres)
    figures = {name: np.full(k, np.nan) for name in ("peak", "area", "position_error", "shape_deformation")}
    centroid = np.full((k, 2), np.nan)
    for target in np.flatnonzero(component >= 0):
        j = component[target]
        figures["peak"][target] = components.peaks[j]
        figures["area"][target] = components.areas[j]
        centroid[target] = components.centroids[j]
        figures["position_error"][target] = distances[target, j]
        figures["shape_deformation"][target] = _deformation(geometry, cells, labels == j)
    return TargetFigures(
        component=component,
        centroid=centroid,
        equivalent_radius=np.sqrt(figures["area"] / np.pi),
        n_artifacts=int(components.count - np.count_nonzero(component >= 0)),
        components=components,
        **figures,
    )


def count_artifacts(
    geometry: Geometry, image: np.ndarray, centres: Sequence[Sequence[float]], *, max_distance: float = np.inf
) -> int:
    """The number of artifacts: half-amplitude components matched to none of the targets.

    `target_figures(geometry, image, centres, max_distance=max_distance).n_artifacts`: the
    extra blobs.

    Arguments:
        geometry: The cells: a `diffeit.Mesh`, or a `diffeit.render.PixelGrid` (pixels off its
            mask are ignored).
        image: One value per cell, (E,) on a mesh or (n_rows, n_columns) on a grid, in any
            unit (for example dsigma in S/sq).
        centres: The true centres, (K, 2) m, or one (x, y).
        max_distance: The farthest a component's centroid may lie from its target, m
            (default: no limit).

    Returns:
        The number of artifacts.

    Raises:
        ValueError: As `target_figures`.
    """
    return target_figures(geometry, image, centres, max_distance=max_distance).n_artifacts


# --- Cross-section -----------------------------------------------------------------------------


@dataclass(frozen=True)
class CrossSection:
    """Values along a straight line through the domain (`cross_section`).

    Attributes:
        distance: (n,) the signed position of each point along the line from its anchor point,
            m, increasing.
        points: (n, 2) the points, m.
        values: (n,) the value of the cell containing each point (the image's unit).
    """

    distance: np.ndarray
    points: np.ndarray
    values: np.ndarray


def cross_section(
    geometry: Geometry,
    image: np.ndarray,
    *,
    through: Sequence[float] | None = None,
    direction: Sequence[float] = (1.0, 0.0),
    n_points: int = 201,
) -> CrossSection:
    """The profile of an image along a straight line, by point sampling.

    `n_points` points evenly spaced over the line's chord of the geometry's bounding box are
    kept where they lie in the domain (a mesh triangle, or a pixel of the mask); each takes the
    value of the cell containing it. The default line runs through the peak along x: the
    dissertation's Fig. 5.1.

    Arguments:
        geometry: The cells: a `diffeit.Mesh`, or a `diffeit.render.PixelGrid` (pixels off its
            mask are ignored).
        image: One value per cell, (E,) on a mesh or (n_rows, n_columns) on a grid, in any
            unit (for example dsigma in S/sq).
        through: A point (x, y) of the line, m, its anchor (distance 0); default the centre of
            the peak's cell.
        direction: The line's direction, any finite non-zero (dx, dy).
        n_points: How many points to sample along the chord (an integer >= 2), before those
            outside the domain are dropped.

    Returns:
        The `CrossSection`.

    Raises:
        ValueError: For `n_points` not an integer >= 2, a zero or non-finite direction, a
            `through` that is not one finite point, a line that misses the domain, another
            geometry, an image of the wrong shape, or non-finite values (in the mask).
    """
    cells = _cells(geometry, image)
    if not (isinstance(n_points, int | np.integer) and n_points >= 2):
        raise ValueError(f"n_points must be an integer >= 2; got {n_points!r}")
    direction = np.asarray(direction, dtype=float)
    if direction.shape != (2,) or not np.all(np.isfinite(direction)) or not np.any(direction):
        raise ValueError(f"direction must be a finite non-zero (dx, dy); got {direction.tolist()}")
    direction = direction / np.linalg.norm(direction)
    peak_centre = cells.centres[np.argmax(np.abs(cells.values))]
    anchor = peak_centre if through is None else _checked_point(through, "through")
    low, high = _bounding_box(geometry)
    # The segment of the line inside the bounding box (slab method).
    moving = direction != 0
    enter, leave = (low - anchor)[moving] / direction[moving], (high - anchor)[moving] / direction[moving]
    start, stop = np.max(np.minimum(enter, leave)), np.min(np.maximum(enter, leave))
    if start >= stop or np.any(~moving & ((anchor < low) | (anchor > high))):
        raise ValueError(f"the line through {anchor.tolist()} along {direction.tolist()} misses the domain")
    distance = np.linspace(start, stop, n_points)
    points = anchor + distance[:, None] * direction
    index = _locate(geometry, points)
    kept = index >= 0
    if not np.any(kept):
        raise ValueError(f"the line through {anchor.tolist()} along {direction.tolist()} misses the domain")
    return CrossSection(distance=distance[kept], points=points[kept], values=cells.values[index[kept]])


def _bounding_box(geometry: Geometry) -> tuple[np.ndarray, np.ndarray]:
    if _is_mesh(geometry):
        return geometry.nodes.min(axis=0), geometry.nodes.max(axis=0)
    return np.array([geometry.x_edges[0], geometry.y_edges[0]]), np.array([geometry.x_edges[-1], geometry.y_edges[-1]])


def _locate(geometry: Geometry, points: np.ndarray) -> np.ndarray:
    """(P,) the index of the cell containing each point (among the value-carrying cells), -1 off
    the domain."""
    if _is_mesh(geometry):
        return locate(geometry, points)
    n_rows, n_columns = geometry.mask.shape
    column = np.floor((points[:, 0] - geometry.x_edges[0]) / np.diff(geometry.x_edges[:2])[0]).astype(int)
    row = np.floor((points[:, 1] - geometry.y_edges[0]) / np.diff(geometry.y_edges[:2])[0]).astype(int)
    on_grid = (column >= 0) & (column < n_columns) & (row >= 0) & (row < n_rows)
    index = np.full(geometry.mask.shape, -1)
    index[geometry.mask] = np.arange(np.count_nonzero(geometry.mask))
    return np.where(on_grid, index[np.clip(row, 0, n_rows - 1), np.clip(column, 0, n_columns - 1)], -1)


# --- Correlation -------------------------------------------------------------------------------


def correlation(geometry: Geometry, truth: np.ndarray, image: np.ndarray) -> float:
    """The area-weighted Pearson correlation of a true and a reconstructed image.

    cov_w(truth, image) / sqrt(var_w(truth) var_w(image)) with weights a_k / sum a_k
    (docs/science.md#figures-of-merit).

    Arguments:
        geometry: The cells: a `diffeit.Mesh`, or a `diffeit.render.PixelGrid` (pixels off its
            mask are ignored).
        truth: The true image, one value per cell.
        image: The reconstructed image, one value per cell, on the same geometry.

    Returns:
        The correlation, in [-1, 1].

    Raises:
        ValueError: For another geometry, images of the wrong shape, non-finite values (in the
            mask), or a constant image (zero variance).
    """
    truth_cells = _cells(geometry, truth, "truth")
    cells = _cells(geometry, image)
    for name, values in (("truth", truth_cells.values), ("image", cells.values)):
        if np.ptp(values) == 0:
            raise ValueError(f"correlation is undefined for a constant {name} (zero variance)")
    weights = cells.areas / cells.areas.sum()
    a = truth_cells.values - weights @ truth_cells.values
    b = cells.values - weights @ cells.values
    return float((weights @ (a * b)) / np.sqrt((weights @ a**2) * (weights @ b**2)))


# --- GREIT figures of merit --------------------------------------------------------------------


@dataclass(frozen=True)
class GreitFigures:
    """GREIT's figures of merit of one single-target image (`greit_figures`).

    Attributes:
        amplitude_response: AR, the image's integral over the truth's (1 for a perfect
            amplitude; dimensionless).
        radial_position_error: PE = |centre - o| - |q - o|, m: signed, > 0 when the image is
            pulled towards the middle.
        resolution: RES = sqrt(A_q / A_0), dimensionless.
        shape_deformation: SD of the amplitude set S_q, dimensionless, in [0, 1).
        ringing: RNG, the opposite-sign amplitude outside the equal-area disc over the
            amplitude inside it (>= 0, dimensionless).
    """

    amplitude_response: float
    radial_position_error: float
    resolution: float
    shape_deformation: float
    ringing: float


def greit_figures(
    geometry: Geometry, image: np.ndarray, centre: Sequence[float], truth: np.ndarray, *, fraction: float = 0.25
) -> GreitFigures:
    """Adler et al. (2009)'s figures of merit of an image of one target.

    With x_hat the image, S_q the amplitude set at `fraction` (GREIT: a quarter of the peak),
    A_q its area, q its centroid, A_0 the domain's area, o the domain's centroid and C the disc
    of area A_q centred on q (phi_k: part of cell k in C):

    - amplitude response AR = sum_k a_k x_hat_k / sum_k a_k truth_k (1 for a perfect amplitude);
    - position error PE = |centre - o| - |q - o| (m; radial: > 0 when the image is pulled towards
      the middle, the sign Adler et al. use; diffeit's position error is the distance instead);
    - resolution RES = sqrt(A_q / A_0);
    - shape deformation SD = sum_(k in S_q) a_k (1 - phi_k) / A_q;
    - ringing RNG = sum_k a_k (1 - phi_k) max(0, -s x_hat_k) / sum_k a_k phi_k s x_hat_k with
      s = sign(peak): the opposite-sign amplitude outside C over the amplitude inside C (>= 0;
      ValueError when the image inside C does not sum to the peak's sign).

    On a pixel grid phi_k is the fraction of the whole pixel inside C (the part of a rim pixel
    outside the domain counts), weighted by the pixel's area inside the domain.

    Arguments:
        geometry: The cells: a `diffeit.Mesh`, or a `diffeit.render.PixelGrid` (pixels off its
            mask are ignored).
        image: One value per cell, (E,) on a mesh or (n_rows, n_columns) on a grid, in any
            unit (for example dsigma in S/sq).
        centre: The target's true centre (x, y), m.
        truth: The true image, one value per cell, on the same geometry.
        fraction: The fraction of the peak of the amplitude set S_q, in (0, 1]; GREIT's is a
            quarter.

    Returns:
        The `GreitFigures`.

    Raises:
        ValueError: For a centre that is not one finite point, another geometry, images of the
            wrong shape, non-finite values (in the mask), an all-zero image, a fraction outside
            (0, 1], a truth that integrates to 0 (no amplitude response), or an image that
            inside C does not sum to the peak's sign (no ringing).
    """
    true_centre = _checked_point(centre, "centre")
    cells = _cells(geometry, image)
    truth_cells = _cells(geometry, truth, "truth")
    truth_integral = truth_cells.areas @ truth_cells.values
    if truth_integral == 0:
        raise ValueError("truth integrates to 0: the amplitude response is undefined")
    chosen = _cell_set(cells, fraction)
    area = cells.areas[chosen].sum()
    centroid = cells.areas[chosen] @ cells.centres[chosen] / area
    domain_centroid = cells.areas @ cells.centres / cells.areas.sum()
    inside = _disc_fraction(geometry, centroid, np.sqrt(area / np.pi))
    sign = np.sign(peak(cells.values))
    signed = sign * cells.values
    inside_amplitude = (cells.areas * inside) @ signed
    if inside_amplitude <= 0:
        raise ValueError(
            "the image inside the equal-area disc about the amplitude set's centroid is not of the peak's sign "
            "(it sums to <= 0 there): ringing is undefined"
        )
    return GreitFigures(
        amplitude_response=float(cells.areas @ cells.values / truth_integral),
        radial_position_error=float(
            np.linalg.norm(true_centre - domain_centroid) - np.linalg.norm(centroid - domain_centroid)
        ),
        resolution=float(np.sqrt(area / cells.areas.sum())),
        shape_deformation=float(cells.areas[chosen] @ (1 - inside[chosen]) / area),
        ringing=float((cells.areas * (1 - inside)) @ np.maximum(0.0, -signed) / inside_amplitude),
    )
