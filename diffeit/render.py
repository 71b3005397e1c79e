"""Element-wise images on a pixel grid: exact area-weighted averages, for figures and for metrics
computed on pixels.

The grid tiles the bounding box of the mesh with n_rows x n_columns equal pixels, row 0 at the
bottom (smallest y), as `diffeit.inverse.GREIT` lays out its images: `pixel_grid(mesh, 32)` is
the grid of `GREIT(model, grid=32)`, so the metrics of `diffeit.metrics` apply to GREIT images
through it. The value of pixel p is the area-weighted mean of the element values over the part
of p inside the domain,

    x_p = sum_e A_pe x_e / sum_e A_pe,    A_pe = area(pixel p ∩ triangle e)  (m^2),

with the overlap areas A_pe exact up to rounding (each pixel clipped against each triangle). It
is not point sampling: a pixel that straddles an element edge shows the mean of both elements,
and sum_p area_p x_p equals sum_e area_e x_e over the covered pixels. Pixels with less than
`min_coverage` of their area inside the domain are NaN (outside the image).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse

from ._arrays import StaticData, fingerprint, readonly
from .mesh import Mesh, pixel_overlaps, require_flat


@dataclass(eq=False)
class PixelGrid(StaticData):
    """A pixel grid over a mesh and the exact element-to-pixel averaging (module docstring).

    Build with `pixel_grid(mesh, grid, min_coverage)`. Static data, compared and hashed by the
    mesh, shape and coverage it was built from.

    Attributes:
        x_edges: (n_columns + 1,) pixel edges in x, metres.
        y_edges: (n_rows + 1,) pixel edges in y, metres (row 0 at the bottom).
        mask: (n_rows, n_columns) boolean: pixels at least `min_coverage` inside the domain
            (the image).
        pixel_areas: (n_rows, n_columns) each pixel's area inside the domain, m^2 (0 off
            `mask`).
        element_to_pixel: Sparse (n_rows * n_columns, E): rows of `mask` pixels sum to 1,
            other rows are 0.
        n_elements: E, the number of elements of the mesh it was built on.
        fingerprint: A digest of the mesh, shape and coverage.
    """

    x_edges: np.ndarray
    y_edges: np.ndarray
    mask: np.ndarray
    pixel_areas: np.ndarray
    element_to_pixel: scipy.sparse.csr_array = field(repr=False)
    n_elements: int
    fingerprint: bytes = field(repr=False)

    @property
    def shape(self) -> tuple[int, int]:
        """(n_rows, n_columns), the image's shape in pixels."""
        return self.mask.shape

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max), metres: `imshow(image, origin="lower", extent=grid.extent)`."""
        return (float(self.x_edges[0]), float(self.x_edges[-1]), float(self.y_edges[0]), float(self.y_edges[-1]))

    @property
    def pixel_centres(self) -> np.ndarray:
        """(n_rows, n_columns, 2) pixel centres (x, y), metres."""
        x = 0.5 * (self.x_edges[1:] + self.x_edges[:-1])
        y = 0.5 * (self.y_edges[1:] + self.y_edges[:-1])
        return np.stack(np.meshgrid(x, y), axis=-1)

    def render(self, image: np.ndarray) -> np.ndarray:
        """Element values as pixels: area-weighted means, NaN off `mask`.

        Arguments:
            image: (E,) an element image or (T, E) a batch, finite, in any unit.

        Returns:
            (n_rows, n_columns) or (T, n_rows, n_columns), in the input's unit.

        Raises:
            ValueError: For an image of the wrong shape or not finite.
        """
        values = np.asarray(image, dtype=float)
        if values.ndim not in (1, 2) or values.shape[-1] != self.n_elements:
            raise ValueError(
                f"element image has shape {values.shape}; expected ({self.n_elements},) or (T, {self.n_elements})"
            )
        if not np.all(np.isfinite(values)):
            raise ValueError("element image is not finite (NaN or inf)")
        pixels = (self.element_to_pixel @ values.T).T.reshape(*values.shape[:-1], *self.shape)
        return np.where(self.mask, pixels, np.nan)

    def to_elements(self, pixels: np.ndarray) -> np.ndarray:
        """Pixels as element values: each element the overlap-weighted mean of the pixels it meets.

        The weights are the overlap areas A_pe; an element that meets none of `mask`'s pixels
        gets 0. Pixels off `mask` are ignored (they may be NaN). A constant image maps to the
        same constant on every element it covers.

        Arguments:
            pixels: (n_rows, n_columns) a pixel image or (T, n_rows, n_columns) a batch, in any
                unit, finite on `mask`.

        Returns:
            (E,) or (T, E), in the input's unit.

        Raises:
            ValueError: For an image of the wrong shape or not finite inside the mask.
        """
        values = np.asarray(pixels, dtype=float)
        if values.ndim not in (2, 3) or values.shape[-2:] != self.shape:
            raise ValueError(f"pixel image has shape {values.shape}; expected {self.shape} or (T, *{self.shape})")
        flat = np.where(self.mask, values, 0.0).reshape(-1, self.mask.size)
        if not np.all(np.isfinite(flat)):
            raise ValueError("pixel image is not finite (NaN or inf) inside the mask")
        # element_to_pixel holds A_pe / covered_p; times covered_p (pixel_areas) it is A_pe.
        overlap = scipy.sparse.csc_array(self.element_to_pixel.multiply(self.pixel_areas.reshape(-1, 1)))
        weights = np.asarray(overlap.sum(axis=0)).ravel()
        elements = (overlap.T @ flat.T).T / np.where(weights > 0, weights, 1.0)
        return elements.reshape(*values.shape[:-2], self.n_elements)


def pixel_grid(mesh: Mesh, grid: int | tuple[int, int] = 64, min_coverage: float = 0.5) -> PixelGrid:
    """The pixel grid over the bounding box of a mesh, with exact overlap areas (module docstring).

    Building costs one clipping per (pixel, triangle) pair whose boxes meet: build once and
    `render` many images.

    Arguments:
        mesh: The mesh.
        grid: n for an n x n grid, or (n_rows, n_columns); positive integers.
        min_coverage: The fraction of a pixel's area, in [0, 1), that must lie in the domain
            for it to be in the image (0: any overlap; 0.5, the default, as GREIT).

    Returns:
        The `PixelGrid`.

    Raises:
        ValueError: For a grid that is not a positive integer or a pair of them, a
            `min_coverage` outside [0, 1), or a surface mesh (a curved skin).
    """
    require_flat(mesh, "pixel_grid (GREIT and rendered images)")
    shape = (grid, grid) if np.ndim(grid) == 0 else tuple(grid)
    if len(shape) != 2 or not all(isinstance(n, int | np.integer) and n >= 1 for n in shape):
        raise ValueError(f"grid must be a positive integer or a pair of them (n_rows, n_columns); got {grid!r}")
    if not (np.isfinite(min_coverage) and 0 <= min_coverage < 1):
        raise ValueError(f"min_coverage is a fraction of a pixel's area in [0, 1); got {min_coverage}")
    low, high = mesh.nodes.min(axis=0), mesh.nodes.max(axis=0)
    x_edges = np.linspace(low[0], high[0], shape[1] + 1)
    y_edges = np.linspace(low[1], high[1], shape[0] + 1)
    overlap = pixel_overlaps(mesh, x_edges, y_edges)
    covered = overlap.sum(axis=1)
    pixel_area = (x_edges[1] - x_edges[0]) * (y_edges[1] - y_edges[0])
    inside = (covered > 0) & (covered >= min_coverage * pixel_area)
    weights = scipy.sparse.diags_array(np.divide(1.0, covered, out=np.zeros_like(covered), where=inside)) @ overlap
    return PixelGrid(
        x_edges=readonly(x_edges),
        y_edges=readonly(y_edges),
        mask=readonly(inside.reshape(shape)),
        pixel_areas=readonly(np.where(inside, covered, 0.0).reshape(shape)),
        element_to_pixel=scipy.sparse.csr_array(weights),
        n_elements=mesh.n_elements,
        fingerprint=fingerprint(mesh.fingerprint, np.asarray(shape), np.float64(min_coverage)),
    )


def render(mesh: Mesh, image: np.ndarray, grid: int | tuple[int, int] = 64, min_coverage: float = 0.5) -> np.ndarray:
    """Element values on a mesh as pixels: `pixel_grid(mesh, grid, min_coverage).render(image)`.

    Exact area-weighted means, NaN outside the domain. For many images build the grid once.

    Arguments:
        mesh: The mesh.
        image: (E,) an element image or (T, E) a batch, finite, in any unit.
        grid: n for an n x n grid, or (n_rows, n_columns).
        min_coverage: The fraction of a pixel's area, in [0, 1), that must lie in the domain.

    Returns:
        (n_rows, n_columns) or (T, n_rows, n_columns), in the input's unit.

    Raises:
        ValueError: As `pixel_grid` and `PixelGrid.render`.
    """
    return pixel_grid(mesh, grid, min_coverage).render(image)
