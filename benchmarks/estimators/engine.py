"""Benchmark cases of the generic engine's intermittent KF (``kind: kf``) for bench_estimators.py.

The generic kernel (:class:`netkf_cli.engine.PairKernel`): Bernoulli arrivals → batched KF in
the (n, n, runs) layout → counts of P_k ≤ M. Systems as in ``shi2009.py``.
"""

from __future__ import annotations

import numpy as np

from netkf_cli.channels.bernoulli import BernoulliChannel
from netkf_cli.engine import DistributionReducer, PairKernel
from netkf_cli.estimators.kf import KalmanFilterEstimator

from benchmarks.estimators.shi2009 import systems

HORIZON = 100
RUNS = 20_000


class _Make:
    def __init__(self, system: str, backend: str = "numpy"):
        self.system, self.backend = system, backend

    def __call__(self):
        s, _, _, M = systems()[self.system]
        ch = BernoulliChannel(kind="bernoulli", arrival=0.8)
        kernel = PairKernel(s, ch, [KalmanFilterEstimator(kind="kf", backend=self.backend)], HORIZON, [HORIZON],
                            DistributionReducer(np.asarray(M), [HORIZON]))
        return kernel, RUNS, HORIZON


CASES = [{"estimator": "kf", "system": name, "backend": be, "threads": None, "make": _Make(name, be),
          "bound": "per-run n×n products in Python-level entry loops (numpy) / generic-n loops (numba)"}
         for be in ("numpy", "numba") for name in ("scalar", "3-state", "vehicle")]
