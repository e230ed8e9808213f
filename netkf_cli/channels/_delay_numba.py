"""Compiled loops of the delay channel (optional: imported by :mod:`netkf_cli.channels.delay` and
:func:`netkf_cli.estimators.buffered.mkf_runs` only where numba is importable).

* :func:`inverse_cdf` — the same bucketed search as the numpy path, fused in one loop: exactly
  ``np.searchsorted(table, u, side="right")`` (tested);
* :func:`oldest_arrival` — Prop. 3.1's count: the largest kept delay arriving at a time k, a vectorized pass per
  delay value (integers: the same maxima as the numpy passes, tested)."""

from __future__ import annotations

import numba as nb
import numpy as np


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
def oldest_arrival(d, Dmax, k, out):
    """out[r] = the largest δ ≤ min(D_max, k − 1) with d[k − 1 − δ, r] = δ (packet s = k − δ, row s − 1 of ``d``
    (T, runs), arrives exactly at k and is kept), 0 when none: Prop. 3.1's count at one time k. ``out`` (runs,)
    int32 starts at 0; a pass per δ, ascending (the last write is the largest), each a compare-and-select over
    the runs that vectorizes (int32 throughout)."""
    runs = out.shape[0]
    for delta in range(min(Dmax, k - 1) + 1):
        row = d[k - 1 - delta]
        m = np.int32(delta)
        for r in range(runs):
            out[r] = m if row[r] == m else out[r]
