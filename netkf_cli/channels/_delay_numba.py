"""Compiled loops of the delay channel (optional: imported by :mod:`netkf_cli.channels.delay` and
:func:`netkf_cli.estimators.buffered.mkf_runs` only where numba is importable).

* :func:`inverse_cdf` — the same bucketed search as the numpy path, fused in one loop: exactly
  ``np.searchsorted(table, u, side="right")`` (tested);
* :func:`oldest_arrivals` — Prop. 3.1's count: the largest kept delay arriving at each time k, one pass over
  the packets (integers: the same maxima as the numpy passes, tested)."""

from __future__ import annotations

import numba as nb


@nb.njit(cache=True, nogil=True, boundscheck=False)
def inverse_cdf(u, table, lo, amb, K, out):
    """out[i] = #{j : table[j] ≤ u[i]} for flat u ∈ [0, 1): bucket b = ⌊u·K⌋ gives it as lo[b] unless
    the bucket holds a breakpoint (amb[b]), then a binary search."""
    n = table.size
    for i in range(u.size):
        x = u[i]
        b = int(x * K)
        if amb[b]:
            lo_ = 0
            hi_ = n
            while lo_ < hi_:
                m = (lo_ + hi_) >> 1
                if table[m] <= x:
                    lo_ = m + 1
                else:
                    hi_ = m
            out[i] = lo_
        else:
            out[i] = lo[b]


@nb.njit(cache=True, nogil=True, boundscheck=False)
def oldest_arrivals(d, Dmax, out):
    """out[k, r] = max(out[k, r], d_s) over the packets s (row s − 1 of ``d`` (T, runs)) of run r with
    d_s ≤ Dmax that arrive at k = s + d_s ≤ T; ``out`` (T + 1, runs) starts at 0."""
    T, runs = d.shape
    for s in range(T):
        for r in range(runs):
            x = d[s, r]
            if 0 <= x and x <= Dmax and x <= T - 1 - s:  # arrival k = s + 1 + x ≤ T (no overflow for LOST)
                k = s + 1 + x
                if x > out[k, r]:
                    out[k, r] = x
