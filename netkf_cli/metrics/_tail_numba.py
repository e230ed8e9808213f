"""The tail metric's window log-likelihoods compiled (numba): one pass over a window of arrivals per law.

:func:`netkf_cli.metrics.tail.window_loglik` (numpy) is the reference: its sums run over the window's steps in
order for every run (numpy's sum along axis 0 adds the rows one after the other), and these loops add the same
terms in the same order, so the log-likelihoods are the same bits (tests/critical/test_fast_paths.py). Import only
where numba is importable.
"""

from __future__ import annotations

import numba as nb

_opts = dict(cache=True, nogil=True, error_model="numpy")


@nb.njit(**_opts)
def iid_loglik(win, la, lb, out):
    """out (runs,) ← Σ_t (la[t] if win[t, r] else lb[t]) over the window's steps t in order (independent arrivals:
    la[t] = log P(arrival at t), lb[t] = log P(loss at t))."""
    W, runs = win.shape
    for r in range(runs):
        out[r] = 0.0
    for t in range(W):
        a, b = la[t], lb[t]
        for r in range(runs):
            out[r] += a if win[t, r] else b


@nb.njit(**_opts)
def markov_loglik(win, prev, l11, l10, l01, l00, out):
    """out (runs,) ← Σ_t log T[γ_{t−1}, γ_t] over the window (Gilbert–Elliott chain: l11 = log(1 − p), l10 = log p,
    l01 = log q, l00 = log(1 − q)), γ before the window = ``prev`` (runs,)."""
    W, runs = win.shape
    a = prev.copy()
    for r in range(runs):
        out[r] = 0.0
    for t in range(W):
        for r in range(runs):
            b = win[t, r]
            if a[r]:
                out[r] += l11 if b else l10
            else:
                out[r] += l01 if b else l00
            a[r] = b
