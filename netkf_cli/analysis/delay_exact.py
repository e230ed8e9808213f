"""Exact Pr[P_k ≤ M] for the buffered raw-measurement estimator, and the expected number of MKF
runs per step — the two quantities Shi, Xie & Murray 2009 only bound (Thm 3.8) or announce
(abstract) without computing.

Exact probability
-----------------
At time k, packet k − j (age j) is received-and-kept with probability γ̂_j(D) = F(min(j, D_max))
(eq. 4), independently over packets. P_k = f_k ∘ … ∘ f_{k−j+1}(P_{k−j}) where f_t = g̃∘h when y_t
is available and h otherwise (Lemma 3.7). We explore the kept pattern backwards in time (most
recent packet first) as a probability tree and bracket the unknown older history:

* lower: P_{k−j} ≥ P̄ (Lemma 3.7), so P_k ≥ F_suffix(P̄); if F_suffix(P̄) ≰ M then P_k ≰ M;
* upper: if some packet s in the suffix is kept, P_s ≤ M̄ (Lemma 3.4; Appendix B for pair
  packets), so P_k ≤ F_{s+1..k}(M̄) (h and g̃ are monotone, Lemma A.1); the oldest such s is the
  tightest. If that is ≤ M then P_k ≤ M. For Schur-stable A also P_{k−j} ≤ X∞ = h(X∞) (every P_t
  stays below the open-loop stationary covariance), so P_k ≤ F_suffix(X∞) even without a kept packet.

A node is expanded (one more, older packet) only while M lies between its two brackets; nodes
with probability below ``prune`` are closed as "unresolved". The result is a certified interval
[lower, upper] ∋ Pr[P_k ≤ M] (stationary, k → ∞), reported as value = midpoint, err = half-width,
with err < ``tol`` (1e-6 by default) or a warning-level ``converged = False``.

Maps are composed as linear-fractional (Hamiltonian) transformations, P ↦ (T₁₁P + T₁₂)(T₂₁P + T₂₂)⁻¹:
    h:  [[A, Q A⁻ᵀ], [0, A⁻ᵀ]],     g̃:  [[I, 0], [CᵀR⁻¹C, I]],
so appending an older step is a right multiplication (requires A invertible).

With ``horizon`` (finite k, known P_0) the tree stops at packet 1 and is exact; it is then
compared with brute-force enumeration of all 2^k patterns (:func:`brute_force_probability`).

Expected number of MKF runs per step
------------------------------------
By Prop. 3.1 the estimator runs i + 1 MKFs at time k, where y_{k−i} is the oldest packet that
arrives at time k (and is kept); with no arrival it still runs one MKF (the prediction). Hence
R_k = 1 + I_k with I_k = max({i ≤ D_max : d_{k−i} = i} ∪ {0}). The events {d_{k−i} = i} are
independent over i with probabilities f(i), so Pr[I_k ≥ j] = 1 − ∏_{i=j}^{D_max} (1 − f(i)) and

    E[R_k] = 1 + Σ_{j=1}^{D_max} ( 1 − ∏_{i=j}^{D_max} (1 − f(i)) ),     k > D_max,

with D_max = D (``delay_le_D``) or D − 1 (``delay_lt_D``). It increases with D and tends to
1 + Σ_{j≥1} (1 − ∏_{i≥j}(1 − f(i))) as D → ∞ (finite for Poisson delays).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from netkf_cli.linalg import batched, riccati
from netkf_cli.analysis.delay_bounds import max_kept_delay
from netkf_cli.core.errors import ConfigError
from netkf_cli.core.system import LinearSystem
from netkf_cli.core.tolerances import DELAY_EXACT_TOL, PSD_TOL


@dataclass
class ExactResult:
    """Certified bracket of Pr[P_k ≤ M·I] for every M of the grid."""

    M: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    nodes: int
    depth: int
    prune: float

    @property
    def value(self) -> np.ndarray:
        return (self.lower + self.upper) / 2

    @property
    def err(self) -> np.ndarray:
        return (self.upper - self.lower) / 2

    @property
    def converged(self) -> bool:
        return bool(np.all(self.err <= DELAY_EXACT_TOL))


def _lft_matrices(s: LinearSystem) -> tuple[np.ndarray, np.ndarray]:
    """(H, GH): the Hamiltonian matrices of h and of g̃∘h."""
    n = s.n
    if abs(np.linalg.det(s.A)) < 1e-12 * max(1.0, np.abs(s.A).max()) ** n:
        raise ConfigError.at("system.A", "the exact probability composes h in Hamiltonian form and needs A invertible")
    AinvT = np.linalg.inv(s.A).T
    H = np.block([[s.A, s.Q @ AinvT], [np.zeros((n, n)), AinvT]])
    CRC = s.C.T @ np.linalg.solve(s.R, s.C)
    G = np.block([[np.eye(n), np.zeros((n, n))], [CRC, np.eye(n)]])
    return H, G @ H


def _lft_lam(T: np.ndarray, X: np.ndarray, n: int) -> np.ndarray:
    """λ_max of (T₁₁X + T₁₂)(T₂₁X + T₂₂)⁻¹ for a stack T (N, 2n, 2n); NaN for a node whose denominator is singular
    to working precision or whose value is not finite: it is undecided (:func:`_inherit`), and the bracket stays
    certified, only wider.

    A long word's composed map can be that ill-conditioned (A⁻ᵀ's powers: an eigenvalue −0.3 of A grows them 3.3× a
    step; the numerical fuzz found a LinAlgError out of the whole computation). A first-order error bound was tried
    and is far too pessimistic here (on Fig. 9's vehicle it grew to 1e-6 by depth 20 while the values stayed put to
    1e-17, and left the staircase's jump points uncertified), so only a value lost outright is set aside."""
    num = T[:, :n, :n] @ X + T[:, :n, n:]
    den = T[:, n:, :n] @ X + T[:, n:, n:]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        den_inv = 1.0 / den if n == 1 else np.moveaxis(batched.inv_small(np.moveaxis(den, 0, -1)), -1, 0)
        P = num @ den_inv
    P = (P + np.swapaxes(P, 1, 2)) / 2
    ok = np.isfinite(P).all(axis=(1, 2))
    lam = np.full(len(P), np.nan)
    lam[ok] = P[ok, 0, 0] if n == 1 else np.linalg.eigvalsh(P[ok])[:, -1]
    return lam


def _inherit(lam: np.ndarray, parent: np.ndarray) -> np.ndarray:
    """A node's bound from :func:`_lft_lam`, or its parent's where the value is lost (valid: the node's histories are
    some of its parent's)."""
    return np.where(np.isnan(lam), parent, lam)


def _open_loop_bound(s: LinearSystem) -> np.ndarray | None:
    """X∞ solving X = A X Aᵀ + Q when A is Schur stable, else None."""
    if np.max(np.abs(np.linalg.eigvals(s.A))) >= 1 - 1e-9:
        return None

    X = scipy.linalg.solve_discrete_lyapunov(s.A, s.Q)
    return (X + X.T) / 2


def leq_threshold(M: np.ndarray) -> np.ndarray:
    """λ_max(P) ≤ threshold ⇔ P ≤ M·I in :func:`netkf_cli.linalg.riccati.psd_leq`'s tolerance."""
    M = np.asarray(M, dtype=float)
    return M + PSD_TOL * np.maximum(1.0, np.abs(M))


def exact_probability(s: LinearSystem, channel, span: int, M_grid, *, tol: float = DELAY_EXACT_TOL,
                      prune: float | None = None, max_depth: int = 2000, max_nodes: int = 50_000,
                      horizon: int | None = None, P0: np.ndarray | None = None) -> ExactResult:
    """Certified Pr[P_k ≤ M·I] for each M of ``M_grid`` (module docstring).

    Stationary (``horizon=None``): k → ∞, error < ``tol`` unless the node budget runs out (then
    the bracket is still valid, only wider). Finite ``horizon``: exact for P_0 (default P̄).
    """
    M = np.asarray(M_grid, dtype=float).reshape(-1)
    thr = leq_threshold(M)
    n = s.n
    H, GH = _lft_matrices(s)
    Pbar = riccati.pbar(s)
    Mbar = riccati.mbar(s)
    Dmax = max_kept_delay(channel.D, channel.convention)
    X0 = Pbar if P0 is None else np.asarray(P0, dtype=float)
    # lower bracket for the unknown older history: P ≥ P̄ (Lemma 3.7; needs P0 ≥ P̄ in finite mode)
    lower_ok = horizon is None or bool(riccati.psd_leq(Pbar, X0))
    if prune is None:
        prune = 0.0 if horizon is not None else tol * 1e-3
    G = len(M)
    lower = np.zeros(G)
    upper = np.zeros(G)

    # stable A: every P_t ≤ X∞ = A X∞ Aᵀ + Q (induction: h and g̃∘h ≤ h preserve X ≤ X∞, P̄ ≤ X∞), so an
    # un-anchored suffix is still bounded by F_suffix(X∞); needs P0 ≤ X∞ in finite mode
    Xinf = _open_loop_bound(s)
    if Xinf is not None and horizon is not None and not bool(riccati.psd_leq(X0, Xinf)):
        Xinf = None
    # nodes: composed map T (N, 2n, 2n), probability, λ_max of the anchor bound, γ of the last decided packet
    T = np.eye(2 * n)[None].copy()
    prob = np.ones(1)
    hi = np.full(1, np.inf if Xinf is None else float(np.linalg.eigvalsh(Xinf)[-1]))
    gprev = np.zeros(1, dtype=bool)
    lo_n = np.full(1, -np.inf)  # a node's lower bound so far: a child's histories are some of its parent's
    # per node and M: decided ≤ M (yes) or > M (no) at an ancestor, which then holds for every descendant (their
    # histories are some of its): a later, longer word cannot overturn it (its map may have lost precision)
    dyes = np.zeros((1, len(M)), dtype=bool)
    dno = np.zeros((1, len(M)), dtype=bool)
    nodes = 0
    depth = 0
    j = 0
    while len(prob):
        if horizon is not None and j >= horizon:
            break
        if j >= max_depth:
            break
        p = float(channel.cdf(np.asarray(min(j, Dmax))))
        Ts, probs, his, gs, los, yess, nos = [], [], [], [], [], [], []
        for g in (True, False):
            a = np.full(len(prob), g) if span == 1 else (g | gprev)
            step = np.where(a[:, None, None], GH[None], H[None])
            Tc = T @ step
            Tc /= np.abs(Tc).max(axis=(1, 2), keepdims=True)
            pc = prob * (p if g else 1.0 - p)
            hc = _inherit(_lft_lam(T, Mbar, n), hi) if g else hi.copy()
            Ts.append(Tc), probs.append(pc), his.append(hc), gs.append(np.full(len(prob), g)), los.append(lo_n)
            yess.append(dyes), nos.append(dno)
        T = np.concatenate(Ts)
        prob = np.concatenate(probs)
        hi = np.concatenate(his)
        lo_n = np.concatenate(los)
        dyes, dno = np.concatenate(yess), np.concatenate(nos)
        if Xinf is not None:  # both bounds hold: keep the smaller λ_max
            hi = np.fmin(hi, _lft_lam(T, Xinf, n))  # (a lost value: the other bound)
        gprev = np.concatenate(gs)
        keep = prob > 0
        T, prob, hi, gprev, lo_n, dyes, dno = T[keep], prob[keep], hi[keep], gprev[keep], lo_n[keep], dyes[keep], dno[keep]
        nodes += len(prob)
        j += 1
        depth = j
        if horizon is not None and j == horizon:
            lam = _lft_lam(T, X0, n)  # the whole pattern is known: exact P_k (unless the node lost its precision)
            lower += prob @ (dyes | ((_inherit(lam, hi)[:, None] <= thr[None, :]) & ~dno))
            upper += prob @ (~dno & (dyes | (_inherit(lam, lo_n)[:, None] <= thr[None, :])))
            prob = prob[:0]
            break
        if lower_ok:
            lam = _lft_lam(T, Pbar, n)
            lo = _inherit(lam, lo_n)
            lost = np.isnan(lam)  # a longer word only composes more: a lost value does not come back
        else:
            lo, lost = np.zeros(len(prob)), np.zeros(len(prob), dtype=bool)
        sure_yes = dyes | ((hi[:, None] <= thr[None, :]) & ~dno)
        maybe_yes = ~dno & (dyes | (lo[:, None] <= thr[None, :]))
        dyes, dno = sure_yes, ~maybe_yes
        undecided = np.any(maybe_yes & ~sure_yes, axis=1)
        close = ~undecided | (prob < prune) | lost
        if len(prob) - np.count_nonzero(close) > max_nodes:
            # over budget: close the least probable open nodes (still a valid bracket)
            open_idx = np.flatnonzero(~close)
            order = np.argsort(prob[open_idx])
            close[open_idx[order[: len(open_idx) - max_nodes]]] = True
        lower += prob[close] @ sure_yes[close]
        upper += prob[close] @ maybe_yes[close]
        T, prob, hi, gprev, lo_n = T[~close], prob[~close], hi[~close], gprev[~close], lo[~close]
        dyes, dno = dyes[~close], dno[~close]
    if len(prob):  # depth limit: remaining nodes unresolved
        lo = _inherit(_lft_lam(T, Pbar, n), lo_n) if lower_ok else np.zeros(len(prob))
        lower += prob @ (dyes | ((hi[:, None] <= thr[None, :]) & ~dno))
        upper += prob @ (~dno & (dyes | (lo[:, None] <= thr[None, :])))
    return ExactResult(M=M, lower=np.clip(lower, 0, 1), upper=np.clip(upper, 0, 1), nodes=nodes, depth=depth,
                       prune=float(prune))


def brute_force_probability(s: LinearSystem, channel, span: int, M_grid, horizon: int,
                            P0: np.ndarray | None = None) -> np.ndarray:
    """Pr[P_k ≤ M·I] at k = ``horizon`` by enumerating all 2^k kept patterns (k ≤ ~14).

    Independent of every other path: plain loops, ``riccati.h`` and ``riccati.gtilde``.
    """
    M = np.asarray(M_grid, dtype=float).reshape(-1)
    X0 = riccati.pbar(s) if P0 is None else np.asarray(P0, dtype=float)
    Dmax = max_kept_delay(channel.D, channel.convention)
    p = [float(channel.cdf(np.asarray(min(horizon - t, Dmax)))) for t in range(1, horizon + 1)]
    out = np.zeros(len(M))
    for pattern in itertools.product((0, 1), repeat=horizon):
        w = math.prod(p[t] if pattern[t] else 1.0 - p[t] for t in range(horizon))
        if w == 0.0:
            continue
        X = X0
        for t in range(horizon):
            avail = pattern[t] or (span == 2 and t + 1 < horizon and pattern[t + 1])
            X = riccati.h(X, s)
            if avail:
                X = riccati.gtilde(X, s)
        out += w * np.array([bool(riccati.psd_leq(X, m * np.eye(s.n))) for m in M])
    return out


def expected_updates(channel, D: int | None = None) -> float:
    """E[number of MKF runs at time k] for buffer length D, k > D_max (module docstring):

        E[R_k] = 1 + Σ_{j=1}^{D_max} (1 − ∏_{i=j}^{D_max} (1 − f(i)))

    (Prop. 3.1 of Shi, Xie & Murray 2009 with the delay pmf f of eq. 3). The suffix products come
    from one reversed cumulative product: O(D) time and memory (D = 10⁶ takes milliseconds).
    """
    D = channel.D if D is None else D
    Dmax = max_kept_delay(D, channel.convention)
    if Dmax < 1:
        return 1.0
    i = np.arange(0, Dmax + 1)
    F = np.asarray(channel.cdf(i), dtype=float).reshape(Dmax + 1)
    f = np.diff(np.concatenate([[0.0], F]))  # f(0..Dmax)
    suffix = np.cumprod((1.0 - f[1:])[::-1])[::-1]  # suffix[j − 1] = ∏_{i=j}^{Dmax} (1 − f(i))
    return float(1.0 + math.fsum(1.0 - suffix))
