"""Issue 23.3–23.4: a failed run leaves nothing behind (full disk included), the resume cache belongs
to the result folder and is reused only for the identical scenario, and everything that can be
checked is checked before the Monte Carlo. (After each test the autouse debris scan of
tests/safety/conftest.py also looks at the test's folder.)"""

from __future__ import annotations

import errno
import json
import os
import textwrap
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from netkf_cli.runtime import montecarlo
from netkf_cli.app.cli import app

runner = CliRunner()
_real_run_chunk = montecarlo.run_chunk

MC = textwrap.dedent(
    """\
    name: mc
    system: {A: 1.2, C: 1, Q: 1, R: 1}
    channel: {kind: bernoulli, arrival: 0.8}
    estimator: {kind: kf}
    analysis: {kind: distribution, M: [1, 5, 50]}
    montecarlo: {runs: 600, horizon: 30, seed: 1, chunk: 100}
    """
)


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture
def cfg(tmp_path):
    p = tmp_path / "mc.yaml"
    p.write_text(MC)
    return p


def _everything(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


@pytest.fixture
def no_monte_carlo(monkeypatch):
    """Fail the test if any Monte Carlo chunk runs (the refusal must come before)."""
    def boom(*a, **k):
        raise AssertionError("a Monte Carlo chunk ran before the refusal")

    monkeypatch.setattr(montecarlo, "run_chunk", boom)


# ---- failures leave nothing --------------------------------------------------------------------

def test_full_disk_while_storing_a_chunk_leaves_nothing(tmp_path, cfg, monkeypatch):
    real_open = open
    calls = {"n": 0}

    class FillsUp:  # the chunk files montecarlo._store writes: the third fills the disk half-way
        def __init__(self, path, mode):
            self.f = real_open(path, mode)

        def write(self, data):
            calls["n"] += 1
            if calls["n"] == 3:
                self.f.write(b"half a chunk")
                raise OSError(errno.ENOSPC, "No space left on device")
            return self.f.write(data)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

    monkeypatch.setattr(montecarlo, "open", FillsUp, raising=False)  # the module's `open` before the builtin
    before = _everything(tmp_path)
    r = invoke("run", cfg, "--out", tmp_path / "res" / "deep" / "o", "-j", 1, "-q")
    assert r.exit_code == 1, r.output
    assert "No space left on device" in r.output and "Traceback" not in r.output
    assert "nothing of this run was kept" in r.output
    assert _everything(tmp_path) == before  # no cache, no .tmpNNNN, no lock, no res/deep/ folders


def test_a_torn_chunk_file_is_removed_where_it_was_written(tmp_path, monkeypatch):
    real_open = open

    class Torn:  # the file montecarlo._store writes: half a chunk, then the disk is full
        def __init__(self, path, mode):
            self.f = real_open(path, mode)

        def write(self, data):
            self.f.write(bytes(data)[:7])
            raise OSError(errno.ENOSPC, "No space left on device")

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

    monkeypatch.setattr(montecarlo, "open", Torn, raising=False)  # the module's `open` before the builtin
    path = tmp_path / "c" / f"chunk{montecarlo.CHUNK_SUFFIX}"
    with pytest.raises(OSError):
        montecarlo._store(path, {"s": np.ones(3)})
    assert list((tmp_path / "c").iterdir()) == []


def test_full_disk_while_writing_the_result_leaves_nothing(tmp_path, cfg, monkeypatch):
    import netkf_cli.runtime.io as io_mod

    def full(obj, path):
        Path(path).write_text("{")
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(io_mod, "write_json", full)
    before = _everything(tmp_path)
    r = invoke("run", cfg, "--out", tmp_path / "res" / "o", "-j", 1, "-q")
    assert r.exit_code == 1 and "No space left on device" in r.output, r.output
    assert _everything(tmp_path) == before


def test_an_internal_error_mid_run_leaves_nothing(tmp_path, cfg, monkeypatch):
    real = montecarlo.run_chunk
    calls = {"n": 0}

    def bug(kernel, c):
        calls["n"] += 1
        if calls["n"] == 3:
            raise TypeError("simulated bug")
        return real(kernel, c)

    monkeypatch.setattr(montecarlo, "run_chunk", bug)
    before = _everything(tmp_path)
    r = invoke("run", cfg, "--out", tmp_path / "a" / "b" / "o", "-j", 1, "-q")
    assert r.exit_code == 1 and "internal error (TypeError: simulated bug)" in r.output, r.output
    assert _everything(tmp_path) == before  # the chunks of a failed run are no use to anyone: gone


def test_the_api_leaves_nothing_either(tmp_path, cfg, monkeypatch):
    from netkf_cli import load, run

    def bug(kernel, c):
        raise TypeError("simulated bug")

    monkeypatch.setattr(montecarlo, "run_chunk", bug)
    before = _everything(tmp_path)
    with pytest.raises(TypeError):
        run(load(cfg), out=tmp_path / "x" / "y")
    assert _everything(tmp_path) == before


# ---- checked before the Monte Carlo, named in the message --------------------------------------

@pytest.mark.parametrize("old,new,path,needle", [
    ("name: mc", "name: " + "n" * 10_000, "name", "at most 100 characters"),
    ("name: mc", "name: '..'", "name", "dots only"),
    ("name: mc", "name: .hidden", "name", "must not start with a dot"),
    ("name: mc", "name: ../x", "name", "pattern"),
    ("chunk: 100}", "chunk: 100}\noutput: {dpi: 100000}", "output.dpi", "less than or equal to 1200"),
    ("runs: 600,", "runs: 1e15,", "montecarlo.runs", "--yes"),
])
def test_refused_before_any_work_naming_field_and_file(tmp_path, cfg, no_monte_carlo, old, new, path, needle):
    cfg.write_text(MC.replace(old, new))
    before = _everything(tmp_path)
    r = invoke("run", cfg, "--out", tmp_path / "res" / "o", "-j", 1)
    assert r.exit_code == 1, r.output
    assert f"mc.yaml:" in r.output and f" {path}:" in r.output and needle in r.output, r.output
    assert "Traceback" not in r.output and "reduce montecarlo.chunk" not in r.output
    assert _everything(tmp_path) == before


def test_run_count_limit_is_lifted_by_yes_or_the_field(tmp_path, cfg):
    cfg.write_text(MC.replace("runs: 600,", "runs: 1e15,"))
    r = invoke("run", cfg, "--out", tmp_path / "o", "--dry-run")
    assert r.exit_code == 1 and "montecarlo.max_runs" in r.output
    for extra in (("--yes",), ("montecarlo.max_runs=1e16",)):
        r = invoke("run", cfg, *extra, "--out", tmp_path / "o", "--dry-run")
        assert r.exit_code == 0 and "years" in r.output, r.output
    r = invoke("run", cfg, "--runs", 10**13, "--out", tmp_path / "o", "--dry-run")
    assert r.exit_code == 1 and "--runs:" in r.output


def test_output_on_a_mount_point_is_refused_before_any_work(tmp_path, cfg, no_monte_carlo, monkeypatch):
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    real = os.path.ismount
    monkeypatch.setattr(os.path, "ismount", lambda p: Path(p) == mnt or real(p))
    r = invoke("run", cfg, "--out", mnt)
    assert r.exit_code == 1 and "mount point" in r.output and str(mnt / "result") in r.output, r.output
    assert list(mnt.iterdir()) == [] and sorted(p.name for p in tmp_path.iterdir()) == ["mc.yaml", "mnt"]


def test_an_output_name_too_long_for_the_file_system_is_refused_first(tmp_path, cfg, no_monte_carlo):
    for name in ("x" * 300, "y" * 240):  # too long itself; too long for netkf's temporary sibling
        r = invoke("run", cfg, "--out", tmp_path / name)
        assert r.exit_code == 1 and "Choose a shorter --out" in r.output or "file system allows" in r.output, r.output
        assert "Traceback" not in r.output and "File name too long" not in r.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mc.yaml"]


def test_jobs_are_capped_at_the_cores(tmp_path, cfg):
    cores = montecarlo.usable_cores()
    r = invoke("run", cfg, "--out", tmp_path / "o", "--jobs", 32, "--dry-run", "--json")
    assert r.exit_code == 0, r.output
    plan = json.loads(r.output[r.output.index("{"):])
    assert plan["jobs"] == cores
    if cores < 32:
        assert "capped at" in r.output
    with montecarlo.execution("process", 32) as ex:
        assert ex.jobs == cores  # the library holds the same bound (memory: one process per core)


# ---- the resume cache: per folder, identical scenarios only -------------------------------------

def _interrupt_after(monkeypatch, n_ok: int) -> None:
    real = montecarlo.run_chunk
    calls = {"n": 0}

    def dying(kernel, c):
        calls["n"] += 1
        if calls["n"] > n_ok:
            raise KeyboardInterrupt
        return real(kernel, c)

    monkeypatch.setattr(montecarlo, "run_chunk", dying)


def test_resume_reuses_no_chunk_of_another_netkf_build(tmp_path, cfg, monkeypatch):
    """Chunks kept by an interrupted run are not mixed into a run of changed code (an upgrade between the two:
    its statistics may carry other keys, or other numbers): --resume says so and starts over, and the result
    equals an uninterrupted run."""
    from netkf_cli.runtime import io

    assert invoke("run", cfg, "--out", tmp_path / "full", "-j", 1, "-q").exit_code == 0
    _interrupt_after(monkeypatch, 2)
    assert invoke("run", cfg, "--out", tmp_path / "o", "-j", 1, "-q").exit_code == 130
    monkeypatch.setattr(montecarlo, "run_chunk", _real_run_chunk)
    monkeypatch.setattr(io, "code_digest", lambda: "0123456789abcdef")  # the code changed since
    r = invoke("run", cfg, "--out", tmp_path / "o", "-j", 1, "-q", "--resume")
    assert r.exit_code == 0, r.output
    out = " ".join(r.output.split())
    assert "another netkf build" in out and "none reused" in out and "0 chunks reused" in out, out
    man = json.loads((tmp_path / "o" / "manifest.json").read_text())
    assert man["execution"]["resumed"]["chunks_reused"] == 0 and "another netkf build" in man["execution"]["resumed"]["note"]
    name = man["name"]
    assert (tmp_path / "o" / f"{name}.csv").read_bytes() == (tmp_path / "full" / f"{name}.csv").read_bytes()


def test_resume_reuses_only_the_identical_scenario(tmp_path, cfg, monkeypatch):
    assert invoke("run", cfg, "--out", tmp_path / "full", "-j", 1, "-q").exit_code == 0
    res = tmp_path / "res"
    # 1. interrupted after 3 chunks: the chunks are kept, the message says how to continue
    _interrupt_after(monkeypatch, 3)
    r = invoke("run", cfg, "--out", res / "o", "-j", 1, "-q")
    assert r.exit_code == 130 and "--resume" in r.output and str(res / ".netkf-cache" / "o") in r.output, r.output
    assert len(list((res / ".netkf-cache" / "o").rglob("*.chunk"))) == 3
    monkeypatch.setattr(montecarlo, "run_chunk", _real_run_chunk)
    # 2. the seed changed: --resume reuses nothing and says so; the manifest records 0
    r = invoke("run", cfg, "montecarlo.seed=9", "--out", res / "o", "-j", 1, "-q", "--resume")
    assert r.exit_code == 0, r.output
    assert "different scenario" in r.output and "none reused" in r.output and "0 chunks reused" in r.output
    man = json.loads((res / "o" / "manifest.json").read_text())
    assert man["execution"]["resumed"]["requested"] is True and man["execution"]["resumed"]["chunks_reused"] == 0
    assert "different scenario" in man["execution"]["resumed"]["note"]
    assert man["montecarlo"]["seed"] == 9
    # 3. the identical scenario: the 3 finished chunks are reused, the numbers are the uninterrupted ones
    _interrupt_after(monkeypatch, 3)
    assert invoke("run", cfg, "--out", res / "p", "-j", 1, "-q").exit_code == 130
    monkeypatch.setattr(montecarlo, "run_chunk", _real_run_chunk)
    r = invoke("run", cfg, "--out", res / "p", "-j", 1, "-q", "--resume")
    assert r.exit_code == 0 and "3 chunks reused" in r.output, r.output
    man = json.loads((res / "p" / "manifest.json").read_text())
    assert man["execution"]["resumed"] == {"requested": True, "chunks_reused": 3}
    assert (res / "p" / "mc.csv").read_bytes() == (tmp_path / "full" / "mc.csv").read_bytes()
    assert sorted(p.name for p in res.iterdir()) == ["o", "p"]  # caches and locks gone


def test_the_cache_belongs_to_the_result_folder(tmp_path):
    from netkf_cli import load
    from netkf_cli.app.runner import result_paths

    sc = load(MC)
    (a, ca), (b, cb) = result_paths(sc, tmp_path / "a"), result_paths(sc, tmp_path / "b")
    assert ca != cb and ca.name == "a" and cb.name == "b"  # the same scenario into two folders: two caches
