"""End-to-end: every smoothing config at small size against committed golden CSVs, plus the
claims the artefacts exist to show (checked on the fresh small run).

Regenerate after an intended change with ``NETKF_UPDATE_GOLDEN=1 pytest tests/smoothing/test_regression.py``.
Monte Carlo is deterministic for a fixed seed and chunking, and the exact enumerations are
deterministic, so every numeric column must agree to round-off (1e-9 relative).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from netkf_cli.runner import run_scenario_file

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs" / "smoothing"
GOLDEN = Path(__file__).parent / "golden"

SMALL = {
    "table1": (2000, {"analysis": {"paper_steps": 5000}}),
    "critical_rate": (1000, {"analysis": {"lambdas": [0.4, 0.45, 0.6, 0.8], "lags": [-1, 0, 2], "exact_tol": 1e-8}}),
    "retransmission": (2000, {"analysis": {"grid": 30, "g_n_max": 12}}),
    "burstiness": (1000, {"analysis": {"lags": [-1, 0, 2], "mean_bursts": [1.5, 3, 6]}}),
    "burstiness_common": (1000, {"analysis": {"lags": [-1, 0, 2], "mean_bursts": [1.25, 3, 8]}}),
}


def _compare(fresh: Path, gold: Path):
    a, b = pd.read_csv(fresh), pd.read_csv(gold)
    assert list(a.columns) == list(b.columns) and len(a) == len(b), fresh.name
    for c in b.columns:
        if not pd.api.types.is_numeric_dtype(b[c]):
            assert (a[c].fillna("<NA>").astype(str) == b[c].fillna("<NA>").astype(str)).all(), (fresh.name, c)
            continue
        np.testing.assert_allclose(a[c].to_numpy(float), b[c].to_numpy(float), rtol=1e-9, atol=1e-12,
                                   err_msg=f"{fresh.name}:{c}")


@pytest.fixture(scope="module")
def outputs(tmp_path_factory):
    out = {}
    for name, (runs, ov) in SMALL.items():
        out[name] = run_scenario_file(CONFIGS / f"{name}.yaml", out_dir=tmp_path_factory.mktemp(name) / name,
                                      runs=runs, force=True, overrides=ov)
    return out


@pytest.mark.parametrize("name", list(SMALL))
def test_regression(name, outputs):
    out = outputs[name]
    art = f"smoothing_{name}"
    assert (out / f"{art}.png").stat().st_size > 10_000
    csvs = sorted(out.glob("*.csv"))
    assert f"{art}.csv" in {p.name for p in csvs}
    if os.environ.get("NETKF_UPDATE_GOLDEN"):
        GOLDEN.mkdir(exist_ok=True)
        for p in csvs:
            shutil.copy(p, GOLDEN / p.name)
    for p in csvs:
        _compare(p, GOLDEN / p.name)


def test_table1_claims(outputs):
    t = pd.read_csv(outputs["table1"] / "smoothing_table1.csv")
    # every column: Monte Carlo within 5 binomial standard errors of the exact probability
    assert (t[t.series == "z_mc_vs_exact"].value < 5).all()
    # the paper's way (one run) within 5 batch-means standard errors of the exact value
    pw = t[t.series == "prob_paper_way"].set_index("column")
    ex = t[t.series == "prob_exact"].set_index("column")
    assert (np.abs(pw.value - ex.value) < 5 * pw.stderr).all()
    # the guarantee holds at every sufficient rate, and the exact value is certified to 1e-10
    assert (ex.value > 0.95).all() and (ex.stderr < 1e-10).all()
    assert (outputs["table1"] / "table.md").read_text().count("|") > 40


def test_critical_rate_claims(outputs):
    t = pd.read_csv(outputs["critical_rate"] / "smoothing_critical_rate.csv")
    e = t[t.series == "exact"]
    assert np.isinf(e[e.lam < e.lambda_c].value).all() and np.isfinite(e[e.lam > e.lambda_c].value).all()
    # Monte Carlo where the mean has a finite variance: within 5 s.e. (+ bracket half-width) of the exact mean
    m = t[(t.series == "monte_carlo") & (t.reliable > 0)].set_index(["lam", "column"])
    ee = e.set_index(["lam", "column"]).loc[m.index]
    assert len(m) and (np.abs(m.value - ee.value) < 5 * m.stderr + ee.stderr).all()


def test_retransmission_claims(outputs):
    s = pd.read_csv(outputs["retransmission"] / "smoothing_retransmission_summary.csv")
    ks = s[s.quantity == "ks_statistic"]
    assert (ks[ks.versus == "filter"].p_value > 1e-3).all()  # same distribution as the plain filter
    assert (ks[ks.versus != "filter"].p_value < 1e-6).all()  # the smoother is different (better)
    g = pd.read_csv(outputs["retransmission"] / "smoothing_retransmission_g_identity.csv")
    assert np.allclose(g.g_float, 1, atol=1e-12) and (g.g_exact_is_one.dropna() == 1).all()
    assert np.allclose(g.enum_sum.dropna(), 1, atol=1e-12)


@pytest.mark.parametrize("name", ["burstiness", "burstiness_common"])
def test_burstiness_claims(outputs, name):
    t = pd.read_csv(outputs[name] / f"smoothing_{name}.csv")
    assert (t[t.series == "z_mc_vs_exact"].value < 5).all()
    e = t[t.series == "exact"]
    for c, grp in e.groupby("column"):  # longer bursts at the same loss rate: lower probability
        v = grp.sort_values("mean_burst").value.to_numpy()
        assert (np.diff(v) < 1e-12).all(), c
    if name == "burstiness_common":  # at one arrival rate, a longer lag never hurts, whatever the burstiness
        piv = e.pivot_table(index="mean_burst", columns="lag", values="value")
        assert (np.diff(piv.to_numpy(), axis=1) > -1e-12).all()


@pytest.mark.parametrize("name", list(SMALL))
def test_proportions_have_wilson_intervals_of_positive_width(name, outputs):
    """Every Monte Carlo proportion row has ci_low < value-or-equal < ci_high, also at p̂ ∈ {0, 1} (issue 13)."""
    for p in outputs[name].glob("*.csv"):
        t = pd.read_csv(p)
        if "ci_low" not in t.columns:
            continue
        ci = t[t.ci_low.notna()]
        assert len(ci), p.name
        assert (ci.ci_low < ci.ci_high).all(), p.name
        assert ((ci.ci_low <= ci.value + 1e-12) & (ci.value <= ci.ci_high + 1e-12)).all(), p.name
        assert ((ci.ci_low >= 0) & (ci.ci_high <= 1)).all(), p.name


def test_unreliable_monte_carlo_means_are_flagged(outputs):
    t = pd.read_csv(outputs["critical_rate"] / "smoothing_critical_rate.csv")
    m = t[t.series == "monte_carlo"]
    assert ((m.heavy_tail == 1) == (m.lam <= m.lambda_2)).all()
    assert (m[m.heavy_tail == 1].reliable == 0).all()
