"""The markov_modes channel: validation, stationary marginals, vectorized sampling."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from netkf_cli.channels.markov_modes import (
    MarkovModesChannel,
    PrecedenceWarning,
    sample_modes,
    stationary_distribution,
    validate_transition,
)
from netkf_cli.core.errors import ConfigError
from netkf_cli.config.loader import load_scenario_text

from .conftest import CONFIGS, PRINTED_RHO


@pytest.mark.parametrize("name", ["example1", "example2"])
def test_stationary_matches_printed_rho(name):
    # ρ_q = Σ_j ρ_{q/j} ρ_j (text after eq. 20) against the ρ_q the paper prints with each example.
    from .conftest import setup_of

    _, (_, ch, est, *_rest) = setup_of(name)
    np.testing.assert_allclose(ch.rho, PRINTED_RHO[name], rtol=0, atol=1e-12)
    np.testing.assert_allclose(est.rho, PRINTED_RHO[name], rtol=0, atol=0)


def test_empirical_frequencies_match_stationary(example):
    # Per-run fraction of time in each mode: runs are independent, so the mean over R runs has
    # standard error s/√R (s = sample std of the per-run fractions); θ(0) is stationary, so every
    # θ(k) has marginal ρ exactly. 5σ two-sided.
    ch = example["ch"]
    rng = np.random.default_rng(1)
    R, K = 4000, 60
    modes = ch.sample(rng, R, K)
    assert modes.shape == (R, K) and modes.dtype == np.int8
    frac = np.stack([(modes == q).mean(axis=1) for q in range(4)], axis=1)
    se = frac.std(axis=0, ddof=1) / np.sqrt(R)
    assert np.all(np.abs(frac.mean(axis=0) - ch.rho) <= 5 * se + 1e-12)
    # the precedence constraint of the printed chains: mode 2 never follows mode 1
    assert not np.any((modes[:, :-1] == 0) & (modes[:, 1:] == 1))


def test_empirical_transitions():
    # Transition counts from a long chain: each row is a multinomial; 5σ with the binomial s.e.
    T = validate_transition([[0.5, 0.2, 0.2, 0.1], [0.1, 0.6, 0.2, 0.1], [0.3, 0.3, 0.3, 0.1], [0.25] * 4])
    modes = sample_modes(np.random.default_rng(2), 200, 500, T, stationary_distribution(T))
    a, b = modes[:, :-1].ravel(), modes[:, 1:].ravel()
    for j in range(4):
        nj = (a == j).sum()
        phat = np.bincount(b[a == j], minlength=4) / nj
        # Markov-chain pairs from the same row are not independent across time, but given the
        # previous mode the next one is a fresh draw: counts are exactly multinomial given n_j.
        assert np.all(np.abs(phat - T[j]) <= 5 * np.sqrt(T[j] * (1 - T[j]) / nj) + 1e-12)


@pytest.mark.parametrize("T, msg", [
    ([[0.5, 0.5, 0, 0]] * 3, "must be 4×4"),
    ([[0.8, 0, 0.1, 0.2], [0.25] * 4, [0.25] * 4, [0.25] * 4], "must sum to 1"),
    ([[1.1, 0, -0.1, 0], [0.25] * 4, [0.25] * 4, [0.25] * 4], "probabilities in [0, 1]"),
])
def test_bad_transition(T, msg):
    with pytest.raises(ConfigError, match=msg.replace("[", r"\[").replace("]", r"\]")):
        validate_transition(T)


def test_reducible_chain_rejected():
    T = [[1, 0, 0, 0], [0, 1, 0, 0], [0.5, 0, 0.5, 0], [0, 0, 0, 1]]
    with pytest.raises(ValueError, match="more than one stationary distribution"):
        MarkovModesChannel(kind="markov_modes", transition=T)


def test_precedence_warning():
    T = [[0.7, 0.1, 0.1, 0.1]] + [[0.7, 0.1, 0.1, 0.1]] * 3
    with pytest.warns(PrecedenceWarning, match=r"ρ_\{2/1\}"):
        MarkovModesChannel(kind="markov_modes", transition=T)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        MarkovModesChannel(kind="markov_modes", transition=[[0.8, 0, 0.1, 0.1]] + [[0.7, 0.1, 0.1, 0.1]] * 3)


def test_scenario_error_has_dotted_path():
    text = (CONFIGS / "example2.yaml").read_text().replace("- [0.7, 0.15, 0.05, 0.10]\n    - [0.7, 0.15, 0.05, 0.10]\n    - [0.7, 0.15, 0.05, 0.10]",
                                                              "- [0.7, 0.15, 0.05, 0.30]\n    - [0.7, 0.15, 0.05, 0.10]\n    - [0.7, 0.15, 0.05, 0.10]")
    with pytest.raises(ConfigError) as ei:
        load_scenario_text(text, "example2.yaml")
    msg = str(ei.value)
    assert "channel" in msg and "must sum to 1" in msg


def test_recipe_input_errors(tmp_path):
    from netkf_cli.recipes.base import RunContext

    base = (CONFIGS / "example1_exact.yaml").read_text()
    with pytest.raises(ConfigError) as ei:  # refused at load time (netkf validate)
        load_scenario_text(base.replace("S: [[0.2], [0.0]]", "S: [[0.2, 0.0]]"))
    assert "estimator.S" in {p.path for p in ei.value.problems}
    with pytest.raises(ConfigError) as ei:  # refused at load time too (the recipe's check, netkf validate)
        load_scenario_text(base.replace("xs0: [2, -2]", "xs0: [2, -2, 1]"))
    assert "analysis.xs0" in {p.path for p in ei.value.problems}
    with pytest.raises(ConfigError, match="positive semi-definite") as ei:  # refused at load time or at compute
        sc = load_scenario_text(base.replace("S: [[0.2], [0.0]]", "S: [[5.0], [0.0]]"))
        sc.analysis.compute(sc, RunContext(runs=10))
    assert ei.value.problems[0].path == "estimator.S"
    with pytest.raises(ConfigError, match="montecarlo.burn_in"):  # refused at load time (netkf validate) or at compute
        sc = load_scenario_text(base.replace("burn_in: 50", "burn_in: 100"))
        sc.analysis.compute(sc, RunContext(runs=10))
