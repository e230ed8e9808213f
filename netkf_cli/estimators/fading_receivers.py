"""Receivers of Mostofi & Murray 2009: scenario 1 (eqs 7–8), 2 (eqs 10–13) and 3 (eqs 27–28).

A packet carries all of y_k (one arrival stream); it is kept iff Υ[k] ≥ Υ_T (eq. 5). Every recursion
is written on the Kalman core (:mod:`netkf_cli.linalg.kalman`): a dropped packet is γ = 0 (the correction
is multiplied by γ), the communication noise of a kept packet is the core's per-run ``extra_R``
= σ_n²(Υ) I, a suboptimal receiver's true error covariance is :func:`kalman.joseph` of its gain, and
every step goes through the one overflow policy (:class:`kalman.Rescue`; non-finite ⇒ ``inf``):

* scenario 1 — "ideal noise": the kept packet is noise-free apart from R (eq. 7 with S₁ = 0):
  the Kalman filter with intermittent observations (:func:`kalman.update`, γ = keep).
* scenario 2 — no cross-layer path: the estimator treats a kept packet as noise-free. Its gain is
  the optimal gain of its own covariance P_f with zero noise, K = P_f Cᵀ (C P_f Cᵀ)⁻¹
  (:func:`kalman.gain` with R = 0; K = C⁻¹ for an invertible C, eq. 10), and the true error
  covariance is the Joseph form with the true noise, P⁺ = (I − KC) P (I − KC)ᵀ + K(σ_n² I + R)Kᵀ;
  for an invertible C this is eq. (12) with the footnote's σ_n² I + R.
* scenario 3 — cross-layer path: the Kalman filter knows σ_z² = σ_n²(Υ) I + R (eqs 27–28),
  :func:`kalman.update` with ``extra_R`` = σ_n² I (rescue: :func:`kalman.rescue_noisy`).

Time base (netkf's one): P0 = P_{0|0} (:func:`riccati.initial_covariance`); step k uses Υ of trace
step k − 1; ``filtered`` is P_{k|k}, ``predicted`` P_{k+1|k} — the paper's P[k+1] (eqs 6, 12, 28),
which its figures plot. (The paper-figure analyses ``fading_*`` keep the paper's own start:
P[0] = P0 is the prior of the first packet; their kernels drive :class:`Stepper` from that prior.)

All recursions are batched over runs (``(n, n, B)``, run axis innermost); the compiled backend
(:mod:`netkf_cli.estimators._fading_numba`) runs the same primitives from :mod:`netkf_cli.linalg.kalman_numba`.

Two Monte Carlo estimators of E P[k]:

* **naive**: the sample mean of P[k] over runs (any channel; heavy-tailed near the stability limit:
  its variance is infinite once μ ρ⁴ ≥ 1 in scenario 2).
* **burst-conditioned** (i.i.d. channel only; ``variance_reduction: conditioned``): condition on the
  final drop burst. With μ = Pr[drop] and F(P, Υ) the kept-packet update, for i.i.d. Υ
  E[P_{k|k} | P_{k|k−1}] = μ P_{k|k−1} + (1 − μ) E[F(P_{k|k−1}, Υ')], Υ' ~ Υ | Υ ≥ Υ_T,
  so U_{k|k} = μ U_{k|k−1} + (1 − μ) F(P_{k|k−1}, Υ'_k), U_{k+1|k} = A U_{k|k} Aᵀ + Q, U_{0|0} = P0,
  is an unbiased estimate of E P_{k|k} (and of E P_{k+1|k}) for every run (induction on k; Υ'_k is
  independent of P_{k|k−1}). The long drop bursts that make P heavy-tailed enter U only through
  their exact probabilities μ^L, and F(P, Υ') is bounded whatever P is (invertible C), so U has a
  small variance. On a channel trace, Υ'_k is made from the trace's own Υ_k
  (:func:`netkf_cli.channels.fading.snr_given_kept`: Υ itself when kept). For scenario 2 with the
  ``ber`` noise, σ_n²(Υ') in U is replaced by its conditional mean E[σ_n² | kept] (eqs 15–16: exact
  Rao–Blackwellization, the Joseph form is affine in σ_n² with a σ_n²-independent gain).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field
from scipy import special

from netkf_cli.linalg import kalman
from netkf_cli.linalg.kalman import numba_available  # noqa: F401  (re-exported: the one probe)
from netkf_cli.analysis import fading as fa
from netkf_cli.channels.fading import IidCorrelation, NoiseFn, Snr, sample_gain, snr_given_kept  # noqa: F401
from netkf_cli.channels.fading import noise_given_kept, noise_where_kept
from netkf_cli.core.errors import ConfigError
from netkf_cli.estimators import _fading_codegen as fcg
from netkf_cli.linalg import kalman_codegen as kc
from netkf_cli.linalg.riccati import initial_covariance
from netkf_cli.core.spec import EstimatorModel

BackendKind = Literal["auto", "numpy", "numba"]
RECORD_BYTES = 64e6
"""Most bytes of recorded covariances one block of :meth:`ReceiverEstimator.covariances` holds (the reported
steps of a block come out of one recursion call)."""
VarianceReduction = Literal["auto", "none", "conditioned"]


class ReceiverEstimator(EstimatorModel):
    """``kind: receiver`` — Mostofi & Murray 2009 receiver scenario 1, 2 or 3 with drop threshold Υ_T (eq. 5).

    Works from the ``snr`` trace of a ``fading`` channel (one packet per step carrying all of y_k):
    a packet with Υ_t < Υ_T is dropped, a kept one carries communication noise of variance σ_n²(Υ_t)
    (the channel's noise model). Reports ``filtered`` P_{k|k} and ``predicted`` P_{k+1|k} (the
    paper's P[k+1], eqs 6, 12, 28) from P0 = P_{0|0}. On a perfect channel (every packet kept, no
    communication noise) scenarios 1 and 3 are ``kind: kf``, number for number.
    """

    accepts: ClassVar[frozenset[str]] = frozenset({"snr"})
    quantities: ClassVar[tuple[str, ...]] = ("filtered", "predicted")

    kind: Literal["receiver"]
    scenario: Literal[1, 2, 3] = Field(description="1: drop erroneous packets (eqs 7–8); 2: no cross-layer path "
                                                   "(eqs 10–13); 3: cross-layer path (eqs 27–28)")
    threshold: Snr | None = Field(None, description="drop threshold Υ_T with unit (default: the channel's `threshold`)")
    backend: BackendKind = Field("auto", description="numpy (reference) | numba (compiled, equal to rounding) | "
                                                     "auto = numba when importable")
    def for_means(self, channel) -> "ReceiverEstimator":
        """``auto``: the burst-conditioned estimator where only means are taken on an i.i.d. channel (the
        rare long drop bursts that dominate E[P_k] at a high threshold are then integrated, not sampled),
        else none."""
        if self.variance_reduction != "auto":
            return self
        corr = getattr(getattr(channel, "correlation", None), "model", "iid")
        return self.model_copy(update={"variance_reduction": "conditioned" if corr == "iid" else "none"})

    def per_run_covariance(self) -> bool:
        """False under ``variance_reduction: conditioned``: each run then yields an unbiased estimate of
        E[P_k], not its own covariance, so only means may be taken (not Pr[P_k ≤ M])."""
        return self.variance_reduction != "conditioned"

    variance_reduction: VarianceReduction = Field(
        "auto", description="auto (default): conditioned where a metric takes only means on an i.i.d. channel, "
                            "none otherwise. none: P_k of each run (every metric). conditioned: the burst-conditioned "
                            "estimate of E P_k per run (i.i.d. channel only; unbiased for MEANS — mean_vs_time, "
                            "compare's E tr P — with a far smaller variance; not a per-run covariance, so not for "
                            "distribution)")

    def check(self, system, channel) -> None:
        """Refuse pairs that cannot work: a channel without SNR, a missing Υ_T, scenario 2 with m > n,
        a conditioned estimate on a correlated channel."""
        if "snr" not in getattr(channel, "trace_kinds", frozenset()):
            raise ConfigError.at("estimator.kind", "the fading receivers need a channel with an SNR trace "
                                                   "(kind: fading); compatible trace kinds: snr")
        if self.threshold is None and getattr(channel, "threshold", None) is None:
            raise ConfigError.at("estimator.threshold", "give the drop threshold Υ_T, e.g. {value: 14, unit: linear} "
                                                        "(here or as the channel's `threshold`)")
        if self.scenario == 2 and system.m > system.n:
            raise ConfigError.at("system.C", "scenario 2 needs at most as many outputs as states")
        kalman.stream_rows(system, 1, "estimator.kind")  # one packet per step carries all of y_k
        corr = getattr(getattr(channel, "correlation", None), "model", "iid")
        if self.variance_reduction == "conditioned" and corr != "iid":
            raise ConfigError.at("estimator.variance_reduction",
                                 f"conditioned needs an i.i.d. channel (correlation model iid), got {corr}; "
                                 "use variance_reduction: none (or the fading_correlation analysis' SMC)")
        if self.backend == "numba":
            resolve_backend("numba")

    def conventions(self, system, channel) -> dict[str, str]:
        out = {"packet": "one packet per step carries all of y_k",
               "threshold": "kept iff Υ_t ≥ Υ_T (eq. 5)",
               "receiver": {1: "scenario 1: noise-free kept packets (eq. 7)",
                            2: "scenario 2: no cross-layer path, Joseph form of the noise-free gain (eqs 10–12)",
                            3: "scenario 3: cross-layer path, σ_z² = σ_n² I + R (eqs 27–28)"}[self.scenario]}
        if self.variance_reduction == "conditioned":
            out["variance_reduction"] = "burst-conditioned per-run estimate of E P_k (means only)"
        elif self.variance_reduction == "auto":
            out["variance_reduction"] = "auto (burst-conditioned for means on an i.i.d. channel, else none)"
        return out

    def threshold_of(self, channel) -> float | None:
        """Υ_T (linear): the receiver's own ``threshold``, else the channel's (None if neither gives one)."""
        T = self.threshold if self.threshold is not None else getattr(channel, "threshold", None)
        return None if T is None else T.linear

    def renewal_refusal(self, system, quantity: str) -> str | None:
        """Why P_k of this receiver does NOT renew at a received packet (None: it does) — the contract of
        ``kind: burst_mean``: P at the last step is a function of the last received packet's σ_n² and of the
        number of drops since (:meth:`renewal_coefficients`)."""
        if self.scenario != 2:
            return (f"receiver scenario {self.scenario} carries its covariance across a received packet (its gain "
                    "depends on the prior): only scenario 2 with an invertible C renews there")
        rm = ReceiverModel(2, system.A, system.C, system.Q, system.R, None)
        if not rm.square_C:
            return "receiver scenario 2 renews at a received packet only with an invertible C (eq. 10: K = C⁻¹)"
        if quantity != "predicted":
            return f"the renewal form is written for the predicted P_{{k+1|k}} (the paper's P[k+1]), got {quantity}"
        return None

    def renewal_coefficients(self, system, horizon: int, quantity: str = "predicted"):
        """(M1 (k, n, n), M2 (k, n, n), D (n, n)) with k = ``horizon``: P_{k+1|k} = σ² M1[L] + M2[L] when the last
        received packet (noise σ² = σ_n²(Υ) of that packet) is followed by L = 0 … k−1 drops, D when every packet
        was dropped (:func:`memoryless_coefficients` from P_{1|0} = A P0 Aᵀ + Q, P0 = P_{0|0})."""
        why = self.renewal_refusal(system, quantity)
        if why is not None:
            raise ConfigError.at("estimator.scenario", why)
        P10 = kalman.one(kalman.predict, initial_covariance(system), np.atleast_2d(system.A), np.atleast_2d(system.Q))
        return memoryless_coefficients(system.A, system.C, system.Q, system.R, P10, int(horizon))

    def model(self, system, noise) -> "ReceiverModel":
        return ReceiverModel(self.scenario, system.A, system.C, system.Q, system.R, noise)

    def backend_used(self, system, channel, runs: int, horizon: int, steps=None, quantities=None) -> str:
        """The backend its :class:`Stepper` runs on (:func:`stepper_backend`; recorded in the manifest)."""
        rm = self.model(system, NoiseFn.of(channel.noise))
        return stepper_backend(rm, kalman.one(kalman.predict, initial_covariance(system), rm.A, rm.Q), self.backend)

    def _setup(self, system, trace, quantities):
        """(quantities, receiver model, Υ_T): what covariances() and estimates() read from the trace, checked."""
        qs = kalman.check_quantities(quantities, self.quantities, "receiver")
        noise = trace.meta.get("noise")
        if noise is None or trace.snr is None:
            raise ConfigError.at("channel", "the receiver needs an SNR trace with its noise model (channel kind fading)")
        T = self.threshold.linear if self.threshold is not None else trace.meta.get("threshold")
        if T is None:
            raise ConfigError.at("estimator.threshold", "give the drop threshold Υ_T (here or as the channel's `threshold`)")
        return qs, self.model(system, noise), T

    def covariances(self, system, trace, steps, quantities=("filtered",)):
        """Yield (k, {quantity: P}) for k in ``steps`` (1 ≤ k ≤ horizon); P (n, n, runs); overflow → inf."""
        qs, rm, T = self._setup(system, trace, quantities)
        cond = self.variance_reduction == "conditioned"
        B = trace.runs
        if cond:
            if trace.meta.get("correlation", "iid") != "iid":
                raise ConfigError.at("estimator.variance_reduction", "conditioned needs an i.i.d. channel")
            Ya = float(trace.meta["snr_avg"])
            mu = np.full(B, float(fa.mu_ave(T, Ya)))
            noise = trace.meta["noise"]  # (checked by _setup)
            rb = noise.mean_given_kept(T, Ya) if (self.scenario == 2 and isinstance(noise, NoiseFn)) else None
        P00 = initial_covariance(system)
        st = Stepper(rm, kalman.one(kalman.predict, P00, rm.A, rm.Q), B, self.backend, want_u=cond,
                     U0=P00 if cond else None)
        names = {"filtered": "cond_filtered", "predicted": "cond"} if cond else {"filtered": "filtered", "predicted": "true"}
        # the reported steps in blocks: one advance per block records every reported step in it (the same
        # arithmetic as one advance per step, without a Python round trip per step); blocks hold ≤ RECORD_BYTES
        cap = max(1, int(RECORD_BYTES // (8 * rm.n * rm.n * B * (4 if cond else 2))))
        want = sorted(set(int(k) for k in steps))
        t, i = 0, 0
        while i < len(want):
            if want[i] <= t:  # nothing to advance (k = 0): the current state
                out = {q: getattr(st, names[q]) for q in qs}
                yield want[i], out
                i += 1
                continue
            grp = want[i:i + cap]
            k = grp[-1]
            Y = trace.snr[t:k]
            keep = Y >= T
            if rm.scenario == 1:
                s2 = np.zeros(Y.shape)
                s2u = None
            elif cond:  # = σ_n²(Υ) where kept (σ_n² of the sample's Υ computed once per sample: noise_of_trace)
                s2 = noise_given_kept(trace, t, k, T, Ya, rm.noise)
                s2u = None if rb is None else np.full(Y.shape, float(rb))
            else:
                s2 = noise_where_kept(trace, t, k, T, rm.noise)
                s2u = None
            rec = np.full(k - t, -1, dtype=np.int64)
            rec[np.asarray(grp) - t - 1] = np.arange(len(grp))
            got = st.advance(keep, s2, mu if cond else None, s2u, record=rec)
            for j, kk in enumerate(grp):
                yield kk, {q: got[names[q]][j] for q in qs}
            t = k
            i += len(grp)


    def estimates(self, system, trace, y, steps, quantities=("filtered",)):
        """Yield (k, {quantity: (x̂, P)}) (numpy path, ``variance_reduction`` none): the receiver's recursion
        (:func:`correct` / :func:`predict`, as :meth:`covariances`) with the state, x̂_{0|0} = 0 — the gain of a
        kept packet from that recursion: scenario 1 ``kalman.gain``(P, C, R), scenario 3 with ``extra_R`` =
        σ_n²(Υ) I, scenario 2 C⁻¹ or ``kalman.gain`` of the receiver's own P_f with zero noise. ``y`` (m,
        horizon+1, runs): the packets as received (:func:`netkf_cli.engine.state.received`: y_k plus the channel's
        communication noise). Scenario 1's P assumes kept packets are noise-free (eq. 7, S₁ = 0): on a link
        with communication noise it is NOT the error covariance (a NEES check detects it); 2 and 3 report the
        true one."""
        qs, rm, T = self._setup(system, trace, quantities)
        B, n, m = trace.runs, rm.n, rm.C.shape[0]
        state = predict(rm, initial_state(rm, initial_covariance(system), B))
        x = np.zeros((n, B))
        want = sorted({int(k) for k in steps})
        wset = set(want)
        for t in range(want[-1] if want else 0):
            Y = trace.snr[t]
            keep = Y >= T
            s2 = np.zeros(B) if rm.scenario == 1 else rm.noise(np.where(keep, Y, 1.0))
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                if rm.scenario in (1, 3):
                    extra = None if rm.scenario == 1 else s2[None, None, :] * np.eye(m)[:, :, None]
                    K = kalman.gain(state[0], rm.C, rm.R, extra)
                elif rm.state_size() == 1:
                    K = np.broadcast_to(rm.gain_inv[:, :, None], (n, m, B))
                else:
                    K = kalman.gain(state[0], rm.C, np.zeros((m, m)))
                innov = (y[:, t + 1] - rm.C @ x) * keep.astype(float)[None, :]
                x = x + np.einsum("nmr,mr->nr", np.nan_to_num(K), innov)
            post = correct(rm, state, keep, s2)
            if t + 1 in wset:
                P = true_cov(post)
                out = {"filtered": (x, P), "predicted": (rm.A @ x, true_cov(predict(rm, post)))}
                yield t + 1, {q: out[q] for q in qs}
            state, x = predict(rm, post), rm.A @ x  # P_{k+1|k}, x̂_{k+1|k}


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
    general_C: bool = False  # scenario 2: force the general-gain form (the filter's own P_f) even for an invertible C

    def __post_init__(self):
        for name in ("A", "C", "Q", "R"):
            object.__setattr__(self, name, np.ascontiguousarray(np.atleast_2d(getattr(self, name)), dtype=float))

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

    @cached_property
    def rescue(self) -> kalman.Rescue:
        """The one overflow policy for this (C, R) (the floor tr P̄ where C is rank-deficient, as kf's). Made
        once per process and system (:data:`_RESCUES`): the receivers build a model per chunk, and the floor
        is a DARE (Sec. 4.2's C = [1 2 3]: 96 chunks × 2 receivers solved it 192 times)."""
        key = tuple((x.shape, x.tobytes()) for x in (self.A, self.C, self.Q, self.R))
        if key not in _RESCUES:
            _RESCUES[key] = kalman.Rescue.for_system(self.A, self.C, self.Q, self.R, self.C.shape[0])  # one packet: y_k
        return _RESCUES[key]

    @cached_property
    def gain_inv(self) -> np.ndarray:
        """Scenario 2, invertible C: the receiver's gain C⁻¹ (eq. 10)."""
        return np.ascontiguousarray(np.linalg.inv(self.C)) if self.square_C else np.zeros((self.n, self.C.shape[0]))


_RESCUES: dict = {}
""":attr:`ReceiverModel.rescue` by the system's (A, C, Q, R) bytes (a pure function of them)."""


def _nonfinite_inf(P: np.ndarray) -> np.ndarray:
    """The core's policy for an overflowed run (:func:`kalman.clean_nonfinite`): ∞ variances of unknown
    directions are kept, any other non-finite run is ``inf`` everywhere (never a silent NaN)."""
    return kalman.clean_nonfinite(P)


def correct(rm: ReceiverModel, state: list[np.ndarray], gamma: np.ndarray, s2: np.ndarray) -> list[np.ndarray]:
    """The measurement step from the prior(s) ``state`` ([P] or [P_f, P]): γ (B,) keep, σ_n² (B,) per run."""
    C, R = rm.C, rm.R
    m, B = C.shape[0], gamma.shape[0]
    g = np.asarray(gamma, dtype=float)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        extra = None if rm.scenario == 1 else np.asarray(s2, dtype=float)[None, None, :] * np.eye(m)[:, :, None]
        if rm.scenario in (1, 3):
            Pm = state[0]
            flagged = rm.rescue.flag(Pm)
            P = kalman.update(Pm, C, R, g, extra)
            if flagged.any():
                if extra is None:
                    P = rm.rescue.apply(P, Pm, flagged, np.broadcast_to(g, (m, B)))
                else:
                    P = kalman.rescue_noisy(rm.rescue, P, Pm, flagged, g, extra)
            return [_nonfinite_inf(P)]
        if rm.state_size() == 1:
            K = np.broadcast_to(rm.gain_inv[:, :, None], (rm.n, m, B))
            return [_nonfinite_inf(kalman.joseph(state[0], K, C, R, g, extra))]
        Pf, Pt = state
        Z = np.zeros((m, m))
        K = kalman.gain(Pf, C, Z)  # the receiver believes kept packets are noise-free
        return [_nonfinite_inf(kalman.joseph(Pf, K, C, Z, g)), _nonfinite_inf(kalman.joseph(Pt, K, C, R, g, extra))]


def predict(rm: ReceiverModel, state: list[np.ndarray]) -> list[np.ndarray]:
    """A P Aᵀ + Q for every carried covariance (the core's time update)."""
    with np.errstate(over="ignore", invalid="ignore"):
        return [_nonfinite_inf(kalman.predict(X, rm.A, rm.Q)) for X in state]


def initial_state(rm: ReceiverModel, P0: np.ndarray, B: int) -> list[np.ndarray]:
    P = np.repeat(np.asarray(P0, dtype=float)[:, :, None], B, axis=2)
    return [P.copy() for _ in range(rm.state_size())]


def true_cov(state):
    """The true error covariance of the state (last element)."""
    return state[-1]


# --------------------------------------------------------------------------- the batched engine (numpy | numba)

def resolve_backend(backend: str, n: int | None = None) -> str:
    """``auto`` → ``numba`` when importable and measured faster, else ``numpy``; ``numba`` without numba
    is a ConfigError. Measured (benchmarks: /tmp timing of covariance_paths, 2 loaded cores): compiled
    ≈ 1.3–2× the numpy core for n ≥ 2 (Fig. 6, Sec. 4.2 systems), slower for a scalar system (n = 1),
    where the numpy core's few vector operations per step already run near memory speed."""
    if backend == "auto":
        return "numba" if numba_available() and (n is None or n >= 2) else "numpy"
    if backend == "numba" and not numba_available():
        raise ConfigError.at("estimator.backend", "backend numba needs numba: pip install 'netkf[fast]'")
    return backend


def stepper_backend(rm: ReceiverModel, P0, backend: str) -> str:
    """The backend a :class:`Stepper` runs on (what the manifest records): :func:`resolve_backend`, and under
    ``auto`` also numba for a scalar system whose every step needs the overflow rescue (R ≪ P: Theorem 4's
    R = 1e-12): the numpy core's rescue is a batched SVD per step, the compiled variant runs it inline
    (thm4, 200 000 runs × 30 steps, load ≈ 6.5, one process: numpy 12.3 s, compiled 5.5 s; same CSV)."""
    be = resolve_backend(backend, rm.n)
    if backend == "auto" and be == "numpy" and numba_available() and needs_rescue(rm, P0):
        return "numba"
    return be


def needs_rescue(rm: ReceiverModel, P0) -> bool:
    """Scenarios 1 and 3 from a prior whose trace is above the core's rescue limit (:class:`kalman.Rescue`): the
    information-form update then runs at the first step (and, with a tiny R, at every step)."""
    return rm.scenario in (1, 3) and not bool(np.trace(np.atleast_2d(np.asarray(P0, dtype=float))) <= rm.rescue.limit)


class Stepper:
    """Batched receiver recursion over B runs from the PRIOR ``P0`` (P_{1|0}): per step, the
    measurement step (:func:`correct`) then the time update (:func:`predict`).

    ``true`` is the prior (the paper's P[k], = P_{k|k−1}), ``filtered`` the last P_{k|k}. With
    ``want_u`` the burst-conditioned estimate is advanced as well: ``cond`` U_{k+1|k}, ``cond_filtered``
    U_{k|k} (start ``U0`` = U_{0|0}, else the prior P0 is U's prior). ``backend`` ``numpy`` (reference)
    or ``numba`` (the same primitives compiled; equal to rounding).
    """

    def __init__(self, rm: ReceiverModel, P0, B: int, backend: str = "numpy", want_u: bool = False, U0=None):
        self.rm, self.backend, self.want_u = rm, stepper_backend(rm, P0, backend), want_u
        self.state = initial_state(rm, P0, B)
        self._filtered = None
        self.U = self.Uf = None
        if want_u:
            if U0 is None:
                self.U = true_cov(self.state).copy()
            else:
                self.Uf = np.repeat(np.asarray(U0, dtype=float)[:, :, None], B, axis=2)
                self.U = predict(rm, [self.Uf])[0]
        if self.backend == "numba":
            from netkf_cli.estimators import _fading_numba as fnb  # needs numba (optional): compiled recursion

            self._fnb = fnb
            self._mode = fnb.mode_of(rm)
            self._use_rescue = self._mode == 0 and not bool(np.trace(np.asarray(P0, dtype=float)) <= rm.rescue.limit)
            run_major = (lambda X: np.ascontiguousarray(np.moveaxis(X, 2, 0)))
            self._Pt = run_major(self.state[-1])
            self._Pf = run_major(self.state[0]) if self._mode == 2 else np.zeros((1, rm.n, rm.n))
            self._Ft = np.empty_like(self._Pt)
            if want_u:
                self._U = run_major(self.U)
                self._Uf = run_major(self.Uf) if self.Uf is not None else np.empty_like(self._U)
            else:
                self._U = self._Uf = np.zeros((1, rm.n, rm.n))

    # ---- (n, n, B) arrays (copies for the compiled backend, whose run-major state is updated in place)
    @property
    def true(self) -> np.ndarray:
        """The prior P_{k+1|k} (paper: P[k+1]), shape (n, n, B)."""
        return np.moveaxis(self._Pt, 0, 2).copy() if self.backend == "numba" else true_cov(self.state)

    @property
    def filtered(self) -> np.ndarray:
        """P_{k|k} of the last step, shape (n, n, B)."""
        return np.moveaxis(self._Ft, 0, 2).copy() if self.backend == "numba" else self._filtered

    @property
    def cond(self) -> np.ndarray:
        """U_{k+1|k} (burst-conditioned estimate of E P_{k+1|k}), shape (n, n, B)."""
        return np.moveaxis(self._U, 0, 2).copy() if self.backend == "numba" else self.U

    @property
    def cond_filtered(self) -> np.ndarray:
        """U_{k|k} (burst-conditioned estimate of E P_{k|k}), shape (n, n, B)."""
        return np.moveaxis(self._Uf, 0, 2).copy() if self.backend == "numba" else self.Uf

    def kept_true(self, s2: np.ndarray) -> np.ndarray:
        """The next prior (n, n, B) if every run's packet were KEPT with noise variance s2; the state is unchanged."""
        B = np.asarray(s2).shape[0]
        if self.backend == "numba":
            st = [np.moveaxis(self._Pf, 0, 2), np.moveaxis(self._Pt, 0, 2)] if self._mode == 2 else [np.moveaxis(self._Pt, 0, 2)]
        else:
            st = self.state
        s2_ = np.zeros(B) if self.rm.scenario == 1 else np.asarray(s2, dtype=float)
        return true_cov(predict(self.rm, correct(self.rm, st, np.ones(B, dtype=bool), s2_)))

    def step(self, keep: np.ndarray, s2: np.ndarray, mu: np.ndarray | None = None) -> None:
        """One step: keep (B,) bool, s2 (B,) σ_n² of the packet, mu (B,) drop probability (U only)."""
        self.advance(np.asarray(keep)[None, :], np.asarray(s2, dtype=float)[None, :], mu)

    def advance(self, keep: np.ndarray, s2: np.ndarray, mu: np.ndarray | None = None,
                s2u: np.ndarray | None = None, record: np.ndarray | None = None) -> dict[str, np.ndarray] | None:
        """Advance len(keep) steps: keep (T, B) bool, s2 (T, B) σ_n² of the packets (path, and U's kept
        term), ``s2u`` (T, B) a different σ_n² for U's kept term (Rao–Blackwellized), mu (B,).

        ``record`` (T,) int: slot r ≥ 0 of the steps to report (−1 elsewhere; slots 0 … R−1 in order). Returns
        then ``{true, filtered[, cond, cond_filtered]}`` each (R, n, n, B): the properties of the same names
        after each recorded step — one call per block instead of one per reported step (the same arithmetic)."""
        rm = self.rm
        keep = np.ascontiguousarray(keep, dtype=bool)
        s2 = np.zeros(keep.shape) if rm.scenario == 1 else np.ascontiguousarray(s2, dtype=float)
        rec = None if record is None else np.ascontiguousarray(record, dtype=np.int64)
        if self.backend == "numba":
            return self._advance_numba(keep, s2, mu, s2u, rec)
        return self._advance_numpy(keep, s2, mu, s2u, rec)

    def _record_names(self) -> tuple[str, ...]:
        return ("true", "filtered") + (("cond", "cond_filtered") if self.want_u else ())

    def _records(self, rec, B: int) -> dict[str, np.ndarray]:
        R = 0 if rec is None else int(rec.max(initial=-1)) + 1
        n = self.rm.n
        return {k: np.empty((B, R, n, n)) for k in self._record_names()}

    def _advance_numba(self, keep, s2, mu, s2u, rec=None) -> dict[str, np.ndarray] | None:
        rm = self.rm
        B = self._Pt.shape[0]
        start = (self._Pt.copy(), self._Pf.copy(), self._U.copy())
        flags = np.zeros(B, dtype=np.int8)
        mu_ = np.ascontiguousarray(mu, dtype=float) if self.want_u else np.zeros(1)
        s2u_ = s2 if s2u is None else np.ascontiguousarray(s2u, dtype=float)
        tr = (lambda X: np.ascontiguousarray(X.T))  # run-major (B, T): each run's inputs contiguous
        rec_ = np.full(keep.shape[0], -1, dtype=np.int64) if rec is None else rec
        none = np.empty((B, 0, rm.n, rm.n))
        bufs = lambda o: (o["true"], o["filtered"], o.get("cond", none), o.get("cond_filtered", none))  # noqa: E731
        # the rescue variant directly when many runs need it (a tiny R makes kalman.Rescue's limit small:
        # Sec. 4.2's C = [1 2 3], R = 1e-8 flags P0 = I), else the fast variant and a redo of the flagged runs
        inline = fcg.inline_rescue(self._mode, rm.C)
        if (inline or not self._use_rescue) and keep.shape[0] > 0 and fcg.supported(self._mode, rm.n, rm.C.shape[0]):
            # the generated kernel (_fading_codegen, runs innermost); its flag bits: 1 rescue, 2 non-finite
            # (the records are allocated here in the kernel's layout only: issue 20, 23 MB fewer per 50 000-run
            # block of thm4's 30 steps than a run-major set allocated first and then replaced)
            n, nt, R_ = rm.n, rm.n * (rm.n + 1) // 2, int(rec_.max(initial=-1)) + 1
            P, Fk = fcg.pack(self._Pt), np.empty((nt, B))
            U, Uf = (fcg.pack(self._U), np.empty((nt, B))) if self.want_u else (np.zeros((nt, 1)), np.zeros((nt, 1)))
            G = fcg.pack(self._Pf) if self._mode == 2 else np.zeros((nt, 1))
            recs = {k: np.empty((R_, n, n, B)) for k in self._record_names()}
            nil = np.empty((0, n, n, B))
            fcg.kernel(self._mode, rm.A, rm.C, rm.Q, rm.R, rm.gain_inv, rm.rescue.limit, self.want_u, s2u is not None,
                       inline)(
                keep, s2, s2u_, mu_, P, Fk, U, Uf, G, flags, rec_, recs["true"], recs["filtered"],
                recs.get("cond", nil), recs.get("cond_filtered", nil))
            flags = np.where(flags & 2, 2, np.where(flags & 1, 1, 0)).astype(np.int8)
            self._Pt = np.ascontiguousarray(np.moveaxis(kc.unpack(P, n), 2, 0))
            self._Ft = np.ascontiguousarray(np.moveaxis(kc.unpack(Fk, n), 2, 0))
            if self._mode == 2:
                self._Pf = np.ascontiguousarray(np.moveaxis(kc.unpack(G, n), 2, 0))
            if self.want_u:
                self._U = np.ascontiguousarray(np.moveaxis(kc.unpack(U, n), 2, 0))
                self._Uf = np.ascontiguousarray(np.moveaxis(kc.unpack(Uf, n), 2, 0))
            out = {k: np.moveaxis(v, 3, 0) for k, v in recs.items()}  # run-major views
        else:
            out = self._records(rec, B)  # run-major (B, slots, n, n) while the kernel writes them
            self._fnb.kernel(self._mode, rm.n, rm.C.shape[0], rescue=self._use_rescue)(
                tr(keep), tr(s2), tr(s2u_), s2u is not None, mu_, self.want_u,
                rm.A, rm.Q, rm.C, rm.R, rm.gain_inv, rm.rescue.limit, self._Pt, self._Pf, self._Ft, self._U, self._Uf,
                flags, rec_, *bufs(out))
        if (flags == 1).mean() > 0.05:
            self._use_rescue = True
        idx = np.flatnonzero(flags == 1)
        if idx.size:  # the runs that met a prior needing the rescue: redo their block with the rescue inline
            sub = lambda X: np.ascontiguousarray(X[idx])  # noqa: E731
            Pt0, Pf0, U0 = start
            Pt, Ft = sub(Pt0), np.empty((idx.size, rm.n, rm.n))
            U, Uf = (sub(U0), np.empty((idx.size, rm.n, rm.n))) if self.want_u else (self._U, self._Uf)
            f2 = np.zeros(idx.size, dtype=np.int8)
            sub_out = {k: np.empty((idx.size,) + v.shape[1:]) for k, v in out.items()}
            self._fnb.kernel(self._mode, rm.n, rm.C.shape[0], rescue=True)(
                tr(keep[:, idx]), tr(s2[:, idx]), tr(s2u_[:, idx]), s2u is not None, mu_[idx] if self.want_u else mu_,
                self.want_u, rm.A, rm.Q, rm.C, rm.R, rm.gain_inv, rm.rescue.limit, Pt, self._Pf, Ft, U, Uf, f2,
                rec_, *bufs(sub_out))
            self._Pt[idx], self._Ft[idx] = Pt, Ft
            if self.want_u:
                self._U[idx], self._Uf[idx] = U, Uf
            for k, v in sub_out.items():
                out[k][idx] = v
            flags[idx[f2 == 2]] = 2
        idx = np.flatnonzero(flags == 2)
        if idx.size:  # a non-finite value appeared: the numpy core owns what an overflow means
            sub = Stepper(rm, np.eye(rm.n), idx.size, "numpy", want_u=self.want_u)
            Pt0, Pf0, U0 = (np.moveaxis(X, 0, 2) for X in start)
            sub.state = [Pf0[:, :, idx], Pt0[:, :, idx]] if self._mode == 2 else [Pt0[:, :, idx]]
            if self.want_u:
                sub.U = U0[:, :, idx]
            got = sub._advance_numpy(keep[:, idx], s2[:, idx], None if mu is None else np.asarray(mu)[idx],
                                     None if s2u is None else s2u[:, idx], rec)
            self._Pt[idx] = np.moveaxis(true_cov(sub.state), 2, 0)
            if self._mode == 2:
                self._Pf[idx] = np.moveaxis(sub.state[0], 2, 0)
            self._Ft[idx] = np.moveaxis(sub._filtered, 2, 0)
            if self.want_u:
                self._U[idx] = np.moveaxis(sub.U, 2, 0)
                self._Uf[idx] = np.moveaxis(sub.Uf, 2, 0)
            if rec is not None:
                for k, v in got.items():  # (slots, n, n, runs) → run-major
                    out[k][idx] = np.moveaxis(v, 3, 0)
        if rec is None:
            return None
        return {k: np.ascontiguousarray(v.transpose(1, 2, 3, 0)) for k, v in out.items()}  # (slots, n, n, B)

    def _advance_numpy(self, keep, s2, mu, s2u, rec=None) -> dict[str, np.ndarray] | None:
        rm = self.rm
        B = keep.shape[1]
        out = None if rec is None else {k: np.empty((v.shape[1], rm.n, rm.n, B)) for k, v in self._records(rec, 0).items()}
        for t in range(keep.shape[0]):
            F = correct(rm, self.state, keep[t], s2[t])
            if self.want_u:
                if s2u is None:
                    Fk = true_cov(correct(rm, self.state, np.ones_like(keep[t]), s2[t]))
                else:
                    Fk = true_cov(correct(rm, self.state, np.ones_like(keep[t]), s2u[t]))
                m_ = mu[None, None, :]
                with np.errstate(over="ignore", invalid="ignore"):
                    self.Uf = m_ * self.U + (1.0 - m_) * Fk
                self.U = predict(rm, [self.Uf])[0]
            self._filtered = true_cov(F)
            self.state = predict(rm, F)
            if rec is not None and rec[t] >= 0:
                r = rec[t]
                out["true"][r], out["filtered"][r] = true_cov(self.state), self._filtered
                if self.want_u:
                    out["cond"][r], out["cond_filtered"][r] = self.U, self.Uf
        return out


def covariance_paths(rm: ReceiverModel, snr: np.ndarray, threshold, P0, record=None, backend: str = "numpy") -> np.ndarray:
    """Recursion along given SNR traces ``snr`` (horizon, B) with per-column threshold Υ_T, from the
    prior P[0] = ``P0`` (paper convention).

    Returns the true error covariance (prior P[k]) at the steps in ``record`` (default: every step
    0..horizon), shape (len(record), n, n, B).
    """
    H, B = snr.shape
    T = np.broadcast_to(np.asarray(threshold, dtype=float), (B,))
    record = list(range(H + 1)) if record is None else list(record)
    out = np.empty((len(record), rm.n, rm.n, B))
    st = Stepper(rm, P0, B, backend)
    t = 0
    for i, k in sorted(enumerate(record), key=lambda x: x[1]):
        if k > t:
            Y = snr[t:k]
            keep = Y >= T[None, :]
            st.advance(keep, rm.noise(np.where(keep, Y, 1.0)))
            t = k
        out[i] = st.true
    return out


def burst_conditioned_paths(rm: ReceiverModel, rng: np.random.Generator, thresholds: np.ndarray, mus: np.ndarray,
                            snr_avg: float, P0, horizon: int, record, backend: str = "numpy",
                            s2_given_kept: np.ndarray | None = None, final_strata: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Simulate the i.i.d. exponential channel and return (path P[k], burst-conditioned U[k]) at ``record``.

    ``thresholds`` and ``mus`` (= μ_ave(Υ_T), eq. 15) have one entry per batch column. Both outputs
    have shape (len(record), n, n, B); both are unbiased for E P[k] (module doc), U with far smaller
    variance. Per step: keep = (uniform ≥ μ), Υ' = Υ_T + Exp(Υ_ave) for a kept packet (the random
    numbers are drawn step by step in this order, then the recursion runs in blocks).

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
    k = 0
    while k < horizon:
        # one block: up to the next recorded step (or the step before the last one, for the strata)
        stops = [r for r in record if r > k] + [horizon]
        end = min(stops)
        if final_strata and s2_given_kept is None and k < last - 1 < end:
            end = last - 1
        L = end - k
        keep = np.empty((L, B), dtype=bool)
        s2 = np.empty((L, B))
        strata = None
        for j in range(L):
            keep[j] = rng.random(B) >= mus
            s2[j] = rm.noise(thresholds + rng.exponential(snr_avg, B)) if s2_given_kept is None else s2_given_kept
            if final_strata and s2_given_kept is None and k + j + 1 == last:
                assert j == L - 1
                # last recorded step: E over Υ' of the kept update by stratified sampling (K strata of the
                # exponential's CDF, one uniform each) — still unbiased, and the rare low-SNR last packet that
                # dominates the variance at small Υ_T enters with its probability instead of as a 0/1 event
                acc = np.zeros((rm.n, rm.n, B))
                for i in range(final_strata):
                    u = (i + rng.random(B)) / final_strata
                    acc += st.kept_true(rm.noise(thresholds - snr_avg * np.log1p(-u)))
                with np.errstate(over="ignore", invalid="ignore"):
                    drop_u = predict(rm, [st.cond])[0]
                    strata = mus[None, None, :] * drop_u + (1.0 - mus[None, None, :]) * (acc / final_strata)
        st.advance(keep, s2, mus)
        k = end
        if k in pos:
            P_out[pos[k]] = st.true
            U_out[pos[k]] = st.cond if strata is None else strata
    return P_out, U_out


def simulate_states(rm: ReceiverModel, rng: np.random.Generator, snr: np.ndarray, threshold: float, P0) -> dict:
    """State-level check: simulate x, the noisy received packets and the receiver's estimate.

    Returns the final error e = x − x̂ (n, B) and the final covariance P (n, n, B) of the same runs,
    so that E[e eᵀ] can be compared with E[P]. The received packet is ŷ = C x + v + n with
    v ~ N(0, R), n ~ N(0, σ_n²(Υ) I) (Sec. 2.1). x̂ is the prediction x̂[k|k−1] (eq. 6); P0 its prior.
    The receiver's gain is the core's (:func:`kalman.gain` of the covariance and noise it believes in).
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
            K = np.broadcast_to(rm.gain_inv[:, :, None], (n, m, B))  # x̂⁺ = C⁻¹ ŷ (eq. 10)
        elif rm.scenario == 2:
            K = kalman.gain(state[0], C, np.zeros((m, m)))  # the filter's own covariance, noise-free belief
        elif rm.scenario == 1:
            K = kalman.gain(state[0], C, R)
        else:
            K = kalman.gain(state[0], C, R, s2[None, None, :] * np.eye(m)[:, :, None])
        upd = xh + np.einsum("imb,mb->ib", K, y - C @ xh)
        xh_plus = np.where(keep[None, :], upd, xh)
        state = predict(rm, correct(rm, state, keep, np.zeros(B) if rm.scenario == 1 else s2))
        x = A @ x + LQ @ rng.standard_normal((n, B))
        xh = A @ xh_plus
    return {"e": x - xh, "P": true_cov(state)}


# --------------------------------------------------------------------------- Monte Carlo kernels (picklable)


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
        ch, T, H = self.channel, self.thresholds, self.horizon
        G = len(T)
        Ya = ch.mean_snr
        lags = np.arange(self.max_lag + 1)
        out = {}
        iid = ch.model_copy(update={"correlation": IidCorrelation(model="iid")})
        for lab, corr in (("jakes", ch.correlation), ("iid", iid.correlation)):
            if lab == "jakes":  # the gain h itself is needed (its sample autocorrelation): the channel's generator
                h = sample_gain(rng, runs, H, corr)
                snr = Ya * (h.real**2 + h.imag**2)
            else:  # the channel's own sampler (same random numbers as sample_gain for i.i.d. gains)
                snr = iid.sample_trace(rng, runs, H).snr
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


ZERO_LOG_CDF = -800.0
"""Below this log bound the non-central χ²₂ cdf is 0 in double precision (e^−745 is the smallest subnormal)."""


def drop_cdf(x: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """``special.chndtr(x, 2, lam)`` (the non-central χ²₂ cdf), computed only where it can be non-zero.

    Pr[|v|² ≤ x] for v ~ N(m, I₂), |m|² = λ, is 0 at x = 0 and, for √x < √λ, at most
    Pr[|ζ| ≥ √λ − √x] = exp(−(√λ − √x)²/2) (ζ ~ N(0, I₂): |ζ|² is exponential with mean 2); below
    e^{ZERO_LOG_CDF} that is far under the smallest subnormal, so the value is exactly 0 and Boost is not
    called there (most particles of a long forced-drop burst: ~85 % of the calls in Fig. 7). Elsewhere the
    same function on the same inputs: the same bits (tests/fading/test_burst_mean.py checks both)."""
    out = np.zeros(np.broadcast(x, lam).shape)
    sx, sl = np.sqrt(x), np.sqrt(lam)
    live = (x > 0) & ~((sx < sl) & (-0.5 * (sl - sx) ** 2 < ZERO_LOG_CDF))
    if live.all():
        return special.chndtr(x, 2.0, lam)
    out[live] = special.chndtr(x[live], 2.0, lam[live])
    return out


def drop_quantile(p: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """``special.chndtrix(p, 2, lam)`` (the non-central χ²₂ quantile), 0 where ``p`` = 0 without calling it
    (the quantile of probability 0 is the support's end, 0: a particle whose drop probability underflowed)."""
    live = p > 0
    if live.all():
        return special.chndtrix(p, 2.0, lam)
    out = np.zeros(p.shape)
    out[live] = special.chndtrix(p[live], 2.0, lam[live])
    return out


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
    particles are resampled (systematic) when the effective sample size falls below K/2. A cloud whose Ẑ
    reaches 0 (every particle's drop probability underflowed: at Υ_T = 0 at once, on a correlated channel
    within a few steps for most clouds) contributes exactly 0 from then on and is dropped from the arrays, its
    particles no longer moved (no random numbers spent on them); the loop ends when no cloud is left. A second
    cloud does the same from t = 0 for the all-drop term. The kept clouds' initial SNRs are stratified
    (K strata of Pr[Υ_0 | kept], finer at low SNR, each particle weighted by its stratum's probability). Each Monte Carlo "run" is one independent
    pair of clouds, so the standard error over runs is honest. The L = 0 term needs only the
    marginal law of Υ and is added exactly: Pr[kept] E[σ_n² | kept] = σ²_n,ave (eq. 16).

    Sampling the restricted 2-D normal: |v|² = |m/s + ζ|² is non-central χ²₂(λ = |m|²/s²) truncated to
    [0, ρ²/s²] (inverse cdf ``chndtrix``), the angle given the radius von Mises around arg m with
    κ = √λ |v|. ``factor=None`` means independent gains (L = I): then p_t = μ_ave for every particle
    and the estimate is eq. (14) up to the sampling of σ_n²(Υ_0) — the check of the machinery (the particles
    are then moved only at the kept start: their later positions would never be read).

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
        T, H, Lf, K = self.thresholds, self.horizon, self.factor, self.K
        G = len(T)
        n = self.M1.shape[1]
        R = runs
        ngroups = 2 * G * R  # (path type, threshold, run); path type 0: kept start, 1: all drops
        half = ngroups // 2
        # the clouds still alive (Ẑ > 0), by their index in [0, ngroups) (ascending: the kept ones first); a cloud
        # whose Ẑ reached 0 (every particle's drop probability underflowed, or the product did) contributes
        # exactly 0 at every later step, so it is dropped from the arrays — at Υ_T = 0 every cloud dies at once
        gid = np.arange(ngroups)
        C = ngroups * K
        rho2 = np.repeat(np.tile(np.repeat(2.0 * T / self.snr_avg, R), 2), K)  # per particle
        kept_path = np.arange(C) < C // 2
        Zx = np.zeros((C, H))
        Zy = np.zeros((C, H))
        w = np.full(C, 1.0 / K)
        Zhat = np.ones(ngroups)  # of the live clouds
        Zall = np.ones(ngroups)  # of every cloud (the dead ones' last value, 0)
        g0 = np.zeros(C)
        X = np.zeros((n, n, G * R))
        wl = np.zeros((G, len(self.burst_lags)))
        wl2 = np.zeros((G, len(self.burst_lags)))
        ess_min = np.full(ngroups, float(K))
        lag_pos = {L: i for i, L in enumerate(self.burst_lags)}
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
                ng = len(gid)
                nk = int(np.searchsorted(gid, half))  # live kept clouds: the first nk
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
                p = -np.expm1(-xlim / 2.0) if central else drop_cdf(xlim, lam)
                if t == 0:
                    p = np.where(kept_path, np.exp(-xlim / 2.0), p)
                wp = (w * p).reshape(ng, K)
                inc = wp.sum(1)  # Σ_i w_i p_i per group
                if t >= 1 and nk:
                    # contribution of "kept at 0, then t drops": the kept clouds only
                    zprev = Zhat[:nk]
                    mom = (wp[:nk] * g0.reshape(ng, K)[:nk]).sum(1)
                    Xt = self.M1[t][:, :, None] * (zprev * mom)[None, None, :] \
                        + self.M2[t][:, :, None] * (zprev * inc[:nk])[None, None, :]
                    X[:, :, gid[:nk]] += Xt
                Zhat = Zhat * inc
                Zall[gid] = Zhat
                if t >= 1 and t in lag_pos:
                    zr = Zall[:half].reshape(G, R)
                    wl[:, lag_pos[t]] += zr.sum(1)
                    wl2[:, lag_pos[t]] += (zr * zr).sum(1)
                # reweight; resample (systematic) where the effective sample size < K/2
                wn = np.where(inc[:, None] > 0, wp / inc[:, None], 1.0 / K)
                ess = 1.0 / (wn * wn).sum(1)
                ess_min[gid] = np.minimum(ess_min[gid], ess)
                res = ess < K / 2.0
                w = wn.ravel()
                if t + 1 == H:
                    break
                live = Zhat != 0
                if not live.all():  # drop the dead clouds (before resampling: no draws spent on them)
                    if not live.any():
                        break
                    lp = np.repeat(live, K)
                    gid, Zhat, res = gid[live], Zhat[live], res[live]
                    Zx, Zy, g0, w, rho2, kept_path = Zx[lp], Zy[lp], g0[lp], w[lp], rho2[lp], kept_path[lp]
                    mx, my, lam, p, xlim, wn = mx[lp], my[lp], lam[lp], p[lp], xlim[lp], wn[live]
                    ng, C = len(gid), len(gid) * K
                if Lf is not None and np.any(res):
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
                    w.reshape(ng, K)[gidx] = 1.0 / K
                if Lf is None and t > 0:
                    # independent gains: p_t = μ_ave for every particle whatever its past, so after the kept start
                    # (g0) the positions are never read again — moving them would only spend random numbers
                    continue
                # move: forced drop (or, at t = 0 for the kept clouds, a kept packet)
                u = rng.random(C)
                if central:
                    q = -2.0 * np.log1p(-np.clip(u * p, 0.0, 1.0))
                else:
                    q = drop_quantile(np.clip(u * p, 0.0, None), lam)
                if t == 0:
                    # kept start, stratified within each cloud: |v|² − ρ²/s² ~ Exp(mean 2) by inverse cdf at a
                    # uniform point of stratum k = [e_k, e_{k+1}), e_k = (k/K)³ (fine strata at low SNR, where
                    # σ_n²(Υ_0) is large and varies fast); the particle then carries the weight
                    # e_{k+1} − e_k (stratified sampling: unbiased, far less variance than K plain draws)
                    e = (np.arange(K + 1) / K) ** 3
                    kk = np.tile(np.arange(K), ng)
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
            X += self.D[:, :, None] * Zall[half:][None, None, :]
        out = chunk_stats(X, G, R)
        out["w"] = wl
        out["w2"] = wl2
        out["ess"] = ess_min[:half].reshape(G, R).sum(1)
        return out
