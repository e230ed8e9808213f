"""The CSV's ``flag_reason`` says which rule flagged a mean (stats.FLAG_REASONS), for time_average and
mean_vs_time: non-empty exactly where heavy_tail or rare_event is set, ``theory`` exactly where the manifest's
heavy_tail_by_theory names the estimator (kf on i.i.d. loss: φ = log(1 − λ) / (2 log|a|) ≥ −2)."""

import math

import numpy as np
import pandas as pd
import pytest

from netkf_cli.app import golden
from netkf_cli import load, run
from netkf_cli.core.stats import FLAG_REASONS, flag_reason


def test_codes():
    assert flag_reason() == ""
    assert flag_reason(nonfinite=3, sample=True) == "nonfinite"  # the sample rule's verdict is the non-finite run's
    assert flag_reason(sample=True, theory=True, rare=True) == "sample+theory+rare_event"
    assert set("sample+theory+rare_event+nonfinite".split("+")) == set(FLAG_REASONS)


def _time_average(arrival: float, runs: int = 400):
    return run(load({"name": "fr", "system": {"A": 1.3, "C": 1, "Q": 1, "R": 1, "P0": "steady"},
                     "channel": {"kind": "bernoulli", "arrival": arrival}, "estimator": {"kind": "kf"},
                     "analysis": {"kind": "time_average", "M": 5.0},
                     "montecarlo": {"runs": runs, "horizon": 60, "burn_in": 20, "seed": 3}}))


def _consistent(t: pd.DataFrame) -> None:
    flagged = t.heavy_tail.astype(bool) | t.rare_event.astype(bool)
    assert ((t.flag_reason.fillna("") != "") == flagged).all(), t[["heavy_tail", "rare_event", "flag_reason"]]


@pytest.mark.parametrize("arrival, theory", [(0.5, True), (0.95, False)])
def test_time_average_theory_reason(arrival, theory):
    phi = math.log(1 - arrival) / (2 * math.log(1.3))
    assert (phi >= -2) == theory  # the case is what it claims: −1.32 and −5.7
    res = _time_average(arrival)
    t = res.table
    _consistent(t)
    tr = t[(t.source == "monte_carlo") & (t.series == t.series.iloc[0])]
    assert ("theory" in tr.flag_reason.iloc[0]) == theory
    assert bool(tr.heavy_tail.iloc[0]) or not theory
    assert bool(res.meta["heavy_tail_by_theory"]) == theory
    assert (t[t.source == "monte_carlo"].series != tr.series.iloc[0]).any()  # the Pr rows exist and carry no reason
    assert (t[t.series != tr.series.iloc[0]].flag_reason.fillna("") == "").all()


def test_mean_vs_time_sample_reason():
    # A = 1.3 over a lossy channel at a small horizon: early steps are fine, late ones heavy-tailed by the sample rule
    res = run(load({"name": "frm", "system": {"A": 1.3, "C": 1, "Q": 1, "R": 1},
                    "channel": {"kind": "bernoulli", "arrival": 0.4}, "estimator": {"kind": "kf"},
                    "analysis": {"kind": "mean_vs_time", "every": 1},
                    "montecarlo": {"runs": 300, "horizon": 40, "seed": 5}}))
    t = res.table
    _consistent(t)
    assert (t.flag_reason.fillna("") != "").any() and (t.flag_reason.fillna("") == "").any()
    assert set("+".join(t.flag_reason.fillna("")).replace("+", " ").split()) <= {"sample", "rare_event", "nonfinite"}


def test_golden_ignores_flag_reason_only():
    g = pd.DataFrame({"estimator": ["kf", "kf"], "value": [1.0, 2.0], "stderr": [0.1, 0.1], "n": [100, 100],
                      "flag_reason": ["", "sample"]})
    f = g.copy()
    f["flag_reason"] = ["rare_event", ""]
    assert not golden.compare_tables(f, g).problems
    f2 = g.copy()
    f2["estimator"] = ["kf", "smoother"]
    assert golden.compare_tables(f2, g).problems  # other text columns are still compared exactly
