"""The compiled (numba) path of the ``buffered`` estimator against the numpy core, on the same traces.

``backend: numba`` runs the core's compiled filter (``kalman.Filter.run(backend="numba")``: a kernel
generated for the system from the core's equations, rescue-flagged runs on the numpy core) over the
time-k availabilities; the numpy path runs ``kalman.Filter.step``. On the same trace P_k agrees to
rounding, so the engine's statistics are identical: the counts Pr[P_k ≤ M] exactly (unless λ_max is
within rounding of a threshold, which these grids avoid) and the moment sums to 1e-12.
Skipped when numba is not installed.
"""

import numpy as np
import pytest

pytest.importorskip("numba")

from netkf_cli import engine
from netkf_cli.linalg import kalman  # noqa: E402
from netkf_cli.estimators.buffered import BufferedEstimator, availability, mkf  # noqa: E402
from netkf_cli.runtime.montecarlo import execution  # noqa: E402
from netkf_cli.core.system import LinearSystem  # noqa: E402

from ._systems import bernoulli, poisson, scalar_system, vehicle_system  # noqa: E402


def _dense_system() -> LinearSystem:
    """n = 3, m = 1 with generic coefficients, one exact 0, 1 and −1."""
    g = np.random.default_rng(11)
    A = g.normal(size=(3, 3)) * 0.6
    A[0, 1], A[2, 2], A[1, 0] = 0.0, 1.0, -1.0
    C = g.normal(size=(1, 3))
    L = g.normal(size=(3, 3))
    return LinearSystem.create(A, C, L @ L.T * 0.1 + 0.01 * np.eye(3), 0.3)


CASES = {  # name: (system, channel, M grid, horizon)
    "scalar": (scalar_system(), poisson(5, 10), np.geomspace(0.5, 250, 40), 60),
    "vehicle_pairs": (vehicle_system(), poisson(3, 5), np.geomspace(0.06, 3, 30), 40),
    "dense_3x1": (_dense_system(), bernoulli(0.6), np.geomspace(0.05, 20, 30), 30),
}


def _stats(s, ch, M, H, backend, runs=3000, chunk=1500):
    est = BufferedEstimator(kind="buffered", backend=backend)
    d = engine.simulate(s, ch, [est], engine.DistributionReducer(M, [H]), steps=[H], runs=runs, horizon=H,
                        seed=3, chunk=chunk)
    m = engine.simulate(s, ch, [est], engine.MomentReducer([H]), steps=[H], runs=runs, horizon=H, seed=3, chunk=chunk)
    return d, m


@pytest.mark.parametrize("name", list(CASES))
def test_numba_equals_numpy_statistics_on_the_same_traces(name):
    s, ch, M, H = CASES[name]
    dn, mn = _stats(s, ch, M, H, "numpy")
    dc, mc = _stats(s, ch, M, H, "numba")
    assert set(dn) == set(dc) and set(mn) == set(mc)
    for key in dn:
        assert np.array_equal(dn[key], dc[key]), key  # counts: identical
    for key in mn:
        a, b = np.asarray(mn[key], dtype=float), np.asarray(mc[key], dtype=float)
        assert np.allclose(a, b, rtol=1e-12, atol=0), key  # sums of P: equal to rounding


def test_flagged_runs_are_the_numpy_cores():
    """A = diag(10, 0.5): the Rescue flags a run once an outage drives tr P⁻ past 2e8 (≥ 4 lost packets in
    a row); the compiled filter hands those runs to the numpy core (bitwise the numpy path's); the
    others agree to rounding."""
    s = LinearSystem.create(np.diag([10.0, 0.5]), np.eye(2), np.eye(2), np.eye(2))
    tr = bernoulli(0.7).sample_trace(np.random.default_rng(2), 500, 60)
    f = kalman.Filter.of(s, 1)
    P = np.repeat(np.eye(2)[:, :, None], 500, axis=2)
    flagged = np.zeros(500, dtype=bool)
    for t in range(60):  # which runs the rescue test flags at some step (numpy core)
        Pm, P = f.step(P, tr.arrival[:, t])
        flagged |= f.rescue.flag(Pm)
    assert flagged.any() and not flagged.all()
    with np.errstate(all="ignore"):
        (_, Pn), = BufferedEstimator(kind="buffered", backend="numpy").covariances(s, tr, [60])
        (_, Pc), = BufferedEstimator(kind="buffered", backend="numba").covariances(s, tr, [60])
    a, b = Pn["filtered"], Pc["filtered"]
    assert np.array_equal(a[:, :, flagged], b[:, :, flagged])
    # the others to rounding: the update P⁻ − P⁻Cᵀ S⁻¹ C P⁻ loses ~ε·‖P⁻‖/‖R‖ digits, and unflagged
    # priors reach limit = 2e8, so relative to each run's largest entry 1e-16·2e8 = 2e-8 bounds it
    a, b = a[:, :, ~flagged], b[:, :, ~flagged]
    assert np.all(np.abs(a - b).max(axis=(0, 1)) <= 2e-8 * np.abs(a).max(axis=(0, 1)))


def test_process_pool_equals_numpy():
    s, ch, M, H = CASES["scalar"]
    ref, _ = _stats(s, ch, M, H, "numpy", runs=2000, chunk=500)
    with execution("process", jobs=2):
        got, _ = _stats(s, ch, M, H, "numba", runs=2000, chunk=500)
    for key in ref:
        assert np.array_equal(ref[key], got[key]), key


def test_backend_field_and_auto():
    """auto = the core's choice (kalman.choose_backend): compiled for chunks ≥ AUTO_MIN_RUN_STEPS."""
    s = vehicle_system()
    est = BufferedEstimator(kind="buffered")
    assert est.backend == "auto" and est.resolved_backend(s) == "numba"
    assert est.backend_used(s, poisson(3, 5), 100, 100) == "numpy"
    assert est.backend_used(s, poisson(3, 5), 20_000, 100) == "numba"
    assert BufferedEstimator(kind="buffered", backend="numpy").resolved_backend(s) == "numpy"
