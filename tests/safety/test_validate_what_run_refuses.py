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
