"""End-to-end: configs/fusion/*.yaml run small, claims hold, regression against golden CSVs, bad input."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from netkf_cli.errors import ConfigError
from netkf_cli.runner import run_scenario_file

ROOT = Path(__file__).resolve().parents[2]
GOLDEN = Path(__file__).parent / "golden"
CONFIGS = {"fusion_fig1": "fig1.yaml", "fusion_fig2": "fig2.yaml", "fusion_fig3": "fig3.yaml"}
RUNS = 200  # golden size; Monte Carlo is deterministic for a fixed seed/runs/chunk, so goldens compare tightly


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    out = {}
    for name, f in CONFIGS.items():
        out[name] = run_scenario_file(ROOT / "configs" / "fusion" / f, out_dir=tmp_path_factory.mktemp(name) / name,
                                      runs=RUNS, force=True)
    return out


def _read(folder: Path, stem: str) -> pd.DataFrame:
    return pd.read_csv(folder / f"{stem}.csv")


def test_files_written(results):
    for name, folder in results.items():
        files = {p.name for p in folder.iterdir()}
        assert {f"{name}.csv", f"{name}.png", "manifest.json", f"{name}_claims.csv"} <= files


def test_closed_form_claims_hold(results):
    c = _read(results["fusion_fig2"], "fusion_fig2_claims").set_index("claim")
    assert (c.value == 1.0).all(), c


def test_bounds_hold_against_small_monte_carlo(results):
    """Even at 200 runs every bound must hold within 5 standard errors (the recipe computes the margins)."""
    c = _read(results["fusion_fig3"], "fusion_fig3_claims").set_index("claim")
    for claim in ("mf_le_upper_bound", "mf_lower_bound_holds", "mf_remark3_bound_holds", "ibf_lower_bounds_hold",
                  "ibf_lb_le_truncated_exact", "ibf_le_mf", "mf_le_upper_bound_pred", "mf_lower_bound_holds_pred",
                  "ibf_lower_bounds_hold_pred", "psi_with_lambda_as_loss_fails"):
        assert c.loc[claim, "value"] == 1.0, (claim, c.loc[claim].to_dict())
    c1 = _read(results["fusion_fig1"], "fusion_fig1_claims").set_index("claim")
    assert c1.loc["ibf_le_mf_all", "value"] == 1.0 and c1.loc["ibf_le_olpef_all", "value"] == 1.0


def _compare(new: pd.DataFrame, old: pd.DataFrame, label: str) -> None:
    assert list(new.columns) == list(old.columns), label
    assert len(new) == len(old), label
    for col in new.columns:
        if pd.api.types.is_numeric_dtype(old[col]) and pd.api.types.is_numeric_dtype(new[col]):
            # closed forms and seeded Monte Carlo are deterministic: only floating-point noise is allowed
            np.testing.assert_allclose(new[col].to_numpy(float), old[col].to_numpy(float), rtol=1e-9, atol=1e-15,
                                       err_msg=f"{label}:{col}", equal_nan=True)
        else:
            assert new[col].astype(str).tolist() == old[col].astype(str).tolist(), f"{label}:{col}"


def test_regression_against_golden(results):
    update = os.environ.get("NETKF_UPDATE_GOLDEN") == "1"
    for name, folder in results.items():
        for p in sorted(folder.glob("*.csv")):
            g = GOLDEN / p.name
            if update:
                GOLDEN.mkdir(exist_ok=True)
                shutil.copy(p, g)
                continue
            assert g.exists(), f"missing golden {g.name}; regenerate with NETKF_UPDATE_GOLDEN=1"
            _compare(pd.read_csv(p), pd.read_csv(g), p.name)


# ---------------------------------------------------------------------------------------- bad input


def _write(tmp_path, text: str) -> Path:
    p = tmp_path / "s.yaml"
    p.write_text(text)
    return p


BASE3 = """
name: t
system: {{A: {A}, C: {C}, Q: {Q}, R: 1.0e-2, sensors: 3}}
channel: {{kind: multi, sensors: 3, loss: {loss}}}
estimator: {{kind: fusion}}
analysis: {{kind: fusion_vs_loss, loss: {grid}}}
montecarlo: {{runs: 20, horizon: 30, burn_in: 10, chunk: 10}}
"""


def _run(tmp_path, text):
    return run_scenario_file(_write(tmp_path, text), out_dir=tmp_path / "out", force=True)


@pytest.mark.parametrize(
    "fields, path, msg",
    [
        (dict(A=0.9, C=1, Q=1e-4, loss="[0.1, 0.2]", grid="[0.1]"), "channel", "one entry per sensor"),
        (dict(A=0.9, C=1, Q=1e-4, loss=0.1, grid="[0.1, 1.0]"), "analysis.loss[1]", "must be < 1"),
        (dict(A=1.1, C=1, Q=1e-4, loss=0.1, grid="[0.1]"), "system.A", "stable A"),
    ],
)
def test_bad_input_is_a_config_error_with_path(tmp_path, fields, path, msg):
    with pytest.raises((ConfigError, ValueError)) as ei:
        _run(tmp_path, BASE3.format(**fields))
    text = str(ei.value)
    assert msg in text and path.split("[")[0] in text


def test_wrong_channel_kind(tmp_path):
    text = BASE3.format(A=0.9, C=1, Q=1e-4, loss=0.1, grid="[0.1]").replace(
        "channel: {kind: multi, sensors: 3, loss: 0.1}", "channel: {kind: bernoulli, arrival: 0.9}")
    with pytest.raises(ConfigError, match="channel.kind"):
        _run(tmp_path, text)


def test_fig2_ell_above_sensors(tmp_path):
    text = "name: t\nsystem: {A: 0.9, C: 1, Q: 1, R: 10}\nanalysis: {kind: fusion_bounding_functions, sensors: 2, ell: [0, 3]}\n"
    with pytest.raises(ConfigError, match=r"analysis.ell\[1\]"):
        _run(tmp_path, text)


def test_vector_state_runs_its_monte_carlo_and_omits_scalar_only_bounds(tmp_path):
    # issue 12: a vector state used to refuse even its Monte Carlo. Now MF/IBF run for any n; the
    # bounds built on L_f^LB (Prop. 1, Prop. 2 with k >= 2; Lemma 2 is scalar) are omitted and the
    # manifest says why; Psi (any n) and Prop. 2 with k = 1 (any n) are still reported and must hold.
    import json

    text = BASE3.format(A="[[0.9, 0.1], [0, 0.5]]", C="[[1, 0.5]]", Q="[[1.0e-2, 0], [0, 1.0e-2]]", loss=0.1,
                        grid="[0.0, 0.3, 0.6]").replace("runs: 20", "runs: 200")
    out = _run(tmp_path, text)
    t = pd.read_csv(out / "t.csv")
    assert set(t.series) == {"mf_mc", "ibf_mc", "mf_ub_psi", "ibf_lb_k1"}
    assert "bounds_omitted" in json.dumps(json.loads((out / "manifest.json").read_text()))
    c = pd.read_csv(out / "t_claims.csv").set_index("claim")
    for claim in ("mf_le_upper_bound", "ibf_lower_bounds_hold", "ibf_le_mf"):
        assert c.loc[claim, "value"] == 1.0, claim


def test_channel_streams_must_be_the_systems_sensors(tmp_path):
    """A `multi` channel with 3 streams on a system of one sensor: refused, naming the fix."""
    text = BASE3.format(A=0.9, C=1, Q=1e-4, loss=0.1, grid="[0.1]").replace(", sensors: 3}", "}", 1)
    assert "sensors: 3}" not in text.split("channel")[0]
    with pytest.raises(ConfigError, match="system.sensors: 3"):
        _run(tmp_path, text)
