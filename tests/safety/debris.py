"""Leftovers a netkf run must never leave behind (issue 23): resume caches, locks, temporary
folders and files. :func:`scan` lists them; the autouse fixtures in ``tests/safety/conftest.py``
and ``tests/cli/conftest.py`` call it after every test, so every failing CLI case in these folders
is also a no-debris case. A test that interrupts a run on purpose (the cache is kept for
``--resume``) is marked ``keeps_resume_cache``."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DEBRIS = re.compile(r"^\.netkf-cache$|^\..+\.lock$|\.w\.tmp-\d+-|\.existing\.old-\d+-|\.tmp\d+$")
CACHE_ONLY = re.compile(r"^\.netkf-cache$")


def scan(folder: Path, *, keep_cache: bool = False, max_depth: int = 6) -> list[str]:
    """Every debris entry under ``folder`` (relative paths)."""
    found: list[str] = []
    folder = Path(folder)
    if not folder.is_dir():
        return found

    def walk(d: Path, depth: int) -> None:
        try:
            entries = list(os.scandir(d))
        except OSError:
            return
        for e in entries:
            if DEBRIS.search(e.name) and not (keep_cache and CACHE_ONLY.search(e.name)):
                found.append(str(Path(e.path).relative_to(folder)))
                continue
            if keep_cache and CACHE_ONLY.search(e.name):
                continue
            if e.is_dir(follow_symlinks=False) and depth < max_depth:
                walk(Path(e.path), depth + 1)

    walk(folder, 0)
    return sorted(found)


def _ours(name: str) -> bool:
    """In shared folders (the repository's results/, the working folder) only debris of this
    process counts: other people may be running netkf there right now."""
    m = re.search(r"-(\d+)-|\.tmp(\d+)$", name)
    return bool(m) and int(m[1] or m[2]) == os.getpid()


def _shared_folders() -> list[Path]:
    out = [Path.cwd(), ROOT / "results"]
    return [p for p in dict.fromkeys(p.resolve() for p in out) if p.is_dir()]


@pytest.fixture(autouse=True)
def no_debris(request, tmp_path):
    """After each test: nothing of netkf's left in the test's folder, and nothing of this process in
    the working folder or results/ (only ``.netkf-cache`` kept by a test marked keeps_resume_cache)."""
    before = {p: set(scan(p, max_depth=1)) for p in _shared_folders()}
    yield
    keep = request.node.get_closest_marker("keeps_resume_cache") is not None
    killed = request.node.get_closest_marker("sigkilled") is not None  # SIGKILL: nothing can clean up (the next run does)
    left = [] if killed else scan(tmp_path, keep_cache=keep)
    for p, old in before.items():
        left += [f"{p}/{x}" for x in set(scan(p, max_depth=1)) - old if _ours(x)]
    assert not left, f"{request.node.name} left debris behind: {left}"
