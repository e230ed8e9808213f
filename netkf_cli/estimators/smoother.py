"""Kalman fixed-lag smoother with random packet loss (Leong, Dey & Evans 2008, Sec. II), on the Kalman core.

Forward pass: :class:`netkf_cli.linalg.kalman.Filter` (the Kalman filter with intermittent observations,
every step through the one rescue policy :class:`netkf_cli.linalg.kalman.Rescue`), so ``filtered`` and
``predicted`` are exactly those of ``kind: kf``. Backward pass: N Rauch–Tung–Striebel steps from
P_{k|k} back to the target time k − N, t = k−1 … k−N:

    P_{t|k} = P_{t|t} + J_t (P_{t+1|k} − P_{t+1|t}) J_tᵀ,   J_t = P_{t|t} Aᵀ P_{t+1|t}⁻¹
            = P_{t|t, x_{t+1}} + J_t P_{t+1|k} J_tᵀ          (:class:`netkf_cli.linalg.kalman.SmoothStep`)

with P_{t|t, x_{t+1}} = P_{t|t} − J_t A P_{t|t} the core's ``update`` of P_{t|t} by x_{t+1} = A x_t + w_t
(C = A, R = Q; its gain is J_t), through the rescue ``Rescue.for_system(A, A, Q, Q, n)``: the first form subtracts
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
``system.sensors`` (:func:`netkf_cli.linalg.kalman.stream_rows`).

Backends. The batched pass (:func:`_run_shared`): the forward pass is kf's own call (``Filter.run``
with the backend kf chooses, :func:`kalman.choose_backend`: the generated compiled kernel for large
batches), so filtered / predicted / lag-0 smoothed are kf's numbers by construction; the RTS step splits
into J_t, C_t = P_{t|t, x_{t+1}} (functions of P_{t|t} only: computed once per trace step, batched over
the steps) and the affine map P_{t|k} = C_t + J_t P_{t+1|k} J_tᵀ, applied N times per requested step,
batched over the steps. ``numpy``: the core's operations (bit for bit the per-step reference
:func:`_run_core`); with kf's compiled forward pass, the generated kernels of
:mod:`netkf_cli.estimators._smoother_codegen` (A, Q inlined; bit for bit the numpy pass for n ≤ 2, equal
to rounding for n ≥ 3), also after kf's numpy forward pass for batches of ≥ :data:`AUTO_MIN_RTS_RUN_STEPS`. The pass of one trace is kept for the next call on the same arrivals and system, so the engine's
smoothers that differ only in lag share the forward pass, the RTS pieces and the chain (P_{k−4|k}
continues from P_{k−2|k}): the same numbers as separate passes (a test). ``numba``: the batched pass with
the compiled forward and backward passes; for at most :data:`AUTO_NUMBA_MAX_RUNS` runs and one arrival
stream, the per-run kernel built from :mod:`netkf_cli.linalg.kalman_numba`'s inlined primitives (predict,
update, the rescue's information update, gain, the RTS step ``smooth``; equal to rounding, a test), which
``auto`` also takes for lag ≥ 1 there (long runs of few columns, the paper's-way run of Table I).

Monte Carlo: the generic engine (:func:`netkf_cli.engine.simulate` on :meth:`SmootherEstimator.covariances`;
the retransmission schemes of Sec. V are a channel, ``kind: retransmission``).
"""

from __future__ import annotations

import hashlib
import threading
import weakref
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from netkf_cli.linalg import batched, kalman
from netkf_cli.linalg.kalman import numba_available  # noqa: F401  (re-exported: the one probe)
from netkf_cli.linalg import kalman_codegen as kc
from netkf_cli.estimators import _smoother_codegen as sc
from netkf_cli.core.errors import ConfigError
from netkf_cli.estimators.kf import channel_streams, filter_estimates
from netkf_cli.linalg.riccati import initial_covariance
from netkf_cli.core.spec import EstimatorModel, NonNegInt
from netkf_cli.core.system import LinearSystem

MAX_LAG = 64
"""Largest smoothing lag accepted (the work per step grows linearly with the lag)."""

BACKENDS = ("auto", "numpy", "numba")
AUTO_NUMBA_MAX_RUNS = 256
"""``backend: auto`` runs the per-run compiled kernel only for batches of at most this many runs
(measured, experiments/smoothing/README "Speed": it does 1–4e6 run-steps/s for n ≤ 2; the batched
path overtakes it at a few hundred runs). Long runs of few columns — the paper's-way run of
Table I — are where it wins (10–100× a numpy loop over the steps)."""

AUTO_MIN_RTS_RUN_STEPS = 1_000_000
"""``backend: auto`` runs the backward pass on the generated compiled kernels (after kf's numpy forward
pass, when kf's choice is numpy) from this many run-steps (runs × requested steps) per call — by the batch,
not the lag, so the smoothers of every lag on one trace choose alike and share one pass. The kernels
depend only on (A, Q) — one compilation per system and machine, shared by an over grid of channel
parameters — and load in well under a second, which this much work repays (the numpy pass costs ~50 ns
per run-step-lag at n = 1, the compiled ~1 ns); a quick run stays on numpy (numba not even imported for
it). Bit for bit the numpy pass for n ≤ 2 (the same operations in the same order, S⁻¹ in closed form: a
test); equal to rounding for n ≥ 3 (Cholesky)."""

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
        "auto", description="covariance recursion: numpy (reference, batched over runs and steps), numba (kf's "
        "compiled forward pass and generated RTS kernels, equal to rounding; a per-run kernel for at most "
        f"{AUTO_NUMBA_MAX_RUNS} runs of one arrival stream), auto = the forward pass exactly as kf runs it (its "
        "compiled kernel for large batches, then the compiled RTS kernels too) and the per-run kernel for lag ≥ 1 "
        f"and at most {AUTO_NUMBA_MAX_RUNS} runs (where it is measured faster)")

    @property
    def label(self) -> str:
        """The smoothed quantity for this lag, e.g. ``P_{k-2|k}``."""
        return "P_{k|k}" if self.lag == 0 else f"P_{{k-{self.lag}|k}}"

    def first_step(self, quantity: str) -> int:
        return int(self.lag) if quantity == "smoothed" else 1

    def conventions(self, system, channel) -> dict[str, str]:
        return {"smoothed": f"{self.label} (lag N = {self.lag})", "filtered, predicted": "kf's"}

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

    def covariance_blocks(self, system: LinearSystem, trace, steps, quantities=("filtered",)):
        """:meth:`covariances` by blocks of consecutive steps: yield ``(ks, {quantity: P})``, P ``(len(ks), n, n,
        runs)`` — the same arrays, step for step (:func:`run_blocks`); the engine reduces each block in one call."""
        qs = kalman.check_quantities(quantities, self.quantities, "smoother")
        if trace.arrival is None:
            raise ConfigError.at("estimator.kind", "the smoother needs a trace with arrival indicators")
        yield from run_blocks(system, trace.arrival, steps, qs, int(self.lag), backend=self.backend)

    def backend_used(self, system, channel, runs: int, horizon: int, steps=None, quantities=None) -> str:
        """What :func:`plan` chooses for a chunk of ``runs`` runs reporting ``steps`` (default every step) of
        ``quantities`` (default smoothed): "numba (per-run kernel)" or "<forward> forward pass, <numpy|compiled>
        RTS" (recorded in the manifest)."""
        f = kalman.Filter.of(system, channel_streams(channel) or 1, "estimator.kind")
        n_steps = horizon if steps is None else len(steps)
        N = int(self.lag) if quantities is None or "smoothed" in quantities else 0
        how, fwd, rts = plan(f, self.backend, N, runs, horizon, n_steps)
        return "numba (per-run kernel)" if how == "per_run" else f"{fwd} forward pass, {rts} RTS"

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
    runs = gamma.shape[-1]
    one_stream = len(f.groups) == 1
    if prior is not None:
        be = resolve_backend(backend)
        if be == "numba" and one_stream and (backend == "numba" or (N > 0 and runs <= AUTO_NUMBA_MAX_RUNS)):
            yield from _run_numba(f, system, gamma, steps, qs, N, prior)  # the per-run compiled kernel
        else:
            yield from _run_numpy(f, system, gamma, steps, qs, N, prior)
        return
    path = plan(f, backend, N, runs, horizon, len(steps))
    if path == ("per_run", None, None):
        yield from _run_numba(f, system, gamma, steps, qs, N, prior)  # few long runs: the per-run kernel
        return
    _, fwd, rts = path
    yield from _run_shared(f, system, gamma, steps, qs, N, fwd, rts)


def run_blocks(system: LinearSystem, gamma: np.ndarray, steps, quantities=("smoothed",), lag: int = 0, *,
               backend: str = "numpy") -> Iterator[tuple[list[int], dict]]:
    """:func:`run` by blocks: yield ``(ks, {quantity: P (len(ks), n, n, runs)})``, the arrays :func:`run` yields
    at the steps ``ks``, stacked. The shared pass (:func:`plan`) hands out each block of steps it computes
    whole (:func:`_emit_blocks`: no per-step work); the other paths one step at a time."""
    qs = kalman.check_quantities(quantities, ("filtered", "predicted", "smoothed"), "smoother")
    gamma = np.asarray(gamma)
    if gamma.ndim != 3:
        raise ValueError(f"gamma must be (streams, horizon, runs), got shape {gamma.shape}")
    f = kalman.Filter.of(system, gamma.shape[0], "estimator.kind")
    steps = _check_steps(steps, gamma.shape[1])
    if not steps:
        return
    N = int(lag) if "smoothed" in qs else 0
    path = plan(f, backend, N, gamma.shape[-1], gamma.shape[1], len(steps))
    if path[0] == "shared":
        yield from _run_shared(f, system, gamma, steps, qs, N, path[1], path[2], emit=_emit_blocks)
        return
    for k, out in run(system, gamma, steps, qs, lag, backend=backend):
        yield [k], {q: P[None] for q, P in out.items()}


def plan(f: kalman.Filter, backend: str, N: int, runs: int, horizon: int, n_steps: int) -> tuple:
    """How :func:`run` (P0 = P_{0|0}) computes a batch: ``("per_run", None, None)`` — the per-run compiled
    kernel (few long runs of one stream) — or ``("shared", fwd, rts)``: the forward pass is kf's own call
    (Filter.run on ``fwd``, the backend kf would choose: its generated compiled kernel for large batches;
    numba: always), the backward pass the RTS pieces of every step computed once and shared by every step
    and lag (``rts`` compiled with a compiled forward pass, or for a big auto batch). A small auto batch never
    imports numba (kalman.choose_backend). The same choice is what the manifest records (backend_used)."""
    one_stream = len(f.groups) == 1
    few = one_stream and runs <= AUTO_NUMBA_MAX_RUNS and (backend == "numba" or N > 0)
    if backend != "numpy" and few and resolve_backend(backend) == "numba":
        return ("per_run", None, None)
    if backend == "numba":
        resolve_backend("numba")  # a ConfigError without numba
        fwd = "numba" if f.sequential else "numpy"
    else:
        if backend not in BACKENDS:
            resolve_backend(backend)  # the ConfigError naming the backends
        fwd = kalman.choose_backend("auto" if backend == "auto" else "numpy", f, runs * horizon)
    # (by the batch, not the lag: smoothers of every lag on one trace make the same choice and share its pass)
    big = runs * n_steps >= AUTO_MIN_RTS_RUN_STEPS
    compiled = fwd == "numba" or (backend == "auto" and big and numba_available())
    return ("shared", fwd, "compiled" if (compiled and sc.supported(f.A.shape[0])) else "numpy")


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


# ---------------------------------------------------------------------------------------------
# the shared pass: kf's forward pass once per trace, the RTS pieces once per trace step
# ---------------------------------------------------------------------------------------------

SHARE_MARGIN = 4
"""Forward rows kept below each requested step beyond the estimator's own lag, so that the smoothers of
larger lag (up to this) of the same run find the trace's forward pass already done (:func:`_run_shared`)."""
BLOCK_BYTES = 8 * 2**20
"""Memory of one block of the shared pass (stored P_{t|t}, J_t, C_t and a smoothed chain): a request
that fits is one block and is kept for the next estimator on the same trace; a larger one is cut into
blocks of steps (nothing kept). It bounds a chunk's working set (issue 20: at 256 MB a 5000-run chunk of
Table I's 500 steps was one block and held 145 MB; at 8 MB it holds ~12 MB)."""

_TLS = threading.local()
"""Per thread, the last trace's :class:`_Pass` (an executor's threads never share a trace)."""


def _rts_prepare_numpy(back: kalman.SmoothStep, Pf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(J, C) of :class:`kalman.SmoothStep` for P_{t|t} = ``Pf`` (n, n, runs): the gain J and
    C = P_{t|t, x_{t+1}} (the update of Pf by x_{t+1}, through the rescue) — exactly the operations of
    ``SmoothStep.__call__`` before it touches P_{t+1|k}."""
    n = Pf.shape[0]
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        J = kalman.gain(Pf, back.A, back.Q)
        P = kalman.update(Pf, back.A, back.Q)
        if back.rescue is not None:
            flagged = back.rescue.flag(Pf)
            if flagged.any():
                P = back.rescue.apply(P, Pf, flagged, np.ones((n, Pf.shape[-1]), dtype=bool))
    return J, P


def _rts_apply_numpy(J: np.ndarray, C: np.ndarray, Ps: np.ndarray) -> np.ndarray:
    """P_{t|k} = sym(C + J P_{t+1|k} Jᵀ), non-finite ⇒ ∞: the rest of ``SmoothStep.__call__``, so
    ``_rts_apply_numpy(*_rts_prepare_numpy(back, Pf), Ps)`` is ``back(Ps, Pf)`` bit for bit (a test)."""
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        out = batched.sym(C + batched.matmul(batched.matmul(J, Ps), J.swapaxes(0, 1)))
    bad = ~np.isfinite(out).all(axis=(0, 1))
    if bad.any():
        out[:, :, bad] = np.inf
    return out


def _flat(X: np.ndarray) -> np.ndarray:
    """(R, n, n, runs) → (n, n, R·runs), the core's layout for one batched call over R trace steps."""
    R, n, _, runs = X.shape
    return np.moveaxis(X, 0, 2).reshape(n, n, R * runs)


def _unflat(Y: np.ndarray, R: int) -> np.ndarray:
    n, _, m = Y.shape
    return np.ascontiguousarray(np.moveaxis(Y.reshape(n, n, R, m // R), 2, 0))


class _Pass:
    """One trace's forward pass P_{t|t} at ``rows`` (``H`` (R, n, n, runs)), the RTS pieces J_t, C_t of
    the rows prepared so far, and the deepest smoothed chain computed for ``steps``."""

    def __init__(self, f, rows: list[int], H: np.ndarray, rts: str, steps: tuple[int, ...], margin: int, back=None):
        self.f, self.rows, self.H, self.rts, self.steps, self.margin = f, rows, H, rts, steps, margin
        self.pos = {t: i for i, t in enumerate(rows)}
        self.back = kalman.SmoothStep.of(f.A, f.Q) if back is None else back  # (one per call: the blocks share it)
        self.J = self.C = None
        self.ready = np.zeros(len(rows), dtype=bool)
        self.chain: tuple[int, np.ndarray] | None = None  # (lag d, P_{k−d|k} (K, n, n, runs), NaN for k < d)

    def prepare(self, ts) -> None:
        """J_t, C_t for the trace steps ``ts`` (each once per pass)."""
        idx = np.array(sorted({self.pos[t] for t in ts}), dtype=np.int64)
        idx = idx[~self.ready[idx]]
        if idx.size == 0:
            return
        if self.J is None:
            self.J, self.C = np.empty_like(self.H), np.empty_like(self.H)
        if self.rts == "compiled":
            lim = float(self.back.rescue.limit) if self.back.rescue is not None else np.inf
            flag = np.zeros(self.H.shape[::3], dtype=np.bool_)
            sc.kernel_prepare(self.f.A, self.f.Q, lim)(self.H, idx, self.J, self.C, flag)
            fr = np.flatnonzero(flag.any(axis=1))  # (np.nonzero of the whole flag array: ~8 ms a call)
            ti, ri = np.nonzero(flag[fr])
            ti = fr[ti]
            if ti.size:  # the rescue's entries (and anything non-finite): the numpy core, exactly
                J, C = _rts_prepare_numpy(self.back, np.ascontiguousarray(np.moveaxis(self.H[ti, :, :, ri], 0, -1)))
                self.J[ti, :, :, ri] = np.moveaxis(J, -1, 0)
                self.C[ti, :, :, ri] = np.moveaxis(C, -1, 0)
        else:
            J, C = _rts_prepare_numpy(self.back, _flat(self.H[idx]))
            self.J[idx], self.C[idx] = _unflat(J, idx.size), _unflat(C, idx.size)
        self.ready[idx] = True

    def smoothed(self, N: int) -> np.ndarray:
        """P_{k−N|k} for k in ``steps`` (K, n, n, runs), NaN where k < N; from the deepest chain kept when
        its lag d ≤ N (its N − d further steps are the same operations: the same numbers)."""
        K = len(self.steps)
        if self.chain is not None and self.chain[0] == N:
            return self.chain[1]
        d, S0 = (self.chain if self.chain is not None and self.chain[0] < N else (0, None))
        ok = [i for i, k in enumerate(self.steps) if k >= N]
        out = np.full((K,) + self.H.shape[1:], np.nan) if len(ok) < K else None
        if ok:
            ks = [self.steps[i] for i in ok]
            self.prepare([k - u for k in ks for u in range(d + 1, N + 1)])
            tix = np.array([[self.pos[k - u] for u in range(d + 1, N + 1)] for k in ks], dtype=np.int64)
            sidx = np.array(ok if S0 is not None else [self.pos[k] for k in ks], dtype=np.int64)
            src = S0 if S0 is not None else self.H
            if self.rts == "compiled":
                res = np.empty((len(ok),) + self.H.shape[1:])
                sc.kernel_chain(self.H.shape[1])(src, sidx, self.J, self.C, tix, res)
            else:
                m = len(ok)
                Ps = _flat(src[sidx])
                for u in range(tix.shape[1]):
                    Ps = _rts_apply_numpy(_flat(self.J[tix[:, u]]), _flat(self.C[tix[:, u]]), Ps)
                res = _unflat(Ps, m)
            if out is None:  # every step smooths back N steps: the result is the output
                out = res
            else:
                out[ok] = res
        if self.chain is None or N > self.chain[0]:
            self.chain = (N, out)
        return out


def _fingerprint(gamma: np.ndarray) -> bytes:
    g = np.ascontiguousarray(gamma)
    data = np.packbits(g).tobytes() if g.dtype == np.bool_ else g.tobytes()
    return hashlib.blake2b(data, digest_size=16).digest() + repr((g.shape, g.dtype.str)).encode()


def _blocks(steps: list[int], L: int, row_bytes: int) -> list[list[int]]:
    """``steps`` cut into consecutive groups whose rows ∪ [k − L, k] fit :data:`BLOCK_BYTES`."""
    most = max(L + 2, BLOCK_BYTES // max(row_bytes, 1))
    out, cur, lo = [], [], None
    for k in steps:
        if cur and (k - lo + 1) > most:
            out.append(cur)
            cur = []
        if not cur:
            lo = max(0, k - L)
        cur.append(k)
    if cur:
        out.append(cur)
    return out


def _keep(gamma: np.ndarray, key, ps: _Pass) -> None:
    """Keep ``ps`` for the next call on these arrivals, and drop it when the arrival array is freed."""
    _TLS.last = (key, ps)
    try:
        weakref.finalize(gamma, _forget, key)
    except TypeError:  # not weak-referenceable: kept until the next pass replaces it
        pass


def _forget(key) -> None:
    got = getattr(_TLS, "last", None)
    if got is not None and got[0] == key:
        _TLS.last = None


def _run_shared(f: kalman.Filter, system, gamma, steps, qs, N, fwd: str, rts: str, emit=None):
    """Forward: :meth:`kalman.Filter.run` with backend ``fwd`` (exactly kf's numbers; numba: streamed by
    :func:`_forward_stream`) at every trace step a requested step's backward pass reads; backward: J_t, C_t
    once per trace step (:class:`_Pass`, ``rts`` numpy = the core's operations batched over trace steps, bit
    for bit :func:`_run_core`; compiled = :mod:`netkf_cli.estimators._smoother_codegen`, equal to rounding),
    then for every requested step the N affine RTS maps batched over the steps. A request that fits one block
    (:data:`BLOCK_BYTES`) is kept (per thread) for the next call on the same arrivals and system — the
    engine's other estimators on the same trace — so smoothers that differ only in lag share the forward
    pass, the RTS pieces and the chain (the same numbers as separate calls, a test). A larger request is cut
    into blocks of steps, each holding only the rows [k − N, k] of its steps, and nothing is kept: the
    working set is one block whatever the horizon and chunk (issue 20); every number is the one-block
    number (per run and step the same operations on the same operands, a test). ``emit`` (default
    :func:`_emit`, one step at a time; :func:`_emit_blocks`) hands out each block's covariances."""
    emit = _emit if emit is None else emit
    runs, n = gamma.shape[-1], f.A.shape[0]
    smooth = "smoothed" in qs and N > 0
    L = max(N, SHARE_MARGIN)
    row_bytes = 4 * n * n * runs * 8
    blocks = _blocks(steps, L, row_bytes)
    P0 = initial_covariance(system)
    key = None
    if len(blocks) == 1:
        key = (_fingerprint(gamma), f.A.tobytes(), f.C.tobytes(), f.Q.tobytes(), f.R.tobytes(), f.groups,
               P0.tobytes(), fwd, rts, tuple(steps))
        got = getattr(_TLS, "last", None)
        if got is not None and got[0] == key and got[1].margin >= N:
            yield from emit(got[1], qs, N)
            return
    else:  # nothing is kept for another estimator: only the rows this lag reads
        L = N if smooth else 0
        blocks = _blocks(steps, L, row_bytes)
    back = kalman.SmoothStep.of(f.A, f.Q)
    P0r = np.repeat(P0[:, :, None], runs, axis=2)
    kept = _forward_kept(f, P0, gamma, steps, N, fwd) if key is None else None
    if kept is not None:  # the forward pass kept whole: a block's rows are a slice of it (no copy)
        rows_all, store = kept
        at = {t: i for i, t in enumerate(rows_all)}
        for block in blocks:
            rows = _window(block, L, 0)
            if rows[0] >= 1 and at[rows[-1]] - at[rows[0]] == len(rows) - 1:
                H = store[at[rows[0]]:at[rows[-1]] + 1]
            else:
                H = np.stack([P0r if t == 0 else store[at[t]] for t in rows])
            ps = _Pass(f, rows, H, rts, tuple(block), L, back)
            del H
            yield from emit(ps, qs, N if smooth else 0)
            del ps
        return
    forward = _forward(f, P0, gamma, _window(steps, L, 1), fwd)  # streamed: only the rows of the blocks to come
    have: dict[int, np.ndarray] = {0: P0r}
    last = 0
    for block in blocks:
        rows = _window(block, L, 0)
        while last < rows[-1]:
            last, P = next(forward)
            have[last] = P
        H = np.stack([have[t] for t in rows])
        for t in [u for u in have if u < rows[-1] + 1 - L]:
            del have[t]
        ps = _Pass(f, rows, H, rts, tuple(block), L, back)
        del H
        if key is not None:
            _keep(gamma, key, ps)
        yield from emit(ps, qs, N if smooth else 0)
        del ps


def _window(steps: list[int], L: int, lo: int) -> list[int]:
    """The sorted trace steps t ≥ ``lo`` in ∪_k [k − L, k] over ``steps`` (ascending): one range when the steps are
    consecutive (a time average's), else the union."""
    if steps[-1] - steps[0] == len(steps) - 1:
        return list(range(max(lo, steps[0] - L), steps[-1] + 1))
    return sorted({t for k in steps for t in range(max(lo, k - L), k + 1)})


FORWARD_BYTES = 24 * 2**20
"""Largest forward pass (P_{t|t} at the rows of every requested step) kept for the next estimator on the same
trace when a request is cut into blocks (:func:`_forward_kept`; a larger one is redone by each estimator).
The engine's smoothers of one trace (Table I: lags 0 … 4) would otherwise redo it each: kf's numpy pass (batches
under ``kalman.AUTO_MIN_RUN_STEPS`` = 1e6 run-steps) costs ~0.3 ms per step in numpy's per-call overhead
whatever the batch, the compiled one ~20 µs per step. 24 MB holds the configs' chunks at n = 1 (5000 runs ×
504 rows: 20 MB)."""


def _forward(f: kalman.Filter, P0: np.ndarray, gamma: np.ndarray, want: list[int], fwd: str):
    """``(t, P_{t|t})`` for t in ``want``: kf's forward pass on backend ``fwd`` (:meth:`kalman.Filter.run`;
    numba with kf's generated kernel: :func:`_forward_stream`, the same numbers)."""
    if fwd == "numba" and f.sequential and kc.supported(f.A.shape[0], f.groups):
        return _forward_stream(f, P0, gamma, want)
    return ((k, d["filtered"]) for k, d in f.run(P0, gamma, want, ("filtered",), backend=fwd))


def _forward_kept(f: kalman.Filter, P0: np.ndarray, gamma: np.ndarray, steps: list[int], N: int, fwd: str):
    """``(rows, store)``: P_{t|t} = store[i] at t = rows[i], the rows of [k − max(N, SHARE_MARGIN), k] of ``steps``
    (t ≥ 1), from kf's forward pass (:func:`_forward`), kept (per thread, until the arrivals are freed) for the next
    call on the same arrivals, system, steps and backend with a lag of at most that margin — the same array, so the
    same numbers; None when it would exceed :data:`FORWARD_BYTES` (the caller streams the rows it reads)."""
    L = max(N, SHARE_MARGIN)
    rows = _window(steps, L, 1)
    n, runs = f.A.shape[0], gamma.shape[-1]
    if len(rows) * n * n * runs * 8 > FORWARD_BYTES:
        return None
    key = (_fingerprint(gamma), f.A.tobytes(), f.C.tobytes(), f.Q.tobytes(), f.R.tobytes(), f.groups,
           np.asarray(P0).tobytes(), fwd, tuple(steps))
    got = getattr(_TLS, "forward", None)
    if got is not None and got[0] == key and got[1] >= N:
        return got[2], got[3]
    _TLS.forward = None  # (a previous trace's pass: freed before this one is built)
    store = np.empty((len(rows), n, n, runs))
    for i, (_, P) in enumerate(_forward(f, P0, gamma, rows, fwd)):
        store[i] = P
    _TLS.forward = (key, L, rows, store)  # kept for the next estimator on this trace
    try:
        weakref.finalize(gamma, _forget_forward, key)
    except TypeError:  # not weak-referenceable: kept until the next pass replaces it
        pass
    return rows, store


def _forget_forward(key) -> None:
    got = getattr(_TLS, "forward", None)
    if got is not None and got[0] == key:
        _TLS.forward = None


def _forward_stream(f: kalman.Filter, P0: np.ndarray, gamma: np.ndarray, want: list[int]) -> Iterator[tuple[int, np.ndarray]]:
    """Yield ``(k, P_{k|k})`` for k in ``want``: ``f.run(P0, gamma, want, ("filtered",), backend="numba")``
    streamed, one step's covariances at a time (:meth:`kalman.Filter.stream_generated`: kf's generated kernel
    and the rescue's numpy redo of flagged runs), without holding the whole horizon (issue 20: 19 MB per
    5000 runs × 500 steps, n = 1); the first-flagged pass is shared by the engine's smoothers on one trace
    (:func:`_first_flagged`)."""
    runs = gamma.shape[-1]
    P_init = np.array(np.repeat(np.asarray(P0, dtype=float)[:, :, None], runs, axis=2), dtype=float, order="C")
    yield from f.stream_generated(P_init, gamma, want,
                                  flagged=lambda adv, P, gam, upto: _first_flagged(f, adv, P, gam, upto))


def _first_flagged(f: kalman.Filter, adv, P_init: np.ndarray, gam: np.ndarray, upto: int) -> np.ndarray:
    """Per run, the first step t ≤ ``upto`` after which kf's generated kernel ``adv`` has flagged it for the
    rescue (``upto`` + 1: never), from the kernel one step at a time (its flag is deterministic per step and
    stays set). Kept per thread for the next estimator on the same arrivals and filter (the engine's smoothers
    on one trace), until the arrivals are freed."""
    key = (_fingerprint(gam), f.A.tobytes(), f.C.tobytes(), f.Q.tobytes(), f.R.tobytes(), f.groups,
           float(f.rescue.limit), P_init[:, :, :1].tobytes())
    got = getattr(_TLS, "flagged", None)
    if got is not None and got[0] == key and got[1] >= upto:
        return np.minimum(got[2], upto + 1)
    first = kalman.first_flagged(adv, P_init, gam, upto)
    if np.all(P_init == P_init[:, :, :1]):  # (one P0 for every run: the key holds it)
        _TLS.flagged = (key, upto, first)
        try:
            weakref.finalize(gam, _forget_flagged, key)
        except TypeError:  # not weak-referenceable: kept until the next pass replaces it
            pass
    return first


def _forget_flagged(key) -> None:
    got = getattr(_TLS, "flagged", None)
    if got is not None and got[0] == key:
        _TLS.flagged = None


def _forward_compiled(f: kalman.Filter, P0: np.ndarray, gamma: np.ndarray, want: list[int]) -> dict[int, dict]:
    """``dict(f.run(P0, gamma, want, ("filtered",), backend="numba"))`` by :func:`_forward_stream`, every step
    held (tests, benchmarks)."""
    return {k: {"filtered": P} for k, P in _forward_stream(f, P0, gamma, want)}


def _emit(ps: _Pass, qs, N: int):
    S = ps.smoothed(N) if ("smoothed" in qs and N > 0) else None
    for i, k in enumerate(ps.steps):
        P = ps.H[ps.pos[k]]
        out = kalman.report(P, tuple(q for q in qs if q != "smoothed"), ps.f.A, ps.f.Q)
        if "smoothed" in qs:
            out["smoothed"] = P if N == 0 else S[i]
        yield k, {q: out[q] for q in qs}


def _emit_blocks(ps: _Pass, qs, N: int):
    """:func:`_emit` for the whole block: ``(steps, {quantity: P (K, n, n, runs)})``, the arrays _emit yields
    step by step (P_{k|k} the rows of ``ps.H``, a view when they are consecutive; ``smoothed`` the chain itself)."""
    idx = [ps.pos[k] for k in ps.steps]
    H = ps.H[idx[0]:idx[-1] + 1] if idx == list(range(idx[0], idx[-1] + 1)) else ps.H[idx]
    out = {}
    for q in qs:
        if q == "filtered" or (q == "smoothed" and N == 0):
            out[q] = H
        elif q == "smoothed":
            out[q] = ps.smoothed(N)
        else:
            out[q] = np.stack([kalman.report(P, (q,), ps.f.A, ps.f.Q)[q] for P in H])
    yield list(ps.steps), out


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
"""netkf_cli.linalg.kalman_numba, bound when the kernel is first compiled (numba is optional)."""

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

        from netkf_cli.linalg import kalman_numba  # needs numba: the compiled primitives

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
