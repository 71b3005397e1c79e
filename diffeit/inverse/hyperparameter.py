"""Choosing the regularisation hyperparameter of linearised reconstruction, and converting it to
and from the values EIDORS and pyEIT use.

All methods work on the normalised problem of `LinearisedProblem` (unit-free hyperparameter
lambda, data y = dV / s, prior covariance scaled to a unit-mean data-space covariance G). One
eigendecomposition G = U diag(g) U^T serves every candidate lambda: with y_hat = U^T y and the
filter factors f_i = g_i / (g_i + lambda^2),

    residual norm^2  ||J_n x - y||^2       = sum_i (1 - f_i)^2 y_hat_i^2
    solution norm^2  x^T (P/c)^-1 x        = sum_i g_i y_hat_i^2 / (g_i + lambda^2)^2
    GCV(lambda)      = M ||r||^2 / (M - sum_i f_i)^2          (minimised)

- "gcv": generalised cross-validation (Golub, Heath and Wahba 1979), no noise level needed.
- "lcurve": the corner of the L-curve (log residual norm, log solution norm) (Hansen 1992), the
  candidate of largest curvature, no noise level needed.
- "discrepancy": Morozov's principle: the lambda whose residual norm equals `safety` times the
  expected noise norm; needs `noise` (percent of RMS(V_ref), docs/science.md#noise).
- "noise_figure": the lambda whose noise figure NF = SNR_data / SNR_image equals
  `noise_figure` (Adler and Guardo 1996, as EIDORS's `choose_noise_figure`: SNR_data =
  ||y_t||^2 / trace(Sigma), SNR_image = ||A x_t||^2 / trace(A R Sigma R^T A), for a small
  central target x_t, white noise Sigma in volts and A the element areas). EIDORS's GREIT
  uses NF = 0.5. Larger lambda gives a smaller NF.

With several frames (T, M) the norms add up over frames.

A choice at an end of the candidates (or a discrepancy or noise-figure level not reached within
them) is `RESULTS.selection_at_boundary`: `select_hyperparameter` raises for it unless called
with `throw=False`, and the selection's `result` carries the code.
"""

from __future__ import annotations

from typing import Literal

import equinox as eqx
import jax
import numpy as np

from .._threads import host_algebra
from ..forward import ForwardModel
from ..mesh import disc_fraction, onto_surface
from ..results import RESULTS, throw_if_failed
from .linearised import LinearisedProblem, check_frames
from .one_step import OneStep
from .priors import AbstractPrior, Noser, Tikhonov

Method = Literal["gcv", "lcurve", "discrepancy", "noise_figure"]
DEFAULT_CANDIDATES = np.logspace(-6, 2, 161)


class HyperparameterSelection(eqx.Module):
    """The chosen hyperparameter and the curve it was chosen from.

    Returned by `select_hyperparameter`; the methods are defined in the module docstring.

    Attributes:
        value: The chosen lambda (unit-free).
        method: "gcv", "lcurve", "discrepancy" or "noise_figure" (static).
        candidates: (K,) the lambdas evaluated, increasing.
        criterion: (K,) what the method looks at per candidate: the GCV function, the
            L-curve curvature, the residual norm over the noise norm, or the noise figure.
        residual_norm: (K,) ||J_n x - y|| (unit-free, summed over frames).
        solution_norm: (K,) the prior seminorm of x.
        target: The level a discrepancy or noise-figure method aims at (None otherwise).
        result: `RESULTS.successful`, or `RESULTS.selection_at_boundary` when the value is
            the smallest or largest candidate (or the target level is not reached within the
            candidates, and the nearest end is taken).
    """

    value: float
    method: str = eqx.field(static=True)
    candidates: np.ndarray
    criterion: np.ndarray
    residual_norm: np.ndarray
    solution_norm: np.ndarray
    target: float | None
    result: RESULTS


@host_algebra
def select_hyperparameter(
    model: ForwardModel,
    voltage_difference: jax.Array,
    method: Method = "gcv",
    *,
    prior: str | AbstractPrior = "noser",
    background: float | np.ndarray = 1.0,
    normalised: bool = False,
    reference: jax.Array | None = None,
    candidates: np.ndarray | None = None,
    noise: float | None = None,
    safety: float = 1.0,
    noise_figure: float = 0.5,
    target_radius: float | None = None,
    throw: bool = True,
    problem: LinearisedProblem | None = None,
) -> HyperparameterSelection:
    """Choose the `OneStep` hyperparameter for voltage differences.

    "discrepancy" and "noise_figure" refine between the two bracketing candidates. See the
    module docstring for the definitions of the methods.

    Arguments:
        model: The forward model.
        voltage_difference: dV, (M,) or (T, M), volts; several frames add their norms.
        method: "gcv" (default), "lcurve", "discrepancy" or "noise_figure".
        prior: The prior, a name or a prior, as in `OneStep`.
        background: The background conductivity, S/sq, scalar or (E,).
        normalised: Normalised differences dV / V_ref, as in `OneStep`.
        reference: (M,) the measured reference V_ref, volts; needed when `normalised`.
        candidates: The lambdas tried, at least 3, finite and positive (default 161 values
            from 1e-6 to 1e2, log-spaced); sorted.
        noise: The noise level, percent of RMS(V_ref); needed by "discrepancy".
        safety: Multiplies the discrepancy's noise norm (Morozov's tau, 1 by default).
        noise_figure: The NF "noise_figure" aims at (default 0.5).
        target_radius: The central target's radius for "noise_figure", metres (default 5% of
            the mesh's diameter).
        throw: Raise for a choice at an end of the candidates (True), or return it with its
            code (False; its value is the nearest end).
        problem: The `LinearisedProblem` of `model`, `prior`, `background` and `normalised`
            when the caller has built it already (its Jacobian and eigendecomposition are most
            of the cost of a selection), so that several methods share one.

    Returns:
        The `HyperparameterSelection`.

    Raises:
        ValueError: For a `problem` of another model or normalisation, voltage differences of
            the wrong shape or not finite, normalised differences without `reference`, bad
            candidates, an unknown method, "discrepancy" without a positive `noise`, a
            noise-figure target that covers no element, or the errors of
            `LinearisedProblem`.
        diffeit.results.SolverError: With `throw=True`, for `RESULTS.selection_at_boundary`.
    """
    if problem is None:
        problem = LinearisedProblem(model, prior, background, normalised=normalised)
    elif problem.model is not model or problem.normalised != bool(normalised):
        raise ValueError("problem must be the linearised problem of this model (and normalisation)")
    dv = np.atleast_2d(np.asarray(check_frames(voltage_difference, model.n_measurements, "voltage differences")))
    if normalised and reference is None:
        raise ValueError("normalised differences need the measured reference voltages: pass reference=V_ref")
    y = np.asarray(problem.normalised_data(dv, None if reference is None else np.asarray(reference)))
    lambdas = np.sort(np.asarray(DEFAULT_CANDIDATES if candidates is None else candidates, dtype=np.float64))
    if lambdas.ndim != 1 or len(lambdas) < 3 or not np.all(np.isfinite(lambdas) & (lambdas > 0)):
        raise ValueError("candidates must be at least 3 finite positive hyperparameters")
    eigenvalues, vectors = problem.eigenvalues, problem.eigenvectors
    spectrum = np.sum((y @ vectors) ** 2, axis=0)  # sum over frames of y_hat_i^2
    residual, solution = _norms(eigenvalues, spectrum, lambdas)

    if method == "gcv":
        n = len(eigenvalues)
        dof = n - np.sum(eigenvalues / (eigenvalues + lambdas[:, None] ** 2), axis=1)
        criterion = n * residual**2 / len(y) / dof**2
        selection = _at_index(lambdas, criterion, residual, solution, method, int(np.argmin(criterion)))
    elif method == "lcurve":
        criterion = _curvature(np.log(residual), np.log(solution), np.log(lambdas))
        selection = _at_index(lambdas, criterion, residual, solution, method, int(np.argmax(criterion)))
    elif method == "discrepancy":
        if noise is None or not noise > 0:
            raise ValueError("the discrepancy principle needs the noise level: noise=p for p% of RMS(V_ref)")
        volts = noise / 100 * np.sqrt(np.mean(problem.reference**2))
        noise_norm = safety * np.sqrt(len(y) * np.sum((volts / problem.data_scale) ** 2))

        def level(lam: np.ndarray) -> np.ndarray:
            return _norms(eigenvalues, spectrum, lam)[0] / noise_norm

        selection = _crossing(lambdas, level, 1.0, residual, solution, method, increasing=True)
    elif method == "noise_figure":
        figure = _noise_figure_function(problem, eigenvalues, vectors, target_radius)
        selection = _crossing(lambdas, figure, noise_figure, residual, solution, method, increasing=False)
    else:
        raise ValueError(f"unknown method {method!r}; choose one of {Method.__args__}")
    return throw_if_failed(selection, selection.result, f"hyperparameter selection by {method}") if throw else selection


def _norms(eigenvalues: np.ndarray, spectrum: np.ndarray, lambdas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    shift = eigenvalues + np.asarray(lambdas)[..., None] ** 2
    residual = np.sqrt(np.sum((np.asarray(lambdas)[..., None] ** 2 / shift) ** 2 * spectrum, axis=-1))
    solution = np.sqrt(np.sum(eigenvalues * spectrum / shift**2, axis=-1))
    return residual, solution


def _curvature(rho: np.ndarray, eta: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Signed curvature of the curve (rho(t), eta(t)); the L-curve's corner is its maximum."""
    d_rho, d_eta = np.gradient(rho, t), np.gradient(eta, t)
    dd_rho, dd_eta = np.gradient(d_rho, t), np.gradient(d_eta, t)
    return (d_rho * dd_eta - dd_rho * d_eta) / np.maximum(d_rho**2 + d_eta**2, 1e-300) ** 1.5


def _at_index(lambdas, criterion, residual, solution, method, index, target=None) -> HyperparameterSelection:
    """The selection of candidate `index`: at the boundary when it is the first or the last."""
    result = RESULTS.selection_at_boundary if index in (0, len(lambdas) - 1) else RESULTS.successful
    value = float(lambdas[index])
    return HyperparameterSelection(value, method, lambdas, criterion, residual, solution, target, result)


def _crossing(lambdas, function, target, residual, solution, method, *, increasing: bool) -> HyperparameterSelection:
    """The lambda where the monotone `function` crosses `target`, refined by bisection in log
    lambda between the bracketing candidates."""
    values = function(lambdas)
    above = values >= target if increasing else values <= target
    if above.all() or not above.any():
        index = 0 if above.all() else len(lambdas) - 1
        return _at_index(lambdas, values, residual, solution, method, index, target)
    first = int(np.argmax(above))
    low, high = np.log(lambdas[max(first - 1, 0)]), np.log(lambdas[first])
    for _ in range(50):
        middle = 0.5 * (low + high)
        reached = function(np.array([np.exp(middle)]))[0]
        if (reached >= target) == increasing:
            high = middle
        else:
            low = middle
    value = float(np.exp(0.5 * (low + high)))
    return HyperparameterSelection(value, method, lambdas, values, residual, solution, target, RESULTS.successful)


def _noise_figure_function(problem: LinearisedProblem, eigenvalues, vectors, target_radius):
    """NF(lambdas) for a small target at the centre of the mesh's area (see the module), taken
    onto a curved skin's surface (the mean of its centroids lies inside its chord)."""
    mesh = problem.model.mesh
    areas = mesh.element_areas
    centre = onto_surface(mesh, areas @ mesh.element_centroids / areas.sum())
    diameter = np.ptp(mesh.nodes, axis=0).max()
    radius = 0.05 * diameter if target_radius is None else target_radius
    target = disc_fraction(mesh, centre, radius)
    if not target.any():
        raise ValueError(f"the noise-figure target (radius {radius:g} m at {centre}) covers no element")
    data = problem.jacobian @ target  # y_t
    # White noise in volts is diag(s_rms / data_scale)^2 in the normalised data.
    noise_root = np.sqrt(np.mean(problem.reference**2)) / problem.data_scale
    weights = areas / areas.sum()
    image_basis = weights[:, None] * (problem.prior_jacobian @ vectors)  # A P J_n^T U / c, (E, M)
    image_gram = image_basis.T @ image_basis
    noise_gram = image_gram * ((vectors.T * noise_root) @ (vectors.T * noise_root).T).T
    data_snr = np.sum(data**2) / np.sum(noise_root**2)
    target_hat = vectors.T @ data

    def figure(lambdas: np.ndarray) -> np.ndarray:
        inverse = 1.0 / (eigenvalues + np.asarray(lambdas)[:, None] ** 2)  # (K, M)
        signal = np.einsum("ki,ij,kj->k", inverse * target_hat, image_gram, inverse * target_hat)
        noise_power = np.einsum("ki,ij,kj->k", inverse, noise_gram, inverse)
        return data_snr / (signal / noise_power)

    return figure


# ---------------------------------------------------------------------------------------------
# EIDORS and pyEIT

Tool = Literal["eidors", "pyeit"]


def to_external_hyperparameter(reconstruction: OneStep, tool: Tool) -> float:
    """The value another tool needs for the same one-step reconstruction.

    Both tools solve min ||J dsigma - dV||^2 + w dsigma^T R dsigma with J for a 1 A drive:
    pyEIT's JAC takes w as `lamb` directly (a squared weight), EIDORS takes w = hp^2 and its
    `hyperparameter.value` is hp. diffeit's objective, multiplied out, is the same with
    w = lambda^2 c s^2 / (background^2 I^2) x (its P^-1 over their R), with s = RMS(V_0),
    c the prior scale and I the drive current (docs/science.md#linearised-reconstruction). The
    priors must be the same family: `Noser(exponent=p)` is EIDORS's `prior_noser` (p = 0.5) and
    pyEIT's "kotre" with that p (pyEIT's default p is 0.2); `Tikhonov()` is EIDORS's
    `prior_tikhonov` and pyEIT's "dgn". Absolute differences and a uniform background only; the
    same mesh and protocol.

    Arguments:
        reconstruction: The `OneStep` solver, on a model.
        tool: "pyeit" or "eidors".

    Returns:
        pyEIT's `lamb` (w), or EIDORS's hyperparameter value (hp).

    Raises:
        ValueError: For a solver without a model, or a prior or tool the other tool lacks.
    """
    if reconstruction.problem is None:
        raise ValueError("the OneStep has no model: bind it first (solver.bound(model, background))")
    weight = reconstruction.hyperparameter**2 * _weight_factor(reconstruction.problem, tool)
    return float(np.sqrt(weight) if tool == "eidors" else weight)


def from_external_hyperparameter(
    value: float,
    model: ForwardModel,
    tool: Tool,
    *,
    prior: str | AbstractPrior = "noser",
    background: float = 1.0,
) -> float:
    """diffeit's unit-free hyperparameter for EIDORS's `hyperparameter.value` or pyEIT's `lamb`.

    The inverse of `to_external_hyperparameter`, which explains the mapping.

    Arguments:
        value: EIDORS's hp or pyEIT's `lamb` (w), positive.
        model: The forward model (the same mesh and protocol as the other tool's).
        tool: "eidors" or "pyeit".
        prior: The prior, "noser" (default) or "tikhonov", or a `Noser` or `Tikhonov`.
        background: The uniform background conductivity, S/sq.

    Returns:
        lambda, unit-free.

    Raises:
        ValueError: For a value that is not positive, an unknown tool, or a prior the other
            tool lacks (or a NOSER exponent other than 0.5 for EIDORS).
    """
    if not value > 0:
        raise ValueError(f"the {tool} hyperparameter must be positive; got {value}")
    weight = value**2 if tool == "eidors" else value
    problem = LinearisedProblem(model, prior, background)
    return float(np.sqrt(weight / _weight_factor(problem, tool)))


def _weight_factor(problem: LinearisedProblem, tool: Tool) -> float:
    """w / lambda^2 for `tool` (see `to_external_hyperparameter`)."""
    if tool not in Tool.__args__:
        raise ValueError(f"unknown tool {tool!r}; choose one of {Tool.__args__}")
    if problem.normalised:
        raise ValueError("the conversion covers absolute differences only")
    background = problem.background
    if not np.allclose(background, background[0], rtol=1e-12):
        raise ValueError("the conversion needs a uniform background")
    if isinstance(problem.prior, Noser):
        exponent = problem.prior.exponent
    elif isinstance(problem.prior, Tikhonov):
        exponent = 0.0
    else:
        raise ValueError(f"{tool} has no one-step prior of the family {type(problem.prior).__name__}")
    if tool == "eidors" and exponent not in (0.0, 0.5):
        raise ValueError("EIDORS's prior_noser uses the exponent 0.5")
    s = problem.data_scale[0]
    current = problem.model.drive_current
    # P^-1 over R: diag(J_n^T J_n)^p / diag(J_1A^T J_1A)^p = (background I / s)^(2p).
    ratio = (background[0] * current / s) ** (2 * exponent)
    return problem.prior_scale * s**2 / (background[0] ** 2 * current**2) * ratio
