"""The compiled reductions and the fused kf kernel (issue 20) against the numpy references.

λ_max (netkf_cli.linalg._reduce_numba) equals eigvalsh to 1e-12 relative, the generated PSD-order decisions
(netkf_cli.linalg.reduce_codegen) equal the numpy reducers' exactly (including thresholds within rounding of
λ_max, near-degenerate and non-finite P), every reducer's compiled update equals its numpy update (counts
exactly, sums to rounding), and the fused kf kernel (uniforms → arrivals → generated filter → reduction)
equals the numpy path: the same uniforms give the same trace, counts are equal, sums agree to rounding.
"""

from __future__ import annotations

import numpy as np
import pytest

from netkf_cli.linalg import batched, kalman
from netkf_cli import engine
from netkf_cli.linalg import kalman_codegen as kc
from netkf_cli.channels.bernoulli import BernoulliChannel
from netkf_cli.channels.gilbert_elliott import GilbertElliottChannel
from netkf_cli.estimators.kf import KalmanFilterEstimator
from netkf_cli.core.system import LinearSystem

numba = pytest.importorskip("numba")
from netkf_cli.linalg import _reduce_numba as rn  # noqa: E402  (needs numba)
from netkf_cli.linalg import reduce_codegen as rc  # noqa: E402


def _batch(n: int, runs: int, seed: int = 0) -> np.ndarray:
    """(n, n, runs): Wishart, near-degenerate (λ_max double or triple up to 1e-13), rank-deficient, scaled
    over 1e-8 … 1e8, an exactly scalar matrix, zero and two non-finite runs."""
    rng = np.random.default_rng(seed)
    G = rng.standard_normal((runs, n, n))
    P = np.einsum("rij,rkj->rik", G, G)
    k = runs // 4
    Qm, _ = np.linalg.qr(rng.standard_normal((k, n, n)))
    lam = np.ones((k, n)) * 3.0
    lam[:, -1] = rng.uniform(0.0, 1.0, k)  # λ_max of multiplicity n − 1 (n ≥ 3) or n (n ≤ 2 after the next line)
    lam[:, :-1] += rng.choice([0.0, 1e-13, 1e-9], size=(k, n - 1))
    P[:k] = np.einsum("rij,rj,rkj->rik", Qm, lam, Qm)
    P[k:2 * k] *= np.geomspace(1e-8, 1e8, k)[:, None, None]
    P[2 * k:2 * k + 3] = np.broadcast_to(np.outer(np.arange(1, n + 1), np.arange(1, n + 1)), (3, n, n))  # rank 1
    P[-1] = 0.0
    P[-2] = 2.5 * np.eye(n)
    P[-3, 0, 0] = np.inf
    P[-4, n - 1, 0] = P[-4, 0, n - 1] = np.nan
    P = 0.5 * (P + P.transpose(0, 2, 1))
    return np.ascontiguousarray(np.moveaxis(P, 0, -1))


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_lambda_max_equals_eigvalsh(n):
    P = _batch(n, 4000, seed=n)
    ref = batched.lambda_max(P)
    out = np.empty(P.shape[-1])
    rn.lmax_tri(engine._tri(P), n, out)
    fin = np.isfinite(ref)
    assert np.array_equal(np.isfinite(out), fin) and np.all(out[~fin] == np.inf)
    scale = np.maximum(np.abs(ref[fin]), 1e-300)
    assert np.max(np.abs(out[fin] - ref[fin]) / scale * (ref[fin] != 0)) < 1e-12
    assert np.all(np.abs(out[fin][ref[fin] == 0]) < 1e-300)


def _thresholds_near(lam: np.ndarray, rng) -> np.ndarray:
    """M values whose thresholds M + tol·max(1, M) sit on λ_max of some runs, within 0, ±1 ulp, ±1e-15 …"""
    lam = lam[np.isfinite(lam) & (lam > 0)]
    pick = rng.choice(lam, 12)
    M = []
    for lm, rel in zip(pick, [0.0, 1e-16, -1e-16, 1e-15, -1e-15, 1e-13, -1e-13, 1e-11, -1e-11, 1e-9, 0.0, -1e-12]):
        target = lm * (1 + rel)
        M.append(target / (1 + batched.PSD_TOL) if target >= 1 else target - batched.PSD_TOL)
    return np.array(sorted(M + list(np.quantile(lam, [0.1, 0.5, 0.9])) + [0.0, 1e-300]))


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_psd_order_decisions_equal_the_numpy_reducer(n):
    rng = np.random.default_rng(10 + n)
    P = _batch(n, 3000, seed=20 + n)
    M = _thresholds_near(batched.lambda_max(P), rng)[::-1]  # any order of M
    st_np, st_nb = {}, {}
    a, b = engine.DistributionReducer(M, [1]), engine.DistributionReducer(M, [1])
    a.backend, b.backend = "numpy", "numba"
    a.update(st_np, 0, 1, P)
    b.update(st_nb, 0, 1, P)
    assert np.array_equal(st_np["count_0"], st_nb["count_0"])
    assert np.array_equal(st_np["nonfinite_0"], st_nb["nonfinite_0"])
    # the per-run decisions too (the stationary kernel's indicators), not only their sums
    red, st = engine.StationaryReducer([1], M), {}
    red.backend = "numba"
    red.update(st, 0, 1, P)
    a = st["_acc"][0]
    ind = a["ind"].copy()  # the eigvalsh-decided runs, plus the kernel's per-run histogram (as finish folds it)
    ind[engine._thresholds(M)[1]] += np.cumsum(a["hist"][:-1], axis=0)
    ok = batched.lambda_max(P)[None, :] <= (M + batched.PSD_TOL * np.maximum(1.0, M))[:, None]
    assert np.array_equal(ind.astype(bool), ok & ~a["bad"][None, :]) and ind.max() == 1
    # the certificates (conservative) leave few runs to eigvalsh: here mostly the near-degenerate quarter,
    # whose λ_max = 3 (+ 1e-13) is a threshold
    thr, order = engine._thresholds(M)
    amb = np.zeros(P.shape[-1], dtype=bool)
    rc.kernel_dist(n)(engine._tri(P), thr, order, np.zeros(len(M)), amb)
    assert amb.sum() < 0.3 * P.shape[-1]


def _sums_close(a: dict, b: dict, rtol: float) -> None:
    assert set(a) == set(b)
    for key in a:
        if key in (engine.FUSED_CHUNKS, engine.REDUCED):  # which path ran (recorded for the manifest), not a statistic
            continue
        x, y = np.asarray(a[key], float), np.asarray(b[key], float)
        if key.startswith(("count", "nonfinite", "max_nsteps")) or key == "n":
            assert np.array_equal(x, y), key
        else:
            np.testing.assert_allclose(y, x, rtol=rtol, atol=0, err_msg=key)


@pytest.mark.parametrize("n", [1, 3, 4])
def test_reducers_compiled_equal_numpy(n):
    Ps = [_batch(n, 600, seed=30 + k) for k in range(4)]
    M = np.array([0.5, 2.0, 8.0, 30.0])
    steps = [1, 2, 3, 4]
    for make in (lambda: engine.DistributionReducer(M, steps), lambda: engine.MomentReducer(steps),
                 lambda: engine.MomentReducer(steps, lmax=False), lambda: engine.StationaryReducer(steps, M),
                 lambda: engine.StationaryReducer(steps), lambda: engine.TimeAverageReducer(steps)):
        out = []
        for be in ("numpy", "numba"):
            red, st = make(), {}
            red.backend = be
            for k, P in zip(steps, Ps):
                red.update(st, 0, k, np.where(np.isfinite(P), P, 0.0) if isinstance(red, engine.TimeAverageReducer) else P)
            if hasattr(red, "finish"):
                red.finish(st)
            out.append(st)
        _sums_close(out[0], out[1], rtol=1e-12)  # the same numbers summed in another order


@pytest.mark.parametrize("n", [1, 2, 3, 4])
@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_stationary_block_update_is_the_per_step_updates(n, backend):
    """StationaryReducer.update_block (one compiled call per block of steps) against one update per step: the
    same statistics exactly (per run the same sums in the same order; the runs left to eigvalsh decided the
    same way; a step of the block not in the reducer's steps skipped)."""
    rng = np.random.default_rng(40 + n)
    P = np.stack([_batch(n, 700, seed=50 + n + k) for k in range(5)])  # (K, n, n, runs), NaN / inf runs
    P[:, ..., ::7] *= 1e3
    M = _thresholds_near(batched.lambda_max(P[2]), rng)
    steps = [3, 4, 6, 7]
    ks = [3, 4, 5, 6, 7]  # 5: not a step of the reducer
    for Ms in (M, None):
        out = []
        for block in (False, True):
            red, st = engine.StationaryReducer(steps, Ms), {}
            red.backend = backend
            for j in (0, 1):
                if block:
                    red.update_block(st, j, ks[:2], P[:2])
                    red.update_block(st, j, ks[2:], P[2:])
                else:
                    for k, Pk in zip(ks, P):
                        red.update(st, j, k, Pk)
            red.finish(st)
            out.append(st)
        assert set(out[0]) == set(out[1])
        for key in out[0]:
            assert np.array_equal(np.asarray(out[0][key]), np.asarray(out[1][key]), equal_nan=True), key


SYSTEMS = {
    "scalar": LinearSystem.create(1.3, 1.0, 0.5, 0.8),
    "3-state": LinearSystem.create(np.array([[1.1, 0.3, 0.0], [0.0, 0.9, 0.4], [0.2, 0.0, 1.05]]),
                                   np.array([[1.0, 0.0, 1.0]]), 0.1 * np.eye(3), 0.5),
    "vehicle": LinearSystem.create(np.array([[1, 0, 0.5, 0], [0, 1, 0, 0.5], [0, 0, 1, 0], [0, 0, 0, 1.0]]),
                                   np.hstack([np.eye(2), np.zeros((2, 2))]), 0.01 * np.eye(4), 0.001 * np.eye(2)),
    # unstable, long bursts: many runs overflow the rescue limit and are carried on the numpy core
    "rescue": LinearSystem.create(np.diag([1e3, 0.5]), np.eye(2), np.eye(2), np.eye(2)),
}
CHANNELS = {"bernoulli": BernoulliChannel(kind="bernoulli", arrival=0.7),
            "gilbert_elliott": GilbertElliottChannel(kind="gilbert_elliott", loss_rate=0.3, mean_burst=4.0)}


@pytest.mark.parametrize("ch", list(CHANNELS))
def test_uniforms_give_the_sampled_trace(ch):
    c = CHANNELS[ch]
    a = c.sample_trace(np.random.default_rng(5), 300, 40).arrival[0]
    b = c.arrivals_from_uniforms(c.uniforms(np.random.default_rng(5), 300, 40))
    assert np.array_equal(a, b)


@pytest.mark.parametrize("system", list(SYSTEMS))
@pytest.mark.parametrize("ch", list(CHANNELS))
def test_fused_kf_equals_the_numpy_path(system, ch):
    s, c = SYSTEMS[system], CHANNELS[ch]
    H, R = 40, 700
    allk, win = list(range(1, H + 1)), list(range(21, H + 1))
    M = np.array([0.3, 1.0, 3.0, 10.0, 1e3])
    cases = [(lambda: engine.DistributionReducer(M, [10, H]), [10, H], "filtered"),
             (lambda: engine.MomentReducer(allk), allk, "filtered"),
             (lambda: engine.MomentReducer(allk, lmax=False), allk, "predicted"),
             (lambda: engine.StationaryReducer(win, M), win, "predicted"),
             (lambda: engine.TimeAverageReducer(win), win, "filtered"),
             (lambda: engine.PairedReducer(allk), allk, "filtered")]  # no compiled update: unpacked P
    for make, steps, q in cases:
        out = []
        for be in ("numpy", "numba"):
            red = make()
            red.backend = be
            ests = [KalmanFilterEstimator(kind="kf", backend=be) for _ in range(2 if isinstance(red, engine.PairedReducer) else 1)]
            ker = engine.PairKernel(s, c, ests, H, steps, red, q)
            assert (ker.fused(R) is not None) == (be == "numba")
            out.append(ker(np.random.default_rng(3), R))
            assert out[-1][engine.FUSED_CHUNKS].tolist() == [int(be == "numba")] * len(ests)
        # the compiled filter is the numpy core's equations in another association order: rounding only
        _sums_close(out[0], out[1], rtol=1e-9)
    if system == "rescue":  # the numpy redo of flagged runs was exercised
        fz = KalmanFilterEstimator(kind="kf", backend="numba").fused(s, c, 1)
        u = c.uniforms(np.random.default_rng(3), R, H)
        T, g, flag = fz.start(R)
        fz.advance(T, u, g, flag, 0, H)
        assert flag.sum() > 10


@pytest.mark.parametrize("ch", list(CHANNELS))
def test_fused_filter_step_is_the_compiled_kernel_bit_for_bit(ch):
    s, c = SYSTEMS["vehicle"], CHANNELS[ch]
    fz = KalmanFilterEstimator(kind="kf", backend="numba").fused(s, c, 1)
    f = fz.f
    u = c.uniforms(np.random.default_rng(1), 500, 30)
    gam = np.ascontiguousarray(c.arrivals_from_uniforms(u)[None])
    T1, g, fl1 = fz.start(500)
    fz.advance(T1, u, g, fl1, 0, 30)
    T0, _, fl0 = fz.start(500)
    kc.kernel(f.A, f.C, f.Q, f.R, f.groups, f.rescue.limit)(T0, gam, 0, 30, fl0)
    assert np.array_equal(T0, T1) and np.array_equal(fl0, fl1)


def test_auto_picks_the_fused_path_with_numba_and_numpy_without(monkeypatch):
    s, c = SYSTEMS["scalar"], CHANNELS["bernoulli"]
    red = engine.DistributionReducer(np.array([1.0]), [50])
    ker = engine.PairKernel(s, c, [KalmanFilterEstimator(kind="kf")], 50, [50], red)
    big = kalman.AUTO_MIN_RUN_STEPS // 50
    assert ker.fused(big) is not None and ker.fused(big - 1) is None
    assert engine._compiled("auto", np.zeros((1, 1, engine.REDUCE_MIN_RUNS)), None)
    monkeypatch.setattr(kalman, "numba_available", lambda: False)
    ker = engine.PairKernel(s, c, [KalmanFilterEstimator(kind="kf")], 50, [50], red)
    assert ker.fused(big) is None
    assert not engine._compiled("auto", np.zeros((1, 1, engine.REDUCE_MIN_RUNS)), None)
    st = ker(np.random.default_rng(0), 300)  # the numpy path runs
    assert st["count_0"].sum() > 0
