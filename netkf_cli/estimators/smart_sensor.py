"""Sensor with computation capability (Shi, Xie & Murray 2009, Sec. 4, Fig. 4, Thm 4.1).

The sensor runs its own Kalman filter (in steady state, P_k^s = P̄) and sends x̂_k^s. The remote
estimator uses the most recent estimate it has received and kept:

    N_k = min{t ≥ 0 : γ_{k−t} = 1}   (eq. 7),      x̂_k = A^{N_k} x̂^s_{k−N_k},   P_k = h^{N_k}(P̄).

So Pr[P_k ≤ M] = Pr[N_k < k₂(M)] = 1 − θ(k₂, D) (Thm 4.1, eq. 11). The Monte Carlo below
draws N_k from the delays and evaluates P_k = h^{N_k}(P̄) (it does not use k₂).
"""

from __future__ import annotations

from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from netkf_cli import riccati
from netkf_cli.channels.delay import max_kept_delay
from netkf_cli.estimators.buffered import leq_threshold, single_link, trace_delays
from netkf_cli.spec import EstimatorModel
from netkf_cli.system import LinearSystem

H_POWER_MAX = 100_000


class SmartSensorEstimator(EstimatorModel):
    """``kind: smart_sensor`` — the sensor sends its steady-state estimate x̂_k^s (Sec. 4)."""

    accepts: ClassVar[frozenset[str]] = frozenset({"delay", "arrival"})
    quantity: ClassVar[str] = "P_{k|k}"

    kind: Literal["smart_sensor"] = Field(description="the sensor sends its own steady-state estimate (Shi 2009, Sec. 4)")

    def check(self, system: LinearSystem, channel) -> None:
        """Needs P̄ (the sensor's steady-state filter): (A, C) detectable, (A, √Q) stabilizable; and a
        single link."""
        single_link(channel, "smart_sensor")
        riccati.pbar(system)

    def covariances(self, system: LinearSystem, trace, steps):
        """Yield (k, P_k (n, n, runs)): P_k = h^{N_k}(P̄) (Sec. 4), N_k from the time-k view (eq. 7).

        Packet s is kept by k iff d_s ≤ min(k − s, D_max) (``meta['buffer']``, ``meta['convention']``;
        no buffer in meta: every delay is kept; a pure-loss trace: arrival = delay 0). Before any
        packet is kept, the remote estimator predicts from its prior: P_k = h^k(P0) (P0 = P̄ when
        ``steady``). An overflowed hᵗ is ∞ in every entry (P_k ≰ M for every M).
        """
        yield from smart_covariances(system, trace, steps)


def _h_table(s: LinearSystem, X0: np.ndarray, t_max: int) -> np.ndarray:
    """hᵗ(X0) for t = 0..t_max, shape (t_max + 1, n, n); all-∞ once an iterate is not finite."""
    out = np.empty((t_max + 1, s.n, s.n))
    X = np.asarray(X0, dtype=float)
    for t in range(t_max + 1):
        if not np.all(np.isfinite(X)):
            out[t:] = np.inf
            break
        out[t] = X
        with np.errstate(over="ignore", invalid="ignore"):
            X = riccati.h(X, s)
    return out


def smart_covariances(s: LinearSystem, trace, steps):
    """Generator behind :meth:`SmartSensorEstimator.covariances`."""
    T, runs = trace.horizon, trace.runs
    d = trace_delays(trace).astype(np.int64)
    D = trace.meta.get("buffer")
    Dmax = T if D is None else max_kept_delay(int(D), trace.meta.get("convention", "delay_le_D"))
    Pbar = riccati.pbar(s)
    H = _h_table(s, Pbar, T)
    H0 = H if s.P0 is None else _h_table(s, s.P0, T)
    for k in sorted(int(k) for k in steps):
        if not 1 <= k <= T:
            raise ValueError(f"steps must lie in 1..{T}, got {k}")
        age = np.arange(k)[:, None]  # age t of packet s = k − t
        kept = d[k - 1::-1] <= np.minimum(age, Dmax)  # (k, runs), row t = packet k − t
        any_kept = kept.any(axis=0)
        N = np.where(any_kept, np.argmax(kept, axis=0), 0)
        P = np.where(any_kept[:, None, None], H[N], H0[k])
        yield k, np.ascontiguousarray(P.transpose(1, 2, 0))


def sample_N(rng: np.random.Generator, runs: int, channel) -> np.ndarray:
    """N_k (eq. 7) per run, int64 (a huge value when no packet is ever kept).

    The packet of age i is kept by k with probability F(min(i, D_max)), independently over i, so
    Pr[N_k ≥ t] = θ(t, D) = ∏_{i<t} (1 − F(min(i, D_max))) (eq. 8). Inverse transform: one uniform
    u per run, N_k = #{t ∈ 1..D_max+1 : u < θ(t, D)} (exact), and past the buffer (N_k = D_max + 1)
    the remainder is geometric with success probability F(D_max). O(D_max + runs·log D_max) —
    linear in the buffer length (the former loop drew D_max + 1 uniforms per run).
    """
    Dmax = max_kept_delay(channel.D, channel.convention)
    F = np.asarray(channel.cdf(np.arange(Dmax + 1)), dtype=float).reshape(Dmax + 1)
    th = np.cumprod(1.0 - F)  # th[t − 1] = θ(t, D), t = 1..Dmax+1 (non-increasing)
    u = rng.random(runs)
    N = (len(th) - np.searchsorted(th[::-1], u, side="right")).astype(np.int64)  # #{t : θ(t) > u}
    left = N == Dmax + 1
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
                "nonfinite": np.int64(np.count_nonzero(np.isnan(lam))),
                "sum_N": float(Nf.sum()), "sumsq_N": float((Nf**2).sum())}
