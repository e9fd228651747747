"""Topology files: YAML text in, a validated frozen :class:`dvla.config.Topology` out.

This module owns reading topology files, validating them against the schema declared in
:mod:`dvla.config` plus the semantic rules a runnable cluster needs, and writing a resolved
topology back to YAML (the copy kept in the run directory).

Validation never stops at the first problem: the whole file is walked and every problem is
reported as ``file:line: key.path: message``, so a user fixes a file in one pass. Parsing works on
the node graph of ``yaml.compose`` rather than on plain Python data because only nodes carry
line numbers. The schema walk is generic (dataclass fields and type hints), so a field added to
``dvla.config`` is accepted here without touching this file; only the semantic rules are listed
by hand.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import importlib
import ipaddress
import math
import os
import re
import sys
import types
import typing
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Literal, NamedTuple, Union

import yaml
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

from dvla.config import (
    LIBERO_ASSETS_ENV,
    LIBERO_ASSETS_FIX,
    LIBERO_ENV,
    LIBERO_SUITES,
    OBS_MODES,
    ROLE_KINDS,
    ROLE_LANES,
    BudgetConfig,
    EvalConfig,
    LiberoConfig,
    LinkConfig,
    SimulateConfig,
    NodeConfig,
    PPOConfig,
    RackConfig,
    ReplicationConfig,
    RolePlacement,
    SshConfig,
    TlsConfig,
    TaskConfig,
    Topology,
    WandbConfig,
    grpo_layout_problems,
    libero_assets_problem,
)

from ..fabric.keys import check_name
from .process import is_local_host

__all__ = [
    "Problem",
    "TopologyError",
    "load_topology",
    "parse_topology",
    "topology_to_dict",
    "dump_topology_yaml",
]

#: run ids become key expressions, directory and process names: keep them plain
RUN_ID_RE = re.compile(r"[a-z0-9][a-z0-9_-]{0,39}")
#: hosts that mean "this machine"
LOCAL_HOSTS = ("localhost", "127.0.0.1")
#: weight chunks below this waste per-message overhead; above it they stall the data plane
MIN_CHUNK_BYTES = 4096
MAX_CHUNK_BYTES = 64 << 20
#: Topology fields the loader fills in; a file may not set them
LOADER_OWNED = frozenset({"source"})

# A topology file is input like any other: these bound what reading one can cost.
#: largest file read (a topology of 1,000 nodes is ~100 KiB)
MAX_FILE_BYTES = 1 << 20
#: deepest nesting of lists and mappings (a topology needs ~10; PyYAML's composer recurses)
MAX_DEPTH = 64
#: most values in the document once aliases are expanded (a "billion laughs" file has 10^9)
MAX_VALUES = 100_000
#: longest value quoted back in a message
MAX_SHOWN = 80
#: most problems listed (the rest are counted in one last line)
MAX_PROBLEMS = 100

_TAG = "tag:yaml.org,2002:"
_NONE_TYPE = type(None)
#: plain scalars like ``3e-4`` are strings to YAML 1.1 but numbers to everyone writing them
_EXPONENT_FLOAT_RE = re.compile(r"[-+]?(?:\d[\d_]*\.?[\d_]*|\.\d[\d_]*)[eE][-+]?\d+")
#: host names: a DNS name or IPv4 address (labels of letters, digits, '_' and '-', none starting
#: with '-', at most 253 characters); IPv6 addresses are checked by :mod:`ipaddress`
_DNS_HOST_RE = re.compile(r"(?=.{1,253}$)[A-Za-z0-9_][A-Za-z0-9_-]{0,62}(?:\.[A-Za-z0-9_][A-Za-z0-9_-]{0,62})*\.?")
#: ssh login names: POSIX portable user names (plus a trailing '$' for machine accounts)
_SSH_USER_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}\$?")


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


class _Invalid:
    """Marks a value that could not be read (its problem is already reported)."""

    __slots__ = ()

    def __repr__(self) -> str:
        return "<invalid>"


INVALID: Any = _Invalid()


def _cut(text: str) -> str:
    """`text` cut to MAX_SHOWN characters for a message (a file may hold a huge value)."""
    return text if len(text) <= MAX_SHOWN else f"{text[:MAX_SHOWN - 3]}... ({len(text)} characters)"


def _show(value: Any) -> str:
    """``repr`` of a value from the file, for a message."""
    return _cut(repr(value))


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
            cut = max(path.rfind("."), path.rfind("["))
            path = path[:cut] if cut > 0 else ""
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
    return f"{path}.{key}" if path else key


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


def _unknown_value(what: str, value: str, options: typing.Sequence[str]) -> str:
    """``unknown role 'x' (expected a, b)``, with a suggestion when one is close."""
    close = difflib.get_close_matches(value, list(options), n=1)
    hint = f"did you mean {close[0]!r}? " if close else ""
    return f"unknown {what} {_show(value)} ({hint}expected {', '.join(options)})"


# --------------------------------------------------------------------------------------------
# schema introspection


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _yaml_fields(cls: type) -> dict[str, dataclasses.Field]:
    """Fields a file may set, in declaration order."""
    skip = LOADER_OWNED if cls is Topology else frozenset()
    return {f.name: f for f in dataclasses.fields(cls) if f.name not in skip}


def _unwrap_optional(hint: Any) -> tuple[Any, bool]:
    """``X | None`` -> (X, True); anything else -> (hint, False)."""
    if typing.get_origin(hint) not in (Union, types.UnionType):
        return hint, False
    rest = [a for a in typing.get_args(hint) if a is not _NONE_TYPE]
    if len(rest) != 1:
        raise TypeError(f"unsupported union in the topology schema: {hint!r}")
    return rest[0], True


def _describe_hint(hint: Any) -> str:
    """What a value of this type looks like, for "expected ..." messages."""
    inner, nullable = _unwrap_optional(hint)
    origin = typing.get_origin(inner)
    if inner is bool:
        text = "true or false"
    elif inner is int:
        text = "an integer"
    elif inner is float:
        text = "a number"
    elif inner is str:
        text = "a string"
    elif origin is Literal:
        text = "one of " + ", ".join(str(a) for a in typing.get_args(inner))
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
        return f"string {_show(node.value)}"
    return f"{kind} {_cut(node.value)}"


# --------------------------------------------------------------------------------------------
# YAML nodes -> partially validated values


@dataclass
class _Partial:
    """A dataclass mapping as read so far: the keys present (or defaulted) and their values.

    Semantic checks run on partials rather than on built dataclasses so that one bad field does
    not hide problems elsewhere in the same object.
    """

    cls: type
    path: str
    values: dict[str, Any]
    #: False when a required key is missing
    complete: bool = True

    def get(self, name: str) -> Any:
        """The value of a field: as read, else its default, else INVALID."""
        if name in self.values:
            return self.values[name]
        f = {f.name: f for f in dataclasses.fields(self.cls)}[name]
        if f.default is not dataclasses.MISSING:
            return f.default
        if f.default_factory is not dataclasses.MISSING:
            return f.default_factory()
        return INVALID

    def where(self, name: str) -> str:
        return _join(self.path, name)


def _mismatch(node: Node, hint: Any, path: str, ctx: _Context, advice: str = "") -> Any:
    ctx.report(path, f"expected {_describe_hint(hint)}, got {_describe_node(node)}{advice}", _line(node))
    return INVALID


def _convert(node: Node, hint: Any, path: str, ctx: _Context) -> Any:
    """Read ``node`` as a value of type ``hint``; report problems and return INVALID on failure."""
    inner, nullable = _unwrap_optional(hint)
    if nullable and isinstance(node, ScalarNode) and node.tag == _TAG + "null":
        return None
    origin = typing.get_origin(inner)
    if inner is Any:
        return ctx.construct(node, path)
    if dataclasses.is_dataclass(inner):
        return _convert_dataclass(node, hint, inner, path, ctx)
    if origin is tuple:
        return _convert_tuple(node, hint, inner, path, ctx)
    if origin is dict:
        return _convert_dict(node, hint, inner, path, ctx)
    if origin is Literal:
        return _convert_literal(node, hint, inner, path, ctx)
    if inner in (bool, int, float, str):
        return _convert_scalar(node, hint, inner, path, ctx)
    raise TypeError(f"unsupported type in the topology schema at {path}: {hint!r}")


def _convert_scalar(node: Node, hint: Any, kind: type, path: str, ctx: _Context) -> Any:
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
        ctx.report(path, f"{_cut(value)} is not a finite number (.nan and .inf are refused everywhere)", _line(node))
        return INVALID
    advice = ""
    if kind is int and written_as_exponent and float(value.replace("_", "")).is_integer():
        advice = f" (write integers out in full: {int(float(value.replace('_', '')))})"
    elif kind is str and value is not None:
        advice = " (quote it to make it a string)"
    return _mismatch(node, hint, path, ctx, advice)


def _convert_literal(node: Node, hint: Any, inner: Any, path: str, ctx: _Context) -> Any:
    options = typing.get_args(inner)
    if not isinstance(node, ScalarNode):
        return _mismatch(node, hint, path, ctx)
    value = ctx.construct(node, path)
    if value is INVALID:
        return INVALID
    if any(type(value) is type(o) and value == o for o in options):
        return value
    if isinstance(value, str):
        ctx.report(path, _unknown_value(_leaf(path), value, [str(o) for o in options]), _line(node))
        return INVALID
    return _mismatch(node, hint, path, ctx)


def _convert_tuple(node: Node, hint: Any, inner: Any, path: str, ctx: _Context) -> Any:
    args = typing.get_args(inner)
    if len(args) != 2 or args[1] is not Ellipsis:
        raise TypeError(f"only tuple[T, ...] is supported in the topology schema, got {inner!r}")
    if not isinstance(node, SequenceNode):
        return _mismatch(node, hint, path, ctx)
    items = []
    for i, item in enumerate(node.value):
        item_path = f"{path}[{i}]"
        ctx.lines[item_path] = _line(item)
        items.append(_convert(item, args[0], item_path, ctx))
    return tuple(items)


def _entries(node: MappingNode, path: str, ctx: _Context) -> Iterator[tuple[str, int, Node]]:
    """(key, key line, value node) of a mapping; non-string and repeated keys are reported.

    YAML merge keys (``<<: *defaults``) are honoured, so racks of similar nodes can share one
    anchored definition; keys written in the mapping itself win over merged ones.
    """
    first_seen: dict[str, int] = {}
    merged: list[tuple[str, int, Node]] = []
    for key_node, value_node in node.value:
        key_line = _line(key_node)
        if key_node.tag == _TAG + "merge":
            merged.extend(_merged_entries(value_node, path, ctx))
            continue
        if not (isinstance(key_node, ScalarNode) and key_node.tag == _TAG + "str"):
            ctx.report(path, f"keys must be strings, got {_describe_node(key_node)}", key_line)
            continue
        key = key_node.value
        if key in first_seen:
            ctx.report(_join(path, key), f"duplicate key {_show(key)} (first at line {first_seen[key]})", key_line)
            continue
        first_seen[key] = key_line
        yield key, key_line, value_node
    for key, key_line, value_node in merged:
        if key not in first_seen:
            first_seen[key] = key_line
            yield key, key_line, value_node


def _merged_entries(source: Node, path: str, ctx: _Context) -> list[tuple[str, int, Node]]:
    """Entries a ``<<`` key brings in: from a mapping, or from a list of them (earlier wins)."""
    sources = source.value if isinstance(source, SequenceNode) else [source]
    entries: list[tuple[str, int, Node]] = []
    for mapping in sources:
        if not isinstance(mapping, MappingNode):
            message = f"'<<' expects a mapping or a list of mappings, got {_describe_node(mapping)}"
            ctx.report(path, message, _line(mapping))
            continue
        entries.extend(_entries(mapping, path, ctx))
    return entries


def _convert_dict(node: Node, hint: Any, inner: Any, path: str, ctx: _Context) -> Any:
    key_type, value_type = typing.get_args(inner)
    if key_type is not str:
        raise TypeError(f"only dict[str, ...] is supported in the topology schema, got {inner!r}")
    if not isinstance(node, MappingNode):
        return _mismatch(node, hint, path, ctx)
    out = {}
    for key, key_line, value_node in _entries(node, path, ctx):
        ctx.lines[_join(path, key)] = key_line
        out[key] = _convert(value_node, value_type, _join(path, key), ctx)
    return INVALID if any(v is INVALID for v in out.values()) else out


def _unknown_key(key: str, accepted: typing.Iterable[str]) -> str:
    options = list(accepted)
    # two suggestions: typos often sit between two fields ('hostname': 'host' or 'name'?)
    close = difflib.get_close_matches(key, options, n=2)
    if close:
        return f"unknown key {_show(key)} (did you mean {' or '.join(repr(c) for c in close)}?)"
    return f"unknown key {_show(key)} (expected one of: {', '.join(options)})"


def _convert_dataclass(node: Node, hint: Any, cls: type, path: str, ctx: _Context) -> Any:
    if not isinstance(node, MappingNode):
        return _mismatch(node, hint, path, ctx)
    accepted = _yaml_fields(cls)
    partial = _Partial(cls, path, {})
    for key, key_line, value_node in _entries(node, path, ctx):
        if key not in accepted:
            ctx.report(_join(path, key), _unknown_key(key, accepted), key_line)
            continue
        ctx.lines[_join(path, key)] = key_line
        partial.values[key] = _convert(value_node, _hints(cls)[key], _join(path, key), ctx)
    _fill_absent(partial, accepted, ctx)
    return partial


def _fill_absent(partial: _Partial, accepted: dict[str, dataclasses.Field], ctx: _Context) -> None:
    """Report missing required keys; expand absent nested dataclasses so they get checked too."""
    for name, f in accepted.items():
        if name in partial.values:
            continue
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            ctx.report(partial.where(name), f"missing required key {name!r}", ctx.line_of(partial.path))
            partial.complete = False
            continue
        default = partial.get(name)
        if dataclasses.is_dataclass(default):
            partial.values[name] = _partial_of(default, partial.where(name))


def _partial_of(value: Any, path: str) -> Any:
    """A default dataclass instance as a partial (so defaults go through the same checks)."""
    if dataclasses.is_dataclass(value):
        fields = _yaml_fields(type(value))
        return _Partial(type(value), path, {n: _partial_of(getattr(value, n), _join(path, n)) for n in fields})
    if isinstance(value, tuple):
        return tuple(_partial_of(v, f"{path}[{i}]") for i, v in enumerate(value))
    return value


# --------------------------------------------------------------------------------------------
# partials -> frozen dataclasses


def _build(value: Any, ctx: _Context) -> Any:
    """Instantiate partials bottom-up; every subtree is built so each reports its own errors."""
    if isinstance(value, _Partial):
        kwargs = {name: _build(v, ctx) for name, v in value.values.items()}
        if not value.complete or any(v is INVALID for v in kwargs.values()):
            return INVALID
        try:
            return value.cls(**kwargs)
        except ValueError as err:
            ctx.report(_blamed_field(value, str(err)), str(err))
            return INVALID
    if isinstance(value, tuple):
        items = tuple(_build(v, ctx) for v in value)
        return INVALID if any(v is INVALID for v in items) else items
    return value


def _blamed_field(partial: _Partial, message: str) -> str:
    """Path of the field a ``__post_init__`` message names first, else of the mapping itself."""
    best: tuple[int, str] | None = None
    for name in partial.values:
        found = re.search(rf"\b{re.escape(name)}\b", message)
        if found and (best is None or found.start() < best[0]):
            best = (found.start(), name)
    return partial.where(best[1]) if best else partial.path


# --------------------------------------------------------------------------------------------
# semantic checks


class _Range(NamedTuple):
    """Allowed numeric range of a field: above `low` (or equal unless `low_open`), at most `high`."""

    low: float
    high: float | None = None
    low_open: bool = False
    note: str = ""


def _describe_range(name: str, r: _Range) -> str:
    if r.high is None:
        text = f"{name} {'>' if r.low_open else '>='} {r.low}"
    else:
        text = f"{name} in {'(' if r.low_open else '['}{r.low}, {r.high}]"
    return text + (f" {r.note}" if r.note else "")


_AT_LEAST_1 = _Range(low=1)
_AT_LEAST_0 = _Range(low=0)
_POSITIVE = _Range(low=0, low_open=True)
_FRACTION = _Range(low=0, high=1, low_open=True)

#: numeric ranges, per schema class and field (None values are skipped: None means "off")
_RANGES: dict[type, dict[str, _Range]] = {
    Topology: {"base_port": _Range(low=1024, high=65000)},
    TaskConfig: {
        "envs_per_rollout": _AT_LEAST_1, "chunk_steps": _AT_LEAST_1, "max_episode_steps": _AT_LEAST_1,
        # vision-language observations and GRPO
        "image_size": _Range(low=8, high=1024), "instruction_tokens": _Range(low=1, high=512),
        "action_chunk": _AT_LEAST_1, "group_size": _AT_LEAST_1,
        "grpo_gamma": _Range(low=0, high=1, low_open=True), "grpo_std_floor": _AT_LEAST_0,
    },
    PPOConfig: {
        "gae_lambda": _Range(low=0, high=1),
        "lr": _POSITIVE,
        "clip": _POSITIVE,
        "update_epochs": _AT_LEAST_1,
        "minibatches": _AT_LEAST_1,
        "batch_steps": _AT_LEAST_1,
        "ent_coef": _AT_LEAST_0,
        "vf_coef": _AT_LEAST_0,
        "max_grad_norm": _POSITIVE,
        "target_kl": _POSITIVE,
        "max_policy_lag": _AT_LEAST_0,
    },
    EvalConfig: {"episodes": _AT_LEAST_1, "every_versions": _AT_LEAST_1, "seed_offset": _AT_LEAST_0, "envs": _AT_LEAST_1},
    BudgetConfig: {
        "max_env_steps": _AT_LEAST_1,
        "until_success": _FRACTION,
        "consecutive": _AT_LEAST_1,
        "max_wall_s": _POSITIVE,
    },
    ReplicationConfig: {
        "topk_fraction": _FRACTION,
        "snapshot_every": _AT_LEAST_1,
        "fanout": _AT_LEAST_1,
        "relay_fanout": _AT_LEAST_1,
        "chunk_bytes": _Range(low=MIN_CHUNK_BYTES, high=MAX_CHUNK_BYTES, note="(4 KiB to 64 MiB)"),
    },
    LinkConfig: {"node_gbit": _POSITIVE, "rack_uplink_gbit": _POSITIVE},
    SimulateConfig: {
        "nodes": _AT_LEAST_1, "racks": _AT_LEAST_1, "params": _AT_LEAST_1, "trainable_fraction": _FRACTION,
        "env_steps_per_s": _POSITIVE, "step_bytes": _POSITIVE, "learner_steps_per_s": _POSITIVE,
        "node_memory_gib": _POSITIVE, "hop_latency_s": _AT_LEAST_0, "process_gbit": _POSITIVE,
    },
    RolePlacement: {"count": _AT_LEAST_1},
    SshConfig: {"port": _Range(low=1, high=65535), "connect_timeout_s": _AT_LEAST_1},
    WandbConfig: {"init_timeout_s": _Range(low=0, high=600, low_open=True),
                  "finish_timeout_s": _Range(low=0, high=600, low_open=True)},
}


def _check_ranges(p: _Partial, ctx: _Context) -> None:
    for name, allowed in _RANGES.get(p.cls, {}).items():
        v = p.get(name)
        if type(v) not in (int, float):
            continue
        # (NaN and infinities never get here: reading the file refuses them)
        above = v > allowed.low if allowed.low_open else v >= allowed.low
        if not (above and (allowed.high is None or v <= allowed.high)):
            ctx.report(p.where(name), f"{v!r} is out of range (expected {_describe_range(name, allowed)})")


def _check_run_id(p: _Partial, ctx: _Context) -> None:
    run = p.get("run")
    if isinstance(run, str) and not RUN_ID_RE.fullmatch(run):
        ctx.report(
            p.where("run"),
            f"invalid run id {_show(run)} (expected 1 to 40 of a-z, 0-9, '_', '-', starting with a letter or digit)",
        )


def _placed_nodes(topo: _Partial) -> tuple[list[_Partial], bool]:
    """Every readable node, and whether every rack and node could be read."""
    racks = topo.get("racks")
    if not isinstance(racks, tuple):
        return [], False
    nodes: list[_Partial] = []
    complete = True
    for rack in racks:
        rack_nodes = rack.get("nodes") if isinstance(rack, _Partial) else INVALID
        if not isinstance(rack_nodes, tuple):
            complete = False
            continue
        for node in rack_nodes:
            if isinstance(node, _Partial):
                nodes.append(node)
            else:
                complete = False
    return nodes, complete


def _check_unique_names(items: typing.Iterable[Any], what: str, ctx: _Context) -> None:
    first_line: dict[str, int] = {}
    for item in items:
        name = item.get("name") if isinstance(item, _Partial) else INVALID
        if not isinstance(name, str):
            continue
        if name in first_line:
            ctx.report(item.where("name"), f"duplicate {what} name {_show(name)} (first at line {first_line[name]})")
        else:
            first_line[name] = ctx.line_of(item.where("name"))


def _check_names(p: _Partial, ctx: _Context) -> None:
    racks = p.get("racks")
    if isinstance(racks, tuple):
        _check_unique_names(racks, "rack", ctx)
    # node names are unique across racks: process names and keys are derived from them
    _check_unique_names(_placed_nodes(p)[0], "node", ctx)


def _key_chunk_problem(what: str, value: str) -> str | None:
    """Why `value` cannot be one Zenoh key chunk (see dvla.fabric.keys.check_name), or None."""
    try:
        check_name(what, value)
    except ValueError:
        return (f"invalid {what} {_show(value)} (expected 1 to 64 of letters, digits, '_', '.', '-', starting with"
                " a letter or digit: it becomes part of key expressions and process names)")
    return None


def _check_key_name(p: _Partial, ctx: _Context) -> None:
    """Rack and node names: one key chunk each, and so are the process names made from them."""
    name = p.get("name")
    if not isinstance(name, str):
        return
    what = "rack name" if p.cls is RackConfig else "node name"
    problem = _key_chunk_problem(what, name)
    if problem is None and p.cls is NodeConfig:  # processes are named <role>-<node>-<index>
        counts = _role_counts(p) or {}
        longest = max((f"{kind}-{name}-{n - 1}" for kind, n in counts.items()), key=len, default="")
        if longest and _key_chunk_problem("process name", longest):
            problem = f"node name {_show(name)} makes process name {_show(longest)} longer than 64 characters"
    if problem:
        ctx.report(p.where("name"), problem)


def _check_has_racks(p: _Partial, ctx: _Context) -> None:
    if p.get("racks") == ():
        ctx.report(p.where("racks"), "no racks (expected at least one rack with an actor and a rollout)")


def _check_required_roles(p: _Partial, ctx: _Context) -> None:
    nodes, complete = _placed_nodes(p)
    kinds: set[str] = set()
    for node in nodes:
        roles = node.get("roles")
        if not isinstance(roles, tuple):
            complete = False
            continue
        for placement in roles:
            kind = placement.get("role") if isinstance(placement, _Partial) else INVALID
            if isinstance(kind, str):
                kinds.add(kind)
            else:
                complete = False
    # an unreadable role might have been the actor: only claim absence when everything was read;
    # an empty topology is reported once, by the rack and node checks
    if not complete or not nodes:
        return
    for required in ("actor", "rollout"):
        if required not in kinds:
            ctx.report(p.where("racks"), f"no {required} placed (expected at least one node with role {required})")


def _check_eval_shards(p: _Partial, ctx: _Context) -> None:
    """Each evaluator plays a block of every evaluation's episodes: no more evaluators than episodes."""
    task = p.get("task")
    ev = task.get("eval") if isinstance(task, _Partial) else None
    episodes = ev.get("episodes") if isinstance(ev, _Partial) else EvalConfig().episodes
    if type(episodes) is not int:
        return
    evaluators = sum((_role_counts(node) or {}).get("evaluator", 0) for node in _placed_nodes(p)[0])
    if evaluators > episodes:
        ctx.report(p.where("racks"), f"{evaluators} evaluators but task.eval.episodes is {episodes} "
                                     "(each evaluator plays a block of every evaluation's episodes: place at most that many)")


def _check_policy_checkpoint(p: _Partial, ctx: _Context) -> None:
    """A Hugging Face policy's checkpoint directory is checked here (files, dvla_policy.json,
    family; nothing is loaded), so a bad one is one line before anything starts. A path missing
    on this machine is left to the roles when some node is remote (it may exist only there)."""
    task = p.get("task")
    if not isinstance(task, _Partial):
        return
    policy, kwargs = task.get("policy"), task.get("policy_kwargs")
    family = _CHECKPOINT_FAMILY.get(policy) if isinstance(policy, str) else None
    if family is None:
        return
    where = task.where("policy_kwargs")
    path = kwargs.get("checkpoint") if isinstance(kwargs, (dict, _Partial)) else None
    if not isinstance(path, str) or not path:
        ctx.report(where, f"policy {policy!r} needs policy_kwargs.checkpoint: a local checkpoint directory (docs/policies.md)")
        return
    from dvla.learn.vla.checkpoint import CheckpointError, check_checkpoint  # no torch: file checks only

    remote = any(isinstance(n.get("host"), str) and n.get("host") not in LOCAL_HOSTS for n in _placed_nodes(p)[0])
    if remote and not os.path.exists(path):
        return
    try:
        check_checkpoint(path, family)
    except CheckpointError as err:
        ctx.report(f"{where}.checkpoint", str(err))


def _check_netns_hosts(p: _Partial, ctx: _Context) -> None:
    if p.get("emulate") != "netns":
        return
    for node in _placed_nodes(p)[0]:
        host = node.get("host")
        if isinstance(host, str) and host not in LOCAL_HOSTS:
            ctx.report(
                node.where("host"),
                f"remote host {_show(host)} with emulate: netns (netns emulation runs every node on this machine;"
                f" expected {' or '.join(LOCAL_HOSTS)})",
            )


# --- vision-language observations and GRPO ---------------------------------------------------

#: registered policies and the observations they read (user "module:Class" policies: any)
_POLICY_OBS = {"mlp": "state", "tiny-vla": "rgb", "vla-tokens": "rgb", "vla-flow": "rgb"}
#: policies loaded from a Hugging Face checkpoint directory -> the family dvla_policy.json names
_CHECKPOINT_FAMILY = {"vla-tokens": "tokens", "vla-flow": "flow"}


def _check_obs_and_policy(p: _Partial, ctx: _Context) -> None:
    env, obs_mode, policy = p.get("env"), p.get("obs_mode"), p.get("policy")
    if isinstance(obs_mode, str) and isinstance(env, str) and ":" not in env and obs_mode not in OBS_MODES:
        ctx.report(p.where("obs_mode"), _unknown_value("obs_mode", obs_mode, OBS_MODES))
    if isinstance(policy, str) and ":" not in policy and policy not in _POLICY_OBS:
        ctx.report(p.where("policy"), _unknown_value("policy", policy, (*_POLICY_OBS, "module:Class")))
        return
    if isinstance(policy, str) and ":" in policy:
        problem = _user_class_problem(policy)
        if problem:
            ctx.report(p.where("policy"), problem)
        return
    wanted = _POLICY_OBS.get(policy) if isinstance(policy, str) else None
    if wanted and isinstance(obs_mode, str) and obs_mode in OBS_MODES and obs_mode != wanted:
        ctx.report(p.where("policy"), f"policy {policy!r} reads {wanted!r} observations, but obs_mode is {obs_mode!r}")


def _user_class_problem(spec: str) -> str | None:
    """Why the user policy ``module:Class`` cannot be imported here, or None.

    The module is imported as the roles will import it, with the working directory on the path
    (``python -m`` puts it there): a typo or a missing dependency stops `dvla plan`/`dvla up`
    before anything starts instead of crashing every rollout."""
    module, _, attr = spec.partition(":")
    if not module or not attr.isidentifier():
        return f"invalid policy {_show(spec)} (expected 'module:Class', e.g. my_policy:SharedTrunkPolicy)"
    cwd = os.getcwd()
    added = cwd not in sys.path and "" not in sys.path
    if added:
        sys.path.insert(0, cwd)
    try:
        found = getattr(importlib.import_module(module), attr, None)
    except (Exception, SystemExit) as err:  # whatever the module raises while it is imported
        return f"cannot import policy {_show(spec)}: {type(err).__name__}: {_cut(str(err))}"
    finally:
        if added:
            sys.path.remove(cwd)
    if not callable(found):
        return f"policy {_show(spec)}: module {_show(module)} has no class {_show(attr)}"
    return None


def _check_grpo(p: _Partial, ctx: _Context) -> None:
    names = ("algorithm", "group_size", "chunk_steps", "max_episode_steps", "action_chunk", "envs_per_rollout")
    values = {n: p.get(n) for n in names}
    if values["algorithm"] != "grpo" or any(type(values[n]) is not int or values[n] < 1 for n in names[1:]):
        return
    for key, message in grpo_layout_problems(types.SimpleNamespace(**values)):
        ctx.report(p.where(key), message)


_SIM_BACKENDS = ("auto", "physx_cpu", "physx_cuda")


def _check_env_batching(p: _Partial, ctx: _Context) -> None:
    """``sim_backend`` is one ManiSkill knows; ``env_batching: scene`` only where one scene of the
    rollout's envs can be built and played (dvla/learn/envs.py: sim_layout)."""
    backend = p.get("sim_backend")
    if isinstance(backend, str) and backend not in _SIM_BACKENDS:
        ctx.report(p.where("sim_backend"), f"{_show(backend)} is not one of {', '.join(_SIM_BACKENDS)}")
    if p.get("env_batching") != "scene":
        return
    env, n = p.get("env"), p.get("envs_per_rollout")
    fix = "set env_batching: auto (or loop)"
    if env == LIBERO_ENV:
        ctx.report(p.where("env_batching"), f"scene: LIBERO's envs are separate MuJoCo simulators, one per env; {fix}")
    elif backend == "physx_cpu" and type(n) is int and n > 1 and isinstance(env, str) and ":" not in env:
        ctx.report(p.where("env_batching"),
                   f"scene: ManiSkill puts {n} envs (envs_per_rollout) in one scene only on physx_cuda, and "
                   f"sim_backend is physx_cpu; set sim_backend: physx_cuda (or auto on CUDA nodes), or {fix}")
    if p.get("algorithm") == "grpo":
        ctx.report(p.where("env_batching"),
                   f"scene: algorithm grpo needs group_size envs per seeded initial state, which one scene does not give; {fix}")
    chunk = p.get("action_chunk")
    if type(chunk) is int and chunk > 1:
        ctx.report(p.where("env_batching"),
                   f"scene: one scene plays one simulator step per transition, and action_chunk is {chunk}; {fix}")


# --- LIBERO -----------------------------------------------------------------------------------


def _check_libero_task(p: _Partial, ctx: _Context) -> None:
    """``env: libero`` reads images (obs_mode rgb); ``task.libero`` goes with it and nothing else."""
    env, libero = p.get("env"), p.get("libero")
    if env != LIBERO_ENV:
        if isinstance(libero, _Partial) and isinstance(env, str):
            ctx.report(p.where("libero"), f"set, but task.env is {_show(env)} (expected env: {LIBERO_ENV} to run "
                                          "LIBERO tasks, or no libero section)")
        return
    obs_mode = p.get("obs_mode")
    if isinstance(obs_mode, str) and obs_mode != "rgb":
        ctx.report(p.where("obs_mode"), f"{obs_mode!r} with env {LIBERO_ENV} (expected rgb: LIBERO's observations are "
                                        "camera images and proprioception)")
    if libero is None:  # LiberoConfig's defaults: assets from the environment
        problem = _libero_assets_from_env()
        if problem:
            ctx.report(_join(p.path, "libero.assets"), problem)


def _libero_assets_from_env() -> str | None:
    path = os.environ.get(LIBERO_ASSETS_ENV)
    if not path:
        return f"not set and {LIBERO_ASSETS_ENV} is empty (expected LIBERO's assets directory; {LIBERO_ASSETS_FIX})"
    problem = libero_assets_problem(os.path.abspath(os.path.expanduser(path)))
    return f"{LIBERO_ASSETS_ENV}: {problem}" if problem else None


def _check_libero(p: _Partial, ctx: _Context) -> None:
    """Task ids of the suite, each once; the assets directory (relative to the file) exists."""
    suite, ids = p.get("suite"), p.get("task_ids")
    n = LIBERO_SUITES.get(suite) if isinstance(suite, str) else None
    if ids == ():
        ctx.report(p.where("task_ids"), "empty list (expected task ids of the suite, or null for every task)")
    first: dict[int, int] = {}
    for i, t in enumerate(ids if isinstance(ids, tuple) else ()):
        if type(t) is not int:
            continue
        where = f"{p.where('task_ids')}[{i}]"
        if n is not None and not 0 <= t < n:
            ctx.report(where, f"unknown task id {t} in {suite} (expected 0 .. {n - 1})")
        elif t in first:
            ctx.report(where, f"duplicate task id {t} (already at task_ids[{first[t]}])")
        else:
            first[t] = i
    assets = p.get("assets")
    if isinstance(assets, str) and assets.strip():
        resolved = os.path.abspath(os.path.join(ctx.base_dir, os.path.expanduser(assets)))
        p.values["assets"] = resolved
        problem = libero_assets_problem(resolved)
    elif assets is None:
        problem = _libero_assets_from_env()
    else:
        return
    if problem:
        ctx.report(p.where("assets"), problem)


def _check_stop_condition(p: _Partial, ctx: _Context) -> None:
    limits = ("max_env_steps", "until_success", "max_wall_s")
    values = [p.get(name) for name in limits]
    if all(v is None for v in values):
        ctx.report(p.path, f"no stop condition (expected at least one of {', '.join(limits)} to be set)")


def _check_rack_nodes(p: _Partial, ctx: _Context) -> None:
    if p.get("nodes") == ():
        ctx.report(p.where("nodes"), "rack has no nodes (expected at least one node)")


def _check_node_roles(p: _Partial, ctx: _Context) -> None:
    roles = p.get("roles")
    if roles == ():
        ctx.report(p.where("roles"), f"node has no roles (expected at least one of {', '.join(ROLE_KINDS)})")
        return
    if not isinstance(roles, tuple):
        return
    # a replicator is the node's single entry point of the weight tree; two would split it
    replicators = 0
    for placement in roles:
        if not (isinstance(placement, _Partial) and placement.get("role") == "replicator"):
            continue
        count = placement.get("count")
        replicators += count if type(count) is int else 1
        if replicators > 1:
            ctx.report(placement.path, f"at most one replicator per node, this node places {replicators}")
            return


def _check_cpus(p: _Partial, ctx: _Context) -> None:
    _check_cpu_list(p.get("cpus"), p.where("cpus"), ctx)


def _check_cpu_list(cpus: Any, where: str, ctx: _Context) -> None:
    if not isinstance(cpus, tuple):
        return
    if not cpus:
        ctx.report(where, "empty cpu list (expected at least one core index, or null for no pinning)")
    first_index: dict[int, int] = {}
    for i, cpu in enumerate(cpus):
        path = f"{where}[{i}]"
        if type(cpu) is not int:
            continue
        if cpu < 0:
            ctx.report(path, f"negative cpu index {cpu} (expected >= 0)")
        elif cpu in first_index:
            ctx.report(path, f"duplicate cpu {cpu} (already listed at {_leaf(where)}[{first_index[cpu]}])")
        else:
            first_index[cpu] = i


def _check_lane_cpus(p: _Partial, ctx: _Context) -> None:
    """``lane_cpus`` names lanes the role has, each with a valid cpu list."""
    lanes = p.get("lane_cpus")
    if not isinstance(lanes, dict):
        return
    role = p.get("role")
    known = ROLE_LANES.get(role) if isinstance(role, str) else None
    for lane, cpus in lanes.items():
        where = _join(p.where("lane_cpus"), lane)
        if known is not None and lane not in known:
            ctx.report(where, _unknown_value(f"{role} lane", lane, known))
        _check_cpu_list(cpus, where, ctx)


# --- remote nodes (SSH) -----------------------------------------------------------------------


def _is_remote(host: Any) -> bool:
    """A valid host that is not this machine (its roles start over SSH); an invalid one is
    reported on its own."""
    return isinstance(host, str) and bool(host.strip()) and not is_local_host(host) and host_problem(host) is None


def _check_remote_addresses(p: _Partial, ctx: _Context) -> None:
    """With remote nodes, local nodes must bind where the remote ones can reach them (not loopback)."""
    nodes = _placed_nodes(p)[0]
    remote = next((n for n in nodes if _is_remote(n.get("host"))), None)
    if remote is None or p.get("emulate") == "netns":  # netns with a remote host is reported elsewhere
        return
    for node in nodes:
        if _is_remote(node.get("host")):
            continue
        address = node.get("address")
        if address is None or (isinstance(address, str) and address.startswith("127.")):
            ctx.report(
                node.where("address"),
                f"{_show(address)} on a local node while {remote.where('host')} is remote {_show(remote.get('host'))}"
                " (expected the address remote nodes reach this machine at; loopback is not reachable from them)",
            )


def host_problem(host: str) -> str | None:
    """Why `host` cannot name a node (it ends up on ssh's command line), or None when it can: a
    DNS name, an IPv4 address or an IPv6 address (bare or in brackets); never a leading '-'."""
    bare = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if ":" in bare:
        try:
            ipaddress.IPv6Address(bare)
            return None
        except ValueError:
            return f"invalid host {_show(host)} (not an IPv6 address)"
    if bare == host and _DNS_HOST_RE.fullmatch(host):
        return None
    at = "; the login user goes in ssh.user" if "@" in host else ""
    return (f"invalid host {_show(host)} (expected a DNS name or an IP address: letters, digits, '.', '_', '-',"
            f" no label starting with '-'{at})")


def _check_host(p: _Partial, ctx: _Context) -> None:
    for name in ("host", "address"):  # the address ends up in Zenoh locators: no room for extras
        value = p.get(name)
        if isinstance(value, str) and value.strip():  # empty: reported with the other empty strings
            problem = host_problem(value)
            if problem:
                ctx.report(p.where(name), problem.replace("invalid host", f"invalid {name}", 1))


def _check_ssh(p: _Partial, ctx: _Context) -> None:
    user = p.get("user")
    if isinstance(user, str) and not _SSH_USER_RE.fullmatch(user):
        ctx.report(p.where("user"), f"invalid user {_show(user)} (expected a login name: letters, digits, '_', '.',"
                                    " '-', not starting with '-'; no '@', ':' or spaces)")
    for name in ("python", "workdir", "identity_file", "known_hosts_file"):
        value = p.get(name)
        if isinstance(value, str) and not value.isprintable():
            ctx.report(p.where(name), f"{_show(value)} holds control characters (expected a plain path)")


def _check_tls(p: _Partial, ctx: _Context) -> None:
    planes = p.get("planes")
    if isinstance(planes, tuple):
        if not planes:
            ctx.report(p.where("planes"), "empty planes (expected ctrl, data or both; or drop the tls section)")
        else:
            named = [x for x in planes if isinstance(x, str)]
            if len(set(named)) != len(named):
                ctx.report(p.where("planes"), f"repeated plane in {named}")


#: characters W&B refuses in project names
_WANDB_PROJECT_FORBIDDEN = "/\\#?%:"
#: longest W&B tag
_WANDB_TAG_MAX = 64


def _check_wandb(p: _Partial, ctx: _Context) -> None:
    project = p.get("project")
    if isinstance(project, str) and any(c in project for c in _WANDB_PROJECT_FORBIDDEN):
        ctx.report(p.where("project"), f"invalid W&B project {_show(project)} (no {' '.join(_WANDB_PROJECT_FORBIDDEN)})")
    tags = p.get("tags")
    for i, tag in enumerate(tags if isinstance(tags, tuple) else ()):
        if isinstance(tag, str) and not 1 <= len(tag.strip()) <= _WANDB_TAG_MAX:
            ctx.report(f"{p.where('tags')}[{i}]", f"invalid W&B tag {_show(tag)} (expected 1 to {_WANDB_TAG_MAX} characters)")


def _role_counts(node: _Partial) -> dict[str, int] | None:
    """role kind -> processes placed on `node` (None when a placement could not be read)."""
    roles = node.get("roles")
    if not isinstance(roles, tuple):
        return None
    counts: dict[str, int] = {}
    for placement in roles:
        kind = placement.get("role") if isinstance(placement, _Partial) else INVALID
        count = placement.get("count") if isinstance(placement, _Partial) else INVALID
        if not isinstance(kind, str) or type(count) is not int:
            return None
        counts[kind] = counts.get(kind, 0) + count
    return counts


def _check_learners(p: _Partial, ctx: _Context) -> None:
    """The learner group's ratio holds on every node (or over the run); nccl needs CUDA."""
    group, task = p.get("learners"), p.get("task")
    if not isinstance(group, _Partial):
        return
    if group.get("backend") == "nccl" and isinstance(task, _Partial) and task.get("device") == "cpu":
        ctx.report(group.where("backend"), "nccl needs CUDA but task.device is 'cpu' (expected gloo or auto)")
    ratio = group.get("ratio")
    if not isinstance(ratio, str):
        return
    m = re.fullmatch(r"\s*([1-9][0-9]*)\s*:\s*([1-9][0-9]*)\s*", ratio)
    if m is None:
        ctx.report(group.where("ratio"), f"{_show(ratio)} is not a rollout:learner ratio (expected e.g. '3:1' or '1:1')")
        return
    want = (int(m[1]), int(m[2]))
    nodes, complete = _placed_nodes(p)
    counted = [(node, _role_counts(node)) for node in nodes]
    if not complete or any(c is None for _n, c in counted):
        return
    if group.get("ratio_per") == "run":
        counted = [(p, {k: sum(c.get(k, 0) for _n, c in counted) for k in ("rollout", "actor")})]  # type: ignore[union-attr]
    for where, c in counted:
        rollouts, actors = c.get("rollout", 0), c.get("actor", 0)  # type: ignore[union-attr]
        if (rollouts or actors) and rollouts * want[1] != actors * want[0]:
            name = where.get("name") if where is not p else "the run"
            ctx.report(group.where("ratio"), f"ratio {ratio} but {name!s} places {rollouts} rollout(s) and {actors} actor(s)"
                                             f" (expected {want[0]} rollouts per {want[1]} actor(s))")


_CHECKS: dict[type, list[Callable[[_Partial, _Context], None]]] = {
    Topology: [
        _check_run_id, _check_has_racks, _check_names, _check_required_roles, _check_netns_hosts, _check_remote_addresses,
        _check_learners, _check_eval_shards, _check_policy_checkpoint,
    ],
    SshConfig: [_check_ssh],
    TlsConfig: [_check_tls],
    WandbConfig: [_check_wandb],
    TaskConfig: [_check_obs_and_policy, _check_grpo, _check_libero_task, _check_env_batching],
    LiberoConfig: [_check_libero],
    BudgetConfig: [_check_stop_condition],
    RackConfig: [_check_rack_nodes, _check_key_name],
    NodeConfig: [_check_node_roles, _check_cpus, _check_key_name, _check_host],
    RolePlacement: [_check_cpus, _check_lane_cpus],
}


#: string fields that may not be empty, and what is expected instead
_NOT_EMPTY: dict[type, dict[str, str]] = {
    Topology: {"secret_file": "a path, or null for a per-run secret"},
    TaskConfig: {"env": "an env id like 'PushCube-v1' or 'module:function'",
                 "instruction": "words, or null for the task's default"},
    LiberoConfig: {"assets": "a directory, or null for $DVLA_LIBERO_ASSETS"},
    NodeConfig: {"host": "a host name; localhost for this machine", "address": "an IP address, or null to derive it"},
    SshConfig: {"python": "a non-empty string", "workdir": "a non-empty string",
                "identity_file": "a path, or null for ssh's default", "known_hosts_file": "a path, or null for ssh's default"},
    TlsConfig: {"root_ca": "a PEM file path", "cert": "a PEM file path", "key": "a PEM file path"},
    WandbConfig: {"project": "a W&B project name", "entity": "a W&B user or team, or null for the default",
                  "name": "a W&B run name, or null for the run id"},
}

#: file paths (resolved against the topology file's directory, "~" expanded), and what a missing
#: one is called (None: it need not exist here)
_FILES: dict[type, dict[str, str | None]] = {
    Topology: {"secret_file": "secret file"},
    SshConfig: {"identity_file": "identity file", "known_hosts_file": None},
    TlsConfig: {"root_ca": "TLS file", "cert": "TLS file", "key": "TLS file"},
}


def _check_strings(p: _Partial, ctx: _Context) -> None:
    """Reject empty strings; make file paths absolute and require the files that must exist."""
    for name, expected in _NOT_EMPTY.get(p.cls, {}).items():
        value = p.get(name)
        if isinstance(value, str) and not value.strip():
            ctx.report(p.where(name), f"empty {name} (expected {expected})")
    for name, what in _FILES.get(p.cls, {}).items():
        value = p.get(name)
        if not isinstance(value, str) or not value.strip():
            continue
        resolved = os.path.abspath(os.path.join(ctx.base_dir, os.path.expanduser(value)))
        p.values[name] = resolved
        if what is not None and not os.path.isfile(resolved):
            ctx.report(p.where(name), f"{what} not found: {resolved}")


def _check_tree(value: Any, ctx: _Context) -> None:
    if isinstance(value, _Partial):
        _check_ranges(value, ctx)
        _check_strings(value, ctx)
        for check in _CHECKS.get(value.cls, ()):
            check(value, ctx)
        for child in value.values.values():
            _check_tree(child, ctx)
    elif isinstance(value, tuple):
        for child in value:
            _check_tree(child, ctx)


# --------------------------------------------------------------------------------------------
# entry points


class _BoundedLoader(yaml.SafeLoader):
    """SafeLoader refusing nesting deeper than MAX_DEPTH while composing (PyYAML's composer
    recurses once per level: 10,000 nested lists would end in a RecursionError)."""

    depth = 0

    def compose_node(self, parent: Node | None, index: Any) -> Node:
        if self.depth >= MAX_DEPTH:
            raise yaml.composer.ComposerError(
                None, None, f"nested deeper than {MAX_DEPTH} levels of lists and mappings", self.peek_event().start_mark)
        self.depth += 1
        try:
            return super().compose_node(parent, index)
        finally:
            self.depth -= 1


class _Refused(Exception):
    """A document refused as a whole: the line and why."""

    def __init__(self, line: int, reason: str) -> None:
        super().__init__(reason)
        self.line = line


def _expanded(node: Node, level: int, memo: dict[int, tuple[int, int]], open_: set[int]) -> tuple[int, int]:
    """(values, depth) of `node` once aliases are expanded, `node` being at nesting `level`
    (memoised per node: linear in the file). Aliases are shared nodes, so a small file can stand
    for 10^9 values ("billion laughs") or nest far deeper than it is written: raises
    :class:`_Refused` above MAX_VALUES, deeper than MAX_DEPTH, or on an alias of a node inside itself."""
    key = id(node)
    size, depth = memo.get(key, (1, 1))
    if level + depth - 1 > MAX_DEPTH:
        raise _Refused(_line(node), f"nested deeper than {MAX_DEPTH} levels once aliases are expanded")
    if key in memo:
        return memo[key]
    if key in open_:
        raise _Refused(_line(node), "an alias refers to a list or mapping from inside itself (a cycle)")
    open_.add(key)
    children: list[Node] = []
    if isinstance(node, SequenceNode):
        children = node.value
    elif isinstance(node, MappingNode):
        children = [n for pair in node.value for n in pair]
    for child in children:
        child_size, child_depth = _expanded(child, level + 1, memo, open_)
        size, depth = size + child_size, max(depth, child_depth + 1)
        if size > MAX_VALUES:
            raise _Refused(_line(node), f"more than {MAX_VALUES} values once aliases are expanded")
    open_.discard(key)
    memo[key] = (size, depth)
    return size, depth


def _compose(text: str, ctx: _Context) -> Node | None:
    if len(text) > MAX_FILE_BYTES:
        ctx.report("", f"{len(text)} characters, more than a topology needs (at most {MAX_FILE_BYTES})", 0)
        return None
    try:
        root = yaml.compose(text, Loader=_BoundedLoader)
    except yaml.MarkedYAMLError as err:
        mark = err.problem_mark or err.context_mark
        ctx.report("<yaml>", f"invalid YAML: {_yaml_reason(err)}", mark.line + 1 if mark else 1)
        return None
    except yaml.YAMLError as err:
        ctx.report("<yaml>", f"invalid YAML: {_yaml_reason(err)}", 1)
        return None
    if root is not None:
        try:
            _expanded(root, 1, {}, set())
        except _Refused as err:
            ctx.report("<yaml>", f"refused: {err}", err.line)
            return None
    return root


def parse_topology(text: str, source: str = "<memory>") -> Topology:
    """Parse and validate topology YAML ``text`` read from ``source`` (used in messages).

    Relative paths in the file (``secret_file``, SSH keys, TLS files) are resolved against the directory of
    ``source``. Raises :class:`TopologyError` listing every problem found.
    """
    ctx = _Context(source)
    root_node = _compose(text, ctx)
    topo: Any = INVALID
    if root_node is None and not ctx.problems:
        ctx.report("", "empty topology (expected a mapping with at least 'run' and 'racks')")
    elif root_node is not None:
        ctx.lines[""] = _line(root_node)
        root = _convert(root_node, Topology, "", ctx)
        if isinstance(root, _Partial):
            _check_tree(root, ctx)
            root.values["source"] = source
            topo = _build(root, ctx)
    if ctx.problems:
        raise TopologyError(sorted(ctx.problems, key=lambda p: p.line))
    if not isinstance(topo, Topology):
        raise RuntimeError(f"{source}: topology could not be built but no problem was reported")
    return topo


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


def _plain(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {name: _plain(getattr(value, name)) for name in _yaml_fields(type(value))}
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


def topology_to_dict(topo: Topology) -> dict[str, Any]:
    """The topology as plain dicts, lists and scalars, every default filled in (``source`` left out:
    the loader sets it)."""
    return _plain(topo)


def dump_topology_yaml(topo: Topology) -> str:
    """YAML that :func:`parse_topology` reads back to an equal topology (given the same source)."""
    origin = " ".join(topo.source.split())
    header = f"# resolved topology of run {topo.run}, read from {origin}; every default filled in\n"
    body = yaml.safe_dump(topology_to_dict(topo), sort_keys=False, default_flow_style=False, allow_unicode=True)
    return header + body
