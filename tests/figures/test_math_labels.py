"""Plain-text math in CSV labels is typeset in figures (metrics.common.math_text): Leong's closed forms and the
smoother's conventions drew "1-(1-λ)^(k1+N+1)" and "P_{k-1|k}" raw in legends and footnotes."""

import pytest

from netkf_cli.metrics.common import conventions_note, math_text
from netkf_cli.runtime import plotting


@pytest.mark.parametrize("plain, typeset", [
    ("guarantee 1-(1-λ)^(k1+N+1) of eq. (8), smoothed", r"guarantee $1-(1-\lambda)^{k_1+N+1}$ of eq. (8), smoothed"),
    ("1-(1-λ)^k1 of eq. (7)", r"$1-(1-\lambda)^{k_1}$ of eq. (7)"),
    ("Lemma 1 lower bound (1-λ)^(N+1) E[tr P_k|k-1], smoothed",
     r"Lemma 1 lower bound $(1-\lambda)^{N+1}$ $\mathrm{E}[\mathrm{tr}\,P_{k \mid k-1}]$, smoothed"),
    ("smoothed: P_{k-1|k} (lag N = 1)", r"smoothed: $P_{k-1 \mid k}$ (lag N = 1)"),
    ("P0 = P̄ (steady state)", r"$P_0$ = $\bar{P}$ (steady state)"),
    (r"left alone: $P_{k|k}$, E[tr P]", r"left alone: $P_{k|k}$, E[tr P]"),
])
def test_math_text(plain, typeset):
    assert math_text(plain) == typeset


def test_every_typeset_label_parses():
    """What math_text makes is valid mathtext (matplotlib raises on a bad string when it lays it out)."""
    plotting._mpl()  # matplotlib as netkf sets it up
    from matplotlib.mathtext import MathTextParser

    parser = MathTextParser("agg")
    for s in ("guarantee 1-(1-λ)^(k1+N+1) of eq. (8)", "(1-λ)^(N+1) E[tr P_k|k-1]", "P_{k-4|k} (lag N = 4)"):
        for i, part in enumerate(math_text(s).split("$")):
            if i % 2:
                parser.parse(f"${part}$", dpi=100)  # raises ValueError on bad mathtext


def test_conventions_note_is_typeset_and_balanced():
    note = conventions_note({"smoother lag=0": "bernoulli channel; smoothed: P_{k|k} (lag N = 0); filtered, predicted: kf's",
                             "smoother lag=2": "bernoulli channel; smoothed: P_{k-2|k} (lag N = 2); filtered, predicted: kf's"})
    assert note == (r"bernoulli channel; filtered, predicted: kf's — smoother lag=0: smoothed: $P_{k \mid k}$ (lag N = 0)"
                    r" | smoother lag=2: smoothed: $P_{k-2 \mid k}$ (lag N = 2)")
    assert note.count("(") == note.count(")")
