"""``kind: state_error`` — the estimators' actual errors beside the covariances they report (NEES), and trajectories.

The engine simulates the true state behind every channel trace (:mod:`netkf_cli.engine.state`:
x_0 ~ N(0, P_{0|0}), x_{k+1} = A x_k + w_k, y_k = C x_k + v_k, the receiver's signal per the channel's
packet model) and runs every estimator's ``estimates`` on the same runs (common random numbers). Per
estimator and step k it reports

* ``empirical`` — tr E[(x − x̂)(x − x̂)ᵀ] = E‖x − x̂‖², the empirical error covariance's trace (± s.e.);
* ``reported``  — E[tr P], the mean of the covariance the estimator reports (± s.e.);
* ``nees``      — the mean normalized estimation error squared eᵀ P⁺ e (± s.e.), beside ``expected`` =
  E[rank P] (= n for a nonsingular P): if P is each run's error covariance and the error Gaussian,
  eᵀ P⁺ e ~ χ²(rank P). A mean NEES off its expectation by more than 5 s.e. says P is not the error
  covariance (an optimistic or a pessimistic P, a biased estimate);

and in ``<name>_summary.csv`` the averages over the window k in (``window_from``, horizon] of the
three (one sample per run: exact s.e.), the paired difference of the windowed E‖e‖² against the first
estimator (common random numbers), and per estimator the fraction of steps at which
|NEES − expected| ≤ 5 s.e. and |E‖e‖² − E tr P| ≤ 5 s.e. (paired): ``nees_consistent_fraction``,
``empirical_equals_reported_fraction``. ``trajectories: K`` draws the first K runs of the trajectory
stream :data:`TRAJECTORY_STREAM` + s (s = the Monte Carlo's stream, ``ctx.stream``: 0, or the ``over``
point's index under ``streams: independent``) (``<name>_trajectories.csv``: true state and every estimate,
and the channel's mode or arrival path). Monte Carlo chunks draw from ``SeedSequence(seed, spawn_key=(s, i))``
with s < 2³⁰ (an ``over`` grid or a sweep has at most 10 000 points), so the trajectories never reuse a
chunk's random numbers — the old "stream + 1" was the next ``over`` point's stream under ``independent``.

Which x the estimate aims at: ``filtered`` x̂_{k|k} → x_k, ``predicted`` x̂_{k+1|k} → x_{k+1}. The
state-level recursions are each estimator's ``estimates`` (its ``backend``: the Markov filters compile theirs,
equal to their numpy reference to rounding); the per-step reduction is numpy (the n = 2 NEES compiled).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from netkf_cli.core.lazy import pandas as pd
from pydantic import Field

from netkf_cli.engine import state
from netkf_cli.core.artefact import Artefact, RunContext
from netkf_cli.core.errors import ConfigError
from netkf_cli.metrics.common import (LABEL_COLUMNS, GenericMetric, PaperRef, Quantity, conventions_note, grid_conventions, describe, labels,
                                      math_text, needs, quantity_text)
from netkf_cli.runtime.plotting import footnote, legend_outside, new_figure, paper_title, series_style
from netkf_cli.core.spec import Matrix, NonNegInt, PositiveInt
from netkf_cli.core.stats import mean_se

Z = 5.0  # consistency tolerance in standard errors (a two-sided 5σ event has p ≈ 6e-7 per step)
TRAJECTORY_STREAM = 2**30  # trajectories: stream TRAJECTORY_STREAM + s, reserved (no Monte Carlo stream reaches 2³⁰)
COLUMNS = ["k", "estimator", "series", "value", "stderr", "expected", "n", "nonfinite"] + LABEL_COLUMNS
SUMMARY_COLUMNS = ["estimator", "series", "value", "stderr", "z", "expected", "n", "window"] + LABEL_COLUMNS
SERIES_TEXT = {"empirical": "empirical E‖x − x̂‖²", "reported": "reported E[tr P]", "nees": "mean NEES"}


class StateError(GenericMetric):
    """``kind: state_error`` — empirical error covariance vs reported P, NEES and trajectories of any estimator (numpy path)."""

    kind: Literal["state_error"]
    quantities: list[Quantity] | None = Field(None, description="several quantities in one pass (default: `quantity`); "
                                                                "each estimator reports those it offers")
    every: PositiveInt | None = Field(None, description="report every this many steps (default: at most 200 points)")
    window_from: NonNegInt | None = Field(None, description="the summary averages over k in (window_from, horizon] "
                                                           "(default: montecarlo.burn_in)")
    trajectories: NonNegInt = Field(0, description="draw the true state and the estimates of this many runs (the "
                                                   "first runs of the reserved stream 2³⁰ + the Monte Carlo's stream: "
                                                   "never a Monte Carlo chunk's random numbers)")
    S: Matrix | None = Field(None, description="cross-covariance E[w_k v_kᵀ] (n×m) of the simulated process and "
                                               "measurement noise (default 0); the estimators assume 0")
    log_y: bool = Field(False, description="logarithmic y axis for E‖e‖² and E tr P")
    paper: PaperRef | None = Field(None, description="the paper figure this reproduces (title only)")
    title: str = Field("", description="what the figure shows")

    def needs_per_run_covariance(self) -> bool:
        return False

    def check(self, scenario) -> None:
        super().check(scenario)
        s = needs(scenario, "system")
        for i, e in enumerate(needs(scenario, "estimators")):
            if not callable(getattr(e, "estimates", None)):
                raise ConfigError.at(f"estimators[{i}].kind" if scenario.estimators else "estimator.kind",
                                     f"{e.kind} has no state-level estimates(); state_error needs the estimate x̂ "
                                     f"(`netkf list` shows which estimators have it)")
        if self.S is not None and np.asarray(self.S, float).shape != (s.n, s.m):
            raise ConfigError.at("analysis.S", f"must be {s.n}×{s.m} (rows = states, columns = outputs), "
                                               f"got {np.asarray(self.S, float).shape}")
        if self.S is not None:  # the simulated noise [w; v] is drawn from it: it must be a covariance
            Sigma = state.noise_covariance(s, np.asarray(self.S, float))
            low = float(np.linalg.eigvalsh(0.5 * (Sigma + Sigma.T)).min())
            try:
                state.psd_factor(Sigma)
            except ValueError:
                raise ConfigError.at("analysis.S", f"the joint noise covariance [[Q, S], [Sᵀ, R]] must be positive "
                                                   f"semi-definite; its smallest eigenvalue is {low:.3g}") from None
        H = scenario.montecarlo.horizon
        if self._window_from(scenario) >= H:
            raise ConfigError.at("analysis.window_from", f"must be < montecarlo.horizon = {H}")

    def _window_from(self, scenario) -> int:
        return int(self.window_from if self.window_from is not None else getattr(scenario.montecarlo, "burn_in", 0) or 0)

    def steps(self, horizon: int, first: int = 1) -> list[int]:
        every = self.every or max(1, -(-horizon // 200))
        ks = [k for k in range(every, horizon + 1, every) if k >= first]
        return ks if ks and ks[-1] == horizon else ks + [horizon]

    # ------------------------------------------------------------------------------------ compute
    def compute(self, scenario, ctx: RunContext) -> Artefact:
        s, ch, ests = needs(scenario, "system"), needs(scenario, "channel"), needs(scenario, "estimators")
        mc = scenario.montecarlo
        H, qs = mc.horizon, self.quantity_list()
        cols = state.columns_of(ests, qs)
        first = max(ests[j].first_step(q) for j, q in cols)
        ks = self.steps(H, first)
        w0 = max(self._window_from(scenario), first - 1)
        window = list(range(w0 + 1, H + 1))
        runs = ctx.mc_runs(scenario)
        ctx.total(runs)
        stream = int(getattr(ctx, "stream", 0) or 0)
        S = None if self.S is None else np.asarray(self.S, float)
        tr = None
        if self.trajectories:  # first: a one-chunk serial run that loads every compiled kernel in this process,
            # so the Monte Carlo's forked workers inherit them (the numbers do not depend on the order: own stream)
            tstream = TRAJECTORY_STREAM + stream
            allk = list(range(first, H + 1))
            tr = state.trajectories(s, ch, ests, runs=self.trajectories, steps=allk, horizon=H, seed=mc.seed,
                                    stream=tstream, quantity=qs, S=S)
        st = state.simulate_errors(s, ch, ests, steps=ks, runs=runs, horizon=H, seed=mc.seed, chunk=mc.chunk,
                                   stream=stream, quantity=qs, window=window, S=S, progress=ctx.progress,
                                   label=self.kind)
        labs = labels(ests)
        lab_q = {q: describe(scenario, s, ests, q) for q in qs}
        n = int(st["n"])
        rows, summary = [], []
        wtext = f"k={window[0]}..{window[-1]}"
        first_of = {}
        for c, (j, q) in enumerate(cols):
            lab, lab_cols = labs[j], lab_q[q][j]
            first_of.setdefault(q, lab)
            bad = st[f"nonfinite_{c}"]
            m_ok = np.maximum(n - bad, 1)
            emp, emp_se = mean_se(st[f"sum_e2_{c}"], st[f"sum_e4_{c}"], m_ok)
            rep, rep_se = mean_se(st[f"sum_trP_{c}"], st[f"sumsq_trP_{c}"], m_ok)
            ne, ne_se = mean_se(st[f"sum_nees_{c}"], st[f"sumsq_nees_{c}"], m_ok)
            dd, dd_se = mean_se(st[f"sum_d_{c}"], st[f"sumsq_d_{c}"], m_ok)
            rank = st[f"sum_rank_{c}"] / m_ok
            for i, k in enumerate(ks):
                common = dict(k=k, estimator=lab, n=n, nonfinite=int(bad[i]), **lab_cols)
                rows.append(dict(series="empirical", value=emp[i], stderr=emp_se[i], expected=rep[i], **common))
                rows.append(dict(series="reported", value=rep[i], stderr=rep_se[i], expected=np.nan, **common))
                rows.append(dict(series="nees", value=ne[i], stderr=ne_se[i], expected=rank[i], **common))
            nees_ok = np.abs(ne - rank) <= Z * ne_se + 1e-12 * np.maximum(rank, 1)
            emp_ok = np.abs(dd) <= Z * dd_se + 1e-12 * np.maximum(rep, 1)
            wbad = float(st[f"win_nonfinite_{c}"])
            wn = max(n - wbad, 1)
            wm, ws = mean_se(st[f"win_sum_{c}"], st[f"win_sumsq_{c}"], wn)
            base = dict(estimator=lab, n=n, window=wtext, **lab_cols)
            summary += [dict(series="empirical", value=wm[0], stderr=ws[0], expected=wm[1], **base),
                        dict(series="reported", value=wm[1], stderr=ws[1], expected=np.nan, **base),
                        dict(series="nees", value=wm[2], stderr=ws[2], expected=wm[3], **base)]
            if first_of[q] != lab:
                dm, ds = mean_se(st[f"diff_sum_{c}"], st[f"diff_sumsq_{c}"], st[f"diff_n_{c}"])
                summary.append(dict(series=f"empirical minus {first_of[q]}", value=float(dm), stderr=float(ds),
                                    z=float(dm / ds) if ds > 0 else np.nan, expected=np.nan, **base))
            summary += [dict(series="nees_consistent_fraction", value=float(nees_ok.mean()), stderr=np.nan,
                             expected=np.nan, **base),
                        dict(series="empirical_equals_reported_fraction", value=float(emp_ok.mean()), stderr=np.nan,
                             expected=np.nan, **base)]
        if "mode_frac" in st:  # the channel's modes: empirical frequency per run (± s.e.) beside the stationary ρ_q
            fm, fs = mean_se(st["mode_frac"], st["mode_fracsq"], n)
            rho = np.asarray(getattr(ch, "rho", np.full(len(fm), np.nan)), float)
            base = dict(estimator="", n=n, window=f"k=1..{H}", quantity="", P0="", conventions=f"{ch.kind} channel")
            summary += [dict(series=f"mode {i + 1} frequency", value=float(fm[i]), stderr=float(fs[i]),
                             expected=float(rho[i]), **base) for i in range(len(fm))]
            dev = np.abs(fm - rho) / np.maximum(fs, 1e-300)
            summary.append(dict(series="mode frequency max deviation (s.e.)", value=float(dev.max()), stderr=np.nan,
                                expected=np.nan, **base))
        table = pd.DataFrame(rows, columns=COLUMNS)
        extra = {"summary": pd.DataFrame(summary, columns=SUMMARY_COLUMNS)}
        truth = {"filtered": "x̂_{k|k} against x_k", "predicted": "x̂_{k+1|k} against x_{k+1}"}
        meta = {"runs": n, "estimators": labs, "quantities": qs, "steps": f"{ks[0]}…{ks[-1]}", "window": wtext,
                "labels": {lab: lab_q[qs[0]][j] for j, lab in enumerate(labs)},
                "truth": {q: truth.get(q, q) for q in qs},
                "simulation": "x_0 ~ N(0, P_{0|0}), x_{k+1} = A x_k + w_k, y_k = C x_k + v_k, [w; v] ~ N(0, [[Q, S], [Sᵀ, R]]), "
                              f"S = {'0' if S is None else S.tolist()}; stream {stream}: the trace, then the states, "
                              "from each chunk's generator",
                "consistency_rule": f"|mean NEES − E rank P| ≤ {Z:g} s.e.; |E‖e‖² − E tr P| ≤ {Z:g} s.e. (paired)",
                "backend": "each estimator's estimates() (its backend); the reduction numpy, the n = 2 NEES compiled "
                           "when numba imports"}
        if tr is not None:
            extra["trajectories"] = _trajectory_table(tr, labs, cols, allk)
            meta["trajectories"] = f"the first {self.trajectories} run(s) of stream {tstream} (SeedSequence(seed, "\
                                   f"spawn_key=({tstream}, 0)))"
        return Artefact(table, meta=meta, extra_tables=extra)

    # ------------------------------------------------------------------------------------ plot
    def plot(self, tables, scenario):
        q = self.quantity_list()[0]  # the figure draws the first quantity (the CSVs hold all)
        if self.over:
            return self._plot_over(tables, q)
        t = tables["main"]
        t = t[t["quantity"] == q] if "quantity" in t else t
        traj = tables.get("trajectories")
        if traj is not None and "quantity" in traj:
            traj = traj[traj["quantity"].isna() | (traj["quantity"].astype(str).isin(["", "nan", q]))]
        comps = sorted(int(c) for c in traj["component"].unique() if c > 0) if traj is not None and len(traj) else []
        nrow = len(comps) + 2
        fig, axes = new_figure(nrows=nrow, width=9.0, height=2.8)
        axes = list(np.atleast_1d(axes))
        labs = list(dict.fromkeys(t.estimator))
        hat = r"\hat{x}_{k\mid k}" if q == "filtered" else r"\hat{x}_{k\mid k-1}"
        for ax, c in zip(axes, comps):
            d = traj[(traj.component == c) & (traj.run == 0)]
            tru = d[d.series == "true"]
            first = c == comps[0]  # one legend (on the first state's panel) for every state's panel: same styles
            ax.plot(tru.k, tru.value, color="black", lw=1.8, label="true state" if first else "_nolegend_")
            for i, lab in enumerate(labs):
                e = d[d.series == lab]
                sty = series_style(i + 1)
                ax.plot(e.k, e.value, color=sty["color"], ls=sty["linestyle"], lw=1.2, label=lab if first else "_nolegend_")
            _mark_channel(ax, traj, legend=first)
            ax.set_xlabel(r"time step $k$")
            ax.set_ylabel(rf"$x_{c}$, ${hat}$" if q == "filtered" else rf"$x_{c}(k)$, ${hat}$")
            ax.set_title(f"state {c}: true and estimated (one run)")
            if first:
                legend_outside(ax)
        ax = axes[len(comps)]
        for i, lab in enumerate(labs):
            sty = series_style(i + 1)
            e = t[(t.estimator == lab) & (t.series == "empirical")]
            r = t[(t.estimator == lab) & (t.series == "reported")]
            ax.plot(e.k, e.value, color=sty["color"], ls="-", lw=1.3, label=f"{lab}: empirical E‖x − x̂‖² (±1.96 s.e.)")
            ax.fill_between(e.k, e.value - 1.96 * e.stderr, e.value + 1.96 * e.stderr, color=sty["color"], alpha=0.2, lw=0)
            ax.plot(r.k, r.value, color=sty["color"], ls=(0, (1, 1.5)), lw=1.6, label=f"{lab}: reported E[tr P]")
        if self.log_y:
            ax.set_yscale("log")
        else:
            ax.set_ylim(bottom=0)
        ax.set_xlabel(r"time step $k$")
        ax.set_ylabel("squared error")
        ax.set_title(f"empirical error covariance (trace) vs reported {_qtext(q, '$P_k$')}")
        legend_outside(ax)
        ax = axes[len(comps) + 1]
        for i, lab in enumerate(labs):
            sty = series_style(i + 1)
            e = t[(t.estimator == lab) & (t.series == "nees")]
            ax.plot(e.k, e.value, color=sty["color"], ls=sty["linestyle"], lw=1.3, label=f"{lab} (band ±{Z:g} s.e.)")
            ax.fill_between(e.k, e.value - Z * e.stderr, e.value + Z * e.stderr, color=sty["color"], alpha=0.15, lw=0)
            ax.plot(e.k, e.expected, color=sty["color"], lw=0.8, ls=(0, (1, 1)),
                    label=r"dotted: each one's $\chi^2$ expectation E[rank P]" if i == 0 else "_nolegend_")
        ax.set_xlabel(r"time step $k$")
        ax.set_ylabel(r"mean NEES $e^\top P^{+} e$")
        ax.set_title("consistency: mean NEES against its chi-square expectation")
        legend_outside(ax)
        what = self.title or "estimation error vs reported covariance (NEES)"
        fig.suptitle(paper_title(self.paper.topic if self.paper else None, self.paper.figure if self.paper else None, what))
        n = int(t.n.max()) if len(t) else 0
        lab0 = t.iloc[0] if len(t) else None
        note = f"n = {n:,} runs per step; {q} ${_qtext(q)}$"
        if lab0 is not None:
            note += f"; {math_text(lab0.P0)}; {conventions_note(grid_conventions(t))}"
        if comps:
            note += "; trajectories: run 0 of the reserved stream 2³⁰ (+ the point's stream)"
        footnote(fig, note)
        return fig


    def _plot_over(self, tables, q: str):
        """With ``over``: the window averages against the grid's first path (E‖e‖² beside E tr P; NEES)."""
        path = next(iter(self.over))
        sm = tables["summary"]
        sm = sm[(sm["quantity"] == q) & (sm["estimator"].notna())] if "quantity" in sm else sm
        fig, axes = new_figure(nrows=2, width=7.6, height=3.4)
        labs = [e for e in dict.fromkeys(sm.estimator) if isinstance(e, str) and e]
        for i, lab in enumerate(labs):
            sty = series_style(i + 1)
            e = sm[(sm.estimator == lab) & (sm.series == "empirical")].sort_values(path)
            r = sm[(sm.estimator == lab) & (sm.series == "reported")].sort_values(path)
            axes[0].errorbar(e[path], e.value, yerr=1.96 * e.stderr, color=sty["color"], marker=sty["marker"], ls="-",
                             lw=1.2, capsize=3, label=f"{lab}: empirical E‖x − x̂‖² (±1.96 s.e.)")
            axes[0].plot(r[path], r.value, color=sty["color"], ls=(0, (1, 1.5)), lw=1.6, label=f"{lab}: reported E[tr P]")
            ne = sm[(sm.estimator == lab) & (sm.series == "nees")].sort_values(path)
            axes[1].errorbar(ne[path], ne.value, yerr=Z * ne.stderr, color=sty["color"], marker=sty["marker"], ls="-",
                             lw=1.2, capsize=3, label=f"{lab} (±{Z:g} s.e.)")
            axes[1].plot(ne[path], ne.expected, color=sty["color"], ls=(0, (1, 1)), lw=0.8,
                         label=r"dotted: $\chi^2$ expectation E[rank P]" if i == 0 else "_nolegend_")
        for ax in axes:
            ax.set_xlabel(path)
            legend_outside(ax)
        axes[0].set_ylabel("squared error")
        axes[0].set_ylim(bottom=0)
        axes[1].set_ylabel(r"mean NEES $e^\top P^{+} e$")
        w = sm.window.iloc[0] if len(sm) else ""
        axes[0].set_title(f"window average ({w}) of the error and of the reported {_qtext(q, '$P_k$')}")
        axes[1].set_title("consistency: mean NEES against its chi-square expectation")
        what = self.title or "estimation error vs reported covariance (NEES)"
        fig.suptitle(paper_title(self.paper.topic if self.paper else None, self.paper.figure if self.paper else None, what))
        footnote(fig, f"n = {int(sm.n.max()) if len(sm) else 0:,} runs per point; {q} ${_qtext(q)}$; "
                      f"per-step values in the CSV")
        return fig


def _qtext(quantity: str, what: str = "P_k") -> str:
    """:func:`quantity_text` with a visible conditioning bar (mathtext drops a bare ``|`` in a subscript)."""
    return quantity_text(quantity, what)  # quantity_text draws the bar with \mid itself


def _trajectory_table(tr: dict, labs: list[str], cols, steps: list[int]) -> pd.DataFrame:
    """Tidy rows (run, k, component, series, quantity, value): true x_k, each estimate at the time it aims at
    (x̂_{k|k} at k, x̂_{k+1|k} at k + 1), the channel's mode (1-based) or arrival at k (component 0)."""
    x = tr["traj_x"]
    n, T1, R = x.shape
    rows = []
    for r in range(R):
        for k in range(T1):
            for c in range(n):
                rows.append((r, k, c + 1, "true", "", float(x[c, k, r])))
        for ci, (j, q) in enumerate(cols):
            xh = tr[f"traj_{ci}"]
            shift = state.truth_index(0, q)
            for i, k in enumerate(steps):
                if k + shift < T1:
                    for c in range(n):
                        rows.append((r, k + shift, c + 1, labs[j], q, float(xh[c, i, r])))
        for key, name in (("traj_mode", "mode"), ("traj_arrival", "arrival")):
            if key in tr:
                a = tr[key]
                a = a[0] if a.ndim == 3 else a  # arrival (S, T, R): stream 0
                rows += [(r, t + 1, 0, name, "", float(a[t, r] + (1 if name == "mode" else 0))) for t in range(a.shape[0])]
    return pd.DataFrame(rows, columns=["run", "k", "component", "series", "quantity", "value"])


def _mark_channel(ax, traj: pd.DataFrame, legend: bool = True) -> None:
    """Markers under the curve where the channel did not deliver an on-time measurement (run 0);
    ``legend=False``: unlabelled (a panel that shares another panel's legend)."""
    d = traj[(traj.run == 0) & (traj.component == 0)]
    if not len(d):
        return
    lo, hi = ax.get_ylim()
    rug = lo - 0.06 * (hi - lo)
    if (d.series == "mode").any():
        m = d[d.series == "mode"]
        for qq, mk, name in ((2, "^", "delayed"), (3, "x", "missing"), (4, "s", "dropout")):
            kk = m.k[m.value == qq]
            if len(kk):
                ax.plot(kk, np.full(len(kk), rug), mk, ms=4, color="0.35", ls="none", label=f"mode {qq} ({name}) at k" if legend else "_nolegend_")
    else:
        a = d[d.series == "arrival"]
        kk = a.k[a.value < 0.5]
        if len(kk):
            ax.plot(kk, np.full(len(kk), rug), "x", ms=4, color="0.35", ls="none", label="packet lost at k" if legend else "_nolegend_")
