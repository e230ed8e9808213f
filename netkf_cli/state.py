"""State-level simulation: the true state x_k and the measurements behind a channel trace.

Most metrics need only the covariances P_k (they depend on the arrival history alone, design.md
"covariance-only mode"). A consistency check (NEES) and the trajectory figures need the state
itself: this module draws, for the runs of one chunk (vectorized over runs, run axis innermost,
time-major like :class:`netkf_cli.trace.Trace`)

    x_0 ~ N(0, P_{0|0}),   x_{k+1} = A x_k + w_k,   y_k = C x_k + v_k,   [w_k; v_k] ~ N(0, [[Q, S], [Sᵀ, R]])

(P_{0|0} = :func:`netkf_cli.riccati.initial_covariance`: every estimator starts from x̂_{0|0} = 0 with
that error covariance; S, the noise cross-covariance E[w_k v_kᵀ], is 0 unless given), and the
signal each receiver sees at step k (:func:`received`):

* an ``arrival`` / ``delay`` trace: the sensor's measurement y_k itself (the estimator decides from
  the trace which packets it has);
* a ``mode`` trace (Moayedi et al. 2009, four packet modes): mode 1 on time z_k = y_k, mode 2
  delayed z_k = y_{k−1}, mode 3 missing z_k = v_k (noise only), mode 4 dropout z_k = z_{k−1}
  (the last received value held; z_0 = v_0, nothing received at time 0) — the packet model of
  :class:`netkf_cli.estimators.markov_filters.AugmentedModel` on netkf's time base.

Streams: the kernel that calls :func:`simulate` passes its chunk's generator **after** the channel
has sampled the trace from it, so the states of a chunk are a function of (seed, stream, chunk)
alone — any executor, job count or scheduling gives the same bits (:mod:`netkf_cli.montecarlo`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from netkf_cli.riccati import initial_covariance
from netkf_cli.tolerances import PSD_INPUT_TOL


@dataclass
class States:
    """True states and signals of one chunk: ``x`` (n, horizon+1, runs) with x[:, k] = x_k; ``y``
    (m, horizon+1, runs) the sensor's measurements y_k = C x_k + v_k; ``v`` the measurement noise;
    ``z`` what the receiver sees (:func:`received`; ``y`` itself unless the trace has modes)."""

    x: np.ndarray
    y: np.ndarray
    v: np.ndarray
    z: np.ndarray

    @property
    def runs(self) -> int:
        return self.x.shape[-1]


def psd_factor(M: np.ndarray) -> np.ndarray:
    """L with L Lᵀ = M for symmetric PSD M (a singular Q or P0 is allowed; eigenvalues < 0 clipped)."""
    M = 0.5 * (np.asarray(M, float) + np.asarray(M, float).T)
    w, V = np.linalg.eigh(M)
    if w.size and w.min() < -PSD_INPUT_TOL * max(1.0, float(np.abs(M).max())):
        raise ValueError("the covariance to sample from is not positive semi-definite")
    return V * np.sqrt(np.clip(w, 0.0, None))


def noise_covariance(system, S: np.ndarray | None = None) -> np.ndarray:
    """Σ = [[Q, S], [Sᵀ, R]] of ε_k = [w_k; v_k]."""
    Q, R = np.asarray(system.Q, float), np.asarray(system.R, float)
    n, m = Q.shape[0], R.shape[0]
    S = np.zeros((n, m)) if S is None else np.asarray(S, float).reshape(n, m)
    return np.block([[Q, S], [S.T, R]])


def simulate(system, trace, rng: np.random.Generator, S: np.ndarray | None = None) -> States:
    """x_0 … x_T, y_0 … y_T and the received signal for the ``trace.runs`` runs of ``trace`` (module docstring)."""
    A, C = np.asarray(system.A, float), np.asarray(system.C, float)
    n, m = A.shape[0], C.shape[0]
    T, runs = trace.horizon, trace.runs
    L0 = psd_factor(initial_covariance(system))
    Ls = psd_factor(noise_covariance(system, S))
    x = np.empty((n, T + 1, runs))
    x[:, 0] = L0 @ rng.standard_normal((n, runs))
    eps = np.einsum("pq,qtr->ptr", Ls, rng.standard_normal((n + m, T + 1, runs)))  # ε_k = [w_k; v_k], k = 0 … T
    w, v = eps[:n], np.ascontiguousarray(eps[n:])
    for k in range(T):
        x[:, k + 1] = A @ x[:, k] + w[:, k]
    y = np.einsum("mn,ntr->mtr", C, x) + v
    return States(x, y, v, received(trace, y, v))


def received(trace, y: np.ndarray, v: np.ndarray) -> np.ndarray:
    """What the receiver sees at each step (module docstring): ``y`` unless the trace carries modes."""
    if trace.mode is None:
        return y
    z = np.empty_like(y)
    z[:, 0] = v[:, 0]
    mode = np.asarray(trace.mode)  # (T, runs): mode of step k is trace step k − 1, 0-based (0 on time … 3 dropout)
    for k in range(1, y.shape[1]):
        q = mode[k - 1]
        z[:, k] = np.where(q == 0, y[:, k], np.where(q == 1, y[:, k - 1], np.where(q == 2, v[:, k], z[:, k - 1])))
    return z
