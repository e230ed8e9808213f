"""Issue 20.3: the smoother's working set per chunk is bounded, whatever the horizon.

The engine's smoothers of Table I (lags 0, 1, 2, 4 on one trace, common random numbers) on one chunk of
4000 runs: the Python-heap peak (tracemalloc; numpy's buffers are traced) of the estimators' pass and the
reducer, after the trace is sampled. The shared pass used to hold the whole horizon five times over (P_{t|t},
J_t, C_t and two smoothed chains, (steps, n, n, runs) each): measured here 81 MB at 300 steps and 210 MB at
1200 (145 MB per 5000-run chunk of configs/smoothing/table1.yaml). Blocks of steps bound it by
``smoother.BLOCK_BYTES`` (8 MB, plus the numpy backward pass's temporaries at 300 steps, where the batch is
below the compiled RTS threshold) and the forward pass kept for the next estimator when it fits
``smoother.FORWARD_BYTES`` (24 MB): measured 31 MB at 300 steps, 12.5 MB at 1200. The bound (48 MB) is 1.5×
that and far below the old values; the peak does not grow with the horizon (the 1200-step peak is at most the
300-step one plus 4 MB; the old pass failed both). No timing.
"""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from netkf_cli import engine
from netkf_cli.channels.bernoulli import BernoulliChannel
from netkf_cli.core.system import LinearSystem
from netkf_cli.estimators import smoother as sm
from netkf_cli.estimators.smoother import SmootherEstimator

RUNS = 4000
BOUND_MB = 48.0


def _peak_mb(horizon: int, blocks: bool = False) -> tuple[float, dict]:
    s = LinearSystem.create(1.3, 1, 0.5, 1, None)  # Table I's system
    ch = BernoulliChannel(kind="bernoulli", arrival=0.45)
    ests = [SmootherEstimator(kind="smoother", lag=lag) for lag in (0, 1, 2, 4)]
    steps = list(range(61, horizon + 1))
    red = engine.StationaryReducer(steps, np.array([6.25]))
    trace = ch.sample_trace(np.random.default_rng(7), RUNS, horizon)
    for attr in ("last", "forward", "flagged"):  # nothing kept from another test
        setattr(sm._TLS, attr, None)
    stats: dict = {}
    tracemalloc.start()
    try:
        for j, est in enumerate(ests):
            if blocks:  # the engine's way for a time average: a block of steps per call
                for ks, out in est.covariance_blocks(s, trace, steps, ("smoothed",)):
                    red.update_block(stats, j, ks, out["smoothed"])
                continue
            for k, P, w in engine.covariances(est, s, trace, steps, "smoothed"):
                red.update(stats, j, k, P, w)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    red.finish(stats)
    return peak / 2**20, stats


@pytest.mark.skipif(not sm.numba_available(), reason="numba not installed (the configs' compiled path)")
@pytest.mark.parametrize("blocks", [False, True])
def test_smoother_chunk_working_set_is_bounded_and_flat_in_the_horizon(blocks):
    for h in (300, 1200):  # warm-up: numba's import and the kernels' loading allocate on the traced heap once
        _peak_mb(h, blocks)
    short, st_short = _peak_mb(300, blocks)
    long, st_long = _peak_mb(1200, blocks)
    assert short < BOUND_MB, f"{short:.1f} MB at 300 steps"
    assert long < BOUND_MB, f"{long:.1f} MB at 1200 steps (the whole-horizon pass held 210 MB)"
    assert long <= short + 4.0, f"grows with the horizon: {short:.1f} → {long:.1f} MB"
    # the statistics are there (the pass ran): every run counted in each column's time average
    for st in (st_short, st_long):
        for j in range(4):
            assert np.isfinite(st[f"sum_avg_{j}"]).all()
