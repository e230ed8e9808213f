"""Starting netkf loads no library only a few analyses need: every ``netkf`` command and every forked worker
would pay it (cvxpy with the scipy.stats it loads: ~40 MB resident and ~1 s here; issue 20's 300 MB)."""

import subprocess
import sys

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
