"""Fig. 3 of Shi, Xie & Murray 2009: θ(k_i(M), D) against the buffer length D, log scale.

θ(k, D) = ∏_{j<k} (1 − γ̂_j(D)) (eq. 8) with k₁(M), k₂(M) of eqs (5)–(6); the floor
θ(k, D→∞) is the smallest ε a buffer can guarantee (Sec. 3.4).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import pandas as pd
from pydantic import Field

from netkf_cli.analysis import delay_bounds as db
from netkf_cli.channels.delay import CONVENTION_HELP
from netkf_cli.plotting import footnote, new_figure
from netkf_cli.recipes.base import Artefact, RunContext
from netkf_cli.spec import AnalysisModel, PositiveFloat, PositiveInt


def delay_label(channel) -> str:
    """Short text for a delay channel: 'Poisson d = 5' etc."""
    if channel.kind == "bernoulli":
        return f"Bernoulli γ = {channel.arrival:g}"
    dist = channel.delay
    if dist.kind == "poisson":
        return f"Poisson d = {dist.mean:g}"
    if dist.kind == "geometric":
        return f"geometric p = {dist.p:g}"
    return f"pmf {list(dist.probs)} (loss {dist.loss:.3g})"


class ThetaVsBuffer(AnalysisModel):
    """``kind: theta_vs_buffer`` — θ(k₁(M), D) and θ(k₂(M), D) for D = 1 … D_max (Fig. 3)."""

    kind: Literal["theta_vs_buffer"]
    M: list[PositiveFloat] = Field(min_length=1, description="error bounds M (scalar M means M·I)")
    D_max: PositiveInt = Field(15, description="largest buffer length on the x-axis")

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
        fig, ax = new_figure()
        colors = iter(["C0", "C1", "C2", "C3", "C4", "C5", "C6"])
        for M, g in t.groupby("M", sort=True):
            c = next(colors)
            for name, style, marker in (("k1", "-", "o"), ("k2", "--", "s")):
                th = g[g.series == f"theta_{name}"].sort_values("D")
                k = g[g.series == name]["value"].iloc[0]
                ks = "∞" if not np.isfinite(k) else f"{int(k)}"
                if (th.value > 0).any():
                    ax.semilogy(th.D, th.value, style, marker=marker, ms=4, color=c,
                                label=f"θ(k{name[1]}, D), M = {M:g} (k{name[1]} = {ks})")
        ax.set_xlabel("buffer length D")
        ax.set_ylabel("θ(k_i(M), D) = Pr[N_k ≥ k_i]")
        ax.set_title(f"Fig. 3 — θ(k_i, D) for different M ({delay_label(scenario.channel)})")
        ax.legend(fontsize=8)
        footnote(fig, f"convention {t.convention.iloc[0]}: {CONVENTION_HELP[t.convention.iloc[0]]}")
        return fig
