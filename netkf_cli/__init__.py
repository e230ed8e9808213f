"""netkf — Kalman filtering over lossy, delaying and fading networks.

YAML scenario → pydantic Scenario → channel sampler → estimator recursion →
metrics / closed forms → tidy CSV + PNG + manifest.
"""

import os as _os

# netkf parallelizes across processes (--jobs, Dask) and its products are many small ones: BLAS
# threads only contend (a 24×24·24×10⁴ product measured 36× slower under load with threads). A
# user's own setting wins; this must run before numpy is first imported to take effect.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")

# numba's parallel kernels may run in this process before a process pool forks its workers
# (GNU OpenMP aborts a forked child: "fork() called from a process already using GNU OpenMP");
# the fork-safe threading layers (tbb, workqueue) do not. A user's own setting wins.
_os.environ.setdefault("NUMBA_THREADING_LAYER", "forksafe")

from netkf_cli.core._version import __version__  # noqa: E402,F401

from netkf_cli.app.api import load, run  # noqa: E402,F401  (the public API: netkf_cli.load / netkf_cli.run)
