"""Filters for the four-mode Markov measurement channel (Moayedi, Soh & Foo 2009).

Augmented model (eqs 5–19), made exact
--------------------------------------
The paper stacks ``X(k) = [x(k); x(k−1); y(k−1)]`` with noise ``W(k) = [w(k); v(k); v(k−1)]``
(eq. 7) and treats ``W`` as white (eq. 26). It is not: ``v(k−1)`` is in ``W(k−1)`` and in
``W(k)``, and ``X(k)`` contains ``y(k−1)``, which holds ``v(k−1)`` in modes 1 and 3. We
therefore carry ``v(k−1)`` in the state,

    ξ(k) = [x(k); x(k−1); y(k−1); v(k−1)],      ε(k) = [w(k); v(k)],
    E ε(k) ε(k)ᵀ = Σ = [[Q, S], [Sᵀ, R]]  (white),

which also handles a process/measurement noise cross-covariance ``S`` (Example 1 of the
paper, where ``v = 0.2 w``, has a singular Σ). For mode ``θ(k) = q`` (0-based ``i = q − 1``):

    y(k)   = H_q ξ(k) + J_q ε(k)                      (eqs 6, 9, 12, 15, 18)
    ξ(k+1) = F_q ξ(k) + G_q ε(k),  F_q = [[A,0,0,0],[I,0,0,0],[H_q],[0,0,0,0]],
                                   G_q = [[I,0],[0,0],[J_q],[0,I]]   (eqs 8, 11, 14, 17)

    q=1: H=[C 0 0 0], J=[0 I]    q=2: H=[0 C 0 I], J=0
    q=3: H=0,          J=[0 I]    q=4: H=[0 0 I 0], J=0

The initial condition follows eq. (35): ``x(−1) = x(0)``, ``y(−1) = v(−1)``.

Filters (all run on the same simulated runs)
--------------------------------------------
* :func:`lmmse_filter` — the exact linear minimum-mean-square filter for this Markov-jump
  system when the receiver does **not** see the modes (Costa 1994/2002 construction):
  ``Z(k) = [ξ(k)·1{θ(k)=1}; …; ξ(k)·1{θ(k)=4}]`` obeys ``Z(k+1) = 𝔽 Z(k) + ν(k)``,
  ``y(k) = ℍ Z(k) + η(k)`` with ``𝔽[j, i] = ρ_{j/i} F_i``, ``ℍ = [H_1 … H_4]``,
  ``η = J_θ ε`` and ``ν`` a martingale difference; ``ν, η`` are uncorrelated with the past,
  so the Kalman recursion with their second moments (from ``Q_i(k) = E ξξᵀ 1{θ(k)=i}``) is
  the best *linear* (affine) estimator of ``Z`` — hence of ``ξ = Σ_i Z_i``.
* :func:`naive_filter` — the Kalman filter that assumes every packet is mode 1.
* the LMI filter of the paper (:mod:`netkf_cli.estimators.markov_lmi`).
* :func:`mode_aware_step` — the time-varying Kalman filter on ξ for a receiver that knows
  θ(k) (per run; the lower bound).

All filters whose gains do not depend on the data are :class:`LinearFilter` objects
``s(k+1) = A_s(k) s(k) + G_s(k) y(k)``, ``x̂(k|k−1) = E_p s(k)``,
``x̂(k|k) = E_f(k) s(k) + L_f(k) y(k)``; :func:`exact_mse` evaluates any of them exactly
through the second moments of the joint Markov-jump system ``[ξ; s]``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from netkf_cli.errors import ConfigError
from netkf_cli.spec import EstimatorModel, NonNegFloat, NonNegInt, PositiveFloat

N_MODES = 4


# --------------------------------------------------------------------------- helpers
def psd_sqrt(M: np.ndarray) -> np.ndarray:
    """A factor ``L`` with ``L Lᵀ = M`` for symmetric PSD ``M`` (eigenvalues < 0 clipped)."""
    M = (M + M.T) / 2
    w, V = np.linalg.eigh(M)
    return V * np.sqrt(np.clip(w, 0.0, None))


def pinv_psd(S: np.ndarray, scale: np.ndarray | float, rtol: float = 1e-9) -> np.ndarray:
    """Pseudo-inverse of symmetric PSD matrices (batched over leading axes).

    Eigenvalues below ``rtol * scale`` count as zero: an innovation with (numerically) zero
    variance carries no information and gets zero gain — e.g. a held packet (mode 4) whose
    value the receiver already knows.
    """
    S = np.asarray(S)
    m = S.shape[-1]
    scale = np.asarray(scale, dtype=float)
    if m == 1:
        s = S[..., 0, 0]
        ok = s > rtol * scale
        inv = np.where(ok, 1.0 / np.where(ok, s, 1.0), 0.0)
        return inv[..., None, None]
    w, V = np.linalg.eigh((S + np.swapaxes(S, -1, -2)) / 2)
    thr = (rtol * scale)[..., None] if np.ndim(scale) else rtol * scale
    ok = w > thr
    winv = np.where(ok, 1.0 / np.where(ok, w, 1.0), 0.0)
    return (V * winv[..., None, :]) @ np.swapaxes(V, -1, -2)


# --------------------------------------------------------------------------- model
@dataclass(frozen=True, eq=False)
class AugmentedModel:
    """The exact four-mode augmented model (module docstring; eqs 5–19 with v(k−1) in the state)."""

    A: np.ndarray
    C: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    S: np.ndarray
    F: np.ndarray = field(repr=False)  # (N, d, d)
    G: np.ndarray = field(repr=False)  # (N, d, p)
    H: np.ndarray = field(repr=False)  # (N, m, d)
    J: np.ndarray = field(repr=False)  # (N, m, p)
    Sigma: np.ndarray = field(repr=False)  # (p, p) covariance of ε = [w; v]
    Lsig: np.ndarray = field(repr=False)  # (p, p) with Lsig Lsigᵀ = Sigma

    @property
    def n(self) -> int:
        return self.A.shape[0]

    @property
    def m(self) -> int:
        return self.C.shape[0]

    @property
    def d(self) -> int:
        return 2 * self.n + 2 * self.m

    @property
    def p(self) -> int:
        return self.n + self.m

    @property
    def Ex(self) -> np.ndarray:
        """Selects x(k) from ξ(k)."""
        E = np.zeros((self.n, self.d))
        E[:, : self.n] = np.eye(self.n)
        return E

    @classmethod
    def build(cls, A, C, Q, R, S=None) -> "AugmentedModel":
        A, C, Q, R = (np.atleast_2d(np.asarray(M, dtype=float)) for M in (A, C, Q, R))
        n, m = A.shape[0], C.shape[0]
        S = np.zeros((n, m)) if S is None else np.atleast_2d(np.asarray(S, dtype=float))
        if S.shape != (n, m):
            raise ValueError(f"S must be {n}×{m} (E[w vᵀ]), got {S.shape}")
        Sigma = np.block([[Q, S], [S.T, R]])
        Sigma = (Sigma + Sigma.T) / 2
        if np.linalg.eigvalsh(Sigma).min() < -1e-9 * max(1.0, np.abs(Sigma).max()):
            raise ValueError("the joint noise covariance [[Q, S], [Sᵀ, R]] must be positive semi-definite")
        d, p = 2 * n + 2 * m, n + m
        ix, ixp, iy, iv = slice(0, n), slice(n, 2 * n), slice(2 * n, 2 * n + m), slice(2 * n + m, d)
        H = np.zeros((N_MODES, m, d))
        J = np.zeros((N_MODES, m, p))
        H[0][:, ix] = C                      # q=1: y = C x(k) + v(k)          (eq. 9)
        J[0][:, n:] = np.eye(m)
        H[1][:, ixp] = C                     # q=2: y = C x(k−1) + v(k−1)      (eq. 12)
        H[1][:, iv] = np.eye(m)
        J[2][:, n:] = np.eye(m)              # q=3: y = v(k)                   (eq. 15)
        H[3][:, iy] = np.eye(m)              # q=4: y = y(k−1)                 (eq. 18)
        F = np.zeros((N_MODES, d, d))
        G = np.zeros((N_MODES, d, p))
        for i in range(N_MODES):
            F[i][ix, ix] = A
            F[i][ixp, ix] = np.eye(n)
            F[i][iy, :] = H[i]
            G[i][ix, :n] = np.eye(n)
            G[i][iy, :] = J[i]
            G[i][iv, n:] = np.eye(m)
        return cls(A, C, Q, R, S, F, G, H, J, Sigma, psd_sqrt(Sigma))

    def initial_moments(self, x0: np.ndarray, P0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean and covariance of ξ(0) = [x(0); x(0); v(−1); v(−1)] (eq. 35)."""
        n, m = self.n, self.m
        mean = np.concatenate([x0, x0, np.zeros(2 * m)])
        cov = np.zeros((self.d, self.d))
        cov[: 2 * n, : 2 * n] = np.block([[P0, P0], [P0, P0]])
        cov[2 * n:, 2 * n:] = np.block([[self.R, self.R], [self.R, self.R]])
        return mean, cov


# --------------------------------------------------------------------------- linear filters
@dataclass(frozen=True, eq=False)
class LinearFilter:
    """A filter with data-independent gains, length-K sequences.

    ``s(k+1) = As[k] s(k) + Gs[k] y(k)``; ``x̂(k|k−1) = Ep s(k)``;
    ``x̂(k|k) = Ef[k] s(k) + Lf[k] y(k)``; ``s(0) = s0``.
    ``predicted`` holds the filter's own claim of E‖e(k|k−1)‖² and E‖e(k|k)‖² (if any).
    """

    name: str
    As: np.ndarray  # (K, r, r)
    Gs: np.ndarray  # (K, r, m)
    Ep: np.ndarray  # (n, r)
    Ef: np.ndarray  # (K, n, r)
    Lf: np.ndarray  # (K, n, m)
    s0: np.ndarray  # (r,)
    s0_map: np.ndarray  # (r, n): s0 = s0_map @ x̂0 (how the initial estimate enters the state)
    predicted: dict = field(default_factory=dict)

    def with_initial_estimate(self, xhat0: np.ndarray) -> "LinearFilter":
        """The same gains started from another initial estimate x̂(0) (e.g. the paper's x_s(0))."""
        return replace(self, s0=self.s0_map @ np.asarray(xhat0, dtype=float))

    @property
    def horizon(self) -> int:
        return self.As.shape[0]


def naive_filter(model: AugmentedModel, x0: np.ndarray, P0: np.ndarray, horizon: int) -> LinearFilter:
    """Kalman filter that assumes every y(k) = C x(k) + v(k) (mode 1), with E[w vᵀ] = S.

    Predictor form with correlated noise: K = (A P Cᵀ + S) Σ_y⁻¹, Σ_y = C P Cᵀ + R,
    P⁺ = A P Aᵀ + Q − K Σ_y Kᵀ; filtered gain K_f = P Cᵀ Σ_y⁻¹.
    """
    A, C, Q, R, S = model.A, model.C, model.Q, model.R, model.S
    n, m = model.n, model.m
    As = np.empty((horizon, n, n)); Gs = np.empty((horizon, n, m))
    Ef = np.empty((horizon, n, n)); Lf = np.empty((horizon, n, m))
    P = np.array(P0, dtype=float)
    tp, tf = np.empty(horizon), np.empty(horizon)
    for k in range(horizon):
        Sy = C @ P @ C.T + R
        Kf = np.linalg.solve(Sy, C @ P).T
        K = np.linalg.solve(Sy, (A @ P @ C.T + S).T).T
        tp[k] = np.trace(P)
        tf[k] = np.trace(P - Kf @ Sy @ Kf.T)
        As[k], Gs[k] = A - K @ C, K
        Ef[k], Lf[k] = np.eye(n) - Kf @ C, Kf
        P = A @ P @ A.T + Q - K @ Sy @ K.T
        P = (P + P.T) / 2
    return LinearFilter("naive_kf", As, Gs, np.eye(n), Ef, Lf, np.asarray(x0, float).copy(), np.eye(n),
                        {"assumed_pred": tp, "assumed_filt": tf})


def mode_second_moments(model: AugmentedModel, T: np.ndarray, pi0: np.ndarray, M0: np.ndarray, horizon: int):
    """π_i(k) and Q_i(k) = E[ξ(k) ξ(k)ᵀ 1{θ(k)=i}] for k = 0..horizon−1 (uncentered)."""
    N, d = N_MODES, model.d
    pis = np.empty((horizon, N)); Qs = np.empty((horizon, N, d, d))
    pi = np.asarray(pi0, float).copy()
    Qi = pi[:, None, None] * M0[None]
    GSG = np.einsum("iap,pq,ibq->iab", model.G, model.Sigma, model.G)
    for k in range(horizon):
        pis[k], Qs[k] = pi, Qi
        inner = model.F @ Qi @ np.swapaxes(model.F, 1, 2) + pi[:, None, None] * GSG
        Qi = np.einsum("ij,iab->jab", T, inner)
        Qi = (Qi + np.swapaxes(Qi, 1, 2)) / 2
        pi = T.T @ pi
    return pis, Qs


def lmmse_filter(model: AugmentedModel, T: np.ndarray, pi0: np.ndarray, x0: np.ndarray, P0: np.ndarray,
                 horizon: int) -> LinearFilter:
    """Exact LMMSE filter for the Markov-jump model with unobserved modes (module docstring).

    With ``Q_i(k)``, ``π_i(k)`` from :func:`mode_second_moments` and ``p_ij = ρ_{j/i}``:

        Σ_ν[j,l] = Σ_i (δ_jl p_ij − p_ij p_il) F_i Q_i F_iᵀ + δ_jl Σ_i p_ij π_i G_i Σ G_iᵀ
        Σ_νη[j]  = Σ_i π_i p_ij G_i Σ J_iᵀ,      Σ_η = Σ_i π_i J_i Σ J_iᵀ
        Σ_y = ℍ P ℍᵀ + Σ_η,  K = (𝔽 P ℍᵀ + Σ_νη) Σ_y⁺,  P⁺ = 𝔽 P 𝔽ᵀ + Σ_ν − K Σ_y Kᵀ
        Ẑ(k+1) = 𝔽 Ẑ + K (y − ℍ Ẑ);  filtered: K_f = P ℍᵀ Σ_y⁺.

    Initial: Ẑ_i(0) = π_i(0) ξ̄(0); P(0)[i,j] = δ_ij π_i M0 − π_i π_j ξ̄ ξ̄ᵀ, M0 = E ξ(0)ξ(0)ᵀ.
    """
    N, d, n, m = N_MODES, model.d, model.n, model.m
    r = N * d
    xbar, cov = model.initial_moments(np.asarray(x0, float), np.asarray(P0, float))
    M0 = cov + np.outer(xbar, xbar)
    pis, Qs = mode_second_moments(model, T, pi0, M0, horizon)
    F, G, H, J, Sig = model.F, model.G, model.H, model.J, model.Sigma
    FF = np.zeros((r, r))
    for j in range(N):
        for i in range(N):
            FF[j * d:(j + 1) * d, i * d:(i + 1) * d] = T[i, j] * F[i]
    HH = np.concatenate(list(H), axis=1)  # (m, r)
    GSG = np.einsum("iap,pq,ibq->iab", G, Sig, G)
    GSJ = np.einsum("iap,pq,ibq->iab", G, Sig, J)
    JSJ = np.einsum("iap,pq,ibq->iab", J, Sig, J)
    sumI = np.tile(np.eye(d), (1, N))  # ξ = Σ_i Z_i
    Ep = model.Ex @ sumI
    P = -np.kron(np.outer(pi0, pi0), np.outer(xbar, xbar))
    for i in range(N):
        P[i * d:(i + 1) * d, i * d:(i + 1) * d] += pi0[i] * M0
    As = np.empty((horizon, r, r)); Gs = np.empty((horizon, r, m))
    Ef = np.empty((horizon, n, r)); Lf = np.empty((horizon, n, m))
    tp, tf = np.empty(horizon), np.empty(horizon)
    for k in range(horizon):
        pi, Qi = pis[k], Qs[k]
        FQF = F @ Qi @ np.swapaxes(F, 1, 2)
        Snu = np.zeros((r, r))
        for j in range(N):
            for l in range(N):
                blk = -np.einsum("i,i,iab->ab", T[:, j], T[:, l], FQF)
                if j == l:
                    blk = blk + np.einsum("i,iab->ab", T[:, j], FQF) + np.einsum("i,i,iab->ab", T[:, j], pi, GSG)
                Snu[j * d:(j + 1) * d, l * d:(l + 1) * d] = blk
        Snueta = np.concatenate([np.einsum("i,i,iab->ab", pi, T[:, j], GSJ) for j in range(N)], axis=0)
        Seta = np.einsum("i,iab->ab", pi, JSJ)
        Sy = HH @ P @ HH.T + Seta
        Syinv = pinv_psd(Sy, np.trace(Sy) + 1e-300)
        Kf = P @ HH.T @ Syinv
        K = (FF @ P @ HH.T + Snueta) @ Syinv
        Pf = P - Kf @ Sy @ Kf.T
        tp[k] = np.trace(Ep @ P @ Ep.T)
        tf[k] = np.trace(Ep @ Pf @ Ep.T)
        As[k], Gs[k] = FF - K @ HH, K
        Ef[k], Lf[k] = Ep @ (np.eye(r) - Kf @ HH), Ep @ Kf
        P = FF @ P @ FF.T + Snu - K @ Sy @ K.T
        P = (P + P.T) / 2
    # Ẑ_i(0) = π_i(0) [x̂0; x̂0; 0; 0]
    lift = np.zeros((d, n)); lift[:n] = np.eye(n); lift[n:2 * n] = np.eye(n)
    s0_map = np.concatenate([pi0[i] * lift for i in range(N)], axis=0)
    return LinearFilter("lmmse", As, Gs, Ep, Ef, Lf, s0_map @ np.asarray(x0, float), s0_map,
                        {"pred": tp, "filt": tf})


def exact_mse(model: AugmentedModel, filt: LinearFilter, T: np.ndarray, pi0: np.ndarray,
              x0: np.ndarray, P0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact E‖x(k) − x̂(k|k−1)‖² and E‖x(k) − x̂(k|k)‖², k = 0..K−1, for any LinearFilter.

    Second moments of the joint Markov-jump system η = [ξ; s]:
    ``𝒜_q = [[F_q, 0], [G_s H_q, A_s]]``, ``ℬ_q = [[G_q], [G_s J_q]]``,
    ``Q_j(k+1) = Σ_i ρ_{j/i} (𝒜_i Q_i 𝒜_iᵀ + π_i ℬ_i Σ ℬ_iᵀ)``, ``Q_i(0) = π_i(0) E η(0)η(0)ᵀ``.
    Exact whatever the gains and the initial estimate s0 (no Gaussianity needed).
    """
    N, d, n = N_MODES, model.d, model.n
    K, r = filt.horizon, filt.As.shape[1]
    D = d + r
    xbar, cov = model.initial_moments(np.asarray(x0, float), np.asarray(P0, float))
    eta0 = np.concatenate([xbar, filt.s0])
    M0 = np.outer(eta0, eta0)
    M0[:d, :d] += cov
    pi = np.asarray(pi0, float).copy()
    Qi = pi[:, None, None] * M0[None]
    Ex = model.Ex
    mse_p, mse_f = np.empty(K), np.empty(K)
    Cp = np.concatenate([Ex, -filt.Ep], axis=1)
    for k in range(K):
        Qsum = Qi.sum(0)
        mse_p[k] = np.trace(Cp @ Qsum @ Cp.T)
        tot = 0.0
        for i in range(N):
            Cf = np.concatenate([Ex - filt.Lf[k] @ model.H[i], -filt.Ef[k]], axis=1)
            LJ = filt.Lf[k] @ model.J[i]
            tot += np.trace(Cf @ Qi[i] @ Cf.T) + pi[i] * np.trace(LJ @ model.Sigma @ LJ.T)
        mse_f[k] = tot
        if k == K - 1:
            break
        Aq = np.zeros((N, D, D)); Bq = np.zeros((N, D, model.p))
        for i in range(N):
            Aq[i, :d, :d] = model.F[i]
            Aq[i, d:, :d] = filt.Gs[k] @ model.H[i]
            Aq[i, d:, d:] = filt.As[k]
            Bq[i, :d] = model.G[i]
            Bq[i, d:] = filt.Gs[k] @ model.J[i]
        inner = Aq @ Qi @ np.swapaxes(Aq, 1, 2) + pi[:, None, None] * (Bq @ model.Sigma @ np.swapaxes(Bq, 1, 2))
        Qi = np.einsum("ij,iab->jab", T, inner)
        Qi = (Qi + np.swapaxes(Qi, 1, 2)) / 2
        pi = T.T @ pi
    return mse_p, mse_f


# --------------------------------------------------------------------------- simulation
def draw_initial(model: AugmentedModel, rng: np.random.Generator, runs: int, x0, P0) -> np.ndarray:
    """ξ(0) for ``runs`` runs, shape (runs, d): x(0) ~ N(x0, P0), x(−1) = x(0), y(−1) = v(−1) (eq. 35)."""
    n, m = model.n, model.m
    x = np.asarray(x0, float)[None, :] + rng.standard_normal((runs, n)) @ psd_sqrt(np.asarray(P0, float)).T
    v = rng.standard_normal((runs, m)) @ psd_sqrt(model.R).T
    return np.concatenate([x, x, v, v], axis=1)


def draw_noise(model: AugmentedModel, rng: np.random.Generator, runs: int, horizon: int) -> np.ndarray:
    """ε(k) = [w(k); v(k)] ~ N(0, Σ), shape (horizon, runs, p)."""
    return rng.standard_normal((horizon, runs, model.p)) @ model.Lsig.T


def plant_step(model: AugmentedModel, xi: np.ndarray, eps: np.ndarray, mode: np.ndarray):
    """One step of the true system for all runs: returns y(k) (runs, m) and ξ(k+1) (runs, d)."""
    runs = xi.shape[0]
    idx = np.arange(runs)
    y_all = np.einsum("qmd,rd->qrm", model.H, xi) + np.einsum("qmp,rp->qrm", model.J, eps)
    y = y_all[mode, idx]
    n, m = model.n, model.m
    x = xi[:, :n]
    xi_next = np.concatenate([x @ model.A.T + eps[:, :n], x, y, eps[:, n:]], axis=1)
    return y, xi_next


class ModeAwareKF:
    """Time-varying KF on ξ for a receiver that knows θ(k) (per run, batched; ``P`` is (runs, d, d)).

    With F, G, H, J of the current mode: Σ_y = H P Hᵀ + J Σ Jᵀ,
    K = (F P Hᵀ + G Σ Jᵀ) Σ_y⁺, ξ̂⁺ = F ξ̂ + K (y − H ξ̂), P⁺ = F P Fᵀ + G Σ Gᵀ − K Σ_y Kᵀ;
    filtered K_f = P Hᵀ Σ_y⁺. Σ_y⁺ treats (numerically) zero innovation variance as no
    information (a held packet, or a delayed packet whose content is already known).
    """

    name = "mode_aware_kf"

    def __init__(self, model: AugmentedModel, runs: int, xhat0: np.ndarray, P0: np.ndarray):
        self.model = model
        mean, cov = model.initial_moments(np.asarray(xhat0, float), np.asarray(P0, float))
        self.xi = np.repeat(mean[None], runs, axis=0)
        self.P = np.repeat(cov[None], runs, axis=0)
        m = model
        self.GSG = np.einsum("iap,pq,ibq->iab", m.G, m.Sigma, m.G)
        self.GSJ = np.einsum("iap,pq,ibq->iab", m.G, m.Sigma, m.J)
        self.JSJ = np.einsum("iap,pq,ibq->iab", m.J, m.Sigma, m.J)
        self.scale = np.trace(m.Sigma)

    def predicted(self) -> tuple[np.ndarray, np.ndarray]:
        n = self.model.n
        return self.xi[:, :n], np.trace(self.P[:, :n, :n], axis1=1, axis2=2)

    def step(self, y: np.ndarray, mode: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Update with y(k) in mode θ(k); returns x̂(k|k) and tr P_x(k|k); moves to k+1."""
        md = self.model
        n = md.n
        F, H = md.F[mode], md.H[mode]
        P, xi = self.P, self.xi
        PHt = P @ np.swapaxes(H, 1, 2)
        Sy = H @ PHt + self.JSJ[mode]
        scale = self.scale + np.trace(P, axis1=1, axis2=2)
        Syi = pinv_psd(Sy, scale)
        innov = y - np.einsum("rmd,rd->rm", H, xi)
        Kf = PHt @ Syi
        K = (F @ PHt + self.GSJ[mode]) @ Syi
        xf = xi[:, :n] + np.einsum("rdm,rm->rd", Kf[:, :n], innov)
        Pf_x = P[:, :n, :n] - Kf[:, :n] @ Sy @ np.swapaxes(Kf[:, :n], 1, 2)
        self.xi = np.einsum("rab,rb->ra", F, xi) + np.einsum("rdm,rm->rd", K, innov)
        Pn = F @ P @ np.swapaxes(F, 1, 2) + self.GSG[mode] - K @ Sy @ np.swapaxes(K, 1, 2)
        self.P = (Pn + np.swapaxes(Pn, 1, 2)) / 2
        return xf, np.trace(Pf_x, axis1=1, axis2=2)


def run_linear(filt: LinearFilter, ys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Run a LinearFilter on y (horizon, runs, m); returns x̂(k|k−1), x̂(k|k), each (horizon, runs, n)."""
    K, runs = ys.shape[0], ys.shape[1]
    s = np.repeat(filt.s0[None], runs, axis=0)
    xp = np.empty((K, runs, filt.Ep.shape[0])); xf = np.empty_like(xp)
    for k in range(K):
        xp[k] = s @ filt.Ep.T
        xf[k] = s @ filt.Ef[k].T + ys[k] @ filt.Lf[k].T
        s = s @ filt.As[k].T + ys[k] @ filt.Gs[k].T
    return xp, xf


# --------------------------------------------------------------------------- scenario block
class MarkovLMIEstimator(EstimatorModel):
    """``kind: markov_lmi`` — the paper's LMI filter design (Sec. III) and its comparison filters.

    ``rho`` are the mode marginals the design uses (the paper's printed ρ_q; ``stationary`` =
    computed from the channel). ``design: closed_form`` (default) solves each per-step LMI problem
    through its normal equations (the same convex quadratic; the SDP optimum matches it within the
    solver tolerance) and solves the SDP itself at ``sdp_check`` steps as a check; ``design: sdp``
    solves every step's SDP with cvxpy (≈ 10 s for 100 steps).

    Generic metrics (``covariances``): ``filter`` picks the filter whose per-run error covariance is
    reported — the LMI filter, the naive KF (fixed gains: the conditional second moment given the
    mode path, a Joseph-type recursion) or the mode-aware KF (its own P). Model used there: zero
    cross-covariance S, E x(0) = 0, P0 = system.P0 (0 when absent); the filtered estimate x̂(k|k).
    """

    accepts: ClassVar[frozenset[str]] = frozenset({"mode"})
    quantity: ClassVar[str] = "P_{k|k}"

    kind: Literal["markov_lmi"]
    rho: Literal["stationary"] | list[NonNegFloat] = Field(
        "stationary", description="design marginals ρ_1..ρ_4 (sum 1) or 'stationary'")
    design: Literal["sdp", "closed_form"] = Field("closed_form", description="how the per-step LMI problem "
                                                  "(eqs 34/34a, 37/37a) is solved: closed_form (normal equations) or sdp (cvxpy)")
    sdp_check: NonNegInt = Field(3, description="with design: closed_form, the number of steps at which the SDP is "
                                               "also solved and compared (0: none)")
    solver: Literal["CLARABEL", "SCS"] = Field("CLARABEL", description="SDP solver used through cvxpy")
    solver_tol: PositiveFloat = Field(1e-8, description="solver feasibility/gap tolerance (Clarabel tol_gap_abs, "
                                                       "tol_gap_rel, tol_feas; SCS eps_abs, eps_rel)")
    eps: PositiveFloat = Field(1e-5, description="ε of eqs (33a)/(34a)/(37a) (relative to the block size) and of "
                                               "eq. (35) (variance of x_s(0) around its value)")
    precedence: bool = Field(True, description="use the precedence rule of eq. (34) for q = 2 (exclude j = 1 in Φ_2)")
    backend: Literal["auto", "numpy", "numba"] = Field(
        "auto", description="mode-aware KF in the Monte Carlo: auto = numba when importable and m = 1, else numpy "
                            "(the reference; the compiled step equals it to rounding)")
    filter: Literal["lmi", "mode_aware", "naive", "lmmse"] = Field(
        "lmi", description="filter whose per-run error covariance P_{k|k} the generic metrics see (the markov_filters "
                           "analysis always compares all four)")

    def check(self, system, channel) -> None:
        """Refuse what has no per-run covariance or no model: the LMMSE's P is an expectation."""
        if self.filter == "lmmse":
            raise ConfigError.at("estimator.filter", "the exact LMMSE's error covariance is an expectation over all mode "
                                 "paths (Costa's construction), not a per-run quantity, so per-run metrics cannot use it; "
                                 "use analysis kind markov_filters (exact MSE and Monte Carlo) or filter: lmi | naive | "
                                 "mode_aware")
        if self.rho != "stationary":
            if len(self.rho) != N_MODES:
                raise ConfigError.at("estimator.rho", f"needs 4 marginals ρ_1..ρ_4, got {len(self.rho)}")
            if abs(sum(self.rho) - 1) > 1e-9:
                raise ConfigError.at("estimator.rho", f"must sum to 1, got {sum(self.rho):.12g}")

    def _model(self, system):
        n = np.atleast_2d(np.asarray(system.A, float)).shape[0]
        P0 = getattr(system, "P0", None)
        P0 = np.zeros((n, n)) if P0 is None or isinstance(P0, str) else np.atleast_2d(np.asarray(P0, float))
        return AugmentedModel.build(system.A, system.C, system.Q, system.R), np.zeros(n), P0

    def covariances(self, system, trace, steps):
        """Yield ``(k, P_k)`` (n, n, runs): error covariance of x̂(k−1|k−1) given the mode path in ``trace.mode``."""
        self.check(system, None)
        if trace.mode is None:
            raise ConfigError.at("channel.kind", "markov_lmi needs a mode trace (channel kind markov_modes)")
        model, x0, P0 = self._model(system)
        steps = sorted(int(k) for k in steps)
        if not steps:
            return
        modes = np.asarray(trace.mode, dtype=np.int64)
        if self.filter == "mode_aware":
            cls = ModeAwareKFNumba if resolve_backend(self.backend, model.m) == "numba" else ModeAwareKFTr
            kf = cls(model, trace.runs, x0, P0, states=False)
            want = set(steps)
            for t in range(steps[-1]):
                _, _, Pfx = kf.step(None, modes[t], want_cov=(t + 1) in want)
                if t + 1 in want:
                    yield t + 1, Pfx
            return
        K = steps[-1]
        if self.filter == "naive":
            filt = naive_filter(model, x0, P0, K)
        else:
            from netkf_cli.estimators.markov_lmi import lmi_design

            if self.rho == "stationary":
                rho = np.asarray(trace.meta.get("rho"), float) if trace.meta.get("rho") is not None else None
                if rho is None:
                    raise ConfigError.at("estimator.rho", "the trace carries no mode marginals; give rho explicitly")
            else:
                rho = np.asarray(self.rho, float)
            try:
                filt = lmi_design(model, rho, x0, P0, K, design=self.design, solver=self.solver, tol=self.solver_tol,
                                  eps=self.eps, precedence=self.precedence, sdp_check=0).filter
            except RuntimeError as e:
                raise ConfigError.at("estimator", f"{e}; try `solver: SCS`, a larger `eps` or `design: closed_form`") from None
        yield from linear_filter_covariances(model, filt, modes, x0, P0, steps, "filtered")


# =========================================================================== run-innermost layout
# Everything below keeps the run axis innermost (design.md): states (d, runs), covariances
# (d, d, runs), traces (horizon, runs). Per-mode constant matrices are applied to the runs of
# that mode as one BLAS product (runs grouped by mode at each step), so there is no Python loop
# over runs and no per-run matrix stacks.


def _pinv_small_tr(S: np.ndarray, scale: np.ndarray, rtol: float = 1e-9) -> np.ndarray:
    """Pseudo-inverse of PSD (m, m, runs) with the zero-variance rule of :func:`pinv_psd`."""
    if S.shape[0] == 1:
        s = S[0, 0]
        ok = s > rtol * scale
        return np.where(ok, 1.0 / np.where(ok, s, 1.0), 0.0)[None, None, :]
    return np.moveaxis(pinv_psd(np.moveaxis(S, -1, 0), scale), 0, -1)


def _lm(A: np.ndarray, X: np.ndarray) -> np.ndarray:
    """A X for a constant A (p, a) and X (a, b, runs) as one GEMM."""
    a, b, r = X.shape
    return (A @ X.reshape(a, b * r)).reshape(A.shape[0], b, r)


def _cong(A: np.ndarray, X: np.ndarray) -> np.ndarray:
    """A X Aᵀ for a constant A and symmetric X (a, a, runs): two GEMMs and one transpose copy."""
    Y = _lm(A, X)  # (p, a, r): Y[i, j] = (A X)_{ij}
    Z = _lm(A, np.ascontiguousarray(Y.transpose(1, 0, 2)))  # Z[k, i] = Σ_j A_kj (AX)_ij = (A X Aᵀ)_{ik}
    return 0.5 * (Z + Z.transpose(1, 0, 2))


def _pmul(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Per-run product X_r Y_r for X (a, b, runs), Y (b, c, runs) (small inner dimension b)."""
    out = X[:, :1, :] * Y[None, 0, :, :]
    for j in range(1, X.shape[1]):
        out = out + X[:, j : j + 1, :] * Y[None, j, :, :]
    return out


class ModeGroups:
    """Which runs are in which mode at one step (``mode`` (runs,) 0-based).

    The most frequent mode is applied to *all* runs (contiguous, no gather: ``all_one``), the
    other modes to their gathered runs, which then overwrite their slots — ``order`` lists the
    main mode first.
    """

    def __init__(self, mode: np.ndarray):
        mode = np.asarray(mode)
        counts = np.bincount(mode, minlength=N_MODES)
        main = int(np.argmax(counts))
        self.idx = [np.flatnonzero(mode == q) if (q != main and counts[q]) else None for q in range(N_MODES)]
        self.idx[main] = np.arange(mode.size)
        self.all_one = [q == main for q in range(N_MODES)]
        self.order = [main] + [q for q in range(N_MODES) if q != main and counts[q]]


class ModeAwareKFTr:
    """The mode-aware KF of :class:`ModeAwareKF` with the run axis innermost: ξ̂ (d, runs), P (d, d, runs).

    Same equations (Σ_y = H P Hᵀ + J Σ Jᵀ, K = (F P Hᵀ + G Σ Jᵀ) Σ_y⁺, P⁺ = F P Fᵀ + G Σ Gᵀ − K Σ_y Kᵀ,
    K_f = P Hᵀ Σ_y⁺), the runs of each mode updated together with that mode's constant matrices.
    ``states=False`` propagates the covariances only (the generic ``covariances()`` path).
    """

    def __init__(self, model: AugmentedModel, runs: int, xhat0: np.ndarray, P0: np.ndarray, states: bool = True):
        self.model = md = model
        mean, cov = model.initial_moments(np.asarray(xhat0, float), np.asarray(P0, float))
        self.xi = np.repeat(mean[:, None], runs, axis=1) if states else None
        self.P = np.repeat(cov[:, :, None], runs, axis=2)
        self.GSG = np.einsum("iap,pq,ibq->iab", md.G, md.Sigma, md.G)
        self.GSJ = np.einsum("iap,pq,ibq->iab", md.G, md.Sigma, md.J)
        self.JSJ = np.einsum("iap,pq,ibq->iab", md.J, md.Sigma, md.J)
        self.scale = float(np.trace(md.Sigma))

    def predicted(self) -> tuple[np.ndarray | None, np.ndarray]:
        n = self.model.n
        return (None if self.xi is None else self.xi[:n]), np.einsum("iir->r", self.P[:n, :n])

    def step(self, y: np.ndarray | None, mode: np.ndarray, groups: ModeGroups | None = None,
             want_cov: bool = False):
        """Update with y(k) (m, runs) in mode θ(k) (runs,); returns (x̂(k|k) (n, runs) or None,
        tr P_x(k|k) (runs,), and P_x(k|k) (n, n, runs) if ``want_cov``); moves to k+1."""
        md = self.model
        n, d = md.n, md.d
        groups = groups or ModeGroups(mode)
        runs = mode.size
        trf = np.empty(runs)
        Pfx = np.empty((n, n, runs)) if want_cov else None
        xf = np.empty((n, runs)) if self.xi is not None else None
        Pn_all = np.empty_like(self.P)
        xin_all = np.empty_like(self.xi) if self.xi is not None else None
        for q in groups.order:
            idx = groups.idx[q]
            full = groups.all_one[q]
            P = self.P if full else self.P[:, :, idx]
            F, H = md.F[q], md.H[q]
            PHt = np.ascontiguousarray(_lm(H, P).transpose(1, 0, 2))  # (d, m, r) = P Hᵀ (P symmetric)
            Sy = _lm(H, PHt) + self.JSJ[q][:, :, None]
            Syi = _pinv_small_tr(Sy, self.scale + np.einsum("iir->r", P))
            Kf = _pmul(PHt, Syi)  # (d, m, r)
            K = _pmul(_lm(F, PHt) + self.GSJ[q][:, :, None], Syi)
            KfS = _pmul(Kf[:n], Sy)
            corr_x = _pmul(KfS, Kf[:n].transpose(1, 0, 2))
            Pfx_q = P[:n, :n] - corr_x
            tr_q = np.einsum("iir->r", Pfx_q)
            Pn = _cong(F, P) + self.GSG[q][:, :, None] - _pmul(_pmul(K, Sy), K.transpose(1, 0, 2))
            Pn = 0.5 * (Pn + Pn.transpose(1, 0, 2))
            if full:
                Pn_all, trf = Pn, tr_q
                if want_cov:
                    Pfx = Pfx_q
            else:
                Pn_all[:, :, idx] = Pn
                trf[idx] = tr_q
                if want_cov:
                    Pfx[:, :, idx] = Pfx_q
            if self.xi is not None:
                xi = self.xi if full else self.xi[:, idx]
                yq = y if full else y[:, idx]
                innov = yq - H @ xi
                xf_q = xi[:n] + np.einsum("dmr,mr->dr", Kf[:n], innov)
                xin = F @ xi + np.einsum("dmr,mr->dr", K, innov)
                if full:
                    xf, xin_all = xf_q, xin
                else:
                    xf[:, idx] = xf_q
                    xin_all[:, idx] = xin
        self.P = Pn_all
        if self.xi is not None:
            self.xi = xin_all
        return xf, trf, Pfx


def plant_outputs_tr(model: AugmentedModel, xi: np.ndarray, eps: np.ndarray, mode: np.ndarray) -> np.ndarray:
    """y(k) (m, runs) of every run in its mode: H_θ ξ + J_θ ε (ξ (d, runs), ε (p, runs))."""
    y_all = np.einsum("qmd,dr->qmr", model.H, xi) + np.einsum("qmp,pr->qmr", model.J, eps)
    return np.take_along_axis(y_all, mode[None, None, :].astype(np.intp), axis=0)[0]


def plant_next_tr(model: AugmentedModel, xi: np.ndarray, eps: np.ndarray, y: np.ndarray) -> np.ndarray:
    """ξ(k+1) = [A x + w; x; y; v] (d, runs)."""
    n = model.n
    x = xi[:n]
    return np.concatenate([model.A @ x + eps[:n], x, y, eps[n:]], axis=0)


class MarkovMSEKernel:
    """Monte Carlo kernel of the Markov-mode comparison (module-level, picklable; issue 12.5).

    Simulates the plant and the mode chain (``channel.sample_trace``) at the state level, runs the
    mode-aware KF and every :class:`LinearFilter` in ``linear`` on the same runs (run axis
    innermost) and returns additive statistics with fixed keys (:meth:`keys`): per-k sums and sums
    of squares of ‖e‖², per-run window averages (sum, squares), paired differences for the ordering
    claims, the mode-aware KF's own tr P, empirical mode fractions and non-finite counts.
    """

    FILTERS = ("mode_aware_kf", "lmmse", "lmi", "naive_kf")
    ESTIMATES = ("predicted", "filtered")
    PAIRS = (("lmmse", "mode_aware_kf"), ("lmi", "lmmse"), ("naive_kf", "lmmse"))

    def __init__(self, model: AugmentedModel, channel, linear: dict, x0, P0, horizon: int, burn_in: int,
                 filters: tuple[str, ...] | None = None, backend: str = "numpy"):
        self.model, self.channel, self.linear = model, channel, dict(linear)
        # mode-aware KF: "numpy" (reference) or "numba" (compiled per-run step, m = 1; equal to rounding)
        self.backend = resolve_backend(backend, model.m)
        self.x0, self.P0 = np.asarray(x0, float), np.asarray(P0, float)
        self.K, self.burn = int(horizon), int(burn_in)
        if not 0 <= self.burn < self.K:
            raise ValueError(f"burn_in must be in [0, horizon), got {burn_in}")
        # which filters run (default: all four); a subset is used by the per-estimator benchmarks
        self.filters = tuple(f for f in self.FILTERS if filters is None or f in filters)
        self.linear = {f: F for f, F in self.linear.items() if f in self.filters}
        missing = set(self.filters) - {"mode_aware_kf"} - set(self.linear)
        if missing:
            raise ValueError(f"linear filters missing: {sorted(missing)}")
        self.pairs = tuple((a, b) for a, b in self.PAIRS if a in self.filters and b in self.filters)

    def keys(self) -> list[str]:
        out = []
        for f in self.filters:
            for e in self.ESTIMATES:
                out += [f"sum_{f}_{e}", f"sq_{f}_{e}", f"win_{f}_{e}", f"winsq_{f}_{e}", f"win3_{f}_{e}", f"win4_{f}_{e}"]
        for e in self.ESTIMATES:
            out += [f"sum_trP_{e}", f"sq_trP_{e}", f"win_trP_{e}", f"winsq_trP_{e}"]
        for a, b in self.pairs:
            for e in self.ESTIMATES:
                out += [f"dwin_{a}_{b}_{e}", f"dwinsq_{a}_{b}_{e}"]
        out += [f"nonfinite_{f}" for f in self.filters] + ["mode_frac_sum", "mode_frac_sq"]
        return out

    def __call__(self, rng: np.random.Generator, nr: int) -> dict[str, np.ndarray]:
        md, K, burn = self.model, self.K, self.burn
        n = md.n
        modes = self.channel.sample_trace(rng, nr, K).mode  # (K, nr) int8
        xbar, cov = md.initial_moments(self.x0, self.P0)
        xi = xbar[:, None] + psd_sqrt(cov) @ rng.standard_normal((md.d, nr))
        eps = np.einsum("pq,kqr->kpr", md.Lsig, rng.standard_normal((K, md.p, nr)))
        states = {f: np.repeat(F.s0[:, None], nr, axis=1) for f, F in self.linear.items()}
        mak_cls = ModeAwareKFNumba if self.backend == "numba" else ModeAwareKFTr
        mak = mak_cls(md, nr, self.x0, self.P0) if "mode_aware_kf" in self.filters else None
        st: dict = {}
        win = {(f, e): np.zeros(nr) for f in self.filters for e in self.ESTIMATES}
        for f in self.filters:
            for e in self.ESTIMATES:
                st[f"sum_{f}_{e}"] = np.zeros(K)
                st[f"sq_{f}_{e}"] = np.zeros(K)
        winP = {e: np.zeros(nr) for e in self.ESTIMATES}
        for e in self.ESTIMATES:
            st[f"sum_trP_{e}"] = np.zeros(K)
            st[f"sq_trP_{e}"] = np.zeros(K)
        trp = trf = np.zeros(nr)
        for k in range(K):
            mode = modes[k]
            x = xi[:n]
            y = plant_outputs_tr(md, xi, eps[k], mode)
            err = {}
            for f, F in self.linear.items():
                s = states[f]
                err[(f, "predicted")] = x - F.Ep @ s
                err[(f, "filtered")] = x - (F.Ef[k] @ s + F.Lf[k] @ y)
                states[f] = F.As[k] @ s + F.Gs[k] @ y
            if mak is not None:
                xp, trp = mak.predicted()
                err[("mode_aware_kf", "predicted")] = x - xp
                xf, trf, _ = mak.step(y, mode, ModeGroups(mode))
                err[("mode_aware_kf", "filtered")] = x - xf
            for (f, e), ev in err.items():
                se = np.einsum("ir,ir->r", ev, ev)
                st[f"sum_{f}_{e}"][k] = se.sum()
                st[f"sq_{f}_{e}"][k] = (se * se).sum()
                if k >= burn:
                    win[(f, e)] += se
            for e, tr in (("predicted", trp), ("filtered", trf)):
                st[f"sum_trP_{e}"][k] = tr.sum()
                st[f"sq_trP_{e}"][k] = (tr * tr).sum()
                if k >= burn:
                    winP[e] += tr
            xi = plant_next_tr(md, xi, eps[k], y)
        L = K - burn
        for (f, e), v in win.items():
            v = v / L
            v2 = v * v
            st[f"win_{f}_{e}"] = np.asarray(v.sum())
            st[f"winsq_{f}_{e}"] = np.asarray(v2.sum())
            st[f"win3_{f}_{e}"] = np.asarray((v2 * v).sum())  # for the heavy-tail diagnostic
            st[f"win4_{f}_{e}"] = np.asarray((v2 * v2).sum())
        for e in self.ESTIMATES:
            v = winP[e] / L
            st[f"win_trP_{e}"] = np.asarray(v.sum())
            st[f"winsq_trP_{e}"] = np.asarray((v * v).sum())
        for a, b in self.pairs:
            for e in self.ESTIMATES:
                dv = (win[(a, e)] - win[(b, e)]) / L
                st[f"dwin_{a}_{b}_{e}"] = np.asarray(dv.sum())
                st[f"dwinsq_{a}_{b}_{e}"] = np.asarray((dv * dv).sum())
        for f in self.filters:
            st[f"nonfinite_{f}"] = np.asarray(float(sum(int((~np.isfinite(win[(f, e)])).sum()) for e in self.ESTIMATES)))
        freq = np.stack([(modes == q).mean(axis=0) for q in range(N_MODES)])  # (N, nr)
        st["mode_frac_sum"] = freq.sum(axis=1)
        st["mode_frac_sq"] = (freq * freq).sum(axis=1)
        return st


def linear_filter_covariances(model: AugmentedModel, filt: LinearFilter, modes: np.ndarray, x0, P0, steps,
                              estimate: str = "filtered"):
    """Per-run error second moment of a fixed-gain filter given its mode path: yield (k, P_k) (n, n, runs).

    ζ = [ξ; s] (dimension D = d + r); given θ(0..k) the conditional second moment
    M(k) = E[ζζᵀ | θ] follows the Joseph-type recursion M(k+1) = 𝒜_q M 𝒜_qᵀ + ℬ_q Σ ℬ_qᵀ with
    𝒜_q = [[F_q, 0], [G_s H_q, A_s]], ℬ_q = [[G_q], [G_s J_q]] (eq. 29 with the filter's gains),
    M(0) = E ζ(0)ζ(0)ᵀ. Step t = k − 1 of the trace carries y(t): P_k is the error of x̂(t|t)
    (``estimate='filtered'``: (E_x − L_f H_q) ξ − E_f s − L_f J_q ε) or of x̂(t|t−1)
    (``'predicted'``: E_x ξ − E_p s). Exact for any gains (no Gaussianity needed).
    """
    d, n = model.d, model.n
    r = filt.As.shape[1]
    D = d + r
    K, runs = modes.shape
    xbar, cov = model.initial_moments(np.asarray(x0, float), np.asarray(P0, float))
    z0 = np.concatenate([xbar, filt.s0])
    M0 = np.outer(z0, z0)
    M0[:d, :d] += cov
    M = np.repeat(M0[:, :, None], runs, axis=2)
    Ex = model.Ex
    want = sorted(int(k) for k in steps)
    last = want[-1] if want else 0
    wset = set(want)
    Sig = model.Sigma
    for t in range(min(K, last)):
        groups = ModeGroups(modes[t])
        if t + 1 in wset:
            out = np.empty((n, n, runs))
            for q in groups.order:
                idx = groups.idx[q]
                Mq = M if groups.all_one[q] else M[:, :, idx]
                if estimate == "filtered":
                    Cq = np.concatenate([Ex - filt.Lf[t] @ model.H[q], -filt.Ef[t]], axis=1)
                    LJ = filt.Lf[t] @ model.J[q]
                    val = _cong(Cq, Mq) + (LJ @ Sig @ LJ.T)[:, :, None]
                else:
                    Cq = np.concatenate([Ex, -filt.Ep], axis=1)
                    val = _cong(Cq, Mq)
                if groups.all_one[q]:
                    out = val.copy()
                else:
                    out[:, :, idx] = val
            yield t + 1, out
        if t + 1 >= last:
            return
        Mn = np.empty_like(M)
        for q in groups.order:
            idx = groups.idx[q]
            Aq = np.zeros((D, D))
            Aq[:d, :d] = model.F[q]
            Aq[d:, :d] = filt.Gs[t] @ model.H[q]
            Aq[d:, d:] = filt.As[t]
            Bq = np.concatenate([model.G[q], filt.Gs[t] @ model.J[q]], axis=0)
            Mq = M if groups.all_one[q] else M[:, :, idx]
            val = _cong(Aq, Mq) + (Bq @ Sig @ Bq.T)[:, :, None]
            if groups.all_one[q]:
                Mn = val
            else:
                Mn[:, :, idx] = val
        M = Mn


# =========================================================================== compiled mode-aware KF
_NB_STEP = None


def numba_available() -> bool:
    try:
        import numba  # noqa: F401
    except ImportError:
        return False
    return True


def resolve_backend(backend: str, m: int) -> str:
    """``auto`` → ``numba`` when numba imports and m = 1 (closed-form scalar innovation), else ``numpy``."""
    if backend == "auto":
        return "numba" if (m == 1 and numba_available()) else "numpy"
    if backend == "numba":
        if not numba_available():
            raise ConfigError.at("estimator.backend", "numba is not installed: pip install 'netkf[fast]' or use numpy")
        if m != 1:
            raise ConfigError.at("estimator.backend", f"the compiled mode-aware KF handles one output (m = 1), got m = {m}")
    return backend


def _numba_step():
    """Compile (once, cached on disk) the per-run mode-aware KF step for m = 1."""
    global _NB_STEP
    if _NB_STEP is not None:
        return _NB_STEP
    import numba

    @numba.njit(cache=True, fastmath=False, nogil=True)
    def step(P, xi, y, mode, rowptr, cols, vals, H, GSG, GSJ, JSJ, scale, n, has_x, xf, trf, trp):  # pragma: no cover
        # F_q in CSR form (rowptr[q], cols[q], vals[q]): F = [[A,0,0,0],[I,0,0,0],[H_q],[0]] is mostly zeros
        R = P.shape[0]  # P is (runs, d, d) here: one run's covariance is contiguous
        d = P.shape[1]
        Pl = np.empty((d, d))
        FP = np.empty((d, d))
        PHt = np.empty(d)
        K = np.empty(d)
        xl = np.empty(d)
        for r in range(R):
            q = mode[r]
            tr = 0.0
            for i in range(d):
                for j in range(d):
                    Pl[i, j] = P[r, i, j]
                tr += Pl[i, i]
            t = 0.0
            for i in range(n):
                t += Pl[i, i]
            trp[r] = t
            # P Hᵀ, Σ_y = H P Hᵀ + J Σ Jᵀ (m = 1)
            Sy = JSJ[q, 0, 0]
            for a in range(d):
                s = 0.0
                for b in range(d):
                    s += Pl[a, b] * H[q, 0, b]
                PHt[a] = s
                Sy += H[q, 0, a] * s
            Syi = 1.0 / Sy if Sy > 1e-9 * (scale + tr) else 0.0
            innov = 0.0
            if has_x:
                innov = y[0, r]
                for a in range(d):
                    xl[a] = xi[a, r]
                    innov -= H[q, 0, a] * xl[a]
            # gains: K_f = P Hᵀ Σ_y⁺, K = (F P Hᵀ + G Σ Jᵀ) Σ_y⁺
            t = 0.0
            for i in range(n):
                kf = PHt[i] * Syi
                t += Pl[i, i] - kf * kf * Sy
                if has_x:
                    xf[i, r] = xl[i] + kf * innov
            trf[r] = t
            for a in range(d):
                s = GSJ[q, a, 0]
                for kk in range(rowptr[q, a], rowptr[q, a + 1]):
                    s += vals[q, kk] * PHt[cols[q, kk]]
                K[a] = s * Syi
            if has_x:
                for a in range(d):
                    s = K[a] * innov
                    for kk in range(rowptr[q, a], rowptr[q, a + 1]):
                        s += vals[q, kk] * xl[cols[q, kk]]
                    xi[a, r] = s
            # P⁺ = F P Fᵀ + G Σ Gᵀ − K Σ_y Kᵀ, symmetrized
            for a in range(d):
                for b in range(d):
                    s = 0.0
                    for kk in range(rowptr[q, a], rowptr[q, a + 1]):
                        s += vals[q, kk] * Pl[cols[q, kk], b]
                    FP[a, b] = s
            for a in range(d):
                for b in range(a, d):
                    s1 = 0.0
                    for kk in range(rowptr[q, b], rowptr[q, b + 1]):
                        s1 += FP[a, cols[q, kk]] * vals[q, kk]
                    s2 = 0.0
                    for kk in range(rowptr[q, a], rowptr[q, a + 1]):
                        s2 += FP[b, cols[q, kk]] * vals[q, kk]
                    v = 0.5 * (s1 + s2) + 0.5 * (GSG[q, a, b] + GSG[q, b, a]) - K[a] * K[b] * Sy
                    P[r, a, b] = v
                    P[r, b, a] = v

    _NB_STEP = step
    return step


class ModeAwareKFNumba(ModeAwareKFTr):
    """:class:`ModeAwareKFTr` with the per-run step compiled by numba (m = 1): same inputs and outputs,
    equal to the numpy reference to rounding (tested). Internally P is kept as (runs, d, d) — a per-run
    loop wants each run's covariance contiguous (the run-innermost layout would touch d² pages per run)."""

    def __init__(self, model: AugmentedModel, runs: int, xhat0, P0, states: bool = True):
        if model.m != 1:
            raise ValueError("the compiled mode-aware KF needs m = 1")
        super().__init__(model, runs, xhat0, P0, states)
        self.P = np.ascontiguousarray(np.moveaxis(self.P, -1, 0))
        self._fn = _numba_step()
        md = model
        self._H = np.ascontiguousarray(md.H)
        nnz = int(max((md.F[q] != 0).sum() for q in range(N_MODES)))
        d = md.d
        self._rowptr = np.zeros((N_MODES, d + 1), np.int64)
        self._cols = np.zeros((N_MODES, max(nnz, 1)), np.int64)
        self._vals = np.zeros((N_MODES, max(nnz, 1)))
        for q in range(N_MODES):
            k = 0
            for a in range(d):
                for c in range(d):
                    if md.F[q, a, c] != 0.0:
                        self._cols[q, k], self._vals[q, k] = c, md.F[q, a, c]
                        k += 1
                self._rowptr[q, a + 1] = k
        self._dummy_x = np.zeros((md.d, 1))
        self._dummy_y = np.zeros((1, 1))

    def predicted(self):
        n = self.model.n
        return (None if self.xi is None else self.xi[:n].copy()), np.einsum("rii->r", self.P[:, :n, :n])

    def step(self, y, mode, groups=None, want_cov: bool = False):
        md = self.model
        n, R = md.n, mode.size
        has_x = self.xi is not None
        Pfx = None
        if want_cov:  # P_x(k|k) = P_xx − K_f,x Σ_y K_f,xᵀ from the current (runs, d, d) P, vectorized (m = 1)
            P = self.P
            Hr = md.H[mode][:, 0, :]  # (runs, d)
            PHt = np.einsum("rab,rb->ra", P, Hr)
            Sy = np.einsum("ra,ra->r", Hr, PHt) + self.JSJ[mode][:, 0, 0]
            ok = Sy > 1e-9 * (self.scale + np.einsum("rii->r", P))
            Syi = np.where(ok, 1.0 / np.where(ok, Sy, 1.0), 0.0)
            Kx = PHt[:, :n] * Syi[:, None]
            Pfx = np.moveaxis(P[:, :n, :n] - Kx[:, :, None] * Kx[:, None, :] * Sy[:, None, None], 0, -1)
        xf = np.empty((n, R)) if has_x else np.empty((n, 1))
        trf, trp = np.empty(R), np.empty(R)
        self._fn(self.P, self.xi if has_x else self._dummy_x, y if has_x else self._dummy_y,
                 np.ascontiguousarray(mode, dtype=np.int64), self._rowptr, self._cols, self._vals, self._H,
                 self.GSG, self.GSJ, self.JSJ,
                 self.scale, n, has_x, xf, trf, trp)
        return (xf if has_x else None), trf, Pfx
