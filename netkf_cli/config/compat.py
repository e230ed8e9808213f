"""Cross-block checks of a scenario: what makes sense together (channel × estimator × analysis),
and :func:`compatibility`, the table `netkf list` prints, computed from these same checks.

Run by the loader after the schema validation, so ``netkf validate`` rejects everything
``netkf run`` would: an estimator that cannot read the channel's traces (the message names
the compatible channel kinds), a system the estimator cannot work with, an analysis that
needs another channel or estimator, ``burn_in ≥ horizon``.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Annotated, Any, Literal, get_args, get_origin

import numpy as np
import yaml
from pydantic import ValidationError

from netkf_cli.core.errors import ConfigError, Problem
from netkf_cli.config.kinds import GENERIC_METRICS
from netkf_cli.config.scenario import MonteCarloSpec, OutputSpec, SystemSpec, kinds, scenario_model
from netkf_cli.core.spec import AnalysisModel, ChannelModel, EstimatorModel
from netkf_cli.linalg import riccati


def compatible_channels(estimator_cls) -> list[str]:
    """Channel kinds whose traces this estimator class accepts."""
    acc = getattr(estimator_cls, "accepts", frozenset())
    return sorted(k for k, c in kinds(ChannelModel).items() if getattr(c, "trace_kinds", frozenset()) & acc)


def compatible_estimators(channel_cls) -> list[str]:
    """Estimator kinds that accept this channel class's traces."""
    tk = getattr(channel_cls, "trace_kinds", frozenset())
    return sorted(k for k, c in kinds(EstimatorModel).items() if getattr(c, "accepts", frozenset()) & tk)


def check_pair(channel, estimator, path: str = "estimator.kind", strict: bool = True) -> None:
    """Refuse an estimator that cannot read this channel's traces.

    ``strict`` (the generic metrics and the engine): both must declare what they produce and
    read. Paper recipes that drive their own kernels pass ``strict=False``: only a declared
    mismatch is refused there.
    """
    acc = getattr(estimator, "accepts", frozenset())
    tk = getattr(channel, "trace_kinds", frozenset())
    if strict and not tk:
        raise ConfigError.at(path.replace("estimator", "channel", 1) if path.startswith("estimator") else "channel.kind",
                             f"channel {channel.kind!r} does not sample traces for the generic metrics")
    if strict and not acc:
        raise ConfigError.at(path, f"estimator {estimator.kind!r} reports no per-run error covariance, so the generic "
                                   f"metrics cannot use it (only its paper analysis)")
    if acc and tk and not (acc & tk):
        raise ConfigError.at(
            path,
            f"estimator {estimator.kind!r} needs a channel providing {'/'.join(sorted(acc))}, but channel "
            f"{channel.kind!r} provides {'/'.join(sorted(tk))}; compatible channels: "
            f"{', '.join(compatible_channels(type(estimator))) or 'none'}")


def check_scenario(scenario) -> None:
    """Raise one ConfigError with every cross-block problem of a validated scenario."""
    problems: list[Problem] = []

    def collect(fn, *args):
        try:
            fn(*args)
        except ConfigError as exc:
            problems.extend(exc.problems)

    mc = scenario.montecarlo
    if mc.burn_in >= mc.horizon:
        problems.append(Problem("montecarlo.burn_in", f"must be < horizon = {mc.horizon} (time averages are over k in "
                                                      f"(burn_in, horizon]), got {mc.burn_in}"))
    ch, ests = scenario.channel, scenario.estimator_list()
    if callable(getattr(ch, "check_montecarlo", None)):  # a channel's own limits on runs × horizon (a recording's rows)
        collect(ch.check_montecarlo, mc)
    many = bool(scenario.estimators)
    if many and scenario.estimator is not None:
        problems.append(Problem("estimators", "give either `estimator:` (one) or `estimators:` (a list), not both"))
    system = None
    if scenario.system is None and ests:
        collect(scenario.linear_system)  # every estimator runs on (A, C, Q, R): the words `netkf run` refuses with
    if scenario.system is not None:
        try:
            system = scenario.system.build()
        except ConfigError:
            system = None  # reported by the loader already
    for i, es in enumerate(ests):
        if ch is None:
            break
        path = f"estimators[{i}]" if many else "estimator"
        before = len(problems)
        collect(check_pair, ch, es, f"{path}.kind", _generic(scenario.analysis))
        if len(problems) == before and system is not None:
            try:
                es.check(system, ch)
            except ConfigError as exc:
                problems.extend(replace(p, path=p.path.replace("estimator", path, 1)) if many else p
                                for p in exc.problems)
    check = getattr(scenario.analysis, "check", None)
    if callable(check):
        collect(check, scenario)
    if ests and system is not None and system.P0 is None and not any(p.path == "system" for p in problems):
        collect(riccati.initial_covariance, system)  # every estimator starts from P_{0|0}: unset P0 is P̄ (core/spec)
    if problems:
        raise ConfigError(problems)


def _generic(analysis) -> bool:
    return getattr(analysis, "kind", None) in GENERIC_METRICS


# ---- compatibility, computed from what `netkf validate` accepts ----------------------------------

_ROOT = __import__("pathlib").Path(__file__).resolve().parents[2]
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
    """One validated instance per channel kind and estimator kind, and the systems to check them on,
    as ``(label, system block, LinearSystem)``: the representative ones, then the examples'.

    An estimator is its kind's defaults (``{kind: K}``, what a scenario that names only the kind runs)
    wherever they validate: the table is a claim about the kind, so an example's own fields (a
    cross-covariance S shaped for its 2-state system, a strategy list without the default olpef) must
    not add or hide a condition. A kind with required fields, and every channel kind (a rate, a file),
    is taken from the example scenarios (configs/, experiments/), else from its minimal fields."""
    fam = {"channel": kinds(ChannelModel), "estimator": kinds(EstimatorModel), "analysis": kinds(AnalysisModel)}
    found: dict[str, dict] = {"channel": {}, "estimator": {}, "analysis": {}}
    for k, cls in fam["estimator"].items():
        try:
            found["estimator"][k] = cls.model_validate({"kind": k})
        except (ValidationError, ConfigError, ValueError):
            pass
    for k, cls in fam["analysis"].items():
        try:
            found["analysis"][k] = cls.model_validate({"kind": k})
        except (ValidationError, ConfigError, ValueError):
            pass
    systems: list = []
    files = sorted(_ROOT.glob("configs/**/*.yaml")) + sorted(_ROOT.glob("experiments/*/*.yaml"))
    for f in files:
        try:  # (the loader sits above this module: plain YAML, then YAML 1.2 numbers such as 1e-3)
            data = _yaml12_numbers(safe_load(f.read_text(encoding="utf-8")))
        except (OSError, yaml.YAMLError):
            continue
        if not isinstance(data, dict):
            continue
        blocks = [("channel", data.get("channel")), ("analysis", data.get("analysis"))] + \
            [("estimator", e) for e in [data.get("estimator"), *(data.get("estimators") or [])]]
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


_FLOAT12 = __import__("re").compile(r"^[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?$")


def safe_load(text: str):
    """``yaml.safe_load(text)`` (PyYAML's safe schema, for the files that are not scenarios: published.yaml, and
    the example scenarios `netkf list` reads here) on libyaml's parser when PyYAML has it — the same data, ~4x
    faster (the six published.yaml files were a third of the reproduction's discovery; the 47 examples a
    third of `netkf list`)."""
    return yaml.load(text, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))


def _yaml12_numbers(x):
    """Text that YAML 1.2 reads as a number (``1e-3``; YAML 1.1 leaves it text) as that number."""
    if isinstance(x, dict):
        return {k: _yaml12_numbers(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_yaml12_numbers(v) for v in x]
    if isinstance(x, str) and _FLOAT12.match(x):
        return float(x)
    return x


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
    try:
        tr = channel.sample_trace(np.random.default_rng(0), 1, 1)
        arr = getattr(tr, "arrival", None)
        return int(arr.shape[0]) if arr is not None else getattr(tr, "sensors", None)
    except Exception:  # noqa: BLE001 - a channel that cannot sample reports it when it runs
        return None


def _variants(channel, m: int) -> list:
    """The example channel, and the same channel with its stream count set to the system's outputs."""
    out = [channel]
    hook = getattr(channel, "with_streams", None)
    if callable(hook):  # a channel whose stream count is not a field (a trace: its recording's columns)
        try:
            v = hook(m)
            if v is not None and _streams(v) != _streams(channel):
                out.append(v)
        except (ValidationError, ConfigError, ValueError):
            pass
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


def _stable(system) -> bool:
    return bool(np.max(np.abs(np.linalg.eigvals(system.A))) < 1)


def _condition(trials: list[tuple]) -> str:
    """Words for the rule that separates accepted from refused trials (streams S, outputs m, the system)."""
    streams = [
        ("one stream (a single link carrying all of y_k)", lambda S, m: S == 1),
        ("one stream per output row of C (streams = outputs)", lambda S, m: S == m),
        ("one stream, or one per output row of C", lambda S, m: S in (1, m)),
    ]
    bad = next(t for t in trials if not t[2])
    for words, rule in streams:
        if all((t[0] is not None and rule(t[0], t[1])) == t[2] for t in trials):
            return words
    stable = "a stable A (spectral radius < 1)"
    for words, rule in [(stable, lambda S, m: True)] + [(f"{w}, and {stable}", r) for w, r in streams]:
        if all((t[0] is not None and rule(t[0], t[1]) and _stable(t[5])) == t[2] for t in trials):
            unstable = next((t for t in trials if not t[2] and t[0] is not None and rule(t[0], t[1])), bad)
            return f"{words}; refused otherwise (on {unstable[4]}: {unstable[3]})"
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
                        trials.append((_streams(variant), system.m, True, "", label, system))
                    except ConfigError as exc:
                        trials.append((_streams(variant), system.m, False, "; ".join(p.message for p in exc.problems),
                                       label, system))
                    except Exception as exc:  # noqa: BLE001 - a check that crashes is not an acceptance
                        trials.append((_streams(variant), system.m, False, f"{type(exc).__name__}: {exc}", label,
                                       system))
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


# ---- what each generic metric accepts of every estimator kind, computed the same way ---------------

METRIC_MONTECARLO = {"runs": 10, "horizon": 5}
"""The Monte Carlo block of the scenarios :func:`metric_compatibility` checks (a short horizon every example
recording covers)."""


def metric_scenario(system_block, channel, estimator, analysis):
    """The scenario `netkf validate` would check for (system, channel, estimator, analysis), unvalidated
    (its parts are validated instances)."""
    return scenario_model().model_construct(
        name="compat", description="", system=SystemSpec.model_validate(system_block), channel=channel,
        estimator=estimator, estimators=None, analysis=analysis, montecarlo=MonteCarloSpec(**METRIC_MONTECARLO),
        output=OutputSpec(), sweep=None)


def metric_compatibility() -> dict[str, dict[str, dict]]:
    """``{generic metric kind: {estimator kind: {"status": yes | conditional | no, "condition"/"reason"}}}``
    for every generic metric that does not state its own requirements (``works_with``): the scenario check
    :func:`check_scenario` (what `netkf validate` runs) of the metric, with its defaults (or the example
    scenarios' where it has required fields), on every (channel, system, stream count) on which the estimator
    kind validates with mean_vs_time (the metric every pair is listed for), on the representative systems."""
    return _metric_cached()


def _metric_cached(_cache: dict = {}) -> dict:  # noqa: B006 - a process-wide cache
    if "v" in _cache:
        return _cache["v"]
    found, every_system = _examples()
    table = compatibility()
    baseline = found["analysis"]["mean_vs_time"]
    metrics = {k: a for k, a in found["analysis"].items()
               if k in GENERIC_METRICS and not getattr(type(a), "works_with", None)}
    out: dict[str, dict[str, dict]] = {k: {} for k in sorted(metrics)}
    for ek, es in sorted(found["estimator"].items()):
        # the representative systems; the examples' too for a kind that validates on none of them (receiver)
        for systems in (every_system[:len(REPRESENTATIVE_SYSTEMS)], every_system[len(REPRESENTATIVE_SYSTEMS):]):
            trials = _metric_trials(table, found["channel"], ek, es, systems, baseline, metrics)
            if any(trials.values()):
                break
        for k in metrics:
            t = trials[k]
            if not t:
                out[k][ek] = {"status": "unknown", "reason": f"no channel and system {ek} validates on as the "
                                                            "examples set it, to check it on"}
            elif all(x[2] for x in t):
                out[k][ek] = {"status": "yes"}
            elif not any(x[2] for x in t):
                out[k][ek] = {"status": "no", "reason": t[0][3]}
            else:
                out[k][ek] = {"status": "conditional", "condition": _condition(t)}
    _cache["v"] = out
    return out


def _metric_trials(table, channels, ek, es, systems, baseline, metrics) -> dict[str, list]:
    """Per metric, the trials (streams, outputs, accepted, refusal, system label, system, channel kind) of estimator
    ``es`` on every channel it combines with and every system and stream count it validates on with ``baseline``."""
    trials: dict[str, list] = {k: [] for k in metrics}
    for ck, ch in sorted(channels.items()):
        if table.get(ck, {}).get(ek, {}).get("status") in (None, "no", "unknown"):
            continue
        for label, spec, system in systems:
            for variant in _variants(ch, system.m):
                if _refusal(metric_scenario(spec, variant, es, baseline)) is not None:
                    continue  # the pair itself is refused here: not the metric's doing
                for k, a in metrics.items():
                    why = _refusal(metric_scenario(spec, variant, es, a))
                    trials[k].append((_streams(variant), system.m, why is None, why or "", label, system, ck))
    return trials


def _refusal(scenario) -> str | None:
    """None where :func:`check_scenario` accepts the scenario, else its problems in words."""
    try:
        check_scenario(scenario)
        return None
    except ConfigError as exc:
        return "; ".join(f"{p.path}: {p.message}" if p.path else p.message for p in exc.problems)
    except Exception as exc:  # noqa: BLE001 - a check that crashes is not an acceptance
        return f"{type(exc).__name__}: {exc}"
