"""The generated fading-receiver step (netkf_cli/estimators/_fading_codegen.py, runs innermost) against the
numpy reference on the same uniforms: every mode (0 scenarios 1/3, with and without the inline information-form
rescue; 1 scenario 2 invertible C; 2 scenario 2 general C), with and without the burst-conditioned U, the
overflow path (non-finite values redone on the numpy core), and a check that the generated path really ran."""

import numpy as np
import pytest

from netkf_cli.channels.fading import FadingChannel
from netkf_cli.estimators import _fading_codegen as fcg
from netkf_cli.linalg import kalman_codegen as kc
from netkf_cli.estimators import fading_receivers as fr
from netkf_cli.estimators.fading_receivers import ReceiverEstimator
from netkf_cli.core.system import LinearSystem

pytestmark = pytest.mark.skipif(not fr.numba_available(), reason="numba not installed")

A5 = np.array([[2, 0.3, 0.45], [0.4, 0.2, 0.5], [1.5, 0.6, 0.34]])
Q5 = 1e-3 * np.eye(3)
BOTH = ("filtered", "predicted")
SYSTEMS = {
    # R = 1e-8 I: kalman.Rescue's limit is 0.75, the prior P_{1|0} (tr 7.5) and every drop burst need the rescue
    "fig6": dict(A=A5, C=2 * np.eye(3), Q=Q5, R=1e-8 * np.eye(3), P0=np.eye(3)),
    "sec42": dict(A=A5, C=np.array([[1.0, 2, 3]]), Q=Q5, R=np.array([[1e-8]]), P0=np.eye(3)),
    "m2": dict(A=A5, C=np.array([[1.0, 0, 1], [0, 1, 0]]), Q=Q5, R=np.array([[1e-2, 3e-3], [3e-3, 2e-2]]),
               P0=np.eye(3)),
    "overflow": dict(A=np.diag([1e6, 0.5]), C=np.eye(2), Q=np.eye(2), R=np.eye(2), P0=np.eye(2)),
}
CASES = [(sc, name) for name in sorted(SYSTEMS) for sc in (1, 2, 3)]


def chan():
    return FadingChannel.model_validate({"kind": "fading", "snr_avg": {"value": 20, "unit": "dB"},
                                         "noise": {"model": "ber", "N_p": 10, "Delta": 0.0390625}})


def run(sc, name, vr, backend, T=12.0, runs=300, H=60, steps=(1, 2, 3, 10, 33, 60)):
    s = LinearSystem(**SYSTEMS[name])
    tr = chan().sample_trace(np.random.default_rng(4), runs, H)
    est = ReceiverEstimator.model_validate({"kind": "receiver", "scenario": sc, "backend": backend,
                                            "variance_reduction": vr, "threshold": {"value": T, "unit": "linear"}})
    return dict(est.covariances(s, tr, list(steps), BOTH))


@pytest.mark.parametrize("vr", ["none", "conditioned"])
@pytest.mark.parametrize("sc,name", CASES)
def test_generated_equals_numpy_on_the_same_uniforms(sc, name, vr, monkeypatch):
    """Per run equal to rounding relative to the run's largest entry (sums in another order, amplified by the
    near-singular updates from P0 and after drop bursts: the scalar kernel itself is 1.2e-8 off numpy on
    m2 at k = 3, the generated one 1.9e-8; bound 1e-7), the means over runs ≤ 1e-9; the same entries non-finite.
    The generated kernel must have run (counted)."""
    calls = []
    real = fcg.kernel

    def counted(*a, **k):
        calls.append(a[0])
        return real(*a, **k)

    monkeypatch.setattr(fcg, "kernel", counted)
    ref = run(sc, name, vr, "numpy")
    got = run(sc, name, vr, "numba")
    rm = fr.ReceiverModel(sc, SYSTEMS[name]["A"], SYSTEMS[name]["C"], Q5, SYSTEMS[name]["R"], None)
    if fcg.supported(_mode(rm), rm.n, rm.C.shape[0]):
        assert calls, "the generated kernel did not run"
    for k in ref:
        for q in BOTH:
            x, y = ref[k][q], got[k][q]
            assert np.array_equal(np.isfinite(x), np.isfinite(y)), (k, q)
            f = np.isfinite(x).all(axis=(0, 1))
            scale = np.abs(x[..., f]).max(axis=(0, 1))
            err = np.abs(y[..., f] - x[..., f]).max(axis=(0, 1)) / scale
            assert err.max(initial=0) <= 1e-7, (k, q, err.max())
            if f.any():
                np.testing.assert_allclose(y[..., f].mean(-1), x[..., f].mean(-1), rtol=1e-9, atol=1e-300)


def _mode(rm):
    return 0 if rm.scenario in (1, 3) else (1 if rm.state_size() == 1 else 2)


def test_overflow_is_redone_on_the_numpy_core():
    """A = diag(1e6, 0.5), every packet dropped (Υ_T huge): P overflows to inf within a few steps; the generated
    kernel flags the runs (bit 1) and the numpy core defines the result — the same inf pattern and numbers."""
    for sc in (1, 2, 3):
        ref = run(sc, "overflow", "none", "numpy", T=1e9, runs=20, H=80, steps=(1, 40, 80))
        got = run(sc, "overflow", "none", "numba", T=1e9, runs=20, H=80, steps=(1, 40, 80))
        assert not np.isfinite(ref[80]["predicted"]).all()
        for k in ref:
            for q in BOTH:
                x, y = ref[k][q], got[k][q]
                assert np.array_equal(np.isfinite(x), np.isfinite(y))
                f = np.isfinite(x)
                np.testing.assert_allclose(y[f], x[f], rtol=1e-12, atol=1e-300)


@pytest.mark.parametrize("mode,name", [(0, "fig6"), (0, "sec42"), (1, "fig6"), (2, "sec42"), (2, "m2"), (0, "m2")])
def test_kernel_step_equals_scalar_kernel(mode, name):
    """One block through the generated kernel and through the scalar one-run-at-a-time kernel
    (_fading_numba) on the same keep/σ² inputs: same flags where no rescue is needed, states equal to rounding.
    With the inline rescue (mode 0, full-rank C) the generated kernel leaves no run for the scalar rescue."""
    from netkf_cli.estimators import _fading_numba as fnb

    S = SYSTEMS[name]
    A, C, R = S["A"], S["C"], S["R"]
    sc = 3 if mode == 0 else 2
    rm = fr.ReceiverModel(sc, A, C, Q5, R, None)
    assert _mode(rm) == mode
    rng = np.random.default_rng(7)
    B, T, n, m = 257, 50, 3, C.shape[0]
    keep = rng.random((T, B)) < 0.7
    keep[::3] = True  # bursts of at most two drops: a well-conditioned update (after long bursts P ≫ R and every
    # backend, the scalar kernel and numpy included, is off by up to 1e-3 per run: the cancellation of P − K C P)
    s2 = 1e-6 * rng.random((T, B))
    s2u = 1e-6 * rng.random((T, B))
    mu = rng.random(B)
    P0 = np.repeat((0.01 * np.eye(n))[None], B, axis=0) + 1e-3 * rng.random((B, 1, 1)) * np.ones((1, n, n))
    inline = fcg.inline_rescue(mode, C)
    for want_u, sep in ((False, False), (True, False), (True, True)):
        # scalar (run-major)
        Pt, Pf, U = P0.copy(), P0.copy(), P0.copy()
        Ft, Uf = np.empty_like(Pt), np.empty_like(Pt)
        fl = np.zeros(B, dtype=np.int8)
        rec = np.full(T, -1, dtype=np.int64)
        rec[[9, T - 1]] = [0, 1]
        rs = [np.empty((B, 2, n, n)) for _ in range(4)]
        tr = lambda X: np.ascontiguousarray(X.T)  # noqa: E731
        fnb.kernel(mode, n, m, rescue=inline)(tr(keep), tr(s2), tr(s2u), sep, mu, want_u, A, Q5, C, R, rm.gain_inv,
                                              rm.rescue.limit, Pt, Pf, Ft, U, Uf, fl, rec, *rs)
        # generated (packed, runs innermost)
        P, G, Uv = fcg.pack(P0), fcg.pack(P0), fcg.pack(P0)
        F, Ufv = np.empty_like(P), np.empty_like(P)
        fg = np.zeros(B, dtype=np.int8)
        rg = [np.empty((2, n, n, B)) for _ in range(4)]
        fcg.kernel(mode, A, C, Q5, R, rm.gain_inv, rm.rescue.limit, want_u, sep, inline)(
            keep, s2, s2u if sep else s2, mu, P, F, Uv, Ufv, G, fg, rec, *rg)
        if inline:
            assert not (fg & 1).any() and not (fl == 1).any()
        else:
            np.testing.assert_array_equal((fg & 1) > 0, fl == 1)
        assert not (fg & 2).any() and not (fl == 2).any()
        ok = fl == 0
        _close(kc.unpack(P, n)[..., ok], np.moveaxis(Pt, 0, 2)[..., ok])
        _close(kc.unpack(F, n)[..., ok], np.moveaxis(Ft, 0, 2)[..., ok])
        if mode == 2:
            _close(kc.unpack(G, n)[..., ok], np.moveaxis(Pf, 0, 2)[..., ok])
        for j in range(4 if want_u else 2):
            _close(rg[j][..., ok], np.moveaxis(rs[j], 0, 3)[..., ok])
        if want_u:
            _close(kc.unpack(Uv, n)[..., ok], np.moveaxis(U, 0, 2)[..., ok])


def _close(y, x, bound=1e-9):
    """Per run (last axis) max |y − x| / max |x| ≤ bound: rounding, amplified by the standard update's
    cancellation ε · tr P / R (fig6's R = 1e-8 with tr P ≈ 0.03–0.75: ~1e-10, seen 1.0e-10; the others ≤ 4e-13)."""
    y, x = np.asarray(y), np.asarray(x)
    ax = tuple(range(x.ndim - 1))
    err = np.abs(y - x).max(axis=ax) / np.abs(x).max(axis=ax)
    assert err.max(initial=0) <= bound, err.max()


@pytest.mark.parametrize("mode,name", [(0, "fig6"), (0, "sec42"), (1, "fig6"), (2, "sec42"), (2, "m2")])
def test_tiles_are_invisible(mode, name):
    """The kernel advances runs in tiles of fcg.TILE (the loop over a tile's runs vectorised); with the inline rescue a
    tile step takes the plain update when no run of the tile needs the rescue, the rescue variant otherwise. Each
    run's numbers must not depend on its tile: every run alone (B = 1) gives the same bytes as all runs together
    (B not a multiple of TILE; priors with tr P above and below kalman.Rescue's limit mixed within tiles)."""
    S = SYSTEMS[name]
    A, C, R = S["A"], S["C"], S["R"]
    sc = 3 if mode == 0 else 2
    rm = fr.ReceiverModel(sc, A, C, Q5, R, None)
    rng = np.random.default_rng(3)
    B, T, n = 2 * fcg.TILE + 5, 20, 3
    keep = rng.random((T, B)) < 0.6
    s2 = 1e-4 * rng.random((T, B))
    s2u = 1e-4 * rng.random((T, B))
    mu = rng.random(B)
    scale = np.where(rng.random(B) < 0.1, 2.0, 0.05 * rng.random(B))  # a few runs start above the limit
    P0 = fcg.pack(np.eye(n)[None] * scale[:, None, None])
    inline = fcg.inline_rescue(mode, C)
    rec = np.full(T, -1, dtype=np.int64)
    rec[[4, T - 1]] = [0, 1]

    def go(idx):
        b = len(idx)
        P, U = P0[:, idx].copy(), P0[:, idx].copy()
        G = P0[:, idx].copy() if mode == 2 else np.zeros((6, 1))
        F, Uf = np.zeros((6, b)), np.zeros((6, b))
        fl = np.zeros(b, dtype=np.int8)
        recs = [np.zeros((2, n, n, b)) for _ in range(4)]
        fcg.kernel(mode, A, C, Q5, R, rm.gain_inv, rm.rescue.limit, True, True, inline)(
            np.ascontiguousarray(keep[:, idx]), np.ascontiguousarray(s2[:, idx]), np.ascontiguousarray(s2u[:, idx]),
            mu[idx], P, F, U, Uf, G, fl, rec, *recs)
        return [P, F, U, Uf, fl[None]] + ([G] if mode == 2 else []) + [r.reshape(-1, b) for r in recs]

    together = go(np.arange(B))
    for b in range(B):
        alone = go(np.array([b]))
        for x, y in zip(together, alone):
            assert x[:, b].tobytes() == y[:, 0].tobytes(), b
