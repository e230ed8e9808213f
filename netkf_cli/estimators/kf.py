"""Kalman filter with intermittent observations (Sinopoli et al. 2004, eqs. 8–9), batched over runs.

    P_{k|k−1} = A P_{k−1|k−1} Aᵀ + Q,
    P_{k|k}   = P_{k|k−1} − γ_k P_{k|k−1} Cᵀ (C P_{k|k−1} Cᵀ + R)⁻¹ C P_{k|k−1},

with γ_k ∈ {0, 1} the arrival of y_k. The recursion is the Kalman core's :class:`netkf_cli.kalman.Filter`:
a channel with one arrival stream carries all of y_k in one packet; a channel with S streams carries
the S sensors of ``system.sensors`` (default: one sensor per output row), each with its own γ.
P0 = P_{0|0} (``system.P0``; unset = P̄). Quantities: ``filtered`` P_{k|k}, ``predicted`` P_{k+1|k}.
"""

from __future__ import annotations

from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from netkf_cli import kalman
from netkf_cli.errors import ConfigError
from netkf_cli.riccati import initial_covariance
from netkf_cli.spec import EstimatorModel


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
                            "equations, equal to rounding, ~10× faster) | auto = numba for chunks of ≥ 2e6 run-steps "
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

    def backend_used(self, system, channel, runs: int, horizon: int) -> str:
        """The backend a chunk of ``runs`` × ``horizon`` runs on (recorded in the manifest)."""
        S = channel_streams(channel) or 1
        return kalman.choose_backend(self.backend, kalman.Filter.of(system, S), runs * horizon)

