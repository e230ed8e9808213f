"""Retransmission over an i.i.d. loss link: the effective arrival pattern of Leong, Dey & Evans 2008, Sec. V.

One packet per slot over a Bernoulli(λ) link. A fresh slot t sends y_t. After a failure (of y_t or
of one of its retransmissions) the sensor asks, with probability p, for a retransmission of the same
measurement, at most N times (p = 1: the deterministic scheme of Sec. V-A, 0 < p < 1: the random
scheme of Sec. V-B, p = 0 or N = 0: no retransmission, i.e. the plain Bernoulli channel); while it
retransmits, the new measurements are discarded. The trace is the *effective* arrival pattern
γ̃_t = 1 iff y_t eventually reaches the estimator — at most N slots late, so an estimate that uses
γ̃_{≤k} is available at time k + N (the latency of a lag-N smoother, which the paper compares).

Every γ̃_t of the trace is final: the link is simulated N slots past the horizon, so the last
measurements' retransmissions are complete. Uniforms: those of ``rng.random((horizon + N, 2, runs))``
(drawn a block of slots at a time) — per slot, one for the link and one for the decision to ask.
"""

from __future__ import annotations

from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from netkf_cli.core.spec import ChannelModel, NonNegInt, Probability
from netkf_cli.core.trace import Trace
from netkf_cli.linalg.kalman import numba_available

MAX_BUDGET = 50


AUTO_MIN_SLOTS = 1_000_000
"""``backend: auto`` of :func:`effective_arrivals` compiles the slot loop (numba, when installed) from this
many run-slots: the numpy loop costs ~12 passes over the runs per slot (~50–150 ms for 5 000 runs × 362
slots), the compiled one the same logic per run and slot on the same uniforms (the same trace, a test);
below it (a quick run) importing numba would cost more than it saves."""

_JIT: dict[str, object] = {}


UNIFORM_BLOCK = 1 << 18
"""effective_arrivals draws its uniforms in blocks of slots of about this many entries: the same numbers as one
``rng.random((horizon + N, 2, runs))`` (the generator's stream is sequential, slot-major), without a
(horizon + N) × 2 × runs float array (29 MB for 5 000 runs × 362 slots: the peak of a smoothing chunk)."""


def effective_arrivals(rng: np.random.Generator, runs: int, horizon: int, lam: float, N: int, p: float,
                       backend: str = "auto") -> np.ndarray:
    """γ̃ of shape ``(horizon, runs)`` (time-major, run axis innermost), bool: see the module docstring.

    ``numpy``: vectorized over runs, a loop over the horizon + N slots; ``numba``: the same loop compiled
    (:func:`_slots_loop`), on the same uniforms — the same trace; ``auto``: numba from
    :data:`AUTO_MIN_SLOTS` run-slots when it is installed. The uniforms come in blocks of slots
    (:data:`UNIFORM_BLOCK`), the loop's state carried from one block to the next."""
    slots = horizon + N
    compiled = backend == "numba" or (backend == "auto" and runs * slots >= AUTO_MIN_SLOTS and numba_available())
    loop = _compiled() if compiled else _slots_numpy
    out = np.zeros((slots, runs), dtype=np.bool_)
    count = np.zeros(runs, dtype=np.int64)    # retransmissions used so far for the pending measurement
    pending = np.zeros(runs, dtype=np.int64)  # index of the measurement being retransmitted
    retrying = np.zeros(runs, dtype=np.bool_)
    rows = max(1, min(slots, UNIFORM_BLOCK // max(2 * runs, 1)))
    for t0 in range(0, slots, rows):
        u = rng.random((min(rows, slots - t0), 2, runs))
        loop(u, t0, float(lam), int(N), float(p), out, count, pending, retrying)
    return out[:horizon]


def _slots_numpy(u, t0, lam, N, p, out, count, pending, retrying):
    """Slots t0 … t0 + len(u) − 1 of the loop, vectorized over runs; ``count``, ``pending`` and ``retrying``
    (per run) are updated in place for the next block."""
    ar = np.arange(out.shape[1])
    for i in range(u.shape[0]):
        t = t0 + i
        succ, ask = u[i, 0] < lam, u[i, 1] < p
        fresh = ~retrying
        out[t, fresh] = succ[fresh]                    # fresh transmission of y_t
        start = fresh & ~succ & ask & (N > 0)
        won = retrying & succ                          # a retransmission of y_pending arrives (y_t discarded)
        out[pending[won], ar[won]] = True
        cont = retrying & ~succ & ask & (count < N)
        count[:] = np.where(start, 1, np.where(cont, count + 1, 0))
        pending[:] = np.where(start, t, pending)
        retrying[:] = start | cont


def _slots_loop(u, t0, lam, N, p, out, count, pending, retrying):
    """:func:`_slots_numpy` per run (compiled): the numpy statements, one run at a time."""
    runs = out.shape[1]
    for i in range(u.shape[0]):
        t = t0 + i
        for r in range(runs):
            succ = u[i, 0, r] < lam
            ask = u[i, 1, r] < p
            if not retrying[r]:
                out[t, r] = succ
                start = (not succ) and ask and N > 0
                cont = False
            else:
                if succ:
                    out[pending[r], r] = True
                start = False
                cont = (not succ) and ask and count[r] < N
            count[r] = 1 if start else (count[r] + 1 if cont else 0)
            if start:
                pending[r] = t
            retrying[r] = start or cont


def _compiled():
    f = _JIT.get("loop")
    if f is None:
        import numba as nb  # optional (netkf[fast]): imported only when the compiled loop runs

        f = _JIT["loop"] = nb.njit(cache=True, nogil=True)(_slots_loop)
    return f


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
