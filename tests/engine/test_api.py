"""The Python API as the README shows it: load from a dict / YAML, run, get DataFrames and the figure."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from netkf_cli import load, run
from netkf_cli.core.errors import ConfigError

README = Path(__file__).resolve().parents[2] / "README.md"


def test_readme_python_example_runs():
    """The ```python block under 'Python API' in the README, executed as written."""
    text = README.read_text(encoding="utf-8")
    m = re.search(r"## Python API.*?```python\n(.*?)```", text, re.S)
    assert m, "README has no Python API example"
    ns: dict = {}
    exec(compile(m.group(1), "README.md", "exec"), ns)  # noqa: S102 - our own documentation
    assert isinstance(ns["res"].table, pd.DataFrame) and len(ns["res"].table) > 0
    assert ns["res"].figure is not None


def test_api_figures_are_not_kept_by_pyplot(tmp_path):
    """run() returns its figure to the caller and leaves pyplot's list of open figures as it was (a loop of API
    runs in a notebook kept every figure and warned at the 21st); the figure still saves."""
    import matplotlib.pyplot as plt
    sc = load({"name": "f", "system": {"A": 1.2, "C": 1, "Q": 1, "R": 1},
               "channel": {"kind": "bernoulli", "arrival": 0.7}, "estimator": {"kind": "kf"},
               "analysis": {"kind": "mean_vs_time", "every": 5}, "montecarlo": {"runs": 20, "horizon": 10}})
    before = plt.get_fignums()
    figs = [run(sc).figure for _ in range(3)]
    assert plt.get_fignums() == before
    figs[0].savefig(tmp_path / "f.png")
    assert (tmp_path / "f.png").stat().st_size > 1000


def test_recorded_arrivals_replayed_from_an_array():
    sc = load({"name": "rec", "system": {"A": 2.0, "C": 1, "Q": 1, "R": 1, "P0": 1},
               "channel": {"kind": "bernoulli", "arrival": 0.5}, "estimator": {"kind": "kf"},
               "analysis": {"kind": "mean_vs_time", "every": 1, "log_y": False},
               "montecarlo": {"runs": 1, "horizon": 3, "chunk": 1}})
    res = run(sc, arrivals=np.array([1, 0, 1]))
    # hand computation in tests/engine/test_reference.py: 5/6, 13/3, 55/58
    np.testing.assert_allclose(res.table.value.to_numpy(), [5 / 6, 13 / 3, 55 / 58], rtol=1e-13)


def test_bad_dict_gives_dotted_path():
    with pytest.raises(ConfigError, match=r"channel\.arrival"):
        load({"name": "x", "system": {"A": 1, "C": 1, "Q": 1, "R": 1}, "channel": {"kind": "bernoulli", "arrival": 2},
              "estimator": {"kind": "kf"}, "analysis": {"kind": "mean_vs_time"}})
