"""Benchmark cases of the Chiuso & Schenato fusion strategies for ``benchmarks/bench_estimators.py``.

``CASES``: dicts ``{"estimator": "fusion_MF" | "fusion_IBF" | "fusion_OLPEF", "system": ..., "backend":
"numpy", "threads": None, "make": callable() -> (kernel, runs, horizon)}``. The kernel is the one
the artefacts use (:class:`netkf_cli.estimators.fusion.FusionKernel`, one strategy): it samples the
N-sensor arrival trace and returns per-run time averages of tr P_{t|t} over the second half of the
horizon. One run advanced one step (all N sensors fused) is one run-step.

Systems (N sensors with independent Bernoulli links, loss 0.5):
* scalar — the paper's Fig. 3 system (A = 0.9, C = 1, Q = 1e-4, R = 1e-2), N = 25;
* 3-state — a stable 3-state system with one output per sensor, N = 10;
* 4-state — a damped version of the Shi 2009 vehicle (A scaled to spectral radius 0.95), two
  outputs per sensor, N = 10.

No compiled backend: the numpy MF on the scalar system runs ~1e7–3e7 run-steps/s (the
recursion is a few vector ops per step; the N-sensor arrival sampling costs as much); IBF and
OLPEF are bounded by their per-(time, run) history (O(max τ) Riccati steps, and a τ-histogram
quadratic form), see the printed numbers.
"""

from __future__ import annotations

import numpy as np

from netkf_cli.channels.multi import MultiChannel
from netkf_cli.estimators.fusion import FusionKernel
from netkf_cli.system import LinearSystem

HORIZON = 100
RUNS = 5_000


def systems() -> dict:
    """name → (system, N)."""
    scalar = LinearSystem.create(0.9, 1.0, 1e-4, 1e-2)
    A3 = np.array([[0.8, 0.2, 0.0], [0.0, 0.7, 0.3], [0.1, 0.0, 0.6]])
    three = LinearSystem.create(A3, np.array([[1.0, 0.5, 0.2]]), 0.01 * np.eye(3), 0.1)
    Av = 0.95 * np.array([[1, 0, 0.5, 0], [0, 1, 0, 0.5], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    vehicle = LinearSystem.create(Av, np.hstack([np.eye(2), np.zeros((2, 2))]), 0.01 * np.eye(4), 0.01 * np.eye(2))
    return {"scalar": (scalar, 25), "3-state": (three, 10), "4-state": (vehicle, 10)}


class _Make:
    """Picklable ``make()``."""

    def __init__(self, strategy: str, system: str):
        self.strategy, self.system = strategy, system

    def __call__(self):
        s, N = systems()[self.system]
        ch = MultiChannel(kind="multi", sensors=N, loss=0.5)
        kernel = FusionKernel(s.A, s.C, s.Q, s.R, None, ch, [self.strategy], HORIZON, HORIZON // 2)
        return kernel, RUNS, HORIZON


BOUND = {
    "mf": "RNG: N raw 64-bit draws per run-step for the per-sensor trace (the MF recursion alone runs ≈ 2e7)",
    "ibf": "work: the Riccati recursion is re-run over the last max τ steps at every evaluation time (O(T·max τ))",
    "olpef": "work: a τ-histogram quadratic form per (time, run), O((max τ)²), plus the per-sensor RNG",
}
CASES = [{"estimator": f"fusion_{strat.upper()}", "system": name, "backend": "numpy", "threads": None,
          "make": _Make(strat, name), "bound": BOUND[strat]}
         for strat in ("mf", "ibf", "olpef") for name in ("scalar", "3-state", "4-state")]
