"""Kalman filter with intermittent observations (Sinopoli et al. 2004, eqs. 8–9), batched over runs.

    P_{k|k−1} = A P_{k−1|k−1} Aᵀ + Q,
    P_{k|k}   = P_{k|k−1} − γ_k P_{k|k−1} Cᵀ (C P_{k|k−1} Cᵀ + R)⁻¹ C P_{k|k−1},

with γ_k ∈ {0, 1} the arrival of y_k. The recursion is the Kalman core's :class:`netkf_cli.linalg.kalman.Filter`:
a channel with one arrival stream carries all of y_k in one packet; a channel with S streams carries
the S sensors of ``system.sensors`` (default: one sensor per output row), each with its own γ.
P0 = P_{0|0} (``system.P0``; unset = P̄). Quantities: ``filtered`` P_{k|k}, ``predicted`` P_{k+1|k}.
"""

from __future__ import annotations

from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from netkf_cli.linalg import kalman, kf_fused
from netkf_cli.core.errors import ConfigError
from netkf_cli.linalg.riccati import initial_covariance
from netkf_cli.core.spec import EstimatorModel


def channel_streams(channel) -> int | None:
    """Number of arrival streams the channel produces (a 1-run, 1-step sample: generic and cheap)."""
    if channel is None:
        return None
    n = getattr(channel, "streams", None)
    if callable(n):
        return int(n())
    try:
        return channel.sample_trace(np.random.default_rng(0), 1, 1).sensors
    except Exception:  # noqa: BLE001 - the channel reports its own problems when it runs
        return None


class KalmanFilterEstimator(EstimatorModel):
    """``kind: kf`` — the Kalman filter with intermittent observations (Sinopoli et al. 2004)."""

    kind: Literal["kf"]
    backend: Literal["auto", "numpy", "numba"] = Field(
        "auto", description="numpy (the core, reference) | numba (a kernel generated for the system from the core's "
                            "equations, equal to rounding, ~10× faster) | auto = numba for chunks of ≥ 1e6 run-steps "
                            "when numba is importable")

    accepts: ClassVar[frozenset[str]] = frozenset({"arrival"})
    quantities: ClassVar[tuple[str, ...]] = ("filtered", "predicted")

    def check(self, system, channel) -> None:
        S = channel_streams(channel)
        if S is not None:
            kalman.stream_rows(system, S, "estimator.kind")

    def covariances(self, system, trace, steps, quantities=("filtered",)):
        """Yield (k, {quantity: P}) for k in ``steps`` (1 ≤ k ≤ horizon); P shaped (n, n, runs)."""
        qs = kalman.check_quantities(quantities, self.quantities, "kf")
        f = kalman.Filter.of(system, trace.arrival.shape[0], "estimator.kind")
        backend = kalman.choose_backend(self.backend, f, trace.runs * trace.horizon)
        yield from f.run(initial_covariance(system), trace.arrival, steps, qs, backend=backend)

    def covariance_blocks(self, system, trace, steps, quantities=("filtered",)):
        """:meth:`covariances` by blocks of consecutive steps (at most :data:`BLOCK_BYTES` of P_{k|k}): yield
        ``(ks, {quantity: P (len(ks), n, n, runs)})`` — the filter's P_{k|k} of the steps stacked, ``predicted``
        A P Aᵀ + Q of the whole block in one call of the core's ``predict``, which is elementwise in the run axis
        for n ≤ :data:`BLOCK_MAX_N` (so the numbers of :meth:`covariances`, a test; larger n: step by step). The
        engine reduces each block in one call."""
        qs = kalman.check_quantities(quantities, self.quantities, "kf")
        f = kalman.Filter.of(system, trace.arrival.shape[0], "estimator.kind")
        backend = kalman.choose_backend(self.backend, f, trace.runs * trace.horizon)
        n, runs = f.A.shape[0], trace.runs
        size = max(1, BLOCK_BYTES // (n * n * runs * 8))
        ks, Ps = [], []
        for k, out in f.run(initial_covariance(system), trace.arrival, steps, ("filtered",), backend=backend):
            ks.append(k)
            Ps.append(out["filtered"])
            if len(ks) == size:
                yield ks, _block(f, np.stack(Ps), qs)
                ks, Ps = [], []
        if ks:
            yield ks, _block(f, np.stack(Ps), qs)

    def backend_used(self, system, channel, runs: int, horizon: int, steps=None, quantities=None) -> str:
        """The backend a chunk of ``runs`` × ``horizon`` runs on (recorded in the manifest)."""
        S = channel_streams(channel) or 1
        return kalman.choose_backend(self.backend, kalman.Filter.of(system, S), runs * horizon)

    def fused(self, system, channel, run_steps: int) -> "kf_fused.FusedFilter | None":
        """The fused kernel (:mod:`netkf_cli.linalg.kf_fused`: the channel's uniforms → arrivals → generated filter
        step, reduced by the engine in the same pass) where it applies: the channel has an ``arrival_law``
        (bernoulli, gilbert_elliott), the backend is numba (``auto``: :func:`kalman.choose_backend`) and the
        system has a generated kernel with one arrival stream; else None (the trace → covariances path)."""
        law = getattr(channel, "arrival_law", None)
        if law is None:
            return None
        f = kalman.Filter.of(system, 1, "estimator.kind")
        if kalman.choose_backend(self.backend, f, run_steps) != "numba" or not kf_fused.supported(f):
            return None
        name, params = law()
        return kf_fused.FusedFilter(f, name, params, initial_covariance(system))

    def estimates(self, system, trace, y, steps, quantities=("filtered",)):
        """Yield (k, {quantity: (x̂ (n, runs), P (n, n, runs))}): the state estimate beside the covariance of
        :meth:`covariances` (the same recursion: :func:`filter_estimates`; numpy path). ``y`` (m, horizon+1,
        runs) is what the receiver sees at each step (:mod:`netkf_cli.engine.state`), x̂_{0|0} = 0."""
        qs = kalman.check_quantities(quantities, self.quantities, "kf")
        f = kalman.Filter.of(system, trace.arrival.shape[0], "estimator.kind")
        yield from filter_estimates(f, initial_covariance(system), trace.arrival, y, steps, qs)


BLOCK_BYTES = 2**20
"""P_{k|k} held per block of steps by :meth:`KalmanFilterEstimator.covariance_blocks` (26 steps of 5000 scalar runs):
small enough that a block's temporaries stay in cache (4 MB blocks: Table I's predictor column 1.5 s CPU, 1 MB: 1.0 s)."""
BLOCK_MAX_N = 8
"""Largest n whose ``predict`` of a block is one call: ``batched.left`` is a sum over A's row with the run axis
innermost (elementwise in it) up to n = 8, a BLAS product above (whose rounding may depend on the batch)."""


def _block(f: "kalman.Filter", H: np.ndarray, qs) -> dict:
    """{quantity: P (K, n, n, runs)} of a block H of P_{k|k} (K, n, n, runs): ``predicted`` in one ``report``
    over the K·runs columns (n ≤ BLOCK_MAX_N), else step by step."""
    K, n, _, runs = H.shape
    out = {}
    for q in qs:
        if q == "filtered":
            out[q] = H
        elif n <= BLOCK_MAX_N:
            flat = np.ascontiguousarray(H.transpose(1, 2, 0, 3)).reshape(n, n, K * runs)
            out[q] = kalman.report(flat, (q,), f.A, f.Q)[q].reshape(n, n, K, runs).transpose(2, 0, 1, 3)
        else:
            out[q] = np.stack([kalman.report(P, (q,), f.A, f.Q)[q] for P in H])
    return out


def filter_estimates(f: "kalman.Filter", P0, gamma, y, steps, quantities=("filtered",), x0=None):
    """x̂ and P of the Kalman filter with intermittent observations ``f`` (the steps of ``Filter.step``:
    the covariance is ``f.correct`` itself; the gain of each arrived sensor group is ``kalman.gain`` of
    the covariance that group's update starts from). ``gamma`` (S, horizon, runs); step k uses
    gamma[:, k − 1] and y[:, k]. Yields (k, {quantity: (x̂, P)}); ``predicted`` is (A x̂_{k|k}, A P Aᵀ + Q)."""
    want = sorted({int(k) for k in steps})
    runs = gamma.shape[-1]
    n = f.A.shape[0]
    P = np.repeat(np.asarray(P0, float)[:, :, None], runs, axis=2)
    x = np.zeros((n, runs)) if x0 is None else np.array(x0, float)
    t = 0
    for k in want:
        while t < k:
            g, yt = gamma[:, t], y[:, t + 1]
            with np.errstate(over="ignore", invalid="ignore"):
                Pm = kalman.predict(P, f.A, f.Q)
                x = f.A @ x
                if len(f.groups) == 1 or f.sequential:
                    Pg = Pm
                    for s, rows in enumerate(f.groups):
                        r = list(rows)
                        K = kalman.gain(Pg, f.C[r], f.R[np.ix_(r, r)])
                        innov = (yt[r] - f.C[r] @ x) * g[s].astype(float)[None, :]
                        x = x + np.einsum("nmr,mr->nr", K, innov)
                        if s < len(f.groups) - 1:
                            Pg = kalman.update(Pg, f.C[r], f.R[np.ix_(r, r)], g[s])
                else:  # correlated sensors: one joint update of the arrived rows, per arrival pattern
                    mask = kalman.row_mask(g, f.groups, f.C.shape[0])
                    pats, inv = np.unique(mask, axis=1, return_inverse=True)
                    for j in range(pats.shape[1]):
                        r, idx = np.flatnonzero(pats[:, j]), np.flatnonzero(inv.ravel() == j)
                        if r.size:
                            K = kalman.gain(Pm[:, :, idx], f.C[r], f.R[np.ix_(r, r)])
                            x[:, idx] += np.einsum("nmr,mr->nr", K, yt[np.ix_(r, idx)] - f.C[r] @ x[:, idx])
                P = f.correct(Pm, g)
            t += 1
        out = {}
        for q, Pq in kalman.report(P, quantities, f.A, f.Q).items():
            out[q] = (x if q == "filtered" else f.A @ x, Pq)
        yield k, out

