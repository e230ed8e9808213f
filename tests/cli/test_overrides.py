"""Issue 23.1: `key=value` overrides (CLI run and validate, the Python API) and `netkf run --dry-run`.

The overrides through the CLI, the API and `validate` must give byte-identical results to the same
scenario written out; a bad override is reported like a bad line of the file; a dry run writes nothing.
"""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import pytest
from typer.testing import CliRunner

from netkf_cli import load, run
from netkf_cli.app.cli import app
from netkf_cli.core.errors import ConfigError

runner = CliRunner()

BASE = textwrap.dedent(
    """\
    name: ov
    system: {A: 1.2, C: 1, Q: 1, R: 1}
    channel: {kind: bernoulli, arrival: 0.8}
    estimator: {kind: kf}
    analysis: {kind: mean_vs_time, every: 5}
    montecarlo: {runs: 300, horizon: 20, seed: 3, chunk: 100}
    """
)
OVERRIDES = ["channel.arrival=0.6", "montecarlo.runs=4e2", "system.A=[[1.1, 0.2], [0, 0.9]]", "system.C=[[1, 0]]",
             "system.Q=[[1, 0], [0, 1]]", "montecarlo.seed=5"]
# the same scenario, written out by hand
WRITTEN = textwrap.dedent(
    """\
    name: ov
    system: {A: [[1.1, 0.2], [0, 0.9]], C: [[1, 0]], Q: [[1, 0], [0, 1]], R: 1}
    channel: {kind: bernoulli, arrival: 0.6}
    estimator: {kind: kf}
    analysis: {kind: mean_vs_time, every: 5}
    montecarlo: {runs: 400, horizon: 20, seed: 5, chunk: 100}
    """
)


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture
def files(tmp_path):
    base, written = tmp_path / "base.yaml", tmp_path / "written.yaml"
    base.write_text(BASE)
    written.write_text(WRITTEN)
    return base, written


def _csv(folder: Path) -> bytes:
    return (folder / "ov.csv").read_bytes()


def test_overrides_cli_api_validate_equal_the_written_scenario(tmp_path, files):
    base, written = files
    r = invoke("run", base, *OVERRIDES, "--out", tmp_path / "cli", "-j", 1, "-q")
    assert r.exit_code == 0, r.output
    r = invoke("run", written, "--out", tmp_path / "file", "-j", 1, "-q")
    assert r.exit_code == 0, r.output
    assert _csv(tmp_path / "cli") == _csv(tmp_path / "file")
    m_cli = json.loads((tmp_path / "cli" / "manifest.json").read_text())
    m_file = json.loads((tmp_path / "file" / "manifest.json").read_text())
    assert m_cli["scenario_hash"] == m_file["scenario_hash"]  # the resolved scenario is what is hashed
    assert m_cli["scenario"] == m_file["scenario"]
    assert m_cli["overrides"] == OVERRIDES and m_file["overrides"] == []
    # the API: strings (the CLI grammar) and a {dotted.path: python value} mapping
    as_dict = {"channel.arrival": 0.6, "montecarlo.runs": 400, "system.A": [[1.1, 0.2], [0, 0.9]],
               "system.C": [[1, 0]], "system.Q": [[1, 0], [0, 1]], "montecarlo.seed": 5}
    run(load(base), overrides=as_dict, out=tmp_path / "api")
    assert _csv(tmp_path / "api") == _csv(tmp_path / "file")
    assert load(base, OVERRIDES) == load(written) == load(base, as_dict)
    res = run(load(base), overrides=OVERRIDES)
    assert res.table.equals(run(load(written)).table)
    # validate accepts the same overrides (and fails on a bad one)
    r = invoke("validate", base, *OVERRIDES)
    assert r.exit_code == 0, r.output


def test_interrupt_hint_repeats_the_overrides(tmp_path, files, monkeypatch):
    import netkf_cli.app.runner as runner_mod

    def stop(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(runner_mod, "run_scenario", stop)
    r = invoke("run", files[0], "channel.arrival=0.6", "system.A=[[1.1]]", "--out", tmp_path / "o")
    assert r.exit_code == 130
    assert "interrupted:" in r.output and "nothing was kept" in r.output


@pytest.mark.parametrize("override,path,needle", [
    ("channel.arrival=2", "channel.arrival", "less than or equal to 1"),
    ("channel.arrival=.nan", "", "must be a finite number"),
    ("montecarlo.runs=yes", "montecarlo.runs", "expected an integer, got the text 'yes'"),
    ("montecarlo.runs=2.5", "montecarlo.runs", "fractional part"),
    ("channel.bogus=1", "channel.bogus", "unknown key"),
    ("bogus=1", "bogus", "unknown key"),
    ("system.A.x=1", "system.A", "not a block of fields"),
    ("system.A=[[1, 2]]", "system.A", "square"),
    ("estimator.kind=psychic", "estimator.kind", "unknown kind"),
    ("a..b=1", "", "empty part"),
    ("~nothing", "nothing", "nothing to delete"),
    ("system.A=[1, [2]", "", "YAML"),
])
def test_bad_override_names_the_override_and_the_field(tmp_path, files, override, path, needle):
    base = files[0]
    for args in (("validate", base, override), ("run", base, override, "--out", tmp_path / "o")):
        r = invoke(*args)
        assert r.exit_code == 1, r.output
        assert "command line" in r.output and override.split("=")[0].lstrip("~") in r.output, r.output
        if path:
            assert f"{path}:" in r.output, r.output
        assert needle in r.output, r.output
        assert "Traceback" not in r.output and "internal error" not in r.output
    assert not (tmp_path / "o").exists()
    with pytest.raises(ConfigError, match="command line"):
        load(base, [override])


def test_a_bad_value_in_the_file_keeps_its_line_next_to_an_override(tmp_path):
    cfg = tmp_path / "s.yaml"
    cfg.write_text(BASE.replace("every: 5", "every: 0"))
    r = invoke("validate", cfg, "channel.arrival=2")
    assert r.exit_code == 1
    assert "command line (channel.arrival=2) channel.arrival:" in r.output
    assert "s.yaml:5 analysis.every:" in r.output


def test_an_argument_without_equals_is_a_usage_error(files):
    r = invoke("run", files[0], "channel.arrival")
    assert r.exit_code == 2 and "not a key=value override" in r.output


def test_delete_and_list_index_and_sweep_overrides(tmp_path, files):
    base = files[0]
    sc = load(base, ["~channel.arrival", "channel=\n  kind: gilbert_elliott\n  loss_rate: 0.2\n  mean_burst: 3"])
    assert sc.channel.kind == "gilbert_elliott"
    two = base.with_name("two.yaml")
    two.write_text(BASE.replace("estimator: {kind: kf}", "estimators: [{kind: kf}, {kind: smoother, lag: 1}]")
                   .replace("mean_vs_time, every: 5", "compare, M: [1, 5]"))
    assert load(two, ["estimators[1].lag=3"]).estimators[1].lag == 3
    assert load(two, ["estimators.1.lag=2"]).estimators[1].lag == 2
    r = invoke("validate", two, "estimators[5].lag=3")
    assert r.exit_code == 1 and "index 5 is out of range" in r.output
    r = invoke("validate", base, "sweep.channel.arrival=[0.5, 0.7]", "sweep.mode=zip")
    assert r.exit_code == 0, r.output
    assert load(base, ["sweep.channel.arrival=[0.5, 0.7]"]).sweep.axes == {"channel.arrival": [0.5, 0.7]}


# ---- --dry-run ----------------------------------------------------------------------------------

def test_dry_run_prints_the_plan_and_writes_nothing(tmp_path, files):
    base = files[0]
    before = sorted(p.name for p in tmp_path.rglob("*"))
    out = tmp_path / "deep" / "folder" / "o"
    r = invoke("run", base, "channel.arrival=0.6", "montecarlo.runs=2e5", "--out", out, "--dry-run", "-j", 2)
    assert r.exit_code == 0, r.output
    assert "arrival: 0.6" in r.output and "runs: 200000" in r.output  # the resolved scenario
    assert "200,000 Monte Carlo runs × 20 steps" in r.output and "4e+06 run-steps" in r.output
    assert "2,000 chunks" in r.output and "ETA" in r.output
    assert "executor:" in r.output and f"writes:   {out}/" in r.output
    assert sorted(p.name for p in tmp_path.rglob("*")) == before  # nothing written, no folder made
    r = invoke("run", base, "--out", out, "--dry-run", "--json")
    assert r.exit_code == 0, r.output
    plan = json.loads(r.output)
    assert plan["runs"] == 300 and plan["chunks"] == 3 and plan["folder"] == str(out)
    assert plan["scenario"]["channel"]["arrival"] == 0.8 and plan["run_steps"] == 300 * 20
    assert not (tmp_path / "deep").exists()


def test_dry_run_makes_the_pre_run_checks(tmp_path, files):
    base = files[0]
    afile = tmp_path / "afile"
    afile.write_text("x")
    r = invoke("run", base, "--out", afile, "--dry-run")
    assert r.exit_code == 1 and "is a file" in r.output
    r = invoke("run", base, "montecarlo.runs=1e15", "--out", tmp_path / "o", "--dry-run")
    assert r.exit_code == 1 and "montecarlo.runs" in r.output and "--yes" in r.output
    r = invoke("run", base, "montecarlo.runs=1e15", "--out", tmp_path / "o", "--dry-run", "--yes")
    assert r.exit_code == 0 and "years" in r.output, r.output
    assert afile.read_text() == "x" and not (tmp_path / "o").exists()


def test_the_api_plans_like_the_dry_run(tmp_path, files):
    from netkf_cli.app.api import plan

    base = files[0]
    r = invoke("run", base, "channel.arrival=0.6", "--out", tmp_path / "o", "--dry-run", "--json", "-j", 1)
    cli = json.loads(r.output)
    api = plan(load(base), overrides=["channel.arrival=0.6"], out=tmp_path / "o")
    assert {k: v for k, v in cli.items() if k not in ("scenario", "overrides")} == api
    with pytest.raises(ConfigError, match="runs"):
        plan(load(base), runs=0)
    assert not (tmp_path / "o").exists()
