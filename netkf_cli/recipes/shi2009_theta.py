"""Fig. 3 of Shi, Xie & Murray 2009: θ(k_i(M), D) against the buffer length D, log scale.

θ(k, D) = ∏_{j<k} (1 − γ̂_j(D)) (eq. 8) with k₁(M), k₂(M) of eqs (5)–(6); the floor
θ(k, D→∞) is the smallest ε a buffer can guarantee (Sec. 3.4).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from netkf_cli.core.lazy import pandas as pd
from pydantic import Field

from netkf_cli.analysis import delay_bounds as db
from netkf_cli.channels.delay import CONVENTION_HELP, delay_label  # noqa: F401 - delay_label re-exported
from netkf_cli.runtime.plotting import PALETTE, footnote, legend_outside, new_figure, paper_title
from netkf_cli.recipes.base import Artefact, RunContext
from netkf_cli.core.errors import ConfigError
from netkf_cli.core.spec import AnalysisModel, PositiveFloat, PositiveInt


class ThetaVsBuffer(AnalysisModel):
    """``kind: theta_vs_buffer`` — θ(k₁(M), D) and θ(k₂(M), D) for D = 1 … D_max (Fig. 3)."""

    kind: Literal["theta_vs_buffer"] = Field(description="θ(k_i(M), D) against the buffer length D (Shi 2009, Fig. 3)")
    M: list[PositiveFloat] = Field(min_length=1, description="error bounds M (scalar M means M·I)")
    D_max: PositiveInt = Field(15, le=10_000, description="largest buffer length on the x-axis (≤ 10 000: one θ per D and M)")

    def check(self, scenario) -> None:
        """k₁ and k₂ exist at every M (M̄ and P̄ exist, M ≥ M̄ and M ≥ P̄: Thms 3.8 and 4.1), reported by
        ``netkf validate`` before any work."""
        s = scenario.linear_system()
        paths = [f"analysis.M[{i}]" for i in range(len(self.M))]
        problems = []
        for k_each in (db.k1_each, db.k2_each):
            try:
                k_each(self.M, s, paths)
            except ConfigError as exc:
                problems += [p for p in exc.problems if p not in problems]
        if problems:
            raise ConfigError(problems)

    def compute(self, scenario, ctx: RunContext) -> Artefact:
        s = scenario.linear_system()
        ch = scenario.require_channel("delay", "bernoulli")
        conv = ch.convention
        rows = []
        for i, M in enumerate(self.M):
            path = f"analysis.M[{i}]"
            ks = {"k1": db.k1(M, s, path), "k2": db.k2(M, s, path)}
            for name, k in ks.items():
                rows.append(dict(M=M, D=np.nan, series=name, k=k, value=k, convention=conv))
                for D in range(1, self.D_max + 1):
                    rows.append(dict(M=M, D=D, series=f"theta_{name}", k=k,
                                     value=db.theta(k, D, ch.cdf, conv), convention=conv))
                rows.append(dict(M=M, D=np.nan, series=f"floor_{name}", k=k,
                                 value=db.theta_floor(k, ch.cdf, conv), convention=conv))
        table = pd.DataFrame(rows, columns=["M", "D", "series", "k", "value", "convention"])
        table["k"] = table["k"].replace(np.inf, np.nan)
        return Artefact(table, meta={"convention": conv, "convention_meaning": CONVENTION_HELP[conv],
                                     "delay": delay_label(ch)})

    def plot(self, tables, scenario):
        t = tables["main"]
        fig, ax = new_figure(width=7.6, height=4.6)
        for ci, (M, g) in enumerate(t.groupby("M", sort=True)):
            c = PALETTE[ci % len(PALETTE)]
            ks = {name: g[g.series == name]["value"].iloc[0] for name in ("k1", "k2")}
            same = ks["k1"] == ks["k2"] or (not np.isfinite(ks["k1"]) and not np.isfinite(ks["k2"]))
            for name, ls, marker, ms in (("k1", "-", "o", 6.5), ("k2", "--", "s", 3.5)):
                th = g[g.series == f"theta_{name}"].sort_values("D")
                k = ks[name]
                kt = r"\infty" if not np.isfinite(k) else f"{int(k)}"
                i = name[1]
                note = r" (= $k_1$: curves coincide)" if (same and name == "k2") else ""
                pos = th[th.value > 0]
                if len(pos):
                    # hollow large circles under small squares: both visible when k₁ = k₂
                    ax.semilogy(pos.D, pos.value, linestyle=ls, marker=marker, ms=ms, mfc="none" if name == "k1" else c,
                                color=c, label=rf"$\theta(k_{i}, D)$, $M = {M:g}$, $k_{i} = {kt}$" + note)
        ax.set_xlabel(r"buffer length $D$ (time steps)")
        ax.set_ylabel(r"$\theta(k_i(M), D) = \Pr[N_k \geq k_i]$")
        fig.suptitle(paper_title("shi2009", 3, rf"$\theta(k_i(M), D)$ vs buffer length $D$, {delay_label(scenario.channel, math=True)}"))
        legend_outside(ax)
        conv = t.convention.iloc[0]
        footnote(fig, f"Convention {conv}: {CONVENTION_HELP[conv]}. "
                      "θ(k, D) = product of (1 − γ̂ⱼ(D)) over j < k (eq. 8); k₁(M), k₂(M) of eqs (5)–(6); "
                      "1 − θ(k₁, D) ≤ Pr[P_k ≤ M] ≤ 1 − θ(k₂, D) (Thm 3.8).")
        return fig

