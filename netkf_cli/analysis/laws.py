"""Discrete laws the closed forms and samplers read, without importing scipy.stats (~20 MB resident and
~0.3 s in every process that loads it: issue 20's 300 MB).

Each function is scipy.stats' on the same arguments, bit for bit (tests/unit/test_laws.py): the same special
function (scipy.special's ``pdtr``; Boost's binomial pmf/cdf, which scipy.stats.binom itself calls through
``scipy.special._ufuncs``) behind the same support and argument rules.
"""

from __future__ import annotations

import numpy as np
from scipy import special
from scipy.special import _ufuncs

__all__ = ["poisson_cdf", "binom_pmf", "binom_cdf"]


def poisson_cdf(i, mu: float):
    """F(i) = Σ_{j ≤ i} μʲ e^{−μ} / j! of Poisson delays (Shi et al. eq. 3, Example 3.10): ``scipy.special.pdtr``
    at ⌊i⌋, 0 below the support, 1 at +∞, NaN for a NaN i or μ < 0 — what ``scipy.stats.poisson.cdf`` computes."""
    k = np.asarray(i)
    out = np.zeros(k.shape, dtype=float)
    if not float(mu) >= 0.0:
        out[...] = np.nan
        return out[()] if out.ndim == 0 else out
    if k.dtype.kind == "f":
        out[np.isposinf(k)] = 1.0
        out[np.isnan(k)] = np.nan
        good = (k >= 0) & np.isfinite(k)
    else:
        good = k >= 0
    if np.any(good):
        out[good] = np.clip(special.pdtr(np.floor(k[good]), float(mu)), 0, 1)
    return out[()] if out.ndim == 0 else out


def _binom_args(k, n, p):
    k, n, p = np.broadcast_arrays(np.asarray(k, dtype=float), np.asarray(n, dtype=float), np.asarray(p, dtype=float))
    ok = (n >= 0) & (np.floor(n) == n) & (p >= 0) & (p <= 1)  # scipy.stats.binom's argcheck (NaN: not ok)
    return k, n, p, ok


def binom_pmf(k, n, p):
    """Pr[ℓ = k] of ℓ ~ Binomial(n, p): C(n, k) pᵏ (1 − p)ⁿ⁻ᵏ (Boost's ``binom_pdf``), 0 off the support
    {0, …, n} and at a non-integer k, NaN for n not a non-negative integer or p ∉ [0, 1] — scipy.stats.binom.pmf."""
    k, n, p, ok = _binom_args(k, n, p)
    out = np.zeros(k.shape)
    out[~ok | np.isnan(k)] = np.nan
    cond = ok & (k >= 0) & (k <= n) & (np.floor(k) == k)
    if np.any(cond):
        out[cond] = np.clip(_ufuncs._binom_pmf(k[cond], n[cond], p[cond]), 0, 1)
    return out[()] if out.ndim == 0 else out


def binom_cdf(k, n, p):
    """Pr[ℓ ≤ k] of ℓ ~ Binomial(n, p) (Boost's ``binom_cdf`` at ⌊k⌋): 0 below 0, 1 from n on, NaN for a NaN k,
    n not a non-negative integer or p ∉ [0, 1] — scipy.stats.binom.cdf."""
    k, n, p, ok = _binom_args(k, n, p)
    out = np.zeros(k.shape)
    out[(k >= n) & ok] = 1.0
    out[~ok | np.isnan(k)] = np.nan
    cond = ok & (k >= 0) & (k < n) & np.isfinite(k)
    if np.any(cond):
        out[cond] = np.clip(_ufuncs._binom_cdf(np.floor(k[cond]), n[cond], p[cond]), 0, 1)
    return out[()] if out.ndim == 0 else out
