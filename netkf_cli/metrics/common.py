"""What the generic metrics share: grids, estimator labels, the paper reference of a figure."""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from netkf_cli.errors import ConfigError
from netkf_cli.spec import AnalysisModel, PositiveFloat, PositiveInt, StrictModel


class MGrid(StrictModel):
    """An M grid: ``num`` points from ``start`` to ``stop`` (``spacing`` log or linear)."""

    start: PositiveFloat = Field(description="smallest M")
    stop: PositiveFloat = Field(description="largest M")
    num: PositiveInt = Field(60, le=10_000, description="number of grid points (≤ 10 000)")
    spacing: Literal["log", "linear"] = Field("log", description="log or linear spacing")

    @model_validator(mode="after")
    def _order(self):
        if self.stop <= self.start:
            raise ValueError(f"stop must exceed start, got start = {self.start:g}, stop = {self.stop:g}")
        return self

    def values(self) -> np.ndarray:
        if self.spacing == "log":
            return np.geomspace(self.start, self.stop, self.num)
        return np.linspace(self.start, self.stop, self.num)


def m_values(M) -> np.ndarray:
    return M.values() if isinstance(M, MGrid) else np.asarray(M, dtype=float)


class PaperRef(StrictModel):
    """Which paper figure a scenario reproduces (only for the title; user scenarios leave it out)."""

    topic: Literal["shi2009", "fading", "smoothing", "fusion", "markov", "critical"] = Field(
        description="paper topic (see `netkf list`)")
    figure: str = Field("", description='figure or table, e.g. "Fig. 5"')


def labels(estimators) -> list[str]:
    """One label per estimator: its kind, plus the settings that tell repeated kinds apart."""
    kinds = [e.kind for e in estimators]
    out = []
    for e in estimators:
        lab = e.kind
        if kinds.count(e.kind) > 1:
            same = [o for o in estimators if o.kind == e.kind]
            for f, v in e.model_dump().items():
                if f != "kind" and len({str(o.model_dump().get(f)) for o in same}) > 1:
                    lab += f" {f}=" + (",".join(map(str, v)) if isinstance(v, list) else str(v))
        out.append(lab)
    if len(set(out)) < len(out):
        out = [f"{lab} #{i + 1}" for i, lab in enumerate(out)]
    return out


def needs(scenario, what: str):
    """The scenario's system / channel / estimators, or a ConfigError naming the missing block."""
    if what == "channel":
        if scenario.channel is None:
            raise ConfigError.at("channel", "this metric needs a `channel:` block (netkf list shows the kinds)")
        return scenario.channel
    if what == "estimators":
        ests = scenario.estimator_list()
        if not ests:
            raise ConfigError.at("estimator", "this metric needs an `estimator:` (or `estimators:`, a list)")
        return ests
    return scenario.linear_system()


def step_of(at, horizon: int, path: str = "analysis.at") -> int:
    """The time index k of ``at`` (``stationary`` = the horizon: P_k after a burn-in from P0)."""
    if at == "stationary":
        return horizon
    if at > horizon:
        raise ConfigError.at(path, f"must be ≤ montecarlo.horizon = {horizon}, got {at}")
    return int(at)


class GenericMetric(AnalysisModel):
    """What distribution, mean_vs_time and compare share: validation and the engine call."""

    def check(self, scenario) -> None:
        needs(scenario, "channel"), needs(scenario, "estimators")
        if hasattr(self, "at"):
            step_of(self.at, scenario.montecarlo.horizon)

    def simulate(self, scenario, ctx, reducer, steps, horizon: int):
        """Run the scenario's estimators on its channel's traces (stream 0): (system, estimators, statistics)."""
        from netkf_cli import engine

        s, ch, ests = needs(scenario, "system"), needs(scenario, "channel"), needs(scenario, "estimators")
        mc = scenario.montecarlo
        runs = ctx.mc_runs(scenario)
        ctx.total(runs)
        st = engine.simulate(s, ch, ests, reducer, steps=steps, runs=runs, horizon=horizon, seed=mc.seed,
                             chunk=mc.chunk, stream=0, progress=ctx.progress, label=self.kind)
        return s, ests, st
