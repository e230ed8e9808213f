"""The Kalman-core primitives appended for the Markov-mode filters, against per-run textbook references.

``kalman.update_pinv`` / ``kalman_numba.update_pinv``: P − P Cᵀ S⁺ C P with S⁺ the Moore–Penrose
pseudo-inverse of S = C P Cᵀ + R where S is (numerically) singular, the plain update where it is regular.
"""

from __future__ import annotations

import numpy as np
import pytest

from netkf_cli.linalg import kalman


def _psd(rng, n, rank=None):
    X = rng.standard_normal((n, rank or n))
    return X @ X.T


def _root(P):
    w, V = np.linalg.eigh(P)
    return V * np.sqrt(np.clip(w, 0, None))


def _ref(P, C, R, e, floor):
    """Per-run textbook reference: S⁺ by eigen-decomposition, eigenvalues ≤ floor dropped."""
    S = C @ P @ C.T + R
    w, V = np.linalg.eigh(0.5 * (S + S.T))
    keep = w > floor
    Sp = (V[:, keep] / w[keep]) @ V[:, keep].T
    K = P @ C.T @ Sp
    return P - K @ C @ P, K @ e


@pytest.mark.parametrize("m", [1, 2, 3])
def test_update_pinv_equals_the_pseudo_inverse_update(m):
    rng = np.random.default_rng(m)
    n, runs = 5, 40
    C = rng.standard_normal((m, n))
    Ps = np.stack([_psd(rng, n, rank=rng.integers(1, n + 1)) for _ in range(runs)], axis=-1)
    # half the runs: zero measurement noise and C's rows redundant with P (a known measurement)
    R = np.zeros((m, m))
    C[-1] = C[0] if m > 1 else C[-1]
    # an innovation lies in the range of S (with R = 0: e = C δ, δ ~ (0, P)); there every generalized inverse agrees
    e = np.stack([C @ _root(Ps[:, :, r])
                  @ rng.standard_normal(n) for r in range(runs)], axis=-1)
    floor = 1e-9 * (1 + np.einsum("iir->r", Ps))
    Pf, dx = kalman.update_pinv(Ps, C, R, floor, e)
    for r in range(runs):
        want_P, want_dx = _ref(Ps[:, :, r], C, R, e[:, r], floor[r])
        np.testing.assert_allclose(Pf[:, :, r], want_P, rtol=1e-8, atol=1e-8 * np.abs(Ps[:, :, r]).max())
        np.testing.assert_allclose(dx[:, r], want_dx, rtol=1e-7, atol=1e-7 * (1 + np.abs(want_dx).max()))


def test_update_pinv_regular_is_the_plain_update_bit_for_bit_and_a_known_measurement_is_no_update():
    rng = np.random.default_rng(7)
    n, m, runs = 3, 2, 30
    C = rng.standard_normal((m, n))
    R = _psd(rng, m) + np.eye(m)
    P = np.stack([_psd(rng, n) for _ in range(runs)], axis=-1)
    Pf, dx = kalman.update_pinv(P, C, R, np.zeros(runs), rng.standard_normal((m, runs)))
    np.testing.assert_array_equal(Pf, kalman.update(P, C, R))
    # m = 1, R = 0, C P Cᵀ = 0 (the measured direction is already known): P is left alone, zero gain
    C1 = np.array([[1.0, 0.0, 0.0]])
    P0 = P.copy()
    P0[0, :, :] = 0.0
    P0[:, 0, :] = 0.0
    Pf1, dx1 = kalman.update_pinv(P0, C1, np.zeros((1, 1)), np.full(runs, 1e-12), np.ones((1, runs)))
    np.testing.assert_array_equal(Pf1, P0)
    np.testing.assert_array_equal(dx1, 0.0)


@pytest.mark.parametrize("m", [1, 2])
def test_compiled_update_pinv_equals_numpy(m):
    pytest.importorskip("numba")
    import numba

    from netkf_cli.linalg import kalman_numba as kn

    @numba.njit
    def call(P, C, R, floor, e):
        n = P.shape[0]
        out, dx = np.empty((n, n)), np.empty(n)
        S, X = np.empty((C.shape[0], C.shape[0])), np.empty((C.shape[0], n))
        kn.update_pinv(P, C, R, floor, e.copy(), out, dx, S, X)
        return out, dx

    rng = np.random.default_rng(10 + m)
    n, runs = 4, 25
    C = rng.standard_normal((m, n))
    for R in (np.zeros((m, m)), _psd(rng, m) + 0.1 * np.eye(m)):
        P = np.stack([_psd(rng, n, rank=rng.integers(1, n + 1)) for _ in range(runs)], axis=-1)
        e = np.stack([C @ _root(P[:, :, r]) @ rng.standard_normal(n) for r in range(runs)], axis=-1)
        floor = 1e-9 * (1 + np.einsum("iir->r", P))
        Pf, dx = kalman.update_pinv(P, C, R, floor, e)
        for r in range(runs):
            a, b = call(np.ascontiguousarray(P[:, :, r]), C, R, floor[r], e[:, r])
            np.testing.assert_allclose(a, Pf[:, :, r], rtol=1e-9, atol=1e-9 * np.abs(P[:, :, r]).max())
            np.testing.assert_allclose(b, dx[:, r], rtol=1e-8, atol=1e-8 * (1 + np.abs(dx[:, r]).max()))



def test_compiled_sparse_predict_equals_the_dense_predict():
    pytest.importorskip("numba")
    import numba

    from netkf_cli.linalg import kalman_numba as kn
    from netkf_cli.estimators.markov_filters import _csr

    @numba.njit
    def call(P, q, rowptr, cols, vals, Q):
        n = P.shape[0]
        out, tmp = np.empty((n, n)), np.empty((n, n))
        kn.predict_csr(P, q, rowptr, cols, vals, Q, out, tmp)
        return out

    rng = np.random.default_rng(3)
    n, modes = 6, 3
    A = rng.standard_normal((modes, n, n)) * (rng.random((modes, n, n)) < 0.4)
    rowptr, cols, vals = _csr(A)
    P = _psd(rng, n)
    Q = np.stack([_psd(rng, n) for _ in range(modes)])
    for q in range(modes):
        np.testing.assert_allclose(call(P, q, rowptr, cols, vals, Q), kalman.one(kalman.predict, P, A[q], Q[q]),
                                   rtol=1e-13, atol=1e-13)
