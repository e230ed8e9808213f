"""Every configs/fading/*.yaml run small and compared with tests/fading/golden/ (regenerate: python -m tests.fading.test_regression)."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from netkf_cli.runner import run_scenario_file

ROOT = Path(__file__).resolve().parents[2]
GOLDEN = Path(__file__).parent / "golden"
RUNS = {"fig3": 10, "fig4": 2000, "fig5": 10, "fig6": 40, "sec42": 40, "fig7": 100, "thm4": 2000}
# small horizons keep the suite fast; the override is part of what the golden files record
OVERRIDES = {"fig6": {"montecarlo": {"horizon": 60}}, "sec42": {"montecarlo": {"horizon": 60}},
             "fig7": {"montecarlo": {"horizon": 60}}, "thm4": {"analysis": {"k_max": 10}}}


def _run(stem, out):
    return run_scenario_file(ROOT / "configs" / "fading" / f"{stem}.yaml", out_dir=out, runs=RUNS[stem], force=True,
                             overrides=OVERRIDES.get(stem))


@pytest.mark.parametrize("stem", sorted(RUNS))
def test_config_matches_golden(stem, tmp_path):
    res = _run(stem, tmp_path / stem)
    assert (res / f"fading_{stem}.png").exists()
    csvs = sorted(res.glob("*.csv"))
    assert csvs
    for c in csvs:
        new, old = pd.read_csv(c), pd.read_csv(GOLDEN / c.name)
        assert list(new.columns) == list(old.columns), c.name
        assert len(new) == len(old), c.name
        for col in new.columns:
            if new[col].dtype.kind in "fi":
                # identical seed ⇒ deterministic; CSVs are written with 10 significant digits. 1e-6: the goldens
                # come from backend auto (numba when installed); the numpy path agrees to ≤ 1e-7 relative on
                # the means (tests/fading/test_engine.py), so the same goldens hold without numba
                np.testing.assert_allclose(new[col].to_numpy(float), old[col].to_numpy(float), rtol=1e-6, atol=1e-300,
                                           equal_nan=True, err_msg=f"{c.name}:{col}")
            else:
                assert (new[col].astype(str) == old[col].astype(str)).all(), f"{c.name}:{col}"


if __name__ == "__main__":
    import shutil
    import tempfile

    GOLDEN.mkdir(exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for stem in sorted(RUNS):
            res = _run(stem, Path(tmp) / stem)
            for c in res.glob("*.csv"):
                shutil.copy(c, GOLDEN / c.name)
            print("golden", stem)
