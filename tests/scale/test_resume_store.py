"""The resume store's chunk files (runtime.montecarlo): what a finished chunk writes is what a resumed run reads,
bit for bit, and anything else (a torn file, another format) reads as "compute this chunk again"."""

import numpy as np
import pytest

from netkf_cli.runtime import montecarlo as mc


def _stats():
    rng = np.random.default_rng(3)
    return {"sum_tr_0": rng.random(300), "n": np.asarray(4000), "hist": rng.integers(0, 9, (3, 7)).astype(np.int64),
            "flags": rng.random(5) < 0.5, "nonfinite_0": np.asarray(2, dtype=np.int32), "empty": np.zeros((0, 4)),
            "label": np.asarray("stationary"), "max": 7.5}


def test_round_trip_is_exact(tmp_path):
    path = tmp_path / "call0000-x" / f"s0-chunk000001-runs4000-seed7{mc.CHUNK_SUFFIX}"
    stats = _stats()
    mc._store(path, stats)
    back = mc._load(path)
    assert list(back) == list(stats)
    for k, v in stats.items():
        v = np.asarray(v)
        assert back[k].dtype == v.dtype and back[k].shape == v.shape and np.array_equal(back[k], v), k
        assert back[k].flags.writeable  # the sums add into them
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temporary file left


@pytest.mark.parametrize("cut", [0, 5, 20, -1])
def test_a_torn_or_foreign_file_reads_as_missing(tmp_path, cut):
    data = mc._dump_stats(_stats())
    path = tmp_path / f"c{mc.CHUNK_SUFFIX}"
    path.write_bytes(data[:cut] if cut else b"PK\x03\x04 an old npz")
    assert mc._load(path) is None
    assert mc._load(tmp_path / "absent.chunk") is None


def test_object_arrays_are_not_stored(tmp_path):
    path = tmp_path / f"c{mc.CHUNK_SUFFIX}"
    mc._store(path, {"x": np.array([object()], dtype=object)})
    assert not path.exists()


def test_stored_runs_counts_the_chunks_a_resume_reuses(tmp_path):
    """The interrupt message counts finished runs from the store (a worker stores a chunk before the parent's
    progress bar hears of it): the chunks' names, as _cache_path writes them, over every call."""
    from types import SimpleNamespace
    ex = SimpleNamespace(cache_dir=tmp_path)
    plan = mc.plan_chunks(runs=25_000, chunk=10_000, seed=7)
    for call, label in ((0, "mc"), (1, "sweep point 2")):
        for i in (0, 2):  # chunk 1 not finished
            mc._store(mc._cache_path(ex, call, label, plan[i]), _stats())
    (tmp_path / "call0000-mc" / "x.chunk.tmp123").write_bytes(b"torn")  # a temporary is no finished chunk
    assert mc.stored_runs(tmp_path) == 2 * (10_000 + 5_000)
    assert mc.stored_runs(tmp_path / "absent") == 0
