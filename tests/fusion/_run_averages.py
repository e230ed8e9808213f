"""Per-run time averages of the fusion strategies through the engine's one call into an estimator
(:func:`netkf_cli.engine.covariances`): the path-wise checks need each run's value, which the engine's
reducers only hand back summed (the former ``estimators.fusion.fusion_run_averages``, now test-only)."""

from __future__ import annotations

import numpy as np

from netkf_cli.linalg import batched
from netkf_cli import engine
from netkf_cli.estimators.fusion import FusionEstimator, identical_sensors
from netkf_cli.core.trace import Trace


def run_averages(gamma: np.ndarray, A, C, Q, R, P0, burn_in: int, strategies=("mf", "ibf")) -> dict[str, np.ndarray]:
    """Per run (runs,), the average over k in (burn_in, T] of tr P_{k|k} (``<s>_f``) and, for mf / ibf,
    tr P_{k+1|k} (``<s>_p``), N identical sensors, γ in the legacy layout (runs, T, N)."""
    runs, T, N = gamma.shape
    system = identical_sensors(A, C, Q, R, N, P0)
    trace = Trace(runs=runs, horizon=T, arrival=np.ascontiguousarray(np.transpose(gamma, (2, 1, 0))))
    steps = list(range(burn_in + 1, T + 1))
    out: dict[str, np.ndarray] = {}
    for s in strategies:
        for q, tag in (("filtered", "f"), ("predicted", "p")):
            if s == "olpef" and q == "predicted":
                continue
            acc = np.zeros(runs)
            for _, P, _w in engine.covariances(FusionEstimator(kind="fusion", strategies=[s]), system, trace, steps, q):
                acc += batched.trace(P)
            out[f"{s}_{tag}"] = acc / len(steps)
    return out
