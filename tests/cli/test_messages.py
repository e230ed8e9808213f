"""Issue 23.4, 23.6, 23.7: refusals that name the field and the file (traces, huge matrices in
`validate` and `critical`, sweep plot filters), what is accepted that was refused (a Gilbert–Elliott
loss sweep from 0), the README's main job leaving a result folder untouched, CITATION.cff."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from netkf_cli.app.cli import app

ROOT = Path(__file__).resolve().parents[2]
runner = CliRunner()

TRACE = textwrap.dedent(
    """\
    name: tr
    system: {A: 1.2, C: 1, Q: 1, R: 1}
    channel: {kind: trace, file: rec.csv, values: delay, buffer: 2}
    estimator: {kind: buffered}
    analysis: {kind: mean_vs_time, every: 1}
    montecarlo: {runs: 1, horizon: 4}
    """
)


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.mark.parametrize("cell,needle", [
    ("-5", "a delay must be ≥ 0"),
    ("-0.5", "whole number of steps"),
    ("2.5", "whole number of steps"),
    ("1e300", "beyond the largest supported delay"),
    ("-inf", "finite"),
    ("soon", "expected a delay"),
])
def test_bad_delay_trace_is_refused_naming_file_line_and_column(tmp_path, cell, needle):
    (tmp_path / "rec.csv").write_text(f"sensor\n0\n1\n{cell}\n2\n")
    cfg = tmp_path / "s.yaml"
    cfg.write_text(TRACE)
    for args in (("validate", cfg), ("run", cfg, "--out", tmp_path / "o")):
        r = invoke(*args)
        assert r.exit_code == 1, r.output
        assert "s.yaml:3 channel.file:" in r.output and "rec.csv line 4 column 1" in r.output, r.output
        assert needle in r.output and "internal error" not in r.output and "Traceback" not in r.output
    assert not (tmp_path / "o").exists()


def test_good_delay_trace_with_lost_markers_runs(tmp_path):
    """An empty cell is a lost packet, and in a one-column file an empty cell is a blank line between rows: 4 rows
    here (0, lost, -1, lost). The reader dropped that line, so the recording had 3 rows (every later step shifted
    by one) and `netkf run` refused horizon 4 after `netkf validate` said ✓. Blank lines around the data are
    formatting; one more step than the recording holds is refused at validate."""
    from netkf_cli.channels.trace_file import LOST, read_recording

    (tmp_path / "rec.csv").write_text("\nsensor\n0\n\n-1\nlost\n\n\n")
    assert read_recording(tmp_path / "rec.csv", "delay").tolist() == [[0, LOST, LOST, LOST]]
    cfg = tmp_path / "s.yaml"
    cfg.write_text(TRACE)
    assert invoke("validate", cfg).exit_code == 0
    r = invoke("run", cfg, "--out", tmp_path / "o", "-q")
    assert r.exit_code == 0, r.output
    cfg.write_text(TRACE.replace("horizon: 4", "horizon: 5"))
    r = invoke("validate", cfg)
    assert r.exit_code == 1 and "mode once needs 5 rows (offset + horizon), the recording has 4" in r.output, r.output
    (tmp_path / "rec.csv").write_text("a\n1\n\n0\n1\n")  # arrivals: a blank line is no value
    cfg.write_text(TRACE.replace("values: delay, buffer: 2", "values: arrival").replace("buffered", "kf"))
    r = invoke("validate", cfg)
    assert r.exit_code == 1 and "rec.csv line 3 column 1: expected 0 or 1, got ''" in r.output, r.output


def test_bad_arrival_trace_names_file_and_line(tmp_path):
    (tmp_path / "rec.csv").write_text("a\n1\n0\n2\n1\n")
    cfg = tmp_path / "s.yaml"
    cfg.write_text(TRACE.replace("values: delay, buffer: 2", "values: arrival").replace("buffered", "kf"))
    r = invoke("validate", cfg)
    assert r.exit_code == 1 and "rec.csv line 4 column 1: expected 0 or 1" in r.output, r.output


HUGE = textwrap.dedent(
    """\
    name: big
    system: {A: [[A11, 0], [0, 0.5]], C: [[1, 1]], Q: [[1, 0], [0, 1]], R: 1}
    channel: {kind: bernoulli, arrival: 0.8}
    estimator: {kind: kf}
    analysis: {kind: mean_vs_time}
    """
)


@pytest.mark.parametrize("a11", ["1.7e308", "1e200", "-1e60"])
def test_huge_system_matrix_is_named_in_validate_and_critical(tmp_path, a11):
    cfg = tmp_path / "s.yaml"
    cfg.write_text(HUGE.replace("A11", a11))
    for args in (("validate", cfg), ("critical", "--config", cfg), ("run", cfg, "--out", tmp_path / "o")):
        r = invoke(*args)
        assert r.exit_code == 1, (args, r.output)
        assert "s.yaml:2 system.A:" in r.output and "magnitude" in r.output, r.output
        assert "internal error" not in r.output and "OverflowError" not in r.output and "detectable" not in r.output


def test_gilbert_elliott_loss_sweep_starts_at_zero(tmp_path):
    cfg = tmp_path / "s.yaml"
    cfg.write_text(textwrap.dedent(
        """\
        name: ge
        system: {A: 1.2, C: 1, Q: 1, R: 1}
        channel: {kind: gilbert_elliott, loss_rate: 0.2, mean_burst: 3}
        estimator: {kind: kf}
        analysis: {kind: mean_vs_time, every: 10}
        montecarlo: {runs: 50, horizon: 20, chunk: 50}
        sweep: {channel.loss_rate: [0, 0.1, 0.3]}
        """))
    r = invoke("run", cfg, "--out", tmp_path / "o", "-j", 1, "-q")
    assert r.exit_code == 0, r.output
    assert invoke("validate", cfg, "channel.loss_rate=0").exit_code == 0
    r = invoke("validate", cfg, "channel.loss_rate=-0.1")
    assert r.exit_code == 1 and "channel.loss_rate" in r.output


SWEEP = textwrap.dedent(
    """\
    name: sw
    system: {A: 1.4, C: 1, Q: 0.2, R: 0.5}
    channel: {kind: delay, delay: {kind: poisson, mean: 5}, buffer: 10}
    analysis: {kind: theta_vs_buffer, M: [50], D_max: 4}
    sweep:
      channel.delay.mean: [3, 5]
      plot: PLOT
    """
)


@pytest.mark.parametrize("plot,cmd,path,needle", [
    ("{where: {MM: 50}}", "run", "sweep.plot.where.MM", "is not a column"),
    ("{series: nope}", "run", "sweep.plot.series", "is not a series"),
    ("{x: channel.buffer}", "validate", "sweep.plot", "x must be one of the swept fields"),
])
def test_sweep_plot_names_what_the_table_has(tmp_path, plot, cmd, path, needle):
    cfg = tmp_path / "s.yaml"
    cfg.write_text(SWEEP.replace("PLOT", plot))
    args = ("validate", cfg) if cmd == "validate" else ("run", cfg, "--out", tmp_path / "o", "-j", 1)
    r = invoke(*args)
    assert r.exit_code == 1, r.output
    assert f"{path}" in r.output and needle in r.output and "s.yaml:" in r.output, r.output
    assert not (tmp_path / "o").exists()


def test_sweep_plot_where_on_an_existing_column_is_accepted(tmp_path):
    cfg = tmp_path / "s.yaml"
    cfg.write_text(SWEEP.replace("PLOT", "{where: {M: 50}, series: theta_k1}"))
    assert invoke("run", cfg, "--out", tmp_path / "o", "-j", 1, "-q").exit_code == 0


# ---- the README's main job leaves a result folder as it was ------------------------------------

def test_rerun_of_the_same_scenario_leaves_the_folder_untouched(tmp_path):
    out = tmp_path / "fig3"
    r = invoke("run", ROOT / "configs" / "fig3.yaml", "--out", out)
    assert r.exit_code == 0 and "wrote" in r.output, r.output
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    man = json.loads(before["manifest.json"])
    # every time printed is the manifest's
    assert f"in {man['command_time_s']:.2f} s (compute {man['wall_time_s']:.2f} s)" in r.output
    r = invoke("run", ROOT / "configs" / "fig3.yaml", "--out", out)
    assert r.exit_code == 0 and "already holds this exact result" in r.output and "left untouched" in r.output
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # manifest included: a clean checkout stays clean
    import re

    assert not re.search(r"\d+\.\d+ s\b", r.output)  # no time printed that the manifest does not hold


def test_a_changed_result_is_rewritten(tmp_path):
    out = tmp_path / "fig3"
    assert invoke("run", ROOT / "configs" / "fig3.yaml", "--out", out).exit_code == 0
    (out / "fig3.csv").write_bytes((out / "fig3.csv").read_bytes() + b"\n")  # no longer what this scenario gives
    r = invoke("run", ROOT / "configs" / "fig3.yaml", "--out", out)
    assert r.exit_code == 0 and "wrote" in r.output
    assert not (out / "fig3.csv").read_bytes().endswith(b"\n\n")


# ---- CITATION.cff --------------------------------------------------------------------------------

def test_citation_file_lists_the_five_papers():
    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text(encoding="utf-8"))
    assert cff["cff-version"] == "1.2.0" and cff["title"] and cff["authors"] and cff["message"]
    titles = [r["title"].lower() for r in cff["references"]]
    assert len(titles) == 5
    papers = (ROOT.parent / "shared" / "papers" / "README.md")
    for words in ("packet-delaying network", "random sensor delays", "wireless fading channels",
                  "kalman smoothing with random packet loss", "information fusion strategies"):
        assert sum(words in t for t in titles) == 1, words
    for r in cff["references"]:
        assert r["type"] in ("article", "conference-paper") and len(r["authors"]) >= 2
        assert all("family-names" in a and "given-names" in a for a in r["authors"])
    if papers.exists():  # the shared list of the papers netkf reproduces names the same five
        text = papers.read_text(encoding="utf-8").lower()
        assert all(t.split(":")[0][:30] in text for t in titles)


def test_api_messages_print_numbers_not_numpy_reprs():
    """A value from a numpy array is printed as a number ("got 2"), not as numpy 2's repr ("got np.float64(2.0)")."""
    import numpy as np

    import netkf_cli
    from netkf_cli.core.errors import ConfigError

    sc = netkf_cli.load({"name": "m", "system": {"A": 1.2, "C": 1, "Q": 1, "R": 1},
                         "channel": {"kind": "bernoulli", "arrival": 0.8}, "estimator": {"kind": "kf"},
                         "analysis": {"kind": "mean_vs_time"}, "montecarlo": {"runs": 20, "horizon": 5}})
    for kw, needle in [({"arrivals": np.array([1, 2, 1, 1, 1])}, "got 2 at index (1,)"),
                       ({"arrivals": np.array([1.0, np.nan, 1, 1, 1])}, "got nan at index (1,)"),
                       ({"runs": np.float64(2.5)}, "got 2.5")]:
        with pytest.raises(ConfigError) as exc:
            netkf_cli.run(sc, **kw)
        assert needle in str(exc.value) and "np." not in str(exc.value), str(exc.value)
