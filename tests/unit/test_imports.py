"""Imports sit at the top of their module (issue 21): an import inside a function hides a dependency
from the layered contract's reader and is how import cycles survive. The one exception is an
*optional* library — one the package does not require unconditionally — which is imported where
it is used (so netkf runs without it), with a one-line comment saying why. The optional libraries
are read from pyproject.toml (``[project.optional-dependencies]`` but the ``dev`` toolchain, and the
dependencies with an environment marker, minus the unconditional dependencies), so this list cannot drift from the
packaging; a netkf_cli module that itself needs one of them at import time (``kalman_numba``,
``dask_plugin`` …) counts as optional too.

Fails naming ``file:line`` of every function-level import that is not optional, or that has no
reason comment."""

from __future__ import annotations

import ast
import re
import tomllib
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PKG = ROOT / "netkf_cli"
TOOLING = {"dev"}
DEFERRED = ("cvxpy", "scipy.stats", "matplotlib", "PIL", "clarabel")
"""Required libraries imported at first use for their cost (~20–40 MB and up to 1 s each in every process and
forked worker; issue 20's 300 MB): like optional ones they need a reason comment, and
tests/unit/test_import_footprint.py / tests/figures/test_lazy_matplotlib.py check netkf's start-up loads none."""


def _deferred(name: str) -> bool:
    return any(name == d or name.startswith(d + ".") for d in DEFERRED)
"""Extras of the developer's toolchain (pytest, import-linter …): not libraries netkf_cli may use."""


def _dist(req: str) -> str:
    """Normalized distribution name of a requirement string (``dask[distributed]>=2024.1`` → dask)."""
    return re.sub(r"[-_.]+", "-", re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)", req).group(1)).lower()


def optional_distributions() -> set[str]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    deps = project.get("dependencies", [])
    required = {_dist(r) for r in deps if ";" not in r}
    conditional = {_dist(r) for r in deps if ";" in r}
    extras = {_dist(r) for name, reqs in project.get("optional-dependencies", {}).items() if name not in TOOLING
              for r in reqs}
    return (conditional | extras) - required


def optional_libraries() -> set[str]:
    """Top-level import names of the optional distributions (installed ones from their metadata,
    the others by their distribution name)."""
    dists = optional_distributions()
    names = {d.replace("-", "_") for d in dists}
    for module, owners in metadata.packages_distributions().items():
        if {_dist(o) for o in owners} & dists:
            names.add(module)
    return names


def _module_name(path: Path) -> tuple[str, str]:
    """(module, package its relative imports start from)."""
    parts = path.relative_to(ROOT).with_suffix("").parts
    if parts[-1] == "__init__":
        return ".".join(parts[:-1]), ".".join(parts[:-1])
    return ".".join(parts), ".".join(parts[:-1])


def _imported(node: ast.Import | ast.ImportFrom, package: str) -> list[str]:
    """Absolute names an import statement binds (``from a import b`` → a and a.b: b may be a module);
    ``package`` resolves relative imports."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    base = node.module or ""
    if node.level:
        parts = package.split(".")
        parts = parts[: len(parts) - node.level + 1]
        base = ".".join([*parts, base] if base else parts)
    return [base] + [f"{base}.{a.name}" for a in node.names]


def _guarded(tree: ast.Module) -> set[ast.AST]:
    """Module-level imports inside ``try: … except ImportError``: the module imports without them."""
    out = set()
    for node in tree.body:
        if isinstance(node, ast.Try) and any(
                h.type is not None and "ImportError" in ast.unparse(h.type) for h in node.handlers):
            out.update(n for n in ast.walk(node) if isinstance(n, (ast.Import, ast.ImportFrom)))
    return out


def _is(name: str, names: set[str]) -> bool:
    return any(name == n or name.startswith(n + ".") for n in names)


def scan() -> tuple[dict[str, list], dict[str, list], dict[str, str]]:
    """Per module: its unguarded module-level imports, its function-level imports (with lines), and
    the package its relative imports start from."""
    top: dict[str, list] = {}
    inner: dict[str, list] = {}
    packages: dict[str, str] = {}
    for f in sorted(PKG.rglob("*.py")):
        mod, package = _module_name(f)
        packages[mod] = package
        src = f.read_text(encoding="utf-8")
        tree = ast.parse(src, str(f))
        guarded = _guarded(tree)
        in_fn = set()
        for fn in ast.walk(tree):
            if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                in_fn.update(n for n in ast.walk(fn) if isinstance(n, (ast.Import, ast.ImportFrom)))
        lines = src.splitlines()
        top[mod] = [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))
                    and n not in in_fn and n not in guarded]
        inner[mod] = [(f, n, lines) for n in sorted(in_fn, key=lambda n: n.lineno)]
    return top, inner, packages


def optional_modules(libs: set[str], top: dict[str, list], packages: dict[str, str]) -> set[str]:
    """netkf_cli modules that cannot be imported without an optional library (transitively)."""
    opt: set[str] = set()
    changed = True
    while changed:
        changed = False
        for mod, nodes in top.items():
            if mod in opt:
                continue
            names = [n for node in nodes for n in _imported(node, packages[mod])]
            if any(n.split(".")[0] in libs or n in opt for n in names):
                opt.add(mod)
                changed = True
    return opt


def _reason(node: ast.AST, lines: list[str]) -> bool:
    """A comment on the import's lines or the line above, saying more than a ``noqa``."""
    comments = " ".join(m.group(1) for i in range(max(0, node.lineno - 2), node.end_lineno)
                        if (m := re.search(r"#(.*)$", lines[i])))
    comments = re.sub(r"noqa(:\s*[A-Z]+[0-9]+(,\s*[A-Z]+[0-9]+)*)?", "", comments)
    return bool(re.search(r"[A-Za-z]{3,}", comments))


def test_the_optional_libraries_come_from_pyproject():
    libs = optional_libraries()
    assert {"numba", "dask"} <= libs, libs
    assert not libs & {"numpy", "scipy", "matplotlib", "pydantic", "yaml", "rich", "typer", "pandas", "cvxpy"}, libs


def test_imports_inside_functions_only_for_optional_libraries():
    libs = optional_libraries()
    top, inner, packages = scan()
    opt = optional_modules(libs, top, packages)
    assert "netkf_cli.linalg.kalman_numba" in opt  # the compiled primitives need numba at import
    bad, silent = [], []
    for mod, found in inner.items():
        for f, node, lines in found:
            names = _imported(node, packages[mod])
            optional = (isinstance(node, ast.Import)
                        and all(n.split(".")[0] in libs or n in opt or _deferred(n) for n in names)) or (
                isinstance(node, ast.ImportFrom)
                and (names[0].split(".")[0] in libs or names[0] in opt or _deferred(names[0])
                     or all(n in opt for n in names[1:])))
            where = f"{f.relative_to(ROOT)}:{node.lineno}: {lines[node.lineno - 1].strip()}"
            if not optional:
                bad.append(where)
            elif not _reason(node, lines):
                silent.append(where)
    assert not bad, ("imports inside functions (move them to the module top; optional libraries "
                     f"{sorted(libs)} excepted):\n" + "\n".join(bad))
    assert not silent, "lazy optional imports without a one-line reason comment:\n" + "\n".join(silent)
