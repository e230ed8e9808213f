"""Kalman fixed-lag smoother with random packet loss (Leong, Dey & Evans 2008, Sec. II, eqs 3–4).

Covariance-only and batched over runs: every matrix is stored as ``(rows, cols, runs)`` with
the run index innermost, and the loop is over time only.

The augmented-state model of Anderson & Moore (x_k, x_{k−1}, …, x_{k−N−1}) with a lost packet
applied by multiplying the gain by γ_k gives, with Σ_k = P_{k|k−1},
X_k^{(i)} = E[e_k e_{k−i}ᵀ | Y_{k−1}] (the cross blocks P^{(0,i)}_{k|k−1}, X^{(0)} = Σ) and
D_k^{(i)} = P_{k−i|k−1} (the diagonal blocks), S_k = C Σ_k Cᵀ + R:

    P_{k−i|k} = P_{k−i|k−1} − γ_k X^{(i)ᵀ} Cᵀ S_k⁻¹ C X^{(i)}        i = 0 … N   (eq. 4; i = 0: P_{k|k})
    X^{(i)}_{k|k} = X^{(i)} − γ_k Σ_k Cᵀ S_k⁻¹ C X^{(i)}
    P_{k+1|k} = A P_{k|k} Aᵀ + Q,   X_{k+1}^{(i+1)} = A X^{(i)}_{k|k},   D_{k+1}^{(i+1)} = P_{k−i|k}   (eq. 3)

which is eq. (3)'s P^{(i)}_{k+1|k} = A P^{(i−1)}_{k|k−1} − γ_k K_k C P^{(i−1)}_{k|k−1} with
K_k = A Σ_k Cᵀ S_k⁻¹ (the transposes written out for the matrix case). A lost packet
(γ_k = 0) propagates P_{k−i|k} = P_{k−i|k−1}, exactly as the paper notes below eq. (4).

A run whose covariance overflows (a very long loss burst of an unstable system) is set to
``inf`` from then on and compares as "not ≤ M" (see ``riccati.psd_leq``); nothing crashes and
no NaN is produced.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field

from netkf_cli.spec import EstimatorModel, NonNegInt
from netkf_cli.system import LinearSystem


class SmootherEstimator(EstimatorModel):
    """``kind: smoother`` — fixed-lag Kalman smoother under packet loss (Leong 2008, eqs 3–4).

    Reports P_{k|k−1}, P_{k|k} and P_{k|k+N} for N = 1 … ``lag``.
    """

    kind: Literal["smoother"]
    lag: NonNegInt = Field(4, description="largest smoothing lag N_max (0 = filter only)")


def _mm(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Batched matrix product of ``(a, b, runs)`` and ``(b, c, runs)``."""
    if X.shape[0] == 1 and X.shape[1] == 1 and Y.shape[0] == 1:
        return X * Y
    return np.einsum("ijr,jkr->ikr", X, Y)


def _mT(X: np.ndarray) -> np.ndarray:
    return np.swapaxes(X, 0, 1)


def _const_mm(A: np.ndarray, X: np.ndarray) -> np.ndarray:
    """A @ X for a constant matrix A and a batched X ``(b, c, runs)``."""
    return np.einsum("ij,jkr->ikr", A, X)


def _solve_batched(S: np.ndarray, B: np.ndarray) -> np.ndarray:
    """S⁻¹ B for batched S ``(m, m, runs)`` and B ``(m, c, runs)`` (closed form for m ≤ 2)."""
    m = S.shape[0]
    if m == 1:
        return B / S
    if m == 2:
        a, b, c, d = S[0, 0], S[0, 1], S[1, 0], S[1, 1]
        det = a * d - b * c
        inv = np.empty_like(S)
        inv[0, 0], inv[0, 1], inv[1, 0], inv[1, 1] = d / det, -b / det, -c / det, a / det
        return _mm(inv, B)
    Sr = np.moveaxis(S, -1, 0)
    Br = np.moveaxis(B, -1, 0)
    return np.moveaxis(np.linalg.solve(Sr, Br), 0, -1)


def _sym(X: np.ndarray) -> np.ndarray:
    return 0.5 * (X + _mT(X))


def initial_prediction(system: LinearSystem) -> np.ndarray:
    """P_{0|−1}: the system's P0, or P* (the steady-state prediction covariance) for ``P0: steady``."""
    if system.P0 is not None:
        return system.P0
    from netkf_cli.riccati import pstar

    return pstar(system)


def iter_fixed_lag(
    system: LinearSystem, gamma: np.ndarray, lag: int, P0: np.ndarray | None = None
) -> Iterator[tuple[int, np.ndarray, np.ndarray, list[np.ndarray]]]:
    """Step the smoother over ``gamma`` (``(runs, horizon)``, arrivals), yielding for each k

    ``(k, P_{k|k−1}, P_{k|k}, [P_{k−1|k}, …, P_{k−lag|k}])``, each ``(n, n, runs)``
    (entries for k − i < 0 are meaningless and must be ignored by the caller).
    """
    gamma = np.asarray(gamma)
    if gamma.ndim != 2:
        raise ValueError(f"gamma must be (runs, horizon), got shape {gamma.shape}")
    if lag < 0:
        raise ValueError(f"lag must be ≥ 0, got {lag}")
    runs, horizon = gamma.shape
    n = system.n
    A, C, Q, R = system.A, system.C, system.Q, system.R
    P0 = initial_prediction(system) if P0 is None else np.asarray(P0, dtype=float)
    g = gamma.astype(float).T  # (horizon, runs)
    Qb, Rb = Q[:, :, None], R[:, :, None]
    Sigma = np.repeat(P0[:, :, None], runs, axis=2).astype(float)
    X = [Sigma] + [np.zeros((n, n, runs)) for _ in range(lag)]  # X^{(i)}, i = 0..lag
    D = [None] + [np.zeros((n, n, runs)) for _ in range(lag)]  # D^{(i)} = P_{k−i|k−1}, i = 1..lag
    diverged = np.zeros(runs, dtype=bool)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        for k in range(horizon):
            gk = g[k]
            Sigma = X[0]
            CX = [_const_mm(C, Xi) for Xi in X]  # C X^{(i)}, (m, n, runs)
            S = _const_mm(C, _mT(CX[0])) + Rb  # C Σ Cᵀ + R
            G = [_solve_batched(S, CXi) for CXi in CX]  # S⁻¹ C X^{(i)}
            filt = _sym(Sigma - gk * _mm(_mT(CX[0]), G[0]))  # P_{k|k}
            lagged = [_sym(D[i] - gk * _mm(_mT(CX[i]), G[i])) for i in range(1, lag + 1)]  # P_{k−i|k}
            bad = ~np.isfinite(Sigma).all(axis=(0, 1)) | ~np.isfinite(filt).all(axis=(0, 1))
            diverged |= bad
            if diverged.any():
                for arr in [Sigma, filt, *lagged]:
                    arr[:, :, diverged] = np.inf
            yield k, Sigma, filt, lagged
            if k == horizon - 1:
                break
            # time update, eq. (3)
            newX = [None] * (lag + 1)
            newX[0] = _sym(_const_mm(A, _mT(_const_mm(A, filt)))) + Qb  # A P_{k|k} Aᵀ + Q
            for i in range(lag):
                Xu = filt if i == 0 else X[i] - gk * _mm(_mT(CX[0]), G[i])  # X^{(i)}_{k|k}
                newX[i + 1] = _const_mm(A, Xu)
            newD = [None] + [filt] + lagged[: lag - 1] if lag >= 1 else [None]
            X, D = newX, newD
            if diverged.any():
                for arr in X:
                    arr[:, :, diverged] = np.inf


@dataclass
class SmootherResult:
    """Covariances at the recorded ``times``: ``pred[t]`` = P_{t|t−1}, ``smooth[t, N]`` = P_{t|t+N}
    (``smooth[:, 0]`` is the filter P_{t|t}); arrays ``(len(times), [lag+1,] n, n, runs)``."""

    times: np.ndarray
    pred: np.ndarray
    smooth: np.ndarray

    @property
    def filt(self) -> np.ndarray:
        return self.smooth[:, 0]


def fixed_lag_smoother(
    system: LinearSystem,
    gamma: np.ndarray,
    lag: int,
    P0: np.ndarray | None = None,
    *,
    times: Sequence[int] | np.ndarray | None = None,
) -> SmootherResult:
    """Run eqs (3)–(4) over arrivals ``gamma`` (``(runs, horizon)``) and record P_{t|t−1}, P_{t|t+N}
    (N = 0 … lag) at ``times`` (default: every t with t + lag < horizon). Batched over runs."""
    gamma = np.asarray(gamma)
    if gamma.ndim != 2:
        raise ValueError(f"gamma must be (runs, horizon), got shape {gamma.shape}")
    runs, horizon = gamma.shape
    if times is None:
        times = np.arange(0, horizon - lag)
    times = np.asarray(times, dtype=int)
    if times.size and (times.min() < 0 or times.max() + lag >= horizon):
        raise ValueError(f"times must satisfy 0 ≤ t and t + lag < horizon = {horizon}")
    n = system.n
    pos = {int(t): j for j, t in enumerate(times)}
    pred = np.full((len(times), n, n, runs), np.nan)
    smooth = np.full((len(times), lag + 1, n, n, runs), np.nan)
    last_needed = int(times.max()) + lag if times.size else -1
    for k, Sigma, filt, lagged in iter_fixed_lag(system, gamma, lag, P0):
        if k in pos:
            pred[pos[k]] = Sigma
            smooth[pos[k], 0] = filt
        for i in range(1, lag + 1):
            j = pos.get(k - i)
            if j is not None:
                smooth[j, i] = lagged[i - 1]
        if k >= last_needed:
            break
    return SmootherResult(times=times, pred=pred, smooth=smooth)
