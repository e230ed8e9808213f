"""CI regenerates every paper artefact at quick size and checks it (issues 8, 13, 14).

A change that moves a figure fails here with a message naming the artefact and the number:
either a printed number or claim that is expected to hold, or a committed full-size golden CSV
under results/ that the fresh quick run no longer matches (netkf_cli/app/golden.py: Monte Carlo rows
within 5 combined standard errors, closed forms 1e-9·scale + 1e-7 relative, optimizer outputs at
the optimizer's tolerance as declared in experiments/<topic>/published.yaml).
"""

from netkf_cli.app.report import MAX_BYTES
from tests.reproduce._quick import quick_reproduction


def test_reproduce_quick_check_passes_on_the_repository(tmp_path_factory):
    run = quick_reproduction(tmp_path_factory)
    assert run.exit_code == 0, run.output
    assert (run.out / "REPORT.md").exists()


def test_report_is_small_and_links_the_notes(tmp_path_factory):
    run = quick_reproduction(tmp_path_factory)
    report = run.out / "REPORT.md"
    assert report.exists(), run.output
    text = report.read_text(encoding="utf-8")
    assert len(text.encode("utf-8")) < MAX_BYTES, f"REPORT.md is {len(text.encode())} bytes"
    assert "experiments/shi2009/README.md)" in text
    assert "## Buffer convention" not in text  # topic notes are linked, not pasted
    assert "| quantity | where | printed | ours | difference | verdict |" in text
    assert "| the paper's claim | where | holds? | evidence |" in text


def test_every_interval_in_every_fresh_table_has_positive_width(tmp_path_factory):
    """Issue 13.2: proportions carry a Wilson interval that is never of zero width (p̂ ∈ {0, 1}
    included) and contains the estimate."""
    import numpy as np
    import pandas as pd

    run = quick_reproduction(tmp_path_factory)
    checked = 0
    for csv in sorted(run.out.glob("*/*.csv")):
        df = pd.read_csv(csv)
        if not {"ci_low", "ci_high"} <= set(df.columns):
            continue
        lo, hi = df["ci_low"].to_numpy(float), df["ci_high"].to_numpy(float)
        rows = np.isfinite(lo) & np.isfinite(hi)
        bad = rows & ~(lo < hi)
        assert not bad.any(), f"{csv.name}: zero-width interval in rows {np.flatnonzero(bad)[:5].tolist()}"
        if "value" in df.columns:
            v = df["value"].to_numpy(float)
            outside = rows & np.isfinite(v) & ((v < lo - 1e-12) | (v > hi + 1e-12))
            assert not outside.any(), f"{csv.name}: estimate outside its interval in rows {np.flatnonzero(outside)[:5].tolist()}"
        checked += int(rows.sum())
    assert checked > 0, "no table carries ci_low/ci_high yet"
