"""The same filter under many names gives the same numbers (the Kalman core issue).

On one recorded arrival trace, every estimator that reduces to the Kalman filter with intermittent
observations — ``kf``, ``buffered`` with zero delay, ``fusion`` MF with one sensor (and with N
sensors against ``kf`` on the stacked outputs), ``smoother`` with lag 0, ``receiver`` on a perfect
link, the Markov mode-aware filter with only the normal mode — reports the same P_{k|k} and
P_{k+1|k} at every k (relative 1e-12), from the same P0 = P_{0|0}; and ``compare`` of any two gives a
paired difference of exactly 0. Then the means: exact enumeration of all 2^k arrival sequences
against each estimator's ``mean_vs_time`` (4 standard errors), with P0 given and defaulted; and the
information-form rescue (A = diag(1e6, 0.5)) through every estimator that accepts the run.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from netkf_cli import load, run
from netkf_cli.linalg.riccati import initial_covariance
from netkf_cli.config.scenario import kinds
from netkf_cli.core.spec import EstimatorModel
from netkf_cli.core.system import LinearSystem
from netkf_cli.core.trace import LOST, Trace

RTOL = 1e-12
"""Same primitives in the same order give the same bits; 1e-12 leaves room for a reordered sum."""

STEPS = list(range(1, 31))


def _est(kind: str, **fields):
    return kinds(EstimatorModel)[kind].model_validate({"kind": kind, **fields})


def _systems():
    return {
        "scalar": LinearSystem.create(1.3, 1.0, 0.5, 0.8),
        "2-state": LinearSystem.create([[1.05, 0.3], [0.0, 0.9]], [[1.0, 0.0], [0.0, 1.0]],
                                       [[0.2, 0.05], [0.05, 0.3]], [[0.5, 0.0], [0.0, 0.4]], [[2.0, 0.3], [0.3, 1.0]]),
    }


def _gamma(runs=6, horizon=30, streams=1, seed=3, lam=0.6):
    return np.random.default_rng(seed).random((streams, horizon, runs)) < lam


def _check_same(ref: dict, got: dict, who: str, quantities=("filtered", "predicted")):
    for k in ref:
        for q in quantities:
            a, b = ref[k][q], got[k][q]
            np.testing.assert_allclose(b, a, rtol=RTOL, atol=0, err_msg=f"{who}: {q} at k = {k}")


def _kf(system, trace, qs=("filtered", "predicted")):
    return dict(_est("kf").covariances(system, trace, STEPS, qs))


@pytest.mark.parametrize("sysname", ["scalar", "2-state"])
def test_buffered_with_zero_delay_is_kf(sysname):
    s = _systems()[sysname]
    g = _gamma()
    ref = _kf(s, Trace(g.shape[2], g.shape[1], arrival=g))
    delay = np.where(g, 0, LOST).astype(np.int32)
    tr = Trace(g.shape[2], g.shape[1], delay=delay, arrival=g, meta={"buffer": 4, "convention": "delay_le_D"})
    got = dict(_est("buffered", packet="measurement").covariances(s, tr, STEPS, ("filtered", "predicted")))
    _check_same(ref, got, "buffered (zero delay)")


@pytest.mark.parametrize("sysname", ["scalar", "2-state"])
def test_smoother_lag0_is_kf(sysname):
    s = _systems()[sysname]
    g = _gamma()
    tr = Trace(g.shape[2], g.shape[1], arrival=g)
    ref = _kf(s, tr)
    est = _est("smoother", lag=0)
    got = dict(est.covariances(s, tr, STEPS, ("filtered", "predicted", "smoothed")))
    _check_same(ref, got, "smoother lag 0")
    for k in STEPS:
        np.testing.assert_allclose(got[k]["smoothed"], ref[k]["filtered"], rtol=RTOL, atol=0)


@pytest.mark.parametrize("sysname", ["scalar", "2-state"])
def test_fusion_mf_one_sensor_is_kf(sysname):
    s = _systems()[sysname]
    g = _gamma()
    tr = Trace(g.shape[2], g.shape[1], arrival=g)
    ref = _kf(s, tr)
    got = dict(_est("fusion", strategies=["mf"]).covariances(s, tr, STEPS, ("filtered", "predicted")))
    _check_same(ref, got, "fusion MF, one sensor")


@pytest.mark.parametrize("N", [2, 5])
def test_fusion_mf_n_sensors_is_kf_on_the_stacked_outputs(N):
    base = _systems()["2-state"]
    groups = tuple(tuple(range(i * base.m, (i + 1) * base.m)) for i in range(N))
    s = LinearSystem.create(base.A, np.vstack([base.C] * N), base.Q, np.kron(np.eye(N), base.R), base.P0, sensors=groups)
    g = _gamma(streams=N)
    tr = Trace(g.shape[2], g.shape[1], arrival=g)
    ref = _kf(s, tr)
    got = dict(_est("fusion", strategies=["mf"]).covariances(s, tr, STEPS, ("filtered", "predicted")))
    _check_same(ref, got, f"fusion MF, {N} sensors")


def test_kf_streams_mean_sensors_not_rows():
    """Two identical scalar sensors (system.sensors: 2) vs one 2-row output: the first loses a whole
    sensor per stream, the second a row — with C = I₂ both are the same measurement per stream."""
    A, Q = np.array([[0.9, 0.2], [0.0, 0.8]]), np.eye(2)
    rows = LinearSystem.create(A, np.eye(2), Q, np.eye(2))  # default: one sensor per output row
    sens = LinearSystem.create(A, np.eye(2), Q, np.eye(2), sensors=((0,), (1,)))
    g = _gamma(streams=2)
    tr = Trace(g.shape[2], g.shape[1], arrival=g)
    _check_same(_kf(rows, tr), _kf(sens, tr), "rows = sensors when each sensor is one row")


def test_compare_of_two_names_gives_a_paired_difference_of_zero():
    sc = load({"name": "one_filter", "system": {"A": 1.2, "C": 1, "Q": 1, "R": 1},
               "channel": {"kind": "bernoulli", "arrival": 0.7},
               "estimators": [{"kind": "kf"}, {"kind": "buffered", "packet": "measurement"}, {"kind": "smoother", "lag": 0}],
               "analysis": {"kind": "compare", "at": 20, "M": [2.0, 5.0]},
               "montecarlo": {"runs": 3000, "horizon": 20, "chunk": 1000}})
    t = run(sc).table
    d = t[t.statistic.str.startswith("diff_mean_trace")]
    assert len(d) == 2
    assert (d.value == 0).all() and (d.stderr == 0).all()
    p = t[t.statistic == "prob_leq_M"].pivot(index="M", columns="estimator", values="value")
    assert (p.nunique(axis=1) == 1).all()


# ----------------------------------------------------------------------------------------------
# exact enumeration of every arrival sequence against mean_vs_time
# ----------------------------------------------------------------------------------------------

def _enumerate(s: LinearSystem, lam: float, K: int):
    """E[tr P_{k|k}], E[tr P_{k+1|k}] for k = 1 … K over all 2^K i.i.d. arrival sequences (textbook loop)."""
    P0 = initial_covariance(s)
    Ef, Ep = np.zeros(K), np.zeros(K)
    for seq in itertools.product((0, 1), repeat=K):
        w = np.prod([lam if g else 1 - lam for g in seq])
        P = P0
        for k, g in enumerate(seq):
            Pm = s.A @ P @ s.A.T + s.Q
            if g:
                S = s.C @ Pm @ s.C.T + s.R
                P = Pm - Pm @ s.C.T @ np.linalg.solve(S, s.C @ Pm)
            else:
                P = Pm
            Ef[k] += w * np.trace(P)
            Ep[k] += w * np.trace(s.A @ P @ s.A.T + s.Q)
    return Ef, Ep


ENUM_ESTIMATORS = [{"kind": "kf"}, {"kind": "buffered", "packet": "measurement"}, {"kind": "smoother", "lag": 1},
                   {"kind": "fusion", "strategies": ["mf"]}]


@pytest.mark.parametrize("system", [
    {"A": 1.25, "C": 1, "Q": 1, "R": 1},
    {"A": 1.25, "C": 1, "Q": 1, "R": 1, "P0": 3.0},
    {"A": [[1.1, 0.4], [0.0, 0.7]], "C": [[1, 0]], "Q": [[1, 0], [0, 0.5]], "R": 0.5},
    {"A": [[1.1, 0.4], [0.0, 0.7]], "C": [[1, 0]], "Q": [[1, 0], [0, 0.5]], "R": 0.5, "P0": [[2, 0], [0, 1]]},
], ids=["scalar-P0bar", "scalar-P0given", "2state-P0bar", "2state-P0given"])
@pytest.mark.parametrize("quantity", ["filtered", "predicted"])
def test_mean_vs_time_matches_exact_enumeration(system, quantity):
    K, lam = 10, 0.6
    sc = load({"name": "enum", "system": system, "channel": {"kind": "bernoulli", "arrival": lam},
               "estimators": ENUM_ESTIMATORS, "analysis": {"kind": "mean_vs_time", "every": 1, "quantity": quantity},
               "montecarlo": {"runs": 6000, "horizon": K, "chunk": 2000, "seed": 11}})
    t = run(sc).table
    Ef, Ep = _enumerate(sc.linear_system(), lam, K)
    exact = Ef if quantity == "filtered" else Ep
    assert set(t.quantity) == {quantity}
    for lab, g in t.groupby("estimator"):
        g = g.sort_values("k")
        ex = exact[g.k.to_numpy() - 1]
        z = (g.value.to_numpy() - ex) / g.stderr.to_numpy()
        # each step's mean is over 6000 independent runs: |z| ≤ 4 per step; 10 steps × 4 estimators ×
        # 16 cases ≈ 640 looks at 4σ have a family-wise false-alarm rate ≈ 4 %, acceptable for a fixed seed
        assert np.all(np.abs(z) <= 4.0), f"{lab} ({quantity}): z = {np.round(z, 2)}"


# ----------------------------------------------------------------------------------------------
# the rescue
# ----------------------------------------------------------------------------------------------

def test_rescue_gives_the_same_p_through_every_estimator_that_accepts_the_run():
    s = LinearSystem.create([[1e6, 0.0], [0.0, 0.5]], np.eye(2), np.eye(2), np.eye(2), np.eye(2))
    g = _gamma(runs=50, horizon=12, lam=0.05, seed=9)
    tr = Trace(g.shape[2], g.shape[1], arrival=g, delay=np.where(g, 0, LOST).astype(np.int32),
               meta={"buffer": 2, "convention": "delay_le_D"})
    steps = list(range(1, 13))
    ref = dict(_est("kf").covariances(s, tr, steps, ("filtered",)))
    # every P is finite (no cancellation to nonsense, no NaN) and the information form agrees with the
    # textbook value on the observed coordinate: after an arrival P[0,0] = 1/(1/P⁻ + 1) ≤ 1
    for k, out in ref.items():
        P = out["filtered"]
        assert np.isfinite(P).all()
        arrived = g[0, k - 1]
        assert np.all(P[0, 0, arrived] <= 1.0 + 1e-9)
    for kind, fields in (("buffered", {"packet": "measurement"}), ("smoother", {"lag": 0}),
                         ("fusion", {"strategies": ["mf"]})):
        got = dict(_est(kind, **fields).covariances(s, tr, steps, ("filtered",)))
        _check_same(ref, got, f"{kind} (rescue)", ("filtered",))


def test_rescue_with_a_rank_deficient_c_is_the_same_through_kf_and_fusion():
    """C = [1 1] (rank 1 < n = 2): the rescue limit comes from the noise seen through C, so a prior of
    1e12 is updated in information form by every estimator, not left to cancel digits."""
    s = LinearSystem.create([[1e6, 0.0], [0.0, 0.5]], [[1.0, 1.0]], np.eye(2), 1.0, np.eye(2))
    g = _gamma(runs=40, horizon=10, lam=0.3, seed=4)
    tr = Trace(g.shape[2], g.shape[1], arrival=g)
    steps = list(range(1, 11))
    ref = dict(_est("kf").covariances(s, tr, steps, ("filtered",)))
    for kind, fields in (("fusion", {"strategies": ["mf"]}), ("smoother", {"lag": 0})):
        got = dict(_est(kind, **fields).covariances(s, tr, steps, ("filtered",)))
        _check_same(ref, got, f"{kind} (rank-deficient C)", ("filtered",))
    P = ref[10]["filtered"]
    assert np.isfinite(P).all() and np.all(np.linalg.eigvalsh(np.moveaxis(P, -1, 0))[:, 0] > 0)
