"""Every estimator's Monte Carlo side by side (issue 15): run-steps/s, ratios, targets, scaling.

    python benchmarks/bench_estimators.py            # all cases
    python benchmarks/bench_estimators.py --quick    # fewer repetitions
    python benchmarks/bench_estimators.py --only fading smoothing

Cases come from ``benchmarks/estimators/<topic>.py`` (each exposes ``CASES``: dicts with
``estimator``, ``system``, ``backend``, ``threads``, ``make() -> (kernel, runs, horizon)``).
For every case: the first call (compile time for numba, reported separately), then the best
of ``repeat`` calls on one core, and on two cores (two chunks on the process pool). Baselines on
the same systems: the per-run numpy loop and FilterPy (``pip install -e '.[bench]'``), one run
at a time (``shi2009.per_run_loop`` / ``filterpy_loop``), and each topic's ``ANCHORS`` (plain vectorized
numpy / hand-written numba loops on the same problem, measured in the same process). Targets (this 2-core
machine): numpy ≥ 2e7 and compiled ≥ 1e8 run-steps/s for n ≤ 4, or a case's own ``target`` (fusion MF
2e7, IBF/OLPEF 1e7); a case that misses says what bounds it (its ``profile(kernel)``: measured split,
or its ``bound`` note). ``--cli``: ``netkf run --jobs 2`` of composed scenarios, wall time and peak PSS.
Writes ``benchmarks/scaling.png``: time against runs × horizon and peak memory against runs
for one numpy case per topic (memory must stay flat: chunked).
"""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from netkf_cli.runtime import montecarlo, workers  # noqa: E402
from benchmarks.bench_memory import TARGET_MB, measure  # noqa: E402

TARGET = {"numpy": 2e7, "compiled": 1e8}


def load_cases(only: list[str] | None) -> list[tuple[str, dict]]:
    import benchmarks.estimators as pkg

    out = []
    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda i: i.name):
        if only and info.name not in only:
            continue
        mod = importlib.import_module(f"benchmarks.estimators.{info.name}")
        out += [(info.name, c) for c in getattr(mod, "CASES", [])]
    return out


def anchors(only: list[str] | None):
    """(topic, name, fn) of the topics' ``ANCHORS`` (plain numpy / hand-written numba loops, one core)."""
    import benchmarks.estimators as pkg

    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda i: i.name):
        if only and info.name not in only:
            continue
        mod = importlib.import_module(f"benchmarks.estimators.{info.name}")
        for name, fn in getattr(mod, "ANCHORS", {}).items():
            yield info.name, name, fn


CLI_SCENARIOS = {
    # the floor: the plain kf on a Bernoulli link (what any netkf run costs: interpreter, libraries, workers)
    "kf bernoulli (scalar; the floor)": """\
name: bench_kf_floor
system: {{A: 1.2, C: 1, Q: 1, R: 1}}
channel: {{kind: bernoulli, arrival: 0.8}}
estimator: {{kind: kf}}
analysis: {{kind: time_average, quantity: filtered}}
montecarlo: {{runs: {runs}, horizon: 200, burn_in: 100, seed: 1}}
""",
    # issue 20's composed fusion scenario: the 4-state vehicle, N = 25 identical sensors, loss 0.5
    "fusion MF (vehicle, N=25)": """\
name: bench_fusion_mf
system: {{A: [[1, 0, 0.5, 0], [0, 1, 0, 0.5], [0, 0, 1, 0], [0, 0, 0, 1]], C: [[1, 0, 0, 0], [0, 1, 0, 0]],
         Q: [[0.01, 0, 0, 0], [0, 0.01, 0, 0], [0, 0, 0.01, 0], [0, 0, 0, 0.01]], R: [[0.001, 0], [0, 0.001]], sensors: 25}}
channel: {{kind: multi, sensors: 25, loss: 0.5{sampling}}}
estimator: {{kind: fusion, strategies: [mf]}}
analysis: {{kind: time_average, quantity: filtered}}
montecarlo: {{runs: {runs}, horizon: 200, burn_in: 100, seed: 1}}
""",
    "fusion IBF (vehicle, N=25)": """\
name: bench_fusion_ibf
system: {{A: [[1, 0, 0.5, 0], [0, 1, 0, 0.5], [0, 0, 1, 0], [0, 0, 0, 1]], C: [[1, 0, 0, 0], [0, 1, 0, 0]],
         Q: [[0.01, 0, 0, 0], [0, 0.01, 0, 0], [0, 0, 0.01, 0], [0, 0, 0, 0.01]], R: [[0.001, 0], [0, 0.001]], sensors: 25}}
channel: {{kind: multi, sensors: 25, loss: 0.5{sampling}}}
estimator: {{kind: fusion, strategies: [ibf]}}
analysis: {{kind: time_average, quantity: filtered}}
montecarlo: {{runs: {runs}, horizon: 200, burn_in: 100, seed: 1}}
""",
}


def cli_runs(runs: int) -> None:
    """``netkf run --jobs 2`` of the composed scenarios: wall time, run-steps/s, peak PSS (netkf + workers;
    :func:`benchmarks.bench_memory.measure`)."""
    print(f"\nnetkf run --jobs 2 of composed scenarios, {runs} runs × 200 steps (wall time with start-up, and the "
          f"runner's own compute time):")
    with tempfile.TemporaryDirectory() as tmp:
        for name, text in CLI_SCENARIOS.items():
            for sampling in ("", ", sampling: counts") if "MF" in name else ("",):
                cfg = Path(tmp) / "s.yaml"
                cfg.write_text(text.format(runs=runs, sampling=sampling))
                r = measure(cfg, Path(tmp) / "out", None)
                label = name + (" sampling: counts" if sampling else "")
                if r["rc"]:
                    print(f"  {label:45s} FAILED: {r['err']}")
                    continue
                dt, compute = r["wall"], r["compute"]
                print(f"  {label:45s} {dt:6.1f} s ({runs * 200 / dt:9.3e} run-steps/s), compute {compute:5.1f} s "
                      f"({runs * 200 / compute:9.3e} run-steps/s)  peak PSS {r['pss']:6.0f} MB"
                      f"  {'ok' if r['pss'] <= TARGET_MB else f'OVER {TARGET_MB:.0f} MB'}")


def timed(fn, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def one_core(kernel, runs: int, repeat: int) -> float:
    """One process, one BLAS thread (numpy was imported before netkf here: its OpenBLAS would use every core)."""
    rng = np.random.default_rng(0)
    with workers.limit_blas():
        return timed(lambda: kernel(rng, runs), repeat)


def two_cores(kernel, runs: int, repeat: int) -> float:
    with montecarlo.execution("process", jobs=2):
        montecarlo.run_chunked(kernel, 2 * runs, runs, seed=1)  # warm the pool (and per-worker compile)
        return timed(lambda: montecarlo.run_chunked(kernel, 2 * runs, runs, seed=1), repeat) / 2


def baselines(system: str, runs: int = 200, horizon: int = 100) -> dict[str, float]:
    from benchmarks.estimators import shi2009

    out = {}
    t = timed(lambda: shi2009.per_run_loop(system, runs, horizon), 1)
    out["per-run numpy loop"] = runs * horizon / t
    try:
        t = timed(lambda: shi2009.filterpy_loop(system, runs, horizon), 1)
        out["FilterPy"] = runs * horizon / t
    except ImportError:
        pass
    return out


def scaling(cases, path: Path) -> None:
    """Time vs run-steps and peak traced memory vs runs, one numpy case per topic."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seen, picks = set(), []
    for topic, c in cases:
        if topic not in seen and c["backend"] == "numpy":
            seen.add(topic)
            picks.append((topic, c))
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.2))
    for topic, c in picks:
        kernel, runs, horizon = c["make"]()
        chunk = max(1, runs // 4)
        xs, ts, mem = [], [], []
        for mult in (1, 2, 4, 8):
            n = chunk * mult
            tracemalloc.start()
            t0 = time.perf_counter()
            montecarlo.run_chunked(kernel, n, chunk, seed=0)
            ts.append(time.perf_counter() - t0)
            mem.append(tracemalloc.get_traced_memory()[1] / 2**20)
            tracemalloc.stop()
            xs.append(n * horizon)
        label = f"{topic}: {c['estimator']} ({c['system']})"
        a1.loglog(xs, ts, "o-", label=label)
        a2.semilogx([x / horizon for x in xs], mem, "o-", label=label)
    a1.set_xlabel("run-steps (runs × horizon)")
    a1.set_ylabel("wall time [s]")
    a1.set_title("time grows linearly with the work")
    a2.set_xlabel("runs (chunk fixed)")
    a2.set_ylabel("peak traced memory [MiB]")
    a2.set_title("memory is flat in the number of runs")
    a2.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.02, 1))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    print(f"wrote {path}")


def busy_cores(seconds: float = 1.0) -> float:
    """Cores kept busy by other processes over the next ``seconds`` (/proc/stat; Linux). The load average is
    a decaying mean over a minute: a job that just ended still reads as 'busy' (0.75 after a CI run)."""
    def snap():
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:]]
        return sum(v), v[3] + v[4]  # total, idle + iowait
    try:
        t0, i0 = snap()
        time.sleep(seconds)
        t1, i1 = snap()
    except OSError:
        return float("nan")
    return (os.cpu_count() or 1) * (1.0 - (i1 - i0) / max(t1 - t0, 1))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--only", nargs="*")
    ap.add_argument("--no-scaling", action="store_true")
    ap.add_argument("--cli", action="store_true", help="also time `netkf run --jobs 2` of composed scenarios "
                                                       "(fusion MF/IBF on the vehicle) and measure their peak memory")
    ap.add_argument("--cli-runs", type=int, default=200_000)
    args = ap.parse_args()
    repeat = 1 if args.quick else 3
    cases = load_cases(args.only)
    load, busy = os.getloadavg()[0], busy_cores()
    print(f"{len(cases)} cases; load average {load:.2f} on {os.cpu_count()} cores, {busy:.2f} cores busy now"
          + (" — the machine is busy, numbers are low" if busy > 0.25 else ""))
    base_cache: dict[str, dict] = {}
    hdr = f"{'topic':10s} {'estimator':22s} {'system':8s} {'backend':13s} {'first':>7s} {'1 core':>10s} {'2 cores':>10s} {'×FilterPy':>9s}  target"
    print(hdr)
    print("-" * len(hdr))
    for topic, c in cases:
        t0 = time.perf_counter()
        kernel, runs, horizon = c["make"]()
        rng = np.random.default_rng(0)
        kernel(rng, min(runs, 1000))  # first call: compile / load cache
        first = time.perf_counter() - t0
        r1 = runs * horizon / one_core(kernel, runs, repeat)
        try:
            r2 = runs * horizon / two_cores(kernel, runs, repeat)
        except Exception as exc:  # noqa: BLE001 - a benchmark reports, it does not stop
            r2 = float("nan")
            print(f"   (2 cores failed: {exc})")
        if c["system"] not in base_cache:
            try:
                base_cache[c["system"]] = baselines(c["system"])
            except Exception as exc:  # noqa: BLE001 - said on the baseline's line
                base_cache[c["system"]] = {"none": f"{type(exc).__name__}: {exc}"[:120]}
        fp = base_cache[c["system"]].get("FilterPy")  # (absent: no baseline for this system)
        kind = "numpy" if c["backend"] == "numpy" else "compiled"
        best = max(r1, r2 if np.isfinite(r2) else 0)
        target = c.get("target", TARGET[kind])
        if best >= target:
            ok = f"ok ({target:.0e})"
        else:  # what bounds it: the case's measured split if it has one, else its note
            why = c["profile"](kernel) if "profile" in c else c.get("bound", "see case notes")
            ok = f"MISSED ({target:.0e}: {why})"
        est = c["estimator"] + ("/engine" if c.get("path") == "engine" else "")
        print(f"{topic:10s} {est:22s} {c['system']:8s} {c['backend']:13s} {first:6.2f}s {r1:10.3e} {r2:10.3e} "
              f"{(best / fp if fp else float('nan')):9.0f}  {ok}")
    for name, b in base_cache.items():
        print("baseline", name, ", ".join(f"{k}: {v:.3e}" if k != "none" else f"none here ({v})" for k, v in b.items()))
    for topic, fn_name, fn in anchors(args.only):
        try:
            print(f"anchor {topic}: {fn_name}: {fn():.3e} run-steps/s (1 core)")
        except Exception as exc:  # noqa: BLE001
            print(f"anchor {topic}: {fn_name}: failed ({exc})")
    if args.cli:
        cli_runs(args.cli_runs)
    if not args.no_scaling:
        scaling(cases, ROOT / "benchmarks" / "scaling.png")


if __name__ == "__main__":
    main()
