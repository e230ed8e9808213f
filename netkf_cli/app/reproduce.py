"""``netkf reproduce``: every paper artefact regenerated, checked against the paper, reported.

A topic is a folder of ``configs/`` (top-level configs belong to ``shi2009``) with notes in
``experiments/<topic>/README.md`` and, in ``experiments/<topic>/published.yaml``, what the
paper says, in two kinds of entries, plus how the topic's golden CSVs are compared::

    citation: "L. Shi, L. Xie, R. M. Murray, … Automatica 45 (2009) 2134–2140"
    printed:                         # numbers that appear in the paper, where they appear
      - id: ex310_theta_7_6          # unique within the topic
        artefact: fig3               # the config's `name`
        csv: fig3                    # file stem in the result folder (default: the artefact name)
        select: {M: 50, D: 6, series: theta_k1}   # column == value filters selecting ONE row
        column: value                # default: value
        quantity: "θ(7, 6) at M = 50"
        where: "Example 3.10 (Sec. 3.4)"          # page / figure / table / equation / section
        printed: 0.0313
        tol_abs: 5.0e-5              # or tol_rel (printed to 4 decimals: half a unit of the last digit)
        interval: [threshold_low, threshold_high] # optional: an argmin's near-optimal interval
        expect: reproduce            # or: differs (then `reason` is required)
    claims:                          # what the paper claims in words, and the number that decides it
      - id: fig5_mc_between_bounds
        artefact: fig5
        csv: fig5_summary
        select: {quantity: mc_within_bounds_5se_fraction}
        claim: "Pr[P_k ≤ M] lies between the bounds of Thm 3.8"
        where: "Fig. 5, Thm 3.8"
        check: "fraction of the M grid where lower − 5σ ≤ Monte Carlo ≤ upper + 5σ"
        holds_if: {min: 1.0}         # and/or max
        expect: holds                # or: fails (then `reason` is required)
    golden:                          # per CSV stem: netkf_cli.app.golden rules (closed / mc / optimizer …)
      fading_fig5_optima:
        - {columns: [threshold], kind: optimizer, rtol: 1.0e-6, why: "…"}

Adding a paper means adding configs and these two files; no code here changes. Under
``--quick`` each Monte Carlo uses ``montecarlo.quick_size()`` runs and every tolerance (and every
claim's threshold) is widened by 5 standard errors of the row it reads (its ``stderr`` column).
"""

from __future__ import annotations

import functools
import gc
import json
import math
import subprocess
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from netkf_cli.core import lazy
from netkf_cli.core.lazy import pandas as pd
from pydantic import Field, ValidationError, model_validator
from rich.table import Table

from netkf_cli.app import golden as golden_mod
from netkf_cli.linalg import kalman
from netkf_cli.runtime import io, montecarlo, plotting
from netkf_cli.core.errors import ConfigError, NetkfError, Problem
from netkf_cli.config.compat import safe_load
from netkf_cli.config.loader import line_index, load_scenario, validation_problems
from netkf_cli.app.report import write_report as _write
from netkf_cli.app.runner import run_scenario
from netkf_cli.metrics.common import deferred_reference_checks
from netkf_cli.core.spec import StrictModel
from netkf_cli.runtime.workers import pool_kwargs  # pool workers ignore Ctrl-C and die with this process
from netkf_cli.core.tolerances import MC_SIGMAS

TOP_LEVEL_TOPIC = "shi2009"


class _Entry(StrictModel):
    id: str = Field(..., description="unique within the topic")
    artefact: str = Field(..., description="the config's `name`")
    csv: str | None = Field(None, description="CSV stem in the result folder (default: the artefact name)")
    select: dict[str, Any] = Field(default_factory=dict, description="column == value filters selecting ONE row")
    column: str = Field("value", description="the column holding our number")
    where: str = Field(..., min_length=1, description="where in the paper: page, figure, table, equation or section")
    reason: str = Field("", description="why we differ, or how the paper's words were read")


class Printed(_Entry):
    """A number that appears in the paper."""

    quantity: str = Field(..., min_length=1, description="what the number is, with the paper's symbols")
    printed: float = Field(..., description="the value as printed (linear units)")
    printed_text: str = Field("", description="as typeset, when it is not a plain number (e.g. '12 + ε, −1 < ε < 1')")
    tol_abs: float | None = Field(None, ge=0, description="absolute tolerance (e.g. half a unit of the last printed digit)")
    tol_rel: float | None = Field(None, ge=0, description="relative tolerance")
    interval: list[str] | None = Field(None, min_length=2, max_length=2,
                                       description="columns [low, high] of our near-optimal interval (argmins of flat objectives)")
    expect: Literal["reproduce", "differs"] = Field("reproduce", description="reproduce, or differs (with a reason)")

    @model_validator(mode="after")
    def _tolerance_and_reason(self):
        if self.tol_abs is None and self.tol_rel is None:
            raise ValueError("give tol_abs or tol_rel")
        if self.expect == "differs" and not self.reason.strip():
            raise ValueError("expect: differs needs a `reason`")
        return self


class Bounds(StrictModel):
    min: float | None = Field(None, description="the claim holds when our number is ≥ min")
    max: float | None = Field(None, description="the claim holds when our number is ≤ max")

    @model_validator(mode="after")
    def _one(self):
        if self.min is None and self.max is None:
            raise ValueError("give min and/or max")
        return self

    def text(self, column: str) -> str:
        if self.min is not None and self.max is not None:
            return f"{_fmt(self.min)} ≤ {column} ≤ {_fmt(self.max)}"
        return f"{column} ≥ {_fmt(self.min)}" if self.min is not None else f"{column} ≤ {_fmt(self.max)}"


class Claim(_Entry):
    """A claim of the paper in words, and the number of ours that decides it."""

    claim: str = Field(..., min_length=1, description="the paper's claim, in words")
    check: str = Field(..., min_length=1, description="how our CSV decides it, in words")
    holds_if: Bounds = Field(..., description="the claim holds when our number lies within these bounds")
    expect: Literal["holds", "fails"] = Field("holds", description="holds, or fails (with a reason)")
    evidence: list[str] = Field(default_factory=list, description="columns of the same row (or of evidence_csv) shown as evidence")
    evidence_csv: str | None = Field(None, description="CSV stem holding the evidence columns (same `select`)")
    every_row: bool = Field(False, description="`select` may match several rows; the claim must hold on each")

    @model_validator(mode="after")
    def _reason(self):
        if self.expect == "fails" and not self.reason.strip():
            raise ValueError("expect: fails needs a `reason`")
        return self


class Published(StrictModel):
    citation: str = Field("", description="the paper, as cited")
    printed: list[Printed] = Field(default_factory=list, description="numbers that appear in the paper")
    claims: list[Claim] = Field(default_factory=list, description="claims in words, decided by our numbers")
    golden: dict[str, list[golden_mod.GoldenRule]] = Field(default_factory=dict,
                                                           description="per CSV stem: how golden CSVs are compared")


def _fmt(x) -> str:
    if x is None:
        return "—"
    x = float(x)
    if x == 0:
        return "0"
    if not math.isfinite(x):
        return str(x)
    a = abs(x)
    return f"{x:.4g}" if 1e-3 <= a < 1e5 else f"{x:.3e}"


@dataclass
class Artefact:
    topic: str
    name: str
    config: Path
    scenario: Any = field(default=None, repr=False, compare=False)  # as :func:`discover` validated it


#: config path → the scenario :func:`discover` loaded, for :func:`_run_one` while :func:`run_all` runs (a forked
#: pool worker inherits it): each scenario is parsed and validated once per reproduction, not once more to run it
_SCENARIOS: dict[str, Any] = {}


@dataclass
class CheckResult:
    """A printed number against ours."""

    check: Printed
    ours: float | None
    stderr: float | None
    tol: float
    ok: bool
    note: str = ""
    interval: tuple[float, float] | None = None

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
            return "≈ agrees (expected to differ)" if self.ok else "differs, as expected"
        return "✓ reproduces" if self.ok else "✗ does not reproduce"


@dataclass
class ClaimResult:
    """A claim of the paper, decided by one number of ours."""

    claim: Claim
    ours: float | None
    stderr: float | None
    holds: bool | None
    evidence: dict[str, Any] = field(default_factory=dict)
    note: str = ""
    n_rows: int = 1

    @property
    def ok(self) -> bool:
        return self.holds is not None and self.holds == (self.claim.expect == "holds")

    @property
    def failed(self) -> bool:
        return self.claim.expect == "holds" and not self.holds

    def verdict(self) -> str:
        if self.holds is None:
            return f"✗ {self.note}"
        if self.claim.expect == "fails":
            return "holds (expected not to)" if self.holds else "does not hold, as expected"
        return "✓ holds" if self.holds else "✗ does not hold"


@dataclass
class ArtefactOutcome:
    artefact: Artefact
    folder: Path | None
    wall_time: float
    error: str | None = None
    checks: list[CheckResult] = field(default_factory=list)
    claims: list[ClaimResult] = field(default_factory=list)
    golden: list[str] = field(default_factory=list)  # golden mismatches
    golden_checked: bool = False
    previous: str | None = None  # not run by this command: when its result was made (its manifest's `created`)

    @property
    def failed(self) -> bool:
        return (self.error is not None or any(c.failed for c in self.checks) or any(c.failed for c in self.claims)
                or bool(self.golden))


def topic_of(config: Path, configs_root: Path) -> str:
    rel = config.relative_to(configs_root)
    return rel.parts[0] if len(rel.parts) > 1 else TOP_LEVEL_TOPIC


def discover(root: Path, topics: list[str]) -> tuple[list[Artefact], dict[str, Published]]:
    """Every config (by topic) and every published.yaml; inconsistencies are errors."""
    configs_root = root / "configs"
    if not configs_root.is_dir():
        raise ConfigError([Problem("", "no configs/ folder here: run netkf reproduce from the project's root", str(root))])
    arts: list[Artefact] = []
    problems: list[Problem] = []
    for cfg in sorted(configs_root.rglob("*.yaml")):
        try:
            with deferred_reference_checks():  # each artefact's run checks them before its Monte Carlo
                sc = load_scenario(cfg)
        except ConfigError as exc:
            problems.extend(exc.problems)
            continue
        arts.append(Artefact(topic_of(cfg, configs_root), sc.name, cfg, sc))
    names: dict[str, Path] = {}
    for a in arts:
        if a.name in names:
            problems.append(Problem("name", f"artefact name {a.name!r} is also used by {names[a.name]}", str(a.config)))
        names[a.name] = a.config
    all_topics = sorted({a.topic for a in arts})
    exp_root = root / "experiments"
    # a folder of worked-example scenarios without published.yaml (experiments/engine: the generic metrics,
    # not a paper) is not a report section; any other folder is, and must have configs
    def _section(p: Path) -> bool:
        return p.is_dir() and ((p / "published.yaml").exists() or not any(p.glob("*.yaml")))

    exp_topics = sorted(p.name for p in exp_root.iterdir() if _section(p)) if exp_root.is_dir() else []
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
            published[t] = Published.model_validate(safe_load(f.read_text(encoding="utf-8")) or {})
        except ValidationError as exc:
            text = f.read_text(encoding="utf-8")
            problems.extend(validation_problems(exc, safe_load(text), line_index(text), str(f)))
            continue
        ids = set()
        for key, entries in (("printed", published[t].printed), ("claims", published[t].claims)):
            for i, c in enumerate(entries):
                if c.id in ids:
                    problems.append(Problem(f"{key}[{i}].id", f"duplicate id {c.id!r}", str(f)))
                ids.add(c.id)
                if c.artefact not in names or topic_of(names[c.artefact], configs_root) != t:
                    problems.append(Problem(f"{key}[{i}].artefact", f"no config of topic {t!r} is named {c.artefact!r}", str(f)))
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


@functools.lru_cache(maxsize=8)
def _read_table(path: str, mtime_ns: int, size: int) -> pd.DataFrame:
    """A result CSV, read once for all the checks and claims on it (keyed by its path, mtime and size: a file
    written again is read again). Callers select from it and never modify it."""
    return pd.read_csv(path)


def _rows(entry: _Entry, folder: Path, many: bool = False) -> tuple[pd.DataFrame | None, str]:
    """The CSV row(s) an entry reads (exactly one unless ``many``), or (None, why not)."""
    path = folder / f"{entry.csv or entry.artefact}.csv"
    if not path.exists():
        return None, f"{path.name} not written"
    st = path.stat()
    df = _read_table(str(path), st.st_mtime_ns, st.st_size)
    try:
        rows = _select(df, entry.select)
    except KeyError as exc:
        return None, str(exc).strip('"')
    if len(rows) == 0 or (len(rows) != 1 and not many):
        return None, f"`select` {entry.select} selects {len(rows)} rows of {path.name}, expected {'≥ 1' if many else 1}"
    if entry.column not in rows.columns:
        return None, f"column {entry.column!r} not in {path.name}"
    return rows, ""


def _row(entry: _Entry, folder: Path) -> tuple[pd.Series | None, str]:
    """The one CSV row an entry reads, or (None, why not)."""
    rows, note = _rows(entry, folder)
    return (None, note) if rows is None else (rows.iloc[0], "")


def _stderr(row: pd.Series) -> float | None:
    se = row.get("stderr") if "stderr" in row.index else None
    try:
        se = float(se) if se is not None and pd.notna(se) else None
    except (TypeError, ValueError):
        se = None
    return se if se is not None and se > 0 else None


def evaluate(check: Printed, folder: Path, quick: bool) -> CheckResult:
    """A printed number against our CSV cell (for an argmin: against our near-optimal interval)."""
    tol = check.tol_abs if check.tol_abs is not None else check.tol_rel * abs(check.printed)
    row, note = _row(check, folder)
    if row is None:
        return CheckResult(check, None, None, tol, False, note)
    ours = float(row[check.column])
    se = _stderr(row)
    if quick and se is not None:
        tol = max(tol, MC_SIGMAS * se)
    ok = bool(np.isfinite(ours) and abs(ours - check.printed) <= tol * (1 + 1e-12))
    interval = None
    if check.interval:
        try:
            lo, hi = (float(row[c]) for c in check.interval)
        except (KeyError, TypeError, ValueError):
            return CheckResult(check, ours, se, tol, False, f"interval columns {check.interval} not in the row")
        interval = (lo, hi)
        # the printed argmin is consistent with ours when [printed ± tol] meets the near-optimal set
        ok = bool(np.isfinite(lo) and np.isfinite(hi) and check.printed + tol >= lo and check.printed - tol <= hi)
    return CheckResult(check, ours, se, tol, ok, interval=interval)


def evaluate_claim(claim: Claim, folder: Path, quick: bool) -> ClaimResult:
    """Does the claim hold in our numbers (on every selected row when ``every_row``)? Under
    --quick the bounds widen by 5 s.e. of the row. ``ours`` is the row furthest from holding."""
    rows, note = _rows(claim, folder, many=claim.every_row)
    if rows is None:
        return ClaimResult(claim, None, None, None, note=note)
    b = claim.holds_if
    results = []
    for _, row in rows.iterrows():
        ours = float(row[claim.column])
        se = _stderr(row)
        slack = MC_SIGMAS * se if (quick and se is not None) else 0.0
        lo_ok = b.min is None or ours >= b.min - slack - 1e-12 * max(1.0, abs(b.min))
        hi_ok = b.max is None or ours <= b.max + slack + 1e-12 * max(1.0, abs(b.max))
        # ±∞ is a value (a diverged E[P] is +∞): it holds against a one-sided bound it satisfies; NaN never
        valid = bool(np.isfinite(ours) or (ours == math.inf and b.max is None) or (ours == -math.inf and b.min is None))
        with np.errstate(invalid="ignore"):
            margin = min(ours - b.min if b.min is not None else math.inf, b.max - ours if b.max is not None else math.inf)
        results.append((valid and lo_ok and hi_ok, margin if valid else -math.inf, ours, se, row))
    holds = all(r[0] for r in results)
    worst = min(results, key=lambda r: r[1])
    _, _, ours, se, row = worst
    evidence = {c: row[c] for c in claim.evidence if c in row.index}
    if claim.evidence_csv:
        ev_row, _ = _row(claim.model_copy(update={"csv": claim.evidence_csv, "column": claim.evidence[0] if claim.evidence else "value",
                                                  "select": {**claim.select, **({k: row[k] for k in claim.select if k in row.index})}}), folder)
        if ev_row is not None:
            evidence = {c: ev_row[c] for c in claim.evidence if c in ev_row.index}
    res = ClaimResult(claim, ours, se, holds, evidence)
    res.n_rows = len(results)
    return res


def compare_golden(fresh: Path, golden: Path, name: str, rules=None) -> list[str]:
    """The fresh (quick) main table ``<name>.csv`` against the committed full-size one
    (:mod:`netkf_cli.app.golden`, ``quick=True``); one line per mismatch naming the artefact, the
    row and the deviation. A committed result folder without its main CSV is a mismatch."""
    res = golden_mod.compare_files(fresh / f"{name}.csv", golden / f"{name}.csv", rules or (), quick=True)
    return [f"{name}: {p}" for p in res.problems]


def _run_one(args) -> tuple[str, str | None, float, str | None]:
    """Worker: run one config into its folder; returns (name, folder, wall time, error)."""
    config, folder, quick = args

    t0 = time.perf_counter()
    try:
        sc = _SCENARIOS.get(config)
        if sc is None:  # not discovered in this process (a spawned worker, or a direct call)
            sc = load_scenario(config)
        runs = sc.montecarlo.quick_size() if quick else None
        with kalman.eager_compile():  # numba is paid here anyway: small batches compiled too
            run_scenario(sc, source=config, out_dir=folder, runs=runs, quick=quick, force=True, resumable=False)
        return sc.name, str(folder), time.perf_counter() - t0, None
    except NetkfError as exc:
        return Path(config).stem, None, time.perf_counter() - t0, str(exc)
    finally:
        _freeze_survivors()


def _freeze_survivors() -> None:
    """After an artefact: collect its garbage, then freeze what survives (the per-process caches it filled: kernels,
    mathtext parses, glyphs, layouts), so that the automatic full collections of the next artefacts stop
    re-traversing them. The full reproduction in one process: GC 1.8 -> 1.0 s CPU (17 full collections 1.3 s -> 44
    of 0.5 s), peak RSS 492 -> 477 MB. run_all unfreezes at its end (workers end with the pool)."""
    gc.collect()
    gc.freeze()


def _expected_wall(a: Artefact, out_root: Path, golden_root: Path | None) -> float:
    """How long an artefact took last time: its manifest in ``out_root`` (the previous run of this
    mode), else the committed full-size one; 0 when neither exists."""
    for folder in (out_root / a.name, golden_root / a.name if golden_root else None):
        if folder is None:
            continue
        try:
            return float(json.loads((folder / "manifest.json").read_text(encoding="utf-8")).get("wall_time_s", 0.0))
        except (OSError, ValueError, TypeError, AttributeError):
            continue
    return 0.0


def run_all(arts: list[Artefact], out_root: Path, quick: bool, jobs: int, on_done=None,
            golden_root: Path | None = None) -> dict[str, tuple]:
    """Run every artefact; with ``jobs`` > 1 on a process pool, longest first (the previous wall
    times: the makespan is then at most the longest artefact or 4/3 of the even share)."""
    tasks = {a.name: (str(a.config), str(out_root / a.name), quick) for a in arts}
    _SCENARIOS.update({str(a.config): a.scenario for a in arts if a.scenario is not None})
    results: dict[str, tuple] = {}
    if jobs > 1:
        montecarlo.warm_compiler()  # numba's LLVM and typing set up once here: the forked workers inherit it
        plotting.setup()  # so is matplotlib (imported at first use): every worker draws, and would import it privately
        lazy.load_all()  # and pandas & co.: every worker writes tables, and this process judges them while they run
    # the ~200 000 objects alive now (modules, numba, matplotlib, the scenarios) live as long as the process:
    # frozen, the cyclic collector stops re-traversing them on every full collection of every artefact
    # (gc 3.0 -> 1.4 s CPU over the 37 quick artefacts), and forked workers stop touching (copying) their pages
    gc.collect()
    gc.freeze()
    with io.fixed_commit():  # one git look for every manifest
        io.git_commit()  # asked before the workers fork: they inherit the answer
        try:
            if jobs <= 1:
                for a in arts:
                    results[a.name] = _run_one(tasks[a.name])
                    if on_done:
                        on_done(a, results[a.name])
            else:
                order = sorted(arts, key=lambda a: -_expected_wall(a, out_root, golden_root))  # stable among equals
                with ProcessPoolExecutor(max_workers=min(jobs, len(arts)) or 1, **pool_kwargs()) as ex:
                    futures = {ex.submit(_run_one, tasks[a.name]): a for a in order}
                    for fut in as_completed(futures):
                        a = futures[fut]
                        results[a.name] = fut.result()
                        if on_done:
                            on_done(a, results[a.name])
        finally:
            gc.unfreeze()
            _SCENARIOS.clear()
    return results


def dirty_tree(root: Path) -> list[str] | None:
    """Modified tracked files of the git work tree at ``root`` outside ``results/`` (what makes
    a manifest's commit ``+dirty``); None when ``root`` is not a git work tree or git is missing."""
    try:
        r = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ".", ":(exclude)results"],
                           cwd=root, capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return None
    if r.returncode != 0:
        return None
    return [ln[3:] for ln in r.stdout.splitlines() if ln.strip()]


def reproduce(topics: list[str], *, quick: bool, out_root: Path | None, check: bool, jobs: int, write_report: bool,
              console, quiet: bool = False, root: Path | None = None, allow_dirty: bool = False) -> bool:
    """Run, check, summarize and (optionally) write the report. Returns True when nothing failed.

    Writing into the repository's own ``results/`` (the committed goldens and REPORT.md) needs
    a clean git tree, so that what is committed says which code made it; ``allow_dirty``
    (``--allow-dirty``) overrides this."""
    root = Path(root or Path.cwd())
    golden_root = root / "results"
    if out_root is None:
        out_root = root / ("build/quick-results" if quick else "results")
    out_root = Path(out_root)
    if quick and out_root.resolve() == golden_root.resolve():
        raise ConfigError.at("--out", "a --quick run must not overwrite the committed full-size results/; choose another --out")
    all_arts, published = discover(root, topics)
    if out_root.resolve() == golden_root.resolve() and not allow_dirty:
        dirty = dirty_tree(root)
        if dirty:
            shown = ", ".join(dirty[:5]) + (f" and {len(dirty) - 5} more" if len(dirty) > 5 else "")
            raise ConfigError.at("--out", f"the git tree has uncommitted changes ({shown}): results/ and REPORT.md "
                                          "are committed outputs and must come from a clean commit. Commit first, "
                                          "write elsewhere with --out DIR, or pass --allow-dirty")
    arts = [a for a in all_arts if not topics or a.topic in topics]
    if not quiet:
        console.print(f"reproducing {len(arts)} artefacts ({'quick' if quick else 'full size'}) into {out_root}/ with {jobs} job(s)")

    def done(a, r):
        if not quiet:
            mark = "✓" if r[3] is None else "✗"
            console.print(f"  {mark} {a.topic}/{a.name}  {r[2]:.1f} s" + (f"  — {r[3]}" if r[3] else ""), highlight=False, markup=False)

    def judge(o: ArtefactOutcome, folder: Path) -> None:
        pub = published[o.artefact.topic]
        o.checks = [evaluate(c, folder, quick) for c in pub.printed if c.artefact == o.artefact.name]
        o.claims = [evaluate_claim(c, folder, quick) for c in pub.claims if c.artefact == o.artefact.name]

    judged: dict[str, ArtefactOutcome] = {}

    def finished(a, r):  # judged as soon as it is written, while the pool's other workers still run
        done(a, r)
        name, folder, wall, error = r
        o = ArtefactOutcome(a, Path(folder) if folder else None, wall, error)
        if folder:
            judge(o, Path(folder))
            g = golden_root / a.name
            if check and quick:
                if g.is_dir():
                    o.golden = compare_golden(Path(folder), g, a.name, published[a.topic].golden.get(a.name))
                else:
                    o.golden = [f"{a.name}: no committed result results/{a.name}/ to compare with "
                                f"(run `netkf reproduce {a.topic}` at full size and commit it)"]
                o.golden_checked = True
        judged[a.name] = o

    run_all(arts, out_root, quick, jobs, finished, golden_root)
    outcomes = [judged[a.name] for a in arts]
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
        man = json.loads((folder / "manifest.json").read_text())
        o = ArtefactOutcome(a, folder, man.get("wall_time_s", 0.0), previous=str(man.get("created", "earlier")))
        judge(o, folder)
        report_outcomes.append(o)
    if write_report:
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
                    console.print(f"  {o.artefact.name}: check {c.check.id} ({c.check.quantity}): {c.note or d}", markup=False, highlight=False)
            for c in o.claims:
                if c.failed:
                    d = c.note or f"{c.claim.column} = {c.ours:.6g}, needs {c.claim.holds_if.text(c.claim.column)}"
                    console.print(f"  {o.artefact.name}: claim {c.claim.id} ({c.claim.claim}): {d}", markup=False, highlight=False)
            for gm in o.golden:
                console.print(f"  golden: {gm}", markup=False, highlight=False)
    return not failed


def summarize(outcomes: list[ArtefactOutcome], console, quick: bool) -> None:
    t = Table(title=f"netkf reproduce ({'quick' if quick else 'full size'})")
    for col in ("artefact", "printed ✓", "claims ✓", "failed", "largest deviation", "golden", "wall time"):
        t.add_column(col)
    for o in outcomes:
        n_ok = sum(1 for c in o.checks if c.ok or c.check.expect == "differs")
        n_claims = sum(1 for c in o.claims if not c.failed and c.holds is not None)
        n_bad = sum(1 for c in o.checks if c.failed) + sum(1 for c in o.claims if c.failed)
        worst = None  # the printed number closest to (or furthest past) its tolerance
        for c in o.checks:
            if c.ours is None or c.check.expect == "differs" or c.interval is not None:
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
        t.add_row(f"{o.artefact.topic}/{o.artefact.name}", f"{n_ok}/{len(o.checks)}", f"{n_claims}/{len(o.claims)}",
                  str(n_bad), wtxt, gold, f"{o.wall_time:.1f} s")
    console.print(t)
