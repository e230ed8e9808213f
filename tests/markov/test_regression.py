"""End-to-end: the four configs (state_error Monte Carlo + closed forms of each example) at small size (horizon 20, 400 runs) against committed golden CSVs.

Regenerate after an intended change with ``NETKF_UPDATE_GOLDEN=1 pytest tests/markov/test_regression.py``.
Monte Carlo is deterministic for a fixed seed and chunking, so rows that do not involve the LMI
filter must agree to round-off (1e-9 relative). Rows that involve the LMI filter depend on the
SDP solver's iterates (Clarabel, gap tolerance 1e-8): 1e-4 relative, the accuracy the gains are
known to (see test_filters.test_sdp_matches_closed_form_and_bound).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from netkf_cli.app.runner import run_scenario_file

from .conftest import CONFIGS

GOLDEN = Path(__file__).parent / "golden"
SMALL = {"montecarlo": {"horizon": 20, "burn_in": 10, "chunk": 200}}
RUNS = 400


def _is_lmi(df: pd.DataFrame) -> np.ndarray:
    mask = np.zeros(len(df), bool)
    for c in df.columns:
        if not pd.api.types.is_numeric_dtype(df[c]):
            mask |= df[c].astype(str).str.contains("lmi").to_numpy()
    return mask


@pytest.mark.parametrize("name", ["example1", "example2", "example1_exact", "example2_exact"])
def test_regression(name, tmp_path):
    out = run_scenario_file(CONFIGS / f"{name}.yaml", out_dir=tmp_path / name, runs=RUNS, force=True, overrides=SMALL)
    art = f"markov_{name}"
    assert (out / f"{art}.png").stat().st_size > 10_000
    csvs = sorted(out.glob("*.csv"))
    want = ({"", "_mse", "_modes", "_claims"} if name.endswith("_exact") else {"", "_summary", "_trajectories"})
    assert {p.name for p in csvs} == {f"{art}{x}.csv" for x in want}
    if os.environ.get("NETKF_UPDATE_GOLDEN"):
        GOLDEN.mkdir(exist_ok=True)
        for p in csvs:
            shutil.copy(p, GOLDEN / p.name)
    for p in csvs:
        fresh, gold = pd.read_csv(p), pd.read_csv(GOLDEN / p.name)
        assert list(fresh.columns) == list(gold.columns) and len(fresh) == len(gold), p.name
        lmi = _is_lmi(gold)
        for c in gold.columns:
            if not pd.api.types.is_numeric_dtype(gold[c]):
                assert (fresh[c].fillna("").astype(str) == gold[c].fillna("").astype(str)).all(), (p.name, c)
                continue
            a, b = fresh[c].to_numpy(float), gold[c].to_numpy(float)
            np.testing.assert_allclose(a[~lmi], b[~lmi], rtol=1e-9, atol=1e-12, err_msg=f"{p.name}:{c}")
            np.testing.assert_allclose(a[lmi], b[lmi], rtol=1e-4, atol=1e-9, err_msg=f"{p.name}:{c} (lmi rows)")
    if name.endswith("_exact"):
        claims = pd.read_csv(out / f"{art}_claims.csv")
        c = claims[claims["series"].str.startswith("claim_")]
        assert (c["value"] == 1.0).all(), c[c["value"] != 1.0]
    else:  # every filter's reported P is its error covariance at every step (5 s.e.), at this small size too
        sm = pd.read_csv(out / f"{art}_summary.csv")
        frac = sm[sm["series"].isin(["nees_consistent_fraction", "empirical_equals_reported_fraction"])]
        assert (frac["value"] == 1.0).all(), frac[frac["value"] != 1.0]
