"""Benchmark cases of the Moayedi, Soh & Foo Markov-mode filters for ``benchmarks/bench_estimators.py``.

``CASES``: dicts ``{"estimator": "markov_lmi" | "markov_lmmse" | "markov_mode_aware" | "markov_naive",
"system": ..., "backend": "numpy" | "numba", "threads": None | 1, "make": callable() -> (kernel, runs, horizon)}``
(``numba``: the compiled mode-aware KF step, listed only when numba imports).
The kernel is the artefacts' state-level Monte Carlo
(:class:`netkf_cli.estimators.markov_filters.MarkovMSEKernel`) restricted to one filter: it samples
the mode chain, the plant and its noise, runs the filter and returns squared-error statistics.
One run advanced one step is one run-step. Gains are designed once in ``make()`` (closed form).

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
from netkf_cli.estimators.markov_filters import (
    AugmentedModel,
    MarkovMSEKernel,
    lmmse_filter,
    naive_filter,
    numba_available,
)
from netkf_cli.estimators.markov_lmi import lmi_design

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


FILTER = {"markov_lmi": "lmi", "markov_lmmse": "lmmse", "markov_mode_aware": "mode_aware_kf", "markov_naive": "naive_kf"}


class _Make:
    """Picklable ``make()``: designs the filter and returns the one-filter state-level kernel."""

    def __init__(self, estimator: str, system: str, backend: str = "numpy"):
        self.estimator, self.system, self.backend = estimator, system, backend

    def __call__(self):
        A, C, Q, R = systems()[self.system]
        md = AugmentedModel.build(A, C, Q, R)
        ch = MarkovModesChannel(kind="markov_modes", transition=CHAIN)
        n, K = md.n, HORIZON
        x0, P0 = np.zeros(n), np.zeros((n, n))
        f = FILTER[self.estimator]
        linear = {}
        if f == "lmmse":
            linear["lmmse"] = lmmse_filter(md, ch.T, ch.pi0, x0, P0, K)
        elif f == "lmi":
            linear["lmi"] = lmi_design(md, ch.rho, x0, P0, K, design="closed_form").filter
        elif f == "naive_kf":
            linear["naive_kf"] = naive_filter(md, x0, P0, K)
        kernel = MarkovMSEKernel(md, ch, linear, x0, P0, K, K // 2, filters=(f,), backend=self.backend)
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
if numba_available():  # the compiled mode-aware KF (per-run step, m = 1), one thread per chunk
    CASES += [{"estimator": "markov_mode_aware", "system": name, "backend": "numba", "threads": 1,
               "make": _Make("markov_mode_aware", name, "numba"),
               "bound": "flops: ≈ 3d³ per run-step in the compiled Riccati step, plus the shared numpy plant simulation"}
              for name in ("scalar", "example2", "4-state")]
