"""The Kalman core compiled: the primitives of :mod:`netkf_cli.kalman` on one run's small matrices.

Compiled kernels (numba) loop over runs outside and time inside, holding one run's covariance as a
small ``(n, n)`` work array; these functions are the same equations as the numpy core, written
entry by entry and inlined into every kernel (``inline="always"``), so a compiled kernel never
writes its own Kalman gain. ``tests/unit/test_kalman_core.py`` checks each against the numpy core
on random systems. Import this module only where numba is importable (it is optional).

    predict   out = A P Aᵀ + Q
    update    out = P − γ P Cᵀ (C P Cᵀ + R)⁻¹ C P             (optimal gain, any m: Gauss–Jordan)
    joseph    out = (I − γKC) P (I − γKC)ᵀ + γ K R Kᵀ        (any gain)
    smooth    out = Pf + J (Ps − Pp) Jᵀ, J = Pf Aᵀ Pp⁻¹      (RTS step)
"""

from __future__ import annotations

import numba as nb
import numpy as np

_opts = dict(cache=True, nogil=True, inline="always")


@nb.njit(**_opts)
def sym(P):
    n = P.shape[0]
    for i in range(n):
        for j in range(i + 1, n):
            v = 0.5 * (P[i, j] + P[j, i])
            P[i, j] = v
            P[j, i] = v


@nb.njit(**_opts)
def predict(P, A, Q, out, tmp):
    """out = A P Aᵀ + Q (``tmp`` an n×n work array)."""
    n = P.shape[0]
    for i in range(n):
        for j in range(n):
            acc = 0.0
            for k in range(n):
                acc += A[i, k] * P[k, j]
            tmp[i, j] = acc
    for i in range(n):
        for j in range(i, n):
            acc = Q[i, j]
            for k in range(n):
                acc += tmp[i, k] * A[j, k]
            out[i, j] = acc
            out[j, i] = acc


@nb.njit(**_opts)
def solve_inplace(S, B):
    """B ← S⁻¹ B for a small (m, m) S (destroyed) and (m, k) B: Gauss–Jordan with partial pivoting
    (closed form for m = 1)."""
    m = S.shape[0]
    k = B.shape[1]
    if m == 1:
        inv = 1.0 / S[0, 0]
        for c in range(k):
            B[0, c] *= inv
        return
    for col in range(m):
        piv = col
        best = abs(S[col, col])
        for r in range(col + 1, m):
            if abs(S[r, col]) > best:
                best = abs(S[r, col])
                piv = r
        if piv != col:
            for c in range(m):
                t = S[col, c]
                S[col, c] = S[piv, c]
                S[piv, c] = t
            for c in range(k):
                t = B[col, c]
                B[col, c] = B[piv, c]
                B[piv, c] = t
        d = 1.0 / S[col, col]
        for c in range(m):
            S[col, c] *= d
        for c in range(k):
            B[col, c] *= d
        for r in range(m):
            if r != col:
                f = S[r, col]
                if f != 0.0:
                    for c in range(m):
                        S[r, c] -= f * S[col, c]
                    for c in range(k):
                        B[r, c] -= f * B[col, c]


@nb.njit(**_opts)
def update(P, C, R, gamma, out, PCt, S, X):
    """out = P − γ P Cᵀ S⁻¹ C P, S = C P Cᵀ + R; work arrays PCt (n, m), S (m, m), X (m, n)."""
    n = P.shape[0]
    m = C.shape[0]
    if gamma == 0.0:
        for i in range(n):
            for j in range(n):
                out[i, j] = P[i, j]
        return
    for i in range(n):
        for a in range(m):
            acc = 0.0
            for k in range(n):
                acc += P[i, k] * C[a, k]
            PCt[i, a] = acc
    for a in range(m):
        for b in range(m):
            acc = R[a, b]
            for k in range(n):
                acc += C[a, k] * PCt[k, b]
            S[a, b] = acc
        for j in range(n):
            X[a, j] = PCt[j, a]  # C P
    solve_inplace(S, X)  # S⁻¹ C P
    for i in range(n):
        for j in range(i, n):
            acc = 0.0
            for a in range(m):
                acc += PCt[i, a] * X[a, j]
            v = P[i, j] - gamma * acc
            w = P[j, i] - gamma * acc
            out[i, j] = 0.5 * (v + w)
            out[j, i] = out[i, j]


@nb.njit(**_opts)
def joseph(P, K, C, R, gamma, out, IKC, tmp):
    """out = (I − γKC) P (I − γKC)ᵀ + γ K R Kᵀ; work arrays IKC (n, n), tmp (n, n)."""
    n = P.shape[0]
    m = C.shape[0]
    for i in range(n):
        for j in range(n):
            acc = 0.0
            for a in range(m):
                acc += K[i, a] * C[a, j]
            IKC[i, j] = (1.0 if i == j else 0.0) - gamma * acc
    for i in range(n):
        for j in range(n):
            acc = 0.0
            for k in range(n):
                acc += IKC[i, k] * P[k, j]
            tmp[i, j] = acc
    for i in range(n):
        for j in range(i, n):
            acc = 0.0
            for k in range(n):
                acc += tmp[i, k] * IKC[j, k]
            if gamma != 0.0:
                for a in range(m):
                    for b in range(m):
                        acc += gamma * K[i, a] * R[a, b] * K[j, b]
            out[i, j] = acc
            out[j, i] = acc


def work(n: int, m: int) -> tuple[np.ndarray, ...]:
    """Work arrays for :func:`predict` / :func:`update`: (tmp n×n, PCt n×m, S m×m, X m×n)."""
    return np.empty((n, n)), np.empty((n, m)), np.empty((m, m)), np.empty((m, n))
