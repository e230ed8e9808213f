"""The LMI-designed filter of Moayedi, Soh & Foo 2009, Sec. III (eqs 24–44).

Filter (eqs 24, 41, 44):  x_s(k+1) = A_s(k) x_s(k) + G_s(k) y(k),  x_s(k|k) = x_s(k) + L(k) y(k).

What is solved, exactly
-----------------------
``ζ(k) = [ξ(k); x_s(k)]`` with ξ the exact augmented state of
:mod:`netkf_cli.estimators.markov_filters` (the paper's X(k) plus v(k−1), so the driving noise
ε = [w; v] is white with covariance Σ = L_Σ L_Σᵀ, possibly singular). For mode q:

    A_F,q = [[F_q, 0], [G_s H_q, A_s]],  B_F,q = [[G_q], [G_s J_q]]                 (eq. 29)
    A_F,q(k|k) = [[I, 0], [L H_q, I]],   B_F,q(k|k) = [[0], [L J_q]]                 (eq. 36)
    Γ_F = [I 0 0 0 −I]  (e = x − x_s),   Γ_0 = [I_d 0]  (the ξ block)                (eq. 28)

Λ_j(k) is the design's second moment of ζ(k) given θ(k−1) = j; the design knows only the
marginals ρ_q (not ρ_{q/j}) and mixes (eq. 34)

    Φ_q(k) = Σ_j ρ_j Λ_j(k)                                  (q ≠ 2)
    Φ_2(k) = Σ_{j≥2} ρ_j Λ_j(k) / Σ_{j≥2} ρ_j                 (precedence: no 1 → 2)

**Prediction step** (eqs 34, 34a, 41), one SDP per k, variables A_s, G_s, Λ_q (q = 1..4):

    minimize   Σ_q ρ_q tr(Γ_F Λ_q Γ_Fᵀ)
    subject to [[Λ_q, A_F,q Φ_q^{1/2}, B_F,q L_Σ], [·, I, 0], [·, 0, I]] ⪰ 0      (34), q = 1..4
               Γ_0 Λ_q Γ_0ᵀ ⪯ F_q Φ_q,ξ F_qᵀ + G_q Σ G_qᵀ + ε_q I                      (34a)

with ε_q = ε·max(1, tr(F_q Φ_q,ξ F_qᵀ + G_q Σ G_qᵀ)/d) (ε relative to the block's size: an
absolute ε ≈ 0 leaves the feasible set without interior and interior-point solvers fail).

The first LMI is eq. (34) with the Schur complement taken through factors instead of
Φ⁻¹ and Λ_W⁻¹ (Φ is singular at k = 0 and Σ is singular in Example 1); it is equivalent to
Λ_q ⪰ A_F,q Φ_q A_F,qᵀ + B_F,q Σ B_F,qᵀ (eqs 30–32). The right side of (34a) is the paper's
"minimum-trace Λ_ζ,q,0" in closed form (the ξ block does not depend on the gains).
**Update step** (eqs 37, 37a, 43): the same with A_F,q(k|k), B_F,q(k|k), variable L and
Γ_0 Λ_q(k|k) Γ_0ᵀ ⪯ Φ_q,ξ + εI.

After each solve Λ_q(k+1) is *recomputed* as A_F,q Φ_q A_F,qᵀ + B_F,q Σ B_F,qᵀ with the
solved gains (eq. 32) — the SDP's Λ_q is only an upper bound and is not unique off the
error block, so propagating it would make the recursion depend on the solver's path.
Why this matches the paper: the objective is their eq. (41)/(43) objective, the LMIs are
(34)/(37) and (34a)/(37a), and the recursion is (32). Because A_F,q, B_F,q are affine in the
gains, the problem is a convex quadratic in (A_s, G_s) (resp. L); :func:`step_closed_form`
solves its normal equations, which the tests use to check the SDP.

The scenario block ``kind: markov_lmi`` (:class:`MarkovLMIEstimator`, the generic per-run covariances of the
LMI, naive and mode-aware filters on netkf's time base) lives here, above
:mod:`netkf_cli.estimators.markov_filters` (which imports nothing of this module).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field
from scipy import sparse

from netkf_cli.linalg import kalman
from netkf_cli.linalg import sdp as conic
from netkf_cli.core.errors import ConfigError
from netkf_cli.estimators import _markov_codegen
from netkf_cli.estimators.kf import channel_streams
from netkf_cli.estimators.markov_filters import (
    N_MODES,
    AugmentedModel,
    LinearFilter,
    ModeAwareCompiled,
    ModeAwareKFTr,
    linear_filter_covariances,
    linear_filter_covariances_compiled,
    lmmse_filter,
    mode_aware_estimates_compiled,
    naive_filter,
    pinv_psd,
    psd_sqrt,
    resolve_backend,
)
from netkf_cli.linalg.riccati import initial_covariance
from netkf_cli.core.spec import EstimatorModel, Matrix, NonNegFloat, NonNegInt, PositiveFloat


def design_weights(rho: np.ndarray, precedence: bool = True) -> np.ndarray:
    """W with Φ_q = Σ_j W[q, j] Λ_j (eq. 34): ρ_j, and for q = 2 the precedence-renormalized row."""
    rho = np.asarray(rho, float)
    W = np.tile(rho, (N_MODES, 1))
    if precedence:
        w2 = rho.copy()
        w2[0] = 0.0
        if w2.sum() > 0:
            W[1] = w2 / w2.sum()
    return W


@dataclass
class LMIDesign:
    """Result of :func:`lmi_design`: the filter plus per-step diagnostics."""

    filter: LinearFilter
    diagnostics: dict = field(default_factory=dict)


class _Blocks:
    """Constant matrices of the ζ system for a model."""

    def __init__(self, model: AugmentedModel):
        n, m, d, p = model.n, model.m, model.d, model.p
        self.n, self.m, self.d, self.p, self.D = n, m, d, p, d + n
        D = d + n
        self.Gam = np.zeros((n, D))
        self.Gam[:, :n] = np.eye(n)
        self.Gam[:, d:] = -np.eye(n)
        self.model = model

    # ---- exact propagation with given gains
    def AF(self, q, As, Gs):
        md, d, n = self.model, self.d, self.n
        M = np.zeros((self.D, self.D))
        M[:d, :d] = md.F[q]
        M[d:, :d] = Gs @ md.H[q]
        M[d:, d:] = As
        return M

    def BF(self, q, Gs):
        md, d = self.model, self.d
        return np.concatenate([md.G[q], Gs @ md.J[q]], axis=0)

    def AFu(self, q, L):
        md, d, n = self.model, self.d, self.n
        M = np.eye(self.D)
        M[d:, :d] = L @ md.H[q]
        return M

    def BFu(self, q, L):
        md, d = self.model, self.d
        return np.concatenate([np.zeros((d, self.p)), L @ md.J[q]], axis=0)

    def propagate(self, Phi, As, Gs):
        S = self.model.Sigma
        out = []
        for q in range(N_MODES):
            A, B = self.AF(q, As, Gs), self.BF(q, Gs)
            L = A @ Phi[q] @ A.T + B @ S @ B.T
            out.append((L + L.T) / 2)
        return np.array(out)

    def update(self, Phi, L):
        S = self.model.Sigma
        out = []
        for q in range(N_MODES):
            A, B = self.AFu(q, L), self.BFu(q, L)
            M = A @ Phi[q] @ A.T + B @ S @ B.T
            out.append((M + M.T) / 2)
        return np.array(out)

    def cost(self, rho, Lams):
        return float(sum(rho[q] * np.trace(self.Gam @ Lams[q] @ self.Gam.T) for q in range(N_MODES)))


def step_closed_form(blocks: _Blocks, rho, Phi):
    """Minimizers of the prediction and update objectives (normal equations).

    Prediction: e(k+1) = t_q − Θ u_q with Θ = [A_s G_s], t_q = [A 0 0 0 0] ζ + [I 0] ε,
    u_q = [[0 I], [H_q 0]] ζ + [0; J_q] ε, so Θ = R_tu R_uu⁺ with
    R_uu = Σ ρ_q (U_q Φ_q U_qᵀ + V_q Σ V_qᵀ), R_tu = Σ ρ_q (T Φ_q U_qᵀ + E_w Σ V_qᵀ).
    Update: e(k|k) = Γ_F ζ − L (H̃_q ζ + J_q ε) ⇒ L = (Σ ρ_q Γ_F Φ_q H̃_qᵀ)(Σ ρ_q (H̃_q Φ_q H̃_qᵀ + J_q Σ J_qᵀ))⁺.
    """
    md = blocks.model
    n, m, d, p, D = blocks.n, blocks.m, blocks.d, blocks.p, blocks.D
    Sig = md.Sigma
    T = np.zeros((n, D)); T[:, :n] = md.A
    Ew = np.zeros((n, p)); Ew[:, :n] = np.eye(n)
    Ruu = np.zeros((n + m, n + m)); Rtu = np.zeros((n, n + m))
    Ryy = np.zeros((m, m)); Rey = np.zeros((n, m))
    for q in range(N_MODES):
        U = np.zeros((n + m, D)); U[:n, d:] = np.eye(n); U[n:, :d] = md.H[q]
        V = np.zeros((n + m, p)); V[n:] = md.J[q]
        Ruu += rho[q] * (U @ Phi[q] @ U.T + V @ Sig @ V.T)
        Rtu += rho[q] * (T @ Phi[q] @ U.T + Ew @ Sig @ V.T)
        Ht = np.zeros((m, D)); Ht[:, :d] = md.H[q]
        Ryy += rho[q] * (Ht @ Phi[q] @ Ht.T + md.J[q] @ Sig @ md.J[q].T)
        Rey += rho[q] * (blocks.Gam @ Phi[q] @ Ht.T)
    Theta = Rtu @ pinv_psd(Ruu, np.trace(Ruu) + 1e-300, rtol=1e-12)
    L = Rey @ pinv_psd(Ryy, np.trace(Ryy) + 1e-300, rtol=1e-12)
    return Theta[:, :n], Theta[:, n:], L


class _SDP:
    """The prediction and update SDPs of one design (eqs 34/34a, 37/37a) handed to Clarabel directly.

    The same problems as :class:`_CvxpySDP` (minimize Σ_q ρ_q tr(Γ_F Λ_q Γ_Fᵀ) subject to the LMIs, the LMI
    block symmetrized as there), in the conic form cvxpy would give Clarabel: every LMI is affine in the
    unknowns (A_s, G_s, Λ_1..Λ_4 resp. L, Λ_1..Λ_4), read off by probing (:func:`netkf_cli.linalg.sdp.probes`),
    one PSD-triangle cone each. No cvxpy import (~0.7 s CPU per process) nor its canonicalization (~0.1 s per
    solve). The optimum agrees with cvxpy's to the solver's tolerance (tests/markov/test_filters.py).
    """

    def __init__(self, blocks: _Blocks, rho, eps: float, solver: str, tol: float):
        md = blocks.model
        n, m, d, p, D = blocks.n, blocks.m, blocks.d, blocks.p, blocks.D
        self.blocks, self.rho, self.tol, self.eps = blocks, np.asarray(rho, float), tol, eps
        lams = [conic.Var((D, D), symmetric=True) for _ in range(N_MODES)]
        self.vars_p = [conic.Var((n, n)), conic.Var((n, m))] + lams
        self.vars_u = [conic.Var((n, m))] + lams
        self.Z_dn = np.zeros((d, n))

    def _lmi(self, Lam, AFPh, BFL):
        """The stacked block [[Λ, A_F Φ^½, B_F L_Σ], [·, I, 0], [·, 0, I]] (symmetrized by svec)."""
        P, D = Lam.shape[0], Lam.shape[1]
        p = BFL.shape[2]
        M = np.zeros((P, 2 * D + p, 2 * D + p))
        M[:, :D, :D] = Lam
        M[:, :D, D:2 * D] = AFPh
        M[:, :D, 2 * D:] = BFL
        M[:, D:2 * D, :D] = AFPh.transpose(0, 2, 1)
        M[:, 2 * D:, :D] = BFL.transpose(0, 2, 1)
        M[:, D:, D:] += np.eye(D + p)
        return M

    def _solve(self, variables, lmis):
        """min Σ_q ρ_q tr(Γ_F Λ_q Γ_Fᵀ) s.t. ``lmis`` ⪰ 0 (stacked probes) → (values, objective, status, seconds)."""
        import clarabel  # here, not at module level: only an SDP check or design: sdp solves one

        rho, Gam = self.rho, self.blocks.Gam
        units = [(i, E) for i, v in enumerate(variables) for E in v.units()]
        nx, first = len(units), len(variables) - N_MODES  # the Λ_q are the last N_MODES unknowns
        c = np.zeros(nx)
        for k, (i, E) in enumerate(units):
            if i >= first:
                c[k] = rho[i - first] * np.trace(Gam @ E @ Gam.T)
        rows, b, cones = [], [], []
        for V, _ in conic.probes(variables, lmis, stacked=True):
            rows.append(-(V[1:] - V[0]).T)
            b.append(V[0])
            cones.append(clarabel.PSDTriangleConeT(conic._svec_order(V.shape[1])))
        settings = clarabel.DefaultSettings()
        settings.verbose = False
        settings.tol_gap_abs = settings.tol_gap_rel = settings.tol_feas = self.tol
        t = time.perf_counter()
        try:
            sol = clarabel.DefaultSolver(sparse.csc_matrix((nx, nx)), c, sparse.csc_matrix(np.vstack(rows)),
                                         np.concatenate(b), cones, settings).solve()
        except Exception as exc:  # pragma: no cover - a solver crash
            raise RuntimeError(f"LMI solve failed: {exc}") from None
        dt = time.perf_counter() - t
        status = conic.STATUS.get(str(sol.status).split(".")[-1], str(sol.status))
        x = np.asarray(sol.x, dtype=float)
        if status not in ("optimal", "optimal_inaccurate") or x.size != nx or not np.all(np.isfinite(x)):
            raise RuntimeError(f"LMI solve failed: {status}")
        values = [np.zeros(v.shape) for v in variables]
        for k, (i, E) in enumerate(units):
            values[i] = values[i] + x[k] * E
        return values, float(c @ x), status, dt

    def predict(self, Phi):
        md, d = self.blocks.model, self.blocks.d
        Ph = [psd_sqrt(Phi[q]) for q in range(N_MODES)]
        X0 = []
        for q in range(N_MODES):
            X = md.F[q] @ Phi[q][:d, :d] @ md.F[q].T + md.G[q] @ md.Sigma @ md.G[q].T
            X0.append((X + X.T) / 2 + _eps_block(self.eps, X))

        def lmis(vals):
            As, Gs, Lams = vals[0], vals[1], vals[2:]
            out = []
            for q in range(N_MODES):
                P = As.shape[0]
                AF = np.zeros((P,) + Phi[q].shape)
                AF[:, :d, :d] = md.F[q]
                AF[:, d:, :d] = Gs @ md.H[q]
                AF[:, d:, d:] = As
                BF = np.concatenate([np.broadcast_to(md.G[q], (P,) + md.G[q].shape), Gs @ md.J[q]], axis=1)
                out.append((self._lmi(Lams[q], AF @ Ph[q], BF @ md.Lsig), False))
                out.append((X0[q] - Lams[q][:, :d, :d], False))
            return out

        (a, g, *L), val, status, dt = self._solve(self.vars_p, lmis)
        return a, g, np.array(L), val, status, dt

    def update(self, Phi):
        md, d, n = self.blocks.model, self.blocks.d, self.blocks.n
        Ph = [psd_sqrt(Phi[q]) for q in range(N_MODES)]
        X0 = [(Phi[q][:d, :d] + Phi[q][:d, :d].T) / 2 + _eps_block(self.eps, Phi[q][:d, :d]) for q in range(N_MODES)]

        def lmis(vals):
            Lg, Lams = vals[0], vals[1:]
            out = []
            for q in range(N_MODES):
                P = Lg.shape[0]
                AF = np.zeros((P,) + Phi[q].shape)
                AF[:, :d, :d] = np.eye(d)
                AF[:, d:, :d] = Lg @ md.H[q]
                AF[:, d:, d:] = np.eye(n)
                BF = np.concatenate([np.zeros((P, d, md.Lsig.shape[0])), Lg @ md.J[q]], axis=1)
                out.append((self._lmi(Lams[q], AF @ Ph[q], BF @ md.Lsig), False))
                out.append((X0[q] - Lams[q][:, :d, :d], False))
            return out

        (Lg, *L), val, status, dt = self._solve(self.vars_u, lmis)
        return Lg, np.array(L), val, status, dt


def _eps_block(eps: float, X0: np.ndarray) -> np.ndarray:
    """εI of (34a)/(37a), relative to the size of the block: ε·max(1, tr X0 / d)·I."""
    d = X0.shape[0]
    return eps * max(1.0, float(np.trace(X0)) / d) * np.eye(d)


class _CvxpySDP:
    """The prediction and update SDPs of one design, built once with cvxpy Parameters (DPP): the path of
    ``solver: SCS`` (and the reference :class:`_SDP` is tested against)."""

    def __init__(self, blocks: _Blocks, rho, eps: float, solver: str, tol: float):
        import cvxpy as cp  # here, not at module level: cvxpy (with the scipy.stats it loads) costs ~40 MB and ~1 s in every process
        self.cp = cp
        md = blocks.model
        n, m, d, p, D = blocks.n, blocks.m, blocks.d, blocks.p, blocks.D
        self.blocks, self.solver, self.tol, self.eps = blocks, solver, tol, eps
        Gam, Ls = blocks.Gam, md.Lsig
        I_D, I_p = np.eye(D), np.eye(p)
        Z_Dp, Z_dn = np.zeros((D, p)), np.zeros((d, n))

        def lmi(Lam, AFPh, BFL):
            M = cp.bmat([[Lam, AFPh, BFL], [AFPh.T, I_D, Z_Dp], [BFL.T, Z_Dp.T, I_p]])
            return (M + M.T) / 2 >> 0

        # prediction
        self.As = cp.Variable((n, n), name="A_s")
        self.Gs = cp.Variable((n, m), name="G_s")
        self.Lp = [cp.Variable((D, D), symmetric=True, name=f"Lambda_{q + 1}") for q in range(N_MODES)]
        self.Php = [cp.Parameter((D, D), name=f"Phi_half_{q + 1}") for q in range(N_MODES)]
        self.X0p = [cp.Parameter((d, d), name=f"X0_{q + 1}") for q in range(N_MODES)]  # includes +εI
        cons = []
        for q in range(N_MODES):
            AF = cp.bmat([[md.F[q], Z_dn], [self.Gs @ md.H[q], self.As]])
            BF = cp.vstack([md.G[q], self.Gs @ md.J[q]])
            cons.append(lmi(self.Lp[q], AF @ self.Php[q], BF @ Ls))
            cons.append(self.X0p[q] - self.Lp[q][:d, :d] >> 0)
        obj = sum(rho[q] * cp.trace(Gam @ self.Lp[q] @ Gam.T) for q in range(N_MODES))
        self.pred = cp.Problem(cp.Minimize(obj), cons)
        # update
        self.L = cp.Variable((n, m), name="L")
        self.Lu = [cp.Variable((D, D), symmetric=True, name=f"Lambda_kk_{q + 1}") for q in range(N_MODES)]
        self.Phu = [cp.Parameter((D, D), name=f"Phi_half_u_{q + 1}") for q in range(N_MODES)]
        self.X0u = [cp.Parameter((d, d), name=f"X0_u_{q + 1}") for q in range(N_MODES)]
        cons = []
        for q in range(N_MODES):
            AF = cp.bmat([[np.eye(d), Z_dn], [self.L @ md.H[q], np.eye(n)]])
            BF = cp.vstack([np.zeros((d, p)), self.L @ md.J[q]])
            cons.append(lmi(self.Lu[q], AF @ self.Phu[q], BF @ Ls))
            cons.append(self.X0u[q] - self.Lu[q][:d, :d] >> 0)
        obj = sum(rho[q] * cp.trace(Gam @ self.Lu[q] @ Gam.T) for q in range(N_MODES))
        self.upd = cp.Problem(cp.Minimize(obj), cons)

    def _solve(self, prob):
        cp = self.cp
        if self.solver == "CLARABEL":
            opts = dict(tol_gap_abs=self.tol, tol_gap_rel=self.tol, tol_feas=self.tol)
        else:
            opts = dict(eps_abs=self.tol, eps_rel=self.tol, max_iters=200000)
        t = time.perf_counter()
        prob.solve(solver=getattr(cp, self.solver), **opts)
        dt = time.perf_counter() - t
        if prob.status not in ("optimal", "optimal_inaccurate"):
            raise RuntimeError(f"LMI solve failed: {prob.status}")
        return dt

    def _eps(self, X0):
        """εI of (34a)/(37a), relative to the size of the block: ε·max(1, tr X0 / d)·I."""
        d = X0.shape[0]
        return self.eps * max(1.0, float(np.trace(X0)) / d) * np.eye(d)

    def predict(self, Phi):
        md = self.blocks.model
        d = self.blocks.d
        for q in range(N_MODES):
            self.Php[q].value = psd_sqrt(Phi[q])
            X0 = md.F[q] @ Phi[q][:d, :d] @ md.F[q].T + md.G[q] @ md.Sigma @ md.G[q].T
            self.X0p[q].value = (X0 + X0.T) / 2 + self._eps(X0)
        dt = self._solve(self.pred)
        return self.As.value, self.Gs.value, np.array([L.value for L in self.Lp]), self.pred.value, self.pred.status, dt

    def update(self, Phi):
        d = self.blocks.d
        for q in range(N_MODES):
            self.Phu[q].value = psd_sqrt(Phi[q])
            X0 = Phi[q][:d, :d]
            self.X0u[q].value = (X0 + X0.T) / 2 + self._eps(X0)
        dt = self._solve(self.upd)
        return self.L.value, np.array([L.value for L in self.Lu]), self.upd.value, self.upd.status, dt


def sdp_check_steps(horizon: int, count: int) -> list[int]:
    """The ``count`` steps (evenly spread over 0..horizon−1, always k = 0 and the last) checked by SDP."""
    if count <= 0 or horizon <= 0:
        return []
    return sorted({int(round(v)) for v in np.linspace(0, horizon - 1, min(count, horizon))})


def lmi_design(model: AugmentedModel, rho, x0, P0, horizon: int, *, design: str = "sdp",
               solver: str = "CLARABEL", tol: float = 1e-8, eps: float = 1e-5,
               precedence: bool = True, progress=None, sdp_check: int = 0, base: str = "paper") -> LMIDesign:
    """Gains A_s(k), G_s(k), L(k), k = 0..horizon−1, by the conceptual algorithm of Sec. III-C.

    Initialization (eq. 35, with the prior mean x̂0 = E x(0) instead of 0):
    Λ_j(0) = E ζ(0)ζ(0)ᵀ + diag(0, εI), ζ(0) = [ξ(0); x̂0], for every j.
    ``design='closed_form'`` replaces each SDP (eqs 34/34a, 37/37a) by :func:`step_closed_form` (the
    same convex quadratic's normal equations: the SDP optimum matches it to the solver's tolerance);
    with ``sdp_check = c > 0`` the SDPs are still solved at c steps (:func:`sdp_check_steps`) on the
    same Φ_q, as a check recorded in the diagnostics (their gains are not used).
    ``base``: the initial condition ξ(0) of the design (:meth:`AugmentedModel.prior_moments`: the
    paper's eq. 35, or netkf's P0 = P_{0|0} with the first measurement one step later).
    """
    rho = np.asarray(rho, float)
    blocks = _Blocks(model)
    n, m, d, D = blocks.n, blocks.m, blocks.d, blocks.D
    x0 = np.asarray(x0, float)
    xbar, cov = model.prior_moments(x0, np.asarray(P0, float), base)
    x0 = xbar[:n]  # the design's x_s(0) = E x at the first measurement
    zbar = np.concatenate([xbar, x0])
    Lam0 = np.outer(zbar, zbar)
    Lam0[:d, :d] += cov
    Lam0[d:, d:] += eps * np.eye(n)
    Lam = np.repeat(Lam0[None], N_MODES, axis=0)
    W = design_weights(rho, precedence)
    checks = set(sdp_check_steps(horizon, sdp_check)) if design == "closed_form" else set()
    sdp = (_SDP if solver == "CLARABEL" else _CvxpySDP)(blocks, rho, eps, solver, tol) if (design == "sdp" or checks) else None
    K = horizon
    As = np.zeros((K, n, n)); Gs = np.zeros((K, n, m)); Lf = np.zeros((K, n, m))
    mse_p, mse_f = np.empty(K), np.empty(K)
    diag = {"max_rel_excess_over_closed_form": 0.0, "max_rel_gap_sdp_vs_recomputed": 0.0,
            "min_eig_bound_minus_recomputed": np.inf, "solve_seconds": 0.0, "solves": 0,
            "statuses": set(), "max_gain_diff_vs_closed_form": 0.0}
    for k in range(K):
        Phi = np.einsum("qj,jab->qab", W, Lam)
        mse_p[k] = blocks.cost(rho, Lam) if k > 0 else float(np.trace(blocks.Gam @ Lam0 @ blocks.Gam.T))
        Asc, Gsc, Lc = step_closed_form(blocks, rho, Phi)
        best_u = blocks.cost(rho, blocks.update(Phi, Lc))
        use_sdp = design == "sdp"
        if use_sdp or k in checks:
            L, Lam_sdp, val, status, dt = sdp.update(Phi)
            _record(diag, blocks, rho, val, status, dt, Lam_sdp, blocks.update(Phi, L), best_u, L - Lc)
            if not use_sdp:
                L = Lc
        else:
            L = Lc
        Lf[k] = L
        mse_f[k] = blocks.cost(rho, blocks.update(Phi, L))
        if k < K - 1:
            best_p = blocks.cost(rho, blocks.propagate(Phi, Asc, Gsc))
            if use_sdp or k in checks:
                a, g, Lam_sdp, val, status, dt = sdp.predict(Phi)
                Lam = blocks.propagate(Phi, a, g)
                _record(diag, blocks, rho, val, status, dt, Lam_sdp, Lam, best_p,
                        np.concatenate([a - Asc, g - Gsc], axis=1))
                if not use_sdp:
                    a, g = Asc, Gsc
                    Lam = blocks.propagate(Phi, a, g)
            else:
                a, g = Asc, Gsc
                Lam = blocks.propagate(Phi, a, g)
            As[k], Gs[k] = a, g
        else:
            As[k], Gs[k] = As[k - 1] if k else As[k], Gs[k - 1] if k else Gs[k]
        if progress is not None:
            progress(1)
    diag["statuses"] = sorted(diag["statuses"])
    diag.update(design=design, solver=solver if sdp is not None else None, tol=tol, eps=eps,
                precedence=precedence, rho=rho.tolist(), sdp_checked_steps=sorted(checks) if design == "closed_form" else "all")
    filt = LinearFilter("lmi", As, Gs, np.eye(n), np.repeat(np.eye(n)[None], K, axis=0), Lf,
                        x0.copy(), np.eye(n), {"design_pred": mse_p, "design_filt": mse_f})
    return LMIDesign(filt, diag)


def _record(diag, blocks, rho, val, status, dt, Lam_sdp, Lam_exact, best, gain_diff):
    exact = blocks.cost(rho, Lam_exact)
    scale = max(abs(best), 1e-12)
    diag["max_rel_excess_over_closed_form"] = max(diag["max_rel_excess_over_closed_form"], (exact - best) / scale)
    diag["max_rel_gap_sdp_vs_recomputed"] = max(diag["max_rel_gap_sdp_vs_recomputed"], abs(val - exact) / scale)
    mins = min(float(np.linalg.eigvalsh(((Ls - Le) + (Ls - Le).T) / 2).min() / max(1.0, np.abs(Le).max()))
               for Ls, Le in zip(Lam_sdp, Lam_exact))
    diag["min_eig_bound_minus_recomputed"] = min(diag["min_eig_bound_minus_recomputed"], mins)
    diag["max_gain_diff_vs_closed_form"] = max(diag["max_gain_diff_vs_closed_form"], float(np.abs(gain_diff).max()))
    diag["solve_seconds"] += dt
    diag["solves"] += 1
    diag["statuses"].add(status)


# =========================================================================== scenario block
_DESIGNS: dict = {}
_DESIGNS_MAX = 16


def _key_part(x):
    if isinstance(x, AugmentedModel):
        return tuple(_key_part(M) for M in (x.A, x.C, x.Q, x.R, x.S))
    if isinstance(x, np.ndarray):
        return (x.shape, np.ascontiguousarray(x, dtype=float).tobytes())
    return x


def _designed(key: tuple, make):
    """A filter's data-independent gains, computed once per process for the same inputs (``key``: the filter and
    every number its design reads): every chunk of a run (and its trajectories) uses the same gains, the LMMSE's
    r = 4d Riccati recursion and the LMI design are a fixed cost per chunk otherwise. Deterministic: a cached
    value equals a recomputed one bit for bit."""
    k = tuple(_key_part(x) for x in key)
    if k not in _DESIGNS:
        if len(_DESIGNS) >= _DESIGNS_MAX:
            _DESIGNS.pop(next(iter(_DESIGNS)))
        _DESIGNS[k] = make()
    return _DESIGNS[k]


def _modes_of(trace) -> np.ndarray:
    """(horizon, runs) 0-based modes: the trace's mode path, or — for a one-stream arrival trace — mode 1
    where the packet arrived and mode 3 (noise only: nothing about x) where it did not."""
    if trace.mode is not None:  # the trace's own integers (int8): every consumer indexes or compares them, the
        mode = np.asarray(trace.mode)  # compiled kernels copy a block of steps to int64 (an int64 copy here: 8 MB a chunk)
        return mode if np.issubdtype(mode.dtype, np.integer) else mode.astype(np.int8)
    if trace.arrival is not None and trace.arrival.shape[0] == 1:
        return np.where(np.asarray(trace.arrival[0], bool), 0, 2).astype(np.int8)
    raise ConfigError.at("channel.kind", "markov_lmi needs a mode trace (channel kind markov_modes) or a one-stream "
                                         "arrival trace (a lost packet is mode 3, noise only)")


class MarkovLMIEstimator(EstimatorModel):
    """``kind: markov_lmi`` — the paper's LMI filter design (Sec. III) and its comparison filters.

    ``rho`` are the mode marginals the design uses (the paper's printed ρ_q; ``stationary`` =
    computed from the channel). ``design: closed_form`` (default) solves each per-step LMI problem
    through its normal equations (the same convex quadratic; the SDP optimum matches it within the
    solver tolerance) and solves the SDP itself at ``sdp_check`` steps as a check; ``design: sdp``
    solves every step's SDP with cvxpy (≈ 10 s for 100 steps).

    Generic metrics (``covariances``): ``filter`` picks the filter whose per-run error covariance is
    reported — the LMI filter or the naive KF (fixed gains: the conditional second moment given the
    mode path, :func:`linear_filter_covariances`) or the mode-aware KF (its own P, on the Kalman core).
    netkf's time base: P0 = P_{0|0} = ``riccati.initial_covariance(system)``, E x_0 = 0, zero
    cross-covariance; step k is the update with y_k in mode θ_k (trace step k − 1). Quantities:
    ``filtered`` P_{k|k} (the error of x̂(k|k)) and ``predicted`` P_{k+1|k} (of x̂(k+1|k)). With only
    mode 1 (or modes 1 and 3) the mode-aware KF is ``kind: kf`` with γ_k = 1{θ_k = 1}, step for step.
    """

    accepts: ClassVar[frozenset[str]] = frozenset({"mode"})
    quantities: ClassVar[tuple[str, ...]] = ("filtered", "predicted")

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
        "auto", description="auto = numba when importable, else numpy (the reference; equal to rounding): the "
                            "fixed-gain filters' per-run covariances, the mode-aware KF (covariances; with states for "
                            "one output) in kernels generated per system, run by run (measured faster)")
    S: Matrix | None = Field(None, description="cross-covariance E[w_k v_kᵀ] (n×m) of process and measurement noise the "
                                               "filters are built for (default 0; Moayedi's Example 1 has v = 0.2 w)")
    filter: Literal["lmi", "mode_aware", "naive", "lmmse"] = Field(
        "lmi", description="filter whose error covariances the generic metrics see: per run given the mode path "
                           "(lmi, naive, mode_aware), or E[e eᵀ] over all mode paths (lmmse: metrics of means only)")

    def per_run_covariance(self) -> bool:
        """The exact LMMSE reports E[e eᵀ] over all mode paths (Costa's construction; the same P in every run),
        not each run's covariance: metrics of means (mean_vs_time, time_average, state_error) may use it, per-run
        ones (Pr[P_k ≤ M]) refuse it."""
        return self.filter != "lmmse"

    def check(self, system, channel) -> None:
        """S of the right shape, 4 design marginals, one packet stream."""
        if self.S is not None:
            if np.asarray(self.S, float).shape != (system.n, system.m):
                raise ConfigError.at("estimator.S", f"must be {system.n}×{system.m} (rows = states, columns = outputs), "
                                                    f"got {np.asarray(self.S, float).shape}")
            try:
                self._model(system)
            except ValueError as e:
                raise ConfigError.at("estimator.S", str(e)) from None
        if self.rho != "stationary":
            if len(self.rho) != N_MODES:
                raise ConfigError.at("estimator.rho", f"needs 4 marginals ρ_1..ρ_4, got {len(self.rho)}")
            if abs(sum(self.rho) - 1) > 1e-9:
                raise ConfigError.at("estimator.rho", f"must sum to 1, got {sum(self.rho):.12g}")
        if channel is not None:
            S = channel_streams(channel)
            if S is not None and S != 1:
                raise ConfigError.at("estimator.kind", f"markov_lmi models one packet per step carrying all of y_k "
                                     f"(its mode says what the packet holds); the channel has {S} arrival streams — "
                                     f"use channel kind markov_modes, or kind: kf for per-sensor arrivals")
            kalman.stream_rows(system, 1, "estimator.kind")

    def conventions(self, system, channel) -> dict[str, str]:
        """The packet model and the start (eq. 35 one step later: what a delayed or held packet holds at k = 1)."""
        return {"packet": "one packet per step carries y_k (mode 1 on time, 2 z_{k-1} delayed, 3 noise only, "
                          "4 y_{k-1} held)",
                "start": "y_0 = v_0 (a delayed/held first packet is noise)"}

    def backend_used(self, system, channel, runs: int, horizon: int, steps=None, quantities=None) -> str:
        """The backend :meth:`covariances` runs on (recorded in the manifest): the exact LMMSE is one closed
        recursion for every run (numpy); the mode-aware filter with correlated noise (S ≠ 0) runs on numpy;
        else :func:`resolve_backend`."""
        model = self._model(system)[0]
        if self.filter == "lmmse" or (self.filter == "mode_aware" and np.any(model.S)):
            return "numpy"
        return resolve_backend(self.backend, model.m)

    def _model(self, system):
        n = np.atleast_2d(np.asarray(system.A, float)).shape[0]
        S = None if self.S is None else np.asarray(self.S, float)
        return AugmentedModel.build(system.A, system.C, system.Q, system.R, S), np.zeros(n), initial_covariance(system)

    def covariances(self, system, trace, steps, quantities=("filtered",)):
        """Yield ``(k, {quantity: P_k})`` (n, n, runs) given the mode path of the trace (netkf's time base)."""
        qs = kalman.check_quantities(quantities, self.quantities, "markov_lmi")
        self.check(system, None)
        modes = _modes_of(trace)
        model, x0, P0 = self._model(system)
        steps = sorted({int(k) for k in steps})
        if not steps:
            return
        if self.filter == "mode_aware":
            yield from self._mode_aware(model, x0, P0, modes, steps, qs)
            return
        if self.filter == "lmmse":
            for k, Ps in self._lmmse(model, x0, P0, trace, steps, qs)[1]:
                yield k, Ps
            return
        filt = self._fixed_gain(model, x0, P0, trace, steps[-1])
        lfc = linear_filter_covariances_compiled if resolve_backend(self.backend, model.m) == "numba" \
            else linear_filter_covariances
        yield from lfc(model, filt, modes, x0, P0, steps, qs, base="contract")

    def _lmmse(self, model, x0, P0, trace, want, qs):
        """Costa's exact LMMSE for the trace's chain and (k, {q: P}) with P = E[e eᵀ] (the same for every run)."""
        T, pi0 = (np.asarray(trace.meta.get(key), float) for key in ("transition", "initial"))
        filt = _designed(("lmmse", model, T, pi0, x0, P0, want[-1] + 1),
                         lambda: lmmse_filter(model, T, pi0, x0, P0, want[-1] + 1, base="contract"))
        cov = {"filtered": filt.predicted["filt_cov"], "predicted": filt.predicted["pred_cov"][1:]}
        runs = trace.runs
        return filt, ((k, {q: np.repeat(cov[q][k - 1][:, :, None], runs, axis=2) for q in qs}) for k in want)

    def estimates(self, system, trace, y, steps, quantities=("filtered",)):
        """Yield (k, {quantity: (x̂ (n, runs), P (n, n, runs))}): the estimate of ``filter`` beside the P of
        :meth:`covariances` (numpy path; x̂ from the same gains). ``y`` (m, horizon+1, runs) is what the
        receiver sees (:func:`netkf_cli.engine.state.received`: the mode's packet). Every P here is the filter's
        error covariance given the mode path (the naive KF's own Riccati P, which assumes mode 1, is not
        reported), so a NEES check passes for every ``filter``."""
        qs = kalman.check_quantities(quantities, self.quantities, "markov_lmi")
        self.check(system, None)
        modes = _modes_of(trace)
        model, x0, P0 = self._model(system)
        want = sorted({int(k) for k in steps})
        if not want:
            return
        n = model.n
        compiled = resolve_backend(self.backend, model.m) == "numba"
        if self.filter == "mode_aware" and compiled and _markov_codegen.mode_aware_supported(model.d, model.m):
            res = mode_aware_estimates_compiled(model, modes, y, x0, P0, want, base="contract")
            for k in want:
                xf, Pf, xp, Pp = res[k]
                yield k, {q: (xf, Pf) if q == "filtered" else (xp, Pp) for q in qs}
            return
        if self.filter == "mode_aware":
            kf = ModeAwareKFTr(model, modes.shape[1], x0, P0, states=True, base="contract")
            wset = set(want)
            for t in range(want[-1]):
                xf, _, Pfx = kf.step(y[:, t + 1], modes[t], want_cov=(t + 1) in wset)
                if t + 1 in wset:  # predicted: the x block of P(k+1|k) (= A P_{k|k} Aᵀ + Q when S = 0)
                    yield t + 1, {q: (xf, Pfx) if q == "filtered" else (kf.xi[:n].copy(), kf.P[:n, :n].copy())
                                  for q in qs}
            return
        if self.filter == "lmmse":  # Costa's exact LMMSE: the chain from the trace, P = E[e eᵀ] (the same for every run)
            filt, covs = self._lmmse(model, x0, P0, trace, want, qs)
        else:
            filt = self._fixed_gain(model, x0, P0, trace, want[-1])
            lfc = linear_filter_covariances_compiled if compiled else linear_filter_covariances
            covs = lfc(model, filt, modes, x0, P0, want, qs, base="contract")
        s = np.repeat(filt.s0[:, None], modes.shape[1], axis=1)
        t = 0
        for k, Ps in covs:
            while t < k:  # trace step t carries z_{t+1}: x̂(t+1|t+1) = E_f s + L_f z, s ← A_s s + G_s z
                z = y[:, t + 1]
                if t + 1 == k:  # x̂(k|k) only at the reported steps (the same matmuls, not at the others)
                    xf = filt.Ef[t] @ s + filt.Lf[t] @ z
                s = filt.As[t] @ s + filt.Gs[t] @ z
                t += 1
            yield k, {q: (xf if q == "filtered" else filt.Ep @ s, P) for q, P in Ps.items()}

    def _fixed_gain(self, model, x0, P0, trace, K: int):
        """The naive KF or the LMI filter (data-independent gains) for K steps on netkf's time base."""
        if self.filter == "naive":
            prior_x = model.prior_moments(x0, P0, "contract")[1][: model.n, : model.n]
            return _designed(("naive", model, x0, prior_x, K), lambda: naive_filter(model, x0, prior_x, K))
        if self.rho == "stationary":
            rho = np.asarray(trace.meta.get("rho"), float) if trace.meta.get("rho") is not None else None
            if rho is None:
                raise ConfigError.at("estimator.rho", "the trace carries no mode marginals; give rho explicitly")
        else:
            rho = np.asarray(self.rho, float)
        try:
            filt = _designed(("lmi", model, rho, x0, P0, K, self.design, self.solver, self.solver_tol, self.eps,
                              self.precedence),
                             lambda: lmi_design(model, rho, x0, P0, K, design=self.design, solver=self.solver,
                                                tol=self.solver_tol, eps=self.eps, precedence=self.precedence,
                                                sdp_check=0, base="contract").filter)
        except RuntimeError as e:
            raise ConfigError.at("estimator", f"{e}; try `solver: SCS`, a larger `eps` or `design: closed_form`") from None
        return filt

    def _mode_aware(self, model, x0, P0, modes, steps, qs):
        runs = modes.shape[1]
        A, Q = np.asarray(model.A, float), np.asarray(model.Q, float)
        if np.any(model.S):  # correlated noise: P(k+1|k) is the decorrelated time update's x block, numpy path
            kf = ModeAwareKFTr(model, runs, x0, P0, states=False, base="contract")
            want = set(steps)
            for t in range(steps[-1]):
                _, _, Pfx = kf.step(None, modes[t], want_cov=(t + 1) in want)
                if t + 1 in want:
                    yield t + 1, {q: Pfx if q == "filtered" else kf.P[:model.n, :model.n].copy() for q in qs}
            return
        if resolve_backend(self.backend, model.m) == "numba":
            kf = ModeAwareCompiled(model, runs, x0, P0, states=False, base="contract")
            t = 0
            for k in steps:
                Pfx, _ = kf.advance(modes, t, k)
                t = k
                yield k, kalman.report(Pfx, qs, A, Q)
            return
        kf = ModeAwareKFTr(model, runs, x0, P0, states=False, base="contract")
        want = set(steps)
        for t in range(steps[-1]):
            _, _, Pfx = kf.step(None, modes[t], want_cov=(t + 1) in want)
            if t + 1 in want:
                yield t + 1, kalman.report(Pfx, qs, A, Q)
