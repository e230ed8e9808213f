"""Python API: load a scenario (YAML file, YAML text or a dict), run it, get DataFrames and the figure.

    >>> from netkf_cli import load, run
    >>> sc = load({"name": "demo", "system": {"A": 1.2, "C": 1, "Q": 1, "R": 1},
    ...            "channel": {"kind": "bernoulli", "arrival": 0.8}, "estimator": {"kind": "kf"},
    ...            "analysis": {"kind": "mean_vs_time"}, "montecarlo": {"runs": 2000, "horizon": 50}})
    >>> res = run(sc)                       # nothing is written unless out= is given
    >>> res.table.head()                    # tidy pandas DataFrame (the CSV)
    >>> res.figure.savefig("demo.png")      # the matplotlib figure

``run(sc, arrivals=gamma)`` replays a recorded arrival sequence (a numpy array, shape
(horizon,) or (sensors, horizon), 0/1) instead of the scenario's channel. Errors are
:class:`netkf_cli.errors.ConfigError` with the dotted field path, as on the command line.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from pydantic import ValidationError

from netkf_cli import montecarlo
from netkf_cli.errors import ConfigError


@dataclass
class Result:
    """What one run produced: the main table, every extra table, the figure, the manifest meta."""

    table: pd.DataFrame
    tables: dict[str, pd.DataFrame] = field(default_factory=dict)
    figure: Any = None
    meta: dict = field(default_factory=dict)
    folder: Path | None = None


def load(source: str | Path | dict, overrides: dict | None = None):
    """A validated Scenario from a YAML file path, YAML text (containing a newline) or a dict."""
    from netkf_cli.loader import deep_merge, load_scenario, load_scenario_text, validation_problems

    if isinstance(source, dict):
        from netkf_cli.compat import check_scenario
        from netkf_cli.scenario import scenario_model

        data = deep_merge(source, overrides) if overrides else source
        try:
            sc = scenario_model().model_validate(data)
        except ValidationError as exc:
            raise ConfigError(validation_problems(exc, data, {}, None)) from None
        check_scenario(sc)
        return sc
    if isinstance(source, str) and "\n" in source:
        return load_scenario_text(source, None, overrides)
    return load_scenario(source, overrides)


def run(scenario, *, runs: int | None = None, arrivals: np.ndarray | None = None, out: str | Path | None = None,
        jobs: int = 1, executor: str = "serial", force: bool = False) -> Result:
    """Run a scenario (from :func:`load`); write the result folder only if ``out`` is given."""
    from netkf_cli import runner
    from netkf_cli.recipes.base import RunContext

    if isinstance(scenario, (str, Path, dict)):
        scenario = load(scenario)
    if arrivals is not None:
        from netkf_cli.channels.trace_file import TraceChannel

        scenario = scenario.model_copy(update={"channel": TraceChannel.from_array(np.asarray(arrivals))})
    if out is not None:
        folder = runner.run_scenario(scenario, out_dir=out, runs=runs, force=force,
                                     executor="process" if jobs > 1 else executor, jobs=jobs)
        name = scenario.name
        tables = {p.stem[len(name) + 1:] or "main": pd.read_csv(p) for p in sorted(Path(folder).glob(f"{name}*.csv"))}
        tables["main"] = pd.read_csv(Path(folder) / f"{name}.csv")
        return Result(tables["main"], tables, None, {}, Path(folder))
    ctx = RunContext(runs=runs)
    mode = executor if executor != "serial" else ("process" if jobs > 1 else "serial")
    with montecarlo.execution(mode, jobs):
        art = runner.compute(scenario, ctx)
    tables = {"main": art.table, **art.extra_tables}
    fig = scenario.analysis.plot(tables, scenario) if scenario.sweep is None else None
    return Result(art.table, tables, fig, art.meta)
