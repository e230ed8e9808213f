"""Random packet delay with a receive buffer of length D (Shi, Xie & Murray 2009, Sec. 2.2–2.3).

Each packet's delay d_k is i.i.d. with pmf f (eq. 3); missing mass is loss (f(∞)).
Delays are sampled as integers; a lost packet gets :data:`LOST`.

The buffer convention (which delays the estimator keeps) is a scenario field, because the
paper is not self-consistent: Sec. 2.3 and eq. (4) discard delays ≥ D, while Example 3.10's
printed θ values and the floors θ(k, k−1) of Sec. 3.4 follow "keep delays ≤ D"
(evidence in ``experiments/shi2009/README.md``).
"""

from __future__ import annotations

import math
import sys
from typing import Annotated, ClassVar, Literal, Union

import numpy as np
from pydantic import Field, model_validator

# the buffer rule is the paper's (closed forms use it too): defined with them, one layer down
from netkf_cli.analysis.delay_bounds import CONVENTION_HELP, DEFAULT_CONVENTION, Convention, max_kept_delay  # noqa: F401
from netkf_cli.analysis.laws import poisson_cdf
from netkf_cli.linalg.kalman import AUTO_MIN_RUN_STEPS
from netkf_cli.core.spec import ChannelModel, NonNegFloat, PositiveInt, Probability, StrictModel
from netkf_cli.core.trace import LOST, Trace  # LOST: the delay of a packet that never arrives



class PoissonDelay(StrictModel):
    """f(i) = dⁱ e^{−d} / i!  (Example 3.10)."""

    kind: Literal["poisson"] = Field("poisson", description="Poisson delays f(i) = dⁱe^{−d}/i! (Example 3.10)")
    mean: NonNegFloat = Field(description="mean delay d (time steps)")

    def cdf(self, i: np.ndarray | int) -> np.ndarray:
        return poisson_cdf(i, self.mean)

    def sample(self, rng: np.random.Generator, size) -> np.ndarray:
        return rng.poisson(self.mean, size=size).astype(np.int32)

    @property
    def loss(self) -> float:
        return 0.0


class GeometricDelay(StrictModel):
    """f(i) = p (1 − p)ⁱ, i = 0, 1, … (number of failed attempts before success)."""

    kind: Literal["geometric"] = Field("geometric", description="geometric delays f(i) = p(1 − p)ⁱ")
    p: Annotated[float, Field(gt=0.0, le=1.0, description="per-step delivery probability")]

    def cdf(self, i: np.ndarray | int) -> np.ndarray:
        i = np.asarray(i)
        return np.where(i < 0, 0.0, 1.0 - (1.0 - self.p) ** (np.maximum(i, -1) + 1))

    def sample(self, rng: np.random.Generator, size) -> np.ndarray:
        return (rng.geometric(self.p, size=size) - 1).astype(np.int32)

    @property
    def loss(self) -> float:
        return 0.0


class PmfDelay(StrictModel):
    """An explicit pmf f(0), f(1), …, f(L); the missing mass 1 − Σ f is loss (f(∞))."""

    kind: Literal["pmf"] = Field("pmf", description="explicit delay pmf f(0), f(1), …; missing mass = loss")
    probs: list[Probability] = Field(min_length=1, description="f(0), f(1), …; missing mass = loss")

    @model_validator(mode="after")
    def _sums_to_at_most_one(self):
        total = math.fsum(self.probs)
        if total > 1 + 1e-9:
            raise ValueError(f"probabilities must sum to at most 1 (the rest is loss), got {total:.6g}")
        return self

    def cdf(self, i: np.ndarray | int) -> np.ndarray:
        c = np.concatenate([[0.0], np.cumsum(self.probs)])
        i = np.asarray(i)
        return c[np.clip(i + 1, 0, len(self.probs))]

    def sample(self, rng: np.random.Generator, size) -> np.ndarray:
        p = np.asarray(self.probs, dtype=float)
        support = np.append(np.arange(len(p), dtype=np.int64), LOST)
        probs = np.append(p, max(0.0, 1.0 - p.sum()))
        probs /= probs.sum()
        return rng.choice(support, size=size, p=probs).astype(np.int32)

    @property
    def loss(self) -> float:
        return max(0.0, 1.0 - math.fsum(self.probs))


DelayDistribution = Annotated[Union[PoissonDelay, GeometricDelay, PmfDelay], Field(discriminator="kind")]


class DelayChannel(ChannelModel):
    """``kind: delay`` — i.i.d. delays from ``delay`` and a receive buffer of length ``buffer`` (D).

    Trace (:meth:`sample_trace`): ``delay`` holds every packet's delay d_t (int32, :data:`LOST` for
    a lost packet or one that would arrive after the horizon) and ``meta`` the buffer D and the
    convention, which the buffered estimator applies; ``arrival`` = [d_t = 0], i.e. the packet is
    usable *on time*, so an estimator that does not buffer (a plain intermittent KF) can run on
    the same trace and sees the delay channel as a loss channel with loss rate 1 − f(0).
    """

    trace_kinds: ClassVar[frozenset[str]] = frozenset({"delay", "arrival"})

    kind: Literal["delay"] = Field(description="i.i.d. random packet delays with a receive buffer (Shi 2009, Sec. 2.2–2.3)")
    delay: DelayDistribution = Field(description="delay pmf f (eq. 3): {kind: poisson|geometric|pmf, …}")
    buffer: PositiveInt = Field(description="buffer length D")
    convention: Convention = Field(DEFAULT_CONVENTION, description="; ".join(f"{k}: {v}" for k, v in CONVENTION_HELP.items()))

    def cdf(self, i):
        return self.delay.cdf(i)

    def loss_rate(self) -> float:
        """Stationary probability that a packet is never kept by the buffer: 1 − F(D_max) (eq. 4)."""
        return float(1.0 - float(self.cdf(np.asarray(max_kept_delay(self.D, self.convention)))))

    def delay_pmf(self, n: int) -> np.ndarray:
        """f(0), …, f(n − 1) (eq. 3); the missing mass is loss or a delay ≥ n."""
        return delay_pmf(self, n)

    def sample_trace(self, rng: np.random.Generator, runs: int, horizon: int) -> Trace:
        """A :class:`~netkf_cli.core.trace.Trace` with ``delay`` (1, horizon, runs) and ``arrival`` = [d = 0].

        One uniform per packet, time-major (``rng.random((horizon, runs))``), inverted through the
        cdf (exact for the pmf of eq. 3, see :func:`delays_from_uniforms`): the same uniforms, in the
        same order, as the covariance Monte Carlo kernel, so the kept patterns agree packet by packet.
        Delays ≥ horizon (the packet cannot arrive within the trace) and lost packets are LOST.
        """
        return delay_trace(self, rng, runs, horizon)

    @property
    def D(self) -> int:
        return self.buffer


# ---------------------------------------------------------------------------------------------
# Vectorized samplers for the delay-buffer Monte Carlo (issue 3). Added below the models; the
# models above are unchanged. Every function works for any channel with ``.cdf`` (delay or
# bernoulli: f(0) = γ, f(∞) = 1 − γ).
#
# Sampling is by inverse CDF: a packet's delay is d = min{i : u < F(i)} with u ~ U[0, 1), so
# the event "d ≤ i" is exactly "u < F(i)". This is an exact sampler of the pmf f (eq. 3),
# including loss (F(∞) < 1 ⇒ u ≥ F(i) for every i with probability 1 − F(∞)), and it lets the
# Monte Carlo kernels decide "received and kept by time k" with one comparison per packet.
# ---------------------------------------------------------------------------------------------


def cdf_table(channel, cap: int) -> np.ndarray:
    """F(0), …, F(cap) as float64 (the delay cdf of ``channel``)."""
    return np.asarray(channel.cdf(np.arange(cap + 1)), dtype=float).reshape(cap + 1)


def delays_from_uniforms(u: np.ndarray, table: np.ndarray) -> np.ndarray:
    """Capped delays min(d, cap + 1) from uniforms u, with ``table`` = F(0..cap) (inverse CDF).

    The value ``cap + 1`` means "later than cap, or lost". d ≤ i ⇔ u < F(i) for i ≤ cap.
    """
    return np.searchsorted(table, u, side="right").astype(np.int16)


def sample_capped_delays(rng: np.random.Generator, channel, size, cap: int) -> np.ndarray:
    """i.i.d. delays min(d, cap + 1) from ``channel``'s pmf (eq. 3), one per packet, int16."""
    return delays_from_uniforms(rng.random(size), cdf_table(channel, cap))


def kept_thresholds(channel, horizon: int) -> np.ndarray:
    """Per packet s = 1..k (k = horizon) at time k: Pr[γ_s^{(k)} = 1] = F(min(k − s, D_max)) = γ̂_{k−s}(D).

    Packet s is received and kept by time k iff u_s < threshold[s − 1] (eq. 4 under the
    channel's convention: D_max = D under ``delay_le_D``, D − 1 under ``delay_lt_D``).
    """
    Dmax = max_kept_delay(channel.D, channel.convention)
    age = horizon - np.arange(1, horizon + 1)
    return np.asarray(channel.cdf(np.minimum(age, Dmax)), dtype=float).reshape(horizon)


def kept_at(delays: np.ndarray, k: int, D: int, convention: Convention) -> np.ndarray:
    """γ_s^{(k)} for packets s = 1..k from their delays (axis 0 = packet s − 1, any trailing run axes).

    Packet s is received by time k iff d_s ≤ k − s, and kept iff d_s ≤ D_max (the buffer
    discards older data before receiving it, Sec. 2.3).
    """
    age = (k - np.arange(1, delays.shape[0] + 1)).reshape((-1,) + (1,) * (delays.ndim - 1))
    Dmax = max_kept_delay(D, convention)
    return (delays.astype(np.int64) <= np.minimum(age, Dmax)) & (age >= 0)


def arrivals_now(delays: np.ndarray, k: int, D: int, convention: Convention) -> np.ndarray:
    """Packets arriving *exactly* at time k and kept: d_s = k − s ≤ D_max (axis 0 = packet s − 1)."""
    age = (k - np.arange(1, delays.shape[0] + 1)).reshape((-1,) + (1,) * (delays.ndim - 1))
    Dmax = max_kept_delay(D, convention)
    return (delays.astype(np.int64) == age) & (age <= Dmax)


def delay_pmf(channel, n: int) -> np.ndarray:
    """f(0), …, f(n − 1) of any channel with a ``cdf`` (missing mass: loss or delays ≥ n)."""
    F = np.asarray(channel.cdf(np.arange(int(n))), dtype=float).reshape(int(n))
    return np.diff(np.concatenate([[0.0], F]))


_BUCKETS: dict = {}


def _buckets(table: np.ndarray, K: int) -> tuple[np.ndarray, np.ndarray]:
    """(lo, amb) of :func:`inverse_cdf`'s K buckets for ``table``: d at each bucket's left end, and whether a
    breakpoint lies inside it (its right end differs). Kept for the last few tables: a trace inverts block after
    block through the same table."""
    key = (K, table.tobytes())
    hit = _BUCKETS.get(key)
    if hit is None:
        edges = np.arange(K + 1, dtype=float) / K
        lo = np.searchsorted(table, edges[:-1], side="right").astype(np.int32)
        hi = np.searchsorted(table, np.nextafter(edges[1:], 0.0), side="right").astype(np.int32)
        if len(_BUCKETS) >= 8:
            _BUCKETS.clear()
        hit = _BUCKETS[key] = (lo, lo != hi)
    return hit


def inverse_cdf(u: np.ndarray, table: np.ndarray, buckets: int = 1 << 12, compiled: bool | None = None,
                out: np.ndarray | None = None) -> np.ndarray:
    """``np.searchsorted(table, u, side="right")`` (int32) for u ∈ [0, 1), ~5× faster on big arrays.

    d(u) = #{i : F(i) ≤ u} is non-decreasing, so on the bucket [b/K, (b+1)/K) it lies between its
    values at the two ends (K = ``buckets``, a power of two: u·K is exact); where they agree (all
    but ≈ len(table)/K of the buckets) that is d, elsewhere a binary search decides. Exact.
    ``compiled``: True = the same search as one compiled loop where numba imports
    (:mod:`netkf_cli.channels._delay_numba`, ~5× the numpy path; identical results, tested); None
    (default) = compiled for arrays of ≥ ``kalman.AUTO_MIN_RUN_STEPS`` entries (the size from which
    the core compiles too: numba's import is then paid anyway); False = numpy. ``out``: an int32 array of u's
    shape to write into (C-contiguous; returned).
    """
    K = int(buckets)
    lo, amb_b = _buckets(np.ascontiguousarray(table, dtype=float), K)
    if compiled is None:
        compiled = u.size >= AUTO_MIN_RUN_STEPS
    if compiled:
        try:
            from netkf_cli.channels import _delay_numba  # optional (numba): the same search, one fused loop
        except ImportError:
            pass
        else:
            if out is None:
                out = np.empty(u.shape, dtype=np.int32)
            _delay_numba.inverse_cdf(np.ascontiguousarray(u, dtype=float).reshape(-1),
                                     np.ascontiguousarray(table, dtype=float), lo, amb_b, K, out.reshape(-1))
            return out
    b = (u * K).astype(np.int32)
    d = lo[b]
    amb = np.flatnonzero(amb_b[b])
    if amb.size:
        flat = d.reshape(-1)
        flat[amb] = np.searchsorted(table, u.reshape(-1)[amb], side="right")
    if out is not None:
        out[...] = d
        return out
    return d


TRACE_BLOCK = 1 << 18
"""delay_trace draws and inverts its uniforms in blocks of rows of about this many entries (one reused buffer,
cache-sized): the same numbers as one ``rng.random((horizon, runs))`` (the generator's stream is sequential,
time-major), without a horizon × runs float array per chunk."""


def compiled_trace(entries: int) -> bool:
    """Whether :func:`delay_trace` inverts a horizon × runs array of ``entries`` with the compiled loop (the same
    integers): from ``kalman.AUTO_MIN_RUN_STEPS`` entries (numba's import is then paid anyway), or from
    :data:`TRACE_BLOCK` entries once numba is imported in this process (the loop's cached kernel, ~0.1 s, is all
    it costs; a 20 000 × 60 trace 7.2 -> 2.6 ms)."""
    return entries >= AUTO_MIN_RUN_STEPS or ("numba" in sys.modules and entries >= TRACE_BLOCK)


def delay_trace(channel, rng: np.random.Generator, runs: int, horizon: int) -> Trace:
    """Sample a delay trace for ``channel`` (see :meth:`DelayChannel.sample_trace`): the uniforms of
    ``rng.random((horizon, runs))``, in blocks of rows (:data:`TRACE_BLOCK`), through :func:`inverse_cdf`,
    compiled or not as :func:`compiled_trace` decides for the whole horizon × runs array (each block alone is
    smaller than the threshold: passing ``None`` let every block choose numpy)."""
    table = cdf_table(channel, horizon - 1)
    compiled = compiled_trace(horizon * runs)
    d = np.empty((horizon, runs), dtype=np.int32)
    rows = max(1, min(horizon, TRACE_BLOCK // max(runs, 1)))
    buf = np.empty((rows, runs))
    for t0 in range(0, horizon, rows):
        u = buf[: min(rows, horizon - t0)]
        rng.random(out=u)
        inverse_cdf(u, table, compiled=compiled, out=d[t0:t0 + len(u)])
    d[d >= horizon] = LOST
    return Trace(runs=runs, horizon=horizon, delay=d[None], arrival=(d == 0)[None],
                 meta={"channel": channel.kind, "buffer": int(channel.D), "convention": channel.convention,
                       "D_max_kept_delay": max_kept_delay(channel.D, channel.convention),
                       "arrival_means": "delay 0 (usable on time)"})


# ---------------------------------------------------------------------------------------------
# What the delay-buffer estimators (buffered, smart_sensor) and the Shi 2009 recipes read from a
# channel or a trace: the single link's delays, the keep rule of the buffer and the delay-law label
# (the MKF runs per step are the buffered estimator's updates() hook) — no filtering.
# ---------------------------------------------------------------------------------------------


def trace_delays(trace) -> np.ndarray:
    """(horizon, runs) delays of the single link of a trace: ``delay``, else ``arrival`` as 0 / LOST."""
    if trace.sensors > 1:
        raise ValueError(f"a buffered/smart-sensor estimator reads one link, the trace has {trace.sensors}")
    if trace.delay is not None:
        return trace.delay[0]
    if trace.arrival is not None:
        return np.where(trace.arrival[0], 0, LOST).astype(np.int32)
    raise ValueError("a delay-buffer estimator needs a trace with delay or arrival")


def trace_max_kept_delay(trace) -> int:
    """D_max of the trace's buffer (``meta['buffer']``, ``meta['convention']``); no buffer in the meta
    (a pure-loss or replayed trace): every delay within the horizon is kept."""
    D = trace.meta.get("buffer")
    if D is None:
        return int(trace.horizon)
    return max_kept_delay(int(D), trace.meta.get("convention", DEFAULT_CONVENTION))


def kept_by(d: np.ndarray, k: int, Dmax: int, first: int = 0) -> np.ndarray:
    """γ_s^{(k)} = [d_s ≤ min(k − s, D_max)] for packets s = first+1 … k (eq. 4 in the time-k view),
    from the delays ``d`` (horizon, runs) of packets 1 … horizon; shape (k − first, runs)."""
    age = (k - np.arange(first + 1, k + 1))[:, None]
    return d[first:k] <= np.minimum(age, Dmax)


def delay_label(channel, math: bool = False) -> str:
    """Short text for a delay law: 'Poisson d = 5' (``math=True``: mathtext, 'Poisson $d = 5$')."""
    def eq(name: str, value: str) -> str:
        return f"${name} = {value}$" if math else f"{name} = {value}"

    if channel.kind == "bernoulli":
        return "Bernoulli " + eq(r"\gamma" if math else "γ", f"{channel.arrival:g}")
    dist = getattr(channel, "delay", None)
    if channel.kind == "trace":
        return f"recorded {getattr(channel, 'values', 'arrival')}s ({channel.file})"
    if dist is None:
        return f"{channel.kind} channel"
    if dist.kind == "poisson":
        return "Poisson " + eq("d", f"{dist.mean:g}")
    if dist.kind == "geometric":
        return "geometric " + eq("p", f"{dist.p:g}")
    if math:
        return rf"pmf (loss ${dist.loss:.3g}$)"
    return f"pmf {list(dist.probs)} (loss {dist.loss:.3g})"
