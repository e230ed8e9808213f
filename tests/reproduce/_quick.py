"""One quick reproduction of every artefact per test session, shared by the tests that need it.

``tests/reproduce/test_repo_artefacts.py`` checks it (``--quick --check``) and
``tests/figures/test_lint.py`` lints the figures it drew (``NETKF_FIGURE_LINT``), so the suite
pays for the quick reproduction once — also under pytest-xdist: the first worker that needs it
runs it into the session's shared temporary folder under a file lock, and the others read what it
left there (``result.json``). tests/conftest.py schedules the figure lint first and the other
reader last, so no worker waits for it.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

from typer.testing import CliRunner

from netkf_cli.app.cli import app
from tests.conftest import ROOT

try:
    import fcntl
except ImportError:  # not POSIX: no lock (run in-process there: -n 0)
    fcntl = None


@dataclass
class QuickRun:
    out: Path        # the artefact folders and REPORT.md
    lint: Path       # one <figure>.json per saved figure (netkf_cli.runtime.plotting.lint findings)
    exit_code: int
    output: str


_CACHE: dict[str, QuickRun] = {}


def _shared_base(tmp_path_factory) -> Path:
    """The session's temporary folder: under xdist each worker's basetemp is <session>/popen-gwN."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


def _run(base: Path) -> QuickRun:
    out, lint = base / "quick", base / "lint"
    jobs = str(min(2, os.cpu_count() or 1))
    old_env, old_cwd = os.environ.get("NETKF_FIGURE_LINT"), Path.cwd()
    os.environ["NETKF_FIGURE_LINT"] = str(lint)  # inherited by the worker processes
    os.chdir(ROOT)
    try:
        r = CliRunner().invoke(app, ["reproduce", "--quick", "--check", "--out", str(out), "--jobs", jobs])
    finally:
        os.chdir(old_cwd)
        if old_env is None:
            os.environ.pop("NETKF_FIGURE_LINT", None)
        else:
            os.environ["NETKF_FIGURE_LINT"] = old_env
    return QuickRun(out, lint, r.exit_code, r.output)


def quick_reproduction(tmp_path_factory) -> QuickRun:
    if "run" not in _CACHE:
        base = _shared_base(tmp_path_factory) / "quick-reproduction"
        base.mkdir(parents=True, exist_ok=True)
        record = base / "result.json"
        with open(base / ".lock", "w") as lock:
            if fcntl is not None:
                fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes (or the worker dies)
            if record.exists():
                d = json.loads(record.read_text(encoding="utf-8"))
                run = QuickRun(Path(d["out"]), Path(d["lint"]), int(d["exit_code"]), d["output"])
            else:
                run = _run(base)
                record.write_text(json.dumps({k: str(v) if isinstance(v, Path) else v for k, v in asdict(run).items()}),
                                  encoding="utf-8")
        _CACHE["run"] = run
    return _CACHE["run"]
