"""The issue-12 contract for the Shi 2009 channels and estimators, and the overflow fix (issue 14.4).

* channels: ``trace_kinds``, ``sample_trace`` (layout, delays vs the inverse-CDF kernel),
  ``loss_rate``, ``delay_pmf``;
* estimators: ``covariances`` against an independent per-run loop (``riccati.h``/``gtilde`` on
  the kept pattern of every k) on the same trace, for every step; ``check``;
* one filter, many names: ``buffered`` on a zero-delay / pure-loss trace IS ``kf`` (relative 1e-12
  at every k, filtered and predicted);
* overflow: A = diag(1e6, 0.5), C = I, Bernoulli 0.05 — the same P as ``kf`` (the core's one Rescue
  policy), Pr[P_k ≤ M] within 5 s.e. of the exact 0.05 where the policy is exact, no numpy warnings,
  the compiled backend equal to numpy.
"""

import warnings

import numpy as np
import pytest

from netkf_cli.linalg import riccati
from netkf_cli.channels.delay import kept_at, max_kept_delay
from netkf_cli.core.errors import ConfigError
from netkf_cli.estimators.buffered import BufferedEstimator, availability, packet_span
from netkf_cli.estimators.kf import KalmanFilterEstimator
from netkf_cli.estimators.smart_sensor import SmartSensorEstimator
from netkf_cli.linalg.riccati import initial_covariance
from netkf_cli.core.system import LinearSystem
from netkf_cli.core.trace import LOST, Trace

from ._systems import bernoulli, pmf, poisson, scalar_system, vehicle_system


def _dense_3x1() -> LinearSystem:
    """n = 3, m = 1: C not invertible and not the Appendix B case (2m ≠ n)."""
    g = np.random.default_rng(3)
    A = g.normal(size=(3, 3)) * 0.5 + np.diag([1.1, 0.3, 0.2])
    L = g.normal(size=(3, 3))
    return LinearSystem.create(A, g.normal(size=(1, 3)), L @ L.T * 0.1 + 0.01 * np.eye(3), 0.4)


def _overflow_system() -> LinearSystem:
    return LinearSystem.create(np.diag([1e6, 0.5]), np.eye(2), np.eye(2), np.eye(2))


# --------------------------------------------------------------------------------------------
# channels
# --------------------------------------------------------------------------------------------


def test_delay_channel_trace_layout_and_kinds():
    ch = poisson(3, 4, "delay_lt_D")
    assert ch.trace_kinds == frozenset({"delay", "arrival"})
    tr = ch.sample_trace(np.random.default_rng(0), 7, 30)
    assert isinstance(tr, Trace) and tr.delay.shape == (1, 30, 7) and tr.delay.dtype == np.int32
    assert tr.meta["buffer"] == 4 and tr.meta["convention"] == "delay_lt_D"
    assert np.array_equal(tr.arrival, tr.delay == 0)  # arrival = usable on time
    assert np.all((tr.delay >= 0) & ((tr.delay < 30) | (tr.delay == LOST)))


def test_delay_trace_uses_the_kernel_uniforms():
    """d ≤ j ⇔ u < F(j): the trace's delays reproduce the kernel's kept decisions packet by packet."""
    ch = pmf([0.3, 0.2, 0.1], 2)  # loss 0.4
    T, runs = 12, 500
    tr = ch.sample_trace(np.random.default_rng(4), runs, T)
    U = np.random.default_rng(4).random((T, runs))
    F = ch.cdf(np.arange(T))
    for j in range(T):
        assert np.array_equal(tr.delay[0] <= j, U < F[j])
    # lost packets are LOST; empirical loss rate within 5 s.e. of 0.4
    lost = (tr.delay[0] == LOST).mean()
    assert abs(lost - 0.4) <= 5 * np.sqrt(0.24 / (T * runs))


def test_loss_rate_and_pmf():
    ch = pmf([0.5, 0.25], 1)
    assert np.allclose(ch.delay_pmf(4), [0.5, 0.25, 0, 0])
    assert ch.loss_rate() == pytest.approx(0.25)  # delay_le_D, D = 1: delays 0 and 1 kept
    assert pmf([0.5, 0.25], 1, "delay_lt_D").loss_rate() == pytest.approx(0.5)
    b = bernoulli(0.7)
    assert b.trace_kinds == frozenset({"arrival"})
    assert b.loss_rate() == pytest.approx(0.3) and np.allclose(b.delay_pmf(3), [0.7, 0, 0])
    tr = b.sample_trace(np.random.default_rng(1), 4000, 5)
    assert tr.arrival.shape == (1, 5, 4000) and tr.delay is None
    assert abs(tr.arrival.mean() - 0.7) <= 5 * np.sqrt(0.21 / 20000)


# --------------------------------------------------------------------------------------------
# estimators: batched covariances == a per-run loop on the same trace
# --------------------------------------------------------------------------------------------


def _loop_buffered(s, delays, k, D, conv, span, P0):
    """P_k of one run: kept pattern at k (eq. 4), availability, then h / g̃ step by step."""
    kept = kept_at(delays[:k], k, D, conv)
    a = availability(kept, span)
    X = P0
    for t in range(k):
        X = riccati.h(X, s)
        if a[t]:
            X = riccati.gtilde(X, s)
    return X


def _loop_smart(s, delays, k, D, conv, P0):
    Dmax = max_kept_delay(D, conv)
    X = riccati.pbar(s)
    for t in range(k):  # packet k − t, age t
        if delays[k - 1 - t] <= min(t, Dmax):
            return riccati.h_power(X, s, t)
    return riccati.h_power(P0, s, k)


CASES = {  # system, channel, span
    "scalar": (scalar_system(), poisson(2, 3), 1),
    "vehicle_pairs": (vehicle_system(), poisson(1.5, 2, "delay_lt_D"), 2),
    "dense_3x1_measurement": (_dense_3x1(), pmf([0.4, 0.2, 0.2], 2), 1),
    "bernoulli_2x2": (LinearSystem.create([[1.2, 0.3], [0, 0.8]], np.eye(2), np.eye(2) * 0.1, np.eye(2) * 0.2),
                      bernoulli(0.6), 1),
    # buffer longer than the horizon: which packets are final is decided by the in-flight ones
    "big_buffer_2x2": (LinearSystem.create([[1.1, 0.2], [0, 0.9]], np.eye(2), np.eye(2) * 0.1, np.eye(2) * 0.3),
                       pmf([0.3, 0.1, 0.1, 0.1, 0.05, 0.05, 0.05], 40), 1),
    "big_buffer_vehicle_pairs": (vehicle_system(), pmf([0.4, 0.1, 0.1, 0.1, 0.1], 40, "delay_lt_D"), 2),
}


@pytest.mark.parametrize("name", list(CASES))
def test_buffered_covariances_equal_per_run_loop(name):
    s, ch, span = CASES[name]
    est = BufferedEstimator(kind="buffered", backend="numpy")
    assert est.span(s) == span
    est.check(s, ch)
    T, runs = 16, 12
    tr = ch.sample_trace(np.random.default_rng(7), runs, T)
    steps = list(range(1, T + 1))
    got = dict(est.covariances(s, tr, steps, ("filtered", "predicted")))
    assert sorted(got) == steps
    d = tr.delay[0] if tr.delay is not None else np.where(tr.arrival[0], 0, LOST)
    P0 = initial_covariance(s)
    for k in (1, 2, 5, 9, T):
        P, Pp = got[k]["filtered"], got[k]["predicted"]
        assert P.shape == (s.n, s.n, runs)
        for r in range(runs):
            ref = _loop_buffered(s, d[:, r], k, ch.D, ch.convention, span, P0)
            assert np.allclose(P[:, :, r], ref, rtol=1e-9, atol=1e-12), (name, k, r)
            assert np.allclose(Pp[:, :, r], riccati.h(ref, s), rtol=1e-9, atol=1e-12), (name, k, r)  # P_{k+1|k}
    # one step only (the engine's usual case) gives the same matrices
    (k, P1), = est.covariances(s, tr, [T])
    assert k == T and np.array_equal(P1["filtered"], got[T]["filtered"])


@pytest.mark.parametrize("name", ["scalar", "vehicle_pairs", "bernoulli_2x2"])
def test_smart_sensor_covariances_equal_per_run_loop(name):
    s, ch, _ = CASES[name]
    est = SmartSensorEstimator(kind="smart_sensor")
    est.check(s, ch)
    T, runs = 14, 10
    tr = ch.sample_trace(np.random.default_rng(8), runs, T)
    d = tr.delay[0] if tr.delay is not None else np.where(tr.arrival[0], 0, LOST)
    got = dict(est.covariances(s, tr, [1, 4, T]))
    P0 = riccati.pbar(s)
    for k, out in got.items():
        P = out["filtered"]
        for r in range(runs):
            ref = _loop_smart(s, d[:, r], k, ch.D, ch.convention, P0)
            assert np.allclose(P[:, :, r], ref, rtol=1e-9, atol=1e-12), (name, k, r)


def _carried_G(s, k):
    """G_k carried forward from G_0 = [P_{0|0}] as smart_covariances did in every chunk before the history was
    kept (the reference of the kept SensorHistory, bit for bit)."""
    from netkf_cli.estimators.smart_sensor import _finite_or_inf
    from netkf_cli.linalg import kalman

    f = kalman.Filter.of(s, 1, "estimator.kind")
    Ps = initial_covariance(s)[:, :, None]
    G = Ps.copy()
    for _ in range(k):
        with np.errstate(over="ignore", invalid="ignore"):
            _, Ps = f.step(Ps, np.ones((1, 1), dtype=bool))
            G = _finite_or_inf(np.concatenate([Ps, kalman.predict(G, f.A, f.Q)], axis=2))
    return G


@pytest.mark.parametrize("s", [scalar_system(), vehicle_system(), _overflow_system()], ids=["scalar", "vehicle", "overflow"])
def test_smart_sensor_history_is_the_carried_recursion(s):
    """The G_k a process keeps per system (SensorHistory) are the per-chunk recursion's, bit for bit, whatever order
    the steps are asked in (a smaller step than the last restarts it), and every chunk reads the same matrices."""
    from netkf_cli.estimators.smart_sensor import SensorHistory, sensor_history

    h = SensorHistory(s)
    for k in (5, 9, 2, 9, 30, 1):
        assert np.array_equal(h.at(k), _carried_G(s, k), equal_nan=True), k
    assert sensor_history(s) is sensor_history(s) and not sensor_history(s).at(3).flags.writeable
    ch = poisson(3, 4)
    est = SmartSensorEstimator(kind="smart_sensor")
    tr = ch.sample_trace(np.random.default_rng(5), 30, 20)
    first, again = (dict(est.covariances(s, tr, [3, 20], ("filtered", "predicted"))) for _ in range(2))
    for k in (3, 20):
        for q in ("filtered", "predicted"):
            assert np.array_equal(first[k][q], again[k][q], equal_nan=True)


def _brute_smart(s, d, Dmax, k, P0):
    """P_{k|k} of the smart sensor by brute force, textbook formulas: the sensor's KF P^s_t from P0 with
    every measurement, N_k by scanning packets newest first, then N_k predictions."""
    A, C, Q, R = s.A, s.C, s.Q, s.R
    Ps = [P0]
    for _ in range(k):
        X = A @ Ps[-1] @ A.T + Q
        Ps.append(X - X @ C.T @ np.linalg.solve(C @ X @ C.T + R, C @ X))
    N = next((j for j in range(k) if d[k - j - 1] <= min(j, Dmax)), k)  # packet k − j has age j
    X = Ps[k - N]
    for _ in range(N):
        X = A @ X @ A.T + Q
    return X


@pytest.mark.parametrize("s", [scalar_system(), vehicle_system(),
                               LinearSystem.create([[1.1, 0.2], [0, 0.7]], [[1.0, 0.5]], np.eye(2) * 0.3, 0.4,
                                                   P0=np.diag([5.0, 2.0]))], ids=["scalar", "vehicle", "P0_set"])
def test_smart_sensor_equals_brute_force(s):
    """P_{k|k} = h^{N_k}(P^s_{k−N_k}) (P^s the sensor's own KF from P_{0|0}; no packet kept: h^k(P_{0|0}))
    and P_{k+1|k} = h(P_{k|k}) at every k, against the brute force above (relative 1e-12)."""
    ch = poisson(3, 4)
    T, runs = 25, 40
    tr = ch.sample_trace(np.random.default_rng(3), runs, T)
    got = dict(SmartSensorEstimator(kind="smart_sensor").covariances(s, tr, range(1, T + 1), ("filtered", "predicted")))
    P0 = initial_covariance(s)
    none_kept = 0
    for k in range(1, T + 1):
        for r in range(runs):
            X = _brute_smart(s, tr.delay[0, :, r], 4, k, P0)
            scale = np.abs(X).max()
            assert np.abs(got[k]["filtered"][:, :, r] - X).max() <= 1e-12 * scale, (k, r)
            Xp = s.A @ X @ s.A.T + s.Q
            assert np.abs(got[k]["predicted"][:, :, r] - Xp).max() <= 1e-12 * np.abs(Xp).max(), (k, r)
            none_kept += all(tr.delay[0, k - j - 1, r] > min(j, 4) for j in range(k))
    assert none_kept > 0  # the "no packet kept yet" branch was exercised (early k)


TRACES = {"bernoulli": bernoulli(0.6), "zero_delay_pmf": pmf([0.7], 3)}


@pytest.mark.parametrize("s", [scalar_system(), vehicle_system(), _dense_3x1()], ids=["scalar", "vehicle", "dense_3x1"])
@pytest.mark.parametrize("chname", list(TRACES))
@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_buffered_on_zero_delay_is_kf(s, chname, backend):
    """One filter, many names: on a pure-loss / zero-delay trace the time-k view is the arrival
    pattern, and buffered runs kalman.Filter — the same numbers as kf at every k (relative 1e-12),
    filtered and predicted, on either backend of the core (numpy: bitwise)."""
    tr = TRACES[chname].sample_trace(np.random.default_rng(4), 300, 40)
    ks = list(range(1, 41))
    if backend == "numba":
        pytest.importorskip("numba")
    ref = dict(KalmanFilterEstimator(kind="kf", backend=backend).covariances(s, tr, ks, ("filtered", "predicted")))
    est = BufferedEstimator(kind="buffered", packet="measurement", backend=backend)
    got = dict(est.covariances(s, tr, ks, ("filtered", "predicted")))
    for k in ks:
        for q in ("filtered", "predicted"):
            if backend == "numpy":
                assert np.array_equal(got[k][q], ref[k][q]), (k, q)
            assert np.abs(got[k][q] - ref[k][q]).max() <= 1e-12 * np.abs(ref[k][q]).max(), (k, q)
    for k in (1, 17, 40):  # one requested step (the compiled path under auto)
        (_, one), = est.covariances(s, tr, [k], ("filtered", "predicted"))
        for q in ("filtered", "predicted"):
            assert np.abs(one[q] - ref[k][q]).max() <= 1e-12 * np.abs(ref[k][q]).max(), (k, q)


def test_conventions_name_buffer_rule_packet_and_law():
    s = scalar_system()
    le = BufferedEstimator(kind="buffered").conventions(s, poisson(5, 10))
    lt = BufferedEstimator(kind="buffered").conventions(s, poisson(5, 10, "delay_lt_D"))
    assert le["buffer"] == "D = 10" and le["convention"].startswith("delay_le_D")
    assert lt["convention"].startswith("delay_lt_D") and le != lt
    assert le["packet"] == "y_k" and le["delay law"] == "Poisson d = 5"
    assert BufferedEstimator(kind="buffered").conventions(vehicle_system(), poisson(3, 5))["packet"] == "(y_k, y_k-1)"
    assert "estimate" in SmartSensorEstimator(kind="smart_sensor").conventions(s, poisson(5, 10))["packet"]


def test_any_C_simulates_with_measurement_packets():
    """Issue 12: n = 3, m = 1 (not Appendix B) — auto → measurement packets, check passes, P finite."""
    s = _dense_3x1()
    assert packet_span(s, "auto") == 1
    with pytest.raises(ConfigError):
        riccati.mbar(s)  # the bounds are unavailable, the simulation is not
    est = BufferedEstimator(kind="buffered")
    est.check(s, bernoulli(0.5))
    (_, P), = est.covariances(s, bernoulli(0.5).sample_trace(np.random.default_rng(0), 50, 40), [40])
    assert np.all(np.isfinite(P["filtered"]))


def test_check_refuses_an_unusable_backend(monkeypatch):
    from netkf_cli.linalg import kalman

    monkeypatch.setattr(kalman, "numba_available", lambda: False)
    s = scalar_system()
    BufferedEstimator(kind="buffered", backend="auto").check(s, bernoulli(0.5))  # falls back to numpy
    assert BufferedEstimator(kind="buffered", backend="auto").resolved_backend(s) == "numpy"
    with pytest.raises(ConfigError) as e:
        BufferedEstimator(kind="buffered", backend="numba").check(s, bernoulli(0.5))
    assert e.value.problems[0].path == "estimator.backend"


def test_numba_philox_is_no_longer_a_backend():
    from pydantic import ValidationError

    with pytest.raises(ValidationError):
        BufferedEstimator(kind="buffered", backend="numba_philox")


# --------------------------------------------------------------------------------------------
# overflow (issue 14.4): the core's one Rescue policy, the same P as kf
# --------------------------------------------------------------------------------------------


def _overflow_mc(H, n, ests):
    from netkf_cli import engine

    red = engine.DistributionReducer(np.array([2.0, 5.0, 10.0]), [H])
    return engine.simulate(_overflow_system(), bernoulli(0.05), ests, red, steps=[H], runs=n, horizon=H, seed=0,
                           chunk=10_000)


def test_overflow_system_monte_carlo_matches_exact_without_warnings():
    """A = diag(1e6, 0.5), C = I, γ = 0.05. P_k ≤ M·I (M ∈ {2, 5, 10}) iff y_k arrived: with it,
    P_k = g̃(·) ≤ M̄ = R = I and its second entry ≤ 1; without it, P_k,11 ≥ 1e12·… . So the exact
    probability is γ = 0.05 (also what delay_exact certifies). At k = 20 every prior is finite
    (P_11 ≤ 1e12^20 ≪ 1e308) and the Rescue's information-form update is exact. 5 s.e. of a proportion
    at p = 0.05, n = 20 000: 5·√(0.05·0.95/20000) = 0.0077. buffered and kf: the same counts."""
    n = 20_000
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no raw numpy warnings
        st = _overflow_mc(20, n, [BufferedEstimator(kind="buffered"), KalmanFilterEstimator(kind="kf")])
    p = st["count_0"][0] / n
    assert np.all(np.abs(p - 0.05) <= 5 * np.sqrt(0.05 * 0.95 / n))
    assert np.array_equal(st["count_0"], st["count_1"]) and st["nonfinite_0"][0] == 0


def test_overflow_system_recovers_after_an_overflowed_prior():
    """k = 120: most runs have met a gap of > 26 lost packets (P_11 overflowed to ∞); the exact answer is
    still 0.05: kalman.Rescue gives the unknown direction information 0 and recovers at the next arrival."""
    n = 10_000
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        st = _overflow_mc(120, n, [BufferedEstimator(kind="buffered")])
    p = st["count_0"][0] / n
    assert np.all(np.abs(p - 0.05) <= 5 * np.sqrt(0.05 * 0.95 / n))


@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_overflow_covariances_equal_kf(backend):
    """Through the generic contract, on one trace: buffered gives kf's P at k = 120 (bitwise with numpy;
    compiled: the runs the Rescue flags are the numpy core's, the others equal to rounding), including
    which runs are ∞. Runs whose last packet arrived and whose prior stayed finite have
    P_k = diag(≈1, the scalar recursion a = 0.5, q = r = 1)."""
    if backend == "numba":
        pytest.importorskip("numba")
    s = _overflow_system()
    tr = bernoulli(0.05).sample_trace(np.random.default_rng(2), 4000, 120)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        (k, out), = BufferedEstimator(kind="buffered", backend=backend).covariances(s, tr, [120], ("filtered", "predicted"))
        (_, ref), = KalmanFilterEstimator(kind="kf").covariances(s, tr, [120], ("filtered", "predicted"))
    for q in ("filtered", "predicted"):
        fin = np.isfinite(ref[q])
        assert np.array_equal(fin, np.isfinite(out[q])), q
        assert np.allclose(out[q][fin], ref[q][fin], rtol=1e-12, atol=0), q
    P = out["filtered"]
    got = tr.arrival[0, -1] & np.isfinite(P).all(axis=(0, 1))
    assert got.any()
    Pa = P[:, :, got]
    assert np.allclose(Pa[0, 0], 1.0, rtol=1e-9) and np.allclose(Pa[0, 1], 0.0, atol=1e-12)
    for r in np.flatnonzero(got)[:20]:
        x = riccati.pbar(s)[1, 1]
        for t in range(120):
            x = 0.25 * x + 1
            if tr.arrival[0, t, r]:
                x = x / (1 + x)
        assert P[1, 1, r] == pytest.approx(x, rel=1e-9)
    miss = ~tr.arrival[0, -1]
    lam = np.where(np.isfinite(P[0, 0, miss]), P[0, 0, miss], np.inf)
    assert np.all(lam > 1e10)


# --------------------------------------------------------------------------------------------
# bounded loops over the buffer length (issue 14.3)
# --------------------------------------------------------------------------------------------


def test_huge_buffer_is_linear():
    """D = 10⁶: the closed form, the updates kernel and the smart sensor on a trace finish in well under
    a second each (the former O(D²) loop never finished). Limits are generous for a loaded machine."""
    import time

    from netkf_cli.analysis import delay_exact as dx

    ch = poisson(5, 1_000_000)
    t = time.perf_counter()
    eu = dx.expected_updates(ch)
    tr = ch.sample_trace(np.random.default_rng(0), 2000, 60)
    st = {"sum": sum(float(r.sum()) for _, r in BufferedEstimator(kind="buffered").updates(scalar_system(), tr, [60]))}
    (_, out), = SmartSensorEstimator(kind="smart_sensor").covariances(scalar_system(), tr, [60])
    assert time.perf_counter() - t < 3.0
    # D → ∞ limit vs D = 40: Poisson(5) mass beyond 40 is < 1e-20
    assert eu == pytest.approx(dx.expected_updates(poisson(5, 40)), rel=1e-12)
    assert np.isfinite(st["sum"]) and np.isfinite(out["filtered"]).all()


def test_multi_sensor_channel_is_refused():
    from netkf_cli.channels.multi import MultiChannel

    ch = MultiChannel(kind="multi", sensors=3, loss=0.2)
    for est in (BufferedEstimator(kind="buffered"), SmartSensorEstimator(kind="smart_sensor")):
        with pytest.raises(ConfigError) as e:
            est.check(scalar_system(), ch)
        assert e.value.problems[0].path == "estimator.kind"


@pytest.mark.parametrize("name", ["scalar", "vehicle_pairs", "big_buffer_2x2", "bernoulli_2x2", "dense_3x1_measurement"])
def test_compiled_covariances_equal_numpy(name):
    """Backend numba: the core's compiled filter (kalman.Filter.run) over the time-k availabilities gives
    the numpy core's P_k to rounding (relative 1e-12), both quantities, one step and several."""
    pytest.importorskip("numba")
    s, ch, _ = CASES[name]
    tr = ch.sample_trace(np.random.default_rng(12), 700, 30)
    for k in (30, 17):
        (_, Pn), = BufferedEstimator(kind="buffered", backend="numpy").covariances(s, tr, [k], ("filtered", "predicted"))
        (_, Pc), = BufferedEstimator(kind="buffered", backend="numba").covariances(s, tr, [k], ("filtered", "predicted"))
        for q in Pn:
            assert np.abs(Pn[q] - Pc[q]).max() <= 1e-12 * np.abs(Pn[q]).max(), (name, k, q)
    several = [5, 17, 30]
    gn = dict(BufferedEstimator(kind="buffered", backend="numpy").covariances(s, tr, several))
    gc = dict(BufferedEstimator(kind="buffered", backend="numba").covariances(s, tr, several))
    for k in several:
        assert np.abs(gn[k]["filtered"] - gc[k]["filtered"]).max() <= 1e-12 * np.abs(gn[k]["filtered"]).max(), k


@pytest.mark.parametrize("ch", [poisson(5, 10), pmf([0.3, 0.2, 0.1], 2), poisson(0.01, 3), bernoulli(0.999)])
def test_bucketed_inverse_cdf_is_searchsorted(ch):
    """Exact, including u on and next to every breakpoint F(i) and u just below 1."""
    from netkf_cli.channels.delay import cdf_table, inverse_cdf

    tab = cdf_table(ch, 49)
    u = np.random.default_rng(0).random((50, 3000))
    edge = np.unique(np.concatenate([tab, np.nextafter(tab, 0), np.nextafter(tab, 1), [0.0, 1 - 2**-53]]))
    edge = edge[(edge >= 0) & (edge < 1)]
    u[0, :len(edge)] = edge
    ref = np.searchsorted(tab, u, side="right")
    assert np.array_equal(inverse_cdf(u, tab, compiled=False), ref)  # numpy path
    assert np.array_equal(inverse_cdf(u, tab), ref)  # default (numpy at this size)
    assert np.array_equal(inverse_cdf(u, tab, compiled=True), ref)  # compiled where numba imports
    assert inverse_cdf(u, tab, compiled=True).dtype == np.int32 == inverse_cdf(u, tab, compiled=False).dtype
    for compiled in (False, True):  # into a given array (delay_trace's rows), through the kept buckets again
        out = np.full(u.shape, -1, dtype=np.int32)
        assert inverse_cdf(u, tab, compiled=compiled, out=out) is out and np.array_equal(out, ref)


@pytest.mark.filterwarnings("ignore:buffered.*overflowed:UserWarning")  # the metric's one-line summary
def test_overflow_scenario_end_to_end(tmp_path):
    """Issue 14.4 through the scenario runner and the generic distribution metric: Monte Carlo within
    5 s.e. of the exact 0.05 (s.e. at p = 0.05, n = 4000: 0.0034), no numpy warning. Horizon 20: where
    the core's Rescue is exact (see test_overflow_system_recovers_after_an_overflowed_prior)."""
    import pandas as pd
    import yaml

    from netkf_cli.app.runner import run_scenario_file

    doc = {"name": "overflow", "system": {"A": [[1e6, 0], [0, 0.5]], "C": [[1, 0], [0, 1]], "Q": [[1, 0], [0, 1]],
                                          "R": [[1, 0], [0, 1]]},
           "channel": {"kind": "bernoulli", "arrival": 0.05}, "estimator": {"kind": "buffered"},
           "analysis": {"kind": "distribution", "M": [2, 5, 10]},
           "montecarlo": {"runs": 4000, "horizon": 20, "burn_in": 0, "seed": 0, "chunk": 2000}}
    p = tmp_path / "overflow.yaml"
    p.write_text(yaml.safe_dump(doc), encoding="utf-8")
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        out = run_scenario_file(p, out_dir=tmp_path / "out", force=True)
    t = pd.read_csv(out / "overflow.csv")
    mc = t[t.series == "monte_carlo"]
    assert len(mc) == 3
    assert np.all(np.abs(mc.value - 0.05) <= 5 * np.sqrt(0.05 * 0.95 / 4000))
    ex = t[t.series == "exact"]
    assert np.allclose(ex.value, 0.05, atol=1e-6)
