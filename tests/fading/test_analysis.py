"""Closed forms of Mostofi & Murray 2009 (analysis/fading.py) against printed numbers and independent checks."""

import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy import integrate

from netkf_cli.analysis import fading as fa

A5 = np.array([[2, 0.3, 0.45], [0.4, 0.2, 0.5], [1.5, 0.6, 0.34]])


def test_alpha_delta_printed():
    # printed after Fig. 5: N_p = 10, Δ = 0.0391 → α = 1.27e-4, δ = 533.3 (Δ = 40/2^10 rounded)
    a, d = fa.noise_params_from_bits(10, 40 / 2**10)
    assert abs(a - 1.27e-4) < 0.005e-4
    assert abs(d - 533.3) < 0.05
    # the rounded Δ = 0.0391 gives δ = 534.4: the printed δ needs the unrounded step
    assert abs(fa.noise_params_from_bits(10, 0.0391)[1] - 534.357) < 1e-3


def test_delta_by_bit_flip_simulation():
    """Quantize uniform values to N_p bits, flip each bit w.p. p: E n_c² = δ p, E n_q² = α."""
    rng = np.random.default_rng(0)
    Np, D, p, n = 6, 0.25, 0.02, 400_000
    a, d = fa.noise_params_from_bits(Np, D)
    y = rng.uniform(0, D * 2**Np, n)
    code = np.floor(y / D).astype(np.int64)
    flips = (rng.random((n, Np)) < p) @ (1 << np.arange(Np))
    yq = (code + 0.5) * D
    yr = ((code ^ flips) + 0.5) * D
    nq, nc = y - yq, yq - yr
    # 5 standard errors of a sample mean: 5 * std / sqrt(n)
    assert abs(np.mean(nq**2) - a) < 5 * np.std(nq**2) / math.sqrt(n)
    assert abs(np.mean(nc**2) - d * p) < 5 * np.std(nc**2) / math.sqrt(n)


@settings(max_examples=25, deadline=None)
@given(T=st.floats(0, 80), ydb=st.floats(0, 30))
def test_averages_closed_form_vs_quadrature(T, ydb):
    Y = float(fa.db_to_linear(ydb))
    a, d = fa.noise_params_from_bits(10, 40 / 2**10)
    assert math.isclose(float(fa.mu_ave(T, Y)), fa.mu_ave_quad(T, Y), rel_tol=1e-9, abs_tol=1e-14)
    assert math.isclose(float(fa.sigma2_n_ave(T, Y, a, d)), fa.sigma2_n_ave_quad(T, Y, a, d), rel_tol=1e-8, abs_tol=1e-15)


def test_stability_limit():
    rho = fa.rho_max(A5)
    T = fa.max_stable_threshold(100.0, rho)
    assert math.isclose(float(fa.mu_ave(T, 100.0)), rho**-2, rel_tol=1e-12)
    assert np.all(np.isinf(fa.ep_inf(A5, 2 * np.eye(3), 1e-3 * np.eye(3), float(fa.mu_ave(T * 1.001, 100.0)), 1e-3)))
    assert fa.max_stable_threshold(100.0, 0.9) == math.inf


def test_ep_inf_is_limit_of_recursion_14_and_kron_solve():
    mu, s2 = 0.1, 0.01
    C, Q = 2 * np.eye(3), 1e-3 * np.eye(3)
    X = fa.ep_inf(A5, C, Q, mu, s2)
    rec = fa.ep_recursion(A5, C, Q, mu, s2, np.eye(3), 400)[-1]
    np.testing.assert_allclose(rec, X, rtol=1e-10)
    Th = Q + s2 * A5 @ np.linalg.inv(C.T @ C) @ A5.T
    vecX = np.linalg.solve(np.eye(9) - mu * np.kron(A5, A5), Th.ravel())
    np.testing.assert_allclose(vecX.reshape(3, 3), X, rtol=1e-10)


def test_theorem1_optimum_equals_roots_of_24_and_26():
    As = np.array([[1.8, 0.3, 0.1], [0.3, 0.5, 0.2], [0.1, 0.2, -0.4]])  # symmetric: Thm 1 applies
    C, Q = 2 * np.eye(3), 1e-3 * np.eye(3)
    assert all(fa.theorem1_assumptions(As, C, Q).values())
    a, d = fa.noise_params_from_bits(10, 40 / 2**10)
    for Y in (50.0, 100.0, 300.0):
        Tn, _ = fa.optimal_threshold("norm", As, C, Q, Y, a, d)
        Td, _ = fa.optimal_threshold("det", As, C, Q, Y, a, d)
        assert Tn == pytest.approx(fa.eq24_root(Y, a, d, As, 2.0, 1e-3), rel=1e-5)
        assert Td == pytest.approx(fa.eq26_root(Y, a, d, As, 2.0, 1e-3), rel=1e-5)


def test_fig5_optimum_printed_14():
    a, d = fa.noise_params_from_bits(10, 40 / 2**10)
    T, _ = fa.optimal_threshold("norm", A5, 2 * np.eye(3), 1e-3 * np.eye(3), 100.0, a, d)
    assert round(T) == 14
    assert not fa.theorem1_assumptions(A5, 2 * np.eye(3), 1e-3 * np.eye(3))["A_symmetric"]


@pytest.mark.filterwarnings("ignore::scipy.integrate.IntegrationWarning")
@pytest.mark.parametrize("x", [1e-8, 1e-3, 0.5, 3.0, 40.0, 599.0, 601.0, 5e3, 1e6])
def test_scaled_exp1_vs_quadrature(x):
    ref = integrate.quad(lambda t: math.exp(-t) / (x + t), 0, np.inf, epsabs=0, epsrel=1e-13, limit=500)[0]
    assert fa.scaled_exp1(np.array([x]))[0] == pytest.approx(ref, rel=1e-10)


@pytest.mark.parametrize("a,beta,Y,P0", [(1.5, 1.0, 10.0, 1.0), (2.0, 0.3, 100.0, 5.0), (1.1, 2.0, 3.0, 0.2)])
def test_theorem4_series_vs_nested_quadrature(a, beta, Y, P0):
    e = fa.theorem4_mean(a, beta, Y, P0, 2)
    for k in (1, 2):
        assert e[k] == pytest.approx(fa.theorem4_quadrature(a, beta, Y, P0, k), rel=1e-7)


def test_theorem4_series_vs_monte_carlo():
    a, beta, Y, P0, K, n = 1.5, 1.0, 10.0, 1.0, 8, 100_000
    rng = np.random.default_rng(1)
    P = np.full(n, P0)
    e = fa.theorem4_mean(a, beta, Y, P0, K)
    for k in range(1, K + 1):
        P = fa.theorem4_step(P, rng.exponential(Y, n), a, beta)
        # 5 standard errors of the sample mean (P[k] is bounded by a^{2k} P0, finite variance)
        assert abs(P.mean() - e[k]) < 5 * P.std() / math.sqrt(n), k


def test_jakes_numbers():
    fd = fa.doppler_hz(25 * fa.MPH, 1e9)
    assert fd == pytest.approx(37.28, abs=0.01)
    assert float(fa.jakes_autocorr(3, fd, 0.01)) == pytest.approx(0.30, abs=0.005)  # "0.3 after three transmissions"


def test_batched_scans_give_the_scalar_values_and_roots_bit_for_bit():
    """The root scans of eqs (24)/(26) evaluate the residual on the whole grid at once: the same bytes as one call
    per threshold, and the same roots as the scalar scan; optimal_thresholds (the grid's E P∞ solved once for
    both criteria) = the grid scan + bounded Brent of each criterion on its own."""
    from scipy import optimize

    a, d = fa.noise_params_from_bits(10, 40 / 2**10)
    q, vs = 1e-3, 2.0
    C, Q = vs * np.eye(3), q * np.eye(3)
    for Y in (31.6, 100.0, 1000.0):
        rho, eigs = fa.rho_max(A5), np.linalg.eigvals(A5)
        Tmax = fa.max_stable_threshold(Y, rho)
        Ts = np.linspace(0.0, Tmax * (1 - 1e-7), 4000)
        assert fa.eq26_residuals(Ts, Y, a, d, eigs, vs, q).tobytes() == \
            np.array([fa.eq26_residual(t, Y, a, d, eigs, vs, q) for t in Ts]).tobytes()
        assert np.asarray(fa.eq24_residual(Ts, Y, a, d, rho, vs, q)).tobytes() == \
            np.array([float(fa.eq24_residual(t, Y, a, d, rho, vs, q)) for t in Ts]).tobytes()
        g = lambda t: fa.eq26_residual(t, Y, a, d, eigs, vs, q)  # noqa: E731
        batched = fa._root_in_stable_range(g, Tmax, scan=lambda x: fa.eq26_residuals(x, Y, a, d, eigs, vs, q))
        assert batched == fa._root_in_stable_range(g, Tmax) and len(batched) == 1
        assert fa.eq26_root(Y, a, d, A5, vs, q) == batched[0]
        both = fa.optimal_thresholds(("norm", "det"), A5, C, Q, Y, a, d)
        for kind in ("norm", "det"):
            f = fa._objective(kind, A5, C, Q, Y, a, d)
            grid = np.linspace(0.0, Tmax * (1 - 1e-9), 400)
            vals = np.array([f(t) for t in grid])
            i = int(np.argmin(vals))
            res = optimize.minimize_scalar(f, bounds=(grid[max(i - 1, 0)], grid[min(i + 1, 399)]), method="bounded",
                                           options={"xatol": 1e-9})
            ref = (float(res.x), float(res.fun)) if res.fun <= vals[i] else (float(grid[i]), float(vals[i]))
            assert both[kind] == ref == fa.optimal_threshold(kind, A5, C, Q, Y, a, d)
