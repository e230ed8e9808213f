"""``netkf reproduce``: every paper artefact regenerated, checked against the print, reported.

A topic is a folder of ``configs/`` (top-level configs belong to ``shi2009``) with notes in
``experiments/<topic>/README.md`` and printed numbers in ``experiments/<topic>/published.yaml``::

    checks:
      - id: ex310_theta_7_6          # unique within the topic
        artefact: fig3               # the config's `name`
        csv: fig3                    # file stem in the result folder (default: the artefact name)
        where: {M: 50, D: 6, series: theta_k1}   # column == value filters selecting ONE row
        column: value                # default: value
        quantity: "θ(7, 6) at M = 50"
        printed: 0.0313
        tol_abs: 5.0e-5              # or tol_rel
        expect: reproduce            # or: differs (then `reason` is required)
        reason: ""

Adding a paper means adding configs and these two files; no code here changes.
Under ``--quick`` each Monte Carlo uses ``montecarlo.quick_size()`` runs and every tolerance
is widened to at least 5 standard errors of the row it reads (its ``stderr`` column).
"""

from __future__ import annotations

import math
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd
import yaml
from pydantic import Field, ValidationError, model_validator

from netkf_cli.errors import ConfigError, Problem
from netkf_cli.spec import StrictModel

TOP_LEVEL_TOPIC = "shi2009"
STAT_COLUMNS = {"value", "stderr", "n", "n_runs", "runs", "ci_low", "ci_high", "p_value", "reliable", "wall_time_s"}
SIGMAS = 5.0


class Check(StrictModel):
    id: str
    artefact: str
    csv: str | None = None
    where: dict[str, Any] = Field(default_factory=dict)
    column: str = "value"
    quantity: str = ""
    printed: float
    tol_abs: float | None = Field(None, ge=0)
    tol_rel: float | None = Field(None, ge=0)
    expect: Literal["reproduce", "differs"] = "reproduce"
    reason: str = ""
    source: str = ""

    @model_validator(mode="after")
    def _tolerance_and_reason(self):
        if self.tol_abs is None and self.tol_rel is None:
            raise ValueError("give tol_abs or tol_rel")
        if self.expect == "differs" and not self.reason.strip():
            raise ValueError("expect: differs needs a `reason`")
        return self


class Published(StrictModel):
    citation: str = ""
    checks: list[Check] = Field(default_factory=list)


@dataclass
class Artefact:
    topic: str
    name: str
    config: Path


@dataclass
class CheckResult:
    check: Check
    ours: float | None
    stderr: float | None
    tol: float
    ok: bool
    note: str = ""

    @property
    def diff(self) -> float | None:
        return None if self.ours is None else self.ours - self.check.printed

    @property
    def failed(self) -> bool:
        return self.check.expect == "reproduce" and not self.ok

    def verdict(self) -> str:
        if self.ours is None:
            return f"✗ {self.note}"
        if self.check.expect == "differs":
            return ("≈ agrees (expected to differ)" if self.ok else "differs, as expected") + f": {self.check.reason}"
        return "✓ reproduces" if self.ok else "✗ does not reproduce"


@dataclass
class ArtefactOutcome:
    artefact: Artefact
    folder: Path | None
    wall_time: float
    error: str | None = None
    checks: list[CheckResult] = field(default_factory=list)
    golden: list[str] = field(default_factory=list)  # golden mismatches
    golden_checked: bool = False

    @property
    def failed(self) -> bool:
        return self.error is not None or any(c.failed for c in self.checks) or bool(self.golden)


def topic_of(config: Path, configs_root: Path) -> str:
    rel = config.relative_to(configs_root)
    return rel.parts[0] if len(rel.parts) > 1 else TOP_LEVEL_TOPIC


def discover(root: Path, topics: list[str]) -> tuple[list[Artefact], dict[str, Published]]:
    """Every config (by topic) and every published.yaml; inconsistencies are errors."""
    from netkf_cli.loader import load_scenario

    configs_root = root / "configs"
    if not configs_root.is_dir():
        raise ConfigError([Problem("", "no configs/ folder here: run netkf reproduce from the project's root", str(root))])
    arts: list[Artefact] = []
    problems: list[Problem] = []
    for cfg in sorted(configs_root.rglob("*.yaml")):
        try:
            sc = load_scenario(cfg)
        except ConfigError as exc:
            problems.extend(exc.problems)
            continue
        arts.append(Artefact(topic_of(cfg, configs_root), sc.name, cfg))
    names: dict[str, Path] = {}
    for a in arts:
        if a.name in names:
            problems.append(Problem("name", f"artefact name {a.name!r} is also used by {names[a.name]}", str(a.config)))
        names[a.name] = a.config
    all_topics = sorted({a.topic for a in arts})
    exp_root = root / "experiments"
    exp_topics = sorted(p.name for p in exp_root.iterdir() if p.is_dir()) if exp_root.is_dir() else []
    for t in all_topics:
        if not (exp_root / t / "README.md").exists():
            problems.append(Problem("", f"topic {t!r} has configs but no experiments/{t}/README.md (its report section)", str(exp_root / t)))
    for t in exp_topics:
        if t not in all_topics:
            problems.append(Problem("", f"experiments/{t}/ has no configs (a report section without a config)", str(exp_root / t)))
    unknown = [t for t in topics if t not in all_topics]
    if unknown:
        raise ConfigError.at("TOPIC", f"unknown topic(s) {unknown}; available: {all_topics}")
    published: dict[str, Published] = {}
    for t in all_topics:
        f = exp_root / t / "published.yaml"
        if not f.exists():
            published[t] = Published()
            continue
        try:
            published[t] = Published.model_validate(yaml.safe_load(f.read_text(encoding="utf-8")) or {})
        except ValidationError as exc:
            from netkf_cli.loader import line_index, validation_problems

            text = f.read_text(encoding="utf-8")
            problems.extend(validation_problems(exc, yaml.safe_load(text), line_index(text), str(f)))
            continue
        ids = set()
        for i, c in enumerate(published[t].checks):
            if c.id in ids:
                problems.append(Problem(f"checks[{i}].id", f"duplicate id {c.id!r}", str(f)))
            ids.add(c.id)
            if c.artefact not in names or topic_of(names[c.artefact], configs_root) != t:
                problems.append(Problem(f"checks[{i}].artefact", f"no config of topic {t!r} is named {c.artefact!r}", str(f)))
    if problems:
        raise ConfigError(problems)
    return arts, published


def _select(df: pd.DataFrame, where: dict[str, Any]) -> pd.DataFrame:
    mask = np.ones(len(df), dtype=bool)
    for col, want in where.items():
        if col not in df.columns:
            raise KeyError(f"column {col!r} not in CSV (columns: {list(df.columns)})")
        s = df[col]
        if isinstance(want, (int, float)) and not isinstance(want, bool) and pd.api.types.is_numeric_dtype(s):
            mask &= np.isclose(s.to_numpy(dtype=float), float(want), rtol=1e-9, atol=1e-12)
        else:
            mask &= s.astype(str).to_numpy() == str(want)
    return df[mask]


def evaluate(check: Check, folder: Path, quick: bool) -> CheckResult:
    path = folder / f"{check.csv or check.artefact}.csv"
    tol = check.tol_abs if check.tol_abs is not None else check.tol_rel * abs(check.printed)
    if not path.exists():
        return CheckResult(check, None, None, tol, False, f"{path.name} not written")
    df = pd.read_csv(path)
    try:
        rows = _select(df, check.where)
    except KeyError as exc:
        return CheckResult(check, None, None, tol, False, str(exc).strip('"'))
    if len(rows) != 1:
        return CheckResult(check, None, None, tol, False, f"`where` {check.where} selects {len(rows)} rows of {path.name}, expected 1")
    row = rows.iloc[0]
    ours = float(row[check.column])
    se = float(row["stderr"]) if "stderr" in row.index and pd.notna(row["stderr"]) else None
    if quick and se is not None:
        tol = max(tol, SIGMAS * se)
    ok = bool(np.isfinite(ours) and abs(ours - check.printed) <= tol * (1 + 1e-12))
    return CheckResult(check, ours, se, tol, ok)


DIAGNOSTIC_COLUMNS = STAT_COLUMNS | {
    "ess_frac", "finite_variance", "overflowed", "statistic", "statistic_stderr", "printed",
    "threshold_low", "threshold_high", "err",
}


def compare_golden(fresh: Path, golden: Path, name: str) -> list[str]:
    """The fresh (quick) main table ``<name>.csv`` against the committed full-size one.

    Rows are aligned by position (a table's layout depends on the scenario only) and must agree
    on every descriptive column. Then, per row:

    * Monte Carlo (finite ``stderr``): |Δ| ≤ 5·√(se_g² + se_q²), where the quick run's standard
      error is at least the golden's scaled by √(n_golden / n_quick) (an empirical proportion of
      0 or 1 in a small run reports se = 0);
    * closed form (no ``stderr`` and no ``n``): |Δ| ≤ 1e-6 relative;
    * run-dependent diagnostics (no ``stderr`` but a sample size ``n``; ``reliable = 0``; or a
      grid that itself comes from the sample, e.g. an ECDF's x) are not compared.
    Returns one line per mismatch naming the artefact, the row and the deviation.
    """
    out: list[str] = []
    g, f = golden / f"{name}.csv", fresh / f"{name}.csv"
    if not g.exists():
        return out
    if not f.exists():
        return [f"{name}: {g.name} is committed but the fresh run did not write it"]
    a, b = pd.read_csv(f), pd.read_csv(g)
    if "value" not in b.columns:
        return out
    if list(a.columns) != list(b.columns):
        return [f"{name}: {g.name} columns changed: {list(b.columns)} → {list(a.columns)}"]
    if len(a) != len(b):
        return [f"{name}: {g.name} has {len(a)} rows, the golden has {len(b)}"]
    desc = [c for c in b.columns if c not in DIAGNOSTIC_COLUMNS]
    text = [c for c in desc if not pd.api.types.is_numeric_dtype(b[c])]
    num = [c for c in desc if c not in text]
    for c in text:
        bad = a[c].astype(str).to_numpy() != b[c].astype(str).to_numpy()
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            return [f"{name}: {g.name} row {i}: {c} is {a[c].iloc[i]!r}, golden {b[c].iloc[i]!r} (layout changed)"]
    same_grid = np.ones(len(b), dtype=bool)
    for c in num:
        x, y = a[c].to_numpy(float), b[c].to_numpy(float)
        same_grid &= np.isclose(x, y, rtol=1e-9, atol=1e-12, equal_nan=True)
    vg, vf = b["value"].to_numpy(float), a["value"].to_numpy(float)
    sg = b["stderr"].to_numpy(float) if "stderr" in b.columns else np.full(len(b), np.nan)
    sf = a["stderr"].to_numpy(float) if "stderr" in a.columns else np.full(len(a), np.nan)
    ng = b["n"].to_numpy(float) if "n" in b.columns else np.full(len(b), np.nan)
    nf = a["n"].to_numpy(float) if "n" in a.columns else np.full(len(a), np.nan)
    mc = np.isfinite(sg) | np.isfinite(sf)
    with np.errstate(invalid="ignore", divide="ignore"):
        scaled = np.where(np.isfinite(ng) & np.isfinite(nf) & (nf > 0), np.nan_to_num(sg) * np.sqrt(ng / nf), 0.0)
    sf_eff = np.maximum(np.nan_to_num(sf), np.nan_to_num(scaled))
    tol = np.where(mc, SIGMAS * np.sqrt(np.nan_to_num(sg) ** 2 + sf_eff**2) + 1e-12,
                   1e-6 * np.maximum(np.abs(vg), 1e-12))
    compare = same_grid & (mc | ~np.isfinite(ng))
    if "reliable" in b.columns:
        compare &= (b["reliable"].to_numpy(float) != 0) & (a["reliable"].to_numpy(float) != 0)
    with np.errstate(invalid="ignore"):
        agree = (np.isnan(vg) & np.isnan(vf)) | (np.isinf(vg) & (vg == vf)) | (np.abs(vf - vg) <= tol)
    bad = compare & ~agree
    for i in np.flatnonzero(bad)[:5]:
        where = ", ".join(f"{k}={b[k].iloc[i]}" for k in desc if pd.notna(b[k].iloc[i]))
        dev = abs(vf[i] - vg[i])
        kind = f"{dev / (tol[i] / SIGMAS):.1f} σ" if mc[i] else f"rel {dev / max(abs(vg[i]), 1e-300):.2e}"
        out.append(f"{name}: {g.name} [{where}] value {vf[i]:.6g} vs golden {vg[i]:.6g} ({kind})")
    if bad.sum() > 5:
        out.append(f"{name}: {g.name}: {int(bad.sum()) - 5} more rows differ")
    return out


def _run_one(args) -> tuple[str, str | None, float, str | None]:
    """Worker: run one config into its folder; returns (name, folder, wall time, error)."""
    config, folder, quick = args
    from netkf_cli.errors import NetkfError
    from netkf_cli.loader import load_scenario
    from netkf_cli.runner import run_scenario

    t0 = time.perf_counter()
    try:
        sc = load_scenario(config)
        runs = sc.montecarlo.quick_size() if quick else None
        run_scenario(sc, source=config, out_dir=folder, runs=runs, quick=quick, force=True)
        return sc.name, str(folder), time.perf_counter() - t0, None
    except NetkfError as exc:
        return Path(config).stem, None, time.perf_counter() - t0, str(exc)


def run_all(arts: list[Artefact], out_root: Path, quick: bool, jobs: int, on_done=None) -> dict[str, tuple]:
    tasks = [(str(a.config), str(out_root / a.name), quick) for a in arts]
    results: dict[str, tuple] = {}
    if jobs <= 1:
        for a, t in zip(arts, tasks):
            results[a.name] = _run_one(t)
            if on_done:
                on_done(a, results[a.name])
    else:
        with ProcessPoolExecutor(max_workers=jobs) as ex:
            for a, r in zip(arts, ex.map(_run_one, tasks)):
                results[a.name] = r
                if on_done:
                    on_done(a, r)
    return results


def reproduce(topics: list[str], *, quick: bool, out_root: Path | None, check: bool, jobs: int, write_report: bool,
              console, quiet: bool = False, root: Path | None = None) -> bool:
    """Run, check, summarize and (optionally) write the report. Returns True when nothing failed."""
    root = Path(root or Path.cwd())
    golden_root = root / "results"
    if out_root is None:
        out_root = root / ("build/quick-results" if quick else "results")
    out_root = Path(out_root)
    if quick and out_root.resolve() == golden_root.resolve():
        raise ConfigError.at("--out", "a --quick run must not overwrite the committed full-size results/; choose another --out")
    all_arts, published = discover(root, topics)
    arts = [a for a in all_arts if not topics or a.topic in topics]
    if not quiet:
        console.print(f"reproducing {len(arts)} artefacts ({'quick' if quick else 'full size'}) into {out_root}/ with {jobs} job(s)")

    def done(a, r):
        if not quiet:
            mark = "✓" if r[3] is None else "✗"
            console.print(f"  {mark} {a.topic}/{a.name}  {r[2]:.1f} s" + (f"  — {r[3]}" if r[3] else ""), highlight=False, markup=False)

    raw = run_all(arts, out_root, quick, jobs, done)
    outcomes = []
    for a in arts:
        name, folder, wall, error = raw[a.name]
        o = ArtefactOutcome(a, Path(folder) if folder else None, wall, error)
        if folder:
            for c in published[a.topic].checks:
                if c.artefact == a.name:
                    o.checks.append(evaluate(c, Path(folder), quick))
            g = golden_root / a.name
            if check and quick and g.is_dir():
                o.golden = compare_golden(Path(folder), g, a.name)
                o.golden_checked = True
        outcomes.append(o)
    summarize(outcomes, console, quick)
    # the report covers every artefact: those not run now are read from their existing folders
    ran = {o.artefact.name for o in outcomes}
    report_outcomes = []
    for a in all_arts:
        if a.name in ran:
            report_outcomes.append(next(o for o in outcomes if o.artefact.name == a.name))
            continue
        folder = out_root / a.name
        if not (folder / "manifest.json").exists():
            report_outcomes.append(ArtefactOutcome(a, None, 0.0, "not run yet: netkf reproduce " + a.topic))
            continue
        import json

        wall = json.loads((folder / "manifest.json").read_text()).get("wall_time_s", 0.0)
        o = ArtefactOutcome(a, folder, wall)
        o.checks = [evaluate(c, folder, quick) for c in published[a.topic].checks if c.artefact == a.name]
        report_outcomes.append(o)
    if write_report:
        from netkf_cli.report import write_report as _write

        path = _write(report_outcomes, published, out_root / "REPORT.md", root=root, quick=quick)
        if not quiet:
            console.print(f"report: {path}")
    failed = [o for o in outcomes if o.failed]
    if failed and (check or not quiet):
        console.print("[bold red]failed:[/]")
        for o in failed:
            if o.error:
                console.print(f"  {o.artefact.name}: run failed: {o.error}", markup=False, highlight=False)
            for c in o.checks:
                if c.failed:
                    d = "n/a" if c.ours is None else f"ours {c.ours:.6g} vs printed {c.check.printed:.6g} (|Δ| {abs(c.diff):.3g} > tol {c.tol:.3g})"
                    console.print(f"  {o.artefact.name}: check {c.check.id} ({c.check.quantity or c.check.where}): {c.note or d}", markup=False, highlight=False)
            for gm in o.golden:
                console.print(f"  golden: {gm}", markup=False, highlight=False)
    return not failed


def summarize(outcomes: list[ArtefactOutcome], console, quick: bool) -> None:
    from rich.table import Table

    t = Table(title=f"netkf reproduce ({'quick' if quick else 'full size'})")
    for col in ("artefact", "checks passed", "failed", "largest deviation", "golden", "wall time"):
        t.add_column(col)
    for o in outcomes:
        n_ok = sum(1 for c in o.checks if c.ok or c.check.expect == "differs")
        n_bad = sum(1 for c in o.checks if c.failed)
        worst = None  # the check closest to (or furthest past) its tolerance
        for c in o.checks:
            if c.ours is None or c.check.expect == "differs":
                continue
            ratio = abs(c.diff) / c.tol if c.tol > 0 else (0.0 if c.diff == 0 else math.inf)
            if worst is None or ratio > worst[0]:
                worst = (ratio, c)
        if worst is None:
            wtxt = "—"
        else:
            c = worst[1]
            rel = abs(c.diff) / abs(c.check.printed) if c.check.printed else abs(c.diff)
            wtxt = f"{100 * rel:.2g} % rel" + (f" ({abs(c.diff) / c.stderr:.1f} σ)" if c.stderr else "")
        gold = "run failed" if o.error else (f"{len(o.golden)} moved" if o.golden else ("ok" if o.golden_checked else "—"))
        t.add_row(f"{o.artefact.topic}/{o.artefact.name}", str(n_ok), str(n_bad), wtxt, gold, f"{o.wall_time:.1f} s")
    console.print(t)
