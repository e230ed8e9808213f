"""Sensor with computation capability (Shi, Xie & Murray 2009, Sec. 4, Fig. 4, Thm 4.1).

The sensor runs its own Kalman filter on every measurement and sends its estimate x̂^s_t; packets
are delayed and buffered as in Sec. 2.3. The remote estimator uses the most recent estimate it has
received and kept, and predicts it forward:

    N_k = min{t ≥ 0 : γ^{(k)}_{k−t} = 1}   (eq. 7; N_k = k when no packet is kept by k),
    x̂_{k|k} = A^{N_k} x̂^s_{k−N_k},

so, exactly (on the one time base, from P_{0|0} = :func:`netkf_cli.linalg.riccati.initial_covariance`),

    filtered   P_{k|k}   = h^{N_k}(P^s_{k−N_k}),     P^s_0 = P_{0|0},  P^s_t = g̃(h(P^s_{t−1}))  (the sensor's KF),
    predicted  P_{k+1|k} = h(P_{k|k}) = h^{N_k+1}(P^s_{k−N_k}),

with h(X) = AXAᵀ + Q and g̃ the measurement update (the core's ``predict``/``update``). When no
packet is kept the receiver's estimate is A^k x̂_0: P_{k|k} = h^k(P_{0|0}) (the same formula with
N_k = k, P^s_0 = P_{0|0}). With the default P_{0|0} = P̄ the sensor's filter is in steady state,
P^s_t = P̄ (to rounding), and P_{k|k} = h^{N_k}(P̄): Thm 4.1, Pr[P_k ≤ M] = 1 − θ(k₂(M), D) (eq. 11).
An overflowed covariance is ∞ in every entry (P ≰ M for every M).
"""

from __future__ import annotations

import weakref
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from netkf_cli.linalg import kalman
from netkf_cli.channels.delay import kept_by, trace_delays, trace_max_kept_delay
from netkf_cli.estimators.buffered import delay_conventions, single_link
from netkf_cli.estimators.kf import filter_estimates
from netkf_cli.linalg.riccati import initial_covariance
from netkf_cli.core.spec import EstimatorModel
from netkf_cli.core.system import LinearSystem


class SmartSensorEstimator(EstimatorModel):
    """``kind: smart_sensor`` — the sensor sends its own Kalman estimate x̂_k^s (Sec. 4)."""

    accepts: ClassVar[frozenset[str]] = frozenset({"delay", "arrival"})
    quantities: ClassVar[tuple[str, ...]] = ("filtered", "predicted")

    kind: Literal["smart_sensor"] = Field(description="the sensor sends its own Kalman estimate (Shi 2009, Sec. 4)")

    def check(self, system: LinearSystem, channel) -> None:
        """One packet stream (a packet carries the sensor's whole estimate) and a computable P_{0|0}
        (P̄ by default: (A, C) detectable, (A, √Q) stabilizable)."""
        single_link(system, channel, "smart_sensor")
        initial_covariance(system)

    def conventions(self, system: LinearSystem, channel) -> dict[str, str]:
        return delay_conventions(channel, packet="x̂^s_k (the sensor's KF estimate)")

    def covariances(self, system: LinearSystem, trace, steps, quantities=("filtered",)):
        """Yield (k, {quantity: P (n, n, runs)}) with P_{k|k} = h^{N_k}(P^s_{k−N_k}) (module docstring).

        Packet s is kept by k iff d_s ≤ min(k − s, D_max) (``meta['buffer']``, ``meta['convention']``;
        no buffer in meta: every delay is kept; a pure-loss trace: arrival = delay 0).
        """
        qs = kalman.check_quantities(quantities, self.quantities, "smart_sensor")
        yield from smart_covariances(system, trace, steps, qs)

    def estimates(self, system: LinearSystem, trace, y, steps, quantities=("filtered",)):
        """Yield (k, {quantity: (x̂, P)}): x̂_{k|k} = A^{N_k} x̂^s_{k−N_k} beside the P of :meth:`covariances`
        (numpy path). x̂^s is the sensor's Kalman filter on every y_t (``kf.filter_estimates``, every γ = 1,
        x̂^s_0 = 0); ``y`` (m, horizon+1, runs) the sensor's measurements (:mod:`netkf_cli.engine.state`)."""
        qs = kalman.check_quantities(quantities, self.quantities, "smart_sensor")
        want = sorted({int(k) for k in steps})
        if not want:
            return
        f = kalman.Filter.of(system, 1, "estimator.kind")
        runs, n = trace.runs, f.A.shape[0]
        xs = np.zeros((n, want[-1] + 1, runs))
        every = np.ones((1, trace.horizon, runs), dtype=bool)
        for t, out in filter_estimates(f, initial_covariance(system), every, y, range(1, want[-1] + 1)):
            xs[:, t] = out["filtered"][0]
        for k, Ps, N in smart_covariances(system, trace, want, qs, with_age=True):
            x = np.empty((n, runs))
            for age in np.unique(N):
                idx = np.flatnonzero(N == age)
                x[:, idx] = np.linalg.matrix_power(f.A, int(age)) @ xs[:, k - int(age), idx]
            yield k, {q: (x if q == "filtered" else f.A @ x, P) for q, P in Ps.items()}


def _finite_or_inf(G: np.ndarray) -> np.ndarray:
    bad = ~np.isfinite(G).all(axis=(0, 1))
    if bad.any():
        G[:, :, bad] = np.inf
    return G


class SensorHistory:
    """G_k of :func:`smart_covariances` for one system: G_k[:, :, j] = h^j(P^s_{k−j}), j = 0 … k, carried forward
    in k (G_k = [P^s_k, h(G_{k−1})], one batched prediction per step). It depends on the system alone — not on the
    trace — so it is computed once per process and system and kept (:data:`_HISTORIES`): the G_k of the steps
    asked for, and the recursion's state to go on from (a smaller k not kept restarts it, the same arithmetic)."""

    def __init__(self, s: LinearSystem):
        self.f = kalman.Filter.of(s, 1, "estimator.kind")
        self.P0 = initial_covariance(s)[:, :, None]
        self._restart()
        self.kept: dict[int, np.ndarray] = {}

    def _restart(self) -> None:
        self.t, self.Ps = 0, self.P0.copy()  # the sensor's P^s_t (one run, every measurement received)
        self.G = self.Ps.copy()  # G_0 = [P^s_0]

    def at(self, k: int) -> np.ndarray:
        """G_k, (n, n, k + 1); read-only (shared by every chunk)."""
        if k not in self.kept:
            if k < self.t:
                self._restart()
            f, one = self.f, np.ones((1, 1), dtype=bool)
            while self.t < k:
                with np.errstate(over="ignore", invalid="ignore"):
                    _, self.Ps = f.step(self.Ps, one)
                    self.G = _finite_or_inf(np.concatenate([self.Ps, kalman.predict(self.G, f.A, f.Q)], axis=2))
                self.t += 1
            if len(self.kept) >= 1024:
                self.kept.clear()
            self.G.setflags(write=False)
            self.kept[k] = self.G
        return self.kept[k]


_HISTORIES: "weakref.WeakKeyDictionary[LinearSystem, SensorHistory]" = weakref.WeakKeyDictionary()


def sensor_history(s: LinearSystem) -> SensorHistory:
    """The kept :class:`SensorHistory` of ``s`` (a LinearSystem is immutable and hashed by identity)."""
    h = _HISTORIES.get(s)
    if h is None:
        h = _HISTORIES[s] = SensorHistory(s)
    return h


def smart_covariances(s: LinearSystem, trace, steps, quantities=("filtered",), with_age: bool = False):
    """Generator behind :meth:`SmartSensorEstimator.covariances`: P_{k|k} = G_k[:, :, N_k] per run, with G_k of the
    kept :class:`SensorHistory`."""
    T = trace.horizon
    d = trace_delays(trace)  # int32, only compared (an int64 copy was 16 MB of a 20 000 × 100 chunk)
    Dmax = trace_max_kept_delay(trace)
    hist = sensor_history(s)
    f = hist.f
    want = sorted(int(k) for k in steps)
    for k in want:
        if not 1 <= k <= T:
            raise ValueError(f"steps must lie in 1..{T}, got {k}")
    final = d <= Dmax  # a packet older than D_max is kept iff its delay is ≤ D_max (its final status)
    last = np.zeros(trace.runs, dtype=np.int64)  # newest finally kept packet among 1 … done (0: none)
    done = 0
    for k in want:
        G = hist.at(k)
        w0 = max(0, k - Dmax - 1)  # packets 1 … w0 have age > D_max at k
        while done < w0:
            last = np.where(final[done], done + 1, last)
            done += 1
        kept = kept_by(d, k, Dmax, w0)[::-1]  # (k − w0, runs), row j = packet k − j (age j ≤ D_max)
        N = np.where(kept.any(axis=0), np.argmax(kept, axis=0), np.where(last > 0, k - last, k))
        out = kalman.report(np.ascontiguousarray(G[:, :, N]), quantities, f.A, f.Q)
        yield (k, out, N) if with_age else (k, out)
