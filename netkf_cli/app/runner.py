"""One run, as the data flow reads: load → compute (sample → covariances → summarize) → write.

The analysis model's ``compute`` does the sampling and the recursions; this module only
expands sweeps, sets where Monte Carlo chunks execute (and the resume cache), times the
run, writes the CSVs, draws the figure *from the written CSVs* and writes the manifest,
all inside an atomic result folder.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from netkf_cli.core.lazy import pandas as pd

from netkf_cli.runtime import io, montecarlo
from netkf_cli.config import sweep
from netkf_cli.core.errors import ConfigError, Problem
from netkf_cli.config.loader import load_scenario, locate, parse_overrides, validate_data
from netkf_cli.runtime.plotting import save
from netkf_cli.recipes.base import Artefact, RunContext

CACHE_DIR = ".netkf-cache"


def default_out_dir(scenario) -> Path:
    return Path(scenario.output.dir) / scenario.name


HASH_EXCLUDE = {"montecarlo": {"max_runs"}}
"""Fields that cannot change a number (the run-count guard): not part of the scenario hash."""


def scenario_hash(scenario, runs: int | None) -> str:
    """Hash of the resolved scenario (after overrides) and the run-size override: the resume key
    and how a rerun of the same scenario is recognised."""
    blob = json.dumps({"scenario": scenario.model_dump(mode="json", exclude=HASH_EXCLUDE), "runs": runs},
                      sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def same_scenario(manifest: dict, scenario, runs: int | None) -> bool:
    """Whether an existing result (its manifest) was made from this scenario at this run size, so
    that rerunning it loses nothing. The same hash, or — for results written before fields were
    added to the schema — every field the old manifest recorded has the same value now."""
    if manifest.get("scenario_hash") == scenario_hash(scenario, runs):
        return True
    old, mc = manifest.get("scenario"), manifest.get("montecarlo") or {}
    if not isinstance(old, dict) or mc.get("runs") != int(runs or scenario.montecarlo.runs):
        return False
    return _covers(old, scenario.model_dump(mode="json", by_alias=True))


def _covers(old, new) -> bool:
    if isinstance(old, dict):
        return isinstance(new, dict) and all(k in new and _covers(v, new[k]) for k, v in old.items())
    if isinstance(old, list):
        return isinstance(new, list) and len(old) == len(new) and all(_covers(a, b) for a, b in zip(old, new))
    return old == new


def compute(scenario, ctx: RunContext, source: str | Path | None = None) -> Artefact:
    """Run the scenario's analysis (every sweep point); ConfigErrors get file and line."""
    file = str(source) if source else None
    try:
        if scenario.sweep is None:
            return _analysis(scenario, ctx, file)
        points = sweep.expand(scenario, file, validate_data)  # all, before running
        return _points(points, ctx, lambda sc, c, i: _analysis(sc, c, file),
                       lambda art, coords: sweep.check_plot(scenario.sweep, sweep.add_coords(art.table, coords)),
                       {"sweep": {"mode": scenario.sweep.mode, "axes": scenario.sweep.axes}})
    except ConfigError as exc:
        if source is not None:
            raise locate(exc, source) from None
        raise


class ProgressTotals:
    """The one total of a run's progress bar, from two sources that describe the same work.

    A recipe may declare its whole size up front (``ctx.total(n)``: every Monte Carlo run of every
    series, plus non-Monte-Carlo units such as LMI iterations) while :func:`montecarlo.run_chunked`
    announces each call's runs as it starts (``add_total``). Adding both counted the runs twice (a
    bar ending at 50 %, an ETA twice too long); the total is the larger of the two.
    """

    def __init__(self, update: Callable[[int | None], None] | None = None):
        self.declared = 0
        self.planned = 0
        self._update = update

    @property
    def total(self) -> int | None:
        return max(self.declared, self.planned) or None

    def set_total(self, n: int) -> None:
        self.declared = int(n)
        if self._update:
            self._update(self.total)

    def add_total(self, n: int) -> None:
        self.planned += int(n)
        if self._update:
            self._update(self.total)


def _analysis(scenario, ctx: RunContext, file: str | None) -> Artefact:
    """One scenario's analysis; an ``analysis.over`` grid runs the metric at every point (validated first,
    like a file), on a stream allocated here: 0 at every point (``streams: common``, common random
    numbers) or the point's index (``streams: independent``)."""
    over = getattr(scenario.analysis, "over", None)
    if not over:
        art = scenario.analysis.compute(scenario, ctx)
        _check_artefact(scenario, art)
        return art
    points = sweep.expand_over(scenario, file, validate_data)
    independent = getattr(scenario.analysis, "streams", "common") == "independent"
    art = _points(points, ctx, lambda sc, c, i: _analysis(sc, replace(c, stream=i if independent else 0), file),
                  None, {"over": {"paths": list(over), "points": len(points),
                                  "streams": "independent (stream i at point i)" if independent else
                                  "common (stream 0 at every point: common random numbers)"}})
    finish = getattr(scenario.analysis, "finish_over", None)
    return finish(scenario, art) if finish is not None else art


def _points(points, ctx: RunContext, run, check_first, meta: dict) -> Artefact:
    """Run ``run(scenario, ctx, i)`` at every (coords, scenario) point; one table with a column per path."""
    tables, extras, metas = [], {}, []
    done_total = 0  # progress units declared by the points already finished
    for i, (coords, sc) in enumerate(points):
        declared = [0]

        def point_total(n: int, _d=declared, _base=done_total) -> None:
            _d[0] = n
            ctx.total(_base + n)

        art = run(sc, replace(ctx, set_total=point_total if ctx.set_total else None), i)
        done_total += declared[0]
        _check_artefact(sc, art)
        if not tables and check_first is not None:  # plot.where / plot.series name columns and series
            check_first(art, coords)
        tables.append(sweep.add_coords(art.table, coords))
        for k, df in art.extra_tables.items():
            extras.setdefault(k, []).append(sweep.add_coords(df, coords))
        metas.append({"point": coords, **art.meta})
    return Artefact(pd.concat(tables, ignore_index=True), meta={**meta, "points": metas},
                    extra_tables={k: pd.concat(v, ignore_index=True) for k, v in extras.items()})


def _check_artefact(scenario, art) -> None:
    if not isinstance(art, Artefact):
        raise TypeError(f"{type(scenario.analysis).__name__}.compute must return an Artefact")


def write_result(scenario, art: Artefact, out: Path, *, force: bool, ctx: RunContext,
                 source: str | Path | None, wall_time: float, execution: dict | None = None,
                 overrides: list[str] | None = None, started: float | None = None,
                 info: dict | None = None) -> Path:
    """Write the result folder atomically. A rerun of the same scenario whose files come out
    byte-identical to the folder already there, with the same manifest ``meta``, leaves that folder (and its manifest) untouched,
    so reproducing a committed result leaves a clean checkout clean (``info["unchanged"]``)."""
    name = scenario.name
    h = scenario_hash(scenario, ctx.runs)
    unchanged = False
    with io.atomic_folder(out, force=force, scenario_hash=h,
                          same=lambda man: same_scenario(man, scenario, ctx.runs)) as tmp:
        io.write_csv(art.table, tmp / f"{name}.csv")
        for key, df in art.extra_tables.items():
            io.write_csv(df, tmp / f"{name}_{key}.csv")
        for fname, text in art.extra_text.items():
            (tmp / fname).write_text(text, encoding="utf-8")
        tables = {"main": io.read_csv(tmp / f"{name}.csv")}
        for key in art.extra_tables:
            tables[key] = io.read_csv(tmp / f"{name}_{key}.csv")
        fig = sweep.plot(tables, scenario) if scenario.sweep is not None else scenario.analysis.plot(tables, scenario)
        save(fig, tmp / f"{name}.png", dpi=scenario.output.dpi, formats=scenario.output.formats)  # <name>.<fmt>
        mc = scenario.montecarlo
        files = sorted(p.name for p in tmp.iterdir()) + ["manifest.json"]
        if io.same_files(out, tmp, h, lambda man: same_scenario(man, scenario, ctx.runs), meta=art.meta):
            unchanged = True
            raise io.KeepExisting
        manifest = {
            "name": name,
            "written_by": io.WRITTEN_BY,
            "source": io.display_path(source),
            "overrides": list(overrides or []),
            "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "wall_time_s": round(wall_time, 3),
            "scenario": scenario.model_dump(mode="json", by_alias=True),
            "scenario_hash": h,
            "montecarlo": {"runs": ctx.mc_runs(scenario), "runs_in_scenario": mc.runs, "seed": mc.seed,
                           "chunk": mc.chunk, "quick": ctx.quick,
                           "stream_layout": "chunk i of stream s uses SeedSequence(seed, spawn_key=(s, i))"},
            "execution": execution or {"executor": "serial", "jobs": 1},
            "meta": art.meta,
            "files": files,
            "versions": io.versions(),
            "git_commit": io.git_commit(),
        }
        if started is not None:  # the whole command up to this write: what `netkf run` prints
            manifest["command_time_s"] = round(max(time.perf_counter() - started, wall_time), 3)
        io.write_json(manifest, tmp / "manifest.json")
    if info is not None:
        info["unchanged"] = unchanged
    return out


def result_paths(scenario, out_dir: str | Path | None = None, runs: int | None = None) -> tuple[Path, Path]:
    """``(result folder, resume cache folder)`` of a run. The cache belongs to the result folder
    (``<parent>/.netkf-cache/<folder name>/``), so the same scenario can run into two folders at once."""
    out = Path(out_dir) if out_dir is not None else default_out_dir(scenario)
    return out, out.parent / CACHE_DIR / out.name


def sweep_points(scenario) -> int:
    """Points a run computes: sweep points × the analysis's ``over`` points."""
    over = getattr(scenario.analysis, "over", None)
    n_over = len(next(iter(over.values()))) if over else 1
    if scenario.sweep is None:
        return n_over
    sizes = [len(v) for v in scenario.sweep.axes.values()] or [1]
    return n_over * (max(sizes) if scenario.sweep.mode == "zip" else int(np.prod(sizes, dtype=float)))


def run_counts(scenario, runs: int | None = None, quick: bool = False) -> list[int]:
    """The Monte Carlo run count of every point (a sweep may sweep ``montecarlo.runs``)."""
    mc = scenario.montecarlo
    base = int(runs or (mc.quick_size() if quick else mc.runs))
    if runs is None and scenario.sweep is not None and "montecarlo.runs" in scenario.sweep.axes:
        vals = [v for v in scenario.sweep.axes["montecarlo.runs"] if isinstance(v, (int, float))]
        return [int(v) for v in vals] or [base]
    return [base]


def work_size(scenario, runs: int | None = None, quick: bool = False) -> int:
    """Rough size of a run in run-steps: Monte Carlo runs × horizon × sweep points (for the
    up-front warning on large runs; recipes with several series take a small multiple of it)."""
    mc = scenario.montecarlo
    n = max(run_counts(scenario, runs, quick))
    return int(min(float(n) * mc.horizon * sweep_points(scenario), 2**62))


LARGE_RUN_S = 120.0
"""Runs expected to take longer than this say so (with an ETA) before they start."""
RUN_STEPS_PER_S = 1e7
"""Rough per-process speed of the covariance recursions, for the ETA only (the generic engine's
KF on this machine; compiled estimators are faster)."""


@dataclass
class RunPlan:
    """What a run will do, decided before any work (``netkf run --dry-run`` prints it)."""

    scenario: object
    out: Path
    cache: Path
    runs: int
    points: int
    run_steps: int
    chunks: int
    jobs: int
    executor: str
    replaces: bool
    eta_s: float

    def as_json(self) -> dict:
        return {"folder": str(self.out), "resume_cache": str(self.cache), "runs": self.runs, "sweep_points": self.points,
                "horizon": self.scenario.montecarlo.horizon, "run_steps": self.run_steps, "chunks": self.chunks,
                "chunk": self.scenario.montecarlo.chunk, "executor": self.executor, "jobs": self.jobs,
                "replaces_existing": self.replaces, "eta_s": round(self.eta_s, 1),
                "scenario_hash": scenario_hash(self.scenario, None if self.runs == self.scenario.montecarlo.runs
                                               else self.runs)}


def plan_run(scenario, *, out_dir: str | Path | None = None, runs: int | None = None, quick: bool = False,
             force: bool = False, executor: str = "serial", jobs: int = 1, yes: bool = False,
             runs_option: str = "--runs") -> RunPlan:
    """Every check that can be made before the Monte Carlo, with no side effect: the result folder
    (replaceable, not a mount point, a valid name, creatable), the run count against
    ``montecarlo.max_runs`` (``yes`` lifts it). Raises :class:`ConfigError` / :class:`OutputError`."""
    out, cache = result_paths(scenario, out_dir, runs)
    replaces = io.check_target(out, force=force, scenario_hash=scenario_hash(scenario, runs),
                               same=lambda man: same_scenario(man, scenario, runs))
    io.check_location(out)
    mc = scenario.montecarlo
    counts = run_counts(scenario, runs, quick)
    n, size, eta = check_run_count(scenario, runs, quick=quick, yes=yes, jobs=jobs, runs_option=runs_option)
    points = sweep_points(scenario)
    chunks = sum(-(-c // max(1, min(mc.chunk, c))) for c in counts) * (points if len(counts) == 1 else 1)
    return RunPlan(scenario, out, cache, n, points, size, int(chunks), max(1, jobs), executor, replaces, eta)


def check_run_count(scenario, runs: int | None = None, *, quick: bool = False, yes: bool = False, jobs: int = 1,
                    runs_option: str = "--runs") -> tuple[int, int, float]:
    """Refuse a run count above ``montecarlo.max_runs`` unless ``yes``; returns (runs, run-steps, ETA s)."""
    mc = scenario.montecarlo
    if runs is not None:  # a run count given here would silently replace the counts the scenario varies
        varied = [f"{block}.montecarlo.runs" for block, axes in
                  (("sweep", scenario.sweep.axes if scenario.sweep is not None else {}),
                   ("analysis.over", getattr(scenario.analysis, "over", None) or {})) if "montecarlo.runs" in axes]
        if varied:
            raise ConfigError.at(runs_option, f"the scenario varies the run count ({varied[0]}); {runs_option} would "
                                              f"give every point {runs} runs: drop one of the two")
    counts = run_counts(scenario, runs, quick)
    n = max(counts)
    size = work_size(scenario, runs, quick)
    eta = size / (RUN_STEPS_PER_S * max(1, jobs))
    chunk = min(mc.chunk, n)
    montecarlo.check_chunk_memory(chunk, mc.horizon, min(max(1, jobs), -(-n // chunk)))
    if n > mc.max_runs and not yes:
        path = runs_option if runs else ("sweep.montecarlo.runs" if n != mc.runs else "montecarlo.runs")
        raise ConfigError([Problem(path, f"{n:.3g} runs is above the limit montecarlo.max_runs = {mc.max_runs:.3g} "
                                         f"(about {size:.2g} run-steps, rough ETA {duration(eta)} on {max(1, jobs)} "
                                         f"process{'es' if jobs > 1 else ''}); lower it, or pass --yes (API: yes=True) "
                                         f"or raise montecarlo.max_runs if you mean it")])
    return n, size, eta


def duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    if seconds < 2 * 86400:
        return f"{seconds / 3600:.1f} h"
    if seconds < 2 * 365 * 86400:
        return f"{seconds / 86400:.0f} days"
    return f"{seconds / (365 * 86400):.2g} years"


CACHE_STAMP = "scenario.json"


def _open_cache(cache: Path, h: str, resume: bool, scenario) -> dict:
    """Prepare the resume cache of this run; returns what the manifest says about resuming.

    Without ``resume`` an old cache is discarded. With it, the cache is reused only if its stamp
    holds this scenario's hash; chunks of another scenario (an edited seed, runs, a field) are
    never mixed in: they are discarded and the run says so."""
    note = None
    stamp = cache / CACHE_STAMP
    code = io.code_digest()
    if cache.exists():
        try:
            old = json.loads(stamp.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            old = {}
        n_old = sum(1 for _ in cache.rglob(f"*{montecarlo.CHUNK_SUFFIX}")) if resume else 0
        held = f"--resume: the cache {cache}/ held {n_old} chunk{'s' if n_old != 1 else ''}"
        if resume and old.get("scenario_hash") != h:
            note = (f"{held} of a different scenario (hash {old.get('scenario_hash', 'unknown')}, this one is {h}); "
                    f"none reused, the run starts from the beginning")
        elif resume and old.get("code") != code:
            note = (f"{held} computed by another netkf build (code {old.get('code', 'unknown')}, this one is {code}: "
                    f"their statistics may differ); none reused, the run starts from the beginning")
        if not resume or note:
            io._rmtree(cache)
    elif resume:
        note = f"--resume: no cache of an interrupted run in {cache}/; the run starts from the beginning"
    cache.mkdir(parents=True, exist_ok=True)
    if not stamp.exists():
        stamp.write_text(json.dumps({"scenario_hash": h, "code": code, "name": scenario.name}) + "\n",
                         encoding="utf-8")
    return {"requested": resume, "chunks_reused": 0, **({"note": note} if note else {})}


def run_scenario(scenario, *, source: str | Path | None = None, out_dir: str | Path | None = None,
                 runs: int | None = None, quick: bool = False, force: bool = False,
                 progress: Callable[[int], None] | None = None,
                 set_total: Callable[[int], None] | None = None,
                 add_total: Callable[[int], None] | None = None,
                 executor: str = "serial", jobs: int = 1, scheduler: str | None = None,
                 resume: bool = False, yes: bool = True, overrides: list[str] | None = None,
                 started: float | None = None, info: dict | None = None,
                 notify: Callable[[str], None] | None = None, resumable: bool = True) -> Path:
    """Compute and write one scenario. Finished Monte Carlo chunks are kept in
    ``<out>/../.netkf-cache/<out name>/`` until the result is written, so ``resume=True`` after an
    interruption reuses them (only if the scenario is identical) and gives exactly the
    uninterrupted numbers. ``resumable=False`` keeps no chunks (``netkf reproduce``, which has no
    ``--resume``: a file per chunk written, renamed and deleted for nothing, 719 of them).

    Before any work, :func:`plan_run` checks everything that can be checked. The result folder
    is locked for the whole run (a concurrent run into the same folder gets :class:`BusyError`);
    leftovers of killed runs are cleaned. A run that fails for any reason but an interrupt leaves
    nothing behind: no cache, no lock, no temporary file, no folder it created.
    """
    info = {} if info is None else info
    ctx = RunContext(runs=runs, quick=quick, progress=progress, set_total=set_total)
    plan = plan_run(scenario, out_dir=out_dir, runs=runs, quick=quick, force=force, executor=executor, jobs=jobs,
                    yes=yes)
    out, cache = plan.out, plan.cache
    h = scenario_hash(scenario, runs)
    created = io.make_parent(out)
    try:
        lock = io.FileLock(out, "result folder").acquire()
    except BaseException:
        for d in reversed(created):  # folders this run created, if still empty
            _rmdir_empty(d)
        raise
    interrupted = False
    try:  # from here on the folder, its cache and what this run made are ours to clean
        io.clean_leftovers(out.parent)
        resumed = _open_cache(cache, h, resume, scenario) if resumable else {"requested": False, "chunks_reused": 0}
        if resumed.get("note") and notify:
            notify(resumed["note"])
        t0 = time.perf_counter()
        with montecarlo.execution(executor, jobs, scheduler, cache_dir=cache if resumable else None, progress=progress,
                                  add_total=add_total) as ex:
            art = compute(scenario, ctx, source)
            where = ex.report()  # where the chunks really ran (tested: a promise in the manifest)
        resumed["chunks_reused"] = ex.chunks_cached
        info["resume"] = resumed
        folder = write_result(scenario, art, out, force=force, ctx=ctx, source=source,
                              wall_time=time.perf_counter() - t0,
                              execution={"executor": executor, "jobs": jobs, "scheduler": scheduler,
                                         "resumed": resumed, "chunks_ran": where},
                              overrides=overrides, started=started, info=info)
    except KeyboardInterrupt:
        interrupted = True  # finished chunks stay for --resume
        raise
    finally:
        try:
            if not interrupted or not _has_chunks(cache):
                if cache.exists():
                    io._rmtree(cache)
                _rmdir_empty(cache.parent)
        finally:
            lock.release()
            for d in reversed(created):  # folders this run created, if empty (a failed run's)
                _rmdir_empty(d)
    return folder


def _has_chunks(cache: Path) -> bool:
    return cache.is_dir() and any(cache.rglob(f"*{montecarlo.CHUNK_SUFFIX}"))


def _rmdir_empty(d: Path) -> None:
    try:
        d.rmdir()  # only if empty
    except OSError:
        pass


def run_scenario_file(path: str | Path, *, out_dir: str | Path | None = None, runs: int | None = None,
                      quick: bool = False, force: bool = False, overrides=None,
                      progress=None, set_total=None, **execution) -> Path:
    """Load a scenario file (with ``overrides``: ``key=value`` strings or ``{dotted.path: value}``)
    and run it; returns the result folder."""
    scenario = load_scenario(path, overrides)
    texts = [o.text for o in parse_overrides(overrides)]
    return run_scenario(scenario, source=path, out_dir=out_dir, runs=runs, quick=quick, force=force,
                        progress=progress, set_total=set_total, overrides=texts, **execution)
