"""mkf_runs' three ways to find the oldest kept packet arriving at each k (numpy: a pass per delay value below
MKF_DELAY_LOOP_MAX, np.maximum.at's scatter above; compiled: a vectorized pass per delay value at each k) give the same counts, on random delay traces with lost packets,
delays beyond the buffer and beyond the horizon, for both buffer conventions and no buffer at all."""

from __future__ import annotations

import numpy as np
import pytest

from netkf_cli.estimators import buffered
from netkf_cli.core.trace import LOST, Trace


def _trace(rng, T, runs, D, convention):
    d = rng.poisson(4.0, (T, runs)).astype(np.int32)
    d[rng.random((T, runs)) < 0.2] = LOST
    meta = {} if D is None else {"buffer": D, "convention": convention}
    return Trace(runs=runs, horizon=T, delay=d[None], arrival=(d == 0)[None], meta=meta)


@pytest.mark.parametrize("D,convention", [(0, "delay_le_D"), (3, "delay_le_D"), (3, "delay_lt_D"), (12, "delay_le_D"),
                                          (None, "delay_le_D")])
def test_delay_passes_equal_the_scatter(D, convention, monkeypatch):
    tr = _trace(np.random.default_rng(D or 99), 40, 300, D, convention)
    steps = range(1, 41)
    fast = [r.copy() for _, r in buffered.mkf_runs(tr, steps, compiled=False)]
    monkeypatch.setattr(buffered, "MKF_DELAY_LOOP_MAX", 0)  # force the scatter
    slow = [r.copy() for _, r in buffered.mkf_runs(tr, steps, compiled=False)]
    assert all(np.array_equal(a, b) for a, b in zip(fast, slow))
    if buffered._oldest_compiled() is not None:  # numba present: the compiled pass (the default) gives them too
        comp = [r.copy() for _, r in buffered.mkf_runs(tr, steps)]
        assert all(np.array_equal(a, b) and a.dtype == b.dtype for a, b in zip(fast, comp))
    top = max(float(a.max()) for a in fast)
    assert top == 1.0 if D == 0 else top > 1.0  # D = 0 keeps only undelayed packets; else delayed ones arrive and count
