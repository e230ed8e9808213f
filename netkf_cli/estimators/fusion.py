"""MF, IBF and OLPEF estimators at a fusion centre fed by N lossy links (Chiuso & Schenato, Sec. II).

All three error covariances depend on the arrival trace γ (runs, T, N) only, so everything here
is covariance-only and batched over runs (loop over time, runs vectorized).

Time convention: measurements y_t^i at t = 0, 1, …, T−1; the prior of x_0 has covariance
P_{0|−1} = P0 (``None`` → P_m, the steady state with all N sensors). Identical sensors:
``C`` and ``R`` are ONE sensor's output matrix and noise covariance (the paper's C_i, R_ii).

* MF (eqs (6)–(9)): P_{t|t} = Φ_f(P_{t|t−1}, ℓ_t), ℓ_t = Σ_i γ_t^i. With identical sensors the
  pseudo-inverse update of eq. (7) with the received rows equals fusing their average, whose
  noise is R/ℓ_t — eq. (14); ℓ_t = 0 leaves P unchanged.
* IBF (Sec. II-B): sensor i has delivered y^i_{0..t−τ_i}, so at time s the centre holds the
  measurements of ℓ_s^{(t)} = #{i : τ_i ≤ t − s} sensors, a count that grows going back in
  time. P^IBF_{t|t} is the Riccati recursion with those counts from s = t − K (K = max_i τ_i,
  before which every sensor contributes and the full-information recursion applies) to t.
  Cost O(K) per evaluation time, vectorized over runs and evaluation times.
* OLPEF (eqs (10)–(11)): the steady-state centralized gain L = [L^1 … L^N] is split into partial
  estimates z^i; the centre sums A^{τ_i} z^i_{t−τ_i}. Its error is not a Riccati recursion, but given
  the τ's it is a fixed linear combination of the jointly Gaussian, stationary process
  (x_t, z^1_t, …, z^N_t); we precompute the lagged covariances of (x, z^a, z^b) once (a Lyapunov
  equation, exchangeable sensors) and evaluate the exact error covariance per run as a quadratic
  form in the histogram of τ. Assumption (documented): the sensors' partial-estimate filters run in
  steady state since −∞ (we evaluate after burn-in only).
"""

from __future__ import annotations

from typing import ClassVar, Literal

import numpy as np
import scipy.linalg
from pydantic import Field

from netkf_cli import batched as bt
from netkf_cli.analysis.fusion_bounds import _as2d, p_m, phi_f
from netkf_cli.channels.multi import times_since_arrival, times_since_arrival_tr
from netkf_cli.errors import ConfigError
from netkf_cli.spec import EstimatorModel

Strategy = Literal["mf", "ibf", "olpef"]
STRATEGIES: tuple[str, ...] = ("mf", "ibf", "olpef")


class FusionEstimator(EstimatorModel):
    """``kind: fusion`` — fusion-centre strategies of Chiuso & Schenato (MF, IBF, OLPEF).

    Works from ``arrival`` traces of S sensors (``channel.kind: multi``); ``system.C``/``system.R``
    are ONE sensor's (identical sensors). ``covariances`` reports P_{t|t} (fusion time t = k − 1:
    trace step t carries the measurements of time t) of ``strategies[0]`` for any state dimension.
    """

    accepts: ClassVar[frozenset[str]] = frozenset({"arrival"})
    quantity: ClassVar[str] = "P_{t|t}"

    kind: Literal["fusion"]
    strategies: list[Strategy] = Field(default_factory=lambda: list(STRATEGIES), min_length=1,
                                       description="strategies to simulate: mf (measurement fusion, eqs 6–9), ibf "
                                                   "(infinite bandwidth), olpef (open-loop partial estimates, eqs 10–11); "
                                                   "the first one is what covariances() reports")
    eval_block: int = Field(8, gt=0, description="IBF/OLPEF: evaluation times processed together (memory knob)")

    def check(self, system, channel) -> None:
        """Refuse what cannot work: OLPEF's stationary tables need a stable A (eq. (11))."""
        if "olpef" in self.strategies:
            A = _as2d(system.A)
            rho = float(np.max(np.abs(np.linalg.eigvals(A))))
            if rho >= 1.0:
                raise ConfigError.at("estimator.strategies",
                                     f"olpef needs a stable A (its partial-estimate filters run in steady state); "
                                     f"spectral radius of system.A is {rho:.4g} ≥ 1 — use mf or ibf")

    def covariances(self, system, trace, steps):
        """Yield ``(k, P_{k−1|k−1})`` shaped (n, n, runs) of ``strategies[0]`` from ``trace.arrival``.

        Trace step t carries the N packets of fusion time t, so k = t + 1 ↔ P_{t|t}. Prior
        P_{0|−1} = system.P0, or P_m (steady state with all N sensors) when P0 is not given.
        """
        if trace.arrival is None:
            raise ConfigError.at("channel.kind", "fusion needs an arrival trace (channel kind multi)")
        A, C, Q, R = (_as2d(M) for M in (system.A, system.C, system.Q, system.R))
        N = trace.arrival.shape[0]
        P0 = initial_prior(A, C, Q, R, N, getattr(system, "P0", None))
        strat = self.strategies[0]
        steps = [int(k) for k in steps]
        want = set(steps)
        if strat == "mf":
            counts = trace.arrival.sum(axis=0, dtype=np.int64).astype(float)
            for t, Pf, _ in mf_cov_iter(counts, A, C, Q, R, P0):
                if t + 1 in want:
                    yield t + 1, Pf
                if t + 1 >= steps[-1]:
                    return
            return
        tau = times_since_arrival_tr(trace.arrival)  # (T, runs, N)
        runs = trace.runs
        if strat == "ibf":
            Pfull = full_information_priors(A, C, Q, R, N, P0, trace.horizon)
        else:
            tables = OLPEFTables(A, C, Q, R, N)
        for k in steps:
            t = k - 1
            rows_t = np.full(runs, t)
            if strat == "ibf":
                Pf, _ = ibf_covariances_at(tau[t], rows_t, A, C, Q, R, Pfull, full=True)
            else:
                Pf = tables.error_cov(tau[t], rows_t)
            yield k, np.ascontiguousarray(np.moveaxis(Pf, 0, -1))


def _trace(P: np.ndarray) -> np.ndarray:
    return np.trace(P, axis1=-2, axis2=-1)


def initial_prior(A, C, Q, R, N: int, P0) -> np.ndarray:
    """P_{0|−1}: P0 if given, else P_m (steady state with N sensors)."""
    return p_m(A, C, Q, R, N) if P0 is None else _as2d(P0)


# ----------------------------------------------------------------------------------------
# MF
# ----------------------------------------------------------------------------------------


def mf_covariances(counts: np.ndarray, A, C, Q, R, P0) -> tuple[np.ndarray, np.ndarray]:
    """MF error covariances, eqs (7)–(9), for ℓ_t = ``counts`` of shape (runs, T).

    Returns (trace P_{t|t}, trace P_{t+1|t}), each (runs, T). Overflow → inf, never NaN.
    """
    A, C, Q, R, P0 = map(_as2d, (A, C, Q, R, P0))
    runs, T = counts.shape
    n = A.shape[0]
    Pf_tr = np.empty((runs, T))
    Pp_tr = np.empty((runs, T))
    if n == 1 and C.shape[0] == 1:
        a2, c2, q, r = A[0, 0] ** 2, C[0, 0] ** 2, Q[0, 0], R[0, 0]
        p = np.full(runs, P0[0, 0])
        with np.errstate(over="ignore", invalid="ignore"):
            for t in range(T):
                pf = p * r / (counts[:, t] * c2 * p + r)
                pf = np.where(np.isinf(p), np.where(counts[:, t] > 0, r / np.maximum(counts[:, t] * c2, 1e-300), np.inf), pf)
                Pf_tr[:, t] = pf
                p = a2 * pf + q
                Pp_tr[:, t] = p
        return Pf_tr, Pp_tr
    P = np.broadcast_to(P0, (runs, n, n)).copy()
    for t in range(T):
        Pf = phi_f(P, counts[:, t], C, R)
        Pf_tr[:, t] = _trace(Pf)
        P = A @ Pf @ A.T + Q
        P = (P + np.swapaxes(P, -1, -2)) / 2
        Pp_tr[:, t] = _trace(P)
    return Pf_tr, Pp_tr


def _phi_f_tr(P: np.ndarray, ell: np.ndarray, C: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Φ_f(P, ℓ) = P − ℓ P Cᵀ (ℓ C P Cᵀ + R)⁻¹ C P, eq. (14), in the (n, n, runs) layout (ℓ per run).

    Closed-form small solves through :mod:`netkf_cli.batched` (m ≤ 2); ℓ = 0 leaves P unchanged.
    """
    PCt = bt.right(P, C.T)  # (n, m, runs)
    S = bt.left(C, PCt) * ell[None, None, :] + R[:, :, None]
    with np.errstate(invalid="ignore", over="ignore"):
        corr = bt.matmul(PCt, bt.solve_small(S, PCt.swapaxes(0, 1))) * ell[None, None, :]
        return bt.sym(P - corr)


def mf_cov_iter(counts: np.ndarray, A, C, Q, R, P0):
    """MF covariances, eqs (7)–(9): yield ``(t, P_{t|t}, P_{t+1|t})`` each (n, n, runs), t = 0..T−1.

    ``counts`` (T, runs) = ℓ_t (received packets at time t), run axis innermost.
    """
    A, C, Q, R, P0 = map(_as2d, (A, C, Q, R, P0))
    T, runs = counts.shape
    P = np.repeat(P0[:, :, None], runs, axis=2)
    for t in range(T):
        Pf = _phi_f_tr(P, counts[t], C, R)
        with np.errstate(invalid="ignore", over="ignore"):
            P = bt.riccati_h(Pf, A, Q)
        yield t, Pf, P


def mf_traces_tr(counts: np.ndarray, A, C, Q, R, P0) -> tuple[np.ndarray, np.ndarray]:
    """(tr P_{t|t}, tr P_{t+1|t}), each (T, runs), for ℓ_t = ``counts`` (T, runs). Any n; scalar fast path."""
    A, C, Q, R, P0 = map(_as2d, (A, C, Q, R, P0))
    T, runs = counts.shape
    Pf_tr = np.empty((T, runs))
    Pp_tr = np.empty((T, runs))
    if A.shape[0] == 1 and C.shape[0] == 1:
        a2, c2, q, r = A[0, 0] ** 2, C[0, 0] ** 2, Q[0, 0], R[0, 0]
        p = np.full(runs, P0[0, 0])
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            for t in range(T):
                lc = counts[t] * c2
                pf = p * r / (lc * p + r)
                if not np.all(np.isfinite(p)):
                    pf = np.where(np.isinf(p), np.where(lc > 0, r / np.where(lc > 0, lc, 1.0), np.inf), pf)
                Pf_tr[t] = pf
                p = a2 * pf + q
                Pp_tr[t] = p
        return Pf_tr, Pp_tr
    for t, Pf, Pp in mf_cov_iter(counts, A, C, Q, R, P0):
        Pf_tr[t] = bt.trace(Pf)
        Pp_tr[t] = bt.trace(Pp)
    return Pf_tr, Pp_tr


def full_information_priors(A, C, Q, R, N: int, P0, T: int) -> np.ndarray:
    """P_{s|s−1} for s = 0..T with all N sensors at every step, shape (T+1, n, n)."""
    A, Q = _as2d(A), _as2d(Q)
    out = np.empty((T + 1,) + A.shape)
    P = _as2d(P0)
    out[0] = P
    for s in range(T):
        P = A @ phi_f(P, np.float64(N), C, R) @ A.T + Q
        P = (P + P.T) / 2
        out[s + 1] = P
    return out


# ----------------------------------------------------------------------------------------
# IBF
# ----------------------------------------------------------------------------------------


def ell_profiles(tau: np.ndarray, K: int) -> np.ndarray:
    """ℓ^{(t)}_{t−k} = #{i : τ_i ≤ k} for k = 0..K, from τ of shape (rows, N) → (rows, K+1), int."""
    rows, N = tau.shape
    tc = np.minimum(tau, K + 1).astype(np.int64)
    flat = (np.arange(rows, dtype=np.int64)[:, None] * (K + 2) + tc).ravel()
    hist = np.bincount(flat, minlength=rows * (K + 2)).reshape(rows, K + 2)
    return np.cumsum(hist[:, : K + 1], axis=1)


def ibf_covariances_at(tau: np.ndarray, t: np.ndarray, A, C, Q, R, Pfull: np.ndarray,
                       full: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """IBF error covariance at evaluation times (see :func:`_ibf_core`), rows grouped by how far back
    their recursion must start (most rows need a few steps, the largest reach in a block ~3× more), so
    the work is ~Σ_rows reach instead of rows × max reach. Same numbers as one call (row-wise recursion)."""
    rows = tau.shape[0]
    reach = np.minimum(tau.max(axis=1), t) if rows else np.zeros(0, dtype=np.int64)
    if rows < 2048:
        return _ibf_core(tau, t, A, C, Q, R, Pfull, full)
    edges = [-1, 4, 8, 16, int(reach.max())]
    outs = None
    for lo, hi in zip(edges[:-1], edges[1:]):
        if hi <= lo:
            continue
        sel = np.flatnonzero((reach > lo) & (reach <= hi))
        if sel.size == 0:
            continue
        f, p = _ibf_core(tau[sel], t[sel], A, C, Q, R, Pfull, full)
        if outs is None:
            outs = (np.empty((rows,) + f.shape[1:]), np.empty((rows,) + p.shape[1:]))
        outs[0][sel], outs[1][sel] = f, p
    return outs


def _ibf_core(tau: np.ndarray, t: np.ndarray, A, C, Q, R, Pfull: np.ndarray,
              full: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """IBF error covariance at evaluation times.

    ``tau`` (rows, N): times since each sensor's last arrival at time ``t`` (rows,) (τ = t+1: nothing
    received yet). ``Pfull`` (T+1, n, n): full-information priors P_{s|s−1}. Returns
    (trace P^IBF_{t|t}, trace P^IBF_{t+1|t}), each (rows,); with ``full=True`` the matrices, each (rows, n, n).
    """
    A, C, Q, R = map(_as2d, (A, C, Q, R))
    rows = tau.shape[0]
    n = A.shape[0]
    reach = np.minimum(tau.max(axis=1), t)  # how far back the recursion must start for this row
    K = int(reach.max()) if rows else 0
    ell = ell_profiles(tau, K)  # (rows, K+1)
    start = np.maximum(t - K, 0)
    P = Pfull[start].copy()  # (rows, n, n)
    scalar = n == 1 and C.shape[0] == 1
    if scalar:
        a2, c2, q, r = A[0, 0] ** 2, C[0, 0] ** 2, Q[0, 0], R[0, 0]
        p = P[:, 0, 0]
        for k in range(K, -1, -1):
            active = (t - k) >= 0
            pf = p * r / (ell[:, k] * c2 * p + r)
            if k == 0:
                if full:
                    return pf[:, None, None], (a2 * pf + q)[:, None, None]
                return pf, a2 * pf + q
            p = np.where(active, a2 * pf + q, p)
    # vector states: the (n, n, rows) layout, closed-form small solves (netkf_cli.batched)
    Pt = np.ascontiguousarray(np.moveaxis(P, 0, -1))
    for k in range(K, -1, -1):
        active = (t - k) >= 0
        Pf = _phi_f_tr(Pt, ell[:, k].astype(float), C, R)
        with np.errstate(invalid="ignore", over="ignore"):
            Pn = bt.riccati_h(Pf, A, Q)
        if k == 0:
            if full:
                return np.moveaxis(Pf, -1, 0), np.moveaxis(Pn, -1, 0)
            return bt.trace(Pf), bt.trace(Pn)
        Pt = np.where(active[None, None, :], Pn, Pt)
    raise AssertionError("unreachable")


# ----------------------------------------------------------------------------------------
# OLPEF
# ----------------------------------------------------------------------------------------


class OLPEFTables:
    """Lagged covariances of the stationary (x_t, z^a_t, z^b_t) for N identical sensors (eqs (10)–(11)).

    Steady-state CKF: P_m (prediction), per-sensor gain L^i = P_m Cᵀ (R + N C P_m Cᵀ)⁻¹ (the i-th
    block of P_m C̄ᵀ (C̄ P_m C̄ᵀ + I⊗R)⁻¹), F = (I − N L^1 C) A. Partial estimates
    z^i_{t+1} = F z^i_t + L^i (C A x_t + C w_t + v^i_{t+1}). The joint (x, z^a, z^b) is linear with
    transition 𝒜 and stationary covariance Σ (Lyapunov); Cov(X_{s+d}, X_s) = 𝒜^d Σ.
    """

    def __init__(self, A, C, Q, R, N: int):
        A, C, Q, R = map(_as2d, (A, C, Q, R))
        rho = float(np.max(np.abs(np.linalg.eigvals(A))))
        if rho >= 1.0:
            raise ConfigError.at("system.A", f"OLPEF's stationary analysis needs a stable A; spectral radius {rho:.4g} ≥ 1")
        n = A.shape[0]
        self.A, self.n, self.N = A, n, N
        Pm = p_m(A, C, Q, R, N)
        L1 = np.linalg.solve(R + N * C @ Pm @ C.T, C @ Pm).T  # (n, m)
        F = (np.eye(n) - N * L1 @ C) @ A
        Z = np.zeros((n, n))
        LCA = L1 @ C @ A
        self.calA = np.block([[A, Z, Z], [LCA, F, Z], [LCA, Z, F]])
        G = np.vstack([np.eye(n), L1 @ C, L1 @ C])
        W = G @ Q @ G.T
        W[n : 2 * n, n : 2 * n] += L1 @ R @ L1.T
        W[2 * n :, 2 * n :] += L1 @ R @ L1.T
        self.Sigma = scipy.linalg.solve_discrete_lyapunov(self.calA, W)
        self.Sigma = (self.Sigma + self.Sigma.T) / 2
        self.Pm, self.L1, self.F = Pm, L1, F
        self._K = -1
        self._extend(16)

    def _extend(self, K: int) -> None:
        """Tables for lags 0..K: tr(Cov(x_t, A^a z_{t−a})), tr(A^a (C_same(0) − C_cross(0)) A^aᵀ), T_ab."""
        if K <= self._K:
            return
        n = self.n
        x, za, zb = slice(0, n), slice(n, 2 * n), slice(2 * n, 3 * n)
        Apow = np.empty((K + 1, n, n))
        G = np.empty((K + 1, 3 * n, 3 * n))  # 𝒜^d Σ
        Apow[0], G[0] = np.eye(n), self.Sigma
        for d in range(1, K + 1):
            Apow[d] = self.A @ Apow[d - 1]
            G[d] = self.calA @ G[d - 1]
        Cxz = G[:, x, za]  # Cov(x_{s+d}, z_s)
        Ccross = G[:, za, zb]  # Cov(z^a_{s+d}, z^b_s)
        self.sxx = float(np.trace(self.Sigma[x, x]))
        # linear term: tr(Cov(x_t, A^a z_{t−a})) = tr(Cxz(a) A^aᵀ)
        self.lin = np.einsum("dij,dij->d", Cxz, Apow)
        diag0 = self.Sigma[za, za] - self.Sigma[za, zb]
        self.diag = np.einsum("dij,jk,dik->d", Apow, diag0, Apow)
        # T_ab = tr(A^a Cov(z^i_{t−a}, z^j_{t−b}) A^bᵀ); Cov = Ccross(a−b)ᵀ (a ≥ b) or Ccross(b−a) (a < b)
        a = np.arange(K + 1)
        dmat = np.abs(a[:, None] - a[None, :])
        Cab = np.where((a[:, None] >= a[None, :])[..., None, None], np.swapaxes(Ccross[dmat], -1, -2), Ccross[dmat])
        self.T = np.einsum("aij,abjk,bik->ab", Apow, Cab, Apow)
        # the same tables as matrices (for the full error covariance, any n)
        self.sxxM = self.Sigma[x, x]
        self.linM = np.einsum("dij,dkj->dik", Cxz, Apow)  # Cov(x_t, A^a z_{t−a}) = Cxz(a) A^aᵀ
        self.diagM = np.einsum("dij,jk,dlk->dil", Apow, diag0, Apow)
        self.TM = np.einsum("aij,abjk,blk->abil", Apow, Cab, Apow)
        self._K = K

    def error_trace(self, tau: np.ndarray, t: np.ndarray) -> np.ndarray:
        """tr Var(x_t − Σ_i A^{τ_i} z^i_{t−τ_i}) per row, eq. (11); sensors with nothing received yet
        (τ_i = t+1) contribute the estimate 0."""
        received = tau <= t[:, None]
        K = int(np.where(received, tau, 0).max()) if tau.size else 0
        self._extend(K)
        rows = tau.shape[0]
        tc = np.where(received, tau, K + 1).astype(np.int64)
        flat = (np.arange(rows, dtype=np.int64)[:, None] * (K + 2) + tc).ravel()
        h = np.bincount(flat, minlength=rows * (K + 2)).reshape(rows, K + 2)[:, : K + 1].astype(float)
        T = self.T[: K + 1, : K + 1]
        quad = ((h @ T) * h).sum(axis=1)
        return self.sxx - 2 * h @ self.lin[: K + 1] + h @ self.diag[: K + 1] + quad


    def error_cov(self, tau: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Var(x_t − Σ_i A^{τ_i} z^i_{t−τ_i}) per row as a matrix, (rows, n, n), eq. (11) — the
        matrix form of :meth:`error_trace` (same histogram h of τ)."""
        received = tau <= t[:, None]
        K = int(np.where(received, tau, 0).max()) if tau.size else 0
        self._extend(K)
        rows = tau.shape[0]
        tc = np.where(received, tau, K + 1).astype(np.int64)
        flat = (np.arange(rows, dtype=np.int64)[:, None] * (K + 2) + tc).ravel()
        h = np.bincount(flat, minlength=rows * (K + 2)).reshape(rows, K + 2)[:, : K + 1].astype(float)
        lin = np.einsum("ra,aij->rij", h, self.linM[: K + 1])
        out = self.sxxM[None] - lin - np.swapaxes(lin, 1, 2) + np.einsum("ra,aij->rij", h, self.diagM[: K + 1])
        out += np.einsum("ra,rb,abij->rij", h, h, self.TM[: K + 1, : K + 1], optimize=True)
        return (out + np.swapaxes(out, 1, 2)) / 2


# ----------------------------------------------------------------------------------------
# One chunk of runs → per-run time averages
# ----------------------------------------------------------------------------------------


def fusion_run_averages(
    gamma: np.ndarray,
    A,
    C,
    Q,
    R,
    P0,
    burn_in: int,
    strategies=STRATEGIES,
    eval_block: int = 8,
    olpef_tables: OLPEFTables | None = None,
) -> dict[str, np.ndarray]:
    """Per-run averages over t ∈ [burn_in, T) of each strategy's error variance (trace), each (runs,).

    Keys: ``mf_f`` (tr P_{t|t}), ``mf_p`` (tr P_{t+1|t}), ``ibf_f``, ``ibf_p``, ``olpef_f``.
    """
    runs, T, N = gamma.shape
    if not 0 <= burn_in < T:
        raise ConfigError.at("montecarlo.burn_in", f"must be in [0, horizon) = [0, {T}), got {burn_in}")
    P0 = initial_prior(A, C, Q, R, N, P0)
    out: dict[str, np.ndarray] = {}
    if "mf" in strategies:
        counts = gamma.sum(axis=2, dtype=np.int64).astype(float)
        Pf, Pp = mf_covariances(counts, A, C, Q, R, P0)
        out["mf_f"] = Pf[:, burn_in:].mean(axis=1)
        out["mf_p"] = Pp[:, burn_in:].mean(axis=1)
    need_tau = "ibf" in strategies or "olpef" in strategies
    if not need_tau:
        return out
    tau = times_since_arrival(gamma)
    times = np.arange(burn_in, T)
    acc = {k: np.zeros(runs) for k in (["ibf_f", "ibf_p"] if "ibf" in strategies else []) + (["olpef_f"] if "olpef" in strategies else [])}
    Pfull = full_information_priors(A, C, Q, R, N, P0, T) if "ibf" in strategies else None
    if "olpef" in strategies and olpef_tables is None:
        olpef_tables = OLPEFTables(A, C, Q, R, N)
    for b0 in range(0, times.size, eval_block):
        tb = times[b0 : b0 + eval_block]
        E = tb.size
        tau_b = np.transpose(tau[:, tb, :], (1, 0, 2)).reshape(E * runs, N)  # rows = (time, run)
        t_rows = np.repeat(tb, runs)
        if "ibf" in strategies:
            f, p = ibf_covariances_at(tau_b, t_rows, A, C, Q, R, Pfull)
            acc["ibf_f"] += f.reshape(E, runs).sum(axis=0)
            acc["ibf_p"] += p.reshape(E, runs).sum(axis=0)
        if "olpef" in strategies:
            acc["olpef_f"] += olpef_tables.error_trace(tau_b, t_rows).reshape(E, runs).sum(axis=0)
    for k, v in acc.items():
        out[k] = v / times.size
    return out


def fusion_keys(strategies) -> tuple[str, ...]:
    """The statistics a fusion Monte Carlo reports, in a fixed order (known before any chunk runs)."""
    keys: list[str] = []
    if "mf" in strategies:
        keys += ["mf_f", "mf_p"]
    if "ibf" in strategies:
        keys += ["ibf_f", "ibf_p"]
    if "olpef" in strategies:
        keys += ["olpef_f"]
    return tuple(keys)


def fusion_averages_tr(
    arrival: np.ndarray,
    A,
    C,
    Q,
    R,
    P0,
    burn_in: int,
    strategies=STRATEGIES,
    eval_block: int = 8,
    olpef_tables: OLPEFTables | None = None,
) -> dict[str, np.ndarray]:
    """:func:`fusion_run_averages` on a trace-layout arrival array ``(N, T, runs)`` (run axis innermost).

    Per-run averages over t ∈ [burn_in, T) of tr P_{t|t} (``*_f``) and tr P_{t+1|t} (``*_p``), keys
    :func:`fusion_keys`; any state dimension.
    """
    N, T, runs = arrival.shape
    if not 0 <= burn_in < T:
        raise ConfigError.at("montecarlo.burn_in", f"must be in [0, horizon) = [0, {T}), got {burn_in}")
    P0 = initial_prior(A, C, Q, R, N, P0)
    out: dict[str, np.ndarray] = {}
    if "mf" in strategies:
        counts = arrival.sum(axis=0, dtype=np.int64).astype(float)  # (T, runs)
        Pf, Pp = mf_traces_tr(counts, A, C, Q, R, P0)
        out["mf_f"] = Pf[burn_in:].mean(axis=0)
        out["mf_p"] = Pp[burn_in:].mean(axis=0)
    if "ibf" not in strategies and "olpef" not in strategies:
        return out
    tau = times_since_arrival_tr(arrival)  # (T, runs, N)
    times = np.arange(burn_in, T)
    acc = {k: np.zeros(runs) for k in fusion_keys(strategies) if not k.startswith("mf")}
    Pfull = full_information_priors(A, C, Q, R, N, P0, T) if "ibf" in strategies else None
    if "olpef" in strategies and olpef_tables is None:
        olpef_tables = OLPEFTables(A, C, Q, R, N)
    for b0 in range(0, times.size, eval_block):
        tb = times[b0 : b0 + eval_block]
        E = tb.size
        tau_b = tau[tb].reshape(E * runs, N)  # rows = (time, run), contiguous
        t_rows = np.repeat(tb, runs)
        if "ibf" in strategies:
            f, p = ibf_covariances_at(tau_b, t_rows, A, C, Q, R, Pfull)
            acc["ibf_f"] += f.reshape(E, runs).sum(axis=0)
            acc["ibf_p"] += p.reshape(E, runs).sum(axis=0)
        if "olpef" in strategies:
            acc["olpef_f"] += olpef_tables.error_trace(tau_b, t_rows).reshape(E, runs).sum(axis=0)
    for k, v in acc.items():
        out[k] = v / times.size
    return out


class FusionKernel:
    """Monte Carlo kernel of the fusion strategies (module-level, picklable; issue 12.5).

    ``kernel(rng, runs)`` samples ``channel.sample_trace`` and returns additive statistics with
    fixed keys, over d = x − ``shift`` for the per-run time averages x of :func:`fusion_keys`
    (order ``self.keys``): ``sum`` (K,), ``cross`` (K, K) (sums of products, for paired ratios),
    ``sum3``, ``sum4`` (K,) (for the heavy-tail diagnostic) and ``nonfinite`` (K,). The mean is
    ``shift + sum / runs``.
    """

    def __init__(self, A, C, Q, R, P0, channel, strategies, horizon: int, burn_in: int, eval_block: int = 8):
        self.A, self.C, self.Q, self.R = (_as2d(M) for M in (A, C, Q, R))
        self.P0 = None if P0 is None else _as2d(P0)
        self.channel = channel
        self.strategies = tuple(s for s in STRATEGIES if s in strategies)
        self.horizon, self.burn_in, self.eval_block = int(horizon), int(burn_in), int(eval_block)
        if not 0 <= self.burn_in < self.horizon:
            raise ConfigError.at("montecarlo.burn_in", f"must be < horizon = {horizon}, got {burn_in}")
        self.keys = fusion_keys(self.strategies)
        self.tables = OLPEFTables(self.A, self.C, self.Q, self.R, channel.sensors) if "olpef" in self.strategies else None
        # Moments are accumulated about a fixed shift c (a pilot mean from a private, fixed stream that
        # never touches the Monte Carlo streams): per-run averages can vary by 1e-5 relative, and raw
        # sums of x², x⁴ would cancel catastrophically in the variance and the kurtosis.
        pilot = self._averages(np.random.default_rng(np.random.SeedSequence(0, spawn_key=(2**31 - 1,))), 64)
        self.shift = np.where(np.isfinite(pilot).all(axis=1), pilot.mean(axis=1), 0.0)

    def _averages(self, rng: np.random.Generator, runs: int) -> np.ndarray:
        tr = self.channel.sample_trace(rng, runs, self.horizon)
        avg = fusion_averages_tr(tr.arrival, self.A, self.C, self.Q, self.R, self.P0, self.burn_in,
                                 self.strategies, self.eval_block, self.tables)
        return np.stack([avg[k] for k in self.keys])  # (K, runs)

    def __call__(self, rng: np.random.Generator, runs: int) -> dict[str, np.ndarray]:
        X = self._averages(rng, runs) - self.shift[:, None]
        bad = ~np.isfinite(X)
        Xf = np.where(bad, 0.0, X)
        X2 = Xf * Xf
        return {"sum": Xf.sum(axis=1), "cross": Xf @ Xf.T, "sum3": (X2 * Xf).sum(axis=1), "sum4": (X2 * X2).sum(axis=1),
                "nonfinite": bad.sum(axis=1)}


def heavy_tail_flag(s1, s2, s3, s4, n: int, rel: float = 0.25) -> np.ndarray:
    """True where a sample mean's standard error is itself unreliable (heavy tail).

    From raw sums of x, x², x³, x⁴ over n samples: the relative standard error of the sample
    variance is ≈ √((κ − 1)/n) with κ = m₄/σ⁴ (m₄ the fourth central moment). Flag when it exceeds
    ``rel`` (then "±5 s.e." means little). A run-level primitive that belongs in montecarlo.py.
    """
    s1, s2, s3, s4 = (np.asarray(v, float) for v in (s1, s2, s3, s4))
    mu = s1 / n
    e2, e3, e4 = s2 / n, s3 / n, s4 / n
    var = np.maximum(e2 - mu**2, 0.0)
    m4 = np.maximum(e4 - 4 * mu * e3 + 6 * mu**2 * e2 - 3 * mu**4, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        kappa = np.where(var > 1e-14 * np.maximum(mu**2, 1e-300), m4 / np.maximum(var, 1e-300) ** 2, 1.0)
    return np.sqrt(np.maximum(kappa - 1.0, 0.0) / n) > rel
