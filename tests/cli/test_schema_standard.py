"""`netkf schema` is standard JSON Schema: integer bounds render as exclusiveMinimum / minimum /
maximum, never as pydantic's own ``gt``/``ge``/``lt``/``le`` (which editors ignore, so that
``runs: 0`` went unflagged: a constraint placed after a BeforeValidator in ``Annotated``)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from netkf_cli.app.cli import app

ROOT = Path(__file__).resolve().parents[2]

#: pydantic constraint names that are not JSON Schema keywords (JSON Schema spells them
#: exclusiveMinimum, minimum, exclusiveMaximum, maximum, multipleOf, minLength/minItems ...).
PYDANTIC_ONLY = {"gt", "ge", "lt", "le", "multiple_of", "min_length", "max_length", "allow_inf_nan",
                 "max_digits", "decimal_places"}

# Where a schema keyword's value holds subschemas (everything else is data: default, enum, const ...).
_MAPS = {"properties", "$defs", "definitions", "patternProperties", "dependentSchemas"}
_ONE = {"items", "additionalProperties", "not", "if", "then", "else", "contains", "propertyNames",
        "additionalItems", "unevaluatedItems", "unevaluatedProperties"}
_LISTS = {"anyOf", "oneOf", "allOf", "prefixItems"}


def _schema():
    r = CliRunner().invoke(app, ["schema"])
    assert r.exit_code == 0, r.output
    return json.loads(r.output)


def _keywords(schema, where="#"):
    """Yield (location, keyword, value) for every keyword of every (sub)schema, property names excluded."""
    if not isinstance(schema, dict):
        return
    for key, value in schema.items():
        yield where, key, value
        if key in _MAPS and isinstance(value, dict):
            for name, sub in value.items():
                yield from _keywords(sub, f"{where}/{key}/{name}")
        elif key in _ONE:
            yield from _keywords(value, f"{where}/{key}")
        elif key in _LISTS and isinstance(value, list):
            for i, sub in enumerate(value):
                yield from _keywords(sub, f"{where}/{key}/{i}")


def _resolve(root, sub):
    while "$ref" in sub:
        ref = sub["$ref"]
        assert ref.startswith("#/"), ref
        node = root
        for part in ref[2:].split("/"):
            node = node[part]
        sub = node
    return sub


def _property(root, dotted):
    node = root
    for name in dotted.split("."):
        node = _resolve(root, _resolve(root, node)["properties"][name])
    return node


def test_schema_has_no_pydantic_only_keywords():
    sch = _schema()
    bad = [f"{where}: {key}={value!r}" for where, key, value in _keywords(sch) if key in PYDANTIC_ONLY]
    assert not bad, f"{len(bad)} non-standard keywords in `netkf schema`: {bad}"


@pytest.mark.parametrize("dotted,lower,upper", [
    ("montecarlo.runs", 1, None),
    ("montecarlo.horizon", 1, None),
    ("montecarlo.chunk", 1, None),
    ("montecarlo.seed", 0, None),
    ("montecarlo.burn_in", 0, None),
    ("output.dpi", 1, 1200),
])
def test_integer_bounds_are_standard(dotted, lower, upper):
    p = _property(_schema(), dotted)
    assert p["type"] == "integer"
    lo = p["minimum"] if "minimum" in p else p["exclusiveMinimum"] + 1
    assert lo == lower, p
    assert p.get("maximum") == upper, p


def test_shipped_configs_validate_against_the_schema():
    """Every shipped config is valid under `netkf schema` (a matrix written as a number or one row too)."""
    jsonschema = pytest.importorskip("jsonschema")
    from netkf_cli.config.loader import parse_yaml

    validator = jsonschema.Draft202012Validator(_schema())
    configs = sorted((ROOT / "configs").rglob("*.yaml"))
    assert configs
    bad = {}
    for path in configs:
        errors = [f"{'.'.join(map(str, e.absolute_path))}: {e.message[:160]}"
                  for e in validator.iter_errors(parse_yaml(path.read_text(), str(path)))]
        if errors:
            bad[path.relative_to(ROOT).as_posix()] = errors
    assert not bad, bad


def test_schema_rejects_out_of_range_integers():
    jsonschema = pytest.importorskip("jsonschema")
    from netkf_cli.config.loader import parse_yaml

    validator = jsonschema.Draft202012Validator(_schema())
    doc = parse_yaml((ROOT / "configs" / "fig5.yaml").read_text())
    validator.validate(doc)
    for field, value in (("runs", 0), ("horizon", 0), ("seed", -1), ("burn_in", -1)):
        bad = {**doc, "montecarlo": {**doc["montecarlo"], field: value}}
        with pytest.raises(jsonschema.ValidationError):
            validator.validate(bad)
    with pytest.raises(jsonschema.ValidationError):
        validator.validate({**doc, "output": {"dpi": 1201}})
    validator.validate({**doc, "output": {"dpi": 1200}})
