"""Bad input to the smoothing configurations (exit code 1, the dotted field path in the message) and the
huge-A cases (issue 14) as results, not tracebacks."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from netkf_cli.app import runner
from netkf_cli.core.artefact import RunContext
from netkf_cli.app.cli import app
from netkf_cli.config.loader import load_scenario_text

BASE = "name: bad\nsystem: {A: 1.3, C: 1, Q: 0.5, R: 1}\nmontecarlo: {runs: 100, burn_in: 10, horizon: 30}\n"
TA = "analysis: {kind: time_average, M: 6.25, references: [leong_exact]}\nestimator: {kind: smoother, lag: 1}\n"


@pytest.mark.parametrize(
    "body, needle",
    [
        ("channel: {kind: retransmission, arrival: 0.6, budget: 2, p: 1.5}\n" + TA, "channel.p"),
        ("channel: {kind: retransmission, arrival: 0.6, budget: 1000}\n" + TA, "channel.budget"),
        ("channel: {kind: bernoulli, arrival: 0.6}\nestimator: {kind: smoother, lag: 1}\n"
         "analysis: {kind: time_average, M: 6.25, references: [leong_nonsense]}\n", "analysis.references"),
        ("channel: {kind: gilbert_elliott, loss_rate: 0.6, mean_burst: 3}\nestimator: {kind: smoother, lag: 1}\n"
         "analysis: {kind: time_average, M: 6.25, over: {channel.mean_burst: [1.0, 3.0]}}\n", "mean_burst"),
    ],
)
def test_bad_input_exit_1_with_path(tmp_path, body, needle):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(BASE + body)
    r = CliRunner().invoke(app, ["validate", str(cfg)])
    assert r.exit_code == 1, r.output
    assert needle in r.output and "Traceback" not in r.output


def _run(tmp_path, text: str) -> pd.DataFrame:
    cfg = tmp_path / "big.yaml"
    cfg.write_text(text)
    r = CliRunner().invoke(app, ["run", str(cfg), "--out", str(tmp_path / "out")])
    assert r.exit_code == 0, r.output
    assert "Traceback" not in r.output and "overflow encountered" not in r.output
    return pd.read_csv(tmp_path / "out" / "big.csv")


def _compute(text: str) -> pd.DataFrame:
    """The main table without the figure (the CLI path is test_huge_a_critical_rate_is_a_result_not_a_traceback)."""
    sc = load_scenario_text(text)
    return runner.compute(sc, RunContext()).table


def test_huge_a_critical_rate_is_a_result_not_a_traceback(tmp_path):
    """A = 10⁶: every E[P] is ∞ (λ ≤ λ_c = 1 − 10⁻¹²), exit 0, the Monte Carlo means flagged."""
    t = _run(tmp_path, "name: big\nsystem: {A: 1.0e6, C: 1, Q: 0.5, R: 1}\nchannel: {kind: bernoulli, arrival: 0.5}\n"
                       "estimators: [{kind: smoother, lag: 0}, {kind: smoother, lag: 1}]\n"
                       "montecarlo: {runs: 300, burn_in: 30, horizon: 80, chunk: 300}\n"
                       "analysis: {kind: time_average, quantity: smoothed, over: {channel.arrival: [0.5, 0.99]}, "
                       "references: [leong_exact, leong_lemma1]}\n")
    cf = t[t.source == "closed_form"]
    assert len(cf) == 8 and np.isinf(cf.value).all()  # 2 points × 2 lags × (exact, Lemma 1 bound)
    mc = t[t.source == "monte_carlo"]
    assert (mc.heavy_tail | mc.rare_event | ~np.isfinite(mc.value)).all()


def test_huge_a_exact_and_monte_carlo_agree():
    """A = 10⁶, M = 10¹³ (M̄ ≈ 10¹², k₁ = 1): one loss after an arrival keeps P ≈ A² r/c² ≈ 10¹² ≤ M, two do
    not, so Pr[P_{k|k} ≤ M] = 1 − (1 − λ)² and Pr[P_{k|k+1} ≤ M] = 1 − (1 − λ)³. An absolute PSD tolerance in
    the information form (10⁻¹⁰ against M⁻¹ = 10⁻¹³) once reported 1.0 here. Monte Carlo within 5 s.e."""
    lam = 0.5
    t = _compute(f"name: big\nsystem: {{A: 1.0e6, C: 1, Q: 0.5, R: 1}}\nchannel: {{kind: bernoulli, arrival: {lam}}}\n"
                       "estimators: [{kind: smoother, lag: 0}, {kind: smoother, lag: 1}]\n"
                       "montecarlo: {runs: 1000, burn_in: 30, horizon: 80, chunk: 1000}\n"
                       "analysis: {kind: time_average, quantity: smoothed, M: 1.0e13, references: [leong_exact]}\n")
    ex = t[t.source == "closed_form"].set_index("estimator").value
    np.testing.assert_allclose([ex["smoother lag=0"], ex["smoother lag=1"]], [1 - (1 - lam) ** 2, 1 - (1 - lam) ** 3], atol=1e-9)
    mc = t[(t.source == "monte_carlo") & (t.series == "Pr[P<=M]")].set_index("estimator")
    assert (np.abs(mc.value - ex[mc.index]) <= 5 * mc.stderr).all()
