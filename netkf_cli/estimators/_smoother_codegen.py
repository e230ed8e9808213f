"""The smoother's backward pass compiled per system: generated numba kernels of the Rauch–Tung–Striebel step.

The RTS step of :class:`netkf_cli.linalg.kalman.SmoothStep` splits into a part that depends only on the filtered
P_{t|t} and an affine map applied to P_{t+1|k}:

    prepare  U = P_{t|t} Aᵀ,  S = A U + Q,  X = S⁻¹ Uᵀ,  J_t = Xᵀ,  C_t = sym(P_{t|t} − U X)
    apply    P_{t|k} = sym(C_t + J_t P_{t+1|k} J_tᵀ)            (non-finite ⇒ ∞ everywhere)

so J_t and C_t are computed once per trace step t and shared by every step k and every lag that passes
through t (:mod:`netkf_cli.estimators.smoother`). Both kernels are written out as scalar expressions with
the system's numbers A, Q as constants (zeros skipped, ones dropped: :func:`kalman_codegen._lin`), in the
core's order of operations (S⁻¹ in closed form for n ≤ 2 — bit for bit the numpy core —, an unrolled
Cholesky factor for 3 ≤ n ≤ :data:`kalman_codegen.MAX_N`, equal to rounding). Arrays are
``(rows, n, n, runs)``, run axis innermost. ``rts_prepare`` flags an entry (t, r) whose P_{t|t} has
tr ≥ the rescue limit of :class:`kalman.SmoothStep` or is non-finite, or whose result is non-finite: the caller
redoes those entries on the numpy core (the rescue policy stays the core's). Kernels are generated,
written and cached by :mod:`netkf_cli.linalg.kalman_codegen`'s loader (one file per source hash, numba's disk
cache), depend only on (A, Q, limit) and are compiled once per machine.
"""

from __future__ import annotations

import numpy as np

from netkf_cli.linalg import kalman_codegen as kc

MAX_N = kc.MAX_N
"""Largest state dimension a kernel is generated for."""


def supported(n: int) -> bool:
    return 1 <= n <= MAX_N


def _header(fn: str, args: str) -> list[str]:
    return ["import numpy as np", "import numba as nb", "",
            "@nb.njit(cache=True, nogil=True, fastmath=False, error_model='numpy')", f"def {fn}({args}):"]


def _sym(i: int, j: int) -> tuple[int, int]:
    return (i, j) if i <= j else (j, i)


def source_prepare(A, Q, limit: float) -> str:
    """The source of ``rts_prepare(H, rows, J, C, flag)``: for t in ``rows`` and every run r, J[t] and C[t]
    from H[t] = P_{t|t} (all ``(T, n, n, runs)``); ``flag`` (T, runs) bool set where the numpy core must
    redo the entry (tr P_{t|t} ≥ ``limit``, or anything non-finite)."""
    A, Q = (np.atleast_2d(np.asarray(x, dtype=float)) for x in (A, Q))
    n = A.shape[0]
    rng = range(n)
    L = _header("rts_prepare", "H, rows, J, C, flag")
    L += [f"    limit = {kc._num(limit)}", "    runs = H.shape[3]", "    for q in range(rows.shape[0]):",
          "        t = rows[q]", "        Ht = H[t]", "        Jt = J[t]", "        Ct = C[t]", "        ft = flag[t]",
          "        for r in range(runs):"]
    ind = " " * 12
    for i in rng:
        for j in range(i, n):
            L.append(f"{ind}p{i}_{j} = Ht[{i}, {j}, r]")

    def p(i, j):
        a, b = _sym(i, j)
        return f"p{a}_{b}"

    # U = P Aᵀ: U[i, a] = Σ_j A[a, j] P[i, j]   (batched.right(P, Aᵀ) = left(A, Pᵀ)ᵀ, j ascending)
    for i in rng:
        for a in rng:
            L.append(f"{ind}u{i}_{a} = {kc._lin([(A[a, j], p(i, j)) for j in rng])}")
    # S = A U + Q (full: the core does not symmetrize it)
    for a in rng:
        for b in rng:
            L.append(f"{ind}s{a}_{b} = {kc._lin([(A[a, k], f'u{k}_{b}') for k in rng])} + {kc._num(Q[a, b])}")
    # X = S⁻¹ Uᵀ: X[a, c] = (S⁻¹ U[c, :]ᵀ)[a]
    if n == 1:
        L.append(f"{ind}i0_0 = 1.0 / s0_0")
        for c in rng:
            L.append(f"{ind}x0_{c} = i0_0 * u{c}_0")
    elif n == 2:  # batched.inv_small, then batched.matmul(inv, Uᵀ)
        L += [f"{ind}det = s0_0 * s1_1 - s0_1 * s1_0", f"{ind}i0_0 = s1_1 / det", f"{ind}i0_1 = -s0_1 / det",
              f"{ind}i1_0 = -s1_0 / det", f"{ind}i1_1 = s0_0 / det"]
        for a in rng:
            for c in rng:
                L.append(f"{ind}x{a}_{c} = i{a}_0 * u{c}_0 + i{a}_1 * u{c}_1")
    else:  # Cholesky S = L Lᵀ (upper triangle of S), then forward / back substitution per column
        # (reciprocals of the pivots: 3 divisions instead of n² + 2n, whose dependent chains bound the loop)
        for j in rng:
            acc = " - ".join([f"s{j}_{j}"] + [f"l{j}_{k} * l{j}_{k}" for k in range(j)])
            L.append(f"{ind}d{j} = 1.0 / np.sqrt({acc})")
            for i in range(j + 1, n):
                acc = " - ".join([f"s{j}_{i}"] + [f"l{i}_{k} * l{j}_{k}" for k in range(j)])
                L.append(f"{ind}l{i}_{j} = ({acc}) * d{j}")
        for c in rng:
            for a in rng:
                acc = " - ".join([f"u{c}_{a}"] + [f"l{a}_{k} * y{k}_{c}" for k in range(a)])
                L.append(f"{ind}y{a}_{c} = ({acc}) * d{a}")
            for a in reversed(rng):
                acc = " - ".join([f"y{a}_{c}"] + [f"l{k}_{a} * x{k}_{c}" for k in range(a + 1, n)])
                L.append(f"{ind}x{a}_{c} = ({acc}) * d{a}")
    # corr = U X (batched.matmul: a ascending); C = sym(P − corr)
    for i in rng:
        for j in rng:
            L.append(f"{ind}k{i}_{j} = " + " + ".join(f"u{i}_{a} * x{a}_{j}" for a in rng))
    chk = []
    for i in rng:
        for j in range(i, n):
            L.append(f"{ind}c{i}_{j} = 0.5 * (({p(i, j)} - k{i}_{j}) + ({p(j, i)} - k{j}_{i}))")
            chk.append(f"c{i}_{j}")
    for i in rng:
        for a in rng:
            L.append(f"{ind}Jt[{i}, {a}, r] = x{a}_{i}")
            chk.append(f"x{a}_{i}")
    for i in rng:
        for j in rng:
            a, b = _sym(i, j)
            L.append(f"{ind}Ct[{i}, {j}, r] = c{a}_{b}")
    L.append(f"{ind}tr = " + " + ".join(f"p{i}_{i}" for i in rng))
    L.append(f"{ind}ft[r] = not ((tr < limit) & " + " & ".join(f"({e} - {e} == 0.0)" for e in chk) + ")")
    return "\n".join(L) + "\n"


def source_chain(n: int) -> str:
    """The source of ``rts_chain(S0, sidx, J, C, tix, out)``: per output i, start from S0[sidx[i]] and apply
    the RTS map of rows tix[i, 0], tix[i, 1], … (C + J P Jᵀ, symmetrized; a non-finite result is ∞ in
    every entry, as :class:`kalman.SmoothStep`), into out[i] — the run loop innermost (branch-free: the
    compiler vectorizes it). Independent of the system's numbers (J and C carry them)."""
    rng = range(n)
    L = _header("rts_chain", "S0, sidx, J, C, tix, out")
    L += ["    K = tix.shape[0]", "    D = tix.shape[1]", "    runs = S0.shape[3]", "    inf = np.inf",
          "    for i in range(K):", "        s = sidx[i]", "        for r in range(runs):"]
    for a in rng:
        for b in rng:
            L.append(f"            out[i, {a}, {b}, r] = S0[s, {a}, {b}, r]")
    L += ["        o = out[i]", "        for u in range(D):", "            t = tix[i, u]", "            Jt = J[t]", "            Ct = C[t]",
          "            for r in range(runs):"]
    ind = " " * 16

    def p(i, j):
        a, b = _sym(i, j)
        return f"p{a}_{b}"

    for a in rng:
        for b in range(a, n):
            L.append(f"{ind}p{a}_{b} = o[{a}, {b}, r]")
    for a in rng:
        for b in rng:
            L.append(f"{ind}j{a}_{b} = Jt[{a}, {b}, r]")
    # Y = J P (batched.matmul, inner index ascending), Z = Y Jᵀ, new = sym(C + Z)
    for a in rng:
        for b in rng:
            L.append(f"{ind}y{a}_{b} = " + " + ".join(f"j{a}_{k} * {p(k, b)}" for k in rng))
    for a in rng:
        for b in rng:
            L.append(f"{ind}z{a}_{b} = " + " + ".join(f"y{a}_{k} * j{b}_{k}" for k in rng))
    new = []
    for a in rng:
        for b in range(a, n):
            L.append(f"{ind}e{a}_{b} = 0.5 * ((Ct[{a}, {b}, r] + z{a}_{b}) + (Ct[{b}, {a}, r] + z{b}_{a}))")
            new.append(f"e{a}_{b}")
    L.append(f"{ind}ok = " + " & ".join(f"({e} - {e} == 0.0)" for e in new))
    for a in rng:
        for b in rng:
            e = "e%d_%d" % _sym(a, b)
            L.append(f"{ind}o[{a}, {b}, r] = {e} if ok else inf")
    return "\n".join(L) + "\n"


_LOADED: dict = {}
"""The kernels loaded in this process, by what they are generated from (the smoother calls them once per block
of steps: generating the source again each time cost ~0.2 ms a call)."""


def kernel_prepare(A, Q, limit: float):
    """The compiled ``rts_prepare`` (:func:`source_prepare`) for this (A, Q, limit)."""
    A, Q = (np.atleast_2d(np.asarray(x, dtype=float)) for x in (A, Q))
    key = ("p", A.shape, A.tobytes(), Q.tobytes(), float(limit))
    k = _LOADED.get(key)
    if k is None:
        k = _LOADED[key] = kc._load(source_prepare(A, Q, limit), "netkf_rtsp", "rts_prepare")
    return k


def kernel_chain(n: int):
    """The compiled ``rts_chain`` (:func:`source_chain`) for n states."""
    k = _LOADED.get(("c", n))
    if k is None:
        k = _LOADED[("c", n)] = kc._load(source_chain(n), "netkf_rtsc", "rts_chain")
    return k
