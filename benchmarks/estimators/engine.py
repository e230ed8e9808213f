"""Benchmark cases of the generic engine's intermittent KF (``kind: kf``) for bench_estimators.py.

The kernel ``netkf run`` builds for a composed scenario (:class:`netkf_cli.engine.PairKernel`): a
``bernoulli`` (or ``gilbert_elliott``) channel → ``kf`` → the reducer of a metric: ``distribution``
(counts of P_k ≤ M at k = horizon, 50 M), ``mean_vs_time`` (E tr P_k at every step) and ``time_average``
(per-run averages of tr P_k and of 1[P_k ≤ M] over k in (50, 100], 10 M). ``numpy``: the reference
(trace → Filter.run on the numpy core → numpy reducer); ``numba``: the fused kernel (the channel's
uniforms → arrivals → generated filter step → compiled reduction, issue 20). Systems as in ``shi2009.py``.
``profile`` prints the measured split per run-step on one core.
"""

from __future__ import annotations

import time

import numpy as np

from netkf_cli.channels.bernoulli import BernoulliChannel
from netkf_cli.channels.gilbert_elliott import GilbertElliottChannel
from netkf_cli.engine import DistributionReducer, MomentReducer, PairKernel, StationaryReducer
from netkf_cli.estimators.kf import KalmanFilterEstimator
from netkf_cli.linalg.kalman import numba_available

from benchmarks.estimators.shi2009 import systems

HORIZON = 100
RUNS = 20_000
CHANNELS = {"bernoulli": lambda: BernoulliChannel(kind="bernoulli", arrival=0.8),
            "gilbert_elliott": lambda: GilbertElliottChannel(kind="gilbert_elliott", loss_rate=0.2, mean_burst=2.0)}


def _reducer(metric: str, M: np.ndarray):
    if metric == "distribution":
        return DistributionReducer(np.asarray(M), [HORIZON]), [HORIZON]
    if metric == "mean_vs_time":
        ks = list(range(1, HORIZON + 1))
        return MomentReducer(ks, lmax=False), ks
    win = list(range(HORIZON // 2 + 1, HORIZON + 1))
    return StationaryReducer(win, np.asarray(M)[::5]), win


class _Make:
    def __init__(self, system: str, backend: str = "numpy", metric: str = "distribution", channel: str = "bernoulli"):
        self.system, self.backend, self.metric, self.channel = system, backend, metric, channel

    def __call__(self):
        s, _, _, M = systems()[self.system]
        red, steps = _reducer(self.metric, M)
        red.backend = self.backend  # numpy: the whole reference path; numba: compiled reductions
        kernel = PairKernel(s, CHANNELS[self.channel](), [KalmanFilterEstimator(kind="kf", backend=self.backend)],
                            HORIZON, steps, red)
        return kernel, RUNS, HORIZON


def _best(fn, repeat: int = 3) -> float:
    out = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        out = min(out, time.perf_counter() - t0)
    return out


def profile(kernel) -> str:
    """The measured split of one chunk (ns per run-step, one core): trace or uniforms, recursion, reduction."""
    rs = RUNS * HORIZON
    ns = 1e9 / rs
    ch, red = kernel.channel, kernel.reducer
    fz = kernel.fused(RUNS)
    if fz is None:  # the numpy path: trace, the filter reporting every reduced step, the reducer
        est = kernel.estimators[0]
        tt = _best(lambda: ch.sample_trace(np.random.default_rng(0), RUNS, HORIZON), 1)
        trace = ch.sample_trace(np.random.default_rng(0), RUNS, HORIZON)
        tf = _best(lambda: [None for _ in est.covariances(kernel.system, trace, kernel.steps)], 1)

        def both():
            st = {}
            for k, o in est.covariances(kernel.system, trace, kernel.steps):
                red.update(st, 0, k, o["filtered"])
            getattr(red, "finish", lambda s: None)(st)
        tr = _best(both, 1) - tf
        return f"trace {tt * ns:.1f} + filter {tf * ns:.1f} + reduction {tr * ns:.1f} ns per run-step"
    f = fz[0]
    u = ch.uniforms(np.random.default_rng(0), RUNS, HORIZON)
    tu = _best(lambda: ch.uniforms(np.random.default_rng(0), RUNS, HORIZON))

    def adv():
        T, g, fl = f.start(RUNS)
        t = 0
        for k in kernel.steps:
            f.advance(T, u, g, fl, t, k)
            t = k
        return T
    ta = _best(adv)
    T = adv()

    def adv_flags():
        T, g, fl = f.start(RUNS)
        f.advance(T, u, g, fl, 0, kernel.steps[-1])
        return fl
    n = f.f.A.shape[0]

    def reduce():
        st = {}
        for k in kernel.steps:
            red.update_tri(st, 0, k, T, n)
        getattr(red, "finish", lambda s: None)(st)
    tr = _best(reduce)
    # the whole chunk on the same uniforms: what the parts above leave out is the rescue, runs the kernel flags
    # (tr P⁻ above Rescue.limit) continuing on the numpy core, step by step in Python, from the step they are flagged
    tw = _best(lambda: kernel(np.random.default_rng(0), RUNS))
    flagged = int(np.count_nonzero(adv_flags()))
    rest = max(tw - tu - ta - tr, 0.0)
    return (f"uniforms {tu * ns:.1f} + arrivals & filter {ta * ns:.1f} + reduction {tr * ns:.1f} + the rest "
            f"{rest * ns:.1f} ns per run-step (the rest: {flagged} of {RUNS} runs flagged for the rescue continue on "
            f"the numpy core, {rest * 1e3:.1f} ms of the chunk's {tw * 1e3:.1f}; numpy's PCG64 uniforms alone bound "
            f"one core at {1 / tu * rs:.2e})")


def _uniform_rate() -> float:
    """numpy's generator: uniforms per second on one core (the fused kernel's input; its bound)."""
    rng = np.random.default_rng(0)
    t = _best(lambda: rng.random((HORIZON, RUNS)))
    return RUNS * HORIZON / t


ANCHORS = {"numpy rng.random((horizon, runs)), uniforms/s": _uniform_rate}

CASES = []
for _metric in ("distribution", "mean_vs_time", "time_average"):
    for _be in ("numpy", "numba") if numba_available() else ("numpy",):
        for _name in ("scalar", "3-state", "vehicle"):
            CASES.append({"estimator": f"kf {_metric}", "system": _name, "backend": _be, "threads": None,
                          "path": "engine", "make": _Make(_name, _be, _metric), "profile": profile})
for _be in ("numpy", "numba") if numba_available() else ("numpy",):
    for _name in ("scalar", "3-state", "vehicle"):
        CASES.append({"estimator": "kf distribution GE", "system": _name, "backend": _be, "threads": None,
                      "path": "engine", "make": _Make(_name, _be, "distribution", "gilbert_elliott"), "profile": profile})
