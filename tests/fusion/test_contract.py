"""The `multi` + `fusion` contract on the Kalman core (issue 19): one sensor model, one time base,
named quantities, MF = kf on the same sensors, one rescue policy, the stream check."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import yaml
from typer.testing import CliRunner

from netkf_cli import kalman
from netkf_cli.channels.multi import (MultiChannel, _raw_threshold, sample_multi_trace_arrivals, times_since_arrival,
                                      times_since_arrival_tr)
from netkf_cli.errors import ConfigError
from netkf_cli.estimators.fusion import FusionEstimator, FusionKernel, OLPEFTables, Sensors, identical_sensors
from netkf_cli.estimators.kf import KalmanFilterEstimator
from netkf_cli.riccati import initial_covariance
from netkf_cli.system import LinearSystem
from netkf_cli.trace import Trace

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
    ch = MultiChannel(kind="multi", sensors=3, loss=0.3)
    k = FusionKernel(identical_sensors(A2, C2, Q2, R2, 3), ch, ["mf", "ibf", "olpef"], horizon=30, burn_in=10)
    st = k(np.random.default_rng(0), 50)
    assert np.all(np.isfinite(st["sum"])) and not st["nonfinite"].any()
    legacy = FusionKernel(SYS2.A, SYS2.C, SYS2.Q, SYS2.R, None, ch, ["mf", "ibf", "olpef"], horizon=30, burn_in=10)
    st2 = legacy(np.random.default_rng(0), 50)
    for key in st:
        np.testing.assert_array_equal(st[key], st2[key])


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
    from netkf_cli.cli import app

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
