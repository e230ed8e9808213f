"""Bad-input corpus (issue 14.7): every topic's real config, broken one field at a time.

Each case asserts: exit code 1, the ``file:line dotted.path`` of the problem in the message, a
word of the explanation, no traceback, no "internal error", and nothing left in the output
folder. ``validate`` is used where the problem is found at load time; cases found only when the
analysis starts (``M`` below ``M̄``, ``burn_in ≥ horizon`` …) go through ``run`` with a tiny
``--runs``. Typer's CliRunner keeps this fast (one process); the subprocess cases live in
test_outputs.py / test_workers.py.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from netkf_cli.app.cli import app

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = ROOT / "configs"
runner = CliRunner()


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


def _line_of(text: str, needle: str) -> int:
    i = text.index(needle)
    return text[:i].count("\n") + 1


# (id, config, old, new, dotted path, needle, line | None (= line of `new`), command)
V, R = "validate", "run"
CASES = [
    # ---- Shi 2009: configs/fig5.yaml, fig8.yaml, updates_vs_buffer.yaml -----------------------
    ("A-not-square", "fig5.yaml", "A: 1.4,", "A: [[1, 2]],", "system.A", "square", None, V),
    ("Q-not-psd", "fig5.yaml", "Q: 0.2,", "Q: -0.2,", "system.Q", "positive semi-definite", None, V),
    ("R-not-pd", "fig5.yaml", "R: 0.5,", "R: 0,", "system.R", "positive definite", None, V),
    ("C-wrong-dims", "fig5.yaml", "C: 1,", "C: [[1, 0]],", "system.C", "", None, V),
    ("P0-bad-word", "fig5.yaml", "P0: steady", "P0: stable", "system.P0", "", None, V),
    ("P0-not-psd", "fig5.yaml", "P0: steady", "P0: -1", "system.P0", "", None, V),
    ("A-bool", "fig5.yaml", "A: 1.4,", "A: true,", "system.A", "boolean", None, V),
    ("A-text-yes", "fig5.yaml", "A: 1.4,", "A: yes,", "system.A", "", None, V),
    ("delay-mean-negative", "fig5.yaml", "mean: 5}", "mean: -1}", "channel.delay.mean", "greater than or equal to 0", None, V),
    ("delay-mean-nan", "fig5.yaml", "mean: 5}", "mean: .nan}", "channel.delay.mean", "must be a finite number", None, V),
    ("delay-mean-inf", "fig5.yaml", "mean: 5}", "mean: .inf}", "channel.delay.mean", "must be a finite number", None, V),
    ("delay-kind-unknown", "fig5.yaml", "{kind: poisson,", "{kind: uniform,", "channel.delay.kind", "unknown kind", None, V),
    ("pmf-prob-above-1", "fig5.yaml", "{kind: poisson, mean: 5}", "{kind: pmf, probs: [0.5, 1.5]}", "channel.delay.probs[1]", "less than or equal to 1", None, V),
    ("pmf-mass-above-1", "fig5.yaml", "{kind: poisson, mean: 5}", "{kind: pmf, probs: [0.6, 0.7]}", "channel.delay", "sum to at most 1", None, V),
    ("geometric-p-zero", "fig5.yaml", "{kind: poisson, mean: 5}", "{kind: geometric, p: 0}", "channel.delay.p", "greater than 0", None, V),
    ("buffer-zero", "fig5.yaml", "buffer: 10", "buffer: 0", "channel.buffer", "greater than 0", None, V),
    ("buffer-yes", "fig5.yaml", "buffer: 10", "buffer: yes", "channel.buffer", "expected an integer", None, V),
    ("buffer-fraction", "fig5.yaml", "buffer: 10", "buffer: 2.5", "channel.buffer", "fractional part", None, V),
    ("convention-unknown", "fig5.yaml", "convention: delay_le_D", "convention: delay_le", "channel.convention", "", None, V),
    ("channel-unknown-key", "fig5.yaml", "buffer: 10", "bufer: 10", "channel.bufer", "unknown key", None, V),
    ("channel-kind-unknown", "fig5.yaml", "kind: delay\n", "kind: telepathy\n", "channel.kind", "unknown kind", None, V),
    ("estimator-kind-unknown", "fig5.yaml", "{kind: buffered}", "{kind: psychic}", "estimator.kind", "unknown kind", None, V),
    ("estimator-unknown-key", "fig8.yaml", "{kind: smart_sensor}", "{kind: smart_sensor, gain: 2}", "estimator.gain", "unknown key", None, V),
    ("M-below-Mbar", "fig3.yaml", "M: [50, 150, 500]", "M: [50, 0.1, 500]", "analysis.M[1]", "M̄", None, R),
    ("M-num-zero", "fig5.yaml", "num: 60,", "num: 0,", "analysis.M.num", "", None, V),
    ("M-spacing-unknown", "fig5.yaml", "spacing: log}", "spacing: cubic}", "analysis.M.spacing", "", None, V),
    ("runs-yes", "fig5.yaml", "runs: 200000,", "runs: yes,", "montecarlo.runs", "expected an integer, got the text 'yes'", None, V),
    ("runs-on", "fig5.yaml", "runs: 200000,", "runs: on,", "montecarlo.runs", "expected an integer", None, V),
    ("runs-true", "fig5.yaml", "runs: 200000,", "runs: true,", "montecarlo.runs", "boolean", None, V),
    ("runs-zero", "fig5.yaml", "runs: 200000,", "runs: 0,", "montecarlo.runs", "greater than 0", None, V),
    ("runs-nan", "fig5.yaml", "runs: 200000,", "runs: .nan,", "montecarlo.runs", "must be a finite number", None, V),
    ("runs-1e400", "fig5.yaml", "runs: 200000,", "runs: 1e400,", "montecarlo.runs", "must be a finite number", None, V),
    ("seed-negative", "fig5.yaml", "seed: 105,", "seed: -1,", "montecarlo.seed", "greater than or equal to 0", None, V),
    ("chunk-off", "fig5.yaml", "chunk: 20000}", "chunk: off}", "montecarlo.chunk", "expected an integer", None, V),
    ("horizon-inf", "fig5.yaml", "horizon: 100,", "horizon: .inf,", "montecarlo.horizon", "must be a finite number", None, V),
    ("burn-in-at-horizon", "fig5.yaml", "horizon: 100,", "horizon: 100, burn_in: 100,", "montecarlo.burn_in", "horizon", None, R),
    ("montecarlo-unknown-key", "fig5.yaml", "seed: 105,", "sed: 105,", "montecarlo.sed", "unknown key", None, V),
    ("top-unknown-key", "fig5.yaml", "estimator: {kind: buffered}", "estimator: {kind: buffered}\nplot: yes", "plot", "unknown key", "plot: yes", V),
    ("name-with-slash", "fig5.yaml", "name: fig5", "name: ../fig5", "name", "pattern", None, V),
    ("analysis-kind-unknown", "fig5.yaml", "analysis:\n  kind: ", "analysis:\n  kind: no_such_", "analysis.kind", "unknown kind 'no_such_", None, V),
    ("duplicate-key", "fig5.yaml", "estimator: {kind: buffered}", "estimator: {kind: buffered}\nestimator: {kind: buffered}", "", "duplicate key 'estimator'", -1, V),
    ("updates-M-negative", "updates_vs_buffer.yaml", "M: [5, 20, 50]", "M: [5, -20, 50]", "analysis.M[1]", "greater than 0", None, V),
    ("updates-unknown-reference", "updates_vs_buffer.yaml", "references: [shi_expected_updates,", "references: [no_such_reference,", "analysis.references", "unknown closed form", None, V),
    ("sweep-bad-path", "fig5.yaml", "estimator: {kind: buffered}", "estimator: {kind: buffered}\nsweep: {channel.bufer: [1, 2]}", "channel.bufer", "unknown key", "channel.bufer", V),
    ("sweep-bad-value", "fig5.yaml", "estimator: {kind: buffered}", "estimator: {kind: buffered}\nsweep: {channel.buffer: [1, 0]}", "channel.buffer", "sweep point channel.buffer=0", "channel.buffer: [1, 0]", V),
    # ---- fading: Mostofi & Murray ----------------------------------------------------------
    ("fading-unit-unknown", "fading/fig3.yaml", "{value: 20, unit: dB}", "{value: 20, unit: dBm}", "channel.snr_avg.unit", "", None, V),
    ("fading-Np-zero", "fading/fig3.yaml", "N_p: 10,", "N_p: 0,", "channel.noise.N_p", "greater than 0", None, V),
    ("fading-Delta-negative", "fading/fig3.yaml", "Delta: 0.0390625}", "Delta: -0.04}", "channel.noise.Delta", "greater than 0", None, V),
    ("fading-snr-num-zero", "fading/fig3.yaml", "num: 161}", "num: 0}", "analysis.snr.num", "", None, V),
    ("fading-snr-value-nan", "fading/fig3.yaml", "{value: 20, unit: dB}", "{value: .nan, unit: dB}", "channel.snr_avg.value", "must be a finite number", None, V),
    ("fading-noise-model-unknown", "fading/thm4.yaml", "{model: inverse_snr,", "{model: inverse_noise,", "channel.noise.model", "", None, V),
    ("fading-beta-negative", "fading/thm4.yaml", "beta: 1.0}", "beta: -1.0}", "channel.noise.beta", "greater than or equal to 0", None, V),
    ("fading-a-inf", "fading/thm4.yaml", "A: 1.5,", "A: .inf,", "system.A", "must be a finite number", None, V),  # a = system.A
    ("fading-kmax-negative", "fading/thm4.yaml", "horizon: 30,", "horizon: -1,", "montecarlo.horizon", "greater than 0", None, V),  # k_max = horizon
    ("fading-unknown-key", "fading/thm4.yaml", "  references: [fading_theorem4,", "  kmax: 30\n  references: [fading_theorem4,", "analysis.kmax", "unknown key", "kmax: 30", V),
    # ---- fusion: Chiuso & Schenato -----------------------------------------------------------
    ("fusion-sensors-zero", "fusion/fig1.yaml", "sensors: 25", "sensors: 0", "channel.sensors", "greater than 0", None, V),
    ("fusion-loss-above-1", "fusion/fig1.yaml", "loss: 0.5 ", "loss: 1.5 ", "channel.loss", "less than or equal to 1", None, V),
    ("fusion-strategy-unknown", "fusion/fig1.yaml", "strategies: [olpef]", "strategies: [xyz]", "estimators[2].strategies[0]", "", None, V),
    ("fusion-R-not-pd", "fusion/fig1.yaml", "R: 10}", "R: -10}", "system.R", "positive definite", None, V),
    ("fusion-Q-1e-3-ok-but-R-zero", "fusion/fig3.yaml", "R: 1.0e-2}", "R: 0e-2}", "system.R", "positive definite", None, V),
    ("fusion-A-C-mismatch", "fusion/fig3.yaml", "A: 0.9,", "A: [[0.9, 0], [0, 0.5]],", "system.C", "", None, V),
    ("fusion-loss-grid-negative", "fusion/fig3.yaml", "channel.loss: [0.0, 0.1,", "channel.loss: [-0.1, 0.1,", "channel.loss", "over point channel.loss=-0.1", None, V),
    # ---- critical: an empty rate list passed validate, then `netkf run` failed with an internal error ----------
    ("critical-lambdas-empty", "critical/scalar_a2.yaml", "lambdas: [0.76, 0.78, 0.8, 0.82, 0.85, 0.88, 0.9, 0.93, 0.95, 0.97, 0.99]", "lambdas: []", "analysis.lambdas", "needs at least one arrival rate λ, got an empty list", None, V),
    ("critical-lambdas-empty-run", "critical/scalar_a2.yaml", "lambdas: [0.76, 0.78, 0.8, 0.82, 0.85, 0.88, 0.9, 0.93, 0.95, 0.97, 0.99]", "lambdas: []", "analysis.lambdas", "needs at least one arrival rate λ", None, R),
    # ---- markov: Moayedi, Soh & Foo --------------------------------------------------------
    ("markov-transition-not-stochastic", "markov/example1.yaml", "- [0.8, 0.0, 0.10, 0.10]", "- [0.9, 0.0, 0.10, 0.10]", "channel.transition[0]", "must sum to 1", None, V),
    ("markov-transition-3-columns", "markov/example1.yaml", "- [0.8, 0.0, 0.10, 0.10]", "- [0.8, 0.0, 0.20]", "channel.transition", "not a matrix", "transition:", V),
    ("markov-rho-length", "markov/example1_exact.yaml", "rho: [0.8, 0.02, 0.09, 0.09]", "rho: [0.8, 0.2]", "estimator.rho", "needs 4 marginals", None, V),
    ("markov-solver-unknown", "markov/example1_exact.yaml", "solver: CLARABEL", "solver: MAGIC", "estimator.solver", "'CLARABEL' or 'SCS'", None, V),
    ("markov-Q-not-psd", "markov/example1.yaml", "Q: [[1, 0], [0, 0]]", "Q: [[1, 2], [2, 1]]", "system.Q", "positive semi-definite", None, V),
    ("markov-initial-not-distribution", "markov/example1.yaml", "initial: stationary", "initial: [0.5, 0.6]", "channel.initial", "needs 4 probabilities", None, V),
    ("markov-S-wrong-dims", "markov/example1_exact.yaml", "S: [[0.2], [0.0]]", "S: [[0.2, 0.1, 0.0]]", "estimator.S", "must be 2×1", None, V),
    ("markov-estimators-S-wrong-dims", "markov/example1.yaml", "S: [[0.2], [0.0]]", "S: [[0.2, 0.1, 0.0]]", "estimators[0].S", "must be 2×1", None, V),
    ("markov-plant-S-wrong-dims", "markov/example1.yaml", "S: [[0.2], [0.0]]                   #", "S: [[0.2, 0.1, 0.0]]                #", "analysis.S", "must be 2×1", None, R),
    # ---- smoothing: Leong, Dey & Evans ---------------------------------------------------
    # eps (Table I's 1 − guarantee) is gone: the config holds the arrival rates it gave, a probability grid
    ("smoothing-eps-above-1", "smoothing/table1.yaml", "channel.arrival: [0.3481636551311609,", "channel.arrival: [1.3481636551311609,", "channel.arrival", "less than or equal to 1, got 1.348", None, V),
    ("smoothing-eps-unknown-key", "smoothing/table1.yaml", "  M: 6.25", "  M: 6.25\n  eps: 0.05", "analysis.eps", "unknown key", None, V),
    # lags are estimator blocks now (the predictor P_{k|k-1} is `quantity: predicted`): a negative lag is refused
    ("smoothing-lag-below-minus-1", "smoothing/table1.yaml", "{kind: smoother, lag: 0}", "{kind: smoother, lag: -1}", "estimators[0].lag", "greater than or equal to 0", None, V),
    ("smoothing-M-nan", "smoothing/table1.yaml", "M: 6.25", "M: .nan", "analysis.M", "must be a finite number", None, V),
    # a model-level check whose sentence starts with the field: reported at the field's line (hoisted)
    ("time-average-M-negative", "smoothing/burstiness.yaml", "M: 6.25", "M: -6.25", "analysis.M", "M must be finite and > 0", None, V),
    ("smoothing-retrans-p-above-1", "smoothing/retransmission.yaml", "channel.p: [0.0, 0.25,", "channel.p: [1.5, 0.25,", "channel.p", "less than or equal to 1, got 1.5 (over point channel.p=1.5)", None, V),
    ("smoothing-retrans-channel-p-above-1", "smoothing/retransmission.yaml", "p: 1.0}", "p: 1.5}", "channel.p", "less than or equal to 1", None, V),
    ("smoothing-arrival-above-1", "smoothing/retransmission.yaml", "arrival: 0.6,", "arrival: 1.2,", "channel.arrival", "less than or equal to 1", None, V),
    ("smoothing-ge-loss-rate-1", "smoothing/burstiness.yaml", "loss_rate: 0.5492802716530588,", "loss_rate: 1,", "channel.loss_rate", "less than 1", None, V),
    ("smoothing-ge-burst-below-1", "smoothing/burstiness.yaml", "mean_burst: 3}", "mean_burst: 0.5}", "channel.mean_burst", "greater than or equal to 1", None, V),
]


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_broken_config(tmp_path, case):
    cid, config, old, new, path, needle, line, cmd = case
    text = (CONFIGS / config).read_text(encoding="utf-8")
    assert text.count(old) >= 1, f"{cid}: {old!r} not in {config} (the config changed; update the case)"
    broken = text.replace(old, new, 1)
    cfg = tmp_path / Path(config).name
    cfg.write_text(broken, encoding="utf-8")
    if line is None:  # the line of the changed text (its last line when it adds lines)
        line = _line_of(broken, new.split("\n")[-1] if "\n" in new.rstrip("\n") else new)
    elif line == -1:  # the last line of the changed text, which repeats an earlier one
        line = broken.index(new) + len(new)
        line = broken[:line].count("\n") + 1
    elif isinstance(line, str):
        line = _line_of(broken, line)
    out = tmp_path / "out" / "o"
    args = ("validate", cfg) if cmd == V else ("run", cfg, "--out", out, "--runs", 40, "--jobs", 1, "-q")
    r = invoke(*args)
    assert r.exit_code == 1, f"{cid}: exit {r.exit_code}\n{r.output}"
    where = f"{cfg.name}:{line} {path}" + (":" if path else "")
    assert where in r.output, f"{cid}: expected {where!r} in\n{r.output}"
    assert needle in r.output, f"{cid}: expected {needle!r} in\n{r.output}"
    assert "Traceback" not in r.output and "internal error" not in r.output
    assert not out.exists()
    assert not out.parent.exists() or not list(out.parent.iterdir()), list(out.parent.iterdir())


def test_an_override_is_named_for_a_model_level_check_on_its_field(tmp_path):
    """analysis.M=[-1] on the command line fails a check of the analysis model ("M must be finite and > 0"): the
    error names the override, not the file's line of analysis (which holds another value)."""
    r = invoke("run", CONFIGS / "smoothing" / "burstiness.yaml", "analysis.M=[-1]", "--out", tmp_path / "o", "-q")
    assert r.exit_code == 1, r.output
    assert "command line (analysis.M=[-1]) analysis.M: M must be finite and > 0" in " ".join(r.output.split())
    assert "burstiness.yaml" not in r.output and not (tmp_path / "o").exists()


@pytest.mark.parametrize("config", ["smoothing/table1.yaml", "updates_vs_buffer.yaml", "fusion/fig1.yaml"])
def test_a_problem_is_reported_once(tmp_path, config):
    """burn_in ≥ horizon is one problem: the scenario check and the metric's own check said it twice, in two
    wordings, for every time-averaging metric."""
    r = invoke("validate", CONFIGS / config, "montecarlo.horizon=1")
    assert r.exit_code == 1, r.output
    assert r.output.count("montecarlo.burn_in:") == 1, r.output


@pytest.mark.parametrize("config, override, needle", [
    ("fading/fig3.yaml", "channel.noise={model: inverse_snr, beta: 0.1}", "needs the noise model `ber`"),
    ("fading/fig4.yaml", "channel.correlation={model: jakes, carrier_hz: 9e8, speed: {value: 10, unit: m/s}, "
                         "interval_s: 0.01}", "needs an i.i.d. channel"),
    ("fading/fig5.yaml", "system.C=[[1,0,0],[0,1,0],[0,0,0]]", "needs an invertible (square) C"),
    ("markov/example1_exact.yaml", "estimator={kind: kf}", "needs an estimator of kind markov_lmi"),
    ("markov/example1_exact.yaml", "analysis.x0=[1,2,3]", "must have 2 entries"),
    ("fusion/fig2.yaml", "analysis.ell=[7]", "must be ≤ sensors = 6, got 7"),
    ("fig3.yaml", "analysis.M=[0.1, 3]", "analysis.M[0]: must satisfy M ≥ M̄ = 0.5 (Thm 3.8 needs M ≥ M̄), got M = 0.1"),
    ("markov/example1.yaml", "analysis.S=[[2.0],[0.0]]", "the joint noise covariance [[Q, S], [Sᵀ, R]] must be positive "
                                                         "semi-definite"),
])
def test_validate_reports_what_the_recipe_would_refuse(tmp_path, config, override, needle):
    """A paper recipe's own requirements are checked by `netkf validate` (they were found only by `netkf run`, when
    the work began, and named the file's line instead of the override that broke them)."""
    r = invoke("validate", CONFIGS / config, override)
    out = " ".join(r.output.split())
    assert r.exit_code == 1 and needle in out and f"command line ({override})" in out, out
    r = invoke("run", CONFIGS / config, override, "--out", tmp_path / "o", "-q")
    assert r.exit_code == 1 and needle in " ".join(r.output.split()) and not (tmp_path / "o").exists()


@pytest.mark.parametrize("config, overrides, needle", [
    ("fig5.yaml", ["system.C=0"], "system.P0: unset (or steady), P0 is P̄"),
    ("critical/tail_scalar.yaml", ["system.C=0"], "system.P0: unset (or steady), P0 is P̄"),
    ("smoothing/table1.yaml", ["system.C=[[0]]"], "system.P0: unset (or steady), P0 is P̄"),
    ("fusion/fig2.yaml", ["system.A=1.5", "system.C=0"], "P_m = Φ(P_m, N) has no stabilizing solution"),
    ("fig5.yaml", ["system.R=1e45"], "(A, C) is detectable and (A, √Q) stabilizable, so the solver failed numerically"),
])
def test_validate_reports_a_start_or_bound_that_does_not_exist(tmp_path, config, overrides, needle):
    """An undetectable system: P0 unset means P̄ for every estimator (core/spec), and P̄ does not exist; fusion's
    P_m neither. `netkf validate` says so (it said ✓, and `netkf run` refused at the first chunk)."""
    r = invoke("validate", CONFIGS / config, *overrides)
    out = " ".join(r.output.split())
    assert r.exit_code == 1 and needle in out and "detectable" in out and out.count("•") == 1, out
    r = invoke("run", CONFIGS / config, *overrides, "--out", tmp_path / "o", "-q")
    assert r.exit_code == 1 and needle in " ".join(r.output.split()) and not (tmp_path / "o").exists()


def test_validate_reports_a_closed_form_that_cannot_be_drawn(tmp_path):
    """A reference's own conditions (Leong's enumeration: lag ≤ 8; 0 < λ < 1) are checked by `netkf validate`, once
    per problem with the over points it fails at, and by `netkf run` before any Monte Carlo (they were found after
    it, when the rows were drawn)."""
    r = invoke("validate", CONFIGS / "smoothing" / "retransmission.yaml", "estimator.lag=20")
    out = " ".join(r.output.split())
    assert r.exit_code == 1 and out.count("•") == 1, out
    assert "smoother lags up to 8, got 20" in out and "(at every over point: channel.p; 5 points)" in out, out
    text = (CONFIGS / "smoothing" / "table1_predictor.yaml").read_text(encoding="utf-8")
    bad = tmp_path / "t.yaml"
    bad.write_text(text.replace("0.3481636551311609", "0.0", 1), encoding="utf-8")
    r = invoke("validate", bad)
    out = " ".join(r.output.split())
    assert r.exit_code == 1 and "needs both arrivals and losses" in out and "(over point channel.arrival=0.0)" in out
    assert f"t.yaml:{_line_of(text, 'channel.arrival: [')} channel:" in out, out


def test_reference_checks_are_deferred_only_where_asked():
    """netkf reproduce's discovery loads every config without evaluating its references (serial work its
    artefacts' runs do anyway, before their Monte Carlo); a load anywhere else evaluates them."""
    from netkf_cli.config.loader import load_scenario
    from netkf_cli.core.errors import ConfigError
    from netkf_cli.metrics.common import deferred_reference_checks

    cfg = CONFIGS / "smoothing" / "retransmission.yaml"
    with deferred_reference_checks():
        assert load_scenario(cfg, overrides=["estimator.lag=20"]).estimator.lag == 20
    with pytest.raises(ConfigError, match="smoother lags up to 8, got 20"):
        load_scenario(cfg, overrides=["estimator.lag=20"])


def test_corpus_is_large_enough():
    files = {"file-level": len(FILE_CASES)}
    assert len(CASES) + len(FILE_CASES) >= 60, files


# ---- whole-file problems ----------------------------------------------------------------------

def _bomb() -> bytes:
    lines = ['a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for i in range(1, 10):
        p, c = chr(96 + i), chr(97 + i)
        lines.append(f"{c}: &{c} [" + ",".join([f"*{p}"] * 9) + "]")
    return ("\n".join(lines) + "\n").encode()


FIG5 = (CONFIGS / "fig5.yaml").read_text(encoding="utf-8")
FILE_CASES = [
    ("latin-1", FIG5.replace("≤", "<=").encode("utf-8").replace(b"Murray", "Müray".encode("latin-1")), "not UTF-8 text"),
    ("utf-16", FIG5.encode("utf-16"), "UTF-16"),
    ("utf-16-no-bom", FIG5.encode("utf-16-le"), "UTF-16"),
    ("binary", bytes(range(256)) * 4, "binary file"),
    ("alias-bomb", _bomb(), "alias bomb"),
    ("empty", b"", "the file is empty"),
    ("only-comment", b"# nothing here\n", "the file is empty"),
    ("list-top-level", b"- name: fig5\n- analysis: x\n", "holds a list"),
    ("scalar-top-level", b"fig5\n", "holds a single string"),
    ("yaml-syntax", b"name: t\nsystem: {A: 1\n  bad", "YAML syntax error"),
    ("tab-indent", b"name: t\nsystem:\n\tA: 1\n", "YAML syntax error"),
    ("deep-nesting", b"a: " + b"[" * 300 + b"]" * 300 + b"\n", "nested"),
    ("unknown-tag", b"name: !!python/object:os.system ls\n", "YAML"),
    ("integer-key", b"name: t\n1: 2\n", "keys must be names"),
    ("null-key", b"name: t\n~: 2\n", "keys must be names"),
]


@pytest.mark.parametrize("cid,data,needle", FILE_CASES, ids=[c[0] for c in FILE_CASES])
def test_bad_file(tmp_path, cid, data, needle):
    cfg = tmp_path / "bad.yaml"
    cfg.write_bytes(data)
    out = tmp_path / "o"
    for args in (("validate", cfg), ("run", cfg, "--out", out)):
        t0 = time.perf_counter()
        r = invoke(*args)
        assert time.perf_counter() - t0 < 5, f"{cid}: took too long"
        assert r.exit_code == 1, f"{cid}: exit {r.exit_code}\n{r.output}"
        assert "bad.yaml" in r.output and needle in r.output, f"{cid}:\n{r.output}"
        assert "Traceback" not in r.output and "internal error" not in r.output
    assert not out.exists()


def test_alias_bomb_refused_within_a_second(tmp_path):
    cfg = tmp_path / "bomb.yaml"
    cfg.write_bytes(_bomb())
    invoke("validate", tmp_path / "warm.yaml")  # imports done outside the timing
    t0 = time.perf_counter()
    r = invoke("validate", cfg)
    assert time.perf_counter() - t0 < 1.0
    assert r.exit_code == 1 and "alias bomb" in r.output


def test_directory_and_missing_file(tmp_path):
    r = invoke("validate", tmp_path)
    assert r.exit_code == 1 and "is a folder" in r.output and "Traceback" not in r.output
    r = invoke("run", tmp_path / "nope.yaml")
    assert r.exit_code == 1 and "nope.yaml file not found" in r.output


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads any file")
def test_unreadable_file(tmp_path):
    cfg = tmp_path / "s.yaml"
    cfg.write_text(FIG5)
    cfg.chmod(0)
    r = invoke("validate", cfg)
    assert r.exit_code == 1 and "cannot read the file" in r.output


# ---- YAML 1.2 numbers are numbers ------------------------------------------------------------

@pytest.mark.parametrize("q", ["1e-3", "1.0e-3", "1E-3", "0.001", "+1e-3"])
def test_yaml_12_exponent_floats_are_numbers(tmp_path, q):
    cfg = tmp_path / "s.yaml"
    cfg.write_text(FIG5.replace("Q: 0.2,", f"Q: {q},"))
    r = invoke("validate", cfg)
    assert r.exit_code == 0, r.output


def test_integral_floats_are_exact_integers(tmp_path):
    from netkf_cli.config.loader import load_scenario

    cfg = tmp_path / "s.yaml"
    cfg.write_text(FIG5.replace("runs: 200000,", "runs: 2e5,").replace("buffer: 10", "buffer: 10.0"))
    sc = load_scenario(cfg)
    assert sc.montecarlo.runs == 200000 and isinstance(sc.montecarlo.runs, int)
    assert sc.channel.buffer == 10 and isinstance(sc.channel.buffer, int)


# ---- netkf mind arguments ----------------------------------------------------------------------

@pytest.mark.parametrize("args,needle", [
    (("--M", 50, "--d", "inf"), "--d: must be a finite number"),
    (("--M", 50, "--d", "nan"), "--d: must be a finite number"),
    (("--M", "nan"), "--M: must be a finite number"),
    (("--M", "inf"), "--M: must be a finite number"),
    (("--M", 50, "--eps", "nan"), "--eps: must be a finite number"),
    (("--M", 50, "--eps", -0.1), "--eps: must be a probability"),
    (("--M", 50, "--d", -1), "--d: must be a mean delay"),
    (("--M", 50, "--d", 1e9), "--d: must be a mean delay"),
    (("--M", 0.1), "M̄"),
])
def test_mind_bad_numbers(args, needle):
    r = invoke("mind", *args)
    assert r.exit_code == 1, r.output
    assert needle in r.output and "Traceback" not in r.output


def test_mind_bad_config(tmp_path):
    cfg = tmp_path / "s.yaml"
    cfg.write_bytes(FIG5.encode("utf-16"))
    r = invoke("mind", "--M", 50, "--config", cfg)
    assert r.exit_code == 1 and "UTF-16" in r.output


def _limit_memory():  # the child may not take the shared machine down while the bug exists
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (2 * 2**30, 2 * 2**30))


def test_huge_sweep_is_refused_quickly(tmp_path):
    import subprocess
    import sys

    cfg = tmp_path / "s.yaml"
    cfg.write_text(FIG5 + "sweep: {channel.buffer: {from: 1, to: 1e9}}\n")
    try:
        r = subprocess.run([sys.executable, "-m", "netkf_cli.app.cli", "validate", str(cfg)], capture_output=True,
                           text=True, timeout=10, preexec_fn=_limit_memory)
    except subprocess.TimeoutExpired:
        pytest.fail("validate did not refuse a 1e9-point sweep within 10 s")
    assert r.returncode == 1 and "sweep" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.parametrize("args", [("critical", "--tol", "nan"), ("critical", "--tol=inf"),
                                  ("critical", "--arrival", "NaN"), ("mind", "--M", 50, "--d", "-inf")])
def test_non_finite_option_values_of_any_command(args):
    """Caught for every command before click's range checks (which would say "≤ 0.1" for NaN)."""
    r = invoke(*args)
    assert r.exit_code == 1, r.output
    assert "must be a finite number" in r.output and "Traceback" not in r.output


def test_a_chunk_plan_above_the_available_memory_is_refused_before_it_starts(tmp_path, monkeypatch):
    """Memory is bounded by the chunk size and the horizon (a chunk holds its runs' traces, ~8 B per run-step): a
    horizon of 1e12 grew to 24 GB and was killed by the system's OOM killer (the UX fuzz). Refused, naming the
    field, with a chunk size that would fit; nothing is written."""
    from netkf_cli.runtime import montecarlo

    monkeypatch.setattr(montecarlo, "available_memory", lambda: 2e9)
    cfg = CONFIGS / "fig5.yaml"
    r = invoke("run", cfg, "montecarlo.horizon=50000", "--jobs", "1", "--out", tmp_path / "o", "-q")
    out = " ".join(r.output.split())
    assert r.exit_code == 1 and "montecarlo.chunk: a chunk holds its runs' whole traces: 20000 runs × 50000 steps is about 8 GB in 1 process" in out
    assert "chunks of 4000 runs would fit" in out and not (tmp_path / "o").exists(), out
    r = invoke("run", cfg, "montecarlo.horizon=1e12", "--runs", "2", "--out", tmp_path / "o", "-q")
    assert r.exit_code == 1 and "montecarlo.horizon: a chunk holds" in " ".join(r.output.split()), r.output
    assert invoke("run", cfg, "--runs", "100", "--out", tmp_path / "o", "-q").exit_code == 0  # 8 MB: fine


@pytest.mark.parametrize("config, overrides, needle", [
    ("fig5.yaml", ["analysis.references=[kf_bernoulli_bounds]"],
     "analysis.references: distribution draws no closed-form references"),
    ("fig5.yaml", ["analysis={kind: time_average, references: [fading_lemma5]}", "estimator={kind: kf}",
                   "channel={kind: bernoulli, arrival: 0.8}", "montecarlo.burn_in=50"],
     "analysis.references[0]: fading_lemma5 gives nothing for this scenario: it gives Mostofi & Murray 2009, Lemma 5"),
])
def test_a_reference_that_cannot_be_drawn_is_refused(tmp_path, config, overrides, needle):
    """references were accepted by every generic metric but drawn by four; a closed form that gives no rows for the
    scenario was silently empty while the manifest listed it and the figure's footnote said it was drawn (the UX
    fuzz)."""
    r = invoke("validate", CONFIGS / config, *overrides)
    out = " ".join(r.output.split())
    assert r.exit_code == 1 and needle in out, out
    r = invoke("run", CONFIGS / config, *overrides, "--out", tmp_path / "o", "-q")
    assert r.exit_code == 1 and needle in " ".join(r.output.split()) and not (tmp_path / "o").exists()


def test_a_jakes_channel_needs_its_white_floor(tmp_path):
    """nugget: 0 passed validate and crashed netkf run ('Matrix is not positive definite': J₀'s Toeplitz matrix alone
    is singular to rounding), at the shipped Fig. 7 settings too (the fields fuzz). Refused at validate."""
    r = invoke("validate", CONFIGS / "fading" / "fig7.yaml", "channel.correlation.nugget=0")
    out = " ".join(r.output.split())
    assert r.exit_code == 1 and "nugget: Input should be greater than 0, got 0" in out, out


def test_small_messages_name_their_source(tmp_path):
    """The UX fuzz: an unknown key given by an override was the file's; a result folder that cannot be made did not
    say it is the result folder; a sweep's plot.where listed the swept column twice."""
    r = invoke("validate", CONFIGS / "fig3.yaml", "foo.bar=1")
    assert "command line (foo.bar=1) foo: unknown key" in " ".join(r.output.split()), r.output
    if Path("/proc/self").is_dir():  # Linux: nothing, not even root, can make a folder in /proc
        r = invoke("run", CONFIGS / "fig3.yaml", "output.dir=/proc/netkf-test/x", "-q")
        assert r.exit_code == 1 and "--out or output.dir" in " ".join(r.output.split()), r.output
    cfg = tmp_path / "sp.yaml"
    cfg.write_text("name: sp\nsystem: {A: 1.2, C: 1, Q: 1, R: 1}\nchannel: {kind: bernoulli, arrival: 0.8}\n"
                   "estimator: {kind: kf}\nanalysis: {kind: time_average}\nmontecarlo: {runs: 100, horizon: 20, seed: 1}\n"
                   "sweep: {channel.arrival: [0.5, 0.6], plot: {where: {foo: 1}}}\n", encoding="utf-8")
    r = invoke("run", cfg, "--out", tmp_path / "o", "-q")
    out = " ".join(r.output.split())
    assert r.exit_code == 1 and "columns: channel.arrival, estimator," in out, out
