"""Delay sampler (inverse CDF), kept indicators, and the MKF over the time-k view (on the Kalman core)
against per-run references."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from netkf_cli.linalg import riccati
from netkf_cli.channels.delay import (LOST, arrivals_now, cdf_table, delays_from_uniforms, kept_at,  # noqa: F401
                                      kept_thresholds, sample_capped_delays)
from netkf_cli.linalg import kalman
from netkf_cli.estimators.buffered import BufferedEstimator, availability, covariance_from_kept, mkf
from netkf_cli.core.system import LinearSystem

from ._systems import bernoulli, pmf, poisson, scalar_system, vehicle_system


@pytest.mark.parametrize("ch", [poisson(3, 5), pmf([0.5, 0.2, 0.1], 4), bernoulli(0.7)])
def test_inverse_cdf_delays_have_the_channel_pmf(ch):
    """Capped delays from uniforms have pmf f(0..cap) and mass 1 − F(cap) at cap+1.

    Each bin count is Binomial(n, f): |count/n − f| ≤ 5·√(f(1−f)/n) (5σ per bin).
    """
    n, cap = 200_000, 6
    d = sample_capped_delays(np.random.default_rng(1), ch, n, cap)
    F = cdf_table(ch, cap)
    f = np.diff(np.concatenate([[0.0], F, [1.0]]))
    emp = np.bincount(d, minlength=cap + 2) / n
    assert np.all(np.abs(emp - f) <= 5 * np.sqrt(f * (1 - f) / n) + 1e-12)


def test_inverse_cdf_agrees_with_the_model_sampler():
    """The channel model's own sampler (rng.poisson) and the inverse-CDF path give the same pmf (5σ per bin)."""
    ch = poisson(5, 10)
    n, cap = 200_000, 12
    a = np.minimum(ch.delay.sample(np.random.default_rng(2), n), cap + 1)
    b = sample_capped_delays(np.random.default_rng(3), ch, n, cap)
    pa, pb = np.bincount(a, minlength=cap + 2) / n, np.bincount(b, minlength=cap + 2) / n
    # difference of two independent proportions: s.e. √(2 p(1−p)/n)
    p = (pa + pb) / 2
    assert np.all(np.abs(pa - pb) <= 5 * np.sqrt(2 * p * (1 - p) / n) + 1e-12)


@pytest.mark.parametrize("conv,Dmax", [("delay_le_D", 3), ("delay_lt_D", 2)])
def test_kept_and_arrivals_follow_the_convention(conv, Dmax):
    k = 8
    delays = np.array([0, 1, 2, 3, 4, 9, LOST, 0])  # packets s = 1..8
    kept = kept_at(delays, k, 3, conv)
    age = k - np.arange(1, k + 1)
    expect = (delays.astype(np.int64) <= np.minimum(age, Dmax))
    assert np.array_equal(kept, expect)
    now = arrivals_now(delays, k, 3, conv)
    assert np.array_equal(now, (delays == age) & (age <= Dmax))
    # kept_thresholds = Pr[kept by k] = F(min(age, Dmax))
    ch = poisson(2, 3, conv)
    th = kept_thresholds(ch, k)
    assert np.allclose(th, ch.cdf(np.minimum(age, Dmax)))


def _loop_mkf(s: LinearSystem, P0, avail_seq):
    """Per-run, per-step reference: P ← g̃(h(P)) if available else h(P) (Sec. 3.1).

    Also returns the largest |P⁻| met: the update P⁻ − K S Kᵀ cancels digits in proportion to it.
    """
    P, big = P0, 1.0
    for a in avail_seq:
        P = riccati.h(P, s)
        big = max(big, float(np.abs(P).max()))
        if a:
            P = riccati.gtilde(P, s)
    return P, big


def _random_system(draw, n, m):
    rng = np.random.default_rng(draw(st.integers(0, 2**31)))
    A = rng.normal(size=(n, n))
    # spectral radius in [0.3, 1.2]: long outages stay moderate, so both paths keep their digits
    # (the update P⁻ − K S Kᵀ loses ~ eps·|P⁻|²/|R| when P⁻ explodes; that is conditioning, not a bug)
    A *= draw(st.floats(0.3, 1.2)) / max(np.max(np.abs(np.linalg.eigvals(A))), 1e-3)
    C = rng.normal(size=(m, n))
    Lq = rng.normal(size=(n, n))
    Lr = rng.normal(size=(m, m))
    return LinearSystem.create(A, C, Lq @ Lq.T + 0.1 * np.eye(n), Lr @ Lr.T + 0.2 * np.eye(m)), rng


@settings(max_examples=25, deadline=None)
@given(st.data(), st.integers(1, 4), st.integers(1, 3))
def test_batched_mkf_equals_per_run_loop(data, n, m):
    """The MKF on the core (``kalman.Filter.step`` with γ_t = a_t) equals the plain loop (riccati.h /
    g̃) for random systems, any n, m."""
    s, rng = _random_system(data.draw, n, m)
    runs, T = 7, 12
    avail = rng.random((T, runs)) < 0.6
    P0 = np.eye(n) * 0.5
    got = mkf(kalman.Filter.of(s, 1), np.repeat(P0[:, :, None], runs, axis=2), avail)
    for r in range(runs):
        ref, big = _loop_mkf(s, P0, avail[:, r])
        # both paths round differently; the error is ~ machine eps × the largest prior met
        assert np.allclose(got[:, :, r], ref, rtol=1e-8, atol=1e-11 * big)
        assert np.array_equal(got[:, :, r], got[:, :, r].T)
        assert np.linalg.eigvalsh(got[:, :, r])[0] >= -1e-11 * big


def test_all_packets_kept_gives_the_standard_filter():
    """γ ≡ 1 ⇒ the MKF is the Kalman filter: P_k → P̄ = g̃(P*) (scipy DARE)."""
    for s in (scalar_system(), vehicle_system()):
        P = covariance_from_kept(s, np.ones((200, 3), dtype=bool), 1, P0=np.eye(s.n))
        assert np.allclose(P, riccati.pbar(s)[:, :, None], rtol=1e-9, atol=1e-12)


def test_overflow_is_counted_not_nan():
    """An unstable run with no packets overflows to ∞ (the core's Rescue policy: the variances of the
    unknown directions are ∞, their decoupled covariances stay 0, nothing is NaN): λ_max = ∞, counted as
    P ≰ M; a run that keeps receiving stays finite."""
    from netkf_cli.linalg import batched

    s = LinearSystem.create(np.diag([3.0, 2.0]), np.eye(2), np.eye(2), np.eye(2))
    with np.errstate(all="ignore"):
        P = covariance_from_kept(s, np.tile(np.array([[False, True]]), (800, 1)), 1, P0=np.eye(2))
    assert np.all(np.isinf(np.diagonal(P[:, :, 0]))) and not np.isnan(P).any()
    assert np.all(np.isfinite(P[:, :, 1]))
    assert batched.lambda_max(P)[0] == np.inf and not batched.psd_leq(P, 1e6)[0]
    s1 = LinearSystem.create(3.0, 1, 1, 1)
    with np.errstate(all="ignore"):
        P1 = covariance_from_kept(s1, np.zeros((800, 1), dtype=bool), 1, P0=np.eye(1))
    assert np.isinf(P1).all() and not np.isnan(P1).any()


@pytest.mark.parametrize("which", ["scalar", "vehicle"])
def test_covariances_equal_reference_on_the_same_delays(which):
    """sample_trace + covariances([k]) (prefix pass, compiled or numpy) give the P_k of the reference
    path (delays from the same uniforms → kept_at → covariance_from_kept)."""
    s, ch, span = (scalar_system(), poisson(5, 10), 1) if which == "scalar" else (vehicle_system(), poisson(3, 5), 2)
    runs, k = 500, 40
    tr = ch.sample_trace(np.random.default_rng(7), runs, k)
    u = np.random.default_rng(7).random((k, runs))
    delays = delays_from_uniforms(u, cdf_table(ch, k - 1))
    kept = kept_at(delays, k, ch.D, ch.convention)
    ref = covariance_from_kept(s, kept, span)
    for backend in ("numpy", "numba"):
        (_, out), = BufferedEstimator(kind="buffered", backend=backend).covariances(s, tr, [k])
        assert np.abs(out["filtered"] - ref).max() <= 1e-12 * np.abs(ref).max(), backend
    (_, out), = BufferedEstimator(kind="buffered", backend="numpy").covariances(s, tr, [k])
    assert np.array_equal(out["filtered"], ref)  # the numpy path is the same core sequence: bitwise


def test_availability_pair_packets():
    kept = np.array([[0], [1], [0], [0], [1]], dtype=bool)
    assert availability(kept, 2)[:, 0].tolist() == [True, True, False, True, True]
    assert availability(kept, 1)[:, 0].tolist() == kept[:, 0].tolist()


@pytest.mark.parametrize("runs,horizon,block", [(7, 5, 1 << 18), (300, 40, 1000), (301, 41, 1000), (5, 3, 1),
                                                (20_000, 60, 1 << 18)])
def test_delay_trace_in_blocks_is_the_one_shot_trace(runs, horizon, block, monkeypatch):
    """delay_trace draws its uniforms in blocks of rows into one buffer: the same delays, arrivals and generator
    state afterwards as one rng.random((horizon, runs)) inverted at once (searchsorted, LOST beyond the horizon)."""
    from netkf_cli.channels import delay as dl

    monkeypatch.setattr(dl, "TRACE_BLOCK", block)
    ch = poisson(5, 10)
    r1, r2 = np.random.default_rng(11), np.random.default_rng(11)
    tr = dl.delay_trace(ch, r1, runs, horizon)
    u = r2.random((horizon, runs))
    d = np.searchsorted(cdf_table(ch, horizon - 1), u, side="right").astype(np.int32)
    d[d >= horizon] = LOST
    assert tr.delay.dtype == np.int32 and np.array_equal(tr.delay[0], d)
    assert np.array_equal(tr.arrival[0], d == 0)
    assert r1.random() == r2.random()  # the same number of uniforms consumed


def test_delay_trace_compiles_for_the_whole_array(monkeypatch):
    """The compiled-or-not choice is made for the whole horizon × runs array (compiled_trace), not per block: a
    trace of ≥ AUTO_MIN_RUN_STEPS entries inverts every block with the compiled loop (before, each block of
    TRACE_BLOCK entries was below the threshold and took the numpy path); a small one in a process without numba
    stays on numpy."""
    import sys

    from netkf_cli.channels import delay as dl
    from netkf_cli.linalg.kalman import AUTO_MIN_RUN_STEPS

    seen = []
    real = dl.inverse_cdf
    monkeypatch.setattr(dl, "inverse_cdf", lambda u, table, **kw: (seen.append(kw.get("compiled")), real(u, table, **kw))[1])
    runs = AUTO_MIN_RUN_STEPS // 100
    dl.delay_trace(poisson(5, 10), np.random.default_rng(1), runs, 100)
    assert len(seen) > 1 and all(c is True for c in seen)
    assert dl.compiled_trace(AUTO_MIN_RUN_STEPS) and not dl.compiled_trace(dl.TRACE_BLOCK - 1)
    monkeypatch.delitem(sys.modules, "numba", raising=False)
    assert not dl.compiled_trace(dl.TRACE_BLOCK)  # numba not imported: its import is not worth a small trace
