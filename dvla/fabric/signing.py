"""HMAC-SHA256 signed envelopes for the control plane.

This module owns authentication of control messages (weights, commands, status, ...): a
:class:`Signer` wraps an already-encoded payload (see :mod:`dvla.fabric.codec`) in an envelope,
a :class:`Verifier` checks it and returns the payload. Every process of a run shares one secret
(:func:`load_secret`); the tag also covers the Zenoh key expression, so a message signed for
one key cannot be replayed on another.

Envelope layout (all integers little-endian; see docs/wire-format.md)::

    offset  size  field
    0       4     magic b"DVS1"
    4       1     sender_len (S, 1..255)
    5       S     sender, UTF-8
    5+S     8     ts_ns, uint64, sender's wall clock (ns since the Unix epoch)
    13+S    16    nonce, random
    29+S    4     payload_len (P), uint32
    33+S    P     payload
    33+S+P  32    tag = HMAC-SHA256(secret, u16 key_len | key_expr UTF-8 | bytes [0, 33+S+P))

Freshness: an envelope is accepted if ``|now - ts_ns| <= max_age`` and its nonce has not been
seen. Nonces are remembered for ``max_age`` (at most ``replay_window`` of them); when the store
is full the oldest entry is dropped and its timestamp becomes that sender's *horizon*: anything
from that sender stamped at or before it is refused as stale, so a dropped nonce can never be
replayed. Memory is therefore bounded whatever the message rate.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets
import struct
import threading
import time
from collections import OrderedDict
from typing import Callable, NamedTuple

from dvla.fabric.errors import SecretError, SignatureError

__all__ = [
    "MAGIC",
    "MIN_SECRET_BYTES",
    "SecretError",
    "SignatureError",
    "Signer",
    "Verifier",
    "load_secret",
    "new_secret",
]

MAGIC = b"DVS1"
"""First bytes of every signed envelope."""

MIN_SECRET_BYTES = 16
"""Shortest accepted shared secret."""

NONCE_BYTES = 16
TAG_BYTES = 32
_TS_NONCE_LEN = struct.Struct("<Q16sI")  # ts_ns, nonce, payload_len
_KEY_LEN = struct.Struct("<H")
_MIN_ENVELOPE = len(MAGIC) + 1 + 1 + _TS_NONCE_LEN.size + TAG_BYTES  # one-byte sender, empty payload


def _check_secret(secret: bytes) -> bytes:
    if not isinstance(secret, (bytes, bytearray)):
        raise SecretError(f"secret must be bytes, got {type(secret).__name__}")
    if len(secret) < MIN_SECRET_BYTES:
        raise SecretError(f"secret is {len(secret)} bytes, need at least {MIN_SECRET_BYTES}")
    return bytes(secret)


def _key_prefix(key_expr: str) -> bytes:
    """Length-prefixed key expression, so (key, header) boundaries are unambiguous."""
    key = key_expr.encode("utf-8")
    if len(key) > 0xFFFF:
        raise ValueError(f"key expression of {len(key)} bytes is too long")
    return _KEY_LEN.pack(len(key)) + key


class Signer:
    """Seals payloads as ``sender``; thread-safe (no mutable state)."""

    def __init__(self, secret: bytes, sender: str, *, clock: Callable[[], int] = time.time_ns) -> None:
        self._secret = _check_secret(secret)
        name = sender.encode("utf-8")
        if not 1 <= len(name) <= 255:
            raise ValueError(f"sender name must be 1..255 UTF-8 bytes, got {len(name)}")
        self.sender = sender
        self._sender_field = bytes((len(name),)) + name
        self._clock = clock

    def seal(self, key_expr: str, payload: bytes | bytearray | memoryview) -> bytes:
        """Return the envelope carrying ``payload`` for publication on ``key_expr``."""
        size = memoryview(payload).nbytes
        if size > 0xFFFFFFFF:
            raise ValueError(f"payload of {size} bytes exceeds the uint32 length field")
        header = b"".join((MAGIC, self._sender_field,
                           _TS_NONCE_LEN.pack(self._clock(), os.urandom(NONCE_BYTES), size)))
        mac = hmac.new(self._secret, _key_prefix(key_expr), hashlib.sha256)
        mac.update(header)
        mac.update(payload)
        return b"".join((header, payload, mac.digest()))


class _Parsed(NamedTuple):
    sender: str
    ts_ns: int
    nonce: bytes
    payload_start: int
    body_end: int


def _parse(env: memoryview) -> _Parsed:
    """Split an envelope into its fields; raises SignatureError(unsigned|malformed)."""
    if len(env) < len(MAGIC) or env[: len(MAGIC)] != MAGIC:
        raise SignatureError("unsigned", "no DVS1 envelope magic")
    if len(env) < _MIN_ENVELOPE:
        raise SignatureError("malformed", f"envelope of {len(env)} bytes is too short")
    sender_len = env[len(MAGIC)]
    fixed_end = len(MAGIC) + 1 + sender_len + _TS_NONCE_LEN.size
    if sender_len == 0 or fixed_end + TAG_BYTES > len(env):
        raise SignatureError("malformed", f"bad sender length {sender_len}")
    ts_ns, nonce, payload_len = _TS_NONCE_LEN.unpack_from(env, fixed_end - _TS_NONCE_LEN.size)
    if fixed_end + payload_len + TAG_BYTES != len(env):
        raise SignatureError("malformed", f"payload length {payload_len} disagrees with envelope size {len(env)}")
    try:
        sender = str(env[len(MAGIC) + 1: len(MAGIC) + 1 + sender_len], "utf-8")
    except UnicodeDecodeError as exc:
        raise SignatureError("malformed", "sender is not UTF-8") from exc
    return _Parsed(sender, ts_ns, nonce, fixed_end, fixed_end + payload_len)


class Verifier:
    """Checks envelopes sealed with the same secret; thread-safe.

    ``clock`` (ns) is injectable for tests; it must be the wall clock in production because
    timestamps come from other hosts.
    """

    def __init__(self, secret: bytes, max_age_s: float = 30.0, replay_window: int = 4096, *,
                 clock: Callable[[], int] = time.time_ns) -> None:
        self._secret = _check_secret(secret)
        if max_age_s <= 0 or replay_window < 1:
            raise ValueError("max_age_s must be > 0 and replay_window >= 1")
        self.max_age_ns = int(max_age_s * 1e9)
        self.replay_window = replay_window
        self._clock = clock
        self._lock = threading.Lock()
        self._seen: OrderedDict[bytes, tuple[str, int]] = OrderedDict()  # nonce -> (sender, ts), arrival order
        self._horizon: dict[str, int] = {}  # sender -> newest ts among forgotten nonces

    def open(self, key_expr: str, envelope: bytes | bytearray | memoryview) -> tuple[str, bytes]:
        """Return ``(sender, payload)`` or raise :class:`SignatureError`."""
        env = self._view(envelope)
        parsed = _parse(env)
        self._check_tag(key_expr, env, parsed)
        self._check_fresh(parsed)
        return parsed.sender, bytes(env[parsed.payload_start: parsed.body_end])

    @staticmethod
    def _view(envelope: object) -> memoryview:
        try:
            env = memoryview(envelope)  # type: ignore[arg-type]
            return env if env.ndim == 1 and env.format == "B" else env.cast("B")
        except (TypeError, ValueError) as exc:
            raise SignatureError("unsigned", f"not a bytes-like object: {type(envelope).__name__}") from exc

    def _check_tag(self, key_expr: str, env: memoryview, parsed: _Parsed) -> None:
        try:
            mac = hmac.new(self._secret, _key_prefix(key_expr), hashlib.sha256)
        except (UnicodeEncodeError, ValueError) as exc:
            raise SignatureError("bad_signature", "key expression cannot have been signed") from exc
        mac.update(env[: parsed.body_end])
        if not hmac.compare_digest(mac.digest(), env[parsed.body_end:]):
            raise SignatureError("bad_signature", f"tag mismatch (claimed sender {parsed.sender!r})")

    def _check_fresh(self, parsed: _Parsed) -> None:
        now = self._clock()
        age = now - parsed.ts_ns
        if abs(age) > self.max_age_ns:
            raise SignatureError("stale", f"timestamp off by {age / 1e9:.3f}s (limit {self.max_age_ns / 1e9:.3f}s)")
        with self._lock:
            self._forget_older_than(now - self.max_age_ns)
            if parsed.nonce in self._seen:
                raise SignatureError("replay", f"nonce already seen from {parsed.sender!r}")
            if parsed.ts_ns <= self._horizon.get(parsed.sender, -1):
                raise SignatureError("stale", f"timestamp at or before {parsed.sender!r}'s replay horizon")
            self._seen[parsed.nonce] = (parsed.sender, parsed.ts_ns)
            while len(self._seen) > self.replay_window:
                self._drop_oldest()

    def _drop_oldest(self) -> None:
        _, (sender, ts) = self._seen.popitem(last=False)
        if ts > self._horizon.get(sender, -1):
            self._horizon[sender] = ts

    def _forget_older_than(self, cutoff_ns: int) -> None:
        # Arrival order only approximates timestamp order; stopping at the first young entry
        # is fine because every dropped entry still raises its sender's horizon.
        while self._seen:
            _, (_, ts) = next(iter(self._seen.items()))
            if ts >= cutoff_ns:
                break
            self._drop_oldest()


def new_secret() -> str:
    """A fresh random 32-byte secret, hex encoded (store it in a file or ``DVLA_SECRET``)."""
    return secrets.token_hex(32)


def _secret_from_text(raw: bytes, origin: str) -> bytes:
    """Strip surrounding whitespace; decode as hex when it is hex, else use the bytes as-is."""
    text = raw.strip()
    if text and len(text) % 2 == 0 and all(c in b"0123456789abcdefABCDEF" for c in text):
        text = bytes.fromhex(text.decode("ascii"))
    if len(text) < MIN_SECRET_BYTES:
        raise SecretError(f"secret from {origin} is {len(text)} bytes, need at least {MIN_SECRET_BYTES} "
                          f"(generate one with dvla.fabric.signing.new_secret())")
    return text


def load_secret(path: str | None, env_var: str = "DVLA_SECRET") -> bytes:
    """Load the run's shared secret from ``path`` if given, else from environment variable ``env_var``.

    The content may be hex (decoded) or raw bytes (used as-is); surrounding whitespace is ignored
    so ``echo <secret> > file`` and ``export DVLA_SECRET=<secret>`` give the same key.
    Raises :class:`SecretError` naming the file or variable when missing, unreadable or shorter
    than :data:`MIN_SECRET_BYTES` bytes.
    """
    if path is not None:
        try:
            with open(path, "rb") as f:
                raw = f.read()
        except OSError as exc:
            raise SecretError(f"cannot read secret file {path!r}: {exc.strerror or exc}") from exc
        return _secret_from_text(raw, f"file {path!r}")
    value = os.environ.get(env_var)
    if not value:
        raise SecretError(f"no secret: environment variable {env_var} is unset or empty and no secret file was given")
    return _secret_from_text(value.encode("utf-8"), f"environment variable {env_var}")
