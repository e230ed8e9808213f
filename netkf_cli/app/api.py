"""Python API: load a scenario (YAML file, YAML text or a dict), run it, get DataFrames and the figure.

    >>> from netkf_cli import load, run
    >>> sc = load({"name": "demo", "system": {"A": 1.2, "C": 1, "Q": 1, "R": 1},
    ...            "channel": {"kind": "bernoulli", "arrival": 0.8}, "estimator": {"kind": "kf"},
    ...            "analysis": {"kind": "mean_vs_time"}, "montecarlo": {"runs": 2000, "horizon": 50}})
    >>> res = run(sc)                       # nothing is written unless out= is given
    >>> res.table.head()                    # tidy pandas DataFrame (the CSV)
    >>> res.figure.savefig("demo.png")      # the matplotlib figure
    >>> run(sc, overrides={"channel.arrival": 0.6, "montecarlo.runs": 500})   # as `netkf run FILE key=value`

Every argument is checked as strictly as a YAML scenario, and every refusal is a
:class:`netkf_cli.core.errors.ConfigError` naming the argument (``arrivals``, ``runs``, ``overrides``
…) or the dotted field path, as on the command line:

* ``arrivals`` replays a recorded 0/1 arrival sequence instead of the scenario's channel: shape
  ``(horizon,)`` (one stream) or ``(horizon, streams)``; ``delays`` replays recorded delays
  (integers ≥ 0 in steps, ``-1`` for a packet that never arrived) the same way;
* ``runs`` is an integer ≥ 1 (``montecarlo.max_runs`` applies, ``yes=True`` lifts it);
* ``overrides`` are ``key=value`` strings (the command line's grammar) or ``{dotted.path: value}``.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from netkf_cli.core.lazy import pandas as pd

from netkf_cli.runtime import montecarlo, plotting
from netkf_cli.app import runner
from netkf_cli.config import sweep
from netkf_cli.channels.trace_file import TraceChannel
from netkf_cli.config.compat import check_scenario
from netkf_cli.core.errors import ConfigError, Problem
from netkf_cli.config.loader import _plain, apply_overrides, load_scenario, load_scenario_text, parse_overrides, validate_data
from netkf_cli.recipes.base import RunContext
from netkf_cli.config.scenario import ScenarioBase


@dataclass
class Result:
    """What one run produced: the main table, every extra table, the figure, the manifest meta."""

    table: pd.DataFrame
    tables: dict[str, pd.DataFrame] = field(default_factory=dict)
    figure: Any = None
    meta: dict = field(default_factory=dict)
    folder: Path | None = None


def _bad(arg: str, message: str) -> ConfigError:
    return ConfigError([Problem(arg, message)])


def _got(x: Any) -> str:
    r = repr(x)
    return f"{type(x).__name__} {r if len(r) <= 60 else r[:57] + '...'}"


def _is_scenario(x: Any) -> bool:
    return isinstance(x, ScenarioBase)


def load(source: str | Path | dict, overrides=None):
    """A validated Scenario from a YAML file path, YAML text (containing a newline) or a dict, after
    ``overrides``. The same checks as ``netkf validate``, with the same messages."""
    if _is_scenario(source):
        return with_overrides(source, overrides) if overrides else source
    if isinstance(source, dict):
        ovs = parse_overrides(overrides)
        data = _plain(source)
        if ovs:
            data = apply_overrides(data, ovs)
        return validate_data(data, None, {}, None, ovs)
    if isinstance(source, str) and "\n" in source:
        return load_scenario_text(source, None, overrides)
    if isinstance(source, (str, Path)) and not isinstance(source, bool):
        if isinstance(source, str) and not Path(source).exists() and any(c in source for c in ":{"):
            raise _bad("source", f"load() reads a str without a newline as a file path, and there is no file "
                                 f"{source[:60]!r}; YAML text must contain a newline (or pass a dict)")
        return load_scenario(source, overrides)
    raise _bad("source", f"load() takes a scenario: a dict, a YAML file path (str or pathlib.Path) or YAML text "
                         f"(a str containing a newline); got {_got(source)}")


def with_overrides(scenario, overrides):
    """The scenario with ``overrides`` applied and validated again (as ``netkf run FILE key=value``)."""
    ovs = parse_overrides(overrides)
    if not ovs:
        return scenario
    data = scenario.model_dump(mode="json", by_alias=True, exclude_none=True)
    return validate_data(apply_overrides(data, ovs), None, {}, None, ovs)


def _check_int(arg: str, v: Any, low: int = 1) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise _bad(arg, f"must be an integer ≥ {low}, got {_got(v)}")
    if isinstance(v, (float, np.floating)) and (not math.isfinite(v) or not float(v).is_integer()):
        raise _bad(arg, f"must be an integer ≥ {low}, got {float(v)!r}")
    if int(v) < low:
        raise _bad(arg, f"must be an integer ≥ {low}, got {int(v)}")
    return int(v)


def recorded_channel(data: Any, horizon: int, *, arg: str = "arrivals", values: str = "arrival", **kw):
    """A ``trace`` channel replaying ``data`` (shape ``(horizon,)`` or ``(horizon, streams)``), each
    value checked: 0/1 arrivals, or delays (integers ≥ 0; −1 = lost). The channel's ``file`` names
    the array's digest, so two different recordings are two different scenarios (hash, resume)."""
    try:
        arr = np.asarray(data)
    except Exception as exc:  # noqa: BLE001 - whatever the object, one message naming the argument
        raise _bad(arg, f"must be a numpy array (or a list of numbers), got {_got(data)} ({exc})") from None
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise _bad(arg, f"must hold numbers, got an array of {arr.dtype} ({_got(data)})")
    if arr.ndim not in (1, 2) or arr.size == 0:
        raise _bad(arg, f"must have shape (horizon,) = ({horizon},) or (horizon, streams) = ({horizon}, S), "
                        f"got shape {arr.shape}")
    if arr.shape[0] != horizon:
        hint = ("; it looks like (streams, horizon): pass arrivals.T" if arr.ndim == 2 and arr.shape[1] == horizon
                else "; set montecarlo.horizon (e.g. overrides={'montecarlo.horizon': %d}) or cut the recording"
                % arr.shape[0])
        raise _bad(arg, f"must have shape (horizon,) = ({horizon},) or (horizon, streams) = ({horizon}, S) with "
                        f"montecarlo.horizon = {horizon}, got shape {arr.shape}{hint}")
    a = arr.astype(float)
    if not np.isfinite(a).all():
        i = np.argwhere(~np.isfinite(a))[0]
        raise _bad(arg, f"must hold finite numbers, got {float(a[tuple(i)])!r} at index {tuple(int(x) for x in i)}")
    if values == "arrival":
        bad = (a != 0) & (a != 1)
        want = "0 (lost) or 1 (arrived)"
    else:
        bad = (a != np.round(a)) | (a < -1)
        want = "a delay in steps (an integer ≥ 0) or -1 (lost)"
    if bad.any():
        i = tuple(int(x) for x in np.argwhere(bad)[0])
        raise _bad(arg, f"values must be {want}, got {float(a[i]):g} at index {i}")
    if values == "delay" and (a > np.iinfo(np.int32).max).any():
        raise _bad(arg, f"delays must be below {np.iinfo(np.int32).max} steps, got {a.max():.3g}")
    rows = a.T if a.ndim == 2 else a  # (streams, horizon) or (horizon,)
    digest = hashlib.sha256(np.ascontiguousarray(rows).tobytes() + str(rows.shape).encode()).hexdigest()[:16]
    ch = TraceChannel.from_array(rows.astype(int) if values == "delay" else rows.astype(bool), values=values, **kw)
    return ch.model_copy(update={"file": f"<{arg} array sha256:{digest}>"})


def plan(scenario, *, runs: int | None = None, out: str | Path | None = None, jobs: int = 1, force: bool = False,
         overrides=None, yes: bool = False) -> dict:
    """What :func:`run` would do, computed and written nothing (``netkf run --dry-run``): the folder,
    run count, sweep points, run-steps, chunks, executor, ETA and scenario hash, after the same
    checks a run makes first (the output folder, ``montecarlo.max_runs``)."""
    if isinstance(scenario, (str, Path, dict)) and not isinstance(scenario, bool):
        scenario = load(scenario)
    elif not _is_scenario(scenario):
        raise _bad("scenario", f"plan() takes a Scenario from load(), got {_got(scenario)}")
    runs = None if runs is None else _check_int("runs", runs)
    jobs = min(_check_int("jobs", jobs), montecarlo.usable_cores())
    if overrides:
        scenario = with_overrides(scenario, overrides)
    p = runner.plan_run(scenario, out_dir=out, runs=runs, force=force, executor="process" if jobs > 1 else "serial",
                        jobs=jobs, yes=yes, runs_option="runs")
    return p.as_json()


def run(scenario, *, runs: int | None = None, arrivals: np.ndarray | None = None, delays: np.ndarray | None = None,
        buffer: int | None = None, out: str | Path | None = None, jobs: int = 1, executor: str = "serial",
        force: bool = False, overrides=None, yes: bool = False) -> Result:
    """Run a scenario (from :func:`load`); write the result folder only if ``out`` is given.

    ``arrivals`` / ``delays`` replay a recording instead of the scenario's channel (see the module
    docstring; ``buffer`` is the receive buffer for ``delays``, by default the scenario channel's, whose keep rule
    ``convention`` applies too); ``overrides`` change fields first.
    """
    if isinstance(scenario, (str, Path, dict)) and not isinstance(scenario, bool):
        scenario = load(scenario)
    elif not _is_scenario(scenario):
        raise _bad("scenario", f"run() takes a Scenario from load() (or what load() takes: a dict, a YAML file "
                               f"path or YAML text), got {_got(scenario)}")
    runs = None if runs is None else _check_int("runs", runs)
    jobs = _check_int("jobs", jobs)
    if executor not in ("serial", "process", "dask"):
        raise _bad("executor", f"must be 'serial', 'process' or 'dask', got {executor!r}")
    if out is not None and not isinstance(out, (str, Path)):
        raise _bad("out", f"must be a folder path (str or pathlib.Path), got {_got(out)}")
    if not isinstance(force, bool) or not isinstance(yes, bool):
        raise _bad("force" if not isinstance(force, bool) else "yes", "must be True or False")
    if overrides:
        scenario = with_overrides(scenario, overrides)
    if arrivals is not None and delays is not None:
        raise _bad("arrivals", "give either arrivals (0/1) or delays, not both")
    if buffer is not None and delays is None:
        raise _bad("buffer", "goes with delays= (the receive buffer of a delay recording)")
    rec = arrivals if arrivals is not None else delays
    if rec is not None:
        arg = "arrivals" if arrivals is not None else "delays"
        kw = {}
        if delays is not None:  # the scenario channel's receive buffer and keep rule, unless buffer= is given
            old = scenario.channel
            if buffer is not None:
                kw["buffer"] = _check_int("buffer", buffer)
            elif getattr(old, "buffer", None) is not None:
                kw["buffer"] = int(old.buffer)
            if getattr(old, "convention", None) is not None:
                kw["convention"] = old.convention
        ch = recorded_channel(rec, scenario.montecarlo.horizon, arg=arg,
                              values="arrival" if arrivals is not None else "delay", **kw)
        scenario = scenario.model_copy(update={"channel": ch})
        try:
            check_scenario(scenario)  # the estimator must be able to read this recording (streams, …)
        except ConfigError as exc:
            raise ConfigError([Problem(p.path.replace("channel", arg, 1) if p.path.startswith("channel") else p.path,
                                       f"{p.message} (with the recording passed as {arg}=)") for p in exc.problems]) \
                from None
    n_jobs = jobs if executor in ("process", "dask") or jobs > 1 else 1
    mode = executor if executor != "serial" else ("process" if n_jobs > 1 else "serial")
    if mode == "process":
        n_jobs = min(n_jobs, montecarlo.usable_cores())
    if out is not None:
        folder = runner.run_scenario(scenario, out_dir=out, runs=runs, force=force, executor=mode, jobs=n_jobs,
                                     yes=yes)
        name = scenario.name
        tables = {p.stem[len(name) + 1:] or "main": pd.read_csv(p) for p in sorted(Path(folder).glob(f"{name}*.csv"))}
        tables["main"] = pd.read_csv(Path(folder) / f"{name}.csv")
        return Result(tables["main"], tables, None, {}, Path(folder))
    runner.check_run_count(scenario, runs, yes=yes, jobs=n_jobs, runs_option="runs")
    ctx = RunContext(runs=runs)
    with montecarlo.execution(mode, n_jobs):
        art = runner.compute(scenario, ctx)
    tables = {"main": art.table, **art.extra_tables}
    if scenario.sweep is None:
        fig = scenario.analysis.plot(tables, scenario)
    else:
        fig = sweep.plot(tables, scenario)
    return Result(art.table, tables, plotting.detach(fig), art.meta)
