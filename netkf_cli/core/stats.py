"""One statistics module: means and standard errors from additive sums, Wilson intervals, the
heavy-tail and rare-event rules. Every metric and recipe uses these (core layer: numpy only).

Monte Carlo statistics in netkf are additive over chunks (sums of x, x², x³, x⁴ per step and
estimator, or of weighted samples w·x for a variance-reduced estimator), so the same functions
serve every executor and chunking.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from netkf_cli.core.tolerances import HEAVY_TAIL_RSE, RARE_EVENT_FRACTION

EPS = np.finfo(float).eps


def mean_se(s1, s2, n):
    """Sample mean and its standard error √(s²/n) (s² the unbiased sample variance) from Σx, Σx², n."""
    s1, s2 = np.asarray(s1, dtype=float), np.asarray(s2, dtype=float)
    n = np.maximum(np.asarray(n, dtype=float), 1.0)
    with np.errstate(invalid="ignore", over="ignore"):
        mean = s1 / n
        var = np.maximum(s2 / n - mean * mean, 0.0) * n / np.maximum(n - 1.0, 1.0)
        var = np.where(_degenerate(var, mean), 0.0, var)
        return mean, np.sqrt(var / n)


def _degenerate(var, mean):
    """The variance from raw sums is below its own round-off (≈ 100 ε · mean²): every sample is the same
    number up to rounding (e.g. a perfect channel), so the variance is 0, not noise."""
    with np.errstate(invalid="ignore", over="ignore"):
        return var <= 100.0 * EPS * np.asarray(mean, dtype=float) ** 2


def proportion_stderr(p, n) -> np.ndarray:
    """Standard error √(p(1−p)/n) of an empirical proportion over n independent samples."""
    p = np.asarray(p, dtype=float)
    return np.sqrt(np.clip(p * (1 - p), 0, None) / n)


def wilson_interval(successes, n, z: float = 1.96) -> tuple[np.ndarray, np.ndarray]:
    """Wilson score interval for a binomial proportion (never of zero width, also at p̂ ∈ {0, 1}).

    p̃ = (p̂ + z²/2n) / (1 + z²/n),  half-width = z/(1 + z²/n) · √(p̂(1−p̂)/n + z²/4n²).

    The interval contains p̂ (exactly: at p̂ = 1 the upper end is 1, at p̂ = 0 the lower end 0); the ends are
    clamped to p̂ so that rounding cannot put p̂ outside it (p̃ + half came out 1 − 2⁻⁵³ at p̂ = 1, and a
    figure's error bar hi − p̂ negative).
    """
    k = np.asarray(successes, dtype=float)
    n = np.asarray(n, dtype=float)
    p = k / n
    z2 = z * z
    denom = 1.0 + z2 / n
    centre = (p + z2 / (2 * n)) / denom
    half = z / denom * np.sqrt(np.clip(p * (1 - p), 0, None) / n + z2 / (4 * n * n))
    return np.clip(np.minimum(centre - half, p), 0.0, 1.0), np.clip(np.maximum(centre + half, p), 0.0, 1.0)


def central4(s1, s2, s3, s4, n):
    """Fourth central moment from raw sums Σx, Σx², Σx³, Σx⁴ over n samples."""
    with np.errstate(invalid="ignore", over="ignore"):
        mu = s1 / n
        return s4 / n - 4 * mu * s3 / n + 6 * mu**2 * s2 / n - 3 * mu**4


def heavy_tail_flag(s1, s2, s3, s4, n, nonfinite):
    """(variance, relative s.e. of the variance, heavy?) — see :data:`netkf_cli.core.tolerances.HEAVY_TAIL_RSE`.

    A sample whose variance is below its own round-off (every run the same number, e.g. a perfect
    channel) is not heavy-tailed: its relative s.e. is 0.
    """
    n = np.maximum(n, 1)
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        mu = s1 / n
        var = np.maximum(s2 / n - mu**2, 0.0)
        degenerate = _degenerate(var, mu)
        rse = np.sqrt(np.maximum(central4(s1, s2, s3, s4, n) - var**2, 0.0) / n) / np.where(var > 0, var, np.nan)
        rse = np.where((var > 0) & ~degenerate, rse, 0.0)
        var = np.where(degenerate, 0.0, var)
        heavy = (np.asarray(nonfinite) > 0) | ~np.isfinite(rse) | (rse > HEAVY_TAIL_RSE)
    return var, rse, heavy


def rare_event_flag(s1, max_x, n):
    """True where more than RARE_EVENT_FRACTION of Σx comes from the single largest sample (n ≥ 2):
    the mean then rests on one event of probability ~1/n (non-negative samples, e.g. tr P)."""
    s1, max_x = np.asarray(s1, dtype=float), np.asarray(max_x, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(s1 > 0, max_x / s1, 0.0)
    return (np.asarray(n) >= 2) & (frac > RARE_EVENT_FRACTION)


FLAG_REASONS = {
    "nonfinite": "a run diverged (non-finite)",
    "sample": "the sample's variance is too uncertain (relative s.e. of the sample variance above HEAVY_TAIL_RSE)",
    "theory": "the theoretical tail exponent says E[(tr P)^2] is infinite (manifest: heavy_tail_by_theory)",
    "rare_event": "one run carries more than half of the sum",
}
"""The codes of a CSV's ``flag_reason`` column (joined by ``+``; empty when the mean is reliable)."""


def flag_reason(*, nonfinite=0, sample=False, theory=False, rare=False) -> str:
    """Why a mean is flagged: the :data:`FLAG_REASONS` codes that apply, joined by ``+`` ("" = reliable).
    ``sample`` is the heavy-tail rule's sample part (what :func:`heavy_tail_flag` says beyond non-finite runs)."""
    codes = [c for c, on in (("nonfinite", int(nonfinite) > 0), ("sample", bool(sample) and int(nonfinite) == 0),
                             ("theory", bool(theory)), ("rare_event", bool(rare))) if on]
    return "+".join(codes)


@dataclass
class MeanSummary:
    """E[·] over runs with its standard error and reliability diagnostics (``unreliable`` = heavy-tailed
    or rare-event dominated or non-finite: not drawn as a result)."""

    mean: np.ndarray
    stderr: np.ndarray
    n: int
    nonfinite: np.ndarray
    heavy_tail: np.ndarray
    rare_event: np.ndarray

    @property
    def unreliable(self) -> np.ndarray:
        return self.heavy_tail | self.rare_event
