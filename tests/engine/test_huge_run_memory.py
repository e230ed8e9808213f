"""``runs: 10**12`` starts with memory independent of runs (lazy chunk plans, chunked statistics)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")

CFG = """\
name: huge
system: {A: 1.2, C: 1, Q: 1, R: 1}
channel: {kind: bernoulli, arrival: 0.8}
estimator: {kind: kf}
analysis: {kind: distribution, M: [1, 5, 50]}
montecarlo: {runs: 1000000000000, horizon: 50, chunk: 20000}
"""


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def test_a_trillion_runs_starts_in_bounded_memory(tmp_path):
    cfg = tmp_path / "huge.yaml"
    cfg.write_text(CFG, encoding="utf-8")
    proc = subprocess.Popen([sys.executable, "-m", "netkf_cli.cli", "run", str(cfg), "--out", str(tmp_path / "o")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        peak = 0.0
        t0 = time.monotonic()
        while time.monotonic() - t0 < 6.0:  # the first seconds: start-up, planning, the first chunks
            assert proc.poll() is None, proc.communicate()
            peak = max(peak, _rss_mb(proc.pid))
            time.sleep(0.2)
        assert peak < 500, f"RSS reached {peak:.0f} MB"
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            out, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
    assert "ETA" in out + err  # the size was announced before the run started
    assert not (tmp_path / "o").exists()  # nothing half-written
