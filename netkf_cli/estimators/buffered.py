"""Buffered optimal estimator for raw measurements (Shi, Xie & Murray 2009, Sec. 3, Prop. 3.1).

The sensor sends y_k; packets are delayed (eq. 3) and the estimator keeps a packet iff its
delay is within the buffer (``channel.convention``). At time k the estimator re-runs the
modified Kalman filter (MKF, Sec. 3.1) from the oldest newly arrived packet (Prop. 3.1), so

    P_{k|k} = f_k ∘ f_{k−1} ∘ … ∘ f_1 (P_{0|0}),   f_t = g̃∘h if y_t is available at time k, else h,

i.e. P_{k|k} is the MKF run over the *time-k view* of the arrival pattern γ_t^{(k)} (Lemma 3.7's
composition, footnote 2): the Kalman filter with intermittent observations
(:class:`netkf_cli.linalg.kalman.Filter`, the same one ``kf`` runs) fed with the time-k availabilities.
On a zero-delay (pure-loss) trace it IS ``kf``, step for step. P_{0|0} =
:func:`netkf_cli.linalg.riccati.initial_covariance` (``system.P0``; unset = P̄); step k is the time of the
newest measurement y_k; quantities ``filtered`` P_{k|k} and ``predicted`` P_{k+1|k} = h(P_{k|k}).

Packets (``packet``):
* ``measurement`` — a packet carries y_t (all of y_t: one packet stream; Sec. 3);
* ``pair`` — a packet carries (y_t, y_{t−1}) (Appendix B, C not invertible but [C; CA] is):
  y_t is available at time k iff packet t or packet t + 1 is kept by k;
* ``auto`` — ``measurement`` if C is invertible, else ``pair`` when [C; CA] is.

Overflow is the core's one policy (:class:`netkf_cli.linalg.kalman.Rescue`, via ``Filter``): a run whose
prior is nearly overflowed is updated in information form; a non-finite run is ∞ (P ≰ M).
"""

from __future__ import annotations

from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from netkf_cli.linalg import kalman
from netkf_cli.channels.delay import (CONVENTION_HELP, DEFAULT_CONVENTION, LOST, delay_label, kept_at, kept_by,
                                      max_kept_delay, trace_delays, trace_max_kept_delay)
from netkf_cli.core.errors import ConfigError
from netkf_cli.estimators.kf import channel_streams, filter_estimates
from netkf_cli.linalg.riccati import initial_covariance
from netkf_cli.core.spec import EstimatorModel
from netkf_cli.core.system import LinearSystem

PacketKind = Literal["auto", "measurement", "pair"]
BackendKind = Literal["numpy", "numba", "auto"]


class BufferedEstimator(EstimatorModel):
    """``kind: buffered`` — raw measurements, optimal re-run of the MKF over the buffer (Prop. 3.1)."""

    accepts: ClassVar[frozenset[str]] = frozenset({"delay", "arrival"})
    quantities: ClassVar[tuple[str, ...]] = ("filtered", "predicted")

    kind: Literal["buffered"] = Field(description="raw measurements, MKF re-run over the receive buffer (Shi 2009, Prop. 3.1)")
    packet: PacketKind = Field(
        "auto",
        description="what a packet carries: measurement = y_k (Sec. 3, any C), pair = (y_k, y_{k-1}) "
        "(Appendix B); auto = pair iff C is not invertible but [C; CA] is, else measurement",
    )
    backend: BackendKind = Field(
        "auto",
        description="numpy (the core, reference) | numba (the core's compiled filter, kalman.Filter.run: equal "
        "to rounding) | auto = numba for chunks of ≥ 1e6 run-steps when numba is importable (kalman.choose_backend)",
    )

    def span(self, s: LinearSystem) -> int:
        """Number of consecutive measurements a packet carries (1 or 2)."""
        return packet_span(s, self.packet)

    def resolved_backend(self, system: LinearSystem, run_steps: int = kalman.AUTO_MIN_RUN_STEPS) -> str:
        """The backend a chunk of ``run_steps`` run-steps runs on (``kalman.choose_backend``)."""
        return kalman.choose_backend(self.backend, kalman.Filter.of(system, 1), run_steps)

    def backend_used(self, system: LinearSystem, channel, runs: int, horizon: int, steps=None, quantities=None) -> str:
        """The backend a chunk of ``runs`` × ``horizon`` runs on (recorded in the manifest)."""
        return self.resolved_backend(system, runs * horizon)

    def check(self, system: LinearSystem, channel) -> None:
        """One packet stream carrying all of y_k (the buffer model of Sec. 2.3); a packet kind that
        fits C; a usable backend."""
        single_link(system, channel, "buffered")
        packet_span(system, self.packet)
        self.resolved_backend(system)

    def conventions(self, system: LinearSystem, channel) -> dict[str, str]:
        """Buffer length D, keep rule, packet content and delay law (the numbers depend on each)."""
        return delay_conventions(channel, packet="(y_k, y_k-1)" if packet_span(system, self.packet) == 2 else "y_k")

    def covariances(self, system: LinearSystem, trace, steps, quantities=("filtered",)):
        """Yield (k, {quantity: P (n, n, runs)}): the MKF over the time-k view (Prop. 3.1).

        The trace's ``delay`` (or, for a pure-loss trace, ``arrival`` as delay 0 / lost) and
        ``meta['buffer']``/``meta['convention']`` (no buffer in meta: every delay is kept) give
        γ_s^{(k)} = [d_s ≤ min(k − s, D_max)] (eq. 4). Packets older than the oldest packet still in
        flight at k (in any run) have their final status, so one pass over the final pattern carries
        the common prefix and each requested k re-runs only the steps from that packet on, from a
        copy (the re-run of Prop. 3.1).
        """
        qs = kalman.check_quantities(quantities, self.quantities, "buffered")
        yield from buffered_covariances(system, trace, steps, packet_span(system, self.packet), qs,
                                        backend=self.backend)

    def estimates(self, system: LinearSystem, trace, y, steps, quantities=("filtered",)):
        """Yield (k, {quantity: (x̂, P)}): the MKF over the time-k view run with the state (``kf.filter_estimates``:
        the same ``Filter`` steps as :meth:`covariances`, the gain of each step from that recursion), from
        x̂_{0|0} = 0, P_{0|0} at every k (the re-run of Prop. 3.1 from the start: O(k) per step; numpy path).
        ``y`` (m, horizon+1, runs) the sensor's measurements; a pair packet's y_t is used when packet t or t + 1
        is kept."""
        qs = kalman.check_quantities(quantities, self.quantities, "buffered")
        span = packet_span(system, self.packet)
        d = trace_delays(trace)  # int32, only compared
        Dmax = trace_max_kept_delay(trace)
        f = kalman.Filter.of(system, 1, "estimator.kind")
        P0 = initial_covariance(system)
        for k in sorted({int(k) for k in steps}):
            avail = availability(kept_by(d, k, Dmax), span)[:k]
            (_, out), = filter_estimates(f, P0, avail[None], y, [k], qs)
            yield k, out

    def updates(self, system: LinearSystem, trace, steps):
        """Yield (k, R_k (runs,)): the filter recursions (MKF runs, Prop. 3.1) run at time k — 1 + the age
        of the oldest packet that arrives at k and is kept, 1 when none arrives (measurement packets).

        The hook of the ``updates`` metric (:mod:`netkf_cli.metrics.updates`): an estimator that reports
        how many filter recursions it runs per step defines ``updates(system, trace, steps)``."""
        self.check_updates(system)
        yield from mkf_runs(trace, steps)

    def check_updates(self, system: LinearSystem, path: str = "estimator") -> None:
        """Refuse what :meth:`updates` cannot count (the ``updates`` metric's check, at validate): pair packets,
        asked for or chosen by ``auto``."""
        if packet_span(system, self.packet) == 1:
            return
        why = ("packet: auto chose pair packets (y_k, y_k-1), as C is not invertible but [C; CA] is"
               if self.packet == "auto" else "got packet: pair")
        raise ConfigError.at(f"{path}.packet", f"update counts are defined for measurement packets (span 1) only "
                                               f"({why}); set packet: measurement to count them")


MKF_DELAY_LOOP_MAX = 64
"""mkf_runs: below this D_max, a pass per delay value (D_max + 1 vectorized passes; compiled per k where numba
imports) instead of ``np.maximum.at``'s scatter (≈ 3× slower per packet at D_max ≤ 15; tests/shi2009 check both
give the same maxima)."""


def _oldest_compiled():
    """:func:`netkf_cli.channels._delay_numba.oldest_arrival` where numba imports, else None."""
    try:
        from netkf_cli.channels import _delay_numba  # optional: needs numba (numpy passes otherwise)
    except ImportError:
        return None
    return _delay_numba.oldest_arrival


def mkf_runs(trace, steps, compiled: bool | None = None):
    """(k, R_k) for k in ``steps``: R_k = 1 + max{d_s : s + d_s = k, d_s ≤ D_max} (1 when no kept packet
    arrives at k), from the trace's delays (packet s = 1 … horizon at row s − 1) and its buffer.

    ``compiled`` (None = where numba imports, True likewise, False = numpy): at each k a compiled pass per delay
    value over the rows that can arrive at k (:func:`netkf_cli.channels._delay_numba.oldest_arrival`, vectorized
    over the runs; no (horizon, runs) table); the counts are integers, so every path gives the same R_k (tested)."""
    d = trace_delays(trace)
    T, runs = d.shape
    Dmax = trace_max_kept_delay(trace)
    kernel = _oldest_compiled() if (compiled is None or compiled) and Dmax < MKF_DELAY_LOOP_MAX else None
    if kernel is not None:  # min(D_max, k − 1) + 1 passes at each k: for short buffers (a long one scatters)
        d = np.ascontiguousarray(d, dtype=np.int32)
        for k in steps:
            _check_step(k, T)
            row = np.zeros(runs, dtype=np.int32)
            kernel(d, int(Dmax), int(k), row)
            yield int(k), 1.0 + row  # float64, as the numpy table gives
        return
    oldest = np.zeros((T + 1, runs), dtype=np.int64)  # row k: the largest kept delay arriving at time k
    if Dmax < MKF_DELAY_LOOP_MAX:  # a pass per delay value δ, ascending: the last write at (k, run) is the largest
        for delta in range(min(Dmax, T - 1) + 1):  # packet s (row s − 1) with d_s = δ arrives at k = s + δ ≤ T
            np.copyto(oldest[1 + delta:], delta, where=d[: T - delta] == delta)
    else:  # a long buffer: scatter each kept packet's delay to its arrival time (the same maxima)
        d = d.astype(np.int64)
        arrive = np.arange(1, T + 1)[:, None] + d
        t_idx, r_idx = np.nonzero((d <= Dmax) & (arrive <= T))
        np.maximum.at(oldest, (arrive[t_idx, r_idx], r_idx), d[t_idx, r_idx])
    for k in steps:
        _check_step(k, T)
        yield int(k), 1.0 + oldest[int(k)]


def _check_step(k, T: int) -> None:
    if not 1 <= k <= T:
        raise ValueError(f"steps must lie in 1..{T}, got {k}")


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


def delay_conventions(channel, packet: str) -> dict[str, str]:
    """The labels of a delay-buffer estimator's numbers: D, keep rule, packet content, delay law."""
    out = {}
    recorded = channel is not None and channel.kind == "trace" and getattr(channel, "values", "") == "delay"
    if channel is not None and (channel.kind == "delay" or recorded):
        conv = getattr(channel, "convention", DEFAULT_CONVENTION)
        out["buffer"] = f"D = {channel.D if channel.kind == 'delay' else channel.buffer}"
        out["convention"] = f"{conv} (d {'≤' if conv == 'delay_le_D' else '<'} D kept)"
    elif channel is not None and channel.kind == "bernoulli":
        out["buffer"] = "none (pure loss: delay 0)"
    out["packet"] = packet
    if channel is not None:
        out["delay law"] = delay_label(channel)
    return out


def single_link(system: LinearSystem, channel, kind: str) -> None:
    """Refuse a multi-stream channel: here one packet stream carries the whole measurement y_k
    (``kalman.stream_rows`` with one stream), delayed as one packet."""
    S = channel_streams(channel)
    if S is None or S == 1:
        kalman.stream_rows(system, 1, "estimator.kind")
        return
    raise ConfigError.at("estimator.kind", f"the {kind} estimator reads one packet stream (all of y_k in one "
                         f"delayed packet), but channel {channel.kind!r} has {S} arrival streams: use a "
                         "single-link channel (delay, bernoulli, gilbert_elliott, trace with one column), or "
                         "estimator kind kf / fusion for one stream per sensor")


# ---------------------------------------------------------------------------------------------
# The MKF over the time-k view, on the Kalman core
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


def mkf(f: kalman.Filter, P: np.ndarray, avail: np.ndarray, backend: str = "numpy") -> np.ndarray:
    """P_{t|t} after the MKF steps t = 1 … len(avail) from ``P`` (n, n, runs): the core's filter
    (``Filter.run``) with γ_t = a_t, on ``backend`` (numpy: ``f.step`` per step; numba: the core's
    compiled filter, rescue-flagged runs on the numpy core)."""
    if avail.shape[0] == 0:
        return P
    (_, out), = f.run(P, np.asarray(avail, dtype=bool)[None], [avail.shape[0]], ("filtered",), backend=backend)
    return out["filtered"]


def covariance_from_kept(s: LinearSystem, kept: np.ndarray, span: int, P0: np.ndarray | None = None) -> np.ndarray:
    """P_{k|k} (n, n, runs) from the time-k kept indicators ``kept`` (k, runs) (Prop. 3.1), numpy core."""
    kept = np.asarray(kept, dtype=bool)
    P0 = initial_covariance(s) if P0 is None else np.asarray(P0, dtype=float)
    P = np.repeat(P0[:, :, None], kept.shape[1], axis=2)
    return mkf(kalman.Filter.of(s, 1), P, availability(kept, span))


def buffered_covariances(s: LinearSystem, trace, steps, span: int = 1, quantities=("filtered",),
                         backend: str = "numpy"):
    """Generator of (k, {quantity: P_k}) for ``BufferedEstimator.covariances`` (see there).

    ``backend`` (numpy | numba | auto, :func:`netkf_cli.linalg.kalman.choose_backend`) is the core filter's:
    every MKF pass is ``kalman.Filter.run`` (:func:`mkf`).
    """
    T, runs = trace.horizon, trace.runs
    d = trace_delays(trace)
    Dmax = trace_max_kept_delay(trace)
    f = kalman.Filter.of(s, 1, "estimator.kind")
    be = kalman.choose_backend(backend, f, runs * T)
    P0 = initial_covariance(s)
    steps = sorted(int(k) for k in steps)
    for k in steps:
        if not 1 <= k <= T:
            raise ValueError(f"steps must lie in 1..{T}, got {k}")
    if len(steps) == 1:  # one pass over the time-k view
        k = steps[0]
        yield from f.run(P0, availability(kept_by(d, k, Dmax), span)[None], [k], quantities, backend=be)
        return
    final = d <= Dmax  # (T, runs): final kept status of packet t + 1
    a_final = availability(final, span)
    # packet s is in flight (kept later, not yet arrived) at times s … s + d_s − 1: the latest such
    # time over runs, per packet (−1: never in flight)
    dmax = np.where(final, d, 0).max(axis=1, initial=0).astype(np.int64)  # longest kept delay per packet
    last = np.where(dmax > 0, np.arange(1, T + 1) + dmax - 1, -1)
    base = np.repeat(P0[:, :, None], runs, axis=2)
    done = 0  # MKF steps of the final pattern applied to ``base``
    for k in steps:
        # packets before the oldest one still in flight at k have their final status; a pair packet
        # (span 2) also needs the next packet's status, and packet k + 1 does not exist yet at k
        inflight = np.flatnonzero(last[:k] >= k)
        j = int(inflight[0]) if len(inflight) else k  # packets 1..j are final at time k
        b = max(0, j - (span - 1))  # steps 1..b use final statuses (non-decreasing in k)
        if b < done:  # pragma: no cover - cannot happen (the oldest in-flight packet only moves on)
            base, done = np.repeat(P0[:, :, None], runs, axis=2), 0
        base = mkf(f, base, a_final[done:b], be)
        done = b
        P = base if b == k else mkf(f, base, availability(kept_by(d, k, Dmax, b), span), be)
        yield k, kalman.report(P, quantities, f.A, f.Q)


# ---------------------------------------------------------------------------------------------
# State-level simulation: the literal Prop. 3.1 estimator on simulated x_k, y_k
# ---------------------------------------------------------------------------------------------


def _mkf_full(f: kalman.Filter, x, P, y, gam):
    """One MKF step (Sec. 3.1) on the core: x (runs, n), P (n, n, runs), y (runs, m), gam (runs,) bool."""
    xm = x @ f.A.T
    Pm, Pn = f.step(P, gam[None])
    with np.errstate(invalid="ignore", over="ignore"):
        K = kalman.gain(Pm, f.C, f.R) * gam.astype(float)[None, None, :]  # γ K, (n, m, runs)
        xn = xm + np.einsum("iar,ra->ri", K, y - xm @ f.C.T)
    return xn, Pn


def simulate_states(s: LinearSystem, channel, span: int, runs: int, horizon: int, rng: np.random.Generator,
                    P0: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Simulate x_k, y_k, packet delays and the estimator of Prop. 3.1 literally, at k = ``horizon``.

    Delays come from the channel model's own sampler (``channel.delay.sample``; bernoulli:
    d = 0 or lost), independent of the inverse-CDF trace sampler. At every time k the estimator
    finds the oldest measurement that became available at k (new packets with d_s = k − s ≤ D_max;
    a pair packet also brings y_{s−1}) and re-runs the MKF from there, reusing its stored
    (x̂_t, P_t) for older t (Prop. 3.1). Returns at k = horizon: ``x``, ``xhat``, ``e`` (runs, n),
    ``P`` (runs, n, n), ``mkf_runs`` (horizon, runs), ``delays`` (horizon, runs).
    """
    f = kalman.Filter.of(s, 1)
    n, m = s.n, s.m
    P0 = initial_covariance(s) if P0 is None else np.asarray(P0, dtype=float)
    D, conv = channel.D, channel.convention
    if channel.kind == "bernoulli":
        delays = np.where(rng.random((horizon, runs)) < channel.arrival, 0, LOST).astype(np.int64)
    else:
        delays = channel.delay.sample(rng, (horizon, runs)).astype(np.int64)
    LQ, LR, LP = _psd_sqrt(s.Q), _psd_sqrt(s.R), _psd_sqrt(P0)
    x = rng.standard_normal((runs, n)) @ LP.T
    xs = np.zeros((horizon + 1, runs, n))  # stored estimates x̂_t (index t), t = 0..k
    Ps = np.zeros((horizon + 1, n, n, runs))
    Ps[0] = P0[:, :, None]
    ys = np.zeros((horizon + 1, runs, m))
    avail_prev = np.zeros((horizon + 1, runs), dtype=bool)  # a_t as known at k − 1
    mkf_runs = np.zeros((horizon, runs), dtype=np.int64)
    for k in range(1, horizon + 1):
        x = x @ s.A.T + rng.standard_normal((runs, n)) @ LQ.T
        ys[k] = x @ s.C.T + rng.standard_normal((runs, m)) @ LR.T
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
            xn, Pn = _mkf_full(f, xs[t - 1], Ps[t - 1], ys[t], avail_now[t])
            xs[t] = np.where(act[:, None], xn, xs[t])
            Ps[t] = np.where(act[None, None, :], Pn, Ps[t])
        avail_prev = avail_now
    return {"x": x, "xhat": xs[horizon], "e": x - xs[horizon], "P": np.moveaxis(Ps[horizon], -1, 0),
            "mkf_runs": mkf_runs, "delays": delays}


def _psd_sqrt(X: np.ndarray) -> np.ndarray:
    w, V = np.linalg.eigh((X + X.T) / 2)
    return V * np.sqrt(np.clip(w, 0, None))


__all__ = ["BufferedEstimator", "packet_span", "availability", "covariance_from_kept", "buffered_covariances",
           "simulate_states", "single_link", "delay_conventions", "CONVENTION_HELP", "max_kept_delay"]
