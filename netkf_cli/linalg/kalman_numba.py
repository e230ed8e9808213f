"""The Kalman core compiled: the primitives of :mod:`netkf_cli.linalg.kalman` on one run's small matrices.

Compiled kernels (numba) loop over runs outside and time inside, holding one run's covariance as a
small ``(n, n)`` work array; these functions are the same equations as the numpy core, written
entry by entry and inlined into every kernel (``inline="always"``), so a compiled kernel never
writes its own Kalman gain. ``tests/unit/test_kalman_core.py`` checks each against the numpy core
on random systems. Import this module only where numba is importable (it is optional).

    predict   out = A P Aᵀ + Q
    update    out = P − γ P Cᵀ (C P Cᵀ + R)⁻¹ C P             (optimal gain, any m: Gauss–Jordan)
    joseph    out = (I − γKC) P (I − γKC)ᵀ + γ K R Kᵀ        (any gain)
    smooth    out = P_{t|t, x_{t+1}} + J Ps Jᵀ, J = Pf Aᵀ (A Pf Aᵀ + Q)⁻¹   (RTS step, conditioning form:
              Pf updated by x_{t+1} = A x_t + w, so no two P-sized numbers are subtracted)
    information_update, update_pinv, predict_csr, filter_advance   (see each function)

Kernels generated per system with the constants inlined (the fast filter path) are in
:mod:`netkf_cli.linalg.kalman_codegen`.
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
    innovation(P, C, R, X, S)  # X = C P, S = C P Cᵀ + R
    for i in range(n):
        for a in range(m):
            PCt[i, a] = X[a, i]  # P Cᵀ (P symmetric)
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


# ----------------------------------------------------------------------------------------------
# appended (issue 19, the smoother): the information-form update of kalman.Rescue and the RTS step
# ----------------------------------------------------------------------------------------------

@nb.njit(**_opts)
def information_update(Pm, info, out, W, Y):
    """out = (Pm⁻¹ + info)⁻¹, symmetrised: :func:`netkf_cli.linalg.kalman.information_update` for one run
    (the information form of the update, ``info`` = C̃ᵀR̃⁻¹C̃; the rescue of :class:`kalman.Rescue`).
    ``Pm`` finite; work arrays W, Y (n, n). A prior singular to working precision (scaled to a unit diagonal,
    σ_min ≤ n·ε·σ_max: :func:`netkf_cli.linalg.kalman.numerically_singular`) gives out = ∞: the run has diverged."""
    n = Pm.shape[0]
    if n > 1:
        for i in range(n):  # scaled to a unit diagonal (kalman.numerically_singular)
            dd = np.sqrt(abs(Pm[i, i])) if Pm[i, i] != 0.0 else 1.0
            Y[i, 0] = dd
        for i in range(n):
            for j in range(n):
                W[i, j] = Pm[i, j] / Y[i, 0] / Y[j, 0]
        sv = np.linalg.svd(W)[1]
        if sv[n - 1] <= sv[0] * n * 2.220446049250313e-16:
            for i in range(n):
                for j in range(n):
                    out[i, j] = np.inf
            return
    for i in range(n):
        for j in range(n):
            W[i, j] = Pm[i, j]
            Y[i, j] = 1.0 if i == j else 0.0
    solve_inplace(W, Y)  # Y = Pm⁻¹
    for i in range(n):
        for j in range(n):
            W[i, j] = Y[i, j] + info[i, j]
            out[i, j] = 1.0 if i == j else 0.0
    solve_inplace(W, out)  # (Pm⁻¹ + info)⁻¹
    sym(out)


@nb.njit(**_opts)
def smooth(Ps, Pf, A, Q, info, limit, out, J, Xn, Sn, PCt, W, Y):
    """out = P_{t|t, x_{t+1}} + J Ps Jᵀ: one RTS step in conditioning form for one run,
    :class:`netkf_cli.linalg.kalman.SmoothStep` (Ps = P_{t+1|T}, Pf = P_{t|t}; J = Pf Aᵀ (A Pf Aᵀ + Q)⁻¹ and
    P_{t|t, x_{t+1}} = the update of Pf by x_{t+1} = A x_t + w_t, redone in information form
    (Pf⁻¹ + ``info``)⁻¹, ``info`` = AᵀQ⁻¹A, when tr Pf > ``limit``; ``limit`` = inf: no rescue). A
    non-finite result is inf. ``out`` may not alias the inputs; work arrays J, W, Y (n, n), Xn (n, n),
    Sn (n, n), PCt (n, n)."""
    n = Pf.shape[0]
    gain(Pf, A, Q, J, Sn, Xn)
    update(Pf, A, Q, 1.0, out, PCt, Sn, Xn)
    tr = 0.0
    for i in range(n):
        tr += Pf[i, i]
    if not (tr <= limit):
        finite = True
        for i in range(n):
            for j in range(n):
                if not np.isfinite(Pf[i, j]):
                    finite = False
        if finite:
            information_update(Pf, info, out, W, Y)
    for a in range(n):
        for j in range(n):
            acc = 0.0
            for b in range(n):
                acc += Ps[a, b] * J[j, b]
            W[a, j] = acc  # Ps Jᵀ
    bad = False
    for i in range(n):
        for j in range(n):
            acc = 0.0
            for a in range(n):
                acc += J[i, a] * W[a, j]
            out[i, j] += acc
            if not np.isfinite(out[i, j]):
                bad = True
    sym(out)
    if bad:
        for i in range(n):
            for j in range(n):
                out[i, j] = np.inf


# ----------------------------------------------------------------------------------------------
# appended (issue 19, the fading receivers): the gain alone, for a filter whose covariance is then
# propagated by :func:`joseph` (a gain computed from another covariance or another R)
# ----------------------------------------------------------------------------------------------

@nb.njit(**_opts)
def innovation(P, C, R, X, S):
    """X = C P (m, n) and S = C P Cᵀ + R (m, m) for one run: :func:`netkf_cli.linalg.kalman.innovation`."""
    n = P.shape[0]
    m = C.shape[0]
    for a in range(m):
        for j in range(n):
            acc = 0.0
            for k in range(n):
                acc += C[a, k] * P[k, j]
            X[a, j] = acc
    for a in range(m):
        for b in range(m):
            acc = R[a, b]
            for k in range(n):
                acc += X[a, k] * C[b, k]
            S[a, b] = acc


@nb.njit(**_opts)
def gain(P, C, R, K, S, X):
    """K = P Cᵀ (C P Cᵀ + R)⁻¹ for one run: :func:`netkf_cli.linalg.kalman.gain` (the optimal gain of the
    covariance P and noise R; Sinopoli 2004 eq. 9). K (n, m) out; work arrays S (m, m), X (m, n)."""
    n = P.shape[0]
    m = C.shape[0]
    innovation(P, C, R, X, S)
    solve_inplace(S, X)  # S⁻¹ C P = Kᵀ (P, S symmetric)
    for i in range(n):
        for a in range(m):
            K[i, a] = X[a, i]


# ----------------------------------------------------------------------------------------------
# appended (issue 19, the Markov-mode filters): the update when an innovation can have zero variance
# ----------------------------------------------------------------------------------------------

@nb.njit(**_opts)
def update_pinv(P, C, R, floor, e, out, dx, S, X):
    """out = P − P Cᵀ S⁺ C P and dx = P Cᵀ S⁺ e for one run: :func:`netkf_cli.linalg.kalman.update_pinv`
    (S = C P Cᵀ + R; innovation directions of variance ≤ ``floor`` get zero gain). Symmetric pivoted
    elimination — the sequential scalar update on decorrelated rows, pivot = the largest remaining
    variance, stop at ≤ floor; for a regular S it is :func:`update` to rounding. ``e`` (m,) is
    overwritten; work arrays S (m, m), X (m, n)."""
    n = P.shape[0]
    m = C.shape[0]
    innovation(P, C, R, X, S)
    for i in range(n):
        dx[i] = 0.0
        for j in range(n):
            out[i, j] = P[i, j]
    for _ in range(m):
        p = -1
        best = floor
        for a in range(m):
            if S[a, a] > best:
                best = S[a, a]
                p = a
        if p < 0:
            break
        inv = 1.0 / S[p, p]
        for i in range(n):
            bi = X[p, i] * inv
            dx[i] += bi * e[p]
            for j in range(i, n):
                v = out[i, j] - bi * X[p, j]
                out[i, j] = v
        for a in range(m):
            if a != p:
                f = S[a, p] * inv
                if f != 0.0:
                    for c in range(m):
                        S[a, c] -= f * S[p, c]
                    for c in range(n):
                        X[a, c] -= f * X[p, c]
                    e[a] -= f * e[p]
        for c in range(m):
            S[p, c] = 0.0
            S[c, p] = 0.0
        for c in range(n):
            X[p, c] = 0.0
        e[p] = 0.0
    for i in range(n):
        for j in range(i + 1, n):
            out[j, i] = out[i, j]


# ----------------------------------------------------------------------------------------------
# the compiled filter recursion (kalman.Filter with backend numba)
# ----------------------------------------------------------------------------------------------

@nb.njit(cache=True, nogil=True)
def filter_advance(P, A, C, Q, R, gamma, starts, lens, t0, t1, limit, flag):
    """Advance every run of P (n, n, runs) over trace steps t0 … t1 − 1: predict, then one sequential
    update per sensor group s (rows starts[s] … starts[s] + lens[s], applied iff gamma[r, s, t]; the
    arrivals run-major, (runs, S, horizon), so one run's history is contiguous) —
    :meth:`netkf_cli.linalg.kalman.Filter.step` for block-diagonal R, entry by entry. A run whose prior has
    tr P⁻ > ``limit`` or is non-finite is flagged (``flag[r]``) and left where it was: the numpy core
    (:class:`netkf_cli.linalg.kalman.Rescue`) redoes it, so the rescue policy stays the core's."""
    n = P.shape[0]
    runs = P.shape[2]
    G = starts.shape[0]
    mmax = 1
    for s in range(G):
        if lens[s] > mmax:
            mmax = lens[s]
    Pl = np.empty((n, n))
    Pm = np.empty((n, n))
    out = np.empty((n, n))
    tmp = np.empty((n, n))
    PCt = np.empty((n, mmax))
    S = np.empty((mmax, mmax))
    X = np.empty((mmax, n))
    for r in range(runs):
        if flag[r]:
            continue
        for i in range(n):
            for j in range(n):
                Pl[i, j] = P[i, j, r]
        for t in range(t0, t1):
            predict(Pl, A, Q, Pm, tmp)
            tr = 0.0
            for i in range(n):
                tr += Pm[i, i]
            if not (tr <= limit):
                flag[r] = True
                break
            for s in range(G):
                if gamma[r, s, t]:
                    a = starts[s]
                    b = a + lens[s]
                    mg = lens[s]
                    update(Pm, C[a:b], R[a:b, a:b], 1.0, out, PCt[:, :mg], S[:mg, :mg], X[:mg])
                    for i in range(n):
                        for j in range(n):
                            Pm[i, j] = out[i, j]
            for i in range(n):
                for j in range(n):
                    Pl[i, j] = Pm[i, j]
        if not flag[r]:
            for i in range(n):
                for j in range(n):
                    P[i, j, r] = Pl[i, j]


# ----------------------------------------------------------------------------------------------
# appended (issue 19, the Markov-mode filters): the time update with sparse per-mode transitions
# ----------------------------------------------------------------------------------------------

@nb.njit(**_opts)
def predict_csr(P, q, rowptr, cols, vals, Q, out, tmp):
    """out = A_q P A_qᵀ + Q_q (:func:`predict`) with the per-mode A_q in CSR form: row a of A_q has the
    values ``vals[q, rowptr[q, a]:rowptr[q, a+1]]`` at columns ``cols[q, …]`` (an augmented state's
    transition is mostly zeros); ``Q`` (modes, n, n). ``tmp`` an n×n work array."""
    n = P.shape[0]
    for a in range(n):
        for j in range(n):
            acc = 0.0
            for k in range(rowptr[q, a], rowptr[q, a + 1]):
                acc += vals[q, k] * P[cols[q, k], j]
            tmp[a, j] = acc  # (A_q P)[a, j]
    for a in range(n):
        for b in range(a, n):
            acc = Q[q, a, b]
            for k in range(rowptr[q, b], rowptr[q, b + 1]):
                acc += tmp[a, cols[q, k]] * vals[q, k]
            out[a, b] = acc
            out[b, a] = acc
