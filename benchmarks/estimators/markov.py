"""Benchmark cases of the Moayedi, Soh & Foo Markov-mode filters for ``benchmarks/bench_estimators.py``.

``CASES``: dicts ``{"estimator": "markov_lmi" | "markov_lmmse" | "markov_mode_aware" | "markov_naive",
"system": ..., "backend": "numpy" | "numba", "threads": None | 1, "make": callable() -> (kernel, runs, horizon)}``
(``numba`` rows listed only when numba imports).
The kernel is the one ``netkf run`` builds for the artefacts' ``analysis.kind: state_error`` (the generic
state path :class:`netkf_cli.engine.state.StateErrorKernel`) with one ``markov_lmi`` estimator: it samples the mode
chain (``channel.sample_trace``), the plant and its noise (:func:`netkf_cli.engine.state.simulate`), runs the
filter's ``estimates`` and reduces squared errors, tr P and NEES per step (filtered, every step; window = the
second half). One run advanced one step is one run-step. Gains are designed once per process (closed form).
``backend: numba`` is what ``auto`` runs: the fixed-gain filters' per-run covariances (LMI, naive) and the
mode-aware KF with states (m = 1) in kernels generated per system (:mod:`netkf_cli.estimators._markov_codegen`;
D = d + r ≤ 10, so the 4-state system, D = 14, stays on numpy there); the LMMSE is numpy in both (one P for
every run; its r = 4d state update is a BLAS product). The NEES of n = 2 is compiled whenever numba imports
(also in the numpy rows). ``markov_mode_aware/engine`` (numba): the mode-aware KF's covariance-only path
(:class:`netkf_cli.engine.PairKernel` + ``TimeAverageReducer``, what ``time_average`` / ``mean_vs_time`` run).

Systems (mode chain of Example 2):
* scalar — A = 0.9, C = 1, Q = 1, R = 0.25 (augmented state ξ: d = 4);
* example2 — the paper's Example 2 (n = 2, d = 6);
* 4-state — a stable 4-state system with one output (d = 10).

What bounds them (numpy): the augmented state ξ = [x; x(k−1); y(k−1); v(k−1)] has d = 2n + 2m,
the exact LMMSE carries r = 4d states (24 for Example 2: 24² multiply-adds per run-step for the
filter alone), and the mode-aware KF propagates a d × d covariance per run (≈ 3d³ flops, memory
bound in numpy: ~20 passes over d²·8 bytes per run-step). The plant simulation (normal draws for
x(0), w, v) is shared by every case and is part of the measured cost.
"""

from __future__ import annotations

import numpy as np

from netkf_cli.channels.markov_modes import MarkovModesChannel
from netkf_cli.engine import PairKernel, TimeAverageReducer
from netkf_cli.estimators.markov_filters import numba_available
from netkf_cli.estimators.markov_lmi import MarkovLMIEstimator
from netkf_cli.engine.state import StateErrorKernel
from netkf_cli.core.system import LinearSystem

HORIZON = 100
RUNS = 5_000
CHAIN = [[0.7, 0.0, 0.1, 0.2], [0.7, 0.15, 0.05, 0.1], [0.7, 0.15, 0.05, 0.1], [0.7, 0.15, 0.05, 0.1]]


def systems() -> dict:
    """name → (A, C, Q, R)."""
    A4 = np.array([[0.9, 0.1, 0, 0], [0, 0.8, 0.2, 0], [0, 0, 0.7, 0.1], [0.1, 0, 0, 0.6]])
    return {
        "scalar": (0.9, 1.0, 1.0, 0.25),
        "example2": ([[0.8, 0], [0.9, 0.2]], [[1, 1]], [[0.36, 0.30], [0.30, 0.25]], 0.25),
        "4-state": (A4, [[1.0, 0, 0.5, 0]], 0.1 * np.eye(4), 0.25),
    }


FILTER = {"markov_lmi": "lmi", "markov_lmmse": "lmmse", "markov_mode_aware": "mode_aware", "markov_naive": "naive"}


class _Make:
    """Picklable ``make()``: the one-filter generic kernel (state level for numpy, covariance only for numba)."""

    def __init__(self, estimator: str, system: str, backend: str = "numpy", engine: bool = False):
        self.estimator, self.system, self.backend, self.engine = estimator, system, backend, engine

    def __call__(self):
        A, C, Q, R = systems()[self.system]
        n = np.atleast_2d(A).shape[0]
        sysm = LinearSystem.create(A, C, Q, R, P0=np.zeros((n, n)))
        ch = MarkovModesChannel(kind="markov_modes", transition=CHAIN, initial="stationary")
        est = MarkovLMIEstimator(kind="markov_lmi", filter=FILTER[self.estimator], design="closed_form", sdp_check=0,
                                 backend=self.backend)
        steps = list(range(1, HORIZON + 1))
        if self.backend == "numba" and self.engine:
            window = steps[HORIZON // 2:]
            kernel = PairKernel(sysm, ch, [est], HORIZON, window, TimeAverageReducer(window))
        else:
            kernel = StateErrorKernel(sysm, ch, [est], HORIZON, steps, [(0, "filtered")], window=steps[HORIZON // 2:])
        return kernel, RUNS, HORIZON


BOUND = {
    "markov_lmi": "state-level simulation: normal draws for w, v and the augmented plant state per run-step",
    "markov_naive": "state-level simulation: normal draws for w, v and the augmented plant state per run-step",
    "markov_lmmse": "flops: the LMMSE state has r = 4d entries, r² multiply-adds per run-step (576 for n = 2)",
    "markov_mode_aware": "memory: a d×d covariance per run (d = 2n + 2m), ~20 numpy passes of 8d² bytes per run-step",
}
CASES = [{"estimator": est, "system": name, "backend": "numpy", "threads": None, "make": _Make(est, name),
          "bound": BOUND[est]}
         for est in FILTER for name in ("scalar", "example2", "4-state")]
COMPILED_BOUND = {
    "markov_lmi": "the shared state-level work (normal draws for x, w, v; the per-step reduction in numpy passes)",
    "markov_naive": "the shared state-level work (normal draws for x, w, v; the per-step reduction in numpy passes)",
    "markov_mode_aware": "the shared state-level work (normal draws for x, w, v; the per-step reduction in numpy passes)",
}
if numba_available():  # what `auto` runs at state level; and the mode-aware KF's covariance-only engine path
    CASES += [{"estimator": est, "system": name, "backend": "numba", "threads": 1,
               "make": _Make(est, name, "numba"), "bound": COMPILED_BOUND[est]}
              for est in ("markov_lmi", "markov_naive", "markov_mode_aware") for name in ("scalar", "example2")]
    CASES += [{"estimator": "markov_mode_aware", "system": name, "backend": "numba", "threads": 1, "path": "engine",
               "make": _Make("markov_mode_aware", name, "numba", engine=True),
               "bound": "flops: ≈ 3d³ per run-step in the compiled Riccati step (covariance only: no plant simulation)"}
              for name in ("scalar", "example2", "4-state")]
