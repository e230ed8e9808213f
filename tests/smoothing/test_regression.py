"""Every smoothing config (generic time_average with Leong 2008's closed forms as references) at small
size against committed golden CSVs (the main table, figures drawn once), and the closed forms against the Monte Carlo beside them.

Regenerate after an intended change with ``NETKF_UPDATE_GOLDEN=1 pytest tests/smoothing/test_regression.py``.
Monte Carlo is deterministic for a fixed seed and chunking, and the exact enumerations are deterministic,
so every numeric column must agree to round-off (1e-9 relative). Closed form vs Monte Carlo: 5 standard
errors of the Monte Carlo row (time averages, one sample per run: the s.e. is exact).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from netkf_cli.app import runner
from netkf_cli.core.artefact import RunContext
from netkf_cli.config.loader import load_scenario
from netkf_cli.app.runner import run_scenario_file

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs" / "smoothing"
GOLDEN = Path(__file__).parent / "golden"
Z = 5.0
LAM2 = 0.4507197283469412  # eq. (8)'s rate for N = 2
LAM0 = 0.6315968501359612  # eq. (8)'s rate for N = 0 (the filter)
LAM_PRED = 0.7763932022500211  # eq. (7)'s rate (the predictor)

SHORT = {"burn_in": 20, "horizon": 80}  # P0 = P̄: (1 − λ)^20 < 10⁻⁴ at the smallest rate, below the s.e.
LAGS02 = [{"kind": "smoother", "lag": 0}, {"kind": "smoother", "lag": 2}]
SMALL = {
    "table1": (300, {"estimators": LAGS02, "analysis": {"over": {"channel.arrival": [LAM2, LAM0]}}, "montecarlo": SHORT}),
    "table1_predictor": (300, {"analysis": {"over": {"channel.arrival": [LAM0, LAM_PRED]}}, "montecarlo": SHORT}),
    "critical_rate": (300, {"estimators": [{"kind": "smoother", "lag": 0}, {"kind": "smoother", "lag": 3}],
                            "analysis": {"over": {"channel.arrival": [0.39, 0.41, 0.8, 0.95]}}, "montecarlo": SHORT}),
    "retransmission": (400, {"analysis": {"over": {"channel.p": [0.0, 0.5, 1.0]}}, "montecarlo": SHORT}),
    "burstiness": (300, {"estimators": LAGS02, "analysis": {"over": {"channel.mean_burst": [1.5, 2.218673683682758, 6.0]}},
                         "montecarlo": SHORT}),
    "burstiness_common": (300, {"estimators": LAGS02, "analysis": {"over": {"channel.mean_burst": [1.25, 3.0, 8.0]}},
                                "montecarlo": SHORT}),
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
    """Each config's main table at small size, computed without the figure (figures: test_figure_is_written)."""
    out = {}
    for name, (runs, ov) in SMALL.items():
        path = CONFIGS / f"{name}.yaml"
        art = runner.compute(load_scenario(path, ov), RunContext(runs=runs), source=path)
        folder = tmp_path_factory.mktemp(name)
        art.table.to_csv(folder / f"smoothing_{name}.csv", index=False)
        out[name] = folder
    return out


def _table(outputs, name) -> pd.DataFrame:
    return pd.read_csv(outputs[name] / f"smoothing_{name}.csv")


def _paired(t: pd.DataFrame, path: str, ref_prefix: str = "exact") -> pd.DataFrame:
    """Monte Carlo rows joined with the closed-form row of the same point, estimator, quantity and M."""
    keys = [path, "estimator", "quantity", "M"]
    mc = t[t.source == "monte_carlo"].copy()
    cf = t[(t.source == "closed_form") & t.series.str.startswith(ref_prefix)].copy()
    for d in (mc, cf):
        d["M"] = d["M"].fillna(-1.0)
    return mc.merge(cf[keys + ["value"]], on=keys, suffixes=("", "_ref"))


@pytest.mark.parametrize("name", list(SMALL))
def test_regression(name, outputs):
    fresh = outputs[name] / f"smoothing_{name}.csv"
    if os.environ.get("NETKF_UPDATE_GOLDEN"):
        GOLDEN.mkdir(exist_ok=True)
        shutil.copy(fresh, GOLDEN / fresh.name)
    _compare(fresh, GOLDEN / fresh.name)


def test_figure_is_written(tmp_path):
    runs, ov = SMALL["table1_predictor"]  # every config's figure: netkf reproduce --quick
    out = run_scenario_file(CONFIGS / "table1_predictor.yaml", out_dir=tmp_path / "r", runs=runs, force=True, overrides=ov)
    assert (out / "smoothing_table1_predictor.png").stat().st_size > 10_000


@pytest.mark.parametrize("name, path", [("table1", "channel.arrival"), ("table1_predictor", "channel.arrival"),
                                        ("retransmission", "channel.p"), ("burstiness", "channel.mean_burst"),
                                        ("burstiness_common", "channel.mean_burst")])
def test_exact_probability_equals_monte_carlo_within_5_se(name, path, outputs):
    """Every Monte Carlo Pr[P ≤ M] within 5 s.e. of the certified exact stationary probability at its point
    (retransmission: of i.i.d. loss at the link's λ for every p — the paper's g(n) = 1)."""
    p = _paired(_table(outputs, name), path)
    p = p[p.series == "Pr[P<=M]"]
    assert len(p) >= 2
    se0 = p.stderr == 0  # every run averaged 1 (or 0): no plug-in s.e.; the rule of three bounds 1 − p instead
    assert (p.value[se0].isin([0.0, 1.0]) & (np.abs(p.value - p.value_ref)[se0] <= 3 / p.n[se0])).all()
    q = p[~se0]
    assert len(q) and (np.abs(q.value - q.value_ref) <= Z * q.stderr).all(), q[["estimator", "quantity", path, "value",
                                                                                "value_ref", "stderr"]]


def test_table1_guarantee_is_one_minus_eps_at_each_columns_rate(outputs):
    t = _table(outputs, "table1")
    g = t[t.series.str.startswith("guarantee")]

    def at(d, lam, est=None):
        r = d[np.isclose(d["channel.arrival"], lam, rtol=1e-12) & ((d.estimator == est) if est else True)]
        assert len(r) == 1
        return float(r.value.iloc[0])

    assert at(g, LAM2, "smoother lag=2") == pytest.approx(0.95, abs=1e-12)
    assert at(g, LAM0, "smoother lag=0") == pytest.approx(0.95, abs=1e-12)
    # the guarantee holds: the exact probability is above it everywhere
    p = _paired(t, "channel.arrival", "guarantee")
    ex = _paired(t, "channel.arrival")
    both = p.merge(ex, on=["channel.arrival", "estimator", "quantity", "M", "series"], suffixes=("_g", "_e"))
    assert len(both) and (both.value_ref_e >= both.value_ref_g - 1e-12).all()
    tp = _table(outputs, "table1_predictor")
    assert at(tp[tp.series.str.startswith("guarantee")], LAM_PRED) == pytest.approx(0.95, abs=1e-12)


def test_critical_rate_exact_means_and_monte_carlo(outputs):
    t = _table(outputs, "critical_rate")
    ex = t[(t.source == "closed_form") & t.series.str.startswith("exact")]
    lam_c = 1 - 1 / 1.3**2
    assert np.isinf(ex[ex["channel.arrival"] < lam_c].value).all()
    assert np.isfinite(ex[ex["channel.arrival"] > lam_c].value).all()
    # Monte Carlo where E[P²] < ∞ (λ > 1 − 1/a⁴ = 0.65): within 5 s.e. of the exact mean, and not flagged
    p = _paired(t, "channel.arrival")
    p = p[(p.series == "E[tr P]") & (p["channel.arrival"] > 0.7)]
    assert len(p) == 2 * p.estimator.nunique() and not p.heavy_tail.any()
    assert (np.abs(p.value - p.value_ref) <= Z * p.stderr).all()
    # Lemma 1's lower bound under the exact smoothed mean; both ∞ below λ_c
    lb = _paired(t, "channel.arrival", "Lemma 1")
    lb = lb[lb.series == "E[tr P]"].merge(ex[["channel.arrival", "estimator", "value"]], on=["channel.arrival", "estimator"],
                                          suffixes=("", "_exact"))
    fin = np.isfinite(lb.value_exact)
    assert (lb.value_ref[fin] <= lb.value_exact[fin] * (1 + 1e-9)).all() and np.isinf(lb.value_ref[~fin]).all()


def test_retransmission_g_identity_and_smoother_better(outputs):
    t = _table(outputs, "retransmission")
    g = t[t.series.str.startswith("max |g(n) - 1|")]
    assert set(g["channel.p"]) == {0.0, 0.5, 1.0} and (g.value <= 1e-12).all()
    mc = t[(t.source == "monte_carlo") & (t.series == "Pr[P<=M]")].pivot_table(
        index=["channel.p", "M"], columns="quantity", values="value")
    assert (mc.smoothed > mc.filtered).all()


@pytest.mark.parametrize("name", ["burstiness", "burstiness_common"])
def test_burstiness_exact_decreases_with_the_burst_length(name, outputs):
    t = _table(outputs, name)
    e = t[(t.source == "closed_form") & t.series.str.startswith("exact")]
    for lab, grp in e.groupby("estimator"):  # longer bursts at the same loss rate: lower probability
        v = grp.sort_values("channel.mean_burst").value.to_numpy()
        assert (np.diff(v) < 1e-12).all(), lab
    piv = e.pivot_table(index="channel.mean_burst", columns="estimator", values="value")
    lags = sorted(piv.columns, key=lambda c: int(c.split("=")[1]))
    assert (np.diff(piv[lags].to_numpy(), axis=1) > -1e-12).all()  # a longer lag never hurts
    gi = t[t.series.str.startswith("guarantee")]
    assert len(gi) and gi.series.str.contains("i.i.d. loss only").all()
