"""The one Kalman core: batched predict / update / rescue / smoothing primitives (run axis innermost).

Every estimator of netkf is written on these functions, and no other module computes a Kalman
gain. Covariances are ``(n, n, runs)`` arrays (design.md's fast layout); system matrices are
constant ``(n, n)`` / ``(m, n)`` arrays. A single matrix is the case ``runs = 1``
(:func:`one`). The equations, with γ ∈ {0, 1} the arrival of a measurement (Sinopoli et al. 2004,
eqs. 8–9; Shi, Xie & Murray 2009, eqs. 5–6):

    predict   P_{k|k−1} = A P_{k−1|k−1} Aᵀ + Q                                     (h)
    innovation S = C P Cᵀ + R (+ per-run extra noise),   gain K = P Cᵀ S⁻¹
    update    P_{k|k}   = P_{k|k−1} − γ K C P_{k|k−1}                               (g̃, optimal K)
    Joseph    P_{k|k}   = (I − γKC) P (I − γKC)ᵀ + γ K R Kᵀ                         (any K)
    rows      only the rows that arrived: C̃ = W C, R̃ = W R W + (I − W), W = diag(mask)
    rescue    P_{k|k}   = (P_{k|k−1}⁻¹ + C̃ᵀ R̃⁻¹ C̃)⁻¹  for runs with tr P_{k|k−1} > RESCUE_RATIO·scale
    smoothing P_{t|T}   = P_{t|t, x_{t+1}} + J P_{t+1|T} Jᵀ,  J = P_{t|t} Aᵀ P_{t+1|t}⁻¹   (RTS, as the
              update of P_{t|t} by x_{t+1} = A x_t + w: :class:`SmoothStep`)

Time base (every estimator, every metric): ``P0`` is P_{0|0} (``system.P0``; unset = P̄); step
k = 1 … horizon is the time of the newest measurement y_k that could have been used; the named
quantities at step k are ``filtered`` P_{k|k}, ``predicted`` P_{k+1|k} and ``smoothed``
P_{k−N|k} (a lag-N smoother). A channel's arrival stream s carries sensor s of
``system.sensors`` (:func:`stream_rows`).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Iterable, Iterator

import numpy as np
import scipy.linalg

from netkf_cli.linalg import batched
from netkf_cli.linalg import kalman_codegen as kc
from netkf_cli.core import llvm_pages
from netkf_cli.core.errors import ConfigError
from netkf_cli.core.tolerances import PSD_TOL, RESCUE_RATIO

QUANTITIES = ("filtered", "predicted", "smoothed")
"""The named covariances an estimator can report at step k."""

SYMBOL = {"filtered": "P_{k|k}", "predicted": "P_{k+1|k}", "smoothed": "P_{k-N|k}"}
"""What each quantity is, for CSVs, figures and ``netkf list``."""

MEANING = {"filtered": "filtered P_{k|k} (after the step-k update)",
           "predicted": "predicted P_{k+1|k} (one step ahead of the step-k update)",
           "smoothed": "smoothed P_{k−N|k} (lag N, from the measurements up to k)"}


# ----------------------------------------------------------------------------------------------
# one-step primitives
# ----------------------------------------------------------------------------------------------

def predict(P: np.ndarray, A: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """P_{k|k−1} = A P Aᵀ + Q per run (the time update h, Shi 2009 eq. 5)."""
    return batched.riccati_h(P, A, Q)


def innovation(P: np.ndarray, C: np.ndarray, R: np.ndarray, extra_R: np.ndarray | None = None):
    """(P Cᵀ, S = C P Cᵀ + R [+ extra_R]) per run; ``extra_R`` (m, m, runs) is per-run added noise."""
    PCt = batched.right(P, C.T)
    S = batched.left(C, PCt) + R[:, :, None]
    if extra_R is not None:
        S = S + extra_R
    return PCt, S


def gain(P: np.ndarray, C: np.ndarray, R: np.ndarray, extra_R: np.ndarray | None = None) -> np.ndarray:
    """The optimal gain K = P Cᵀ S⁻¹ per run, shaped (n, m, runs)."""
    PCt, S = innovation(P, C, R, extra_R)
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        return batched.solve_small(S, PCt.swapaxes(0, 1)).swapaxes(0, 1)


def update(P: np.ndarray, C: np.ndarray, R: np.ndarray, gamma: np.ndarray | None = None,
           extra_R: np.ndarray | None = None) -> np.ndarray:
    """P − γ·P Cᵀ S⁻¹ C P per run (optimal gain; Sinopoli 2004 eq. 9). ``gamma`` (runs,) in {0, 1}
    multiplies the correction, so a lost measurement leaves P bit-for-bit unchanged."""
    PCt, S = innovation(P, C, R, extra_R)
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        corr = batched.matmul(PCt, batched.solve_small(S, PCt.swapaxes(0, 1)))
        if gamma is not None:
            corr = corr * np.asarray(gamma, dtype=float)[None, None, :]
        return batched.sym(P - corr)


def update_rows(P: np.ndarray, C: np.ndarray, R: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The exact update with the output rows that arrived, per run: ``mask`` (m, runs) in {0, 1}.

    C̃ = W C, R̃ = W R W + (I − W) (W = diag(mask)): S̃ is block-diagonal (observed block, identity on
    the missing rows), so K̃ = P C̃ᵀ S̃⁻¹ is the gain of the observed subset for any (non-diagonal) R.
    """
    w = np.asarray(mask, dtype=float)
    PCt, S = innovation(P, C, R)
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        PCt = PCt * w[None, :, :]
        m = C.shape[0]
        S = S * (w[:, None, :] * w[None, :, :])
        idx = np.arange(m)
        S[idx, idx] += 1.0 - w
        corr = batched.matmul(PCt, batched.solve_small(S, PCt.swapaxes(0, 1)))
        return batched.sym(P - corr)


def joseph(P: np.ndarray, K: np.ndarray, C: np.ndarray, R: np.ndarray, gamma: np.ndarray | None = None,
           extra_R: np.ndarray | None = None) -> np.ndarray:
    """(I − γKC) P (I − γKC)ᵀ + γ K (R [+ extra_R]) Kᵀ per run: the error covariance of ANY gain K
    (n, m, runs) — a filter whose gain is not the optimal one for the true noise (Joseph form)."""
    n = P.shape[0]
    with np.errstate(invalid="ignore", over="ignore"):
        Kg = K if gamma is None else K * np.asarray(gamma, dtype=float)[None, None, :]
        KC = batched.right(Kg, C)  # (n, n, runs)
        IKC = np.eye(n)[:, :, None] - KC
        out = batched.matmul(batched.matmul(IKC, P), IKC.swapaxes(0, 1))
        Rr = np.broadcast_to(R[:, :, None], R.shape + (P.shape[-1],)) if extra_R is None else R[:, :, None] + extra_R
        out = out + batched.matmul(batched.matmul(Kg, Rr), Kg.swapaxes(0, 1))
        return batched.sym(out)


def _clean_pattern(P: np.ndarray) -> np.ndarray:
    """(runs,) bool for P (n, n, runs): every non-finite entry lies where both its row's and its
    column's variance are +∞ (unknown directions), nothing is NaN — the ∞ pattern the rescue keeps."""
    d = np.diagonal(P).T  # (n, runs)
    unknown = ~np.isfinite(d)
    allowed = unknown[:, None, :] & unknown[None, :, :]
    bad = ~np.isfinite(P) & ~allowed
    return ~bad.any(axis=(0, 1)) & ~np.isnan(P).any(axis=(0, 1)) & np.all(~unknown | (d == np.inf), axis=0)


def _inv(X: np.ndarray) -> np.ndarray:
    """``np.linalg.inv`` of a batch (k, n, n); 1×1 matrices, none zero, as 1/x — LAPACK's inverse of a 1×1
    matrix, bit for bit (a test) without its per-matrix call (the rescue's scalar runs, step after step)."""
    if X.shape[-1] == 1 and np.all(X != 0):
        with np.errstate(over="ignore"):  # (a subnormal x: ∞, as LAPACK's, which does not warn)
            return 1.0 / X
    return np.linalg.inv(X)


def _prior_inv(X: np.ndarray) -> np.ndarray:
    """:func:`_inv` of a batch of finite priors (k, n, n); a prior singular to working precision gets NaN: its run
    is beyond what the information form resolves and :func:`information_update` returns it as ∞, diverged.

    Singular to working precision is numpy's ``matrix_rank`` < n of the prior scaled to a unit diagonal
    (:func:`numerically_singular`; LAPACK's zero pivot is the extreme case): a flagged prior so large along one
    direction that the others are lost beside it, after a long loss burst of an unstable A or an undetectable
    mode's growth. The posterior's error is ≈ ε·κ(P⁻) relative (a coupled 2-state system, against exact
    arithmetic: 7e-6 at κ = 2e11, 1e-2 at 3e14, 0.24 at 3e15; the scaled κ is of the same size there); beyond
    1/(nε) the computed P⁺ was garbage, once an indefinite matrix of trace −26, which Pr[P ≤ M] counted as small.
    The compiled kernels decide alike (kalman_numba.information_update). An invertible batch is inverted as
    before, bit for bit (one LAPACK call per matrix either way)."""
    try:
        out = _inv(X)
    except np.linalg.LinAlgError:
        out = np.empty_like(X)
        for i in range(X.shape[0]):
            try:
                out[i] = _inv(X[i:i + 1])[0]
            except np.linalg.LinAlgError:
                out[i] = np.nan
    if X.shape[-1] > 1:
        lost = numerically_singular(X)
        if lost.any():
            out[lost] = np.nan
    return out


def numerically_singular(X: np.ndarray) -> np.ndarray:
    """(k,) bool for a batch of finite symmetric matrices (k, n, n): rank < n to working precision once each is
    scaled to a unit diagonal, D^-1/2 X D^-1/2 — σ_min ≤ n·ε·σ_max, numpy's ``matrix_rank`` criterion. The
    scaling is what an inversion's accuracy depends on (van der Sluis): diag(5e23, 0.5) is exact and inverted
    exactly (scaled: I), while a loss burst's prior, both variances 1e15 and correlated to 1 − 1e-16 along the
    unstable direction, has lost its other direction to rounding."""
    d = np.sqrt(np.abs(np.diagonal(X, axis1=1, axis2=2)))
    d = np.where(d > 0, d, 1.0)
    sv = np.linalg.svd(X / d[:, :, None] / d[:, None, :], compute_uv=False)
    return sv[:, -1] <= sv[:, 0] * X.shape[-1] * np.finfo(float).eps


def _full_rank(M: np.ndarray) -> np.ndarray:
    """``np.linalg.matrix_rank(M) == n`` per matrix of a batch (k, n, n); for 1×1 matrices without a NaN,
    finite and non-zero — svd's |m| > |m|·ε, the same decision (a test) without a batched svd."""
    n = M.shape[-1]
    if n == 1 and not np.isnan(M).any():
        return (np.isfinite(M) & (M != 0))[:, 0, 0]
    return np.linalg.matrix_rank(M) == n


def prior_information(X: np.ndarray) -> np.ndarray:
    """P⁻¹ per run for X (k, n, n) whose +∞ entries, if any, are the variances of directions with no
    information: a run whose non-finite entries all lie in rows/columns with a +∞ diagonal, the rest
    finite, gets the limit of P⁻¹ as those variances → ∞ — 0 in those directions, the inverse of the
    finite block elsewhere (its coupling to the ∞ directions vanishes in the limit). Any other
    non-finite run (a NaN, ∞ coupling two known directions) has no usable prior: information 0."""
    k, n, _ = X.shape
    Y = np.zeros_like(X)
    finite = np.isfinite(X).all(axis=(1, 2))
    if finite.any():
        Y[finite] = _prior_inv(X[finite])
    rest = np.flatnonzero(~finite)
    if rest.size:
        Xr = X[rest]
        clean = _clean_pattern(np.moveaxis(Xr, 0, -1))
        known = np.isfinite(np.diagonal(Xr, axis1=1, axis2=2))  # (r, n)
        codes = known @ (1 << np.arange(n))
        for code in np.unique(codes[clean]):  # one batched inverse per pattern of known directions
            f = ((code >> np.arange(n)) & 1).astype(bool)
            if not f.any():
                continue
            sel = clean & (codes == code)
            blk = Xr[sel][:, f][:, :, f]
            Yr = np.zeros((int(sel.sum()), n, n))
            Yr[np.ix_(np.arange(Yr.shape[0]), f, f)] = _prior_inv(blk)
            Y[rest[sel]] = Yr
    return Y


def information_update(Pm: np.ndarray, info: np.ndarray) -> np.ndarray:
    """(P⁻⁻¹ + I)⁻¹ per run, ``info`` (n, n) or (n, n, runs) the measurement information C̃ᵀR̃⁻¹C̃
    (the information form of the update; an unknown direction of P⁻, variance ∞, has information 0:
    :func:`prior_information`). A run whose posterior information is singular (a direction neither the
    prior nor the measurement knows), or whose finite prior is singular to working precision, is ∞."""
    X = np.moveaxis(Pm, -1, 0)
    info_r = np.moveaxis(info, -1, 0) if info.ndim == 3 else np.broadcast_to(info, X.shape)
    M = prior_information(X) + info_r
    n = M.shape[-1]
    ok = np.isfinite(M).all(axis=(1, 2))  # a prior singular to working precision: NaN information (_prior_inv)
    if ok.any():
        ok[ok] = _full_rank(M[ok])
    out = np.full_like(M, np.inf)
    if np.any(ok):
        out[ok] = _inv(M[ok])
    return np.moveaxis(0.5 * (out + out.transpose(0, 2, 1)), 0, -1)


def clean_nonfinite(P: np.ndarray) -> np.ndarray:
    """Runs of P (n, n, runs) that are non-finite in any way other than the ∞ variance of unknown
    directions (:func:`prior_information`) are set to ∞ everywhere: a diverged run is counted as such,
    never a NaN."""
    bad = ~np.isfinite(P).all(axis=(0, 1))
    if not bad.any():
        return P
    P = P.copy()
    idx = np.flatnonzero(bad)
    P[:, :, idx[~_clean_pattern(P[:, :, idx])]] = np.inf
    return P


# ----------------------------------------------------------------------------------------------
# the one rescue policy
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Rescue:
    """The one overflow policy of netkf.

    Before an update, a run whose prior has ``tr P⁻ > limit`` (or is non-finite) is flagged. After
    the standard update, a flagged run with a finite prior and at least one arrived row is redone in
    information form (exact where the standard form cancels every digit: A = diag(1e6, 0.5)); a run
    that is non-finite after the step is set to ``inf`` everywhere (counted as diverged by the
    metrics, never a silent NaN). ``limit = RESCUE_RATIO · tr((CᵀR⁻¹C)⁻¹)`` when C has full column
    rank, else ``RESCUE_RATIO · tr P̄`` (the best posterior, every packet received: a prior that far
    above it cancels digits where the filter knows the state well), or ``RESCUE_RATIO · tr R / ‖C‖₂²``
    where P̄ does not exist (:data:`netkf_cli.core.tolerances.RESCUE_RATIO`). A filter that updates several rows at
    once has that limit lowered to where a loss burst's standard update still keeps the same accuracy
    (:meth:`for_system`, :func:`burst_limit`): there the cancellation grows like ‖P⁻‖², not ‖P⁻‖.
    """

    C: np.ndarray
    R: np.ndarray
    limit: float

    @classmethod
    def of(cls, C: np.ndarray, R: np.ndarray, floor: float | None = None) -> "Rescue":
        """``floor``: the smallest posterior the filter reaches (tr P̄, :meth:`Filter.of`), used when C is
        rank-deficient; without it, the noise seen through C, tr R / ‖C‖₂²."""
        info = C.T @ np.linalg.solve(R, C)
        if np.linalg.matrix_rank(info) == C.shape[1]:
            scale = float(np.trace(np.linalg.inv(info)))
        elif floor is not None and np.isfinite(floor) and floor > 0:
            scale = float(floor)
        else:  # the noise seen through C: a prior this far above it cancels digits in the measured directions
            scale = float(np.trace(R)) / max(float(np.linalg.norm(C, 2)) ** 2, 1e-300)
        return cls(C, R, RESCUE_RATIO * scale)

    @classmethod
    def for_system(cls, A, C, Q, R, rows: int, groups=None, sequential: bool = True) -> "Rescue":
        """The policy of a filter of (A, C, Q, R) that updates ``rows`` output rows at once: :meth:`of` with the floor
        tr P̄, its limit lowered by :func:`burst_limit` where rows ≥ 2. With ``groups`` (the rows each arrival stream
        carries) the burst is probed with every group of ≥ 2 rows alone, as the filter updates it when only that
        stream arrives (and with all rows too where the groups are not updated one after another): two 2-row
        sensors probed together gave a limit 40x too high for one sensor's update (1.5e6 against 3.7e4; the kf and
        the fusion centre, each right to 1e-7 there, then differed by up to 2 % after long bursts)."""
        rescue = cls.of(C, R, pbar_trace(A, C, Q, R))
        if rows >= 2:
            sets = [list(range(C.shape[0]))] if groups is None else [list(g) for g in groups if len(g) >= 2]
            if groups is not None and not sequential and len(groups) > 1:
                sets.append(list(range(C.shape[0])))
            limit = min(burst_limit(A, C[r], Q, R[np.ix_(r, r)], rescue.limit) for r in sets)
            rescue = cls(C, R, limit)
        return rescue

    def flag(self, Pm: np.ndarray) -> np.ndarray:
        """(runs,) bool: the prior is nearly overflowed (or non-finite)."""
        with np.errstate(invalid="ignore", over="ignore"):
            return ~(batched.trace(Pm) <= self.limit)

    def apply(self, P: np.ndarray, Pm: np.ndarray, flagged: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Fix the flagged runs of the updated ``P`` (from prior ``Pm``); ``rows`` (m, runs) the arrived rows:
        no row arrived ⇒ P = P⁻ exactly; else the information form (unknown directions of P⁻ carry
        information 0, so a run recovers from an overflowed prior as soon as its packets arrive)."""
        idx = np.flatnonzero(flagged)
        if idx.size == 0:
            return P
        if P.shape[0] == 1 and self.C.shape[0] == 1:
            out = self._apply_scalar(P, Pm, idx, rows)
            if out is not None:
                return out
        P = P.copy()
        w = np.asarray(rows, dtype=float)[:, idx]
        prior = Pm[:, :, idx]
        arrived = w.sum(axis=0) > 0
        P[:, :, idx[~arrived]] = prior[:, :, ~arrived]
        if arrived.any():
            ww = w[:, arrived]
            m = self.C.shape[0]
            Rt = self.R[:, :, None] * (ww[:, None, :] * ww[None, :, :])
            Rt[np.arange(m), np.arange(m)] += 1.0 - ww
            Ct = self.C[:, :, None] * ww[:, None, :]  # (m, n, k)
            RiC = np.moveaxis(np.linalg.solve(np.moveaxis(Rt, -1, 0), np.moveaxis(Ct, -1, 0)), 0, -1)
            info = np.einsum("min,mjn->ijn", Ct, RiC)
            P[:, :, idx[arrived]] = information_update(prior[:, :, arrived], info)
        P[:, :, idx] = clean_nonfinite(P[:, :, idx])
        return P

    def _apply_scalar(self, P: np.ndarray, Pm: np.ndarray, idx: np.ndarray, rows: np.ndarray) -> np.ndarray | None:
        """:meth:`apply` for n = m = 1 on the flagged runs ``idx``, elementwise: the same operations on the same
        numbers (a test) without the batched LAPACK calls and axis moves. An arrived run's measurement information
        c r⁻¹ c is the same for every run (its row weight is 1): computed once, by :meth:`apply`'s own operations;
        then :func:`information_update` — 1/P⁻ for a finite prior (0 for ∞, the rescue's unknown direction),
        M = that + information, 1/M where M is finite and non-zero (else ∞), and the symmetrization 0.5·(x + x) —
        and :func:`clean_nonfinite` (NaN or −∞ ⇒ ∞). None (the general path decides) for a zero prior or a NaN in
        M, where the LAPACK calls raise."""
        w = np.asarray(rows, dtype=float)[0, idx]
        prior = Pm[0, 0, idx]
        arrived = w > 0  # (w.sum(axis=0) over the one row)
        x = prior.copy()  # nothing arrived: P⁻ exactly
        if arrived.any():
            a = np.flatnonzero(arrived)
            ww = w[a[:1]][None, :]
            Rt = self.R[:, :, None] * (ww[:, None, :] * ww[None, :, :])
            Rt[0, 0] += 1.0 - ww[0]
            Ct = self.C[:, :, None] * ww[:, None, :]
            RiC = np.moveaxis(np.linalg.solve(np.moveaxis(Rt, -1, 0), np.moveaxis(Ct, -1, 0)), 0, -1)
            info = np.einsum("min,mjn->ijn", Ct, RiC)[0, 0, 0]
            pa = prior[a]
            finite = np.isfinite(pa)
            if np.any(pa[finite] == 0):
                return None
            with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
                Y = np.where(finite, 1.0 / np.where(finite, pa, 1.0), 0.0)
                M = Y + info
                if np.isnan(M).any():
                    return None
                ok = np.isfinite(M) & (M != 0)
                o = np.where(ok, 1.0 / np.where(ok, M, 1.0), np.inf)
                x[a] = 0.5 * (o + o)
        x[np.isnan(x) | (x == -np.inf)] = np.inf  # clean_nonfinite: only +∞ (an unknown direction) stays
        P = P.copy()
        P[0, 0, idx] = x
        return P


# ----------------------------------------------------------------------------------------------
# the sensor model and the filter recursion
# ----------------------------------------------------------------------------------------------

def stream_rows(system, streams: int, path: str = "channel") -> tuple[tuple[int, ...], ...]:
    """Output rows each arrival stream carries: one stream = all of y_k (one packet); S streams =
    the S sensors of ``system.sensors`` (default: one sensor per output row)."""
    if streams == 1:
        return (tuple(range(system.m)),)
    groups = system.sensor_rows
    if streams == len(groups):
        return groups
    raise ConfigError.at(path, f"the channel has {streams} arrival streams, but the system has {len(groups)} "
                               f"sensor(s) ({'system.sensors' if system.sensors is not None else 'one per output row of C'}): "
                               f"a stream carries one sensor's whole measurement, or one stream carries all of y_k; "
                               f"set system.sensors: {streams} for {streams} identical sensors measuring C x")


def row_mask(gamma_t: np.ndarray, groups: tuple[tuple[int, ...], ...], m: int) -> np.ndarray:
    """(m, runs) row arrivals from stream arrivals ``gamma_t`` (S, runs)."""
    out = np.empty((m, gamma_t.shape[-1]), dtype=bool)
    for s, rows in enumerate(groups):
        out[list(rows)] = gamma_t[s]
    return out


def dare(A, C, Q, R) -> np.ndarray:
    """P* = A P* Aᵀ + Q − A P* Cᵀ (C P* Cᵀ + R)⁻¹ C P* Aᵀ, the steady-state prediction covariance (the filtering
    DARE), by ``scipy.linalg.solve_discrete_are`` on the dual problem; LinAlgError where it has no finite PSD
    solution with a (marginally) stable closed loop A − K C, K = A P* Cᵀ (C P* Cᵀ + R)⁻¹.

    scipy raises for most undetectable systems, but not for all: with an undetected unstable complex pair
    (A with eigenvalues 1.47 ± 0.32i, C = 0) it returned an indefinite matrix of size 1e16, the solution of the
    Lyapunov equation P = A P Aᵀ + Q, which no covariance satisfies. Checked here, so every caller refuses it.

    Memoized per (A, C, Q, R) (a copy is returned; the same LinAlgError is raised again): validation, P̄, P0 and
    the closed forms ask for the same system's P* many times (the quick reproduction: 503 solves of ~40 systems)."""
    A, C, Q, R = (np.atleast_2d(np.asarray(X, dtype=float)) for X in (A, C, Q, R))
    key = tuple((X.shape, X.tobytes()) for X in (A, C, Q, R))
    got = _DARE.get(key)
    if got is None:
        try:
            got = _dare(A, C, Q, R)
        except np.linalg.LinAlgError as exc:
            got = exc
        if len(_DARE) >= 256:  # a bound: the systems of this process's runs
            _DARE.clear()
        _DARE[key] = got
    if isinstance(got, np.linalg.LinAlgError):
        raise np.linalg.LinAlgError(*got.args)
    return got.copy()


_DARE: dict = {}


def _dare(A, C, Q, R) -> np.ndarray:
    """:func:`dare` without the memo."""
    X = scipy.linalg.solve_discrete_are(A.T, C.T, Q, R)
    if not np.all(np.isfinite(X)):
        raise np.linalg.LinAlgError("the solution is not finite")
    X = (X + X.T) / 2
    eig = np.linalg.eigvalsh(X)
    if eig[0] < -PSD_TOL * max(1.0, float(np.max(np.abs(eig)))):
        raise np.linalg.LinAlgError(f"the solution is not positive semi-definite (smallest eigenvalue {eig[0]:.3g})")
    K = np.linalg.solve(C @ X @ C.T + R, C @ X @ A.T).T
    rho = float(np.max(np.abs(np.linalg.eigvals(A - K @ C))))
    if rho > 1.0 + 1e-8:
        raise np.linalg.LinAlgError(f"the solution is not stabilizing (spectral radius of A − K C is {rho:.6g})")
    return X


BURST_PROBE_STEPS = 100
BURST_PROBE_DOUBLINGS = 40
""":func:`burst_limit` walks a loss burst step by step for BURST_PROBE_STEPS steps (a stable A converges long
before, an unstable one passes the rescue limit), then doubles its length BURST_PROBE_DOUBLINGS times."""

_BURST_LIMITS: dict = {}


def burst_limit(A, C, Q, R, limit: float) -> float:
    """The rescue limit for an update of several rows at once: the largest prior trace ≤ ``limit`` up to which the
    standard update of a loss burst's prior agrees with the same update in extended precision to
    ε·RESCUE_RATIO (the accuracy the trace rule gives one row: relative error ≈ 2e-8, max-entry norm).

    With one row S = C P Cᵀ + R is a number and the standard form's cancellation costs ε·‖P‖/‖P⁺‖, linear in the
    prior, which :class:`Rescue`'s trace rule bounds. With several rows S is ill-conditioned too when the prior is
    stretched along one direction (a loss burst of an unstable A), and the error grows like ‖P‖²: 2 states, 2 rows,
    a coupled R gave 1e-9 at tr P⁻ = 1.5e4, 6e-5 at 4e6 and a negative-definite P⁺ at 1.2e9, below that system's
    trace-rule limit 6.7e9 (numpy and the compiled kernels also disagreed there). So the burst is walked from P̄
    (P⁻ ← A P⁻ Aᵀ + Q, every step updated both ways) and the limit lowered to the last prior that agreed; a burst
    that converges (stable A) or passes ``limit`` keeps it. Where long double is no wider than double the walk has
    no reference and ``limit`` is kept. Memoized per system."""
    key = (A.tobytes(), C.tobytes(), Q.tobytes(), R.tobytes(), A.shape, C.shape, float(limit))
    if key in _BURST_LIMITS:
        return _BURST_LIMITS[key]
    out = limit
    if np.finfo(np.longdouble).eps < np.finfo(float).eps:
        tol = np.finfo(float).eps * RESCUE_RATIO
        try:
            P = one(update, dare(A, C, Q, R), C, R)
        except (np.linalg.LinAlgError, ValueError):
            P = np.eye(A.shape[0]) * max(float(np.trace(Q)), 1.0)
        last, Phi, W = 0.0, np.eye(A.shape[0]), np.zeros_like(Q)
        for i in range(BURST_PROBE_STEPS + BURST_PROBE_DOUBLINGS):
            if i < BURST_PROBE_STEPS:  # one lost step: P⁻ ← A P⁻ Aᵀ + Q (and A^L, the burst's own W_L)
                Pn, Phi, W = one(predict, P, A, Q), A @ Phi, one(predict, W, A, Q)
            else:  # then bursts twice as long each time (a marginally stable A grows only polynomially)
                Pn, W, Phi = Phi @ P @ Phi.T + W, Phi @ W @ Phi.T + W, Phi @ Phi
                Pn = (Pn + Pn.T) / 2
            t = float(np.trace(Pn))
            if not (np.isfinite(t) and t <= limit):
                break
            ref = _update_extended(Pn, C, R)
            err = float(np.max(np.abs(one(update, Pn, C, R) - ref)) / max(float(np.max(np.abs(ref))), 1e-300))
            if err > tol:
                out = last
                break
            if abs(t - last) <= 1e-10 * t:
                break  # converged (a stable A): no burst reaches further
            P, last = Pn, t
    _BURST_LIMITS[key] = out
    return out


def _update_extended(P: np.ndarray, C: np.ndarray, R: np.ndarray) -> np.ndarray:
    """P − P Cᵀ S⁻¹ C P in long double (Gaussian elimination with partial pivoting: numpy's solvers are double only),
    the reference of :func:`burst_limit`."""
    ld = np.longdouble
    P, C, R = P.astype(ld), C.astype(ld), R.astype(ld)
    S, B = C @ P @ C.T + R, C @ P
    m = S.shape[0]
    for c in range(m):
        p = c + int(np.argmax(np.abs(S[c:, c])))
        S[[c, p]], B[[c, p]] = S[[p, c]], B[[p, c]]
        f = S[:, c] / S[c, c]
        f[c] = 0.0  # every other row at once
        S -= np.outer(f, S[c])
        B -= np.outer(f, B[c])
    X = B / np.diag(S)[:, None]
    out = P - (C @ P).T @ X
    return ((out + out.T) / 2).astype(float)


def pbar_trace(A, C, Q, R) -> float | None:
    """tr P̄ (P̄ = g̃(P*), the filtered steady state with every packet) when C is rank-deficient and the
    DARE has a stabilizing solution; None otherwise (full-rank C needs no floor)."""
    if np.linalg.matrix_rank(C) == A.shape[0]:
        return None
    try:
        X = dare(A, C, Q, R)
    except (np.linalg.LinAlgError, ValueError):
        return None
    return float(np.trace(one(update, X, C, R)))


def _block_diagonal(R: np.ndarray, groups) -> bool:
    mask = np.zeros(R.shape, dtype=bool)
    for g in groups:
        mask[np.ix_(g, g)] = True
    return not np.any(R[~mask])


@dataclass(frozen=True)
class Filter:
    """The Kalman filter with intermittent observations over sensor groups (Sinopoli 2004 eqs. 8–9).

    ``groups``: output rows per arrival stream. With block-diagonal R across the groups (independent
    sensors) the sensors are processed one after another, each with its own γ (exact, and with one
    group it is the textbook update); otherwise one joint update of the arrived rows
    (:func:`update_rows`). Every step goes through :class:`Rescue`.
    """

    A: np.ndarray
    C: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    groups: tuple[tuple[int, ...], ...]
    rescue: Rescue
    sequential: bool

    @classmethod
    def of(cls, system, streams: int = 1, path: str = "channel") -> "Filter":
        groups = stream_rows(system, streams, path)
        A, C, Q, R = (np.ascontiguousarray(x, dtype=float) for x in (system.A, system.C, system.Q, system.R))
        sequential = _block_diagonal(R, groups)
        rows = max(len(g) for g in groups) if sequential else C.shape[0]  # rows updated at once
        return cls(A, C, Q, R, groups, Rescue.for_system(A, C, Q, R, rows, groups, sequential), sequential)

    def correct(self, Pm: np.ndarray, gamma_t: np.ndarray) -> np.ndarray:
        """P_{k|k} from P_{k|k−1} and the stream arrivals ``gamma_t`` (S, runs) of step k."""
        flagged = self.rescue.flag(Pm)
        if len(self.groups) == 1:
            P = update(Pm, self.C, self.R, gamma_t[0])
        elif self.sequential:
            P = Pm
            for s, rows in enumerate(self.groups):
                r = list(rows)
                P = update(P, self.C[r], self.R[np.ix_(r, r)], gamma_t[s])
        else:
            P = update_rows(Pm, self.C, self.R, row_mask(gamma_t, self.groups, self.C.shape[0]))
        if flagged.any():
            P = self.rescue.apply(P, Pm, flagged, row_mask(gamma_t, self.groups, self.C.shape[0]))
        return P

    def step(self, P: np.ndarray, gamma_t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(P_{k|k−1}, P_{k|k}) from P_{k−1|k−1}."""
        with np.errstate(over="ignore", invalid="ignore"):
            Pm = predict(P, self.A, self.Q)
            return Pm, self.correct(Pm, gamma_t)

    def run(self, P0: np.ndarray, gamma: np.ndarray, steps: Iterable[int],
            quantities: Iterable[str] = ("filtered",), backend: str = "numpy") -> Iterator[tuple[int, dict[str, np.ndarray]]]:
        """Yield (k, {quantity: P}) for k in ``steps``: ``gamma`` (S, horizon, runs), step k uses
        gamma[:, k − 1]; ``filtered`` = P_{k|k}, ``predicted`` = P_{k+1|k} = A P_{k|k} Aᵀ + Q.
        ``backend`` numba runs :func:`netkf_cli.linalg.kalman_numba.filter_advance` (the same equations
        compiled; runs the rescue flags are redone here, so the rescue policy is this module's)."""
        qs = check_quantities(quantities, ("filtered", "predicted"))
        want = sorted(set(int(k) for k in steps))
        runs = gamma.shape[-1]
        P = np.repeat(np.asarray(P0, dtype=float)[:, :, None], runs, axis=2) if P0.ndim == 2 else P0
        if backend == "numba" and self.sequential:
            yield from self._run_compiled(P, gamma, want, qs)
            return
        t = 0
        for k in want:
            while t < k:
                _, P = self.step(P, gamma[:, t])
                t += 1
            yield k, report(P, qs, self.A, self.Q)

    def _run_compiled(self, P, gamma, want, qs):
        """The numba path of :meth:`run`: a kernel generated for this system where it can be
        (:mod:`netkf_cli.linalg.kalman_codegen`: n ≤ 6, sensor groups of ≤ 4 rows; :meth:`stream_generated`),
        the generic compiled step otherwise; runs flagged by the rescue test continue on the numpy core
        from their start."""
        n = self.A.shape[0]
        P = np.array(P, dtype=float, order="C")
        if kc.supported(n, self.groups):
            for k, Pk in self.stream_generated(P, gamma, want):
                yield k, report(Pk, qs, self.A, self.Q)
            return
        from netkf_cli.linalg import kalman_numba as kn  # optional dependency (numba): compiled primitives

        P_init = P.copy()  # the flagged runs restart from their own P0
        flag = np.zeros(P.shape[-1], dtype=np.bool_)
        if any(list(g) != list(range(g[0], g[0] + len(g))) for g in self.groups):
            raise ValueError("compiled filter: sensor groups must be contiguous rows")
        gam_r = np.ascontiguousarray(gamma.transpose(2, 0, 1))  # run-major for the compiled loop
        starts = np.array([g[0] for g in self.groups], dtype=np.int64)
        lens = np.array([len(g) for g in self.groups], dtype=np.int64)

        def advance(t0, t1):
            kn.filter_advance(P, self.A, self.C, self.Q, self.R, gam_r, starts, lens, t0, t1, self.rescue.limit, flag)
            return P.copy()

        redo = FlaggedRuns(P_init, lambda Pk, tt, ix: self.step(Pk, gamma[:, tt][:, ix])[1])
        t = 0
        for k in want:
            out = redo.fill(advance(t, k), flag, k)
            t = k
            yield k, report(out, qs, self.A, self.Q)

    def generated_kernel(self):
        """kf's kernel generated for this system (:func:`kalman_codegen.kernel`: ``adv(T, gam, t0, t1, flag)``)."""
        return kc.kernel(self.A, self.C, self.Q, self.R, self.groups, self.rescue.limit)

    def stream_generated(self, P_init: np.ndarray, gamma: np.ndarray, want: list[int],
                         flagged=None) -> Iterator[tuple[int, np.ndarray]]:
        """Yield ``(k, P_{k|k})`` (a new array each step) for k in ``want`` on the generated kernel, from
        ``P_init`` (n, n, runs). A run the kernel flags for the :class:`Rescue` at step t is reported from
        the numpy core (:meth:`step` from its own P0, bit for bit the numpy path) from the first step of
        ``want`` ≥ t on. One kernel pass while no run is flagged; at the first flag, the step at which
        each run is first flagged comes from a second pass from ``P_init`` (``flagged(adv, P_init, gam,
        upto)``, default :func:`first_flagged`), and the runs it names advance once through the numpy core
        in step with the reporting pass — no restart from P0 when runs are flagged at many different
        steps (bursty loss: O(flagged runs × steps²) numpy steps), no per-step index set arithmetic."""
        n, runs = self.A.shape[0], gamma.shape[-1]
        if not want:
            return
        P_init = np.array(P_init, dtype=float, order="C")
        adv = self.generated_kernel()
        gam = np.ascontiguousarray(gamma)
        idx = k0 = Pn = None
        tn = 0
        T, flag, t = kc.pack(P_init), np.zeros(runs, dtype=np.bool_), 0
        for k in want:  # the kernel's calls, reported; the flagged runs on the numpy core
            adv(T, gam, t, k, flag)
            t = k
            Pk = kc.unpack(T, n)
            if idx is None and flag.any():  # the first flag: when is every run first flagged?
                first = (flagged or first_flagged)(adv, P_init, gam, want[-1])
                idx = np.flatnonzero(first <= want[-1])
                # a run flagged at step t is reported from the numpy core from the first step of want ≥ t on
                k0 = np.asarray(want, dtype=np.int64)[np.searchsorted(want, first[idx])]
                Pn = P_init[:, :, idx]
            if idx is not None:
                while tn < k:
                    Pn = self.step(Pn, gamma[:, tn][:, idx])[1]
                    tn += 1
                sel = k0 <= k
                if sel.any():
                    Pk[:, :, idx[sel]] = Pn[:, :, sel]
            yield k, Pk


def first_flagged(adv, P_init: np.ndarray, gam: np.ndarray, upto: int) -> np.ndarray:
    """Per run, the first step t ≤ ``upto`` after which the generated kernel ``adv`` (:meth:`Filter.generated_kernel`)
    has flagged it for the rescue (``upto`` + 1: never), from the kernel one step at a time (its flag is
    deterministic per step and stays set)."""
    runs = gam.shape[-1]
    first = np.full(runs, upto + 1, dtype=np.int64)
    T, flag = kc.pack(P_init), np.zeros(runs, dtype=np.bool_)
    for t in range(upto):
        adv(T, gam, t, t + 1, flag)
        first[flag & (first > upto)] = t + 1
    return first


class FlaggedRuns:
    """The runs a compiled kernel flagged for :class:`Rescue`, carried on the numpy core instead.

    ``step(P, t, idx)`` is the numpy step t → t + 1 of runs ``idx``. :meth:`fill` at step k: the runs
    already on the numpy core advance from the last step, the newly flagged ones restart from their P0
    (``P_init``) up to k, and their covariances replace the kernel's in ``out`` (n, n, runs)."""

    def __init__(self, P_init: np.ndarray, step):
        self.P_init, self.step = P_init, step
        self.idx = np.zeros(0, dtype=np.int64)
        self.Pn = P_init[:, :, :0]
        self.t = 0

    def fill(self, out: np.ndarray, flag: np.ndarray, k: int) -> np.ndarray:
        flagged = np.flatnonzero(flag)
        new = np.setdiff1d(flagged, self.idx) if flagged.size else flagged  # usually none: no set operation
        if self.idx.size:  # runs already on the numpy core: one step at a time
            for tt in range(self.t, k):
                self.Pn = self.step(self.Pn, tt, self.idx)
        if new.size:  # newly flagged: the numpy core from their P0 up to k
            Pnew = self.P_init[:, :, new]
            for tt in range(k):
                Pnew = self.step(Pnew, tt, new)
            idx, Pn = np.concatenate([self.idx, new]), np.concatenate([self.Pn, Pnew], axis=2)
            order = np.argsort(idx)
            self.idx, self.Pn = idx[order], Pn[:, :, order]
        self.t = k
        if self.idx.size:
            out[:, :, self.idx] = self.Pn
        return out


AUTO_MIN_RUN_STEPS = 1_000_000
"""``backend: auto`` compiles only chunks of at least this many run-steps (20 000 runs × 50 steps): a new
system's kernel costs ~2 s to generate and compile once per machine, then ~0.5 s per process to import
numba and load it (measured 2026-12-04: 0.26 + 0.24 s), which the compiled recursion (~10× the numpy core
at n = 4, benchmarks/) repays within the first few such chunks (Shi Fig. 9, 10 chunks of 20 000 × 60 on
the 4-state vehicle: `netkf run` 5.1 -> 4.8 s wall, the same CSVs); small test-sized runs stay on numpy."""

EAGER_MIN_RUN_STEPS = 50_000
"""``backend: auto``'s floor within :func:`eager_compile` (``netkf reproduce``): its processes import numba anyway and
its full size compiles the same per-system kernels, so only the compiled step's speed counts, which beats numpy's
per-step overhead from a few 10⁴ run-steps. The quick reproduction's batches (5e4-4.5e5 run-steps) move to the
compiled kernels (workers' CPU 18.7 -> 14.5-15.0 s, 2026-12-06); every full-size batch is ≥ AUTO_MIN_RUN_STEPS
already. Compiled and numpy differ by round-off only (tests/unit/test_kalman_core)."""

_eager = False


@contextlib.contextmanager
def eager_compile():
    """Within the block, ``backend: auto`` compiles small batches too: the Kalman recursions from
    EAGER_MIN_RUN_STEPS run-steps, the engine's reductions from ``engine.EAGER_REDUCE_MIN_RUNS`` runs. For a command
    that pays numba's import and the systems' kernels anyway (``netkf reproduce``); still a function of the batch's
    size alone, so the numbers do not depend on the process's state (the manifest says which backend each estimator
    ran on; the reductions agree with numpy's to round-off with the same decisions)."""
    global _eager
    old, _eager = _eager, True
    try:
        yield
    finally:
        _eager = old


def eager() -> bool:
    """Whether this is inside :func:`eager_compile`."""
    return _eager


def numba_available() -> bool:
    """numba importable (an optional dependency: where it is missing, everything runs on numpy). Once it is,
    LLVM's pages are unmapped after each compilation (:mod:`netkf_cli.core.llvm_pages`)."""
    try:
        import numba  # noqa: F401  (optional: probed only, never required)
    except ImportError:
        return False
    llvm_pages.install()
    return True


def choose_backend(backend: str, f: "Filter", run_steps: int, path: str = "estimator.backend") -> str:
    """The backend that runs: ``numpy``; ``numba`` (refused with a message when numba is missing or the
    recursion is not sequential); ``auto`` = numba when importable, the sensors are independent
    (block-diagonal R) and the batch has ≥ AUTO_MIN_RUN_STEPS run-steps (EAGER_MIN_RUN_STEPS within
    :func:`eager_compile`), else numpy."""
    floor = EAGER_MIN_RUN_STEPS if _eager else AUTO_MIN_RUN_STEPS
    if backend == "numpy" or (backend == "auto" and run_steps < floor):
        return "numpy"  # (auto on a small batch: numba is not even imported, ~0.5 s saved per process)
    ok = numba_available() and f.sequential
    if backend == "numba":
        if not ok:
            raise ConfigError.at(path, "backend numba needs numba installed and independent sensors (R block-diagonal "
                                       "across the channel's streams); use backend: numpy or auto")
        return "numba"
    return "numba" if ok else "numpy"


def report(P_filtered: np.ndarray, quantities: tuple[str, ...], A: np.ndarray, Q: np.ndarray) -> dict[str, np.ndarray]:
    """{quantity: P} from P_{k|k}: ``predicted`` is A P_{k|k} Aᵀ + Q (P_{k+1|k})."""
    out = {}
    for q in quantities:
        if q == "filtered":
            out[q] = P_filtered
        elif q == "predicted":
            with np.errstate(over="ignore", invalid="ignore"):
                out[q] = predict(P_filtered, A, Q)
    return out


def check_quantities(quantities: Iterable[str], offered: Iterable[str], who: str = "this estimator") -> tuple[str, ...]:
    """The requested quantities as a tuple, or a ConfigError naming what ``who`` offers."""
    qs = (quantities,) if isinstance(quantities, str) else tuple(quantities)
    offered = tuple(offered)
    bad = [q for q in qs if q not in offered]
    if bad:
        raise ConfigError.at("analysis.quantity", f"{who} does not report {', '.join(bad)}; it reports "
                                                  f"{', '.join(offered)}")
    return qs


def one(fn, P: np.ndarray, *args, **kw) -> np.ndarray:
    """Apply a batched primitive to a single (n, n) matrix (runs = 1)."""
    return fn(np.asarray(P, dtype=float)[:, :, None], *args, **kw)[:, :, 0]


# ----------------------------------------------------------------------------------------------
# appended (issue 19, the fading receivers): the rescue with per-run added measurement noise
# ----------------------------------------------------------------------------------------------

def rescue_noisy(rescue: Rescue, P: np.ndarray, Pm: np.ndarray, flagged: np.ndarray, gamma: np.ndarray,
                 extra_R: np.ndarray) -> np.ndarray:
    """:meth:`Rescue.apply` for one packet carrying all of y_k with noise R + ``extra_R`` (m, m, runs)
    per run (communication noise on top of the sensor noise; Mostofi & Murray 2009 eqs 27–28,
    σ_z² = σ_n² I + R): a flagged run whose packet was lost (``gamma`` (runs,) = 0) keeps P⁻ exactly;
    one whose packet arrived is redone as (P⁻⁻¹ + Cᵀ (R + extra_R)⁻¹ C)⁻¹ (:func:`information_update`,
    unknown directions of P⁻ carry information 0); then :func:`clean_nonfinite`. With ``extra_R`` = 0
    this is :meth:`Rescue.apply` with every row arrived."""
    idx = np.flatnonzero(flagged)
    if idx.size == 0:
        return P
    P = P.copy()
    prior = Pm[:, :, idx]
    arrived = np.asarray(gamma)[idx] > 0
    P[:, :, idx[~arrived]] = prior[:, :, ~arrived]
    if arrived.any():
        C = rescue.C
        Rt = rescue.R[:, :, None] + extra_R[:, :, idx[arrived]]
        Ct = np.broadcast_to(C[:, :, None], C.shape + (int(arrived.sum()),))
        RiC = np.moveaxis(np.linalg.solve(np.moveaxis(Rt, -1, 0), np.moveaxis(Ct, -1, 0)), 0, -1)
        info = np.einsum("min,mjn->ijn", Ct, RiC)
        P[:, :, idx[arrived]] = information_update(prior[:, :, arrived], info)
    P[:, :, idx] = clean_nonfinite(P[:, :, idx])
    return P
    P = P.copy()
    prior = Pm[:, :, idx]
    redo = np.isfinite(prior).all(axis=(0, 1)) & (np.asarray(gamma)[idx] > 0)
    if redo.any():
        C = rescue.C
        Rt = rescue.R[:, :, None] + extra_R[:, :, idx[redo]]
        Ct = np.broadcast_to(C[:, :, None], C.shape + (int(redo.sum()),))
        RiC = np.moveaxis(np.linalg.solve(np.moveaxis(Rt, -1, 0), np.moveaxis(Ct, -1, 0)), 0, -1)
        info = np.einsum("min,mjn->ijn", Ct, RiC)
        P[:, :, idx[redo]] = information_update(prior[:, :, redo], info)
    bad = idx[~np.isfinite(P[:, :, idx]).all(axis=(0, 1))]
    P[:, :, bad] = np.inf
    return P


# ----------------------------------------------------------------------------------------------
# appended (issue 19, the Markov-mode filters): the update when an innovation can have zero variance
# ----------------------------------------------------------------------------------------------

def update_pinv(P: np.ndarray, C: np.ndarray, R: np.ndarray, floor: np.ndarray,
                innov: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """(P − P Cᵀ S⁺ C P, P Cᵀ S⁺ e) per run, S = C P Cᵀ + R, where S⁺ gives zero gain to innovation
    directions whose variance is ≤ ``floor`` (runs,): a measurement the receiver already knows carries
    no information (a held packet or an already-known delayed one, Moayedi, Soh & Foo 2009 modes 2
    and 4, where R = 0 and S can vanish). ``innov`` (m, runs) is the innovation e (the second output
    is then the state correction K e; else None).

    A run whose S is regular (every pivot below > floor) is :func:`update` / :func:`gain` bit for bit.
    Otherwise S⁺ is the generalized inverse of symmetric pivoted elimination: the rows of the
    measurement are decorrelated one at a time (pivot = the largest remaining innovation variance s,
    P ← P − b bᵀ / s with b the pivot row of the residual C P — the sequential scalar update,
    Anderson & Moore 1979 §6.4), stopping when s ≤ floor. Any generalized inverse gives the same
    update when the remaining rows are exactly redundant (their residual variance is 0).
    """
    floor = np.broadcast_to(np.asarray(floor, dtype=float), (P.shape[-1],))
    m = C.shape[0]
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        PCt, S = innovation(P, C, R)
        if m == 1:
            reg = S[0, 0] > floor
            Pe, dxe = P, None
        else:
            Pe, dxe, reg = _pivoted_update(P, PCt, S, floor, innov)
        if reg.all():
            Pf = update(P, C, R)
            dx = None if innov is None else batched.matmul(gain(P, C, R), innov[:, None, :])[:, 0, :]
            return Pf, dx
        Pf = np.array(P if m == 1 else Pe, copy=True)
        dx = None if innov is None else (np.zeros((P.shape[0], P.shape[-1])) if m == 1 else dxe.copy())
        idx = np.flatnonzero(reg)
        if idx.size:
            Pr = P[:, :, idx]
            Pf[:, :, idx] = update(Pr, C, R)
            if innov is not None:
                dx[:, idx] = batched.matmul(gain(Pr, C, R), innov[:, None, idx])[:, 0, :]
        return Pf, dx


def _pivoted_update(P, PCt, S, floor, innov):
    """The pivoted sequential update of :func:`update_pinv` for every run: (P_f, K e or None, regular)."""
    n, runs = P.shape[0], P.shape[-1]
    m = S.shape[0]
    S = S.copy()
    B = PCt.swapaxes(0, 1).copy()  # (m, n, runs): C P
    e = None if innov is None else np.array(innov, dtype=float, copy=True)
    out = P.copy()
    dx = None if innov is None else np.zeros((n, runs))
    regular = np.ones(runs, dtype=bool)
    cols = np.arange(runs)
    idx = np.arange(m)
    for _ in range(m):
        diag = S[idx, idx]  # (m, runs); pivoted rows are 0
        p = np.argmax(diag, axis=0)
        s = diag[p, cols]
        ok = s > floor
        regular &= ok
        sinv = np.where(ok, 1.0 / np.where(ok, s, 1.0), 0.0)
        b = B[p, :, cols].T  # (n, runs)
        out -= b[:, None, :] * b[None, :, :] * sinv
        f = S[:, p, cols] * sinv  # (m, runs)
        Sp = S[p, :, cols].T  # (m, runs)
        S -= f[:, None, :] * Sp[None, :, :]
        B -= f[:, None, :] * b[None, :, :]
        if e is not None:
            ep = e[p, cols]
            dx += b * (ep * sinv)
            e -= f * ep
        S[p, :, cols] = 0.0
        S[:, p, cols] = 0.0
        B[p, :, cols] = 0.0
    return batched.sym(out), dx, regular


# ----------------------------------------------------------------------------------------------
# appended (issue 19, the smoother): the RTS step in conditioning form, through the one rescue policy
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class SmoothStep:
    """One Rauch–Tung–Striebel step written as a measurement update (exact for huge P_{t|t}).

        P_{t|T} = P_{t|t, x_{t+1}} + J P_{t+1|T} Jᵀ,    J = P_{t|t} Aᵀ (A P_{t|t} Aᵀ + Q)⁻¹,
        P_{t|t, x_{t+1}} = P_{t|t} − J A P_{t|t}

    P_{t|t, x_{t+1}} is the update of P_{t|t} by the "measurement" x_{t+1} = A x_t + w_t (C = A, R = Q)
    and J its gain, so this is the textbook RTS step Pf + J (Ps − Pp) Jᵀ (since J Pp Jᵀ = J A Pf)
    without the subtraction of the two large terms Pf and J Pp Jᵀ: the update goes through
    :class:`Rescue` ``.for_system(A, A, Q, Q, n)`` (information form (Pf⁻¹ + AᵀQ⁻¹A)⁻¹ for tr Pf > limit — e.g.
    after a loss at A = diag(1e6, 0.5), where the covariance form cancels every digit). The "measurement" has n
    rows, so the limit is :func:`burst_limit`'s for n ≥ 2: with the trace rule alone (Rescue.of) a 2-state
    system after a 24-step loss burst gave a negative-definite P_{26|28} of trace 49.7 where the exact one is 2.09
    (tr Pf 1.2e9 under the trace rule's 1.9e9; burst_limit: 2.7e4). Q singular: no rescue. A non-finite result
    is ``inf``.
    """

    A: np.ndarray
    Q: np.ndarray
    rescue: Rescue | None

    @classmethod
    def of(cls, A: np.ndarray, Q: np.ndarray) -> "SmoothStep":
        A, Q = np.asarray(A, dtype=float), np.asarray(Q, dtype=float)
        ok = np.linalg.matrix_rank(Q) == Q.shape[0]
        return cls(A, Q, Rescue.for_system(A, A, Q, Q, A.shape[0]) if ok else None)

    def __call__(self, Ps_next: np.ndarray, Pf: np.ndarray) -> np.ndarray:
        """P_{t|T} from P_{t+1|T} (``Ps_next``) and P_{t|t} (``Pf``), both (n, n, runs)."""
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            J = gain(Pf, self.A, self.Q)
            P = update(Pf, self.A, self.Q)
            if self.rescue is not None:
                flagged = self.rescue.flag(Pf)
                if flagged.any():
                    P = self.rescue.apply(P, Pf, flagged, np.ones((self.A.shape[0], Pf.shape[-1]), dtype=bool))
            out = batched.sym(P + batched.matmul(batched.matmul(J, Ps_next), J.swapaxes(0, 1)))
        bad = ~np.isfinite(out).all(axis=(0, 1))
        if bad.any():
            out[:, :, bad] = np.inf
        return out


# ----------------------------------------------------------------------------------------------
# appended (issue 19, the fusion strategies): the update with c identical sensors per run
# ----------------------------------------------------------------------------------------------

def update_counts(P: np.ndarray, C: np.ndarray, R: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """P − c·P Cᵀ (c·C P Cᵀ + R)⁻¹ C P per run: the update with c identical, independent sensors
    (each y_i = C x + v_i, v_i ~ N(0, R)) that arrived, ``counts`` (runs,) real ≥ 0.

    Chiuso & Schenato eq. (14), Φ_f(P, ℓ): fusing c identical measurements equals fusing their
    average, whose noise is R/c; it is the information form (P⁻¹ + c·CᵀR⁻¹C)⁻¹ and equals c
    sequential :func:`update` calls (tested). c = 0 leaves P unchanged; c = 1 is :func:`update`
    bit for bit (the same operations, the factors 1.0 exact). Rescue: as :class:`Filter` does, flag
    before with the stacked sensors' :class:`Rescue` and ``apply`` with the arrived rows.
    """
    c = np.asarray(counts, dtype=float)
    PCt = batched.right(P, C.T)
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        S = batched.left(C, PCt) * c[None, None, :] + R[:, :, None]
        corr = batched.matmul(PCt, batched.solve_small(S, PCt.swapaxes(0, 1))) * c[None, None, :]
        return batched.sym(P - corr)
