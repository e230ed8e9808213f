"""``netkf mind``: the minimum receive-buffer length for Pr[P_k ≤ M] ≥ 1 − ε.

Raw measurements (Sec. 3.4): D_s = min{D : θ(k₁, D) ≤ ε} is sufficient, D_n = min{D : θ(k₂, D) ≤ ε}
is necessary (Thm 3.8). Smart sensor (Sec. 4): D* = min{D : θ(k₂, D) ≤ ε} is necessary and
sufficient (Thm 4.1). θ(k, D) stops decreasing at D = k − 1 (``delay_le_D``) or k (``delay_lt_D``):
if its floor exceeds ε no buffer can do it. A ``--D-max`` cap is another matter: a minimum above it is
reported as such, with its value (``reason``: ``above_D_max``, not ``theta_floor``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from netkf_cli.analysis import delay_bounds as db
from netkf_cli.channels.delay import CONVENTION_HELP, DEFAULT_CONVENTION, PoissonDelay, delay_label
from netkf_cli.core.errors import ConfigError
from netkf_cli.config.loader import load_scenario, locate
from netkf_cli.core.system import LinearSystem

EXAMPLE_310 = dict(A=1.4, C=1.0, Q=0.2, R=0.5)
DEFAULT_D = 5.0


def _num(x):
    if x is None:
        return None
    if isinstance(x, float) and math.isinf(x):
        return None
    return int(x) if float(x).is_integer() else float(x)


def one_minus(eps: float) -> str:
    """1 − ε as the verdict prints it: ``0.97`` for ε = 0.03, but ``1 − 1e-09`` where 6 digits would round it to 1."""
    text = f"{1 - eps:g}"
    return text if abs((1 - float(text)) - eps) <= 0.01 * eps else f"1 − {eps:g}"


def _mat(X: np.ndarray):
    X = np.asarray(X)
    return float(X.ravel()[0]) if X.size == 1 else X.tolist()


def _fmt(X) -> str:
    X = np.asarray(X)
    if X.size == 1:
        return f"{float(X.ravel()[0]):.4g}"
    return "[" + "; ".join(" ".join(f"{v:.3g}" for v in row) for row in X) + "]"


def _k(k) -> str:
    return "∞" if k is None or math.isinf(k) else str(int(k))


def _D(D, uncapped, D_max) -> str:
    """A minimum buffer as the report prints it: above ``--D-max`` is not the same as no finite D (θ's floor > ε)."""
    if D is not None:
        return str(D)
    if uncapped is not None:
        return f"none up to D_max = {D_max} ({uncapped} without the cap)"
    return "none (no finite D)"


@dataclass
class MindReport:
    sizing: db.BufferSizing
    system_label: str
    delay_label: str

    def as_json(self) -> dict:
        s = self.sizing
        return {
            "M": s.M, "eps": s.eps, "sensor": s.sensor, "convention": s.convention,
            "convention_meaning": CONVENTION_HELP[s.convention],
            "system": self.system_label, "delay": self.delay_label,
            "mbar": _mat(s.mbar), "pbar": _mat(s.pbar),
            "k1": _num(s.k1), "k2": _num(s.k2),
            "theta_floor_1": s.theta_floor_1, "theta_floor_2": s.theta_floor_2,
            "D_s": s.D_s, "D_n": s.D_n, "D_star": s.D_star, "D_max": s.D_max,
            "D_s_uncapped": s.D_s_uncapped, "D_n_uncapped": s.D_n_uncapped, "D_star_uncapped": s.D_star_uncapped,
            "feasible": s.feasible, "feasible_uncapped": s.feasible_uncapped, "reason": s.reason,
            "verdict": self.verdict(),
        }

    def verdict(self) -> str:
        """One paragraph: D_s / D_n (Thm 3.8) or D* (Thm 4.1) within ``--D-max``, else why not: the shortest
        buffer is longer than D_max, or θ(k, D → ∞) > ε leaves no finite D."""
        s = self.sizing
        req = f"Pr[P_k ≤ {s.M:g}] ≥ {one_minus(s.eps)}"
        if s.sensor == "smart":
            if s.D_star is not None:
                return (f"A buffer of D* = {s.D_star} is necessary and sufficient for {req} "
                        f"with a smart sensor (Thm 4.1).")
            if s.D_star_uncapped is not None:
                return (f"No buffer up to --D-max {s.D_max} meets the requirement: the shortest buffer that meets it is "
                        f"above the cap, D* = {s.D_star_uncapped} (necessary and sufficient for {req} with a smart "
                        f"sensor, Thm 4.1); raise --D-max to {s.D_star_uncapped}.")
            return (f"No buffer length meets the requirement: even D → ∞ leaves Pr[P_k > {s.M:g}] = θ(k2) = "
                    f"{s.theta_floor_2:.4g} > ε = {s.eps:g}; the smallest ε any buffer achieves is {s.theta_floor_2:.4g}.")
        between = ("Between the bounds, only the exact probability or a Monte Carlo (netkf run with a prob_vs_M "
                   "analysis) can tell.")
        if s.D_s is not None:
            return (f"A buffer of D = {s.D_s} guarantees {req} (sufficient, Thm 3.8); "
                    f"no buffer shorter than D_n = {s.D_n} can achieve it (necessary)."
                    + ("" if s.D_s == s.D_n else f" The minimum lies in [{s.D_n}, {s.D_s}]."))
        if s.D_s_uncapped is not None and s.D_n is not None:
            return (f"No buffer up to --D-max {s.D_max} is guaranteed to suffice: the sufficient bound needs "
                    f"D_s = {s.D_s_uncapped} (Thm 3.8; raise --D-max to {s.D_s_uncapped}). A buffer of at least "
                    f"D_n = {s.D_n} is necessary, so the minimum lies in [{s.D_n}, {s.D_s_uncapped}]. " + between)
        if s.D_s_uncapped is not None:
            return (f"No buffer up to --D-max {s.D_max} meets the requirement: the shortest buffer that meets it is "
                    f"above the cap. Without the cap, D = {s.D_s_uncapped} guarantees {req} (sufficient, Thm 3.8) "
                    f"and no buffer shorter than D_n = {s.D_n_uncapped} can achieve it (necessary)"
                    + ("" if s.D_s_uncapped == s.D_n_uncapped
                       else f"; the minimum lies in [{s.D_n_uncapped}, {s.D_s_uncapped}]")
                    + f". Raise --D-max to {s.D_s_uncapped}.")
        if s.D_n_uncapped is not None and s.D_n is None:
            return (f"No buffer length is guaranteed to suffice: even D → ∞ leaves the sufficient bound at θ(k1) = "
                    f"{s.theta_floor_1:.4g} > ε = {s.eps:g}. A buffer of at least D_n = {s.D_n_uncapped} is necessary, "
                    f"which is above --D-max {s.D_max}: no buffer up to the cap can achieve it. The smallest ε any "
                    f"buffer is guaranteed to meet is {s.theta_floor_1:.4g} "
                    f"(from D = {db.saturation_D(s.k1, s.convention)} on).")
        if s.D_n is not None:
            return (f"No buffer length is guaranteed to suffice: even D → ∞ leaves the sufficient bound at θ(k1) = "
                    f"{s.theta_floor_1:.4g} > ε = {s.eps:g}. A buffer of at least D_n = {s.D_n} is necessary; "
                    f"the smallest ε any buffer is guaranteed to meet is {s.theta_floor_1:.4g} "
                    f"(from D = {db.saturation_D(s.k1, s.convention)} on). " + between)
        sat = db.saturation_D(s.k1, s.convention)
        if s.theta_floor_1 == s.theta_floor_2:
            best = (f"Here k1 = k2, so the bounds coincide: the smallest ε any buffer achieves is "
                    f"{s.theta_floor_1:.4g}, reached from D = {sat} on.")
        else:
            best = (f"The smallest ε any buffer is guaranteed (sufficient bound) is {s.theta_floor_1:.4g}, reached "
                    f"from D = {sat} on; no buffer achieves ε below {s.theta_floor_2:.4g}.")
        return (f"No buffer length can meet the requirement: even D → ∞ leaves Pr[P_k > {s.M:g}] ≥ θ(k2) = "
                f"{s.theta_floor_2:.4g} > ε = {s.eps:g} (the necessary condition of Thm 3.8 fails). " + best)

    def text(self) -> str:
        s = self.sizing
        lines = [
            f"Buffer sizing for Pr[P_k ≤ M] ≥ 1 − ε   (Shi, Xie & Murray 2009, {'Sec. 3.4' if s.sensor == 'raw' else 'Sec. 4'})",
            f"  system      {self.system_label}",
            f"  delay       {self.delay_label}",
            f"  convention  {s.convention}: {CONVENTION_HELP[s.convention]}",
            f"  sensor      {'raw measurements (y_k sent)' if s.sensor == 'raw' else 'smart sensor (its estimate sent)'}",
            f"  M = {s.M:g}{' (·I)' if np.asarray(s.pbar).size > 1 else ''}, ε = {s.eps:g}",
            "",
            f"  M̄ = {_fmt(s.mbar)}    P̄ = {_fmt(s.pbar)}",
        ]
        if s.sensor == "raw":
            lines += [
                f"  k1(M) = {_k(s.k1)}    k2(M) = {_k(s.k2)}",
                f"  floor of θ as D → ∞:  θ(k1) = {s.theta_floor_1:.4g}   θ(k2) = {s.theta_floor_2:.4g}",
                f"  D_s (sufficient) = {_D(s.D_s, s.D_s_uncapped, s.D_max)}    "
                f"D_n (necessary) = {_D(s.D_n, s.D_n_uncapped, s.D_max)}",
            ]
        else:
            lines += [
                f"  k2(M) = {_k(s.k2)}",
                f"  floor of θ as D → ∞:  θ(k2) = {s.theta_floor_2:.4g}",
                f"  D* (necessary and sufficient) = {_D(s.D_star, s.D_star_uncapped, s.D_max)}",
            ]
        lines += ["", "Verdict: " + self.verdict()]
        return "\n".join(lines)


MAX_D = 1e4
"""Largest Poisson mean delay accepted by ``--d`` (θ is 1 to machine precision long before)."""


def check_arguments(*, M: float, eps: float, d: float | None) -> None:
    """Refuse non-finite or out-of-range ``--M``, ``--eps``, ``--d`` with one message each."""
    problems = []
    for opt, v in (("--M", M), ("--eps", eps), ("--d", d)):
        if v is not None and not math.isfinite(v):
            problems.append(ConfigError.at(opt, f"must be a finite number, got {v}").problems[0])
    if math.isfinite(eps) and not 0.0 <= eps <= 1.0:
        problems.append(ConfigError.at("--eps", f"must be a probability in [0, 1], got {eps:g}").problems[0])
    if d is not None and math.isfinite(d) and not 0.0 <= d <= MAX_D:
        problems.append(ConfigError.at("--d", f"must be a mean delay in [0, {MAX_D:g}] steps, got {d:g}").problems[0])
    if problems:
        raise ConfigError(problems)


def mind_report(*, M: float, eps: float, config: Path | None, d: float | None, sensor: str,
                convention: str | None, D_max: int | None) -> MindReport:
    """Size the buffer for the default Example 3.10 or a scenario's system and delay channel."""
    check_arguments(M=M, eps=eps, d=d)
    if config is not None:
        sc = load_scenario(config)
        try:
            s = sc.linear_system()
            ch = sc.require_channel("delay", "bernoulli")
        except ConfigError as exc:
            raise locate(exc, config) from None
        cdf, conv = ch.cdf, convention or ch.convention
        sys_label, delay = f"from {config}", delay_label(ch)
    else:
        s = LinearSystem.create(**EXAMPLE_310)
        dist = PoissonDelay(mean=DEFAULT_D if d is None else d)
        cdf, conv = dist.cdf, convention or DEFAULT_CONVENTION
        sys_label = "Example 3.10: A = 1.4, C = 1, Q = 0.2, R = 0.5"
        delay = f"Poisson, mean d = {dist.mean:g}" + (" (default: the mean the printed θ values imply)" if d is None else "")
    sizing = db.size_buffer(M, eps, s, cdf, conv, sensor=sensor, D_max=D_max, path="--M")
    return MindReport(sizing, sys_label, delay)
