"""The PSD-order reductions compiled per state dimension: generated numba code with P in scalar locals.

:mod:`netkf_cli.linalg._reduce_numba` states the method (certified decisions of λ_max(P) ≤ th by bounds, then
LDLᵀ certificates, λ_max itself only inside a 1e-11 margin; a binary search over ascending thresholds);
these kernels write it out for one n (the entries of the packed upper triangle as locals ``p{i}_{j}``,
the LDLᵀ unrolled), so nothing is a function call or an array access per run but the entries' loads,
and they leave a run whose λ_max lies within the margin of a threshold to the caller, which decides it
with the numpy reducer's own ``batched.lambda_max`` (eigvalsh) — so the decisions are the numpy
reducer's exactly, by construction, wherever the certificates hold (a generic-n version with small work arrays ran 10–20× slower: every call passes and reference-counts
its arrays). Cached like every generated kernel (:func:`netkf_cli.linalg.kalman_codegen._load`); decisions
equal to eigvalsh's (tests/engine/test_reduce_numba.py).
"""

from __future__ import annotations

from netkf_cli.linalg import kalman_codegen as kc
from netkf_cli.core.tolerances import LAMBDA_MAX_MARGIN


def _tri(n):
    return [(i, j) for i in range(n) for j in range(i, n)]


def _p(i, j):
    return f"p{min(i, j)}_{max(i, j)}"


def _ldl(n: int, t: str, ind: str) -> list[str]:
    """Lines setting ``sgn`` (+1 certified t·I − P > 0, −1 certified not ⪰ 0, 0 neither) for the locals P."""
    L = []
    for i in range(n):
        for j in range(i + 1):
            L.append(f"{ind}w{i}_{j} = {t} - {_p(i, j)}" if i == j else f"{ind}w{i}_{j} = -{_p(i, j)}")
        L.append(f"{ind}m{i} = abs(w{i}_{i})")

    def step(k: int, ind: str) -> list[str]:
        out = [f"{ind}if m{k} > lim:", f"{ind}    sgn = 0",
               f"{ind}elif not w{k}_{k} > 0.0:", f"{ind}    sgn = -1 if w{k}_{k} < -1e-9 * m{k} else 0"]
        if k == n - 1:
            return out + [f"{ind}else:", f"{ind}    sgn = 1"]
        out.append(f"{ind}else:")
        for i in range(k + 1, n):
            out.append(f"{ind}    f{i} = w{i}_{k} / w{k}_{k}")
            for j in range(k + 1, i + 1):
                out.append(f"{ind}    x = f{i} * w{j}_{k}")
                out.append(f"{ind}    w{i}_{j} = w{i}_{j} - x")
                if j == i:
                    out.append(f"{ind}    m{i} = m{i} + abs(x)")
        return out + step(k + 1, ind + "    ")

    return L + step(0, ind)


def _search(n: int, ind: str) -> list[str]:
    """Lines setting ``i0`` = the number of ascending thresholds ``thr`` below λ_max of the locals P (run r),
    or ``ambig`` when a threshold lies within the margin of λ_max (the caller decides that run with numpy)."""
    tri_abs = {i: [f"abs({_p(i, j)})" for j in range(n) if j != i] for i in range(n)}
    L = [f"{ind}lo = " + (f"max({', '.join(_p(i, i) for i in range(n))})" if n > 1 else "p0_0"),
         f"{ind}hi = " + (f"max({', '.join(' + '.join([_p(i, i)] + tri_abs[i]) for i in range(n))})" if n > 1 else "p0_0"),
         f"{ind}sc = " + (f"max({', '.join(' + '.join([f'abs({_p(i, i)})'] + tri_abs[i]) for i in range(n))})" if n > 1 else "abs(p0_0)"),
         f"{ind}ambig = False",
         f"{ind}i0 = 0",
         f"{ind}i1 = nM",
         f"{ind}while i0 < i1:",
         f"{ind}    mid = (i0 + i1) // 2",
         f"{ind}    th = thr[mid]"]
    if n == 1:
        L.append(f"{ind}    yes = p0_0 <= th")
    else:
        i2 = ind + "        "
        L += [f"{ind}    ref = abs(th) + sc",
              f"{ind}    mg = {kc._num(LAMBDA_MAX_MARGIN)} * ref",
              f"{ind}    lim = 1e3 * ref",
              f"{ind}    if hi + mg < th:", f"{ind}        yes = True",
              f"{ind}    elif lo - mg > th:", f"{ind}        yes = False",
              f"{ind}    else:"]
        L += _ldl(n, "(th - mg)", i2)
        L += [f"{i2}if sgn == 1:", f"{i2}    yes = True", f"{i2}else:"]
        L += _ldl(n, "(th + mg)", i2 + "    ")
        L += [f"{i2}    if sgn == -1:", f"{i2}        yes = False", f"{i2}    else:",
              f"{i2}        ambig = True", f"{i2}        break"]
    L += [f"{ind}    if yes:", f"{ind}        i1 = mid", f"{ind}    else:", f"{ind}        i0 = mid + 1"]
    return L


def _head(fn: str, args: str) -> list[str]:
    return ["import math", "import numpy as np", "import numba as nb", "",
            "@nb.njit(cache=True, nogil=True, fastmath=False, error_model='numpy')", f"def {fn}({args}):"]


def _loads(n: int, ind: str) -> list[str]:
    L = [f"{ind}{_p(i, j)} = T[{k}, r]" for k, (i, j) in enumerate(_tri(n))]
    L.append(f"{ind}fin = " + " and ".join(f"math.isfinite({_p(i, j)})" for i, j in _tri(n)))
    return L


def source_dist(n: int) -> str:
    """``dist_counts(T, thr, order, cnt, amb)``: cnt[order[i]] += #runs with λ_max ≤ thr[i] (thr ascending)
    over the runs it decides; ``amb[r]`` raised for the runs it leaves to the caller (a threshold within
    the margin of their λ_max); returns the number of runs with a non-finite P (counted as not ≤ M)."""
    L = _head("dist_counts", "T, thr, order, cnt, amb")
    L += ["    nM = thr.shape[0]", "    c = np.zeros(nM + 1)", "    bad = 0",
          "    for r in range(T.shape[1]):"]
    L += _loads(n, "        ")
    L += ["        if not fin:", "            bad += 1", "            continue"]
    L += _search(n, "        ")
    L += ["        if ambig:", "            amb[r] = True", "            continue", "        c[i0] += 1.0"]
    L += ["    acc = 0.0", "    for i in range(nM):", "        acc += c[i]", "        cnt[order[i]] += acc", "    return bad"]
    return "\n".join(L) + "\n"


def source_stationary(n: int) -> str:
    """``stationary_acc(T, thr, tr_acc, bad, hist, amb)``: per run, bad |= P not finite; tr_acc += tr P
    (finite runs); hist[i0, r] += 1 with i0 the number of the ascending thresholds ``thr`` below λ_max (finite
    runs it decides; one write per run and step: the indicator of threshold i is Σ_{i0 ≤ i} hist[i0], summed
    once per chunk by the caller; ``thr`` empty: no indicator); ``amb[r]`` raised for the runs it leaves to the
    caller."""
    L = _head("stationary_acc", "T, thr, tr_acc, bad, hist, amb")
    L += ["    nM = thr.shape[0]", "    for r in range(T.shape[1]):"]
    L += _loads(n, "        ")
    L += _stationary_step(n, "        ", "amb")
    return "\n".join(L) + "\n"


def _stationary_step(n: int, ind: str, amb: str) -> list[str]:
    """The per-run body of the stationary accumulation, its packed triangle and ``fin`` loaded (at indent ``ind``;
    ``amb`` the array its ambiguous runs are raised in)."""
    return [f"{ind}if not fin:", f"{ind}    bad[r] = True", f"{ind}    continue",
            f"{ind}tr_acc[r] += " + " + ".join(_p(i, i) for i in range(n)),
            f"{ind}if nM == 0:", f"{ind}    continue",
            *_search(n, ind),
            f"{ind}if ambig:", f"{ind}    {amb}[r] = True", f"{ind}    continue",
            f"{ind}hist[i0, r] += 1.0"]


def source_stationary_block(n: int) -> str:
    """``stationary_block(X, thr, tr_acc, bad, hist, amb)``: :func:`source_stationary` for the K steps of one block
    X (K, n, n, runs) at once, step after step (so per run the same sums in the same order as K calls), each step's
    packed triangle formed in the loop as the engine's ``_tri`` forms it, (P[i, j] + P[j, i]) · 0.5 (the same two
    operations); ``amb`` (K, runs) raised for the (step, run) it leaves to the caller. n = 1:
    :func:`_source_stationary_block_scalar`."""
    if n == 1:
        return _source_stationary_block_scalar()
    L = _head("stationary_block", "X, thr, tr_acc, bad, hist, amb")
    L += ["    nM = thr.shape[0]", "    for s in range(X.shape[0]):", "        Xs = X[s]", "        ams = amb[s]",
          "        for r in range(X.shape[3]):"]
    L += [f"            {_p(i, j)} = (Xs[{i}, {j}, r] + Xs[{j}, {i}, r]) * 0.5" for i, j in _tri(n)]
    L.append("            fin = " + " and ".join(f"math.isfinite({_p(i, j)})" for i, j in _tri(n)))
    L += _stationary_step(n, "            ", "ams")
    return "\n".join(L) + "\n"


def _source_stationary_block_scalar() -> str:
    """:func:`source_stationary_block` for n = 1, branch-free so that the run loops vectorize: per step, one loop
    adds p = (P + P)·0.5 to tr_acc where p is finite (+0.0 elsewhere: tr_acc, a sum from +0.0, is never −0.0, so
    unchanged) and raises ``bad`` where it is not; then per threshold bin i one loop counts the finite runs whose
    p lies in it — the binary search's i0 = i ⇔ (i = nM or p ≤ thr[i]) and (i = 0 or not p ≤ thr[i − 1]), thr
    ascending — the same counts. A scalar λ_max is p itself: no run is ambiguous."""
    L = _head("stationary_block", "X, thr, tr_acc, bad, hist, amb")
    L += ["    nM = thr.shape[0]", "    runs = X.shape[3]", "    for s in range(X.shape[0]):", "        Xs = X[s, 0, 0]",
          "        for r in range(runs):",
          "            p = (Xs[r] + Xs[r]) * 0.5",
          "            fin = math.isfinite(p)",
          "            bad[r] = bad[r] | (fin ^ True)",
          "            tr_acc[r] += p if fin else 0.0",
          "        if nM == 0:", "            continue",
          "        h, hi = hist[0], thr[0]",
          "        for r in range(runs):  # i = 0: p ≤ thr[0]",
          "            p = (Xs[r] + Xs[r]) * 0.5",
          "            h[r] += 1.0 if math.isfinite(p) & (p <= hi) else 0.0",
          "        for i in range(1, nM):",
          "            h, lo, hi = hist[i], thr[i - 1], thr[i]",
          "            for r in range(runs):",
          "                p = (Xs[r] + Xs[r]) * 0.5",
          "                h[r] += 1.0 if math.isfinite(p) & (p <= hi) & ((p <= lo) ^ True) else 0.0",
          "        h, lo = hist[nM], thr[nM - 1]",
          "        for r in range(runs):  # i = nM: not p ≤ thr[nM − 1]",
          "            p = (Xs[r] + Xs[r]) * 0.5",
          "            h[r] += 1.0 if math.isfinite(p) & ((p <= lo) ^ True) else 0.0"]
    return "\n".join(L) + "\n"


_KERNELS: dict = {}


def source_moments(n: int) -> str:
    """``moment_sums(T, want_lmax, out, acc, acc2, b)`` over the runs of T: out ← [Σtr, Σtr², Σtr³, Σtr⁴, Σλ,
    Σλ², #non-finite, max(0, tr)] of the finite runs (λ sums 0 unless ``want_lmax``: λ_max by
    :func:`netkf_cli.linalg._reduce_numba.lmax_loaded` on the scratch b (n, n)); acc, acc2 (n(n+1)/2,) ← Σ P, Σ P²
    of the packed entries (as :func:`netkf_cli.linalg._reduce_numba.moment_sums`, with P in scalar locals)."""
    tri = _tri(n)
    L = ["import math", "import numpy as np", "import numba as nb", "from netkf_cli.linalg._reduce_numba import lmax_loaded", "",
         "@nb.njit(cache=True, nogil=True, fastmath=False, error_model='numpy')",
         "def moment_sums(T, want_lmax, out, acc, acc2, b):",
         "    s1 = 0.0", "    s2 = 0.0", "    s3 = 0.0", "    s4 = 0.0", "    l1 = 0.0", "    l2 = 0.0",
         "    bad = 0", "    mx = 0.0"]
    L += [f"    e{k} = 0.0\n    f{k} = 0.0" for k in range(len(tri))]
    L += ["    for r in range(T.shape[1]):"]
    L += _loads(n, "        ")
    L += ["        if not fin:", "            bad += 1", "            continue"]
    for k, (i, j) in enumerate(tri):
        L += [f"        e{k} += {_p(i, j)}", f"        f{k} += {_p(i, j)} * {_p(i, j)}"]
    L += ["        tr = " + " + ".join(_p(i, i) for i in range(n)),
          "        t2 = tr * tr", "        s1 += tr", "        s2 += t2", "        s3 += t2 * tr", "        s4 += t2 * t2",
          "        if tr > mx:", "            mx = tr",
          "        if want_lmax:"]
    L += [f"            b[{i}, {j}] = {_p(i, j)}" for i in range(n) for j in range(n)]
    L += ["            lm = lmax_loaded(b, " + str(n) + ")", "            l1 += lm", "            l2 += lm * lm"]
    L += [f"    acc[{k}] = e{k}\n    acc2[{k}] = f{k}" for k in range(len(tri))]
    L += ["    out[0] = s1", "    out[1] = s2", "    out[2] = s3", "    out[3] = s4", "    out[4] = l1", "    out[5] = l2",
          "    out[6] = bad", "    out[7] = mx"]
    return "\n".join(L) + "\n"


def kernel_moments(n: int):
    key = ("moment_sums", n)
    if key not in _KERNELS:  # the source is generated and hashed once per process
        _KERNELS[key] = kc._load(source_moments(n), "netkf_rmom", "moment_sums")
    return _KERNELS[key]


def kernel_dist(n: int):
    key = ("dist_counts", n)
    if key not in _KERNELS:  # the source is generated and hashed once per process
        _KERNELS[key] = kc._load(source_dist(n), "netkf_rdist", "dist_counts")
    return _KERNELS[key]


def kernel_stationary(n: int):
    key = ("stationary_acc", n)
    if key not in _KERNELS:  # the source is generated and hashed once per process
        _KERNELS[key] = kc._load(source_stationary(n), "netkf_rstat", "stationary_acc")
    return _KERNELS[key]


def kernel_stationary_block(n: int):
    key = ("stationary_block", n)
    if key not in _KERNELS:  # the source is generated and hashed once per process
        _KERNELS[key] = kc._load(source_stationary_block(n), "netkf_rstb", "stationary_block")
    return _KERNELS[key]
