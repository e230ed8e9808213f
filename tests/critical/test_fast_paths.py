"""The critical topic's fast paths give the numbers of the paths they replaced, bit for bit.

* V̄ at every rate in one batched fixed-point iteration (:func:`cr.v_bars`) = the former one-rate loop;
* the LMIs' probes stacked on one axis (``sdp.max_margin(stacked=True)``) = one probe per call: the same conic data;
* the critical recipe's Monte Carlo time average on the engine (its fused kernel: uniforms → arrivals → filter →
  trace, compiled) = the former trace → generated kernel → numpy prediction → trace pass (:class:`_FormerKernel`);
* the engine's fused kernel carries rescue-flagged runs on the numpy core exactly as the compiled (non-fused)
  filter does (a second kernel pass finds when each run is first flagged);
* the tail metric's window log-likelihoods compiled (metrics/_tail_numba) = numpy's sums;
* the engine's compiled time-average step (_reduce_numba.trace_acc) = numpy's trace / L.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from netkf_cli import engine
from netkf_cli.analysis import critical as cr
from netkf_cli.channels.bernoulli import BernoulliChannel
from netkf_cli.channels.gilbert_elliott import GilbertElliottChannel
from netkf_cli.core.system import LinearSystem
from netkf_cli.estimators.kf import KalmanFilterEstimator
from netkf_cli.linalg import kalman, sdp
from netkf_cli.metrics.tail import covariances, kf_for, time_average_mean
from netkf_cli.runtime.montecarlo import run_chunked

SYSTEMS = {  # (A, C, Q, R) of configs/critical/*.yaml
    "vehicle": (np.array([[1, 0, 0.5, 0], [0, 1, 0, 0.5], [0, 0, 1, 0], [0, 0, 0, 1.0]]),
                np.array([[1, 0, 0, 0], [0, 1, 0, 0.0]]), 0.01 * np.eye(4), 0.001 * np.eye(2)),
    "two_unstable": (np.array([[1.25, 0], [1, 1.1]]), np.array([[0, 1.0]]), np.eye(2), np.eye(1)),
    "degenerate_parity": (np.diag([2.0, -2.0]), np.array([[1.0, 1.0]]), np.eye(2), np.eye(1)),
    "scalar_a2": (np.array([[2.0]]), np.array([[1.0]]), np.eye(1), np.eye(1)),
}


# ---------------------------------------------------------------------------------------------
# V̄: batched fixed-point iteration
# ---------------------------------------------------------------------------------------------


def _former_v_bar(A, C, Q, R, lam, *, rtol=1e-12, max_iter=200_000):
    """The one-rate loop :func:`cr.v_bar` ran before :func:`cr.v_bars` (iteration, then Newton polish)."""
    n = A.shape[0]
    V = np.zeros((n, n))
    scale = 1.0 + float(np.trace(Q))
    for _ in range(max_iter):
        Vn = cr.modified_riccati(V, A, C, Q, R, lam)
        if not np.all(np.isfinite(Vn)) or np.trace(Vn) > 1e14 * scale:
            return np.full((n, n), np.inf)
        step = np.abs(Vn - V).max()
        V = Vn
        if step <= 1e-8 * max(1.0, np.abs(V).max()):
            break
    else:
        return np.full((n, n), np.inf)
    return cr._v_bar_polish(V, A, C, Q, R, lam, rtol)


@pytest.mark.parametrize("name", list(SYSTEMS))
def test_v_bars_equal_the_one_rate_loop_bit_for_bit(name):
    A, C, Q, R = SYSTEMS[name]
    lm = cr.lambda_max(A, C, tol=1e-4).hi
    # above λ_max (converging at very different speeds) and below it (diverging): every column stops on its own
    lams = [lm + 0.002, lm + 0.05, 0.5 * (lm + 1), 0.99] + ([lm - 0.05] if lm > 0.1 else []) + [lm + 0.01]
    got = cr.v_bars(A, C, Q, R, lams, max_iter=20_000)
    for lam, V in zip(lams, got):
        ref = _former_v_bar(A, C, Q, R, lam, max_iter=20_000)
        assert np.array_equal(V, ref), (name, lam)
    assert any(np.isfinite(V).all() for V in got)
    assert any(np.isinf(V).all() for V in got) == (lm > 0.1)
    assert np.array_equal(cr.v_bar(A, C, Q, R, lams[1]), got[1])


def test_v_bars_stops_at_max_iter_like_the_loop():
    A, C, Q, R = SYSTEMS["scalar_a2"]
    got = cr.v_bars(A, C, Q, R, [0.7501, 0.9], max_iter=30)  # 0.7501 needs far more than 30 steps
    assert np.isinf(got[0]).all() and np.array_equal(got[1], _former_v_bar(A, C, Q, R, 0.9, max_iter=30))


# ---------------------------------------------------------------------------------------------
# LMIs: stacked probes
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(SYSTEMS))
def test_stacked_probes_give_the_same_conic_data(name):
    A, C, _, _ = SYSTEMS[name]
    n = A.shape[0]
    lmi = cr._SinopoliLMI(A, C)
    for lam in (0.0, 0.3, 0.77, 1.0):
        f = lambda v, lam=lam: [(lmi.psi(v[0], v[1], lam), True), (v[0], True), (np.eye(n) - v[0], False)]  # noqa: E731
        for (a, ma), (b, mb) in zip(sdp.probes(lmi.vars, f), sdp.probes(lmi.vars, f, stacked=True)):
            assert ma == mb and np.array_equal(a, b)
    mk = cr._MarkovLMI(A, C)
    for p, q in ((0.3, 0.6), (0.05, 0.999), (1.0, 0.41)):
        T = np.array([[1 - q, q], [p, 1 - p]])

        def g(v, T=T):
            M0, M1 = mk.blocks(v[0], v[1], v[2], T)
            return [(M0, True), (M1, True), (v[0], True), (v[1], True), (np.eye(n) - v[0], False)]

        for (a, ma), (b, mb) in zip(sdp.probes(mk.vars, g), sdp.probes(mk.vars, g, stacked=True)):
            assert ma == mb and np.array_equal(a, b)


def test_stacked_and_per_probe_solves_agree():
    A, C, _, _ = SYSTEMS["two_unstable"]
    lmi = cr._SinopoliLMI(A, C)
    f = lambda v: [(lmi.psi(v[0], v[1], 0.6), True), (v[0], True), (np.eye(2) - v[0], False)]  # noqa: E731
    a, b = sdp.max_margin(lmi.vars, f), sdp.max_margin(lmi.vars, f, stacked=True)
    assert a.t == b.t and a.status == b.status and all(np.array_equal(x, y) for x, y in zip(a.values, b.values))


# ---------------------------------------------------------------------------------------------
# Monte Carlo time average on the engine's fused kernel
# ---------------------------------------------------------------------------------------------


class _FormerKernel:
    """The critical recipe's former Monte Carlo chunk (metrics.tail.TimeAverageKernel): per run, the average of
    tr P_{k+1|k} over k in (burn_in, horizon] from ``estimator.covariances``; sums of it and its powers."""

    def __init__(self, system, channel, estimator, horizon, burn_in):
        self.system, self.channel, self.estimator = system, channel, estimator
        self.horizon, self.burn_in = horizon, burn_in

    def __call__(self, rng, runs):
        trace = self.channel.sample_trace(rng, runs, self.horizon)
        steps = list(range(self.burn_in + 1, self.horizon + 1))
        acc = np.zeros(runs)
        with np.errstate(over="ignore", invalid="ignore"):
            for _, P in covariances(self.estimator, self.system, trace, steps, "predicted"):
                acc += np.einsum("iir->r", P) / len(steps)
        ok = np.isfinite(acc)
        a = np.where(ok, acc, 0.0)
        with np.errstate(over="ignore"):
            return {"s1": np.asarray(a.sum()), "s2": np.asarray((a * a).sum()), "s3": np.asarray((a**3).sum()),
                    "s4": np.asarray((a**4).sum()), "bad": np.asarray(float((~ok).sum())), "n": np.asarray(float(runs))}


@pytest.mark.parametrize("name, lam", [("vehicle", 0.3), ("two_unstable", 0.5), ("degenerate_parity", 0.8),
                                        ("degenerate_parity", 0.97), ("scalar_a2", 0.78)])
def test_time_average_mean_is_the_former_kernel_bit_for_bit(name, lam):
    """Chunks of ≥ 1e6 run-steps: the former pass ran the generated kernel, the engine runs the fused one."""
    pytest.importorskip("numba")
    s = LinearSystem.create(*SYSTEMS[name])
    ch = BernoulliChannel(kind="bernoulli", arrival=lam)
    est = kf_for("predicted")
    runs, horizon, burn_in, chunk = 7000, 300, 200, 3500
    old = run_chunked(_FormerKernel(s, ch, est, horizon, burn_in), runs, chunk, 11, stream=3)
    new = time_average_mean(s, ch, est, runs=runs, horizon=horizon, burn_in=burn_in, seed=11, chunk=chunk, stream=3)
    n, bad = float(old["n"]), int(old["bad"])
    m = max(n - bad, 1.0)
    mu = float(old["s1"]) / m
    se = math.sqrt(max(float(old["s2"]) / m - mu * mu, 0.0) * m / max(m - 1, 1) / m)
    assert new["n"] == n and new["nonfinite"] == bad
    assert new["mean_trace"] == (mu if bad == 0 else math.inf) and new["stderr"] == se


# ---------------------------------------------------------------------------------------------
# the engine's fused kernel: rescue-flagged runs
# ---------------------------------------------------------------------------------------------

RESCUE = LinearSystem.create(np.diag([2.0, -2.0]), np.array([[1.0, 1.0]]), np.eye(2), np.eye(1))
CHANNELS = {"bernoulli": BernoulliChannel(kind="bernoulli", arrival=0.6),
            "gilbert_elliott": GilbertElliottChannel(kind="gilbert_elliott", p_gb=0.3, p_bg=0.6)}


@pytest.mark.parametrize("ch", list(CHANNELS))
@pytest.mark.parametrize("quantity", ["filtered", "predicted"])
def test_fused_flagged_runs_equal_the_compiled_filter(ch, quantity):
    """Many runs flagged at many different steps (long loss bursts of a degenerate system): the fused chunk
    equals the compiled filter's (stream_generated) bit for bit on statistics that read the diagonal."""
    pytest.importorskip("numba")
    c = CHANNELS[ch]
    H, R = 120, 3000
    steps = list(range(31, H + 1))
    out = []
    for fused in (True, False):
        ker = engine.PairKernel(RESCUE, c, [KalmanFilterEstimator(kind="kf", backend="numba")], H, steps,
                                engine.TimeAverageReducer(steps), quantity)
        if not fused:
            ker._fused_cache[R] = None  # the trace → compiled covariances → reducer path
        out.append(ker(np.random.default_rng(8), R))
        assert out[-1][engine.FUSED_CHUNKS].tolist() == [int(fused)]
    for key in ("sum_avg", "sumsq_avg", "sum3_avg", "sum4_avg", "max_avg", "nonfinite_avg"):
        assert np.array_equal(out[0][key], out[1][key]), key
    fz = KalmanFilterEstimator(kind="kf", backend="numba").fused(RESCUE, c, 1)
    first = fz.first_flagged(c.uniforms(np.random.default_rng(8), R, H), H)
    flagged_at = np.unique(first[first <= H])
    assert flagged_at.size > 10 and (first <= H).sum() > 30  # flags at many steps: the numpy redo was exercised


# ---------------------------------------------------------------------------------------------
# the tail metric's importance weights: window log-likelihoods compiled
# ---------------------------------------------------------------------------------------------

LAWS = [("bernoulli", 0.5), ("bernoulli", 0.97 * 0.3), ("bernoulli", 1.0), ("bernoulli", 0.0),
        ("bernoulli_steps", np.array([0.97, 0.3, 0.97, 0.3, 0.0, 1.0, 0.5] * 6)),
        ("gilbert_elliott", (0.2, 0.6)), ("gilbert_elliott", (1 - 0.3 * 0.8, 0.6 * 0.3)),
        ("gilbert_elliott", (1.0, 0.0)), ("gilbert_elliott", (0.0, 1.0))]


@pytest.mark.parametrize("law", LAWS, ids=lambda law: f"{law[0]}")
@pytest.mark.parametrize("W", [1, 7, 40])
def test_window_loglik_compiled_equals_numpy(law, W):
    pytest.importorskip("numba")
    from netkf_cli.metrics.tail import window_loglik

    rng = np.random.default_rng(W)
    runs = 3001
    arr = rng.random((1, 60, runs)) < rng.uniform(0.2, 0.9, runs)  # a trace; windows are views of it, as in TailKernel
    win, prev = arr[0, 60 - W:], arr[0, 60 - W - 1]
    a = window_loglik(law, prev, win, backend="numpy")
    b = window_loglik(law, prev, win, backend="numba")
    assert np.array_equal(a, b)  # the same sums in the same order, -inf included
    assert window_loglik(law, prev[:100], win[:, :100]).shape == (100,)  # auto: numpy below COMPILED_MIN_RUNS


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_compiled_trace_average_is_numpys_bit_for_bit(n):
    """engine.TimeAverageReducer's compiled step (_reduce_numba.trace_acc) adds tr P / L as numpy's trace does."""
    pytest.importorskip("numba")
    from netkf_cli.linalg import _reduce_numba as rn
    from netkf_cli.linalg import kalman_codegen as kc

    rng = np.random.default_rng(n)
    runs = 5001
    acc_nb, acc_np = np.zeros(runs), np.zeros(runs)
    for step in range(5):
        X = rng.standard_normal((n, n, runs)) * 10.0 ** rng.uniform(-8, 8, runs)
        P = np.einsum("ijr,kjr->ikr", X, X)
        P[:, :, :3] = [np.inf, np.nan, 1e308][step % 3]  # non-finite and overflowing runs propagate alike
        rn.trace_acc(kc.pack(P), n, 7.0, acc_nb)
        with np.errstate(over="ignore", invalid="ignore"):
            acc_np += np.einsum("iir->r", P) / 7.0
        assert np.array_equal(acc_nb, acc_np, equal_nan=True)


def test_tail_manifest_says_which_likelihood_and_filter_ran(monkeypatch):
    """The tail's manifest names the estimators' backends and the likelihood path its chunks took (recorded per
    chunk, tail.LOGLIK_CHUNKS): numpy below the floor, compiled above it, both with shares when the last chunk
    is smaller; plain Monte Carlo has none. The numbers do not depend on it."""
    import netkf_cli
    from netkf_cli.metrics import tail

    def run(runs, chunk, importance=True):
        sc = netkf_cli.load({"name": "tail_paths", "system": {"A": [[1.3, 0], [0, 1.1]], "C": [[1, 1]],
                                                              "Q": [[1, 0], [0, 1]], "R": 1},
                             "channel": {"kind": "gilbert_elliott", "p_gb": 0.2, "p_bg": 0.6},
                             "estimator": {"kind": "kf"},
                             "analysis": {"kind": "tail", "M": [10.0, 100.0], "importance": importance},
                             "montecarlo": {"runs": runs, "horizon": 40, "seed": 3, "chunk": chunk}})
        return netkf_cli.run(sc)

    small = run(900, 900)
    assert small.meta["likelihood"] == "numpy" and small.meta["backends"] == {"kf": "numpy"}
    assert run(900, 900, importance=False).meta["likelihood"].startswith("none")
    monkeypatch.setattr(tail, "COMPILED_MIN_RUNS", 500)
    if kalman.numba_available():
        big = run(900, 900)
        assert big.meta["likelihood"] == "numba (metrics/_tail_numba)"
        np.testing.assert_array_equal(big.table["value"].to_numpy(float), small.table["value"].to_numpy(float))
        assert run(1200, 900).meta["likelihood"] == "numba (metrics/_tail_numba) (1 of 2 chunks), numpy (1)"


@pytest.mark.parametrize("horizon, windows", [(1, []), (2, [1]), (3, [2])])
def test_tail_default_windows_end_before_the_reported_step(horizon, windows):
    """The default tilt windows fit before the reported step k (a window W resamples steps k − W … k − 1): at k = 1
    none does and the run is plain Monte Carlo; it raised a shape mismatch in the chunk before."""
    import netkf_cli

    sc = netkf_cli.load({"name": "tail_short", "system": {"A": 1.2, "C": 1, "Q": 1, "R": 1},
                         "channel": {"kind": "bernoulli", "arrival": 0.8}, "estimator": {"kind": "kf"},
                         "analysis": {"kind": "tail", "M": [1.0, 2.0]},
                         "montecarlo": {"runs": 40, "horizon": horizon, "seed": 1, "chunk": 40}})
    res = netkf_cli.run(sc)
    imp = res.meta["importance_sampling"]
    assert (imp["windows"] if isinstance(imp, dict) else []) == windows
    assert (res.table["value"].between(0, 1)).all()


def test_a_tail_where_no_run_exceeds_any_M_draws_its_empty_axes(tmp_path):
    """One run, every estimate 0: the figure shows the M range and says why it is empty (matplotlib refused the log
    axis before: an internal error from `netkf run configs/critical/tail_parity.yaml --runs 1`)."""
    from typer.testing import CliRunner

    from netkf_cli.app.cli import app

    cfg = Path(__file__).resolve().parents[2] / "configs" / "critical" / "tail_parity.yaml"
    r = CliRunner().invoke(app, ["run", str(cfg), "--runs", "1", "--out", str(tmp_path / "o"), "-q", "--yes"])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "o" / "critical_tail_parity.png").stat().st_size > 0
