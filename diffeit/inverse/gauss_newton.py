"""Gauss-Newton reconstruction on log-conductivity, absolute and difference, in measurement space."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from .._threads import host_algebra
from ..forward import ForwardModel
from .linearised import check_frames
from .priors import AbstractPrior, PriorOperator, prior_named

# Armijo's sufficient-decrease constant, the step halvings tried, the largest change of
# ln(sigma) in one step (a factor e^4 ~ 55: steps beyond it are scaled down, not taken), and the
# Levenberg-Marquardt retries before an iteration gives up.
_ARMIJO = 1e-4
_HALVINGS = 12
_MAX_LOG_STEP = 4.0
_DAMPING_RETRIES = 6


@dataclass(frozen=True)
class GaussNewtonResult:
    """What a Gauss-Newton reconstruction returns (for a batch, arrays gain a leading T axis and
    `history`, `stop_reason`, `iterations` are tuples with one entry per frame).

    - `conductivity`: (E,) the reconstructed sheet conductivity, S/sq (positive by construction).
    - `contact_impedance`: (L,) ohm m: estimated when asked, else the model's.
    - `reference`: (E,) the conductivity the prior is centred on: the best homogeneous fit
      (absolute) or the background (difference); `conductivity - reference` is the change.
    - `history`: the objective (data misfit plus prior, normalised, see `GaussNewton`) at every
      iterate, the start included: it never rises.
    - `stop_reason`: "discrepancy" (misfit at the noise level), "stagnation" (the objective no
      longer decreases by a relative `stagnation_tolerance`), "max_iterations", or "line_search_failed" (no step
      decreased the objective, even damped).
    - `iterations`: accepted steps.
    - `misfit`: the final normalised data misfit ||V - v|| / s.
    """

    conductivity: np.ndarray
    contact_impedance: np.ndarray
    reference: np.ndarray
    history: np.ndarray | tuple[np.ndarray, ...]
    stop_reason: str | tuple[str, ...]
    iterations: int | tuple[int, ...]
    misfit: np.ndarray

    @property
    def conductivity_change(self) -> np.ndarray:
        """conductivity - reference, S/sq."""
        return self.conductivity - self.reference


@dataclass(frozen=True, eq=False)
class GaussNewton:
    """Regularised Gauss-Newton on s = ln(sigma), with Levenberg-Marquardt damping and a
    backtracking line search; every step is solved in measurement space (M x M).

    `GaussNewton(model, prior="laplace", hyperparameter=1e-2, max_iterations=20, noise=None,
    discrepancy_safety=1.05, contact_impedance_spread=1.0, stagnation_tolerance=1e-6)`

    The objective, with v the data, s_d = RMS(V(sigma_0)) the data scale at the start and
    s_ref the prior's centre (ln of the start for absolute imaging, of the background for
    difference imaging):

        Phi(s, w) = ||V(e^s, e^w) - v||^2 / s_d^2 + hyperparameter^2 (s - s_ref)^T (c P^-1) (s - s_ref)
                    + (hyperparameter / contact_impedance_spread)^2 ||w - w_ref||^2

    P is the prior of `diffeit.inverse.priors`, c its scale at the start (as in
    `LinearisedProblem`: the hyperparameter is unit-free and means what it means for
    `OneStep`); w = ln z enters only when the contact impedance is estimated. A step solves the
    damped linearisation: with J_n = dV/ds / s_d and the damping mu,

        delta = a + (P/c) J_n^T (J_n (P/c) J_n^T + (hyperparameter^2 + mu) I)^-1 (-r - J_n a),
        a = -hyperparameter^2 (s - s_ref) / (hyperparameter^2 + mu)

    (with an extra block for w), an M x M solve whatever the mesh size. mu shrinks after a
    full step and grows after a shortened or failed one. The iteration stops at the noise
    level when `noise` (percent of RMS(v)) is known (the discrepancy principle,
    ||r|| <= `discrepancy_safety` x the expected noise norm), when the objective stagnates (a
    relative decrease below `stagnation_tolerance`; 0 never stops for that), or after
    `max_iterations`. The prior's sparse factorisations are made once, at construction.

    `absolute(v)` and `difference(dv)` accept one frame (M,) or a batch (T, M): a batch runs
    in one loop, every frame with its own step, damping and stop.
    """

    model: ForwardModel
    prior: str | AbstractPrior = "laplace"
    hyperparameter: float = 1e-2
    max_iterations: int = 20
    noise: float | None = None
    discrepancy_safety: float = 1.05
    contact_impedance_spread: float = 1.0
    stagnation_tolerance: float = 1e-6
    bound_prior: Callable[[np.ndarray], PriorOperator] = field(init=False, repr=False)
    """The prior on the model's mesh, factorised once (`AbstractPrior.bind`)."""

    def __post_init__(self) -> None:
        if not (np.isfinite(self.hyperparameter) and self.hyperparameter > 0):
            raise ValueError(f"hyperparameter must be finite and positive; got {self.hyperparameter}")
        if self.max_iterations < 0:
            raise ValueError(f"max_iterations must be >= 0; got {self.max_iterations}")
        if self.noise is not None and not self.noise > 0:
            raise ValueError(f"noise is a percentage of RMS(v) and must be positive; got {self.noise}")
        if not self.contact_impedance_spread > 0:
            raise ValueError(f"contact_impedance_spread must be positive; got {self.contact_impedance_spread}")
        prior = prior_named(self.prior) if isinstance(self.prior, str) else self.prior
        if not isinstance(prior, AbstractPrior):
            raise ValueError(f"prior must be a name or a diffeit.inverse prior; got {self.prior!r}")
        if not self.stagnation_tolerance >= 0:
            raise ValueError(f"stagnation_tolerance must be >= 0; got {self.stagnation_tolerance}")
        object.__setattr__(self, "prior", prior)
        object.__setattr__(self, "bound_prior", prior.bind(self.model.mesh))

    @host_algebra
    def absolute(
        self,
        voltages: jax.Array,
        *,
        initial: float | np.ndarray | None = None,
        estimate_contact_impedance: bool = False,
    ) -> GaussNewtonResult:
        """Absolute imaging of measured voltages `voltages` (M,) or (T, M), volts.

        The start (and the prior's centre) is the best homogeneous conductivity, a closed-form
        least-squares fit v ~ V(1) / sigma refined by three scalar Newton steps, unless
        `initial` (S/sq, scalar or (E,)) is given. `estimate_contact_impedance` fits one
        contact impedance per electrode jointly, starting from the model's.
        """
        frames, single, dtype = self._frames(voltages)
        if initial is None:
            start = np.log(self._homogeneous_fit(frames))[:, None] * np.ones(self.model.n_elements)
        else:
            start = np.log(_positive_map(initial, self.model.n_elements))[None] * np.ones((len(frames), 1))
        return self._solve(frames, start, estimate_contact_impedance, single, dtype)

    @host_algebra
    def difference(self, voltage_difference: jax.Array, *, background: float | np.ndarray = 1.0) -> GaussNewtonResult:
        """Nonlinear difference imaging: the conductivity sigma with V(sigma) - V(background)
        = `voltage_difference` (M,) or (T, M) volts, starting from and regularised towards the
        `background` (S/sq, scalar or (E,)); `conductivity_change` is the image."""
        frames, single, dtype = self._frames(voltage_difference)
        background = _positive_map(background, self.model.n_elements)
        reference = np.asarray(self.model.measure(jnp.asarray(background)))
        start = np.log(background)[None] * np.ones((len(frames), 1))
        return self._solve(frames + reference, start, False, single, dtype)

    def _frames(self, frames: jax.Array) -> tuple[np.ndarray, bool, np.dtype]:
        """(T, M) float64 frames, whether one frame was given, and its dtype: the iteration runs
        in float64 (its line search compares objectives that differ in late digits), and the
        results come back in the input's precision."""
        array = np.asarray(check_frames(frames, self.model.n_measurements, "frames"))
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
        for _ in range(3):  # the contact impedance makes V(sigma) not exactly V(1) / sigma
            voltages, slope = _uniform_slope(self.model, jnp.asarray(level), jnp.asarray(z))
            voltages, slope = np.asarray(voltages), np.asarray(slope)  # V and dV / d ln(sigma_h), (T, M)
            level = level - np.sum(slope * (voltages - frames), axis=1) / np.sum(slope**2, axis=1)
        return np.exp(level)

    def _solve(
        self, frames: np.ndarray, start: np.ndarray, estimate_z: bool, single: bool, dtype: np.dtype
    ) -> GaussNewtonResult:
        model, mesh = self.model, self.model.mesh
        n_frames, n_electrodes = len(frames), mesh.n_electrodes
        weight = self.hyperparameter**2
        z_weight = weight / self.contact_impedance_spread**2
        log_z_ref = np.broadcast_to(np.log(np.asarray(model.contact_impedance)), (n_frames, n_electrodes)).copy()
        s, w, s_ref = start.copy(), log_z_ref.copy(), start.copy()

        voltages, jacobian, z_jacobian = _evaluate(model, jnp.asarray(s), jnp.asarray(w), True, estimate_z)
        voltages, jacobian = np.asarray(voltages), np.asarray(jacobian)
        scale = np.sqrt(np.mean(voltages**2, axis=1))  # s_d per frame, fixed from here on
        operators, prior_scale = [], np.empty(n_frames)
        for k in range(n_frames):
            normalised = jacobian[k] / scale[k]
            operator = self.bound_prior(normalised)
            operators.append(operator)
            prior_scale[k] = np.sum(operator.root_transpose(np.ascontiguousarray(normalised.T)) ** 2) / len(normalised)
        noise_norm = None
        if self.noise is not None:
            rms_data = np.sqrt(np.mean(frames**2, axis=1))
            noise_norm = self.discrepancy_safety * self.noise / 100 * rms_data / scale * np.sqrt(frames.shape[1])

        def objective(k: int, residual: np.ndarray, s_k: np.ndarray, w_k: np.ndarray) -> float:
            deviation = s_k - s_ref[k]
            prior_term = prior_scale[k] * deviation @ operators[k].precision(deviation)
            return float(residual @ residual + weight * prior_term + z_weight * np.sum((w_k - log_z_ref[k]) ** 2))

        residual = (voltages - frames) / scale[:, None]
        value = np.array([objective(k, residual[k], s[k], w[k]) for k in range(n_frames)])
        history = [[v] for v in value]
        stop = [""] * n_frames
        iterations = [0] * n_frames
        damping = np.zeros(n_frames)
        active = np.ones(n_frames, dtype=bool)
        if noise_norm is not None:
            for k in np.flatnonzero(np.linalg.norm(residual, axis=1) <= noise_norm):
                stop[k], active[k] = "discrepancy", False

        for _ in range(self.max_iterations):
            if not active.any():
                break
            steps, slopes = {}, {}
            for k in np.flatnonzero(active):
                steps[k], slopes[k] = self._step(
                    jacobian[k] / scale[k],
                    None if z_jacobian is None else np.asarray(z_jacobian[k]) / scale[k],
                    residual[k],
                    s[k] - s_ref[k],
                    w[k] - log_z_ref[k],
                    operators[k],
                    prior_scale[k],
                    damping[k],
                    z_weight,
                )
            accepted = self._line_search(frames, scale, s, w, steps, slopes, value, objective, estimate_z)
            for k in np.flatnonzero(active):
                if k not in accepted:
                    # No decrease along this step: damp harder (shorter, more regularised steps).
                    damping[k] = max(10 * damping[k], weight)
                    if damping[k] > weight * 10**_DAMPING_RETRIES:
                        stop[k], active[k] = "line_search_failed", False
                    continue
                length, new_s, new_w, new_value, new_residual = accepted[k]
                damping[k] = damping[k] / 3 if length == 1.0 else max(2 * damping[k], weight * 1e-3)
                decrease = (value[k] - new_value) / max(value[k], np.finfo(float).tiny)
                s[k], w[k], value[k], residual[k] = new_s, new_w, new_value, new_residual
                history[k].append(new_value)
                iterations[k] += 1
                if noise_norm is not None and np.linalg.norm(new_residual) <= noise_norm[k]:
                    stop[k], active[k] = "discrepancy", False
                elif decrease < self.stagnation_tolerance:
                    stop[k], active[k] = "stagnation", False
            if active.any():
                # The whole batch, always: a fixed shape compiles once.
                _, jacobian, z_jacobian = _evaluate(model, jnp.asarray(s), jnp.asarray(w), True, estimate_z)
                jacobian = np.asarray(jacobian)
        for k in np.flatnonzero(active):
            stop[k] = "max_iterations"

        conductivity = np.exp(s).astype(dtype)
        contact_impedance = np.exp(w).astype(dtype)
        misfit = np.linalg.norm(residual, axis=1)
        reference = np.exp(s_ref).astype(dtype)
        histories = tuple(np.array(h) for h in history)
        if single:
            return GaussNewtonResult(
                conductivity[0], contact_impedance[0], reference[0], histories[0], stop[0], iterations[0], misfit[0]
            )
        return GaussNewtonResult(
            conductivity, contact_impedance, reference, histories, tuple(stop), tuple(iterations), misfit
        )

    def _step(
        self,
        jacobian: np.ndarray,
        z_jacobian: np.ndarray | None,
        residual: np.ndarray,
        deviation: np.ndarray,
        z_deviation: np.ndarray,
        operator: PriorOperator,
        prior_scale: float,
        damping: float,
        z_weight: float,
    ) -> tuple[tuple[np.ndarray, np.ndarray], float]:
        """The damped Gauss-Newton step (delta_s, delta_w) and the objective's directional
        derivative along it (negative: a descent direction)."""
        weight = self.hyperparameter**2
        alpha = weight + damping
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
            beta = z_weight * (1 + damping / weight)
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
        return (delta_s, delta_w), float(slope)

    def _line_search(self, frames, scale, s, w, steps, slopes, value, objective, estimate_z) -> dict:
        """Backtracking (Armijo) for every frame with a step at once: {frame: (length, s, w,
        objective, residual)} for the frames whose objective decreased sufficiently. Each
        halving evaluates the whole batch (a fixed shape compiles once); frames without a
        pending trial stay where they are."""
        accepted, lengths = {}, {}
        for k, (delta_s, delta_w) in steps.items():
            largest = max(np.abs(delta_s).max(), np.abs(delta_w).max(initial=0.0))
            lengths[k] = min(1.0, _MAX_LOG_STEP / largest) if largest > 0 else 1.0
        pending = [k for k in steps if slopes[k] < 0]
        for _ in range(_HALVINGS):
            if not pending:
                break
            trial_s, trial_w = s.copy(), w.copy()
            for k in pending:
                trial_s[k] = s[k] + lengths[k] * steps[k][0]
                trial_w[k] = w[k] + lengths[k] * steps[k][1]
            voltages, _, _ = _evaluate(self.model, jnp.asarray(trial_s), jnp.asarray(trial_w), False, estimate_z)
            residual = (np.asarray(voltages) - frames) / scale[:, None]
            still = []
            for k in pending:
                trial = objective(k, residual[k], trial_s[k], trial_w[k])
                if np.isfinite(trial) and trial <= value[k] + _ARMIJO * lengths[k] * slopes[k]:
                    accepted[k] = (lengths[k], trial_s[k], trial_w[k], trial, residual[k])
                else:
                    lengths[k] /= 2
                    still.append(k)
            pending = still
        return accepted


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


@partial(jax.jit, static_argnums=(3, 4))
def _evaluate(model: ForwardModel, log_sigma: jax.Array, log_z: jax.Array, with_jacobian: bool, with_z: bool):
    """Voltages (T, M), and dV/d ln(sigma) (T, M, E) and dV/d ln(z) (T, M, L) when asked, for a
    batch of log-conductivities and log contact impedances: one vmapped call."""

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
