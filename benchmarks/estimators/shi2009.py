"""Benchmark cases of the Shi 2009 delay-buffer estimators for ``benchmarks/bench_estimators.py``.

``CASES`` is a list of dicts::

    {"estimator": "buffered" | "smart_sensor", "system": "scalar" | "3-state" | "vehicle",
     "backend": "numpy" | "numba" | "auto", "threads": None, "path": "engine",
     "make": callable() -> (kernel, runs, horizon)}

``kernel(rng, runs)`` is the generic engine's kernel the artefacts run (``channel.sample_trace`` →
``estimator.covariances`` → Pr[P_k ≤ M] counts at k = horizon, as the ``distribution`` metric does);
one run advanced one step is one run-step, so a case runs ``runs × horizon`` run-steps per call.
(The dedicated Monte Carlo kernels and ``numba_philox`` are gone: the estimators run on the Kalman
core, the compiled backend is the core's ``kalman.Filter.run(backend="numba")``.) Compiled cases are
listed only when numba imports.

``per_run_loop(system, runs, horizon, seed)`` is the baseline the batched kernels are compared
with: the obvious per-run, per-step intermittent-KF loop (``np.linalg.solve`` on one matrix at a
time) on Bernoulli arrivals of the case's kept probability — and ``filterpy_loop`` the same with
FilterPy's ``KalmanFilter`` (ImportError when FilterPy is missing).

Systems:
* scalar — Example 3.10 (A = 1.4, C = 1, Q = 0.2, R = 0.5), Poisson d = 5, D = 10 (Fig. 5);
* 3-state — Mostofi & Murray Sec. 4.2's dense unstable A, C = [1 2 3], Bernoulli 0.95 (m = 1);
* vehicle — Sec. 5.2's 4-state vehicle, Appendix B pair packets, Poisson d = 3, D = 5 (Fig. 9).
"""

from __future__ import annotations

import numpy as np

from netkf_cli.channels.bernoulli import BernoulliChannel
from netkf_cli.channels.delay import DelayChannel
from netkf_cli.linalg.kalman import numba_available
from netkf_cli.core.system import LinearSystem

HORIZON = 100
RUNS = 20_000  # one chunk of the artefacts' default layout


def systems() -> dict:
    """name → (system, channel, packet span, M grid)."""
    scalar = LinearSystem.create(1.4, 1, 0.2, 0.5)
    A = np.array([[1, 0, 0.5, 0], [0, 1, 0, 0.5], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    vehicle = LinearSystem.create(A, np.hstack([np.eye(2), np.zeros((2, 2))]), 0.01 * np.eye(4), 0.001 * np.eye(2))
    A3 = np.array([[2, 0.3, 0.45], [0.4, 0.2, 0.5], [1.5, 0.6, 0.34]])
    three = LinearSystem.create(A3, np.array([[1.0, 2, 3]]), 0.001 * np.eye(3), 1e-8, np.eye(3))
    return {
        "scalar": (scalar, DelayChannel(kind="delay", delay={"kind": "poisson", "mean": 5}, buffer=10), 1,
                   np.geomspace(0.5, 250, 60)),
        "3-state": (three, BernoulliChannel(kind="bernoulli", arrival=0.95), 1, np.geomspace(1e-3, 1, 50)),
        "vehicle": (vehicle, DelayChannel(kind="delay", delay={"kind": "poisson", "mean": 3}, buffer=5), 2,
                    np.geomspace(0.06, 3, 50)),
    }


class _Make:
    """Picklable ``make()``: the generic engine's kernel for the case (compiles/loads numba code on first use)."""

    def __init__(self, estimator: str, system: str, backend: str, threads: int | None = None, path: str = "engine"):
        self.estimator, self.system, self.backend, self.threads, self.path = estimator, system, backend, threads, path

    def __call__(self):
        from netkf_cli.engine import DistributionReducer, PairKernel
        from netkf_cli.estimators.buffered import BufferedEstimator
        from netkf_cli.estimators.smart_sensor import SmartSensorEstimator

        s, ch, span, M = systems()[self.system]
        est = (SmartSensorEstimator(kind="smart_sensor") if self.estimator == "smart_sensor" else
               BufferedEstimator(kind="buffered", backend=self.backend, packet="pair" if span == 2 else "measurement"))
        return PairKernel(s, ch, [est], HORIZON, [HORIZON], DistributionReducer(M, [HORIZON])), RUNS, HORIZON


def _cases() -> list[dict]:
    out = []
    for name in ("scalar", "3-state", "vehicle"):
        for backend in ("numpy", "numba") if numba_available() else ("numpy",):
            out.append({"estimator": "buffered", "system": name, "backend": backend, "threads": None, "path": "engine",
                        "make": _Make("buffered", name, backend)})
    for name in ("scalar", "vehicle"):
        out.append({"estimator": "smart_sensor", "system": name, "backend": "numpy", "threads": None, "path": "engine",
                    "make": _Make("smart_sensor", name, "numpy")})
    return out


CASES = _cases()


def _arrivals(system: str, runs: int, horizon: int, seed: int) -> tuple:
    s, ch, span, _ = systems()[system]
    keep = 1.0 - ch.loss_rate()
    avail = np.random.default_rng(seed).random((horizon, runs)) < keep
    return s, (s.P0 if s.P0 is not None else np.eye(s.n)), avail


def per_run_loop(system: str, runs: int, horizon: int = HORIZON, seed: int = 0) -> np.ndarray:
    """P_k (runs, n, n) of the intermittent KF, one run and one step at a time (the baseline)."""
    s, P0, avail = _arrivals(system, runs, horizon, seed)
    A, C, Q, R = s.A, s.C, s.Q, s.R
    out = np.empty((runs, s.n, s.n))
    for r in range(runs):
        P = P0.copy()
        for t in range(horizon):
            P = A @ P @ A.T + Q
            if avail[t, r]:
                PCt = P @ C.T
                P = P - PCt @ np.linalg.solve(C @ PCt + R, PCt.T)
        out[r] = P
    return out


def filterpy_loop(system: str, runs: int, horizon: int = HORIZON, seed: int = 0) -> np.ndarray:
    """The same with FilterPy (``predict`` every step, ``update`` on arrival)."""
    from filterpy.kalman import KalmanFilter

    s, P0, avail = _arrivals(system, runs, horizon, seed)
    out = np.empty((runs, s.n, s.n))
    z = np.zeros(s.m)
    for r in range(runs):
        kf = KalmanFilter(dim_x=s.n, dim_z=s.m)
        kf.F, kf.H, kf.Q, kf.R, kf.P = s.A, s.C, s.Q, s.R, P0.copy()
        for t in range(horizon):
            kf.predict()
            kf.update(z if avail[t, r] else None)
        out[r] = kf.P
    return out

for _c in CASES:  # what bounds the generic-engine path (trace → covariances), measured with a profiler
    if _c.get("path") == "engine":
        _c["bound"] = ("the engine path materializes the delay trace (uniforms + inverse CDF, int32 per packet and "
                       "run: ~60 % of a chunk) and the time-k view in numpy before the core's filter")
