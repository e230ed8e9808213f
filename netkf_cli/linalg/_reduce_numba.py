"""The engine's reductions compiled (numba): λ_max, the PSD order P ≤ M·I, traces and power sums per run.

The numpy reducers of :mod:`netkf_cli.engine` are the reference; these functions compute the same
statistics in one pass over a batch of covariances held as packed upper triangles ``T`` shaped
(n(n+1)/2, runs) (:func:`netkf_cli.linalg.kalman_codegen.pack`, the compiled filter's layout, run axis
innermost), so a compiled filter kernel reduces its state without unpacking it and the numpy
reducers' (n, n, runs) arrays are reduced after one pack. Import only where numba is importable.

λ_max (:func:`lmax_tri`) of the symmetric part of P, n ≤ 4 (any n works; the scratch is n × n):
n = 1 the entry, n = 2 the closed form m + hypot(h, b) (m, h the half sum / difference of the
diagonal, b the off-diagonal), n ≥ 3 cyclic Jacobi rotations (Rutishauser's form) until the
last sweep whose every off-diagonal entry is negligible (|a_pq| ≤ max(1e-2·eps·√|a_pp a_qq|,
1e-3·eps·‖P‖_F): set to 0, a perturbation far below the rounding of the rotations). Accuracy: each rotation is backward stable, so
|λ̃ − λ| ≤ c·eps·‖P‖_F with c ≈ 10 (a few sweeps), i.e. ≤ ~1e-14·λ_max relative for a PSD P
(‖P‖_F ≤ √n·λ_max) and the same bound as LAPACK's eigvalsh; near-degenerate λ_max loses nothing
(Jacobi's error does not depend on the eigenvalue gap). Tested against eigvalsh to 1e-12 relative
(tests/engine/test_reduce_numba.py). A non-finite P has λ_max = +∞ (as ``batched.lambda_max``).

The PSD order P ≤ M·I ⇔ λ_max ≤ th = M + tol (n = 1: P ≤ th exactly, as numpy) is decided, outside
a margin mg = LAMBDA_MAX_MARGIN·(|th| + max_i Σ_j |P_ij|) (≥ 1e-11·‖P‖₂, far above the ~n·eps·‖P‖ error of either
eigenvalue routine, so the decision is the one eigvalsh gives), by certificates: bounds that hold for
any symmetric matrix (λ_max ≥ max_i P_ii, λ_max ≤ max_i (P_ii + Σ_{j≠i} |P_ij|), Gershgorin), then the
LDLᵀ factorization of (th − mg)·I − P (every pivot positive: P < th − mg up to its backward error
γ_n·|L||D||Lᵀ|, Higham Thm 9.3, bounded by requiring each pivot's magnitude ≤ 1e3·(|th| + ‖P‖)) or of
(th + mg)·I − P (a pivot < −1e-9 of its magnitude: P is not ≤ th + mg); only inside the margin by
eigvalsh itself (the caller's numpy). The decision is monotone in th, so for ascending thresholds a
binary search decides ~log₂ nM of them per run. Those kernels are generated per n with P in scalar
locals (:mod:`netkf_cli.linalg.reduce_codegen`), as are the moment sums; this module holds λ_max and the
time-average sum.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

_EPS = 2.220446049250313e-16

_opts = dict(cache=True, nogil=True, error_model="numpy")


@nb.njit(**_opts)
def load(T, n, r, a):
    """a (n, n) ← the run r of the packed upper triangle T; False when an entry is not finite."""
    k = 0
    ok = True
    for i in range(n):
        for j in range(i, n):
            v = T[k, r]
            if not math.isfinite(v):
                ok = False
            a[i, j] = v
            a[j, i] = v
            k += 1
    return ok


@nb.njit(**_opts)
def jacobi_lmax(a, n):
    """Largest eigenvalue of the symmetric a (n, n), destroyed (cyclic Jacobi; see the module doc)."""
    fro = 0.0
    for i in range(n):
        for j in range(n):
            fro += a[i, j] * a[i, j]
    tiny = 1e-3 * _EPS * math.sqrt(fro)
    for _sweep in range(60):
        rotated = False
        for p in range(n):
            for q in range(p + 1, n):
                apq = a[p, q]
                app, aqq = a[p, p], a[q, q]
                if abs(apq) <= max(1e-2 * _EPS * math.sqrt(abs(app * aqq)), tiny):
                    a[p, q] = 0.0  # negligible: a perturbation ≤ 1e-2·eps·‖P‖
                    a[q, p] = 0.0
                    continue
                rotated = True
                theta = (aqq - app) / (2.0 * apq)
                if abs(theta) > 1e150:
                    t = 0.5 / theta
                else:
                    t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                    if theta < 0.0:
                        t = -t
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                tau = s / (1.0 + c)
                a[p, p] = app - t * apq
                a[q, q] = aqq + t * apq
                a[p, q] = 0.0
                a[q, p] = 0.0
                for r in range(n):
                    if r != p and r != q:
                        arp, arq = a[r, p], a[r, q]
                        vp = arp - s * (arq + tau * arp)
                        vq = arq + s * (arp - tau * arq)
                        a[r, p] = vp
                        a[p, r] = vp
                        a[r, q] = vq
                        a[q, r] = vq
        if not rotated:
            break
    lm = a[0, 0]
    for i in range(1, n):
        if a[i, i] > lm:
            lm = a[i, i]
    return lm


@nb.njit(**_opts)
def lmax_loaded(a, n):
    """λ_max of the (finite, symmetric) a (n, n) loaded by :func:`load` (a is destroyed for n ≥ 3)."""
    if n == 1:
        return a[0, 0]
    if n == 2:
        return 0.5 * (a[0, 0] + a[1, 1]) + math.hypot(0.5 * (a[0, 0] - a[1, 1]), a[0, 1])
    return jacobi_lmax(a, n)


@nb.njit(**_opts)
def lmax_tri(T, n, out):
    """out (runs,) ← λ_max of every run of the packed T (+∞ where not finite)."""
    a = np.empty((n, n))
    for r in range(T.shape[1]):
        if load(T, n, r, a):
            out[r] = lmax_loaded(a, n)
        else:
            out[r] = np.inf


@nb.njit(**_opts)
def trace_acc(T, n, L, acc):
    """TimeAverageReducer at one step: acc (runs,) += tr P / L (non-finite values propagate). The diagonal is
    summed in order (0 + P₀₀ + P₁₁ + …, numpy's einsum order) one row of T at a time, so the run loops vectorize."""
    runs = T.shape[1]
    tr = np.zeros(runs)
    k = 0
    for i in range(n):
        for r in range(runs):
            tr[r] += T[k, r]
        k += n - i
    for r in range(runs):
        acc[r] += tr[r] / L
