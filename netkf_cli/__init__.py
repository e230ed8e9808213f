"""netkf — Kalman filtering over lossy, delaying and fading networks.

YAML scenario → pydantic Scenario → channel sampler → estimator recursion →
metrics / closed forms → tidy CSV + PNG + manifest.
"""

__version__ = "0.1.0"


def load(source, overrides=None):
    """Load and validate a scenario (YAML path, YAML text or dict): see :mod:`netkf_cli.api`."""
    from netkf_cli.api import load as _load

    return _load(source, overrides)


def run(scenario, **kw):
    """Run a scenario and return a :class:`netkf_cli.api.Result`: see :mod:`netkf_cli.api`."""
    from netkf_cli.api import run as _run

    return _run(scenario, **kw)
