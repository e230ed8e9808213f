"""Generated compiled kernels of the Markov-mode fixed-gain filters (per system; numba, optional).

:func:`~netkf_cli.estimators.markov_filters.linear_filter_covariances` propagates per run the second moment
M of ζ = [ξ; s] (D = d + r), M⁺ = 𝒜_{t,q} M 𝒜_{t,q}ᵀ + ℬΣℬᵀ_{t,q}, with 𝒜_{t,q} = [[F_q, 0], [G_s(t) H_q,
A_s(t)]] mostly zeros (the augmented transition F_q: a shift, one copied block, the mode's measurement row).
This module writes that recursion out as scalar expressions over the upper triangle of one run's M (kept in
locals across the time loop): entries that are zero for every gain are skipped, the model's constants (F_q,
G_qΣG_qᵀ, E_x) inlined as numbers, the gain-dependent ones read from the stacked arrays — so the code depends on
the model alone (one kernel per system for the LMI and the naive filter, any horizon). The operations are the numpy
core's in its order (``batched.left`` / ``right`` term by term in ascending index, then ``sym``, then + Q),
so for D ≤ 8 the numbers are the numpy path's bit for bit where no BLAS product intervenes — which keeps
the degenerate cases (a covariance that is exactly 0, the NEES rank of it) identical. The reports — P_{k|k} =
C_{t,q} M C_{t,q}ᵀ + L_f J_q Σ J_qᵀ L_fᵀ before the step, P_{k+1|k} = C_p M⁺ C_pᵀ after it — and the
round-off guard (∞ where ε·‖C‖_F²·tr M > FIXED_GAIN_PRECISION·tr P) are written the same way. The same
equations as the numpy path, in another floating-point order: equal to rounding
(``tests/markov/test_fast_paths.py``). Compiled and cached on disk by source hash through
``netkf_cli.linalg.kalman_codegen._load`` (numba compiles each system once per machine).
"""

from __future__ import annotations

import numpy as np

from netkf_cli.linalg import kalman_codegen


MAX_DIM = 10
"""Largest D = d + r (fixed gain) or d (mode-aware) written out: the kernel has O(D³) lines (≈ 1 200 at D = 8,
numba compiles it in ≈ 15 s once per system); larger systems take the numpy path."""


def mode_aware_supported(d: int, m: int) -> bool:
    """Whether :func:`source_mode_aware` covers the model (one output, d ≤ :data:`MAX_DIM`)."""
    return m == 1 and d <= MAX_DIM


def _num(x: float) -> str:
    return repr(float(x))


def _m(i: int, j: int) -> str:
    return f"m{min(i, j)}_{max(i, j)}"


def _sym(X: str, i: int, j: int) -> str:
    """(X + Xᵀ)/2 at (i, j) as ``batched.sym`` computes it (the diagonal unchanged)."""
    return f"{X}{i}_{j}" if i == j else f"0.5 * ({X}{i}_{j} + {X}{j}_{i})"


def _coef(name: str, q: int, i: int, j: int, const, val) -> str:
    if const[q, i, j]:
        return _num(val[q, i, j])
    return f"{name}[idx, {i}, {j}]"


def _sum(terms: list[tuple[str, str]], start: str | None = None) -> str:
    """Σ coef·var with 1.0 and −1.0 folded; ``start`` the first term (a number or a load)."""
    parts = [] if start is None else [start]
    for c, v in terms:
        if c == "1.0":
            parts.append(f"+ {v}")
        elif c == "-1.0":
            parts.append(f"- {v}")
        else:
            parts.append(f"+ {c} * {v}")
    if not parts:
        return "0.0"
    s = " ".join(parts)
    return s[2:] if s.startswith("+ ") else ("-" + s[2:] if s.startswith("- ") else s)


def source(A: np.ndarray, BSB: np.ndarray, Cf: np.ndarray, LJS: np.ndarray, Cp: np.ndarray, H: np.ndarray,
           J: np.ndarray, d: int) -> str:
    """The kernel ``run`` for stacked 𝒜 (T, N, D, D), ℬΣℬᵀ (T, N, D, D), C_f (T, N, n, D), L_fJΣJᵀL_fᵀ
    (T, N, n, n) and the constant C_p (n, D); its arguments are the same arrays flattened to index t·N + q.
    What is written depends on the model only (H_q, J_q, d, C_p and the ξ blocks F_q, G_qΣG_qᵀ of the first
    step): entries that can be nonzero for some gains are read from the arrays, the model's own inlined.

    One call runs trace steps t0 … t1 − 1 (a block of steps): ``Mu`` (runs, D(D+1)/2) holds each run's M (upper
    triangle, row by row) at t0 and is overwritten with M at t1; ``modes`` (runs, t1 − t0) are the block's modes;
    ``slot[t + 1]`` ≥ 0 is the block's output row of step k = t + 1. The numbers do not depend on the blocks
    (M is carried in float64 between them: the same operations in the same order)."""
    N, D = A.shape[1], A.shape[2]
    n = Cp.shape[0]
    hcol = (H != 0.0).any(axis=1)  # (N, d): the columns each mode's measurement reads
    jany = (J != 0.0).any(axis=(1, 2))  # (N,): the mode's packet carries noise
    anz = np.zeros((N, D, D), bool)
    aco = np.zeros((N, D, D), bool)
    aval = np.zeros((N, D, D))
    anz[:, :d, :d] = A[0, :, :d, :d] != 0.0
    aco[:, :d, :d] = True
    aval[:, :d, :d] = A[0, :, :d, :d]
    anz[:, d:, :d] = hcol[:, None, :]
    anz[:, d:, d:] = True
    bnz = np.zeros((N, D, D), bool)
    bco = np.zeros((N, D, D), bool)
    bval = np.zeros((N, D, D))
    bnz[:, :d, :d] = BSB[0, :, :d, :d] != 0.0
    bco[:, :d, :d] = True
    bval[:, :d, :d] = BSB[0, :, :d, :d]
    bnz[:, d:, :] |= jany[:, None, None]
    bnz[:, :, d:] |= jany[:, None, None]
    Ex = Cp[:, :d]
    cnz = np.zeros((N, n, D), bool)
    cco = np.zeros((N, n, D), bool)
    cval = np.zeros((N, n, D))
    cnz[:, :, :d] = (Ex != 0.0)[None] | hcol[:, None, :]
    cco[:, :, :d] = ~hcol[:, None, :]
    cval[:, :, :d] = Ex[None]
    cnz[:, :, d:] = True
    lnz = np.broadcast_to(jany[:, None, None], (N, n, n))
    lco = np.zeros((N, n, n), bool)
    lval = np.zeros((N, n, n))
    up = [(i, j) for i in range(D) for j in range(i, D)]
    L = ["import numpy as np", "import numba as nb", "", "",
         "@nb.njit(cache=True, nogil=True)",
         "def run(Mu, modes, t0, t1, AA, BB, slot, CF, LJ, sumCf, sumCp, want_f, want_p, eps, prec, out_f, out_p):",
         "    runs = modes.shape[0]",
         "    for r in range(runs):"]
    L += [f"        {_m(i, j)} = Mu[r, {u}]" for u, (i, j) in enumerate(up)]
    L += ["        for t in range(t0, t1):",
          "            q = modes[r, t - t0]",
          f"            idx = t * {N} + q",
          "            s = slot[t + 1]"]
    I = "                "
    for q in range(N):
        b_ = f"b{q}"  # the branch's own names: numba's SSA pass costs (names defined more than once) × (blocks)
        L.append(f"            {'if' if q == 0 else 'elif'} q == {q}:")
        # the filtered report, before the step
        L.append(I + "if s >= 0 and want_f:")
        J = I + "    "
        for a in range(n):
            for j in range(D):
                terms = [(_coef("CF", q, a, k, cco, cval), _m(k, j)) for k in range(D) if cnz[q, a, k]]
                L.append(J + f"{b_}x{a}_{j} = {_sum(terms)}")
        for a in range(n):
            for b in range(n):
                terms = [(_coef("CF", q, b, k, cco, cval), f"{b_}x{a}_{k}") for k in range(D) if cnz[q, b, k]]
                L.append(J + f"{b_}c{a}_{b} = {_sum(terms)}")
        for a in range(n):
            for b in range(a, n):
                st = (_num(lval[q, a, b]) if lco[q, a, b] else f"LJ[idx, {a}, {b}]") if lnz[q, a, b] else "0.0"
                L.append(J + f"{b_}p{a}_{b} = {_sym(b_ + 'c', a, b)} + {st}")
        L.append(J + f"{b_}trm = {' + '.join(_m(i, i) for i in range(D))}")
        L.append(J + f"{b_}trp = {' + '.join(f'{b_}p{a}_{a}' for a in range(n))}")
        L.append(J + f"{b_}bad = not (eps * sumCf[idx] * {b_}trm <= prec * {b_}trp)")
        for a in range(n):
            for b in range(n):
                L.append(J + f"out_f[s, {a}, {b}, r] = np.inf if {b_}bad else {b_}p{min(a, b)}_{max(a, b)}")
        # the step: t = 𝒜 M, M⁺ = t 𝒜ᵀ + ℬΣℬᵀ (upper triangle)
        for i in range(D):
            for j in range(D):
                terms = [(_coef("AA", q, i, k, aco, aval), _m(k, j)) for k in range(D) if anz[q, i, k]]
                L.append(I + f"{b_}t{i}_{j} = {_sum(terms)}")
        for i in range(D):
            for j in range(D):
                terms = [(_coef("AA", q, j, k, aco, aval), f"{b_}t{i}_{k}") for k in range(D) if anz[q, j, k]]
                L.append(I + f"{b_}u{i}_{j} = {_sum(terms)}")
        for i, j in up:
            st = (_num(bval[q, i, j]) if bco[q, i, j] else f"BB[idx, {i}, {j}]") if bnz[q, i, j] else "0.0"
            L.append(I + f"{b_}n{i}_{j} = {_sym(b_ + 'u', i, j)} + {st}")
        L += [I + f"{_m(i, j)} = {b_}n{i}_{j}" for i, j in up]
    # the predicted report, after the step
    L.append("            if s >= 0 and want_p:")
    I = "                "
    for a in range(n):
        for j in range(D):
            terms = [(_num(Cp[a, k]), _m(k, j)) for k in range(D) if Cp[a, k] != 0.0]
            L.append(I + f"x{a}_{j} = {_sum(terms)}")
    for a in range(n):
        for b in range(n):
            terms = [(_num(Cp[b, k]), f"x{a}_{k}") for k in range(D) if Cp[b, k] != 0.0]
            L.append(I + f"c{a}_{b} = {_sum(terms)}")
    for a in range(n):
        for b in range(a, n):
            L.append(I + f"p{a}_{b} = {_sym('c', a, b)} + 0.0")
    L.append(I + f"trm = {' + '.join(_m(i, i) for i in range(D))}")
    L.append(I + f"trp = {' + '.join(f'p{a}_{a}' for a in range(n))}")
    L.append(I + "bad = not (eps * sumCp * trm <= prec * trp)")
    for a in range(n):
        for b in range(n):
            L.append(I + f"out_p[s, {a}, {b}, r] = np.inf if bad else p{min(a, b)}_{max(a, b)}")
    L += [f"        Mu[r, {u}] = {_m(i, j)}" for u, (i, j) in enumerate(up)]  # the state at t1, for the next block
    return "\n".join(L) + "\n"


def kernel(A, BSB, Cf, LJS, Cp, H, J, d: int):
    """The compiled ``run`` for this model (generated, written once, numba-cached: :func:`source`)."""
    return kalman_codegen._load(source(A, BSB, Cf, LJS, Cp, H, J, d), "netkf_markov_fixed", "run")  # its shared loader


# =========================================================================== the mode-aware KF (one output)
def source_mode_aware(H: np.ndarray, Rq: np.ndarray, Fb: np.ndarray, Qb: np.ndarray, Dg: np.ndarray, n: int) -> str:
    """The kernel ``run`` of :class:`~netkf_cli.estimators.markov_filters.ModeAwareKFTr` with states for m = 1:
    per mode q the scalar pseudo-inverse update (S = H_q P H_qᵀ + R_q; no gain unless S > floor =
    ZERO_INNOVATION_RTOL·(tr Σ + tr P): ``kalman.update_pinv`` for one row), then P⁺ = F̄_q P_f F̄_qᵀ + Q̄_q,
    ξ̂⁺ = F̄_q ξ̂_f + D_q y; H, R_q, F̄, Q̄, D inlined (structural zeros skipped). Mode 3 (H = 0) leaves P, ξ̂.
    A run whose x block trips the plain KF's overflow flag in a mode-1 / mode-3 step is flagged and left.

    One call runs trace steps t0 … t1 − 1 (a block of steps): ``xi`` (runs, d) and ``Pu`` (runs, d(d+1)/2, the upper
    triangle row by row) hold each run's ξ̂(t0+1|t0) and P at t0 and are overwritten with those at t1; ``modes`` and
    ``y`` (runs, t1 − t0) are the block's modes and received values (column t − t0 is step k = t + 1);
    ``slot[t + 1]`` ≥ 0 is the block's output row of step t + 1. A run flagged before the call is skipped."""
    N, d = Fb.shape[0], Fb.shape[1]
    up = [(i, j) for i in range(d) for j in range(i, d)]
    P = lambda i, j: f"p{min(i, j)}_{max(i, j)}"  # noqa: E731
    Fp = lambda i, j: f"f{min(i, j)}_{max(i, j)}"  # noqa: E731
    L = ["import numpy as np", "import numba as nb", "", "",
         "@nb.njit(cache=True, nogil=True)",
         "def run(xi, Pu, modes, y, t0, t1, scale, rtol, limit, slot, xf_out, Pf_out, xp_out, Pp_out, flag):",
         "    runs = modes.shape[0]",
         "    for r in range(runs):",
         "        if flag[r]:",
         "            continue"]
    L += [f"        {P(i, j)} = Pu[r, {u}]" for u, (i, j) in enumerate(up)]
    L += [f"        x{i} = xi[r, {i}]" for i in range(d)]
    L += ["        for t in range(t0, t1):",
          "            q = modes[r, t - t0]",
          "            yy = y[r, t - t0]"]
    I = "                "
    for q in range(N):
        L.append(f"            {'if' if q == 0 else 'elif'} q == {q}:")
        if q in (0, 2):
            L.append(I + f"if not ({' + '.join(P(i, i) for i in range(n))} <= limit):")
            L.append(I + "    flag[r] = True")
            L.append(I + "    break")
        h = H[q, 0]
        b_ = f"b{q}"  # the branch's own names for its intermediates (numba's SSA pass: names defined more than once)
        hz = [k for k in range(d) if h[k] != 0.0]
        if not hz:  # noise only: P_f = P, ξ̂_f = ξ̂
            L += [I + f"{Fp(i, j)} = {P(i, j)}" for i, j in up]
            L += [I + f"g{i} = x{i}" for i in range(d)]
        else:
            for i in range(d):
                L.append(I + f"{b_}u{i} = {_sum([(_num(h[k]), P(k, i)) for k in hz])}")
            L.append(I + f"{b_}ss = ({_sum([(_num(h[k]), f'{b_}u{k}') for k in hz])}) + {_num(Rq[q, 0, 0])}")
            L.append(I + f"if {b_}ss > rtol * (scale + ({' + '.join(P(i, i) for i in range(d))})):")
            J = I + "    "
            L.append(J + f"{b_}inv = 1.0 / {b_}ss")
            L.append(J + f"{b_}e = yy - ({_sum([(_num(h[k]), f'x{k}') for k in hz])})")
            for i in range(d):
                L.append(J + f"{b_}b{i} = {b_}inv * {b_}u{i}")  # numpy's order: S⁻¹ (C P), then P Cᵀ · that, then (X + Xᵀ)/2
            L += [J + (f"{Fp(i, j)} = {P(i, j)} - {b_}u{i} * {b_}b{i}" if i == j else
                       f"{Fp(i, j)} = 0.5 * (({P(i, j)} - {b_}u{i} * {b_}b{j}) + ({P(i, j)} - {b_}u{j} * {b_}b{i}))")
                  for i, j in up]
            L += [J + f"g{i} = x{i} + {b_}b{i} * {b_}e" for i in range(d)]
            L.append(I + "else:")
            L += [J + f"{Fp(i, j)} = {P(i, j)}" for i, j in up]
            L += [J + f"g{i} = x{i}" for i in range(d)]
        F = Fb[q]
        for i in range(d):
            for j in range(d):
                L.append(I + f"{b_}w{i}_{j} = {_sum([(_num(F[i, k]), Fp(k, j)) for k in range(d) if F[i, k] != 0.0])}")
        for i in range(d):
            for j in range(d):
                L.append(I + f"{b_}v{i}_{j} = {_sum([(_num(F[j, k]), f'{b_}w{i}_{k}') for k in range(d) if F[j, k] != 0.0])}")
        for i, j in up:
            L.append(I + f"{P(i, j)} = {_sym(b_ + 'v', i, j)} + {_num(Qb[q, i, j])}")
        for i in range(d):
            st = f"{_num(Dg[q, i, 0])} * yy" if Dg[q, i, 0] != 0.0 else None
            L.append(I + f"x{i} = {_sum([(_num(F[i, k]), f'g{k}') for k in range(d) if F[i, k] != 0.0], st)}")
    L.append("            s = slot[t + 1]")
    L.append("            if s >= 0:")
    I = "                "
    for i in range(n):
        L.append(I + f"xf_out[s, {i}, r] = g{i}")
        L.append(I + f"xp_out[s, {i}, r] = x{i}")
        for j in range(n):
            L.append(I + f"Pf_out[s, {i}, {j}, r] = {Fp(i, j)}")
            L.append(I + f"Pp_out[s, {i}, {j}, r] = {P(i, j)}")
    L.append("        if flag[r]:")
    L.append("            continue")
    L += [f"        Pu[r, {u}] = {P(i, j)}" for u, (i, j) in enumerate(up)]  # the state at t1, for the next block
    L += [f"        xi[r, {i}] = x{i}" for i in range(d)]
    return "\n".join(L) + "\n"


def kernel_mode_aware(H, Rq, Fb, Qb, Dg, n: int):
    """The compiled mode-aware ``run`` for these per-mode matrices (m = 1; generated, numba-cached)."""
    return kalman_codegen._load(source_mode_aware(H, Rq, Fb, Qb, Dg, n), "netkf_markov_aware", "run")  # its shared loader
