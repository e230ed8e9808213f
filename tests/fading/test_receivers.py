"""Receiver recursions (estimators/fading_receivers.py): identities, orderings, unbiasedness, state-level check."""

import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.linalg import solve_discrete_are

from netkf_cli.analysis import fading as fa
from netkf_cli.estimators import fading_receivers as fr

A5 = np.array([[2, 0.3, 0.45], [0.4, 0.2, 0.5], [1.5, 0.6, 0.34]])
C5, Q5, R5 = 2 * np.eye(3), 1e-3 * np.eye(3), 1e-8 * np.eye(3)
AL, DE = fa.noise_params_from_bits(10, 40 / 2**10)


def noise(s):
    return fa.sigma2_n(s, AL, DE)


def rm(sc, A=A5, C=C5, Q=Q5, R=R5, general=False, nz=noise):
    return fr.ReceiverModel(sc, np.atleast_2d(A), np.atleast_2d(C), np.atleast_2d(Q), np.atleast_2d(R), nz, general_C=general)


def test_general_C_scenario2_equals_eq12():
    th = np.full(300, 10.0)
    mu = fa.mu_ave(th, 100.0)
    a = fr.burst_conditioned_paths(rm(2), np.random.default_rng(3), th, mu, 100.0, np.eye(3), 40, [10, 40])
    b = fr.burst_conditioned_paths(rm(2, general=True), np.random.default_rng(3), th, mu, 100.0, np.eye(3), 40, [10, 40])
    for x, y in zip(a, b):
        np.testing.assert_allclose(x, y, rtol=1e-10)


def test_perfect_channel_scenario3_converges_to_dare():
    # threshold 0 and a constant σ_n² = s: every packet kept with noise R + s I → the standard KF / DARE
    s = 0.05
    r = rm(3, nz=lambda y: np.full_like(np.asarray(y, float), s))
    snr = np.ones((200, 2))
    P = fr.covariance_paths(r, snr, 0.0, np.eye(3), record=[200])[0][:, :, 0]
    X = solve_discrete_are(A5.T, C5.T, Q5, R5 + s * np.eye(3))
    np.testing.assert_allclose(P, X, rtol=1e-9)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10**6), t1=st.floats(0, 8), dt=st.floats(0, 8))
def test_scenario3_below_scenario2_and_monotone_in_threshold(seed, t1, dt):
    """Pathwise on the same Υ realizations: P₃(Υ_T1) ≤ P₃(Υ_T2) for Υ_T1 ≤ Υ_T2 (Thm 3) and P₃ ≤ P₂."""
    rng = np.random.default_rng(seed)
    n = 2
    A = rng.standard_normal((n, n))
    A *= 1.3 / fa.rho_max(A)
    C = rng.standard_normal((n, n)) + 2 * np.eye(n)
    Q = 1e-2 * np.eye(n)
    R = 1e-4 * np.eye(n)
    snr = rng.exponential(10.0, (60, 64))
    P0 = np.eye(n)
    P3a = fr.covariance_paths(rm(3, A, C, Q, R), snr, t1, P0)
    P3b = fr.covariance_paths(rm(3, A, C, Q, R), snr, t1 + dt, P0)
    P2a = fr.covariance_paths(rm(2, A, C, Q, R), snr, t1, P0)
    for X, Y in ((P3a, P3b), (P3a, P2a)):
        D = np.moveaxis(Y - X, (1, 2), (-2, -1))
        # the forward error of the recursion at step t is relative to the largest covariance the path has
        # carried up to t (a loss burst grows P⁻ by ρ(A)² per step; the update back to a small posterior
        # keeps an absolute error ~ ε·max‖P⁻‖·cond), not to the final P: tolerance 1e-9 of that path maximum
        peak = np.maximum.accumulate(np.maximum(np.abs(X), np.abs(Y)).max(axis=(1, 2)), axis=0)  # (T+1, runs)
        assert np.all(np.linalg.eigvalsh((D + np.swapaxes(D, -1, -2)) / 2).min(-1) >= -1e-9 * (1 + peak))


def _z(X, exact):
    n = X.shape[-1]
    m = X.mean(-1)
    se = X.std(-1) / math.sqrt(n)
    return np.abs(m - exact) / se


def test_burst_conditioned_unbiased_scenario2_vs_eq14():
    # U is unbiased for E P[k]; eq. (14) is exact: |mean − exact| < 5 standard errors, entrywise
    Ts, N, H = np.array([8.0, 14.0, 17.0]), 4000, 60
    th, mu = np.repeat(Ts, N), np.repeat(fa.mu_ave(Ts, 100.0), N)
    _, U = fr.burst_conditioned_paths(rm(2), np.random.default_rng(11), th, mu, 100.0, np.eye(3), H, [H])
    U = U[0].reshape(3, 3, len(Ts), N)
    for i, T in enumerate(Ts):
        ex = fa.ep_recursion(A5, C5, Q5, float(fa.mu_ave(T, 100.0)), float(fa.sigma2_n_ave(T, 100.0, AL, DE)), np.eye(3), H, R=R5)[-1]
        assert np.all(_z(U[:, :, i, :], ex) < 5), T


def test_burst_conditioned_scenario1_matches_lemma5_bound():
    # scenario 1 with R → 0: E P = eq. (32) (the kept update is Q up to R-size terms); U's spread is ~0
    Ts, N, H = np.array([10.0, 16.0]), 500, 100
    th, mu = np.repeat(Ts, N), np.repeat(fa.mu_ave(Ts, 100.0), N)
    _, U = fr.burst_conditioned_paths(rm(1), np.random.default_rng(2), th, mu, 100.0, np.eye(3), H, [H])
    U = U[0].reshape(3, 3, len(Ts), N)
    for i, T in enumerate(Ts):
        ex = fa.lower_bound_recursion(A5, Q5, float(fa.mu_ave(T, 100.0)), np.eye(3), H)[-1]
        np.testing.assert_allclose(U[:, :, i, :].mean(-1), ex, rtol=1e-4)


@pytest.mark.parametrize("sc", [2, 3])
def test_state_level_simulation_matches_covariance(sc):
    """E[e eᵀ] of simulated states equals E[P] (P is the conditional error covariance): 5 standard errors."""
    A, C, Q, R = np.array([[1.2, 0.2], [0.0, 0.9]]), np.array([[1.0, 0.3], [0.0, 1.0]]), 0.05 * np.eye(2), 0.01 * np.eye(2)
    r = rm(sc, A, C, Q, R, nz=lambda y: 0.02 + 2.0 * fa.omega(np.sqrt(np.asarray(y, float))))
    rng = np.random.default_rng(5 + sc)
    N = 40_000
    snr = rng.exponential(5.0, (30, N))
    out = fr.simulate_states(r, rng, snr, 1.0, np.eye(2))
    e, P = out["e"], out["P"]
    D = np.einsum("ib,jb->ijb", e, e) - P  # mean zero
    se = D.std(-1) / math.sqrt(N)
    assert np.all(np.abs(D.mean(-1)) < 5 * se)


def test_state_level_general_C():
    A, C, Q, R = np.array([[1.1, 0.3], [0.0, 0.8]]), np.array([[1.0, 2.0]]), 0.05 * np.eye(2), np.array([[0.01]])
    r = rm(2, A, C, Q, R, nz=lambda y: 0.02 + 2.0 * fa.omega(np.sqrt(np.asarray(y, float))))
    rng = np.random.default_rng(9)
    N = 40_000
    out = fr.simulate_states(r, rng, rng.exponential(5.0, (25, N)), 1.0, np.eye(2))
    D = np.einsum("ib,jb->ijb", out["e"], out["e"]) - out["P"]
    assert np.all(np.abs(D.mean(-1)) < 5 * D.std(-1) / math.sqrt(N))


def test_rescue_is_made_once_per_system_and_equals_a_fresh_one():
    """ReceiverModel.rescue is kept per (A, C, Q, R) (a model is built per chunk; Sec. 4.2's floor is a DARE): the
    same limit as kalman.Rescue.of with the floor tr P̄ computed now, for a full-rank and a rank-deficient C."""
    from netkf_cli.linalg import kalman

    A = np.array([[2, 0.3, 0.45], [0.4, 0.2, 0.5], [1.5, 0.6, 0.34]])
    Q = 1e-3 * np.eye(3)
    for C, R in ((2 * np.eye(3), 1e-8 * np.eye(3)), (np.array([[1.0, 2, 3]]), np.array([[1e-8]])),
                 (np.array([[1.0, 2, 3]]), np.array([[1e-6]]))):
        a, b = fr.ReceiverModel(3, A, C, Q, R, None), fr.ReceiverModel(2, A.copy(), C.copy(), Q, R, None)
        fresh = kalman.Rescue.of(np.atleast_2d(C), np.atleast_2d(R), kalman.pbar_trace(A, np.atleast_2d(C), Q,
                                                                                       np.atleast_2d(R)))
        assert a.rescue is b.rescue
        assert a.rescue.limit == fresh.limit
        assert np.array_equal(a.rescue.C, fresh.C) and np.array_equal(a.rescue.R, fresh.R)
