"""The issue-12 contract for the Shi 2009 channels and estimators, and the overflow fix (issue 14.4).

* channels: ``trace_kinds``, ``sample_trace`` (layout, delays vs the inverse-CDF kernel),
  ``loss_rate``, ``delay_pmf``;
* estimators: ``covariances`` against an independent per-run loop (``riccati.h``/``gtilde`` on
  the kept pattern of every k) on the same trace, for every step; ``check``;
* overflow: A = diag(1e6, 0.5), C = I, Bernoulli 0.05 — Pr[P_k ≤ M] within 5 s.e. of the exact 0.05,
  no numpy warnings, the numba backend equal to numpy.
"""

import warnings

import numpy as np
import pytest

from netkf_cli import riccati
from netkf_cli.channels.delay import kept_at, max_kept_delay
from netkf_cli.errors import ConfigError
from netkf_cli.estimators.buffered import (BufferedEstimator, availability, buffered_mc_kernel,
                                           packet_span)
from netkf_cli.estimators.smart_sensor import SmartSensorEstimator
from netkf_cli.montecarlo import run_chunked
from netkf_cli.system import LinearSystem
from netkf_cli.trace import LOST, Trace

from ._systems import bernoulli, pmf, poisson, scalar_system, vehicle_system


def _dense_3x1() -> LinearSystem:
    """n = 3, m = 1: C not invertible and not the Appendix B case (2m ≠ n)."""
    g = np.random.default_rng(3)
    A = g.normal(size=(3, 3)) * 0.5 + np.diag([1.1, 0.3, 0.2])
    L = g.normal(size=(3, 3))
    return LinearSystem.create(A, g.normal(size=(1, 3)), L @ L.T * 0.1 + 0.01 * np.eye(3), 0.4)


def _overflow_system() -> LinearSystem:
    return LinearSystem.create(np.diag([1e6, 0.5]), np.eye(2), np.eye(2), np.eye(2))


# --------------------------------------------------------------------------------------------
# channels
# --------------------------------------------------------------------------------------------


def test_delay_channel_trace_layout_and_kinds():
    ch = poisson(3, 4, "delay_lt_D")
    assert ch.trace_kinds == frozenset({"delay", "arrival"})
    tr = ch.sample_trace(np.random.default_rng(0), 7, 30)
    assert isinstance(tr, Trace) and tr.delay.shape == (1, 30, 7) and tr.delay.dtype == np.int32
    assert tr.meta["buffer"] == 4 and tr.meta["convention"] == "delay_lt_D"
    assert np.array_equal(tr.arrival, tr.delay == 0)  # arrival = usable on time
    assert np.all((tr.delay >= 0) & ((tr.delay < 30) | (tr.delay == LOST)))


def test_delay_trace_uses_the_kernel_uniforms():
    """d ≤ j ⇔ u < F(j): the trace's delays reproduce the kernel's kept decisions packet by packet."""
    ch = pmf([0.3, 0.2, 0.1], 2)  # loss 0.4
    T, runs = 12, 500
    tr = ch.sample_trace(np.random.default_rng(4), runs, T)
    U = np.random.default_rng(4).random((T, runs))
    F = ch.cdf(np.arange(T))
    for j in range(T):
        assert np.array_equal(tr.delay[0] <= j, U < F[j])
    # lost packets are LOST; empirical loss rate within 5 s.e. of 0.4
    lost = (tr.delay[0] == LOST).mean()
    assert abs(lost - 0.4) <= 5 * np.sqrt(0.24 / (T * runs))


def test_loss_rate_and_pmf():
    ch = pmf([0.5, 0.25], 1)
    assert np.allclose(ch.delay_pmf(4), [0.5, 0.25, 0, 0])
    assert ch.loss_rate() == pytest.approx(0.25)  # delay_le_D, D = 1: delays 0 and 1 kept
    assert pmf([0.5, 0.25], 1, "delay_lt_D").loss_rate() == pytest.approx(0.5)
    b = bernoulli(0.7)
    assert b.trace_kinds == frozenset({"arrival"})
    assert b.loss_rate() == pytest.approx(0.3) and np.allclose(b.delay_pmf(3), [0.7, 0, 0])
    tr = b.sample_trace(np.random.default_rng(1), 4000, 5)
    assert tr.arrival.shape == (1, 5, 4000) and tr.delay is None
    assert abs(tr.arrival.mean() - 0.7) <= 5 * np.sqrt(0.21 / 20000)


# --------------------------------------------------------------------------------------------
# estimators: batched covariances == a per-run loop on the same trace
# --------------------------------------------------------------------------------------------


def _loop_buffered(s, delays, k, D, conv, span, P0):
    """P_k of one run: kept pattern at k (eq. 4), availability, then h / g̃ step by step."""
    kept = kept_at(delays[:k], k, D, conv)
    a = availability(kept, span)
    X = P0
    for t in range(k):
        X = riccati.h(X, s)
        if a[t]:
            X = riccati.gtilde(X, s)
    return X


def _loop_smart(s, delays, k, D, conv, P0):
    Dmax = max_kept_delay(D, conv)
    X = riccati.pbar(s)
    for t in range(k):  # packet k − t, age t
        if delays[k - 1 - t] <= min(t, Dmax):
            return riccati.h_power(X, s, t)
    return riccati.h_power(P0, s, k)


CASES = {  # system, channel, span
    "scalar": (scalar_system(), poisson(2, 3), 1),
    "vehicle_pairs": (vehicle_system(), poisson(1.5, 2, "delay_lt_D"), 2),
    "dense_3x1_measurement": (_dense_3x1(), pmf([0.4, 0.2, 0.2], 2), 1),
    "bernoulli_2x2": (LinearSystem.create([[1.2, 0.3], [0, 0.8]], np.eye(2), np.eye(2) * 0.1, np.eye(2) * 0.2),
                      bernoulli(0.6), 1),
    # buffer longer than the horizon: which packets are final is decided by the in-flight ones
    "big_buffer_2x2": (LinearSystem.create([[1.1, 0.2], [0, 0.9]], np.eye(2), np.eye(2) * 0.1, np.eye(2) * 0.3),
                       pmf([0.3, 0.1, 0.1, 0.1, 0.05, 0.05, 0.05], 40), 1),
    "big_buffer_vehicle_pairs": (vehicle_system(), pmf([0.4, 0.1, 0.1, 0.1, 0.1], 40, "delay_lt_D"), 2),
}


@pytest.mark.parametrize("name", list(CASES))
def test_buffered_covariances_equal_per_run_loop(name):
    s, ch, span = CASES[name]
    est = BufferedEstimator(kind="buffered")
    assert est.span(s) == span
    est.check(s, ch)
    T, runs = 16, 12
    tr = ch.sample_trace(np.random.default_rng(7), runs, T)
    steps = list(range(1, T + 1))
    got = dict(est.covariances(s, tr, steps))
    assert sorted(got) == steps
    d = tr.delay[0] if tr.delay is not None else np.where(tr.arrival[0], 0, LOST)
    P0 = riccati.pbar(s)
    for k in (1, 2, 5, 9, T):
        P = got[k]
        assert P.shape == (s.n, s.n, runs)
        for r in range(runs):
            ref = _loop_buffered(s, d[:, r], k, ch.D, ch.convention, span, P0)
            assert np.allclose(P[:, :, r], ref, rtol=1e-9, atol=1e-12), (name, k, r)
    # one step only (the Monte Carlo kernel's case) gives the same matrices
    (k, P1), = est.covariances(s, tr, [T])
    assert k == T and np.array_equal(P1, got[T])


@pytest.mark.parametrize("name", ["scalar", "vehicle_pairs", "bernoulli_2x2"])
def test_smart_sensor_covariances_equal_per_run_loop(name):
    s, ch, _ = CASES[name]
    est = SmartSensorEstimator(kind="smart_sensor")
    est.check(s, ch)
    T, runs = 14, 10
    tr = ch.sample_trace(np.random.default_rng(8), runs, T)
    d = tr.delay[0] if tr.delay is not None else np.where(tr.arrival[0], 0, LOST)
    got = dict(est.covariances(s, tr, [1, 4, T]))
    P0 = riccati.pbar(s)
    for k, P in got.items():
        for r in range(runs):
            ref = _loop_smart(s, d[:, r], k, ch.D, ch.convention, P0)
            assert np.allclose(P[:, :, r], ref, rtol=1e-9, atol=1e-12), (name, k, r)


def test_buffered_covariances_at_horizon_equal_the_monte_carlo_kernel():
    """sample_trace + covariances([T]) and the kernel read the same uniforms: the same P_k per run."""
    s, ch = vehicle_system(), poisson(2, 3)
    T, runs = 25, 300
    M = np.geomspace(0.05, 2, 7)
    tr = ch.sample_trace(np.random.default_rng(9), runs, T)
    (_, P), = BufferedEstimator(kind="buffered", packet="pair").covariances(s, tr, [T])
    kern = buffered_mc_kernel(s, ch, 2, T, M, P0=None, backend="numpy")
    mkf, _ = kern.run_uniforms(np.random.default_rng(9).random((T, runs)), runs)
    assert np.array_equal(P, mkf.matrices().transpose(1, 2, 0))


def test_any_C_simulates_with_measurement_packets():
    """Issue 12: n = 3, m = 1 (not Appendix B) — auto → measurement packets, check passes, P finite."""
    s = _dense_3x1()
    assert packet_span(s, "auto") == 1
    with pytest.raises(ConfigError):
        riccati.mbar(s)  # the bounds are unavailable, the simulation is not
    est = BufferedEstimator(kind="buffered")
    est.check(s, bernoulli(0.5))
    (_, P), = est.covariances(s, bernoulli(0.5).sample_trace(np.random.default_rng(0), 50, 40), [40])
    assert np.all(np.isfinite(P))


def test_check_refuses_an_unusable_backend(monkeypatch):
    from netkf_cli.estimators import buffered_numba as bn

    monkeypatch.setattr(bn, "numba_available", lambda: False)

    def missing():
        raise bn.NumbaUnavailable.at("estimator.backend", "numba is not installed")

    monkeypatch.setattr(bn, "require_numba", missing)
    s = scalar_system()
    BufferedEstimator(kind="buffered", backend="auto").check(s, bernoulli(0.5))  # falls back to numpy
    with pytest.raises(ConfigError) as e:
        BufferedEstimator(kind="buffered", backend="numba").check(s, bernoulli(0.5))
    assert e.value.problems[0].path == "estimator.backend"


# --------------------------------------------------------------------------------------------
# overflow (issue 14.4)
# --------------------------------------------------------------------------------------------


def test_overflow_system_monte_carlo_matches_exact_without_warnings():
    """A = diag(1e6, 0.5), C = I, γ = 0.05. P_k ≤ M·I (M ∈ {2, 5, 10}) iff y_k arrived: with it,
    P_k = g̃(·) ≤ M̄ = R = I and its second entry ≤ 1; without it, P_k,11 ≥ 1e12·… . So the exact
    probability is γ = 0.05 (also what delay_exact certifies). 5 s.e. of a proportion at p = 0.05,
    n = 20 000: 5·√(0.05·0.95/20000) = 0.0077; the old code gave 0.0005 (NaN-poisoned runs)."""
    s = _overflow_system()
    n = 20_000
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no raw numpy warnings
        kern = buffered_mc_kernel(s, bernoulli(0.05), 1, 200, [2.0, 5.0, 10.0], P0=None, backend="numpy")
        st = run_chunked(kern, n, 10_000, 0, stream=0)
    p = st["count_leq"] / st["n"]
    assert np.all(np.abs(p - 0.05) <= 5 * np.sqrt(0.05 * 0.95 / n))
    assert st["nonfinite"] == 0 and st["overflow"] > 0 and st["rescued"] > 0


def test_overflow_covariances_reset_exactly_on_arrival():
    """Through the generic contract: runs whose last packet arrived have P_k = g̃(h(P_{k−1})), i.e.
    diag(≈1/(1 + 1e-12…), g̃ of the stable entry) — finite and ≤ I; the others are huge or ∞."""
    s = _overflow_system()
    tr = bernoulli(0.05).sample_trace(np.random.default_rng(2), 4000, 120)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        (k, P), = BufferedEstimator(kind="buffered").covariances(s, tr, [120])
    got = tr.arrival[0, -1]
    assert got.any() and (~got).any()
    Pa = P[:, :, got]
    assert np.allclose(Pa[0, 0], 1.0, rtol=1e-9) and np.allclose(Pa[0, 1], 0.0, atol=1e-12)
    # stable entry: the exact MKF value of a per-run scalar recursion a = 0.5, q = r = 1
    for r in np.flatnonzero(got)[:20]:
        x = riccati.pbar(s)[1, 1]
        for t in range(120):
            x = 0.25 * x + 1
            if tr.arrival[0, t, r]:
                x = x / (1 + x)
        assert P[1, 1, r] == pytest.approx(x, rel=1e-9)
    lam = np.where(np.isfinite(P[0, 0, ~got]), P[0, 0, ~got], np.inf)
    assert np.all(lam > 1e10)


def test_overflow_numba_equals_numpy():
    pytest.importorskip("numba")
    s = _overflow_system()
    M = [2.0, 5.0, 10.0]
    ref = run_chunked(buffered_mc_kernel(s, bernoulli(0.05), 1, 80, M, backend="numpy"), 3000, 1500, 1)
    fast = run_chunked(buffered_mc_kernel(s, bernoulli(0.05), 1, 80, M, backend="numba", threads=1), 3000, 1500, 1)
    for key in ref:
        assert np.array_equal(ref[key], fast[key]), key


# --------------------------------------------------------------------------------------------
# bounded loops over the buffer length (issue 14.3)
# --------------------------------------------------------------------------------------------


def test_huge_buffer_is_linear():
    """D = 10⁶: the closed form, the updates kernel and the smart-sensor sampler finish in well under
    a second each (the former O(D²) loop never finished). Limits are generous for a loaded machine."""
    import time

    from netkf_cli.analysis import delay_exact as dx
    from netkf_cli.estimators.buffered import UpdatesKernel
    from netkf_cli.estimators.smart_sensor import sample_N

    ch = poisson(5, 1_000_000)
    t = time.perf_counter()
    eu = dx.expected_updates(ch)
    st = UpdatesKernel(ch)(np.random.default_rng(0), 10_000)
    N = sample_N(np.random.default_rng(0), 10_000, ch)
    assert time.perf_counter() - t < 3.0
    # D → ∞ limit vs D = 40: Poisson(5) mass beyond 40 is < 1e-20
    assert eu == pytest.approx(dx.expected_updates(poisson(5, 40)), rel=1e-12)
    assert np.isfinite(st["sum"]) and N.max() < 100


def test_smart_sampler_matches_theta():
    """Pr[N_k ≥ t] = θ(t, D) (eq. 8) for t = 1..8, within 5 s.e. (the inverse transform is exact)."""
    from netkf_cli.analysis import delay_bounds as db
    from netkf_cli.estimators.smart_sensor import sample_N

    ch = pmf([0.3, 0.1, 0.2], 3)  # loss 0.4: geometric tail past the buffer
    n = 50_000
    N = sample_N(np.random.default_rng(1), n, ch)
    for t in range(1, 9):
        th = db.theta(t, ch.D, ch.cdf, ch.convention)
        assert abs((N >= t).mean() - th) <= 5 * np.sqrt(th * (1 - th) / n) + 1 / n, t


def test_updates_vs_buffer_refuses_a_huge_D_max_at_validate_time():
    from pydantic import ValidationError

    from netkf_cli.recipes.shi2009_updates import D_MAX_LIMIT, UpdatesVsBuffer

    UpdatesVsBuffer(kind="updates_vs_buffer", D_max=D_MAX_LIMIT)
    with pytest.raises(ValidationError):
        UpdatesVsBuffer(kind="updates_vs_buffer", D_max=D_MAX_LIMIT + 1)


def test_multi_sensor_channel_is_refused():
    from netkf_cli.channels.multi import MultiChannel

    ch = MultiChannel(kind="multi", sensors=3, loss=0.2)
    for est in (BufferedEstimator(kind="buffered"), SmartSensorEstimator(kind="smart_sensor")):
        with pytest.raises(ConfigError) as e:
            est.check(scalar_system(), ch)
        assert e.value.problems[0].path == "estimator.kind"


@pytest.mark.parametrize("name", ["scalar", "vehicle_pairs", "big_buffer_2x2", "bernoulli_2x2"])
def test_compiled_covariances_equal_numpy(name):
    """One requested step with backend auto (numba present): the compiled MKF on the time-k kept
    pattern gives the numpy path's P_k bit for bit."""
    pytest.importorskip("numba")
    s, ch, _ = CASES[name]
    tr = ch.sample_trace(np.random.default_rng(12), 700, 30)
    for k in (30, 17):
        (_, Pn), = BufferedEstimator(kind="buffered", backend="numpy").covariances(s, tr, [k])
        (_, Pc), = BufferedEstimator(kind="buffered", backend="auto").covariances(s, tr, [k])
        assert np.array_equal(Pn, Pc), (name, k)


def test_compiled_covariances_fall_back_on_overflow():
    pytest.importorskip("numba")
    s = _overflow_system()
    tr = bernoulli(0.05).sample_trace(np.random.default_rng(2), 500, 60)
    (_, Pn), = BufferedEstimator(kind="buffered", backend="numpy").covariances(s, tr, [60])
    (_, Pc), = BufferedEstimator(kind="buffered", backend="auto").covariances(s, tr, [60])
    assert np.array_equal(Pn, Pc)


def test_overflow_covariances_equal_the_kernel_bitwise():
    """With the information-form rescue active, covariances([T]) (prefix pass + re-run from a copy)
    and the Monte Carlo kernel (one pass) still give the same P_k bits on the same uniforms."""
    s, ch = _overflow_system(), pmf([0.05, 0.02], 1)
    T, runs = 60, 400
    tr = ch.sample_trace(np.random.default_rng(5), runs, T)
    (_, P), = BufferedEstimator(kind="buffered", backend="numpy").covariances(s, tr, [T])
    kern = buffered_mc_kernel(s, ch, 1, T, [1.0], P0=None, backend="numpy")
    mkf, _ = kern.run_uniforms(np.random.default_rng(5).random((T, runs)), runs)
    assert mkf.rescued.any()
    assert np.array_equal(P, mkf.matrices().transpose(1, 2, 0))


@pytest.mark.parametrize("ch", [poisson(5, 10), pmf([0.3, 0.2, 0.1], 2), poisson(0.01, 3), bernoulli(0.999)])
def test_bucketed_inverse_cdf_is_searchsorted(ch):
    """Exact, including u on and next to every breakpoint F(i) and u just below 1."""
    from netkf_cli.channels.delay import cdf_table, inverse_cdf

    tab = cdf_table(ch, 49)
    u = np.random.default_rng(0).random((50, 3000))
    edge = np.unique(np.concatenate([tab, np.nextafter(tab, 0), np.nextafter(tab, 1), [0.0, 1 - 2**-53]]))
    edge = edge[(edge >= 0) & (edge < 1)]
    u[0, :len(edge)] = edge
    assert np.array_equal(inverse_cdf(u, tab), np.searchsorted(tab, u, side="right"))


@pytest.mark.filterwarnings("ignore:buffered.*overflowed:UserWarning")  # the metric's one-line summary
def test_overflow_scenario_end_to_end(tmp_path):
    """Issue 14.4 through the scenario runner and the generic distribution metric: Monte Carlo within
    5 s.e. of the exact 0.05 (s.e. at p = 0.05, n = 4000: 0.0034), no numpy warning."""
    import pandas as pd
    import yaml

    from netkf_cli.runner import run_scenario_file

    doc = {"name": "overflow", "system": {"A": [[1e6, 0], [0, 0.5]], "C": [[1, 0], [0, 1]], "Q": [[1, 0], [0, 1]],
                                          "R": [[1, 0], [0, 1]]},
           "channel": {"kind": "bernoulli", "arrival": 0.05}, "estimator": {"kind": "buffered"},
           "analysis": {"kind": "distribution", "M": [2, 5, 10]},
           "montecarlo": {"runs": 4000, "horizon": 120, "seed": 0, "chunk": 2000}}
    p = tmp_path / "overflow.yaml"
    p.write_text(yaml.safe_dump(doc), encoding="utf-8")
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        out = run_scenario_file(p, out_dir=tmp_path / "out", force=True)
    t = pd.read_csv(out / "overflow.csv")
    mc = t[t.series == "monte_carlo"]
    assert len(mc) == 3
    assert np.all(np.abs(mc.value - 0.05) <= 5 * np.sqrt(0.05 * 0.95 / 4000))
    ex = t[t.series == "exact"]
    assert np.allclose(ex.value, 0.05, atol=1e-6)
