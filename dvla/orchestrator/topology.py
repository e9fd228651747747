"""Topology files: YAML text in, a validated frozen :class:`dvla.config.Topology` out.

Also writes a resolved topology back to YAML (the run directory's copy). The rules are the
schema's, beside each field in :mod:`dvla.config`; the reader walks the dataclasses generically,
reading each value by its type hint and applying the field's rules, then the object's
``problems()``. Only the checks against this machine live here.

Every problem is reported at once as ``file:line: key.path: message``; a rule reading a value
already reported is skipped. Parsing walks ``yaml.compose``'s nodes: only they carry line numbers.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import importlib
import json
import math
import os
import re
import sys
import types
import typing
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Literal

import yaml
from yaml.events import AliasEvent
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

from dvla.config import (LIBERO_ASSETS_ENV, LIBERO_ASSETS_FIX, LIBERO_ENV, LOCAL_HOSTS, Problems, TaskConfig, Topology, cut,
                         libero_assets_problem, show, unknown_value, unwrap_optional)

from .process import is_local_host

__all__ = ["Problem", "TopologyError", "load_topology", "parse_topology", "topology_to_dict", "dump_topology_yaml"]

#: Topology fields the loader fills in; a file may not set them
LOADER_OWNED = frozenset({"source"})

# A topology file is input like any other: these bound what reading one can cost.
#: largest file read (a topology of 1,000 nodes is ~100 KiB)
MAX_FILE_BYTES = 1 << 20
#: deepest nesting of lists and mappings (a topology needs ~10; PyYAML's composer recurses)
MAX_DEPTH = 64
#: most problems listed (the rest are counted in one last line)
MAX_PROBLEMS = 100

_TAG = "tag:yaml.org,2002:"
#: plain scalars like ``3e-4`` are strings to YAML 1.1 but numbers to everyone writing them
_EXPONENT_FLOAT_RE = re.compile(r"[-+]?(?:\d[\d_]*\.?[\d_]*|\.\d[\d_]*)[eE][-+]?\d+")


# --------------------------------------------------------------------------------------------
# problems


@dataclass(frozen=True)
class Problem:
    """One thing wrong with a topology file."""

    #: file the problem is in
    source: str
    #: 1-based line (0: no line applies, e.g. the file cannot be read)
    line: int
    #: dotted key path, e.g. ``racks[1].nodes[2].roles[0].role`` ("" for the whole document)
    path: str
    #: what is wrong: the bad value and what was expected
    message: str

    def __str__(self) -> str:
        where = f"{self.source}:{self.line}" if self.line > 0 else self.source
        return f"{where}: {self.path or '<root>'}: {self.message}"


class TopologyError(ValueError):
    """A topology file is invalid; ``problems`` lists everything wrong with it, in line order."""

    def __init__(self, problems: list[Problem]) -> None:
        self.problems = list(problems)
        if len(self.problems) > MAX_PROBLEMS:  # a hostile file may hold a million mistakes
            rest = self.problems[MAX_PROBLEMS:]
            more = Problem(rest[0].source, rest[0].line, rest[0].path, f"{len(rest)} more problem(s) from here on not shown")
            self.problems = [*self.problems[:MAX_PROBLEMS], more]
        super().__init__("\n".join(str(p) for p in self.problems))


#: a value that could not be read (its problem is already reported)
INVALID: Any = object()


def _one_line(text: str, limit: int) -> str:
    """`text` as one printable line of at most about `limit` characters (the middle cut out)."""
    text = "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)
    if len(text) <= limit:
        return text
    return f"{text[:limit * 3 // 4]} ... {text[-limit // 4:]}"


class _Context:
    """Problems found so far and the line of every key path seen."""

    def __init__(self, source: str) -> None:
        self.source = source
        #: directory relative paths in the file are resolved against ("<memory>": the working dir)
        self.base_dir = os.getcwd() if source.startswith("<") else os.path.dirname(os.path.abspath(source))
        self.problems: list[Problem] = []
        self.lines: dict[str, int] = {"": 1}

    def report(self, path: str, message: str, line: int | None = None) -> None:
        if line is None:
            line = self.line_of(path)
        # paths hold the file's keys and messages its values: whatever they are, one short line
        self.problems.append(Problem(self.source, line, _one_line(path, 200), _one_line(message, 400)))

    def line_of(self, path: str) -> int:
        """Line of ``path``, or of its nearest ancestor present in the file (absent keys)."""
        while path not in self.lines:
            cut_at = max(path.rfind("."), path.rfind("["))
            path = path[:cut_at] if cut_at > 0 else ""
        return self.lines[path]

    def construct(self, node: Node, path: str) -> Any:
        """Python value of a node, by YAML's own rules (tags, ints, floats, bools)."""
        # a fresh constructor per value: a failed construction leaves a constructor's state dirty
        try:
            value = yaml.constructor.SafeConstructor().construct_object(node, deep=True)
        except yaml.YAMLError as err:
            self.report(path, f"cannot read value: {_yaml_reason(err)}", _line(node))
            return INVALID
        except (ValueError, OverflowError) as err:  # e.g. 2024-13-45, or an integer of 5,000 digits
            self.report(path, f"cannot read value: {err}", _line(node))
            return INVALID
        bad = _non_finite(value)
        if bad is not None:
            self.report(path, f"{bad} is not a finite number (.nan and .inf are refused everywhere)", _line(node))
            return INVALID
        return value


def _non_finite(value: Any) -> float | None:
    """The first NaN or infinity in a value read from the file (nested in lists and mappings too)."""
    if isinstance(value, float):
        return None if math.isfinite(value) else value
    items = value.values() if isinstance(value, dict) else value if isinstance(value, list) else ()
    return next((bad for bad in map(_non_finite, items) if bad is not None), None)


def _line(node: Node) -> int:
    return node.start_mark.line + 1


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path and key else path or key


def _leaf(path: str) -> str:
    """Last key name of a path (``racks[0].nodes[1].host`` -> ``host``)."""
    return re.sub(r"\[\d+\]$", "", path.rsplit(".", 1)[-1])


def _yaml_reason(err: yaml.YAMLError) -> str:
    """The parser's complaint, saying where the construct it was inside began."""
    if not isinstance(err, yaml.MarkedYAMLError):
        return str(err).splitlines()[0] if str(err) else type(err).__name__
    reason = err.problem or str(err)
    if err.context:
        where = err.context_mark
        started = f" started at line {where.line + 1}" if where and where is not err.problem_mark else ""
        reason += f" ({err.context}{started})"
    return reason


# --------------------------------------------------------------------------------------------
# schema introspection


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _yaml_fields(cls: type) -> dict[str, dataclasses.Field]:
    """Fields a file may set, in declaration order."""
    skip = LOADER_OWNED if cls is Topology else frozenset()
    return {f.name: f for f in dataclasses.fields(cls) if f.name not in skip}


_SCALARS = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}


def _describe_hint(hint: Any) -> str:
    """What a value of this type looks like, for "expected ..." messages."""
    inner, nullable = unwrap_optional(hint)
    origin = typing.get_origin(inner)
    if inner in _SCALARS:
        text = _SCALARS[inner]
    elif origin is Literal:
        text = "one of " + ", ".join(str(a) for a in typing.get_args(inner))
    elif origin in (typing.Union, types.UnionType):  # a scalar or a word, e.g. int | Literal["auto"]
        text = " or ".join(_describe_hint(a) for a in typing.get_args(inner))
    elif origin is tuple:
        text = f"a list (of {_describe_hint(typing.get_args(inner)[0])})"
    elif origin is dict or dataclasses.is_dataclass(inner):
        text = "a mapping"
    else:
        text = "a value"
    return f"{text} or null" if nullable else text


def _describe_node(node: Node) -> str:
    """What the file actually holds, quoting the text as written."""
    if isinstance(node, SequenceNode):
        return "a list"
    if isinstance(node, MappingNode):
        return "a mapping"
    kinds = {"null": "null", "bool": "boolean", "int": "integer", "float": "number", "str": "string", "timestamp": "date"}
    kind = kinds.get(node.tag.removeprefix(_TAG), node.tag)
    if kind == "null":
        return "null"
    if kind == "string":
        return f"string {show(node.value)}"
    return f"{kind} {cut(node.value)}"


# --------------------------------------------------------------------------------------------
# YAML nodes -> values: built dataclasses, or INVALID once a problem is reported


def _mismatch(node: Node, hint: Any, path: str, ctx: _Context, advice: str = "") -> Any:
    ctx.report(path, f"expected {_describe_hint(hint)}, got {_describe_node(node)}{advice}", _line(node))
    return INVALID


def _read(node: Node, hint: Any, path: str, ctx: _Context) -> Any:
    """Read ``node`` as a value of type ``hint``; report problems and return INVALID on failure."""
    inner, nullable = unwrap_optional(hint)
    if nullable and isinstance(node, ScalarNode) and node.tag == _TAG + "null":
        return None
    origin = typing.get_origin(inner)
    if inner is Any:
        return ctx.construct(node, path)
    if dataclasses.is_dataclass(inner):
        return _read_dataclass(node, hint, inner, path, ctx)
    if origin is tuple:
        return _read_tuple(node, hint, inner, path, ctx)
    if origin is dict:
        return _read_dict(node, hint, inner, path, ctx)
    if origin is Literal:
        return _read_literal(node, hint, inner, path, ctx)
    if origin in (typing.Union, types.UnionType):
        return _read_union(node, hint, inner, path, ctx)
    if inner in _SCALARS:
        return _read_scalar(node, hint, inner, path, ctx)
    raise TypeError(f"unsupported type in the topology schema at {path}: {hint!r}")


def _read_scalar(node: Node, hint: Any, kind: type, path: str, ctx: _Context) -> Any:
    if not isinstance(node, ScalarNode):
        return _mismatch(node, hint, path, ctx)
    value = ctx.construct(node, path)
    if value is INVALID:
        return INVALID
    # type(...) is, not isinstance: YAML true/false must not pass as the integers 1/0
    if type(value) is kind:
        return value
    if kind is float and type(value) is int:
        return float(value)
    written_as_exponent = node.style is None and isinstance(value, str) and _EXPONENT_FLOAT_RE.fullmatch(value)
    if kind is float and written_as_exponent:
        number = float(value.replace("_", ""))
        if math.isfinite(number):
            return number
        ctx.report(path, f"{cut(value)} is not a finite number (.nan and .inf are refused everywhere)", _line(node))
        return INVALID
    advice = ""
    if kind is int and written_as_exponent and float(value.replace("_", "")).is_integer():
        advice = f" (write integers out in full: {int(float(value.replace('_', '')))})"
    elif kind is str and value is not None:
        advice = " (quote it to make it a string)"
    return _mismatch(node, hint, path, ctx, advice)


def _read_union(node: Node, hint: Any, inner: Any, path: str, ctx: _Context) -> Any:
    """A scalar read as the first arm of the union that takes its YAML type (``int | Literal["auto"]``:
    an integer, else the word)."""
    if not isinstance(node, ScalarNode):
        return _mismatch(node, hint, path, ctx)
    value = ctx.construct(node, path)
    if value is INVALID:
        return INVALID
    for arm in typing.get_args(inner):
        if typing.get_origin(arm) is Literal:
            if any(type(value) is type(o) and value == o for o in typing.get_args(arm)):
                return value
        elif type(value) is arm:
            return _read(node, arm, path, ctx)
    return _mismatch(node, hint, path, ctx)


def _read_literal(node: Node, hint: Any, inner: Any, path: str, ctx: _Context) -> Any:
    options = typing.get_args(inner)
    if not isinstance(node, ScalarNode):
        return _mismatch(node, hint, path, ctx)
    value = ctx.construct(node, path)
    if value is INVALID:
        return INVALID
    if any(type(value) is type(o) and value == o for o in options):
        return value
    if isinstance(value, str):
        ctx.report(path, unknown_value(_leaf(path), value, [str(o) for o in options]), _line(node))
        return INVALID
    return _mismatch(node, hint, path, ctx)


def _read_tuple(node: Node, hint: Any, inner: Any, path: str, ctx: _Context) -> Any:
    args = typing.get_args(inner)
    if len(args) != 2 or args[1] is not Ellipsis:
        raise TypeError(f"only tuple[T, ...] is supported in the topology schema, got {inner!r}")
    if not isinstance(node, SequenceNode):
        return _mismatch(node, hint, path, ctx)
    items = []
    for i, item in enumerate(node.value):
        ctx.lines[f"{path}[{i}]"] = _line(item)
        items.append(_read(item, args[0], f"{path}[{i}]", ctx))
    return INVALID if any(v is INVALID for v in items) else tuple(items)


def _entries(node: MappingNode, path: str, ctx: _Context) -> Iterator[tuple[str, int, Node]]:
    """(key, key line, value node) of a mapping; non-string and repeated keys are reported."""
    first_seen: dict[str, int] = {}
    for key_node, value_node in node.value:
        key_line = _line(key_node)
        if key_node.tag == _TAG + "merge":
            ctx.report(path, "merge keys ('<<') are refused like anchors and aliases (write the keys out)", key_line)
            continue
        if not (isinstance(key_node, ScalarNode) and key_node.tag == _TAG + "str"):
            ctx.report(path, f"keys must be strings, got {_describe_node(key_node)}", key_line)
            continue
        key = key_node.value
        if key in first_seen:
            ctx.report(_join(path, key), f"duplicate key {show(key)} (first at line {first_seen[key]})", key_line)
            continue
        first_seen[key] = key_line
        ctx.lines[_join(path, key)] = key_line
        yield key, key_line, value_node


def _read_dict(node: Node, hint: Any, inner: Any, path: str, ctx: _Context) -> Any:
    key_type, value_type = typing.get_args(inner)
    if key_type is not str:
        raise TypeError(f"only dict[str, ...] is supported in the topology schema, got {inner!r}")
    if not isinstance(node, MappingNode):
        return _mismatch(node, hint, path, ctx)
    out = {key: _read(value_node, value_type, _join(path, key), ctx) for key, _key_line, value_node in _entries(node, path, ctx)}
    return INVALID if any(v is INVALID for v in out.values()) else out


def _unknown_key(key: str, accepted: typing.Iterable[str]) -> str:
    options = list(accepted)
    # two suggestions: typos often sit between two fields ('hostname': 'host' or 'name'?)
    close = difflib.get_close_matches(key, options, n=2)
    if close:
        return f"unknown key {show(key)} (did you mean {' or '.join(repr(c) for c in close)}?)"
    return f"unknown key {show(key)} (expected one of: {', '.join(options)})"


class _Unread(Exception):
    """A rule read a field the file got wrong (already reported): the rule is skipped."""


@functools.cache
def _partial_class(cls: type) -> type:
    """``cls`` for objects holding only the fields that could be read: reading another raises _Unread."""

    fields = {f.name for f in dataclasses.fields(cls)}

    def get(self: Any, name: str) -> Any:
        if name in fields and name not in object.__getattribute__(self, "__dict__"):
            raise _Unread(name)  # not the class attribute: that is the field's default
        return object.__getattribute__(self, name)

    return type(cls.__name__, (cls,), {"__getattribute__": get})


def _read_dataclass(node: Node, hint: Any, cls: type, path: str, ctx: _Context) -> Any:
    """The object a mapping describes: every key read and every field's rules applied (absent keys
    take their defaults), then the class's ``problems()`` and the checks against this machine.
    Where some field could not be read, the object is partial (see :func:`_partial_class`) and
    each rule that reads such a field, directly or in a nested object, stops there: the rules
    between fields never report what follows from a value already reported."""
    if not isinstance(node, MappingNode):
        return _mismatch(node, hint, path, ctx)
    accepted = _yaml_fields(cls)
    values: dict[str, Any] = {}
    for key, key_line, value_node in _entries(node, path, ctx):
        if key in accepted:
            values[key] = _read(value_node, _hints(cls)[key], _join(path, key), ctx)
        else:
            ctx.report(_join(path, key), _unknown_key(key, accepted), key_line)
    for name, f in accepted.items():
        if name in values:
            values[name] = _apply_rules(f, values[name], _join(path, name), ctx)
        elif f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING:
            default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
            values[name] = _apply_rules(f, default, _join(path, name), ctx)
        else:
            ctx.report(_join(path, name), f"missing required key {name!r}", ctx.line_of(path))
            values[name] = INVALID
    if all(v is not INVALID for v in values.values()):
        obj = cls(**values)
    else:
        obj = object.__new__(_partial_class(cls))
        for name, value in values.items():
            if value is not INVALID:
                object.__setattr__(obj, name, value)
    for rules in (getattr(cls, "problems", None), *_MACHINE_CHECKS.get(cls, ())):
        try:
            for key, message in rules(obj) if rules else ():
                ctx.report(_join(path, key), message)
        except _Unread:
            pass
    return obj


def _apply_rules(f: dataclasses.Field, value: Any, path: str, ctx: _Context) -> Any:
    """``value`` after the rules :func:`dvla.config.rule` put on field ``f`` (a path made
    absolute against the file's directory), or INVALID once the first broken one is reported."""
    meta = f.metadata
    if value is INVALID or value is None or not meta:
        return value
    problem, allowed = None, meta.get("range")
    if allowed is not None and type(value) in (int, float) and not allowed.holds(value):
        problem = f"{value!r} is out of range (expected {allowed.describe(f.name)})"
    elif "nonempty" in meta and not value.strip():
        problem = f"empty {f.name} (expected {meta['nonempty']})"
    else:
        if "path" in meta:
            value = os.path.abspath(os.path.join(ctx.base_dir, os.path.expanduser(value)))
            if meta["path"] and not os.path.isfile(value):
                problem = f"{meta['path']} not found: {value}"
        if problem is None and "check" in meta:
            problem = meta["check"](value)
    if problem is None:
        return value
    ctx.report(path, problem)
    return INVALID


# --------------------------------------------------------------------------------------------
# checks against this machine


def _user_policy_problems(task: TaskConfig) -> Problems:
    """A user policy ``module:Class`` is imported as the roles will import it, with the working
    directory on the path (``python -m`` puts it there): a typo or a missing dependency stops
    `dvla plan`/`dvla up` before anything starts instead of crashing every rollout."""
    if ":" not in task.policy:
        return
    module, _, attr = task.policy.partition(":")
    if not module or not attr.isidentifier():
        yield "policy", f"invalid policy {show(task.policy)} (expected 'module:Class', e.g. my_policy:SharedTrunkPolicy)"
        return
    cwd = os.getcwd()
    added = cwd not in sys.path and "" not in sys.path
    if added:
        sys.path.insert(0, cwd)
    try:
        found = getattr(importlib.import_module(module), attr, None)
    except (Exception, SystemExit) as err:  # whatever the module raises while it is imported
        yield "policy", f"cannot import policy {show(task.policy)}: {type(err).__name__}: {cut(str(err))}"
        return
    finally:
        if added:
            sys.path.remove(cwd)
    if not callable(found):
        yield "policy", f"policy {show(task.policy)}: module {show(module)} has no class {show(attr)}"


def _libero_assets_problems(task: TaskConfig) -> Problems:
    """LIBERO's assets from the environment when the topology names none."""
    if task.env != LIBERO_ENV or (task.libero is not None and task.libero.assets is not None):
        return
    path = os.environ.get(LIBERO_ASSETS_ENV)
    if not path:
        yield "libero.assets", (f"not set and {LIBERO_ASSETS_ENV} is empty (expected LIBERO's assets directory; "
                                f"{LIBERO_ASSETS_FIX})")
    elif problem := libero_assets_problem(os.path.abspath(os.path.expanduser(path))):
        yield "libero.assets", f"{LIBERO_ASSETS_ENV}: {problem}"


def _checkpoint_problems(topo: Topology) -> Problems:
    """A Hugging Face policy's checkpoint directory is checked here (files, dvla_policy.json,
    family; nothing is loaded), so a bad one is one line before anything starts. A path missing
    on this machine is left to the roles when some node is remote (it may exist only there)."""
    from dvla.learn.vla.checkpoint import FAMILIES, CheckpointError, check_checkpoint  # no torch: file checks only
    from dvla.learn.vla.lerobot_format import LEROBOT_FAMILIES, check_lerobot
    from dvla.learn.vla.openvla_format import OPENVLA_FAMILIES, check_openvla

    task = topo.task
    family = {policy: family for family, policy in FAMILIES.items()}.get(task.policy)
    if family is None and task.policy not in LEROBOT_FAMILIES + OPENVLA_FAMILIES:
        return
    path = task.policy_kwargs.get("checkpoint")
    if not isinstance(path, str) or not path:
        yield "task.policy_kwargs", (f"policy {task.policy!r} needs policy_kwargs.checkpoint: a local checkpoint "
                                     "directory (docs/policies.md)" + (" or a cached Hugging Face repo id"
                                                                       if family is None else ""))
        return
    if any(node.host not in LOCAL_HOSTS for _rack, node in topo.nodes()) and not os.path.exists(path):
        return
    try:
        kwargs = task.policy_kwargs
        if task.policy in OPENVLA_FAMILIES:  # a Prismatic directory, or a cached repo id
            check_openvla(path, task.policy, dataset=kwargs.get("dataset"), chunk_size=kwargs.get("chunk_size"))
        elif family is None:  # a LeRobot directory, or a Hugging Face repo id in the local cache
            check_lerobot(path, task.policy, tokenizer=kwargs.get("tokenizer"))
        else:
            check_checkpoint(path, family)
    except CheckpointError as err:
        yield "task.policy_kwargs.checkpoint", str(err)


def _percept_problems(topo: Topology) -> Problems:
    """tiny-vla's ``policy_kwargs.percept``: a perception file (``dvla/learn/vla/percept.py``) every
    role loads; its safetensors header is checked (``check_percept``; nothing is loaded). A path missing on this
    machine is left to the roles when some node is remote."""
    task = topo.task
    path = task.policy_kwargs.get("percept") if task.policy == "tiny-vla" else None
    if path is None:
        return
    key = "task.policy_kwargs.percept"
    if not isinstance(path, str) or not path:
        yield key, f"expected the path of a perception file (benchmarks/learn_vla.py pretrain), got {path!r}"
        return
    if any(node.host not in LOCAL_HOSTS for _rack, node in topo.nodes()) and not os.path.exists(path):
        return
    from dvla.learn.vla.checkpoint import CheckpointError, check_percept  # no torch: a header check

    try:
        check_percept(path)
    except CheckpointError as err:
        yield key, str(err)


def _remote_address_problems(topo: Topology) -> Problems:
    """With remote nodes, local nodes must bind where the remote ones can reach them (not loopback)."""
    placed = topo.placed()
    remote = next(((key, node) for key, node in placed if not is_local_host(node.host)), None)
    if remote is None or topo.emulate == "netns":  # netns with a remote host is a problem of its own
        return
    for key, node in placed:
        if is_local_host(node.host) and (node.address is None or node.address.startswith("127.")):
            yield f"{key}.address", (f"{show(node.address)} on a local node while {remote[0]}.host is remote "
                                     f"{show(remote[1].host)} (expected the address remote nodes reach this machine "
                                     "at; loopback is not reachable from them)")


_MACHINE_CHECKS: dict[type, tuple[Callable[[Any], Problems], ...]] = {
    TaskConfig: (_user_policy_problems, _libero_assets_problems),
    Topology: (_checkpoint_problems, _percept_problems, _remote_address_problems),
}


# --------------------------------------------------------------------------------------------
# entry points


class _Refused(yaml.MarkedYAMLError):
    """YAML a topology file may not use."""


class _Loader(yaml.SafeLoader):
    """SafeLoader refusing anchors and aliases (no topology needs them, and a few aliases make a
    small file stand for 10^9 values) and nesting deeper than MAX_DEPTH (PyYAML's composer
    recurses once per level: 10,000 nested lists would end in a RecursionError)."""

    depth = 0

    def compose_node(self, parent: Node | None, index: Any) -> Node:
        event = self.peek_event()
        if isinstance(event, AliasEvent) or getattr(event, "anchor", None):
            raise _Refused(None, None, "YAML anchors and aliases are refused (write the value out)", event.start_mark)
        if self.depth >= MAX_DEPTH:
            raise yaml.composer.ComposerError(
                None, None, f"nested deeper than {MAX_DEPTH} levels of lists and mappings", event.start_mark)
        self.depth += 1
        try:
            return super().compose_node(parent, index)
        finally:
            self.depth -= 1


def _compose(text: str, ctx: _Context) -> Node | None:
    if len(text) > MAX_FILE_BYTES:
        ctx.report("", f"{len(text)} characters, more than a topology needs (at most {MAX_FILE_BYTES})", 0)
        return None
    try:
        return yaml.compose(text, Loader=_Loader)
    except _Refused as err:
        ctx.report("<yaml>", err.problem, err.problem_mark.line + 1)
    except yaml.MarkedYAMLError as err:
        mark = err.problem_mark or err.context_mark
        ctx.report("<yaml>", f"invalid YAML: {_yaml_reason(err)}", mark.line + 1 if mark else 1)
    except yaml.YAMLError as err:
        ctx.report("<yaml>", f"invalid YAML: {_yaml_reason(err)}", 1)
    return None


def parse_topology(text: str, source: str = "<memory>") -> Topology:
    """Parse and validate topology YAML ``text`` read from ``source`` (used in messages).

    Relative paths in the file (``secret_file``, SSH keys, TLS files, LIBERO's assets) are resolved
    against the directory of ``source``. Raises :class:`TopologyError` listing every problem found.
    """
    ctx = _Context(source)
    root_node = _compose(text, ctx)
    topo: Any = INVALID
    if root_node is None and not ctx.problems:
        ctx.report("", "empty topology (expected a mapping with at least 'run' and 'racks')")
    elif root_node is not None:
        ctx.lines[""] = _line(root_node)
        topo = _read(root_node, Topology, "", ctx)
    if ctx.problems:
        raise TopologyError(sorted(ctx.problems, key=lambda p: p.line))
    if type(topo) is not Topology:
        raise RuntimeError(f"{source}: topology could not be built but no problem was reported")
    return dataclasses.replace(topo, source=source)


def load_topology(path: str | os.PathLike[str]) -> Topology:
    """Read and validate the topology file at ``path``; see :func:`parse_topology`."""
    source = os.fspath(path)
    try:
        with open(source, "rb") as f:
            data = f.read(MAX_FILE_BYTES + 1)
        if len(data) > MAX_FILE_BYTES:
            raise TopologyError([Problem(source, 0, "", f"file larger than {MAX_FILE_BYTES} bytes (a topology is"
                                                        " a few KiB; refused unread)")])
        text = data.decode("utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise TopologyError([Problem(source, 0, "", f"cannot read topology file: {_one_line(str(err), 200)}")]) from err
    return parse_topology(text, source)


def topology_to_dict(topo: Topology) -> dict[str, Any]:
    """The topology as plain dicts, lists and scalars, every default filled in (``source`` left out:
    the loader sets it)."""
    plain = json.loads(json.dumps(dataclasses.asdict(topo)))  # tuples become lists
    return {k: v for k, v in plain.items() if k not in LOADER_OWNED}


def dump_topology_yaml(topo: Topology) -> str:
    """YAML that :func:`parse_topology` reads back to an equal topology (given the same source)."""
    origin = " ".join(topo.source.split())
    header = f"# resolved topology of run {topo.run}, read from {origin}; every default filled in\n"
    body = yaml.safe_dump(topology_to_dict(topo), sort_keys=False, default_flow_style=False, allow_unicode=True)
    return header + body
