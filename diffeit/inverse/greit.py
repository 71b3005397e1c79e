"""GREIT: a linear difference reconstructor on a fixed pixel grid, trained on simulated targets.

After Adler et al. (2009), "GREIT: a unified approach to 2D linear EIT reconstruction of lung
images", Physiol. Meas. 30 S35, and EIDORS's `mk_GREIT_model`. Instead of inverting a forward
model on the mesh, the reconstruction matrix R is fitted so that it maps the simulated
voltages of many small targets, spread uniformly over the domain, onto chosen "desired" images
of those targets on a pixel grid: blurred copies of the targets, so that every position gets
the same point spread function (the same resolution and position error), and a noise term keeps
the noise amplification in check.
"""

from __future__ import annotations

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize
import scipy.sparse
import scipy.special
from scipy.spatial import cKDTree

from .._arrays import IdentityModule
from .._threads import host_algebra
from ..forward import ForwardModel
from ..mesh import Mesh, distance_to_segments, element_sample_points, locate
from ..render import PixelGrid, pixel_grid
from .linearised import LinearisedProblem, apply_matrix, check_frames
from .priors import Tikhonov

DEFAULT_HYPERPARAMETER = 0.3
_TRAININGS = ("linearised", "nonlinear")
# A pixel belongs to the image when at least this fraction of its area lies in the domain.
_INSIDE_FRACTION = 0.5
# Midpoint rule on 8^2 sub-triangles for the targets' element fractions (as disc_fraction).
_TARGET_SAMPLING_LEVEL = 8
# The noise-figure search scans the hyperparameter over these decades, then refines a crossing.
_NOISE_FIGURE_SCAN = np.logspace(-8, 4, 121)


class GREIT(IdentityModule):
    """GREIT-style linear difference reconstruction onto a fixed pixel grid.

    **The grid.** `grid` x `grid` pixels (or `(n_rows, n_columns)`) tile the bounding box of the
    mesh: after construction `grid` is that `diffeit.render.PixelGrid` (`pixel_grid(mesh, grid)`),
    which gives the pixel centres, the mask, the pixel areas, the extent and the rendering of
    element fields; `diffeit.metrics` (e.g. `position_error(rec.grid, image, centre)`) reads
    GREIT images through it. `image[i, j]` is the pixel at x = `grid.pixel_centres[i, j, 0]`,
    y = `grid.pixel_centres[i, j, 1]`, row 0 at the bottom (smallest y):
    `plt.imshow(image, origin="lower", extent=rec.grid.extent)`. A pixel is in the image
    (`grid.mask`) when at least half of its area lies in the domain (exact triangle-square
    overlap areas). Pixels outside are exactly 0 in every image: EIDORS makes them NaN, but
    diffeit returns no NaN; use `grid.mask` (e.g. `np.where(rec.grid.mask, image, np.nan)`
    for a figure).

    **Training.** `n_targets` discs of radius r = `target_radius` * R, where R is half the
    larger side of the bounding box (R = 1 m on the unit disc), at positions drawn uniformly
    (seeded by `seed`) among those whose disc lies wholly in the domain. Each target k is a
    relative conductivity change x_k = dsigma / background on the mesh (element fractions
    inside the disc), scaled to unit strength: the integral of x_k over the sheet equals the
    sheet's area A. Its measurement is, in the normalised units of `LinearisedProblem`
    (absolute differences),

        y_k = J_n x_k,  J_n = diag(1/s) J diag(background),  s = RMS(V(background))   ("linearised")

    (one Jacobian for all targets), or, with `training="nonlinear"`, the simulated difference
    (V(background (1 + contrast chi_k)) - V(background)) / s scaled by the same unit-strength
    factor, all targets in one batched (`jax.vmap`) solve; `contrast` only matters there.
    Its desired image d_k is the target convolved with a Gaussian of standard deviation
    w = `blur` * R (the desired point spread function), averaged over each pixel exactly (the
    disc enters as the Gaussian of equal second moments, variance w^2 + r^2 / 4, which is
    accurate for r << w), so each desired image also integrates to A.

    **The matrix.** R_n minimises the mean training error plus the expected effect of noise,

        (1/K) sum_k ||d_k - R_n y_k||^2 + lambda^2 ||R_n||_F^2
            = E_k E_n ||d_k - R_n (y_k + n)||^2,  n ~ N(0, lambda^2 I),

    summed over the pixels in the mask, so that

        R_n = D Y^T (Y Y^T + K lambda^2 I)^-1 = D Y^T U diag(1 / (m_i + K lambda^2)) U^T,

    with Y (n_meas, K) the training measurements, D (n_pixels, K) the desired images and
    Y Y^T = U diag(m_i) U^T: a measurement-space computation (an n_meas x n_meas
    eigenproblem), and no n_pixels x n_pixels or n_elem x n_elem matrix. Directions with m_i
    at rounding level (reciprocal readings repeat each other) are dropped. Each
    pixel's row is an independent ridge regression, so the number of pixels does not change
    R_n, and dividing by K makes lambda independent of the number of targets.

    **The hyperparameter** lambda is unit-free: it is the standard deviation of independent
    measurement noise, as a fraction of RMS(V_reference) ("p%" noise, docs/science.md#noise, is lambda = p/100),
    per unit target strength. An object whose relative change integrates to S times the sheet's
    area (S = 9 * 0.04 = 0.36 for a disc of radius 0.2 and 10x conductivity on the unit disc,
    linearised; its true response is weaker, about 1.6 / 9 of that) seen with p% noise is
    matched by lambda = p / (100 S) (a touch of radius 0.1 and -30% on the unit disc, S = 0.003,
    with 1% noise: lambda about 3). It does not move with the drive current, the background,
    the number of targets or pixels, or (linearised) the target contrast. EIDORS's `weight` w
    enters as (Y Y^T + (w mean|Y|)^2 I) with EIDORS's own normalisation (Y = V/V_ref - 1, no
    1/K), so lambda ~ w mean|Y| / sqrt(K) only roughly; to carry a setting over, match the
    noise figure instead.

    **Noise figure.** Give `noise_figure` instead of `hyperparameter` (EIDORS's usual way,
    e.g. 0.5) and lambda is chosen so that the reconstructor has that noise figure: the
    training target nearest the domain's centroid is the signal y_0, and (Adler and Guardo 1996,
    EIDORS `calc_noise_figure`, amplitude form, independent equal noise in normalised units)

        NF = SNR_in / SNR_out = mean_m |y_0m| sqrt(mean_p sum_m R_pm^2) / mean_p |(R_n y_0)_p|

    over the measurements m and the pixels p in the mask. Larger lambda, smaller NF. Either way,
    both fields hold the values in effect after construction.

    **Units.** `reconstruct` gives dsigma in S/sq per pixel: the relative change times the
    pixel's background (the area-weighted mean of `background` over the pixel); `matrix` is in
    S/sq per volt.

    **Arguments:**

    - `model`: the forward model on which the targets are simulated (its mesh sets the domain).
    - `grid`: pixels per side, or (n_rows, n_columns); at least 2 each.
    - `hyperparameter`: lambda > 0, unit-free (above); default 0.3 (noise figure 0.87 on the
      16-electrode unit disc) unless `noise_figure` is given.
    - `noise_figure`: NF > 0 to choose lambda by; not together with `hyperparameter`.
    - `target_radius`: training target radius, a fraction of R (default 0.05).
    - `n_targets`: number of training targets K (default 500).
    - `blur`: standard deviation of the desired Gaussian point spread function, a fraction of
      R (default 0.15: half-amplitude diameter 2.35 * 0.15 = 0.35 R).
    - `background`: reference conductivity, scalar or (E,), S/sq (held by `problem`).
    - `training`: "linearised" (default) or "nonlinear" (above).
    - `contrast`: relative conductivity change of the nonlinear training targets, > -1, not 0.
    - `seed`: seed of the target positions.
    """

    problem: LinearisedProblem = eqx.field(repr=False)
    """The normalisation (J_n, s) at the background; its prior is not used."""
    grid: PixelGrid = eqx.field(static=True, repr=False)
    hyperparameter: float = eqx.field(static=True)
    noise_figure: float = eqx.field(static=True)
    target_radius: float = eqx.field(static=True)
    n_targets: int = eqx.field(static=True)
    blur: float = eqx.field(static=True)
    training: Literal["linearised", "nonlinear"] = eqx.field(static=True)
    contrast: float = eqx.field(static=True)
    seed: int = eqx.field(static=True)
    matrix: jax.Array = eqx.field(repr=False)
    """(n_rows * n_columns, n_meas) reconstruction matrix, S/sq per volt; rows of pixels
    outside the mask are zero. Pixels are in row-major (C) order of the image."""
    target_centres: np.ndarray = eqx.field(repr=False)
    """(K, 2) centres of the training targets, metres."""

    @host_algebra
    def __init__(
        self,
        model: ForwardModel,
        *,
        grid: int | tuple[int, int] = 32,
        hyperparameter: float | None = None,
        noise_figure: float | None = None,
        target_radius: float = 0.05,
        n_targets: int = 500,
        blur: float = 0.15,
        background: float | np.ndarray = 1.0,
        training: Literal["linearised", "nonlinear"] = "linearised",
        contrast: float = 0.1,
        seed: int = 0,
    ) -> None:
        _check_settings(hyperparameter, noise_figure, target_radius, n_targets, blur, training, contrast)
        self.target_radius, self.n_targets, self.blur = float(target_radius), int(n_targets), float(blur)
        self.training, self.contrast, self.seed = training, float(contrast), seed
        mesh = model.mesh
        self.grid = _image_grid(mesh, grid)
        self.problem = LinearisedProblem(model, Tikhonov(), background)
        size = 0.5 * float(np.max(np.ptp(mesh.nodes, axis=0)))  # R: the lengths below are fractions of it
        radius = self.target_radius * size
        self.target_centres = _target_positions(mesh, self.n_targets, radius, np.random.default_rng(seed))
        measurements = _training_measurements(self.problem, self.target_centres, radius, training, self.contrast)
        desired = _desired_images(self.grid, mesh, self.target_centres, radius, self.blur * size)
        fit = _RidgeFit(measurements, desired, _central_measurement(mesh, self.target_centres, measurements))
        if hyperparameter is None:
            hyperparameter = DEFAULT_HYPERPARAMETER if noise_figure is None else fit.solve(noise_figure)
        self.hyperparameter = float(hyperparameter)
        self.noise_figure = fit.noise_figure(self.hyperparameter)
        self.matrix = jnp.asarray(_pixel_matrix(self.grid, self.problem, fit.matrix(self.hyperparameter)))

    @property
    def model(self) -> ForwardModel:
        """The forward model the targets are simulated on."""
        return self.problem.model

    @property
    def shape(self) -> tuple[int, int]:
        """(n_rows, n_columns) of an image."""
        return self.grid.shape

    def reconstruct(self, voltage_difference: jax.Array) -> jax.Array:
        """Conductivity change dsigma (S/sq) per pixel for dV = V - V_reference (volts).

        `voltage_difference` is (n_meas,) or a batch (T, n_meas); the result is one image
        (n_rows, n_columns) or (T, n_rows, n_columns), exactly 0 outside the grid's mask, in the
        input's dtype. Works under jit and vmap, as `OneStep.reconstruct` does.
        """
        dv = check_frames(voltage_difference, self.model.n_measurements, "voltage differences")
        return apply_matrix(self.matrix, dv).reshape(*dv.shape[:-1], *self.shape)


def _check_settings(hyperparameter, noise_figure, target_radius, n_targets, blur, training, contrast) -> None:
    """Refuse settings out of range, naming them (the grid and background are checked where
    they are used)."""
    if hyperparameter is not None and noise_figure is not None:
        raise ValueError("give hyperparameter or noise_figure, not both: the noise figure chooses the hyperparameter")
    for name, value in (("hyperparameter", hyperparameter), ("noise_figure", noise_figure)):
        if value is not None and not (np.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be finite and positive; got {value}")
    for name, value in (("target_radius", target_radius), ("blur", blur)):
        if not (np.isfinite(value) and 0 < value < 1):
            raise ValueError(f"{name} is a fraction of half the domain's size, in (0, 1); got {value}")
    if not (isinstance(n_targets, int | np.integer) and n_targets >= 1):
        raise ValueError(f"n_targets must be a positive integer; got {n_targets!r}")
    if training not in _TRAININGS:
        raise ValueError(f"training must be one of {_TRAININGS}; got {training!r}")
    if not (np.isfinite(contrast) and contrast > -1 and contrast != 0):
        raise ValueError(f"contrast (relative conductivity change) must be > -1 and not 0; got {contrast}")


def _image_grid(mesh: Mesh, grid: int | tuple[int, int]) -> PixelGrid:
    """The pixel grid of the images: at least 2 x 2 pixels, at least one of them in the domain."""
    shape = (grid, grid) if np.ndim(grid) == 0 else tuple(grid)
    if len(shape) != 2 or not all(isinstance(n, int | np.integer) and n >= 2 for n in shape):
        raise ValueError(f"grid must be an integer >= 2 or a pair of them (n_rows, n_columns); got {grid!r}")
    pixels = pixel_grid(mesh, shape, _INSIDE_FRACTION)
    if not np.any(pixels.mask):
        raise ValueError(f"no pixel of the {shape[0]} x {shape[1]} grid lies at least half in the domain")
    return pixels


def _training_measurements(
    problem: LinearisedProblem, centres: np.ndarray, radius: float, training: str, contrast: float
) -> np.ndarray:
    """Y (n_meas, K): the normalised measurements of the unit-strength targets (class docstring)."""
    mesh, model = problem.model.mesh, problem.model
    fractions, target_areas = _disc_fractions(mesh, centres, radius)  # (E, K) sparse, (K,)
    strength = mesh.element_areas.sum() / target_areas  # unit strength: each x_k integrates to the sheet's area
    if training == "linearised":
        return np.asarray((fractions.T @ problem.jacobian.T).T) * strength
    perturbed = problem.background * (1 + contrast * fractions.T.toarray())  # (K, E)
    voltages = np.asarray(jax.vmap(model.measure)(jnp.asarray(perturbed)))
    return (voltages - problem.reference).T / problem.data_scale[:, None] * (strength / contrast)


def _desired_images(grid: PixelGrid, mesh: Mesh, centres: np.ndarray, radius: float, width: float) -> np.ndarray:
    """D (pixels in the mask, K): each target disc of `radius` blurred by a Gaussian of standard
    deviation `width` (m), scaled to integrate to the sheet's area as the targets do; the disc
    enters as the Gaussian of equal second moments (class docstring)."""
    images = _pixel_gaussians(centres, np.sqrt(width**2 + radius**2 / 4), grid.x_edges, grid.y_edges)
    return images[grid.mask.ravel()] * mesh.element_areas.sum()


def _central_measurement(mesh: Mesh, centres: np.ndarray, measurements: np.ndarray) -> np.ndarray:
    """y_0 (n_meas,): the measurement of the training target nearest the domain's centroid."""
    centroid = mesh.element_areas @ mesh.element_centroids / mesh.element_areas.sum()
    return measurements[:, np.argmin(np.linalg.norm(centres - centroid, axis=1))]


def _pixel_matrix(grid: PixelGrid, problem: LinearisedProblem, normalised: np.ndarray) -> np.ndarray:
    """The (n_pixels, n_meas) matrix in S/sq per volt from R_n (mask pixels, unit-free): rows
    times each pixel's background, columns over s, rows outside the mask zero."""
    inside = grid.mask.ravel()
    pixel_background = (grid.element_to_pixel @ problem.background)[inside]
    matrix = np.zeros((len(inside), normalised.shape[1]))
    matrix[inside] = normalised * pixel_background[:, None] / problem.data_scale
    return matrix


class _RidgeFit:
    """R_n and its noise figure as functions of the hyperparameter, in the eigenbasis of
    Y Y^T = U diag(m_i) U^T (an n_meas x n_meas eigenproblem: an SVD of Y costs more and is slow
    under thread contention). Directions below rounding (reciprocal pairs of readings duplicate
    each other: Y Y^T has rank 104 of 208 for the adjacent protocol) carry no information about
    the targets and are dropped, so lambda -> 0 is the pseudo-inverse. A noise-figure scan
    costs no matrix products."""

    def __init__(self, measurements: np.ndarray, desired: np.ndarray, signal: np.ndarray) -> None:
        eigenvalues, left = np.linalg.eigh(measurements @ measurements.T)
        kept = eigenvalues > len(eigenvalues) * np.finfo(float).eps * eigenvalues.max()
        self.eigenvalues, self.left = eigenvalues[kept], left[:, kept]
        self.projected = (desired @ measurements.T) @ self.left  # D Y^T U, (n_pixels, rank)
        self.n_targets = measurements.shape[1]
        self.column_norms = np.sum(self.projected**2, axis=0)  # ||R_n||_F^2 = sum_i f_i^2 ||(D Y^T U)_i||^2
        self.projected_signal = self.projected * (self.left.T @ signal)  # R_n y_0 = this @ f
        self.signal_amplitude = float(np.mean(np.abs(signal)))

    def filter(self, hyperparameter: float) -> np.ndarray:
        """f_i = 1 / (m_i + K lambda^2), so that R_n = D Y^T U diag(f) U^T; m_i > 0, so never inf."""
        return 1 / (self.eigenvalues + self.n_targets * hyperparameter**2)

    def matrix(self, hyperparameter: float) -> np.ndarray:
        """R_n (pixels in the mask, n_meas), unit-free."""
        return (self.projected * self.filter(hyperparameter)) @ self.left.T

    def noise_figure(self, hyperparameter: float) -> float:
        """NF of R_n (class docstring of GREIT)."""
        factors = self.filter(hyperparameter)
        noise = np.sqrt(self.column_norms @ factors**2 / len(self.projected))
        image = np.mean(np.abs(self.projected_signal @ factors))
        return float(self.signal_amplitude * noise / image)

    def solve(self, target: float) -> float:
        """The hyperparameter of noise figure `target`: the first crossing on a log scan, refined."""
        figures = np.array([self.noise_figure(h) for h in _NOISE_FIGURE_SCAN])
        excess = figures - target
        crossing = np.flatnonzero(np.sign(excess[:-1]) != np.sign(excess[1:]))
        if len(crossing) == 0:
            raise ValueError(
                f"noise figure {target} is out of reach: for hyperparameters from {_NOISE_FIGURE_SCAN[0]:g} to "
                f"{_NOISE_FIGURE_SCAN[-1]:g} it lies between {figures.min():.3g} and {figures.max():.3g}"
            )
        i = crossing[0]
        log_root = scipy.optimize.brentq(
            lambda t: self.noise_figure(10.0**t) - target,
            np.log10(_NOISE_FIGURE_SCAN[i]),
            np.log10(_NOISE_FIGURE_SCAN[i + 1]),
        )
        return float(10.0**log_root)


def _target_positions(mesh: Mesh, n_targets: int, radius: float, rng: np.random.Generator) -> np.ndarray:
    """(n_targets, 2) centres drawn uniformly over the points of the domain at least `radius`
    from its boundary (rejection sampling in the bounding box)."""
    start, end = mesh.nodes[mesh.boundary_edges[:, 0]], mesh.nodes[mesh.boundary_edges[:, 1]]
    low, high = mesh.nodes.min(axis=0), mesh.nodes.max(axis=0)
    found = np.empty((0, 2))
    for _ in range(10):  # enough wherever at least 1 in 50 points of the box is a valid centre
        points = rng.uniform(low, high, size=(5 * n_targets, 2))
        points = points[locate(mesh, points) >= 0]
        found = np.concatenate([found, points[distance_to_segments(points, start, end) >= radius]])
        if len(found) >= n_targets:
            return found[:n_targets]
    raise ValueError(
        f"could not place {n_targets} training targets of radius {radius:g} m wholly inside the domain "
        f"(found {len(found)}): lower target_radius"
    )


def _disc_fractions(mesh: Mesh, centres: np.ndarray, radius: float) -> tuple[scipy.sparse.csc_array, np.ndarray]:
    """(E, K) sparse fraction of each element inside each disc (midpoint rule on 64
    sub-triangles, as `diffeit.mesh.disc_fraction`), and (K,) the discs' areas on the mesh."""
    samples = element_sample_points(mesh, _TARGET_SAMPLING_LEVEL)
    centroids = mesh.element_centroids
    reach = np.max(np.linalg.norm(mesh.nodes[mesh.triangles] - centroids[:, None], axis=2))
    near = cKDTree(centroids).query_ball_point(centres, radius + reach)
    target = np.repeat(np.arange(len(centres)), [len(n) for n in near])
    element = np.concatenate([np.asarray(n, dtype=int) for n in near])
    inside = np.linalg.norm(samples[element] - centres[target][:, None], axis=2) < radius
    fraction = inside.mean(axis=1)
    kept = fraction > 0
    fractions = scipy.sparse.csc_array(
        (fraction[kept], (element[kept], target[kept])), shape=(mesh.n_elements, len(centres))
    )
    areas = fractions.T @ mesh.element_areas
    if np.any(areas <= 0):
        raise ValueError("a training target covers no element: raise target_radius or refine the mesh")
    return fractions, areas


def _pixel_gaussians(centres: np.ndarray, width: float, x_edges: np.ndarray, y_edges: np.ndarray) -> np.ndarray:
    """(n_rows * n_columns, K): the mean over each pixel of the unit-mass Gaussian of standard
    deviation `width` about each centre, 1/m^2 (exact: the Gaussian separates in x and y)."""

    def along(edges: np.ndarray, positions: np.ndarray) -> np.ndarray:  # (n_cells, K)
        cumulative = scipy.special.ndtr((edges[:, None] - positions[None]) / width)
        return np.diff(cumulative, axis=0) / np.diff(edges)[:, None]

    x_part, y_part = along(x_edges, centres[:, 0]), along(y_edges, centres[:, 1])
    return (y_part[:, None, :] * x_part[None, :, :]).reshape(-1, len(centres))
