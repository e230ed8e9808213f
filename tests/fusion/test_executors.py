"""Fusion Monte Carlo (fig3's generic config: MF, IBF, OLPEF on a multi channel over a loss grid) on every
executor: byte-identical CSVs under --jobs 2, and resume after an interrupt (issue 12.5: the old closure
kernel learned its statistic names while running, so a run whose chunks all came from the resume cache
never learned them, ``KeyError: 'mf_f'``).

The generic kernel's chunks really run on the workers (none in the parent) and pickle: tests/engine/
test_executors.py (every per-run estimator, fusion included, serial = process pool = Dask bit for bit);
fusion's kernel on Dask: tests/markov/test_executors.py::test_dask_runs_fusion_and_markov_kernels.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from netkf_cli.runtime import montecarlo
from netkf_cli.app.runner import run_scenario_file

ROOT = Path(__file__).resolve().parents[2]
CFG = ROOT / "configs" / "fusion" / "fig3.yaml"
SMALL = {"montecarlo": {"horizon": 40, "burn_in": 20, "chunk": 50}, "analysis": {"over": {"channel.loss": [0.2, 0.6]}}}
RUNS = 200  # 4 chunks per grid point


def _in_parent(folder) -> int:
    return json.loads((folder / "manifest.json").read_text())["execution"]["chunks_ran"]["chunks_in_parent"]


def test_jobs2_csv_is_byte_identical(tmp_path):
    a = run_scenario_file(CFG, out_dir=tmp_path / "serial" / "f", runs=RUNS, overrides=SMALL, executor="serial")
    b = run_scenario_file(CFG, out_dir=tmp_path / "jobs2" / "f", runs=RUNS, overrides=SMALL, executor="process", jobs=2)
    for p in sorted(a.glob("*.csv")):
        assert p.read_bytes() == (b / p.name).read_bytes(), p.name
    # jobs=2 is the parent and one worker (Execution.workers): the worker computed at least the first chunk
    assert _in_parent(b) < 8 and _in_parent(a) == 8


def test_resume_after_interrupt_equals_uninterrupted(tmp_path, monkeypatch):
    full = run_scenario_file(CFG, out_dir=tmp_path / "full" / "f", runs=RUNS, overrides=SMALL, executor="serial")
    real = montecarlo.run_chunk
    calls = {"n": 0}

    def dying(kernel, c):
        calls["n"] += 1
        if calls["n"] == 6:  # Ctrl-C in the second grid point, after 5 finished chunks
            raise KeyboardInterrupt
        return real(kernel, c)

    monkeypatch.setattr(montecarlo, "run_chunk", dying)
    out = tmp_path / "res" / "f"
    with pytest.raises(KeyboardInterrupt):
        run_scenario_file(CFG, out_dir=out, runs=RUNS, overrides=SMALL, executor="serial")
    assert not out.exists()
    monkeypatch.setattr(montecarlo, "run_chunk", lambda k, c: (calls.__setitem__("n", calls["n"] + 1), real(k, c))[1])
    calls["n"] = 0
    run_scenario_file(CFG, out_dir=out, runs=RUNS, overrides=SMALL, executor="serial", resume=True)
    assert calls["n"] == 8 - 5  # the first grid point came entirely from the cache (the old KeyError case)
    for p in sorted(full.glob("*.csv")):
        assert p.read_bytes() == (out / p.name).read_bytes(), p.name
