"""`netkf validate` reports what `netkf run` would refuse (the fuzz's scenarios that validated and then failed at
run): validate exits 1 naming the field and what was expected, and run exits 1 with the same words and leaves no
output folder."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from netkf_cli.app.cli import app

runner = CliRunner()


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


CASES = {
    "no_system": ("""
name: no_system
channel: {kind: bernoulli, arrival: 0.8}
estimator: {kind: kf}
analysis: {kind: mean_vs_time}
montecarlo: {runs: 20, horizon: 10}
""", ["system: this analysis needs a `system:` block (A, C, Q, R)"]),
    "updates_auto_pair_packets": ("""
name: updates_auto_pair_packets
system: {A: [[1.1, 0.2], [0, 0.9]], C: [[1, 0]], Q: [[1, 0], [0, 1]], R: 1}
channel: {kind: delay, delay: {kind: poisson, mean: 2}, buffer: 3}
estimator: {kind: buffered}
analysis: {kind: updates}
montecarlo: {runs: 200, horizon: 25, burn_in: 5, seed: 1}
""", ["estimator.packet: update counts are defined for measurement packets (span 1) only",
      "auto chose pair packets", "set packet: measurement"]),
    "updates_pair_packets_in_a_list": ("""
name: updates_pair_packets_in_a_list
system: {A: [[1.1, 0.2], [0, 0.9]], C: [[1, 0]], Q: [[1, 0], [0, 1]], R: 1}
channel: {kind: delay, delay: {kind: poisson, mean: 2}, buffer: 3}
estimators: [{kind: buffered, packet: measurement}, {kind: buffered, packet: pair}]
analysis: {kind: updates}
montecarlo: {runs: 200, horizon: 25, burn_in: 5, seed: 1}
""", ["estimators[1].packet: update counts are defined for measurement packets (span 1) only (got packet: pair)"]),
    "trace_once_too_short": ("""
name: trace_once_too_short
system: {A: 1.2, C: 1, Q: 1, R: 1}
channel: {kind: trace, file: short.csv, mode: once}
estimator: {kind: kf}
analysis: {kind: mean_vs_time}
montecarlo: {runs: 5, horizon: 20}
""", ["channel.file: mode once needs 20 rows (offset + horizon), the recording has 3"]),
    "trace_once_strides_past_the_end": ("""
name: trace_once_strides_past_the_end
system: {A: 1.2, C: 1, Q: 1, R: 1}
channel: {kind: trace, file: short.csv, mode: once, stride: 1}
estimator: {kind: kf}
analysis: {kind: mean_vs_time}
montecarlo: {runs: 5, horizon: 2}
""", ["channel.file: mode once needs 6 rows (offset + horizon + stride·(runs − 1)), the recording has 3"]),
    "tail_window_beyond_the_step": ("""
name: tail_window_beyond_the_step
system: {A: 1.2, C: 1, Q: 1, R: 1}
channel: {kind: bernoulli, arrival: 0.8}
estimator: {kind: kf}
analysis: {kind: tail, M: [1, 10], windows: [1000]}
montecarlo: {runs: 50, horizon: 30}
""", ["analysis.windows: every window must be < the reported step k = 30, got [1000]"]),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_validate_reports_what_run_would_refuse(tmp_path, case):
    text, needles = CASES[case]
    f = tmp_path / f"{case}.yaml"
    f.write_text(text.lstrip(), encoding="utf-8")
    (tmp_path / "short.csv").write_text("a\n1\n0\n1\n", encoding="utf-8")
    r = invoke("validate", f)
    out = " ".join(r.output.split())
    assert r.exit_code == 1 and all(n in out for n in needles) and out.count("•") == 1, out
    r = invoke("run", f, "--out", tmp_path / "o", "-q")
    out = " ".join(r.output.split())
    assert r.exit_code == 1 and all(n in out for n in needles), out
    assert not (tmp_path / "o").exists()


def test_what_run_accepts_still_validates(tmp_path):
    """The checks above refuse only what run refuses: a recording long enough, or cycled; a window before the step;
    windows without importance sampling (unused); measurement packets counted."""
    (tmp_path / "short.csv").write_text("a\n1\n0\n1\n", encoding="utf-8")
    for case, overrides in [("trace_once_too_short", ["channel.mode=cycle"]),
                            ("trace_once_too_short", ["montecarlo.horizon=3"]),
                            ("trace_once_strides_past_the_end", ["montecarlo.runs=2"]),
                            ("tail_window_beyond_the_step", ["analysis.windows=[29]"]),
                            ("tail_window_beyond_the_step", ["analysis.importance=false"]),
                            ("updates_auto_pair_packets", ["estimator.packet=measurement"])]:
        f = tmp_path / f"{case}.yaml"
        f.write_text(CASES[case][0].lstrip(), encoding="utf-8")
        r = invoke("validate", f, *overrides)
        assert r.exit_code == 0, (case, overrides, r.output)
