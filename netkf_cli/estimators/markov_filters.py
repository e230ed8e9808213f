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
* :class:`ModeAwareKFTr` — the time-varying Kalman filter on ξ for a receiver that knows
  θ(k) (per run; the lower bound), on the Kalman core (``kalman.update_pinv`` + ``kalman.predict``),
  compiled twin :class:`ModeAwareCompiled` on ``kalman_numba``'s primitives (covariances only), and with states
  (one output) :func:`mode_aware_estimates_compiled` (a kernel generated per model).

All filters whose gains do not depend on the data are :class:`LinearFilter` objects
``s(k+1) = A_s(k) s(k) + G_s(k) y(k)``, ``x̂(k|k−1) = E_p s(k)``,
``x̂(k|k) = E_f(k) s(k) + L_f(k) y(k)``; :func:`exact_mse` evaluates any of them exactly
through the second moments of the joint Markov-jump system ``[ξ; s]``; their per-run error covariances given
the mode path are :func:`linear_filter_covariances` (numpy, the reference) or
:func:`linear_filter_covariances_compiled` (a kernel generated per system, :mod:`netkf_cli.estimators._markov_codegen`).

Time bases
----------
The paper's (``base="paper"``, the ``markov_filters`` analysis): x(0) ~ (x0, P0) is the prior of the
first measurement y(0). netkf's (``base="contract"``, the ``markov_lmi`` estimator's ``covariances``):
P0 = P_{0|0}, the first measurement is y_1 on trace step 0 (:meth:`AugmentedModel.prior_moments`).
The scenario block (``kind: markov_lmi``) is :class:`netkf_cli.estimators.markov_lmi.MarkovLMIEstimator`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from netkf_cli.linalg import batched, kalman
from netkf_cli.linalg.kalman import numba_available  # noqa: F401  (re-exported: the one probe)
from netkf_cli.core.errors import ConfigError
from netkf_cli.estimators import _markov_codegen
from netkf_cli.core.tolerances import FIXED_GAIN_PRECISION, PSD_INPUT_TOL, ZERO_INNOVATION_RTOL

N_MODES = 4


# --------------------------------------------------------------------------- helpers
def psd_sqrt(M: np.ndarray) -> np.ndarray:
    """A factor ``L`` with ``L Lᵀ = M`` for symmetric PSD ``M`` (eigenvalues < 0 clipped)."""
    M = (M + M.T) / 2
    w, V = np.linalg.eigh(M)
    return V * np.sqrt(np.clip(w, 0.0, None))


def pinv_psd(S: np.ndarray, scale: np.ndarray | float, rtol: float = ZERO_INNOVATION_RTOL) -> np.ndarray:
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
        if np.linalg.eigvalsh(Sigma).min() < -PSD_INPUT_TOL * max(1.0, np.abs(Sigma).max()):
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


    # ---- the filtered-form per-mode matrices (the measurement noise J_q ε(k) is correlated with G_q ε(k))
    @property
    def Rq(self) -> np.ndarray:
        """(N, m, m) measurement noise of each mode, J_q Σ J_qᵀ (R in modes 1, 3; 0 in modes 2, 4)."""
        return np.einsum("iap,pq,ibq->iab", self.J, self.Sigma, self.J)

    @property
    def GSG(self) -> np.ndarray:
        """(N, d, d) G_q Σ G_qᵀ."""
        return np.einsum("iap,pq,ibq->iab", self.G, self.Sigma, self.G)

    def decorrelated(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(F̄, D, Q̄) per mode, each (N, ·, ·): the time update after the measurement update of mode q.

        G_q ε(k) = D_q J_q ε(k) + G_q ε̃(k) with D_q = G_q Σ J_qᵀ R_q⁺ and ε̃ = ε − Σ J_qᵀ R_q⁺ J_q ε
        uncorrelated with J_q ε (Anderson & Moore 1979, §5.5, correlated noise); J_q ε = y − H_q ξ, so

            ξ(k+1) = F̄_q ξ(k) + D_q y(k) + G_q ε̃(k),   F̄_q = F_q − D_q H_q,
            P(k+1|k) = F̄_q P(k|k) F̄_qᵀ + Q̄_q,         Q̄_q = G_q (Σ − Σ J_qᵀ R_q⁺ J_q Σ) G_qᵀ

        (``kalman.predict``). With S = 0 the x rows of F̄_q are [A 0 0 0] and Q̄_q's x block is Q: the
        x block of P(k+1|k) is A P_x(k|k) Aᵀ + Q, the plain KF's prediction."""
        N, d = N_MODES, self.d
        Rq = self.Rq
        Fb, D, Qb = np.empty((N, d, d)), np.empty((N, d, self.m)), np.empty((N, d, d))
        for q in range(N):
            Rp = pinv_psd(Rq[q], np.trace(Rq[q]) + 1e-300)
            SJ = self.Sigma @ self.J[q].T  # Σ J_qᵀ (p, m)
            D[q] = self.G[q] @ SJ @ Rp
            Fb[q] = self.F[q] - D[q] @ self.H[q]
            St = self.Sigma - SJ @ Rp @ SJ.T
            Qb[q] = self.G[q] @ (0.5 * (St + St.T)) @ self.G[q].T
            Qb[q] = 0.5 * (Qb[q] + Qb[q].T)
        return Fb, D, Qb

    def prior_moments(self, x0: np.ndarray, P0: np.ndarray, base: str = "paper") -> tuple[np.ndarray, np.ndarray]:
        """Mean and covariance of ξ at the first measurement.

        ``paper``: ξ(0) with x(0) ~ (x0, P0) measured by y(0) (eq. 35, :meth:`initial_moments`).
        ``contract``: netkf's time base — P0 = P_{0|0} (the covariance of x_0 given the data up to
        time 0), the first measurement is y_1 (trace step 0): ξ(1) = F_3 ξ(0) + G_3 ε(0) =
        [A x_0 + w_0; x_0; v_0; v_0] (nothing was received at time 0: eq. 35's y(−1) = v(−1) one
        step later), covariance ``kalman.predict`` of eq. 35's. Its x block is A P0 Aᵀ + Q = P_{1|0}."""
        mean, cov = self.initial_moments(np.asarray(x0, float), np.asarray(P0, float))
        if base == "paper":
            return mean, cov
        if base != "contract":
            raise ValueError(f"base must be 'paper' or 'contract', got {base!r}")
        return self.F[2] @ mean, kalman.one(kalman.predict, cov, self.F[2], self.GSG[2])


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

    On the core (``P0`` the prior of the first measurement): K_f = ``kalman.gain``(P, C, R),
    P_f = ``kalman.update``(P, C, R); the correlated noise w = S R⁺ v + w̃ makes the time update
    P⁺ = ``kalman.predict``(P_f, Ā, Q − S R⁺ Sᵀ), Ā = A − S R⁺ C (Anderson & Moore 1979, §5.5), and the
    predictor gain K = Ā K_f + S R⁺ (= (A P Cᵀ + S) Σ_y⁻¹): s(k+1) = (A − K C) s(k) + K y(k).
    Its gains are optimal only in mode 1; the true error of this fixed-gain filter in every mode is
    the joint second-moment recursion (:func:`exact_mse`, :func:`linear_filter_covariances`).
    """
    A, C, Q, R, S = model.A, model.C, model.Q, model.R, model.S
    n, m = model.n, model.m
    SRi = S @ pinv_psd(R, np.trace(R) + 1e-300)
    Abar, Qbar = A - SRi @ C, Q - SRi @ S.T
    Qbar = 0.5 * (Qbar + Qbar.T)
    As = np.empty((horizon, n, n)); Gs = np.empty((horizon, n, m))
    Ef = np.empty((horizon, n, n)); Lf = np.empty((horizon, n, m))
    P = np.array(P0, dtype=float)[:, :, None]
    tp, tf = np.empty(horizon), np.empty(horizon)
    for k in range(horizon):
        Kf = kalman.gain(P, C, R)[:, :, 0]
        Pf = kalman.update(P, C, R)
        tp[k] = np.trace(P[:, :, 0])
        tf[k] = np.trace(Pf[:, :, 0])
        K = Abar @ Kf + SRi
        As[k], Gs[k] = A - K @ C, K
        Ef[k], Lf[k] = np.eye(n) - Kf @ C, Kf
        P = kalman.predict(Pf, Abar, Qbar)
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
                 horizon: int, base: str = "paper") -> LinearFilter:
    """Exact LMMSE filter for the Markov-jump model with unobserved modes (module docstring).

    With ``Q_i(k)``, ``π_i(k)`` from :func:`mode_second_moments` and ``p_ij = ρ_{j/i}``:

        Σ_ν[j,l] = Σ_i (δ_jl p_ij − p_ij p_il) F_i Q_i F_iᵀ + δ_jl Σ_i p_ij π_i G_i Σ G_iᵀ
        Σ_νη[j]  = Σ_i π_i p_ij G_i Σ J_iᵀ,      Σ_η = Σ_i π_i J_i Σ J_iᵀ
        Σ_y = ℍ P ℍᵀ + Σ_η,  K = (𝔽 P ℍᵀ + Σ_νη) Σ_y⁺,  P⁺ = 𝔽 P 𝔽ᵀ + Σ_ν − K Σ_y Kᵀ
        Ẑ(k+1) = 𝔽 Ẑ + K (y − ℍ Ẑ);  filtered: K_f = P ℍᵀ Σ_y⁺,
    computed on the core in filtered form: P_f, K_f = ``kalman.update_pinv``(P, ℍ, Σ_η), then
    P⁺ = ``kalman.predict``(P_f, 𝔽 − D ℍ, Σ_ν − D Σ_νηᵀ), K = (𝔽 − D ℍ) K_f + D, D = Σ_νη Σ_η⁺ (the same K).

    Initial: Ẑ_i(0) = π_i(0) ξ̄(0); P(0)[i,j] = δ_ij π_i M0 − π_i π_j ξ̄ ξ̄ᵀ, M0 = E ξ(0)ξ(0)ᵀ.
    """
    N, d, n, m = N_MODES, model.d, model.n, model.m
    r = N * d
    xbar, cov = model.prior_moments(np.asarray(x0, float), np.asarray(P0, float), base)
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
    cp, cf = np.empty((horizon, n, n)), np.empty((horizon, n, n))  # the x-error covariances themselves
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
        # on the core: the filtered update with the pseudo-inverse rule (the gain as K e_j on m copies of P),
        # then the time update with ν decorrelated from η: ν = D η + ν̃, D = Σ_νη Σ_η⁺ (Anderson & Moore §5.5)
        Sy_tr = np.trace(HH @ P @ HH.T + Seta)
        Prep = np.repeat(P[:, :, None], m, axis=2)
        Pf3, Kf = kalman.update_pinv(Prep, HH, Seta, ZERO_INNOVATION_RTOL * Sy_tr, np.eye(m))
        Pf = Pf3[:, :, 0]
        D = Snueta @ pinv_psd(Seta, np.trace(Seta) + 1e-300)
        Fb = FF - D @ HH
        Snu_t = Snu - D @ Snueta.T
        K = Fb @ Kf + D
        cp[k], cf[k] = Ep @ P @ Ep.T, Ep @ Pf @ Ep.T
        tp[k], tf[k] = np.trace(cp[k]), np.trace(cf[k])
        As[k], Gs[k] = FF - K @ HH, K
        Ef[k], Lf[k] = Ep @ (np.eye(r) - Kf @ HH), Ep @ Kf
        P = kalman.one(kalman.predict, Pf, Fb, 0.5 * (Snu_t + Snu_t.T))
    # Ẑ_i(0) = π_i(0) [x̂0; x̂0; 0; 0]
    lift = np.zeros((d, n)); lift[:n] = np.eye(n); lift[n:2 * n] = np.eye(n)
    s0_map = np.concatenate([pi0[i] * lift for i in range(N)], axis=0)
    return LinearFilter("lmmse", As, Gs, Ep, Ef, Lf, s0_map @ np.asarray(x0, float), s0_map,
                        {"pred": tp, "filt": tf, "pred_cov": cp, "filt_cov": cf})


def exact_mse(model: AugmentedModel, filt: LinearFilter, T: np.ndarray, pi0: np.ndarray,
              x0: np.ndarray, P0: np.ndarray, base: str = "paper") -> tuple[np.ndarray, np.ndarray]:
    """Exact E‖x(k) − x̂(k|k−1)‖² and E‖x(k) − x̂(k|k)‖², k = 0..K−1, for any LinearFilter.

    Second moments of the joint Markov-jump system η = [ξ; s]:
    ``𝒜_q = [[F_q, 0], [G_s H_q, A_s]]``, ``ℬ_q = [[G_q], [G_s J_q]]``,
    ``Q_j(k+1) = Σ_i ρ_{j/i} (𝒜_i Q_i 𝒜_iᵀ + π_i ℬ_i Σ ℬ_iᵀ)``, ``Q_i(0) = π_i(0) E η(0)η(0)ᵀ``.
    Exact whatever the gains and the initial estimate s0 (no Gaussianity needed).
    """
    N, d, n = N_MODES, model.d, model.n
    K, r = filt.horizon, filt.As.shape[1]
    D = d + r
    xbar, cov = model.prior_moments(np.asarray(x0, float), np.asarray(P0, float), base)
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


# =========================================================================== run-innermost layout
# Everything below keeps the run axis innermost (design.md): states (d, runs), covariances
# (d, d, runs), traces (horizon, runs). Per-mode constant matrices are applied to the runs of
# that mode together (runs grouped by mode at each step) with the Kalman core's primitives.


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
    """Time-varying KF on ξ for a receiver that knows θ(k), run axis innermost: ξ̂ (d, runs), P (d, d, runs).

    Written on the Kalman core, in filtered form. ``P`` is the prior P(k|k−1) of ξ. Step k in mode q:

        P(k|k)   = ``kalman.update_pinv``(P, H_q, R_q)   (R_q = J_q Σ J_qᵀ; zero-variance innovations —
                   a held packet, a delayed one whose value is known — get no gain)
        P(k+1|k) = ``kalman.predict``(P(k|k), F̄_q, Q̄_q)  (the correlated noise decorrelated,
                   :meth:`AugmentedModel.decorrelated`);  ξ̂(k+1|k) = F̄_q ξ̂(k|k) + D_q y(k)

    Mode 3 (noise only: H_3 = 0) leaves P(k|k) = P(k|k−1). The x block of a mode-1 / mode-3 step goes
    through the plain KF's overflow policy ``kalman.Rescue.for_system`` (flag on tr P_x(k|k−1), redo
    in information form): with only modes 1 and 3 the x block is ``kalman.Filter`` with γ = 1{θ = 1}
    step for step. ``base``: which initial condition ``P0`` is (:meth:`AugmentedModel.prior_moments`).
    ``states=False`` propagates the covariances only (the generic ``covariances()`` path).
    """

    def __init__(self, model: AugmentedModel, runs: int, xhat0: np.ndarray, P0: np.ndarray, states: bool = True,
                 base: str = "paper"):
        self.model = md = model
        mean, cov = model.prior_moments(np.asarray(xhat0, float), np.asarray(P0, float), base)
        self.xi = np.repeat(mean[:, None], runs, axis=1) if states else None
        self.P = np.repeat(cov[:, :, None], runs, axis=2)
        self.Rq = md.Rq
        self.Fb, self.D, self.Qb = md.decorrelated()
        self.scale = float(np.trace(md.Sigma))
        self.rescue = kalman.Rescue.for_system(md.A, md.C, md.Q, md.R, md.m)  # Filter.of's: the same limit

    def predicted(self) -> tuple[np.ndarray | None, np.ndarray]:
        n = self.model.n
        return (None if self.xi is None else self.xi[:n]), batched.trace(self.P[:n, :n])

    def floor(self, P: np.ndarray) -> np.ndarray:
        """(runs,) innovation variance at or below which a direction carries no information."""
        return ZERO_INNOVATION_RTOL * (self.scale + batched.trace(P))

    def step(self, y: np.ndarray | None, mode: np.ndarray, groups: ModeGroups | None = None,
             want_cov: bool = False):
        """Update with y(k) (m, runs) in mode θ(k) (runs,); returns (x̂(k|k) (n, runs) or None,
        tr P_x(k|k) (runs,), and P_x(k|k) (n, n, runs) if ``want_cov``); moves to k+1."""
        md = self.model
        n = md.n
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
            xi = None if self.xi is None else (self.xi if full else self.xi[:, idx])
            yq = None if y is None else (y if full else y[:, idx])
            with np.errstate(over="ignore", invalid="ignore"):
                if q == 2:  # noise only: nothing about ξ(k) (v(k) enters through D_3 in the time update)
                    Pf, dx = P, None
                else:
                    e = None if xi is None else yq - md.H[q] @ xi
                    Pf, dx = kalman.update_pinv(P, md.H[q], self.Rq[q], self.floor(P), e)
                if q in (0, 2):  # the plain KF's overflow policy on the x block (a mode-1 / mode-3 step is its γ = 1 / 0)
                    flagged = self.rescue.flag(P[:n, :n])
                    if flagged.any():
                        rows = np.full((md.m, P.shape[-1]), q == 0)
                        Pf = Pf.copy()
                        Pf[:n, :n] = self.rescue.apply(Pf[:n, :n], P[:n, :n], flagged, rows)
                Pn = kalman.predict(Pf, self.Fb[q], self.Qb[q])
            tr_q = batched.trace(Pf[:n, :n])
            if full:
                Pn_all, trf = Pn, tr_q
                if want_cov:
                    Pfx = np.ascontiguousarray(Pf[:n, :n])
            else:
                Pn_all[:, :, idx] = Pn
                trf[idx] = tr_q
                if want_cov:
                    Pfx[:, :, idx] = Pf[:n, :n]
            if xi is not None:
                xfq = xi if dx is None else xi + dx
                xin = self.Fb[q] @ xfq + self.D[q] @ yq
                if full:
                    xf, xin_all = xfq[:n], xin
                else:
                    xf[:, idx] = xfq[:n]
                    xin_all[:, idx] = xin
        self.P = Pn_all
        if self.xi is not None:
            self.xi = xin_all
        return xf, trf, Pfx


def _resolved(P: np.ndarray, C: np.ndarray, M: np.ndarray) -> np.ndarray:
    """P = C M Cᵀ (+ noise) per run, or ``inf`` where round-off can have cancelled its digits:
    ε_mach·‖C‖_F²·tr M > FIXED_GAIN_PRECISION·tr P (an unstable plant's second moment M grows without
    bound; :data:`netkf_cli.core.tolerances.FIXED_GAIN_PRECISION`)."""
    with np.errstate(over="ignore", invalid="ignore"):
        noise = np.finfo(float).eps * float(np.sum(C * C)) * batched.trace(M)
        lost = ~(noise <= FIXED_GAIN_PRECISION * batched.trace(P))
    if lost.any():
        P = P.copy()
        P[:, :, lost] = np.inf
    return P


def linear_filter_covariances(model: AugmentedModel, filt: LinearFilter, modes: np.ndarray, x0, P0, steps,
                              quantities=("filtered",), base: str = "paper"):
    """Per-run error covariances of a fixed-gain filter given its mode path: yield (k, {quantity: P}).

    ζ = [ξ; s] (dimension D = d + r); given θ the conditional second moment M = E[ζζᵀ | θ] follows the
    Lyapunov (Joseph-type, any gain) recursion M⁺ = 𝒜_q M 𝒜_qᵀ + ℬ_q Σ ℬ_qᵀ, 𝒜_q = [[F_q, 0],
    [G_s H_q, A_s]], ℬ_q = [[G_q], [G_s J_q]] (eq. 29 with the filter's gains; Costa, Fragoso & Marques
    2005, Prop. 3.35) — ``kalman.predict``(M, 𝒜_q, ℬ_q Σ ℬ_qᵀ) on the runs of each mode. Trace step
    t = k − 1 carries the k-th measurement: ``filtered`` P_{k|k} = C_q M C_qᵀ + L_f J_q Σ J_qᵀ L_fᵀ with
    C_q = [E_x − L_f H_q, −E_f] (the error of x̂(k|k)), ``predicted`` P_{k+1|k} = [E_x, −E_p] M⁺ [·]ᵀ
    (the error of the next x̂(·|·−1) = E_p s). Exact for any gains (no Gaussianity needed).
    """
    d, n = model.d, model.n
    r = filt.As.shape[1]
    D = d + r
    K, runs = modes.shape
    xbar, cov = model.prior_moments(np.asarray(x0, float), np.asarray(P0, float), base)
    z0 = np.concatenate([xbar, filt.s0])
    M0 = np.outer(z0, z0)
    M0[:d, :d] += cov
    M = np.repeat(M0[:, :, None], runs, axis=2)
    want = sorted(int(k) for k in steps)
    last = want[-1] if want else 0
    wset = set(want)
    Sig = model.Sigma
    Cp = np.concatenate([model.Ex, -filt.Ep], axis=1)
    zero_n = np.zeros((n, n))
    for t in range(min(K, last)):
        groups = ModeGroups(modes[t])
        report = t + 1 in wset
        out = {q: np.empty((n, n, runs)) for q in quantities} if report else None
        Mn = np.empty_like(M)
        for q in groups.order:
            idx = groups.idx[q]
            Mq = M if groups.all_one[q] else M[:, :, idx]
            Aq = np.zeros((D, D))
            Aq[:d, :d] = model.F[q]
            Aq[d:, :d] = filt.Gs[t] @ model.H[q]
            Aq[d:, d:] = filt.As[t]
            Bq = np.concatenate([model.G[q], filt.Gs[t] @ model.J[q]], axis=0)
            val = kalman.predict(Mq, Aq, Bq @ Sig @ Bq.T)
            if groups.all_one[q]:
                Mn = val
            else:
                Mn[:, :, idx] = val
            if report:
                got = {}
                if "filtered" in quantities:
                    Cq = np.concatenate([model.Ex - filt.Lf[t] @ model.H[q], -filt.Ef[t]], axis=1)
                    LJ = filt.Lf[t] @ model.J[q]
                    got["filtered"] = _resolved(kalman.predict(Mq, Cq, LJ @ Sig @ LJ.T), Cq, Mq)
                if "predicted" in quantities:
                    got["predicted"] = _resolved(kalman.predict(val, Cp, zero_n), Cp, val)
                for qn, v in got.items():
                    if groups.all_one[q]:
                        out[qn] = v.copy()
                    else:
                        out[qn][:, :, idx] = v
        M = Mn
        if report:
            yield t + 1, out


# =========================================================================== compiled mode-aware KF
_NB_KERNEL = None


def resolve_backend(backend: str, m: int | None = None) -> str:
    """``auto`` → ``numba`` when numba imports (measured faster for every m: see the module docstring),
    else ``numpy``; ``numba`` without numba is a ConfigError. ``m`` is accepted for compatibility."""
    if backend == "auto":
        return "numba" if numba_available() else "numpy"
    if backend == "numba" and not numba_available():
        raise ConfigError.at("estimator.backend", "numba is not installed: pip install 'netkf[fast]' or use numpy")
    return backend


def _numba_kernel():
    """Compile (once, cached on disk) the run-outer, time-inner mode-aware KF (covariance only) on kalman_numba's primitives."""
    global _NB_KERNEL
    if _NB_KERNEL is not None:
        return _NB_KERNEL
    import numba  # optional (netkf[fast]): imported only when the compiled backend runs

    from netkf_cli.linalg import kalman_numba as kn  # needs numba: the compiled primitives

    @numba.njit(cache=True, nogil=True)
    def run(P, modes, t0, t1, H, Rq, rowptr, cols, vals, Qb, scale, rtol, n, limit, Pfx, flag):  # pragma: no cover - compiled
        # F̄_q in CSR form (rowptr[q], cols[q], vals[q]): the augmented transition is mostly zeros
        # P (runs, d, d) = P(t0|t0−1) in, P(t1|t1−1) out; Pfx (n, n, runs) = P_x(t1−1|t1−1);
        # modes (runs, T): each run contiguous
        d = P.shape[1]
        runs = P.shape[0]
        m = H.shape[1]
        Pl = np.empty((d, d))
        Pf = np.empty((d, d))
        tmp = np.empty((d, d))
        S = np.empty((m, m))
        X = np.empty((m, d))
        e = np.zeros(m)
        dx = np.empty(d)
        for r in range(runs):
            for i in range(d):
                for j in range(d):
                    Pl[i, j] = P[r, i, j]
            for t in range(t0, t1):
                q = modes[r, t]
                trx = 0.0
                tra = 0.0
                for i in range(d):
                    tra += Pl[i, i]
                    if i < n:
                        trx += Pl[i, i]
                if (q == 0 or q == 2) and not (trx <= limit):
                    flag[r] = True  # the plain KF's overflow policy applies: numpy redoes this run
                if q == 2:
                    for i in range(d):
                        for j in range(d):
                            Pf[i, j] = Pl[i, j]
                else:
                    kn.update_pinv(Pl, H[q], Rq[q], rtol * (scale + tra), e, Pf, dx, S, X)
                if t == t1 - 1:
                    for i in range(n):
                        for j in range(n):
                            Pfx[i, j, r] = Pf[i, j]
                kn.predict_csr(Pf, q, rowptr, cols, vals, Qb, Pl, tmp)
            if flag[r]:
                continue  # left at its input: the numpy path redoes this run from there
            for i in range(d):
                for j in range(d):
                    P[r, i, j] = Pl[i, j]

    _NB_KERNEL = run
    return run


def _csr(F: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rowptr (N, d+1), cols (N, nnz), vals (N, nnz)) of the per-mode matrices F (N, d, d)."""
    N, d = F.shape[0], F.shape[1]
    nnz = max(1, int(max((F[q] != 0).sum() for q in range(N))))
    rowptr, cols, vals = np.zeros((N, d + 1), np.int64), np.zeros((N, nnz), np.int64), np.zeros((N, nnz))
    for q in range(N):
        k = 0
        for a in range(d):
            for c in range(F.shape[2]):
                if F[q, a, c] != 0.0:
                    cols[q, k], vals[q, k] = c, F[q, a, c]
                    k += 1
            rowptr[q, a + 1] = k
    return rowptr, cols, vals


class ModeAwareCompiled:
    """The mode-aware KF of :class:`ModeAwareKFTr` compiled, covariance only (numba, kalman_numba's inlined
    ``update_pinv`` / ``predict``): a run-outer, time-inner loop on one run's d×d covariance at a time,
    the (d, d, runs) layout in and out. Equal to the numpy path to rounding (tested); a run whose
    x block trips the plain KF's overflow flag (``kalman.Rescue``) is redone by the numpy path. (The
    state-level estimates with states: :func:`mode_aware_estimates_compiled`.)"""

    def __init__(self, model: AugmentedModel, runs: int, xhat0, P0, states: bool = False, base: str = "paper"):
        if states:
            raise ValueError("the compiled mode-aware KF is covariance only (states: the numpy ModeAwareKFTr)")
        self.ref = ModeAwareKFTr(model, runs, xhat0, P0, False, base)
        self.model = model
        self._fn = _numba_kernel()
        self._args = (np.ascontiguousarray(model.H), np.ascontiguousarray(self.ref.Rq), *_csr(self.ref.Fb),
                      np.ascontiguousarray(self.ref.Qb))

    @property
    def P(self):
        return self.ref.P

    def advance(self, modes: np.ndarray, t0: int, t1: int):
        """Run steps t0 … t1−1 (``modes`` (K, runs)); returns (P_x(t1−1|t1−1) (n, n, runs), None)."""
        md, ref = self.model, self.ref
        n, runs = md.n, modes.shape[1]
        PT = np.ascontiguousarray(np.moveaxis(ref.P, -1, 0))  # (runs, d, d): one run's P contiguous
        Pfx = np.empty((n, n, runs))
        flag = np.zeros(runs, dtype=np.bool_)
        mT = np.ascontiguousarray(modes[t0:t1].T, dtype=np.int64)  # run-outer: each run's modes contiguous
        self._fn(PT, mT, 0, t1 - t0, *self._args, ref.scale, ZERO_INNOVATION_RTOL, n, ref.rescue.limit, Pfx, flag)
        P = np.moveaxis(PT, 0, -1)  # a view in the (d, d, runs) layout
        if flag.any():  # the overflow policy: these runs through the numpy reference
            idx = np.flatnonzero(flag)
            sub = ModeAwareKFTr.__new__(ModeAwareKFTr)
            sub.__dict__.update(ref.__dict__)
            sub.P = P[:, :, idx]  # flagged runs were left at their input
            sub.xi = None
            for t in range(t0, t1):
                _, _, pf = sub.step(None, modes[t, idx], want_cov=t == t1 - 1)
                if t == t1 - 1:
                    Pfx[:, :, idx] = pf
            P[:, :, idx] = sub.P
        ref.P = P
        return Pfx, None


# =========================================================================== compiled state-level paths
def linear_filter_covariances_compiled(model: AugmentedModel, filt: LinearFilter, modes: np.ndarray, x0, P0, steps,
                                       quantities=("filtered",), base: str = "paper"):
    """:func:`linear_filter_covariances` compiled: the same recursion per run in a kernel generated for these
    matrices (:mod:`netkf_cli.estimators._markov_codegen`: structural zeros skipped, constants inlined); equal to
    the numpy path to rounding. Yields (k, {quantity: P (n, n, runs)})."""
    d, n = model.d, model.n
    r = filt.As.shape[1]
    D = d + r
    if D > _markov_codegen.MAX_DIM:  # the written-out kernel grows as D³: numpy beyond
        yield from linear_filter_covariances(model, filt, modes, x0, P0, steps, quantities, base)
        return
    K, runs = modes.shape
    want = sorted(int(k) for k in steps)
    if not want:
        return
    t1 = min(K, want[-1])
    xbar, cov = model.prior_moments(np.asarray(x0, float), np.asarray(P0, float), base)
    z0 = np.concatenate([xbar, filt.s0])
    M0 = np.outer(z0, z0)
    M0[:d, :d] += cov
    Sig = model.Sigma
    A = np.zeros((t1, N_MODES, D, D))
    A[:, :, :d, :d] = model.F[None]
    A[:, :, d:, :d] = np.einsum("tra,qad->tqrd", filt.Gs[:t1], model.H)
    A[:, :, d:, d:] = filt.As[:t1, None]
    B = np.concatenate([np.broadcast_to(model.G[None], (t1,) + model.G.shape),
                        np.einsum("tra,qap->tqrp", filt.Gs[:t1], model.J)], axis=2)  # (t1, N, D, p)
    BSB = np.einsum("tqap,pr,tqbr->tqab", B, Sig, B)
    Cf = np.concatenate([model.Ex[None, None] - np.einsum("tna,qad->tqnd", filt.Lf[:t1], model.H),
                         np.broadcast_to(-filt.Ef[:t1, None], (t1, N_MODES, n, r))], axis=3)  # (t1, N, n, D)
    LJ = np.einsum("tna,qap->tqnp", filt.Lf[:t1], model.J)
    LJS = np.einsum("tqap,pr,tqbr->tqab", LJ, Sig, LJ)
    Cp = np.ascontiguousarray(np.concatenate([model.Ex, -filt.Ep], axis=1))
    flat = lambda X: np.ascontiguousarray(X.reshape((t1 * N_MODES,) + X.shape[2:]))  # noqa: E731 - index t·N + q
    slot = np.full(t1 + 1, -1, np.int64)
    rep = [k for k in want if k <= t1]
    wf, wp = "filtered" in quantities, "predicted" in quantities
    iu = np.triu_indices(D)
    Mu = np.broadcast_to(M0[iu], (runs, iu[0].size)).copy()  # each run's M (upper triangle), carried
    Cff = flat(Cf)
    args = (flat(A), flat(BSB), slot, Cff, flat(LJS), np.ascontiguousarray((Cff * Cff).sum(axis=(1, 2))),
            float(np.sum(Cp * Cp)), wf, wp, float(np.finfo(float).eps), FIXED_GAIN_PRECISION)
    run = _markov_codegen.kernel(A, BSB, Cf, LJS, Cp, model.H, model.J, d)
    for t0, t1b in _blocks(t1, BLOCK_STEPS):  # a block of steps at a time: its reports only (memory ∝ block × runs)
        brep = [k for k in rep if t0 < k <= t1b]
        slot[t0 + 1: t1b + 1] = -1
        slot[brep] = np.arange(len(brep))
        out_f = np.empty((len(brep) if wf else 0, n, n, runs))
        out_p = np.empty((len(brep) if wp else 0, n, n, runs))
        mT = np.ascontiguousarray(modes[t0:t1b].T, dtype=np.int64)
        run(Mu, mT, t0, t1b, *args, out_f, out_p)
        for i, k in enumerate(brep):
            got = {}
            if wf:
                got["filtered"] = out_f[i]
            if wp:
                got["predicted"] = out_p[i]
            yield k, {q: got[q] for q in quantities}


BLOCK_STEPS = 4
"""Steps per call of the compiled kernels (:func:`linear_filter_covariances_compiled`,
:func:`mode_aware_estimates_compiled`): a chunk's per-run outputs exist for one block of steps at a time
(4 · n² · 8 B per run and quantity), whatever the horizon. The numbers do not depend on it (tested)."""


def _blocks(t1: int, size: int):
    """(t0, t1) of consecutive blocks of ``size`` steps covering 0 … t1 − 1."""
    size = max(1, int(size))
    return [(t0, min(t1, t0 + size)) for t0 in range(0, t1, size)]


def mode_aware_estimates_compiled(model: AugmentedModel, modes: np.ndarray, y: np.ndarray, xhat0, P0, steps,
                                  base: str = "paper") -> "Mapping[int, tuple]":
    """The mode-aware KF with states (:class:`ModeAwareKFTr`, ``states=True``) compiled for one output (m = 1:
    a kernel generated for this model, :func:`netkf_cli.estimators._markov_codegen.source_mode_aware`) over trace
    steps 0 … max(steps) − 1: {k: (x̂(k|k), P_x(k|k), x̂(k+1|k), P_x(k+1|k))} for k in ``steps`` (run axis
    last). ``y`` (m, horizon+2, runs): trace step t reads y[:, t + 1]. A run that trips the plain KF's overflow
    flag is redone by the numpy reference. Equal to the numpy path to rounding.

    A lazy mapping (:func:`mode_aware_blocks`): reading the steps in ascending order runs the kernel once, a
    block of :data:`BLOCK_STEPS` steps at a time, and keeps one block's outputs (memory ∝ block × runs, not
    horizon × runs); reading an earlier step again reruns from the start (the same numbers)."""
    return _LazySteps(lambda: mode_aware_blocks(model, modes, y, xhat0, P0, steps, base),
                      sorted({int(k) for k in steps}))


class _LazySteps(Mapping):
    """{k: value} over a generator of (k, value) in ascending k (``make()`` starts it): a forward read advances
    it and keeps only the value read; a read behind it restarts the generator."""

    def __init__(self, make, keys):
        self._make, self._keys = make, list(keys)
        self._keyset = set(self._keys)
        self._gen, self._last = None, None

    def __getitem__(self, k):
        k = int(k)
        if k not in self._keyset:
            raise KeyError(k)
        if self._last is not None and self._last[0] == k:
            return self._last[1]
        if self._gen is None or (self._last is not None and k < self._last[0]):
            self._gen, self._last = self._make(), None
        for kk, val in self._gen:
            self._last = (kk, val)
            if kk == k:
                return val
        raise KeyError(k)  # pragma: no cover - every key is yielded

    def __iter__(self):
        return iter(self._keys)

    def __len__(self):
        return len(self._keys)


def _open_loop_trace_max(model: AugmentedModel, P0x: np.ndarray, t1: int) -> float:
    """max over k < t1 of tr Σ_x(k), Σ_x(k+1) = A Σ_x(k) Aᵀ + Q from the prior's x block: the unconditional
    covariance of x_k, which bounds the x block of every run's prior P(k|k−1) (conditioning on the modes and
    the measurements only lowers it; x's dynamics do not depend on the modes)."""
    A, Q = model.A, model.Q
    Sx, top = np.array(P0x, float), 0.0
    with np.errstate(over="ignore", invalid="ignore"):
        for _ in range(t1):
            tr = float(np.trace(Sx))
            if not np.isfinite(tr):
                return np.inf
            top = max(top, tr)
            Sx = A @ Sx @ A.T + Q
    return top


def mode_aware_blocks(model: AugmentedModel, modes: np.ndarray, y: np.ndarray, xhat0, P0, steps, base: str = "paper"):
    """Yield (k, (x̂(k|k), P_x(k|k), x̂(k+1|k), P_x(k+1|k))) for k in ``steps`` ascending
    (:func:`mode_aware_estimates_compiled`), the kernel run a block of :data:`BLOCK_STEPS` steps at a time with
    each run's ξ̂ and P carried between blocks (the same operations: the same numbers).

    Blocks need a run never to trip the overflow flag after its first block (its earlier outputs were already
    yielded; the numpy reference redoes a flagged run from the start): used when the open-loop bound
    (:func:`_open_loop_trace_max`) stays below a quarter of the flag's limit over the horizon; otherwise the
    whole horizon is one block (exactly the one-call algorithm)."""
    md = model
    if md.m != 1:
        raise ValueError("the compiled mode-aware KF with states needs one output (m = 1): use ModeAwareKFTr")
    n, d, runs = md.n, md.d, modes.shape[1]
    want = sorted({int(k) for k in steps})
    if not want:
        return
    t1 = want[-1]
    ref = ModeAwareKFTr(md, 1, xhat0, P0, states=True, base=base)
    size = BLOCK_STEPS if _open_loop_trace_max(md, ref.P[:n, :n, 0], t1) <= 0.25 * ref.rescue.limit else t1
    iu = np.triu_indices(d)
    xi = np.broadcast_to(ref.xi[:, 0], (runs, d)).copy()
    Pu = np.broadcast_to(ref.P[:, :, 0][iu], (runs, iu[0].size)).copy()
    flag = np.zeros(runs, dtype=np.bool_)
    slot = np.full(t1 + 1, -1, np.int64)
    run = _markov_codegen.kernel_mode_aware(md.H, ref.Rq, ref.Fb, ref.Qb, ref.D, n)
    redo = []  # (runs, the numpy reference for them) of the runs flagged so far, run from the start
    for t0, tb in _blocks(t1, size):
        bw = [k for k in want if t0 < k <= tb]
        slot[:] = -1
        slot[bw] = np.arange(len(bw))
        S = len(bw)
        xf, xp = np.empty((S, n, runs)), np.empty((S, n, runs))
        Pf, Pp = np.empty((S, n, n, runs)), np.empty((S, n, n, runs))
        before = flag.copy()
        yT = np.ascontiguousarray(y[0, t0 + 1: tb + 1].T)  # (runs, block): one run contiguous
        mT = np.ascontiguousarray(modes[t0:tb].T, dtype=np.int64)
        run(xi, Pu, mT, yT, t0, tb, ref.scale, ZERO_INNOVATION_RTOL, ref.rescue.limit, slot, xf, Pf, xp, Pp, flag)
        new = np.flatnonzero(flag & ~before)
        if new.size:  # the overflow policy: these runs through the numpy reference from the start
            kf = ModeAwareKFTr(md, new.size, xhat0, P0, states=True, base=base)
            for t in range(t0):
                kf.step(y[:, t + 1, new], modes[t, new])
            redo.append((new, kf))
        for idx, kf in redo:
            for t in range(t0, tb):
                a, _, pf = kf.step(y[:, t + 1, idx], modes[t, idx], want_cov=slot[t + 1] >= 0)
                s = slot[t + 1]
                if s >= 0:
                    xf[s][:, idx], Pf[s][:, :, idx] = a, pf
                    xp[s][:, idx], Pp[s][:, :, idx] = kf.xi[:n], kf.P[:n, :n]
        for i, k in enumerate(bw):
            yield k, (xf[i], Pf[i], xp[i], Pp[i])
