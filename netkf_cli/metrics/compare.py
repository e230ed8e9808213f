"""``kind: compare`` — several estimators on the same sampled traces (common random numbers).

For each estimator: E[tr P_k] at step ``at`` (standard error, heavy-tail flag) and, for each M
of ``M``, Pr[P_k ≤ M] with its Wilson interval; for every estimator after the first, the
paired difference E[tr P_k − tr P_k^{ref}] against the first (the reference), whose standard
error comes from the per-run differences — far smaller than the two separate standard errors
when the estimators see the same traces. An estimator compared with itself gives identical
columns and a difference of exactly 0.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import pandas as pd
from pydantic import Field

from netkf_cli import engine
from netkf_cli.metrics.common import GenericMetric, PaperRef, labels, step_of
from netkf_cli.montecarlo import proportion_stderr, wilson_interval
from netkf_cli.plotting import footnote, new_figure, paper_title, series_style
from netkf_cli.recipes.base import Artefact, RunContext
from netkf_cli.spec import PositiveFloat, PositiveInt

COLUMNS = ["estimator", "quantity", "M", "value", "stderr", "ci_low", "ci_high", "n", "heavy_tail", "k"]


class BothReducer:
    """Paired trace differences and P ≤ M counts in one pass over the same traces."""

    def __init__(self, M, steps):
        self.paired = engine.PairedReducer(steps)
        self.dist = engine.DistributionReducer(M, steps) if len(M) else None

    def update(self, stats, j, k, P):
        self.paired.update(stats, j, k, P)
        if self.dist is not None:
            self.dist.update(stats, j, k, P)


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
        rows = []
        base = dict(k=k, ci_low=np.nan, ci_high=np.nan)
        for j, lab in enumerate(labs):
            ms = engine.mean_summary(st, j, "tr")
            rows.append(dict(base, estimator=lab, quantity="mean_trace", M=np.nan, value=ms.mean[0], stderr=ms.stderr[0],
                             n=n, heavy_tail=bool(ms.heavy_tail[0])))
            if j > 0:
                nd = max(int(st[f"n_diff_{j}"][0]), 1)
                mean, se = engine_mean_se(st[f"sum_diff_{j}"][0], st[f"sumsq_diff_{j}"][0], nd)
                rows.append(dict(base, estimator=lab, quantity=f"diff_mean_trace_vs_{labs[0]}", M=np.nan, value=mean,
                                 stderr=se, n=nd, heavy_tail=bool(ms.heavy_tail[0])))
            if len(M):
                cnt = st[f"count_{j}"][0]
                p = cnt / n
                lo, hi = wilson_interval(cnt, n)
                for i, m in enumerate(M):
                    rows.append(dict(estimator=lab, quantity="prob_leq_M", M=m, value=p[i], stderr=proportion_stderr(p[i], n),
                                     ci_low=lo[i], ci_high=hi[i], n=n, heavy_tail=False, k=k))
        return Artefact(pd.DataFrame(rows, columns=COLUMNS),
                        meta={"runs": n, "at": k, "estimators": labs, "reference": labs[0],
                              "common_random_numbers": "every estimator runs on the same sampled traces"})

    def plot(self, tables, scenario):
        t = tables["main"]
        has_m = (t.quantity == "prob_leq_M").any()
        fig, axes = new_figure(ncols=2 if has_m else 1, width=5.2 if has_m else 6.8, height=4.4)
        axes = np.atleast_1d(axes)
        ax = axes[0]
        m = t[t.quantity == "mean_trace"].reset_index(drop=True)
        left_out = 0
        for i, r in m.iterrows():
            sty = series_style(i)
            heavy = str(r.heavy_tail).lower() in ("true", "1")
            if heavy or not np.isfinite(r.value):
                left_out += 1
                continue
            ax.errorbar([i], [r.value], yerr=[1.96 * r.stderr], fmt=sty["marker"], color=sty["color"], capsize=3,
                        label=f"{r.estimator}")
        ax.set_xticks(range(len(m)))
        ax.set_xticklabels([str(e) for e in m.estimator], rotation=15, fontsize=9)
        ax.set_xlabel("estimator")
        ax.set_ylabel(r"$\mathrm{E}[\mathrm{tr}\,P_k]$ (± 1.96 s.e.)")
        if has_m:
            ax2 = axes[1]
            for i, (lab, g) in enumerate(t[t.quantity == "prob_leq_M"].groupby("estimator", sort=False)):
                sty = series_style(i)
                yerr = np.clip(np.vstack([g.value - g.ci_low, g.ci_high - g.value]), 0, None)
                ax2.errorbar(g.M, g.value, yerr=yerr, fmt=sty["marker"], ls=sty["linestyle"], color=sty["color"],
                             capsize=2, label=lab)
            ax2.set_xscale("log")
            ax2.set_xlabel(r"$M$ (the bound is $M\,I_n$)")
            ax2.set_ylabel(r"$\Pr[P_k \leq M]$ (95 % Wilson)")
            ax2.legend(loc="lower right", fontsize=9)
        what = self.title or "estimators on common random numbers"
        fig.suptitle(paper_title(self.paper.topic if self.paper else None, self.paper.figure if self.paper else None, what))
        note = f"k = {int(t.k.iloc[0])}, n = {int(t.n.max()):,} runs, reference = {m.estimator.iloc[0]}"
        if left_out:
            note += f"; {left_out} heavy-tailed means not drawn (see CSV)"
        footnote(fig, note)
        return fig


def engine_mean_se(s1: float, s2: float, n: int) -> tuple[float, float]:
    """Sample mean and standard error from Σx, Σx² over n samples."""
    mean = s1 / n
    var = max(s2 / n - mean * mean, 0.0) * n / max(n - 1, 1)
    return float(mean), float(np.sqrt(var / n))
