"""One quick reproduction of every artefact per test session, shared by the tests that need it.

``tests/reproduce/test_repo_artefacts.py`` checks it (``--quick --check``) and
``tests/figures/test_lint.py`` lints the figures it drew (``NETKF_FIGURE_LINT``), so the suite
pays for the quick reproduction once.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from typer.testing import CliRunner

from netkf_cli.cli import app
from tests.conftest import ROOT


@dataclass
class QuickRun:
    out: Path        # the artefact folders and REPORT.md
    lint: Path       # one <figure>.json per saved figure (netkf_cli.plotting.lint findings)
    exit_code: int
    output: str


_CACHE: dict[str, QuickRun] = {}


def quick_reproduction(tmp_path_factory) -> QuickRun:
    if "run" not in _CACHE:
        base = tmp_path_factory.mktemp("quick-reproduction")
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
        _CACHE["run"] = QuickRun(out, lint, r.exit_code, r.output)
    return _CACHE["run"]
