"""Every per-run estimator's generic kernel really runs on worker processes (process pool and
Dask) with byte-identical CSVs, and an interrupted run resumes to the uninterrupted numbers."""

from __future__ import annotations

import json

import pytest
import yaml

from netkf_cli.runtime import montecarlo
from netkf_cli.config.compat import compatible_channels
from netkf_cli.app.runner import run_scenario_file
from netkf_cli.config.scenario import kinds
from netkf_cli.core.spec import EstimatorModel

from .conftest import SCALAR, sample_estimators


def _bernoulli_estimators() -> list[dict]:
    out = []
    for k, spec in sorted(sample_estimators().items()):
        cls = kinds(EstimatorModel)[k]
        if "bernoulli" in compatible_channels(cls) and cls.covariances is not EstimatorModel.covariances:
            if k == "fusion":
                spec = {**spec, "strategies": [s for s in spec.get("strategies", ["mf"]) if s != "olpef"] or ["mf"]}
            out.append(spec)
    return out


@pytest.fixture
def cfg(tmp_path):
    doc = {"name": "ex", "system": SCALAR, "channel": {"kind": "bernoulli", "arrival": 0.7},
           "estimators": _bernoulli_estimators(), "analysis": {"kind": "compare", "M": [2.0, 10.0]},
           "montecarlo": {"runs": 4000, "horizon": 30, "seed": 11, "chunk": 500}}
    p = tmp_path / "ex.yaml"
    p.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return p


def _ran(folder):
    return json.loads((folder / "manifest.json").read_text())["execution"]["chunks_ran"]


def test_every_estimator_runs_on_workers_with_identical_csvs(cfg, tmp_path):
    assert len(_bernoulli_estimators()) >= 3  # kf, buffered, smoother at least
    a = run_scenario_file(cfg, out_dir=tmp_path / "serial", executor="serial")
    assert _ran(a) == {"chunks": 8, "processes": 1, "chunks_in_parent": 8}
    b = run_scenario_file(cfg, out_dir=tmp_path / "jobs2", executor="process", jobs=2)
    # jobs=2: the parent and one worker (Execution.workers); the worker computes at least the first chunk
    assert _ran(b)["chunks"] == 8 and _ran(b)["processes"] <= 2 and _ran(b)["chunks_in_parent"] < 8
    assert (a / "ex.csv").read_bytes() == (b / "ex.csv").read_bytes()
    pytest.importorskip("dask.distributed")
    c = run_scenario_file(cfg, out_dir=tmp_path / "dask", executor="dask", jobs=2, scheduler="local")
    assert _ran(c)["chunks_in_parent"] == 0 and _ran(c)["chunks"] == 8
    assert (a / "ex.csv").read_bytes() == (c / "ex.csv").read_bytes()


def test_generic_kernel_resumes_to_identical_numbers(cfg, tmp_path, monkeypatch):
    full = run_scenario_file(cfg, out_dir=tmp_path / "full", executor="serial")
    real = montecarlo.run_chunk
    calls = {"n": 0}

    def dying(kernel, c):
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt
        return real(kernel, c)

    monkeypatch.setattr(montecarlo, "run_chunk", dying)
    out = tmp_path / "res"
    with pytest.raises(KeyboardInterrupt):
        run_scenario_file(cfg, out_dir=out, executor="serial")
    monkeypatch.setattr(montecarlo, "run_chunk", real)
    res = run_scenario_file(cfg, out_dir=out, executor="serial", resume=True)
    assert _ran(res)["chunks"] == 5 and _ran(res)["chunks_from_resume_cache"] == 3
    assert (res / "ex.csv").read_bytes() == (full / "ex.csv").read_bytes()
