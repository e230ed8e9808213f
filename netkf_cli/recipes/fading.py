"""Artefacts of Mostofi & Murray 2009 (fading channels) that are paper arithmetic: Figs 3, 4, 5 (closed forms),
and Fig. 7 (correlated channel; its sequential Monte Carlo of the drop bursts has no generic metric yet).

Fig. 6, Sec. 4.2 and Theorem 4 are configurations of the generic metrics (configs/fading/fig6.yaml, sec42.yaml:
time_average over the threshold; thm4.yaml: mean_vs_time) with the closed forms as ``references`` providers in
``analysis/fading.py``.

Thresholds Υ_T and SNRs always carry an explicit unit in the YAML; tables hold both the linear
value (``threshold``) and dB (``threshold_db``). The paper's Υ_T axis (optimum "14" at 20 dB)
is LINEAR.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
import pandas as pd
from pydantic import Field, model_validator

from netkf_cli.analysis import fading as fa
from netkf_cli.channels.fading import Snr, jakes_factor
from netkf_cli.errors import ConfigError
from netkf_cli.estimators import fading_receivers as fr
from netkf_cli.montecarlo import run_chunked
from netkf_cli.plotting import PALETTE, footnote, legend_outside, new_figure, paper_title, series_style
from netkf_cli.recipes.base import Artefact, RunContext
from netkf_cli.spec import AnalysisModel, FiniteFloat, PositiveInt, StrictModel

RELIABLE_REL_SE = 0.05  # a Monte Carlo mean is flagged unreliable above 5 % relative standard error, …
# … when the estimator has infinite variance (naive mean with drop-continuation probability
# μ_c and μ_c ρ_max⁴ ≥ 1: a burst of L drops scales P by ~ρ^{2L}, so E P² = Σ μ_c^L ρ^{4L} diverges;
# then the sample standard error is meaningless however small it looks), or when a run overflowed.
# ``ess_frac`` = (Σ tr P)²/(N Σ (tr P)²) is reported as a further diagnostic only.


PAPER_QUANTITY = ("predicted P_{k+1|k} at k = horizon: the paper's P[k] (eqs 6, 12, 28), which its figures plot; "
                  "start P[0] = P0 = the prior of y_1 (the paper's convention; the generic receiver estimator "
                  "starts from P_{0|0} = P0 instead)")
"""What the fading figures' ‖E P[k]‖ is, in netkf's quantities (manifest ``quantity``, figure footnote)."""


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


def _P0(s):
    if s.P0 is None:
        raise ConfigError.at("system.P0", "the fading receivers need an explicit initial covariance P0")
    return s.P0


def _receiver_model(scenario, sc: int, s=None) -> fr.ReceiverModel:
    s = s or scenario.linear_system()
    ch = scenario.channel
    if sc == 2 and s.m > s.n:
        raise ConfigError.at("system.C", "scenario 2 needs at most as many outputs as states")
    return fr.ReceiverModel(sc, s.A, s.C, s.Q, s.R, ch.noise.variance)


def _norm_and_se(sumX, sumXX, N):
    """‖mean‖₂ of symmetric matrices and its delta-method standard error.

    sumX (n, n, G), sumXX (n², n², G) = Σ vec(X)vec(X)ᵀ. ∂‖M‖/∂M = u uᵀ for the top eigenvector u.
    """
    n = sumX.shape[0]
    G = sumX.shape[2]
    val, se = np.full(G, np.nan), np.full(G, np.nan)
    for g in range(G):
        M = sumX[:, :, g] / N
        if not np.all(np.isfinite(M)):
            val[g] = np.inf
            continue
        w, V = np.linalg.eigh((M + M.T) / 2)
        j = int(np.argmax(np.abs(w)))
        u = V[:, j]
        grad = np.outer(u, u).ravel()
        cov = (sumXX[:, :, g] / N - np.outer(M.ravel(), M.ravel())) * N / max(N - 1, 1)
        val[g] = abs(w[j])
        se[g] = math.sqrt(max(float(grad @ cov @ grad), 0.0) / N)
    return val, se


def _summ(tot, N, label, finite_var):
    val, se = _norm_and_se(tot["sum"], tot["sumsq"], N)
    with np.errstate(invalid="ignore", divide="ignore"):
        ess = tot["tr"] ** 2 / tot["tr2"] / N
        rel = se / val
    reliable = (rel < RELIABLE_REL_SE) & np.asarray(finite_var, dtype=bool) & (tot["inf"] == 0)
    return pd.DataFrame({"series": label, "value": val, "stderr": se, "n": N, "ess_frac": ess,
                         "finite_variance": np.asarray(finite_var, dtype=int),
                         "reliable": reliable.astype(int), "overflowed": tot["inf"]})


def _thr_cols(T):
    return {"threshold": T, "threshold_db": fa.linear_to_db(T)}


# --------------------------------------------------------------------------- Fig. 3


class FadingNoiseCurves(AnalysisModel):
    """``kind: fading_noise_curves`` — Fig. 3(a) σ_n²(Υ) and Fig. 3(b) packet-drop probability vs Υ."""

    kind: Literal["fading_noise_curves"]
    snr: Grid = Field(description="x-axis: instantaneous SNR Υ")
    threshold: Snr = Field(description="Υ_T of the step approximation eq. (5) in Fig. 3(b)")
    N_p_curve: PositiveInt = Field(10, description="bits per packet of the smooth packet-error curve 1 − (1 − Ω(√Υ))^N_p")

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

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        ch = _fading(scenario, iid_only=True)
        a, d = _ber_params(ch)
        s = scenario.linear_system()
        if s.m != s.n or abs(np.linalg.det(s.C)) < 1e-12:
            raise ConfigError.at("system.C", "eq. (20) needs an invertible (square) C; for a general C simulate the receivers (configs/fading/sec42.yaml: time_average)")
        rho = fa.rho_max(s.A)
        assum = fa.theorem1_assumptions(s.A, s.C, s.Q)
        varsigma, q = float(s.C[0, 0]), float(s.Q[0, 0])
        rows, opt = [], []
        for Ya, Ya_raw in zip(self.snr_avgs.linear, self.snr_avgs.raw):
            Tmax = fa.max_stable_threshold(Ya, rho)
            hi = Tmax if math.isfinite(Tmax) else 10 * Ya
            T = np.linspace(0, hi, self.num_thresholds + 1)[:-1]
            mu, s2 = fa.mu_ave(T, Ya), fa.sigma2_n_ave(T, Ya, a, d)
            v = [fa.spectral_norm(fa.ep_inf(s.A, s.C, s.Q, m_, s_, s.R)) for m_, s_ in zip(mu, s2)]
            dets = [float(np.linalg.det(fa.ep_inf(s.A, s.C, s.Q, m_, s_, s.R))) for m_, s_ in zip(mu, s2)]
            base = {"snr_avg": Ya, "snr_avg_db": float(fa.linear_to_db(Ya))}
            rows.append(pd.DataFrame({**base, **_thr_cols(T), "series": "norm_EPinf", "value": v}))
            rows.append(pd.DataFrame({**base, **_thr_cols(T), "series": "det_EPinf", "value": dets}))
            Tn, vn = fa.optimal_threshold("norm", s.A, s.C, s.Q, Ya, a, d, s.R)
            Td, vd = fa.optimal_threshold("det", s.A, s.C, s.Q, Ya, a, d, s.R)
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


# --------------------------------------------------------------------------- Fig. 7


class FadingCorrelation(AnalysisModel):
    """``kind: fading_correlation`` — Fig. 7: correlated (Jakes) vs i.i.d. channel, ‖E P[k]‖ at k = horizon vs Υ_T.

    Scenario 2 with an invertible C forgets everything at a kept packet, so E P[k] is a sum over the
    length of the final drop burst; the burst probabilities of the correlated channel are estimated
    by sequential Monte Carlo (:class:`~netkf_cli.estimators.fading_receivers.BurstSMCKernel`,
    unbiased, finite variance), the same estimator on the i.i.d. channel is checked against the
    exact eq. (14). Main table: ``jakes_smc``, ``iid_smc``, ``iid_exact``; ``bursts``: Pr[kept, then
    L drops] per channel; ``path_mean``: the plain sample means (diagnostic only: heavy-tailed, never
    plotted); ``autocorr``: the generated gain against J₀ (eq. 65).
    """

    kind: Literal["fading_correlation"]
    thresholds: Grid = Field(description="the drop thresholds Υ_T (eq. 5) with their unit")
    receiver: Literal[2, 3] = Field(2, description="receiver scenario (2: no cross-layer path, 3: cross-layer path)")
    max_lag: PositiveInt = Field(8, description="largest lag of the autocorrelation check against J₀ (eq. 65)")
    smc_runs: PositiveInt = Field(12, description="independent particle clouds per threshold (the Monte Carlo runs of the SMC)")
    particles: PositiveInt = Field(32, description="particles K per cloud (sequential Monte Carlo of the drop bursts)")
    smc_chunk: PositiveInt = Field(4, description="clouds per Monte Carlo chunk")
    burst_panel: list[FiniteFloat] = Field([12.0, 20.0], description="Υ_T values (same unit as thresholds) "
                                                                      "whose burst probabilities are drawn")
    backend: fr.BackendKind = Field("auto", description="backend of the path-mean diagnostic: numpy | numba | auto")

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        ch = _fading(scenario)
        if ch.correlation.model != "jakes":
            raise ConfigError.at("channel.correlation.model", "this analysis compares a Jakes channel with the i.i.d. one: use model: jakes")
        s = scenario.linear_system()
        P0 = _P0(s)
        Ya = ch.mean_snr
        T = self.thresholds.linear
        G = len(T)
        H = scenario.montecarlo.horizon
        N = ctx.mc_runs(scenario)
        rm = _receiver_model(scenario, self.receiver, s)
        rm = fr.ReceiverModel(rm.scenario, rm.A, rm.C, rm.Q, rm.R, fr.NoiseFn.of(ch.noise))
        lags = np.arange(self.max_lag + 1)
        rho = fa.rho_max(s.A)
        backend = fr.resolve_backend(self.backend, s.n)
        # ---- plain sample means (diagnostic), burst statistics, autocorrelation: stream 0
        tot = run_chunked(fr.CorrelatedPathKernel(ch, rm, T, P0, H, self.max_lag, backend=backend), N,
                          scenario.montecarlo.chunk, scenario.montecarlo.seed, stream=0, progress=ctx.progress,
                          label="fading_correlation_paths")
        paths = []
        for lab in ("jakes", "iid"):
            with np.errstate(invalid="ignore", divide="ignore"):
                p1 = tot[f"{lab}_d1"] / tot[f"{lab}_d0"]          # Pr[drop | 1 drop before]
                p2 = tot[f"{lab}_d2"] / tot[f"{lab}_d1"]          # Pr[drop | 2 drops before]
            pc = np.fmax(np.nan_to_num(p1), np.nan_to_num(p2))
            df = _summ({k: tot[f"{lab}_{k}"] for k in fr.STAT_KEYS}, N, f"{lab}_path_mean", pc * rho**4 < 1)
            df.insert(0, "drop_continuation", pc)
            for k, v in _thr_cols(T).items():
                df.insert(0, k, v)
            df.insert(0, "channel", lab)
            paths.append(df)
        frames, bursts = [], []
        smc_ok = self.receiver == 2 and s.m == s.n and abs(np.linalg.det(s.C)) > 1e-12 and ch.noise.model == "ber"
        meta_smc = "not applicable (needs receiver 2, an invertible C and the ber noise model)"
        if smc_ok:
            coeffs = fr.memoryless_coefficients(s.A, s.C, s.Q, s.R, P0, H)
            L = jakes_factor(H, ch.correlation)
            # --quick keeps the number of independent clouds (the degrees of freedom of the standard
            # error the golden comparison relies on) and uses fewer particles per cloud (still unbiased)
            R = self.smc_runs
            K = self.particles if not ctx.quick else max(8, self.particles // 4)
            for stream, lab, factor in ((1, "jakes", L), (2, "iid", None)):
                kern = fr.BurstSMCKernel(factor, T, Ya, rm.noise, coeffs, H, particles=K)
                st = run_chunked(kern, R, self.smc_chunk, scenario.montecarlo.seed, stream=stream,
                                 progress=None, label=f"fading_correlation_smc_{lab}")
                df = _summ({k: st[k] for k in fr.STAT_KEYS}, R, f"{lab}_smc", np.ones(G, bool))
                df.insert(0, "min_ess_frac", st["ess"] / R / K)
                for k, v in _thr_cols(T).items():
                    df.insert(0, k, v)
                df.insert(0, "channel", lab)
                frames.append(df)
                for j, Lb in enumerate(kern.burst_lags):
                    m_ = st["w"][:, j] / R
                    se_ = np.sqrt(np.maximum(st["w2"][:, j] / R - m_**2, 0) / max(R - 1, 1))
                    with np.errstate(invalid="ignore", divide="ignore"):
                        rel = (se_ / m_ < RELIABLE_REL_SE) & (m_ > 0)
                    bursts.append(pd.DataFrame({"channel": lab, **_thr_cols(T), "L": Lb, "series": f"{lab}_smc",
                                                "value": m_, "stderr": se_, "n": R, "reliable": rel.astype(int)}))
                    if lab == "iid":
                        mu = fa.mu_ave(T, Ya)
                        bursts.append(pd.DataFrame({"channel": "iid", **_thr_cols(T), "L": Lb, "series": "iid_exact",
                                                    "value": (1 - mu) * mu**Lb, "stderr": 0.0, "n": np.nan, "reliable": 1}))
            meta_smc = (f"sequential Monte Carlo of the drop bursts: {R} independent clouds x "
                        f"{K} particles per threshold, resampling at ESS < K/2")
        if ch.noise.model == "ber" and s.m == s.n and self.receiver == 2:
            a, d = ch.noise.params
            v = [fa.spectral_norm(fa.ep_recursion(s.A, s.C, s.Q, float(fa.mu_ave(t_, Ya)), float(fa.sigma2_n_ave(t_, Ya, a, d)), P0, H, s.R)[-1]) for t_ in T]
            frames.append(pd.DataFrame({"channel": "iid", **_thr_cols(T), "min_ess_frac": np.nan, "series": "iid_exact",
                                        "value": v, "stderr": 0.0, "n": np.nan, "ess_frac": np.nan, "finite_variance": 1,
                                        "reliable": 1, "overflowed": 0.0}))
        table = pd.concat(frames, ignore_index=True) if frames else paths[0].iloc[:0]
        opt = []
        for lab in table.series.unique() if len(table) else []:
            g = table[(table.series == lab) & (table.reliable == 1)].reset_index(drop=True)
            if not len(g):
                continue
            i = int(np.nanargmin(g.value.to_numpy()))
            near = g[(g.value - g.value[i]) <= 2 * np.hypot(g.stderr, g.stderr[i])]
            last_rel = bool(i == len(g) - 1 and len(g) < int((table.series == lab).sum()))
            opt.append({"series": lab, "threshold": g.threshold[i], "value": g.value[i], "stderr": g.stderr[i],
                        "threshold_low": near.threshold.min(), "threshold_high": near.threshold.max(),
                        "at_edge_of_reliable_range": int(last_rel)})
        ac = tot["ac"] / N
        ac_se = np.sqrt(np.maximum(tot["ac2"] / N - ac**2, 0) / (N - 1))
        pcm = tot["pc"] / N / Ya**2 - 1.0  # corr of |h|²: E[Υ_t Υ_{t−k}]/Υ_ave² − 1 = J0²
        pc_se = np.sqrt(np.maximum(tot["pc2"] / N - (tot["pc"] / N) ** 2, 0) / (N - 1)) / Ya**2
        J = ch.correlation.autocorr(lags)
        actab = pd.DataFrame({"lag": lags, "lag_s": lags * ch.correlation.interval_s, "J0": J, "gain_autocorr": ac,
                              "gain_autocorr_stderr": ac_se, "power_autocorr": pcm, "power_autocorr_stderr": pc_se,
                              "J0_squared": J**2})
        extra = {"autocorr": actab, "path_mean": pd.concat(paths, ignore_index=True), "optima": pd.DataFrame(opt)}
        if bursts:
            extra["bursts"] = pd.concat(bursts, ignore_index=True)
        return Artefact(table, extra_tables=extra,
                        meta={"doppler_hz": ch.correlation.doppler, "horizon": H, "runs_path_mean": N,
                              "quantity": PAPER_QUANTITY,
                              "smc": meta_smc, "nugget": ch.correlation.nugget,
                              "stability_limit_iid_eq19": fa.max_stable_threshold(Ya, rho),
                              "first_zero_of_J0_s": 2.404825557695773 / (2 * np.pi * ch.correlation.doppler),
                              "reliable_rule": f"stderr/value < {RELIABLE_REL_SE}, no overflow",
                              "path_mean": "plain sample means: diagnostic only (heavy-tailed), never plotted"})

    def plot(self, tables, scenario):
        t, ac = tables["main"], tables["autocorr"]
        bursts = tables.get("bursts")
        fig, axs = new_figure(ncols=3, width=4.6, height=4.4)
        ax, axb, ax2 = axs
        H = scenario.montecarlo.horizon
        omitted = 0
        styles = {"iid_exact": (PALETTE[0], "-", None, r"uncorrelated, exact (eq. 14)"),
                  "iid_smc": (PALETTE[0], "none", "s", r"uncorrelated, SMC $\pm$2 s.e."),
                  "jakes_smc": (PALETTE[1], "--", "o", r"correlated (Jakes), SMC $\pm$2 s.e.")}
        for lab in ("iid_exact", "iid_smc", "jakes_smc"):
            g = t[t.series == lab]
            if not len(g):
                continue
            c, ls, mk, name = styles[lab]
            omitted += int((g.reliable == 0).sum())
            if lab == "iid_exact":
                ax.plot(g.threshold, g.value, color=c, ls=ls, label=name)
            else:  # unreliable points are not drawn (NaN breaks the line there)
                y = g.value.where(g.reliable == 1)
                ax.errorbar(g.threshold, y, yerr=2 * g.stderr.where(g.reliable == 1), color=c, ls=ls, marker=mk, ms=5,
                            mfc="none" if lab == "iid_smc" else c, label=name)
        ax.set_yscale("log")
        ax.set_xlabel(r"drop threshold $\Upsilon_T$ (linear power ratio)")
        ax.set_ylabel(rf"$\|E\,P[{H}]\|$")
        ax.set_title(r"(a) performance vs $\Upsilon_T$")
        ax.legend(loc="upper right")
        if bursts is not None:
            axb.axhline(1.0, color=PALETTE[0], ls="-", label="uncorrelated (exact ratio 1)")
            for i, T0 in enumerate(self.burst_panel):
                T0l = float(fa.db_to_linear(T0)) if self.thresholds.unit == "dB" else float(T0)
                ex = bursts[(bursts.series == "iid_exact") & np.isclose(bursts.threshold, T0l)].set_index("L")
                g = bursts[(bursts.series == "jakes_smc") & np.isclose(bursts.threshold, T0l) & (bursts.reliable == 1)]
                if not len(g) or not len(ex):
                    continue
                base = ex.value.reindex(g.L).to_numpy()
                st = series_style(i + 1)
                axb.errorbar(g.L, g.value / base, yerr=2 * g.stderr / base, color=st["color"], ls=st["linestyle"],
                             marker=st["marker"], ms=4, label=rf"Jakes / uncorrelated, $\Upsilon_T$ = {T0:g}, $\pm$2 s.e.")
            axb.set_xlabel(r"burst length $L$ (transmissions)")
            axb.set_ylabel(r"Pr[kept, then $L$ drops]: Jakes / i.i.d.")
            axb.set_title("(b) drop bursts: correlated / uncorrelated")
            axb.legend(loc="upper left", fontsize=9)
        ax2.errorbar(ac.lag, ac.gain_autocorr, yerr=5 * ac.gain_autocorr_stderr, fmt="o", color=PALETTE[1],
                     label=r"sample $E\,h_t h^*_{t-k}$ $\pm$5 s.e.")
        ax2.plot(ac.lag, ac.J0, color="k", ls="-", label=r"$J_0(2\pi f_D k T)$ (eq. 65)")
        ax2.errorbar(ac.lag, ac.power_autocorr, yerr=5 * ac.power_autocorr_stderr, fmt="s", color=PALETTE[0],
                     mfc="none", label=r"sample corr. of $\Upsilon$ $\pm$5 s.e.")
        ax2.plot(ac.lag, ac.J0_squared, color="k", ls=":", label=r"$J_0^2$")
        ax2.set_xlabel(r"lag $k$ (transmissions, $T$ = 10 ms)")
        ax2.set_ylabel("autocorrelation")
        ax2.set_title("(c) generated channel vs eq. (65)")
        ax2.legend(loc="upper right", fontsize=9)
        ch = scenario.channel
        fig.suptitle(paper_title("fading", 7, rf"correlated vs uncorrelated channel, scenario {self.receiver}, "
                                              rf"$\Upsilon_{{ave}}$ = {ch.snr_avg.value:g} {ch.snr_avg.unit}"))
        note = ("SMC: sequential Monte Carlo of the drop bursts (unbiased); plain sample means are heavy-tailed and not drawn; "
                f"P[{scenario.montecarlo.horizon}] = predicted $P_{{k+1 \\mid k}}$, from P[0] = P0 (paper's start)")
        if omitted:
            note += f"; {omitted} SMC point(s) with relative s.e. ≥ {RELIABLE_REL_SE:.0%} not drawn"
        footnote(fig, note)
        return fig
