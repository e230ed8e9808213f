"""Monte Carlo against the exact second moments, and the ordering of the four filters — on the generic
state path (:func:`netkf_cli.engine.state.simulate_errors`: the plant behind the channel's mode trace, every
``markov_lmi`` filter's ``estimates`` on the same runs), netkf's time base (P0 = P_{0|0}, first measurement y_1)."""

from __future__ import annotations

import numpy as np
import pytest

from netkf_cli.engine import state
from netkf_cli.estimators.markov_filters import exact_mse, lmmse_filter, naive_filter
from netkf_cli.estimators.markov_lmi import lmi_design
from netkf_cli.core.stats import mean_se

from .conftest import setup_of

Z = 5.0  # 5σ two-sided: p ≈ 6e-7 per comparison, so the ~130 comparisons below stay far from a false alarm
K, BURN, R = 40, 20, 3000
FILTERS = ("lmmse", "mode_aware", "lmi", "naive")  # lmmse first: the paired window differences are against it
QS = ("predicted", "filtered")


@pytest.fixture(scope="module", params=["example1", "example2"])
def run(request):
    sc, (sysm, ch, est, md, x0, xs0, P0, rho) = setup_of(request.param)
    ests = [est.model_copy(update={"filter": f, "rho": [float(r) for r in rho], "design": "closed_form",
                                   "sdp_check": 0}) for f in FILTERS]
    window = list(range(BURN + 1, K + 1))
    st = state.simulate_errors(sysm, ch, ests, steps=list(range(1, K + 1)), runs=R, horizon=K, seed=11, chunk=R,
                               quantity=QS, window=window, S=None if est.S is None else np.asarray(est.S, float))
    model, mx0, mP0 = ests[0]._model(sysm)
    return dict(st=st, ch=ch, model=model, x0=mx0, P0=mP0, rho=rho)


def _col(f: str, q: str) -> int:
    return FILTERS.index(f) * len(QS) + QS.index(q)  # state.columns_of: estimator-major


def test_linear_filters_exact_vs_monte_carlo(run):
    # Every linear filter's MSE is computable exactly (joint Markov-jump second moments, :func:`exact_mse` on
    # the contract time base: index i ↔ the measurement y_{i+1}, so P_{k|k} ↔ mse_f[k−1], P_{k+1|k} ↔ mse_p[k]);
    # the Monte Carlo mean of ‖e_k‖² over R independent runs has s.e. s_k/√R. Checked per k (every 5th step)
    # and on the window average, for LMMSE, LMI and naive KF, predicted and filtered. The gains are the ones
    # the estimator builds (closed-form LMI design).
    st, ch, md, x0, P0 = run["st"], run["ch"], run["model"], run["x0"], run["P0"]
    prior_x = md.prior_moments(x0, P0, "contract")[1][: md.n, : md.n]
    gains = {"lmmse": lmmse_filter(md, ch.T, ch.pi0, x0, P0, K + 1, base="contract"),
             "naive": naive_filter(md, x0, prior_x, K + 1),
             "lmi": lmi_design(md, run["rho"], x0, P0, K + 1, design="closed_form", base="contract").filter}
    ks = np.arange(1, K + 1)
    for f, F in gains.items():
        mse_p, mse_f = exact_mse(md, F, ch.T, ch.pi0, x0, P0, base="contract")
        exact = {"filtered": mse_f[ks - 1], "predicted": mse_p[ks]}
        for q in QS:
            c = _col(f, q)
            e2, e4 = st[f"sum_e2_{c}"], st[f"sum_e4_{c}"]
            m, s = mean_se(e2, e4, R)
            sel = slice(0, K, 5)
            assert np.all(np.abs(m[sel] - exact[q][sel]) <= Z * s[sel]), (f, q, m[sel], exact[q][sel], s[sel])
            wm, ws = mean_se(st[f"win_sum_{c}"][0], st[f"win_sumsq_{c}"][0], R)
            assert abs(wm - exact[q][BURN:].mean()) <= Z * ws, (f, q, wm, exact[q][BURN:].mean(), ws)
    # mode-aware KF: its own P (conditional on the mode path) averaged over runs estimates the same E‖e‖² as
    # its squared errors; both are Monte Carlo means over the same runs (positively correlated), so
    # |a − b| ≤ 5·√(s_a² + s_b²) is conservative.
    for q in QS:
        c = _col("mode_aware", q)
        (a, b), (sa, sb) = mean_se(st[f"win_sum_{c}"][:2], st[f"win_sumsq_{c}"][:2], R)
        assert abs(a - b) <= Z * np.hypot(sa, sb), (q, a, b, sa, sb)


def test_ordering_on_same_runs(run):
    # Paired per-run differences of the window-averaged squared error against LMMSE (the filters see the same
    # runs): mode-aware ≤ LMMSE ≤ LMI and LMMSE ≤ naive KF, each within 5 s.e. of the paired difference.
    st = run["st"]
    for f, sign in (("mode_aware", -1.0), ("lmi", 1.0), ("naive", 1.0)):
        for q in QS:
            c = _col(f, q)
            n = float(st[f"diff_n_{c}"])
            assert n == R
            dm, ds = mean_se(st[f"diff_sum_{c}"], st[f"diff_sumsq_{c}"], n)
            assert sign * dm >= -Z * ds, (f, q, dm, ds)
