"""Buffered optimal estimator for raw measurements (Shi, Xie & Murray 2009, Sec. 3, Prop. 3.1).

The sensor sends y_k; packets are delayed (eq. 3) and the estimator keeps a packet iff its
delay is within the buffer (``channel.convention``). At time k the estimator re-runs the
modified Kalman filter (MKF, Sec. 3.1) from the oldest newly arrived packet (Prop. 3.1), so

    P_k = f_k ∘ f_{k−1} ∘ … ∘ f_1 (P_0),   f_t = g̃∘h if y_t is available at time k, else h,

i.e. P_k is the MKF run over the *time-k view* of the arrival pattern γ_t^{(k)} (Lemma 3.7's
composition, footnote 2). It depends only on which packets are received-and-kept by time k,
which is what the covariance-only Monte Carlo exploits: one forward MKF pass per run with
the kept indicators as seen at the sampling time k.

Packets (``packet``):
* ``measurement`` — a packet carries y_t (Sec. 3; M̄ = C⁻¹RC⁻ᵀ needs C invertible);
* ``pair`` — a packet carries (y_t, y_{t−1}) (Appendix B, C not invertible but [C; CA] is):
  y_t is available at time k iff packet t or packet t + 1 is kept by k;
* ``auto`` — ``measurement`` if C is invertible, else ``pair``.

Stationary sampling: each run contributes ONE sample, P_k at k = horizon (the first
``horizon − 1`` steps are the burn-in). The samples are independent, so the standard error of
an empirical probability is exactly √(p(1−p)/n) with n = runs, and no batch-means correction
is needed. (Taking P_k at every step after a burn-in would give correlated samples.)

Memory layout (design.md): P is held as one contiguous array per matrix entry (run index
innermost), only the entries i ≤ j are computed (exact symmetry), the 2×2 innovation
covariance is inverted in closed form, and a missing packet multiplies the gain by γ = 0.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from netkf_cli import riccati
from netkf_cli.channels.delay import LOST, kept_at, max_kept_delay
from netkf_cli.errors import ConfigError
from netkf_cli.riccati import PSD_TOL
from netkf_cli.spec import EstimatorModel
from netkf_cli.system import LinearSystem

PacketKind = Literal["auto", "measurement", "pair"]
BackendKind = Literal["numpy", "numba", "numba_philox", "auto"]


class BufferedEstimator(EstimatorModel):
    """``kind: buffered`` — raw measurements, optimal re-run of the MKF over the buffer (Prop. 3.1)."""

    kind: Literal["buffered"]
    packet: PacketKind = Field(
        "auto",
        description="what a packet carries: measurement = y_k (Sec. 3), pair = (y_k, y_{k-1}) "
        "(Appendix B, for non-invertible C); auto picks measurement iff C is invertible",
    )
    backend: BackendKind = Field(
        "numpy",
        description="covariance Monte Carlo backend: numpy (reference); numba (optional extra netkf[fast]: "
        "compiled, same random numbers, P_k bitwise equal to numpy); numba_philox (compiled with in-kernel "
        "counter-based random numbers: fastest, statistically equivalent, not equal); auto = numba if "
        "installed, else numpy",
    )

    def span(self, s: LinearSystem) -> int:
        """Number of consecutive measurements a packet carries (1 or 2)."""
        return packet_span(s, self.packet)


def _c_invertible(s: LinearSystem) -> bool:
    return s.m == s.n and np.linalg.matrix_rank(s.C) == s.n


def _pair_invertible(s: LinearSystem) -> bool:
    return 2 * s.m == s.n and np.linalg.matrix_rank(np.vstack([s.C @ s.A, s.C])) == s.n


def packet_span(s: LinearSystem, packet: PacketKind = "auto", path: str = "estimator.packet") -> int:
    """1 for ``measurement`` packets, 2 for Appendix B ``pair`` packets (``auto`` decides from C)."""
    if packet == "measurement":
        return 1
    if packet == "pair":
        return 2
    if _c_invertible(s):
        return 1
    if _pair_invertible(s):
        return 2
    raise ConfigError.at(
        path,
        f"auto needs C invertible or, per Appendix B, [C; CA] square and invertible; got C of shape "
        f"{s.m}×{s.n}: choose packet: measurement explicitly (then M̄ and the bounds are unavailable)",
    )


# ---------------------------------------------------------------------------------------------
# Batched MKF step, covariance only
# ---------------------------------------------------------------------------------------------


def _lincomb(terms, const: float, out: np.ndarray, tmp: np.ndarray) -> np.ndarray:
    """Σ coef·array + const into ``out`` (zero coefficients skipped); a lone unit term is aliased."""
    nz = [(c, a) for c, a in terms if c != 0.0]
    if not nz:
        out.fill(const)
        return out
    if len(nz) == 1 and nz[0][0] == 1.0 and const == 0.0:
        return nz[0][1]
    c0, a0 = nz[0]
    if c0 == 1.0:
        np.copyto(out, a0)
    elif c0 == -1.0:
        np.negative(a0, out=out)
    else:
        np.multiply(a0, c0, out=out)
    for c, a in nz[1:]:
        if c == 1.0:
            np.add(out, a, out=out)
        elif c == -1.0:
            np.subtract(out, a, out=out)
        else:
            np.multiply(a, c, out=tmp)
            np.add(out, tmp, out=out)
    if const != 0.0:
        np.add(out, const, out=out)
    return out


class MKFBatch:
    """Error covariances of ``runs`` MKFs (Sec. 3.1) advanced in lock-step, one array per entry.

    ``step(avail)`` applies P ← (I − γ K C)(A P Aᵀ + Q) with K = P⁻Cᵀ(CP⁻Cᵀ + R)⁻¹, γ = ``avail``
    (bool per run). Scalar systems use the information form P = 1/(1/P⁻ + γ c²/r), which maps an
    overflowed P⁻ = ∞ to the exact r/c² instead of NaN. For n > 1 a non-finite P (overflow of an
    unstable run) stays non-finite and is reported as λ_max = ∞ (counted as P ≰ M).
    """

    def __init__(self, s: LinearSystem, runs: int):
        self.s, self.runs, self.n, self.m = s, int(runs), s.n, s.m
        self.scalar = self.n == 1 and self.m == 1
        if self.scalar:
            self.a2 = float(s.A[0, 0] ** 2)
            self.q = float(s.Q[0, 0])
            self.beta = float(s.C[0, 0] ** 2 / s.R[0, 0])
            self.P = np.empty(self.runs)
            self._tmp = np.empty(self.runs)
            return
        n, m = self.n, self.m
        self._idx = {}
        k = 0
        for i in range(n):
            for j in range(i, n):
                self._idx[(i, j)] = self._idx[(j, i)] = k
                k += 1
        nu = k
        R = self.runs
        self._buf = [np.empty((nu, R)), np.empty((nu, R))]  # double buffer: old P stays valid
        self._cur = 0
        self._T = np.empty((n, n, R))
        self._Pm = np.empty((nu, R))
        self._U = np.empty((n, m, R))
        self._S = np.empty((m, m, R))
        self._Si = np.empty((m, m, R))
        self._V = np.empty((n, m, R))
        self._det = np.empty(R)
        self._g = np.empty(R)
        self._tmp = np.empty(R)
        self._tmp2 = np.empty(R)

    # -- state -------------------------------------------------------------------------------
    def set(self, P0: np.ndarray) -> None:
        P0 = np.asarray(P0, dtype=float).reshape(self.n, self.n)
        if self.scalar:
            self.P.fill(P0[0, 0])
            return
        buf = self._buf[self._cur]
        for (i, j), k in self._idx.items():
            if i <= j:
                buf[k].fill(P0[i, j])

    def entry(self, i: int, j: int) -> np.ndarray:
        if self.scalar:
            return self.P
        return self._buf[self._cur][self._idx[(i, j)]]

    def matrices(self) -> np.ndarray:
        """P as a ``(runs, n, n)`` array (a copy)."""
        out = np.empty((self.runs, self.n, self.n))
        for i in range(self.n):
            for j in range(self.n):
                out[:, i, j] = self.entry(i, j)
        return out

    def lam_max(self) -> np.ndarray:
        """Largest eigenvalue of each P (∞ for a non-finite P): P ≤ M·I ⇔ λ_max(P) ≤ M."""
        if self.scalar:
            return np.where(np.isfinite(self.P), self.P, np.inf)
        Pm = self.matrices()
        finite = np.all(np.isfinite(Pm), axis=(1, 2))
        Pm[~finite] = 0.0
        lam = np.linalg.eigvalsh(Pm)[:, -1]
        lam[~finite] = np.inf
        return lam

    # -- one MKF step ------------------------------------------------------------------------
    def step(self, avail: np.ndarray) -> None:
        """P_t = (I − γ_t K_t C)(A P_{t−1} Aᵀ + Q) for every run (MKF, Sec. 3.1)."""
        if self.scalar:
            P, t = self.P, self._tmp
            np.multiply(P, self.a2, out=P)
            np.add(P, self.q, out=P)  # P⁻ = a²P + q  (h)
            np.reciprocal(P, out=t)
            np.add(t, self.beta, out=t, where=avail)  # information update where γ = 1  (g̃)
            np.reciprocal(t, out=P)
            return
        s, n, m = self.s, self.n, self.m
        A, C, Q, R = s.A, s.C, s.Q, s.R
        old = self._buf[self._cur]
        new = self._buf[1 - self._cur]
        idx = self._idx
        tmp = self._tmp
        # T = A P
        T = [[None] * n for _ in range(n)]
        for i in range(n):
            for j in range(n):
                T[i][j] = _lincomb([(A[i, k], old[idx[(k, j)]]) for k in range(n)], 0.0, self._T[i, j], tmp)
        # P⁻ = T Aᵀ + Q  (i ≤ j)
        Pm = {}
        for i in range(n):
            for j in range(i, n):
                Pm[(i, j)] = Pm[(j, i)] = _lincomb([(A[j, l], T[i][l]) for l in range(n)], Q[i, j],
                                                   self._Pm[idx[(i, j)]], tmp)
        # U = P⁻ Cᵀ  (n×m),  S = C U + R  (m×m, a ≤ b)
        U = [[_lincomb([(C[a, j], Pm[(i, j)]) for j in range(n)], 0.0, self._U[i, a], tmp) for a in range(m)]
             for i in range(n)]
        S = {}
        for a in range(m):
            for b in range(a, m):
                S[(a, b)] = S[(b, a)] = _lincomb([(C[a, i], U[i][b]) for i in range(n)], R[a, b], self._S[a, b], tmp)
        # γ S⁻¹ in closed form (m ≤ 2), batched solve otherwise
        g = self._g
        np.copyto(g, avail)
        Si = self._Si
        if m == 1:
            np.divide(g, S[(0, 0)], out=Si[0, 0])
            Sinv = {(0, 0): Si[0, 0]}
        elif m == 2:
            det = self._det
            np.multiply(S[(0, 0)], S[(1, 1)], out=det)
            np.multiply(S[(0, 1)], S[(0, 1)], out=tmp)
            np.subtract(det, tmp, out=det)
            np.divide(g, det, out=det)  # γ / det
            np.multiply(S[(1, 1)], det, out=Si[0, 0])
            np.multiply(S[(0, 0)], det, out=Si[1, 1])
            np.multiply(S[(0, 1)], det, out=Si[0, 1])
            np.negative(Si[0, 1], out=Si[0, 1])
            Sinv = {(0, 0): Si[0, 0], (1, 1): Si[1, 1], (0, 1): Si[0, 1], (1, 0): Si[0, 1]}
        else:
            Sm = np.empty((self.runs, m, m))
            for a in range(m):
                for b in range(m):
                    Sm[:, a, b] = S[(a, b)]
            inv = np.linalg.solve(Sm, np.broadcast_to(np.eye(m), Sm.shape)) * g[:, None, None]
            Sinv = {}
            for a in range(m):
                for b in range(m):
                    np.copyto(Si[a, b], inv[:, a, b])
                    Sinv[(a, b)] = Si[a, b]
        # V = U (γ S⁻¹) = γ K  (the gain multiplied by γ)
        V = [[None] * m for _ in range(n)]
        for i in range(n):
            for a in range(m):
                V[i][a] = _prod_sum([(U[i][b], Sinv[(b, a)]) for b in range(m)], self._V[i, a], tmp)
        # P = P⁻ − V Uᵀ  (i ≤ j)
        for i in range(n):
            for j in range(i, n):
                out = new[idx[(i, j)]]
                np.copyto(out, Pm[(i, j)])
                for a in range(m):
                    np.multiply(V[i][a], U[j][a], out=tmp)
                    np.subtract(out, tmp, out=out)
        self._cur = 1 - self._cur


def _prod_sum(pairs, out: np.ndarray, tmp: np.ndarray) -> np.ndarray:
    """Σ x·y over array pairs into ``out``."""
    x, y = pairs[0]
    np.multiply(x, y, out=out)
    for x, y in pairs[1:]:
        np.multiply(x, y, out=tmp)
        np.add(out, tmp, out=out)
    return out


# ---------------------------------------------------------------------------------------------
# Covariance P_k from a kept pattern (reference path) and the Monte Carlo kernel (hot path)
# ---------------------------------------------------------------------------------------------


def availability(kept: np.ndarray, span: int) -> np.ndarray:
    """Measurement availability a_t from packet kept indicators (axis 0 = time t − 1).

    span 1: a_t = γ_t.  span 2 (Appendix B, packet t carries y_t and y_{t−1}): a_t = γ_t ∨ γ_{t+1}.
    """
    kept = np.asarray(kept, dtype=bool)
    if span == 1:
        return kept
    a = kept.copy()
    a[:-1] |= kept[1:]
    return a


def covariance_from_kept(s: LinearSystem, kept: np.ndarray, span: int, P0: np.ndarray | None = None) -> MKFBatch:
    """P_k for each run from the time-k kept indicators ``kept`` of shape (k, runs) (Prop. 3.1)."""
    kept = np.asarray(kept, dtype=bool)
    k, runs = kept.shape
    a = availability(kept, span)
    mkf = MKFBatch(s, runs)
    mkf.set(riccati.pbar(s) if P0 is None else P0)
    for t in range(k):
        mkf.step(a[t])
    return mkf


def leq_threshold(M: np.ndarray) -> np.ndarray:
    """λ_max(P) ≤ threshold ⇔ P ≤ M·I in :func:`netkf_cli.riccati.psd_leq`'s tolerance."""
    M = np.asarray(M, dtype=float)
    return M + PSD_TOL * np.maximum(1.0, np.abs(M))


def buffered_mc_kernel(s: LinearSystem, channel, span: int, horizon: int, M_grid, P0: np.ndarray | None = None,
                       backend: str = "numpy", threads: int | None = None):
    """Monte Carlo kernel for ``montecarlo.run_chunked``: P_k at k = ``horizon``, one sample per run.

    Per run: draw u_s ~ U[0,1) for packets s = 1..k in time order (one (runs,) array per packet),
    γ_s^{(k)} = [u_s < F(min(k − s, D_max))] (inverse-CDF delays, see ``channels.delay``), run the
    MKF over the availability pattern, and return additive statistics:

    * ``count_leq[j]`` — #runs with P_k ≤ M_j·I,   ``n`` — #runs,   ``overflow`` — #non-finite P_k;
    * ``sum_P``, ``sumsq_P`` — Σ P_k and Σ P_k² entrywise (for E[P_k]); ``sum_trace``, ``sumsq_trace``;
    * ``sum_updates``, ``sumsq_updates`` — MKF runs at time k (Prop. 3.1: 1 + age of the oldest
      packet arriving exactly at k, or 1 if none), with arrivals d_s = k − s ⇔ F(k−s−1) ≤ u_s < F(k−s).

    The kernel is a picklable object, so process/dask executors can ship it to workers. ``backend``
    (``numpy`` | ``numba`` | ``numba_philox`` | ``auto``) selects the implementation; the resolved
    name is the kernel's ``backend`` attribute (record it in the artefact's meta). ``threads``
    (numba backends only): compiled threads per chunk, ``None`` = all cores.
    """
    if backend != "numpy":
        from netkf_cli.estimators import buffered_numba as bn

        backend = bn.resolve_backend(backend, s)
        if backend in bn.NUMBA_BACKENDS:
            return bn.NumbaMCKernel(s, channel, span, horizon, M_grid, P0,
                                    rng_mode="numpy" if backend == "numba" else "philox", threads=threads)
    return BufferedMCKernel(s, channel, span, horizon, M_grid, P0)


class BufferedMCKernel:
    """Picklable kernel ``(rng, runs) -> stats`` (see :func:`buffered_mc_kernel`)."""

    backend = "numpy"

    def __init__(self, s: LinearSystem, channel, span: int, horizon: int, M_grid, P0=None):
        self.s, self.span, self.horizon = s, int(span), int(horizon)
        self.thr = leq_threshold(np.asarray(M_grid, dtype=float))
        self.P0 = riccati.pbar(s) if P0 is None else np.asarray(P0, dtype=float)
        self.Dmax = max_kept_delay(channel.D, channel.convention)
        self.ages = horizon - np.arange(1, horizon + 1)
        self.F_keep = np.asarray(channel.cdf(np.minimum(self.ages, self.Dmax)), dtype=float)  # γ̂_{k−s}(D)
        self.F_prev = np.where(self.ages >= 1, np.asarray(channel.cdf(np.maximum(self.ages - 1, 0)), dtype=float), 0.0)

    def __call__(self, rng: np.random.Generator, runs: int):
        s, span, horizon, ages, Dmax = self.s, self.span, self.horizon, self.ages, self.Dmax
        F_keep, F_prev = self.F_keep, self.F_prev
        n = s.n
        mkf = MKFBatch(s, runs)
        mkf.set(self.P0)
        u = np.empty(runs)
        kept_prev = np.empty(runs, dtype=bool)
        kept_cur = np.empty(runs, dtype=bool)
        avail = np.empty(runs, dtype=bool)
        oldest = np.zeros(runs)  # age of the oldest packet arriving exactly at k
        arrived = np.empty(runs, dtype=bool)
        for idx in range(horizon):
            rng.random(out=u)
            np.less(u, F_keep[idx], out=kept_cur)
            if ages[idx] <= Dmax:
                np.greater_equal(u, F_prev[idx], out=arrived)
                arrived &= kept_cur
                np.maximum(oldest, np.where(arrived, float(ages[idx]), 0.0), out=oldest)
            if span == 1:
                mkf.step(kept_cur)
            else:
                # time t = idx (1-based idx) uses γ_t ∨ γ_{t+1}: step the previous time now
                if idx > 0:
                    np.logical_or(kept_prev, kept_cur, out=avail)
                    mkf.step(avail)
                kept_prev, kept_cur = kept_cur, kept_prev
        if span == 2:
            mkf.step(kept_prev)  # time k: only packet k can carry y_k
        lam = mkf.lam_max()
        finite = np.isfinite(lam)
        count = np.count_nonzero(lam[:, None] <= self.thr[None, :], axis=0)
        Pm = mkf.matrices()
        return chunk_statistics(Pm, finite, count, oldest, runs, n)


def chunk_statistics(Pm: np.ndarray, finite: np.ndarray, count: np.ndarray, oldest: np.ndarray,
                     runs: int, n: int) -> dict:
    """Additive statistics of one chunk (shared by the numpy and the compiled backends).

    ``Pm`` (runs, n, n) final covariances (overflowed runs are zeroed here and counted in
    ``overflow``), ``count`` runs with P_k ≤ M per M, ``oldest`` MKF re-runs minus one per run.
    """
    Pm[~finite] = 0.0
    updates = 1.0 + oldest
    tr = np.trace(Pm, axis1=1, axis2=2)
    return {
        "sum_trace": float(tr.sum()),
        "sumsq_trace": float((tr**2).sum()),
        "count_leq": np.asarray(count).astype(np.int64),
        "n": np.int64(runs),
        "overflow": np.int64(runs - np.count_nonzero(finite)),
        "sum_P": Pm.sum(axis=0).reshape(n, n),
        "sumsq_P": (Pm**2).sum(axis=0).reshape(n, n),
        "sum_updates": float(updates.sum()),
        "sumsq_updates": float((updates**2).sum()),
    }


# ---------------------------------------------------------------------------------------------
# State-level simulation: the literal Prop. 3.1 estimator on simulated x_k, y_k
# ---------------------------------------------------------------------------------------------


def _mkf_full(A, C, Q, R, x, P, y, gam):
    """One MKF step (Sec. 3.1) on stacks: x (runs, n), P (runs, n, n), y (runs, m), gam (runs,) bool."""
    xm = x @ A.T
    Pm = A @ P @ A.T + Q
    S = C @ Pm @ C.T + R
    PCt = Pm @ C.T
    K = np.linalg.solve(S, np.swapaxes(PCt, -1, -2))  # S⁻¹ C P⁻  (S symmetric)
    K = np.swapaxes(K, -1, -2) * gam[:, None, None]  # γ K
    innov = y - xm @ C.T
    xn = xm + np.einsum("rij,rj->ri", K, innov)
    Pn = Pm - K @ C @ Pm
    return xn, (Pn + np.swapaxes(Pn, -1, -2)) / 2


def simulate_states(s: LinearSystem, channel, span: int, runs: int, horizon: int, rng: np.random.Generator,
                    P0: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Simulate x_k, y_k, packet delays and the estimator of Prop. 3.1 literally, at k = ``horizon``.

    Delays come from the channel model's own sampler (``channel.delay.sample``; bernoulli:
    d = 0 or lost), independent of the inverse-CDF path of the covariance kernel. At every time k
    the estimator finds the oldest measurement that became available at k (new packets with
    d_s = k − s ≤ D_max; a pair packet also brings y_{s−1}) and re-runs the MKF from there,
    reusing its stored (x̂_t, P_t) for older t (Prop. 3.1). Returns at k = horizon: ``x``, ``xhat``,
    ``e`` (runs, n), ``P`` (runs, n, n), ``mkf_runs`` (horizon, runs), ``delays`` (horizon, runs).
    """
    A, C, Q, R = s.A, s.C, s.Q, s.R
    n, m = s.n, s.m
    P0 = riccati.pbar(s) if P0 is None else np.asarray(P0, dtype=float)
    D, conv = channel.D, channel.convention
    Dmax = max_kept_delay(D, conv)
    if channel.kind == "bernoulli":
        delays = np.where(rng.random((horizon, runs)) < channel.arrival, 0, LOST).astype(np.int64)
    else:
        delays = channel.delay.sample(rng, (horizon, runs)).astype(np.int64)
    LQ = _psd_sqrt(Q)
    LR = _psd_sqrt(R)
    LP = _psd_sqrt(P0)
    x = rng.standard_normal((runs, n)) @ LP.T
    xs = np.zeros((horizon + 1, runs, n))  # stored estimates x̂_t (index t), t = 0..k
    Ps = np.zeros((horizon + 1, runs, n, n))
    Ps[0] = P0
    ys = np.zeros((horizon + 1, runs, m))
    avail_prev = np.zeros((horizon + 1, runs), dtype=bool)  # a_t as known at k − 1
    mkf_runs = np.zeros((horizon, runs), dtype=np.int64)
    for k in range(1, horizon + 1):
        x = x @ A.T + rng.standard_normal((runs, n)) @ LQ.T
        ys[k] = x @ C.T + rng.standard_normal((runs, m)) @ LR.T
        kept = kept_at(delays[:k], k, D, conv)  # (k, runs): γ_t^{(k)}, t = 1..k
        a = availability(kept, span)
        avail_now = np.zeros((horizon + 1, runs), dtype=bool)
        avail_now[1:k + 1] = a
        newly = avail_now & ~avail_prev
        newly[k] = True  # time k always needs its MKF (prediction at least)
        start = np.argmax(newly, axis=0)  # oldest newly available time per run
        mkf_runs[k - 1] = k - start + 1
        for t in range(int(start.min()), k + 1):
            act = start <= t
            xn, Pn = _mkf_full(A, C, Q, R, xs[t - 1], Ps[t - 1], ys[t], avail_now[t])
            xs[t] = np.where(act[:, None], xn, xs[t])
            Ps[t] = np.where(act[:, None, None], Pn, Ps[t])
        avail_prev = avail_now
    return {"x": x, "xhat": xs[horizon], "e": x - xs[horizon], "P": Ps[horizon],
            "mkf_runs": mkf_runs, "delays": delays}


def _psd_sqrt(X: np.ndarray) -> np.ndarray:
    w, V = np.linalg.eigh((X + X.T) / 2)
    return V * np.sqrt(np.clip(w, 0, None))
