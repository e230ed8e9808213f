"""config.loader's two YAML loaders (libyaml's parser and the pure-Python one) read every file the same way."""

from pathlib import Path

import pytest

from netkf_cli.config import loader as L
from netkf_cli.core.errors import ConfigError

ROOT = Path(__file__).resolve().parents[2]
FILES = sorted(ROOT.glob("configs/**/*.yaml")) + sorted(ROOT.glob("experiments/*/published.yaml"))
needs_libyaml = pytest.mark.skipif(L._CLineLoader is None, reason="PyYAML without libyaml")


def _both(text):
    fast = L._compose_and_construct(L._CLineLoader(text), None)
    pure = L._compose_and_construct(L._LineLoader(text), None)
    return fast, pure


@needs_libyaml
def test_every_shipped_file_gives_the_same_data_and_line_index():
    assert len(FILES) > 30
    for f in FILES:
        fast, pure = _both(f.read_text(encoding="utf-8"))
        assert fast == pure, f


@needs_libyaml
def test_yaml_12_scalars_and_refusals_are_the_same():
    text = "a: yes\nb: 1e-3\nc: 0x1F\nd: 0o17\ne: on\nf: true\ng: ~\nh: 1_000\ni: '1e3'\nj: [1, 2.5, -.5]\n"
    fast, pure = _both(text)
    assert fast == pure
    assert fast[0] == {"a": "yes", "b": 1e-3, "c": 31, "d": 15, "e": "on", "f": True, "g": None, "h": "1_000",
                       "i": "1e3", "j": [1, 2.5, -0.5]}
    for bad in ("a: 1\na: 2\n", "a: [1, 2\n", "1: x\n", "a: !!python/object x\n"):
        with pytest.raises(ConfigError) as fast_err:
            L._compose_and_construct(L._CLineLoader(bad), None)
        with pytest.raises(ConfigError) as parsed:
            L.parse_yaml(bad, "s.yaml")  # the message a user reads comes from the pure-Python loader
        with pytest.raises(ConfigError) as pure_err:
            L._compose_and_construct(L._LineLoader(bad), "s.yaml")
        assert str(parsed.value) == str(pure_err.value)
        assert fast_err.value.problems[0].line == pure_err.value.problems[0].line


def test_a_text_that_could_nest_deeply_goes_to_the_pure_python_loader_and_deep_nesting_is_refused():
    wide = "".join(f"k{i}: {i}\n" for i in range(L.C_PARSE_MAX_NESTERS + 1))  # one ':' per line: could nest
    assert isinstance(L._loader(wide), L._LineLoader)
    assert L.parse_yaml(wide) == {f"k{i}": i for i in range(L.C_PARSE_MAX_NESTERS + 1)}
    deep = "a: " + "[" * (L.MAX_DEPTH + 50) + "]" * (L.MAX_DEPTH + 50) + "\n"  # libyaml's to parse, ours to refuse
    assert L._CLineLoader is None or isinstance(L._loader(deep), L._CLineLoader)
    with pytest.raises(ConfigError, match="nested more than"):
        L.parse_yaml(deep, "deep.yaml")
    assert L.line_index(deep) == {}


def test_safe_load_is_pyyamls_safe_load_on_every_published_and_example_file():
    """compat.safe_load (libyaml) reads what yaml.safe_load reads: published.yaml (the reproduction's discovery)
    and every example scenario `netkf list` reads for its compatibility table."""
    import yaml

    from netkf_cli.config.compat import safe_load

    files = sorted(ROOT.glob("experiments/*/published.yaml"))
    assert len(files) >= 6
    examples = sorted(ROOT.glob("configs/**/*.yaml")) + sorted(ROOT.glob("experiments/*/*.yaml"))
    assert len(examples) >= 40
    for f in files + examples:
        text = f.read_text(encoding="utf-8")
        assert safe_load(text) == yaml.safe_load(text), f
