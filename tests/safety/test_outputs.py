"""Result folders are safe (issue 14.2, 14.5, 14.6): netkf never deletes what it did not write,
concurrent runs do not clobber each other, killed writes are cleaned up, permissions are normal,
manifests hold no absolute author paths, progress and timings are honest, interrupts and OS
errors are one line."""

from __future__ import annotations

import json
import os
import re
import signal
import stat
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from netkf_cli.runtime import io
from netkf_cli.app.cli import app

ROOT = Path(__file__).resolve().parents[2]
runner = CliRunner()

THETA = textwrap.dedent(
    """\
    name: t
    system: {A: 1.4, C: 1, Q: 0.2, R: 0.5}
    channel: {kind: delay, delay: {kind: poisson, mean: 5}, buffer: 10}
    analysis: {kind: theta_vs_buffer, M: [50, 150], D_max: 8}
    """
)


def mc_config(runs: int, name: str = "mc", chunk: int = 20000) -> str:
    return textwrap.dedent(
        f"""\
        name: {name}
        system: {{A: 1.4, C: 1, Q: 0.2, R: 0.5}}
        channel: {{kind: delay, delay: {{kind: poisson, mean: 5}}, buffer: 10}}
        estimator: {{kind: buffered}}
        analysis: {{kind: prob_vs_M, M: [50, 150]}}
        montecarlo: {{runs: {runs}, horizon: 100, burn_in: 50, seed: 0, chunk: {chunk}}}
        """
    )


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture
def theta(tmp_path):
    cfg = tmp_path / "t.yaml"
    cfg.write_text(THETA)
    return cfg


def _tree(path: Path) -> dict:
    return {str(p.relative_to(path)): (p.read_bytes() if p.is_file() else None) for p in sorted(path.rglob("*"))}


# ---- never delete what netkf did not write ------------------------------------------------------

def test_force_onto_folder_with_foreign_file_is_refused(tmp_path, theta):
    out = tmp_path / "res"
    assert invoke("run", theta, "--out", out).exit_code == 0
    (out / "thesis.tex").write_text("three years of work")
    before = _tree(out)
    r = invoke("run", theta, "--out", out, "--force")
    assert r.exit_code == 1 and "thesis.tex" in r.output and "did not write" in r.output
    assert _tree(out) == before


def test_force_onto_folder_without_manifest_is_refused(tmp_path, theta):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("x")
    r = invoke("run", theta, "--out", out, "--force")
    assert r.exit_code == 1 and "not a result folder netkf wrote" in r.output
    assert (out / "notes.txt").read_text() == "x" and len(list(out.iterdir())) == 1


def test_empty_folder_is_used_without_force(tmp_path, theta):
    out = tmp_path / "empty"
    out.mkdir()
    r = invoke("run", theta, "--out", out)
    assert r.exit_code == 0, r.output
    assert (out / "manifest.json").exists()


def test_force_onto_forged_manifest_with_foreign_file_is_refused(tmp_path, theta):
    out = tmp_path / "res"
    out.mkdir()
    (out / "manifest.json").write_text(json.dumps({"written_by": "netkf", "files": ["manifest.json"]}))
    (out / "data.csv").write_text("precious")
    r = invoke("run", theta, "--out", out, "--force")
    assert r.exit_code == 1 and "data.csv" in r.output
    assert (out / "data.csv").read_text() == "precious"


def test_force_onto_a_file_is_refused(tmp_path, theta):
    f = tmp_path / "afile"
    f.write_text("keep me")
    r = invoke("run", theta, "--out", f, "--force")
    assert r.exit_code == 1 and "is a file" in r.output
    assert f.read_text() == "keep me"


def test_out_below_a_file_is_one_message(tmp_path, theta):
    f = tmp_path / "afile"
    f.write_text("keep me")
    r = invoke("run", theta, "--out", f / "sub" / "res")
    assert r.exit_code == 1 and "is a file, not a folder" in r.output and "Traceback" not in r.output
    assert f.read_text() == "keep me"


def test_force_onto_cwd_and_parents_is_refused(tmp_path, theta, monkeypatch):
    (tmp_path / "keep.txt").write_text("x")
    monkeypatch.chdir(tmp_path)
    for target in (".", tmp_path, tmp_path.parent):
        r = invoke("run", theta, "--out", target, "--force")
        assert r.exit_code == 1 and "current folder" in r.output, r.output
    assert (tmp_path / "keep.txt").read_text() == "x"


def test_force_onto_repository_results_root_is_refused(theta):
    results = ROOT / "results"
    before = sorted(p.name for p in results.iterdir())
    for target in (results, ROOT):
        r = invoke("run", theta, "--out", target, "--force")
        assert r.exit_code == 1, r.output
        assert "results root" in r.output or "current folder" in r.output or "repository" in r.output
    assert sorted(p.name for p in results.iterdir()) == before


def test_committed_results_are_recognised_as_netkfs():
    """Folders written before the ``written_by`` marker: accepted by the manifest's shape."""
    for folder in sorted((ROOT / "results").iterdir()):
        if folder.is_dir() and (folder / "manifest.json").exists():
            man, why = io.netkf_ownership(folder)
            assert man is not None, f"{folder.name}: {why}"


def test_same_scenario_replaces_without_force_other_needs_it(tmp_path, theta):
    out = tmp_path / "res"
    assert invoke("run", theta, "--out", out).exit_code == 0
    assert invoke("run", theta, "--out", out).exit_code == 0  # same hash: a reproducible rerun
    other = tmp_path / "u.yaml"
    other.write_text(THETA.replace("D_max: 8", "D_max: 9"))
    r = invoke("run", other, "--out", out)
    assert r.exit_code == 1 and "--force" in r.output
    assert invoke("run", other, "--out", out, "--force").exit_code == 0
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_symlink_target_is_refused(tmp_path, theta):
    real = tmp_path / "real"
    assert invoke("run", theta, "--out", real).exit_code == 0
    link = tmp_path / "link"
    link.symlink_to(real)
    r = invoke("run", theta, "--out", link, "--force")
    assert r.exit_code == 1 and "symbolic link" in r.output
    assert link.is_symlink() and (real / "manifest.json").exists()


# ---- permissions, manifests, leftovers -----------------------------------------------------------

def test_result_permissions_follow_umask(tmp_path, theta):
    old = os.umask(0o022)
    try:
        out = tmp_path / "res"
        assert invoke("run", theta, "--out", out).exit_code == 0
    finally:
        os.umask(old)
    assert stat.S_IMODE(out.stat().st_mode) == 0o755
    for f in out.iterdir():
        assert stat.S_IMODE(f.stat().st_mode) == 0o644, f


def test_manifest_has_marker_and_no_absolute_source(tmp_path, theta, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert invoke("run", "t.yaml", "--out", "res").exit_code == 0
    man = json.loads((tmp_path / "res" / "manifest.json").read_text())
    assert man["written_by"] == "netkf" and man["source"] == "t.yaml"
    # a config outside the working folder and the repository: its name only
    elsewhere = tmp_path / "deep" / "x"
    elsewhere.mkdir(parents=True)
    monkeypatch.chdir(elsewhere)
    assert invoke("run", tmp_path / "t.yaml", "--out", "res2", "--force").exit_code == 0
    man = json.loads((elsewhere / "res2" / "manifest.json").read_text())
    assert man["source"] == "t.yaml"
    assert str(tmp_path) not in json.dumps(man)


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_killed_write_leftovers_are_cleaned_by_next_run(tmp_path, theta):
    parent = tmp_path / "results"
    parent.mkdir()
    dead = _dead_pid()
    tmp_left = parent / f".other.w.tmp-{dead}-abc1"
    tmp_left.mkdir()
    (tmp_left / "other.csv").write_text("half")
    old_left = parent / f".gone.existing.old-{dead}-abc2"  # killed between the two renames
    old_left.mkdir()
    (old_left / "manifest.json").write_text("{}")
    live = parent / f".busy.w.tmp-{os.getppid()}-abc3"  # owner alive: untouched
    live.mkdir()
    foreign = parent / ".my.w.tmp-notes"  # not netkf's name pattern: untouched
    foreign.mkdir()
    stale = parent / ".killed.lock"  # the lock file of a SIGKILLed run: nobody holds it
    stale.write_text("pid 1: netkf run x")
    r = invoke("run", theta, "--out", parent / "t")
    assert r.exit_code == 0, r.output
    assert not tmp_left.exists()
    assert not old_left.exists() and (parent / "gone" / "manifest.json").exists()  # restored
    assert live.exists() and foreign.exists()
    assert not stale.exists()
    live.rmdir()  # ours, made by this test (the debris scan runs after it)


def test_force_over_read_only_result_leaves_nothing_behind(tmp_path, theta):
    out = tmp_path / "res"
    assert invoke("run", theta, "--out", out).exit_code == 0
    for f in out.iterdir():
        f.chmod(0o444)
    out.chmod(0o555)
    r = invoke("run", theta, "--out", out, "--force")
    assert r.exit_code == 0, r.output
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_unwritable_output_is_one_message(tmp_path, theta, monkeypatch):
    """A read-only output folder (simulated: the tests may run as root, who writes anywhere)."""
    ro = tmp_path / "ro"
    ro.mkdir()
    real_open = os.open

    def deny(path, *a, **k):
        if str(path).startswith(str(ro)):
            raise PermissionError(13, "Permission denied", str(path))
        return real_open(path, *a, **k)

    monkeypatch.setattr(io.os, "open", deny)
    r = invoke("run", theta, "--out", ro / "res")
    assert r.exit_code == 1, r.output
    assert "cannot write in" in r.output and "Permission denied" in r.output and "Traceback" not in r.output
    assert not list(ro.iterdir())


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_parent_is_one_message(tmp_path, theta):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        r = invoke("run", theta, "--out", ro / "res")
        assert r.exit_code == 1 and "Permission denied" in r.output and "Traceback" not in r.output
    finally:
        ro.chmod(0o755)


# ---- locks: concurrent runs --------------------------------------------------------------------

def default_sigint() -> None:
    """preexec_fn: the child starts with SIGINT at its default, as from a terminal. A process that starts with SIGINT
    ignored keeps ignoring it (Python installs its KeyboardInterrupt handler only over SIG_DFL; a non-interactive
    shell's background job is started so, on purpose), and a test process can inherit SIG_IGN from whatever started
    it: a fresh-clone CI run once got rc 0 here (the run ignored Ctrl-C and finished)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start_long_run(cfg: Path, out: Path, extra=()) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "netkf_cli.app.cli", "run", str(cfg), "--out", str(out),
                             "--jobs", "1", "-q", *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True, preexec_fn=default_sigint)


def _wait_for(pred, seconds: float, proc: subprocess.Popen | None = None) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if pred():
            return True
        if proc is not None and proc.poll() is not None:
            return pred()
        time.sleep(0.05)
    return False


def test_concurrent_run_is_refused_and_first_stays_intact(tmp_path):
    cfg = tmp_path / "mc.yaml"
    cfg.write_text(mc_config(runs=600_000, chunk=10_000))
    out = tmp_path / "res" / "mc"
    first = _start_long_run(cfg, out)
    try:
        lock = out.parent / ".mc.lock"
        cache_root = out.parent / ".netkf-cache"
        assert _wait_for(lambda: lock.exists() and lock.read_text().startswith("pid"), 60, first), first.stderr.read()
        # the first run has stored some chunks (so a deleted cache would show)
        _wait_for(lambda: any(cache_root.rglob("*.chunk")), 30, first)
        chunks_before = set(cache_root.rglob("*.chunk"))
        r = invoke("run", cfg, "--out", out)  # same folder
        assert r.exit_code == 1 and "in use by another netkf run" in r.output and f"pid {first.pid}" in r.output
        # the same scenario into another folder at the same time: its own resume cache, it works
        r = invoke("run", cfg, "--out", out.parent / "mc2", "--runs", 20_000, "-j", 1)
        assert r.exit_code == 0, r.output
        now = set(cache_root.rglob("*.chunk"))
        # looked at after the listing: a run removes its cache only after its result folder (with the manifest) is
        # complete, so no manifest now means the first had not finished when the listing was taken (the process
        # may still be alive after removing its cache: its exit status is no witness)
        if not (out / "manifest.json").exists():
            assert chunks_before <= now  # nothing of the first's cache deleted
        assert first.wait(300) == 0, first.stderr.read()
    finally:
        if first.poll() is None:
            first.kill()
    man = json.loads((out / "manifest.json").read_text())
    assert man["written_by"] == "netkf" and man["montecarlo"]["runs"] == 600_000
    assert sorted(p.name for p in out.parent.iterdir()) == ["mc", "mc2"]  # locks and caches gone


# ---- interrupts ----------------------------------------------------------------------------------

@pytest.mark.keeps_resume_cache
@pytest.mark.parametrize("how", ["ctrl-c", "sigterm"])
def test_interrupt_is_one_line_with_resume_hint(tmp_path, how):
    cfg = tmp_path / "mc.yaml"
    cfg.write_text(mc_config(runs=50_000_000, chunk=20_000))
    out = tmp_path / "res" / "mc"
    proc = _start_long_run(cfg, out, extra=("--jobs", "2"))
    try:
        cache_root = out.parent / ".netkf-cache"
        assert _wait_for(lambda: any(cache_root.rglob("*.chunk")), 90, proc), proc.stderr.read()
        if how == "ctrl-c":
            os.killpg(proc.pid, signal.SIGINT)  # what a terminal does: the whole process group
        else:
            proc.send_signal(signal.SIGTERM)  # `kill PID`: the main process only
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("large run")]
    assert len(lines) == 1, err
    assert "interrupted:" in lines[0] and "--resume" in lines[0] and "Monte Carlo runs finished" in lines[0]
    assert not out.exists() and any(cache_root.rglob("*.chunk"))  # the chunks are kept for --resume
    assert not [p for p in out.parent.iterdir() if p.name.endswith(".lock")]


# ---- the error layer -----------------------------------------------------------------------------

def test_internal_error_is_one_line_and_debug_shows_it(tmp_path, theta, monkeypatch):
    import netkf_cli.app.runner as runner_mod

    def boom(*a, **k):
        raise TypeError("simulated bug")

    monkeypatch.setattr(runner_mod, "compute", boom)
    r = invoke("run", theta, "--out", tmp_path / "o")
    assert r.exit_code == 1 and "internal error (TypeError: simulated bug)" in r.output
    assert "Traceback" not in r.output and not (tmp_path / "o").exists()
    r = invoke("--debug", "run", theta, "--out", tmp_path / "o")
    assert isinstance(r.exception, TypeError)


def test_debug_reraises_user_errors(tmp_path):
    from netkf_cli.core.errors import ConfigError

    bad = tmp_path / "b.yaml"
    bad.write_text("name: [")
    r = invoke("--debug", "validate", bad)
    assert isinstance(r.exception, ConfigError)


def test_large_run_announces_eta_before_starting(tmp_path, monkeypatch):
    import netkf_cli.app.runner as runner_mod

    cfg = tmp_path / "big.yaml"
    cfg.write_text(mc_config(runs=10**12))

    def stop(*a, **k):
        raise KeyboardInterrupt  # we only want what is printed before the run starts

    monkeypatch.setattr(runner_mod, "run_scenario", stop)
    t0 = time.perf_counter()
    r = invoke("run", cfg, "--out", tmp_path / "o", "--jobs", 2)
    assert time.perf_counter() - t0 < 20
    assert "large run:" in r.output and "ETA" in r.output and "58 days" in r.output, r.output
    assert r.exit_code == 130


# ---- progress and timings --------------------------------------------------------------------------

@pytest.mark.parametrize("config", ["fig5.yaml", "smoothing/retransmission.yaml", "fading/thm4.yaml"])
def test_progress_total_is_counted_once(tmp_path, config):
    from netkf_cli.config.loader import load_scenario
    from netkf_cli.app.runner import ProgressTotals, run_scenario

    sc = load_scenario(ROOT / "configs" / config)
    done = [0]
    totals = ProgressTotals()
    run_scenario(sc, source=ROOT / "configs" / config, out_dir=tmp_path / "o", runs=300,
                 progress=lambda n: done.__setitem__(0, done[0] + n),
                 set_total=totals.set_total, add_total=totals.add_total)
    assert totals.total is not None and done[0] == totals.total, (done[0], totals.declared, totals.planned)


def test_wrote_in_is_the_whole_command(tmp_path, theta, monkeypatch):
    import netkf_cli.config.loader as loader_mod

    real = loader_mod.load_scenario

    def slow_load(*a, **k):
        time.sleep(0.6)  # stands for start-up work before the run's own timer starts
        return real(*a, **k)

    monkeypatch.setattr(loader_mod, "load_scenario", slow_load)
    r = invoke("run", theta, "--out", tmp_path / "o")
    assert r.exit_code == 0, r.output
    shown = float(re.search(r" in ([0-9.]+) s", r.output)[1])
    compute = float(re.search(r"\(compute ([0-9.]+) s\)", r.output)[1])
    man = json.loads((tmp_path / "o" / "manifest.json").read_text())
    # every time printed is the manifest's: the whole command up to the write, and the compute time
    assert shown >= 0.6 and abs(shown - man["command_time_s"]) <= 0.0051 and abs(compute - man["wall_time_s"]) <= 0.0051
    assert man["command_time_s"] >= man["wall_time_s"]


def test_result_from_an_older_schema_is_the_same_scenario(tmp_path, theta):
    """A committed result written before a field was added (another hash, the field absent from
    its manifest) is still recognised as the same scenario; a changed value is not."""
    out = tmp_path / "res"
    assert invoke("run", theta, "--out", out).exit_code == 0
    man = json.loads((out / "manifest.json").read_text())
    man["scenario_hash"] = "0" * 16
    del man["scenario"]["output"]  # as if `output:` did not exist yet
    (out / "manifest.json").write_text(json.dumps(man))
    assert invoke("run", theta, "--out", out).exit_code == 0
    man = json.loads((out / "manifest.json").read_text())
    man["scenario_hash"] = "0" * 16
    man["scenario"]["channel"]["buffer"] = 11
    (out / "manifest.json").write_text(json.dumps(man))
    r = invoke("run", theta, "--out", out)
    assert r.exit_code == 1 and "--force" in r.output
