"""Issue 23.2: the Python API is as strict as the YAML — every argument checked, every refusal a
ConfigError naming the argument or the dotted field; every CLI bad-input case refused by the API too."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from netkf_cli import load, run
from netkf_cli.core.errors import ConfigError
from tests.safety.test_bad_input import CASES, CONFIGS, FILE_CASES, R

SC = {"name": "api", "system": {"A": 1.2, "C": 1, "Q": 1, "R": 1},
      "channel": {"kind": "bernoulli", "arrival": 0.8}, "estimator": {"kind": "kf"},
      "analysis": {"kind": "mean_vs_time", "every": 5}, "montecarlo": {"runs": 50, "horizon": 20, "chunk": 50}}


@pytest.fixture(scope="module")
def sc():
    return load(SC)


def _refused(fn, *needles):
    with pytest.raises(ConfigError) as ei:
        fn()
    text = str(ei.value)
    for n in needles:
        assert n in text, f"{n!r} not in {text!r}"
    return text


# ---- arrivals / delays ------------------------------------------------------------------------

@pytest.mark.parametrize("arrivals,needles", [
    (np.array([1, 2] * 10), ("arrivals", "0 (lost) or 1", "got 2 at", "index (1,)")),
    (np.array([1.0, np.nan] * 10), ("arrivals", "finite", "nan")),
    (np.array([1, 0] * 5), ("arrivals", "shape", "(10,)", "horizon = 20")),
    (np.ones((2, 20)), ("arrivals", "shape (2, 20)", "arrivals.T")),
    (np.ones((20, 2, 1)), ("arrivals", "shape (20, 2, 1)")),
    (np.array([]), ("arrivals", "shape")),
    (np.array(["1", "0"] * 10), ("arrivals", "numbers")),
    ([[1, 0], [1]], ("arrivals",)),
    (np.ones((20, 3)), ("arrivals",)),  # 3 streams for a 1-output system: the estimator's check, naming arrivals
])
def test_bad_arrivals_are_refused_naming_arrivals(sc, arrivals, needles):
    _refused(lambda: run(sc, arrivals=arrivals, runs=1), *needles)


def test_good_arrivals_and_delays_are_replayed(sc):
    res = run(sc, arrivals=np.array([1, 0, 0, 1, 1] * 4), runs=1)
    assert len(res.table) == 4
    two = load({**SC, "system": {"A": [[1.1, 0], [0, 0.9]], "C": [[1, 0], [0, 1]], "Q": [[1, 0], [0, 1]],
                                 "R": [[1, 0], [0, 1]]}})
    res = run(two, arrivals=np.ones((20, 2)), runs=1)  # (horizon, streams)
    assert len(res.table) == 4
    buf = load({**SC, "estimator": {"kind": "buffered"}})
    ok = run(buf, delays=np.array([0, 1, -1, 2] * 5), buffer=3, runs=1)
    assert len(ok.table) == 4
    _refused(lambda: run(buf, delays=np.array([0, -3] * 10), runs=1), "delays", "-1 (lost)", "got -3 at")
    _refused(lambda: run(buf, delays=np.array([0, 0.5] * 10), runs=1), "delays", "0.5")
    _refused(lambda: run(buf, delays=np.array([0, 1e300] * 10), runs=1), "delays")
    _refused(lambda: run(buf, arrivals=np.ones(20), delays=np.zeros(20)), "either")
    _refused(lambda: run(buf, buffer=3), "buffer", "delays")


def test_two_recordings_are_two_scenarios(sc):
    from netkf_cli.app.api import recorded_channel
    from netkf_cli.app.runner import scenario_hash

    a = sc.model_copy(update={"channel": recorded_channel(np.ones(20), 20)})
    b = sc.model_copy(update={"channel": recorded_channel(np.r_[np.ones(19), 0], 20)})
    assert scenario_hash(a, None) != scenario_hash(b, None)  # never resumed or "unchanged" into each other


# ---- runs, jobs, executor, out, the scenario itself ------------------------------------------------

@pytest.mark.parametrize("kw,needles", [
    ({"runs": 0}, ("runs", "≥ 1", "got 0")),
    ({"runs": -5}, ("runs", "≥ 1")),
    ({"runs": 2.5}, ("runs", "2.5")),
    ({"runs": True}, ("runs", "bool")),
    ({"runs": "100"}, ("runs", "str")),
    ({"runs": float("nan")}, ("runs", "nan")),
    ({"runs": 10**15}, ("runs", "montecarlo.max_runs", "yes=True")),
    ({"jobs": 0}, ("jobs", "≥ 1")),
    ({"executor": "gpu"}, ("executor", "'gpu'")),
    ({"out": 5}, ("out", "folder path")),
    ({"force": "yes"}, ("force",)),
    ({"overrides": ["channel.arrival=2"]}, ("command line (channel.arrival=2) channel.arrival",)),
    ({"overrides": 7}, ("overrides",)),
])
def test_bad_run_arguments_are_refused_naming_them(sc, kw, needles):
    _refused(lambda: run(sc, **kw), *needles)


def test_integral_runs_like_the_yaml(sc):
    assert len(run(sc, runs=40.0).table) == 4  # as `runs: 40.0` in a file


@pytest.mark.parametrize("source,needles", [
    (123, ("load() takes a scenario", "a dict, a YAML file path", "got int 123")),
    (None, ("load() takes a scenario", "NoneType")),
    (["name: x"], ("got list",)),
    (b"name: x\n", ("got bytes",)),
    ("name: x", ("without a newline as a file path",)),
    ("nope.yaml", ("nope.yaml", "file not found")),
    ({"name": "x", "system": {"A": 1, "C": 1, "Q": -1, "R": 1}, "analysis": {"kind": "mean_vs_time"}},
     ("system.Q", "positive semi-definite")),  # the system checks the YAML gets
    ({**SC, "system": {"A": 1e308, "C": 1, "Q": 1, "R": 1}}, ("system.A", "magnitude")),
    ({**SC, "montecarlo": {"runs": float("inf")}}, ("montecarlo.runs", "finite")),
    ({**SC, "montecarlo": {"runs": np.int64(0)}}, ("montecarlo.runs", "greater than 0")),
    ({**SC, "name": "."}, ("name", "dots only")),
])
def test_load_refuses_what_it_cannot_take(source, needles):
    _refused(lambda: load(source), *needles)


def test_numpy_values_in_a_dict_are_numbers():
    sc = load({**SC, "system": {"A": np.array([[1.2]]), "C": np.float64(1), "Q": 1, "R": 1},
               "montecarlo": {"runs": np.int64(30), "horizon": 20}})
    assert sc.montecarlo.runs == 30 and sc.system.A == [[1.2]]


def test_run_refuses_what_is_not_a_scenario():
    _refused(lambda: run(42), "run() takes a Scenario", "int 42")


# ---- every CLI bad-input case, through the API ---------------------------------------------------

@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_every_cli_bad_input_case_is_refused_by_the_api(tmp_path, case):
    cid, config, old, new, path, needle, _line, cmd = case
    text = (CONFIGS / config).read_text(encoding="utf-8").replace(old, new, 1)
    cfg = tmp_path / Path(config).name
    cfg.write_text(text, encoding="utf-8")
    for source in (cfg, text):  # a file path and YAML text
        with pytest.raises(ConfigError) as ei:
            sc = load(source)
            if cmd == R:  # found when the analysis starts, as on the command line
                run(sc, runs=40)
        msg = str(ei.value)
        assert (f"{path}:" in msg) if path else True, f"{cid}: {path!r} not in {msg!r}"
        assert needle in msg, f"{cid}: {needle!r} not in {msg!r}"
    if cmd != R:  # the same problem as a dict (what a Python caller builds: NaN and inf included)
        import yaml

        from netkf_cli.config.loader import _LineLoader

        try:
            data = yaml.load(text, Loader=_LineLoader)  # noqa: S506 - netkf's safe loader, without the finite check
        except yaml.YAMLError:
            data = None  # e.g. a duplicate key: no dict can hold it
        if isinstance(data, dict):
            with pytest.raises(ConfigError) as ei:
                load(data)
            assert (f"{path}:" in str(ei.value)) if path else True, f"{cid}: {ei.value}"


@pytest.mark.parametrize("cid,data,needle", FILE_CASES, ids=[c[0] for c in FILE_CASES])
def test_every_bad_file_is_refused_by_the_api(tmp_path, cid, data, needle):
    cfg = tmp_path / "bad.yaml"
    cfg.write_bytes(data)
    _refused(lambda: load(cfg), needle)


def test_replayed_delays_keep_the_scenarios_buffer_and_keep_rule():
    """run(sc, delays=…) replays the recording through the scenario's own receive buffer and convention (it used
    buffer 1 and delay_le_D whatever the scenario said, and the CSV said only 'delay law: trace channel')."""
    base = {"name": "t", "system": {"A": 1.3, "C": 1, "Q": 1, "R": 1, "P0": 1},
            "estimator": {"kind": "buffered", "packet": "measurement"}, "analysis": {"kind": "mean_vs_time", "every": 1},
            "montecarlo": {"runs": 1, "horizon": 8, "seed": 1}}
    dly = np.array([3, 3, 0, -1, 2, 3, 1, 0])

    def with_channel(D, conv):
        return load({**base, "channel": {"kind": "delay", "delay": {"kind": "poisson", "mean": 1}, "buffer": D,
                                         "convention": conv}})

    lt3 = run(with_channel(3, "delay_lt_D"), delays=dly, runs=1).table
    le2 = run(with_channel(2, "delay_le_D"), delays=dly, runs=1).table
    le3 = run(with_channel(3, "delay_le_D"), delays=dly, runs=1).table
    np.testing.assert_array_equal(lt3.value, le2.value)  # d < 3 kept = d ≤ 2 kept
    assert not np.array_equal(le3.value, le2.value)  # the buffer matters on this recording
    np.testing.assert_array_equal(run(with_channel(2, "delay_le_D"), delays=dly, buffer=3, runs=1).table.value,
                                  le3.value)  # buffer= still overrides
    conv = lt3.conventions.iloc[0]
    assert "D = 3" in conv and "delay_lt_D" in conv and "recorded delays (<delays array sha256:" in conv, conv
