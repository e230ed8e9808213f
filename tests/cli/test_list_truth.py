"""Issue 23.5: what `netkf list` says combines is what `netkf validate` accepts — for every
(channel, estimator) pair, on every system it was computed on — and a pair that works only on
some systems is printed with its condition."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from netkf_cli.app.cli import app
from netkf_cli.core.errors import ConfigError
from netkf_cli.config.compat import _examples, _variants, compatibility
from netkf_cli.config.loader import validate_data

runner = CliRunner()


@pytest.fixture(scope="module")
def setup():
    found, systems = _examples()
    return compatibility(), found, systems


def _validate(system_block: dict, channel, estimator) -> bool:
    """The whole `netkf validate` path (schema, system, compat, estimator check) on a scenario dict."""
    data = {"name": "pair", "system": system_block, "channel": channel.model_dump(mode="json", by_alias=True),
            "estimator": estimator.model_dump(mode="json", by_alias=True),
            "analysis": {"kind": "mean_vs_time"}, "montecarlo": {"runs": 10, "horizon": 5}}
    try:
        validate_data(data)
        return True
    except ConfigError:
        return False


def test_every_pair_agrees_with_validate(setup):
    table, found, systems = setup
    assert table and all(table.values())
    checked = 0
    for ck, row in table.items():
        for ek, v in row.items():
            ch, es = found["channel"][ck], found["estimator"][ek]
            outcomes = [_validate(spec, variant, es) for _label, spec, system in systems
                        for variant in _variants(ch, system.m)]
            checked += len(outcomes)
            if v["status"] == "yes":
                assert all(outcomes), (ck, ek, "listed as combining, but validate refuses it on some system")
            elif v["status"] == "no":
                assert not any(outcomes), (ck, ek, "listed as not combining, but validate accepts it")
            elif v.get("fields_only"):  # the example estimator's own fields are refused on every system
                assert not any(outcomes), (ck, ek, v)
                assert "estimator's fields" in v["condition"]
            else:
                assert v["status"] == "conditional" and any(outcomes) and not all(outcomes), (ck, ek, v)
                assert v["condition"]
    assert checked > 100


def test_a_many_sensor_channel_is_not_listed_as_combining_unconditionally(setup):
    table, found, systems = setup
    ch = found["channel"]["multi"]
    assert ch.sensors > 1  # the fusion example: 25 sensors
    for ek, v in table["multi"].items():
        es = found["estimator"][ek]
        scalar = systems[0][1]
        if not _validate(scalar, ch, es):  # refused by validate for the 25-sensor channel on a scalar plant
            assert v["status"] != "yes", ek


def test_list_prints_the_conditions(setup):
    table, _, _ = setup
    r = runner.invoke(app, ["list", "multi"])
    assert r.exit_code == 0, r.output
    for ek, v in table["multi"].items():
        if v["status"] == "conditional":
            assert f"{ek} on multi: {v['condition']}" in r.output
    r = runner.invoke(app, ["list", "--json"])
    info = json.loads(r.output)
    for ck, row in table.items():
        listed = set(info["channel"][ck]["estimators"])
        assert listed == {e for e, v in row.items() if v["status"] != "no"}
        for ek in listed:
            assert ck in info["estimator"][ek]["channels"]
    r = runner.invoke(app, ["list"])
    assert r.exit_code == 0 and "validate" in r.output
