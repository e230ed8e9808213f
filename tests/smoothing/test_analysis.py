"""Closed forms and exact computations of Leong, Dey & Evans 2008 (analysis/smoothing.py)."""

from __future__ import annotations

import itertools
import math
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from netkf_cli.linalg import riccati
from netkf_cli.analysis import smoothing as sm
from netkf_cli.channels.retransmission import RetransmissionChannel
from netkf_cli.core.errors import ConfigError
from netkf_cli.core.tolerances import SMOOTHING_MEAN_TOL
from netkf_cli.estimators.smoother import fixed_lag_smoother
from netkf_cli.core.system import LinearSystem

S = LinearSystem.create(1.3, 1, 0.5, 1)
PRINTED_LAMBDA = [0.776, 0.632, 0.527, 0.451, 0.393, 0.348]  # Table I, second row
LAGS = [None, 0, 1, 2, 3, 4]


def bern(lam):
    return np.array([[1 - lam, lam], [1 - lam, lam]]), np.array([1 - lam, lam])


def test_mbar_k1_and_table1_rates_to_the_printed_digits():
    assert sm.leong_mbar(S)[0, 0] == pytest.approx(1.3**2 * 1 + 0.5)  # M̄ = A C⁻¹ R C⁻ᵀ Aᵀ + Q = 2.19
    assert sm.k1(S, 6.25) == 2  # "it can be determined that k1 = 2"
    for lag, printed in zip(LAGS, PRINTED_LAMBDA):
        assert round(sm.sufficient_arrival_rate(2, 0.05, lag), 3) == printed


def test_k1_guards():
    with pytest.raises(ConfigError, match="M̄"):
        sm.k1(S, 2.0)  # M below M̄ = 2.19
    stable = LinearSystem.create(0.5, 1, 0.5, 1)
    assert math.isinf(sm.k1(stable, 10.0))
    assert sm.sufficient_arrival_rate(math.inf, 0.05, 2) == 0.0
    with pytest.raises(ConfigError, match="C square"):
        sm.leong_mbar(LinearSystem.create(np.eye(2), [[1.0, 0.0]], np.eye(2), 1.0))


def test_exact_probability_hand_derivation():
    # k1 = 2 and h²(x) ≤ 6.25 ⟺ x ≤ 1.7174 ⟺ the arrival before it was preceded by an arrival:
    # P(P_{k|k-1} ≤ M) = λ + λ(1−λ) + λ²(1−λ)²  (γ_{k-1} = 1; or 0,1 before; or 0,0 then 1,1)
    for lam in (0.5, 0.7763932, 0.9):
        e = sm.exact_probability(S, 6.25, None, *bern(lam))
        assert e.width < 1e-15
        assert e.value == pytest.approx(lam + lam * (1 - lam) + lam**2 * (1 - lam) ** 2, abs=1e-14)
        # any arrival in the smoothing window makes P_{k|k+N} ≤ 1 ≤ M here, so
        # P(P_{k|k+N} ≤ M) = 1 − (1−λ)^{N+1} (1 − P(P_{k|k-1} ≤ M))
        for N in (0, 2):
            eN = sm.exact_probability(S, 6.25, N, *bern(lam))
            assert eN.value == pytest.approx(1 - (1 - lam) ** (N + 1) * (1 - e.value), abs=1e-14)


def _brute_force_bracket(s, M, lag, T, pi, L):
    """Enumerate every pattern of L past + (lag+1) future arrivals with its Markov probability,
    propagating the smoother itself from P* and from a huge P0 at time k − L: lower/upper bounds."""
    F = 1 if lag is None else lag + 1  # for P_{k|k-1}, γ_k is summed out
    pats = np.array(list(itertools.product((0, 1), repeat=L + F)), bool)
    w = pi[pats[:, 0].astype(int)].copy()
    for t in range(1, L + F):
        w *= T[pats[:, t - 1].astype(int), pats[:, t].astype(int)]
    out = []
    for P0 in (riccati.pstar(s), 1e8 * np.eye(s.n)):
        res = fixed_lag_smoother(s, pats, 0 if lag is None else lag, P0=P0, times=[L])
        P = res.pred[0] if lag is None else res.smooth[0, lag]
        ok = riccati.psd_leq(np.moveaxis(P, -1, 0), sm.as_bound(M, s.n))
        out.append(float(w[ok].sum()))
    return out[1], out[0]  # huge prior: fewer ok (lower bound); P*: upper bound


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 1000), lag=st.sampled_from([None, 0, 1, 2]), markov=st.booleans())
def test_exact_probability_is_bracketed_by_brute_force(seed, lag, markov):
    rng = np.random.default_rng(seed)
    a = rng.uniform(0.6, 1.6)
    s = LinearSystem.create(a, rng.uniform(0.5, 2), rng.uniform(0.2, 1), rng.uniform(0.2, 2))
    M = float(sm.leong_mbar(s)[0, 0]) * rng.uniform(1.05, 4)
    if markov:
        p_gb, p_bg = rng.uniform(0.1, 0.6), rng.uniform(0.2, 0.9)
        T = np.array([[1 - p_bg, p_bg], [p_gb, 1 - p_gb]])
        pi = np.array([p_gb, p_bg]) / (p_gb + p_bg)
    else:
        T, pi = bern(rng.uniform(0.3, 0.9))
    e = sm.exact_probability(s, M, lag, T, pi)
    lo, hi = _brute_force_bracket(s, M, lag, T, pi, L=10)
    # the certified bracket lies inside the brute-force one (which is looser: only 10 past steps)
    assert lo - 1e-12 <= e.lower <= e.upper <= hi + 1e-12
    assert e.width < 1e-8


def test_exact_probability_matrix_case_vs_monte_carlo():
    s = LinearSystem.create([[1.1, 0.2], [0.0, 0.9]], np.eye(2), np.eye(2) * 0.4, np.eye(2) * 0.8)
    M = 3.0
    lam = 0.55
    runs = 40_000
    g = np.random.default_rng(4).random((runs, 62)) < lam
    res = fixed_lag_smoother(s, g, 1, P0=riccati.pstar(s), times=[60])
    for lag, P in ((None, res.pred[0]), (0, res.smooth[0, 0]), (1, res.smooth[0, 1])):
        e = sm.exact_probability(s, M, lag, *bern(lam))
        p = riccati.psd_leq(np.moveaxis(P, -1, 0), sm.as_bound(M, 2)).mean()
        se = math.sqrt(e.value * (1 - e.value) / runs)  # binomial s.e. at the exact value; runs independent
        assert abs(p - e.value) < 5 * se + e.width


def test_exact_mean_vs_monte_carlo_and_lemma1():
    lam = 0.8  # > 1 − 1/a⁴ = 0.65: E[P²] < ∞, so the sample mean has a finite s.e.
    runs = 60_000
    g = np.random.default_rng(8).random((runs, 63)) < lam
    res = fixed_lag_smoother(S, g, 2, times=[60])
    for lag, P in ((None, res.pred[0]), (0, res.smooth[0, 0]), (2, res.smooth[0, 2])):
        e = sm.exact_mean(S, lam, lag)
        x = P[0, 0]
        assert float(e.upper[0, 0] - e.lower[0, 0]) < 1e-5
        # 5 s.e. of the sample mean (finite variance) plus the initial-transient bias (P0 = P* at k = 0:
        # bounded by (1−λ)^60 ρ(A)^120-type terms, < 1e-20 here) and the bracket width
        assert abs(x.mean() - e.value[0, 0]) < 5 * x.std() / math.sqrt(runs) + 1e-5
    Ep = sm.exact_mean(S, lam, None).value[0, 0]
    for N in (0, 1, 3):  # Lemma 1: (1−λ)^{N+1} E[P_{k|k-1}] ≤ E[P_{k|k+N}] ≤ E[P_{k|k-1}]
        EN = sm.exact_mean(S, lam, N).value[0, 0]
        assert (1 - lam) ** (N + 1) * Ep <= EN <= Ep


def test_exact_mean_diverges_exactly_at_lambda_c():
    lc = sm.critical_rate(S)
    assert lc == pytest.approx(1 - 1 / 1.69)
    for lag in (None, 0, 3):
        assert np.isinf(sm.exact_mean(S, lc - 1e-9, lag).value).all()
        assert np.isfinite(sm.exact_mean(S, lc + 0.01, lag).value).all()
    # and grows without bound as λ ↓ λ_c (like 1/(1 − (1−λ)a²))
    e1 = sm.exact_mean(S, lc + 1e-2, 3).value[0, 0]
    e2 = sm.exact_mean(S, lc + 1e-3, 3).value[0, 0]
    assert e2 > 5 * e1


def test_g_identity_exact_and_float():
    for N in (1, 2, 3, 6):
        for p in (Fraction(0), Fraction(1, 3), Fraction(1, 2), Fraction(9, 10), Fraction(1)):
            assert all(v == 1 for v in sm.retransmission_g(25, N, p))  # exact rational arithmetic
        for p in np.linspace(0, 1, 11):
            assert np.allclose(sm.retransmission_g(60, N, float(p)), 1.0, atol=1e-12)


def test_the_papers_seven_ways_for_1000_with_N2():
    p = Fraction(2, 7)
    ways = dict(sm.enumerate_retransmission_ways(3, 2, p))
    q = 1 - p
    expected = {  # Sec. V-B, in the paper's order
        "1 0* 0* 0*": q**3, "1 0* 0R0*": q * p * q, "1 0R0* 0*": p * q**2, "1 0R0R0": p**2,
        "0R1 0* 0*": p * q**2, "0R1 0R0*": p**2 * q, "0R0R1 0*": p**2 * q,
    }
    assert ways == expected and sum(ways.values()) == 1
    for n in range(8):  # enumeration == recursion (10)–(11) == 1
        assert sum(w for _, w in sm.enumerate_retransmission_ways(n, 3, p)) == sm.retransmission_g(n, 3, p)[n] == 1


@pytest.mark.parametrize("p", [1.0, 0.5])
def test_retransmission_channel_pattern_has_rate_lambda(p):
    """The effective pattern of the retransmission channel: Pr[γ̃_t = 1] = λ and Pr[γ̃_t = γ̃_{t+1} = 1] = λ²
    (the law of i.i.d. loss, Sec. V), also at the last steps (every retransmission completed). 5 s.e."""
    lam, N, runs, H = 0.6, 2, 20_000, 80
    ch = RetransmissionChannel(kind="retransmission", arrival=lam, budget=N, p=p)
    g = ch.sample_trace(np.random.default_rng(1), runs, H).arrival[0]  # (H, runs)
    se = math.sqrt(lam * (1 - lam) / runs)
    se2 = math.sqrt(lam**2 * (1 - lam**2) / runs)
    for t in (60, H - 2):  # one column per run: independent samples
        assert abs(g[t].mean() - lam) < 5 * se
        assert abs((g[t] & g[t + 1]).mean() - lam**2) < 5 * se2
    with pytest.raises(ValidationError):
        RetransmissionChannel(kind="retransmission", arrival=lam, budget=N, p=1.5)
    # p = 0: no retransmission, the link's own pattern
    g0 = RetransmissionChannel(kind="retransmission", arrival=lam, budget=N, p=0.0).sample_trace(
        np.random.default_rng(2), 4, 50).arrival[0]
    u = np.random.default_rng(2).random((52, 2, 4))[:50, 0]
    assert np.array_equal(g0, u < lam)


def test_g_identity_in_rationals():
    for N in (1, 2, 3, 5):
        for p in (0.0, 0.3, 0.5, 0.9, 1.0):
            assert sm.retransmission_g_is_one(12, N, p)


def test_future_information_matches_smoothed_from_prior():
    s = LinearSystem.create([[1.1, 0.3], [0.0, 0.7]], [[1.0, 0.5]], np.diag([0.4, 0.2]), 0.6)
    P = np.array([[2.0, 0.3], [0.3, 1.0]])
    for f in [(1,), (0, 1), (1, 0, 1), (0, 1, 1, 1)]:
        J = sm.future_information(s, f)
        np.testing.assert_allclose(np.linalg.inv(np.linalg.inv(P) + J), sm.smoothed_from_prior(P, s, f), rtol=1e-10)


def test_compiled_scalar_enumeration_is_the_numpy_one_bit_for_bit(monkeypatch):
    """``_Batch.evaluate`` compiled (numba, scalar systems) and on numpy give the same P_lo, Y_hi bits, and so the
    same exact means and probabilities; J(f) memoized gives the J of a fresh computation."""
    if sm._scalar_kernel() is None:
        pytest.skip("numba not importable: only the numpy path exists")
    bt = sm._Batch(S)
    bits = np.random.default_rng(3).integers(0, 2, size=(4000, 30)).astype(np.int8)
    bits[:5] = 0  # all losses: P_lo grows, Y_hi stays 0
    P1, Y1 = bt.evaluate(bits)
    ref = {lam: (sm.exact_mean(S, lam, 3), sm.exact_probability(S, 5.0, 1, *bern(lam))) for lam in (0.45, 0.7)}
    monkeypatch.setattr(sm, "_KERNEL", [None])
    monkeypatch.setattr(sm, "_FUTURE_J", {})
    P2, Y2 = bt.evaluate(bits)
    assert P1.shape == P2.shape == (4000, 1, 1) and Y1.shape == Y2.shape
    assert np.array_equal(P1, P2) and np.array_equal(Y1, Y2)
    assert np.all(Y1[:5] == 0.0) and np.all(P1[5:] < P1[0])
    for lam, (m, p) in ref.items():
        m2, p2 = sm.exact_mean(S, lam, 3), sm.exact_probability(S, 5.0, 1, *bern(lam))
        assert np.array_equal(m.lower, m2.lower) and np.array_equal(m.upper, m2.upper)
        assert (p.lower, p.upper, p.nodes) == (p2.lower, p2.upper, p2.nodes)
    for f in ((1,), (0, 1), (1, 0, 1, 1)):
        assert np.array_equal(sm._future_information_cached(S, f), sm.future_information(S, f))


@pytest.mark.parametrize("s", [S, LinearSystem.create(1.3, 0.7, 0.5, 2.0), LinearSystem.create(-1.6, 2.0, 1.5, 0.3)])
def test_compiled_scalar_exact_mean_is_the_numpy_one_bit_for_bit(s, monkeypatch):
    """``exact_mean``'s compiled level (``_expect_bounded_scalar``: the brackets of g and of every (P⁻¹ + J_f)⁻¹
    and the gaps in one pass) gives the numpy φ's (``_expect_bounded``) bits: every lag, rates near λ_c and far
    from it, the configs' tolerance and a coarse one, a node budget that stops the enumeration."""
    if sm._compiled_module() is None:
        pytest.skip("numba not importable: only the numpy path exists")
    lc = sm.critical_rate(s)
    cases = [(lam, lag, SMOOTHING_MEAN_TOL, 400_000) for lam in (lc + 0.004, 0.5 * (1 + lc), 0.93) for lag in (None, 0, 2)]
    cases += [(0.93, 4, 1e-4, 400_000), (0.8, 2, 1e-12, 3000)]
    got = [sm.exact_mean(s, lam, lag, tol=tol, max_nodes=nodes) for lam, lag, tol, nodes in cases]
    monkeypatch.setattr(sm, "_KERNEL", [None])
    for (lam, lag, tol, nodes), a in zip(cases, got):
        b = sm.exact_mean(s, lam, lag, tol=tol, max_nodes=nodes)
        assert np.array_equal(a.lower, b.lower) and np.array_equal(a.upper, b.upper), (lam, lag, tol)
