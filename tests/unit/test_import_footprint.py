"""Starting netkf loads no library only a few analyses need: every ``netkf`` command and every forked worker
would pay it (cvxpy with the scipy.stats it loads: ~40 MB resident and ~1 s here; issue 20's 300 MB)."""

import subprocess
from pathlib import Path
import sys

import pytest

HEAVY = ("cvxpy", "scipy.stats", "clarabel")


def test_cli_import_loads_no_cvxpy_or_scipy_stats():
    code = ("import sys, netkf_cli.app.cli; "
            f"print(','.join(m for m in {HEAVY!r} if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "", f"importing netkf_cli.app.cli loaded {out}: import it where it is used"


def test_the_critical_lmi_loads_clarabel_and_not_cvxpy():
    """The lazy import is not a missing one: solving Sinopoli's LMI loads Clarabel, and (netkf's own conic form,
    netkf_cli.linalg.sdp) not cvxpy."""
    code = ("import sys, numpy as np; from netkf_cli.analysis.critical import _SinopoliLMI as L; "
            "t, st, cert = L(np.array([[1.2]]), np.array([[1.0]])).margin(0.5); "
            "print('clarabel' in sys.modules, 'cvxpy' in sys.modules, st, cert)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "True False optimal True"


def test_pandas_loads_when_a_table_is_built_not_before():
    """pandas (40 MB resident) is netkf_cli.core.lazy's proxy: starting netkf does not load it, the first
    ``pd.<name>`` does, and the proxy then is the module's namespace (the same objects, not copies)."""
    code = ("import sys, netkf_cli.app.cli, netkf_cli.metrics.time_average as ta; before = 'pandas' in sys.modules; "
            "df = ta.pd.DataFrame({'a': [1.0]}); import pandas; "
            "print(before, 'pandas' in sys.modules, ta.pd.DataFrame is pandas.DataFrame, type(df) is pandas.DataFrame)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "False True True True"


def test_a_one_point_run_forks_its_worker_and_computes_its_chunks_without_pandas(tmp_path):
    """The point of the lazy proxy (issue 20's 300 MB): a forked worker shares nothing it was not given, and
    pandas loaded in the parent before the fork or during the chunks was 40 MB more at the run's peak. Here
    the parent says, at the fork and at the end of every chunk it computed, whether pandas was loaded."""
    from netkf_cli.runtime.montecarlo import usable_cores

    if usable_cores() < 2:
        pytest.skip("--jobs 2 runs serially on one core: no fork to check")
    cfg = Path(__file__).resolve().parents[2] / "configs" / "markov" / "example1.yaml"
    code = f"""
import os, sys
seen = []
os.register_at_fork(before=lambda: seen.append(('fork', 'pandas' in sys.modules)))
import netkf_cli.runtime.montecarlo as mc
chunk = mc.run_chunk
def spy(kernel, c):
    out = chunk(kernel, c)
    seen.append(('chunk', 'pandas' in sys.modules))
    return out
mc.run_chunk = spy
from netkf_cli.app.runner import run_scenario_file
run_scenario_file({str(cfg)!r}, out_dir={str(tmp_path / 'out')!r}, runs=400, force=True, executor='process', jobs=2,
                  overrides={{'montecarlo': {{'horizon': 20, 'burn_in': 10, 'chunk': 100}}}})
print(seen, 'pandas' in sys.modules)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-3000:]
    seen, loaded = out.stdout.strip().rsplit(" ", 1)
    assert loaded == "True"  # the tables were built
    assert "('fork', False)" in seen and "('chunk', False)" in seen and "True)" not in seen, seen


def test_a_command_freezes_its_objects_at_exit():
    """The interpreter's last garbage collection skips what a finished command is about to free (cli.NetkfGroup
    registers gc.freeze at exit): an exit handler registered before netkf's runs after it and sees a frozen heap."""
    code = ("import atexit, gc, sys; atexit.register(lambda: print('frozen', gc.get_freeze_count() > 0)); "
            "from netkf_cli.app.cli import app; sys.argv = ['netkf', 'list']; app()")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "frozen True"
