"""State-level simulation: the true state x_k and the measurements behind a channel trace.

Most metrics need only the covariances P_k (they depend on the arrival history alone, design.md
"covariance-only mode"). A consistency check (NEES) and the trajectory figures need the state
itself: this module draws, for the runs of one chunk (vectorized over runs, run axis innermost,
time-major like :class:`netkf_cli.core.trace.Trace`)

    x_0 ~ N(0, P_{0|0}),   x_{k+1} = A x_k + w_k,   y_k = C x_k + v_k,   [w_k; v_k] ~ N(0, [[Q, S], [Sᵀ, R]])

(P_{0|0} = :func:`netkf_cli.linalg.riccati.initial_covariance`: every estimator starts from x̂_{0|0} = 0 with
that error covariance; S, the noise cross-covariance E[w_k v_kᵀ], is 0 unless given), and the
signal each receiver sees at step k (:func:`received`):

* an ``arrival`` / ``delay`` trace: the sensor's measurement y_k itself (the estimator decides from
  the trace which packets it has);
* an ``snr`` trace (a fading link, Mostofi & Murray 2009): y_k + n_k, n_k ~ N(0, σ_n²(Υ_k) I) with the
  channel's noise model (a dropped packet is never read);
* a ``mode`` trace (Moayedi et al. 2009, four packet modes): mode 1 on time z_k = y_k, mode 2
  delayed z_k = y_{k−1}, mode 3 missing z_k = v_k (noise only), mode 4 dropout z_k = z_{k−1}
  (the last received value held; z_0 = v_0, nothing received at time 0) — the packet model of
  :class:`netkf_cli.estimators.markov_filters.AugmentedModel` on netkf's time base.

Streams: the kernel that calls :func:`simulate` passes its chunk's generator **after** the channel
has sampled the trace from it, so the states of a chunk are a function of (seed, stream, chunk)
alone — any executor, job count or scheduling gives the same bits (:mod:`netkf_cli.runtime.montecarlo`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from netkf_cli.linalg import kalman_codegen
from netkf_cli.core.errors import ConfigError
from netkf_cli.runtime.montecarlo import run_chunked
from netkf_cli.linalg.riccati import initial_covariance
from netkf_cli.core.tolerances import PSD_INPUT_TOL, ZERO_INNOVATION_RTOL


@dataclass
class States:
    """True states and signals of one chunk: ``x`` (n, horizon+2, runs) with x[:, k] = x_k, k = 0 … horizon+1
    (x_{horizon+1} is what the last predicted estimate x̂_{horizon+1|horizon} aims at); ``y``
    (m, horizon+2, runs) the sensor's measurements y_k = C x_k + v_k; ``v`` the measurement noise;
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
    """x_0 … x_{T+1}, y_0 … y_{T+1} and the received signal for the ``trace.runs`` runs of ``trace`` (module docstring)."""
    A, C = np.asarray(system.A, float), np.asarray(system.C, float)
    n, m = A.shape[0], C.shape[0]
    T, runs = trace.horizon, trace.runs
    L0 = psd_factor(initial_covariance(system))
    Ls = psd_factor(noise_covariance(system, S))
    x = np.empty((n, T + 2, runs))
    x[:, 0] = L0 @ rng.standard_normal((n, runs))
    eps = np.einsum("pq,qtr->ptr", Ls, rng.standard_normal((n + m, T + 2, runs)))  # ε_k = [w_k; v_k], k = 0 … T+1
    w, v = eps[:n], np.ascontiguousarray(eps[n:])
    for k in range(T + 1):
        x[:, k + 1] = A @ x[:, k] + w[:, k]
    y = np.einsum("mn,ntr->mtr", C, x) + v
    comm = None
    if trace.snr is not None and callable(trace.meta.get("noise")):  # a fading link's communication noise
        comm = rng.standard_normal((m, T, runs))
    return States(x, y, v, received(trace, y, v, comm))


BLOCK_STEPS = 8
"""Steps per block of :class:`StateBlocks` (and of the :class:`StateErrorKernel` pass over them): a chunk's
per-run state arrays exist for one block of steps at a time. The numbers do not depend on it (tested)."""

_SKIP = 1 << 16  # normals drawn (and dropped) at a time while finding where each row of a draw starts


class _NormalRows:
    """The standard normals of one ``rng.standard_normal((rows, length, runs))`` call, served a block of the
    middle axis at a time (:meth:`take`, consecutive blocks), never all held at once.

    In C order row p of that draw is the ``length · runs`` normals after rows 0 … p − 1, and successive draws
    from a Generator continue one stream (``standard_normal(a)`` then ``standard_normal(b)`` equals
    ``standard_normal(a + b)``). So each row gets a copy of the bit generator at the row's start (found by drawing
    and dropping the rows before it), and ``rng`` ends where the one call would have left it."""

    def __init__(self, rng: np.random.Generator, rows: int, length: int, runs: int):
        self.runs, self.gens = runs, []
        bg = rng.bit_generator
        for _ in range(rows):
            g = np.random.Generator(type(bg)())
            g.bit_generator.state = bg.state
            self.gens.append(g)
            left = length * runs
            while left:
                k = min(left, _SKIP)
                rng.standard_normal(k)
                left -= k

    def take(self, steps: int) -> np.ndarray:
        """The next ``steps`` columns of every row: (rows, steps, runs)."""
        out = np.empty((len(self.gens), steps, self.runs))
        for p, g in enumerate(self.gens):
            out[p] = g.standard_normal((steps, self.runs))
        return out


class StateBlocks:
    """:func:`simulate` a block of steps at a time: the same random numbers in the same order and the same
    arithmetic (bit for bit), with only one block's x, y, v, z held (memory ∝ block × runs, not horizon × runs).

    Construction draws x_0 and advances ``rng`` past every normal :func:`simulate` draws (:class:`_NormalRows`);
    :meth:`blocks` then yields, for consecutive time blocks [t0, t1) of k = 0 … horizon+1,
    (t0, x, y, v, z) with x[:, j] = x_{t0+j} (and so on). It can be iterated again (the same numbers)."""

    def __init__(self, system, trace, rng: np.random.Generator, S: np.ndarray | None = None):
        self.A, self.C = np.asarray(system.A, float), np.asarray(system.C, float)
        self.n, self.m = self.A.shape[0], self.C.shape[0]
        self.trace, self.T, self.runs = trace, trace.horizon, trace.runs
        n, m, T, runs = self.n, self.m, self.T, self.runs
        L0 = psd_factor(initial_covariance(system))
        self.Ls = psd_factor(noise_covariance(system, S))
        self.x0 = L0 @ rng.standard_normal((n, runs))
        self._eps = self._snap(_NormalRows(rng, n + m, T + 2, runs))
        self._comm = None
        if trace.snr is not None and callable(trace.meta.get("noise")):  # a fading link's communication noise
            self._comm = self._snap(_NormalRows(rng, m, T, runs))
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                s2 = np.asarray(trace.meta["noise"](np.asarray(trace.snr, float)), float)
            self._sd = np.sqrt(np.where(np.isfinite(s2), np.maximum(s2, 0.0), 0.0))

    @staticmethod
    def _snap(rows: _NormalRows) -> list:
        return [g.bit_generator.state for g in rows.gens]

    @staticmethod
    def _rows(states: list, runs: int) -> _NormalRows:
        rows = _NormalRows.__new__(_NormalRows)
        rows.runs, rows.gens = runs, []
        for st in states:
            g = np.random.Generator(getattr(np.random, st["bit_generator"])())
            g.bit_generator.state = st
            rows.gens.append(g)
        return rows

    def blocks(self, size: int | None = None, x_only: bool = False):
        """Yield (t0, x, y, v, z) for consecutive blocks of ``size`` steps (default :data:`BLOCK_STEPS`);
        ``x_only``: (t0, x, None, None, None) (the same x, without the measurements)."""
        n, T, runs, A, C = self.n, self.T, self.runs, self.A, self.C
        size = max(1, int(size or BLOCK_STEPS))
        eps_rows = self._rows(self._eps, runs)
        comm_rows = None if self._comm is None else self._rows(self._comm, runs)
        mode = None if self.trace.mode is None else np.asarray(self.trace.mode)
        xk = self.x0
        y_prev = z_prev = None
        for t0 in range(0, T + 2, size):
            t1 = min(T + 2, t0 + size)
            tb = t1 - t0
            eps = np.einsum("pq,qtr->ptr", self.Ls, eps_rows.take(tb))  # ε_k = [w_k; v_k], k = t0 … t1−1
            w, v = eps[:n], np.ascontiguousarray(eps[n:])
            x = np.empty((n, tb, runs))
            x[:, 0] = xk
            for j in range(tb - 1):
                x[:, j + 1] = A @ x[:, j] + w[:, j]
            if t1 - 1 <= T:  # x_{t1}, the next block's first state
                xk = A @ x[:, tb - 1] + w[:, tb - 1]
            if x_only:
                yield t0, x, None, None, None
                continue
            y = np.einsum("mn,ntr->mtr", C, x) + v
            if comm_rows is not None:
                z = y.copy()
                c0, c1 = max(t0, 1), min(t1, T + 1)  # z_k += σ_n(Υ_k) n_k for k = 1 … T
                if c1 > c0:
                    z[:, c0 - t0: c1 - t0] += self._sd[None, c0 - 1: c1 - 1] * comm_rows.take(c1 - c0)
            elif mode is None:
                z = y
            else:
                z = np.empty_like(y)
                for j in range(tb):
                    k = t0 + j
                    if k == 0:
                        z[:, 0] = v[:, 0]
                        continue
                    q = mode[min(k, mode.shape[0]) - 1]
                    yp = y[:, j - 1] if j else y_prev
                    zp = z[:, j - 1] if j else z_prev
                    z[:, j] = np.where(q == 0, y[:, j], np.where(q == 1, yp, np.where(q == 2, v[:, j], zp)))
                y_prev, z_prev = y[:, tb - 1].copy(), z[:, tb - 1].copy()
            yield t0, x, y, v, z

    def received(self) -> np.ndarray:
        """z (m, horizon+2, runs), what the receiver sees (:func:`received`), block by block."""
        z = np.empty((self.m, self.T + 2, self.runs))
        for t0, _, _, _, zb in self.blocks():
            z[:, t0: t0 + zb.shape[1]] = zb
        return z

    def states(self) -> States:
        """x and z whole, block by block (y and v are not kept: ``States.y``, ``States.v`` are None)."""
        x = np.empty((self.n, self.T + 2, self.runs))
        z = np.empty((self.m, self.T + 2, self.runs))
        for t0, xb, _, _, zb in self.blocks():
            x[:, t0: t0 + xb.shape[1]] = xb
            z[:, t0: t0 + zb.shape[1]] = zb
        return States(x, None, None, z)


def received(trace, y: np.ndarray, v: np.ndarray, comm: np.ndarray | None = None) -> np.ndarray:
    """What the receiver sees at each step (module docstring): ``y`` unless the trace carries modes or SNRs;
    a fading link adds σ_n(Υ_k) · ``comm`` (standard normal draws, (m, horizon, runs)) to y_k, k ≥ 1, with the
    channel's noise model σ_n²(Υ) (``trace.meta['noise']``; a dropped packet is never read)."""
    if comm is not None:
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            s2 = np.asarray(trace.meta["noise"](np.asarray(trace.snr, float)), float)
        sd = np.sqrt(np.where(np.isfinite(s2), np.maximum(s2, 0.0), 0.0))
        z = y.copy()
        z[:, 1: trace.horizon + 1] += sd[None] * comm
        return z
    if trace.mode is None:
        return y
    z = np.empty_like(y)
    z[:, 0] = v[:, 0]
    mode = np.asarray(trace.mode)  # (T, runs): mode of step k is trace step k − 1, 0-based (0 on time … 3 dropout)
    for k in range(1, y.shape[1]):
        q = mode[min(k, mode.shape[0]) - 1]
        z[:, k] = np.where(q == 0, y[:, k], np.where(q == 1, y[:, k - 1], np.where(q == 2, v[:, k], z[:, k - 1])))
    return z


# ---------------------------------------------------------------------------------------------- NEES
def nees(err: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(eᵀ P⁺ e, rank P) per run for errors ``err`` (n, runs) and covariances ``P`` (n, n, runs).

    P⁺ is the pseudo-inverse (eigenvalues below ``ZERO_INNOVATION_RTOL``·λ_max count as zero): a
    direction the estimator knows exactly (P singular, e.g. x_0 known) has no error to normalize. If
    P is the error covariance of a Gaussian error, eᵀ P⁺ e ~ χ²(rank P): mean rank P, variance 2 rank P.
    n ≤ 2 in closed form (:func:`_nees_small`: the same eigen-decomposition, equal to ``eigh`` to rounding),
    larger n through ``np.linalg.eigh`` (:func:`nees_eigh`, the reference).
    """
    if P.shape[0] <= 2:
        fn = _nees_kernel()
        if fn is None or P.shape[0] == 1:
            return _nees_small(err, P)
        q, rank = np.empty(err.shape[1]), np.empty(err.shape[1])
        fn(np.ascontiguousarray(err), np.ascontiguousarray(P), ZERO_INNOVATION_RTOL, q, rank)
        return q, rank
    return nees_eigh(err, P)


NEES2_SOURCE = """import math
import numpy as np
import numba as nb


@nb.njit(cache=True, nogil=True)
def nees2(err, P, rtol, q, rank):
    a = c = b01 = b10 = np.nan  # the previous run's P (NaN: never equal)
    lmax = lmin = vx = vy = tol = 0.0
    for r in range(err.shape[1]):
        if P[0, 0, r] == a and P[1, 1, r] == c and P[0, 1, r] == b01 and P[1, 0, r] == b10:
            _nees2_quad(err, r, lmax, lmin, vx, vy, tol, q, rank)  # the same P: its eigen-decomposition again
            continue
        a = P[0, 0, r]
        c = P[1, 1, r]
        b01 = P[0, 1, r]
        b10 = P[1, 0, r]
        b = 0.5 * (b01 + b10)
        h = 0.5 * (a - c)
        rr = math.hypot(h, b)
        mid = 0.5 * (a + c)
        lmax = mid + rr
        lmin = mid - rr
        if h >= 0.0:
            vx = rr + h
            vy = b
        else:
            vx = b
            vy = rr - h
        nv = math.hypot(vx, vy)
        if nv > 0.0:
            vx = vx / nv
            vy = vy / nv
        else:
            vx = 1.0
            vy = 0.0
        tol = max(rtol * max(lmax, 0.0), 0.0)
        _nees2_quad(err, r, lmax, lmin, vx, vy, tol, q, rank)


@nb.njit(inline="always")
def _nees2_quad(err, r, lmax, lmin, vx, vy, tol, q, rank):
    u1 = vx * err[0, r] + vy * err[1, r]
    u2 = -vy * err[0, r] + vx * err[1, r]
    s = 0.0
    k = 0.0
    if lmax > tol:
        s += u1 * u1 / lmax
        k += 1.0
    if lmin > tol:
        s += u2 * u2 / lmin
        k += 1.0
    q[r] = s
    rank[r] = k
"""
""":func:`_nees_small` for n = 2 in one compiled pass (the same operations in the same order); a run whose P
equals the previous run's (the exact LMMSE reports one P for every run) reuses its eigen-decomposition — the same
inputs, so the same numbers — without the two ``hypot``s that bound the pass."""

_NEES2 = []


def _nees_kernel():
    """The compiled n = 2 NEES when numba imports (through ``kalman_codegen``'s kernel cache), else None."""
    if not _NEES2:
        try:
            import numba  # noqa: F401  (optional: the compiled NEES only when netkf[fast] is installed)
        except ImportError:
            _NEES2.append(None)
        else:
            _NEES2.append(kalman_codegen._load(NEES2_SOURCE, "netkf_nees2", "nees2"))  # its shared loader
    return _NEES2[0]


def nees_eigh(err: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`nees` through ``np.linalg.eigh`` per run (any n; the reference of the closed forms)."""
    w, V = np.linalg.eigh(np.moveaxis(0.5 * (P + P.swapaxes(0, 1)), -1, 0))  # (runs, n), (runs, n, n)
    tol = ZERO_INNOVATION_RTOL * np.maximum(w[:, -1:], 0.0)
    ok = w > np.maximum(tol, 0.0)
    winv = np.where(ok, 1.0 / np.where(ok, w, 1.0), 0.0)
    u = np.einsum("rji,jr->ri", V, err)
    return (u * u * winv).sum(axis=1), ok.sum(axis=1).astype(float)


def _nees_small(err: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`nees` for n = 1, 2, vectorized over runs: the eigenvalues of the symmetrized 2×2 P,
    λ± = (a + c)/2 ± r, r = hypot((a − c)/2, b), the unit eigenvector of λ+ from whichever of
    (r + h, b), (b, r − h) (h = (a − c)/2) is the better conditioned, the other one orthogonal."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if P.shape[0] == 1:
            w = P[0, 0]
            ok = w > 0.0
            e = err[0]
            return np.where(ok, e * e / np.where(ok, w, 1.0), 0.0), ok.astype(float)
        a, c = P[0, 0], P[1, 1]
        b = 0.5 * (P[0, 1] + P[1, 0])
        h = 0.5 * (a - c)
        r = np.hypot(h, b)
        mid = 0.5 * (a + c)
        lmax, lmin = mid + r, mid - r
        pos = h >= 0.0
        vx = np.where(pos, r + h, b)
        vy = np.where(pos, b, r - h)
        nv = np.hypot(vx, vy)
        zero = ~(nv > 0.0)  # r = 0: P = a I, any basis
        nv = np.where(zero, 1.0, nv)
        vx, vy = np.where(zero, 1.0, vx / nv), np.where(zero, 0.0, vy / nv)
        u1 = vx * err[0] + vy * err[1]
        u2 = -vy * err[0] + vx * err[1]
        tol = np.maximum(ZERO_INNOVATION_RTOL * np.maximum(lmax, 0.0), 0.0)
        ok1, ok2 = lmax > tol, lmin > tol
        q = np.where(ok1, u1 * u1 / np.where(ok1, lmax, 1.0), 0.0) + np.where(ok2, u2 * u2 / np.where(ok2, lmin, 1.0), 0.0)
        return q, ok1.astype(float) + ok2.astype(float)


def truth_index(k: int, quantity: str, lag: int = 0) -> int:
    """The time of the state a quantity at step k estimates: x_k (filtered), x_{k+1} (predicted), x_{k−N}."""
    return {"filtered": k, "predicted": k + 1, "smoothed": k - lag}[quantity]


def _check_estimates(estimator, system, channel) -> None:
    if not callable(getattr(estimator, "estimates", None)):
        raise ConfigError.at("estimator.kind", f"estimator {estimator.kind!r} has no state-level estimates() "
                                               f"(`netkf list` shows which do)")
    estimator.check(system, channel)


class StateErrorKernel:
    """Sample a trace, the states behind it (:func:`simulate`), run every estimator's ``estimates`` on the
    same runs; reduce per column c = (estimator j, quantity q) (``columns``) and step: Σ‖e‖², Σ‖e‖⁴, Σ e eᵀ,
    Σ tr P, Σ (tr P)², Σ NEES, Σ NEES², Σ rank P, Σ and Σ² of ‖e‖² − tr P (paired), non-finite count; per run
    the average over ``window`` of ‖e‖², tr P, NEES and rank P (one sample per run: exact standard errors)
    and the paired difference of the windowed ‖e‖² against the first column of the same quantity. A mode
    trace adds per run the fraction of steps in each mode (``mode_frac``). ``keep`` > 0: the chunk instead
    returns its first ``keep`` runs' true states and estimates (trajectories)."""

    def __init__(self, system, channel, estimators, horizon: int, steps, columns, window=(), S=None, keep: int = 0):
        self.system, self.channel, self.estimators = system, channel, list(estimators)
        self.horizon, self.steps = int(horizon), sorted(int(k) for k in steps)
        self.columns = [(int(j), str(q)) for j, q in columns]
        self.window = sorted(int(k) for k in window)
        self.S, self.keep = S, int(keep)

    def __call__(self, rng: np.random.Generator, runs: int) -> dict:
        trace = self.channel.sample_trace(rng, runs, self.horizon)
        if self.keep:  # trajectories: a few runs
            st = simulate(self.system, trace, rng, self.S)
        else:  # the same numbers a block of steps at a time: no whole-horizon noise, y or v (StateBlocks)
            st = StateBlocks(self.system, trace, rng, self.S).states()
        want = sorted(set(self.steps) | set(self.window))
        K, n = len(self.steps), st.x.shape[0]
        win = set(self.window)
        pos: dict = {}
        for i, kk in enumerate(self.steps):  # step → its position (the first, as list.index), once per chunk
            pos.setdefault(kk, i)
        out: dict = {"n": np.asarray(runs)}
        if self.keep:
            out["traj_x"] = st.x[:, : self.horizon + 1].copy()
            if trace.mode is not None:
                out["traj_mode"] = trace.mode.astype(float)
            elif trace.arrival is not None:
                out["traj_arrival"] = trace.arrival.astype(float)
        elif trace.mode is not None:
            frac = np.stack([(trace.mode == q).mean(axis=0) for q in range(int(trace.mode.max(initial=0)) + 1)])
            nm = len(trace.meta.get("rho", [])) or frac.shape[0]
            f = np.zeros((nm, runs))
            f[: frac.shape[0]] = frac
            out["mode_frac"], out["mode_fracsq"] = f.sum(axis=1), (f * f).sum(axis=1)
        refs: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        for j, est in enumerate(self.estimators):
            cols = [(c, q) for c, (jj, q) in enumerate(self.columns) if jj == j]
            if not cols:
                continue
            lag = int(getattr(est, "lag", 0) or 0)
            acc = {}
            for c, q in cols:
                acc[c] = {"wa": np.zeros((4, runs)), "bad": np.zeros(runs, bool),
                          "traj": np.full((n, len(want), runs), np.nan) if self.keep else None}
                if not self.keep:
                    acc[c].update({key: np.zeros(shape) for key, shape in (
                        ("sum_e2", K), ("sum_e4", K), ("sum_eeT", (K, n, n)), ("sum_trP", K), ("sumsq_trP", K),
                        ("sum_nees", K), ("sumsq_nees", K), ("sum_rank", K), ("sum_d", K), ("sumsq_d", K),
                        ("nonfinite", K))})
            for k, res in est.estimates(self.system, trace, st.z, want, tuple(q for _, q in cols)):
                for c, q in cols:
                    a = acc[c]
                    xh, P = res[q]
                    if a["traj"] is not None:
                        a["traj"][:, want.index(k)] = xh
                        continue
                    e = st.x[:, truth_index(k, q, lag)] - xh
                    ok = np.isfinite(e).all(axis=0) & np.isfinite(P).all(axis=(0, 1))
                    if ok.all():  # the usual case: no masking needed
                        e2, trP = (e * e).sum(axis=0), np.trace(P)
                        qq, rank = nees(e, P)
                    else:
                        e = np.where(ok, e, 0.0)
                        Pf = np.where(ok, P, 0.0)
                        e2, trP = (e * e).sum(axis=0), np.trace(Pf)
                        qq, rank = nees(e, Pf + (~ok) * np.eye(n)[:, :, None])
                        qq, rank = np.where(ok, qq, 0.0), np.where(ok, rank, 0.0)
                    if k in win:
                        a["wa"] += np.stack([e2, trP, qq, rank]) / len(self.window)
                        a["bad"] |= ~ok
                    i = pos.get(k)
                    if i is not None:
                        a["sum_e2"][i] = e2.sum()
                        a["sum_e4"][i] = (e2 * e2).sum()
                        a["sum_eeT"][i] = np.einsum("ir,jr->ij", e, e)
                        a["sum_trP"][i] = trP.sum()
                        a["sumsq_trP"][i] = (trP * trP).sum()
                        a["sum_nees"][i] = qq.sum()
                        a["sumsq_nees"][i] = (qq * qq).sum()
                        a["sum_rank"][i] = rank.sum()
                        a["sum_d"][i] = (e2 - trP).sum()
                        a["sumsq_d"][i] = ((e2 - trP) ** 2).sum()
                        a["nonfinite"][i] = (~ok).sum()
            for c, q in cols:
                a = acc[c]
                if a["traj"] is not None:
                    out[f"traj_{c}"] = a["traj"]
                    continue
                out.update({f"{key}_{c}": v for key, v in a.items() if key not in ("wa", "bad", "traj")})
                if self.window:
                    wa, bad = a["wa"], a["bad"]
                    wa[:, bad] = 0.0
                    out[f"win_sum_{c}"] = wa.sum(axis=1)
                    out[f"win_sumsq_{c}"] = (wa * wa).sum(axis=1)
                    out[f"win_nonfinite_{c}"] = np.asarray(float(bad.sum()))
                    if q not in refs:
                        refs[q] = (wa[0].copy(), bad.copy())
                    ref, ref_bad = refs[q]
                    both = ~(bad | ref_bad)
                    d = np.where(both, wa[0] - ref, 0.0)
                    out[f"diff_sum_{c}"] = np.asarray(d.sum())
                    out[f"diff_sumsq_{c}"] = np.asarray((d * d).sum())
                    out[f"diff_n_{c}"] = np.asarray(float(both.sum()))
        if self.keep:
            out = {k: (v[..., : self.keep] if k.startswith("traj") else v) for k, v in out.items()}
        return out


def columns_of(estimators, quantities) -> list[tuple[int, str]]:
    """(estimator j, quantity q) for every listed quantity each estimator offers, estimator-major."""
    return [(j, q) for j, e in enumerate(estimators) for q in quantities if q in getattr(e, "quantities", ("filtered",))]


def simulate_errors(system, channel, estimators, *, steps, runs: int, horizon: int, seed: int, chunk: int,
                    stream: int = 0, quantity="filtered", window=(), S=None, progress=None,
                    label: str = "state_error") -> dict:
    """Summed :class:`StateErrorKernel` statistics over all chunks of ``stream`` (any executor, same bits);
    ``quantity`` one name or several (columns: :func:`columns_of`)."""
    for es in estimators:
        _check_estimates(es, system, channel)
    qs = (quantity,) if isinstance(quantity, str) else tuple(quantity)
    kernel = StateErrorKernel(system, channel, estimators, horizon, steps, columns_of(estimators, qs), window, S)
    return run_chunked(kernel, runs, chunk, seed, stream=stream, progress=progress, label=label)


def trajectories(system, channel, estimators, *, runs: int, steps, horizon: int, seed: int, stream: int,
                 quantity: str = "filtered", S=None) -> dict:
    """The first ``runs`` runs of stream ``stream`` (one chunk): ``traj_x`` (n, horizon+1, runs), per estimator
    column ``traj_c`` (n, len(steps), runs) (:func:`columns_of`) and the channel's mode or arrival path."""
    qs = (quantity,) if isinstance(quantity, str) else tuple(quantity)
    kernel = StateErrorKernel(system, channel, estimators, horizon, steps, columns_of(estimators, qs), (), S, keep=runs)
    return run_chunked(kernel, runs, runs, seed, stream=stream, label="trajectories")
