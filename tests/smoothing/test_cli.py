"""Bad input to the smoothing artefacts: exit code 1 and the dotted field path in the message."""

from __future__ import annotations

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
    ],
)
def test_bad_input_exit_1_with_path(tmp_path, body, needle):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(BASE + body)
    r = CliRunner().invoke(app, ["run", str(cfg), "--out", str(tmp_path / "out")])
    assert r.exit_code == 1, r.output
    assert needle in r.output
    assert "Traceback" not in r.output
