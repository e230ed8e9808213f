"""fig3 and updates_vs_buffer figures in the shared style (issue 13): the title names the paper and
the figure, the figure-lint finds nothing (labels, legend entries ↔ series, fonts, canvas), and what
is drawn is what the CSV says (the plotted θ values are the CSV's)."""

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from netkf_cli.app.runner import run_scenario_file

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("name,runs,title", [("fig3", None, "Shi, Xie & Murray 2009 — Fig. 3:"),
                                             ("updates_vs_buffer", 300, "Shi, Xie & Murray 2009 — Sec. 5.1:")])
def test_figure_lint_and_title(tmp_path, monkeypatch, name, runs, title):
    lint = tmp_path / "lint"
    monkeypatch.setenv("NETKF_FIGURE_LINT", str(lint))
    out = run_scenario_file(ROOT / "configs" / f"{name}.yaml", out_dir=tmp_path / name, runs=runs, force=True)
    report = json.loads((lint / f"{name}.json").read_text(encoding="utf-8"))
    assert report["problems"] == [], report["problems"]
    assert report["titles"][0].startswith(title)
    assert (out / f"{name}.png").stat().st_size > 10_000


def test_fig3_draws_the_csv(tmp_path):
    """Every θ series of the CSV is one line of the figure with exactly those points."""
    import matplotlib

    matplotlib.use("Agg")
    from netkf_cli.config.loader import load_scenario

    out = run_scenario_file(ROOT / "configs" / "fig3.yaml", out_dir=tmp_path / "fig3", force=True)
    t = pd.read_csv(out / "fig3.csv")
    sc = load_scenario(ROOT / "configs" / "fig3.yaml")
    fig = sc.analysis.plot({"main": t}, sc)
    lines = [ln for ln in fig.axes[0].get_lines() if not ln.get_label().startswith("_")]
    series = t[t.series.str.startswith("theta_")]
    assert len(lines) == series.groupby(["M", "series"]).ngroups
    drawn = sorted(tuple(np.round(ln.get_ydata(), 12)) for ln in lines)
    want = sorted(tuple(np.round(g.sort_values("D").value.to_numpy(), 12)) for _, g in series.groupby(["M", "series"]))
    assert drawn == want
