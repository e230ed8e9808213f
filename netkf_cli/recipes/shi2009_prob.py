"""Shared helpers of the Shi, Xie & Murray 2009 recipes (mean delay d, M̄ with a clear message, packet span).

Figs 5–9 (Pr[P_k ≤ M] against M) are configs of the generic ``distribution`` metric
(:mod:`netkf_cli.metrics.distribution`), which attaches Thm 3.8, Thm 4.1 and the certified
exact probability where their assumptions hold; the buffer trade-off (expected MKF runs per
step) is :mod:`netkf_cli.recipes.shi2009_updates`.
"""

from __future__ import annotations

import numpy as np

from netkf_cli.linalg import riccati
from netkf_cli.core.errors import ConfigError
from netkf_cli.estimators.buffered import packet_span
from netkf_cli.metrics.common import MGrid, m_values  # noqa: F401 - re-exported for older imports

SHORT_CONVENTION = {"delay_le_D": "kept iff d_k ≤ D", "delay_lt_D": "kept iff d_k < D"}


def mean_delay(channel) -> float:
    """d: the mean delay (Poisson mean; for other pmfs the mean, ∞ with loss; bernoulli: NaN)."""
    if channel.kind == "bernoulli":
        return float("nan")
    dist = channel.delay
    if dist.kind == "poisson":
        return float(dist.mean)
    if dist.kind == "geometric":
        return (1 - dist.p) / dist.p
    if dist.loss > 0:
        return float("inf")
    return float(np.dot(np.arange(len(dist.probs)), dist.probs))


def _span(scenario, s) -> int:
    es = scenario.estimator
    packet = es.packet if (es is not None and es.kind == "buffered") else "auto"
    return packet_span(s, packet)


def _mbar_or_error(s):
    try:
        return riccati.mbar(s)
    except ConfigError as exc:
        raise ConfigError.at(
            "estimator.kind", "the buffered (raw measurement) sensor needs M̄ (Thm 3.8): " + exc.problems[0].message
        ) from None
