"""Compiled (numba) MKF over the time-k view for the ``buffered`` estimator (Shi 2009, Prop. 3.1).

The kernel is the core's compiled primitives (:mod:`netkf_cli.kalman_numba`, inlined) in a loop:
per run, P ← P_{0|0}; for t = 1 … k: P⁻ = A P Aᵀ + Q (``predict``), P = P⁻ − a_t P⁻Cᵀ(CP⁻Cᵀ + R)⁻¹CP⁻
(``update``) — the same step as :class:`netkf_cli.kalman.Filter` with one packet stream, so the
numbers equal the numpy path to rounding (a test checks it on the same trace). The one overflow
policy (:class:`netkf_cli.kalman.Rescue`) is honoured by flagging: a run whose prior has
tr P⁻ > ``rescue.limit`` (or is non-finite) is left by the kernel and redone by the numpy core
(the caller, ``buffered.buffered_covariances``), so rescued runs are bit for bit the numpy ones.

Runs are independent (``prange`` over runs in the parent process; a serial twin inside executor
worker processes, which already use every core). numba is optional: import this module only where
it is importable (``buffered`` imports it inside a function).
"""

from __future__ import annotations

import multiprocessing

import numba as nb
import numpy as np

from netkf_cli import kalman_numba as kn


def _mkf_body(A, C, Q, R, P0, avail, limit, out, flag, r):
    n = A.shape[0]
    m = C.shape[0]
    P = P0.copy()
    Pm = np.empty((n, n))
    tmp = np.empty((n, n))
    PCt = np.empty((n, m))
    S = np.empty((m, m))
    X = np.empty((m, n))
    for t in range(avail.shape[1]):
        kn.predict(P, A, Q, Pm, tmp)
        tr = 0.0
        for i in range(n):
            tr += Pm[i, i]
        if not (tr <= limit):  # Rescue.flag: the numpy core redoes this run
            flag[r] = True
            return
        kn.update(Pm, C, R, 1.0 if avail[r, t] else 0.0, P, PCt, S, X)
    for i in range(n):
        for j in range(n):
            out[i, j, r] = P[i, j]


_body = nb.njit(cache=True, nogil=True, inline="always")(_mkf_body)


@nb.njit(cache=True, nogil=True, parallel=True)
def _mkf_parallel(A, C, Q, R, P0, avail, limit, out, flag):
    for r in nb.prange(avail.shape[0]):
        _body(A, C, Q, R, P0, avail, limit, out, flag, r)


@nb.njit(cache=True, nogil=True)
def _mkf_serial(A, C, Q, R, P0, avail, limit, out, flag):
    for r in range(avail.shape[0]):
        _body(A, C, Q, R, P0, avail, limit, out, flag, r)


def filtered(A, C, Q, R, P0: np.ndarray, avail: np.ndarray, limit: float, threads: int | None = None):
    """(P_{k|k} (n, n, runs), flagged (runs,) bool) of the MKF over the availabilities ``avail``
    (k, runs) from P0 (n, n). Flagged runs (``Rescue.flag`` fired at some step) are NOT filled: the
    caller redoes them with the numpy core."""
    avail = np.asarray(avail, dtype=bool)
    k, runs = avail.shape
    n = A.shape[0]
    P0 = np.ascontiguousarray(P0, dtype=float)
    out = np.full((n, n, runs), np.nan)
    flag = np.zeros(runs, dtype=bool)
    fn = _mkf_serial if (threads == 1 or multiprocessing.parent_process() is not None) else _mkf_parallel
    fn(A, C, Q, R, P0, np.ascontiguousarray(avail.T), float(limit), out, flag)
    return out, flag
