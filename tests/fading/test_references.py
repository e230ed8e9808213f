"""The paper configs as generic metrics (issue 21): the closed forms of analysis/fading.py (``references``
providers) against the generic engine's Monte Carlo on FadingChannel.sample_trace, at small sizes.

numpy backend throughout (what is compared is closed form vs Monte Carlo, not compiled vs numpy: no numba
compile time here). Tolerances: 5 standard errors of the Monte Carlo mean; where the estimator is exact per
run (scenario 2 with an invertible C, burst-conditioned and Rao–Blackwellized: s.e. 0) the floating-point
agreement of two evaluations of the same recursion.
"""

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from netkf_cli.analysis import fading as fa
from netkf_cli.analysis import references
from netkf_cli.core.errors import ConfigError
from netkf_cli.config.loader import load_scenario
from netkf_cli.metrics.common import labels
from netkf_cli.app.runner import run_scenario_file

ROOT = Path(__file__).resolve().parents[2]
CFG = ROOT / "configs" / "fading"
NUMPY_PAIR = [{"kind": "receiver", "scenario": 2, "backend": "numpy"},
              {"kind": "receiver", "scenario": 3, "backend": "numpy"}]


def _point(path, overrides=None, **extra):
    """A references.Point of a config (with the horizon the finite-time closed forms need); loaded without the
    check that its references give rows (these tests ask the providers themselves when they give none)."""
    from netkf_cli.metrics.common import deferred_reference_checks

    with deferred_reference_checks():
        sc = load_scenario(path, overrides)
    ests = sc.estimator_list()
    mc = sc.montecarlo.model_dump()
    mc.update(extra)
    return SimpleNamespace(system=sc.linear_system(), channel=sc.channel.model_dump(),
                           estimators=[e.model_dump() for e in ests], labels=labels(ests),
                           quantities=sc.analysis.quantity_list(), metric=sc.analysis.model_dump(), montecarlo=mc)


def _run(path, tmp, overrides, runs):
    out = run_scenario_file(path, out_dir=tmp, runs=runs, force=True, overrides=overrides)
    return pd.read_csv(out / f"{load_scenario(path).name}.csv")


def test_every_provider_is_registered_and_resolves():
    for name in ("fading_scenario2_exact", "fading_lemma5", "fading_theorem4", "fading_theorem4_quadrature"):
        assert callable(references.resolve(name)), name
        assert references.describe()[name].startswith("Mostofi & Murray 2009"), name


def test_theorem4_eq56_vs_generic_monte_carlo(tmp_path):
    """configs/fading/thm4.yaml at 20 000 runs, k ≤ 6: the receiver's predicted P_{k+1|k} from the channel's
    traces within 5 s.e. of eq. (56) at P[0] = a² P0 = 1; the nested quadrature (k = 1, 2) equals eq. (56)."""
    ov = {"montecarlo.horizon": 6, "estimator.backend": "numpy"}
    t = _run(CFG / "thm4.yaml", tmp_path, ov, 20_000)
    mc = t[t.series == "trace"].set_index("k")
    pt = _point(CFG / "thm4.yaml", ov)
    ref = pd.DataFrame(fa.theorem4(pt)).set_index("k")
    assert list(ref.index) == [1, 2, 3, 4, 5, 6]
    e56 = fa.theorem4_mean(1.5, 1.0, 10.0, 1.0, 6)
    np.testing.assert_allclose(ref.value, e56[1:], rtol=1e-12)     # P[0] = a² P0 = 1: the paper's start
    z = (mc.value.loc[ref.index] - ref.value) / mc.stderr.loc[ref.index]
    assert (np.abs(z) < 5).all(), z.to_dict()
    quad = pd.DataFrame(fa.theorem4_quadrature_rows(pt)).set_index("k")
    np.testing.assert_allclose(quad.value, ref.value.loc[[1, 2]], rtol=1e-7)
    # filtered P_{k|k} = P_{k+1|k}/a² (Q = 0)
    pt_f = SimpleNamespace(**{**vars(pt), "quantities": ["filtered"]})
    np.testing.assert_allclose(pd.DataFrame(fa.theorem4(pt_f)).value, ref.value / 2.25, rtol=1e-14)


def test_theorem4_needs_its_case():
    # per-step rows need the steps: a point without the horizon gets none (not a wrong constant)
    bare = SimpleNamespace(**{k: v for k, v in vars(_point(CFG / "thm4.yaml")).items() if k != "montecarlo"})
    assert fa.theorem4(bare) == [] and fa.theorem4_quadrature_rows(bare) == []
    pt = _point(CFG / "thm4.yaml", {"system.Q": 0.1})
    assert fa.theorem4(pt) == [] and fa.theorem4_quadrature_rows(pt) == []
    pt = _point(CFG / "thm4.yaml", {"estimator.threshold": {"value": 1, "unit": "linear"}})
    assert fa.theorem4(pt) == []


THRESHOLDS = [0, 2, 9, 16]


@pytest.fixture(scope="module")
def fig6_small(tmp_path_factory):
    """configs/fading/fig6.yaml (‖E P_k‖ at one step) at 300 runs, k = 40, four thresholds, numpy backend."""
    ov = {"montecarlo.horizon": 40, "analysis.at": 40, "analysis.over": {"channel.threshold.value": THRESHOLDS},
          "estimators": NUMPY_PAIR}
    t = _run(CFG / "fig6.yaml", tmp_path_factory.mktemp("fig6"), ov, 300)
    return t, ov


def test_fig6_scenario2_conditioned_is_eq14s_norm(fig6_small):
    """Scenario 2, invertible C, ber noise: the conditioned per-run estimate is eq. (14) in every run (s.e. 0),
    so ‖mean‖ equals the provider's exact ‖E P_{k+1|k}‖₂ (eq. 14) at the same step."""
    t, ov = fig6_small
    mc = t[(t.source == "monte_carlo") & (t.estimator == "receiver scenario=2")].set_index("channel.threshold.value")
    for T in THRESHOLDS:
        pt = _point(CFG / "fig6.yaml", {**ov, "channel.threshold.value": T})
        ref = fa.scenario2_exact(pt)
        assert len(ref) == 1 and ref[0]["estimator"] == "receiver scenario=2"
        assert mc.stderr.loc[T] <= 1e-12 * mc.value.loc[T]
        assert mc.value.loc[T] == pytest.approx(ref[0]["value"], rel=1e-9), T


def test_fig6_scenario3_above_lemma5_bound(fig6_small):
    t, ov = fig6_small
    mc = t[(t.source == "monte_carlo") & (t.estimator == "receiver scenario=3")].set_index("channel.threshold.value")
    for T in THRESHOLDS:
        ref = fa.lemma5_lower_bound(_point(CFG / "fig6.yaml", {**ov, "channel.threshold.value": T}))
        assert len(ref) == 1 and ref[0]["estimator"] == "receiver scenario=3"
        assert ref[0]["statistic"] == "norm_of_mean"
        assert mc.value.loc[T] > ref[0]["value"] - 5 * mc.stderr.loc[T], T


@pytest.mark.parametrize("T", [0.0, 2.0])
def test_fig6_scenario2_plain_paths_vs_eq14(tmp_path, T):
    """Without variance reduction (each run's own P_{k+1|k}) scenario 2's ‖mean‖ at k = 40 is within 5
    delta-method s.e. of eq. (14)'s norm where its variance is finite (μ ρ_max⁴ < 1: Υ_T ≤ 2 at Υ_ave = 100)."""
    ov = {"montecarlo.horizon": 40, "analysis.at": 40, "analysis.over": {"channel.threshold.value": [T]},
          "estimators": [{"kind": "receiver", "scenario": 2, "backend": "numpy", "variance_reduction": "none"}]}
    t = _run(CFG / "fig6.yaml", tmp_path, ov, 4000)  # one step (no time average): 4000 runs for a clear eigen-gap
    mc = t[t.source == "monte_carlo"].iloc[0]
    ref = fa.scenario2_exact(_point(CFG / "fig6.yaml", {**ov, "channel.threshold.value": T}))[0]["value"]
    assert mc.stderr > 0
    assert abs(mc.value - ref) < 5 * mc.stderr, (mc.value, ref, mc.stderr)


def test_stationary_reference_is_the_old_time_average():
    """Without the horizon the providers give the k → ∞ limit (eq. 20, Lemma 5's fixed point). With the former
    criterion (E tr P averaged over k in (500, 700]) it is the exact average to 1e-8 relative even next to the
    stability limit (μ ρ² = 0.953 at Υ_T = 17)."""
    for T in (0.0, 12.0, 17.0):
        ov = {"channel.threshold.value": T, "analysis.at": None, "analysis.statistic": "mean_trace",
              "montecarlo.horizon": 700, "montecarlo.burn_in": 500}
        exact = _point(CFG / "fig6.yaml", ov)
        stat = SimpleNamespace(**{k: v for k, v in vars(exact).items() if k != "montecarlo"})
        for fn in (fa.scenario2_exact, fa.lemma5_lower_bound):
            a, b = fn(exact), fn(stat)
            assert len(a) == len(b) == 1
            assert a[0]["value"] == pytest.approx(b[0]["value"], rel=1e-8), (fn.__name__, T)
    assert "E P[∞] (eq. 20)" in fa.scenario2_exact(stat)[0]["series"]


def test_fig6_norm_at_300_is_the_stationary_norm_and_forgets_the_start():
    """The configs' ‖E P[300]‖ (eq. 14 at k = 300 from netkf's start P_{1|0} = A P0 Aᵀ + Q) against ‖E P[∞]‖
    (eq. 20) and eq. 14 from the paper's own start P[0] = P0 = I: eq. 14 is affine, so two starts X0, Y0 differ
    after k steps by exactly μ^k A^k (X0 − Y0) A^kᵀ, and by Weyl the norms by at most its norm — 1e-16 relative at
    Υ_T ≤ 14, 9e-5 at Υ_T = 17 (μ ρ² = 0.952: 0.952^300 = 4e-7 times ‖A Aᵀ‖/‖E P∞‖ ≈ 300). Lemma 5's eq. 32
    likewise. The statistic is λ_max of the matrix, not its trace."""
    sc = load_scenario(CFG / "fig6.yaml")
    A, C, Q, R = (np.atleast_2d(np.asarray(getattr(sc.linear_system(), x), dtype=float)) for x in "ACQR")
    ab = fa.noise_params_from_bits(10, 0.0390625)
    k = 300
    for T in (0.0, 12.0, 14.0, 17.0):
        pt = _point(CFG / "fig6.yaml", {"channel.threshold.value": T})
        assert pt.metric["at"] == k and pt.metric["statistic"] == "norm_of_mean"
        s2 = fa.scenario2_exact(pt)[0]
        assert s2["statistic"] == "norm_of_mean" and "‖E P‖" in s2["series"]
        mu, sig = float(fa.mu_ave(T, 100.0)), float(fa.sigma2_n_ave(T, 100.0, *ab))
        Ak = np.linalg.matrix_power(A, k)
        gap = lambda X0, Y0: mu**k * np.linalg.norm(Ak @ (X0 - Y0) @ Ak.T, 2) + 1e-15 * s2["value"]
        start = A @ A.T + Q
        inf = fa.ep_inf(A, C, Q, mu, sig, R)
        paper_start = fa.ep_recursion(A, C, Q, mu, sig, np.eye(3), k, R)[k]
        assert abs(s2["value"] - np.linalg.eigvalsh(inf)[-1]) <= gap(start, inf), T
        assert abs(s2["value"] - np.linalg.eigvalsh(paper_start)[-1]) <= gap(start, np.eye(3)), T
        assert s2["value"] < np.trace(inf) * (1 - 1e-3)  # a norm, not the trace
        lb = fa.lemma5_lower_bound(pt)[0]
        fixed = fa.solve_discrete_lyapunov(np.sqrt(mu) * A, Q)
        assert abs(lb["value"] - np.linalg.eigvalsh(fixed)[-1]) <= gap(start, fixed), T
        if T <= 14:
            assert s2["value"] == pytest.approx(np.linalg.eigvalsh(inf)[-1], rel=1e-12)


def test_lemma5_bound_for_a_non_invertible_C():
    """Sec. 4.2 (C = [1 2 3]): no eq. (14) for scenario 2; Lemma 5 bounds every receiver."""
    pt = _point(CFG / "sec42.yaml", {"channel.threshold.value": 12})
    assert fa.scenario2_exact(pt) == []
    assert [r["estimator"] for r in fa.lemma5_lower_bound(pt)] == ["receiver scenario=3"]


def test_threshold_from_the_channel_or_the_estimator_is_the_same(tmp_path):
    """The channel's Υ_T (what `over` sweeps) is used by a receiver that gives none; its own wins otherwise."""
    base = {"montecarlo.horizon": 12, "analysis.at": 12, "analysis.over": {"channel.threshold.value": [9]},
            "estimators": [{"kind": "receiver", "scenario": 3, "backend": "numpy"}]}
    a = _run(CFG / "fig6.yaml", tmp_path / "a", base, 50)
    own = {**base, "analysis.over": {"channel.threshold.value": [0]},
           "estimators": [{"kind": "receiver", "scenario": 3, "backend": "numpy", "threshold": {"value": 9, "unit": "linear"}}]}
    b = _run(CFG / "fig6.yaml", tmp_path / "b", own, 50)
    va = a[a.source == "monte_carlo"].value.to_numpy()
    vb = b[b.source == "monte_carlo"].value.to_numpy()
    assert len(va) == 1
    np.testing.assert_array_equal(va, vb)


def test_receiver_without_any_threshold_is_refused():
    with pytest.raises(ConfigError, match="threshold"):
        load_scenario(CFG / "thm4.yaml", {"estimator.threshold": None})


def test_fig4_averages_vs_channel_monte_carlo():
    """eqs (15)–(16) against Υ sampled by FadingChannel.sample_trace (what the receivers see): the drop
    fraction and the mean communication noise of kept packets (σ_n² · 1[kept]) within 5 s.e."""
    sc = load_scenario(CFG / "fig4.yaml")
    ch = sc.channel
    n = 200_000
    tr = ch.sample_trace(np.random.default_rng(4), n, 1)
    Y = tr.snr[0]
    a, d = ch.noise.params
    for T in (0.0, 8.0, 20.0, 40.0):
        drop = Y < T
        mu = float(fa.mu_ave(T, ch.mean_snr))
        assert abs(drop.mean() - mu) <= 5 * math.sqrt(max(mu * (1 - mu), 1e-300) / n) + 1e-15, T
        s2 = np.where(drop, 0.0, tr.meta["noise"](np.where(drop, 1.0, Y)))
        assert abs(s2.mean() - float(fa.sigma2_n_ave(T, ch.mean_snr, a, d))) < 5 * s2.std() / math.sqrt(n), T
