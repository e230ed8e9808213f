"""The reliability flags are right in both directions (issue 19, item 4).

* A = 2 over a perfect channel: every run is the same number (the DARE value), the sample variance is
  round-off — no step is flagged heavy-tailed or rare-event dominated, every step is drawn;
* a sample whose sum is carried by one run is flagged rare-event dominated;
* an infinite-variance (Pareto α = 1.5) sample is flagged heavy-tailed, an exponential one is not.
"""

from __future__ import annotations

import numpy as np

from netkf_cli import load, run
from netkf_cli.core.stats import heavy_tail_flag, mean_se, rare_event_flag


def _sums(x):
    return x.sum(), (x**2).sum(), (x**3).sum(), (x**4).sum()


def test_perfect_channel_unstable_plant_is_not_flagged():
    sc = load({"name": "a2", "system": {"A": 2, "C": 1, "Q": 1, "R": 1},
               "channel": {"kind": "bernoulli", "arrival": 1.0}, "estimator": {"kind": "kf"},
               "analysis": {"kind": "mean_vs_time", "every": 1}, "montecarlo": {"runs": 3000, "horizon": 40}})
    res = run(sc)
    t = res.table
    assert not t.heavy_tail.any() and not t.rare_event.any()
    assert (t.stderr == 0).all()
    # every step is drawn: the plotted line has one finite point per step
    line = res.figure.axes[0].get_lines()[0]
    assert np.isfinite(np.asarray(line.get_ydata(), dtype=float)).sum() == 40


def test_degenerate_sample_has_zero_variance_not_noise():
    x = np.full(1000, 4.23606797749979)
    m, se = mean_se(x.sum(), (x * x).sum(), 1000)
    assert se == 0.0 and abs(m - x[0]) < 1e-12
    _, rse, heavy = heavy_tail_flag(*_sums(x), 1000, 0)
    assert rse == 0.0 and not heavy


def test_rare_event_and_heavy_tail_rules_in_both_directions():
    rng = np.random.default_rng(0)
    light = rng.exponential(size=20_000)
    assert not rare_event_flag(light.sum(), light.max(), light.size)
    assert not heavy_tail_flag(*_sums(light), light.size, 0)[2]
    one = np.full(20_000, 1e-3)
    one[17] = 1e3  # one run carries 98 % of the sum
    assert rare_event_flag(one.sum(), one.max(), one.size)
    pareto = rng.pareto(1.5, size=20_000) + 1  # infinite variance
    assert heavy_tail_flag(*_sums(pareto), pareto.size, 0)[2]


def test_a_means_only_estimator_is_refused_where_each_runs_covariance_is_needed():
    from netkf_cli.core.errors import ConfigError

    base = {"name": "vr", "system": {"A": 2, "C": 1, "Q": 0.001, "R": 1e-8},
            "channel": {"kind": "fading", "snr_avg": {"value": 20, "unit": "dB"},
                        "noise": {"model": "ber", "N_p": 10, "Delta": 0.0390625}},
            "estimator": {"kind": "receiver", "scenario": 2, "threshold": {"value": 2, "unit": "linear"},
                          "variance_reduction": "conditioned"},
            "montecarlo": {"runs": 200, "horizon": 10}}
    for analysis in ({"kind": "distribution", "M": [1.0]}, {"kind": "tail", "M": [1.0, 10.0]}):
        try:
            load({**base, "analysis": analysis})
        except ConfigError as exc:
            assert "variance_reduction" in str(exc)
        else:
            raise AssertionError(f"{analysis['kind']} accepted a means-only estimator")
    load({**base, "analysis": {"kind": "mean_vs_time"}})  # means: fine


def test_a_legend_names_only_what_is_drawn_when_every_mean_is_flagged():
    """Every mean of a time average flagged (kf, A = 1.2, λ ≤ 0.5: tail exponent φ ≥ −2, E[(tr P)²] = ∞) is drawn
    hollow, off the line: the legend then has the hollow entry only, not a "(Monte Carlo)" line with nothing on it
    (smoothing/table1's top panel listed five such entries)."""
    sc = load({"name": "flagged", "system": {"A": 1.2, "C": 1, "Q": 1, "R": 1},
               "channel": {"kind": "bernoulli", "arrival": 0.5}, "estimator": {"kind": "kf"},
               "analysis": {"kind": "time_average", "over": {"channel.arrival": [0.45, 0.5]}},
               "montecarlo": {"runs": 200, "horizon": 40, "burn_in": 10, "seed": 1}})
    res = run(sc)
    assert res.table.query("source == 'monte_carlo'").heavy_tail.all()
    labels = [t.get_text() for ax in res.figure.axes if ax.get_legend() for t in ax.get_legend().get_texts()]
    assert any("unreliable" in s for s in labels) and not any("(Monte Carlo)" in s for s in labels), labels
    notes = " ".join(t.get_text() for t in res.figure._netkf_footnotes)
    assert "; 2 unreliable means drawn hollow" in notes, notes
    one = run(sc, overrides={"analysis.over": {"channel.arrival": [0.5]}})  # one flagged mean: singular
    assert "; 1 unreliable mean drawn hollow" in " ".join(t.get_text() for t in one.figure._netkf_footnotes)
