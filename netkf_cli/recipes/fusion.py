"""Fig. 2 of Chiuso & Schenato (information fusion over N packet-drop links): closed form, no Monte Carlo.

* ``fusion_bounding_functions`` (Fig. 2): Φ_f(P, ℓ) and its chord L_f^LB(P, ℓ) (Lemma 2) for ℓ = 0…6.

Figs 1 and 3 are configurations of the generic ``time_average`` metric (configs/fusion/fig1.yaml,
fig3.yaml: ``over`` system.Q / channel.loss, the bounds of Sec. III as the ``fusion_bounds`` and
``fusion_centralized`` references of :mod:`netkf_cli.analysis.fusion_bounds`); their claims read the
metric's derived ``pairs`` table (experiments/fusion/published.yaml).

The artefact also writes a ``claims`` table: one row per checkable statement of the paper, with
``value`` 1.0 (holds in our numbers) or 0.0, and ``claims_evidence`` (the two sides compared, the margin).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from netkf_cli.core.lazy import pandas as pd
from pydantic import Field

from netkf_cli.analysis import fusion_bounds as fb
from netkf_cli.core.errors import ConfigError, Problem
from netkf_cli.runtime.plotting import footnote, legend_outside, new_figure, paper_title, series_style
from netkf_cli.recipes.base import Artefact, RunContext
from netkf_cli.core.spec import AnalysisModel, NonNegInt, PositiveFloat, PositiveInt

CONVENTIONS = {
    "P": "prediction error variance P (the argument of the Riccati filtering map)",
    "ell": "number of packets received in the step (of N sensors)",
}


def _claim(claim: str, holds: bool, lhs: float, rhs: float, margin: float, detail: str) -> dict:
    return dict(claim=claim, value=1.0 if holds else 0.0, lhs=float(lhs), rhs=float(rhs), margin=float(margin), detail=detail)


def _claim_tables(claims: list[dict]) -> dict[str, pd.DataFrame]:
    """``claims`` (claim, value ∈ {0, 1}: what published.yaml checks) and ``claims_evidence`` (the numbers
    compared; no ``value`` column, so they never enter golden comparisons)."""
    df = pd.DataFrame(claims, columns=["claim", "value", "lhs", "rhs", "margin", "detail"])
    return {"claims": df[["claim", "value"]], "claims_evidence": df[["claim", "lhs", "rhs", "margin", "detail"]]}


# ----------------------------------------------------------------------------------------
# Fig. 2
# ----------------------------------------------------------------------------------------


class FusionBoundingFunctions(AnalysisModel):
    """``kind: fusion_bounding_functions`` — Fig. 2: Φ_f(P, ℓ) and L_f^LB(P, ℓ) vs P (scalar system)."""

    kind: Literal["fusion_bounding_functions"]
    sensors: PositiveInt = Field(description="N, which fixes P_m = Φ(P_m, N)")
    ell: list[NonNegInt] = Field(default_factory=lambda: list(range(7)), min_length=1, description="numbers of received packets ℓ")
    points: PositiveInt = Field(241, ge=3, description="grid points in P")
    P_max_factor: PositiveFloat = Field(1.15, description="the P axis runs from 0 to P_max_factor · P_M")

    def check(self, scenario) -> None:
        """ℓ received packets out of N = sensors: reported by ``netkf validate``, before any work."""
        problems = [Problem(f"analysis.ell[{i}]", f"must be ≤ sensors = {self.sensors}, got {l}")
                    for i, l in enumerate(self.ell) if l > self.sensors]
        s = scenario.linear_system()
        try:  # P_m and P_M exist (a detectable, stable scalar system)
            model = fb.ScalarFusionModel.from_matrices(s.A, s.C, s.Q, s.R, self.sensors)
            model.pm, model.pM
        except ConfigError as exc:
            problems += exc.problems
        if problems:
            raise ConfigError(problems)

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        s = scenario.linear_system()
        self.check(scenario)
        model = fb.ScalarFusionModel.from_matrices(s.A, s.C, s.Q, s.R, self.sensors)
        pm, pM = model.pm, model.pM
        P = np.linspace(0.0, self.P_max_factor * pM, self.points)
        P = np.unique(np.concatenate([P, [pm, pM]]))
        rows, checks, claims = [], [], []
        inside = np.linspace(pm, pM, 2001)
        for l in self.ell:
            for series, vals in (("phi_f", model.phi_f(P, l)), ("lf_lb", model.lf_lb(P, l))):
                rows += [dict(P=p, ell=l, series=series, value=v) for p, v in zip(P, vals)]
            gap = model.phi_f(inside, l) - model.lf_lb(inside, l)
            end_err = max(abs(model.phi_f(pm, l) - model.lf_lb(pm, l)), abs(model.phi_f(pM, l) - model.lf_lb(pM, l)))
            checks.append(dict(ell=l, min_gap_on_Pm_PM=float(gap.min()), max_gap_on_Pm_PM=float(gap.max()), chord_endpoint_error=float(end_err)))
        lem = fb.lemma1_violations(model, np.linspace(pm, pM, 401), np.linspace(0, self.sensors, 4 * self.sensors + 1))
        ck = pd.DataFrame(checks)
        scale = pM
        claims.append(_claim("lf_lb_le_phi_f", bool((ck.min_gap_on_Pm_PM >= -1e-12 * scale).all()), ck.min_gap_on_Pm_PM.min(), 0.0, 1e-12 * scale,
                             "L_f^LB(P, l) <= Phi_f(P, l) on [P_m, P_M] for every l (Lemma 2)"))
        claims.append(_claim("phi_f_concave_in_P", lem["concave_ok"], lem["concave_in_P_max_second_diff"], 0.0, 1e-12,
                             "max relative second difference in P on [P_m, P_M] <= 0 (Lemma 1)"))
        claims.append(_claim("phi_f_convex_in_ell", lem["convex_ok"], lem["convex_in_ell_min_second_diff"], 0.0, 1e-12,
                             "min relative second difference in l on [0, N] >= 0 (Lemma 1)"))
        table = pd.DataFrame(rows, columns=["P", "ell", "series", "value"])
        marks = pd.DataFrame([dict(name="P_m", value=pm), dict(name="P_M", value=pM)])
        meta = {"conventions": CONVENTIONS, "P_m": pm, "P_M": pM, "sensors": self.sensors}
        return Artefact(table, meta=meta, extra_tables={"checks": ck, "marks": marks, **_claim_tables(claims)})

    def plot(self, tables, scenario):
        t, marks = tables["main"], tables["marks"].set_index("name")["value"]
        fig, ax = new_figure(width=7.6, height=5.0)
        ells = sorted(t.ell.unique())
        for i, l in enumerate(ells):
            st = series_style(i)
            d = t[(t.ell == l) & (t.series == "phi_f")].sort_values("P")
            every = max(1, len(d) // 8)
            ax.plot(d.P, d.value, color=st["color"], ls="-", lw=1.7, marker=st["marker"], ms=4.5,
                    markevery=(i % every, every), label=rf"$\ell = {int(l)}$")
            d = t[(t.ell == l) & (t.series == "lf_lb")].sort_values("P")
            ax.plot(d.P, d.value, color=st["color"], lw=1.1, ls="--", label="_chord")
        for name, tex in (("P_m", "P_m"), ("P_M", "P_M")):
            ax.axvline(marks[name], color="0.4", lw=0.8, ls=":")
            ax.text(marks[name], 0.02, f" ${tex}$ = {marks[name]:.3g}", transform=ax.get_xaxis_transform(), ha="left",
                    va="bottom", fontsize=9, color="0.25")
        # style key: every coloured pair above is drawn in these two line styles
        ax.plot([], [], color="k", ls="-", lw=1.7, label=r"$\Phi_f(P,\ell)$ (eq. 14)")
        ax.plot([], [], color="k", ls="--", lw=1.1, label=r"$L_f^{LB}(P,\ell)$ (Lemma 2, eq. 17)")
        legend_outside(ax)
        ax.set_xlabel(r"prediction error variance $P$")
        ax.set_ylabel(r"filtering error variance")
        s = scenario.system
        ax.set_title(paper_title("fusion", 2, r"bounding functions $\Phi_f$ and $L_f^{LB}$") +
                     f"\nA = {s.A[0][0]:g}, C = {s.C[0][0]:g}, Q = {s.Q[0][0]:g}, R = {s.R[0][0]:g}, N = {scenario.analysis.sensors}")
        footnote(fig, r"solid: $\Phi_f$; dashed (same colour): its chord through $P_m$ and $P_M$, a lower bound on "
                      r"$[P_m, P_M]$ only")
        return fig
