"""One reference test over every estimator with per-run covariances (Stone Soup's pattern):

* a perfect channel (every packet, on time, at a huge SNR) gives the DARE steady state: ``filtered``
  P̄ and ``predicted`` P* for every estimator that reports them;
* the batched recursion equals a loop over single runs on the same trace, every quantity;
* the intermittent KF equals a textbook per-run loop on random systems (hypothesis);
* the ``trace`` channel reproduces a hand-computed covariance sequence.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sl
from hypothesis import given, settings
from hypothesis import strategies as st

from netkf_cli.channels.trace_file import TraceChannel
from netkf_cli.estimators.kf import KalmanFilterEstimator
from netkf_cli.config.scenario import kinds
from netkf_cli.core.spec import EstimatorModel
from netkf_cli.core.system import LinearSystem
from netkf_cli.core.trace import Trace

from .conftest import sample_estimators


def _dare(s: LinearSystem):
    """(P*, P̄): predicted and filtered steady states of the always-arriving KF."""
    X = sl.solve_discrete_are(s.A.T, s.C.T, s.Q, s.R)
    Pf = X - X @ s.C.T @ np.linalg.solve(s.C @ X @ s.C.T + s.R, s.C @ X)
    return X, Pf


def _sample_channel(kind: str):
    import tempfile
    from pathlib import Path

    from netkf_cli.config.compat import compatible_channels
    from netkf_cli.core.spec import ChannelModel

    from .conftest import sample_channels

    chans = sample_channels(Path(tempfile.mkdtemp()))
    names = [c for c in compatible_channels(kinds(EstimatorModel)[kind]) if c in chans and c != "trace"]
    return kinds(ChannelModel)[names[0]].model_validate(chans[names[0]])


def _sampled_trace(kind: str, runs: int, horizon: int, seed: int = 7) -> Trace:
    """A trace from the first sample channel the estimator accepts (its meta carries what the
    estimator needs from the channel, e.g. a fading noise model)."""
    return _sample_channel(kind).sample_trace(np.random.default_rng(seed), runs, horizon)


def _perfect_trace(kind: str, runs: int, horizon: int) -> Trace:
    """Every packet, on time, at a huge SNR, in mode 0 ('normal')."""
    tr = _sampled_trace(kind, runs, horizon)
    if tr.arrival is not None:
        tr.arrival[...] = True
    if tr.delay is not None:
        tr.delay[...] = 0
    if tr.snr is not None:  # (a fading channel's SNR array is read-only: shared by the traces of one sample)
        tr.snr = np.full(tr.snr.shape, 1e12)
    if tr.mode is not None:
        tr.mode[...] = 0
    return tr


def _per_run_estimators():
    out = []
    for k, cls in sorted(kinds(EstimatorModel).items()):
        if getattr(cls, "accepts", None) and cls.covariances is not EstimatorModel.covariances:
            out.append(k)
    return out


SYSTEMS = {
    "scalar": LinearSystem.create(1.3, 1.0, 0.5, 0.8, 2.0),
    "stable": LinearSystem.create([[0.8, 0.3], [0.0, 0.6]], [[1.0, 0.5]], [[0.3, 0.0], [0.0, 0.2]], 0.4,
                                  [[1.0, 0.0], [0.0, 1.0]]),
    "2-state": LinearSystem.create([[1.05, 0.3], [0.0, 0.9]], [[1.0, 0.0], [0.0, 1.0]], [[0.2, 0.05], [0.05, 0.3]],
                                   [[0.5, 0.0], [0.0, 0.4]], [[1.0, 0.0], [0.0, 1.0]]),
}


def _estimator(kind: str):
    from netkf_cli.config.scenario import kinds as _k

    return _k(EstimatorModel)[kind].model_validate(sample_estimators()[kind])


def _with_sensors(s: LinearSystem, streams: int) -> LinearSystem:
    """The system with ``streams`` identical sensors (system.sensors: N) when the channel has several streams."""
    if streams <= 1 or streams == s.n_sensors:
        return s
    groups = tuple(tuple(range(i * s.m, (i + 1) * s.m)) for i in range(streams))
    return LinearSystem.create(s.A, np.vstack([s.C] * streams), s.Q, np.kron(np.eye(streams), s.R), s.P0, sensors=groups)


@pytest.mark.parametrize("kind", _per_run_estimators())
@pytest.mark.parametrize("sysname", sorted(SYSTEMS))
def test_perfect_channel_gives_dare_steady_state(kind, sysname):
    s = SYSTEMS[sysname]
    est = _estimator(kind)
    if kind == "markov_lmi":  # the LMI filter's fixed gains are not optimal: its mode-aware KF is
        est = est.model_copy(update={"filter": "mode_aware"})
    if kind == "receiver":  # scenario 3 knows each step's SNR (cross-layer): the optimal filter
        est = est.model_copy(update={"scenario": 3})
    if kind == "smoother":  # lag 0 is the filter
        est = est.model_copy(update={"lag": 0})
    if kind == "fusion":  # measurement fusion is the centralized KF of the stacked sensors
        est = est.model_copy(update={"strategies": ["mf"]})
    horizon = 400
    tr = _perfect_trace(kind, 3, horizon)
    s = _with_sensors(s, tr.sensors)
    try:
        est.check(s, _sample_channel(kind))
    except Exception as exc:  # noqa: BLE001 - a system the estimator refuses is not this test's business
        pytest.skip(f"{kind} refuses {sysname}: {exc}")
    qs = [q for q in ("filtered", "predicted") if q in est.quantities]
    assert qs, f"{kind} reports neither filtered nor predicted"
    (k, out), = list(est.covariances(s, tr, [horizon], qs))
    ref_sys = s
    if kind == "receiver":  # a perfect link still carries the noise model's floor σ_n²(Υ → ∞) (quantization)
        floor = float(_sample_channel(kind).noise.variance(np.array([1e12]))[0])
        ref_sys = LinearSystem.create(s.A, s.C, s.Q, s.R + floor * np.eye(s.m))
    Ppred, Pfilt = _dare(ref_sys)
    for q in qs:
        P = out[q]
        # contraction of the Riccati map: after 400 steps the error is far below 1e-9 for these systems
        np.testing.assert_allclose(P[:, :, 0], Pfilt if q == "filtered" else Ppred, rtol=1e-8, atol=1e-10,
                                   err_msg=f"{kind}: {q}")
        assert np.array_equal(P[:, :, 0], P[:, :, 2])


@pytest.mark.parametrize("kind", _per_run_estimators())
def test_batched_equals_single_runs_on_the_same_trace(kind):
    s = SYSTEMS["scalar"]
    est = _estimator(kind)
    runs, horizon = 9, 40
    tr = _sampled_trace(kind, runs, horizon)
    s = _with_sensors(s, tr.sensors)
    steps = [5, 17, 40]
    qs = [q for q in est.quantities if 5 >= est.first_step(q)]
    batched = dict(est.covariances(s, tr, steps, qs))
    for r in range(runs):
        def cut(a, r=r):
            return None if a is None else a[..., r:r + 1].copy()

        one = Trace(1, horizon, arrival=cut(tr.arrival), delay=cut(tr.delay), snr=cut(tr.snr), mode=cut(tr.mode),
                    meta=tr.meta)
        for k, out in est.covariances(s, one, steps, qs):
            for q in qs:
                np.testing.assert_allclose(batched[k][q][:, :, r], out[q][:, :, 0], rtol=1e-12, atol=1e-12)


def _textbook_kf(s: LinearSystem, gamma: np.ndarray, P0: np.ndarray) -> list[np.ndarray]:
    """Sinopoli et al. 2004, eqs (8)–(9), one run, no vectorization."""
    P, out = P0.copy(), []
    for g in gamma:
        Pp = s.A @ P @ s.A.T + s.Q
        S = s.C @ Pp @ s.C.T + s.R
        P = Pp - g * Pp @ s.C.T @ np.linalg.solve(S, s.C @ Pp)
        out.append((P, s.A @ P @ s.A.T + s.Q))  # (P_{k|k}, P_{k+1|k})
    return out


@settings(max_examples=25, deadline=None, derandomize=True)
@given(n=st.integers(1, 4), m=st.integers(1, 3), seed=st.integers(0, 10_000), lam=st.floats(0.2, 1.0))
def test_kf_equals_textbook_loop_on_random_systems(n, m, seed, lam):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n)) * 0.6
    C = rng.normal(size=(m, n))
    L = rng.normal(size=(n, n))
    Q = L @ L.T + 0.1 * np.eye(n)
    Rm = rng.normal(size=(m, m))
    R = Rm @ Rm.T + 0.2 * np.eye(m)
    s = LinearSystem.create(A, C, Q, R, np.eye(n))
    runs, horizon = 4, 30
    gam = rng.random((1, horizon, runs)) < lam
    tr = Trace(runs, horizon, arrival=gam)
    got_both = dict(KalmanFilterEstimator(kind="kf").covariances(s, tr, range(1, horizon + 1), ("filtered", "predicted")))
    for r in range(runs):
        both = _textbook_kf(s, gam[0, :, r].astype(float), np.eye(n))
        for q, i in (("filtered", 0), ("predicted", 1)):
            ref = [b[i] for b in both]
            got = {k: v[q] for k, v in got_both.items()}
            _compare_textbook(got, ref, r, horizon)


def _compare_textbook(got, ref, r, horizon):
    """got[k] (n, n, runs) against the textbook ref[k − 1] for run r at k = 1, 10, horizon."""
    for k in (1, 10, horizon):
        # both are float64; the update P − PCᵀS⁻¹CP cancels digits on unstable, badly conditioned
        # draws (‖P‖ up to 1e7 here), so the agreement is measured relative to ‖P‖: 1e-7·‖P‖ is
        # orders above the observed round-off (≤ 3e-8·‖P‖ over these examples) and far below any
        # modelling error (a wrong gain or a missed γ changes P at order one)
        scale = max(1.0, float(np.abs(ref[k - 1]).max()))
        np.testing.assert_allclose(got[k][:, :, r], ref[k - 1], rtol=0, atol=1e-7 * scale)
        assert np.allclose(got[k][:, :, r], got[k][:, :, r].T)
        assert np.linalg.eigvalsh(got[k][:, :, r])[0] > -1e-9


def test_trace_channel_reproduces_hand_computed_sequence(tmp_path):
    """a = 2, c = 1, q = 1, r = 1, P0 = 1 and arrivals 1, 0, 1: by hand
    P1⁻ = 4·1 + 1 = 5, P1 = 5 − 25/6 = 5/6; P2 = 4·5/6 + 1 = 13/3 (lost);
    P3⁻ = 4·13/3 + 1 = 55/3, P3 = 55/3 − (55/3)²/(55/3 + 1) = 55/58."""
    f = tmp_path / "rec.csv"
    f.write_text("sensor\n1\n0\n1\n", encoding="utf-8")
    ch = TraceChannel(kind="trace", file=str(f), mode="once")
    s = LinearSystem.create(2.0, 1.0, 1.0, 1.0, 1.0)
    tr = ch.sample_trace(None, 2, 3)
    got = {k: P["filtered"][0, 0, 0] for k, P in KalmanFilterEstimator(kind="kf").covariances(s, tr, [1, 2, 3])}
    assert got[1] == pytest.approx(5 / 6, rel=1e-14)
    assert got[2] == pytest.approx(13 / 3, rel=1e-14)
    assert got[3] == pytest.approx(55 / 58, rel=1e-14)
    # the same recording from a numpy array (Python API) and cycle mode
    ch2 = TraceChannel.from_array(np.array([1, 0, 1]), mode="cycle")
    tr2 = ch2.sample_trace(None, 1, 6)
    assert tr2.arrival[0, :, 0].tolist() == [True, False, True, True, False, True]


def test_trace_channel_once_mode_refuses_a_short_recording(tmp_path):
    from netkf_cli.core.errors import ConfigError

    f = tmp_path / "rec.csv"
    f.write_text("1\n0\n", encoding="utf-8")
    with pytest.raises(ConfigError, match="mode once needs 5 rows"):
        TraceChannel(kind="trace", file=str(f)).sample_trace(None, 1, 5)
