"""``kf`` fused (issue 20): the channel's uniforms → arrivals → the generated filter step, one compiled pass.

For a ``bernoulli`` or ``gilbert_elliott`` channel the arrivals are a function of one uniform per step and
run, ``u = rng.random((horizon, runs))`` (the channel's own draw, :meth:`arrival_law` / ``uniforms``), so the
compiled kernel reads u and forms γ itself — Bernoulli γ = u < p; Gilbert γ₀ = u₀ < π_good,
γ_t = (u_t ≥ p_gb if γ_{t−1} else u_t < p_bg) — exactly the comparisons of the numpy sampler, so the
same uniforms give the same trace bit for bit. The step is :func:`netkf_cli.linalg.kalman_codegen.source`'s
generated ``advance`` with its arrival read replaced (the text of that kernel is not touched: the
non-fused path keeps its cached kernel), so the fused filter equals the compiled filter bit for bit and
the numpy core to rounding. The caller (:class:`netkf_cli.engine.PairKernel`) reduces the packed state
(n(n+1)/2, runs) after each reported step with :mod:`netkf_cli.linalg._reduce_numba`, never materialising the
(T, runs) trace or an (n, n, runs) covariance per step, and redoes rescue-flagged runs on the numpy core.
"""

from __future__ import annotations

import numpy as np

from netkf_cli.linalg import kalman
from netkf_cli.linalg import kalman_codegen as kc

LAWS = ("bernoulli", "gilbert_elliott")


def source_fused(A, C, Q, R, groups, limit: float, law: str = "bernoulli") -> str:
    """The source of ``advance_u(P, u, gprev, pa, pb, pc, t0, t1, flag)``: :func:`kc.source`'s ``advance``
    for one arrival stream with γ formed from the uniforms u (horizon, runs) in the loop, branch-free (so
    the run loop still vectorizes): ``law`` bernoulli γ = u < pa; gilbert_elliott with p_gb = pa,
    p_bg = pb, π_good = pc and ``gprev`` (runs,) the previous arrival."""
    if len(groups) != 1:
        raise ValueError("fused kf: one arrival stream")
    src = kc.source(A, C, Q, R, groups, limit)
    head = "def advance(P, gam, t0, t1, flag):"
    loop = "        for r in range(runs):\n"
    read = "            g = gam[0, t, r]\n"
    if src.count(head) != 1 or src.count(read) != 1 or src.count(loop) != 1:
        raise ValueError("fused kf: unexpected kernel source")
    if law == "bernoulli":
        arrival = "            g = 1.0 if u[t, r] < pa else 0.0\n"
    elif law == "gilbert_elliott":
        src = src.replace(loop, "        first = t == 0\n" + loop)
        arrival = ("            ut = u[t, r]\n"
                   "            gp = gprev[r]\n"
                   "            gb = (first & (ut < pc)) | (~first & ((gp & (ut >= pa)) | (~gp & (ut < pb))))\n"
                   "            gprev[r] = gb\n"
                   "            g = 1.0 if gb else 0.0\n")
    else:
        raise ValueError(f"fused kf: no arrival law {law!r}")
    return src.replace(head, "def advance_u(P, u, gprev, pa, pb, pc, t0, t1, flag):").replace(read, arrival)


def source_predict(A, Q) -> str:
    """The source of ``predict_tri(T, out)``: out ← A P Aᵀ + Q per run, packed upper triangles (the
    ``predicted`` quantity P_{k+1|k} of a filtered P_{k|k})."""
    A, Q = np.atleast_2d(np.asarray(A, float)), np.atleast_2d(np.asarray(Q, float))
    n = A.shape[0]
    tri = [(i, j) for i in range(n) for j in range(i, n)]

    def p(i, j):
        return f"p{min(i, j)}_{max(i, j)}"

    L = ["import numpy as np", "import numba as nb", "",
         "@nb.njit(cache=True, nogil=True, fastmath=False, error_model='numpy')",
         "def predict_tri(T, out):", "    for r in range(T.shape[1]):"]
    L += [f"        {p(i, j)} = T[{k}, r]" for k, (i, j) in enumerate(tri)]
    for i in range(n):
        for j in range(n):
            L.append(f"        x{i}_{j} = {kc._lin([(A[i, k], p(k, j)) for k in range(n)])}")
    for k, (i, j) in enumerate(tri):
        L.append(f"        out[{k}, r] = {kc._lin([(A[j, q], f'x{i}_{q}') for q in range(n)])} + {kc._num(Q[i, j])}")
    return "\n".join(L) + "\n"


def supported(f: "kalman.Filter") -> bool:
    """The fused kernel exists for this filter: one arrival stream, a generated kernel (kc.supported)."""
    return len(f.groups) == 1 and kc.supported(f.A.shape[0], f.groups)


class FusedFilter:
    """The fused kernel of one ``kf`` filter ``f`` under the arrival law ``(law, params)`` of a channel."""

    def __init__(self, f: "kalman.Filter", law: str, params: tuple[float, ...], P0: np.ndarray):
        self.f, self.law, self.P0 = f, LAWS.index(law), np.asarray(P0, dtype=float)
        self.params = tuple(float(x) for x in params) + (0.0,) * (3 - len(params))
        self.adv = kc._load(source_fused(f.A, f.C, f.Q, f.R, f.groups, f.rescue.limit, law), "netkf_kfu", "advance_u")
        self.pred = kc._load(source_predict(f.A, f.Q), "netkf_kfp", "predict_tri")

    def start(self, runs: int):
        """(T, gprev, flag): the packed P0 of ``runs`` runs, the arrival memory and the rescue flags."""
        P = np.repeat(self.P0[:, :, None], runs, axis=2)
        return kc.pack(P), np.zeros(runs, dtype=np.bool_), np.zeros(runs, dtype=np.bool_)

    def advance(self, T, u, gprev, flag, t0: int, t1: int) -> None:
        """Steps t0 … t1 − 1 in place (T then holds P_{t1|t1}); ``flag`` raised for runs the numpy core redoes."""
        pa, pb, pc = self.params
        self.adv(T, u, gprev, pa, pb, pc, t0, t1, flag)

    def first_flagged(self, u, upto: int) -> np.ndarray:
        """Per run, the first step t ≤ ``upto`` after which this kernel has flagged it for the rescue (``upto`` + 1:
        never): :func:`kalman.first_flagged` on a second pass over the same uniforms ``u`` from P0."""
        pa, pb, pc = self.params
        gprev = np.zeros(u.shape[-1], dtype=np.bool_)

        def adv(T, uu, t0, t1, flag):
            self.adv(T, uu, gprev, pa, pb, pc, t0, t1, flag)

        return kalman.first_flagged(adv, np.broadcast_to(self.P0[:, :, None], self.P0.shape + (u.shape[-1],)), u, upto)

    def predicted(self, T, out=None):
        """A P Aᵀ + Q of the packed T (into ``out``)."""
        out = np.empty_like(T) if out is None else out
        self.pred(T, out)
        return out
