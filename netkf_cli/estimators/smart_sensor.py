"""Sensor with computation capability (Shi, Xie & Murray 2009, Sec. 4, Fig. 4, Thm 4.1).

The sensor runs its own Kalman filter (in steady state, P_k^s = P̄) and sends x̂_k^s. The remote
estimator uses the most recent estimate it has received and kept:

    N_k = min{t ≥ 0 : γ_{k−t} = 1}   (eq. 7),      x̂_k = A^{N_k} x̂^s_{k−N_k},   P_k = h^{N_k}(P̄).

So Pr[P_k ≤ M] = Pr[N_k < k₂(M)] = 1 − θ(k₂, D) (Thm 4.1, eq. 11). The Monte Carlo below
draws N_k from the delays and evaluates P_k = h^{N_k}(P̄) (it does not use k₂).
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from netkf_cli import riccati
from netkf_cli.channels.delay import max_kept_delay
from netkf_cli.estimators.buffered import leq_threshold
from netkf_cli.spec import EstimatorModel
from netkf_cli.system import LinearSystem

H_POWER_MAX = 100_000


class SmartSensorEstimator(EstimatorModel):
    """``kind: smart_sensor`` — the sensor sends its steady-state estimate x̂_k^s (Sec. 4)."""

    kind: Literal["smart_sensor"]


def sample_N(rng: np.random.Generator, runs: int, channel) -> np.ndarray:
    """N_k (eq. 7) per run, int64 (a huge value when no packet is ever kept).

    Packets of age i = 0..D_max are kept by k iff u_i < F(i) (inverse-CDF delays); a packet older
    than D_max is kept iff its delay is ≤ D_max, probability F(D_max), independently, so past the
    buffer N_k − (D_max + 1) is geometric (failures before the first success).
    """
    Dmax = max_kept_delay(channel.D, channel.convention)
    F = np.asarray(channel.cdf(np.arange(Dmax + 1)), dtype=float).reshape(Dmax + 1)
    N = np.full(runs, -1, dtype=np.int64)
    for i in range(Dmax + 1):
        hit = (rng.random(runs) < F[i]) & (N < 0)
        N[hit] = i
    left = N < 0
    p = float(F[Dmax])
    if p > 0:
        N[left] = Dmax + 1 + (rng.geometric(p, size=int(left.sum())) - 1)
    else:
        N[left] = np.iinfo(np.int64).max // 2
    return N


def h_power_lam_max(s: LinearSystem, t_max: int, X0: np.ndarray | None = None) -> np.ndarray:
    """λ_max(hᵗ(X0)) for t = 0..t_max (X0 = P̄ by default); ∞ once the iterate overflows."""
    X = riccati.pbar(s) if X0 is None else np.asarray(X0, dtype=float)
    out = np.empty(t_max + 1)
    for t in range(t_max + 1):
        if not np.all(np.isfinite(X)):
            out[t:] = np.inf
            break
        out[t] = np.linalg.eigvalsh(X)[-1]
        with np.errstate(over="ignore", invalid="ignore"):
            X = riccati.h(X, s)
    return out


def smart_mc_kernel(s: LinearSystem, channel, M_grid):
    """Kernel for ``run_chunked``: P_k = h^{N_k}(P̄) per run; counts of P_k ≤ M_j·I and Σ N_k (picklable)."""
    return SmartMCKernel(s, channel, M_grid)


class SmartMCKernel:
    """Picklable kernel ``(rng, runs) -> stats`` (see :func:`smart_mc_kernel`)."""

    def __init__(self, s: LinearSystem, channel, M_grid):
        self.s, self.channel = s, channel
        self.thr = leq_threshold(np.asarray(M_grid, dtype=float))
        self.lam_tab = h_power_lam_max(s, 64)

    def lam_of(self, N: np.ndarray) -> np.ndarray:
        """λ_max(h^N(P̄)); beyond H_POWER_MAX the last value (converged for stable A, ∞ for unstable A)."""
        need = int(min(N.max(initial=0), H_POWER_MAX))
        if need >= len(self.lam_tab):
            self.lam_tab = h_power_lam_max(self.s, max(need, 2 * len(self.lam_tab)))
        tab = self.lam_tab
        return np.where(N < len(tab), tab[np.minimum(N, len(tab) - 1)], tab[-1])

    def __call__(self, rng: np.random.Generator, runs: int):
        N = sample_N(rng, runs, self.channel)
        lam = self.lam_of(N)
        count = np.count_nonzero(lam[:, None] <= self.thr[None, :], axis=0)
        Nf = np.minimum(N, H_POWER_MAX).astype(float)
        return {"count_leq": count.astype(np.int64), "n": np.int64(runs),
                "overflow": np.int64(np.count_nonzero(~np.isfinite(lam))),
                "sum_N": float(Nf.sum()), "sumsq_N": float((Nf**2).sum())}
