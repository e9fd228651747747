"""Signed envelopes: a keyed BLAKE3 tag with the run secret, plus the sender's Ed25519 signature.

A :class:`Signer` wraps an encoded payload in an envelope, a :class:`Verifier` checks it and
returns the payload. The tag (one secret per run, :func:`load_secret`) proves run membership
and covers the key expression and an optional *binding* (a query's nonce); with an
:class:`~dvla.fabric.identity.Identity` the sender also signs the tag and ships its certificate,
so a receiver knows which member sent it (:func:`dvla.fabric.identity.authorize` decides what it
may send). Layout, freshness and the replay horizon: docs/wire-format.md, section 4; bounded
memory whatever the message rate: docs/security.md.

Keyed BLAKE3 (the ``blake3`` package) rather than HMAC-SHA256, and libsodium's Ed25519 (PyNaCl)
rather than OpenSSL's: on 256 KiB trajectory chunks the tag costs ~60 instead of ~230 us a side
and a signature check ~60 instead of ~130-170 us (docs/benchmarks.md, "Authentication").
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

import blake3

from dvla.fabric.errors import SecretError, SignatureError
from dvla.fabric.identity import PUBLIC_BYTES, SIGNATURE_BYTES, Identity, verify_certificate, verify_signature

__all__ = [
    "MAGIC",
    "MIN_SECRET_BYTES",
    "Opened",
    "SecretError",
    "SignatureError",
    "Signer",
    "Verifier",
    "key_id",
    "load_secret",
    "new_secret",
]

MAGIC = b"DVS4"
"""First bytes of every signed envelope (DVS4: keyed BLAKE3 tag; DVS3 used HMAC-SHA256, DVS2 did
not pad the payload; both are refused as ``unsigned``)."""

_OLD_MAGICS = (b"DVS2", b"DVS3")

MAC_CONTEXT = "dvla 2026-11 envelope tag v4"
"""BLAKE3 key-derivation context: the tag key is ``BLAKE3.derive_key(MAC_CONTEXT, secret)``."""

PAYLOAD_ALIGN = 8
"""Zero bytes after the identity block put the payload at a multiple of this from the envelope's
start, so the arrays of a received message stay aligned views of the received buffer."""

MIN_SECRET_BYTES = 16
"""Shortest accepted shared secret."""

NONCE_BYTES = 16
TAG_BYTES = 32
_HEAD = struct.Struct("<4s4sBB")  # magic, key_id, flags, sender_len
_TS_NONCE_LEN = struct.Struct("<Q16sI")  # ts_ns, nonce, payload_len
_KEY_LEN = struct.Struct("<H")
_FLAG_IDENTITY = 1
_SIG_DOMAIN = b"dvla-sig1"
_MIN_ENVELOPE = _HEAD.size + 1 + _TS_NONCE_LEN.size + TAG_BYTES  # one-byte sender, empty payload
#: verified (run-independent) certificates remembered, and senders with a replay horizon
_CERT_CACHE = 4096
_HORIZONS = 65536


def _check_secret(secret: bytes) -> bytes:
    if not isinstance(secret, (bytes, bytearray)):
        raise SecretError(f"secret must be bytes, got {type(secret).__name__}")
    if len(secret) < MIN_SECRET_BYTES:
        raise SecretError(f"secret is {len(secret)} bytes, need at least {MIN_SECRET_BYTES}")
    return bytes(secret)


def key_id(secret: bytes) -> bytes:
    """The 4-byte identifier of a secret carried by every envelope it signs (rotation: a
    receiver tells "signed with another key" from "forged")."""
    return hashlib.sha256(b"dvla-key-id" + secret).digest()[:4]


def mac_key(secret: bytes) -> bytes:
    """The 32-byte key of every tag made with ``secret`` (BLAKE3 in key-derivation mode)."""
    return blake3.blake3(secret, derive_key_context=MAC_CONTEXT).digest()


def _mac_prefix(key_expr: str, bind: bytes) -> bytes:
    """Length-prefixed key expression and binding, so boundaries are unambiguous."""
    key = key_expr.encode("utf-8")
    if len(key) > 0xFFFF or len(bind) > 0xFF:
        raise ValueError(f"key expression of {len(key)} bytes or binding of {len(bind)} bytes is too long")
    return _KEY_LEN.pack(len(key)) + key + bytes((len(bind),)) + bind


def _pad_after(header_len: int) -> int:
    return -header_len % PAYLOAD_ALIGN


def nonce_of(envelope: bytes | bytearray | memoryview) -> bytes:
    """The nonce of an envelope this process sealed (what a query's reply must be bound to)."""
    env = memoryview(envelope)
    start = _HEAD.size + env[_HEAD.size - 1] + 8
    return bytes(env[start: start + NONCE_BYTES])


class Signer:
    """Seals payloads as ``sender`` (with ``identity``'s signature when given); thread-safe."""

    def __init__(self, secret: bytes, sender: str, *, identity: Identity | None = None,
                 clock: Callable[[], int] = time.time_ns) -> None:
        self._secret = _check_secret(secret)
        self._kid = key_id(self._secret)
        self._mac_key = mac_key(self._secret)
        if identity is not None:
            sender = identity.name
        name = sender.encode("utf-8")
        if not 1 <= len(name) <= 255:
            raise ValueError(f"sender name must be 1..255 UTF-8 bytes, got {len(name)}")
        self.sender = sender
        self.identity = identity
        self._sender_field = bytes((len(name),)) + name
        self._ident_block = b""
        if identity is not None:
            kind = identity.kind.encode("utf-8")
            self._ident_block = bytes((len(kind),)) + kind + identity.public + identity.certificate
        self._flags = _FLAG_IDENTITY if identity is not None else 0
        self._pad = bytes(_pad_after(_HEAD.size + len(name) + _TS_NONCE_LEN.size + len(self._ident_block)))
        self._clock = clock

    def seal(self, key_expr: str, payload: bytes | bytearray | memoryview, *, bind: bytes = b"") -> bytes:
        """Return the envelope carrying ``payload`` for publication on ``key_expr`` (bound to
        ``bind``: a query's nonce when this is its reply)."""
        size = memoryview(payload).nbytes
        if size > 0xFFFFFFFF:
            raise ValueError(f"payload of {size} bytes exceeds the uint32 length field")
        header = b"".join((_HEAD.pack(MAGIC, self._kid, self._flags, self._sender_field[0]), self._sender_field[1:],
                           _TS_NONCE_LEN.pack(self._clock(), os.urandom(NONCE_BYTES), size), self._ident_block,
                           self._pad))
        mac = blake3.blake3(_mac_prefix(key_expr, bind), key=self._mac_key)
        mac.update(header)
        mac.update(payload)
        tag = mac.digest()
        sig = self.identity.sign(_SIG_DOMAIN + tag) if self.identity is not None else b""
        return b"".join((header, payload, tag, sig))


class Opened(NamedTuple):
    """A verified envelope: who sent it (``kind`` "" without an identity block) and its payload
    (a view of the envelope's bytes)."""

    sender: str
    kind: str
    payload: memoryview
    nonce: bytes


class _Parsed(NamedTuple):
    key_id: bytes
    sender: str
    ts_ns: int
    nonce: bytes
    kind: str
    public: bytes
    cert: bytes
    payload_start: int
    body_end: int
    sig: bytes


def _parse(env: memoryview) -> _Parsed:
    """Split an envelope into its fields; raises SignatureError(unsigned|malformed)."""
    if len(env) < len(MAGIC) or env[: len(MAGIC)] != MAGIC:
        if bytes(env[: len(MAGIC)]) in _OLD_MAGICS:
            raise SignatureError("unsigned", f"envelope version {bytes(env[:4]).decode()} is no longer accepted "
                                 f"(this receiver reads {MAGIC.decode()}: upgrade the sender)")
        raise SignatureError("unsigned", f"no {MAGIC.decode()} envelope magic")
    if len(env) < _MIN_ENVELOPE:
        raise SignatureError("malformed", f"envelope of {len(env)} bytes is too short")
    _, kid, flags, sender_len = _HEAD.unpack_from(env, 0)
    pos = _HEAD.size + sender_len
    if sender_len == 0 or pos + _TS_NONCE_LEN.size + TAG_BYTES > len(env) or flags & ~_FLAG_IDENTITY:
        raise SignatureError("malformed", f"bad sender length {sender_len} or flags {flags}")
    ts_ns, nonce, payload_len = _TS_NONCE_LEN.unpack_from(env, pos)
    pos += _TS_NONCE_LEN.size
    kind, public, cert, sig_len = "", b"", b"", 0
    try:
        sender = str(env[_HEAD.size: _HEAD.size + sender_len], "utf-8")
        if flags & _FLAG_IDENTITY:
            kind_len = env[pos] if pos < len(env) else 0
            kind = str(env[pos + 1: pos + 1 + kind_len], "utf-8")
            pos += 1 + kind_len
            public = bytes(env[pos: pos + PUBLIC_BYTES])
            cert = bytes(env[pos + PUBLIC_BYTES: pos + PUBLIC_BYTES + SIGNATURE_BYTES])
            pos += PUBLIC_BYTES + SIGNATURE_BYTES
            sig_len = SIGNATURE_BYTES
    except UnicodeDecodeError as exc:
        raise SignatureError("malformed", "sender or kind is not UTF-8") from exc
    pad = _pad_after(pos)
    if any(env[pos: pos + pad]):
        raise SignatureError("malformed", "non-zero padding before the payload")
    pos += pad
    if pos + payload_len + TAG_BYTES + sig_len != len(env):
        raise SignatureError("malformed", f"payload length {payload_len} disagrees with envelope size {len(env)}")
    body_end = pos + payload_len
    sig = bytes(env[body_end + TAG_BYTES:])
    return _Parsed(bytes(kid), sender, ts_ns, nonce, kind, public, cert, pos, body_end, sig)


class Verifier:
    """Checks envelopes sealed with the same secret; thread-safe. With ``operator`` (the run's
    operator public key) and ``run``, every envelope must also carry an identity that operator
    certified. ``clock`` (ns) must be the wall clock outside tests: timestamps come from other hosts.
    """

    def __init__(self, secret: bytes, max_age_s: float = 30.0, replay_window: int = 4096, *,
                 operator: bytes | None = None, run: str = "", clock: Callable[[], int] = time.time_ns) -> None:
        self._secret = _check_secret(secret)
        self._kid = key_id(self._secret)
        self._mac_key = mac_key(self._secret)
        if max_age_s <= 0 or replay_window < 1:
            raise ValueError("max_age_s must be > 0 and replay_window >= 1")
        self.max_age_ns = int(max_age_s * 1e9)
        self.replay_window = replay_window
        if operator is not None and len(operator) != PUBLIC_BYTES:
            raise ValueError(f"operator public key must be {PUBLIC_BYTES} bytes, got {len(operator)}")
        self._operator = bytes(operator) if operator is not None else None
        self._run = run
        self._clock = clock
        self._lock = threading.Lock()
        self._seen: OrderedDict[bytes, tuple[str, int]] = OrderedDict()  # nonce -> (sender, ts), arrival order
        self._horizon: dict[str, int] = {}  # sender -> newest ts among forgotten nonces
        self._floor = -1  # horizon of every sender once the horizon map overflowed
        self._certs: OrderedDict[tuple[str, str, bytes, bytes], None] = OrderedDict()  # verified certificates

    @property
    def nonces_held(self) -> int:
        """Nonces remembered against replays: at most ``replay_window``, none older than ``max_age_s``."""
        with self._lock:
            return len(self._seen)

    def open(self, key_expr: str, envelope: bytes | bytearray | memoryview, *, bind: bytes = b"",
             fresh: bool = True, received_ns: int | None = None) -> Opened:
        """Verify and return an :class:`Opened`, or raise :class:`SignatureError`.

        ``fresh=False`` skips the timestamp and replay checks (an old envelope kept as proof,
        e.g. the actor's manifest inside a snapshot reply). ``received_ns``: when this receiver
        took the envelope off the wire, by its own ``clock``; the timestamp's age is judged then,
        so an envelope that waited in the receiver's own bounded queue is not stale (None: now)."""
        env = self._view(envelope)
        parsed = _parse(env)
        if parsed.key_id != self._kid:
            raise SignatureError("key_id", f"signed with key id {parsed.key_id.hex()}, ours is {self._kid.hex()} "
                                 f"(claimed sender {parsed.sender!r}; another run, or a rotated secret)")
        tag = self._check_tag(key_expr, bind, env, parsed)
        if fresh:  # cheap checks first: a captured envelope with a flipped signature bit is a replay
            self._check_fresh(parsed, received_ns)
        if self._operator is not None:
            self._check_identity(parsed, tag)
        if fresh:
            self._remember(parsed)
        return Opened(parsed.sender, parsed.kind, env[parsed.payload_start: parsed.body_end], parsed.nonce)

    @staticmethod
    def _view(envelope: object) -> memoryview:
        try:
            env = memoryview(envelope)  # type: ignore[arg-type]
            return env if env.ndim == 1 and env.format == "B" else env.cast("B")
        except (TypeError, ValueError) as exc:
            raise SignatureError("unsigned", f"not a bytes-like object: {type(envelope).__name__}") from exc

    def _check_tag(self, key_expr: str, bind: bytes, env: memoryview, parsed: _Parsed) -> bytes:
        try:
            mac = blake3.blake3(_mac_prefix(key_expr, bind), key=self._mac_key)
        except (UnicodeEncodeError, ValueError) as exc:
            raise SignatureError("bad_signature", "key expression cannot have been signed") from exc
        mac.update(env[: parsed.body_end])
        tag = mac.digest()
        if not hmac.compare_digest(tag, env[parsed.body_end: parsed.body_end + TAG_BYTES]):
            raise SignatureError("bad_signature", f"tag mismatch (claimed sender {parsed.sender!r})")
        return tag

    def _check_identity(self, parsed: _Parsed, tag: bytes) -> None:
        assert self._operator is not None
        if not parsed.sig:
            raise SignatureError("no_identity", f"no identity block (claimed sender {parsed.sender!r})")
        entry = (parsed.sender, parsed.kind, parsed.public, parsed.cert)
        with self._lock:
            known = entry in self._certs
        if not known:
            if not verify_certificate(self._operator, self._run, parsed.kind, parsed.sender, parsed.public, parsed.cert):
                raise SignatureError("bad_identity", f"certificate of {parsed.sender!r} ({parsed.kind}) not issued by this run's operator")
            with self._lock:
                self._certs[entry] = None
                while len(self._certs) > _CERT_CACHE:
                    self._certs.popitem(last=False)
        if not verify_signature(parsed.public, _SIG_DOMAIN + tag, parsed.sig):
            raise SignatureError("bad_identity", f"signature of {parsed.sender!r} does not verify")

    def _check_fresh(self, parsed: _Parsed, received_ns: int | None = None) -> None:
        """Raise stale/replay without remembering anything (the identity is not checked yet)."""
        now = self._clock()
        if received_ns is not None:
            now = min(now, received_ns)  # never later than now: a receive time cannot extend a timestamp's life
        age = now - parsed.ts_ns
        if abs(age) > self.max_age_ns:
            raise SignatureError("stale", f"timestamp off by {age / 1e9:.3f}s (limit {self.max_age_ns / 1e9:.3f}s)")
        with self._lock:
            self._forget_older_than(now - self.max_age_ns)
            self._check_unseen(parsed)

    def _check_unseen(self, parsed: _Parsed) -> None:
        if parsed.nonce in self._seen:
            raise SignatureError("replay", f"nonce already seen from {parsed.sender!r}")
        if parsed.ts_ns <= max(self._horizon.get(parsed.sender, -1), self._floor):
            raise SignatureError("stale", f"timestamp at or before {parsed.sender!r}'s replay horizon")

    def _remember(self, parsed: _Parsed) -> None:
        """Accept the nonce of a fully verified envelope (checked again: another thread may have
        accepted the same envelope meanwhile)."""
        with self._lock:
            self._check_unseen(parsed)
            self._seen[parsed.nonce] = (parsed.sender, parsed.ts_ns)
            while len(self._seen) > self.replay_window:
                self._drop_oldest()

    def _drop_oldest(self) -> None:
        _, (sender, ts) = self._seen.popitem(last=False)
        if ts > self._horizon.get(sender, -1):
            if sender not in self._horizon and len(self._horizon) >= _HORIZONS:
                # Only a holder of the secret reaches here; still bounded: forget every horizon
                # but raise a common floor, so nothing forgotten becomes replayable.
                self._floor = max(self._floor, *self._horizon.values())
                self._horizon.clear()
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
    """The run's shared secret from ``path``, else from environment variable ``env_var``: hex or raw
    bytes, surrounding whitespace ignored. :class:`SecretError` names the file or variable when
    missing, unreadable or shorter than :data:`MIN_SECRET_BYTES`."""
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
