"""Executors, resume and retry: the same numbers whatever ran the chunks (issue 9)."""

import os
import textwrap

import numpy as np
import pytest

from netkf_cli.runtime import montecarlo
from netkf_cli.core.errors import NetkfError
from netkf_cli.app.runner import run_scenario_file

SCENARIO = textwrap.dedent(
    """\
    name: ex
    system: {A: 1.4, C: 1, Q: 0.2, R: 0.5, P0: steady}
    channel: {kind: delay, delay: {kind: poisson, mean: 5}, buffer: 10}
    estimator: {kind: buffered}
    analysis: {kind: prob_vs_M, M: [1, 3, 10, 30, 100]}
    montecarlo: {runs: 6000, horizon: 40, seed: 11, chunk: 1000}
    """
)


@pytest.fixture
def cfg(tmp_path):
    p = tmp_path / "ex.yaml"
    p.write_text(SCENARIO)
    return p


def _csv(folder):
    return (folder / "ex.csv").read_bytes()


def test_serial_jobs2_and_dask_local_cluster_give_identical_csvs(cfg, tmp_path):
    a = run_scenario_file(cfg, out_dir=tmp_path / "serial", executor="serial")
    b = run_scenario_file(cfg, out_dir=tmp_path / "jobs2", executor="process", jobs=2)
    assert _csv(a) == _csv(b)
    pytest.importorskip("dask.distributed")
    c = run_scenario_file(cfg, out_dir=tmp_path / "dask", executor="dask", jobs=2, scheduler="local")
    assert _csv(a) == _csv(c)


def test_interrupted_run_resumes_to_identical_numbers(cfg, tmp_path, monkeypatch):
    full = run_scenario_file(cfg, out_dir=tmp_path / "full", executor="serial")
    real = montecarlo.run_chunk
    calls = {"n": 0}

    def dying(kernel, c):
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt  # Ctrl-C after three finished chunks
        return real(kernel, c)

    monkeypatch.setattr(montecarlo, "run_chunk", dying)
    out = tmp_path / "res"
    with pytest.raises(KeyboardInterrupt):
        run_scenario_file(cfg, out_dir=out, executor="serial")
    assert not out.exists()  # nothing half-written
    assert list((tmp_path / ".netkf-cache").rglob("*.chunk"))  # finished chunks kept for --resume
    monkeypatch.setattr(montecarlo, "run_chunk", lambda k, c: (calls.__setitem__("n", calls["n"] + 1), real(k, c))[1])
    calls["n"] = 0
    run_scenario_file(cfg, out_dir=out, executor="serial", resume=True)
    assert calls["n"] == 6 - 3  # only the unfinished chunks ran
    assert _csv(out) == _csv(full)
    assert not list((tmp_path / ".netkf-cache").rglob("*.chunk"))  # cache cleared after success


class Flaky:
    """A kernel that fails the first `fails` times it is called."""

    def __init__(self, fails):
        self.fails = fails

    def __call__(self, rng, n):
        if self.fails > 0:
            self.fails -= 1
            raise RuntimeError("a bug in a kernel")
        return {"s": rng.random(n).sum(), "n": n}


class DiesOnce:
    """Kills its worker process the first time it runs in a worker (a lost worker, not a bug); in the parent,
    which computes chunks too (Execution.workers), it never dies."""

    def __init__(self, flag):
        self.flag = str(flag)
        self.parent = os.getpid()

    def __call__(self, rng, n):
        if os.getpid() != self.parent and not os.path.exists(self.flag):
            open(self.flag, "w").close()
            os._exit(1)
        return {"s": rng.random(n).sum(), "n": n}


def test_exception_in_a_kernel_is_a_bug_not_retried_and_names_the_chunk():
    with pytest.raises(RuntimeError, match="a bug in a kernel") as info:
        montecarlo.run_chunked(Flaky(1), 10, 4, seed=3, label="demo")
    assert any("chunk 0 of stream 0 (runs 0–3, seed 3, demo)" in n for n in info.value.__notes__)


def test_lost_worker_is_retried_with_identical_numbers(tmp_path):
    ref = montecarlo.run_chunked(Flaky(0), 4000, 1000, seed=3)
    with montecarlo.execution("process", jobs=2):
        got = montecarlo.run_chunked(DiesOnce(tmp_path / "died"), 4000, 1000, seed=3)
    assert (tmp_path / "died").exists()
    assert got["s"] == ref["s"] and got["n"] == 4000


class SlowInWorkers:
    """Sleeps in worker processes only, so that the parent, one of the jobs, has time to compute chunks."""

    def __init__(self):
        self.parent = os.getpid()

    def __call__(self, rng, n):
        import time

        if os.getpid() != self.parent:
            time.sleep(0.3)
        return {"s": rng.random(n).sum(), "n": n}


def test_jobs2_is_the_parent_and_one_worker_with_identical_numbers():
    """--jobs 2 forks one worker and the parent computes chunks too (Execution.workers): two processes ran
    chunks, the worker at least the first, and the sums equal the serial ones exactly (chunk order kept)."""
    ref = montecarlo.run_chunked(SlowInWorkers(), 6000, 1000, seed=4)
    with montecarlo.execution("process", jobs=2) as ex:
        assert ex.workers() == 1
        got = montecarlo.run_chunked(SlowInWorkers(), 6000, 1000, seed=4)
        ran = ex.report()
    assert got["s"] == ref["s"] and got["n"] == 6000
    assert ran["chunks"] == 6 and ran["processes"] == 2 and 1 <= ran["chunks_in_parent"] <= 5, ran


class Steady:
    """Every chunk takes the same time wherever it runs (a sleep): how the chunks are shared is the schedule's."""

    def __call__(self, rng, n):
        import time

        time.sleep(0.2)
        return {"s": rng.random(n).sum(), "n": n}


@pytest.mark.parametrize("chunks", [2, 4])
def test_a_short_run_is_shared_between_the_parent_and_its_worker(chunks):
    """--jobs 2 on a run of 2 or 4 equal chunks: the parent computes half of them. (Queuing two chunks per
    worker gave both chunks of a 2-chunk run to the one worker while the parent waited, and 1 of 4.)"""
    ref = montecarlo.run_chunked(Flaky(0), chunks * 1000, 1000, seed=5)
    with montecarlo.execution("process", jobs=2) as ex:
        got = montecarlo.run_chunked(Steady(), chunks * 1000, 1000, seed=5)
        ran = ex.report()
    assert got["s"] == ref["s"] and got["n"] == chunks * 1000
    assert ran["chunks"] == chunks and ran["chunks_in_parent"] == chunks // 2, ran


def test_a_closure_kernel_is_refused_on_worker_processes():
    def closure(rng, n):
        return {"n": n}

    with montecarlo.execution("process", jobs=2):
        with pytest.raises(montecarlo.KernelNotShippable, match="cannot be pickled"):
            montecarlo.run_chunked(closure, 100, 10, seed=0)


def test_streams_are_spawn_keys_not_seed_arithmetic():
    k = Flaky(0)
    a = montecarlo.run_chunked(k, 100, 100, seed=5, stream=1)
    b = montecarlo.run_chunked(k, 100, 100, seed=6, stream=0)
    ref = np.random.default_rng(np.random.SeedSequence(5, spawn_key=(1, 0))).random(100).sum()
    assert a["s"] == ref and a["s"] != b["s"]


def test_chunk_plan_is_lazy():
    plan = montecarlo.plan_chunks(10**12, 20_000, 0)
    assert len(plan) == 50_000_000 and plan[-1].runs == 20_000 and plan[3].first_run == 60_000


def test_chunk_streams_depend_on_seed_and_index_only():
    k = Flaky(0)
    a = montecarlo.run_chunked(k, 10_000, 1000, seed=5)
    with montecarlo.execution("process", jobs=2):
        b = montecarlo.run_chunked(k, 10_000, 1000, seed=5)
    assert a["s"] == b["s"] and a["n"] == b["n"] == 10_000
    assert np.isclose(a["s"] / 10_000, 0.5, atol=5 * np.sqrt(1 / 12 / 10_000))
