"""Closed-form bounds for fusion over N lossy links (Chiuso & Schenato, Sec. III).

Notation follows the paper, with one deliberate change: the paper's λ is the packet LOSS
probability; every function here takes ``loss`` (= λ of Sec. III-C and IV) or ``arrival``
(= 1 − loss) by name. N identical sensors: every sensor has output matrix C and noise
covariance R (the paper's C_i, R_ii), independent noises.

    L_f(P, L, ℓ) = (I − LC) P (I − LC)ᵀ + (1/ℓ) L R Lᵀ                      eq. (12)
    Φ_f(P, ℓ)    = P − ℓ P Cᵀ (ℓ C P Cᵀ + R)⁻¹ C P                        eq. (14)
    Φ(P, ℓ)      = A Φ_f(P, ℓ) Aᵀ + Q                                     eq. (15)
    P_m = Φ(P_m, N),  P_M = A P_M Aᵀ + Q                                  Sec. III
    L_f^LB(P, ℓ) = chord of Φ_f(·, ℓ) through P_m and P_M (scalar n)      Lemma 2, eq. (17)
    L^LB(P, ℓ)   = A L_f^LB(P, ℓ) Aᵀ + Q                                   Sec. III

Φ_f is written as ``P − ℓ P Cᵀ (ℓ C P Cᵀ + R)⁻¹ C P`` (multiply eq. (14) by ℓ/ℓ) so that
ℓ = 0 (no packet) gives Φ_f = P without dividing by zero; ℓ may be any real ≥ 0 (Lemma 1
and the Jensen steps of Props 1–2 evaluate it at E ℓ, which is not an integer).

The bounds that use L^LB (Prop. 1, Prop. 2 for k ≥ 2) are restricted to scalar states
(n = 1): for n > 1 the paper's eq. (16) is a min–max problem over the PSD interval
[P_m, P_M] that the paper does not solve either; we raise a clear error instead.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np
import scipy.linalg

from netkf_cli.analysis.laws import binom_pmf
from netkf_cli.linalg import kalman
from netkf_cli.core.errors import ConfigError


def _sym(X: np.ndarray) -> np.ndarray:
    return (X + np.swapaxes(X, -1, -2)) / 2


def _as2d(X) -> np.ndarray:
    return np.atleast_2d(np.asarray(X, dtype=float))


# ----------------------------------------------------------------------------------------
# Riccati operators, eqs (12)–(15)
# ----------------------------------------------------------------------------------------


def phi_f(P, ell, C, R) -> np.ndarray:
    """Φ_f(P, ℓ) = P − ℓ P Cᵀ (ℓ C P Cᵀ + R)⁻¹ C P, eq. (14).

    Batched: ``P`` is ``(..., n, n)``, ``ell`` broadcasts against the leading axes ``...``
    (real ℓ ≥ 0 allowed). Scalar systems (n = m = 1) use the closed form P R / (ℓ C² P + R).
    Non-finite P (an overflowed run) propagates as inf, never NaN: with C ≠ 0 and ℓ > 0,
    Φ_f(inf) = R/(ℓC²) is finite; with ℓ = 0 it stays inf.
    """
    P = np.asarray(P, dtype=float)
    C = _as2d(C)
    R = _as2d(R)
    ell = np.asarray(ell, dtype=float)
    n, m = C.shape[1], C.shape[0]
    if n == 1 and m == 1:
        c, r = C[0, 0], R[0, 0]
        p = P[..., 0, 0]
        with np.errstate(invalid="ignore", over="ignore"):
            out = p * r / (ell * c * c * p + r)
            out = np.where(np.isinf(p), np.where(ell * c * c > 0, r / np.where(ell * c * c > 0, ell * c * c, 1.0), np.inf), out)
        return out[..., None, None]
    lead = np.broadcast_shapes(P.shape[:-2], ell.shape)
    Pt = np.moveaxis(np.broadcast_to(P, lead + P.shape[-2:]).reshape((-1,) + P.shape[-2:]), 0, -1)
    out = kalman.update_counts(np.ascontiguousarray(Pt), C, R, np.broadcast_to(ell, lead).reshape(-1))  # the core's eq. (14)
    return np.moveaxis(out, -1, 0).reshape(lead + P.shape[-2:])


def phi(P, ell, A, C, Q, R) -> np.ndarray:
    """Φ(P, ℓ) = A Φ_f(P, ℓ) Aᵀ + Q, eq. (15) (prediction after fusing ℓ sensors)."""
    A = _as2d(A)
    return _sym(A @ phi_f(P, ell, C, R) @ A.T + _as2d(Q))


def l_f(P, L, ell, C, R) -> np.ndarray:
    """L_f(P, L, ℓ) = (I − LC) P (I − LC)ᵀ + (1/ℓ) L R Lᵀ, eq. (12) (filtering error of gain L)."""
    C, R, L = _as2d(C), _as2d(R), _as2d(L)
    P = np.asarray(P, dtype=float)
    I_LC = np.eye(C.shape[1]) - L @ C
    return _sym(I_LC @ P @ I_LC.T + (L @ R @ L.T) / ell)


def kalman_gain(P, ell, C, R) -> np.ndarray:
    """K = P Cᵀ (C P Cᵀ + R/ℓ)⁻¹, eq. (13) (gain applied to the average of ℓ measurements)."""
    C, R, P = _as2d(C), _as2d(R), _as2d(P)
    return kalman.gain(P[:, :, None], C, R / ell)[:, :, 0]  # the Kalman core's gain


# ----------------------------------------------------------------------------------------
# P_m, P_M and the chord lower bound (Lemma 2)
# ----------------------------------------------------------------------------------------


def p_m(A, C, Q, R, N: int) -> np.ndarray:
    """P_m = Φ(P_m, N): steady-state prediction variance with all N sensors every step (Sec. III).

    Fusing N identical sensors equals one sensor with noise R/N, so P_m is the stabilizing
    DARE solution for (A, C, Q, R/N).
    """
    A, C, Q, R = map(_as2d, (A, C, Q, R))
    try:
        P = kalman.dare(A, C, Q, R / N)
    except (np.linalg.LinAlgError, ValueError) as exc:
        raise ConfigError.at(
            "system", f"P_m = Φ(P_m, N) has no stabilizing solution ({exc}); (A, C) must be detectable"
        ) from None
    return _sym(P)


def p_M(A, Q) -> np.ndarray:
    """P_M = A P_M Aᵀ + Q: stationary state variance, the prediction error with no data (Sec. III)."""
    A, Q = _as2d(A), _as2d(Q)
    rho = float(np.max(np.abs(np.linalg.eigvals(A))))
    if rho >= 1.0:
        raise ConfigError.at(
            "system.A",
            f"the bounds of Sec. III need a stable A (P_M = A P_M Aᵀ + Q must exist); spectral radius is {rho:.4g} ≥ 1",
        )
    return _sym(scipy.linalg.solve_discrete_lyapunov(A, Q))


def _require_scalar(A, what: str) -> None:
    if _as2d(A).shape[0] != 1:
        raise ConfigError.at(
            "system.A",
            f"{what} uses the linear lower bound L_f^LB, which is implemented for scalar states only "
            f"(Lemma 2, eq. (17)); n = {_as2d(A).shape[0]} needs the convex program of eq. (16)",
        )


@dataclass(frozen=True)
class ScalarFusionModel:
    """The paper's identical-sensor scalar setting: x⁺ = a x + w, y^i = c x + v^i, i = 1..N."""

    a: float
    c: float
    q: float
    r: float
    N: int

    @classmethod
    def from_matrices(cls, A, C, Q, R, N: int) -> "ScalarFusionModel":
        _require_scalar(A, "this bound")
        return cls(float(_as2d(A)[0, 0]), float(_as2d(C)[0, 0]), float(_as2d(Q)[0, 0]), float(_as2d(R)[0, 0]), int(N))

    @cached_property
    def pm(self) -> float:
        """P_m (a DARE: solved once per model, the bounds read it hundreds of times)."""
        return float(p_m(self.a, self.c, self.q, self.r, self.N)[0, 0])

    @cached_property
    def pM(self) -> float:
        return float(p_M(self.a, self.q)[0, 0])

    def phi_f(self, p, ell):
        """Φ_f(P, ℓ) = P R / (ℓ C² P + R), eq. (14) for n = m = 1."""
        p = np.asarray(p, dtype=float)
        return p * self.r / (np.asarray(ell, dtype=float) * self.c**2 * p + self.r)

    def phi(self, p, ell):
        """Φ(P, ℓ) = A² Φ_f(P, ℓ) + Q, eq. (15)."""
        return self.a**2 * self.phi_f(p, ell) + self.q

    def lf_lb_coeffs(self, ell):
        """Slope and intercept of L_f^LB(P, ℓ) = slope·P + icpt, the chord of eq. (17)."""
        pm, pM = self.pm, self.pM
        fm, fM = self.phi_f(pm, ell), self.phi_f(pM, ell)
        if pM - pm <= 1e-12 * pM:  # degenerate interval (A = 0 or C = 0): any line through the point; take slope 0
            return np.zeros_like(np.asarray(fm, dtype=float)), fm
        slope = (fM - fm) / (pM - pm)
        return slope, fm - slope * pm

    def lf_lb(self, p, ell):
        """L_f^LB(P, ℓ), Lemma 2 eq. (17): the chord through (P_m, Φ_f(P_m,ℓ)) and (P_M, Φ_f(P_M,ℓ))."""
        s, b = self.lf_lb_coeffs(ell)
        return s * np.asarray(p, dtype=float) + b

    def l_lb(self, p, ell):
        """L^LB(P, ℓ) = A² L_f^LB(P, ℓ) + Q (Sec. III, after Remark 1)."""
        return self.a**2 * self.lf_lb(p, ell) + self.q


# ----------------------------------------------------------------------------------------
# MF upper bound: fixed point of Ψ (Sec. III-A, from Schenato 2007 [9])
# ----------------------------------------------------------------------------------------


def psi(S, arrival: float, A, C, Q, R, N: int, *, filtering: bool = False) -> np.ndarray:
    """Ψ(S) for N identical sensors with ARRIVAL probability p (Sec. III-A).

    Ψ(S) = A S Aᵀ + Q − p A S C̄ᵀ (p C̄ S C̄ᵀ + (1−p) S_C + R̄)⁻¹ C̄ S Aᵀ with the stacked
    C̄ = 1_N ⊗ C, R̄ = I_N ⊗ R, S_C = I_N ⊗ C S Cᵀ. The printed symbol is λ, but re-deriving the
    constant-gain filter's expected error (E[Γ C̄ S C̄ᵀ Γ] = p² C̄SC̄ᵀ + p(1−p) S_C, E[Γ R̄ Γ] = p R̄
    for Γ = diag(γ^i)) shows that this λ is the ARRIVAL probability of [9], not this paper's
    loss probability. By exchangeability the N·m × N·m inverse reduces to an m × m one:
        C̄ᵀ(·)⁻¹C̄ = N Cᵀ (D + pN C S Cᵀ)⁻¹ C,   D = (1−p) C S Cᵀ + R.
    ``filtering=True`` returns the filtering error of the same constant gain,
    S − pN S Cᵀ (D + pN C S Cᵀ)⁻¹ C S (our derivation; the paper prints only the prediction form).
    """
    A, C, Q, R, S = map(_as2d, (A, C, Q, R, S))
    p = float(arrival)
    CSC = C @ S @ C.T
    D = (1 - p) * CSC + R + p * N * CSC
    SCt = S @ C.T
    Sf = _sym(S - p * N * SCt @ np.linalg.solve(D, SCt.T))
    if filtering:
        return Sf
    return _sym(A @ Sf @ A.T + Q)


def mf_upper_bound(arrival: float, A, C, Q, R, N: int, *, tol: float = 1e-13, max_iter: int = 200000):
    """(S, S_f): the fixed point S = Ψ(S) and the filtering error at it (Sec. III-A).

    E[P_MF] ≤ S (prediction) and E[P^f_MF] ≤ S_f: the optimal time-varying MF is at least as good
    as the best constant-gain filter L̄ on every loss sequence. Ψ is monotone (a minimum over L̄
    of maps affine in S), so iterating from S = 0 increases to the least fixed point.
    """
    A = _as2d(A)
    n = A.shape[0]
    S = np.zeros((n, n))
    for _ in range(max_iter):
        S_new = psi(S, arrival, A, C, Q, R, N)
        if not np.all(np.isfinite(S_new)) or np.abs(S_new).max() > 1e300:
            raise ConfigError.at("channel.loss", "Ψ has no finite fixed point at this loss probability (MF upper bound diverges)")
        if np.abs(S_new - S).max() <= tol * max(1.0, np.abs(S_new).max()):
            S = S_new
            break
        S = S_new
    else:
        raise ConfigError.at("channel.loss", f"the fixed-point iteration of Ψ did not converge in {max_iter} steps")
    return S, psi(S, arrival, A, C, Q, R, N, filtering=True)


# ----------------------------------------------------------------------------------------
# MF lower bound, Prop. 1
# ----------------------------------------------------------------------------------------


def mf_lower_bound(loss: float, model: ScalarFusionModel) -> tuple[float, float]:
    """(P̄_MF^LB, P̄_MF^{f,LB}) of Prop. 1 with E ℓ = N(1 − λ), λ = ``loss``.

    P̄ = L^LB(P̄, Eℓ) is linear in P̄: with L^LB(P, ℓ) = s·P + b (s = A²·slope_f, b = A²·icpt_f + Q),
    P̄ = b / (1 − s). Then P̄^f = L_f^LB(P̄, Eℓ).
    """
    Eell = model.N * (1.0 - loss)
    sf, bf = model.lf_lb_coeffs(Eell)
    s, b = model.a**2 * sf, model.a**2 * bf + model.q
    P = b / (1.0 - s)
    return float(P), float(model.lf_lb(P, Eell))


# ----------------------------------------------------------------------------------------
# IBF lower bounds, Prop. 2 (+ the exact truncated quantity they bound)
# ----------------------------------------------------------------------------------------


@lru_cache(maxsize=256)
def backward_transition(N: int, loss: float) -> np.ndarray:
    """T[ℓ, ℓ'] = p(ℓ_{t−k−1} = ℓ' | ℓ_{t−k} = ℓ) = Binom(N−ℓ, 1−λ) at ℓ'−ℓ (Sec. III-C).

    The printed density C(N−ℓ_{t−k}, ℓ−ℓ_{t−k}) λ^{N−ℓ} (1−λ)^{ℓ−ℓ_{t−k}} is exactly this
    (τ^i geometric and memoryless); checked in tests against simulated arrival traces.
    Cached (every bound at every k reads it; read-only).
    """
    T = np.zeros((N + 1, N + 1))
    for l in range(N + 1):
        T[l, l:] = binom_pmf(np.arange(N - l + 1), N - l, 1.0 - loss)
    T.flags.writeable = False
    return T


def ibf_lower_bound(k: int, loss: float, model: ScalarFusionModel) -> tuple[float, float]:
    """(P̄_IBF^LB(k), P̄_IBF^{f,LB}(k)) of Prop. 2, λ = ``loss``.

    k = 1: Φ(P_m, N(1−λ)) and Φ_f(P_m, N(1−λ)) (valid for any n; scalar here).
    k ≥ 2: E[ L^LB_{ℓ_t} ∘ … ∘ L^LB_{ℓ_{t−k+2}} ( Φ(P_m, E[ℓ_{t−k+1} | ℓ_{t−k+2}]) ) ], the outer
    map being L_f^LB for the filtering bound. Because every L^LB(·, ℓ) is affine, the expectation
    over the backward Markov chain ℓ_t → ℓ_{t−1} → … is computed exactly by a backward recursion
    U_j(ℓ) = L^LB( E[U_{j+1}(ℓ_{t−j−1}) | ℓ_{t−j} = ℓ], ℓ ) — O(k N²) work, no enumeration.
    Here ℓ_t ~ Binom(N, 1−λ) is the UNCONDITIONAL law (the bound P̄(k) is read as "pretend all
    packets up to t−k arrived", see experiments/fusion/README.md).
    """
    if k < 1:
        raise ValueError("k must be ≥ 1")
    N, pm = model.N, model.pm
    p_arr = 1.0 - loss
    if k == 1:
        Eell = N * p_arr
        return float(model.phi(pm, Eell)), float(model.phi_f(pm, Eell))
    ells = np.arange(N + 1, dtype=float)
    T = backward_transition(N, loss)
    cond_mean = ells + p_arr * (N - ells)  # E[ℓ_{t−k} | ℓ_{t−k+1} = ℓ]
    inner = model.phi(pm, cond_mean)  # Φ(P_m, E[ℓ_{t−k+1} | ℓ_{t−k+2}]) as a function of ℓ_{t−k+2}
    # levels j = k−2 (oldest, ℓ_{t−k+2}) … 0 (ℓ_t); U at level j is a function of ℓ_{t−j}
    U = inner
    for j in range(k - 2, 0, -1):
        U = model.l_lb(U, ells)  # apply L^LB(·, ℓ_{t−j})
        U = T @ U  # E[· | ℓ_{t−j+1}]  (ℓ_{t−j} given ℓ_{t−j+1})
    w = binom_pmf(np.arange(N + 1), N, p_arr)  # law of ℓ_t
    pred = float(w @ model.l_lb(U, ells))
    filt = float(w @ model.lf_lb(U, ells))
    return pred, filt


@dataclass(frozen=True)
class IBFBoundSequence:
    """P̄_IBF^{(f),LB}(k), k = 1..K, and where the stopping rule stopped (Remark 2)."""

    k: np.ndarray
    pred: np.ndarray
    filt: np.ndarray
    k_stop: int
    rtol: float

    @property
    def best_pred(self) -> float:
        """Every P̄^LB(k) is a valid lower bound, so their maximum is too."""
        return float(self.pred.max())

    @property
    def best_filt(self) -> float:
        return float(self.filt.max())


def ibf_lower_bounds(loss: float, model: ScalarFusionModel, *, rtol: float = 1e-3, k_max: int = 50, k_min: int = 3) -> IBFBoundSequence:
    """Prop. 2 for k = 1, 2, … with the stopping rule of Remark 2 made explicit.

    Stop at the first k ≥ k_min whose filtering bound improves on the previous one by less than
    ``rtol`` (relative); always compute at least k_min values. Returns every computed k.
    """
    ks, pr, fi = [], [], []
    k_stop = k_max
    for k in range(1, k_max + 1):
        p, f = ibf_lower_bound(k, loss, model)
        ks.append(k)
        pr.append(p)
        fi.append(f)
        if k >= max(k_min, 2) and abs(fi[-1] - fi[-2]) <= rtol * abs(fi[-2]):
            k_stop = k
            break
    return IBFBoundSequence(np.array(ks), np.array(pr), np.array(fi), k_stop, rtol)


def ibf_truncated_exact(k: int, loss: float, model: ScalarFusionModel) -> tuple[float, float]:
    """P̃(k) = E[Φ(…Φ(Φ(P_m, ℓ_{t−k+1}), ℓ_{t−k+2})…, ℓ_t)] exactly (prediction, filtering).

    This is the quantity Prop. 2 bounds from below: the IBF error if every packet up to time t−k
    had arrived (ℓ_s = N for s ≤ t−k), with the true joint law of ℓ_{t−k+1..t}. It is a lower
    bound of E[P_IBF] path by path (Φ decreases in ℓ) and increases to it as k → ∞. Computed by
    enumerating the C(N+k−1, k−1)… nondecreasing paths of the backward chain (feasible for
    small k·N); used to check P̄^LB(k) ≤ P̃(k) ≤ Monte Carlo.
    """
    N, pm = model.N, model.pm
    T = backward_transition(N, loss)
    w0 = binom_pmf(np.arange(N + 1), N, 1.0 - loss)
    # paths as arrays: prob, current (oldest so far) ℓ, and the list of ℓ's newest→oldest
    prob = w0.copy()
    cur = np.arange(N + 1)
    path = [cur.copy()]
    keep = prob > 0
    prob, cur, path = prob[keep], cur[keep], [p[keep] for p in path]
    for _ in range(k - 1):
        nxt_prob = (prob[:, None] * T[cur, :]).ravel()
        nxt = np.tile(np.arange(N + 1), cur.size)
        rep = np.repeat(np.arange(cur.size), N + 1)
        keep = nxt_prob > 1e-300
        prob, cur = nxt_prob[keep], nxt[keep]
        path = [p[rep][keep] for p in path] + [nxt[keep]]
    # compose oldest first: P = P_m, then Φ with ℓ_{t−k+1}, …, ℓ_{t−1}; filtering with ℓ_t last
    P = np.full(prob.size, pm)
    for ell in reversed(path[1:]):
        P = model.phi(P, ell)
    Pf = model.phi_f(P, path[0])
    Pp = model.a**2 * Pf + model.q
    return float(prob @ Pp), float(prob @ Pf)


# ----------------------------------------------------------------------------------------
# Lemma 1 checks (used by the tests and by the fig2 recipe's self-check)
# ----------------------------------------------------------------------------------------


def lemma1_violations(model: ScalarFusionModel, P_grid: np.ndarray, ell_grid: np.ndarray, tol: float = 1e-12) -> dict:
    """Second differences of Φ_f on a grid: concave in P (≤ 0), convex in ℓ (≥ 0), Lemma 1."""
    F = model.phi_f(P_grid[:, None], ell_grid[None, :])
    scale = np.abs(F).max()
    dP = F[2:, :] - 2 * F[1:-1, :] + F[:-2, :]
    dl = F[:, 2:] - 2 * F[:, 1:-1] + F[:, :-2]
    return {
        "concave_in_P_max_second_diff": float(dP.max()) / scale,
        "convex_in_ell_min_second_diff": float(dl.min()) / scale,
        "concave_ok": bool(dP.max() <= tol * scale),
        "convex_ok": bool(dl.min() >= -tol * scale),
    }


def binom_mean(N: int, loss: float) -> float:
    """E ℓ_t = N(1 − λ) with λ the loss probability."""
    return N * (1.0 - loss)


# ----------------------------------------------------------------------------------------
# References providers (netkf_cli/analysis/references.py REGISTRY): closed-form rows beside the
# Monte Carlo of a generic metric, from a references.Point of plain values
# ----------------------------------------------------------------------------------------

MF_UB = "upper bound: Ψ fixed point (Sec. III-A)"
MF_LB = "lower bound: Prop. 1"
MF_R3 = "lower bound: max(Prop. 1, Prop. 2) (Remark 3)"
PSI_AS_LOSS = "Ψ with λ read as the loss probability (as printed)"
IBF_LB_K = "lower bound: Prop. 2, k = {k}"
IBF_LB_BEST = "lower bound: Prop. 2, k until converged"
IBF_TRUNC_K = "exact truncated P(k), k = {k}"
CKF = "centralized KF without loss: tr Φ_f(P_m, N)"


def point_sensors(point):
    """(A, C1, Q, R1, N) of a point whose system has N identical sensors (``system.sensors: N``), or
    None when the sensors differ (the bounds of Sec. III assume identical sensors)."""
    s = point.system
    C, R = _as2d(s.C), _as2d(s.R)
    groups = s.sensor_rows
    blocks = [(C[list(g)], R[np.ix_(g, g)]) for g in groups]
    c0, r0 = blocks[0]
    if not all(c.shape == c0.shape and np.array_equal(c, c0) and np.array_equal(r, r0) for c, r in blocks):
        return None
    cross = R.copy()
    for g in groups:
        cross[np.ix_(g, g)] = 0.0
    if np.any(cross != 0.0):
        return None
    return _as2d(s.A), c0, _as2d(s.Q), r0, len(groups)


def _strategy_labels(point, strategy: str) -> list[str]:
    """Labels of the point's fusion estimators that report ``strategy`` (their first strategy)."""
    return [lab for e, lab in zip(point.estimators, point.labels)
            if e.get("kind") == "fusion" and (e.get("strategies") or ["mf"])[0] == strategy]


def _loss(point) -> float:
    loss = point.channel.get("loss")
    if isinstance(loss, list):
        if len(set(loss)) != 1:
            raise ConfigError.at("channel.loss", "the bounds of Sec. III assume one loss probability for every sensor")
        loss = loss[0]
    if loss is None:
        raise ConfigError.at("channel.loss", "the fusion bounds need a multi channel with a loss probability")
    return float(loss)


def _pair_rows(series: str, labels: list[str], pred: float, filt: float, quantities, both: bool = True) -> list[dict]:
    """Rows of one bound for the point's quantities (``both=False``: the filtering form only)."""
    out = []
    for lab in labels or [""]:
        for q, v in (("predicted", pred), ("filtered", filt)):
            if q in quantities and (both or q == "filtered"):
                out.append(dict(series=series, estimator=lab, quantity=q, value=float(v)))
    return out


def centralized_reference(point) -> list[dict]:
    """Centralized Kalman filter with every packet (Chiuso–Schenato Sec. III): tr Φ_f(P_m, N) and tr P_m."""
    sens = point_sensors(point)
    if sens is None:
        return []
    A, C1, Q, R1, N = sens
    pm = p_m(A, C1, Q, R1, N)
    return _pair_rows(CKF, [""], float(np.trace(pm)), float(np.trace(phi_f(pm, np.float64(N), C1, R1))),
                      point.quantities)


def fusion_bounds_reference(point) -> list[dict]:
    """Chiuso–Schenato bounds on E[P] of MF and IBF (Sec. III: Ψ upper bound, Props 1–2, Remark 3).

    Filtered P_{k|k}: every bound; predicted P_{k+1|k}: the Ψ upper bound and Prop. 1 (the rest of the
    prediction forms add lines to a figure, not checks)."""
    sens = point_sensors(point)
    if sens is None:
        return []
    A, C1, Q, R1, N = sens
    lam = _loss(point)
    if lam >= 1.0:
        raise ConfigError.at("channel.loss", "must be < 1 (with every packet lost there is no steady state to bound)")
    qs = point.quantities
    mf, ibf = _strategy_labels(point, "mf"), _strategy_labels(point, "ibf")
    k_show = [1, 2, 3]
    rtol, k_max = 1e-3, 60
    rows: list[dict] = []
    if mf:
        S, Sf = mf_upper_bound(1.0 - lam, A, C1, Q, R1, N)
        rows += _pair_rows(MF_UB, mf, np.trace(S), np.trace(Sf), qs)
    scalar = A.shape[0] == 1 and C1.shape[0] == 1
    if not scalar:
        # Prop. 2 with k = 1 only (no L_f^LB: valid for any n)
        if ibf:
            pm = p_m(A, C1, Q, R1, N)
            Eell = np.float64(N * (1.0 - lam))
            rows += _pair_rows(IBF_LB_K.format(k=1), ibf, np.trace(phi(pm, Eell, A, C1, Q, R1)),
                               np.trace(phi_f(pm, Eell, C1, R1)), qs, both=False)
        return rows
    model = ScalarFusionModel.from_matrices(A, C1, Q, R1, N)
    seq = ibf_lower_bounds(lam, model, rtol=rtol, k_max=k_max)
    if mf:
        lbp, lbf = mf_lower_bound(lam, model)
        rows += _pair_rows(MF_LB, mf, lbp, lbf, qs)
        rows += _pair_rows(MF_R3, mf, max(lbp, seq.best_pred), max(lbf, seq.best_filt), qs, both=False)
        if lam > 0:
            S2, Sf2 = mf_upper_bound(lam, A, C1, Q, R1, N)
        else:
            S2 = Sf2 = np.atleast_2d(p_M(A, Q))  # no arrivals: the open-loop variance
        rows += _pair_rows(PSI_AS_LOSS, mf, S2[0, 0], Sf2[0, 0], qs, both=False)
    if ibf:
        for k in k_show:
            rows += _pair_rows(IBF_LB_K.format(k=k), ibf, *ibf_lower_bound(k, lam, model), qs, both=False)
        rows += _pair_rows(IBF_LB_BEST, ibf, seq.best_pred, seq.best_filt, qs, both=False)
        for k in k_show:
            rows += _pair_rows(IBF_TRUNC_K.format(k=k), ibf, *ibf_truncated_exact(k, lam, model), qs, both=False)
    return rows


__all__ = [
    "phi_f", "phi", "l_f", "kalman_gain", "p_m", "p_M", "ScalarFusionModel", "psi", "mf_upper_bound",
    "mf_lower_bound", "backward_transition", "ibf_lower_bound", "ibf_lower_bounds", "ibf_truncated_exact",
    "IBFBoundSequence", "lemma1_violations", "binom_mean",
]
