"""Benchmark cases of the Leong, Dey & Evans fixed-lag smoother for ``benchmarks/bench_estimators.py``.

``CASES``: dicts ``{"estimator": "smoother_lag0" | "smoother_lag1" | "smoother_lag3", "system": "scalar" |
"3-state" | "vehicle", "backend": "numpy" | "numba", "threads": None, "make": callable() -> (kernel, runs,
horizon)}``.

The kernel is the one ``netkf run`` builds for a ``distribution`` analysis of the smoothed covariance at the
last step (the generic engine: :class:`netkf_cli.engine.PairKernel` → ``SmootherEstimator.covariances`` →
:class:`netkf_cli.engine.DistributionReducer`): per chunk it samples a Bernoulli(0.8) arrival trace of
``horizon`` steps, runs the filter over it and the lag-N smoother block for P_{H−N|H} (quantity ``smoothed``
at step H), and counts P ≤ M (PSD order) and non-finite runs. A run-step is one step of the trace. Only the
requested step is smoothed (one block for the last N steps), so lags cost little more than the filter;
``SmootherEstimator.covariances`` with every step requested runs N blocks per step.

The numpy and numba backends work on the same uniforms: bitwise-equal statistics for the scalar
system, equal to round-off for vector systems (tests/smoothing/test_contract.py). Systems as in
``shi2009.py`` (scalar A = 1.4; the 3-state system of Shi 2009 Fig. 8; the 4-state vehicle).
"""

from __future__ import annotations

import numpy as np

from netkf_cli.channels.bernoulli import BernoulliChannel
from netkf_cli.engine import DistributionReducer, PairKernel
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


_BACKENDS = ("numpy", "numba") if numba_available() else ("numpy",)
CASES = [{"estimator": f"smoother_lag{lag}", "system": name, "backend": be, "threads": None, "make": _Make(lag, name, be)}
         for lag in (0, 1, 3) for name in ("scalar", "3-state", "vehicle") for be in _BACKENDS]

# What bounds a case that misses its target (profiled by the smoothing helper):
_BOUND = {
    "numpy": "per-run 4×4 products as numpy entry passes and eigvalsh in the PSD test (memory traffic)",
    "numba": "generic-n compiled loops (no per-system code generation as in buffered_numba) and eigvalsh in the PSD test",
}
for _c in CASES:
    _c["bound"] = _BOUND[_c["backend"]]
