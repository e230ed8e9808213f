"""`netkf reproduce --help` names every topic `netkf reproduce` runs (the folders of configs/ plus shi2009), no more:
the help listed five topics after a sixth (critical) was added."""

from __future__ import annotations

import re

from typer.testing import CliRunner

from netkf_cli.app.cli import app
from netkf_cli.app.reproduce import discover
from tests.conftest import ROOT


def test_help_lists_exactly_the_topics():
    arts, _ = discover(ROOT, [])
    topics = sorted({a.topic for a in arts})
    res = CliRunner().invoke(app, ["reproduce", "--help"], env={"COLUMNS": "400", "TERM": "dumb", "NO_COLOR": "1"})
    assert res.exit_code == 0, res.output
    text = " ".join(res.output.split())
    listed = re.search(r"\(default: all\): ([a-z0-9_, ]+?) \(", text)
    assert listed, text
    assert sorted(t.strip() for t in listed.group(1).split(",")) == topics
