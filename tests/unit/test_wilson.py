"""core.stats.wilson_interval contains p̂ for every count (the tail figure's error bars hi − p̂ and p̂ − lo are
drawn as given: a rounding of p̃ + half to 1 − 2⁻⁵³ at p̂ = 1 made matplotlib refuse the figure)."""

from __future__ import annotations

import numpy as np

from netkf_cli.core.stats import wilson_interval


def test_the_interval_contains_the_proportion_at_every_count():
    n = np.arange(1, 20_001)
    for k in (0 * n, n, n // 2, n // 3, np.minimum(n, 7)):
        lo, hi = wilson_interval(k, n)
        p = k / n
        assert np.all(lo <= p) and np.all(p <= hi) and np.all(lo >= 0) and np.all(hi <= 1)
    lo0, hi1 = wilson_interval(0 * n, n)[0], wilson_interval(n, n)[1]
    assert np.all(lo0 == 0.0) and np.all(hi1 == 1.0)


def test_the_interval_is_wilsons_away_from_the_ends():
    k, n, z = 37, 200, 1.96
    p = k / n
    c = (p + z * z / (2 * n)) / (1 + z * z / n)
    h = z / (1 + z * z / n) * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    lo, hi = wilson_interval(k, n)
    assert (lo, hi) == (c - h, c + h)
