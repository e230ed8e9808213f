"""The shared figure style (netkf_cli/runtime/plotting.py): titles, palette, formats and the lint itself."""

import json

import numpy as np
import pytest

from netkf_cli.runtime import plotting as P


def test_paper_titles():
    assert P.paper_title("shi2009", 5, "Pr[P_k ≤ M], D = 10, d = 5") == \
        "Shi, Xie & Murray 2009 — Fig. 5: Pr[P_k ≤ M], D = 10, d = 5"
    assert P.paper_title("smoothing", "Table I", "arrival rates") == "Leong, Dey & Evans 2008 — Table I: arrival rates"
    assert P.paper_title("fusion", None, "x") == "Chiuso & Schenato 2009 — x"
    assert P.paper_title(None, 3, "my scenario") == "my scenario"
    with pytest.raises(ValueError):
        P.paper_title("nope", 1, "x")


def test_series_styles_differ_in_colour_linestyle_and_marker():
    styles = [P.series_style(i) for i in range(len(P.PALETTE))]
    for key in ("color", "linestyle", "marker"):
        vals = [repr(s[key]) for s in styles[:6]]
        assert len(set(vals)) == 6, key
    assert len(set(P.PALETTE)) == len(P.PALETTE) == 8


def _clean_figure():
    fig, ax = P.new_figure()
    x = np.linspace(0, 10, 30)
    for i in range(2):
        ax.plot(x, np.sin(x + i), **{**P.series_style(i), "marker": None}, label=rf"$\Upsilon_T$ = {i} dB")
    ax.errorbar([1, 2], [0.1, 0.2], yerr=[0.05, 0.05], fmt="o", label="Monte Carlo ± 1 s.e.")
    ax.set_title(P.paper_title("fading", 5, r"$\|E\,P_\infty\|$ vs $\Upsilon_T$"))
    ax.set_xlabel(r"$\Upsilon_T$ (dB)")
    ax.set_ylabel(r"$P_{k|k-1}$")
    P.legend_outside(ax)
    P.footnote(fig, "provenance " * 40)
    return fig


def test_clean_figure_passes_lint_and_every_format_is_written(tmp_path):
    fig = _clean_figure()
    P._layout(fig)
    assert P.lint(fig) == []
    files = P.save(fig, tmp_path / "f.png", formats=["png", "pdf", "svg"], dpi=80)
    assert [f.name for f in files] == ["f.png", "f.pdf", "f.svg"]
    assert (tmp_path / "f.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (tmp_path / "f.pdf").read_bytes()[:5] == b"%PDF-"
    assert b"<svg" in (tmp_path / "f.svg").read_bytes()[:2000]


def test_old_call_still_writes_the_given_path(tmp_path):
    fig = _clean_figure()
    assert P.save(fig, tmp_path / "old.png", dpi=50) == [tmp_path / "old.png"]
    assert (tmp_path / "old.png").exists() and not (tmp_path / "old.pdf").exists()


def test_pdf_and_svg_are_reproducible_byte_for_byte(tmp_path):
    P.save(_clean_figure(), tmp_path / "a", formats=["pdf", "svg"])
    P.save(_clean_figure(), tmp_path / "b", formats=["pdf", "svg"])
    for ext in ("pdf", "svg"):
        assert (tmp_path / f"a.{ext}").read_bytes() == (tmp_path / f"b.{ext}").read_bytes(), ext


def test_unknown_format_is_refused(tmp_path):
    with pytest.raises(ValueError, match="unknown figure format"):
        P.save(_clean_figure(), tmp_path / "x", formats=["bmp"])


def test_lint_finds_each_kind_of_problem():
    fig, ax = P.new_figure()
    ax.plot([1, 2], [3, 4], label="drawn, not in legend")
    ax.plot([1, 2], [4, 3], "o")  # unlabelled markers
    ax.legend(handles=[ax.plot([], [], label="x")[0]], labels=["ghost entry"], fontsize=7)
    ax.text(30, 30, "far away")
    P._layout(fig)
    problems = "\n".join(P.lint(fig))
    for needle in ("no title", "no x-axis label", "no y-axis label", "'ghost entry' has no drawn series",
                   "'drawn, not in legend' has no legend entry", "without a label", "lies outside the canvas",
                   "< 9 pt"):
        assert needle in problems, (needle, problems)


def test_upsilon_uses_a_font_with_a_distinct_glyph():
    """DejaVu Sans draws U+03A5 like a Latin Y; the mathtext font set must not be DejaVu's."""
    import matplotlib

    assert matplotlib.rcParams["mathtext.fontset"] not in ("dejavusans", "dejavuserif")
    fig, ax = P.new_figure()
    t = ax.text(0.5, 0.5, r"$\Upsilon_T \leq \theta$")
    fig.canvas.draw()
    assert t.get_window_extent().width > 0


def test_a_title_wider_than_the_canvas_is_wrapped_not_cut(tmp_path):
    fig, ax = P.new_figure(width=5.0)
    ax.plot([1, 2], [1, 2])
    ax.set_xlabel("x (1)")
    ax.set_ylabel("y (1)")
    ax.set_title(P.paper_title("smoothing", "Table I (extension)",
                               r"Table I under Gilbert–Elliott loss, each column at its eq. (8) rate, $\Pr[P_{k|k+N} \leq M]$"))
    P._layout(fig)
    assert P.lint(fig) == []
    # the math span is never broken (its bar drawn as \mid: plotting.math_bars)
    assert "\n" in ax.get_title() and r"$\Pr[P_{k \mid k+N} \leq M]$" in ax.get_title().replace("\n", " ")


def test_a_wrapped_title_keeps_short_parentheses_and_assignments_whole():
    """A break falls between phrases, not in "diag(1.3, 1.1)" nor between "A =" and its value (the tail figure's
    title once ended "A =" / "diag(1.3, 1.1)"); a parenthesis longer than 24 characters may still break."""
    t = r"tail of $\mathrm{tr}\,P_k$ (Mo & Sinopoli 2012) over Gilbert–Elliott loss p = 0.2, q = 0.6, A = diag(1.3, 1.1)"
    for width in range(12, 90, 3):
        lines = P._wrap(t, width).split("\n")
        assert " ".join(lines) == t
        for whole in ("diag(1.3, 1.1)", "A = diag(1.3, 1.1)", "p = 0.2,", "q = 0.6,", r"$\mathrm{tr}\,P_k$",
                      "(Mo & Sinopoli 2012)"):
            assert any(whole in line for line in lines), (width, whole, lines)
    long = "x (a parenthesis of more than twenty-four characters) y"
    assert "\n" in P._wrap(long, 20).strip("\n") and P._wrap(long, 20).replace("\n", " ") == long


def test_lint_sees_a_legend_over_the_data():
    import numpy as np

    fig, ax = P.new_figure()
    x = np.linspace(0, 1, 50)
    ax.plot(x, np.ones_like(x) * 0.9, label="near the top")
    ax.plot(x, x * 0.1, label="near the bottom")
    ax.set_xlabel("x (1)")
    ax.set_ylabel("y (1)")
    ax.set_title(P.paper_title(None, None, "legend test"))
    ax.set_ylim(0, 1)
    ax.legend(loc="upper right")
    P._layout(fig)
    assert any("legend covers" in p for p in P.lint(fig))
    ax.legend(loc="center")  # an empty region
    P._layout(fig)
    assert P.lint(fig) == []


def _short_log_axis():
    """Leong burstiness' x axis: L_B = 1.25 … 8 on a log scale (less than a decade), a narrow panel."""
    fig, ax = P.new_figure(width=3.2)
    x = np.array([1.25, 1.5, 2.0, 2.2, 3.0, 4.0, 6.0, 8.0])
    ax.plot(x, 1 / x, **P.series_style(0), label="a series")
    ax.set_xscale("log")
    ax.set_title(P.paper_title("smoothing", "Table I", "burstiness"))
    ax.set_xlabel("mean loss-burst length")
    ax.set_ylabel("value")
    ax.legend()
    return fig, ax


def test_lint_reports_overlapping_tick_labels():
    fig, ax = _short_log_axis()
    fig.set_dpi(P.STYLE["savefig.dpi"])
    fig.tight_layout()
    problems = P.lint(fig)  # matplotlib's own labels: 2×10⁰ 3×10⁰ 4×10⁰ 6×10⁰ on a 2.5-inch axis
    assert any("x-axis tick labels" in p and "overlap" in p for p in problems), problems
    P._mpl().plt.close(fig)


def test_save_labels_a_short_log_axis_with_plain_numbers(tmp_path, monkeypatch):
    lint_dir = tmp_path / "lint"
    monkeypatch.setenv("NETKF_FIGURE_LINT", str(lint_dir))
    fig, ax = _short_log_axis()
    P.save(fig, tmp_path / "f.png")
    assert json.loads((lint_dir / "f.json").read_text(encoding="utf-8"))["problems"] == []
    labels = [t.get_text() for t in ax.get_xticklabels(minor=True) + ax.get_xticklabels() if t.get_text()]
    assert labels == ["1.5", "2", "3", "4", "5", "6", "8"], labels  # the last grid point, 8, labelled too
    assert P._nice_log_ticks(0.013, 0.2) == [0.02, 0.03, 0.05, 0.1, 0.2]  # more than MAX_LOG_TICKS: a coarser set
    assert P._nice_log_ticks(1.1, 1.4) == []  # nothing nice in view: matplotlib's ticks stay, in plain numbers
    fig2, ax2 = P.new_figure()
    ax2.plot([1.1, 1.4], [1, 2])
    ax2.set_xscale("log")
    ax2.set_xlim(1.1, 1.4)
    P.plain_log_labels(fig2)
    assert type(ax2.xaxis.get_minor_formatter()).__name__ == "PlainLogFormatter"
    P._mpl().plt.close(fig2)
    # a log axis over several decades keeps matplotlib's 10ⁿ labels
    fig, ax = P.new_figure()
    ax.loglog([1e-3, 1e2], [1, 2], label="wide")
    P.plain_log_labels(fig)
    assert type(ax.xaxis.get_major_formatter()).__name__ == "LogFormatterSciNotation"
    P._mpl().plt.close(fig)


def test_a_log_axis_with_nothing_positive_is_drawn_and_says_so(tmp_path):
    """matplotlib (3.11) refuses to draw a log axis whose data are all ≤ 0 ("Data cannot be log-scaled"): save gives
    it a decade and a note instead of failing; limits a plot set itself are kept."""
    fig, ax = P.new_figure()
    ax.errorbar([], [], yerr=[[], []], fmt="o")  # what the tail drew for a run with every estimate 0
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("M (1)")
    ax.set_ylabel("p (1)")
    P.save(fig, tmp_path / "empty.png")
    assert (tmp_path / "empty.png").stat().st_size > 0
    assert ax.get_ylim() == (1.0, 10.0) and any(t.get_text() == P.EMPTY_LOG_NOTE for t in ax.texts)
    fig, ax = P.new_figure()
    ax.plot([], [])
    ax.set_yscale("log")
    ax.set_ylim(1e-3, 1)
    P.save(fig, tmp_path / "kept.png")
    assert ax.get_ylim() == (1e-3, 1) and not ax.texts


def test_lint_sees_a_legend_entry_whose_series_is_all_nan():
    """A series whose every value is NaN (every mean flagged and drawn elsewhere) has nothing on the axes: its legend
    entry is a problem; a legend proxy drawn with no points at all (a key to colours) is not."""
    fig, ax = P.new_figure()
    ax.errorbar([1, 2], [np.nan, np.nan], yerr=[1, 1], label="flagged means (Monte Carlo)")
    ax.plot([1, 2], [1, 2], label="drawn")
    ax.plot([], [], color="k", label="proxy: black = exact")
    ax.set_xlabel("x (1)")
    ax.set_ylabel("y (1)")
    ax.set_title("t")
    P.legend_outside(ax)
    P._layout(fig)
    problems = P.lint(fig)
    assert problems == ["axes 0 ('t'): legend entry 'flagged means (Monte Carlo)' names a series with no finite point"]
