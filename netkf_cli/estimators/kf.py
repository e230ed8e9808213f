"""Kalman filter with intermittent observations (Sinopoli et al. 2004, eqs. 8–9), batched over runs.

    P_{k|k−1} = A P_{k−1} Aᵀ + Q,
    P_k       = P_{k|k−1} − γ_k P_{k|k−1} Cᵀ (C P_{k|k−1} Cᵀ + R)⁻¹ C P_{k|k−1},

with γ_k ∈ {0, 1} the arrival of y_k. With one arrival stream (S = 1) the whole y_k is lost or
received; with S = m streams (one per output, e.g. a ``multi`` channel) row i of C is updated
with its own γ (sequential processing, exact for diagonal R). ``P0`` is the error covariance
of x̂_0 at k = 0 (``system.P0``; unspecified or ``steady`` = P̄, the steady-state filtered
covariance with every packet received). ``quantity: filtered`` reports P_k = P_{k|k},
``predicted`` reports P_{k+1|k}.
"""

from __future__ import annotations

from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from netkf_cli import batched, riccati
from netkf_cli.errors import ConfigError
from netkf_cli.spec import EstimatorModel


RATIO = 1e8
"""A run whose predicted covariance exceeds RATIO·‖(CᵀR⁻¹C)⁻¹‖ is updated in information form: the
standard form P − P Cᵀ S⁻¹ C P cancels every digit when ‖P‖/‖R‖ ≳ 1/ε (e.g. A = 1e6)."""


def _information_update(Pm: np.ndarray, info: np.ndarray) -> np.ndarray:
    """P⁺ = (P⁻⁻¹ + CᵀR⁻¹C)⁻¹ per run (Sinopoli 2004, eq. 9 in information form); P⁻ = ∞ ⇒ P⁻⁻¹ = 0."""
    X = np.moveaxis(Pm, -1, 0)
    finite = np.isfinite(X).all(axis=(1, 2))
    Y = np.zeros_like(X)
    if finite.any():
        Y[finite] = np.linalg.inv(X[finite])
    out = np.linalg.inv(Y + info[None])
    return np.moveaxis(0.5 * (out + out.transpose(0, 2, 1)), 0, -1)


def _guard(P, Pm, huge, arrived, info, full_rank: bool) -> np.ndarray:
    """Runs flagged ``huge`` before the update: the exact information-form update on arrival (C of
    full column rank), ``inf`` when non-finite otherwise — a diverged run is counted as such,
    never a silent NaN or a cancellation-made small number."""
    P = P.copy()
    idx = np.flatnonzero(huge)
    arr = arrived[idx]
    if full_rank and arr.any():
        P[:, :, idx[arr]] = _information_update(Pm[:, :, arr], info)
    rest = idx[~arr] if full_rank else idx
    bad = rest[~np.isfinite(P[:, :, rest]).all(axis=(0, 1))]
    P[:, :, bad] = np.inf
    return P


def _streams(channel) -> int | None:
    """Number of arrival streams the channel produces (a 1-run, 1-step sample: generic and cheap)."""
    if channel is None:
        return None
    try:
        return channel.sample_trace(np.random.default_rng(0), 1, 1).sensors
    except Exception:  # noqa: BLE001 - the channel reports its own problems when it runs
        return None


def initial_covariance(system) -> np.ndarray:
    """P0 of the system, or P̄ when it is unspecified/steady (the one meaning of P0 in netkf)."""
    return riccati.pbar(system) if system.P0 is None else np.asarray(system.P0, dtype=float)


class KalmanFilterEstimator(EstimatorModel):
    """``kind: kf`` — the Kalman filter with intermittent observations (Sinopoli et al. 2004)."""

    kind: Literal["kf"]
    report: Literal["filtered", "predicted"] = Field(
        "filtered", description="which covariance is reported: filtered P_{k|k} or predicted P_{k+1|k}")
    backend: Literal["auto", "numpy", "numba"] = Field(
        "auto", description="numpy (reference) | numba (compiled, equal to rounding) | auto = numpy: measured, the "
                            "compiled generic-n kernel is no faster than the run-innermost numpy path (benchmarks/)")

    def resolved_backend(self, system, streams: int = 1) -> str:
        """The backend that runs: numba needs one arrival stream, filtered reporting and n, m ≤ 8."""
        if self.backend == "numpy":
            return "numpy"
        ok = streams == 1 and self.report == "filtered" and system.n <= 8 and system.m <= 8
        if self.backend == "numba" and not ok:
            raise ConfigError.at("estimator.backend", "backend numba supports one arrival stream, report: filtered "
                                 "and n, m ≤ 8; use backend: numpy (or auto)")
        try:
            import numba  # noqa: F401
        except ImportError:
            if self.backend == "numba":
                raise ConfigError.at("estimator.backend", "backend numba needs numba installed") from None
            return "numpy"
        # auto: numpy — on this machine the compiled generic-n kernel measured no faster (scalar 3.5e7 vs
        # 8e7, 3-state 1.8e7 vs 1.7e7, vehicle 8.7e6 vs 9.0e6 run-steps/s; bench_estimators.py --only engine)
        return "numba" if (ok and self.backend == "numba") else "numpy"

    accepts: ClassVar[frozenset[str]] = frozenset({"arrival"})
    quantity: ClassVar[str] = "P_{k|k}"

    def check(self, system, channel) -> None:
        S = _streams(channel)
        if S not in (None, 1, system.m):
            raise ConfigError.at("estimator.kind", f"kf needs one arrival stream or one per output (m = {system.m}); "
                                 f"the channel has {S} streams")

    def covariances(self, system, trace, steps):
        """Yield (k, P) for k in ``steps`` (1 ≤ k ≤ horizon); P shaped (n, n, runs)."""
        steps = sorted(int(k) for k in steps)
        gam = trace.arrival
        S = gam.shape[0]
        if S not in (1, system.m):
            raise ConfigError.at("estimator.kind", f"kf: the trace has {S} arrival streams, expected 1 or m = {system.m}")
        A, C, Q, R = system.A, system.C, system.Q, system.R
        if self.resolved_backend(system, S) == "numba":
            yield from self._compiled(system, trace, steps)
            return
        P = np.repeat(initial_covariance(system)[:, :, None], trace.runs, axis=2)
        info = C.T @ np.linalg.solve(R, C)  # CᵀR⁻¹C: the information of one measurement
        P_one = np.linalg.inv(info) if np.linalg.matrix_rank(info) == system.n else None
        limit = RATIO * (np.trace(P_one) if P_one is not None else np.trace(R) * 1e8)
        want = iter(steps)
        nxt = next(want, None)
        with np.errstate(over="ignore", invalid="ignore"):
            for t in range(trace.horizon):
                if nxt is None:
                    return
                P = batched.riccati_h(P, A, Q)
                k = t + 1
                if self.report == "predicted" and k == nxt:
                    yield k, P
                    nxt = next(want, None)
                huge = ~(batched.trace(P) <= limit)  # nearly overflowed, or inf/nan
                Pm = P[:, :, huge] if huge.any() else None
                if S == 1:
                    P = batched.kf_update(P, C, R, gam[0, t])
                else:
                    for i in range(S):
                        P = batched.kf_update(P, C[i:i + 1], R[i:i + 1, i:i + 1], gam[i, t])
                if Pm is not None:
                    P = _guard(P, Pm, huge, gam[:, t].all(axis=0), info, P_one is not None)
                if self.report == "filtered" and k == nxt:
                    yield k, P
                    nxt = next(want, None)

    def _compiled(self, system, trace, steps):
        """The numba path: advance between requested steps; flagged (overflowing) runs are redone in numpy."""
        from netkf_cli.estimators.kf_numba import kernel

        advance = kernel()
        A, C, Q, R = (np.ascontiguousarray(x, dtype=float) for x in (system.A, system.C, system.Q, system.R))
        info = C.T @ np.linalg.solve(R, C)
        P_one = np.linalg.inv(info) if np.linalg.matrix_rank(info) == system.n else None
        limit = RATIO * (np.trace(P_one) if P_one is not None else np.trace(R) * 1e8)
        runs = trace.runs
        P = np.ascontiguousarray(np.repeat(initial_covariance(system)[:, :, None], runs, axis=2))
        gam = np.ascontiguousarray(trace.arrival[0])
        flag = np.zeros(runs, dtype=np.bool_)
        t = 0
        for k in steps:
            advance(P, gam, A, C, Q, R, t, k, limit, flag)
            t = k
            if flag.any():  # rare: overflowing runs go through the numpy reference from the start
                idx = np.flatnonzero(flag)
                sub = type(trace)(len(idx), trace.horizon, arrival=trace.arrival[:, :, idx])
                ref = self.model_copy(update={"backend": "numpy"})
                done = dict(ref.covariances(system, sub, [k]))
                out = P.copy()
                out[:, :, idx] = done[k]
                yield k, out
            else:
                yield k, P.copy()
