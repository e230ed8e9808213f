"""Fading engine (issues 12, 13, 15): compiled = numpy, picklable kernels on worker processes,
the estimator/channel contract, the variance-reduced estimators against exact values."""

import json
import math
import pickle

import numpy as np
import pytest

from netkf_cli import engine
from netkf_cli.analysis import fading as fa
from netkf_cli.channels.fading import FadingChannel, jakes_factor
from netkf_cli.estimators import fading_receivers as fr
from netkf_cli.runtime.montecarlo import execution, mean_and_stderr, run_chunked
from netkf_cli.core.system import LinearSystem

A5 = np.array([[2, 0.3, 0.45], [0.4, 0.2, 0.5], [1.5, 0.6, 0.34]])
Q5 = 1e-3 * np.eye(3)
AL, DE = fa.noise_params_from_bits(10, 40 / 2**10)
NZ = fr.NoiseFn("ber", AL, DE)
CASES = {  # (scenario, C, R)
    "s1": (1, 2 * np.eye(3), 1e-8 * np.eye(3)),
    "s2_square": (2, 2 * np.eye(3), 1e-8 * np.eye(3)),
    "s3_square": (3, 2 * np.eye(3), 1e-8 * np.eye(3)),
    "s2_general": (2, np.array([[1.0, 2, 3]]), np.array([[1e-8]])),
    "s3_general": (3, np.array([[1.0, 2, 3]]), np.array([[1e-8]])),
    "s3_m2": (3, np.array([[1.0, 0, 1], [0, 1, 0]]), np.diag([1e-4, 2e-4])),
}
needs_numba = pytest.mark.skipif(not fr.numba_available(), reason="numba not installed")


def rm(key):
    sc, C, R = CASES[key]
    return fr.ReceiverModel(sc, A5, C, Q5, R, NZ)


def chan(**kw):
    base = {"kind": "fading", "snr_avg": {"value": 20, "unit": "dB"}, "noise": {"model": "ber", "N_p": 10, "Delta": 0.0390625}}
    base.update(kw)
    return FadingChannel.model_validate(base)


# ------------------------------------------------------------------ compiled backend = numpy reference


@needs_numba
@pytest.mark.parametrize("key", sorted(CASES))
def test_numba_equals_numpy_on_the_same_uniforms(key):
    """Same uniforms ⇒ same recursion. The compiled loop sums matrix products in index order and numpy
    (einsum/BLAS) may not, so per-run values agree to rounding, amplified by the information-form
    inversions of near-singular matrices after drop bursts (≤ 1e-6 relative per run, seen for m < n);
    the MEANS over runs agree to 1e-7 relative (1e-12 for the well-conditioned cases) — far below any
    Monte Carlo standard error (≥ 1e-4 relative at the artefacts' sizes)."""
    th = np.repeat(np.array([0.0, 6.0, 12.0, 17.0]), 200)
    mu = fa.mu_ave(th, 100.0)
    out = {}
    for be in ("numpy", "numba"):
        out[be] = fr.burst_conditioned_paths(rm(key), np.random.default_rng(3), th, mu, 100.0, np.eye(3), 40, [10, 40],
                                             backend=be, final_strata=4)
    for x, y in zip(out["numpy"], out["numba"]):
        assert np.array_equal(np.isfinite(x), np.isfinite(y))
        f = np.isfinite(x)
        np.testing.assert_allclose(y[f], x[f], rtol=1e-6, atol=1e-300)
        np.testing.assert_allclose(y.mean(-1), x.mean(-1), rtol=1e-7)


@needs_numba
@pytest.mark.parametrize("C,R", [(2 * np.eye(3), 1e-8 * np.eye(3)), (np.array([[1.0, 2, 3]]), np.array([[1e-8]]))],
                         ids=["square", "general"])
def test_numba_engine_statistics_equal_numpy(C, R):
    # the generic engine's time-average statistics (what time_average / mean_vs_time reduce) of receivers 2 and 3
    # (the burst-conditioned estimate for means, Rao–Blackwellized for receiver 2) on the same uniforms
    from netkf_cli.estimators.fading_receivers import ReceiverEstimator

    s = LinearSystem.create(A5, C, Q5, R, np.eye(3))
    ch = chan(threshold={"value": 14, "unit": "linear"})
    steps = list(range(11, 31))
    out = {}
    for be in ("numpy", "numba"):
        ests = [ReceiverEstimator(kind="receiver", scenario=sc, backend=be) for sc in (2, 3)]
        out[be] = engine.simulate(s, ch, ests, engine.TimeAverageReducer(steps), steps=steps, runs=100, horizon=30,
                                  seed=1, chunk=50)
    a, b = out["numpy"], out["numba"]
    assert sorted(a) == sorted(b) and a["n"] == 100
    for k in a:
        np.testing.assert_allclose(b[k], a[k], rtol=1e-7, err_msg=k)  # see the test above


def test_backend_auto_picks_numba_when_importable_and_numpy_when_hidden(monkeypatch):
    import sys

    if fr.numba_available():
        assert fr.resolve_backend("auto") == "numba"
    monkeypatch.setitem(sys.modules, "numba", None)  # import numba now raises ImportError
    assert fr.resolve_backend("auto") == "numpy"
    from netkf_cli.core.errors import ConfigError

    with pytest.raises(ConfigError) as e:
        fr.resolve_backend("numba")
    assert "estimator.backend" in str(e.value)


# ------------------------------------------------------------------ kernels are picklable and really run on workers


@pytest.mark.parametrize("make", ["paths", "smc"])
def test_kernels_pickle_and_process_pool_equals_serial(make):
    # Fig. 7's own kernels (the receivers' generic kernel on workers: the fig6 case below)
    T = np.array([2.0, 14.0])
    if make == "paths":
        jch = chan(correlation={"model": "jakes", "carrier_hz": 1e9, "speed": {"value": 25, "unit": "mph"}, "interval_s": 0.01})
        k = fr.CorrelatedPathKernel(jch, fr.ReceiverModel(2, np.array([[2.0]]), np.array([[1.0]]), np.array([[1e-3]]),
                                                          np.array([[1e-8]]), NZ), T, np.eye(1), 12, 3, backend="numpy")
    else:
        k = fr.BurstSMCKernel(None, T, 100.0, NZ, fr.memoryless_coefficients(2.0, 1.0, 1e-3, 1e-8, 1.0, 12), 12, particles=4)
    pickle.loads(pickle.dumps(k))
    serial = run_chunked(k, 40, 10, 5, stream=3)
    with execution("process", jobs=2):
        par = run_chunked(k, 40, 10, 5, stream=3)
    assert sorted(serial) == sorted(par)
    for key in serial:
        assert np.array_equal(serial[key], par[key]), key


@pytest.mark.parametrize("stem,extra", [("fig6", {"analysis": {"at": 20, "over": {"channel.threshold.value": [0, 9, 16]}},
                                                 # numpy: what is tested is the executor, not compiled code
                                                 "estimators": [{"kind": "receiver", "scenario": s, "backend": "numpy"}
                                                                for s in (2, 3)]}),
                                        ("fig7", {"analysis": {"over": {"channel.threshold.value": [2, 14]}}})])
def test_jobs2_csv_equals_serial_byte_for_byte(tmp_path, stem, extra):
    """Worker processes give the same bytes as the parent (no BLAS product whose rounding depends on the
    thread count: the Jakes generator and the SMC's conditional means use einsum)."""
    from pathlib import Path

    from netkf_cli.app.runner import run_scenario_file

    cfg = Path(__file__).resolve().parents[2] / "configs" / "fading" / f"{stem}.yaml"
    ov = {**extra, "montecarlo": {"horizon": 20, "chunk": 10, **extra.get("montecarlo", {})}}
    a = run_scenario_file(cfg, out_dir=tmp_path / "serial", runs=40, force=True, overrides=ov)
    b = run_scenario_file(cfg, out_dir=tmp_path / "jobs2", runs=40, force=True, overrides=ov, executor="process", jobs=2)
    ran = json.loads((b / "manifest.json").read_text())["execution"]["chunks_ran"]
    # the chunks really ran on two processes: the parent and its one worker (jobs=2, Execution.workers)
    assert ran["chunks"] >= 4 and ran["chunks_in_parent"] < ran["chunks"] and ran["processes"] <= 2, ran
    names = sorted(p.name for p in a.glob("*.csv"))
    assert names
    for name in names:
        assert (a / name).read_bytes() == (b / name).read_bytes(), name


# ------------------------------------------------------------------ contracts (issue 12)


def test_channel_trace_contract():
    ch = chan()
    assert ch.trace_kinds == frozenset({"snr"})
    tr = ch.sample_trace(np.random.default_rng(0), 7, 5)
    assert tr.snr.shape == (5, 7) and tr.kinds == frozenset({"snr"})
    np.testing.assert_array_equal(tr.snr, ch.sample(np.random.default_rng(0), 7, 5).snr)
    law = ch.snr_law()
    assert law["distribution"] == "exponential" and law["mean"] == pytest.approx(100.0)
    assert float(law["mu_ave"](14.0)) == pytest.approx(1 - math.exp(-0.14))
    pickle.dumps(tr.meta["noise"])


@pytest.mark.parametrize("sc", [1, 2, 3])
def test_estimator_covariances_equal_the_reference_recursion(sc):
    from netkf_cli.estimators.fading_receivers import ReceiverEstimator

    s = LinearSystem.create(A5, 2 * np.eye(3), Q5, 1e-8 * np.eye(3), np.eye(3))
    est = ReceiverEstimator.model_validate({"kind": "receiver", "scenario": sc, "threshold": {"value": 10, "unit": "linear"},
                                            "backend": "numpy"})
    ch = chan()
    est.check(s, ch)
    assert "snr" in est.accepts and est.quantities == ("filtered", "predicted")
    tr = ch.sample_trace(np.random.default_rng(2), 30, 25)
    got = dict(est.covariances(s, tr, [1, 7, 25], ("predicted",)))
    # system.P0 is P_{0|0}: the prior of y_1 is A P0 Aᵀ + Q; after y_k, ``predicted`` is P_{k+1|k}
    ref = fr.covariance_paths(fr.ReceiverModel(sc, A5, 2 * np.eye(3), Q5, 1e-8 * np.eye(3), NZ), tr.snr, 10.0,
                              A5 @ A5.T + Q5, record=[1, 7, 25])
    for i, k in enumerate([1, 7, 25]):
        assert sorted(got[k]) == ["predicted"] and got[k]["predicted"].shape == (3, 3, 30)
        np.testing.assert_allclose(got[k]["predicted"], ref[i], rtol=1e-12)


def test_estimator_check_refuses_bad_pairs():
    from netkf_cli.core.errors import ConfigError
    from netkf_cli.estimators.fading_receivers import ReceiverEstimator

    s = LinearSystem.create(A5, 2 * np.eye(3), Q5, 1e-8 * np.eye(3), np.eye(3))
    est = ReceiverEstimator.model_validate({"kind": "receiver", "scenario": 2})
    with pytest.raises(ConfigError) as e:
        est.check(s, chan())
    assert "estimator.threshold" in str(e.value)

    class NoSnr:
        trace_kinds = frozenset({"arrival"})

    est = ReceiverEstimator.model_validate({"kind": "receiver", "scenario": 2, "threshold": {"value": 3, "unit": "dB"}})
    with pytest.raises(ConfigError) as e:
        est.check(s, NoSnr())
    assert "snr" in str(e.value)
    est.check(s.with_P0(None), chan())  # P0 left out = P̄ (the one meaning of P0 in netkf)


def test_degenerate_run_is_nonfinite_not_an_exception():
    """P0 = 0 with scenario 2 and m < n: the filter's C P_f Cᵀ is 0 at the first packet (0/0 gain). Both
    backends give non-finite values for those runs instead of raising (numpy error model when compiled)."""
    r = fr.ReceiverModel(2, np.array([[1.7, -0.8], [1.0, 0.0]]), np.array([[0.03, 0.026]]), np.array([[1.0, 0], [0, 0]]),
                         np.array([[0.04]]), NZ)
    snr = np.full((5, 4), 50.0)
    for be in ("numpy",) + (("numba",) if fr.numba_available() else ()):
        P = fr.covariance_paths(r, snr, 2.0, np.zeros((2, 2)), record=[5], backend=be)
        assert not np.all(np.isfinite(P)), be


# ------------------------------------------------------------------ variance-reduced estimators vs exact values


def test_rao_blackwellized_scenario2_is_eq14_per_run():
    """Scenario 2, invertible C: with σ_n² replaced by E[σ_n² | kept] the conditioned estimate is the exact
    mean eq. (14) in every run (the randomness of the drops is averaged out by the burst conditioning)."""
    Ts = np.array([4.0, 14.0, 17.0])
    th = np.repeat(Ts, 50)
    mu = fa.mu_ave(th, 100.0)
    _, U = fr.burst_conditioned_paths(rm("s2_square"), np.random.default_rng(0), th, mu, 100.0, np.eye(3), 60, [60],
                                      s2_given_kept=NZ.mean_given_kept(th, 100.0))
    for i, T in enumerate(Ts):
        ex = fa.ep_recursion(A5, 2 * np.eye(3), Q5, float(fa.mu_ave(T, 100.0)), float(fa.sigma2_n_ave(T, 100.0, AL, DE)),
                             np.eye(3), 60, R=1e-8 * np.eye(3))[-1]
        np.testing.assert_allclose(U[0][:, :, i * 50:(i + 1) * 50], np.repeat(ex[:, :, None], 50, 2), rtol=1e-10)


@pytest.mark.parametrize("backend", ["numpy", pytest.param("numba", marks=needs_numba)])
def test_final_strata_keeps_the_conditioned_estimator_unbiased(backend):
    # scenario 2 (square C) with SAMPLED σ_n² and the stratified last step: mean within 5 s.e. of eq. (14)
    Ts, N, H = np.array([1.0, 8.0, 16.0]), 3000, 40
    th = np.repeat(Ts, N)
    mu = fa.mu_ave(th, 100.0)
    _, U = fr.burst_conditioned_paths(rm("s2_square"), np.random.default_rng(4), th, mu, 100.0, np.eye(3), H, [H],
                                      backend=backend, final_strata=8)
    U = U[0].reshape(3, 3, len(Ts), N)
    for i, T in enumerate(Ts):
        ex = fa.ep_recursion(A5, 2 * np.eye(3), Q5, float(fa.mu_ave(T, 100.0)), float(fa.sigma2_n_ave(T, 100.0, AL, DE)),
                             np.eye(3), H, R=1e-8 * np.eye(3))[-1]
        m, se = U[:, :, i].mean(-1), U[:, :, i].std(-1) / math.sqrt(N)
        assert np.all(np.abs(m - ex) < 5 * se + 1e-12 * np.abs(ex)), T


def test_memoryless_coefficients_reproduce_eq14_for_iid_bursts():
    """Σ_L (1−μ)μᴸ (s̄ M1[L] + M2[L]) + μᴴ D = eq. (14) — the decomposition the SMC estimator uses."""
    H, Ya = 50, 100.0
    M1, M2, D = fr.memoryless_coefficients(2.0, 1.0, 1e-3, 1e-8, 1.0, H)
    for T in (3.0, 20.0, 28.0):
        mu = float(fa.mu_ave(T, Ya))
        sbar = float(NZ.mean_given_kept(T, Ya))
        L = np.arange(H)
        v = np.sum((1 - mu) * mu**L * (sbar * M1[:, 0, 0] + M2[:, 0, 0])) + mu**H * D[0, 0]
        ex = fa.ep_recursion(2.0, 1.0, 1e-3, mu, float(fa.sigma2_n_ave(T, Ya, AL, DE)), 1.0, H, 1e-8)[-1][0, 0]
        assert v == pytest.approx(ex, rel=1e-10)


def test_smc_iid_matches_eq14():
    # independent gains: the SMC weights are exactly (1−μ)μᴸ; only σ_n²(Υ_0) is sampled. 5 s.e. (over clouds).
    # Υ_T = 0 first: its clouds die after one step and are dropped, moving every other cloud's index
    H, Ya, T, R = 60, 100.0, np.array([0.0, 2.0, 10.0, 20.0, 28.0]), 40
    k = fr.BurstSMCKernel(None, T, Ya, NZ, fr.memoryless_coefficients(2.0, 1.0, 1e-3, 1e-8, 1.0, H), H, particles=8)
    st = k(np.random.default_rng(0), R)
    m, se = mean_and_stderr(st["sum"][0, 0], st["sumsq"][0, 0], R)
    ex = np.array([fa.ep_recursion(2.0, 1.0, 1e-3, float(fa.mu_ave(t, Ya)), float(fa.sigma2_n_ave(t, Ya, AL, DE)), 1.0, H,
                                   1e-8)[-1][0, 0] for t in T])
    assert np.all(np.abs(m - ex) < 5 * se + 1e-12 * ex)
    mu = fa.mu_ave(T, Ya)
    for j, L in enumerate(k.burst_lags):
        np.testing.assert_allclose(st["w"][:, j] / R, (1 - mu) * mu**L, rtol=1e-10)


def test_smc_iid_draws_only_for_the_kept_start():
    """Independent gains: p_t = μ_ave for every particle, so after the kept start the particles' positions are
    never read and are not moved (no random numbers spent on them). The draws are the start's alone, whatever
    the horizon, and the estimate does not depend on what the generator would give afterwards (a generator
    that turns to another stream after the start's draws gives the same bytes)."""

    class Switching:  # the real generator for the first `keep` calls, then another stream
        def __init__(self, keep):
            self.calls, self.keep = 0, keep
            self.a, self.b = np.random.default_rng(3), np.random.default_rng(99)

        def __getattr__(self, name):
            def call(*args, **kw):
                self.calls += 1
                return getattr(self.a if self.calls <= self.keep else self.b, name)(*args, **kw)
            return call

    T = np.array([2.0, 20.0])
    outs = []
    for H in (5, 60):
        k = fr.BurstSMCKernel(None, T, 100.0, NZ, fr.memoryless_coefficients(2.0, 1.0, 1e-3, 1e-8, 1.0, H), H,
                              particles=8)
        g = Switching(keep=4)
        outs.append(k(g, 6))
        assert g.calls == 4  # t = 0: the move's uniforms, the kept start's strata, the angles (von Mises, uniform)
    ref = fr.BurstSMCKernel(None, T, 100.0, NZ, fr.memoryless_coefficients(2.0, 1.0, 1e-3, 1e-8, 1.0, 60), 60,
                            particles=8)(np.random.default_rng(3), 6)
    for key in ref:
        assert ref[key].tobytes() == outs[1][key].tobytes(), key


def test_smc_jakes_agrees_with_plain_monte_carlo_where_that_is_reliable():
    """Short horizon and a low threshold: the plain sample mean of P[H] has a small, finite variance there.
    The SMC estimate on the same Jakes channel must agree within 5 combined standard errors."""
    H, Ya, T = 25, 100.0, np.array([0.0, 4.0, 8.0])  # Υ_T = 0: its clouds die at once, the others' indices move
    jch = chan(correlation={"model": "jakes", "carrier_hz": 1e9, "speed": {"value": 25, "unit": "mph"}, "interval_s": 0.01})
    r2 = fr.ReceiverModel(2, np.array([[2.0]]), np.array([[1.0]]), np.array([[1e-3]]), np.array([[1e-8]]), NZ)
    N = 20000
    plain = fr.CorrelatedPathKernel(jch, r2, T, np.eye(1), H, 2, backend="numpy")(np.random.default_rng(1), N)
    pm, pse = mean_and_stderr(plain["jakes_sum"][0, 0], plain["jakes_sumsq"][0, 0], N)
    R = 30
    smc = fr.BurstSMCKernel(jakes_factor(H, jch.correlation), T, Ya, NZ,
                            fr.memoryless_coefficients(2.0, 1.0, 1e-3, 1e-8, 1.0, H), H, particles=16)(np.random.default_rng(2), R)
    sm, sse = mean_and_stderr(smc["sum"][0, 0], smc["sumsq"][0, 0], R)
    assert np.all(np.abs(sm - pm) < 5 * np.hypot(sse, pse)), (sm, sse, pm, pse)


def test_smc_at_zero_threshold_is_the_exact_no_drop_term():
    """Υ_T = 0 keeps every packet: E P[H] = M1[0] E[σ_n² | kept] + M2[0] exactly, every burst probability of L ≥ 1
    is exactly 0 — the clouds, all dead after one step, are dropped and add nothing (s.e. 0 over the runs)."""
    H, Ya, R = 40, 100.0, 6
    jch = chan(correlation={"model": "jakes", "carrier_hz": 1e9, "speed": {"value": 25, "unit": "mph"}, "interval_s": 0.01})
    M1, M2, D = fr.memoryless_coefficients(2.0, 1.0, 1e-3, 1e-8, 1.0, H)
    for factor in (None, jakes_factor(H, jch.correlation)):
        k = fr.BurstSMCKernel(factor, [0.0], Ya, NZ, (M1, M2, D), H, particles=8)
        st = k(np.random.default_rng(3), R)
        exact = M1[0, 0, 0] * float(NZ.mean_given_kept(np.array([0.0]), Ya)[0]) + M2[0, 0, 0]
        assert st["sum"][0, 0, 0] / R == pytest.approx(exact, rel=1e-14)
        assert st["tr2"][0] / R == pytest.approx(exact**2, rel=1e-13)
        assert np.all(st["w"][0, 1:] == 0) and st["w"][0, 0] == pytest.approx(R)


def test_drop_cdf_and_quantile_are_scipys_where_they_compute_and_zero_where_they_skip():
    """fading_receivers.drop_cdf / drop_quantile skip Boost only where its answer is 0: the same bits everywhere,
    on a grid running from x = 0 and λ = 0 deep into the region the bound e^{−(√λ−√x)²/2} < e^{−800} skips."""
    from scipy import special

    x, lam = np.meshgrid(np.r_[0.0, np.geomspace(1e-8, 400.0, 60)], np.r_[0.0, np.geomspace(1e-8, 1e7, 80)])
    x, lam = x.ravel(), lam.ravel()
    skipped = (np.sqrt(x) < np.sqrt(lam)) & (-0.5 * (np.sqrt(lam) - np.sqrt(x)) ** 2 < fr.ZERO_LOG_CDF)
    assert skipped.sum() > 1000 and (~skipped).sum() > 1000
    np.testing.assert_array_equal(fr.drop_cdf(x, lam), special.chndtr(x, 2.0, lam))
    u = np.random.default_rng(0).random(x.size)
    target = u * special.chndtr(x, 2.0, lam)
    assert (target == 0).sum() > 1000 and (target > 0).sum() > 1000
    np.testing.assert_array_equal(fr.drop_quantile(target, lam), special.chndtrix(target, 2.0, lam))


@needs_numba
@pytest.mark.parametrize("sc", [1, 2, 3])
def test_generic_compiled_step_for_four_states_equals_numpy(sc):
    """n = 4, m = 2 (Gauss–Jordan in the inlined primitives) and the rescue variant: compiled against numpy."""
    A = 0.95 * np.array([[1, 0, 0.5, 0], [0, 1, 0, 0.5], [0, 0, 1, 0], [0, 0, 0, 1.0]]) * 1.3
    C = np.hstack([np.eye(2), np.zeros((2, 2))]) if sc != 2 else np.eye(4) + 0.1
    R = 1e-3 * np.eye(C.shape[0])
    r4 = fr.ReceiverModel(sc, A, C, 1e-2 * np.eye(4), R, NZ)
    th = np.repeat(np.array([0.0, 10.0, 16.0]), 100)
    mu = fa.mu_ave(th, 100.0)
    a = fr.burst_conditioned_paths(r4, np.random.default_rng(5), th, mu, 100.0, np.eye(4), 30, [30], backend="numpy")
    b = fr.burst_conditioned_paths(r4, np.random.default_rng(5), th, mu, 100.0, np.eye(4), 30, [30], backend="numba")
    for x, y in zip(a, b):
        np.testing.assert_allclose(y.mean(-1), x.mean(-1), rtol=1e-7)


@pytest.mark.parametrize("vr", ["none", "conditioned"])
def test_receivers_of_one_trace_share_its_noise_variances(vr, monkeypatch):
    """Receivers reading one sample compute σ_n²(Υ) of its whole SNR array once (channels.fading.noise_of_trace, shared
    by every trace of the sample: DrawnSamples), each then only the dropped entries of its threshold; their
    covariances are bit for bit those each gets from a trace of its own, on a copy of the sample never shared."""
    from netkf_cli.core.trace import Trace
    from netkf_cli.estimators.fading_receivers import ReceiverEstimator

    s = LinearSystem.create(A5, 2 * np.eye(3), Q5, 1e-8 * np.eye(3), np.eye(3))
    ests = [ReceiverEstimator.model_validate({"kind": "receiver", "scenario": sc, "variance_reduction": vr,
                                              "threshold": {"value": 10, "unit": "linear"}, "backend": "numpy"})
            for sc in (2, 3)]
    ch = chan()
    sizes = []
    real = fr.NoiseFn.__call__
    monkeypatch.setattr(fr.NoiseFn, "__call__", lambda self, snr: (sizes.append(np.size(snr)), real(self, snr))[1])
    seq = np.random.SeedSequence(40 + ["none", "conditioned"].index(vr), spawn_key=(0, 1))  # a state not drawn yet
    shared = [ch.sample_trace(np.random.default_rng(seq), 20, 12) for _ in range(3)]  # one sample, three traces
    got = [dict(e.covariances(s, tr, [3, 12], ("predicted",))) for tr in shared for e in ests]
    assert shared[2].snr is shared[1].snr
    whole = [z for z in sizes if z == 20 * 12]
    assert 1 <= len(whole) <= 2 and len(sizes) > len(whole)  # (the first draw of a state is not kept: at most 2)
    assert all(z < 20 * 12 for z in sizes if z != 20 * 12)  # per threshold: only the dropped entries
    sizes.clear()
    for i, tr in enumerate(shared):
        for j, e in enumerate(ests):
            own = Trace(runs=20, horizon=12, snr=np.array(tr.snr), meta=dict(tr.meta))
            o = dict(e.covariances(s, own, [3, 12], ("predicted",)))
            for k in (3, 12):
                assert np.array_equal(got[2 * i + j][k]["predicted"], o[k]["predicted"])
    assert sizes.count(20 * 12) == 6  # an unshared trace computes its own σ_n²(Υ)
