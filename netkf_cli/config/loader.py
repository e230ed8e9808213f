"""YAML → Scenario, with every problem reported at once as ``file:line dotted.path: message``."""

from __future__ import annotations

import copy
import math
import re
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from pydantic import ValidationError

from netkf_cli.config import sweep
from netkf_cli.config.compat import check_scenario  # cross-block checks: channel × estimator × analysis
from netkf_cli.core.errors import ConfigError, Problem
from netkf_cli.config.scenario import SystemSpec, scenario_model


MAX_FILE_BYTES = 4 * 1024 * 1024
"""Largest scenario file read (scenarios are a few kB; a bigger file is not a scenario)."""
MAX_NODES = 200_000
"""Largest scenario, in YAML nodes after expanding aliases (refuses "billion laughs" bombs)."""
MAX_DEPTH = 200
"""Deepest nesting of lists/mappings accepted."""


class _Yaml12Resolver(yaml.resolver.BaseResolver):
    """YAML 1.2 core-schema scalars: ``1e-3``, ``1e6`` and ``1.0e6`` are floats; only
    ``true``/``false`` are booleans (``yes``, ``no``, ``on``, ``off`` stay strings); no sexagesimal
    numbers; ``0o17``/``0x1F`` integers; ``.inf``/``.nan`` floats (refused later as non-finite)."""


_Yaml12Resolver.yaml_implicit_resolvers = {}
_Yaml12Resolver.add_implicit_resolver(
    "tag:yaml.org,2002:bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF"))
_Yaml12Resolver.add_implicit_resolver(
    "tag:yaml.org,2002:int", re.compile(r"^(?:[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+)$"), list("-+0123456789"))
_Yaml12Resolver.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?"
               r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"),
    list("-+.0123456789"))
_Yaml12Resolver.add_implicit_resolver(
    "tag:yaml.org,2002:null", re.compile(r"^(?:~|null|Null|NULL|)$"), ["~", "n", "N", ""])


class _LineLoader(yaml.reader.Reader, yaml.scanner.Scanner, yaml.parser.Parser, yaml.composer.Composer,
                  yaml.constructor.SafeConstructor, _Yaml12Resolver):
    """Safe loader with YAML 1.2 scalars that rejects duplicate keys (a silent overwrite hides a typo)."""

    def __init__(self, stream):
        yaml.reader.Reader.__init__(self, stream)
        yaml.scanner.Scanner.__init__(self)
        yaml.parser.Parser.__init__(self)
        yaml.composer.Composer.__init__(self)
        yaml.constructor.SafeConstructor.__init__(self)
        _Yaml12Resolver.__init__(self)


def _construct_int(loader, node):
    text = loader.construct_scalar(node).replace("_", "")
    if text.startswith(("0o", "0x")):
        return int(text[2:], 8 if text[1] == "o" else 16)
    return int(text)


def _construct_float(loader, node):
    text = loader.construct_scalar(node).lower()
    if text.endswith(".inf"):
        return float("-inf") if text.startswith("-") else float("inf")
    if text == ".nan":
        return float("nan")
    return float(text)


_LineLoader.add_constructor("tag:yaml.org,2002:int", _construct_int)
_LineLoader.add_constructor("tag:yaml.org,2002:float", _construct_float)


def _construct_mapping(loader, node, deep=False):
    keys = set()
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if not isinstance(key, str):
            raise yaml.constructor.ConstructorError(
                None, None, f"keys must be names (text), got {key!r}", key_node.start_mark
            )
        if key in keys:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r}", key_node.start_mark
            )
        keys.add(key)
    return loader.construct_mapping(node, deep=deep)


_LineLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)

if getattr(yaml, "__with_libyaml__", False):
    class _CLineLoader(yaml._yaml.CParser, yaml.constructor.SafeConstructor, _Yaml12Resolver):
        """:class:`_LineLoader` on libyaml's parser (PyYAML's C extension): the same resolver and constructors
        (the same data, the same line index: every configs/ file checked by tests/unit), ~3x faster — the
        reproduction's discovery parses every scenario before any work starts. An error re-parses with the
        pure-Python loader, whose messages carry the context a user reads."""

        def __init__(self, stream):
            yaml._yaml.CParser.__init__(self, stream)
            yaml.constructor.SafeConstructor.__init__(self)
            _Yaml12Resolver.__init__(self)

    _CLineLoader.yaml_constructors = _LineLoader.yaml_constructors
else:  # pragma: no cover - PyYAML built without libyaml
    _CLineLoader = None

C_PARSE_MAX_NESTERS = 20 * MAX_DEPTH
"""libyaml composes nodes by C recursion (no RecursionError: 20 000 nested lists parse, 100 000 crash the process,
checked with PyYAML 6.0.3): it parses only a text with fewer than this many characters that can open a nesting
level (``[{-:?``; the largest shipped file has 569); others go to the pure-Python loader, which refuses deep
nesting with a message."""


def _loader(text: str, fast: bool = True):
    """The loader of ``text``: libyaml's when available and the text cannot nest deeply, else pure Python."""
    if fast and _CLineLoader is not None and sum(text.count(c) for c in "[{-:?") < C_PARSE_MAX_NESTERS:
        return _CLineLoader(text)
    return _LineLoader(text)


def _check_size(root, file: str | None) -> None:
    """Refuse a document whose alias-expanded size or depth is beyond :data:`MAX_NODES` /
    :data:`MAX_DEPTH`, in time linear in the number of distinct nodes (sizes are memoized)."""
    sizes: dict[int, int] = {}
    aliased = 0

    def size(node, depth: int) -> int:
        nonlocal aliased
        if depth > MAX_DEPTH:
            raise ConfigError([Problem("", f"nested more than {MAX_DEPTH} levels deep; not a scenario",
                                       file, node.start_mark.line + 1)])
        key = id(node)
        if key in sizes:
            aliased += 1
            return sizes[key]
        if isinstance(node, yaml.MappingNode):
            n = 1 + sum(size(k, depth + 1) + size(v, depth + 1) for k, v in node.value)
        elif isinstance(node, yaml.SequenceNode):
            n = 1 + sum(size(v, depth + 1) for v in node.value)
        else:
            n = 1
        sizes[key] = n = min(n, 10 * MAX_NODES)
        return n

    if root is not None and size(root, 0) > MAX_NODES:
        raise ConfigError([Problem("", f"expands to more than {MAX_NODES:,} YAML nodes"
                                       + (" through aliases (*name); refusing an alias bomb" if aliased else "")
                                       + "; a scenario is much smaller", file, 1)])


def line_index(text: str) -> dict[tuple, int]:
    """Map every key path (tuple of keys / list indices) to its 1-based line in the YAML text."""
    for fast in (True, False):
        loader = _loader(text, fast)
        if fast and isinstance(loader, _LineLoader):
            continue  # the pure-Python loader anyway: once
        try:
            root = loader.get_single_node()
            _check_size(root, None)
            return _node_index(root)
        except (yaml.YAMLError, ConfigError, RecursionError):
            continue
        finally:
            loader.dispose()
    return {}


def _node_index(root) -> dict[tuple, int]:
    """:func:`line_index` of an already composed (and size-checked) YAML node."""
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
    if inp is not None and not isinstance(inp, (dict, list)) and " got " not in msg:
        return f"{msg}, got {inp!r}"
    return msg


def validation_problems(exc: ValidationError, data: Any, index: dict, file: str | None, prefix: tuple = ()) -> list[Problem]:
    problems, seen = [], set()
    for err in exc.errors():
        loc = prefix + _clean_loc(tuple(err["loc"]), _get(data, prefix))
        if err["type"] == "union_tag_invalid":
            loc = loc + ("kind",)
        msg = _message(err)
        loc, msg = _hoist_field(loc, msg, data)
        key = (loc, msg)
        if key in seen:
            continue
        seen.add(key)
        problems.append(Problem(_dotted(loc), msg, file, line_of(index, loc)))
    return problems


_FIELD_PREFIX = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)((?:\[\d+\])*): (.+)$", re.S)


_FIELD_SUBJECT = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*) (?:must|needs|has|is|cannot) ")


def _hoist_field(loc: tuple, msg: str, data: Any) -> tuple[tuple, str]:
    """A model-level check that names its field (``"initial: needs 4 probabilities"`` at
    ``channel``) is reported at that field (``channel.initial``), so its line is the field's. So is one
    whose sentence starts with the field (``"M must be finite and > 0"`` at ``analysis``): the message kept
    whole, and an override of that field (``analysis.M=[-1]``) is named as its source."""
    m = _FIELD_PREFIX.match(msg)
    if not m:
        s = _FIELD_SUBJECT.match(msg)
        try:
            block = _get(data, loc) if s else None
        except (KeyError, IndexError, TypeError):
            block = None
        if isinstance(block, dict) and s[1] in block:
            return loc + (s[1],), msg
        return loc, msg
    try:
        block = _get(data, loc)
    except (KeyError, IndexError, TypeError):
        return loc, msg
    if not isinstance(block, dict) or m[1] not in block:
        return loc, msg
    new = loc + (m[1],)
    cur = block[m[1]]
    for idx in re.findall(r"\[(\d+)\]", m[2]):
        i = int(idx)
        if not isinstance(cur, list) or i >= len(cur):
            break
        new, cur = new + (i,), cur[i]
    return new, m[3]


def _get(data, path):
    for p in path:
        data = data[p]
    return data


def parse_yaml(text: str, file: str | None = None) -> Any:
    """Parse one YAML document under YAML 1.2 scalar rules, within the size limits; every
    number must be finite. Errors are :class:`ConfigError` with file and line."""
    return _parse_yaml(text, file)[0]


def _parse_yaml(text: str, file: str | None = None) -> tuple[Any, dict[tuple, int]]:
    """:func:`parse_yaml` and the :func:`line_index` of the same text, from one composition of it."""
    loader = _loader(text)
    if not isinstance(loader, _LineLoader):
        try:
            return _compose_and_construct(loader, file)
        except (yaml.YAMLError, ConfigError):
            pass  # the pure-Python loader says what is wrong (below), with its own words and context
    return _compose_and_construct(loader if isinstance(loader, _LineLoader) else _LineLoader(text), file)


def _compose_and_construct(loader, file: str | None) -> tuple[Any, dict[tuple, int]]:
    try:
        root = loader.get_single_node()
        _check_size(root, file)
        index = _node_index(root) if root is not None else {}  # before construction (a merge key flattens the nodes)
        data = loader.construct_document(root) if root is not None else None
    except RecursionError:
        raise ConfigError([Problem("", "nested too deeply; not a scenario", file)]) from None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark else None
        col = f", column {mark.column + 1}" if mark else ""
        what = exc.problem or str(exc)
        if isinstance(exc, yaml.constructor.ConstructorError):
            if what.startswith(("duplicate key", "keys must be")):
                why = " (the second would silently replace the first)" if what.startswith("duplicate") else ""
                raise ConfigError([Problem("", f"{what}{col}{why}", file, line)]) from None
            raise ConfigError([Problem("", f"YAML error{col}: {what} (netkf reads plain YAML: no tags)",
                                       file, line)]) from None
        raise ConfigError([Problem("", f"YAML syntax error{col}: {what}", file, line)]) from None
    except yaml.YAMLError as exc:
        raise ConfigError([Problem("", f"YAML error: {exc}", file)]) from None
    finally:
        loader.dispose()
    bad = list(_non_finite(data, ()))
    if bad:
        raise ConfigError([Problem(_dotted(path), f"must be a finite number, got {v!r}", file, line_of(index, path))
                           for path, v in bad])
    return data, index


def _non_finite(data: Any, path: tuple):
    """Paths of every non-finite float (``.nan``, ``.inf``) in parsed YAML."""
    if isinstance(data, float) and not math.isfinite(data):
        yield path, data
    elif isinstance(data, dict):
        for k, v in data.items():
            yield from _non_finite(v, path + (k,))
    elif isinstance(data, list):
        for i, v in enumerate(data):
            yield from _non_finite(v, path + (i,))


MAX_ENTRY = 1e50
"""Largest magnitude of a system matrix entry: the Riccati recursions multiply up to about six
such factors (A P Aᵀ, C P Cᵀ + R, their inverse …), and 1e50⁶ = 1e300 still fits a double
(≤ 1.8e308); beyond it products overflow to inf and every answer would be meaningless."""


def _system_magnitudes(sysdata: dict) -> list[Problem]:
    """``system.A`` with entries near 1e308 (or ρ(A) = 1e200) is refused here, naming the matrix,
    before any analysis squares it into an overflow."""
    problems = []
    for key in ("A", "C", "Q", "R", "P0"):
        v = sysdata.get(key)
        flat = list(_numbers(v))
        if not flat:
            continue
        big = max(abs(x) for x in flat)
        if big > MAX_ENTRY:
            problems.append(Problem(f"system.{key}", f"entries must be at most {MAX_ENTRY:.0e} in magnitude, got "
                                    f"{big:.3g}: products of such numbers overflow double precision (rescale the "
                                    f"state or the output)"))
    return problems


def _numbers(v):
    if isinstance(v, bool):
        return
    if isinstance(v, (int, float)):
        yield float(v)
    elif isinstance(v, list):
        for x in v:
            yield from _numbers(x)


def validate_data(data: Any, file: str | None = None, index: dict | None = None, base_dir: str | None = None,
                  overrides: "list[Override] | tuple" = ()):
    """The one validation of a scenario, whatever it came from (a file, YAML text, a Python dict,
    with or without overrides): schema, system semantics, cross-block checks. Raises one
    :class:`ConfigError` with every problem found; a problem at an overridden field names the
    override instead of a line of the file."""
    index = index or {}
    if data is None:
        raise ConfigError([Problem("", "the file is empty; a scenario is a mapping with keys name, analysis, …", file, 1)])
    if not isinstance(data, dict):
        got = {list: "a list", str: "a single string"}.get(type(data), f"a {type(data).__name__}")
        raise ConfigError([Problem("", f"a scenario must be a mapping with keys name, analysis, …; this file holds {got}",
                                   file, 1)])
    bad = list(_non_finite(data, ()))
    if bad:
        raise ConfigError(attribute([Problem(_dotted(path), f"must be a finite number, got {v!r}", file,
                                             line_of(index, path)) for path, v in bad], overrides))
    Model = scenario_model()
    problems: list[Problem] = []
    scenario = None
    try:
        scenario = Model.model_validate(data, context={"base_dir": base_dir})
    except ValidationError as exc:
        problems.extend(validation_problems(exc, data, index, file))
    # semantic checks of the system block (shapes, definiteness, magnitudes), reported with the others
    sysdata = data.get("system")
    if isinstance(sysdata, dict):
        sys_problems = _system_magnitudes(sysdata)
        if not sys_problems:
            try:
                SystemSpec.model_validate(sysdata).build()
            except ValidationError:
                pass  # already reported above
            except ConfigError as exc:
                sys_problems = exc.problems
        for p in sys_problems:
            problems.append(Problem(p.path, p.message, file, line_of(index, _keys(p.path))))
    if problems:
        raise ConfigError(attribute(problems, overrides))

    try:
        check_scenario(scenario)
    except ConfigError as exc:
        raise ConfigError(attribute([p if p.file else Problem(p.path, p.message, file, line_of(index, _keys(p.path)))
                                     for p in exc.problems], overrides)) from None
    if scenario.sweep is not None or getattr(scenario.analysis, "over", None):  # every point gets these same
        try:  # checks, now (as `netkf validate` promises)
            sweep.check_axes(scenario)
            if scenario.sweep is not None:
                sweep.expand(scenario, file, validate_data)
            else:
                sweep.expand_over(scenario, file, validate_data)
        except ConfigError as exc:
            raise ConfigError(attribute(locate_index(exc, index, file).problems, overrides)) from None
    return scenario


def load_scenario_text(text: str, file: str | None = None, overrides=None):
    """Parse and validate (after applying ``overrides``); raise one :class:`ConfigError` with every
    problem found."""
    data, index = _parse_yaml(text, file)
    ovs = parse_overrides(overrides)
    if ovs and isinstance(data, dict):  # (anything else is refused by validate_data, naming the file)
        data = apply_overrides(data, ovs)
    base_dir = str(Path(file).resolve().parent) if file else None
    return validate_data(data, file, index, base_dir, ovs)


# ---- command-line overrides: key=value with dotted paths (the Hydra / OmegaConf grammar) -----------

OVERRIDE_FILE = "command line"
_KEY = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


@dataclass(frozen=True)
class Override:
    """One override: ``channel.arrival=0.6`` (set), ``+key=value`` / ``++key=value`` (set, also a
    key the file does not have), ``~key`` (delete). ``text`` is how it was given."""

    keys: tuple
    value: Any
    text: str
    delete: bool = False
    merge: bool = False  # a Python mapping given through the API: merged into a mapping already there

    @property
    def dotted(self) -> str:
        return _dotted(self.keys)

    def where(self) -> str:
        return f"{OVERRIDE_FILE} ({self.text})"


def _split_path(path: str, text: str) -> tuple:
    """``a.b[0].c`` or ``a.b.0.c`` → ('a', 'b', 0, 'c'); under ``sweep`` the rest is one dotted key
    (sweep axes are field paths themselves), except ``sweep.mode`` and ``sweep.plot.…``."""
    def bad(why: str) -> ConfigError:
        return ConfigError([Problem("", f"override {text!r}: {why}", OVERRIDE_FILE)])

    if not path:
        raise bad("expected key=value with a dotted key, e.g. channel.arrival=0.6")
    if path.startswith("sweep.") and not path.startswith(("sweep.mode", "sweep.plot")):
        return ("sweep", path.removeprefix("sweep."))
    keys: list = []
    for part in path.split("."):
        m = re.fullmatch(r"([^\[\]]*)((?:\[\d+\])*)", part)
        if not m or (not m[1] and not keys):
            raise bad(f"{path!r} is not a dotted field path (names separated by dots, list items as [i] or .i)")
        name, idx = m[1], [int(i) for i in re.findall(r"\[(\d+)\]", m[2])]
        if name:
            if name.isdigit():
                keys.append(int(name))
            elif _KEY.match(name):
                keys.append(name)
            else:
                raise bad(f"{name!r} is not a field name (letters, digits and _)")
        elif not idx:
            raise bad(f"{path!r} has an empty part")
        keys.extend(idx)
    return tuple(keys)


def parse_override(text: str) -> Override:
    """One ``key=value`` string; the value is read with the scenario files' YAML 1.2 rules."""
    if not isinstance(text, str):
        raise ConfigError([Problem("", f"an override is a 'key=value' string, got {type(text).__name__} {text!r}",
                                   OVERRIDE_FILE)])
    s = text.strip()
    if s.startswith("~"):
        key = s[1:].split("=", 1)[0]
        return Override(_split_path(key, text), None, text, delete=True)
    if "=" not in s:
        raise ConfigError([Problem("", f"override {text!r}: expected key=value (e.g. channel.arrival=0.6 or "
                                       f"'system.A=[[1.1, 0], [0, 0.9]]'), or ~key to delete a key", OVERRIDE_FILE)])
    key, value = s.split("=", 1)
    key = key.lstrip("+")
    keys = _split_path(key.strip(), text)
    return Override(keys, parse_yaml(value, f"{OVERRIDE_FILE} ({text})"), text)


def parse_overrides(items) -> list[Override]:
    """Overrides from a list of ``key=value`` strings or a mapping ``{dotted.path: value}`` (Python
    values, used as they are; a mapping value is merged into a mapping already there, as
    ``load(d, overrides={"analysis": {"grid": 30}})`` always did)."""
    if not items:
        return []
    if isinstance(items, Override):
        return [items]
    if isinstance(items, dict):
        out = []
        for k, v in items.items():
            if not isinstance(k, str):
                raise ConfigError([Problem("", f"override keys are dotted field paths (text), got {k!r}", OVERRIDE_FILE)])
            out.append(Override(_split_path(k, f"{k}={v!r}"), _plain(v), f"{k}={_short(v)}", merge=True))
        return out
    if isinstance(items, str):
        items = [items]
    try:
        seq = list(items)
    except TypeError:
        raise ConfigError([Problem("", f"overrides must be a list of 'key=value' strings or a dict "
                                       f"{{dotted.path: value}}, got {type(items).__name__}", OVERRIDE_FILE)]) from None
    return [o if isinstance(o, Override) else parse_override(o) for o in seq]


def _short(v) -> str:
    r = repr(v)
    return r if len(r) <= 60 else r[:57] + "..."


def _plain(v):
    """numpy scalars and arrays as plain Python numbers and lists (what YAML would have given)."""
    if isinstance(v, np.ndarray):
        return _plain(v.tolist())
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return v


def apply_overrides(data: dict, overrides: list[Override]) -> dict:
    """A copy of ``data`` with every override applied in order; impossible paths are one
    :class:`ConfigError` naming each override."""
    data = copy.deepcopy(data)
    problems = []
    for o in overrides:
        cur: Any = data
        ok = True
        for i, k in enumerate(o.keys[:-1]):
            nxt = o.keys[i + 1]
            here = _dotted(o.keys[: i + 1])
            if isinstance(k, int):
                if not isinstance(cur, list) or k >= len(cur):
                    problems.append(Problem(here, _index_problem(cur, k), o.where()))
                    ok = False
                    break
                if not isinstance(cur[k], (dict, list)):
                    cur[k] = {}
                cur = cur[k]
            else:
                if not isinstance(cur, dict):
                    problems.append(Problem(here, f"cannot set a field inside {_what(cur)}", o.where()))
                    ok = False
                    break
                if k not in cur or cur[k] is None:
                    if o.delete:
                        problems.append(Problem(o.dotted, "is not in the scenario; nothing to delete", o.where()))
                        ok = False
                        break
                    cur[k] = [] if isinstance(nxt, int) else {}
                elif not isinstance(cur[k], (dict, list)):
                    problems.append(Problem(here, f"holds {_what(cur[k])}, not a block of fields: cannot set "
                                                  f"{o.dotted}", o.where()))
                    ok = False
                    break
                cur = cur[k]
        if not ok:
            continue
        last = o.keys[-1]
        if isinstance(last, int):
            if not isinstance(cur, list) or last >= len(cur):
                problems.append(Problem(o.dotted, _index_problem(cur, last), o.where()))
                continue
        elif not isinstance(cur, dict):
            problems.append(Problem(o.dotted, f"cannot set a field inside {_what(cur)}", o.where()))
            continue
        if o.delete:
            if isinstance(last, int):
                del cur[last]
            elif last in cur:
                del cur[last]
            else:
                problems.append(Problem(o.dotted, "is not in the scenario; nothing to delete", o.where()))
            continue
        old = cur[last] if (isinstance(last, int) or last in cur) else None
        cur[last] = deep_merge(old, o.value) if (o.merge and isinstance(old, dict) and isinstance(o.value, dict)) \
            else copy.deepcopy(o.value)
    if problems:
        raise ConfigError(problems)
    return data


def _index_problem(cur, k: int) -> str:
    if not isinstance(cur, list):
        return f"item [{k}] of {_what(cur)}: not a list"
    return f"index {k} is out of range (the list has {len(cur)} item{'s' if len(cur) != 1 else ''})"


def _what(v) -> str:
    if isinstance(v, bool):
        return "a boolean"
    if isinstance(v, (int, float)):
        return f"the number {v!r}"
    if isinstance(v, str):
        return f"the text {v!r}"
    if isinstance(v, list):
        return "a list"
    return f"a {type(v).__name__}"


def attribute(problems: list[Problem], overrides) -> list[Problem]:
    """A problem at (or inside) an overridden field is the override's, not the file's: it names
    ``command line (key=value)`` instead of a line of the file that no longer holds that value."""
    if not overrides:
        return problems
    out = []
    for p in problems:
        hit = None
        for o in overrides:
            d = o.dotted
            if p.path == d or p.path.startswith((d + ".", d + "[")):
                hit = o
            elif d.startswith(p.path + ".") and p.message.startswith(d[len(p.path) + 1:] + ":"):
                hit = o  # a check of the enclosing block that names the field first (a sweep axis: "channel.buffer: …")
            elif d.startswith(p.path + ".") and p.message.startswith("unknown key"):
                hit = o  # foo.bar=1: the unknown key foo is the override's (the file has no foo)
        out.append(replace(p, file=hit.where(), line=None) if hit is not None else p)
    return out


def _keys(dotted: str) -> tuple:
    return tuple(int(k) if k.isdigit() else k for k in dotted.replace("[", ".").replace("]", "").split(".") if k)


def read_text(path: str | Path) -> str:
    """A scenario file's text: UTF-8 (a UTF-8 BOM is allowed), at most :data:`MAX_FILE_BYTES`;
    anything else is one :class:`ConfigError` saying what the file is instead."""
    p, f = Path(path), str(path)
    if not p.exists():
        raise ConfigError([Problem("", "file not found", f)])
    if p.is_dir():
        raise ConfigError([Problem("", "is a folder, expected a scenario YAML file", f)])
    try:
        with open(p, "rb") as fh:
            raw = fh.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise ConfigError([Problem("", f"cannot read the file: {exc.strerror or exc}", f)]) from None
    if len(raw) > MAX_FILE_BYTES:
        raise ConfigError([Problem("", f"is larger than {MAX_FILE_BYTES // 2**20} MB; not a scenario file", f)])
    head = raw[:64] if len(raw) % 2 == 0 else b""
    if raw.startswith((b"\xff\xfe", b"\xfe\xff")) or (len(head) >= 4 and (not any(head[1::2]) or not any(head[0::2]))
                                                       and any(head)):
        raise ConfigError([Problem("", "is UTF-16 text; netkf reads UTF-8 scenario files (save it as UTF-8)", f)])
    if b"\x00" in raw:
        raise ConfigError([Problem("", "is a binary file, not a YAML scenario (UTF-8 text)", f)])
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise ConfigError([Problem("", f"is not UTF-8 text (byte 0x{raw[exc.start]:02x} at offset {exc.start}); "
                                       "save it as UTF-8", f, line)]) from None
    return text


def load_scenario(path: str | Path, overrides=None):
    """A validated Scenario from a YAML file, after ``overrides`` (``key=value`` strings or a
    ``{dotted.path: value}`` mapping)."""
    return load_scenario_text(read_text(path), str(path), overrides)


def locate(exc: ConfigError, path: str | Path) -> ConfigError:
    """Attach file and line (looked up from the dotted path) to problems raised after loading."""
    try:
        index = line_index(read_text(path))
    except ConfigError:
        index = {}
    return locate_index(exc, index, str(path))


def locate_index(exc: ConfigError, index: dict, path: str | None) -> ConfigError:
    """:func:`locate` with the file's line index at hand."""
    if path is None:
        return exc
    probs = []
    for p in exc.problems:
        if p.line is not None or (p.file and Path(p.file) != Path(path)):
            probs.append(p)
            continue
        keys = tuple(int(k) if k.isdigit() else k for k in p.path.replace("[", ".").replace("]", "").split(".") if k)
        line = None
        if p.path.startswith("sweep."):  # sweep keys are dotted paths themselves
            line = index.get(("sweep", p.path.removeprefix("sweep.")))
        elif p.path.startswith("analysis.over."):  # so are an over grid's keys
            line = index.get(("analysis", "over", p.path.removeprefix("analysis.over.")))
        else:  # a bad value at sweep / over points: the entry's line
            kind, swept = sweep.point_keys(p.message)
            block = ("sweep",) if kind == "sweep" else ("analysis", "over")
            line = next((index[(*block, k)] for k in swept if (*block, k) in index), None) if kind else None
        probs.append(Problem(p.path, p.message, p.file or str(path), line or line_of(index, keys)))
    return type(exc)(probs)


def deep_merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = v
    return out
