"""Typed exceptions of the message fabric: a receiver catches :class:`FabricError` and never
guesses which library exception a malformed packet triggers; each carries a ``reason`` code to
count rejections by cause (the codes: docs/wire-format.md, docs/status.md).
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
    """A message could not be encoded or decoded: ``malformed`` (not well-formed msgpack or array
    header), ``schema`` (not a known message), ``type`` (wrong type/dtype or class), ``oversize``
    (a limit), ``shape`` (array shapes disagree with each other or the payload)."""

    REASONS = frozenset({"malformed", "schema", "type", "oversize", "shape"})


class SignatureError(_ReasonError):
    """A signed envelope was rejected: ``unsigned`` (not an envelope), ``malformed`` (broken
    framing), ``bad_signature`` (tag mismatch), ``stale`` (timestamp outside the window),
    ``replay`` (nonce seen), ``key_id`` (another secret: another run or a rotated key),
    ``no_identity`` / ``bad_identity`` (certified signature missing or not verifying),
    ``unauthorized`` (a verified sender that may not send this on this key), ``revoked`` (a
    verified sender whose credential the operator revoked, `dvla identity revoke`)."""

    REASONS = frozenset({"unsigned", "bad_signature", "stale", "replay", "malformed", "key_id", "no_identity",
                         "bad_identity", "unauthorized", "revoked"})


class SecretError(FabricError, ValueError):
    """The shared signing secret is missing, unreadable or too short."""
