"""The fast paths of the Markov filters' state-level simulation equal their references to rounding.

Each compiled or closed-form path consumes the same random numbers as the numpy reference, so the
numbers agree to floating-point rounding (amplified only by a matrix's conditioning)."""

from __future__ import annotations

import numpy as np
import pytest

from netkf_cli import state

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
