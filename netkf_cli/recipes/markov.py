"""Moayedi, Soh & Foo 2009: the paper's arithmetic for its two examples (closed forms, no Monte Carlo).

The Monte Carlo half of each example — the four filters on the same simulated runs, every filter's
error beside the covariance it reports (NEES), the trajectories of Figs 1-1 / 2-1 — is a configuration of
the generic ``state_error`` metric (configs/markov/example1.yaml, example2.yaml). This recipe,
``analysis.kind: markov_exact``, evaluates on the paper's time base (x(0) ~ (x0, P0) is the prior of the
first measurement y(0))

* ``lmmse``    — the exact linear minimum-MSE filter without mode knowledge (Costa's construction),
* ``lmi``      — the paper's LMI-designed filter (Sec. III) and its design claim Λ_ζ,
* ``naive_kf`` — the KF that assumes every packet is an on-time measurement,

exactly through second moments (:func:`exact_mse`), and writes

* ``<name>.csv``        — E‖x(k) − x̂‖² per k, filter and estimate (``exact``; ``design`` for the LMI's Λ_ζ),
* ``<name>_mse.csv``    — the same averaged over the window k = burn_in … horizon−1, also from x_s(0),
* ``<name>_modes.csv``  — ρ_q (stationary, design, initial),
* ``<name>_claims.csv`` — the paper's claims decided by these numbers (``claim_*``: 1.0 = holds) and ratios.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from netkf_cli.core.lazy import pandas as pd
from pydantic import Field

from netkf_cli.channels.markov_modes import MODE_NAMES, N_MODES
from netkf_cli.core.errors import ConfigError, Problem
from netkf_cli.estimators.markov_filters import exact_mse, lmmse_filter, naive_filter
from netkf_cli.estimators.markov_lmi import MarkovLMIEstimator, lmi_design
from netkf_cli.runtime.plotting import LINESTYLES, PALETTE, footnote, legend_outside, new_figure, paper_title
from netkf_cli.recipes.base import Artefact, RunContext
from netkf_cli.core.spec import AnalysisModel

FILTERS = ("lmmse", "lmi", "naive_kf")
LABELS = {"lmmse": "exact LMMSE (modes unobserved)", "lmi": "LMI filter (paper)", "naive_kf": "naive KF (ignores modes)"}
ESTIMATES = ("predicted", "filtered")
XS0_REL = 0.01  # "the estimates track the state from x_s(0)": the window MSE from x_s(0) within 1 % of the one from E x(0)


class MarkovExactAnalysis(AnalysisModel):
    """``kind: markov_exact`` — exact MSEs of the LMMSE, LMI and naive filters and the paper's claims (closed forms).

    Needs ``channel.kind: markov_modes``; ``estimator`` (``kind: markov_lmi``: design settings and S) is optional.
    """

    kind: Literal["markov_exact"]
    x0: list[float] | None = Field(None, description="mean of x(0) (default 0); x(0) ~ N(x0, system.P0), P0 default 0")
    xs0: list[float] | None = Field(None, description="the paper's initial estimate x_s(0) (default x0): the claim "
                                                      "that the filter forgets it is decided from here")

    def check(self, scenario) -> None:
        """What ``netkf validate`` reports before any work: the estimator kind, x0 / xs0 sizes, the estimator's own
        checks (burn_in < horizon is the scenario's check)."""
        self._checked(scenario)

    def _checked(self, scenario):
        sysm = scenario.linear_system()
        ch = scenario.require_channel("markov_modes")
        est = scenario.estimator or MarkovLMIEstimator(kind="markov_lmi")
        if getattr(est, "kind", None) != "markov_lmi":
            raise ConfigError.at("estimator.kind", f"this analysis needs an estimator of kind markov_lmi (or none), got {est.kind}")
        n = sysm.n
        problems = []

        def vec(v, name):
            a = np.zeros(n) if v is None else np.asarray(v, float)
            if a.shape != (n,):
                problems.append(Problem(f"analysis.{name}", f"must have {n} entries (the state dimension), got {a.size}"))
                return np.zeros(n)
            return a

        x0 = vec(self.x0, "x0")
        xs0 = x0 if self.xs0 is None else vec(self.xs0, "xs0")
        try:
            est.check(sysm, ch)
        except ConfigError as e:
            problems.extend(e.problems)
        if problems:
            raise ConfigError(problems)
        return sysm, ch, est, x0, xs0

    def _setup(self, scenario):
        sysm, ch, est, x0, xs0 = self._checked(scenario)
        n = sysm.n
        model = est._model(sysm)[0]
        rho = ch.rho if est.rho == "stationary" else np.asarray(est.rho, float)
        P0 = sysm.P0 if sysm.P0 is not None else np.zeros((n, n))
        return sysm, ch, est, model, x0, xs0, P0, rho

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        sysm, ch, est, model, x0, xs0, P0, rho = self._setup(scenario)
        mc = scenario.montecarlo
        K, burn = mc.horizon, mc.burn_in
        T, pi0 = ch.T, ch.pi0
        ctx.total(K)
        try:
            des = lmi_design(model, rho, x0, P0, K, design=est.design, solver=est.solver, tol=est.solver_tol,
                             eps=est.eps, precedence=est.precedence, progress=ctx.tick, sdp_check=est.sdp_check)
        except RuntimeError as e:  # solver failure: a user-facing message, not a traceback
            raise ConfigError.at("estimator", f"{e}; try `solver: SCS`, a larger `eps` or `design: closed_form`") from None
        linear = {"lmmse": lmmse_filter(model, T, pi0, x0, P0, K), "lmi": des.filter, "naive_kf": naive_filter(model, x0, P0, K)}
        exact = {f: exact_mse(model, F, T, pi0, x0, P0) for f, F in linear.items()}
        exact_xs0 = {f: exact_mse(model, F.with_initial_estimate(xs0), T, pi0, x0, P0) for f, F in linear.items()}
        main, mse, modes, claims = _tables(exact, exact_xs0, linear, K, burn, ch, rho)
        meta = {
            "paper": "Moayedi, Soh & Foo 2009, Optimal Kalman filtering with random sensor delays, packet dropouts "
                     "and missing measurements",
            "model": "ξ(k) = [x(k); x(k−1); y(k−1); v(k−1)], ε = [w; v] white with Σ = [[Q, S], [Sᵀ, R]] "
                     "(eqs 5–19 with v(k−1) carried in the state)",
            "time_base": "the paper's: x(0) ~ (x0, P0) is the prior of the first measurement y(0) (eq. 35)",
            "stationary_rho": ch.rho.tolist(), "design_rho": list(map(float, rho)),
            "initial_mode_distribution": pi0.tolist(), "x0": x0.tolist(), "xs0": xs0.tolist(), "P0": P0.tolist(),
            "S": model.S.tolist(), "horizon": K, "burn_in": burn, "mse_window": f"k = {burn} … {K - 1}",
            "lmi_design": {k: (float(v) if isinstance(v, (np.floating, float)) else v) for k, v in des.diagnostics.items()},
            "monte_carlo": "none (closed forms); the Monte Carlo of the same filters is the state_error artefact",
        }
        return Artefact(table=main, meta=meta, extra_tables={"mse": mse, "modes": modes, "claims": claims},
                        extra_text={"table.md": _markdown(mse, claims, modes)})

    def plot(self, tables, scenario):
        t = tables["main"]
        fig, axes = new_figure(ncols=2, width=5.2, height=4.2)
        colors = {"lmmse": PALETTE[0], "lmi": PALETTE[1], "naive_kf": PALETTE[2]}
        styles = {"lmmse": LINESTYLES[0], "lmi": LINESTYLES[1], "naive_kf": LINESTYLES[3]}
        for ax, e in zip(axes, ESTIMATES):
            shown = ax is axes[-1]  # one legend (under the last panel) for both panels: same styles
            for f in FILTERS:
                d = t[(t["filter"] == f) & (t["estimate"] == e) & (t["quantity"] == "exact")]
                ax.plot(d["k"], d["value"], color=colors[f], ls=styles[f], lw=1.5, label=LABELS[f] if shown else "_nolegend_")
            d = t[(t["filter"] == "lmi") & (t["estimate"] == e) & (t["quantity"] == "design")]
            ax.plot(d["k"], d["value"], color=colors["lmi"], ls=(0, (1, 1)), lw=1.2,
                    label=r"LMI design's bound $\Lambda_\zeta$ (Sec. III-C)" if shown else "_nolegend_")
            ax.set_ylim(bottom=0)
            ax.set_xlabel("time step k")
            hat = r"\hat{x}_{k\mid k-1}" if e == "predicted" else r"\hat{x}_{k\mid k}"
            ax.set_ylabel(rf"exact $\mathrm{{E}}\,\|x_k-{hat}\|^2$")
            ax.set_title(f"({'ab'[ESTIMATES.index(e)]}) {e} estimate ${hat}$")
        legend_outside(axes[-1], loc="below", ncol=2)
        fig.suptitle(paper_title("markov", f"Example {scenario.name.split('example')[-1][:1]}",
                                 "exact mean squared error of the linear filters (closed forms)"))
        footnote(fig, f"{scenario.name}: second-moment recursions of the Markov-jump system [ξ; filter state] "
                      "(no Monte Carlo); the paper's time base, x(0) ~ (x0, P0) the prior of y(0)")
        return fig


def _tables(exact, exact_xs0, linear, K, burn, ch, rho):
    window = f"k={burn}..{K - 1}"
    ks = np.arange(K)
    mt, mw = [], []
    for f in FILTERS:
        for ie, e in enumerate(ESTIMATES):
            ex = exact[f][ie]
            mt += [(int(k), f, e, "exact", float(a)) for k, a in zip(ks, ex)]
            mw.append((f, e, "exact", float(ex[burn:].mean()), window))
            mw.append((f, e, "exact_from_xs0", float(exact_xs0[f][ie][burn:].mean()), window))
            if f == "lmi":
                dz = linear["lmi"].predicted["design_pred" if e == "predicted" else "design_filt"]
                mt += [(int(k), f, e, "design", float(a)) for k, a in zip(ks, dz)]
                mw.append((f, e, "design", float(dz[burn:].mean()), window))
            if f == "lmmse":
                mw.append((f, e, "riccati", float(linear["lmmse"].predicted["pred" if e == "predicted" else "filt"][burn:].mean()),
                           window))
    main = pd.DataFrame(mt, columns=["k", "filter", "estimate", "quantity", "value"])
    mse = pd.DataFrame(mw, columns=["filter", "estimate", "quantity", "value", "window"])
    mrows = []
    for q in range(N_MODES):
        mrows += [(q + 1, MODE_NAMES[q], "stationary", float(ch.rho[q])), (q + 1, MODE_NAMES[q], "design", float(rho[q])),
                  (q + 1, MODE_NAMES[q], "initial", float(ch.pi0[q]))]
    modes = pd.DataFrame(mrows, columns=["q", "mode", "quantity", "value"])

    def get(f, e, qn):
        return float(mse[(mse["filter"] == f) & (mse["estimate"] == e) & (mse["quantity"] == qn)]["value"].iloc[0])

    crows = []
    for e in ESTIMATES:
        exv = get("lmmse", e, "exact")
        ric = get("lmmse", e, "riccati")
        crows.append(("claim_lmmse_riccati_equals_exact", e, float(abs(ric - exv) <= 1e-8 * exv), ric - exv))
        lx, l0 = get("lmi", e, "exact_from_xs0"), get("lmi", e, "exact")
        crows.append(("claim_lmi_forgets_xs0", e, float(abs(lx - l0) <= XS0_REL * l0), lx - l0))
        crows.append(("ratio_lmi_over_lmmse", e, l0 / exv, l0 - exv))
        ds_ = get("lmi", e, "design")
        crows.append(("ratio_lmi_design_over_exact", e, ds_ / l0, ds_ - l0))
        dz = linear["lmi"].predicted["design_pred" if e == "predicted" else "design_filt"]
        exk = exact["lmi"][0 if e == "predicted" else 1]
        pos = exk > 1e-12 * exk.max()
        rmin = float(np.min(dz[pos] / exk[pos]))
        crows.append(("claim_lmi_design_bounds_exact", e, float(rmin >= 1 - 1e-9), rmin))
        nv = get("naive_kf", e, "exact")
        crows.append(("ratio_naive_over_lmmse", e, nv / exv, nv - exv))
    claims = pd.DataFrame(crows, columns=["series", "estimate", "value", "statistic"])
    return main, mse, modes, claims


def _markdown(mse: pd.DataFrame, claims: pd.DataFrame, modes: pd.DataFrame) -> str:
    out = ["| filter | estimate | exact MSE | from x_s(0) | LMI design claim |", "|---|---|---|---|---|"]
    for f in FILTERS:
        for e in ESTIMATES:
            d = mse[(mse["filter"] == f) & (mse["estimate"] == e)].set_index("quantity")
            dz = f"{d.loc['design', 'value']:.5g}" if "design" in d.index else "—"
            out.append(f"| {LABELS[f]} | {e} | {d.loc['exact', 'value']:.5g} | {d.loc['exact_from_xs0', 'value']:.5g} | {dz} |")
    out += ["", "| q | mode | stationary ρ_q | design ρ_q |", "|---|---|---|---|"]
    for q in range(1, N_MODES + 1):
        d = modes[modes["q"] == q].set_index("quantity")
        out.append(f"| {q} | {MODE_NAMES[q - 1]} | {d.loc['stationary', 'value']:.6g} | {d.loc['design', 'value']:.6g} |")
    out += ["", "| claim | estimate | value | statistic |", "|---|---|---|---|"]
    for _, r in claims.iterrows():
        out.append(f"| {r['series']} | {r['estimate']} | {r['value']:.6g} | {r['statistic']:.4g} |")
    return "\n".join(out) + "\n"
