"""Sweeps: one row per point with the swept columns; a bad point is rejected before any work starts."""

import textwrap

import pandas as pd
from typer.testing import CliRunner

from netkf_cli.app.cli import app

runner = CliRunner()

BASE = textwrap.dedent(
    """\
    name: sw
    system: {{A: 1.4, C: 1, Q: 0.2, R: 0.5}}
    channel: {{kind: delay, delay: {{kind: poisson, mean: 5}}, buffer: 10}}
    analysis: {{kind: theta_vs_buffer, M: [50], D_max: 4}}
    sweep:
      channel.delay.mean: {means}
      analysis.D_max: {{from: 2, to: 4}}
      {extra}
    """
)


def test_product_sweep_table_and_figure(tmp_path):
    cfg = tmp_path / "s.yaml"
    cfg.write_text(BASE.format(means="[3, 5]", extra="plot: {series: theta_k1, logy: true}"))
    r = runner.invoke(app, ["run", str(cfg), "--out", str(tmp_path / "o"), "-j", "1"])
    assert r.exit_code == 0, r.output
    t = pd.read_csv(tmp_path / "o" / "sw.csv")
    assert list(t.columns[:2]) == ["channel.delay.mean", "analysis.D_max"]
    pts = t[["channel.delay.mean", "analysis.D_max"]].drop_duplicates()
    assert len(pts) == 2 * 3
    # each point's rows equal an unswept run of that point
    one = t[(t["channel.delay.mean"] == 3) & (t["analysis.D_max"] == 2) & (t.series == "theta_k1")]
    assert one.D.tolist() == [1, 2]
    assert (tmp_path / "o" / "sw.png").stat().st_size > 10_000


def test_zip_sweep(tmp_path):
    cfg = tmp_path / "s.yaml"
    cfg.write_text(BASE.format(means="[3, 4, 5]", extra="mode: zip"))
    r = runner.invoke(app, ["run", str(cfg), "--out", str(tmp_path / "o"), "-j", "1"])
    assert r.exit_code == 0, r.output
    t = pd.read_csv(tmp_path / "o" / "sw.csv")
    assert len(t[["channel.delay.mean", "analysis.D_max"]].drop_duplicates()) == 3


def test_bad_point_rejected_before_running(tmp_path):
    cfg = tmp_path / "s.yaml"
    cfg.write_text(BASE.format(means="[3, -1]", extra=""))
    r = runner.invoke(app, ["run", str(cfg), "--out", str(tmp_path / "o")])
    assert r.exit_code == 1
    out = " ".join(r.output.split())
    # one line for the bad value, naming the three points (of six) it fails at, on the sweep entry's line
    assert out.count("•") == 1 and "s.yaml:6 channel.delay.mean" in out, out
    assert "(sweep points channel.delay.mean=-1, analysis.D_max=2; channel.delay.mean=-1, analysis.D_max=3; " in out
    assert not (tmp_path / "o").exists()


def test_unknown_path_and_zip_length(tmp_path):
    cfg = tmp_path / "s.yaml"
    cfg.write_text(BASE.format(means="[3]", extra="channel.bogus: [1]"))
    r = runner.invoke(app, ["run", str(cfg), "--out", str(tmp_path / "o")])
    assert r.exit_code == 1 and "channel.bogus" in r.output
    cfg.write_text(BASE.format(means="[3, 4]", extra="mode: zip"))
    r = runner.invoke(app, ["validate", str(cfg)])
    assert r.exit_code == 1 and "zip needs lists of equal length" in r.output


def test_a_bad_range_says_what_is_wrong_with_it(tmp_path):
    """{from: 3, to: 1} is empty (it said only "expected a non-empty list or {from, to, step}"); a missing or
    unknown key of a range is named under its axis; a range given on the command line is named as the source."""
    cfg = tmp_path / "s.yaml"
    cfg.write_text(BASE.format(means="[3]", extra=""))
    cases = {"{from: 3, to: 1}": "channel.buffer: {from: 3, to: 1} is empty: from must be ≤ to",
             "{from: 1}": "channel.buffer: to: required field is missing",
             "{from: 1, to: 3, stp: 1}": "channel.buffer: stp: unknown key",
             "{from: 1, to: 3, step: 0}": "channel.buffer: step must be a finite number > 0"}
    for rng, needle in cases.items():
        r = runner.invoke(app, ["validate", str(cfg), f"sweep.channel.buffer={rng}"])
        out = " ".join(r.output.split())
        assert r.exit_code == 1 and needle in out, out
        assert f"command line (sweep.channel.buffer={rng}) sweep:" in out, out


import pytest  # noqa: E402

_BASE = """\
name: clash
system: {A: 1.2, C: 1, Q: 1, R: 1}
channel: {kind: bernoulli, arrival: 0.8}
estimator: {kind: kf}
montecarlo: {runs: 100, horizon: 20, seed: 1}
"""


@pytest.mark.parametrize("extra, needle", [
    ("analysis: {kind: mean_vs_time, over: {channel.arrival: [0.5, 0.9]}}\nsweep: {channel.arrival: [0.6, 0.7]}\n",
     "sweep.channel.arrival: is also set by analysis.over (channel.arrival)"),
    ("analysis: {kind: mean_vs_time}\nsweep: {estimator: [{kind: kf}, {kind: smoother, lag: 1}]}\n",
     "sweep.estimator: 'estimator' is a column of the result table already"),
    ("analysis: {kind: time_average, over: {estimator: [{kind: kf}, {kind: smoother, lag: 1}]}}\n",
     "analysis.over: 'estimator' is a column of the result table already"),
])
def test_a_path_swept_twice_or_named_like_a_column_is_refused_before_any_work(tmp_path, extra, needle):
    """These were internal errors (pandas: 'cannot insert …, already exists') after the whole Monte Carlo."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text(_BASE + extra, encoding="utf-8")
    for cmd in (["validate", str(cfg)], ["run", str(cfg), "--out", str(tmp_path / "o"), "-q"]):
        r = runner.invoke(app, cmd)
        assert r.exit_code == 1 and needle in " ".join(r.output.split()), r.output
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("extra", ["analysis: {kind: mean_vs_time}\nsweep: {montecarlo.runs: [50, 100]}\n",
                                   "analysis: {kind: mean_vs_time, over: {montecarlo.runs: [50, 100]}}\n"])
def test_runs_option_does_not_silently_replace_a_varied_run_count(tmp_path, extra):
    """--runs gave every point its count while the CSV's montecarlo.runs column still said 50 and 100 (the UX fuzz)."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text(_BASE + extra, encoding="utf-8")
    r = runner.invoke(app, ["run", str(cfg), "--runs", "200", "--out", str(tmp_path / "o"), "-q"])
    assert r.exit_code == 1 and "--runs: the scenario varies the run count" in " ".join(r.output.split()), r.output
    assert not (tmp_path / "o").exists()
    r = runner.invoke(app, ["run", str(cfg), "--out", str(tmp_path / "o"), "-q"])
    assert r.exit_code == 0, r.output
    t = pd.read_csv(tmp_path / "o" / "clash.csv")
    assert sorted(set(t.n)) == [50, 100]
