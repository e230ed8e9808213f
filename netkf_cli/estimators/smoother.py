"""Kalman fixed-lag smoother with random packet loss (Leong, Dey & Evans 2008, Sec. II, eqs 3–4).

Covariance-only and batched over runs: every matrix is stored as ``(rows, cols, runs)`` with
the run index innermost, and the loop is over time only.

Recursion. With Σ_t = P_{t|t−1}, S_t = C Σ_t Cᵀ + R, G_t = S_t⁻¹ C Σ_t and, for a *target* time
j ≤ t, D_j = P_{j|t−1} and X_j = E[e_{t|t−1} e_{j|t−1}ᵀ] (the cross blocks P^{(i)} of the
augmented state of Anderson & Moore, i = t − j), eq. (4) and the cross-covariance update read

    P_{t|t}   = Σ_t − γ_t Σ_t Cᵀ S_t⁻¹ C Σ_t                       (the filter, i = 0)
    P_{j|t}   = D_j − γ_t X_jᵀ Cᵀ S_t⁻¹ C X_j                        (eq. 4, i = t − j ≥ 1)
    X_j ← A (X_j − γ_t G_tᵀ C X_j),   Σ_{t+1} = A P_{t|t} Aᵀ + Q      (eq. 3)

and a new target starts with D_t = X_t = P_{t|t}. A lost packet (γ_t = 0) leaves every
quantity as it was (P_{j|t} = P_{j|t−1}, as the paper notes below eq. 4); it is applied by
*selecting* (``where``), not by multiplying the correction by 0, so an overflowed correction
never turns into NaN.

Only the targets that are asked for are tracked, each for ``L`` steps: P_{k−L|k} at a few
steps costs a filter plus ``L`` block updates per target (the full augmented recursion is the
special case "every step is a target").

Scalar systems (n = m = 1) use an overflow-safe form: P_{t|t} = r / (c² + r/Σ_t) and the smoother
blocks in information form (:func:`_requests_scalar`), so a run whose prediction covariance
overflowed to ``inf`` during a long loss burst gets the correct finite P_{t|t} = r/c² at its next
arrival, and the correct finite P_{j|t} once a later measurement arrives. Vector systems use the
covariance form; an entry that overflows makes the run's recorded covariance ``inf`` ("not ≤ M",
see :func:`netkf_cli.batched.psd_leq`) — never NaN, never an exception.

Backends: ``numpy`` (the reference) and ``numba`` (``_nb_*`` below, compiled lazily on first
use with an on-disk cache), which performs the same recursion per run on the same arrival array: bitwise equal for scalar systems, equal to a few ulps for vector systems (summation
order of the small products). ``auto`` = numba when importable, numpy otherwise.

Monte Carlo kernels (module-level, picklable, additive statistics with fixed keys):
:class:`SmootherMCKernel` (P_{k|k−1}, P_{k|k+N} at one step k for several lags, common random
numbers across lags) and :class:`RetransmissionKernel` (Sec. V).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from netkf_cli import batched as bt
from netkf_cli.errors import ConfigError
from netkf_cli.spec import EstimatorModel, NonNegInt
from netkf_cli.system import LinearSystem

MAX_LAG = 64
"""Largest smoothing lag accepted (the work per target grows linearly with the lag)."""

BACKENDS = ("auto", "numpy", "numba")
PRED = -1
"""Lag code of the one-step predictor P_{k|k−1} in request lists."""


# =============================================================================================
# the estimator (scenario contract, issue 12)
# =============================================================================================


class SmootherEstimator(EstimatorModel):
    """``kind: smoother`` — fixed-lag Kalman smoother under packet loss (Leong 2008, eqs 3–4).

    ``covariances`` yields P_{k−L|k} (L = ``lag``; L = 0 is the filter P_{k|k}).
    """

    accepts: ClassVar[frozenset[str]] = frozenset({"arrival"})
    quantity: ClassVar[str] = "P_{k-L|k}"

    kind: Literal["smoother"]
    lag: NonNegInt = Field(1, le=MAX_LAG, description=f"smoothing lag L: the estimate of x_{{k−L}} from y_1 … y_k "
                           f"(0 = the filter P_{{k|k}}; at most {MAX_LAG})")
    backend: Literal["auto", "numpy", "numba"] = Field(
        "auto", description="covariance recursion: numpy (reference), numba (compiled, same numbers), "
        "auto = numba when importable")

    @property
    def label(self) -> str:
        """The reported quantity for this lag, e.g. ``P_{k-2|k}``."""
        return "P_{k|k}" if self.lag == 0 else f"P_{{k-{self.lag}|k}}"

    def check(self, system, channel) -> None:
        kinds = getattr(channel, "trace_kinds", frozenset())
        if channel is not None and kinds and not (kinds & self.accepts):
            raise ConfigError.at("estimator.kind", f"the smoother needs a channel with arrival indicators "
                                 f"(bernoulli, gilbert_elliott, …); channel {getattr(channel, 'kind', '?')} gives {sorted(kinds)}")
        if channel is not None and getattr(channel, "kind", None) == "multi":
            raise ConfigError.at("estimator.kind", "the smoother takes one sensor's arrivals; channel multi has several")

    def covariances(self, system: LinearSystem, trace, steps) -> Iterator[tuple[int, np.ndarray]]:
        """Yield ``(k, P_{k−L|k})`` for k in ``steps`` (1 ≤ k ≤ horizon), each ``(n, n, runs)``.

        Time convention of :mod:`netkf_cli.trace`: step t carries y_{t+1}; P_{1|0} = A P0 Aᵀ + Q
        with P0 = P_{0|0} (``steady``: P̄, so P_{1|0} = P*). For k < L the target time k − L is
        before the start: those steps yield NaN (undefined). Overflow is ``inf``.
        """
        if trace.arrival is None:
            raise ConfigError.at("estimator.kind", "the smoother needs a trace with arrival indicators")
        if trace.arrival.shape[0] != 1:
            raise ConfigError.at("estimator.kind", f"the smoother takes one sensor's arrivals, the trace has {trace.arrival.shape[0]}")
        steps = [int(k) for k in steps]
        if any(b <= a for a, b in zip(steps[:-1], steps[1:])) or (steps and (steps[0] < 1 or steps[-1] > trace.horizon)):
            raise ValueError(f"steps must be ascending integers in 1..{trace.horizon}")
        L = int(self.lag)
        gamma = np.asarray(trace.arrival[0], dtype=bool)  # (T, runs), index t ↔ y_{t+1}
        n, runs = system.n, trace.runs
        Sigma1 = first_prediction(system)
        # core index t = measurement y_{t+1}; a target j ↔ x_{j+1}. P_{k−L|k} ↔ target k−L−1 at lag L.
        # k − L = 0 (x_0, before any measurement): the core's "virtual" target −1 (handled below).
        valid = [k for k in steps if k - L >= 1]
        res = {}
        if valid:
            targets = np.array([k - L - 1 for k in valid], dtype=np.int64)
            _, out = smoother_requests(system, gamma, Sigma1, targets, (L,), want_pred=False, backend=self.backend)
            res = {k: out[i, 0] for i, k in enumerate(valid)}
        zero = [k for k in steps if k - L == 0]
        if zero:
            for k, P in _x0_smoothed(system, gamma, zero):
                res[k] = P
        for k in steps:
            yield k, res[k] if k in res else np.full((n, n, runs), np.nan)


def first_prediction(system: LinearSystem) -> np.ndarray:
    """P_{1|0} = A P0 Aᵀ + Q with P0 = P_{0|0} (``steady`` → P̄ = g̃(P*), so P_{1|0} = P*)."""
    from netkf_cli import riccati

    if system.P0 is None:
        return riccati.pstar(system)
    return bt.sym(system.A @ system.P0 @ system.A.T) + system.Q


def _x0_smoothed(system: LinearSystem, gamma: np.ndarray, ks: list[int]):
    """P_{0|k} (x_0 given y_1 … y_k): the prior P0 augmented in front of the core recursion."""
    from netkf_cli import riccati

    P0 = riccati.pbar(system) if system.P0 is None else system.P0
    A, C, Q, R = system.A, system.C, system.Q, system.R
    runs = gamma.shape[1]
    D = np.repeat(P0[:, :, None], runs, axis=2)
    X = bt.left(A, D)  # Cov(e_{1|0}, e_{0|0})
    Sigma = np.repeat(first_prediction(system)[:, :, None], runs, axis=2)
    want = set(ks)
    with np.errstate(all="ignore"):
        for t in range(max(ks)):
            g = gamma[t][None, None, :]
            CS = bt.left(C, Sigma)
            S = bt.right(CS, C.T) + R[:, :, None]
            G = bt.solve_small(S, CS)
            F = np.where(g, bt.sym(Sigma - bt.matmul(CS.swapaxes(0, 1), G)), Sigma)
            CX = bt.left(C, X)
            D = np.where(g, bt.sym(D - bt.matmul(CX.swapaxes(0, 1), bt.solve_small(S, CX))), D)
            X = bt.left(A, np.where(g, X - bt.matmul(G.swapaxes(0, 1), CX), X))
            Sigma = bt.riccati_h(F, A, Q)
            if t + 1 in want:
                yield t + 1, _inf_if_bad(D.copy())


def _inf_if_bad(P: np.ndarray) -> np.ndarray:
    """In place on ``(…, n, n, runs)``: a matrix with any non-finite entry becomes all-``inf``
    (overflow, never NaN)."""
    bad = ~np.isfinite(P).all(axis=(-3, -2))
    if bad.any():
        P[np.broadcast_to(bad[..., None, None, :], P.shape)] = np.inf
    return P


# =============================================================================================
# backends
# =============================================================================================


def numba_available() -> bool:
    try:
        import numba  # noqa: F401
    except ImportError:
        return False
    return True


def resolve_backend(backend: str) -> str:
    """``auto`` → ``numba`` when importable, else ``numpy``; ``numba`` without numba is a ConfigError."""
    if backend not in BACKENDS:
        raise ConfigError.at("estimator.backend", f"must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if backend == "numpy":
        return "numpy"
    if numba_available():
        return "numba"
    if backend == "numba":
        raise ConfigError.at("estimator.backend", "backend numba needs numba: pip install 'netkf[fast]'")
    return "numpy"


def smoother_requests(
    system: LinearSystem,
    gamma: np.ndarray,
    Sigma0: np.ndarray,
    targets,
    lags: Sequence[int],
    *,
    want_pred: bool = False,
    backend: str = "numpy",
) -> tuple[np.ndarray | None, np.ndarray]:
    """Covariances of chosen targets at chosen lags, batched over runs.

    ``gamma`` ``(T, runs)`` arrivals (index t = the t-th measurement of the recursion), ``Sigma0``
    the prediction covariance of measurement 0 (``(n, n)``), ``targets`` ascending measurement
    indices j, ``lags`` ascending N ≥ 0 with j + max(lags) < T. Returns ``pred`` ``(J, n, n, runs)``
    (P_{j|j−1}, if ``want_pred``) and ``out`` ``(J, len(lags), n, n, runs)`` (P_{j|j+N}).
    Non-finite runs are ``inf``.
    """
    gamma = np.asarray(gamma)
    if gamma.ndim != 2:
        raise ValueError(f"gamma must be (T, runs), got shape {gamma.shape}")
    targets = np.asarray(targets, dtype=np.int64).ravel()
    lags = tuple(int(x) for x in lags)
    if not lags or any(x < 0 for x in lags) or any(b <= a for a, b in zip(lags[:-1], lags[1:])):
        raise ValueError(f"lags must be ascending integers ≥ 0, got {lags}")
    T = gamma.shape[0]
    if targets.size and (targets[0] < 0 or np.any(np.diff(targets) <= 0) or targets[-1] + lags[-1] >= T):
        raise ValueError(f"targets must be ascending, ≥ 0, with target + lag < T = {T}")
    be = resolve_backend(backend)
    Sigma0 = np.asarray(Sigma0, dtype=float)
    if be == "numba":
        pred, out = _requests_numba(system, gamma, Sigma0, targets, lags, want_pred)
    elif system.n == 1 and system.m == 1:
        pred, out = _requests_scalar(system, gamma, Sigma0, targets, lags, want_pred)
    else:
        pred, out = _requests_matrix(system, gamma, Sigma0, targets, lags, want_pred)
    _inf_if_bad(out)
    if pred is not None:
        _inf_if_bad(pred)
    return pred, out


def _requests_scalar(s: LinearSystem, gamma, Sigma0, targets, lags, want_pred):
    """Scalar systems, overflow-safe, 1-D arrays over runs (the numba backend performs exactly these
    floating-point operations in this order).

    Filter: P_{t|t} = r / (c² + r/Σ_t) after an arrival. Smoother blocks in information form: given
    e_j, the later prediction error is e_t = α e_j + ε with Var ε = V (α = X/D, V = Σ − X²/D: finite
    even when D and Σ overflowed), so a received y_t adds c²α²/(c²V + r) to Y = P_{j|t}⁻¹ and
    conditions ε: α ← α r/(c²V + r), V ← V r/(c²V + r); then α ← aα, V ← a²V + q (eq. 4 rewritten;
    P_{j|t} = 1/Y). A target starts with Y = 1/P_{j|j}, α = 1, V = 0.
    """
    T, runs = gamma.shape
    a, c, q, r = float(s.A[0, 0]), float(s.C[0, 0]), float(s.Q[0, 0]), float(s.R[0, 0])
    c2, a2 = c * c, a * a
    J, NL = len(targets), len(lags)
    pred = np.empty((J, 1, 1, runs)) if want_pred else None
    out = np.empty((J, NL, 1, 1, runs))
    if J == 0:
        return pred, out
    Lmax = lags[-1]
    lagpos = {N: i for i, N in enumerate(lags)}
    tpos = {int(j): i for i, j in enumerate(targets)}
    t_end = int(targets[-1]) + Lmax + 1
    Sig = np.full(runs, float(Sigma0[0, 0]))
    active: dict[int, list] = {}
    with np.errstate(all="ignore"):
        for t in range(t_end):
            g = gamma[t]
            F = np.where(g, r / (c2 + r / Sig), Sig)
            i = tpos.get(t)
            if i is not None:
                if want_pred:
                    pred[i, 0, 0] = Sig
                if 0 in lagpos:
                    out[i, lagpos[0], 0, 0] = F
            for j in list(active):
                Y, al, V = active[j]
                den = c2 * V + r
                ca = c * al
                Y = np.where(g, Y + ca * (ca / den), Y)
                al = np.where(g, al * (r / den), al)
                V = np.where(g, V * (r / den), V)
                age = t - j
                if age in lagpos:
                    out[tpos[j], lagpos[age], 0, 0] = 1.0 / Y
                if age >= Lmax:
                    del active[j]
                else:
                    active[j] = [Y, a * al, a2 * V + q]
            if i is not None and Lmax > 0:
                active[t] = [1.0 / F, np.full(runs, a), np.full(runs, q)]
            Sig = a2 * F + q
    return pred, out


BLOCK = 8192
"""Runs per block of the numpy vector path (keeps the (n, n, block) arrays in cache)."""


def _left(A: np.ndarray, P: np.ndarray) -> np.ndarray:
    """A P for a constant A (p×n) and P (n, k, runs): one BLAS product on the reshaped batch."""
    n, k, r = P.shape
    return (A @ np.ascontiguousarray(P).reshape(n, k * r)).reshape(A.shape[0], k, r)


def _right(P: np.ndarray, B: np.ndarray) -> np.ndarray:
    """P B for P (k, n, runs) and a constant B (n×p): Bᵀ P[i] for every row block i (batched matmul)."""
    return np.matmul(B.T, P)


def _mm(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Per-run product of X (a, b, runs) and Y (b, c, runs) (einsum's C loop, no path search)."""
    return np.einsum("ijr,jkr->ikr", X, Y)


def _sym(P: np.ndarray) -> np.ndarray:
    return 0.5 * (P + P.swapaxes(0, 1))


def _requests_matrix(s: LinearSystem, gamma, Sigma0, targets, lags, want_pred):
    """Vector systems: covariance form, closed-form S⁻¹ for m ≤ 2, runs in blocks of :data:`BLOCK`."""
    T, runs = gamma.shape
    n = s.n
    J, NL = len(targets), len(lags)
    pred = np.empty((J, n, n, runs)) if want_pred else None
    out = np.empty((J, NL, n, n, runs))
    for b0 in range(0, runs, BLOCK):
        b1 = min(runs, b0 + BLOCK)
        pb, ob = _requests_matrix_block(s, gamma[:, b0:b1], Sigma0, targets, lags, want_pred)
        out[..., b0:b1] = ob
        if want_pred:
            pred[..., b0:b1] = pb
    return pred, out


def _requests_matrix_block(s: LinearSystem, gamma, Sigma0, targets, lags, want_pred):
    T, runs = gamma.shape
    n, m = s.n, s.m
    A, C, Q, R = s.A, s.C, s.Q, s.R
    J, NL = len(targets), len(lags)
    pred = np.empty((J, n, n, runs)) if want_pred else None
    out = np.empty((J, NL, n, n, runs))
    if J == 0:
        return pred, out
    Lmax = lags[-1]
    lagpos = {N: i for i, N in enumerate(lags)}
    tpos = {int(j): i for i, j in enumerate(targets)}
    t_end = int(targets[-1]) + Lmax + 1
    Sigma = np.repeat(Sigma0[:, :, None], runs, axis=2)
    Rb, Qb = R[:, :, None], Q[:, :, None]
    CT = C.T
    active: dict[int, list] = {}
    with np.errstate(all="ignore"):
        for t in range(t_end):
            g = gamma[t][None, None, :]
            CS = _left(C, Sigma)  # C Σ  (m, n, runs)
            S = _right(CS, CT) + Rb
            if m <= 2:
                Sinv = bt.inv_small(S)
                solve = lambda B, Sinv=Sinv: _mm(Sinv, B)  # noqa: E731
            else:
                solve = lambda B, S=S: bt.solve_small(S, B)  # noqa: E731
            G = solve(CS)  # S⁻¹ C Σ
            F = np.where(g, _sym(Sigma - _mm(CS.swapaxes(0, 1), G)), Sigma)
            i = tpos.get(t)
            if i is not None:
                if want_pred:
                    pred[i] = Sigma
                if 0 in lagpos:
                    out[i, lagpos[0]] = F
            for j in list(active):
                D, X = active[j]
                CX = _left(C, X)
                D = np.where(g, _sym(D - _mm(CX.swapaxes(0, 1), solve(CX))), D)
                Xf = np.where(g, X - _mm(G.swapaxes(0, 1), CX), X)
                age = t - j
                if age in lagpos:
                    out[tpos[j], lagpos[age]] = D
                if age >= Lmax:
                    del active[j]
                else:
                    active[j] = [D, _left(A, Xf)]
            if i is not None and Lmax > 0:
                active[t] = [F, _left(A, F)]
            Sigma = _sym(_right(_left(A, F), A.T)) + Qb
    return pred, out


# =============================================================================================
# the historical interface (all lags at chosen times), used by tests and analyses
# =============================================================================================


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
    backend: str = "numpy",
) -> SmootherResult:
    """Run eqs (3)–(4) over arrivals ``gamma`` (``(runs, horizon)``, index 0 = the first measurement,
    whose prior is ``P0`` = P_{0|−1}, default: the system's P0, or P* for ``steady``) and record
    P_{t|t−1}, P_{t|t+N} (N = 0 … lag) at ``times`` (default: every t with t + lag < horizon)."""
    gamma = np.asarray(gamma)
    if gamma.ndim != 2:
        raise ValueError(f"gamma must be (runs, horizon), got shape {gamma.shape}")
    if lag < 0 or lag > MAX_LAG:
        raise ValueError(f"lag must be in 0..{MAX_LAG}, got {lag}")
    runs, horizon = gamma.shape
    if times is None:
        times = np.arange(0, horizon - lag)
    times = np.asarray(times, dtype=int)
    if times.size and (times.min() < 0 or times.max() + lag >= horizon):
        raise ValueError(f"times must satisfy 0 ≤ t and t + lag < horizon = {horizon}")
    if P0 is None:
        P0 = initial_prediction(system)
    pred, out = smoother_requests(system, np.ascontiguousarray(gamma.T), np.asarray(P0, float), times,
                                  tuple(range(lag + 1)), want_pred=True, backend=backend)
    return SmootherResult(times=times, pred=pred, smooth=out)


def initial_prediction(system: LinearSystem) -> np.ndarray:
    """P_{0|−1} of :func:`fixed_lag_smoother`: the system's P0, or P* for ``P0: steady``."""
    if system.P0 is not None:
        return system.P0
    from netkf_cli.riccati import pstar

    return pstar(system)


# =============================================================================================
# Monte Carlo kernels (module-level, picklable; additive statistics with fixed keys)
# =============================================================================================


def lag_key(lag: int) -> str:
    """Statistic-key fragment of a column: ``pred`` (P_{k|k−1}) or ``lagN`` (P_{k|k+N})."""
    return "pred" if lag == PRED else f"lag{int(lag)}"


def loss_arrivals(channel, rng: np.random.Generator, runs: int, horizon: int) -> np.ndarray:
    """Arrival indicators ``(horizon, runs)`` bool from a one-sensor loss channel's ``sample_trace``."""
    tr = channel.sample_trace(rng, runs, horizon)
    if tr.arrival is None or tr.arrival.shape[0] != 1:
        raise ConfigError.at("channel.kind", f"needs one sensor's arrival indicators, channel {getattr(channel, 'kind', '?')} gives none")
    return tr.arrival[0]


def covariance_stats(P: np.ndarray, M: np.ndarray | None, key: str) -> dict[str, float | int]:
    """Additive statistics of a batch ``(n, n, runs)``: count ≤ M, Σ tr, Σ tr², non-finite runs."""
    finite = np.isfinite(P).all(axis=(0, 1))
    tr = np.where(finite, bt.trace(np.where(finite[None, None, :], P, 0.0)), 0.0)
    with np.errstate(over="ignore"):  # a finite P with tr² > 1.8e308: the sum of squares is inf (heavy tail)
        out = {f"sum_tr_{key}": float(tr.sum()), f"sumsq_tr_{key}": float((tr * tr).sum()),
               f"overflow_{key}": int((~finite).sum())}
    if M is not None:
        out[f"leq_{key}"] = int(bt.psd_leq(P, M).sum())
    return out


@dataclass(frozen=True)
class SmootherMCKernel:
    """One sample per run of P_{k|k−1} (lag −1) and P_{k|k+N} (lags N ≥ 0) at step ``k``, all lags on
    the same arrival trace (common random numbers). The trace has ``k + max(lag, 0) + 1`` steps;
    the recursion starts from the prediction covariance ``Sigma0`` at step 0.

    Statistics: ``n``; per lag key (``pred``, ``lag0`` …): ``leq_*`` (count of P ≤ M in the PSD order,
    if ``M`` is given), ``sum_tr_*``, ``sumsq_tr_*`` (over finite runs), ``overflow_*`` (runs whose
    covariance overflowed: counted as not ≤ M, excluded from the sums).
    """

    system: LinearSystem
    channel: object
    k: int
    lags: tuple[int, ...]
    M: np.ndarray | None = None
    Sigma0: np.ndarray | None = None
    backend: str = "auto"

    def keys(self) -> list[str]:
        ks = ["n"]
        for lag in self.lags:
            key = lag_key(lag)
            ks += [f"sum_tr_{key}", f"sumsq_tr_{key}", f"overflow_{key}"] + ([f"leq_{key}"] if self.M is not None else [])
        return sorted(ks)

    def horizon(self) -> int:
        return self.k + max(max(self.lags), 0) + 1

    def __call__(self, rng: np.random.Generator, runs: int) -> dict:
        gamma = loss_arrivals(self.channel, rng, runs, self.horizon())
        return self.stats(gamma)

    def stats(self, gamma: np.ndarray) -> dict:
        """The statistics of one batch of arrivals ``(horizon, runs)`` (what ``__call__`` returns)."""
        runs = gamma.shape[1]
        Sigma0 = initial_prediction(self.system) if self.Sigma0 is None else self.Sigma0
        smooth_lags = tuple(sorted({int(l) for l in self.lags if l >= 0})) or (0,)
        pred, out = smoother_requests(self.system, gamma, Sigma0, [self.k], smooth_lags,
                                      want_pred=PRED in self.lags, backend=self.backend)
        stats: dict = {"n": runs}
        for lag in self.lags:
            P = pred[0] if lag == PRED else out[0, smooth_lags.index(int(lag))]
            stats.update(covariance_stats(P, self.M, lag_key(lag)))
        return stats


@dataclass(frozen=True)
class RetransmissionKernel:
    """Sec. V of Leong 2008: P_{k|k} without retransmission, with each retransmission scheme (p), and
    P_{k|k+N} of the lag-N smoother, one sample per run at step ``k`` over an i.i.d. Bernoulli(λ)
    channel. The filter and the smoother share one arrival trace; each retransmission scheme draws
    its own (independent samples, as a two-sample test needs).

    Statistics (additive): ``n``; per scheme key: ``cdf_<key>`` counts of x ≤ ``grid`` (x = P, or
    tr P for n > 1), ``leq_<key>`` (P ≤ M), ``overflow_<key>``; per retransmission scheme also
    ``ones_<key>``, ``pairs_<key>``, ``slots_<key>`` (γ̃ over steps 10 … k−1) for its effective rate.
    """

    system: LinearSystem
    lam: float
    N: int
    ps: tuple[float, ...]
    k: int
    M: float
    grid: np.ndarray
    backend: str = "auto"

    def schemes(self) -> list[str]:
        return ["filter"] + [f"retx_p{p:g}" for p in self.ps] + [f"smoother_lag{self.N}"]

    def horizon(self) -> int:
        return self.k + 2 * self.N + 2

    def _x(self, P: np.ndarray) -> np.ndarray:
        x = P[0, 0] if P.shape[0] == 1 else bt.trace(P)
        return np.where(np.isfinite(x), x, np.inf)

    def _add(self, stats: dict, key: str, P: np.ndarray) -> None:
        x = self._x(P)
        stats[f"cdf_{key}"] = (x[None, :] <= self.grid[:, None]).sum(axis=1).astype(np.int64)
        stats[f"leq_{key}"] = int(bt.psd_leq(P, self.M).sum())
        stats[f"overflow_{key}"] = int((~np.isfinite(x)).sum())

    def __call__(self, rng: np.random.Generator, runs: int) -> dict:
        from netkf_cli.analysis.smoothing import simulate_retransmission

        H, k = self.horizon(), self.k
        Sigma0 = initial_prediction(self.system)
        stats: dict = {"n": runs}
        g = rng.random((H, runs)) < self.lam
        _, out = smoother_requests(self.system, g, Sigma0, [k], (0, self.N), backend=self.backend)
        self._add(stats, "filter", out[0, 0])
        self._add(stats, f"smoother_lag{self.N}", out[0, 1])
        for p in self.ps:
            key = f"retx_p{p:g}"
            gt = simulate_retransmission(rng, runs, H, self.lam, self.N, p)  # (runs, H)
            _, o2 = smoother_requests(self.system, np.ascontiguousarray(gt.T), Sigma0, [k], (0,), backend=self.backend)
            self._add(stats, key, o2[0, 0])
            win = gt[:, 10:k]
            stats[f"ones_{key}"] = int(win.sum())
            stats[f"pairs_{key}"] = int((win[:, :-1] & win[:, 1:]).sum())
            stats[f"slots_{key}"] = int(win.size)
        return stats


def paper_way_indicators(system: LinearSystem, gamma: np.ndarray, lags: Sequence[int], M: np.ndarray, burn: int,
                         backend: str = "auto") -> np.ndarray:
    """Table I "the paper's way": one long run per column (``gamma`` ``(steps, columns)``, column c at
    its own rate), the indicator 1{P_{t|t+N_c} ≤ M} (N_c = ``lags[c]``, −1 = P_{t|t−1}) at every t in
    burn … steps − max lag − 1. Returns ``(times, columns)`` bool. Uses the compiled backend when
    available: a Python loop over 10⁵ steps is what made this slow.
    """
    steps, cols = gamma.shape
    Lmax = max(max(lags), 0)
    targets = np.arange(burn, steps - Lmax)
    smooth_lags = tuple(sorted({int(l) for l in lags if l >= 0})) or (0,)
    pred, out = smoother_requests(system, gamma, initial_prediction(system), targets, smooth_lags,
                                  want_pred=PRED in lags, backend=backend)
    ind = np.empty((len(targets), cols), dtype=bool)
    for c, lag in enumerate(lags):
        P = pred[:, :, :, c] if lag == PRED else out[:, smooth_lags.index(int(lag)), :, :, c]  # (J, n, n)
        ind[:, c] = bt.psd_leq(np.moveaxis(P, 0, -1), M)
    return ind


# =============================================================================================
# compiled backend (numba): plain-Python loops, jitted lazily (numba is imported only when used)
# =============================================================================================


NB_BLOCK = 256
"""Runs per block of the compiled backend: the time loop is outer, the run loop inner (SIMD)."""


def _nb_scalar_impl(a, c, q, r, sig0, gamma, tslot, lagslot, Lmax, want_pred, t_end, pred, out):
    """Per run, exactly the floating-point operations of :func:`_requests_scalar` in the same order
    (blocks of 256 runs, time outer, runs inner)."""
    runs = gamma.shape[1]
    c2 = c * c
    a2 = a * a
    W = Lmax + 1
    B = 256
    sig = np.empty(B)
    F = np.empty(B)
    Y = np.empty((W, B))
    AL = np.empty((W, B))
    V = np.empty((W, B))
    tj = np.empty(W, np.int64)
    l0 = lagslot[0]
    for b0 in range(0, runs, B):
        nb = min(B, runs - b0)
        for w in range(W):
            tj[w] = -1
        for rr in range(nb):
            sig[rr] = sig0
        for t in range(t_end):
            gt = gamma[t, b0:b0 + nb]
            for rr in range(nb):
                s_ = sig[rr]
                F[rr] = r / (c2 + r / s_) if gt[rr] else s_
            i = tslot[t]
            if i >= 0:
                for rr in range(nb):
                    if want_pred:
                        pred[i, 0, 0, b0 + rr] = sig[rr]
                    if l0 >= 0:
                        out[i, l0, 0, 0, b0 + rr] = F[rr]
            for w in range(W):
                j = tj[w]
                if j < 0:
                    continue
                age = t - j
                ls = lagslot[age]
                for rr in range(nb):
                    y = Y[w, rr]
                    al = AL[w, rr]
                    v = V[w, rr]
                    if gt[rr]:
                        den = c2 * v + r
                        ca = c * al
                        y = y + ca * (ca / den)
                        al = al * (r / den)
                        v = v * (r / den)
                    Y[w, rr] = y
                    AL[w, rr] = a * al
                    V[w, rr] = a2 * v + q
                    if ls >= 0:
                        out[tslot[j], ls, 0, 0, b0 + rr] = 1.0 / y
                if age >= Lmax:
                    tj[w] = -1
            if i >= 0 and Lmax > 0:
                w = t % W
                tj[w] = t
                for rr in range(nb):
                    Y[w, rr] = 1.0 / F[rr]
                    AL[w, rr] = a
                    V[w, rr] = q
            for rr in range(nb):
                sig[rr] = a2 * F[rr] + q


def _nb_gauss_jordan(S, Si, m):
    """Si = S⁻¹ by Gauss–Jordan elimination with partial pivoting (m > 2)."""
    Wk = np.empty((m, 2 * m))
    for i in range(m):
        for k in range(m):
            Wk[i, k] = S[i, k]
            Wk[i, m + k] = 1.0 if i == k else 0.0
    for col in range(m):
        piv = col
        for i in range(col + 1, m):
            if abs(Wk[i, col]) > abs(Wk[piv, col]):
                piv = i
        if piv != col:
            for k in range(2 * m):
                tmp = Wk[col, k]
                Wk[col, k] = Wk[piv, k]
                Wk[piv, k] = tmp
        p = Wk[col, col]
        for k in range(2 * m):
            Wk[col, k] = Wk[col, k] / p
        for i in range(m):
            if i != col:
                f = Wk[i, col]
                for k in range(2 * m):
                    Wk[i, k] = Wk[i, k] - f * Wk[col, k]
    for i in range(m):
        for k in range(m):
            Si[i, k] = Wk[i, m + k]


_gauss_jordan = _nb_gauss_jordan  # replaced by its compiled version before the matrix core is compiled


def _nb_matrix_impl(A, C, Q, R, Sig0, gamma, tslot, lagslot, Lmax, want_pred, t_end, pred, out):
    """The recursion of :func:`_requests_matrix` (same formulas; small products summed in index order),
    in blocks of 256 runs with the run loop innermost. Products with a structural zero of A or C are
    skipped (exactly the same finite values; an overflowed entry times a zero coefficient gives 0
    here, NaN → ``inf`` in numpy)."""
    n = A.shape[0]
    m = C.shape[0]
    runs = gamma.shape[1]
    W = Lmax + 1
    B = 256
    Sig = np.empty((n, n, B))
    F = np.empty((n, n, B))
    tmp = np.empty((n, n, B))
    tmp2 = np.empty((n, n, B))
    CS = np.empty((m, n, B))
    S = np.empty((m, m, B))
    Si = np.empty((m, m, B))
    G = np.empty((m, n, B))
    CX = np.empty((m, n, B))
    H = np.empty((m, n, B))
    D = np.empty((W, n, n, B))
    X = np.empty((W, n, n, B))
    acc = np.empty(B)
    tj = np.empty(W, np.int64)
    l0 = lagslot[0]
    for b0 in range(0, runs, B):
        nb = min(B, runs - b0)
        for w in range(W):
            tj[w] = -1
        for i in range(n):
            for k in range(n):
                for rr in range(nb):
                    Sig[i, k, rr] = Sig0[i, k]
        for t in range(t_end):
            gt = gamma[t, b0:b0 + nb]
            # CS = C Σ, S = CS Cᵀ + R, Si = S⁻¹, G = Si CS
            for i in range(m):
                for k in range(n):
                    for rr in range(nb):
                        acc[rr] = 0.0
                    for l in range(n):
                        cil = C[i, l]
                        if cil == 0.0:  # structural zeros of A, C (the vehicle's A has 10 of 16)
                            continue
                        for rr in range(nb):
                            acc[rr] += cil * Sig[l, k, rr]
                    for rr in range(nb):
                        CS[i, k, rr] = acc[rr]
            for i in range(m):
                for k in range(m):
                    for rr in range(nb):
                        acc[rr] = 0.0
                    for l in range(n):
                        ckl = C[k, l]
                        if ckl == 0.0:  # structural zeros of A, C (the vehicle's A has 10 of 16)
                            continue
                        for rr in range(nb):
                            acc[rr] += CS[i, l, rr] * ckl
                    for rr in range(nb):
                        S[i, k, rr] = acc[rr] + R[i, k]
            if m == 1:
                for rr in range(nb):
                    Si[0, 0, rr] = 1.0 / S[0, 0, rr]
            elif m == 2:
                for rr in range(nb):
                    det = S[0, 0, rr] * S[1, 1, rr] - S[0, 1, rr] * S[1, 0, rr]
                    Si[0, 0, rr] = S[1, 1, rr] / det
                    Si[0, 1, rr] = -S[0, 1, rr] / det
                    Si[1, 0, rr] = -S[1, 0, rr] / det
                    Si[1, 1, rr] = S[0, 0, rr] / det
            else:
                for rr in range(nb):
                    _gauss_jordan(S[:, :, rr], Si[:, :, rr], m)
            for i in range(m):
                for k in range(n):
                    for rr in range(nb):
                        acc[rr] = 0.0
                    for l in range(m):
                        for rr in range(nb):
                            acc[rr] += Si[i, l, rr] * CS[l, k, rr]
                    for rr in range(nb):
                        G[i, k, rr] = acc[rr]
            # F = sym(Σ − CSᵀ G) where γ, else Σ
            for i in range(n):
                for k in range(n):
                    for rr in range(nb):
                        acc[rr] = 0.0
                    for l in range(m):
                        for rr in range(nb):
                            acc[rr] += CS[l, i, rr] * G[l, k, rr]
                    for rr in range(nb):
                        tmp[i, k, rr] = Sig[i, k, rr] - acc[rr]
            for i in range(n):
                for k in range(n):
                    for rr in range(nb):
                        F[i, k, rr] = 0.5 * (tmp[i, k, rr] + tmp[k, i, rr]) if gt[rr] else Sig[i, k, rr]
            ti = tslot[t]
            if ti >= 0:
                for i in range(n):
                    for k in range(n):
                        for rr in range(nb):
                            if want_pred:
                                pred[ti, i, k, b0 + rr] = Sig[i, k, rr]
                            if l0 >= 0:
                                out[ti, l0, i, k, b0 + rr] = F[i, k, rr]
            for w in range(W):
                j = tj[w]
                if j < 0:
                    continue
                # CX = C X, H = Si CX
                for i in range(m):
                    for k in range(n):
                        for rr in range(nb):
                            acc[rr] = 0.0
                        for l in range(n):
                            cil = C[i, l]
                            if cil == 0.0:  # structural zeros of A, C (the vehicle's A has 10 of 16)
                                continue
                            for rr in range(nb):
                                acc[rr] += cil * X[w, l, k, rr]
                        for rr in range(nb):
                            CX[i, k, rr] = acc[rr]
                for i in range(m):
                    for k in range(n):
                        for rr in range(nb):
                            acc[rr] = 0.0
                        for l in range(m):
                            for rr in range(nb):
                                acc[rr] += Si[i, l, rr] * CX[l, k, rr]
                        for rr in range(nb):
                            H[i, k, rr] = acc[rr]
                # D ← sym(D − CXᵀ H) where γ
                for i in range(n):
                    for k in range(n):
                        for rr in range(nb):
                            acc[rr] = 0.0
                        for l in range(m):
                            for rr in range(nb):
                                acc[rr] += CX[l, i, rr] * H[l, k, rr]
                        for rr in range(nb):
                            tmp[i, k, rr] = D[w, i, k, rr] - acc[rr]
                for i in range(n):
                    for k in range(n):
                        for rr in range(nb):
                            tmp2[i, k, rr] = 0.5 * (tmp[i, k, rr] + tmp[k, i, rr]) if gt[rr] else D[w, i, k, rr]
                for i in range(n):
                    for k in range(n):
                        for rr in range(nb):
                            D[w, i, k, rr] = tmp2[i, k, rr]
                # Xf = X − Gᵀ CX where γ;  X ← A Xf
                for i in range(n):
                    for k in range(n):
                        for rr in range(nb):
                            acc[rr] = 0.0
                        for l in range(m):
                            for rr in range(nb):
                                acc[rr] += G[l, i, rr] * CX[l, k, rr]
                        for rr in range(nb):
                            tmp[i, k, rr] = X[w, i, k, rr] - acc[rr] if gt[rr] else X[w, i, k, rr]
                for i in range(n):
                    for k in range(n):
                        for rr in range(nb):
                            acc[rr] = 0.0
                        for l in range(n):
                            ail = A[i, l]
                            if ail == 0.0:  # structural zeros of A, C (the vehicle's A has 10 of 16)
                                continue
                            for rr in range(nb):
                                acc[rr] += ail * tmp[l, k, rr]
                        for rr in range(nb):
                            X[w, i, k, rr] = acc[rr]
                age = t - j
                ls = lagslot[age]
                if ls >= 0:
                    for i in range(n):
                        for k in range(n):
                            for rr in range(nb):
                                out[tslot[j], ls, i, k, b0 + rr] = D[w, i, k, rr]
                if age >= Lmax:
                    tj[w] = -1
            if ti >= 0 and Lmax > 0:
                w = t % W
                tj[w] = t
                for i in range(n):
                    for k in range(n):
                        for rr in range(nb):
                            acc[rr] = 0.0
                        for l in range(n):
                            ail = A[i, l]
                            if ail == 0.0:  # structural zeros of A, C (the vehicle's A has 10 of 16)
                                continue
                            for rr in range(nb):
                                acc[rr] += ail * F[l, k, rr]
                        for rr in range(nb):
                            D[w, i, k, rr] = F[i, k, rr]
                            X[w, i, k, rr] = acc[rr]
            # Σ ← sym(A F Aᵀ) + Q
            for i in range(n):
                for k in range(n):
                    for rr in range(nb):
                        acc[rr] = 0.0
                    for l in range(n):
                        ail = A[i, l]
                        if ail == 0.0:  # structural zeros of A, C (the vehicle's A has 10 of 16)
                            continue
                        for rr in range(nb):
                            acc[rr] += ail * F[l, k, rr]
                    for rr in range(nb):
                        tmp[i, k, rr] = acc[rr]
            for i in range(n):
                for k in range(n):
                    for rr in range(nb):
                        acc[rr] = 0.0
                    for l in range(n):
                        akl = A[k, l]
                        if akl == 0.0:  # structural zeros of A, C (the vehicle's A has 10 of 16)
                            continue
                        for rr in range(nb):
                            acc[rr] += tmp[i, l, rr] * akl
                    for rr in range(nb):
                        tmp2[i, k, rr] = acc[rr]
            for i in range(n):
                for k in range(n):
                    for rr in range(nb):
                        Sig[i, k, rr] = 0.5 * (tmp2[i, k, rr] + tmp2[k, i, rr]) + Q[i, k]


_JIT: dict[str, object] = {}


def _jitted(name: str):
    """The compiled version of ``_nb_<name>_impl`` (compiled once per process, cached on disk)."""
    f = _JIT.get(name)
    if f is None:
        import numba

        opts = dict(cache=True, error_model="numpy", nogil=True)
        if name == "matrix":
            globals()["_gauss_jordan"] = numba.njit(**opts)(_nb_gauss_jordan)  # resolved when the core compiles
            f = numba.njit(**opts)(_nb_matrix_impl)
        else:
            f = numba.njit(**opts)(_nb_scalar_impl)
        _JIT[name] = f
    return f


def _requests_numba(s: LinearSystem, gamma, Sigma0, targets, lags, want_pred):
    """The compiled backend of :func:`smoother_requests` (same arrays in, same arrays out)."""
    T, runs = gamma.shape
    n = s.n
    J, NL = len(targets), len(lags)
    pred = np.empty((J, n, n, runs)) if want_pred else np.empty((0, n, n, runs))
    out = np.empty((J, NL, n, n, runs))
    if J == 0:
        return (pred if want_pred else None), out
    Lmax = lags[-1]
    t_end = int(targets[-1]) + Lmax + 1
    tslot = np.full(t_end, -1, dtype=np.int64)
    tslot[targets] = np.arange(J)
    lagslot = np.full(Lmax + 1, -1, dtype=np.int64)
    lagslot[list(lags)] = np.arange(NL)
    g = np.ascontiguousarray(gamma[:t_end], dtype=np.bool_)
    if n == 1 and s.m == 1:
        _jitted("scalar")(float(s.A[0, 0]), float(s.C[0, 0]), float(s.Q[0, 0]), float(s.R[0, 0]), float(Sigma0[0, 0]),
                          g, tslot, lagslot, Lmax, bool(want_pred), t_end, pred, out)
    else:
        _jitted("matrix")(np.ascontiguousarray(s.A), np.ascontiguousarray(s.C), np.ascontiguousarray(s.Q), np.ascontiguousarray(s.R),
          np.ascontiguousarray(Sigma0, dtype=float), g, tslot, lagslot, Lmax, bool(want_pred), t_end, pred, out)
    return (pred if want_pred else None), out
