"""Fusion Monte Carlo on every executor: module-level kernels, worker processes, resume (issue 12.5).

The old closure kernel learned its statistic names while running, so a run whose chunks all came
from the resume cache never learned them (``KeyError: 'mf_f'``); :class:`FusionKernel` knows its
keys when it is built.
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import numpy as np
import pytest

from netkf_cli import montecarlo
from netkf_cli.channels.multi import MultiChannel
from netkf_cli.estimators.fusion import FusionKernel
from netkf_cli.runner import run_scenario_file

ROOT = Path(__file__).resolve().parents[2]
CFG = ROOT / "configs" / "fusion" / "fig3.yaml"
SMALL = {"montecarlo": {"horizon": 40, "burn_in": 20, "chunk": 50}, "analysis": {"over": {"channel.loss": [0.2, 0.6]}}}
RUNS = 200  # 4 chunks per grid point


class ParentCounter:
    """Wraps a kernel; counts the chunks that ran in the process that built it (must be 0 on a pool)."""

    def __init__(self, inner):
        self.inner, self.parent = inner, os.getpid()

    def __call__(self, rng, n):
        out = dict(self.inner(rng, n))
        out["in_parent"] = np.array(int(os.getpid() == self.parent))
        return out


def _kernel(strategies=("mf", "ibf", "olpef")):
    ch = MultiChannel(kind="multi", sensors=4, loss=0.4)
    return FusionKernel(0.9, 1.0, 1e-2, 1.0, None, ch, strategies, horizon=30, burn_in=10)


def test_kernel_is_picklable_with_fixed_keys():
    k = _kernel()
    k2 = pickle.loads(pickle.dumps(k))
    a = k(np.random.default_rng(1), 30)
    b = k2(np.random.default_rng(1), 30)
    assert set(a) == {"sum", "cross", "sum3", "sum4", "nonfinite"} and k.keys == ("mf_f", "mf_p", "ibf_f", "ibf_p", "olpef_f")
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])


def test_worker_processes_do_the_work_and_agree_bitwise():
    k = ParentCounter(_kernel())
    serial = montecarlo.run_chunked(k, 120, 30, 5, stream=3)
    with montecarlo.execution("process", jobs=2):
        pooled = montecarlo.run_chunked(k, 120, 30, 5, stream=3)
    assert serial["in_parent"] == 4 and pooled["in_parent"] == 0  # 4 chunks, none in the parent under --jobs 2
    for key in ("sum", "cross", "sum3", "sum4", "nonfinite"):
        np.testing.assert_array_equal(serial[key], pooled[key])


def test_jobs2_csv_is_byte_identical(tmp_path):
    a = run_scenario_file(CFG, out_dir=tmp_path / "serial" / "f", runs=RUNS, overrides=SMALL, executor="serial")
    b = run_scenario_file(CFG, out_dir=tmp_path / "jobs2" / "f", runs=RUNS, overrides=SMALL, executor="process", jobs=2)
    for p in sorted(a.glob("*.csv")):
        assert p.read_bytes() == (b / p.name).read_bytes(), p.name
    # Dask: tests/markov/test_executors.py::test_dask_runs_fusion_and_markov_kernels (one cluster for both)


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
