"""Result folders: CSV + PNG + manifest, written to a temporary folder and renamed into place.

An interrupted run leaves no half-written ``results/<name>/``: either the previous folder
or the complete new one.
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import subprocess
import tempfile
import time
from contextlib import contextmanager
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from netkf_cli import __version__
from netkf_cli.errors import ResultExistsError

DEPENDENCIES = ("numpy", "scipy", "pandas", "matplotlib", "pydantic", "typer", "pyyaml")


def versions() -> dict[str, str]:
    out = {"netkf": __version__, "python": platform.python_version()}
    for d in DEPENDENCIES:
        try:
            out[d] = metadata.version(d)
        except metadata.PackageNotFoundError:
            out[d] = "not installed"
    return out


def git_commit(where: Path | None = None) -> str | None:
    """The commit of the source tree (``+dirty`` if modified), or None outside git."""
    cwd = where or Path(__file__).resolve().parent
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=cwd, capture_output=True, text=True, timeout=5)
        if sha.returncode != 0:
            return None
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=cwd,
                               capture_output=True, text=True, timeout=5)
        return sha.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return None


def write_csv(df: pd.DataFrame, path: Path) -> None:
    """Tidy CSV: no index, plain floats with full precision."""
    df.to_csv(path, index=False, float_format="%.10g")


def read_csv(path: Path) -> pd.DataFrame:
    return pd.read_csv(path)


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return v if np.isfinite(v) else (None if np.isnan(v) else ("inf" if v > 0 else "-inf"))
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def write_json(obj: Any, path: Path) -> None:
    path.write_text(json.dumps(_jsonable(obj), indent=2, ensure_ascii=False) + "\n", encoding="utf-8")


@contextmanager
def atomic_folder(final: Path, force: bool = False):
    """Yield a temporary folder next to ``final``; on success rename it to ``final``.

    Refuses to replace an existing ``final`` unless ``force``. On any exception (including
    KeyboardInterrupt) the temporary folder is removed and ``final`` is untouched.
    """
    final = Path(final)
    if final.exists() and not force:
        raise ResultExistsError(f"{final} already exists; use --force to replace it or --out to choose another folder")
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.tmp-", dir=final.parent))
    try:
        yield tmp
        if final.exists():
            old = final.parent / f".{final.name}.old-{os.getpid()}-{time.time_ns()}"
            final.rename(old)
            tmp.rename(final)
            shutil.rmtree(old, ignore_errors=True)
        else:
            tmp.rename(final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
