"""The manifest's ``backends`` says what ran (issue 20: "the manifest says which ran").

* No estimator reports ``auto``: every ``backend: auto`` is resolved to what its recursion runs on.
* The fused kf kernel is recorded by the engine (``engine.FUSED_CHUNKS``), not predicted: a run that takes it
  says so, the same run with numba hidden says numpy, and the numbers agree.
* The smoother's and the receivers' recorded choice is the one their recursion makes (one rule each:
  ``smoother.plan``, ``fading_receivers.stepper_backend``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import netkf_cli
from netkf_cli import engine
from netkf_cli.linalg import kalman
from netkf_cli.estimators import fading_receivers as fr
from netkf_cli.estimators import smoother as sm

ROOT = Path(__file__).resolve().parents[2]
CONFIGS = sorted(str(p.relative_to(ROOT / "configs")) for p in (ROOT / "configs").rglob("*.yaml"))
VEHICLE = {"A": [[1, 0, 0.1, 0], [0, 1, 0, 0.1], [0, 0, 1, 0], [0, 0, 0, 1]],
           "C": [[1, 0, 0, 0], [0, 1, 0, 0]], "Q": (0.01 * np.eye(4)).tolist(), "R": (0.1 * np.eye(2)).tolist()}


def _scenario(system, channel, estimator, runs=400, horizon=30, chunk=400):
    return netkf_cli.load({"name": "backends", "system": system, "channel": channel, "estimator": estimator,
                           "analysis": {"kind": "mean_vs_time"},
                           "montecarlo": {"runs": runs, "horizon": horizon, "seed": 1, "chunk": chunk}})


@pytest.mark.parametrize("cfg", CONFIGS)
def test_no_estimator_of_a_config_reports_auto(cfg):
    sc = netkf_cli.load(ROOT / "configs" / cfg)
    if getattr(sc, "system", None) is None or getattr(sc, "channel", None) is None or not sc.estimator_list():
        pytest.skip("a recipe without a Monte Carlo estimator")
    s, mc = sc.linear_system(), sc.montecarlo
    for est in sc.estimator_list():
        used = est.backend_used(s, sc.channel, min(mc.chunk, mc.runs), mc.horizon)
        assert "auto" not in used and used.split()[0].rstrip(",") in ("numpy", "numba"), (est.kind, used)


def test_fused_kernel_is_recorded_and_agrees_with_numpy(monkeypatch):
    big = kalman.AUTO_MIN_RUN_STEPS // 30 + 1  # a chunk that `auto` runs in the fused kernel
    sc = _scenario(VEHICLE, {"kind": "bernoulli", "arrival": 0.7}, {"kind": "kf"}, runs=big, chunk=big)
    fused = netkf_cli.run(sc)
    assert fused.meta["backends"] == {"kf": engine.FUSED_LABEL}
    monkeypatch.setattr(kalman, "numba_available", lambda: False)
    plain = netkf_cli.run(sc)
    assert plain.meta["backends"] == {"kf": "numpy"}
    a, b = (r.table["value"].to_numpy(float) for r in (fused, plain))
    np.testing.assert_allclose(a, b, rtol=1e-9)  # the compiled filter's association order: rounding only


def test_smoother_records_the_plan_its_recursion_runs():
    sc = netkf_cli.load(ROOT / "configs" / "smoothing" / "table1.yaml")
    s, est = sc.linear_system(), sc.estimator_list()[-1]
    assert est.lag > 0
    f = kalman.Filter.of(s, 1)
    for runs, n_steps in [(10, 30), (400, 30), (200_000, 30)]:
        how, fwd, rts = sm.plan(f, "auto", est.lag, runs, 30, n_steps)
        want = "numba (per-run kernel)" if how == "per_run" else f"{fwd} forward pass, {rts} RTS"
        assert est.backend_used(s, sc.channel, runs, 30, steps=range(n_steps)) == want
    assert est.backend_used(s, sc.channel, 400, 30, quantities=("filtered",)) \
        == "{} forward pass, {} RTS".format(*sm.plan(f, "auto", 0, 400, 30, 30)[1:])


def test_receiver_records_the_stepper_backend():
    sc = netkf_cli.load(ROOT / "configs" / "fading" / "thm4.yaml")  # R = 1e-12: the rescue rule decides
    s, est = sc.linear_system(), sc.estimator_list()[0]
    rm = est.model(s, fr.NoiseFn.of(sc.channel.noise))
    P = kalman.one(kalman.predict, np.atleast_2d(s.P0), rm.A, rm.Q)
    assert fr.Stepper(rm, P, 4, "auto").backend == fr.stepper_backend(rm, P, "auto")
    assert est.backend_used(s, sc.channel, 400, 30) in ("numpy", "numba")


def test_a_stale_manifest_statement_is_rewritten(tmp_path, monkeypatch):
    """Identical files and meta leave the folder untouched; identical files with a changed ``meta`` (here the
    fused kernel's label) rewrite it, so a committed manifest never keeps saying what no longer ran."""
    big = kalman.AUTO_MIN_RUN_STEPS // 30 + 1
    sc = _scenario(VEHICLE, {"kind": "bernoulli", "arrival": 0.7}, {"kind": "kf"}, runs=big, chunk=big)
    out = tmp_path / "r"
    netkf_cli.run(sc, out=out)
    man = (out / "manifest.json").read_text()
    netkf_cli.run(sc, out=out)
    assert (out / "manifest.json").read_text() == man  # unchanged: kept, timestamps and all
    monkeypatch.setattr(engine, "FUSED_LABEL", "numba, fused (relabelled)")
    csv = (out / "backends.csv").read_bytes()
    netkf_cli.run(sc, out=out)
    assert (out / "backends.csv").read_bytes() == csv
    assert '"numba, fused (relabelled)"' in (out / "manifest.json").read_text()


@pytest.mark.parametrize("analysis", [{"kind": "mean_vs_time"}, {"kind": "distribution", "M": [0.5, 1.0], "at": 20},
                                      {"kind": "time_average", "M": [1.0]}])
def test_the_reductions_that_ran_are_recorded(monkeypatch, analysis):
    """The manifest's ``reduction`` is counted by the reducers as they decide (engine.REDUCED), chunk by chunk: a
    batch below the floor says numpy, one above it the compiled label, a run whose last chunk falls below it both
    with their shares; hiding numba says numpy; the numbers agree."""
    def run(runs, chunk):
        sc = netkf_cli.load({"name": "reductions", "system": VEHICLE, "channel": {"kind": "bernoulli", "arrival": 0.7},
                             "estimator": {"kind": "kf", "backend": "numpy"}, "analysis": analysis,
                             "montecarlo": {"runs": runs, "horizon": 30, "seed": 1, "chunk": chunk}})
        return netkf_cli.run(sc)

    small = run(300, 300)
    assert small.meta["reduction"] == "numpy"
    monkeypatch.setattr(engine, "REDUCE_MIN_RUNS", 250)
    compiled = run(300, 300)
    if kalman.numba_available():
        assert compiled.meta["reduction"] == engine.REDUCTION_LABEL
        mixed = run(400, 300)  # a chunk of 300 runs (compiled) and one of 100 (numpy): the same steps each
        c = mixed.meta["reduction"].split(" (")[2].split(" of ")[0]
        assert mixed.meta["reduction"] == f"{engine.REDUCTION_LABEL} ({c} of {2 * int(c)} step reductions), numpy ({c})"
    monkeypatch.setattr(kalman, "numba_available", lambda: False)
    hidden = run(300, 300)
    assert hidden.meta["reduction"] == "numpy"
    for r in (compiled, hidden):
        a, b = (x.table["value"].to_numpy(float) for x in (small, r))
        np.testing.assert_allclose(b, a, rtol=1e-9, atol=0)
