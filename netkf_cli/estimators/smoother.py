"""Kalman fixed-lag smoother with random packet loss (Leong, Dey & Evans 2008, Sec. II), on the Kalman core.

Forward pass: :class:`netkf_cli.kalman.Filter` (the Kalman filter with intermittent observations,
every step through the one rescue policy :class:`netkf_cli.kalman.Rescue`), so ``filtered`` and
``predicted`` are exactly those of ``kind: kf``. Backward pass: N Rauch–Tung–Striebel steps from
P_{k|k} back to the target time k − N, t = k−1 … k−N:

    P_{t|k} = P_{t|t} + J_t (P_{t+1|k} − P_{t+1|t}) J_tᵀ,   J_t = P_{t|t} Aᵀ P_{t+1|t}⁻¹
            = P_{t|t, x_{t+1}} + J_t P_{t+1|k} J_tᵀ          (:class:`netkf_cli.kalman.SmoothStep`)

with P_{t|t, x_{t+1}} = P_{t|t} − J_t A P_{t|t} the core's ``update`` of P_{t|t} by x_{t+1} = A x_t + w_t
(C = A, R = Q; its gain is J_t), through the rescue ``Rescue.of(A, Q)``: the first form subtracts
two numbers of the size of P_{t|t} and loses every digit after a loss burst at A = 10⁶; the second
does not (a test). The RTS recursion holds for any time-varying measurement model, so with the
arrivals γ_t it is the covariance of x_{k−N} given the received y_1 … y_k — the same P_{k−N|k} as the
paper's augmented-state recursion (eqs 3–4; Anderson & Moore), checked against brute-force
Gaussian conditioning. We use RTS rather than the augmented state because it reuses the forward
pass unchanged (so filtered/predicted are kf's by construction) and costs N small steps per step.

Time base (every estimator): P0 = P_{0|0} (``system.P0``; unset = P̄); step k = 1 … horizon carries
y_k (trace step t = k − 1). Quantities at step k: ``filtered`` P_{k|k}, ``predicted`` P_{k+1|k},
``smoothed`` P_{k−N|k} (defined from k = N: P_{0|N} smooths back to P0). Lag 0: smoothed is the
filtered array itself. Overflow: a run whose forward pass is non-finite (inf by the rescue policy)
is inf in every quantity, never NaN.

Sensors: a channel with one arrival stream carries all of y_k; S streams carry the S sensors of
``system.sensors`` (:func:`netkf_cli.kalman.stream_rows`).

Backends: ``numpy`` (the reference: the forward pass :meth:`kalman.Filter.run` on the numpy core,
the backward pass batched RTS) and ``numba`` (one compiled kernel per run built from
:mod:`netkf_cli.kalman_numba`'s inlined primitives — predict, update, the rescue's information
update, gain, the RTS step ``smooth``; one arrival stream or one sensor; equal to rounding, a
test). ``auto``: the forward pass is kf's own call (``Filter.run`` with the backend kf chooses,
:func:`kalman.choose_backend`: the generated compiled kernel for large batches), so filtered /
predicted / lag-0 smoothed are kf's numbers by construction; the per-run compiled kernel only where
it is measured faster (lag ≥ 1, batches of at most :data:`AUTO_NUMBA_MAX_RUNS` runs: long runs of
few columns, the paper's-way run of Table I).

Monte Carlo: the generic engine (:func:`netkf_cli.engine.simulate` on :meth:`SmootherEstimator.covariances`;
the retransmission schemes of Sec. V are a channel, ``kind: retransmission``).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from netkf_cli import kalman
from netkf_cli.errors import ConfigError
from netkf_cli.estimators.kf import channel_streams, filter_estimates
from netkf_cli.riccati import initial_covariance
from netkf_cli.spec import EstimatorModel, NonNegInt
from netkf_cli.system import LinearSystem

MAX_LAG = 64
"""Largest smoothing lag accepted (the work per step grows linearly with the lag)."""

BACKENDS = ("auto", "numpy", "numba")
AUTO_NUMBA_MAX_RUNS = 256
"""``backend: auto`` runs the per-run compiled kernel only for batches of at most this many runs
(measured, experiments/smoothing/README "Speed": it does 1–4e6 run-steps/s for n ≤ 2; the batched
path overtakes it at a few hundred runs). Long runs of few columns — the paper's-way run of
Table I — are where it wins (10–100× a numpy loop over the steps)."""


# =============================================================================================
# the estimator
# =============================================================================================


class SmootherEstimator(EstimatorModel):
    """``kind: smoother`` — fixed-lag Kalman smoother under packet loss (Leong 2008), on the Kalman core.

    ``covariances`` yields ``filtered`` P_{k|k}, ``predicted`` P_{k+1|k} (both exactly kf's) and
    ``smoothed`` P_{k−N|k} (N = ``lag``; N = 0 is the filter).
    """

    accepts: ClassVar[frozenset[str]] = frozenset({"arrival"})
    quantities: ClassVar[tuple[str, ...]] = ("filtered", "predicted", "smoothed")

    kind: Literal["smoother"]
    lag: NonNegInt = Field(1, le=MAX_LAG, description=f"smoothing lag N: smoothed = P_{{k−N|k}}, the estimate of x_{{k−N}} "
                           f"from y_1 … y_k (0 = the filter P_{{k|k}}; at most {MAX_LAG})")
    backend: Literal["auto", "numpy", "numba"] = Field(
        "auto", description="covariance recursion: numpy (reference, batched over runs), numba (a per-run kernel on "
        "the core's compiled primitives, equal to rounding; one arrival stream or one sensor), auto = the forward pass "
        f"exactly as kf runs it (its compiled kernel for large batches) and the per-run kernel only for lag ≥ 1 and at "
        f"most {AUTO_NUMBA_MAX_RUNS} runs (where it is measured faster)")

    @property
    def label(self) -> str:
        """The smoothed quantity for this lag, e.g. ``P_{k-2|k}``."""
        return "P_{k|k}" if self.lag == 0 else f"P_{{k-{self.lag}|k}}"

    def first_step(self, quantity: str) -> int:
        return int(self.lag) if quantity == "smoothed" else 1

    def conventions(self, system, channel) -> dict[str, str]:
        return {"lag": f"N = {self.lag} (smoothed = P_{{k-{self.lag}|k}}; filtered, predicted = kf's)"}

    def check(self, system, channel) -> None:
        kinds = getattr(channel, "trace_kinds", frozenset())
        if channel is not None and kinds and not (kinds & self.accepts):
            raise ConfigError.at("estimator.kind", f"the smoother needs a channel with arrival indicators "
                                 f"(bernoulli, gilbert_elliott, …); channel {getattr(channel, 'kind', '?')} gives {sorted(kinds)}")
        S = channel_streams(channel)
        if S is not None and system is not None:
            kalman.stream_rows(system, S, "estimator.kind")

    def covariances(self, system: LinearSystem, trace, steps, quantities=("filtered",)) -> Iterator[tuple[int, dict]]:
        """Yield ``(k, {quantity: P})`` for k in ``steps`` (ascending, 1 ≤ k ≤ horizon), P ``(n, n, runs)``.

        ``smoothed`` at k < N (before its first step) is NaN (undefined); overflow is ``inf``.
        """
        qs = kalman.check_quantities(quantities, self.quantities, "smoother")
        if trace.arrival is None:
            raise ConfigError.at("estimator.kind", "the smoother needs a trace with arrival indicators")
        yield from run(system, trace.arrival, steps, qs, int(self.lag), backend=self.backend)

    def estimates(self, system: LinearSystem, trace, y, steps, quantities=("filtered",)):
        """Yield (k, {quantity: (x̂, P)}) (numpy path): the filter's x̂_{t|t}, P_{t|t} (``kf.filter_estimates``,
        exactly kf) and, for ``smoothed``, N Rauch–Tung–Striebel steps back from k on the core — the gain
        J = ``kalman.gain``(P_{t|t}, A, Q) of :class:`kalman.SmoothStep` (the update of P_{t|t} by x_{t+1}),
        x̂_{t|k} = x̂_{t|t} + J (x̂_{t+1|k} − A x̂_{t|t}), P_{t|k} = ``SmoothStep``. x̂_{0|0} = 0."""
        qs = kalman.check_quantities(quantities, self.quantities, "smoother")
        want = sorted({int(k) for k in steps})
        if not want:
            return
        f = kalman.Filter.of(system, trace.arrival.shape[0], "estimator.kind")
        N = int(self.lag) if "smoothed" in qs else 0
        back = kalman.SmoothStep.of(f.A, f.Q)
        P0 = initial_covariance(system)
        runs, n = trace.runs, f.A.shape[0]
        hist = {0: (np.zeros((n, runs)), np.repeat(P0[:, :, None], runs, axis=2))}
        wset = set(want)
        fq = tuple(q for q in qs if q != "smoothed")
        for k, out in filter_estimates(f, P0, trace.arrival, y, range(1, want[-1] + 1), ("filtered",)):
            hist[k] = out["filtered"]
            for old in [u for u in hist if u < k - N]:
                del hist[old]
            if k not in wset:
                continue
            x, P = hist[k]
            res = {q: ((x, P) if q == "filtered" else (f.A @ x, kalman.predict(P, f.A, f.Q))) for q in fq}
            if "smoothed" in qs:
                if k < N:
                    res["smoothed"] = (np.full((n, runs), np.nan), np.full((n, n, runs), np.nan))
                else:
                    xs, Ps = x, P
                    for t in range(k - 1, k - N - 1, -1):
                        xf, Pf = hist[t]
                        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
                            J = kalman.gain(Pf, f.A, f.Q)
                            xs = xf + np.einsum("nmr,mr->nr", J, xs - f.A @ xf)
                        Ps = back(Ps, Pf)
                    res["smoothed"] = (xs, Ps)
            yield k, {q: res[q] for q in qs}


# =============================================================================================
# the recursion (forward Filter + backward RTS), numpy and compiled
# =============================================================================================


def numba_available() -> bool:
    try:
        import numba  # noqa: F401  (optional: probed only, never required)
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


def _check_steps(steps, horizon: int) -> list[int]:
    steps = [int(k) for k in steps]
    if any(b <= a for a, b in zip(steps[:-1], steps[1:])) or (steps and (steps[0] < 0 or steps[-1] > horizon)):
        raise ValueError(f"steps must be ascending integers in 1..{horizon}")
    return steps


def run(system: LinearSystem, gamma: np.ndarray, steps, quantities=("smoothed",), lag: int = 0, *,
        backend: str = "numpy", prior: np.ndarray | None = None) -> Iterator[tuple[int, dict]]:
    """The smoother's recursion: yield ``(k, {quantity: P})`` for k in ``steps``.

    ``gamma`` ``(S, horizon, runs)`` stream arrivals (trace step t carries y_{t+1}). P0 = P_{0|0} =
    :func:`initial_covariance`; ``prior`` (n, n) instead gives P_{1|0} directly (the historical
    interface :func:`fixed_lag_smoother`; then nothing smooths back to time 0: steps k ≥ N + 1).
    """
    qs = kalman.check_quantities(quantities, ("filtered", "predicted", "smoothed"), "smoother")
    gamma = np.asarray(gamma)
    if gamma.ndim != 3:
        raise ValueError(f"gamma must be (streams, horizon, runs), got shape {gamma.shape}")
    f = kalman.Filter.of(system, gamma.shape[0], "estimator.kind")
    horizon = gamma.shape[1]
    steps = _check_steps(steps, horizon)
    if not steps:
        return
    N = int(lag) if "smoothed" in qs else 0
    be = resolve_backend(backend)
    runs = gamma.shape[-1]
    if be == "numba" and len(f.groups) == 1 and (backend == "numba" or (N > 0 and runs <= AUTO_NUMBA_MAX_RUNS)):
        yield from _run_numba(f, system, gamma, steps, qs, N, prior)  # the per-run compiled kernel
    elif prior is not None:
        yield from _run_numpy(f, system, gamma, steps, qs, N, prior)
    else:
        # the forward pass is kf's own call (Filter.run, the backend kf would choose: its generated
        # compiled kernel for large batches), the backward pass the batched numpy RTS
        fwd = kalman.choose_backend("auto" if backend == "auto" else "numpy", f, runs * horizon)
        yield from _run_core(f, system, gamma, steps, qs, N, fwd)


def _run_core(f: kalman.Filter, system, gamma, steps, qs, N, fwd: str):
    """Forward: :meth:`kalman.Filter.run` (exactly kf's numbers) at the steps the backward pass needs;
    backward: N :class:`kalman.SmoothStep` steps per requested step."""
    runs = gamma.shape[-1]
    n = f.A.shape[0]
    back = kalman.SmoothStep.of(f.A, f.Q)
    smooth = "smoothed" in qs and N > 0
    need = set(steps)
    if smooth:
        for k in steps:
            if k >= N:
                need.update(range(k - N, k + 1))
    P0 = initial_covariance(system)
    store = {0: np.repeat(P0[:, :, None], runs, axis=2)}
    pos = sorted(k for k in need if k >= 1)
    forward = f.run(P0, gamma, pos, ("filtered",), backend=fwd) if pos else iter(())
    last = 0
    for k in steps:
        while last < k:
            last, d = next(forward)
            store[last] = d["filtered"]
        P = store[k]
        out = kalman.report(P, tuple(q for q in qs if q != "smoothed"), f.A, f.Q)
        if "smoothed" in qs:
            if N == 0:
                out["smoothed"] = P
            elif k < N:
                out["smoothed"] = np.full((n, n, runs), np.nan)
            else:
                Ps = P
                for t in range(k - 1, k - N - 1, -1):
                    Ps = back(Ps, store[t])
                out["smoothed"] = Ps
        for old in [u for u in store if u < k + 1 - N]:
            del store[old]
        yield k, {q: out[q] for q in qs}


def _P0(system, runs: int, prior) -> tuple[np.ndarray | None, np.ndarray | None]:
    if prior is not None:
        return None, np.repeat(np.asarray(prior, dtype=float)[:, :, None], runs, axis=2)
    return np.repeat(initial_covariance(system)[:, :, None], runs, axis=2), None


def _smoothed(back: kalman.SmoothStep, Pf: dict, k: int, N: int) -> np.ndarray:
    """P_{k−N|k} from the stored P_{t|t} (``Pf[t]``), t = k−N … k."""
    Ps = Pf[k]
    for t in range(k - 1, k - N - 1, -1):
        Ps = back(Ps, Pf[t])
    return Ps


def _run_numpy(f: kalman.Filter, system, gamma, steps, qs, N, prior):
    runs = gamma.shape[-1]
    n = f.A.shape[0]
    P, Pm1 = _P0(system, runs, prior)
    back = kalman.SmoothStep.of(f.A, f.Q)
    Pf: dict[int, np.ndarray] = {}
    if P is not None:
        Pf[0] = P
    keep = N > 0 and "smoothed" in qs
    t = 0
    for k in steps:
        while t < k:
            with np.errstate(over="ignore", invalid="ignore"):
                Pm = Pm1 if (t == 0 and Pm1 is not None) else kalman.predict(P, f.A, f.Q)
                P = f.correct(Pm, gamma[:, t])
            if keep:
                Pf[t + 1] = P
                for old in [u for u in Pf if u < t + 1 - N]:
                    del Pf[old]
            t += 1
        out = kalman.report(P, tuple(q for q in qs if q != "smoothed"), f.A, f.Q)
        if "smoothed" in qs:
            if N == 0:
                out["smoothed"] = P if k > 0 else Pf[0]
            elif k - N < (0 if Pm1 is None else 1):
                out["smoothed"] = np.full((n, n, runs), np.nan)
            else:
                Pf[k] = P
                out["smoothed"] = _smoothed(back, Pf, k, N)
        yield k, {q: out[q] for q in qs}


def _inf_if_bad(P: np.ndarray) -> np.ndarray:
    """In place on ``(…, n, n, runs)``: a matrix with any non-finite entry becomes all-``inf``
    (overflow, never NaN)."""
    bad = ~np.isfinite(P).all(axis=(-3, -2))
    if bad.any():
        P[np.broadcast_to(bad[..., None, None, :], P.shape)] = np.inf
    return P


kn = None
"""netkf_cli.kalman_numba, bound when the kernel is first compiled (numba is optional)."""

_JIT: dict[str, object] = {}


def _nb_kernel(A, C, Q, R, info, limit, info_s, limit_s, P0, Pm1, use_prior, gamma, slot, N, wf, wp, ws, outF, outP, outS,
               flag):
    """Per run (outer loop), per step: predict, update, the rescue (as :class:`kalman.Rescue` for one
    sensor group), the output slots, and N :func:`kalman_numba.smooth` steps back over the ring buffer
    of P_{t|t} — all kalman_numba primitives, inlined."""
    n = A.shape[0]
    m = C.shape[0]
    T = slot.shape[0] - 1
    runs = gamma.shape[0]
    W = N + 1
    Pf = np.empty((W, n, n))
    Pm = np.empty((n, n))
    Pn = np.empty((n, n))
    Ps = np.empty((n, n))
    Ps2 = np.empty((n, n))
    tmp = np.empty((n, n))
    w1 = np.empty((n, n))
    w2 = np.empty((n, n))
    w3 = np.empty((n, n))
    w4 = np.empty((n, n))
    w5 = np.empty((n, n))
    w6 = np.empty((n, n))
    PCt = np.empty((n, m))
    S = np.empty((m, m))
    X = np.empty((m, n))
    t0 = 1 if use_prior else 0
    for r in range(runs):
        for i in range(n):
            for j in range(n):
                Pf[0, i, j] = P0[i, j]
        for t in range(1, T + 1):
            if t == 1 and use_prior:
                for i in range(n):
                    for j in range(n):
                        Pm[i, j] = Pm1[i, j]
            else:
                kn.predict(Pf[(t - 1) % W], A, Q, Pm, tmp)
            g = 1.0 if gamma[r, t - 1] else 0.0
            if _correct(Pm, C, R, g, info, limit, Pn, PCt, S, X, w1, w2):
                flag[r] = True  # non-finite: this run is redone on the numpy core (the rescue policy's)
                break
            for i in range(n):
                for j in range(n):
                    Pf[t % W, i, j] = Pn[i, j]
            s_ = slot[t]
            if s_ < 0:
                continue
            if wf:
                for i in range(n):
                    for j in range(n):
                        outF[r, s_, i, j] = Pn[i, j]
            if wp:
                kn.predict(Pn, A, Q, Ps, tmp)
                for i in range(n):
                    for j in range(n):
                        outP[r, s_, i, j] = Ps[i, j]
            if ws:
                if t - N < t0:
                    for i in range(n):
                        for j in range(n):
                            outS[r, s_, i, j] = np.nan
                    continue
                for i in range(n):
                    for j in range(n):
                        Ps[i, j] = Pn[i, j]
                for u in range(t - 1, t - N - 1, -1):
                    _smooth(Ps, Pf[u % W], A, Q, info_s, limit_s, Ps2, w1, w2, w3, w4, w5, w6)
                    for i in range(n):
                        for j in range(n):
                            Ps[i, j] = Ps2[i, j]
                bad = False
                for i in range(n):
                    for j in range(n):
                        if not np.isfinite(Ps[i, j]):
                            bad = True
                for i in range(n):
                    for j in range(n):
                        outS[r, s_, i, j] = np.inf if bad else Ps[i, j]
    # step 0 (P_{0|0}) is never a slot of the kernel: handled by the caller


def _nb_correct(Pm, C, R, g, info, limit, Pn, PCt, S, X, w1, w2):
    """Pn = P_{k|k} from Pm = P_{k|k−1}: kalman_numba.update, then :class:`kalman.Rescue` for one sensor
    group with a finite prior (tr Pm > limit: redo in information form if the packet arrived; lost: Pm
    exactly). Returns True when Pm or Pn is non-finite: the caller hands that run to the numpy core,
    whose rescue policy decides (an overflowed prior recovers at the next arrival)."""
    n = Pm.shape[0]
    tr = 0.0
    for i in range(n):
        tr += Pm[i, i]
    kn.update(Pm, C, R, g, Pn, PCt, S, X)
    if not (tr <= limit):
        for i in range(n):
            for j in range(n):
                if not np.isfinite(Pm[i, j]):
                    return True
        if g != 0.0:
            kn.information_update(Pm, info, Pn, w1, w2)
    for i in range(n):
        for j in range(n):
            if not np.isfinite(Pn[i, j]):
                return True
    return False


def _nb_smooth(Ps, Pf, A, Q, info_s, limit_s, out, w1, w2, w3, w4, w5, w6):
    """kalman_numba.smooth (one RTS step in conditioning form), as a compiled call of its own."""
    kn.smooth(Ps, Pf, A, Q, info_s, limit_s, out, w1, w2, w3, w4, w5, w6)


_correct = _smooth = None  # the compiled helpers, bound by _kernel()


def _kernel():
    """The compiled recursion (built lazily: numba is imported only when used; cached on disk). The
    filter correction and the RTS step are compiled as functions of their own (not inlined into the
    kernel): each inlines its kalman_numba primitives once, which keeps the first compilation short."""
    f = _JIT.get("k")
    if f is None:
        import numba as nb  # optional (netkf[fast]): imported only when the compiled backend runs

        from netkf_cli import kalman_numba  # needs numba: the compiled primitives

        opts = dict(cache=True, nogil=True, error_model="numpy")
        g = globals()
        g["kn"] = kalman_numba  # resolved by numba when it compiles the kernel
        g["_correct"] = nb.njit(**opts)(_nb_correct)
        g["_smooth"] = nb.njit(**opts)(_nb_smooth)
        f = _JIT["k"] = nb.njit(**opts)(_nb_kernel)
    return f


def _run_numba(f: kalman.Filter, system, gamma, steps, qs, N, prior):
    runs = gamma.shape[-1]
    n = f.A.shape[0]
    pos = [k for k in steps if k >= 1]
    T = pos[-1] if pos else 0
    slot = np.full(T + 1, -1, dtype=np.int64)
    slot[pos] = np.arange(len(pos))
    K = len(pos)
    wf, wp, ws = ("filtered" in qs) or (N == 0 and "smoothed" in qs), "predicted" in qs, ("smoothed" in qs and N > 0)
    outF = np.empty((runs, K if wf else 0, n, n))  # run-major inside the kernel (one run's steps contiguous)
    outP = np.empty((runs, K if wp else 0, n, n))
    outS = np.empty((runs, K if ws else 0, n, n))
    use_prior = prior is not None
    P0 = initial_covariance(system) if not use_prior else np.zeros((n, n))
    Pm1 = np.asarray(prior, dtype=float) if use_prior else np.zeros((n, n))
    info = f.C.T @ np.linalg.solve(f.R, f.C)
    back = kalman.SmoothStep.of(f.A, f.Q)
    info_s = f.A.T @ np.linalg.solve(f.Q, f.A) if back.rescue is not None else np.zeros((n, n))
    limit_s = float(back.rescue.limit) if back.rescue is not None else np.inf
    flag = np.zeros(runs, dtype=np.bool_)
    if K:
        g = np.ascontiguousarray(gamma[0, :T].T, dtype=np.bool_)  # (runs, T)
        _kernel()(f.A, f.C, f.Q, f.R, info, float(f.rescue.limit), info_s, limit_s, np.ascontiguousarray(P0, dtype=float),
                  np.ascontiguousarray(Pm1), use_prior, g, slot, N, wf, wp, ws, outF, outP, outS, flag)
    # back to the core layout (K, n, n, runs), run axis innermost
    outF, outP, outS = (np.ascontiguousarray(np.moveaxis(o, 0, -1)) for o in (outF, outP, outS))
    idx = np.flatnonzero(flag)
    if idx.size and K:  # runs that met a non-finite covariance: the numpy core from the start (its rescue policy)
        sub = np.ascontiguousarray(gamma[:, :, idx])
        redo = _run_numpy if use_prior else (lambda *a: _run_core(*a[:-1], "numpy"))
        for k, d in redo(f, system, sub, pos, tuple(dict.fromkeys(q for q in ("filtered", "predicted", "smoothed")
                                                               if (q == "filtered" and wf) or (q == "predicted" and wp)
                                                               or (q == "smoothed" and ws))), N, prior):
            i = slot[k]
            if wf:
                outF[i][..., idx] = d["filtered"]
            if wp:
                outP[i][..., idx] = d["predicted"]
            if ws:
                outS[i][..., idx] = d["smoothed"]
    for k in steps:
        if k == 0:  # P_{0|0} (lag 0 only): the prior itself
            P = np.repeat(initial_covariance(system)[:, :, None], runs, axis=2)
            yield 0, {q: (P if q != "predicted" else kalman.predict(P, f.A, f.Q)) for q in qs}
            continue
        i = slot[k]
        out = {}
        for q in qs:
            if q == "filtered" or (q == "smoothed" and N == 0):
                out[q] = outF[i]
            elif q == "predicted":
                out[q] = outP[i]
            else:
                out[q] = outS[i]
        yield k, out


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
    """Eqs (3)–(4) over arrivals ``gamma`` (``(runs, horizon)``, index 0 = the first measurement,
    whose prior is ``P0`` = P_{0|−1}, default P_{1|0} of the one time base, A P_{0|0} Aᵀ + Q) and record
    P_{t|t−1}, P_{t|t+N} (N = 0 … lag) at ``times`` (default: every t with t + lag < horizon).

    On the core time base, index t is step t + 1: P_{t|t+N} here is ``smoothed`` (lag N) at step t + 1 + N.
    """
    gamma = np.asarray(gamma)
    if gamma.ndim != 2:
        raise ValueError(f"gamma must be (runs, horizon), got shape {gamma.shape}")
    if lag < 0 or lag > MAX_LAG:
        raise ValueError(f"lag must be in 0..{MAX_LAG}, got {lag}")
    runs, horizon = gamma.shape
    times = np.arange(0, horizon - lag) if times is None else np.asarray(times, dtype=int)
    if times.size and (times.min() < 0 or times.max() + lag >= horizon):
        raise ValueError(f"times must satisfy 0 ≤ t and t + lag < horizon = {horizon}")
    prior = first_prediction(system) if P0 is None else np.asarray(P0, dtype=float)
    g = np.ascontiguousarray(gamma.T)[None]
    n = system.n
    pred = np.empty((len(times), n, n, runs))
    smooth = np.empty((len(times), lag + 1, n, n, runs))
    # P_{t|t−1} (index t) = predicted at step t (step 0: the prior)
    want = sorted({int(t) for t in times if t >= 1})
    got = dict(run(system, g, want, ("predicted",), 0, backend=backend, prior=prior)) if want else {}
    for i, t in enumerate(times):
        pred[i] = np.repeat(prior[:, :, None], runs, axis=2) if t == 0 else got[int(t)]["predicted"]
    for N in range(lag + 1):
        ks = [int(t) + 1 + N for t in times]
        got = dict(run(system, g, sorted(set(ks)), ("smoothed",), N, backend=backend, prior=prior))
        for i, k in enumerate(ks):
            smooth[i, N] = got[k]["smoothed"]
    return SmootherResult(times=times, pred=pred, smooth=smooth)


def first_prediction(system: LinearSystem) -> np.ndarray:
    """P_{1|0} = A P_{0|0} Aᵀ + Q (P_{0|0} = :func:`initial_covariance`; unset P0: P̄, so P_{1|0} = P*)."""
    return kalman.one(kalman.predict, initial_covariance(system), system.A, system.Q)


initial_prediction = first_prediction
"""The historical name (P_{0|−1} of :func:`fixed_lag_smoother` = P_{1|0} of the one time base)."""
