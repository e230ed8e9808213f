"""`netkf list` / `netkf schema` explain every field: no schema property without a description."""

from netkf_cli.config.scenario import json_schema


def test_every_schema_field_has_a_description():
    sch = json_schema()
    missing = [f"Scenario.{k}" for k, v in sch["properties"].items() if not v.get("description")]
    for name, d in sch.get("$defs", {}).items():
        missing += [f"{name}.{k}" for k, v in d.get("properties", {}).items() if k != "kind" and not v.get("description")]
    assert not missing, f"{len(missing)} fields without a description: {missing}"
