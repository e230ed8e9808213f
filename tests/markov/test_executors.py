"""Markov Monte Carlo on every executor: the module-level kernel runs on workers and resumes (issue 12.5)."""

from __future__ import annotations

import os

import numpy as np
import pytest

from netkf_cli import montecarlo
from netkf_cli.estimators.markov_filters import MarkovMSEKernel, lmmse_filter, naive_filter
from netkf_cli.estimators.markov_lmi import lmi_design
from netkf_cli.runner import run_scenario_file

from .conftest import CONFIGS, setup_of

SMALL = {"montecarlo": {"horizon": 20, "burn_in": 10, "chunk": 100}}  # the state_error config: sdp_check 0 already
RUNS = 400  # 4 chunks


class ParentCounter:
    """Counts the chunks that ran in the process that built it (0 on a process pool)."""

    def __init__(self, inner):
        self.inner, self.parent = inner, os.getpid()

    def __call__(self, rng, n):
        out = dict(self.inner(rng, n))
        out["in_parent"] = np.array(int(os.getpid() == self.parent))
        return out


def test_worker_processes_do_the_work_and_agree_bitwise():
    sc, (sysm, ch, est, md, x0, xs0, P0, rho) = setup_of("example2")
    K = 15
    lin = {"lmmse": lmmse_filter(md, ch.T, ch.pi0, x0, P0, K), "naive_kf": naive_filter(md, x0, P0, K),
           "lmi": lmi_design(md, rho, x0, P0, K, design="closed_form").filter}
    k = ParentCounter(MarkovMSEKernel(md, ch, lin, x0, P0, K, 5))
    serial = montecarlo.run_chunked(k, 120, 30, 9, stream=2)
    with montecarlo.execution("process", jobs=2):
        pooled = montecarlo.run_chunked(k, 120, 30, 9, stream=2)
    assert serial["in_parent"] == 4 and pooled["in_parent"] == 0
    for key in serial:
        if key != "in_parent":
            np.testing.assert_array_equal(serial[key], pooled[key])


def test_jobs2_csv_is_byte_identical(tmp_path):
    cfg = CONFIGS / "example2.yaml"
    a = run_scenario_file(cfg, out_dir=tmp_path / "serial" / "m", runs=RUNS, overrides=SMALL, executor="serial")
    b = run_scenario_file(cfg, out_dir=tmp_path / "jobs2" / "m", runs=RUNS, overrides=SMALL, executor="process", jobs=2)
    for p in sorted(a.glob("*.csv")):
        assert p.read_bytes() == (b / p.name).read_bytes(), p.name


def test_dask_runs_fusion_and_markov_kernels():
    # One LocalCluster (2 single-threaded worker processes) for both topics' kernels: the chunks run on
    # the workers (none in this process) and the summed statistics equal the serial ones bit for bit.
    pytest.importorskip("dask.distributed")
    from netkf_cli.channels.multi import MultiChannel
    from netkf_cli.estimators.fusion import FusionKernel

    sc, (sysm, ch, est, md, x0, xs0, P0, rho) = setup_of("example2")
    K = 12
    lin = {"lmmse": lmmse_filter(md, ch.T, ch.pi0, x0, P0, K), "naive_kf": naive_filter(md, x0, P0, K),
           "lmi": lmi_design(md, rho, x0, P0, K, design="closed_form").filter}
    kernels = [ParentCounter(MarkovMSEKernel(md, ch, lin, x0, P0, K, 4)),
               ParentCounter(FusionKernel(0.9, 1.0, 1e-2, 1.0, None, MultiChannel(kind="multi", sensors=4, loss=0.4),
                                          ["mf", "ibf", "olpef"], horizon=30, burn_in=10))]
    serial = [montecarlo.run_chunked(k, 90, 30, 4, stream=1) for k in kernels]
    with montecarlo.execution("dask", jobs=2, scheduler="local"):
        dask = [montecarlo.run_chunked(k, 90, 30, 4, stream=1) for k in kernels]
    for a, b in zip(serial, dask):
        assert a["in_parent"] == 3 and b["in_parent"] == 0
        for key in a:
            if key != "in_parent":
                np.testing.assert_array_equal(a[key], b[key])


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
