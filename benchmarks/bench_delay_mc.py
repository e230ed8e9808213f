"""Speed of the delay-buffer covariance Monte Carlo (issue 3). Run on demand, never in the tests:

    python benchmarks/bench_delay_mc.py            # full (≈ 1 min)
    python benchmarks/bench_delay_mc.py --quick

For the Fig. 5 (scalar, D = 10, d = 5) and Fig. 9 (4-state vehicle, Appendix B pair packets,
D = 5, d = 3) workloads it measures, side by side in one process and on the SAME arrival
patterns, run-steps per second (one run advanced by one time step = one run-step) of

* ``netkf``: the generic engine as the ``distribution`` metric runs it (``DelayChannel.sample_trace``
  → ``BufferedEstimator.covariances`` on the Kalman core, backend numpy → Pr[P_k ≤ M] counts), one core;
* ``loop``: the obvious per-run, per-step loop (numpy matrices, ``np.linalg.inv``);
* ``filterpy``: FilterPy's ``KalmanFilter.predict/update`` per run and step (if installed);

and the end-to-end wall time of ``netkf run configs/fig5.yaml`` and ``configs/fig9.yaml`` at their
default sizes (a fresh process each: includes Python start-up and imports).
Memory is bounded by the chunk size: the kernel holds O(chunk · n²) floats whatever the run count.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")  # one core

import argparse  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from netkf_cli import engine
from netkf_cli.linalg import riccati  # noqa: E402
from netkf_cli.channels.delay import DelayChannel  # noqa: E402
from netkf_cli.estimators.buffered import BufferedEstimator, availability, covariance_from_kept  # noqa: E402
from netkf_cli.core.system import LinearSystem  # noqa: E402


def workloads():
    scalar = LinearSystem.create(1.4, 1, 0.2, 0.5)
    A = np.array([[1, 0, 0.5, 0], [0, 1, 0, 0.5], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    C = np.hstack([np.eye(2), np.zeros((2, 2))])
    vehicle = LinearSystem.create(A, C, 0.01 * np.eye(4), 0.001 * np.eye(2))
    ch5 = DelayChannel(kind="delay", delay={"kind": "poisson", "mean": 5}, buffer=10)
    ch9 = DelayChannel(kind="delay", delay={"kind": "poisson", "mean": 3}, buffer=5)
    return [("Fig. 5 scalar (D=10, d=5)", scalar, ch5, 1, np.geomspace(0.5, 250, 60)),
            ("Fig. 9 4-state (D=5, d=3)", vehicle, ch9, 2, np.geomspace(0.06, 3, 50))]


def kept_flags(ch, horizon, runs, seed):
    """The kept indicators γ_s^{(k)} at k = horizon of ``runs`` runs of a sampled delay trace."""
    from netkf_cli.channels.delay import kept_by, trace_delays, trace_max_kept_delay

    tr = ch.sample_trace(np.random.default_rng(seed), runs, horizon)
    return kept_by(trace_delays(tr), horizon, trace_max_kept_delay(tr))


def loop_mkf(s, P0, avail):
    """The obvious per-run, per-step MKF (Sec. 3.1) with np.linalg.inv."""
    A, C, Q, R = s.A, s.C, s.Q, s.R
    out = []
    for r in range(avail.shape[1]):
        P = P0.copy()
        for t in range(avail.shape[0]):
            Pm = A @ P @ A.T + Q
            if avail[t, r]:
                K = Pm @ C.T @ np.linalg.inv(C @ Pm @ C.T + R)
                P = (np.eye(s.n) - K @ C) @ Pm
            else:
                P = Pm
        out.append(P)
    return np.array(out)


def filterpy_mkf(s, P0, avail):
    from filterpy.kalman import KalmanFilter

    out = []
    for r in range(avail.shape[1]):
        kf = KalmanFilter(dim_x=s.n, dim_z=s.m)
        kf.F, kf.H, kf.Q, kf.R, kf.P = s.A, s.C, s.Q, s.R, P0.copy()
        z = np.zeros(s.m)
        for t in range(avail.shape[0]):
            kf.predict()
            kf.update(z if avail[t, r] else None)
        out.append(kf.P.copy())
    return np.array(out)


def timed(f, *a):
    t = time.perf_counter()
    r = f(*a)
    return r, time.perf_counter() - t


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller sizes, skip end-to-end runs")
    args = ap.parse_args(argv)
    horizon = 100
    runs = 40_000 if args.quick else 200_000
    loop_runs = 40 if args.quick else 200
    print(f"numpy {np.__version__}, one core, horizon {horizon}; run-steps/s = runs × horizon / wall time\n")
    print(f"{'workload':28s} {'method':10s} {'runs':>8s} {'time [s]':>9s} {'run-steps/s':>12s} {'speed-up':>9s}")
    for label, s, ch, span, M in workloads():
        P0 = riccati.pbar(s)
        est = BufferedEstimator(kind="buffered", backend="numpy")

        def mc(n):
            return engine.simulate(s, ch, [est], engine.DistributionReducer(M, [horizon]), steps=[horizon], runs=n,
                                   horizon=horizon, seed=0, chunk=20_000)
        mc(20_000)  # warm-up
        _, dt = timed(mc, runs)
        ours = runs * horizon / dt
        print(f"{label:28s} {'netkf':10s} {runs:8d} {dt:9.3f} {ours:12.3e} {'1':>9s}")
        # same arrivals for the reference loops: chunk 0's first loop_runs runs
        avail = availability(kept_flags(ch, horizon, loop_runs, 0), span)
        ref, dt = timed(loop_mkf, s, P0, avail)
        rate = loop_runs * horizon / dt
        print(f"{'':28s} {'loop':10s} {loop_runs:8d} {dt:9.3f} {rate:12.3e} {ours / rate:9.0f}")
        # agreement check on those runs
        mk = np.moveaxis(covariance_from_kept(s, kept_flags(ch, horizon, loop_runs, 0), span, P0), -1, 0)
        err = np.max(np.abs(mk - ref) / np.maximum(1e-12, np.abs(ref).max(axis=(1, 2), keepdims=True)))
        try:
            fp, dt = timed(filterpy_mkf, s, P0, avail)
            rate = loop_runs * horizon / dt
            err = max(err, float(np.max(np.abs(fp - ref) / np.abs(ref).max(axis=(1, 2), keepdims=True))))
            print(f"{'':28s} {'filterpy':10s} {loop_runs:8d} {dt:9.3f} {rate:12.3e} {ours / rate:9.0f}")
        except ImportError:
            print(f"{'':28s} {'filterpy':10s} (not installed)")
        print(f"{'':28s} max relative difference between methods: {err:.1e}")
    if args.quick:
        return
    print()
    for cfg in ("fig5", "fig9"):
        with tempfile.TemporaryDirectory() as tmp:
            t = time.perf_counter()
            subprocess.run([sys.executable, "-c", "from netkf_cli.app.cli import app; app()", "run",
                            str(ROOT / "configs" / f"{cfg}.yaml"), "--out", str(Path(tmp) / cfg), "--force"],
                           check=True, cwd=ROOT, capture_output=True)
            print(f"end to end: netkf run configs/{cfg}.yaml (default size): {time.perf_counter() - t:.2f} s")


if __name__ == "__main__":
    main()
