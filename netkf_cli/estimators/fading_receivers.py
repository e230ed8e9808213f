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
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from netkf_cli import batched
from netkf_cli.analysis import fading as fa
from netkf_cli.channels.fading import Snr
from netkf_cli.errors import ConfigError
from netkf_cli.spec import EstimatorModel

BackendKind = Literal["auto", "numpy", "numba"]


class ReceiverEstimator(EstimatorModel):
    """``kind: receiver`` — Mostofi & Murray 2009 receiver scenario 1, 2 or 3 with drop threshold Υ_T (eq. 5).

    Works from the ``snr`` trace of a ``fading`` channel: per step, a packet with Υ_t < Υ_T is
    dropped, a kept one carries communication noise of variance σ_n²(Υ_t) (the channel's noise
    model). Reports the one-step prediction error covariance after y_k, P_{k+1|k} — the paper's
    P[k+1] (eqs 6, 12, 28). ``system.P0`` is P_{0|0} as everywhere in netkf (P̄ when left out), so
    the prior of y_1 is A P0 Aᵀ + Q. (The paper-figure analyses ``fading_*`` use the paper's own
    convention instead: P[0] = P0 is the prior of the first packet.)
    """

    accepts: ClassVar[frozenset[str]] = frozenset({"snr"})
    quantity: ClassVar[str] = "P_{k+1|k}"

    kind: Literal["receiver"]
    scenario: Literal[1, 2, 3] = Field(description="1: drop erroneous packets (eqs 7–8); 2: no cross-layer path "
                                                   "(eqs 10–13); 3: cross-layer path (eqs 27–28)")
    threshold: Snr | None = Field(None, description="drop threshold Υ_T with unit (analyses that sweep Υ_T ignore it)")
    backend: BackendKind = Field("auto", description="numpy (reference) | numba (compiled, equal to rounding) | "
                                                     "auto = numba when importable")

    def check(self, system, channel) -> None:
        """Refuse pairs that cannot work: a channel without SNR, a missing Υ_T, scenario 2 with m > n."""
        if "snr" not in getattr(channel, "trace_kinds", frozenset()):
            raise ConfigError.at("estimator.kind", "the fading receivers need a channel with an SNR trace "
                                                   "(kind: fading); compatible trace kinds: snr")
        if self.threshold is None:
            raise ConfigError.at("estimator.threshold", "give the drop threshold Υ_T, e.g. {value: 14, unit: linear}")
        if self.scenario == 2 and system.m > system.n:
            raise ConfigError.at("system.C", "scenario 2 needs at most as many outputs as states")
        if self.backend == "numba":
            resolve_backend("numba")

    def model(self, system, noise) -> "ReceiverModel":
        return ReceiverModel(self.scenario, system.A, system.C, system.Q, system.R, noise)

    def covariances(self, system, trace, steps):
        """Yield (k, P_{k+1|k}) for k in ``steps`` (ascending, 1..horizon), shaped (n, n, runs); overflow → inf/NaN."""
        noise = trace.meta.get("noise")
        if noise is None or trace.snr is None:
            raise ConfigError.at("channel", "the receiver needs an SNR trace with its noise model (channel kind fading)")
        rm = self.model(system, noise)
        from netkf_cli import riccati

        P00 = riccati.pbar(system) if system.P0 is None else np.asarray(system.P0, dtype=float)
        P10 = rm.A @ P00 @ rm.A.T + rm.Q  # prior of y_1 (one prediction from P_{0|0})
        st = Stepper(rm, 0.5 * (P10 + P10.T), trace.runs, self.backend)
        T = self.threshold.linear
        todo = sorted(int(k) for k in steps)
        k = 0
        for t in range(trace.horizon):
            if not todo:
                return
            snr = trace.snr[t]
            keep = snr >= T
            st.step(keep, rm.noise(np.where(keep, snr, 1.0)))
            k = t + 1
            while todo and todo[0] == k:
                todo.pop(0)
                yield k, np.array(st.true)


# --------------------------------------------------------------------------- batched linear algebra


def _mm(X, Y):
    return batched.matmul(X, Y)


def _cmm(A, X):
    return np.einsum("ij,jkb->ikb", A, X)


def _mmc(X, A):
    return np.einsum("ijb,jk->ikb", X, A)


def _sym(X):
    return batched.sym(X)


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
            out = np.empty_like(Y)
            out[0, 0], out[0, 1], out[1, 0], out[1, 1] = d / det, -b / det, -c / det, a / det
        elif m == 3:
            a, b, c = Y[0, 0], Y[0, 1], Y[0, 2]
            d, e, f = Y[1, 0], Y[1, 1], Y[1, 2]
            g, h, i = Y[2, 0], Y[2, 1], Y[2, 2]
            A_, B_, C_ = e * i - f * h, -(d * i - f * g), d * h - e * g
            det = a * A_ + b * B_ + c * C_
            out = np.empty_like(Y)
            out[0, 0], out[0, 1], out[0, 2] = A_ / det, -(b * i - c * h) / det, (b * f - c * e) / det
            out[1, 0], out[1, 1], out[1, 2] = B_ / det, (a * i - c * g) / det, -(a * f - c * d) / det
            out[2, 0], out[2, 1], out[2, 2] = C_ / det, -(a * h - b * g) / det, (a * e - b * d) / det
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
    """A P Aᵀ + Q (symmetrized): the shared batched time update."""
    return batched.riccati_h(P, rm.A, rm.Q)


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
        return [batched.riccati_h(Pp, A, Q)]
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


# --------------------------------------------------------------------------- the batched engine (numpy | numba)

def numba_available() -> bool:
    """True iff numba can be imported (``backend: auto`` then compiles)."""
    try:
        import numba  # noqa: F401
    except ImportError:
        return False
    return True


def resolve_backend(backend: str) -> str:
    """``auto`` → ``numba`` when importable, else ``numpy``; ``numba`` without numba is a ConfigError."""
    if backend == "auto":
        return "numba" if numba_available() else "numpy"
    if backend == "numba" and not numba_available():
        raise ConfigError.at("estimator.backend", "backend numba needs numba: pip install 'netkf[fast]'")
    return backend


def _constants(rm: ReceiverModel):
    """(mode, G, r, M1, M2) for the compiled step (see ``_fading_numba``)."""
    n = rm.n
    G = np.zeros((n, n, 1))
    r = np.ones(1)
    M1 = M2 = np.zeros((n, n))
    if rm.scenario in (1, 3):
        mode = 0
        r, U = np.linalg.eigh(rm.R)
        Ct = U.T @ rm.C
        G = np.ascontiguousarray(np.einsum("ia,ib->abi", Ct, Ct))
    elif rm.state_size() == 1:
        mode = 1
        Ci = np.linalg.inv(rm.C)
        M1 = rm.A @ Ci @ Ci.T @ rm.A.T
        M2 = rm.A @ Ci @ rm.R @ Ci.T @ rm.A.T + rm.Q
    else:
        mode = 2
    return mode, G, np.ascontiguousarray(r, dtype=float), np.ascontiguousarray(M1), np.ascontiguousarray(M2)


class Stepper:
    """Batched receiver recursion over B runs (columns): ``step(keep, s2, mu)`` advances one time step.

    ``backend`` ``numpy`` (reference: :func:`kept_update` / :func:`drop_update`) or ``numba``
    (compiled, same inputs, equal to rounding). With ``want_u`` the burst-conditioned estimate U
    is advanced as well (module doc). ``true`` is the true error covariance P[k] (n, n, B).
    """

    def __init__(self, rm: ReceiverModel, P0, B: int, backend: str = "numpy", want_u: bool = False):
        self.rm, self.backend, self.want_u = rm, resolve_backend(backend), want_u
        self.state = initial_state(rm, P0, B)
        self.U = true_cov(self.state).copy() if want_u else None
        if self.backend == "numba":
            from netkf_cli.estimators import _fading_numba as fnb

            self._c = _constants(rm)
            self._nb_generic = fnb.step
            spec = fnb.specialized_step(self._c[0], rm.n, rm.C.shape[0])
            self._nb = (lambda mode, *a: spec(*a)) if spec is not None else fnb.step
            self._A, self._Q = np.ascontiguousarray(rm.A), np.ascontiguousarray(rm.Q)
            self._C, self._R = np.ascontiguousarray(rm.C), np.ascontiguousarray(rm.R)
            self._dummy_u = np.zeros((1, rm.n, rm.n))
            # run-major copies for the compiled loop (see _fading_numba.step)
            self.state = [np.ascontiguousarray(np.moveaxis(X, 2, 0)) for X in self.state]
            if want_u:
                self.U = np.ascontiguousarray(np.moveaxis(self.U, 2, 0))

    @property
    def true(self) -> np.ndarray:
        """P[k], shape (n, n, B)."""
        X = true_cov(self.state)
        return np.moveaxis(X, 0, 2) if self.backend == "numba" else X

    @property
    def cond(self) -> np.ndarray:
        """U[k] (burst-conditioned estimate), shape (n, n, B)."""
        return np.moveaxis(self.U, 0, 2) if self.backend == "numba" else self.U

    def kept_true(self, s2: np.ndarray) -> np.ndarray:
        """P[k+1] (n, n, B) if every run's packet were KEPT with noise variance s2; the state is unchanged."""
        if self.backend == "numba":
            mode, G, r, M1, M2 = self._c
            Pf, Pt = (np.array(X) for X in (self.state[0], self.state[-1]))
            s2_ = np.zeros(Pt.shape[0]) if self.rm.scenario == 1 else np.ascontiguousarray(s2, dtype=float)
            keep = np.ones(Pt.shape[0], dtype=bool)
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                self._nb(mode, Pf, Pt, self._dummy_u, keep, s2_, s2_, False,
                         self._A, self._Q, self._C, self._R, G, r, M1, M2)
            return np.moveaxis(Pt, 0, 2)
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            return true_cov(kept_update(self.rm, self.state, s2))

    def step(self, keep: np.ndarray, s2: np.ndarray, mu: np.ndarray | None = None) -> None:
        rm = self.rm
        if self.backend == "numba":
            mode, G, r, M1, M2 = self._c
            Pt = self.state[-1]
            Pf = self.state[0]
            s2_ = np.zeros(keep.shape[0]) if rm.scenario == 1 else np.ascontiguousarray(s2, dtype=float)
            U = self.U if self.want_u else self._dummy_u
            mu_ = np.ascontiguousarray(mu, dtype=float) if self.want_u else s2_
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                self._nb(mode, Pf, Pt, U, np.ascontiguousarray(keep), s2_, mu_, self.want_u,
                         self._A, self._Q, self._C, self._R, G, r, M1, M2)
            return
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            ku = kept_update(rm, self.state, s2)
            du = drop_update(rm, self.state)
            if self.want_u:
                self.U = mu[None, None, :] * _drop(rm, self.U) + (1.0 - mu[None, None, :]) * true_cov(ku)
            self.state = [_where(keep, a, b) for a, b in zip(ku, du)]


def covariance_paths(rm: ReceiverModel, snr: np.ndarray, threshold, P0, record=None, backend: str = "numpy") -> np.ndarray:
    """Recursion along given SNR traces ``snr`` (horizon, B) with per-column threshold Υ_T.

    Returns the true error covariance at the steps in ``record`` (default: every step 0..horizon),
    shape (len(record), n, n, B).
    """
    H, B = snr.shape
    T = np.broadcast_to(np.asarray(threshold, dtype=float), (B,))
    record = list(range(H + 1)) if record is None else list(record)
    out = np.empty((len(record), rm.n, rm.n, B))
    st = Stepper(rm, P0, B, backend)
    pos = {k: i for i, k in enumerate(record)}
    if 0 in pos:
        out[pos[0]] = st.true
    for k in range(H):
        keep = snr[k] >= T
        st.step(keep, rm.noise(np.where(keep, snr[k], 1.0)))
        if k + 1 in pos:
            out[pos[k + 1]] = st.true
    return out


def burst_conditioned_paths(rm: ReceiverModel, rng: np.random.Generator, thresholds: np.ndarray, mus: np.ndarray,
                            snr_avg: float, P0, horizon: int, record, backend: str = "numpy",
                            s2_given_kept: np.ndarray | None = None, final_strata: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Simulate the i.i.d. exponential channel and return (path P[k], burst-conditioned U[k]) at ``record``.

    ``thresholds`` and ``mus`` (= μ_ave(Υ_T), eq. 15) have one entry per batch column. Both outputs
    have shape (len(record), n, n, B); both are unbiased for E P[k] (module doc), U with far smaller
    variance. Per step: keep = (uniform ≥ μ), Υ' = Υ_T + Exp(Υ_ave) for a kept packet.

    ``s2_given_kept`` (per column): replace σ_n²(Υ') by its conditional mean E[σ_n²(Υ) | Υ ≥ Υ_T] =
    σ²_n,ave/(1 − μ_ave) (eqs 15–16) — exact Rao–Blackwellization for scenario 2, whose error
    covariance is affine in every σ_n² with coefficients fixed by the drop pattern (eq. 12 / Joseph
    form with a σ_n²-independent gain); no exponential is drawn then.

    ``final_strata`` = K > 0 (sampled σ_n² only): at the last recorded step the kept-packet term of U
    is averaged over K stratified draws of Υ' (unbiased; removes the variance of the last packet's SNR,
    which dominates for scenario 3 at small Υ_T where μ ≈ 0 and U ≈ F(P, Υ')). Only U changes.
    """
    B = thresholds.shape[0]
    record = list(record)
    pos = {k: i for i, k in enumerate(record)}
    P_out = np.empty((len(record), rm.n, rm.n, B))
    U_out = np.empty_like(P_out)
    st = Stepper(rm, P0, B, backend, want_u=True)
    if 0 in pos:
        P_out[pos[0]] = st.true
        U_out[pos[0]] = st.cond
    last = max(record) if record else 0
    for k in range(horizon):
        keep = rng.random(B) >= mus
        if s2_given_kept is None:
            s2 = rm.noise(thresholds + rng.exponential(snr_avg, B))  # memoryless: Υ | Υ ≥ Υ_T
        else:
            s2 = s2_given_kept
        U_strat = None
        if final_strata and s2_given_kept is None and k + 1 == last:
            # last recorded step: E over Υ' of the kept update by stratified sampling (K strata of the
            # exponential's CDF, one uniform each) — still unbiased, and the rare low-SNR last packet that
            # dominates the variance at small Υ_T enters with its probability instead of as a 0/1 event
            acc = np.zeros((rm.n, rm.n, B))
            for i in range(final_strata):
                u = (i + rng.random(B)) / final_strata
                acc += st.kept_true(rm.noise(thresholds - snr_avg * np.log1p(-u)))
            with np.errstate(over="ignore", invalid="ignore"):
                U_strat = mus[None, None, :] * _drop(rm, st.cond) + (1.0 - mus[None, None, :]) * (acc / final_strata)
        st.step(keep, s2, mus)
        if k + 1 in pos:
            P_out[pos[k + 1]] = st.true
            U_out[pos[k + 1]] = st.cond if U_strat is None else U_strat
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


# --------------------------------------------------------------------------- Monte Carlo kernels (picklable)


@dataclass(frozen=True)
class NoiseFn:
    """σ_n²(Υ) as a picklable callable: ``ber`` α + δ Ω(√Υ) (Sec. 3.1) or ``inverse_snr`` β/Υ (eq. 50)."""

    model: str
    alpha: float = 0.0
    delta: float = 0.0
    beta: float = 0.0

    @classmethod
    def of(cls, noise) -> "NoiseFn":
        """From a channel's ``NoiseModel``."""
        if noise.model == "ber":
            a, d = noise.params
            return cls("ber", alpha=float(a), delta=float(d))
        return cls("inverse_snr", beta=float(noise.beta))

    def __call__(self, snr):
        snr = np.asarray(snr, dtype=float)
        if self.model == "ber":
            return fa.sigma2_n(snr, self.alpha, self.delta)
        with np.errstate(divide="ignore"):
            return self.beta / snr

    def mean_given_kept(self, threshold, snr_avg):
        """E[σ_n²(Υ) | Υ ≥ Υ_T] = σ²_n,ave(Υ_T)/(1 − μ_ave(Υ_T)) (eqs 15–16); ``None`` unless ``ber``."""
        if self.model != "ber":
            return None
        T = np.asarray(threshold, dtype=float)
        return fa.sigma2_n_ave(T, snr_avg, self.alpha, self.delta) / np.exp(-T / snr_avg)


STAT_KEYS = ("sum", "sumsq", "tr", "tr2", "inf")


def chunk_stats(X: np.ndarray, G: int, N: int) -> dict[str, np.ndarray]:
    """Additive statistics of per-run matrices X (n, n, G·N) grouped by grid point (column g·N + i).

    ``sum`` (n, n, G) Σ X, ``sumsq`` (n², n², G) Σ vec X vec Xᵀ, ``tr``/``tr2`` Σ tr X and Σ (tr X)²,
    ``inf`` the number of runs whose X overflowed.
    """
    n = X.shape[0]
    Xg = np.ascontiguousarray(X).reshape(n, n, G, N)
    V = Xg.reshape(n * n, G, N)
    with np.errstate(over="ignore", invalid="ignore"):
        tr = np.trace(Xg, axis1=0, axis2=1)  # (G, N)
        return {"sum": Xg.sum(-1), "sumsq": np.einsum("agr,bgr->abg", V, V),
                "tr": tr.sum(-1), "tr2": (tr**2).sum(-1), "inf": (~np.isfinite(tr)).sum(-1).astype(float)}


class ReceiverMeanKernel:
    """E P[H] of receiver scenarios on the i.i.d. fading channel for a grid of thresholds (Fig. 6, Sec. 4.2).

    Per scenario ``s``: keys ``s{s}_path_<stat>`` (plain sample mean of P[H] along the simulated
    paths — heavy-tailed) and ``s{s}_conditioned_<stat>`` (burst-conditioned U[H]; for scenario 2
    with the ``ber`` noise also Rao–Blackwellized over σ_n², see :func:`burst_conditioned_paths`),
    ``<stat>`` in :data:`STAT_KEYS`. One chunk of ``runs`` runs simulates runs × G columns.
    """

    def __init__(self, models: dict[int, ReceiverModel], thresholds, snr_avg: float, P0, horizon: int,
                 backend: str = "numpy", rao_blackwell: bool = True, final_strata: int = 16):
        self.models = dict(models)
        self.final_strata = int(final_strata)
        self.thresholds = np.asarray(thresholds, dtype=float)
        self.snr_avg, self.P0, self.horizon = float(snr_avg), np.asarray(P0, dtype=float), int(horizon)
        self.backend, self.rao_blackwell = backend, rao_blackwell

    def __call__(self, rng: np.random.Generator, runs: int) -> dict[str, np.ndarray]:
        T = self.thresholds
        G = len(T)
        th = np.repeat(T, runs)
        mu = fa.mu_ave(th, self.snr_avg)
        out = {}
        for sc, rm in self.models.items():
            s2 = None
            if sc == 1:
                s2 = np.zeros_like(th)  # scenario 1 ignores σ_n² (eq. 7 with S₁ = 0): no SNR to draw
            elif sc == 2 and self.rao_blackwell and isinstance(rm.noise, NoiseFn):
                s2 = rm.noise.mean_given_kept(th, self.snr_avg)
            P, U = burst_conditioned_paths(rm, rng, th, mu, self.snr_avg, self.P0, self.horizon, [self.horizon],
                                           backend=self.backend, s2_given_kept=s2, final_strata=self.final_strata)
            for lab, X in (("path", P[0]), ("conditioned", U[0])):
                for k, v in chunk_stats(X, G, runs).items():
                    out[f"s{sc}_{lab}_{k}"] = v
        return out


class CorrelatedPathKernel:
    """Plain sample mean of P[H] on a Jakes-correlated channel and on the i.i.d. one (Fig. 7 diagnostics).

    Also the burst statistics (d0, d1, d2: drops, drop pairs, drop triples) and the generated gain's
    sample autocorrelation at lags 0..max_lag, averaged per run over the horizon (``ac``, ``pc``
    and their squares over runs).
    """

    def __init__(self, channel, rm: ReceiverModel, thresholds, P0, horizon: int, max_lag: int, backend: str = "numpy"):
        self.channel, self.rm = channel, rm
        self.thresholds = np.asarray(thresholds, dtype=float)
        self.P0, self.horizon, self.max_lag, self.backend = np.asarray(P0, float), int(horizon), int(max_lag), backend

    def __call__(self, rng: np.random.Generator, runs: int) -> dict[str, np.ndarray]:
        from netkf_cli.channels.fading import IidCorrelation, sample_gain

        ch, T, H = self.channel, self.thresholds, self.horizon
        G = len(T)
        Ya = ch.mean_snr
        lags = np.arange(self.max_lag + 1)
        out = {}
        for lab, corr in (("jakes", ch.correlation), ("iid", IidCorrelation(model="iid"))):
            h = sample_gain(rng, runs, H, corr)
            snr = Ya * (h.real**2 + h.imag**2)
            Pk = covariance_paths(self.rm, np.tile(snr, (1, G)), np.repeat(T, runs), self.P0, record=[H],
                                  backend=self.backend)[0]
            for k, v in chunk_stats(Pk, G, runs).items():
                out[f"{lab}_{k}"] = v
            d = snr[None, :, :] < T[:, None, None]  # (G, H, runs) drops
            out[f"{lab}_d1"] = (d[:, 1:-1] & d[:, :-2]).sum((1, 2)).astype(float)
            out[f"{lab}_d2"] = (d[:, 2:] & d[:, 1:-1] & d[:, :-2]).sum((1, 2)).astype(float)
            out[f"{lab}_d0"] = d[:, :-2].sum((1, 2)).astype(float)
            if lab == "jakes":
                # per run, the average over every pair (t, t − k) with t ≥ max_lag (stationary): one
                # independent sample per run, far less noise than a single pair
                t0 = np.arange(self.max_lag, H)
                prod = np.stack([(h[t0] * np.conj(h[t0 - k])).real.mean(0) for k in lags])  # (lags, runs)
                out["ac"] = prod.sum(1)
                out["ac2"] = (prod**2).sum(1)
                p = np.stack([(snr[t0] * snr[t0 - k]).mean(0) for k in lags])
                out["pc"] = p.sum(1)
                out["pc2"] = (p**2).sum(1)
        return out


class FadingAveragesKernel:
    """Fig. 4: drop counts and Σ σ_n², Σ σ_n⁴ of kept packets per threshold (one SNR sample per run)."""

    def __init__(self, channel, thresholds):
        self.channel, self.thresholds = channel, np.asarray(thresholds, dtype=float)

    def __call__(self, rng: np.random.Generator, runs: int) -> dict[str, np.ndarray]:
        ch, T = self.channel, self.thresholds
        Y = ch.sample(rng, runs, 1).snr[0]
        keep = Y[None, :] >= T[:, None]
        s2 = np.where(keep, ch.noise.variance(Y)[None, :], 0.0)
        return {"drop": (~keep).sum(1).astype(float), "s2": s2.sum(1), "s2sq": (s2**2).sum(1)}


class Theorem4Kernel:
    """Theorem 4 (eq. 51): Σ P[k], Σ P[k]² and Σ of the exact last-step conditional mean a²ϖβ Π(ϖβ/P[k−1]) (Lemma 7)."""

    def __init__(self, a: float, beta: float, snr_avg: float, P0: float, k_max: int):
        self.a, self.beta, self.snr_avg, self.P0, self.k_max = float(a), float(beta), float(snr_avg), float(P0), int(k_max)

    def __call__(self, rng: np.random.Generator, runs: int) -> dict[str, np.ndarray]:
        a, beta, Ya, P0, K = self.a, self.beta, self.snr_avg, self.P0, self.k_max
        w = 1.0 / Ya
        P = np.full(runs, P0)
        s, s2, r, r2 = (np.zeros(K + 1) for _ in range(4))
        s[0], s2[0], r[0], r2[0] = P0 * runs, P0 * P0 * runs, P0 * runs, P0 * P0 * runs
        for k in range(K):
            cond = a * a * w * beta * fa.scaled_exp1(w * beta / P)  # E[P[k+1] | P[k]] (Lemma 7)
            P = fa.theorem4_step(P, rng.exponential(Ya, runs), a, beta)
            s[k + 1], s2[k + 1] = P.sum(), (P * P).sum()
            r[k + 1], r2[k + 1] = cond.sum(), (cond * cond).sum()
        return {"s": s, "s2": s2, "r": r, "r2": r2}


# --------------------------------------------------------------------------- Fig. 7: drop bursts of a correlated channel


def memoryless_coefficients(A, C, Q, R, P0, horizon: int):
    """Scenario 2 with an invertible C forgets everything at a kept packet (eq. 12). With the last kept
    packet L steps before the end (L = 0 … H−1; noise variance σ² = σ_n²(Υ) of that packet):

        P[H] = σ² M1[L] + M2[L],  M1[L] = Aᴸ A C⁻¹C⁻ᵀ Aᵀ Aᴸᵀ,
        M2[L] = Aᴸ (A C⁻¹ R C⁻ᵀ Aᵀ + Q) Aᴸᵀ + Σ_{i<L} Aⁱ Q Aⁱᵀ;

    with no kept packet at all, P[H] = D = Aᴴ P0 Aᴴᵀ + Σ_{i<H} Aⁱ Q Aⁱᵀ (eqs 12–13 unrolled).
    Returns (M1 (H, n, n), M2 (H, n, n), D (n, n)).
    """
    A, C, Q, R, P0 = (np.atleast_2d(np.asarray(x, dtype=float)) for x in (A, C, Q, R, P0))
    n = A.shape[0]
    Ci = np.linalg.inv(C)
    K1 = A @ Ci @ Ci.T @ A.T
    K2 = A @ Ci @ R @ Ci.T @ A.T + Q
    M1, M2 = np.empty((horizon, n, n)), np.empty((horizon, n, n))
    Ak = np.eye(n)
    S = np.zeros((n, n))  # Σ_{i<L} Aⁱ Q Aⁱᵀ
    with np.errstate(over="ignore", invalid="ignore"):
        for L in range(horizon):
            M1[L] = Ak @ K1 @ Ak.T
            M2[L] = Ak @ K2 @ Ak.T + S
            S = S + Ak @ Q @ Ak.T
            Ak = A @ Ak
        D = Ak @ P0 @ Ak.T + S
    return M1, M2, D


def gaussian_factor(autocorr: np.ndarray, nugget: float) -> np.ndarray:
    """Lower Cholesky factor of the stationary covariance Σ_ts = (ρ(|t−s|) + ε δ_ts)/(1 + ε) (unit power).

    ρ = J₀(2π f_D k T) for Jakes (eq. 65). The sampled Jakes spectrum vanishes above f_D, so Σ is
    singular up to rounding; the white "nugget" ε makes it positive definite (a noise floor ε below
    the fading power) and makes every step's conditional law given the past well defined.
    """
    H = len(autocorr)
    lags = np.arange(H)
    S = np.asarray(autocorr, dtype=float)[np.abs(lags[:, None] - lags[None, :])] + nugget * np.eye(H)
    return np.linalg.cholesky(S / (1.0 + nugget))


class BurstSMCKernel:
    """E P[H] of scenario 2 (invertible C) on a Gaussian-process fading channel by sequential Monte Carlo.

    For scenario 2 with an invertible C, P[H] depends only on the last kept packet: its distance L to
    the end and its noise σ_n²(Υ) (:func:`memoryless_coefficients`). By stationarity,

        E P[H] = Σ_{L<H} E[1{Υ_0 ≥ Υ_T, Υ_1..Υ_L < Υ_T} (σ_n²(Υ_0) M1[L] + M2[L])] + Pr[Υ_0..Υ_{H−1} < Υ_T] D.

    The probabilities of long drop bursts are what the plain sample mean never sees; here they are
    estimated directly. The gain h_t = (x_t + i y_t)/√2 with x = L z_x, y = L z_y (L from
    :func:`gaussian_factor`, z standard normal) has, given the past, the law N(m_t, s_t² I₂) with
    m_t = Σ_{u<t} L_tu z_u and s_t = L_tt. A cloud of K particles starts with a kept packet
    (Υ_0 drawn given Υ_0 ≥ Υ_T; exact weight Pr[kept] = e^{−Υ_T/Υ_ave}) and every later step is
    FORCED to be a drop: each particle moves by the conditional law restricted to the disk
    |w|² < ρ² = 2Υ_T/Υ_ave and is weighted by the probability of that disk, p_t = Pr[drop_t | past]
    (non-central χ²₂ cdf) — a fully adapted particle filter for the event "L drops in a row".
    With normalized weights w_i, Ẑ_t = Ẑ_{t−1} Σ_i w_i p_t^i estimates Pr[kept, then t drops] and
    Ẑ_{t−1} Σ_i w_i p_t^i σ_n²(Υ_0^i) the σ_n² moment, both UNBIASED (Del Moral 2004, Thm 7.4.2);
    particles are resampled (systematic) when the effective sample size falls below K/2. A second
    cloud does the same from t = 0 for the all-drop term. The kept clouds' initial SNRs are stratified
    (K strata of Pr[Υ_0 | kept], finer at low SNR, each particle weighted by its stratum's probability). Each Monte Carlo "run" is one independent
    pair of clouds, so the standard error over runs is honest. The L = 0 term needs only the
    marginal law of Υ and is added exactly: Pr[kept] E[σ_n² | kept] = σ²_n,ave (eq. 16).

    Sampling the restricted 2-D normal: |v|² = |m/s + ζ|² is non-central χ²₂(λ = |m|²/s²) truncated to
    [0, ρ²/s²] (inverse cdf ``chndtrix``), the angle given the radius von Mises around arg m with
    κ = √λ |v|. ``factor=None`` means independent gains (L = I): then p_t = μ_ave for every particle
    and the estimate is eq. (14) up to the sampling of σ_n²(Υ_0) — the check of the machinery.

    Keys: ``sum``/``sumsq``/``tr``/``tr2``/``inf`` of the per-run estimate (n, n, G); ``w`` (G, len(burst_lags))
    Σ over runs of Ẑ_L (Pr[kept, then L drops]) at ``burst_lags`` and ``w2`` Σ Ẑ_L²; ``ess`` (G,) Σ over runs and steps of
    the smallest effective sample size seen by a cloud (diagnostic).
    """

    def __init__(self, factor: np.ndarray | None, thresholds, snr_avg: float, noise, coeffs, horizon: int,
                 particles: int = 32, burst_lags=(0, 1, 2, 5, 10, 20, 50, 100, 200)):
        self.factor = None if factor is None else np.ascontiguousarray(factor)
        self.thresholds = np.asarray(thresholds, dtype=float)
        self.snr_avg, self.noise, self.horizon = float(snr_avg), noise, int(horizon)
        self.M1, self.M2, self.D = coeffs
        self.K = int(particles)
        self.burst_lags = tuple(int(x) for x in burst_lags if x < horizon)

    def __call__(self, rng: np.random.Generator, runs: int) -> dict[str, np.ndarray]:
        from scipy import special

        T, H, Lf, K = self.thresholds, self.horizon, self.factor, self.K
        G = len(T)
        n = self.M1.shape[1]
        R = runs
        ngroups = 2 * G * R  # (path type, threshold, run); path type 0: kept start, 1: all drops
        C = ngroups * K
        rho2 = np.repeat(np.tile(np.repeat(2.0 * T / self.snr_avg, R), 2), K)  # per particle
        kept_path = np.arange(C) < C // 2
        Zx = np.zeros((C, H))
        Zy = np.zeros((C, H))
        w = np.full(C, 1.0 / K)
        Zhat = np.ones(ngroups)
        g0 = np.zeros(C)
        X = np.zeros((n, n, G * R))
        wl = np.zeros((G, len(self.burst_lags)))
        wl2 = np.zeros((G, len(self.burst_lags)))
        ess_min = np.full(ngroups, float(K))
        lag_pos = {L: i for i, L in enumerate(self.burst_lags)}
        half = ngroups // 2
        thr = np.repeat(T, R)
        mean_g = self.noise.mean_given_kept(thr, self.snr_avg)
        pk = np.exp(-thr / self.snr_avg)
        with np.errstate(over="ignore", invalid="ignore", divide="ignore", under="ignore"):
            # L = 0: exact (marginal law of Υ)
            X += (self.M1[0][:, :, None] * mean_g[None, None, :] + self.M2[0][:, :, None]) * pk[None, None, :]
            if 0 in lag_pos:
                wl[:, lag_pos[0]] += pk.reshape(G, R).sum(1)
                wl2[:, lag_pos[0]] += (pk * pk).reshape(G, R).sum(1)
            for t in range(H):
                if Lf is None or t == 0:
                    mx = np.zeros(C)
                    my = np.zeros(C)
                    s = 1.0 if Lf is None else Lf[0, 0]
                else:
                    row = Lf[t, :t]
                    # einsum, not BLAS: bit-for-bit the same whatever the BLAS thread count (serial = workers)
                    mx = np.einsum("ij,j->i", Zx[:, :t], row)
                    my = np.einsum("ij,j->i", Zy[:, :t], row)
                    s = Lf[t, t]
                lam = (mx * mx + my * my) / (s * s)
                xlim = rho2 / (s * s)
                central = Lf is None or t == 0  # m = 0: the central χ²₂ is exponential (closed forms)
                p = -np.expm1(-xlim / 2.0) if central else special.chndtr(xlim, 2.0, lam)
                if t == 0:
                    p = np.where(kept_path, np.exp(-xlim / 2.0), p)
                wp = (w * p).reshape(ngroups, K)
                inc = wp.sum(1)  # Σ_i w_i p_i per group
                if t >= 1:
                    # contribution of "kept at 0, then t drops": the kept clouds only
                    zprev = Zhat[:half]
                    mom = (wp[:half] * g0.reshape(ngroups, K)[:half]).sum(1)
                    Xt = self.M1[t][:, :, None] * (zprev * mom)[None, None, :] \
                        + self.M2[t][:, :, None] * (zprev * inc[:half])[None, None, :]
                    X += Xt
                Zhat = Zhat * inc
                if t >= 1 and t in lag_pos:
                    zr = Zhat[:half].reshape(G, R)
                    wl[:, lag_pos[t]] += zr.sum(1)
                    wl2[:, lag_pos[t]] += (zr * zr).sum(1)
                # reweight; resample (systematic) where the effective sample size < K/2
                with np.errstate(invalid="ignore", divide="ignore"):
                    wn = np.where(inc[:, None] > 0, wp / inc[:, None], 1.0 / K)
                ess = 1.0 / (wn * wn).sum(1)
                ess_min = np.minimum(ess_min, ess)
                res = ess < K / 2.0
                w = wn.ravel()
                if Lf is not None and np.any(res) and t + 1 < H:
                    gidx = np.nonzero(res)[0]
                    cw = np.cumsum(wn[gidx], axis=1)
                    cw[:, -1] = 1.0
                    pos = (rng.random(len(gidx))[:, None] + np.arange(K)[None, :]) / K
                    pick = np.empty((len(gidx), K), dtype=np.int64)
                    for j in range(len(gidx)):  # searchsorted per resampled group (K small)
                        pick[j] = np.searchsorted(cw[j], pos[j])
                    src = (gidx[:, None] * K + np.minimum(pick, K - 1)).ravel()
                    dst = (gidx[:, None] * K + np.arange(K)[None, :]).ravel()
                    Zx[dst, :t] = Zx[src, :t]
                    Zy[dst, :t] = Zy[src, :t]
                    g0[dst] = g0[src]
                    mx[dst], my[dst], lam[dst], p[dst] = mx[src], my[src], lam[src], p[src]
                    w.reshape(ngroups, K)[gidx] = 1.0 / K
                if t + 1 == H:
                    break
                # move: forced drop (or, at t = 0 for the kept clouds, a kept packet)
                u = rng.random(C)
                if central:
                    q = -2.0 * np.log1p(-np.clip(u * p, 0.0, 1.0))
                else:
                    q = special.chndtrix(np.clip(u * p, 0.0, None), 2.0, lam)
                if t == 0:
                    # kept start, stratified within each cloud: |v|² − ρ²/s² ~ Exp(mean 2) by inverse cdf at a
                    # uniform point of stratum k = [e_k, e_{k+1}), e_k = (k/K)³ (fine strata at low SNR, where
                    # σ_n²(Υ_0) is large and varies fast); the particle then carries the weight
                    # e_{k+1} − e_k (stratified sampling: unbiased, far less variance than K plain draws)
                    e = (np.arange(K + 1) / K) ** 3
                    kk = np.tile(np.arange(K), ngroups)
                    us = e[kk] + rng.random(C) * (e[kk + 1] - e[kk])
                    q = np.where(kept_path, xlim - 2.0 * np.log1p(-us), q)
                    w = np.where(kept_path, (e[kk + 1] - e[kk]), w)
                q = np.maximum(q, 0.0)
                kap = np.sqrt(lam * q)
                ang = np.where(kap > 0, rng.vonmises(np.arctan2(my, mx), np.maximum(kap, 1e-300)),
                               rng.uniform(-np.pi, np.pi, C))
                r = np.sqrt(q)
                Zx[:, t] = r * np.cos(ang) - mx / s
                Zy[:, t] = r * np.sin(ang) - my / s
                if t == 0:
                    g0 = self.noise(self.snr_avg * (s * s) * q / 2.0)  # Υ = Υ_ave s²|v|²/2
            X += self.D[:, :, None] * Zhat[half:][None, None, :]
        out = chunk_stats(X, G, R)
        out["w"] = wl
        out["w2"] = wl2
        out["ess"] = ess_min[:half].reshape(G, R).sum(1)
        return out
