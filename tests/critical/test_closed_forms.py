"""Closed forms of the critical-rate topic (issue 16): λ_min, λ_max (LMI), S̄, V̄, exact cases, GE."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st

from netkf_cli.analysis import critical as cr
from netkf_cli.analysis import smoothing as sm
from netkf_cli.channels.delay import DelayChannel
from netkf_cli.core.system import LinearSystem

VEHICLE_A = np.array([[1, 0, 0.5, 0], [0, 1, 0, 0.5], [0, 0, 1, 0], [0, 0, 0, 1.0]])
VEHICLE_C = np.array([[1, 0, 0, 0], [0, 1, 0, 0.0]])
TWO_UNSTABLE_A = np.array([[1.25, 0], [1, 1.1]])
TWO_UNSTABLE_C = np.array([[0, 1.0]])


# ---------------------------------------------------------------------------------------------
# λ_min, λ_max
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("a, lam_c", [(1.25, 0.36), (2.0, 0.75)])
def test_scalar_lambda_c_is_exact(a, lam_c):
    rep = cr.critical_report(a, 1.0, tol=1e-6)
    assert rep.exact is not None and rep.exact.key == "scalar"
    assert rep.exact.value == pytest.approx(1 - 1 / a**2, abs=1e-15)
    assert rep.exact.value == pytest.approx(lam_c, abs=1e-15)
    # the LMI bracket contains λ_c = λ_min and is as narrow as the bisection tolerance
    assert rep.lam_max.lo - 1e-6 <= lam_c <= rep.lam_max.hi + 1e-6
    assert rep.lam_max.hi - rep.lam_max.lo <= 1e-6


def _random_system(seed: int, n: int, m: int, scale: float):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    A *= scale / cr.spectral_radius(A)
    C = rng.normal(size=(m, n))
    return A, C


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 3), m=st.integers(1, 2), scale=st.floats(0.5, 2.5))
def test_lambda_min_le_lambda_max_le_one(seed, n, m, scale):
    A, C = _random_system(seed, n, m, scale)
    lm = cr.lambda_max(A, C, tol=1e-3)
    if math.isinf(lm.hi):  # (A, C) not detectable: the LMI is infeasible even at λ = 1
        assert not cr.is_detectable(A, C)
        return
    assert lm.lo <= lm.hi <= 1.0
    # Thm 3 ≤ Thm 4: the bisection started at 0, so this is a check, not an input (tol: bisection width)
    assert cr.lambda_min(A) <= lm.hi + 1e-9


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_lambda_max_equals_lambda_min_when_C_invertible(seed):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(3, 3))
    A *= 1.6 / cr.spectral_radius(A)
    C = rng.normal(size=(3, 3))  # invertible almost surely
    tol = 1e-5
    lm = cr.lambda_max(A, C, tol=tol)
    lmin = cr.lambda_min(A)
    assert lm.lo - tol <= lmin <= lm.hi
    assert abs(lm.hi - lmin) <= 2 * tol
    assert cr.exact_case(A, C).key == "c_invertible"


def test_lambda_max_matches_brute_force_iteration():
    """λ_max from the LMI = where the modified Riccati iteration stops diverging (Thm 4/5)."""
    lm = cr.lambda_max(TWO_UNSTABLE_A, TWO_UNSTABLE_C, tol=1e-5)
    Q, R = np.eye(2), np.eye(1)
    # just above λ_max the iteration converges, clearly below it diverges
    assert np.isfinite(cr.v_bar(TWO_UNSTABLE_A, TWO_UNSTABLE_C, Q, R, lm.hi + 0.01)).all()
    assert not np.isfinite(cr.v_bar(TWO_UNSTABLE_A, TWO_UNSTABLE_C, Q, R, lm.lo - 0.01, max_iter=20_000)).all()


def test_strict_gap_example_and_cases():
    rep = cr.critical_report(TWO_UNSTABLE_A, TWO_UNSTABLE_C)
    # two unstable eigenvalues, C not invertible — but non-degenerate (issue 22): λ_c = λ_min although λ_max is larger
    assert rep.exact is not None and rep.exact.key == "non_degenerate"
    assert rep.lam_min == pytest.approx(0.36) and rep.exact.value == pytest.approx(0.36)
    assert rep.lam_max.lo > rep.lam_min + 0.1  # λ_min < λ_max strictly (≈ 0.4711)
    js = rep.as_json()
    assert js["lambda_c"] == pytest.approx(0.36) and js["proven"] is True and js["interval"][0] == pytest.approx(0.36)
    assert "exactly" in rep.verdict()


def test_exact_case_conditions():
    assert cr.exact_case(np.diag([0.5, 0.9]), np.array([[1.0, 0]])).key == "stable"
    assert cr.exact_case(VEHICLE_A, VEHICLE_C).key == "marginal"
    assert cr.exact_case(np.array([[1.25, 1], [0, 0.9]]), np.array([[1.0, 0]])).key == "single_unstable"
    # C invertible on the observable subspace (the second state is unobservable and stable)
    A = np.array([[1.5, 0], [0, 0.5]])
    assert cr.exact_case(A, np.array([[1.0, 0]])).key == "c_invertible_observable"
    undet = cr.exact_case(np.array([[1.25, 0], [1, 1.1]]), np.array([[1.0, 0]]))
    assert undet.key == "undetectable" and undet.value is None
    assert cr.exact_case(np.diag([2.0, 1.5]), np.array([[1.0, 1.0]])).key == "non_degenerate"
    assert cr.exact_case(np.diag([2.0, -2.0, 1.5]), np.array([[1.0, 1.0, 1.0]])) is None  # degenerate, 3 states


# ---------------------------------------------------------------------------------------------
# S̄, V̄
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("lam", [0.37, 0.6, 0.9])
def test_s_bar_is_a_discrete_lyapunov_solution(lam):
    A, Q = TWO_UNSTABLE_A, np.array([[1.0, 0.2], [0.2, 0.5]])
    S = cr.s_bar(A, Q, lam)
    ref = scipy.linalg.solve_discrete_lyapunov(np.sqrt(1 - lam) * A, Q)
    np.testing.assert_allclose(S, ref, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(S, (1 - lam) * A @ S @ A.T + Q, rtol=1e-9)
    # below λ_min = 0.36 the Lyapunov equation has no PSD solution (scipy would return an indefinite one)
    assert np.isinf(cr.s_bar(A, Q, 0.35)).all()


@pytest.mark.parametrize("lam", [0.5, 0.7, 0.95])
def test_v_bar_is_the_limit_of_the_modified_riccati_iteration(lam):
    A, C, Q, R = TWO_UNSTABLE_A, TWO_UNSTABLE_C, np.eye(2), np.eye(1)
    V = cr.v_bar(A, C, Q, R, lam)
    X = np.zeros((2, 2))
    # at most 20 000 steps, stopping once a step moves X by less than 1e-14 of its size (the iteration
    # from 0 increases monotonically to V̄; stopping early can only leave X farther from V̄ than
    # 20 000 steps would, so the assertion below is exactly as strict)
    for _ in range(20_000):
        X, old = cr.modified_riccati(X, A, C, Q, R, lam), X
        if np.abs(X - old).max() <= 1e-14 * np.abs(X).max():
            break
    np.testing.assert_allclose(V, X, rtol=1e-8)
    np.testing.assert_allclose(cr.modified_riccati(V, A, C, Q, R, lam), V, rtol=1e-10)
    # and S̄ ≤ V̄ in the PSD order
    assert np.linalg.eigvalsh(V - cr.s_bar(A, Q, lam)).min() >= -1e-9


@pytest.mark.parametrize("a, lam", [(1.25, 0.37), (1.25, 0.5), (2.0, 0.8), (2.0, 0.95)])
def test_scalar_exact_mean_between_s_bar_and_v_bar(a, lam):
    """Sinopoli Thms 3–4 against netkf's exact stationary scalar mean (certified bracket)."""
    s = LinearSystem.create(a, 1.0, 1.0, 1.0)
    e = sm.exact_mean(s, lam, None, tol=1e-10)
    S = float(cr.s_bar(s.A, s.Q, lam)[0, 0])
    V = float(cr.v_bar(s.A, s.C, s.Q, s.R, lam)[0, 0])
    assert S <= float(e.lower[0, 0]) and float(e.upper[0, 0]) <= V


def test_v_bar_infinite_below_lambda_max():
    assert np.isinf(cr.v_bar(2.0, 1.0, 1.0, 1.0, 0.7, max_iter=5000)).all()
    assert np.isinf(cr.s_bar(2.0, 1.0, 0.7)).all()


# ---------------------------------------------------------------------------------------------
# Gilbert–Elliott
# ---------------------------------------------------------------------------------------------


def test_markov_lmi_reduces_to_sinopoli_for_iid_loss():
    """At p = 1 − λ, q = λ the Gilbert chain is i.i.d.: the Markov LMI's threshold is λ_max."""
    lm = cr.lambda_max(TWO_UNSTABLE_A, TWO_UNSTABLE_C, tol=1e-5)
    lmi = cr._MarkovLMI(TWO_UNSTABLE_A, TWO_UNSTABLE_C)
    for d in (0.005, 0.02):
        assert lmi.feasible(1 - (lm.hi + d), lm.hi + d)[0]
        assert not lmi.feasible(1 - (lm.lo - d), lm.lo - d)[0]


def test_scalar_ge_curve_is_exact_and_independent_of_p():
    pts = cr.ge_critical_curve(np.array([[2.0]]), np.array([[1.0]]), [0.1, 0.5, 1.0], tol=1e-4)
    for pt in pts:
        assert pt.q_exact == pytest.approx(0.75)
        assert pt.q_necessary == pytest.approx(0.75)
        assert 0.75 <= pt.q_sufficient <= 0.75 + 2e-4  # the sufficient LMI is tight in the scalar case


def _scalar_ge_mean(a, q_noise, r, p, q, runs, horizon, burn, seed):
    """Brute force: scalar KF under a stationary Gilbert chain, one sample of P_{k+1|k} per run."""
    from netkf_cli.channels.gilbert_elliott import sample_gilbert_elliott

    rng = np.random.default_rng(seed)
    g = sample_gilbert_elliott(rng, runs, horizon, p, q)
    P = np.full(runs, 1.0)
    for k in range(horizon):
        P = a * a * P + q_noise
        P = np.where(g[:, k], P * r / (P + r), P)
    return P


@pytest.mark.parametrize("p, q", [(0.3, 0.6), (0.8, 0.7)])
def test_scalar_ge_bounds_bracket_brute_force(p, q):
    a, qn, r = 1.25, 1.0, 1.0
    lo, hi = cr.ge_scalar_bounds(a, 1.0, qn, r, p, q)
    # P here is the prediction after the last step: a² P_post + Q with L losses before → h^{L+1}
    # the loop ends after the update of the last step; one more prediction gives P_{k+1|k}
    Pk = _scalar_ge_mean(a, qn, r, p, q, runs=40_000, horizon=80, burn=0, seed=7)
    pred = a * a * Pk + qn
    m, se = pred.mean(), pred.std(ddof=1) / math.sqrt(pred.size)
    # (1−q)a⁴ < 1 here, so the sample mean has a finite variance; 5 standard errors
    assert (1 - q) * a**4 < 1
    assert lo - 5 * se <= m <= hi + 5 * se


def test_scalar_ge_bounds_diverge_exactly_at_the_critical_recovery_rate():
    a = 2.0
    assert math.isinf(cr.ge_scalar_bounds(a, 1, 1, 1, 0.5, 0.75)[0])
    assert math.isfinite(cr.ge_scalar_bounds(a, 1, 1, 1, 0.5, 0.7501)[1])
    # i.i.d. special case p = 1 − λ, q = λ: E[h^{L+1}(0)] = a²·0 + Q·E[Σ_{i≤L} a^{2i}] = S̄ exactly
    # (S̄ = Q/(1 − (1−λ)a²) is the mean of the same geometric sum)
    lam = 0.9
    lo, hi = cr.ge_scalar_bounds(a, 1, 1, 1, 1 - lam, lam)
    assert lo == pytest.approx(float(cr.s_bar(a, 1.0, lam)[0, 0]), rel=1e-12)


# ---------------------------------------------------------------------------------------------
# delay with a receive buffer
# ---------------------------------------------------------------------------------------------


def test_delay_effective_rate_uses_the_buffer_convention():
    from scipy import stats

    ch = DelayChannel(kind="delay", delay={"kind": "poisson", "mean": 3}, buffer=5, convention="delay_le_D")
    lam, Dmax = cr.delay_effective_rate(ch)
    assert Dmax == 5 and lam == pytest.approx(stats.poisson.cdf(5, 3))
    ch2 = DelayChannel(kind="delay", delay={"kind": "pmf", "probs": [0.5, 0.2]}, buffer=1, convention="delay_lt_D")
    lam2, D2 = cr.delay_effective_rate(ch2)
    assert D2 == 0 and lam2 == pytest.approx(0.5)


def test_degenerate_parity_example_lambda_max():
    """A = diag(2, −2), C = [1 1]: only arrivals of both parities separate the modes, so
    λ_c = 1 − 1/a⁴ = 0.9375 (derived, README); the LMI bound meets it: λ_c = λ_max = 0.9375 > λ_min = 0.75."""
    lm = cr.lambda_max(np.diag([2.0, -2.0]), np.array([[1.0, 1.0]]), tol=1e-5)
    assert cr.lambda_min(np.diag([2.0, -2.0])) == pytest.approx(0.75)
    assert lm.lo - 1e-5 <= 0.9375 <= lm.hi + 1e-5
    assert cr.exact_case(np.diag([2.0, -2.0]), np.array([[1.0, 1.0]])).key == "degenerate_2x2_p2"
