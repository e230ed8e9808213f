"""NEES / empirical-covariance consistency (issue 21): the empirical error covariance of the simulated
estimates equals the reported P within Monte Carlo error, for every estimator with ``estimates``.

Tolerance (per step and series): 5 standard errors of the Monte Carlo mean. With a Gaussian error and P its
covariance, NEES ~ χ²(rank P) (variance 2·rank), so the s.e. of the mean NEES over R runs is ≈ √(2 rank / R);
‖e‖² − tr P is paired per run. A two-sided 5σ event has p ≈ 6e-7, so the ~200 comparisons below fail by chance
with probability ≈ 1e-4.
"""

from __future__ import annotations

import numpy as np
import pytest

from netkf_cli.engine import state
from netkf_cli.channels.delay import DelayChannel
from netkf_cli.channels.fading import FadingChannel
from netkf_cli.channels.markov_modes import MarkovModesChannel
from netkf_cli.channels.multi import MultiChannel
from netkf_cli.estimators.buffered import BufferedEstimator
from netkf_cli.estimators.fading_receivers import ReceiverEstimator
from netkf_cli.estimators.fusion import FusionEstimator
from netkf_cli.estimators.kf import KalmanFilterEstimator
from netkf_cli.estimators.markov_lmi import MarkovLMIEstimator
from netkf_cli.estimators.smart_sensor import SmartSensorEstimator
from netkf_cli.estimators.smoother import SmootherEstimator
from netkf_cli.core.stats import mean_se
from netkf_cli.core.system import LinearSystem
from netkf_cli.core.trace import Trace

Z = 5.0
RUNS, HORIZON = 4000, 12
STEPS = [1, 2, 3, 5, 8, 12]


class TwoLinks:
    """Two independent Bernoulli links (one stream per sensor), for the multi-sensor Kalman filter."""

    kind = "two_links"
    trace_kinds = frozenset({"arrival"})

    def __init__(self, p=(0.7, 0.4)):
        self.p = np.asarray(p)

    def sample_trace(self, rng, runs, horizon):
        return Trace(runs=runs, horizon=horizon, arrival=rng.random((2, horizon, runs)) < self.p[:, None, None])


class OneLink(TwoLinks):
    def __init__(self, p=0.6):
        self.p = np.asarray([p])

    def sample_trace(self, rng, runs, horizon):
        return Trace(runs=runs, horizon=horizon, arrival=rng.random((1, horizon, runs)) < self.p[0])


SYS2 = LinearSystem(A=np.array([[1.1, 0.2], [0.0, 0.9]]), C=np.eye(2), Q=0.3 * np.eye(2), R=np.diag([0.5, 0.8]))
SYS2_CORR = LinearSystem(A=SYS2.A, C=SYS2.C, Q=SYS2.Q, R=np.array([[0.5, 0.3], [0.3, 0.8]]))  # joint update of rows
MARKOV_SYS = LinearSystem(A=np.array([[0.8, 0.0], [0.9, 0.2]]), C=np.array([[1.0, 1.0]]),
                          Q=np.array([[0.36, 0.30], [0.30, 0.25]]), R=np.array([[0.25]]), P0=np.zeros((2, 2)))
MARKOV_CH = MarkovModesChannel(kind="markov_modes", transition=[[0.7, 0, 0.1, 0.2], [0.7, 0.15, 0.05, 0.1],
                                                                [0.7, 0.15, 0.05, 0.1], [0.7, 0.15, 0.05, 0.1]],
                               initial="stationary")

CASES = {
    "kf one packet": (SYS2, OneLink(), KalmanFilterEstimator(kind="kf")),
    "kf two sensors (sequential)": (LinearSystem(A=SYS2.A, C=SYS2.C, Q=SYS2.Q, R=SYS2.R), TwoLinks(),
                                    KalmanFilterEstimator(kind="kf")),
    "kf two correlated sensors (joint)": (SYS2_CORR, TwoLinks(), KalmanFilterEstimator(kind="kf")),
    "markov mode-aware KF": (MARKOV_SYS, MARKOV_CH, MarkovLMIEstimator(kind="markov_lmi", filter="mode_aware")),
    "markov naive KF": (MARKOV_SYS, MARKOV_CH, MarkovLMIEstimator(kind="markov_lmi", filter="naive")),
    "markov LMI filter": (MARKOV_SYS, MARKOV_CH, MarkovLMIEstimator(kind="markov_lmi", filter="lmi")),
    # the exact LMMSE reports E[e eᵀ] over all mode paths (the same P in every run): NEES and ‖e‖² − tr P
    # still have mean rank P and 0 when that P is the error covariance
    "markov exact LMMSE": (MARKOV_SYS, MARKOV_CH, MarkovLMIEstimator(kind="markov_lmi", filter="lmmse")),
}
# Moayedi's Example 1: the measurement noise is the process noise (v = 0.2 w): singular Σ, cross-covariance S
EX1_SYS = LinearSystem(A=np.array([[1.7240, -0.7788], [1.0, 0.0]]), C=np.array([[0.0286, 0.0264]]),
                       Q=np.array([[1.0, 0.0], [0.0, 0.0]]), R=np.array([[0.04]]), P0=np.zeros((2, 2)))
EX1_S = [[0.2], [0.0]]
EX1_CH = MarkovModesChannel(kind="markov_modes", transition=[[0.8, 0, 0.1, 0.1], [0.8, 0.1, 0.05, 0.05],
                                                             [0.8, 0.1, 0.05, 0.05], [0.8, 0.1, 0.05, 0.05]],
                            initial="stationary")
DELAY = DelayChannel(kind="delay", delay={"kind": "poisson", "mean": 1.5}, buffer=3)
PAIR_SYS = LinearSystem(A=SYS2.A, C=np.array([[1.0, 0.0]]), Q=SYS2.Q, R=np.array([[0.5]]))  # [C; CA] invertible
CASES["buffered (delays, D = 3)"] = (SYS2, DELAY, BufferedEstimator(kind="buffered"))
CASES["buffered, pair packets (y_t, y_t-1)"] = (PAIR_SYS, DELAY, BufferedEstimator(kind="buffered", packet="pair"))
CASES["smart sensor (delays, D = 3)"] = (SYS2, DELAY, SmartSensorEstimator(kind="smart_sensor"))
CASES["smoother lag 2 (its filter)"] = (SYS2, OneLink(), SmootherEstimator(kind="smoother", lag=2))
FADING = FadingChannel(kind="fading", snr_avg={"value": 6, "unit": "linear"}, threshold={"value": 2, "unit": "linear"},
                       noise={"model": "inverse_snr", "beta": 0.5})  # σ_n² = 0.5/Υ on kept packets
NOISE_FREE = FadingChannel(kind="fading", snr_avg={"value": 6, "unit": "linear"}, threshold={"value": 2, "unit": "linear"},
                           noise={"model": "inverse_snr", "beta": 0.0})
for sc in (2, 3):
    CASES[f"receiver scenario {sc} (fading, σ_n² = 0.5/Υ)"] = (SYS2, FADING, ReceiverEstimator(kind="receiver", scenario=sc,
                                                                                                variance_reduction="none"))
CASES["receiver scenario 2, C 1×2 (the receiver's own P_f gain)"] = (PAIR_SYS, FADING, ReceiverEstimator(
    kind="receiver", scenario=2, variance_reduction="none"))
CASES["receiver scenario 1 (no communication noise)"] = (SYS2, NOISE_FREE, ReceiverEstimator(kind="receiver", scenario=1,
                                                                                               variance_reduction="none"))
TWO_SENSORS = LinearSystem(A=SYS2.A, C=np.array([[1.0, 0.0], [1.0, 0.0]]), Q=SYS2.Q, R=np.diag([0.5, 0.5]),
                           sensors=((0,), (1,)))  # two identical sensors, one link each
CASES["fusion MF (two sensors)"] = (TWO_SENSORS, TwoLinks(), FusionEstimator(kind="fusion", strategies=["mf"]))
CASES["fusion IBF (two sensors)"] = (TWO_SENSORS, TwoLinks(), FusionEstimator(kind="fusion", strategies=["ibf"]))
CASES["fusion IBF on a multi channel"] = (TWO_SENSORS, MultiChannel(kind="multi", sensors=2, loss=0.4),
                                          FusionEstimator(kind="fusion", strategies=["ibf"]))
for f in ("mode_aware", "naive", "lmi", "lmmse"):
    CASES[f"markov {f}, correlated noise (Example 1)"] = (EX1_SYS, EX1_CH,
                                                          MarkovLMIEstimator(kind="markov_lmi", filter=f, S=EX1_S))


def _consistency(st, j, n):
    out = {}
    bad = st[f"nonfinite_{j}"]
    assert not bad.any()
    out["nees"] = mean_se(st[f"sum_nees_{j}"], st[f"sumsq_nees_{j}"], n)
    out["rank"] = st[f"sum_rank_{j}"] / n
    out["d"] = mean_se(st[f"sum_d_{j}"], st[f"sumsq_d_{j}"], n)
    return out


@pytest.mark.parametrize("quantity", ["filtered", "predicted"])
@pytest.mark.parametrize("case", list(CASES))
def test_empirical_error_covariance_equals_reported_P(case, quantity):
    system, channel, est = CASES[case]
    S = np.asarray(est.S, float) if getattr(est, "S", None) is not None else None
    st = state.simulate_errors(system, channel, [est], steps=STEPS, runs=RUNS, horizon=HORIZON, seed=21,
                               chunk=RUNS // 2, quantity=quantity, S=S)
    c = _consistency(st, 0, RUNS)
    (ne, ne_se), rank, (d, d_se) = c["nees"], c["rank"], c["d"]
    assert np.all(np.abs(ne - rank) <= Z * ne_se), (case, quantity, ne, rank, ne_se)
    assert np.all(np.abs(d) <= Z * d_se), (case, quantity, d, d_se)
    # the test has power: an estimator reporting 0.7 P would be caught (NEES 1/0.7 = 1.43× its expectation)
    assert np.all(0.43 * rank > 2 * Z * ne_se)


def test_nees_detects_scenario_1_on_a_noisy_link():
    """Mostofi's scenario 1 assumes kept packets carry no communication noise (eq. 7, S₁ = 0): its P is the error
    covariance only on such a link; with σ_n² = 2/Υ its errors exceed what it reports, and NEES says so."""
    est = ReceiverEstimator(kind="receiver", scenario=1, variance_reduction="none")
    noisy = FADING.model_copy(update={"noise": NOISE_FREE.noise.model_copy(update={"beta": 2.0})})
    st = state.simulate_errors(SYS2, noisy, [est], steps=STEPS, runs=RUNS, horizon=HORIZON, seed=24, chunk=RUNS)
    (ne, ne_se), rank = mean_se(st["sum_nees_0"], st["sumsq_nees_0"], RUNS), st["sum_rank_0"] / RUNS
    assert np.all(ne[1:] - rank[1:] > Z * ne_se[1:]), (ne, rank, ne_se)


@pytest.mark.parametrize("system,channel", [(SYS2, OneLink()), (TWO_SENSORS, TwoLinks())], ids=["one link", "two sensors"])
def test_smoothed_estimates_are_consistent(system, channel):
    """x̂_{k−N|k} against x_{k−N} (N = 2; the first smoothed step is k = N, back to x_0)."""
    est = SmootherEstimator(kind="smoother", lag=2)
    st = state.simulate_errors(system, channel, [est], steps=[2, 3, 5, 8, 12], runs=RUNS, horizon=HORIZON, seed=23,
                               chunk=RUNS, quantity="smoothed")
    c = _consistency(st, 0, RUNS)
    (ne, ne_se), rank, (d, d_se) = c["nees"], c["rank"], c["d"]
    assert np.all(np.abs(ne - rank) <= Z * ne_se), (ne, rank, ne_se)
    assert np.all(np.abs(d) <= Z * d_se), (d, d_se)
    filt = state.simulate_errors(system, channel, [est], steps=[10], runs=RUNS, horizon=HORIZON, seed=23, chunk=RUNS)
    assert st["sum_e2_0"][-1] < filt["sum_e2_0"][-1]  # x̂_{10|12} beats x̂_{10|10} on the same runs


def test_nees_detects_a_wrong_covariance():
    """An estimator whose reported P is not its error covariance fails the check: a Kalman filter told R/4
    (its P is the optimistic Riccati P of the wrong model, its estimate over-trusts the data)."""
    wrong = LinearSystem(A=SYS2.A, C=SYS2.C, Q=SYS2.Q, R=SYS2.R / 4)

    class Overconfident:  # a plain wrapper, not an EstimatorModel subclass (which would join the kind registry)
        kind, quantities = "kf", ("filtered", "predicted")

        def check(self, system, channel):
            pass

        def estimates(self, system, trace, y, steps, quantities=("filtered",)):
            return KalmanFilterEstimator(kind="kf").estimates(wrong, trace, y, steps, quantities)

    st = state.simulate_errors(SYS2, OneLink(), [Overconfident()], steps=STEPS, runs=RUNS, horizon=HORIZON,
                               seed=22, chunk=RUNS)
    (ne, ne_se), rank = mean_se(st["sum_nees_0"], st["sumsq_nees_0"], RUNS), st["sum_rank_0"] / RUNS
    assert np.all(ne - rank > Z * ne_se)


def test_states_do_not_depend_on_chunking_or_executor_layout():
    """The same chunk plan gives the same bits; the state draws come after the trace from each chunk's rng."""
    system, channel, est = CASES["kf one packet"]
    a = state.simulate_errors(system, channel, [est], steps=STEPS, runs=400, horizon=HORIZON, seed=5, chunk=200)
    b = state.simulate_errors(system, channel, [est], steps=STEPS, runs=400, horizon=HORIZON, seed=5, chunk=200)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])


def test_received_signal_follows_the_markov_packet_model():
    rng = np.random.default_rng(3)
    tr = MARKOV_CH.sample_trace(rng, 500, 20)
    st = state.simulate(MARKOV_SYS, tr, rng)
    z, y, v = st.z, st.y, st.v
    np.testing.assert_array_equal(z[:, 0], v[:, 0])
    for k in range(1, 21):
        q = tr.mode[k - 1]
        np.testing.assert_array_equal(z[:, k, q == 0], y[:, k, q == 0])
        np.testing.assert_array_equal(z[:, k, q == 1], y[:, k - 1, q == 1])
        np.testing.assert_array_equal(z[:, k, q == 2], v[:, k, q == 2])
        np.testing.assert_array_equal(z[:, k, q == 3], z[:, k - 1, q == 3])


def test_every_estimator_kind_has_state_level_estimates():
    from netkf_cli.config.scenario import kinds
    from netkf_cli.core.spec import EstimatorModel

    missing = [k for k, c in kinds(EstimatorModel).items() if not callable(getattr(c, "estimates", None))]
    assert not missing, missing
    tested = {type(e).__name__ for _, _, e in CASES.values()}
    assert {c.__name__ for c in kinds(EstimatorModel).values()} <= tested


def test_state_error_through_the_cli(tmp_path):
    """The metric end to end: CSV, summary, trajectories, figure; two estimators on the same runs."""
    import pandas as pd
    import yaml
    from typer.testing import CliRunner

    from netkf_cli.app.cli import app

    doc = {"name": "se", "system": {"A": [[1.1, 0.2], [0, 0.9]], "C": [[1, 0], [0, 1]], "Q": [[0.3, 0], [0, 0.3]],
                                    "R": [[0.5, 0], [0, 0.8]]},
           "channel": {"kind": "bernoulli", "arrival": 0.6},
           "estimators": [{"kind": "kf"}, {"kind": "smoother", "lag": 1}],
           "analysis": {"kind": "state_error", "quantities": ["filtered", "predicted"], "trajectories": 2},
           "montecarlo": {"runs": 400, "horizon": 10, "seed": 1, "chunk": 200, "burn_in": 4}}
    p = tmp_path / "se.yaml"
    p.write_text(yaml.safe_dump(doc), encoding="utf-8")
    res = CliRunner().invoke(app, ["run", str(p), "--out", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    t = pd.read_csv(tmp_path / "out" / "se.csv")
    assert set(t.series) == {"empirical", "reported", "nees"} and set(t.quantity) == {"filtered", "predicted"}
    sm = pd.read_csv(tmp_path / "out" / "se_summary.csv")
    # the smoother's filter is kf's, step for step: the same estimate on the same runs, difference exactly 0
    d = sm[sm.series == "empirical minus kf"]
    assert len(d) == 2 and (d.value == 0).all()
    tr = pd.read_csv(tmp_path / "out" / "se_trajectories.csv")
    assert set(tr.run) == {0, 1} and {"true", "kf", "arrival"} <= set(tr.series)
    assert (tmp_path / "out" / "se.png").stat().st_size > 10_000


def test_state_error_over_a_grid(tmp_path):
    """``over:``: one table with a column per path; the figure draws the window averages against the grid."""
    import pandas as pd
    import yaml
    from typer.testing import CliRunner

    from netkf_cli.app.cli import app

    doc = {"name": "so", "system": {"A": 0.9, "C": 1, "Q": 1, "R": 1}, "channel": {"kind": "bernoulli", "arrival": 0.5},
           "estimator": {"kind": "kf"}, "analysis": {"kind": "state_error", "over": {"channel.arrival": [0.3, 0.9]}},
           "montecarlo": {"runs": 300, "horizon": 6, "seed": 2, "chunk": 300, "burn_in": 2}}
    p = tmp_path / "so.yaml"
    p.write_text(yaml.safe_dump(doc), encoding="utf-8")
    res = CliRunner().invoke(app, ["run", str(p), "--out", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    sm = pd.read_csv(tmp_path / "out" / "so_summary.csv")
    emp = sm[sm.series == "empirical"].set_index("channel.arrival").value
    assert emp[0.3] > emp[0.9]  # fewer arrivals, larger errors
    assert (tmp_path / "out" / "so.png").stat().st_size > 10_000
