"""Closed forms and exact computations for Leong, Dey & Evans 2008 ("On Kalman smoothing with
random packet loss", IEEE TSP 56(8)), plus the exact quantities the paper only bounds.

Paper quantities
* M̄ = A C⁻¹ R C⁻ᵀ Aᵀ + Q (C invertible, Sec. IV) — the prediction covariance right after an
  arrival from an infinitely uncertain prior, i.e. g(∞).
* k₁ = min{k ∈ ℤ⁺ : hᵏ(M̄) ≰ M}, h(X) = A X Aᵀ + Q (Sec. IV).
* λ ≥ 1 − ε^{1/k₁} suffices for P(P_{k|k−1} ≤ M) > 1 − ε (eq. 7, from Shi et al. 2005 Cor. 4);
  λ ≥ 1 − ε^{1/(k₁+N+1)} for P(P_{k|k+N} ≤ M) > 1 − ε (eq. 8; N = 0 is the filter P_{k|k}).
* f(n), g(n) of the random retransmission scheme (eqs 10–11) and g(n) = 1.
* λ_c = 1 − 1/ρ(A)² for the critical arrival rate (Lemma 1; exact when C is invertible).

Beyond the paper (exact values, so that the guarantees' slack is visible)
* :func:`exact_probability` — the stationary P(P_{k|k+N} ≤ M) for i.i.d. or Markov (Gilbert)
  loss, by enumeration of the recent arrival pattern (a backward tree, see below), returned as
  a certified interval [lower, upper] whose width is reported.
* :func:`exact_mean` — the stationary E[P_{k|k−1}], E[P_{k|k+N}] for i.i.d. loss (exact
  decomposition over the last arrival + enumeration of a bounded function).
* :func:`batch_posterior_covariance` — Cov(x_k | all received y_t, t ≤ j) by brute-force
  Gaussian conditioning of the joint law of (x_0 … x_T, y_0 … y_T): the reference for eqs 3–4.

How the enumeration works. Conditioned on x_k, the measurements y_k … y_{k+N} are independent
of the past, so P_{k|k+N} = (P_{k|k−1}⁻¹ + J(f))⁻¹ where J(f) is the Fisher information on x_k
of the *received* future measurements (future pattern f = γ_k … γ_{k+N}). P_{k|k−1} is the
image of P_{k−j|k−j−1} under the j Riccati maps of the suffix s = γ_{k−j} … γ_{k−1}; in
stationarity (started at P*) P_{k−j|k−j−1} ∈ [P*, ∞) and every map is monotone, so
P_{k|k−1} ∈ [Φ_s(P*), Φ_s(∞)] (the upper end computed in information form, which needs A
invertible). A suffix is *resolved* for pattern f when both ends agree on "P_{k|k+N} ≤ M";
otherwise it is extended one step further into the past. The probability of unresolved
suffixes dropped at the cut-off (``tol`` per node, ``max_depth``) is the reported interval
width, so the result is a rigorous bracket, not an approximation of unknown quality.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from fractions import Fraction

import numpy as np
import scipy.linalg

from netkf_cli.linalg import kalman, riccati
from netkf_cli.core.errors import ConfigError, TheoremConditionError
from netkf_cli.core.system import LinearSystem
from netkf_cli.core.tolerances import EXACT_PSD_TOL, SMOOTHING_EXACT_TOL, SMOOTHING_MEAN_TOL

K_MAX = 100_000
MAX_EXACT_LAG = 8
"""Largest lag N of :func:`exact_probability`: it enumerates the 2^(N+1) future arrival patterns
(N = 12 took 150 s for one column of a 2-state system; N = 8 is 16× less)."""
MAX_MEAN_LAG = 8
"""Largest lag N of :func:`exact_mean` (2^(N+1) − 1 bounded functions, each enumerated)."""


# --------------------------------------------------------------------------------------------
# M̄, k₁, arrival rates (Sec. IV, eqs 7–8)
# --------------------------------------------------------------------------------------------


def as_bound(M, n: int, path: str = "analysis.M") -> np.ndarray:
    """A scalar M means M·Iₙ; a matrix must be n×n, symmetric positive definite."""
    Ma = np.asarray(M, dtype=float)
    Ma = float(Ma) * np.eye(n) if Ma.ndim == 0 else np.atleast_2d(Ma)
    if Ma.shape != (n, n):
        raise ConfigError.at(path, f"must be a scalar or an {n}×{n} matrix, got shape {Ma.shape}")
    if not np.allclose(Ma, Ma.T) or np.linalg.eigvalsh(riccati.sym(Ma)).min() <= 0:
        raise ConfigError.at(path, "must be symmetric positive definite (a covariance bound)")
    return riccati.sym(Ma)


def leong_mbar(s: LinearSystem, path: str = "system.C") -> np.ndarray:
    """M̄ = A C⁻¹ R C⁻ᵀ Aᵀ + Q for C invertible (Sec. IV, Leong 2008).

    Any prediction covariance one step after an arrival satisfies P_{k+1|k} ≤ M̄ (g(X) ≤ g(∞) = M̄).
    For non-invertible C the paper defers to Epstein et al. [17]; not implemented here.
    """
    if s.m != s.n or np.linalg.matrix_rank(s.C) < s.n:
        raise ConfigError.at(
            path,
            f"Leong's M̄ = A C⁻¹ R C⁻ᵀ Aᵀ + Q needs C square and invertible, got C of shape {s.m}×{s.n} "
            f"(rank {np.linalg.matrix_rank(s.C)}); the non-invertible case (Epstein et al. 2008) is not implemented",
        )
    CiR = np.linalg.solve(s.C, s.R)
    CiRCit = np.linalg.solve(s.C, CiR.T).T
    return riccati.sym(s.A @ CiRCit @ s.A.T + s.Q)


def k1(s: LinearSystem, M, Mbar: np.ndarray | None = None, k_max: int = K_MAX) -> float:
    """k₁ = min{k ≥ 1 : hᵏ(M̄) ≰ M} (Sec. IV); ``math.inf`` if hᵏ(M̄) ≤ M for every k ≤ k_max."""
    Mm = as_bound(M, s.n)
    X = leong_mbar(s) if Mbar is None else Mbar
    if not bool(riccati.psd_leq(X, Mm)):
        raise TheoremConditionError.at(
            "analysis.M", f"must satisfy M ≥ M̄ = {np.array2string(X, precision=4)} for the guarantee of eq. (7) to make sense"
        )
    for k in range(1, k_max + 1):
        Xn = riccati.h(X, s)
        if not bool(riccati.psd_leq(Xn, Mm)) or not np.all(np.isfinite(Xn)):
            return float(k)
        if np.abs(Xn - X).max() <= 1e-15 * max(1.0, float(np.abs(X).max())):
            return math.inf  # converged to the fixed point of h below M (stable A)
        X = Xn
    return math.inf


def sufficient_arrival_rate(k1_value: float, eps: float, lag: int | None) -> float:
    """λ ≥ 1 − ε^{1/k₁} (eq. 7, ``lag=None``: P_{k|k−1}) or 1 − ε^{1/(k₁+N+1)} (eq. 8, lag N ≥ 0)."""
    if not 0 < eps < 1:
        raise ConfigError.at("analysis.eps", f"must be in (0, 1), got {eps}")
    k = k1_value if lag is None else k1_value + lag + 1
    if math.isinf(k):
        return 0.0
    return 1.0 - eps ** (1.0 / k)


def critical_rate(s: LinearSystem) -> float:
    """λ_c = 1 − 1/ρ(A)² (Sinopoli et al. 2004; exact when C is invertible). 0 for stable A."""
    rho = float(np.max(np.abs(np.linalg.eigvals(s.A))))
    return max(0.0, 1.0 - 1.0 / rho**2) if rho > 0 else 0.0


def second_moment_rate(s: LinearSystem) -> float:
    """1 − 1/ρ(A)⁴: below this arrival rate E[P²] = ∞ for C invertible (the k-step loss run has
    probability (1−λ)ᵏ and P grows like ρ^{2k}), so a Monte Carlo mean has no finite standard error."""
    rho = float(np.max(np.abs(np.linalg.eigvals(s.A))))
    return max(0.0, 1.0 - 1.0 / rho**4) if rho > 0 else 0.0


# --------------------------------------------------------------------------------------------
# Information of future measurements, batch conditioning
# --------------------------------------------------------------------------------------------


def future_information(s: LinearSystem, pattern) -> np.ndarray:
    """J(f): Fisher information on x_k of the received y_{k+i} (f_i = 1), i = 0 … len(f)−1.

    y_{k+i} = C Aⁱ x_k + η_i, η_i = C Σ_{l<i} A^{i−1−l} w_{k+l} + v_{k+i} (correlated across i):
    J = Hᵀ Σ_η⁻¹ H with H = [C Aⁱ]_{i received} (:func:`_future_model`). Computed recursively — a
    Kalman filter of the noise part started at x_k known: α_0 = I, V_0 = 0 and, for each i, if
    f_i = 1 (S = C V Cᵀ + R): J += (Cα)ᵀ S⁻¹ (Cα), α ← α − V Cᵀ S⁻¹ C α, V ← V − V Cᵀ S⁻¹ C V;
    then α ← A α, V ← A V Aᵀ + Q. Equal to the batch form, but never forms Σ_η, which is
    numerically singular for a strongly unstable A (A = 10⁶: entries 1 and 10¹²⁴).
    """
    n = s.n
    J = np.zeros((n, n))
    al = np.eye(n)
    V = np.zeros((n, n))
    for i, b in enumerate(int(x) for x in pattern):
        if i:
            al = s.A @ al
            V = riccati.sym(s.A @ V @ s.A.T) + s.Q
        if b:  # the Kalman core's gain and update on the noise part; J accumulates (Cα)ᵀ S⁻¹ (Cα)
            Vb = V[:, :, None]
            S = kalman.innovation(Vb, s.C, s.R)[1][:, :, 0]
            Ca = s.C @ al
            J = J + Ca.T @ np.linalg.solve(S, Ca)
            al = al - kalman.gain(Vb, s.C, s.R)[:, :, 0] @ Ca
            V = kalman.one(kalman.update, V, s.C, s.R)
    return riccati.sym(J)


_FUTURE_J: dict = {}


def _future_information_cached(s: LinearSystem, pattern) -> np.ndarray:
    """:func:`future_information` memoized per (system, pattern) in this process (a copy: the enumerations
    recompute the same J(f) for every arrival rate and lag)."""
    key = (_skey(s), tuple(int(b) for b in pattern))
    if key not in _FUTURE_J:
        _FUTURE_J[key] = future_information(s, key[1])
    return _FUTURE_J[key].copy()


def smoothed_from_prior(P: np.ndarray, s: LinearSystem, pattern) -> np.ndarray:
    """P_{k|k+N} = (P⁻¹ + J(f))⁻¹ from P_{k|k−1} = P and the future arrival pattern f, computed as
    (I + P J)⁻¹ P (valid for a singular P)."""
    J = future_information(s, pattern)
    return riccati.sym(np.linalg.solve(np.eye(s.n) + P @ J, P))


def batch_posterior_covariance(s: LinearSystem, gamma, k: int, upto: int, P0: np.ndarray) -> np.ndarray:
    """Cov(x_k | y_t for all t ≤ ``upto`` with γ_t = 1), by conditioning the joint Gaussian law of
    (x_0, …, x_T, y_0, …, y_T) — brute force, no recursion; the reference for eqs (3)–(4).

    x_0 ~ N(·, P0), x_{t+1} = A x_t + w_t; ``upto = k − 1`` gives P_{k|k−1}.
    """
    n, m = s.n, s.m
    T = max(k, upto) + 1
    # Cov(x_t) and Cov(x_s, x_t) = A^{s−t} Cov(x_t) for s ≥ t
    V = [np.asarray(P0, dtype=float)]
    for _ in range(1, T):
        V.append(s.A @ V[-1] @ s.A.T + s.Q)
    big = np.zeros((n * T, n * T))
    for t in range(T):
        X = V[t]
        for u in range(t, T):
            big[u * n:(u + 1) * n, t * n:(t + 1) * n] = X
            big[t * n:(t + 1) * n, u * n:(u + 1) * n] = X.T
            X = s.A @ X
    rec = [t for t in range(min(upto, T - 1) + 1) if gamma[t]]
    Pkk = big[k * n:(k + 1) * n, k * n:(k + 1) * n]
    if not rec:
        return Pkk
    H = np.zeros((m * len(rec), n * T))
    for a, t in enumerate(rec):
        H[a * m:(a + 1) * m, t * n:(t + 1) * n] = s.C
    Syy = H @ big @ H.T + np.kron(np.eye(len(rec)), s.R)
    Sxy = big[k * n:(k + 1) * n, :] @ H.T
    return riccati.sym(Pkk - Sxy @ np.linalg.solve(Syy, Sxy.T))


# --------------------------------------------------------------------------------------------
# Exact stationary probability P(P_{k|k+N} ≤ M) by enumeration of the recent arrival pattern
# --------------------------------------------------------------------------------------------


def _require_invertible_A(s: LinearSystem) -> np.ndarray:
    if np.linalg.matrix_rank(s.A) < s.n:
        raise ConfigError.at("system.A", "the exact enumeration bounds P_{k|k−1} from above in information form, which needs A invertible")
    return np.linalg.inv(s.A)


_KERNEL: list = []


def _compiled_module():
    """:mod:`netkf_cli.analysis._smoothing_numba` where numba imports, else None (probed once)."""
    if not _KERNEL:
        try:
            from netkf_cli.analysis import _smoothing_numba  # optional: needs numba (numpy fallback below)
        except ImportError:
            _KERNEL.append(None)
        else:
            _KERNEL.append(_smoothing_numba)
    return _KERNEL[0]


def _scalar_kernel():
    """:func:`netkf_cli.analysis._smoothing_numba.evaluate_scalar` where numba imports, else None."""
    mod = _compiled_module()
    return None if mod is None else mod.evaluate_scalar


class _Batch:
    """Batched (leading axis = node) Riccati maps in covariance and information form."""

    def __init__(self, s: LinearSystem):
        self.s = s
        self.Ainv = _require_invertible_A(s)
        self.CRC = riccati.sym(s.C.T @ np.linalg.solve(s.R, s.C))
        self.Pst = riccati.pstar(s)
        self.I = np.eye(s.n)
        self.scalar = s.n == 1 and s.m == 1
        if self.scalar:
            a, c = float(s.A[0, 0]), float(s.C[0, 0])
            self.a2, self.c2, self.q, self.r = a * a, c * c, float(s.Q[0, 0]), float(s.R[0, 0])
            self.crc = self.c2 / self.r
        self._J: dict = {}

    @staticmethod
    def sym(X):
        return 0.5 * (X + np.swapaxes(X, -1, -2))

    def cov_step(self, P: np.ndarray, gam: np.ndarray) -> np.ndarray:
        """P ← A P Aᵀ + Q − γ A P Cᵀ (C P Cᵀ + R)⁻¹ C P Aᵀ, batched."""
        s = self.s
        if self.scalar:  # elementwise: a² P r/(c² P + r) + q after an arrival, a² P + q after a loss
            p = P[:, 0, 0]
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                upd = np.where(gam > 0, self.r / (self.c2 + self.r / p), p)
                return (self.a2 * upd + self.q)[:, None, None]
        Pr = np.moveaxis(P, 0, -1)  # the Kalman core's layout (n, n, nodes)
        Pu = kalman.update(Pr, s.C, s.R, np.asarray(gam, dtype=float))
        return np.moveaxis(kalman.predict(Pu, s.A, s.Q), -1, 0)

    def info_step(self, Y: np.ndarray, gam: np.ndarray) -> np.ndarray:
        """Y ← Z (I + Q Z)⁻¹, Z = A⁻ᵀ (Y + γ CᵀR⁻¹C) A⁻¹ (valid for singular Y, i.e. P = ∞ directions)."""
        if self.scalar:  # Y ← Z/(1 + qZ), Z = (Y + γ c²/r)/a²
            z = (Y[:, 0, 0] + gam * self.crc) / self.a2
            return (z / (1.0 + self.q * z))[:, None, None]
        Z = self.Ainv.T @ (Y + gam[:, None, None] * self.CRC) @ self.Ainv
        K = self.I + self.s.Q @ Z
        out = np.swapaxes(np.linalg.solve(np.swapaxes(K, -1, -2), np.swapaxes(Z, -1, -2)), -1, -2)
        return self.sym(out)

    def evaluate(self, bits: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For suffixes ``bits`` (B, j) (oldest first): P_lo = Φ_s(P*), Y_hi = (Φ_s(∞))⁻¹ (information).
        Scalar systems run compiled where numba imports (:mod:`netkf_cli.analysis._smoothing_numba`: the same
        operations per node, the same bits; ≈ 5× the numpy steps, which are the fallback)."""
        B = bits.shape[0]
        n = self.s.n
        if self.scalar and bits.shape[1] and _scalar_kernel() is not None:
            P = np.empty(B)
            Y = np.empty(B)
            _scalar_kernel()(np.ascontiguousarray(bits), float(self.Pst[0, 0]), self.a2, self.c2, self.q, self.r,
                             self.crc, P, Y)
            return P[:, None, None], Y[:, None, None]
        P = np.broadcast_to(self.Pst, (B, n, n)).copy()
        Y = np.zeros((B, n, n))
        for c in range(bits.shape[1]):
            gam = bits[:, c].astype(float)
            P = self.cov_step(P, gam)
            Y = self.info_step(Y, gam)
        return P, Y

    def smoothed(self, P: np.ndarray, pattern) -> np.ndarray:
        """Batched :func:`smoothed_from_prior`: (P⁻¹ + J(f))⁻¹."""
        if self.scalar:  # (P⁻¹ + J(f))⁻¹ = P / (1 + P J(f))
            key = tuple(int(b) for b in pattern)
            if key not in self._J:
                self._J[key] = float(_future_information_cached(self.s, key)[0, 0])
            J = self._J[key]
            if J == 0.0:
                return P
            with np.errstate(over="ignore", invalid="ignore"):
                return np.where(np.isinf(P), 1.0 / J, P / (1.0 + P * J))
        key = tuple(int(b) for b in pattern)
        if key not in self._J:
            self._J[key] = _future_information_cached(self.s, key)
        J = self._J[key]
        return self.sym(np.linalg.solve(self.I + P @ J, P))  # (I + P J)⁻¹ P = (P⁻¹ + J)⁻¹


def _future_model(s: LinearSystem, pattern):
    """(H, Σ_η) of the received future measurements y_{k+i} = C Aⁱ x_k + η_i (see :func:`future_information`)."""
    f = [int(b) for b in pattern]
    idx = [i for i, b in enumerate(f) if b]
    if not idx:
        return None, None
    n, m = s.n, s.m
    Ap = [np.eye(n)]
    for _ in range(max(idx) + 1):
        Ap.append(s.A @ Ap[-1])
    H = np.vstack([s.C @ Ap[i] for i in idx])
    Sig = np.zeros((len(idx) * m, len(idx) * m))
    for a, i in enumerate(idx):
        for b, j in enumerate(idx):
            acc = np.zeros((n, n))
            for l in range(min(i, j)):
                acc += Ap[i - 1 - l] @ s.Q @ Ap[j - 1 - l].T
            Sig[a * m:(a + 1) * m, b * m:(b + 1) * m] = s.C @ acc @ s.C.T + (s.R if i == j else 0.0)
    return H, Sig


def _min_eig(X: np.ndarray) -> np.ndarray:
    if X.shape[-1] == 1:
        return X[..., 0, 0]
    return np.linalg.eigvalsh(0.5 * (X + np.swapaxes(X, -1, -2)))[..., 0]


@dataclass(frozen=True)
class ExactProbability:
    """A certified bracket lower ≤ P(·) ≤ upper; ``value`` is its midpoint, ``width`` = upper − lower."""

    lower: float
    upper: float
    nodes: int
    depth: int

    @property
    def value(self) -> float:
        return 0.5 * (self.lower + self.upper)

    @property
    def width(self) -> float:
        return self.upper - self.lower


def exact_probability(
    s: LinearSystem,
    M,
    lag: int | None,
    T: np.ndarray,
    pi: np.ndarray,
    *,
    tol: float = 1e-14,
    max_depth: int = 2000,
    max_nodes: int = 200_000,
) -> ExactProbability:
    """Stationary P(P_{k|k+N} ≤ M) (``lag=N``; ``lag=None`` for P_{k|k−1}), arrivals a 2-state Markov
    chain ``T[a, b] = P(γ_{k+1}=b | γ_k=a)`` with stationary ``pi`` (Bernoulli: identical rows).

    Backward enumeration over the recent arrival pattern (module docstring), vectorized over the
    nodes of one level; returns a certified bracket. Nodes of joint weight < ``tol`` that are still
    undecided are dropped into the bracket's width.
    """
    if lag is not None and not 0 <= lag <= MAX_EXACT_LAG:
        raise ConfigError.at("analysis.lags", f"the exact probability enumerates 2^(N+1) future patterns: N must be in 0..{MAX_EXACT_LAG}, got {lag}")
    Mm = as_bound(M, s.n)
    Minv = np.linalg.inv(Mm)
    bt = _Batch(s)
    T = np.asarray(T, dtype=float)
    pi = np.asarray(pi, dtype=float)
    if np.any(pi <= 0):
        raise ConfigError.at("channel", "the exact enumeration needs both arrivals and losses to be possible (0 < λ < 1)")
    futures = [()] if lag is None else list(itertools.product((0, 1), repeat=lag + 1))
    F = len(futures)
    Js = [_future_information_cached(s, f) for f in futures]
    fw = np.array([np.prod([T[a, b] for a, b in zip(f[:-1], f[1:])]) if f else 1.0 for f in futures])
    first = np.array([f[0] if f else -1 for f in futures])
    scale = float(np.abs(Minv).max())  # relative: an absolute tolerance would swamp M⁻¹ for a large M
    lower, lost, nodes, depth = 0.0, 0.0, 0, 0
    bits = np.zeros((1, 0), dtype=np.int8)
    W = np.array([[pi[f[0]] * fw[i] if f else 1.0 for i, f in enumerate(futures)]])
    while bits.shape[0]:
        nodes += bits.shape[0]
        P_lo, Y_hi = bt.evaluate(bits)
        ok = np.zeros(W.shape, dtype=bool)
        bad = np.zeros(W.shape, dtype=bool)
        for i, f in enumerate(futures):
            ok[:, i] = _min_eig(Y_hi + Js[i] - Minv) >= -EXACT_PSD_TOL * scale
            Ps = bt.smoothed(P_lo, f)
            bad[:, i] = ~ok[:, i] & (_min_eig(Mm - Ps) < -EXACT_PSD_TOL * max(1.0, float(np.abs(Mm).max())))
        lower += float(W[ok].sum())
        W = np.where(ok | bad, 0.0, W)
        tot = W.sum(axis=1)
        small = (tot > 0) & ((tot < tol) | (depth >= max_depth))
        lost += float(tot[small].sum())
        keep = (tot > 0) & ~small
        bits, W = bits[keep], W[keep]
        if not bits.shape[0]:
            break
        if 2 * bits.shape[0] > max_nodes:
            lost += float(W.sum())
            break
        kids_bits, kids_W = [], []
        for b in (0, 1):
            if bits.shape[1]:
                a = bits[:, 0].astype(int)
                factor = (pi[b] * T[b, a] / pi[a])[:, None] * np.ones((1, F))
            elif futures[0]:
                factor = np.broadcast_to(pi[b] * T[b, first] / pi[first], W.shape)
            else:
                factor = np.full(W.shape, pi[b])
            kids_bits.append(np.hstack([np.full((bits.shape[0], 1), b, dtype=np.int8), bits]))
            kids_W.append(W * factor)
        bits, W = np.vstack(kids_bits), np.vstack(kids_W)
        depth += 1
    return ExactProbability(lower=lower, upper=min(1.0, lower + lost), nodes=nodes, depth=depth)


# --------------------------------------------------------------------------------------------
# Exact stationary means (i.i.d. loss), Lemma 1
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ExactMean:
    """Bracket on a stationary mean (matrices); ``inf`` entries mean E[·] is unbounded (λ ≤ λ_c)."""

    lower: np.ndarray
    upper: np.ndarray

    @property
    def value(self) -> np.ndarray:
        return 0.5 * (self.lower + self.upper)


def _expect_bounded(phis, caps, weights, bt: _Batch, lam: float, tol: float, max_depth: int, max_nodes: int):
    """E[φ_i(P_{k|k−1})] under i.i.d. Bernoulli(λ) for monotone φ_i with φ_i ≤ ``caps[i]`` (brackets).

    ``phis[i](P_lo, Y_hi) -> (φ(P_lo), φ(P_hi))`` batched; a node is refined while
    weight × Σ_i weights[i]·tr(φ_i(P_hi) − φ_i(P_lo)) > tol.
    """
    n = bt.s.n
    K = len(phis)
    lo_sum = [np.zeros((n, n)) for _ in range(K)]
    hi_sum = [np.zeros((n, n)) for _ in range(K)]
    bits = np.zeros((1, 0), dtype=np.int8)
    w = np.ones(1)
    depth = 0
    while bits.shape[0]:
        P_lo, Y_hi = bt.evaluate(bits)
        vals = [phi(P_lo, Y_hi) for phi in phis]
        fins = [np.all(np.isfinite(hi), axis=(1, 2)) for _, hi in vals]
        gap = np.zeros(bits.shape[0])
        for i, (lo, hi) in enumerate(vals):
            fin = fins[i]
            gi = np.where(fin, np.trace(np.where(fin[:, None, None], hi - lo, 0.0), axis1=1, axis2=2), np.inf)
            gap += weights[i] * gi
        stop = (w * gap <= tol) | (depth >= max_depth) | (w < 1e-300)
        if 2 * int((~stop).sum()) > max_nodes:
            stop[:] = True
        w_stop = w[stop]
        for i, (lo, hi) in enumerate(vals):  # the capped upper ends of the stopped nodes only (the same values)
            hi_c = np.where(fins[i][stop][:, None, None], hi[stop], caps[i])
            lo_sum[i] += np.einsum("b,bij->ij", w_stop, lo[stop])
            hi_sum[i] += np.einsum("b,bij->ij", w_stop, hi_c)
        bits, w = bits[~stop], w[~stop]
        if not bits.shape[0]:
            break
        bits = np.vstack([np.hstack([np.full((bits.shape[0], 1), b, dtype=np.int8), bits]) for b in (1, 0)])
        w = np.concatenate([w * lam, w * (1 - lam)])
        depth += 1
    return lo_sum, hi_sum


def _expect_bounded_scalar(Js, caps, weights, bt: _Batch, lam: float, tol: float, max_depth: int, max_nodes: int):
    """:func:`_expect_bounded` for a scalar system and the φ of :func:`exact_mean` — φ_0 = g, φ_{1+f} = (P⁻¹ +
    J_f)⁻¹ with J_f = ``Js[f]`` — each level's brackets and gaps in one compiled pass over the nodes
    (:func:`netkf_cli.analysis._smoothing_numba.expect_level_scalar`: the numpy φ's operations per node); the
    stopping rule, the sums (the same ``einsum`` on the same arrays) and the next level as there: the same bits
    (a test)."""
    mod = _compiled_module()
    kern, ev = mod.expect_level_scalar, mod.evaluate_scalar_cols
    pst = float(bt.Pst[0, 0])
    K = len(Js) + 1
    Jv = np.asarray(Js, dtype=float)
    wv = np.asarray(weights, dtype=float)
    capv = np.array([float(c[0, 0]) for c in caps])[:, None]
    lo_sum = [np.zeros((1, 1)) for _ in range(K)]
    hi_sum = [np.zeros((1, 1)) for _ in range(K)]
    cols = np.zeros((0, 1), dtype=np.int8)  # the nodes' suffixes as columns (row 0 the oldest step)
    w = np.ones(1)
    depth = 0
    while cols.shape[1]:
        B = cols.shape[1]
        P_lo, Y_hi = np.empty(B), np.empty(B)
        ev(cols, pst, bt.a2, bt.c2, bt.q, bt.r, bt.crc, P_lo, Y_hi)  # _Batch.evaluate, compiled
        LO, HI, FIN, gap = np.empty((K, B)), np.empty((K, B)), np.empty((K, B), dtype=np.bool_), np.empty(B)
        kern(P_lo, Y_hi, bt.a2, bt.c2, bt.q, bt.r, bt.crc, Jv, wv, LO, HI, FIN, gap)
        stop = (w * gap <= tol) | (depth >= max_depth) | (w < 1e-300)
        if 2 * int((~stop).sum()) > max_nodes:
            stop[:] = True
        idx = np.flatnonzero(stop)
        if idx.size:  # (nothing stopped: the sums would add +0.0 to sums that start at +0.0, unchanged)
            w_stop = w[idx]
            LOs = LO.take(idx, axis=1)
            HIc = np.where(FIN.take(idx, axis=1), HI.take(idx, axis=1), capv)  # the capped upper ends
            for i in range(K):
                lo_sum[i] += np.einsum("b,bij->ij", w_stop, LOs[i].reshape(-1, 1, 1))
                hi_sum[i] += np.einsum("b,bij->ij", w_stop, HIc[i].reshape(-1, 1, 1))
        go = np.flatnonzero(~stop)
        if not go.size:
            break
        kept, w = cols.take(go, axis=1), w[go]
        m = go.size
        cols = np.empty((kept.shape[0] + 1, 2 * m), dtype=np.int8)  # children: γ = 1 then γ = 0, one step older
        cols[0, :m], cols[0, m:] = 1, 0
        cols[1:, :m], cols[1:, m:] = kept, kept
        w = np.concatenate([w * lam, w * (1 - lam)])
        depth += 1
    return lo_sum, hi_sum


def exact_mean(s: LinearSystem, lam: float, lag: int | None, *, tol: float = 1e-9, max_depth: int = 400,
               max_nodes: int = 400_000) -> ExactMean:
    """Stationary E[P_{k|k−1}] (``lag=None``) or E[P_{k|k+N}] (lag N ≥ 0) under i.i.d. loss, C invertible.

    Decomposition over the last arrival (Bernoulli): with j losses since it,
    P_{k|k−1} = hʲ(g(P')) with P' ~ the stationary law, independent of j, and hʲ affine, so
        E[P_{k|k−1}] = V + (1−λ) W,  V = λ E[g(P)] + (1−λ) A V Aᵀ,  W = Q + (1−λ) A W Aᵀ,
    finite iff (1−λ) ρ(A)² < 1, i.e. λ > λ_c (Lemma 1's threshold). E[g(P)] is the expectation of a
    bounded (g ≤ M̄) monotone function, bracketed by enumeration. For the smoother,
    P_{k|k+N} = (P⁻¹ + J(f))⁻¹ ≤ J(f)⁻¹ is bounded whenever f has an arrival, and equals P_{k|k−1}
    when f is all losses (probability (1−λ)^{N+1}). ``tol`` bounds each bracket's trace width
    contribution per node (the total width is reported in ``upper − lower``).
    """
    if not 0 < lam < 1:
        raise ConfigError.at("analysis.lambdas", f"arrival rates must be in (0, 1) for the exact mean, got {lam}")
    if lag is not None and not 0 <= lag <= MAX_MEAN_LAG:
        raise ConfigError.at("analysis.lags", f"the exact mean enumerates 2^(N+1) future patterns: N must be in 0..{MAX_MEAN_LAG}, got {lag}")
    Mbar = leong_mbar(s)
    bt = _Batch(s)
    A, Q = s.A, s.Q
    a2 = (1 - lam) * float(np.max(np.abs(np.linalg.eigvals(A)))) ** 2
    inf = np.full((s.n, s.n), np.inf)

    def phi_g(P_lo, Y_hi):
        lo = bt.cov_step(P_lo, np.ones(P_lo.shape[0]))
        if bt.scalar:
            hi = bt.a2 / (Y_hi + bt.crc) + bt.q
        else:
            hi = bt.sym(A @ np.linalg.solve(Y_hi + bt.CRC, np.broadcast_to(A.T, Y_hi.shape)) + Q)
        return lo, hi

    phis, caps, wts, Js = [phi_g], [Mbar], [1.0 if a2 < 1 else 0.0], []
    futs = [] if lag is None else [f for f in itertools.product((0, 1), repeat=lag + 1) if any(f)]
    for f in futs:
        J = _future_information_cached(s, f)
        pf = lam ** sum(f) * (1 - lam) ** (len(f) - sum(f))

        def phi_f(P_lo, Y_hi, f=f, J=J):
            if bt.scalar:
                return bt.smoothed(P_lo, f), 1.0 / (Y_hi + J)
            return bt.smoothed(P_lo, f), bt.sym(np.linalg.inv(Y_hi + J))

        phis.append(phi_f)
        caps.append(np.linalg.inv(J))
        wts.append(pf)
        Js.append(float(J[0, 0]) if bt.scalar else None)
    if bt.scalar and _compiled_module() is not None:  # the same φ compiled (the same bits)
        lo_s, hi_s = _expect_bounded_scalar(Js, caps, wts, bt, lam, tol, max_depth, max_nodes)
    else:
        lo_s, hi_s = _expect_bounded(phis, caps, wts, bt, lam, tol, max_depth, max_nodes)
    if a2 >= 1:
        Ep = (inf, inf)
    else:
        As = math.sqrt(1 - lam) * A
        W = scipy.linalg.solve_discrete_lyapunov(As, Q)
        Ep = tuple(riccati.sym(scipy.linalg.solve_discrete_lyapunov(As, lam * Eg) + (1 - lam) * W) for Eg in (lo_s[0], hi_s[0]))
    if lag is None:
        return ExactMean(*Ep)
    out = []
    for b, sums in enumerate((lo_s, hi_s)):
        tot = (1 - lam) ** (lag + 1) * Ep[b]
        for i, f in enumerate(futs):
            tot = tot + wts[i + 1] * sums[i + 1]
        out.append(tot)
    return ExactMean(out[0], out[1])


# --------------------------------------------------------------------------------------------
# Retransmission (Sec. V)
# --------------------------------------------------------------------------------------------


def retransmission_f(n_max: int, N: int, p) -> list:
    """f(0 … n_max) of eq. (10): total decision-probability of the ways to produce n successive 0's.

    Works with floats or :class:`fractions.Fraction` (exact arithmetic).
    """
    one = p * 0 + 1
    f = []

    def F(i):
        return f[i] if i >= 0 else 0 * one

    for n in range(n_max + 1):
        if n == 0:
            f.append(one)
            continue
        total = 0 * one
        for j in range(N):  # ask j times, all fail, then stop asking: p^j (1−p) f(n−j−1)
            total += p**j * (1 - p) * F(n - j - 1)
        total += p**N * F(n - N - 1)  # asked N times, all failed
        f.append(total)
    return f


def retransmission_g(n_max: int, N: int, p) -> list:
    """g(n) = f(n) + p f(n−1) + … + pᴺ f(n−N) (eq. 11); the paper shows g(n) = 1."""
    f = retransmission_f(n_max, N, p)
    return [sum((p**i * f[n - i] for i in range(N + 1) if n - i >= 0), 0 * p) for n in range(n_max + 1)]


def enumerate_retransmission_ways(n: int, N: int, p) -> list[tuple[str, object]]:
    """Every way the random-retransmission scheme produces "1 followed by n 0's", with its
    decision probability (channel factors λ(1−λ)ⁿ excluded, as in the paper's n = 3, N = 2 example).

    Brute force over events: the first measurement arrives after r ∈ {0 … N} retransmissions
    (weight pʳ, occupies 1 + r positions, the r discarded slots read as 0); each later block is
    a lost measurement retransmitted j times without success (1 + j positions), weight
    pʲ(1 − p) if it then stops asking (j < N), pᴺ if the budget is exhausted (j = N).
    Symbols: ``1``/``0`` original, ``R1``/``R0`` a retransmission's outcome, ``*`` "did not ask".
    """
    ways: list[tuple[str, object]] = []

    def zeros(rem: int, prefix: str, w):
        if rem == 0:
            ways.append((prefix, w))
            return
        for j in range(0, N + 1):
            if 1 + j > rem:
                break
            if j < N:
                sym_ = "0" + "R0" * j + "*"
                wj = p**j * (1 - p)
            else:
                sym_ = "0" + "R0" * N
                wj = p**N
            zeros(rem - 1 - j, prefix + " " + sym_, w * wj)

    for r in range(0, N + 1):
        if r > n:
            break
        head = "1" if r == 0 else "0" + "R0" * (r - 1) + "R1"
        zeros(n - r, head, p**r)
    return ways


# --------------------------------------------------------------------------------------------
# Closed-form references for the generic metrics (``analysis.references``, see analysis/references.py)
# --------------------------------------------------------------------------------------------

G_N_MAX = 30
"""Largest n of the g(n) = 1 check (eqs 10–11) in floating point; exact rationals up to 12."""
_CACHE: dict = {}


def _memo(key, fn):
    if key not in _CACHE:
        _CACHE[key] = fn()
    return _CACHE[key]


def _skey(s: LinearSystem) -> tuple:
    return tuple(np.asarray(x, dtype=float).tobytes() for x in (s.A, s.C, s.Q, s.R))


def arrival_chain(ch: dict) -> tuple[np.ndarray, np.ndarray] | None:
    """The 2-state Markov chain (T, π) of the arrival pattern of a channel given as its field dict:
    ``bernoulli`` (and ``retransmission``, whose effective pattern has the law of i.i.d. loss at the
    link's λ — the point of Sec. V), ``gilbert_elliott`` (p_gb, p_bg, or loss_rate + mean burst:
    p_bg = 1/L_B, p_gb = π_B p_bg/(1 − π_B)); None for any other channel."""
    kind = ch.get("kind")
    if kind in ("bernoulli", "retransmission"):
        lam = float(ch["arrival"])
        return np.array([[1 - lam, lam], [1 - lam, lam]]), np.array([1 - lam, lam])
    if kind == "gilbert_elliott":
        if ch.get("p_gb") is not None:
            p_gb, p_bg = float(ch["p_gb"]), float(ch["p_bg"])
        else:
            pi_b = float(ch.get("pi_loss", ch.get("loss_rate")))
            p_bg = 1.0 / float(ch["mean_burst"])
            p_gb = min(1.0, pi_b * p_bg / (1.0 - pi_b))
        lam = p_bg / (p_gb + p_bg)
        return np.array([[1 - p_bg, p_bg], [p_gb, 1 - p_gb]]), np.array([1 - lam, lam])
    return None


def _iid_rate(ch: dict) -> float | None:
    return float(ch["arrival"]) if ch.get("kind") in ("bernoulli", "retransmission") else None


def _m_values(metric: dict) -> list[float]:
    """The M values of a metric's field dict: a scalar, a list, or a grid {start, stop, num, spacing}."""
    M = metric.get("M")
    if M is None:
        return []
    if isinstance(M, dict):
        f = np.geomspace if M.get("spacing", "log") == "log" else np.linspace
        return [float(v) for v in f(M["start"], M["stop"], int(M["num"]))]
    return [float(v) for v in np.atleast_1d(np.asarray(M, dtype=float))]


def _columns(point) -> list[tuple[str, str, int | None]]:
    """(estimator label, quantity, lag) of every reported column the closed forms cover: kf and the
    smoother; ``predicted`` P_{k+1|k} has the stationary law of P_{k|k−1} (lag None), ``filtered`` is
    lag 0, ``smoothed`` the smoother's lag N."""
    out = []
    for e, lab in zip(point.estimators, point.labels):
        if e.get("kind") not in ("kf", "smoother"):
            continue
        for q in point.quantities:
            if q == "predicted":
                out.append((lab, q, None))
            elif q == "filtered":
                out.append((lab, q, 0))
            elif q == "smoothed" and e.get("kind") == "smoother":
                lag = int(e.get("lag", 0))
                if lag > min(MAX_EXACT_LAG, MAX_MEAN_LAG):
                    raise ConfigError.at("analysis.references", f"Leong's closed forms enumerate the 2^(N+1) future "
                                         f"arrival patterns: smoother lags up to {MAX_EXACT_LAG}, got {lag} ({lab})")
                out.append((lab, q, lag))
    return out


def _scalar_system(point) -> LinearSystem:
    """The point's system (its P0 plays no role in a stationary law)."""
    return point.system


def reference_exact(point) -> list[dict]:
    """Leong 2008: exact stationary Pr[P ≤ M] (certified enumeration; i.i.d., retransmission or Gilbert–Elliott loss) and, in a time_average without M on i.i.d. loss, E[tr P] (∞ for λ ≤ λ_c)."""
    s = _scalar_system(point)
    chain = arrival_chain(point.channel)
    if chain is None:
        return []
    T, pi = chain
    rows = []
    ck = (round(float(T[0, 1]), 15), round(float(T[1, 1]), 15))
    for lab, q, lag in _columns(point):
        for m in _m_values(point.metric):
            ex = _memo(("p", _skey(s), ck, lag, m), lambda: exact_probability(s, m, lag, T, pi, tol=SMOOTHING_EXACT_TOL))
            rows.append(dict(series=f"exact, {q}, M = {m:g}", value=ex.value, estimator=lab, quantity=q, M=m))
        lam = _iid_rate(point.channel)
        if point.metric.get("kind") == "time_average" and point.metric.get("M") is None and lam is not None and 0 < lam < 1:
            rows.append(dict(series=f"exact, {q}", value=_exact_trace_mean(s, lam, lag), estimator=lab, quantity=q))
    return rows


def _exact_trace_mean(s: LinearSystem, lam: float, lag: int | None) -> float:
    """tr of the stationary E[P] (midpoint of the certified bracket), ∞ for λ ≤ λ_c."""
    if lam <= critical_rate(s):
        return math.inf

    def f():
        e = exact_mean(s, lam, lag, tol=SMOOTHING_MEAN_TOL)
        return 0.5 * (float(np.trace(e.lower)) + float(np.trace(e.upper)))

    return _memo(("m", _skey(s), lam, lag), f)


def reference_lemma1(point) -> list[dict]:
    """Leong 2008, Lemma 1: E[tr P_{k|k+N}] ≥ (1−λ)^{N+1} E[tr P_{k|k−1}] under i.i.d. loss (so the smoother diverges with the filter at λ_c)."""
    lam = _iid_rate(point.channel)
    if lam is None or not 0 < lam < 1:
        return []
    s = _scalar_system(point)
    rows = []
    for lab, q, lag in _columns(point):
        if q == "smoothed":
            with np.errstate(over="ignore", invalid="ignore"):
                v = (1 - lam) ** (lag + 1) * _exact_trace_mean(s, lam, None)
            rows.append(dict(series="Lemma 1 lower bound (1-λ)^(N+1) E[tr P_k|k-1], smoothed", value=v, estimator=lab, quantity=q))
    return rows


def reference_eq8(point) -> list[dict]:
    """Leong 2008, eqs (7)–(8): the guarantee Pr[P ≤ M] ≥ 1 − (1−λ)^{k₁+N+1} under i.i.d. loss (N = 0 filter, exponent k₁ for P_{k|k−1}; Gilbert–Elliott: at the stationary rate, marked i.i.d. only); needs C invertible and M ≥ M̄."""
    chain = arrival_chain(point.channel)
    if chain is None or point.channel.get("kind") == "retransmission":
        return []
    lam = float(chain[1][1])  # the stationary arrival rate
    iid = "" if point.channel.get("kind") == "bernoulli" else " (i.i.d. loss only)"
    s = _scalar_system(point)
    try:
        Mbar = leong_mbar(s)
    except ConfigError:
        return []
    rows = []
    for m in _m_values(point.metric):
        try:
            kk = k1(s, m, Mbar)
        except (TheoremConditionError, ConfigError):
            continue
        for lab, q, lag in _columns(point):
            e = kk if lag is None else kk + lag + 1
            rule = "1-(1-λ)^k1 of eq. (7)" if lag is None else "1-(1-λ)^(k1+N+1) of eq. (8)"
            rows.append(dict(series=f"guarantee {rule}{iid}, {q}, M = {m:g}", value=1.0 - (1.0 - lam) ** e,
                             estimator=lab, quantity=q, M=m))
    return rows


def reference_retransmission_g(point) -> list[dict]:
    """Leong 2008, Sec. V: max |g(n) − 1| over n ≤ 30 of eqs (10)–(11) for the channel's budget N and p (g(n) = 1: the scheme is distributed like plain filtering)."""
    ch = point.channel
    if ch.get("kind") != "retransmission" or int(ch["budget"]) == 0:
        return []
    g = retransmission_g(G_N_MAX, int(ch["budget"]), float(ch["p"]))
    return [dict(series=f"max |g(n) - 1| over n <= {G_N_MAX}, eq. (11)", value=float(np.max(np.abs(np.asarray(g) - 1.0))))]


def retransmission_g_is_one(n_max: int, N: int, p) -> bool:
    """g(n) = 1 for every n ≤ n_max in exact rational arithmetic (p as a Fraction of denominator ≤ 1000)."""
    return all(v == 1 for v in retransmission_g(n_max, N, Fraction(p).limit_denominator(1000)))
