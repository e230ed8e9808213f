"""Peak memory and wall time of ``netkf run --jobs 2`` for every paper scenario (issue 20 item 3).

    python benchmarks/bench_memory.py                      # every config in configs/, full size
    python benchmarks/bench_memory.py fig5 fusion/fig1     # configs whose path contains one of these
    python benchmarks/bench_memory.py fig9 --runs 2000000  # the same scenario at 10x its runs: flat in runs?

Memory is the peak proportional set size (PSS) of netkf and its worker processes together, sampled every
50 ms from /proc/<pid>/smaps_rollup (Linux): forked workers share the parent's pages, and PSS counts a shared
page once across the processes (the sum of RSS counts it in each; printed beside it). The target is 300 MB.
PSS is split into its anonymous part (the heap, arrays, numba's compiled code: what the processes themselves
allocate) and its file-backed part (mapped libraries, clean and shared with the page cache): the latter depends
on the kernel as much as on netkf: on 2026-12-06's machine (kernel 6.18), importing numba mapped 106 MB of the
170 MB libllvmlite.so (81 of its 84 MB of code, clean pages) and fig5.yaml peaked at 308 MB (145 anonymous) where
2026-12-04's machine measured 254 MB. Since 2026-12-07 netkf unmaps the library's clean pages whenever numba's
compiler lock is released (netkf_cli/core/llvm_pages.py): the `llvm` column is ~2 MB at a peak that falls in the
Monte Carlo or the figure, and 70-112 MB only at one that falls while numba is imported or a kernel loads.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

TARGET_MB = 300.0


def _descendants(pid: int) -> list[int]:
    """Every descendant of ``pid``, from /proc/<p>/stat's parent field (Linux; no extra dependency)."""
    parent = {}
    for p in Path("/proc").iterdir():
        if p.name.isdigit():
            try:
                parent[int(p.name)] = int((p / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                pass
    out, todo = [], [pid]
    while todo:
        cur = todo.pop()
        kids = [c for c, pp in parent.items() if pp == cur]
        out += kids
        todo += kids
    return out


def _tree_mb(pid: int) -> dict[str, float]:
    """PSS, RSS, PSS's anonymous and file-backed parts, and the PSS of numba's LLVM library (libllvmlite.so) in MB,
    over a process and its descendants (/proc/<p>/smaps_rollup and smaps, read together: a process that exits
    between the two reads is left out of both)."""
    keys = {"Pss:": "pss", "Rss:": "rss", "Pss_Anon:": "anon", "Pss_File:": "file"}
    out = dict.fromkeys([*keys.values(), "llvm"], 0.0)
    for p in [pid, *_descendants(pid)]:
        try:
            rollup = Path(f"/proc/{p}/smaps_rollup").read_text()
            maps = Path(f"/proc/{p}/smaps").read_text()
        except OSError:
            continue
        for line in rollup.splitlines():
            k = keys.get(line.split(maxsplit=1)[0]) if line else None
            if k:
                out[k] += int(line.split()[1]) / 1024
        inside = False
        for line in maps.splitlines():
            head = line.split(maxsplit=1)[0] if line else ""
            if not head.endswith(":"):  # a mapping's header: address range, perms, offset, device, inode, path
                inside = "libllvmlite" in line
            elif inside and head == "Pss:":
                out["llvm"] += int(line.split()[1]) / 1024
    return out


def measure(config: Path, out: Path, runs: int | None) -> dict:
    """``netkf run config --jobs 2`` into ``out``: rc, wall and compute time, peak PSS / RSS sum / processes."""
    cmd = [str(Path(sys.executable).with_name("netkf")), "run", str(config), "--jobs", "2", "--force", "--yes",
           "--out", str(out)] + (["--runs", str(runs)] if runs else [])
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=ROOT)
    peak = {"pss": 0.0, "rss": 0.0, "anon": 0.0, "file": 0.0, "llvm": 0.0, "procs": 1}

    def watch():
        while proc.poll() is None:
            now = _tree_mb(proc.pid)
            if now["pss"] > peak["pss"]:
                peak.update(now, procs=1 + len(_descendants(proc.pid)))
            time.sleep(0.05)

    th = threading.Thread(target=watch)
    th.start()
    stdout, stderr = proc.communicate()
    th.join()
    m = re.search(r"compute ([0-9.]+) s", stdout.decode())
    return {"rc": proc.returncode, "wall": time.perf_counter() - t0, "compute": float(m.group(1)) if m else float("nan"),
            "err": stderr.decode()[-300:], **peak}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("only", nargs="*", help="configs whose path (under configs/) contains one of these")
    ap.add_argument("--runs", type=int, default=None, help="override montecarlo.runs (default: the config's)")
    a = ap.parse_args()
    cfgs = sorted((ROOT / "configs").rglob("*.yaml"))
    if a.only:
        cfgs = [c for c in cfgs if any(s in str(c.relative_to(ROOT / "configs")) for s in a.only)]
    with open("/proc/loadavg") as f:
        load = f.read().split()[0]
    print(f"netkf run --jobs 2, {'the configs’ own runs' if a.runs is None else f'{a.runs} runs'}; load average {load} "
          f"on this machine at the start (2 cores)")
    print(f"{'config':42s} {'peak PSS':>9s} {'(anon':>7s} {'file':>7s} {'llvm)':>6s} {'(RSS sum)':>10s} {'procs':>5s} "
          f"{'wall':>7s} {'compute':>8s}")
    worst = 0.0
    with tempfile.TemporaryDirectory() as tmp:
        for c in cfgs:
            r = measure(c, Path(tmp) / c.stem, a.runs)
            name = str(c.relative_to(ROOT / "configs"))
            if r["rc"]:
                print(f"{name:42s} FAILED: {r['err']}")
                continue
            worst = max(worst, r["pss"])
            flag = "ok" if r["pss"] <= TARGET_MB else f"OVER {TARGET_MB:.0f} MB" + (
                f" (numba's LLVM library maps {r['llvm']:.0f} MB of it, see the docstring)" if r["llvm"] >= 10 else "")
            print(f"{name:42s} {r['pss']:7.0f} MB {r['anon']:7.0f} {r['file']:7.0f} {r['llvm']:6.0f} {r['rss']:7.0f} MB "
                  f"{r['procs']:5d} "
                  f"{r['wall']:6.1f}s {r['compute']:7.1f}s  {flag}", flush=True)
    with open("/proc/loadavg") as f:
        load = f.read().split()[0]
    print(f"largest peak PSS {worst:.0f} MB (target {TARGET_MB:.0f} MB); load average {load} at the end")


if __name__ == "__main__":
    main()
