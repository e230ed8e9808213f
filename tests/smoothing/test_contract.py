"""The smoother and Gilbert–Elliott channel contracts (issue 12), the compiled backend (issue 15),
picklable kernels on worker processes, and overflow handling (issue 14)."""

from __future__ import annotations

import os
import pickle
import sys

import numpy as np
import pytest

from netkf_cli import montecarlo as mc
from netkf_cli import riccati
from netkf_cli.analysis.smoothing import batch_posterior_covariance
from netkf_cli.channels.bernoulli import BernoulliChannel
from netkf_cli.channels.gilbert_elliott import GilbertElliottChannel
from netkf_cli.errors import ConfigError
from netkf_cli.estimators import smoother as sm_est
from netkf_cli.estimators.smoother import (
    PRED,
    RetransmissionKernel,
    SmootherEstimator,
    SmootherMCKernel,
    smoother_requests,
)
from netkf_cli.system import LinearSystem
from netkf_cli.trace import Trace

numba_missing = not sm_est.numba_available()


def random_system(rng, n, m, P0=True, rho=1.1):
    A = rng.normal(size=(n, n))
    A *= rho / max(np.abs(np.linalg.eigvals(A)).max(), 1e-3)  # mildly unstable, like the papers' plants
    C = rng.normal(size=(m, n))
    Lq = rng.normal(size=(n, n)) * 0.5
    Lr = rng.normal(size=(m, m)) * 0.5
    L0 = rng.normal(size=(n, n))
    return LinearSystem.create(A, C, Lq @ Lq.T + 0.05 * np.eye(n), Lr @ Lr.T + 0.2 * np.eye(m),
                               (L0 @ L0.T + 0.1 * np.eye(n)) if P0 else None)


def est(lag, backend="numpy"):
    return SmootherEstimator(kind="smoother", lag=lag, backend=backend)


# --------------------------------------------------------------------------- channel contract
def test_gilbert_elliott_contract():
    ch = GilbertElliottChannel(kind="gilbert_elliott", loss_rate=0.3, mean_burst=3)
    assert ch.trace_kinds == frozenset({"arrival"})
    assert ch.loss_rate() == 0.3
    tr = ch.sample_trace(np.random.default_rng(1), 20_000, 50)
    assert isinstance(tr, Trace) and tr.arrival.shape == (1, 50, 20_000) and tr.arrival.dtype == bool
    # stationary from k = 0: the loss rate at every step is π_B; 5 s.e. of a mean of 20 000 × 50
    # correlated indicators (variance inflation (1+ρ)/(1−ρ), ρ = 1 − p_gb − p_bg = 0.524 ⇒ × 3.2)
    se = np.sqrt(0.3 * 0.7 / (20_000 * 50) * 3.2)
    assert abs((~tr.arrival).mean() - 0.3) < 5 * se
    # the YAML key is still loss_rate (alias): the manifest round-trips
    assert ch.model_dump(by_alias=True)["loss_rate"] == 0.3


# --------------------------------------------------------------------------- estimator contract
@pytest.mark.parametrize("n, m", [(1, 1), (2, 1), (3, 2)])
@pytest.mark.parametrize("lag", [0, 1, 3])
def test_covariances_equal_batch_gaussian_conditioning(n, m, lag):
    """P_{k−L|k} of the trace convention (step t carries y_{t+1}, P0 = P_{0|0}) against brute-force
    conditioning of the joint Gaussian law (y_0 never observed)."""
    rng = np.random.default_rng(10 * n + m + 100 * lag)
    s = random_system(rng, n, m)
    T, runs = 8, 3
    arr = rng.random((T, runs)) < 0.6
    tr = Trace(runs=runs, horizon=T, arrival=arr[None])
    steps = list(range(1, T + 1))
    out = dict(est(lag).covariances(s, tr, steps))
    assert sorted(out) == steps
    for k in steps:
        P = out[k]
        assert P.shape == (n, n, runs)
        if k < lag:
            assert np.isnan(P).all()
            continue
        for r in range(runs):
            g = np.concatenate([[False], arr[:, r]])  # index 0 = y_0 (not sent)
            ref = batch_posterior_covariance(s, g, k - lag, k, s.P0)
            np.testing.assert_allclose(P[:, :, r], ref, rtol=1e-8, atol=1e-9 * max(1.0, np.abs(ref).max()))


def test_lag0_perfect_channel_is_the_dare_filter():
    s = LinearSystem.create([[1.2, 0.4], [0.0, 0.8]], [[1.0, 0.0]], np.eye(2) * 0.3, 0.5, np.eye(2) * 5)
    tr = Trace(runs=2, horizon=300, arrival=np.ones((1, 300, 2), bool))
    (k, P), = list(est(0).covariances(s, tr, [300]))
    np.testing.assert_allclose(P[:, :, 0], riccati.gtilde(riccati.pstar(s), s), rtol=1e-9)


def test_check_refuses_a_channel_without_arrivals():
    class Fake:
        kind = "fading"
        trace_kinds = frozenset({"snr"})

    with pytest.raises(ConfigError, match="arrival"):
        est(1).check(None, Fake())
    est(1).check(None, BernoulliChannel(kind="bernoulli", arrival=0.5))  # fine
    assert SmootherEstimator.accepts == frozenset({"arrival"})


def test_lag_limit_is_a_validation_error():
    with pytest.raises(Exception, match="lag"):
        SmootherEstimator(kind="smoother", lag=sm_est.MAX_LAG + 1)


# --------------------------------------------------------------------------- backends
@pytest.mark.skipif(numba_missing, reason="numba not installed")
@pytest.mark.parametrize("n, m", [(1, 1), (2, 1), (3, 2), (4, 2), (3, 3)])
def test_numba_equals_numpy_on_the_same_arrivals(n, m):
    rng = np.random.default_rng(n * 7 + m)
    s = random_system(rng, n, m)
    g = rng.random((40, 700)) < 0.55
    P0 = np.eye(n)
    p1, o1 = smoother_requests(s, g, P0, [0, 3, 17, 30], (0, 1, 4), want_pred=True, backend="numpy")
    p2, o2 = smoother_requests(s, g, P0, [0, 3, 17, 30], (0, 1, 4), want_pred=True, backend="numba")
    if n == m == 1:  # the same floating-point operations in the same order: bitwise equal
        assert np.array_equal(o1, o2) and np.array_equal(p1, p2)
    else:  # products summed in another order: equal to round-off
        np.testing.assert_allclose(o2, o1, rtol=1e-10, atol=1e-12 * np.abs(o1).max())
        np.testing.assert_allclose(p2, p1, rtol=1e-10, atol=1e-12 * np.abs(p1).max())


@pytest.mark.skipif(numba_missing, reason="numba not installed")
def test_kernel_statistics_identical_across_backends():
    s = LinearSystem.create(1.3, 1, 0.5, 1, None)
    ch = GilbertElliottChannel(kind="gilbert_elliott", loss_rate=0.4, mean_burst=3)
    stats = []
    for be in ("numpy", "numba"):
        k = SmootherMCKernel(system=s, channel=ch, k=30, lags=(PRED, 0, 2), M=np.array([[6.25]]), backend=be)
        stats.append(k(np.random.default_rng(7), 5000))
    assert stats[0].keys() == stats[1].keys()
    for key in stats[0]:
        assert stats[0][key] == stats[1][key], key


def test_auto_backend_picks_numba_when_importable(monkeypatch):
    if not numba_missing:
        assert sm_est.resolve_backend("auto") == "numba"
    monkeypatch.setitem(sys.modules, "numba", None)  # hide numba: import fails
    assert sm_est.resolve_backend("auto") == "numpy"
    with pytest.raises(ConfigError, match="numba"):
        sm_est.resolve_backend("numba")


# --------------------------------------------------------------------------- kernels on workers
class _WhereKernel:
    """A module-level wrapper: counts the chunks that ran outside the parent process."""

    def __init__(self, inner, parent):
        self.inner, self.parent = inner, parent

    def __call__(self, rng, runs):
        out = dict(self.inner(rng, runs))
        out["not_parent"] = int(os.getpid() != self.parent)
        return out


def test_kernels_pickle_and_run_on_worker_processes_with_identical_sums():
    s = LinearSystem.create(1.3, 1, 0.5, 1, None)
    ker = SmootherMCKernel(system=s, channel=BernoulliChannel(kind="bernoulli", arrival=0.6), k=20, lags=(PRED, 0, 1),
                           M=np.array([[6.25]]))
    rk = RetransmissionKernel(system=s, lam=0.6, N=2, ps=(1.0, 0.5), k=20, M=6.25, grid=np.geomspace(0.2, 50, 30))
    for kern in (ker, rk):
        pickle.loads(pickle.dumps(kern))
    wrapped = _WhereKernel(ker, os.getpid())
    serial = mc.run_chunked(wrapped, 4000, 1000, 11, stream=3)
    with mc.execution("process", jobs=2):
        par = mc.run_chunked(wrapped, 4000, 1000, 11, stream=3)
    assert int(serial["not_parent"]) == 0 and int(par["not_parent"]) == 4
    for key in serial:
        if key != "not_parent":
            assert np.array_equal(serial[key], par[key]), key


# --------------------------------------------------------------------------- overflow (issue 14)
def test_huge_a_bernoulli_monte_carlo_matches_the_exact_probability():
    """A = 10⁶, λ = 0.05: P_{k|k−1} overflows in long loss bursts, but P_{k|k} = r/(c² + r/Σ) ≤ 1 after any
    arrival and ≥ q·10¹² after a loss, so Pr[P_{k|k} ≤ 10] = λ exactly. 5 binomial s.e."""
    s = LinearSystem.create(1e6, 1, 0.5, 1, None)
    for backend in ("numpy",) + (() if numba_missing else ("numba",)):
        ker = SmootherMCKernel(system=s, channel=BernoulliChannel(kind="bernoulli", arrival=0.05), k=200, lags=(PRED, 0, 1),
                               M=np.array([[10.0]]), backend=backend)
        with np.errstate(all="raise"):
            st = ker(np.random.default_rng(3), 20_000)
        p = st["leq_lag0"] / st["n"]
        assert abs(p - 0.05) < 5 * np.sqrt(0.05 * 0.95 / 20_000)
        assert st["overflow_pred"] > 0  # the prediction did overflow in some runs, and was counted
        # lag 1: ≤ M iff γ_k = 1 or γ_{k+1} = 1 (the next measurement pins x_k down): 1 − 0.95²
        p1 = st["leq_lag1"] / st["n"]
        assert abs(p1 - (1 - 0.95**2)) < 5 * np.sqrt(0.0975 * 0.9025 / 20_000)


def test_future_information_recursion_equals_the_batch_form_and_survives_huge_a():
    import itertools

    from netkf_cli.analysis import smoothing as asm

    rng = np.random.default_rng(0)
    for n, m in [(1, 1), (2, 1), (3, 2)]:
        s = random_system(rng, n, m)
        for f in itertools.product((0, 1), repeat=4):
            H, Sig = asm._future_model(s, f)
            batch = np.zeros((n, n)) if H is None else H.T @ np.linalg.solve(Sig, H)
            np.testing.assert_allclose(asm.future_information(s, f), batch, rtol=1e-9, atol=1e-10)
    big = LinearSystem.create(1e6, 1, 0.5, 1)  # Σ_η is numerically singular here; the recursion is not
    J = asm.future_information(big, (0, 1))  # y_{k+1} = 10⁶ x_k + w_k + v: J = 10¹²/(q + r)
    np.testing.assert_allclose(J, [[1e12 / 1.5]], rtol=1e-12)
