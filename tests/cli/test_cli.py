"""Every command through typer's CliRunner, including every class of bad input."""

import json
import textwrap

import pytest
from typer.testing import CliRunner

from netkf_cli.app.cli import app

runner = CliRunner()

GOOD = textwrap.dedent(
    """\
    name: t
    system: {A: 1.4, C: 1, Q: 0.2, R: 0.5}
    channel:
      kind: delay
      delay: {kind: poisson, mean: 5}
      buffer: 10
    analysis:
      kind: theta_vs_buffer
      M: [50, 150]
      D_max: 8
    """
)


def write(tmp_path, text, name="s.yaml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


def test_help_lists_commands():
    r = invoke("--help")
    assert r.exit_code == 0
    for cmd in ("run", "validate", "schema", "mind", "list", "reproduce"):
        assert cmd in r.output


def test_run_writes_csv_png_manifest_and_refuses_overwrite(tmp_path):
    cfg = write(tmp_path, GOOD)
    out = tmp_path / "res"
    r = invoke("run", cfg, "--out", out)
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in out.iterdir()) == ["manifest.json", "t.csv", "t.png"]
    man = json.loads((out / "manifest.json").read_text())
    assert man["meta"]["convention"] == "delay_le_D"
    assert man["scenario"]["channel"]["convention"] == "delay_le_D"
    assert "numpy" in man["versions"]
    assert man["written_by"] == "netkf" and man["source"] == "s.yaml" or not man["source"].startswith("/")
    r = invoke("run", cfg, "--out", out)  # same scenario, same hash: a reproducible rerun replaces it
    assert r.exit_code == 0, r.output
    r = invoke("run", cfg, "--out", out, "--runs", 7)  # another run size: refused without --force
    assert r.exit_code == 1 and "different scenario" in r.output
    r = invoke("run", cfg, "--out", out, "--runs", 7, "--force")
    assert r.exit_code == 0
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".res")]  # no temp folders left


def test_failed_run_leaves_no_folder(tmp_path):
    cfg = write(tmp_path, GOOD.replace("M: [50, 150]", "M: [50, 0.1]"))
    out = tmp_path / "res"
    r = invoke("run", cfg, "--out", out)
    assert r.exit_code == 1
    assert "analysis.M[1]" in r.output and "M̄ = 0.5" in r.output and "s.yaml:9" in r.output
    assert not out.exists() and not list(tmp_path.glob(".res*"))


def test_validate_ok_and_schema(tmp_path):
    cfg = write(tmp_path, GOOD)
    r = invoke("validate", cfg)
    assert r.exit_code == 0 and "✓" in r.output
    r = invoke("schema")
    assert r.exit_code == 0
    schema = json.loads(r.output)
    assert "analysis" in schema["properties"]


def test_list_kinds():
    r = invoke("list")
    assert r.exit_code == 0
    for k in ("delay", "bernoulli", "theta_vs_buffer"):
        assert k in r.output


@pytest.mark.parametrize(
    "old,new,path,line,needle",
    [
        ("  buffer: 10", "  bufer: 10", "channel.bufer", 6, "unknown key"),
        ("A: 1.4,", "A: [[1, 2, 3], [4, 5, 6]],", "system.A", 2, "must be square"),
        ("Q: 0.2,", "Q: -1,", "system.Q", 2, "positive semi-definite"),
        ("R: 0.5", "R: 0", "system.R", 2, "positive definite"),
        ("delay: {kind: poisson, mean: 5}", "delay: {kind: pmf, probs: [1.5]}", "channel.delay.probs[0]", 5, "less than or equal to 1"),
        ("delay: {kind: poisson, mean: 5}", "delay: {kind: poisson, mean: -1}", "channel.delay.mean", 5, "greater than or equal to 0"),
        ("delay: {kind: poisson, mean: 5}", "delay: {kind: uniform, mean: 5}", "channel.delay.kind", 5, "unknown kind"),
        ("  kind: theta_vs_buffer", "  kind: nope", "analysis.kind", 8, "'nope'"),
        ("  D_max: 8", "  D_max: 0", "analysis.D_max", 10, "greater than 0"),
    ],
)
def test_bad_input_names_file_line_and_field(tmp_path, old, new, path, line, needle):
    assert old in GOOD
    cfg = write(tmp_path, GOOD.replace(old, new))
    for cmd in (("validate", cfg), ("run", cfg, "--out", tmp_path / "o")):
        r = invoke(*cmd)
        assert r.exit_code == 1, r.output
        assert f"s.yaml:{line} {path}:" in r.output, r.output
        assert needle in r.output
        assert "Traceback" not in r.output
    assert not (tmp_path / "o").exists()


def test_several_problems_reported_at_once(tmp_path):
    bad = GOOD.replace("  buffer: 10", "  bufer: 10").replace("Q: 0.2,", "Q: -1,")
    r = invoke("validate", write(tmp_path, bad))
    assert r.exit_code == 1
    assert "channel.bufer" in r.output and "system.Q" in r.output


def test_yaml_syntax_error_has_line_and_column(tmp_path):
    r = invoke("validate", write(tmp_path, "name: t\nsystem: {A: 1\n  bad"))
    assert r.exit_code == 1
    assert "YAML syntax error, column" in r.output and "s.yaml:" in r.output


def test_duplicate_key_is_an_error(tmp_path):
    r = invoke("validate", write(tmp_path, GOOD + "name: again\n"))
    assert r.exit_code == 1 and "duplicate key 'name'" in r.output


def test_missing_file_and_usage_error(tmp_path):
    r = invoke("run", tmp_path / "nope.yaml")
    assert r.exit_code == 1 and "file not found" in r.output
    r = invoke("run", "--bogus")
    assert r.exit_code == 2


# ---- netkf mind -------------------------------------------------------------------------

def test_mind_m50_eps003_explains_infeasibility():
    r = invoke("mind", "--M", 50, "--eps", 0.03)
    assert r.exit_code == 0, r.output
    assert "k1(M) = 7" in r.output and "k2(M) = 7" in r.output
    assert "No buffer length can meet the requirement" in r.output and "0.03133" in r.output


def test_mind_m150_necessary_but_no_sufficient():
    r = invoke("mind", "--M", 150, "--eps", 0.001)
    assert r.exit_code == 0
    assert "D_n (necessary) = 7" in r.output and "No buffer length is guaranteed to suffice" in r.output


def test_mind_json_keys_and_min_D():
    r = invoke("mind", "--M", 50, "--eps", 0.05, "--json")
    assert r.exit_code == 0
    j = json.loads(r.output)
    for key in ("k1", "k2", "mbar", "pbar", "theta_floor_1", "theta_floor_2", "D_s", "D_n", "D_star", "feasible", "convention"):
        assert key in j
    assert j["D_s"] == 6 and j["D_n"] == 6 and j["D_star"] is None and j["feasible"] is True
    r = invoke("mind", "--M", 50, "--eps", 0.05, "--json", "--convention", "delay_lt_D")
    assert json.loads(r.output)["D_s"] == 7  # one more under eq. (4)'s convention


def test_mind_verdict_prints_the_confidence_it_guarantees():
    """1 − ε as the verdict prints it: never rounded to 1 (ε = 1e-9 read "≥ 1")."""
    from netkf_cli.app.mind import one_minus

    assert [one_minus(e) for e in (0.03, 0.5, 1e-4, 1e-9, 0.0)] == ["0.97", "0.5", "0.9999", "1 − 1e-09", "1"]
    r = invoke("mind", "--M", 1e9, "--eps", 1e-9)
    assert r.exit_code == 0 and "Pr[P_k ≤ 1e+09] ≥ 1 − 1e-09" in " ".join(r.output.split()), r.output


def test_mind_smart_sensor():
    j = json.loads(invoke("mind", "--M", 150, "--eps", 0.001, "--sensor", "smart", "--json").output)
    assert j["D_star"] == 7 and j["D_s"] is None and j["feasible"]


def test_mind_refuses_M_below_mbar():
    r = invoke("mind", "--M", 0.1)
    assert r.exit_code == 1
    assert "--M" in r.output and "M ≥ M̄ = 0.5" in r.output and "Thm 3.8" in r.output


def test_mind_usage_errors():
    assert invoke("mind", "--M", 50, "--sensor", "clever").exit_code == 2
    r = invoke("mind", "--M", 50, "--eps", 1.5)  # a bad value is bad input (exit 1), like --d inf
    assert r.exit_code == 1 and "--eps: must be a probability in [0, 1]" in r.output
    assert invoke("mind").exit_code == 2


def test_mind_from_config_and_d_max(tmp_path):
    cfg = write(tmp_path, GOOD)
    j = json.loads(invoke("mind", "--M", 50, "--eps", 0.05, "--config", cfg, "--json").output)
    assert j["D_s"] == 6
    j = json.loads(invoke("mind", "--M", 50, "--eps", 0.05, "--d", 5, "--D-max", 5, "--json").output)
    assert j["D_s"] is None and j["feasible"] is False
    assert j["D_s_uncapped"] == 6 and j["reason"] == "above_D_max"
    assert invoke("mind", "--M", 50, "--config", cfg, "--d", 3).exit_code == 2


def test_mind_d_max_below_the_minimum_is_not_infeasibility():
    """--D-max 5 where D = 6 does it: 'above the cap', never 'D → ∞ … 0.03133 > ε = 0.05' (the fuzz)."""
    r = invoke("mind", "--M", 50, "--D-max", 5)
    assert r.exit_code == 0, r.output
    out = " ".join(r.output.split())
    assert "D_s (sufficient) = none up to D_max = 5 (6 without the cap)" in out
    assert "D_n (necessary) = none up to D_max = 5 (6 without the cap)" in out
    verdict = out.split("Verdict:")[1]
    assert "No buffer up to --D-max 5 meets the requirement" in verdict and "Raise --D-max to 6" in verdict
    assert "no finite D" not in out and "D → ∞" not in verdict and "> ε" not in verdict
    j = json.loads(invoke("mind", "--M", 50, "--D-max", 5, "--json").output)
    assert (j["D_s"], j["D_n"], j["D_max"], j["D_s_uncapped"], j["D_n_uncapped"]) == (None, None, 5, 6, 6)
    assert j["feasible"] is False and j["feasible_uncapped"] is True and j["reason"] == "above_D_max"
    assert "D → ∞" not in j["verdict"]
    j = json.loads(invoke("mind", "--M", 50, "--D-max", 6, "--json").output)  # the cap reached: as without it
    assert j["D_s"] == 6 and j["feasible"] is True and j["reason"] is None


def test_mind_d_max_between_the_bounds():
    """D_n ≤ D_max < D_s: D_n is given, D_s is above the cap; θ(k1)'s floor (0.004179) is below ε."""
    r = invoke("mind", "--M", 150, "--eps", 0.005, "--D-max", 6)
    out = " ".join(r.output.split())
    assert "D_s (sufficient) = none up to D_max = 6 (7 without the cap)" in out and "D_n (necessary) = 6" in out
    assert "the sufficient bound needs D_s = 7" in out and "[6, 7]" in out and "D → ∞" not in out.split("Verdict:")[1]
    # θ(k1)'s floor above ε (no finite D_s), D_n = 7 above the cap: both said, each for what it is
    r = invoke("mind", "--M", 150, "--eps", 0.001, "--D-max", 5)
    out = " ".join(r.output.split())
    assert "D_s (sufficient) = none (no finite D)" in out and "D_n (necessary) = none up to D_max = 5 (7 without the cap)" in out
    assert "θ(k1) = 0.004179 > ε = 0.001" in out and "D_n = 7 is necessary, which is above --D-max 5" in out
    j = json.loads(invoke("mind", "--M", 150, "--eps", 0.001, "--D-max", 5, "--json").output)
    assert j["D_s_uncapped"] is None and j["D_n_uncapped"] == 7 and j["reason"] == "theta_floor"


def test_mind_truly_infeasible_says_theta_floor():
    """ε = 0.03 below θ(k2, ∞) = 0.03133: no finite D, with or without a cap."""
    for cap in ((), ("--D-max", 3)):
        j = json.loads(invoke("mind", "--M", 50, "--eps", 0.03, "--json", *cap).output)
        assert j["D_s"] is None and j["D_s_uncapped"] is None and j["D_n_uncapped"] is None
        assert j["feasible"] is False and j["feasible_uncapped"] is False and j["reason"] == "theta_floor"
        assert "0.03133 > ε = 0.03" in j["verdict"]
    r = invoke("mind", "--M", 50, "--eps", 0.03, "--D-max", 3)
    assert "D_s (sufficient) = none (no finite D)" in r.output and "without the cap" not in r.output


def test_mind_smart_sensor_d_max():
    """Smart sensor (Thm 4.1): D* = 7 above --D-max 5 is not 'θ(k2) = 0.0002846 > ε = 0.001'."""
    r = invoke("mind", "--M", 150, "--eps", 0.001, "--sensor", "smart", "--D-max", 5)
    out = " ".join(r.output.split())
    assert "D* (necessary and sufficient) = none up to D_max = 5 (7 without the cap)" in out
    verdict = out.split("Verdict:")[1]
    assert "D* = 7" in verdict and "raise --D-max to 7" in verdict and "D → ∞" not in verdict and "> ε" not in verdict
    j = json.loads(invoke("mind", "--M", 150, "--eps", 0.001, "--sensor", "smart", "--D-max", 5, "--json").output)
    assert j["D_star"] is None and j["D_star_uncapped"] == 7 and j["feasible"] is False and j["feasible_uncapped"] is True
    assert j["reason"] == "above_D_max"
    j = json.loads(invoke("mind", "--M", 50, "--eps", 0.03, "--sensor", "smart", "--D-max", 5, "--json").output)
    assert j["D_star_uncapped"] is None and j["reason"] == "theta_floor" and "0.03133 > ε = 0.03" in j["verdict"]
