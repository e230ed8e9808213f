"""Shared fixtures-as-functions for the shi2009 tests: Example 3.10 and the Sec. 5.2 vehicle."""

import numpy as np

from netkf_cli.channels.bernoulli import BernoulliChannel
from netkf_cli.channels.delay import DelayChannel
from netkf_cli.core.system import LinearSystem


def scalar_system() -> LinearSystem:
    """Example 3.10: A = 1.4, C = 1, Q = 0.2, R = 0.5."""
    return LinearSystem.create(1.4, 1, 0.2, 0.5)


def vehicle_system() -> LinearSystem:
    """Sec. 5.2: constant-velocity vehicle, C = [I₂ 0] (Appendix B packets)."""
    A = np.array([[1, 0, 0.5, 0], [0, 1, 0, 0.5], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    C = np.hstack([np.eye(2), np.zeros((2, 2))])
    return LinearSystem.create(A, C, 0.01 * np.eye(4), 0.001 * np.eye(2))


def poisson(d: float, D: int, convention: str = "delay_le_D") -> DelayChannel:
    return DelayChannel(kind="delay", delay={"kind": "poisson", "mean": d}, buffer=D, convention=convention)


def pmf(probs, D: int, convention: str = "delay_le_D") -> DelayChannel:
    return DelayChannel(kind="delay", delay={"kind": "pmf", "probs": list(probs)}, buffer=D, convention=convention)


def bernoulli(gamma: float) -> BernoulliChannel:
    return BernoulliChannel(kind="bernoulli", arrival=gamma)
