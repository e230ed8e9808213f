"""What ``netkf list`` shows: every kind with its fields (name, type, default, meaning) and what composes."""

from __future__ import annotations

from types import UnionType
from typing import Annotated, Any, Literal, Union, get_args, get_origin

from pydantic.fields import PydanticUndefined

GENERIC_METRICS = ("distribution", "mean_vs_time", "compare", "tail")


def _type_name(ann: Any) -> str:
    """A short readable type: ``list[float] | MGrid``, ``'log' | 'linear'``, ``int``."""
    origin, args = get_origin(ann), get_args(ann)
    if origin is Annotated:
        return _type_name(args[0])
    if origin is Literal:
        return " | ".join(repr(a) for a in args)
    if origin in (Union, UnionType):
        return " | ".join(_type_name(a) for a in args)
    if origin in (list, tuple, dict):
        return f"{origin.__name__}[{', '.join(_type_name(a) for a in args)}]"
    if ann is type(None):
        return "None"
    return getattr(ann, "__name__", str(ann))


def fields_of(cls) -> list[dict]:
    """Name, type, default and description of every field except ``kind``."""
    out = []
    for name, f in cls.model_fields.items():
        if name == "kind":
            continue
        default = "required" if f.default is PydanticUndefined and f.default_factory is None else (
            repr(f.default) if f.default_factory is None else repr(f.default_factory()))
        out.append({"name": f.alias or name, "type": _type_name(f.annotation), "default": default,
                    "description": f.description or ""})
    return out


# ---- compatibility, computed from what `netkf validate` accepts ----------------------------------

_ROOT = __import__("pathlib").Path(__file__).resolve().parents[1]
REPRESENTATIVE_SYSTEMS = {
    "scalar (n = m = 1)": {"A": 1.2, "C": 1, "Q": 1, "R": 1},
    "2 states, 1 output": {"A": [[1.05, 0.3], [0, 0.9]], "C": [[1, 0]], "Q": [[0.2, 0], [0, 0.3]], "R": 0.5},
    "2 states, 2 outputs": {"A": [[1.05, 0.3], [0, 0.9]], "C": [[1, 0], [0, 1]], "Q": [[0.2, 0], [0, 0.3]],
                            "R": [[0.5, 0], [0, 0.5]]},
    "stable scalar": {"A": 0.9, "C": 1, "Q": 1, "R": 1},
}
"""Systems every (channel, estimator) pair is checked on, besides the systems of the example scenarios."""
_STREAM_FIELDS = ("sensors", "streams")


def _examples() -> tuple[dict, list]:
    """One validated instance per channel kind and estimator kind, from the example scenarios
    (configs/, experiments/), else from the defaults alone; and the systems to check them on,
    as ``(label, system block, LinearSystem)``: the representative ones, then the examples'."""
    from pydantic import ValidationError

    from netkf_cli.errors import ConfigError
    from netkf_cli.loader import parse_yaml
    from netkf_cli.scenario import SystemSpec, kinds
    from netkf_cli.spec import ChannelModel, EstimatorModel

    fam = {"channel": kinds(ChannelModel), "estimator": kinds(EstimatorModel)}
    found: dict[str, dict] = {"channel": {}, "estimator": {}}
    systems: list = []
    files = sorted(_ROOT.glob("configs/**/*.yaml")) + sorted(_ROOT.glob("experiments/*/*.yaml"))
    for f in files:
        try:
            data = parse_yaml(f.read_text(encoding="utf-8"), str(f))
        except (OSError, ConfigError):
            continue
        if not isinstance(data, dict):
            continue
        blocks = [("channel", data.get("channel"))] + [("estimator", e) for e in
                                                       [data.get("estimator"), *(data.get("estimators") or [])]]
        for family, block in blocks:
            if not isinstance(block, dict) or block.get("kind") not in fam[family] or block["kind"] in found[family]:
                continue
            try:
                found[family][block["kind"]] = fam[family][block["kind"]].model_validate(
                    block, context={"base_dir": str(f.parent)})
            except (ValidationError, ConfigError, ValueError):
                continue
        if isinstance(data.get("system"), dict) and len(systems) < 40:
            try:
                systems.append((f"the system of {f.relative_to(_ROOT).as_posix()}", data["system"],
                                SystemSpec.model_validate(data["system"]).build()))
            except (ValidationError, ConfigError, ValueError):
                pass
    for family, known in fam.items():
        for k, cls in known.items():
            if k not in found[family]:
                for data in ({"kind": k}, _minimal(cls, k)):
                    try:
                        found[family][k] = cls.model_validate(data)
                        break
                    except (ValidationError, ConfigError, ValueError):
                        pass
    reps = []
    for label, spec in REPRESENTATIVE_SYSTEMS.items():
        reps.append((label, spec, SystemSpec.model_validate(spec).build()))
    return found, reps + systems


def _minimal(cls, kind: str) -> dict:
    """``{"kind": kind}`` with every required field that has a fixed set of values (a Literal) set to
    its first value: enough to instantiate a kind no example scenario uses."""
    data: dict[str, Any] = {"kind": kind}
    for name, f in cls.model_fields.items():
        if name == "kind" or not f.is_required():
            continue
        ann = f.annotation
        if get_origin(ann) is Annotated:
            ann = get_args(ann)[0]
        if get_origin(ann) is Literal:
            data[f.alias or name] = get_args(ann)[0]
    return data


def _streams(channel) -> int | None:
    import numpy as np

    try:
        tr = channel.sample_trace(np.random.default_rng(0), 1, 1)
        arr = getattr(tr, "arrival", None)
        return int(arr.shape[0]) if arr is not None else getattr(tr, "sensors", None)
    except Exception:  # noqa: BLE001 - a channel that cannot sample reports it when it runs
        return None


def _variants(channel, m: int) -> list:
    """The example channel, and the same channel with its stream count set to the system's outputs."""
    from pydantic import ValidationError

    out = [channel]
    for f in _STREAM_FIELDS:
        if f in type(channel).model_fields and getattr(channel, f) != m:
            data = channel.model_dump(by_alias=True)
            data[f] = m
            for k, v in list(data.items()):  # per-stream lists (e.g. per-sensor loss) become their first value
                if isinstance(v, list) and len(v) == getattr(channel, f):
                    data[k] = v[0]
            try:
                out.append(type(channel).model_validate(data))
            except (ValidationError, ValueError):
                pass
    return out


def _condition(trials: list[tuple]) -> str:
    """Words for the rule that separates accepted from refused trials (streams S, outputs m)."""
    ok = [t for t in trials if t[2]]
    rules = [
        ("one stream (a single link carrying all of y_k)", lambda S, m: S == 1),
        ("one stream per output row of C (streams = outputs)", lambda S, m: S == m),
        ("one stream, or one per output row of C", lambda S, m: S in (1, m)),
    ]
    for words, rule in rules:
        if all((t[0] is not None and rule(t[0], t[1])) == t[2] for t in trials):
            return words
    bad = next(t for t in trials if not t[2])
    return f"depends on the system (refused on {bad[4]}: {bad[3]})"


def compatibility() -> dict[str, dict[str, dict]]:
    """``{channel kind: {estimator kind: {"status": yes | conditional | no, "condition"/"reason"}}}``,
    computed by running the checks `netkf validate` runs — :func:`compat.check_pair` (for the
    generic metrics) and ``estimator.check(system, channel)`` — on every representative system
    and stream count. Nothing is hard-coded, so it stays true when an estimator changes."""
    return _compat_cached()


def _compat_cached(_cache: dict = {}) -> dict:  # noqa: B006 - a process-wide cache
    if "v" in _cache:
        return _cache["v"]
    from netkf_cli.compat import check_pair
    from netkf_cli.errors import ConfigError

    from netkf_cli.scenario import kinds
    from netkf_cli.spec import ChannelModel, EstimatorModel

    found, systems = _examples()
    table: dict[str, dict[str, dict]] = {}
    for ck in sorted(set(kinds(ChannelModel)) - set(found["channel"])):
        table[ck] = {ek: {"status": "unknown", "reason": f"no example of channel kind {ck} to check it on"}
                     for ek in kinds(EstimatorModel)}
    for ck, ch in sorted(found["channel"].items()):
        row = table.setdefault(ck, {})
        for ek in sorted(set(kinds(EstimatorModel)) - set(found["estimator"])):
            row[ek] = {"status": "unknown", "reason": f"no example of estimator kind {ek} to check it on"}
        for ek, es in sorted(found["estimator"].items()):
            try:
                check_pair(ch, es, "estimator.kind", strict=True)
            except ConfigError as exc:
                row[ek] = {"status": "no", "reason": "; ".join(p.message for p in exc.problems)}
                continue
            trials = []
            for label, _spec, system in systems:
                for variant in _variants(ch, system.m):
                    try:
                        es.check(system, variant)
                        trials.append((_streams(variant), system.m, True, "", label))
                    except ConfigError as exc:
                        trials.append((_streams(variant), system.m, False, "; ".join(p.message for p in exc.problems),
                                       label))
                    except Exception as exc:  # noqa: BLE001 - a check that crashes is not an acceptance
                        trials.append((_streams(variant), system.m, False, f"{type(exc).__name__}: {exc}", label))
            if all(t[2] for t in trials):
                row[ek] = {"status": "yes"}
            elif not any(t[2] for t in trials):
                msgs = {t[3] for t in trials}
                if trials and len(msgs) == 1:  # the same refusal on every system: the example's own fields
                    row[ek] = {"status": "conditional", "fields_only": True,
                               "condition": f"with the estimator's fields set for it ({msgs.pop()})"}
                else:
                    row[ek] = {"status": "no", "reason": trials[0][3] if trials else "no system to check it on"}
            else:
                row[ek] = {"status": "conditional", "condition": _condition(trials)}
    _cache["v"] = table
    return table


def describe() -> dict[str, dict[str, dict]]:
    """{family: {kind: {doc, fields, …compatibility}}} for channel, estimator and analysis."""
    from netkf_cli.scenario import kinds
    from netkf_cli.spec import AnalysisModel, ChannelModel, EstimatorModel

    compat = compatibility()
    out: dict[str, dict[str, dict]] = {}
    for family, base in (("channel", ChannelModel), ("estimator", EstimatorModel), ("analysis", AnalysisModel)):
        fam = {}
        for k, cls in sorted(kinds(base).items()):
            doc = (cls.__doc__ or "").strip().splitlines()[0].replace("``", "") if cls.__doc__ else ""
            entry: dict[str, Any] = {"doc": doc, "fields": fields_of(cls)}
            if family == "channel":
                entry["trace"] = sorted(getattr(cls, "trace_kinds", ()))
                row = compat.get(k, {})
                entry["estimators"] = sorted(e for e, v in row.items() if v["status"] != "no")
                entry["conditions"] = {e: v["condition"] for e, v in row.items() if v["status"] == "conditional"}
            elif family == "estimator":
                entry["accepts"] = sorted(getattr(cls, "accepts", ()))
                col = {c: row[k] for c, row in compat.items() if k in row}
                entry["channels"] = sorted(c for c, v in col.items() if v["status"] != "no")
                entry["conditions"] = {c: v["condition"] for c, v in col.items() if v["status"] == "conditional"}
                from netkf_cli.kalman import MEANING

                entry["quantities"] = {q: MEANING[q] for q in getattr(cls, "quantities", ("filtered",))}
            else:
                entry["generic"] = k in GENERIC_METRICS
                if k in GENERIC_METRICS:
                    entry["works_with"] = "any channel with any estimator it is compatible with (see the estimators)"
            fam[k] = entry
        out[family] = fam
    return out
