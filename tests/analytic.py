"""Reference solutions of 2D EIT on the unit disc (pure numpy/scipy).

Used by the tests to check the finite-element forward model. Conventions:

* Unit disc, polar ``(r, theta)``; boundary arc length is ``dtheta``.
* ``div(sigma grad u) = 0``, ``sigma`` homogeneous (``sigma0``) or with a concentric
  inclusion: ``sigma1`` for ``r < rho``, ``sigma0`` for ``rho < r < 1`` (sheet S/sq).
* Complete electrode model (CEM): electrode ``l`` covers ``[theta_l - alpha, theta_l + alpha]``
  with contact impedance ``z_l`` (ohm m); ``sigma du/dr = (U_l - u) / z_l`` on ``e_l``, ``0``
  between electrodes, ``int_{e_l} sigma du/dr dtheta = I_l`` (current *entering* through ``l``).
* Ground: electrode potentials are shifted so that ``sum_l U_l = 0``.
"""

from collections.abc import Callable

import numpy as np
import scipy.fft
import scipy.linalg

PRECONDITIONER_MODES = 512  # size K of the dense low-mode block preconditioner


def dirichlet_to_neumann_eigenvalues(
    n: np.ndarray,
    conductivity: float = 1.0,
    inclusion_radius: float = 0.0,
    inclusion_conductivity: float = 1.0,
) -> np.ndarray:
    """Eigenvalues ``lambda_n`` of the Dirichlet-to-Neumann map for the trace ``cos(n theta)``.

    Inside ``u = c r^n``, outside ``u = a (r^n + k r^-n)``; continuity of ``u`` and of
    ``sigma du/dr`` at ``r = rho`` gives ``k = mu rho^(2n)``, ``mu = (sigma0 - sigma1) / (sigma0 +
    sigma1)``, hence

        lambda_n = sigma0 n (1 - mu rho^(2n)) / (1 + mu rho^(2n)),

    which is ``sigma0 n`` for ``rho = 0`` or ``sigma1 = sigma0``.
    """
    mu = (conductivity - inclusion_conductivity) / (conductivity + inclusion_conductivity)
    k = mu * float(inclusion_radius) ** (2.0 * np.asarray(n, dtype=float))
    return conductivity * n * (1.0 - k) / (1.0 + k)


def _arc_integrals(k: np.ndarray, centres: np.ndarray, half_angle: float) -> tuple[np.ndarray, np.ndarray]:
    """``int_{e_l} cos(k theta)``, ``int_{e_l} sin(k theta)``, shapes ``(L, len(k))``.

    Over ``[c - alpha, c + alpha]``: ``2 alpha cos(k c) sinc(k alpha)`` and ``2 alpha sin(k c)
    sinc(k alpha)`` (``sinc(x) = sin(x) / x``), valid for every integer ``k``, including 0.
    """
    kc = np.outer(centres, k)
    width = 2.0 * half_angle * np.sinc(k * half_angle / np.pi)
    return width * np.cos(kc), width * np.sin(kc)


def cem_disc_electrode_potentials(
    currents: np.ndarray,
    electrode_angles: np.ndarray,
    half_angle: float,
    contact_impedance: float | np.ndarray,
    conductivity: float = 1.0,
    inclusion_radius: float = 0.0,
    inclusion_conductivity: float = 1.0,
    n_modes: int = 8192,
    extrapolate: bool = True,
) -> np.ndarray:
    """Electrode potentials of the CEM on the unit disc by a spectral Galerkin method.

    ``u`` is expanded in the conductivity-harmonic functions with boundary traces ``1,
    cos(n theta), sin(n theta)``, ``n = 1..N``. The Galerkin error is ``C N^-2 + o(N^-2)`` (the
    current density jumps at electrode edges), so by default the result is Richardson-extrapolated
    from ``N`` and ``N/2`` modes: ``(4 U_N - U_{N/2}) / 3``. Measured relative error at the default
    ``N`` (16 electrodes, ``alpha = 0.1``): 9e-10, 4e-10, 6e-7 for ``sigma z = 0.1, 0.01, 0.001``
    in ~0.5-1 s; the ``N^-2`` constant grows like ``1 / (sigma z)``, so raise ``n_modes`` (16384:
    1e-7 at ``sigma z = 0.001``) for very small contact impedance.

    Args:
        currents: ``(L,)`` or ``(n_patterns, L)`` injected currents [A], each summing to zero.
        electrode_angles: ``(L,)`` electrode centres ``theta_l`` [rad].
        half_angle: electrode half-angle ``alpha`` [rad] (arc length ``2 alpha``); electrodes must
            not overlap.
        contact_impedance: ``z_l`` [ohm m], positive, scalar or ``(L,)``.
        conductivity: background conductivity ``sigma0`` [S/sq].
        inclusion_radius: radius ``rho < 1`` of the concentric inclusion; 0 means homogeneous.
        inclusion_conductivity: inclusion conductivity ``sigma1`` [S/sq].
        n_modes: number ``N`` of Fourier modes.
        extrapolate: Richardson-extrapolate from ``N`` and ``N/2`` modes.

    Returns:
        Electrode potentials ``U`` [V], shaped like ``currents``, summing to zero over electrodes.
    """
    currents = np.asarray(currents, dtype=float)
    patterns = np.atleast_2d(currents)
    if np.any(np.abs(patterns.sum(axis=1)) > 1e-9 * np.abs(patterns).sum(axis=1)):
        raise ValueError("each current pattern must sum to zero")
    theta = np.asarray(electrode_angles, dtype=float)
    inv_z = np.broadcast_to(1.0 / np.asarray(contact_impedance, float), theta.shape)

    def solve(n: int) -> np.ndarray:
        dtn = dirichlet_to_neumann_eigenvalues(
            np.arange(1, n + 1), conductivity, inclusion_radius, inclusion_conductivity
        )
        return _galerkin_potentials(patterns, theta, half_angle, inv_z, dtn)

    potentials = solve(n_modes)
    if extrapolate:
        potentials = (4.0 * potentials - solve(n_modes // 2)) / 3.0
    return potentials.reshape(currents.shape)


def _galerkin_potentials(
    patterns: np.ndarray,
    theta: np.ndarray,
    half_angle: float,
    inv_z: np.ndarray,
    dtn: np.ndarray,
    rtol: float = 1e-13,
) -> np.ndarray:
    """Galerkin electrode potentials ``(n_patterns, L)`` with ``N = len(dtn)``.

    With the trace ``a_0 + sum_n a_n cos(n theta) + b_n sin(n theta)`` the CEM weak form

        int sigma grad u . grad v + sum_l (1/z_l) int_{e_l} (u - U_l)(v - V_l) dtheta = sum_l I_l V_l

    is symmetric positive definite once ``U_{L-1} = 0`` is grounded (its current is implied by
    ``sum I = 0``). The energy is ``pi lambda_n (a_n^2 + b_n^2)`` (diagonal, zero for ``a_0``);
    the boundary term multiplies the trace by ``w = sum_l 1_{e_l} / z_l``. Splitting into modes
    ``x = (a_n, b_n)`` and few unknowns ``y = (a_0, U_0..U_{L-2})``, ``[[A, C], [C^T, S]] [x; y]
    = [0; I]``: ``A X = C`` is solved by preconditioned CG (``A`` is diagonal + compact, so a
    few tens of FFT matvecs suffice), then ``(S - C^T X) y = I`` densely.
    """
    n_modes = dtn.size
    n = np.arange(1, n_modes + 1)
    # Only w's modes k <= 2N reach output modes m <= N, so w may be replaced
    # by that trig polynomial (from the closed-form arc integrals); then w f
    # has degree 3N and M > 4N samples multiply it without aliasing.
    k = np.arange(2 * n_modes + 1)
    w_cos, w_sin = (inv_z @ t for t in _arc_integrals(k, theta, half_angle))
    n_fft = scipy.fft.next_fast_len(4 * n_modes + 2, real=True)
    w_samples = scipy.fft.irfft(n_fft / (2 * np.pi) * (w_cos - 1j * w_sin), n_fft)

    def boundary_matvec(x: np.ndarray) -> np.ndarray:
        """``(p, 2N)`` rows ``(a_n, b_n)`` -> ``int w f cos, int w f sin``."""
        half = np.zeros((x.shape[0], n_fft // 2 + 1), dtype=complex)
        half[:, 1 : n_modes + 1] = 0.5 * n_fft * (x[:, :n_modes] - 1j * x[:, n_modes:])
        f = scipy.fft.irfft(half, n_fft)  # trace samples on a uniform grid
        g = 2 * np.pi / n_fft * scipy.fft.rfft(w_samples * f)[:, 1 : n_modes + 1]
        return np.hstack([g.real, -g.imag])

    energy = np.pi * np.concatenate([dtn, dtn])
    # Preconditioner: exact block for modes <= K (where the boundary term is
    # comparable to the energy), Jacobi above. Product-to-sum identities give
    # int w cos(m) cos(n) = (w_cos(m - n) + w_cos(m + n)) / 2 etc.
    n_low = min(n_modes, PRECONDITIONER_MODES)
    m, j = np.meshgrid(n[:n_low], n[:n_low], indexing="ij")
    cos_sin = w_sin[m + j] + np.sign(j - m) * w_sin[abs(j - m)]
    low = np.block([[w_cos[abs(m - j)] + w_cos[m + j], cos_sin], [cos_sin.T, w_cos[abs(m - j)] - w_cos[m + j]]])
    low_idx = np.concatenate([np.arange(n_low), n_modes + np.arange(n_low)])
    low = scipy.linalg.cho_factor(0.5 * low + np.diag(energy[low_idx]))
    diag = energy + 0.5 * w_cos[0] + 0.5 * np.concatenate([w_cos[2 * n], -w_cos[2 * n]])

    def precondition(r: np.ndarray) -> np.ndarray:
        z = r / diag
        z[:, low_idx] = scipy.linalg.cho_solve(low, r[:, low_idx].T).T
        return z

    # Rows of C^T: a_0 couples through int w phi_n, U_l through
    # -(1/z_l) int_{e_l} phi_n; S is the small block of (a_0, U).
    cos_e, sin_e = _arc_integrals(n, theta, half_angle)
    coupling = -inv_z[:, None] * np.hstack([cos_e, sin_e])  # (L, 2N)
    c_rows = np.vstack([-coupling.sum(axis=0), coupling[:-1]])
    s_mat = np.diag(np.concatenate([[w_cos[0]], 2 * half_angle * inv_z[:-1]]))
    s_mat[0, 1:] = s_mat[1:, 0] = -2 * half_angle * inv_z[:-1]

    x = _block_pcg(lambda v: energy * v + boundary_matvec(v), c_rows, precondition, rtol)
    rhs = np.vstack([np.zeros(patterns.shape[0]), patterns[:, :-1].T])
    y = scipy.linalg.solve(s_mat - c_rows @ x.T, rhs, assume_a="pos")
    potentials = np.zeros_like(patterns)
    potentials[:, :-1] = y[1:].T
    return potentials - potentials.mean(axis=1, keepdims=True)


def _block_pcg(
    matvec: Callable[[np.ndarray], np.ndarray],
    rhs: np.ndarray,
    precondition: Callable[[np.ndarray], np.ndarray],
    rtol: float,
    max_iter: int = 1000,
) -> np.ndarray:
    """Preconditioned CG for SPD ``A x = b``, one independent system per row."""
    x, r = np.zeros_like(rhs), rhs.copy()
    p = z = precondition(r)
    rz = np.sum(r * z, axis=1, keepdims=True)
    stop = rtol * np.linalg.norm(rhs, axis=1)
    for _ in range(max_iter):
        if np.all(np.linalg.norm(r, axis=1) <= stop):
            return x
        ap = matvec(p)
        step = rz / np.sum(p * ap, axis=1, keepdims=True)
        x, r = x + step * p, r - step * ap
        z = precondition(r)
        rz, rz_old = np.sum(r * z, axis=1, keepdims=True), rz
        p = z + (rz / rz_old) * p
    raise RuntimeError("CG did not converge")


def dipole_potential(
    x: np.ndarray,
    source: np.ndarray,
    sink: np.ndarray,
    current: float = 1.0,
    conductivity: float = 1.0,
) -> np.ndarray:
    """Potential of a boundary point-electrode dipole on the unit disc.

        u(x) = current / (pi sigma) * ln(|x - sink| / |x - source|)

    Current enters at the boundary point ``source`` and leaves at ``sink``. On ``|x| = 1``,
    ``d/dr ln|x - s| = 1/2`` for ``|s| = 1``, so the two logarithms' normal derivatives cancel
    and ``u`` is the exact Neumann solution (each log carries flux ``current`` through a half
    circle around its point). Defined up to an additive constant; ``x`` has shape ``(..., 2)``.
    """
    x = np.asarray(x, dtype=float)
    d_sink = np.linalg.norm(x - np.asarray(sink, dtype=float), axis=-1)
    d_source = np.linalg.norm(x - np.asarray(source, dtype=float), axis=-1)
    return current / (np.pi * conductivity) * np.log(d_sink / d_source)
