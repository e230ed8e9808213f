"""CI regenerates every paper artefact at quick size and checks it (issue 8).

A change that moves a figure fails here with a message naming the artefact and the number:
either a published check that is expected to reproduce, or a committed full-size golden
CSV under results/ that the fresh quick run no longer matches (5 combined standard errors
for Monte Carlo rows, 1e-6 relative for closed forms).
"""

import os

from typer.testing import CliRunner

from netkf_cli.cli import app
from tests.conftest import ROOT


def test_reproduce_quick_check_passes_on_the_repository(tmp_path, monkeypatch):
    monkeypatch.chdir(ROOT)
    jobs = str(min(2, os.cpu_count() or 1))
    r = CliRunner().invoke(app, ["reproduce", "--quick", "--check", "--out", str(tmp_path / "quick"), "--jobs", jobs])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "quick" / "REPORT.md").exists()
