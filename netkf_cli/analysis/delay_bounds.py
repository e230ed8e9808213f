"""Closed forms of Shi, Xie & Murray 2009 for a receive buffer of length D.

* γ̂_i(D) = F(min(i, D_max))  with D_max the largest kept delay (eq. 4; D_max = D − 1 under
  ``delay_lt_D``, D under ``delay_le_D``) — Pr[γ_{k−i} = 1].
* θ(k, D) = ∏_{j=0}^{k−1} (1 − γ̂_j(D))  = Pr[N_k ≥ k]                        (eqs 8–9)
* k₁(M) = min{t ≥ 1 : hᵗ(M̄) ≰ M},  k₂(M) = min{t ≥ 1 : hᵗ(P̄) ≰ M}          (eqs 5–6)
* 1 − θ(k₁, D) ≤ Pr[P_k ≤ M] ≤ 1 − θ(k₂, D)                                  (Thm 3.8, eq. 10)
* smart sensor: Pr[P_k ≤ M] = 1 − θ(k₂, D)                                     (Thm 4.1, eq. 11)
* minimum buffers D_s, D_n (Sec. 3.4) and D* (Sec. 4) by binary search (Remark 3.9).

``k = math.inf`` means hᵗ(·) ≤ M for every t (possible for stable A); then θ(∞, D) is the
probability that no packet ever arrives, 0 whenever F(D_max) > 0.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from netkf_cli.linalg import riccati
from netkf_cli.core.errors import TheoremConditionError
from netkf_cli.core.system import LinearSystem
from netkf_cli.core.tolerances import PSD_TOL

Convention = Literal["delay_le_D", "delay_lt_D"]
DEFAULT_CONVENTION: Convention = "delay_le_D"
CONVENTION_HELP = {
    "delay_le_D": "a packet is kept iff its delay d_k ≤ D (Example 3.10, Sec. 3.4, the paper's figures)",
    "delay_lt_D": "a packet is kept iff its delay d_k < D, i.e. d_k ≥ D is discarded (Sec. 2.3, eq. 4)",
}
"""The buffer convention (which delays the estimator keeps): the paper is not self-consistent (Sec. 2.3 /
eq. 4 vs Example 3.10's printed numbers; ``experiments/shi2009/README.md``)."""


def max_kept_delay(D: int, convention: Convention) -> int:
    """The largest delay the buffer keeps: D under ``delay_le_D``, D − 1 under ``delay_lt_D``."""
    return D if convention == "delay_le_D" else D - 1

K_MAX = 100_000  # iterations of h before declaring hᵗ(X) ≤ M for all t

Cdf = Callable[[np.ndarray], np.ndarray]


def as_matrix_bound(M, n: int) -> np.ndarray:
    """A scalar M means M·Iₙ (Fig. 9: "M means M × I₄"); a matrix is taken as is."""
    M = np.asarray(M, dtype=float)
    if M.ndim == 0:
        return float(M) * np.eye(n)
    return np.atleast_2d(M)


def gamma_hat(cdf: Cdf, i: np.ndarray | int, D: int, convention: Convention) -> np.ndarray:
    """γ̂_i(D) = Pr[y_{k−i} received and kept by time k] (eq. 4 under the chosen convention)."""
    i = np.asarray(i)
    return np.asarray(cdf(np.minimum(i, max_kept_delay(D, convention))), dtype=float)


def theta(k: float, D: int, cdf: Cdf, convention: Convention) -> float:
    """θ(k, D) = ∏_{j=0}^{k−1} (1 − γ̂_j(D)) (eq. 8): probability of k consecutive misses."""
    if D < 1:
        raise ValueError(f"buffer length D must be ≥ 1, got {D}")
    if k <= 0:
        return 1.0
    Dmax = max_kept_delay(D, convention)
    if math.isinf(k):
        # factors are constant (1 − F(D_max)) for j ≥ D_max: the infinite product is 0 unless F(D_max) = 0
        return 0.0 if float(cdf(np.asarray(Dmax))) > 0 else float(np.prod(1 - gamma_hat(cdf, np.arange(max(Dmax, 0) + 1), D, convention)))
    j = np.arange(int(k))
    factors = 1.0 - gamma_hat(cdf, j, D, convention)
    return float(np.prod(factors))


def saturation_D(k: float, convention: Convention) -> int:
    """The D beyond which θ(k, D) no longer changes: k − 1 (``delay_le_D``) or k (``delay_lt_D``)."""
    if math.isinf(k):
        return 1
    return max(1, int(k) - 1) if convention == "delay_le_D" else max(1, int(k))


def theta_floor(k: float, cdf: Cdf, convention: Convention) -> float:
    """lim_{D→∞} θ(k, D): the smallest ε any buffer can guarantee (Sec. 3.4)."""
    return theta(k, saturation_D(k, convention), cdf, convention)


class Orbit:
    """The orbit hᵗ(X0), t = 0, 1, … of eqs (5)–(6), computed once and kept: k₁(M) and k₂(M) walk the same
    orbit (of M̄, of P̄) at every M of a grid, so each point, and whether it equals its predecessor to
    rounding (the walk's stop for a stable A), is computed once per system instead of once per M."""

    def __init__(self, X0: np.ndarray, s: LinearSystem):
        self.s = s
        self.points = [np.asarray(X0)]
        self.converged = [False]  # converged[t]: hᵗ(X0) allclose to hᵗ⁻¹(X0)

    def point(self, t: int) -> np.ndarray:
        """hᵗ(X0) (t ≥ 0), extending the orbit as needed."""
        while len(self.points) <= t:
            X = self.points[-1]
            Xn = riccati.h(X, self.s)
            self.converged.append(bool(np.allclose(Xn, X, rtol=1e-13, atol=1e-15)))
            self.points.append(Xn)
        return self.points[t]


_ORBITS: dict = {}
"""Orbits by (X0, A, Q): a grid of M, and the points of an ``over`` grid that share the system, reuse them."""


def orbit(X0: np.ndarray, s: LinearSystem) -> Orbit:
    """The kept :class:`Orbit` of X0 under h (h reads A and Q only)."""
    key = tuple((np.shape(x), np.asarray(x, dtype=float).tobytes()) for x in (X0, s.A, s.Q))
    orb = _ORBITS.get(key)
    if orb is None:
        if len(_ORBITS) >= 64:
            _ORBITS.clear()
        orb = _ORBITS[key] = Orbit(np.array(X0, dtype=float), s)
    return orb


def leq_each(X: np.ndarray, Ms: np.ndarray, tol: float = PSD_TOL) -> np.ndarray:
    """``riccati.psd_leq(X, M)`` for every M of the stack ``Ms`` (K, n, n), each with its own scale
    max(1, |M|) (one batched eigvalsh; ``psd_leq`` on the stack would scale all by the largest M)."""
    Ms = np.asarray(Ms, dtype=float)
    D = Ms - np.asarray(X, dtype=float)
    finite = np.all(np.isfinite(D), axis=(-1, -2))
    D = np.where(finite[..., None, None], D, 0.0)
    emin = D[..., 0, 0] if D.shape[-1] == 1 else np.linalg.eigvalsh(riccati.sym(D))[..., 0]
    scale = np.maximum(1.0, np.abs(Ms).max(axis=(-1, -2)))
    return finite & (emin >= -tol * scale)


def first_exceedances(X0: np.ndarray, Ms: np.ndarray, s: LinearSystem, k_max: int = K_MAX) -> np.ndarray:
    """min{t ≥ 1 : hᵗ(X0) ≰ M} for every M of the stack ``Ms`` (K, n, n), ``math.inf`` where hᵗ(X0) ≤ M for all t
    (eqs 5–6): one walk along the kept :func:`orbit`, each point compared with the M not yet exceeded; the
    walk stops once the orbit has converged (stable A) below them."""
    orb = orbit(X0, s)
    Ms = np.asarray(Ms, dtype=float)
    out = np.full(len(Ms), math.inf)
    pending = np.arange(len(Ms))
    for t in range(1, k_max + 1):
        if not pending.size:
            break
        ok = leq_each(orb.point(t), Ms[pending])
        out[pending[~ok]] = t
        pending = pending[ok]
        if orb.converged[t]:
            break  # converged without exceeding the rest: inf
    return out


def first_exceedance(X0: np.ndarray, M: np.ndarray, s: LinearSystem, k_max: int = K_MAX) -> float:
    """min{t ≥ 1 : hᵗ(X0) ≰ M}, or ``math.inf`` when hᵗ(X0) ≤ M for all t (eqs 5–6)."""
    return float(first_exceedances(X0, np.asarray(M, dtype=float)[None], s, k_max)[0])


def k1(M, s: LinearSystem, path: str = "M") -> float:
    """k₁(M) = min{t ≥ 1 : hᵗ(M̄) ≰ M} (eq. 5). Requires M ≥ M̄ (Thm 3.8)."""
    return float(k1_each([M], s, [path])[0])


def k2(M, s: LinearSystem, path: str = "M") -> float:
    """k₂(M) = min{t ≥ 1 : hᵗ(P̄) ≰ M} (eq. 6). Requires M ≥ P̄ (Thm 4.1)."""
    return float(k2_each([M], s, [path])[0])


def k1_each(Ms, s: LinearSystem, paths=None) -> np.ndarray:
    """k₁(M) (eq. 5) at every M of ``Ms`` (scalars mean M·Iₙ), along one orbit; each must be ≥ M̄ (Thm 3.8)."""
    return _k_each(Ms, s, riccati.mbar(s), "M̄", "Thm 3.8 needs M ≥ M̄", paths)


def k2_each(Ms, s: LinearSystem, paths=None) -> np.ndarray:
    """k₂(M) (eq. 6) at every M of ``Ms`` (scalars mean M·Iₙ), along one orbit; each must be ≥ P̄ (Thm 4.1)."""
    return _k_each(Ms, s, riccati.pbar(s), "P̄", "Thm 4.1 needs M ≥ P̄", paths)


def _k_each(Ms, s: LinearSystem, X0: np.ndarray, name: str, why: str, paths) -> np.ndarray:
    Mm = np.array([as_matrix_bound(M, s.n) for M in Ms], dtype=float).reshape(-1, s.n, s.n)
    bad = np.flatnonzero(~leq_each(X0, Mm))
    if bad.size:
        i = int(bad[0])
        require_at_least(Mm[i], X0, name, why, paths[i] if paths is not None else "M")
    return first_exceedances(X0, Mm, s)


def _fmt(X: np.ndarray) -> str:
    if X.size == 1:
        return f"{float(X.ravel()[0]):.6g}"
    return "[" + "; ".join(" ".join(f"{v:.4g}" for v in row) for row in X) + "]"


def require_at_least(M: np.ndarray, lower: np.ndarray, name: str, why: str, path: str) -> None:
    if not bool(riccati.psd_leq(lower, M)):
        raise TheoremConditionError.at(
            path, f"must satisfy M ≥ {name} = {_fmt(lower)} ({why}), got M = {_fmt(M)}"
        )


def bounds(M, D: int, s: LinearSystem, cdf: Cdf, convention: Convention, path: str = "M") -> tuple[float, float]:
    """(1 − θ(k₁, D), 1 − θ(k₂, D)): lower and upper bounds on Pr[P_k ≤ M] (Thm 3.8)."""
    return 1 - theta(k1(M, s, path), D, cdf, convention), 1 - theta(k2(M, s, path), D, cdf, convention)


def smart_sensor_probability(M, D: int, s: LinearSystem, cdf: Cdf, convention: Convention, path: str = "M") -> float:
    """Pr[P_k ≤ M] = 1 − θ(k₂, D) for a sensor that sends its own estimate (Thm 4.1, eq. 11)."""
    return 1 - theta(k2(M, s, path), D, cdf, convention)


def min_buffer(k: float, eps: float, cdf: Cdf, convention: Convention, D_max: int | None = None) -> int | None:
    """min{D ≥ 1 : θ(k, D) ≤ ε} by binary search (Remark 3.9); ``None`` when no D achieves it.

    θ(k, ·) is non-increasing and constant beyond :func:`saturation_D`, so the search runs
    over [1, saturation_D(k)]. With ``D_max`` the answer is also ``None`` if it exceeds D_max
    (:func:`size_buffer` keeps both answers apart: :attr:`BufferSizing.reason`).
    """
    hi = saturation_D(k, convention)
    if theta(k, hi, cdf, convention) > eps:
        return None
    lo = 1
    while lo < hi:
        mid = (lo + hi) // 2
        if theta(k, mid, cdf, convention) <= eps:
            hi = mid
        else:
            lo = mid + 1
    if D_max is not None and lo > D_max:
        return None
    return lo


@dataclass(frozen=True)
class BufferSizing:
    """Everything ``netkf mind`` reports (Sec. 3.4 and Sec. 4)."""

    M: float | list
    eps: float
    sensor: str
    convention: Convention
    mbar: np.ndarray
    pbar: np.ndarray
    k1: float | None
    k2: float
    theta_floor_1: float | None
    theta_floor_2: float
    D_s: int | None
    D_n: int | None
    D_star: int | None
    D_max: int | None = None
    """The cap (``--D-max``): D_s, D_n, D* are ``None`` above it; the ``*_uncapped`` fields are not."""
    D_s_uncapped: int | None = None
    D_n_uncapped: int | None = None
    D_star_uncapped: int | None = None

    @property
    def feasible(self) -> bool:
        """Some D ≤ D_max meets the requirement (D_s for raw measurements, D* for a smart sensor)."""
        return (self.D_star if self.sensor == "smart" else self.D_s) is not None

    @property
    def feasible_uncapped(self) -> bool:
        """Some finite D meets it: θ(k, D → ∞) ≤ ε, k = k₁ (raw, Thm 3.8) or k₂ (smart, Thm 4.1)."""
        return (self.D_star_uncapped if self.sensor == "smart" else self.D_s_uncapped) is not None

    @property
    def reason(self) -> str | None:
        """Why :attr:`feasible` is false: ``"above_D_max"`` (a finite D does it, only longer than D_max)
        or ``"theta_floor"`` (θ(k, D → ∞) > ε: no finite D); ``None`` when feasible."""
        if self.feasible:
            return None
        return "above_D_max" if self.feasible_uncapped else "theta_floor"


def _capped(D: int | None, D_max: int | None) -> int | None:
    return None if D is None or (D_max is not None and D > D_max) else D


def size_buffer(M, eps: float, s: LinearSystem, cdf: Cdf, convention: Convention, sensor: str = "raw",
                D_max: int | None = None, path: str = "M") -> BufferSizing:
    """Minimum buffer lengths for Pr[P_k ≤ M] ≥ 1 − ε: D_s, D_n (raw, Sec. 3.4) or D* (smart, Sec. 4),
    each both as found and capped at ``D_max`` (``None`` above it)."""
    Pb = riccati.pbar(s)
    if sensor == "raw":
        Mb = riccati.mbar(s)
        kk1 = k1(M, s, path)  # checks M ≥ M̄ first: the condition Thm 3.8 states
        kk2 = k2(M, s, path)
        D_s = min_buffer(kk1, eps, cdf, convention)
        D_n = min_buffer(kk2, eps, cdf, convention)
        return BufferSizing(M, eps, sensor, convention, Mb, Pb, kk1, kk2, theta_floor(kk1, cdf, convention),
                            theta_floor(kk2, cdf, convention), _capped(D_s, D_max), _capped(D_n, D_max), None,
                            D_max, D_s, D_n, None)
    kk2 = k2(M, s, path)
    D_star = min_buffer(kk2, eps, cdf, convention)
    Mb = riccati.mbar(s) if _has_mbar(s) else np.full_like(Pb, np.nan)
    return BufferSizing(M, eps, sensor, convention, Mb, Pb, None, kk2, None, theta_floor(kk2, cdf, convention),
                        None, None, _capped(D_star, D_max), D_max, None, None, D_star)


def _has_mbar(s: LinearSystem) -> bool:
    try:
        riccati.mbar(s)
        return True
    except Exception:
        return False
