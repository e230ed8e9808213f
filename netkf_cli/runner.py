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
from dataclasses import replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pandas as pd

from netkf_cli import io, montecarlo, sweep
from netkf_cli.errors import ConfigError
from netkf_cli.loader import load_scenario, locate
from netkf_cli.plotting import save
from netkf_cli.recipes.base import Artefact, RunContext

CACHE_DIR = ".netkf-cache"


def default_out_dir(scenario) -> Path:
    return Path(scenario.output.dir) / scenario.name


def scenario_hash(scenario, runs: int | None) -> str:
    """Hash of the resolved scenario (and the run-size override): the resume key."""
    blob = json.dumps({"scenario": scenario.model_dump(mode="json"), "runs": runs}, sort_keys=True)
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
    try:
        if scenario.sweep is None:
            art = scenario.analysis.compute(scenario, ctx)
            _check_artefact(scenario, art)
            return art
        points = sweep.expand(scenario, str(source) if source else None)  # validate all before running
        tables, extras, metas = [], {}, []
        done_total = 0  # progress units declared by the points already finished
        for coords, sc in points:
            declared = [0]

            def point_total(n: int, _d=declared, _base=done_total) -> None:
                _d[0] = n
                ctx.total(_base + n)

            art = sc.analysis.compute(sc, replace(ctx, set_total=point_total if ctx.set_total else None))
            done_total += declared[0]
            _check_artefact(sc, art)
            tables.append(sweep.add_coords(art.table, coords))
            for k, df in art.extra_tables.items():
                extras.setdefault(k, []).append(sweep.add_coords(df, coords))
            metas.append({"point": coords, **art.meta})
        return Artefact(pd.concat(tables, ignore_index=True),
                        meta={"sweep": {"mode": scenario.sweep.mode, "axes": scenario.sweep.axes}, "points": metas},
                        extra_tables={k: pd.concat(v, ignore_index=True) for k, v in extras.items()})
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


def _check_artefact(scenario, art) -> None:
    if not isinstance(art, Artefact):
        raise TypeError(f"{type(scenario.analysis).__name__}.compute must return an Artefact")


def write_result(scenario, art: Artefact, out: Path, *, force: bool, ctx: RunContext,
                 source: str | Path | None, wall_time: float, execution: dict | None = None) -> Path:
    name = scenario.name
    with io.atomic_folder(out, force=force, scenario_hash=scenario_hash(scenario, ctx.runs),
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
        manifest = {
            "name": name,
            "written_by": io.WRITTEN_BY,
            "source": io.display_path(source),
            "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "wall_time_s": round(wall_time, 3),
            "scenario": scenario.model_dump(mode="json", by_alias=True),
            "scenario_hash": scenario_hash(scenario, ctx.runs),
            "montecarlo": {"runs": ctx.mc_runs(scenario), "runs_in_scenario": mc.runs, "seed": mc.seed,
                           "chunk": mc.chunk, "quick": ctx.quick,
                           "stream_layout": "chunk i uses SeedSequence(seed, spawn_key=(i,))"},
            "execution": execution or {"executor": "serial", "jobs": 1},
            "meta": art.meta,
            "files": sorted(p.name for p in tmp.iterdir()) + ["manifest.json"],
            "versions": io.versions(),
            "git_commit": io.git_commit(),
        }
        io.write_json(manifest, tmp / "manifest.json")
    return out


def result_paths(scenario, out_dir: str | Path | None = None, runs: int | None = None) -> tuple[Path, Path]:
    """``(result folder, resume cache folder)`` of a run."""
    out = Path(out_dir) if out_dir is not None else default_out_dir(scenario)
    return out, out.parent / CACHE_DIR / scenario_hash(scenario, runs)


def work_size(scenario, runs: int | None = None, quick: bool = False) -> int:
    """Rough size of a run in run-steps: Monte Carlo runs × horizon × sweep points (for the
    up-front warning on large runs; recipes with several series take a small multiple of it)."""
    mc = scenario.montecarlo
    n = int(runs or (mc.quick_size() if quick else mc.runs))
    points = 1
    if scenario.sweep is not None:
        sizes = [len(v) for v in scenario.sweep.axes.values()] or [1]
        points = max(sizes) if scenario.sweep.mode == "zip" else int(np.prod(sizes, dtype=float))
    return int(min(n * mc.horizon * points, 2**62))


def run_scenario(scenario, *, source: str | Path | None = None, out_dir: str | Path | None = None,
                 runs: int | None = None, quick: bool = False, force: bool = False,
                 progress: Callable[[int], None] | None = None,
                 set_total: Callable[[int], None] | None = None,
                 add_total: Callable[[int], None] | None = None,
                 executor: str = "serial", jobs: int = 1, scheduler: str | None = None,
                 resume: bool = False) -> Path:
    """Compute and write one scenario. Finished Monte Carlo chunks are kept in
    ``<out>/../.netkf-cache/<scenario hash>/`` until the result is written, so ``resume=True``
    after an interruption reuses them and gives exactly the uninterrupted numbers.

    Before any work: the result folder must be writable and replaceable (:func:`io.check_target`:
    an existing folder is replaced only if netkf wrote it and the scenario is the same, or with
    ``force``); the folder and the cache are locked for the whole run (a concurrent run into the
    same folder or cache gets :class:`BusyError`); leftovers of killed runs are cleaned.
    """
    ctx = RunContext(runs=runs, quick=quick, progress=progress, set_total=set_total)
    out, cache = result_paths(scenario, out_dir, runs)
    io.check_target(out, force=force, scenario_hash=scenario_hash(scenario, runs),
                    same=lambda man: same_scenario(man, scenario, runs))
    io.make_parent(out)
    keep_cache = True
    try:
        with io.FileLock(out, "result folder"), io.FileLock(cache, "resume cache"):
            io.clean_leftovers(out.parent)
            if cache.exists() and not resume:
                io._rmtree(cache)
            t0 = time.perf_counter()
            try:
                with montecarlo.execution(executor, jobs, scheduler, cache_dir=cache, progress=progress,
                                          add_total=add_total) as ex:
                    art = compute(scenario, ctx, source)
                    where = ex.report()  # where the chunks really ran (tested: a promise in the manifest)
                folder = write_result(scenario, art, out, force=force, ctx=ctx, source=source,
                                      wall_time=time.perf_counter() - t0,
                                      execution={"executor": executor, "jobs": jobs, "scheduler": scheduler,
                                                 "resumed": resume, "chunks_ran": where})
            except ConfigError:
                keep_cache = False  # the scenario must change: its chunks can never be resumed
                raise
            keep_cache = False
    finally:
        if not keep_cache and cache.exists():
            io._rmtree(cache)
        try:
            cache.parent.rmdir()  # only if empty
        except OSError:
            pass
    return folder


def run_scenario_file(path: str | Path, *, out_dir: str | Path | None = None, runs: int | None = None,
                      quick: bool = False, force: bool = False, overrides: dict | None = None,
                      progress=None, set_total=None, **execution) -> Path:
    """Load a scenario file and run it; returns the result folder."""
    scenario = load_scenario(path, overrides)
    return run_scenario(scenario, source=path, out_dir=out_dir, runs=runs, quick=quick, force=force,
                        progress=progress, set_total=set_total, **execution)
