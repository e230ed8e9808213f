"""Chunked, reproducible Monte Carlo.

Runs are split into chunks of ``chunk`` runs; chunk ``i`` draws from
``SeedSequence(seed, spawn_key=(i,))`` only. A kernel returns *additive* statistics
(counts, sums, sums of squares) which are summed in chunk order, so the result is
bitwise identical whatever executor, job count or scheduling order computed the chunks,
and memory is bounded by the chunk size.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

Stats = Mapping[str, np.ndarray | float | int]
Kernel = Callable[[np.random.Generator, int], Stats]


@dataclass(frozen=True)
class Chunk:
    """One unit of Monte Carlo work: its index, its run count and its seed."""

    index: int
    runs: int
    seed: int

    def rng(self) -> np.random.Generator:
        return np.random.default_rng(np.random.SeedSequence(self.seed, spawn_key=(self.index,)))


def plan_chunks(runs: int, chunk: int, seed: int) -> list[Chunk]:
    """Split ``runs`` into chunks of ``chunk`` runs (the last one smaller)."""
    if runs < 1:
        raise ValueError(f"runs must be ≥ 1, got {runs}")
    chunk = max(1, min(chunk, runs))
    count = math.ceil(runs / chunk)
    return [Chunk(i, min(chunk, runs - i * chunk), seed) for i in range(count)]


def add_stats(total: dict | None, part: Stats) -> dict:
    """Add one chunk's statistics into the running total (creates it on first use)."""
    if total is None:
        return {k: np.array(v, dtype=float if np.asarray(v).dtype.kind == "f" else np.asarray(v).dtype, copy=True) for k, v in part.items()}
    if set(total) != set(part):
        raise ValueError(f"kernel returned different keys across chunks: {sorted(total)} vs {sorted(part)}")
    for k, v in part.items():
        total[k] = total[k] + np.asarray(v)
    return total


def run_chunk(kernel: Kernel, c: Chunk) -> Stats:
    return kernel(c.rng(), c.runs)


def run_chunked(
    kernel: Kernel,
    runs: int,
    chunk: int,
    seed: int,
    *,
    progress: Callable[[int], None] | None = None,
    label: str = "",
) -> dict[str, np.ndarray]:
    """Run ``kernel(rng, n)`` over all chunks and return the summed statistics.

    ``progress(n_runs_done_in_this_chunk)`` is called after every chunk.
    """
    total = None
    for c in plan_chunks(runs, chunk, seed):
        total = add_stats(total, run_chunk(kernel, c))
        if progress is not None:
            progress(c.runs)
    return total  # type: ignore[return-value]


def mean_and_stderr(total: np.ndarray, total_sq: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Sample mean and its standard error from a sum and a sum of squares over ``n`` samples."""
    mean = np.asarray(total) / n
    var = np.maximum(np.asarray(total_sq) / n - mean**2, 0.0) * n / max(n - 1, 1)
    return mean, np.sqrt(var / n)


def proportion_stderr(p: np.ndarray | float, n: int) -> np.ndarray:
    """Standard error √(p(1−p)/n) of an empirical proportion over n independent samples."""
    p = np.asarray(p, dtype=float)
    return np.sqrt(np.clip(p * (1 - p), 0, None) / n)
