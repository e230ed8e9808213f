"""Receivers of Mostofi & Murray 2009: scenario 1 (eqs 7–8), 2 (eqs 10–13) and 3 (eqs 27–28).

A packet is kept iff Υ[k] ≥ Υ_T (eq. 5). What happens to a kept packet:

* scenario 1 — "ideal noise": the kept packet is noise-free apart from the observation noise R
  (eq. 7 with S₁ = 0): P⁺ = (P⁻¹ + Cᵀ R⁻¹ C)⁻¹.
* scenario 2 — no cross-layer path: the estimator does not know σ_n² and treats a kept packet
  as noise-free, x̂[k+1] = A C⁻¹ ŷ[k] (eq. 10). For an invertible C the error covariance is
  eq. (12) with the footnote's σ_n² I + R: P[k+1] = A C⁻¹(σ_n²(Υ) I + R)C⁻ᵀ Aᵀ + Q.
  For a non-invertible C (Sec. 4.2) we use the same estimator idea as a Kalman filter that
  believes the measurement noise is zero: its own covariance P_f gives the gain
  K = P_f Cᵀ (C P_f Cᵀ)⁻¹, and the true error covariance follows the Joseph form
  P⁺ = (I − KC) P (I − KC)ᵀ + K(σ_n² I + R)Kᵀ. With an invertible C, K = C⁻¹ and this is eq. (12).
* scenario 3 — cross-layer path: the Kalman filter uses σ_z² = σ_n²(Υ) I + R (eqs 27–28),
  P⁺ = (P⁻¹ + Cᵀ σ_z⁻² C)⁻¹ (information form: exact even when P is huge after a drop burst).

A dropped packet always gives P[k+1] = A P Aᵀ + Q.

All recursions are batched: matrices are ``(n, n, B)`` with the batch index (runs × thresholds)
innermost; the loop is over time only. Overflow of an unstable run gives ``inf``, never a crash.

Two Monte Carlo estimators of E P[k] are provided:

* **naive**: the sample mean of P[k] over runs (works for any channel, heavy-tailed near the
  stability limit: its variance is infinite once μ ρ⁴ ≥ 1 in scenario 2).
* **burst-conditioned** (i.i.d. channel only): condition on the final drop burst. With
  μ = Pr[drop] and F(P, Υ) the kept-packet update, for i.i.d. Υ
  E[P[k+1] | P[k]] = μ (A P[k] Aᵀ + Q) + (1 − μ) E[F(P[k], Υ') ], Υ' ~ Υ | Υ ≥ Υ_T = Υ_T + Exp(Υ_ave),
  so U[k+1] = μ (A U[k] Aᵀ + Q) + (1 − μ) F(P[k], Υ'[k]), U[0] = P[0], is an unbiased estimate
  of E P[k+1] for every run (induction on k; Υ'[k] is independent of P[k]). The long drop
  bursts that make P[k] heavy-tailed enter U only through their exact probabilities μ^L,
  and F(P, Υ') is bounded by A C⁻¹σ_z²C⁻ᵀAᵀ + Q whatever P is (invertible C), so U has a
  small variance. The path P itself is simulated with keep = (uniform ≥ μ) and Υ' as the
  SNR of kept packets, i.e. the exact i.i.d. channel.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field

from netkf_cli.channels.fading import Snr
from netkf_cli.spec import EstimatorModel


class ReceiverEstimator(EstimatorModel):
    """``kind: receiver`` — Mostofi & Murray 2009 receiver scenario 1, 2 or 3 with drop threshold Υ_T (eq. 5)."""

    kind: Literal["receiver"]
    scenario: Literal[1, 2, 3] = Field(description="1: drop erroneous packets (eqs 7–8); 2: no cross-layer path "
                                                   "(eqs 10–13); 3: cross-layer path (eqs 27–28)")
    threshold: Snr | None = Field(None, description="drop threshold Υ_T with unit (analyses that sweep Υ_T ignore it)")


# --------------------------------------------------------------------------- batched linear algebra


def _mm(X, Y):
    return np.einsum("ijb,jkb->ikb", X, Y)


def _cmm(A, X):
    return np.einsum("ij,jkb->ikb", A, X)


def _mmc(X, A):
    return np.einsum("ijb,jk->ikb", X, A)


def _sandwich(A, X):
    """A X Aᵀ for constant A, batched X."""
    return np.einsum("ikb,lk->ilb", np.einsum("ij,jkb->ikb", A, X), A)


def _sym(X):
    return 0.5 * (X + np.swapaxes(X, 0, 1))


def inv_small(X: np.ndarray) -> np.ndarray:
    """Inverse of a batch ``(m, m, B)`` of symmetric positive-definite matrices.

    Closed form (adjugate/determinant) for m ≤ 3 after scaling each matrix by its largest
    entry (no overflow of the m-fold products); ``np.linalg.inv`` otherwise.
    """
    m = X.shape[0]
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        s = np.max(np.abs(X), axis=(0, 1))
        s = np.where(s > 0, s, 1.0)
        Y = X / s
        if m == 1:
            out = 1.0 / Y
        elif m == 2:
            a, b, c, d = Y[0, 0], Y[0, 1], Y[1, 0], Y[1, 1]
            det = a * d - b * c
            out = np.stack([np.stack([d, -b]), np.stack([-c, a])]) / det
        elif m == 3:
            a, b, c = Y[0, 0], Y[0, 1], Y[0, 2]
            d, e, f = Y[1, 0], Y[1, 1], Y[1, 2]
            g, h, i = Y[2, 0], Y[2, 1], Y[2, 2]
            A_, B_, C_ = e * i - f * h, -(d * i - f * g), d * h - e * g
            det = a * A_ + b * B_ + c * C_
            out = np.stack([
                np.stack([A_, -(b * i - c * h), b * f - c * e]),
                np.stack([B_, a * i - c * g, -(a * f - c * d)]),
                np.stack([C_, -(a * h - b * g), a * e - b * d]),
            ]) / det
        else:
            out = np.moveaxis(np.linalg.inv(np.moveaxis(Y, 2, 0)), 0, 2)
        return out / s


# --------------------------------------------------------------------------- the model of one receiver


@dataclass(frozen=True)
class ReceiverModel:
    """Everything the recursions need, as float arrays. ``noise`` maps linear SNR → σ_n²."""

    scenario: int
    A: np.ndarray
    C: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    noise: object  # callable snr -> sigma2
    general_C: bool = False  # scenario 2: force the Kalman-gain form even for an invertible C

    @property
    def n(self) -> int:
        return self.A.shape[0]

    @property
    def square_C(self) -> bool:
        C = self.C
        return C.shape[0] == C.shape[1] and abs(np.linalg.det(C)) > 1e-12 * max(1.0, np.abs(C).max()) ** C.shape[0]

    def state_size(self) -> int:
        """Number of covariance matrices carried per run (2 for scenario 2 with the general-C form)."""
        return 2 if (self.scenario == 2 and (self.general_C or not self.square_C)) else 1


def _drop(rm: ReceiverModel, P):
    return _sym(_sandwich(rm.A, P)) + rm.Q[:, :, None]


def kept_update(rm: ReceiverModel, state: list[np.ndarray], sigma2: np.ndarray) -> list[np.ndarray]:
    """Next-step covariance(s) P[k+1] for a KEPT packet with communication-noise variance σ_n² (per batch)."""
    A, C, Q, R = rm.A, rm.C, rm.Q, rm.R
    n, m = rm.n, C.shape[0]
    if rm.scenario == 1 or rm.scenario == 3:
        P = state[0]
        if rm.scenario == 1:
            info = (C.T @ np.linalg.solve(R, C))[:, :, None]
        else:
            # Cᵀ (σ² I + R)⁻¹ C = Σ_i c_i c_iᵀ / (r_i + σ²) with R = U diag(r) Uᵀ, c_i = (Uᵀ C)_i
            r, U = np.linalg.eigh(R)
            Ct = U.T @ C
            G = np.einsum("ia,ib->abi", Ct, Ct)  # (n, n, m)
            with np.errstate(divide="ignore"):
                w = 1.0 / (r[:, None] + sigma2[None, :])  # (m, B)
            info = np.tensordot(G, w, axes=([2], [0]))  # (n, n, B)
        Pp = inv_small(_sym(inv_small(P) + info))
        return [_sym(_sandwich(A, Pp)) + Q[:, :, None]]
    # scenario 2
    if rm.state_size() == 1:
        Ci = np.linalg.inv(C)
        M1 = A @ Ci @ Ci.T @ A.T
        M2 = A @ Ci @ R @ Ci.T @ A.T + Q
        return [M1[:, :, None] * sigma2[None, None, :] + M2[:, :, None]]
    Pf, Pt = state
    S = _sym(_mm(_cmm(C, Pf), np.broadcast_to(C.T[:, :, None], (n, m, 1))))  # C Pf Cᵀ  (m, m, B)
    K = _mm(_mmc(Pf, C.T), inv_small(S))  # (n, m, B)
    IKC = np.eye(n)[:, :, None] - _mmc(K, C)
    Rz = R[:, :, None] + sigma2[None, None, :] * np.eye(m)[:, :, None]
    KT = np.swapaxes(K, 0, 1)
    Pt_plus = _sym(_mm(_mm(IKC, Pt), np.swapaxes(IKC, 0, 1)) + _mm(_mm(K, Rz), KT))
    Pf_plus = _sym(_mm(_mm(IKC, Pf), np.swapaxes(IKC, 0, 1)))  # filter believes zero measurement noise
    return [_drop(rm, Pf_plus), _drop(rm, Pt_plus)]


def drop_update(rm: ReceiverModel, state):
    return [_drop(rm, X) for X in state]


def initial_state(rm: ReceiverModel, P0: np.ndarray, B: int) -> list[np.ndarray]:
    P = np.repeat(np.asarray(P0, dtype=float)[:, :, None], B, axis=2)
    return [P.copy() for _ in range(rm.state_size())]


def true_cov(state):
    """The true error covariance of the state (last element)."""
    return state[-1]


def _where(mask, X, Y):
    return np.where(mask[None, None, :], X, Y)


def covariance_paths(rm: ReceiverModel, snr: np.ndarray, threshold, P0, record=None) -> np.ndarray:
    """Naive recursion along given SNR traces ``snr`` (horizon, B) with per-column threshold Υ_T.

    Returns the true error covariance at the steps in ``record`` (default: every step 0..horizon),
    shape (len(record), n, n, B).
    """
    H, B = snr.shape
    T = np.broadcast_to(np.asarray(threshold, dtype=float), (B,))
    record = list(range(H + 1)) if record is None else list(record)
    out = np.empty((len(record), rm.n, rm.n, B))
    state = initial_state(rm, P0, B)
    pos = {k: i for i, k in enumerate(record)}
    if 0 in pos:
        out[pos[0]] = true_cov(state)
    with np.errstate(over="ignore", invalid="ignore"):
        for k in range(H):
            keep = snr[k] >= T
            s2 = rm.noise(np.where(keep, snr[k], 1.0))
            ku = kept_update(rm, state, s2)
            du = drop_update(rm, state)
            state = [_where(keep, a, b) for a, b in zip(ku, du)]
            if k + 1 in pos:
                out[pos[k + 1]] = true_cov(state)
    return out


def burst_conditioned_paths(rm: ReceiverModel, rng: np.random.Generator, thresholds: np.ndarray, mus: np.ndarray,
                            snr_avg: float, P0, horizon: int, record) -> tuple[np.ndarray, np.ndarray]:
    """Simulate the i.i.d. exponential channel and return (naive P[k], burst-conditioned U[k]) at ``record``.

    ``thresholds`` and ``mus`` (= μ_ave(Υ_T)) have one entry per batch column. Both outputs have shape
    (len(record), n, n, B); both are unbiased for E P[k] (see module doc), U with far smaller variance.
    """
    B = thresholds.shape[0]
    record = list(record)
    pos = {k: i for i, k in enumerate(record)}
    P_out = np.empty((len(record), rm.n, rm.n, B))
    U_out = np.empty_like(P_out)
    state = initial_state(rm, P0, B)
    U = true_cov(state).copy()
    if 0 in pos:
        P_out[pos[0]] = U
        U_out[pos[0]] = U
    mu = mus[None, None, :]
    with np.errstate(over="ignore", invalid="ignore"):
        for k in range(horizon):
            keep = rng.random(B) >= mus
            snr_kept = thresholds + rng.exponential(snr_avg, B)  # memoryless: Υ | Υ ≥ Υ_T
            ku = kept_update(rm, state, rm.noise(snr_kept))
            du = drop_update(rm, state)
            U = mu * _drop(rm, U) + (1.0 - mu) * true_cov(ku)
            state = [_where(keep, a, b) for a, b in zip(ku, du)]
            if k + 1 in pos:
                P_out[pos[k + 1]] = true_cov(state)
                U_out[pos[k + 1]] = U
    return P_out, U_out


def simulate_states(rm: ReceiverModel, rng: np.random.Generator, snr: np.ndarray, threshold: float, P0) -> dict:
    """State-level check: simulate x, the noisy received packets and the receiver's estimate.

    Returns the final error e = x − x̂ (n, B) and the final covariance P (n, n, B) of the same runs,
    so that E[e eᵀ] can be compared with E[P]. The received packet is ŷ = C x + v + n with
    v ~ N(0, R), n ~ N(0, σ_n²(Υ) I) (Sec. 2.1). x̂ is the prediction x̂[k|k−1] (eq. 6).
    """
    A, C, Q, R = rm.A, rm.C, rm.Q, rm.R
    n, m = rm.n, C.shape[0]
    H, B = snr.shape
    LQ = np.linalg.cholesky(Q + 1e-300 * np.eye(n)) if np.any(Q) else np.zeros((n, n))
    LR = np.linalg.cholesky(R)
    L0 = np.linalg.cholesky(P0)
    x = L0 @ rng.standard_normal((n, B))
    xh = np.zeros((n, B))
    state = initial_state(rm, P0, B)
    for k in range(H):
        keep = snr[k] >= threshold
        s2 = rm.noise(np.where(keep, snr[k], 1.0))
        y = C @ x + LR @ rng.standard_normal((m, B)) + np.sqrt(s2)[None, :] * rng.standard_normal((m, B))
        if rm.scenario == 2 and rm.state_size() == 1:
            upd = np.linalg.solve(C, y)  # x̂⁺ = C⁻¹ ŷ (eq. 10)
        else:
            P = state[0]  # the filter's own covariance
            if rm.scenario == 2:
                Rf = np.zeros((m, m, B))
            elif rm.scenario == 1:
                Rf = np.broadcast_to(R[:, :, None], (m, m, B))
            else:
                Rf = R[:, :, None] + s2[None, None, :] * np.eye(m)[:, :, None]
            S = _mm(_cmm(C, P), np.broadcast_to(C.T[:, :, None], (n, m, B))) + Rf
            K = _mm(_mmc(P, C.T), inv_small(_sym(S)))
            upd = xh + np.einsum("imb,mb->ib", K, y - C @ xh)
        xh_plus = np.where(keep[None, :], upd, xh)
        ku = kept_update(rm, state, s2)
        du = drop_update(rm, state)
        state = [_where(keep, a, b) for a, b in zip(ku, du)]
        x = A @ x + LQ @ rng.standard_normal((n, B))
        xh = A @ xh_plus
    return {"e": x - xh, "P": true_cov(state)}
