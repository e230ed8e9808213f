"""plotting.save's cheaper figure (issue 20): laid out at the dpi it is saved at, one draw per format, the footnote wrapped by bisection with
matplotlib's own line breaks, PNGs as RGB, unfiltered rows at a lower zlib level — and the same pixels as matplotlib's plain path."""

import io

import numpy as np
import pytest
import matplotlib.image as mpimg
from PIL import Image
from matplotlib.figure import Figure

from netkf_cli.runtime import plotting as P

NOTES = [
    "provenance " * 40,
    r"runs of $\bar V$ and $\lambda_c$ " * 6,
    # math spans with spaces: prefixes that end inside a span are drawn as plain text ("$\mathrm{tr}\,E[P_{k"),
    # the next ones as mathtext again
    r"Monte Carlo: $\mathrm{tr}\,E[P_{k \mid k-1}]$ against $\sum_{i=1}^{N} a_i$ over n = 400 runs " * 4,
    "first line kept as given\n$P_0$ = system.P0; fading channel; packet: one packet per step carries all of y_k; "
    "threshold: kept iff Υ_t ≥ Υ_T (eq. 5) — receiver scenario=2: no cross-layer path (eqs 10–12)",
    "a single-word-line\n\nwordwordwordwordwordwordwordwordwordwordwordwordwordwordwordwordwordwordwordwordwordwordword x",
]


@pytest.mark.parametrize("width", [6.4, 3.5])
@pytest.mark.parametrize("text", NOTES, ids=range(len(NOTES)))
def test_footnote_breaks_are_matplotlibs(text, width):
    fig, _ = P.new_figure(width=width)
    t = fig.text(0.01, 0.005, text, fontsize=P.MIN_FONT_PT, ha="left", va="bottom", wrap=True)
    t.get_window_extent(fig.canvas.get_renderer())
    theirs = t._get_wrapped_text()  # matplotlib's scan over every prefix
    assert theirs.count("\n") > text.count("\n")  # the case wraps at all
    assert P._wrapped_text(t) == theirs
    # with a right margin: matplotlib's scan over a room that much narrower
    room = t._get_wrap_line_width()
    margin = P.FOOTNOTE_X * fig.bbox.width
    ours = P._wrapped_text(t, margin)
    t._get_wrap_line_width = lambda: room - margin
    assert ours == t._get_wrapped_text()
    P._mpl().plt.close(fig)


def test_a_footnote_keeps_its_left_margin_on_the_right():
    """matplotlib wraps to the canvas edge: this text's widest line ends 6 px from it (past the left margin's
    width); netkf's footnote lines end at least FOOTNOTE_X of the width before it."""
    text = " ".join(["kept", "iff", "Υ_t", "≥", "Υ_T"] * 40)
    fig, _ = P.new_figure(width=6.4)
    P.footnote(fig, text)
    (t,) = fig._netkf_footnotes
    t.get_window_extent(fig.canvas.get_renderer())
    x0, right = P.FOOTNOTE_X * fig.bbox.width, (1 - P.FOOTNOTE_X) * fig.bbox.width
    theirs = [x0 + t._get_rendered_text_width(line) for line in t._get_wrapped_text().split("\n")]
    assert max(theirs) > right  # the case: matplotlib's own breaks run into the right margin
    P._layout(fig)  # what save does first: the footnote's breaks frozen
    ours = [x0 + t._get_rendered_text_width(line) for line in t.get_text().split("\n")]
    assert len(ours) > 1 and max(ours) <= right
    P._mpl().plt.close(fig)


def _figure():
    fig, ax = P.new_figure()
    x = np.logspace(-3, 2, 40)
    for i in range(3):
        ax.loglog(x, (i + 1) / (1 + x), **{**P.series_style(i), "markevery": 5}, label=rf"$\lambda$ = {i}")
    ax.set_title(P.paper_title("critical", None, r"$\mathrm{tr}\,E[P_{k \mid k-1}]$ against the arrival rate"))
    ax.set_xlabel(r"$\lambda$")
    ax.set_ylabel("trace")
    P.legend_outside(ax)
    P.footnote(fig, NOTES[2])
    return fig


def test_one_draw_per_format_and_the_pixels_of_matplotlibs_path(tmp_path, monkeypatch):
    draws = []
    real = Figure.draw
    monkeypatch.setattr(Figure, "draw", lambda self, renderer: (draws.append(1), real(self, renderer))[1])
    (png,) = P.save(_figure(), tmp_path / "f.png")
    assert len(draws) == 1  # tight_layout's placeholder engine made savefig draw twice
    monkeypatch.setattr(Figure, "draw", real)

    fig = _figure()  # the same figure through matplotlib's own calls: its wrapping, layout engine left, zlib 6
    fig.set_dpi(P.STYLE["savefig.dpi"])  # save lays a figure out at the dpi it writes it at
    notes = fig._netkf_footnotes
    r = fig.canvas.get_renderer()
    h, y = fig.bbox.height, 0.005 * fig.bbox.height
    for t in notes:
        t.set_y(y / h)
        y += t.get_window_extent(r).height + 2
    fig.tight_layout(rect=(0, min(0.4, (y + 4) / h), 1, 1))
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=P.STYLE["savefig.dpi"])
    P._mpl().plt.close(fig)
    ours, theirs = mpimg.imread(png), mpimg.imread(io.BytesIO(buf.getvalue()), format="png")
    # matplotlib writes RGBA whatever the figure holds; ours is RGB when every pixel is opaque (a netkf figure's face)
    assert theirs.shape[2] == 4 and (theirs[:, :, 3] == 1.0).all()
    assert ours.shape == theirs.shape[:2] + (3,) and np.array_equal(ours, theirs[:, :, :3])
    assert png.read_bytes() != buf.getvalue()  # RGB at another zlib level: other bytes, the same pixels
    with Image.open(png) as im, Image.open(io.BytesIO(buf.getvalue())) as mpl_im:
        assert im.mode == "RGB" and im.info["dpi"] == pytest.approx(mpl_im.info["dpi"])
        assert im.info["Software"] == mpl_im.info["Software"]


def test_a_figure_with_transparent_pixels_keeps_its_alpha(tmp_path):
    def figure():
        fig, ax = P.new_figure()
        fig.patch.set_alpha(0.0)  # a see-through face: RGB would paint it black
        ax.plot([0, 1], [0, 1], label="x")
        ax.set_title("t")
        return fig

    (png,) = P.save(figure(), tmp_path / "f.png")
    fig = figure()
    fig.set_dpi(P.STYLE["savefig.dpi"])
    P._layout(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=P.STYLE["savefig.dpi"])  # matplotlib's PNG of the same figure
    P._mpl().plt.close(fig)
    with Image.open(png) as im:
        assert im.mode == "RGBA" and im.getextrema()[3][0] < 255
    assert np.array_equal(mpimg.imread(png), mpimg.imread(io.BytesIO(buf.getvalue()), format="png"))
