"""Write constraints.txt: the installed versions of netkf[dev]'s whole dependency closure.

Run after an intended upgrade (``python .ci/freeze_constraints.py``), then run the suite and
commit both. CI installs with ``pip install -e ".[dev]" -c constraints.txt``; ``.ci/latest``
installs the newest versions instead and runs the golden tests (tolerances must hold there too).
"""

from __future__ import annotations

import re
import sys
from importlib import metadata
from pathlib import Path

from packaging.markers import default_environment
from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[1]
EXTRAS = ("dev",)


def canon(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def closure(root: str, extras: tuple[str, ...]) -> dict[str, str]:
    seen: dict[str, str] = {}
    todo = [(root, set(extras))]
    while todo:
        name, ex = todo.pop()
        try:
            dist = metadata.distribution(name)
        except metadata.PackageNotFoundError:
            continue
        key = canon(dist.metadata["Name"])
        if key in seen and not ex:
            continue
        seen[key] = dist.version
        for r in dist.requires or []:
            req = Requirement(r)
            env = default_environment()
            ok = req.marker is None or any(req.marker.evaluate({**env, "extra": e}) for e in (ex or {""}))
            if ok:
                todo.append((req.name, set(req.extras)))
    return seen


def main() -> int:
    pins = closure("netkf", EXTRAS)
    for tool in ("netkf", "pip", "setuptools", "wheel"):  # the project itself and build tooling
        pins.pop(tool, None)
    lines = [
        "# Versions CI installs (pip install -e \".[dev]\" -c constraints.txt): netkf[dev]'s dependency",
        "# closure as installed when the goldens were last regenerated. Regenerate with",
        "# `python .ci/freeze_constraints.py`; `.ci/latest` checks the newest versions.",
        f"# Python {sys.version.split()[0]}",
    ]
    lines += [f"{k}=={v}" for k, v in sorted(pins.items())]
    (ROOT / "constraints.txt").write_text("\n".join(lines) + "\n", encoding="utf-8")
    print(f"constraints.txt: {len(pins)} pins")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
