"""The ``netkf`` command: a thin typer app.

This is the only place where exceptions become messages and exit codes:
1 for bad input (one line per problem, ``file:line dotted.path: message``), 2 for bad usage.
"""

from __future__ import annotations

import atexit
import contextlib
import errno
import functools
import gc
import json
import math
import os
import shlex
import signal
import sys
import threading
import time
import warnings
from pathlib import Path
from typing import Annotated, Optional

import typer
import yaml
from typer.core import TyperGroup
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from netkf_cli.config import loader
from netkf_cli.app import runner  # (called as loader.x / runner.x: the tests' seams)
from netkf_cli.analysis import references
from netkf_cli.core._version import __version__
from netkf_cli.core.errors import ConfigError, NetkfError, Problem
from netkf_cli.core.tolerances import CRITICAL_BISECTION_TOL, CRITICAL_BISECTION_TOL_MAX, CRITICAL_BISECTION_TOL_MIN
from netkf_cli.config.compat import compatibility, metric_compatibility
from netkf_cli.config.kinds import describe
from netkf_cli.config.loader import attribute, locate, parse_overrides
from netkf_cli.metrics.critical import critical_answer
from netkf_cli.app.mind import mind_report
from netkf_cli.runtime.montecarlo import CHUNK_SUFFIX, stored_runs, usable_cores
from netkf_cli.app.reproduce import reproduce as do_reproduce
from netkf_cli.app.runner import LARGE_RUN_S, ProgressTotals, duration, plan_run
from netkf_cli.config.scenario import json_schema

EXIT_INTERRUPTED = 130  # 128 + SIGINT, the shell convention for a command stopped by Ctrl-C
_STATE: dict = {"debug": False, "t0": None}


def _process_age() -> float | None:
    """Seconds since this process started (Linux ``/proc``), or None."""
    try:
        stat = Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()
        start_ticks = int(stat[19])
        uptime = float(Path("/proc/uptime").read_text().split()[0])
        return max(0.0, uptime - start_ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError):
        return None


def command_started() -> float:
    """``time.perf_counter()`` value at which this command started: the process start when run as
    the ``netkf`` program (so start-up and imports count), else the moment the command was invoked."""
    t0 = _STATE["t0"] if _STATE["t0"] is not None else time.perf_counter()
    argv0 = Path(sys.argv[0]).name if sys.argv else ""
    if argv0 in ("netkf", "cli.py", "__main__.py"):
        age = _process_age()
        if age is not None:
            return min(t0, time.perf_counter() - age)
    return t0


def _report_unexpected(exc: BaseException) -> int:
    """One line for anything that is not a NetkfError; returns the exit code."""
    if isinstance(exc, KeyboardInterrupt):
        err.print("[bold red]interrupted[/] (Ctrl-C): what had finished is kept, nothing is half-written.",
                  highlight=False)
        return EXIT_INTERRUPTED
    if isinstance(exc, MemoryError):
        err.print("[bold red]error:[/] out of memory; reduce montecarlo.chunk, the grid or --jobs", highlight=False)
        return 1
    if isinstance(exc, OSError):
        where = f" {exc.filename}" if getattr(exc, "filename", None) else ""
        full = exc.errno in (errno.ENOSPC, getattr(errno, "EDQUOT", -1))
        what = (f"{exc.strerror or exc}{' writing' + where if where else ''}; the run stopped and nothing of this "
                "run was kept (free some space and run it again)") if full else f"cannot access{where}: {exc.strerror or exc}"
        err.print("[bold red]error:[/] " + escape(what), highlight=False)
        return 1
    err.print("[bold red]error:[/] " + escape(f"internal error ({type(exc).__name__}: {exc}). This is a bug in netkf: "
              "please report it with the scenario; `netkf --debug …` shows the traceback."), highlight=False)
    return 1


def _refuse_non_finite_options(args: list[str]) -> None:
    """``--d inf``, ``--tol nan``: one clear message (exit 1) for every option of every command,
    before click's range checks, which compare NaN falsely ("should be ≤ 0.1")."""
    problems = []
    for i, tok in enumerate(args):
        if tok == "--":
            break
        opt, val = (tok.split("=", 1) if tok.startswith("--") and "=" in tok
                    else (args[i - 1], tok) if i and args[i - 1].startswith("-") and not tok.startswith("--")
                    else (None, None))
        if opt is None or not opt.startswith("-"):
            continue
        try:
            bad = not math.isfinite(float(val))
        except ValueError:
            continue
        if bad:
            problems.append(Problem(opt, f"must be a finite number, got {val}"))
    if problems:
        raise ConfigError(problems)


def _cli_control() -> tuple[type[BaseException], ...]:
    """Exceptions typer/click use for exits and usage errors (exit 2): never turned into messages."""
    kinds: list = [typer.Exit, typer.Abort]
    for mod, names in (("typer.exceptions", ("TyperException",)), ("typer._click.exceptions", ("ClickException",)),
                       ("click.exceptions", ("ClickException", "Exit", "Abort"))):
        try:
            m = __import__(mod, fromlist=list(names))
        except ImportError:
            continue
        kinds += [getattr(m, n) for n in names if hasattr(m, n)]
    return tuple(kinds)


_CLI_CONTROL = _cli_control()


class NetkfGroup(TyperGroup):
    """Every command runs inside one error layer: user errors (NetkfError) become one block and
    exit 1; OS errors, interrupts and bugs one line each; a traceback only with ``--debug``.

    At exit the command's objects are frozen for the garbage collector: the interpreter's last collection
    then skips what the process is about to free anyway (the modules, numba's and matplotlib's caches, the
    results), 0.35 -> 0.05 s at the end of ``netkf reproduce --quick`` (2026-12-06). Exit handlers still run."""

    def invoke(self, ctx):
        if not _STATE.get("freeze_at_exit"):
            _STATE["freeze_at_exit"] = atexit.register(gc.freeze)
        try:
            _refuse_non_finite_options([*getattr(ctx, "_protected_args", []), *ctx.args])
            return super().invoke(ctx)
        except _CLI_CONTROL:
            raise
        except NetkfError as exc:
            if _STATE["debug"]:
                raise
            _print_error(exc)
            raise typer.Exit(1) from None
        except BaseException as exc:  # noqa: BLE001 - the one place exceptions become messages
            if _STATE["debug"] or isinstance(exc, (SystemExit, GeneratorExit)):
                raise
            raise typer.Exit(_report_unexpected(exc)) from None


app = typer.Typer(
    cls=NetkfGroup,
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
    _print_error(exc)
    raise typer.Exit(1)


def _print_error(exc: NetkfError) -> None:
    if isinstance(exc, ConfigError):
        err.print("[bold red]error:[/] invalid input", highlight=False)
        for p in exc.problems:
            err.print(f"  • {p.render()}", highlight=False, markup=False)
    else:
        err.print("[bold red]error:[/] " + escape(str(exc)), highlight=False)


def user_errors(fn):
    """Kept for commands that use it; the group's error layer (:class:`NetkfGroup`) does the work."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        return fn(*args, **kwargs)

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


_SEEN_WARNINGS: set[str] = set()


def _show_warning(message, category, filename, lineno, file=None, line=None):
    """User-facing warnings (e.g. a scenario the paper's assumptions do not cover) as one line,
    each distinct message once per command (numpy's overflow warnings would repeat per chunk)."""
    text = str(message)
    if text in _SEEN_WARNINGS:
        return
    _SEEN_WARNINGS.add(text)
    if issubclass(category, RuntimeWarning) and "encountered" in text:
        text = f"numerical {text} (shown once; typically runs whose covariance diverged)"
    err.print("[yellow]warning:[/] " + escape(text), highlight=False)


@app.callback()
def main(
    version: Annotated[Optional[bool], typer.Option("--version", callback=version_callback, is_eager=True,
                                                    help="Print the version and exit.")] = None,
    debug: Annotated[bool, typer.Option("--debug", help="Show the full traceback of any error.")] = False,
):
    """netkf — networked Kalman filtering: reproduce the papers, answer design questions."""
    _STATE["t0"] = time.perf_counter()
    _STATE["debug"] = debug
    _SEEN_WARNINGS.clear()
    warnings.showwarning = _show_warning


def _split_overrides(args: list[Path] | list[str] | None) -> tuple[list[Path], list[str]]:
    """Files and ``key=value`` / ``~key`` overrides among positional arguments (an existing file
    whose name holds ``=`` is a file)."""
    files, ovs = [], []
    for a in args or []:
        t = str(a)
        if ("=" in t or t.startswith("~")) and not Path(t).is_file():
            ovs.append(t)
        else:
            files.append(Path(t))
    return files, ovs


@app.command()
@user_errors
def run(
    config: Annotated[Path, typer.Argument(help="Scenario YAML file.")],
    overrides: Annotated[Optional[list[str]], typer.Argument(
        help="Field overrides key=value with dotted paths, e.g. channel.arrival=0.6 montecarlo.runs=2e5 "
             "'system.A=[[1.1,0],[0,0.9]]' (values read as YAML 1.2); ~key deletes a key.", show_default=False)] = None,
    out_dir: Annotated[Optional[Path], typer.Option("--out", help="Result folder (default: <output.dir>/<name>).")] = None,
    runs: Annotated[Optional[int], typer.Option("--runs", min=1, help="Override the Monte Carlo size.")] = None,
    force: Annotated[bool, typer.Option("--force", help="Replace an existing result folder.")] = False,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
    as_json: Annotated[bool, typer.Option("--json", help="Print a JSON summary instead of text.")] = False,
    jobs: Annotated[Optional[int], typer.Option("--jobs", "-j", min=1, help="Local processes for Monte Carlo chunks (default and at most: the cores).")] = None,
    executor: Annotated[str, typer.Option("--executor", help="local (process pool on --jobs cores) or dask.")] = "local",
    scheduler: Annotated[Optional[str], typer.Option("--scheduler", help="Dask scheduler address, or 'local' for a LocalCluster.")] = None,
    resume: Annotated[bool, typer.Option("--resume", help="Reuse the finished chunks of an interrupted run of the identical scenario.")] = False,
    dry_run: Annotated[bool, typer.Option("--dry-run", help="Print the resolved scenario, its size, ETA, executor and folder; run and write nothing.")] = False,
    yes: Annotated[bool, typer.Option("--yes", "-y", help="Accept a run count above montecarlo.max_runs.")] = False,
):
    """Run a scenario: write <name>.csv, <name>.png and manifest.json into the result folder."""
    if executor not in ("local", "dask"):
        raise typer.BadParameter("must be 'local' or 'dask'", param_hint="--executor")
    if scheduler is not None and executor != "dask":
        raise typer.BadParameter("--scheduler goes with --executor dask", param_hint="--scheduler")
    extra_files, overrides = _split_overrides(overrides)
    if extra_files:
        raise typer.BadParameter(f"one scenario file per run; {extra_files[0]} is not a key=value override",
                                 param_hint="OVERRIDES")
    cores = usable_cores()
    n_jobs = jobs or cores
    remote = executor == "dask" and scheduler not in (None, "local")
    if n_jobs > cores and not remote:
        err.print(f"[yellow]note:[/] --jobs {n_jobs} capped at {cores}, the cores of this machine (more processes "
                  f"would only add memory: each holds its own numpy, numba …)", highlight=False)
        n_jobs = cores
    mode = "dask" if executor == "dask" else ("process" if n_jobs > 1 else "serial")
    scenario = loader.load_scenario(config, overrides)
    try:
        plan = plan_run(scenario, out_dir=out_dir, runs=runs, force=force, executor=mode, jobs=n_jobs, yes=yes)
    except ConfigError as exc:  # a field's problem: its file and line (or the override that set it)

        fields = ConfigError([p for p in exc.problems if not p.path.startswith("-")])
        options = [p for p in exc.problems if p.path.startswith("-")]
        located = locate(fields, config).problems if fields.problems else []
        raise ConfigError(attribute(located, parse_overrides(overrides)) + options) from None
    out_path, cache = plan.out, plan.cache
    if dry_run:
        _print_plan(plan, config, overrides, as_json)
        return
    if plan.eta_s > LARGE_RUN_S:
        err.print(f"[yellow]large run:[/] {scenario.name} is about {plan.run_steps:.2g} run-steps (Monte Carlo runs × "
                  f"horizon{' × sweep points' if scenario.sweep is not None else ''}); rough ETA {duration(plan.eta_s)} "
                  f"on {n_jobs} process{'es' if n_jobs > 1 else ''}. Ctrl-C stops it keeping finished chunks; "
                  f"--resume continues.", highlight=False)
    info: dict = {}
    with _terminate_as_interrupt(), make_progress(quiet or as_json) as prog:
        task = prog.add_task(f"{scenario.name} (Monte Carlo runs)", total=None)
        totals = ProgressTotals(lambda t: prog.update(task, total=t))
        try:
            folder = runner.run_scenario(
                scenario, source=config, out_dir=out_dir, runs=runs, force=force,
                progress=lambda n: prog.advance(task, n), set_total=totals.set_total, add_total=totals.add_total,
                executor=mode, jobs=n_jobs, scheduler=scheduler or ("local" if executor == "dask" else None),
                resume=resume, yes=yes, overrides=overrides, started=command_started(), info=info,
                notify=lambda msg: err.print("[yellow]note:[/] " + escape(msg), highlight=False),
            )
        except KeyboardInterrupt:
            # a worker stores its chunk before the parent hears of it: the store is the truth of what --resume reuses
            done = max(int(prog.tasks[0].completed), stored_runs(cache))
            again = " ".join(["netkf run", _quote(config), *map(_quote, overrides)]
                             + (["--out", _quote(out_dir)] if out_dir else []) + (["--runs", str(runs)] if runs else [])
                             + (["--yes"] if yes else []) + ["--resume"])
            what = (f"{done:,} of {totals.total:,} Monte Carlo runs finished" if totals.total and done
                    else "no Monte Carlo run had finished")
            kept = (f"; their chunks are kept in {cache}/ — `{again}` continues from there"
                    if cache.is_dir() and any(cache.rglob(f"*{CHUNK_SUFFIX}")) else "; nothing was kept, rerun to start again")
            err.print("[bold red]interrupted:[/] " + escape(f"{what}, {out_path} not written{kept}"), highlight=False)
            raise typer.Exit(EXIT_INTERRUPTED) from None
    manifest = json.loads((folder / "manifest.json").read_text())
    reused = (info.get("resume") or {}).get("chunks_reused", 0)
    if as_json:
        out.print_json(json.dumps({"folder": str(folder), "files": manifest["files"], "unchanged": info.get("unchanged", False),
                                   "command_time_s": manifest.get("command_time_s"), "compute_time_s": manifest["wall_time_s"],
                                   "chunks_reused": reused, "meta": manifest["meta"]}))
        return
    conv = manifest["meta"].get("convention")
    tail = (f"; buffer convention {conv}" if conv else "") + (f"; {reused} chunk{'s' if reused != 1 else ''} reused "
                                                               f"from the resume cache" if resume else "")
    if info.get("unchanged"):
        out.print(f"[green]✓[/] {scenario.name}: {folder}/ already holds this exact result (same scenario, "
                  f"byte-identical {', '.join(f for f in manifest['files'] if f != 'manifest.json')}); left untouched, "
                  f"its manifest still records how it was made ({manifest.get('created')})" + tail, highlight=False)
        return
    out.print(f"[green]✓[/] {scenario.name}: wrote {folder}/ ({', '.join(manifest['files'])}) in "
              f"{manifest.get('command_time_s', manifest['wall_time_s']):.2f} s (compute {manifest['wall_time_s']:.2f} s)"
              + tail, highlight=False)


def _quote(x) -> str:
    return shlex.quote(str(x))


def _print_plan(plan, config: Path, overrides: list[str], as_json: bool) -> None:
    """``--dry-run``: what the run would do, from the same checks the run makes first."""
    sc = plan.scenario
    resolved = sc.model_dump(mode="json", by_alias=True, exclude_none=True)
    info = plan.as_json()
    if as_json:
        sys.stdout.write(json.dumps({"scenario": resolved, "overrides": overrides, **info}, indent=2,
                                    ensure_ascii=False) + "\n")
        return
    head = f"# netkf run {config} --dry-run" + (f" (overrides: {' '.join(overrides)})" if overrides else "")
    out.print(head + "\n" + yaml.safe_dump(resolved, sort_keys=False, allow_unicode=True, default_flow_style=None,
                                           width=100).rstrip(), highlight=False, markup=False)
    mc = sc.montecarlo
    pts = f" × {plan.points} sweep points" if plan.points > 1 else ""
    lines = [
        f"size:     {plan.runs:,} Monte Carlo runs × {mc.horizon} steps{pts} ≈ {plan.run_steps:.3g} run-steps; "
        f"{plan.chunks:,} chunk{'s' if plan.chunks != 1 else ''} of ≤ {mc.chunk:,} runs per Monte Carlo series",
        f"ETA:      about {duration(plan.eta_s)} (rough: {plan.jobs} process{'es' if plan.jobs > 1 else ''} at ~1e7 "
        f"run-steps/s each)",
        f"executor: {plan.executor}" + (f", {plan.jobs} processes" if plan.executor != "serial" else ""),
        f"writes:   {plan.out}/" + (" (replacing the result there)" if plan.replaces else "")
        + f"; resume cache {plan.cache}/ while it runs",
        "dry run: nothing was computed or written.",
    ]
    out.print("\n".join(lines), highlight=False, markup=False)


@contextlib.contextmanager
def _terminate_as_interrupt():
    """Inside this block ``kill PID`` (SIGTERM) stops a run like Ctrl-C: locks released, finished
    chunks kept for --resume, one line. (Pool workers reset SIGTERM: netkf_cli.runtime.workers.)"""
    def handler(signum, frame):
        raise KeyboardInterrupt

    previous = None
    if threading.current_thread() is threading.main_thread():
        try:
            if signal.getsignal(signal.SIGTERM) == signal.SIG_DFL:
                previous = signal.signal(signal.SIGTERM, handler)
        except (ValueError, OSError):  # pragma: no cover
            previous = None
    try:
        yield
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


@app.command()
@user_errors
def validate(
    configs: Annotated[list[str], typer.Argument(help="Scenario YAML files, then optional key=value overrides "
                                                      "applied to each (as `netkf run`).")],
):
    """Check scenarios without running them (every problem of every file is reported)."""
    files, overrides = _split_overrides(configs)
    if not files:
        raise typer.BadParameter("give at least one scenario file", param_hint="CONFIGS")
    problems = []
    for c in files:
        try:
            sc = loader.load_scenario(c, overrides)  # (every sweep point is validated too, as `run` does first)
            out.print(f"[green]✓[/] {c}: {sc.name} (analysis {sc.analysis.kind})", highlight=False)
        except ConfigError as exc:
            problems.extend(exc.problems)
    if problems:
        raise ConfigError(problems)


@app.command()
def schema():
    """Print the JSON Schema of a scenario file (for editor completion)."""
    sys.stdout.write(json.dumps(json_schema(), indent=2, ensure_ascii=False) + "\n")


@app.command("list")
@user_errors
def list_kinds(
    kind: Annotated[Optional[str], typer.Argument(help="Show one kind in full (its fields), e.g. `netkf list kf`.")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Machine-readable output.")] = False,
):
    """List the channel, estimator and analysis kinds, their fields and which combine."""
    info = describe(compatibility(), metric_compatibility())
    if kind == "references":
        info = {}
    elif kind is not None:
        found = {fam: entries[kind] for fam, entries in info.items() if kind in entries}
        if not found:
            known = sorted(k for entries in info.values() for k in entries)
            raise NetkfError(f"unknown kind {kind!r}; known kinds: {', '.join(known)}")
        info = {fam: {kind: e} for fam, e in found.items()}
    if as_json:
        if kind is None or kind == "references":
            info = {**info, "references": references.describe()}
        sys.stdout.write(json.dumps(info, indent=2, ensure_ascii=False) + "\n")
        return
    for fam, entries in info.items():
        out.print(f"[bold]{fam} kinds[/]")
        for k, e in entries.items():
            out.print(f"  {k:<22} {e['doc']}", highlight=False, markup=False)
            if fam == "channel":
                out.print(f"  {'':<22} trace: {', '.join(e['trace']) or '—'}; estimators: "
                          f"{_with_conditions(e['estimators'], e.get('conditions', {}))}", highlight=False, markup=False)
            elif fam == "estimator":
                out.print(f"  {'':<22} accepts: {', '.join(e['accepts']) or '—'}; channels: "
                          f"{_with_conditions(e['channels'], e.get('conditions', {}))}", highlight=False, markup=False)
            if fam in ("channel", "estimator") and e.get("conditions") and (kind is not None or len(entries) == 1):
                for other, cond in e["conditions"].items():
                    a, b = (other, k) if fam == "channel" else (k, other)
                    out.print(f"      {a} on {b}: {cond}", highlight=False, markup=False)
                if e.get("quantities"):
                    out.print(f"  {'':<22} reports (analysis.quantity): {'; '.join(e['quantities'].values())}",
                              highlight=False, markup=False)
            elif e.get("generic"):
                out.print(f"  {'':<22} generic metric: {e['works_with']}", highlight=False, markup=False)
                if kind is not None or len(entries) == 1:
                    for other, cond in e.get("conditions", {}).items():
                        out.print(f"      {k} with {other}: {cond}", highlight=False, markup=False)
                    for other, why in e.get("refused", {}).items():
                        out.print(f"      {k} refuses {other}: {why}", highlight=False, markup=False)
                    for other, why in e.get("unchecked", {}).items():
                        out.print(f"      {k} with {other}: not checked ({why})", highlight=False, markup=False)
            if kind is not None or len(entries) == 1:
                for f in e["fields"]:
                    out.print(f"      {f['name']:<14} {f['type']:<28} default {f['default']:<14} {f['description']}",
                              highlight=False, markup=False)
    if kind is None or kind == "references":
        out.print("[bold]closed-form references[/] " + escape("(a generic metric's `references: [name, …]`: rows "
                                                              "with source = closed_form beside the Monte Carlo)"))
        for name, doc in references.describe().items():
            out.print(f"  {name:<22} {doc}", highlight=False, markup=False)
    if kind is None:
        out.print("* combines on some systems only; `netkf list KIND` shows a kind's fields and those conditions. "
                  "(Computed by running the checks `netkf validate` makes on representative systems.)", highlight=False)


def _with_conditions(kinds: list[str], conditions: dict) -> str:
    return ", ".join(k + ("*" if k in conditions else "") for k in kinds) or "—"


@app.command()
@user_errors
def mind(
    M: Annotated[float, typer.Option("--M", help="Error-covariance bound M (a scalar; for n > 1 it means M·I).")],
    eps: Annotated[float, typer.Option("--eps", help="Allowed probability ε of P_k ≰ M (in [0, 1]).")] = 0.05,
    config: Annotated[Optional[Path], typer.Option("--config", help="Take the system and the delay channel from this scenario.")] = None,
    d: Annotated[Optional[float], typer.Option("--d", help="Poisson mean delay d ≥ 0 (default 5, the mean Example 3.10's printed θ values imply).")] = None,
    sensor: Annotated[str, typer.Option("--sensor", help="raw: the sensor sends y_k (Sec. 3, D_s and D_n); smart: it sends its estimate (Sec. 4, D*).")] = "raw",
    convention: Annotated[Optional[str], typer.Option("--convention", help="delay_le_D (default; kept iff delay ≤ D, as the paper's printed numbers) or delay_lt_D (kept iff delay < D, eq. 4).")] = None,
    D_max: Annotated[Optional[int], typer.Option("--D-max", help="Largest buffer you can afford; a longer minimum is not offered (feasible: false), but reported as above the cap with its value (reason: above_D_max).", min=1)] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
):
    """Minimum receive-buffer length D so that Pr[P_k ≤ M] ≥ 1 − ε (Shi, Xie & Murray 2009, Sec. 3.4 and 4).

    Without --config: Example 3.10 (A = 1.4, C = 1, Q = 0.2, R = 0.5) with Poisson delays of
    mean d = 5 — the mean for which the printed θ(7,6) = 0.0313, θ(8,7) = 0.0042,
    θ(9,8) = 0.0003 are reproduced (under the delay_le_D convention).
    """
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
def critical(
    config: Annotated[Optional[Path], typer.Option("--config", help="Take the system (and the channel, if any) from this scenario.")] = None,
    arrival: Annotated[Optional[float], typer.Option("--arrival", help="Judge i.i.d. arrivals at this rate λ (overrides the scenario's channel).", min=0.0, max=1.0)] = None,
    tol: Annotated[float, typer.Option("--tol", help="Bisection tolerance on λ_max.", min=CRITICAL_BISECTION_TOL_MIN,
                                       max=CRITICAL_BISECTION_TOL_MAX)] = CRITICAL_BISECTION_TOL,
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object.")] = False,
):
    """Critical arrival rate λ_c (Sinopoli et al. 2004): λ_min ≤ λ_c ≤ λ_max, exact where proven, E[P] bounds.

    Without --config: Example 3.10 of Shi, Xie & Murray 2009 (A = 1.4, C = 1, Q = 0.2, R = 0.5), as `netkf mind`.
    """
    scenario = where = None
    if config is not None:
        scenario = loader.load_scenario(config)
        where = functools.partial(locate, path=config)
    answer = critical_answer(config=config, scenario=scenario, locate=where, arrival=arrival, tol=tol)
    if as_json:
        sys.stdout.write(json.dumps(answer.as_json(), indent=2, ensure_ascii=False) + "\n")
    else:
        out.print(answer.text(), highlight=False, markup=False)


@app.command()
@user_errors
def reproduce(
    topics: Annotated[Optional[list[str]], typer.Argument(help="Topics to run (default: all): critical, fading, fusion, markov, shi2009, smoothing (the folders of configs/; its top-level configs are shi2009).")] = None,
    quick: Annotated[bool, typer.Option("--quick", help="Small Monte Carlo sizes; tolerances widened by their standard errors.")] = False,
    out_dir: Annotated[Optional[Path], typer.Option("--out", help="Root folder of the results (default: results/, or build/quick-results/ with --quick).")] = None,
    check: Annotated[bool, typer.Option("--check", help="Exit 1 if a check expected to reproduce fails, or a golden CSV moved.")] = False,
    jobs: Annotated[int, typer.Option("--jobs", min=1, help="Artefacts run concurrently on this many local processes.")] = 1,
    report: Annotated[bool, typer.Option("--report/--no-report", help="Write <out>/REPORT.md.")] = True,
    quiet: Annotated[bool, typer.Option("--quiet", "-q")] = False,
    allow_dirty: Annotated[bool, typer.Option("--allow-dirty", help="Write into the repository's results/ even with uncommitted changes.")] = False,
):
    """Regenerate every paper artefact (configs/), compare with experiments/<topic>/published.yaml, write a report."""
    ok = do_reproduce(topics or [], quick=quick, out_root=out_dir, check=check, jobs=jobs, write_report=report,
                      console=out, quiet=quiet, allow_dirty=allow_dirty)
    if check and not ok:
        raise typer.Exit(1)


if __name__ == "__main__":  # pragma: no cover
    app()
