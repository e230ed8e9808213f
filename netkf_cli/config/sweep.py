"""Parameter sweeps: a ``sweep:`` block over dotted field paths of the scenario.

    sweep:
      channel.delay.mean: [1, 2, 3, 4, 5, 6]
      channel.buffer: {from: 1, to: 15}        # integers from..to inclusive (optional step)
      mode: product                            # or zip (all lists the same length)
      plot: {series: monte_carlo, where: {M: 50}}

Every point is validated before anything runs (a bad point fails with its coordinates);
the artefact's tables get one column per swept field (named by its dotted path).
"""

from __future__ import annotations

import itertools
import re
from typing import Any, Literal

import numpy as np
from netkf_cli.core.lazy import pandas as pd
from pydantic import Field, ValidationError, model_validator

from netkf_cli.core.errors import ConfigError, Problem
from netkf_cli.runtime.plotting import MIN_FONT_PT, footnote, new_figure
from netkf_cli.core.spec import StrictModel
from netkf_cli.metrics.common import at_points


MAX_POINTS = 10_000
"""Most points a sweep may have (each point is a full artefact run): checked before anything is built."""


class SweepRange(StrictModel):
    from_: float = Field(alias="from", description="first value")
    to: float = Field(description="last value (inclusive)")
    step: float = Field(1.0, description="increment (> 0)")

    def values(self) -> list:
        if not (self.step > 0 and np.isfinite(self.step)):
            raise ValueError("step must be a finite number > 0")
        if not (np.isfinite(self.from_) and np.isfinite(self.to)):
            raise ValueError("from and to must be finite numbers")
        n = int(np.floor((self.to - self.from_) / self.step + 1e-9)) + 1
        if n < 1:
            raise ValueError(f"{{from: {self.from_:g}, to: {self.to:g}}} is empty: from must be ≤ to (the values go "
                             f"up by step = {self.step:g})")
        if n > MAX_POINTS:
            raise ValueError(f"{{from: {self.from_:g}, to: {self.to:g}, step: {self.step:g}}} has {n:,} values; "
                             f"a sweep may have at most {MAX_POINTS:,} points")
        vals = [self.from_ + i * self.step for i in range(max(n, 0))]
        return [int(v) if float(v).is_integer() else v for v in vals]


class SweepPlot(StrictModel):
    x: str | None = Field(None, description="swept field on the x-axis (default: the first)")
    series: str | None = Field(None, description="which `series` of the table to draw (default: the first)")
    where: dict[str, Any] = Field(default_factory=dict, description="column == value filters (e.g. {M: 50})")
    logy: bool = Field(False, description="logarithmic y axis")


def _range_problem(err: dict) -> str:
    """One pydantic error of a ``{from, to, step}`` range, in the loader's words."""
    where = ".".join(str(x) for x in err["loc"])
    what = {"missing": "required field is missing",
            "extra_forbidden": "unknown key (a range has from, to and step)"}.get(err["type"], err["msg"])
    return f"{where}: {what}" if where else what


class SweepSpec(StrictModel):
    """``sweep:`` dotted field paths → values; ``mode: product | zip``; optional ``plot``."""

    mode: Literal["product", "zip"] = Field("product", description="product: every combination of the axes; zip: "
                                                                   "the i-th values together (equal lengths)")
    plot: SweepPlot = Field(default_factory=SweepPlot, description="what the sweep figure draws")
    axes: dict[str, list[Any]] = Field(default_factory=dict, description="dotted field path → values (filled from "
                                                                          "the sweep block's other keys)")

    @model_validator(mode="before")
    @classmethod
    def _collect_axes(cls, data):
        if not isinstance(data, dict):
            return data
        data = dict(data)
        axes = dict(data.pop("axes", {}) or {})
        for key in list(data):
            if key in ("mode", "plot"):
                continue
            val = data.pop(key)
            if isinstance(val, dict):
                try:
                    val = SweepRange.model_validate(val).values()
                except ValidationError as exc:  # what is wrong with the range's keys, under the swept path
                    raise ValueError(f"{key}: " + "; ".join(_range_problem(e) for e in exc.errors())) from None
                except ValueError as exc:  # or with its values
                    raise ValueError(f"{key}: {exc}") from None
            if not isinstance(val, list) or not val:
                raise ValueError(f"{key}: expected a non-empty list or {{from, to, step}}")
            axes[key] = val
        data["axes"] = axes
        return data

    @model_validator(mode="after")
    def _check(self):
        if not self.axes:
            raise ValueError("a sweep needs at least one dotted field path with values")
        if self.plot.x is not None and self.plot.x not in self.axes:
            raise ValueError(f"plot: x must be one of the swept fields ({', '.join(self.axes)}), got {self.plot.x!r}")
        if self.mode == "zip" and len({len(v) for v in self.axes.values()}) > 1:
            raise ValueError(f"mode zip needs lists of equal length, got {[len(v) for v in self.axes.values()]}")
        count = len(next(iter(self.axes.values()))) if self.mode == "zip" else int(np.prod([len(v) for v in self.axes.values()], dtype=float))
        if count > MAX_POINTS:
            raise ValueError(f"the sweep has {count:,} points; at most {MAX_POINTS:,} are allowed (each point is a "
                             f"whole run): split it or use coarser steps")
        return self

    def points(self) -> list[dict[str, Any]]:
        keys = list(self.axes)
        combos = zip(*self.axes.values()) if self.mode == "zip" else itertools.product(*self.axes.values())
        return [dict(zip(keys, c)) for c in combos]


def _set(data: dict, path: str, value: Any) -> None:
    parts = path.split(".")
    cur = data
    for p in parts[:-1]:
        if not isinstance(cur, dict) or p not in cur or not isinstance(cur[p], dict):
            raise KeyError(p)
        cur = cur[p]
    if not isinstance(cur, dict):
        raise KeyError(parts[-1])
    cur[parts[-1]] = value


def expand(scenario, file: str | None, validate) -> list[tuple[dict, Any]]:
    """All sweep points as (coordinates, validated Scenario); every bad point is reported at once.

    ``validate(data, file)`` is the scenario check applied to each point — the loader's own
    (:func:`netkf_cli.config.loader.validate_data`: schema, system, channel × estimator × analysis), passed
    in because the loader sits above this module — so a point gets exactly the checks of a file."""

    base = scenario.model_dump(mode="json", by_alias=True, exclude={"sweep"})
    return _expand(base, scenario.sweep.points(), "sweep", file, validate)


def over_points(over: dict[str, list[Any]]) -> list[dict[str, Any]]:
    """The points of an analysis's ``over:`` grid (several paths: zipped, equal lengths)."""
    keys = list(over)
    return [dict(zip(keys, c)) for c in zip(*over.values())]


def expand_over(scenario, file: str | None, validate) -> list[tuple[dict, Any]]:
    """The points of ``analysis.over`` as (coordinates, validated Scenario), like :func:`expand`.

    Each point is the scenario with the paths set and ``over`` removed, checked exactly as a file."""
    base = scenario.model_dump(mode="json", by_alias=True, exclude={"sweep"})
    base["analysis"].pop("over", None)
    return _expand(base, over_points(scenario.analysis.over), "analysis.over", file, validate)


def _expand(base: dict, points: list[dict], prefix: str, file: str | None, validate) -> list[tuple[dict, Any]]:
    out, problems = [], []
    at: dict[tuple[str, str], list[str]] = {}  # (path, message) → the points it fails at
    what = "sweep point" if prefix == "sweep" else "over point"
    for coords in points:
        data = _deep_copy(base)
        where = ", ".join(f"{k}={v}" for k, v in coords.items())
        bad = False
        for path, v in coords.items():
            try:
                _set(data, path, v)
            except KeyError:
                problems.append(Problem(f"{prefix}.{path}", "is not a field path of this scenario", file))
                bad = True
        if bad:
            continue
        try:  # the same checks as a scenario file (schema, system, channel × estimator × analysis)
            with at_points():
                out.append((coords, validate(data, file)))
        except ConfigError as exc:
            for p in exc.problems:
                at.setdefault((p.path, p.message), []).append(where)
    keys = ", ".join(points[0]) if points else ""
    for (path, message), wheres in at.items():  # one line per problem, naming the points it fails at
        if len(wheres) == len(points) > 1:
            message = f"{message} (at every {what}: {keys}; {len(points)} points)"
        else:
            message = f"{message} ({what}{'s' if len(wheres) > 1 else ''} {'; '.join(wheres)})"
        problems.append(Problem(path, message, file))
    if problems:
        # de-duplicate (a bad path repeats at every point)
        seen, uniq = set(), []
        for p in problems:
            if (p.path, p.message) not in seen:
                seen.add((p.path, p.message))
                uniq.append(p)
        raise ConfigError(uniq)
    return out


_EVERY_POINT = re.compile(r"\(at every (sweep|over) point: (.*); \d+ points\)$")
_SOME_POINTS = re.compile(r"\((sweep|over) points? (.*)\)$")


def point_keys(message: str) -> tuple[str | None, list[str]]:
    """("sweep" | "over", the swept paths) named at the end of a message of :func:`_expand` ("… (sweep point
    a=1, b=2)", "… (over points a=1; a=3)", "… (at every over point: a; 5 points)"); (None, []) otherwise."""
    m = _EVERY_POINT.search(message)
    if m:
        return m[1], [k.strip() for k in m[2].split(", ")]
    m = _SOME_POINTS.search(message)
    if m:
        return m[1], [kv.split("=", 1)[0].strip() for kv in m[2].split("; ")[0].split(", ")]
    return None, []


def _deep_copy(x):
    if isinstance(x, dict):
        return {k: _deep_copy(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_deep_copy(v) for v in x]
    return x


def check_plot(spec: "SweepSpec", table: pd.DataFrame) -> None:
    """``plot.where`` and ``plot.series`` must name what the table holds: checked on the first
    point's table, before the other points run (a filter on a missing column would silently draw
    everything)."""
    cols = list(dict.fromkeys([*spec.axes, *table.columns]))
    problems = [Problem(f"sweep.plot.where.{k}", f"is not a column of the table; columns: {', '.join(map(str, cols))}")
                for k in spec.plot.where if k not in cols]
    if spec.plot.series is not None and "series" in table.columns:
        have = sorted(map(str, table["series"].dropna().unique()))
        if spec.plot.series not in have:
            problems.append(Problem("sweep.plot.series", f"is not a series of the table; series: {', '.join(have)}"))
    if problems:
        raise ConfigError(problems)


TABLE_COLUMNS = ("estimator",)
"""Result-table columns a sweep or over path could be named like (a path is its table column): the whole
``estimator`` block is compared with ``estimators:``, not swept."""


def check_axes(scenario) -> None:
    """The sweep and ``analysis.over`` paths can be table columns: not both the same path (or one inside the
    other: the over value would silently replace the swept one), and not a name the table has already."""
    swept = list(scenario.sweep.axes) if scenario.sweep is not None else []
    over = list(getattr(scenario.analysis, "over", None) or {})
    problems = []
    for block, paths in (("sweep", swept), ("analysis.over", over)):
        for a in paths:
            if a in TABLE_COLUMNS:
                problems.append(Problem(f"{block}.{a}" if block == "sweep" else "analysis.over",
                                        f"{a!r} is a column of the result table already: sweep a field inside it "
                                        f"(e.g. {a}.lag), or list several estimators under `estimators:`"))
    for a in swept:
        for o in over:
            if a == o or a.startswith(o + ".") or o.startswith(a + "."):
                problems.append(Problem(f"sweep.{a}", f"is also set by analysis.over ({o}): the over value would "
                                                      "replace the swept one; give the path in one of the two"))
    if problems:
        raise ConfigError(problems)


def add_coords(df: pd.DataFrame, coords: dict) -> pd.DataFrame:
    df = df.copy()
    for i, (k, v) in enumerate(coords.items()):
        if k in df.columns:  # check_axes refuses the known cases before any work; a metric's own column else
            raise ConfigError.at(k, f"the swept path {k!r} is also a column of this analysis's table "
                                    f"({', '.join(map(str, df.columns))}): sweep another path")
        df.insert(i, k, v)
    return df


def plot(tables, scenario):
    """Default sweep figure: value against the first swept field, one line per value of the second."""
    t = tables["main"]
    spec = scenario.sweep
    axes = list(spec.axes)
    x = spec.plot.x or axes[0]
    others = [a for a in axes if a != x]
    line = others[0] if others else None
    if "series" in t.columns:
        series = spec.plot.series or str(t["series"].iloc[0])
        t = t[t["series"].astype(str) == series]
    else:
        series = "value"
    for col, want in spec.plot.where.items():
        if col in t.columns:
            t = t[np.isclose(t[col].astype(float), float(want))] if isinstance(want, (int, float)) else t[t[col].astype(str) == str(want)]
    fixed = []
    by = [x] + ([line] if line else [])
    for c in [c for c in t.columns if c not in {"value", "stderr", "n", "series"} and c not in axes]:
        # a column that still varies within one (x, line) point is an extra dimension: fix it
        if len(t) and t.groupby(by, dropna=False)[c].nunique(dropna=False).max() > 1:
            first = t[c].iloc[0]
            t = t[t[c] == first] if pd.notna(first) else t[t[c].isna()]
            fixed.append(f"{c} = {first:g}" if isinstance(first, (int, float, np.number)) else f"{c} = {first}")
    fig, ax = new_figure()
    groups = t.groupby(line, sort=True) if line else [(None, t)]
    flagged_total = 0
    for val, g in groups:
        g = g.sort_values(x)
        label = f"{line} = {val}" if line else series
        bad = _unreliable(g)  # heavy-tailed / rare-event dominated / not reliable: hollow, off the line
        flagged_total += int(bad.sum())
        y = g["value"].where(~bad)
        shown = label if np.isfinite(y.to_numpy(dtype=float)).any() else "_nolegend_"  # every mean flagged: no entry
        if "stderr" in g.columns and g["stderr"].notna().any():
            h = ax.errorbar(g[x], y, yerr=g["stderr"].where(~bad), marker="o", ms=3, capsize=2, label=shown)
        else:
            (h,) = ax.plot(g[x], y, marker="o", ms=3, label=shown)
        if bad.any():
            colour = h[0].get_color() if isinstance(h, tuple) or hasattr(h, "lines") else h.get_color()
            ax.plot(g[x][bad], g["value"][bad], ls="none", marker="o", ms=6, mfc="none", color=colour,
                    label=f"{label}: unreliable (flagged in the CSV)")
    if spec.plot.logy:
        ax.set_yscale("log")
    ax.set_xlabel(x)
    ax.set_ylabel(f"value (series {series})")
    where = [f"{k} = {v}" for k, v in spec.plot.where.items()] + fixed
    ax.set_title(f"{scenario.name}: {series}" + (f" ({', '.join(where)})" if where else ""), fontsize=10)
    if line:
        ax.legend(fontsize=MIN_FONT_PT, ncol=2)
    footnote(fig, f"sweep ({spec.mode}) over {', '.join(axes)}; {len(spec.points())} points"
             + (f"; {flagged_total} unreliable point{'s' if flagged_total != 1 else ''} drawn hollow, off the line" if flagged_total else ""))
    return fig


def _unreliable(g: pd.DataFrame) -> np.ndarray:
    """Rows the CSV flags: heavy_tail / rare_event true, or reliable false."""
    def flag(col, bad_when_true=True):
        v = g[col].astype(str).str.lower().isin(["true", "1", "1.0"]).to_numpy()
        return v if bad_when_true else ~v

    bad = np.zeros(len(g), dtype=bool)
    for col in ("heavy_tail", "rare_event"):
        if col in g.columns:
            bad |= flag(col)
    if "reliable" in g.columns:
        bad |= flag("reliable", bad_when_true=False)
    return bad
