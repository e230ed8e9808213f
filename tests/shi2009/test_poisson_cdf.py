"""The Poisson delay cdf (eq. 3) without scipy.stats: ``poisson_cdf`` gives scipy.stats.poisson.cdf's values bit for
bit (the same scipy.special.pdtr on the same arguments), its types (a scalar for a scalar), and its edges (0 below
the support, 1 at +∞, NaN for NaN)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from netkf_cli.analysis.delay_references import DelayLaw
from netkf_cli.analysis.laws import poisson_cdf


@pytest.mark.parametrize("mu", [0.0, 0.01, 3.0, 5.0, 5.5, 30.0, 200.0])
def test_poisson_cdf_is_scipy_stats_bit_for_bit(mu):
    for k in (np.arange(-3, 400), np.arange(-3.0, 400.0, 0.5), np.array([-np.inf, np.inf, np.nan, 2.0]),
              3, -1, 7.0, np.int64(4), [1, 2, 3], np.arange(6).reshape(2, 3)):
        want, got = stats.poisson.cdf(k, mu), poisson_cdf(k, mu)
        assert type(got) is type(want)
        assert np.asarray(got).shape == np.asarray(want).shape
        assert np.array_equal(np.asarray(got), np.asarray(want), equal_nan=True), (mu, k)


def test_poisson_cdf_edges_and_the_channel_use_it():
    assert poisson_cdf(-1, 5.0) == 0.0 and poisson_cdf(np.inf, 5.0) == 1.0 and np.isnan(poisson_cdf(np.nan, 5.0))
    assert poisson_cdf(0, 5.0) == pytest.approx(np.exp(-5.0), rel=1e-15)  # f(0) = e^{−d}
    law = DelayLaw.of({"kind": "delay", "delay": {"kind": "poisson", "mean": 5}, "buffer": 10})
    from netkf_cli.channels.delay import PoissonDelay

    i = np.arange(-2, 40)
    assert np.array_equal(law.cdf(i), stats.poisson.cdf(i, 5.0))
    assert np.array_equal(PoissonDelay(mean=5).cdf(i), stats.poisson.cdf(i, 5.0))
