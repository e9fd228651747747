"""A message laid out in its own wire bytes: fill its arrays in place, send it without encoding.

A rollout writes every step of a trajectory chunk into arrays anyway. With a :class:`WireBuffer`
those arrays are views of the bytes that go on the wire, so publishing a chunk costs no encoding
pass and no copy of the array data on the sender: only the few scalars that change per chunk
(``seq``, ``policy_version``, ``created_ns``) are packed into their slots, range-checked.

    wb = WireBuffer(template_chunk, wide=("seq", "policy_version", "created_ns"))
    wb.msg.actions[t] = actions            # writes straight into the wire bytes
    wb.seal(seq=7, policy_version=3, created_ns=time.time_ns())
    fabric.publish_traj(wb)                # Zenoh copies wb.buf during the put

The bytes are exactly a message :func:`dvla.fabric.codec.encode` could have produced, except
that the ``wide`` integer fields always use msgpack's 64-bit forms (``0xcf``/``0xd3``), which
every msgpack decoder accepts (docs/wire-format.md). The buffer is reusable once a publish has
returned; keep a pool of them to overlap filling one with sending another.
"""

from __future__ import annotations

import dataclasses
import struct
from typing import Any

from .codec import _DTYPES_BY_WIRE_NAME, _SCHEMAS_BY_CLASS, encode_into, learn_layout
from .errors import CodecError
from .layout import _SCALAR
from .messages import Message

_WIDE = 2**63 - 1
"""A template value that makes msgpack write the field as a uint64: its slot then holds any
value from 0 to 2**64 - 1 without changing the layout."""


class WireBuffer:
    """One message's wire bytes (``buf``) and a message whose arrays are writable views of them.

    ``wide`` names integer fields that change from message to message; every other scalar
    (strings, the rest of the integers) keeps the template's value. Arrays keep their shapes
    and dtypes; their contents are whatever was last written into ``msg``'s arrays.
    """

    def __init__(self, template: Message, wide: tuple[str, ...] = ()) -> None:
        schema = _SCHEMAS_BY_CLASS.get(type(template))
        if schema is None:
            raise CodecError("type", f"not a fabric message: {type(template).__name__}")
        for name in wide:
            if type(getattr(template, name, None)) is not int:
                raise CodecError("type", f"{type(template).__name__}.{name}: a wide field must be an int")
        self.buf = bytearray()
        encode_into(dataclasses.replace(template, **{name: _WIDE for name in wide}), self.buf, layouts=False)
        layout = learn_layout(self.buf, schema, _DTYPES_BY_WIRE_NAME)
        if layout is None:
            raise CodecError("type", f"{type(template).__name__} has no fixed layout (lists or free-form maps)")
        self.layout = layout
        self._scalars: dict[str, tuple[int, Any]] = {}
        for kind, name, key, off, arg in layout.slots:
            if name in wide and key is None and kind == _SCALAR:
                self._scalars[name] = (off, arg)
        missing = set(wide) - set(self._scalars)
        if missing:
            raise CodecError("type", f"{type(template).__name__}: no 64-bit slot for {sorted(missing)}")
        #: the message as laid out; write into its arrays (views of ``buf``), never rebind them
        self.seal(**{name: getattr(template, name) for name in wide})
        self.msg: Any = self.message()
        self.nbytes = len(self.buf)

    def seal(self, **values: int) -> None:
        """Pack the given wide fields into their slots. Raises :class:`CodecError` for a value
        that is not an int in the slot's range (nothing else can have changed: the arrays are
        views with fixed shapes and dtypes, every other field is fixed by the template, and the
        message's value checks ran once on the template)."""
        for name, value in values.items():
            slot = self._scalars.get(name)
            if slot is None:
                raise CodecError("type", f"{name!r} is not a wide field of this buffer")
            if type(value) is not int:
                raise CodecError("type", f"{name}: expected int, got {type(value).__name__}")
            off, st = slot
            try:
                st.pack_into(self.buf, off, value)
            except struct.error as exc:  # out of the slot's range
                raise CodecError("type", f"{name}: {value} does not fit a 64-bit msgpack integer") from exc

    def message(self) -> Any:
        """The message as a receiver decodes it now (arrays are views of ``buf``); runs the
        message's value checks."""
        msg = self.layout.build(self.buf)
        if msg is None:
            raise CodecError("schema", f"{self.layout.cls.__name__} wire buffer no longer matches its layout")
        return msg
