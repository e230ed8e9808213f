"""The worked examples of experiments/engine run through the real CLI (small Monte Carlo) and say
what their README says."""

from pathlib import Path

import pandas as pd
import pytest
from typer.testing import CliRunner

from netkf_cli.app.cli import app

EXAMPLES = Path(__file__).resolve().parents[2] / "experiments" / "engine"


@pytest.mark.parametrize("name", ["gilbert_compare", "smoother_lags", "trace_replay", "distribution_below_mbar"])
def test_example_runs(tmp_path, name):
    # trace_replay is one run by design (the recording is the randomness, one run per chunk): 400 of them were 400
    # chunks of the same replay, 20 s of the suite
    runs = [] if name == "trace_replay" else ["--runs", "400"]
    res = CliRunner().invoke(app, ["run", str(EXAMPLES / f"{name}.yaml"), *runs, "--out", str(tmp_path / name)])
    assert res.exit_code == 0, res.output
    t = pd.read_csv(tmp_path / name / f"{name}.csv")
    if name == "gilbert_compare":  # on pure loss the buffered MKF is the KF, exactly (paired difference ≈ 0)
        d = t[(t.estimator == "buffered") & t.statistic.str.startswith("diff_")].value.iloc[0]
        assert abs(d) < 1e-12
        assert set(t.quantity) == {"filtered"}
    if name == "smoother_lags":  # lag 0 is the filter; every extra lag lowers E[tr P_{k−N|k}] on the same traces
        assert set(t.quantity) == {"smoothed"}
        m = t[t.statistic == "mean_trace"].set_index("estimator").value
        d = t[t.statistic.str.startswith("diff_")].set_index("estimator")
        assert m.iloc[2] < m.iloc[1] < m.iloc[0]
        # paired differences against lag 0: negative by far more than their paired standard errors
        assert (d.value + 5 * d.stderr < 0).all()
    if name == "distribution_below_mbar":
        assert t[t.series == "lower_bound"].M.min() >= 0.5 > t[t.series == "monte_carlo"].M.min()
