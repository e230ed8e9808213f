"""The generic ``updates`` metric (expected filter recursions per step) and the buffered estimator's hook.

(Kept beside the fusion tests: the same helper moved Shi's updates_vs_buffer onto the generic metrics.)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from netkf_cli.analysis import delay_exact as dx
from netkf_cli.channels.delay import DelayChannel
from netkf_cli.core.errors import ConfigError
from netkf_cli.estimators.buffered import BufferedEstimator, mkf_runs
from netkf_cli.app.runner import run_scenario_file
from netkf_cli.core.system import LinearSystem
from netkf_cli.core.trace import LOST, Trace

ROOT = Path(__file__).resolve().parents[2]
SYS = LinearSystem.create(1.4, 1, 0.2, 0.5)


def test_hook_counts_by_hand():
    """Packets 1…6 with delays 0, 2, LOST, 1, 0, 4 and D = 3 (delay_le_D): arrivals at 1 (packet 1, d 0),
    4 (packet 2, d 2), 5 (packets 4 and 5, d 1 and 0) — packet 6 (d 4 > D) is discarded — so R = 1, 1, 1, 3, 2, 1."""
    d = np.array([0, 2, LOST, 1, 0, 4], dtype=np.int32)[:, None]
    tr = Trace(runs=1, horizon=6, delay=d[None], arrival=(d == 0)[None], meta={"buffer": 3, "convention": "delay_le_D"})
    got = [float(r[0]) for _, r in mkf_runs(tr, range(1, 7))]
    assert got == [1.0, 1.0, 1.0, 3.0, 2.0, 1.0]


def test_hook_on_a_pure_loss_trace_is_one_recursion_per_step():
    arr = np.random.default_rng(0).random((1, 20, 7)) < 0.6
    tr = Trace(runs=7, horizon=20, arrival=arr)
    for _, r in BufferedEstimator(kind="buffered").updates(SYS, tr, range(1, 21)):
        assert np.all(r == 1.0)


@pytest.mark.parametrize("mean,D", [(3.0, 4), (5.0, 9)])
def test_monte_carlo_equals_the_closed_form(mean, D):
    """Per-run averages over 40 stationary steps (k > D_max), 4 000 runs: within 5 s.e. of Prop. 3.1's
    closed form (P(|Z| > 5) ≈ 6e-7 per comparison)."""
    ch = DelayChannel(kind="delay", delay={"kind": "poisson", "mean": mean}, buffer=D)
    tr = ch.sample_trace(np.random.default_rng(7), 4000, 60)
    steps = range(21, 61)
    avg = sum(r for _, r in BufferedEstimator(kind="buffered").updates(SYS, tr, steps)) / len(steps)
    se = avg.std(ddof=1) / np.sqrt(avg.size)
    assert abs(avg.mean() - dx.expected_updates(ch)) <= 5 * se


def _config(tmp_path, **analysis):
    cfg = yaml.safe_load((ROOT / "configs" / "updates_vs_buffer.yaml").read_text())
    cfg["analysis"].update(analysis)
    p = tmp_path / "u.yaml"
    p.write_text(yaml.safe_dump(cfg, allow_unicode=True))
    return p


def test_config_small_claims_and_tables(tmp_path):
    """The config at 600 runs on a short grid: MC within 5 s.e. of the closed form at every point, the
    closed-form Pr rows non-decreasing in D and non-increasing in d (the trend table the claims read)."""
    p = _config(tmp_path, over={"channel.buffer": [1, 3, 6, 1, 3, 6], "channel.delay.mean": [3, 3, 3, 5, 5, 5]})
    out = run_scenario_file(p, out_dir=tmp_path / "out", runs=600, force=True)
    t = pd.read_csv(out / "updates_vs_buffer.csv")
    assert {"channel.buffer", "channel.delay.mean", "source", "M"} <= set(t.columns)
    pairs = pd.read_csv(out / "updates_vs_buffer_pairs.csv")
    z = pairs[(pairs.a_source == "monte_carlo") & pairs.b_series.str.startswith("E[MKF runs")].z
    assert len(z) == 6 and (z.abs() <= 5).all(), z
    tr = pd.read_csv(out / "updates_vs_buffer_trend.csv")
    ex = tr[tr.series.str.startswith("exact")]
    assert (ex[ex.path == "channel.buffer"]["diff"] >= -1e-9).all()
    assert (ex[ex.path == "channel.delay.mean"]["diff"] <= 1e-9).all()
    assert (out / "updates_vs_buffer.png").exists()


def test_an_estimator_without_the_hook_is_refused(tmp_path):
    cfg = yaml.safe_load((ROOT / "configs" / "updates_vs_buffer.yaml").read_text())
    cfg["estimator"] = {"kind": "kf"}
    p = tmp_path / "u.yaml"
    p.write_text(yaml.safe_dump(cfg, allow_unicode=True))
    with pytest.raises(ConfigError) as e:
        run_scenario_file(p, out_dir=tmp_path / "out", runs=100, force=True)
    assert any("updates" in pr.message for pr in e.value.problems)
