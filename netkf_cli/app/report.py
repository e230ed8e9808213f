"""``REPORT.md``: per paper, per artefact — the figure, what the paper *printed* (printed | ours |
difference | verdict) and what it *claimed* (claim | holds? | evidence). Topic notes are linked,
not pasted; the report stays small (about 1 KB per artefact: < 40 KB for the 36 of round 4) so that it can
be read at a glance."""

from __future__ import annotations

import os
import re
from datetime import datetime, timezone
from pathlib import Path

from netkf_cli.runtime import io
from netkf_cli.runtime.plotting import PAPERS

MAX_BYTES = 40_000  # 30 KB held 33 artefacts with ~100 claims; round 4 has 36 and ~140
_REASON_CHARS = 240


def _fmt(x) -> str:
    if x is None:
        return "—"
    try:
        x = float(x)
    except (TypeError, ValueError):
        return str(x)
    if x == 0:
        return "0"
    if x != x:
        return "nan"
    a = abs(x)
    if a == float("inf"):
        return "∞" if x > 0 else "−∞"
    return f"{x:.4g}" if 1e-3 <= a < 1e5 else f"{x:.3e}"


def _short(text: str, limit: int | None = None) -> str:
    """One line, optionally shortened with an ellipsis (no escaping)."""
    t = " ".join(str(text).split())
    if limit is not None and len(t) > limit:
        t = t[: max(limit - 1, 0)].rstrip() + "…" if limit > 0 else ""
    return t


def _cell(text: str, limit: int | None = None) -> str:
    """Markdown-table-safe text, optionally shortened."""
    return _short(text, limit).replace("|", "\\|")


def _title(readme: Path, topic: str) -> str:
    text = readme.read_text(encoding="utf-8") if readme.exists() else ""
    m = re.search(r"^# (.+)$", text, flags=re.M)
    return m.group(1).strip() if m else topic


def _ours(c) -> str:
    if c.ours is None:
        return "—"
    if c.interval is not None:  # an argmin of a flat objective: the near-optimal interval, not "x ± se"
        lo, hi = c.interval
        return f"[{_fmt(lo)}, {_fmt(hi)}] (argmin {_fmt(c.ours)})"
    return _fmt(c.ours) + (f" ± {_fmt(c.stderr)}" if c.stderr else "")


def _diff(c) -> str:
    if c.ours is None:
        return "—"
    if c.interval is not None:
        lo, hi = c.interval
        p = c.check.printed
        return "inside" if lo <= p <= hi else f"{_fmt(p - (lo if p < lo else hi))} outside"
    return f"{c.diff:+.3g}" if c.diff else "0"


def _printed_table(checks) -> list[str]:
    out = ["| quantity | where | printed | ours | difference | verdict |", "|---|---|---|---|---|---|"]
    for c in checks:
        p = c.check
        printed = _cell(p.printed_text) if p.printed_text else _fmt(p.printed)
        tol = f" (±{c.tol:.2g})" if c.ours is not None else ""
        verdict = c.verdict() + tol
        if (p.expect == "differs" or (not c.ok and p.reason)) and _REASON_CHARS > 0:
            verdict += ": " + _cell(p.reason, _REASON_CHARS)
        out.append(f"| {_cell(p.quantity)} | {_cell(p.where)} | {printed} | {_ours(c)} | {_diff(c)} | {verdict} |")
    return out


def _claims_table(claims) -> list[str]:
    out = ["| the paper's claim | where | holds? | evidence |", "|---|---|---|---|"]
    for c in claims:
        cl = c.claim
        if c.ours is None:
            ev = c.note
        else:
            ev = f"{_short(cl.check, min(160, _REASON_CHARS))}: {_fmt(c.ours)}" + (f" ± {_fmt(c.stderr)}" if c.stderr else "")
            if c.n_rows > 1:
                ev += f" (worst of {c.n_rows} rows)"
            if c.evidence:
                shown = dict(c.evidence)
                for k in list(shown):  # "x = 1.2 ± 0.1" for a value and its standard error
                    if f"{k}_stderr" in shown:
                        se = shown.pop(f"{k}_stderr")
                        shown[k] = f"{_fmt(shown[k])} ± {_fmt(se)}" if se and se == se else _fmt(shown[k])
                ev += "; " + ", ".join(f"{k} = {v if isinstance(v, str) and '±' in v else _fmt(v)}" for k, v in shown.items())
            if not c.ok:
                ev += f" (holds if {cl.holds_if.text(cl.column)})"
        if cl.reason and (cl.expect == "fails" or not c.ok) and _REASON_CHARS > 0:
            ev += ". " + _short(cl.reason, _REASON_CHARS)
        out.append(f"| {_cell(cl.claim)} | {_cell(cl.where)} | {c.verdict()} | {_cell(ev, _REASON_CHARS + 240)} |")
    return out


def write_report(outcomes, published, path: Path, *, root: Path, quick: bool) -> Path:
    """Write REPORT.md atomically; long evidence texts are shortened until it fits MAX_BYTES."""
    global _REASON_CHARS
    path = Path(path)
    saved = _REASON_CHARS
    try:
        for limit in (240, 160, 110, 70, 0):  # 0: evidence without the explanations (see the notes)
            _REASON_CHARS = limit
            text = _render(outcomes, published, path, root=root, quick=quick)
            if len(text.encode("utf-8")) <= MAX_BYTES:
                break
    finally:
        _REASON_CHARS = saved
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".md.tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(path)
    return path


def _render(outcomes, published, path: Path, *, root: Path, quick: bool) -> str:
    commit = io.git_commit(root) or "n/a"
    lines = [
        "# netkf reproduction report",
        "",
        f"Generated by `netkf reproduce{' --quick' if quick else ''}` on "
        f"{datetime.now(timezone.utc).strftime('%Y-%m-%d %H:%M UTC')} (netkf {io.versions()['netkf']}, commit "
        f"`{commit}`{' — **uncommitted changes**' if commit.endswith('+dirty') else ''}). Per artefact: the command "
        "that regenerates it, its figure, the numbers **printed** in the paper next to ours "
        "(✓ = within the stated tolerance"
        + (", widened to 5 standard errors for Monte Carlo rows under `--quick`" if quick else "")
        + "; argmins of flat objectives are shown as the interval of near-optimal values), and the paper's "
        "**claims** with the number of ours that decides each. *Differs* / *does not hold, as expected* "
        "mark known disagreements, explained in the topic's notes (linked).",
        "",
    ]

    by_topic: dict[str, list] = {}
    for o in outcomes:
        by_topic.setdefault(o.artefact.topic, []).append(o)
    order = [t for t in PAPERS if t in by_topic] + sorted(t for t in by_topic if t not in PAPERS)
    topics = {t: by_topic[t] for t in order}  # the headline paper first, then the others
    lines.append("| paper | artefacts | printed ✓ | printed ✗ | known differences | claims hold | claims ✗ | claims known not to hold |")
    lines.append("|---|---|---|---|---|---|---|---|")
    for topic, outs in topics.items():
        title = _title(root / "experiments" / topic / "README.md", topic)
        ok = sum(1 for o in outs for c in o.checks if c.ok and c.check.expect == "reproduce")
        bad = sum(1 for o in outs for c in o.checks if c.failed)
        differs = sum(1 for o in outs for c in o.checks if c.check.expect == "differs")
        c_ok = sum(1 for o in outs for c in o.claims if c.holds and c.claim.expect == "holds")
        c_bad = sum(1 for o in outs for c in o.claims if c.failed)
        c_known = sum(1 for o in outs for c in o.claims if c.claim.expect == "fails")
        lines.append(f"| [{_cell(title)}](#{topic}) | {len(outs)} | {ok} | {bad} | {differs} | {c_ok} | {c_bad} | {c_known} |")
    lines.append("")
    for topic, outs in topics.items():
        readme = root / "experiments" / topic / "README.md"
        title = _title(readme, topic)
        lines += [f'<a id="{topic}"></a>', f"## {title}", ""]
        pub = published.get(topic)
        if pub is not None and pub.citation:
            lines += [pub.citation, ""]
        notes = os.path.relpath(readme, path.parent).replace(os.sep, "/")
        lines += [f"Regenerate: `netkf reproduce {topic}` · notes on conventions, misprints and differences: "
                  f"[{os.path.relpath(readme, root).replace(os.sep, '/')}]({notes})", ""]
        for o in outs:
            a = o.artefact
            rel_cfg = os.path.relpath(a.config, root).replace(os.sep, "/")
            if o.error and o.error.startswith("not run yet"):
                took = "not run yet"
            elif o.previous is not None:
                took = f"not run by this command (its result of {o.previous}: compute {o.wall_time:.1f} s)"
            else:
                took = f"{o.wall_time:.1f} s"
            lines += [f"### {a.name}", "", f"`netkf run {rel_cfg}` — {took}", ""]
            if o.error and o.error.startswith("not run yet"):
                lines += [f"*Not run yet: `netkf reproduce {a.topic}`.*", ""]
                continue
            if o.error:
                lines += [f"**Run failed:** {_cell(o.error, 400)}", ""]
                continue
            png = o.folder / f"{a.name}.png" if o.folder else None
            if png and png.exists():
                lines += [f"![{a.name}]({os.path.relpath(png, path.parent).replace(os.sep, '/')})", ""]
            if o.checks:
                lines += _printed_table(o.checks) + [""]
            if o.claims:
                lines += _claims_table(o.claims) + [""]
            if not o.checks and not o.claims:
                lines += ["*The paper prints no number and makes no checkable claim about this artefact "
                          "(figure only; see the notes).*", ""]
            for g in o.golden[:3]:
                lines.append(f"- golden mismatch: {_cell(g, 200)}")
            if len(o.golden) > 3:
                lines.append(f"- … and {len(o.golden) - 3} more (`netkf reproduce {a.topic} --quick --check`)")
            if o.golden:
                lines.append("")
    return "\n".join(lines) + "\n"
