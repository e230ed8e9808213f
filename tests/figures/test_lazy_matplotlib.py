"""matplotlib is imported by the first function that draws, not with netkf (issue 20): every ``netkf`` start and
every forked worker that never draws saved ≈ 0.5 s and ≈ 27 MB RSS. Each check runs in a fresh interpreter
(this test session has imported matplotlib long ago)."""

import subprocess
import sys
import textwrap

from tests.conftest import ROOT


def _fresh(code: str) -> str:
    r = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=ROOT, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    return r.stdout.strip()


def test_importing_the_cli_does_not_import_matplotlib():
    out = _fresh("""
        import sys
        import netkf_cli.app.cli, netkf_cli.app.api, netkf_cli.app.reproduce, netkf_cli.runtime.plotting
        print(sorted(m for m in sys.modules if m == "matplotlib" or m.startswith(("matplotlib.", "PIL"))))
    """)
    assert out == "[]", f"imported at netkf's import: {out}"


def test_the_first_figure_sets_up_backend_style_and_mathtext_cache():
    out = _fresh("""
        import sys
        from netkf_cli.runtime import plotting as P
        assert P.STYLE["axes.prop_cycle"] is None and "matplotlib" not in sys.modules
        fig, ax = P.new_figure()
        import matplotlib
        from matplotlib.mathtext import MathTextParser
        rc = matplotlib.rcParams
        print(matplotlib.get_backend().lower(), rc["mathtext.fontset"], rc["font.size"], rc["savefig.dpi"],
              rc["axes.prop_cycle"].by_key()["color"] == list(P.PALETTE),
              rc["axes.prop_cycle"].by_key()["linestyle"][4] == P.LINESTYLES[4],
              getattr(MathTextParser._parse_cached, "_netkf_shared", False),
              not ax.spines["top"].get_visible() and not ax.spines["right"].get_visible())
    """)
    assert out == "agg stixsans 10.0 150.0 True True True True", out


def test_a_forked_worker_draws_whether_or_not_its_parent_set_matplotlib_up(tmp_path):
    """``netkf reproduce`` workers draw: from a parent that never imported matplotlib, and from one that did
    (``plotting.setup()`` before the pool, and after drawing a figure with mathtext: the shared cache is
    cleared in the child)."""
    out = _fresh(f"""
        import multiprocessing as mp, sys
        from pathlib import Path
        from netkf_cli.runtime import plotting as P

        def draw(name):
            fig, ax = P.new_figure()
            ax.semilogy([1, 2, 3], [1e-3, 1e-1, 1e1], label=r"$P_{{k \\mid k-1}}$")
            ax.set_title(P.paper_title("shi2009", 5, r"$\\Upsilon_T$"))
            ax.set_xlabel("k"); ax.set_ylabel("P")
            P.legend_outside(ax)
            P.footnote(fig, r"runs of $\\bar V$ " * 12)
            return [p.stat().st_size for p in P.save(fig, Path({str(tmp_path)!r}) / name)]

        ctx = mp.get_context("fork")
        with ctx.Pool(1) as pool:
            cold = pool.apply(draw, ("cold.png",))
        assert "matplotlib" not in sys.modules
        draw("parent.png")
        with ctx.Pool(1) as pool:
            warm = pool.apply(draw, ("warm.png",))
        print(cold[0] > 1000, warm[0] > 1000)
    """)
    assert out == "True True", out
    assert (tmp_path / "cold.png").read_bytes() == (tmp_path / "warm.png").read_bytes() == \
        (tmp_path / "parent.png").read_bytes()
