"""Work matplotlib redoes for every tick, text and figure, done once per process: the same pixels.

Writing the 37 figures of a reproduction spent ~3 s CPU rendering glyphs (FreeType, one glyph at a time), ~1.6 s
constructing ticks and ~0.8 s measuring plain text, most of it for something already done for an earlier tick,
label or figure. ``install(m)`` (called once by ``plotting._mpl()``, with its matplotlib namespace) sets up:

* :func:`share_glyph_bitmaps` — a drawn glyph's bitmap kept per font, size, dpi, glyph and sub-pixel offset;
* :func:`share_glyph_positions` — a plain string's glyphs and their positions (FreeType's layout) kept per font,
  size, dpi and string;
* :func:`clone_ticks` — a new tick copied from a freshly constructed one of the same axis instead of
  constructed again;
* :func:`share_text_metrics` — a plain text's extent kept per process instead of per renderer (every figure gets
  a new renderer);
* :func:`share_math_glyph_infos` — a mathtext glyph's font metrics kept per process instead of per parse;
* :func:`share_text_layouts` — a text's layout (lines, extents, alignment offsets) kept per process for what it
  depends on, instead of computed at every extent query and draw.

Each is private matplotlib API, checked when it is installed: without what it needs, or (for the glyph drawing,
whose body it repeats) with another version of the method it replaces, matplotlib's own code stays
(tests/figures/test_drawcache compares each with matplotlib's path). A forked child starts without the kept
bitmaps (they hold the parent's FT2Font objects, as the mathtext cache does: plotting.share_mathtext_parses).
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import math
import os
from types import SimpleNamespace

import numpy as np

#: glyph bitmaps kept per process (a reproduction draws ~20 000 distinct ones, ~3 MB); the cache is emptied when full
GLYPH_CACHE = 65536
#: plain-text extents kept per process
METRICS_CACHE = 8192
#: the attribute of an ``Axis`` that holds its prototype ticks (:func:`clone_ticks`)
PROTOTYPES = "_netkf_tick_prototypes"
#: text layouts kept per process
LAYOUT_CACHE = 8192
#: sha256 (first 16 hex digits) of the sources of the ``Text`` methods :func:`share_text_layouts` reads the inputs of
#: (matplotlib 3.11); another source keeps matplotlib's own layout
LAYOUT_SOURCES = "9a62cbfce5448fed"
#: the ``Text`` methods whose sources :data:`LAYOUT_SOURCES` fingerprints: ``_get_layout`` and what it calls on the text
LAYOUT_METHODS = ("_get_layout", "_get_wrapped_text", "_preprocess_math", "get_rotation", "get_rotation_mode",
                  "_get_multialignment", "_ha_for_angle", "_va_for_angle", "get_parse_math", "get_usetex", "get_wrap",
                  "get_text", "get_horizontalalignment", "get_verticalalignment", "get_transform_rotates_text")
#: mathtext glyph infos kept per process
MATH_INFO_CACHE = 16384
#: sha256 (first 16 hex digits) of the sources of ``_mathtext.TruetypeFonts._get_info``, ``TruetypeFonts.__init__`` and
#: ``Fonts.__init__`` (matplotlib 3.11) that :func:`share_math_glyph_infos` reads the inputs of
MATH_INFO_SOURCES = ("83776fb9cc5a1be7", "8242ec1612e80afb", "e584d9da73e5572c")
#: plain strings' glyph positions kept per process
POSITIONS_CACHE = 8192
#: sha256 (first 16 hex digits) of the sources of ``RendererAgg.draw_text`` and ``RendererAgg._prepare_font`` that
#: :func:`share_glyph_positions` repeats (matplotlib 3.11)
DRAW_TEXT_SOURCES = ("a08e437e92594360", "0d1177abbed013cc")
#: sha256 (first 16 hex digits) of the source of ``RendererAgg._draw_text_glyphs_and_boxes`` that
#: :func:`share_glyph_bitmaps` repeats (matplotlib 3.11); another source keeps matplotlib's own
GLYPHS_SOURCE = "ccc4749c98095394"


def install(m: SimpleNamespace) -> dict[str, bool]:
    """Every fast path of this module; ``{name: installed}``."""
    return {"glyph_bitmaps": share_glyph_bitmaps(m), "glyph_positions": share_glyph_positions(m),
            "ticks": clone_ticks(m), "text_metrics": share_text_metrics(m), "text_layouts": share_text_layouts(m),
            "math_glyph_infos": share_math_glyph_infos(m)}


# ---------------------------------------------------------------------------------------------- glyph bitmaps
def _install(owner, name: str, fn, current, cache_name: str | None = None, cache: dict | None = None,
             forget_at_fork: bool = False) -> bool:
    """Put ``fn`` in place of ``owner.<name>`` (``current``, kept as ``fn.original``), marked installed (the
    installers are idempotent); its per-process ``cache`` is kept as ``fn.<cache_name>`` (the tests read it) and,
    with ``forget_at_fork``, cleared in a forked child (which must not use the parent's FT2Font objects). True."""
    if forget_at_fork:
        os.register_at_fork(after_in_child=cache.clear)
    fn._netkf_shared = True
    fn.original = current
    if cache_name is not None:
        setattr(fn, cache_name, cache)
    setattr(owner, name, fn)
    return True


def _source_hash(fn) -> str | None:
    try:
        return hashlib.sha256(inspect.getsource(fn).encode()).hexdigest()[:16]
    except (OSError, TypeError):  # pragma: no cover - no source (a frozen install)
        return None


def share_glyph_bitmaps(m: SimpleNamespace) -> bool:
    """``RendererAgg._draw_text_glyphs_and_boxes`` (every text and mathtext string Agg draws), with each glyph's
    bitmap rendered once per process for its font, size, dpi, glyph, load flags, render mode, transform and
    sub-pixel offset.

    matplotlib 3.11 renders every glyph of every string with FreeType (~55 µs each: load, hint, rasterize) at
    its position in 1/64 pixel, ``X = 64·qx + rx`` (0 ≤ rx < 64; Y likewise). Moving a glyph's outline by whole
    pixels (64·qx in 26.6 fixed point) moves its bitmap by qx pixels and changes nothing else, so the bitmap
    rendered at (rx, ry) is kept, and drawn at left + qx, top + qy: the same bytes matplotlib's call gives
    (tests/figures/test_drawcache). 43 % of the 34 000 glyphs of a reproduction's figures are such repeats, and
    the rotation matrix, which matplotlib builds with numpy per glyph, is built once per string. Everything else
    (the rule boxes of mathtext, ``draw_text_image``) is matplotlib's code, unchanged. Installed only over the
    method it was written from (:data:`GLYPHS_SOURCE`); True when installed (idempotent)."""
    from matplotlib.backends import backend_agg  # with matplotlib (the caller set the backend up)

    Renderer = backend_agg.RendererAgg
    current = Renderer.__dict__.get("_draw_text_glyphs_and_boxes")
    if getattr(current, "_netkf_shared", False):
        return True
    from matplotlib import ft2font  # with matplotlib

    if (current is None or _source_hash(current) != GLYPHS_SOURCE or not hasattr(ft2font, "RenderMode")
            or not hasattr(ft2font.FT2Font, "_render_glyph") or not hasattr(ft2font.FT2Font, "_set_transform")):
        return False  # another matplotlib: its own drawing
    NORMAL, MONO = ft2font.RenderMode.NORMAL, ft2font.RenderMode.MONO
    get_hinting_flag = backend_agg.get_hinting_flag
    bitmaps: dict = {}
    matrices: dict = {}

    def _draw_text_glyphs_and_boxes(self, gc, x, y, angle, glyphs, boxes):
        # y is downwards (matplotlib's method, with the bitmaps and the matrix kept).
        cos = math.cos(math.radians(angle))
        sin = math.sin(math.radians(angle))
        load_flags = get_hinting_flag()
        antialiased = gc.get_antialiased()
        mode = NORMAL if antialiased else MONO
        dpi, height = self.dpi, self.height
        draw_text_image = self._renderer.draw_text_image
        for font, size, glyph_index, slant, extend, dx, dy in glyphs:  # dy is upwards.
            shape = (cos, sin, slant, extend)
            matrix = matrices.get(shape)
            if matrix is None:
                matrix = matrices[shape] = (0x10000 * np.array([[cos, -sin], [sin, cos]])
                                            @ [[extend, extend * slant], [0, 1]]).round().astype(int)
            # FreeType's y is upwards.
            qx, rx = divmod(round(0x40 * (x + dx * cos - dy * sin)), 0x40)
            qy, ry = divmod(round(0x40 * (height - y + dx * sin + dy * cos)), 0x40)
            key = (font, size, dpi, glyph_index, load_flags, mode, shape, rx, ry)
            kept = bitmaps.get(key)
            if kept is None:
                font.set_size(size, dpi)
                font._set_transform(matrix, [rx, ry])
                bitmap = font._render_glyph(glyph_index, load_flags, mode)
                buffer = bitmap.buffer
                if not antialiased:
                    buffer *= 0xff
                if len(bitmaps) >= GLYPH_CACHE:
                    bitmaps.clear()
                kept = bitmaps[key] = (buffer, bitmap.left, bitmap.top)
            buffer, left, top = kept
            # draw_text_image's y is downwards & the bitmap bottom side.
            draw_text_image(buffer, left + qx, int(height) - (top + qy) + buffer.shape[0], 0, gc)
        if boxes:  # mathtext's rules (fraction bars, roots): matplotlib's own code, no glyph left to draw
            current(self, gc, x, y, angle, (), boxes)

    return _install(Renderer, "_draw_text_glyphs_and_boxes", _draw_text_glyphs_and_boxes, current, "bitmaps", bitmaps,
                    forget_at_fork=True)


def share_glyph_positions(m: SimpleNamespace) -> bool:
    """``RendererAgg.draw_text`` for plain text with FreeType's layout of the string (its glyphs and their
    positions, ``FT2Font._layout``, ~24 µs per character) kept per process for the font, its size, the dpi, the
    string, the hinting flags, the font features and the language: the tick labels, axis labels and legend entries
    of 37 figures were laid out 808 times, 285 distinct. The font is prepared (looked up, cleared, sized) and the
    glyphs drawn (:func:`share_glyph_bitmaps`) as matplotlib's method does; math text goes to its ``draw_mathtext``
    as before. Installed only over the method sources it repeats (:data:`DRAW_TEXT_SOURCES`); True when installed
    (idempotent)."""
    from matplotlib.backends import backend_agg  # with matplotlib (the caller set the backend up)

    Renderer = backend_agg.RendererAgg
    current = Renderer.__dict__.get("draw_text")
    if getattr(current, "_netkf_shared", False):
        return True
    if current is None or (_source_hash(current), _source_hash(Renderer._prepare_font)) != DRAW_TEXT_SOURCES:
        return False  # another matplotlib: its own drawing
    get_hinting_flag = backend_agg.get_hinting_flag
    positions: dict = {}

    def draw_text(self, gc, x, y, s, prop, angle, ismath=False, mtext=None):
        # docstring inherited (matplotlib's method, with the layout kept)
        if ismath:
            return self.draw_mathtext(gc, x, y, s, prop, angle)
        font = self._prepare_font(prop)
        size = prop.get_size_in_points()
        flags = get_hinting_flag()
        features = mtext.get_fontfeatures() if mtext is not None else None
        language = mtext.get_language() if mtext is not None else None
        key = (font, size, self.dpi, s, flags, features, language)
        glyphs = positions.get(key)
        if glyphs is None:
            if len(positions) >= POSITIONS_CACHE:
                positions.clear()
            glyphs = positions[key] = tuple((item.ft_object, item.glyph_index, item.x, item.y)
                                            for item in font._layout(s, flags=flags, features=features, language=language))
        self._draw_text_glyphs_and_boxes(
            gc, x, y, angle, ((ft_object, size, index, 0, 1, gx, gy) for ft_object, index, gx, gy in glyphs), [])

    return _install(Renderer, "draw_text", draw_text, current, "positions", positions, forget_at_fork=True)


# ---------------------------------------------------------------------------------------------- ticks
def _copy_artist(artist, registry):
    """A new artist with ``artist``'s attributes (shared: matplotlib replaces rather than mutates them) and its own
    (empty) callback registry."""
    new = object.__new__(type(artist))
    new.__dict__.update(artist.__dict__)
    new._callbacks = registry(signals=["pchanged"])
    return new


def _copy_tick(tick, registry):
    """A tick as ``tick`` was: its five artists copied, the labels with their own font properties."""
    new = _copy_artist(tick, registry)
    for name in ("tick1line", "tick2line", "gridline", "label1", "label2"):
        setattr(new, name, _copy_artist(getattr(tick, name), registry))
    new.label1._fontproperties = tick.label1._fontproperties.copy()
    new.label2._fontproperties = tick.label2._fontproperties.copy()
    return new


def clone_ticks(m: SimpleNamespace) -> bool:
    """``Axis._get_tick``: a new tick is a copy of a fresh one of the same axis (major or minor), instead of
    constructing five artists again (~0.5 ms: 3 Line2D, 2 Text, their markers and transforms).

    The first tick an axis constructs is copied before it is used (the prototype, kept on the axis in the
    attribute :data:`PROTOTYPES`: it refers to its axes, so a cache outside the figure would keep every figure
    alive); a later tick is a copy of the prototype as long as what construction reads is unchanged — the axis'
    tick keywords (``tick_params``) and the rcParams — and constructed (and a new prototype kept) otherwise. The
    caller then does what it did to a constructed tick (``_copy_tick_props`` from the first tick, positions,
    labels). A copy shares the prototype's attribute objects, which matplotlib replaces rather than mutates (data,
    paths, markers, transforms), and gets its own artists, callback registries and font properties
    (tests/figures/test_drawcache: the same state as a constructed tick, the same pixels). Only for the plain
    ``XAxis``/``YAxis`` and their ``XTick``/``YTick``
    (polar and 3-D axes construct as before). True when installed (idempotent)."""
    maxis = m.matplotlib.axis
    current = maxis.Axis.__dict__.get("_get_tick")
    if getattr(current, "_netkf_shared", False):
        return True
    registry = getattr(m.matplotlib.cbook, "CallbackRegistry", None)
    if current is None or registry is None or not all(hasattr(maxis, c) for c in ("XAxis", "YAxis", "XTick", "YTick")):
        return False  # pragma: no cover - another matplotlib
    plain = {maxis.XAxis: maxis.XTick, maxis.YAxis: maxis.YTick}
    rc = m.matplotlib.rcParams

    def _get_tick(self, major):
        kw = self._major_tick_kw if major else self._minor_tick_kw
        # on the axis itself ({major: (tick_kw, rc, tick)}): a prototype refers to its axes, and a cache outside the
        # figure would keep every figure alive
        prototypes = self.__dict__.get(PROTOTYPES)
        kept = prototypes.get(major) if prototypes is not None else None
        if kept is not None and kept[0] == kw and dict.__eq__(rc, kept[1]):
            return _copy_tick(kept[2], registry)
        tick = current(self, major)
        if plain.get(type(self)) is type(tick) and tick.label1._bbox_patch is None and tick.label2._bbox_patch is None:
            self.__dict__.setdefault(PROTOTYPES, {})[major] = (dict(kw), dict.copy(rc), _copy_tick(tick, registry))
        return tick

    return _install(maxis.Axis, "_get_tick", _get_tick, current)


# ---------------------------------------------------------------------------------------------- text metrics
def _hashable(v):
    return tuple(v) if isinstance(v, list) else v


def _rc_values(rc, keys: tuple[str, ...]):
    """A function giving the current values of the rcParams ``keys`` (hashable: lists as tuples), rebuilt only when
    the rcParams changed since the last call (one C-level comparison of the whole dict, ~5 µs, instead of ~0.5 µs
    per key)."""
    last: list = [None, None]

    def values() -> tuple:
        if last[0] is None or not dict.__eq__(rc, last[0]):
            # lists copied: one changed in place differs from its copy (the comparison is by value)
            last[0] = {k: list(v) if isinstance(v, list) else v for k, v in dict.items(rc)}
            last[1] = tuple(_hashable(dict.__getitem__(rc, k)) for k in keys)
        return last[1]

    return values


def share_text_metrics(m: SimpleNamespace) -> bool:
    """``text._get_text_metrics_with_cache`` for plain (not math) text on Agg: one process-wide cache instead of
    matplotlib's one per renderer — every figure draws with a new renderer, and the tick labels "0.2", "10", the
    axis labels and legend entries of 37 figures were measured again by each (787 FreeType layouts, 376
    distinct; ~24 µs per character).

    ``RendererAgg.get_text_width_height_descent(s, prop, False)`` depends on the string, the font properties,
    the renderer's dpi, and, through the font lookup and FreeType's loading, the ``font.*`` and ``text.*``
    rcParams and the fonts matplotlib knows: the key holds exactly those, and a miss calls that method. Math text
    (its parse is shared: plotting.share_mathtext_parses), other renderers and a dpi other than the renderer's
    keep matplotlib's cache. True when installed (idempotent)."""
    mtext = m.matplotlib.text
    current = getattr(mtext, "_get_text_metrics_with_cache", None)
    if getattr(current, "_netkf_shared", False):
        return True
    from matplotlib import font_manager  # with matplotlib
    from matplotlib.backends.backend_agg import RendererAgg  # with matplotlib (the caller set the backend up)

    if current is None or not hasattr(font_manager, "fontManager"):
        return False  # pragma: no cover - another matplotlib
    rc = m.matplotlib.rcParams
    rc_values = _rc_values(rc, tuple(k for k in rc if k.startswith(("font.", "text."))))
    measuring: list = []  # the renderer of the call in progress (a miss measures with it)

    @functools.lru_cache(METRICS_CACHE)
    def shared(text, fontprop, dpi, rc_state, fonts):
        return RendererAgg.get_text_width_height_descent(measuring[-1], text, fontprop, False)

    def _get_text_metrics_with_cache(renderer, text, fontprop, ismath, dpi):
        if ismath or type(renderer) is not RendererAgg or renderer.dpi != dpi:
            return current(renderer, text, fontprop, ismath, dpi)
        fm = font_manager.fontManager
        measuring.append(renderer)
        try:  # a copy of the font properties, as matplotlib's cache keeps: the caller may change its own later
            return shared(text, fontprop.copy(), dpi, rc_values(), (id(fm), len(fm.ttflist), len(fm.afmlist)))
        finally:
            measuring.pop()

    return _install(mtext, "_get_text_metrics_with_cache", _get_text_metrics_with_cache, current, "cache", shared)


# ---------------------------------------------------------------------------------------------- text layouts
def _layout_sources(Text) -> str | None:
    parts = [_source_hash(getattr(Text, name, None)) for name in LAYOUT_METHODS]
    return None if None in parts else hashlib.sha256("".join(parts).encode()).hexdigest()[:16]


def share_text_layouts(m: SimpleNamespace) -> bool:
    """``Text._get_layout`` on Agg: one process-wide cache of layouts instead of the computation at every call —
    each extent query (tight_layout's passes, the axis-label placement, the legend's packing) and each draw of a
    text lays it out again (7 845 calls for the 37 figures, 562 distinct, ~130 µs each besides the extents).

    The layout of a text that does not wrap and does not use TeX depends on (reading matplotlib 3.11's
    ``_get_layout`` and the methods it calls on the text, :data:`LAYOUT_METHODS`): the string, the font
    properties, whether to parse math, the line spacing, the multi-line alignment, the horizontal and vertical
    alignment, the rotation and rotation mode, the figure's dpi, and, through its extents, the renderer's dpi,
    the ``font.*``, ``text.*`` and ``mathtext.*`` rcParams and the fonts matplotlib knows — the key holds exactly
    those; a miss calls matplotlib's method. Each call gets its own bounding box and list (the cached tuples
    inside are immutable). A wrapping or TeX text, another renderer (PDF, SVG: their font metrics hook), a
    ``Text`` subclass overriding any of those methods, and another version of their sources
    (:data:`LAYOUT_SOURCES`) keep matplotlib's own layout. True when installed (idempotent)."""
    from matplotlib import font_manager  # with matplotlib
    from matplotlib.backends.backend_agg import RendererAgg  # with matplotlib (the caller set the backend up)

    Text = m.matplotlib.text.Text
    current = Text.__dict__.get("_get_layout")
    if getattr(current, "_netkf_shared", False):
        return True
    if current is None or _layout_sources(Text) != LAYOUT_SOURCES:
        return False  # another matplotlib: its own layout
    rc = m.matplotlib.rcParams
    rc_values = _rc_values(rc, tuple(k for k in rc if k.startswith(("font.", "text.", "mathtext."))))
    plain_classes: dict[type, bool] = {}  # Text subclasses that override none of LAYOUT_METHODS
    layouts: dict = {}

    def _get_layout(self, renderer):
        cls = type(self)
        plain = plain_classes.get(cls)
        if plain is None:
            plain = plain_classes[cls] = all(getattr(cls, n) is getattr(Text, n) for n in LAYOUT_METHODS)
        if not plain or type(renderer) is not RendererAgg or self._wrap or self._usetex:
            return current(self, renderer)
        fm = font_manager.fontManager
        # a copy of the font properties: the text may change its own later (as in matplotlib's extent cache)
        key = (self._text, self._fontproperties.copy(), self._parse_math, self._linespacing, self._multialignment,
               self._horizontalalignment, self._verticalalignment, self._rotation_mode, self.get_rotation(),
               self.get_figure(root=True).dpi, renderer.dpi,
               rc_values(), (id(fm), len(fm.ttflist), len(fm.afmlist)))
        kept = layouts.get(key)
        if kept is None:
            if len(layouts) >= LAYOUT_CACHE:
                layouts.clear()
            bbox, info, corner = current(self, renderer)
            kept = layouts[key] = (bbox.frozen(), tuple(info), corner)
        bbox, info, corner = kept
        return bbox.frozen(), list(info), corner

    return _install(Text, "_get_layout", _get_layout, current, "layouts", layouts)


# ---------------------------------------------------------------------------------------------- mathtext glyph infos
def share_math_glyph_infos(m: SimpleNamespace) -> bool:
    """``_mathtext.TruetypeFonts._get_info`` (a glyph's font, index and metrics: FreeType loads the glyph) kept per
    process instead of per parse: every mathtext parse builds a new font set whose cache starts empty, and a
    footnote of 160 characters loads ~50 glyphs (a third of its ~15 ms parse) that the parses before it loaded too.

    The info depends on the font set's class, its default font properties and load flags, the ``mathtext.*`` and
    ``font.*`` rcParams (the font set's font map, read when it is made; the font lookup) and the arguments (font
    name, class, symbol, size, dpi): the key holds exactly those, a miss calls matplotlib's method. A kept info
    still sets its font's size as the method does (``font.set_size``: the kerning read next depends on it), so the
    font's state after the call is the same. Installed only over the 3.11 sources it reads
    (:data:`MATH_INFO_SOURCES`); True when installed (idempotent)."""
    from matplotlib import _mathtext  # with matplotlib

    TruetypeFonts = _mathtext.TruetypeFonts
    current = TruetypeFonts.__dict__.get("_get_info")
    if getattr(current, "_netkf_shared", False):
        return True
    sources = (_source_hash(current), _source_hash(TruetypeFonts.__init__), _source_hash(_mathtext.Fonts.__init__))
    if current is None or sources != MATH_INFO_SOURCES:
        return False  # another matplotlib: its own
    rc = m.matplotlib.rcParams
    rc_values = _rc_values(rc, tuple(k for k in rc if k.startswith(("mathtext.", "font."))))
    infos: dict = {}

    def _get_info(self, fontname, font_class, sym, fontsize, dpi):
        key = (type(self), self.default_font_prop.copy(), self.load_glyph_flags, rc_values(),
               fontname, font_class, sym, fontsize, dpi)
        info = infos.get(key)
        if info is None:
            if len(infos) >= MATH_INFO_CACHE:
                infos.clear()
            info = infos[key] = current(self, fontname, font_class, sym, fontsize, dpi)
        else:
            info.font.set_size(fontsize, dpi)  # what the method does to the font before loading the glyph
        return info

    return _install(TruetypeFonts, "_get_info", _get_info, current, "infos", infos, forget_at_fork=True)
