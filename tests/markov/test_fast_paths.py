"""The fast paths of the Markov filters' state-level simulation equal their references to rounding.

Each compiled or closed-form path consumes the same random numbers as the numpy reference, so the
numbers agree to floating-point rounding (amplified only by a matrix's conditioning)."""

from __future__ import annotations

import numpy as np
import pytest

from netkf_cli.linalg import kalman
from netkf_cli.engine import state
from netkf_cli.channels.markov_modes import MarkovModesChannel
from netkf_cli.estimators.markov_filters import AugmentedModel, numba_available
from netkf_cli.estimators.markov_lmi import MarkovLMIEstimator
from netkf_cli.core.system import LinearSystem

EPS = np.finfo(float).eps


@pytest.mark.parametrize("n", [1, 2])
def test_nees_closed_form_equals_eigh(n):
    rng = np.random.default_rng(7)
    R = 4000
    L = rng.standard_normal((n, n, R))
    P = np.einsum("ikr,jkr->ijr", L, L)
    P[:, :, :50] = 0.0                                   # rank 0
    P[:, :, 50:100] = 3.0 * np.eye(n)[:, :, None]        # scaled identity (any eigenbasis)
    v = rng.standard_normal((n, 1, R))
    P[:, :, 100:200] = (v * v.transpose(1, 0, 2))[:, :, 100:200]  # rank 1
    if n == 2:
        P[:, :, 200:250] = np.diag([2.0, 0.0])[:, :, None]  # exactly singular, axis-aligned
        P[:, :, 250:300] = np.diag([0.0, 5.0])[:, :, None]
    e = rng.standard_normal((n, R))
    q_ref, r_ref = state.nees_eigh(e, P)
    q, r = state.nees(e, P)
    np.testing.assert_array_equal(r, r_ref)
    w = np.linalg.eigvalsh(np.moveaxis(P, -1, 0))
    cond = np.where(w[:, 0] > 1e-9 * w[:, -1], w[:, -1] / np.maximum(w[:, 0], 1e-300), 1.0)
    assert np.all(np.abs(q - q_ref) <= 16 * EPS * cond * np.maximum(np.abs(q_ref), 1.0))


# ----------------------------------------------------------------------------- compiled vs numpy, per filter
needs_numba = pytest.mark.skipif(not numba_available(), reason="the compiled paths need numba (netkf[fast])")

EX1 = dict(A=[[1.7240, -0.7788], [1, 0]], C=[[0.0286, 0.0264]], Q=[[1, 0], [0, 0]], R=0.04, S=[[0.2], [0.0]],
           T=[[0.8, 0.0, 0.10, 0.10], [0.8, 0.1, 0.05, 0.05], [0.8, 0.1, 0.05, 0.05], [0.8, 0.1, 0.05, 0.05]],
           rho=[0.8, 0.02, 0.09, 0.09])
EX2 = dict(A=[[0.8, 0], [0.9, 0.2]], C=[[1, 1]], Q=[[0.36, 0.30], [0.30, 0.25]], R=0.25, S=None,
           T=[[0.7, 0.0, 0.1, 0.2], [0.7, 0.15, 0.05, 0.1], [0.7, 0.15, 0.05, 0.1], [0.7, 0.15, 0.05, 0.1]],
           rho=[0.7, 0.045, 0.085, 0.17])


def _estimates(case, filt, backend, runs=300, horizon=30):
    sysm = LinearSystem.create(case["A"], case["C"], case["Q"], case["R"], P0=np.zeros((2, 2)))
    ch = MarkovModesChannel(kind="markov_modes", transition=case["T"], initial="stationary")
    est = MarkovLMIEstimator(kind="markov_lmi", filter=filt, rho=case["rho"], S=case["S"], design="closed_form",
                             sdp_check=0, backend=backend)
    rng = np.random.default_rng(11)
    trace = ch.sample_trace(rng, runs, horizon)
    S = None if case["S"] is None else np.asarray(case["S"], float)
    st = state.simulate(sysm, trace, rng, S)
    steps = list(range(1, horizon + 1))
    return [(k, {q: (x.copy(), P.copy()) for q, (x, P) in r.items()})
            for k, r in est.estimates(sysm, trace, st.z, steps, ("filtered", "predicted"))]


@needs_numba
@pytest.mark.parametrize("case", [EX1, EX2], ids=["example1", "example2"])
@pytest.mark.parametrize("filt", ["mode_aware", "lmi", "naive"])
def test_compiled_estimates_equal_numpy(case, filt):
    """Same simulated measurements → the same x̂ and P to rounding. Tolerance: the recursions run ≤ 30 steps
    of products of O(10) terms in another order, ≈ 1e3·ε per step relative, amplified by the conditioning
    of Example 1's (A nearly unstable, C ≈ 0.03) update: 1e-10 relative to max(1, |value|)."""
    ref, got = _estimates(case, filt, "numpy"), _estimates(case, filt, "numba")
    assert [k for k, _ in ref] == [k for k, _ in got]
    for (k, r1), (_, r2) in zip(ref, got):
        for q in ("filtered", "predicted"):
            for a, b in zip(r1[q], r2[q]):
                assert np.array_equal(np.isfinite(a), np.isfinite(b)), (filt, k, q)
                ok = np.isfinite(a)
                np.testing.assert_allclose(b[ok], a[ok], rtol=1e-10, atol=1e-10 * max(1.0, np.abs(a[ok]).max()),
                                           err_msg=f"{filt} k={k} {q}")


@needs_numba
def test_compiled_mode_aware_hands_overflowing_runs_to_numpy():
    """An unstable plant with long noise-only streaks: some runs' x block passes the plain KF's overflow limit
    (``kalman.Rescue``); the compiled kernel flags them and the numpy reference redoes them — same numbers."""
    case = dict(A=[[3.0, 0.0], [0.0, 0.5]], C=[[1.0, 0.5]], Q=[[1, 0], [0, 1]], R=0.1, S=None,
                T=[[0.3, 0.0, 0.6, 0.1]] + [[0.3, 0.05, 0.6, 0.05]] * 3, rho="stationary")
    md = AugmentedModel.build(case["A"], case["C"], case["Q"], case["R"])
    limit = kalman.Rescue.of(md.C, md.R).limit
    ref, got = _estimates(case, "mode_aware", "numpy", runs=200, horizon=40), \
        _estimates(case, "mode_aware", "numba", runs=200, horizon=40)
    assert max(np.trace(r["predicted"][1]).max() for _, r in ref) > limit  # the rescue path is exercised
    for (k, r1), (_, r2) in zip(ref, got):
        for q in ("filtered", "predicted"):
            for a, b in zip(r1[q], r2[q]):
                assert np.array_equal(np.isfinite(a), np.isfinite(b))
                ok = np.isfinite(a)
                np.testing.assert_allclose(b[ok], a[ok], rtol=1e-10, atol=1e-10 * max(1.0, np.abs(a[ok]).max()))


@needs_numba
def test_compiled_nees_equals_numpy_closed_form():
    """The compiled n = 2 NEES is :func:`state._nees_small` operation for operation: the same bits."""
    rng = np.random.default_rng(9)
    R = 3000
    L = rng.standard_normal((2, 2, R))
    P = np.einsum("ikr,jkr->ijr", L, L)
    P[:, :, :30] = 0.0
    P[:, :, 30:60] = np.diag([2.0, 0.0])[:, :, None]
    P[:, :, 60:90] = 4.0 * np.eye(2)[:, :, None]
    P[:, :, 90:400] = P[:, :, 95:96]  # one P in many runs (the exact LMMSE): its eigen-decomposition is reused
    P[:, :, 400:402] = np.array([[1.0, 0.0], [-0.0, 0.0]])[:, :, None]  # then the same P with signed zeros
    P[:, :, 401] = np.array([[1.0, -0.0], [0.0, -0.0]])
    P[:, :, 402:404] = np.nan
    P[:, :, 404] = [[1.0, 0.5], [0.5, 2.0]]  # the same diagonal, another off-diagonal: not the same P
    P[:, :, 405] = [[1.0, -0.5], [-0.5, 2.0]]
    e = rng.standard_normal((2, R))
    q, r = state.nees(e, P)
    q0, r0 = state._nees_small(e, P)
    np.testing.assert_array_equal(r, r0)
    np.testing.assert_array_equal(q, q0)
