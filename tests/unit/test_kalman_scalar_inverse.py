"""The Kalman core's 1×1 shortcuts (kalman._inv, kalman._full_rank: the rescue's information form on scalar runs)
against the LAPACK calls they replace, bit for bit, and the information update through them against the
general path."""

from __future__ import annotations

import numpy as np
import pytest

from netkf_cli.linalg import kalman


def _values(seed: int, k: int = 100_000) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = rng.standard_normal(k) * 10.0 ** rng.uniform(-300, 300, k)
    return np.concatenate([x, [5e-324, -5e-324, 1e-310, 2.2e-308, 1.7e308, -1.7e308, 1.0, -1.0, 3.0]])


def test_scalar_inverse_is_lapacks_bit_for_bit():
    X = _values(1).reshape(-1, 1, 1)
    assert np.array_equal(kalman._inv(X), np.linalg.inv(X))
    with pytest.raises(np.linalg.LinAlgError):  # a zero: LAPACK's own answer (singular), not 1/0
        kalman._inv(np.array([[[2.0]], [[0.0]]]))
    Y = np.random.default_rng(2).standard_normal((50, 2, 2))
    assert np.array_equal(kalman._inv(Y), np.linalg.inv(Y))


def test_scalar_rank_is_the_svd_decision():
    X = np.concatenate([_values(3), [0.0, -0.0, np.inf, -np.inf]]).reshape(-1, 1, 1)
    assert np.array_equal(kalman._full_rank(X), np.linalg.matrix_rank(X) == 1)
    with pytest.raises(np.linalg.LinAlgError):  # a NaN: svd's failure, as before
        kalman._full_rank(np.array([[[1.0]], [[np.nan]]]))
    Y = np.random.default_rng(4).standard_normal((50, 3, 3))
    Y[::5, 2] = Y[::5, 1]
    assert np.array_equal(kalman._full_rank(Y), np.linalg.matrix_rank(Y) == 3)


def test_scalar_information_update_is_the_general_path(monkeypatch):
    """information_update on scalar runs (prior finite, huge, ∞, or 0 information) with the shortcuts and with
    the LAPACK calls forced (the general path): the same bits."""
    Pm = np.concatenate([np.abs(_values(5, 5000)[:5000]) + 1e-300, [np.inf, 1e300, 1e-300]]).reshape(1, 1, -1)
    for info in (np.array([[0.7]]), np.array([[0.0]]), np.abs(_values(6, Pm.shape[-1])[:Pm.shape[-1]]).reshape(1, 1, -1)):
        with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
            fast = kalman.information_update(Pm, info)
            monkeypatch.setattr(kalman, "_inv", np.linalg.inv)
            monkeypatch.setattr(kalman, "_full_rank", lambda M: np.linalg.matrix_rank(M) == M.shape[-1])
            slow = kalman.information_update(Pm, info)
            monkeypatch.undo()
        assert np.array_equal(fast, slow)
