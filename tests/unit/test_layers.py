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


def _layer_contracts():
    contracts = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["importlinter"]["contracts"]
    return [c for c in contracts if c["type"] == "layers"]


def _named(layers):
    return {m.strip() for layer in layers for m in layer.split(":")}


def test_every_module_is_in_a_layer():
    """A module no layers contract names is not checked at all (import-linter ignores it silently). The folders
    are the layers: every package directly under netkf_cli/ is a layer of the root contract (and no module sits
    flat beside them), and the modules of a package with an ordered inside (app, config, runtime, linalg, core)
    each sit in that package's own contract; every name a contract gives exists."""
    contracts = _layer_contracts()
    root = contracts[0]["layers"]
    pkg = ROOT / "netkf_cli"
    flat = sorted(p.stem for p in pkg.glob("*.py") if p.stem != "__init__")
    assert not flat, f"modules flat in netkf_cli/ (outside every layer folder): {flat}"
    packages = {f"netkf_cli.{p.name}" for p in pkg.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    named = _named(root)
    assert packages == named, (f"packages in no layer: {sorted(packages - named)}; "
                               f"layers naming no package: {sorted(named - packages)}")
    inner = {next(iter(_named(c["layers"]))).rsplit(".", 1)[0]: _named(c["layers"]) for c in contracts[1:]}
    assert set(inner) == {"netkf_cli.app", "netkf_cli.config", "netkf_cli.runtime", "netkf_cli.linalg",
                          "netkf_cli.core"}, sorted(inner)
    for package, names in inner.items():
        folder = ROOT / package.replace(".", "/")
        present = {f"{package}.{p.stem}" for p in folder.glob("*.py") if p.stem != "__init__"}
        assert not present - names, f"modules of {package} in no layer of its contract: {sorted(present - names)}"
        assert not names - present, f"{package}'s contract names modules that do not exist: {sorted(names - present)}"
