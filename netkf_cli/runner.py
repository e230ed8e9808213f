"""One run, as the data flow reads: load → compute (sample → covariances → summarize) → write.

The analysis model's ``compute`` does the sampling and the recursions; this module only
times it, writes the CSVs, draws the figure *from the written CSVs* and the manifest, all
inside an atomic result folder.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path

from netkf_cli import io
from netkf_cli.errors import ConfigError
from netkf_cli.loader import load_scenario, locate
from netkf_cli.plotting import save
from netkf_cli.recipes.base import Artefact, RunContext


def default_out_dir(scenario, source: Path | None = None) -> Path:
    return Path(scenario.output.dir) / scenario.name


def compute(scenario, ctx: RunContext, source: str | Path | None = None) -> Artefact:
    """Run the scenario's analysis; ConfigErrors get the file and line of the field they name."""
    try:
        art = scenario.analysis.compute(scenario, ctx)
    except ConfigError as exc:
        if source is not None:
            raise locate(exc, source) from None
        raise
    if not isinstance(art, Artefact):
        raise TypeError(f"{type(scenario.analysis).__name__}.compute must return an Artefact")
    return art


def write_result(scenario, art: Artefact, out: Path, *, force: bool, ctx: RunContext,
                 source: str | Path | None, wall_time: float) -> Path:
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
        fig = scenario.analysis.plot(tables, scenario)
        save(fig, tmp / f"{name}.png", dpi=scenario.output.dpi)
        mc = scenario.montecarlo
        manifest = {
            "name": name,
            "source": str(source) if source else None,
            "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "wall_time_s": round(wall_time, 3),
            "scenario": scenario.model_dump(mode="json"),
            "montecarlo": {"runs": ctx.mc_runs(scenario), "runs_in_scenario": mc.runs, "seed": mc.seed,
                           "chunk": mc.chunk, "quick": ctx.quick,
                           "stream_layout": "chunk i uses SeedSequence(seed, spawn_key=(i,))"},
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
                 set_total: Callable[[int], None] | None = None) -> Path:
    ctx = RunContext(runs=runs, quick=quick, progress=progress, set_total=set_total)
    out = Path(out_dir) if out_dir is not None else default_out_dir(scenario)
    if out.exists() and not force:
        from netkf_cli.errors import ResultExistsError

        raise ResultExistsError(f"{out} already exists; use --force to replace it or --out to choose another folder")
    t0 = time.perf_counter()
    art = compute(scenario, ctx, source)
    return write_result(scenario, art, out, force=force, ctx=ctx, source=source,
                        wall_time=time.perf_counter() - t0)


def run_scenario_file(path: str | Path, *, out_dir: str | Path | None = None, runs: int | None = None,
                      quick: bool = False, force: bool = False, overrides: dict | None = None,
                      progress=None, set_total=None) -> Path:
    """Load a scenario file and run it; returns the result folder."""
    scenario = load_scenario(path, overrides)
    return run_scenario(scenario, source=path, out_dir=out_dir, runs=runs, quick=quick, force=force,
                        progress=progress, set_total=set_total)
