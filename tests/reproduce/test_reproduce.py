"""`netkf reproduce` on a small synthetic project: checks, exit codes, --jobs, consistency."""

import shutil
import textwrap

import pytest
from typer.testing import CliRunner

from netkf_cli.app.cli import app

runner = CliRunner()

FIG3 = textwrap.dedent(
    """\
    name: {name}
    system: {{A: 1.4, C: 1, Q: 0.2, R: 0.5}}
    channel: {{kind: delay, delay: {{kind: poisson, mean: 5}}, buffer: 10}}
    analysis: {{kind: theta_vs_buffer, M: [50, 150], D_max: 9}}
    """
)

PUBLISHED = textwrap.dedent(
    """\
    citation: "test"
    printed:
      - {{id: k1_150, artefact: t1, select: {{M: 150, series: k1}}, quantity: "k1(150)", where: "Example 3.10",
          printed: 8, tol_abs: 0}}
      - {{id: theta_8_7, artefact: t1, select: {{M: 150, D: 7, series: theta_k1}}, quantity: "θ(8, 7)",
          where: "Example 3.10", printed: {theta}, tol_abs: 0.00005}}
      - {{id: known, artefact: t2, select: {{M: 50, D: 6, series: theta_k1}}, quantity: "θ(7, 6)", where: "Example 3.10",
          printed: 0.0506, tol_abs: 0.00005, expect: differs, reason: "eq. (4) convention"}}
    claims:
      - {{id: theta_small, artefact: t1, select: {{M: 150, D: 9, series: theta_k2}}, claim: "θ(9, 9) is tiny",
          where: "Sec. 3.4", check: "θ(k2, 9) at M = 150", holds_if: {{max: {claim_max}}}}}
      - {{id: known_claim, artefact: t2, select: {{M: 50, D: 6, series: theta_k1}}, claim: "θ(7, 6) ≥ 0.04",
          where: "Sec. 3.4", check: "θ(7, 6)", holds_if: {{min: 0.04}}, expect: fails, reason: "it is 0.0313"}}
    """
)


@pytest.fixture
def project(tmp_path, monkeypatch):
    (tmp_path / "configs").mkdir()
    (tmp_path / "experiments" / "shi2009").mkdir(parents=True)
    (tmp_path / "configs" / "t1.yaml").write_text(FIG3.format(name="t1"))
    (tmp_path / "configs" / "t2.yaml").write_text(FIG3.format(name="t2"))
    (tmp_path / "experiments" / "shi2009" / "README.md").write_text("# Test paper\n\nnotes\n")
    (tmp_path / "experiments" / "shi2009" / "published.yaml").write_text(PUBLISHED.format(theta=0.0042, claim_max=0.001))
    monkeypatch.chdir(tmp_path)
    return tmp_path


def test_check_passes_and_report_lists_every_config(project):
    r = runner.invoke(app, ["reproduce", "--check", "--quiet"])
    assert r.exit_code == 0, r.output
    report = (project / "results" / "REPORT.md").read_text()
    assert "### t1" in report and "### t2" in report and "differs, as expected" in report
    assert "![t1](t1/t1.png)" in report
    assert "| θ is tiny" not in report and "θ(9, 9) is tiny" in report and "✓ holds" in report
    assert "does not hold, as expected" in report
    assert "(../experiments/shi2009/README.md)" in report  # notes linked, not pasted
    assert "notes\n" not in report


def test_perturbed_published_value_fails_and_is_named(project):
    pub = project / "experiments" / "shi2009" / "published.yaml"
    pub.write_text(PUBLISHED.format(theta=0.0052, claim_max=0.001))
    r = runner.invoke(app, ["reproduce", "--check"])
    assert r.exit_code == 1
    assert "t1: check theta_8_7" in r.output and "0.0052" in r.output
    pub.write_text(PUBLISHED.format(theta=0.0042, claim_max=0.001))
    assert runner.invoke(app, ["reproduce", "--check", "--quiet", "--out", "r2"]).exit_code == 0


def test_jobs_2_equals_serial(project):
    assert runner.invoke(app, ["reproduce", "--quiet", "--out", "serial"]).exit_code == 0
    assert runner.invoke(app, ["reproduce", "--quiet", "--out", "par", "--jobs", "2"]).exit_code == 0
    for name in ("t1", "t2"):
        assert (project / "serial" / name / f"{name}.csv").read_bytes() == (project / "par" / name / f"{name}.csv").read_bytes()


def test_config_without_section_and_section_without_config_are_errors(project):
    (project / "configs" / "extra").mkdir()
    (project / "configs" / "extra" / "x.yaml").write_text(FIG3.format(name="x"))
    r = runner.invoke(app, ["reproduce", "--quiet"])
    assert r.exit_code == 1 and "topic 'extra' has configs but no experiments/extra/README.md" in r.output
    shutil.rmtree(project / "configs" / "extra")
    (project / "experiments" / "orphan").mkdir()
    r = runner.invoke(app, ["reproduce", "--quiet"])
    assert r.exit_code == 1 and "experiments/orphan/ has no configs" in r.output


def test_check_naming_unknown_artefact_is_an_error(project):
    pub = project / "experiments" / "shi2009" / "published.yaml"
    pub.write_text(pub.read_text().replace("artefact: t1", "artefact: nope", 1))
    r = runner.invoke(app, ["reproduce", "--quiet"])
    assert r.exit_code == 1 and "no config of topic 'shi2009' is named 'nope'" in r.output


def test_claim_that_stops_holding_fails_and_is_named(project):
    pub = project / "experiments" / "shi2009" / "published.yaml"
    pub.write_text(PUBLISHED.format(theta=0.0042, claim_max=1e-9))
    r = runner.invoke(app, ["reproduce", "--check"])
    assert r.exit_code == 1
    assert "t1: claim theta_small (θ(9, 9) is tiny)" in r.output


def test_printed_entry_needs_where_and_quantity(project):
    pub = project / "experiments" / "shi2009" / "published.yaml"
    pub.write_text(pub.read_text().replace(' where: "Example 3.10",', "", 1))
    r = runner.invoke(app, ["reproduce", "--quiet"])
    assert r.exit_code == 1 and "printed[0].where" in r.output


def test_quick_golden_comparison_catches_a_moved_number(project):
    assert runner.invoke(app, ["reproduce", "--quiet"]).exit_code == 0  # full size → results/ (golden)
    assert runner.invoke(app, ["reproduce", "--quick", "--check", "--quiet"]).exit_code == 0
    golden = project / "results" / "t1" / "t1.csv"
    text = golden.read_text().replace("0.004179082952", "0.005179082952")
    assert text != golden.read_text()
    golden.write_text(text)
    r = runner.invoke(app, ["reproduce", "--quick", "--check"])
    assert r.exit_code == 1 and "golden: t1: t1.csv" in r.output


def test_quick_refuses_to_overwrite_golden(project):
    r = runner.invoke(app, ["reproduce", "--quick", "--out", "results"])
    assert r.exit_code == 1 and "--out" in r.output


def _git(cwd, *args):
    import subprocess

    subprocess.run(["git", "-c", "user.email=t@example.org", "-c", "user.name=t", *args], cwd=cwd, check=True,
                   capture_output=True)


def test_writing_results_refuses_a_dirty_tree_unless_allowed(project):
    _git(project, "init", "-q")
    _git(project, "add", "-A")
    _git(project, "commit", "-q", "-m", "init")
    assert runner.invoke(app, ["reproduce", "--quiet"]).exit_code == 0  # clean: results/ may be written
    (project / "configs" / "t1.yaml").write_text(FIG3.format(name="t1").replace("D_max: 9", "D_max: 8"))
    r = runner.invoke(app, ["reproduce", "--quiet"])
    assert r.exit_code == 1 and "uncommitted changes" in r.output and "configs/t1.yaml" in r.output
    assert "--allow-dirty" in r.output
    assert runner.invoke(app, ["reproduce", "--quiet", "--allow-dirty"]).exit_code == 0
    # another output folder is not the committed results/: allowed
    assert runner.invoke(app, ["reproduce", "--quiet", "--out", "elsewhere"]).exit_code == 0
    # results/ itself being modified (by a previous run) does not make the tree dirty
    _git(project, "checkout", "-q", "--", "configs/t1.yaml")
    assert runner.invoke(app, ["reproduce", "--quiet"]).exit_code == 0
