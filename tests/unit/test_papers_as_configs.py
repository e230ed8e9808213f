"""Issue 21: the papers are configurations of the generic pieces; recipes/ holds only paper arithmetic.

* at least 22 of the paper configs (configs/**.yaml) use an analysis kind that lives outside recipes/
  (a generic metric, or a generic analysis such as ``critical`` that answers any system);
* recipes/ runs no Monte Carlo: no chunked runs, no engine, no trace sampling, no random generator;
* recipes/ stays small (≤ 1 500 lines): paper arithmetic, claims, table layouts and plots.
"""

import ast
from pathlib import Path

import pytest

from netkf_cli.config.loader import load_scenario

ROOT = Path(__file__).resolve().parents[2]
RECIPES = ROOT / "netkf_cli" / "recipes"
MIN_GENERIC = 22
MAX_RECIPE_LINES = 1500

MC_NAMES = {"run_chunked", "simulate", "sample_trace", "default_rng", "SeedSequence", "PairKernel", "Generator",
            "mean_covariance", "time_average_mean"}
MC_MODULES = {"netkf_cli.runtime.montecarlo", "netkf_cli.engine", "netkf_cli.runtime.workers", "netkf_cli.engine.state"}
"""Modules that run Monte Carlo. A recipe may read a channel module's labels and distributions (paper
arithmetic) but never builds a channel: no ``…Channel`` class is named."""


def _paper_configs() -> list[Path]:
    return sorted(p for p in (ROOT / "configs").rglob("*.yaml"))


def test_paper_configs_are_configurations_of_generic_analyses():
    generic, recipe = [], []
    for p in _paper_configs():
        sc = load_scenario(p)
        (recipe if type(sc.analysis).__module__.startswith("netkf_cli.recipes") else generic).append(
            f"{p.relative_to(ROOT)} ({sc.analysis.kind})")
    assert len(generic) >= MIN_GENERIC, (f"{len(generic)} of {len(generic) + len(recipe)} paper configs use analyses "
                                         f"outside recipes/ (need ≥ {MIN_GENERIC}); still recipes: {recipe}")


def _recipe_files() -> list[Path]:
    return sorted(p for p in RECIPES.glob("*.py"))


KNOWN_MONTE_CARLO: dict[str, str] = {}
"""The recipes that still run Monte Carlo, each with the reason (issue 21 stays open for them). A recipe
leaves this list when it is converted: the test fails if a listed recipe no longer needs its entry."""


@pytest.mark.parametrize("path", _recipe_files(), ids=lambda p: p.name)
def test_recipes_run_no_monte_carlo(path):
    tree = ast.parse(path.read_text(encoding="utf-8"))
    bad = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            mod = node.module
            if any(mod == m or mod.startswith(m + ".") for m in MC_MODULES):
                bad.append(f"line {node.lineno}: imports {mod}")
            bad += [f"line {node.lineno}: imports {a.name}" for a in node.names
                    if a.name in MC_NAMES or a.name.endswith("Channel")]
        elif isinstance(node, ast.Import):
            bad += [f"line {node.lineno}: imports {a.name}" for a in node.names
                    if any(a.name == m or a.name.startswith(m + ".") for m in MC_MODULES)]
        elif isinstance(node, ast.Attribute) and (node.attr in MC_NAMES or node.attr.endswith("Channel")):
            bad.append(f"line {node.lineno}: uses .{node.attr}")
        elif isinstance(node, ast.Name) and node.id in MC_NAMES:
            bad.append(f"line {node.lineno}: uses {node.id}")
    if path.name in KNOWN_MONTE_CARLO:
        assert bad, f"{path.name} runs no Monte Carlo any more: remove it from KNOWN_MONTE_CARLO"
        return
    assert not bad, f"{path.name} runs Monte Carlo (it belongs in a generic metric): " + "; ".join(bad)


def test_recipes_are_small():
    lines = {p.name: len(p.read_text(encoding="utf-8").splitlines()) for p in _recipe_files()}
    assert sum(lines.values()) <= MAX_RECIPE_LINES, f"recipes/ has {sum(lines.values())} lines: {lines}"
