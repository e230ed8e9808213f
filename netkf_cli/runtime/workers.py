"""Worker processes die with their parent, and leave Ctrl-C to it.

A Monte Carlo run starts worker processes (a ``ProcessPoolExecutor``, or Dask workers). If the
main process is killed (SIGKILL, OOM killer, a closed terminal), nothing tells those workers to
stop: they stay alive, holding memory and cores. And on Ctrl-C the terminal sends SIGINT to every
process of the group, so each idle worker printed its own ``KeyboardInterrupt`` traceback.

Use::

    from concurrent.futures import ProcessPoolExecutor
    from netkf_cli.runtime import workers

    pool = ProcessPoolExecutor(max_workers=jobs, **workers.pool_kwargs())

(create the pool in the thread that submits to it: see :func:`pool_kwargs`), and for Dask::

    from netkf_cli.runtime.dask_plugin import DieWithParentPlugin  # needs distributed (netkf[dask])

    client.register_plugin(DieWithParentPlugin())

Each worker then (1) ignores SIGINT (the parent handles Ctrl-C and shuts the pool down), (2) on
Linux asks the kernel for SIGTERM when its parent dies (``prctl(PR_SET_PDEATHSIG)``), and (3) runs
a watchdog thread that exits the worker within ``WATCHDOG_S`` seconds when its parent changes or
the main netkf process is gone (other systems, forkserver/spawn start methods, Dask nannies).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import multiprocessing
import os
import signal
import sys
import threading
import time
from contextlib import contextmanager

from threadpoolctl import threadpool_limits

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>
WATCHDOG_S = 0.5
EXIT_ORPHANED = 128 + signal.SIGTERM

_started = False


def set_parent_death_signal(sig: int = signal.SIGTERM) -> bool:
    """Linux: the kernel sends ``sig`` to this process when the thread that created it exits.
    Returns False where unavailable (not Linux, no libc)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        return _libc().prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


@functools.cache
def _libc():
    """The C library (Linux), loaded once; None where it cannot be loaded."""
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    except OSError:
        return None


def release_free_memory() -> bool:
    """Give the C heap's free pages back to the system (glibc ``malloc_trim(0)``); False where unavailable.

    A Monte Carlo chunk's arrays are freed when it ends, but glibc keeps freed heap memory for reuse, and
    after a freed large block its mmap threshold rises (up to 32 MB), so later arrays of that size come
    from the heap too: after the chunks, the parent went on to the analysis and the figure holding tens of
    MB it no longer used (smoothing table1: 248 → 205 MB PSS, markov example1 248 → 209, measured).
    Called where a phase ends (:func:`netkf_cli.runtime.montecarlo.run_chunked`), not per chunk: trimmed
    pages are faulted in again by the next chunk."""
    if not sys.platform.startswith("linux"):
        return False
    libc = _libc()
    trim = getattr(libc, "malloc_trim", None) if libc is not None else None
    if trim is None:  # not glibc (musl has no malloc_trim)
        return False
    trim(0)
    return True


def _alive(pid: int) -> bool:
    """True if ``pid`` exists and is not a zombie (a killed parent stays a zombie until reaped)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True  # exists, owned by someone else
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            return f.read().rsplit(b")", 1)[1].split()[0] != b"Z"
    except (OSError, IndexError):
        return True  # no /proc: trust kill(0)


def _origin() -> int:
    """The pid of the process that started this one: multiprocessing records it at start (the
    netkf process, even under the forkserver start method where ``getppid()`` is the server), so
    it is right even if that process died before this runs."""
    try:
        pp = multiprocessing.parent_process()
        if pp is not None and pp.pid:
            return int(pp.pid)
    except (ImportError, AttributeError, ValueError):
        pass
    return os.getppid()


def _orphaned(origin: int, ppid0: int, main_pid: int | None) -> bool:
    return (os.getppid() != ppid0 or not _alive(origin) or not _alive(ppid0)
            or (main_pid is not None and not _alive(main_pid)))


def start_watchdog(main_pid: int | None = None, interval: float = WATCHDOG_S) -> threading.Thread:
    """A daemon thread that ends this process when its parent changes (it was re-parented because
    the parent died), or the process that started it (or ``main_pid``) no longer exists."""
    origin, ppid0 = _origin(), os.getppid()

    def watch() -> None:
        while True:
            time.sleep(interval)
            if _orphaned(origin, ppid0, main_pid):
                os._exit(EXIT_ORPHANED)

    t = threading.Thread(target=watch, name="netkf-parent-watchdog", daemon=True)
    t.start()
    return t


BLAS_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def blas_threads() -> int:
    """BLAS threads per Monte Carlo process: ``OPENBLAS_NUM_THREADS`` (or OMP_, MKL_), which ``import netkf_cli``
    sets to 1 unless the user set one (netkf runs processes in parallel, and its matrix products are small)."""
    for var in BLAS_THREAD_VARS:
        try:
            return max(1, int(os.environ[var]))
        except (KeyError, ValueError):
            continue
    return 1


@contextmanager
def limit_blas():
    """Hold BLAS to :func:`blas_threads` threads in this process for the block (threadpoolctl). The environment
    variable takes effect only if set before numpy is first imported; a script or notebook that imported numpy
    before netkf got OpenBLAS's default, one thread per core, and with ``--jobs 2`` two such processes on two
    cores: the Moayedi 4-state filter's two chunks took 7.1–8.6 s in parallel, 4.9 s one after the other, 2.1 s
    with one thread each."""
    with threadpool_limits(limits=blas_threads(), user_api="blas"):
        yield


def init_worker(main_pid: int | None = None, pdeathsig: bool = True) -> None:
    """Pool-worker initializer: ignore SIGINT, default SIGTERM, die with the parent (PDEATHSIG + watchdog).

    ``main_pid`` is the netkf process that owns the pool (``os.getpid()`` there); if it is
    already gone when the worker starts, the worker exits at once."""
    global _started
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # not the parent's "SIGTERM = Ctrl-C" handler
    threadpool_limits(limits=blas_threads(), user_api="blas")  # for good: a forked worker inherits the parent's
    # limit, one started by spawn, forkserver or Dask does not
    if _started:
        return
    _started = True
    if pdeathsig:
        set_parent_death_signal(signal.SIGTERM)
    if _orphaned(_origin(), os.getppid(), main_pid):
        os._exit(EXIT_ORPHANED)  # the parent died before we could register
    start_watchdog(main_pid)


def pool_kwargs() -> dict:
    """``initializer``/``initargs`` for ``ProcessPoolExecutor`` (or ``multiprocessing.Pool``).

    PR_SET_PDEATHSIG fires when the *thread* that forked the worker ends, so it is only requested
    when the pool is created in the main thread (ProcessPoolExecutor starts workers from the
    thread that calls ``submit``; create and use the pool in one thread). Elsewhere the watchdog
    alone does the job."""
    in_main = threading.current_thread() is threading.main_thread()
    return {"initializer": init_worker, "initargs": (os.getpid(), in_main)}


def die_with_parent(main_pid: int | None = None, pdeathsig: bool = True) -> None:
    """Alias of :func:`init_worker` (the name ``montecarlo._worker_init`` calls): in a pool worker,
    ignore SIGINT and exit when the parent process dies."""
    init_worker(main_pid, pdeathsig)
