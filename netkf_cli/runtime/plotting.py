"""Shared figure style. Recipes draw with matplotlib (Agg) from their CSV tables only.

What every netkf figure uses (issue 13):

* ``new_figure(...)`` — a figure in the project's style (fonts ≥ 9 pt at the saved size: font
  sizes are in points and figures are saved at their own size, never rescaled);
* ``paper_title(topic, figure, what)`` — ``"Shi, Xie & Murray 2009 — Fig. 5: …"``;
* mathtext for symbols: ``r"$\\Upsilon_T$"``, ``r"$P_{k \\mid k-1}$"`` (``\\mid``: a bare ``|`` in a
  subscript reads as an l), ``r"$L_f^{LB}$"``, rendered
  with the STIX sans fonts (DejaVu Sans, the text font, draws a plain-Unicode Υ exactly like a
  Latin "Y": write ``$\\Upsilon$``; ≤ and θ are fine either way);
* ``PALETTE`` (Okabe–Ito, colour-blind safe), ``LINESTYLES``, ``MARKERS`` and
  ``series_style(i)`` for the i-th series: colour, line style and marker all differ;
* ``legend_outside(ax)`` — the legend to the right of the axes, never over the data;
* ``footnote(fig, text)`` — a provenance line under the axes (wrapped, 9 pt);
* ``save(fig, path, formats=("png",), dpi=...)`` — lays the figure out so that no text leaves
  the canvas, then writes every requested format of the same figure.

``lint(fig)`` lists what a referee would object to (no title, unlabelled axes, a legend entry
without a series or a series without a legend entry, a legend over data points, text outside
the canvas, fonts < 9 pt, tick labels of one axis that overlap);
when the environment variable ``NETKF_FIGURE_LINT`` names a folder, ``save`` writes the
findings there as ``<figure stem>.json`` (the figure-lint test reads them).
"""

from __future__ import annotations

import functools
import io
import json
import math
import os
import re
import struct
import textwrap
import warnings
import zlib
from collections.abc import Iterable
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING

import numpy as np

from netkf_cli.runtime import drawcache

if TYPE_CHECKING:  # annotations only: matplotlib itself is imported by the first function that draws (_mpl)
    from matplotlib.figure import Figure

#: Okabe & Ito (2008) colour-blind-safe palette; yellow last (weak on white).
PALETTE: tuple[str, ...] = (
    "#0072B2",  # blue
    "#D55E00",  # vermillion
    "#009E73",  # bluish green
    "#CC79A7",  # reddish purple
    "#E69F00",  # orange
    "#56B4E9",  # sky blue
    "#000000",  # black
    "#F0E442",  # yellow
)
LINESTYLES: tuple = ("-", "--", "-.", ":", (0, (5, 1.5)), (0, (3, 1, 1, 1, 1, 1)), (0, (1, 1)), (0, (8, 2, 2, 2)))
MARKERS: tuple[str, ...] = ("o", "s", "^", "D", "v", "P", "X", "*")
MIN_FONT_PT = 9.0

PAPERS: dict[str, str] = {
    "shi2009": "Shi, Xie & Murray 2009",
    "fading": "Mostofi & Murray 2009",
    "smoothing": "Leong, Dey & Evans 2008",
    "fusion": "Chiuso & Schenato 2009",
    "markov": "Moayedi, Soh & Foo 2009",
    "critical": "Sinopoli et al. 2004",
}

STYLE = {
    "figure.dpi": 100,
    "savefig.dpi": 150,
    "axes.grid": True,
    "grid.alpha": 0.3,
    "axes.spines.top": False,
    "axes.spines.right": False,
    "axes.prop_cycle": None,  # cycler(color=PALETTE) + cycler(linestyle=LINESTYLES), set by _mpl() (a matplotlib object)
    "legend.frameon": False,
    "font.family": "DejaVu Sans",
    # STIX sans: upright sans like DejaVu, but a Υ with curved arms (DejaVu's Υ looks like "Y")
    "mathtext.fontset": "stixsans",
    "font.size": 10,
    "axes.titlesize": 11,
    "axes.labelsize": 10,
    "xtick.labelsize": 9,
    "ytick.labelsize": 9,
    "legend.fontsize": 9,
    "legend.title_fontsize": 9,
    "figure.titlesize": 11,
    "lines.linewidth": 1.5,
    "lines.markersize": 5,
    "errorbar.capsize": 2,
    "svg.fonttype": "path",
    "svg.hashsalt": "netkf",  # deterministic element ids: the same figure gives the same SVG
    "pdf.fonttype": 42,
}
#: mathtext parses kept per process (matplotlib keeps 50 per renderer, and every figure, and every dpi
#: of a figure, gets a new renderer: a log axis' "$10^{-2}$" was parsed again by each of them)
MATHTEXT_CACHE = 4096


@functools.cache
def _mpl() -> SimpleNamespace:
    """matplotlib on the Agg backend with the netkf style, set up once per process at the first figure.

    Importing this module (and so ``netkf_cli.app.cli``: every ``netkf`` start, every forked worker that
    never draws) does not import matplotlib: ≈ 0.5 s and 27 MB RSS that only drawing needs (issue 20).
    What happens here is what importing this module did before, in the same order: the Agg backend,
    ``rcParams.update(STYLE)`` (the process-wide default for netkf figures: titles, labels and legends
    created after ``new_figure`` returns get these sizes too — an rc_context would only cover creation),
    then the shared mathtext cache (``share_mathtext_parses``) and the other process-wide shortcuts under the
    drawing (:mod:`netkf_cli.runtime.drawcache`: glyph bitmaps, ticks, plain-text extents; the same pixels)."""
    import matplotlib  # here, not at module level: ≈ 0.5 s and 27 MB RSS in every process, needed only to draw

    matplotlib.use("Agg")
    import matplotlib.mathtext  # with matplotlib, after the backend choice (above)
    import matplotlib.pyplot as plt  # with matplotlib, after the backend choice (above)
    import matplotlib.text  # with matplotlib (above)
    import matplotlib.transforms  # with matplotlib (above)

    m = SimpleNamespace(matplotlib=matplotlib, plt=plt, mathtext=matplotlib.mathtext, text=matplotlib.text,
                        transforms=matplotlib.transforms)
    # matplotlib re-exports its cycler dependency
    STYLE["axes.prop_cycle"] = matplotlib.cycler(color=list(PALETTE)) + matplotlib.cycler(linestyle=list(LINESTYLES))
    matplotlib.rcParams.update(STYLE)
    m.shared_mathtext = _install_shared_mathtext(m)
    m.drawcache = drawcache.install(m)
    return m


def setup() -> None:
    """Import matplotlib and apply the netkf style now rather than at the first figure: a parent about to
    fork workers that draw (``netkf reproduce --jobs N``) calls it once, so they share its pages instead of
    each importing matplotlib again."""
    _mpl()


def share_mathtext_parses() -> bool:
    """One process-wide cache of mathtext parses instead of matplotlib's 50 per renderer.

    Every figure (and, before ``save`` laid a figure out at the dpi it writes it at, the layout at
    ``figure.dpi`` and the save at ``savefig.dpi`` of one figure) draws with a new renderer, each
    with its own ``MathTextParser`` whose ``_parse_cached`` is an
    ``lru_cache(50)`` keyed on the parser: a quick reproduction parsed 1 999 strings (log-axis tick
    labels such as ``$\\mathdefault{10^{0}}$`` 73 times) with 1 454 misses, pyparsing being most of
    a figure's text layout. The parse depends only on the parser's output type (raster/vector),
    the string, dpi, font properties, antialiasing, hinting and the ``mathtext.*`` rcParams, so this
    cache keys on exactly those (the rcParams included) and returns the same objects matplotlib's own
    cache does: the pixels are unchanged. Private API: if matplotlib moves it, its own cache stays.
    Returns True when installed (idempotent); ``_mpl()`` installs it at the first figure."""
    return _mpl().shared_mathtext


def _install_shared_mathtext(m: SimpleNamespace) -> bool:
    """``share_mathtext_parses``' work, done once by ``_mpl()``."""
    matplotlib, MathTextParser = m.matplotlib, m.mathtext.MathTextParser
    mathtext_rc = tuple(k for k in matplotlib.rcParams if k.startswith("mathtext."))
    current = MathTextParser.__dict__.get("_parse_cached")
    if getattr(current, "_netkf_shared", False):
        return True
    per_parser = getattr(current, "__wrapped__", None)
    if per_parser is None:  # pragma: no cover - another matplotlib
        return False
    parsers: dict[str, MathTextParser] = {}

    @functools.lru_cache(MATHTEXT_CACHE)
    def shared(output_type, s, dpi, prop, antialiased, load_glyph_flags, rc):
        return per_parser(parsers[output_type], s, dpi, prop, antialiased, load_glyph_flags)

    def _parse_cached(self, s, dpi, prop, antialiased, load_glyph_flags):
        parsers.setdefault(self._output_type, self)
        rc = tuple(matplotlib.rcParams[k] for k in mathtext_rc)
        return shared(self._output_type, s, dpi, prop, antialiased, load_glyph_flags, rc)

    def forget():  # a forked child must not draw with the parent's fonts: their open files share one offset
        shared.cache_clear()
        parsers.clear()

    # matplotlib clears its font cache (font_manager._get_font) in a forked child for the same reason; a parse
    # kept here holds the parent's FT2Font objects, and two workers reading glyphs through one inherited file
    # offset fail with "FT_Load_Glyph … invalid outline" (seen in a quick reproduction run from a process that
    # had drawn figures before forking)
    os.register_at_fork(after_in_child=forget)
    _parse_cached._netkf_shared = True
    _parse_cached.cache = shared  # cache_info() / cache_clear()
    _parse_cached.original = current  # matplotlib's own (the tests render with both)
    MathTextParser._parse_cached = _parse_cached
    return True


def series_style(i: int) -> dict:
    """Colour, line style and marker of the i-th series (all three differ between neighbours).

    Use as ``ax.plot(x, y, **series_style(i), label=...)``; for a curve on a dense grid drop the
    marker (``markevery`` or ``{**series_style(i), "marker": None}``).
    """
    return {"color": PALETTE[i % len(PALETTE)], "linestyle": LINESTYLES[i % len(LINESTYLES)],
            "marker": MARKERS[i % len(MARKERS)]}


_SUBSCRIPT = re.compile(r"_\{[^{}$]*\|[^{}$]*\}")


def math_bars(text: str) -> str:
    """A bare ``|`` in a mathtext subscript (``$P_{k|k}$``) as ``\\mid``: the STIX sans draw it like an l
    ("Pklk"). Only inside ``$…$`` spans and ``_{…}`` groups; ``\\|`` and text outside math are kept."""
    parts = text.split("$")
    for i in range(1, len(parts), 2):  # the odd parts are math (an unpaired $ leaves the rest as text)
        if i == len(parts) - 1:
            break
        parts[i] = _SUBSCRIPT.sub(lambda m: re.sub(r"(?<!\\)\|", r" \\mid ", m.group(0)), parts[i])
    return "$".join(parts)


def paper_title(topic: str | None, figure: str | int | None, what: str) -> str:
    """``"<paper> — <figure>: <what>"``; ``topic=None`` (a user's scenario) gives ``what`` alone.

    ``figure`` may be ``5`` (→ "Fig. 5"), a string such as ``"Table I"``, ``"Sec. 4.2"``, or None.
    """
    what = math_bars(what)  # titles come from configs too
    if topic is None:
        return what
    if topic not in PAPERS:
        raise ValueError(f"unknown topic {topic!r}; known: {sorted(PAPERS)}")
    paper = PAPERS[topic]
    if figure is None or figure == "":
        return f"{paper} — {what}"
    fig = f"Fig. {figure}" if isinstance(figure, int) else str(figure)
    return f"{paper} — {fig}: {what}"


def legend_outside(ax, *, loc: str = "right", **kw):
    """A legend outside the axes (``loc="right"``: to the right, top-aligned; ``"below"``: under
    the x-axis label). ``save`` shrinks the axes so that it stays on the canvas."""
    if loc == "right":
        kw = {"loc": "upper left", "bbox_to_anchor": (1.02, 1.0), "borderaxespad": 0.0, **kw}
    elif loc == "below":
        # a fixed distance (in points) under the axes, whatever their height: clears the tick labels
        # and the x-axis label even when a long footnote shrinks the axes
        kw = {"loc": "upper center", "bbox_to_anchor": (0.5, 0.0),
              "bbox_transform": _mpl().transforms.offset_copy(ax.transAxes, fig=ax.figure, y=-40, units="points"),
              "borderaxespad": 0.0, "ncol": kw.pop("ncol", 2), **kw}
    else:
        raise ValueError("loc must be 'right' or 'below'")
    return ax.legend(**kw)


def new_figure(ncols: int = 1, nrows: int = 1, width: float = 6.4, height: float = 4.4, **kw) -> tuple[Figure, object]:
    """A figure with the project's style; returns (fig, axes).

    ``width`` is per column when ``ncols > 1``, ``height`` per row (as before)."""
    plt = _mpl().plt
    # at the dpi ``save`` writes by default: a text measured before the save (a legend's width) is then laid out
    # and its mathtext parsed once, at the dpi of the layout and of the file
    kw.setdefault("dpi", STYLE["savefig.dpi"])
    with plt.rc_context(STYLE):
        fig, ax = plt.subplots(nrows, ncols, figsize=(width * ncols if ncols > 1 else width, height * nrows), **kw)
    for a in (ax.flat if hasattr(ax, "flat") else [ax]):
        a.grid(True, alpha=0.3)
        a.spines["top"].set_visible(False)
        a.spines["right"].set_visible(False)
    return fig, ax


def detach(fig: Figure | None) -> Figure | None:
    """``fig`` no longer held by pyplot (``plt.close``): what the Python API returns lives as long as its caller
    keeps it (pyplot keeps every figure it made until closed: 20 API runs in a notebook warned and kept them all);
    it still draws, saves and shows in Jupyter."""
    if fig is not None:
        _mpl().plt.close(fig)
    return fig


FOOTNOTE_X = 0.01
"""A footnote's left margin, and its right one (:func:`_wrapped_text`), as a fraction of the figure's width."""


def footnote(fig: Figure, text: str) -> None:
    """A provenance line under the axes (convention, sample counts …); wrapped to the width."""
    t = fig.text(FOOTNOTE_X, 0.005, text, fontsize=MIN_FONT_PT, color="0.3", ha="left", va="bottom", wrap=True)
    fig._netkf_footnotes = [*getattr(fig, "_netkf_footnotes", []), t]


def _wrap(text: str, width: int) -> str:
    """textwrap that never breaks inside a $…$ mathtext span, nor inside a short parenthesis such as
    "diag(1.3, 1.1)" (up to 24 characters: a longer one may break), nor around an "=" ("A = diag(1.3, 1.1)")."""
    protected = text
    for span in (r"\$[^$]*\$", r"\([^()$]{0,24}\)", r"\S+ = \S+"):  # in turn: a joined span is one word for the next
        protected = re.sub(span, lambda m: m.group(0).replace(" ", "\x00"), protected)
    out = "\n".join(textwrap.fill(line, max(width, 10), break_long_words=False, break_on_hyphens=False)
                    for line in protected.split("\n"))
    return out.replace("\x00", " ")


def _fit_titles(fig: Figure) -> None:
    """Wrap a title wider than the canvas (a long paper_title) onto two or more lines."""
    texts = [fig._suptitle] if getattr(fig, "_suptitle", None) is not None else []
    for ax in fig.axes:
        texts += [ax.title, ax._left_title, ax._right_title]
    texts = [t for t in texts if t is not None and t.get_visible() and t.get_text().strip()]
    if not texts:
        return
    r = fig.canvas.get_renderer()  # a text's extent is laid out on demand (wrapping included): no full draw needed
    W = fig.bbox.width * 0.96
    for t in texts:
        w = t.get_window_extent(r).width
        if w > W:
            # characters as drawn: math_bars' "\\mid " draws one bar
            longest = max(len(line.replace(r" \mid ", "|")) for line in t.get_text().split("\n"))
            t.set_text(_wrap(t.get_text().replace(" — ", " —\n", 1), int(longest * W / w * 0.95)))
            shrink = 0.9
            while t.get_window_extent(r).width > W and shrink > 0.4:  # the first split was not enough: wrap
                # everything, narrower each time (characters are not equally wide: a mathtext span's source,
                # e.g. "\\mid ", is longer than what it draws)
                t.set_text(_wrap(t.get_text().replace("\n", " "), int(longest * W / w * shrink)))
                shrink -= 0.1


def _wrapped_text(t, margin: float = 0.0) -> str:
    """matplotlib's ``Text._get_wrapped_text``, the same line breaks with a fraction of its measurements.

    matplotlib breaks each line before the first word whose prefix ``" ".join(words[:i])``, i = 2, 3, …, is wider
    than the room to the canvas edge, measuring every prefix in turn (a footnote line of 20 words: 20 renderings of
    up to 120 characters, ≈ 0.03 ms per character, or a mathtext parse when the prefix holds ``$…$``). The width of
    a prefix grows with i as long as it is drawn the same way — as plain text (the union of its glyphs' boxes) or
    as mathtext (a row of boxes) —, so within each run of prefixes drawn the same way (``cbook.is_math_text``) one
    measurement of the run's last prefix says whether the break lies in it, and an interpolation search
    (:func:`_first_too_wide`) finds it: the first prefix too wide, as matplotlib's scan finds it. The prefixes are measured by matplotlib's own
    ``_get_rendered_text_width`` (its renderer, rounding and cache), with its ``_get_wrap_line_width`` less
    ``margin`` pixels (the room kept free at the right edge)."""
    is_math = _mpl().matplotlib.cbook.is_math_text
    width = t._get_rendered_text_width
    room = t._get_wrap_line_width() - margin
    lines = []
    rate = None  # pixels per character, from the last measurement
    for unwrapped in t.get_text().split("\n"):  # the user's line breaks are kept
        words = unwrapped.split(" ")
        while words:
            n = len(words)
            if n == 1:
                lines.append(words.pop(0))
                continue
            prefix = [" ".join(words[:i]) for i in range(n + 1)]
            first = None  # the first i in 2..n whose prefix is too wide
            i = 2
            while i <= n and first is None:
                mode, j = is_math(prefix[i]), i
                while j < n and is_math(prefix[j + 1]) == mode:
                    j += 1
                try:
                    first, rate = _first_too_wide(prefix, i, j, room, width, rate)
                except ValueError:  # a prefix matplotlib's scan may never reach is not valid mathtext: scan as it does
                    first = next((k for k in range(i, j + 1) if width(prefix[k]) > room), None)
                i = j + 1
            if first is None:
                lines.append(prefix[n])
                words = []
            else:
                lines.append(prefix[first - 1])
                words = words[first - 1:]
    return "\n".join(lines)


def _first_too_wide(prefix: list[str], i: int, j: int, room: float, width, rate: float | None):
    """``(first, rate)``: the first k in [i, j] with ``width(prefix[k]) > room`` (None when ``prefix[j]`` fits), for
    widths that grow with k in [i, j] (one drawing mode), and the pixels per character last measured.

    The answer of a scan or a bisection, found by interpolation search on the prefixes' lengths in characters
    (width per character is nearly constant along a line): the next prefix measured is the longest one the
    measurements so far (or ``rate``, from the lines before) put inside the room, then the next one. A line's break
    costs about two measurements of about one line's length, instead of the run's last prefix (up to the whole rest
    of the text) and log2(j − i) more: each a mathtext parse when the prefix holds ``$…$`` (~13 ms per 160 characters)."""
    a, w_a, c_a = i - 1, 0.0, 0  # a: the last index known to fit (i − 1: not measured, taken as 0 px at 0 chars)
    b = w_b = None  # b: the first index known too wide (None: none known in [i, j])
    while b is None or b - a > 1:
        hi = j if b is None else b - 1
        if b is not None:
            c_b = len(prefix[b])
            c_star = c_a + (room - w_a) * (c_b - c_a) / max(w_b - w_a, 1e-12)  # characters at the room's edge
        else:
            c_star = room / rate if rate else math.inf  # no rate yet: the run's last prefix, as a plain scan would end
        g = a + 1
        while g < hi and len(prefix[g + 1]) <= c_star:  # the longest prefix in (a, hi] at most c_star long
            g += 1
        w_g = width(prefix[g])
        if w_g > 0:
            rate = w_g / len(prefix[g])
        if w_g > room:
            b, w_b = g, w_g
        else:
            a, w_a, c_a = g, w_g, len(prefix[g])
            if b is None and a == j:
                return None, rate
    return b, rate


def _wrap_once(t, renderer) -> None:
    """Freeze a ``wrap=True`` text's line breaks: matplotlib re-wraps it (measuring every word prefix) at every
    extent query and draw — half the time of a small run's figure. The breaks are matplotlib's own (as
    ``_wrapped_text`` finds them), taken once."""
    if not t.get_wrap() or t.get_usetex():  # matplotlib does not wrap TeX either
        return
    try:
        t._renderer = renderer  # what get_window_extent(renderer) binds: the renderer the wrapping measures with
        # matplotlib's room runs to the canvas edge, where a footnote's last word then touches it (Mostofi Thm 4's
        # "Y_t"): the left margin is kept on the right too
        wrapped = _wrapped_text(t, FOOTNOTE_X * t.get_figure().bbox.width)  # matplotlib's private helpers: if they
        # move, keep matplotlib's wrapping on
    except AttributeError:  # pragma: no cover - another matplotlib
        return
    t.set_text(wrapped)
    t.set_wrap(False)


NICE_LOG_TICKS = ((1, 1.5, 2, 3, 4, 5, 6, 8), (1, 2, 3, 5), (1, 2, 5))
"""Mantissas a short log axis is labelled at (:func:`plain_log_labels`), the first set with at most
:data:`MAX_LOG_TICKS` ticks in view."""
MAX_LOG_TICKS = 8


def _nice_log_ticks(lo: float, hi: float) -> list[float]:
    """Ticks m·10ⁿ in [lo, hi] for the first mantissa set of :data:`NICE_LOG_TICKS` giving ≤ MAX_LOG_TICKS of them."""
    decades = range(int(np.floor(np.log10(lo))), int(np.floor(np.log10(hi))) + 1)
    for subs in NICE_LOG_TICKS:
        ticks = [float(f"{m * 10.0 ** d:.12g}") for d in decades for m in subs if lo <= m * 10.0 ** d <= hi]
        if len(ticks) <= MAX_LOG_TICKS:
            return ticks
    return ticks


@functools.cache
def _plain_log_formatter(ticker):
    """``ticker.LogFormatter`` writing every label as ``%g`` ("0.4", "2"; its own writes "4e-01" below 1)."""
    class PlainLogFormatter(ticker.LogFormatter):
        def _num_to_string(self, x, vmin, vmax):
            return f"{x:g}"

    return PlainLogFormatter


def plain_log_labels(fig: Figure) -> None:
    """Plain-number tick labels ("1.5 2 3 4 5 6 8") on every log axis that spans less than a factor 20 between
    10⁻³ and 10⁴: there matplotlib labels the minor ticks "2×10⁰ 3×10⁰ 4×10⁰ …", wide enough to collide, and
    leaves the ends of the axis unlabelled (Leong burstiness, L_B = 1.25 … 8: its 8 had no label; ``lint``
    reports overlapping tick labels). The labelled ticks are the nice numbers of :data:`NICE_LOG_TICKS` in
    view (the minor log ticks stay, unlabelled); with fewer than two in view, matplotlib's ticks are written as
    plain numbers. An axis with a formatter of its own, or a wider span (where only the decades 10ⁿ are
    labelled), is left as it is."""
    ticker = _mpl().matplotlib.ticker
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            if axis.get_scale() != "log" or type(axis.get_major_formatter()) is not ticker.LogFormatterSciNotation:
                continue
            lo, hi = sorted(axis.get_view_interval())
            if not (1e-3 <= lo and hi <= 1e4 and hi < 20 * lo):
                continue
            ticks = _nice_log_ticks(lo, hi)
            if len(ticks) < 2:  # too narrow for two nice numbers: matplotlib's choice of ticks, written as %g
                axis.set_major_formatter(_plain_log_formatter(ticker)())
                axis.set_minor_formatter(_plain_log_formatter(ticker)(labelOnlyBase=False))
                continue
            axis.set_major_locator(ticker.FixedLocator(ticks))
            axis.set_major_formatter(ticker.FuncFormatter(lambda v, _pos: f"{v:g}"))
            axis.set_minor_formatter(ticker.NullFormatter())


@contextmanager
def _tight_bboxes_once():
    """Within one ``tight_layout``: each artist's layout bounding box computed once.

    With a ``rect`` (the footnotes' room at the bottom), matplotlib's ``get_tight_layout_figure`` runs
    ``_auto_adjust_subplotpars`` twice, and each pass asks every axes (and, inside, each of its children) for
    ``artist._get_tightbbox_for_layout_only`` — ticks updated, every label's extent measured — with nothing
    moved in between: the second pass gets the first one's boxes. Memoized here for the duration of the call
    (keyed by the artist and the renderer), the layout is the same (the same subplot parameters, the same
    pixels: tests/figures) for half the work: tight_layout was 45 % of writing the 37 figures. A matplotlib
    without that private function runs unchanged."""
    martist = _mpl().matplotlib.artist
    orig = getattr(martist, "_get_tightbbox_for_layout_only", None)
    if orig is None:  # pragma: no cover - another matplotlib
        yield
        return
    memo: dict = {}

    def once(obj, *args, **kwargs):
        key = (id(obj), tuple(id(a) for a in args), tuple((k, id(v)) for k, v in sorted(kwargs.items())))
        hit = memo.get(key)
        if hit is None:
            hit = memo[key] = (obj, args, orig(obj, *args, **kwargs))  # obj, args kept alive: ids stay theirs
        return hit[2]

    martist._get_tightbbox_for_layout_only = once
    try:
        yield
    finally:
        martist._get_tightbbox_for_layout_only = orig


EMPTY_LOG_NOTE = "nothing to draw: no positive value on this log scale"


def empty_log_axes(fig: Figure) -> None:
    """A log axis with nothing positive to draw (a tail run of one run: every probability 0) gets the decade
    [1, 10] and says so in the axes: matplotlib (3.11) refuses to draw a log axis whose data are all ≤ 0."""
    for ax in fig.axes:
        empty = [name for name, scale, minpos, lim in (("x", ax.get_xscale(), ax.dataLim.minposx, ax.get_xlim()),
                                                        ("y", ax.get_yscale(), ax.dataLim.minposy, ax.get_ylim()))
                 if scale == "log" and not np.isfinite(minpos) and min(lim) <= 0]  # limits the plot set are kept
        for name in empty:
            getattr(ax, f"set_{name}lim")(1, 10)
        if empty:
            ax.text(0.5, 0.5, EMPTY_LOG_NOTE, transform=ax.transAxes, ha="center", va="center", color="0.3")


def _layout(fig: Figure) -> None:
    """tight_layout with room at the bottom for the (wrapped) footnotes; long titles wrapped; short log axes
    labelled with plain numbers (:func:`plain_log_labels`); an empty log axis drawable (:func:`empty_log_axes`)."""
    empty_log_axes(fig)
    plain_log_labels(fig)
    _fit_titles(fig)
    notes = getattr(fig, "_netkf_footnotes", [])
    bottom = 0.0
    if notes:
        r = fig.canvas.get_renderer()
        h = fig.bbox.height
        y = 0.005 * h
        for t in notes:  # stack them upwards, bottom line first
            t.set_y(y / h)
            _wrap_once(t, r)
            y += t.get_window_extent(r).height + 2
        bottom = min(0.4, (y + 4) / h)

    engine = fig.get_layout_engine()
    try:
        with warnings.catch_warnings():  # a layout that cannot fit is reported by lint(), not as a warning
            warnings.filterwarnings("ignore", message="Tight layout not applied")
            with _tight_bboxes_once():
                fig.tight_layout(rect=(0, bottom, 1, 1))
    except (ValueError, RuntimeError):  # pragma: no cover - degenerate layouts
        pass
    if engine is None:
        # tight_layout leaves a placeholder layout engine behind, and savefig draws a figure that has one twice
        # (a draw "to make sure the layout works", then the printed one): a third of the save's CPU for nothing,
        # the layout being done. Without an engine the printed draw is the only one (the same pixels, tested).
        fig.set_layout_engine(None)


KNOWN_FORMATS = ("png", "pdf", "svg")
#: zlib level of the PNGs' unfiltered rows (lossless: the same pixels at any level). The 37 full-size figures: level 1
#: 6.06 MB, 3 5.78 MB (0.05 s more CPU of 0.45), 6 5.30 MB (2.5x the CPU); Pillow's filtered rows at 3: 6.19 MB
PNG_COMPRESS_LEVEL = 3


def save(fig: Figure, path, dpi: int | None = None, formats: Iterable[str] | None = None) -> list[Path]:
    """Lay out and write ``fig``; returns the files written.

    ``save(fig, "out/fig5.png", dpi=150)`` writes that PNG (the old call); with ``formats``
    (e.g. ``("png", "pdf", "svg")``) every format is written next to ``path`` with the same stem
    (a known suffix on ``path`` is replaced). PDF and SVG carry no creation date, so they are
    reproducible byte for byte.
    """
    path = Path(path)
    suffix = path.suffix.lower().lstrip(".")
    if formats is None:
        formats = (suffix,) if suffix in KNOWN_FORMATS else ("png",)
    formats = tuple(dict.fromkeys(str(f).lower().lstrip(".") for f in formats))
    bad = [f for f in formats if f not in KNOWN_FORMATS]
    if bad or not formats:
        _mpl().plt.close(fig)
        raise ValueError(f"unknown figure format(s) {bad or formats}; choose from {KNOWN_FORMATS}")
    plt = _mpl().plt
    stem = path.with_suffix("") if suffix in KNOWN_FORMATS else path
    dpi = dpi or STYLE["savefig.dpi"]
    # laid out at the dpi it is saved at: the layout's text extents, mathtext parses and renderer are then the
    # save's own (one parse per string instead of one per dpi, the renderer reused by savefig)
    fig.set_dpi(dpi)
    _layout(fig)
    lint_dir = os.environ.get("NETKF_FIGURE_LINT")
    if lint_dir:
        try:
            fig.canvas.draw()  # the lint reads drawn positions (a legend's loc="best" is placed at draw time)
            problems = lint(fig)
        except Exception as exc:  # the lint must never stop a figure from being written
            problems = [f"lint crashed: {type(exc).__name__}: {exc}"]
        report = {"figure": stem.name, "problems": problems, "titles": titles(fig)}
        Path(lint_dir).mkdir(parents=True, exist_ok=True)
        (Path(lint_dir) / f"{stem.name}.json").write_text(json.dumps(report, indent=1, ensure_ascii=False), encoding="utf-8")
    written = []
    meta = {"pdf": {"CreationDate": None}, "svg": {"Date": None}}
    try:
        for f in formats:
            out = stem.with_name(stem.name + "." + f)
            if f == "png":
                _write_png(fig, out, dpi)
            else:
                fig.savefig(out, dpi=dpi, format=f, metadata=meta[f])
            written.append(out)
    finally:
        plt.close(fig)
    return written


def _write_png(fig: Figure, out: Path, dpi: float) -> None:
    """The PNG matplotlib's ``savefig(format="png")`` writes — the same draw, pixels, dpi and "Software" text —
    as RGB when every pixel is opaque (a netkf figure's white face: always), its rows unfiltered, deflated at
    :data:`PNG_COMPRESS_LEVEL`.

    matplotlib hands Pillow the RGBA canvas whatever it holds; an opaque image's alpha channel is a quarter of
    the bytes zlib compresses for nothing (37 figures: 20 % less encoding CPU, files 10 % smaller). Pillow's
    encoder also tries the five PNG row filters on every row and keeps the best (half its time); a figure's
    flat colours compress better unfiltered (filter type 0: the 37 full-size figures 5.8 instead of 6.2 MB, the
    encoding 1.1 -> 0.45 s CPU), so the file is written here: signature, IHDR, tEXt, pHYs (dots per metre, as
    Pillow writes the dpi), one IDAT, IEND (PNG spec, ISO/IEC 15948). The canvas is drawn by
    ``savefig(format="rgba")`` (the raw buffer after savefig's own face-colour and dpi handling, read in place:
    :class:`_RawCanvas`), so the pixels are matplotlib's (tests/figures/test_save_cost); the rows are built and
    deflated a band of :data:`PNG_BAND_BYTES` at a time, so the PNG costs no copy of the whole canvas."""
    from PIL import Image  # pillow: matplotlib's own dependency, imported with it (at the first figure)

    canvas = _RawCanvas()
    fig.savefig(canvas, dpi=dpi, format="rgba")
    r = fig.canvas.get_renderer()  # the one savefig drew with: the raw buffer is its (height, width, 4) pixels
    w, h = int(r.width), int(r.height)
    rgba = np.asarray(canvas.view, dtype=np.uint8).reshape(h, w, 4)
    mode = "RGB" if rgba[:, :, 3].min() == 255 else "RGBA"
    channels = len(mode)
    # the rows deflated a band at a time (the same stream as one call: no flush in between), each row its filter
    # type (0: none) then its pixels; Pillow drops the alpha bytes ~10x faster than a strided numpy copy
    band = max(1, min(h, PNG_BAND_BYTES // (4 * w)))
    rows = np.zeros((band, 1 + w * channels), dtype=np.uint8)
    deflate = zlib.compressobj(PNG_COMPRESS_LEVEL)
    idat = []
    for top in range(0, h, band):
        n = min(band, h - top)
        px = Image.frombuffer("RGBA", (w, n), rgba[top:top + n], "raw", "RGBA", 0, 1).tobytes("raw", mode)
        rows[:n, 1:] = np.frombuffer(px, dtype=np.uint8).reshape(n, w * channels)
        idat.append(deflate.compress(rows[:n]))
    idat.append(deflate.flush())
    software = f"Matplotlib version{_mpl().matplotlib.__version__}, https://matplotlib.org/"
    per_metre = int(dpi / 0.0254 + 0.5)
    out.write_bytes(b"\x89PNG\r\n\x1a\n"
                    + _png_chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2 if mode == "RGB" else 6, 0, 0, 0))
                    + _png_chunk(b"tEXt", b"Software\0" + software.encode("latin-1"))
                    + _png_chunk(b"pHYs", struct.pack(">IIB", per_metre, per_metre, 1))
                    + _png_chunk(b"IDAT", b"".join(idat))
                    + _png_chunk(b"IEND", b""))


PNG_BAND_BYTES = 1 << 20
"""Canvas bytes turned into PNG rows at a time (:func:`_write_png`): a figure's whole RGBA canvas copied to bytes,
to RGB and to filtered rows was 3 copies of up to 12 MB at the peak of a small run (smoothing table1's two panels,
1712 x 1695 px), ~40 MB over the 300 MB of issue 20."""


class _RawCanvas:
    """The file ``savefig(format="rgba")`` writes into: it keeps the memoryview of the renderer's own buffer that
    matplotlib's ``print_raw`` writes, without copying it (valid until the figure is drawn again)."""

    view = None

    def write(self, data) -> int:
        self.view = data
        return len(memoryview(data).cast("B"))

    def seek(self, offset: int, whence: int = 0) -> int:  # what matplotlib checks to take it as a file handle
        return 0


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    """A PNG chunk: length, type, data, CRC-32 of type and data."""
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


# ---------------------------------------------------------------------------- figure lint
def titles(fig: Figure) -> list[str]:
    """Every non-empty title of the figure: the suptitle first, then the axes titles."""
    out = []
    if getattr(fig, "_suptitle", None) is not None and fig._suptitle.get_text().strip():
        out.append(fig._suptitle.get_text())
    for ax in fig.axes:
        for loc in ("center", "left", "right"):
            s = ax.get_title(loc=loc)
            if s.strip():
                out.append(s)
    return out


def _is_reference_line(ax, line) -> bool:
    """axhline/axvline and friends: drawn in a blended (axes-fraction) transform."""
    return line.get_transform() != ax.transData and not line.get_transform().contains_branch(ax.transData)


def _series(ax) -> tuple[list[str], int]:
    """(labels of labelled series, number of unlabelled data series) drawn in ``ax``."""
    handles, labels = ax.get_legend_handles_labels()
    in_container = set()
    for c in ax.containers:
        for child in c.get_children() if hasattr(c, "get_children") else c:
            if child is not None:
                in_container.add(id(child))
    unlabelled = 0
    for line in ax.get_lines():
        if not line.get_visible() or id(line) in in_container or _is_reference_line(ax, line):
            continue
        lab = line.get_label() or ""
        if lab.startswith("_child") or lab == "":
            unlabelled += 1
    for coll in ax.collections:
        lab = coll.get_label() or ""
        if type(coll).__name__ == "PathCollection" and id(coll) not in in_container and coll.get_visible() \
                and (lab.startswith("_child") or lab == ""):
            unlabelled += 1  # a scatter without a label
    return labels, unlabelled


def _shows_nothing(handle) -> bool:
    """Whether a legend handle's artist has points but none finite (a series whose every value is NaN: its legend
    entry would name a line that is not there). A handle with no points at all is a legend proxy (a key to the
    colours or line styles, drawn with ``plot([], [])``): deliberate."""
    line = handle[0] if isinstance(handle, tuple) or type(handle).__name__ == "ErrorbarContainer" else handle
    if line is None:
        return False
    if hasattr(line, "get_xydata"):
        xy = np.asarray(line.get_xydata(), dtype=float)
    elif hasattr(line, "get_offsets"):
        xy = np.asarray(line.get_offsets(), dtype=float)
    else:
        return False  # patches, bars, images: drawn as they are
    return xy.size > 0 and not np.isfinite(xy).all(axis=-1).any()


def lint(fig: Figure) -> list[str]:
    """What a referee would object to, as readable lines (empty = clean). Call after layout."""
    problems: list[str] = []
    if not titles(fig):
        problems.append("no title (use plotting.paper_title)")
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    axes = [a for a in fig.axes if a.get_visible() and a.axison]
    fig_legend_labels = [t.get_text() for lg in fig.legends for t in lg.get_texts()]
    all_series: list[str] = []
    for i, ax in enumerate(axes):
        name = f"axes {i}" + (f" ({ax.get_title()!r})" if ax.get_title() else "")
        has_data = bool(ax.get_lines() or ax.collections or ax.patches or ax.images or ax.containers)
        if not has_data:
            continue
        for which, get, shared in (("x", ax.get_xlabel, ax.get_shared_x_axes()), ("y", ax.get_ylabel, ax.get_shared_y_axes())):
            if get().strip():
                continue
            sib = [s for s in shared.get_siblings(ax) if s is not ax]
            if not any((s.get_xlabel() if which == "x" else s.get_ylabel()).strip() for s in sib):
                problems.append(f"{name}: no {which}-axis label")
        labels, unlabelled = _series(ax)
        all_series += labels
        lg = ax.get_legend()
        legend_labels = [t.get_text() for t in lg.get_texts()] if lg is not None else []
        for lab in legend_labels:
            if lab not in labels:
                problems.append(f"{name}: legend entry {lab!r} has no drawn series")
        for h, lab in zip(*ax.get_legend_handles_labels()):
            if lab in legend_labels and _shows_nothing(h):
                problems.append(f"{name}: legend entry {lab!r} names a series with no finite point")
        for lab in labels:
            if lab not in legend_labels and lab not in fig_legend_labels:
                problems.append(f"{name}: series {lab!r} has no legend entry")
        if unlabelled and (legend_labels or labels or unlabelled > 1):
            problems.append(f"{name}: {unlabelled} drawn series without a label (no legend entry)")
    for i, ax in enumerate(axes):
        n = _points_under_legend(ax, r)
        if n:
            problems.append(f"axes {i}: the legend covers {n} data point(s) (use legend_outside or an empty region)")
        for which, a, b in _overlapping_tick_labels(ax, r):
            problems.append(f"axes {i}: {which}-axis tick labels {a!r} and {b!r} overlap")
    for lab in fig_legend_labels:
        if lab not in all_series:
            problems.append(f"figure legend entry {lab!r} has no drawn series")
    W, H = fig.bbox.width, fig.bbox.height

    every_tick, drawn_tick = _tick_labels(fig)
    seen = set()
    for t in fig.findobj(_mpl().text.Text):
        if id(t) in seen or not t.get_visible() or not t.get_text().strip():
            continue
        seen.add(id(t))
        if id(t) in every_tick and id(t) not in drawn_tick:
            continue
        if t.get_fontsize() < MIN_FONT_PT - 1e-6:
            problems.append(f"text {t.get_text()[:40]!r}: {t.get_fontsize():.1f} pt < {MIN_FONT_PT:g} pt")
        try:
            bb = t.get_window_extent(r)
        except (RuntimeError, ValueError):
            continue
        if bb.x0 < -1 or bb.y0 < -1 or bb.x1 > W + 1 or bb.y1 > H + 1:
            problems.append(f"text {t.get_text()[:40]!r} lies outside the canvas")
    return problems


def _points_under_legend(ax, renderer) -> int:
    """How many drawn data vertices (lines, markers, scatter points) lie under the axes' legend."""
    lg = ax.get_legend()
    if lg is None or not lg.get_visible():
        return 0
    bb = lg.get_window_extent(renderer).padded(-2)
    if bb.width <= 0 or bb.height <= 0 or not bb.overlaps(ax.get_window_extent(renderer)):
        return 0
    pts = []
    for line in ax.get_lines():
        if line.get_visible() and not _is_reference_line(ax, line):
            xy = np.column_stack([np.asarray(line.get_xdata(), float), np.asarray(line.get_ydata(), float)])
            if len(xy):
                pts.append(line.get_transform().transform(xy))
    for coll in ax.collections:
        if coll.get_visible() and type(coll).__name__ == "PathCollection":
            off = coll.get_offsets()
            if len(off):
                pts.append(coll.get_offset_transform().transform(np.asarray(off, float)))
    if not pts:
        return 0
    xy = np.vstack(pts)
    xy = xy[np.isfinite(xy).all(axis=1)]
    axbb = ax.get_window_extent(renderer)
    inside_axes = (xy[:, 0] >= axbb.x0) & (xy[:, 0] <= axbb.x1) & (xy[:, 1] >= axbb.y0) & (xy[:, 1] <= axbb.y1)
    under = (xy[:, 0] > bb.x0) & (xy[:, 0] < bb.x1) & (xy[:, 1] > bb.y0) & (xy[:, 1] < bb.y1)
    return int((under & inside_axes).sum())


def _overlapping_tick_labels(ax, renderer) -> list[tuple[str, str, str]]:
    """(axis, label, label) for every two drawn tick labels of one axis whose boxes overlap (e.g. the minor
    labels "3×10⁰" and "4×10⁰" of a log axis spanning less than a decade)."""
    out = []
    for which, axis in (("x", ax.xaxis), ("y", ax.yaxis)):
        try:
            shown = axis._update_ticks()  # the ticks inside the view (what draw() draws)
        except Exception:  # pragma: no cover - private API moved: no check
            continue
        boxes = []
        for tk in shown:
            for lab in (tk.label1, tk.label2):
                if lab.get_visible() and lab.get_text().strip():
                    boxes.append((lab.get_text(), lab.get_window_extent(renderer)))
        for j, (ta, ba) in enumerate(boxes):
            for tb, bb in boxes[j + 1:]:
                if ba.padded(-0.5).overlaps(bb.padded(-0.5)):
                    out.append((which, ta, tb))
    return out


def _tick_labels(fig) -> tuple[set[int], set[int]]:
    """(ids of every tick label, ids of the tick labels actually drawn)."""
    every, drawn = set(), set()
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            for tk in axis.get_major_ticks() + axis.get_minor_ticks():
                every.update((id(tk.label1), id(tk.label2)))
            try:
                shown = axis._update_ticks()  # the ticks inside the view (what draw() draws)
            except Exception:  # pragma: no cover - private API moved: check every label
                shown = axis.get_major_ticks() + axis.get_minor_ticks()
            for tk in shown:
                if tk.label1.get_visible():
                    drawn.add(id(tk.label1))
                if tk.label2.get_visible():
                    drawn.add(id(tk.label2))
    return every, drawn
