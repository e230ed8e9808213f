"""The engine's block path for kf (KalmanFilterEstimator.covariance_blocks → StationaryReducer.update_block): the
arrays of covariances() step by step, stacked — ``predicted`` of a whole block in one call of the core's predict —
and the statistics of the per-step path, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from netkf_cli import engine
from netkf_cli.channels.bernoulli import BernoulliChannel
from netkf_cli.channels.gilbert_elliott import GilbertElliottChannel
from netkf_cli.core.system import LinearSystem
from netkf_cli.estimators import kf as kf_mod
from netkf_cli.estimators.kf import KalmanFilterEstimator

SYSTEMS = {
    "scalar": LinearSystem.create(1.3, 1.0, 0.5, 1.0),
    "2-state": LinearSystem.create([[1.2, 0.4], [0.0, 0.8]], [[1.0, 0.5]], np.eye(2) * 0.3, [[0.5]]),
    "vehicle": LinearSystem.create(np.array([[1, 0, 0.5, 0], [0, 1, 0, 0.5], [0, 0, 1, 0], [0, 0, 0, 1.0]]),
                                   np.hstack([np.eye(2), np.zeros((2, 2))]), 0.01 * np.eye(4), 0.001 * np.eye(2)),
    "rescue": LinearSystem.create(np.diag([1e3, 0.5]), np.eye(2), np.eye(2), np.eye(2)),  # runs on the numpy core
    "9-state": LinearSystem.create(0.9 * np.eye(9) + 0.05 * np.eye(9, k=1), np.eye(9)[:3], 0.1 * np.eye(9), np.eye(3)),
}


@pytest.mark.parametrize("name", list(SYSTEMS))
@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_kf_blocks_are_the_per_step_covariances(name, backend, monkeypatch):
    pytest.importorskip("numba") if backend == "numba" else None
    s = SYSTEMS[name]
    ch = GilbertElliottChannel(kind="gilbert_elliott", loss_rate=0.4, mean_burst=5.0)
    trace = ch.sample_trace(np.random.default_rng(1), 300, 60)
    est = KalmanFilterEstimator(kind="kf", backend=backend)
    steps = [1, 2, 3, 10, 11, 12, 13, 40, 59, 60]
    monkeypatch.setattr(kf_mod, "BLOCK_BYTES", s.n * s.n * 300 * 8 * 3)  # blocks of 3 steps
    for qs in (("filtered",), ("predicted",), ("filtered", "predicted")):
        ref = dict(est.covariances(s, trace, steps, qs))
        got = {}
        for ks, out in est.covariance_blocks(s, trace, steps, qs):
            assert 1 <= len(ks) <= 3 and set(out) == set(qs)
            for i, k in enumerate(ks):
                got[k] = {q: out[q][i] for q in qs}
        assert sorted(got) == steps
        for k in steps:
            for q in qs:
                assert np.array_equal(ref[k][q], got[k][q], equal_nan=True), (k, q)


@pytest.mark.parametrize("M", [None, (2.0, 6.25)])
def test_kf_engine_blocks_give_the_statistics_of_the_per_step_path(M, monkeypatch):
    s = SYSTEMS["scalar"]
    ch = BernoulliChannel(kind="bernoulli", arrival=0.45)
    steps = list(range(21, 81))
    monkeypatch.setattr(engine, "REDUCE_MIN_RUNS", 100)  # the compiled reductions for this small batch
    monkeypatch.setattr(kf_mod, "BLOCK_BYTES", 600 * 8 * 7)

    def sim():
        return engine.simulate(s, ch, [KalmanFilterEstimator(kind="kf", backend="numba")],
                               engine.StationaryReducer(steps, None if M is None else np.array(M)), steps=steps,
                               runs=600, horizon=80, seed=3, chunk=600, quantity=("predicted",))

    blocks = sim()
    monkeypatch.delattr(KalmanFilterEstimator, "covariance_blocks")
    per_step = sim()
    assert set(blocks) == set(per_step)
    for key in blocks:
        assert np.array_equal(np.asarray(blocks[key]), np.asarray(per_step[key]), equal_nan=True), key
