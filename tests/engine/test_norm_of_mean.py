"""``time_average`` with ``statistic: norm_of_mean``: ‖E P_k‖₂ and its delta-method s.e. (metrics/norm_of_mean.py).

* the reducer against a brute-force numpy computation on the same stored per-run P (chunked, weighted);
* the metric against the exact E P_k of a Bernoulli-loss Kalman filter, enumerated over every loss pattern;
* the delta-method s.e. against the spread over independent seeds;
* scenario 2 of Mostofi & Murray (invertible C, burst-conditioned: exact per run) against eq. (14)'s norm;
* the eigen-gap flag, and the config errors.
"""

import itertools

import numpy as np
import pytest

from netkf_cli.app import runner
from netkf_cli.core.artefact import RunContext
from netkf_cli.core.errors import ConfigError
from netkf_cli.config.loader import load_scenario_text
from netkf_cli.metrics import norm_of_mean as nm
from netkf_cli.runtime.montecarlo import add_stats
from netkf_cli.core.tolerances import EIGEN_GAP_SE

A = [[1.25, 0.3], [0.0, 0.8]]
C = [[1.0, 0.5]]
Q = [[0.5, 0.1], [0.1, 0.3]]
R = 0.7
P0 = [[20.0, 3.0], [3.0, 10.0]]  # far from stationarity: E P_k moves a lot per step (a step off by one shows)
P0_NEAR = [[2.0, 0.3], [0.3, 1.0]]  # near it: a light-tailed P_k for the s.e.-vs-spread check
LAM = 0.8

KF = f"""
name: nom
system: {{A: {A}, C: {C}, Q: {Q}, R: {R}, P0: {P0}}}
channel: {{kind: bernoulli, arrival: {LAM}}}
estimator: {{kind: kf}}
analysis: {{kind: time_average, statistic: norm_of_mean, at: {{at}}, quantities: [predicted, filtered]}}
montecarlo: {{{{runs: {{runs}}, horizon: {{at}}, burn_in: 0, seed: {{seed}}, chunk: 1000}}}}
"""


def _kf(at: int, runs: int, seed: int, p0=P0):
    text = KF.replace("{at}", str(at)).replace("{runs}", str(runs)).replace("{seed}", str(seed))
    text = text.replace(f"P0: {P0}", f"P0: {p0}")
    return runner.compute(load_scenario_text(text.replace("{{", "{").replace("}}", "}")), RunContext()).table


def _random_P(rng, n, runs, scale):
    G = rng.standard_normal((n, n, runs)) * scale[:, None, None]
    return np.einsum("ijr,kjr->ikr", G, G) + 0.1 * np.eye(n)[:, :, None]


def _brute(X, w=None):
    """(‖mean‖₂, delta-method s.e.) straight from the stored per-run matrices X (runs, n, n)."""
    if w is not None:
        X = X * w[:, None, None]
    M = X.mean(axis=0)
    lam, V = np.linalg.eigh(M)
    u = V[:, -1]
    # the gradient of λ_max at M in direction D is uᵀ D u: its variance over runs / runs
    g = np.einsum("i,rij,j->r", u, X, u)
    return lam[-1], g.std(ddof=1) / np.sqrt(len(g))


@pytest.mark.parametrize("weighted", [False, True])
def test_reducer_equals_brute_force_on_the_same_runs_for_any_chunking(weighted):
    rng = np.random.default_rng(1)
    n, runs, steps = 3, 900, [4, 7]
    Ps = {k: _random_P(rng, n, runs, np.array([3.0, 1.0, 0.5])) for k in steps}
    w = rng.exponential(1.0, runs) if weighted else None
    Xbar = np.mean([np.moveaxis(Ps[k], -1, 0) for k in steps], axis=0)  # per-run time average (runs, n, n)
    want, want_se = _brute(Xbar, w)
    for cuts in ([0, 900], [0, 100, 450, 900], [0, 1, 899, 900]):
        total = None
        for a, b in zip(cuts[:-1], cuts[1:]):
            red, st = nm.MeanMatrixReducer(steps), {}
            for k in steps:
                red.update(st, 0, k, Ps[k][:, :, a:b], None if w is None else w[a:b])
            red.finish(st)
            st["n"] = np.asarray(b - a)
            total = add_stats(total, st)
        r = nm.norm_of_mean(total, 0)
        assert r["value"] == pytest.approx(want, rel=1e-12)
        assert r["stderr"] == pytest.approx(want_se, rel=1e-9)
        assert not r["eigen_gap"]
        # the shifted sums (second pass about a constant) give the same mean and s.e.
        c = nm.packed_mean(total, 0)
        red, st = nm.MeanMatrixReducer(steps, {0: c}), {}
        for k in steps:
            red.update(st, 0, k, Ps[k], w)
        red.finish(st)
        st["n"] = np.asarray(runs)
        rs = nm.norm_of_mean(st, 0, {0: c})
        assert rs["value"] == pytest.approx(want, rel=1e-12)
        assert rs["stderr"] == pytest.approx(want_se, rel=1e-9)


def test_nonfinite_runs_are_left_out_and_counted():
    rng = np.random.default_rng(2)
    P = _random_P(rng, 2, 50, np.array([1.0, 1.0]))
    P[0, 0, 7] = np.inf
    red, st = nm.MeanMatrixReducer([1]), {}
    red.update(st, 0, 1, P)
    red.finish(st)
    st["n"] = np.asarray(50)
    assert int(st["nonfinite_0"]) == 1
    keep = np.delete(np.moveaxis(P, -1, 0), 7, axis=0)
    assert nm.norm_of_mean(st, 0)["value"] == pytest.approx(_brute(keep)[0], rel=1e-12)


def test_a_degenerate_top_eigenvalue_is_flagged_and_has_no_stderr():
    # isotropic per-run matrices: E P = c I, λ1 = λ2, so λ_max is not differentiable there
    rng = np.random.default_rng(3)
    P = _random_P(rng, 2, 2000, np.array([1.0, 1.0]))
    red, st = nm.MeanMatrixReducer([1]), {}
    red.update(st, 0, 1, P)
    red.finish(st)
    st["n"] = np.asarray(2000)
    r = nm.norm_of_mean(st, 0)
    assert r["eigen_gap"] and np.isnan(r["stderr"])
    assert r["gap_noise"] * EIGEN_GAP_SE > 1


def _exact_kf(k: int, p0=P0):
    """E P_{k|k} and E P_{k+1|k} of the intermittent Kalman filter from P_{0|0} = P0, every one of the 2^k
    arrival patterns weighted by its probability (netkf's time base: predict, then update if received)."""
    a, c, q = np.array(A), np.array(C), np.array(Q)
    filt = np.zeros((2, 2))
    for pat in itertools.product([0, 1], repeat=k):
        P = np.array(p0)
        for g in pat:
            P = a @ P @ a.T + q
            if g:
                S = c @ P @ c.T + R
                P = P - P @ c.T @ np.linalg.solve(S, c @ P)
        filt += LAM ** sum(pat) * (1 - LAM) ** (k - sum(pat)) * P
    return {"filtered": filt, "predicted": a @ filt @ a.T + q}


def test_kf_norm_of_mean_matches_the_enumerated_exact_mean_within_5_se():
    k = 6
    exact = {q: np.linalg.norm(M, 2) for q, M in _exact_kf(k).items()}
    t = _kf(k, 100_000, 11)
    mc = t[t.source == "monte_carlo"]
    assert set(mc.series) == {"‖E P‖"} and set(mc.quantity) == {"predicted", "filtered"}
    for _, r in mc.iterrows():
        assert r.flag_reason in ("", np.nan) or str(r.flag_reason) == "nan"
        z = (r.value - exact[r.quantity]) / r.stderr
        assert abs(z) < 5, (r.quantity, r.value, exact[r.quantity], r.stderr)
        # the test sees a step off by one: E P_5 and E P_7 are 14 and 4.4 s.e. away from E P_6 here
        assert r.stderr < 0.03 * r.value


def test_delta_method_se_matches_the_spread_over_independent_seeds():
    k, K = 5, 40
    vals, ses = [], []
    for seed in range(K):
        t = _kf(k, 2000, 100 + seed, P0_NEAR)
        r = t[(t.source == "monte_carlo") & (t.quantity == "predicted")].iloc[0]
        vals.append(r.value)
        ses.append(r.stderr)
    spread, se = np.std(vals, ddof=1), np.mean(ses)
    # the sample s.d. of K values has relative s.e. ≈ 1/√(2(K − 1)) = 11 %: 4.5 of them either side
    tol = 4.5 / np.sqrt(2 * (K - 1))
    assert abs(spread / se - 1) < tol, (spread, se)
    exact = np.linalg.norm(_exact_kf(k, P0_NEAR)["predicted"], 2)  # and the seeds' mean is on the exact value
    assert abs(np.mean(vals) - exact) < 5 * se / np.sqrt(K)


FADING = """
name: nomf
system:
  A: [[2, 0.3, 0.45], [0.4, 0.2, 0.5], [1.5, 0.6, 0.34]]
  C: [[2, 0, 0], [0, 2, 0], [0, 0, 2]]
  Q: [[0.001, 0, 0], [0, 0.001, 0], [0, 0, 0.001]]
  R: [[1.0e-8, 0, 0], [0, 1.0e-8, 0], [0, 0, 1.0e-8]]
  P0: [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
channel:
  kind: fading
  snr_avg: {value: 20, unit: dB}
  noise: {model: ber, N_p: 10, Delta: 0.0390625}
  threshold: {value: 0, unit: linear}
estimators: [{kind: receiver, scenario: 2}, {kind: receiver, scenario: 3}]
analysis:
  kind: time_average
  statistic: norm_of_mean
  at: 40
  quantity: predicted
  over: {channel.threshold.value: [4, 14]}
  references: [fading_scenario2_exact, fading_lemma5]
montecarlo: {runs: 300, horizon: 40, burn_in: 0, seed: 5, chunk: 100}
"""


def test_fading_scenario2_is_eq14s_norm_and_scenario3_is_above_lemma5():
    t = runner.compute(load_scenario_text(FADING), RunContext()).table
    for T in (4, 14):
        g = t[t["channel.threshold.value"] == T]
        mc2 = g[(g.source == "monte_carlo") & (g.estimator == "receiver scenario=2")].iloc[0]
        ex2 = g[g.reference == "fading_scenario2_exact"].iloc[0]
        assert mc2.value == pytest.approx(ex2.value, rel=1e-9)  # burst-conditioned scenario 2: exact per run
        assert mc2.stderr < 1e-9 * mc2.value
        mc3 = g[(g.source == "monte_carlo") & (g.estimator == "receiver scenario=3")].iloc[0]
        lb = g[g.reference == "fading_lemma5"].iloc[0]
        assert mc3.value > lb.value - 5 * mc3.stderr
        assert mc3.value < mc2.value  # the cross-layer path helps (Fig. 6)


SCALAR = f"system: {{A: {A}, C: {C}, Q: {Q}, R: {R}, P0: {P0}}}", "system: {A: 1.2, C: 1, Q: 1, R: 1, P0: 1}"


@pytest.mark.parametrize("edits, where", [
    ([("statistic: norm_of_mean,", "statistic: norm_of_mean, M: [3],")], "norm_of_mean"),
    ([("at: 4,", "at: 9,")], "analysis.at"),
    ([("burn_in: 0", "burn_in: 2")], "montecarlo.burn_in"),
    # a closed form of E tr P (Sinopoli et al.'s scalar bounds) is not a bound on ‖E P‖: refused, not drawn
    ([SCALAR, ("quantities: [predicted, filtered]", "quantities: [predicted], references: [kf_bernoulli_bounds]")],
     "analysis.references"),
])
def test_bad_configs_name_the_field(edits, where):
    text = KF.replace("{at}", "4").replace("{runs}", "50").replace("{seed}", "1")
    text = text.replace("{{", "{").replace("}}", "}").replace("horizon: 4", "horizon: 5")
    for edit in edits:
        assert edit[0] in text
        text = text.replace(*edit)
    with pytest.raises((ConfigError, ValueError)) as e:
        runner.compute(load_scenario_text(text, file="nom.yaml"), RunContext())
    assert where in str(e.value), str(e.value)


MVT = KF.replace("analysis: {kind: time_average, statistic: norm_of_mean, at: {at}, quantities: [predicted, filtered]}",
                 "analysis: {kind: mean_vs_time, of: {of}, quantity: predicted, every: {at}}")
assert MVT != KF


def test_norm_of_mean_equals_the_norm_of_mean_vs_times_entries_on_the_same_runs():
    """Another reducer on the same traces: mean_vs_time's E P_k entries (MomentReducer), unpacked, have the same
    λ_max; mean_vs_time's E λ_max(P_k) is ≥ it (λ_max is convex: Jensen, exactly on any sample); and time_average's
    mean_trace at the same step is mean_vs_time's E tr P_k."""
    k, runs, seed = 6, 3000, 21
    norm = _kf(k, runs, seed)
    norm = norm[(norm.source == "monte_carlo") & (norm.quantity == "predicted")].iloc[0]

    def mvt(of):
        text = MVT.replace("{of}", of).replace("{at}", str(k)).replace("{runs}", str(runs)).replace("{seed}", str(seed))
        t = runner.compute(load_scenario_text(text.replace("{{", "{").replace("}}", "}")), RunContext()).table
        return t[t.k == k]

    ent = mvt("entries")
    M = np.zeros((2, 2))
    for _, r in ent.iterrows():
        a, b = (int(x) - 1 for x in r.series[2:-1].split(","))
        M[a, b] = M[b, a] = r.value
    assert norm.value == pytest.approx(np.linalg.eigvalsh(M)[-1], rel=1e-12)
    assert mvt("lambda_max").value.iloc[0] >= norm.value * (1 - 1e-12)
    text = KF.replace("statistic: norm_of_mean", "statistic: mean_trace").replace("{at}", str(k)).replace(
        "{runs}", str(runs)).replace("{seed}", str(seed)).replace("quantities: [predicted, filtered]", "quantity: predicted")
    tr = runner.compute(load_scenario_text(text.replace("{{", "{").replace("}}", "}")), RunContext()).table
    tr = tr[tr.source == "monte_carlo"].iloc[0]
    assert tr.series == "E[tr P]"
    assert tr.value == pytest.approx(mvt("trace").value.iloc[0], rel=1e-12)
    assert tr.value == pytest.approx(np.trace(M), rel=1e-12)
