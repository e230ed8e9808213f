"""Bad input to the smoothing artefacts: exit code 1 and the dotted field path in the message."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from netkf_cli.cli import app

BASE = "name: bad\nsystem: {A: 1.3, C: 1, Q: 0.5, R: 1}\nmontecarlo: {runs: 100}\n"


@pytest.mark.parametrize(
    "body, needle",
    [
        ("channel: {kind: gilbert_elliott, loss_rate: 0.8, mean_burst: 2}\n"
         "analysis: {kind: smoothing_burstiness, M: 6.25, eps: 0.05, mean_bursts: [5]}\n", "mean_burst"),
        ("channel: {kind: gilbert_elliott, loss_rate: 0.3, p_bg: 0.5}\n"
         "analysis: {kind: smoothing_burstiness, M: 6.25, eps: 0.05, mean_bursts: [5]}\n", "not a mix"),
        ("analysis: {kind: smoothing_table1, M: 2.0, eps: 0.05}\n", "analysis.M"),
        ("analysis: {kind: smoothing_table1, M: 6.25, eps: 1.5}\n", "analysis.eps"),
        ("analysis: {kind: smoothing_table1, M: 6.25, eps: 0.05, lags: [0, 1], printed_prob: [0.9]}\n", "printed_prob"),
        ("channel: {kind: gilbert_elliott, loss_rate: 0.3, mean_burst: 2}\n"
         "analysis: {kind: smoothing_retransmission, N: 2, M: 6.25}\n", "channel.kind"),
        ("channel: {kind: bernoulli, arrival: 0.6}\n"
         "analysis: {kind: smoothing_critical_rate, lambdas: {start: 0.5, stop: 0.4}}\n", "analysis.lambdas"),
        # loops that grow with a config value are refused above a stated limit (issue 14)
        ("analysis: {kind: smoothing_table1, M: 6.25, eps: 0.05, lags: [0, 20]}\n", "analysis.lags"),
        ("analysis: {kind: smoothing_table1, M: 6.25, eps: 0.05, paper_steps: 100000000}\n", "analysis.paper_steps"),
        ("analysis: {kind: smoothing_critical_rate, lambdas: {start: 0.5, stop: 0.9, num: 100000}}\n", "analysis.lambdas"),
        ("analysis: {kind: smoothing_critical_rate, lambdas: [0.5], lags: [-1, 9]}\n", "analysis.lags"),
        ("channel: {kind: bernoulli, arrival: 0.6}\n"
         "analysis: {kind: smoothing_retransmission, N: 9, M: 6.25}\n", "analysis.N"),
        ("channel: {kind: bernoulli, arrival: 0.6}\n"
         "analysis: {kind: smoothing_retransmission, M: 6.25, grid: 100000}\n", "analysis.grid"),
        ("analysis: {kind: smoothing_burstiness, M: 6.25, eps: 0.05, mean_bursts: [1e9]}\n", "analysis.mean_bursts"),
        ("estimator: {kind: smoother, lag: 100000}\n"
         "analysis: {kind: smoothing_table1, M: 6.25, eps: 0.05}\n", "estimator.lag"),
    ],
)
def test_bad_input_exit_1_with_path(tmp_path, body, needle):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(BASE + body)
    r = CliRunner().invoke(app, ["run", str(cfg), "--out", str(tmp_path / "out")])
    assert r.exit_code == 1, r.output
    assert needle in r.output
    assert "Traceback" not in r.output


@pytest.mark.parametrize("cmd", ["validate", "run"])
def test_limits_are_refused_by_validate_too(tmp_path, cmd):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(BASE + "analysis: {kind: smoothing_table1, M: 6.25, eps: 0.05, lags: [0, 20]}\n")
    args = [cmd, str(cfg)] + (["--out", str(tmp_path / "out")] if cmd == "run" else [])
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 1 and "analysis.lags" in r.output and "Traceback" not in r.output


def test_huge_a_critical_rate_is_a_result_not_a_traceback(tmp_path):
    """A = 10⁶ (issue 14: OverflowError in the closed form): every E[P] is ∞ (λ ≤ λ_c = 1 − 10⁻¹²), exit 0."""
    cfg = tmp_path / "big.yaml"
    cfg.write_text("name: big\nsystem: {A: 1.0e6, C: 1, Q: 0.5, R: 1}\nmontecarlo: {runs: 500, burn_in: 30, chunk: 500}\n"
                   "analysis: {kind: smoothing_critical_rate, lambdas: [0.5, 0.99], lags: [-1, 0, 1]}\n")
    r = CliRunner().invoke(app, ["run", str(cfg), "--out", str(tmp_path / "out")])
    assert r.exit_code == 0, r.output
    assert "Traceback" not in r.output and "overflow encountered" not in r.output
    import pandas as pd

    t = pd.read_csv(tmp_path / "out" / "big.csv")
    assert np.isinf(t[t.series == "exact"].value).all()
    m = t[t.series == "monte_carlo"]
    assert (m.reliable == 0).all() and (m.heavy_tail == 1).all()


def test_huge_a_table1_exact_and_monte_carlo_agree(tmp_path):
    """A = 10⁶, M = 10¹³ (M̄ ≈ 10¹²): Pr[P ≤ M] is the probability that the last measurement arrived,
    0.95 at every column's rate (k₁ = 1: 1 − ε^(1/k₁) = 0.95 …). An absolute PSD tolerance in the
    information form (10⁻¹⁰ against M⁻¹ = 10⁻¹³) once reported 1.0 here, with exit 0."""
    cfg = tmp_path / "t1.yaml"
    cfg.write_text("name: t1big\nsystem: {A: 1.0e6, C: 1, Q: 0.5, R: 1}\nmontecarlo: {runs: 2000, burn_in: 60, chunk: 1000}\n"
                   "analysis: {kind: smoothing_table1, M: 1.0e13, eps: 0.05, lags: [-1, 0, 2], paper_steps: 2000}\n")
    r = CliRunner().invoke(app, ["run", str(cfg), "--out", str(tmp_path / "out")])
    assert r.exit_code == 0, r.output
    import pandas as pd

    t = pd.read_csv(tmp_path / "out" / "t1big.csv")
    ex = t[t.series == "prob_exact"]
    np.testing.assert_allclose(ex.value, 0.95, atol=1e-9)
    assert (t[t.series == "z_mc_vs_exact"].value < 5).all()
