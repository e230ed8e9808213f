"""The compiled KF (``backend: numba``) against the numpy reference, and what ``auto`` picks."""

from __future__ import annotations

import builtins

import numpy as np
import pytest

from netkf_cli.estimators.kf import KalmanFilterEstimator
from netkf_cli.system import LinearSystem
from netkf_cli.trace import Trace

pytest.importorskip("numba")


@pytest.mark.parametrize("n,m", [(1, 1), (3, 1), (4, 2), (3, 3)])
def test_numba_equals_numpy_to_rounding(n, m):
    rng = np.random.default_rng(n * 10 + m)
    A = rng.normal(size=(n, n)) * 0.8
    C = rng.normal(size=(m, n))
    L = rng.normal(size=(n, n))
    s = LinearSystem.create(A, C, L @ L.T + 0.1 * np.eye(n), np.eye(m), np.eye(n))
    tr = Trace(300, 60, arrival=rng.random((1, 60, 300)) < 0.6)
    a = dict(KalmanFilterEstimator(kind="kf", backend="numpy").covariances(s, tr, [7, 30, 60]))
    b = dict(KalmanFilterEstimator(kind="kf", backend="numba").covariances(s, tr, [7, 30, 60]))
    for k in a:
        # another operation order: agreement to ~1e3 ulps of ‖P‖ (observed ≤ 2e-12 relative)
        scale = np.maximum(1.0, np.abs(a[k]).max(axis=(0, 1)))
        assert np.all(np.abs(a[k] - b[k]) <= 1e-10 * scale)


def test_numba_hands_overflowing_runs_to_the_reference():
    s = LinearSystem.create(np.diag([1e6, 0.5]), np.eye(2), np.eye(2), np.eye(2), np.eye(2))
    rng = np.random.default_rng(1)
    tr = Trace(2000, 40, arrival=rng.random((1, 40, 2000)) < 0.05)
    a = dict(KalmanFilterEstimator(kind="kf", backend="numpy").covariances(s, tr, [40]))[40]
    b = dict(KalmanFilterEstimator(kind="kf", backend="numba").covariances(s, tr, [40]))[40]
    fin = np.isfinite(a).all(axis=(0, 1))
    assert np.array_equal(fin, np.isfinite(b).all(axis=(0, 1)))
    np.testing.assert_allclose(a[:, :, fin], b[:, :, fin], rtol=1e-10)
    arrived = tr.arrival[0, -1]
    assert np.all(b[0, 0, arrived] <= 1.0)  # an arrival bounds P by (CᵀR⁻¹C)⁻¹ = I, never a cancelled 0 or NaN


def test_auto_is_numpy_and_numba_needs_numba(monkeypatch):
    """auto = numpy for the KF (the compiled kernel measured no faster); an explicit numba without numba is a
    clear error."""
    from netkf_cli.errors import ConfigError

    s = LinearSystem.create(1.2, 1, 1, 1)
    assert KalmanFilterEstimator(kind="kf").resolved_backend(s) == "numpy"
    assert KalmanFilterEstimator(kind="kf", backend="numba").resolved_backend(s) == "numba"
    real = builtins.__import__

    def no_numba(name, *args, **kw):
        if name == "numba" or name.startswith("numba."):
            raise ImportError("hidden for the test")
        return real(name, *args, **kw)

    monkeypatch.setattr(builtins, "__import__", no_numba)
    with pytest.raises(ConfigError, match="needs numba"):
        KalmanFilterEstimator(kind="kf", backend="numba").resolved_backend(s)
