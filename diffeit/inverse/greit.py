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

from .._threads import host_algebra
from ..forward import ForwardModel
from ..mesh import Mesh, disc_fractions, distance_to_segments, locate
from ..render import PixelGrid, pixel_grid
from ..results import RESULTS
from .linearised import LinearisedProblem, apply_matrix, check_frames
from .priors import Tikhonov
from .solution import AbstractSolver, Solution, finished, finite_codes, model_of

DEFAULT_HYPERPARAMETER = 0.3
_TRAININGS = ("linearised", "nonlinear")
# A pixel belongs to the image when at least this fraction of its area lies in the domain.
_INSIDE_FRACTION = 0.5
# Midpoint rule on 8^2 sub-triangles for the targets' element fractions (as disc_fraction).
_TARGET_SAMPLING_LEVEL = 8
# The noise-figure search scans the hyperparameter over these decades, then refines a crossing.
_NOISE_FIGURE_SCAN = np.logspace(-8, 4, 121)


class GREIT(AbstractSolver):
    """GREIT: linear difference reconstruction trained onto a fixed pixel grid.

    After Adler et al. (2009) and EIDORS's `mk_GREIT_model`. Instead of inverting the forward
    model, the reconstruction matrix is fitted so that it maps the simulated voltages of
    `n_targets` small disc targets, spread uniformly over the domain, onto desired images of
    them on a `grid` of pixels: the targets blurred by a Gaussian of standard deviation
    `blur`, so that every position gets the same point spread function, with a noise term
    weighed by the hyperparameter. Pixels are the images of `stats["pixels"]`; the solution's
    `value` is on the mesh's elements, each the overlap-weighted mean of the pixels it meets
    (`grid.to_elements`). The method, the training, the units of the hyperparameter and the
    noise figure are in docs/science.md#greit.

    The pixel grid (`grid`, a `diffeit.render.PixelGrid` after construction) tiles the mesh's
    bounding box: `image[i, j]` is the pixel at `grid.pixel_centres[i, j]`, row 0 at the
    bottom (`plt.imshow(image, origin="lower", extent=rec.grid.extent)`). A pixel is in the
    image (`grid.mask`) when at least half of its area lies in the domain; pixels outside are
    exactly 0 in every image (`np.where(rec.grid.mask, image, np.nan)` for a figure).
    `diffeit.metrics` reads pixel images through the grid.

    Arguments:
        model: The forward model on which the targets are simulated (its mesh sets the
            domain); None for an unbound solver (see `bound`).
        grid: Pixels per side, or (n_rows, n_columns); at least 2 each.
        hyperparameter: lambda > 0, unit-free: the standard deviation of the measurement noise
            as a fraction of RMS(V_reference), per unit target strength; default 0.3 (its
            noise figure is in docs/science.md#greit) unless `noise_figure` is given.
        noise_figure: NF > 0 to choose lambda by (EIDORS's usual way, e.g. 0.5); not
            together with `hyperparameter`.
        target_radius: Training target radius, a fraction of R, half the larger side of the
            bounding box.
        n_targets: Number of training targets K.
        blur: Standard deviation of the desired Gaussian point spread function, a fraction of
            R (0.15: half-amplitude diameter 0.35 R).
        background: Reference conductivity, S/sq, scalar or (E,).
        training: "linearised" (targets through the Jacobian) or "nonlinear" (simulated
            differences at `contrast`).
        contrast: Relative conductivity change of the nonlinear training targets, > -1, not 0.
        seed: Seed of the target positions.

    Attributes:
        problem: The normalisation (J_n, s) at the background (a `LinearisedProblem`; its
            prior is not used). None when unbound.
        grid: The `PixelGrid` of the images (the requested size when unbound).
        hyperparameter: lambda in effect (on a model, whichever of it and the noise figure
            was given), unit-free.
        noise_figure: The noise figure in effect (on a model, whichever was given).
        by_noise_figure: Whether the noise figure chose the hyperparameter (and so chooses it
            again on `bound`).
        target_radius: As given, a fraction of R.
        n_targets: K, as given.
        blur: As given, a fraction of R.
        background: The background conductivity as given (S/sq, scalar or (E,)).
        training: "linearised" or "nonlinear".
        contrast: As given.
        seed: As given.
        matrix: (n_rows * n_columns, n_meas) reconstruction matrix, S/sq per volt; rows of
            pixels outside the mask are zero. Pixels are in row-major (C) order of the image.
            None when unbound.
        element_matrix: (E, n_meas): `matrix` followed by `grid.to_elements`, S/sq per volt.
            None when unbound.
        target_centres: (K, 2) centres of the training targets, metres. None when unbound.

    Raises:
        ValueError: For settings out of range (both `hyperparameter` and `noise_figure`
            given, either not finite and positive, a target radius or blur outside (0, 1),
            a non-positive number of targets, an unknown training, a contrast <= -1 or 0), a
            grid smaller than 2 x 2 or with no pixel in the domain, targets that do not fit
            in it or cover no element; a noise figure out of reach.
    """

    problem: LinearisedProblem | None = eqx.field(repr=False)
    grid: PixelGrid | int | tuple[int, int] = eqx.field(static=True, repr=False)
    hyperparameter: float | None = eqx.field(static=True)
    noise_figure: float | None = eqx.field(static=True)
    by_noise_figure: bool = eqx.field(static=True, repr=False)
    target_radius: float = eqx.field(static=True)
    n_targets: int = eqx.field(static=True)
    blur: float = eqx.field(static=True)
    background: float | np.ndarray = eqx.field(repr=False)
    training: Literal["linearised", "nonlinear"] = eqx.field(static=True)
    contrast: float = eqx.field(static=True)
    seed: int = eqx.field(static=True)
    matrix: jax.Array | None = eqx.field(repr=False)
    element_matrix: jax.Array | None = eqx.field(repr=False)
    target_centres: np.ndarray | None = eqx.field(repr=False)

    @host_algebra
    def __init__(
        self,
        model: ForwardModel | None = None,
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
        self.background = background
        self.by_noise_figure = noise_figure is not None
        if hyperparameter is None and noise_figure is None:
            hyperparameter = DEFAULT_HYPERPARAMETER
        if model is None:
            self.grid = grid
            self.hyperparameter = None if hyperparameter is None else float(hyperparameter)
            self.noise_figure = None if noise_figure is None else float(noise_figure)
            self.problem = self.matrix = self.element_matrix = self.target_centres = None
            return
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
            hyperparameter = fit.solve(noise_figure)
        self.hyperparameter = float(hyperparameter)
        self.noise_figure = fit.noise_figure(self.hyperparameter)
        matrix = _pixel_matrix(self.grid, self.problem, fit.matrix(self.hyperparameter))
        self.matrix = jnp.asarray(matrix)
        self.element_matrix = jnp.asarray(self.grid.to_elements(matrix.T.reshape(-1, *self.grid.shape)).T)

    @property
    def model(self) -> ForwardModel | None:
        """The forward model the targets are simulated on (None when unbound)."""
        return None if self.problem is None else self.problem.model

    @property
    def shape(self) -> tuple[int, int]:
        """(n_rows, n_columns), the shape of an image in pixels."""
        if isinstance(self.grid, PixelGrid):
            return self.grid.shape
        return (self.grid, self.grid) if np.ndim(self.grid) == 0 else tuple(self.grid)

    def bound(
        self,
        model: ForwardModel,
        background: float | np.ndarray | None = None,
        *,
        hyperparameter: float | None = None,
        noise_figure: float | None = None,
    ) -> GREIT:
        """This solver's settings on another model (see `AbstractSolver.bound`), trained afresh.

        A solver designed for a noise figure is designed for it again on `model`, unless
        `hyperparameter` or `noise_figure` is given (not both) to replace the design.

        Arguments:
            model: The forward model to train on.
            background: The background conductivity (S/sq, scalar or (E,)); None keeps this
                solver's.
            hyperparameter: lambda replacing this solver's design; None keeps it.
            noise_figure: A noise figure replacing this solver's design; None keeps it.

        Returns:
            A new `GREIT` on `model`.

        Raises:
            ValueError: As the constructor.
        """
        if hyperparameter is None and noise_figure is None:
            if self.by_noise_figure:
                noise_figure = self.noise_figure
            else:
                hyperparameter = self.hyperparameter
        return GREIT(
            model,
            grid=self.shape,
            hyperparameter=hyperparameter,
            noise_figure=noise_figure,
            target_radius=self.target_radius,
            n_targets=self.n_targets,
            blur=self.blur,
            background=self.background if background is None else background,
            training=self.training,
            contrast=self.contrast,
            seed=self.seed,
        )

    def solve(self, data: jax.Array, *, throw: bool = True) -> Solution:
        """Reconstruct voltage differences on the pixel grid and on the mesh's elements.

        dV = V - V_reference, volts. Works under jit and vmap, in the input's dtype (float32 in, float32 out).

        Arguments:
            data: dV, (M,) or a batch (T, M), volts.
            throw: Raise for a frame whose image is not finite (True), or return its code.

        Returns:
            The `Solution`: `value` dsigma (E,) or (T, E), S/sq, on the model's elements;
            `result` per frame `RESULTS.successful`, or `RESULTS.nonfinite` for an image that
            is not finite; `stats["pixels"]` the pixel images (n_rows, n_columns) or
            (T, n_rows, n_columns), S/sq, exactly 0 outside `grid.mask`.

        Raises:
            ValueError: For data of the wrong shape or not finite, or an unbound solver.
            diffeit.results.SolverError: With `throw=True`, for a frame whose image is not finite.
        """
        model = model_of(self)
        dv = check_frames(data, model.n_measurements, "voltage differences")
        images, pixels, codes = _images(self.element_matrix, self.matrix, dv)
        pixels = pixels.reshape(*dv.shape[:-1], *self.shape)
        return finished(images, codes, {"pixels": pixels}, "GREIT reconstruction", throw)


@jax.jit
def _images(element_matrix: jax.Array, matrix: jax.Array, frames: jax.Array) -> tuple[jax.Array, jax.Array, RESULTS]:
    """The element images, the (flat) pixel images and the codes (`finite_codes`) of `frames`
    (..., M): one compiled call."""
    images = apply_matrix(element_matrix, frames)
    return images, apply_matrix(matrix, frames), finite_codes(images)


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
    """Y (n_meas, K): the normalised measurements of the unit-strength targets (docs/science.md#greit)."""
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
    enters as the Gaussian of equal second moments (docs/science.md#greit)."""
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
        """NF of R_n (docs/science.md#greit)."""
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
    sub-triangles, `diffeit.mesh.disc_fractions`), and (K,) the discs' areas on the mesh."""
    fractions = disc_fractions(mesh, centres, radius, _TARGET_SAMPLING_LEVEL)
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
