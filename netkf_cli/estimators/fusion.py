"""MF, IBF and OLPEF at a fusion centre fed by N lossy links (Chiuso & Schenato, Sec. II), on the Kalman core.

The sensors are the system's (``system.sensors``; :func:`netkf_cli.linalg.kalman.stream_rows`): arrival stream
i of a ``multi`` channel carries sensor i's whole measurement y_k^i = C_i x_k + v_k^i; a channel with one
stream carries all of y_k in one packet (one "sensor"). ``system.sensors: N`` = N identical sensors
(C, R copied N times). Every error covariance depends on the arrival trace only (covariance-only mode),
batched over runs (loop over time, run axis innermost).

Time base (netkf's one): P0 = P_{0|0} = ``riccati.initial_covariance(system)`` (``system.P0``; unset =
P̄ of the stacked system, i.e. P_{1|0} = P_m, the all-sensors steady state of the paper); step k = 1 …
horizon is the time of the newest measurement y_k (trace step k − 1); quantities ``filtered`` P_{k|k}
and ``predicted`` P_{k+1|k} = A P_{k|k} Aᵀ + Q (:func:`netkf_cli.linalg.kalman.report`).

* MF (eqs (6)–(9)): the Kalman filter with the sensors that arrived at step k — ``kalman.Filter``
  itself (so MF with one sensor, or with N sensors, IS ``kf`` on the same trace); with N identical
  sensors the update depends on the count ℓ_k = Σ_i γ_k^i only, eq. (14): ``kalman.update_counts``
  (= ℓ_k sequential updates, tested), with the same ``kalman.Rescue`` as the Filter.
* IBF (Sec. II-B): at step k sensor i has delivered every y^i_s up to its last arrival (τ_i steps ago),
  so the centre runs the Riccati recursion with the sensors {i : τ_i ≤ k − s} at step s, from the
  full-information P_{s|s} before the oldest gap. Cost O(max τ) per evaluated step, vectorized over runs
  (rows grouped by how far back they reach).
* OLPEF (eqs (10)–(11)): the steady-state centralized gain L = [L^1 … L^N] split into partial estimates
  z^i; the centre sums A^{τ_i} z^i_{k−τ_i}. Given the τ's the error is a fixed linear combination of the
  jointly Gaussian stationary (x, z^1, …, z^N), so its covariance is a quadratic form in the histogram
  of τ over precomputed lagged covariances (identical sensors). Assumption (documented): the partial
  filters run in steady state since −∞ (evaluate after a burn-in); a sensor with nothing received yet
  contributes the estimate 0.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import ClassVar, Literal

import numpy as np
import scipy.linalg
from pydantic import Field

from netkf_cli.linalg import kalman
from netkf_cli.linalg import kalman_codegen as kc
from netkf_cli.analysis.fusion_bounds import _as2d, p_m
from netkf_cli.channels.multi import block_steps
from netkf_cli.core.errors import ConfigError
from netkf_cli.estimators.kf import channel_streams, filter_estimates
from netkf_cli.linalg.riccati import initial_covariance
from netkf_cli.core.spec import EstimatorModel
from netkf_cli.core.system import LinearSystem

Strategy = Literal["mf", "ibf", "olpef"]
STRATEGIES: tuple[str, ...] = ("mf", "ibf", "olpef")


def identical_sensors(A, C, Q, R, N: int, P0=None) -> LinearSystem:
    """The system with N identical sensors (C, R) — what ``system.sensors: N`` builds (C stacked N
    times, R block-diagonal); ``P0`` is P_{0|0} (None = P̄)."""
    C1, R1 = _as2d(C), _as2d(R)
    m = C1.shape[0]
    return LinearSystem.create(A, np.vstack([C1] * N), Q, np.kron(np.eye(N), R1), P0,
                               sensors=[tuple(range(i * m, (i + 1) * m)) for i in range(N)])


_SENSORS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()
"""Sensors per system (a LinearSystem is immutable and hashed by identity) and stream count."""


@dataclass(frozen=True)
class Sensors:
    """The fusion centre's sensors: the core's :class:`~netkf_cli.linalg.kalman.Filter` over the channel's
    streams, and (C1, R1) of one sensor when all N are identical and independent (else ``None``)."""

    filt: kalman.Filter
    C1: np.ndarray | None
    R1: np.ndarray | None
    N: int

    @classmethod
    def of(cls, system, streams: int, path: str = "estimator.kind") -> "Sensors":
        """The sensors of ``system`` read through ``streams`` arrival streams; built once per (system, streams) in
        a process and kept (:data:`_SENSORS`): the check, the backend and every chunk's covariances ask again."""
        kept = _SENSORS.setdefault(system, {})
        if streams not in kept:
            kept[streams] = cls._build(system, streams, path)
        return kept[streams]

    @classmethod
    def _build(cls, system, streams: int, path: str) -> "Sensors":
        f = kalman.Filter.of(system, streams, path)
        N = len(f.groups)
        C1 = R1 = None
        if N == 1:
            C1, R1 = f.C, f.R
        elif f.sequential:
            blocks = [(f.C[list(g)], f.R[np.ix_(g, g)]) for g in f.groups]
            c0, r0 = blocks[0]
            if all(c.shape == c0.shape and np.array_equal(c, c0) and np.array_equal(r, r0) for c, r in blocks):
                C1, R1 = c0, r0
        return cls(f, C1, R1, N)

    @property
    def identical(self) -> bool:
        return self.C1 is not None

    def correct(self, Pm: np.ndarray, arrived: np.ndarray, counts: np.ndarray | None = None) -> np.ndarray:
        """P_{k|k} from P_{k|k−1} with the sensors ``arrived`` (N, runs) bool: the core's Filter, or for
        N > 1 identical sensors the count update (eq. (14); ``counts`` = ``arrived.sum(0)`` if known)
        under the same Rescue."""
        if self.N == 1 or not self.identical:
            return self.filt.correct(Pm, arrived)
        flagged = self.filt.rescue.flag(Pm)
        P = kalman.update_counts(Pm, self.C1, self.R1, arrived.sum(axis=0) if counts is None else counts)
        if flagged.any():
            P = self.filt.rescue.apply(P, Pm, flagged, kalman.row_mask(arrived, self.filt.groups, self.filt.C.shape[0]))
        return P

    def step(self, P: np.ndarray, arrived: np.ndarray) -> np.ndarray:
        with np.errstate(over="ignore", invalid="ignore"):
            return self.correct(kalman.predict(P, self.filt.A, self.filt.Q), arrived)

    def correct_counts(self, Pm: np.ndarray, counts: np.ndarray) -> np.ndarray:
        """P_{k|k} from P_{k|k−1} with ``counts`` (runs,) of the N identical sensors arrived (eq. (14)), without
        the per-sensor pattern: the Filter's Rescue on the flagged runs in information form, whose
        information c·C1ᵀR1⁻¹C1 depends on the count only (equal to ``correct`` to rounding)."""
        flagged = self.filt.rescue.flag(Pm)
        P = kalman.update_counts(Pm, self.C1, self.R1, counts)
        idx = np.flatnonzero(flagged)
        if idx.size:
            P = P.copy()
            c = np.asarray(counts, dtype=float)[idx]
            prior = Pm[:, :, idx]
            fixed = prior.copy()  # no sensor arrived: P = P⁻ exactly
            some = c > 0
            if some.any():
                info1 = self.C1.T @ np.linalg.solve(self.R1, self.C1)
                fixed[:, :, some] = kalman.information_update(prior[:, :, some], info1[:, :, None] * c[some])
            P[:, :, idx] = kalman.clean_nonfinite(fixed)
        return P


class FusionEstimator(EstimatorModel):
    """``kind: fusion`` — fusion-centre strategies of Chiuso & Schenato (MF, IBF, OLPEF).

    Works from ``arrival`` traces whose streams are the system's sensors (``channel.kind: multi`` with
    ``system.sensors: N``). ``covariances`` reports ``strategies[0]``: ``filtered`` P_{k|k} and
    ``predicted`` P_{k+1|k} on netkf's time base, any state dimension.
    """

    accepts: ClassVar[frozenset[str]] = frozenset({"arrival"})
    quantities: ClassVar[tuple[str, ...]] = ("filtered", "predicted")

    kind: Literal["fusion"]
    strategies: list[Strategy] = Field(default_factory=lambda: list(STRATEGIES), min_length=1,
                                       description="strategies to simulate: mf (measurement fusion, eqs 6–9), ibf "
                                                   "(infinite bandwidth), olpef (open-loop partial estimates, eqs 10–11); "
                                                   "the first one is what covariances() reports")
    backend: Literal["auto", "numpy", "numba"] = Field(
        "auto", description="numpy (the reference) | numba (kernels generated for the system by kalman_codegen: MF's "
                            "count update, IBF's count steps from the full-information P, OLPEF's τ-histogram form, "
                            "equal to rounding; identical sensors, or MF = kf's compiled filter) | auto = numba for "
                            "chunks of ≥ 4e4 run-steps when numba is importable (identical sensors: the kernels read "
                            "the system's numbers from a vector, one compile per zero pattern; else kf's rule, ≥ 1e6)")

    def check(self, system, channel) -> None:
        """The channel's streams must be the system's sensors; OLPEF needs identical sensors and a stable A."""
        S = channel_streams(channel)
        sens = Sensors.of(system, S, "estimator.kind") if S is not None else None
        if "olpef" in self.strategies:
            rho = float(np.max(np.abs(np.linalg.eigvals(_as2d(system.A)))))
            if rho >= 1.0:
                raise ConfigError.at("estimator.strategies",
                                     f"olpef needs a stable A (its partial-estimate filters run in steady state); "
                                     f"spectral radius of system.A is {rho:.4g} ≥ 1 — use mf or ibf")
            if sens is not None and not sens.identical:
                raise ConfigError.at("estimator.strategies",
                                     "olpef's tables assume identical, independent sensors (system.sensors: N copies "
                                     "of one C, R); these sensors differ — use mf or ibf")

    def conventions(self, system, channel) -> dict[str, str]:
        return {"fusion": self.strategies[0], "streams": "stream i = sensor i of system.sensors"}

    def backend_used(self, system, channel, runs: int, horizon: int, steps=None, quantities=None) -> str:
        """The backend a chunk of ``runs`` × ``horizon`` runs on (recorded in the manifest)."""
        S = channel_streams(channel)
        sens = Sensors.of(system, S, "estimator.kind") if S is not None else None
        if sens is None:
            return "numpy"
        if sens.identical and (sens.N > 1 or self.strategies[0] != "mf"):
            return _mf_backend(self.backend, sens, runs * horizon)
        if self.strategies[0] == "mf":
            return kalman.choose_backend(self.backend, sens.filt, runs * horizon)
        return "numpy"

    def covariances(self, system, trace, steps, quantities=("filtered",)):
        """Yield ``(k, {quantity: P})`` of ``strategies[0]``, P shaped (n, n, runs), for k in ``steps``."""
        qs = kalman.check_quantities(quantities, self.quantities, "fusion")
        if "arrival" not in trace.kinds:
            raise ConfigError.at("channel.kind", "fusion needs an arrival trace (channel kind multi)")
        sens = Sensors.of(system, trace.sensors, "estimator.kind")
        P0 = initial_covariance(system)
        strat = self.strategies[0]
        want = sorted(set(int(k) for k in steps))
        A, Q = sens.filt.A, sens.filt.Q
        if strat == "mf":
            if sens.N == 1 or not sens.identical:
                backend = kalman.choose_backend(self.backend, sens.filt, trace.runs * trace.horizon)
                yield from sens.filt.run(P0, trace.arrival, want, qs, backend=backend)  # exactly kf
                return
            backend = _mf_backend(self.backend, sens, trace.runs * trace.horizon)
            yield from _mf_run(sens, P0, trace, want, qs, backend)
            return
        if strat == "olpef":
            if not sens.identical:
                raise ConfigError.at("estimator.strategies", "olpef needs identical sensors (system.sensors: N)")
            tables = _cached("olpef", sens, P0, lambda: OLPEFTables(A, sens.C1, Q, sens.R1, sens.N))
        else:
            ibf = _cached("ibf", sens, P0, lambda: IBF(sens, P0)) if sens.identical else IBF(sens, P0)
        if sens.identical and _mf_backend(self.backend, sens, trace.runs * trace.horizon) == "numba":
            yield from _history_compiled(strat, sens, ibf if strat == "ibf" else tables, trace, want, qs)
            return
        for k, tau in _taus(trace, want):
            t = k - 1
            if strat == "ibf":
                P = ibf.at(tau, t)
            else:
                Pf = tables.error_cov(np.ascontiguousarray(tau.T), np.full(tau.shape[1], t))
                P = np.ascontiguousarray(np.moveaxis(Pf, 0, -1))
            yield k, kalman.report(P, qs, A, Q)


    def estimates(self, system, trace, y, steps, quantities=("filtered",)):
        """Yield (k, {quantity: (x̂, P)}) of ``strategies[0]`` with the state (numpy path, ``kf.filter_estimates``):
        MF is the Kalman filter with the sensors that arrived (``Sensors.filt``, as :meth:`covariances`); IBF the
        same filter over the time-k view — sensor i's y^i_s for every s up to its last arrival — re-run from
        x̂_{0|0} = 0, P_{0|0} at each k (O(k) per step). OLPEF has none: its covariance assumes partial filters
        in steady state since −∞, which a simulation from x_0 does not have."""
        qs = kalman.check_quantities(quantities, self.quantities, "fusion")
        sens = Sensors.of(system, trace.sensors, "estimator.kind")
        P0 = initial_covariance(system)
        strat = self.strategies[0]
        if strat == "olpef":
            raise ConfigError.at("estimator.strategies", "olpef has no state-level estimates (its covariance assumes "
                                                         "partial filters in steady state since −∞); use mf or ibf")
        if strat == "mf":
            yield from filter_estimates(sens.filt, P0, trace.arrival, y, steps, qs)
            return
        for k in sorted({int(k) for k in steps}):
            t = np.arange(k)[None, :, None]
            last = np.where(trace.arrival[:, :k], t, -1).max(axis=1)  # (S, runs): last arrival's trace step
            (_, out), = filter_estimates(sens.filt, P0, t <= last[:, None, :], y, [k], qs)
            yield k, out


AUTO_MIN_RUN_STEPS = 40_000
"""``backend: auto`` runs the fusion kernels (identical sensors) on chunks of at least this many run-steps
(the paper figures' quick chunks, 200 runs × 200 steps, included: fig1 --quick 1.9 → 0.5 s CPU once numba is
loaded).
They read the system's numbers from a vector (``kalman_codegen`` symbolic kernels: the source depends on
the shapes and the zero / ±1 pattern only), so a grid over Q or the loss shares one compile per machine; what a process pays is numba's start (~0.3–0.8 s, once), which
the compiled IBF/OLPEF (3–6× numpy) repay within one 1000-run × 200-step chunk of the paper's figures.
(``kalman.AUTO_MIN_RUN_STEPS``, 1e6, is for kf's per-system kernels.)"""


def _mf_backend(backend: str, sens: Sensors, run_steps: int) -> str:
    """kalman.choose_backend for the count update; numba only where a kernel can be generated."""
    if backend == "auto":
        ok = run_steps >= AUTO_MIN_RUN_STEPS and kalman.numba_available() and sens.filt.sequential
        backend = "numba" if ok else "numpy"
        if ok and not kc.supported(sens.filt.A.shape[0], [tuple(range(sens.C1.shape[0]))]):
            return "numpy"
    b = kalman.choose_backend(backend, sens.filt, run_steps)
    if b == "numba" and not kc.supported(sens.filt.A.shape[0], [tuple(range(sens.C1.shape[0]))]):
        if backend == "numba":
            raise ConfigError.at("estimator.backend", f"no compiled MF kernel for n = {sens.filt.A.shape[0]} states, "
                                                      f"{sens.C1.shape[0]} rows per sensor (n ≤ {kc.MAX_N}, rows ≤ "
                                                      f"{kc.MAX_GROUP}); use backend: numpy or auto")
        return "numpy"
    return b


def trace_counts(trace, N: int) -> np.ndarray:
    """ℓ_k = Σ_i γ_k^i, (horizon, runs) integers: the channel's own counts (``sampling: counts``, no
    per-sensor pattern drawn) or the sum of the per-sensor trace (one pass)."""
    c = getattr(trace, "counts", None)
    if c is not None:
        return c
    return trace.arrival.sum(axis=0, dtype=np.uint8 if N < 256 else np.int32)


def _mf_run(sens: Sensors, P0: np.ndarray, trace, want, qs, backend: str = "numpy"):
    """MF with N identical sensors: the count update (eq. (14)), step k from trace step k − 1.

    The count ℓ is all MF reads (:func:`trace_counts`; a :class:`~netkf_cli.channels.multi.CountTrace`
    never draws its per-sensor pattern here), and the Rescue is the count form
    (:meth:`Sensors.correct_counts`). ``backend`` numba: the generated kernel
    (:func:`netkf_cli.linalg.kalman_codegen.kernel_counts`) advances the upper triangle of P between reported
    steps; flagged runs are redone on the numpy count update from P0, as :meth:`kalman.Filter.run` does."""
    runs = trace.runs
    counts = trace_counts(trace, sens.N)
    A, Q = sens.filt.A, sens.filt.Q
    P = np.repeat(np.asarray(P0, dtype=float)[:, :, None], runs, axis=2)
    if backend == "numba":
        yield from _mf_compiled(sens, P, counts, want, qs)
        return
    t = 0
    for k in want:
        while t < k:
            with np.errstate(over="ignore", invalid="ignore"):
                P = sens.correct_counts(kalman.predict(P, A, Q), counts[t])
            t += 1
        yield k, kalman.report(P, qs, A, Q)


def _mf_compiled(sens: Sensors, P: np.ndarray, counts: np.ndarray, want, qs):
    A, Q = sens.filt.A, sens.filt.Q
    n = A.shape[0]
    adv = kc.kernel_counts(A, sens.C1, Q, sens.R1, None)  # symbolic: one kernel per shape, the system in sv
    sv = kc.system_vector(A, sens.C1, Q, sens.R1, sens.filt.rescue.limit)
    P_init = P.copy()
    T = kc.pack(P)
    cnt = np.ascontiguousarray(counts)
    flag = np.zeros(P.shape[-1], dtype=np.bool_)

    def step(Pk, tt, ix):
        with np.errstate(over="ignore", invalid="ignore"):
            return sens.correct_counts(kalman.predict(Pk, A, Q), cnt[tt, ix])

    redo = kalman.FlaggedRuns(P_init, step)  # runs flagged for the rescue: on the numpy core
    t = 0
    for k in want:
        adv(T, cnt, t, k, flag, sv)
        out = redo.fill(kc.unpack(T, n), flag, k)
        t = k
        yield k, kalman.report(out, qs, A, Q)


_MODELS: dict = {}
"""IBF / OLPEFTables per strategy and system (identical sensors), kept across the chunks a process runs: their
tables (IBF's full-information P_{j|j}, OLPEF's lagged covariances) depend on the system only."""


def _cached(strategy: str, sens: Sensors, P0, make):
    f = sens.filt
    key = (strategy, sens.N, float(f.rescue.limit)) + tuple((x.shape, x.tobytes()) for x in
                                                           map(np.asarray, (f.A, f.Q, sens.C1, sens.R1, P0)))
    if key not in _MODELS:
        if len(_MODELS) >= 64:
            _MODELS.clear()
        _MODELS[key] = make()
    return _MODELS[key]


def _history_compiled(strat: str, sens: Sensors, model, trace, want, qs):
    """IBF / OLPEF with N identical sensors on the generated kernels (:func:`kalman_codegen.source_ibf`,
    :func:`~netkf_cli.linalg.kalman_codegen.source_olpef`): per reported step, each run's τ from the last
    arrivals (N, runs) and the evaluation in one compiled pass (IBF: K count steps from the
    full-information P; OLPEF: the quadratic form in the τ histogram). IBF runs flagged by the Rescue
    test are redone on the numpy :class:`IBF`."""
    A, Q = sens.filt.A, sens.filt.Q
    n, N, runs = A.shape[0], sens.N, trace.runs
    last = np.full((N, runs), -1, dtype=np.int32)
    out = np.empty((n * (n + 1) // 2, runs))
    if strat == "ibf":
        kern = kc.kernel_ibf(A, sens.C1, Q, sens.R1, None)  # symbolic, as _mf_compiled
        sv = kc.system_vector(A, sens.C1, Q, sens.R1, sens.filt.rescue.limit)
        full = model.packed_full(trace.horizon)
        cum = np.zeros(trace.horizon + 2, dtype=np.int64)
        flag = np.zeros(runs, dtype=np.bool_)
    else:
        kern = kc.kernel_olpef(n)
        vals, cnts = np.zeros(N, dtype=np.int64), np.zeros(trace.horizon + 2)

        iu = np.triu_indices(n)

        def tabs():  # packed upper triangles (kalman_codegen.source_olpef)
            sw = np.swapaxes
            D = 0.5 * (model.diagM + sw(model.diagM, -1, -2)) - model.linM - sw(model.linM, -1, -2)
            TS = 0.5 * (model.TM + sw(model.TM, -1, -2))
            return (np.ascontiguousarray(model.sxxM[iu]), np.ascontiguousarray(D[:, iu[0], iu[1]]),
                    np.ascontiguousarray(TS[:, :, iu[0], iu[1]]))
        tab = tabs()
    blocks = _Blocks(trace)
    t = 0
    for k in want:
        tt = k - 1
        for blk, off, s0, s1 in blocks.segments(t, k):  # the last segment's evaluation is the one kept
            if strat == "ibf":
                flag[:] = False
                kern(blk, off, last, s0, s1, full, out, flag, cum, sv)
            else:
                worst = kern(blk, off, last, s0, s1, *tab, out, vals, cnts)
        if strat == "ibf":
            P = kc.unpack(out, n)
            idx = np.flatnonzero(flag)
            if idx.size:
                P[:, :, idx] = model.at(tt - last[:, idx], tt)
        else:
            if worst > model._K:
                model._extend(int(worst))
                tab = tabs()
                kern(blk, off, last, k, k, *tab, out, vals, cnts)
            P = kc.unpack(out, n)
        t = k
        yield k, kalman.report(P, qs, A, Q)


class _Blocks:
    """Blocks of a trace's arrivals for a pass over time: the whole array of an eager (or materialised)
    trace, else the trace's ``steps(t0, t1)`` in blocks of ~RAW_BLOCK arrivals (a lazily drawn
    :class:`~netkf_cli.channels.multi.SensorTrace` is never materialised whole)."""

    def __init__(self, trace):
        self.trace, self.T = trace, trace.horizon
        lazy = hasattr(trace, "steps") and not getattr(trace, "materialized", True)
        self.B = block_steps(self.T, trace.runs, trace.sensors) if lazy else self.T
        self.blk, self.b0, self.b1 = (None, 0, 0) if lazy else (trace.arrival, 0, self.T)

    def segments(self, t: int, k: int):
        """(block, its first step, s0, s1) covering the steps [t, k)."""
        while t < k:
            if not self.b0 <= t < self.b1:
                self.b0, self.b1 = t, min(self.T, t + self.B)
                self.blk = np.ascontiguousarray(self.trace.steps(self.b0, self.b1))
            s1 = min(k, self.b1)
            yield self.blk, self.b0, t, s1
            t = s1

    def step(self, t: int) -> np.ndarray:
        """Arrivals of step t, (N, runs)."""
        for blk, off, _, _ in self.segments(t, t + 1):
            return blk[:, t - off]


def _taus(trace, want):
    """(k, τ) for k in ``want``: τ (N, runs) int32 = steps since each sensor's last arrival at trace step
    k − 1 (k when nothing arrived yet: only P0 is known), updated incrementally (memory O(N · runs), the
    trace read in blocks)."""
    blocks = _Blocks(trace)
    last = np.full((trace.sensors, trace.runs), -1, dtype=np.int32)
    t = 0
    for k in want:
        while t < k:
            np.copyto(last, np.int32(t), where=blocks.step(t))
            t += 1
        yield k, (k - 1) - last


# ----------------------------------------------------------------------------------------
# IBF
# ----------------------------------------------------------------------------------------


class IBF:
    """The infinite-bandwidth fusion centre on the core: P^IBF_{k|k} from the times since arrival τ."""

    def __init__(self, sens: Sensors, P0: np.ndarray):
        self.sens = sens
        self.full = [np.asarray(P0, dtype=float)[:, :, None]]  # full-information P_{j|j}, j = 0, 1, …
        self._packed = None

    def packed_full(self, J: int) -> np.ndarray:
        """P_{j|j}, j = 0 … J, packed upper triangles (J + 1, n(n+1)/2), C-contiguous (the compiled kernel's
        table; kept, so the chunks of a run compute it once)."""
        if self._packed is None or self._packed.shape[0] <= J:
            self._packed = np.ascontiguousarray(np.stack([kc.pack(self._full(j))[:, 0] for j in range(J + 1)]))
        return self._packed[: J + 1]

    def _full(self, j: int) -> np.ndarray:
        """P_{j|j} with every sensor at every step (one run). The step is a function of P alone, so once two
        consecutive P_{j|j} are equal bit for bit every later one is too (from P0 = P̄, the default, at once):
        the rest of the table is that P, without stepping (a 200-step table ~30 -> ~1 ms)."""
        ones = np.ones((self.sens.N, 1), dtype=bool)
        while len(self.full) <= j:
            last = self.full[-1]
            if len(self.full) > 1 and np.array_equal(last, self.full[-2]):
                self.full.append(last)  # a fixed point of the step: P_{j+1} = step(P_j) = step(P_{j-1}) = P_j, bit for bit
            else:
                self.full.append(self.sens.step(last, ones))
        return self.full[j]

    def at(self, tau: np.ndarray, t: int) -> np.ndarray:
        """P^IBF at step t + 1 (trace step t), (n, n, runs), from τ (N, runs): rows grouped by reach
        (≤ 4, ≤ 8, ≤ 16, the rest) so the work is ~Σ_rows reach, not rows × max reach."""
        runs = tau.shape[1]
        reach = np.minimum(tau.max(axis=0), t + 1) if runs else np.zeros(0, dtype=np.int32)
        top = int(reach.max()) if runs else 0
        if runs < 2048:
            return self._core(tau, t, top)
        n = self.sens.filt.A.shape[0]
        out = np.empty((n, n, runs))
        lo = -1
        for hi in (4, 8, 16, top):
            if hi <= lo:
                continue
            sel = np.flatnonzero((reach > lo) & (reach <= hi))
            if sel.size:
                out[:, :, sel] = self._core(tau[:, sel], t, int(reach[sel].max()))
            lo = hi
        return out

    def _core(self, tau: np.ndarray, t: int, K: int) -> np.ndarray:
        """From the full-information P at step t + 1 − K, K steps with the sensors {i : τ_i ≤ b},
        b = K − 1 … 0 (trace steps t − b)."""
        P = np.repeat(self._full(t + 1 - K), tau.shape[1], axis=2)
        for b in range(K - 1, -1, -1):
            P = self.sens.step(P, tau <= b)
        return P


# ----------------------------------------------------------------------------------------
# OLPEF
# ----------------------------------------------------------------------------------------


class OLPEFTables:
    """Lagged covariances of the stationary (x_t, z^a_t, z^b_t) for N identical sensors (eqs (10)–(11)).

    Steady-state CKF: P_m (prediction), per-sensor gain L^i = P_m Cᵀ (R + N C P_m Cᵀ)⁻¹ (the i-th
    block of P_m C̄ᵀ (C̄ P_m C̄ᵀ + I⊗R)⁻¹), F = (I − N L^1 C) A. Partial estimates
    z^i_{t+1} = F z^i_t + L^i (C A x_t + C w_t + v^i_{t+1}). The joint (x, z^a, z^b) is linear with
    transition 𝒜 and stationary covariance Σ (Lyapunov); Cov(X_{s+d}, X_s) = 𝒜^d Σ.
    """

    def __init__(self, A, C, Q, R, N: int):
        A, C, Q, R = map(_as2d, (A, C, Q, R))
        rho = float(np.max(np.abs(np.linalg.eigvals(A))))
        if rho >= 1.0:
            raise ConfigError.at("system.A", f"OLPEF's stationary analysis needs a stable A; spectral radius {rho:.4g} ≥ 1")
        n = A.shape[0]
        self.A, self.n, self.N = A, n, N
        Pm = p_m(A, C, Q, R, N)
        L1 = np.linalg.solve(R + N * C @ Pm @ C.T, C @ Pm).T  # (n, m)
        F = (np.eye(n) - N * L1 @ C) @ A
        Z = np.zeros((n, n))
        LCA = L1 @ C @ A
        self.calA = np.block([[A, Z, Z], [LCA, F, Z], [LCA, Z, F]])
        G = np.vstack([np.eye(n), L1 @ C, L1 @ C])
        W = G @ Q @ G.T
        W[n : 2 * n, n : 2 * n] += L1 @ R @ L1.T
        W[2 * n :, 2 * n :] += L1 @ R @ L1.T
        self.Sigma = scipy.linalg.solve_discrete_lyapunov(self.calA, W)
        self.Sigma = (self.Sigma + self.Sigma.T) / 2
        self.Pm, self.L1, self.F = Pm, L1, F
        self._K = -1
        self._extend(16)

    def _extend(self, K: int) -> None:
        """Tables for lags 0..K: tr(Cov(x_t, A^a z_{t−a})), tr(A^a (C_same(0) − C_cross(0)) A^aᵀ), T_ab."""
        if K <= self._K:
            return
        n = self.n
        x, za, zb = slice(0, n), slice(n, 2 * n), slice(2 * n, 3 * n)
        Apow = np.empty((K + 1, n, n))
        G = np.empty((K + 1, 3 * n, 3 * n))  # 𝒜^d Σ
        Apow[0], G[0] = np.eye(n), self.Sigma
        for d in range(1, K + 1):
            Apow[d] = self.A @ Apow[d - 1]
            G[d] = self.calA @ G[d - 1]
        Cxz = G[:, x, za]  # Cov(x_{s+d}, z_s)
        Ccross = G[:, za, zb]  # Cov(z^a_{s+d}, z^b_s)
        self.sxx = float(np.trace(self.Sigma[x, x]))
        # linear term: tr(Cov(x_t, A^a z_{t−a})) = tr(Cxz(a) A^aᵀ)
        self.lin = np.einsum("dij,dij->d", Cxz, Apow)
        diag0 = self.Sigma[za, za] - self.Sigma[za, zb]
        self.diag = np.einsum("dij,jk,dik->d", Apow, diag0, Apow)
        # T_ab = tr(A^a Cov(z^i_{t−a}, z^j_{t−b}) A^bᵀ); Cov = Ccross(a−b)ᵀ (a ≥ b) or Ccross(b−a) (a < b)
        a = np.arange(K + 1)
        dmat = np.abs(a[:, None] - a[None, :])
        Cab = np.where((a[:, None] >= a[None, :])[..., None, None], np.swapaxes(Ccross[dmat], -1, -2), Ccross[dmat])
        self.T = np.einsum("aij,abjk,bik->ab", Apow, Cab, Apow)
        # the same tables as matrices (for the full error covariance, any n)
        self.sxxM = self.Sigma[x, x]
        self.linM = np.einsum("dij,dkj->dik", Cxz, Apow)  # Cov(x_t, A^a z_{t−a}) = Cxz(a) A^aᵀ
        self.diagM = np.einsum("dij,jk,dlk->dil", Apow, diag0, Apow)
        self.TM = np.einsum("aij,abjk,blk->abil", Apow, Cab, Apow)
        self._K = K

    def error_trace(self, tau: np.ndarray, t: np.ndarray) -> np.ndarray:
        """tr Var(x_t − Σ_i A^{τ_i} z^i_{t−τ_i}) per row, eq. (11); sensors with nothing received yet
        (τ_i = t+1) contribute the estimate 0."""
        received = tau <= t[:, None]
        K = int(np.where(received, tau, 0).max()) if tau.size else 0
        self._extend(K)
        rows = tau.shape[0]
        tc = np.where(received, tau, K + 1).astype(np.int64)
        flat = (np.arange(rows, dtype=np.int64)[:, None] * (K + 2) + tc).ravel()
        h = np.bincount(flat, minlength=rows * (K + 2)).reshape(rows, K + 2)[:, : K + 1].astype(float)
        T = self.T[: K + 1, : K + 1]
        quad = ((h @ T) * h).sum(axis=1)
        return self.sxx - 2 * h @ self.lin[: K + 1] + h @ self.diag[: K + 1] + quad


    def error_cov(self, tau: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Var(x_t − Σ_i A^{τ_i} z^i_{t−τ_i}) per row as a matrix, (rows, n, n), eq. (11) — the
        matrix form of :meth:`error_trace` (same histogram h of τ)."""
        received = tau <= t[:, None]
        K = int(np.where(received, tau, 0).max()) if tau.size else 0
        self._extend(K)
        rows = tau.shape[0]
        tc = np.where(received, tau, K + 1).astype(np.int64)
        flat = (np.arange(rows, dtype=np.int64)[:, None] * (K + 2) + tc).ravel()
        h = np.bincount(flat, minlength=rows * (K + 2)).reshape(rows, K + 2)[:, : K + 1].astype(float)
        n, L = self.n, K + 1
        # the contractions as GEMMs over row blocks (einsum without BLAS was ~10× slower; memory O(block·L·n²))
        lin = (h @ self.linM[:L].reshape(L, n * n)).reshape(rows, n, n)
        out = self.sxxM[None] - lin - np.swapaxes(lin, 1, 2) + (h @ self.diagM[:L].reshape(L, n * n)).reshape(rows, n, n)
        TM = self.TM[:L, :L].transpose(0, 2, 3, 1).reshape(L, n * n * L)  # [a, (i, j, b)]
        for r0 in range(0, rows, 2048):
            hb = h[r0 : r0 + 2048]
            out[r0 : r0 + 2048] += np.einsum("rkb,rb->rk", (hb @ TM).reshape(hb.shape[0], n * n, L), hb).reshape(-1, n, n)
        return (out + np.swapaxes(out, 1, 2)) / 2
