"""References providers for a delay-buffer channel (Shi, Xie & Murray 2009), from plain values.

* :func:`expected_updates_reference` — E[MKF runs per step] of the buffered estimator (Prop. 3.1):
  ``1 + Σ_{j=1}^{D_max} (1 − Π_{i=j}^{D_max} (1 − f(i)))`` (:func:`netkf_cli.analysis.delay_exact.expected_updates`).
* :func:`buffer_probability_reference` — Pr[P_k ≤ M] at stationarity for each ``M`` of the metric: the
  certified exact probability and the bounds 1 − θ(k₁, D), 1 − θ(k₂, D) of Thm 3.8 (raw measurement packets).

A provider sees the channel as its ``model_dump()`` dict; :class:`DelayLaw` rebuilds the delay cdf of
eq. (3) from it (``delay: {kind: poisson | geometric | pmf}``, or ``bernoulli``: f(0) = arrival, the rest loss).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from netkf_cli.analysis import delay_bounds as db
from netkf_cli.analysis import delay_exact as dx
from netkf_cli.analysis.laws import poisson_cdf
from netkf_cli.core.errors import ConfigError
from netkf_cli.core.tolerances import DELAY_EXACT_TOL

UPDATES = "E[MKF runs per step], closed form (Prop. 3.1)"
EXACT = "exact Pr[P_k <= M] (certified)"
LOWER = "lower bound 1 - theta(k1, D) (Thm 3.8)"
UPPER = "upper bound 1 - theta(k2, D) (Thm 3.8)"


@dataclass(frozen=True)
class DelayLaw:
    """What the closed forms read of a delay channel: the delay cdf F (eq. 3), the buffer D, the keep rule."""

    law: dict
    D: int
    convention: str

    @classmethod
    def of(cls, channel: dict) -> "DelayLaw | None":
        """The channel's delay law, or None for a channel without one (no closed form applies)."""
        kind = channel.get("kind")
        if kind == "delay":
            return cls(dict(channel["delay"]), int(channel["buffer"]), str(channel.get("convention", db.DEFAULT_CONVENTION)))
        if kind == "bernoulli":
            return cls({"kind": "bernoulli", "arrival": float(channel["arrival"])}, 1, "delay_le_D")
        return None

    def cdf(self, i):
        i = np.asarray(i)
        k = self.law["kind"]
        if k == "poisson":
            return poisson_cdf(i, float(self.law["mean"]))
        if k == "geometric":
            p = float(self.law["p"])
            return np.where(i < 0, 0.0, 1.0 - (1.0 - p) ** (np.maximum(i, -1) + 1))
        if k == "pmf":
            c = np.concatenate([[0.0], np.cumsum(self.law["probs"])])
            return c[np.clip(i + 1, 0, len(self.law["probs"]))]
        if k == "bernoulli":
            return np.where(i < 0, 0.0, self.law["arrival"])
        raise ConfigError.at("channel.delay.kind", f"no delay cdf for {k!r}")


def _buffered_labels(point) -> list[str]:
    return [lab for e, lab in zip(point.estimators, point.labels) if e.get("kind") == "buffered"]


def expected_updates_reference(point) -> list[dict]:
    """Expected MKF runs per step of the buffered estimator on a delay channel (Shi 2009, Prop. 3.1)."""
    law = DelayLaw.of(point.channel)
    labs = _buffered_labels(point)
    if law is None or not labs:
        return []
    value = dx.expected_updates(law)
    return [dict(series=UPDATES, estimator=lab, quantity="updates", value=value) for lab in labs]


def buffer_probability_reference(point) -> list[dict]:
    """Stationary Pr[P_k ≤ M] of the buffered estimator: certified exact value and Thm 3.8 bounds (Shi 2009)."""
    law = DelayLaw.of(point.channel)
    labs = _buffered_labels(point)
    Ms = point.metric.get("M")
    if law is None or not labs or Ms is None:
        return []
    Ms = np.atleast_1d(np.asarray(Ms, dtype=float))
    s = point.system
    rows = []
    ex = dx.exact_probability(s, law, 1, Ms)
    for i, m in enumerate(Ms):
        lo = 1.0 - db.theta(db.k1(m, s, f"analysis.M[{i}]"), law.D, law.cdf, law.convention)
        hi = 1.0 - db.theta(db.k2(m, s, f"analysis.M[{i}]"), law.D, law.cdf, law.convention)
        for lab in labs:
            if ex.err[i] <= DELAY_EXACT_TOL and ex.upper[i] >= lo - DELAY_EXACT_TOL and ex.lower[i] <= hi + DELAY_EXACT_TOL:
                # certified, and inside Thm 3.8's bounds (a word's map that lost its precision can decide wrongly)
                rows.append(dict(series=EXACT, estimator=lab, quantity="filtered", M=float(m), value=float(ex.value[i])))
            rows += [dict(series=LOWER, estimator=lab, quantity="filtered", M=float(m), value=lo),
                     dict(series=UPPER, estimator=lab, quantity="filtered", M=float(m), value=hi)]
    return rows
