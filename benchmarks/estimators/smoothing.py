"""Benchmark cases of the Leong, Dey & Evans fixed-lag smoother for ``benchmarks/bench_estimators.py``.

``CASES``: dicts ``{"estimator": "smoother_lag0" | "smoother_lag1" | "smoother_lag3", "system": "scalar" |
"3-state" | "vehicle", "backend": "numpy" | "numba", "threads": None, "make": callable() -> (kernel, runs,
horizon)}``.

The kernel is the one ``netkf run`` builds for a ``distribution`` analysis of the smoothed covariance at the
last step (the generic engine: :class:`netkf_cli.engine.PairKernel` → ``SmootherEstimator.covariances`` →
:class:`netkf_cli.engine.DistributionReducer`): per chunk it samples a Bernoulli(0.8) arrival trace of
``horizon`` steps, runs the filter over it and the lag-N smoother block for P_{H−N|H} (quantity ``smoothed``
at step H), and counts P ≤ M (PSD order) and non-finite runs. A run-step is one step of the trace. Only the
requested step is smoothed (kf's forward pass, then J_t, C_t for the last N trace steps and N RTS maps), so
lags cost little more than the filter. ``smoother lags 0,1,2,4 time_average GE`` is the configs' workload
(configs/smoothing/burstiness*.yaml: every step of (60, 560] requested, four lags on one Gilbert–Elliott trace,
sharing one forward pass and chain). ``profile(kernel)``: the measured split (trace, forward, backward, reducer).

The numpy and numba backends work on the same uniforms: bitwise-equal statistics for the scalar
system, equal to round-off for vector systems (tests/smoothing/test_contract.py). Systems as in
``shi2009.py`` (scalar A = 1.4; the 3-state system of Shi 2009 Fig. 8; the 4-state vehicle).
"""

from __future__ import annotations

import time

import numpy as np

from netkf_cli.linalg import kalman
from netkf_cli.channels.bernoulli import BernoulliChannel
from netkf_cli.channels.gilbert_elliott import GilbertElliottChannel
from netkf_cli.engine import DistributionReducer, PairKernel, StationaryReducer
from netkf_cli.estimators import smoother as sm
from netkf_cli.estimators.smoother import SmootherEstimator, numba_available

from benchmarks.estimators.shi2009 import systems

HORIZON = 100
RUNS = {"numpy": 20_000, "numba": 50_000}


class _Make:
    """Picklable ``make()``."""

    def __init__(self, lag: int, system: str, backend: str):
        self.lag, self.system, self.backend = lag, system, backend

    def __call__(self):
        s = systems()[self.system][0]
        M = systems()[self.system][3]
        Mm = np.array([float(np.median(M))])  # P ≤ Mm·I
        ch = BernoulliChannel(kind="bernoulli", arrival=0.8)
        est = SmootherEstimator(kind="smoother", lag=self.lag, backend=self.backend)
        kernel = PairKernel(s, ch, [est], HORIZON, [HORIZON], DistributionReducer(Mm, [HORIZON]), quantity="smoothed")
        return kernel, RUNS[self.backend], HORIZON


class _MakeTA:
    """The configs' workload (configs/smoothing/burstiness*.yaml): smoothers of lags 0, 1, 2, 4 on one
    Gilbert–Elliott trace, ``time_average`` (per-run averages of 1[P_{k−N|k} ≤ M] over k in (60, 560]); a
    run-step is one step of the trace (serving the four smoothers)."""

    def __init__(self, system: str, backend: str):
        self.system, self.backend = system, backend

    def __call__(self):
        s = systems()[self.system][0]
        ch = GilbertElliottChannel(kind="gilbert_elliott", loss_rate=0.4, mean_burst=3.0)
        ests = [SmootherEstimator(kind="smoother", lag=lag, backend=self.backend) for lag in (0, 1, 2, 4)]
        steps = list(range(TA_BURN + 1, TA_HORIZON + 1))
        kernel = PairKernel(s, ch, ests, TA_HORIZON, steps, StationaryReducer(steps, np.array([6.25])), quantity="smoothed")
        return kernel, TA_RUNS, TA_HORIZON


TA_RUNS, TA_HORIZON, TA_BURN = 4000, 560, 60


def _best(fn, repeat: int = 3) -> float:
    """Best CPU time of ``repeat`` calls (process time: less sensitive to a loaded machine than wall time)."""
    out = float("inf")
    for _ in range(repeat):
        t0 = time.process_time()
        fn()
        out = min(out, time.process_time() - t0)
    return out


def profile(kernel) -> str:
    """The measured split of one chunk (ns per run-step, one core): the trace, kf's forward pass (once per
    trace: shared by the smoothers), the backward pass (J_t, C_t once per trace step, the chain of every
    lag) with the yields, and the reducer."""
    runs, H = (TA_RUNS, TA_HORIZON) if len(kernel.estimators) > 1 else (RUNS[kernel.estimators[0].backend], HORIZON)
    ns = 1e9 / (runs * H)
    s, ch = kernel.system, kernel.channel
    tt = _best(lambda: ch.sample_trace(np.random.default_rng(0), runs, H))
    trace = ch.sample_trace(np.random.default_rng(0), runs, H)
    f = kalman.Filter.of(s, 1)
    lag = max(int(e.lag) for e in kernel.estimators)
    want = sorted({t for k in kernel.steps for t in range(max(1, k - max(lag, sm.SHARE_MARGIN)), k + 1)})
    P0 = sm.initial_covariance(s)
    if kernel.estimators[0].backend == "numpy" or runs * H < kalman.AUTO_MIN_RUN_STEPS:
        tf = _best(lambda: list(f.run(P0, trace.arrival, want, ("filtered",), backend="numpy")))
    else:
        tf = _best(lambda: sm._forward_compiled(f, P0, trace.arrival, want))

    def smooth():
        sm._TLS.last = None
        for e in kernel.estimators:
            for _ in e.covariances(s, trace, kernel.steps, ("smoothed",)):
                pass
    ts = _best(smooth) - tf

    def both():
        sm._TLS.last = None
        st = {}
        for j, e in enumerate(kernel.estimators):
            for k, o in e.covariances(s, trace, kernel.steps, ("smoothed",)):
                kernel.reducer.update(st, j, k, o["smoothed"])
        getattr(kernel.reducer, "finish", lambda x: None)(st)
    tr = _best(both) - ts - tf
    return (f"trace {tt * ns:.1f} + forward {tf * ns:.1f} + backward & yields {ts * ns:.1f} + reduction {tr * ns:.1f} "
            f"ns per run-step")


_BACKENDS = ("numpy", "numba") if numba_available() else ("numpy",)
CASES = [{"estimator": f"smoother_lag{lag}", "system": name, "backend": be, "threads": None, "make": _Make(lag, name, be),
          "profile": profile} for lag in (0, 1, 3) for name in ("scalar", "3-state", "vehicle") for be in _BACKENDS]
CASES += [{"estimator": "smoother lags 0,1,2,4 time_average GE", "system": "scalar", "backend": be, "threads": None,
           "make": _MakeTA("scalar", be), "profile": profile} for be in _BACKENDS]
