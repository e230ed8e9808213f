"""netkf_cli.analysis.laws: the Binomial pmf/cdf the fusion bounds and the multi channel's count sampler read are
scipy.stats.binom's, bit for bit, on every argument rule (support, integrality, bad n or p, NaN, broadcasting),
and using them loads no scipy.stats."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scipy import stats

from netkf_cli.analysis.laws import binom_cdf, binom_pmf

KS = np.array([-np.inf, -3.0, -1.0, -0.5, 0.0, 0.5, 1.0, 2.0, 2.7, 5.0, 9.0, 10.0, 10.5, 11.0, 25.0, np.inf, np.nan])
NS = [0, 1, 2, 5, 10, 25, 60, 200]
PS = [0.0, 1e-12, 0.05, 0.3, 0.5, 0.7, 0.999999, 1.0]


@pytest.mark.parametrize("n", NS)
@pytest.mark.parametrize("p", PS)
def test_binomial_is_scipy_stats_bit_for_bit(n, p):
    ks = np.concatenate([KS, np.arange(n + 2, dtype=float)])
    for ours, theirs in ((binom_pmf, stats.binom.pmf), (binom_cdf, stats.binom.cdf)):
        got, want = ours(ks, n, p), theirs(ks, n, p)
        np.testing.assert_array_equal(got, want, err_msg=f"{ours.__name__}(k, {n}, {p})")
        assert got.dtype == want.dtype


@pytest.mark.parametrize("n, p", [(-1, 0.5), (2.5, 0.5), (5, -0.1), (5, 1.1), (5, np.nan), (np.nan, 0.5)])
def test_bad_arguments_are_nan_as_scipy_stats(n, p):
    for ours, theirs in ((binom_pmf, stats.binom.pmf), (binom_cdf, stats.binom.cdf)):
        np.testing.assert_array_equal(ours(KS, n, p), theirs(KS, n, p))


def test_broadcasting_and_scalars():
    k, n, p = np.arange(6)[:, None], np.array([3, 5]), np.array([[0.2], [0.9]])[:, :, None]
    for ours, theirs in ((binom_pmf, stats.binom.pmf), (binom_cdf, stats.binom.cdf)):
        np.testing.assert_array_equal(ours(k, n, p), theirs(k, n, p))
        assert ours(2, 5, 0.3) == theirs(2, 5, 0.3) and np.ndim(ours(2, 5, 0.3)) == 0


def test_the_fusion_bounds_and_the_count_sampler_load_no_scipy_stats():
    code = ("import sys; from netkf_cli.analysis import fusion_bounds as fb; from netkf_cli.channels import multi; "
            "fb.backward_transition(25, 0.3); multi.count_tables(25, 0.6); print('scipy.stats' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "False"
