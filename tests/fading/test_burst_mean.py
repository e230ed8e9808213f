"""The generic burst_mean (sequential Monte Carlo of the drop bursts) and autocorrelation metrics (issue 21)."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from netkf_cli.core.errors import ConfigError
from netkf_cli.config.loader import load_scenario
from netkf_cli.app.runner import run_scenario_file

ROOT = Path(__file__).resolve().parents[2]
FIG7 = ROOT / "configs" / "fading" / "fig7.yaml"
CHANNEL = ROOT / "configs" / "fading" / "fig7_channel.yaml"


def test_renewal_coefficients_are_the_receivers_recursion():
    """σ² M1[L] + M2[L] (last kept packet L steps before k, its noise σ²) and D (no packet kept) equal the
    scenario-2 recursion from P_{0|0} = P0 step by step: netkf's time base, predicted P_{k+1|k} at k = horizon."""
    sc = load_scenario(FIG7)
    s, e = sc.linear_system(), sc.estimator_list()[0]
    k = 12
    M1, M2, D = e.renewal_coefficients(s, k, "predicted")
    A, C, Q, R, P0 = (np.atleast_2d(x) for x in (s.A, s.C, s.Q, s.R, s.P0))
    Ci = np.linalg.inv(C)
    s2 = 0.37
    for L in [None, *range(k)]:
        P = A @ P0 @ A.T + Q  # P_{1|0}
        for t in range(1, k + 1):  # step t: the correction of packet t, then the prediction P_{t+1|t}
            kept = L is not None and t == k - L
            Pf = Ci @ (s2 * np.eye(1) + R) @ Ci.T if kept else P
            P = A @ Pf @ A.T + Q
        want = D if L is None else s2 * M1[L] + M2[L]
        np.testing.assert_allclose(want, P, rtol=1e-12)
    # the paper's P[0] = 1 (configs/fading/fig7.yaml: P0 = (1 − q)/4)
    assert float((A @ P0 @ A.T + Q)[0, 0]) == pytest.approx(1.0, rel=1e-14)


def test_independent_baseline_matches_eq14(tmp_path):
    """Independent gains: the SMC's burst weights are exact, only σ_n²(Υ_0) is sampled; its E P at k = horizon
    agrees with eq. (14) within 5 s.e. at every threshold, and its burst probabilities are (1 − μ) μᴸ."""
    res = run_scenario_file(FIG7, out_dir=tmp_path / "f7", runs=12, force=True,
                            overrides={"montecarlo": {"horizon": 40, "chunk": 4},
                                       "analysis": {"over": {"channel.threshold.value": [2, 14, 28]}}})
    t = pd.read_csv(res / "fading_fig7.csv")
    x = "channel.threshold.value"
    mc = t[(t.channel == "independent") & (t.source == "monte_carlo") & (t.series == "trace")].set_index(x)
    ex = t[(t.channel == "independent") & (t.source == "closed_form") & (t.series == "trace")].set_index(x)
    assert len(mc) == 3 and len(ex) == 3
    assert (np.abs(mc.value - ex.value) <= 5 * mc.stderr + 1e-12 * ex.value).all(), (mc.value, ex.value, mc.stderr)
    assert not len(t[(t.channel == "correlated") & (t.source == "closed_form")])  # eq. 14 is for i.i.d. gains only
    b = pd.read_csv(res / "fading_fig7_bursts.csv")
    bi = b[b.channel == "independent"]
    mu = 1 - np.exp(-bi[x].astype(float) / 100.0)
    # the CSV keeps 10 significant digits: rounding ≤ 5e-10 relative
    np.testing.assert_allclose(bi.value, np.exp(-bi[x].astype(float) / 100.0) * mu**bi.L, rtol=1e-9)


@pytest.mark.parametrize("override,where,words", [
    ({"estimator": {"kind": "receiver", "scenario": 3}}, "estimator.scenario", "carries its covariance"),
    ({"system": {"A": [[2, 0], [0, 0.5]], "C": [[1, 1]], "Q": [[0.001, 0], [0, 0.001]], "R": 1.0e-8,
                 "P0": [[1, 0], [0, 1]]}},
     "estimator.scenario", "invertible C"),
    ({"channel": {"kind": "bernoulli", "arrival": 0.8, "snr_avg": None, "correlation": None, "noise": None,
                  "threshold": None}}, None, None),
])
def test_burst_mean_refuses_what_it_cannot_do(override, where, words):
    with pytest.raises(ConfigError) as e:
        load_scenario(FIG7, override)
    if where is not None:
        assert any(p.path == where and words in p.message for p in e.value.problems), e.value.problems


def test_burst_mean_refuses_a_filtered_quantity():
    with pytest.raises(ConfigError):
        load_scenario(FIG7, {"analysis": {"quantity": "filtered"}})


def test_autocorrelation_of_independent_gains(tmp_path):
    """i.i.d. gains: the sample autocorrelation is δ_k0 within 5 s.e. at every lag (gain and power)."""
    text = CHANNEL.read_text(encoding="utf-8")
    jakes = "  correlation: {model: jakes, carrier_hz: 1.0e9, speed: {value: 25, unit: mph}, interval_s: 0.01}\n"
    assert jakes in text
    cfg = tmp_path / "iid.yaml"
    cfg.write_text(text.replace(jakes, "  correlation: {model: iid}\n"), encoding="utf-8")
    res = run_scenario_file(cfg, out_dir=tmp_path / "c", runs=200, force=True, overrides={"montecarlo": {"horizon": 40}})
    t = pd.read_csv(res / "fading_fig7_channel.csv")
    mc = t[t.source == "monte_carlo"]
    assert len(mc) == 18 and (np.abs(mc.z[mc.stderr > 0]) < 5).all()
    assert np.allclose(mc[(mc.series == "gain") & (mc.lag == 0)].value, 1.0, atol=5 * mc.stderr.max())


JAKES0 = """\
name: jakes0
system: {A: 1.2, C: 1, Q: 1, R: 1}
channel: {kind: fading, snr_avg: {value: 20, unit: dB}, noise: {model: ber, N_p: 10, Delta: 0.0390625},
          correlation: {model: jakes, carrier_hz: 1.0e9, speed: {value: 0, unit: mph}, interval_s: 0.01}}
analysis: {kind: autocorrelation, max_lag: 5}
montecarlo: {runs: 200, horizon: 30, seed: 1}
"""


def test_autocorrelation_of_a_static_jakes_channel(tmp_path):
    """speed 0 (f_D = 0) is a valid Jakes channel: the gain is the same at every step (up to the nugget), as the
    receivers already used it. The autocorrelation metric divided by f_D for the first zero of J₀
    (ZeroDivisionError out of `netkf run`): J₀(0) = 1 at every lag never crosses zero, the manifest says "inf"."""
    import json

    cfg = tmp_path / "jakes0.yaml"
    cfg.write_text(JAKES0, encoding="utf-8")
    res = run_scenario_file(cfg, out_dir=tmp_path / "a", force=True)
    t = pd.read_csv(res / "jakes0.csv")
    model = t[t.source == "closed_form"]
    assert (model.value == 1.0).all()  # ρ_k = J₀(0) = 1, for the gain and the power
    mc = t[(t.source == "monte_carlo") & (t.series == "gain")]
    assert len(mc) == 6 and (np.abs(mc.z) < 5).all()
    meta = json.loads((res / "manifest.json").read_text(encoding="utf-8"))["meta"]
    assert meta["doppler_hz"] == 0.0 and meta["first_zero_of_J0_s"] == "inf"
    # the receivers and time_average on the same static channel (they ran before the fix): still the same, and
    # the limit of a vanishing speed
    values = []
    for speed in (0, 1e-9):
        text = (JAKES0.replace("{kind: autocorrelation, max_lag: 5}", "{kind: time_average}")
                .replace("value: 0, unit: mph", f"value: {speed}, unit: mph")
                + "estimator: {kind: receiver, scenario: 2, threshold: {value: 14, unit: linear}}\n")
        cfg.write_text(text, encoding="utf-8")
        res = run_scenario_file(cfg, out_dir=tmp_path / f"t{speed}", force=True)
        values.append(pd.read_csv(res / "jakes0.csv", comment="#").value.iloc[0])
    assert np.isfinite(values[0]) and values[0] == pytest.approx(values[1], rel=1e-6)
