"""Every numerical tolerance sits in one module (issue 21.4): netkf_cli/core/tolerances.py.

A module-level constant named like a tolerance (…TOL…, …MARGIN…, …SIGMAS…, ROUNDOFF…) assigned a float
(a count such as the smoother's SHARE_MARGIN = 4 rows is not a tolerance) anywhere else in netkf_cli/ fails this test, naming the file and line: import it from core.tolerances."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PKG = ROOT / "netkf_cli"
HOME = PKG / "core" / "tolerances.py"
WORDS = ("TOL", "MARGIN", "SIGMAS", "ROUNDOFF")


def _numeric(node) -> bool:
    return all(isinstance(n, ast.Constant) and isinstance(n.value, (int, float)) or
               isinstance(n, (ast.BinOp, ast.UnaryOp, ast.operator, ast.unaryop, ast.Attribute, ast.Name, ast.Load))
               for n in ast.walk(node)) and any(isinstance(n, ast.Constant) and isinstance(n.value, float) for n in ast.walk(node))


def test_tolerances_are_defined_only_in_core_tolerances():
    stray = []
    for path in sorted(PKG.rglob("*.py")):
        if path == HOME:
            continue
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            if isinstance(node, (ast.Assign, ast.AnnAssign)):
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                for t in targets:
                    if isinstance(t, ast.Name) and t.id.isupper() and any(w in t.id for w in WORDS) \
                            and node.value is not None and _numeric(node.value):
                        stray.append(f"{path.relative_to(ROOT)}:{node.lineno} {t.id}")
    assert not stray, "tolerances outside netkf_cli/core/tolerances.py: " + ", ".join(stray)


def test_the_tolerance_module_documents_every_constant():
    tree = ast.parse(HOME.read_text(encoding="utf-8"))
    body = tree.body
    for i, node in enumerate(body):
        if isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Name) and node.targets[0].id.isupper():
            nxt = body[i + 1] if i + 1 < len(body) else None
            assert isinstance(nxt, ast.Expr) and isinstance(getattr(nxt, "value", None), ast.Constant) \
                and isinstance(nxt.value.value, str), f"{node.targets[0].id}: no docstring saying what it decides"
