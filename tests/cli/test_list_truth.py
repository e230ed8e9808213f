"""Issue 23.5: what `netkf list` says combines is what `netkf validate` accepts — for every
(channel, estimator) pair, on every system it was computed on — and a pair that works only on
some systems is printed with its condition."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from netkf_cli.app.cli import app
from netkf_cli.core.errors import ConfigError
from netkf_cli.config.compat import REPRESENTATIVE_SYSTEMS, _examples, _variants, compatibility, metric_compatibility
from netkf_cli.config.scenario import kinds
from netkf_cli.core.spec import EstimatorModel
from netkf_cli.config.loader import validate_data
from netkf_cli.core.trace import LOST

runner = CliRunner()


@pytest.fixture(scope="module")
def setup():
    found, systems = _examples()
    return compatibility(), found, systems


_CSV = Path(tempfile.mkdtemp(prefix="netkf-list-truth-"))


def _channel_block(channel) -> dict:
    """The channel as a scenario block; a recording given as an array (a trace's stream variant) as a CSV file."""
    block = channel.model_dump(mode="json", by_alias=True)
    if channel.kind == "trace" and block["file"].startswith("<"):
        rec = channel.recording()
        rows = np.where(rec == LOST, -1, rec.astype(np.int64)).T if channel.values == "delay" else rec.astype(int).T
        f = _CSV / f"trace_{len(list(_CSV.iterdir()))}.csv"
        f.write_text("\n".join(",".join(str(int(v)) for v in r) for r in rows) + "\n", encoding="utf-8")
        block["file"] = str(f)
    return block


def _validate(system_block: dict, channel, estimator, analysis: dict | None = None) -> bool:
    """The whole `netkf validate` path (schema, system, compat, estimator check) on a scenario dict."""
    data = {"name": "pair", "system": system_block, "channel": _channel_block(channel),
            "estimator": estimator.model_dump(mode="json", by_alias=True),
            "analysis": analysis or {"kind": "mean_vs_time"}, "montecarlo": {"runs": 10, "horizon": 5}}
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


# ---- the fuzz of `netkf list` (issue: list promises) -------------------------------------------------------

SCALAR = {"A": 1.2, "C": 1, "Q": 1, "R": 1}


def test_an_estimator_kind_is_listed_as_its_defaults(setup):
    """The table is a claim about a kind: its defaults (what `{kind: K}` runs) where they validate, not an example
    scenario's fields (markov_lmi's S shaped for a 2-state system made `markov_lmi on markov_modes` 'refused on
    scalar (n = m = 1): must be 1×1, got (2, 1)'; fusion's example strategies without olpef hid its condition)."""
    table, found, _ = setup
    for k, cls in kinds(EstimatorModel).items():
        try:
            default = cls.model_validate({"kind": k})
        except Exception:  # noqa: BLE001 - required fields: the example is used
            continue
        assert found["estimator"][k] == default, k
    v = table["markov_modes"]["markov_lmi"]
    assert "(2, 1)" not in v.get("condition", "") and "scalar" not in v.get("condition", ""), v
    modes = found["channel"]["markov_modes"]
    assert _validate(SCALAR, modes, found["estimator"]["markov_lmi"])  # S omitted: a scalar markov_lmi validates


def test_fusion_and_single_link_estimators_state_their_conditions(setup):
    """fusion's default strategies include olpef (refused for an unstable A); buffered and smart_sensor read one
    packet stream, so a trace recording with 2 columns is refused: the table says both."""
    table, found, _ = setup
    for ck in ("bernoulli", "delay", "gilbert_elliott", "trace"):
        v = table[ck]["fusion"]
        assert v["status"] == "conditional" and "stable A" in v["condition"] and "olpef" in v["condition"], (ck, v)
    fusion = found["estimator"]["fusion"]
    assert not _validate(SCALAR, found["channel"]["bernoulli"], fusion)
    assert _validate({**SCALAR, "A": 0.9}, found["channel"]["bernoulli"], fusion)
    trace = found["channel"]["trace"]
    two = {"A": [[1.05, 0.3], [0, 0.9]], "C": [[1, 0], [0, 1]], "Q": [[0.2, 0], [0, 0.3]], "R": [[0.5, 0], [0, 0.5]]}
    for ek in ("buffered", "smart_sensor"):
        v = table["trace"][ek]
        assert v["status"] == "conditional" and v["condition"].startswith("one stream"), (ek, v)
        assert _validate(two, trace, found["estimator"][ek])
        assert not _validate(two, trace.with_streams(2), found["estimator"][ek])
    assert _validate(two, trace.with_streams(2), found["estimator"]["kf"])


def test_every_generic_metric_agrees_with_validate(setup):
    """What `netkf list` says a generic metric takes (computed: metric_compatibility) is what `netkf validate`
    accepts, with that metric, on the channels and systems each estimator validates on with mean_vs_time."""
    table, found, systems = setup
    metrics = metric_compatibility()
    assert "updates" in metrics and "mean_vs_time" in metrics
    reps = len(REPRESENTATIVE_SYSTEMS)
    checked = 0
    for k, row in metrics.items():
        analysis = found["analysis"][k].model_dump(mode="json", by_alias=True)
        for ek, v in row.items():
            if v["status"] == "unknown":
                continue
            es = found["estimator"][ek]
            for group in (systems[:reps], systems[reps:]):
                outcomes = [_validate(spec, variant, es, analysis) for ck, ch in found["channel"].items()
                            if table[ck][ek]["status"] not in ("no", "unknown") for _l, spec, system in group
                            for variant in _variants(ch, system.m) if _validate(spec, variant, es)]
                if outcomes:
                    break
            checked += len(outcomes)
            if v["status"] == "yes":
                assert all(outcomes), (k, ek, "listed as taking it, but validate refuses it somewhere")
            elif v["status"] == "no":
                assert not any(outcomes), (k, ek, "listed as refusing it, but validate accepts it")
            else:
                assert any(outcomes) and not all(outcomes) and v["condition"], (k, ek, v)
    assert checked > 100


def test_updates_lists_the_estimators_that_report_counts():
    """`updates` was listed as working with 'any channel with any estimator it is compatible with'; only buffered
    (measurement packets) has the updates() hook: kf, smoother, smart_sensor, fusion are refused at validate."""
    r = runner.invoke(app, ["list", "--json"])
    info = json.loads(r.output)["analysis"]["updates"]
    assert "any estimator" not in info["works_with"], info["works_with"]
    assert info["estimators"] == ["buffered"] and "buffered" in info["conditions"]
    assert {"kf", "smoother", "smart_sensor", "fusion"} <= set(info["refused"])
    r = runner.invoke(app, ["list", "updates"])
    out = " ".join(r.output.split())
    assert r.exit_code == 0 and "updates refuses kf: estimator.kind: kf does not report" in out, out
    assert "updates with buffered:" in out and "auto chose pair packets" in out, out
    r = runner.invoke(app, ["list"])
    line = next(ln for ln in r.output.splitlines()[r.output.splitlines().index(
        next(x for x in r.output.splitlines() if x.startswith("  updates "))) + 1:][:1])
    assert "estimators buffered*" in line and "refused: fusion, kf" in line, line
