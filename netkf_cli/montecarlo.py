"""Chunked, reproducible, resumable Monte Carlo.

Runs are split into chunks of ``chunk`` runs; chunk ``i`` draws from
``SeedSequence(seed, spawn_key=(i,))`` only. A kernel returns *additive* statistics
(counts, sums, sums of squares) which are summed in chunk order, so the result is
bitwise identical whatever executor (serial, local processes, Dask), job count or
completion order computed the chunks, and memory is bounded by the chunk size.

Where and how chunks run is not the recipe's business: the CLI sets it once with
:func:`execution` (``--jobs``, ``--executor dask --scheduler …``, ``--resume``) and every
:func:`run_chunked` call inside uses it. With a cache folder, each finished chunk's
statistics are stored (keyed by the resolved scenario's hash, the call's position in the
run and the chunk index) so an interrupted run can be resumed and yields exactly the
numbers of an uninterrupted one.
"""

from __future__ import annotations

import contextvars
import math
import os
import pickle
from collections.abc import Callable, Mapping
from concurrent.futures import Executor, ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from netkf_cli.errors import NetkfError

Stats = Mapping[str, np.ndarray | float | int]
Kernel = Callable[[np.random.Generator, int], Stats]


class ChunkFailed(NetkfError):
    """A chunk failed twice (first failure retried once)."""


@dataclass(frozen=True)
class Chunk:
    """One unit of Monte Carlo work: its index, its run count and its seed."""

    index: int
    runs: int
    seed: int
    first_run: int = 0

    def rng(self) -> np.random.Generator:
        return np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=(self.index,)))


def plan_chunks(runs: int, chunk: int, seed: int) -> list[Chunk]:
    """Split ``runs`` into chunks of ``chunk`` runs (the last one smaller)."""
    if runs < 1:
        raise ValueError(f"runs must be ≥ 1, got {runs}")
    chunk = max(1, min(chunk, runs))
    count = math.ceil(runs / chunk)
    return [Chunk(i, min(chunk, runs - i * chunk), seed, i * chunk) for i in range(count)]


def add_stats(total: dict | None, part: Stats) -> dict:
    """Add one chunk's statistics into the running total (creates it on first use)."""
    if total is None:
        return {k: np.array(v, copy=True) for k, v in part.items()}
    if set(total) != set(part):
        raise ValueError(f"kernel returned different keys across chunks: {sorted(total)} vs {sorted(part)}")
    for k, v in part.items():
        total[k] = total[k] + np.asarray(v)
    return total


def run_chunk(kernel: Kernel, c: Chunk) -> dict:
    return {k: np.asarray(v) for k, v in kernel(c.rng(), c.runs).items()}


@dataclass
class Execution:
    """Where chunks run: ``serial``, ``process`` (``jobs`` local processes) or ``dask``."""

    executor: str = "serial"
    jobs: int = 1
    scheduler: str | None = None  # dask: an address, or "local" for a LocalCluster
    cache_dir: Path | None = None  # resume store for this run (None: no caching)
    retries: int = 1
    calls: int = 0  # run_chunked calls so far in this run (part of the cache key)
    progress: Callable[[int], None] | None = None  # runs finished (when a recipe passes none)
    add_total: Callable[[int], None] | None = None  # runs planned: lets a progress bar show an ETA
    _pool: Executor | None = field(default=None, repr=False)
    _client: object | None = field(default=None, repr=False)
    _cluster: object | None = field(default=None, repr=False)

    def pool(self) -> Executor:
        if self._pool is None:
            self._pool = ProcessPoolExecutor(max_workers=self.jobs)
        return self._pool

    def client(self):
        if self._client is None:
            try:
                from dask.distributed import Client, LocalCluster
            except ImportError:
                raise NetkfError("--executor dask needs dask.distributed: pip install 'netkf[dask]'") from None
            if self.scheduler in (None, "local"):
                self._cluster = LocalCluster(n_workers=self.jobs, threads_per_worker=1, processes=True,
                                             dashboard_address=None)
                self._client = Client(self._cluster)
            else:
                self._client = Client(self.scheduler)
        return self._client

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None
        if self._client is not None:
            self._client.close()
            self._client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None


_EXEC: contextvars.ContextVar[Execution] = contextvars.ContextVar("netkf_execution", default=Execution())


@contextmanager
def execution(executor: str = "serial", jobs: int = 1, scheduler: str | None = None, cache_dir: Path | None = None,
              progress: Callable[[int], None] | None = None, add_total: Callable[[int], None] | None = None):
    """Run every :func:`run_chunked` inside this block on the given executor (and cache)."""
    if executor not in ("serial", "process", "dask"):
        raise ValueError(f"unknown executor {executor!r}")
    if executor == "process" and jobs <= 1:
        executor = "serial"
    ex = Execution(executor=executor, jobs=max(1, jobs), scheduler=scheduler,
                   cache_dir=Path(cache_dir) if cache_dir else None, progress=progress, add_total=add_total)
    token = _EXEC.set(ex)
    try:
        yield ex
    finally:
        _EXEC.reset(token)
        ex.close()


def _picklable(obj) -> bool:
    try:
        pickle.dumps(obj)
        return True
    except Exception:
        return False


def _cache_path(ex: Execution, call: int, label: str, c: Chunk) -> Path | None:
    if ex.cache_dir is None:
        return None
    safe = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in label)[:60]
    return ex.cache_dir / f"call{call:04d}-{safe}" / f"chunk{c.index:06d}-runs{c.runs}-seed{c.seed}.npz"


def _load(path: Path | None) -> dict | None:
    if path is None or not path.exists():
        return None
    try:
        with np.load(path) as z:
            return {k: z[k] for k in z.files}
    except Exception:
        return None  # a torn file from a killed run: recompute


def _store(path: Path | None, stats: dict) -> None:
    if path is None:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".tmp{os.getpid()}")
    with open(tmp, "wb") as f:
        np.savez(f, **stats)
    tmp.replace(path)


def _describe(label: str, c: Chunk) -> str:
    return f"chunk {c.index} (runs {c.first_run}–{c.first_run + c.runs - 1}, seed {c.seed}{', ' + label if label else ''})"


def run_chunked(
    kernel: Kernel,
    runs: int,
    chunk: int,
    seed: int,
    *,
    progress: Callable[[int], None] | None = None,
    label: str = "",
) -> dict[str, np.ndarray]:
    """Run ``kernel(rng, n)`` over all chunks and return the statistics summed in chunk order.

    ``progress(n_runs)`` is called as chunks finish. A failing chunk is retried once, then
    reported with its coordinates (:class:`ChunkFailed`).
    """
    ex = _EXEC.get()
    call = ex.calls
    ex.calls += 1
    progress = progress or ex.progress
    chunks = plan_chunks(runs, chunk, seed)
    if ex.add_total is not None:
        ex.add_total(runs)
    results: dict[int, dict] = {}
    paths = {c.index: _cache_path(ex, call, label, c) for c in chunks}
    todo = []
    for c in chunks:
        cached = _load(paths[c.index])
        if cached is not None:
            results[c.index] = cached
            if progress:
                progress(c.runs)
        else:
            todo.append(c)

    def finish(c: Chunk, stats: dict) -> None:
        results[c.index] = stats
        _store(paths[c.index], stats)
        if progress:
            progress(c.runs)

    mode = ex.executor
    if mode != "serial" and (len(todo) <= 1 or not _picklable(kernel)):
        mode = "serial"  # nothing to parallelize, or a closure that cannot travel to workers
    if mode == "serial":
        for c in todo:
            finish(c, _retrying(lambda c=c: run_chunk(kernel, c), label, c, ex.retries))
    elif mode == "process":
        pool = ex.pool()
        futures = {c.index: pool.submit(run_chunk, kernel, c) for c in todo}
        for c in todo:
            try:
                stats = futures[c.index].result()
            except (KeyboardInterrupt, SystemExit):
                raise
            except Exception:
                stats = _retrying(lambda c=c: pool.submit(run_chunk, kernel, c).result(), label, c, ex.retries - 1)
            finish(c, stats)
    else:  # dask
        from dask.distributed import as_completed

        client = ex.client()
        futs = {client.submit(run_chunk, kernel, c, pure=False): c for c in todo}
        for fut in as_completed(list(futs)):
            c = futs[fut]
            try:
                stats = fut.result()
            except Exception:
                stats = _retrying(lambda c=c: client.submit(run_chunk, kernel, c, pure=False).result(), label, c,
                                  ex.retries - 1)
            finish(c, stats)
    total = None
    for c in chunks:  # fixed order: bitwise identical sums
        total = add_stats(total, results[c.index])
    return total  # type: ignore[return-value]


def _retrying(fn, label: str, c: Chunk, retries: int):
    last = None
    for _ in range(max(0, retries) + 1):
        try:
            return fn()
        except (KeyboardInterrupt, SystemExit):
            raise
        except Exception as exc:  # noqa: BLE001 - reported with coordinates below
            last = exc
    raise ChunkFailed(f"Monte Carlo {_describe(label, c)} failed twice: {type(last).__name__}: {last}") from last


def mean_and_stderr(total: np.ndarray, total_sq: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Sample mean and its standard error from a sum and a sum of squares over ``n`` samples."""
    mean = np.asarray(total) / n
    var = np.maximum(np.asarray(total_sq) / n - mean**2, 0.0) * n / max(n - 1, 1)
    return mean, np.sqrt(var / n)


def proportion_stderr(p: np.ndarray | float, n: int) -> np.ndarray:
    """Standard error √(p(1−p)/n) of an empirical proportion over n independent samples."""
    p = np.asarray(p, dtype=float)
    return np.sqrt(np.clip(p * (1 - p), 0, None) / n)
