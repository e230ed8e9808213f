"""``kind: burst_mean`` — E P_k at k = horizon by sequential Monte Carlo over the channel's drop bursts.

Near a stability limit the plain sample mean of P_k is dominated by long drop bursts it almost never
samples (a burst of L drops scales P by ~ρ^{2L}; with drop-continuation probability μ_c and μ_c ρ⁴ ≥ 1 its
variance is infinite). For an estimator that *renews* at a received packet — P_k depends only on the last
received packet's communication noise σ² and on the number L of drops since —

    E P_k = Σ_{L<k} E[1{received, then L drops} (σ² M1[L] + M2[L])] + Pr[k drops] D,

and the burst probabilities are estimated directly by a sequential Monte Carlo (a fully adapted particle
filter forced through the drop event, unbiased: Del Moral 2004, Thm 7.4.2), one independent pair of particle
clouds per Monte Carlo run, so the standard error over runs is honest.

Contract (refused with a message otherwise):

* the channel offers ``drop_law(threshold, horizon)``: a drop process made by thresholding a complex
  Gaussian gain (:class:`netkf_cli.channels.fading.GaussianDropLaw`: its Cholesky factor over the horizon,
  the mean SNR, σ_n²(Υ)); ``baseline: independent`` also needs ``independent()``, the same channel with
  its time correlation removed (same marginal law);
* one estimator offering ``renewal_refusal(system, quantity)`` (None when it renews) and
  ``renewal_coefficients(system, horizon, quantity)`` → (M1, M2, D), and ``threshold_of(channel)``.

Rows per point: ``series`` ``norm`` (‖E P_k‖₂, the spectral norm the fading papers plot; delta-method s.e.)
and ``trace`` (E tr P_k), for the channel and, with ``baseline: independent``, for its independent
counterpart (column ``channel``: correlated | independent) on the same random stream (common random
numbers); ``references`` rows (closed forms, at k = horizon) for each. Extra table ``bursts``: the
estimated Pr[received, then L drops] at ``burst_lags``. A mean with relative s.e. ≥ ``RELIABLE_REL_SE``
or an overflowed run is flagged ``reliable = 0`` and not drawn.
"""

from __future__ import annotations

import math
from typing import ClassVar, Literal

import numpy as np
from netkf_cli.core.lazy import pandas as pd
from pydantic import Field

from netkf_cli.core.artefact import Artefact, RunContext
from netkf_cli.core.errors import ConfigError
from netkf_cli.estimators.fading_receivers import BurstSMCKernel
from netkf_cli.metrics import derived
from netkf_cli.metrics.common import LABEL_COLUMNS, describe, GenericMetric, labels, math_text, needs, PaperRef
from netkf_cli.runtime.montecarlo import run_chunked
from netkf_cli.runtime.plotting import PALETTE, footnote, legend_outside, new_figure, paper_title, series_style
from netkf_cli.core.spec import PositiveInt
from netkf_cli.core.stats import mean_se
from netkf_cli.core.tolerances import ROUNDOFF_VARIANCE

RELIABLE_REL_SE = 0.05
"""A mean is flagged unreliable (not drawn) above 5 % relative standard error or with an overflowed run."""
COLUMNS = ["channel", "estimator", "series", "k", "value", "stderr", "n", "particles", "ess_frac", "min_ess_frac",
           "reliable", "overflowed", "source", "reference"] + LABEL_COLUMNS
BURST_COLUMNS = ["channel", "L", "value", "stderr", "n", "reliable"]


def norm_and_se(sumX: np.ndarray, sumXX: np.ndarray, N: int) -> tuple[float, float]:
    """‖mean‖₂ of symmetric matrices and its delta-method standard error: ``sumX`` (n, n) Σ X, ``sumXX``
    (n², n²) Σ vec X vec Xᵀ over N runs; ∂‖M‖/∂M = u uᵀ for the top eigenvector u."""
    M = sumX / N
    if not np.all(np.isfinite(M)):
        return math.inf, math.nan
    w, V = np.linalg.eigh((M + M.T) / 2)
    j = int(np.argmax(np.abs(w)))
    grad = np.outer(V[:, j], V[:, j]).ravel()
    cov = (sumXX / N - np.outer(M.ravel(), M.ravel())) * N / max(N - 1, 1)
    var = max(float(grad @ cov @ grad), 0.0)
    if var <= ROUNDOFF_VARIANCE * w[j] ** 2:  # the runs agree to rounding (stats.mean_se's rule): s.e. 0, not noise
        var = 0.0
    return float(abs(w[j])), math.sqrt(var / N)


class BurstMean(GenericMetric):
    """``kind: burst_mean`` — E P_k at k = horizon (‖·‖₂ and trace) by sequential Monte Carlo of the drop bursts."""

    draws_references: ClassVar[bool] = True

    works_with: ClassVar[str] = ("a channel with drop_law (drops threshold a Gaussian gain: fading) and one estimator "
                                 "with renewal_coefficients (receiver scenario 2, invertible C)")

    kind: Literal["burst_mean"]
    quantity: Literal["predicted"] = Field("predicted", description="P_{k+1|k} at k = horizon (from P_{0|0} = P0): "
                                                                    "the fading papers' P[k+1]")
    particles: PositiveInt = Field(32, description="particles per cloud (--quick: a quarter, at least 8; unbiased "
                                                   "either way); montecarlo.runs = independent cloud pairs")
    baseline: Literal["none", "independent"] = Field("none", description="independent: also the channel with its "
                                                                         "time correlation removed (same marginals)")
    burst_lags: list[int] = Field([0, 1, 2, 5, 10, 20, 50, 100, 200],
                                  description="burst lengths L whose Pr[received, then L drops] the bursts table reports")
    burst_panel: list[float] = Field(default_factory=list, description="values of the over grid's first path whose "
                                                                       "burst probabilities the figure draws")
    log_y: bool = Field(True, description="logarithmic y axis")
    x_label: str = Field("", description="x-axis label for the over grid (default: its first path)")
    paper: PaperRef | None = Field(None, description="the paper figure this reproduces (title only)")
    title: str = Field("", description="what the figure shows")

    def check(self, scenario) -> None:
        super().check(scenario)
        ch = needs(scenario, "channel")
        ests = needs(scenario, "estimators")
        if len(ests) != 1:
            raise ConfigError.at("estimators", "burst_mean takes one estimator (its renewal form drives the SMC)")
        e = ests[0]
        if not callable(getattr(ch, "drop_law", None)):
            raise ConfigError.at("channel.kind", f"burst_mean needs a channel whose drops threshold a Gaussian gain "
                                                 f"(drop_law: kind fading), got {ch.kind}")
        if self.baseline == "independent" and not callable(getattr(ch, "independent", None)):
            raise ConfigError.at("analysis.baseline", f"channel {ch.kind} has no independent counterpart")
        refusal = getattr(e, "renewal_refusal", None)
        if not callable(refusal):
            raise ConfigError.at("estimator.kind", f"burst_mean needs an estimator that renews at a received packet "
                                                   f"(renewal coefficients: receiver scenario 2), got {e.kind}")
        why = refusal(scenario.linear_system(), self.quantity)
        if why is not None:
            raise ConfigError.at("estimator.scenario", why)
        if e.threshold_of(ch) is None:
            raise ConfigError.at("estimator.threshold", "give the drop threshold Υ_T (here or as the channel's `threshold`)")
        if any(L < 0 for L in self.burst_lags):
            raise ConfigError.at("analysis.burst_lags", f"burst lengths are ≥ 0, got {self.burst_lags}")

    def reference_scenarios(self, scenario) -> list:
        """The scenario and, with ``baseline: independent``, its independent channel's (the references are drawn for
        each: an i.i.d.-only closed form gives rows for the baseline)."""
        ch = scenario.channel
        if self.baseline == "independent" and callable(getattr(ch, "independent", None)):
            return [scenario, scenario.model_copy(update={"channel": ch.independent()})]
        return [scenario]

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        s, ch, (e,) = needs(scenario, "system"), needs(scenario, "channel"), needs(scenario, "estimators")
        mc = scenario.montecarlo
        H, R = mc.horizon, ctx.mc_runs(scenario)
        K = self.particles if not ctx.quick else max(8, self.particles // 4)
        T = float(e.threshold_of(ch))
        coeffs = e.renewal_coefficients(s, H, self.quantity)
        lab = labels([e])[0]
        cols = describe(scenario, s, [e], self.quantity)[0]
        chans = [("correlated" if self.baseline == "independent" else ch.kind, ch, scenario)]
        if self.baseline == "independent":
            ind = ch.independent()
            chans.append(("independent", ind, scenario.model_copy(update={"channel": ind})))
        ctx.total(R * len(chans))
        rows, bursts, metas = [], [], {}
        for name, c, sc in chans:
            law = c.drop_law(T, H)
            kern = BurstSMCKernel(law.factor, [T], law.snr_avg, law.noise, coeffs, H, particles=K,
                                  burst_lags=self.burst_lags)
            st = run_chunked(kern, R, mc.chunk, mc.seed, stream=ctx.stream, progress=ctx.progress,
                             label=f"burst_mean {name}")
            val, se = norm_and_se(st["sum"][:, :, 0], st["sumsq"][:, :, 0], R)
            tr, tr2 = float(st["tr"][0]), float(st["tr2"][0])
            tr_m, tr_se = (float(x) for x in mean_se(tr, tr2, R))  # s.e. 0 where the runs agree to rounding
            with np.errstate(invalid="ignore", divide="ignore"):
                ess = tr**2 / tr2 / R if tr2 > 0 else np.nan
            inf = float(st["inf"][0])
            base = dict(channel=name, estimator=lab, k=H, n=R, particles=K, ess_frac=ess,
                        min_ess_frac=float(st["ess"][0]) / R / K, overflowed=inf, source="monte_carlo", reference="",
                        **cols)
            for series, v, sv in (("norm", val, se), ("trace", tr_m, tr_se)):
                ok = inf == 0 and np.isfinite(v) and v > 0 and sv / v < RELIABLE_REL_SE
                rows.append(dict(base, series=series, value=v, stderr=sv, reliable=int(ok)))
            for j, L in enumerate(kern.burst_lags):
                m_, se_ = (float(x) for x in mean_se(st["w"][0, j], st["w2"][0, j], R))
                bursts.append(dict(channel=name, L=L, value=m_, stderr=se_, n=R,
                                   reliable=int(m_ > 0 and se_ / m_ < RELIABLE_REL_SE)))
            for r in self.reference_rows(sc, [lab]):
                if r.get("k", H) != H or r.get("quantity", self.quantity) != self.quantity:
                    continue
                rows.append(dict(channel=name, estimator=r.get("estimator", "") or lab, series="trace", k=H,
                                 value=r["value"], stderr=np.nan, n=0, particles=0, ess_frac=np.nan,
                                 min_ess_frac=np.nan, reliable=1, overflowed=0.0, source="closed_form",
                                 reference=f"{r['reference']}: {r['series']}", quantity=self.quantity, P0=cols["P0"],
                                 conventions=cols["conventions"]))
                if s.n == 1:  # a scalar: the norm is the value itself
                    rows.append(dict(rows[-1], series="norm"))
            metas[name] = {"drop_probability_model": "independent gains" if law.factor is None else
                           "Gaussian gain, Cholesky factor over the horizon"}
        return Artefact(pd.DataFrame(rows, columns=COLUMNS), extra_tables={"bursts": pd.DataFrame(bursts, columns=BURST_COLUMNS)},
                        meta={"runs": R, "particles": K, "threshold": T, "horizon": H, "quantity": self.quantity,
                              "channels": metas, "estimator": lab,
                              "smc": f"{R} independent cloud pairs x {K} particles, systematic resampling at ESS < K/2; "
                                     "the L = 0 term exact (marginal law of the SNR)",
                              "streams": "the channel and its independent counterpart: the same stream (common random numbers)",
                              "reliable_rule": f"stderr/value < {RELIABLE_REL_SE}, no overflow"})

    def finish_over(self, scenario, art: Artefact) -> Artefact:
        """The over grid's ``trend`` table (differences along each path) beside the main table, for claims."""
        t = art.table.assign(estimator=art.table["channel"] + ": " + art.table["estimator"])
        return Artefact(art.table, meta=art.meta,
                        extra_tables={**art.extra_tables, "trend": derived.trend(t, list(self.over or {}))})

    # --- the figure -------------------------------------------------------------------------------------
    def plot(self, tables, scenario):
        t = tables["main"]
        b = tables.get("bursts")
        x = next(iter(self.over)) if self.over else None
        short = "" if x is None else (x.split(".")[-2] if x.endswith(".value") else x.split(".")[-1])
        panel_b = b is not None and len(b) and x is not None and self.burst_panel
        fig, axs = new_figure(ncols=2 if panel_b else 1, width=5.6, height=4.6)
        ax = np.atleast_1d(axs)[0]
        series = "norm"
        omitted = 0
        for i, (name, g) in enumerate(t[(t.series == series) & (t.source == "monte_carlo")].groupby("channel", sort=False)):
            g = g.sort_values(x) if x else g
            xs = g[x].astype(float) if x else np.zeros(len(g))
            ok = g.reliable.astype(int) == 1
            omitted += int((~ok).sum())
            st = series_style(i + 1)
            ax.errorbar(xs, g.value.where(ok), yerr=2 * g.stderr.where(ok), color=st["color"], ls=st["linestyle"],
                        marker=st["marker"], ms=5, capsize=2, label=f"{name}: SMC $\\pm$2 s.e.")
        ref = t[(t.series == series) & (t.source == "closed_form")]
        for j, ((name, rname), g) in enumerate(ref.groupby(["channel", "reference"], sort=False)):
            g = g.sort_values(x) if x else g
            ax.plot(g[x].astype(float) if x else np.zeros(len(g)), g.value, color=PALETTE[0], ls="-", marker="D",
                    mfc="none", ms=7, zorder=3, label=f"{name}: closed form ({rname.split(': ', 1)[-1]})")
        if self.log_y:
            ax.set_yscale("log")
        H = int(t.k.dropna().iloc[0]) if t.k.notna().any() else scenario.montecarlo.horizon
        ax.set_ylabel(rf"$\|\mathrm{{E}}\,P_{{k+1 \mid k}}\|$ at k = {H}")
        if x:
            ax.set_xlabel(self.x_label or x)
        ax.set_title(f"(a) performance vs {short}" if x else "(a) performance")
        if ax.get_legend_handles_labels()[0]:  # below the axes: the curve runs corner to corner (the figure lint)
            legend_outside(ax, loc="below", ncol=1)
        if panel_b:
            axb = np.atleast_1d(axs)[1]
            base = b[b.channel == "independent"] if self.baseline == "independent" else None
            k = 0
            for x0 in self.burst_panel:
                at = b[np.isclose(b[x].astype(float), float(x0))]
                for name, g in at[at.channel != "independent"].groupby("channel", sort=False) if base is not None else \
                        at.groupby("channel", sort=False):
                    g = g[g.reliable == 1]
                    if base is not None:  # the ratio to the independent channel (its burst law: (1 − μ) μᴸ)
                        ref = at[at.channel == "independent"].set_index("L").reindex(g.L)
                        keep = (ref.value.to_numpy() > 0)
                        g, rv, rs = g[keep], ref.value.to_numpy()[keep], ref.stderr.fillna(0).to_numpy()[keep]
                        y = g.value.to_numpy() / rv
                        yerr = y * np.hypot(g.stderr.to_numpy() / g.value.to_numpy(), rs / rv)
                    else:
                        y, yerr = g.value.to_numpy(), g.stderr.to_numpy()
                    if not len(g):
                        continue
                    k += 1
                    st = series_style(k)
                    axb.errorbar(g.L, y, yerr=2 * yerr, color=st["color"], ls=st["linestyle"], marker=st["marker"],
                                 ms=4, capsize=2, label=f"{name}{' / independent' if base is not None else ''}, "
                                                        f"{short} = {x0:g}, $\\pm$2 s.e.")
            if base is not None:
                axb.axhline(1.0, color=PALETTE[0], ls="-", label="independent (ratio 1)")
                axb.set_ylabel("Pr[received, then $L$ drops]\nratio to independent")  # two lines: the axes are short
                axb.set_title("(b) drop bursts: correlated / independent")
            else:
                axb.set_yscale("log")
                axb.set_ylabel(r"Pr[received, then $L$ drops]")
                axb.set_title("(b) drop bursts")
            axb.set_xlabel(r"burst length $L$ (steps; reliable estimates only)")
            if axb.get_legend_handles_labels()[0]:
                legend_outside(axb, loc="below", ncol=1)
        fig.suptitle(paper_title(self.paper.topic if self.paper else None, self.paper.figure if self.paper else None,
                                 self.title or "E P by sequential Monte Carlo of the drop bursts"))
        mcr = t[t.source == "monte_carlo"]
        n = int(mcr.n.max()) if len(mcr) else 0
        K = int(mcr.particles.max()) if len(mcr) else 0
        note = (f"sequential Monte Carlo of the drop bursts (unbiased): n = {n} independent cloud pairs x {K} particles "
                f"per point")
        if omitted:
            note += f"; {omitted} point(s) with relative s.e. ≥ {RELIABLE_REL_SE:.0%} (or an overflow) not drawn"
        if len(mcr):
            note += f"\n{math_text(str(mcr.P0.iloc[0]))}"
        footnote(fig, note)
        return fig
