"""`output.formats` (issue 13.4): the runner writes each requested format of the same figure."""

import json
import textwrap

import pytest

from netkf_cli.core.errors import ConfigError
from netkf_cli.config.loader import load_scenario
from netkf_cli.app.runner import run_scenario_file

SCENARIO = textwrap.dedent(
    """\
    name: fmt
    system: {{A: 1.4, C: 1, Q: 0.2, R: 0.5}}
    channel: {{kind: delay, delay: {{kind: poisson, mean: 5}}, buffer: 10}}
    analysis: {{kind: theta_vs_buffer, M: [50], D_max: 4}}
    output: {{formats: {formats}}}
    """
)


def _run(tmp_path, formats):
    cfg = tmp_path / "fmt.yaml"
    cfg.write_text(SCENARIO.format(formats=formats))
    return run_scenario_file(cfg, out_dir=tmp_path / "out", force=True)


def test_pdf_only_writes_a_pdf_and_lists_it(tmp_path):
    out = _run(tmp_path, "[pdf]")
    assert (out / "fmt.pdf").read_bytes()[:5] == b"%PDF-"
    assert not (out / "fmt.png").exists()
    files = json.loads((out / "manifest.json").read_text())["files"]
    assert "fmt.pdf" in files and "fmt.png" not in files


def test_three_formats(tmp_path):
    out = _run(tmp_path, "[png, pdf, svg]")
    assert (out / "fmt.png").read_bytes()[:4] == b"\x89PNG"
    assert (out / "fmt.pdf").read_bytes()[:5] == b"%PDF-"
    assert b"<svg" in (out / "fmt.svg").read_bytes()[:2000]
    files = json.loads((out / "manifest.json").read_text())["files"]
    assert {"fmt.png", "fmt.pdf", "fmt.svg"} <= set(files)


def test_default_is_png(tmp_path):
    cfg = tmp_path / "d.yaml"
    cfg.write_text(SCENARIO.format(formats="[png]").replace("    output: {formats: [png]}\n", "").replace("output: {formats: [png]}\n", ""))
    assert load_scenario(cfg).output.formats == ["png"]


@pytest.mark.parametrize("bad", ["[bmp]", "[]"])
def test_unknown_or_empty_format_is_a_config_error(tmp_path, bad):
    cfg = tmp_path / "b.yaml"
    cfg.write_text(SCENARIO.format(formats=bad))
    with pytest.raises(ConfigError) as e:
        load_scenario(cfg)
    assert "output.formats" in str(e.value)
