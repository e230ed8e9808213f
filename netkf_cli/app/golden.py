"""Golden tables: one comparison, per-column tolerances derived from the numerics (issue 14.1).

A *golden* is a committed CSV; a *fresh* table is the same CSV written again (by a test at the
same size, or by ``netkf reproduce --quick`` against the committed full-size ``results/``).
Rows are aligned by position (a table's layout depends on the scenario only); the columns and
every text column must be identical. Each numeric cell is then compared according to its
**kind**, declared per CSV in the topic's ``experiments/<topic>/published.yaml``::

    golden:
      fading_fig5_optima:                       # CSV stem
        - columns: [threshold, threshold_db]
          kind: optimizer
          atol: 1.0e-6
          why: "minimize_scalar(method='bounded', xatol=1e-9) on a flat objective: ..."
      markov_example1:
        - {columns: [value], select: {series: lmi}, kind: optimizer, rtol: 1.0e-4, atol: 1.0e-9, why: "..."}

The first rule whose ``columns`` (or ``["*"]``) and ``select`` match a cell decides; cells no
rule matches follow the tidy-CSV conventions of ``design.md`` (:data:`CONVENTIONS`), and every
other numeric column is a **closed form**. The kinds and their tolerances:

``closed`` (default)
    ``|Δ| ≤ atol·scale + rtol·|golden|`` with ``rtol = 1e-7``, ``atol = 1e-9`` and ``scale`` the
    largest finite ``|golden|`` of the column (so an entry that is zero up to round-off —
    −4.9e-16 against 2.3e-17 — is compared absolutely, at the column's scale). Why these
    numbers: the CSV keeps 10 significant digits (rounding ≤ 5e-10 relative); LAPACK/BLAS builds
    differ by a few ulps (~1e-15) per operation, amplified by the recursions we run (a Riccati
    map iterated 20 times with |A|² ≈ 2 multiplies an error by ~1e6 → ~1e-10). 1e-7 leaves a
    margin of ≥ 100 over that and still catches any change in the 7th digit.
``mc`` (Monte Carlo)
    ``|Δ| ≤ sigmas·√(se_golden² + se_fresh²)`` (sigmas = 5: a false alarm has probability
    ~6e-7 per normal cell; when a standard error comes from few samples — n replicate runs —
    ``sigmas`` becomes the Student-t quantile with n − 1 degrees of freedom of the same tail
    probability, e.g. 10.3 for n = 12). ``se`` is read from the rule's ``stderr`` column (default
    ``stderr``) and, where ``ci_low``/``ci_high`` exist, at least ``(ci_high − ci_low)/3.92``;
    a proportion reported with ``se = 0`` (p̂ ∈ {0, 1}) gets the Agresti–Coull floor
    ``√(p̃(1 − p̃)/(n + 4))``, ``p̃ = (n p̂ + 2)/(n + 4)``. When the fresh run is smaller than the
    golden (``--quick``), its se is at least the golden's scaled by ``√(n_golden/n_fresh)``.
    Rows without any uncertainty (closed-form rows of a mixed table: ``stderr`` empty and no
    sample size) are compared as ``closed``; rows with a sample size but no uncertainty are
    run-dependent: compared as ``closed`` at equal size, skipped otherwise. Rows flagged
    ``reliable = 0`` in either table are skipped.
``optimizer``
    ``|Δ| ≤ atol + rtol·|golden|`` as declared; the rule's ``why`` must say where the numbers
    come from (the optimizer's own tolerance: xatol, gap tolerances …). No default.
``stderr``
    a standard error is itself a Monte Carlo estimate: at equal sample size n, relative
    difference ≤ sigmas·√(1/(2(n_a − 1)) + 1/(2(n_b − 1))) (normal-theory s.e. of a sample
    standard deviation), 0.5 when n is unknown; not compared when the sizes differ.
``size``
    sample sizes: equal when both runs have the same size, not compared under ``--quick``.
``cdf``
    a distribution function F evaluated on a sample-dependent grid (the rule's ``grid`` column,
    e.g. an ECDF at sample quantiles; declare the grid column itself ``diagnostic``): the fresh
    F(x) must lie within the golden values at the neighbouring golden grid points (F is
    monotone), widened by the Monte Carlo tolerance above.
``diagnostic``
    not compared (run-dependent diagnostics: p-values, effective sample sizes, reliability and
    heavy-tail flags, overflow counts, wall times).

A comparison can never pass vacuously: a missing or empty golden, a fresh table that is
missing, changed columns or row counts, or a table in which no numeric cell was compared are
all failures. Regenerating (``NETKF_UPDATE_GOLDEN=1``, :func:`check_folder` with
``update=True``) writes the goldens and then fails, so a run that regenerated never passes.
"""

from __future__ import annotations

import os
import re
import shutil
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from netkf_cli.core.lazy import pandas as pd
from pydantic import Field, model_validator
from scipy.special import ndtr, stdtrit

from netkf_cli.config.compat import safe_load
from netkf_cli.core.spec import StrictModel
from netkf_cli.core.tolerances import GOLDEN_CLOSED_ATOL, GOLDEN_CLOSED_RTOL, MC_SIGMAS

Z95 = 1.959963984540054
UPDATE_ENV = "NETKF_UPDATE_GOLDEN"

Kind = Literal["closed", "mc", "optimizer", "stderr", "size", "diagnostic", "cdf"]


class GoldenRule(StrictModel):
    """How some cells of one golden CSV are compared (first matching rule wins)."""

    columns: list[str] = Field(..., min_length=1, description='columns this rule covers, or ["*"] for every numeric column')
    select: dict[str, Any] = Field(default_factory=dict,
                                   description="rows: column → value, list of values, or /regex/ for text columns")
    kind: Kind = Field(..., description="closed | mc | optimizer | stderr | size | diagnostic | cdf (see netkf_cli/app/golden.py)")
    atol: float | None = Field(None, ge=0, description="absolute tolerance (closed: times the column's scale)")
    rtol: float | None = Field(None, ge=0, description="relative tolerance")
    sigmas: float = Field(MC_SIGMAS, gt=0, description="Monte Carlo: number of combined standard errors")
    stderr: str | None = Field(None, description="Monte Carlo: the column holding this column's standard error")
    n: str | None = Field(None, description="the column holding the sample size (default n, n_runs or runs)")
    grid: str | None = Field(None, description="cdf: the column holding the (sample-dependent) abscissa x of F(x)")
    why: str = Field("", description="where the tolerance comes from (required for optimizer and diagnostic)")

    @model_validator(mode="after")
    def _justified(self):
        if self.kind in ("optimizer", "diagnostic") and not self.why.strip():
            raise ValueError(f"kind {self.kind} needs `why` (where the tolerance comes from)")
        if self.kind == "optimizer" and self.atol is None and self.rtol is None:
            raise ValueError("kind optimizer needs atol and/or rtol (the optimizer's own tolerance)")
        if self.kind == "cdf" and not self.grid:
            raise ValueError("kind cdf needs `grid`: the column holding x")
        return self


#: The tidy-CSV conventions of design.md, applied where no declared rule matches.
CONVENTIONS: dict[str, GoldenRule] = {
    "value": GoldenRule(columns=["value"], kind="mc", stderr="stderr"),
    "ci_low": GoldenRule(columns=["ci_low"], kind="mc", stderr="stderr"),
    "ci_high": GoldenRule(columns=["ci_high"], kind="mc", stderr="stderr"),
    "statistic": GoldenRule(columns=["statistic"], kind="mc", stderr="statistic_stderr"),
    "stderr": GoldenRule(columns=["stderr"], kind="stderr"),
    "statistic_stderr": GoldenRule(columns=["statistic_stderr"], kind="stderr"),
    **{c: GoldenRule(columns=[c], kind="size") for c in ("n", "n_runs", "runs")},
    **{c: GoldenRule(columns=[c], kind="diagnostic", why="run-dependent diagnostic")
       for c in ("reliable", "heavy_tail", "p_value", "wall_time_s", "ess_frac", "min_ess_frac", "finite_variance",
                 "overflowed")},
}
SIZE_COLUMNS = ("n", "n_runs", "runs")
DIAGNOSTIC_TEXT = {"flag_reason": "why a mean is flagged (codes of stats.FLAG_REASONS): run-dependent, like heavy_tail"}
"""Text columns that are run-dependent diagnostics: not compared (every other text column must be identical)."""


class GoldenError(AssertionError):
    """A golden comparison failed (or goldens were regenerated, which also fails)."""


@dataclass
class Comparison:
    """The outcome for one table: mismatch lines, and how many cells of each kind were compared."""

    name: str
    problems: list[str] = field(default_factory=list)
    compared: dict[str, int] = field(default_factory=dict)
    skipped: int = 0

    @property
    def ok(self) -> bool:
        return not self.problems


def parse_rules(spec: Mapping[str, Any] | None) -> dict[str, list[GoldenRule]]:
    """``{csv stem: [rule, ...]}`` from a published.yaml ``golden:`` mapping."""
    out: dict[str, list[GoldenRule]] = {}
    for stem, rules in (spec or {}).items():
        out[str(stem)] = [r if isinstance(r, GoldenRule) else GoldenRule.model_validate(r) for r in rules or []]
    return out


def rules_for_topic(root: Path, topic: str) -> dict[str, list[GoldenRule]]:
    """The ``golden:`` block of ``experiments/<topic>/published.yaml`` (empty if none)."""
    f = Path(root) / "experiments" / topic / "published.yaml"
    if not f.exists():
        return {}
    data = safe_load(f.read_text(encoding="utf-8")) or {}
    return parse_rules(data.get("golden"))


def _row_mask(df: pd.DataFrame, select: Mapping[str, Any]) -> np.ndarray:
    mask = np.ones(len(df), dtype=bool)
    for col, want in select.items():
        if col not in df.columns:
            raise KeyError(f"golden rule selects on column {col!r}, not in the table (columns: {list(df.columns)})")
        wants = want if isinstance(want, list) else [want]
        s = df[col]
        m = np.zeros(len(df), dtype=bool)
        for w in wants:
            if isinstance(w, str) and len(w) >= 2 and w.startswith("/") and w.endswith("/"):
                rx = re.compile(w[1:-1])
                m |= np.array([bool(rx.search(str(v))) for v in s], dtype=bool)
            elif isinstance(w, (int, float)) and not isinstance(w, bool) and pd.api.types.is_numeric_dtype(s):
                m |= np.isclose(s.to_numpy(float), float(w), rtol=1e-9, atol=1e-12)
            else:
                m |= s.astype(str).to_numpy() == str(w)
        mask &= m
    return mask


def _col(df: pd.DataFrame, name: str | None) -> np.ndarray:
    if name is None or name not in df.columns or not pd.api.types.is_numeric_dtype(df[name]):
        return np.full(len(df), np.nan)
    return df[name].to_numpy(float)


def _size_column(df: pd.DataFrame, rule: GoldenRule | None) -> str | None:
    if rule is not None and rule.n:
        return rule.n
    return next((c for c in SIZE_COLUMNS if c in df.columns), None)


def _agresti_coull_se(p: np.ndarray, n: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore", divide="ignore"):
        pt = (n * p + 2.0) / (n + 4.0)
        return np.sqrt(pt * (1.0 - pt) / (n + 4.0))


def _t_factor(sigmas: float, ng: np.ndarray, nf: np.ndarray) -> np.ndarray:
    """``sigmas`` normal standard errors as a Student-t quantile of the same tail probability
    when the standard errors come from few samples (ν = min(n) − 1; e.g. 12 replicate runs:
    5σ → 10.3; ≥ 1000 samples: 5.03). Unknown n: the normal value."""
    p_half = ndtr(-sigmas)  # the normal upper tail (what scipy.stats.norm.sf computes)
    n = np.fmin(ng, nf)
    out = np.full(n.shape, float(sigmas))
    ok = np.isfinite(n) & (n >= 2)
    if ok.any():
        out[ok] = np.maximum(-stdtrit(n[ok] - 1.0, p_half), sigmas)  # Student-t upper quantile (= scipy.stats.t.isf)
    return out


def _uncertainty(df: pd.DataFrame, rule: GoldenRule, n: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Per-row standard error of a Monte Carlo column (NaN where the row has none)."""
    se = _col(df, rule.stderr or "stderr")
    lo, hi = _col(df, "ci_low"), _col(df, "ci_high")
    with np.errstate(invalid="ignore"):
        se_ci = (hi - lo) / (2 * Z95)
        se = np.fmax(se, se_ci)  # fmax ignores NaN
        is_prop = np.isfinite(n) & (n > 0) & (v >= 0) & (v <= 1)
        zero = np.isfinite(se) & (se == 0) & is_prop
    se = np.where(zero, _agresti_coull_se(v, n), se)
    return se


def compare_tables(fresh: pd.DataFrame, golden: pd.DataFrame, rules: Iterable[GoldenRule] = (), *,
                   name: str = "table", quick: bool = False, max_lines: int = 5) -> Comparison:
    """Compare ``fresh`` with ``golden`` cell by cell (see the module docstring)."""
    res = Comparison(name)
    rules = list(rules)
    if len(golden) == 0:
        res.problems.append(f"{name}: the golden table is empty (a comparison with nothing cannot pass)")
        return res
    if list(fresh.columns) != list(golden.columns):
        res.problems.append(f"{name}: columns changed: golden {list(golden.columns)} → fresh {list(fresh.columns)}")
        return res
    if len(fresh) != len(golden):
        res.problems.append(f"{name}: {len(fresh)} rows, the golden has {len(golden)}")
        return res
    text = [c for c in golden.columns if not pd.api.types.is_numeric_dtype(golden[c])
            or not pd.api.types.is_numeric_dtype(fresh[c])]
    for c in (c for c in text if c not in DIAGNOSTIC_TEXT):
        # an empty cell reads back as missing (NaN under pandas' string dtype, where NaN != NaN): compare as ""
        bad = (fresh[c].astype(object).where(fresh[c].notna(), "").astype(str).to_numpy()
               != golden[c].astype(object).where(golden[c].notna(), "").astype(str).to_numpy())
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            res.problems.append(f"{name} row {i}: {c} is {fresh[c].iloc[i]!r}, golden {golden[c].iloc[i]!r} (layout changed)")
            return res
    numeric = [c for c in golden.columns if c not in text]
    # which rule governs each cell
    masks = []
    for r in rules:
        try:
            masks.append((r, _row_mask(golden, r.select)))
        except KeyError as exc:
            res.problems.append(f"{name}: {exc.args[0]}")
            return res
    reliable = np.ones(len(golden), dtype=bool)
    if "reliable" in golden.columns:
        with np.errstate(invalid="ignore"):
            reliable = (_col(golden, "reliable") != 0) & (_col(fresh, "reliable") != 0)
    desc_cols = [c for c in golden.columns if (c in text or c not in CONVENTIONS) and c not in DIAGNOSTIC_TEXT]
    lines: list[str] = []
    n_bad = 0
    for c in numeric:
        assigned = np.zeros(len(golden), dtype=bool)
        plan: list[tuple[GoldenRule, np.ndarray]] = []
        for r, m in masks:
            if c in r.columns or r.columns == ["*"]:
                take = m & ~assigned
                if take.any():
                    plan.append((r, take))
                    assigned |= take
        if not assigned.all():
            plan.append((CONVENTIONS.get(c, GoldenRule(columns=[c], kind="closed")), ~assigned))
        for r, rows in plan:
            bad, tol, how = _compare_cells(fresh, golden, c, r, rows, reliable, quick, res, text)
            for i in np.flatnonzero(bad):
                n_bad += 1
                if len(lines) < max_lines:
                    where = ", ".join(f"{k}={golden[k].iloc[i]}" for k in desc_cols
                                      if k != c and pd.notna(golden[k].iloc[i]))[:160]
                    fv, gv = float(fresh[c].iloc[i]), float(golden[c].iloc[i])
                    h = how if isinstance(how, str) else how[i]
                    lines.append(f"{name} row {i} [{where}] {c}: {fv:.10g} vs golden {gv:.10g} "
                                 f"(|Δ| {abs(fv - gv):.3g} > {h} tolerance {tol[i]:.3g})")
    res.problems += lines
    if n_bad > len(lines):
        res.problems.append(f"{name}: {n_bad - len(lines)} more cells differ")
    if not res.problems and sum(res.compared.values()) == 0:
        res.problems.append(f"{name}: no numeric cell was compared (every cell skipped): the comparison would pass vacuously")
    return res


def _compare_cells(fresh, golden, c, rule: GoldenRule, rows, reliable, quick, res: Comparison, text=()):
    """(bad mask, tolerance per row, description); counts compared/skipped cells into ``res``."""
    with np.errstate(all="ignore"):  # ±inf and NaN cells are handled explicitly below
        if rule.kind == "cdf":
            return _compare_cdf(fresh, golden, c, rule, rows, res, list(text))
        return _compare_cells_inner(fresh, golden, c, rule, rows, reliable, quick, res)


def _compare_cdf(fresh, golden, c, rule: GoldenRule, rows, res: Comparison, text: list[str]):
    """A distribution function F evaluated on a sample-dependent grid x (e.g. an ECDF at sample
    quantiles): the fresh F(x_f) is compared with the golden F bracketed by monotonicity,
    F_g(x⁻) ≤ F(x_f) ≤ F_g(x⁺) at the golden grid points around x_f (0 and 1 beyond its ends),
    widened by the Monte Carlo tolerance of both estimates (Agresti–Coull floor for F̂ ∈ {0, 1}).
    Rows are grouped by the text columns (one curve per group)."""
    f, g = _col(fresh, c), _col(golden, c)
    xf, xg = _col(fresh, rule.grid), _col(golden, rule.grid)
    ncol = _size_column(golden, rule)
    ng, nf = _col(golden, ncol), _col(fresh, ncol)
    seg = np.nan_to_num(_uncertainty(golden, rule, ng, g))
    sef = np.nan_to_num(_uncertainty(fresh, rule, nf, f))
    tfac = _t_factor(rule.sigmas, ng, nf)
    tol = np.full(len(g), np.nan)
    bad = np.zeros(len(g), dtype=bool)
    keys = golden[text].astype(str).agg("\x1f".join, axis=1).to_numpy() if text else np.zeros(len(g), dtype=str)
    compared = 0
    for key in np.unique(keys[rows]):
        idx = np.flatnonzero(rows & (keys == key))
        gi = idx[np.argsort(xg[idx], kind="stable")]
        xs, Fs, ss = xg[gi], g[gi], seg[gi]
        for j in idx:
            if not (np.isfinite(xf[j]) and np.isfinite(f[j])):
                continue
            k = np.searchsorted(xs, xf[j], side="right")  # xs[k-1] ≤ x < xs[k]
            lo = Fs[k - 1] if k > 0 else 0.0
            hi = Fs[k] if k < len(xs) else 1.0
            if k > 0 and xs[k - 1] == xf[j]:
                hi = max(hi, Fs[k - 1]) if k < len(xs) else Fs[k - 1]
            s_g = max(ss[k - 1] if k > 0 else 0.0, ss[k] if k < len(xs) else 0.0)
            t = tfac[j] * np.sqrt(s_g**2 + sef[j] ** 2) + 1e-12
            tol[j] = (hi - lo) + t
            bad[j] = f[j] < lo - t or f[j] > hi + t
            compared += 1
    res.compared["cdf"] = res.compared.get("cdf", 0) + compared
    res.skipped += int(rows.sum()) - compared
    return bad, tol, "cdf"


def _compare_cells_inner(fresh, golden, c, rule: GoldenRule, rows, reliable, quick, res: Comparison):
    f, g = _col(fresh, c), _col(golden, c)
    tol = np.full(len(g), np.nan)
    cmp = rows.copy()
    kind = rule.kind
    ncol = _size_column(golden, rule)
    ng, nf = _col(golden, ncol), _col(fresh, ncol)
    same_size = np.isfinite(ng) & np.isfinite(nf) & (ng == nf)
    if kind == "diagnostic" or (kind in ("size", "stderr") and quick):
        res.skipped += int(rows.sum())
        return np.zeros(len(g), bool), tol, kind
    finite_scale = np.abs(g[np.isfinite(g)])
    scale = float(finite_scale.max()) if finite_scale.size else 0.0
    closed_tol = (rule.atol if rule.kind == "closed" and rule.atol is not None else GOLDEN_CLOSED_ATOL) * scale \
        + (rule.rtol if rule.kind == "closed" and rule.rtol is not None else GOLDEN_CLOSED_RTOL) * np.abs(g)
    if kind == "closed":
        tol = closed_tol
    elif kind == "optimizer":
        tol = (rule.atol or 0.0) + (rule.rtol or 0.0) * np.abs(g)
    elif kind == "size":
        tol = np.zeros(len(g))
    elif kind == "stderr":
        with np.errstate(invalid="ignore", divide="ignore"):
            rel = np.where(same_size & (ng > 1), rule.sigmas * np.sqrt(1 / (2 * (ng - 1)) + 1 / (2 * (nf - 1))), 0.5)
        rel = np.minimum(rel, 1.0)
        # at different sizes (not --quick: e.g. a test at another size) the s.e. are not comparable
        cmp &= same_size | ~np.isfinite(ng)
        tol = rel * np.abs(g) + 1e-300
    elif kind == "mc":
        seg = _uncertainty(golden, rule, ng, g)
        sef = _uncertainty(fresh, rule, nf, f)
        has_se = (np.isfinite(seg) & (seg > 0)) | (np.isfinite(sef) & (sef > 0))
        with np.errstate(invalid="ignore", divide="ignore"):
            scaled = np.where(np.isfinite(ng) & np.isfinite(nf) & (nf > 0), np.nan_to_num(seg) * np.sqrt(ng / nf), 0.0)
        sef_eff = np.maximum(np.nan_to_num(sef), np.nan_to_num(scaled))
        mc_tol = _t_factor(rule.sigmas, ng, nf) * np.sqrt(np.nan_to_num(seg) ** 2 + sef_eff**2)
        run_dependent = ~has_se & np.isfinite(ng) & (ng > 0)
        tol = np.where(has_se, mc_tol, closed_tol)
        cmp &= ~(run_dependent & ~same_size)  # a sample-derived number without an s.e., at another size
        cmp &= reliable | ~has_se
    with np.errstate(invalid="ignore"):
        agree = (np.isnan(g) & np.isnan(f)) | (np.isinf(g) & (g == f)) | (np.abs(f - g) <= tol * (1 + 1e-12))
    bad = cmp & ~agree
    res.skipped += int((rows & ~cmp).sum())
    if kind == "mc":  # rows without an uncertainty were compared as closed forms
        res.compared["closed"] = res.compared.get("closed", 0) + int((cmp & ~has_se).sum())
        res.compared["mc"] = res.compared.get("mc", 0) + int((cmp & has_se).sum())
        how = np.where(has_se, "mc", "closed")
    else:
        res.compared[kind] = res.compared.get(kind, 0) + int(cmp.sum())
        how = kind
    return bad, tol, how


def compare_files(fresh: Path, golden: Path, rules: Iterable[GoldenRule] = (), *, quick: bool = False) -> Comparison:
    """Compare two CSV files; a missing or empty golden or a missing fresh file fails."""
    fresh, golden = Path(fresh), Path(golden)
    name = golden.name
    if not golden.exists():
        return Comparison(name, [f"{name}: no golden file {golden} (regenerate with {UPDATE_ENV}=1, then commit)"])
    if not fresh.exists():
        return Comparison(name, [f"{name}: the golden is committed but the fresh run did not write {fresh.name}"])
    try:
        g = pd.read_csv(golden)
    except pd.errors.EmptyDataError:
        return Comparison(name, [f"{name}: the golden file is empty"])
    return compare_tables(pd.read_csv(fresh), g, rules, name=name, quick=quick)


def check_folder(fresh_dir: Path, golden_dir: Path, rules: Mapping[str, list[GoldenRule]] | None = None, *,
                 stems: Iterable[str] | None = None, quick: bool = False, update: bool | None = None) -> list[Comparison]:
    """Every CSV of ``fresh_dir`` (or the given ``stems``) against ``golden_dir``; raises
    :class:`GoldenError` listing every mismatch. With ``update`` (default: the environment
    variable ``NETKF_UPDATE_GOLDEN``) the fresh CSVs are copied into ``golden_dir`` and the call
    fails anyway: a run that regenerated its goldens never passes."""
    fresh_dir, golden_dir = Path(fresh_dir), Path(golden_dir)
    rules = dict(rules or {})
    if update is None:
        update = bool(os.environ.get(UPDATE_ENV))
    names = sorted(stems) if stems is not None else sorted(p.stem for p in fresh_dir.glob("*.csv"))
    if not names:
        raise GoldenError(f"no CSV in {fresh_dir} to compare (a comparison with nothing cannot pass)")
    if update:
        golden_dir.mkdir(parents=True, exist_ok=True)
        for s in names:
            shutil.copy(fresh_dir / f"{s}.csv", golden_dir / f"{s}.csv")
        raise GoldenError(f"regenerated {len(names)} golden file(s) in {golden_dir}: review the diff, commit, "
                          f"and re-run without {UPDATE_ENV} (a run that regenerates goldens always fails)")
    out = [compare_files(fresh_dir / f"{s}.csv", golden_dir / f"{s}.csv", rules.get(s, ()), quick=quick) for s in names]
    problems = [p for c in out for p in c.problems]
    if problems:
        raise GoldenError("golden mismatch:\n  " + "\n  ".join(problems))
    return out


def check_topic_folder(fresh_dir: Path, golden_dir: Path, topic: str, *, root: Path | None = None,
                       stems: Iterable[str] | None = None, quick: bool = False) -> list[Comparison]:
    """:func:`check_folder` with the rules of ``experiments/<topic>/published.yaml`` — what a
    topic's regression test calls::

        res = run_scenario_file(cfg, out_dir=tmp_path / "x", runs=RUNS, force=True)
        golden.check_topic_folder(res, Path(__file__).parent / "golden", "fading")
    """
    root = Path(root) if root is not None else Path(__file__).resolve().parents[2]
    return check_folder(fresh_dir, golden_dir, rules_for_topic(root, topic), stems=stems, quick=quick)


def describe(comparisons: Iterable[Comparison]) -> str:
    """One line: how many cells of each kind were compared and skipped."""
    tot: dict[str, int] = {}
    skipped = 0
    for c in comparisons:
        for k, v in c.compared.items():
            tot[k] = tot.get(k, 0) + v
        skipped += c.skipped
    return ", ".join(f"{k} {v}" for k, v in sorted(tot.items())) + f"; skipped {skipped}"


__all__ = ["GoldenRule", "GoldenError", "Comparison", "CONVENTIONS", "compare_tables", "compare_files",
           "check_folder", "check_topic_folder", "parse_rules", "rules_for_topic", "describe"]
