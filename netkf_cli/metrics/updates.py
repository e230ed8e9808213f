"""``kind: updates`` — expected filter recursions per step, for any estimator that reports how many it runs.

A channel metric of computation: per run, the average over k in (burn_in, horizon] of the number of
filter recursions R_k the estimator runs at time k (the buffered estimator of Shi, Xie & Murray 2009
re-runs its MKF from the oldest newly arrived packet: R_k = 1 + that packet's age, Prop. 3.1); one sample
per run, so the mean over runs has an exact standard error.

The hook: an estimator reports its counts by defining ``updates(system, trace, steps)``, a generator of
``(k, R_k)`` with R_k shaped (runs,) (:meth:`netkf_cli.estimators.buffered.BufferedEstimator.updates`).
Estimators in a list share the sampled traces. ``references`` add closed forms (``source =
closed_form``): the expected count (``shi_expected_updates``) and, beside it, closed-form Pr[P_k ≤ M]
for each ``M`` (``shi_buffer_probability``: certified exact value and Thm 3.8 bounds). With ``over`` the
figure draws against the grid's first path, one line per value of the other paths; the artefact also
writes the derived tables ``pairs`` and ``trend`` (:mod:`netkf_cli.metrics.derived`) for claims.
"""

from __future__ import annotations

from typing import ClassVar, Literal

import numpy as np
from netkf_cli.core.lazy import pandas as pd
from pydantic import Field

from netkf_cli.core.artefact import Artefact, RunContext
from netkf_cli.core.errors import ConfigError
from netkf_cli.metrics import derived
from netkf_cli.metrics.common import drawn_refs, GenericMetric, conventions_label, labels, math_text, needs, p0_label, PaperRef
from netkf_cli.runtime.montecarlo import run_chunked
from netkf_cli.runtime.plotting import MARKERS, PALETTE, footnote, legend_outside, new_figure, paper_title
from netkf_cli.core.spec import PositiveFloat
from netkf_cli.core.stats import heavy_tail_flag, mean_se, rare_event_flag

SERIES = "E[updates per step]"
COLUMNS = ["estimator", "quantity", "series", "M", "value", "stderr", "n", "nonfinite", "heavy_tail", "rare_event",
           "source", "reference", "P0", "conventions"]


class CountKernel:
    """Picklable chunk kernel: sample one trace batch, per estimator and run the average of R_k over ``steps``;
    additive statistics ``sum/sumsq/sum3/sum4/max_<j>`` and ``n``."""

    def __init__(self, system, channel, estimators, horizon: int, steps):
        self.system, self.channel, self.estimators = system, channel, list(estimators)
        self.horizon, self.steps = int(horizon), sorted(int(k) for k in steps)

    def __call__(self, rng: np.random.Generator, runs: int) -> dict:
        trace = self.channel.sample_trace(rng, runs, self.horizon)
        out: dict = {"n": np.asarray(runs)}
        for j, est in enumerate(self.estimators):
            acc = np.zeros(runs)
            for _, r in est.updates(self.system, trace, self.steps):
                acc += np.asarray(r, dtype=float)
            avg = acc / len(self.steps)
            for key, val in (("sum", avg.sum()), ("sumsq", (avg * avg).sum()), ("sum3", (avg**3).sum()),
                             ("sum4", (avg**4).sum())):
                out[f"{key}_{j}"] = float(val)
            out[f"max_{j}"] = float(avg.max()) if runs else 0.0
        return out


class Updates(GenericMetric):
    """``kind: updates`` — expected filter recursions per step (time average after a burn-in), per estimator."""

    draws_references: ClassVar[bool] = True

    kind: Literal["updates"]
    M: list[PositiveFloat] | None = Field(None, description="error bounds M for the references that give Pr[P_k ≤ M] "
                                                            "beside the counts (e.g. shi_buffer_probability)")
    log_x: bool = Field(False, description="logarithmic x axis (the over grid's first path)")
    x_label: str = Field("", description="x-axis label for the over grid (default: its first path)")
    paper: PaperRef | None = Field(None, description="the paper figure this reproduces (title only)")
    title: str = Field("", description="what the figure shows")

    def check(self, scenario) -> None:
        needs(scenario, "channel")
        ests = needs(scenario, "estimators")
        many = bool(scenario.estimators)
        for i, e in enumerate(ests):
            if not callable(getattr(e, "updates", None)):
                raise ConfigError.at(f"{'estimators[%d]' % i if many else 'estimator'}.kind",
                                     f"{e.kind} does not report how many filter recursions it runs per step "
                                     "(no updates() hook); the updates metric needs one (e.g. buffered)")
        system = _system_or_none(scenario)
        for i, e in enumerate(ests):  # what the hook refuses on this system (buffered: pair packets)
            hook = getattr(e, "check_updates", None)
            if system is not None and callable(hook):
                hook(system, f"estimators[{i}]" if many else "estimator")
        # burn_in < horizon: checked for every scenario (config.compat.check_scenario)

    def needs_per_run_covariance(self) -> bool:
        return False

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        s, ch, ests = needs(scenario, "system"), needs(scenario, "channel"), needs(scenario, "estimators")
        mc = scenario.montecarlo
        runs = ctx.mc_runs(scenario)
        ctx.total(runs)
        steps = list(range(mc.burn_in + 1, mc.horizon + 1))
        for e in ests:
            e.check(s, ch)
        st = run_chunked(CountKernel(s, ch, ests, mc.horizon, steps), runs, mc.chunk, mc.seed, stream=ctx.stream,
                         progress=ctx.progress, label=self.kind)
        labs = labels(ests)
        n = int(st["n"])
        rows = []
        for j, (e, lab) in enumerate(zip(ests, labs)):
            mean, se = (float(x) for x in mean_se(st[f"sum_{j}"], st[f"sumsq_{j}"], n))
            _, _, heavy = heavy_tail_flag(st[f"sum_{j}"], st[f"sumsq_{j}"], st[f"sum3_{j}"], st[f"sum4_{j}"], n, 0)
            rare = bool(rare_event_flag(st[f"sum_{j}"], st[f"max_{j}"], n))
            rows.append(dict(estimator=lab, quantity="updates", series=SERIES, M=np.nan, value=mean, stderr=se, n=n,
                             nonfinite=0, heavy_tail=bool(heavy), rare_event=rare, source="monte_carlo", reference="",
                             P0=p0_label(s), conventions=conventions_label(s, ch, e)))
        for r in self.reference_rows(scenario, labs):
            rows.append(dict(estimator=r.get("estimator", ""), quantity=r.get("quantity", "updates"), series=r["series"],
                             M=r.get("M", np.nan), value=r["value"], stderr=np.nan, n=0, nonfinite=0, heavy_tail=False,
                             rare_event=False, source="closed_form", reference=r["reference"], P0="", conventions=""))
        return Artefact(pd.DataFrame(rows, columns=COLUMNS),
                        meta={"runs": n, "estimators": labs, "references": list(self.references),
                              "average": f"per run over k = {steps[0]}…{steps[-1]} (burn-in {mc.burn_in})",
                              "updates": "filter recursions run at time k, reported by the estimator's updates() hook"})

    def finish_over(self, scenario, art: Artefact) -> Artefact:
        """The over grid's derived tables (pairs, trend) beside the main table, for claims."""
        extra = dict(art.extra_tables)
        extra.update(derived.tables(art.table, list(self.over or {})))
        return Artefact(art.table, meta=art.meta, extra_tables=extra)

    # --- the figure -------------------------------------------------------------------------------------
    def plot(self, tables, scenario):
        t = tables["main"]
        x = next(iter(self.over)) if self.over else None
        rest = [p for p in (self.over or {}) if p != x and p in t.columns]
        prob = t[t.M.notna()]
        Ms = sorted(prob.M.unique())
        groups = list(dict.fromkeys(map(tuple, t[rest].to_numpy()))) if rest else [()]
        ncols = 1 + (len(groups) if len(prob) else 0)
        fig, axes = new_figure(ncols=ncols, width=4.6, height=5.2)
        axes = np.atleast_1d(axes)
        ax = axes[0]

        def sel(df, g):
            m = np.ones(len(df), dtype=bool)
            for c, v in zip(rest, g):
                m &= (df[c] == v).to_numpy()
            return df[m]

        def gname(g):
            return ", ".join(f"{'.'.join(c.split('.')[1:])} = {v:g}" if isinstance(v, (int, float))
                             else f"{'.'.join(c.split('.')[1:])} = {v}" for c, v in zip(rest, g))

        upd = t[t.M.isna()]
        for i, g in enumerate(groups):
            d = sel(upd, g)
            colour = PALETTE[i % len(PALETTE)]
            for lab, h in d[d.source == "monte_carlo"].groupby("estimator", sort=False):
                h = h.sort_values(x) if x else h
                xs = h[x].astype(float) if x else np.arange(len(h))
                ax.errorbar(xs, h.value, yerr=1.96 * h.stderr, fmt=MARKERS[i % len(MARKERS)], ms=5, mfc="none",
                            color=colour, capsize=2, label=f"{lab}{', ' + gname(g) if g else ''}: Monte Carlo ± 1.96 s.e.")
            for (lab, name), h in d[d.source == "closed_form"].groupby(["estimator", "series"], sort=False):
                h = h.sort_values(x) if x else h
                xs = h[x].astype(float) if x else np.arange(len(h))
                ax.plot(xs, h.value, color=colour, ls="--", lw=1.2, label=f"{gname(g) + ': ' if g else ''}{name}")
        ax.set_ylabel("expected filter recursions per step")
        ax.set_title("computation")
        for ax_p, g in zip(axes[1:], groups if len(prob) else []):
            d = sel(prob, g)
            for i, m in enumerate(Ms):
                colour = PALETTE[i % len(PALETTE)]
                dm = d[d.M == m]
                ser = list(dict.fromkeys(dm.series))
                lo = [s for s in ser if s.startswith("lower")]
                hi = [s for s in ser if s.startswith("upper")]
                if lo and hi and x:
                    a, b = dm[dm.series == lo[0]].sort_values(x), dm[dm.series == hi[0]].sort_values(x)
                    ax_p.fill_between(a[x].astype(float).to_numpy(), a.value.to_numpy(float), b.value.to_numpy(float),
                                      color=colour, alpha=0.15, lw=0, label=f"M = {m:g}: bounds ({lo[0].split('(')[-1][:-1]})")
                for s_ in ser:
                    if s_ in lo + hi:
                        continue
                    h = dm[dm.series == s_].sort_values(x) if x else dm[dm.series == s_]
                    xs = h[x].astype(float) if x else np.arange(len(h))
                    ax_p.plot(xs, h.value, color=colour, marker=MARKERS[i % len(MARKERS)], ms=4, lw=1.3,
                              label=f"M = {m:g}: {s_}")
            ax_p.set_ylim(-0.02, 1.02)
            ax_p.set_ylabel(r"stationary $\Pr[P_k \leq M]$ (closed form)")
            ax_p.set_title("performance" + (f", {gname(g)}" if g else ""))
        for a in axes:
            if x:
                a.set_xlabel(self.x_label or x)
                if self.log_x:
                    a.set_xscale("log")
            if a.get_legend_handles_labels()[0]:
                legend_outside(a, loc="below", ncol=1)
        what = self.title or "expected filter recursions per step" + (f" against {self.x_label or x}" if x else "")
        fig.suptitle(paper_title(self.paper.topic if self.paper else None, self.paper.figure if self.paper else None,
                                 what), fontsize=11)
        mcr = t[t.source == "monte_carlo"]
        n = int(mcr.n.max()) if len(mcr) else 0
        footnote(fig, f"Monte Carlo: n = {n:,} runs per point, each averaged over k in (burn-in "
                      f"{scenario.montecarlo.burn_in}, horizon {scenario.montecarlo.horizon}]"
                 + (f"; dashed / lines: closed form ({', '.join(drawn_refs(t))})" if drawn_refs(t) else "")
                 + (f"\n{math_text(mcr.P0.iloc[0])}; {_shared(mcr.conventions)}" if len(mcr) else ""))
        return fig


def _system_or_none(scenario):
    """The scenario's system, or None where it has none or a bad one (reported by the scenario's own checks)."""
    try:
        return scenario.linear_system()
    except ConfigError:
        return None


def _shared(conventions: pd.Series) -> str:
    """The convention labels every point shares (those that vary over the grid are on the axes)."""
    parts = [str(c).split("; ") for c in conventions]
    return "; ".join(p for p in parts[0] if all(p in q for q in parts[1:]))
