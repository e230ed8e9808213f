"""i.i.d. packet loss: each packet arrives with probability γ (``arrival``).

As a delay channel this is f(0) = γ, f(∞) = 1 − γ (Shi 2009, Sec. 2.2): every buffer
length gives the same result, and :meth:`BernoulliChannel.cdf` lets the delay-buffer
closed forms treat it as one.
"""

from __future__ import annotations

from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from netkf_cli.core.spec import ChannelModel, PositiveInt, Probability
from netkf_cli.core.trace import Trace


UNIFORM_BLOCK = 1 << 18
"""Uniforms drawn at once by :meth:`BernoulliChannel.sample_trace` (2 MB of float64)."""


def sample_arrivals(rng: np.random.Generator, runs: int, horizon: int, arrival: float) -> np.ndarray:
    """Arrival indicators γ, shape ``(runs, horizon)``, bool, i.i.d. Bernoulli(arrival)."""
    return rng.random((runs, horizon)) < arrival


class BernoulliChannel(ChannelModel):
    """``kind: bernoulli`` — every packet arrives independently with probability ``arrival``.

    Trace (:meth:`sample_trace`): ``arrival`` γ_t, shape (1, horizon, runs), from
    ``rng.random((horizon, runs)) < γ`` — one uniform per packet, time-major, the same uniforms
    the delay-buffer Monte Carlo kernel draws (f(0) = γ, f(∞) = 1 − γ).
    """

    trace_kinds: ClassVar[frozenset[str]] = frozenset({"arrival"})

    kind: Literal["bernoulli"] = Field(description="i.i.d. packet loss: each packet arrives with probability γ")
    arrival: Probability = Field(description="arrival probability γ (1 − loss rate)")
    buffer: PositiveInt = Field(1, description="buffer length D (irrelevant for pure loss)")
    convention: Literal["delay_le_D", "delay_lt_D"] = Field(
        "delay_le_D", description="buffer convention (irrelevant for pure loss: f(i) = 0 for i ≥ 1)")

    def loss_rate(self) -> float:
        """Stationary loss probability 1 − γ."""
        return float(1.0 - self.arrival)

    def delay_pmf(self, n: int) -> np.ndarray:
        """f(0) = γ, f(i) = 0 for 1 ≤ i < n (the rest, 1 − γ, is loss)."""
        out = np.zeros(int(n))
        if n > 0:
            out[0] = self.arrival
        return out

    def uniforms(self, rng: np.random.Generator, runs: int, horizon: int) -> np.ndarray:
        """The one uniform per step and run the trace is a function of: ``rng.random((horizon, runs))``."""
        return rng.random((horizon, runs))

    def arrival_law(self) -> tuple[str, tuple[float, ...]]:
        """("bernoulli", (γ,)): γ_t = u_t < γ (:meth:`arrivals_from_uniforms`; a compiled kernel that forms
        the arrivals from :meth:`uniforms` itself, :mod:`netkf_cli.linalg.kf_fused`, makes the same comparison)."""
        return "bernoulli", (float(self.arrival),)

    def arrivals_from_uniforms(self, u: np.ndarray) -> np.ndarray:
        """γ (horizon, runs) bool from the uniforms ``u`` (horizon, runs)."""
        return u < self.arrival

    def sample_trace(self, rng: np.random.Generator, runs: int, horizon: int) -> Trace:
        """``Trace.arrival`` (1, horizon, runs) i.i.d. Bernoulli(γ) (see the class docstring).

        The uniforms are drawn a block of steps at a time (consecutive ``rng.random`` calls continue one
        stream: the same numbers as ``rng.random((horizon, runs))``), so a chunk holds the bool trace and one
        block of float64 uniforms, not 8 bytes per run-step (22 MB for 5000 runs × 560 steps)."""
        arr = np.empty((horizon, runs), dtype=bool)
        step = max(1, UNIFORM_BLOCK // max(runs, 1))
        for t0 in range(0, horizon, step):
            t1 = min(horizon, t0 + step)
            np.less(rng.random((t1 - t0, runs)), self.arrival, out=arr[t0:t1])
        return Trace(runs=runs, horizon=horizon, arrival=arr[None],
                     meta={"channel": "bernoulli", "arrival": float(self.arrival)})

    def cdf(self, i):
        i = np.asarray(i)
        return np.where(i >= 0, self.arrival, 0.0)

    @property
    def D(self) -> int:
        return self.buffer

    def sample(self, rng: np.random.Generator, runs: int, horizon: int) -> np.ndarray:
        return sample_arrivals(rng, runs, horizon, self.arrival)
