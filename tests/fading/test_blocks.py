"""The receivers' reported steps come out of one recursion call per block (issue 20), and ``backend: auto`` takes
the compiled rescue for a scalar system whose every step needs it (Theorem 4's R = 1e-12): the same numbers."""

import numpy as np
import pytest

from netkf_cli.channels.fading import FadingChannel
from netkf_cli.estimators import fading_receivers as fr
from netkf_cli.estimators.fading_receivers import ReceiverEstimator
from netkf_cli.core.system import LinearSystem

needs_numba = pytest.mark.skipif(not fr.numba_available(), reason="numba not installed")
A5 = np.array([[2, 0.3, 0.45], [0.4, 0.2, 0.5], [1.5, 0.6, 0.34]])
BOTH = ("filtered", "predicted")
BACKENDS = ["numpy", "numba"] if fr.numba_available() else ["numpy"]


def chan(**kw):
    base = {"kind": "fading", "snr_avg": {"value": 20, "unit": "dB"}, "noise": {"model": "ber", "N_p": 10, "Delta": 0.0390625}}
    base.update(kw)
    return FadingChannel.model_validate(base)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("sc,vr,C", [(2, "auto", 2 * np.eye(3)), (3, "auto", 2 * np.eye(3)), (2, "auto", np.array([[1.0, 2, 3]])),
                                     (3, "none", 2 * np.eye(3)), (1, "none", np.array([[1.0, 2, 3]]))])
def test_one_block_equals_one_call_per_step(backend, sc, vr, C, monkeypatch):
    """Every step 1…30 reported from one call (and from blocks of 7 steps: RECORD_BYTES small) is bit for bit what
    a separate run up to that single step gives (the same recursion on the same trace)."""
    R = 1e-8 * np.eye(C.shape[0])
    s = LinearSystem.create(A5, C, 1e-3 * np.eye(3), R, np.eye(3))
    ch = chan(threshold={"value": 14, "unit": "linear"})
    e = ReceiverEstimator(kind="receiver", scenario=sc, backend=backend, variance_reduction=vr).for_means(ch)
    tr = ch.sample_trace(np.random.default_rng(5), 60, 30)
    steps = list(range(1, 31))
    whole = dict(e.covariances(s, tr, steps, BOTH))
    monkeypatch.setattr(fr, "RECORD_BYTES", 8 * 9 * 60 * 4 * 7)  # blocks of 7 steps (14 without the conditioned U)
    blocks = dict(e.covariances(s, tr, steps, BOTH))
    for k in (1, 2, 7, 8, 17, 30):
        single = dict(e.covariances(s, tr, [k], BOTH))[k]
        for q in BOTH:
            np.testing.assert_array_equal(whole[k][q], single[q], err_msg=f"{k} {q}")
            np.testing.assert_array_equal(blocks[k][q], single[q], err_msg=f"{k} {q} blocks")


def _thm4():
    s = LinearSystem.create(np.array([[1.5]]), np.array([[1.0]]), np.array([[0.0]]), np.array([[1e-12]]),
                            np.array([[1 / 2.25]]))
    ch = chan(snr_avg={"value": 10, "unit": "dB"}, noise={"model": "inverse_snr", "beta": 1.0})
    return s, ch


@needs_numba
def test_auto_compiles_the_scalar_rescue_and_equals_numpy():
    """Theorem 4's system (R = 1e-12: every prior is above kalman.Rescue's limit): auto runs the compiled rescue
    variant (a scalar system otherwise stays on numpy); per run equal to the numpy core to rounding."""
    s, ch = _thm4()
    rm = ReceiverEstimator(kind="receiver", scenario=3, threshold={"value": 0, "unit": "linear"}).model(s, None)
    assert fr.needs_rescue(rm, np.array([[1.0]]))
    assert fr.Stepper(rm, np.array([[1.0]]), 4, "auto").backend == "numba"
    rm2 = fr.ReceiverModel(2, s.A, s.C, s.Q, s.R, None)
    assert fr.Stepper(rm2, np.array([[1.0]]), 4, "auto").backend == "numpy"  # scenario 2: no rescue, stays numpy
    tr = ch.sample_trace(np.random.default_rng(2), 500, 30)
    out = {}
    for be in ("numpy", "auto"):
        e = ReceiverEstimator(kind="receiver", scenario=3, threshold={"value": 0, "unit": "linear"}, backend=be,
                              variance_reduction="none")
        out[be] = dict(e.covariances(s, tr, range(1, 31), BOTH))
    for k in range(1, 31):
        for q in BOTH:
            x, y = out["numpy"][k][q], out["auto"][k][q]
            assert np.array_equal(np.isfinite(x), np.isfinite(y))
            f = np.isfinite(x)
            np.testing.assert_allclose(y[f], x[f], rtol=1e-12, atol=1e-300)
