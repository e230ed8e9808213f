"""``kind: fading`` — wireless fading channel of Mostofi & Murray 2009 (Sec. 2.1, Sec. 4.1).

The instantaneous received SNR is Υ[k] = Υ_ave |h[k]|² (eq. 3) with a unit-power complex
Gaussian gain h (Rayleigh fading, so Υ is exponential with mean Υ_ave):

* ``correlation: {model: iid}`` — h[k] independent from one transmission to the next (Sec. 2).
* ``correlation: {model: jakes, carrier_hz, speed, interval_s}`` — E h[t]h*[t−k] = J₀(2π f_D k T),
  f_D = s_mob F_c / c (eq. 65). Generated exactly (for the horizon) as a stationary complex
  Gaussian sequence: h = L z, z ~ CN(0, I), L the Cholesky factor of the Toeplitz covariance
  Σ_ij = (J₀(2π f_D T |i−j|) + ε δ_ij)/(1 + ε). The sampled Jakes spectrum vanishes above f_D, so
  J₀'s Toeplitz matrix is singular up to rounding; the white floor ε (``nugget``, default 1e-9 of
  the fading power) makes it positive definite, and gives every step a well-defined conditional
  law given the past (used by the sequential Monte Carlo of Fig. 7). Results at the Fig. 7
  thresholds where the estimates are reliable do not change between ε = 1e-9 and 1e-6.

The communication-noise model σ_n²(Υ) lives here as well (``noise:``): ``model: ber`` is
α + δ·Ω(√Υ) (Sec. 3.1) with α, δ given or derived from N_p and Δ; ``model: inverse_snr`` is
β/Υ (eq. 50, Theorem 4).

SNR values are never guessed: every SNR carries ``unit: linear | dB``.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from functools import lru_cache
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field, model_validator

from netkf_cli.analysis import fading as fa
from netkf_cli.core.spec import ChannelModel, FiniteFloat, NonNegFloat, PositiveFloat, PositiveInt, StrictModel
from netkf_cli.core.trace import Trace


class Snr(StrictModel):
    """An SNR with its unit: ``{value: 20, unit: dB}`` or ``{value: 100, unit: linear}``."""

    value: FiniteFloat = Field(description="the SNR value (Υ) in the given unit")
    unit: Literal["linear", "dB"] = Field(description="'linear' (power ratio) or 'dB' (10 log10)")

    @model_validator(mode="after")
    def _check(self):
        if self.unit == "linear" and self.value < 0:
            raise ValueError(f"a linear SNR must be >= 0, got {self.value}")
        return self

    @property
    def linear(self) -> float:
        return float(fa.db_to_linear(self.value)) if self.unit == "dB" else float(self.value)


class Speed(StrictModel):
    """A speed with its unit."""

    value: NonNegFloat = Field(description="mobile speed s_mob (≥ 0; 0 is a static channel: f_D = 0, the same gain at every step)")
    unit: Literal["m/s", "mph", "km/h"] = Field(description="unit of the speed")

    @property
    def mps(self) -> float:
        return self.value * {"m/s": 1.0, "mph": fa.MPH, "km/h": 1 / 3.6}[self.unit]


class IidCorrelation(StrictModel):
    """Independent gains from one transmission to the next (Sec. 2)."""

    model: Literal["iid"] = Field(description="iid: h[k] independent over k")


class JakesCorrelation(StrictModel):
    """Jakes-correlated gains E h[t]h*[t−k] = J₀(2π f_D k T) (eq. 65)."""

    model: Literal["jakes"] = Field(description="jakes: Clarke/Jakes autocorrelation J₀ (eq. 65)")
    carrier_hz: PositiveFloat = Field(description="carrier frequency F_c in Hz")
    speed: Speed = Field(description="mobile speed s_mob")
    interval_s: PositiveFloat = Field(description="time between consecutive transmissions in seconds")
    nugget: PositiveFloat = Field(1e-9, description="white floor ε > 0 added to the J₀ covariance (relative to the "
                                                    "fading power) so that it is positive definite (Cholesky generation: "
                                                    "J₀'s Toeplitz matrix alone is singular to rounding)")

    @property
    def doppler(self) -> float:
        return fa.doppler_hz(self.speed.mps, self.carrier_hz)

    def autocorr(self, lags):
        return fa.jakes_autocorr(lags, self.doppler, self.interval_s)


class NoiseModel(StrictModel):
    """σ_n²(Υ). ``ber``: α + δ Ω(√Υ), give (alpha, delta) or (N_p, Delta). ``inverse_snr``: β/Υ (eq. 50)."""

    model: Literal["ber", "inverse_snr"] = Field(description="ber: σ_n² = α + δ Ω(√Υ) (Sec. 3.1); inverse_snr: σ_n² = β/Υ (eq. 50)")
    alpha: NonNegFloat | None = Field(None, description="α, quantization floor of σ_n² (model ber)")
    delta: NonNegFloat | None = Field(None, description="δ, weight of the bit-error term of σ_n² (model ber)")
    N_p: PositiveInt | None = Field(None, description="bits per packet")
    Delta: PositiveFloat | None = Field(None, description="quantization step Δ")
    beta: NonNegFloat | None = Field(None, description="β of σ_n² = β/Υ (model inverse_snr)")

    @model_validator(mode="after")
    def _check(self):
        given = {k for k in ("alpha", "delta", "N_p", "Delta", "beta") if getattr(self, k) is not None}
        if self.model == "ber":
            if given == {"alpha", "delta"} or given == {"N_p", "Delta"}:
                return self
            raise ValueError("model ber needs exactly one pair: (alpha, delta) or (N_p, Delta); "
                             f"got {sorted(given) or 'none'}")
        if given != {"beta"}:
            raise ValueError(f"model inverse_snr needs exactly `beta`; got {sorted(given) or 'none'}")
        return self

    @property
    def params(self) -> tuple[float, float]:
        """(α, δ) for model ber."""
        if self.alpha is not None:
            return float(self.alpha), float(self.delta)
        return fa.noise_params_from_bits(self.N_p, self.Delta)

    def variance(self, snr):
        """σ_n²(Υ) for an array of linear SNRs (inf for Υ = 0 under inverse_snr)."""
        snr = np.asarray(snr, dtype=float)
        if self.model == "ber":
            a, d = self.params
            return fa.sigma2_n(snr, a, d)
        with np.errstate(divide="ignore"):
            return self.beta / snr


@dataclass(frozen=True)
class NoiseFn:
    """σ_n²(Υ) as a picklable callable: ``ber`` α + δ Ω(√Υ) (Sec. 3.1) or ``inverse_snr`` β/Υ (eq. 50).

    It travels with the trace (``Trace.meta['noise']``): the channel defines what a kept packet's
    communication noise is, every receiver reads it from there."""

    model: str
    alpha: float = 0.0
    delta: float = 0.0
    beta: float = 0.0

    @classmethod
    def of(cls, noise) -> "NoiseFn":
        """From a channel's ``NoiseModel``."""
        if noise.model == "ber":
            a, d = noise.params
            return cls("ber", alpha=float(a), delta=float(d))
        return cls("inverse_snr", beta=float(noise.beta))

    def __call__(self, snr):
        snr = np.asarray(snr, dtype=float)
        if self.model == "ber":
            return fa.sigma2_n(snr, self.alpha, self.delta)
        with np.errstate(divide="ignore"):
            return self.beta / snr

    def mean_given_kept(self, threshold, snr_avg):
        """E[σ_n²(Υ) | Υ ≥ Υ_T] = σ²_n,ave(Υ_T)/(1 − μ_ave(Υ_T)) (eqs 15–16); ``None`` unless ``ber``."""
        if self.model != "ber":
            return None
        T = np.asarray(threshold, dtype=float)
        return fa.sigma2_n_ave(T, snr_avg, self.alpha, self.delta) / np.exp(-T / snr_avg)


def snr_given_kept(snr, threshold: float, snr_avg: float) -> np.ndarray:
    """Υ' per entry: Υ itself where Υ ≥ Υ_T (kept), else an SNR with the law of Υ | Υ ≥ Υ_T made from
    the same Υ — for i.i.d. exponential Υ (mean Υ_ave) independent of whether the packet was kept.

    With F the exponential cdf and μ = F(Υ_T): given a drop, V = F(Υ)/μ is uniform, so
    Υ' = F⁻¹(μ + (1 − μ) V) = Υ_T + Υ_ave·(−log(1 − V)) (memoryless), written with expm1 for
    accuracy; given a keep, (F(Υ) − μ)/(1 − μ) is uniform and Υ' = Υ. Either way Υ' ~ Υ | Υ ≥ Υ_T and
    Υ' is independent of the keep decision (the burst-conditioned receiver estimator needs both)."""
    Y = np.asarray(snr, dtype=float)
    drop = Y < float(threshold)
    if float(threshold) <= 0 or not drop.any():
        return Y
    out = Y.copy()
    out[drop] = snr_given_dropped(Y[drop], threshold, snr_avg)
    return out


def snr_given_dropped(snr, threshold: float, snr_avg: float) -> np.ndarray:
    """Υ' of :func:`snr_given_kept` for dropped entries Υ < Υ_T only (Υ_T > 0): Υ_T + Υ_ave·(−log(1 − V))."""
    Y = np.asarray(snr, dtype=float)
    T, a = float(threshold), float(snr_avg)
    with np.errstate(divide="ignore", invalid="ignore"):
        e = T / a - np.log(np.expm1((T - Y) / a)) + np.log(-np.expm1(-T / a))  # −log(1 − V) ~ Exp(1)
    return T + a * np.maximum(e, 0.0)


def noise_of_trace(trace: Trace, noise) -> np.ndarray:
    """σ_n²(Υ) of every entry of ``trace.snr`` (horizon, runs), computed once per drawn sample (shared by the
    traces of one sample: :class:`DrawnSamples`). Not to be modified. (Kept with the SNR array it was computed
    from: a trace whose ``snr`` was replaced by another array gets its own.)"""
    snr = trace.snr
    got = trace.derived(("noise_of_trace", noise), lambda: (snr, noise(snr)))
    return got[1] if got[0] is snr else noise(snr)


def _per_threshold(trace: Trace, key, params, make) -> np.ndarray:
    """``make()`` for ``params`` (a threshold's), the same array for every receiver that asks for this trace, ``key``
    and ``params`` in a row (the receivers of one chunk: computed once). One value per ``key`` among the trace's
    derived values, replaced when other params come: those are shared by the traces of one sample
    (:class:`DrawnSamples`), which a sweep reads at every threshold."""
    d = trace._derived
    try:
        got = d.get(key)
    except TypeError:  # an unhashable part (a caller's own noise function): not shared
        return make()
    if got is None or got[0] != params or got[1] is not trace.snr:
        got = d[key] = (params, trace.snr, make())
    return got[2]


def noise_where_kept(trace: Trace, t: int, k: int, threshold: float, noise) -> np.ndarray:
    """σ_n²(Υ) of steps t … k−1 where the packet is kept (Υ ≥ Υ_T), σ_n²(1) where dropped (a placeholder the
    receivers never use): ``noise(np.where(Υ ≥ Υ_T, Υ, 1.0))`` entry for entry (the same elementwise function),
    with the kept entries taken from :func:`noise_of_trace`. Not to be modified (:func:`_per_threshold`)."""
    def make():
        Y = trace.snr[t:k]
        out = noise_of_trace(trace, noise)[t:k].copy()
        drop = ~(Y >= threshold)
        if drop.any():
            out[drop] = noise(np.ones(int(drop.sum())))
        return out

    return _per_threshold(trace, ("noise_where_kept", t, k, noise), float(threshold), make)


def noise_given_kept(trace: Trace, t: int, k: int, threshold: float, snr_avg: float, noise) -> np.ndarray:
    """σ_n²(Υ') of steps t … k−1, Υ' = :func:`snr_given_kept` (Υ itself where kept):
    ``noise(snr_given_kept(Υ, Υ_T, Υ_ave))`` entry for entry, with the kept entries taken from
    :func:`noise_of_trace` (only the dropped ones, a fraction μ_ave, are evaluated per threshold). Not to be
    modified (:func:`_per_threshold`)."""
    def make():
        Y = trace.snr[t:k]
        out = noise_of_trace(trace, noise)[t:k].copy()
        drop = Y < float(threshold)
        if float(threshold) > 0 and drop.any():
            out[drop] = noise(snr_given_dropped(Y[drop], threshold, snr_avg))
        return out

    return _per_threshold(trace, ("noise_given_kept", t, k, noise), (float(threshold), float(snr_avg)), make)


@dataclass
class DrawnSamples:
    """The SNR samples this process drew, by the state of the generator they were drawn from.

    The points of a sweep with common random numbers (``streams: common``) draw chunk i from the same
    generator state at every point (Fig. 6: 18 thresholds × 4 chunks, 4 distinct samples). A state seen a
    second time is kept: its SNR array (read-only), the generator's state after the draw — restored on a hit,
    so the caller's generator continues exactly as after a fresh draw — and what receivers derive from the
    sample alone (:func:`noise_of_trace`). A state seen once keeps only its key (a scenario without repeats
    holds no arrays); at most ``max_bytes`` of arrays, the least recently used dropped first."""

    max_bytes: float = 64e6
    seen: OrderedDict = field(default_factory=OrderedDict)
    kept: OrderedDict = field(default_factory=OrderedDict)

    def draw(self, key, rng: np.random.Generator, sample) -> tuple[np.ndarray, dict]:
        """(snr, derived) for ``key`` (which must name everything the draw depends on besides ``rng``'s state):
        ``sample()`` draws it from ``rng``."""
        key = (repr(rng.bit_generator.state),) + tuple(key)
        hit = self.kept.get(key)
        if hit is not None:
            self.kept.move_to_end(key)
            rng.bit_generator.state = hit[1]
            return hit[0], hit[2]
        snr = sample()
        snr.flags.writeable = False  # (whether kept or not: a trace's SNR is never written in place)
        derived: dict = {}
        if key in self.seen:
            self.kept[key] = (snr, rng.bit_generator.state, derived)
            while len(self.kept) > 1 and sum(_nbytes(v) for v in self.kept.values()) > self.max_bytes:
                self.kept.popitem(last=False)
        else:
            self.seen[key] = None
            if len(self.seen) > 4096:
                self.seen.popitem(last=False)
        return snr, derived


def _nbytes(entry) -> int:
    """Bytes of a kept sample: its SNR array and the arrays derived from it (held in tuples beside it)."""
    arrays = [x for v in entry[2].values() for x in (v if isinstance(v, tuple) else (v,))]
    return entry[0].nbytes + sum(x.nbytes for x in arrays if isinstance(x, np.ndarray) and x is not entry[0])


DRAWN = DrawnSamples()


@dataclass(frozen=True)
class FadingTrace:
    """Linear SNR Υ[k] per run, shape ``(horizon, runs)`` (time-major: ``snr[k]`` is contiguous over runs)."""

    snr: np.ndarray


@lru_cache(maxsize=16)
def _jakes_factor(horizon: int, phase_step: float, nugget: float) -> np.ndarray:
    """Lower Cholesky factor of Σ_ts = (J₀(phase_step·|t−s|) + ε δ_ts)/(1 + ε) (unit power)."""
    lags = np.arange(horizon)
    r = fa.special.j0(phase_step * lags)
    S = r[np.abs(lags[:, None] - lags[None, :])] + nugget * np.eye(horizon)
    return np.linalg.cholesky(S / (1.0 + nugget))


def jakes_factor(horizon: int, corr) -> np.ndarray:
    """The factor L with h = L z (z ~ CN(0, I)) used by :func:`sample_gain` for a Jakes correlation."""
    return _jakes_factor(int(horizon), float(2 * np.pi * corr.doppler * corr.interval_s), float(corr.nugget))


def sample_gain(rng: np.random.Generator, runs: int, horizon: int, corr) -> np.ndarray:
    """Complex unit-power channel gains h, shape (horizon, runs)."""
    re, im = gain_parts(rng, runs, horizon, corr)
    return re + 1j * im


def gain_parts(rng: np.random.Generator, runs: int, horizon: int, corr) -> tuple[np.ndarray, np.ndarray]:
    """(Re h, Im h) of :func:`sample_gain`, bit for bit, without its complex arrays (the SNR needs only
    |h|² = Re² + Im²: a 300 × 1000 chunk 10.4 → 6.5 ms).

    h = (x + i y)/√2 with x, y standard normal (x drawn first); numpy divides a complex by √2 as a complex,
    (x + y·0)·(1/√2) + i (y − x·0)·(1/√2) (Smith's algorithm), which is x·(1/√2) and y·(1/√2) exactly. A Jakes
    gain is L z, each part on its own (einsum, not BLAS: a multi-threaded GEMM's rounding depends on the thread
    count, and the channel must be bit-for-bit the same in the parent and in any worker process)."""
    scale = 1.0 / np.sqrt(2.0)
    x = rng.standard_normal((horizon, runs))
    y = rng.standard_normal((horizon, runs))
    x *= scale
    y *= scale
    if corr.model == "iid":
        return x, y
    L = jakes_factor(horizon, corr)
    return np.einsum("ij,jk->ik", L, x), np.einsum("ij,jk->ik", L, y)


@dataclass(frozen=True)
class GaussianDropLaw:
    """A drop process made by thresholding a complex-Gaussian gain: drop_t iff Υ_ave |h_t|² < Υ_T, h = L z.

    ``factor`` L (horizon, horizon) lower triangular (None: independent gains), ``noise`` σ_n²(Υ) of a kept
    packet. Given the past, h_t is N(Σ_{u<t} L_tu z_u, L_tt²) per real component: each step's drop probability
    and its conditional law are closed forms (non-central χ²₂), which a sequential Monte Carlo of the drop
    bursts moves through (:class:`netkf_cli.estimators.fading_receivers.BurstSMCKernel`)."""

    factor: np.ndarray | None
    snr_avg: float
    threshold: float
    noise: NoiseFn


class FadingChannel(ChannelModel):
    """``kind: fading`` — Rayleigh fading SNR Υ (exponential, mean ``snr_avg``), i.i.d. or Jakes-correlated."""

    kind: Literal["fading"]
    trace_kinds: ClassVar[frozenset[str]] = frozenset({"snr"})
    snr_avg: Snr = Field(description="average received SNR Υ_ave with its unit")
    correlation: IidCorrelation | JakesCorrelation = Field(IidCorrelation(model="iid"), discriminator="model",
                                                           description="time correlation of the gain h: iid or jakes (eq. 65)")
    noise: NoiseModel = Field(description="communication-noise variance σ_n²(Υ)")
    threshold: Snr | None = Field(None, description="drop threshold Υ_T (eq. 5) of every receiver that gives none "
                                                    "(one place to sweep it: analysis.over {channel.threshold.value: …})")

    @model_validator(mode="after")
    def _positive(self):
        if not self.snr_avg.linear > 0:
            raise ValueError("snr_avg must be > 0 (linear)")
        return self

    @property
    def mean_snr(self) -> float:
        return self.snr_avg.linear

    def sample(self, rng: np.random.Generator, runs: int, horizon: int) -> FadingTrace:
        re, im = gain_parts(rng, runs, horizon, self.correlation)
        return FadingTrace(self.mean_snr * (re**2 + im**2))

    def sample_trace(self, rng: np.random.Generator, runs: int, horizon: int) -> Trace:
        """Issue-12 trace: ``snr`` (horizon, runs) linear Υ_t (eq. 3); ``meta['noise']`` is σ_n²(·) (picklable).

        Same random numbers as :meth:`sample`. A receiver turns Υ_t into the drop (Υ_t < Υ_T, eq. 5)
        and the communication-noise variance σ_n²(Υ_t) of each step.
        """
        snr, derived = DRAWN.draw((runs, horizon, self.mean_snr, repr(self.correlation)), rng,
                                  lambda: self.sample(rng, runs, horizon).snr)
        trace = Trace(runs=runs, horizon=horizon, snr=snr,
                      meta={"noise": NoiseFn.of(self.noise), "snr_avg": self.mean_snr,
                            "correlation": self.correlation.model,
                            "threshold": None if self.threshold is None else self.threshold.linear})
        trace._derived = derived  # what is derived from the sample alone, shared by its traces (DrawnSamples)
        return trace

    def drop_law(self, threshold: float, horizon: int) -> "GaussianDropLaw":
        """The contract of a drop-burst sequential Monte Carlo (``kind: burst_mean``): a packet is dropped iff
        Υ_t = Υ_ave |h_t|² < Υ_T with h a stationary unit-power complex Gaussian sequence, h = L z (z ~ CN(0, I);
        L :func:`jakes_factor` for Jakes, ``None`` for i.i.d. gains), and a kept packet carries σ_n²(Υ_t)."""
        factor = None if self.correlation.model == "iid" else jakes_factor(horizon, self.correlation)
        return GaussianDropLaw(factor, self.mean_snr, float(threshold), NoiseFn.of(self.noise))

    def sample_gain(self, rng: np.random.Generator, runs: int, horizon: int) -> np.ndarray:
        """The unit-power complex gains h, shape (horizon, runs) — the same random numbers as :meth:`sample`
        (Υ = Υ_ave |h|²); the contract of ``kind: autocorrelation``."""
        return sample_gain(rng, runs, horizon, self.correlation)

    def gain_autocorr(self, lags) -> np.ndarray:
        """The model's E h_t h*_{t−k} at ``lags``: J₀(2π f_D k T) (eq. 65) for Jakes, δ_k0 for i.i.d. gains."""
        lags = np.asarray(lags)
        if self.correlation.model == "iid":
            return (lags == 0).astype(float)
        return np.asarray(self.correlation.autocorr(lags), dtype=float)

    def independent(self) -> "FadingChannel":
        """The same channel with independent gains from one transmission to the next (same marginal law of Υ)."""
        return self.model_copy(update={"correlation": IidCorrelation(model="iid")})

    def snr_law(self) -> dict:
        """What closed forms may use: Υ is exponential with mean Υ_ave (Rayleigh, eq. 3); i.i.d. or Jakes (eq. 65).

        ``mu_ave(T)`` = Pr[Υ < Υ_T] (eq. 15) holds marginally for both correlation models; the
        mean recursions (eqs 14, 20) need ``correlation == 'iid'``.
        """
        law = {"distribution": "exponential", "mean": self.mean_snr, "correlation": self.correlation.model,
               "mu_ave": lambda T: fa.mu_ave(T, self.mean_snr)}
        if self.correlation.model == "jakes":
            law["doppler_hz"] = self.correlation.doppler
            law["autocorr"] = self.correlation.autocorr
        return law
