"""Leong, Dey & Evans 2008 — Kalman smoothing with random packet loss: the artefacts.

* ``kind: smoothing_table1`` — Table I: for P_{k|k−1}, P_{k|k}, P_{k|k+1…N} the sufficient arrival
  rate (eqs 7–8), the probability simulated the paper's way (one long run, time average, batch-means
  standard error), a high-precision Monte Carlo (independent runs, one sample each) and the exact
  stationary probability (enumeration, certified bracket), next to the printed row.
* ``kind: smoothing_critical_rate`` — Lemma 1: exact E[P_{k|k−1}], E[P_{k|k+N}] against λ, diverging
  together at λ_c = 1 − 1/a²; Monte Carlo means flagged unreliable where E[P²] = ∞.
* ``kind: smoothing_retransmission`` — Sec. V: CDF of P_{k|k} without / with deterministic and random
  retransmission and with a lag-N smoother on the same channel; KS tests; g(n) = 1 (eqs 10–11).
* ``kind: smoothing_burstiness`` — the Table I experiment under Gilbert–Elliott loss with the same
  stationary loss rate: exact and Monte Carlo P(P_{k|k+N} ≤ M) against the mean burst length.
"""

from __future__ import annotations

import math
from fractions import Fraction
from typing import Literal

import numpy as np
import pandas as pd
from pydantic import Field, model_validator
from scipy import stats

from netkf_cli import riccati
from netkf_cli.analysis import smoothing as sm
from netkf_cli.channels.bernoulli import sample_arrivals
from netkf_cli.channels.gilbert_elliott import sample_gilbert_elliott
from netkf_cli.errors import ConfigError
from netkf_cli.estimators.smoother import fixed_lag_smoother
from netkf_cli.montecarlo import plan_chunks, proportion_stderr, run_chunked
from netkf_cli.plotting import footnote, new_figure
from netkf_cli.recipes.base import Artefact, RunContext
from netkf_cli.spec import AnalysisModel, PositiveFloat, PositiveInt, Probability, StrictModel

PAPER = "Leong, Dey & Evans 2008"


def label(lag: int | None) -> str:
    """Column label of Table I: P_k|k-1, P_k|k, P_k|k+N."""
    if lag is None:
        return "P_k|k-1"
    return "P_k|k" if lag == 0 else f"P_k|k+{lag}"


def tex_label(lag: int | None) -> str:
    if lag is None:
        return r"$P_{k|k-1}$"
    return r"$P_{k|k}$" if lag == 0 else rf"$P_{{k|k+{lag}}}$"


def _lag_value(lag: int | None) -> float:
    """Numeric lag column: −1 for the predictor P_{k|k−1}."""
    return -1.0 if lag is None else float(lag)


def _lags_from(values: list[int]) -> list[int | None]:
    return [None if v < 0 else int(v) for v in values]


def _bernoulli_chain(lam: float) -> tuple[np.ndarray, np.ndarray]:
    return np.array([[1 - lam, lam], [1 - lam, lam]]), np.array([1 - lam, lam])


def _ge_chain(lam: float, burst: float) -> tuple[np.ndarray, np.ndarray, float, float]:
    p_bg = 1.0 / burst
    p_gb = (1 - lam) * p_bg / lam
    if p_gb > 1 + 1e-12:
        raise ConfigError.at("analysis.mean_bursts", f"mean burst {burst:g} too short for loss rate {1 - lam:.4g} (needs ≥ {(1 - lam) / lam:.4g})")
    p_gb = min(p_gb, 1.0)
    T = np.array([[1 - p_bg, p_bg], [p_gb, 1 - p_gb]])
    return T, np.array([1 - lam, lam]), p_gb, p_bg


def _covariance_at(res, lag: int | None, j: int = 0) -> np.ndarray:
    """(runs, n, n) covariance of column ``lag`` at recorded time index j."""
    P = res.pred[j] if lag is None else res.smooth[j, lag]
    return np.moveaxis(P, -1, 0)


def _prob_kernel(s, M, lag, horizon, sampler):
    """Monte Carlo kernel: one sample of 1{P_{k|k+N} ≤ M} per run at k = horizon − lag − 1."""
    L = 0 if lag is None else lag
    k = horizon - L - 1

    def kernel(rng, n):
        g = sampler(rng, n, horizon)
        res = fixed_lag_smoother(s, g, L, times=[k])
        ok = riccati.psd_leq(_covariance_at(res, lag), M)
        return {"count": int(ok.sum()), "n": n, "overflow": int((~np.isfinite(_covariance_at(res, lag))).any(axis=(1, 2)).sum())}

    return kernel


def _z(p: float, exact: float, n: int) -> float:
    se0 = math.sqrt(max(exact * (1 - exact), 0.0) / n)
    return abs(p - exact) / se0 if se0 > 0 else (0.0 if p == exact else math.inf)


# =============================================================================================
# Table I
# =============================================================================================


class Table1(AnalysisModel):
    """``kind: smoothing_table1`` — Table I of Leong, Dey & Evans 2008 (Sec. IV)."""

    kind: Literal["smoothing_table1"]
    M: PositiveFloat | list[list[float]] = Field(description="covariance bound M (scalar means M·Iₙ)")
    eps: float = Field(gt=0, lt=1, description="ε of the constraint P(P ≤ M) > 1 − ε")
    lags: list[int] = Field([-1, 0, 1, 2, 3, 4], description="columns: −1 = P_{k|k−1}, N ≥ 0 = P_{k|k+N}")
    paper_steps: PositiveInt = Field(100_000, description="length of the single run 'simulated the paper's way'")
    paper_batches: PositiveInt = Field(50, description="batches for the batch-means standard error of the single run")
    printed_lambda: list[float] | None = Field(None, description="the printed arrival-rate row (for the side-by-side table)")
    printed_prob: list[float] | None = Field(None, description="the printed probability row")

    @model_validator(mode="after")
    def _check(self):
        if not self.lags:
            raise ValueError("lags must list at least one column")
        if any(v < -1 for v in self.lags):
            raise ValueError("lags: use −1 for P_{k|k−1} and N ≥ 0 for P_{k|k+N}")
        for f in ("printed_lambda", "printed_prob"):
            v = getattr(self, f)
            if v is not None and len(v) != len(self.lags):
                raise ValueError(f"{f} must have one entry per lag ({len(self.lags)}), got {len(v)}")
        return self

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        s = scenario.linear_system()
        if scenario.channel is not None and scenario.channel.kind != "bernoulli":
            raise ConfigError.at("channel.kind", "Table I uses i.i.d. (bernoulli) loss at the rates of eq. (8); "
                                 "omit `channel` or use kind bernoulli (see smoothing_burstiness for Gilbert–Elliott)")
        M = sm.as_bound(self.M, s.n)
        Mbar = sm.leong_mbar(s)
        k1 = sm.k1(s, M, Mbar)
        mc = scenario.montecarlo
        runs = ctx.mc_runs(scenario)
        lags = _lags_from(self.lags)
        steps = self.paper_steps if ctx.runs is None else min(self.paper_steps, 10 * int(ctx.runs))
        ctx.total(runs * len(lags))
        lams = [sm.sufficient_arrival_rate(k1, self.eps, lag) for lag in lags]
        rows = []
        # --- the paper's way: one run of `steps` steps per column, all columns in one batched loop
        Lmax = max(0 if l is None else l for l in lags)
        rng = np.random.default_rng(np.random.SeedSequence(mc.seed, spawn_key=(10_000,)))
        g = np.vstack([rng.random(steps) < lam for lam in lams])  # (columns, steps)
        burn = min(mc.burn_in, steps // 10)
        times = np.arange(burn, steps - Lmax)
        res = fixed_lag_smoother(s, g, Lmax, times=times)
        paper = []
        for c, lag in enumerate(lags):
            P = res.pred[:, :, :, c] if lag is None else res.smooth[:, lag, :, :, c]
            ok = riccati.psd_leq(P, M).astype(float)
            batches = np.array_split(ok, self.paper_batches)
            bm = np.array([b.mean() for b in batches])
            paper.append((ok.mean(), bm.std(ddof=1) / math.sqrt(len(bm)), len(ok)))
        # --- high precision: independent runs, one sample each
        exact = []
        for c, (lag, lam) in enumerate(zip(lags, lams)):
            horizon = mc.burn_in + (0 if lag is None else lag) + 1
            kern = _prob_kernel(s, M, lag, horizon, lambda r, n, h, lam=lam: sample_arrivals(r, n, h, lam))
            st = run_chunked(kern, runs, mc.chunk, mc.seed + 7919 * c, progress=ctx.progress, label=label(lag))
            n = int(st["n"])
            p = float(st["count"]) / n
            T, pi = _bernoulli_chain(lam)
            ex = sm.exact_probability(s, M, lag, T, pi)
            exact.append(ex)
            base = dict(column=label(lag), lag=_lag_value(lag), k1=k1, eps=self.eps)
            pr_l = self.printed_lambda[c] if self.printed_lambda else np.nan
            pr_p = self.printed_prob[c] if self.printed_prob else np.nan
            rows += [
                dict(base, series="lambda_eq8", value=lam, stderr=0.0, n=np.nan, printed=pr_l),
                dict(base, series="prob_paper_way", value=paper[c][0], stderr=paper[c][1], n=paper[c][2], printed=pr_p),
                dict(base, series="prob_monte_carlo", value=p, stderr=float(proportion_stderr(p, n)), n=n, printed=pr_p),
                dict(base, series="prob_exact", value=ex.value, stderr=ex.width / 2, n=np.nan, printed=pr_p),
                dict(base, series="z_mc_vs_exact", value=_z(p, ex.value, n), stderr=np.nan, n=n, printed=np.nan),
                dict(base, series="overflow_runs", value=float(st["overflow"]), stderr=np.nan, n=n, printed=np.nan),
            ]
        table = pd.DataFrame(rows)
        md = self._markdown(table, lags)
        meta = {
            "paper": PAPER + ", Table I",
            "Mbar": Mbar, "k1": k1, "M": M, "eps": self.eps,
            "lambda_rule": "eq. (7) 1 − ε^(1/k1) for P_k|k-1; eq. (8) 1 − ε^(1/(k1+N+1)) for P_k|k+N (N = 0: P_k|k)",
            "paper_way": {"steps": int(steps), "burn_in": int(burn), "batches": self.paper_batches,
                          "stderr": "batch means over consecutive blocks (the indicator is autocorrelated)",
                          "seed": f"SeedSequence({mc.seed}, spawn_key=(10000,))"},
            "monte_carlo": {"runs": runs, "sample": f"one sample per run at k = burn_in = {mc.burn_in} from P0",
                            "stderr": "binomial sqrt(p(1-p)/n)"},
            "exact": {"method": "backward enumeration of the recent arrival pattern, certified bracket (stderr column = half-width)",
                      "nodes": [e.nodes for e in exact], "max_width": max(e.width for e in exact)},
        }
        return Artefact(table, meta=meta, extra_text={"table.md": md})

    def _markdown(self, t: pd.DataFrame, lags) -> str:
        cols = [label(l) for l in lags]
        def row(series, fmt, printed=False):
            out = []
            for c in cols:
                r = t[(t.column == c) & (t.series == series)].iloc[0]
                v = r.printed if printed else r.value
                if printed and not np.isfinite(v):
                    out.append("—")
                elif series.startswith("prob_") and not printed and series != "prob_exact":
                    out.append(f"{v:{fmt}} ± {r.stderr:.4f}")
                else:
                    out.append(f"{v:{fmt}}")
            return out
        lines = ["| | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
        lines.append("| λ printed | " + " | ".join(row("lambda_eq8", ".3f", True)) + " |")
        lines.append("| λ eq. (7)/(8), ours | " + " | ".join(row("lambda_eq8", ".3f")) + " |")
        lines.append("| P(P ≤ M) printed | " + " | ".join(row("prob_paper_way", ".3f", True)) + " |")
        lines.append("| paper's way (1 run) | " + " | ".join(row("prob_paper_way", ".4f")) + " |")
        lines.append("| Monte Carlo | " + " | ".join(row("prob_monte_carlo", ".4f")) + " |")
        lines.append("| exact | " + " | ".join(row("prob_exact", ".5f")) + " |")
        return "\n".join(lines) + "\n"

    def plot(self, tables, scenario):
        t = tables["main"]
        cols = list(dict.fromkeys(t.column))
        fig, axes = new_figure(ncols=2, width=6.2, height=4.4, gridspec_kw={"width_ratios": [1.0, 1.25]})
        ax = axes[0]
        x = np.arange(len(cols))
        get = lambda s_: t[t.series == s_].set_index("column").loc[cols]  # noqa: E731
        lam, pw, mcv, ex = get("lambda_eq8"), get("prob_paper_way"), get("prob_monte_carlo"), get("prob_exact")
        eps = float(t.eps.iloc[0])
        ax.axhline(1 - eps, color="0.3", ls=":", lw=1, label=f"1 − ε = {1 - eps:g}")
        if np.isfinite(pw.printed).any():
            ax.plot(x, pw.printed, "s", mfc="none", color="C3", ms=9, label="printed (Table I)")
        ax.errorbar(x - 0.12, pw.value, yerr=pw.stderr, fmt="^", color="C1", capsize=3, label="paper's way (1 run, ±1 s.e.)")
        ax.errorbar(x + 0.12, mcv.value, yerr=mcv.stderr, fmt="o", color="C0", capsize=3, label="Monte Carlo (±1 s.e.)")
        ax.plot(x, ex.value, "_", color="k", ms=18, mew=2, label="exact")
        ax.set_xticks(x, [tex_label(None if c == "P_k|k-1" else (0 if c == "P_k|k" else int(c.split("+")[1]))) for c in cols])
        ax.set_ylabel(r"$\mathbb{P}(P \leq M)$ at the rate of eq. (7)/(8)")
        ax.set_title("Table I: probability at the sufficient arrival rate", fontsize=10)
        ax.legend(fontsize=7, loc="lower left")
        ax2 = axes[1]
        ax2.axis("off")
        ax2.grid(False)
        cell = [
            [f"{v:.3f}" if np.isfinite(v) else "—" for v in lam.printed],
            [f"{v:.3f}" for v in lam.value],
            [f"{v:.3f}" if np.isfinite(v) else "—" for v in pw.printed],
            [f"{v:.4f}" for v in pw.value],
            [f"{v:.4f}" for v in mcv.value],
            [f"{v:.4f}" for v in ex.value],
        ]
        rl = ["λ printed", "λ eq.(7)/(8)", "P printed", "paper's way", "Monte Carlo", "exact"]
        tb = ax2.table(cellText=cell, rowLabels=rl, colLabels=[c.replace("P_", "") for c in cols], loc="center", cellLoc="center")
        tb.auto_set_font_size(False)
        tb.set_fontsize(7.5)
        tb.scale(1.0, 1.6)
        for j in range(len(cols)):
            for i in (1, 3):
                tb[(i, j)].set_facecolor("#f3e3e3")
        ax2.set_title(f"A = {_num(scenario.system.A)}, C = {_num(scenario.system.C)}, Q = {_num(scenario.system.Q)}, "
                      f"R = {_num(scenario.system.R)}, M = {_num(self.M)}, ε = {eps:g}", fontsize=9)
        n = int(mcv.n.iloc[0])
        footnote(fig, f"{PAPER}, Table I. Monte Carlo: {n} independent runs, one sample each; paper's way: one run of "
                      f"{int(pw.n.iloc[0])} steps (batch-means s.e.); exact: enumeration (certified). Shaded rows: printed.")
        return fig


def _num(x) -> str:
    a = np.asarray(x, dtype=float)
    return f"{float(a.ravel()[0]):g}" if a.size == 1 else np.array2string(a, precision=3)


# =============================================================================================
# Lemma 1 — critical arrival rate
# =============================================================================================


class LambdaGrid(StrictModel):
    start: Probability
    stop: Probability
    num: PositiveInt = 30

    @model_validator(mode="after")
    def _order(self):
        if not 0 < self.start < self.stop < 1:
            raise ValueError(f"need 0 < start < stop < 1, got start = {self.start:g}, stop = {self.stop:g}")
        return self

    def values(self) -> np.ndarray:
        return np.linspace(self.start, self.stop, self.num)


class CriticalRate(AnalysisModel):
    """``kind: smoothing_critical_rate`` — Lemma 1: E[P] of filter and smoothers against λ."""

    kind: Literal["smoothing_critical_rate"]
    lambdas: list[Probability] | LambdaGrid = Field(description="arrival rates (list or {start, stop, num})")
    lags: list[int] = Field([-1, 0, 1, 3], description="−1 = P_{k|k−1}, N ≥ 0 = P_{k|k+N}")
    exact_tol: PositiveFloat = Field(1e-10, description="per-node trace tolerance of the exact enumeration")
    monte_carlo: bool = True

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        s = scenario.linear_system()
        sm.leong_mbar(s, path="system.C")  # C invertible needed for the exact means
        lam_c = sm.critical_rate(s)
        lam_2 = sm.second_moment_rate(s)
        lams = self.lambdas.values() if isinstance(self.lambdas, LambdaGrid) else np.asarray(self.lambdas, float)
        if np.any((lams <= 0) | (lams >= 1)):
            raise ConfigError.at("analysis.lambdas", "arrival rates must lie in (0, 1)")
        lags = _lags_from(self.lags)
        mc = scenario.montecarlo
        runs = ctx.mc_runs(scenario)
        Lmax = max(0 if l is None else l for l in lags)
        ctx.total(runs * len(lams))
        rows = []
        for i, lam in enumerate(lams):
            exact = {}
            for lag in lags:
                if lam <= lam_c:
                    lo = hi = np.inf
                else:
                    e = sm.exact_mean(s, float(lam), lag, tol=self.exact_tol)
                    lo, hi = float(np.trace(e.lower)), float(np.trace(e.upper))
                exact[lag] = (lo, hi)
                base = dict(lam=float(lam), lag=_lag_value(lag), column=label(lag), lambda_c=lam_c, lambda_2=lam_2)
                rows.append(dict(base, series="exact", value=0.5 * (lo + hi), stderr=0.5 * (hi - lo), n=np.nan, reliable=1.0))
            for lag in lags:
                if lag is None:
                    continue
                lb = (1 - lam) ** (lag + 1) * exact[None][0] if None in exact else np.nan
                rows.append(dict(lam=float(lam), lag=_lag_value(lag), column=label(lag), lambda_c=lam_c, lambda_2=lam_2,
                                 series="lemma1_lower", value=lb, stderr=0.0, n=np.nan, reliable=1.0))
            if self.monte_carlo:
                horizon = mc.burn_in + Lmax + 1
                k = mc.burn_in

                def kernel(rng, n, lam=lam):
                    g = sample_arrivals(rng, n, horizon, lam)
                    res = fixed_lag_smoother(s, g, Lmax, times=[k])
                    out = {"n": n}
                    for lag in lags:
                        tr = np.trace(_covariance_at(res, lag), axis1=1, axis2=2)
                        out[f"s{label(lag)}"] = float(tr.sum())
                        out[f"q{label(lag)}"] = float((tr ** 2).sum())
                    return out

                st = run_chunked(kernel, runs, mc.chunk, mc.seed + 104729 * i, progress=ctx.progress, label=f"λ={lam:.3f}")
                n = int(st["n"])
                for lag in lags:
                    mean = float(st[f"s{label(lag)}"]) / n
                    var = max(float(st[f"q{label(lag)}"]) / n - mean ** 2, 0.0) * n / max(n - 1, 1)
                    rows.append(dict(lam=float(lam), lag=_lag_value(lag), column=label(lag), lambda_c=lam_c, lambda_2=lam_2,
                                     series="monte_carlo", value=mean, stderr=math.sqrt(var / n), n=n,
                                     reliable=float(lam > lam_2)))
        table = pd.DataFrame(rows)
        meta = {"paper": PAPER + ", Lemma 1 (Sec. III)", "lambda_c": lam_c, "lambda_c_rule": "1 − 1/ρ(A)² (exact for C invertible)",
                "lambda_second_moment": lam_2,
                "reliable": "Monte Carlo means are flagged unreliable (reliable = 0) for λ ≤ 1 − 1/ρ(A)⁴ where E[P²] = ∞: "
                            "the sample mean has no finite standard error there",
                "value": "trace of the stationary mean; exact = midpoint of a certified bracket (stderr = half-width)",
                "monte_carlo": {"runs": runs, "sample": f"one sample per run at k = {mc.burn_in} from P0"}}
        return Artefact(table, meta=meta)

    def plot(self, tables, scenario):
        t = tables["main"]
        fig, ax = new_figure(width=7.0, height=4.8)
        lam_c, lam_2 = float(t.lambda_c.iloc[0]), float(t.lambda_2.iloc[0])
        cols = list(dict.fromkeys(t.column))
        for j, c in enumerate(cols):
            e = t[(t.column == c) & (t.series == "exact") & np.isfinite(t.value)]
            ax.plot(e.lam, e.value, "-", color=f"C{j}", label=f"exact E[tr {c.replace('_', '')}]")
            m = t[(t.column == c) & (t.series == "monte_carlo")]
            good, bad = m[m.reliable > 0], m[m.reliable <= 0]
            ax.errorbar(good.lam, good.value, yerr=good.stderr, fmt="o", ms=3.5, color=f"C{j}", capsize=2)
            ax.plot(bad.lam, bad.value, "x", ms=5, color=f"C{j}")
            lb = t[(t.column == c) & (t.series == "lemma1_lower") & np.isfinite(t.value)]
            if len(lb) and c == cols[-1]:
                ax.plot(lb.lam, lb.value, ":", color=f"C{j}", lw=1, label=f"(1−λ)^(N+1) E[P_k|k-1] (Lemma 1, {c.replace('_', '')})")
        ax.axvline(lam_c, color="k", lw=1.2, ls="--", label=f"λ_c = 1 − 1/a² = {lam_c:.4f}")
        if t.lam.min() < lam_c:
            ax.axvspan(t.lam.min(), lam_c, color="0.85", alpha=0.5, lw=0)
        ax.axvline(lam_2, color="0.4", lw=0.8, ls="-.", label=f"E[P²] = ∞ below λ = {lam_2:.3f} (MC × unreliable)")
        ax.set_yscale("log")
        ax.set_xlabel("arrival rate λ")
        ax.set_ylabel("stationary E[tr P]  (log scale)")
        ax.set_title("Lemma 1: smoothing does not move the critical arrival rate", fontsize=10)
        ax.plot([], [], "o", color="0.4", ms=3.5, label="Monte Carlo mean ±1 s.e.")
        ax.plot([], [], "x", color="0.4", label="Monte Carlo mean, heavy-tailed (no finite s.e.)")
        ax.legend(fontsize=7, loc="lower left", ncol=2)
        n = t[t.series == "monte_carlo"].n
        footnote(fig, f"{PAPER}, Lemma 1. Lines: exact stationary means; dots: Monte Carlo at finite k "
                      f"({int(n.iloc[0]) if len(n) else 0} runs/λ); shaded: E[P] = ∞")
        return fig


# =============================================================================================
# Section V — retransmission
# =============================================================================================


class Retransmission(AnalysisModel):
    """``kind: smoothing_retransmission`` — Sec. V: retransmission vs filtering vs smoothing."""

    kind: Literal["smoothing_retransmission"]
    N: PositiveInt = Field(2, description="retransmission budget N (and the smoother lag: the same latency)")
    p: list[Probability] = Field([1.0, 0.5], description="probabilities of asking for a retransmission (1 = deterministic, Sec. V-A)")
    M: PositiveFloat = Field(description="threshold for the reported P(P_{k|k} ≤ M)")
    grid: PositiveInt = Field(120, description="points of the CDF grid")
    g_n_max: PositiveInt = Field(30, description="largest n of the g(n) = 1 check")
    g_check_N: list[PositiveInt] = Field([1, 2, 3, 5], description="budgets N for the g(n) check")
    g_check_p: list[Probability] = Field([0.0, 0.3, 0.5, 0.9, 1.0], description="p values for the g(n) check")

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        s = scenario.linear_system()
        ch = scenario.require_channel("bernoulli")
        lam = float(ch.arrival)
        if not 0 < lam < 1:
            raise ConfigError.at("channel.arrival", f"must be in (0, 1) for a loss channel, got {lam}")
        mc = scenario.montecarlo
        runs = ctx.mc_runs(scenario)
        N = self.N
        horizon = mc.burn_in + 2 * N + 2
        k = mc.burn_in  # well before the end: late retransmissions are complete by then
        schemes = ["filter"] + [f"retx_p{p:g}" for p in self.p] + [f"smoother_lag{N}"]
        samples = {sc: [] for sc in schemes}
        gstats = {f"retx_p{p:g}": [0, 0, 0] for p in self.p}  # ones, pairs 11, count
        ctx.total(runs)
        for c in plan_chunks(runs, mc.chunk, mc.seed):
            rng = c.rng()
            n = c.runs
            g = sample_arrivals(rng, n, horizon, lam)
            res = fixed_lag_smoother(s, g, N, times=[k])
            samples["filter"].append(_covariance_at(res, 0)[:, 0, 0] if s.n == 1 else np.trace(_covariance_at(res, 0), axis1=1, axis2=2))
            Ps = _covariance_at(res, N)
            samples[f"smoother_lag{N}"].append(Ps[:, 0, 0] if s.n == 1 else np.trace(Ps, axis1=1, axis2=2))
            for p in self.p:
                gt = sm.simulate_retransmission(rng, n, horizon, lam, N, p)
                r2 = fixed_lag_smoother(s, gt, 0, times=[k])
                P = _covariance_at(r2, 0)
                samples[f"retx_p{p:g}"].append(P[:, 0, 0] if s.n == 1 else np.trace(P, axis1=1, axis2=2))
                win = gt[:, 10:k]
                st = gstats[f"retx_p{p:g}"]
                st[0] += int(win.sum())
                st[1] += int((win[:, :-1] & win[:, 1:]).sum())
                st[2] += win.size
            ctx.tick(n)
        S = {sc: np.concatenate(v) for sc, v in samples.items()}
        allv = np.concatenate([v[np.isfinite(v)] for v in S.values()])
        lo, hi = float(np.quantile(allv, 0.0005)), float(np.quantile(allv, 0.9995))
        xs = np.unique(np.concatenate([np.geomspace(max(lo * 0.95, 1e-12), hi * 1.05, self.grid), [self.M]]))
        rows = []
        Tm, pi = _bernoulli_chain(lam)
        scalar = s.n == 1
        for sc, v in S.items():
            n = len(v)
            vs = np.sort(v)
            F = np.searchsorted(vs, xs, side="right") / n
            for x, f in zip(xs, F):
                rows.append(dict(scheme=sc, series="ecdf", x=float(x), value=float(f), stderr=float(proportion_stderr(f, n)), n=n))
        if scalar:
            for sc, lag in (("filter", 0), (f"smoother_lag{N}", N)):
                for x in xs:
                    ex = sm.exact_probability(s, float(x), lag, Tm, pi, tol=1e-12)
                    rows.append(dict(scheme=sc, series="exact_cdf", x=float(x), value=ex.value, stderr=ex.width / 2, n=np.nan))
        table = pd.DataFrame(rows)
        # statistics: KS (two-sample) of every retransmission scheme vs the plain filter and vs the smoother
        summ = []
        for p in self.p:
            sc = f"retx_p{p:g}"
            for other in ("filter", f"smoother_lag{N}"):
                ks = stats.ks_2samp(S[sc], S[other])
                summ.append(dict(quantity="ks_statistic", scheme=sc, versus=other, value=float(ks.statistic), p_value=float(ks.pvalue)))
            ones, pairs, cnt = gstats[sc]
            summ.append(dict(quantity="effective_arrival_rate", scheme=sc, versus="lambda", value=ones / cnt, p_value=np.nan))
            summ.append(dict(quantity="effective_P11", scheme=sc, versus="lambda^2", value=pairs / (cnt * (k - 11) / (k - 10)), p_value=np.nan))
        for sc, v in S.items():
            n = len(v)
            pm = float(np.mean(v <= self.M))
            summ.append(dict(quantity="prob_leq_M", scheme=sc, versus="-", value=pm, p_value=np.nan, stderr=float(proportion_stderr(pm, n)), n=n))
        if scalar:
            for sc, lag in (("filter", 0), (f"smoother_lag{N}", N)):
                ex = sm.exact_probability(s, self.M, lag, Tm, pi)
                summ.append(dict(quantity="prob_leq_M_exact", scheme=sc, versus="-", value=ex.value, p_value=np.nan, stderr=ex.width / 2))
        summary = pd.DataFrame(summ)
        summary["lambda"], summary["N"], summary["M"] = lam, N, self.M
        # g(n) = 1 (eqs 10–11): floats over a grid, exact rationals, and brute-force enumeration
        grow = []
        for NN in self.g_check_N:
            for p in self.g_check_p:
                gv = sm.retransmission_g(self.g_n_max, NN, float(p))
                gx = sm.retransmission_g(min(self.g_n_max, 12), NN, Fraction(p).limit_denominator(1000))
                for nn, val in enumerate(gv):
                    enum = sm.enumerate_retransmission_ways(nn, NN, Fraction(p).limit_denominator(1000)) if nn <= 8 else None
                    grow.append(dict(N=NN, p=float(p), n=nn, g_float=val, g_exact_is_one=float(gx[nn] == 1) if nn < len(gx) else np.nan,
                                     enum_ways=len(enum) if enum is not None else np.nan,
                                     enum_sum=float(sum(w for _, w in enum)) if enum is not None else np.nan))
        gtab = pd.DataFrame(grow)
        meta = {"paper": PAPER + ", Sec. V", "lambda": lam, "N": N, "p": self.p, "runs": runs,
                "sample": f"one sample per run at k = {k} (retransmissions of measurements ≤ k are complete by the horizon {horizon})",
                "x": "P_k|k (trace if n > 1) — filter with and without retransmission; smoother P_k|k+N with the same latency N",
                "ks": "scipy.stats.ks_2samp, two-sided; the distribution has atoms, so the KS p-value is conservative",
                "g_identity_max_abs_dev": float(np.max(np.abs(gtab.g_float - 1.0)))}
        return Artefact(table, meta=meta, extra_tables={"summary": summary, "g_identity": gtab})

    def plot(self, tables, scenario):
        t, summ = tables["main"], tables["summary"]
        fig, axes = new_figure(ncols=2, width=5.6, height=4.6)
        ax = axes[0]
        retx_colors = iter(["C2", "C1", "C4", "C5", "C6"])
        for sc in dict.fromkeys(t.scheme):
            e = t[(t.scheme == sc) & (t.series == "ecdf")]
            col = "C0" if sc == "filter" else ("C3" if sc.startswith("smoother") else next(retx_colors))
            lw = 3.0 if sc == "filter" else 1.4
            ls = "-" if sc in ("filter",) or sc.startswith("smoother") else "--"
            name = sc.replace("retx_p1", "retransmission, deterministic (p=1)").replace("retx_p", "retransmission, random p=") if sc.startswith("retx") else sc
            name = "filter, no retransmission" if sc == "filter" else name.replace("smoother_lag", "smoother, lag N = ")
            ax.step(e.x, e.value, where="post", color=col, lw=lw, ls=ls, alpha=0.85 if sc == "filter" else 1, label=name + " (MC)")
            x = t[(t.scheme == sc) & (t.series == "exact_cdf")]
            if len(x):
                ax.plot(x.x, x.value, ":", color="k", lw=1)
        ax.plot([], [], ":", color="k", label="exact CDF (enumeration)")
        ax.axvline(float(summ.M.iloc[0]), color="0.5", lw=0.8)
        ax.set_xscale("log")
        ax.set_xlabel(r"$P_{k|k}$ (smoother: $P_{k|k+N}$)")
        ax.set_ylabel("empirical CDF")
        ax.set_title(f"Sec. V: λ = {float(summ['lambda'].iloc[0]):g}, N = {int(summ.N.iloc[0])}", fontsize=10)
        ax.legend(fontsize=7, loc="lower right")
        ax2 = axes[1]
        ks = summ[summ.quantity == "ks_statistic"]
        labels = [f"{r.scheme.replace('retx_', '')}\nvs {r.versus.replace('smoother_lag', 'smoother N=')}" for r in ks.itertuples()]
        y = np.arange(len(ks))
        ax2.barh(y, ks.p_value, color=["C2" if "filter" == v else "C3" for v in ks.versus])
        for yy, r in zip(y, ks.itertuples()):
            ax2.text(min(r.p_value, 0.95) + 0.02, yy, f"D = {r.value:.4f}, p = {r.p_value:.3g}", va="center", fontsize=7)
        ax2.set_yticks(y, labels, fontsize=7)
        ax2.axvline(0.05, color="k", ls="--", lw=0.8, label="0.05")
        ax2.set_xlim(0, 1.35)
        ax2.set_xlabel("two-sample KS p-value")
        ax2.set_title("equivalence (green: vs filter) and smoother gap (red)", fontsize=9)
        ax2.legend(fontsize=7, loc="lower right")
        n = int(t[t.series == "ecdf"].n.iloc[0])
        footnote(fig, f"{PAPER}, Sec. V. {n} runs per scheme, one sample each, the same Bernoulli channel law; "
                      "retransmitted measurements reach the filter up to N steps late.")
        return fig


# =============================================================================================
# Gilbert–Elliott (bursty) loss
# =============================================================================================


class Burstiness(AnalysisModel):
    """``kind: smoothing_burstiness`` — Table I's experiment under Gilbert–Elliott loss.

    Each column keeps its Table I arrival rate (eq. 8) as the *stationary* arrival rate, and the
    mean loss-burst length is swept; mean burst 1/λ is i.i.d. loss (the Bernoulli point).
    """

    kind: Literal["smoothing_burstiness"]
    M: PositiveFloat
    eps: float = Field(gt=0, lt=1)
    lags: list[int] = Field([-1, 0, 1, 2, 3, 4])
    mean_bursts: list[PositiveFloat] = Field(description="mean loss-burst lengths L_B (≥ 1) to sweep")
    common_rate: Probability | None = Field(None, description="use this stationary arrival rate for every column "
                                           "instead of each column's eq. (8) rate")

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        s = scenario.linear_system()
        if scenario.channel is not None and scenario.channel.kind != "gilbert_elliott":
            raise ConfigError.at("channel.kind", "smoothing_burstiness sweeps a gilbert_elliott channel; omit `channel` or use that kind")
        M = sm.as_bound(self.M, s.n)
        k1 = sm.k1(s, M)
        lags = _lags_from(self.lags)
        mc = scenario.montecarlo
        runs = ctx.mc_runs(scenario)
        rows = []
        ctx.total(runs * len(lags) * (len(self.mean_bursts) + 1))
        for c, lag in enumerate(lags):
            lam = self.common_rate if self.common_rate is not None else sm.sufficient_arrival_rate(k1, self.eps, lag)
            bursts = sorted(set([float(b) for b in self.mean_bursts] + [1.0 / lam]))
            for b_i, L in enumerate(bursts):
                if L < (1 - lam) / lam - 1e-12:
                    continue  # not realisable at this loss rate
                T, pi, p_gb, p_bg = _ge_chain(lam, L)
                ex = sm.exact_probability(s, M, lag, T, pi)
                horizon = mc.burn_in + (0 if lag is None else lag) + 1
                kern = _prob_kernel(s, M, lag, horizon, lambda r, n, h, a=p_gb, b=p_bg: sample_gilbert_elliott(r, n, h, a, b))
                st = run_chunked(kern, runs, mc.chunk, mc.seed + 7919 * c + 31 * b_i, progress=ctx.progress)
                n = int(st["n"])
                p = float(st["count"]) / n
                base = dict(column=label(lag), lag=_lag_value(lag), arrival=lam, mean_burst=L, p_gb=p_gb, p_bg=p_bg,
                            iid=float(abs(L - 1 / lam) < 1e-12), eps=self.eps)
                rows.append(dict(base, series="exact", value=ex.value, stderr=ex.width / 2, n=np.nan))
                rows.append(dict(base, series="monte_carlo", value=p, stderr=float(proportion_stderr(p, n)), n=n))
                rows.append(dict(base, series="z_mc_vs_exact", value=_z(p, ex.value, n), stderr=np.nan, n=n))
        table = pd.DataFrame(rows)
        meta = {"paper": PAPER + ", Table I under Gilbert–Elliott loss (extension)", "k1": k1,
                "channel": "two-state Markov (Gilbert): γ is the state; P(loss→arrival) = 1/L_B; stationary arrival rate fixed",
                "arrival_rate": "each column's eq. (8) rate" if self.common_rate is None else self.common_rate,
                "monte_carlo": {"runs": runs, "sample": f"one per run at k = burn_in = {mc.burn_in}, chain started stationary"}}
        return Artefact(table, meta=meta)

    def plot(self, tables, scenario):
        t = tables["main"]
        fig, ax = new_figure(width=7.0, height=4.8)
        eps = float(t.eps.iloc[0])
        for j, c in enumerate(dict.fromkeys(t.column)):
            e = t[(t.column == c) & (t.series == "exact")].sort_values("mean_burst")
            m = t[(t.column == c) & (t.series == "monte_carlo")].sort_values("mean_burst")
            lam = float(e.arrival.iloc[0])
            ax.plot(e.mean_burst, e.value, "-", color=f"C{j}", label=f"{c.replace('_', '')} at λ = {lam:.3f}")
            ax.errorbar(m.mean_burst, m.value, yerr=m.stderr, fmt="o", ms=3, color=f"C{j}", capsize=2)
            iid = e[e.iid > 0]
            ax.plot(iid.mean_burst, iid.value, "*", ms=11, color=f"C{j}", mec="k", mew=0.6)
        ax.axhline(1 - eps, color="k", ls="--", lw=1, label=f"1 − ε = {1 - eps:g} (the guarantee of eq. 8, i.i.d. only)")
        ax.plot([], [], "*", color="0.5", mec="k", label="i.i.d. point (L_B = 1/λ)")
        ax.set_xscale("log")
        ax.set_xlabel("mean loss-burst length L_B (steps, log scale)")
        ax.set_ylabel(r"$\mathbb{P}(P_{k|k+N} \leq M)$")
        rates = t.arrival.unique()
        if len(rates) == 1:
            ax.set_title(f"Smoothing under Gilbert–Elliott loss, common stationary arrival rate λ = {rates[0]:g}", fontsize=10)
        else:
            ax.set_title("Table I under Gilbert–Elliott loss: each column at its eq. (8) stationary rate", fontsize=10)
        ax.legend(fontsize=7, loc="lower left")
        n = t[t.series == "monte_carlo"].n
        footnote(fig, f"Lines: exact (enumeration over the Markov arrival pattern); dots: Monte Carlo ±1 s.e. "
                      f"({int(n.iloc[0])} runs per point).")
        return fig
