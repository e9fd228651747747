"""The one wire codec of dvla: message dataclass <-> msgpack bytes (docs/wire-format.md)::

    {"v": SCHEMA_VERSION, "t": <type tag>, "b": {<field name>: <value>, ...}}

numpy arrays travel as msgpack ext type :data:`ARRAY_EXT_CODE` (a small header, then the raw
C-order little-endian bytes). :func:`encode` copies each array's bytes once; :func:`decode` never
(``np.frombuffer`` views), so it uses the small reader below rather than msgpack's ``Unpacker``,
which copies every ext payload. The reader checks :class:`Limits` on every declared length before
touching data, so a forged length cannot allocate beyond the input. :func:`decode` raises
:class:`CodecError` for any bad input and nothing else.
"""

from __future__ import annotations

import dataclasses
import struct
import typing
from dataclasses import dataclass
from typing import Any, Callable

import msgpack
import numpy as np

from dvla.fabric.errors import CodecError
from dvla.fabric.messages import MESSAGE_TYPES, Message

__all__ = [
    "ARRAY_EXT_CODE",
    "DEFAULT_LIMITS",
    "DTYPES",
    "SCHEMA_VERSION",
    "CodecError",
    "Limits",
    "decode",
    "encode",
    "encode_into",
]

SCHEMA_VERSION = 3
"""Version of the top-level map and of every message schema; bumped on any incompatible change."""

ARRAY_EXT_CODE = 1
"""msgpack ext type code of a numpy array."""

ARRAY_ALIGN = 8
"""The encoder pads array headers so array data starts at a multiple of this many bytes from
the start of the message (so views are aligned whenever the receive buffer is)."""

MAX_ARRAY_PAD = 63
"""Largest padding a decoder accepts in an array header."""

DTYPES: dict[str, np.dtype] = {
    name: np.dtype(code)
    for name, code in (
        ("bool", "|b1"), ("uint8", "|u1"), ("int8", "|i1"), ("int16", "<i2"), ("int32", "<i4"),
        ("int64", "<i8"), ("float16", "<f2"), ("float32", "<f4"), ("float64", "<f8"),
    )
}
"""The array dtype allowlist: wire name -> little-endian numpy dtype."""

_DTYPES_BY_WIRE_NAME: dict[bytes, np.dtype] = {name.encode("ascii"): dt for name, dt in DTYPES.items()}
_WIRE_NAME_BY_DTYPE: dict[np.dtype, bytes] = {dt: name.encode("ascii") for name, dt in DTYPES.items()}

_MiB = 1 << 20


@dataclass(frozen=True, kw_only=True)
class Limits:
    """Upper bounds a decoder enforces before allocating or viewing anything.

    The encoder enforces the same bounds so a sender fails loudly instead of emitting
    messages that a default receiver would drop.
    """

    #: whole encoded message, bytes
    max_message_bytes: int = 256 * _MiB
    #: one array's data (and one msgpack bin value), bytes
    max_array_bytes: int = 256 * _MiB
    #: dimensions of one array
    max_ndim: int = 8
    #: one string (keys included), UTF-8 bytes
    max_str_len: int = 1 * _MiB
    #: entries of one map
    max_map_len: int = 65536
    #: items of one list
    max_list_len: int = 1 << 20
    #: nesting depth of maps/lists (the top-level map is depth 1)
    max_depth: int = 32


DEFAULT_LIMITS = Limits()


# --------------------------------------------------------------------------------------------
# Field schemas, compiled once from the message dataclasses' type hints.
# --------------------------------------------------------------------------------------------

Path = Any
"""Where a value sits, for error messages: a field name, or ``(parent path, key)``. Kept as
nested tuples so the string is only built when an error is actually raised."""

Checker = Callable[[Any, Path], Any]
"""Takes a field value and its path; returns the normalised value or raises CodecError("type")."""


def _path_str(path: Path) -> str:
    if isinstance(path, tuple):
        parent, key = path
        return f"{_path_str(parent)}[{key!r}]"
    return str(path)


def _type_error(path: Path, value: Any, expected: str) -> CodecError:
    return CodecError("type", f"{_path_str(path)}: {type(value).__name__}, expected {expected}")


def _checker(types: type | tuple[type, ...], expected: str, convert: Callable[[Any], Any] = lambda v: v,
             refuse: tuple[type, ...] = ()) -> Checker:
    def check(value: Any, path: Path) -> Any:
        if isinstance(value, refuse) or not isinstance(value, types):
            raise _type_error(path, value, expected)
        return convert(value)

    return check


def _dict_checker(value_checker: Checker) -> Checker:
    def check(value: Any, path: Path) -> dict[str, Any]:
        if not isinstance(value, dict):
            raise _type_error(path, value, "dict")
        out = {}
        for key, item in value.items():
            if not isinstance(key, str):
                raise CodecError("type", f"{_path_str(path)}: key {key!r} is not a str")
            out[key] = value_checker(item, (path, key))
        return out

    return check


# bool is an int subclass in Python but a distinct msgpack type, so ints refuse it; floats accept
# integers because other encoders may write 1 for 1.0.
_SCALAR_CHECKERS: dict[Any, Checker] = {
    str: _checker(str, "str"),
    int: _checker((int, np.integer), "int", int, refuse=(bool,)),
    float: _checker((float, int, np.floating, np.integer), "float", float, refuse=(bool, np.bool_)),
    bool: _checker((bool, np.bool_), "bool", bool),
    bytes: _checker((bytes, bytearray, memoryview), "bytes"),
    np.ndarray: _checker(np.ndarray, "numpy.ndarray"),
    Any: lambda value, path: value,
}


def _compile_hint(hint: Any) -> Checker:
    """Turn a field's type hint into a checker; unknown hint shapes are a programming error."""
    if hint in _SCALAR_CHECKERS:
        return _SCALAR_CHECKERS[hint]
    if hint is dict:
        return _dict_checker(_SCALAR_CHECKERS[Any])
    if typing.get_origin(hint) is dict:
        key_hint, value_hint = typing.get_args(hint)
        if key_hint is str:
            return _dict_checker(_compile_hint(value_hint))
    raise TypeError(f"codec cannot check fields of type {hint!r}")


@dataclass(frozen=True)
class _Schema:
    cls: type
    tag: str
    fields: tuple[tuple[str, Checker], ...]
    names: frozenset[str]


def _compile_schema(cls: type) -> _Schema:
    hints = typing.get_type_hints(cls)
    fields = tuple((f.name, _compile_hint(hints[f.name])) for f in dataclasses.fields(cls))
    return _Schema(cls=cls, tag=cls.TYPE_TAG, fields=fields, names=frozenset(name for name, _ in fields))


_SCHEMAS_BY_TAG: dict[str, _Schema] = {tag: _compile_schema(cls) for tag, cls in MESSAGE_TYPES.items()}
_SCHEMAS_BY_CLASS: dict[type, _Schema] = {s.cls: s for s in _SCHEMAS_BY_TAG.values()}


# --------------------------------------------------------------------------------------------
# Encoding
# --------------------------------------------------------------------------------------------

_U8 = struct.Struct("<B")
_SHAPE_STRUCTS = [struct.Struct(f"<{n}I") for n in range(256)]
_MAX_DIM = (1 << 32) - 1
#: u8 name length + name, per wire dtype name
_NAME_PREFIX = {name: _U8.pack(len(name)) + name for name in _DTYPES_BY_WIRE_NAME}
#: pad-length byte followed by that many zero bytes, per pad length
_PAD_BYTES = [_U8.pack(pad) + bytes(pad) for pad in range(ARRAY_ALIGN)]
#: msgpack bin 8/16/32 and ext 8/16/32 frames: (length bound, header struct, type byte)
_BIN_FRAMES = ((1 << 8, struct.Struct(">BB"), 0xC4), (1 << 16, struct.Struct(">BH"), 0xC5), (1 << 32, struct.Struct(">BI"), 0xC6))
_EXT_FRAMES = ((1 << 8, struct.Struct(">BBb"), 0xC7), (1 << 16, struct.Struct(">BHb"), 0xC8), (1 << 32, struct.Struct(">BIb"), 0xC9))


def _frame(frames: tuple, length: int) -> tuple[struct.Struct, int]:
    """The smallest (header struct, type byte) of ``frames`` that can hold ``length`` bytes."""
    return next((st, code) for bound, st, code in frames if length < bound)


def _wire_array(arr: np.ndarray, path: Path, limits: Limits) -> tuple[bytes, np.ndarray]:
    """Check an array against the allowlist/limits; return (wire dtype name, C-contiguous LE array)."""
    dtype = arr.dtype
    name = _WIRE_NAME_BY_DTYPE.get(dtype)
    if name is None and dtype.byteorder == ">":
        name = _WIRE_NAME_BY_DTYPE.get(dtype.newbyteorder("<"))
    if name is None:
        raise CodecError("type", f"{_path_str(path)}: dtype {dtype} not in {sorted(DTYPES)}")
    if arr.ndim > limits.max_ndim:
        raise CodecError("oversize", f"{_path_str(path)}: ndim {arr.ndim} > {limits.max_ndim}")
    if arr.ndim and max(arr.shape) > _MAX_DIM:
        raise CodecError("oversize", f"{_path_str(path)}: a dimension of {arr.shape} exceeds uint32")
    if arr.nbytes > limits.max_array_bytes:
        raise CodecError("oversize", f"{_path_str(path)}: {arr.nbytes} bytes > {limits.max_array_bytes}")
    if dtype.byteorder == ">":
        arr = arr.astype(dtype.newbyteorder("<"), order="C")  # byte-swap (the one copy)
    elif not arr.flags.c_contiguous:
        arr = np.ascontiguousarray(arr)  # gather strided data (the one copy)
    return name, arr


class _Writer:
    """Accumulates the output as a list of pieces; small values go through one msgpack Packer,
    array and bin data are appended as buffer views so ``b"".join`` copies them exactly once."""

    def __init__(self, limits: Limits) -> None:
        self.limits = limits
        # Small initial buffer: only headers and scalars go through the packer (its 256 KiB
        # default would be an extra large allocation per message).
        self.packer = msgpack.Packer(use_bin_type=True, autoreset=False, buf_size=4096)
        self.pieces: list[Any] = []
        self.offset = 0  # bytes in ``pieces``

    def _flush(self) -> None:
        chunk = self.packer.bytes()
        if chunk:
            self.pieces.append(chunk)
            self.offset += len(chunk)
            self.packer.reset()

    def finish(self) -> bytes:
        self._check_size()
        return b"".join(self.pieces)

    def finish_into(self, buf: bytearray) -> int:
        """Write the message into ``buf``, resized to its length; returns that length."""
        self._check_size()
        n = self.offset
        del buf[n:]
        buf.extend(bytes(n - len(buf)))
        view, pos = memoryview(buf), 0
        for piece in self.pieces:
            piece = memoryview(piece).cast("B")
            view[pos:pos + len(piece)] = piece
            pos += len(piece)
        return n

    def _check_size(self) -> None:
        self._flush()
        if self.offset > self.limits.max_message_bytes:
            raise CodecError("oversize", f"message {self.offset} bytes > {self.limits.max_message_bytes}")

    def map_header(self, n: int, path: Path) -> None:
        if n > self.limits.max_map_len:
            raise CodecError("oversize", f"{_path_str(path)}: map of {n} entries > {self.limits.max_map_len}")
        self.packer.pack_map_header(n)

    def string(self, value: str, path: Path) -> None:
        # A char is at most 4 UTF-8 bytes: only long strings need the exact (encoding) check.
        if len(value) * 4 > self.limits.max_str_len and len(value.encode("utf-8")) > self.limits.max_str_len:
            raise CodecError("oversize", f"{_path_str(path)}: string longer than {self.limits.max_str_len} bytes")
        self.packer.pack(value)

    def value(self, value: Any, path: Path, depth: int) -> None:
        if isinstance(value, np.ndarray):
            self.array(value, path)
        elif value is None or isinstance(value, (bool, int, float)):
            self.packer.pack(value)
        elif isinstance(value, str):
            self.string(value, path)
        elif isinstance(value, dict):
            self.mapping(value, path, depth + 1)
        elif isinstance(value, (list, tuple)):
            self.sequence(value, path, depth + 1)
        elif isinstance(value, (bytes, bytearray, memoryview)):
            self.binary(value, path)
        elif isinstance(value, np.generic):
            self.value(value.item(), path, depth)
        else:
            raise CodecError("type", f"{_path_str(path)}: cannot encode {type(value).__name__}")

    def _enter(self, depth: int, path: Path) -> None:
        if depth > self.limits.max_depth:
            raise CodecError("oversize", f"{_path_str(path)}: nesting deeper than {self.limits.max_depth}")

    def mapping(self, value: dict, path: Path, depth: int) -> None:
        self._enter(depth, path)
        self.map_header(len(value), path)
        for key, item in value.items():
            if not isinstance(key, str):
                raise CodecError("type", f"{_path_str(path)}: key {key!r} is not a str")
            self.string(key, path)
            self.value(item, (path, key), depth)

    def sequence(self, value: list | tuple, path: Path, depth: int) -> None:
        self._enter(depth, path)
        if len(value) > self.limits.max_list_len:
            raise CodecError("oversize", f"{_path_str(path)}: list of {len(value)} items > {self.limits.max_list_len}")
        self.packer.pack_array_header(len(value))
        for i, item in enumerate(value):
            self.value(item, (path, i), depth)

    def binary(self, value: bytes | bytearray | memoryview, path: Path) -> None:
        view = memoryview(value).cast("B") if isinstance(value, memoryview) else value
        n = len(view)
        if n > self.limits.max_array_bytes:
            raise CodecError("oversize", f"{_path_str(path)}: {n} bytes > {self.limits.max_array_bytes}")
        self._flush()
        st, code = _frame(_BIN_FRAMES, n)
        self.pieces += [st.pack(code, n), view]
        self.offset += st.size + n

    def array(self, value: np.ndarray, path: Path) -> None:
        name, arr = _wire_array(value, path, self.limits)
        ndim = arr.ndim
        header = _NAME_PREFIX[name] + _U8.pack(ndim) + _SHAPE_STRUCTS[ndim].pack(*arr.shape)
        hlen = len(header) + 1  # + the pad-length byte
        nbytes = arr.nbytes
        # Pick the frame size assuming the largest pad, so choosing the pad can't change it.
        st, code = _frame(_EXT_FRAMES, hlen + (ARRAY_ALIGN - 1) + nbytes)
        self._flush()
        pad = -(self.offset + st.size + hlen) % ARRAY_ALIGN
        head = st.pack(code, hlen + pad + nbytes, ARRAY_EXT_CODE) + header + _PAD_BYTES[pad]
        self.pieces.append(head)
        self.offset += len(head)
        if nbytes:
            self.pieces.append(arr)
            self.offset += nbytes


def encode(msg: Message, limits: Limits = DEFAULT_LIMITS) -> bytes:
    """Encode a message. Raises :class:`CodecError` if it is not a valid, encodable message."""
    return _write(msg, limits).finish()


def encode_into(msg: Message, buf: bytearray, limits: Limits = DEFAULT_LIMITS) -> int:
    """:func:`encode` into a reused buffer (resized to the message; returns its length): a fresh
    megabyte object per large message delays the sender's control traffic (docs/benchmarks.md)."""
    return _write(msg, limits).finish_into(buf)


def _write(msg: Message, limits: Limits) -> "_Writer":
    schema = _SCHEMAS_BY_CLASS.get(type(msg))
    if schema is None:
        raise CodecError("type", f"not a fabric message: {type(msg).__name__}")
    try:
        values = [(name, check(getattr(msg, name), name)) for name, check in schema.fields]
        msg.validate()
        writer = _Writer(limits)
        writer.packer.pack_map_header(3)
        writer.packer.pack("v")
        writer.packer.pack(SCHEMA_VERSION)
        writer.packer.pack("t")
        writer.packer.pack(schema.tag)
        writer.packer.pack("b")
        writer.map_header(len(values), "b")
        for name, value in values:
            writer.packer.pack(name)
            writer.value(value, name, 2)
        return writer
    except CodecError:
        raise
    except (TypeError, ValueError, OverflowError) as exc:
        # msgpack refuses e.g. ints beyond 64 bits or strings with lone surrogates.
        raise CodecError("type", f"{type(exc).__name__}: {exc}") from exc


# --------------------------------------------------------------------------------------------
# Decoding
# --------------------------------------------------------------------------------------------

# Fixed-width scalars: first byte -> big-endian struct.
_FIXED_SCALARS = {
    b: struct.Struct(">" + fmt)
    for b, fmt in zip(range(0xCA, 0xD4), ("f", "d", "B", "H", "I", "Q", "b", "h", "i", "q"))
}
# Length-prefixed values: first byte -> (kind, width of the big-endian length).
_SIZED = {
    0xC4: ("bin", 1), 0xC5: ("bin", 2), 0xC6: ("bin", 4),
    0xC7: ("ext", 1), 0xC8: ("ext", 2), 0xC9: ("ext", 4),
    0xD9: ("str", 1), 0xDA: ("str", 2), 0xDB: ("str", 4),
    0xDC: ("list", 2), 0xDD: ("list", 4),
    0xDE: ("map", 2), 0xDF: ("map", 4),
}
_FIXEXT_LEN = {0xD4: 1, 0xD5: 2, 0xD6: 4, 0xD7: 8, 0xD8: 16}
_CONSTANTS = {0xC0: None, 0xC2: False, 0xC3: True}


class _Reader:
    """Recursive-descent msgpack reader over a flat byte memoryview; arrays come out as views
    of it."""

    __slots__ = ("data", "pos", "end", "limits")

    def __init__(self, data: memoryview, limits: Limits) -> None:
        self.data = data
        self.pos = 0
        self.end = len(data)
        self.limits = limits

    def _take(self, n: int) -> int:
        """Claim the next ``n`` bytes; return their start offset."""
        start = self.pos
        if n > self.end - start:
            raise CodecError("malformed", f"truncated: need {n} bytes at offset {start}, have {self.end - start}")
        self.pos = start + n
        return start

    def value(self, depth: int) -> Any:
        b = self.data[self._take(1)]
        if b <= 0x7F:
            return b
        if b >= 0xE0:
            return b - 0x100
        if b <= 0x8F:
            return self.mapping(b & 0x0F, depth + 1)
        if b <= 0x9F:
            return self.sequence(b & 0x0F, depth + 1)
        if b <= 0xBF:
            return self.string(b & 0x1F)
        if b in _CONSTANTS:
            return _CONSTANTS[b]
        if b in _FIXED_SCALARS:
            st = _FIXED_SCALARS[b]
            return st.unpack_from(self.data, self._take(st.size))[0]
        if b in _FIXEXT_LEN:
            return self.ext(_FIXEXT_LEN[b])
        if b not in _SIZED:
            raise CodecError("malformed", f"invalid msgpack type byte 0x{b:02x} at offset {self.pos}")
        kind, width = _SIZED[b]
        start = self._take(width)
        n = int.from_bytes(self.data[start:start + width], "big")
        if kind == "str":
            return self.string(n)
        if kind == "bin":
            return self.binary(n)
        if kind == "ext":
            return self.ext(n)
        if kind == "list":
            return self.sequence(n, depth + 1)
        return self.mapping(n, depth + 1)

    def string(self, n: int) -> str:
        if n > self.limits.max_str_len:
            raise CodecError("oversize", f"string of {n} bytes > {self.limits.max_str_len}")
        start = self._take(n)
        try:
            return str(self.data[start:start + n], "utf-8")
        except UnicodeDecodeError as exc:
            raise CodecError("malformed", f"invalid UTF-8 at offset {start}") from exc

    def binary(self, n: int) -> bytes:
        if n > self.limits.max_array_bytes:
            raise CodecError("oversize", f"bin of {n} bytes > {self.limits.max_array_bytes}")
        start = self._take(n)
        return bytes(self.data[start:start + n])

    def _enter(self, depth: int, count: int, min_item_bytes: int, limit: int, what: str) -> None:
        if depth > self.limits.max_depth:
            raise CodecError("oversize", f"nesting deeper than {self.limits.max_depth}")
        if count > limit:
            raise CodecError("oversize", f"{what} of {count} entries > {limit}")
        # Every entry takes at least one byte: reject impossible counts before looping.
        if count * min_item_bytes > self.end - self.pos:
            raise CodecError("malformed", f"truncated {what} of {count} entries at offset {self.pos}")

    def sequence(self, n: int, depth: int) -> list:
        self._enter(depth, n, 1, self.limits.max_list_len, "list")
        return [self.value(depth) for _ in range(n)]

    def mapping(self, n: int, depth: int) -> dict:
        self._enter(depth, n, 2, self.limits.max_map_len, "map")
        out: dict[str, Any] = {}
        for _ in range(n):
            key = self.value(depth)
            if type(key) is not str:
                raise CodecError("schema", f"map key {key!r} is not a str")
            if key in out:
                raise CodecError("schema", f"duplicate map key {key!r}")
            out[key] = self.value(depth)
        return out

    def ext(self, n: int) -> np.ndarray:
        code_at = self._take(1)
        code = int.from_bytes(self.data[code_at:code_at + 1], "big", signed=True)
        if code != ARRAY_EXT_CODE:
            raise CodecError("type", f"unsupported ext type {code} at offset {code_at}")
        start = self._take(n)
        return self.array(start, start + n)

    def array(self, start: int, stop: int) -> np.ndarray:
        """Parse an array ext payload occupying ``data[start:stop]`` into a view of the input."""
        data, limits = self.data, self.limits
        # Layout: u8 name_len | name | u8 ndim | u32le shape[ndim] | u8 pad | pad zeros | data
        if start >= stop:
            raise CodecError("malformed", f"empty array header at offset {start}")
        name_len = data[start]
        p = start + 1
        if p + name_len + 1 > stop:
            raise CodecError("malformed", f"array header truncated at offset {start}")
        name = bytes(data[p:p + name_len])
        dtype = _DTYPES_BY_WIRE_NAME.get(name)
        if dtype is None:
            raise CodecError("type", f"array dtype {name!r} not in the allowlist")
        p += name_len
        ndim = data[p]
        p += 1
        if ndim > limits.max_ndim:
            raise CodecError("oversize", f"array ndim {ndim} > {limits.max_ndim}")
        if p + 4 * ndim + 1 > stop:
            raise CodecError("malformed", f"array header truncated at offset {start}")
        shape = _SHAPE_STRUCTS[ndim].unpack_from(data, p)
        p += 4 * ndim
        pad = data[p]
        p += 1
        if pad > MAX_ARRAY_PAD or p + pad > stop:
            raise CodecError("malformed", f"bad array header padding {pad} at offset {p - 1}")
        if pad and any(data[p:p + pad]):
            raise CodecError("malformed", "non-zero array header padding")
        p += pad
        count = 1
        for dim in shape:
            count *= dim
        nbytes = count * dtype.itemsize  # exact Python int: a forged shape cannot overflow
        if nbytes != stop - p:
            raise CodecError("shape", f"array {dtype.name}{list(shape)} needs {nbytes} bytes, payload has {stop - p}")
        if nbytes > limits.max_array_bytes:
            raise CodecError("oversize", f"array of {nbytes} bytes > {limits.max_array_bytes}")
        if count == 0:
            return np.empty(shape, dtype)
        return np.ndarray(shape, dtype, data, p)


def _byte_view(buf: Any) -> memoryview:
    """A flat byte memoryview of ``buf``."""
    try:
        mv = memoryview(buf)
        return mv if mv.ndim == 1 and mv.format == "B" else mv.cast("B")  # a strided view is refused
    except (TypeError, ValueError) as exc:
        raise CodecError("malformed", f"not a contiguous bytes-like object: {type(buf).__name__}") from exc


def decode(
    buf: bytes | bytearray | memoryview,
    expect: type | tuple[type, ...] | None = None,
    limits: Limits = DEFAULT_LIMITS,
) -> Message:
    """Decode one message whose arrays are views into ``buf`` (no copy).

    With ``bytes`` input the arrays are read-only; with a ``bytearray`` or writable memoryview
    they are writable and alias it, so don't reuse that buffer while the message is alive.
    ``expect`` restricts the accepted message classes. Any bad input raises
    :class:`CodecError` (and nothing else).
    """
    try:
        data = _byte_view(buf)
        if len(data) > limits.max_message_bytes:
            raise CodecError("oversize", f"message {len(data)} bytes > {limits.max_message_bytes}")
        reader = _Reader(data, limits)
        top = reader.value(0)
        if reader.pos != reader.end:
            raise CodecError("malformed", f"{reader.end - reader.pos} trailing bytes")
        if not isinstance(top, dict):
            raise CodecError("schema", f"top level is {type(top).__name__}, expected map")
        if top.keys() != {"v", "t", "b"}:
            raise CodecError("schema", f"top-level keys {sorted(top)}, expected ['b', 't', 'v']")
        version, tag, body = top["v"], top["t"], top["b"]
        if type(version) is not int or version != SCHEMA_VERSION:
            raise CodecError("schema", f"schema version {version!r}, this codec speaks {SCHEMA_VERSION}")
        schema = _SCHEMAS_BY_TAG.get(tag) if isinstance(tag, str) else None
        if schema is None:
            raise CodecError("schema", f"unknown message type {tag!r}")
        if expect is not None and not issubclass(schema.cls, expect):
            raise CodecError("type", f"got {schema.cls.__name__}, expected {expect}")
        if not isinstance(body, dict):
            raise CodecError("schema", f"body is {type(body).__name__}, expected map")
        if body.keys() != schema.names:
            missing = sorted(schema.names - body.keys())
            extra = sorted(body.keys() - schema.names)
            raise CodecError("schema", f"{schema.tag}: missing fields {missing}, unknown fields {extra}")
        msg = schema.cls(**{name: check(body[name], name) for name, check in schema.fields})
        msg.validate()
        return msg
    except CodecError:
        raise
    except Exception as exc:
        # Safety net: whatever slipped past the explicit checks is still just a bad packet.
        raise CodecError("malformed", f"{type(exc).__name__}: {exc}") from exc
