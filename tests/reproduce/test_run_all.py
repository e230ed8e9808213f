"""reproduce.run_all: the driver's process setup (what workers inherit), not the artefacts themselves."""

import gc
import os
import weakref
from pathlib import Path

import pytest

from netkf_cli.app import reproduce as R
from netkf_cli.linalg import kalman


def _report(args):
    """Stands in for _run_one in a forked worker: (name, folder, frozen objects, pid as the 'error')."""
    config, folder, quick = args
    return Path(config).stem, folder, gc.get_freeze_count(), str(os.getpid())


def test_workers_inherit_frozen_objects_and_the_parent_unfreezes(monkeypatch, tmp_path):
    monkeypatch.setattr(R, "_run_one", _report)
    arts = [R.Artefact("t", f"a{i}", tmp_path / f"a{i}.yaml") for i in range(4)]
    done = []
    res = R.run_all(arts, tmp_path, True, 2, on_done=lambda a, r: done.append(a.name))
    assert sorted(done) == sorted(res) == [a.name for a in arts]
    assert all(r[2] > 10_000 for r in res.values())  # numpy, matplotlib, pydantic … frozen before the fork
    assert all(r[3] != str(os.getpid()) for r in res.values())  # they ran in workers
    assert gc.get_freeze_count() == 0


def test_serial_path_freezes_too_and_unfreezes(monkeypatch, tmp_path):
    monkeypatch.setattr(R, "_run_one", _report)
    res = R.run_all([R.Artefact("t", "a", tmp_path / "a.yaml")], tmp_path, True, 1)
    assert res["a"][2] > 10_000 and res["a"][3] == str(os.getpid())
    assert gc.get_freeze_count() == 0


def _runs_what_it_was_given(args):
    """Stands in for run_scenario's caller in a forked worker: which scenario _run_one would run, and whether it
    had to load the config again."""
    config, folder, quick = args
    sc = R._SCENARIOS.get(config)
    return Path(config).stem, folder, 0, None if sc is None else sc.tag


def test_the_discovered_scenario_is_run_not_loaded_again(monkeypatch, tmp_path):
    """Each scenario is parsed and validated once per reproduction: run_all hands discover's object to _run_one
    (inherited by forked workers), and forgets it afterwards."""
    from types import SimpleNamespace

    ran = []
    monkeypatch.setattr(R, "run_scenario", lambda sc, **kw: ran.append(sc))
    monkeypatch.setattr(R, "load_scenario", lambda path: (_ for _ in ()).throw(AssertionError(f"{path} loaded again")))
    sc = SimpleNamespace(name="a", montecarlo=SimpleNamespace(quick_size=lambda: 5))
    res = R.run_all([R.Artefact("t", "a", tmp_path / "a.yaml", sc)], tmp_path, True, 1)
    assert res["a"][3] is None and ran == [sc]  # no error: the object itself ran
    assert R._SCENARIOS == {}
    monkeypatch.setattr(R, "_run_one", _runs_what_it_was_given)
    arts = [R.Artefact("t", f"b{i}", tmp_path / f"b{i}.yaml", SimpleNamespace(tag=f"sc{i}")) for i in range(3)]
    res = R.run_all(arts, tmp_path, True, 2)
    assert {k: v[3] for k, v in res.items()} == {"b0": "sc0", "b1": "sc1", "b2": "sc2"}  # in the workers too
    assert R._SCENARIOS == {}


def test_reproduce_keeps_no_resume_chunks_a_plain_run_does(tmp_path, monkeypatch):
    """netkf reproduce has no --resume: its runs store no chunk files (one per chunk, written, renamed and deleted
    for nothing); `netkf run` keeps them until its result is written. The same numbers either way."""
    from netkf_cli.config.loader import load_scenario
    from netkf_cli.runtime import montecarlo

    stored = []
    real = montecarlo._store
    monkeypatch.setattr(montecarlo, "_store", lambda path, stats: (stored.append(path), real(path, stats)))
    root = Path(__file__).resolve().parents[2]
    sc = load_scenario(root / "configs" / "fig5.yaml")
    R._SCENARIOS[str(root / "configs" / "fig5.yaml")] = sc
    try:
        name, folder, _, err = R._run_one((str(root / "configs" / "fig5.yaml"), str(tmp_path / "r" / "fig5"), True))
    finally:
        R._SCENARIOS.clear()
    assert err is None and [p for p in stored if p is not None] == []
    assert not (tmp_path / "r" / ".netkf-cache").exists()
    R.run_scenario(sc, out_dir=tmp_path / "p" / "fig5", runs=sc.montecarlo.quick_size(), quick=True, force=True)
    assert [p for p in stored if p is not None]  # a plain run stores its finished chunks for --resume
    assert (tmp_path / "r" / "fig5" / "fig5.csv").read_bytes() == (tmp_path / "p" / "fig5" / "fig5.csv").read_bytes()


def test_reproduce_compiles_small_batches_and_says_so(tmp_path):
    """netkf reproduce runs auto's Kalman recursions compiled from kalman.EAGER_MIN_RUN_STEPS run-steps (numba is
    imported in its processes anyway); a plain run of the same size stays on numpy; each manifest says which ran."""
    pytest.importorskip("numba")
    import json
    from netkf_cli.config.loader import load_scenario

    root = Path(__file__).resolve().parents[2]
    cfg = root / "configs" / "fig9.yaml"
    sc = load_scenario(cfg)
    runs = sc.montecarlo.quick_size()
    assert kalman.EAGER_MIN_RUN_STEPS <= runs * sc.montecarlo.horizon < kalman.AUTO_MIN_RUN_STEPS  # in between
    name, folder, _, err = R._run_one((str(cfg), str(tmp_path / "r" / "fig9"), True))
    assert err is None
    R.run_scenario(sc, out_dir=tmp_path / "p" / "fig9", runs=runs, quick=True, force=True)

    def backends(folder):
        return json.loads((folder / "manifest.json").read_text())["meta"]["backends"]
    assert backends(tmp_path / "r" / "fig9")["buffered"] == "numba"
    assert backends(tmp_path / "p" / "fig9")["buffered"] == "numpy"
    assert not kalman.eager()  # reproduce's floors only while it runs


def test_what_survives_an_artefact_is_frozen_its_garbage_collected(monkeypatch, tmp_path):
    class Cycle:
        pass

    def artefact(sc, **kw):  # leaves one cache entry behind and one garbage cycle
        keep.append(Cycle())
        c = Cycle()
        c.self = c
        garbage.append(weakref.ref(c))

    keep, garbage = [], []
    monkeypatch.setattr(R, "run_scenario", artefact)
    from types import SimpleNamespace

    sc = SimpleNamespace(name="a", montecarlo=SimpleNamespace(quick_size=lambda: 5))
    R._SCENARIOS[str(tmp_path / "a.yaml")] = sc
    try:
        before = gc.get_freeze_count()
        R._run_one((str(tmp_path / "a.yaml"), str(tmp_path / "a"), True))
        assert gc.get_freeze_count() > before  # the survivors, the cache entry among them
        assert garbage[0]() is None  # collected before the freeze, not frozen alive
    finally:
        R._SCENARIOS.clear()
        gc.unfreeze()


def test_a_partial_reproduction_reports_what_it_did_not_run_as_such(tmp_path):
    """`netkf reproduce <topic>` writes a report of every artefact: those it ran with their time, one already in the
    folder as "not run by this command" with when its result was made, one never run as "not run yet" (both said
    "— 0.0 s" before, as if they had run)."""
    import json
    import shutil

    from typer.testing import CliRunner

    from netkf_cli.app.cli import app

    root = Path(__file__).resolve().parents[2]
    shutil.copytree(root / "results" / "fading_fig3", tmp_path / "fading_fig3")
    created = json.loads((tmp_path / "fading_fig3" / "manifest.json").read_text())["created"]
    r = CliRunner().invoke(app, ["reproduce", "--quick", "shi2009", "--out", str(tmp_path), "--jobs", "1"])
    assert r.exit_code == 0, r.output
    rep = (tmp_path / "REPORT.md").read_text(encoding="utf-8")
    assert "`netkf run configs/fading/fig3.yaml` — not run by this command (its result of " + created in rep
    assert "`netkf run configs/fading/fig4.yaml` — not run yet" in rep
    line = next(s for s in rep.splitlines() if s.startswith("`netkf run configs/fig5.yaml` — "))
    assert line.endswith(" s") and "not run" not in line
