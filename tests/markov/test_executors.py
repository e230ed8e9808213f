"""Markov Monte Carlo (Example 2's generic state_error config) on every executor: the generic kernel's chunks run
on the workers (none in the parent, the manifest's execution record), the CSVs are byte-identical to the serial
run, and an interrupted run resumes to the uninterrupted numbers (issue 12.5)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from netkf_cli.runtime import montecarlo
from netkf_cli.app.runner import run_scenario_file

from .conftest import CONFIGS

ROOT = Path(__file__).resolve().parents[2]
SMALL = {"montecarlo": {"horizon": 20, "burn_in": 10, "chunk": 100}}  # the state_error config: sdp_check 0 already
RUNS = 400  # 4 chunks


def _ran(folder) -> dict:
    return json.loads((folder / "manifest.json").read_text())["execution"]["chunks_ran"]


def test_jobs2_csv_is_byte_identical(tmp_path):
    cfg = CONFIGS / "example2.yaml"
    a = run_scenario_file(cfg, out_dir=tmp_path / "serial" / "m", runs=RUNS, overrides=SMALL, executor="serial")
    b = run_scenario_file(cfg, out_dir=tmp_path / "jobs2" / "m", runs=RUNS, overrides=SMALL, executor="process", jobs=2)
    for p in sorted(a.glob("*.csv")):
        assert p.read_bytes() == (b / p.name).read_bytes(), p.name
    # jobs=2 is the parent and one worker (Execution.workers): the 4 Monte Carlo chunks ran on both, the worker
    # computing at least the first (a single-chunk pass, the trajectory run, stays in the parent)
    ran = _ran(b)
    assert _ran(a)["chunks_in_parent"] == _ran(a)["chunks"] == 5 == ran["chunks"]
    assert ran["processes"] == 2 and 1 <= ran["chunks_in_parent"] <= 4, ran


def test_dask_runs_fusion_and_markov_kernels(tmp_path):
    # One LocalCluster (2 single-threaded worker processes) for both topics' generic configs (markov Example 2's
    # state_error, fusion Fig. 3's time_average over a loss grid): the chunks run on the workers (none in this
    # process) and the CSVs equal the serial ones byte for byte.
    distributed = pytest.importorskip("dask.distributed")
    runs = [(CONFIGS / "example2.yaml", {"montecarlo": {"horizon": 12, "burn_in": 4, "chunk": 30}}),
            (ROOT / "configs" / "fusion" / "fig3.yaml",
             {"montecarlo": {"horizon": 30, "burn_in": 10, "chunk": 30}, "analysis": {"over": {"channel.loss": [0.4]}}})]
    serial = [run_scenario_file(c, out_dir=tmp_path / "serial" / c.stem, runs=90, overrides=o, executor="serial")
              for c, o in runs]
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  scheduler_kwargs={"dashboard_address": "127.0.0.1:0"}) as cl:
        dask = [run_scenario_file(c, out_dir=tmp_path / "dask" / c.stem, runs=90, overrides=o, executor="dask",
                                  jobs=2, scheduler=cl.scheduler_address) for c, o in runs]
    for a, b in zip(serial, dask):
        assert _ran(a)["chunks_in_parent"] == _ran(a)["chunks"] == _ran(b)["chunks"] >= 3
        assert _ran(b)["chunks_in_parent"] <= 1  # markov's trajectory run: one chunk, kept in the parent
        for p in sorted(a.glob("*.csv")):
            assert p.read_bytes() == (b / p.name).read_bytes(), p.name


def test_resume_after_interrupt_equals_uninterrupted(tmp_path, monkeypatch):
    cfg = CONFIGS / "example2.yaml"
    full = run_scenario_file(cfg, out_dir=tmp_path / "full" / "m", runs=RUNS, overrides=SMALL, executor="serial")
    real = montecarlo.run_chunk
    calls = {"n": 0}

    def dying(kernel, c):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt  # after two finished chunks
        return real(kernel, c)

    monkeypatch.setattr(montecarlo, "run_chunk", dying)
    out = tmp_path / "res" / "m"
    with pytest.raises(KeyboardInterrupt):
        run_scenario_file(cfg, out_dir=out, runs=RUNS, overrides=SMALL, executor="serial")
    monkeypatch.setattr(montecarlo, "run_chunk", lambda k, c: (calls.__setitem__("n", calls["n"] + 1), real(k, c))[1])
    calls["n"] = 0
    run_scenario_file(cfg, out_dir=out, runs=RUNS, overrides=SMALL, executor="serial", resume=True)
    assert calls["n"] == (4 - 2) + 1  # the two unfinished Monte Carlo chunks, then the trajectory run's one chunk
    for p in sorted(full.glob("*.csv")):
        assert p.read_bytes() == (out / p.name).read_bytes(), p.name
