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
from typing import Literal

import numpy as np
from pydantic import Field

from netkf_cli.spec import EstimatorModel, NonNegFloat, PositiveFloat

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
        inner = np.einsum("iab,ibc,idc->iad", model.F, Qi, model.F) + pi[:, None, None] * GSG
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
        FQF = np.einsum("iab,ibc,idc->iad", F, Qi, F)
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
        inner = np.einsum("iab,ibc,idc->iad", Aq, Qi, Aq) + pi[:, None, None] * np.einsum(
            "iap,pq,ibq->iab", Bq, model.Sigma, Bq)
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
    computed from the channel). ``design: sdp`` solves the LMI problems with cvxpy;
    ``closed_form`` solves the same per-step problem through its normal equations (identical
    optimum, used to verify the SDP).
    """

    kind: Literal["markov_lmi"]
    rho: Literal["stationary"] | list[NonNegFloat] = Field(
        "stationary", description="design marginals ρ_1..ρ_4 (sum 1) or 'stationary'")
    design: Literal["sdp", "closed_form"] = Field("sdp", description="how the per-step LMI problem is solved")
    solver: Literal["CLARABEL", "SCS"] = Field("CLARABEL", description="SDP solver used through cvxpy")
    solver_tol: PositiveFloat = Field(1e-8, description="solver feasibility/gap tolerance (Clarabel tol_gap_abs, "
                                                       "tol_gap_rel, tol_feas; SCS eps_abs, eps_rel)")
    eps: PositiveFloat = Field(1e-5, description="ε of eqs (33a)/(34a)/(37a) (relative to the block size) and of "
                                               "eq. (35) (variance of x_s(0) around its value)")
    precedence: bool = Field(True, description="use the precedence rule of eq. (34) for q = 2 (exclude j = 1 in Φ_2)")
