"""One run, as the data flow reads: load → compute (sample → covariances → summarize) → write.

The analysis model's ``compute`` does the sampling and the recursions; this module only
expands sweeps, sets where Monte Carlo chunks execute (and the resume cache), times the
run, writes the CSVs, draws the figure *from the written CSVs* and writes the manifest,
all inside an atomic result folder.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import time
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path

import pandas as pd

from netkf_cli import io, montecarlo, sweep
from netkf_cli.errors import ConfigError, ResultExistsError
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


def compute(scenario, ctx: RunContext, source: str | Path | None = None) -> Artefact:
    """Run the scenario's analysis (every sweep point); ConfigErrors get file and line."""
    try:
        if scenario.sweep is None:
            art = scenario.analysis.compute(scenario, ctx)
            _check_artefact(scenario, art)
            return art
        points = sweep.expand(scenario, str(source) if source else None)  # validate all before running
        tables, extras, metas = [], {}, []
        for coords, sc in points:
            art = sc.analysis.compute(sc, ctx)
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


def _check_artefact(scenario, art) -> None:
    if not isinstance(art, Artefact):
        raise TypeError(f"{type(scenario.analysis).__name__}.compute must return an Artefact")


def write_result(scenario, art: Artefact, out: Path, *, force: bool, ctx: RunContext,
                 source: str | Path | None, wall_time: float, execution: dict | None = None) -> Path:
    name = scenario.name
    with io.atomic_folder(out, force=force) as tmp:
        io.write_csv(art.table, tmp / f"{name}.csv")
        for key, df in art.extra_tables.items():
            io.write_csv(df, tmp / f"{name}_{key}.csv")
        for fname, text in art.extra_text.items():
            (tmp / fname).write_text(text, encoding="utf-8")
        tables = {"main": io.read_csv(tmp / f"{name}.csv")}
        for key in art.extra_tables:
            tables[key] = io.read_csv(tmp / f"{name}_{key}.csv")
        fig = sweep.plot(tables, scenario) if scenario.sweep is not None else scenario.analysis.plot(tables, scenario)
        save(fig, tmp / f"{name}.png", dpi=scenario.output.dpi)
        mc = scenario.montecarlo
        manifest = {
            "name": name,
            "source": str(source) if source else None,
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


def run_scenario(scenario, *, source: str | Path | None = None, out_dir: str | Path | None = None,
                 runs: int | None = None, quick: bool = False, force: bool = False,
                 progress: Callable[[int], None] | None = None,
                 set_total: Callable[[int], None] | None = None,
                 add_total: Callable[[int], None] | None = None,
                 executor: str = "serial", jobs: int = 1, scheduler: str | None = None,
                 resume: bool = False) -> Path:
    """Compute and write one scenario. Finished Monte Carlo chunks are kept in
    ``<out>/../.netkf-cache/<scenario hash>/`` until the result is written, so ``resume=True``
    after an interruption reuses them and gives exactly the uninterrupted numbers."""
    ctx = RunContext(runs=runs, quick=quick, progress=progress, set_total=set_total)
    out = Path(out_dir) if out_dir is not None else default_out_dir(scenario)
    if out.exists() and not force:
        raise ResultExistsError(f"{out} already exists; use --force to replace it or --out to choose another folder")
    cache = out.parent / CACHE_DIR / scenario_hash(scenario, runs)
    if cache.exists() and not resume:
        shutil.rmtree(cache, ignore_errors=True)
    t0 = time.perf_counter()
    with montecarlo.execution(executor, jobs, scheduler, cache_dir=cache, progress=progress, add_total=add_total):
        art = compute(scenario, ctx, source)
    folder = write_result(scenario, art, out, force=force, ctx=ctx, source=source,
                          wall_time=time.perf_counter() - t0,
                          execution={"executor": executor, "jobs": jobs, "scheduler": scheduler, "resumed": resume})
    shutil.rmtree(cache, ignore_errors=True)
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
