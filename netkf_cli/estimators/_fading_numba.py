"""Compiled (numba) step of the fading receivers (Mostofi & Murray 2009) — imported only on demand.

One call advances every run of a batch by one time step, exactly the recursion of
:mod:`netkf_cli.estimators.fading_receivers` (numpy reference), on the SAME random numbers
(the keep decisions and σ_n² values are computed by numpy and passed in):

* ``mode 0`` — scenarios 1 and 3, information form:
  P⁺ = (P⁻¹ + Σ_i G_i /(r_i + σ²))⁻¹ with Cᵀ(σ² I + R)⁻¹C = Σ_i G_i/(r_i + σ²) (eigen-split of R;
  scenario 1 passes σ² = 0), then P[k+1] = sym(A P⁺ Aᵀ) + Q;
* ``mode 1`` — scenario 2, invertible C, eq. (12): P[k+1] = M1 σ² + M2;
* ``mode 2`` — scenario 2, general C: gain K = P_f Cᵀ (C P_f Cᵀ)⁻¹ from the filter's own
  covariance, true covariance by the Joseph form with σ² I + R.

A dropped packet gives sym(A P Aᵀ) + Q. With ``want_u`` the burst-conditioned estimate
U ← μ (sym(A U Aᵀ) + Q) + (1 − μ) F(P, Υ') is advanced too (module doc of fading_receivers).

Matrix products are summed in index order (numpy's einsum/BLAS may sum in another order), so
the two backends agree to rounding (≈1e-13 relative), not bit for bit. Inverses use the same
closed forms as :func:`fading_receivers.inv_small` (scaled adjugate, divisions replaced by
one reciprocal) for n ≤ 3 and
Gauss–Jordan with partial pivoting beyond. Compiled without fastmath, cached on disk, with numpy's
error model (a division by zero gives inf/NaN like the numpy reference, never an exception: a
degenerate run, e.g. P_f = 0 in scenario 2 with m < n, is counted as non-finite).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, error_model="numpy")
def _inv(X, n, out, Y):
    """Inverse of a symmetric positive-definite n×n matrix X into ``out`` (``Y`` is scratch)."""
    s = 0.0
    bad = False
    for i in range(n):
        for j in range(n):
            a = abs(X[i, j])
            if a != a:
                bad = True
            elif a > s:
                s = a
    if bad or not (s > 0.0):
        s = 1.0
    inv_s = 1.0 / s
    for i in range(n):
        for j in range(n):
            Y[i, j] = X[i, j] * inv_s
    if n == 1:
        out[0, 0] = (1.0 / Y[0, 0]) / s
    elif n == 2:
        a, b, c, d = Y[0, 0], Y[0, 1], Y[1, 0], Y[1, 1]
        fac = (1.0 / (a * d - b * c)) * inv_s
        out[0, 0] = d * fac
        out[0, 1] = -b * fac
        out[1, 0] = -c * fac
        out[1, 1] = a * fac
    elif n == 3:
        a, b, c = Y[0, 0], Y[0, 1], Y[0, 2]
        d, e, f = Y[1, 0], Y[1, 1], Y[1, 2]
        g, h, i = Y[2, 0], Y[2, 1], Y[2, 2]
        A_ = e * i - f * h
        B_ = -(d * i - f * g)
        C_ = d * h - e * g
        fac = (1.0 / (a * A_ + b * B_ + c * C_)) * inv_s
        out[0, 0] = A_ * fac
        out[0, 1] = -(b * i - c * h) * fac
        out[0, 2] = (b * f - c * e) * fac
        out[1, 0] = B_ * fac
        out[1, 1] = (a * i - c * g) * fac
        out[1, 2] = -(a * f - c * d) * fac
        out[2, 0] = C_ * fac
        out[2, 1] = -(a * h - b * g) * fac
        out[2, 2] = (a * e - b * d) * fac
    else:  # Gauss–Jordan with partial pivoting on the scaled matrix
        for i in range(n):
            for j in range(n):
                out[i, j] = 1.0 if i == j else 0.0
        for col in range(n):
            p = col
            best = abs(Y[col, col])
            for r in range(col + 1, n):
                if abs(Y[r, col]) > best:
                    best = abs(Y[r, col])
                    p = r
            if p != col:
                for j in range(n):
                    t = Y[col, j]
                    Y[col, j] = Y[p, j]
                    Y[p, j] = t
                    t = out[col, j]
                    out[col, j] = out[p, j]
                    out[p, j] = t
            piv = Y[col, col]
            for j in range(n):
                Y[col, j] /= piv
                out[col, j] /= piv
            for r in range(n):
                if r != col:
                    f_ = Y[r, col]
                    if f_ != 0.0:
                        for j in range(n):
                            Y[r, j] -= f_ * Y[col, j]
                            out[r, j] -= f_ * out[col, j]
        for i in range(n):
            for j in range(n):
                out[i, j] *= inv_s


@njit(cache=True, error_model="numpy")
def _drop(A, Q, X, n, out, T):
    """out = sym(A X Aᵀ) + Q (T scratch)."""
    for i in range(n):
        for k in range(n):
            acc = 0.0
            for j in range(n):
                acc += A[i, j] * X[j, k]
            T[i, k] = acc
    for i in range(n):
        for l in range(n):
            acc = 0.0
            for k in range(n):
                acc += T[i, k] * A[l, k]
            out[i, l] = acc
    for i in range(n):
        for l in range(i, n):
            v = 0.5 * (out[i, l] + out[l, i])
            out[i, l] = v + Q[i, l]
            out[l, i] = v + Q[l, i]


@njit(cache=True, error_model="numpy")
def step(mode, Pf, Pt, U, keep, s2, mu, want_u, A, Q, C, R, G, r, M1, M2):
    """Advance every run b of ``Pt`` (true covariance; ``Pf`` the filter's own one in mode 2) by one step.

    State arrays are RUN-MAJOR ``(B, n, n)`` (each run's matrix contiguous: the compiled loop
    is over runs, so this layout reads one cache line per run instead of n² strided ones); ``keep`` (B,) bool, ``s2`` (B,) σ_n² of the
    packet, ``mu`` (B,) drop probability of the run's threshold (used when ``want_u``).
    """
    n = A.shape[0]
    m = C.shape[0]
    B = Pt.shape[0]
    P = np.empty((n, n))
    X = np.empty((n, n))
    Y = np.empty((n, n))
    T = np.empty((n, n))
    W = np.empty((n, n))
    K_t = np.empty((n, n))  # kept result, true covariance
    K_f = np.empty((n, n))  # kept result, filter covariance (mode 2)
    D = np.empty((n, n))
    S = np.empty((m, m))
    Si = np.empty((m, m))
    Sy = np.empty((m, m))
    PC = np.empty((n, m))
    K = np.empty((n, m))
    IKC = np.empty((n, n))
    Pf_l = np.empty((n, n))
    w = np.empty(m)
    for b in range(B):
        kp = keep[b]
        need_kept = kp or want_u
        for i in range(n):
            for j in range(n):
                P[i, j] = Pt[b, i, j]
        if need_kept:
            if mode == 0:
                for q in range(m):
                    w[q] = 1.0 / (r[q] + s2[b])
                _inv(P, n, X, Y)
                for i in range(n):
                    for j in range(n):
                        acc = 0.0
                        for q in range(m):
                            acc += G[i, j, q] * w[q]
                        X[i, j] = X[i, j] + acc
                for i in range(n):
                    for j in range(i, n):
                        v = 0.5 * (X[i, j] + X[j, i])
                        X[i, j] = v
                        X[j, i] = v
                _inv(X, n, W, Y)
                _drop(A, Q, W, n, K_t, T)
            elif mode == 1:
                for i in range(n):
                    for j in range(n):
                        K_t[i, j] = M1[i, j] * s2[b] + M2[i, j]
            else:
                for i in range(n):
                    for j in range(n):
                        Pf_l[i, j] = Pf[b, i, j]
                # PC = Pf Cᵀ (n, m); S = sym(C Pf Cᵀ)
                for i in range(n):
                    for q in range(m):
                        acc = 0.0
                        for j in range(n):
                            acc += Pf_l[i, j] * C[q, j]
                        PC[i, q] = acc
                for q in range(m):
                    for p in range(m):
                        acc = 0.0
                        for j in range(n):
                            acc += C[q, j] * PC[j, p]
                        S[q, p] = acc
                for q in range(m):
                    for p in range(q, m):
                        v = 0.5 * (S[q, p] + S[p, q])
                        S[q, p] = v
                        S[p, q] = v
                _inv(S, m, Si, Sy)
                for i in range(n):
                    for q in range(m):
                        acc = 0.0
                        for p in range(m):
                            acc += PC[i, p] * Si[p, q]
                        K[i, q] = acc
                for i in range(n):
                    for j in range(n):
                        acc = 0.0
                        for q in range(m):
                            acc += K[i, q] * C[q, j]
                        IKC[i, j] = (1.0 if i == j else 0.0) - acc
                # true: IKC Pt IKCᵀ + K (R + s2 I) Kᵀ
                for i in range(n):
                    for k in range(n):
                        acc = 0.0
                        for j in range(n):
                            acc += IKC[i, j] * P[j, k]
                        T[i, k] = acc
                for i in range(n):
                    for l in range(n):
                        acc = 0.0
                        for k in range(n):
                            acc += T[i, k] * IKC[l, k]
                        acc2 = 0.0
                        for q in range(m):
                            for p in range(m):
                                rz = R[q, p] + (s2[b] if q == p else 0.0)
                                acc2 += K[i, q] * rz * K[l, p]
                        X[i, l] = acc + acc2
                for i in range(n):
                    for l in range(i, n):
                        v = 0.5 * (X[i, l] + X[l, i])
                        X[i, l] = v
                        X[l, i] = v
                _drop(A, Q, X, n, K_t, T)
                # filter: IKC Pf IKCᵀ
                for i in range(n):
                    for k in range(n):
                        acc = 0.0
                        for j in range(n):
                            acc += IKC[i, j] * Pf_l[j, k]
                        T[i, k] = acc
                for i in range(n):
                    for l in range(n):
                        acc = 0.0
                        for k in range(n):
                            acc += T[i, k] * IKC[l, k]
                        X[i, l] = acc
                for i in range(n):
                    for l in range(i, n):
                        v = 0.5 * (X[i, l] + X[l, i])
                        X[i, l] = v
                        X[l, i] = v
                _drop(A, Q, X, n, K_f, T)
        if want_u:
            for i in range(n):
                for j in range(n):
                    W[i, j] = U[b, i, j]
            _drop(A, Q, W, n, D, T)
            mb = mu[b]
            for i in range(n):
                for j in range(n):
                    U[b, i, j] = mb * D[i, j] + (1.0 - mb) * K_t[i, j]
        if kp:
            for i in range(n):
                for j in range(n):
                    Pt[b, i, j] = K_t[i, j]
            if mode == 2:
                for i in range(n):
                    for j in range(n):
                        Pf[b, i, j] = K_f[i, j]
        else:
            _drop(A, Q, P, n, D, T)
            for i in range(n):
                for j in range(n):
                    Pt[b, i, j] = D[i, j]
            if mode == 2:
                for i in range(n):
                    for j in range(n):
                        Pf_l[i, j] = Pf[b, i, j]
                _drop(A, Q, Pf_l, n, D, T)
                for i in range(n):
                    for j in range(n):
                        Pf[b, i, j] = D[i, j]


# ---------------------------------------------------------------------------------------------
# Specialized straight-line kernels (n ≤ 3 states, m ≤ 3 outputs): the same recursion as ``step``
# with every small loop unrolled, generated per (mode, n, m), written once to a content-addressed
# file in the cache folder and compiled with cache=True (later processes load the machine code).
# With runtime-sized loops the generic ``step`` spends most of its time in loop overhead (scalar
# receiver: 8e6 run-steps/s per core, a hand-specialized loop 2.4e8 on the same machine).
# ---------------------------------------------------------------------------------------------


class _G:
    def __init__(self):
        self.lines: list[str] = []
        self.k = 0

    def v(self, expr: str) -> str:
        name = f"t{self.k}"
        self.k += 1
        self.lines.append(f"{name} = {expr}")
        return name

    def put(self, line: str) -> None:
        self.lines.append(line)


def _g_inv(g: _G, X, n):
    """Scaled closed-form inverse of the n×n symbolic matrix X (list of lists of names), n ≤ 3."""
    flat = [X[i][j] for i in range(n) for j in range(n)]
    s = g.v("0.0")
    for x in flat:
        g.put(f"{s} = abs({x}) if abs({x}) > {s} else {s}")
    g.put(f"{s} = {s} if {s} > 0.0 else 1.0")
    inv_s = g.v(f"1.0 / {s}")
    Y = [[g.v(f"{X[i][j]} * {inv_s}") for j in range(n)] for i in range(n)]
    if n == 1:
        return [[g.v(f"(1.0 / {Y[0][0]}) / {s}")]]
    if n == 2:
        a, b, c, d = Y[0][0], Y[0][1], Y[1][0], Y[1][1]
        fac = g.v(f"(1.0 / ({a} * {d} - {b} * {c})) * {inv_s}")
        return [[g.v(f"{d} * {fac}"), g.v(f"-{b} * {fac}")], [g.v(f"-{c} * {fac}"), g.v(f"{a} * {fac}")]]
    a, b, c = Y[0]
    d, e, f = Y[1]
    gg, h, i = Y[2]
    A_ = g.v(f"{e} * {i} - {f} * {h}")
    B_ = g.v(f"-({d} * {i} - {f} * {gg})")
    C_ = g.v(f"{d} * {h} - {e} * {gg}")
    fac = g.v(f"(1.0 / ({a} * {A_} + {b} * {B_} + {c} * {C_})) * {inv_s}")
    return [[g.v(f"{A_} * {fac}"), g.v(f"-({b} * {i} - {c} * {h}) * {fac}"), g.v(f"({b} * {f} - {c} * {e}) * {fac}")],
            [g.v(f"{B_} * {fac}"), g.v(f"({a} * {i} - {c} * {gg}) * {fac}"), g.v(f"-({a} * {f} - {c} * {d}) * {fac}")],
            [g.v(f"{C_} * {fac}"), g.v(f"-({a} * {h} - {b} * {gg}) * {fac}"), g.v(f"({a} * {e} - {b} * {d}) * {fac}")]]


def _g_sum(terms):
    return " + ".join(terms) if terms else "0.0"


def _g_drop(g: _G, X, n):
    """sym(A X Aᵀ) + Q (A, Q as scalar names a_i_j, q_i_j)."""
    T = [[g.v(_g_sum([f"a_{i}_{j} * {X[j][k]}" for j in range(n)])) for k in range(n)] for i in range(n)]
    O = [[g.v(_g_sum([f"{T[i][k]} * a_{l}_{k}" for k in range(n)])) for l in range(n)] for i in range(n)]
    out = [[None] * n for _ in range(n)]
    for i in range(n):
        for l in range(i, n):
            v = g.v(f"0.5 * ({O[i][l]} + {O[l][i]})")
            out[i][l] = g.v(f"{v} + q_{i}_{l}")
            out[l][i] = out[i][l] if i == l else g.v(f"{v} + q_{l}_{i}")
    return out


def _g_sym(g: _G, X, n):
    out = [[None] * n for _ in range(n)]
    for i in range(n):
        for j in range(i, n):
            out[i][j] = g.v(f"0.5 * ({X[i][j]} + {X[j][i]})")
            out[j][i] = out[i][j]
    return out


def _source(mode: int, n: int, m: int) -> str:
    body = _G()
    body.put("kp = keep[b]")
    body.put("s2b = s2[b]")
    P = [[body.v(f"Pt[b, {i}, {j}]") for j in range(n)] for i in range(n)]
    kept = _G()
    kept.k = 10_000
    if mode == 0:
        Xi = _g_inv(kept, P, n)
        w = [kept.v(f"1.0 / (r_{q} + s2b)") for q in range(m)]
        Xs = [[kept.v(f"{Xi[i][j]} + ({_g_sum([f'g_{i}_{j}_{q} * {w[q]}' for q in range(m)])})") for j in range(n)] for i in range(n)]
        Xs = _g_sym(kept, Xs, n)
        W = _g_inv(kept, Xs, n)
        Kt = _g_drop(kept, W, n)
        Kf = None
    elif mode == 1:
        Kt = [[kept.v(f"m1_{i}_{j} * s2b + m2_{i}_{j}") for j in range(n)] for i in range(n)]
        Kf = None
    else:
        F = [[kept.v(f"Pf[b, {i}, {j}]") for j in range(n)] for i in range(n)]
        PC = [[kept.v(_g_sum([f"{F[i][j]} * c_{q}_{j}" for j in range(n)])) for q in range(m)] for i in range(n)]
        S = [[kept.v(_g_sum([f"c_{q}_{j} * {PC[j][p]}" for j in range(n)])) for p in range(m)] for q in range(m)]
        S = _g_sym(kept, S, m)
        Si = _g_inv(kept, S, m)
        K = [[kept.v(_g_sum([f"{PC[i][p]} * {Si[p][q]}" for p in range(m)])) for q in range(m)] for i in range(n)]
        IKC = [[kept.v(f"{1.0 if i == j else 0.0} - ({_g_sum([f'{K[i][q]} * c_{q}_{j}' for q in range(m)])})")
                for j in range(n)] for i in range(n)]
        T = [[kept.v(_g_sum([f"{IKC[i][j]} * {P[j][k]}" for j in range(n)])) for k in range(n)] for i in range(n)]
        X = [[kept.v(_g_sum([f"{T[i][k]} * {IKC[l][k]}" for k in range(n)]) + " + " +
                     _g_sum([f"{K[i][q]} * (rr_{q}_{p}{' + s2b' if q == p else ''}) * {K[l][p]}"
                             for q in range(m) for p in range(m)])) for l in range(n)] for i in range(n)]
        Kt = _g_drop(kept, _g_sym(kept, X, n), n)
        T2 = [[kept.v(_g_sum([f"{IKC[i][j]} * {F[j][k]}" for j in range(n)])) for k in range(n)] for i in range(n)]
        X2 = [[kept.v(_g_sum([f"{T2[i][k]} * {IKC[l][k]}" for k in range(n)])) for l in range(n)] for i in range(n)]
        Kf = _g_drop(kept, _g_sym(kept, X2, n), n)
    drop = _G()
    drop.k = 20_000
    D = _g_drop(drop, P, n)
    if mode == 2:
        F2 = [[drop.v(f"Pf[b, {i}, {j}]") for j in range(n)] for i in range(n)]
        Df = _g_drop(drop, F2, n)
    ug = _G()
    ug.k = 30_000
    Uv = [[ug.v(f"U[b, {i}, {j}]") for j in range(n)] for i in range(n)]
    DU = _g_drop(ug, Uv, n)
    ug.put("mb = mu[b]")
    for i in range(n):
        for j in range(n):
            ug.put(f"U[b, {i}, {j}] = mb * {DU[i][j]} + (1.0 - mb) * {Kt[i][j]}")
    lines = ["def step_gen(Pf, Pt, U, keep, s2, mu, want_u, A, Q, C, R, G, r, M1, M2):",
             "    B = Pt.shape[0]"]
    for i in range(n):
        for j in range(n):
            lines += [f"    a_{i}_{j} = A[{i}, {j}]", f"    q_{i}_{j} = Q[{i}, {j}]",
                      f"    m1_{i}_{j} = M1[{i}, {j}] if M1.shape[0] > {i} else 0.0",
                      f"    m2_{i}_{j} = M2[{i}, {j}] if M2.shape[0] > {i} else 0.0"]
            for q in range(m):
                lines.append(f"    g_{i}_{j}_{q} = G[{i}, {j}, {q}] if G.shape[2] > {q} else 0.0")
    for q in range(m):
        lines.append(f"    r_{q} = r[{q}] if r.shape[0] > {q} else 1.0")
        for j in range(n):
            lines.append(f"    c_{q}_{j} = C[{q}, {j}]")
        for p in range(m):
            lines.append(f"    rr_{q}_{p} = R[{q}, {p}]")
    lines.append("    for b in range(B):")
    ind = "        "
    lines += [ind + x for x in body.lines]
    lines.append(ind + "if kp or want_u:")
    lines += [ind + "    " + x for x in kept.lines]
    lines.append(ind + "    if want_u:")
    lines += [ind + "        " + x for x in ug.lines]
    lines.append(ind + "    if kp:")
    for i in range(n):
        for j in range(n):
            lines.append(ind + f"        Pt[b, {i}, {j}] = {Kt[i][j]}")
            if mode == 2:
                lines.append(ind + f"        Pf[b, {i}, {j}] = {Kf[i][j]}")
    lines.append(ind + "if not kp:")
    lines += [ind + "    " + x for x in drop.lines]
    for i in range(n):
        for j in range(n):
            lines.append(ind + f"    Pt[b, {i}, {j}] = {D[i][j]}")
            if mode == 2:
                lines.append(ind + f"    Pf[b, {i}, {j}] = {Df[i][j]}")
    return "\n".join(lines) + "\n"


_SPECIALIZED: dict = {}


def specialized_step(mode: int, n: int, m: int):
    """The compiled straight-line step for (mode, n, m), or None when n > 3 or m > 3 (generic ``step``)."""
    if n > 3 or m > 3:
        return None
    key = (mode, n, m)
    if key in _SPECIALIZED:
        return _SPECIALIZED[key]
    import hashlib
    import importlib.util
    import os
    import tempfile
    from pathlib import Path

    import numba

    from netkf_cli.estimators.buffered_numba import _cache_dir  # the shared compiled-kernel folder

    src = "from numba import njit\n\n\n@njit(cache=True, error_model=\"numpy\")\n" + _source(mode, n, m)
    digest = hashlib.sha256((src + numba.__version__ + np.__version__).encode()).hexdigest()[:16]
    root = Path(_cache_dir())
    path = root / f"netkf_fading_{mode}_{n}_{m}_{digest}.py"
    if not path.exists():
        fd, tmp = tempfile.mkstemp(dir=root, suffix=".tmp")
        with os.fdopen(fd, "w") as f:
            f.write(src)
        os.replace(tmp, path)  # atomic: concurrent workers see the whole file or none
    import sys

    spec = importlib.util.spec_from_file_location(path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[path.stem] = mod  # numba's on-disk cache re-imports the module by this name
    spec.loader.exec_module(mod)
    _SPECIALIZED[key] = mod.step_gen
    return mod.step_gen
