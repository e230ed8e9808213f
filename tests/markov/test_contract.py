"""Channel/estimator contract (issue 12) for `markov_modes` + `markov_lmi`: traces, per-run covariances."""

from __future__ import annotations

import numpy as np

from netkf_cli.core.tolerances import RESCUE_RATIO
import pytest
import scipy.linalg

from netkf_cli.channels.markov_modes import MarkovModesChannel
from netkf_cli.core.errors import ConfigError
from netkf_cli.estimators.kf import KalmanFilterEstimator
from netkf_cli.estimators.markov_filters import (
    AugmentedModel,
    ModeAwareKFTr,
    exact_mse,
    lmmse_filter,
    naive_filter,
    pinv_psd,
)
from netkf_cli.estimators.markov_lmi import MarkovLMIEstimator, lmi_design
from netkf_cli.config.loader import load_scenario_text
from netkf_cli.core.trace import Trace
from netkf_cli.core.system import LinearSystem

from tests.burst_system import BURST

from .conftest import CONFIGS

EX2 = LinearSystem.create([[0.8, 0], [0.9, 0.2]], [[1, 1]], [[0.36, 0.30], [0.30, 0.25]], 0.25, P0=[[0, 0], [0, 0]])
CHAIN = [[0.7, 0.0, 0.1, 0.2], [0.7, 0.15, 0.05, 0.1], [0.7, 0.15, 0.05, 0.1], [0.7, 0.15, 0.05, 0.1]]


def _ch(transition=CHAIN):
    return MarkovModesChannel(kind="markov_modes", transition=transition)


def test_trace_carries_modes_arrivals_and_the_chain():
    ch = _ch()
    assert ch.trace_kinds == {"mode", "arrival"}
    tr = ch.sample_trace(np.random.default_rng(0), 4000, 30)
    assert tr.mode.shape == (30, 4000) and tr.mode.dtype == np.int8
    np.testing.assert_array_equal(tr.arrival[0], tr.mode == 0)
    np.testing.assert_allclose(tr.meta["rho"], ch.rho)
    assert ch.loss_rate() == pytest.approx(1 - ch.rho[0])
    # same generator state ⇒ the legacy (runs, horizon) sampler is the transpose
    np.testing.assert_array_equal(ch.sample(np.random.default_rng(0), 4000, 30), tr.mode.T)


def test_perfect_channel_mode_aware_gives_the_dare_steady_state():
    # every packet on time (mode 1 forever): the mode-aware KF is the ordinary KF, so its
    # filtered P_x(k|k) converges to the filtering DARE solution.
    perfect = _ch([[1.0, 0, 0, 0]] * 4)
    tr = perfect.sample_trace(np.random.default_rng(1), 3, 200)
    est = MarkovLMIEstimator(kind="markov_lmi", filter="mode_aware")
    P = dict(est.covariances(EX2, tr, [200]))[200]["filtered"]
    Pp = scipy.linalg.solve_discrete_are(EX2.A.T, EX2.C.T, EX2.Q, EX2.R)
    Pf = Pp - Pp @ EX2.C.T @ np.linalg.solve(EX2.C @ Pp @ EX2.C.T + EX2.R, EX2.C @ Pp)
    for r in range(3):
        np.testing.assert_allclose(P[:, :, r], Pf, rtol=1e-8, atol=1e-10)


def test_mode_aware_states_equal_the_textbook_predictor_form_per_run():
    # the core's filtered form (update_pinv, then the decorrelated time update) against the textbook
    # predictor form with correlated noise, run by run: Σ_y = H P Hᵀ + J Σ Jᵀ, K = (F P Hᵀ + G Σ Jᵀ) Σ_y⁺,
    # ξ̂⁺ = F ξ̂ + K (y − H ξ̂), P⁺ = F P Fᵀ + G Σ Gᵀ − K Σ_y Kᵀ; filtered x̂ = ξ̂ + P Hᵀ Σ_y⁺ (y − H ξ̂).
    md = AugmentedModel.build(EX2.A, EX2.C, EX2.Q, EX2.R, [[0.12], [0.10]])  # v = 0.2 w₀ + …: S = 0.2 g
    rng = np.random.default_rng(2)
    R, K = 40, 30
    modes = _ch().sample_trace(rng, R, K).mode
    ys = rng.standard_normal((K, 1, R))
    b = ModeAwareKFTr(md, R, np.zeros(2), np.eye(2))
    mean, cov = md.initial_moments(np.zeros(2), np.eye(2))
    xs = [mean.copy() for _ in range(R)]
    Ps = [cov.copy() for _ in range(R)]
    Sg = md.Sigma
    for k in range(K):
        xb, tb, Pb = b.step(ys[k], modes[k], want_cov=True)
        for r in range(R):
            q = modes[k, r]
            F, G, H, J = md.F[q], md.G[q], md.H[q], md.J[q]
            P, x, y = Ps[r], xs[r], ys[k][:, r]
            Sy = H @ P @ H.T + J @ Sg @ J.T
            Si = pinv_psd(Sy, np.trace(Sg) + np.trace(P))
            innov = y - H @ x
            Kf = P @ H.T @ Si
            np.testing.assert_allclose(xb[:, r], (x + Kf @ innov)[:2], rtol=1e-9, atol=1e-10)
            np.testing.assert_allclose(Pb[:, :, r], (P - Kf @ Sy @ Kf.T)[:2, :2], rtol=1e-9, atol=1e-10)
            Kg = (F @ P @ H.T + G @ Sg @ J.T) @ Si
            xs[r] = F @ x + Kg @ innov
            Pn = F @ P @ F.T + G @ Sg @ G.T - Kg @ Sy @ Kg.T
            Ps[r] = (Pn + Pn.T) / 2
        np.testing.assert_allclose(np.trace(Pb), tb, rtol=1e-12)


@pytest.mark.parametrize("backend", ["numpy", "numba"])
@pytest.mark.parametrize("sysname", ["ex2", "overflow", "3x2", "burst"])
def test_mode_aware_with_only_modes_1_and_3_is_the_kf_step_for_step(backend, sysname):
    # modes 1 (on time) and 3 (noise only) are the kf's γ = 1 and γ = 0: same P0 = P_{0|0}, same step k,
    # filtered and predicted, relative 1e-12 (the x block goes through the same primitive sequence and the
    # same kalman.Rescue — A = diag(1e6, 0.5) overflows in the standard form and is rescued alike; "burst": two
    # rows, a coupled R, loss bursts of 10-30 steps, where kalman.burst_limit lowers the rescue limit below the
    # trace rule's: tests/unit/test_kalman_core's system).
    if backend == "numba":
        pytest.importorskip("numba")
    S = {"ex2": EX2,
         "overflow": LinearSystem.create([[1e6, 0], [0, 0.5]], [[1, 0]], np.eye(2), 1.0),
         "3x2": LinearSystem.create([[1.1, 0.2, 0], [0, 0.9, 0.1], [0, 0, 0.7]], [[1, 0, 1], [0, 1, 0]], np.eye(3),
                                    [[1, 0.3], [0.3, 2]]),
         "burst": LinearSystem.create(**BURST)}[sysname]
    rng = np.random.default_rng(0)
    R, K = 50, 40
    arr = rng.random((1, K, R)) < 0.7
    if sysname == "burst":  # run r loses steps 4 … 4 + L_r − 1, L_r from 10 to 30
        L = 10 + np.arange(R) % 21
        arr = ~((np.arange(K)[:, None] >= 3) & (np.arange(K)[:, None] < 3 + L[None, :]))[None]
    tr = Trace(runs=R, horizon=K, mode=np.where(arr[0], 0, 2).astype(np.int8), arrival=arr, meta={})
    ks = range(1, K + 1)
    kf = dict(KalmanFilterEstimator(kind="kf").covariances(S, tr, ks, ("filtered", "predicted")))
    est = MarkovLMIEstimator(kind="markov_lmi", filter="mode_aware", backend=backend)
    ma = dict(est.covariances(S, tr, ks, ("filtered", "predicted")))
    eps = np.finfo(float).eps
    tol = np.full(R, 1e-12)
    for k in ks:
        if sysname == "burst" and k > 1:
            # a burst's prior is ill-conditioned by design: a float64 update of it promises ε·RESCUE_RATIO, or the
            # prior's own rounding ε·κ(P⁻) where larger (tests/unit/test_kalman_core), carried by the steps after
            # it; numpy's path is the kf's primitive for primitive (equal), the compiled one agrees to that per run
            # (measured 6e-5 at a 30-step burst, κ ~ 1e12; before both used the same rescue limit numpy's mode-aware
            # filter was 80x off)
            prior = kf[k - 1]["predicted"]
            kappa = np.linalg.cond(np.moveaxis(prior, -1, 0))
            tol = np.maximum(tol, 2 * np.maximum(eps * RESCUE_RATIO, 16 * eps * kappa))
        for q in ("filtered", "predicted"):
            a, b = ma[k][q], kf[k][q]
            np.testing.assert_array_equal(np.isfinite(a), np.isfinite(b))
            fin = np.isfinite(b).all(axis=(0, 1))
            scale = np.abs(b[:, :, fin]).max(axis=(0, 1))
            err = np.abs(a - b)[:, :, fin].max(axis=(0, 1)) / scale
            allowed = tol[fin]
            if q == "predicted":  # A δ Aᵀ of the filtered error δ (|A δ Aᵀ|max ≤ n ‖A‖₂² |δ|max), against P_{k+1|k}
                Pf = kf[k]["filtered"][:, :, fin]
                allowed = allowed * np.maximum(1.0, S.n * np.linalg.norm(S.A, 2) ** 2 * np.abs(Pf).max(axis=(0, 1)) / scale)
            assert np.all(err <= allowed), (k, q, float(err.max()))


@pytest.mark.parametrize("which", ["lmi", "naive"])
def test_fixed_gain_covariances_average_to_the_exact_mse(which):
    # Given the mode path, P_k(θ) = E[e eᵀ | θ] exactly; its mean over independent mode paths is
    # the unconditional MSE, which exact_mse computes without sampling. tr P_k(θ) is bounded, so
    # the Monte Carlo mean over R paths has s.e. sd/√R: allow 5 s.e. at k = 5, 20, 40.
    ch = _ch()
    R, K = 4000, 40
    tr = ch.sample_trace(np.random.default_rng(3), R, K)
    est = MarkovLMIEstimator(kind="markov_lmi", filter=which)
    # netkf's time base: P0 = P_{0|0}, first measurement y_1 (exact_mse / the design with base="contract")
    got = {k: v["filtered"] for k, v in est.covariances(EX2, tr, [5, 20, 40])}
    md = AugmentedModel.build(EX2.A, EX2.C, EX2.Q, EX2.R)
    x0, P0 = np.zeros(2), np.zeros((2, 2))
    prior_x = md.prior_moments(x0, P0, "contract")[1][:2, :2]
    filt = (naive_filter(md, x0, prior_x, K) if which == "naive"
            else lmi_design(md, ch.rho, x0, P0, K, design="closed_form", base="contract").filter)
    ex = exact_mse(md, filt, ch.T, ch.pi0, x0, P0, base="contract")[1]
    for k, P in got.items():
        trP = np.trace(P)
        assert np.all(trP > 0)
        m, se = trP.mean(), trP.std(ddof=1) / np.sqrt(R)
        assert abs(m - ex[k - 1]) <= 5 * se + 1e-12, (which, k, m, ex[k - 1], se)


def test_lmmse_reports_its_expected_covariance_and_per_run_metrics_refuse_it():
    """The exact LMMSE's P is E[e eᵀ] over all mode paths (the same in every run): metrics of means may use it
    (it is then exact_mse on netkf's time base), a metric of each run's P (Pr[P_k ≤ M]) refuses it."""
    est = MarkovLMIEstimator(kind="markov_lmi", filter="lmmse")
    assert not est.per_run_covariance()
    tr = _ch().sample_trace(np.random.default_rng(4), 7, 10)
    md = AugmentedModel.build(EX2.A, EX2.C, EX2.Q, EX2.R)
    x0, P0 = np.zeros(2), np.asarray(EX2.P0, float)
    filt = lmmse_filter(md, _ch().T, _ch().pi0, x0, P0, 11, base="contract")
    ex_p, ex_f = exact_mse(md, filt, _ch().T, _ch().pi0, x0, P0, base="contract")
    for k, Ps in est.covariances(EX2, tr, [1, 4, 10], ("filtered", "predicted")):
        for q, ex in (("filtered", ex_f[k - 1]), ("predicted", ex_p[k])):
            assert np.allclose(Ps[q], Ps[q][:, :, :1])  # the same P in every run
            assert np.trace(Ps[q][:, :, 0]) == pytest.approx(ex, rel=1e-9)
    text = (CONFIGS / "example2_exact.yaml").read_text().split("analysis:")[0].replace(
        "kind: markov_lmi", "kind: markov_lmi\n  filter: lmmse")
    with pytest.raises(ConfigError, match="each run's covariance"):
        load_scenario_text(text + "analysis: {kind: distribution, M: [1, 2]}\nmontecarlo: {runs: 10, horizon: 5}\n")


def test_backend_auto_picks_numba_when_present_and_numpy_when_hidden(monkeypatch):
    import sys

    from netkf_cli.estimators import markov_filters as mf

    if mf.numba_available():
        assert mf.resolve_backend("auto", 1) == "numba"
        assert mf.resolve_backend("auto", 2) == "numba"  # the compiled filter handles any m
    monkeypatch.setitem(sys.modules, "numba", None)  # import numba now raises ImportError
    assert not mf.numba_available()
    assert mf.resolve_backend("auto", 1) == "numpy"
    with pytest.raises(ConfigError, match="estimator.backend"):
        mf.resolve_backend("numba", 1)


@pytest.mark.parametrize("which", ["lmi", "naive", "mode_aware"])
def test_batched_covariances_equal_a_per_run_loop(which):
    # issue 12: batched == per-run loop on the same trace. The loop is the textbook recursion one run
    # at a time: for fixed gains M⁺ = 𝒜_q M 𝒜_qᵀ + ℬ_q Σ ℬ_qᵀ on ζ = [ξ; x_s], error of x̂(k|k) read off
    # M; for the mode-aware KF the plain Riccati step with Σ_y⁺ (zero-variance innovations get no gain).
    # netkf's time base: P0 = P_{0|0}; ξ at the first measurement y_1 is ξ(1) = [A x_0 + w_0; x_0; v_0; v_0].
    ch = _ch()
    R, K = 7, 18
    tr = ch.sample_trace(np.random.default_rng(4), R, K)
    est = MarkovLMIEstimator(kind="markov_lmi", filter=which)
    got = {k: v["filtered"] for k, v in est.covariances(EX2, tr, range(1, K + 1), ("filtered", "predicted"))}
    pred = {k: v["predicted"] for k, v in est.covariances(EX2, tr, range(1, K + 1), ("filtered", "predicted"))}
    md = AugmentedModel.build(EX2.A, EX2.C, EX2.Q, EX2.R)
    x0, P0, n, d = np.zeros(2), np.zeros((2, 2)), 2, md.d
    c0 = np.zeros((d, d))
    c0[:2, :2] = EX2.A @ P0 @ EX2.A.T + EX2.Q
    c0[:2, 2:4] = EX2.A @ P0
    c0[2:4, :2] = P0 @ EX2.A.T
    c0[2:4, 2:4] = P0
    c0[4:, 4:] = EX2.R
    xbar, cov = np.zeros(d), c0
    Sg = md.Sigma
    if which == "mode_aware":
        for r in range(R):
            P = cov.copy()
            for t in range(K):
                q = tr.mode[t, r]
                F, G, H, J = md.F[q], md.G[q], md.H[q], md.J[q]
                Sy = H @ P @ H.T + J @ Sg @ J.T
                Si = pinv_psd(Sy, np.trace(Sg) + np.trace(P))
                Kf = P @ H.T @ Si
                np.testing.assert_allclose(got[t + 1][:, :, r], (P - Kf @ Sy @ Kf.T)[:n, :n], rtol=1e-8, atol=1e-10)
                Kg = (F @ P @ H.T + G @ Sg @ J.T) @ Si
                P = F @ P @ F.T + G @ Sg @ G.T - Kg @ Sy @ Kg.T
                P = (P + P.T) / 2
                np.testing.assert_allclose(pred[t + 1][:, :, r], P[:n, :n], rtol=1e-8, atol=1e-10)
        return
    filt = (naive_filter(md, x0, c0[:2, :2], K) if which == "naive"
            else lmi_design(md, ch.rho, x0, P0, K, design="closed_form", base="contract").filter)
    for r in range(R):
        z0 = np.concatenate([xbar, filt.s0])
        M = np.outer(z0, z0)
        M[:d, :d] += cov
        for t in range(K):
            q = tr.mode[t, r]
            Cf = np.concatenate([md.Ex - filt.Lf[t] @ md.H[q], -filt.Ef[t]], axis=1)
            LJ = filt.Lf[t] @ md.J[q]
            want = Cf @ M @ Cf.T + LJ @ Sg @ LJ.T
            np.testing.assert_allclose(got[t + 1][:, :, r], want, rtol=1e-9, atol=1e-12)
            Aq = np.block([[md.F[q], np.zeros((d, filt.As.shape[1]))], [filt.Gs[t] @ md.H[q], filt.As[t]]])
            Bq = np.vstack([md.G[q], filt.Gs[t] @ md.J[q]])
            M = Aq @ M @ Aq.T + Bq @ Sg @ Bq.T
            Cp = np.concatenate([md.Ex, -filt.Ep], axis=1)
            np.testing.assert_allclose(pred[t + 1][:, :, r], Cp @ M @ Cp.T, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("m", [1, 2])
def test_mode_aware_covariances_compiled_equal_numpy(m):
    # the compiled run-outer filter (kalman_numba's inlined update_pinv / predict) against the numpy core on
    # the same trace, every mode, m = 1 and m = 2 (two outputs: the pivoted pseudo-inverse update)
    pytest.importorskip("numba")
    S = EX2 if m == 1 else LinearSystem.create(EX2.A, [[1, 1], [0, 1]], EX2.Q, [[0.25, 0.05], [0.05, 0.5]])
    tr = _ch().sample_trace(np.random.default_rng(12), 300, 30)
    qs = ("filtered", "predicted")
    a = dict(MarkovLMIEstimator(kind="markov_lmi", filter="mode_aware", backend="numpy").covariances(S, tr, [1, 7, 30], qs))
    b = dict(MarkovLMIEstimator(kind="markov_lmi", filter="mode_aware", backend="numba").covariances(S, tr, [1, 7, 30], qs))
    assert sorted(a) == sorted(b) == [1, 7, 30]
    for k in a:
        for q in qs:
            np.testing.assert_allclose(b[k][q], a[k][q], rtol=1e-9, atol=1e-12)


def test_naive_with_only_mode_1_is_the_kf_and_an_unresolvable_covariance_is_inf():
    # the naive KF's gains are the KF's when every packet is on time: its exact per-run error covariance
    # (the joint second moment of [ξ; s], eq. 29) is the kf's P, to the round-off of that route (1e-9 relative
    # on a stable plant). With A = diag(1e6, 0.5) that second moment grows as 1e12 per step and the readout
    # C M Cᵀ cancels every digit: reported as inf (diverged), never as a wrong finite number.
    R, K = 5, 30
    tr = Trace(runs=R, horizon=K, mode=np.zeros((K, R), np.int8), arrival=np.ones((1, K, R), bool), meta={})
    ks = range(1, K + 1)
    qs = ("filtered", "predicted")
    kf = dict(KalmanFilterEstimator(kind="kf").covariances(EX2, tr, ks, qs))
    nv = dict(MarkovLMIEstimator(kind="markov_lmi", filter="naive").covariances(EX2, tr, ks, qs))
    for k in ks:
        for q in qs:
            np.testing.assert_allclose(nv[k][q], kf[k][q], rtol=1e-9, atol=1e-12)
    S = LinearSystem.create([[1e6, 0], [0, 0.5]], [[1, 0]], np.eye(2), 1.0)
    got = dict(MarkovLMIEstimator(kind="markov_lmi", filter="naive").covariances(S, tr, [1, 5, 30], qs))
    for k in got:
        for q in qs:
            assert np.isinf(got[k][q]).all(), (k, q)
