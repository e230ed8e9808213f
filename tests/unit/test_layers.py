"""The layered import contract (pyproject.toml [tool.importlinter]) holds: imports go down only, no
cycles. Fails on any cycle or upward import, naming the offending import chain."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def test_import_contract_is_kept():
    exe = shutil.which("lint-imports", path=str(Path(sys.executable).parent)) or shutil.which("lint-imports")
    if exe is None:
        pytest.fail("lint-imports (import-linter, a dev dependency) is not installed: pip install -e '.[dev]'")
    res = subprocess.run([exe, "--no-cache"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout[-6000:] + res.stderr[-2000:]
    assert "0 broken" in res.stdout


def test_every_module_is_in_a_layer():
    """A module the layers contract does not name is not checked at all (import-linter ignores it silently):
    every module and package directly under netkf_cli/ sits in one layer, and every name in a layer exists."""
    contracts = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["importlinter"]["contracts"]
    layers = next(c for c in contracts if c["type"] == "layers")["layers"]
    named = {m.strip().removeprefix("netkf_cli.") for layer in layers for m in layer.split(":")}
    pkg = ROOT / "netkf_cli"
    present = {p.stem for p in pkg.glob("*.py") if p.stem != "__init__"} | {
        p.name for p in pkg.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert not present - named, f"modules in no layer of pyproject's [tool.importlinter] contract: {sorted(present - named)}"
    assert not named - present, f"layers naming modules that do not exist: {sorted(named - present)}"
