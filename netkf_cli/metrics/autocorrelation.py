"""``kind: autocorrelation`` — a channel's sampled gain against the autocorrelation its model states.

Checks the channel's generator, not an estimator: per run, the average over the steps t ≥ ``max_lag`` (the
stationary part of the horizon) of Re h_t h*_{t−k} (series ``gain``) and of |h_t|²|h_{t−k}|² − 1 (series
``power``: for a complex Gaussian gain E|h_t|²|h_s|² − 1 = |ρ_{t−s}|²), one independent sample per run, so
the mean over runs has an exact standard error. Beside each, the model's ρ_k (``gain``) and |ρ_k|²
(``power``) as ``source = closed_form`` rows, and the z-score of the difference.

Contract (refused otherwise): the channel offers ``sample_gain(rng, runs, horizon)`` → complex (horizon, runs)
unit-power gains and ``gain_autocorr(lags)`` → the model's E h_t h*_{t−k} (``kind: fading``: J₀ of eq. 65 for
Jakes, δ_k0 for i.i.d.).
"""

from __future__ import annotations

import math
from typing import ClassVar, Literal

import numpy as np
from netkf_cli.core.lazy import pandas as pd
from pydantic import Field

from netkf_cli.core.artefact import Artefact, RunContext
from netkf_cli.core.errors import ConfigError
from netkf_cli.metrics.common import needs, PaperRef
from netkf_cli.runtime.montecarlo import run_chunked
from netkf_cli.runtime.plotting import PALETTE, footnote, new_figure, paper_title
from netkf_cli.core.spec import AnalysisModel, PositiveInt

COLUMNS = ["series", "lag", "value", "stderr", "n", "z", "source"]


class GainAutocorrKernel:
    """Per chunk: Σ over runs of the per-run time averages (and their squares) of Re h_t h*_{t−k} and
    |h_t|²|h_{t−k}|², k = 0 … max_lag (picklable: the channel model travels with it)."""

    def __init__(self, channel, horizon: int, max_lag: int):
        self.channel, self.horizon, self.max_lag = channel, int(horizon), int(max_lag)

    def __call__(self, rng: np.random.Generator, runs: int) -> dict[str, np.ndarray]:
        h = self.channel.sample_gain(rng, runs, self.horizon)
        t0 = np.arange(self.max_lag, self.horizon)
        p2 = h.real**2 + h.imag**2
        ac = np.stack([(h[t0] * np.conj(h[t0 - k])).real.mean(0) for k in range(self.max_lag + 1)])  # (lags, runs)
        pc = np.stack([(p2[t0] * p2[t0 - k]).mean(0) for k in range(self.max_lag + 1)])
        return {"ac": ac.sum(1), "ac2": (ac**2).sum(1), "pc": pc.sum(1), "pc2": (pc**2).sum(1)}


class Autocorrelation(AnalysisModel):
    """``kind: autocorrelation`` — sample autocorrelation of a channel's gain (and power) vs its model's."""

    works_with: ClassVar[str] = "a channel with sample_gain and gain_autocorr (fading); no estimator"

    kind: Literal["autocorrelation"]
    max_lag: PositiveInt = Field(8, description="largest lag k (steps)")
    paper: PaperRef | None = Field(None, description="the paper figure this reproduces (title only)")
    title: str = Field("", description="what the figure shows")

    def check(self, scenario) -> None:
        ch = needs(scenario, "channel")
        if not (callable(getattr(ch, "sample_gain", None)) and callable(getattr(ch, "gain_autocorr", None))):
            raise ConfigError.at("channel.kind", f"autocorrelation needs a channel with a sampled complex gain and "
                                                 f"its model autocorrelation (kind fading), got {ch.kind}")
        if self.max_lag >= scenario.montecarlo.horizon:
            raise ConfigError.at("analysis.max_lag", f"must be < montecarlo.horizon = {scenario.montecarlo.horizon}")

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        ch, mc = needs(scenario, "channel"), scenario.montecarlo
        N = ctx.mc_runs(scenario)
        ctx.total(N)
        st = run_chunked(GainAutocorrKernel(ch, mc.horizon, self.max_lag), N, mc.chunk, mc.seed, stream=ctx.stream,
                         progress=ctx.progress, label="autocorrelation")
        lags = np.arange(self.max_lag + 1)
        rho = ch.gain_autocorr(lags)
        rows = []
        for series, s1, s2, shift, model in (("gain", st["ac"], st["ac2"], 0.0, rho),
                                             ("power", st["pc"], st["pc2"], 1.0, np.abs(rho) ** 2)):
            m = s1 / N
            se = np.sqrt(np.maximum(s2 / N - m**2, 0) / max(N - 1, 1))
            for k in lags:
                z = (m[k] - shift - model[k]) / se[k] if se[k] > 0 else math.nan
                rows.append(dict(series=series, lag=int(k), value=m[k] - shift, stderr=se[k], n=N, z=z,
                                 source="monte_carlo"))
                rows.append(dict(series=series, lag=int(k), value=model[k], stderr=math.nan, n=0, z=math.nan,
                                 source="closed_form"))
        meta = {"runs": N, "horizon": mc.horizon, "averaged_over": f"t = {self.max_lag} … {mc.horizon - 1} per run"}
        corr = getattr(ch, "correlation", None)
        if getattr(corr, "model", "") == "jakes":
            # speed 0 (f_D = 0): a static channel, J₀(0) = 1 at every lag, which never crosses zero (the manifest says "inf")
            meta.update(doppler_hz=corr.doppler, interval_s=corr.interval_s, nugget=corr.nugget,
                        first_zero_of_J0_s=2.404825557695773 / (2 * np.pi * corr.doppler) if corr.doppler > 0 else math.inf)
        return Artefact(pd.DataFrame(rows, columns=COLUMNS), meta=meta)

    def plot(self, tables, scenario):
        t = tables["main"]
        fig, ax = new_figure(width=7.0, height=4.6)
        for i, (series, name, mname) in enumerate((("gain", r"sample $E\,h_t h^*_{t-k}$", r"model $\rho_k$"),
                                                   ("power", "sample corr. of the power", r"model $\rho_k^2$ (power; $\rho$ real here)"))):
            g = t[(t.series == series) & (t.source == "monte_carlo")]
            r = t[(t.series == series) & (t.source == "closed_form")]
            ax.plot(r.lag, r.value, color="k", ls="-" if i == 0 else ":", label=mname)
            ax.errorbar(g.lag, g.value, yerr=5 * g.stderr, fmt="o" if i == 0 else "s", color=PALETTE[1 - i],
                        mfc=PALETTE[1 - i] if i == 0 else "none", capsize=2, label=rf"{name} $\pm$5 s.e.")
        ax.set_xlabel(r"lag $k$ (steps)")
        ax.set_ylabel("autocorrelation")
        ax.legend(loc="upper right")
        fig.suptitle(paper_title(self.paper.topic if self.paper else None, self.paper.figure if self.paper else None,
                                 self.title or "sampled channel gain vs its model autocorrelation"))
        n = int(t.n.max()) if len(t) else 0
        footnote(fig, f"n = {n:,} runs, each averaged over t = {self.max_lag} … {scenario.montecarlo.horizon - 1}; "
                      f"|z| ≤ {np.nanmax(np.abs(t.z)):.2f} over the lags (sample − model)/s.e.")
        return fig
