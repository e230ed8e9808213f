"""The fading receivers on the one Kalman core (issue 19): the same filter under another name gives the same
numbers, compiled = numpy on the same trace, the one rescue, the named quantities on the one time base, the
variance-reduced mean through the generic engine, the primitives this port added to the core."""

import subprocess
import sys

import numpy as np
import pytest
from scipy import special

from netkf_cli import engine
from netkf_cli.linalg import kalman
from netkf_cli.analysis import fading as fa
from netkf_cli.channels.fading import FadingChannel, NoiseFn, snr_given_kept
from netkf_cli.core.errors import ConfigError
from netkf_cli.estimators import fading_receivers as fr
from netkf_cli.estimators.fading_receivers import ReceiverEstimator
from netkf_cli.estimators.kf import KalmanFilterEstimator
from netkf_cli.core.system import LinearSystem
from netkf_cli.core.trace import Trace

needs_numba = pytest.mark.skipif(not fr.numba_available(), reason="numba not installed")
BACKENDS = ["numpy", pytest.param("numba", marks=needs_numba)]
A5 = np.array([[2, 0.3, 0.45], [0.4, 0.2, 0.5], [1.5, 0.6, 0.34]])
Q5 = 1e-3 * np.eye(3)
BOTH = ("filtered", "predicted")


def chan(noise=None, **kw):
    base = {"kind": "fading", "snr_avg": {"value": 20, "unit": "dB"},
            "noise": noise or {"model": "ber", "N_p": 10, "Delta": 0.0390625}}
    base.update(kw)
    return FadingChannel.model_validate(base)


def receiver(sc, T, **kw):
    return ReceiverEstimator.model_validate({"kind": "receiver", "scenario": sc,
                                             "threshold": {"value": T, "unit": "linear"}, **kw})


SYSTEMS = {
    "sec42": dict(A=A5, C=np.array([[1.0, 2, 3]]), Q=Q5, R=np.array([[0.1]])),
    "fig6": dict(A=A5, C=2 * np.eye(3), Q=Q5, R=1e-2 * np.eye(3), P0=np.eye(3)),
    "m2": dict(A=A5, C=np.array([[1.0, 0, 1], [0, 1, 0]]), Q=Q5, R=np.array([[1e-2, 3e-3], [3e-3, 2e-2]])),
    "overflow": dict(A=np.diag([1e6, 0.5]), C=np.eye(2), Q=np.eye(2), R=np.eye(2), P0=np.eye(2)),
}


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("sc", [1, 3])
@pytest.mark.parametrize("name", sorted(SYSTEMS))
def test_receiver_on_a_perfect_channel_is_kf(name, sc, backend):
    """Every packet kept (Υ_T = 0) and no communication noise (α = δ = 0): scenarios 1 and 3 are the Kalman
    filter — same P0 = P_{0|0}, same step k, both quantities, every k; the numpy path is the kf's primitive
    sequence (bit for bit), the compiled one its inlined twin (rounding). A = diag(1e6, 0.5) goes through the
    one rescue (kalman.Rescue) in both."""
    s = LinearSystem(**SYSTEMS[name])
    runs, H = 40, 15
    tr = chan({"model": "ber", "alpha": 0, "delta": 0}).sample_trace(np.random.default_rng(1), runs, H)
    arr = Trace(runs=runs, horizon=H, arrival=np.ones((1, H, runs), bool))
    ref = dict(KalmanFilterEstimator(kind="kf").covariances(s, arr, range(1, H + 1), BOTH))
    got = dict(receiver(sc, 0, backend=backend).covariances(s, tr, range(1, H + 1), BOTH))
    assert sorted(got) == list(range(1, H + 1))
    for k in ref:
        for q in BOTH:
            assert got[k][q].shape == (s.n, s.n, runs)
            scale = np.abs(ref[k][q]).max(axis=(0, 1))
            err = np.abs(got[k][q] - ref[k][q]).max(axis=(0, 1)) / scale
            assert err.max() <= (0.0 if backend == "numpy" else 1e-12), (k, q, err.max())


CASES = {  # (scenario, system)
    "s1_fig6": (1, "fig6"), "s2_fig6": (2, "fig6"), "s3_fig6": (3, "fig6"),
    "s2_sec42": (2, "sec42"), "s3_sec42": (3, "sec42"), "s3_m2": (3, "m2"), "s2_m2": (2, "m2"),
}


@needs_numba
@pytest.mark.parametrize("vr", ["none", "conditioned"])
@pytest.mark.parametrize("key", sorted(CASES))
def test_compiled_equals_numpy_on_the_same_trace(key, vr):
    """The estimator's two backends on one recorded SNR trace, both quantities at several k (blocks of 1 and of
    several steps): equal to rounding (products summed in another order; per run ≤ 1e-8 relative, amplified
    by near-singular updates after drop bursts; the means over runs ≤ 1e-11)."""
    sc, name = CASES[key]
    s = LinearSystem(**SYSTEMS[name])
    tr = chan().sample_trace(np.random.default_rng(4), 300, 40)
    steps = [1, 2, 3, 10, 25, 40]
    out = {be: dict(receiver(sc, 12.0, backend=be, variance_reduction=vr).covariances(s, tr, steps, BOTH))
           for be in ("numpy", "numba")}
    for k in steps:
        for q in BOTH:
            x, y = out["numpy"][k][q], out["numba"][k][q]
            assert np.array_equal(np.isfinite(x), np.isfinite(y))
            f = np.isfinite(x)
            np.testing.assert_allclose(y[f], x[f], rtol=1e-8, atol=1e-300 + 1e-13 * np.abs(x[f]).max())
            np.testing.assert_allclose(y.mean(-1), x.mean(-1), rtol=1e-11, atol=1e-300)


def test_filtered_and_predicted_on_the_one_time_base():
    """P0 = P_{0|0}; step k uses Υ of trace step k − 1; predicted = A P_{k|k} Aᵀ + Q; the prior of y_1 is
    A P0 Aᵀ + Q (covariance_paths from that prior gives the same P_{k+1|k})."""
    s = LinearSystem(A5, 2 * np.eye(3), Q5, 1e-8 * np.eye(3), np.eye(3))
    tr = chan().sample_trace(np.random.default_rng(2), 30, 25)
    for sc in (1, 2, 3):
        got = dict(receiver(sc, 10.0, backend="numpy").covariances(s, tr, [1, 7, 25], BOTH))
        rm = fr.ReceiverModel(sc, A5, 2 * np.eye(3), Q5, 1e-8 * np.eye(3), tr.meta["noise"])
        ref = fr.covariance_paths(rm, tr.snr, 10.0, A5 @ A5.T + Q5, record=[1, 7, 25])
        for i, k in enumerate([1, 7, 25]):
            np.testing.assert_allclose(got[k]["predicted"], ref[i], rtol=1e-12)
            np.testing.assert_allclose(got[k]["predicted"], kalman.predict(got[k]["filtered"], A5, Q5), rtol=1e-12)
    with pytest.raises(ConfigError, match="smoothed"):
        next(iter(receiver(1, 10.0).covariances(s, tr, [1], ("smoothed",))))


def test_scenario2_invertible_filtered_is_the_memoryless_update():
    """Scenario 2 with an invertible C forgets the past at a kept packet (eq. 12): P_{k|k} = C⁻¹(σ_n² I + R)C⁻ᵀ."""
    C, R = 2 * np.eye(3), 1e-8 * np.eye(3)
    s = LinearSystem(A5, C, Q5, R, np.eye(3))
    tr = chan().sample_trace(np.random.default_rng(5), 50, 6)
    got = dict(receiver(2, 5.0, backend="numpy").covariances(s, tr, [6], BOTH))[6]["filtered"]
    kept = tr.snr[5] >= 5.0
    s2 = tr.meta["noise"](tr.snr[5])
    Ci = np.linalg.inv(C)
    for b in np.flatnonzero(kept):
        np.testing.assert_allclose(got[:, :, b], Ci @ (s2[b] * np.eye(3) + R) @ Ci.T, rtol=1e-12)


# ------------------------------------------------------------------ honest rare events (issue 19 item 4)


FIG7_SYSTEM = LinearSystem(A=2 * np.eye(1), C=np.eye(1), Q=1e-3 * np.eye(1), R=1e-8 * np.eye(1), P0=np.eye(1))


def _engine_mean(est, ch, k, runs, seed=0, quantity="predicted"):
    st = engine.simulate(FIG7_SYSTEM, ch, [est], engine.MomentReducer([k]), steps=[k], runs=runs, horizon=k,
                         seed=seed, chunk=2500, quantity=quantity)
    ms = engine.mean_summary(st, 0)
    return float(ms.mean[0]), float(ms.stderr[0])


def _exact(mu, s2ave, k, quantity):
    """E P_{k+1|k} by eq. (14) (eq. 38 with R) from P[0] = P_{1|0} = A P0 Aᵀ + Q; E P_{k|k} = μ E P_{k|k−1} +
    C⁻¹(σ²_n,ave + (1 − μ) R)C⁻ᵀ (the kept update of scenario 2 is memoryless)."""
    E = fa.ep_recursion(2.0, 1.0, 1e-3, mu, s2ave, np.eye(1) * (4 + 1e-3), k, 1e-8)
    if quantity == "predicted":
        return float(E[k][0, 0])
    return float(mu * E[k - 1][0, 0] + s2ave + (1 - mu) * 1e-8)


@pytest.mark.parametrize("quantity", BOTH)
def test_conditioned_mean_vs_time_is_exact_for_scenario2_ber(quantity):
    """Receiver scenario 2, Υ_T = 12 (Fig. 7's i.i.d. system), k = 8, 10 000 runs through the generic engine
    (MomentReducer + mean_summary: what mean_vs_time reports). The naive per-run P is heavy-tailed (drop bursts
    of probability μ^L scale P by 4^L: μ·16 > 1, infinite variance as k grows); its sample mean misses the
    bursts. With ``variance_reduction: conditioned`` the per-run estimate U is unbiased and, for scenario 2
    with an invertible C and the ber noise (σ_n² Rao–Blackwellized), EXACTLY the mean recursion in every
    run: zero variance, so the check is equality to rounding (1e-12 relative) — and at least as tight as
    5 s.e. of the naive estimate."""
    ch = chan()
    AL, DE = fa.noise_params_from_bits(10, 0.0390625)
    mu, s2 = float(fa.mu_ave(12.0, 100.0)), float(fa.sigma2_n_ave(12.0, 100.0, AL, DE))
    exact = _exact(mu, s2, 8, quantity)
    m, se = _engine_mean(receiver(2, 12.0, variance_reduction="conditioned"), ch, 8, 10_000, quantity=quantity)
    assert abs(m - exact) <= 5 * se + 1e-12 * exact, (m, se, exact)
    m0, se0 = _engine_mean(receiver(2, 12.0, variance_reduction="none"), ch, 8, 10_000, quantity=quantity)
    assert abs(m - exact) <= 5 * se0


@pytest.mark.parametrize("quantity", BOTH)
def test_default_mean_vs_time_is_right_on_the_rare_event_transient(quantity):
    """The same transient as a new user meets it: `netkf`'s mean_vs_time with the receiver's defaults
    (variance_reduction: auto → conditioned where only means are taken on an i.i.d. channel) gives the
    exact recursion at k = 8 (before: 0.02538 ± 0.00045 against 0.03483, z = −21, unflagged)."""
    from netkf_cli import load, run

    AL, DE = fa.noise_params_from_bits(10, 0.0390625)
    mu, s2 = float(fa.mu_ave(12.0, 100.0)), float(fa.sigma2_n_ave(12.0, 100.0, AL, DE))
    exact = _exact(mu, s2, 8, quantity)
    sc = load({"name": "rare", "system": {"A": 2, "C": 1, "Q": 1e-3, "R": 1e-8, "P0": 1},
               "channel": {"kind": "fading", "snr_avg": {"value": 20, "unit": "dB"},
                           "noise": {"model": "ber", "N_p": 10, "Delta": 0.0390625}},
               "estimator": {"kind": "receiver", "scenario": 2, "threshold": {"value": 12, "unit": "linear"}},
               "analysis": {"kind": "mean_vs_time", "every": 1, "quantity": quantity},
               "montecarlo": {"runs": 10_000, "horizon": 8, "chunk": 2500}})
    t = run(sc).table
    r = t[t.k == 8].iloc[0]
    assert abs(r.value - exact) <= 5 * r.stderr + 1e-12 * exact, (r.value, r.stderr, exact)
    assert "auto" in r.conventions


@pytest.mark.parametrize("backend", BACKENDS)
def test_conditioned_mean_with_sampled_noise_within_5_se(backend):
    """The same with σ_n² = β/Υ (inverse_snr): no Rao–Blackwellization, U keeps the variance of σ_n²(Υ') of
    the last kept term (bounded: σ_n² ≤ β/Υ_T), so this is a genuine Monte Carlo check. Exact:
    σ²_n,ave = E[σ_n² 1{Υ ≥ Υ_T}] = (β/Υ_ave) E₁(Υ_T/Υ_ave). 10 000 runs; |mean − exact| ≤ 5 s.e. (the s.e.
    of the sample mean of i.i.d. per-run U: P(|z| > 5) ≈ 6e-7 for a correct estimator)."""
    beta = 0.05
    ch = chan({"model": "inverse_snr", "beta": beta})
    mu = float(fa.mu_ave(12.0, 100.0))
    s2 = beta / 100.0 * float(special.exp1(12.0 / 100.0))
    for quantity in BOTH:
        exact = _exact(mu, s2, 8, quantity)
        m, se = _engine_mean(receiver(2, 12.0, variance_reduction="conditioned", backend=backend), ch, 8, 10_000,
                             seed=3, quantity=quantity)
        assert se > 0 and abs(m - exact) <= 5 * se, (quantity, m, se, exact)
        assert se < 0.02 * exact  # the variance reduction is real: ~1 % relative s.e. from 10 000 runs


def test_snr_given_kept_has_the_conditional_law_and_ignores_the_keep():
    """Υ' = Υ where kept; for a drop, Υ' − Υ_T ~ Exp(Υ_ave) (mean Υ_ave, s.e. Υ_ave/√n): 5 s.e. on 2e5 draws."""
    rng = np.random.default_rng(0)
    Y = rng.exponential(100.0, 200_000)
    Yp = snr_given_kept(Y, 12.0, 100.0)
    kept = Y >= 12.0
    np.testing.assert_array_equal(Yp[kept], Y[kept])
    d = Yp[~kept] - 12.0
    assert d.min() >= 0
    assert abs(d.mean() - 100.0) <= 5 * 100.0 / np.sqrt(d.size)
    assert abs(np.median(d) - 100.0 * np.log(2)) <= 5 * 100.0 / np.sqrt(d.size)


def test_check_refuses_conditioned_on_a_correlated_channel_and_labels_conventions():
    s = LinearSystem(A5, 2 * np.eye(3), Q5, 1e-8 * np.eye(3), np.eye(3))
    jakes = chan(correlation={"model": "jakes", "carrier_hz": 1e9, "speed": {"value": 25, "unit": "mph"},
                              "interval_s": 0.01})
    with pytest.raises(ConfigError, match="i.i.d."):
        receiver(2, 12.0, variance_reduction="conditioned").check(s, jakes)
    receiver(2, 12.0).check(s, jakes)
    conv = receiver(2, 12.0, variance_reduction="conditioned").conventions(s, chan())
    assert "all of y_k" in conv["packet"] and "means only" in conv["variance_reduction"]
    assert "Υ_T" in receiver(3, 1.0).conventions(s, chan())["threshold"]


def test_channel_does_not_import_an_estimator():
    # the (empty) package netkf_cli.estimators may be imported by the top-level discovery; no estimator module
    code = ("import sys, netkf_cli.channels.fading; "
            "print([m for m in sys.modules if m.startswith('netkf_cli.estimators.')])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", out


# ------------------------------------------------------------------ primitives this port added to the core


def test_rescue_noisy_is_the_information_form_per_run():
    """kalman.rescue_noisy against the textbook information form per run, (P⁻⁻¹ + Cᵀ(R + E_b)⁻¹C)⁻¹, for the
    flagged runs whose packet arrived; a lost packet leaves P⁻ exactly; an unflagged run is untouched; an
    overflowed prior (∞ variance of one direction) is never NaN; extra_R = 0 is Rescue.apply with every row
    arrived (the same overflow semantics as kf)."""
    rng = np.random.default_rng(0)
    n, m, B = 3, 2, 6
    C, R = rng.standard_normal((m, n)), np.diag([0.3, 0.5])
    G = rng.standard_normal((n, n, B))
    Pm = np.einsum("ikb,jkb->ijb", G, G) + np.eye(3)[:, :, None]
    Pm[0, :, 4] = Pm[:, 0, 4] = 0.0
    Pm[0, 0, 4] = np.inf  # direction 0 unknown
    extra = rng.uniform(0, 2, B)[None, None, :] * np.eye(m)[:, :, None]
    gamma = np.array([1, 1, 0, 1, 1, 1.0])
    flagged = np.array([True, False, True, True, True, False])
    P = kalman.update(Pm, C, R, gamma, extra)
    resc = kalman.Rescue.of(C, R)
    out = kalman.rescue_noisy(resc, P, Pm, flagged, gamma, extra)
    for b in range(B):
        if flagged[b] and gamma[b] and np.isfinite(Pm[:, :, b]).all():
            ref = np.linalg.inv(np.linalg.inv(Pm[:, :, b]) + C.T @ np.linalg.inv(R + extra[:, :, b]) @ C)
            np.testing.assert_allclose(out[:, :, b], ref, rtol=1e-12)
        elif flagged[b] and not gamma[b]:
            np.testing.assert_array_equal(out[:, :, b], Pm[:, :, b])
        elif flagged[b]:
            assert not np.isnan(out[:, :, b]).any()
        else:
            np.testing.assert_array_equal(out[:, :, b], P[:, :, b])
    z = np.zeros_like(extra)
    np.testing.assert_array_equal(kalman.rescue_noisy(resc, kalman.update(Pm, C, R, gamma), Pm, flagged, gamma, z),
                                  resc.apply(kalman.update(Pm, C, R, gamma), Pm, flagged, np.broadcast_to(gamma, (m, B))))


@needs_numba
def test_kalman_numba_gain_equals_the_core_gain():
    """kalman_numba.gain (appended) against kalman.gain and the textbook P Cᵀ (C P Cᵀ + R)⁻¹, m = 1, 2, 3."""
    from netkf_cli.linalg import kalman_numba as kn

    rng = np.random.default_rng(1)
    for m in (1, 2, 3):
        n = 4
        G = rng.standard_normal((n, n))
        P = G @ G.T + np.eye(n)
        C = rng.standard_normal((m, n))
        R = np.eye(m) * 0.1 if m > 1 else np.zeros((1, 1))
        K = np.empty((n, m))
        kn.gain(P, C, R, K, np.empty((m, m)), np.empty((m, n)))
        ref = P @ C.T @ np.linalg.inv(C @ P @ C.T + R)
        np.testing.assert_allclose(K, ref, rtol=1e-10)
        np.testing.assert_allclose(K, kalman.gain(P[:, :, None], C, R)[:, :, 0], rtol=1e-10)


def test_noise_fn_lives_with_the_channel():
    assert fr.NoiseFn is NoiseFn
    tr = chan().sample_trace(np.random.default_rng(0), 3, 2)
    assert isinstance(tr.meta["noise"], NoiseFn) and tr.meta["correlation"] == "iid"
