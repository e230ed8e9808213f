"""The estimator itself, not only its covariance: simulated states, the literal Prop. 3.1 re-runs."""

import numpy as np
import pytest

from netkf_cli.analysis.delay_exact import expected_updates
from netkf_cli.channels.delay import kept_at
from netkf_cli.estimators.buffered import covariance_from_kept, simulate_states

from ._systems import poisson, scalar_system, vehicle_system


@pytest.mark.parametrize("which", ["scalar", "vehicle"])
def test_error_variance_equals_predicted_covariance(which):
    """E[e_k e_kᵀ] = E[P_k] (P_k = E[e eᵀ | Y_k]) and E[e_kᵀ P_k⁻¹ e_k] = n.

    Per run, e_i²  and e P⁻¹ e are i.i.d. over runs: the sample means are compared with 5 standard
    errors of the per-run differences (e_i² − P_ii) and (eᵀP⁻¹e − n) — both have mean 0 exactly
    when the estimator is optimal.
    """
    if which == "scalar":
        s, ch, span, runs, k = scalar_system(), poisson(5, 10), 1, 20_000, 40
    else:
        s, ch, span, runs, k = vehicle_system(), poisson(3, 5), 2, 6_000, 25
    out = simulate_states(s, ch, span, runs, k, np.random.default_rng(11))
    e, P = out["e"], out["P"]
    for i in range(s.n):
        diff = e[:, i] ** 2 - P[:, i, i]
        assert abs(diff.mean()) <= 5 * diff.std(ddof=1) / np.sqrt(runs)
    nis = np.einsum("ri,rij,rj->r", e, np.linalg.inv(P), e) - s.n
    assert abs(nis.mean()) <= 5 * nis.std(ddof=1) / np.sqrt(runs)
    # the literal re-running estimator and the covariance-only path agree run by run
    kept = kept_at(out["delays"], k, ch.D, ch.convention)
    ref = np.moveaxis(covariance_from_kept(s, kept, span), -1, 0)
    assert np.allclose(P, ref, rtol=1e-9, atol=1e-12)


def test_literal_estimator_runs_the_expected_number_of_mkfs():
    """Mean MKF runs per step of the literal Prop. 3.1 estimator (steps k > D_max) vs the closed form."""
    s, ch = scalar_system(), poisson(5, 6)
    out = simulate_states(s, ch, 1, 4000, 30, np.random.default_rng(12))
    R = out["mkf_runs"][-1].astype(float)  # time k = 30 > D_max: stationary
    assert abs(R.mean() - expected_updates(ch)) <= 5 * R.std(ddof=1) / np.sqrt(len(R))
