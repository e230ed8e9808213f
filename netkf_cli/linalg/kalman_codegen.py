"""The Kalman core compiled per system: generated numba kernels of :meth:`kalman.Filter.step`.

For a given (A, C, Q, R, sensor groups) the filter's step is written out as scalar expressions with
the system's numbers as constants (zeros skipped, ones dropped), over the upper triangle of P kept
as one contiguous array per entry with the run axis innermost — design.md's fast layout — and the
inner loop over runs is branch-free (a lost packet multiplies the correction by γ = 0), so the
compiler vectorizes it. The equations are exactly the core's:

    predict  M = A P Aᵀ + Q
    update   per sensor group g (rows of C, block-diagonal R):  U = M C_gᵀ, S = C_g U + R_g,
             P ← M − γ_g U S⁻¹ Uᵀ   (S⁻¹ in closed form for groups of one or two rows)

A run whose prior trace exceeds the rescue limit, or is non-finite, is flagged; the caller
(:meth:`kalman.Filter.run`) redoes it on the numpy core, so the rescue policy stays the core's.
Kernels are cached on disk by the hash of their source (``NETKF_KERNEL_CACHE``, default
``~/.cache/netkf/kernels``); numba compiles each once per machine. Tested against the numpy core
in ``tests/unit/test_kalman_core.py``.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import sys
from pathlib import Path

import numpy as np

MAX_N = 6
"""Largest state dimension a kernel is generated for (the expression size grows as n³)."""
MAX_GROUP = 4
"""Largest sensor group (rows per stream) a kernel is generated for: S⁻¹ in closed form for one or two
rows, through an unrolled Cholesky factor S = L Lᵀ (correction W Wᵀ, W = U L⁻ᵀ) for three or four."""


def supported(n: int, groups) -> bool:
    return n <= MAX_N and all(1 <= len(g) <= MAX_GROUP for g in groups)


def _num(x: float) -> str:
    return repr(float(x))


def _lin(terms: list[tuple[float, str]]) -> str:
    """Σ coef·name with zeros skipped and ±1 folded; '0.0' when empty."""
    out = []
    for c, v in terms:
        if c == 0.0:
            continue
        if c == 1.0:
            out.append(f"+ {v}")
        elif c == -1.0:
            out.append(f"- {v}")
        else:
            out.append(f"+ {_num(c)} * {v}")
    if not out:
        return "0.0"
    s = " ".join(out)
    return s[2:] if s.startswith("+ ") else "-" + s[2:]


def cholesky_correction(n: int, m: int, tri, out, src, scale: str = "") -> list[str]:
    """Straight-line lines of P_out = P_src − scale·U S⁻¹ Uᵀ for m ≥ 3 outputs, from the locals ``u{i}_{a}`` (U = P Cᵀ)
    and ``s{a}_{b}`` (S, upper triangle): Cholesky S = L Lᵀ, W = U L⁻ᵀ, U S⁻¹ Uᵀ = W Wᵀ (the same operations in the
    same order for every kernel that uses it). ``out(i, j)`` / ``src(i, j)`` name P's upper-triangle entries."""
    L = []
    for j in range(m):
        acc = " - ".join([f"s{j}_{j}"] + [f"l{j}_{k} * l{j}_{k}" for k in range(j)])
        L.append(f"l{j}_{j} = np.sqrt({acc})")
        for i in range(j + 1, m):
            acc = " - ".join([f"s{j}_{i}"] + [f"l{i}_{k} * l{j}_{k}" for k in range(j)])
            L.append(f"l{i}_{j} = ({acc}) / l{j}_{j}")
    for i in range(n):
        for a in range(m):
            acc = " - ".join([f"u{i}_{a}"] + [f"w{i}_{b} * l{a}_{b}" for b in range(a)])
            L.append(f"w{i}_{a} = ({acc}) / l{a}_{a}")
    for i, j in tri:
        corr = " + ".join(f"w{i}_{a} * w{j}_{a}" for a in range(m))
        L.append(f"{out(i, j)} = {src(i, j)} - {scale}({corr})")
    return L


def gain_correction(n: int, m: int, tri, out, src, g: str = "") -> list[str]:
    """Straight-line lines of P_out = P_src − K Uᵀ with K = U S⁻¹·g for m ≤ 2 outputs (S inverted in closed form),
    from the locals ``u{i}_{a}`` and ``s{a}_{b}``; ``g`` a factor folded into S⁻¹ (the arrival γ or a count), ""
    for none. The same operations in the same order for every kernel that uses it."""
    if m == 1:
        L = [f"i0_0 = {g or '1.0'} / s0_0"]
        inv = {(0, 0): "i0_0"}
    else:
        f = f"{g} * " if g else ""
        L = ["det = s0_0 * s1_1 - s0_1 * s0_1", f"i0_0 = {f}s1_1 / det", f"i1_1 = {f}s0_0 / det",
             f"i0_1 = -{f}s0_1 / det"]
        inv = {(0, 0): "i0_0", (1, 1): "i1_1", (0, 1): "i0_1", (1, 0): "i0_1"}
    for i in range(n):
        for a in range(m):
            L.append(f"k{i}_{a} = " + " + ".join(f"u{i}_{b} * {inv[(b, a)]}" for b in range(m)))
    for i, j in tri:
        corr = " + ".join(f"k{i}_{a} * u{j}_{a}" for a in range(m))
        L.append(f"{out(i, j)} = {src(i, j)} - ({corr})")
    return L


def source(A, C, Q, R, groups, limit: float) -> str:
    """The Python source of ``advance(P, gam, t0, t1, flag)`` for this system (see the module doc)."""
    A, C, Q, R = (np.asarray(x, dtype=float) for x in (A, C, Q, R))
    n = A.shape[0]
    tri = [(i, j) for i in range(n) for j in range(i, n)]
    pos = {ij: k for k, ij in enumerate(tri)}

    def p(name, i, j):
        return f"{name}{min(i, j)}_{max(i, j)}"

    L = []
    L.append("import numpy as np")
    L.append("import numba as nb")
    L.append("")
    L.append("@nb.njit(cache=True, nogil=True, fastmath=False, error_model='numpy')")
    L.append("def advance(P, gam, t0, t1, flag):")
    L.append("    runs = P.shape[1]")
    L.append(f"    limit = {_num(limit)}")
    L.append("    for t in range(t0, t1):")
    L.append("        for r in range(runs):")
    for (i, j), k in pos.items():
        L.append(f"            {p('p', i, j)} = P[{k}, r]")
    # predict: X = A P (full n×n), M = X Aᵀ + Q (upper triangle)
    for i in range(n):
        for j in range(n):
            L.append(f"            x{i}_{j} = {_lin([(A[i, k], p('p', k, j)) for k in range(n)])}")
    for i, j in tri:
        e = _lin([(A[j, k], f"x{i}_{k}") for k in range(n)])
        L.append(f"            {p('m', i, j)} = {e} + {_num(Q[i, j])}")
    L.append("            tr = " + " + ".join(p("m", i, i) for i in range(n)))
    L.append("            flag[r] = flag[r] or not (tr <= limit)")
    cur = "m"
    for g_idx, rows in enumerate(groups):
        rows = list(rows)
        mg = len(rows)
        Cg, Rg = C[rows], R[np.ix_(rows, rows)]
        L.append(f"            g = gam[{g_idx}, t, r]")
        # U = M Cgᵀ (n × mg)
        for i in range(n):
            for a in range(mg):
                L.append(f"            u{i}_{a} = {_lin([(Cg[a, k], p(cur, i, k)) for k in range(n)])}")
        # S = Cg U + Rg (mg × mg, symmetric)
        for a in range(mg):
            for b in range(a, mg):
                L.append(f"            s{a}_{b} = {_lin([(Cg[a, k], f'u{k}_{b}') for k in range(n)])} + {_num(Rg[a, b])}")
        if mg >= 3:  # Cholesky S = L Lᵀ; U S⁻¹ Uᵀ = W Wᵀ with W = U L⁻ᵀ
            nxt = f"q{g_idx}_"
            L += ["            " + x for x in cholesky_correction(n, mg, tri, lambda i, j, o=nxt: p(o, i, j),
                                                                  lambda i, j, c=cur: p(c, i, j), "g * ")]
            cur = nxt
            continue
        nxt = f"q{g_idx}_"  # K = U S⁻¹ γ ; P ← M − K Uᵀ (upper triangle)
        L += ["            " + x for x in gain_correction(n, mg, tri, lambda i, j, o=nxt: p(o, i, j),
                                                            lambda i, j, c=cur: p(c, i, j), "g")]
        cur = nxt
    L.append("            tr = " + " + ".join(p(cur, i, i) for i in range(n)))
    L.append("            flag[r] = flag[r] or not (tr == tr)  # a NaN from the update: the numpy core redoes it")
    for (i, j), k in pos.items():
        L.append(f"            P[{k}, r] = {p(cur, i, j)}")
    return "\n".join(L) + "\n"


def _lin_symbolic(terms: list[tuple[float | str, str]]) -> str:
    """:func:`_lin` where a coefficient may be a local's name (then ``name * v``, as ``_lin`` writes a constant)."""
    out = []
    for c, v in terms:
        if isinstance(c, str):
            out.append(f"+ {c} * {v}")
        elif c == 1.0:
            out.append(f"+ {v}")
        elif c == -1.0:
            out.append(f"- {v}")
        elif c != 0.0:
            out.append(f"+ {_num(c)} * {v}")
    if not out:
        return "0.0"
    s = " ".join(out)
    return s[2:] if s.startswith("+ ") else "-" + s[2:]


def _symbols(A, C1, Q, R1):
    """(A, C1, Q, R1) as object arrays: the entries 0 and ±1 kept as numbers (dropped / folded as :func:`_lin`
    does: the kernel's structure), every other entry the name of its local (:func:`_system_locals`)."""
    def sym(X, name, tri):
        r, c = X.shape
        return np.array([[float(X[i, j]) if X[i, j] in (0.0, 1.0, -1.0) else
                          (f"{name}{min(i, j)}_{max(i, j)}" if tri else f"{name}{i}_{j}") for j in range(c)]
                         for i in range(r)], dtype=object)
    return sym(A, "sa", False), sym(C1, "sc", False), sym(Q, "sq", True), sym(R1, "sr", True)


def _system_locals(n: int, mg: int, ind: str = "    ") -> list[str]:
    """Lines reading the system vector ``sv`` (:func:`system_vector`) into the locals of :func:`_symbols`
    and ``limit``."""
    L, k = [], 0
    for name, r, c, tri in (("sa", n, n, False), ("sc", mg, n, False), ("sq", n, n, True), ("sr", mg, mg, True)):
        for i in range(r):
            for j in range(i if tri else 0, c):
                L.append(f"{ind}{name}{i}_{j} = sv[{k}]")
                k += 1
    return L + [f"{ind}limit = sv[{k}]"]


def system_vector(A, C1, Q, R1, limit: float) -> np.ndarray:
    """The float64 vector ``sv`` a symbolic kernel reads (:func:`_system_locals`): A and C1 row by row, the
    upper triangles of Q and R1, then the rescue limit."""
    A, C1, Q, R1 = _as2(A, C1, Q, R1)
    iq, ir = np.triu_indices(A.shape[0]), np.triu_indices(C1.shape[0])
    return np.ascontiguousarray(np.concatenate([A.ravel(), C1.ravel(), Q[iq], R1[ir], [float(limit)]]))


def _count_step(A, C1, Q, R1, ind: str, g: str, symbolic: bool = False) -> list[str]:
    """Straight-line lines of one predicted count update, from the locals ``p{i}_{j}`` (upper triangle of
    P_{k−1|k−1}) to ``q{i}_{j}`` (P_{k|k}), count ``g`` (a float expression); raises ``flag[r]`` when the
    prior's trace exceeds ``limit`` or is non-finite, or the update gives a NaN. ``symbolic``: the system's
    numbers other than 0 and ±1 are the locals of :func:`_system_locals` (``sa``/``sc``/``sq``/``sr``), so the
    source depends on the zero / ±1 pattern only (one kernel for a whole grid over Q or the loss) and is the
    inlined expression with names for numbers: the same operations in the same order, the same bits."""
    n, mg = A.shape[0], C1.shape[0]
    tri = [(i, j) for i in range(n) for j in range(i, n)]

    def p(name, i, j):
        return f"{name}{min(i, j)}_{max(i, j)}"

    lin, num = _lin, _num
    if symbolic:
        lin = _lin_symbolic
        num = str  # a name, or repr of 0.0 / ±1.0 (as _num)
        A, C1, Q, R1 = _symbols(A, C1, Q, R1)

    L = []
    for i in range(n):
        for j in range(n):
            L.append(f"x{i}_{j} = {lin([(A[i, k], p('p', k, j)) for k in range(n)])}")
    for i, j in tri:
        L.append(f"{p('m', i, j)} = {lin([(A[j, k], f'x{i}_{k}') for k in range(n)])} + {num(Q[i, j])}")
    L.append("tr = " + " + ".join(p("m", i, i) for i in range(n)))
    L.append("flag[r] = flag[r] or not (tr <= limit)")
    L.append(f"g = {g}")
    for i in range(n):
        for a in range(mg):
            L.append(f"u{i}_{a} = {lin([(C1[a, k], p('m', i, k)) for k in range(n)])}")
    for a in range(mg):
        for b in range(a, mg):
            L.append(f"s{a}_{b} = g * ({lin([(C1[a, k], f'u{k}_{b}') for k in range(n)])}) + {num(R1[a, b])}")
    if mg >= 3:
        L += cholesky_correction(n, mg, tri, lambda i, j: p("q", i, j), lambda i, j: p("m", i, j), "g * ")
    else:
        L += gain_correction(n, mg, tri, lambda i, j: p("q", i, j), lambda i, j: p("m", i, j), "g")
    L.append("tr = " + " + ".join(p("q", i, i) for i in range(n)))
    L.append("flag[r] = flag[r] or not (tr == tr)")
    return [ind + x for x in L]


def _header(fn: str, args: str, limit: float | None, n: int = 0, mg: int = 0) -> list[str]:
    """The kernel's first lines; ``limit`` None = symbolic (the system and limit read from ``sv``)."""
    L = ["import numpy as np", "import numba as nb", "",
         "@nb.njit(cache=True, nogil=True, fastmath=False, error_model='numpy')"]
    if limit is None:
        return L + [f"def {fn}({args}, sv):"] + _system_locals(n, mg)
    return L + [f"def {fn}({args}):", f"    limit = {_num(limit)}"]


def _as2(*xs):
    return (np.atleast_2d(np.asarray(x, dtype=float)) for x in xs)


def source_counts(A, C1, Q, R1, limit: float | None) -> str:
    """The source of ``advance_counts(P, cnt, t0, t1, flag)``: the count update of N identical sensors
    (:func:`netkf_cli.linalg.kalman.update_counts`, Chiuso & Schenato eq. (14)) after the prediction, per run

        M = A P Aᵀ + Q,  U = M C1ᵀ,  S = c·C1 U + R1,  P ← M − c·U S⁻¹ Uᵀ,   c = cnt[t, r]

    (c = 0 leaves M; S⁻¹ in closed form for one or two rows, the unrolled Cholesky factor for three or
    four), the upper triangle of P as in :func:`source`, the same rescue flag (prior trace above
    ``limit`` or non-finite, or a NaN after the update: the caller redoes the run on the numpy core).
    ``limit`` None: the symbolic kernel ``advance_counts(P, cnt, t0, t1, flag, sv)`` of every system of
    these shapes (``sv`` = :func:`system_vector`; the same bits for finite P, one compile per shape)."""
    A, C1, Q, R1 = _as2(A, C1, Q, R1)
    n = A.shape[0]
    tri = [(i, j) for i in range(n) for j in range(i, n)]
    L = _header("advance_counts", "P, cnt, t0, t1, flag", limit, n, C1.shape[0])
    L += ["    runs = P.shape[1]", "    for t in range(t0, t1):", "        for r in range(runs):"]
    L += [f"            p{i}_{j} = P[{k}, r]" for k, (i, j) in enumerate(tri)]
    L += _count_step(A, C1, Q, R1, " " * 12, "float(cnt[t, r])", limit is None)
    L += [f"            P[{k}, r] = q{i}_{j}" for k, (i, j) in enumerate(tri)]
    return "\n".join(L) + "\n"


def source_ibf(A, C1, Q, R1, limit: float | None) -> str:
    """The source of ``ibf_eval(arrival, off, last, t0, t1, full, out, flag, cum)``: ``last`` (N, runs) int32
    (the last arrival, −1 = nothing yet) advanced over trace steps t0 … t1 − 1 of ``arrival`` (N, steps, runs)
    holding trace steps off, off + 1, …,
    then the infinite-bandwidth centre with N identical sensors at trace step t = t1 − 1, per run
    (:class:`netkf_cli.estimators.fusion.IBF`): τ_i = t − last_i, K = max τ (≤ t + 1); from the full-information
    ``full[t + 1 − K]`` (packed upper triangle, (J, n(n+1)/2)), K count steps with ℓ_b = #{i : τ_i ≤ b},
    b = K − 1 … 0 (the count form of the sensors {i : τ_i ≤ b}); ``out`` (n(n+1)/2, runs); ``cum``
    int64 scratch of ≥ t + 2 zeros (left zero); ``flag`` as in :func:`source_counts`; ``limit`` None: symbolic,
    as :func:`source_counts` (argument ``sv`` last)."""
    A, C1, Q, R1 = _as2(A, C1, Q, R1)
    n = A.shape[0]
    tri = [(i, j) for i in range(n) for j in range(i, n)]
    L = _header("ibf_eval", "arrival, off, last, t0, t1, full, out, flag, cum", limit, n, C1.shape[0])
    L += _advance_last()
    L += ["    t = t1 - 1",
          "    for r in range(runs):",
          "        K = 0",
          "        for i in range(N):",
          "            tau = t - last[i, r]",
          "            cum[tau] += 1",
          "            if tau > K:",
          "                K = tau",
          "        for b in range(1, K):",
          "            cum[b] += cum[b - 1]",
          "        j0 = t + 1 - K"]
    L += [f"        p{i}_{j} = full[j0, {k}]" for k, (i, j) in enumerate(tri)]
    L += ["        for b in range(K - 1, -1, -1):"]
    L += _count_step(A, C1, Q, R1, " " * 12, "float(cum[b])", limit is None)
    L += [f"            p{i}_{j} = q{i}_{j}" for i, j in tri]
    L += [f"        out[{k}, r] = p{i}_{j}" for k, (i, j) in enumerate(tri)]
    L += ["        for b in range(K + 1):", "            cum[b] = 0"]
    return "\n".join(L) + "\n"


def _advance_last() -> list[str]:
    """Lines updating ``last`` (N, runs) with the arrivals of trace steps t0 … t1 − 1 (run axis innermost;
    ``arrival`` holds steps off, off + 1, …: a block of the trace)."""
    return ["    N, runs = last.shape",
            "    for s in range(t0, t1):",
            "        for i in range(N):",
            "            for r in range(runs):",
            "                last[i, r] = s if arrival[i, s - off, r] else last[i, r]  # a select: no branch to mispredict"]


def source_olpef(n: int) -> str:
    """The source of ``olpef_eval(arrival, off, last, t0, t1, sxx, D, TS, out, vals, cnts)`` (``last``
    advanced as in :func:`source_ibf`, then at t = t1 − 1): OLPEF's error covariance (Chiuso & Schenato
    eqs (10)–(11); :meth:`netkf_cli.estimators.fusion.OLPEFTables.error_cov`) per run from the histogram h
    of the received τ_i = t − last_i ≤ t (``cnts`` float scratch of ≥ L zeros, left zero; ``vals`` int64
    scratch of N entries: the distinct τ):

        Σ = sxx + Σ_a h_a D_a + Σ_a h_a² TS_aa + 2 Σ_{a<b} h_a h_b TS_ab,

    D_a = sym(diag_a) − lin_a − lin_aᵀ and TS_ab = sym(TM_ab) = TS_ba, every table packed as upper
    triangles (sxx (n(n+1)/2,), D (L, ·), TS (L, L, ·)); ``out`` (n(n+1)/2, runs). Returns the largest
    received τ: if it is ≥ L the tables were too short (those runs are wrong) and the caller extends them
    and calls again."""
    nt = n * (n + 1) // 2
    L = ["import numpy as np", "import numba as nb", "",
         "@nb.njit(cache=True, nogil=True, fastmath=False, error_model='numpy')",
         "def olpef_eval(arrival, off, last, t0, t1, sxx, D, TS, out, vals, cnts):"]
    L += _advance_last()
    L += ["    t = t1 - 1",
          "    Kmax = D.shape[0] - 1",
          "    worst = 0",
          "    for r in range(runs):",
          "        m = 0",
          "        for i in range(N):",
          "            tau = t - last[i, r]",
          "            if tau > t:",
          "                continue",
          "            if tau > worst:",
          "                worst = tau",
          "            if tau > Kmax:",
          "                continue",
          "            vals[m] = tau  # kept if tau is new (branch-free: a first occurrence is unpredictable)",
          "            m += cnts[tau] == 0.0",
          "            cnts[tau] += 1.0"]
    L += [f"        e{k} = sxx[{k}]" for k in range(nt)]
    L += ["        for q in range(m):", "            a = vals[q]", "            h = cnts[a]", "            hh = h * h"]
    L += [f"            e{k} += h * D[a, {k}] + hh * TS[a, a, {k}]" for k in range(nt)]
    L += ["            for q2 in range(q + 1, m):", "                b = vals[q2]", "                hb = 2.0 * h * cnts[b]"]
    L += [f"                e{k} += hb * TS[a, b, {k}]" for k in range(nt)]
    L += [f"        out[{k}, r] = e{k}" for k in range(nt)]
    L += ["        for q in range(m):", "            cnts[vals[q]] = 0.0"]
    L.append("    return worst")
    return "\n".join(L) + "\n"


SELECT_SOURCE = """import numpy as np
import numba as nb

@nb.njit(cache=True, nogil=True, fastmath=False)
def select_given_counts(raw, left, r, out):
    one53 = np.uint64(1) << np.uint64(53)
    sh = np.uint64(11)
    lf = np.uint64(left)
    for j in range(raw.size):
        h = (raw[j] >> sh) * lf < r[j]
        out[j] = h
        if h:
            r[j] -= one53
"""
"""One sensor's step of the selection sampler (:func:`netkf_cli.channels.multi.arrivals_given_counts`)
compiled: arrived = (raw >> 11)·left < r, r −= 2⁵³ on arrival — the numpy passes fused, the same bits."""


def kernel_select():
    """The compiled ``select_given_counts`` (:data:`SELECT_SOURCE`)."""
    return _load(SELECT_SOURCE, "netkf_select", "select_given_counts")


def _cache_dir() -> Path:
    d = Path(os.environ.get("NETKF_KERNEL_CACHE", Path.home() / ".cache" / "netkf" / "kernels"))
    d.mkdir(parents=True, exist_ok=True)
    return d


_LOADED: dict[str, object] = {}


def kernel(A, C, Q, R, groups, limit: float):
    """The compiled ``advance`` for this system (generated, written once, imported, numba-cached)."""
    return _load(source(A, C, Q, R, groups, limit), "netkf_kf", "advance")


def kernel_counts(A, C1, Q, R1, limit: float | None):
    """The compiled ``advance_counts`` (:func:`source_counts`) for N identical sensors (C1, R1); ``limit``
    None: the symbolic kernel of these shapes (pass :func:`system_vector` as ``sv``)."""
    return _load(source_counts(A, C1, Q, R1, limit), "netkf_mf", "advance_counts")


def kernel_ibf(A, C1, Q, R1, limit: float | None):
    """The compiled ``ibf_eval`` (:func:`source_ibf`) for N identical sensors (C1, R1); ``limit`` None:
    symbolic, as :func:`kernel_counts`."""
    return _load(source_ibf(A, C1, Q, R1, limit), "netkf_ibf", "ibf_eval")


def kernel_olpef(n: int):
    """The compiled ``olpef_eval`` (:func:`source_olpef`) for n states."""
    return _load(source_olpef(n), "netkf_olpef", "olpef_eval")


def _load(src: str, prefix: str, fn: str):
    key = hashlib.sha256(src.encode()).hexdigest()[:20]
    if key in _LOADED:
        return _LOADED[key]
    path = _cache_dir() / f"{prefix}_{key}.py"
    if not path.exists():
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(src, encoding="utf-8")
        os.replace(tmp, path)  # atomic: concurrent workers never import half a file
    name = f"{prefix}_{key}"
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    _LOADED[key] = getattr(mod, fn)
    return _LOADED[key]


def pack(P: np.ndarray) -> np.ndarray:
    """(n, n, runs) → (n(n+1)/2, runs), the upper triangle row by row (the kernel's layout)."""
    n = P.shape[0]
    iu = np.triu_indices(n)
    return np.ascontiguousarray(P[iu[0], iu[1], :])


_TRIU: dict[int, tuple[np.ndarray, np.ndarray]] = {}


def unpack(T: np.ndarray, n: int) -> np.ndarray:
    """(…, n(n+1)/2, runs) → (…, n, n, runs), symmetric (a new array; n = 1 a reshaped copy)."""
    if n == 1:
        return T[..., None, :].copy()
    iu = _TRIU.get(n)
    if iu is None:
        iu = _TRIU[n] = np.triu_indices(n)
    P = np.empty(T.shape[:-2] + (n, n, T.shape[-1]))
    P[..., iu[0], iu[1], :] = T
    P[..., iu[1], iu[0], :] = T
    return P
