"""i.i.d. packet loss: each packet arrives with probability γ (``arrival``).

As a delay channel this is f(0) = γ, f(∞) = 1 − γ (Shi 2009, Sec. 2.2): every buffer
length gives the same result, and :meth:`BernoulliChannel.cdf` lets the delay-buffer
closed forms treat it as one.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from netkf_cli.spec import ChannelModel, PositiveInt, Probability


def sample_arrivals(rng: np.random.Generator, runs: int, horizon: int, arrival: float) -> np.ndarray:
    """Arrival indicators γ, shape ``(runs, horizon)``, bool, i.i.d. Bernoulli(arrival)."""
    return rng.random((runs, horizon)) < arrival


class BernoulliChannel(ChannelModel):
    """``kind: bernoulli`` — every packet arrives independently with probability ``arrival``."""

    kind: Literal["bernoulli"]
    arrival: Probability = Field(description="arrival probability γ (1 − loss rate)")
    buffer: PositiveInt = Field(1, description="buffer length D (irrelevant for pure loss)")
    convention: Literal["delay_le_D", "delay_lt_D"] = "delay_le_D"

    def cdf(self, i):
        i = np.asarray(i)
        return np.where(i >= 0, self.arrival, 0.0)

    @property
    def D(self) -> int:
        return self.buffer

    def sample(self, rng: np.random.Generator, runs: int, horizon: int) -> np.ndarray:
        return sample_arrivals(rng, runs, horizon, self.arrival)
