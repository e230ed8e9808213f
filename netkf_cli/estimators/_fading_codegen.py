"""The fading receivers' block step generated per system, the run axis innermost (issue 20).

The same recursion as :mod:`netkf_cli.estimators._fading_numba` (one run at a time, scalar code LLVM
does not vectorise), written out as scalar expressions with the system's numbers as constants (zeros
skipped, ones dropped; :func:`netkf_cli.linalg.kalman_codegen._lin`) over the upper triangle of each covariance,
one contiguous array per entry with the runs innermost, and a loop over runs without data-dependent
control flow (a dropped packet selects P_{k|k−1} instead of the kept update) — the layout of
:mod:`netkf_cli.linalg.kalman_codegen`. The runs go in tiles of :data:`TILE`: a tile's state is copied into
one local work array whose rows lie a constant ``TILE`` doubles apart, advanced through the whole block
(L1-resident) and copied back. With the rows at constant distances LLVM needs no runtime alias check between
them and vectorises the loop over a tile's runs (packed vmulpd/vdivpd/vsqrtpd on ymm registers; the
untiled loop over 24–30 separate rows was scalar code). Fig. 6's receivers, 3 states, per run-step: scenario 3
74 → 30 ns, scenario 2 42 → 22 ns (the same inputs, the same bytes). Modes (:func:`_fading_numba.mode_of`):

* ``0`` — scenarios 1 and 3: P − U S⁻¹ Uᵀ, U = P Cᵀ, S = C P Cᵀ + R + σ² I (S⁻¹ closed form for one or
  two rows, an unrolled Cholesky factor for three or four, as kalman_codegen); a prior with
  tr P > limit (or non-finite) raises bit 0 of ``flags``: the caller redoes that run's block with the
  scalar kernel's rescue variant (the rescue policy stays :class:`kalman.Rescue`'s). With C of full column
  rank the information-form rescue runs inline (:func:`inline_rescue`), selected branch-free per run; a tile's
  step computes it only when one of the tile's priors needs it (a prior with tr P > limit: ~0.4 % of Fig. 6's
  run-steps);
* ``1`` — scenario 2 with an invertible C: the Joseph form (I − C⁻¹C) P (·)ᵀ + C⁻¹ (R + σ² I) C⁻ᵀ (eq. 12)
  with I − C⁻¹C evaluated as the scalar kernel does (``kalman_numba.joseph``) and inlined.

A non-finite P, U_{k|k} or U_{k+1|k} raises bit 1: the caller redoes the run's block on the numpy core
(which owns what an overflow means), as for the scalar kernel. The same inputs (keep decisions and σ²
values from numpy, the same uniforms) give the scalar kernel's numbers to rounding: sums run in
another order. Kernels are cached on disk by the hash of their source (``kalman_codegen._load``).
Tested against the numpy reference in ``tests/fading/test_fading_codegen.py``.
"""

from __future__ import annotations

import numpy as np

from netkf_cli.linalg.kalman_codegen import _lin, _load, _num, cholesky_correction, gain_correction

MAX_N = 6
MAX_M = 4


def supported(mode: int, n: int, m: int) -> bool:
    return (mode in (0, 1) and n <= MAX_N and 1 <= m <= MAX_M) or (mode == 2 and n <= MAX_N and 1 <= m <= 2)


def _kept2(A, C, R, src: str, srcf: str, s2: str, out: str, outf: str | None) -> list[str]:
    """Mode 2 (scenario 2, general C): the noise-free gain K = F Cᵀ (C F Cᵀ)⁻¹ of the filter's own F (locals
    ``srcf``), then the Joseph forms (I − KC) P (·)ᵀ + K (R + σ² I) Kᵀ → ``out`` and (I − KC) F (·)ᵀ → ``outf``
    (as ``kalman_numba.gain`` / ``joseph``; S⁻¹ in closed form, one or two rows)."""
    n, m = A.shape[0], C.shape[0]
    tri = [(i, j) for i in range(n) for j in range(i, n)]
    L = []
    for i in range(n):
        for a in range(m):
            L.append(f"{out}u{i}_{a} = {_lin([(C[a, k], _p(srcf, i, k)) for k in range(n)])}")
    for a in range(m):
        for b in range(a, m):
            L.append(f"{out}s{a}_{b} = {_lin([(C[a, k], f'{out}u{k}_{b}') for k in range(n)])}")
    if m == 1:
        L.append(f"{out}i0_0 = 1.0 / {out}s0_0")
        inv = {(0, 0): f"{out}i0_0"}
    else:
        L.append(f"{out}det = {out}s0_0 * {out}s1_1 - {out}s0_1 * {out}s0_1")
        L.append(f"{out}i0_0 = {out}s1_1 / {out}det")
        L.append(f"{out}i1_1 = {out}s0_0 / {out}det")
        L.append(f"{out}i0_1 = -{out}s0_1 / {out}det")
        inv = {(0, 0): f"{out}i0_0", (1, 1): f"{out}i1_1", (0, 1): f"{out}i0_1", (1, 0): f"{out}i0_1"}
    for i in range(n):
        for a in range(m):
            L.append(f"{out}k{i}_{a} = " + " + ".join(f"{out}u{i}_{b} * {inv[(b, a)]}" for b in range(m)))
    for i in range(n):
        for j in range(n):
            terms = [(-C[a, j], f"{out}k{i}_{a}") for a in range(m)]
            e = _lin(terms)
            L.append(f"{out}c{i}_{j} = " + (f"1.0 + ({e})" if i == j else e))
    for a in range(m):
        for b in range(a, m):
            L.append(f"{_p(out + 'rz', a, b)} = {_num(R[a, b])}" + (f" + {s2}" if a == b else ""))
    for dst, sp, noisy in ((out, src, True), (outf, srcf, False)):
        if dst is None:
            continue
        for i in range(n):
            for j in range(n):
                L.append(f"{dst}t{i}_{j} = " + " + ".join(f"{out}c{i}_{k} * {_p(sp, k, j)}" for k in range(n)))
        for i, j in tri:
            e = " + ".join(f"{dst}t{i}_{k} * {out}c{j}_{k}" for k in range(n))
            if noisy:
                e += " + " + " + ".join(f"{out}k{i}_{a} * {_p(out + 'rz', a, b)} * {out}k{j}_{b}"
                                        for a in range(m) for b in range(m))
            L.append(f"{_p(dst, i, j)} = {e}")
    return L


def pack(X: np.ndarray) -> np.ndarray:
    """Run-major (B, n, n) → (n(n+1)/2, B), the upper triangle row by row (the kernel's layout)."""
    iu = np.triu_indices(X.shape[1])
    return np.ascontiguousarray(X[:, iu[0], iu[1]].T)


def _p(name, i, j):
    return f"{name}{min(i, j)}_{max(i, j)}"


def _chol_inv(src: str, n: int, out: str) -> list[str]:
    """Lines of the inverse of the SPD (n, n) locals ``src`` (upper triangle) into ``out``: the Cholesky factor
    L, Z = L⁻¹, out = Zᵀ Z (a non-SPD input gives NaN: the caller flags it)."""
    L = []
    for j in range(n):
        acc = " - ".join([_p(src, j, j)] + [f"{out}l{j}_{k} * {out}l{j}_{k}" for k in range(j)])
        L.append(f"{out}l{j}_{j} = np.sqrt({acc})")
        for i in range(j + 1, n):
            acc = " - ".join([_p(src, j, i)] + [f"{out}l{i}_{k} * {out}l{j}_{k}" for k in range(j)])
            L.append(f"{out}l{i}_{j} = ({acc}) / {out}l{j}_{j}")
    for i in range(n):
        L.append(f"{out}z{i}_{i} = 1.0 / {out}l{i}_{i}")
        for j in range(i - 1, -1, -1):
            acc = " + ".join(f"{out}l{i}_{k} * {out}z{k}_{j}" for k in range(j, i))
            L.append(f"{out}z{i}_{j} = -({acc}) / {out}l{i}_{i}")
    for i in range(n):
        for j in range(i, n):
            L.append(f"{_p(out, i, j)} = " + " + ".join(f"{out}z{k}_{i} * {out}z{k}_{j}" for k in range(j, n)))
    return L


def inline_rescue(mode: int, C) -> bool:
    """Mode 0 with C of full column rank: the information-form rescue (:class:`kalman.Rescue`) runs inline."""
    C = np.atleast_2d(np.asarray(C, dtype=float))
    return mode == 0 and C.shape[0] >= C.shape[1] and np.linalg.matrix_rank(C) == C.shape[1]


def _kept(mode, A, C, R, Kc, src: str, s2: str, out: str, rescue: bool = False, need: str = "True") -> list[str]:
    """Lines of the kept update from the prior locals ``src`` to ``out`` (upper triangle), noise σ² = ``s2``.
    ``rescue`` (mode 0): a prior with tr > limit takes the information form (P⁻¹ + Cᵀ(R + σ² I)⁻¹C)⁻¹ instead
    (selected branch-free); where that is non-finite while ``need`` holds, flag bit 0 (the scalar rescue redoes
    the run)."""
    n, m = A.shape[0], C.shape[0]
    tri = [(i, j) for i in range(n) for j in range(i, n)]
    L = []
    if rescue:
        L += [ln for ln in _kept(mode, A, C, R, Kc, src, s2, out + "s")]
        L.append("trr = " + " + ".join(_p(src, i, i) for i in range(n)))
        L.append("big = not (trr <= limit)")
        for a in range(m):
            for b in range(a, m):
                L.append(f"{_p(out + 'rz', a, b)} = {_num(R[a, b])}" + (f" + {s2}" if a == b else ""))
        L += _chol_inv(out + "rz", m, out + "ri")  # (R + σ² I)⁻¹
        for a in range(m):
            for j in range(n):
                L.append(f"{out}g{a}_{j} = " + " + ".join(f"{_p(out + 'ri', a, b)} * {_num(C[b, j])}"
                                                           for b in range(m) if C[b, j] != 0.0) if any(
                    C[b, j] != 0.0 for b in range(m)) else f"{out}g{a}_{j} = 0.0")
        L += _chol_inv(src, n, out + "pi")  # P⁻¹
        for i, j in tri:
            info = _lin([(C[a, i], f"{out}g{a}_{j}") for a in range(m)])
            L.append(f"{_p(out + 'mm', i, j)} = {_p(out + 'pi', i, j)} + {info}")
        L += _chol_inv(out + "mm", n, out + "in")
        fin = " + ".join(_p(out + "in", i, j) for i, j in tri)
        L.append(f"okr = ({fin}) - ({fin}) == 0.0")
        L.append(f"f = f | (np.int8(1) if (big and not okr and {need}) else np.int8(0))")
        for i, j in tri:
            L.append(f"{_p(out, i, j)} = {_p(out + 'in', i, j)} if big else {_p(out + 's', i, j)}")
        return L
    if mode == 2:
        return _kept2(A, C, R, src, "g", s2, out, out + "f")
    if mode == 1:
        # I − K C exactly as kalman_numba.joseph evaluates it (γ = 1), then inlined as constants
        IKC = np.empty((n, n))
        for i in range(n):
            for j in range(n):
                acc = 0.0
                for a in range(m):
                    acc += Kc[i, a] * C[a, j]
                IKC[i, j] = (1.0 if i == j else 0.0) - 1.0 * acc
        for a in range(m):
            for b in range(a, m):
                rz = _num(R[a, b]) + (f" + {s2}" if a == b else "")
                L.append(f"rz{a}_{b} = {rz}")
        for i in range(n):
            for j in range(n):
                L.append(f"{out}x{i}_{j} = {_lin([(IKC[i, k], _p(src, k, j)) for k in range(n)])}")
        for i, j in tri:
            terms = [(IKC[j, k], f"{out}x{i}_{k}") for k in range(n)]
            terms += [(Kc[i, a] * Kc[j, b], _p("rz", a, b)) for a in range(m) for b in range(m)]
            L.append(f"{_p(out, i, j)} = {_lin(terms)}")
        return L
    # mode 0: U = P Cᵀ, S = C U + R + σ² I, out = P − U S⁻¹ Uᵀ
    for i in range(n):
        for a in range(m):
            L.append(f"u{i}_{a} = {_lin([(C[a, k], _p(src, i, k)) for k in range(n)])}")
    for a in range(m):
        for b in range(a, m):
            extra = f" + {s2}" if a == b else ""
            L.append(f"s{a}_{b} = {_lin([(C[a, k], f'u{k}_{b}') for k in range(n)])} + {_num(R[a, b])}{extra}")
    if m >= 3:
        return L + cholesky_correction(n, m, tri, lambda i, j: _p(out, i, j), lambda i, j: _p(src, i, j))
    return L + gain_correction(n, m, tri, lambda i, j: _p(out, i, j), lambda i, j: _p(src, i, j))


def _predict(A, Q, src: str, out: str) -> list[str]:
    n = A.shape[0]
    L = []
    for i in range(n):
        for j in range(n):
            L.append(f"{out}x{i}_{j} = {_lin([(A[i, k], _p(src, k, j)) for k in range(n)])}")
    for i in range(n):
        for j in range(i, n):
            L.append(f"{_p(out, i, j)} = {_lin([(A[j, k], f'{out}x{i}_{k}') for k in range(n)])} + {_num(Q[i, j])}")
    return L


TILE = 32
"""Runs per tile: each tile's state stays in a local work array (L1-resident) for the whole block, its rows at
constant distances (``TILE`` doubles apart), so LLVM's dependence analysis needs no runtime checks between them and
vectorises the loop over the tile's runs."""


def _body(mode, A, C, Q, R, Kc, limit, want_u, separate_u, rescue, rows) -> list[str]:
    """The lines of one run-step, reading and writing the tile's work array ``S`` (row r of lane l at
    ``S[r * TILE + l]``, :func:`_layout` ``rows``); inputs of run ``b``."""
    A, C, Q, R, Kc = (np.atleast_2d(np.asarray(x, dtype=float)) for x in (A, C, Q, R, Kc))
    n = A.shape[0]
    tri = [(i, j) for i in range(n) for j in range(i, n)]

    def at(name, k):
        return f"S[{(rows[name] + k) * TILE} + l]"

    body = [f"p{i}_{j} = {at('P', k)}" for k, (i, j) in enumerate(tri)]
    if mode == 2:
        body += [f"g{i}_{j} = {at('G', k)}" for k, (i, j) in enumerate(tri)]
    body.append("kp = keep[t, b]")
    body.append("sv = s2[t, b]")
    if mode == 0 and rescue:
        body.append("f = np.int8(0)")
    elif mode == 0:
        body.append("tr = " + " + ".join(_p("p", i, i) for i in range(n)))
        # (as the scalar kernel: the prior is checked whenever a kept update is needed — U's kept term every step)
        cond = "not (tr <= limit)" if want_u else "kp and not (tr <= limit)"
        body.append(f"f = np.int8(1) if {cond} else np.int8(0)")
    else:
        body.append("f = np.int8(0)")
    body += _kept(mode, A, C, R, Kc, "p", "sv", "kt", rescue, "True" if want_u and not separate_u else "kp")
    if want_u:
        for k, (i, j) in enumerate(tri):
            body.append(f"v{i}_{j} = {at('U', k)}")
        body.append("mb = mu[b]")
        if separate_u:
            body.append("su = s2u[t, b]")
            body += _kept(mode, A, C, R, Kc, "p", "su", "ku", rescue)
            ku = "ku"
        else:
            ku = "kt"
        for i, j in tri:
            body.append(f"{_p('ul', i, j)} = mb * {_p('v', i, j)} + (1.0 - mb) * {_p(ku, i, j)}")
        body += _predict(A, Q, "ul", "un")
        body.append("fin = " + " + ".join(_p("ul", i, j) for i, j in tri) + " + "
                    + " + ".join(_p("un", i, j) for i, j in tri))
    for i, j in tri:
        body.append(f"{_p('fl', i, j)} = {_p('kt', i, j)} if kp else {_p('p', i, j)}")
    body += _predict(A, Q, "fl", "pn")
    ptr = " + ".join(_p("pn", i, j) for i, j in tri)
    if mode == 2:  # the filter's own covariance: A (kept ? its Joseph form : F) Aᵀ + Q
        for i, j in tri:
            body.append(f"{_p('gl', i, j)} = {_p('ktf', i, j)} if kp else {_p('g', i, j)}")
        body += _predict(A, Q, "gl", "gn")
        ptr += " + " + " + ".join(_p("gn", i, j) for i, j in tri)
    body.append(f"fin = {'fin + ' if want_u else ''}{ptr}")
    body.append("f = f | (np.int8(0) if fin - fin == 0.0 else np.int8(2))")
    # the flag bits as counts (float rows of S: one work array, no int8 array in the vectorised loop)
    body.append(f"{at('flag1', 0)} += np.float64(f & np.int8(1))")
    body.append(f"{at('flag2', 0)} += np.float64(f >> np.int8(1))")
    for k, (i, j) in enumerate(tri):
        body.append(f"{at('P', k)} = {_p('pn', i, j)}")
        body.append(f"{at('F', k)} = {_p('fl', i, j)}")
        if mode == 2:
            body.append(f"{at('G', k)} = {_p('gn', i, j)}")
        if want_u:
            body.append(f"{at('U', k)} = {_p('un', i, j)}")
            body.append(f"{at('Uf', k)} = {_p('ul', i, j)}")
    return body


def _layout(mode: int, n: int, want_u: bool) -> dict[str, int]:
    """First row of each packed state in the tile's work array (then the two flag-count rows)."""
    nt = n * (n + 1) // 2
    names = ["P", "F"] + (["U", "Uf"] if want_u else []) + (["G"] if mode == 2 else [])
    rows = {k: i * nt for i, k in enumerate(names)}
    rows["flag1"], rows["flag2"] = len(names) * nt, len(names) * nt + 1
    return rows


def source(mode: int, A, C, Q, R, Kc, limit: float, want_u: bool, separate_u: bool, rescue: bool = False) -> str:
    """The source of ``advance(keep, s2, s2u, mu, P, F, U, Uf, G, flags, rec, RecP, RecF, RecU, RecUf)``:
    keep/s2/s2u (T, B) time-major, mu (B,), the state packed (n(n+1)/2, B) (``P`` the prior, ``F`` the last
    P_{k|k}, ``U``/``Uf`` the burst-conditioned prior and last U_{k|k}, ``G`` the filter's own prior P_f in
    mode 2), ``flags`` (B,) int8 bits (0: the
    rescue is needed, 1: a non-finite value), ``rec`` (T,) the record slot of step t (−1: none), records
    (slots, n, n, B).

    The runs go in tiles of ``TILE``: a tile's state is copied into the work array ``S``, advanced through
    all T steps (the loop over its runs innermost, vectorised), and copied back. With the inline rescue
    (mode 0) a step runs the plain update when no run of the tile has a prior with tr > limit (or
    non-finite) — then the rescue variant's selection keeps the plain update for every run and raises no
    flag: the same numbers — and the variant with the information form otherwise."""
    A, C = np.atleast_2d(np.asarray(A, dtype=float)), np.atleast_2d(np.asarray(C, dtype=float))
    n = A.shape[0]
    tri = [(i, j) for i in range(n) for j in range(i, n)]
    rows = _layout(mode, n, want_u)
    states = [("P", "P"), ("U", "U")] if want_u else [("P", "P")]
    if mode == 2:
        states.append(("G", "G"))
    outs = [("F", "F")] + ([("Uf", "Uf")] if want_u else [])
    I1, I2, I3, I4 = (" " * k for k in (8, 12, 16, 20))
    L = ["import numpy as np", "import numba as nb", "",
         "@nb.njit(cache=True, nogil=True, fastmath=False, error_model='numpy')",
         "def advance(keep, s2, s2u, mu, P, F, U, Uf, G, flags, rec, RecP, RecF, RecU, RecUf):",
         "    T, B = keep.shape",
         f"    limit = {_num(limit)}",
         f"    S = np.zeros({(rows['flag2'] + 1) * TILE})",
         f"    for b0 in range(0, B, {TILE}):",
         f"{I1}w = min({TILE}, B - b0)",
         f"{I1}for l in range(w):"]
    for name, arr in states:
        for k in range(len(tri)):
            L.append(f"{I2}S[{(rows[name] + k) * TILE} + l] = {arr}[{k}, b0 + l]")
    L.append(f"{I2}S[{rows['flag1'] * TILE} + l] = 0.0")
    L.append(f"{I2}S[{rows['flag2'] * TILE} + l] = 0.0")
    L.append(f"{I1}for t in range(T):")
    plain = _body(mode, A, C, Q, R, Kc, limit, want_u, separate_u, False, rows)
    if mode == 0 and rescue:
        full = _body(mode, A, C, Q, R, Kc, limit, want_u, separate_u, True, rows)
        # the plain update where no run of the tile needs the rescue (f = 0: the rescue variant raises no bit 0)
        plain = [ln for ln in plain if not ln.startswith(("tr = ", "f = np.int8(1) if"))]
        plain.insert(plain.index("sv = s2[t, b]") + 1, "f = np.int8(0)")
        L.append(f"{I2}nbig = 0")
        L.append(f"{I2}for l in range(w):")
        L.append(f"{I3}trr = " + " + ".join(f"S[{(rows['P'] + tri.index((i, i))) * TILE} + l]" for i in range(n)))
        L.append(f"{I3}nbig += 0 if trr <= limit else 1")
        L.append(f"{I2}if nbig == 0:")
        L.append(f"{I3}for l in range(w):")
        L.append(f"{I4}b = b0 + l")
        L += [I4 + s for s in plain]
        L.append(f"{I2}else:")
        L.append(f"{I3}for l in range(w):")
        L.append(f"{I4}b = b0 + l")
        L += [I4 + s for s in full]
    else:
        L.append(f"{I2}for l in range(w):")
        L.append(f"{I3}b = b0 + l")
        L += [I3 + s for s in plain]
    L += [f"{I2}r = rec[t]", f"{I2}if r >= 0:"]
    names = [("RecP", "P"), ("RecF", "F")] + ([("RecU", "U"), ("RecUf", "Uf")] if want_u else [])
    for k, (i, j) in enumerate(tri):  # the records full (slots, n, n, B): the caller's layout, no unpacking
        L.append(f"{I3}for l in range(w):")
        for rn, sn in names:
            L.append(f"{I4}{rn}[r, {i}, {j}, b0 + l] = S[{(rows[sn] + k) * TILE} + l]")
            if i != j:
                L.append(f"{I4}{rn}[r, {j}, {i}, b0 + l] = S[{(rows[sn] + k) * TILE} + l]")
    L.append(f"{I1}for l in range(w):")
    for name, arr in states + outs:
        for k in range(len(tri)):
            L.append(f"{I2}{arr}[{k}, b0 + l] = S[{(rows[name] + k) * TILE} + l]")
    L.append(f"{I2}flags[b0 + l] = flags[b0 + l] | (np.int8(1) if S[{rows['flag1'] * TILE} + l] > 0.0 else np.int8(0))"
             f" | (np.int8(2) if S[{rows['flag2'] * TILE} + l] > 0.0 else np.int8(0))")
    return "\n".join(L) + "\n"


_KERNELS: dict = {}


def kernel(mode: int, A, C, Q, R, Kc, limit: float, want_u: bool, separate_u: bool, rescue: bool = False):
    """The compiled ``advance`` (:func:`source`) for this receiver (generated, written once, numba-cached; the
    source made once per process and arguments: every block of every chunk asks for it)."""
    arrs = tuple(np.atleast_2d(np.asarray(x, dtype=float)) for x in (A, C, Q, R, Kc))
    key = (int(mode), tuple((x.shape, x.tobytes()) for x in arrs), float(limit), bool(want_u), bool(separate_u),
           bool(rescue))
    if key not in _KERNELS:
        src = source(mode, *arrs, limit, bool(want_u), bool(separate_u), bool(rescue))
        _KERNELS[key] = _load(src, "netkf_fading", "advance")
    return _KERNELS[key]
