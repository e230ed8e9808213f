"""netkf's numba cache is kept per state of its sources (netkf_cli/__init__.py): numba checks a cached function
against its own file only, and a kernel inlining kalman_numba's primitives kept the old ones when only
kalman_numba.py changed (found when the rescue's singular-prior check did not reach the smoother's kernel)."""

import os
import subprocess
import sys
import time

import pytest

import netkf_cli


def test_the_folder_follows_every_source_file(tmp_path):
    pkg, root = tmp_path / "pkg", tmp_path / "cache"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "a.py").write_text("import numba\n")
    (pkg / "sub" / "b.py").write_text("import numba as nb  # primitives\n")
    (pkg / "c.py").write_text("z = 3\n")  # no compiled code
    first = netkf_cli._numba_cache_dir(pkg, root)
    assert first and os.path.isdir(first) and netkf_cli._numba_cache_dir(pkg, root) == first
    (pkg / "c.py").write_text("z = 30\n")  # a module without compiled code: the same kernels
    assert netkf_cli._numba_cache_dir(pkg, root) == first
    (pkg / "sub" / "b.py").write_text("import numba as nb  # primitives, changed\n")  # what a kernel may inline
    second = netkf_cli._numba_cache_dir(pkg, root)
    assert second != first and os.path.isdir(second)


def test_only_the_newest_folders_are_kept(tmp_path):
    pkg, root = tmp_path / "pkg", tmp_path / "cache"
    pkg.mkdir()
    made = []
    for i in range(5):
        (pkg / "a.py").write_text("import numba  # " + "1" * (i + 1) + "\n")
        made.append(netkf_cli._numba_cache_dir(pkg, root, keep=3))
        t = time.time() - 100 + i
        os.utime(made[-1], (t, t))
    assert sorted(os.listdir(root)) == sorted(os.path.basename(d) for d in made[-3:])


def test_numba_uses_it_and_a_users_setting_wins(tmp_path):
    pytest.importorskip("numba")
    code = "import netkf_cli, numba.core.config as c, os; print(c.CACHE_DIR == os.environ['NUMBA_CACHE_DIR'], c.CACHE_DIR)"
    env = {**os.environ, "NETKF_NUMBA_CACHE": str(tmp_path / "n")}
    env.pop("NUMBA_CACHE_DIR", None)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout.split()
    assert out[0] == "True" and out[1].startswith(str(tmp_path / "n"))
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "mine")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout.split()
    assert out == ["True", str(tmp_path / "mine")]
