"""What ``netkf list`` shows: every kind with its fields (name, type, default, meaning) and what composes."""

from __future__ import annotations

from types import UnionType
from typing import Annotated, Any, Literal, Union, get_args, get_origin

from pydantic.fields import PydanticUndefined

from netkf_cli.linalg.kalman import MEANING
from netkf_cli.config.scenario import kinds
from netkf_cli.core.spec import AnalysisModel, ChannelModel, EstimatorModel

GENERIC_METRICS = ("distribution", "mean_vs_time", "compare", "tail", "time_average", "state_error", "updates",
                   "burst_mean", "autocorrelation")


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


ANY_ESTIMATOR = "any channel with any estimator it is compatible with (see the estimators)"


def describe(compat: dict | None = None, metrics: dict | None = None) -> dict[str, dict[str, dict]]:
    """{family: {kind: {doc, fields, …compatibility}}} for channel, estimator and analysis.

    ``compat`` is :func:`netkf_cli.config.compat.compatibility` and ``metrics``
    :func:`netkf_cli.config.compat.metric_compatibility` (what `netkf validate` accepts, computed; passed in
    because compat sits beside this module): without them no pair is listed, and a generic metric without its
    own ``works_with`` is listed as working with any estimator."""
    compat = compat or {}
    metrics = metrics or {}
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

                entry["quantities"] = {q: MEANING[q] for q in getattr(cls, "quantities", ("filtered",))}
                entry["state_estimates"] = ("numpy path (state_error: x̂ beside P)" if callable(getattr(cls, "estimates", None))
                                            else "none")
            else:
                entry["generic"] = k in GENERIC_METRICS
                if k in GENERIC_METRICS:
                    entry["works_with"] = getattr(cls, "works_with", None) or ANY_ESTIMATOR
                    if k in metrics:
                        entry.update(_metric_entry(metrics[k]))
            fam[k] = entry
        out[family] = fam
    return out


def _metric_entry(row: dict) -> dict:
    """A generic metric's estimators (computed: :func:`netkf_cli.config.compat.metric_compatibility`) and the
    words `netkf list` prints for them."""
    ok = sorted(e for e, v in row.items() if v["status"] in ("yes", "conditional"))
    refused = {e: v["reason"] for e, v in sorted(row.items()) if v["status"] == "no"}
    unknown = sorted(e for e, v in row.items() if v["status"] == "unknown")
    conditions = {e: v["condition"] for e, v in sorted(row.items()) if v["status"] == "conditional"}
    if not refused and not conditions:
        words = ANY_ESTIMATOR
    else:
        words = (f"estimators {', '.join(e + ('*' if e in conditions else '') for e in ok) or '—'}, each on a channel "
                 f"it is compatible with" + (f"; refused: {', '.join(refused)}" if refused else ""))
    return {"works_with": words, "estimators": ok, "conditions": conditions, "refused": refused,
            "unchecked": {e: row[e]["reason"] for e in unknown}}
