"""netkf — Kalman filtering over lossy, delaying and fading networks.

YAML scenario → pydantic Scenario → channel sampler → estimator recursion →
metrics / closed forms → tidy CSV + PNG + manifest.
"""

import hashlib as _hashlib
import os as _os
import shutil as _shutil
from pathlib import Path as _Path

# netkf parallelizes across processes (--jobs, Dask) and its products are many small ones: BLAS
# threads only contend (a 24×24·24×10⁴ product measured 36× slower under load with threads). A
# user's own setting wins; this must run before numpy is first imported to take effect.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")

# numba's parallel kernels may run in this process before a process pool forks its workers
# (GNU OpenMP aborts a forked child: "fork() called from a process already using GNU OpenMP");
# the fork-safe threading layers (tbb, workqueue) do not. A user's own setting wins.
_os.environ.setdefault("NUMBA_THREADING_LAYER", "forksafe")


def _numba_cache_dir(pkg: _Path, root: _Path, keep: int = 8) -> str | None:
    """numba checks a cached function against its own source file only, so a compiled kernel that inlines another
    module's primitives (kalman_numba's, in the smoother, Markov and fading kernels) stayed stale when only that
    module changed: after a `git pull` of an editable install the smoother ran the old rescue. netkf's kernels are
    therefore cached per state of its compiled sources: ``root``/<digest of each .py file of ``pkg`` that names
    numba (a kernel, a compiled primitive, a kernel generator): path, size, mtime> (~3 ms), the ``keep`` newest
    such folders kept. None where it cannot be made (numba's default then)."""
    h = _hashlib.sha256()
    for f in sorted(pkg.rglob("*.py")):
        if b"numba" in f.read_bytes():
            st = f.stat()
            h.update(f"{f.relative_to(pkg)}:{st.st_size}:{st.st_mtime_ns};".encode())
    d = root / h.hexdigest()[:16]
    try:
        if not d.is_dir():
            d.mkdir(parents=True, exist_ok=True)
            for p in sorted((p for p in root.iterdir() if p.is_dir()), key=lambda p: p.stat().st_mtime)[:-keep]:
                _shutil.rmtree(p, ignore_errors=True)  # earlier states of the sources
    except OSError:  # no writable home
        return None
    return str(d)


if "NUMBA_CACHE_DIR" not in _os.environ:  # a user's own setting wins; set before numba is imported
    _dir = _numba_cache_dir(_Path(__file__).resolve().parent,
                            _Path(_os.environ.get("NETKF_NUMBA_CACHE", _Path.home() / ".cache" / "netkf" / "numba")))
    if _dir:
        _os.environ["NUMBA_CACHE_DIR"] = _dir

from netkf_cli.core._version import __version__  # noqa: E402,F401

from netkf_cli.app.api import load, run  # noqa: E402,F401  (the public API: netkf_cli.load / netkf_cli.run)
