"""Artefacts of Mostofi & Murray 2009 (fading channels): Figs 3–7, Sec. 4.2 and Theorem 4.

Thresholds Υ_T and SNRs always carry an explicit unit in the YAML; tables hold both the linear
value (``threshold``) and dB (``threshold_db``). The paper's Υ_T axis (optimum "14" at 20 dB)
is LINEAR.

Monte Carlo means of P near the stability limit are dominated by rare long drop bursts, so
for the i.i.d. channel we report the burst-conditioned estimator (see
``estimators/fading_receivers.py``), whose variance stays small, next to the naive sample mean,
each with its standard error (delta method for the spectral norm) and a ``reliable`` flag.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
import pandas as pd
from pydantic import Field, model_validator

from netkf_cli.analysis import fading as fa
from netkf_cli.channels.fading import FadingChannel, Snr, sample_gain
from netkf_cli.errors import ConfigError
from netkf_cli.estimators import fading_receivers as fr
from netkf_cli.montecarlo import run_chunked
from netkf_cli.plotting import footnote, new_figure
from netkf_cli.recipes.base import Artefact, RunContext
from netkf_cli.spec import AnalysisModel, FiniteFloat, PositiveFloat, PositiveInt, StrictModel

RELIABLE_REL_SE = 0.05  # a Monte Carlo mean is flagged unreliable above 5 % relative standard error, …
# … when the estimator has infinite variance (naive mean with drop-continuation probability
# μ_c and μ_c ρ_max⁴ ≥ 1: a burst of L drops scales P by ~ρ^{2L}, so E P² = Σ μ_c^L ρ^{4L} diverges;
# then the sample standard error is meaningless however small it looks), or when a run overflowed.
# ``ess_frac`` = (Σ tr P)²/(N Σ (tr P)²) is reported as a further diagnostic only.


class Grid(StrictModel):
    """A grid of SNR values with its unit: ``{unit: linear, values: [...]}`` or ``{unit, start, stop, num}``."""

    unit: Literal["linear", "dB"]
    values: list[FiniteFloat] | None = None
    start: FiniteFloat | None = None
    stop: FiniteFloat | None = None
    num: PositiveInt | None = None

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


def _fading(scenario, *, iid_only=False) -> FadingChannel:
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


def _stats(X, G, N):
    """Additive statistics of per-run matrices X (n, n, G*N) grouped by grid point."""
    n = X.shape[0]
    Xg = X.reshape(n, n, G, N)
    V = Xg.reshape(n * n, G, N)
    with np.errstate(over="ignore", invalid="ignore"):
        tr = np.trace(Xg, axis1=0, axis2=1)  # (G, N)
        return {"sum": Xg.sum(-1), "sumsq": np.einsum("agr,bgr->abg", V, V),
                "tr": tr.sum(-1), "tr2": (tr**2).sum(-1), "inf": (~np.isfinite(tr)).sum(-1).astype(float)}


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
        fig, (ax1, ax2) = new_figure(ncols=2, width=5.6)
        s = t[t.series == "sigma2_n"]
        ax1.semilogy(s.snr_db, s.value, "-", color="C0", label="σ_n²(Υ) = α + δ Ω(√Υ)")
        a = float(p[p.quantity == "alpha"].value.iloc[0])
        d = float(p[p.quantity == "delta"].value.iloc[0])
        ax1.axhline(a, ls=":", color="0.4", label=f"quantization floor α = {a:.3g}")
        ax1.set_xlabel("instantaneous SNR Υ (dB)")
        ax1.set_ylabel("communication noise variance σ_n²")
        ax1.set_title(f"Fig. 3(a) — σ_n²(Υ), δ = {d:.4g}")
        ax1.legend(fontsize=8)
        for series, style, lab in (("packet_error", "-", "packet error 1 − (1 − Ω(√Υ))^{N_p}"),
                                   ("drop_step", "*--", "threshold model, eq. (5)")):
            g = t[t.series == series]
            ax2.plot(g.snr_db, g.value, style, ms=4, label=lab)
        T = float(p[p.quantity == "threshold"].value.iloc[0])
        ax2.set_xlabel("instantaneous SNR Υ (dB)")
        ax2.set_ylabel("probability of packet drop μ")
        ax2.set_title(f"Fig. 3(b) — μ vs Υ (Υ_T = {T:g} = {10 * np.log10(T):.3g} dB)")
        ax2.legend(fontsize=8)
        return fig


# --------------------------------------------------------------------------- Fig. 4


class FadingAverages(AnalysisModel):
    """``kind: fading_averages`` — Fig. 4: μ_ave(Υ_T) and σ²_n,ave(Υ_T), eqs (15)–(16): closed form, quadrature, Monte Carlo."""

    kind: Literal["fading_averages"]
    thresholds: Grid

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        ch = _fading(scenario, iid_only=True)
        a, d = _ber_params(ch)
        Ya = ch.mean_snr
        T = self.thresholds.linear
        N = ctx.mc_runs(scenario)

        def kernel(rng, n):
            Y = ch.sample(rng, n, 1).snr[0]
            keep = Y[None, :] >= T[:, None]
            s2 = np.where(keep, ch.noise.variance(Y)[None, :], 0.0)
            return {"drop": (~keep).sum(1).astype(float), "s2": s2.sum(1), "s2sq": (s2**2).sum(1)}

        mc = run_chunked(kernel, N, scenario.montecarlo.chunk, scenario.montecarlo.seed, progress=ctx.progress)
        rows = []
        mu_mc = mc["drop"] / N
        s2_mc = mc["s2"] / N
        s2_se = np.sqrt(np.maximum(mc["s2sq"] / N - s2_mc**2, 0) / (N - 1))
        for quantity, closed, quad, m, se in (
            ("mu_ave", fa.mu_ave(T, Ya), [fa.mu_ave_quad(t, Ya) for t in T], mu_mc, np.sqrt(mu_mc * (1 - mu_mc) / N)),
            ("sigma2_n_ave", fa.sigma2_n_ave(T, Ya, a, d), [fa.sigma2_n_ave_quad(t, Ya, a, d) for t in T], s2_mc, s2_se),
        ):
            for method, v, e, n in (("closed_form", closed, np.nan, np.nan), ("quadrature", quad, np.nan, np.nan),
                                    ("monte_carlo", m, se, N)):
                rows.append(pd.DataFrame({**_thr_cols(T), "quantity": quantity, "series": f"{quantity}_{method}",
                                          "method": method, "value": v, "stderr": e, "n": n}))
        table = pd.concat(rows, ignore_index=True)
        return Artefact(table, meta={"snr_avg_linear": Ya, "alpha": a, "delta": d,
                                     "threshold_unit_in_table": "threshold linear, threshold_db in dB"})

    def plot(self, tables, scenario):
        t = tables["main"]
        fig, ax = new_figure()
        ax2 = ax.twinx()
        for q, axis, c, lab in (("mu_ave", ax, "C0", "μ_ave (eq. 15)"), ("sigma2_n_ave", ax2, "C1", "σ²_n,ave (eq. 16)")):
            g = t[t.quantity == q]
            cf = g[g.method == "closed_form"]
            axis.plot(cf.threshold, cf.value, "-", color=c, label=f"{lab}, closed form")
            qd = g[g.method == "quadrature"]
            axis.plot(qd.threshold, qd.value, "o", mfc="none", ms=6, color=c, label=f"{lab}, quadrature")
            mc = g[g.method == "monte_carlo"]
            axis.errorbar(mc.threshold, mc.value, yerr=5 * mc.stderr, fmt="x", ms=4, color=c, label=f"{lab}, Monte Carlo ±5 s.e.")
        ax2.set_yscale("log")
        ax.set_xlabel("drop threshold Υ_T (linear)")
        ax.set_ylabel("average probability of packet drop μ_ave", color="C0")
        ax2.set_ylabel("average communication noise σ²_n,ave (log)", color="C1")
        ax2.grid(False)
        ch = scenario.channel
        ax.set_title(f"Fig. 4 — μ_ave and σ²_n,ave vs Υ_T (Υ_ave = {ch.snr_avg.value:g} {ch.snr_avg.unit})")
        h1, l1 = ax.get_legend_handles_labels()
        h2, l2 = ax2.get_legend_handles_labels()
        ax.legend(h1 + h2, l1 + l2, fontsize=7, loc="center right")
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
            raise ConfigError.at("system.C", "eq. (20) needs an invertible (square) C; see kind fading_receivers for general C")
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
        t, o = tables["main"], tables["optima"]
        fig, ax = new_figure()
        for i, (Ya_db, g) in enumerate(t[t.series == "norm_EPinf"].groupby("snr_avg_db")):
            c = f"C{i}"
            ax.semilogy(g.threshold, g.value, "-", color=c, label=f"Υ_ave = {Ya_db:.3g} dB")
            oo = o[np.isclose(o.snr_avg_db, Ya_db)]
            on = oo[oo.quantity == "opt_norm_numerical"]
            ax.plot(on.threshold, on.objective, "o", color=c, ms=7)
            r = oo[oo.quantity == "root_eq24"]
            ax.plot(r.threshold, [g.value.min()] * len(r), "x", color="k", ms=8)
            lim = oo[oo.quantity == "stability_limit"].threshold.iloc[0]
            ax.axvline(lim, color=c, ls=":", lw=0.8)
        ax.plot([], [], "o", color="0.3", label="numerical optimum (eq. 21)")
        ax.plot([], [], "x", color="k", label="root of eq. (24), Thm 1")
        ax.plot([], [], ":", color="0.3", label="stability limit μ_ave = ρ_max⁻² (eq. 19)")
        ax.set_xlabel("drop threshold Υ_T (linear)")
        ax.set_ylabel("‖E P[∞]‖ (spectral norm, log)")
        ax.set_title("Fig. 5 — scenario 2 (no cross-layer path): ‖E P∞‖ vs Υ_T")
        ax.legend(fontsize=7)
        footnote(fig, "eq. (20) by a discrete Lyapunov solve; Thm 1 assumes a symmetric A (not the case here)")
        return fig


# --------------------------------------------------------------------------- Fig. 6 and Sec. 4.2


class FadingReceivers(AnalysisModel):
    """``kind: fading_receivers`` — ‖E P[k]‖ after ``horizon`` steps vs Υ_T for receiver scenarios (Fig. 6, Sec. 4.2).

    i.i.d. channel. Series per scenario s: ``s{s}_conditioned`` (burst-conditioned Monte Carlo),
    ``s{s}_naive`` (plain sample mean), and where they exist the exact means: ``s2_exact`` (eq. 14,
    invertible C) and ``s1_R0_exact`` (eq. 32, Lemma 5's lower bound for scenario 3).
    """

    kind: Literal["fading_receivers"]
    thresholds: Grid
    scenarios: list[Literal[1, 2, 3]] = Field([2, 3], min_length=1)

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        ch = _fading(scenario, iid_only=True)
        s = scenario.linear_system()
        P0 = _P0(s)
        Ya = ch.mean_snr
        T = self.thresholds.linear
        G = len(T)
        H = scenario.montecarlo.horizon
        N = ctx.mc_runs(scenario)
        mus = fa.mu_ave(T, Ya)
        rho = fa.rho_max(s.A)
        models = {sc: _receiver_model(scenario, sc, s) for sc in self.scenarios}

        def kernel(rng, n):
            out = {}
            th, mu = np.repeat(T, n), np.repeat(mus, n)
            for sc, rm in models.items():
                P, U = fr.burst_conditioned_paths(rm, rng, th, mu, Ya, P0, H, [H])
                for lab, X in (("naive", P[0]), ("conditioned", U[0])):
                    for k, v in _stats(X, G, n).items():
                        out[f"s{sc}_{lab}_{k}"] = v
            return out

        tot = run_chunked(kernel, N, scenario.montecarlo.chunk, scenario.montecarlo.seed, progress=ctx.progress)
        frames = []
        for sc in self.scenarios:
            for lab in ("conditioned", "naive"):
                t = {k: tot[f"s{sc}_{lab}_{k}"] for k in ("sum", "sumsq", "tr", "tr2", "inf")}
                fv = np.ones(G, bool) if lab == "conditioned" else mus * rho**4 < 1
                df = _summ(t, N, f"s{sc}_{lab}", fv)
                df.insert(0, "scenario", sc)
                df.insert(1, "method", lab)
                for k, v in _thr_cols(T).items():
                    df.insert(2, k, v)
                frames.append(df)
        exact = []
        square = s.m == s.n and abs(np.linalg.det(s.C)) > 1e-12
        if square and ch.noise.model == "ber":
            a, d = ch.noise.params
            exact.append(("s2_exact", 2, [fa.spectral_norm(fa.ep_recursion(s.A, s.C, s.Q, m_, float(fa.sigma2_n_ave(t_, Ya, a, d)), P0, H, s.R)[-1]) for m_, t_ in zip(mus, T)]))
        exact.append(("s1_R0_exact", 1, [fa.spectral_norm(fa.lower_bound_recursion(s.A, s.Q, m_, P0, H)[-1]) for m_ in mus]))
        for lab, sc, v in exact:
            frames.append(pd.DataFrame({"scenario": sc, "method": "exact", **{k: v_ for k, v_ in _thr_cols(T).items()},
                                        "series": lab, "value": v, "stderr": 0.0, "n": np.nan, "ess_frac": np.nan,
                                        "finite_variance": 1, "reliable": 1, "overflowed": 0.0}))
        table = pd.concat(frames, ignore_index=True)
        # the best threshold per scenario from the conditioned estimator, with the set of thresholds
        # statistically indistinguishable from it (within 2 combined standard errors)
        opt = []
        for sc in self.scenarios:
            g = table[table.series == f"s{sc}_conditioned"].reset_index(drop=True)
            i = int(np.nanargmin(g.value.to_numpy()))
            near = g[(g.value - g.value[i]) <= 2 * np.hypot(g.stderr, g.stderr[i])]
            opt.append({"scenario": sc, "quantity": "argmin_conditioned", "threshold": g.threshold[i],
                        "value": g.value[i], "stderr": g.stderr[i],
                        "threshold_low": near.threshold.min(), "threshold_high": near.threshold.max()})
        opt.append({"scenario": 0, "quantity": "stability_limit_eq19", "threshold": fa.max_stable_threshold(Ya, rho),
                    "value": np.nan, "stderr": np.nan, "threshold_low": np.nan, "threshold_high": np.nan})
        return Artefact(table, extra_tables={"optima": pd.DataFrame(opt)},
                        meta={"horizon": H, "runs": N, "snr_avg_linear": Ya, "rho_max": rho,
                              "reliable_rule": f"stderr/value < {RELIABLE_REL_SE}, finite variance (naive: mu*rho_max^4 < 1), no overflow",
                              "scenario2_general_C": bool(not square)})

    def plot(self, tables, scenario):
        t, o = tables["main"], tables["optima"]
        fig, ax = new_figure()
        styles = {"conditioned": ("-", "o"), "naive": ("none", "x"), "exact": ("--", None)}
        colors = {1: "C2", 2: "C0", 3: "C1"}
        names = {"s2_exact": "scenario 2 exact (eq. 14)", "s1_R0_exact": "Lemma 5 lower bound (eq. 32)"}
        for lab, g in t.groupby("series", sort=False):
            sc, method = int(g.scenario.iloc[0]), g.method.iloc[0]
            ls, mk = styles[method]
            c = colors[sc] if lab != "s1_R0_exact" else "0.5"
            name = names.get(lab, f"scenario {sc}, {method} MC")
            if method == "exact":
                ax.semilogy(g.threshold, g.value, ls=ls, color=c, label=name)
                continue
            rel = g[g.reliable == 1]
            bad = g[g.reliable == 0]
            ax.errorbar(rel.threshold, rel.value, yerr=2 * rel.stderr, ls=ls, marker=mk, ms=4, color=c, label=f"{name} ±2 s.e.")
            if len(bad):
                ax.plot(bad.threshold, bad.value, ls="none", marker=mk, ms=7, mfc="none", mec="r")
        ax.plot([], [], ls="none", marker="o", mfc="none", mec="r", label="flagged unreliable MC mean")
        lim = o[o.quantity == "stability_limit_eq19"].threshold.iloc[0]
        if np.isfinite(lim):
            ax.axvline(lim, color="k", ls=":", lw=0.8, label="stability limit (eqs 19, 45)")
        ax.set_yscale("log")
        ax.set_xlabel("drop threshold Υ_T (linear)")
        ax.set_ylabel(f"‖E P[k]‖, k = {scenario.montecarlo.horizon}")
        ch = scenario.channel
        ax.set_title(f"{scenario.name}: receivers, Υ_ave = {ch.snr_avg.value:g} {ch.snr_avg.unit}")
        ax.legend(fontsize=7)
        footnote(fig, f"{int(t.n.dropna().iloc[0])} runs; conditioned = exact average over the final drop burst")
        return fig


# --------------------------------------------------------------------------- Fig. 7


class FadingCorrelation(AnalysisModel):
    """``kind: fading_correlation`` — Fig. 7: correlated (Jakes) vs i.i.d. channel, scenario 2, SISO.

    ‖E P[k]‖ at k = horizon vs Υ_T. The correlated channel has no exact mean; its naive Monte
    Carlo mean is shown with its standard error and the reliability flag, next to the same
    estimator on the i.i.d. channel (whose exact value, eq. 14, shows how far the naive mean can be off).
    Also records the sample autocorrelation of the generated gain against J₀ (eq. 65).
    """

    kind: Literal["fading_correlation"]
    thresholds: Grid
    receiver: Literal[2, 3] = Field(2, description="receiver scenario (2: no cross-layer path, 3: cross-layer path)")
    max_lag: PositiveInt = 8

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
        iid = ch.model_copy(update={"correlation": type(ch).model_fields["correlation"].default})
        lags = np.arange(self.max_lag + 1)

        def kernel(rng, n):
            out = {}
            for lab, c in (("jakes", ch), ("iid", iid)):
                h = sample_gain(rng, n, H, c.correlation)
                snr = Ya * (h.real**2 + h.imag**2)
                Pk = fr.covariance_paths(rm, np.tile(snr, (1, G)), np.repeat(T, n), P0, record=[H])[0]
                for k, v in _stats(Pk, G, n).items():
                    out[f"{lab}_{k}"] = v
                d = snr[None, :, :] < T[:, None, None]  # (G, H, n) drops
                out[f"{lab}_d1"] = (d[:, 1:-1] & d[:, :-2]).sum((1, 2)).astype(float)
                out[f"{lab}_d2"] = (d[:, 2:] & d[:, 1:-1] & d[:, :-2]).sum((1, 2)).astype(float)
                out[f"{lab}_d0"] = d[:, :-2].sum((1, 2)).astype(float)
                if lab == "jakes":
                    t0 = H - 1
                    prod = (h[t0][None, :] * np.conj(h[t0 - lags][:, :])).real
                    out["ac"] = prod.sum(1)
                    out["ac2"] = (prod**2).sum(1)
                    p = snr[t0][None, :] * snr[t0 - lags]
                    out["pc"] = p.sum(1)
                    out["pc2"] = (p**2).sum(1)
            return out

        tot = run_chunked(kernel, N, scenario.montecarlo.chunk, scenario.montecarlo.seed, progress=ctx.progress)
        frames = []
        rho = fa.rho_max(s.A)
        for lab in ("jakes", "iid"):
            with np.errstate(invalid="ignore", divide="ignore"):
                p1 = tot[f"{lab}_d1"] / tot[f"{lab}_d0"]          # Pr[drop | 1 drop before]
                p2 = tot[f"{lab}_d2"] / tot[f"{lab}_d1"]          # Pr[drop | 2 drops before]
            pc = np.fmax(np.nan_to_num(p1), np.nan_to_num(p2))
            df = _summ({k: tot[f"{lab}_{k}"] for k in ("sum", "sumsq", "tr", "tr2", "inf")}, N, f"{lab}_naive",
                       pc * rho**4 < 1)
            df.insert(0, "drop_continuation", pc)
            for k, v in _thr_cols(T).items():
                df.insert(0, k, v)
            df.insert(0, "channel", lab)
            frames.append(df)
        if ch.noise.model == "ber" and s.m == s.n and self.receiver == 2:
            a, d = ch.noise.params
            v = [fa.spectral_norm(fa.ep_recursion(s.A, s.C, s.Q, float(fa.mu_ave(t_, Ya)), float(fa.sigma2_n_ave(t_, Ya, a, d)), P0, H, s.R)[-1]) for t_ in T]
            frames.append(pd.DataFrame({"channel": "iid", **_thr_cols(T), "series": "iid_exact", "value": v, "stderr": 0.0,
                                        "n": np.nan, "ess_frac": np.nan, "finite_variance": 1, "reliable": 1,
                                        "overflowed": 0.0, "drop_continuation": fa.mu_ave(T, Ya)}))
        table = pd.concat(frames, ignore_index=True)
        ac = tot["ac"] / N
        ac_se = np.sqrt(np.maximum(tot["ac2"] / N - ac**2, 0) / (N - 1))
        pc = tot["pc"] / N / Ya**2 - 1.0  # corr of |h|²: E[Υ_t Υ_{t−k}]/Υ_ave² − 1 = J0²
        pc_se = np.sqrt(np.maximum(tot["pc2"] / N - (tot["pc"] / N) ** 2, 0) / (N - 1)) / Ya**2
        J = ch.correlation.autocorr(lags)
        actab = pd.DataFrame({"lag": lags, "lag_s": lags * ch.correlation.interval_s, "J0": J, "gain_autocorr": ac,
                              "gain_autocorr_stderr": ac_se, "power_autocorr": pc, "power_autocorr_stderr": pc_se,
                              "J0_squared": J**2})
        return Artefact(table, extra_tables={"autocorr": actab},
                        meta={"doppler_hz": ch.correlation.doppler, "horizon": H, "runs": N,
                              "first_zero_of_J0_s": 2.404825557695773 / (2 * np.pi * ch.correlation.doppler),
                              "reliable_rule": f"stderr/value < {RELIABLE_REL_SE}, finite variance (drop continuation * rho_max^4 < 1), no overflow"})

    def plot(self, tables, scenario):
        t, ac = tables["main"], tables["autocorr"]
        fig, (ax, ax2) = new_figure(ncols=2, width=5.6)
        for lab, c, mk in (("jakes_naive", "C3", "o"), ("iid_naive", "C0", "s")):
            g = t[t.series == lab]
            rel, bad = g[g.reliable == 1], g[g.reliable == 0]
            name = "correlated (Jakes)" if lab.startswith("jakes") else "uncorrelated"
            ax.errorbar(rel.threshold, rel.value, yerr=2 * rel.stderr, marker=mk, ms=4, color=c, ls="-", label=f"{name}, MC ±2 s.e.")
            ax.plot(bad.threshold, bad.value, marker=mk, ms=7, ls="none", mfc="none", mec="r")
        ex = t[t.series == "iid_exact"]
        if len(ex):
            ax.plot(ex.threshold, ex.value, "k--", label="uncorrelated, exact (eq. 14)")
        ax.plot([], [], marker="o", ls="none", mfc="none", mec="r", label="flagged unreliable MC mean")
        ax.set_yscale("log")
        ax.set_xlabel("drop threshold Υ_T (linear)")
        ax.set_ylabel(f"‖E P[k]‖, k = {scenario.montecarlo.horizon}")
        ax.set_title(f"Fig. 7 — channel correlation, scenario {self.receiver}")
        ax.legend(fontsize=7)
        ax2.errorbar(ac.lag, ac.gain_autocorr, yerr=5 * ac.gain_autocorr_stderr, fmt="o", color="C3", label="sample E h_t h*_{t−k} ±5 s.e.")
        ax2.plot(ac.lag, ac.J0, "k-", label="J₀(2π f_D k T)")
        ax2.errorbar(ac.lag, ac.power_autocorr, yerr=5 * ac.power_autocorr_stderr, fmt="s", color="C0", mfc="none", label="sample corr of Υ ±5 s.e.")
        ax2.plot(ac.lag, ac.J0_squared, "k:", label="J₀²")
        ax2.set_xlabel("lag k (transmissions)")
        ax2.set_ylabel("autocorrelation")
        ax2.set_title("generated Jakes channel vs eq. (65)")
        ax2.legend(fontsize=7)
        footnote(fig, f"{int(t.n.dropna().iloc[0])} runs per channel; red circles: MC mean flagged unreliable (heavy drop-burst tail)")
        return fig


# --------------------------------------------------------------------------- Theorem 4


class FadingTheorem4(AnalysisModel):
    """``kind: fading_theorem4`` — E P[k] of eq. (51) (scenario 3, Υ_T = 0, σ_n² = β/Υ): eq. (56) vs Monte Carlo.

    Monte Carlo: the naive mean of P[k] and the mean of a²ϖβ Π(ϖβ/P[k−1]) (Lemma 7 applied to the
    last step, exact conditional expectation), both with standard errors; quadrature for k = 1, 2.
    """

    kind: Literal["fading_theorem4"]
    a: PositiveFloat = Field(description="A = a > 1")
    P0: PositiveFloat = Field(description="P[0]")
    k_max: PositiveInt = 30

    @model_validator(mode="after")
    def _a(self):
        if not self.a > 1:
            raise ValueError(f"Theorem 4 needs a > 1, got a = {self.a}")
        return self

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        ch = _fading(scenario, iid_only=True)
        if ch.noise.model != "inverse_snr":
            raise ConfigError.at("channel.noise.model", "Theorem 4 needs model inverse_snr (σ_n² = β/Υ, eq. 50)")
        a, beta, Ya, P0, K = self.a, float(ch.noise.beta), ch.mean_snr, self.P0, self.k_max
        w = 1.0 / Ya
        N = ctx.mc_runs(scenario)

        def kernel(rng, n):
            P = np.full(n, P0)
            s, s2, r, r2 = (np.zeros(K + 1) for _ in range(4))
            s[0], s2[0], r[0], r2[0] = P0 * n, P0 * P0 * n, P0 * n, P0 * P0 * n
            for k in range(K):
                cond = a * a * w * beta * fa.scaled_exp1(w * beta / P)  # E[P[k+1] | P[k]] (Lemma 7)
                P = fa.theorem4_step(P, rng.exponential(Ya, n), a, beta)
                s[k + 1], s2[k + 1] = P.sum(), (P * P).sum()
                r[k + 1], r2[k + 1] = cond.sum(), (cond * cond).sum()
            return {"s": s, "s2": s2, "r": r, "r2": r2}

        tot = run_chunked(kernel, N, scenario.montecarlo.chunk, scenario.montecarlo.seed, progress=ctx.progress)
        k = np.arange(K + 1)
        rows = [pd.DataFrame({"k": k, "series": "eq56", "value": fa.theorem4_mean(a, beta, Ya, P0, K), "stderr": 0.0, "n": np.nan})]
        for key, lab in (("s", "mc_naive"), ("r", "mc_conditioned")):
            m = tot[key] / N
            se = np.sqrt(np.maximum(tot[key + "2"] / N - m**2, 0) / (N - 1))
            rows.append(pd.DataFrame({"k": k, "series": lab, "value": m, "stderr": se, "n": N}))
        rows.append(pd.DataFrame({"k": [1, 2], "series": "quadrature",
                                  "value": [fa.theorem4_quadrature(a, beta, Ya, P0, j) for j in (1, 2)], "stderr": 0.0, "n": np.nan}))
        table = pd.concat(rows, ignore_index=True)
        return Artefact(table, meta={"a": a, "beta": beta, "snr_avg_linear": Ya, "P0": P0,
                                     "scaled_exp1": "exp(x)*E1(x) for x < 600, asymptotic series beyond"})

    def plot(self, tables, scenario):
        t = tables["main"]
        fig, ax = new_figure()
        e = t[t.series == "eq56"]
        ax.plot(e.k, e.value, "k-", label="Theorem 4, eq. (56)")
        for lab, c, mk in (("mc_naive", "C0", "o"), ("mc_conditioned", "C1", "s")):
            g = t[t.series == lab]
            ax.errorbar(g.k + (0.15 if lab == "mc_conditioned" else 0), g.value, yerr=5 * g.stderr, fmt=mk, ms=3,
                        color=c, mfc="none", label=f"Monte Carlo ({lab[3:]}) ±5 s.e.")
        q = t[t.series == "quadrature"]
        ax.plot(q.k, q.value, "x", color="C3", ms=9, label="nested quadrature (k = 1, 2)")
        ax.set_yscale("log")
        ax.set_xlabel("time step k")
        ax.set_ylabel("E P[k]")
        ax.set_title(f"Theorem 4 — a = {self.a:g}, β = {scenario.channel.noise.beta:g}, "
                     f"Υ_ave = {scenario.channel.snr_avg.value:g} {scenario.channel.snr_avg.unit}, P[0] = {self.P0:g}")
        ax.legend(fontsize=8)
        return fig
