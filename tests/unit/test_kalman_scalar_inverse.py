"""The Kalman core's 1×1 shortcuts (kalman._inv, kalman._full_rank, Rescue._apply_scalar: the rescue's information
form on scalar runs) against the LAPACK calls and the general path they replace, bit for bit."""

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


@pytest.mark.parametrize("c,r", [(1.0, 1.0), (0.7, 2.0), (-1.3, 0.05), (3.0, 1e-9)])
def test_scalar_rescue_is_the_general_path(c, r, monkeypatch):
    """Rescue.apply on scalar runs (finite, huge, ∞, −∞ and NaN priors; arrived or lost; flagged or not) with the
    elementwise path and with it switched off (the general path): the same bits; a zero prior goes to the general
    path, which counts that run as diverged (∞: a singular prior is beyond the information form)."""
    rng = np.random.default_rng(9)
    k = 4000
    Pm = (np.abs(rng.standard_normal(k)) * 10.0 ** rng.uniform(-6, 300, k)).reshape(1, 1, k)
    Pm[0, 0, :8] = [np.inf, -np.inf, np.nan, 1e308, 5e-324, 1.0, 1e8, 3e-310]
    P = Pm * rng.uniform(0.1, 1.0, k)
    rows = rng.random((1, k)) < 0.5
    flagged = rng.random(k) < 0.7
    flagged[:8], rows[0, :3] = True, False  # −∞ / NaN priors lost: P⁻ itself, cleaned to ∞
    resc = kalman.Rescue.of(np.array([[c]]), np.array([[r]]))
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        fast = resc.apply(P, Pm, flagged, rows)
        monkeypatch.setattr(kalman.Rescue, "_apply_scalar", lambda *a: None)
        slow = resc.apply(P, Pm, flagged, rows)
    assert np.array_equal(fast, slow, equal_nan=True)
    assert fast[0, 0, 1] == np.inf and fast[0, 0, 2] == np.inf and np.isfinite(fast[0, 0, 5])
    monkeypatch.undo()
    Pm[0, 0, 10], rows[0, 10], flagged[10] = 0.0, True, True
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        out = resc.apply(P, Pm, flagged, rows)
    assert out[0, 0, 10] == np.inf  # a singular prior: beyond the information form, counted as diverged
    keep = np.arange(k) != 10
    assert np.array_equal(out[..., keep], fast[..., keep], equal_nan=True)  # the other runs as before
