"""The derived tables of an over grid (netkf_cli/metrics/derived.py) that the fusion and Shi claims read."""

from __future__ import annotations

import numpy as np
import pandas as pd

from netkf_cli.metrics import derived


def _table():
    rows = []
    for x in (1, 2):
        for est, v, se in (("a", 10.0 * x, 1.0), ("b", 8.0 * x, 0.5)):
            rows.append(dict(x=x, estimator=est, quantity="filtered", series="E[tr P]", M=np.nan, value=v, stderr=se,
                             source="monte_carlo"))
        rows.append(dict(x=x, estimator="a", quantity="filtered", series="bound", M=np.nan, value=9.0 * x,
                         stderr=np.nan, source="closed_form"))
        rows.append(dict(x=x, estimator="a", quantity="predicted", series="bound", M=np.nan, value=1.0,
                         stderr=np.nan, source="closed_form"))
    return pd.DataFrame(rows)


def test_pairs_compare_rows_of_one_point_and_quantity():
    p = derived.pairs(_table(), ["x"])
    ab = p[(p.x == 2) & (p.a_estimator == "a") & (p.b_estimator == "b") & (p.b_source == "monte_carlo")].iloc[0]
    assert ab["diff"] == 4.0 and ab["ratio"] == 20.0 / 16.0
    assert np.isclose(ab["stderr"], np.hypot(1.0, 0.5)) and np.isclose(ab["z"], 4.0 / np.hypot(1.0, 0.5))
    mb = p[(p.x == 1) & (p.a_estimator == "a") & (p.a_source == "monte_carlo") & (p.b_series == "bound")]
    assert len(mb) == 1 and mb.iloc[0]["z"] == 1.0  # (10 − 9) / 1: a closed form has no standard error
    # a closed-form row is compared with rows of its own estimator only, never across quantities
    assert not ((p.a_source == "closed_form") & (p.b_estimator == "b")).any()
    assert set(p.quantity) == {"filtered"}


def test_z_has_a_round_off_floor_where_the_monte_carlo_is_exact():
    t = pd.DataFrame([dict(x=0, estimator="a", quantity="filtered", series="E[tr P]", M=np.nan, value=1.0 + 1e-13,
                           stderr=0.0, source="monte_carlo"),
                      dict(x=0, estimator="a", quantity="filtered", series="bound", M=np.nan, value=1.0, stderr=np.nan,
                           source="closed_form")])
    z = derived.pairs(t, ["x"]).query("a_source == 'monte_carlo'").z.iloc[0]
    assert np.isfinite(z) and abs(z) < 1e-3


def test_trend_differences_along_each_path_with_the_others_fixed():
    t = _table()
    t["y"] = 7
    tr = derived.trend(t, ["x", "y"])
    row = tr[(tr.path == "x") & (tr.estimator == "b") & (tr.source == "monte_carlo")].iloc[0]
    assert (row["from"], row["to"], row["diff"]) == (1, 2, 8.0)
    assert (tr.path == "y").sum() == 0  # y never varies
