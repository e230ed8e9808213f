"""Monte Carlo against the exact second moments, and the ordering of the four filters."""

from __future__ import annotations

import numpy as np

from netkf_cli.estimators.markov_filters import MarkovMSEKernel, exact_mse, lmmse_filter, naive_filter
from netkf_cli.estimators.markov_lmi import lmi_design
from netkf_cli.montecarlo import mean_and_stderr, run_chunked
from netkf_cli.recipes.markov import ESTIMATES

Z = 5.0  # 5σ two-sided: p ≈ 6e-7 per comparison, so ~60 comparisons below stay far from a false alarm


def test_linear_filters_exact_vs_monte_carlo(example):
    # Every linear filter's MSE is computable exactly (joint Markov-jump second moments);
    # the Monte Carlo mean of ‖e(k)‖² over R independent runs has s.e. s_k/√R. Check per k
    # (every 5th step) and the window average, for LMMSE, LMI and naive KF, predicted and filtered.
    # The closed-form LMI design is used (the SDP is checked against it in test_filters).
    e = example
    md, T, pi0, x0, P0 = e["model"], e["T"], e["pi0"], e["x0"], e["P0"]
    K, burn, R = 40, 20, 3000
    linear = {"lmmse": lmmse_filter(md, T, pi0, x0, P0, K), "naive_kf": naive_filter(md, x0, P0, K),
              "lmi": lmi_design(md, e["rho"], x0, P0, K, design="closed_form").filter}
    st = run_chunked(MarkovMSEKernel(md, e["ch"], linear, x0, P0, K, burn), R, 1500, 11)
    for f, F in linear.items():
        ex = exact_mse(md, F, T, pi0, x0, P0)
        for ie, est in enumerate(ESTIMATES):
            m, s = mean_and_stderr(st[f"sum_{f}_{est}"], st[f"sq_{f}_{est}"], R)
            ks = np.arange(1, K, 5)
            assert np.all(np.abs(m[ks] - ex[ie][ks]) <= Z * s[ks]), (f, est, m[ks], ex[ie][ks], s[ks])
            wm, ws = mean_and_stderr(st[f"win_{f}_{est}"], st[f"winsq_{f}_{est}"], R)
            assert abs(wm - ex[ie][burn:].mean()) <= Z * ws, (f, est)
    # mode-aware KF: its own P (conditional on the mode path) averaged over runs estimates the same
    # E‖e‖² as its squared errors; both are Monte Carlo means over the same runs (positively
    # correlated), so |a − b| ≤ 5·√(s_a² + s_b²) is conservative.
    for est in ESTIMATES:
        a, sa = mean_and_stderr(st[f"win_mode_aware_kf_{est}"], st[f"winsq_mode_aware_kf_{est}"], R)
        b, sb = mean_and_stderr(st[f"win_trP_{est}"], st[f"winsq_trP_{est}"], R)
        assert abs(a - b) <= Z * np.hypot(sa, sb)


def test_ordering_on_same_runs(example):
    # Paired per-run differences of the window-averaged squared error (the filters see the same
    # runs): mean difference ≥ −5 s.e. for mode-aware ≤ LMMSE ≤ LMI and LMMSE ≤ naive KF.
    e = example
    md, T, pi0, x0, P0 = e["model"], e["T"], e["pi0"], e["x0"], e["P0"]
    K, burn, R = 40, 20, 3000
    linear = {"lmmse": lmmse_filter(md, T, pi0, x0, P0, K), "naive_kf": naive_filter(md, x0, P0, K),
              "lmi": lmi_design(md, e["rho"], x0, P0, K, design="closed_form").filter}
    st = run_chunked(MarkovMSEKernel(md, e["ch"], linear, x0, P0, K, burn), R, 3000, 12)
    for a, b in (("lmmse", "mode_aware_kf"), ("lmi", "lmmse"), ("naive_kf", "lmmse")):
        for est in ESTIMATES:
            dm, ds = mean_and_stderr(st[f"dwin_{a}_{b}_{est}"], st[f"dwinsq_{a}_{b}_{est}"], R)
            assert dm >= -Z * ds, (a, b, est, dm, ds)
