"""Typed exceptions of the message fabric.

This module owns every exception that ``dvla.fabric`` raises for bad input: a receiver catches
:class:`FabricError` (or one of its subclasses) and never has to guess which library-level
exception a malformed packet might trigger. Each error carries a short ``reason`` code so that
callers can count rejections by cause without parsing messages.
"""

from __future__ import annotations


class FabricError(Exception):
    """Base class of every error raised by ``dvla.fabric`` for invalid input."""


class _ReasonError(FabricError, ValueError):
    """An error with a ``reason`` code drawn from the subclass's ``REASONS``."""

    REASONS: frozenset[str] = frozenset()

    def __init__(self, reason: str, detail: str = "") -> None:
        if reason not in self.REASONS:
            # A wrong code is a bug in the raiser; keep the accounting vocabulary closed.
            raise ValueError(f"{type(self).__name__}: unknown reason {reason!r}")
        self.reason = reason
        self.detail = detail
        super().__init__(f"{reason}: {detail}" if detail else reason)


class CodecError(_ReasonError):
    """A message could not be encoded or decoded.

    ``reason`` is one of:

    * ``malformed``: the bytes are not a well-formed message (bad msgpack, truncation,
      trailing bytes, bad array header).
    * ``schema``: well-formed, but not a known message (schema version, unknown type tag,
      missing or extra fields, non-string map keys, out-of-range values).
    * ``type``: a field or array has the wrong type/dtype, or the message is not of the
      expected class.
    * ``oversize``: a size limit was exceeded.
    * ``shape``: array shapes disagree with each other or with the payload length.
    """

    REASONS = frozenset({"malformed", "schema", "type", "oversize", "shape"})


class SignatureError(_ReasonError):
    """A signed control-plane envelope was rejected.

    ``reason`` is one of ``unsigned`` (not an envelope at all), ``malformed`` (an envelope
    whose framing is broken), ``bad_signature`` (tag mismatch: wrong secret, or any signed
    byte changed), ``stale`` (timestamp outside the accepted window), ``replay`` (nonce
    already seen), ``key_id`` (signed with another secret: another run or a rotated key),
    ``no_identity`` / ``bad_identity`` (the sender's certified signature is missing or does not
    verify) and ``unauthorized`` (a verified sender that may not send this on this key).
    """

    REASONS = frozenset({"unsigned", "bad_signature", "stale", "replay", "malformed", "key_id", "no_identity",
                         "bad_identity", "unauthorized"})


class SecretError(FabricError, ValueError):
    """The shared signing secret is missing, unreadable or too short."""
