"""configs/fig5..fig9 end to end (small run counts) + golden CSV regression.

Regenerate the golden files after an intended change with
    python -m tests.shi2009.test_configs_regression
"""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from netkf_cli.app.runner import run_scenario_file

ROOT = Path(__file__).resolve().parents[2]
GOLDEN = Path(__file__).resolve().parent / "golden"
CONFIGS = ["fig5", "fig6", "fig7", "fig8", "fig9"]
RUNS: dict[str, int] = {}  # updates_vs_buffer is the generic `updates` metric now: tests/fusion/test_updates.py
DEFAULT_RUNS = 4000


def _run(name, tmp):
    out = run_scenario_file(ROOT / "configs" / f"{name}.yaml", out_dir=Path(tmp) / name,
                            runs=RUNS.get(name, DEFAULT_RUNS), force=True)
    return out


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("shi2009")
    return {name: _run(name, tmp) for name in CONFIGS}


def _mc_rows(t: pd.DataFrame) -> np.ndarray:
    """Rows holding a Monte Carlo estimate (a finite standard error and a sample count), or a
    fraction/claim computed from Monte Carlo estimates (``mc_…_fraction``)."""
    mc = np.zeros(len(t), dtype=bool)
    if "stderr" in t and "n" in t:
        mc |= np.isfinite(t["stderr"].to_numpy(float)) & np.isfinite(t["n"].to_numpy(float))
    if "quantity" in t:
        mc |= t["quantity"].astype(str).str.startswith("mc_").to_numpy()
    return mc


def _compare(got: pd.DataFrame, want: pd.DataFrame, what: str):
    """Closed forms and the certified exact value: tight (rtol 1e-9 absorbs BLAS/libm differences).

    Monte Carlo rows: the random stream layout may change (e.g. SeedSequence spawn keys
    (stream, chunk) instead of (chunk,)), so they compare statistically: |got − want| ≤ 5·√(s_g² + s_w²)
    + 1/n (two independent estimates of the same quantity; 1/n covers the binomial lattice when p̂
    is 0 or 1 and its sample s.e. vanishes), with equal n. Fractions of 5σ checks computed from
    Monte Carlo (``mc_…_fraction``) must stay ≥ 0.9 (a 5σ check fails by chance with probability
    < 1e-6 per point, so a drop means a real change).
    """
    assert list(got.columns) == list(want.columns), what
    assert len(got) == len(want), what
    mc = _mc_rows(want)
    assert np.array_equal(mc, _mc_rows(got)), what
    for col in want.columns:
        g, w = got[col], want[col]
        if pd.api.types.is_numeric_dtype(w):
            gv, wv = g.to_numpy(float), w.to_numpy(float)
            assert np.allclose(gv[~mc], wv[~mc], rtol=1e-9, atol=1e-12, equal_nan=True), (what, col)
        else:
            assert g.astype(str).tolist() == w.astype(str).tolist(), (what, col)
    if mc.any():
        gv, wv = got["value"].to_numpy(float)[mc], want["value"].to_numpy(float)[mc]
        if "stderr" in want:
            sg, sw = got["stderr"].to_numpy(float)[mc], want["stderr"].to_numpy(float)[mc]
            n = want["n"].to_numpy(float)[mc]
            stat = np.isfinite(sw)
            assert np.array_equal(got["n"].to_numpy(float)[mc][stat], n[stat]), (what, "n")
            tol = 5 * np.sqrt(sg[stat] ** 2 + sw[stat] ** 2) + 1.0 / n[stat]
            assert np.all(np.abs(gv[stat] - wv[stat]) <= tol), (what, "monte carlo value")
            frac = ~stat
        else:
            frac = np.ones(len(gv), dtype=bool)
        assert np.all(gv[frac] >= 0.9), (what, "monte carlo 5σ fractions")


def _who(t: pd.DataFrame) -> str:
    """The column naming the estimator: ``sensor`` (recipe layout) or ``estimator`` (generic metric)."""
    return "sensor" if "sensor" in t else "estimator"


CLOSED = ("lower_bound", "upper_bound", "exact", "thm41")


def _compare_by_key(got: pd.DataFrame, want: pd.DataFrame, what: str):
    """Figs 5–9 moved from the recipe layout (``sensor``, k1, k2 …) to the generic ``distribution``
    metric (``estimator``, ci_low, ci_high …): rows are matched by (M, estimator, series), so the
    numbers are checked across the migration. Bounds and Thm 4.1: rtol 1e-9; the certified exact
    value: within the two certified errors; Monte Carlo: 5 combined s.e. + 1/n, equal n."""
    g = got.rename(columns={_who(got): "who"}).set_index(["M", "who", "series"]).sort_index()
    w = want.rename(columns={_who(want): "who"}).set_index(["M", "who", "series"]).sort_index()
    assert set(w.index) <= set(g.index), (what, sorted(set(w.index) - set(g.index))[:5])
    g = g.loc[w.index]
    series = w.index.get_level_values("series")
    for name in ("lower_bound", "upper_bound", "thm41"):
        m = series == name
        assert np.allclose(g.value[m], w.value[m], rtol=1e-9, atol=1e-12), (what, name)
    m = series == "exact"
    # two certified brackets overlap; 1e-9 covers the CSV's 10 significant digits and patterns whose
    # λ_max lies within rounding of the PSD tolerance at M (classified by two different tree depths)
    assert np.all(np.abs(g.value[m] - w.value[m]) <= g.err[m].fillna(0) + w.err[m].fillna(0) + 1e-9), (what, "exact")
    m = series == "monte_carlo"
    assert np.array_equal(g.n[m].to_numpy(float), w.n[m].to_numpy(float)), (what, "n")
    tol = 5 * np.sqrt(g.stderr[m] ** 2 + w.stderr[m] ** 2) + 1.0 / w.n[m]
    assert np.all(np.abs(g.value[m] - w.value[m]) <= tol), (what, "monte carlo")


@pytest.mark.parametrize("name", CONFIGS)
def test_regression_against_golden(results, name):
    out = results[name]
    got = pd.read_csv(out / f"{name}.csv")
    want = pd.read_csv(GOLDEN / f"{name}.csv")
    if _who(got) == _who(want):
        _compare(got, want, name)
        _compare(pd.read_csv(out / f"{name}_summary.csv"), pd.read_csv(GOLDEN / f"{name}_summary.csv"), name + "_summary")
    else:  # migrated to the generic metric: same numbers, new layout; the claims still hold
        _compare_by_key(got, want, name)
        summ = pd.read_csv(out / f"{name}_summary.csv")
        old = pd.read_csv(GOLDEN / f"{name}_summary.csv")
        held = set(old.quantity[(old.quantity.str.endswith("_fraction") | old.quantity.str.startswith("claim_"))
                                & (old.value == 1)])
        new = summ[summ.quantity.isin(held)]
        assert len(new) and np.all(new.value >= 0.9), (name, new)
    assert (out / f"{name}.png").stat().st_size > 10_000


@pytest.mark.parametrize("name", ["fig5", "fig6", "fig7", "fig8", "fig9"])
def test_monte_carlo_inside_the_bounds(results, name):
    """Every M: lower − 5σ ≤ MC ≤ upper + 5σ, σ = √(b(1−b)/n) at the bound b, plus 1/n.

    (Under H₀: p ∈ [lower, upper], p̂ is binomial(n, p)/n, and the bound closest to p̂ gives the
    most lenient admissible σ; 1/n absorbs the lattice when a bound is within 1/n of 0 or 1.)
    For the smart sensor the bounds coincide with Thm 4.1's exact value.
    """
    t = pd.read_csv(results[name] / f"{name}.csv")
    for sensor, g in t.groupby(_who(t)):
        piv = g.pivot(index="M", columns="series", values="value")
        n = g[g.series == "monte_carlo"].set_index("M")["n"]
        lo = piv["lower_bound"] if "lower_bound" in piv else piv["thm41"]
        up = piv["upper_bound"] if "upper_bound" in piv else piv["thm41"]
        p = piv["monte_carlo"]
        assert np.all(p >= lo - 5 * np.sqrt(lo * (1 - lo) / n) - 1 / n), (name, sensor)
        assert np.all(p <= up + 5 * np.sqrt(up * (1 - up) / n) + 1 / n), (name, sensor)
        if "exact" in piv:
            ex = piv["exact"]
            assert np.all((ex >= lo - 1e-9) & (ex <= up + 1e-9))
            assert np.all(np.abs(p - ex) <= 5 * np.sqrt(ex * (1 - ex) / n) + 1 / n)


def test_fig9_has_both_sensors_and_smart_is_better(results):
    t = pd.read_csv(results["fig9"] / "fig9.csv")
    who = t[_who(t)]
    assert set(who) == {"buffered", "smart_sensor"}
    ex = t[(who == "buffered") & (t.series == "exact")].set_index("M").value
    th = t[(who == "smart_sensor") & (t.series == "thm41")].set_index("M").value
    assert np.all(th >= ex - 1e-9)


if __name__ == "__main__":  # regenerate golden files
    import shutil
    import tempfile

    GOLDEN.mkdir(exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for name in CONFIGS:
            out = _run(name, tmp)
            for stem in (name, f"{name}_summary"):
                shutil.copy(out / f"{stem}.csv", GOLDEN / f"{stem}.csv")
            print("wrote", name)
