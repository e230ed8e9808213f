"""Leong, Dey & Evans 2008 — Kalman smoothing with random packet loss: the artefacts.

* ``kind: smoothing_table1`` — Table I: for P_{k|k−1}, P_{k|k}, P_{k|k+1…N} the sufficient arrival
  rate (eqs 7–8), the probability simulated the paper's way (one long run, time average, batch-means
  standard error), a high-precision Monte Carlo (independent runs, one sample each) and the exact
  stationary probability (enumeration, certified bracket), next to the printed row.
* ``kind: smoothing_critical_rate`` — Lemma 1: exact E[P_{k|k−1}], E[P_{k|k+N}] against λ, diverging
  together at λ_c = 1 − 1/a²; Monte Carlo means flagged unreliable where E[P²] = ∞ (not plotted).
* ``kind: smoothing_retransmission`` — Sec. V: CDF of P_{k|k} without / with deterministic and random
  retransmission and with a lag-N smoother on the same channel; two-sample KS statistics against
  their critical values; g(n) = 1 (eqs 10–11).
* ``kind: smoothing_burstiness`` — the Table I experiment under Gilbert–Elliott loss with the same
  stationary loss rate: exact and Monte Carlo P(P_{k|k+N} ≤ M) against the mean burst length.

Time base (the Kalman core's): P0 = P_{0|0} = P̄ (``P0: steady``), so P_{1|0} = P*; step k carries
y_k. A column is a named quantity of an estimator at a step (:func:`netkf_cli.estimators.smoother.column_request`):
P_{k|k−1} = kf's ``predicted`` at step k − 1, P_{k|k} = ``filtered`` at k, P_{k|k+N} = the lag-N
smoother's ``smoothed`` at k + N. The Monte Carlo sample is at k = burn_in + 1 (burn_in Riccati
steps from P*).

Monte Carlo: Table I, the critical rate and the burstiness sweeps run the generic engine
(:func:`netkf_cli.engine.simulate`, the channel's own sampler) with :class:`ColumnReducer`; the
retransmission schemes (an arrival pattern that is not a channel) run
:class:`netkf_cli.estimators.smoother.RetransmissionKernel`, on the same core. Every independent
Monte Carlo computation of an artefact has its own ``stream`` of
:func:`netkf_cli.montecarlo.run_chunked` (chunk i of stream s draws from SeedSequence(seed,
spawn_key=(s, i))); lags compared with each other share one trace (common random numbers).
Proportions carry a Wilson 95 % interval (``ci_low``, ``ci_high``).
"""

from __future__ import annotations

import math
from fractions import Fraction
from typing import Literal

import numpy as np
import pandas as pd
from matplotlib.ticker import NullFormatter
from pydantic import Field, model_validator
from scipy import stats

from netkf_cli import engine, riccati
from netkf_cli.analysis import smoothing as sm
from netkf_cli.channels.bernoulli import BernoulliChannel
from netkf_cli.channels.gilbert_elliott import GilbertElliottChannel, markov_chain_of
from netkf_cli.errors import ConfigError
from netkf_cli.estimators.kf import KalmanFilterEstimator
from netkf_cli.estimators.smoother import (
    PRED,
    RetransmissionKernel,
    SmootherEstimator,
    covariance_stats,
    fixed_lag_smoother,
    lag_key,
    paper_way_indicators,
    resolve_backend,
)
from netkf_cli.montecarlo import proportion_stderr, run_chunked, wilson_interval
from netkf_cli.plotting import PALETTE, footnote, legend_outside, new_figure, paper_title, series_style
from netkf_cli.recipes.base import Artefact, RunContext
from netkf_cli.spec import AnalysisModel, PositiveFloat, PositiveInt, Probability, StrictModel

PAPER = "Leong, Dey & Evans 2008"
TOPIC = "smoothing"

MAX_EXACT_LAG = sm.MAX_EXACT_LAG
"""Largest lag of an artefact with exact values: the enumeration visits 2^(N+1) future patterns."""
MAX_GRID = 200
"""Largest number of points of a λ grid, burst list or CDF grid (each point runs a Monte Carlo or an enumeration)."""
MAX_PAPER_STEPS = 200_000
"""Longest "paper's way" run (its covariances are kept for every step and column: memory is linear in it)."""


def label(lag: int | None) -> str:
    """Column label of Table I: P_k|k-1, P_k|k, P_k|k+N."""
    if lag is None:
        return "P_k|k-1"
    return "P_k|k" if lag == 0 else f"P_k|k+{lag}"


def tex_label(lag: int | None) -> str:
    if lag is None:
        return r"$P_{k|k-1}$"
    return r"$P_{k|k}$" if lag == 0 else rf"$P_{{k|k+{lag}}}$"


def _tex_of_column(c: str) -> str:
    """Mathtext of a CSV column label (``P_k|k+2`` → ``$P_{k|k+2}$``)."""
    return "$P_{" + c[2:] + "}$" if c.startswith("P_") else c


def _lag_value(lag: int | None) -> float:
    """Numeric lag column: −1 for the predictor P_{k|k−1}."""
    return -1.0 if lag is None else float(lag)


def _lags_from(values: list[int]) -> list[int | None]:
    return [None if v < 0 else int(v) for v in values]


def _code(lag: int | None) -> int:
    """Kernel lag code: :data:`PRED` (−1) for P_{k|k−1}."""
    return PRED if lag is None else int(lag)


def _check_lags(values: list[int], limit: int = MAX_EXACT_LAG) -> None:
    if not values:
        raise ValueError("lags must list at least one column")
    if any(v < -1 for v in values):
        raise ValueError("lags: use −1 for P_{k|k−1} and N ≥ 0 for P_{k|k+N}")
    if max(values) > limit:
        raise ValueError(f"lags: at most {limit} (the exact enumeration visits 2^(N+1) future arrival patterns), got {max(values)}")
    if len(set(values)) != len(values):
        raise ValueError("lags: each column once")


def _bernoulli_chain(lam: float) -> tuple[np.ndarray, np.ndarray]:
    """(T, π) of i.i.d. loss, from the channel's own chain (:func:`markov_chain_of`)."""
    return markov_chain_of(BernoulliChannel(kind="bernoulli", arrival=lam))


def _ge_channel(lam: float, burst: float) -> GilbertElliottChannel:
    """The Gilbert–Elliott channel at stationary arrival rate λ and mean loss burst L_B (its own
    parameterisation: p_bg = 1/L_B, p_gb = π_B p_bg/(1 − π_B))."""
    try:
        return GilbertElliottChannel(kind="gilbert_elliott", loss_rate=1.0 - lam, mean_burst=burst)
    except ValueError as e:
        raise ConfigError.at("analysis.mean_bursts", f"mean burst {burst:g} too short for loss rate {1 - lam:.4g} "
                                                     f"(needs ≥ {(1 - lam) / lam:.4g})") from e


def _backend(scenario) -> str:
    """The smoother backend: the scenario's ``estimator: {kind: smoother, backend: …}`` if given, else auto
    (auto stays auto: the smoother picks the compiled kernel only where it is measured faster)."""
    for es in scenario.estimator_list():
        if isinstance(es, SmootherEstimator):
            resolve_backend(es.backend)
            return es.backend
    return "auto"


def sample_step(mc) -> int:
    """The time k of the Monte Carlo sample: burn_in + 1 (burn_in Riccati steps from P_{1|0} = P*)."""
    return int(mc.burn_in) + 1


class ColumnReducer:
    """Engine reducer: estimator j's covariance at its own step ``steps[j]`` → the additive statistics
    of :func:`netkf_cli.estimators.smoother.covariance_stats` under key ``keys[j]`` (count ≤ M in the
    PSD order, Σ tr, Σ tr², non-finite runs)."""

    def __init__(self, keys: list[str], steps: list[int], M: np.ndarray | None):
        self.keys, self.steps, self.M = list(keys), [int(k) for k in steps], M

    def update(self, stats: dict, j: int, k: int, P: np.ndarray, w: np.ndarray | None = None) -> None:
        if w is not None:
            raise ValueError("ColumnReducer counts unweighted samples (no variance-reduced estimator here)")
        if k == self.steps[j]:
            stats.update(covariance_stats(P, self.M, self.keys[j]))


def columns_monte_carlo(system, channel, codes, k: int, M, *, runs: int, mc, stream: int, backend: str = "auto",
                        progress=None, label: str = "") -> dict:
    """Monte Carlo statistics of the columns ``codes`` (−1 = P_{k|k−1}, N ≥ 0 = P_{k|k+N}) at time k,
    through :func:`netkf_cli.engine.simulate` on ``channel``'s traces: the predictor is kf's ``predicted``
    at step k − 1, the others the lag-N smoothers' ``smoothed`` at k + N. Both engine calls draw the same
    traces (same seed, stream, chunking and horizon k + max N): every column on common random numbers."""
    horizon = k + max(max(codes), 0)
    st: dict = {}
    groups = [("predicted", [c for c in codes if c == PRED]), ("smoothed", [c for c in codes if c >= 0])]
    last = [q for q, cs in groups if cs][-1]
    for q, cs in groups:
        if not cs:
            continue
        if q == "predicted":
            ests, steps = [KalmanFilterEstimator(kind="kf")], [k - 1]
        else:
            ests = [SmootherEstimator(kind="smoother", lag=c, backend=backend) for c in cs]
            steps = [k + c for c in cs]
        red = ColumnReducer([lag_key(c) for c in cs], steps, M)
        st.update(engine.simulate(system, channel, ests, red, steps=sorted(set(steps)), runs=runs, horizon=horizon,
                                  seed=mc.seed, chunk=mc.chunk, stream=stream, progress=progress if q == last else None,
                                  label=label, quantity=q))
    return st


def _z(p: float, exact: float, n: int) -> float:
    se0 = math.sqrt(max(exact * (1 - exact), 0.0) / n)
    return abs(p - exact) / se0 if se0 > 0 else (0.0 if p == exact else math.inf)


def _wilson(count: int, n: int) -> tuple[float, float]:
    lo, hi = wilson_interval(count, n)
    return float(lo), float(hi)


def _mc_row(base: dict, series: str, count: int, n: int, **extra) -> dict:
    """A Monte Carlo proportion row: value, binomial s.e., Wilson 95 % interval."""
    p = count / n
    lo, hi = _wilson(count, n)
    return dict(base, series=series, value=p, stderr=float(proportion_stderr(p, n)), ci_low=lo, ci_high=hi, n=n, **extra)


NO_CI = dict(ci_low=np.nan, ci_high=np.nan)


# =============================================================================================
# Table I
# =============================================================================================


class Table1(AnalysisModel):
    """``kind: smoothing_table1`` — Table I of Leong, Dey & Evans 2008 (Sec. IV)."""

    kind: Literal["smoothing_table1"]
    M: PositiveFloat | list[list[float]] = Field(description="covariance bound M (scalar means M·Iₙ)")
    eps: float = Field(gt=0, lt=1, description="ε of the constraint P(P ≤ M) > 1 − ε")
    lags: list[int] = Field([-1, 0, 1, 2, 3, 4], description=f"columns: −1 = P_{{k|k−1}}, N ≥ 0 = P_{{k|k+N}} (N ≤ {MAX_EXACT_LAG})")
    paper_steps: PositiveInt = Field(100_000, le=MAX_PAPER_STEPS,
                                     description="length of the single run 'simulated the paper's way' (steps)")
    paper_batches: PositiveInt = Field(50, ge=2, le=1000, description="batches for the batch-means standard error of the single run")
    printed_lambda: list[float] | None = Field(None, description="the printed arrival-rate row λ (for the side-by-side table)")
    printed_prob: list[float] | None = Field(None, description="the printed probability row P(P ≤ M)")

    @model_validator(mode="after")
    def _check(self):
        _check_lags(self.lags)
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
        backend = _backend(scenario)
        lags = _lags_from(self.lags)
        steps = self.paper_steps if ctx.runs is None else min(self.paper_steps, 10 * int(ctx.runs))
        ctx.total(runs * len(lags))
        lams = [sm.sufficient_arrival_rate(k1, self.eps, lag) for lag in lags]
        rows = []
        # --- the paper's way: one run of `steps` steps per column (each at its own rate), all columns at once
        rng = np.random.default_rng(np.random.SeedSequence(mc.seed, spawn_key=(10_000,)))
        g = np.vstack([rng.random(steps) < lam for lam in lams])  # (columns, steps)
        burn = min(mc.burn_in, steps // 10)
        ind = paper_way_indicators(s, np.ascontiguousarray(g.T), [_code(l) for l in lags], M, burn, backend=backend)
        paper = []
        for c in range(len(lags)):
            ok = ind[:, c].astype(float)
            bm = np.array([b.mean() for b in np.array_split(ok, self.paper_batches)])
            p, se = float(ok.mean()), float(bm.std(ddof=1) / math.sqrt(len(bm)))
            # effective sample size of the correlated indicators (batch means), for a Wilson interval
            n_eff = min(len(ok), p * (1 - p) / se**2) if se > 0 else float(self.paper_batches)
            lo, hi = _wilson(p * n_eff, n_eff)
            paper.append((p, se, len(ok), lo, hi))
        # --- high precision: independent runs, one sample each; column c is Monte Carlo stream c
        exact = []
        for c, (lag, lam) in enumerate(zip(lags, lams)):
            st = columns_monte_carlo(s, BernoulliChannel(kind="bernoulli", arrival=lam), [_code(lag)], sample_step(mc), M,
                                     runs=runs, mc=mc, stream=c, backend=backend, progress=ctx.progress, label=label(lag))
            n = int(st["n"])
            key = lag_key(_code(lag))
            count = int(st[f"leq_{key}"])
            T, pi = _bernoulli_chain(lam)
            ex = sm.exact_probability(s, M, lag, T, pi)
            exact.append(ex)
            base = dict(column=label(lag), lag=_lag_value(lag), k1=k1, eps=self.eps)
            pr_l = self.printed_lambda[c] if self.printed_lambda else np.nan
            pr_p = self.printed_prob[c] if self.printed_prob else np.nan
            p = count / n
            rows += [
                dict(base, series="lambda_eq8", value=lam, stderr=0.0, **NO_CI, n=np.nan, printed=pr_l),
                dict(base, series="prob_paper_way", value=paper[c][0], stderr=paper[c][1], ci_low=paper[c][3],
                     ci_high=paper[c][4], n=paper[c][2], printed=pr_p),
                _mc_row(base, "prob_monte_carlo", count, n, printed=pr_p),
                dict(base, series="prob_exact", value=ex.value, stderr=ex.width / 2, **NO_CI, n=np.nan, printed=pr_p),
                dict(base, series="z_mc_vs_exact", value=_z(p, ex.value, n), stderr=np.nan, **NO_CI, n=n, printed=np.nan),
                dict(base, series="overflow_runs", value=float(st[f"overflow_{key}"]), stderr=np.nan, **NO_CI, n=n, printed=np.nan),
            ]
        table = pd.DataFrame(rows)
        md = self._markdown(table, lags)
        meta = {
            "paper": PAPER + ", Table I",
            "Mbar": Mbar, "k1": k1, "M": M, "eps": self.eps, "backend": backend,
            "lambda_rule": "eq. (7) 1 − ε^(1/k1) for P_k|k-1; eq. (8) 1 − ε^(1/(k1+N+1)) for P_k|k+N (N = 0: P_k|k)",
            "paper_way": {"steps": int(steps), "burn_in": int(burn), "batches": self.paper_batches,
                          "stderr": "batch means over consecutive blocks (the indicator is autocorrelated)",
                          "ci": "Wilson 95 % at the effective sample size p(1−p)/stderr²",
                          "seed": f"SeedSequence({mc.seed}, spawn_key=(10000,))"},
            "time_base": "P0 = P_{0|0} = P̄, P_{1|0} = P*; P_k|k-1 = predicted at step k-1, P_k|k+N = smoothed (lag N) at step k+N",
            "monte_carlo": {"runs": runs, "sample": f"one sample per run at k = burn_in + 1 = {sample_step(mc)} "
                                                    f"({mc.burn_in} Riccati steps from P_{{1|0}} = P*), engine.simulate",
                            "streams": "column c (in the order of `lags`) is stream c",
                            "stderr": "binomial sqrt(p(1-p)/n); ci_low/ci_high: Wilson 95 %"},
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
        fig, axes = new_figure(ncols=2, width=6.4, height=5.0, gridspec_kw={"width_ratios": [1.0, 1.15]})
        ax = axes[0]
        x = np.arange(len(cols))
        get = lambda s_: t[t.series == s_].set_index("column").loc[cols]  # noqa: E731
        lam, pw, mcv, ex = get("lambda_eq8"), get("prob_paper_way"), get("prob_monte_carlo"), get("prob_exact")
        eps = float(t.eps.iloc[0])
        ax.axhline(1 - eps, color="0.3", ls=":", lw=1, label=rf"$1-\varepsilon$ = {1 - eps:g}")
        if np.isfinite(pw.printed).any():
            ax.plot(x, pw.printed, "s", mfc="none", color=PALETTE[1], ms=10, mew=1.5, ls="none", label="printed (Table I)")
        ax.errorbar(x - 0.15, pw.value, yerr=[pw.value - pw.ci_low, pw.ci_high - pw.value], fmt="^", color=PALETTE[4],
                    capsize=3, label="paper's way (1 run, 95 % CI)")
        ax.errorbar(x + 0.15, mcv.value, yerr=[mcv.value - mcv.ci_low, mcv.ci_high - mcv.value], fmt="o", color=PALETTE[0],
                    capsize=3, label="Monte Carlo (Wilson 95 % CI)")
        ax.plot(x, ex.value, "_", color="k", ms=20, mew=2, ls="none", label="exact (enumeration)")
        ax.set_xticks(x, [_tex_of_column(c) for c in cols])
        ax.set_xlabel("estimate (column of Table I)")
        ax.set_ylabel(r"$\Pr[P \leq M]$ at the rate of eq. (7)/(8)")
        ax.set_title("probability at the sufficient arrival rate")
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2, borderaxespad=0.0)
        printed = [float(v) for v in pw.printed if np.isfinite(v)]
        lo = float(np.nanmin([pw.ci_low.min(), mcv.ci_low.min(), ex.value.min(), *printed, 1 - eps]))
        hi = float(np.nanmax([pw.ci_high.max(), mcv.ci_high.max(), ex.value.max(), *printed]))
        ax.set_ylim(lo - 0.15 * (hi - lo), hi + 0.1 * (hi - lo))
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
        rl = [r"$\lambda$ printed", r"$\lambda$ eq. (7)/(8)", "P printed", "paper's way", "Monte Carlo", "exact"]
        tb = ax2.table(cellText=cell, rowLabels=rl, colLabels=[_tex_of_column(c) for c in cols], loc="center", cellLoc="center")
        tb.auto_set_font_size(False)
        tb.set_fontsize(9)
        tb.scale(1.0, 1.7)
        for j in range(len(cols)):
            for i in (1, 3):
                tb[(i, j)].set_facecolor("#f3e3e3")
        ax2.set_title(f"A = {_num(scenario.system.A)}, C = {_num(scenario.system.C)}, Q = {_num(scenario.system.Q)}, "
                      f"R = {_num(scenario.system.R)}, M = {_num(self.M)}, " + rf"$\varepsilon$ = {eps:g}")
        fig.suptitle(paper_title(TOPIC, "Table I", r"sufficient arrival rates and $\Pr[P_{k|k+N} \leq M]$"))
        n = int(mcv.n.iloc[0])
        footnote(fig, f"Monte Carlo: {n} independent runs, one sample each; paper's way: one run of "
                      f"{int(pw.n.iloc[0])} steps (batch-means s.e.); exact: enumeration (certified). Shaded rows: printed.")
        return fig


def _num(x) -> str:
    a = np.asarray(x, dtype=float)
    return f"{float(a.ravel()[0]):g}" if a.size == 1 else np.array2string(a, precision=3)


# =============================================================================================
# Lemma 1 — critical arrival rate
# =============================================================================================


class LambdaGrid(StrictModel):
    """An evenly spaced grid of arrival rates λ."""

    start: Probability = Field(description="smallest arrival rate λ (in (0, 1))")
    stop: Probability = Field(description="largest arrival rate λ (in (0, 1))")
    num: PositiveInt = Field(30, le=MAX_GRID, description=f"number of grid points (at most {MAX_GRID})")

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
    lambdas: list[Probability] | LambdaGrid = Field(description="arrival rates λ (list or {start, stop, num})")
    lags: list[int] = Field([-1, 0, 1, 3], description=f"−1 = P_{{k|k−1}}, N ≥ 0 = P_{{k|k+N}} (N ≤ {sm.MAX_MEAN_LAG})")
    exact_tol: PositiveFloat = Field(1e-10, ge=1e-14, description="per-node trace tolerance of the exact enumeration of E[P]")
    monte_carlo: bool = Field(True, description="also estimate E[tr P] by Monte Carlo at k = burn_in")

    @model_validator(mode="after")
    def _check(self):
        _check_lags(self.lags, sm.MAX_MEAN_LAG)
        if isinstance(self.lambdas, list):
            if not self.lambdas or len(self.lambdas) > MAX_GRID:
                raise ValueError(f"lambdas: between 1 and {MAX_GRID} arrival rates, got {len(self.lambdas)}")
            if any(not 0 < v < 1 for v in self.lambdas):
                raise ValueError("lambdas: arrival rates must lie in (0, 1)")
        return self

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        s = scenario.linear_system()
        sm.leong_mbar(s, path="system.C")  # C invertible needed for the exact means
        lam_c = sm.critical_rate(s)
        lam_2 = sm.second_moment_rate(s)
        lams = self.lambdas.values() if isinstance(self.lambdas, LambdaGrid) else np.asarray(self.lambdas, float)
        lags = _lags_from(self.lags)
        mc = scenario.montecarlo
        runs = ctx.mc_runs(scenario)
        backend = _backend(scenario)
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
                rows.append(dict(base, series="exact", value=0.5 * (lo + hi), stderr=0.5 * (hi - lo), n=np.nan,
                                 reliable=1.0, heavy_tail=0.0))
            for lag in lags:
                if lag is None:
                    continue
                with np.errstate(over="ignore", invalid="ignore"):
                    lb = (1 - lam) ** (lag + 1) * exact[None][0] if None in exact else np.nan
                rows.append(dict(lam=float(lam), lag=_lag_value(lag), column=label(lag), lambda_c=lam_c, lambda_2=lam_2,
                                 series="lemma1_lower", value=lb, stderr=0.0, n=np.nan, reliable=1.0, heavy_tail=0.0))
            if self.monte_carlo:
                # all lags on one trace (common random numbers); grid point i is Monte Carlo stream i
                st = columns_monte_carlo(s, BernoulliChannel(kind="bernoulli", arrival=float(lam)), [_code(l) for l in lags],
                                         sample_step(mc), None, runs=runs, mc=mc, stream=i, backend=backend,
                                         progress=ctx.progress, label=f"λ={lam:.3f}")
                n = int(st["n"])
                for lag in lags:
                    key = lag_key(_code(lag))
                    over = int(st[f"overflow_{key}"])
                    nf = n - over
                    mean, se = math.inf, math.inf
                    if not over and nf >= 2:
                        with np.errstate(over="ignore", invalid="ignore"):
                            m_ = np.float64(st[f"sum_tr_{key}"]) / nf
                            var = (np.float64(st[f"sumsq_tr_{key}"]) / nf - m_ * m_) * nf / (nf - 1)
                        if np.isfinite(m_):
                            mean = float(m_)
                            se = math.sqrt(max(float(var), 0.0) / nf) if np.isfinite(var) else math.inf
                    heavy = float(lam <= lam_2)  # E[P²] = ∞: the sample mean has no finite standard error
                    rows.append(dict(lam=float(lam), lag=_lag_value(lag), column=label(lag), lambda_c=lam_c, lambda_2=lam_2,
                                     series="monte_carlo", value=mean, stderr=se, n=n,
                                     reliable=float(not heavy and math.isfinite(mean)), heavy_tail=heavy))
        table = pd.DataFrame(rows)
        meta = {"paper": PAPER + ", Lemma 1 (Sec. III)", "lambda_c": lam_c, "lambda_c_rule": "1 − 1/ρ(A)² (exact for C invertible)",
                "lambda_second_moment": lam_2, "backend": backend,
                "reliable": "Monte Carlo means are flagged heavy_tail = 1, reliable = 0 for λ ≤ 1 − 1/ρ(A)⁴ where E[P²] = ∞: "
                            "the sample mean has no finite standard error there; they are not plotted",
                "value": "trace of the stationary mean; exact = midpoint of a certified bracket (stderr = half-width)",
                "monte_carlo": {"runs": runs, "sample": f"one sample per run at k = burn_in + 1 = {sample_step(mc)} "
                                                        f"({mc.burn_in} Riccati steps from P_{{1|0}} = P*), engine.simulate",
                                "streams": "grid point i (in the order of `lambdas`) is stream i; all lags share its traces"}}
        return Artefact(table, meta=meta)

    def plot(self, tables, scenario):
        t = tables["main"]
        fig, ax = new_figure(width=9.6, height=5.2)
        lam_c, lam_2 = float(t.lambda_c.iloc[0]), float(t.lambda_2.iloc[0])
        cols = list(dict.fromkeys(t.column))
        hidden = 0
        for j, c in enumerate(cols):
            st_ = series_style(j)
            e = t[(t.column == c) & (t.series == "exact") & np.isfinite(t.value)]
            ax.plot(e.lam, e.value, color=st_["color"], ls=st_["linestyle"], label=f"exact E[tr {_tex_of_column(c)}]")
            m = t[(t.column == c) & (t.series == "monte_carlo")]
            good = m[(m.reliable > 0) & np.isfinite(m.value)]
            hidden += int(len(m) - len(good))
            if len(good):
                ax.errorbar(good.lam, good.value, yerr=1.96 * good.stderr, fmt=st_["marker"], ms=4, color=st_["color"],
                            capsize=2, ls="none", label=f"Monte Carlo E[tr {_tex_of_column(c)}] (95 % CI)")
            lb = t[(t.column == c) & (t.series == "lemma1_lower") & np.isfinite(t.value)]
            if len(lb) and c == cols[-1]:
                N = c.split("+")[1] if "+" in c else "0"
                ax.plot(lb.lam, lb.value, ":", color="0.35", lw=1.2,
                        label=rf"$(1-\lambda)^{{{int(N) + 1}}}\,$E[tr $P_{{k|k-1}}$] (Lemma 1 bound, {_tex_of_column(c)})")
        drawn = t[(t.series != "lemma1_lower") & np.isfinite(t.value) & (t.value > 0)]
        if len(drawn):
            ax.set_yscale("log")
        else:
            ax.text(0.5, 0.5, r"E[P] = ∞ at every $\lambda$ of the grid ($\lambda \leq \lambda_c$)", transform=ax.transAxes,
                    ha="center", va="center", fontsize=10)
        ax.axvline(lam_c, color="k", lw=1.2, ls="--", label=rf"$\lambda_c = 1 - 1/a^2$ = {lam_c:.4f}")
        ax.axvline(lam_2, color="0.4", lw=0.8, ls="-.", label=rf"$1 - 1/a^4$ = {lam_2:.3f} (E[$P^2$] = ∞ below)")
        if t.lam.min() < lam_c:
            ax.axvspan(t.lam.min(), lam_c, color="0.85", alpha=0.5, lw=0)
        ax.set_xlabel(r"arrival rate $\lambda$")
        ax.set_ylabel("stationary E[tr P] (log scale)")
        ax.set_title(paper_title(TOPIC, "Lemma 1", "smoothing does not move the critical arrival rate"))
        if ax.get_legend_handles_labels()[1]:
            legend_outside(ax)
        n = t[t.series == "monte_carlo"].n
        note = (f"Lines: exact stationary means (certified brackets); markers: Monte Carlo at k = burn-in "
                f"({int(n.iloc[0]) if len(n) else 0} runs per λ). Shaded: E[P] = ∞ (λ ≤ λ_c).")
        if hidden:
            note += f" {hidden} Monte Carlo means at λ ≤ 1 − 1/a⁴ (no finite standard error) are in the CSV, not plotted."
        footnote(fig, note)
        return fig


# =============================================================================================
# Section V — retransmission
# =============================================================================================

KS_ALPHA = 0.05


def ks_critical(n1: int, n2: int, alpha: float = KS_ALPHA) -> float:
    """Asymptotic two-sample KS critical value c(α)·√((n₁+n₂)/(n₁n₂)), c(α) = √(−ln(α/2)/2)."""
    return math.sqrt(-0.5 * math.log(alpha / 2)) * math.sqrt((n1 + n2) / (n1 * n2))


class Retransmission(AnalysisModel):
    """``kind: smoothing_retransmission`` — Sec. V: retransmission vs filtering vs smoothing."""

    kind: Literal["smoothing_retransmission"]
    N: PositiveInt = Field(2, le=MAX_EXACT_LAG, description=f"retransmission budget N (and the smoother lag: the same latency; ≤ {MAX_EXACT_LAG})")
    p: list[Probability] = Field([1.0, 0.5], min_length=1, max_length=10,
                                 description="probabilities p of asking for a retransmission (1 = deterministic, Sec. V-A)")
    M: PositiveFloat = Field(description="threshold M of the reported P(P_{k|k} ≤ M)")
    grid: PositiveInt = Field(120, ge=10, le=MAX_GRID, description=f"points of the CDF grid (10 … {MAX_GRID})")
    g_n_max: PositiveInt = Field(30, le=200, description="largest n of the g(n) = 1 check (eqs 10–11; ≤ 200)")
    g_check_N: list[PositiveInt] = Field([1, 2, 3, 5], min_length=1, max_length=10, description="budgets N of the g(n) check")
    g_check_p: list[Probability] = Field([0.0, 0.3, 0.5, 0.9, 1.0], min_length=1, max_length=10, description="p values of the g(n) check")

    @model_validator(mode="after")
    def _check(self):
        if max(self.g_check_N) > 50:
            raise ValueError(f"g_check_N: budgets up to 50, got {max(self.g_check_N)}")
        if len(set(f"{p:g}" for p in self.p)) != len(self.p):
            raise ValueError("p: each probability once")
        return self

    def _grid(self, s, lam: float) -> np.ndarray:
        """The CDF grid (fixed before the Monte Carlo: the kernel counts x ≤ grid): from just below the
        perfect-channel smoother's P_{k|k+N} to the filter's P after K losses in a row, (1−λ)^K ≈ 10⁻³, and M."""
        n = s.n
        ones = np.ones((1, 400), bool)
        low = fixed_lag_smoother(s, ones, self.N, times=[399 - self.N]).smooth[0, self.N, :, :, 0]
        K = int(math.ceil(math.log(1e-3) / math.log(1 - lam))) if lam < 1 else 1
        P = riccati.pbar(s)
        with np.errstate(over="ignore", invalid="ignore"):
            for _ in range(min(K, 10_000)):
                Pn = riccati.h(P, s)
                if not np.isfinite(Pn).all() or np.trace(Pn) > 1e12:
                    break
                P = Pn
        lo, hi = 0.97 * float(np.trace(low)), 1.01 * float(np.trace(P))  # × 1.01: not on an atom of the law
        hi = max(hi, 1.5 * self.M * n, 2 * lo)
        return np.unique(np.concatenate([np.geomspace(lo, hi, self.grid), [float(self.M) * (1 if n == 1 else n)]]))

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        s = scenario.linear_system()
        ch = scenario.require_channel("bernoulli")
        lam = float(ch.arrival)
        if not 0 < lam < 1:
            raise ConfigError.at("channel.arrival", f"must be in (0, 1) for a loss channel, got {lam}")
        mc = scenario.montecarlo
        runs = ctx.mc_runs(scenario)
        backend = _backend(scenario)
        N = self.N
        if mc.burn_in < 12:
            raise ConfigError.at("montecarlo.burn_in", f"must be ≥ 12 (the effective rate is measured over y_11 … y_burn_in), "
                                                       f"got {mc.burn_in}")
        k = sample_step(mc)  # well before the end: late retransmissions are complete by then
        xs = self._grid(s, lam)
        kern = RetransmissionKernel(system=s, lam=lam, N=N, ps=tuple(float(p) for p in self.p), k=k, M=float(self.M),
                                    grid=xs, backend=backend)
        ctx.total(runs)
        st = run_chunked(kern, runs, mc.chunk, mc.seed, stream=0, progress=ctx.progress, label="retransmission")
        n = int(st["n"])
        schemes = kern.schemes()
        rows = []
        Tm, pi = _bernoulli_chain(lam)
        scalar = s.n == 1
        F = {sc: np.asarray(st[f"cdf_{sc}"], dtype=float) / n for sc in schemes}
        for sc in schemes:
            cnt = np.asarray(st[f"cdf_{sc}"])
            lo, hi = wilson_interval(cnt, n)
            for x, c_, l_, h_ in zip(xs, cnt, lo, hi):
                f = c_ / n
                rows.append(dict(scheme=sc, series="ecdf", x=float(x), value=float(f), stderr=float(proportion_stderr(f, n)),
                                 ci_low=float(l_), ci_high=float(h_), n=n))
        if scalar:
            for sc, lag in (("filter", 0), (f"smoother_lag{N}", N)):
                for x in xs:
                    ex = sm.exact_probability(s, float(x), lag, Tm, pi, tol=1e-12)
                    rows.append(dict(scheme=sc, series="exact_cdf", x=float(x), value=ex.value, stderr=ex.width / 2, **NO_CI, n=np.nan))
        table = pd.DataFrame(rows)
        # two-sample KS on the grid (D on the grid ≤ the full-sample D), against its 5 % critical value
        summ = []
        crit = ks_critical(n, n)
        for p in self.p:
            sc = f"retx_p{p:g}"
            for other in ("filter", f"smoother_lag{N}"):
                D = float(np.max(np.abs(F[sc] - F[other])))
                pval = float(stats.kstwobign.sf(D * math.sqrt(n * n / (2 * n))))
                summ.append(dict(quantity="ks_statistic", scheme=sc, versus=other, value=D, p_value=pval,
                                 critical=crit, stderr=np.nan, **NO_CI, n=n))
            ones, pairs, cnt = (int(st[f"{q}_{sc}"]) for q in ("ones", "pairs", "slots"))
            summ.append(dict(quantity="effective_arrival_rate", scheme=sc, versus="lambda", value=ones / cnt, p_value=np.nan,
                             critical=np.nan, stderr=np.nan, **NO_CI, n=cnt))
            summ.append(dict(quantity="effective_P11", scheme=sc, versus="lambda^2", value=pairs / (cnt * (k - 12) / (k - 11)),
                             p_value=np.nan, critical=np.nan, stderr=np.nan, **NO_CI, n=cnt))
        for sc in schemes:
            c_ = int(st[f"leq_{sc}"])
            summ.append(_mc_row(dict(quantity="prob_leq_M", scheme=sc, versus="-"), "prob_leq_M", c_, n, p_value=np.nan,
                                critical=np.nan))
            summ[-1].pop("series")
        if scalar:
            for sc, lag in (("filter", 0), (f"smoother_lag{N}", N)):
                ex = sm.exact_probability(s, self.M, lag, Tm, pi)
                summ.append(dict(quantity="prob_leq_M_exact", scheme=sc, versus="-", value=ex.value, p_value=np.nan,
                                 critical=np.nan, stderr=ex.width / 2, **NO_CI, n=np.nan))
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
        meta = {"paper": PAPER + ", Sec. V", "lambda": lam, "N": N, "p": self.p, "runs": runs, "backend": backend,
                "sample": f"one sample per run at k = {k} (retransmissions of measurements ≤ k are complete by the horizon {kern.horizon()})",
                "x": "P_k|k (trace if n > 1) — filter with and without retransmission; smoother P_k|k+N with the same latency N",
                "ks": ("two-sample Kolmogorov–Smirnov statistic D = max |F₁ − F₂| over the CDF grid (a lower bound of the "
                       f"full-sample D; the distribution has atoms, so the test is conservative), critical value at α = {KS_ALPHA} "
                       "c(α)√(2/n), asymptotic p-value"),
                "streams": "stream 0: filter and smoother share each run's channel trace; each retransmission scheme draws its own",
                "g_identity_max_abs_dev": float(np.max(np.abs(gtab.g_float - 1.0)))}
        return Artefact(table, meta=meta, extra_tables={"summary": summary, "g_identity": gtab})

    def plot(self, tables, scenario):
        t, summ = tables["main"], tables["summary"]
        fig, axes = new_figure(ncols=2, width=5.6, height=4.8, gridspec_kw={"width_ratios": [1.25, 1.0]})
        ax = axes[0]
        names = {}
        for j, sc in enumerate(dict.fromkeys(t.scheme)):
            if sc == "filter":
                name = "filter, no retransmission"
            elif sc.startswith("smoother"):
                name = "smoother, lag N = " + sc.replace("smoother_lag", "") + r" ($P_{k|k+N}$)"
            elif sc == "retx_p1":
                name = "deterministic retransmission (p = 1)"
            else:
                name = "random retransmission, p = " + sc.replace("retx_p", "")
            names[sc] = name
            e = t[(t.scheme == sc) & (t.series == "ecdf")]
            st_ = series_style(j)
            ax.step(e.x, e.value, where="post", color=st_["color"], ls=st_["linestyle"], lw=3.0 if sc == "filter" else 1.6,
                    alpha=0.6 if sc == "filter" else 1.0, label=name + " (MC)")
        x = t[t.series == "exact_cdf"]
        if len(x):
            for sc in dict.fromkeys(x.scheme):
                xx = x[x.scheme == sc]
                ax.step(xx.x, xx.value, where="post", color="k", lw=0.9, ls=":",
                        label="exact CDF (enumeration)" if sc == "filter" else "_nolegend_")
        ax.axvline(float(summ.M.iloc[0]), color="0.5", lw=0.8)
        ax.set_xscale("log")
        ax.set_xlabel(r"$P_{k|k}$ (smoother: $P_{k|k+N}$), log scale")
        ax.set_ylabel("empirical CDF")
        lam_, N_ = float(summ["lambda"].iloc[0]), int(summ.N.iloc[0])
        ax.set_title(rf"CDFs, $\lambda$ = {lam_:g}, N = {N_}, M = {float(summ.M.iloc[0]):g} (grey)")
        ax.legend(loc="lower right")  # the CDFs have all reached 1 there: an empty region
        ax2 = axes[1]
        ks = summ[summ.quantity == "ks_statistic"].reset_index(drop=True)
        y = np.arange(len(ks))
        crit = float(ks.critical.iloc[0])
        vs_f = ks.versus == "filter"
        ax2.plot(ks.value[vs_f], y[vs_f], "o", color=PALETTE[2], ms=8, ls="none", label="D vs the filter (same law?)")
        ax2.plot(ks.value[~vs_f], y[~vs_f], "s", color=PALETTE[1], ms=8, ls="none", label="D vs the smoother")
        ax2.axvline(crit, color="k", ls="--", lw=1)
        ax2.text(crit, len(ks) - 0.5, f" 5 % critical value\n {crit:.4f}", fontsize=9, va="top", ha="left")
        for yy, r in zip(y, ks.itertuples()):
            ax2.annotate(f"D = {r.value:.4f}", (r.value, yy), textcoords="offset points", xytext=(0, 8), ha="center", fontsize=9)
        ax2.set_yticks(y, [f"{names[r.scheme].replace(' retransmission', '')}\nvs {'filter' if r.versus == 'filter' else 'smoother'}"
                           for r in ks.itertuples()])
        ax2.set_xscale("log")
        ax2.set_xlim(min(ks.value.min(), crit) / 3, max(ks.value.max(), crit) * 3)
        ax2.set_ylim(-0.7, len(ks) - 0.3)
        ax2.set_xlabel("two-sample KS statistic D (log scale)")
        ax2.set_ylabel("scheme compared")
        ax2.set_title("same distribution as the filter?")
        ax2.legend(loc="center", bbox_to_anchor=(0.64, 0.5))  # between the critical value and the smoother's points
        fig.suptitle(paper_title(TOPIC, "Sec. V", r"retransmission vs filtering vs smoothing, CDF of $P_{k|k}$"))
        n = int(t[t.series == "ecdf"].n.iloc[0])
        footnote(fig, f"{n} runs per scheme, one sample each, the same Bernoulli channel law; retransmitted measurements "
                      "reach the filter up to N steps late. D below the dashed line: no evidence of a difference at 5 %.")
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
    M: PositiveFloat = Field(description="covariance bound M (scalar: M·Iₙ)")
    eps: float = Field(gt=0, lt=1, description="ε of the constraint P(P ≤ M) > 1 − ε (sets each column's eq. (8) rate)")
    lags: list[int] = Field([-1, 0, 1, 2, 3, 4], description=f"columns: −1 = P_{{k|k−1}}, N ≥ 0 = P_{{k|k+N}} (N ≤ {MAX_EXACT_LAG})")
    mean_bursts: list[PositiveFloat] = Field(min_length=1, max_length=50,
                                             description="mean loss-burst lengths L_B (steps, 1 ≤ L_B ≤ 10⁶) to sweep")
    common_rate: Probability | None = Field(None, description="use this stationary arrival rate λ for every column "
                                           "instead of each column's eq. (8) rate")

    @model_validator(mode="after")
    def _check(self):
        _check_lags(self.lags)
        if any(not 1 <= b <= 1e6 for b in self.mean_bursts):
            raise ValueError("mean_bursts: mean loss-burst lengths must lie in [1, 10⁶] steps")
        if self.common_rate is not None and not 0 < self.common_rate < 1:
            raise ValueError(f"common_rate: must be in (0, 1), got {self.common_rate}")
        return self

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        s = scenario.linear_system()
        if scenario.channel is not None and scenario.channel.kind != "gilbert_elliott":
            raise ConfigError.at("channel.kind", "smoothing_burstiness sweeps a gilbert_elliott channel; omit `channel` or use that kind")
        M = sm.as_bound(self.M, s.n)
        k1 = sm.k1(s, M)
        lags = _lags_from(self.lags)
        mc = scenario.montecarlo
        runs = ctx.mc_runs(scenario)
        backend = _backend(scenario)
        rates = {lag: (self.common_rate if self.common_rate is not None else sm.sufficient_arrival_rate(k1, self.eps, lag))
                 for lag in lags}
        # every (rate, burst) point that is realisable; Monte Carlo stream = index of the burst length in the
        # sorted union of all bursts (columns at one burst share uniforms: common random numbers)
        points = {}
        for lag in lags:
            lam = rates[lag]
            for L in sorted(set([float(b) for b in self.mean_bursts] + [1.0 / lam])):
                if L >= (1 - lam) / lam - 1e-12:
                    points.setdefault((lam, L), []).append(lag)
        all_bursts = sorted({L for _, L in points})
        stream_of = {L: i for i, L in enumerate(all_bursts)}
        ctx.total(runs * len(points))
        res = {}
        for (lam, L), group in points.items():
            ch = _ge_channel(lam, L)
            T, pi = markov_chain_of(ch)
            p_gb, p_bg = ch.transition
            st = columns_monte_carlo(s, ch, [_code(l) for l in group], sample_step(mc), M, runs=runs, mc=mc,
                                     stream=stream_of[L], backend=backend, progress=ctx.progress,
                                     label=f"λ={lam:.3f} L_B={L:g}")
            for lag in group:
                res[(lag, L)] = (T, pi, p_gb, p_bg, int(st[f"leq_{lag_key(_code(lag))}"]), int(st["n"]))
        rows = []
        for lag in lags:
            lam = rates[lag]
            for L in sorted(L_ for (l_, L_) in res if l_ == lag):
                T, pi, p_gb, p_bg, count, n = res[(lag, L)]
                ex = sm.exact_probability(s, M, lag, T, pi)
                base = dict(column=label(lag), lag=_lag_value(lag), arrival=lam, mean_burst=L, p_gb=p_gb, p_bg=p_bg,
                            iid=float(abs(L - 1 / lam) < 1e-12), eps=self.eps)
                rows.append(dict(base, series="exact", value=ex.value, stderr=ex.width / 2, **NO_CI, n=np.nan))
                rows.append(_mc_row(base, "monte_carlo", count, n))
                rows.append(dict(base, series="z_mc_vs_exact", value=_z(count / n, ex.value, n), stderr=np.nan, **NO_CI, n=n))
        table = pd.DataFrame(rows)
        meta = {"paper": PAPER + ", Table I under Gilbert–Elliott loss (extension)", "k1": k1, "backend": backend,
                "channel": "two-state Markov (Gilbert): γ is the state; P(loss→arrival) = 1/L_B; stationary arrival rate fixed",
                "arrival_rate": "each column's eq. (8) rate" if self.common_rate is None else self.common_rate,
                "monte_carlo": {"runs": runs, "sample": f"one per run at k = burn_in + 1 = {sample_step(mc)}, chain started stationary, engine.simulate",
                                "streams": "stream i = the i-th smallest burst length; columns at one (rate, burst) share traces",
                                "ci": "Wilson 95 %"}}
        return Artefact(table, meta=meta)

    def plot(self, tables, scenario):
        t = tables["main"]
        fig, ax = new_figure(width=9.6, height=5.2)
        eps = float(t.eps.iloc[0])
        for j, c in enumerate(dict.fromkeys(t.column)):
            st_ = series_style(j)
            e = t[(t.column == c) & (t.series == "exact")].sort_values("mean_burst")
            m = t[(t.column == c) & (t.series == "monte_carlo")].sort_values("mean_burst")
            lam = float(e.arrival.iloc[0])
            ax.plot(e.mean_burst, e.value, color=st_["color"], ls=st_["linestyle"],
                    label=rf"exact, {_tex_of_column(c)} at $\lambda$ = {lam:.3f}")
            ax.errorbar(m.mean_burst, m.value, yerr=[m.value - m.ci_low, m.ci_high - m.value], fmt=st_["marker"], ms=4,
                        color=st_["color"], capsize=2, ls="none", label=f"Monte Carlo, {_tex_of_column(c)} (95 % CI)")
            iid = e[e.iid > 0]
            ax.plot(iid.mean_burst, iid.value, "*", ms=12, color=st_["color"], mec="k", mew=0.6, ls="none",
                    label="i.i.d. point $L_B = 1/\\lambda$" if j == 0 else "_nolegend_")
        ax.axhline(1 - eps, color="k", ls="--", lw=1, label=rf"$1-\varepsilon$ = {1 - eps:g} (eq. 8's guarantee, i.i.d. only)")
        ax.set_xscale("log")
        ticks = sorted(set(t[t.iid <= 0].mean_burst.round(6)) | {1.0})
        ax.set_xticks(ticks, [f"{b:g}" for b in ticks])
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel(r"mean loss-burst length $L_B$ (steps, log scale)")
        ax.set_ylabel(r"$\Pr[P_{k|k+N} \leq M]$")
        rates = t.arrival.unique()
        if len(rates) == 1:
            what = rf"Gilbert–Elliott loss, all columns at $\lambda$ = {rates[0]:g}"
        else:
            what = "Gilbert–Elliott loss, columns at their eq. (8) rates"
        fig.suptitle(paper_title(TOPIC, "Table I (extension)", what))
        legend_outside(ax)
        n = t[t.series == "monte_carlo"].n
        footnote(fig, f"Lines: exact (enumeration over the Markov arrival pattern); markers: Monte Carlo with Wilson 95 % "
                      f"intervals ({int(n.iloc[0])} runs per point).")
        return fig
