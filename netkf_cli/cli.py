"""The ``netkf`` command: a thin typer app.

This is the only place where exceptions become messages and exit codes:
1 for bad input (one line per problem, ``file:line dotted.path: message``), 2 for bad usage.
"""

from __future__ import annotations

import functools
import json
import os
import sys
import warnings
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from netkf_cli import __version__
from netkf_cli.errors import ConfigError, NetkfError

app = typer.Typer(
    name="netkf",
    help="Kalman filtering over lossy, delaying and fading networks: scenarios → Monte Carlo + closed-form bounds → CSV + PNG.",
    context_settings={"help_option_names": ["-h", "--help"]},
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
out = Console(soft_wrap=True, width=None if sys.stdout.isatty() else 160)
err = Console(stderr=True, soft_wrap=True)


def fail(exc: NetkfError) -> None:
    """Print a user error as one block and exit 1."""
    if isinstance(exc, ConfigError):
        err.print("[bold red]error:[/] invalid input", highlight=False)
        for p in exc.problems:
            err.print(f"  • {p.render()}", highlight=False, markup=False)
    else:
        err.print(f"[bold red]error:[/] {exc}", highlight=False)
    raise typer.Exit(1)


def user_errors(fn):
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except NetkfError as exc:
            fail(exc)

    return wrapper


def make_progress(quiet: bool) -> Progress:
    return Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
        TextColumn("ETA"), TimeRemainingColumn(), console=err, disable=quiet or not err.is_terminal, transient=True,
    )


def version_callback(value: bool):
    if value:
        out.print(f"netkf {__version__}")
        raise typer.Exit()


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """User-facing warnings (e.g. a scenario the paper's assumptions do not cover) as one line."""
    err.print(f"[yellow]warning:[/] {message}", highlight=False)


@app.callback()
def main(
    version: Annotated[Optional[bool], typer.Option("--version", callback=version_callback, is_eager=True,
                                                    help="Print the version and exit.")] = None,
):
    """netkf — networked Kalman filtering: reproduce the papers, answer design questions."""
    warnings.showwarning = _show_warning


@app.command()
@user_errors
def run(
    config: Annotated[Path, typer.Argument(help="Scenario YAML file.")],
    out_dir: Annotated[Optional[Path], typer.Option("--out", help="Result folder (default: <output.dir>/<name>).")] = None,
    runs: Annotated[Optional[int], typer.Option("--runs", min=1, help="Override the Monte Carlo size.")] = None,
    force: Annotated[bool, typer.Option("--force", help="Replace an existing result folder.")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print a JSON summary instead of text.")] = False,
    jobs: Annotated[Optional[int], typer.Option("--jobs", "-j", min=1, help="Local processes for Monte Carlo chunks (default: all cores).")] = None,
    executor: Annotated[str, typer.Option("--executor", help="local (process pool on --jobs cores) or dask.")] = "local",
    scheduler: Annotated[Optional[str], typer.Option("--scheduler", help="Dask scheduler address, or 'local' for a LocalCluster.")] = None,
    resume: Annotated[bool, typer.Option("--resume", help="Reuse the finished chunks of an interrupted run of the same scenario.")] = False,
):
    """Run a scenario: write <name>.csv, <name>.png and manifest.json into the result folder."""
    from netkf_cli.loader import load_scenario
    from netkf_cli.runner import run_scenario

    if executor not in ("local", "dask"):
        raise typer.BadParameter("must be 'local' or 'dask'", param_hint="--executor")
    if scheduler is not None and executor != "dask":
        raise typer.BadParameter("--scheduler goes with --executor dask", param_hint="--scheduler")
    n_jobs = jobs or os.cpu_count() or 1
    mode = "dask" if executor == "dask" else ("process" if n_jobs > 1 else "serial")
    scenario = load_scenario(config)
    with make_progress(quiet or as_json) as prog:
        task = prog.add_task(f"{scenario.name} (Monte Carlo runs)", total=None)
        folder = run_scenario(
            scenario, source=config, out_dir=out_dir, runs=runs, force=force,
            progress=lambda n: prog.advance(task, n), set_total=lambda n: prog.update(task, total=n),
            add_total=lambda n: prog.update(task, total=(prog.tasks[0].total or 0) + n),
            executor=mode, jobs=n_jobs, scheduler=scheduler or ("local" if executor == "dask" else None),
            resume=resume,
        )
    manifest = json.loads((folder / "manifest.json").read_text())
    if as_json:
        out.print_json(json.dumps({"folder": str(folder), "files": manifest["files"],
                                   "wall_time_s": manifest["wall_time_s"], "meta": manifest["meta"]}))
        return
    conv = manifest["meta"].get("convention")
    out.print(f"[green]✓[/] {scenario.name}: wrote {folder}/ ({', '.join(manifest['files'])}) in {manifest['wall_time_s']:.2f} s"
              + (f"; buffer convention {conv}" if conv else ""), highlight=False)


@app.command()
@user_errors
def validate(
    configs: Annotated[list[Path], typer.Argument(help="Scenario YAML files.")],
):
    """Check scenarios without running them (every problem of every file is reported)."""
    from netkf_cli.loader import load_scenario

    problems = []
    for c in configs:
        try:
            sc = load_scenario(c)
            out.print(f"[green]✓[/] {c}: {sc.name} (analysis {sc.analysis.kind})", highlight=False)
        except ConfigError as exc:
            problems.extend(exc.problems)
    if problems:
        raise ConfigError(problems)


@app.command()
def schema():
    """Print the JSON Schema of a scenario file (for editor completion)."""
    from netkf_cli.scenario import json_schema

    sys.stdout.write(json.dumps(json_schema(), indent=2, ensure_ascii=False) + "\n")


@app.command("list")
def list_kinds():
    """List the channel, estimator and analysis kinds a scenario may use."""
    from netkf_cli.scenario import kinds
    from netkf_cli.spec import AnalysisModel, ChannelModel, EstimatorModel

    for title, base in (("channel", ChannelModel), ("estimator", EstimatorModel), ("analysis", AnalysisModel)):
        out.print(f"[bold]{title} kinds[/]")
        for k, cls in sorted(kinds(base).items()):
            doc = (cls.__doc__ or "").strip().splitlines()[0].replace("``", "") if cls.__doc__ else ""
            out.print(f"  {k:<22} {doc}", highlight=False, markup=False)




@app.command()
@user_errors
def mind(
    M: Annotated[float, typer.Option("--M", help="Error-covariance bound M (a scalar; for n > 1 it means M·I).")],
    eps: Annotated[float, typer.Option("--eps", help="Allowed probability ε of P_k ≰ M.", min=0.0, max=1.0)] = 0.05,
    config: Annotated[Optional[Path], typer.Option("--config", help="Take the system and the delay channel from this scenario.")] = None,
    d: Annotated[Optional[float], typer.Option("--d", help="Poisson mean delay d (default 5, the mean Example 3.10's printed θ values imply).", min=0.0)] = None,
    sensor: Annotated[str, typer.Option("--sensor", help="raw: the sensor sends y_k (Sec. 3, D_s and D_n); smart: it sends its estimate (Sec. 4, D*).")] = "raw",
    convention: Annotated[Optional[str], typer.Option("--convention", help="delay_le_D (default; kept iff delay ≤ D, as the paper's printed numbers) or delay_lt_D (kept iff delay < D, eq. 4).")] = None,
    D_max: Annotated[Optional[int], typer.Option("--D-max", help="Largest buffer you can afford; longer answers count as infeasible.", min=1)] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
):
    """Minimum receive-buffer length D so that Pr[P_k ≤ M] ≥ 1 − ε (Shi, Xie & Murray 2009, Sec. 3.4 and 4).

    Without --config: Example 3.10 (A = 1.4, C = 1, Q = 0.2, R = 0.5) with Poisson delays of
    mean d = 5 — the mean for which the printed θ(7,6) = 0.0313, θ(8,7) = 0.0042,
    θ(9,8) = 0.0003 are reproduced (under the delay_le_D convention).
    """
    from netkf_cli.mind import mind_report

    if sensor not in ("raw", "smart"):
        raise typer.BadParameter("must be 'raw' or 'smart'", param_hint="--sensor")
    if convention not in (None, "delay_le_D", "delay_lt_D"):
        raise typer.BadParameter("must be 'delay_le_D' or 'delay_lt_D'", param_hint="--convention")
    if config is not None and d is not None:
        raise typer.BadParameter("give either --config (its channel sets the delays) or --d, not both", param_hint="--d")
    report = mind_report(M=M, eps=eps, config=config, d=d, sensor=sensor, convention=convention, D_max=D_max)
    if as_json:
        sys.stdout.write(json.dumps(report.as_json(), indent=2, ensure_ascii=False) + "\n")
    else:
        out.print(report.text(), highlight=False, markup=False)


@app.command()
@user_errors
def reproduce(
    topics: Annotated[Optional[list[str]], typer.Argument(help="Topics to run (default: all): shi2009, fading, smoothing, fusion, markov.")] = None,
    quick: Annotated[bool, typer.Option("--quick", help="Small Monte Carlo sizes; tolerances widened by their standard errors.")] = False,
    out_dir: Annotated[Optional[Path], typer.Option("--out", help="Root folder of the results (default: results/, or build/quick-results/ with --quick).")] = None,
    check: Annotated[bool, typer.Option("--check", help="Exit 1 if a check expected to reproduce fails, or a golden CSV moved.")] = False,
    jobs: Annotated[int, typer.Option("--jobs", min=1, help="Artefacts run concurrently on this many local processes.")] = 1,
    report: Annotated[bool, typer.Option("--report/--no-report", help="Write <out>/REPORT.md.")] = True,
    quiet: Annotated[bool, typer.Option("--quiet", "-q")] = False,
):
    """Regenerate every paper artefact (configs/), compare with experiments/<topic>/published.yaml, write a report."""
    from netkf_cli.reproduce import reproduce as do_reproduce

    ok = do_reproduce(topics or [], quick=quick, out_root=out_dir, check=check, jobs=jobs, write_report=report,
                      console=out, quiet=quiet)
    if check and not ok:
        raise typer.Exit(1)


if __name__ == "__main__":  # pragma: no cover
    app()
