"""``kind: time_average`` — stationary statistics of P_k: the time average over k in (burn_in, horizon].

Per run, the average over the steps k = burn_in + 1 … horizon of tr P_k (series ``E[tr P]``) and,
when ``M`` is given, of 1[P_k ≤ M·I] (series ``Pr[P<=M]``: the stationary Pr[P_k ≤ M] when the chain
is ergodic); one sample per run, so the mean over runs has an exact standard error. ``quantities``
reports several covariances in one pass (predicted P_{k+1|k}, filtered P_{k|k}, a smoother's
P_{k−N|k}): each estimator reports those it offers, on the same traces (common random numbers).

With ``over`` (a grid of a channel, estimator or system parameter) the figure draws every series
against the grid's first path; ``references`` adds closed-form rows (``source = closed_form``) drawn
as dashed lines beside the Monte Carlo. Unreliable means (heavy-tailed, rare-event dominated or any
run non-finite) are flagged in the CSV and drawn hollow, off the line.

``statistic: norm_of_mean`` reports ‖E P̄‖₂ instead (series ``‖E P‖``): the spectral norm of the MEAN
matrix of the per-run P̄ (P̄ = the time average over the steps, or P_k itself with ``at: k``), with a
delta-method standard error and an eigen-gap flag (:mod:`netkf_cli.metrics.norm_of_mean`) — Mostofi &
Murray 2009's ‖E P[300]‖ (Fig. 6, Sec. 4.2; eq. 21 for k → ∞). Its ``references`` must give the same
quantity (rows marked ``statistic: norm_of_mean``), else the config is refused.
"""

from __future__ import annotations

import re
from typing import ClassVar, Literal

import numpy as np
from netkf_cli.core.lazy import pandas as pd
from pydantic import Field, model_validator

from netkf_cli import engine
from netkf_cli.linalg import kalman
from netkf_cli.core.artefact import Artefact, RunContext
from netkf_cli.core.errors import ConfigError
from netkf_cli.metrics import derived
from netkf_cli.metrics import norm_of_mean as nm
from netkf_cli.metrics.common import (drawn_refs, LABEL_COLUMNS, backends, conventions_note, grid_conventions, describe, GenericMetric,
                                      kf_tail_exponent, labels, math_text, PaperRef, Quantity)
from netkf_cli.core.spec import PositiveInt
from netkf_cli.runtime.plotting import LINESTYLES, MARKERS, MIN_FONT_PT, PALETTE, footnote, legend_outside, new_figure, paper_title
from netkf_cli.core.stats import FLAG_REASONS, flag_reason, heavy_tail_flag, mean_se, rare_event_flag
from netkf_cli.core.tolerances import EIGEN_GAP_SE, ROUNDOFF_VARIANCE

TRACE, PROB, NORM = "E[tr P]", "Pr[P<=M]", "‖E P‖"
AXES_IN = 6.0
"""Inches a time_average figure keeps for its axes with their tick and axis labels, beside the legend (``plot``)."""
M4_ROUNDING = 1e-3
"""Largest relative rounding error of the 4th central moment from raw power sums, ≈ eps·(mean/sd)⁴, accepted
before the power sums are taken again about the mean (:func:`_cancelling`)."""
COLUMNS = ["estimator", "quantity", "series", "M", "value", "stderr", "n", "nonfinite", "heavy_tail", "rare_event",
           "flag_reason", "source", "reference"] + LABEL_COLUMNS[1:]


class TimeAverage(GenericMetric):
    """``kind: time_average`` — time-averaged E[tr P_k] (and Pr[P_k ≤ M]) after a burn-in, per estimator and quantity."""

    draws_references: ClassVar[bool] = True

    kind: Literal["time_average"]
    quantities: list[Quantity] | None = Field(None, description="several quantities in one pass (default: `quantity`); "
                                                                "each estimator reports those it offers")
    M: float | list[float] | None = Field(None, description="also the time-averaged Pr[P_k ≤ M·I] (PSD order) for each M")
    statistic: Literal["mean_trace", "norm_of_mean"] = Field(
        "mean_trace", description="mean_trace: E[tr P̄] (series E[tr P]); norm_of_mean: ‖E P̄‖₂, the spectral norm "
                                  "of the mean matrix with a delta-method s.e. (series ‖E P‖; Mostofi & Murray 2009 "
                                  "Fig. 6's ‖E P[300]‖)")
    at: PositiveInt | None = Field(None, description="one step k instead of the time average over (burn_in, horizon] "
                                                     "(P̄ = P_k; needs burn_in 0 and k ≤ horizon)")
    log_x: bool = Field(False, description="logarithmic x axis (the over grid's first path)")
    log_y: bool = Field(True, description="logarithmic y axis for E[tr P]")
    x_label: str = Field("", description="x-axis label for the over grid (default: its first path)")
    paper: PaperRef | None = Field(None, description="the paper figure this reproduces (title only)")
    title: str = Field("", description="what the figure shows")

    @model_validator(mode="after")
    def _m_positive(self):
        ms = [] if self.M is None else np.atleast_1d(np.asarray(self.M, dtype=float))
        if any(not (m > 0 and np.isfinite(m)) for m in ms):
            raise ValueError(f"M must be finite and > 0, got {self.M}")
        if self.quantities is not None and (not self.quantities or len(set(self.quantities)) < len(self.quantities)):
            raise ValueError(f"quantities: a non-empty list without repeats, got {self.quantities}")
        if self.statistic == "norm_of_mean" and self.M is not None:
            raise ValueError("M (Pr[P_k ≤ M]) is a per-run statistic: give it with statistic: mean_trace, "
                             "not norm_of_mean (a statistic of the mean matrix)")
        return self

    def needs_per_run_covariance(self) -> bool:
        return self.M is not None

    def check(self, scenario) -> None:
        super().check(scenario)
        mc = scenario.montecarlo
        if self.at is not None:
            if self.at > mc.horizon:
                raise ConfigError.at("analysis.at", f"must be ≤ montecarlo.horizon = {mc.horizon}, got {self.at}")
            if mc.burn_in:
                raise ConfigError.at("montecarlo.burn_in", f"must be 0 with analysis.at = {self.at} (the statistic "
                                                           f"is of P at that one step), got {mc.burn_in}")
        # burn_in < horizon: checked for every scenario (config.compat.check_scenario)
        for e in scenario.estimator_list():
            for q in self.quantity_list():
                if q in getattr(e, "quantities", ("filtered",)) and e.first_step(q) > (self.at or mc.horizon):
                    raise ConfigError.at("montecarlo.horizon", f"{e.kind} defines {q} from step {e.first_step(q)} on "
                                                               f"({kalman.SYMBOL[q]}); the horizon is {mc.horizon}")

    def average_steps(self, mc) -> list[int]:
        """The steps averaged per run: (burn_in, horizon], or [at]."""
        return [int(self.at)] if self.at is not None else list(range(mc.burn_in + 1, mc.horizon + 1))

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        mc = scenario.montecarlo
        qs = self.quantity_list()
        steps = self.average_steps(mc)
        if self.statistic == "norm_of_mean":
            return self._compute_norm(scenario, ctx, qs, steps)
        Ms = None if self.M is None else np.atleast_1d(np.asarray(self.M, dtype=float))
        s, ests, st = self.simulate(scenario, ctx, engine.StationaryReducer(steps, Ms), steps, mc.horizon,
                                    quantities=qs)
        shift = _cancelling(st)
        if shift:  # runs that differ by ~1e-5 relative: the same runs again, power sums about the first pass's mean
            s, ests, st = self.simulate(scenario, ctx, engine.StationaryReducer(steps, Ms, shift), steps, mc.horizon,
                                        quantities=qs)
        labs = labels(ests)
        n = int(st["n"])
        rows, theory_flags = [], {}
        for e, lab, q, c, lab_cols, bad, m_ok in _cells(scenario, s, ests, st, qs, "sum_avg"):
            c0 = shift.get(c, 0.0)  # the sums are of (a − c0): shift-invariant variance and 4th moment
            dmean, se = (float(x) for x in mean_se(st[f"sum_avg_{c}"], st[f"sumsq_avg_{c}"], m_ok))
            mean = c0 + dmean
            _, _, heavy = heavy_tail_flag(st[f"sum_avg_{c}"], st[f"sumsq_avg_{c}"], st[f"sum3_avg_{c}"],
                                          st[f"sum4_avg_{c}"], m_ok, bad)
            rare = bool(rare_event_flag(st[f"sum_avg_{c}"] + m_ok * c0, st[f"max_avg_{c}"], m_ok))
            base = dict(estimator=lab, quantity=q, n=n, nonfinite=bad, source="monte_carlo", reference="",
                        P0=lab_cols["P0"], conventions=lab_cols["conventions"])
            by_theory = _heavy_by_theory(s, scenario.channel, e, lab, theory_flags)
            reason = flag_reason(nonfinite=bad, sample=heavy, theory=by_theory, rare=rare)
            heavy = heavy or by_theory  # E[(tr P)²] = ∞: the sample's variance (and s.e.) mean nothing
            rows.append(dict(base, series=TRACE, M=np.nan, value=mean if bad == 0 else np.inf, stderr=se,
                             heavy_tail=bool(heavy), rare_event=rare, flag_reason=reason))
            if Ms is not None:  # a non-finite run counts as not ≤ M: the probability is over every run
                pm, pse = mean_se(st[f"sum_ind_{c}"], st[f"sumsq_ind_{c}"], n)
                for i, m in enumerate(Ms):
                    rows.append(dict(base, series=PROB, M=float(m), value=float(pm[i]), stderr=float(pse[i]),
                                     heavy_tail=False, rare_event=False, flag_reason=""))
        for r in self.reference_rows(scenario, labs):
            rows.append(dict(estimator=r.get("estimator", ""), quantity=r.get("quantity", qs[0]),
                             series=r["series"], M=r.get("M", np.nan), value=r["value"], stderr=np.nan, n=0,
                             nonfinite=0, heavy_tail=False, rare_event=False, flag_reason="", source="closed_form",
                             reference=r["reference"], P0="", conventions=""))
        table = pd.DataFrame(rows, columns=COLUMNS)
        return Artefact(table, meta={"runs": n, "estimators": labs, "quantities": qs,
                                     "average": self._average_text(steps),
                                     "backends": backends(scenario, s, ests, labs, n, mc.horizon, st, steps),
                                     "reduction": engine.reduction_used(st),
                                     "references": list(self.references),
                                     "heavy_tail_rule": f"relative s.e. of the sample variance > {engine.HEAVY_TAIL_RSE}, "
                                                        f"any non-finite run, or (kf and the smoother on i.i.d. or "
                                                        f"Gilbert–Elliott loss) the theoretical tail exponent ≥ −2",
                                     "heavy_tail_by_theory": theory_flags, "flag_reasons": FLAG_REASONS})

    def _average_text(self, steps) -> str:
        if self.at is not None:
            return f"per run P at k = {self.at} (no time average)"
        return f"per run over k = {steps[0]}…{steps[-1]} (burn-in {steps[0] - 1})"

    def _compute_norm(self, scenario, ctx: RunContext, qs, steps) -> Artefact:
        """``statistic: norm_of_mean``: ‖E P̄‖₂ per estimator and quantity, delta-method s.e. (norm_of_mean)."""
        mc = scenario.montecarlo
        s, ests, st = self.simulate(scenario, ctx, nm.MeanMatrixReducer(steps), steps, mc.horizon, quantities=qs)
        # a column whose runs agree to rounding (scenario 2 with an invertible C: exact per run) needs no second
        # pass: its s.e. is 0 and it has no tail (stats' rule for such a sample), whatever the 4th moment says
        shift = {c: nm.packed_mean(st, c) for c in _cancelling(st) if not _constant(st, c)}
        if shift:  # runs that agree to ~1e-5 relative: the same runs again, sums about the first pass's mean
            s, ests, st = self.simulate(scenario, ctx, nm.MeanMatrixReducer(steps, shift), steps, mc.horizon,
                                        quantities=qs)
        labs = labels(ests)
        n = int(st["n"])
        rows, theory_flags = [], {}
        for e, lab, q, c, lab_cols, bad, m_ok in _cells(scenario, s, ests, st, qs, "sum_T"):
            r = nm.norm_of_mean(st, c, shift)
            _, _, heavy = heavy_tail_flag(st[f"sum_avg_{c}"], st[f"sumsq_avg_{c}"], st[f"sum3_avg_{c}"],
                                          st[f"sum4_avg_{c}"], m_ok, bad)
            tr0 = float(np.trace(nm.unpack(shift[c], int(st[f"max_dim_{c}"])))) if c in shift else 0.0
            rare = bool(rare_event_flag(st[f"sum_avg_{c}"] + m_ok * tr0, st[f"max_avg_{c}"], m_ok))
            by_theory = _heavy_by_theory(s, scenario.channel, e, lab, theory_flags)
            reason = flag_reason(nonfinite=bad, sample=heavy, theory=by_theory, rare=rare)
            heavy = heavy or by_theory  # E[(tr P)²] = ∞: the sample's variance (and s.e.) mean nothing
            if r["eigen_gap"]:
                reason = "+".join(x for x in (reason, "eigen_gap") if x)
            rows.append(dict(estimator=lab, quantity=q, series=NORM, M=np.nan,
                             value=r["value"] if bad == 0 else np.inf, stderr=r["stderr"], n=n, nonfinite=bad,
                             heavy_tail=bool(heavy), rare_event=rare, flag_reason=reason, source="monte_carlo",
                             reference="", P0=lab_cols["P0"], conventions=lab_cols["conventions"],
                             eigen_gap=r["gap"]))
        for r in self.reference_rows(scenario, labs):
            if r.get("statistic") != "norm_of_mean":
                raise ConfigError.at("analysis.references", f"{r['reference']!r} does not give ‖E P‖ (statistic: "
                                                            f"norm_of_mean); drop it or use statistic: mean_trace")
            rows.append(dict(estimator=r.get("estimator", ""), quantity=r.get("quantity", qs[0]),
                             series=r["series"], M=np.nan, value=r["value"], stderr=np.nan, n=0,
                             nonfinite=0, heavy_tail=False, rare_event=False, flag_reason="", source="closed_form",
                             reference=r["reference"], P0="", conventions="", eigen_gap=np.nan))
        table = pd.DataFrame(rows, columns=COLUMNS + ["eigen_gap"])
        return Artefact(table, meta={"runs": n, "estimators": labs, "quantities": qs, "statistic": self.statistic,
                                     "average": self._average_text(steps),
                                     "backends": backends(scenario, s, ests, labs, n, mc.horizon, st, steps),
                                     "reduction": engine.reduction_used(st),
                                     "references": list(self.references),
                                     "norm_of_mean": "‖E P̄‖₂ = λ_max of the mean of the per-run packed P̄; s.e. by the "
                                                     "delta method (gradient u uᵀ); eigen_gap column = λ1 − λ2 of the "
                                                     f"mean, flagged when below {EIGEN_GAP_SE:g} s.e. of the (u1, ui) block",
                                     "heavy_tail_rule": f"of tr P̄: relative s.e. of the sample variance > "
                                                        f"{engine.HEAVY_TAIL_RSE}, any non-finite run, or (kf and the "
                                                        f"smoother on i.i.d. or Gilbert–Elliott loss) the theoretical "
                                                        f"tail exponent ≥ −2",
                                     "heavy_tail_by_theory": theory_flags,
                                     "flag_reasons": {**FLAG_REASONS, "eigen_gap": nm.EIGEN_GAP_REASON}})

    def finish_over(self, scenario, art: Artefact) -> Artefact:
        """The over grid's derived tables (``pairs``: MC vs MC / closed form at each point; ``trend``: along each
        path) beside the main table, for claims (:mod:`netkf_cli.metrics.derived`)."""
        return Artefact(art.table, meta=art.meta,
                        extra_tables={**art.extra_tables, **derived.tables(art.table, list(self.over or {}))})

    # --- the figure -------------------------------------------------------------------------------------
    def plot(self, tables, scenario):
        t = tables["main"].copy()
        t["estimator"] = t["estimator"].fillna("").astype(str)  # a reference for every estimator: ""
        x = next(iter(self.over)) if self.over else None
        main = NORM if self.statistic == "norm_of_mean" else TRACE
        panels = [main] + ([PROB] if (t.series == PROB).any() else [])
        fig, axes = new_figure(nrows=len(panels), width=10.5, height=4.4 * len(panels))
        axes = np.atleast_1d(axes)
        flagged = 0
        undrawn: list[str] = []
        for ax, series in zip(axes, panels):
            log = series == main and self.log_y and bool((t[(t.series == main)].value.replace(np.inf, np.nan) > 0).all())
            f, u = self._panel(ax, t, series, x, log)
            flagged += f
            undrawn += u
            ax.set_ylabel(self._ylabel(series))
            if log:
                ax.set_yscale("log")
            if x is not None:
                ax.set_xlabel(self.x_label or x)
                if self.log_x:
                    ax.set_xscale("log")
            if ax.get_legend_handles_labels()[0]:
                legend_outside(ax, loc="right", fontsize=MIN_FONT_PT)
        # a long legend (many closed forms, Fusion Fig. 3) needs a taller panel, or it runs into the footnote
        rows = max((len(ax.get_legend_handles_labels()[0]) for ax in axes), default=0)
        # a wide legend (long closed-form labels, Leong's eq. (8) guarantee) would leave the axes a third of the
        # width: the figure grows to keep AXES_IN inches for the axes and their labels beside the widest legend
        legends = [ax.get_legend() for ax in axes if ax.get_legend() is not None]
        r = fig.canvas.get_renderer()
        legend_in = max((lg.get_window_extent(r).width / fig.dpi for lg in legends), default=0.0)
        fig.set_size_inches(max(fig.get_size_inches()[0], AXES_IN + legend_in + 0.3),
                            len(panels) * max(4.4, 1.9 + 0.25 * rows))
        what = self.title or ("stationary " + ("statistics against " + (self.x_label or x) if x else "statistics"))
        fig.suptitle(paper_title(self.paper.topic if self.paper else None, self.paper.figure if self.paper else None,
                                 what), fontsize=11)
        mcr = t[t.source == "monte_carlo"]
        n = int(mcr.n.max()) if len(mcr) else 0
        note = grid_conventions(mcr)
        per_run = (f"each run's P at k = {self.at}" if self.at is not None else
                   f"each averaged over k in (burn-in {scenario.montecarlo.burn_in}, horizon {scenario.montecarlo.horizon}]")
        footnote(fig, f"Monte Carlo: n = {n:,} runs, {per_run}; error bars ±1.96 s.e."
                 + ("; ‖E P‖₂ = λ_max of the mean matrix, s.e. by the delta method" if main == NORM else "")
                 + (f"; {flagged} unreliable mean{'s' if flagged != 1 else ''} drawn hollow, off the line (CSV heavy_tail / rare_event / flag_reason)" if flagged else "")
                 + (f"; dashed, hollow markers on top: closed form ({', '.join(drawn_refs(t))})" if drawn_refs(t) else "")
                 + (f"; not drawn (≤ 0 on the log axis): {'; '.join(undrawn)}" if undrawn else "")
                 + (f"\n{math_text(mcr.P0.iloc[0])}; {conventions_note(note)}" if len(mcr) else ""))
        return fig

    def _ylabel(self, series: str) -> str:
        when = f" at $k$ = {self.at}" if self.at is not None else ""
        avg = "" if self.at is not None else "time-averaged "
        if series == NORM:
            return avg + r"$\|\mathrm{E}\,P\|_2$" + when
        if series == TRACE:
            return avg + r"$\mathrm{E}[\mathrm{tr}\,P]$" + when
        return avg + r"$\Pr[P \leq M]$" + when

    def _panel(self, ax, t, series, x, log: bool = False) -> tuple[int, list[str]]:
        """Draw one panel; (the number of unreliable means drawn hollow, the closed forms a log axis cannot
        show: every value ≤ 0, e.g. Leong's max |g(n) − 1| = 0 — said in the footnote, not in the legend)."""
        mc = t[(t.source == "monte_carlo") & (t.series == series)]
        ref = t[(t.source == "closed_form") & ((t.series != PROB) if series in (TRACE, NORM) else (t.M.notna()))]
        if series in (TRACE, NORM):
            ref = ref[ref.M.isna()]
        keys = list(dict.fromkeys(zip(mc.estimator, mc.quantity, mc.M.fillna(-1))))
        conv_of = dict(zip(mc.estimator, mc.conventions)) if "conventions" in mc else {}
        colour_of = {}
        flagged = 0
        undrawn: list[str] = []
        for i, (lab, q, m) in enumerate(keys):
            g = mc[(mc.estimator == lab) & (mc.quantity == q) & (mc.M.fillna(-1) == m)]
            colour = PALETTE[i % len(PALETTE)]
            colour_of.setdefault(lab, colour)
            colour_of.setdefault((lab, q), colour)
            colour_of[(lab, q, m)] = colour  # a Pr[P <= M] reference takes its M's colour
            name = f"{lab} · {_sym(q, conv_of.get(lab))}" + ("" if m < 0 else f", M = {m:g}")
            bad = _unreliable(g)
            flagged += int(bad.sum())
            if x is None:
                xs = np.full(len(g), i, dtype=float)
            else:
                g = g.sort_values(x)
                bad = _unreliable(g)
                xs = g[x].astype(float).to_numpy()
            y = np.where(bad, np.nan, g.value.to_numpy(dtype=float))
            ax.errorbar(xs, y, yerr=1.96 * np.where(bad, np.nan, g.stderr.to_numpy(dtype=float)),
                        marker=MARKERS[i % len(MARKERS)], ms=4, capsize=2, color=colour, lw=1.2,
                        ls="-" if x is not None else "none",
                        label=f"{name} (Monte Carlo)" if np.isfinite(y).any() else "_nolegend_")  # none drawn: no entry
            if bad.any() and np.isfinite(g.value.to_numpy()[bad]).any():
                ax.plot(xs[bad], g.value.to_numpy()[bad], ls="none", marker="o", ms=7, mfc="none", color=colour,
                        label=f"{name}: unreliable (flagged in the CSV)")
        several_q = ref.quantity.nunique() > 1
        drawn: dict = {}  # references drawn per (estimator, quantity): each its own dash pattern
        for (lab, q, name), g in ref.groupby(["estimator", "quantity", "series"], sort=False):
            m_ref = g.M.iloc[0] if g.M.nunique(dropna=False) == 1 and pd.notna(g.M.iloc[0]) else -1
            colour = colour_of.get((lab, q, m_ref), colour_of.get((lab, q), colour_of.get(lab, "black")))
            j = drawn[(lab, q)] = drawn.get((lab, q), -1) + 1
            dash = LINESTYLES[1:][j % (len(LINESTYLES) - 1)]
            name = f"{name} · {_sym(q, conv_of.get(lab))}" if several_q else name
            vals = g.value.to_numpy(dtype=float)
            if not np.isfinite(vals).any():
                continue
            if log and not (vals > 0).any():
                shown = sorted(set(float(v) for v in vals))
                undrawn.append(math_text(f"{name} = {shown[0]:.3g}" + (" at every point" if len(shown) == 1 and x else "")
                                         if len(shown) == 1 else f"{name} in [{shown[0]:.3g}, {shown[-1]:.3g}]"))
                continue
            # on top of the Monte Carlo (zorder) with hollow markers: a closed form that agrees with the
            # Monte Carlo to the last digit (Fig. 6's scenario 2) stays visible around the filled points
            style = dict(ls=dash, color=colour, lw=1.1, marker=REF_MARKERS[j % len(REF_MARKERS)], ms=8, mfc="none",
                         mew=1.3, zorder=3, label=math_text(f"{(lab + ': ') if lab else ''}{name}"))
            if x is None:
                ax.plot(np.arange(len(keys)), np.full(len(keys), vals[0]), **style)
            else:
                g = g.sort_values(x)
                ax.plot(g[x].astype(float), g.value.astype(float), markevery=max(1, len(g) // 25), **style)
        if x is None and keys:
            ax.set_xticks(range(len(keys)))
            ax.set_xticklabels([f"{lab}\n{_sym(q, conv_of.get(lab))}" + ("" if m < 0 else f"\nM = {m:g}")
                                for lab, q, m in keys], fontsize=MIN_FONT_PT)
        return flagged, undrawn


REF_MARKERS = ("D", "s", "v", "p")  # closed forms: hollow, unlike the Monte Carlo's filled MARKERS and the flagged "o"


def _unreliable(g) -> np.ndarray:
    """Rows not drawn on the line: heavy-tailed, rare-event dominated, non-finite, or (‖E P‖) a degenerate top
    eigenvalue (flag_reason eigen_gap: the delta-method s.e. is invalid)."""
    gap = g.flag_reason.astype(str).str.contains("eigen_gap").to_numpy()
    return (g.heavy_tail.astype(bool).to_numpy() | g.rare_event.astype(bool).to_numpy()
            | ~np.isfinite(g.value.to_numpy()) | gap)


def _sym(q: str, conventions: str | None = None) -> str:
    """The quantity's symbol in mathtext; ``smoothed`` as the estimator's own P_{k−N|k} where its conventions
    name it (``smoothed: P_{k-2|k} (lag N = 2)``), so a legend says which lag it draws."""
    sym = kalman.SYMBOL.get(q, q)
    if q == "smoothed" and isinstance(conventions, str):
        m = re.search(r"smoothed: (P_\{[^}]*\})", conventions)
        if m:
            sym = m.group(1)
    return f"${sym}$".replace("|", r" \mid ")  # mathtext draws a bare | in a subscript as an l


def _constant(st: dict, c: int) -> bool:
    """Whether column c's per-run tr P̄ are one number up to rounding (variance ≤ ``ROUNDOFF_VARIANCE`` · mean²)."""
    m = max(int(st["n"]) - int(st[f"nonfinite_{c}"]), 1)
    mu = float(st[f"sum_avg_{c}"]) / m
    return float(st[f"sumsq_avg_{c}"]) / m - mu * mu <= ROUNDOFF_VARIANCE * mu * mu


def _heavy_by_theory(system, channel, est, lab: str, theory_flags: dict) -> bool:
    """True where the theoretical tail exponent φ ≥ −2 (kf and the smoother on i.i.d. or Gilbert–Elliott loss,
    Mo & Sinopoli 2012: E[(tr P)²] = ∞); why is recorded in ``theory_flags[lab]`` (the manifest)."""
    phi, why = kf_tail_exponent(system, channel, est)
    if phi is None or phi < -2.0:
        return False
    theory_flags[lab] = (f"tail exponent φ = {phi:.3g} ≥ −2 (Mo & Sinopoli 2012: E[(tr P)²] = ∞"
                         + (", E[tr P] = ∞" if phi >= -1.0 else "") + f"; {why})")
    return True


def _cells(scenario, system, ests, st, qs, key: str):
    """Every reported (estimator, quantity) column of a pass: (estimator, label, quantity, column, its label
    columns, non-finite runs, finite runs ≥ 1). A column without ``<key>_<column>`` is a quantity the
    estimator does not report."""
    n = int(st["n"])
    for j, (e, lab) in enumerate(zip(ests, labels(ests))):
        for qi, q in enumerate(qs):
            c = engine.column(j, qi, len(qs))
            if f"{key}_{c}" in st:
                bad = int(st[f"nonfinite_{c}"])
                yield e, lab, q, c, describe(scenario, system, [e], q)[0], bad, max(n - bad, 1)


def _cancelling(st: dict) -> dict:
    """Per column whose raw 4th power sums lose the 4th central moment to cancellation (eps·(mean/sd)⁴ >
    ``M4_ROUNDING``: runs that agree to ~1e-4 relative, e.g. fusion at small μ_Q), the shift = its mean.

    The statistics are shift-invariant, so a second pass over the same runs (same streams and chunks) about
    this constant gives the same mean and variance and a 4th moment with its digits; a column that does not
    cancel is not run twice."""
    n = int(st["n"])
    out = {}
    for key in st:
        if not key.startswith("sum_avg_"):
            continue
        c = int(key.rsplit("_", 1)[1])
        m_ok = n - int(st[f"nonfinite_{c}"])
        if m_ok < 2:
            continue
        mu = float(st[key]) / m_ok
        var = max(float(st[f"sumsq_avg_{c}"]) / m_ok - mu * mu, 0.0)
        if not np.isfinite(mu) or mu == 0.0:
            continue
        if var > 0.0 and np.finfo(float).eps * (mu * mu / var) ** 2 > M4_ROUNDING:
            out[c] = mu
    return out
