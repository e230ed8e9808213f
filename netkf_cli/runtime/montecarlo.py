"""Chunked, reproducible, resumable Monte Carlo.

Runs are split into chunks of ``chunk`` runs; chunk ``i`` of stream ``s`` draws from
``SeedSequence(seed, spawn_key=(s, i))`` only (``stream`` names an independent Monte Carlo
computation inside one artefact — a grid point, a channel variant — never seed arithmetic;
the same stream gives common random numbers). A kernel returns *additive* statistics
(counts, sums, sums of squares) which are summed in chunk order, so the result is
bitwise identical whatever executor (serial, local processes, Dask), job count or
completion order computed the chunks, and memory is bounded by the chunk size.

Where and how chunks run is not the recipe's business: the CLI sets it once with
:func:`execution` (``--jobs``, ``--executor dask --scheduler …``, ``--resume``) and every
:func:`run_chunked` call inside uses it. With a cache folder (the result folder's own,
``<parent>/.netkf-cache/<folder>/``, stamped by the runner with the scenario hash so that only the
identical scenario reuses it), each finished chunk's statistics are stored (keyed by the call's
position in the run, the stream and the chunk index) so an interrupted run can be resumed and
yields exactly the numbers of an uninterrupted one.
"""

from __future__ import annotations

import contextvars
import gc
import json
import math
import os
import pickle
import re
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Executor, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from netkf_cli.core.stats import mean_se, proportion_stderr, wilson_interval  # noqa: F401 (re-exported: one statistics module)
from netkf_cli.core import llvm_pages
from netkf_cli.core.errors import ConfigError, NetkfError
from netkf_cli.runtime.workers import pool_kwargs  # pool workers ignore Ctrl-C and die with this process
from netkf_cli.runtime.workers import limit_blas, release_free_memory

Stats = Mapping[str, np.ndarray | float | int]
Kernel = Callable[[np.random.Generator, int], Stats]


class ChunkFailed(NetkfError):
    """A chunk failed twice (first failure retried once)."""


class KernelNotShippable(NetkfError):
    """A Monte Carlo kernel cannot be pickled, so it cannot run on worker processes (a bug)."""


@dataclass(frozen=True)
class Chunk:
    """One unit of Monte Carlo work: its index, its run count, its seed and its stream."""

    index: int
    runs: int
    seed: int
    first_run: int = 0
    stream: int = 0

    def rng(self) -> np.random.Generator:
        return np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=(self.stream, self.index)))


class ChunkPlan(Sequence):
    """The chunks of one Monte Carlo computation, made on demand (memory independent of ``runs``)."""

    def __init__(self, runs: int, chunk: int, seed: int, stream: int = 0):
        if runs < 1:
            raise ValueError(f"runs must be ≥ 1, got {runs}")
        self.runs, self.chunk, self.seed, self.stream = runs, max(1, min(chunk, runs)), seed, stream
        self.count = math.ceil(runs / self.chunk)

    def __len__(self) -> int:
        return self.count

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(self.count))]
        if i < 0:
            i += self.count
        if not 0 <= i < self.count:
            raise IndexError(i)
        return Chunk(i, min(self.chunk, self.runs - i * self.chunk), self.seed, i * self.chunk, self.stream)


def plan_chunks(runs: int, chunk: int, seed: int, stream: int = 0) -> ChunkPlan:
    """Split ``runs`` into chunks of ``chunk`` runs (the last one smaller), lazily."""
    return ChunkPlan(runs, chunk, seed, stream)


def add_stats(total: dict | None, part: Stats) -> dict:
    """Add one chunk's statistics into the running total (creates it on first use).

    Keys are summed, except ``max_*`` (element-wise maximum) and ``min_*`` (minimum): all three
    are associative, so the chunk-order total is the same for every executor.
    """
    if total is None:
        return {k: np.array(v, copy=True) for k, v in part.items()}
    if set(total) != set(part):
        raise ValueError(f"kernel returned different keys across chunks: {sorted(total)} vs {sorted(part)}")
    for k, v in part.items():
        if k.startswith("max_"):
            total[k] = np.maximum(total[k], np.asarray(v))
        elif k.startswith("min_"):
            total[k] = np.minimum(total[k], np.asarray(v))
        else:
            total[k] = total[k] + np.asarray(v)
    return total


PID_KEY = "__pid__"


def run_chunk(kernel: Kernel, c: Chunk) -> dict:
    """Run one chunk; the statistics carry the pid of the process that computed them."""
    stats = {k: np.asarray(v) for k, v in kernel(c.rng(), c.runs).items()}
    stats[PID_KEY] = np.asarray(os.getpid())
    return stats


def _plus_one(x):
    return x + 1.0


def warm_compiler() -> None:
    """Set up numba's compiler in this process (one trivial compiled call), if numba is installed."""
    try:
        import numba  # optional dependency (netkf runs on numpy without it)
    except ImportError:
        return
    llvm_pages.install()
    numba.njit(cache=True)(_plus_one)(1.0)


@dataclass
class Execution:
    """Where chunks run: ``serial``, ``process`` (``jobs`` local processes) or ``dask``."""

    executor: str = "serial"
    jobs: int = 1
    scheduler: str | None = None  # dask: an address, or "local" for a LocalCluster
    cache_dir: Path | None = None  # resume store for this run (None: no caching)
    retries: int = 1
    calls: int = 0  # run_chunked calls so far in this run (part of the cache key)
    chunk_pids: dict = field(default_factory=dict)  # pid → number of chunks it computed (the manifest reports it)
    chunks_cached: int = 0  # chunks taken from the resume cache
    progress: Callable[[int], None] | None = None  # runs finished (when a recipe passes none)
    add_total: Callable[[int], None] | None = None  # runs planned: lets a progress bar show an ETA
    _pool: Executor | None = field(default=None, repr=False)
    _client: object | None = field(default=None, repr=False)
    _cluster: object | None = field(default=None, repr=False)

    def workers(self) -> int:
        """Worker processes of the ``process`` executor: ``jobs − 1``, because the parent computes chunks too
        (:func:`run_chunked`). An idle parent holding the imports, numba's compiler and the scenario while
        ``jobs`` workers compute cost a whole process of memory (fig5: 3 processes, ~90 MB PSS each worker)."""
        return max(1, self.jobs - 1)

    def pool(self) -> Executor:
        if self._pool is None:
            # Forked workers share the parent's pages until written; the cyclic collector writes to every
            # object it visits, so each worker soon owned a private copy of the parent's heap (~100 MB of
            # 500 MB PSS for a 2-worker run). Frozen objects are never visited (gc.freeze, the CPython
            # docs' recipe for pre-fork servers); refcounting still frees them. Unfrozen again in close().
            # numba's compiler (LLVM, the target and typing contexts: ~70 MB, measured) is set up on the first
            # compiled call of a process: in every worker it was a private copy (fig5: 83 MB private per
            # worker). Set up here, before the fork, the workers share it and load only their own kernels.
            warm_compiler()
            gc.collect()
            gc.freeze()
            self._pool = ProcessPoolExecutor(max_workers=self.workers(), **pool_kwargs())
        return self._pool

    def client(self):
        if self._client is None:
            try:
                from dask.distributed import Client, LocalCluster  # optional (netkf[dask]): seconds to import
            except ImportError:
                raise NetkfError("--executor dask needs dask.distributed: pip install 'netkf[dask]'") from None
            if self.scheduler in (None, "local"):
                # no dashboard; the scheduler's HTTP server (health routes) on a free local port, not on 8787
                # (taken by another cluster: a warning) nor on every interface
                self._cluster = LocalCluster(n_workers=self.jobs, threads_per_worker=1, processes=True,
                                             dashboard_address=None,
                                             scheduler_kwargs={"dashboard_address": "127.0.0.1:0"})
                self._client = Client(self._cluster)
                from netkf_cli.runtime.dask_plugin import DieWithParentPlugin  # optional: subclasses distributed's WorkerPlugin

                register = getattr(self._client, "register_plugin", None) or self._client.register_worker_plugin
                register(DieWithParentPlugin())  # local workers exit if this process is killed
            else:
                self._client = Client(self.scheduler)
        return self._client

    def report(self) -> dict:
        """Where the chunks really ran: counts per process, and how many ran in this (the parent) process."""
        parent = os.getpid()
        out = {"chunks": sum(self.chunk_pids.values()), "processes": len(self.chunk_pids),
               "chunks_in_parent": self.chunk_pids.get(parent, 0)}
        if self.chunks_cached:
            out["chunks_from_resume_cache"] = self.chunks_cached
        return out

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None
            gc.unfreeze()
        if self._client is not None:
            self._client.close()
            self._client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None


_EXEC: contextvars.ContextVar[Execution] = contextvars.ContextVar("netkf_execution", default=Execution())

_RUN_CACHES: list[dict] = []


def run_cache(cache: dict) -> dict:
    """Register a module-level cache of data that only the current run can read again (a chunk's trace,
    by generator state): it is emptied when the :func:`execution` block ends, before the run writes its
    tables and figure (fusion/fig3: 10 MB of the last point's traces were still held while drawing)."""
    _RUN_CACHES.append(cache)
    return cache


@contextmanager
def execution(executor: str = "serial", jobs: int = 1, scheduler: str | None = None, cache_dir: Path | None = None,
              progress: Callable[[int], None] | None = None, add_total: Callable[[int], None] | None = None):
    """Run every :func:`run_chunked` inside this block on the given executor (and cache)."""
    if executor not in ("serial", "process", "dask"):
        raise ValueError(f"unknown executor {executor!r}")
    if executor == "process":
        jobs = min(jobs, usable_cores())  # more processes than cores only add memory (each imports numpy …)
        if jobs <= 1:
            executor = "serial"
    ex = Execution(executor=executor, jobs=max(1, jobs), scheduler=scheduler,
                   cache_dir=Path(cache_dir) if cache_dir else None, progress=progress, add_total=add_total)
    token = _EXEC.set(ex)
    try:
        with limit_blas():  # one BLAS thread here, as in every worker, whatever was imported first
            yield ex
    finally:
        _EXEC.reset(token)
        ex.close()
        for cache in _RUN_CACHES:
            cache.clear()


def available_memory() -> float | None:
    """Bytes of memory available to new allocations (Linux: /proc/meminfo's MemAvailable; else the free physical
    pages where the system tells); None where unknown."""
    try:
        for line in Path("/proc/meminfo").read_text(encoding="ascii").splitlines():
            if line.startswith("MemAvailable:"):
                return float(line.split()[1]) * 1024.0
    except OSError:
        pass
    try:
        return float(os.sysconf("SC_AVPHYS_PAGES")) * float(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        return None


TRACE_BYTES_PER_RUN_STEP = 8.0
"""What a chunk holds per run and step: its runs' sampled traces (the channel's uniforms, one float64 each),
measured 7.2 (bernoulli + kf) and 9.2 (delay + buffered) bytes per run-step above the process's base on 2e4 × 5e3
chunks; the pre-flight check (:func:`check_chunk_memory`) refuses a chunk plan far above what the machine has."""


def check_chunk_memory(chunk_runs: int, horizon: int, processes: int) -> None:
    """Refuse (montecarlo.chunk) a plan whose chunks cannot fit in the available memory: each of ``processes``
    holds a chunk's traces, about TRACE_BYTES_PER_RUN_STEP per run-step. Memory is bounded by the chunk size
    *and* the horizon; a run that would be killed by the system's out-of-memory killer is refused before it starts."""
    avail = available_memory()
    need = TRACE_BYTES_PER_RUN_STEP * float(chunk_runs) * float(horizon) * max(1, processes)
    if avail is None or need <= 0.8 * avail:
        return
    fit = int(0.8 * avail / (TRACE_BYTES_PER_RUN_STEP * float(horizon) * max(1, processes)))
    hint = (f"lower montecarlo.chunk (chunks of {fit} runs would fit; the chunk is part of the random stream layout, "
            "so the numbers change), the horizon or --jobs" if fit >= 1 else "lower the horizon")
    raise ConfigError.at("montecarlo.chunk" if fit >= 1 else "montecarlo.horizon", f"a chunk holds its runs' whole traces: {chunk_runs} runs × {horizon} steps "
                                             f"is about {need / 1e9:.3g} GB in {max(1, processes)} process"
                                             f"{'es' if processes > 1 else ''}, above the {avail / 1e9:.3g} GB this "
                                             f"machine has available; {hint}")


def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity where the system tells, else the CPU count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _require_picklable(kernel, label: str) -> None:
    """A kernel must travel to worker processes; a closure is a bug, never a silent serial run."""
    try:
        pickle.dumps(kernel)
    except Exception as exc:
        raise KernelNotShippable(
            f"Monte Carlo kernel {type(kernel).__name__}{' (' + label + ')' if label else ''} cannot be pickled, "
            f"so it cannot run on worker processes: {type(exc).__name__}: {exc}. Kernels must be module-level "
            f"classes (netkf_cli/estimators/); this is a bug in netkf, please report it") from None


def _cache_path(ex: Execution, call: int, label: str, c: Chunk) -> Path | None:
    if ex.cache_dir is None:
        return None
    safe = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in label)[:60]
    return ex.cache_dir / f"call{call:04d}-{safe}" / f"s{c.stream}-chunk{c.index:06d}-runs{c.runs}-seed{c.seed}{CHUNK_SUFFIX}"


CHUNK_SUFFIX = ".chunk"
"""A finished chunk's statistics in the resume store (``<parent>/.netkf-cache/<folder>/``)."""


def stored_runs(cache_dir: Path) -> int:
    """How many Monte Carlo runs the resume store under ``cache_dir`` holds (what ``--resume`` reuses),
    read off its chunk files' names (``…-runs<n>-…``); a chunk is stored before its runs are reported to
    the progress bar, so after an interrupt this can be ahead of it."""
    if not cache_dir.is_dir():
        return 0
    return sum(int(m.group(1)) for p in cache_dir.rglob(f"*{CHUNK_SUFFIX}")
               if (m := re.search(r"-runs(\d+)-seed", p.name)))


_CHUNK_MAGIC = b"netkf-chunk-1\n"


def _dump_stats(stats: Mapping) -> bytes:
    """A chunk's statistics as bytes: a magic line, the length of a JSON header ``[[key, dtype, shape], …]``,
    the header, then each array's bytes in order. np.savez wrote a zip member per array (fading_sec42's 116
    chunks: 191 ms CPU to store, now 53 ms, most of it creating and renaming the files); nothing is pickled
    (an object array is refused: TypeError)."""
    arrays = {str(k): np.asarray(v) for k, v in stats.items()}  # tobytes() is C order whatever the layout
    if any(a.dtype.hasobject for a in arrays.values()):
        raise TypeError("chunk statistics hold an object array: not stored")
    header = json.dumps([[k, a.dtype.str, list(a.shape)] for k, a in arrays.items()]).encode()
    return b"".join([_CHUNK_MAGIC, len(header).to_bytes(8, "little"), header, *(a.tobytes() for a in arrays.values())])


def _parse_stats(data: bytes) -> dict | None:
    """:func:`_dump_stats`' bytes back to ``{key: array}`` (writable copies); None for anything else (a torn
    file from a killed run, another format): the chunk is then computed again."""
    m = len(_CHUNK_MAGIC)
    if not data.startswith(_CHUNK_MAGIC) or len(data) < m + 8:
        return None
    n = int.from_bytes(data[m:m + 8], "little")
    try:
        header = json.loads(data[m + 8:m + 8 + n])
        off, out = m + 8 + n, {}
        for key, dt, shape in header:
            dt = np.dtype(dt)
            count = math.prod(shape)
            if dt.hasobject or off + count * dt.itemsize > len(data):
                return None
            out[key] = np.frombuffer(data, dtype=dt, count=count, offset=off).reshape(shape).copy()
            off += count * dt.itemsize
    except (ValueError, TypeError):
        return None
    return out if off == len(data) else None


def _load(path: Path | None) -> dict | None:
    if path is None:
        return None
    try:
        data = path.read_bytes()
    except OSError:
        return None
    return _parse_stats(data)


def _store(path: Path | None, stats: dict) -> None:
    if path is None:
        return
    try:
        data = _dump_stats(stats)
    except TypeError:
        return  # not storable: a resumed run computes this chunk again
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".tmp{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
        tmp.replace(path)
    except BaseException:  # a full disk, an interrupt mid-write: no torn temporary file stays behind
        try:
            tmp.unlink()
        except OSError:
            pass
        raise


def _describe(label: str, c: Chunk) -> str:
    return (f"chunk {c.index} of stream {c.stream} (runs {c.first_run}–{c.first_run + c.runs - 1}, seed {c.seed}"
            f"{', ' + label if label else ''})")


def run_chunked(
    kernel: Kernel,
    runs: int,
    chunk: int,
    seed: int,
    *,
    stream: int = 0,
    progress: Callable[[int], None] | None = None,
    label: str = "",
) -> dict[str, np.ndarray]:
    """Run ``kernel(rng, n)`` over all chunks of ``stream`` and return the statistics summed in chunk order.

    Chunks are planned lazily and summed as they complete in order (at most a window of
    ``2 × jobs`` chunks is held), so memory does not grow with ``runs``. ``progress(n_runs)`` is
    called as chunks finish. A chunk is retried only when its worker process was lost; an
    exception raised by a kernel is a bug and propagates with the chunk's coordinates.
    """
    ex = _EXEC.get()
    call = ex.calls
    ex.calls += 1
    progress = progress or ex.progress
    chunks = plan_chunks(runs, chunk, seed, stream)
    if ex.add_total is not None:
        ex.add_total(runs)
    mode = ex.executor
    if mode != "serial":
        _require_picklable(kernel, label)
        if len(chunks) <= 1:
            mode = "serial"  # nothing to parallelize
    total: dict | None = None

    def finish(c: Chunk, stats: dict, path: Path | None, cached: bool) -> None:
        nonlocal total
        pid = stats.pop(PID_KEY, None)
        if cached:
            ex.chunks_cached += 1
        elif pid is not None:
            ex.chunk_pids[int(pid)] = ex.chunk_pids.get(int(pid), 0) + 1
        if not cached:
            _store(path, stats)
        total = add_stats(total, stats)
        if progress:
            progress(c.runs)

    def attempt(fn, c: Chunk):
        try:
            return fn()
        except (KeyboardInterrupt, SystemExit):
            raise
        except Exception as exc:
            exc.add_note(f"netkf: raised by Monte Carlo {_describe(label, c)}")
            raise

    if mode == "serial":
        for c in chunks:
            path = _cache_path(ex, call, label, c)
            cached = _load(path)
            stats = cached if cached is not None else attempt(lambda c=c: run_chunk(kernel, c), c)
            finish(c, stats, path, cached is not None)
        release_free_memory()  # the chunks' freed arrays: back to the system before the analysis and figure
        return total  # type: ignore[return-value]

    # ``process``: the parent is one of the ``jobs`` processes (Execution.workers). It keeps the workers'
    # window full and, while the chunk it needs next is still running there, computes the next unsubmitted
    # chunk itself. Which process computes a chunk does not change its numbers (its own SeedSequence), and
    # the sums are still taken in chunk order.
    in_parent = mode == "process"
    window = max(2, 2 * (ex.workers() if in_parent else ex.jobs))
    # chunks queued on the pool: with the parent computing too, one per worker — two per worker left the parent
    # nothing to do at the end of a short run (2 chunks: both went to the one worker of --jobs 2, the parent
    # waited; 4 chunks: the parent computed 1), so a few-chunk run barely ran in parallel
    queued = ex.workers() if in_parent else window
    pending: dict[int, object] = {}
    done: dict[int, dict] = {}  # chunks the parent computed ahead of the one summed next
    nxt = 0  # next chunk index to submit (or compute here)

    def submit(c: Chunk):
        if mode == "process":
            return ex.pool().submit(run_chunk, kernel, c)
        return ex.client().submit(run_chunk, kernel, c, pure=False)

    def fill() -> None:
        nonlocal nxt
        while nxt < len(chunks) and len(pending) < queued:
            cn = chunks[nxt]
            if _load(_cache_path(ex, call, label, cn)) is None:
                pending[cn.index] = submit(cn)
            nxt += 1

    for c in chunks:  # consume in order; keep the window full
        fill()
        path = _cache_path(ex, call, label, c)
        if c.index in done:
            finish(c, done.pop(c.index), path, False)
            continue
        cached = _load(path) if c.index not in pending else None
        if cached is not None:
            finish(c, cached, path, True)
            continue
        fut = pending.pop(c.index)
        while in_parent and not fut.done() and nxt < len(chunks) and len(done) < window:
            cn = chunks[nxt]
            nxt += 1
            if _load(_cache_path(ex, call, label, cn)) is None:
                done[cn.index] = attempt(lambda cn=cn: run_chunk(kernel, cn), cn)
            fill()
        stats = None
        for lost in range(ex.retries + 1):
            try:
                stats = attempt(fut.result, c)
                break
            except Exception as exc:
                if not _worker_lost(exc) or lost == ex.retries:
                    if _worker_lost(exc):
                        raise ChunkFailed(f"Monte Carlo {_describe(label, c)}: its worker process was lost "
                                          f"{lost + 1} times ({type(exc).__name__})") from exc
                    raise
                if mode == "process":  # a dead worker breaks the whole pool: rebuild and resubmit
                    if ex._pool is not None:
                        ex._pool.shutdown(wait=False, cancel_futures=True)
                    ex._pool = None
                    for k in list(pending):
                        pending[k] = submit(chunks[k])
                fut = submit(c)
        finish(c, stats, path, False)
    release_free_memory()
    return total  # type: ignore[return-value]


def _worker_lost(exc: BaseException) -> bool:
    """True when a chunk failed because its worker died (not because our code raised)."""
    if isinstance(exc, BrokenProcessPool):
        return True
    name = type(exc).__name__
    return name in ("KilledWorker", "CommClosedError", "FutureCancelledError")


def mean_and_stderr(total: np.ndarray, total_sq: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Sample mean and its standard error from a sum and a sum of squares over ``n`` samples
    (:func:`netkf_cli.core.stats.mean_se`, the one rule)."""
    return mean_se(total, total_sq, n)
