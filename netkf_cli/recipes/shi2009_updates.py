"""Sec. 5.1 of Shi, Xie & Murray 2009: the buffer trade-off (``kind: updates_vs_buffer``).

The expected number of MKF runs per step (closed form, checked by Monte Carlo) and
Pr[P_k ≤ M] (exact + Thm 3.8 bounds) against the buffer length D: the
performance/computation trade-off the buffer exists for.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
import pandas as pd
from pydantic import Field

from netkf_cli.analysis import delay_bounds as db
from netkf_cli.analysis import delay_exact as dx
from netkf_cli.channels.delay import CONVENTION_HELP, UpdatesKernel
from netkf_cli.errors import ConfigError
from netkf_cli.montecarlo import run_chunked, mean_and_stderr
from netkf_cli.plotting import footnote, legend_outside, new_figure, paper_title, series_style
from netkf_cli.recipes.base import Artefact, RunContext
from netkf_cli.recipes.shi2009_prob import SHORT_CONVENTION, _mbar_or_error, _span, mean_delay
from netkf_cli.recipes.shi2009_theta import delay_label
from netkf_cli.spec import AnalysisModel, PositiveFloat

D_MAX_LIMIT = 500


class UpdatesVsBuffer(AnalysisModel):
    """``kind: updates_vs_buffer`` — E[#MKF runs per step] and Pr[P_k ≤ M] against D (trade-off)."""

    kind: Literal["updates_vs_buffer"] = Field(description="E[MKF runs per step] and Pr[P_k ≤ M] against D (Shi 2009, Sec. 5.1)")
    D_max: Annotated[int, Field(gt=0, le=D_MAX_LIMIT)] = Field(
        15, description=f"buffer lengths D = 1 … D_max (at most {D_MAX_LIMIT}: one certified exact probability per D)")
    M: list[PositiveFloat] = Field([50.0], min_length=1, description="error bounds M (scalar M means M·Iₙ)")
    delay_means: list[PositiveFloat] | None = Field(
        None, description="Poisson delay means d to compare (default: the channel's own delay)")

    def _channels(self, scenario):
        ch = scenario.require_channel("delay", "bernoulli")
        if not self.delay_means:
            return [ch]
        if ch.kind != "delay" or ch.delay.kind != "poisson":
            raise ConfigError.at("analysis.delay_means", "needs a channel with a Poisson delay (delay: {kind: poisson})")
        return [ch.model_copy(update={"delay": ch.delay.model_copy(update={"mean": float(m)})}) for m in self.delay_means]

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        s = scenario.linear_system()
        chans = self._channels(scenario)
        span = _span(scenario, s)
        if span != 1:
            raise ConfigError.at("estimator.packet", "updates_vs_buffer counts MKF runs for measurement packets (span 1) only")
        _mbar_or_error(s)
        mc = scenario.montecarlo
        runs = ctx.mc_runs(scenario)
        Ds = list(range(1, self.D_max + 1))
        ctx.total(runs * len(Ds) * len(chans))
        M = np.asarray(self.M, dtype=float)
        kk1 = [db.k1(m, s, f"analysis.M[{i}]") for i, m in enumerate(M)]
        kk2 = [db.k2(m, s, f"analysis.M[{i}]") for i, m in enumerate(M)]
        rows = []
        conv = chans[0].convention
        exact_tab: dict[tuple, float] = {}
        for ci, ch0 in enumerate(chans):
            d = mean_delay(ch0)
            for D in Ds:
                ch = ch0.model_copy(update={"buffer": D})
                base = dict(D=float(D), d=d, convention=conv)
                eu = dx.expected_updates(ch)
                rows.append(dict(base, M=np.nan, series="expected_updates", value=eu, stderr=np.nan, n=np.nan, err=0.0))
                # one independent stream per (delay mean, D): SeedSequence(seed, spawn_key=(stream, chunk))
                st = run_chunked(_updates_kernel(ch), runs, mc.chunk, mc.seed, stream=ci * self.D_max + (D - 1),
                                 progress=ctx.progress, label=f"updates d={d:g} D={D}")
                n = int(st["n"])
                mu, se = mean_and_stderr(st["sum"], st["sumsq"], n)
                rows.append(dict(base, M=np.nan, series="monte_carlo_updates", value=float(mu), stderr=float(se), n=n, err=np.nan))
                ex = dx.exact_probability(s, ch, 1, M)
                for i, m in enumerate(M):
                    rows.append(dict(base, M=m, series="lower_bound", value=1 - db.theta(kk1[i], D, ch.cdf, conv),
                                     stderr=np.nan, n=np.nan, err=0.0))
                    rows.append(dict(base, M=m, series="upper_bound", value=1 - db.theta(kk2[i], D, ch.cdf, conv),
                                     stderr=np.nan, n=np.nan, err=0.0))
                    rows.append(dict(base, M=m, series="exact", value=ex.value[i], stderr=np.nan, n=np.nan, err=ex.err[i]))
                    exact_tab[(d, D, m)] = ex.value[i]
        table = pd.DataFrame(rows, columns=["D", "d", "M", "series", "value", "stderr", "n", "err", "convention"])
        # Sec. 5.1's qualitative claims as numbers
        summ = []
        ds = sorted({mean_delay(c) for c in chans})
        for m in M:
            for d in ds:
                vals = [exact_tab[(d, D, m)] for D in Ds]
                summ.append(dict(quantity="exact_nondecreasing_in_D", d=d, M=m, D=np.nan,
                                 value=float(np.all(np.diff(vals) >= -1e-9))))
                if 5 in Ds and 10 in Ds:
                    summ.append(dict(quantity="exact_D10_minus_D5", d=d, M=m, D=np.nan,
                                     value=exact_tab[(d, 10, m)] - exact_tab[(d, 5, m)]))
            if len(ds) > 1:
                for D in Ds:
                    diffs = [exact_tab[(ds[i], D, m)] - exact_tab[(ds[i + 1], D, m)] for i in range(len(ds) - 1)]
                    summ.append(dict(quantity="exact_smaller_d_minus_larger_d", d=np.nan, M=m, D=float(D),
                                     value=float(min(diffs))))
        # the claims as 1.0 (holds) / 0.0 (fails), over every D ≤ D_max, d and M of the scenario
        kind = {q: [r["value"] for r in summ if r["quantity"] == q] for q in
                ("exact_nondecreasing_in_D", "exact_smaller_d_minus_larger_d", "exact_D10_minus_D5")}
        summ.append(dict(quantity="claim_larger_D_not_worse", d=np.nan, M=np.nan, D=np.nan,
                         value=float(all(v == 1.0 for v in kind["exact_nondecreasing_in_D"]))))
        if kind["exact_smaller_d_minus_larger_d"]:
            summ.append(dict(quantity="claim_smaller_d_not_worse", d=np.nan, M=np.nan, D=np.nan,
                             value=float(min(kind["exact_smaller_d_minus_larger_d"]) >= -1e-9)))
        summary = pd.DataFrame(summ, columns=["quantity", "d", "M", "D", "value"])
        summary["convention"] = conv
        meta = {"convention": conv, "convention_meaning": CONVENTION_HELP[conv],
                "updates_definition": "MKF runs at time k per Prop. 3.1: 1 + age of the oldest packet arriving at k "
                                      "(1 when none arrives); closed form in netkf_cli/analysis/delay_exact.py",
                "runs_per_D": runs}
        return Artefact(table, meta=meta, extra_tables={"summary": summary})

    def plot(self, tables, scenario):
        t = tables["main"]
        ds = sorted(t.d.unique())
        fig, axes = new_figure(ncols=1 + len(ds), width=4.3, height=5.0, sharex=True)
        ax1, perf = axes[0], list(axes[1:])
        conv = str(t.convention.iloc[0])
        for i, (d, g) in enumerate(t.groupby("d", sort=True)):
            st = series_style(i)
            eu = g[g.series == "expected_updates"].sort_values("D")
            mcu = g[g.series == "monte_carlo_updates"].sort_values("D")
            ax1.plot(eu.D, eu.value, color=st["color"], linestyle=st["linestyle"], label=rf"$d = {d:g}$: closed form")
            ax1.errorbar(mcu.D, mcu.value, yerr=1.96 * mcu.stderr, fmt=st["marker"], ms=5, mfc="none", color=st["color"],
                         capsize=2, label=rf"$d = {d:g}$: Monte Carlo ± 1.96 s.e. ($n = {int(mcu.n.max()):,}$)")
        ax1.set_xlabel(r"buffer length $D$ (time steps)")
        ax1.set_ylabel("E[MKF runs per step] (Prop. 3.1)")
        ax1.set_title("computation")
        legend_outside(ax1, loc="below", ncol=1)
        for ax, d in zip(perf, ds):
            g = t[(t.d == d) & t.M.notna()]
            for i, (m, gm) in enumerate(g.groupby("M", sort=True)):
                st = series_style(i)
                ex = gm[gm.series == "exact"].sort_values("D")
                lo = gm[gm.series == "lower_bound"].sort_values("D")
                up = gm[gm.series == "upper_bound"].sort_values("D")
                ax.fill_between(lo.D.to_numpy(), lo.value.to_numpy(), up.value.to_numpy(), color=st["color"], alpha=0.15,
                                linewidth=0, label=rf"$M = {m:g}$: Thm 3.8 bounds")
                ax.plot(ex.D, ex.value, color=st["color"], linestyle=st["linestyle"], marker=st["marker"], ms=4,
                        label=rf"$M = {m:g}$: exact")
            ax.set_xlabel(r"buffer length $D$ (time steps)")
            ax.set_ylabel(r"$\Pr[P_k \leq M]$")
            ax.set_title(rf"performance, Poisson $d = {d:g}$")
            ax.set_ylim(-0.02, 1.02)
            legend_outside(ax, loc="below", ncol=2)
        fig.suptitle(paper_title("shi2009", "Sec. 5.1", r"computation vs performance against the buffer length $D$"))
        footnote(fig, f"{delay_label(scenario.channel).split(' d =')[0]} delays; convention {conv} ({SHORT_CONVENTION[conv]}). "
                      "E[MKF runs] = 1 + Σⱼ (1 − Πᵢ (1 − f(i))), 1 ≤ j ≤ i ≤ D (closed form, netkf); "
                      "exact Pr[P_k ≤ M]: certified, error < 1e-6.")
        return fig


def _updates_kernel(channel):
    """MKF runs at time k (Prop. 3.1): the picklable kernel of :mod:`netkf_cli.channels.delay` (a statistic of the delay law)."""
    return UpdatesKernel(channel)
