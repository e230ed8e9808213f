"""reproduce.run_all: the driver's process setup (what workers inherit), not the artefacts themselves."""

import gc
import os
from pathlib import Path

from netkf_cli.app import reproduce as R


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
