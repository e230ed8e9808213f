"""Closed forms of Shi, Xie & Murray 2009: Example 3.10's printed numbers and structural properties."""

import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from netkf_cli.analysis import delay_bounds as db
from netkf_cli.channels.delay import GeometricDelay, PmfDelay, PoissonDelay
from netkf_cli.core.errors import TheoremConditionError
from netkf_cli.core.system import LinearSystem

EX = LinearSystem.create(1.4, 1, 0.2, 0.5)
D5 = PoissonDelay(mean=5).cdf


def test_example_3_10_k_values():
    assert (db.k1(50, EX), db.k2(50, EX)) == (7, 7)
    assert (db.k1(150, EX), db.k2(150, EX)) == (8, 9)


@pytest.mark.parametrize("k,D,printed", [(7, 6, 0.0313), (8, 7, 0.0042), (9, 8, 0.0003)])
def test_example_3_10_printed_theta_under_delay_le_D(k, D, printed):
    """The printed θ values follow 'keep delays ≤ D' with Poisson mean 5, to the printed 4 decimals."""
    assert round(db.theta(k, D, D5, "delay_le_D"), 4) == printed


@pytest.mark.parametrize("k,D,printed", [(7, 6, 0.0313), (8, 7, 0.0042), (9, 8, 0.0003)])
def test_eq4_convention_does_not_give_the_printed_theta(k, D, printed):
    """Under eq. (4) literally (delay ≥ D discarded) the same (k, D) give other numbers (0.0506, 0.0075, 0.0006)."""
    assert round(db.theta(k, D, D5, "delay_lt_D"), 4) != printed


def test_conventions_differ_by_a_shift_of_one():
    for k in range(1, 12):
        for D in range(1, 14):
            assert db.theta(k, D + 1, D5, "delay_lt_D") == pytest.approx(db.theta(k, D, D5, "delay_le_D"), rel=1e-14)


@settings(max_examples=50, deadline=None)
@given(st.floats(0.1, 8), st.integers(1, 15), st.sampled_from(["delay_le_D", "delay_lt_D"]))
def test_theta_non_increasing_in_D_and_constant_beyond_saturation(d, k, conv):
    cdf = PoissonDelay(mean=d).cdf
    th = [db.theta(k, D, cdf, conv) for D in range(1, 25)]
    assert all(a >= b - 1e-15 for a, b in zip(th, th[1:]))
    sat = db.saturation_D(k, conv)
    assert all(t == pytest.approx(db.theta(k, sat, cdf, conv), rel=1e-12) for t in th[sat - 1:])
    assert db.theta_floor(k, cdf, conv) == pytest.approx(th[-1], rel=1e-12)


def test_bounds_monotone_in_M_and_ordered():
    Ms = np.linspace(0.5, 400, 200)
    lo_hi = np.array([db.bounds(M, 10, EX, D5, "delay_le_D") for M in Ms])
    assert np.all(lo_hi[:, 0] <= lo_hi[:, 1] + 1e-15)  # Lemma 3.6: k1 ≤ k2
    assert np.all(np.diff(lo_hi[:, 0]) >= -1e-15) and np.all(np.diff(lo_hi[:, 1]) >= -1e-15)


def test_min_buffer_binary_search_equals_linear_scan():
    for d in (1, 3, 5, 7):
        cdf = PoissonDelay(mean=d).cdf
        for k in range(1, 12):
            for eps in (0.5, 0.1, 0.03, 0.01, 1e-3, 1e-5):
                for conv in ("delay_le_D", "delay_lt_D"):
                    scan = next((D for D in range(1, 60) if db.theta(k, D, cdf, conv) <= eps), None)
                    assert db.min_buffer(k, eps, cdf, conv) == scan


def test_size_buffer_keeps_a_cap_apart_from_the_theta_floor():
    """A D_max below the minimum is not θ(k, ∞) > ε: the uncapped D_s, D_n, D* and ``reason`` say which."""
    s = db.size_buffer(50, 0.05, EX, D5, "delay_le_D", D_max=5)
    assert (s.D_s, s.D_n, s.D_s_uncapped, s.D_n_uncapped) == (None, None, 6, 6)
    assert not s.feasible and s.feasible_uncapped and s.reason == "above_D_max"
    assert db.size_buffer(50, 0.05, EX, D5, "delay_le_D", D_max=6).reason is None
    s = db.size_buffer(50, 0.03, EX, D5, "delay_le_D", D_max=5)  # ε < θ(k2, ∞) = 0.03133
    assert s.D_s_uncapped is None and not s.feasible_uncapped and s.reason == "theta_floor"
    s = db.size_buffer(150, 0.001, EX, D5, "delay_le_D", sensor="smart", D_max=5)
    assert (s.D_star, s.D_star_uncapped, s.reason) == (None, 7, "above_D_max")


def test_M_below_mbar_is_refused_with_the_reason():
    with pytest.raises(TheoremConditionError, match=r"M ≥ M̄ = 0.5"):
        db.k1(0.1, EX)


def test_stable_system_can_have_infinite_k():
    s = LinearSystem.create(0.5, 1, 0.2, 0.5)
    assert math.isinf(db.k1(10, s))
    assert db.theta(math.inf, 3, D5, "delay_le_D") == 0.0


def _walk_per_M(X0, M, s, k_max=db.K_MAX):
    """The per-M loop first_exceedance was before the kept orbit (the reference of the shared walk)."""
    from netkf_cli.linalg import riccati
    X = X0
    for t in range(1, k_max + 1):
        Xn = riccati.h(X, s)
        if not bool(riccati.psd_leq(Xn, M)):
            return float(t)
        if np.allclose(Xn, X, rtol=1e-13, atol=1e-15):
            return math.inf
        X = Xn
    return math.inf


VEHICLE = LinearSystem.create([[1, 0, 0.5, 0], [0, 1, 0, 0.5], [0, 0, 1, 0], [0, 0, 0, 1]],
                              [[1, 0, 0, 0], [0, 1, 0, 0]], 0.01 * np.eye(4), 0.001 * np.eye(2))


@pytest.mark.parametrize("s", [EX, LinearSystem.create(0.5, 1, 0.2, 0.5), VEHICLE])
def test_shared_orbit_walk_equals_the_per_M_loop(s):
    """k along one kept orbit with one batched comparison per point (first_exceedances, k1_each/k2_each) is the
    per-M loop at every M: grids of scalars M·I and random PSD matrices, both orbits (M̄ and P̄)."""
    from netkf_cli.linalg import riccati
    rng = np.random.default_rng(7)
    n = s.n
    X0s = [riccati.pbar(s)] + ([riccati.mbar(s)] if n != 4 else [])
    Ms = [m * np.eye(n) for m in np.geomspace(0.01, 400, 120)]
    for _ in range(40):
        G = rng.normal(size=(n, n))
        Ms.append(G @ G.T * rng.uniform(0.01, 50))
    Ms = np.array(Ms)
    for X0 in X0s:
        got = db.first_exceedances(X0, Ms, s)
        want = [_walk_per_M(X0, M, s) for M in Ms]
        assert got.tolist() == want
        assert [db.first_exceedance(X0, M, s) for M in Ms[::7]] == want[::7]
    ok = np.array([bool(riccati.psd_leq(riccati.pbar(s), M)) for M in Ms])
    assert db.k2_each(Ms[ok], s).tolist() == [_walk_per_M(riccati.pbar(s), M, s) for M in Ms[ok]]


def test_leq_each_is_psd_leq_per_matrix():
    """The batched comparison gives psd_leq(X, M) for each M with its own scale (finite and non-finite X)."""
    from netkf_cli.linalg import riccati
    rng = np.random.default_rng(3)
    for n in (1, 2, 4):
        Ms = np.array([(lambda G: G @ G.T * rng.uniform(0.1, 30))(rng.normal(size=(n, n))) for _ in range(60)]
                      + [0.5 * np.eye(n)])
        # the last X sits between the tolerances of M = 0.5·I (scale 1) and of the large M: per-M scale decides
        for X in (Ms[0], Ms[5] * 0.5, np.full((n, n), np.inf), Ms[1] + 1e-12, (0.5 + 2e-9) * np.eye(n)):
            assert db.leq_each(X, Ms).tolist() == [bool(riccati.psd_leq(X, M)) for M in Ms]


def test_delay_distributions_cdf_and_sampling_agree():
    rng = np.random.default_rng(3)
    n = 200_000
    for dist in (PoissonDelay(mean=3), GeometricDelay(p=0.4), PmfDelay(probs=[0.5, 0.2, 0.1])):
        x = dist.sample(rng, n)
        for i in range(4):
            p = float(dist.cdf(i))
            emp = np.mean(x <= i)
            assert abs(emp - p) <= 5 * math.sqrt(p * (1 - p) / n) + 1e-12
    assert PmfDelay(probs=[0.5, 0.2, 0.1]).loss == pytest.approx(0.2)
