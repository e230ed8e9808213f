"""``over:`` grids, ``time_average`` and closed-form ``references`` (issue 21's generic pieces).

Each over point equals the scenario run on its own at that point (common streams: stream 0; independent:
stream i), several quantities in one pass equal one pass per quantity, the same filter under two names
(kf, the smoother's forward pass) gives the same numbers exactly, and the time-averaged Monte Carlo
lies between Sinopoli et al.'s closed-form bounds.
"""

from dataclasses import replace

import numpy as np
import pytest

from netkf_cli import engine
from netkf_cli.app import runner
from netkf_cli.core.artefact import RunContext
from netkf_cli.core.errors import ConfigError
from netkf_cli.config.loader import load_scenario_text

BASE = """
name: ov
system: {{A: 1.2, C: 1, Q: 1, R: 1, P0: steady}}
channel: {{kind: bernoulli, arrival: 0.7}}
estimators: [{{kind: kf}}, {{kind: smoother, lag: 2}}]
analysis:
  kind: time_average
  quantities: [predicted, filtered, smoothed]
  {extra}
montecarlo: {{runs: 1500, horizon: 120, burn_in: 40, seed: 3, chunk: 500}}
"""

MC = ["estimator", "quantity", "series", "M", "value", "stderr", "nonfinite"]


def _run(extra: str, ctx: RunContext | None = None):
    text = BASE.format(extra=extra)
    if "quantities:" in extra:  # the test's own list replaces the default one
        text = text.replace("  quantities: [predicted, filtered, smoothed]\n", "")
    sc = load_scenario_text(text)
    return runner.compute(sc, ctx or RunContext()).table


def _mc(t):
    return t[t.source == "monte_carlo"].reset_index(drop=True)


@pytest.mark.parametrize("streams", ["common", "independent"])
def test_each_point_equals_its_own_run(streams):
    grid = _run(f"M: [4]\n  over: {{channel.arrival: [0.6, 0.9]}}\n  streams: {streams}")
    assert "channel.arrival" in grid.columns
    for i, lam in enumerate([0.6, 0.9]):
        alone = _run("M: [4]", RunContext(stream=i if streams == "independent" else 0))
        sc = load_scenario_text(BASE.format(extra="M: [4]").replace("arrival: 0.7", f"arrival: {lam}"))
        alone = runner.compute(sc, RunContext(stream=i if streams == "independent" else 0)).table
        got = _mc(grid[grid["channel.arrival"] == lam])[MC]
        np.testing.assert_array_equal(got.value.to_numpy(), _mc(alone)[MC].value.to_numpy())
        assert got.estimator.tolist() == _mc(alone).estimator.tolist()


def test_independent_streams_differ_from_common():
    a = _mc(_run("over: {channel.arrival: [0.8, 0.8]}\n  streams: common"))
    b = _mc(_run("over: {channel.arrival: [0.8, 0.8]}\n  streams: independent"))
    na = len(a) // 2
    np.testing.assert_array_equal(a.value[:na].to_numpy(), a.value[na:].to_numpy())  # same stream twice
    assert not np.array_equal(b.value[:na].to_numpy(), b.value[na:].to_numpy())


def test_same_filter_under_two_names_and_quantities_in_one_pass():
    t = _mc(_run("M: [3, 10]"))
    for q in ("predicted", "filtered"):
        kf, sm = (t[(t.estimator == e) & (t.quantity == q)].value.to_numpy() for e in ("kf", "smoother"))
        np.testing.assert_array_equal(kf, sm)
    assert set(t[t.estimator == "kf"].quantity) == {"predicted", "filtered"}  # kf offers no smoothed
    assert set(t[t.estimator == "smoother"].quantity) == {"predicted", "filtered", "smoothed"}
    # one quantity at a time gives the same numbers as the several-quantities pass
    sc = load_scenario_text(BASE.format(extra="M: [3, 10]").replace("quantities: [predicted, filtered, smoothed]",
                                                                    "quantity: filtered"))
    one = _mc(runner.compute(sc, RunContext()).table)
    both = t[t.quantity == "filtered"].reset_index(drop=True)
    np.testing.assert_array_equal(one.value.to_numpy(), both.value.to_numpy())
    # smoothing lowers the covariance: P_{k-2|k} ≤ P_{k|k} ≤ P_{k+1|k} run by run, so in the mean
    tr = t[t.series == "E[tr P]"].set_index(["estimator", "quantity"]).value
    assert tr["smoother", "smoothed"] < tr["smoother", "filtered"] < tr["smoother", "predicted"]


def test_time_average_equals_the_engines_mean_covariance():
    t = _mc(_run(""))
    sc = load_scenario_text(BASE.format(extra=""))
    kf = sc.estimator_list()[0]
    mc = sc.montecarlo
    ref = engine.mean_covariance(sc.linear_system(), sc.channel, kf, runs=mc.runs, horizon=mc.horizon,
                                 burn_in=mc.burn_in, seed=mc.seed, chunk=mc.chunk, quantity="predicted")
    got = t[(t.estimator == "kf") & (t.quantity == "predicted")].iloc[0]
    assert got.value == pytest.approx(ref["mean_trace"], rel=1e-12)
    assert got.stderr == pytest.approx(ref["stderr"], rel=1e-9)


def test_probability_extremes_are_exact():
    # P_{k|k} ≥ P̄_{k|k} (every packet received) > 0.2 here, and ≤ 1e9 at every step for arrival 0.7
    t = _mc(_run("M: [0.2, 1.0e9]\n  quantities: [filtered]"))
    pr = t[t.series == "Pr[P<=M]"]
    assert (pr[pr.M == 0.2].value == 0).all() and (pr[pr.M == 1e9].value == 1).all()


def test_monte_carlo_between_the_closed_form_bounds():
    t = _run("quantities: [predicted]\n  references: [kf_bernoulli_bounds]\n  over: {channel.arrival: [0.7, 0.9]}")
    for lam in (0.7, 0.9):
        g = t[t["channel.arrival"] == lam]
        ref = g[g.source == "closed_form"].set_index("series").value
        lo, hi = ref.filter(like="lower").iloc[0], ref.filter(like="upper").iloc[0]
        m = g[(g.source == "monte_carlo") & (g.estimator == "kf")].iloc[0]
        assert lo - 5 * m.stderr <= m.value <= hi + 5 * m.stderr, (lam, lo, m.value, hi)
        assert lo < hi


@pytest.mark.parametrize("extra, where, words", [
    ("over: {channel.arrival: [0.5, 0.6], system.A: [1.1]}", "analysis", "equal length"),
    ("over: {analysis.M: [1, 2]}", "analysis", "start with system."),
    ("references: [no_such_form]", "analysis.references", "unknown closed form"),
    ("over: {channel.arrival: [0.5, 1.5]}", "channel.arrival", "over point channel.arrival=1.5"),
    ("over: {channel.nope: [1]}", "channel.nope", "unknown key (not part of the schema"),
])
def test_bad_grids_are_refused_before_running(extra, where, words):
    with pytest.raises(ConfigError) as e:
        load_scenario_text(BASE.format(extra=extra), file="ov.yaml")
    text = str(e.value)
    assert where in text and words in text, text


def test_runner_counts_over_points_in_the_work_size():
    sc = load_scenario_text(BASE.format(extra="over: {channel.arrival: [0.6, 0.7, 0.8]}"))
    assert runner.sweep_points(sc) == 3
    assert runner.work_size(sc) == 3 * sc.montecarlo.runs * sc.montecarlo.horizon
    assert replace(RunContext(), stream=2).stream == 2


def test_theoretical_tail_flags_means_whose_variance_is_infinite():
    # a = 1.3: E[(tr P)²] = ∞ iff (1 − λ)·a⁴ ≥ 1 (φ = log(1−λ)/(2 log a) ≥ −2), i.e. λ ≤ 1 − 1/a⁴ ≈ 0.650,
    # whatever the sample shows; λ = 0.9 is a result
    text = BASE.format(extra="quantities: [predicted]\n  over: {channel.arrival: [0.6, 0.9]}").replace(
        "A: 1.2", "A: 1.3").replace("  quantities: [predicted, filtered, smoothed]\n", "")
    t = _mc(runner.compute(load_scenario_text(text), RunContext()).table)
    tr = t[t.series == "E[tr P]"]
    assert tr[tr["channel.arrival"] == 0.6].heavy_tail.all()
    assert not tr[tr["channel.arrival"] == 0.9].heavy_tail.any()
