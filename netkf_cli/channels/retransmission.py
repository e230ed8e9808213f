"""Retransmission over an i.i.d. loss link: the effective arrival pattern of Leong, Dey & Evans 2008, Sec. V.

One packet per slot over a Bernoulli(λ) link. A fresh slot t sends y_t. After a failure (of y_t or
of one of its retransmissions) the sensor asks, with probability p, for a retransmission of the same
measurement, at most N times (p = 1: the deterministic scheme of Sec. V-A, 0 < p < 1: the random
scheme of Sec. V-B, p = 0 or N = 0: no retransmission, i.e. the plain Bernoulli channel); while it
retransmits, the new measurements are discarded. The trace is the *effective* arrival pattern
γ̃_t = 1 iff y_t eventually reaches the estimator — at most N slots late, so an estimate that uses
γ̃_{≤k} is available at time k + N (the latency of a lag-N smoother, which the paper compares).

Every γ̃_t of the trace is final: the link is simulated N slots past the horizon, so the last
measurements' retransmissions are complete. Uniforms: ``rng.random((horizon + N, 2, runs))`` —
per slot, one for the link and one for the decision to ask.
"""

from __future__ import annotations

from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from netkf_cli.spec import ChannelModel, NonNegInt, Probability
from netkf_cli.trace import Trace

MAX_BUDGET = 50


def effective_arrivals(rng: np.random.Generator, runs: int, horizon: int, lam: float, N: int, p: float) -> np.ndarray:
    """γ̃ of shape ``(horizon, runs)`` (time-major, run axis innermost), bool: see the module docstring.

    Vectorized over runs, a loop over the horizon + N slots."""
    slots = horizon + N
    u = rng.random((slots, 2, runs))
    out = np.zeros((slots, runs), dtype=bool)
    count = np.zeros(runs, dtype=np.int64)    # retransmissions used so far for the pending measurement
    pending = np.zeros(runs, dtype=np.int64)  # index of the measurement being retransmitted
    retrying = np.zeros(runs, dtype=bool)
    ar = np.arange(runs)
    for t in range(slots):
        succ, ask = u[t, 0] < lam, u[t, 1] < p
        fresh = ~retrying
        out[t, fresh] = succ[fresh]                    # fresh transmission of y_t
        start = fresh & ~succ & ask & (N > 0)
        won = retrying & succ                          # a retransmission of y_pending arrives (y_t discarded)
        out[pending[won], ar[won]] = True
        cont = retrying & ~succ & ask & (count < N)
        count = np.where(start, 1, np.where(cont, count + 1, 0))
        pending = np.where(start, t, pending)
        retrying = start | cont
    return out[:horizon]


class RetransmissionChannel(ChannelModel):
    """``kind: retransmission`` — i.i.d. loss with up to N retransmissions, each asked with probability p (Leong 2008, Sec. V).

    Trace (:meth:`sample_trace`): ``arrival`` (1, horizon, runs), the effective pattern γ̃_t = 1 iff y_t
    reaches the estimator (at most ``budget`` slots late). p = 0 or budget = 0 is the bernoulli channel
    (on other uniforms).
    """

    trace_kinds: ClassVar[frozenset[str]] = frozenset({"arrival"})

    kind: Literal["retransmission"]
    arrival: Probability = Field(description="success probability λ of one transmission over the link")
    budget: NonNegInt = Field(2, le=MAX_BUDGET, description=f"N: at most N retransmissions of one measurement (≤ {MAX_BUDGET})")
    p: Probability = Field(1.0, description="probability of asking for a retransmission after a failure "
                                            "(1: deterministic, Sec. V-A; 0 < p < 1: random, Sec. V-B; 0: none)")

    def loss_rate(self) -> float:
        """Loss probability of one transmission over the link, 1 − λ (not of the effective pattern)."""
        return float(1.0 - self.arrival)

    def conventions(self) -> dict[str, str]:
        return {"retransmission": f"up to {self.budget} retries, asked with p = {self.p:g}; γ̃_t = 1 iff y_t arrives "
                                  f"(≤ {self.budget} slots late)"}

    def sample_trace(self, rng: np.random.Generator, runs: int, horizon: int) -> Trace:
        """``Trace.arrival`` (1, horizon, runs) from :func:`effective_arrivals`."""
        arr = effective_arrivals(rng, runs, horizon, float(self.arrival), int(self.budget), float(self.p))
        return Trace(runs=runs, horizon=horizon, arrival=arr[None],
                     meta={"channel": "retransmission", "arrival": float(self.arrival), "budget": int(self.budget),
                           "p": float(self.p)})
