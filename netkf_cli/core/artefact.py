"""What every analysis (generic metric or paper recipe) receives (:class:`RunContext`) and returns
(:class:`Artefact`). Core layer: metrics and recipes both build on it."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from netkf_cli.core.lazy import pandas as pd


@dataclass
class RunContext:
    """Run-time options that are not part of the scenario.

    ``runs`` overrides the scenario's Monte Carlo size (``--runs``, ``--quick``);
    ``progress(n)`` reports ``n`` more units of work done (runs, grid points …).
    """

    runs: int | None = None
    quick: bool = False
    progress: Callable[[int], None] | None = None
    set_total: Callable[[int], None] | None = None
    stream: int = 0
    """The random stream of this run's Monte Carlo (allocated by the runner: an ``over`` grid's point)."""

    def mc_runs(self, scenario: Any) -> int:
        return int(self.runs or scenario.montecarlo.runs)

    def tick(self, n: int = 1) -> None:
        if self.progress is not None:
            self.progress(n)

    def total(self, n: int) -> None:
        if self.set_total is not None:
            self.set_total(n)


@dataclass
class Artefact:
    """A recipe's output: a tidy table (→ ``<name>.csv``) plus optional extras.

    ``meta`` goes into ``manifest.json`` (conventions, Monte Carlo sizes, solver …);
    ``extra_tables[key]`` → ``<name>_<key>.csv``; ``extra_text[filename]`` → a file as is.
    """

    table: pd.DataFrame
    meta: dict[str, Any] = field(default_factory=dict)
    extra_tables: dict[str, pd.DataFrame] = field(default_factory=dict)
    extra_text: dict[str, str] = field(default_factory=dict)
