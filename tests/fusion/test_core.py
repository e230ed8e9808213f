"""Numerical core of the fusion topic (Chiuso & Schenato): channel, MF, IBF, OLPEF vs brute force."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
from pydantic import ValidationError
from scipy import stats

from netkf_cli.analysis import fusion_bounds as fb
from netkf_cli.channels.multi import MultiChannel, sample_multi_arrivals, times_since_arrival
from netkf_cli.estimators import fusion as fe

from ._run_averages import run_averages
from netkf_cli.core.trace import Trace

SYS1 = dict(A=[[0.9]], C=[[1.0]], Q=[[0.3]], R=[[2.0]])
SYS2 = dict(A=[[0.8, 0.3], [-0.2, 0.7]], C=[[1.0, 0.5]], Q=[[0.4, 0.1], [0.1, 0.2]], R=[[1.5]])


def _mats(d):
    return [np.array(d[k], dtype=float) for k in ("A", "C", "Q", "R")]


# ---------------------------------------------------------------------------------------- channel


def test_multi_sampler_shape_and_rates():
    rng = np.random.default_rng(0)
    loss = np.array([0.0, 0.25, 0.5, 0.9, 1.0])
    g = sample_multi_arrivals(rng, 4000, 50, loss)
    assert g.shape == (4000, 50, 5) and g.dtype == bool
    rate = g.mean(axis=(0, 1))
    n = 4000 * 50
    # each rate is a mean of n Bernoulli(1 - loss): stderr sqrt(p(1-p)/n); 5 sigma (+1e-12 for p in {0,1})
    se = np.sqrt(loss * (1 - loss) / n)
    assert np.all(np.abs(rate - (1 - loss)) <= 5 * se + 1e-12)


def test_multi_channel_model_validation():
    ch = MultiChannel(kind="multi", sensors=3, loss=0.2)
    assert np.allclose(ch.loss_array, 0.2) and ch.common_loss == 0.2
    ch = MultiChannel(kind="multi", sensors=2, loss=[0.1, 0.3])
    assert ch.common_loss is None
    assert ch.sample(np.random.default_rng(1), 7, 5).shape == (7, 5, 2)
    with pytest.raises(ValidationError, match="one entry per sensor"):
        MultiChannel(kind="multi", sensors=3, loss=[0.1, 0.2])
    with pytest.raises(ValidationError):
        MultiChannel(kind="multi", sensors=3, loss=1.5)
    with pytest.raises(ValidationError):
        MultiChannel(kind="multi", sensors=3, loss=0.1, arrival=0.9)  # unknown field: no silent ambiguity
    with pytest.raises(ValueError, match="sensors"):
        sample_multi_arrivals(np.random.default_rng(0), 2, 2, 0.1)


def test_times_since_arrival_by_hand():
    g = np.array([[[1, 0], [0, 0], [1, 0], [0, 1]]], dtype=bool)  # (1 run, T=4, N=2)
    tau = times_since_arrival(g)
    assert tau[0, :, 0].tolist() == [0, 1, 0, 1]
    assert tau[0, :, 1].tolist() == [1, 2, 3, 0]  # nothing yet -> t + 1


def test_backward_chain_marginals_are_binomial():
    # ℓ_{t-k} = #{i: τ_i ≤ k} ~ Binom(N, 1 - λ^{k+1}); the printed transition density must reproduce it.
    N, lam = 7, 0.6
    T = fb.backward_transition(N, lam)
    assert np.allclose(T.sum(axis=1), 1.0)
    w = stats.binom.pmf(np.arange(N + 1), N, 1 - lam)
    for k in range(1, 5):
        w = w @ T
        assert np.allclose(w, stats.binom.pmf(np.arange(N + 1), N, 1 - lam ** (k + 1)), atol=1e-14)


# ---------------------------------------------------------------------------------------- MF


def _kf_received_rows(A, C, Q, R, P0, gamma_run):
    """Per-run KF with the stacked measurement of the received sensors only, eq. (7) with pseudo-inverse;
    P0 = P_{0|0}, step t + 1 uses the packets of trace step t."""
    N = gamma_run.shape[1]
    Cbar_full = np.kron(np.ones((N, 1)), C)
    Rbar_full = np.kron(np.eye(N), R)
    m = C.shape[0]
    P = A @ P0 @ A.T + Q
    out_f, out_p, out_pinv = [], [], []
    for t in range(gamma_run.shape[0]):
        rows = np.repeat(gamma_run[t], m)
        Cr, Rr = Cbar_full[rows], Rbar_full[np.ix_(rows, rows)]
        if rows.any():
            S = Cr @ P @ Cr.T + Rr
            Pf = P - P @ Cr.T @ np.linalg.solve(S, Cr @ P)
        else:
            Pf = P.copy()
        # eq. (7) literally: zero the lost rows and use the Moore-Penrose pseudo-inverse
        G = np.repeat(gamma_run[t], m).astype(float)
        Cz, Rz = G[:, None] * Cbar_full, np.diag(G) @ Rbar_full @ np.diag(G)
        Pf_pinv = P - P @ Cz.T @ np.linalg.pinv(Cz @ P @ Cz.T + Rz) @ Cz @ P
        out_f.append(np.trace(Pf))
        out_pinv.append(np.trace(Pf_pinv))
        P = A @ Pf @ A.T + Q
        out_p.append(np.trace(P))
    return np.array(out_f), np.array(out_p), np.array(out_pinv)


@pytest.mark.parametrize("sysd", [SYS1, SYS2], ids=["scalar", "2state"])
def test_mf_matches_per_run_kalman_filter(sysd):
    A, C, Q, R = _mats(sysd)
    T, runs = 12, 6
    g = sample_multi_arrivals(np.random.default_rng(2), runs, T, [0.2, 0.5, 0.7, 0.4])
    P0 = 1.7 * np.eye(A.shape[0])
    s = fe.identical_sensors(A, C, Q, R, 4, P0)
    trace = Trace(runs=runs, horizon=T, arrival=np.ascontiguousarray(np.transpose(g, (2, 1, 0))))
    out = dict(fe.FusionEstimator(kind="fusion", strategies=["mf"]).covariances(s, trace, range(1, T + 1),
                                                                                ("filtered", "predicted")))
    Pf = np.array([np.trace(out[k]["filtered"]) for k in range(1, T + 1)]).T  # (runs, T)
    Pp = np.array([np.trace(out[k]["predicted"]) for k in range(1, T + 1)]).T
    for r in range(runs):
        f, p, fpinv = _kf_received_rows(A, C, Q, R, P0, g[r])
        assert np.allclose(Pf[r], f, rtol=1e-11) and np.allclose(Pp[r], p, rtol=1e-11)
        assert np.allclose(fpinv, f, rtol=1e-9)


# ---------------------------------------------------------------------------------------- IBF


def _batch_conditional_trace(A, C, Q, R, P0, t, last):
    """Brute force: tr Var(x_t | y^i_s for all s ≤ last[i]) from the joint Gaussian of x_0..x_t and all y."""
    n = A.shape[0]
    V = [P0]
    for s in range(t):
        V.append(A @ V[-1] @ A.T + Q)

    def cxx(s, u):  # Cov(x_s, x_u)
        return np.linalg.matrix_power(A, s - u) @ V[u] if s >= u else (np.linalg.matrix_power(A, u - s) @ V[s]).T

    obs = [(i, s) for i in range(len(last)) for s in range(last[i] + 1)]
    if not obs:
        return np.trace(V[t])
    m = C.shape[0]
    Sxy = np.hstack([cxx(t, s) @ C.T for _, s in obs])
    Syy = np.zeros((m * len(obs), m * len(obs)))
    for a, (i, s) in enumerate(obs):
        for b, (j, u) in enumerate(obs):
            blk = C @ cxx(s, u) @ C.T + (R if (i == j and s == u) else 0.0)
            Syy[a * m:(a + 1) * m, b * m:(b + 1) * m] = blk
    return np.trace(V[t] - Sxy @ np.linalg.solve(Syy, Sxy.T))


@pytest.mark.parametrize("sysd", [SYS1, SYS2], ids=["scalar", "2state"])
def test_ibf_matches_batch_conditioning(sysd):
    A, C, Q, R = _mats(sysd)
    N, T, runs = 3, 7, 5
    g = sample_multi_arrivals(np.random.default_rng(3), runs, T, 0.55, N)
    P0 = 1.3 * np.eye(A.shape[0])  # P_{0|0}: x at step 1 has prior A P0 Aᵀ + Q; step t + 1 uses trace step t
    tau = times_since_arrival(g)
    s = fe.identical_sensors(A, C, Q, R, N, P0)
    trace = Trace(runs=runs, horizon=T, arrival=np.ascontiguousarray(np.transpose(g, (2, 1, 0))))
    out = dict(fe.FusionEstimator(kind="fusion", strategies=["ibf"]).covariances(s, trace, range(1, T + 1)))
    for t in range(T):
        f = np.trace(out[t + 1]["filtered"])
        for r in range(runs):
            last = t - tau[r, t]  # -1: nothing received from that sensor
            ref = _batch_conditional_trace(A, C, Q, R, A @ P0 @ A.T + Q, t, last)
            assert f[r] == pytest.approx(ref, rel=1e-9)


def test_ibf_never_worse_than_mf_pathwise():
    A, C, Q, R = _mats(SYS2)
    g = sample_multi_arrivals(np.random.default_rng(4), 300, 40, 0.5, 5)
    out = run_averages(g, A, C, Q, R, None, 10, strategies=("mf", "ibf"))
    assert np.all(out["ibf_f"] <= out["mf_f"] * (1 + 1e-12))
    assert np.all(out["ibf_p"] <= out["mf_p"] * (1 + 1e-12))


# ---------------------------------------------------------------------------------------- OLPEF


@pytest.mark.parametrize("sysd", [SYS1, SYS2], ids=["scalar", "2state"])
def test_olpef_no_loss_is_centralized_kf(sysd):
    A, C, Q, R = _mats(sysd)
    N = 4
    tab = fe.OLPEFTables(A, C, Q, R, N)
    v = tab.error_trace(np.zeros((3, N), dtype=int), np.full(3, 50))
    ref = np.trace(fb.phi_f(fb.p_m(A, C, Q, R, N), np.float64(N), C, R))
    assert np.allclose(v, ref, rtol=1e-9)


@pytest.mark.parametrize("sysd", [SYS1, SYS2], ids=["scalar", "2state"])
def test_olpef_matches_state_level_simulation(sysd):
    """Simulate x, y^i, the partial estimates z^i (eq. 10) and the centre's eq. (11) for a FIXED loss
    pattern; compare the sample mean of |e|² with the covariance-only value."""
    A, C, Q, R = _mats(sysd)
    n, N, M, T = A.shape[0], 3, 40000, 70
    tab = fe.OLPEFTables(A, C, Q, R, N)
    rng = np.random.default_rng(5)
    gam = np.ones((T, N), dtype=bool)
    gam[-6:, 0] = False  # sensor 0 silent for the last 6 steps
    gam[-2:, 1] = False
    gam[-4:-1, 2] = False
    Lq, Lr = np.linalg.cholesky(Q), np.linalg.cholesky(R)
    x = rng.standard_normal((M, n)) @ np.linalg.cholesky(scipy.linalg.solve_discrete_lyapunov(A, Q)).T
    z = np.zeros((M, N, n))
    zhat = np.zeros((M, N, n))
    L1, F = tab.L1, tab.F
    for t in range(T):
        if t > 0:
            x = x @ A.T + rng.standard_normal((M, n)) @ Lq.T
        y = x[:, None, :] @ C.T + rng.standard_normal((M, N, C.shape[0])) @ Lr.T  # (M, N, m)
        z = z @ F.T + y @ L1.T
        zhat = np.where(gam[t][None, :, None], z, zhat @ A.T)
    e = x - zhat.sum(axis=1)
    se2 = (e**2).sum(axis=1)
    tau = times_since_arrival(gam[None])[:, -1, :]
    ref = tab.error_trace(tau, np.array([T - 1]))[0]
    # z started at 0 (not stationary): after 64 steps the start-up transient is < 1e-5 relative (|eig F| < 0.9)
    assert abs(se2.mean() - ref) <= 5 * se2.std() / np.sqrt(M)


def test_olpef_unstable_A_is_a_clear_error():
    from netkf_cli.core.errors import ConfigError

    with pytest.raises(ConfigError, match="system.A"):
        fe.OLPEFTables([[1.1]], [[1.0]], [[1.0]], [[1.0]], 3)


def test_sensors_are_built_once_per_system_and_streams():
    """Sensors.of keeps what it builds per (system, streams): the same object on every ask, equal to a fresh
    build; another system (even with equal matrices) or another stream count gets its own."""
    s = fe.identical_sensors(0.9, 1.0, 1e-3, 10.0, 5)
    a = fe.Sensors.of(s, 5)
    assert fe.Sensors.of(s, 5) is a
    fresh = fe.Sensors._build(s, 5, "estimator.kind")
    assert (a.N, a.identical) == (fresh.N, fresh.identical) and a.filt.groups == fresh.filt.groups
    assert all(np.array_equal(x, y) for x, y in ((a.C1, fresh.C1), (a.R1, fresh.R1), (a.filt.C, fresh.filt.C),
                                                 (a.filt.R, fresh.filt.R)))
    other = fe.identical_sensors(0.9, 1.0, 1e-3, 10.0, 5)
    assert fe.Sensors.of(other, 5) is not a and fe.Sensors.of(s, 1) is not a and fe.Sensors.of(s, 1).N == 1
