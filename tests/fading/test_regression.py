"""Every configs/fading/*.yaml run small and compared with tests/fading/golden/ (regenerate: python -m tests.fading.test_regression)."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from netkf_cli.app.runner import run_scenario_file

ROOT = Path(__file__).resolve().parents[2]
GOLDEN = Path(__file__).parent / "golden"
RUNS = {"fig3": 10, "fig4": 10, "fig5": 10, "fig6": 40, "sec42": 40, "fig7": 12, "fig7_channel": 100, "thm4": 2000}
# small horizons keep the suite fast; the override is part of what the golden files record. fig6, sec42 and
# thm4 are generic metrics (time_average, mean_vs_time) on the numpy backend here: no compile time.
_NUMPY_PAIR = [{"kind": "receiver", "scenario": s, "backend": "numpy"} for s in (2, 3)]
# fig6 and sec42 report ‖E P_k‖ at one step (analysis.at): the step follows the small horizon
OVERRIDES = {"fig6": {"montecarlo": {"horizon": 60}, "analysis": {"at": 60}, "estimators": _NUMPY_PAIR},
             "sec42": {"montecarlo": {"horizon": 60}, "analysis": {"at": 60}, "estimators": _NUMPY_PAIR},
             "fig7": {"montecarlo": {"horizon": 60}},
             "fig7_channel": {"montecarlo": {"horizon": 60}},
             "thm4": {"montecarlo": {"horizon": 10}, "estimator": {"backend": "numpy"}}}


def _run(stem, out):
    return run_scenario_file(ROOT / "configs" / "fading" / f"{stem}.yaml", out_dir=out, runs=RUNS[stem], force=True,
                             overrides=OVERRIDES.get(stem))


MC_SE_FRACTION = 0.05
MC_RTOL = 1e-2
# Fig. 7's sequential Monte Carlo (and only it, so far) is not bit-reproducible across platforms: its weights
# come from the non-central χ² cdf deep in its tail (scipy.special.chndtr at p ~ 1e-30 … 1e-300), whose last
# digits depend on the platform's floating-point code paths, and a weight that moves by one ulp can flip one
# resampling decision (ESS < K/2) of one cloud, which then follows other random numbers. The golden (generated
# elsewhere) and this machine differ in one cloud: fig7 jakes Υ_T = 22, value 0.33578 vs 0.33577 (5e-5 of its
# s.e. 0.254), min_ess_frac by 8.5e-5 relative, a burst probability 5.376e-87 vs 5.419e-87 (0.008 s.e.); the
# parent commit 069080c fails the same way (checked in a separate worktree), so this is no regression of the
# Kalman-core port. Monte Carlo rows (finite stderr > 0) therefore compare their value within 0.05 s.e. and their
# other statistics (stderr, ess, min ess) within 1 % — still far below any real change of an estimator (which
# moves a mean by O(1) s.e.) —, except the s.e. of a row with fewer than 2 effective runs, compared like its value
# (within 0.05 s.e.): there one cloud carries the estimate, value ≈ s.e., and both move together. Seen on a machine
# without AVX-512 (2026-12-06): fig7 Υ_T row 66/67, ESS 1 of 12 clouds, value and s.e. 56545.8 / 56545.6 in the
# golden, 55399.4 / 55399.3 here (−2.0 %, i.e. 0.02 s.e.);
# closed forms and deterministic rows keep 1e-6 relative.


@pytest.mark.parametrize("stem", sorted(RUNS))
def test_config_matches_golden(stem, tmp_path):
    res = _run(stem, tmp_path / stem)
    assert (res / f"fading_{stem}.png").exists()
    # the over grid's derived tables (pairs, trend) are metrics/derived.py's, tested there: not recorded here
    csvs = sorted(c for c in res.glob("*.csv") if not c.stem.endswith(("_pairs", "_trend")))
    assert csvs
    for c in csvs:
        new, old = pd.read_csv(c), pd.read_csv(GOLDEN / c.name)
        assert list(new.columns) == list(old.columns), c.name
        assert len(new) == len(old), c.name
        mc = np.zeros(len(old), bool)
        one_run = np.zeros(len(old), bool)
        if "stderr" in old.columns:
            se = old["stderr"].to_numpy(float)
            mc = np.isfinite(se) & (se > 0)
        if {"ess_frac", "n"} <= set(old.columns):
            # fewer than 2 effective runs (ESS = (Σ tr)² / Σ tr²): the value and its s.e. are one cloud's, and that
            # cloud following other random numbers on another platform moves both by the same amount (see above)
            with np.errstate(invalid="ignore"):
                one_run = (old["ess_frac"].to_numpy(float) * old["n"].to_numpy(float)) < 2
        for col in new.columns:
            if new[col].dtype.kind in "fi" and mc.any() and col in ("value", "stderr", "ess_frac", "min_ess_frac"):
                x, y = new[col].to_numpy(float), old[col].to_numpy(float)
                on_se = (col == "value") | ((col == "stderr") & one_run)
                tol = np.where(mc, np.where(on_se, MC_SE_FRACTION * se, MC_RTOL * np.abs(y)), 1e-6 * np.abs(y))
                same = (x == y) | (np.abs(x - y) <= tol) | (np.isnan(x) & np.isnan(y))
                assert same.all(), f"{c.name}:{col} rows {np.flatnonzero(~same)}: {x[~same]} vs {y[~same]} (tol {tol[~same]})"
            elif new[col].dtype.kind in "fi":
                # identical seed ⇒ deterministic; CSVs are written with 10 significant digits. 1e-6: the goldens
                # come from backend auto (numba when installed); the numpy path agrees to ≤ 1e-7 relative on
                # the means (tests/fading/test_engine.py), so the same goldens hold without numba
                np.testing.assert_allclose(new[col].to_numpy(float), old[col].to_numpy(float),
                                           rtol=1e-6, atol=1e-300,
                                           equal_nan=True, err_msg=f"{c.name}:{col}")
            else:
                # an empty text cell reads back as missing (NaN ≠ NaN in pandas' str dtype): compare as ""
                assert (new[col].fillna("").astype(str) == old[col].fillna("").astype(str)).all(), f"{c.name}:{col}"


if __name__ == "__main__":
    import shutil
    import tempfile

    GOLDEN.mkdir(exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for stem in sorted(RUNS):
            res = _run(stem, Path(tmp) / stem)
            for c in res.glob("*.csv"):
                if not c.stem.endswith(("_pairs", "_trend")):
                    shutil.copy(c, GOLDEN / c.name)
            print("golden", stem)
