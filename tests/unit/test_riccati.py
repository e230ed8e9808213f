"""Riccati maps against scipy's DARE and textbook identities on random systems."""

import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings, strategies as st

from netkf_cli.linalg import kalman, riccati
from netkf_cli.core.errors import ConfigError
from netkf_cli.core.system import LinearSystem


def random_system(seed: int, n: int, m: int, unstable: bool) -> LinearSystem:
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    rho = max(abs(np.linalg.eigvals(A)))
    A = A / rho * (rng.uniform(1.05, 1.6) if unstable else rng.uniform(0.2, 0.95))
    C = rng.normal(size=(m, n))
    G = rng.normal(size=(n, n))
    Q = G @ G.T + 0.1 * np.eye(n)
    H = rng.normal(size=(m, m))
    R = H @ H.T + 0.1 * np.eye(m)
    return LinearSystem.create(A, C, Q, R)


systems = st.builds(random_system, st.integers(0, 10_000), st.integers(1, 4), st.integers(1, 3), st.booleans())


@settings(max_examples=40, deadline=None)
@given(systems)
def test_pstar_is_the_dare_solution_and_a_fixed_point_of_g(s):
    if not s.is_observable():
        return
    P = riccati.pstar(s)
    ref = scipy.linalg.solve_discrete_are(s.A.T, s.C.T, s.Q, s.R)
    np.testing.assert_allclose(P, ref, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(riccati.g(P, s), P, rtol=1e-7, atol=1e-9)
    assert np.linalg.eigvalsh(P).min() > -1e-10


@settings(max_examples=40, deadline=None)
@given(systems)
def test_iterating_the_filter_converges_to_pbar(s):
    """A perfect channel: P_k = g̃∘h(P_{k−1}) → P̄ = g̃(P*) and h(P̄) = P* (h∘g̃ = g, Sec. 3.1)."""
    if not s.is_observable():
        return
    X = np.eye(s.n)
    # at most 3000 steps, stopping once a step moves X by less than 1e-13 of its size (a contraction
    # with rate ρ is then within 1e-13·ρ/(1 − ρ) of its limit; stopping early can only leave X farther
    # from P̄ than 3000 steps would, so the assertions below are exactly as strict)
    for _ in range(3000):
        X, old = riccati.gtilde(riccati.h(X, s), s), X
        if np.abs(X - old).max() <= 1e-13 * np.abs(X).max():
            break
    Pb = riccati.pbar(s)
    np.testing.assert_allclose(X, Pb, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(riccati.h(Pb, s), riccati.pstar(s), rtol=1e-8, atol=1e-10)
    # Lemma A.1: g̃(X) ≤ X and g(X) ≤ h(X)
    assert riccati.psd_leq(riccati.gtilde(X, s), X)
    assert riccati.psd_leq(riccati.g(X, s), riccati.h(X, s))


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 3))
def test_mbar_bounds_the_filter_after_an_arrival_when_C_invertible(seed, n):
    """Lemma 3.4 / A.1: g̃(X) ≤ M̄ = C⁻¹RC⁻ᵀ for every X ≥ 0."""
    s = random_system(seed, n, n, unstable=True)
    rng = np.random.default_rng(seed + 1)
    G = rng.normal(size=(n, n)) * 10
    X = G @ G.T
    Mb = riccati.mbar(s)
    Cinv = np.linalg.inv(s.C)
    np.testing.assert_allclose(Mb, Cinv @ s.R @ Cinv.T, rtol=1e-10, atol=1e-12)
    assert riccati.psd_leq(riccati.gtilde(X, s), Mb)


def vehicle() -> LinearSystem:
    A = np.array([[1, 0, 0.5, 0], [0, 1, 0, 0.5], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    C = np.hstack([np.eye(2), np.zeros((2, 2))])
    return LinearSystem.create(A, C, 0.01 * np.eye(4), 0.001 * np.eye(2))


def appendix_b_direct(s: LinearSystem) -> np.ndarray:
    """Error of x̃_k = A [CA; C]⁻¹ [y_k; y_{k−1}] written as L·ξ, ξ = (w_{k−1}, v_k, v_{k−1}) independent."""
    n, m = s.n, s.m
    O = np.vstack([s.C @ s.A, s.C])
    Oinv = np.linalg.inv(O)
    # y_k = CA x_{k−1} + C w_{k−1} + v_k ; y_{k−1} = C x_{k−1} + v_{k−1};  e = x_k − x̃_k
    L_w = np.eye(n) - s.A @ Oinv @ np.vstack([s.C, np.zeros((m, n))])
    L_vk = -s.A @ Oinv @ np.vstack([np.eye(m), np.zeros((m, m))])
    L_vk1 = -s.A @ Oinv @ np.vstack([np.zeros((m, m)), np.eye(m)])
    return L_w @ s.Q @ L_w.T + L_vk @ s.R @ L_vk.T + L_vk1 @ s.R @ L_vk1.T


def test_mbar_appendix_b_equals_the_estimators_error_covariance():
    s = vehicle()
    np.testing.assert_allclose(riccati.mbar(s), appendix_b_direct(s), rtol=1e-12, atol=1e-15)


def test_mbar_appendix_b_against_simulated_estimator():
    """Simulate x_{k−1} (arbitrary), w, v and the estimator; the sample covariance matches M̄ (5σ per entry)."""
    s = vehicle()
    rng = np.random.default_rng(7)
    N = 200_000
    x_prev = rng.normal(size=(N, 4)) * 3.0  # the estimator is unbiased for any x_{k−1}
    w = rng.multivariate_normal(np.zeros(4), s.Q, size=N)
    v_k = rng.multivariate_normal(np.zeros(2), s.R, size=N)
    v_k1 = rng.multivariate_normal(np.zeros(2), s.R, size=N)
    x_k = x_prev @ s.A.T + w
    y_k = x_k @ s.C.T + v_k
    y_k1 = x_prev @ s.C.T + v_k1
    O = np.vstack([s.C @ s.A, s.C])
    z = np.linalg.solve(O, np.hstack([y_k, y_k1]).T).T
    e = x_k - z @ s.A.T
    S = e.T @ e / N
    Mb = riccati.mbar(s)
    # stderr of a sample covariance entry ≈ sqrt((Σ_ii Σ_jj + Σ_ij²)/N)
    se = np.sqrt((np.outer(np.diag(Mb), np.diag(Mb)) + Mb**2) / N)
    assert np.all(np.abs(S - Mb) <= 5 * se + 1e-15)


def test_mbar_and_pbar_order_lemma_3_6():
    for s in (LinearSystem.create(1.4, 1, 0.2, 0.5), vehicle()):
        assert riccati.psd_leq(riccati.pbar(s), riccati.mbar(s))


def test_mbar_refuses_when_neither_condition_holds():
    s = LinearSystem.create(np.eye(3) * 1.1, [[1, 0, 0]], np.eye(3), 1.0)
    with pytest.raises(ConfigError, match="system.C"):
        riccati.mbar(s)


def test_psd_leq_counts_overflow_as_exceeding():
    M = np.eye(2)
    X = np.stack([np.eye(2) * 0.5, np.full((2, 2), np.inf), np.eye(2) * 2])
    assert riccati.psd_leq(X, M).tolist() == [True, False, False]


def test_an_undetectable_system_has_no_pstar_even_where_scipy_returns_one():
    """scipy's solve_discrete_are raises for most undetectable systems, but for an undetected unstable complex pair
    (C = 0) it returned the indefinite solution of P = A P Aᵀ + Q (entries ~1e16): every caller refuses it now
    (it was an internal error, 'not positive semi-definite', in the first Monte Carlo chunk)."""
    A = np.array([[2.9303233728272104, -1.3237446883746125], [1.6997235341225119, 0.0]])
    C, Q, R = np.zeros((1, 2)), np.diag([1.0, 0.0]), np.array([[0.04]])
    garbage = scipy.linalg.solve_discrete_are(A.T, C.T, Q, R)  # what scipy answers (documents the need)
    assert np.linalg.eigvalsh((garbage + garbage.T) / 2).min() < 0
    s = LinearSystem.create(A, C, Q, R)
    with pytest.raises(ConfigError, match="no stabilizing solution.*not positive semi-definite"):
        riccati.pstar(s)
    with pytest.raises(ConfigError, match="system.P0.*P̄"):
        riccati.initial_covariance(s)
    assert kalman.pbar_trace(A, C, Q, R) is None
    np.testing.assert_array_equal(riccati.initial_covariance(LinearSystem.create(A, C, Q, R, P0=np.eye(2))), np.eye(2))


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 4), st.integers(1, 3), st.booleans(), st.integers(0, 3))
def test_dare_returns_a_psd_stabilizing_fixed_point_or_refuses(seed, n, m, unstable, zero_rows):
    """kalman.dare on random systems, some made undetectable (rows of C zeroed): its answer is a PSD fixed point of
    g with a (marginally) stable closed loop, and scipy's whenever scipy's is one; otherwise LinAlgError."""
    s = random_system(seed, n, m, unstable)
    C = s.C.copy()
    C[: min(zero_rows, m)] = 0.0
    try:
        P = kalman.dare(s.A, C, s.Q, s.R)
    except (np.linalg.LinAlgError, ValueError):
        return
    s2 = LinearSystem.create(s.A, C, s.Q, s.R)
    assert np.linalg.eigvalsh(P).min() >= -1e-9 * max(1.0, np.abs(P).max())
    np.testing.assert_allclose(riccati.g(P, s2), P, rtol=1e-6, atol=1e-8 * max(1.0, np.abs(P).max()))
    K = s.A @ P @ C.T @ np.linalg.inv(C @ P @ C.T + s.R)
    A_KC = s.A - K @ C
    assert max(abs(np.linalg.eigvals(A_KC))) <= 1 + 1e-8
    np.testing.assert_array_equal(P, (lambda X: (X + X.T) / 2)(scipy.linalg.solve_discrete_are(s.A.T, C.T, s.Q, s.R)))


def test_dare_memo_returns_copies_and_refuses_again():
    """kalman.dare is memoized per (A, C, Q, R): a caller that writes into its answer does not change the next
    caller's, an equal system built anew gets the same numbers, and a refused system is refused again with the
    same message (scipy's 1e16 indefinite answer for an undetected unstable complex pair)."""
    A, C, Q, R = np.array([[1.2, 0.3], [0.0, 0.8]]), np.array([[1.0, 0.0]]), np.eye(2), np.eye(1)
    P = kalman.dare(A, C, Q, R)
    first = P.copy()
    P[:] = -1.0
    np.testing.assert_array_equal(kalman.dare(A.copy(), C.copy(), Q.copy(), R.copy()), first)
    th = 0.213
    B = 1.5 * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    msgs = []
    for _ in range(2):
        with pytest.raises(np.linalg.LinAlgError) as exc:
            kalman.dare(B, np.zeros((1, 2)), np.eye(2), np.eye(1))
        msgs.append(str(exc.value))
    assert msgs[0] == msgs[1] and msgs[0]
