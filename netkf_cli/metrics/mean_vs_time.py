"""``kind: mean_vs_time`` — E[P_k] against k (trace, λ_max or entries) for any channel and estimator(s).

Each step's mean is over independent runs, with its standard error; a step whose sample is
heavy-tailed (relative s.e. of the sample variance above ``tolerances.HEAVY_TAIL_RSE``, or any run
non-finite) or rare-event dominated (one run carries more than ``tolerances.RARE_EVENT_FRACTION``
of the sum) is flagged in the CSV (``heavy_tail``, ``rare_event``) and NOT drawn as a result (the
line is broken there, never bridged): the figure says how many were left out. Estimators in a list
share the sampled traces. ``quantity`` chooses P_{k|k}, P_{k+1|k} or P_{k−N|k}; the CSV says which,
from which P0, under which conventions.
"""

from __future__ import annotations

import warnings
from typing import ClassVar, Literal

import numpy as np
from netkf_cli.core.lazy import pandas as pd
from pydantic import Field

from netkf_cli import engine
from netkf_cli.core.stats import FLAG_REASONS, flag_reason
from netkf_cli.metrics.common import (fold_over, LABEL_COLUMNS, backends, conventions_note, grid_conventions, describe, GenericMetric, horizon_of, labels,
                                      math_text, n_runs_of, PaperRef, quantity_text)
from netkf_cli.runtime.plotting import footnote, legend_outside, new_figure, paper_title, series_style
from netkf_cli.core.artefact import Artefact, RunContext
from netkf_cli.core.spec import PositiveInt

ONE = {"trace": r"$\mathrm{tr}\,P_k$", "lambda_max": r"$\lambda_{\max}(P_k)$", "entries": r"$P_k$ entries"}
COLUMNS = ["k", "estimator", "series", "value", "stderr", "n", "nonfinite", "heavy_tail", "rare_event",
           "flag_reason"] + LABEL_COLUMNS
WHAT = {"trace": r"$\mathrm{E}[\mathrm{tr}\,P_k]$", "lambda_max": r"$\mathrm{E}[\lambda_{\max}(P_k)]$",
        "entries": r"$\mathrm{E}[P_k]$ entries"}


class MeanVsTime(GenericMetric):
    """``kind: mean_vs_time`` — E[P_k] against k with standard errors and heavy-tail flags."""

    draws_references: ClassVar[bool] = True

    kind: Literal["mean_vs_time"]
    of: Literal["trace", "lambda_max", "entries"] = Field("trace", description="tr P_k, λ_max(P_k), or every entry P_k[i, j]")
    every: PositiveInt | None = Field(None, description="report every this many steps (default: at most 200 points)")
    log_y: bool = Field(True, description="logarithmic y axis")
    paper: PaperRef | None = Field(None, description="the paper figure this reproduces (title only)")
    title: str = Field("", description="what the figure shows")

    def steps(self, horizon: int, first: int = 1) -> list[int]:
        every = self.every or max(1, -(-horizon // 200))
        ks = [k for k in range(every, horizon + 1, every) if k >= first]
        return ks if ks and ks[-1] == horizon else ks + [horizon]

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        first = max(e.first_step(self.quantity) for e in scenario.estimator_list())
        ks = self.steps(scenario.montecarlo.horizon, first)
        s, ests, st = self.simulate(scenario, ctx, engine.MomentReducer(ks, lmax=self.of == "lambda_max"), ks,
                                     scenario.montecarlo.horizon)
        labs = labels(ests)
        lab_cols = describe(scenario, s, ests, self.quantity)
        rows, warnings_ = [], []
        for j, lab in enumerate(labs):
            n = int(st["n"])
            tr_summary = engine.mean_summary(st, j, "tr")
            flags = dict(heavy=tr_summary.heavy_tail, rare=tr_summary.rare_event)
            bad = st[f"nonfinite_{j}"]
            reasons = [flag_reason(nonfinite=bad[i], sample=flags["heavy"][i], rare=flags["rare"][i]) for i in range(len(ks))]
            if bad.any():
                warnings_.append(f"{lab}: {int(bad.max())} of {n} runs non-finite at some step (excluded, step flagged)")
            if self.of in ("trace", "lambda_max"):
                ms = engine.mean_summary(st, j, "tr" if self.of == "trace" else "lmax")
                heavy = flags["heavy"]
                for i, k in enumerate(ks):
                    rows.append(dict(k=k, estimator=lab, series=self.of, value=ms.mean[i], stderr=ms.stderr[i], n=n,
                                     nonfinite=int(bad[i]), heavy_tail=bool(heavy[i]), rare_event=bool(flags["rare"][i]),
                                     flag_reason=reasons[i], **lab_cols[j]))
            else:
                heavy = flags["heavy"]
                m_ok = np.maximum(n - bad, 1)[:, None, None]
                mean = st[f"sum_P_{j}"] / m_ok
                var = np.maximum(st[f"sumsq_P_{j}"] / m_ok - mean**2, 0) * m_ok / np.maximum(m_ok - 1, 1)
                se = np.sqrt(var / m_ok)
                nn = mean.shape[1]
                for i, k in enumerate(ks):
                    for a in range(nn):
                        for b in range(a, nn):
                            rows.append(dict(k=k, estimator=lab, series=f"P[{a + 1},{b + 1}]", value=mean[i, a, b],
                                             stderr=se[i, a, b], n=n, nonfinite=int(bad[i]), heavy_tail=bool(heavy[i]),
                                             rare_event=bool(flags["rare"][i]), flag_reason=reasons[i], **lab_cols[j]))
        for w in warnings_:  # one line on the terminal, and in the manifest
            warnings.warn(w, stacklevel=2)
        cols = COLUMNS
        if self.references:  # closed forms at every step they give (k), or stationary (k empty)
            cols = COLUMNS + ["source", "reference"]
            for r in rows:
                r.update(source="monte_carlo", reference="")
            for r in self.reference_rows(scenario, labs):
                rows.append(dict(k=r.get("k", np.nan), estimator=r.get("estimator", ""), series=r["series"],
                                 value=r["value"], stderr=np.nan, n=0, nonfinite=0, heavy_tail=False, rare_event=False,
                                 flag_reason="",
                                 quantity=r.get("quantity", self.quantity), P0="", conventions="",
                                 source="closed_form", reference=r["reference"]))
        table = pd.DataFrame(rows, columns=cols)
        return Artefact(table, meta={"runs": int(st["n"]), "estimators": labs, "steps": f"{ks[0]}…{ks[-1]}",
                                     "quantity": self.quantity, "labels": dict(zip(labs, lab_cols)),
                              "backends": backends(scenario, s, ests, labs, n_runs_of(st), horizon_of(scenario, self), st, ks),
                              "reduction": engine.reduction_used(st),
                                     "heavy_tail_rule": f"relative s.e. of the sample variance > {engine.HEAVY_TAIL_RSE} "
                                                        f"or any non-finite run",
                                     "rare_event_rule": "one run carries more than half of the sum",
                                     "flag_reasons": FLAG_REASONS, "warnings": warnings_})

    def plot(self, tables, scenario):
        t = fold_over(tables["main"], self.over)
        ref = t[t.source == "closed_form"] if "source" in t else t.iloc[:0]
        t = t[t.source != "closed_form"] if "source" in t else t
        fig, ax = new_figure(width=7.4, height=4.6)
        for i, ((lab, ser), g) in enumerate(ref.fillna({"estimator": ""}).groupby(["estimator", "series"], sort=False)):
            g = g.sort_values("k")
            name = f"{lab}: {ser}" if lab else ser
            if g.k.notna().any():
                ax.plot(g.k, g.value, ls=(0, (5, 2 + i)), color="black", lw=1.1, label=f"{name} (closed form)", zorder=4)
            else:  # a stationary value: a horizontal line
                ax.axhline(float(g.value.iloc[0]), ls=(0, (5, 2 + i)), color="black", lw=1.0,
                           label=f"{name} (closed form, stationary)")
        one = len(t) > 0 and int(t.n.max()) == 1  # one run (e.g. a replayed recording): the sequence itself
        left_out = 0
        for i, ((lab, ser), g) in enumerate(t.groupby(["estimator", "series"], sort=False)):
            g = g.sort_values("k")
            bad = _flag(g.heavy_tail) | (_flag(g.rare_event) if "rare_event" in g else False) | ~np.isfinite(g.value)
            left_out += int(bad.sum())
            y = g.value.where(~bad)  # NaN at flagged steps: the line is broken there, never bridged
            se = g.stderr.where(~bad)
            sty = series_style(i)
            name = lab if self.of != "entries" else f"{lab}: {ser}"
            if y.notna().any():
                ax.plot(g.k, y, color=sty["color"], ls=sty["linestyle"], lw=1.3,
                        marker="." if y.notna().sum() < 3 else None,
                        label=name if one else f"{name} (band: ±1.96 s.e.)")
                if not one:
                    ax.fill_between(g.k, y - 1.96 * se, y + 1.96 * se, color=sty["color"], alpha=0.2, lw=0)
        if self.log_y:
            ax.set_yscale("log")
        ax.set_xlabel(r"time step $k$")
        label = quantity_text(self.quantity, ONE[self.of] if one else WHAT[self.of])
        ax.set_ylabel(label)
        what = self.title or f"{label} against $k$" + (" (one run)" if one else "")
        ax.set_title(paper_title(self.paper.topic if self.paper else None, self.paper.figure if self.paper else None, what))
        if ax.get_legend_handles_labels()[0]:
            legend_outside(ax, loc="below", ncol=1)
        else:
            ax.text(0.5, 0.5, "no reliable mean to draw:\nevery step is heavy-tailed at this sample size (see the CSV)",
                    transform=ax.transAxes, ha="center", va="center", fontsize=10)
        n = int(t.n.max()) if len(t) else 0
        lab0 = t.iloc[0] if len(t) else None
        labels_ = (f"{self.quantity} ${quantity_text(self.quantity)}$; {math_text(lab0.P0)}; "
                   f"{conventions_note(grid_conventions(t))}"
                   if lab0 is not None and "P0" in t else "")
        footnote(fig, ("one run: the covariance sequence itself" if one else f"n = {n:,} runs per step")
                 + (f"; {left_out} unreliable step mean{'s' if left_out != 1 else ''} not drawn (heavy-tailed or rare-event dominated: CSV columns "
                    f"heavy_tail, rare_event)" if left_out else "") + (f"\n{labels_}" if labels_ else ""))
        return fig


def _flag(col) -> np.ndarray:
    """A boolean CSV column read back (True/False, 1/0, 'true'/'false')."""
    return col.astype(str).str.lower().isin(["true", "1", "1.0"]).to_numpy()
