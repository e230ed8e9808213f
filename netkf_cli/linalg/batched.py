"""Batched linear algebra for the ``(n, n, runs)`` layout (run axis innermost, design.md).

Every function takes covariances ``P`` shaped ``(n, n, runs)`` (or ``(m, m, runs)``) and
constant system matrices; nothing loops over runs in Python. Small solves are done in
closed form for sizes 1 and 2 and with ``np.linalg.solve`` (on a moved axis) otherwise — no
``inv``. A run that overflowed carries ``inf``/``nan`` and is reported by the metric, never
raised.
"""

from __future__ import annotations

import numpy as np

from netkf_cli.core.tolerances import PSD_TOL


def sym(P: np.ndarray) -> np.ndarray:
    """(P + Pᵀ)/2 over the two leading axes."""
    return 0.5 * (P + P.swapaxes(0, 1))


_PATTERN: dict = {}
"""Per constant matrix A (keyed by shape, dtype and bytes): its rows' nonzero coefficients for :func:`left`."""


def _pattern(A: np.ndarray) -> tuple:
    """Per row of A, ((j, A[i, j], A[i, j] == 1.0), …) over its nonzero entries (cached: the matrices are the
    few constant system matrices, and finding the pattern costs more than the products at small runs)."""
    key = (A.shape, A.dtype.str, A.tobytes())
    pat = _PATTERN.get(key)
    if pat is None:
        p, n = A.shape
        pat = tuple(tuple((j, A[i, j], bool(A[i, j] == 1.0)) for j in range(n) if A[i, j] != 0.0) for i in range(p))
        if len(_PATTERN) > 4096:  # a bound, never reached by the constant system matrices
            _PATTERN.clear()
        _PATTERN[key] = pat
    return pat


def left(A: np.ndarray, P: np.ndarray) -> np.ndarray:
    """A P for a constant matrix A (p×n) and P (n, k, runs).

    Row by row with the run axis innermost, skipping zero coefficients (A is often sparse:
    a constant-velocity model, C = [I 0]); thin BLAS GEMMs are slower than this at n ≤ 8.
    """
    p, n = A.shape
    if n > 8:
        k, r = P.shape[1:]
        return (A @ np.ascontiguousarray(P).reshape(n, k * r)).reshape(p, k, r)
    out = np.empty((p,) + P.shape[1:], dtype=np.result_type(A, P))
    with np.errstate(over="ignore", invalid="ignore"):
        for i, nz in enumerate(_pattern(A)):
            if not nz:
                out[i] = 0.0
                continue
            j0, a0, one0 = nz[0]
            if one0:
                out[i] = P[j0]
            else:
                np.multiply(P[j0], a0, out=out[i])
            for j, a, one in nz[1:]:
                if one:
                    out[i] += P[j]
                else:
                    out[i] += a * P[j]
    return out


def right(P: np.ndarray, B: np.ndarray) -> np.ndarray:
    """P B for P (k, n, runs) and a constant matrix B (n×p): (Bᵀ Pᵀ)ᵀ, one GEMM."""
    return left(B.T, P.swapaxes(0, 1)).swapaxes(0, 1)


def matmul(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Per-run product X_r Y_r for X (a, b, runs), Y (b, c, runs).

    Small inner dimensions (the usual case) are summed entry by entry with the run axis
    innermost — no per-run Python loop and no batched-GEMM transposes.
    """
    b = X.shape[1]
    if b <= 4:
        # out[i, k] = X[i, 0] Y[0, k] + X[i, 1] Y[1, k] + … in this order, all (i, k) at once (broadcast):
        # the same products and sums, so the same bits, with b passes instead of a·c·b
        with np.errstate(over="ignore", invalid="ignore"):
            out = X[:, 0, None, :] * Y[None, 0, :, :]
            for j in range(1, b):
                out += X[:, j, None, :] * Y[None, j, :, :]
        return out
    return np.einsum("ijr,jkr->ikr", X, Y, optimize=True)


def congruence(A: np.ndarray, P: np.ndarray) -> np.ndarray:
    """A P Aᵀ per run (symmetric result)."""
    return sym(right(left(A, P), A.T))


def riccati_h(P: np.ndarray, A: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """h(P) = A P Aᵀ + Q (Shi 2009, eq. 5): the time update."""
    return congruence(A, P) + Q[:, :, None]


def inv_small(S: np.ndarray) -> np.ndarray:
    """S⁻¹ per run for S (m, m, runs): closed form for m ≤ 2, LU otherwise."""
    m = S.shape[0]
    if m == 1:
        with np.errstate(divide="ignore", invalid="ignore"):
            return 1.0 / S
    if m == 2:
        a, b, c, d = S[0, 0], S[0, 1], S[1, 0], S[1, 1]
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            det = a * d - b * c
            out = np.empty_like(S)
            out[0, 0], out[0, 1], out[1, 0], out[1, 1] = d / det, -b / det, -c / det, a / det
        return out
    Sm = np.moveaxis(S, -1, 0)
    eye = np.broadcast_to(np.eye(m), Sm.shape)
    return np.moveaxis(_solve_runs(Sm, eye), 0, -1)


def solve_small(S: np.ndarray, B: np.ndarray) -> np.ndarray:
    """S⁻¹ B per run for S (m, m, runs) and B (m, k, runs)."""
    if S.shape[0] <= 2:
        return matmul(inv_small(S), B)
    X = _solve_runs(np.moveaxis(S, -1, 0), np.moveaxis(B, -1, 0))
    return np.moveaxis(X, 0, -1)


def _solve_runs(Sm: np.ndarray, Bm: np.ndarray) -> np.ndarray:
    """``np.linalg.solve`` over the leading (run) axis, a run whose S is singular to working precision (or not
    finite) giving NaN like the closed forms' division by zero, instead of LinAlgError for the whole batch (a
    run's prior overflowed along one direction makes its S = C P Cᵀ + R singular in double: 3 rows, a long burst).
    Such runs are found by LAPACK's own LU (``det`` and ``solve`` share getrf: a zero pivot in one is in the other)."""
    try:
        return np.linalg.solve(Sm, Bm)
    except np.linalg.LinAlgError:
        with np.errstate(invalid="ignore", over="ignore"):
            bad = ~(np.linalg.det(np.where(np.isfinite(Sm), Sm, 0.0)) != 0) | ~np.isfinite(Sm).all(axis=(-1, -2))
        Sm = np.where(bad[:, None, None], np.eye(Sm.shape[-1]), Sm)
        X = np.linalg.solve(Sm, Bm)
        X[bad] = np.nan
        return X


def psd_leq(P: np.ndarray, M: np.ndarray | float, tol: float = PSD_TOL) -> np.ndarray:
    """Per run: P ≤ M in the PSD order (min eig(M − P) ≥ −tol·max(1, ‖M‖)); non-finite P ⇒ False."""
    n = P.shape[0]
    Mm = np.asarray(M, dtype=float)
    if Mm.ndim == 0:
        Mm = Mm * np.eye(n)
    scale = tol * max(1.0, float(np.abs(Mm).max()))
    finite = np.isfinite(P).all(axis=(0, 1))
    D = Mm[:, :, None] - np.where(finite[None, None, :], P, 0.0)
    if n == 1:
        ok = D[0, 0] >= -scale
    elif n == 2:
        a, b, d = D[0, 0], 0.5 * (D[0, 1] + D[1, 0]), D[1, 1]
        mn = 0.5 * (a + d) - np.sqrt(0.25 * (a - d) ** 2 + b * b)
        ok = mn >= -scale
    else:
        ok = np.linalg.eigvalsh(np.moveaxis(sym(D), -1, 0))[:, 0] >= -scale
    return ok & finite


def trace(P: np.ndarray) -> np.ndarray:
    """tr P per run."""
    return np.einsum("iir->r", P)


def lambda_max(P: np.ndarray) -> np.ndarray:
    """Largest eigenvalue per run (nan for non-finite runs)."""
    n = P.shape[0]
    finite = np.isfinite(P).all(axis=(0, 1))
    if n == 1:
        return np.where(finite, P[0, 0], np.inf)
    Pm = np.moveaxis(np.where(finite[None, None, :], P, 0.0), -1, 0)
    out = np.linalg.eigvalsh(sym(np.moveaxis(Pm, 0, -1)).transpose(2, 0, 1))[:, -1]
    return np.where(finite, out, np.inf)


def psd_sqrt(P: np.ndarray) -> np.ndarray:
    """Symmetric PSD square root per run (negative eigenvalues clipped to 0)."""
    w, V = np.linalg.eigh(np.moveaxis(sym(P), -1, 0))
    w = np.sqrt(np.clip(w, 0.0, None))
    return np.moveaxis(np.einsum("rij,rj,rkj->rik", V, w, V), 0, -1)


def first_exceedance(flags: np.ndarray) -> np.ndarray:
    """Index of the first True along axis 0 per run (flags shaped (T, runs)); T where none."""
    T = flags.shape[0]
    any_ = flags.any(axis=0)
    return np.where(any_, flags.argmax(axis=0), T)
