"""netkf's own conic form of the critical-rate LMIs (netkf_cli.linalg.sdp, Clarabel directly) against the same
problems written in cvxpy (the independent formulation), on random systems: the optimal margins agree."""

import math

import numpy as np
import pytest

from netkf_cli.analysis import critical as cr
from netkf_cli.linalg import sdp

cp = pytest.importorskip("cvxpy")


def _random_system(rng, n, m):
    A = rng.standard_normal((n, n))
    A *= rng.uniform(0.6, 1.8) / max(abs(np.linalg.eigvals(A)))
    return A, rng.standard_normal((m, n))


def _cvxpy_sinopoli(A, C, lam):
    """Sinopoli's Thm 5 LMI as cvxpy states it: max t, Ψ_λ(Y, Z) ⪰ t I, Y ⪰ t I, Y ⪯ I, t ≤ 1."""
    n, m = A.shape[0], C.shape[0]
    Y, Z, t = cp.Variable((n, n), symmetric=True), cp.Variable((n, m)), cp.Variable()
    B = Y @ A + Z @ C
    a, b = math.sqrt(lam), math.sqrt(1 - lam)
    O = np.zeros((n, n))
    Psi = cp.bmat([[Y, a * B, b * (Y @ A)], [a * B.T, Y, O], [b * (Y @ A).T, O, Y]])
    prob = cp.Problem(cp.Maximize(t), [0.5 * (Psi + Psi.T) >> t * np.eye(3 * n), Y >> t * np.eye(n),
                                       Y << np.eye(n), t <= 1])
    prob.solve(solver=cp.CLARABEL)
    return float(t.value)


def _cvxpy_markov(A, C, p, q):
    n, m = A.shape[0], C.shape[0]
    P0, P1 = cp.Variable((n, n), symmetric=True), cp.Variable((n, n), symmetric=True)
    W, t = cp.Variable((n, m)), cp.Variable()
    T = np.array([[1 - q, q], [p, 1 - p]])
    E0, E1 = T[0, 0] * P0 + T[0, 1] * P1, T[1, 0] * P0 + T[1, 1] * P1
    M0 = cp.bmat([[P0, A.T @ E0], [E0 @ A, E0]])
    M1 = cp.bmat([[P1, A.T @ E1 - C.T @ W.T], [E1 @ A - W @ C, E1]])
    I2, I = np.eye(2 * n), np.eye(n)
    prob = cp.Problem(cp.Maximize(t), [0.5 * (M0 + M0.T) >> t * I2, 0.5 * (M1 + M1.T) >> t * I2, P0 >> t * I,
                                       P1 >> t * I, P0 << I, P1 << I, t <= 1])
    prob.solve(solver=cp.CLARABEL)
    return float(t.value)


def test_svec_is_clarabels_upper_triangle_by_columns():
    M = np.array([[1.0, 2.0, 4.0], [2.0, 3.0, 5.0], [4.0, 5.0, 6.0]])
    r2 = math.sqrt(2.0)
    assert np.allclose(sdp.svec(M), [1.0, 2 * r2, 3.0, 4 * r2, 5 * r2, 6.0])


def test_a_known_margin():
    """max t s.t. diag(x, 2 − x) ⪰ t I, t ≤ 1: t* = 1 at x = 1."""
    sol = sdp.max_margin([sdp.Var((1, 1))], lambda v: [(np.diag([v[0][0, 0], 2.0 - v[0][0, 0]]), True)])
    assert sol.status == "optimal" and abs(sol.t - 1.0) < 1e-7 and abs(sol.values[0][0, 0] - 1.0) < 1e-5


@pytest.mark.parametrize("seed", range(6))
def test_sinopoli_margin_equals_cvxpy(seed):
    rng = np.random.default_rng(seed)
    n, m = [(1, 1), (2, 1), (2, 2), (3, 1), (3, 2), (4, 2)][seed]
    A, C = _random_system(rng, n, m)
    lmi = cr._SinopoliLMI(A, C)
    for lam in (0.05, 0.3, 0.6, 0.9, 1.0):
        t, st, cert = lmi.margin(lam)
        ref = _cvxpy_sinopoli(A, C, lam)
        assert st in ("optimal", "optimal_inaccurate")
        assert abs(t - ref) <= 1e-6 * max(1.0, abs(ref)), (lam, t, ref)
        if cert:
            assert t > 0


@pytest.mark.parametrize("seed", range(4))
def test_markov_margin_equals_cvxpy_and_verdicts_agree(seed):
    rng = np.random.default_rng(50 + seed)
    n, m = [(1, 1), (2, 1), (2, 2), (3, 1)][seed]
    A, C = _random_system(rng, n, m)
    lmi = cr._MarkovLMI(A, C)
    for p, q in ((0.1, 0.9), (0.3, 0.5), (0.6, 0.2)):
        ok, st = lmi.feasible(p, q)
        ref = _cvxpy_markov(A, C, p, q)
        assert st in ("optimal", "optimal_inaccurate")
        t = lmi.solve(p, q).t
        assert abs(t - ref) <= 1e-6 * max(1.0, abs(ref)), (p, q, t, ref)
        if abs(ref) > 1e-5:  # away from the boundary the certificate and cvxpy's sign agree
            assert ok == (ref > 0), (p, q, ref)


def test_only_clarabel():
    with pytest.raises(cr.CriticalRateError, match="Clarabel"):
        cr._SinopoliLMI(np.eye(1), np.eye(1), solver="SCS")
