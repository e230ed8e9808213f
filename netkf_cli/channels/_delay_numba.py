"""Compiled inverse CDF of the delay sampler (optional: imported by :func:`netkf_cli.channels.delay.inverse_cdf`
only where numba is importable). The same bucketed search as the numpy path, fused in one loop:
exactly ``np.searchsorted(table, u, side="right")`` (tested)."""

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
