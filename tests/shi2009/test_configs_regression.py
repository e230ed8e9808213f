"""configs/fig5..fig9 and updates_vs_buffer end to end (small run counts) + golden CSV regression.

Regenerate the golden files after an intended change with
    python -m tests.shi2009.test_configs_regression
"""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from netkf_cli.runner import run_scenario_file

ROOT = Path(__file__).resolve().parents[2]
GOLDEN = Path(__file__).resolve().parent / "golden"
CONFIGS = ["fig5", "fig6", "fig7", "fig8", "fig9", "updates_vs_buffer"]
RUNS = {"updates_vs_buffer": 1000}
DEFAULT_RUNS = 4000


def _run(name, tmp):
    out = run_scenario_file(ROOT / "configs" / f"{name}.yaml", out_dir=Path(tmp) / name,
                            runs=RUNS.get(name, DEFAULT_RUNS), force=True)
    return out


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("shi2009")
    return {name: _run(name, tmp) for name in CONFIGS}


def _compare(got: pd.DataFrame, want: pd.DataFrame, what: str):
    assert list(got.columns) == list(want.columns), what
    assert len(got) == len(want), what
    for col in want.columns:
        g, w = got[col], want[col]
        if pd.api.types.is_numeric_dtype(w):
            # closed forms and the certified exact value: tight; Monte Carlo: the seed fixes the stream,
            # so it reproduces to rounding as well (rtol 1e-9 only absorbs BLAS/libm differences)
            assert np.allclose(g.to_numpy(float), w.to_numpy(float), rtol=1e-9, atol=1e-12, equal_nan=True), (what, col)
        else:
            assert g.astype(str).tolist() == w.astype(str).tolist(), (what, col)


@pytest.mark.parametrize("name", CONFIGS)
def test_regression_against_golden(results, name):
    out = results[name]
    for stem in (name, f"{name}_summary"):
        got = pd.read_csv(out / f"{stem}.csv")
        want = pd.read_csv(GOLDEN / f"{stem}.csv")
        _compare(got, want, stem)
    assert (out / f"{name}.png").stat().st_size > 10_000


@pytest.mark.parametrize("name", ["fig5", "fig6", "fig7", "fig8", "fig9"])
def test_monte_carlo_inside_the_bounds(results, name):
    """Every M: lower − 5σ ≤ MC ≤ upper + 5σ, σ = √(b(1−b)/n) at the bound b, plus 1/n.

    (Under H₀: p ∈ [lower, upper], p̂ is binomial(n, p)/n, and the bound closest to p̂ gives the
    most lenient admissible σ; 1/n absorbs the lattice when a bound is within 1/n of 0 or 1.)
    For the smart sensor the bounds coincide with Thm 4.1's exact value.
    """
    t = pd.read_csv(results[name] / f"{name}.csv")
    for sensor, g in t.groupby("sensor"):
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
    assert set(t.sensor) == {"buffered", "smart_sensor"}
    ex = t[(t.sensor == "buffered") & (t.series == "exact")].set_index("M").value
    th = t[(t.sensor == "smart_sensor") & (t.series == "thm41")].set_index("M").value
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
