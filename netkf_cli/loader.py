"""YAML → Scenario, with every problem reported at once as ``file:line dotted.path: message``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError

from netkf_cli.errors import ConfigError, Problem
from netkf_cli.scenario import SystemSpec, scenario_model


class _LineLoader(yaml.SafeLoader):
    """SafeLoader that rejects duplicate keys (a silent overwrite hides a typo)."""


def _construct_mapping(loader, node, deep=False):
    keys = set()
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if key in keys:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r}", key_node.start_mark
            )
        keys.add(key)
    return loader.construct_mapping(node, deep=deep)


_LineLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def line_index(text: str) -> dict[tuple, int]:
    """Map every key path (tuple of keys / list indices) to its 1-based line in the YAML text."""
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError:
        return {}
    index: dict[tuple, int] = {}

    def walk(node, path):
        if isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                p = path + (k.value,)
                index[p] = k.start_mark.line + 1
                walk(v, p)
        elif isinstance(node, yaml.SequenceNode):
            for i, v in enumerate(node.value):
                p = path + (i,)
                index[p] = v.start_mark.line + 1
                walk(v, p)

    if root is not None:
        walk(root, ())
    return index


def line_of(index: dict[tuple, int], path: tuple) -> int | None:
    """Line of the deepest existing prefix of ``path`` (a missing key points at its parent)."""
    p = tuple(path)
    while p:
        if p in index:
            return index[p]
        p = p[:-1]
    return None


def _clean_loc(loc: tuple, data: Any) -> tuple:
    """Drop pydantic's union tags so ``loc`` becomes the user's key path.

    A discriminated union inserts the ``kind`` value after the field name
    (``('channel', 'delay', 'buffer')`` for ``channel: {kind: delay, buffer: …}``); other unions
    insert a type tag (``'list[float]'``, ``'function-after[…]'``). At most one tag per level.
    """
    out, cur, tag_skipped = [], data, False
    for part in loc:
        if isinstance(cur, dict):
            if not tag_skipped and isinstance(part, str) and cur.get("kind") == part:
                tag_skipped = True
                continue
            if part in cur:
                out.append(part)
                cur, tag_skipped = cur[part], False
                continue
            if isinstance(part, str) and ("[" in part or part in _TYPE_TAGS):
                continue
            out.append(part)  # a missing or unknown key: keep it, stop descending
            cur = None
        elif isinstance(cur, list) and isinstance(part, int) and part < len(cur):
            out.append(part)
            cur, tag_skipped = cur[part], False
        elif isinstance(part, str) and ("[" in part or part in _TYPE_TAGS or cur is not None):
            continue  # a tag of a leaf union (e.g. Matrix | 'steady')
        else:
            out.append(part)
    return tuple(out)


_TYPE_TAGS = {"str", "float", "int", "bool", "list", "dict", "none", "literal['steady']"}


def _dotted(path: tuple) -> str:
    s = ""
    for p in path:
        s += f"[{p}]" if isinstance(p, int) else (("." if s else "") + str(p))
    return s


def _message(err: dict) -> str:
    t, msg = err["type"], err["msg"]
    inp = err.get("input")
    if t == "extra_forbidden":
        return "unknown key (not part of the schema; check its spelling)"
    if t == "missing":
        return "required field is missing"
    if t == "union_tag_invalid":
        ctx = err.get("ctx", {})
        return f"unknown kind {ctx.get('tag')!r}; expected one of {ctx.get('expected_tags')}"
    if t == "union_tag_not_found":
        return "needs a `kind:` field"
    msg = msg.removeprefix("Value error, ")
    if inp is not None and not isinstance(inp, (dict, list)):
        return f"{msg}, got {inp!r}"
    return msg


def validation_problems(exc: ValidationError, data: Any, index: dict, file: str | None, prefix: tuple = ()) -> list[Problem]:
    problems, seen = [], set()
    for err in exc.errors():
        loc = prefix + _clean_loc(tuple(err["loc"]), _get(data, prefix))
        if err["type"] == "union_tag_invalid":
            loc = loc + ("kind",)
        msg = _message(err)
        key = (loc, msg)
        if key in seen:
            continue
        seen.add(key)
        problems.append(Problem(_dotted(loc), msg, file, line_of(index, loc)))
    return problems


def _get(data, path):
    for p in path:
        data = data[p]
    return data


def parse_yaml(text: str, file: str | None = None) -> Any:
    try:
        return yaml.load(text, Loader=_LineLoader)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark else None
        col = f", column {mark.column + 1}" if mark else ""
        what = exc.problem or str(exc)
        raise ConfigError([Problem("", f"YAML syntax error{col}: {what}", file, line)]) from None
    except yaml.YAMLError as exc:
        raise ConfigError([Problem("", f"YAML error: {exc}", file)]) from None


def load_scenario_text(text: str, file: str | None = None, overrides: dict | None = None):
    """Parse and validate; raise one :class:`ConfigError` with every problem found."""
    data = parse_yaml(text, file)
    if not isinstance(data, dict):
        raise ConfigError([Problem("", "a scenario must be a mapping with keys name, analysis, …", file, 1)])
    if overrides:
        data = deep_merge(data, overrides)
    index = line_index(text)
    Model = scenario_model()
    problems: list[Problem] = []
    scenario = None
    try:
        scenario = Model.model_validate(data)
    except ValidationError as exc:
        problems.extend(validation_problems(exc, data, index, file))
    # semantic checks of the system block (shapes, definiteness), reported with the others
    sysdata = data.get("system")
    if isinstance(sysdata, dict):
        try:
            SystemSpec.model_validate(sysdata).build()
        except ValidationError:
            pass  # already reported above
        except ConfigError as exc:
            for p in exc.problems:
                problems.append(Problem(p.path, p.message, file, line_of(index, tuple(p.path.split(".")))))
    if problems:
        raise ConfigError(problems)
    return scenario


def load_scenario(path: str | Path, overrides: dict | None = None):
    p = Path(path)
    if not p.exists():
        raise ConfigError([Problem("", "file not found", str(path))])
    if p.is_dir():
        raise ConfigError([Problem("", "is a folder, expected a scenario YAML file", str(path))])
    return load_scenario_text(p.read_text(encoding="utf-8"), str(path), overrides)


def locate(exc: ConfigError, path: str | Path) -> ConfigError:
    """Attach file and line (looked up from the dotted path) to problems raised after loading."""
    try:
        index = line_index(Path(path).read_text(encoding="utf-8"))
    except OSError:
        index = {}
    probs = []
    for p in exc.problems:
        if p.file:
            probs.append(p)
            continue
        keys = tuple(int(k) if k.isdigit() else k for k in p.path.replace("[", ".").replace("]", "").split(".") if k)
        probs.append(Problem(p.path, p.message, str(path), line_of(index, keys)))
    return type(exc)(probs)


def deep_merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = v
    return out
