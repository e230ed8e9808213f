"""burst_mean's standard errors follow the one statistics module: runs that agree to rounding have s.e. 0.

A deterministic quantity (the independent baseline's burst probabilities: every run the same number up to
rounding) gave a cancellation residue ≈ √ε · mean / √n as its s.e. from raw sums, which differs between
machines (a golden compared on another CPU failed on it); a genuinely random one keeps its s.e."""

import math

import numpy as np

from netkf_cli.core.stats import mean_se
from netkf_cli.metrics.burst_mean import norm_and_se


def _sums(X):
    """Σ X and Σ vec X vec Xᵀ over runs (X: runs × n × n)."""
    v = X.reshape(len(X), -1)
    return X.sum(axis=0), v.T @ v


def test_runs_equal_to_rounding_have_zero_se():
    rng = np.random.default_rng(1)
    B = rng.standard_normal((3, 3))
    M = B @ B.T + np.eye(3)
    X = np.array([M * (1 + 4e-16 * rng.standard_normal()) for _ in range(12)])  # one number, rounded 12 ways
    val, se = norm_and_se(*_sums(X), 12)
    assert math.isclose(val, np.linalg.norm(M, 2), rel_tol=1e-12)
    assert se == 0.0
    w = np.full(12, 0.1678445) * (1 + 1e-16 * rng.standard_normal(12))
    m, s = mean_se(w.sum(), (w * w).sum(), 12)
    assert s == 0.0 and math.isclose(m, 0.1678445, rel_tol=1e-14)


def test_random_runs_keep_the_delta_method_se():
    rng = np.random.default_rng(2)
    n, N = 2, 4000
    M = np.diag([3.0, 1.0])  # top eigenvalue 3 with a gap: ∂‖M‖ = e₁e₁ᵀ, so the s.e. is that of X₁₁'s mean
    X = np.array([M + np.diag([rng.normal(0, 0.5), 0.0]) for _ in range(N)])
    val, se = norm_and_se(*_sums(X), N)
    x11 = X[:, 0, 0]
    assert se > 0
    assert math.isclose(se, x11.std(ddof=1) / math.sqrt(N), rel_tol=1e-9)
    assert abs(val - 3.0) < 5 * se
