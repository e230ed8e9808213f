"""Channel/estimator contract (issue 12) for `multi` + `fusion`: traces, covariances, any state dimension."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg

from netkf_cli.analysis.fusion_bounds import p_m, phi_f
from netkf_cli.channels.multi import MultiChannel, times_since_arrival, times_since_arrival_tr
from netkf_cli.errors import ConfigError
from netkf_cli.estimators.fusion import (
    FusionEstimator,
    FusionKernel,
    OLPEFTables,
    fusion_averages_tr,
    fusion_run_averages,
    full_information_priors,
    ibf_covariances_at,
)
from netkf_cli.system import LinearSystem
from netkf_cli.trace import Trace

SYS2 = LinearSystem.create([[0.9, 0.2], [0.0, 0.7]], [[1.0, 0.5]], [[0.3, 0.05], [0.05, 0.2]], [[1.0]])


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


def _trace(N, loss, runs, T, seed=1):
    return MultiChannel(kind="multi", sensors=N, loss=loss).sample_trace(np.random.default_rng(seed), runs, T)


@pytest.mark.parametrize("strategy", ["mf", "ibf", "olpef"])
def test_perfect_channel_gives_the_centralized_steady_state(strategy):
    # loss 0: every strategy is the centralized KF with N sensors; started from P_m it stays at
    # Φ_f(P_m, N), the filtering DARE solution for (A, C, Q, R/N) — any state dimension.
    N = 4
    est = FusionEstimator(kind="fusion", strategies=[strategy])
    tr = _trace(N, 0.0, 5, 30)
    Pm = scipy.linalg.solve_discrete_are(SYS2.A.T, SYS2.C.T, SYS2.Q, SYS2.R / N)
    Pf_star = phi_f(Pm, np.float64(N), SYS2.C, SYS2.R)
    got = dict(est.covariances(SYS2, tr, [1, 10, 30]))
    assert sorted(got) == [1, 10, 30]
    for k, P in got.items():
        assert P.shape == (2, 2, 5)
        np.testing.assert_allclose(P, np.repeat(Pf_star[:, :, None], 5, axis=2), rtol=1e-9, atol=1e-12)


def test_mf_batched_equals_per_run_loop_vector_state():
    N, runs, T = 5, 6, 25
    tr = _trace(N, 0.6, runs, T, seed=4)
    got = dict(FusionEstimator(kind="fusion", strategies=["mf"]).covariances(SYS2, tr, range(1, T + 1)))
    P0 = p_m(SYS2.A, SYS2.C, SYS2.Q, SYS2.R, N)
    for r in range(runs):
        P = P0.copy()
        for t in range(T):
            ell = tr.arrival[:, t, r].sum()
            # eq. (7) literally: KF on the stacked received rows
            if ell:
                Cs = np.vstack([SYS2.C] * ell)
                S = Cs @ P @ Cs.T + np.kron(np.eye(ell), SYS2.R)
                Pf = P - P @ Cs.T @ np.linalg.solve(S, Cs @ P)
            else:
                Pf = P
            np.testing.assert_allclose(got[t + 1][:, :, r], Pf, rtol=1e-9, atol=1e-12)
            P = SYS2.A @ Pf @ SYS2.A.T + SYS2.Q


def test_ibf_and_olpef_matrices_match_their_traces():
    N, runs, T = 6, 40, 30
    tr = _trace(N, 0.5, runs, T, seed=2)
    tau = times_since_arrival_tr(tr.arrival)
    A, C, Q, R = SYS2.A, SYS2.C, SYS2.Q, SYS2.R
    P0 = p_m(A, C, Q, R, N)
    Pfull = full_information_priors(A, C, Q, R, N, P0, T)
    t = np.full(runs, T - 1)
    f_tr, p_tr = ibf_covariances_at(tau[T - 1], t, A, C, Q, R, Pfull)
    f_m, p_m_ = ibf_covariances_at(tau[T - 1], t, A, C, Q, R, Pfull, full=True)
    np.testing.assert_allclose(np.trace(f_m, axis1=1, axis2=2), f_tr, rtol=1e-12)
    tab = OLPEFTables(A, C, Q, R, N)
    E = tab.error_cov(tau[T - 1], t)
    np.testing.assert_allclose(np.trace(E, axis1=1, axis2=2), tab.error_trace(tau[T - 1], t), rtol=1e-10)
    assert np.all(np.linalg.eigvalsh(E) > -1e-12)
    # IBF ≤ MF path-wise (PSD order), from covariances()
    mf = dict(FusionEstimator(kind="fusion", strategies=["mf"]).covariances(SYS2, tr, [T]))[T]
    ibf = dict(FusionEstimator(kind="fusion", strategies=["ibf"]).covariances(SYS2, tr, [T]))[T]
    assert np.all(np.linalg.eigvalsh(np.moveaxis(mf - ibf, -1, 0)) >= -1e-12)


def test_trace_layout_averages_equal_the_legacy_layout():
    N, runs, T = 5, 30, 40
    tr = _trace(N, 0.4, runs, T, seed=7)
    legacy = fusion_run_averages(np.transpose(tr.arrival, (2, 1, 0)), 0.9, 1.0, 1e-2, 1.0, None, 10)
    new = fusion_averages_tr(tr.arrival, 0.9, 1.0, 1e-2, 1.0, None, 10)
    assert set(legacy) == set(new)
    for k in new:
        np.testing.assert_allclose(new[k], legacy[k], rtol=1e-12)


def test_vector_state_monte_carlo_runs():
    ch = MultiChannel(kind="multi", sensors=3, loss=0.3)
    k = FusionKernel(SYS2.A, SYS2.C, SYS2.Q, SYS2.R, None, ch, ["mf", "ibf", "olpef"], horizon=30, burn_in=10)
    st = k(np.random.default_rng(0), 50)
    assert np.all(np.isfinite(st["sum"])) and not st["nonfinite"].any()


def test_check_refuses_olpef_with_unstable_A():
    unstable = LinearSystem.create(1.2, 1.0, 1.0, 1.0)
    with pytest.raises(ConfigError, match="estimator.strategies"):
        FusionEstimator(kind="fusion", strategies=["olpef"]).check(unstable, None)
    FusionEstimator(kind="fusion", strategies=["mf", "ibf"]).check(unstable, None)  # fine


def test_estimator_declares_what_it_accepts():
    assert FusionEstimator.accepts == {"arrival"} and FusionEstimator.quantity == "P_{t|t}"
    with pytest.raises(ConfigError):
        list(FusionEstimator(kind="fusion").covariances(SYS2, Trace(runs=2, horizon=3, mode=np.zeros((3, 2), np.int8)), [1]))


@pytest.mark.parametrize("system", ["scalar", "vector"])
def test_ibf_grouping_by_reach_equals_one_pass(system):
    # ibf_covariances_at groups rows (≥ 2048) by how far back their recursion starts; every row's
    # recursion is row-wise, so the result must equal the single-pass core to round-off.
    from netkf_cli.estimators.fusion import _ibf_core

    A, C, Q, R = (SYS2.A, SYS2.C, SYS2.Q, SYS2.R) if system == "vector" else (0.9, 1.0, 1e-4, 1e-2)
    N, runs, T = 6, 700, 40
    tr = _trace(N, 0.6, runs, T, seed=11)
    tau = times_since_arrival_tr(tr.arrival)
    P0 = p_m(A, C, Q, R, N)
    Pfull = full_information_priors(A, C, Q, R, N, P0, T)
    tb = np.arange(30, 34)
    rows = tau[tb].reshape(-1, N)
    t = np.repeat(tb, runs)
    assert rows.shape[0] >= 2048
    for full in (False, True):
        a = ibf_covariances_at(rows, t, A, C, Q, R, Pfull, full=full)
        b = _ibf_core(rows, t, A, C, Q, R, Pfull, full=full)
        for x, y in zip(a, b):
            np.testing.assert_allclose(x, y, rtol=1e-12, atol=0)
