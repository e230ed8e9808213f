"""N sensors, each behind its own lossy link (Chiuso & Schenato, eq. (2)).

γ_t^i = 1 when the packet sent at time t by sensor i arrives, 0 when it is lost.
NB: the paper's λ is the LOSS probability; here the field is called ``loss`` so a
config can never be read the wrong way round (``arrival = 1 − loss``).

Links are independent across sensors and i.i.d. in time (the paper's Bernoulli model).
``loss`` is one number for every sensor or a list of N per-sensor rates.

The trace (issue 20). ``sampling: per_sensor`` (default): γ_t^i from one raw 64-bit draw per sensor, step
and run — the reference stream, drawn lazily (:class:`SensorTrace`: the same bits as
:func:`sample_multi_trace_arrivals`, any block of steps on demand, so an estimator that reads the trace in
blocks never holds the (N, horizon, runs) array; ``arrival`` is the whole array for any other reader).
``sampling: counts`` (one common loss): the trace is the count ℓ_t = Σ_i γ_t^i ~ Binomial(N, 1 − loss)
from ONE raw draw per run-step (:func:`sample_counts`), exposed as ``trace.counts`` (horizon, runs) beside
the contract's ``arrival``, which is drawn given ℓ only when read (:class:`CountTrace`,
:func:`arrivals_given_counts`: a uniform subset of size ℓ, the same joint law as N independent links) —
another stream with the same statistics (tested within 5 s.e.). MF with identical sensors reads only
``counts``; IBF, OLPEF, kf and the metrics read ``arrival``, consistent with the counts.
``sampling: bytes``: the per-sensor pattern from one byte of a raw draw per sensor (8 per draw) against
⌊256 p⌋, ties resolved exactly by fresh draws (:class:`ByteTrace`: the same law, exact; another stream,
tested within 5 s.e.) — what IBF/OLPEF need at ⅛ of per_sensor's draws. per_sensor stays the default (the
committed results are on it).

What a stream carries (the one sensor model, :func:`netkf_cli.linalg.kalman.stream_rows`): stream i is
sensor i's WHOLE measurement y_k^i = C_i x_k + v_k^i, sensor i of ``system.sensors`` — so the
channel's ``sensors`` must equal the system's number of sensors (``system.sensors: N`` for N
identical sensors each measuring C x with noise R; a list of {C, R} for sensors of their own;
unset = one sensor per output row of C). Every estimator refuses another count, naming the fix.
"""

from __future__ import annotations

from functools import lru_cache
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field, ValidationInfo, field_validator

from netkf_cli.analysis.laws import binom_cdf
from netkf_cli.linalg import kalman
from netkf_cli.linalg import kalman_codegen as kc
from netkf_cli.core.spec import ChannelModel, PositiveInt, Probability
from netkf_cli.core.trace import Trace
from netkf_cli.runtime.montecarlo import run_cache


def sample_multi_arrivals(
    rng: np.random.Generator, runs: int, horizon: int, loss: float | np.ndarray, sensors: int | None = None
) -> np.ndarray:
    """Arrival indicators γ of shape ``(runs, horizon, N)``, bool, γ_t^i ~ Bernoulli(1 − loss_i).

    ``loss`` is a scalar (then ``sensors`` gives N) or an array of N per-sensor loss probabilities.
    """
    loss_arr = np.atleast_1d(np.asarray(loss, dtype=float))
    if loss_arr.ndim != 1:
        raise ValueError("loss must be a scalar or a 1-D array of per-sensor probabilities")
    if loss_arr.size == 1:
        if sensors is None:
            raise ValueError("sensors (N) is required when loss is a scalar")
        loss_arr = np.full(int(sensors), float(loss_arr[0]))
    elif sensors is not None and loss_arr.size != sensors:
        raise ValueError(f"loss has {loss_arr.size} entries but sensors = {sensors}")
    if np.any((loss_arr < 0) | (loss_arr > 1)):
        raise ValueError("loss probabilities must lie in [0, 1]")
    # u < 1 - loss  <=>  arrived; u in [0, 1) so loss = 0 always arrives and loss = 1 never does.
    return rng.random((runs, horizon, loss_arr.size)) < (1.0 - loss_arr)


def _raw_threshold(p: np.ndarray) -> np.ndarray:
    """uint64 thresholds t with P(raw < t) = p for a uniform 64-bit raw draw (exact to 2⁻⁵³ relative)."""
    p = np.clip(np.asarray(p, dtype=float), 0.0, 1.0)
    t = np.ldexp(p, 64)  # < 2**64 for p < 1 (the largest double below 2**64 is 2**64 − 2**11)
    return np.where(p >= 1.0, np.uint64(2**64 - 1), np.minimum(t, 2.0**64 - 2.0**11).astype(np.uint64))


def sample_multi_trace_arrivals(rng: np.random.Generator, runs: int, horizon: int, loss: np.ndarray) -> np.ndarray:
    """Arrival indicators in the trace layout ``(N, horizon, runs)`` (run axis innermost), bool.

    γ_t^i = 1{r_t^i < ⌊(1 − loss_i)·2⁶⁴⌋} with one raw 64-bit draw r per sensor, step and run (the
    generator's native output: twice as fast as a float uniform, and as exact). Monotone in the loss,
    so a grid of loss values on the same stream gives common random numbers. loss = 0 always arrives
    (the threshold is 2⁶⁴ − 1: a raw draw of exactly 2⁶⁴ − 1, probability 2⁻⁶⁴, is the only miss) and
    loss = 1 never does.
    """
    loss = np.asarray(loss, dtype=float).reshape(-1)
    N = loss.size
    thr = _raw_threshold(1.0 - loss)
    out = np.empty((N, horizon, runs), dtype=bool)
    # the draws are consumed sensor by sensor, time by time, run by run (C order of (N, horizon, runs)):
    # drawing them in blocks of whole time steps gives the same bits with O(block) raw memory.
    block = max(1, min(horizon, RAW_BLOCK // max(runs, 1)))
    for i in range(N):
        for t0 in range(0, horizon, block):
            t1 = min(horizon, t0 + block)
            raw = rng.bit_generator.random_raw((t1 - t0) * runs).reshape(t1 - t0, runs)
            np.less(raw, thr[i], out=out[i, t0:t1])
        if loss[i] <= 0.0:
            out[i] = True  # exactly: no draw can be ≥ 2⁶⁴
    return out


RAW_BLOCK = 1 << 20
"""Raw 64-bit draws held at once by :func:`sample_multi_trace_arrivals` (8 MB)."""

MATERIALIZE_MAX = 1 << 24
"""A lazy :class:`SensorTrace` of at most this many arrivals (16 MB of bools: a 1000-run chunk of 25
sensors × 200 steps is 5 MB) is drawn whole on its first read and kept, so the estimators of one chunk
share one draw; a larger one is drawn block by block for each reader (memory O(RAW_BLOCK))."""

_DRAWN: dict = run_cache({})
"""The last small per-sensor traces a process drew (read-only, ≤ MATERIALIZE_MAX arrivals in all), by generator
state, class, loss and size: an ``over`` grid that leaves the channel alone (Fusion Fig. 1 over Q: stream 0 at
every point, common random numbers) samples chunk i's trace once per process, not once per point — the same
bits, since the trace is a function of exactly these. A trace of another loss or size evicts them (a grid over
the channel, Fusion Fig. 3 over the loss, never reads them again: they were 15 of a chunk's 21 MB there); the
run's end (:func:`~netkf_cli.runtime.montecarlo.run_cache`) empties the store."""


# ----------------------------------------------------------------------------------------
# The count sampler (``sampling: counts``): one raw draw per run-step
# ----------------------------------------------------------------------------------------

_CELL_BITS = 16
"""The count sampler's lookup table has 2¹⁶ cells of the raw draw's top bits (512 kB)."""


@lru_cache(maxsize=64)
def count_tables(N: int, p: float) -> tuple[np.ndarray, np.ndarray]:
    """(thr, cell) of the inverse-CDF Binomial(N, p) sampler: ``thr`` (N,) uint64 with
    P(raw < thr_k) = Pr[ℓ ≤ k] (exact to 2⁻⁵³ relative, as :func:`_raw_threshold`), so the count
    ℓ = #{k : raw ≥ thr_k}; ``cell`` (2¹⁶,) uint8 the count of every raw draw in the cell of its top
    16 bits, or 255 where a threshold falls inside the cell (those draws are resolved exactly)."""
    cdf = binom_cdf(np.arange(N), N, p)
    thr = _raw_threshold(cdf)
    if p >= 1.0:
        thr = np.zeros(N, dtype=np.uint64)  # every sensor arrives: ℓ = N for every draw
    shift = np.uint64(64 - _CELL_BITS)
    cells = np.arange(1 << _CELL_BITS, dtype=np.uint64)
    lo = np.searchsorted(thr, cells << shift, side="right")
    hi = np.searchsorted(thr, (cells << shift) | ((np.uint64(1) << shift) - np.uint64(1)), side="right")
    cell = np.where(lo == hi, lo, 255).astype(np.uint8)
    return thr, cell


def sample_counts(rng: np.random.Generator, runs: int, horizon: int, N: int, loss: float) -> np.ndarray:
    """ℓ_t = Σ_i γ_t^i for N independent links of one loss: (horizon, runs) uint8 (int16 for N ≥ 255),
    ℓ ~ Binomial(N, 1 − loss) by inversion of ONE raw 64-bit draw per run-step (run axis innermost,
    time blocks of :data:`RAW_BLOCK` draws). Monotone in the loss (common random numbers over a grid)."""
    thr, cell = count_tables(int(N), float(1.0 - loss))
    dt = np.uint8 if N < 255 else np.int16
    out = np.empty((horizon, runs), dtype=dt)
    if loss >= 1.0:
        out[:] = 0
        return out
    shift = np.uint64(64 - _CELL_BITS)
    block = max(1, min(horizon, RAW_BLOCK // max(runs, 1)))
    for t0 in range(0, horizon, block):
        t1 = min(horizon, t0 + block)
        raw = rng.bit_generator.random_raw((t1 - t0) * runs)
        if N >= 255:  # counts do not fit the uint8 table: exact search for every draw
            out[t0:t1] = np.searchsorted(thr, raw, side="right").reshape(t1 - t0, runs)
            continue
        c = cell[raw >> shift]
        amb = np.flatnonzero(c == 255)
        if amb.size:
            c[amb] = np.searchsorted(thr, raw[amb], side="right")
        out[t0:t1] = c.reshape(t1 - t0, runs)
    return out


def arrivals_given_counts(rng: np.random.Generator, counts: np.ndarray, N: int, compiled: bool = True) -> np.ndarray:
    """Per-sensor arrivals (N, horizon, runs) bool with ``counts`` (horizon, runs) arrived: a uniformly
    random subset of that size (selection sampling: sensor i arrives with probability r/(N − i), r the
    arrivals still to place; one raw draw per sensor, step and run, exact on the 2⁵³ grid).
    Given ℓ ~ Binomial(N, p), this IS the law of N independent Bernoulli(p) links. ``compiled`` (default):
    the per-sensor pass through :func:`netkf_cli.linalg.kalman_codegen.kernel_select` where numba imports (the
    same bits as the numpy passes, tested)."""
    T, runs = counts.shape
    out = np.empty((N, T, runs), dtype=bool)
    block = max(1, min(T, RAW_BLOCK // max(runs, 1)))
    one53 = np.uint64(1) << np.uint64(53)
    sel = kc.kernel_select() if compiled and kalman.numba_available() else None  # the same bits, one fused pass
    for t0 in range(0, T, block):
        t1 = min(T, t0 + block)
        r = counts[t0:t1].astype(np.uint64) * one53  # arrivals still to place, scaled by 2⁵³
        for i in range(N):
            raw = rng.bit_generator.random_raw((t1 - t0) * runs)
            hit = out[i, t0:t1]
            if sel is not None:
                sel(raw, N - i, r.reshape(-1), hit.reshape(-1))
                continue
            np.less((raw >> np.uint64(11)).reshape(t1 - t0, runs) * np.uint64(N - i), r, out=hit)
            r -= hit.astype(np.uint64) * one53
    return out


def block_steps(horizon: int, runs: int, sensors: int = 1) -> int:
    """Time steps per block of a lazy trace: a block of all ``sensors`` holds about :data:`RAW_BLOCK`
    arrivals (1 MB of bools), so reading a trace in blocks costs O(RAW_BLOCK) memory whatever the runs."""
    return max(1, min(horizon, RAW_BLOCK // max(runs * sensors, 1)))


class _LazyArrival(Trace):
    """A trace whose per-sensor ``arrival`` (N, horizon, runs) is drawn on first read (:meth:`_draw`)."""

    _arrival = None

    def _draw(self) -> np.ndarray:
        raise NotImplementedError

    @property
    def arrival(self) -> np.ndarray:  # type: ignore[override]
        if self._arrival is None:
            self._arrival = self._draw()
        return self._arrival

    @arrival.setter
    def arrival(self, value) -> None:
        if value is not None:
            self._arrival = value

    @property
    def materialized(self) -> bool:
        """Whether the per-sensor pattern has been drawn (an estimator read ``arrival``)."""
        return self._arrival is not None


class SensorTrace(_LazyArrival):
    """The per-sensor multi-channel trace (``sampling: per_sensor``), drawn lazily and bit for bit what
    :func:`sample_multi_trace_arrivals` draws: the generator's state is kept and the parent stream
    advanced past the N·horizon·runs raw draws at sampling time; the draw of (sensor i, step t, run r) is
    raw number i·horizon·runs + t·runs + r of that state (PCG64 jumps there in O(log) time).

    ``arrival`` (N, horizon, runs) is drawn on first read (the contract, for any estimator);
    :meth:`steps` gives a block of steps without materialising the whole trace, and ``counts``
    (horizon, runs) the number of sensors that arrived, block by block (memory O(N · block · runs))."""

    def __init__(self, runs: int, horizon: int, state: dict, loss: np.ndarray, meta: dict | None = None):
        self._arrival = None
        self._counts = None
        self._state, self._loss = state, np.asarray(loss, dtype=float).reshape(-1)
        self._thr = _raw_threshold(1.0 - self._loss)
        super().__init__(runs=runs, horizon=horizon, meta=dict(meta or {}))

    def __post_init__(self) -> None:
        pass

    def steps(self, t0: int, t1: int) -> np.ndarray:
        """Arrivals of steps t0 … t1 − 1, (N, t1 − t0, runs) bool (a view once materialised). A trace of at
        most :data:`MATERIALIZE_MAX` arrivals is materialised on its first read (the same bits, drawn once
        for every estimator of the chunk instead of once per estimator)."""
        if self._arrival is None and self._loss.size * self.horizon * self.runs <= MATERIALIZE_MAX:
            self._arrival = self._draw()
        if self._arrival is not None:
            return self._arrival[:, t0:t1]
        return self._draw_steps(t0, t1)

    def _draw_steps(self, t0: int, t1: int) -> np.ndarray:
        N, T, R = self._loss.size, self.horizon, self.runs
        out = np.empty((N, t1 - t0, R), dtype=bool)
        bg = np.random.PCG64()
        for i in range(N):
            if self._loss[i] <= 0.0:
                out[i] = True  # exactly, as the eager sampler
                continue
            bg.state = self._state
            bg.advance(i * T * R + t0 * R)
            np.less(bg.random_raw((t1 - t0) * R).reshape(t1 - t0, R), self._thr[i], out=out[i])
        return out

    def _draw(self) -> np.ndarray:
        small = self._loss.size * self.horizon * self.runs <= MATERIALIZE_MAX
        st = self._state["state"]
        key = (type(self).__name__, st["state"], st["inc"], self._loss.tobytes(), self.horizon, self.runs)
        if small and key in _DRAWN:
            _DRAWN[key] = _DRAWN.pop(key)  # most recently used last
            return _DRAWN[key]
        out = np.empty((self._loss.size, self.horizon, self.runs), dtype=bool)
        b = block_steps(self.horizon, self.runs, self._loss.size)
        for t0 in range(0, self.horizon, b):
            out[:, t0 : t0 + b] = self._draw_steps(t0, min(self.horizon, t0 + b))
        if small:
            out.flags.writeable = False  # shared by every trace drawn from this state
            for old in [k for k in _DRAWN if k[0] != key[0] or k[3:] != key[3:]]:
                del _DRAWN[old]  # another loss or size: an over grid through the channel, never read again
            _DRAWN[key] = out
            while sum(x.size for x in _DRAWN.values()) > MATERIALIZE_MAX:
                _DRAWN.pop(next(iter(_DRAWN)))
        return out

    @property
    def counts(self) -> np.ndarray:
        """ℓ_t = Σ_i γ_t^i, (horizon, runs) uint8 (int32 for N ≥ 256), block by block."""
        if self._counts is None:
            N = self._loss.size
            c = np.empty((self.horizon, self.runs), dtype=np.uint8 if N < 256 else np.int32)
            b = block_steps(self.horizon, self.runs, self._loss.size)
            for t0 in range(0, self.horizon, b):
                t1 = min(self.horizon, t0 + b)
                self.steps(t0, t1).sum(axis=0, dtype=c.dtype, out=c[t0:t1])
            self._counts = c
        return self._counts

    @property
    def kinds(self) -> frozenset[str]:
        return frozenset({"arrival"})

    @property
    def sensors(self) -> int:
        return int(self._loss.size)


class ByteTrace(SensorTrace):
    """The per-sensor trace of ``sampling: bytes``: the same law as ``per_sensor`` from ⅛ of the raw draws.

    Cell (t, i, r) — step, sensor, run — reads byte (t·N + i)·R + r of a run of raw 64-bit draws (little-endian
    bytes, so a block of steps is a contiguous range of draws: seekable, lazy as :class:`SensorTrace`). With
    p_i = 1 − loss_i, t_i = ⌊256 p_i⌋ and f_i = 256 p_i − t_i (both exact in floating point): the packet arrives
    iff byte < t_i, or byte = t_i (probability 1/256) and a fresh raw draw u < ⌊f_i·2⁶⁴⌋; so
    P(arrive) = t_i/256 + f_i/256 = p_i, exact as :func:`_raw_threshold` (2⁻⁵³ relative). The fresh draws of
    step t come from a second range of the parent stream, at t·N·R + j for the j-th ambiguous cell of step t in
    (sensor, run) order: the bits do not depend on how the trace is read in blocks. Another stream than
    ``per_sensor`` (tested within 5 s.e. on the statistics); monotone in the loss (common random numbers)."""

    def __init__(self, runs: int, horizon: int, state: dict, state_fix: dict, loss: np.ndarray,
                 meta: dict | None = None):
        super().__init__(runs, horizon, state, loss, meta)
        p256 = np.ldexp(1.0 - self._loss, 8)
        t = np.floor(p256)
        self._all = t >= 256  # p = 1: every packet arrives (set exactly, no byte read)
        self._t8u = np.minimum(t, 255).astype(np.uint8)
        self._fix = _raw_threshold(p256 - t)
        self._state_fix = state_fix

    @staticmethod
    def raw_draws(sensors: int, horizon: int, runs: int) -> int:
        """Raw draws of the byte range (the parent stream is advanced past them, then past N·T·R more for
        the fresh draws)."""
        return -(-sensors * horizon * runs // 8)

    def _draw_steps(self, t0: int, t1: int) -> np.ndarray:
        N, R, s = self._loss.size, self.runs, t1 - t0
        b0, b1 = t0 * N * R, t1 * N * R
        bg = np.random.PCG64()
        bg.state = self._state
        bg.advance(b0 // 8)
        raw = bg.random_raw(-(-b1 // 8) - b0 // 8).astype("<u8", copy=False)
        byt = raw.view(np.uint8)[b0 % 8 : b0 % 8 + (b1 - b0)].reshape(s, N, R)
        out = np.empty((N, s, R), dtype=bool)
        t8 = self._t8u[None, :, None]
        np.less(byt, t8, out=out.transpose(1, 0, 2))
        amb = np.flatnonzero(byt == t8)  # in (step, sensor, run) order
        if amb.size:
            step, rest = np.divmod(amb, N * R)
            ii, rr = np.divmod(rest, R)
            u = np.empty(amb.size, dtype=np.uint64)
            bg.state = self._state_fix
            pos, lo = 0, 0  # the fix stream's position; ambiguous cells of step j start at t·N·R, t = t0 + j
            for j, c in zip(*np.unique(step, return_counts=True)):
                start = (t0 + int(j)) * N * R
                bg.advance(start - pos)
                u[lo : lo + c] = bg.random_raw(int(c))
                pos, lo = start + int(c), lo + int(c)
            out[ii, step, rr] = u < self._fix[ii]
        if self._all.any():
            out[self._all] = True  # loss 0: exactly, as the eager sampler
        return out


class CountTrace(_LazyArrival):
    """A multi-channel trace sampled as counts (``sampling: counts``): ``counts`` (horizon, runs) is
    ℓ_t = Σ_i γ_t^i; ``arrival`` (N, horizon, runs) is drawn on first read, given the counts
    (:func:`arrivals_given_counts`, from a stream seeded at sampling time), so an estimator that needs
    only ℓ (MF with identical sensors) never pays for N draws per run-step, and any estimator that
    reads the per-sensor pattern sees one consistent with ℓ (the same trace for every estimator)."""

    def __init__(self, runs: int, horizon: int, counts: np.ndarray, sensors: int, seed: np.ndarray,
                 meta: dict | None = None):
        self._arrival = None
        self.counts, self._N, self._seed = counts, int(sensors), seed
        super().__init__(runs=runs, horizon=horizon, meta=dict(meta or {}))

    def __post_init__(self) -> None:
        if self.counts.shape != (self.horizon, self.runs):
            raise ValueError(f"counts must be ({self.horizon}, {self.runs}), got {self.counts.shape}")

    def _draw(self) -> np.ndarray:
        rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(x) for x in self._seed])))
        return arrivals_given_counts(rng, self.counts, self._N)

    def steps(self, t0: int, t1: int) -> np.ndarray:
        """Arrivals of steps t0 … t1 − 1 (the pattern is drawn whole on first use)."""
        return self.arrival[:, t0:t1]

    @property
    def kinds(self) -> frozenset[str]:
        return frozenset({"arrival"})

    @property
    def sensors(self) -> int:
        return self._N


def times_since_arrival_tr(arrival: np.ndarray) -> np.ndarray:
    """τ_t^i in the trace layout: ``arrival`` (N, T, runs) bool → τ (T, runs, N) int32.

    Same definition as :func:`times_since_arrival`; the output puts the sensor axis last because
    the IBF/OLPEF evaluations reduce over sensors per (time, run) row.
    """
    N, T, runs = arrival.shape
    # last arrival time ≤ t: a running maximum over time of (s if packet s arrived else −1)
    steps = np.arange(T, dtype=np.int32)[:, None, None]
    last = np.where(np.transpose(arrival, (1, 2, 0)), steps, np.int32(-1))  # (T, runs, N)
    np.maximum.accumulate(last, axis=0, out=last)
    np.subtract(steps, last, out=last)
    return last


def times_since_arrival(gamma: np.ndarray) -> np.ndarray:
    """τ_t^i: steps since sensor i's last received packet, shape like ``gamma`` (runs, T, N), int32.

    τ = 0 when the packet of time t arrived; a sensor with no packet yet has τ_t = t + 1
    (its last "arrival" is the fictitious time −1, i.e. only the prior is known).
    """
    runs, T, N = gamma.shape
    tau = np.empty((runs, T, N), dtype=np.int32)
    last = np.full((runs, N), -1, dtype=np.int32)
    for t in range(T):
        last = np.where(gamma[:, t, :], t, last)
        tau[:, t, :] = t - last
    return tau


class MultiChannel(ChannelModel):
    """``kind: multi`` — N independent i.i.d. Bernoulli loss links, one per sensor (eq. (2)).

    Arrival stream i carries sensor i's whole measurement (sensor i of ``system.sensors``); N must be
    the system's number of sensors (``system.sensors: N`` for N identical sensors).
    """

    trace_kinds: ClassVar[frozenset[str]] = frozenset({"arrival"})

    kind: Literal["multi"]
    sensors: PositiveInt = Field(description="number of sensors N = arrival streams (the paper's example: 25); stream i "
                                             "carries sensor i's whole measurement y^i = C_i x + v^i, sensor i of "
                                             "system.sensors, so N must be the system's number of sensors "
                                             "(system.sensors: N for N identical sensors)")
    loss: Probability | list[Probability] = Field(
        description="packet LOSS probability (the paper's λ): one value for all sensors or a list of N"
    )
    sampling: Literal["per_sensor", "counts", "bytes"] = Field(
        "per_sensor", description="per_sensor: one raw draw per sensor, step and run (the reference stream) | counts: "
                                  "the number of sensors that arrived, ℓ ~ Binomial(N, 1 − loss), from one draw per "
                                  "run-step, the per-sensor pattern drawn given ℓ only if an estimator reads it (the "
                                  "same law, another stream; MF with identical sensors needs only ℓ); one common loss only "
                                  "| bytes: each sensor's arrival from one BYTE of a raw draw (8 per draw) against ⌊256 p⌋, "
                                  "a byte equal to it resolved exactly by a fresh draw (the same law, exact; another "
                                  "stream): the per-sensor pattern IBF/OLPEF need at ⅛ of per_sensor's draws")

    @field_validator("loss")
    @classmethod
    def _check_loss_length(cls, v, info: ValidationInfo):
        n = info.data.get("sensors")
        if isinstance(v, list) and n is not None and len(v) != n:
            raise ValueError(f"a list must have one entry per sensor ({n}), got {len(v)}")
        return v

    @field_validator("sampling")
    @classmethod
    def _check_sampling(cls, v, info: ValidationInfo):
        loss = info.data.get("loss")
        if v == "counts" and isinstance(loss, list) and len(set(loss)) > 1:
            raise ValueError("sampling: counts needs one loss for every sensor (the count of arrivals is Binomial "
                             "only for identical links); use sampling: per_sensor")
        return v

    @property
    def loss_array(self) -> np.ndarray:
        """Per-sensor loss probabilities, shape (N,)."""
        if isinstance(self.loss, list):
            return np.asarray(self.loss, dtype=float)
        return np.full(self.sensors, float(self.loss))

    @property
    def common_loss(self) -> float | None:
        """The loss probability if every sensor has the same one, else None."""
        arr = self.loss_array
        return float(arr[0]) if np.all(arr == arr[0]) else None

    def with_loss(self, loss: float) -> "MultiChannel":
        return self.model_copy(update={"loss": float(loss)})

    def sample(self, rng: np.random.Generator, runs: int, horizon: int) -> np.ndarray:
        """γ of shape (runs, horizon, N), bool (legacy layout; :meth:`sample_trace` is the contract)."""
        return sample_multi_arrivals(rng, runs, horizon, self.loss_array)

    def sample_trace(self, rng: np.random.Generator, runs: int, horizon: int) -> Trace:
        """``Trace.arrival`` (N, horizon, runs): γ_t^i ~ Bernoulli(1 − loss_i), independent (eq. (2)).

        ``sampling: per_sensor`` on a PCG64 stream (netkf's): a :class:`SensorTrace`, the same bits drawn
        lazily (block by block for the estimators that can, whole when ``arrival`` is read).
        ``sampling: counts``: a :class:`CountTrace` — ``counts`` ℓ_t (horizon, runs) from one raw draw per
        run-step (then two raw draws seed the per-sensor pattern, drawn given ℓ only when read)."""
        meta = {"channel": "multi", "sensors": self.sensors, "loss": self.loss_array.tolist(), "sampling": self.sampling}
        if self.sampling == "counts":
            counts = sample_counts(rng, runs, horizon, self.sensors, float(self.loss_array[0]))
            seed = rng.bit_generator.random_raw(2)
            return CountTrace(runs, horizon, counts, self.sensors, seed, meta)
        if self.sampling == "bytes":
            if not isinstance(rng.bit_generator, np.random.PCG64):
                raise ValueError("sampling: bytes needs a PCG64 stream (netkf's)")
            state = rng.bit_generator.state
            rng.bit_generator.advance(ByteTrace.raw_draws(self.sensors, horizon, runs))
            state_fix = rng.bit_generator.state
            rng.bit_generator.advance(self.sensors * horizon * runs)
            return ByteTrace(runs, horizon, state, state_fix, self.loss_array, meta)
        if isinstance(rng.bit_generator, np.random.PCG64):  # lazy, the same bits (see SensorTrace)
            state = rng.bit_generator.state
            rng.bit_generator.advance(self.sensors * horizon * runs)
            return SensorTrace(runs, horizon, state, self.loss_array, meta)
        arr = sample_multi_trace_arrivals(rng, runs, horizon, self.loss_array)
        return Trace(runs=runs, horizon=horizon, arrival=arr, meta=meta)

    def loss_rate(self) -> float:
        """Stationary probability that one sensor's packet is lost (the paper's λ; the mean over
        sensors when the rates differ)."""
        return float(self.loss_array.mean())
