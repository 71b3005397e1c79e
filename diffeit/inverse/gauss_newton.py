"""Gauss-Newton reconstruction on log-conductivity, absolute and difference, in measurement space."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from .._threads import host_algebra
from ..forward import ForwardModel
from ..results import RESULTS
from .linearised import check_frames
from .priors import AbstractPrior, PriorOperator, prior_named
from .solution import AbstractSolver, Solution, finished, model_of

# Armijo's sufficient-decrease constant, the step halvings tried, the largest change of
# ln(sigma) in one step (a factor e^4 ~ 55: steps beyond it are scaled down, not taken), and the
# Levenberg-Marquardt retries before an iteration gives up.
_ARMIJO = 1e-4
_HALVINGS = 12
_MAX_LOG_STEP = 4.0
_DAMPING_RETRIES = 6
# A frame fitted to this relative RMS misfit (of the data scale) is fitted to rounding: no step
# can lower its objective measurably, and it stops, successful (a frame equal to the reference).
_EXACT_FIT = 1e-10
# The homogeneous start: Gauss-Newton steps on ln(sigma_h), each at most this long, until one
# is shorter than the tolerance.
_LEVEL_STEPS, _LEVEL_STEP, _LEVEL_TOLERANCE = 30, 1.0, 1e-6


class _Frame(NamedTuple):
    """What stays fixed while one frame iterates."""

    data: np.ndarray  # v (M,), volts
    scale: float  # s_d, volts
    operator: PriorOperator  # P, bound at the start
    prior_scale: float  # c
    log_reference: np.ndarray  # s_ref (E,)
    log_z_reference: np.ndarray  # w_ref (L,)
    noise_norm: float | None  # the discrepancy level of the normalised misfit


class _Iterate(NamedTuple):
    """Where one frame's iteration stands."""

    log_conductivity: np.ndarray  # s (E,)
    log_contact_impedance: np.ndarray  # w (L,)
    residual: np.ndarray  # (V(e^s, e^w) - v) / s_d
    objective: float
    jacobian: np.ndarray  # J_n = dV/ds / s_d (M, E), at the last linearisation
    z_jacobian: np.ndarray | None  # dV/dw / s_d (M, L) when the contact impedance is estimated
    damping: float
    history: tuple[float, ...]
    reached_discrepancy: bool
    result: RESULTS | None  # None while iterating


class _Step(NamedTuple):
    """A damped Gauss-Newton step and the objective's directional derivative along it."""

    log_conductivity: np.ndarray
    log_contact_impedance: np.ndarray
    slope: float


class _Trial(NamedTuple):
    """A point the line search accepted: `length` times the step from the iterate."""

    length: float
    log_conductivity: np.ndarray
    log_contact_impedance: np.ndarray
    residual: np.ndarray
    objective: float


class _GaussNewtonIteration(AbstractSolver):
    """The settings and the iteration `GaussNewton` and `AbsoluteGaussNewton` share (see
    `GaussNewton`)."""

    model: ForwardModel | None
    prior: AbstractPrior
    hyperparameter: float = eqx.field(static=True)
    max_iterations: int = eqx.field(static=True)
    noise: float | None = eqx.field(static=True)
    discrepancy_safety: float = eqx.field(static=True)
    contact_impedance_spread: float = eqx.field(static=True)
    stagnation_tolerance: float = eqx.field(static=True)
    bound_prior: Callable[[np.ndarray], PriorOperator] | None = eqx.field(static=True, repr=False)
    """The prior on the model's mesh, factorised once (`AbstractPrior.bind`); None when unbound."""

    def _set_up(
        self,
        model: ForwardModel | None,
        prior: str | AbstractPrior,
        hyperparameter: float,
        max_iterations: int,
        noise: float | None,
        discrepancy_safety: float,
        contact_impedance_spread: float,
        stagnation_tolerance: float,
    ) -> None:
        """Check and set the shared settings (from a subclass's `__init__`)."""
        if not (np.isfinite(hyperparameter) and hyperparameter > 0):
            raise ValueError(f"hyperparameter must be finite and positive; got {hyperparameter}")
        if max_iterations < 0:
            raise ValueError(f"max_iterations must be >= 0; got {max_iterations}")
        if noise is not None and not noise > 0:
            raise ValueError(f"noise is a percentage of RMS(v) and must be positive; got {noise}")
        if not contact_impedance_spread > 0:
            raise ValueError(f"contact_impedance_spread must be positive; got {contact_impedance_spread}")
        if not stagnation_tolerance >= 0:
            raise ValueError(f"stagnation_tolerance must be >= 0; got {stagnation_tolerance}")
        self.model = model
        self.prior = prior_named(prior) if isinstance(prior, str) else prior
        if not isinstance(self.prior, AbstractPrior):
            raise ValueError(f"prior must be a name or a diffeit.inverse prior; got {prior!r}")
        self.hyperparameter = float(hyperparameter)
        self.max_iterations = int(max_iterations)
        self.noise = None if noise is None else float(noise)
        self.discrepancy_safety = float(discrepancy_safety)
        self.contact_impedance_spread = float(contact_impedance_spread)
        self.stagnation_tolerance = float(stagnation_tolerance)
        self.bound_prior = None if model is None else self.prior.bind(model.mesh)

    def _settings(self) -> dict[str, Any]:
        """The shared keyword settings, to build another solver with."""
        return {
            "max_iterations": self.max_iterations,
            "noise": self.noise,
            "discrepancy_safety": self.discrepancy_safety,
            "contact_impedance_spread": self.contact_impedance_spread,
            "stagnation_tolerance": self.stagnation_tolerance,
        }

    def _frames(self, frames: jax.Array) -> tuple[np.ndarray, bool, np.dtype]:
        """(T, M) float64 frames, whether one frame was given, and its dtype: the iteration runs
        in float64 (its line search compares objectives that differ in late digits), and the
        results come back in the input's precision."""
        array = np.asarray(check_frames(frames, model_of(self).n_measurements, "frames"))
        return np.atleast_2d(array).astype(np.float64), array.ndim == 1, array.dtype

    def _homogeneous_fit(self, frames: np.ndarray) -> np.ndarray:
        """(T,) the homogeneous sheet conductivity (S/sq) fitting each frame best."""
        unit = np.asarray(self.model.measure(jnp.ones(self.model.n_elements)))
        projection = frames @ unit
        if np.any(projection <= 0):
            bad = np.flatnonzero(projection <= 0).tolist()
            raise ValueError(
                f"frame(s) {bad} do not correlate positively with the model's voltages: check the protocol's "
                "order and sign (diffeit.protocol.convert) before absolute imaging"
            )
        level = np.log(unit @ unit / projection)  # v ~ V(1) / sigma, exact without contact impedance
        z = np.broadcast_to(
            np.log(np.asarray(self.model.contact_impedance)), (len(frames), self.model.mesh.n_electrodes)
        )
        # The contact impedance makes V(sigma) not exactly V(1) / sigma: far from it where the
        # contact length z sigma is large at sigma = 1 (data in an arbitrary unit, say, whose
        # level is 1e-3), and there an unbounded step overshoots to zero. Steps are bounded.
        for _ in range(_LEVEL_STEPS):
            voltages, slope = _uniform_slope(self.model, jnp.asarray(level), jnp.asarray(z))
            voltages, slope = np.asarray(voltages), np.asarray(slope)  # V and dV / d ln(sigma_h), (T, M)
            step = np.sum(slope * (voltages - frames), axis=1) / np.sum(slope**2, axis=1)
            level = level - np.clip(step, -_LEVEL_STEP, _LEVEL_STEP)
            if np.all(np.abs(step) < _LEVEL_TOLERANCE):
                break
        return np.exp(level)

    def _solve(self, data: np.ndarray, start: np.ndarray, estimate_z: bool) -> tuple[list[_Frame], list[_Iterate]]:
        """Iterate every frame of `data` (T, M) from the log-conductivities `start` (T, E) until
        each has stopped; the whole batch is evaluated at once (a fixed shape compiles once)."""
        frames, iterates = self._start(data, start, estimate_z)
        for _ in range(self.max_iterations):
            steps = [
                None if it.result is not None else self._step(f, it) for f, it in zip(frames, iterates, strict=True)
            ]
            if all(step is None for step in steps):
                break
            trials = self._line_search(frames, iterates, steps, estimate_z)
            iterates = [
                it if step is None else self._advance(f, it, trial)
                for f, it, step, trial in zip(frames, iterates, steps, trials, strict=True)
            ]
            if any(it.result is None for it in iterates):
                iterates = self._relinearise(frames, iterates, estimate_z)
        iterates = [
            it if it.result is not None else it._replace(result=RESULTS.max_iterations_reached) for it in iterates
        ]
        return frames, iterates

    def _start(self, data: np.ndarray, start: np.ndarray, estimate_z: bool) -> tuple[list[_Frame], list[_Iterate]]:
        """Each frame's fixed part (data scale, prior operator and scale at the start, noise
        level) and its first iterate; a frame whose start fits within the noise has stopped."""
        model = self.model
        log_z = np.broadcast_to(np.log(np.asarray(model.contact_impedance)), (len(data), model.mesh.n_electrodes))
        voltages, jacobian, z_jacobian = _evaluate(model, start, log_z, True, estimate_z)
        scale = np.sqrt(np.mean(voltages**2, axis=1))  # s_d per frame, fixed from here on
        frames, iterates = [], []
        for k, frame_data in enumerate(data):
            normalised = jacobian[k] / scale[k]
            operator = self.bound_prior(normalised)
            prior_scale = np.sum(operator.root_transpose(np.ascontiguousarray(normalised.T)) ** 2) / len(normalised)
            noise_norm = None
            if self.noise is not None:
                rms_data = np.sqrt(np.mean(frame_data**2))
                noise_norm = self.discrepancy_safety * self.noise / 100 * rms_data / scale[k] * np.sqrt(len(frame_data))
            frame = _Frame(frame_data, scale[k], operator, prior_scale, start[k].copy(), log_z[k].copy(), noise_norm)
            residual = (voltages[k] - frame_data) / scale[k]
            objective = self._objective(frame, residual, frame.log_reference, frame.log_z_reference)
            reached = _fitted(residual, noise_norm)
            iterate = _Iterate(
                log_conductivity=frame.log_reference,
                log_contact_impedance=frame.log_z_reference,
                residual=residual,
                objective=objective,
                jacobian=normalised,
                z_jacobian=None if z_jacobian is None else z_jacobian[k] / scale[k],
                damping=0.0,
                history=(objective,),
                reached_discrepancy=reached,
                result=RESULTS.successful if reached else None,
            )
            frames.append(frame)
            iterates.append(iterate)
        return frames, iterates

    def _objective(self, frame: _Frame, residual: np.ndarray, s: np.ndarray, w: np.ndarray) -> float:
        """Phi(s, w) (`GaussNewton`, `AbsoluteGaussNewton`) for the normalised `residual` at (s, w)."""
        deviation = s - frame.log_reference
        prior_term = frame.prior_scale * deviation @ frame.operator.precision(deviation)
        weight = self.hyperparameter**2
        z_term = weight / self.contact_impedance_spread**2 * np.sum((w - frame.log_z_reference) ** 2)
        return float(residual @ residual + weight * prior_term + z_term)

    def _step(self, frame: _Frame, iterate: _Iterate) -> _Step:
        """The damped Gauss-Newton step from `iterate` (delta_s, delta_w) and the objective's
        directional derivative along it (negative: a descent direction)."""
        jacobian, z_jacobian, residual = iterate.jacobian, iterate.z_jacobian, iterate.residual
        operator, prior_scale = frame.operator, frame.prior_scale
        deviation = iterate.log_conductivity - frame.log_reference
        z_deviation = iterate.log_contact_impedance - frame.log_z_reference
        weight = self.hyperparameter**2
        z_weight = weight / self.contact_impedance_spread**2
        alpha = weight + iterate.damping
        shift = -weight * deviation / alpha
        # With P = S S^T, B = S^T J^T / sqrt(c): G = J (P/c) J^T = B^T B and (P/c) J^T xi = S B xi /
        # sqrt(c), one sparse solve with M right-hand sides per step.
        root_jt = operator.root_transpose(np.ascontiguousarray(jacobian.T)) / np.sqrt(prior_scale)
        # alpha times the system matrix, G + alpha I (+ the w block): solved by eigendecomposition,
        # leaving out G's numerical null space (see LinearisedProblem), so that a tiny
        # hyperparameter does not divide rounding errors.
        gram = root_jt.T @ root_jt
        right = -residual - jacobian @ shift
        if z_jacobian is not None:
            beta = z_weight * (1 + iterate.damping / weight)
            z_shift = -z_weight * z_deviation / beta
            gram = gram + (alpha / beta) * z_jacobian @ z_jacobian.T
            right = right - z_jacobian @ z_shift
        solution = alpha * _regularised_solve(gram, alpha, right)  # (G / alpha + I)^-1 right
        delta_s = shift + operator.root(root_jt @ solution) / (np.sqrt(prior_scale) * alpha)
        delta_w = np.zeros_like(z_deviation)
        change = jacobian @ delta_s
        if z_jacobian is not None:
            delta_w = z_shift + z_jacobian.T @ solution / beta
            change += z_jacobian @ delta_w
        slope = 2 * (
            residual @ change
            + weight * prior_scale * operator.precision(deviation) @ delta_s
            + z_weight * z_deviation @ delta_w
        )
        return _Step(delta_s, delta_w, float(slope))

    def _line_search(
        self, frames: list[_Frame], iterates: list[_Iterate], steps: list[_Step | None], estimate_z: bool
    ) -> list[_Trial | None]:
        """Backtracking (Armijo) for every frame with a step at once: the accepted trial of each
        frame whose objective decreased sufficiently, None for the others. Each halving
        evaluates the whole batch (a fixed shape compiles once); frames without a pending trial
        stay where they are."""
        lengths = [0.0] * len(steps)
        for k, step in enumerate(steps):
            if step is not None:
                largest = max(np.abs(step.log_conductivity).max(), np.abs(step.log_contact_impedance).max(initial=0.0))
                lengths[k] = min(1.0, _MAX_LOG_STEP / largest) if largest > 0 else 1.0
        pending = [k for k, step in enumerate(steps) if step is not None and step.slope < 0]
        trials: list[_Trial | None] = [None] * len(steps)
        for _ in range(_HALVINGS):
            if not pending:
                break
            trial_s = np.stack([it.log_conductivity for it in iterates])
            trial_w = np.stack([it.log_contact_impedance for it in iterates])
            for k in pending:
                trial_s[k] += lengths[k] * steps[k].log_conductivity
                trial_w[k] += lengths[k] * steps[k].log_contact_impedance
            voltages, _, _ = _evaluate(self.model, trial_s, trial_w, False, estimate_z)
            still = []
            for k in pending:
                frame = frames[k]
                residual = (voltages[k] - frame.data) / frame.scale
                objective = self._objective(frame, residual, trial_s[k], trial_w[k])
                if (
                    np.isfinite(objective)
                    and objective <= iterates[k].objective + _ARMIJO * lengths[k] * steps[k].slope
                ):
                    trials[k] = _Trial(lengths[k], trial_s[k], trial_w[k], residual, objective)
                else:
                    lengths[k] /= 2
                    still.append(k)
            pending = still
        return trials

    def _advance(self, frame: _Frame, iterate: _Iterate, trial: _Trial | None) -> _Iterate:
        """The iterate after a line search: the trial taken and the damping eased, or, without
        a trial, damped harder (shorter, more regularised steps) until the retries run out."""
        weight = self.hyperparameter**2
        if trial is None:
            damping = max(10 * iterate.damping, weight)
            failed = damping > weight * 10**_DAMPING_RETRIES
            return iterate._replace(damping=damping, result=RESULTS.line_search_failed if failed else None)
        damping = iterate.damping / 3 if trial.length == 1.0 else max(2 * iterate.damping, weight * 1e-3)
        decrease = (iterate.objective - trial.objective) / max(iterate.objective, np.finfo(float).tiny)
        reached = _fitted(trial.residual, frame.noise_norm)
        stopped = reached or decrease < self.stagnation_tolerance
        return iterate._replace(
            log_conductivity=trial.log_conductivity,
            log_contact_impedance=trial.log_contact_impedance,
            residual=trial.residual,
            objective=trial.objective,
            damping=damping,
            history=(*iterate.history, trial.objective),
            reached_discrepancy=reached,
            result=RESULTS.successful if stopped else None,
        )

    def _relinearise(self, frames: list[_Frame], iterates: list[_Iterate], estimate_z: bool) -> list[_Iterate]:
        """The iterates with their Jacobians at their current points: the whole batch, always
        (a fixed shape compiles once)."""
        s = np.stack([it.log_conductivity for it in iterates])
        w = np.stack([it.log_contact_impedance for it in iterates])
        _, jacobian, z_jacobian = _evaluate(self.model, s, w, True, estimate_z)
        return [
            it._replace(
                jacobian=jacobian[k] / f.scale, z_jacobian=None if z_jacobian is None else z_jacobian[k] / f.scale
            )
            for k, (f, it) in enumerate(zip(frames, iterates, strict=True))
        ]


class GaussNewton(_GaussNewtonIteration):
    """Nonlinear difference imaging by regularised Gauss-Newton on s = ln(sigma).

    Finds the conductivity sigma with V(sigma) - V(background) = dV, starting from and
    regularised towards the `background`, by minimising

        Phi(s) = ||V(e^s) - v||^2 / s_d^2 + hyperparameter^2 (s - s_ref)^T (c P^-1) (s - s_ref)

    with v = V(background) + dV, s_d = RMS(V(background)) and s_ref = ln(background); P is the
    prior, c its scale at the start (as in `LinearisedProblem`: the hyperparameter is unit-free
    and means what it means for `OneStep`). Every step solves the damped linearisation in
    measurement space (M x M, whatever the mesh size), with Levenberg-Marquardt damping and a
    backtracking line search, so the objective never rises; the conductivity stays positive.
    The iteration stops at the noise level when `noise` is known (the discrepancy principle),
    when the objective stagnates, or after `max_iterations`. A batch of frames runs in one
    loop, every frame with its own step, damping and stop. The equations are in
    docs/science.md#gauss-newton; `AbsoluteGaussNewton` images absolute voltages.

    Arguments:
        model: The forward model of the reconstruction mesh; None for an unbound solver (see
            `bound`).
        prior: "tikhonov", "noser", "laplace", "matern" or a prior of `diffeit.inverse.priors`;
            factorised once, at construction.
        hyperparameter: lambda > 0, unit-free.
        background: The reference conductivity the iteration starts from and is regularised
            towards, S/sq, scalar or (E,).
        max_iterations: The iteration limit (`RESULTS.max_iterations_reached` beyond it).
        noise: The noise level, percent of RMS(v), for the discrepancy principle; None never
            stops for it.
        discrepancy_safety: The factor on the expected noise norm the misfit must reach.
        contact_impedance_spread: The prior spread of ln z (`AbsoluteGaussNewton` only).
        stagnation_tolerance: Stop when the objective decreases by less than this fraction in
            a step; 0 never stops for that.

    Attributes:
        model: The forward model (None when unbound).
        prior: The prior.
        hyperparameter: lambda (static).
        max_iterations: The iteration limit (static).
        noise: The noise level, percent of RMS(v), or None (static).
        discrepancy_safety: As given (static).
        contact_impedance_spread: As given (static).
        stagnation_tolerance: As given (static).
        bound_prior: The prior on the model's mesh, factorised once (`AbstractPrior.bind`);
            None when unbound (static).
        background: The background conductivity (S/sq): (E,) on a model, as given when
            unbound.

    Raises:
        ValueError: For a hyperparameter that is not finite and positive, a negative
            `max_iterations`, a `noise` or `contact_impedance_spread` that is not positive, a
            negative `stagnation_tolerance`, an unknown prior, or a background that is not
            finite and positive.
    """

    background: float | np.ndarray = eqx.field(repr=False)

    def __init__(
        self,
        model: ForwardModel | None = None,
        prior: str | AbstractPrior = "laplace",
        hyperparameter: float = 1e-2,
        *,
        background: float | np.ndarray = 1.0,
        max_iterations: int = 20,
        noise: float | None = None,
        discrepancy_safety: float = 1.05,
        contact_impedance_spread: float = 1.0,
        stagnation_tolerance: float = 1e-6,
    ) -> None:
        self._set_up(
            model,
            prior,
            hyperparameter,
            max_iterations,
            noise,
            discrepancy_safety,
            contact_impedance_spread,
            stagnation_tolerance,
        )
        self.background = background if model is None else _positive_map(background, model.n_elements)

    def bound(
        self, model: ForwardModel, background: float | np.ndarray | None = None, *, hyperparameter: float | None = None
    ) -> GaussNewton:
        """This solver's settings on another model (see `AbstractSolver.bound`).

        Arguments:
            model: The forward model to reconstruct on.
            background: The background conductivity (S/sq, scalar or (E,)); None keeps this
                solver's.
            hyperparameter: lambda replacing this solver's; None keeps it.

        Returns:
            A new `GaussNewton` on `model` (its prior factorised on the model's mesh).
        """
        return GaussNewton(
            model,
            self.prior,
            self.hyperparameter if hyperparameter is None else hyperparameter,
            background=self.background if background is None else background,
            **self._settings(),
        )

    @host_algebra
    def solve(self, data: jax.Array, *, throw: bool = True) -> Solution:
        """Image voltage differences dV = V - V(background) (volts).

        Arguments:
            data: dV, (M,) or a batch (T, M), volts.
            throw: Raise for a frame that failed (True), or return its code.

        Returns:
            The `Solution` (NumPy arrays, in the input's dtype): `value` dsigma = sigma -
            background (E,) or (T, E), S/sq; `result` per frame `RESULTS.successful` (stopped
            at the noise level, by stagnation, or fitted to rounding),
            `RESULTS.max_iterations_reached` or `RESULTS.line_search_failed` (no step, even
            damped, decreased the objective). `stats`: "iterations" (accepted steps),
            "misfit" (the final normalised misfit ||V - v|| / s_d), "history" (the objective
            at every iterate, the start included: it never rises; a tuple of arrays for a
            batch) and "reached_discrepancy" (whether the misfit reached the noise level).

        Raises:
            ValueError: For data of the wrong shape or not finite, or an unbound solver.
            diffeit.results.SolverError: With `throw=True`, for a frame that failed.
        """
        frames, single, dtype = self._frames(data)
        background = np.broadcast_to(self.background, (self.model.n_elements,))
        reference = np.asarray(self.model.measure(jnp.asarray(background)))
        start = np.log(background)[None] * np.ones((len(frames), 1))
        frames, iterates = self._solve(frames + reference, start, False)
        collected = _collected(frames, iterates, single)
        value = (collected.pop("conductivity") - background).astype(dtype)
        del collected["contact_impedance"], collected["reference"]
        result = collected.pop("result")
        return finished(value, result, collected, "Gauss-Newton", throw)


class AbsoluteGaussNewton(_GaussNewtonIteration):
    """Absolute imaging by regularised Gauss-Newton on s = ln(sigma), optionally fitting contact impedances.

    Fits the conductivity (and, with `estimate_contact_impedance`, w = ln z) to measured
    voltages v: the objective of `GaussNewton` with s_ref the start, s_d = RMS(V(start)), plus
    (hyperparameter / contact_impedance_spread)^2 ||w - w_ref||^2 (w_ref = ln of the model's
    contact impedance). The start, and the prior's centre, is the best homogeneous
    conductivity (a closed-form least-squares fit v ~ V(1) / sigma refined by three scalar
    Newton steps) unless `initial` is given. Steps, stops and batches as `GaussNewton`'s;
    docs/science.md#gauss-newton.

    Arguments:
        model: The forward model; None for an unbound solver (see `bound`).
        prior: As `GaussNewton`'s.
        hyperparameter: lambda > 0, unit-free.
        initial: The start and the prior's centre, S/sq, scalar or (E,); None for the best
            homogeneous conductivity of each frame.
        estimate_contact_impedance: Fit one contact impedance per electrode jointly, starting
            from the model's.
        max_iterations: As `GaussNewton`'s.
        noise: As `GaussNewton`'s (percent of RMS(v)).
        discrepancy_safety: As `GaussNewton`'s.
        contact_impedance_spread: The prior spread of ln z around the model's.
        stagnation_tolerance: As `GaussNewton`'s.

    Attributes:
        model: The forward model (None when unbound).
        prior: The prior.
        hyperparameter: lambda (static).
        max_iterations: The iteration limit (static).
        noise: The noise level, percent of RMS(v), or None (static).
        discrepancy_safety: As given (static).
        contact_impedance_spread: As given (static).
        stagnation_tolerance: As given (static).
        bound_prior: The prior on the model's mesh, factorised once (`AbstractPrior.bind`);
            None when unbound (static).
        initial: The start (S/sq): (E,) on a model, as given when unbound; None for the best
            homogeneous conductivity.
        estimate_contact_impedance: Whether the contact impedances are fitted (static).

    Raises:
        ValueError: For a hyperparameter that is not finite and positive, a negative
            `max_iterations`, a `noise` or `contact_impedance_spread` that is not positive, a
            negative `stagnation_tolerance`, an unknown prior, or a given `initial` that is not
            finite and positive.
    """

    initial: float | np.ndarray | None = eqx.field(repr=False)
    estimate_contact_impedance: bool = eqx.field(static=True)

    def __init__(
        self,
        model: ForwardModel | None = None,
        prior: str | AbstractPrior = "laplace",
        hyperparameter: float = 1e-2,
        *,
        initial: float | np.ndarray | None = None,
        estimate_contact_impedance: bool = False,
        max_iterations: int = 20,
        noise: float | None = None,
        discrepancy_safety: float = 1.05,
        contact_impedance_spread: float = 1.0,
        stagnation_tolerance: float = 1e-6,
    ) -> None:
        self._set_up(
            model,
            prior,
            hyperparameter,
            max_iterations,
            noise,
            discrepancy_safety,
            contact_impedance_spread,
            stagnation_tolerance,
        )
        self.initial = initial if model is None or initial is None else _positive_map(initial, model.n_elements)
        self.estimate_contact_impedance = bool(estimate_contact_impedance)

    def bound(
        self, model: ForwardModel, background: float | np.ndarray | None = None, *, hyperparameter: float | None = None
    ) -> AbsoluteGaussNewton:
        """This solver's settings on another model (see `AbstractSolver.bound`).

        Arguments:
            model: The forward model to reconstruct on.
            background: The start (`initial`), S/sq, scalar or (E,); None keeps this solver's.
            hyperparameter: lambda replacing this solver's; None keeps it.

        Returns:
            A new `AbsoluteGaussNewton` on `model`.
        """
        return AbsoluteGaussNewton(
            model,
            self.prior,
            self.hyperparameter if hyperparameter is None else hyperparameter,
            initial=self.initial if background is None else background,
            estimate_contact_impedance=self.estimate_contact_impedance,
            **self._settings(),
        )

    @host_algebra
    def solve(self, data: jax.Array, *, throw: bool = True) -> Solution:
        """Image measured voltages.

        Arguments:
            data: The readings v, (M,) or a batch (T, M), volts.
            throw: Raise for a frame that failed (True), or return its code.

        Returns:
            The `Solution` (NumPy arrays, in the input's dtype): `value` the conductivity
            sigma (E,) or (T, E), S/sq (positive); `result` per frame as `GaussNewton`'s.
            `stats`: those of `GaussNewton` ("iterations", "misfit", "history",
            "reached_discrepancy"), and "contact_impedance" (L,) ohm m (estimated, or the
            model's) and "reference" (E,) the start and prior's centre, S/sq.

        Raises:
            ValueError: For data of the wrong shape or not finite, a frame that does not
                correlate positively with the model's voltages, or an unbound solver.
            diffeit.results.SolverError: With `throw=True`, for a frame that failed.
        """
        frames, single, dtype = self._frames(data)
        n_elements = self.model.n_elements
        if self.initial is None:
            start = np.log(self._homogeneous_fit(frames))[:, None] * np.ones(n_elements)
        else:
            start = np.log(np.broadcast_to(self.initial, (n_elements,)))[None] * np.ones((len(frames), 1))
        frames, iterates = self._solve(frames, start, self.estimate_contact_impedance)
        collected = _collected(frames, iterates, single)
        value = collected.pop("conductivity").astype(dtype)
        for name in ("contact_impedance", "reference"):
            collected[name] = collected[name].astype(dtype)
        result = collected.pop("result")
        return finished(value, result, collected, "Gauss-Newton", throw)


def _collected(frames: list[_Frame], iterates: list[_Iterate], single: bool) -> dict[str, Any]:
    """The iterates as arrays in float64 (the first frame's alone when one frame was given):
    conductivity, contact_impedance, reference, history, iterations, misfit,
    reached_discrepancy and result."""
    collected = {
        "conductivity": np.exp(np.stack([it.log_conductivity for it in iterates])),
        "contact_impedance": np.exp(np.stack([it.log_contact_impedance for it in iterates])),
        "reference": np.exp(np.stack([f.log_reference for f in frames])),
        "history": tuple(np.array(it.history) for it in iterates),
        "iterations": np.array([len(it.history) - 1 for it in iterates]),
        "misfit": np.array([np.linalg.norm(it.residual) for it in iterates]),
        "reached_discrepancy": np.array([it.reached_discrepancy for it in iterates]),
        "result": jax.tree_util.tree_map(lambda *codes: np.stack(codes), *(it.result for it in iterates)),
    }
    if not single:
        return collected
    first = {name: values[0] for name, values in collected.items() if name != "result"}
    first["iterations"] = int(first["iterations"])
    first["misfit"] = float(first["misfit"])
    first["reached_discrepancy"] = bool(first["reached_discrepancy"])
    return {**first, "result": iterates[0].result}


def _fitted(residual: np.ndarray, noise_norm: float | None) -> bool:
    """Whether the normalised `residual` is within the noise (the discrepancy principle, when
    the noise is known) or fits the data to rounding (`_EXACT_FIT`)."""
    norm = float(np.linalg.norm(residual))
    return norm <= _EXACT_FIT * np.sqrt(len(residual)) or (noise_norm is not None and norm <= noise_norm)


def _regularised_solve(gram: np.ndarray, alpha: float, right: np.ndarray) -> np.ndarray:
    """(G + alpha I)^-1 right for a positive semidefinite G. A Cholesky factorisation while
    alpha dominates rounding; for a tiny alpha an eigendecomposition that leaves G's numerical
    null space out (see LinearisedProblem), so that rounding errors are not divided by alpha."""
    gram = 0.5 * (gram + gram.T)
    if alpha > 1e-8 * np.trace(gram) / len(gram):
        return scipy.linalg.cho_solve(scipy.linalg.cho_factor(gram + alpha * np.eye(len(gram))), right)
    eigenvalues, vectors = scipy.linalg.eigh(gram)
    kept = eigenvalues > len(gram) * np.finfo(float).eps * eigenvalues[-1]
    return vectors @ (np.where(kept, 1 / (eigenvalues + alpha), 0) * (vectors.T @ right))


def _positive_map(value, n_elements: int) -> np.ndarray:
    array = np.broadcast_to(np.asarray(value, dtype=np.float64), (n_elements,)).copy()
    if not np.all(np.isfinite(array) & (array > 0)):
        raise ValueError("conductivity must be finite and positive (S/sq), one value or one per element")
    return array


def _evaluate(
    model: ForwardModel, log_sigma: np.ndarray, log_z: np.ndarray, with_jacobian: bool, with_z: bool
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Voltages (T, M), and dV/d ln(sigma) (T, M, E) and dV/d ln(z) (T, M, L) when asked (else
    None), for a batch of log-conductivities and log contact impedances: one vmapped call."""
    outputs = _evaluate_batch(model, jnp.asarray(log_sigma), jnp.asarray(log_z), with_jacobian, with_z)
    return tuple(None if output is None else np.asarray(output) for output in outputs)


@partial(jax.jit, static_argnums=(3, 4))
def _evaluate_batch(model: ForwardModel, log_sigma: jax.Array, log_z: jax.Array, with_jacobian: bool, with_z: bool):
    """`_evaluate` in JAX."""

    def one(log_sigma, log_z):
        sigma, z = jnp.exp(log_sigma), jnp.exp(log_z)
        voltages = model.measure(sigma, z)
        jacobian = model.jacobian(sigma, z, wrt="log_conductivity") if with_jacobian else None
        z_jacobian = model.jacobian(sigma, z, wrt="contact_impedance") * z if with_z else None
        return voltages, jacobian, z_jacobian

    return jax.vmap(one)(log_sigma, log_z)


@jax.jit
def _uniform_slope(model: ForwardModel, log_level: jax.Array, log_z: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Voltages (T, M) of homogeneous sheets of conductivity e^log_level (T,) and their
    derivative in log_level: one directional derivative (a forward-mode solve), not a Jacobian."""

    def voltages(level, log_z):
        sigma = jnp.exp(level) * jnp.ones(model.n_elements, level.dtype)
        return model.measure(sigma, jnp.exp(log_z))

    return jax.vmap(lambda level, z: jax.jvp(lambda x: voltages(x, z), (level,), (jnp.ones_like(level),)))(
        log_level, log_z
    )
