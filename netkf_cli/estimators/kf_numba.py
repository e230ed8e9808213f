"""Compiled intermittent-observation Kalman filter for :mod:`netkf_cli.estimators.kf` (``backend: numba``).

The same recursion (Sinopoli 2004, eqs. 8–9). Runs are processed in blocks of ``BLOCK`` runs
(``prange`` over blocks); inside a block the time loop is outer and the run loop innermost
over entry-major local arrays, which LLVM vectorizes (design.md's layout). A lost packet
multiplies the correction by γ = 0 (branch-free). A run whose predicted covariance passes the
overflow limit is flagged and recomputed by the numpy reference (its information-form
update), so the compiled path never returns a cancelled or NaN covariance. Agreement with
numpy is to rounding (another operation order), tested.
"""

from __future__ import annotations

BLOCK = 128
_KERNEL = None


def kernel():
    """The compiled ``advance`` (compiled on first use, cached on disk)."""
    global _KERNEL
    if _KERNEL is None:
        _KERNEL = _build()
    return _KERNEL


def _build():
    import numpy as np
    from numba import njit, prange

    @njit(parallel=True, cache=True, error_model="numpy", boundscheck=False, fastmath=False)
    def advance(P, gam, A, C, Q, R, t0, t1, limit, flag):  # pragma: no cover - compiled
        n = A.shape[0]
        m = C.shape[0]
        runs = P.shape[2]
        nblocks = (runs + BLOCK - 1) // BLOCK
        for blk in prange(nblocks):
            r0 = blk * BLOCK
            B = min(BLOCK, runs - r0)
            X = np.empty((n, n, B))
            T = np.empty((n, n, B))
            Pp = np.empty((n, n, B))
            CP = np.empty((m, n, B))
            S = np.empty((m, m, B))
            K = np.empty((m, n, B))
            g = np.empty(B)
            for i in range(n):
                for j in range(n):
                    for b in range(B):
                        X[i, j, b] = P[i, j, r0 + b]
            for t in range(t0, t1):
                for b in range(B):
                    g[b] = 1.0 if gam[t, r0 + b] else 0.0
                # T = A X
                for i in range(n):
                    for j in range(n):
                        for b in range(B):
                            T[i, j, b] = 0.0
                        for k in range(n):
                            a = A[i, k]
                            if a != 0.0:
                                for b in range(B):
                                    T[i, j, b] += a * X[k, j, b]
                # Pp = T Aᵀ + Q (upper triangle, mirrored)
                for i in range(n):
                    for j in range(i, n):
                        for b in range(B):
                            Pp[i, j, b] = Q[i, j]
                        for k in range(n):
                            a = A[j, k]
                            if a != 0.0:
                                for b in range(B):
                                    Pp[i, j, b] += T[i, k, b] * a
                        if j > i:
                            for b in range(B):
                                Pp[j, i, b] = Pp[i, j, b]
                # CP = C Pp, S = CP Cᵀ + R
                for a_ in range(m):
                    for j in range(n):
                        for b in range(B):
                            CP[a_, j, b] = 0.0
                        for k in range(n):
                            c = C[a_, k]
                            if c != 0.0:
                                for b in range(B):
                                    CP[a_, j, b] += c * Pp[k, j, b]
                for a_ in range(m):
                    for c_ in range(m):
                        for b in range(B):
                            S[a_, c_, b] = R[a_, c_]
                        for k in range(n):
                            c = C[c_, k]
                            if c != 0.0:
                                for b in range(B):
                                    S[a_, c_, b] += CP[a_, k, b] * c
                # K = S⁻¹ CP (Gauss–Jordan, S SPD: no pivoting), per run, run axis innermost
                for a_ in range(m):
                    for j in range(n):
                        for b in range(B):
                            K[a_, j, b] = CP[a_, j, b]
                for a_ in range(m):
                    for b in range(B):
                        piv = 1.0 / S[a_, a_, b]
                        for c_ in range(a_, m):
                            S[a_, c_, b] *= piv
                        for j in range(n):
                            K[a_, j, b] *= piv
                    for a2 in range(m):
                        if a2 != a_:
                            for b in range(B):
                                f = S[a2, a_, b]
                                for c_ in range(a_, m):
                                    S[a2, c_, b] -= f * S[a_, c_, b]
                                for j in range(n):
                                    K[a2, j, b] -= f * K[a_, j, b]
                # X = Pp − γ CPᵀ K (symmetric)
                for i in range(n):
                    for j in range(i, n):
                        for b in range(B):
                            acc = 0.0
                            for a_ in range(m):
                                acc += CP[a_, i, b] * K[a_, j, b]
                            X[i, j, b] = Pp[i, j, b] - g[b] * acc
                        if j > i:
                            for b in range(B):
                                X[j, i, b] = X[i, j, b]
                for b in range(B):
                    tr = 0.0
                    for i in range(n):
                        tr += Pp[i, i, b]
                    if not (tr <= limit):
                        flag[r0 + b] = True
            for i in range(n):
                for j in range(n):
                    for b in range(B):
                        P[i, j, r0 + b] = X[i, j, b]

    return advance
