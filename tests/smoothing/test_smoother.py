"""The fixed-lag smoother under loss (eqs 3–4) against brute-force Gaussian conditioning and identities,
through the historical interface :func:`fixed_lag_smoother` (index t = measurement t, prior P0 = P_{0|−1};
on the core's time base index t is step t + 1)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st

from netkf_cli.linalg import riccati
from netkf_cli.analysis.smoothing import batch_posterior_covariance
from netkf_cli.estimators.smoother import fixed_lag_smoother
from netkf_cli.core.system import LinearSystem


def random_system(rng, n, m):
    A = rng.normal(size=(n, n)) * 0.8
    C = rng.normal(size=(m, n))
    Lq = rng.normal(size=(n, n)) * 0.5
    Lr = rng.normal(size=(m, m)) * 0.5
    Q = Lq @ Lq.T + 0.05 * np.eye(n)
    R = Lr @ Lr.T + 0.2 * np.eye(m)
    L0 = rng.normal(size=(n, n))
    return LinearSystem.create(A, C, Q, R, L0 @ L0.T + 0.1 * np.eye(n))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 3), m=st.integers(1, 3), lam=st.floats(0.2, 0.9))
def test_matches_batch_gaussian_conditioning(seed, n, m, lam):
    rng = np.random.default_rng(seed)
    s = random_system(rng, n, m)
    T, lag, runs = 9, 3, 2
    g = rng.random((runs, T)) < lam
    res = fixed_lag_smoother(s, g, lag, P0=s.P0)  # x_0 ~ N(·, P0), y_0 the first measurement
    for r in range(runs):
        for j, t in enumerate(res.times):
            ref = batch_posterior_covariance(s, g[r], t, t - 1, s.P0)
            scale = max(1.0, np.abs(ref).max())
            np.testing.assert_allclose(res.pred[j, :, :, r], ref, atol=1e-9 * scale, rtol=1e-8)
            for N in range(lag + 1):
                ref = batch_posterior_covariance(s, g[r], t, t + N, s.P0)
                np.testing.assert_allclose(res.smooth[j, N, :, :, r], ref, atol=1e-9 * scale, rtol=1e-8)


def test_lag0_is_the_filter_and_lags_are_nonincreasing():
    rng = np.random.default_rng(3)
    s = random_system(rng, 3, 2)
    g = rng.random((50, 40)) < 0.6
    res = fixed_lag_smoother(s, g, 4, P0=s.P0)
    # the filter recursion written independently with the spine's maps: P_{k|k} = g̃(P_{k|k-1}) if γ_k
    for r in range(0, 50, 7):
        P = s.P0
        for k in range(40 - 4):
            Pf = riccati.gtilde(P, s) if g[r, k] else P
            np.testing.assert_allclose(res.pred[k, :, :, r], P, rtol=1e-9, atol=1e-11)
            np.testing.assert_allclose(res.filt[k, :, :, r], Pf, rtol=1e-9, atol=1e-11)
            P = riccati.h(Pf, s)
    # P_{k|k-1} ≥ P_{k|k} ≥ P_{k|k+1} ≥ ... in the PSD order
    chain = [np.moveaxis(res.pred, -1, 1)] + [np.moveaxis(res.smooth[:, N], -1, 1) for N in range(5)]
    for a, b in zip(chain[:-1], chain[1:]):
        assert riccati.psd_leq(b, a, tol=1e-10).all()


def test_perfect_channel_converges_to_dare():
    s = LinearSystem.create([[1.2, 0.4], [0.0, 0.8]], [[1.0, 0.0]], np.eye(2) * 0.3, 0.5, np.eye(2) * 5)
    g = np.ones((2, 300), bool)
    res = fixed_lag_smoother(s, g, 0, times=[299])
    Pst = scipy.linalg.solve_discrete_are(s.A.T, s.C.T, s.Q, s.R)
    np.testing.assert_allclose(res.pred[0, :, :, 0], Pst, rtol=1e-9)
    np.testing.assert_allclose(res.filt[0, :, :, 0], riccati.gtilde(Pst, s), rtol=1e-9)


def test_batched_equals_per_run_loop():
    rng = np.random.default_rng(5)
    s = random_system(rng, 2, 1)
    g = rng.random((30, 25)) < 0.5
    res = fixed_lag_smoother(s, g, 2)
    for r in (0, 11, 29):
        one = fixed_lag_smoother(s, g[r:r + 1], 2)
        np.testing.assert_allclose(one.smooth[..., 0], res.smooth[..., r], rtol=1e-12, atol=0)
        np.testing.assert_allclose(one.pred[..., 0], res.pred[..., r], rtol=1e-12, atol=0)


def test_lost_packet_propagates_the_previous_estimate_covariance():
    s = LinearSystem.create(1.3, 1, 0.5, 1, 2.0)
    g = np.array([[1, 1, 0, 0, 1, 0]], bool)
    res = fixed_lag_smoother(s, g, 3)
    # P_{k|k+N} = P_{k|k+N-1} whenever γ_{k+N} = 0 (eq. 4 with γ = 0)
    assert res.smooth[1, 1, 0, 0, 0] == res.smooth[1, 0, 0, 0, 0]  # γ_2 = 0
    assert res.smooth[1, 2, 0, 0, 0] == res.smooth[1, 1, 0, 0, 0]  # γ_3 = 0
    assert res.smooth[1, 3, 0, 0, 0] < res.smooth[1, 2, 0, 0, 0]  # γ_4 = 1


def test_overflow_is_inf_never_nan_and_a_huge_prior_is_rescued():
    """The one rescue policy (kalman.Rescue): a prior that overflowed is inf (never NaN) until a packet
    arrives, then P_{k|k} = r/c² = 1 (the unknown direction carries information 0); a huge but finite
    prior (900⁹⁹ ≈ 1e292) is updated in information form, exact: P_{k|k} = 1/(1/Σ + 1) = 1."""
    s = LinearSystem.create(30.0, 1, 1, 1, 1.0)
    g = np.zeros((3, 260), bool)
    g[1, 100] = True  # after 100 losses (prior finite)
    g[2, 200] = True  # after 200 losses (prior overflowed)
    with np.errstate(all="raise"):
        res = fixed_lag_smoother(s, g, 2, times=[100, 150, 200, 250])
    assert not np.isnan(res.smooth).any() and not np.isnan(res.pred).any()
    assert res.filt[0, 0, 0, 1] == pytest.approx(1.0, rel=1e-12)  # the huge prediction is forgotten at the arrival
    x = 1.0
    for _ in range(50):  # then 50 losses: h⁵⁰(1) = 900⁵⁰ + …, finite (≈ 5e147)
        x = 900.0 * x + 1.0
    np.testing.assert_allclose(res.pred[1, 0, 0, 1], x, rtol=1e-12)
    assert np.isinf(res.pred[2:, :, :, 0]).all() and np.isinf(res.smooth[2:, :, :, :, 0]).all()  # never an arrival
    assert np.isinf(res.pred[2, 0, 0, 2]) and res.filt[2, 0, 0, 2] == pytest.approx(1.0, rel=1e-12)  # recovered
    # x at that arrival is known with variance 1 and the later losses add nothing: P_{t|t+N} = 1 for N = 0, 1, 2
    np.testing.assert_allclose(res.smooth[2, :, 0, 0, 2], 1.0, rtol=1e-9)


def test_bad_input():
    s = LinearSystem.create(1.3, 1, 0.5, 1, 1.0)
    with pytest.raises(ValueError, match="runs, horizon"):
        fixed_lag_smoother(s, np.ones(5, bool), 1)
    with pytest.raises(ValueError, match="times"):
        fixed_lag_smoother(s, np.ones((1, 5), bool), 2, times=[3])


def _rts_reference(A, C, Q, R, P0, gam, k, N):
    """P_{k−N|k} by the RTS recursion with every update and gain in exact rational arithmetic on the float64
    inputs, each step's covariance rounded once to float64 (2 states)."""
    from fractions import Fraction as F

    def mat(X):
        return [[F(float(v)) for v in row] for row in np.asarray(X, float)]

    def mul(X, Y):
        return [[sum(X[i][t] * Y[t][j] for t in range(len(Y))) for j in range(len(Y[0]))] for i in range(len(X))]

    def tr(X):
        return [list(r) for r in zip(*X)]

    def add(X, Y, s=1):
        return [[X[i][j] + s * Y[i][j] for j in range(len(X[0]))] for i in range(len(X))]

    def inv2(X):
        det = X[0][0] * X[1][1] - X[0][1] * X[1][0]
        return [[X[1][1] / det, -X[0][1] / det], [-X[1][0] / det, X[0][0] / det]]

    def rnd(X):
        return [[F(float(v)) for v in row] for row in X]

    A, C, Q, R = (mat(X) for X in (A, C, Q, R))
    P, Pf, Pp = mat(P0), [mat(P0)], []
    for t in range(k):
        Pm = rnd(add(mul(mul(A, P), tr(A)), Q))
        Pp.append(Pm)
        if gam[t]:
            PCt = mul(Pm, tr(C))
            P = rnd(add(Pm, mul(mul(PCt, inv2(add(mul(C, PCt), R))), tr(PCt)), -1))
        else:
            P = Pm
        Pf.append(P)
    Ps = Pf[k]
    for t in range(k - 1, k - N - 1, -1):
        J = mul(mul(Pf[t], tr(A)), inv2(Pp[t]))
        Ps = rnd(add(Pf[t], mul(mul(J, add(Ps, Pp[t], -1)), tr(J))))
    return np.array([[float(v) for v in row] for row in Ps]), [np.array([[float(v) for v in r] for r in X]) for X in Pp]


@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_smoothing_through_a_loss_burst_with_two_states(backend):
    """The RTS step updates P_{t|t} by x_{t+1} (C = A, R = Q): n rows at once, so after a loss burst its cancellation
    grows like ‖P‖², as the filter's does (kalman.burst_limit). 2 states, a coupled system, bursts of 8-30 steps,
    lags 2 and 4: P_{k−N|k} matches the exact recursion to what float64 covariances can promise (ε·RESCUE_RATIO, or
    16 ε κ of the predictions involved, carried forward) and is positive semi-definite. With the trace rule's limit
    alone the numpy path gave a negative-definite P_{26|28} of trace 49.7 (exact 2.09)."""
    if backend == "numba":
        pytest.importorskip("numba")
    from netkf_cli.core.tolerances import RESCUE_RATIO
    from netkf_cli.core.trace import Trace
    from netkf_cli.estimators.smoother import SmootherEstimator

    from tests.burst_system import A, C, Q, R

    s = LinearSystem.create(A, C, Q, R)
    P0 = riccati.initial_covariance(s)
    Ls = np.array([8, 16, 22, 24, 26, 30])
    K = 36
    arr = ~((np.arange(K)[:, None] >= 3) & (np.arange(K)[:, None] < 3 + Ls[None, :]))
    trace = Trace(runs=Ls.size, horizon=K, arrival=arr[None], meta={})
    eps = np.finfo(float).eps
    for N in (2, 4):
        got = dict(SmootherEstimator(kind="smoother", lag=N, backend=backend).covariances(s, trace, range(N, K + 1),
                                                                                           ("smoothed",)))
        for r, L in enumerate(Ls):
            for k in sorted(k for k in {3 + L - 1, 3 + L, 3 + L + 1, 3 + L + N, K} if k <= K):
                want, priors = _rts_reference(A, C, Q, R, P0, arr[:, r], k, N)
                tol = max(eps * RESCUE_RATIO, 16 * eps * max(np.linalg.cond(P) for P in priors))
                P = got[k]["smoothed"][:, :, r]
                np.testing.assert_allclose(P, want, rtol=0, atol=tol * np.abs(want).max(), err_msg=f"L={L} k={k} N={N}")
                assert np.linalg.eigvalsh(P).min() >= -tol * np.abs(want).max(), (L, k, N)
