"""``kind: compare`` — several estimators on the same sampled traces (common random numbers).

For each estimator: E[tr P_k] at step ``at`` (standard error, heavy-tail flag) and, for each M
of ``M``, Pr[P_k ≤ M] with its Wilson interval; for every estimator after the first, the
paired difference E[tr P_k − tr P_k^{ref}] against the first (the reference), whose standard
error comes from the per-run differences — far smaller than the two separate standard errors
when the estimators see the same traces. An estimator compared with itself gives identical
columns and a difference of exactly 0. Every estimator reports the same ``quantity`` (one field
of the metric: different quantities are never side by side); the figure draws the paired
differences with their paired 95 % intervals, which is what common random numbers are for.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from netkf_cli.core.lazy import pandas as pd
from pydantic import Field

from netkf_cli import engine
from netkf_cli.metrics.common import (fold_over, LABEL_COLUMNS, backends, channel_words, describe, GenericMetric, horizon_of,
                                      labels, math_text, n_runs_of, PaperRef, quantity_text, step_of)
from netkf_cli.core.stats import mean_se, proportion_stderr, wilson_interval
from netkf_cli.runtime.plotting import footnote, new_figure, paper_title, series_style
from netkf_cli.core.artefact import Artefact, RunContext
from netkf_cli.core.spec import PositiveFloat, PositiveInt

COLUMNS = ["estimator", "statistic", "M", "value", "stderr", "ci_low", "ci_high", "n", "heavy_tail", "k"] + LABEL_COLUMNS


class BothReducer:
    """Paired trace differences and P ≤ M counts in one pass over the same traces."""

    def __init__(self, M, steps):
        self.paired = engine.PairedReducer(steps)
        self.dist = engine.DistributionReducer(M, steps) if len(M) else None
        self.means_only = self.dist is None

    def update(self, stats, j, k, P, w=None):
        self.paired.update(stats, j, k, P, w)
        if self.dist is not None:
            self.dist.update(stats, j, k, P, w)


class Compare(GenericMetric):
    """``kind: compare`` — estimators side by side on common random numbers (mean tr P, Pr[P ≤ M], differences)."""

    kind: Literal["compare"]
    at: Literal["stationary"] | PositiveInt = Field("stationary", description="step k (stationary = montecarlo.horizon)")
    M: list[PositiveFloat] = Field([], description="bounds M (M·Iₙ) at which Pr[P_k ≤ M] is reported")
    paper: PaperRef | None = Field(None, description="the paper figure this reproduces (title only)")
    title: str = Field("", description="what the figure shows")

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        k = step_of(self.at, scenario.montecarlo.horizon)
        M = np.asarray(self.M, dtype=float)
        s, ests, st = self.simulate(scenario, ctx, BothReducer(M, [k]), [k], k)
        n = int(st["n"])
        labs = labels(ests)
        lab_cols = describe(scenario, s, ests, self.quantity)
        rows = []
        for j, lab in enumerate(labs):
            base = dict(k=k, ci_low=np.nan, ci_high=np.nan, **lab_cols[j])
            ms = engine.mean_summary(st, j, "tr")
            unreliable = bool(ms.unreliable[0])
            rows.append(dict(base, estimator=lab, statistic="mean_trace", M=np.nan, value=ms.mean[0], stderr=ms.stderr[0],
                             ci_low=ms.mean[0] - 1.96 * ms.stderr[0], ci_high=ms.mean[0] + 1.96 * ms.stderr[0],
                             n=n, heavy_tail=unreliable))
            if j > 0:
                nd = max(int(st[f"n_diff_{j}"][0]), 1)
                mean, se = (float(x) for x in mean_se(st[f"sum_diff_{j}"][0], st[f"sumsq_diff_{j}"][0], nd))
                rows.append(dict(base, estimator=lab, statistic=f"diff_mean_trace_vs_{labs[0]}", M=np.nan, value=mean,
                                 stderr=se, ci_low=mean - 1.96 * se, ci_high=mean + 1.96 * se, n=nd,
                                 heavy_tail=unreliable or bool(engine.mean_summary(st, 0, "tr").unreliable[0])))
            if len(M):
                cnt = st[f"count_{j}"][0]
                p = cnt / n
                lo, hi = wilson_interval(cnt, n)
                for i, m in enumerate(M):
                    rows.append(dict(base, estimator=lab, statistic="prob_leq_M", M=m, value=p[i],
                                     stderr=proportion_stderr(p[i], n), ci_low=lo[i], ci_high=hi[i], n=n, heavy_tail=False))
        return Artefact(pd.DataFrame(rows, columns=COLUMNS),
                        meta={"runs": n, "at": k, "estimators": labs, "reference": labs[0], "quantity": self.quantity,
                              "labels": dict(zip(labs, lab_cols)),
                              "backends": backends(scenario, s, ests, labs, n_runs_of(st), horizon_of(scenario, self), st, [k]),
                              "reduction": engine.reduction_used(st),
                              "common_random_numbers": "every estimator runs on the same sampled traces"})

    def plot(self, tables, scenario):
        t = fold_over(tables["main"], self.over)
        has_m = (t.statistic == "prob_leq_M").any()
        fig, axes = new_figure(ncols=2 if has_m else 1, width=5.4 if has_m else 7.0, height=4.6)
        axes = np.atleast_1d(axes)
        ax = axes[0]
        pk = quantity_text(self.quantity)
        means = t[t.statistic == "mean_trace"].reset_index(drop=True)
        ref = str(means.estimator.iloc[0])
        diffs = t[t.statistic.str.startswith("diff_mean_trace_vs_")].reset_index(drop=True)
        left_out = 0
        ax.axhline(0.0, color="0.4", lw=0.8, ls=":")
        for i, r in diffs.iterrows():
            sty = series_style(i + 1)
            if str(r.heavy_tail).lower() in ("true", "1") or not np.isfinite(r.value):
                left_out += 1
                continue
            ax.errorbar([i], [r.value], yerr=[[r.value - r.ci_low], [r.ci_high - r.value]], fmt=sty["marker"],
                        color=sty["color"], capsize=4, label=str(r.estimator))
        ax.set_xticks(range(len(diffs)))
        ax.set_xticklabels([str(e) for e in diffs.estimator], rotation=15, fontsize=9)
        ax.set_xlim(-0.6, max(len(diffs) - 0.4, 0.6))
        ax.set_xlabel(f"estimator (reference: {ref})")
        ax.set_ylabel(rf"paired difference $\mathrm{{E}}[\mathrm{{tr}}\,{pk} - \mathrm{{tr}}\,{pk}^{{\mathrm{{ref}}}}]$" "\n(95 % paired interval)")
        if has_m:
            ax2 = axes[1]
            for i, (lab, g) in enumerate(t[t.statistic == "prob_leq_M"].groupby("estimator", sort=False)):
                sty = series_style(i)
                yerr = np.clip(np.vstack([g.value - g.ci_low, g.ci_high - g.value]), 0, None)
                ax2.errorbar(g.M, g.value, yerr=yerr, fmt=sty["marker"], ls=sty["linestyle"], color=sty["color"],
                             capsize=2, label=lab)
            ax2.set_xscale("log")
            ax2.set_xlabel(r"$M$ (the bound is $M\,I_n$)")
            ax2.set_ylabel(rf"$\Pr[{pk} \leq M]$ (95 % Wilson)")
            ax2.legend(loc="lower right", fontsize=9)
        s = scenario.linear_system()
        what = self.title or f"{len(means)} estimators on common random numbers: n = {s.n} states, m = {s.m} outputs, " \
                             f"{channel_words(scenario.channel)}"
        fig.suptitle(paper_title(self.paper.topic if self.paper else None, self.paper.figure if self.paper else None, what))
        mtxt = ", ".join(f"{r.estimator}: {r.value:.4g} ± {1.96 * r.stderr:.2g}" for r in means.itertuples())
        note = (f"{self.quantity} ${pk}$ at k = {int(t.k.iloc[0])}, n = {int(t.n.max()):,} runs; {math_text(means.P0.iloc[0])}; "
                f"E[tr] (± 1.96 s.e.): {mtxt}")
        if left_out:
            note += f"; {left_out} unreliable differences not drawn (heavy-tailed or rare-event dominated, see CSV)"
        footnote(fig, note)
        return fig
