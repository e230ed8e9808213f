"""Figure lint over every paper artefact at quick size (issue 13): what a referee would check first.

Reuses the session's quick reproduction (tests/reproduce/_quick.py), during which
``plotting.save`` recorded, per figure, the findings of ``plotting.lint``: a non-empty title
naming the paper, labels on both axes, every legend entry matched to a drawn series and every
series to a legend entry, no text outside the canvas, fonts ≥ 9 pt at the saved size.
"""

import json

import pytest
import yaml

from netkf_cli.runtime.plotting import PAPERS
from tests.conftest import ROOT
from tests.reproduce._quick import quick_reproduction

# artefacts whose topic has not been restyled yet (issue 13): see the final report of the presentation helper
AWAITING_RESTYLE: set[str] = set()


def _artefacts() -> list[tuple[str, str]]:
    out = []
    for cfg in sorted((ROOT / "configs").rglob("*.yaml")):
        rel = cfg.relative_to(ROOT / "configs")
        topic = rel.parts[0] if len(rel.parts) > 1 else "shi2009"
        name = (yaml.safe_load(cfg.read_text(encoding="utf-8")) or {}).get("name", cfg.stem)
        out.append((topic, name))
    return out


def _param(topic, name):
    marks = [pytest.mark.xfail(reason="awaiting topic restyle", strict=False)] if name in AWAITING_RESTYLE else []
    return pytest.param(topic, name, id=name, marks=marks)


@pytest.mark.parametrize("topic,name", [_param(t, n) for t, n in _artefacts()])
def test_figure_lint(topic, name, tmp_path_factory):
    run = quick_reproduction(tmp_path_factory)
    f = run.lint / f"{name}.json"
    assert f.exists(), f"no figure was saved for {name}: {run.output[-2000:]}"
    rec = json.loads(f.read_text(encoding="utf-8"))
    problems = list(rec["problems"])
    paper = PAPERS.get(topic)
    if paper and not any(paper in t for t in rec["titles"]):
        problems.append(f"no title names the paper ({paper!r}; use plotting.paper_title): titles {rec['titles']}")
    assert not problems, f"{name}:\n  " + "\n  ".join(problems)
