"""Artefacts of Mostofi & Murray 2009 (fading channels) that are paper arithmetic: Figs 3, 4, 5 (closed forms).

Fig. 6, Sec. 4.2, Theorem 4 and Fig. 7 are configurations of the generic metrics (configs/fading/fig6.yaml,
sec42.yaml: time_average over the threshold; thm4.yaml: mean_vs_time; fig7.yaml: burst_mean, the sequential
Monte Carlo of the drop bursts; fig7_channel.yaml: autocorrelation of the generated gain) with the closed
forms as ``references`` providers in ``analysis/fading.py``.

Thresholds Υ_T and SNRs always carry an explicit unit in the YAML; tables hold both the linear
value (``threshold``) and dB (``threshold_db``). The paper's Υ_T axis (optimum "14" at 20 dB)
is LINEAR.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from netkf_cli.core.lazy import pandas as pd
from pydantic import Field, model_validator

from netkf_cli.analysis import fading as fa
from netkf_cli.channels.fading import Snr
from netkf_cli.core.errors import ConfigError
from netkf_cli.runtime.plotting import PALETTE, footnote, legend_outside, new_figure, paper_title, series_style
from netkf_cli.recipes.base import Artefact, RunContext
from netkf_cli.core.spec import AnalysisModel, FiniteFloat, PositiveInt, StrictModel

class Grid(StrictModel):
    """A grid of SNR values with its unit: ``{unit: linear, values: [...]}`` or ``{unit, start, stop, num}``."""

    unit: Literal["linear", "dB"] = Field(description="unit of the values: linear power ratio or dB")
    values: list[FiniteFloat] | None = Field(None, description="explicit grid values (or give start, stop, num)")
    start: FiniteFloat | None = Field(None, description="first grid value (with stop and num)")
    stop: FiniteFloat | None = Field(None, description="last grid value, inclusive")
    num: PositiveInt | None = Field(None, description="number of evenly spaced grid values")

    @model_validator(mode="after")
    def _check(self):
        rng = (self.start, self.stop, self.num)
        if self.values is not None and all(v is None for v in rng):
            if not self.values:
                raise ValueError("values must not be empty")
        elif self.values is None and all(v is not None for v in rng):
            if self.stop < self.start:
                raise ValueError(f"stop ({self.stop}) must be >= start ({self.start})")
        else:
            raise ValueError("give either `values` or all of `start`, `stop`, `num`")
        if self.unit == "linear" and min(self.raw) < 0:
            raise ValueError("linear SNR values must be >= 0")
        return self

    @property
    def raw(self) -> np.ndarray:
        if self.values is not None:
            return np.asarray(self.values, dtype=float)
        return np.linspace(self.start, self.stop, self.num)

    @property
    def linear(self) -> np.ndarray:
        return fa.db_to_linear(self.raw) if self.unit == "dB" else self.raw


# --------------------------------------------------------------------------- helpers


def _fading(scenario, *, iid_only=False):
    ch = scenario.require_channel("fading")
    if iid_only and ch.correlation.model != "iid":
        raise ConfigError.at("channel.correlation.model", "this analysis needs an i.i.d. channel (model: iid)")
    return ch


def _ber_params(ch, path="channel.noise.model"):
    if ch.noise.model != "ber":
        raise ConfigError.at(path, f"this analysis needs the noise model `ber` (α + δ Ω(√Υ)), got {ch.noise.model}")
    return ch.noise.params


def _thr_cols(T):
    return {"threshold": T, "threshold_db": fa.linear_to_db(T)}


# --------------------------------------------------------------------------- Fig. 3


class FadingNoiseCurves(AnalysisModel):
    """``kind: fading_noise_curves`` — Fig. 3(a) σ_n²(Υ) and Fig. 3(b) packet-drop probability vs Υ."""

    kind: Literal["fading_noise_curves"]
    snr: Grid = Field(description="x-axis: instantaneous SNR Υ")
    threshold: Snr = Field(description="Υ_T of the step approximation eq. (5) in Fig. 3(b)")
    N_p_curve: PositiveInt = Field(10, description="bits per packet of the smooth packet-error curve 1 − (1 − Ω(√Υ))^N_p")

    def check(self, scenario) -> None:
        _ber_params(_fading(scenario))

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        ch = _fading(scenario)
        a, d = _ber_params(ch)
        Y = self.snr.linear
        rows = []
        for series, v in (("sigma2_n", fa.sigma2_n(Y, a, d)),
                          ("packet_error", fa.packet_error_prob(Y, self.N_p_curve)),
                          ("drop_step", fa.drop_indicator(Y, self.threshold.linear))):
            rows.append(pd.DataFrame({"snr": Y, "snr_db": fa.linear_to_db(Y), "series": series, "value": v}))
        table = pd.concat(rows, ignore_index=True)
        params = [("alpha", a), ("delta", d), ("quantization_floor_Delta2_over_12", a)]
        if ch.noise.N_p is not None:
            params += [("N_p", ch.noise.N_p), ("Delta", ch.noise.Delta)]
        params.append(("threshold", self.threshold.linear))
        ptab = pd.DataFrame(params, columns=["quantity", "value"])
        return Artefact(table, meta={"noise": "sigma_n^2 = alpha + delta*Omega(sqrt(snr)); alpha = Delta^2/12, "
                                              "delta = Delta^2 (4^N_p - 1)/3", "snr_unit_in_table": "linear + dB columns"},
                        extra_tables={"params": ptab})

    def plot(self, tables, scenario):
        t, p = tables["main"], tables["params"]
        fig, (ax1, ax2) = new_figure(ncols=2, width=5.2)
        s = t[t.series == "sigma2_n"]
        ax1.semilogy(s.snr_db, s.value, "-", color=PALETTE[0], label=r"$\sigma_n^2(\Upsilon) = \alpha + \delta\,\Omega(\sqrt{\Upsilon})$")
        a = float(p[p.quantity == "alpha"].value.iloc[0])
        d = float(p[p.quantity == "delta"].value.iloc[0])
        ax1.axhline(a, ls=":", color="0.3", label=rf"quantization floor $\alpha$ = {a:.3g}")
        ax1.set_xlabel(r"instantaneous SNR $\Upsilon$ (dB)")
        ax1.set_ylabel(r"communication noise variance $\sigma_n^2$")
        ax1.set_title(rf"(a) $\sigma_n^2(\Upsilon)$, $\delta$ = {d:.4g}")
        ax1.legend(loc="upper right")
        for i, (series, lab) in enumerate((("packet_error", r"packet error $1 - (1 - \Omega(\sqrt{\Upsilon}))^{N_p}$"),
                                           ("drop_step", "threshold model, eq. (5)"))):
            g = t[t.series == series]
            st = series_style(i)
            ax2.plot(g.snr_db, g.value, color=st["color"], ls=st["linestyle"], marker=None if i == 0 else st["marker"],
                     ms=3, markevery=8, label=lab)
        T = float(p[p.quantity == "threshold"].value.iloc[0])
        ax2.set_xlabel(r"instantaneous SNR $\Upsilon$ (dB)")
        ax2.set_ylabel(r"probability of packet drop $\mu$")
        ax2.set_title(rf"(b) $\mu$ vs $\Upsilon$ ($\Upsilon_T$ = {T:g} = {10 * np.log10(T):.3g} dB)")
        ax2.legend(loc="center right")  # both curves are at 0 or 1 there
        fig.suptitle(paper_title("fading", 3, r"communication noise and packet drop vs SNR"))
        return fig

# --------------------------------------------------------------------------- Fig. 4


class FadingAverages(AnalysisModel):
    """``kind: fading_averages`` — Fig. 4: μ_ave(Υ_T) and σ²_n,ave(Υ_T), eqs (15)–(16): closed form and quadrature.

    (The Monte Carlo check of both, from the channel's sampled traces, is tests/fading/test_references.py.)"""

    kind: Literal["fading_averages"]
    thresholds: Grid = Field(description="the drop thresholds Υ_T (eq. 5) with their unit")

    def check(self, scenario) -> None:
        _ber_params(_fading(scenario, iid_only=True))

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        ch = _fading(scenario, iid_only=True)
        a, d = _ber_params(ch)
        Ya = ch.mean_snr
        T = self.thresholds.linear
        rows = []
        for quantity, closed, quad in (
            ("mu_ave", fa.mu_ave(T, Ya), [fa.mu_ave_quad(t, Ya) for t in T]),
            ("sigma2_n_ave", fa.sigma2_n_ave(T, Ya, a, d), [fa.sigma2_n_ave_quad(t, Ya, a, d) for t in T]),
        ):
            for method, v in (("closed_form", closed), ("quadrature", quad)):
                rows.append(pd.DataFrame({**_thr_cols(T), "quantity": quantity, "series": f"{quantity}_{method}",
                                          "method": method, "value": v}))
        table = pd.concat(rows, ignore_index=True)
        return Artefact(table, meta={"snr_avg_linear": Ya, "alpha": a, "delta": d,
                                     "threshold_unit_in_table": "threshold linear, threshold_db in dB"})

    def plot(self, tables, scenario):
        t = tables["main"]
        fig, axs = new_figure(ncols=2, width=5.0)
        for i, (q, lab, ylab) in enumerate((("mu_ave", r"$\mu_{ave}$ (eq. 15)", r"average drop probability $\mu_{ave}$"),
                                            ("sigma2_n_ave", r"$\sigma^2_{n,ave}$ (eq. 16)",
                                             r"average communication noise $\sigma^2_{n,ave}$"))):
            ax = axs[i]
            g = t[t.quantity == q]
            cf = g[g.method == "closed_form"]
            ax.plot(cf.threshold, cf.value, ls="-", color=PALETTE[0], label=f"{lab}, closed form")
            qd = g[g.method == "quadrature"]
            ax.plot(qd.threshold, qd.value, "o", mfc="none", ms=8, color=PALETTE[1], ls="none", label=f"{lab}, quadrature")
            ax.set_xlabel(r"drop threshold $\Upsilon_T$ (linear power ratio)")
            ax.set_ylabel(ylab)
            if i == 1:
                ax.set_yscale("log")
            ax.legend(loc="upper left" if i == 0 else "upper right")
            ax.set_title("(a) drop probability" if i == 0 else "(b) communication noise of kept packets")
        ch = scenario.channel
        fig.suptitle(paper_title("fading", 4, rf"averages vs $\Upsilon_T$, $\Upsilon_{{ave}}$ = {ch.snr_avg.value:g} {ch.snr_avg.unit}"))
        return fig


# --------------------------------------------------------------------------- Fig. 5


class FadingScenario2Steady(AnalysisModel):
    """``kind: fading_scenario2_steady`` — Fig. 5: ‖E P∞‖ (eq. 20, Lyapunov) vs Υ_T for several Υ_ave, with the optima."""

    kind: Literal["fading_scenario2_steady"]
    snr_avgs: Grid = Field(description="the average SNRs Υ_ave of the curves")
    num_thresholds: PositiveInt = Field(200, description="points per curve on [0, stability limit)")

    def check(self, scenario) -> None:
        _ber_params(_fading(scenario, iid_only=True))
        s = scenario.linear_system()
        if s.m != s.n or abs(np.linalg.det(s.C)) < 1e-12:
            raise ConfigError.at("system.C", "eq. (20) needs an invertible (square) C; for a general C simulate the receivers (configs/fading/sec42.yaml: time_average)")

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        self.check(scenario)
        ch = _fading(scenario, iid_only=True)
        a, d = _ber_params(ch)
        s = scenario.linear_system()
        rho = fa.rho_max(s.A)
        assum = fa.theorem1_assumptions(s.A, s.C, s.Q)
        varsigma, q = float(s.C[0, 0]), float(s.Q[0, 0])
        rows, opt = [], []
        for Ya, Ya_raw in zip(self.snr_avgs.linear, self.snr_avgs.raw):
            Tmax = fa.max_stable_threshold(Ya, rho)
            hi = Tmax if math.isfinite(Tmax) else 10 * Ya
            T = np.linspace(0, hi, self.num_thresholds + 1)[:-1]
            mu, s2 = fa.mu_ave(T, Ya), fa.sigma2_n_ave(T, Ya, a, d)
            EP = [fa.ep_inf(s.A, s.C, s.Q, m_, s_, s.R) for m_, s_ in zip(mu, s2)]  # each once: both curves
            v = [fa.spectral_norm(X) for X in EP]
            dets = [float(np.linalg.det(X)) for X in EP]
            base = {"snr_avg": Ya, "snr_avg_db": float(fa.linear_to_db(Ya))}
            rows.append(pd.DataFrame({**base, **_thr_cols(T), "series": "norm_EPinf", "value": v}))
            rows.append(pd.DataFrame({**base, **_thr_cols(T), "series": "det_EPinf", "value": dets}))
            best = fa.optimal_thresholds(("norm", "det"), s.A, s.C, s.Q, Ya, a, d, s.R)
            (Tn, vn), (Td, vd) = best["norm"], best["det"]
            r24 = fa.eq24_root(Ya, a, d, s.A, varsigma, q)
            r26 = fa.eq26_root(Ya, a, d, s.A, varsigma, q)
            for quantity, T_, val in (("opt_norm_numerical", Tn, vn), ("opt_det_numerical", Td, math.exp(vd)),
                                      ("root_eq24", r24, fa.spectral_norm(fa.ep_inf(s.A, s.C, s.Q, float(fa.mu_ave(r24, Ya)), float(fa.sigma2_n_ave(r24, Ya, a, d)), s.R))),
                                      ("root_eq26", r26, float(np.linalg.det(fa.ep_inf(s.A, s.C, s.Q, float(fa.mu_ave(r26, Ya)), float(fa.sigma2_n_ave(r26, Ya, a, d)), s.R)))),
                                      ("stability_limit", Tmax, np.nan),
                                      ("norm_at_zero_threshold", 0.0, v[0])):
                opt.append({**base, "quantity": quantity, "threshold": T_, "threshold_db": float(fa.linear_to_db(T_)),
                            "objective": val})
        table = pd.concat(rows, ignore_index=True)
        return Artefact(table, extra_tables={"optima": pd.DataFrame(opt)},
                        meta={"rho_max": rho, "alpha": a, "delta": d, "theorem1_assumptions": assum,
                              "note": "eq. (20) solved with scipy.linalg.solve_discrete_lyapunov; R enters as in eq. (38)"})

    def plot(self, tables, scenario):
        """Υ_T in dB (log axis): every Υ_ave's stable range fills a large part of the width, so the optimum
        of each curve (the paper's "14" at 20 dB = 11.5 dB) is visible; the curve at Υ_T = 0 is the left end."""
        t, o = tables["main"], tables["optima"]
        fig, ax = new_figure(width=8.0, height=4.6)
        for k, (Ya_db, g) in enumerate(t[t.series == "norm_EPinf"].groupby("snr_avg_db")):
            st = series_style(k)
            g = g[g.threshold > 0]
            oo = o[np.isclose(o.snr_avg_db, Ya_db)]
            on = oo[oo.quantity == "opt_norm_numerical"]
            Topt = float(on.threshold.iloc[0])
            ax.semilogy(g.threshold_db, g.value, color=st["color"], ls=st["linestyle"],
                        label=rf"$\Upsilon_{{ave}}$ = {Ya_db:.3g} dB (optimum $\Upsilon_T$ = {Topt:.2f})")
            ax.plot(on.threshold_db, on.objective, ls="none", marker=st["marker"], color=st["color"], ms=8,
                    label=rf"numerical optimum, $\Upsilon_{{ave}}$ = {Ya_db:.3g} dB")
            lim = oo[oo.quantity == "stability_limit"].threshold.iloc[0]
            if np.isfinite(lim):
                ax.axvline(10 * np.log10(lim), color=st["color"], ls=":", lw=1.0)
        r = o[o.quantity == "root_eq24"]
        rv = []
        for _, row in r.iterrows():
            g = t[(t.series == "norm_EPinf") & np.isclose(t.snr_avg_db, row.snr_avg_db)]
            rv.append(float(np.interp(row.threshold, g.threshold, g.value)))
        ax.plot(r.threshold_db, rv, "x", color="k", ms=10, mew=1.5, ls="none", label="root of eq. (24), Theorem 1")
        ax.plot([], [], color="0.3", ls=":", lw=1.0, label=r"stability limit $\mu_{ave}\rho_{max}^2 = 1$ (eq. 19)")
        ax.set_xlabel(r"drop threshold $\Upsilon_T$ (dB; $\Upsilon_T$ = 14 linear is 11.5 dB)")
        ax.set_ylabel(r"$\|E\,P[\infty]\|$ (spectral norm)")
        fig.suptitle(paper_title("fading", 5, r"scenario 2, $\|E\,P[\infty]\|$ vs $\Upsilon_T$"))
        legend_outside(ax)
        footnote(fig, "eq. (20) by a discrete Lyapunov solve; the curves start at the smallest positive grid "
                      "threshold; Theorem 1 assumes a symmetric A (not the case here)")
        return fig
