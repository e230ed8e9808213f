"""The smoother and Gilbert–Elliott channel contracts (issue 12), the smoother on the Kalman core
(issue 19: named quantities on the one time base, the forward pass is kf's, one rescue policy,
any number of sensors), the compiled backend on kalman_numba's primitives, and overflow handling (the
Monte Carlo checks through the generic engine)."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from netkf_cli import engine
from netkf_cli.linalg import kalman
from netkf_cli.linalg import riccati
from netkf_cli.analysis.smoothing import batch_posterior_covariance
from netkf_cli.channels.bernoulli import BernoulliChannel
from netkf_cli.channels.gilbert_elliott import GilbertElliottChannel
from netkf_cli.core.errors import ConfigError
from netkf_cli.estimators import smoother as sm_est
from netkf_cli.estimators.kf import KalmanFilterEstimator
from netkf_cli.estimators.smoother import SmootherEstimator
from netkf_cli.core.system import LinearSystem
from netkf_cli.core.trace import Trace

numba_missing = not sm_est.numba_available()


def random_system(rng, n, m, P0=True, rho=1.1):
    A = rng.normal(size=(n, n))
    A *= rho / max(np.abs(np.linalg.eigvals(A)).max(), 1e-3)  # mildly unstable, like the papers' plants
    C = rng.normal(size=(m, n))
    Lq = rng.normal(size=(n, n)) * 0.5
    Lr = rng.normal(size=(m, m)) * 0.5
    L0 = rng.normal(size=(n, n))
    return LinearSystem.create(A, C, Lq @ Lq.T + 0.05 * np.eye(n), Lr @ Lr.T + 0.2 * np.eye(m),
                               (L0 @ L0.T + 0.1 * np.eye(n)) if P0 else None)


def est(lag, backend="numpy"):
    return SmootherEstimator(kind="smoother", lag=lag, backend=backend)


# --------------------------------------------------------------------------- channel contract
def test_gilbert_elliott_contract():
    ch = GilbertElliottChannel(kind="gilbert_elliott", loss_rate=0.3, mean_burst=3)
    assert ch.trace_kinds == frozenset({"arrival"})
    assert ch.loss_rate() == 0.3
    tr = ch.sample_trace(np.random.default_rng(1), 20_000, 50)
    assert isinstance(tr, Trace) and tr.arrival.shape == (1, 50, 20_000) and tr.arrival.dtype == bool
    # stationary from k = 0: the loss rate at every step is π_B; 5 s.e. of a mean of 20 000 × 50
    # correlated indicators (variance inflation (1+ρ)/(1−ρ), ρ = 1 − p_gb − p_bg = 0.524 ⇒ × 3.2)
    se = np.sqrt(0.3 * 0.7 / (20_000 * 50) * 3.2)
    assert abs((~tr.arrival).mean() - 0.3) < 5 * se
    # the YAML key is still loss_rate (alias): the manifest round-trips
    assert ch.model_dump(by_alias=True)["loss_rate"] == 0.3


# --------------------------------------------------------------------------- estimator contract
QS = ("filtered", "predicted", "smoothed")


@pytest.mark.parametrize("backend", ["numpy"] + ([] if numba_missing else ["numba"]))
@pytest.mark.parametrize("n, m", [(1, 1), (2, 1), (3, 2)])
@pytest.mark.parametrize("lag", [0, 1, 3])
def test_covariances_equal_batch_gaussian_conditioning(n, m, lag, backend):
    """The three quantities on the one time base (step k carries y_k, P0 = P_{0|0}) against brute-force
    conditioning of the joint Gaussian law of (x_0 … x_T, y_0 … y_T) (y_0 never observed):
    filtered P_{k|k}, predicted P_{k+1|k}, smoothed P_{k−N|k} (P_{0|N} at k = N)."""
    rng = np.random.default_rng(10 * n + m + 100 * lag)
    s = random_system(rng, n, m)
    T, runs = 8, 3
    arr = rng.random((T, runs)) < 0.6
    tr = Trace(runs=runs, horizon=T, arrival=arr[None])
    steps = list(range(1, T + 1))
    out = dict(est(lag, backend).covariances(s, tr, steps, QS))
    assert sorted(out) == steps
    for k in steps:
        assert set(out[k]) == set(QS)
        P = out[k]["smoothed"]
        assert P.shape == (n, n, runs)
        if k < lag:  # before first_step("smoothed") = N: undefined
            assert np.isnan(P).all()
            continue
        for r in range(runs):
            g = np.concatenate([[False], arr[:, r], [False]])  # index 0 = y_0 (not sent)
            for q, (target, upto) in {"smoothed": (k - lag, k), "filtered": (k, k), "predicted": (k + 1, k)}.items():
                ref = batch_posterior_covariance(s, g, target, upto, s.P0)
                np.testing.assert_allclose(out[k][q][:, :, r], ref, rtol=1e-8, atol=1e-9 * max(1.0, np.abs(ref).max()))


def test_first_step_and_conventions():
    assert est(3).first_step("smoothed") == 3 and est(3).first_step("filtered") == 1
    assert est(0).first_step("smoothed") == 0
    assert SmootherEstimator.quantities == QS
    assert est(3).conventions(None, None)["smoothed"] == "P_{k-3|k} (lag N = 3)"
    assert est(0).conventions(None, None)["smoothed"] == "P_{k|k} (lag N = 0)"
    with pytest.raises(ConfigError, match="does not report"):
        list(est(1).covariances(LinearSystem.create(1.3, 1, 0.5, 1), Trace(runs=1, horizon=2, arrival=np.ones((1, 2, 1), bool)),
                                [1], ("bogus",)))


def test_lag0_perfect_channel_is_the_dare_filter():
    s = LinearSystem.create([[1.2, 0.4], [0.0, 0.8]], [[1.0, 0.0]], np.eye(2) * 0.3, 0.5, np.eye(2) * 5)
    tr = Trace(runs=2, horizon=300, arrival=np.ones((1, 300, 2), bool))
    (k, P), = list(est(0).covariances(s, tr, [300], ("smoothed",)))
    np.testing.assert_allclose(P["smoothed"][:, :, 0], riccati.gtilde(riccati.pstar(s), s), rtol=1e-9)


@pytest.mark.parametrize("backend", ["numpy"] + ([] if numba_missing else ["numba"]))
@pytest.mark.parametrize("A", [[[1.2, 0.4], [0.0, 0.8]], [[1e6, 0.0], [0.0, 0.5]]])
def test_forward_pass_is_kf_and_lag0_is_the_filter(A, backend):
    """One filter, many names: filtered/predicted are kf's (numpy: the same primitive sequence, bit for
    bit; numba: to rounding), smoothed with lag 0 is filtered — also for A = diag(1e6, 0.5), where
    every step goes through the rescue (tr P⁻ ≈ 1e12 > the limit)."""
    s = LinearSystem.create(A, np.eye(2), np.eye(2) * 0.3, np.eye(2) * 0.5, None)
    rng = np.random.default_rng(2)
    tr = Trace(runs=40, horizon=25, arrival=rng.random((1, 25, 40)) < 0.6)
    steps = [1, 2, 7, 25]
    ref = dict(KalmanFilterEstimator(kind="kf").covariances(s, tr, steps, ("filtered", "predicted")))
    for lag in (0, 2):
        got = dict(est(lag, backend).covariances(s, tr, steps, QS))
        for k in steps:
            for q in ("filtered", "predicted"):
                if backend == "numpy":
                    assert np.array_equal(got[k][q], ref[k][q]), (lag, k, q)
                else:
                    np.testing.assert_allclose(got[k][q], ref[k][q], rtol=1e-12, atol=0)
            if lag == 0:
                assert np.array_equal(got[k]["smoothed"], got[k]["filtered"])
            elif k >= lag:
                assert np.isfinite(got[k]["smoothed"]).all()
                # smoothing never hurts: P_{k−N|k} ≤ P_{k−N|k−N}
                back = dict(est(0, backend).covariances(s, tr, [k - lag], ("filtered",))) if k - lag >= 1 else None
                if back:
                    Pf = back[k - lag]["filtered"]
                    assert riccati.psd_leq(np.moveaxis(got[k]["smoothed"], -1, 0), np.moveaxis(Pf, -1, 0), tol=1e-9).all()


def test_overflowed_forward_pass_is_inf_in_every_quantity_until_an_arrival():
    """A = 30: P_{k|k−1} overflows after ~105 losses (900¹⁰⁵ > 1.8e308). The rescue policy keeps the
    run inf (never NaN) while its packets are lost, and an arrival recovers it (the unknown direction
    carries information 0: P_{k|k} = r/c² = 1); the backward pass is inf for a window that holds an
    inf forward covariance and finite once the window is past it. Both backends (the compiled kernel
    hands a run that met a non-finite covariance to the numpy core)."""
    s = LinearSystem.create(30.0, 1, 1, 1, 1.0)
    arr = np.zeros((1, 260, 3), bool)
    arr[0, :, 1] = True
    arr[0, 150:, 2] = True  # y_151 … arrive after 150 losses: the prior 900¹⁵⁰ has overflowed
    tr = Trace(runs=3, horizon=260, arrival=arr)
    for backend in ["numpy"] + ([] if numba_missing else ["numba"]):
        with np.errstate(all="raise"):
            out = dict(est(2, backend).covariances(s, tr, [90, 150, 151, 152, 153, 260], QS))
        for k, d in out.items():
            for q, P in d.items():
                assert not np.isnan(P).any(), (backend, k, q)
                assert np.isfinite(P[..., 1]).all()
                assert (k == 90) == bool(np.isfinite(P[..., 0]).all()), (backend, k, q)  # run 0: all lost
        assert np.isinf(out[150]["filtered"][..., 2]).all()
        assert out[151]["filtered"][0, 0, 2] == pytest.approx(1.0, rel=1e-12)  # recovered at the arrival
        assert np.isinf(out[152]["smoothed"][..., 2]).all()  # window 150 … 152 holds P_{150|150} = inf
        assert np.isfinite(out[153]["smoothed"][..., 2]).all()  # window 151 … 153: finite
        np.testing.assert_allclose(out[260]["smoothed"][..., 2], out[260]["smoothed"][..., 1], rtol=1e-9)


def test_rescue_recovers_a_huge_finite_prior():
    """100 losses at A = 30 (prior 900¹⁰⁰ ≈ 1e295, finite) then an arrival: the standard form cancels
    every digit; the rescue (information form) gives P_{k|k} = 1/(1/Σ + c²/r) = 1 to rounding, and the
    smoother P_{k−1|k} = (P_{k−1|k−1}⁻¹ + a²/(q + r))⁻¹-type finite values."""
    s = LinearSystem.create(30.0, 1, 1, 1, 1.0)
    arr = np.zeros((1, 102, 1), bool)
    arr[0, 100:] = True  # y_101, y_102 arrive
    tr = Trace(runs=1, horizon=102, arrival=arr)
    for backend in ["numpy"] + ([] if numba_missing else ["numba"]):
        out = dict(est(1, backend).covariances(s, tr, [101, 102], QS))
        assert out[101]["filtered"][0, 0, 0] == pytest.approx(1.0, rel=1e-12)
        # P_{101|102}: x_101 from y_101 (r = 1) and y_102 = x_102 + v = 30 x_101 + w + v (q + r = 2)
        assert out[102]["smoothed"][0, 0, 0] == pytest.approx(1.0 / (1.0 + 900.0 / 2.0), rel=1e-9)


@pytest.mark.parametrize("backend", ["numpy"] + ([] if numba_missing else ["numba"]))
def test_several_sensors_each_with_its_own_stream(backend):
    """system.sensors: 2 (C, R stacked) and a 2-stream trace: sensor s arrives with stream s. Against brute
    force on the stacked output with the per-sensor arrival pattern (a sensor lost = its rows missing);
    with both streams always equal, the same as one stream carrying all of y_k."""
    from netkf_cli.analysis.smoothing import batch_posterior_covariance as bpc

    C1, R1 = np.array([[1.0, 0.5]]), np.array([[0.4]])
    s2 = LinearSystem.create([[1.1, 0.3], [0.0, 0.9]], np.vstack([C1, C1]), np.eye(2) * 0.2,
                             np.kron(np.eye(2), R1), np.eye(2), sensors=((0,), (1,)))
    rng = np.random.default_rng(5)
    T, runs, lag = 6, 4, 2
    arr = rng.random((2, T, runs)) < 0.5
    out = dict(est(lag, backend).covariances(s2, Trace(runs=runs, horizon=T, arrival=arr), [4, 6], QS))
    for k in (4, 6):
        for r in range(runs):
            # x_t is observed by sensor i at time t iff arr[i, t−1] (its rows of the stacked C)
            Pref = _brute_rows(s2, arr[:, :, r], k - lag, k)
            np.testing.assert_allclose(out[k]["smoothed"][:, :, r], Pref, rtol=1e-8, atol=1e-10)
    same = np.repeat(arr[:1], 2, axis=0)
    a = dict(est(lag, backend).covariances(s2, Trace(runs=runs, horizon=T, arrival=same), [6], QS))
    b = dict(est(lag, backend).covariances(s2, Trace(runs=runs, horizon=T, arrival=same[:1]), [6], QS))
    np.testing.assert_allclose(a[6]["smoothed"], b[6]["smoothed"], rtol=1e-10)
    # a 3-stream channel does not fit 2 sensors: refused with the fix named
    with pytest.raises(ConfigError, match="sensors"):
        list(est(lag, backend).covariances(s2, Trace(runs=1, horizon=T, arrival=np.ones((3, T, 1), bool)), [6], QS))


def _brute_rows(s, arr, target, upto):
    """Cov(x_target | the arrived rows of y_1 … y_upto) by conditioning the joint Gaussian law (x_0 ~ N(·, P0))."""
    n, m = s.n, s.m
    T = max(target, upto) + 1
    V = [s.P0]
    for _ in range(1, T):
        V.append(s.A @ V[-1] @ s.A.T + s.Q)
    big = np.zeros((n * T, n * T))
    for t in range(T):
        X = V[t]
        for u in range(t, T):
            big[u * n:(u + 1) * n, t * n:(t + 1) * n] = X
            big[t * n:(t + 1) * n, u * n:(u + 1) * n] = X.T
            X = s.A @ X
    rows = []
    for t in range(1, upto + 1):
        for i, g in enumerate(s.sensor_rows):
            if arr[i, t - 1]:
                for row in g:
                    rows.append((t, row))
    P = big[target * n:(target + 1) * n, target * n:(target + 1) * n]
    if not rows:
        return P
    H = np.zeros((len(rows), n * T))
    Rb = np.zeros((len(rows), len(rows)))
    for a, (t, row) in enumerate(rows):
        H[a, t * n:(t + 1) * n] = s.C[row]
        for b, (u, row2) in enumerate(rows):
            if u == t:
                Rb[a, b] = s.R[row, row2]
    Syy = H @ big @ H.T + Rb
    Sxy = big[target * n:(target + 1) * n, :] @ H.T
    return riccati.sym(P - Sxy @ np.linalg.solve(Syy, Sxy.T))


def test_check_refuses_a_channel_without_arrivals():
    class Fake:
        kind = "fading"
        trace_kinds = frozenset({"snr"})

    with pytest.raises(ConfigError, match="arrival"):
        est(1).check(None, Fake())
    est(1).check(None, BernoulliChannel(kind="bernoulli", arrival=0.5))  # fine
    assert SmootherEstimator.accepts == frozenset({"arrival"})
    # one stream carries all of y_k: fine for a 2-output system; the stream count is checked against the sensors
    s = LinearSystem.create(np.eye(2), np.eye(2), np.eye(2), np.eye(2))
    est(1).check(s, BernoulliChannel(kind="bernoulli", arrival=0.5))


def test_lag_limit_is_a_validation_error():
    with pytest.raises(Exception, match="lag"):
        SmootherEstimator(kind="smoother", lag=sm_est.MAX_LAG + 1)


# --------------------------------------------------------------------------- backends
@pytest.mark.skipif(numba_missing, reason="numba not installed")
@pytest.mark.parametrize("n, m", [(1, 1), (2, 1), (3, 2), (4, 2), (3, 3)])
def test_numba_equals_numpy_on_the_same_arrivals(n, m):
    """The compiled kernel (kalman_numba's inlined predict/update/information_update/smooth) against the
    numpy core on the same arrival trace: every quantity, to rounding (products summed in another order)."""
    rng = np.random.default_rng(n * 7 + m)
    s = random_system(rng, n, m)
    g = (rng.random((40, 300)) < 0.55)[None]
    steps = [1, 4, 18, 31, 40]
    for lag in (0, 1, 4):
        a = dict(sm_est.run(s, g, steps, QS, lag, backend="numpy"))
        b = dict(sm_est.run(s, g, steps, QS, lag, backend="numba"))
        for k in steps:
            for q in QS:
                x, y = a[k][q], b[k][q]
                if k < lag and q == "smoothed":
                    assert np.isnan(x).all() and np.isnan(y).all()
                    continue
                np.testing.assert_allclose(y, x, rtol=1e-10, atol=1e-12 * np.abs(x).max(), err_msg=f"{lag} {k} {q}")


def _pd(rng, n, scale=1.0):
    L = rng.normal(size=(n, n))
    return L @ L.T * scale + 0.1 * np.eye(n)


def test_smooth_step_in_conditioning_form_is_rts_and_survives_huge_priors():
    """kalman.SmoothStep (the core's one smoothing step) = the textbook RTS step
    Pf + J (Ps − Pp) Jᵀ, J = Pf Aᵀ Pp⁻¹; and, where the textbook form cancels every digit (a scalar
    P_{t|t} = 1e20 at a = 1e6), the exact value: given x_{t+1}, Var x_t = (1/Pf + a²/q)⁻¹ ≈ q/a², plus
    J² P_{t+1|T} with J = Pf a/(a² Pf + q)."""
    rng = np.random.default_rng(9)
    for n in (1, 2, 3, 4):
        A = rng.normal(size=(n, n))
        Pf, Q = _pd(rng, n), _pd(rng, n, 0.3)
        Pp = A @ Pf @ A.T + Q
        Ps = riccati.sym(np.linalg.solve(np.eye(n) + Pp @ _pd(rng, n), Pp))  # some P_{t+1|T} ≤ P_{t+1|t}
        J = Pf @ A.T @ np.linalg.inv(Pp)
        ref = Pf + J @ (Ps - Pp) @ J.T
        got = kalman.SmoothStep.of(A, Q)(Ps[:, :, None], Pf[:, :, None])[:, :, 0]
        np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-12)
    a, q, pf, ps = 1e6, 0.5, 1e20, 0.3
    got = kalman.SmoothStep.of(np.array([[a]]), np.array([[q]]))(np.full((1, 1, 1), ps), np.full((1, 1, 1), pf))[0, 0, 0]
    j = pf * a / (a * a * pf + q)
    assert got == pytest.approx(1.0 / (1.0 / pf + a * a / q) + j * j * ps, rel=1e-12)


@pytest.mark.skipif(numba_missing, reason="numba not installed")
def test_compiled_primitives_equal_the_numpy_core():
    """kalman_numba.smooth and .information_update (appended for the smoother) against
    kalman.SmoothStep and kalman.information_update on random PD matrices (one run), and the huge case."""
    from netkf_cli.linalg import kalman_numba as kn

    rng = np.random.default_rng(9)
    for n in (1, 2, 3, 4):
        A = rng.normal(size=(n, n))
        Pf, Q, Ps = _pd(rng, n), _pd(rng, n, 0.3), _pd(rng, n, 0.2)
        step = kalman.SmoothStep.of(A, Q)
        info_s = A.T @ np.linalg.solve(Q, A)
        out, w = np.empty((n, n)), [np.empty((n, n)) for _ in range(6)]
        for scale in (1.0, 1e14):  # 1e14: tr Pf above the rescue limit → the information form
            P = Pf * scale
            kn.smooth(Ps, P, A, Q, info_s, float(step.rescue.limit), out, *w)
            ref = step(Ps[:, :, None], P[:, :, None])[:, :, 0]
            np.testing.assert_allclose(out, ref, rtol=1e-9, atol=1e-12 * np.abs(ref).max())
        info = _pd(rng, n)
        kn.information_update(Pf, info, out, w[0], w[1])
        np.testing.assert_allclose(out, kalman.one(kalman.information_update, Pf, info), rtol=1e-11)
        np.testing.assert_allclose(out, np.linalg.inv(np.linalg.inv(Pf) + info), rtol=1e-10)


QS3 = ("predicted", "filtered", "smoothed")


def _simulate(s, ch, lag, backend, reducer, steps, runs, horizon, seed, quantities=QS3):
    """The generic engine's statistics of one smoother (every listed quantity in one pass: column = quantity index)."""
    return engine.simulate(s, ch, [est(lag, backend)], reducer, steps=steps, runs=runs, horizon=horizon, seed=seed,
                           chunk=runs, quantity=quantities)


@pytest.mark.skipif(numba_missing, reason="numba not installed")
def test_engine_statistics_identical_across_backends():
    # Table I's columns at k = 30 on a Gilbert–Elliott channel through the generic engine: P_{k|k−1} (predicted
    # at 29), P_{k|k} (filtered at 30), P_{k|k+2} (smoothed, lag 2, at 32); counts of P ≤ M and non-finite runs
    # equal, moment sums equal to rounding (the compiled products are summed in another order)
    s = LinearSystem.create(1.3, 1, 0.5, 1, None)
    ch = GilbertElliottChannel(kind="gilbert_elliott", loss_rate=0.4, mean_burst=3)
    steps = [29, 30, 32]
    for reducer, exact in ((engine.DistributionReducer(np.array([6.25]), steps), True), (engine.MomentReducer(steps), False)):
        a, b = (_simulate(s, ch, 2, be, reducer, steps, 5000, 32, 7) for be in ("numpy", "numba"))
        assert a.keys() == b.keys() and int(a["n"]) == 5000
        for key in a:
            if exact or key.startswith(("count_", "nonfinite_", "n")):
                np.testing.assert_array_equal(a[key], b[key], err_msg=key)
            else:
                np.testing.assert_allclose(b[key], a[key], rtol=1e-12, atol=0, err_msg=key)


def test_auto_backend_picks_numba_when_importable(monkeypatch):
    if not numba_missing:
        assert sm_est.resolve_backend("auto") == "numba"  # then only for batches ≤ AUTO_NUMBA_MAX_RUNS runs
        assert sm_est.AUTO_NUMBA_MAX_RUNS >= 1
    monkeypatch.setitem(sys.modules, "numba", None)  # hide numba: import fails
    assert sm_est.resolve_backend("auto") == "numpy"
    with pytest.raises(ConfigError, match="numba"):
        sm_est.resolve_backend("numba")


# --------------------------------------------------------------------------- kernels on workers
# The smoother's generic kernel pickles and runs on worker processes (process pool and Dask) with byte-identical
# CSVs: tests/engine/test_executors.py::test_every_estimator_runs_on_workers_with_identical_csvs.


# --------------------------------------------------------------------------- overflow (issue 14)
def test_huge_a_bernoulli_monte_carlo_matches_the_exact_probability():
    """A = 10⁶, λ = 0.5: every prior after a loss has tr P⁻ ≥ 10¹² (the rescue's information form
    redoes the update), P_{k|k} = r/(c² + r/Σ) ≤ 1 after any arrival and ≥ q·10¹² after a loss, so
    Pr[P_{k|k} ≤ 10] = λ exactly. Overflow needs ≥ 26 losses in a row (10^(12·26) > 1.8e308):
    probability ≈ 200 · 2⁻²⁶ ≈ 3e-6 per run, so none of the 4000 runs (expected 0.012).
    Tolerance: 5 binomial s.e."""
    s = LinearSystem.create(1e6, 1, 0.5, 1, None)
    runs, lam = 4000, 0.5
    ch = BernoulliChannel(kind="bernoulli", arrival=lam)
    steps = [199, 200, 201]  # k = 200: P_{k|k−1} = predicted at 199, P_{k|k} = filtered at 200, P_{k|k+1} = smoothed at 201
    for backend in ("numpy",) + (() if numba_missing else ("numba",)):
        with np.errstate(all="raise"):
            st = _simulate(s, ch, 1, backend, engine.DistributionReducer(np.array([10.0]), steps), steps, runs, 201, 3)
        assert int(st["n"]) == runs
        p = st["count_1"][1, 0] / runs  # filtered, at step 200
        assert abs(p - lam) < 5 * np.sqrt(lam * (1 - lam) / runs)
        assert st["nonfinite_0"][0] == 0 and st["nonfinite_2"][2] == 0
        # lag 1: ≤ M iff γ_k = 1 or γ_{k+1} = 1 (the next measurement pins x_k down): 1 − (1 − λ)²
        p1 = st["count_2"][2, 0] / runs
        q1 = 1 - (1 - lam) ** 2
        assert abs(p1 - q1) < 5 * np.sqrt(q1 * (1 - q1) / runs)


def test_huge_a_overflowed_runs_recover_at_their_next_arrival():
    """A = 10⁶, λ = 0.05: P_{k|k−1} overflows in long loss bursts (≥ 26 losses), and the rescue policy
    recovers the run at its next arrival (information 0 in the unknown direction), so P_{k|k} = r/(c² +
    r/Σ) ≤ 1 after any arrival and ≥ q·10¹² after a loss: Pr[P_{k|k} ≤ 10] = λ exactly. 5 binomial s.e."""
    s = LinearSystem.create(1e6, 1, 0.5, 1, None)
    runs, lam = 20_000, 0.05
    ch = BernoulliChannel(kind="bernoulli", arrival=lam)
    steps = [199, 200]  # k = 200: P_{k|k−1} = predicted at 199, P_{k|k} = filtered at 200
    for backend in ("numpy",) + (() if numba_missing else ("numba",)):
        with np.errstate(all="raise"):
            st = _simulate(s, ch, 0, backend, engine.DistributionReducer(np.array([10.0]), steps), steps, runs, 200, 3,
                           ("predicted", "filtered"))
        assert abs(st["count_1"][1, 0] / runs - lam) < 5 * np.sqrt(lam * (1 - lam) / runs)
        assert st["nonfinite_0"][0] > 0 and st["nonfinite_1"][1] > 0  # some runs were overflowed at k, and counted


def test_future_information_recursion_equals_the_batch_form_and_survives_huge_a():
    import itertools

    from netkf_cli.analysis import smoothing as asm

    rng = np.random.default_rng(0)
    for n, m in [(1, 1), (2, 1), (3, 2)]:
        s = random_system(rng, n, m)
        for f in itertools.product((0, 1), repeat=4):
            H, Sig = asm._future_model(s, f)
            batch = np.zeros((n, n)) if H is None else H.T @ np.linalg.solve(Sig, H)
            np.testing.assert_allclose(asm.future_information(s, f), batch, rtol=1e-9, atol=1e-10)
    big = LinearSystem.create(1e6, 1, 0.5, 1)  # Σ_η is numerically singular here; the recursion is not
    J = asm.future_information(big, (0, 1))  # y_{k+1} = 10⁶ x_k + w_k + v: J = 10¹²/(q + r)
    np.testing.assert_allclose(J, [[1e12 / 1.5]], rtol=1e-12)
