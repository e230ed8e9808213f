"""Result folders: CSV + PNG + manifest, written to a temporary folder and renamed into place.

An interrupted run leaves no half-written ``results/<name>/``: either the previous folder
or the complete new one.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import platform
import re
import secrets
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from contextlib import contextmanager
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
from netkf_cli.core.lazy import pandas as pd

from netkf_cli.core._version import __version__
from netkf_cli.core.errors import BusyError, NetkfError, OutputError, ResultExistsError
from netkf_cli.runtime.workers import _alive as _workers_alive

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX
    fcntl = None  # type: ignore[assignment]

# every package whose version can move a number or a figure (cvxpy/clarabel: the LMI designs;
# numba: the compiled backend; dask: the distributed executor), plus the CLI's own stack
DEPENDENCIES = ("numpy", "scipy", "pandas", "matplotlib", "pydantic", "cvxpy", "clarabel", "numba", "llvmlite",
                "dask", "distributed", "typer", "pyyaml")


def versions() -> dict[str, str]:
    """Versions of Python, netkf and every numerical dependency ("not installed" if absent)."""
    return dict(_versions())


@functools.cache
def _versions() -> tuple[tuple[str, str], ...]:
    """:func:`versions`, read once per process (≈ 12 ms of dist-info reads: once per artefact of a reproduction
    before; a running command does not see a package upgraded under it)."""
    out = {"netkf": __version__, "python": platform.python_version()}
    for d in DEPENDENCIES:
        try:
            out[d] = metadata.version(d)
        except metadata.PackageNotFoundError:
            out[d] = "not installed"
    return tuple(out.items())


_CODE_DIGEST: list[str] = []


def code_digest() -> str:
    """sha256 (16 hex digits) of netkf's own source (every .py file of the package, by relative path): what made a
    resume store's chunks. Chunks of another build are never mixed into a run (their statistics may have other
    keys or other numbers), installed or editable, with or without git. Computed once per process."""
    if not _CODE_DIGEST:
        pkg = Path(__file__).resolve().parents[1]
        h = hashlib.sha256()
        for f in sorted(pkg.rglob("*.py")):
            h.update(f.relative_to(pkg).as_posix().encode() + b"\0" + f.read_bytes() + b"\0")
        _CODE_DIGEST.append(h.hexdigest()[:16])
    return _CODE_DIGEST[0]


_FIXED_COMMITS: list[dict] = []  # within fixed_commit(): {source tree: git_commit's answer}


@contextmanager
def fixed_commit():
    """Within the block :func:`git_commit` asks git once per source tree: ``netkf reproduce`` runs every artefact
    of one tree, whose manifests all name the commit its processes started from (three git processes per
    artefact before, ~0.25 s of a quick reproduction). Forked workers inherit the answers."""
    _FIXED_COMMITS.append({})
    try:
        yield
    finally:
        _FIXED_COMMITS.pop()


def git_commit(where: Path | None = None) -> str | None:
    """The commit of the source tree (``+dirty`` if a tracked file outside results/ is modified), or None."""
    cwd = where or Path(__file__).resolve().parent
    if not _FIXED_COMMITS:
        return _ask_git(cwd)
    known = _FIXED_COMMITS[-1]
    key = str(Path(cwd).resolve())
    if key not in known:
        known[key] = _ask_git(cwd)
    return known[key]


def _ask_git(cwd: Path) -> str | None:
    """:func:`git_commit`, from git."""
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=cwd, capture_output=True, text=True, timeout=5)
        if sha.returncode != 0:
            return None
        # the *source* tree: results/ (being rewritten by this very run) does not make it dirty
        top = subprocess.run(["git", "rev-parse", "--show-toplevel"], cwd=cwd, capture_output=True, text=True,
                             timeout=5).stdout.strip() or str(cwd)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ".",
                                ":(exclude)results"], cwd=top, capture_output=True, text=True, timeout=5)
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


# ---- result folders: ownership, protection, locks, atomic replacement, leftovers -------------

WRITTEN_BY = "netkf"
MANIFEST = "manifest.json"
LOCK_SUFFIX = ".lock"
_MANIFEST_KEYS = ("name", "scenario", "scenario_hash", "files")
_LEFTOVER = re.compile(r"^\.(?P<name>.+)\.(?P<kind>w\.tmp|existing\.old)-(?P<pid>\d+)-(?P<tag>[0-9a-z]+)$")
_PACKAGE_ROOT = Path(__file__).resolve().parents[2]


def display_path(path: str | Path | None) -> str | None:
    """``path`` as it may be stored in a manifest: relative to the working folder or to the
    repository when inside one of them, else just the file name (never an author's absolute path)."""
    if path is None:
        return None
    p = Path(path)
    try:
        ap = p.resolve()
    except OSError:
        return p.name
    for base in (Path.cwd(), _PACKAGE_ROOT):
        try:
            return ap.relative_to(base.resolve()).as_posix()
        except (ValueError, OSError):
            continue
    return p.name if p.is_absolute() else p.as_posix()


def read_manifest(folder: Path) -> dict | None:
    """The folder's ``manifest.json`` as a dict, or None if missing or unreadable."""
    try:
        obj = json.loads((Path(folder) / MANIFEST).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return obj if isinstance(obj, dict) else None


def netkf_ownership(folder: Path) -> tuple[dict | None, str | None]:
    """``(manifest, None)`` if netkf wrote ``folder`` and it holds nothing else, else ``(None, why)``.

    netkf's folders carry ``"written_by": "netkf"`` in their manifest; folders written before that
    marker existed are recognised by the manifest's shape (name, scenario, scenario_hash, files).
    Any entry not listed in the manifest's ``files`` is a file someone else put there.
    """
    folder = Path(folder)
    man = read_manifest(folder)
    if man is None:
        return None, f"it has no readable {MANIFEST}, so it is not a result folder netkf wrote"
    if man.get("written_by") != WRITTEN_BY and not all(k in man for k in _MANIFEST_KEYS):
        return None, f"its {MANIFEST} was not written by netkf"
    listed = set(man.get("files") or ()) | {MANIFEST}
    try:
        foreign = sorted(e.name for e in os.scandir(folder) if e.name not in listed or not e.is_file(follow_symlinks=False))
    except OSError as exc:
        return None, f"it cannot be listed ({exc.strerror})"
    if foreign:
        more = f" and {len(foreign) - 3} more" if len(foreign) > 3 else ""
        return None, f"it contains files netkf did not write ({', '.join(foreign[:3])}{more})"
    return man, None


def _protected(final: Path) -> str | None:
    """Why ``final`` may never be replaced (a working folder, a repository, results/ …), or None."""
    try:
        target = final.resolve()
    except OSError:
        return None
    cwd = Path.cwd().resolve()
    if target == cwd or target in cwd.parents:
        return "it is the current folder or one of its parents"
    home = Path.home().resolve()
    if target == home or target in home.parents:
        return "it is your home folder or one of its parents"
    for repo in {_PACKAGE_ROOT, *([cwd] if (cwd / ".git").exists() else [])}:
        results = repo / "results"
        if target == results or target in results.parents:
            return f"it is {'the results root' if target == results else 'a parent of the results root'} of {repo.name}/ (only single result folders inside it are replaced)"
    if (target / ".git").exists():
        return "it is a repository"
    return None


def make_parent(final: Path) -> list[Path]:
    """Create ``final``'s parent folders; one :class:`OutputError` if that is impossible. Returns the
    folders it created, outermost first (a failed run removes them again if they are still empty)."""
    parent = Path(final).parent
    missing = []
    p = parent
    while not os.path.lexists(p) and p != p.parent:
        missing.append(p)
        p = p.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        for q in reversed(missing):  # whatever was made before the failure
            try:
                q.rmdir()
            except OSError:
                pass
        for q in (parent, *parent.parents):
            if os.path.lexists(q) and not q.is_dir():
                raise OutputError(f"cannot write {final}: {q} is a file, not a folder") from None
        raise OutputError(f"cannot create {parent} (for the result folder {final}: --out or output.dir): "
                          f"{exc.strerror or exc}") from None
    return list(reversed(missing))


NAME_MAX = 255
_TMP_EXTRA = len(".existing.old-4194304-") + 20 + 1  # the longest temporary name netkf makes next to a folder


def check_location(final: Path) -> None:
    """Refuse, before any work, a result folder that cannot be written where it is: a name too long
    for the file system, a mount point (netkf renames a finished folder into place, which a mount
    point cannot take), a file in the way, a parent that cannot be written."""
    final = Path(final)
    existing = next((q for q in (final.parent, *final.parent.parents) if os.path.lexists(q)), Path("/"))
    try:
        name_max = os.pathconf(existing if existing.is_dir() else existing.parent, "PC_NAME_MAX")
    except (OSError, ValueError):
        name_max = NAME_MAX
    for part in final.parts[len(existing.parts):]:
        if len(part.encode()) > name_max:
            raise OutputError(f"cannot write {_short(final)}: the folder name {_short(Path(part))} is "
                              f"{len(part.encode())} bytes, the file system allows {name_max}")
    if len(final.name.encode()) + _TMP_EXTRA > name_max:
        raise OutputError(f"cannot write {_short(final)}: the folder name is {len(final.name.encode())} bytes; "
                          f"netkf needs at most {name_max - _TMP_EXTRA} (it writes a temporary folder "
                          f"'.<name>.w.tmp-…' next to it). Choose a shorter --out")
    if os.path.lexists(final) and final.is_dir() and os.path.ismount(final):
        raise OutputError(f"{final} is a mount point: netkf writes a result next to it and renames it into place, "
                          f"which a mount point cannot take. Use a folder inside it, e.g. --out {final / 'result'}")
    if not existing.is_dir():
        raise OutputError(f"cannot write {final}: {existing} is a file, not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write in {existing}: Permission denied")


def _short(p: Path) -> str:
    s = str(p)
    return s if len(s) <= 80 else s[:40] + "…" + s[-30:]


class KeepExisting(Exception):
    """Raised inside :func:`atomic_folder` to keep the existing folder (byte-identical result)."""


TIMING_SUFFIX = "_seconds"
"""A meta key ending so is a measured time (e.g. markov_lmi's ``solve_seconds``), not a statement about the
result: it may differ between two runs of the same scenario and does not make a folder stale."""


def _statements(meta) -> str:
    """``meta`` as canonical JSON without its timings (keys ending in :data:`TIMING_SUFFIX`)."""
    def drop(x):
        if isinstance(x, dict):
            return {k: drop(v) for k, v in x.items() if not str(k).endswith(TIMING_SUFFIX)}
        return [drop(v) for v in x] if isinstance(x, list) else x
    return json.dumps(drop(meta), sort_keys=True, ensure_ascii=False)


def same_files(final: Path, tmp: Path, scenario_hash: str, same: Callable[[dict], bool] | None = None,
               meta: dict | None = None) -> bool:
    """True if ``final`` is netkf's result of this scenario (its hash, or ``same(manifest)``: a result
    written before fields were added to the schema), every file just written in ``tmp`` is
    byte-identical to the one there (``manifest.json`` aside, which holds times) and, given ``meta``, its
    manifest's ``meta`` says the same (what ran, the rules applied: a stale statement is rewritten)."""
    final = Path(final)
    if not final.is_dir() or final.is_symlink():
        return False
    man, _ = netkf_ownership(final)
    if man is None or not (man.get("scenario_hash") == scenario_hash or (same is not None and same(man))):
        return False
    if meta is not None and _statements(_jsonable(meta)) != _statements(man.get("meta")):
        return False
    new = sorted(p.name for p in Path(tmp).iterdir())
    if sorted(set(man.get("files") or ()) - {MANIFEST}) != new:
        return False
    try:
        return all((final / n).read_bytes() == (Path(tmp) / n).read_bytes() for n in new)
    except OSError:
        return False


def check_target(final: Path, *, force: bool, scenario_hash: str | None = None,
                 same: Callable[[dict], bool] | None = None) -> bool:
    """Decide whether a result may be written to ``final``; True if an existing folder will be replaced.

    Replaced: a folder netkf wrote (its manifest says so and it holds nothing else) with the same
    scenario hash, or that ``same(manifest)`` recognises as the same scenario (a reproducible
    rerun), or with ``force``. Never replaced: a file, a link, a folder
    with anything netkf did not write, the working folder or its parents, the repository's
    ``results/`` or its parents. Raises :class:`OutputError` / :class:`ResultExistsError`.
    """
    final = Path(final)
    if not os.path.lexists(final):
        return False
    if final.is_symlink():
        raise OutputError(f"{final} is a symbolic link; netkf never replaces it. Choose another --out")
    if not final.is_dir():
        raise OutputError(f"{final} is a file, not a result folder; netkf never replaces it. Choose another --out")
    why = _protected(final)
    if why is None:
        try:
            if not any(os.scandir(final)):
                return True  # an empty folder holds nothing anyone could lose
        except OSError as exc:
            raise OutputError(f"cannot read {final}: {exc.strerror or exc}") from None
        man, why = netkf_ownership(final)
    else:
        man = None
    if man is None:
        raise OutputError(f"{final} exists and will not be replaced{' even with --force' if force else ''}: {why}. "
                          "Choose another --out (netkf only replaces result folders it wrote)")
    if scenario_hash is not None and man.get("scenario_hash") == scenario_hash:
        return True
    if same is not None and same(man):
        return True
    if not force:
        raise ResultExistsError(f"{final} already holds a result of a different scenario or run size; "
                                "use --force to replace it or --out to choose another folder")
    return True


def _alive(pid: int) -> bool:
    """True if ``pid`` exists and is not a zombie (one definition: :func:`netkf_cli.runtime.workers._alive`)."""
    return _workers_alive(pid)


def _rmtree(path: Path) -> None:
    """Remove a folder netkf made, making read-only entries writable first if needed."""
    def onerror(func, p, _exc):
        try:
            os.chmod(os.path.dirname(p) or ".", 0o700)
            os.chmod(p, 0o700)
            func(p)
        except OSError:
            pass
    if sys.version_info >= (3, 12):
        shutil.rmtree(path, onexc=onerror)
    else:  # pragma: no cover
        shutil.rmtree(path, onerror=onerror)


class FileLock:
    """An exclusive ``fcntl.flock`` on ``<parent>/.<name>.lock`` holding the owner's pid and command.

    A second holder gets :class:`BusyError` naming the first. The lock file is removed on release
    (safely: a waiter re-checks that the file it locked is still the one on disk).
    """

    def __init__(self, target: Path, what: str):
        self.target = Path(target)
        self.what = what
        self.path = self.target.parent / f".{self.target.name}{LOCK_SUFFIX}"
        self.fd: int | None = None

    def acquire(self) -> "FileLock":
        if fcntl is None:  # pragma: no cover - not POSIX: no locking
            return self
        for _ in range(20):
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            except FileNotFoundError as exc:
                if self.path.parent.is_dir() and _ > 2:  # not a vanished parent: this folder refuses files
                    raise OutputError(f"cannot write in {self.path.parent}: {exc.strerror or exc}") from None
                continue  # the parent vanished under us (an empty cache folder removed): retry
            except OSError as exc:
                raise OutputError(f"cannot write in {self.path.parent}: {exc.strerror or exc}") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                try:
                    holder = os.read(fd, 4096).decode("utf-8", "replace").strip()
                finally:
                    os.close(fd)
                raise BusyError(f"{self.what} {self.target} is in use by another netkf run "
                                f"({holder or 'unknown process'}); wait for it to finish or choose another --out") from None
            try:
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if not same:  # released and unlinked between our open and flock: lock the new file
                os.close(fd)
                continue
            cmd = " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]) if sys.argv else "?"
            os.ftruncate(fd, 0)
            os.write(fd, f"pid {os.getpid()}: {cmd}\n".encode())
            self.fd = fd
            return self
        raise BusyError(f"could not lock {self.target} (its lock file keeps changing)")

    def release(self) -> None:
        if self.fd is None:
            return
        try:
            os.unlink(self.path)
        except OSError:
            pass
        os.close(self.fd)
        self.fd = None

    def locked_elsewhere(self) -> bool:
        """True if another process holds this lock (without taking it)."""
        if fcntl is None or not self.path.exists():
            return False
        try:
            fd = os.open(self.path, os.O_RDONLY)
        except OSError:
            return False
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            return False
        except OSError:
            return True
        finally:
            os.close(fd)

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc):
        self.release()


def _remove_stale_lock(path: Path) -> bool:
    """Remove a lock file nobody holds (its run was killed): lock it, then unlink it. Safe with
    :class:`FileLock`, whose acquirer re-checks that the file it locked is still on disk."""
    if fcntl is None:
        return False
    try:
        fd = os.open(path, os.O_RDWR)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        if os.fstat(fd).st_ino != os.stat(path).st_ino:
            return False
        os.unlink(path)
        return True
    except OSError:
        return False
    finally:
        os.close(fd)


def clean_leftovers(parent: Path) -> list[str]:
    """Remove what a killed run left in ``parent``: netkf's own ``.<name>.w.tmp-<pid>-…`` folders and
    ``.<name>.existing.old-<pid>-…`` (restored to ``<name>`` if that is missing), only when their
    owner process is gone and nobody holds ``<name>``'s lock, and ``.<name>.lock`` files nobody
    holds. Returns what was done."""
    done: list[str] = []
    try:
        entries = list(os.scandir(parent))
    except OSError:
        return done
    for e in entries:
        if e.name.startswith(".") and e.name.endswith(LOCK_SUFFIX) and e.is_file(follow_symlinks=False):
            if _remove_stale_lock(Path(e.path)):
                done.append(f"removed the stale lock {e.name}")
            continue
        m = _LEFTOVER.match(e.name)
        if not m or not e.is_dir(follow_symlinks=False):
            continue
        pid = int(m["pid"])
        if pid != os.getpid() and _alive(pid):
            continue
        final = Path(parent) / m["name"]
        if FileLock(final, "").locked_elsewhere():
            continue
        path = Path(e.path)
        try:
            if m["kind"] == "existing.old" and not os.path.lexists(final):
                path.rename(final)
                done.append(f"restored {final.name} from an interrupted replacement")
            else:
                _rmtree(path)
                done.append(f"removed {e.name}")
        except OSError:
            continue
    return done


def _token() -> str:
    return f"{time.time_ns():x}{secrets.token_hex(2)}"


@contextmanager
def atomic_folder(final: Path, force: bool = False, scenario_hash: str | None = None,
                  same: Callable[[dict], bool] | None = None):
    """Yield a fresh temporary folder next to ``final``; on success rename it to ``final``.

    Whether an existing ``final`` may be replaced is decided by :func:`check_target` (checked
    again just before the rename). On any exception (including KeyboardInterrupt) the temporary
    folder is removed and ``final`` is untouched. Folders are created with the usual permissions
    (0777 minus the umask), not 0700.
    """
    final = Path(final)
    check_target(final, force=force, scenario_hash=scenario_hash, same=same)
    make_parent(final)
    try:
        tmp = final.parent / f".{final.name}.w.tmp-{os.getpid()}-{_token()}"
        os.mkdir(tmp)
    except OSError as exc:
        raise OutputError(f"cannot write in {final.parent}: {exc.strerror or exc}") from None
    try:
        try:
            yield tmp
        except KeepExisting:
            _rmtree(tmp)
            return
        replace = check_target(final, force=force, scenario_hash=scenario_hash, same=same)
        if replace:
            old = final.parent / f".{final.name}.existing.old-{os.getpid()}-{_token()}"
            final.rename(old)
            try:
                tmp.rename(final)
            except BaseException:
                old.rename(final)
                raise
            _rmtree(old)
        else:
            tmp.rename(final)
    except BaseException as exc:
        if tmp.exists():
            _rmtree(tmp)
        if isinstance(exc, OSError) and not isinstance(exc, NetkfError):
            raise OutputError(f"cannot write {final}: {exc.strerror or exc}") from None
        raise
