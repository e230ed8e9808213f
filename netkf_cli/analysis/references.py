"""Closed forms a generic metric draws beside its Monte Carlo (``analysis.references: [name, …]``).

``REGISTRY`` maps a name to ``"module:function"`` (resolved when used, so this module imports no
closed form and the closed forms import nothing above them). A provider is ``fn(point) -> list[dict]``:
``point`` is a :class:`Point` of plain values (the system's matrices, the channel's, estimators' and
metric's and the Monte Carlo block's fields as dicts, the labels of the estimators, the ``over``
coordinates); each dict returned
is one row with ``series`` (what it is, e.g. ``"upper bound, eq. 13"``), ``value``, and optionally
``estimator`` (one of ``point.labels``; default every estimator: ""), ``quantity``, ``M`` and ``k``.
The metric marks them ``source = closed_form`` with no standard error.
"""

from __future__ import annotations

import importlib
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

REGISTRY: dict[str, str] = {
    "fading_theorem4_quadrature": "netkf_cli.analysis.fading:theorem4_quadrature_rows",
    "fading_theorem4": "netkf_cli.analysis.fading:theorem4",
    "fading_lemma5": "netkf_cli.analysis.fading:lemma5_lower_bound",
    "fading_scenario2_exact": "netkf_cli.analysis.fading:scenario2_exact",
    "fusion_bounds": "netkf_cli.analysis.fusion_bounds:fusion_bounds_reference",
    "fusion_centralized": "netkf_cli.analysis.fusion_bounds:centralized_reference",
    "kf_bernoulli_bounds": "netkf_cli.analysis.references:kf_bernoulli_bounds",
    "shi_buffer_probability": "netkf_cli.analysis.delay_references:buffer_probability_reference",
    "shi_expected_updates": "netkf_cli.analysis.delay_references:expected_updates_reference",
    "leong_exact": "netkf_cli.analysis.smoothing:reference_exact",
    "leong_eq8": "netkf_cli.analysis.smoothing:reference_eq8",
    "leong_lemma1": "netkf_cli.analysis.smoothing:reference_lemma1",
    "leong_retransmission_g": "netkf_cli.analysis.smoothing:reference_retransmission_g",
}


@dataclass(frozen=True)
class Point:
    """What a provider sees of one scenario point (plain values only)."""

    system: Any  # a LinearSystem: A, C, Q, R, P0 (None = steady state P̄) as arrays
    channel: dict
    estimators: list[dict]
    labels: list[str]
    quantities: list[str]
    metric: dict
    coords: dict = field(default_factory=dict)
    montecarlo: dict = field(default_factory=dict)  # horizon, burn_in …: a provider may give finite-time values


def describe() -> dict[str, str]:
    """Name → first docstring line of every provider (for ``netkf list``)."""
    return {name: (resolve(name).__doc__ or "").strip().splitlines()[0] for name in sorted(REGISTRY)}


def resolve(name: str):
    mod, fn = REGISTRY[name].split(":")
    return getattr(importlib.import_module(mod), fn)


def applies_to(name: str) -> str:
    """What the closed form ``name`` is for: the first sentence of its provider's docstring (where it gives no rows,
    the scenario is not one of those)."""
    first = (resolve(name).__doc__ or "").strip().split("\n")[0].strip().rstrip(".")
    return f"it gives {first}" if first else "it does not apply here"


def evaluate(name: str, point: Point) -> list[dict]:
    """The provider's rows, checked: a dict with a finite-or-inf numeric ``value`` and a ``series`` each."""
    rows = list(resolve(name)(point))
    for r in rows:
        if "series" not in r or "value" not in r:
            raise ValueError(f"reference {name!r} returned a row without series/value: {r}")
        r["value"] = float(r["value"])
        if math.isnan(r["value"]):
            raise ValueError(f"reference {name!r} returned NaN for {r['series']}")
        r.setdefault("estimator", "")
    return rows


def kf_bernoulli_bounds(point: Point) -> list[dict]:
    """Sinopoli et al. 2004 (Thm 4) bounds on the stationary E[P_{k+1|k}] of a scalar KF, i.i.d. arrivals λ.

    Lower: S̄ = q / (1 − (1 − λ) a²), the fixed point of S = (1 − λ) a² S + q; upper: V̄, the fixed
    point of the modified Riccati map g_λ(V) = a² V + q − λ a² c² V² / (c² V + r) (both ∞ when
    (1 − λ) a² ≥ 1, at or below the critical arrival rate)."""
    A, C, Q, R = (np.atleast_2d(np.asarray(x, dtype=float)) for x in (point.system.A, point.system.C,
                                                                       point.system.Q, point.system.R))
    if A.shape != (1, 1) or C.shape != (1, 1) or "arrival" not in point.channel:
        return []
    lam = float(point.channel["arrival"])
    a, c, q, r = float(A[0, 0]), float(C[0, 0]), float(Q[0, 0]), float(R[0, 0])
    names = ("lower bound S̄ (Sinopoli et al. 2004, Thm 4)", "upper bound V̄, modified Riccati fixed point (Thm 4)")
    if (1 - lam) * a * a >= 1:
        return [dict(series=n, value=math.inf, quantity="predicted") for n in names]
    lower = q / (1 - (1 - lam) * a * a)
    v = lower
    for _ in range(1_000_000):  # monotone convergence from below (g_λ is increasing and concave)
        new = a * a * v + q - lam * a * a * c * c * v * v / (c * c * v + r)
        if abs(new - v) <= 1e-15 * max(1.0, abs(new)):
            v = new
            break
        v = new
    return [dict(series=names[0], value=lower, quantity="predicted"),
            dict(series=names[1], value=v, quantity="predicted")]
