"""The background conductivity map of a skin (with its contact impedances and an instrument's
per-reading gains), fitted to untouched reference frames."""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from .._threads import host_algebra
from ..forward import ForwardModel
from ..inverse import AbsoluteGaussNewton, LinearisedProblem, Solution
from ..inverse.linearised import check_frames
from ..inverse.priors import AbstractPrior, prior_named
from ..protocol import Protocol
from ..results import RESULTS, throw_if_failed
from ._optimise import History, minimise

# The hyperparameters tried, largest first (half a decade apart), and the bisections in
# log(lambda) between the last candidate above the noise level and the first at or below it.
_CANDIDATES = 10.0 ** (-0.5 * np.arange(13))
_BISECTIONS = 3
# The misfit has levelled off (at the model's own error, above the noise) when half a decade
# smaller lambda lowers it by less than this factor.
_LEVELLED = 0.95
# Readings a single frame must hold beyond what a reciprocal sensor determines, to estimate
# the noise from them.
_MIN_REDUNDANT = 8
# L-BFGS's tolerances for the gain fit, on the objective and on ln(sigma), ln(z), ln(g)
# (relative and absolute: ln(g) starts at 0).
_GAIN_RTOL, _GAIN_ATOL = 1e-6, 1e-5


class BackgroundFit(eqx.Module):
    """The result of `background`: the fitted map, contact impedances and gains, and how they were found.

    Symbols as in `background` and docs/science.md#background-fit.

    Attributes:
        conductivity: (E,) the background sheet conductivity sigma, S/sq (positive).
        contact_impedance: (L,) z, ohm m: fitted when asked, else the model's.
        gain: (M,) the gain g per reading (dimensionless, near 1), or None when not fitted.
        homogeneous: sigma_h, the best homogeneous conductivity, S/sq: the start and the
            prior's centre (and the uniform background to compare with).
        misfit: ||g V(sigma, z) - v|| / ||v||, v the mean of the frames.
        hyperparameter: The lambda used (chosen, or given).
        noise: sigma_n, the standard deviation of one reading of one frame, volts (given,
            estimated from the frames' spread or from the redundant readings of one frame); NaN
            when neither needed nor estimable.
        candidates: (K,) the lambdas fitted, in order.
        discrepancy: (K,) each candidate fit's ||V - v|| / (sqrt(M) sigma_v), sigma_v the
            noise of one reading of the mean frame (NaN without a noise level).
        history: `History`: Phi at the start and after every accepted step (the Gauss-Newton
            steps at the chosen lambda, then the L-BFGS steps of the gain fit; it never rises),
            and max |dPhi/dy| there, y = (s, w when fitted, gamma when fitted): NaN at the
            Gauss-Newton steps but their last (GaussNewton does not report its iterates).
        result: `RESULTS.successful`; `RESULTS.selection_at_boundary` when the misfit levelled
            off above the noise level or did not reach it within the candidates (without
            `estimate_gain`); or the first code other than successful of the Gauss-Newton fit
            (`max_iterations_reached`, `line_search_failed`) and of the gain fit
            (`max_iterations_reached`, `stalled`, `nonfinite`).
    """

    conductivity: np.ndarray
    contact_impedance: np.ndarray
    gain: np.ndarray | None
    homogeneous: float
    misfit: float
    hyperparameter: float
    noise: float
    candidates: np.ndarray
    discrepancy: np.ndarray
    history: History
    result: RESULTS


@host_algebra
def background(
    model: ForwardModel,
    reference: jax.Array | np.ndarray,
    *,
    prior: str | AbstractPrior = "laplace",
    hyperparameter: float | None = None,
    noise: float | None = None,
    estimate_contact_impedance: bool = False,
    contact_impedance_spread: float = 1.0,
    estimate_gain: bool = False,
    gain_spread: float = 0.01,
    discrepancy_safety: float = 1.0,
    max_iterations: int = 30,
    max_gain_steps: int = 2000,
    progress: bool = True,
    throw: bool = True,
) -> BackgroundFit:
    """Fit the background conductivity map of `model`'s mesh to untouched reference frames.

    Fits v ~ g V(sigma, z), v the mean of the frames, V the model's voltages, sigma = e^s the
    sheet conductivity (S/sq), z = e^w the contact impedances (ohm m, when
    `estimate_contact_impedance`) and g = e^gamma one gain per reading (when `estimate_gain`),
    with a smoothness prior on ln sigma centred on the best homogeneous conductivity. Gauss-Newton
    (`diffeit.inverse.AbsoluteGaussNewton`) fits (s, w); with `estimate_gain`, L-BFGS then fits
    s, w and gamma jointly. The hyperparameter is chosen, unless given, by the discrepancy
    principle on the nonlinear fits, with the noise given, taken from the frames' spread or
    estimated from the redundant (reciprocal) readings of one frame. The objective, the choice
    of the hyperparameter and the noise, and what the frames determine of z and g are in
    docs/science.md#background-fit.

    Arguments:
        model: The forward model of the mesh to fit on.
        reference: One frame (M,) or several untouched frames (T, M), volts, in the model's
            protocol order and sign; T frames of one state fit as their mean.
        prior: A name ("laplace", "matern", "noser", "tikhonov") or a prior of
            `diffeit.inverse.priors`, on ln sigma.
        hyperparameter: lambda > 0, unit-free; None chooses it by the discrepancy principle.
        noise: The standard deviation of one reading of one frame, percent of RMS(v); None
            estimates it from the frames.
        estimate_contact_impedance: Fit z too (off by default: the readings of an adjacent
            protocol see it little).
        contact_impedance_spread: The prior's standard deviation of ln z around the model's,
            weighed by lambda.
        estimate_gain: Fit a gain per reading too (instruments that have one).
        gain_spread: The prior's standard deviation of ln g around 0.
        discrepancy_safety: tau of the discrepancy principle: the misfit aimed at is tau times
            the expected noise norm.
        max_iterations: Gauss-Newton steps per fit.
        max_gain_steps: L-BFGS steps of the gain fit.
        progress: Show progress bars.
        throw: Raise for a result other than `RESULTS.successful` (True), or return it in
            `result` (False).

    Returns:
        The `BackgroundFit`.

    Raises:
        ValueError: For a reference of the wrong shape or with non-finite values, a frame that
            does not correlate positively with the model's voltages, invalid options, and, when
            the noise is needed, identical frames or one frame of a protocol without redundant
            readings.
        diffeit.results.SolverError: With `throw=True`, for a result other than
            `RESULTS.successful`.
    """
    frames = np.atleast_2d(np.asarray(check_frames(reference, model.n_measurements, "reference frames"), np.float64))
    _check_options(hyperparameter, noise, contact_impedance_spread, gain_spread, discrepancy_safety, max_iterations)
    prior = prior_named(prior) if isinstance(prior, str) else prior
    data = frames.mean(axis=0)
    noise_std = _noise_std(frames, model.protocol, noise, needed=hyperparameter is None or estimate_gain)
    expected = noise_std * np.sqrt(model.n_measurements / len(frames))

    def solve(value: float) -> Solution:
        solver = AbsoluteGaussNewton(
            model,
            prior,
            value,
            estimate_contact_impedance=estimate_contact_impedance,
            max_iterations=max_iterations,
            contact_impedance_spread=contact_impedance_spread,
        )
        return solver.solve(data, throw=False)

    fit = solve(hyperparameter if hyperparameter is not None else _CANDIDATES[0])
    objective = _Objective(model, prior, data, fit.stats["reference"], contact_impedance_spread)
    # GaussNewton's normalised misfit ||V - v|| / s_d in units of the expected noise norm.
    scale = objective.data_scale / expected
    if hyperparameter is None:

        def ratio(solution: Solution) -> float:
            return solution.stats["misfit"] * scale

        selection = _select(solve, ratio, fit, discrepancy_safety, estimate_gain, progress)
    else:
        selection = _Selection(hyperparameter, fit, [hyperparameter], [fit.stats["misfit"] * scale], RESULTS.successful)
    fit = selection.fit
    unknowns = {"s": np.log(fit.value)}
    if estimate_contact_impedance:
        unknowns["w"] = np.log(fit.stats["contact_impedance"])
    objectives, result = np.asarray(fit.stats["history"]), _first_failure(selection.result, fit.result)
    norms = np.full(len(objectives), np.nan)
    # The gain's prior against the data term: the noise variance of v over s_d^2, per unit of
    # (ln g / gain_spread)^2.
    gain_weight = noise_std**2 / len(frames) / (objective.data_scale * gain_spread) ** 2 if estimate_gain else 0.0
    function = objective.bind(selection.value, gain_weight)
    if estimate_gain:
        unknowns["gamma"] = np.zeros(model.n_measurements)
        minimum = minimise(
            function,
            jax.tree_util.tree_map(jnp.asarray, unknowns),
            max_steps=max_gain_steps,
            rtol=_GAIN_RTOL,
            atol=_GAIN_ATOL,
            progress=progress,
            description="background: gain",
        )
        unknowns = jax.tree_util.tree_map(np.asarray, minimum.value)
        norms[-1] = minimum.gradient_norm[0]
        objectives = np.concatenate([objectives, minimum.objective[1:]])
        norms = np.concatenate([norms, minimum.gradient_norm[1:]])
        result = _first_failure(result, minimum.result)
    else:
        gradient = jax.grad(function)(jax.tree_util.tree_map(jnp.asarray, unknowns))
        norms[-1] = max(float(jnp.max(jnp.abs(g))) for g in jax.tree_util.tree_leaves(gradient))
    conductivity = np.exp(unknowns["s"])
    contact_impedance = np.exp(unknowns["w"]) if "w" in unknowns else np.asarray(model.contact_impedance)
    gain = np.exp(unknowns["gamma"]) if "gamma" in unknowns else None
    voltages = np.asarray(model.measure(jnp.asarray(conductivity), jnp.asarray(contact_impedance)))
    voltages = voltages if gain is None else gain * voltages
    outcome = BackgroundFit(
        conductivity=conductivity,
        contact_impedance=contact_impedance,
        gain=gain,
        homogeneous=float(fit.stats["reference"][0]),
        misfit=float(np.linalg.norm(voltages - data) / np.linalg.norm(data)),
        hyperparameter=float(selection.value),
        noise=float(noise_std),
        candidates=np.asarray(selection.candidates, dtype=float),
        discrepancy=np.asarray(selection.discrepancy, dtype=float),
        history=History(objectives, norms),
        result=result,
    )
    return throw_if_failed(outcome, outcome.result, "background fit") if throw else outcome


def _check_options(hyperparameter, noise, contact_impedance_spread, gain_spread, safety, max_iterations) -> None:
    if hyperparameter is not None and not (np.isfinite(hyperparameter) and hyperparameter > 0):
        raise ValueError(f"hyperparameter must be finite and positive, or None to choose it; got {hyperparameter}")
    if noise is not None and not (np.isfinite(noise) and noise > 0):
        raise ValueError(f"noise is a percentage of RMS(reference) and must be positive; got {noise}")
    for name, value in (
        ("contact_impedance_spread", contact_impedance_spread),
        ("gain_spread", gain_spread),
        ("discrepancy_safety", safety),
    ):
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be finite and positive; got {value}")
    if max_iterations < 1:
        raise ValueError(f"max_iterations must be >= 1; got {max_iterations}")


def _noise_std(frames: np.ndarray, protocol: Protocol, noise: float | None, *, needed: bool) -> float:
    """The standard deviation of one reading of one frame, volts (see `background`)."""
    if noise is not None:
        return noise / 100 * float(np.sqrt(np.mean(frames.mean(axis=0) ** 2)))
    if len(frames) > 1:
        spread = float(np.sqrt(np.mean(np.var(frames, axis=0, ddof=1))))
        if spread == 0 and needed:
            raise ValueError(
                "the reference frames are identical: their spread gives no noise level; pass one of them, "
                "noise= (percent) or hyperparameter="
            )
        return spread
    basis = _reciprocal_span(protocol)
    redundant = protocol.n_measurements - basis.shape[1]
    if redundant < _MIN_REDUNDANT:
        if not needed:
            return float("nan")
        raise ValueError(
            f"one frame of this protocol has {redundant} readings beyond what reciprocity determines, too few "
            "to estimate the noise from: give several untouched frames or noise= (percent), or "
            "hyperparameter= (without estimate_gain)"
        )
    off_span = frames[0] - basis @ (basis.T @ frames[0])
    return float(np.sqrt(off_span @ off_span / redundant))


def _reciprocal_span(protocol: Protocol) -> np.ndarray:
    """(M, r) orthonormal basis of the readings any reciprocal sensor can produce.

    Electrode potentials U = R I for the drive I, R symmetric with zero row sums (potentials
    sum to zero): R is a combination of (e_i - e_j)(e_i - e_j)^T, i < j, under which reading k
    (weights m_k, drive d_k) is (m_k,i - m_k,j)(d_k,i - d_k,j)."""
    first, second = np.triu_indices(protocol.n_electrodes, k=1)
    weights = protocol.measure
    drives = protocol.drive[protocol.drive_index]
    design = (weights[:, first] - weights[:, second]) * (drives[:, first] - drives[:, second])
    vectors, values, _ = np.linalg.svd(design, full_matrices=False)
    rank = int(np.sum(values > max(design.shape) * np.finfo(float).eps * values[0]))
    return vectors[:, :rank]


class _Selection(eqx.Module):
    """The chosen hyperparameter, its fit, and every candidate's discrepancy ratio."""

    value: float
    fit: Solution
    candidates: list[float]
    discrepancy: list[float]
    result: RESULTS


def _select(
    solve: Callable[[float], Solution],
    ratio: Callable[[Solution], float],
    first: Solution,
    safety: float,
    levelling_expected: bool,
    progress: bool,
) -> _Selection:
    """The discrepancy principle over `_CANDIDATES` (`first` is the fit at the largest), refined
    by bisection in log(lambda); or, when the misfit levels off above the noise, the last
    candidate before it did (see `background`)."""
    candidates, ratios, fits = [], [], []
    with tqdm(total=len(_CANDIDATES), desc="background: hyperparameter", disable=not progress, leave=False) as bar:
        for value in _CANDIDATES:
            fit = first if not fits else solve(value)
            candidates.append(float(value))
            ratios.append(ratio(fit))
            fits.append(fit)
            bar.set_postfix(hyperparameter=f"{value:.3g}", discrepancy=f"{ratios[-1]:.3g}")
            bar.update()
            if ratios[-1] <= safety:
                break
            if len(ratios) > 1 and not ratios[-1] < _LEVELLED * ratios[-2]:
                result = RESULTS.successful if levelling_expected else RESULTS.selection_at_boundary
                return _Selection(candidates[-2], fits[-2], candidates, ratios, result)
        else:
            return _Selection(candidates[-1], fits[-1], candidates, ratios, RESULTS.selection_at_boundary)
        chosen = _Selection(candidates[-1], fits[-1], candidates, ratios, RESULTS.successful)
        if len(fits) == 1:
            return chosen
        low, high = np.log(candidates[-1]), np.log(candidates[-2])  # at, above the level
        bar.reset(total=_BISECTIONS)
        for _ in range(_BISECTIONS):
            value = float(np.exp(0.5 * (low + high)))
            fit = solve(value)
            candidates.append(value)
            ratios.append(ratio(fit))
            if ratios[-1] <= safety:
                low, chosen = np.log(value), _Selection(value, fit, candidates, ratios, RESULTS.successful)
            else:
                high = np.log(value)
            bar.set_postfix(hyperparameter=f"{value:.3g}", discrepancy=f"{ratios[-1]:.3g}")
            bar.update()
    return _Selection(chosen.value, chosen.fit, candidates, ratios, chosen.result)


def _first_failure(*results: RESULTS) -> RESULTS:
    return next((result for result in results if result != RESULTS.successful), RESULTS.successful)


class _Objective(eqx.Module):
    """Phi of `background`, with Gauss-Newton's normalisation at the homogeneous start
    `sigma_h`: `bind(lambda, gain_weight)` is a JAX function of the unknowns {"s", and "w",
    "gamma" when fitted}."""

    model: ForwardModel
    data: jax.Array
    data_scale: float
    prior_scale: float
    log_reference: jax.Array
    log_contact_impedance: jax.Array
    contact_impedance_spread: float
    precision: Callable[[np.ndarray], np.ndarray] = eqx.field(static=True)

    def __init__(
        self,
        model: ForwardModel,
        prior: AbstractPrior,
        data: np.ndarray,
        homogeneous: float | np.ndarray,
        contact_impedance_spread: float,
    ) -> None:
        problem = LinearisedProblem(model, prior, homogeneous)
        self.model = model
        self.data = jnp.asarray(data)
        self.data_scale = float(problem.data_scale[0])
        self.prior_scale = problem.prior_scale
        self.log_reference = jnp.log(jnp.asarray(problem.background))
        self.log_contact_impedance = jnp.log(model.contact_impedance)
        self.contact_impedance_spread = float(contact_impedance_spread)
        self.precision = prior.bind(model.mesh)(problem.jacobian).precision

    def bind(self, hyperparameter: float, gain_weight: float) -> Callable[[dict], jax.Array]:
        weight = hyperparameter**2
        quadratic = _quadratic_form(self.precision)

        def objective(unknowns: dict) -> jax.Array:
            s = unknowns["s"]
            w = unknowns.get("w", self.log_contact_impedance)
            voltages = self.model.measure(jnp.exp(s), jnp.exp(w))
            value = weight * self.prior_scale * quadratic(s - self.log_reference)
            if "w" in unknowns:
                deviation = w - self.log_contact_impedance
                value = value + weight / self.contact_impedance_spread**2 * jnp.sum(deviation**2)
            if "gamma" in unknowns:
                voltages = jnp.exp(unknowns["gamma"]) * voltages
                value = value + gain_weight * jnp.sum(unknowns["gamma"] ** 2)
            return jnp.sum((voltages - self.data) ** 2) / self.data_scale**2 + value

        return objective


def _quadratic_form(precision: Callable[[np.ndarray], np.ndarray]) -> Callable[[jax.Array], jax.Array]:
    """x -> x^T Q x in JAX for the symmetric operator `precision` (Q, applied on the host by the
    prior's sparse factors), with its derivative 2 Q x."""

    def apply(x: jax.Array) -> jax.Array:
        return jax.pure_callback(
            lambda v: np.asarray(precision(np.asarray(v)), dtype=v.dtype), jax.ShapeDtypeStruct(x.shape, x.dtype), x
        )

    @jax.custom_jvp
    def quadratic(x: jax.Array) -> jax.Array:
        return x @ apply(x)

    @quadratic.defjvp
    def _(primals, tangents):
        (x,), (dx,) = primals, tangents
        product = apply(x)
        return x @ product, 2 * product @ dx

    return quadratic
