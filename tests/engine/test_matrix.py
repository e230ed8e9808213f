"""Every compatible (channel, estimator) pair × every generic metric runs through the real CLI;
every incompatible pair is refused by ``netkf validate`` with the compatible kinds named."""

from __future__ import annotations

import itertools

import pandas as pd
import pytest
import yaml
from typer.testing import CliRunner

from netkf_cli.app.cli import app
from netkf_cli.config.compat import compatible_channels
from netkf_cli.config.scenario import kinds
from netkf_cli.core.spec import ChannelModel, EstimatorModel

METRICS = {
    "distribution": {"kind": "distribution", "M": [1.0, 5.0, 50.0]},
    "mean_vs_time": {"kind": "mean_vs_time", "every": 5},
    "compare": {"kind": "compare", "M": [5.0]},
}
runner = CliRunner()


def _write(tmp, name, system, channel, estimator, analysis):
    key = "estimators" if isinstance(estimator, list) else "estimator"
    doc = {"name": name, "system": system, "channel": channel, key: estimator, "analysis": analysis,
           "montecarlo": {"runs": 64, "horizon": 20, "seed": 3, "chunk": 32}}
    p = tmp / f"{name}.yaml"
    p.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return p


def _pairs():
    return list(itertools.product(sorted(kinds(ChannelModel)), sorted(kinds(EstimatorModel))))


def _compatible(ch: str, es: str) -> bool:
    return ch in compatible_channels(kinds(EstimatorModel)[es])


def _system_for(samples, tmp, ch, es):
    """The first candidate system on which `netkf validate` accepts the pair (None if none does)."""
    for i, system in enumerate(samples["systems"]):
        p = _write(tmp, f"v-{ch}-{es}-{i}", system, samples["channels"][ch], samples["estimators"][es],
                   METRICS["mean_vs_time"])
        if runner.invoke(app, ["validate", str(p)]).exit_code == 0:
            return system
    return None


@pytest.mark.parametrize("ch,es", [p for p in _pairs() if not _compatible(*p)])
def test_incompatible_pair_refused_by_validate(samples, tmp_path, ch, es):
    p = _write(tmp_path, f"bad-{ch}-{es}", samples["systems"][0], samples["channels"][ch], samples["estimators"][es],
               METRICS["distribution"])
    res = runner.invoke(app, ["validate", str(p)])
    assert res.exit_code == 1, res.output
    # either the trace fields do not match (the compatible channels are named) or one side has no
    # per-run covariance / trace at all (said so)
    assert ("estimator.kind" in res.output and "compatible channels" in res.output) or \
        "no per-run error covariance" in res.output or "does not sample traces" in res.output, res.output
    assert "Traceback" not in res.output


@pytest.mark.parametrize("ch,es", [p for p in _pairs() if _compatible(*p)])
def test_compatible_pair_runs_every_generic_metric(samples, tmp_path, ch, es):
    system = _system_for(samples, tmp_path, ch, es)
    if system is None:
        # the pair reads the same trace fields but needs a system none of the samples provide: the
        # refusal must still be a clear message naming the estimator
        p = _write(tmp_path, f"x-{ch}-{es}", samples["systems"][0], samples["channels"][ch], samples["estimators"][es],
                   METRICS["distribution"])
        res = runner.invoke(app, ["validate", str(p)])
        assert res.exit_code == 1 and "estimator" in res.output and "Traceback" not in res.output
        pytest.skip(f"{es} on {ch}: no sample system satisfies the estimator ({res.output.strip().splitlines()[-1]})")
    for metric, analysis in METRICS.items():
        estimator = samples["estimators"][es]
        if metric == "compare":
            estimator = [estimator, estimator]
        name = f"{metric}-{ch}-{es}".replace("_", "-")
        p = _write(tmp_path, name, system, samples["channels"][ch], estimator, analysis)
        out = tmp_path / "out" / name
        # distribution at the default --jobs (the cores: chunks on a process pool, so every pair's kernel
        # crosses a fork); the other two serial (--jobs 1: same numbers, tested byte-identical in
        # tests/engine/test_executors.py) — a pool per run was a third of this file's time
        jobs = [] if metric == "distribution" else ["--jobs", "1"]
        res = runner.invoke(app, ["run", str(p), "--out", str(out), *jobs])
        assert res.exit_code == 0, res.output
        t = pd.read_csv(out / f"{name}.csv")
        assert len(t) > 0 and (out / f"{name}.png").stat().st_size > 1000
        if metric == "compare":  # an estimator compared with itself: identical columns, difference exactly 0
            mt = t[t.statistic == "mean_trace"].value.tolist()
            assert mt[0] == mt[1]
            assert (t[t.statistic.str.startswith("diff_")].value == 0).all()
        # every generic metric says what its numbers are
        assert {"quantity", "P0", "conventions"} <= set(t.columns)
        assert set(t.quantity) == {"filtered"}


def test_the_core_pairs_are_compatible():
    """Guards the matrix against silently shrinking: these pairs must stay in it."""
    for ch in ("bernoulli", "delay", "gilbert_elliott", "multi", "trace"):
        assert _compatible(ch, "kf"), ch
