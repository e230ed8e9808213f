"""Bursty (correlated) packet loss: the two-state Markov "Gilbert–Elliott" channel.

The channel state is the arrival indicator itself (the Gilbert model, the usual special case
of Gilbert–Elliott with loss probability 0 in the good state and 1 in the bad state):

    γ_k ∈ {1 = good/received, 0 = bad/lost},  Markov with
    P(γ_{k+1} = 0 | γ_k = 1) = p_gb      (a loss burst starts)
    P(γ_{k+1} = 1 | γ_k = 0) = p_bg      (a loss burst ends)

Stationary loss rate      π_B = p_gb / (p_gb + p_bg)
Mean loss-burst length    L_B = 1 / p_bg               (bursts are geometric on {1, 2, …})

It is parameterised either by ``loss_rate`` and ``mean_burst`` (then p_bg = 1/L_B and
p_gb = π_B p_bg / (1 − π_B), which must be ≤ 1, i.e. L_B ≥ π_B / (1 − π_B)), or by the
transition probabilities ``p_gb`` and ``p_bg``. i.i.d. Bernoulli loss with arrival rate λ is
the special case p_gb = 1 − λ, p_bg = λ (mean burst 1/λ). This is the Markovian loss model of
Huang & Dey 2007 (ref. [5] of Leong, Dey & Evans 2008). The first state is drawn from the
stationary law, so the arrival process is stationary from k = 0.

:func:`arrivals_for` draws arrivals from either channel kind (``bernoulli`` or
``gilbert_elliott``); :func:`markov_chain_of` gives the 2-state chain of either kind for the
exact (enumeration) analyses in :mod:`netkf_cli.analysis.smoothing`.
"""

from __future__ import annotations

from typing import ClassVar, Literal

import numpy as np
from pydantic import Field, model_validator

from netkf_cli.channels.bernoulli import UNIFORM_BLOCK, BernoulliChannel, sample_arrivals
from netkf_cli.core.errors import ConfigError
from netkf_cli.core.spec import ChannelModel
from netkf_cli.core.trace import Trace


def sample_gilbert_elliott_tm(
    rng: np.random.Generator, runs: int, horizon: int, p_gb: float, p_bg: float
) -> np.ndarray:
    """Arrival indicators γ, shape ``(horizon, runs)`` (time-major, run axis innermost), bool, from
    the stationary Gilbert chain: one uniform per step and run, ``rng.random((horizon, runs))``.

    Vectorized over runs (loop over time only). γ_0 ~ stationary law P(γ = 1) = p_bg/(p_gb+p_bg).
    """
    if runs < 0 or horizon < 0:
        raise ValueError(f"runs and horizon must be ≥ 0, got {runs}, {horizon}")
    if horizon == 0:
        return np.empty((horizon, runs), dtype=bool)
    return gilbert_elliott_from_uniforms(rng.random((horizon, runs)), p_gb, p_bg)


def pi_good_of(p_gb: float, p_bg: float) -> float:
    """The stationary arrival probability p_bg / (p_gb + p_bg) the chain starts from (1 if it never moves)."""
    return p_bg / (p_gb + p_bg) if (p_gb + p_bg) > 0 else 1.0


def gilbert_elliott_from_uniforms(u: np.ndarray, p_gb: float, p_bg: float, prev: np.ndarray | None = None,
                                  out: np.ndarray | None = None) -> np.ndarray:
    """γ (horizon, runs) bool of the stationary Gilbert chain from the uniforms ``u`` (horizon, runs):
    γ_0 = u_0 < π_good, γ_k = (u_k ≥ p_gb if γ_{k−1} else u_k < p_bg). Given ``prev`` (runs,), the state
    before ``u``'s first step, the chain continues from it (a block of a longer trace); ``out`` is written."""
    horizon, runs = u.shape
    out = np.empty((horizon, runs), dtype=bool) if out is None else out
    if horizon == 0:
        return out
    stay = u >= p_gb  # good stays good with prob 1 − p_gb
    come = u < p_bg  # bad becomes good with prob p_bg
    if prev is None:
        np.less(u[0], pi_good_of(p_gb, p_bg), out=out[0])
    else:
        out[0] = np.where(prev, stay[0], come[0])
    differ = np.not_equal(stay, come, out=stay)
    for k in range(1, horizon):  # γ_k = come_k xor (γ_{k−1} and (stay_k xor come_k)): the same choice, two passes
        np.logical_and(out[k - 1], differ[k], out=out[k])
        np.logical_xor(out[k], come[k], out=out[k])
    return out


def sample_gilbert_elliott(
    rng: np.random.Generator, runs: int, horizon: int, p_gb: float, p_bg: float
) -> np.ndarray:
    """As :func:`sample_gilbert_elliott_tm`, shape ``(runs, horizon)`` (the historical layout)."""
    return sample_gilbert_elliott_tm(rng, runs, horizon, p_gb, p_bg).T


class GilbertElliottChannel(ChannelModel):
    """``kind: gilbert_elliott`` — two-state Markov (Gilbert) bursty loss: loss_rate + mean_burst, or p_gb + p_bg.

    Give either ``loss_rate`` + ``mean_burst`` or ``p_gb`` + ``p_bg`` (not both, not a mix).
    Trace (:meth:`sample_trace`): ``arrival`` (1, horizon, runs), the chain started stationary.
    """

    trace_kinds: ClassVar[frozenset[str]] = frozenset({"arrival"})

    kind: Literal["gilbert_elliott"]
    # YAML key ``loss_rate`` (alias): the attribute name is free for the contract method :meth:`loss_rate`
    pi_loss: float | None = Field(None, alias="loss_rate", ge=0.0, lt=1.0,
                                  description="stationary loss rate π_B = P(γ_k = 0), in [0, 1) (0: no loss, "
                                              "like bernoulli arrival: 1, so a loss sweep can start at 0)")
    mean_burst: float | None = Field(None, ge=1.0, description="mean length of a loss burst L_B = 1/p_bg (steps, ≥ 1)")
    p_gb: float | None = Field(None, ge=0.0, le=1.0, description="P(loss at k+1 | arrival at k) (0: never lose)")
    p_bg: float | None = Field(None, gt=0.0, le=1.0, description="P(arrival at k+1 | loss at k)")

    @model_validator(mode="after")
    def _check_parameterisation(self):
        by_rate = self.pi_loss is not None or self.mean_burst is not None
        by_prob = self.p_gb is not None or self.p_bg is not None
        if by_rate and by_prob:
            given = [a for a, f in (("loss_rate", "pi_loss"), ("mean_burst", "mean_burst"), ("p_gb", "p_gb"), ("p_bg", "p_bg"))
                     if getattr(self, f) is not None]
            raise ValueError(f"give either loss_rate + mean_burst or p_gb + p_bg, not a mix (got {', '.join(given)})")
        if not by_rate and not by_prob:
            raise ValueError("gilbert_elliott needs loss_rate + mean_burst, or p_gb + p_bg")
        if by_rate:
            missing = [a for a, f in (("loss_rate", "pi_loss"), ("mean_burst", "mean_burst")) if getattr(self, f) is None]
            if missing:
                raise ValueError(f"{missing[0]} is required together with " + ("mean_burst" if missing[0] == "loss_rate" else "loss_rate"))
            pi_b, lb = self.pi_loss, self.mean_burst
            need = pi_b / (1.0 - pi_b)
            if lb < need - 1e-12:
                raise ValueError(
                    f"mean_burst: with loss_rate {pi_b:g} the mean burst length must be ≥ π_B/(1−π_B) = {need:.6g} "
                    f"(else P(good→bad) = π_B/((1−π_B)·L_B) would exceed 1), got {lb:g}",
                )
        else:
            missing = [f for f in ("p_gb", "p_bg") if getattr(self, f) is None]
            if missing:
                raise ValueError(f"{missing[0]} is required together with " + ("p_bg" if missing[0] == "p_gb" else "p_gb"))
        return self

    @property
    def transition(self) -> tuple[float, float]:
        """(p_gb, p_bg): P(γ_{k+1}=0 | γ_k=1) and P(γ_{k+1}=1 | γ_k=0)."""
        if self.p_gb is not None:
            return float(self.p_gb), float(self.p_bg)
        p_bg = 1.0 / self.mean_burst
        p_gb = min(1.0, self.pi_loss * p_bg / (1.0 - self.pi_loss))
        return p_gb, p_bg

    @property
    def arrival(self) -> float:
        """Stationary arrival rate λ = P(γ_k = 1) = p_bg / (p_gb + p_bg)."""
        p_gb, p_bg = self.transition
        return p_bg / (p_gb + p_bg)

    @property
    def stationary_loss(self) -> float:
        return 1.0 - self.arrival

    @property
    def burst_mean(self) -> float:
        """Mean loss-burst length 1 / p_bg."""
        return 1.0 / self.transition[1]

    def loss_rate(self) -> float:
        """Stationary loss probability π_B = p_gb / (p_gb + p_bg) (``loss_rate`` itself when given)."""
        return float(self.pi_loss) if self.pi_loss is not None else float(self.stationary_loss)

    def uniforms(self, rng: np.random.Generator, runs: int, horizon: int) -> np.ndarray:
        """The one uniform per step and run the trace is a function of: ``rng.random((horizon, runs))``."""
        if runs < 0 or horizon < 0:
            raise ValueError(f"runs and horizon must be ≥ 0, got {runs}, {horizon}")
        return rng.random((horizon, runs)) if horizon else np.empty((0, runs))

    def arrival_law(self) -> tuple[str, tuple[float, ...]]:
        """("gilbert_elliott", (p_gb, p_bg, π_good)): the comparisons of :func:`gilbert_elliott_from_uniforms`
        (a compiled kernel that forms the arrivals from :meth:`uniforms` itself, :mod:`netkf_cli.linalg.kf_fused`,
        makes the same ones)."""
        p_gb, p_bg = self.transition
        return "gilbert_elliott", (float(p_gb), float(p_bg), float(pi_good_of(p_gb, p_bg)))

    def arrivals_from_uniforms(self, u: np.ndarray) -> np.ndarray:
        """γ (horizon, runs) bool from the uniforms ``u`` (horizon, runs)."""
        p_gb, p_bg = self.transition
        return gilbert_elliott_from_uniforms(u, p_gb, p_bg)

    def sample_trace(self, rng: np.random.Generator, runs: int, horizon: int) -> Trace:
        """``Trace.arrival`` (1, horizon, runs) from :func:`gilbert_elliott_from_uniforms` of :meth:`uniforms`
        (the draws of :func:`sample_gilbert_elliott_tm`, stationary start). The uniforms are drawn a block of
        steps at a time, the chain's state carried (consecutive ``rng.random`` calls continue one stream: the
        same trace as from ``rng.random((horizon, runs))`` at once, without 8 bytes per run-step: 18 MB for
        Leong's 4000 runs × 560 steps)."""
        if runs < 0 or horizon < 0:
            raise ValueError(f"runs and horizon must be ≥ 0, got {runs}, {horizon}")
        p_gb, p_bg = self.transition
        arr = np.empty((horizon, runs), dtype=bool)
        step = max(1, UNIFORM_BLOCK // max(runs, 1))
        for t0 in range(0, horizon, step):
            t1 = min(horizon, t0 + step)
            gilbert_elliott_from_uniforms(rng.random((t1 - t0, runs)), p_gb, p_bg,
                                          prev=arr[t0 - 1] if t0 else None, out=arr[t0:t1])
        return Trace(runs=runs, horizon=horizon, arrival=arr[None],
                     meta={"channel": "gilbert_elliott", "p_gb": p_gb, "p_bg": p_bg, "arrival": self.arrival})

    def sample(self, rng: np.random.Generator, runs: int, horizon: int) -> np.ndarray:
        """γ of shape (runs, horizon), bool (legacy layout; :meth:`sample_trace` is the contract)."""
        p_gb, p_bg = self.transition
        return sample_gilbert_elliott(rng, runs, horizon, p_gb, p_bg)


def markov_chain_of(channel) -> tuple[np.ndarray, np.ndarray]:
    """The arrival process of ``channel`` as a 2-state Markov chain on γ ∈ {0, 1}.

    Returns ``(T, pi)`` with ``T[a, b] = P(γ_{k+1} = b | γ_k = a)`` and ``pi`` stationary.
    Bernoulli(λ) is the chain with identical rows (λ's row), so one code path serves both.
    """
    if isinstance(channel, BernoulliChannel):
        lam = float(channel.arrival)
        T = np.array([[1 - lam, lam], [1 - lam, lam]])
        return T, np.array([1 - lam, lam])
    if isinstance(channel, GilbertElliottChannel):
        p_gb, p_bg = channel.transition
        T = np.array([[1 - p_bg, p_bg], [p_gb, 1 - p_gb]])
        lam = p_bg / (p_gb + p_bg)
        return T, np.array([1 - lam, lam])
    raise ConfigError.at("channel.kind", f"needs a loss channel (bernoulli or gilbert_elliott), got {getattr(channel, 'kind', type(channel).__name__)!r}")


def arrivals_for(channel, rng: np.random.Generator, runs: int, horizon: int) -> np.ndarray:
    """Arrival indicators ``(runs, horizon)`` (bool) from a ``bernoulli`` or ``gilbert_elliott`` channel."""
    if isinstance(channel, BernoulliChannel):
        return sample_arrivals(rng, runs, horizon, channel.arrival)
    if isinstance(channel, GilbertElliottChannel):
        return channel.sample(rng, runs, horizon)
    raise ConfigError.at("channel.kind", f"needs a loss channel (bernoulli or gilbert_elliott), got {getattr(channel, 'kind', type(channel).__name__)!r}")


def channel_arrival_rate(channel) -> float:
    """Stationary arrival rate λ of a ``bernoulli`` or ``gilbert_elliott`` channel."""
    if isinstance(channel, (BernoulliChannel, GilbertElliottChannel)):
        return float(channel.arrival)
    raise ConfigError.at("channel.kind", "needs a loss channel (bernoulli or gilbert_elliott)")
