"""runtime.drawcache: glyph bitmaps, ticks and plain-text extents done once per process — the same pixels and the
same tick state as matplotlib's own path (each test puts matplotlib's function back and compares)."""

import io
import types

import matplotlib
import matplotlib.image as mpimg
import numpy as np
import pytest
from matplotlib import _mathtext
from matplotlib import axis as maxis
from matplotlib import text as mtext
from matplotlib.artist import Artist
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import RendererAgg
from matplotlib.cbook import CallbackRegistry
from matplotlib.figure import Figure
from matplotlib.font_manager import FontProperties
from matplotlib.markers import MarkerStyle
from matplotlib.mathtext import MathTextParser
from matplotlib.path import Path
from matplotlib.transforms import TransformNode

from netkf_cli.runtime import drawcache
from netkf_cli.runtime import plotting as P


@pytest.fixture(autouse=True)
def _installed():
    P.setup()
    assert all(P._mpl().drawcache.values()), P._mpl().drawcache


def _figure(rotated: bool = False):
    """Log and linear axes (mathtext and plain tick labels, minor ticks), math with rule boxes, a rotated label,
    legend and footnote."""
    fig, (a, b) = P.new_figure(ncols=2, width=4.2)
    x = np.logspace(-3, 2, 40)
    a.loglog(x, 1 / (1 + x), **{**P.series_style(0), "marker": None}, label=r"$\frac{1}{1+x}$")
    a.set_xlabel(r"$\sqrt{\Upsilon_T}$ (dB)")
    a.set_ylabel(r"$\lim\ \mathrm{tr}\,E[P_{k \mid k-1}]$")
    b.plot(np.arange(12), np.arange(12) ** 1.5, **P.series_style(1), label="linear, 1.5")
    b.set_xticks(range(0, 12, 2), [f"tick {i}" for i in range(0, 12, 2)], rotation=30 if rotated else 0)
    b.set_title("Text at 0.3 px offsets: «Ωμ ≤ 0.25»", fontsize=10)
    fig.suptitle(P.paper_title("fading", 5, r"$\|E\,P_\infty\|$ vs $\Upsilon_T$"))
    P.legend_outside(b)
    P.footnote(fig, r"runs of $\bar V$ and $\lambda_c$, $\frac{a}{b}$ " * 5)
    return fig


def _pixels(fig) -> np.ndarray:
    buf = io.BytesIO()
    P._layout(fig)
    fig.savefig(buf, format="png", dpi=150)
    P._mpl().plt.close(fig)
    return mpimg.imread(io.BytesIO(buf.getvalue()), format="png")


def _matplotlibs(monkeypatch):
    """matplotlib's own functions back in place of every drawcache path."""
    monkeypatch.setattr(RendererAgg, "_draw_text_glyphs_and_boxes", RendererAgg._draw_text_glyphs_and_boxes.original)
    monkeypatch.setattr(RendererAgg, "draw_text", RendererAgg.draw_text.original)
    monkeypatch.setattr(maxis.Axis, "_get_tick", maxis.Axis._get_tick.original)
    monkeypatch.setattr(mtext, "_get_text_metrics_with_cache", mtext._get_text_metrics_with_cache.original)
    monkeypatch.setattr(mtext.Text, "_get_layout", mtext.Text._get_layout.original)
    monkeypatch.setattr(_mathtext.TruetypeFonts, "_get_info", _mathtext.TruetypeFonts._get_info.original)
    # parses made with the kept glyph infos are not served to matplotlib's path: its own per-parser cache
    monkeypatch.setattr(MathTextParser, "_parse_cached", MathTextParser._parse_cached.original)


@pytest.mark.parametrize("rotated", [False, True])
def test_same_pixels_as_matplotlibs_path(monkeypatch, rotated):
    RendererAgg._draw_text_glyphs_and_boxes.bitmaps.clear()
    RendererAgg.draw_text.positions.clear()
    cold = _pixels(_figure(rotated))
    warm = _pixels(_figure(rotated))  # glyphs, ticks and extents from the first figure
    assert RendererAgg._draw_text_glyphs_and_boxes.bitmaps and RendererAgg.draw_text.positions
    _matplotlibs(monkeypatch)
    theirs = _pixels(_figure(rotated))
    assert np.array_equal(cold, theirs) and np.array_equal(warm, theirs)


def test_unantialiased_text_same_pixels(monkeypatch):
    """FreeType's monochrome bitmaps (0/1, scaled to 0/255 once when kept)."""
    with matplotlib.rc_context({"text.antialiased": False}):
        ours = [_pixels(_figure()), _pixels(_figure())]
        _matplotlibs(monkeypatch)
        theirs = _pixels(_figure())
    assert np.array_equal(ours[0], theirs) and np.array_equal(ours[1], theirs)


def _strings(dpi):
    """One string at several sizes, weights and families, and rotated: kept positions must not cross them."""
    fig = P._mpl().plt.figure(figsize=(4, 3), dpi=dpi)
    for i, kw in enumerate([dict(size=9), dict(size=13), dict(size=9, weight="bold"), dict(size=9, family="serif"),
                            dict(size=11, rotation=20), dict(size=9, family="monospace")]):
        fig.text(0.05, 0.08 + 0.15 * i, "Monte Carlo 0.25 AVWA", **kw)
    for angle in (0, 20, 90):  # the first glyph of each at the same whole pixel: the same sub-pixel offset
        fig.text(200, 100, "MWM", rotation=angle, rotation_mode="anchor", ha="left", va="baseline", transform=None)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    P._mpl().plt.close(fig)
    return mpimg.imread(io.BytesIO(buf.getvalue()), format="png")


def test_one_string_in_other_fonts_sizes_and_dpis_same_pixels(monkeypatch):
    ours = [_strings(dpi) for dpi in (100, 150, 100)]
    _matplotlibs(monkeypatch)
    theirs = [_strings(dpi) for dpi in (100, 150)]
    assert all(np.array_equal(a, b) for a, b in zip(ours, theirs + theirs[:1]))


def test_a_glyph_moved_by_whole_pixels_is_the_same_bitmap_moved():
    """What the kept bitmaps rest on: FreeType renders a glyph offset by 64·q + r (1/64 px) as the glyph at r,
    moved by q pixels — and at another r, another bitmap (so the key must hold r)."""
    from matplotlib import ft2font
    from matplotlib.font_manager import findfont, get_font

    identity = np.array([[0x10000, 0], [0, 0x10000]])
    rotated = (0x10000 * np.array([[0.8, -0.6], [0.6, 0.8]])).round().astype(int)
    for path in (findfont("DejaVu Sans"), findfont(FontProperties(family="STIXGeneral"))):
        font = get_font(path)
        for ch in "g1Ω≤":
            index = font.get_char_index(ord(ch))
            for matrix in (identity, rotated):
                def render(dx, dy):
                    font.set_size(9, 150)
                    font._set_transform(matrix, [dx, dy])
                    b = font._render_glyph(index, ft2font.LoadFlags.DEFAULT, ft2font.RenderMode.NORMAL)
                    return np.array(b.buffer), b.left, b.top
                for rx, ry in ((0, 0), (21, 40), (63, 1)):
                    base, left, top = render(rx, ry)
                    for qx, qy in ((1, 0), (37, 512), (4000, 7)):
                        moved, left2, top2 = render(64 * qx + rx, 64 * qy + ry)
                        assert np.array_equal(moved, base) and (left2, top2) == (left + qx, top + qy)
                shifted = render(32, 0)[0]
                assert shifted.shape != render(0, 0)[0].shape or not np.array_equal(shifted, render(0, 0)[0])


def test_another_method_source_keeps_matplotlibs(monkeypatch):
    """The glyph path repeats matplotlib 3.11's method: over any other source it is not installed."""
    original = RendererAgg._draw_text_glyphs_and_boxes.original

    def _draw_text_glyphs_and_boxes(self, gc, x, y, angle, glyphs, boxes):  # another body
        return original(self, gc, x, y, angle, glyphs, boxes)

    monkeypatch.setattr(RendererAgg, "_draw_text_glyphs_and_boxes", _draw_text_glyphs_and_boxes)
    assert drawcache.share_glyph_bitmaps(P._mpl()) is False
    assert RendererAgg._draw_text_glyphs_and_boxes is _draw_text_glyphs_and_boxes
    monkeypatch.setattr(RendererAgg, "_draw_text_glyphs_and_boxes", original)  # matplotlib's: what it was written from
    assert drawcache._source_hash(original) == drawcache.GLYPHS_SOURCE


# ------------------------------------------------------------------------------------------------- ticks
def _same(a, b, path="", seen=None) -> list[str]:
    """Where two tick states differ (empty: the same): artists attribute by attribute, arrays, paths, markers and
    transforms by value; font properties and callback registries by value and never shared."""
    seen = set() if seen is None else seen
    if (id(a), id(b)) in seen:
        return []
    seen.add((id(a), id(b)))
    if isinstance(a, (Axes, Figure)):
        return [] if a is b else [f"{path}: another axes or figure"]
    if isinstance(a, Artist) or isinstance(a, MarkerStyle):
        if type(a) is not type(b):
            return [f"{path}: {type(a).__name__} vs {type(b).__name__}"]
        if isinstance(a, Artist) and a is b and path:
            return [f"{path}: the same artist object"]
        da, db = vars(a), vars(b)
        if da.keys() != db.keys():
            return [f"{path}: attributes {sorted(da.keys() ^ db.keys())}"]
        return [d for k in da for d in _same(da[k], db[k], f"{path}.{k}", seen)]
    if isinstance(a, CallbackRegistry) or isinstance(a, FontProperties):
        if a is b:
            return [f"{path}: shared"]
        ok = a.callbacks == b.callbacks if isinstance(a, CallbackRegistry) else a == b
        return [] if ok else [f"{path}: {a!r} vs {b!r}"]
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return [] if np.array_equal(np.asarray(a), np.asarray(b)) and np.asarray(a).dtype == np.asarray(b).dtype \
            else [f"{path}: {a!r} vs {b!r}"]
    if isinstance(a, Path):
        return _same(a.vertices, b.vertices, path + ".vertices", seen) + _same(a.codes, b.codes, path + ".codes", seen) \
            + ([] if a._interpolation_steps == b._interpolation_steps else [f"{path}: interpolation steps"])
    if isinstance(a, TransformNode):
        same = type(a) is type(b) and str(a) == str(b)  # the transform tree with its values
        affine = getattr(a, "is_affine", False) and hasattr(a, "get_matrix")
        return [] if same and (not affine or np.array_equal(a.get_matrix(), b.get_matrix())) else [f"{path}: {a} vs {b}"]
    if isinstance(a, types.MethodType):  # a marker's drawing function, bound to its own marker
        return [] if isinstance(b, types.MethodType) and a.__func__ is b.__func__ else [f"{path}: {a!r} vs {b!r}"]
    if isinstance(a, (list, tuple)):
        if type(a) is not type(b) or len(a) != len(b):
            return [f"{path}: {a!r} vs {b!r}"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in _same(x, y, f"{path}[{i}]", seen)]
    try:
        ok = a == b
    except Exception:
        ok = a is b
    return [] if ok is True or (isinstance(ok, np.bool_) and ok) else [f"{path}: {a!r} vs {b!r}"]


def _axes_with_ticks():
    fig, (a, b) = P.new_figure(ncols=2, width=3.5)
    a.loglog(np.logspace(-2, 3, 20), np.logspace(0, 4, 20))
    b.plot([0, 1], [2, 7])
    b.xaxis.set_tick_params(labelsize=11, pad=6, direction="in")  # the tick keywords of b's x-axis changed
    fig.canvas.draw()  # every axis has constructed its ticks (and drawcache its prototypes)
    return fig, [ax for ax in (a, b)]


@pytest.mark.parametrize("major", [True, False])
def test_a_copied_tick_is_a_constructed_tick(major):
    """The state of a new tick, copied from the prototype, equals matplotlib's construction — after what the axis
    then does to either (props from its first tick, a position, a label)."""
    fig, axes = _axes_with_ticks()
    construct = maxis.Axis._get_tick.original
    for ax in axes:
        for axis in (ax.xaxis, ax.yaxis):
            ticks = axis.majorTicks if major else axis.minorTicks
            made = []
            for get in (lambda: construct(axis, major), lambda: axis._get_tick(major)):
                t = get()
                axis._copy_tick_props(ticks[0], t)
                t.update_position(3.0)
                t.label1.set_text("3")
                made.append(t)
            theirs, ours = made
            diff = _same(theirs, ours)
            assert diff == [], (axis, major, diff)
    P._mpl().plt.close(fig)


def test_copies_share_no_artist_font_or_callbacks():
    fig, axes = _axes_with_ticks()
    axis = axes[0].yaxis
    one, two = axis._get_tick(True), axis._get_tick(True)
    for name in ("tick1line", "tick2line", "gridline", "label1", "label2"):
        x, y = getattr(one, name), getattr(two, name)
        assert x is not y and x._callbacks is not y._callbacks
    one.label1.set_fontsize(20)
    one.gridline.set_color("red")
    one.tick1line.set_xdata([5.0])
    assert two.label1.get_fontsize() != 20 and two.gridline.get_color() != "red"
    assert list(two.tick1line.get_xdata()) != [5.0]
    P._mpl().plt.close(fig)


def test_changed_tick_keywords_or_rc_construct_again():
    """A prototype serves only the tick keywords and rcParams it was made under."""
    fig, axes = _axes_with_ticks()
    axis = axes[1].yaxis
    construct = maxis.Axis._get_tick.original
    axis.set_tick_params(which="major", color="red", length=9)
    assert _same(construct(axis, True), axis._get_tick(True)) == []
    with matplotlib.rc_context({"grid.linestyle": ":", "ytick.major.width": 2.5}):
        assert _same(construct(axis, True), axis._get_tick(True)) == []
    assert axis._get_tick(True).tick1line.get_markeredgecolor() == "red"
    P._mpl().plt.close(fig)


# ------------------------------------------------------------------------------------------------- text metrics
def test_plain_text_extents_are_matplotlibs():
    get = mtext._get_text_metrics_with_cache
    props = [FontProperties(size=9), FontProperties(size=11, weight="bold"), FontProperties(family="serif", size=10)]
    for dpi in (100, 150):
        r = RendererAgg(600, 400, dpi)
        for prop in props:
            for s in ("0.25", "Monte Carlo runs per λ", "10", "Ωμ ≤ 0.25"):
                assert get(r, s, prop, False, dpi) == RendererAgg.get_text_width_height_descent(r, s, prop, False)


def test_rc_and_fonts_are_part_of_the_key():
    """The font looked up for a generic family, and FreeType's hinting, come from the rcParams: another value is
    measured again, not served the first one's extent."""
    get = mtext._get_text_metrics_with_cache
    r = RendererAgg(600, 400, 150)
    prop = FontProperties(family="sans-serif", size=10)
    text = "Monte Carlo runs per point"
    first = get(r, text, prop, False, 150)
    for rc in ({"font.sans-serif": ["DejaVu Serif"]}, {"text.hinting": "no_hinting"}):
        with matplotlib.rc_context(rc):
            r2 = RendererAgg(600, 400, 150)
            fresh = RendererAgg.get_text_width_height_descent(r2, text, prop, False)
            assert fresh != first  # the case: this rc changes the extent
            assert get(r2, text, prop, False, 150) == fresh
    assert get(r, text, prop, False, 150) == first


def test_a_saved_figure_is_freed(tmp_path):
    """The prototypes live on their axis: a cache outside the figure (a WeakKeyDictionary whose values refer to
    their axes) kept every saved figure alive."""
    import gc
    import weakref

    fig = _figure()
    gone = weakref.ref(fig)
    P.save(fig, tmp_path / "f.png")  # draws (ticks copied from the prototypes) and closes
    del fig
    gc.collect()
    assert gone() is None


# ------------------------------------------------------------------------------------------------- text layouts
def _layouts_equal(a, b) -> bool:
    (ba, ia, ca), (bb, ib, cb) = a, b
    return np.array_equal(ba.get_points(), bb.get_points()) and ia == ib and ca == cb


TEXTS = ["0.25", r"$\mathdefault{10^{-2}}$", "two\nlines, the second longer", r"$\frac{1}{2}$ and $\sqrt{x}$ mixed",
         "cost $5 and $6", ""]
SETTINGS = [dict(), dict(rotation=30), dict(rotation=90, rotation_mode="anchor"), dict(rotation=45, rotation_mode="xtick"),
            dict(rotation=300, rotation_mode="ytick", ha="left"), dict(ha="right", va="top"), dict(va="top"),
            dict(va="center"), dict(va="baseline"),
            dict(va="center_baseline", ha="center"), dict(multialignment="right"), dict(linespacing=2.0),
            dict(parse_math=False), dict(fontsize=13, fontweight="bold"), dict(family="serif", fontstyle="italic")]


@pytest.mark.parametrize("dpi", [100, 150])
def test_layouts_are_matplotlibs(dpi):
    """One text object changed setting by setting (the key must follow each), and fresh texts: the same layout
    as matplotlib's method, cold and warm."""
    fig = P._mpl().plt.figure(dpi=dpi)
    r = fig.canvas.get_renderer()
    theirs = mtext.Text._get_layout.original
    moving = fig.text(0.3, 0.4, "")
    for text in TEXTS:
        for kw in SETTINGS:
            fresh = fig.text(0.5, 0.5, text, **kw)
            moving.update({"text": text, "rotation": 0, "rotation_mode": "default", "ha": "left", "va": "baseline",
                           "multialignment": "left", "linespacing": 1.2, "parse_math": True, "fontsize": 10,
                           "fontweight": "normal", "family": "DejaVu Sans", "fontstyle": "normal", **kw})
            for t in (fresh, moving, fresh):
                assert _layouts_equal(t._get_layout(r), theirs(t, r)), (text, kw)
    assert len(mtext.Text._get_layout.layouts) > 0
    P._mpl().plt.close(fig)


def test_layout_rc_and_dpi_are_part_of_the_key():
    fig = P._mpl().plt.figure(dpi=100)
    r = fig.canvas.get_renderer()
    original = mtext.Text._get_layout.original
    t = fig.text(0.5, 0.5, r"$\Upsilon_T \leq abcdefgh + xyz$ text")
    stix = t._get_layout(r)
    # (a new renderer for each rc: matplotlib's own extent cache, per renderer, does not follow the rc)
    with matplotlib.rc_context({"mathtext.default": "regular"}):  # not in the font properties (mathtext.fontset is)
        r2 = RendererAgg(640, 480, 100)
        other = t._get_layout(r2)
        assert _layouts_equal(other, original(t, r2)) and not _layouts_equal(other, stix)
    plain = fig.text(0.5, 0.5, "Monte Carlo runs", family="sans-serif")
    sans = plain._get_layout(r)
    with matplotlib.rc_context({"font.sans-serif": ["DejaVu Serif"]}):  # the font the family names
        r2 = RendererAgg(640, 480, 100)
        other = plain._get_layout(r2)
        assert _layouts_equal(other, original(plain, r2)) and not _layouts_equal(other, sans)
    at_100 = t._get_layout(r)
    fig.set_dpi(150)  # the figure's dpi scales the font's line metrics; the renderer (100 dpi) measures
    assert _layouts_equal(t._get_layout(r), original(t, r)) and not _layouts_equal(t._get_layout(r), at_100)
    r72 = RendererAgg(640, 480, 72)  # the figure at 150 dpi, the renderer measuring at 72
    assert _layouts_equal(t._get_layout(r72), original(t, r72)) and not _layouts_equal(t._get_layout(r72), t._get_layout(r))
    P._mpl().plt.close(fig)


def test_each_call_gets_its_own_box_and_lines():
    fig = P._mpl().plt.figure()
    r = fig.canvas.get_renderer()
    t = fig.text(0.5, 0.5, "a\nb")
    bbox, info, _ = t._get_layout(r)
    bbox.x0 += 100
    info.clear()
    again = t._get_layout(r)
    assert _layouts_equal(again, mtext.Text._get_layout.original(t, r))
    P._mpl().plt.close(fig)


def test_wrapping_another_renderer_or_a_subclass_keep_matplotlibs():
    from matplotlib.backends.backend_svg import RendererSVG

    class RightAligned(mtext.Text):  # overrides a method the layout reads
        def _get_multialignment(self):
            return "right"

    fig = P._mpl().plt.figure()
    r = fig.canvas.get_renderer()
    layouts = mtext.Text._get_layout.layouts
    layouts.clear()
    fig.text(0.5, 0.5, "words " * 40, wrap=True).get_window_extent(r)  # wraps at the canvas edge: laid out
    fig.text(0.5, 0.5, "words")._get_layout(RendererSVG(640, 480, io.StringIO()))  # another renderer
    right = RightAligned(0.5, 0.5, "a\nbbbb", figure=fig)
    assert _layouts_equal(right._get_layout(r), mtext.Text._get_layout.original(right, r))
    assert len(layouts) == 0  # none was kept
    P._mpl().plt.close(fig)


def test_rc_values_follow_any_change():
    """The rcParams part of the keys: rebuilt after an assignment and after a list changed in place."""
    rc = {"font.sans-serif": ["DejaVu Sans"], "font.size": 10.0, "axes.grid": True}
    values = drawcache._rc_values(rc, ("font.sans-serif", "font.size"))
    first = values()
    assert first == (("DejaVu Sans",), 10.0) and values() is first  # unchanged: the same tuple
    rc["axes.grid"] = False
    assert values() == first
    rc["font.sans-serif"].insert(0, "DejaVu Serif")
    assert values() == (("DejaVu Serif", "DejaVu Sans"), 10.0)
    rc["font.size"] = 12.0
    assert values()[1] == 12.0


# ------------------------------------------------------------------------------------------------- mathtext glyph infos
MATH = [r"$\mathrm{tr}\,E[P_{k \mid k-1}]$ over $\sum_{i=1}^{N} a_i^{2}$", r"$\frac{AV}{WA}$ and $\sqrt{T_{y_{x}}}$ AVWAY",
        r"$\Upsilon_T \leq \lambda_c^{\alpha_{\beta}}$ text with kerning: AV To Wa", r"$\mathdefault{10^{-2}}$"]


def _parse(s, size, dpi, family):
    """A fresh parse (no parse cache): its glyphs (font name, size, glyph, offsets), rules and extent."""
    prop = FontProperties(size=size, family=family)  # the default font: text outside $…$ and \\mathdefault
    parse = MathTextParser._parse_cached.original.__wrapped__(MathTextParser("path"), s, dpi, prop, True, 0)
    return parse.width, parse.height, parse.depth, [(f.fname, sz, c, g, x, y) for f, sz, c, g, x, y in parse.glyphs], \
        parse.rects


def test_math_parses_with_kept_glyph_infos_are_matplotlibs():
    """The same parse (every glyph's position, so every kern, at every size of sub- and superscripts) with glyph
    infos kept from earlier parses at other sizes and dpis as with matplotlib's per-parse cache."""
    import warnings

    kept = _mathtext.TruetypeFonts._get_info
    cases = [(s, size, dpi, family) for dpi in (150, 100) for size in (9, 11, 9) for family in ("DejaVu Sans", "DejaVu Serif")
             for s in MATH]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the flags as an int (the parser's own default)
        kept.infos.clear()
        ours = [_parse(*c) for c in cases]
        assert kept.infos
        _mathtext.TruetypeFonts._get_info = kept.original
        try:
            theirs = [_parse(*c) for c in cases]
        finally:
            _mathtext.TruetypeFonts._get_info = kept
    assert ours == theirs
