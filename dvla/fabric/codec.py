"""The one wire codec of dvla: message dataclass <-> msgpack bytes.

This module owns the byte encoding of every :mod:`dvla.fabric.messages` type (format in
``docs/wire-format.md``)::

    {"v": SCHEMA_VERSION, "t": <type tag>, "b": {<field name>: <value>, ...}}

numpy arrays travel as msgpack ext type :data:`ARRAY_EXT_CODE` whose payload is a small header
(dtype name, ndim, little-endian uint32 shape, alignment padding) followed by the raw C-order
little-endian array bytes.

Performance contract: :func:`encode` copies each array's bytes exactly once (into the output
buffer); :func:`decode` copies them never (arrays are ``np.frombuffer`` views of the input).
msgpack-python's ``Unpacker`` copies every ext payload into a fresh ``bytes`` before handing it
over, so decoding uses the small msgpack reader below instead; it enforces :class:`Limits` on
every declared length *before* touching the data, and since every value is either a view of the
input or bounded by it, a forged length can never make it allocate beyond the input size.

Safety contract: :func:`decode` raises :class:`CodecError` for any bad input and nothing else.
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
]

SCHEMA_VERSION = 1
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


def _check_str(value: Any, path: Path) -> str:
    if not isinstance(value, str):
        raise _type_error(path, value, "str")
    return value


def _check_int(value: Any, path: Path) -> int:
    # bool is an int subclass in Python but a distinct msgpack type; keep them apart.
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise _type_error(path, value, "int")
    return int(value)


def _check_float(value: Any, path: Path) -> float:
    # Integers are accepted because other encoders may write 1 for 1.0.
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (float, int, np.floating, np.integer)):
        raise _type_error(path, value, "float")
    return float(value)


def _check_bool(value: Any, path: Path) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise _type_error(path, value, "bool")
    return bool(value)


def _check_bytes(value: Any, path: Path) -> Any:
    if not isinstance(value, (bytes, bytearray, memoryview)):
        raise _type_error(path, value, "bytes")
    return value


def _check_ndarray(value: Any, path: Path) -> np.ndarray:
    if not isinstance(value, np.ndarray):
        raise _type_error(path, value, "numpy.ndarray")
    return value


def _check_any(value: Any, path: Path) -> Any:
    return value


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


_SCALAR_CHECKERS: dict[Any, Checker] = {
    str: _check_str, int: _check_int, float: _check_float, bool: _check_bool,
    bytes: _check_bytes, np.ndarray: _check_ndarray, Any: _check_any,
}


def _compile_hint(hint: Any) -> Checker:
    """Turn a field's type hint into a checker; unknown hint shapes are a programming error."""
    if hint in _SCALAR_CHECKERS:
        return _SCALAR_CHECKERS[hint]
    if hint is dict:
        return _dict_checker(_check_any)
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
_EXT_FRAME_LEN = (3, 4, 6)


def _ext_frame(length: int, kind: int) -> bytes:
    """msgpack ext 8/16/32 header; ``kind`` (0, 1, 2) is chosen by :meth:`_Writer.array`."""
    if kind == 0:
        return struct.pack(">BBb", 0xC7, length, ARRAY_EXT_CODE)
    if kind == 1:
        return struct.pack(">BHb", 0xC8, length, ARRAY_EXT_CODE)
    return struct.pack(">BIb", 0xC9, length, ARRAY_EXT_CODE)


def _ext_kind(length: int) -> int:
    return 0 if length < (1 << 8) else 1 if length < (1 << 16) else 2


def _bin_frame(length: int) -> bytes:
    if length < (1 << 8):
        return struct.pack(">BB", 0xC4, length)
    if length < (1 << 16):
        return struct.pack(">BH", 0xC5, length)
    return struct.pack(">BI", 0xC6, length)


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

    def _raw(self, piece: Any, length: int) -> None:
        self.pieces.append(piece)
        self.offset += length

    def finish(self) -> bytes:
        self._flush()
        if self.offset > self.limits.max_message_bytes:
            raise CodecError("oversize", f"message {self.offset} bytes > {self.limits.max_message_bytes}")
        return b"".join(self.pieces)

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
        if type(value) is np.ndarray:  # most values of a trajectory chunk
            self.array(value, path)
        elif value is None or isinstance(value, (bool, int, float)):
            self.packer.pack(value)
        elif isinstance(value, str):
            self.string(value, path)
        elif isinstance(value, np.ndarray):
            self.array(value, path)
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
        frame = _bin_frame(n)
        self._raw(frame, len(frame))
        self._raw(view, n)

    def array(self, value: np.ndarray, path: Path) -> None:
        name, arr = _wire_array(value, path, self.limits)
        ndim = arr.ndim
        header = _NAME_PREFIX[name] + _U8.pack(ndim) + _SHAPE_STRUCTS[ndim].pack(*arr.shape)
        hlen = len(header) + 1  # + the pad-length byte
        nbytes = arr.nbytes
        # Pick the frame size assuming the largest pad, so choosing the pad can't change it.
        kind = _ext_kind(hlen + (ARRAY_ALIGN - 1) + nbytes)
        self._flush()
        pad = -(self.offset + _EXT_FRAME_LEN[kind] + hlen) % ARRAY_ALIGN
        head = _ext_frame(hlen + pad + nbytes, kind) + header + _PAD_BYTES[pad]
        self.pieces.append(head)
        self.offset += len(head)
        if nbytes:
            self.pieces.append(arr)
            self.offset += nbytes


def encode(msg: Message, limits: Limits = DEFAULT_LIMITS) -> bytes:
    """Encode a message. Raises :class:`CodecError` if it is not a valid, encodable message."""
    return _write(msg, limits).finish()


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

_BE_U16 = struct.Struct(">H").unpack_from
_BE_U32 = struct.Struct(">I").unpack_from
_BE_U64 = struct.Struct(">Q").unpack_from
_BE_I8 = struct.Struct(">b").unpack_from
_BE_I16 = struct.Struct(">h").unpack_from
_BE_I32 = struct.Struct(">i").unpack_from
_BE_I64 = struct.Struct(">q").unpack_from
_BE_F32 = struct.Struct(">f").unpack_from
_BE_F64 = struct.Struct(">d").unpack_from

# Fixed-width scalars: first byte -> (width, unpack function).
_FIXED_SCALARS = {
    0xCA: (4, _BE_F32), 0xCB: (8, _BE_F64),
    0xCC: (1, struct.Struct(">B").unpack_from), 0xCD: (2, _BE_U16), 0xCE: (4, _BE_U32), 0xCF: (8, _BE_U64),
    0xD0: (1, _BE_I8), 0xD1: (2, _BE_I16), 0xD2: (4, _BE_I32), 0xD3: (8, _BE_I64),
}
# Length-prefixed values: first byte -> (kind, width of the length, unpack function of the length).
_SIZED = {
    0xC4: ("bin", 1, None), 0xC5: ("bin", 2, _BE_U16), 0xC6: ("bin", 4, _BE_U32),
    0xC7: ("ext", 1, None), 0xC8: ("ext", 2, _BE_U16), 0xC9: ("ext", 4, _BE_U32),
    0xD9: ("str", 1, None), 0xDA: ("str", 2, _BE_U16), 0xDB: ("str", 4, _BE_U32),
    0xDC: ("list", 2, _BE_U16), 0xDD: ("list", 4, _BE_U32),
    0xDE: ("map", 2, _BE_U16), 0xDF: ("map", 4, _BE_U32),
}
_FIXEXT_LEN = {0xD4: 1, 0xD5: 2, 0xD6: 4, 0xD7: 8, 0xD8: 16}


class _Reader:
    """Recursive-descent msgpack reader; arrays come out as views of ``data``.

    ``data`` is the caller's ``bytes``/``bytearray`` itself when possible (slicing those for
    strings is several times cheaper than slicing a memoryview), otherwise a 1-D byte
    memoryview. Hot paths inline their bounds checks: this runs per field of every message.
    """

    __slots__ = ("data", "pos", "end", "limits")

    def __init__(self, data: bytes | bytearray | memoryview, limits: Limits) -> None:
        self.data = data
        self.pos = 0
        self.end = len(data)
        self.limits = limits

    def _truncated(self, n: int, at: int) -> CodecError:
        return CodecError("malformed", f"truncated: need {n} bytes at offset {at}, have {self.end - at}")

    def _take(self, n: int) -> int:
        """Claim the next ``n`` bytes; return their start offset."""
        start = self.pos
        if n > self.end - start:
            raise self._truncated(n, start)
        self.pos = start + n
        return start

    def value(self, depth: int) -> Any:
        pos = self.pos
        if pos >= self.end:
            raise self._truncated(1, pos)
        data = self.data
        b = data[pos]
        pos += 1
        self.pos = pos
        if 0xA0 <= b <= 0xBF:  # fixstr, the most common value (every map key): inlined
            n = b & 0x1F
            if n > self.limits.max_str_len:
                raise CodecError("oversize", f"string of {n} bytes > {self.limits.max_str_len}")
            stop = pos + n
            if stop > self.end:
                raise self._truncated(n, pos)
            self.pos = stop
            try:
                return str(data[pos:stop], "utf-8")
            except UnicodeDecodeError as exc:
                raise CodecError("malformed", f"invalid UTF-8 at offset {pos}") from exc
        if b <= 0x7F:
            return b
        if b >= 0xE0:
            return b - 0x100
        if b <= 0x8F:
            return self.mapping(b & 0x0F, depth + 1)
        if b <= 0x9F:
            return self.sequence(b & 0x0F, depth + 1)
        if 0xC7 <= b <= 0xC9:  # ext 8/16/32 (arrays): skip the generic sized-value dispatch
            width = 1 << (b - 0xC7)
            if pos + width + 1 > self.end:
                raise self._truncated(width + 1, pos)
            n = data[pos] if width == 1 else (_BE_U16 if width == 2 else _BE_U32)(data, pos)[0]
            self.pos = pos + width
            return self.ext(n)
        if b == 0xC0:
            return None
        if b == 0xC2:
            return False
        if b == 0xC3:
            return True
        fixed = _FIXED_SCALARS.get(b)
        if fixed is not None:
            width, unpack = fixed
            return unpack(self.data, self._take(width))[0]
        sized = _SIZED.get(b)
        if sized is not None:
            return self._sized(sized, depth)
        n = _FIXEXT_LEN.get(b)
        if n is not None:
            return self.ext(n)
        raise CodecError("malformed", f"invalid msgpack type byte 0x{b:02x} at offset {pos}")

    def _sized(self, sized: tuple, depth: int) -> Any:
        kind, width, unpack = sized
        start = self._take(width)
        n = self.data[start] if unpack is None else unpack(self.data, start)[0]
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
        start = self.pos
        stop = start + n
        if stop > self.end:
            raise self._truncated(n, start)
        self.pos = stop
        try:
            return str(self.data[start:stop], "utf-8")
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
        value = self.value
        data, end, max_str = self.data, self.end, self.limits.max_str_len
        for _ in range(n):
            pos = self.pos
            b = data[pos] if pos < end else 0
            if 0xA0 <= b <= 0xBF and (b & 0x1F) <= max_str and pos + 1 + (b & 0x1F) <= end:
                # a short str key (every key the reference encoder writes): read inline
                stop = pos + 1 + (b & 0x1F)
                try:
                    key = str(data[pos + 1:stop], "utf-8")
                except UnicodeDecodeError as exc:
                    raise CodecError("malformed", f"invalid UTF-8 at offset {pos + 1}") from exc
                self.pos = stop
            else:
                key = value(depth)
                if type(key) is not str:
                    raise CodecError("schema", f"map key {key!r} is not a str")
            if key in out:
                raise CodecError("schema", f"duplicate map key {key!r}")
            out[key] = value(depth)
        return out

    def ext(self, n: int) -> np.ndarray:
        code_at = self._take(1)
        code = _BE_I8(self.data, code_at)[0]
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
        # One constructor call: a view of `data` (half the cost of frombuffer + reshape).
        return np.ndarray(shape, dtype, data, p)


def _as_byte_sequence(buf: Any) -> bytes | bytearray | memoryview:
    """``buf`` itself if it is bytes/bytearray, else a flat byte memoryview of it."""
    if type(buf) is bytes or type(buf) is bytearray:
        return buf
    try:
        mv = memoryview(buf)
        if mv.ndim != 1 or mv.format != "B":
            mv = mv.cast("B")  # needs C-contiguity; a strided view is refused here
    except (TypeError, ValueError) as exc:
        raise CodecError("malformed", f"not a contiguous bytes-like object: {type(buf).__name__}") from exc
    return mv


def _read_top(data: bytes | bytearray | memoryview, limits: Limits) -> dict:
    reader = _Reader(data, limits)
    top = reader.value(0)
    if reader.pos != reader.end:
        raise CodecError("malformed", f"{reader.end - reader.pos} trailing bytes")
    if not isinstance(top, dict):
        raise CodecError("schema", f"top level is {type(top).__name__}, expected map")
    if top.keys() != {"v", "t", "b"}:
        raise CodecError("schema", f"top-level keys {sorted(top)}, expected ['b', 't', 'v']")
    return top


def _schema_for(top: dict, expect: type | tuple[type, ...] | None) -> _Schema:
    version = top["v"]
    if type(version) is not int or version != SCHEMA_VERSION:
        raise CodecError("schema", f"schema version {version!r}, this codec speaks {SCHEMA_VERSION}")
    tag = top["t"]
    schema = _SCHEMAS_BY_TAG.get(tag) if isinstance(tag, str) else None
    if schema is None:
        raise CodecError("schema", f"unknown message type {tag!r}")
    if expect is not None and not issubclass(schema.cls, expect):
        raise CodecError("type", f"got {schema.cls.__name__}, expected {expect}")
    return schema


def _build(schema: _Schema, body: Any) -> Message:
    if not isinstance(body, dict):
        raise CodecError("schema", f"body is {type(body).__name__}, expected map")
    if body.keys() != schema.names:
        missing = sorted(schema.names - body.keys())
        extra = sorted(body.keys() - schema.names)
        raise CodecError("schema", f"{schema.tag}: missing fields {missing}, unknown fields {extra}")
    kwargs = {name: check(body[name], name) for name, check in schema.fields}
    msg = schema.cls(**kwargs)
    msg.validate()
    return msg


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
        data = _as_byte_sequence(buf)
        if len(data) > limits.max_message_bytes:
            raise CodecError("oversize", f"message {len(data)} bytes > {limits.max_message_bytes}")
        top = _read_top(data, limits)
        return _build(_schema_for(top, expect), top["b"])
    except CodecError:
        raise
    except Exception as exc:
        # Safety net: whatever slipped past the explicit checks is still just a bad packet.
        raise CodecError("malformed", f"{type(exc).__name__}: {exc}") from exc
