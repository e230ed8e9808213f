"""``kind: distribution`` — Pr[P_k ≤ M] against M for any channel and estimator(s).

Monte Carlo from the generic engine (:mod:`netkf_cli.engine`): every listed estimator runs
on the same sampled traces, P_k is taken at step ``at`` (``stationary``: k = horizon, after
the burn-in from P0) and compared with M·Iₙ in the PSD order (a diverged or overflowed run is
never ≤ M). Proportions carry a Wilson interval (``ci_low``, ``ci_high``).

Closed forms are attached only where their assumptions hold:

* ``buffered`` estimator on a ``delay``/``bernoulli`` channel (Shi, Xie & Murray 2009):
  lower/upper bounds 1 − θ(k₁, D), 1 − θ(k₂, D) (Thm 3.8; needs M ≥ M̄) and the certified
  exact stationary probability (needs A invertible);
* ``smart_sensor`` on the same channels: 1 − θ(k₂, D) (Thm 4.1, eq. 11; needs M ≥ P̄).

Step functions are evaluated on a drawing grid that contains the M grid, a 4× denser grid and
every jump point λ_max(hᵗ(M̄)), λ_max(hᵗ(P̄)) in range (table ``curves``), and drawn as
right-continuous steps — so the figure shows exactly what the numbers say.
"""

from __future__ import annotations

import math
import warnings
from typing import Literal

import numpy as np
from netkf_cli.core.lazy import pandas as pd
from pydantic import Field, model_validator

from netkf_cli import engine
from netkf_cli.linalg import riccati
from netkf_cli.analysis import delay_bounds as db
from netkf_cli.analysis import delay_exact as dx
from netkf_cli.channels.delay import delay_label
from netkf_cli.estimators.buffered import packet_span
from netkf_cli.core.errors import ConfigError
from netkf_cli.metrics.common import (fold_over, LABEL_COLUMNS, backends, conventions_note, grid_conventions, describe, GenericMetric, horizon_of, labels, m_values,
                                      math_text, MGrid, n_runs_of, needs, PaperRef, quantity_text, step_of)
from netkf_cli.core.stats import mean_se, proportion_stderr, wilson_interval
from netkf_cli.runtime.plotting import MARKERS, PALETTE, footnote, legend_outside, new_figure, paper_title
from netkf_cli.core.artefact import Artefact, RunContext
from netkf_cli.core.spec import PositiveFloat, PositiveInt

COLUMNS = ["M", "estimator", "series", "value", "stderr", "ci_low", "ci_high", "n", "err", "k"] + LABEL_COLUMNS
K_JUMPS = 2000


def _jump_points(X0: np.ndarray, s, lo: float, hi: float) -> list[float]:
    """λ_max(hᵗ(X0)), t = 0, 1, …, inside [lo, hi]: where k(M) = min{t : hᵗ(X0) ≰ M·I} changes."""
    out, X = [], np.array(X0, dtype=float)
    for _ in range(K_JUMPS):
        lam = float(np.linalg.eigvalsh(X)[-1])
        if not math.isfinite(lam) or lam > hi:
            break
        if lam >= lo:
            out.append(lam)
        Xn = riccati.h(X, s)
        if np.allclose(Xn, X, rtol=1e-13, atol=0):
            break
        X = Xn
    return out


def _dense(M: np.ndarray, scale: str, factor: int = 4) -> np.ndarray:
    lo, hi, num = float(M.min()), float(M.max()), factor * len(M)
    if hi <= lo:
        return M
    return np.geomspace(lo, hi, num) if scale == "log" and lo > 0 else np.linspace(lo, hi, num)


def _delay_pair(channel, est) -> bool:
    return channel.kind in ("delay", "bernoulli") and hasattr(channel, "cdf") and est.kind in ("buffered", "smart_sensor")


class ClosedForms:
    """Shi 2009 closed forms for one (channel, estimator) pair, or none (``available`` False + why)."""

    def __init__(self, s, channel, est, at_stationary: bool, exact: bool, exact_tol: float, quantity: str = "filtered"):
        self.s, self.ch, self.est, self.exact, self.tol = s, channel, est, exact, exact_tol
        self.available, self.why, self.jumps = False, "", []
        self.uncertified: dict[float, tuple[float, float]] = {}  # M → (lower, upper) of a bracket wider than tol
        if quantity != "filtered":
            self.why = f"the closed forms (Shi 2009 Thm 3.8/4.1) are for the filtered P_{{k|k}}, not {quantity}"
            return
        if not _delay_pair(channel, est):
            self.why = f"no closed form for {est.kind} on a {channel.kind} channel"
            return
        if not at_stationary:
            self.why = "the closed forms are stationary (analysis.at: stationary)"
            return
        self.db = db
        self.pbar = riccati.pbar(s)
        try:
            if est.kind == "buffered":
                self.span = packet_span(s, est.packet)
                if self.span == 1 and (s.m != s.n or np.linalg.matrix_rank(s.C) < s.n):
                    self.why = "Thm 3.8 needs C invertible for measurement packets (or packet: pair, Appendix B)"
                    return
                self.mbar = riccati.mbar(s)
            self.available = True
        except ConfigError as exc:
            self.why = f"Thm 3.8 needs M̄: {exc.problems[0].message}"

    def floor(self) -> float:
        """Smallest M (as M·I) where the closed forms hold: λ_max(M̄) (Thm 3.8) or λ_max(P̄) (Thm 4.1)."""
        X = self.mbar if self.est.kind == "buffered" else self.pbar
        return float(np.linalg.eigvalsh(X)[-1])

    def series(self, M: np.ndarray) -> dict[str, np.ndarray]:
        """Bound / exact series at every M (NaN where M is below the floor)."""
        db, ch, D, conv = self.db, self.ch, self.ch.D, self.ch.convention
        ok = M >= self.floor() * (1 - 1e-12)
        out: dict[str, np.ndarray] = {}

        def th(k):
            return 1 - db.theta(k, D, ch.cdf, conv)

        def bound(k_each, where):  # 1 − θ(k(M), D) where M qualifies (k along one orbit), else NaN
            v = np.full(len(M), np.nan)
            if where.any():
                v[where] = [th(k) for k in k_each(M[where], self.s)]
            return v

        if self.est.kind == "buffered":
            out["lower_bound"] = bound(db.k1_each, ok)
        out["upper_bound" if self.est.kind == "buffered" else "thm41"] = bound(
            db.k2_each, (ok | (self.est.kind == "buffered")) & (M >= self._pbar_max()))
        if self.est.kind == "buffered" and self.exact and ok.any():
            try:
                ex = dx.exact_probability(self.s, ch, self.span, M[ok], tol=self.tol)
                v, e = np.full(len(M), np.nan), np.full(len(M), np.nan)
                certified = ex.err <= self.tol  # else a bracket only (lost precision or node budget): not drawn
                # and inside Thm 3.8's bounds (closed forms, independent of the word tree): a word whose composed map
                # lost its precision without becoming singular can decide a node wrongly (a coupled system with an
                # eigenvalue −0.3 of A: the bracket left the bounds by 8e-6)
                lb, ub = (out.get(name, np.full(len(M), np.nan))[ok] for name in ("lower_bound", "upper_bound"))
                certified &= (np.isnan(lb) | (ex.upper >= lb - self.tol)) & (np.isnan(ub) | (ex.lower <= ub + self.tol))
                v[ok] = np.where(certified, ex.value, np.nan)
                e[ok] = ex.err
                out["exact"], out["exact_err"] = v, e
                for m, lo, hi, c in zip(M[ok], ex.lower, ex.upper, certified):
                    if not c:
                        self.uncertified.setdefault(float(m), (float(lo), float(hi)))
            except ConfigError as exc:
                self.why = f"exact probability unavailable: {exc.problems[0].message}"
        return out

    def _pbar_max(self) -> float:
        return float(np.linalg.eigvalsh(self.pbar)[-1]) * (1 - 1e-12)

    def jump_points(self, lo: float, hi: float) -> list[float]:
        pts = _jump_points(self.pbar, self.s, lo, hi)
        if self.est.kind == "buffered":
            pts += _jump_points(self.mbar, self.s, lo, hi)
        return pts


class Distribution(GenericMetric):
    """``kind: distribution`` — Pr[P_k ≤ M] against M (Monte Carlo + closed forms where they hold)."""

    kind: Literal["distribution", "prob_vs_M"]  # prob_vs_M: the name before the generic engine (same analysis)
    M: list[PositiveFloat] | MGrid = Field(description="M grid (scalar M means M·Iₙ): a list or {start, stop, num, spacing}")
    at: Literal["stationary"] | PositiveInt = Field(
        "stationary", description="step k at which P_k is taken; stationary = k = montecarlo.horizon after the burn-in from P0")
    bounds: bool = Field(True, description="overlay closed forms where their assumptions hold (Shi 2009 Thm 3.8/4.1)")
    exact: bool = Field(True, description="compute the certified exact probability where available (buffered sensor)")
    exact_tol: PositiveFloat = Field(1e-8, description="certified error bound of the exact value")
    x_scale: Literal["log", "linear"] = Field("log", description="M axis scale")
    paper: PaperRef | None = Field(None, description="the paper figure this reproduces (title only)")
    title: str = Field("", description="what the figure shows (default: Pr[P_k ≤ M] with the channel)")

    @model_validator(mode="after")
    def _grid_nonempty(self):
        if isinstance(self.M, list) and not self.M:
            raise ValueError("M must list at least one value")
        return self

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        ch = needs(scenario, "channel")
        k = step_of(self.at, scenario.montecarlo.horizon)
        M = m_values(self.M)
        s, ests, st = self.simulate(scenario, ctx, engine.DistributionReducer(M, [k]), [k], k)
        n = int(st["n"])
        labs = labels(ests)
        lab_cols = describe(scenario, s, ests, self.quantity)
        rows, curves, meta = [], [], {"at": k, "runs": n, "estimators": labs, "closed_forms": {},
                                      "quantity": self.quantity, "labels": dict(zip(labs, lab_cols)),
                              "backends": backends(scenario, s, ests, labs, n_runs_of(st), horizon_of(scenario, self), st, [k]),
                              "reduction": engine.reduction_used(st),
                                      "M_means": "M·I_n (PSD order)", "warnings": []}
        for j, (est, lab) in enumerate(zip(ests, labs)):
            cnt = st[f"count_{j}"][0]
            p = cnt / n
            if f"countsq_{j}" in st:  # importance-weighted: normal interval from the s.e. of w·1[P ≤ M]
                p, se = mean_se(cnt, st[f"countsq_{j}"][0], n)
                lo, hi = p - 1.96 * se, p + 1.96 * se
            else:
                se = proportion_stderr(p, n)
                lo, hi = wilson_interval(cnt, n)
            bad = int(st[f"nonfinite_{j}"][0])
            if bad:
                meta["warnings"].append(f"{lab}: {bad} of {n} runs overflowed (counted as P_k > M)")
            for i, m in enumerate(M):
                rows.append(dict(M=m, estimator=lab, series="monte_carlo", value=p[i], stderr=se[i],
                                 ci_low=lo[i], ci_high=hi[i], n=n, err=np.nan, k=k, **lab_cols[j]))
            if not self.bounds:
                continue
            cf = ClosedForms(s, ch, est, self.at == "stationary", self.exact, self.exact_tol, self.quantity)
            meta["closed_forms"][lab] = "attached" if cf.available else cf.why
            if not cf.available:
                continue
            ser = cf.series(M)
            for name, v in ser.items():
                if name == "exact_err":
                    continue
                err = ser["exact_err"] if name == "exact" else np.zeros(len(M))
                for i, m in enumerate(M):
                    if np.isfinite(v[i]):
                        rows.append(dict(M=m, estimator=lab, series=name, value=v[i], stderr=np.nan, ci_low=np.nan,
                                         ci_high=np.nan, n=np.nan, err=err[i], k=k, **lab_cols[j]))
            grid = np.unique(np.concatenate([M, _dense(M, self.x_scale), cf.jump_points(M.min(), M.max())]))
            for name, v in cf.series(grid).items():
                if name == "exact_err":
                    continue
                curves += [dict(M=g, estimator=lab, series=name, value=x) for g, x in zip(grid, v) if np.isfinite(x)]
            meta["closed_forms"][lab] = {"attached": True, "floor_M": cf.floor(), "note": cf.why or None}
            if cf.uncertified:
                pts = sorted(m for m in cf.uncertified if m in set(M.tolist())) or sorted(cf.uncertified)
                lo, hi = cf.uncertified[pts[0]]
                meta["warnings"].append(
                    f"{lab}: the exact probability is not certified to exact_tol = {self.exact_tol:g} at "
                    f"{len(pts)} M (not drawn; e.g. M = {pts[0]:g}: between {lo:.6g} and {hi:.6g}): "
                    "a long loss word's composed map lost double precision (or left Thm 3.8's bounds), or the node "
                    "budget ran out")
        for w in meta["warnings"]:  # one line on the terminal, and in the manifest
            warnings.warn(w, stacklevel=2)
        table = pd.DataFrame(rows, columns=COLUMNS)
        extra = {"curves": pd.DataFrame(curves, columns=["M", "estimator", "series", "value"])} if curves else {}
        summary = claims_summary(table, self.exact_tol)
        if len(summary):
            extra["summary"] = summary
        return Artefact(table, meta=meta, extra_tables=extra)

    def plot(self, tables, scenario):
        t = fold_over(tables["main"], self.over)
        cur = fold_over(tables.get("curves"), self.over)
        fig, ax = new_figure(width=7.4, height=5.6)
        styles = {"lower_bound": dict(ls="--", lw=1.3, lab=r"lower bound $1-\theta(k_1, D)$ (Thm 3.8)"),
                  "upper_bound": dict(ls="-.", lw=1.3, lab=r"upper bound $1-\theta(k_2, D)$ (Thm 3.8)"),
                  "exact": dict(ls="-", lw=1.0, lab="exact (certified)"),
                  "thm41": dict(ls="-", lw=1.6, lab=r"$1-\theta(k_2, D)$ (Thm 4.1, exact)")}
        ests = list(dict.fromkeys(t.estimator))
        for j, lab in enumerate(ests):
            colour = PALETTE[j % len(PALETTE)]
            if cur is not None and len(cur):
                for name, sty in styles.items():
                    g = cur[(cur.estimator == lab) & (cur.series == name)].sort_values("M")
                    if len(g):
                        # bounds on top (the upper bound of Thm 3.8 coincides with Thm 4.1's exact value)
                        ax.plot(g.M, g.value, drawstyle="steps-post", ls=sty["ls"], lw=sty["lw"],
                                color="black" if name == "exact" else colour, label=f"{lab}: {sty['lab']}",
                                zorder=4 if name.endswith("bound") else 3)
            g = t[(t.estimator == lab) & (t.series == "monte_carlo")].sort_values("M")
            if len(g):
                yerr = np.clip(np.vstack([g.value - g.ci_low, g.ci_high - g.value]), 0, None)
                ax.errorbar(g.M, g.value, yerr=yerr, fmt=MARKERS[j % len(MARKERS)], ms=4.0 + 2.0 * j, mfc="none",
                            color=colour, elinewidth=0.8, capsize=1.5, zorder=5,
                            label=f"{lab}: Monte Carlo, 95 % Wilson interval (n = {int(g.n.max()):,})")
        if self.x_scale == "log":
            ax.set_xscale("log")
        ax.set_xlabel(r"$M$ (the bound is $M\,I_n$)")
        pk = quantity_text(self.quantity)
        ax.set_ylabel(rf"$\Pr[{pk} \leq M]$")
        ax.set_ylim(-0.02, 1.02)
        what = self.title or rf"$\Pr[{pk} \leq M]$, {_channel_text(scenario.channel)}"
        ax.set_title(paper_title(self.paper.topic if self.paper else None, self.paper.figure if self.paper else None, what))
        legend_outside(ax, loc="below", ncol=1)
        k = int(t.k.iloc[0])
        lab = t.iloc[0]
        conv = conventions_note(grid_conventions(t)) if "conventions" in t else ""
        footnote(fig, f"{self.quantity} ${pk}$ at k = {k}" + (" (stationary: after the burn-in from P0)" if self.at == "stationary" else "")
                 + (f"; {math_text(lab.P0)}\n{conv}" if "P0" in t else ""))
        return fig


def _channel_text(ch) -> str:
    if ch is None:
        return ""
    if ch.kind in ("delay", "bernoulli"):
        keep = {"delay_le_D": r"kept iff delay $\leq D$", "delay_lt_D": r"kept iff delay $< D$ (eq. 4)"}
        conv = getattr(ch, "convention", None)
        return ((f"$D$ = {ch.buffer} ({keep.get(conv, conv)}), " if ch.kind == "delay" else "")
                + delay_label(ch, math=True))
    return f"{ch.kind} channel"


Z_CLAIM = 5.0
"""Claims compare Monte Carlo with closed forms through a Wilson interval at z = 5 (≈ 5σ)."""


def claims_summary(t: pd.DataFrame, exact_tol: float) -> pd.DataFrame:
    """Per estimator: does the Monte Carlo agree with the closed forms? (fractions of the M grid, 1 = everywhere)."""
    rows = []
    for lab, g in t.groupby("estimator", sort=False):
        mc = g[g.series == "monte_carlo"].set_index("M")
        if not len(mc):
            continue
        n = int(mc.n.iloc[0])
        lo5, hi5 = wilson_interval(np.rint(mc.value * n), n, z=Z_CLAIM)
        lo5, hi5 = pd.Series(lo5, index=mc.index), pd.Series(hi5, index=mc.index)

        def ser(name):
            return g[g.series == name].set_index("M").value

        lb, ub, ex, th = ser("lower_bound"), ser("upper_bound"), ser("exact"), ser("thm41")
        if len(ub):
            M = ub.index
            lower = lb.reindex(M) if len(lb) else pd.Series(0.0, index=M)
            ok = (hi5[M] >= lower - 1e-12) & (lo5[M] <= ub + 1e-12)
            rows += [dict(quantity="mc_within_bounds_5se_fraction", estimator=lab, value=float(ok.mean())),
                     dict(quantity="max_upper_minus_lower", estimator=lab, value=float((ub - lower).max()))]
        if len(ex):
            M = ex.index
            rows += [dict(quantity="mc_equals_exact_5se_fraction", estimator=lab,
                          value=float(((lo5[M] <= ex + exact_tol) & (hi5[M] >= ex - exact_tol)).mean())),
                     dict(quantity="max_exact_err", estimator=lab, value=float(g[g.series == "exact"].err.max()))]
            if len(ub):
                lower = lb.reindex(M) if len(lb) else 0.0
                rows.append(dict(quantity="exact_within_bounds_fraction", estimator=lab,
                                 value=float(((ex >= lower - exact_tol) & (ex <= ub.reindex(M) + exact_tol)).mean())))
        if len(th):
            M = th.index
            rows.append(dict(quantity="mc_equals_thm41_5se_fraction", estimator=lab,
                             value=float(((lo5[M] <= th + 1e-12) & (hi5[M] >= th - 1e-12)).mean())))
    ths = t[t.series == "thm41"]
    exs = t[t.series == "exact"]
    if len(ths) and len(exs):  # Sec. 5.2: the smart sensor does better (pathwise h^N(P̄) ≤ P_k of the raw sensor)
        a = ths.set_index("M").value
        b = exs.set_index("M").value
        M = a.index.intersection(b.index)
        d = a[M] - b[M]
        rows += [dict(quantity="min_thm41_minus_exact", estimator="both", value=float(d.min())),
                 dict(quantity="max_thm41_minus_exact", estimator="both", value=float(d.max())),
                 dict(quantity="claim_smart_at_least_raw_everywhere", estimator="both",
                      value=float((d >= -exact_tol).all()))]
    return pd.DataFrame(rows, columns=["quantity", "estimator", "value"])
