"""The `multi` + `fusion` contract on the Kalman core (issue 19): one sensor model, one time base,
named quantities, MF = kf on the same sensors, one rescue policy, the stream check."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import yaml
from typer.testing import CliRunner

from netkf_cli import engine
from netkf_cli.linalg import kalman, kalman_codegen
from netkf_cli.channels.multi import (MultiChannel, _raw_threshold, sample_multi_trace_arrivals, times_since_arrival,
                                      times_since_arrival_tr)
from netkf_cli.core.errors import ConfigError
from netkf_cli.estimators.fusion import FusionEstimator, OLPEFTables, Sensors, identical_sensors
from netkf_cli.estimators.kf import KalmanFilterEstimator
from netkf_cli.linalg.riccati import initial_covariance
from netkf_cli.core.system import LinearSystem
from netkf_cli.core.trace import Trace

A2, C2, Q2, R2 = [[0.9, 0.2], [0.0, 0.7]], [[1.0, 0.5]], [[0.3, 0.05], [0.05, 0.2]], [[1.0]]
SYS2 = LinearSystem.create(A2, C2, Q2, R2)
BOTH = ("filtered", "predicted")


def _trace(N, loss, runs, T, seed=1):
    return MultiChannel(kind="multi", sensors=N, loss=loss).sample_trace(np.random.default_rng(seed), runs, T)


def _all(est, system, trace, steps, qs=BOTH):
    return dict(est.covariances(system, trace, steps, qs))


def _rel(a, b):
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


# ---------------------------------------------------------------------------------------- channel


def test_multi_trace_layout_and_loss_rate():
    ch = MultiChannel(kind="multi", sensors=3, loss=[0.1, 0.5, 0.8])
    assert ch.trace_kinds == {"arrival"} and ch.loss_rate() == pytest.approx((0.1 + 0.5 + 0.8) / 3)
    R, T = 20000, 10
    tr = ch.sample_trace(np.random.default_rng(0), R, T)
    assert tr.arrival.shape == (3, T, R) and tr.arrival.dtype == bool and tr.kinds == {"arrival"}
    # each sensor's arrival frequency: binomial over R·T draws, 5 s.e.
    p = 1 - np.array([0.1, 0.5, 0.8])
    f = tr.arrival.mean(axis=(1, 2))
    assert np.all(np.abs(f - p) <= 5 * np.sqrt(p * (1 - p) / (R * T)))
    tau = times_since_arrival_tr(tr.arrival)
    np.testing.assert_array_equal(tau, np.transpose(times_since_arrival(np.transpose(tr.arrival, (2, 1, 0))), (1, 0, 2)))


def test_blocked_sampler_gives_the_bits_of_one_draw(monkeypatch):
    """The sampler draws in blocks of whole time steps (bounded memory): the same bits as one big draw."""
    import netkf_cli.channels.multi as multi

    loss = np.array([0.3, 0.0, 0.7, 1.0])
    rng = np.random.default_rng(3)
    raw = rng.bit_generator.random_raw(4 * 37 * 501).reshape(4, 37, 501)
    ref = raw < _raw_threshold(1 - loss)[:, None, None]
    ref[1] = True
    monkeypatch.setattr(multi, "RAW_BLOCK", 3 * 501 + 7)  # blocks of 3 steps, a ragged last block
    got = sample_multi_trace_arrivals(np.random.default_rng(3), 501, 37, loss)
    np.testing.assert_array_equal(got, ref)


# ---------------------------------------------------------------------------------------- one filter, many names


@pytest.mark.parametrize("N", [1, 4])
def test_mf_is_kf_on_the_stacked_sensors(N):
    """MF with N identical sensors (the count update) and kf on the stacked outputs (sequential updates):
    the same filter, relative 1e-12 at every k, both quantities."""
    s = identical_sensors(A2, C2, Q2, R2, N)
    tr = _trace(N, 0.4, 300, 40)
    kf = _all(KalmanFilterEstimator(kind="kf"), s, tr, range(1, 41))
    mf = _all(FusionEstimator(kind="fusion", strategies=["mf"]), s, tr, range(1, 41))
    assert sorted(mf) == list(range(1, 41))
    for k in kf:
        for q in BOTH:
            assert _rel(mf[k][q], kf[k][q]) <= 1e-12, (k, q)


def test_mf_is_kf_with_sensors_of_their_own():
    """A list of sensors with their own C_i, R_i (not identical): MF is the core's Filter itself."""
    Cs = np.array([[1.0, 0.0], [0.3, 1.0], [0.0, 2.0]])
    R = np.diag([0.5, 1.0, 2.0])
    s = LinearSystem.create(A2, Cs, Q2, R, sensors=[(0,), (1, 2)])
    assert not Sensors.of(s, 2).identical
    tr = _trace(2, [0.3, 0.6], 200, 25)
    kf = _all(KalmanFilterEstimator(kind="kf"), s, tr, [1, 2, 25])
    mf = _all(FusionEstimator(kind="fusion", strategies=["mf"]), s, tr, [1, 2, 25])
    for k in kf:
        for q in BOTH:
            np.testing.assert_array_equal(mf[k][q], kf[k][q])


def test_the_new_users_case_reads_the_streams_the_same_way():
    """The issue's report: C = I₂ on `multi` with 2 streams. kf and fusion MF now agree (each stream =
    one sensor = one output row: the system's sensors), and with `system.sensors: 2` (two sensors each
    measuring the whole C x) they agree as well, on a different, smaller error."""
    I2 = np.eye(2)
    rows = LinearSystem.create(A2, I2, Q2, I2)
    twice = identical_sensors(A2, I2, Q2, I2, 2)
    tr = _trace(2, 0.0, 50, 30)
    for s in (rows, twice):
        kf = _all(KalmanFilterEstimator(kind="kf"), s, tr, [30])[30]["filtered"]
        mf = _all(FusionEstimator(kind="fusion", strategies=["mf"]), s, tr, [30])[30]["filtered"]
        assert _rel(mf, kf) <= 1e-12
    a = _all(KalmanFilterEstimator(kind="kf"), rows, tr, [30])[30]["filtered"]
    b = _all(KalmanFilterEstimator(kind="kf"), twice, tr, [30])[30]["filtered"]
    assert np.trace(b[:, :, 0]) < np.trace(a[:, :, 0])


def test_time_base_k1_is_one_update_of_the_predicted_P0():
    """P0 = P_{0|0} (unset = P̄ of the stacked sensors); step k = 1 uses y_1 (trace step 0)."""
    N = 3
    s = identical_sensors(A2, C2, Q2, R2, N, P0=[[2.0, 0.1], [0.1, 1.5]])
    tr = _trace(N, 0.5, 20, 3)
    out = _all(FusionEstimator(kind="fusion", strategies=["mf"]), s, tr, [1])
    Pm = kalman.one(kalman.predict, s.P0, s.A, s.Q)
    for r in range(20):
        ell = int(tr.arrival[:, 0, r].sum())
        Cs, Rs = np.vstack([s.sensor(0)[0]] * ell), np.kron(np.eye(ell), R2)
        Pf = Pm - Pm @ Cs.T @ np.linalg.solve(Cs @ Pm @ Cs.T + Rs, Cs @ Pm) if ell else Pm
        np.testing.assert_allclose(out[1]["filtered"][:, :, r], Pf, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(out[1]["predicted"][:, :, r], s.A @ Pf @ s.A.T + s.Q, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(initial_covariance(identical_sensors(A2, C2, Q2, R2, N)),
                               kalman.one(kalman.update_counts, scipy.linalg.solve_discrete_are(
                                   SYS2.A.T, SYS2.C.T, SYS2.Q, SYS2.R / N), SYS2.C, SYS2.R, np.array([N])), rtol=1e-9)


@pytest.mark.parametrize("strategy", ["mf", "ibf", "olpef"])
def test_perfect_channel_gives_the_centralized_steady_state(strategy):
    # loss 0: every strategy is the centralized KF with N sensors; from P0 = P̄ it stays at P̄ = Φ_f(P_m, N).
    N = 4
    s = identical_sensors(A2, C2, Q2, R2, N)
    Pbar = initial_covariance(s)
    got = _all(FusionEstimator(kind="fusion", strategies=[strategy]), s, _trace(N, 0.0, 5, 30), [1, 10, 30])
    assert sorted(got) == [1, 10, 30]
    for k, Ps in got.items():
        assert Ps["filtered"].shape == (2, 2, 5)
        np.testing.assert_allclose(Ps["filtered"], np.repeat(Pbar[:, :, None], 5, axis=2), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(Ps["predicted"][:, :, 0], s.A @ Pbar @ s.A.T + s.Q, rtol=1e-9)


def test_update_counts_equals_sequential_updates():
    """kalman.update_counts (eq. (14)) = c sequential textbook updates, 1e-12; c = 1 is `update` bit for bit."""
    rng = np.random.default_rng(0)
    n, m, runs = 3, 2, 50
    X = rng.standard_normal((runs, n, n))
    P = np.moveaxis(X @ X.transpose(0, 2, 1) + 0.1 * np.eye(n), 0, -1)
    C = rng.standard_normal((m, n))
    R = np.array([[0.7, 0.2], [0.2, 0.4]])
    c = rng.integers(0, 7, runs)
    got = kalman.update_counts(P, C, R, c)
    for r in range(runs):
        ref = P[:, :, r]
        for _ in range(c[r]):  # the textbook update, per run
            ref = ref - ref @ C.T @ np.linalg.solve(C @ ref @ C.T + R, C @ ref)
        assert _rel(got[:, :, r], ref) <= 1e-12
    ones = np.ones(runs)
    np.testing.assert_array_equal(kalman.update_counts(P, C, R, ones), kalman.update(P, C, R, ones))
    np.testing.assert_array_equal(kalman.update_counts(P, C, R, 0 * ones), P)


def test_one_rescue_policy_huge_A():
    """A = diag(1e6, 0.5): the prior overflows the standard form; MF (count update + Rescue) and kf
    (sequential + Rescue) give the same P, finite and positive."""
    # C of full column rank: Rescue's limit is then RESCUE_RATIO·tr((CᵀR⁻¹C)⁻¹) and every prior of this
    # system is redone in information form (with a rank-deficient C the limit is 1e8·tr R and both forms
    # lose ~4 digits to cancellation, differently: see the issue-19 notes)
    s = identical_sensors([[1e6, 0.0], [0.0, 0.5]], np.eye(2), np.eye(2), np.eye(2), 3)
    tr = _trace(3, 0.3, 64, 12, seed=5)
    kf = _all(KalmanFilterEstimator(kind="kf"), s, tr, range(1, 13))
    mf = _all(FusionEstimator(kind="fusion", strategies=["mf"]), s, tr, range(1, 13))
    for k in kf:
        a, b = mf[k]["filtered"], kf[k]["filtered"]
        np.testing.assert_array_equal(np.isinf(a), np.isinf(b))
        fin = np.isfinite(b).all(axis=(0, 1))
        assert _rel(a[:, :, fin], b[:, :, fin]) <= 1e-9


# ---------------------------------------------------------------------------------------- IBF, OLPEF


def test_ibf_and_olpef_matrices_match_their_traces():
    N, runs, T = 6, 40, 30
    s = identical_sensors(A2, C2, Q2, R2, N)
    tr = _trace(N, 0.5, runs, T, seed=2)
    tau = times_since_arrival_tr(tr.arrival)
    tab = OLPEFTables(s.A, C2, s.Q, R2, N)
    t = np.full(runs, T - 1)
    E = tab.error_cov(tau[T - 1], t)
    np.testing.assert_allclose(np.trace(E, axis1=1, axis2=2), tab.error_trace(tau[T - 1], t), rtol=1e-10)
    assert np.all(np.linalg.eigvalsh(E) > -1e-12)
    ol = _all(FusionEstimator(kind="fusion", strategies=["olpef"]), s, tr, [T])[T]
    np.testing.assert_allclose(np.moveaxis(ol["filtered"], -1, 0), E, rtol=1e-12)
    # IBF ≤ MF path-wise (PSD order), both quantities
    mf = _all(FusionEstimator(kind="fusion", strategies=["mf"]), s, tr, [T])[T]
    ibf = _all(FusionEstimator(kind="fusion", strategies=["ibf"]), s, tr, [T])[T]
    for q in BOTH:
        assert np.all(np.linalg.eigvalsh(np.moveaxis(mf[q] - ibf[q], -1, 0)) >= -1e-12)


@pytest.mark.parametrize("scalar", [True, False])
def test_ibf_grouping_by_reach_equals_one_pass(scalar):
    # IBF groups runs (≥ 2048) by how far back their recursion starts; each run's recursion is its own,
    # so the grouped result equals the single pass to round-off.
    from netkf_cli.estimators.fusion import IBF

    A, C, Q, R = (A2, C2, Q2, R2) if not scalar else (0.9, 1.0, 1e-4, 1e-2)
    N, runs, T = 6, 2100, 40
    s = identical_sensors(A, C, Q, R, N)
    tr = _trace(N, 0.6, runs, T, seed=11)
    tau = np.ascontiguousarray(np.moveaxis(times_since_arrival_tr(tr.arrival)[T - 1], -1, 0))  # (N, runs)
    ibf = IBF(Sensors.of(s, N), initial_covariance(s))
    a = ibf.at(tau, T - 1)
    b = ibf._core(tau, T - 1, int(np.minimum(tau.max(axis=0), T).max()))
    np.testing.assert_allclose(a, b, rtol=1e-12, atol=0)


def test_ibf_with_sensors_of_their_own_is_at_least_as_good_as_mf():
    Cs = np.array([[1.0, 0.0], [0.3, 1.0], [0.0, 2.0]])
    s = LinearSystem.create(A2, Cs, Q2, np.diag([0.5, 1.0, 2.0]), sensors=[(0,), (1,), (2,)])
    tr = _trace(3, [0.3, 0.6, 0.5], 100, 20)
    mf = _all(FusionEstimator(kind="fusion", strategies=["mf"]), s, tr, [20])[20]["filtered"]
    ibf = _all(FusionEstimator(kind="fusion", strategies=["ibf"]), s, tr, [20])[20]["filtered"]
    assert np.all(np.linalg.eigvalsh(np.moveaxis(mf - ibf, -1, 0)) >= -1e-12)


def test_vector_state_monte_carlo_runs():
    # the three strategies on a 2-state system through the generic engine (identical sensors on a multi channel)
    ch = MultiChannel(kind="multi", sensors=3, loss=0.3)
    steps = list(range(11, 31))
    ests = [FusionEstimator(kind="fusion", strategies=[s]) for s in ("mf", "ibf", "olpef")]
    st = engine.simulate(identical_sensors(A2, C2, Q2, R2, 3), ch, ests, engine.StationaryReducer(steps), steps=steps,
                         runs=50, horizon=30, seed=0, chunk=50)
    for j in range(3):
        assert st[f"nonfinite_{j}"] == 0 and np.isfinite(st[f"sum_avg_{j}"]) and st[f"max_nsteps_{j}"] == 20


# ---------------------------------------------------------------------------------------- checks


def test_check_refuses_olpef_with_unstable_A_or_different_sensors():
    unstable = LinearSystem.create(1.2, 1.0, 1.0, 1.0)
    with pytest.raises(ConfigError, match="estimator.strategies"):
        FusionEstimator(kind="fusion", strategies=["olpef"]).check(unstable, None)
    FusionEstimator(kind="fusion", strategies=["mf", "ibf"]).check(unstable, None)  # fine
    own = LinearSystem.create(A2, [[1.0, 0.0], [0.0, 1.0]], Q2, np.diag([1.0, 2.0]))
    with pytest.raises(ConfigError, match="identical"):
        FusionEstimator(kind="fusion", strategies=["olpef"]).check(own, MultiChannel(kind="multi", sensors=2, loss=0.1))


def test_stream_count_must_be_the_systems_sensors():
    one = LinearSystem.create(0.9, 1.0, 1.0, 1.0)
    ch = MultiChannel(kind="multi", sensors=25, loss=0.5)
    for est in (FusionEstimator(kind="fusion"), KalmanFilterEstimator(kind="kf")):
        with pytest.raises(ConfigError, match="system.sensors: 25"):
            est.check(one, ch)
        est.check(identical_sensors(0.9, 1.0, 1.0, 1.0, 25), ch)  # fine


def test_netkf_validate_refuses_a_multi_channel_without_the_sensors(tmp_path):
    from netkf_cli.app.cli import app

    doc = {"name": "multi_check", "system": {"A": 0.9, "C": 1, "Q": 1, "R": 1},
           "channel": {"kind": "multi", "sensors": 2, "loss": 0.0},
           "estimators": [{"kind": "kf"}, {"kind": "fusion", "strategies": ["mf"]}],
           "analysis": {"kind": "mean_vs_time"}, "montecarlo": {"runs": 10, "horizon": 5}}
    p = tmp_path / "s.yaml"
    p.write_text(yaml.safe_dump(doc), encoding="utf-8")
    res = CliRunner().invoke(app, ["validate", str(p)])
    assert res.exit_code == 1, res.output
    assert "estimators[0]" in res.output and "estimators[1]" in res.output and "system.sensors: 2" in res.output
    doc["system"]["sensors"] = 2
    p.write_text(yaml.safe_dump(doc), encoding="utf-8")
    res = CliRunner().invoke(app, ["validate", str(p)])
    assert res.exit_code == 0, res.output


def test_estimator_declares_what_it_reports():
    assert FusionEstimator.accepts == {"arrival"} and FusionEstimator.quantities == BOTH
    with pytest.raises(ConfigError):
        list(FusionEstimator(kind="fusion").covariances(SYS2, Trace(runs=2, horizon=3, mode=np.zeros((3, 2), np.int8)), [1]))
    with pytest.raises(ConfigError, match="smoothed"):
        list(FusionEstimator(kind="fusion").covariances(SYS2, _trace(1, 0.1, 2, 3), [1], ("smoothed",)))


# ---------------------------------------------------------------------------------------- speed paths (issue 20)

import scipy.stats  # noqa: E402

from netkf_cli.channels.multi import CountTrace, arrivals_given_counts, count_tables, sample_counts  # noqa: E402


def _z(x, mean, var, n):
    return abs(x - mean) / np.sqrt(var / n)


@pytest.mark.parametrize("N, loss", [(25, 0.5), (25, 0.3), (7, 0.9), (300, 0.4)])
def test_count_sampler_is_the_exact_inverse_cdf_and_binomial(N, loss):
    """The table lookup gives the exact inverse-CDF count (= searchsorted on the thresholds) for every
    draw, including draws next to every threshold; the counts' pmf is Binomial(N, 1 − loss) within
    5 s.e. per value."""
    thr, cell = count_tables(N, 1.0 - loss)
    raw = np.random.default_rng(5).bit_generator.random_raw(200_000)
    edges = np.concatenate([thr, thr - np.uint64(1), thr + np.uint64(1)])
    rng = np.random.default_rng(0)
    R, T = 4000, 50
    c = sample_counts(rng, R, T, N, loss)
    assert c.shape == (T, R)
    # the same bits through the exact search
    ref_raw = np.random.default_rng(0).bit_generator.random_raw(R * T)
    np.testing.assert_array_equal(c.ravel(), np.searchsorted(thr, ref_raw, side="right"))
    if N < 255:
        for r in (raw, edges):
            got = cell[r >> np.uint64(48)].astype(np.int64)
            exact = np.searchsorted(thr, r, side="right")
            amb = got == 255
            np.testing.assert_array_equal(got[~amb], exact[~amb])
    p = 1.0 - loss
    pmf = scipy.stats.binom.pmf(np.arange(N + 1), N, p)
    f = np.bincount(c.ravel(), minlength=N + 1) / c.size
    ok = pmf * c.size > 20
    assert np.all(np.abs(f - pmf)[ok] <= 5 * np.sqrt(pmf * (1 - pmf) / c.size)[ok])
    assert _z(c.mean(), N * p, N * p * (1 - p), c.size) < 5


def test_count_sampler_extremes_and_common_random_numbers():
    for loss, want in ((0.0, 6), (1.0, 0)):
        tr = MultiChannel(kind="multi", sensors=6, loss=loss, sampling="counts").sample_trace(np.random.default_rng(1), 50, 9)
        assert (tr.counts == want).all() and (tr.arrival.sum(axis=0) == want).all()
    lo = sample_counts(np.random.default_rng(3), 1000, 20, 25, 0.6)
    hi = sample_counts(np.random.default_rng(3), 1000, 20, 25, 0.4)
    assert (hi >= lo).all()  # monotone in the loss on one stream
    with pytest.raises(ValueError, match="one loss for every sensor"):
        MultiChannel(kind="multi", sensors=2, loss=[0.1, 0.2], sampling="counts")


def test_pattern_given_counts_is_independent_bernoulli():
    """Given ℓ ~ Binomial(N, p), the uniform subset is N independent Bernoulli(p): each sensor's rate
    p, each pair's correlation 0 and the sensors' lag-0 joint rate p², within 5 s.e."""
    N, loss, R, T = 12, 0.35, 5000, 20
    tr = MultiChannel(kind="multi", sensors=N, loss=loss, sampling="counts").sample_trace(np.random.default_rng(2), R, T)
    assert isinstance(tr, CountTrace) and not tr.materialized and tr.kinds == {"arrival"} and tr.sensors == N
    a = tr.arrival
    assert tr.materialized and a.shape == (N, T, R) and a is tr.arrival
    np.testing.assert_array_equal(a.sum(axis=0), tr.counts)
    p, n = 1 - loss, R * T
    assert np.all(_z(a.mean(axis=(1, 2)), p, p * (1 - p), n) < 5)
    for i, j in ((0, 1), (0, N - 1), (5, 6)):
        both = (a[i] & a[j]).mean()
        assert _z(both, p * p, p * p * (1 - p * p), n) < 5
    # the pattern is drawn from the seed, so it is reproducible
    tr2 = MultiChannel(kind="multi", sensors=N, loss=loss, sampling="counts").sample_trace(np.random.default_rng(2), R, T)
    np.testing.assert_array_equal(tr2.arrival, a)
    g = arrivals_given_counts(np.random.default_rng(0), np.full((3, 4), N, dtype=np.uint8), N)
    assert g.all()


def test_mf_reads_only_the_counts_and_equals_the_per_sensor_path():
    """MF on a CountTrace never draws the pattern; on the same pattern given explicitly it gives the same P
    (the count update either way; the per-sensor path sums the pattern)."""
    N = 9
    system = identical_sensors(A2, C2, Q2, R2, N)
    ch = MultiChannel(kind="multi", sensors=N, loss=0.45, sampling="counts")
    tr = ch.sample_trace(np.random.default_rng(4), 700, 30)
    est = FusionEstimator(kind="fusion", strategies=["mf"], backend="numpy")
    got = _all(est, system, tr, range(1, 31))
    assert not tr.materialized
    ref = _all(est, system, Trace(runs=700, horizon=30, arrival=tr.arrival), range(1, 31))
    for k in got:
        for q in BOTH:
            np.testing.assert_array_equal(got[k][q], ref[k][q])


def test_count_rescue_equals_the_per_sensor_rescue():
    """A = 10⁶: every prior is flagged; the count-form Rescue (information c·C1ᵀR1⁻¹C1) equals the
    Filter's Rescue on the arrived rows to rounding."""
    N = 4
    system = identical_sensors([[1e6, 0], [0, 0.5]], [[1.0, 1.0]], np.eye(2), [[1.0]], N)
    sens = Sensors.of(system, N)
    tr = _trace(N, 0.5, 400, 6, seed=7)
    P = np.repeat(np.eye(2)[:, :, None], 400, axis=2)
    for t in range(6):
        Pm = kalman.predict(P, sens.filt.A, sens.filt.Q)
        a = sens.correct(Pm, tr.arrival[:, t])
        b = sens.correct_counts(Pm, tr.arrival[:, t].sum(axis=0))
        fin = np.isfinite(a)
        np.testing.assert_array_equal(fin, np.isfinite(b))
        np.testing.assert_allclose(b[fin], a[fin], rtol=1e-9, atol=1e-12)
        P = a


def _time_avg(system, ch, strategy, runs, T, burn, seed, backend="numpy"):
    est = FusionEstimator(kind="fusion", strategies=[strategy], backend=backend)
    tr = ch.sample_trace(np.random.default_rng(seed), runs, T)
    acc = np.zeros(runs)
    for _, P in est.covariances(system, tr, range(burn + 1, T + 1), ("filtered",)):
        acc += np.trace(P["filtered"])
    return acc / (T - burn)


@pytest.mark.parametrize("strategy", ["mf", "ibf", "olpef"])
def test_byte_sampler_agrees_with_the_per_sensor_sampler(strategy):
    """sampling: bytes (another stream, the same law): time-averaged tr P within 5 combined s.e., at a loss
    whose 256·p is not an integer (the byte ties resolved by fresh draws matter)."""
    N, runs, T, burn = 10, 3000, 40, 20
    system = identical_sensors(A2, C2, Q2, R2, N)
    x = _time_avg(system, MultiChannel(kind="multi", sensors=N, loss=0.6037), strategy, runs, T, burn, 11)
    y = _time_avg(system, MultiChannel(kind="multi", sensors=N, loss=0.6037, sampling="bytes"), strategy, runs, T, burn, 12)
    se = np.sqrt(x.var(ddof=1) / runs + y.var(ddof=1) / runs)
    assert abs(x.mean() - y.mean()) < 5 * se, (x.mean(), y.mean(), se)


def test_byte_sampler_has_the_exact_law_and_reads_the_same_bits_in_any_blocks(monkeypatch):
    """sampling: bytes: each sensor's arrival frequency within 5 s.e. of 1 − loss (p = 1 and p = 0 exactly,
    non-dyadic p through the tie draws), no correlation between neighbouring sensors or steps beyond 5 s.e.;
    blocks of any size give the bits of the whole trace, and the parent stream continues past both ranges."""
    from netkf_cli.channels import multi
    from netkf_cli.channels.multi import ByteTrace

    loss = [0.0, 1.0, 0.5, 0.3, 0.123456789, 0.999, 0.6037]
    N, R, T = len(loss), 4000, 60
    ch = MultiChannel(kind="multi", sensors=N, loss=loss, sampling="bytes")
    rng = np.random.default_rng(21)
    tr = ch.sample_trace(rng, R, T)
    after = rng.bit_generator.random_raw(2)
    ref = np.random.default_rng(21).bit_generator
    ref.advance(ByteTrace.raw_draws(N, T, R) + N * T * R)
    np.testing.assert_array_equal(after, ref.random_raw(2))
    a = tr.arrival
    p = 1 - np.asarray(loss)
    freq = a.mean(axis=(1, 2))
    se = np.sqrt(p * (1 - p) / (T * R))
    assert freq[0] == 1.0 and freq[1] == 0.0
    assert np.all(np.abs(freq - p)[2:] < 5 * se[2:]), (freq, p, se)
    x = a[2:].astype(float)  # neighbouring sensors and steps: centred products have mean 0
    c = x - p[2:, None, None]
    for prod in ((c[1:] * c[:-1]).ravel(), (c[:, 1:] * c[:, :-1]).ravel()):
        assert abs(prod.mean()) < 5 * prod.std() / np.sqrt(prod.size)
    monkeypatch.setattr(multi, "MATERIALIZE_MAX", 0)
    lazy = ch.sample_trace(np.random.default_rng(21), R, T)
    for t0, t1 in ((0, 1), (1, 7), (7, 60), (13, 41)):
        np.testing.assert_array_equal(lazy.steps(t0, t1), a[:, t0:t1])
    assert not lazy.materialized
    odd = MultiChannel(kind="multi", sensors=3, loss=0.37, sampling="bytes")  # N·R not a multiple of 8
    whole = odd.sample_trace(np.random.default_rng(2), 333, 11).arrival
    part = odd.sample_trace(np.random.default_rng(2), 333, 11)
    np.testing.assert_array_equal(np.concatenate([part.steps(0, 3), part.steps(3, 4), part.steps(4, 11)], axis=1), whole)


@pytest.mark.parametrize("strategy", ["mf", "ibf", "olpef"])
def test_count_sampler_agrees_with_the_per_sensor_sampler(strategy):
    """The changed sampler (another stream, the same law): time-averaged tr P within 5 combined s.e."""
    N, runs, T, burn = 10, 3000, 40, 20
    system = identical_sensors(A2, C2, Q2, R2, N)
    x = _time_avg(system, MultiChannel(kind="multi", sensors=N, loss=0.6), strategy, runs, T, burn, 11)
    y = _time_avg(system, MultiChannel(kind="multi", sensors=N, loss=0.6, sampling="counts"), strategy, runs, T, burn, 12)
    se = np.sqrt(x.var(ddof=1) / runs + y.var(ddof=1) / runs)
    assert abs(x.mean() - y.mean()) < 5 * se, (x.mean(), y.mean(), se)


needs_numba = pytest.mark.skipif(not kalman.numba_available(), reason="numba not installed")


@needs_numba
@pytest.mark.parametrize("name", ["scalar", "2-state", "vehicle", "3-rows", "huge-A"])
def test_compiled_mf_equals_numpy_on_the_same_counts(name):
    """The generated count-update kernel (kalman_codegen.source_counts) gives numpy's P to rounding on the
    same trace, every reported step and quantity; flagged runs (A = 10⁶) go through the numpy Rescue."""
    Av = [[1, 0, 0.5, 0], [0, 1, 0, 0.5], [0, 0, 1, 0], [0, 0, 0, 1.0]]
    cases = {
        "scalar": (0.9, 1.0, 1e-3, 10.0),
        "2-state": (A2, C2, Q2, R2),
        "vehicle": (Av, np.hstack([np.eye(2), np.zeros((2, 2))]), 0.01 * np.eye(4), 0.001 * np.eye(2)),
        "3-rows": ([[0.9, 0.2, 0], [0, 0.7, 0.1], [0, 0, 0.5]], np.eye(3), 0.1 * np.eye(3),
                   [[1.0, 0.2, 0], [0.2, 1.0, 0.1], [0, 0.1, 1.0]]),
        "huge-A": ([[1e6, 0], [0, 0.5]], [[1.0, 1.0]], np.eye(2), [[1.0]]),
    }
    A, C, Q, R = cases[name]
    N = 6
    system = identical_sensors(A, C, Q, R, N)
    tr = MultiChannel(kind="multi", sensors=N, loss=0.5, sampling="counts").sample_trace(np.random.default_rng(8), 900, 25)
    steps = [1, 2, 7, 8, 20, 25]
    a = _all(FusionEstimator(kind="fusion", strategies=["mf"], backend="numpy"), system, tr, steps)
    b = _all(FusionEstimator(kind="fusion", strategies=["mf"], backend="numba"), system, tr, steps)
    for k in steps:
        for q in BOTH:
            fin = np.isfinite(a[k][q])
            np.testing.assert_array_equal(fin, np.isfinite(b[k][q]))
            np.testing.assert_allclose(b[k][q][fin], a[k][q][fin], rtol=1e-9, atol=1e-12 * np.abs(a[k][q][fin]).max())


@needs_numba
def test_auto_picks_the_compiled_kernels_when_numba_is_present_and_numpy_when_hidden(monkeypatch):
    N = 25
    system = identical_sensors(0.9, 1.0, 1e-3, 10.0, N)
    ch = MultiChannel(kind="multi", sensors=N, loss=0.5, sampling="counts")
    est = FusionEstimator(kind="fusion", strategies=["mf"])
    assert est.backend_used(system, ch, 20_000, 200) == "numba"
    assert est.backend_used(system, ch, 100, 10) == "numpy"  # small chunks: not worth a compile
    assert FusionEstimator(kind="fusion", strategies=["ibf"]).backend_used(system, ch, 20_000, 200) == "numba"
    assert FusionEstimator(kind="fusion", strategies=["olpef"], backend="numpy").backend_used(system, ch, 20_000, 200) == "numpy"
    monkeypatch.setattr(kalman, "numba_available", lambda: False)
    assert est.backend_used(system, ch, 20_000, 200) == "numpy"
    with pytest.raises(ConfigError, match="numba"):
        FusionEstimator(kind="fusion", strategies=["mf"], backend="numba").backend_used(system, ch, 20_000, 200)


@needs_numba
@pytest.mark.parametrize("strategy, name", [("ibf", "scalar"), ("ibf", "2-state"), ("ibf", "vehicle"), ("ibf", "huge-A"),
                                            ("olpef", "scalar"), ("olpef", "2-state"), ("olpef", "vehicle")])
def test_compiled_ibf_and_olpef_equal_numpy_on_the_same_trace(strategy, name):
    """kalman_codegen.source_ibf / source_olpef = the numpy IBF / OLPEFTables to rounding on one trace, at
    every reported step (long gaps: loss 0.8 and a horizon past OLPEF's first 16 lags; A = 10⁶ flags
    every IBF run, redone on the numpy IBF)."""
    Av = 0.95 * np.array([[1, 0, 0.5, 0], [0, 1, 0, 0.5], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    cases = {"scalar": (0.9, 1.0, 1e-3, 10.0), "2-state": (A2, C2, Q2, R2),
             "vehicle": (Av, np.hstack([np.eye(2), np.zeros((2, 2))]), 0.01 * np.eye(4), 0.001 * np.eye(2)),
             "huge-A": ([[1e6, 0], [0, 0.5]], [[1.0, 1.0]], np.eye(2), [[1.0]])}
    A, C, Q, R = cases[name]
    N, runs, T = 5, 600, 40
    system = identical_sensors(A, C, Q, R, N)
    tr = _trace(N, 0.8, runs, T, seed=9)
    steps = [1, 2, 3, 10, 11, 25, 39, 40]
    a = _all(FusionEstimator(kind="fusion", strategies=[strategy], backend="numpy"), system, tr, steps)
    b = _all(FusionEstimator(kind="fusion", strategies=[strategy], backend="numba"), system, tr, steps)
    for k in steps:
        for q in BOTH:
            fin = np.isfinite(a[k][q])
            np.testing.assert_array_equal(fin, np.isfinite(b[k][q]))
            np.testing.assert_allclose(b[k][q][fin], a[k][q][fin], rtol=1e-9, atol=1e-12 * np.abs(a[k][q][fin]).max())


def test_lazy_per_sensor_trace_is_the_eager_sampler_bit_for_bit(monkeypatch):
    """sampling: per_sensor draws lazily (SensorTrace): its blocks, counts and whole arrival equal the eager
    sampler's bits, and the parent stream continues exactly where the eager sampler leaves it."""
    from netkf_cli.channels import multi
    from netkf_cli.channels.multi import SensorTrace

    monkeypatch.setattr(multi, "RAW_BLOCK", 3 * 301 + 5)
    monkeypatch.setattr(multi, "MATERIALIZE_MAX", 0)  # lazy at every size
    loss = np.array([0.0, 0.3, 0.7, 1.0, 0.5])
    ch = MultiChannel(kind="multi", sensors=5, loss=loss.tolist())
    rng = np.random.default_rng(np.random.SeedSequence(4, spawn_key=(0, 2)))
    tr = ch.sample_trace(rng, 301, 23)
    after = rng.bit_generator.random_raw(4)
    rng2 = np.random.default_rng(np.random.SeedSequence(4, spawn_key=(0, 2)))
    ref = sample_multi_trace_arrivals(rng2, 301, 23, loss)
    np.testing.assert_array_equal(after, rng2.bit_generator.random_raw(4))
    assert isinstance(tr, SensorTrace) and tr.sensors == 5 and tr.kinds == {"arrival"}
    np.testing.assert_array_equal(tr.steps(4, 11), ref[:, 4:11])
    np.testing.assert_array_equal(tr.counts, ref.sum(axis=0))
    assert not tr.materialized
    np.testing.assert_array_equal(tr.arrival, ref)
    assert tr.materialized


@pytest.mark.parametrize("strategy, backend", [("ibf", "numpy"), ("olpef", "numpy"),
                                               pytest.param("ibf", "numba", marks=needs_numba),
                                               pytest.param("olpef", "numba", marks=needs_numba),
                                               pytest.param("mf", "numba", marks=needs_numba)])
def test_blocked_reading_of_a_lazy_trace_equals_the_whole_trace(monkeypatch, strategy, backend):
    """IBF / OLPEF / MF read a lazy trace in blocks of a few steps (block edges between reported steps, and
    reported steps several blocks apart) and give what they give on the materialised trace."""
    from netkf_cli.channels import multi

    N, runs, T = 6, 250, 30
    monkeypatch.setattr(multi, "RAW_BLOCK", 4 * runs * N)  # blocks of 4 steps
    monkeypatch.setattr(multi, "MATERIALIZE_MAX", 0)  # lazy at every size
    assert multi.block_steps(T, runs, N) == 4
    system = identical_sensors(A2, C2, Q2, R2, N)
    steps = [1, 2, 3, 5, 6, 7, 8, 9, 19, 30]
    est = FusionEstimator(kind="fusion", strategies=[strategy], backend=backend)
    lazy = _trace(N, 0.6, runs, T, seed=5)
    got = _all(est, system, lazy, steps)
    assert not lazy.materialized or strategy == "mf"
    whole = Trace(runs=runs, horizon=T, arrival=_trace(N, 0.6, runs, T, seed=5).arrival)
    ref = _all(est, system, whole, steps)
    for k in steps:
        for q in BOTH:
            np.testing.assert_array_equal(got[k][q], ref[k][q])


def test_a_small_lazy_trace_is_drawn_once_on_first_read_with_the_same_bits(monkeypatch):
    """A SensorTrace of ≤ MATERIALIZE_MAX arrivals is materialised by its first block read (the estimators of
    a chunk share one draw); its bits are the eager sampler's and a larger trace stays lazy."""
    from netkf_cli.channels import multi

    loss = np.array([0.0, 0.3, 0.7, 1.0, 0.5])
    ch = MultiChannel(kind="multi", sensors=5, loss=loss.tolist())
    ref = sample_multi_trace_arrivals(np.random.default_rng(11), 301, 23, loss)
    monkeypatch.setattr(multi, "MATERIALIZE_MAX", 5 * 23 * 301)
    tr = ch.sample_trace(np.random.default_rng(11), 301, 23)
    np.testing.assert_array_equal(tr.steps(4, 11), ref[:, 4:11])
    assert tr.materialized
    np.testing.assert_array_equal(tr.arrival, ref)
    np.testing.assert_array_equal(tr.counts, ref.sum(axis=0))
    monkeypatch.setattr(multi, "MATERIALIZE_MAX", 5 * 23 * 301 - 1)
    tr = ch.sample_trace(np.random.default_rng(11), 301, 23)
    np.testing.assert_array_equal(tr.steps(4, 11), ref[:, 4:11])
    assert not tr.materialized


def test_small_traces_drawn_from_the_same_state_are_drawn_once_per_process(monkeypatch):
    """An over grid that leaves the channel alone draws chunk i's trace once per process (multi._DRAWN): the
    same state, loss and size give the same read-only array, and every chunk's trace of that loss is kept
    (Fusion Fig. 1: two chunks, 18 points over Q); another loss or size draws anew and evicts the others (a
    grid over the loss never reads them again); the bits are the eager sampler's either way; the kept traces
    stay within MATERIALIZE_MAX arrivals; the end of a run (montecarlo.execution) empties the store."""
    from netkf_cli.channels import multi
    from netkf_cli.runtime.montecarlo import _RUN_CACHES, execution

    monkeypatch.setattr(multi, "_DRAWN", {})
    monkeypatch.setattr("netkf_cli.runtime.montecarlo._RUN_CACHES", [*_RUN_CACHES, multi._DRAWN])
    ch = MultiChannel(kind="multi", sensors=5, loss=0.4)

    def rng(i):
        return np.random.default_rng(np.random.SeedSequence(3, spawn_key=(0, i)))

    with execution("serial"):
        a = ch.sample_trace(rng(1), 300, 20).arrival
        b = ch.sample_trace(rng(1), 300, 20).arrival
        assert b is a and not a.flags.writeable
        np.testing.assert_array_equal(a, sample_multi_trace_arrivals(rng(1), 300, 20, np.full(5, 0.4)))
        a2 = ch.sample_trace(rng(2), 300, 20).arrival  # the next chunk, the same loss: both kept
        assert len(multi._DRAWN) == 2 and ch.sample_trace(rng(1), 300, 20).arrival is a
        c = ch.with_loss(0.5).sample_trace(rng(1), 300, 20).arrival  # the grid moves the loss: the old ones go
        assert c is not a and len(multi._DRAWN) == 1
        np.testing.assert_array_equal(c, sample_multi_trace_arrivals(rng(1), 300, 20, np.full(5, 0.5)))
        d = ch.sample_trace(rng(2), 300, 20).arrival  # back to 0.4: drawn anew, the same bits
        assert d is not a2 and len(multi._DRAWN) == 1
        np.testing.assert_array_equal(d, a2)
        monkeypatch.setattr(multi, "MATERIALIZE_MAX", 2 * 5 * 20 * 300)
        ch.sample_trace(np.random.default_rng(9), 300, 20).arrival
        ch.sample_trace(np.random.default_rng(10), 300, 20).arrival
        ch.sample_trace(np.random.default_rng(11), 300, 20).arrival
        assert sum(x.size for x in multi._DRAWN.values()) <= multi.MATERIALIZE_MAX and multi._DRAWN
    assert multi._DRAWN == {}


@needs_numba
@pytest.mark.parametrize("name", ["scalar", "vehicle", "3-rows"])
def test_symbolic_kernels_give_the_bits_of_the_inlined_ones(name):
    """The fusion kernels read the system's numbers from a vector (kalman_codegen ``limit=None``: one compile
    per shape and zero / ±1 pattern, not per point of an ``over`` grid): the same bits as the kernels with the
    numbers inlined (the same expressions), MF's count update and IBF's evaluation."""
    Av = [[1, 0, 0.5, 0], [0, 1, 0, 0.5], [0, 0, 1, 0], [0, 0, 0, 1.0]]
    cases = {"scalar": (0.9, 1.0, 1e-3, 10.0),
             "vehicle": (Av, np.hstack([np.eye(2), np.zeros((2, 2))]), 0.01 * np.eye(4), 0.001 * np.eye(2)),
             "3-rows": ([[0.9, 0.2, 0], [0, 0.7, 0.1], [0, 0, 0.5]], np.eye(3), 0.1 * np.eye(3),
                        [[1.0, 0.2, 0], [0.2, 1.0, 0.1], [0, 0.1, 1.0]])}
    A, C, Q, R = (np.atleast_2d(np.asarray(x, dtype=float)) for x in cases[name])
    n, N, runs, T, lim = A.shape[0], 6, 300, 30, 1e12
    sv = kalman_codegen.system_vector(A, C, Q, R, lim)
    rng = np.random.default_rng(5)
    cnt = rng.integers(0, N + 1, size=(T, runs)).astype(np.uint8)
    P0 = kalman_codegen.pack(np.repeat(np.eye(n)[:, :, None], runs, axis=2))
    outs = []
    for k, extra in ((kalman_codegen.kernel_counts(A, C, Q, R, lim), ()), (kalman_codegen.kernel_counts(A, C, Q, R, None), (sv,))):
        P, flag = P0.copy(), np.zeros(runs, dtype=bool)
        k(P, cnt, 0, T, flag, *extra)
        outs.append((P, flag))
    np.testing.assert_array_equal(outs[0][0], outs[1][0])
    np.testing.assert_array_equal(outs[0][1], outs[1][1])
    arr = rng.random((N, T, runs)) < 0.4
    full = np.ascontiguousarray(np.repeat(P0[:, :1].T, T + 1, axis=0))
    outs = []
    for k, extra in ((kalman_codegen.kernel_ibf(A, C, Q, R, lim), ()), (kalman_codegen.kernel_ibf(A, C, Q, R, None), (sv,))):
        last, out, flag = np.full((N, runs), -1, dtype=np.int32), np.empty_like(P0), np.zeros(runs, dtype=bool)
        got = []
        for t0, t1 in ((0, 9), (9, 10), (10, T)):
            k(arr, 0, last, t0, t1, full, out, flag, np.zeros(T + 2, dtype=np.int64), *extra)
            got.append(out.copy())
        outs.append((np.array(got), flag))
    assert np.isfinite(outs[0][0]).all()
    np.testing.assert_array_equal(outs[0][0], outs[1][0])
    np.testing.assert_array_equal(outs[0][1], outs[1][1])


@needs_numba
def test_compiled_selection_sampler_gives_the_numpy_bits():
    counts = sample_counts(np.random.default_rng(1), 777, 31, 13, 0.45)
    a = arrivals_given_counts(np.random.default_rng(2), counts, 13, compiled=False)
    b = arrivals_given_counts(np.random.default_rng(2), counts, 13, compiled=True)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(b.sum(axis=0), counts)


@pytest.mark.parametrize("P0", [None, 5.0])
def test_ibf_full_information_table_stops_stepping_only_at_a_fixed_point(P0):
    # IBF._full repeats P_{j|j} once two consecutive ones are equal bit for bit; from P0 = P̄ (None) that is
    # at once, from P0 = 5 after a transient. The table equals stepping every j with the numpy core.
    from netkf_cli.estimators.fusion import IBF

    s = identical_sensors(0.9, 1.0, 1e-4, 1e-2, 6, P0)
    sens = Sensors.of(s, 6)
    table = IBF(sens, initial_covariance(s)).packed_full(120)
    ones = np.ones((6, 1), dtype=bool)
    P = np.asarray(initial_covariance(s), dtype=float)[:, :, None]
    for j in range(121):
        assert np.array_equal(table[j], kalman_codegen.pack(P)[:, 0]), j
        P = sens.step(P, ones)


def test_the_burst_probe_covers_one_sensors_update_and_mf_is_the_kf():
    """Two identical 2-row sensors (the coupled burst system of tests/unit/test_kalman_core): when only one arrives
    after a loss burst the filter updates its 2 rows alone, so the rescue limit is that sensor's burst limit (the
    probe with both sensors' 4 rows gave 1.5e6 against 2.7e4). Then the fusion centre's MF (the count form) and
    the kf (one sensor after the other) agree run by run to the accuracy the core promises (10 ε·RESCUE_RATIO,
    relative) through bursts of 6-16 steps ended by one sensor; before, they differed by up to 2 %."""
    from netkf_cli.core.system import LinearSystem
    from netkf_cli.core.trace import Trace
    from netkf_cli.core.tolerances import RESCUE_RATIO
    from netkf_cli.estimators.fusion import FusionEstimator
    from netkf_cli.estimators.kf import KalmanFilterEstimator

    from tests.burst_system import A, Q, C as C1, R as R1

    one = LinearSystem.create(A, C1, Q, R1)
    two = LinearSystem.create(A, np.vstack([C1, C1]), Q, scipy.linalg.block_diag(R1, R1), sensors=((0, 1), (2, 3)))
    assert kalman.Filter.of(two, 2).rescue.limit == kalman.Filter.of(one, 1).rescue.limit < 1e5
    Ls = np.arange(6, 17)
    K = 3 + Ls.max() + 4
    lost = (np.arange(K)[:, None] >= 3) & (np.arange(K)[:, None] < 3 + Ls[None, :])
    arr = np.stack([~lost, ~lost & (np.arange(K)[:, None] != 3 + Ls[None, :])])  # sensor 2 alone ends each burst
    trace = Trace(runs=Ls.size, horizon=K, arrival=arr, meta={})
    ks = range(1, K + 1)
    kf = dict(KalmanFilterEstimator(kind="kf", backend="numpy").covariances(two, trace, ks, ("filtered",)))
    mf = dict(FusionEstimator(kind="fusion", strategies=["mf"]).covariances(two, trace, ks, ("filtered",)))
    tol = 10 * np.finfo(float).eps * RESCUE_RATIO
    for k in ks:
        a, b = mf[k]["filtered"], kf[k]["filtered"]
        err = np.abs(a - b).max(axis=(0, 1)) / np.abs(b).max(axis=(0, 1))
        assert np.all(err <= tol), (k, float(err.max()))
