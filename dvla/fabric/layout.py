"""Cached message layouts: the decoder's fast path for a message shaped like an earlier one.

A rollout sends thousands of trajectory chunks whose *structure* never changes: the same map
keys, the same array dtypes and shapes, the same encoding widths of its integers. Only the
array data and a few scalars (``seq``, ``policy_version``, ``created_ns``) differ. Walking the
msgpack structure byte by byte for every chunk is most of the decoder's cost.

After the full decoder (:func:`dvla.fabric.codec.decode`) has accepted a message, :func:`learn`
records its :class:`Layout`: every byte that is structure (map headers, keys, type bytes, array
headers) as *constant spans*, and every value of the message body as a *slot* at a fixed offset
(an integer's payload bytes, a string's characters, an array's data). A later message of the
same length whose constant spans are byte-for-byte equal has, by construction, the very parse
the full decoder would produce: every type byte, length and header is the same, so every value
sits at the same offset with the same width. :meth:`Layout.build` then reads the slots
directly: arrays as zero-copy views, scalars with one ``struct`` call each, through the same
field checkers and the same ``validate()`` as the full decoder.

Anything the fast path is unsure about (a differing span, a slot byte outside its type's range,
invalid UTF-8) makes it answer ``None`` and the caller runs the full decoder, which accepts or
rejects with the precise error. So the set of accepted messages, and the values they decode to,
are exactly those of the full decoder; only the time differs.
"""

from __future__ import annotations

import dataclasses
import logging
import struct
import threading
from typing import Any, Callable

import numpy as np

log = logging.getLogger("dvla.fabric")

try:  # the per-message work in C (dvla/fabric/_views.c), when it could be built
    from . import _views as _C
except ImportError:  # no compiler at install time: the same steps in Python
    _C = None

_STRUCTS = {
    0xCA: struct.Struct(">f"), 0xCB: struct.Struct(">d"),
    0xCC: struct.Struct(">B"), 0xCD: struct.Struct(">H"), 0xCE: struct.Struct(">I"), 0xCF: struct.Struct(">Q"),
    0xD0: struct.Struct(">b"), 0xD1: struct.Struct(">h"), 0xD2: struct.Struct(">i"), 0xD3: struct.Struct(">q"),
}
_BE_U16 = struct.Struct(">H").unpack_from
_BE_U32 = struct.Struct(">I").unpack_from
_U32LE = [struct.Struct(f"<{n}I") for n in range(256)]

# Slot kinds (small ints: compared in the per-message loop)
_FIXINT_POS, _FIXINT_NEG, _BOOL, _SCALAR, _STR, _BIN, _ARRAY, _NONE = range(8)


class Layout:
    """One learned message structure, compiled into a straight-line Python function.

    The function compares the constant spans, reads every slot at its fixed offset and builds
    the message; generated once per layout, it runs no loop and no type dispatch per message.
    Nothing taken from the wire is ever part of the generated source: constants, map keys,
    shapes and dtypes reach it as names bound in its namespace.
    """

    __slots__ = ("length", "spans", "slots", "cls", "build", "write")

    def __init__(self, length: int, spans: list[tuple[int, bytes]], slots: list[tuple], cls: type,
                 checkers: dict[str, Callable[[Any, Any], Any]], dict_fields: tuple[str, ...]) -> None:
        self.length = length
        self.spans = spans
        #: (kind, field, dict key or None, offset, arg): arg is a struct, a length, or (shape, dtype)
        self.slots = slots
        self.cls = cls
        #: build(data) -> the decoded message, or None when `data` does not have this layout.
        #: Raises CodecError only from the field checkers or the message's validation, exactly as
        #: the full decoder would for the same bytes.
        self.build: Callable[[Any], Any | None] = _compile(spans, slots, cls, checkers, dict_fields)
        #: write(msg, out) -> the encoded length, or -1 when `msg` does not have this layout:
        #: the encoder's fast path, byte-for-byte the full encoder's output (None: no fast path)
        self.write: Callable[[Any, bytearray], int] | None = _compile_writer(length, spans, slots, cls, dict_fields)


def _compile(spans: list[tuple[int, bytes]], slots: list[tuple], cls: type,
             checkers: dict[str, Callable[[Any, Any], Any]], dict_fields: tuple[str, ...]) -> Callable[[Any], Any]:
    spans_t = tuple((start, bytes(const)) for start, const in spans)  # the C helper's form
    if _C is not None and _plain_fields(cls) == {name for _k, name, _key, _o, _a in slots} and not any(
        key is None and name in checkers and not _implied(checkers[name], kind, arg)
        for kind, name, key, _o, arg in slots
    ):
        return _compile_whole_c(spans_t, slots, cls)
    ns: dict[str, Any] = {"cls": cls, "nd": np.ndarray, "UnicodeDecodeError": UnicodeDecodeError}
    lines = ["def build(data):"]
    arrays = [(i, off, arg) for i, (kind, _n, _k, off, arg) in enumerate(slots) if kind == _ARRAY]
    in_c: set[int] = set()
    if _C is not None and arrays:
        # One C call checks every span and builds every array view (dvla/fabric/_views.c).
        ns["views"], ns["spans_t"] = _C.views, spans_t
        ns["arrays_t"] = tuple(_c_array(off, arg) for _i, off, arg in arrays)
        lines.append("    vs = views(data, spans_t, arrays_t)")
        lines.append("    if vs is None: return None")
        lines.append("    " + ", ".join(f"v{i}" for i, _o, _a in arrays) + ", = vs")
        in_c = {i for i, _o, _a in arrays}
    else:
        for i, (start, const) in enumerate(spans):
            ns[f"c{i}"] = const
            lines.append(f"    if data[{start}:{start + len(const)}] != c{i}: return None")
    fields: dict[str, str] = {}
    dicts: dict[str, list[str]] = {name: [] for name in dict_fields}
    for i, (kind, name, key, off, arg) in enumerate(slots):
        if not name.isidentifier():
            raise _NotCacheable
        v = f"v{i}"
        if i in in_c:
            pass  # built by the C call above
        elif kind == _ARRAY:
            ns[f"shape{i}"], ns[f"dt{i}"] = arg
            lines.append(f"    {v} = nd(shape{i}, dt{i}, data, {off})")
        elif kind == _SCALAR:
            ns[f"u{i}"] = arg.unpack_from
            lines.append(f"    {v} = u{i}(data, {off})[0]")
        elif kind == _FIXINT_POS:
            lines.append(f"    {v} = data[{off}]")
            lines.append(f"    if {v} > 0x7F: return None")
        elif kind == _FIXINT_NEG:
            lines.append(f"    {v} = data[{off}] - 0x100")
            lines.append(f"    if {v} < -32: return None")
        elif kind == _BOOL:
            lines.append(f"    {v} = data[{off}]")
            lines.append(f"    if {v} != 0xC2 and {v} != 0xC3: return None")
            lines.append(f"    {v} = {v} == 0xC3")
        elif kind == _STR:
            lines.append("    try:")
            lines.append(f"        {v} = str(data[{off}:{off + arg}], 'utf-8')")
            lines.append("    except UnicodeDecodeError:")
            lines.append("        return None")
        elif kind == _BIN:
            lines.append(f"    {v} = bytes(data[{off}:{off + arg}])")
        else:  # _NONE
            lines.append(f"    {v} = None")
        if key is None:
            if name in checkers and not _implied(checkers[name], kind, arg):
                ns[f"chk_{name}"] = checkers[name]
                fields[name] = f"chk_{name}({v}, {name!r})"
            else:
                fields[name] = v
        else:
            ns[f"k{i}"] = key
            dicts[name].append(f"k{i}: {v}")
    for name, items in dicts.items():
        fields[name] = "{" + ", ".join(items) + "}"
    if _plain_fields(cls) == set(fields):
        # Every field is on the wire and __init__ would only store them: fill the instance's
        # dict directly (a frozen dataclass's __init__ stores each field through
        # object.__setattr__, which costs more than the rest of the build).
        ns["new"] = object.__new__
        lines.append("    msg = new(cls)")
        lines.append("    msg.__dict__.update(" + ", ".join(f"{name}={expr}" for name, expr in fields.items()) + ")")
    else:
        lines.append("    msg = cls(" + ", ".join(f"{name}={expr}" for name, expr in fields.items()) + ")")
    lines.append("    msg.validate_values()")
    lines.append("    return msg")
    exec(compile("\n".join(lines), f"<dvla layout of {cls.__name__}>", "exec"), ns)
    return ns["build"]


def _c_array(off: int, arg: tuple) -> tuple:
    """An array slot as the C helper takes it: (offset, dtype, shape)."""
    shape, dtype = arg
    return off, dtype, tuple(shape)


def _compile_whole_c(spans_t: tuple, slots: list[tuple], cls: type) -> Callable[[Any], Any]:
    """The build function of a class whose fields need no checker beyond their wire type and
    whose __init__ only stores them: spans, every slot and the instance in one C call
    (dvla/fabric/_views.c), then the message's value checks."""
    slots_t = tuple(
        (kind, name, key, off,
         _c_array(off, arg) if kind == _ARRAY else arg.format[1:] if kind == _SCALAR else arg)
        for kind, name, key, off, arg in slots
    )
    build_c, new = _C.build, object.__new__

    def build(data: Any) -> Any | None:
        msg = build_c(data, new, cls, spans_t, slots_t)
        if msg is not None:
            msg.validate_values()
        return msg

    return build


def _plain_fields(cls: type) -> set[str] | None:
    """The init fields of a dataclass whose __init__ does nothing but store them (no
    ``__post_init__``, no ``__slots__``, no init-only variables), else None."""
    if not dataclasses.is_dataclass(cls) or hasattr(cls, "__post_init__") or hasattr(cls, "__slots__"):
        return None
    fields = dataclasses.fields(cls)
    if any(not f.init or isinstance(f.type, dataclasses.InitVar) for f in fields):
        return None
    return {f.name for f in fields}


# The integer range msgpack's packer writes with each type byte (it always picks the smallest).
_INT_RANGES = {
    0xCC: (0x80, 0xFF), 0xCD: (0x100, 0xFFFF), 0xCE: (0x10000, 0xFFFFFFFF), 0xCF: (1 << 32, (1 << 64) - 1),
    0xD0: (-128, -33), 0xD1: (-32768, -129), 0xD2: (-(1 << 31), -32769), 0xD3: (-(1 << 63), -(1 << 31) - 1),
}
_TYPE_BYTE = {st: b for b, st in _STRUCTS.items()}


def _compile_writer(length: int, spans: list[tuple[int, bytes]], slots: list[tuple], cls: type,
                    dict_fields: tuple[str, ...]) -> Callable[[Any, bytearray], int] | None:
    """The encoder for messages of this layout: checks that each field has exactly the type,
    width, shape and dtype the layout fixes (else -1: the full encoder takes over), checks the
    message's values, then writes the constant spans and every slot into the output buffer."""
    ns: dict[str, Any] = {"nd": np.ndarray, "UnicodeEncodeError": UnicodeEncodeError}
    check = ["def write(msg, out):"]
    put: list[str] = []
    got: dict[str, str] = {}
    dict_keys: dict[str, list[str]] = {name: [] for name in dict_fields}
    for i, (kind, name, key, off, arg) in enumerate(slots):
        if key is not None:
            dict_keys[name].append(key)
    for name, keys in dict_keys.items():
        ns[f"kt_{name}"] = tuple(keys)
        check.append(f"    d_{name} = msg.{name}")
        check.append(f"    if type(d_{name}) is not dict or tuple(d_{name}) != kt_{name}: return -1")
    for i, (kind, name, key, off, arg) in enumerate(slots):
        v = f"v{i}"
        if key is None:
            check.append(f"    {v} = msg.{name}")
        else:
            ns[f"k{i}"] = key
            check.append(f"    {v} = d_{name}[k{i}]")
        if kind == _ARRAY:
            ns[f"shape{i}"], ns[f"dt{i}"] = arg
            check.append(f"    if type({v}) is not nd or {v}.shape != shape{i} or {v}.dtype != dt{i}"
                         f" or not {v}.flags.c_contiguous: return -1")
            put.append(f"    mv[{off}:{off + _nbytes(arg)}] = memoryview({v}).cast('B')")
        elif kind == _SCALAR:
            tb = _TYPE_BYTE[arg]
            ns[f"p{i}"] = arg.pack_into
            if tb == 0xCB:
                check.append(f"    if type({v}) is not float: return -1")
            elif tb in _INT_RANGES:
                lo, hi = _INT_RANGES[tb]
                check.append(f"    if type({v}) is not int or not {lo} <= {v} <= {hi}: return -1")
            else:
                return None  # float32: never written by the packer
            put.append(f"    p{i}(out, {off}, {v})")
        elif kind == _FIXINT_POS:
            check.append(f"    if type({v}) is not int or not 0 <= {v} <= 0x7F: return -1")
            put.append(f"    out[{off}] = {v}")
        elif kind == _FIXINT_NEG:
            check.append(f"    if type({v}) is not int or not -32 <= {v} <= -1: return -1")
            put.append(f"    out[{off}] = {v} + 0x100")
        elif kind == _BOOL:
            check.append(f"    if type({v}) is not bool: return -1")
            put.append(f"    out[{off}] = 0xC3 if {v} else 0xC2")
        elif kind == _STR:
            check.append(f"    if type({v}) is not str: return -1")
            check.append("    try:")
            check.append(f"        b{i} = {v}.encode('utf-8')")
            check.append("    except UnicodeEncodeError:")
            check.append("        return -1")
            check.append(f"    if len(b{i}) != {arg}: return -1")
            put.append(f"    out[{off}:{off + arg}] = b{i}")
        elif kind == _BIN:
            check.append(f"    if (type({v}) is not bytes and type({v}) is not bytearray) or len({v}) != {arg}: return -1")
            put.append(f"    out[{off}:{off + arg}] = {v}")
        else:  # _NONE
            check.append(f"    if {v} is not None: return -1")
    for i, (start, const) in enumerate(spans):
        ns[f"c{i}"] = const
        put.append(f"    out[{start}:{start + len(const)}] = c{i}")
    lines = check + [
        "    msg.validate_values()",
        "    have = len(out)",
        f"    if have > {length}: del out[{length}:]",
        f"    elif have < {length}: out.extend(bytes({length} - have))",
        "    mv = memoryview(out)",
        "    try:",
    ] + ["    " + line for line in put] + [
        "    finally:",
        "        mv.release()  # a live export would forbid resizing `out` next time",
        f"    return {length}",
    ]
    exec(compile("\n".join(lines), f"<dvla layout writer of {cls.__name__}>", "exec"), ns)
    return ns["write"]


def _nbytes(arg: tuple) -> int:
    shape, dtype = arg
    n = dtype.itemsize
    for dim in shape:
        n *= dim
    return n


class LayoutCache:
    """Bounded cache of layouts, keyed by message length and the decoder's limits.

    A few layouts may share a length (two rollouts whose counters have different encoding
    widths); the cache keeps up to `per_length` of them and forgets the oldest lengths first.
    """

    def __init__(self, max_lengths: int = 64, per_length: int = 4) -> None:
        self._by_key: dict[Any, list[Layout]] = {}
        self._lock = threading.Lock()
        self.max_lengths = max_lengths
        self.per_length = per_length

    def candidates(self, key: Any) -> list[Layout]:
        return self._by_key.get(key, ())  # type: ignore[return-value]

    def live(self) -> dict[Any, list[Layout]]:
        """The cache's own key -> layouts dict, for a hot loop that looks layouts up itself
        (read-only: ``add`` replaces a key's list rather than changing it, so a list read from
        it never changes under the reader)."""
        return self._by_key

    def add(self, key: Any, layout: Layout) -> None:
        with self._lock:
            have = list(self._by_key.get(key, ()))
            have.insert(0, layout)
            del have[self.per_length:]
            self._by_key.pop(key, None)
            self._by_key[key] = have
            while len(self._by_key) > self.max_lengths:
                self._by_key.pop(next(iter(self._by_key)))

    def clear(self) -> None:
        with self._lock:
            self._by_key.clear()


def learn(data: bytes | bytearray | memoryview, schema: Any, dtypes: dict[bytes, np.dtype]) -> Layout | None:
    """The layout of `data`, a message the full decoder has just accepted, or None when its
    body holds values the fast path does not read (lists, nested free-form maps, ext types
    other than arrays). `schema` is the codec's compiled schema of the message's class."""
    try:
        return _Walker(data, dtypes).top(schema)
    except _NotCacheable:
        return None
    except Exception:  # a layout is an optimisation: never let learning one fail a message
        log.exception("cannot learn the layout of a %s message", schema.cls.__name__)
        return None


class _NotCacheable(Exception):
    pass


class _Walker:
    """Walks a message already known to be valid, recording constant spans and slots."""

    def __init__(self, data: bytes | bytearray | memoryview, dtypes: dict[bytes, np.dtype]) -> None:
        self.data = bytes(data)
        self.dtypes = dtypes
        self.pos = 0
        self.var: list[tuple[int, int]] = []  # variable byte ranges, in order
        self.slots: list[tuple] = []

    def top(self, schema: Any) -> Layout:
        n = self._map_len()
        for _ in range(n):
            key = self._str_value()
            if key == "b":
                dict_fields = self._body()
            else:
                self._skip()  # "v" and "t": constant bytes, compared like structure
        spans = []
        at = 0
        for start, stop in self.var:
            if start > at:
                spans.append((at, self.data[at:start]))
            at = stop
        if at < len(self.data):
            spans.append((at, self.data[at:]))
        checkers = {name: check for name, check in schema.fields if not _is_identity(check)}
        return Layout(len(self.data), spans, self.slots, schema.cls, checkers, dict_fields)

    # -- structure readers (constant bytes) ---------------------------------------------
    def _byte(self) -> int:
        b = self.data[self.pos]
        self.pos += 1
        return b

    def _map_len(self) -> int:
        b = self._byte()
        if 0x80 <= b <= 0x8F:
            return b & 0x0F
        if b == 0xDE:
            n = _BE_U16(self.data, self.pos)[0]
            self.pos += 2
            return n
        if b == 0xDF:
            n = _BE_U32(self.data, self.pos)[0]
            self.pos += 4
            return n
        raise _NotCacheable

    def _str_len(self, b: int) -> int | None:
        if 0xA0 <= b <= 0xBF:
            return b & 0x1F
        if b == 0xD9:
            n = self.data[self.pos]
            self.pos += 1
            return n
        if b == 0xDA:
            n = _BE_U16(self.data, self.pos)[0]
            self.pos += 2
            return n
        if b == 0xDB:
            n = _BE_U32(self.data, self.pos)[0]
            self.pos += 4
            return n
        return None

    def _str_value(self) -> str:
        n = self._str_len(self._byte())
        if n is None:
            raise _NotCacheable
        s = self.data[self.pos:self.pos + n].decode("utf-8")
        self.pos += n
        return s

    def _skip(self) -> None:
        """Skip a scalar or string value (the top level's "v" and "t")."""
        b = self._byte()
        if b <= 0x7F or b >= 0xE0 or b in (0xC0, 0xC2, 0xC3):
            return
        if b in _STRUCTS:
            self.pos += _STRUCTS[b].size
            return
        n = self._str_len(b)
        if n is None:
            raise _NotCacheable
        self.pos += n

    # -- the body: one slot per value ----------------------------------------------------
    def _slot(self, kind: int, name: str, key: str | None, start: int, stop: int, arg: Any) -> None:
        self.var.append((start, stop))
        self.slots.append((kind, name, key, start, arg))

    def _body(self) -> tuple[str, ...]:
        dict_fields = []
        for _ in range(self._map_len()):
            name = self._str_value()
            b = self.data[self.pos]
            if 0x80 <= b <= 0x8F or b in (0xDE, 0xDF):
                dict_fields.append(name)
                for _ in range(self._map_len()):
                    key = self._str_value()
                    if not self._value(name, key, arrays_only=True):
                        raise _NotCacheable
            elif not self._value(name, None, arrays_only=False):
                raise _NotCacheable
        return tuple(dict_fields)

    def _value(self, name: str, key: str | None, *, arrays_only: bool) -> bool:
        data = self.data
        at = self.pos
        b = data[at]
        if 0xC7 <= b <= 0xC9:
            width = 1 << (b - 0xC7)
            n = data[at + 1] if width == 1 else (_BE_U16 if width == 2 else _BE_U32)(data, at + 1)[0]
            self.pos = at + 1 + width + 1 + n  # frame, ext code, payload
            self._array(name, key, at + 2 + width, self.pos)
            return True
        if arrays_only:
            return False
        self.pos = at + 1
        if b <= 0x7F:
            self._slot(_FIXINT_POS, name, key, at, at + 1, None)
        elif b >= 0xE0:
            self._slot(_FIXINT_NEG, name, key, at, at + 1, None)
        elif b in (0xC2, 0xC3):
            self._slot(_BOOL, name, key, at, at + 1, None)
        elif b == 0xC0:
            self.slots.append((_NONE, name, key, at, None))  # a constant byte, still a value
        elif b in _STRUCTS:
            size = _STRUCTS[b].size
            self.pos = at + 1 + size
            self._slot(_SCALAR, name, key, at + 1, self.pos, _STRUCTS[b])
        elif b in (0xC4, 0xC5, 0xC6):
            width = 1 << (b - 0xC4)
            n = data[at + 1] if width == 1 else (_BE_U16 if width == 2 else _BE_U32)(data, at + 1)[0]
            start = at + 1 + width
            self.pos = start + n
            self._slot(_BIN, name, key, start, self.pos, n)
        else:
            n = self._str_len(b)
            if n is None:
                return False  # list, map or fixext: read by the full decoder only
            start = self.pos
            self.pos = start + n
            self._slot(_STR, name, key, start, self.pos, n)
        return True

    def _array(self, name: str, key: str | None, start: int, stop: int) -> None:
        # u8 name_len | name | u8 ndim | u32le shape[ndim] | u8 pad | pad zeros | data
        data = self.data
        name_len = data[start]
        p = start + 1
        dtype = self.dtypes[data[p:p + name_len]]
        p += name_len
        ndim = data[p]
        p += 1
        shape = _U32LE[ndim].unpack_from(data, p)
        p += 4 * ndim
        p += 1 + data[p]
        if p == stop or 0 in shape:
            raise _NotCacheable  # empty arrays are fresh (not views): left to the full decoder
        self._slot(_ARRAY, name, key, p, stop, (shape, dtype))


def _is_identity(check: Callable[[Any, Any], Any]) -> bool:
    return getattr(check, "__name__", "") in ("_check_ndarray", "_check_any")


_INT_TYPE_BYTES = frozenset(range(0xCC, 0xD4))


def _implied(check: Callable[[Any, Any], Any], kind: int, arg: Any) -> bool:
    """True when the slot's wire type alone guarantees what `check` checks and returns: the
    value is already the plain ``int``, ``float``, ``str`` or ``bool`` the checker would give
    back (a fixint or integer struct reads an int, a float struct a float, ...), so the call
    can be left out of the generated function."""
    name = getattr(check, "__name__", "")
    if name == "_check_int":
        return kind in (_FIXINT_POS, _FIXINT_NEG) or (kind == _SCALAR and _TYPE_BYTE[arg] in _INT_TYPE_BYTES)
    if name == "_check_float":
        return kind == _SCALAR and _TYPE_BYTE[arg] in (0xCA, 0xCB)
    if name == "_check_str":
        return kind == _STR
    if name == "_check_bool":
        return kind == _BOOL
    return False
