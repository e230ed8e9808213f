"""Gilbert–Elliott channel: validation and the sampler's stationary loss rate and burst length."""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest
from pydantic import ValidationError

from netkf_cli.channels.bernoulli import BernoulliChannel
from netkf_cli.channels.retransmission import effective_arrivals
from netkf_cli.channels.gilbert_elliott import (
    GilbertElliottChannel,
    arrivals_for,
    markov_chain_of,
    sample_gilbert_elliott,
)


def ge(**kw):
    return GilbertElliottChannel(kind="gilbert_elliott", **kw)


def test_parameterisations_agree():
    a = ge(loss_rate=0.3, mean_burst=4.0)
    p_gb, p_bg = a.transition
    assert p_bg == pytest.approx(0.25) and p_gb == pytest.approx(0.3 * 0.25 / 0.7)
    b = ge(p_gb=p_gb, p_bg=p_bg)
    assert b.arrival == pytest.approx(0.7) and b.burst_mean == pytest.approx(4.0)
    T, pi = markov_chain_of(a)
    assert np.allclose(T.sum(axis=1), 1) and np.allclose(pi @ T, pi)


@pytest.mark.parametrize(
    "kw, needle",
    [
        (dict(loss_rate=0.8, mean_burst=2.0), "mean_burst"),  # needs L_B ≥ 0.8/0.2 = 4
        (dict(loss_rate=0.3, p_gb=0.2), "not a mix"),
        (dict(loss_rate=0.3), "mean_burst is required"),
        (dict(p_bg=0.3), "p_gb is required"),
        (dict(), "needs loss_rate"),
        (dict(loss_rate=1.2, mean_burst=3), "loss_rate"),
        (dict(loss_rate=0.2, mean_burst=0.5), "mean_burst"),
        (dict(p_gb=-0.1, p_bg=0.5), "p_gb"),  # p_gb = 0 (never lose) is allowed since issue 23
        (dict(p_gb=0.3, p_bg=0.0), "p_bg"),
    ],
)
def test_bad_parameters_are_rejected_with_the_field(kw, needle):
    with pytest.raises(ValidationError) as e:
        ge(**kw)
    assert needle in str(e.value)


def test_bernoulli_is_the_iid_special_case():
    lam = 0.6
    c = ge(loss_rate=1 - lam, mean_burst=1 / lam)
    T, _ = markov_chain_of(c)
    Tb, _ = markov_chain_of(BernoulliChannel(kind="bernoulli", arrival=lam))
    assert np.allclose(T, Tb)


@pytest.mark.parametrize("loss, burst", [(0.3, 4.0), (0.5, 1.5), (0.1, 1.0)])
def test_sampler_stationary_loss_and_mean_burst(loss, burst):
    c = ge(loss_rate=loss, mean_burst=burst)
    p_gb, p_bg = c.transition
    runs, H = 20_000, 400
    g = sample_gilbert_elliott(np.random.default_rng(11), runs, H, p_gb, p_bg)
    assert g.shape == (runs, H) and g.dtype == bool
    # stationary loss rate: one column per run -> i.i.d. Bernoulli(loss) samples (chain started stationary);
    # 5 binomial standard errors
    for col in (0, H - 1):
        x = ~g[:, col]
        se = math.sqrt(loss * (1 - loss) / runs)
        assert abs(x.mean() - loss) < 5 * se
    # burst length: the first burst starting at t ≥ 1 in each run is Geometric(p_bg) on {1, 2, ...}
    # (strong Markov property); runs are independent -> sample mean within 5 s.e. of 1/p_bg,
    # s.e. = sqrt(1 − p_bg)/p_bg/√n. Censoring at H: P(burst > 200) = (1 − p_bg)^200 < 1e-24 here.
    lost = ~g
    starts = lost[:, 1:] & ~lost[:, :-1]
    has = starts[:, : H // 2].any(axis=1)
    t0 = np.argmax(starts, axis=1) + 1
    lengths = []
    for r in np.flatnonzero(has):
        seg = lost[r, t0[r]:]
        lengths.append(np.argmin(seg) if not seg.all() else seg.size)
    L = np.array(lengths, float)
    se = math.sqrt(1 - p_bg) / p_bg / math.sqrt(L.size)
    assert abs(L.mean() - burst) < 5 * se + 1e-12


def test_arrivals_for_both_kinds_and_rejects_others():
    rng = np.random.default_rng(0)
    a = arrivals_for(BernoulliChannel(kind="bernoulli", arrival=0.5), rng, 3, 7)
    b = arrivals_for(ge(loss_rate=0.5, mean_burst=2), rng, 3, 7)
    assert a.shape == b.shape == (3, 7)
    with pytest.raises(ValueError, match="loss channel"):
        arrivals_for(object(), rng, 3, 7)


@pytest.mark.skipif(importlib.util.find_spec("numba") is None, reason="numba not installed")
@pytest.mark.parametrize("lam, N, p", [(0.6, 2, 1.0), (0.6, 2, 0.5), (0.3, 5, 0.25), (0.6, 0, 1.0), (0.6, 2, 0.0)])
def test_retransmission_compiled_slot_loop_is_the_numpy_loop(lam, N, p):
    """The compiled slot loop of the retransmission channel on the same uniforms: the same trace, exactly."""
    a, b = (effective_arrivals(np.random.default_rng(3), 301, 90, lam, N, p, backend=be) for be in ("numpy", "numba"))
    assert a.dtype == b.dtype == bool and np.array_equal(a, b)


@pytest.mark.parametrize("runs,horizon,block", [(1, 1, 1), (7, 3, 1), (7, 3, 3), (5000, 560, 1 << 18), (300_000, 5, 1 << 18),
                                                (1, 10_000, 64)])
def test_bernoulli_trace_in_blocks_is_the_whole_draw(monkeypatch, runs, horizon, block):
    """sample_trace draws its uniforms a block of steps at a time (memory): the same arrivals as one
    rng.random((horizon, runs)) < γ, and the generator ends in the same state."""
    import netkf_cli.channels.bernoulli as bern

    monkeypatch.setattr(bern, "UNIFORM_BLOCK", block)
    ch = bern.BernoulliChannel(kind="bernoulli", arrival=0.37)
    r1, r2 = np.random.default_rng(5), np.random.default_rng(5)
    got = ch.sample_trace(r1, runs, horizon).arrival[0]
    assert got.dtype == bool and np.array_equal(got, r2.random((horizon, runs)) < 0.37)
    assert r1.random() == r2.random()


@pytest.mark.parametrize("runs,horizon,block", [(1, 1, 1), (7, 3, 1), (7, 3, 3), (4000, 560, 1 << 18), (300_000, 5, 1 << 18),
                                                (1, 10_000, 64), (3, 0, 1)])
def test_gilbert_elliott_trace_in_blocks_is_the_whole_draw(monkeypatch, runs, horizon, block):
    """sample_trace draws its uniforms a block of steps at a time, the chain's state carried: the same arrivals
    as gilbert_elliott_from_uniforms of one rng.random((horizon, runs)), and the same generator state after."""
    import netkf_cli.channels.gilbert_elliott as ge

    monkeypatch.setattr(ge, "UNIFORM_BLOCK", block)
    ch = ge.GilbertElliottChannel(kind="gilbert_elliott", loss_rate=0.45, mean_burst=4.0)
    p_gb, p_bg = ch.transition
    r1, r2 = np.random.default_rng(5), np.random.default_rng(5)
    got = ch.sample_trace(r1, runs, horizon).arrival[0]
    want = ge.gilbert_elliott_from_uniforms(r2.random((horizon, runs)), p_gb, p_bg)
    assert got.dtype == bool and got.shape == (horizon, runs) and np.array_equal(got, want)
    assert r1.random() == r2.random()


@pytest.mark.parametrize("p_gb,p_bg", [(0.3, 0.1), (0.0, 1.0), (1.0, 0.5), (0.2, 0.2), (1.0, 1.0)])
def test_gilbert_elliott_from_uniforms_is_the_chains_choice(p_gb, p_bg):
    """gilbert_elliott_from_uniforms (two logical passes per step on the whole block's comparisons) is the chain's
    choice γ_k = (u_k ≥ p_gb if γ_{k−1} else u_k < p_bg) step by step, from the stationary start or a given state;
    uniforms on the thresholds included."""
    import netkf_cli.channels.gilbert_elliott as ge

    rng = np.random.default_rng(8)
    u = rng.random((120, 501))
    u[5, :50], u[6, 50:100] = p_gb, p_bg
    prev = rng.random(501) < 0.5
    for start in (None, prev):
        want = np.empty(u.shape, dtype=bool)
        want[0] = (u[0] < ge.pi_good_of(p_gb, p_bg)) if start is None else np.where(start, u[0] >= p_gb, u[0] < p_bg)
        for k in range(1, u.shape[0]):
            want[k] = np.where(want[k - 1], u[k] >= p_gb, u[k] < p_bg)
        assert np.array_equal(ge.gilbert_elliott_from_uniforms(u, p_gb, p_bg, prev=start), want)


def _one_shot_retransmission(rng, runs, horizon, lam, N, p):
    """The slot loop on one rng.random((horizon + N, 2, runs)) draw (the channel before its uniforms came in blocks)."""
    slots = horizon + N
    u = rng.random((slots, 2, runs))
    out = np.zeros((slots, runs), dtype=bool)
    count, pending, retrying = np.zeros(runs, dtype=np.int64), np.zeros(runs, dtype=np.int64), np.zeros(runs, dtype=bool)
    ar = np.arange(runs)
    for t in range(slots):
        succ, ask = u[t, 0] < lam, u[t, 1] < p
        fresh = ~retrying
        out[t, fresh] = succ[fresh]
        start = fresh & ~succ & ask & (N > 0)
        won = retrying & succ
        out[pending[won], ar[won]] = True
        cont = retrying & ~succ & ask & (count < N)
        count = np.where(start, 1, np.where(cont, count + 1, 0))
        pending = np.where(start, t, pending)
        retrying = start | cont
    return out[:horizon]


@pytest.mark.parametrize("backend", ["numpy", pytest.param("numba", marks=pytest.mark.skipif(
    importlib.util.find_spec("numba") is None, reason="numba not installed"))])
@pytest.mark.parametrize("runs,horizon,N,block", [(301, 90, 2, 1 << 18), (301, 90, 2, 1000), (7, 5, 3, 1), (5, 40, 50, 64)])
def test_retransmission_trace_in_blocks_is_the_one_shot_trace(monkeypatch, backend, runs, horizon, N, block):
    """effective_arrivals draws its uniforms a block of slots at a time, the loop's state carried across blocks:
    the same trace as the loop on one rng.random((horizon + N, 2, runs)), and the generator in the same state."""
    import netkf_cli.channels.retransmission as rt

    monkeypatch.setattr(rt, "UNIFORM_BLOCK", block)
    r1, r2 = np.random.default_rng(9), np.random.default_rng(9)
    got = rt.effective_arrivals(r1, runs, horizon, 0.55, N, 0.7, backend=backend)
    assert np.array_equal(got, _one_shot_retransmission(r2, runs, horizon, 0.55, N, 0.7))
    assert r1.random() == r2.random()
