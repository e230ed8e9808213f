"""netkf — Kalman filtering over lossy, delaying and fading networks.

YAML scenario → pydantic Scenario → channel sampler → estimator recursion →
metrics / closed forms → tidy CSV + PNG + manifest.
"""

__version__ = "0.1.0"
