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

from typing import ClassVar, Literal

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

    accepts: ClassVar[frozenset[str]] = frozenset({"delay", "arrival"})
    quantity: ClassVar[str] = "P_{k|k}"

    kind: Literal["buffered"] = Field(description="raw measurements, MKF re-run over the receive buffer (Shi 2009, Prop. 3.1)")
    packet: PacketKind = Field(
        "auto",
        description="what a packet carries: measurement = y_k (Sec. 3, any C), pair = (y_k, y_{k-1}) "
        "(Appendix B); auto = pair iff C is not invertible but [C; CA] is, else measurement",
    )
    backend: BackendKind = Field(
        "auto",
        description="covariance Monte Carlo backend: auto (default) = numba when importable (m ≤ 2), else numpy; "
        "numpy (the reference); numba (compiled, same random numbers, P_k bitwise equal to numpy); "
        "numba_philox (compiled, in-kernel counter-based random numbers: fastest, statistically equal)",
    )

    def span(self, s: LinearSystem) -> int:
        """Number of consecutive measurements a packet carries (1 or 2)."""
        return packet_span(s, self.packet)

    def resolved_backend(self, system: LinearSystem) -> str:
        """The backend that actually runs (``auto`` → ``numba`` or ``numpy``): record it in the meta."""
        if self.backend == "numpy":
            return "numpy"
        from netkf_cli.estimators import buffered_numba as bn

        return bn.resolve_backend(self.backend, system)

    def check(self, system: LinearSystem, channel) -> None:
        """Simulation needs nothing beyond a valid system: any C works with measurement packets
        (M̄ and the Thm 3.8 bounds are the metric's business). Refuses an unusable ``backend`` and a
        multi-sensor channel."""
        single_link(channel, "buffered")
        packet_span(system, self.packet)
        if self.backend != "numpy":
            from netkf_cli.estimators import buffered_numba as bn

            bn.resolve_backend(self.backend, system)

    def covariances(self, system: LinearSystem, trace, steps):
        """Yield (k, P_k) with P_k shaped (n, n, runs): the MKF over the time-k view (Prop. 3.1).

        The trace's ``delay`` (or, for a pure-loss trace, ``arrival`` as delay 0 / lost) and
        ``meta['buffer']``/``meta['convention']`` (no buffer in meta: every delay is kept) give
        γ_s^{(k)} = [d_s ≤ min(k − s, D_max)] (eq. 4). Packets older than the oldest packet still in
        flight at k (in any run) have their final status, so one MKF pass over the final pattern
        carries the common prefix and each requested k re-runs only the steps from that packet on,
        from a copy (the re-run of Prop. 3.1) — at most D_max + span steps. P0 is the system's
        (``steady`` = P̄). Overflow: ∞ entries (never an exception).
        """
        yield from buffered_covariances(system, trace, steps, packet_span(system, self.packet), backend=self.backend)


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
    if not _c_invertible(s) and _pair_invertible(s):
        return 2
    return 1  # C invertible, or neither: measurement packets simulate for any C (M̄ then does not exist)


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
    overflowed P⁻ = ∞ to the exact r/c² instead of NaN.

    Overflow-safe for n > 1 (issue 14.4). The covariance form loses all precision once P⁻ ≫ R
    (P⁻ − P⁻Cᵀ S⁻¹ C P⁻ cancels numbers of size P⁻) and then overflows to ∞ − ∞ = NaN, which used to
    poison a run for good — a run that had diverged and then received packets was counted as
    P ≰ M forever (Pr 0.0005 instead of 0.05 for A = diag(1e6, 0.5)). So a run
    whose diagonal exceeds :func:`overflow_limit` (checked every :func:`check_every` steps, so that
    P⁻ ≤ ~1e8·scale at every covariance-form update) moves to the *information form* Y = P⁻¹, exact
    for any size of P:

        prediction  Y⁻ = Z − Z L (I + Lᵀ Z L)⁻¹ Lᵀ Z,   Z = A⁻ᵀ Y A⁻¹,  Q = L Lᵀ   (= (A Y⁻¹ Aᵀ + Q)⁻¹)
        update      Y  = Y⁻ + γ Cᵀ R⁻¹ C                                       (= g̃ in information form)

    (Y → 0 in a diverging direction instead of P → ∞), and returns to the covariance form once
    λ_max(P) ≤ limit·1e-4. ``rescued`` counts runs that used it. Needs A invertible; for singular A
    the covariance form is kept and a non-finite P is reported as λ_max = ∞ (P ≰ M) and counted.
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
        # overflow rescue (information form), see the class docstring
        self.limit = overflow_limit(s)
        self.every = check_every(s)
        self._steps = 0
        self._diag = [idx for (i, j), idx in self._idx.items() if i == j]
        self._info = _InfoForm.create(s)
        self._irun = np.empty(0, dtype=np.intp)  # runs currently in information form
        self._Y = np.empty((n, n, 0))
        self.rescued = np.zeros(R, dtype=bool)

    # -- state -------------------------------------------------------------------------------
    def clone(self) -> "MKFBatch":
        """An independent copy (state and rescue bookkeeping; scratch buffers fresh)."""
        c = MKFBatch(self.s, self.runs)
        if self.scalar:
            np.copyto(c.P, self.P)
            return c
        np.copyto(c._buf[0], self._buf[self._cur])
        c._cur = 0
        c._irun, c._Y, c.rescued = self._irun.copy(), self._Y.copy(), self.rescued.copy()
        c._steps = self._steps  # same check schedule as one uninterrupted pass
        return c

    def set(self, P0: np.ndarray) -> None:
        P0 = np.asarray(P0, dtype=float).reshape(self.n, self.n)
        if self.scalar:
            self.P.fill(P0[0, 0])
            return
        buf = self._buf[self._cur]
        for (i, j), k in self._idx.items():
            if i <= j:
                buf[k].fill(P0[i, j])
        self._irun = np.empty(0, dtype=np.intp)
        self._Y = np.empty((self.n, self.n, 0))
        self.rescued[:] = False
        self._steps = 0
        if not np.all(np.isfinite(P0)) or np.abs(np.diag(P0)).max(initial=0.0) > self.limit:
            self._check()

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
        if not self.scalar and len(self._irun):
            out[self._irun] = np.moveaxis(self._info.covariance(self._Y), -1, 0)
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
        if len(self._irun):  # λ_max(P) = 1/λ_min(Y), ∞ for a singular Y (exact, no inverse needed)
            lam[self._irun] = self._info.lam_max(self._Y)
        return lam

    # -- one MKF step ------------------------------------------------------------------------
    def step(self, avail: np.ndarray) -> None:
        """P_t = (I − γ_t K_t C)(A P_{t−1} Aᵀ + Q) for every run (MKF, Sec. 3.1)."""
        if self.scalar:
            P, t = self.P, self._tmp
            with np.errstate(over="ignore", divide="ignore"):
                np.multiply(P, self.a2, out=P)
                np.add(P, self.q, out=P)  # P⁻ = a²P + q  (h)
                np.reciprocal(P, out=t)
                np.add(t, self.beta, out=t, where=avail)  # information update where γ = 1  (g̃)
                np.reciprocal(t, out=P)
            return
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            self._cov_step(avail)
        if len(self._irun):
            self._Y = self._info.step(self._Y, np.asarray(avail, dtype=bool)[self._irun])
            new = self._buf[self._cur]
            for k in range(len(new)):
                new[k][self._irun] = 0.0  # placeholder (finite): these runs live in Y
        self._steps += 1
        if self._steps % self.every == 0:
            self._check()

    def _check(self) -> None:
        """Move runs whose P became huge (or non-finite) to the information form, and back."""
        if self._info is None:
            return
        buf = self._buf[self._cur]
        big = ~(buf[self._diag[0]] <= self.limit)
        for k in self._diag[1:]:
            big |= ~(buf[k] <= self.limit)
        if len(self._irun):
            back = self._info.lam_max(self._Y) <= self.limit * 1e-4
            if back.any():
                P = self._info.covariance(self._Y[:, :, back])
                for (i, j), k in self._idx.items():
                    if i <= j:
                        buf[k][self._irun[back]] = P[i, j]
                self._irun, self._Y = self._irun[~back], self._Y[:, :, ~back]
            big[self._irun] = False
        if big.any():
            new = np.flatnonzero(big)
            P = np.empty((self.n, self.n, len(new)))
            for (i, j), k in self._idx.items():
                P[i, j] = buf[k][new]
            self._Y = np.concatenate([self._Y, self._info.information(P)], axis=2)
            self._irun = np.concatenate([self._irun, new])
            self.rescued[new] = True
            for k in range(len(buf)):
                buf[k][new] = 0.0

    def _cov_step(self, avail: np.ndarray) -> None:
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


def check_every(s: LinearSystem) -> int:
    """Steps between two overflow checks of :class:`MKFBatch`: P may grow by ‖A‖² per step, so
    ``every`` steps grow it by at most ~1e4 (1 ≤ every ≤ 8)."""
    g = float(np.linalg.norm(s.A, 2)) ** 2
    if g <= 1.0:
        return 8
    return int(max(1, min(8, np.floor(4.0 / np.log10(g)))))


def overflow_limit(s: LinearSystem) -> float:
    """Diagonal size of P beyond which :class:`MKFBatch` switches a run to the information form:
    1e8·max(1, q_ii, r_ii) / ‖A‖^(2·every), so that P⁻ ≤ ~1e8·scale at every covariance-form update
    (relative rounding of the update ≤ ~1e-8) even though the check runs every ``check_every`` steps."""
    scale = max(1.0, float(np.abs(np.diag(s.Q)).max()), float(np.abs(np.diag(s.R)).max()))
    g = float(np.linalg.norm(s.A, 2)) ** 2
    return 1e8 * scale / max(1.0, g) ** check_every(s)


class _InfoForm:
    """Information-form MKF step Y = P⁻¹ on ``(n, n, runs)`` stacks (see :class:`MKFBatch`)."""

    def __init__(self, s: LinearSystem):
        n = s.n
        self.n = n
        self.AinvT = np.linalg.solve(s.A, np.eye(n)).T  # A⁻ᵀ (solve, not inv)
        w, V = np.linalg.eigh(riccati.sym(s.Q))
        keep = w > 1e-300
        self.L = V[:, keep] * np.sqrt(w[keep])  # Q = L Lᵀ
        self.J = riccati.sym(s.C.T @ np.linalg.solve(s.R, s.C))  # Cᵀ R⁻¹ C

    @classmethod
    def create(cls, s: LinearSystem):
        """None when A is singular (no information-form prediction)."""
        if np.linalg.matrix_rank(s.A) < s.n:
            return None
        return cls(s)

    def step(self, Y: np.ndarray, avail: np.ndarray) -> np.ndarray:
        from netkf_cli import batched as bt

        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            Z = bt.congruence(self.AinvT, Y)  # A⁻ᵀ Y A⁻¹
            if self.L.shape[1]:
                ZL = bt.right(Z, self.L)
                S = bt.left(self.L.T, ZL) + np.eye(self.L.shape[1])[:, :, None]
                Z = Z - bt.matmul(ZL, bt.solve_small(S, ZL.swapaxes(0, 1)))
            Y = bt.sym(Z) + self.J[:, :, None] * avail.astype(float)[None, None, :]
        return Y

    def information(self, P: np.ndarray) -> np.ndarray:
        """Y = P⁻¹ (a non-finite P: Y = 0 in every direction, i.e. no information)."""
        finite = np.isfinite(P).all(axis=(0, 1))
        out = np.zeros_like(P)
        if finite.any():
            Pm = np.moveaxis(P[:, :, finite], -1, 0)
            out[:, :, finite] = np.moveaxis(np.linalg.solve(Pm, np.broadcast_to(np.eye(self.n), Pm.shape)), 0, -1)
        return 0.5 * (out + out.swapaxes(0, 1))

    def lam_max(self, Y: np.ndarray) -> np.ndarray:
        """λ_max(Y⁻¹) = 1/λ_min(Y), ∞ when Y is singular or non-finite."""
        finite = np.isfinite(Y).all(axis=(0, 1))
        Ym = np.moveaxis(np.where(finite[None, None, :], Y, 0.0), -1, 0)
        lmin = np.linalg.eigvalsh(Ym)[:, 0]
        with np.errstate(divide="ignore", over="ignore"):
            lam = np.where(lmin > 0, 1.0 / np.where(lmin > 0, lmin, 1.0), np.inf)
        return np.where(finite & np.isfinite(lam), lam, np.inf)

    def covariance(self, Y: np.ndarray) -> np.ndarray:
        """P = Y⁻¹ per run; ∞ entries where Y is singular (P unbounded)."""
        ok = np.isfinite(self.lam_max(Y))
        out = np.full_like(Y, np.inf)
        if ok.any():
            Ym = np.moveaxis(Y[:, :, ok], -1, 0)
            P = np.linalg.solve(Ym, np.broadcast_to(np.eye(self.n), Ym.shape))
            out[:, :, ok] = np.moveaxis(0.5 * (P + P.swapaxes(1, 2)), 0, -1)
        return out


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


def single_link(channel, kind: str) -> None:
    """Refuse a multi-sensor channel: one packet stream carries the whole measurement y_k here."""
    S = getattr(channel, "sensors", 1)
    if isinstance(S, int) and S > 1:
        raise ConfigError.at("estimator.kind", f"the {kind} estimator reads one packet stream (the whole y_k per "
                             f"packet), but channel {channel.kind!r} has {S} sensors: use a single-link channel "
                             "(delay, bernoulli, gilbert_elliott, trace with one column) or estimator kind fusion")


def trace_delays(trace) -> np.ndarray:
    """(horizon, runs) delays of the single link of a trace: ``delay``, else ``arrival`` as 0 / LOST."""
    if trace.sensors > 1:
        raise ValueError(f"a buffered/smart-sensor estimator reads one link, the trace has {trace.sensors}")
    if trace.delay is not None:
        return trace.delay[0]
    if trace.arrival is not None:
        return np.where(trace.arrival[0], 0, LOST).astype(np.int32)
    raise ValueError("the buffered estimator needs a trace with delay or arrival")


def buffered_covariances(s: LinearSystem, trace, steps, span: int = 1, P0: np.ndarray | None = None,
                         backend: str = "numpy"):
    """Generator of (k, P_k (n, n, runs)) for ``BufferedEstimator.covariances`` (see there).

    With one requested step and a compiled ``backend`` (``auto`` with numba, m ≤ 2) the MKF over
    the time-k kept pattern runs in the compiled kernel (bitwise equal to the numpy path; a chunk
    in which some run needs the information-form rescue falls back to numpy).
    """
    T, runs = trace.horizon, trace.runs
    d = trace_delays(trace)
    D = trace.meta.get("buffer")
    Dmax = T if D is None else max_kept_delay(int(D), trace.meta.get("convention", "delay_le_D"))
    P0 = (riccati.pbar(s) if s.P0 is None else s.P0) if P0 is None else np.asarray(P0, dtype=float)
    steps = sorted(int(k) for k in steps)
    if len(steps) == 1 and backend != "numpy":
        from netkf_cli.estimators import buffered_numba as bn

        if bn.resolve_backend("auto" if backend == "auto" else "numba", s) == "numba":
            k = steps[0]
            if not 1 <= k <= T:
                raise ValueError(f"steps must lie in 1..{T}, got {k}")
            age = (k - np.arange(1, k + 1))[:, None]
            P = bn.covariance_from_kept(s, d[:k] <= np.minimum(age, Dmax), span, P0)
            if P is not None:
                yield k, P
                return
    final = d <= Dmax  # (T, runs): final kept status of packet t + 1
    a_final = availability(final, span)
    # packet s is in flight (kept later, not yet arrived) at times s … s + d_s − 1: the latest such
    # time over runs, per packet (−1: never in flight)
    dmax = np.where(final, d, 0).max(axis=1, initial=0).astype(np.int64)  # longest kept delay per packet
    last = np.where(dmax > 0, np.arange(1, T + 1) + dmax - 1, -1)
    base = MKFBatch(s, runs)
    base.set(P0)
    done = 0  # MKF steps of the final pattern applied to ``base``
    for k in sorted(int(k) for k in steps):
        if not 1 <= k <= T:
            raise ValueError(f"steps must lie in 1..{T}, got {k}")
        # packets before the oldest one still in flight at k have their final status; a pair packet
        # (span 2) also needs the next packet's status, and packet k + 1 does not exist yet at k
        inflight = np.flatnonzero(last[:k] >= k)
        j = int(inflight[0]) if len(inflight) else k  # packets 1..j are final at time k
        b = max(0, j - (span - 1))  # steps 1..b use final statuses (non-decreasing in k)
        if b < done:  # pragma: no cover - cannot happen (the oldest in-flight packet only moves on)
            base.set(P0)
            done = 0
        while done < b:
            base.step(a_final[done])
            done += 1
        if b == k:
            mkf = base
        else:
            mkf = base.clone()
            age = (k - np.arange(b + 1, k + 1))[:, None]  # packets s = b+1..k
            kept = d[b:k] <= np.minimum(age, Dmax)
            a = availability(kept, span)
            for t in range(k - b):
                mkf.step(a[t])
        yield k, np.ascontiguousarray(mkf.matrices().transpose(1, 2, 0))


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
        mkf, oldest = self._run(lambda idx, out: rng.random(out=out), runs)
        lam = mkf.lam_max()
        finite = np.isfinite(lam)
        count = np.count_nonzero(lam[:, None] <= self.thr[None, :], axis=0)
        Pm = mkf.matrices()
        stats = chunk_statistics(Pm, finite, count, oldest, runs, self.s.n)
        stats["rescued"] = np.int64(np.count_nonzero(mkf.rescued)) if not mkf.scalar else np.int64(0)
        return stats

    def run_uniforms(self, U: np.ndarray, runs: int):
        """(MKFBatch at k = horizon, oldest) from given uniforms U (horizon, runs), time-major:
        the same numbers ``__call__`` draws with ``horizon`` calls of ``rng.random(runs)``."""
        return self._run(lambda idx, out: np.copyto(out, U[idx]), runs)

    def _run(self, draw, runs: int):
        s, span, horizon, ages, Dmax = self.s, self.span, self.horizon, self.ages, self.Dmax
        F_keep, F_prev = self.F_keep, self.F_prev
        mkf = MKFBatch(s, runs)
        mkf.set(self.P0)
        u = np.empty(runs)
        kept_prev = np.empty(runs, dtype=bool)
        kept_cur = np.empty(runs, dtype=bool)
        avail = np.empty(runs, dtype=bool)
        oldest = np.zeros(runs)  # age of the oldest packet arriving exactly at k
        arrived = np.empty(runs, dtype=bool)
        for idx in range(horizon):
            draw(idx, u)
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
        return mkf, oldest


MOMENT_MAX = 1e100  # |P_ij| above this is left out of the moment sums (counted in ``overflow``)


def chunk_statistics(Pm: np.ndarray, finite: np.ndarray, count: np.ndarray, oldest: np.ndarray,
                     runs: int, n: int) -> dict:
    """Additive statistics of one chunk (shared by the numpy and the compiled backends).

    ``Pm`` (runs, n, n) final covariances, ``count`` runs with P_k ≤ M per M, ``oldest`` MKF re-runs
    minus one per run. ``overflow`` counts runs whose P_k is unbounded (∞) or too large for its
    square to be summed (> ``MOMENT_MAX``): they are counted as P_k ≰ M in ``count_leq`` (they are) and
    left out of the moment sums Σ P_k, Σ P_k², Σ tr (so E[P_k] is over the ``n − overflow`` other
    runs); ``nonfinite`` counts runs with a NaN (a numerical failure; 0 expected).
    """
    nonfinite = np.isnan(Pm).any(axis=(1, 2))
    finite = finite & ~nonfinite & (np.abs(np.where(np.isfinite(Pm), Pm, 0.0)).max(axis=(1, 2)) <= MOMENT_MAX)
    Pm[~finite] = 0.0
    updates = 1.0 + oldest
    tr = np.trace(Pm, axis1=1, axis2=2)
    return {
        "sum_trace": float(tr.sum()),
        "sumsq_trace": float((tr**2).sum()),
        "count_leq": np.asarray(count).astype(np.int64),
        "n": np.int64(runs),
        "overflow": np.int64(runs - np.count_nonzero(finite)),
        "nonfinite": np.int64(np.count_nonzero(nonfinite)),
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


# ---------------------------------------------------------------------------------------------
# Number of MKF runs per step (Prop. 3.1), for the updates_vs_buffer artefact
# ---------------------------------------------------------------------------------------------


class UpdatesKernel:
    """Picklable kernel: R_k = 1 + I_k MKF runs at time k, I_k = max{i ≤ D_max : d_{k−i} = i} ∪ {0}.

    The events {d_{k−i} = i} are independent with probabilities f(i), so Pr[I_k < j] =
    ∏_{i=j}^{D_max} (1 − f(i)) =: S_j (non-decreasing in j). Inverse transform with one uniform per
    run: I_k = #{j ∈ 1..D_max : u < 1 − S_j} — exact, O(D_max + runs·log D_max) per chunk.
    Statistics: ``sum``, ``sumsq`` of R_k and ``n``.
    """

    def __init__(self, channel):
        Dmax = max_kept_delay(channel.D, channel.convention)
        F = np.asarray(channel.cdf(np.arange(Dmax + 1)), dtype=float).reshape(Dmax + 1)
        f = np.diff(np.concatenate([[0.0], F]))
        S = np.cumprod((1.0 - f[1:])[::-1])[::-1]  # S[j − 1] = S_j, j = 1..Dmax
        self.ge = 1.0 - S  # Pr[I_k ≥ j], non-increasing in j

    def __call__(self, rng, runs):
        u = rng.random(runs)
        asc = self.ge[::-1]
        oldest = (len(asc) - np.searchsorted(asc, u, side="right")).astype(float)  # #{j : u < Pr[I ≥ j]}
        R = 1.0 + oldest
        return {"sum": float(R.sum()), "sumsq": float((R**2).sum()), "n": np.int64(runs)}
