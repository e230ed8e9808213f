"""The smoother's shared pass (issue 20): kf's forward pass once per trace, the RTS pieces J_t, C_t once per
trace step, the backward maps batched over the steps, the generated compiled kernels — the same numbers as
the per-step reference :func:`smoother._run_core` (numpy: bit for bit; compiled: to rounding, bit for bit
for a scalar system), and smoothers that differ only in lag sharing one pass with exactly the numbers of
separate passes."""

from __future__ import annotations

import numpy as np
import pytest

from netkf_cli import engine
from netkf_cli.linalg import kalman
from netkf_cli.linalg import kalman_codegen as kc
from netkf_cli.channels.gilbert_elliott import GilbertElliottChannel
from netkf_cli.estimators import smoother as sm
from netkf_cli.estimators.smoother import SmootherEstimator
from netkf_cli.core.system import LinearSystem

numba_missing = not sm.numba_available()
QS = ("filtered", "predicted", "smoothed")

SYSTEMS = {
    "scalar": LinearSystem.create(1.3, 1, 0.5, 1, None),  # the configs' system
    "2-state": LinearSystem.create([[1.2, 0.4], [0.0, 0.8]], [[1.0, 0.5]], np.eye(2) * 0.3, [[0.5]], None),
    "3-state": LinearSystem.create([[1.1, 0.3, 0.0], [0.0, 0.9, 0.2], [0.1, 0.0, 1.05]], [[1.0, 0.0, 0.0], [0.0, 1.0, 1.0]],
                                   np.diag([0.3, 0.2, 0.4]) + 0.05, np.diag([0.5, 0.8]), None),
    "huge": LinearSystem.create(np.diag([1e6, 0.5]), np.eye(2), np.eye(2) * 0.3, np.eye(2) * 0.5, None),  # the rescues
}


def _bursty(runs, horizon, seed, burst=8.0):
    """Gilbert–Elliott arrivals with long bursts: the forward pass's rescue flags runs at many steps."""
    ch = GilbertElliottChannel(kind="gilbert_elliott", loss_rate=0.45, mean_burst=burst)
    return ch.sample_trace(np.random.default_rng(seed), runs, horizon).arrival


def _equal(a, b, steps, exact, rtol=1e-11):
    """Bit for bit, or to rounding: relative ``rtol``, and absolute 64 ε × the largest finite filtered P_{t|t}
    entry of the pass — the RTS step's covariance form subtracts terms of that size (after a long burst,
    P_{t|t} ~ 2e7 at the 3-state system: absolute differences ~ε·2e7 = 4e-9 in a smoothed entry of order 1,
    measured; the rescue takes over above 1e8 × its scale)."""
    big = max(float(np.abs(np.where(np.isfinite(a[k]["filtered"]), a[k]["filtered"], 0)).max()) for k in steps)
    for k in steps:
        for q in a[k]:
            x, y = a[k][q], b[k][q]
            if exact:
                assert np.array_equal(x, y, equal_nan=True), (k, q)
            else:
                np.testing.assert_allclose(y, x, rtol=rtol, atol=64 * np.finfo(float).eps * big, err_msg=f"{k} {q}")


@pytest.mark.parametrize("name", list(SYSTEMS))
def test_numpy_shared_pass_is_the_per_step_reference_bit_for_bit(name):
    s = SYSTEMS[name]
    g = _bursty(120, 48, 1)
    f = kalman.Filter.of(s, 1)
    steps = [0, 1, 2, 3, 9, 10, 11, 30, 47, 48]
    for lag in (0, 1, 3):
        sm._TLS.last = None
        a = dict(sm._run_core(f, s, g, steps, QS, lag, "numpy"))
        b = dict(sm._run_shared(f, s, g, steps, QS, lag, "numpy", "numpy"))
        _equal(a, b, steps, exact=True)


def test_rts_pieces_compose_to_the_core_smooth_step():
    rng = np.random.default_rng(3)
    for n in (1, 2, 3):
        A, L1, L2, L3 = (rng.normal(size=(n, n)) for _ in range(4))
        Q = L1 @ L1.T + 0.1 * np.eye(n)
        Pf = np.moveaxis(np.stack([L2 @ L2.T * 10.0 ** e + 0.1 * np.eye(n) for e in (0, 3, 9)]), 0, -1)  # 1e9: rescued
        Ps = np.repeat((L3 @ L3.T)[:, :, None], 3, axis=2)
        back = kalman.SmoothStep.of(A, Q)
        assert np.array_equal(sm._rts_apply_numpy(*sm._rts_prepare_numpy(back, Pf), Ps), back(Ps, Pf))


def test_blocks_give_the_numbers_of_one_block(monkeypatch):
    s = SYSTEMS["2-state"]
    g = _bursty(50, 40, 2)
    f = kalman.Filter.of(s, 1)
    steps = list(range(1, 41))
    one = dict(sm._run_shared(f, s, g, steps, QS, 3, "numpy", "numpy"))
    monkeypatch.setattr(sm, "BLOCK_BYTES", 4 * 4 * 50 * 8 * 9)  # blocks of 9 rows
    assert len(sm._blocks(steps, 4, 4 * 4 * 50 * 8)) > 3
    sm._TLS.last = None
    _equal(one, dict(sm._run_shared(f, s, g, steps, QS, 3, "numpy", "numpy")), steps, exact=True)


@pytest.mark.parametrize("backend", ["numpy"] + ([] if numba_missing else ["numba"]))
def test_lags_on_one_trace_share_one_pass_with_the_numbers_of_separate_passes(backend, monkeypatch):
    """The engine's way (every estimator on the same trace, one after another): lags 0, 1, 2, 4 share one
    forward pass and the chain; the statistics are those of separate passes (nothing kept), exactly."""
    s = SYSTEMS["scalar"]
    ch = GilbertElliottChannel(kind="gilbert_elliott", loss_rate=0.4, mean_burst=4)
    ests = [SmootherEstimator(kind="smoother", lag=lag, backend=backend) for lag in (0, 1, 2, 4)]
    steps = list(range(11, 81))
    calls = []
    run, fwd = kalman.Filter.run, sm._forward_stream
    monkeypatch.setattr(kalman.Filter, "run", lambda *a, **k: (calls.append(1), run(*a, **k))[1])
    monkeypatch.setattr(sm, "_forward_stream", lambda *a: (calls.append(1), fwd(*a))[1])
    monkeypatch.setattr(sm, "AUTO_NUMBA_MAX_RUNS", 0)  # the batched path even for this small batch

    def sim(es):
        return engine.simulate(s, ch, es, engine.StationaryReducer(steps, np.array([2.0, 6.25])), steps=steps,
                               runs=300, horizon=80, seed=4, chunk=300, quantity="smoothed")

    sm._TLS.last = None
    shared = sim(ests)
    assert len(calls) == 1  # one forward pass for the four smoothers
    monkeypatch.setattr(sm, "_keep", lambda *a: None)  # nothing kept: every smoother its own pass
    for j, e in enumerate(ests):
        alone = sim([e])
        for key, val in alone.items():
            if key.endswith("_0"):
                np.testing.assert_array_equal(shared[key[:-1] + str(j)], val, err_msg=f"{j} {key}")
    assert len(calls) == 1 + len(ests)


@pytest.mark.skipif(numba_missing, reason="numba not installed")
@pytest.mark.parametrize("name", list(SYSTEMS))
def test_compiled_backward_pass_equals_numpy(name):
    """The generated prepare/chain kernels on kf's compiled forward pass against the numpy reference on the
    same trace, every lag and quantity: to rounding (the scalar system: bit for bit)."""
    s = SYSTEMS[name]
    g = _bursty(200, 60, 5)
    f = kalman.Filter.of(s, 1)
    steps = [1, 2, 5, 17, 30, 31, 59, 60]
    for lag in (0, 1, 4):
        sm._TLS.last = None
        a = dict(sm._run_core(f, s, g, steps, QS, lag, "numba"))
        b = dict(sm._run_shared(f, s, g, steps, QS, lag, "numba", "compiled"))
        _equal(a, b, steps, exact=False, rtol=1e-9 if name == "huge" else 1e-11)
        if name == "scalar":
            _equal(dict(sm._run_core(f, s, g, steps, QS, lag, "numpy")), b, steps, exact=True)


@pytest.mark.skipif(numba_missing, reason="numba not installed")
@pytest.mark.parametrize("name", ["scalar", "2-state", "huge"])
def test_compiled_run_reports_flagged_runs_from_the_numpy_core(name):
    """Filter.run(backend numba) on the generated kernel (kalman.Filter.stream_generated), on bursty loss where
    runs are flagged at many different steps: at step k a run the kernel has flagged by k carries the numpy
    core's P_{k|k} bit for bit (from its own P0), every other run the kernel's own state bit for bit; and the
    same numbers as the one-pass FlaggedRuns algorithm (restart from P0 when flagged) that it replaced, and as
    the smoother's _forward_compiled (one shared first-flagged pass)."""
    s = SYSTEMS[name]
    g = _bursty(300, 120, 6, burst=12.0)
    f = kalman.Filter.of(s, 1)
    P0 = sm.initial_covariance(s)
    runs = g.shape[-1]
    Pr = np.array(np.repeat(P0[:, :, None], runs, axis=2), order="C")
    adv = f.generated_kernel()
    for want in (list(range(1, 121)), [3, 40, 41, 42, 120]):
        a = dict(f.run(P0, g, want, ("filtered",), backend="numba"))
        ref = dict(f.run(P0, g, want, ("filtered",), backend="numpy"))
        b = sm._forward_compiled(f, P0, g, want)
        T, flag, t = kc.pack(Pr), np.zeros(runs, dtype=np.bool_), 0
        redo = kalman.FlaggedRuns(Pr.copy(), lambda Pk, tt, ix: f.step(Pk, g[:, tt][:, ix])[1])
        seen = 0
        for k in want:
            adv(T, np.ascontiguousarray(g), t, k, flag)
            t = k
            own = kc.unpack(T, s.n)
            got = a[k]["filtered"]
            assert np.array_equal(got[:, :, flag], ref[k]["filtered"][:, :, flag], equal_nan=True), k
            assert np.array_equal(got[:, :, ~flag], own[:, :, ~flag], equal_nan=True), k
            assert np.array_equal(got, redo.fill(own.copy(), flag, k), equal_nan=True), k
            assert np.array_equal(got, b[k]["filtered"], equal_nan=True), k
            seen = max(seen, len(np.unique(kalman.first_flagged(adv, Pr, np.ascontiguousarray(g), k))))
        if name != "huge" and len(want) > 100:
            assert seen > 10  # flagged at many different steps: the case the two passes are for (huge: all at step 1)


@pytest.mark.skipif(numba_missing, reason="numba not installed")
@pytest.mark.parametrize("name", list(SYSTEMS))
def test_compiled_rts_on_the_numpy_forward_pass(name):
    """``auto`` with kf's numpy forward pass and a large batch (AUTO_MIN_RTS_RUN_STEPS): the generated
    kernels give the numpy pass's numbers bit for bit for n ≤ 2 (closed-form S⁻¹, the core's order of
    operations), to rounding for n ≥ 3 (Cholesky)."""
    s = SYSTEMS[name]
    g = _bursty(150, 50, 7)
    f = kalman.Filter.of(s, 1)
    steps = list(range(1, 51))
    for lag in (1, 4):
        sm._TLS.last = None
        a = dict(sm._run_shared(f, s, g, steps, QS, lag, "numpy", "numpy"))
        sm._TLS.last = None
        b = dict(sm._run_shared(f, s, g, steps, QS, lag, "numpy", "compiled"))
        _equal(a, b, steps, exact=s.n <= 2)


@pytest.mark.parametrize("backend", ["numpy", "auto"] + ([] if numba_missing else ["numba"]))
@pytest.mark.parametrize("split", [False, True])
def test_blocks_are_the_per_step_covariances(backend, split, monkeypatch):
    """run_blocks (the engine's covariance_blocks: one array per block of steps) yields, stacked, exactly the
    arrays run yields step by step: every quantity and lag (k < N: NaN), one block (kept for the next lag) or
    many, and the per-run kernel's path (few runs) step by step."""
    s = SYSTEMS["2-state"]
    g = _bursty(300, 60, 8)
    steps = [1, 2, 3, 7, 8, 9, 10, 11, 30, 31, 32, 59, 60]
    if split:
        monkeypatch.setattr(sm, "BLOCK_BYTES", 4 * 4 * 300 * 8 * 9)  # blocks of 9 rows
    for runs in (300, 100):  # 100 ≤ AUTO_NUMBA_MAX_RUNS: auto / numba take the per-run kernel
        gr = np.ascontiguousarray(g[..., :runs])
        for lag in (0, 1, 3, 4):
            sm._TLS.last = sm._TLS.forward = None
            ref = dict(sm.run(s, gr, steps, QS, lag, backend=backend))
            got, seen = {}, []
            for ks, out in sm.run_blocks(s, gr, steps, QS, lag, backend=backend):
                seen.append(ks)
                for i, k in enumerate(ks):
                    got[k] = {q: out[q][i] for q in out}
            assert [k for ks in seen for k in ks] == steps
            if split and runs == 300 and backend != "numba":
                assert len(seen) > 2
            _equal(ref, got, steps, exact=True)


@pytest.mark.parametrize("backend", ["numpy"] + ([] if numba_missing else ["numba"]))
def test_kept_forward_pass_gives_the_streamed_numbers(backend, monkeypatch):
    """Blocks of steps over the forward pass kept whole (_forward_kept: a block's rows sliced from it, shared by
    the lags) and over the forward pass streamed block by block (it does not fit FORWARD_BYTES): the same
    numbers, steps from 1 (row 0 is P0) and with gaps; the kept pass is reused by the next lag."""
    s = SYSTEMS["2-state"]
    g = _bursty(300, 70, 9)
    f = kalman.Filter.of(s, 1)
    monkeypatch.setattr(sm, "BLOCK_BYTES", 4 * 4 * 300 * 8 * 9)  # blocks of 9 rows
    fwd = "numba" if backend == "numba" else "numpy"
    rts = "compiled" if backend == "numba" else "numpy"
    for steps in (list(range(1, 71)), [2, 3, 4, 20, 21, 40, 41, 42, 43, 69, 70]):
        kept, streamed = {}, {}
        sm._TLS.last = sm._TLS.forward = None
        for lag in (0, 1, 3, 4):
            kept[lag] = dict(sm._run_shared(f, s, g, steps, QS, lag, fwd, rts))
            assert sm._TLS.forward is not None and sm._TLS.forward[3].shape[0] == len(sm._window(steps, 4, 1))
        monkeypatch.setattr(sm, "FORWARD_BYTES", 0)
        for lag in (0, 1, 3, 4):
            sm._TLS.last = sm._TLS.forward = None
            streamed[lag] = dict(sm._run_shared(f, s, g, steps, QS, lag, fwd, rts))
            assert sm._TLS.forward is None
            _equal(kept[lag], streamed[lag], steps, exact=True)
        monkeypatch.undo()
        monkeypatch.setattr(sm, "BLOCK_BYTES", 4 * 4 * 300 * 8 * 9)


@pytest.mark.parametrize("M", [None, (2.0, 6.25)])
def test_engine_blocks_give_the_statistics_of_the_per_step_path(M, monkeypatch):
    """The engine's block path (SmootherEstimator.covariance_blocks → StationaryReducer.update_block) against
    its per-step path (covariances → update) on the same traces: the same statistics, bit for bit."""
    s = SYSTEMS["2-state"]
    ch = GilbertElliottChannel(kind="gilbert_elliott", loss_rate=0.4, mean_burst=6)
    ests = [SmootherEstimator(kind="smoother", lag=lag) for lag in (0, 2, 3)]
    steps = list(range(21, 81))
    monkeypatch.setattr(engine, "REDUCE_MIN_RUNS", 100)  # the compiled reductions for this small batch
    monkeypatch.setattr(sm, "BLOCK_BYTES", 4 * 4 * 600 * 8 * 13)  # several blocks

    def sim():
        sm._TLS.last = sm._TLS.forward = None
        return engine.simulate(s, ch, ests, engine.StationaryReducer(steps, None if M is None else np.array(M)),
                               steps=steps, runs=600, horizon=80, seed=5, chunk=600, quantity=("filtered", "smoothed"))

    blocks = sim()
    monkeypatch.delattr(SmootherEstimator, "covariance_blocks")
    steps_ = sim()
    assert set(blocks) == set(steps_)
    for key in blocks:
        assert np.array_equal(np.asarray(blocks[key]), np.asarray(steps_[key]), equal_nan=True), key
