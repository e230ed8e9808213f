"""The generic Monte Carlo engine: channel → trace → estimator(s) → reduced statistics.

One kernel serves every (channel, estimator, metric) combination:

    trace = channel.sample_trace(rng, runs, horizon)            # one batch, run axis innermost
    for each estimator j:                                        # the SAME trace: common random numbers
        for k, Ps in estimator.covariances(system, trace, steps, (quantity,)):
            reducer.update(stats, j, k, Ps[quantity])            # additive statistics only

``quantity`` is one of :data:`netkf_cli.linalg.kalman.QUANTITIES` (filtered P_{k|k}, predicted P_{k+1|k},
smoothed P_{k−N|k}), the same for every estimator of a run.

:class:`PairKernel` and the reducers are module-level classes, so a kernel pickles and runs on
the process pool and on Dask exactly as in the parent, and chunk statistics add up in chunk
order to the same bits for any executor (:mod:`netkf_cli.runtime.montecarlo`).
"""

from __future__ import annotations

import numpy as np

from netkf_cli.linalg import batched, kalman
from netkf_cli.linalg import kalman_codegen as kc
from netkf_cli.linalg import reduce_codegen as rc
from netkf_cli.core.errors import ConfigError
from netkf_cli.runtime.montecarlo import run_chunked
from netkf_cli.core.stats import MeanSummary, central4, heavy_tail_flag, mean_se, rare_event_flag  # noqa: F401 (re-exported)
from netkf_cli.core.tolerances import HEAVY_TAIL_RSE  # noqa: F401 (re-exported)


def covariances(estimator, system, trace, steps, quantity: str = "filtered"):
    """(k, P_k, w) of ``estimator``'s ``quantity`` at ``steps`` (the engine's one call into an estimator).

    ``w`` is ``None``, or the per-run importance weights (runs,) of a variance-reduced estimator
    (E[w] = 1): every statistic is then a mean of w·x (unbiased), its standard error that of w·x.
    """
    for k, out in estimator.covariances(system, trace, steps, (quantity,)):
        yield k, out[quantity], out.get("weight")


def _check_pair(channel, estimator) -> None:
    """The engine's own guard (the loader's ``netkf validate`` gives the full message with the compatible kinds):
    the estimator must read a trace field the channel samples."""
    acc = getattr(estimator, "accepts", frozenset())
    tk = getattr(channel, "trace_kinds", frozenset())
    if not (acc & tk):
        raise ConfigError.at("estimator.kind", f"estimator {estimator.kind!r} needs a channel providing "
                                               f"{'/'.join(sorted(acc)) or 'a trace'}, but channel {channel.kind!r} "
                                               f"provides {'/'.join(sorted(tk)) or 'no trace'}")


REDUCE_MIN_RUNS = 2048
"""A reducer's ``backend: auto`` reduces a batch of at least this many runs with the compiled reductions
(:mod:`netkf_cli.linalg._reduce_numba`, when numba is importable): one pass instead of ~10 numpy passes and a
batched eigvalsh; smaller batches (tests, quick runs) stay on numpy."""
EAGER_REDUCE_MIN_RUNS = 128
"""The same within ``kalman.eager_compile`` (``netkf reproduce``, whose processes import numba anyway): the quick
reproduction's batches of a few hundred to 2000 runs reduced in one compiled pass per block instead of step by step
on numpy (its workers' CPU 14.7 -> 13.7 s, 2026-12-06)."""


def _rn():
    from netkf_cli.linalg import _reduce_numba as rn  # optional dependency (numba): the compiled reductions

    return rn


REDUCED = "reduced_steps"
"""Stats key: (compiled, numpy), how many (estimator, step) reductions of the batch each path made, summed over
the chunks: what the manifest's ``reduction`` reports (recorded, not predicted: :func:`reduction_used`)."""


def _record(stats: dict, compiled: bool, count: int = 1) -> None:
    stats.setdefault(REDUCED, np.zeros(2, dtype=np.int64))[0 if compiled else 1] += count


def reduction_used(stats: dict) -> str:
    """The manifest's statement of which reductions ran, from the counts :data:`REDUCED` recorded: ``numpy``,
    the compiled label, or both with their shares (a last, smaller chunk below the floor, or weighted runs)."""
    c, p = (int(x) for x in np.asarray(stats.get(REDUCED, (0, 0))))
    if c and p:
        return f"{REDUCTION_LABEL} ({c} of {c + p} step reductions), numpy ({p})"
    return REDUCTION_LABEL if c else "numpy"


REDUCTION_LABEL = "numba (compiled reductions: linalg/_reduce_numba)"


def _compiled(backend: str, P: np.ndarray, w) -> bool:
    """Whether a reducer with ``backend`` (numpy | numba | auto) reduces the batch P compiled (never for
    weighted statistics: the compiled reductions have no weights)."""
    if backend == "numpy" or w is not None:
        return False
    if backend == "numba":
        return True
    floor = EAGER_REDUCE_MIN_RUNS if kalman.eager() else REDUCE_MIN_RUNS
    return P.shape[-1] >= floor and kalman.numba_available()


_TRIU: dict = {}


def _tri(P: np.ndarray) -> np.ndarray:
    """The packed upper triangle (kalman_codegen layout) of sym(P) = (P + Pᵀ)/2 (the same operations as
    ``batched.sym``), the matrix every reduction reads."""
    n = P.shape[0]
    if n not in _TRIU:
        i, j = np.triu_indices(n)
        _TRIU[n] = (i * n + j, j * n + i)  # flat positions of P[i, j] and P[j, i]
    fi, fj = _TRIU[n]
    F = P.reshape(n * n, P.shape[-1])
    with np.errstate(over="ignore", invalid="ignore"):
        T = F.take(fi, axis=0)  # 0.5·(P[i, j] + P[j, i]) in place: the same two operations, fewer temporaries
        T += F.take(fj, axis=0)
        T *= 0.5
    return T


def _ambiguous(T: np.ndarray, n: int, amb: np.ndarray, M: np.ndarray):
    """(runs, ok (nM, k)) for the runs a compiled PSD-order kernel left undecided (a threshold within the
    1e-11 margin of their λ_max): decided here exactly as the numpy reducers do (eigvalsh)."""
    idx = np.flatnonzero(amb)
    lm = batched.lambda_max(kc.unpack(T[:, idx], n))
    return idx, lm[None, :] <= (M + batched.PSD_TOL * np.maximum(1.0, M))[:, None]


def _thresholds(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ascending M + PSD_TOL·max(1, M), the index of each in M): P ≤ M·I ⇔ λ_max(P) ≤ this (the numpy
    reducers' comparison), sorted for the compiled binary search."""
    M = np.atleast_1d(np.asarray(M, dtype=float))
    key = M.tobytes()
    if key not in _THRESHOLDS:
        _THRESHOLDS[key] = _sorted_thresholds(M)
    return _THRESHOLDS[key]


_THRESHOLDS: dict = {}


def _sorted_thresholds(M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    thr = M + batched.PSD_TOL * np.maximum(1.0, M)
    order = np.argsort(thr, kind="stable")
    return np.ascontiguousarray(thr[order]), order.astype(np.int64)


def _step_pos(red, k: int):
    """Position of step k in ``red.steps`` (the first, as ``list.index``), None if absent: a dict built once
    per steps list (the reducers are called once per step and estimator: a 300-step list scan each time
    cost ~1 s in a stationary sweep)."""
    cache = red.__dict__.get("_step_pos")
    if cache is None or cache[0] is not red.steps:
        pos: dict = {}
        for i, s in enumerate(red.steps):
            pos.setdefault(s, i)
        cache = red.__dict__["_step_pos"] = (red.steps, pos)
    return cache[1].get(k)


def _step_index(red, k: int) -> int:
    """:func:`_step_pos`, raising ValueError for a step not in ``red.steps`` (as ``list.index``)."""
    i = _step_pos(red, k)
    if i is None:
        raise ValueError(f"{k} is not in list")
    return i


class DistributionReducer:
    """Counts of P_k ≤ M (PSD order; scalar M means M·Iₙ) per estimator, step and M.

    ``backend`` (numpy | numba | auto, :func:`_compiled`): the numpy statistics below, or the same ones
    from :meth:`update_tri` (compiled, equal counts: tests/engine/test_reduce_numba.py)."""

    means_only = False  # Pr[P_k <= M] needs each run's own covariance
    backend = "auto"

    def __init__(self, M: np.ndarray, steps: list[int]):
        self.M = np.asarray(M, dtype=float)
        self.steps = list(steps)

    def update_tri(self, stats: dict, j: int, k: int, T: np.ndarray, n: int) -> None:
        """:meth:`update` for packed covariances T (n(n+1)/2, runs), compiled."""
        i = _step_index(self, k)
        cnt = stats.setdefault(f"count_{j}", np.zeros((len(self.steps), len(self.M))))
        bad = stats.setdefault(f"nonfinite_{j}", np.zeros(len(self.steps)))
        row = np.zeros(len(self.M))
        thr, order = _thresholds(self.M)
        amb = np.zeros(T.shape[-1], dtype=np.bool_)
        bad[i] += rc.kernel_dist(n)(T, thr, order, row, amb)
        if amb.any():
            row += _ambiguous(T, n, amb, self.M)[1].sum(axis=1)
        cnt[i] += row
        stats["n"] = T.shape[-1]
        _record(stats, True)

    def update(self, stats: dict, j: int, k: int, P: np.ndarray, w: np.ndarray | None = None) -> None:
        if _compiled(self.backend, P, w):
            return self.update_tri(stats, j, k, _tri(P), P.shape[0])
        _record(stats, False)
        i = _step_index(self, k)
        cnt = stats.setdefault(f"count_{j}", np.zeros((len(self.steps), len(self.M))))
        bad = stats.setdefault(f"nonfinite_{j}", np.zeros(len(self.steps)))
        lmax = batched.lambda_max(P)  # P ≤ M·I ⇔ λ_max(P) ≤ M (inf for non-finite runs)
        finite = np.isfinite(lmax)
        tol = batched.PSD_TOL * np.maximum(1.0, self.M)
        ok = lmax[None, :] <= (self.M + tol)[:, None]
        if w is None:
            cnt[i] += ok.sum(axis=1)
        else:  # weighted: Σ w·1[P ≤ M] and Σ (w·1)² for the standard error (no Wilson interval)
            cnt[i] += (ok * w[None, :]).sum(axis=1)
            stats.setdefault(f"countsq_{j}", np.zeros((len(self.steps), len(self.M))))[i] += (ok * (w * w)[None, :]).sum(axis=1)
        bad[i] += (~finite).sum()
        stats["n"] = P.shape[-1]


class MomentReducer:
    """Sums of tr P, λ_max(P) (``lmax``: only if asked, it costs an eigenvalue per run and step), P entries
    (and squares, 4th powers of tr P) per estimator and step. ``backend`` as :class:`DistributionReducer`."""

    means_only = True  # only means of P: a variance-reduced estimator may serve them (Estimator.for_means)
    backend = "auto"

    def __init__(self, steps: list[int], lmax: bool = True):
        self.steps = list(steps)
        self.lmax = bool(lmax)

    def update_tri(self, stats: dict, j: int, k: int, T: np.ndarray, n: int) -> None:
        """:meth:`update` for packed covariances T (n(n+1)/2, runs), compiled (sums in run order)."""
        i, K = _step_index(self, k), len(self.steps)
        nt = T.shape[0]
        out, e, e2 = np.zeros(8), np.zeros(nt), np.zeros(nt)
        rc.kernel_moments(n)(T, self.lmax, out, e, e2, np.empty((n, n)))
        sP, sP2 = kc.unpack(e[:, None], n)[:, :, 0], kc.unpack(e2[:, None], n)[:, :, 0]

        def acc(key, shape, value):
            stats.setdefault(f"{key}_{j}", np.zeros(shape))[i] += value

        for key, v in zip(("sum_tr", "sumsq_tr", "sum3_tr", "sum4_tr"), out[:4]):
            acc(key, K, v)
        if self.lmax:
            acc("sum_lmax", K, out[4])
            acc("sumsq_lmax", K, out[5])
        acc("sum_P", (K, n, n), sP)
        acc("sumsq_P", (K, n, n), sP2)
        acc("nonfinite", K, out[6])
        m = stats.setdefault(f"max_tr_{j}", np.zeros(K))
        m[i] = max(m[i], float(out[7]))
        stats["n"] = T.shape[-1]
        _record(stats, True)

    def update(self, stats: dict, j: int, k: int, P: np.ndarray, w: np.ndarray | None = None) -> None:
        if _compiled(self.backend, P, w):
            return self.update_tri(stats, j, k, _tri(P), P.shape[0])
        _record(stats, False)
        i, K, n = _step_index(self, k), len(self.steps), P.shape[0]
        tr = batched.trace(P)
        finite = np.isfinite(P).all(axis=(0, 1))
        lm = batched.lambda_max(P) if self.lmax else tr
        trf, lmf, Pf = np.where(finite, tr, 0.0), np.where(finite, lm, 0.0), np.where(finite, P, 0.0)
        if w is not None:  # a variance-reduced estimator: statistics of w·x (E[w] = 1)
            trf, lmf, Pf = trf * w, lmf * w, Pf * w[None, None, :]

        def acc(key, shape, value):
            stats.setdefault(f"{key}_{j}", np.zeros(shape))[i] += value

        with np.errstate(over="ignore", invalid="ignore"):
            acc("sum_tr", K, trf.sum())
            acc("sumsq_tr", K, (trf * trf).sum())
            acc("sum3_tr", K, (trf**3).sum())
            acc("sum4_tr", K, (trf**4).sum())
            if self.lmax:
                acc("sum_lmax", K, lmf.sum())
                acc("sumsq_lmax", K, (lmf * lmf).sum())
            acc("sum_P", (K, n, n), Pf.sum(axis=-1))
            acc("sumsq_P", (K, n, n), (Pf * Pf).sum(axis=-1))
            acc("nonfinite", K, (~finite).sum())
            m = stats.setdefault(f"max_tr_{j}", np.zeros(K))
            m[i] = max(m[i], float(trf.max()) if trf.size else 0.0)
        stats["n"] = P.shape[-1]


class PairedReducer:
    """Differences tr P_j − tr P_0 on the same traces (common random numbers), and both moments."""

    means_only = True  # only means of P: a variance-reduced estimator may serve them (Estimator.for_means)

    def __init__(self, steps: list[int]):
        self.steps = list(steps)
        self.inner = MomentReducer(steps)

    def update(self, stats: dict, j: int, k: int, P: np.ndarray, w: np.ndarray | None = None) -> None:
        self.inner.update(stats, j, k, P, w)
        i = _step_index(self, k)
        tr = batched.trace(P) if w is None else batched.trace(P) * w
        if j == 0:
            stats.setdefault("_ref", {})[k] = tr
            return
        ref = stats["_ref"][k]
        with np.errstate(invalid="ignore", over="ignore"):
            d = tr - ref
        ok = np.isfinite(d)
        d = np.where(ok, d, 0.0)
        K = len(self.steps)
        stats.setdefault(f"sum_diff_{j}", np.zeros(K))[i] += d.sum()
        stats.setdefault(f"sumsq_diff_{j}", np.zeros(K))[i] += (d * d).sum()
        stats.setdefault(f"n_diff_{j}", np.zeros(K))[i] += ok.sum()
        mx = stats.setdefault(f"max_absdiff_{j}", np.zeros(K))
        mx[i] = max(mx[i], float(np.abs(d).max()))


FUSED_CHUNKS = "fused_chunks"
"""Stats key: per estimator, how many chunks ran in its fused kernel (what the manifest's ``backends`` reports)."""

FUSED_LABEL = "numba, fused (uniforms → arrivals → filter → reduction in one kernel: kf_fused)"


class PairKernel:
    """Sample one trace batch and run every estimator on it; reduce with ``reducer`` (picklable)."""

    def __init__(self, system, channel, estimators, horizon: int, steps, reducer, quantity: str = "filtered"):
        self.system, self.channel, self.estimators = system, channel, list(estimators)
        self.horizon, self.steps, self.reducer = int(horizon), sorted(int(k) for k in steps), reducer
        self.quantity = quantity
        self._fused_cache: dict = {}

    def __getstate__(self):  # the fused kernels (numba dispatchers) are rebuilt in each process
        return {**self.__dict__, "_fused_cache": {}}

    def fused(self, runs: int) -> list | None:
        """Per estimator, its fused kernel (``estimator.fused``: :mod:`netkf_cli.linalg.kf_fused`) for chunks of
        ``runs`` runs, when every estimator has one and one quantity (filtered | predicted) is reduced;
        else None (the trace → covariances → reducer path)."""
        if runs not in self._fused_cache:
            out = None
            if isinstance(self.quantity, str) and self.quantity in ("filtered", "predicted") and self.steps:
                means_only = bool(getattr(self.reducer, "means_only", False))
                out = []
                for est in self.estimators:
                    est = est.for_means(self.channel) if means_only else est
                    fz = getattr(est, "fused", None)
                    fz = fz(self.system, self.channel, runs * self.horizon) if fz is not None else None
                    if fz is None:
                        out = None
                        break
                    out.append(fz)
            self._fused_cache[runs] = out
        return self._fused_cache[runs]

    def _run_fused(self, fzs: list, rng: np.random.Generator, runs: int) -> dict:
        """The chunk in fused kernels: the channel's uniforms (its own draw: the same numbers as
        ``sample_trace``) → per estimator, arrivals and filter steps compiled up to each reported step →
        the reducer's compiled ``update_tri`` on the packed state (or, for a reducer without one, its
        ``update`` on the unpacked P). Rescue-flagged runs are carried on the numpy core from P0 and written over
        their packed columns, as the compiled filter does (:meth:`kalman.Filter.stream_generated`): at the first
        flag, a second kernel pass finds when each run is first flagged (:meth:`FusedFilter.first_flagged`) and
        those runs advance once through the numpy core in step with the reporting pass."""
        u = self.channel.uniforms(rng, runs, self.horizon)
        q, red = self.quantity, self.reducer
        tri = hasattr(red, "update_tri")
        stats: dict = {}
        gam = None
        for j, fz in enumerate(fzs):
            f = fz.f
            n = f.A.shape[0]
            T, gprev, flag = fz.start(runs)
            X = T if q == "filtered" else np.empty_like(T)
            idx = k0 = Pn = None
            t = tn = 0
            for k in self.steps:
                fz.advance(T, u, gprev, flag, t, k)
                t = k
                if q != "filtered":
                    fz.predicted(T, X)
                if idx is None and flag.any():  # the first flag: when is every run first flagged?
                    if gam is None:
                        gam = self.channel.arrivals_from_uniforms(u)[None]
                    first = fz.first_flagged(u, self.steps[-1])
                    idx = np.flatnonzero(first <= self.steps[-1])
                    # a run flagged at step t is reported from the numpy core from the first step ≥ t on
                    k0 = np.asarray(self.steps, dtype=np.int64)[np.searchsorted(self.steps, first[idx])]
                    Pn = np.repeat(fz.P0[:, :, None], idx.size, axis=2)
                if idx is not None:
                    while tn < k:
                        Pn = f.step(Pn, gam[:, tn][:, idx])[1]
                        tn += 1
                    sel = k0 <= k
                    if sel.any():
                        X[:, idx[sel]] = kc.pack(kalman.report(Pn[:, :, sel], (q,), f.A, f.Q)[q])
                if tri:
                    red.update_tri(stats, j, k, X, n)
                else:
                    red.update(stats, j, k, kc.unpack(X, n), None)
        finish = getattr(red, "finish", None)
        if finish is not None:
            finish(stats)
        stats.pop("_ref", None)
        stats["n"] = np.asarray(runs)
        stats[FUSED_CHUNKS] = np.ones(len(fzs), dtype=np.int64)
        return stats

    def __call__(self, rng: np.random.Generator, runs: int) -> dict:
        fzs = self.fused(runs)
        if fzs is not None:
            return self._run_fused(fzs, rng, runs)
        trace = self.channel.sample_trace(rng, runs, self.horizon)
        stats: dict = {}
        means_only = bool(getattr(self.reducer, "means_only", False))
        blocks = hasattr(self.reducer, "update_block")
        for j, est in enumerate(self.estimators):
            est = est.for_means(self.channel) if means_only else est
            if isinstance(self.quantity, str):
                for k, P, w in covariances(est, self.system, trace, self.steps, self.quantity):
                    self.reducer.update(stats, j, k, P, w)
                continue
            # several quantities in one pass: each estimator reports those it offers, in column (j, q)
            qs = [q for q in self.quantity if q in getattr(est, "quantities", ("filtered",))]
            if blocks and hasattr(est, "covariance_blocks"):  # by blocks of steps: one reducer call per block
                for ks, out in est.covariance_blocks(self.system, trace, self.steps, tuple(qs)):
                    for q in qs:
                        if q in out:
                            self.reducer.update_block(stats, column(j, self.quantity.index(q), len(self.quantity)),
                                                      ks, out[q], out.get("weight"))
                continue
            for k, out in est.covariances(self.system, trace, self.steps, tuple(qs)):
                for q in qs:
                    if q in out:
                        self.reducer.update(stats, column(j, self.quantity.index(q), len(self.quantity)), k,
                                            out[q], out.get("weight"))
        finish = getattr(self.reducer, "finish", None)
        if finish is not None:
            finish(stats)
        stats.pop("_ref", None)
        stats["n"] = np.asarray(runs)
        stats[FUSED_CHUNKS] = np.zeros(len(self.estimators), dtype=np.int64)
        return stats


def column(j: int, qi: int, nq: int) -> int:
    """The reducer column of estimator j's quantity qi (of nq) in a several-quantities pass."""
    return j * nq + qi


def simulate(system, channel, estimators, reducer, *, steps, runs: int, horizon: int, seed: int, chunk: int,
             stream: int = 0, progress=None, label: str = "", quantity: str | tuple = "filtered") -> dict:
    """Run the generic kernel over all chunks (on the current executor) and return summed statistics."""
    for es in estimators:
        _check_pair(channel, es)
        es.check(system, channel)
    kernel = PairKernel(system, channel, estimators, horizon, steps, reducer, quantity)
    return run_chunked(kernel, runs, chunk, seed, stream=stream, progress=progress, label=label)


def mean_summary(stats: dict, j: int, key: str = "tr") -> MeanSummary:
    """Mean of tr P (``key='tr'``) or λ_max (``'lmax'``) per step over the finite runs, with flags."""
    n = int(stats["n"])
    bad = stats[f"nonfinite_{j}"]
    m_ok = np.maximum(n - bad, 1)
    s1, s2 = stats[f"sum_{key}_{j}"], stats[f"sumsq_{key}_{j}"]
    mean, se = mean_se(s1, s2, m_ok)
    st1, st2 = stats[f"sum_tr_{j}"], stats[f"sumsq_tr_{j}"]
    _, _, heavy = heavy_tail_flag(st1, st2, stats[f"sum3_tr_{j}"], stats[f"sum4_tr_{j}"], m_ok, bad)
    rare = rare_event_flag(st1, stats[f"max_tr_{j}"], m_ok)
    return MeanSummary(np.where(bad > 0, np.inf, mean), se, n, bad, np.asarray(heavy, dtype=bool),
                       np.asarray(rare, dtype=bool))


def mean_covariance(system, channel, estimator, *, runs: int, horizon: int, burn_in: int = 0, seed: int = 0,
                    chunk: int = 20_000, stream: int = 0, progress=None, quantity: str = "filtered") -> dict:
    """Time-averaged E[tr P_k] (of ``quantity``) over k in (burn_in, horizon] with its standard error and flags.

    The per-run time average is one sample per run (runs are independent), so the standard
    error is exact for the time-averaged quantity. Keys: ``mean_trace``, ``stderr``, ``n``,
    ``heavy_tail``, ``nonfinite``, and ``per_step`` (k, mean, stderr, heavy_tail arrays).
    """
    steps = list(range(burn_in + 1, horizon + 1))
    st = simulate(system, channel, [estimator], TimeAverageReducer(steps), steps=steps, runs=runs,
                  horizon=horizon, seed=seed, chunk=chunk, stream=stream, progress=progress,
                  label="mean_covariance", quantity=quantity)
    n = int(st["n"])
    bad = int(st["nonfinite_avg"])
    m_ok = max(n - bad, 1)
    mean, se = (float(x) for x in mean_se(st["sum_avg"], st["sumsq_avg"], m_ok))
    _, rse, heavy = heavy_tail_flag(st["sum_avg"], st["sumsq_avg"], st["sum3_avg"], st["sum4_avg"], m_ok, bad)
    rare = bool(rare_event_flag(st["sum_avg"], st["max_avg"], m_ok))
    rse, heavy = float(rse), bool(heavy)
    return {"mean_trace": float(mean) if bad == 0 else float("inf"), "stderr": se, "n": n,
            "heavy_tail": bool(heavy), "rare_event": rare, "nonfinite": bad, "rse_variance": rse,
            "quantity": quantity}


class StationaryReducer:
    """Per run and column, the time averages over ``steps`` of tr P_k and of 1[P_k ≤ M] (PSD order, one per M).

    Each run's average is one sample (runs are independent), so its mean's standard error is exact for
    the time-averaged quantity. The per-run sums accumulate across the chunk's steps and :meth:`finish`
    (called by the kernel at the end of a chunk) turns them into additive statistics: per column j,
    ``sum/sumsq/sum3/sum4/max`` of the average trace (``_avg_j``), ``sum/sumsq`` of each M's average
    indicator (``_ind_j``, shape (nM,)), ``nonfinite_j`` (runs with a non-finite P at some step: left out
    of the trace mean, counted as not ≤ M) and ``max_nsteps_j``. A column may cover fewer steps than
    ``steps`` (a smoother's lag): the average is over the steps it reported."""

    backend = "auto"

    def __init__(self, steps: list[int], M=None, shift: dict | None = None):
        self.steps = list(steps)
        self.M = None if M is None else np.atleast_1d(np.asarray(M, dtype=float))
        self.means_only = self.M is None  # Pr[P_k ≤ M] needs each run's own covariance
        self.shift = dict(shift or {})
        """Per column, a constant c subtracted before the power sums (``sum_avg`` … hold Σ(a − c)^p): the
        same for every chunk, near the mean, so the 4th central moment keeps its digits when the runs
        differ by 1e-5 relative (raw Σa⁴ would cancel every digit). ``max_avg`` stays raw."""

    def _acc(self, stats: dict, j: int, runs: int) -> dict:
        acc = stats.setdefault("_acc", {})
        a = acc.get(j)
        if a is None:
            a = acc[j] = {"tr": np.zeros(runs), "bad": np.zeros(runs, dtype=bool), "steps": 0,
                          "ind": None if self.M is None else np.zeros((len(self.M), runs))}
        return a

    def update_tri(self, stats: dict, j: int, k: int, T: np.ndarray, n: int) -> None:
        """:meth:`update` for packed covariances T (n(n+1)/2, runs), compiled."""
        if _step_pos(self, k) is None:
            return
        runs = T.shape[-1]
        a = self._acc(stats, j, runs)
        thr = np.zeros(0) if self.M is None else _thresholds(self.M)[0]
        if a.get("hist") is None:
            a["hist"] = np.zeros((0 if self.M is None else len(self.M) + 1, runs))
        amb = np.zeros(runs, dtype=np.bool_)
        rc.kernel_stationary(n)(T, thr, a["tr"], a["bad"], a["hist"], amb)
        if amb.any():
            idx, ok = _ambiguous(T, n, amb, self.M)
            a["ind"][:, idx] += ok
        a["steps"] += 1
        _record(stats, True)

    def update_block(self, stats: dict, j: int, ks: list[int], P: np.ndarray, w: np.ndarray | None = None) -> None:
        """:meth:`update` for the steps ``ks`` of one block P (K, n, n, runs) in one compiled call
        (:func:`netkf_cli.linalg.reduce_codegen.source_stationary_block`: per run the same sums in step order as
        K calls of :meth:`update`, the same decisions); a batch :meth:`update` would reduce on numpy goes step by
        step through it."""
        _step_pos(self, ks[0])  # (builds the reducer's step index once)
        pos = self.__dict__["_step_pos"][1]
        sel = [i for i, k in enumerate(ks) if k in pos]
        if not sel:
            return
        if not _compiled(self.backend, P[0], w):
            for i in sel:
                self.update(stats, j, ks[i], P[i], w)
            return
        X = np.ascontiguousarray(P if len(sel) == len(ks) else P[sel])
        n, runs = X.shape[1], X.shape[-1]
        a = self._acc(stats, j, runs)
        thr = np.zeros(0) if self.M is None else _thresholds(self.M)[0]
        if a.get("hist") is None:
            a["hist"] = np.zeros((0 if self.M is None else len(self.M) + 1, runs))
        amb = np.zeros((len(sel), runs), dtype=np.bool_)
        rc.kernel_stationary_block(n)(X, thr, a["tr"], a["bad"], a["hist"], amb)
        if self.M is not None:
            for s in np.flatnonzero(amb.any(axis=1)):
                idx, ok = _ambiguous(_tri(X[s]), n, amb[s], self.M)
                a["ind"][:, idx] += ok
        a["steps"] += len(sel)
        _record(stats, True, len(sel))

    def update(self, stats: dict, j: int, k: int, P: np.ndarray, w: np.ndarray | None = None) -> None:
        if _step_pos(self, k) is None:
            return
        if _compiled(self.backend, P, w):
            return self.update_tri(stats, j, k, _tri(P), P.shape[0])
        _record(stats, False)
        a = self._acc(stats, j, P.shape[-1])
        tr = batched.trace(P)
        finite = np.isfinite(P).all(axis=(0, 1))
        a["bad"] |= ~finite
        x = np.where(finite, tr, 0.0)
        a["tr"] += x if w is None else x * w
        if self.M is not None:
            lm = batched.lambda_max(P)
            ok = (lm[None, :] <= (self.M + batched.PSD_TOL * np.maximum(1.0, self.M))[:, None]) & finite[None, :]
            a["ind"] += ok if w is None else ok * w[None, :]
        a["steps"] += 1

    def finish(self, stats: dict) -> None:
        for j, a in stats.pop("_acc", {}).items():
            if a.get("hist") is not None and a["ind"] is not None:  # the compiled update's per-run histogram
                a["ind"][_thresholds(self.M)[1]] += np.cumsum(a["hist"][:-1], axis=0)
            T = max(a["steps"], 1)
            ok = ~a["bad"]
            avg = np.where(ok, a["tr"] / T, 0.0)
            d = np.where(ok, avg - self.shift.get(j, 0.0), 0.0)
            with np.errstate(over="ignore"):
                for key, val in (("sum", d.sum()), ("sumsq", (d * d).sum()), ("sum3", (d**3).sum()),
                                 ("sum4", (d**4).sum())):
                    stats[f"{key}_avg_{j}"] = stats.get(f"{key}_avg_{j}", 0.0) + val
            stats[f"max_avg_{j}"] = max(stats.get(f"max_avg_{j}", 0.0), float(avg.max()) if avg.size else 0.0)
            stats[f"nonfinite_{j}"] = stats.get(f"nonfinite_{j}", 0) + int((~ok).sum())
            stats[f"max_nsteps_{j}"] = np.asarray(a["steps"])
            if a["ind"] is not None:
                ind = a["ind"] / T
                stats[f"sum_ind_{j}"] = stats.get(f"sum_ind_{j}", 0.0) + ind.sum(axis=1)
                stats[f"sumsq_ind_{j}"] = stats.get(f"sumsq_ind_{j}", 0.0) + (ind * ind).sum(axis=1)


class TimeAverageReducer:
    """Per run, the average of tr P_k over ``steps``; sums of it, its square and 4th power."""

    means_only = True  # only means of P: a variance-reduced estimator may serve them (Estimator.for_means)
    backend = "auto"

    def __init__(self, steps: list[int]):
        self.steps = list(steps)

    def update_tri(self, stats: dict, j: int, k: int, T: np.ndarray, n: int) -> None:
        """:meth:`update` for packed covariances T (n(n+1)/2, runs), compiled."""
        acc = stats.get("_acc")
        if acc is None or k == self.steps[0]:
            acc = stats["_acc"] = np.zeros(T.shape[-1])
        _rn().trace_acc(T, n, float(len(self.steps)), acc)
        _record(stats, True)
        if k == self.steps[-1]:
            self._close(stats, acc)

    def update(self, stats: dict, j: int, k: int, P: np.ndarray, w: np.ndarray | None = None) -> None:
        if _compiled(self.backend, P, w):
            return self.update_tri(stats, j, k, _tri(P), P.shape[0])
        _record(stats, False)
        acc = stats.get("_acc")
        if acc is None or k == self.steps[0]:
            acc = stats["_acc"] = np.zeros(P.shape[-1])
        with np.errstate(over="ignore", invalid="ignore"):
            acc += (batched.trace(P) if w is None else batched.trace(P) * w) / len(self.steps)
        if k == self.steps[-1]:
            self._close(stats, acc)

    def _close(self, stats: dict, acc: np.ndarray) -> None:
        """The per-run averages ``acc`` of the chunk into its additive statistics."""
        ok = np.isfinite(acc)
        a = np.where(ok, acc, 0.0)
        with np.errstate(over="ignore"):
            stats["sum_avg"] = stats.get("sum_avg", 0.0) + a.sum()
            stats["sumsq_avg"] = stats.get("sumsq_avg", 0.0) + (a * a).sum()
            stats["sum3_avg"] = stats.get("sum3_avg", 0.0) + (a**3).sum()
            stats["sum4_avg"] = stats.get("sum4_avg", 0.0) + (a**4).sum()
            stats["max_avg"] = max(stats.get("max_avg", 0.0), float(a.max()) if a.size else 0.0)
        stats["nonfinite_avg"] = stats.get("nonfinite_avg", 0) + int((~ok).sum())
        del stats["_acc"]
