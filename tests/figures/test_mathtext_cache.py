"""plotting.share_mathtext_parses: one process-wide cache of mathtext parses (matplotlib keeps 50 per
renderer, and every figure and every dpi gets a new renderer). Same pixels, far fewer parses."""

import io

import numpy as np
import matplotlib
from matplotlib.mathtext import MathTextParser
import matplotlib.image as mpimg

from netkf_cli.runtime import plotting as P


def _png(default: str | None = None) -> np.ndarray:
    """A figure with log axes (mathtext tick labels), math in labels, legend and footnote."""
    with matplotlib.rc_context({"mathtext.default": default} if default else {}):
        fig, ax = P.new_figure()
        x = np.logspace(-3, 2, 40)
        ax.loglog(x, 1 / (1 + x), **{**P.series_style(0), "marker": None}, label=r"$E[P_{k \mid k-1}]$")
        ax.set_xlabel(r"$\Upsilon_T$ (dB)")
        ax.set_ylabel(r"$\lim\ \mathrm{tr}\,E[P]$")
        ax.set_title(P.paper_title("fading", 5, r"$\|E\,P_\infty\|$ vs $\Upsilon_T$"))
        P.legend_outside(ax)
        P.footnote(fig, r"runs of $\bar V$ and $\lambda_c$ " * 6)
        buf = io.BytesIO()
        P._layout(fig)
        fig.savefig(buf, format="png", dpi=150)
        arr = mpimg.imread(io.BytesIO(buf.getvalue()), format="png")
        matplotlib.pyplot.close(fig)
    return arr


def test_installed_and_pixels_identical_to_matplotlibs_own_cache(monkeypatch):
    P.setup()  # matplotlib is set up at the first figure (tests/figures/test_lazy_matplotlib.py), not on import
    shared = MathTextParser._parse_cached
    assert getattr(shared, "_netkf_shared", False), "plotting should install the shared cache at set-up"
    shared.cache.cache_clear()
    cold = _png()
    misses_cold = shared.cache.cache_info().misses
    warm = _png()  # a second figure: every parse is a hit
    info = shared.cache.cache_info()
    assert info.misses == misses_cold and info.hits > 0
    monkeypatch.setattr(MathTextParser, "_parse_cached", shared.original)  # matplotlib's per-renderer cache
    theirs = _png()
    assert np.array_equal(cold, theirs) and np.array_equal(warm, theirs)


def test_rc_params_are_part_of_the_key():
    """A figure drawn with another mathtext.default (not part of the font properties) is not served the first one's parses."""
    stix = _png()
    dejavu = _png("regular")
    assert stix.shape == dejavu.shape and not np.array_equal(stix, dejavu)
    assert np.array_equal(_png(), stix)


def test_idempotent():
    assert P.share_mathtext_parses() is True
    assert getattr(MathTextParser._parse_cached, "_netkf_shared", False)
    assert not getattr(MathTextParser._parse_cached.original, "_netkf_shared", False)


def _shared_parses_in_child(_=None) -> int:
    from matplotlib.mathtext import MathTextParser
    return MathTextParser._parse_cached.cache.cache_info().currsize


def test_a_forked_child_starts_without_the_parents_parses():
    """A kept parse holds the parent's FT2Font objects, whose open font files a forked child shares (one file
    offset): two workers drawing glyphs through them failed with FT_Load_Glyph 'invalid outline'. The child
    starts with an empty shared cache (as matplotlib's own font cache: font_manager clears it at fork)."""
    import multiprocessing as mp

    import matplotlib.pyplot as plt
    from matplotlib.mathtext import MathTextParser

    P.setup()
    fig, ax = plt.subplots()
    ax.set_yscale("log")
    ax.plot([1, 2], [1e-3, 1e2])
    ax.set_title(r"$\mathrm{E}\,P_{k|k-1}$")
    fig.canvas.draw()
    plt.close(fig)
    assert MathTextParser._parse_cached.cache.cache_info().currsize > 0  # the parent keeps parses
    with mp.get_context("fork").Pool(1) as pool:
        assert pool.apply(_shared_parses_in_child) == 0
