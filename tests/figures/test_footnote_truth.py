"""What a figure's legend and footnote say is what it draws, over the whole grid (round-13 referee fixes)."""

import pandas as pd

from netkf_cli.config.loader import load_scenario
from netkf_cli.metrics.common import _span, grid_conventions
from netkf_cli.runtime import plotting
from tests.conftest import ROOT


def test_grid_conventions_name_the_whole_grid_not_one_point():
    t = pd.DataFrame({"estimator": ["kf"] * 3 + ["smoother"] * 3,
                      "conventions": ["bernoulli channel (arrival = 0.35, buffer = 1); filtered"] +
                                     ["bernoulli channel (arrival = 0.5, buffer = 1); filtered"] +
                                     ["bernoulli channel (arrival = 0.78, buffer = 1); filtered"] + ["x; y"] * 3})
    out = grid_conventions(t)
    assert out == {"kf": "filtered; bernoulli channel (arrival = 0.35 … 0.78 along the grid, buffer = 1)",
                   "smoother": "x; y"}
    assert _span("a = 1, b = 2", "a = 1, b = 3") == "a = 1, b = 2 … 3 along the grid"
    assert _span("iid", "jakes") == "iid … jakes (along the grid)"


def _drawn(config, csv):
    sc = load_scenario(ROOT / "configs" / config)
    fig = sc.analysis.plot({"main": pd.read_csv(ROOT / "results" / csv)}, sc)
    legend = [lab for ax in fig.axes for lab in ax.get_legend_handles_labels()[1]]
    notes = " ".join(t.get_text() for t in getattr(fig, "_netkf_footnotes", []))
    plotting._mpl().plt.close(fig)
    return legend, notes


def test_a_closed_form_a_log_axis_cannot_show_is_in_the_footnote_not_the_legend():
    legend, notes = _drawn("smoothing/retransmission.yaml", "smoothing_retransmission/smoothing_retransmission.csv")
    assert not any("g(n)" in lab for lab in legend)  # max |g(n) − 1| = 0: nothing on a log axis
    assert "not drawn (≤ 0 on the log axis)" in notes and "g(n)" in notes
    assert "p = 0 … 1 along the grid" in notes  # the grid runs over p: not "asked with p = 0"
    assert any("P_{k-2" in lab for lab in legend) and not any("k-N" in lab for lab in legend)  # the lag drawn
