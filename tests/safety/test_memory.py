"""Issue 23.4: `runs: 1e12` stays under 500 MB whatever `--jobs` is.

Memory is measured as the proportional set size (PSS, /proc/<pid>/smaps_rollup) summed over netkf
and its worker processes: forked workers share the parent's pages, so summing resident sizes (RSS)
counts the parent's ~250 MB of libraries once per worker — memory the machine does not spend.
`--jobs 32` on a 2-core machine runs 2 workers (capped at the cores), so it holds the same bound.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from netkf_cli.runtime.montecarlo import execution, run_chunked, usable_cores
from tests.safety.test_outputs import default_sigint

pytestmark = pytest.mark.skipif(not Path("/proc/self/smaps_rollup").exists(), reason="needs Linux /proc smaps_rollup")

CFG = """\
name: huge
system: {A: 1.2, C: 1, Q: 1, R: 1}
channel: {kind: bernoulli, arrival: 0.8}
estimator: {kind: kf}
analysis: {kind: distribution, M: [1, 5, 50]}
montecarlo: {runs: 1e12, horizon: 50, chunk: 20000}
"""


def _field(pid: int, name: str, file: str) -> float:
    try:
        for line in Path(f"/proc/{pid}/{file}").read_text().splitlines():
            if line.startswith(name + ":"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def _children(pid: int) -> list[int]:
    out = []
    for p in Path("/proc").iterdir():
        if p.name.isdigit():
            try:
                if int((p / "stat").read_text().rsplit(")", 1)[1].split()[1]) == pid:
                    out.append(int(p.name))
            except (OSError, IndexError, ValueError):
                pass
    return out


@pytest.mark.keeps_resume_cache  # stopped by Ctrl-C on purpose: its finished chunks are kept for --resume
def test_a_trillion_runs_with_many_jobs_stays_under_500_mb(tmp_path):
    cfg = tmp_path / "huge.yaml"
    cfg.write_text(CFG, encoding="utf-8")
    proc = subprocess.Popen([sys.executable, "-m", "netkf_cli.app.cli", "run", str(cfg), "--out", str(tmp_path / "o"),
                             "--jobs", "32"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=default_sigint)  # stopped by SIGINT below: it must not start ignoring it
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True)
    reader.start()
    peak, procs = 0.0, 1
    try:
        t0 = time.monotonic()  # start-up (imports: slow on a busy machine) until the run announces itself
        while not any("large run" in ln for ln in lines) and time.monotonic() - t0 < 120:
            assert proc.poll() is None, (proc.returncode, lines)
            peak = max(peak, sum(_field(p, "Pss", "smaps_rollup") for p in [proc.pid, *_children(proc.pid)]))
            time.sleep(0.2)
        t1 = time.monotonic()
        while time.monotonic() - t1 < 8.0:  # planning, the pool and the first chunks
            assert proc.poll() is None, (proc.returncode, lines)
            pids = [proc.pid, *_children(proc.pid)]
            procs = max(procs, len(pids))
            peak = max(peak, sum(_field(p, "Pss", "smaps_rollup") for p in pids))
            time.sleep(0.2)
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        reader.join(timeout=10)
    err = "".join(lines)
    assert peak < 500, f"netkf and its workers reached {peak:.0f} MB (PSS)"
    assert procs <= 1 + usable_cores() + 1, procs  # the parent, one worker per core (and a resource tracker)
    assert "capped at" in err or usable_cores() >= 32
    assert "ETA" in err and not (tmp_path / "o").exists()


def _private_mb() -> float:
    """This process's private dirty pages (MB): what a forked worker does not share with its parent."""
    return _field(os.getpid(), "Private_Dirty", "smaps_rollup")


def _exp_sum(x):
    s = 0.0
    for v in x:
        s += math.exp(-v)
    return s


class _CompiledKernel:
    """A chunk kernel that compiles a numba function of its own in the worker (as netkf's kernels do),
    and reports the worker's private memory afterwards (``max_``: the largest over the chunks)."""

    def __init__(self):
        self.parent = os.getpid()  # the parent computes chunks too (Execution.workers): only workers report

    def __call__(self, rng, runs):
        numba = pytest.importorskip("numba")
        f = numba.njit(cache=False)(_exp_sum)  # a fresh compilation in this process, never cached
        return {"sum": f(rng.random(runs)), "max_private_mb": _private_mb() if os.getpid() != self.parent else 0.0}


_MEASURE = """
import sys
from netkf_cli.runtime import montecarlo
from tests.safety.test_memory import _CompiledKernel
if sys.argv[1] == "cold":
    montecarlo.warm_compiler = lambda: None  # the parent does not set numba's compiler up before forking
with montecarlo.execution("process", jobs=2):
    st = montecarlo.run_chunked(_CompiledKernel(), runs=4000, chunk=1000, seed=1)
assert 0 < st["sum"] < 4000
print(float(st["max_private_mb"]))
"""


def _worker_private_mb(mode: str) -> float:
    """A worker's private memory, measured from a fresh interpreter (the parent's heap is then the same in every
    run: forked from a long-lived pytest worker, a child copies whatever of that heap it touches, 70 MB seen)."""
    root = Path(__file__).resolve().parents[2]
    r = subprocess.run([sys.executable, "-c", _MEASURE, mode], cwd=root, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    return float(r.stdout.strip().splitlines()[-1])


def test_workers_share_the_parents_compiler_setup():
    """numba's compiler set-up (LLVM, target and typing contexts) is ~70 MB per process; done in the parent
    before the fork (montecarlo.warm_compiler), a worker that compiles its own kernel holds only that kernel
    privately (~20 MB measured) — without it each worker held its own copy (~55 MB measured)."""
    pytest.importorskip("numba")
    if usable_cores() < 2:
        pytest.skip("needs 2 cores for worker processes")
    warm, cold = _worker_private_mb("warm"), _worker_private_mb("cold")
    assert warm < 45, f"a worker holds {warm:.0f} MB privately (without the warm-up: {cold:.0f} MB)"
    assert cold - warm > 15, f"the warm-up saves only {cold - warm:.0f} MB per worker ({cold:.0f} → {warm:.0f})"
