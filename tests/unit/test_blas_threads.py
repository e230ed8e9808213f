"""One BLAS thread per Monte Carlo process, whatever was imported first (runtime.workers.limit_blas).

``import netkf_cli`` sets OPENBLAS_NUM_THREADS=1 (unless the user set it), but that only reaches OpenBLAS if numpy
was not imported yet. A script or notebook that imports numpy first got one BLAS thread per core in the parent
and in every forked worker: ``--jobs 2`` ran the Moayedi 4-state filter slower than ``--jobs 1``. Checked in a
fresh interpreter that imports numpy before netkf, in the parent and in a pool worker; a user's own setting
is kept."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

CODE = """
import numpy as np
import threadpoolctl
from netkf_cli.runtime import montecarlo

def blas():
    return [d["num_threads"] for d in threadpoolctl.threadpool_info() if d["user_api"] == "blas"]

class K:
    def __call__(self, rng, runs):
        return {"threads": np.asarray(blas(), dtype=float), "n": np.asarray(runs)}

before = blas()
with montecarlo.execution("process", jobs=2) as ex:
    inside = blas()
    got = montecarlo.run_chunked(K(), 4, 1, seed=0)
    procs = len(ex.chunk_pids)
import json
print(json.dumps([before, inside, got["threads"].tolist(), procs, blas()]))
"""


def _run(env_threads: str | None):
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS",
                                                             "MKL_NUM_THREADS")}
    if env_threads is not None:
        env["OPENBLAS_NUM_THREADS"] = env_threads
    out = subprocess.run([sys.executable, "-c", CODE], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_numpy_imported_first_still_runs_one_blas_thread_per_process():
    """(numpy's and scipy's OpenBLAS are two libraries: one per entry.)"""
    from netkf_cli.runtime.montecarlo import usable_cores

    before, inside, chunks, procs, after = _run(None)
    if max(before) < 2:
        pytest.skip("OpenBLAS starts with one thread here (one core): nothing to limit")
    assert inside == [1] * len(before)
    assert chunks == [4.0] * len(before)  # each of the 4 chunks saw one thread per library (summed over chunks)
    if usable_cores() >= 2:
        assert procs == 2  # the parent and its worker both computed chunks
    assert after == before  # the limit is the Monte Carlo's: the user's process gets its threads back


def test_a_users_own_blas_setting_is_kept():
    before, inside, chunks, procs, after = _run("2")
    assert before == inside == after == [2] * len(before) and chunks == [8.0] * len(before)
