"""The ``buffered`` estimator's backends side by side, through the generic engine. Run on demand:

    python benchmarks/bench_backends.py            # ≈ 1 min (the core compiles a kernel per system once)
    python benchmarks/bench_backends.py --quick

Workloads (P_k at k = horizon per run, Pr[P_k ≤ M] counts as the ``distribution`` metric reduces):

* scalar — Shi 2009 Fig. 5 (A = 1.4, C = 1, Q = 0.2, R = 0.5), Poisson delays d = 5, buffer D = 10;
* 4-state — Shi 2009 Sec. 5.2 vehicle, Appendix B pair packets, Poisson d = 3, D = 5.

Methods (one run advanced one step = one run-step), one process, one core unless ``--jobs 2``:

* numpy — ``backend: numpy``: ``kalman.Filter.step`` over the time-k view;
* numba — ``backend: numba``: the core's compiled filter (``kalman.Filter.run(backend="numba")``,
  a kernel generated per system from the core's equations; rescue-flagged runs on the numpy core);
* smart — ``smart_sensor`` (P_k = h^{N_k}(P^s_{k−N_k}): one table per step, no per-run filter).

Then what bounds the numba path, per chunk: the delay trace (uniforms + inverse CDF), the time-k
view (kept indicators), the filter itself, the reduction (λ_max). The load average is printed
first: other processes on the machine distort every number.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from netkf_cli.linalg import batched, kalman
from netkf_cli import engine  # noqa: E402
from netkf_cli.channels.delay import DelayChannel, kept_by, trace_delays, trace_max_kept_delay  # noqa: E402
from netkf_cli.estimators.buffered import BufferedEstimator, availability  # noqa: E402
from netkf_cli.estimators.smart_sensor import SmartSensorEstimator  # noqa: E402
from netkf_cli.runtime.montecarlo import execution  # noqa: E402
from netkf_cli.linalg.riccati import initial_covariance  # noqa: E402
from netkf_cli.core.system import LinearSystem  # noqa: E402


def workloads():
    scalar = LinearSystem.create(1.4, 1, 0.2, 0.5)
    A = np.array([[1, 0, 0.5, 0], [0, 1, 0, 0.5], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    vehicle = LinearSystem.create(A, np.hstack([np.eye(2), np.zeros((2, 2))]), 0.01 * np.eye(4), 0.001 * np.eye(2))
    return [("scalar (Fig. 5)", scalar, DelayChannel(kind="delay", delay={"kind": "poisson", "mean": 5}, buffer=10), 1,
             np.geomspace(0.5, 250, 60)),
            ("4-state (Fig. 9)", vehicle, DelayChannel(kind="delay", delay={"kind": "poisson", "mean": 3}, buffer=5), 2,
             np.geomspace(0.06, 3, 50))]


def rate(s, ch, est, M, runs, horizon, jobs):
    def go(n):
        with execution("process" if jobs > 1 else "serial", jobs=jobs):
            return engine.simulate(s, ch, [est], engine.DistributionReducer(M, [horizon]), steps=[horizon], runs=n,
                                   horizon=horizon, seed=0, chunk=20_000)
    go(20_000)  # warm-up: compile / load the kernel
    t = time.perf_counter()
    go(runs)
    return runs * horizon / (time.perf_counter() - t)


def bounds(s, ch, span, horizon, runs=20_000):
    """Seconds per chunk of each stage of the numba path."""
    out = {}
    t = time.perf_counter()
    tr = ch.sample_trace(np.random.default_rng(0), runs, horizon)
    out["trace"] = time.perf_counter() - t
    t = time.perf_counter()
    a = availability(kept_by(trace_delays(tr), horizon, trace_max_kept_delay(tr)), span)[None]
    out["time-k view"] = time.perf_counter() - t
    f = kalman.Filter.of(s, 1)
    P0 = initial_covariance(s)
    t = time.perf_counter()
    (_, P), = f.run(P0, a, [horizon], ("filtered",), backend="numba")
    out["filter"] = time.perf_counter() - t
    t = time.perf_counter()
    batched.lambda_max(P["filtered"])
    out["reduce"] = time.perf_counter() - t
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--jobs", type=int, default=1)
    args = ap.parse_args(argv)
    horizon, runs = 100, (40_000 if args.quick else 200_000)
    print(f"load average {os.getloadavg()[0]:.1f}; horizon {horizon}, {runs} runs, jobs {args.jobs}; run-steps/s\n")
    print(f"{'workload':18s} {'numpy':>10s} {'numba':>10s} {'smart':>10s}")
    for label, s, ch, span, M in workloads():
        packet = "pair" if span == 2 else "measurement"
        r = [rate(s, ch, BufferedEstimator(kind="buffered", packet=packet, backend=b), M, runs, horizon, args.jobs)
             for b in ("numpy", "numba")]
        r.append(rate(s, ch, SmartSensorEstimator(kind="smart_sensor"), M, runs, horizon, args.jobs))
        print(f"{label:18s} " + " ".join(f"{x:10.3g}" for x in r))
    print("\nbounds: seconds per chunk of 20 000 runs (numba path)")
    for label, s, ch, span, _ in workloads():
        b = bounds(s, ch, span, horizon)
        tot = sum(b.values())
        print(f"  {label:18s} " + ", ".join(f"{k} {v * 1e3:.0f} ms ({100 * v / tot:.0f} %)" for k, v in b.items()))


if __name__ == "__main__":
    main()
