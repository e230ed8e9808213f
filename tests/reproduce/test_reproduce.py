"""`netkf reproduce` on a small synthetic project: checks, exit codes, --jobs, consistency."""

import shutil
import textwrap

import pytest
from typer.testing import CliRunner

from netkf_cli.cli import app

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
    checks:
      - {{id: k1_150, artefact: t1, where: {{M: 150, series: k1}}, printed: 8, tol_abs: 0}}
      - {{id: theta_8_7, artefact: t1, where: {{M: 150, D: 7, series: theta_k1}}, printed: {theta}, tol_abs: 0.00005}}
      - {{id: known, artefact: t2, where: {{M: 50, D: 6, series: theta_k1}}, printed: 0.0506, tol_abs: 0.00005,
          expect: differs, reason: "eq. (4) convention"}}
    """
)


@pytest.fixture
def project(tmp_path, monkeypatch):
    (tmp_path / "configs").mkdir()
    (tmp_path / "experiments" / "shi2009").mkdir(parents=True)
    (tmp_path / "configs" / "t1.yaml").write_text(FIG3.format(name="t1"))
    (tmp_path / "configs" / "t2.yaml").write_text(FIG3.format(name="t2"))
    (tmp_path / "experiments" / "shi2009" / "README.md").write_text("# Test paper\n\nnotes\n")
    (tmp_path / "experiments" / "shi2009" / "published.yaml").write_text(PUBLISHED.format(theta=0.0042))
    monkeypatch.chdir(tmp_path)
    return tmp_path


def test_check_passes_and_report_lists_every_config(project):
    r = runner.invoke(app, ["reproduce", "--check", "--quiet"])
    assert r.exit_code == 0, r.output
    report = (project / "results" / "REPORT.md").read_text()
    assert "### t1" in report and "### t2" in report and "differs, as expected" in report
    assert "![t1](t1/t1.png)" in report


def test_perturbed_published_value_fails_and_is_named(project):
    pub = project / "experiments" / "shi2009" / "published.yaml"
    pub.write_text(PUBLISHED.format(theta=0.0052))
    r = runner.invoke(app, ["reproduce", "--check"])
    assert r.exit_code == 1
    assert "t1: check theta_8_7" in r.output and "0.0052" in r.output
    pub.write_text(PUBLISHED.format(theta=0.0042))
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
