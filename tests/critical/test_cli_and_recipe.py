"""`netkf critical` (text, --json, bad input) and the `kind: critical` artefact (small Monte Carlo)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from netkf_cli.app.cli import app
from netkf_cli.config.loader import load_scenario
from netkf_cli.recipes.base import RunContext

runner = CliRunner()


def test_default_system_is_example_310_and_exact(root):
    res = runner.invoke(app, ["critical", "--json"])
    assert res.exit_code == 0, res.output
    js = json.loads(res.stdout)
    assert js["proven"] is True and js["condition"] == "scalar"
    assert js["lambda_c"] == pytest.approx(1 - 1 / 1.4**2)
    assert js["lambda_max"]["lower"] <= js["lambda_c"] <= js["lambda_max"]["upper"] + 1e-12


def test_fig9_vehicle_answers_with_both_bounds_and_the_envelope(root, monkeypatch):
    monkeypatch.chdir(root)
    res = runner.invoke(app, ["critical", "--config", "configs/fig9.yaml", "--json"])
    assert res.exit_code == 0, res.output
    js = json.loads(res.stdout)
    assert js["n"] == 4 and js["lambda_min"] == 0.0
    assert 0.0 < js["lambda_max"]["upper"] < 0.01  # strictly above λ_min = λ_c = 0
    assert js["lambda_c"] == 0.0 and js["condition"] == "marginal"
    ch = js["channel"]
    assert ch["kind"] == "delay" and ch["D_max"] == 5 and ch["bounded"] is True
    env = ch["envelope"]
    assert 0 < env["trace_S_bar"] < env["trace_V_bar"] < np.inf
    text = runner.invoke(app, ["critical", "--config", "configs/fig9.yaml"]).stdout
    assert "λ_max" in text and "tr S̄" in text and "tr V̄" in text and "exactly" in text


def test_two_unstable_is_decided_by_non_degeneracy(root, monkeypatch):
    """Issue 22: the committed two-unstable system is non-degenerate, so λ_c = λ_min = 0.36 (Mo & Sinopoli 2012)."""
    monkeypatch.chdir(root)
    res = runner.invoke(app, ["critical", "--config", "configs/critical/two_unstable.yaml", "--arrival", "0.42", "--json"])
    assert res.exit_code == 0, res.output
    js = json.loads(res.stdout)
    assert js["proven"] is True and js["condition"] == "non_degenerate" and js["lambda_c"] == pytest.approx(0.36)
    assert "Mo & Sinopoli 2012" in js["decided_by"] and js["nondegeneracy"]["non_degenerate"] is True
    assert js["interval"][1] > 0.47  # λ_max stays what the LMI says
    assert js["channel"]["bounded"] is True  # 0.42 > λ_c, although 0.42 < λ_max
    text = runner.invoke(app, ["critical", "--config", "configs/critical/two_unstable.yaml"]).stdout
    assert "decided by: theorem (non_degenerate)" in text and "non-degeneracy (Mo & Sinopoli 2012): yes" in text


def test_undecided_system_gets_a_numerical_certificate(tmp_path):
    """diag(2, −2, 1.5), C = [1 1 1]: degenerate, no theorem; the certificate (not λ_max) judges the channel."""
    cfg = tmp_path / "deg3.yaml"
    cfg.write_text("name: deg3\nsystem: {A: [[2, 0, 0], [0, -2, 0], [0, 0, 1.5]], C: [[1, 1, 1]], Q: [[1, 0, 0], "
                   "[0, 1, 0], [0, 0, 1]], R: 1}\nanalysis: {kind: critical}\n")
    js = json.loads(runner.invoke(app, ["critical", "--config", str(cfg), "--arrival", "0.95", "--json"]).stdout)
    assert js["proven"] is False and js["lambda_c"] is None
    c = js["certificate"]
    assert c is not None and 0.9375 - 1e-3 <= c["upper"] < js["lambda_max"]["upper"] - 0.02
    # lower end: the (2, −2) block alone needs λ > 0.9375 (genie argument), far above λ_min = 0.75
    assert js["lambda_min"] == pytest.approx(0.75) and js["lower_bound"]["value"] == pytest.approx(0.9375)
    assert js["interval"] == [pytest.approx(0.9375), pytest.approx(c["upper"])]
    assert "numerical certificate" in js["decided_by"]
    assert js["channel"]["bounded"] is True and "certificate" in js["channel"]["verdict"]
    js = json.loads(runner.invoke(app, ["critical", "--config", str(cfg), "--arrival", "0.9", "--json"]).stdout)
    assert js["channel"]["bounded"] is False  # 0.9 < 0.9375: proven unbounded through the sub-system
    mid = 0.5 * (0.9375 + c["upper"])
    js = json.loads(runner.invoke(app, ["critical", "--config", str(cfg), "--arrival", f"{mid:.6f}", "--json"]).stdout)
    assert js["channel"]["bounded"] is None and "not decided" in js["channel"]["verdict"]


@pytest.mark.parametrize("args, code, needle", [
    (["critical", "--arrival", "1.5"], 2, "--arrival"),
    (["critical", "--config", "does/not/exist.yaml"], 1, "exist"),
])
def test_bad_input(args, code, needle):
    res = runner.invoke(app, args)
    assert res.exit_code == code
    assert needle in (res.stdout + res.stderr)
    assert "Traceback" not in (res.stdout + res.stderr)


def test_config_without_system_is_a_config_error(tmp_path):
    cfg = tmp_path / "nosys.yaml"
    cfg.write_text("name: nosys\nanalysis: {kind: critical}\n")
    res = runner.invoke(app, ["critical", "--config", str(cfg)])
    assert res.exit_code == 1
    assert "system" in (res.stdout + res.stderr)


def test_recipe_small_run_claims_hold(root):
    sc = load_scenario(root / "configs/critical/scalar_a125.yaml")
    art = sc.analysis.compute(sc, RunContext(runs=1000))
    t, claims, rates = art.table, art.extra_tables["claims"], art.extra_tables["rates"]
    assert set(t.series) == {"S_bar", "V_bar", "monte_carlo"}
    assert (claims.value == 1.0).all(), claims.to_string()
    r = dict(zip(rates.quantity, rates.value))
    assert r["lambda_c"] == pytest.approx(0.36) and r["proven"] == 1.0
    # S̄ ≤ V̄ on the whole grid (both exist above λ_max ≈ λ_c here)
    S = t[t.series == "S_bar"].set_index("lam").value
    V = t[t.series == "V_bar"].set_index("lam").value
    assert (S <= V + 1e-12).all()
    ge = art.extra_tables["ge"]
    assert np.allclose(ge.q_exact, 0.36) and (ge.q_sufficient >= 0.36 - 1e-9).all()
    fig = sc.analysis.plot({"main": t, "rates": rates, "ge": ge}, sc)
    from netkf_cli.runtime import plotting

    plotting._layout(fig)
    assert plotting.lint(fig) == []


def test_monte_carlo_between_bounds_vehicle(root):
    """Monte Carlo means (generic engine) lie between S̄ and V̄ where they are reliable (5 s.e.)."""
    sc = load_scenario(root / "configs/critical/vehicle.yaml")
    an = sc.analysis.model_copy(update={"lambdas": [0.3, 0.6, 0.9], "failure_rates": [0.5]})
    art = an.compute(sc, RunContext(runs=1000))
    t = art.table
    mc = t[(t.series == "monte_carlo") & (t.reliable > 0)]
    assert len(mc) >= 2
    for _, r in mc.iterrows():
        S = t[(t.lam == r.lam) & (t.series == "S_bar")].value.iloc[0]
        V = t[(t.lam == r.lam) & (t.series == "V_bar")].value.iloc[0]
        assert S - 5 * r.stderr <= r.value <= V + 5 * r.stderr


def test_gilbert_elliott_verdict_next_to_bernoulli_at_the_same_loss(tmp_path):
    """a = 2: bursts of mean length 2 (q = 0.5 < 0.75) diverge although i.i.d. loss at the same
    average rate (arrival 0.5/0.6 = 0.833 > 0.75) would be stable: what burstiness costs."""
    cfg = tmp_path / "ge.yaml"
    cfg.write_text("name: ge\nsystem: {A: 2, C: 1, Q: 1, R: 1}\n"
                   "channel: {kind: gilbert_elliott, p_gb: 0.1, p_bg: 0.5}\nanalysis: {kind: critical}\n")
    js = json.loads(runner.invoke(app, ["critical", "--config", str(cfg), "--json"]).stdout)
    ch = js["channel"]
    assert ch["kind"] == "gilbert_elliott" and ch["bounded"] is False and ch["bernoulli_bounded"] is True
    assert ch["q_necessary"] == pytest.approx(0.75)
    cfg.write_text(cfg.read_text().replace("p_bg: 0.5", "p_bg: 0.8"))
    js = json.loads(runner.invoke(app, ["critical", "--config", str(cfg), "--json"]).stdout)
    assert js["channel"]["bounded"] is True


def test_gilbert_elliott_verdict_for_the_degenerate_parity_system(tmp_path):
    """diag(2, −2), C = [1 1] over Gilbert–Elliott: decided by the derived residue-class law, not by q > 0.75."""
    cfg = tmp_path / "pge.yaml"
    cfg.write_text("name: pge\nsystem: {A: [[2, 0], [0, -2]], C: [[1, 1]], Q: [[1, 0], [0, 1]], R: 1}\n"
                   "channel: {kind: gilbert_elliott, p_gb: 0.03, p_bg: 0.85}\nanalysis: {kind: critical}\n")
    ch = json.loads(runner.invoke(app, ["critical", "--config", str(cfg), "--json"]).stdout)["channel"]
    assert ch["bounded"] is True and "q_c(p) = 0.804099" in ch["verdict"]
    cfg.write_text(cfg.read_text().replace("p_gb: 0.03", "p_gb: 0.1"))  # p ≥ 1/16: alternating patterns starve a parity
    ch = json.loads(runner.invoke(app, ["critical", "--config", str(cfg), "--json"]).stdout)["channel"]
    assert ch["bounded"] is False and "no recovery rate suffices" in ch["verdict"] and ch["q"] > ch["q_necessary"]


@pytest.mark.parametrize("config, flat", [("vehicle.yaml", True), ("scalar_a2.yaml", False)])
def test_a_flat_gilbert_elliott_panel_says_what_it_means(root, config, flat):
    """ρ(A) = 1 (the vehicle): every Gilbert–Elliott curve lies on the p-axis, an empty-looking panel; it says so
    (stable for almost every recovery rate), and a panel with visible curves has no such note."""
    import netkf_cli

    res = netkf_cli.run(netkf_cli.load(root / "configs" / "critical" / config), runs=200)
    notes = [t.get_text() for ax in res.figure.axes for t in ax.texts if "every curve lies" in t.get_text()]
    assert bool(notes) == flat, notes


def test_rates_at_or_below_lambda_min_are_named_not_silently_dropped():
    """Asked rates λ ≤ λ_min have no S̄ and no Monte Carlo mean (E[P_k] unbounded): the figure cannot show them and
    its footnote says which (they were left out without a word); a run with none has no such sentence."""
    import netkf_cli

    def notes(lambdas):
        sc = netkf_cli.load({"name": "crit", "system": {"A": 2, "C": 1, "Q": 1, "R": 1},
                             "channel": {"kind": "bernoulli", "arrival": 0.9},
                             "analysis": {"kind": "critical", "lambdas": lambdas},
                             "montecarlo": {"runs": 100, "horizon": 40, "burn_in": 20, "seed": 1}})
        return " ".join(t.get_text() for t in netkf_cli.run(sc).figure._netkf_footnotes)

    assert "Not drawn: λ = 0.5, 0.75 ≤ λ_min = 0.75, where E[P_k] is unbounded" in notes([0.5, 0.75, 0.9])
    assert "Not drawn" not in notes([0.8, 0.9])


def test_tail_probabilities_and_their_intervals_stay_within_one(root):
    """Every run above every M (an undetectable system, C = 0): the importance-sampled estimate is unbiased but
    not bounded by 1 (weights up to K), and p̂ + 1.96 s.e. went to 1.107 here. Both are kept in [0, 1]."""
    sc = load_scenario(root / "configs/critical/tail_scalar.yaml", overrides=["system.C=0", "system.P0=1"])
    t = sc.analysis.compute(sc, RunContext(runs=300)).table
    est = t[t.series == "importance"]
    assert len(est) and (est["count"] == 300).all()  # every run above every M
    assert (t.value.dropna() <= 1).all() and (t.hi.dropna() <= 1).all() and (t.lo.dropna() >= 0).all()
    assert (est.hi == 1).all() and (est.value > 0.8).all()


@pytest.mark.parametrize("tol, ok", [(1e-10, False), (1e-9, True), (1e-3, True), (0.1, True), (0.2, False), (2, False)])
def test_scenario_bisection_tol_has_the_bounds_of_critical_tol(tmp_path, tol, ok):
    """analysis.bisection_tol accepted 2 (any positive number) where `netkf critical --tol` stops at 0.1 (and 1e-9):
    one range for both, refused with the same words."""
    cfg = tmp_path / "s.yaml"
    cfg.write_text("name: t\nsystem: {A: 2, C: 1, Q: 1, R: 1}\nchannel: {kind: bernoulli, arrival: 0.9}\n"
                   f"analysis: {{kind: critical, bisection_tol: {tol!r}}}\n", encoding="utf-8")
    res = runner.invoke(app, ["validate", str(cfg)])
    cli = runner.invoke(app, ["critical", "--tol", repr(tol), "--json"])
    if ok:
        assert res.exit_code == 0, res.output
        assert cli.exit_code == 0, cli.output
        return
    word = "greater than or equal to" if tol < 1e-9 else "less than or equal to 0.1"
    assert res.exit_code == 1 and "s.yaml:4 analysis.bisection_tol:" in res.output and word in res.output, res.output
    assert cli.exit_code != 0 and "--tol" in cli.output and word in " ".join(cli.output.split()), cli.output
