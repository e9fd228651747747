"""Who sent a message: per-process Ed25519 identities certified by the run's operator key.

The run secret proves a message comes from *a* member of the run; an :class:`Identity` says which.
The operator (``dvla up`` and tools sharing its run directory) certifies a fresh key pair per
process (its signature over ``(run, kind, name, public key)``); receivers check the certificate,
the signature, then :func:`authorize`, so a compromised rollout can sign as itself only
(docs/security.md). Credentials travel in one environment variable (:data:`IDENTITY_ENV`, never a
command line): ``dvla-id1:<run>:<kind>:<name>:<seed hex>:<certificate hex>:<operator public hex>``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from nacl.exceptions import BadSignatureError
from nacl.signing import SigningKey, VerifyKey

from .keys import KeySpace, check_name

__all__ = ["IDENTITY_ENV", "KINDS", "OPERATOR", "REVOKED_FILE", "Identity", "IdentityError", "authorize",
           "certificate_message", "read_revoked", "verify_certificate", "verify_signature"]

#: environment variable carrying a process's credential
IDENTITY_ENV = "DVLA_IDENTITY"
#: kind (and name) of the operator's own identity: dvla up, dvla status / stop, the monitor
OPERATOR = "operator"
#: every kind of identity dvla issues
KINDS = (OPERATOR, "actor", "replicator", "rollout", "evaluator", "router")
#: names whose credentials the operator revoked, one a line, in the run directory
REVOKED_FILE = "revoked"
_PREFIX = "dvla-id1"
PUBLIC_BYTES = 32
SIGNATURE_BYTES = 64


class IdentityError(ValueError):
    """A credential that cannot be parsed or does not hold together."""


def _public_bytes(key: SigningKey) -> bytes:
    return bytes(key.verify_key)


def _signing_key(seed: bytes | None) -> SigningKey:
    return SigningKey(seed) if seed is not None else SigningKey.generate()


def verify_signature(public: bytes, message: bytes, signature: bytes) -> bool:
    """Whether `signature` is `public`'s pure Ed25519 (RFC 8032) signature of `message` (libsodium,
    which also refuses small-order and non-canonical keys)."""
    try:
        VerifyKey(public).verify(message, signature)
        return True
    except (BadSignatureError, ValueError, TypeError):
        return False


def certificate_message(run: str, kind: str, name: str, public: bytes) -> bytes:
    """What the operator signs to certify `public` as `name` of `kind` in `run`."""
    return b"\0".join((b"dvla-cert1", run.encode(), kind.encode(), name.encode(), public))


def verify_certificate(operator: bytes, run: str, kind: str, name: str, public: bytes, cert: bytes) -> bool:
    """Whether `cert` is the `operator` (public key) certificate of `public` as `name` of `kind` in `run`."""
    return verify_signature(operator, certificate_message(run, kind, name, public), cert)


@dataclass(frozen=True)
class Identity:
    """One process's signing key, with the certificate that names it and the operator's public
    key (what it checks everybody else's certificates against)."""

    run: str
    kind: str
    name: str
    key: SigningKey
    certificate: bytes
    operator_public: bytes

    @property
    def public(self) -> bytes:
        return _public_bytes(self.key)

    def sign(self, data: bytes) -> bytes:
        return self.key.sign(data).signature

    # -- issuing (the operator) ----------------------------------------------------------------
    @staticmethod
    def operator(run: str, seed: bytes | None = None) -> "Identity":
        """The operator's identity (self-certified): a fresh key, or the one from `seed`."""
        key = _signing_key(seed)
        public = _public_bytes(key)
        cert = key.sign(certificate_message(run, OPERATOR, OPERATOR, public)).signature
        return Identity(run, OPERATOR, OPERATOR, key, cert, public)

    def issue(self, kind: str, name: str, seed: bytes | None = None) -> "Identity":
        """A fresh identity (or the one of the 32-byte `seed`) for process `name` of `kind`,
        certified by this (operator) identity."""
        if self.kind != OPERATOR:
            raise IdentityError(f"{self.name} is a {self.kind}: only the operator issues identities")
        check_name("role", name)
        key = _signing_key(seed)
        cert = self.sign(certificate_message(self.run, kind, name, _public_bytes(key)))
        return Identity(self.run, kind, name, key, cert, self.operator_public)

    # -- the credential text -------------------------------------------------------------------
    def seed(self) -> bytes:
        return bytes(self.key)

    def to_text(self) -> str:
        return ":".join((_PREFIX, self.run, self.kind, self.name, self.seed().hex(), self.certificate.hex(),
                         self.operator_public.hex()))

    @staticmethod
    def from_text(text: str, origin: str = "credential") -> "Identity":
        """Parse and check a credential (its certificate must verify against its operator key)."""
        parts = text.strip().split(":")
        if len(parts) != 7 or parts[0] != _PREFIX:
            raise IdentityError(f"{origin}: not a dvla identity credential ({_PREFIX}:run:kind:name:seed:cert:operator)")
        _, run, kind, name, seed_hex, cert_hex, op_hex = parts
        try:
            seed, cert, op = bytes.fromhex(seed_hex), bytes.fromhex(cert_hex), bytes.fromhex(op_hex)
        except ValueError as exc:
            raise IdentityError(f"{origin}: bad key material: {exc}") from exc
        for what, value, size in (("seed", seed, 32), ("certificate", cert, SIGNATURE_BYTES), ("operator key", op, PUBLIC_BYTES)):
            if len(value) != size:
                raise IdentityError(f"{origin}: bad key material: the {what} is {len(value)} bytes, expected {size}")
        key = SigningKey(seed)
        if not verify_certificate(op, run, kind, name, _public_bytes(key), cert):
            raise IdentityError(f"{origin}: the certificate of {name!r} ({kind}) does not verify against its operator key")
        return Identity(run, kind, name, key, cert, op)

    @staticmethod
    def from_env(env_var: str = IDENTITY_ENV) -> "Identity | None":
        """The credential in `env_var` (None when unset: the process runs without an identity)."""
        value = os.environ.get(env_var)
        return Identity.from_text(value, f"environment variable {env_var}") if value else None


def authorize(keys: KeySpace, key: str, sender: str, kind: str, *, query: bool = False,
              weights_source: str | None = None) -> str | None:
    """None when `sender` (certified as `kind`) may send this message on `key`, else why not.

    `query`: the message is a query's request (not a publication or a reply).
    `weights_source`: the one actor whose weights this receiver follows (None: any actor).
    """
    root = keys.root + "/"
    rest = key[len(root):] if key.startswith(root) else ""
    plane_kind, _, target = rest.rpartition("/")
    if rest == "ctrl/weights":  # every weight manifest and chunk is signed for this one key
        if kind != "actor" or (weights_source is not None and sender != weights_source):
            return f"weights signed by {kind} {sender!r} (only actor {weights_source or '*'} publishes weights)"
        return None
    if plane_kind == "ctrl/cmd":
        return None if kind == OPERATOR else f"command from {kind} {sender!r} (only the operator commands)"
    if plane_kind == "ctrl/status" and query:
        return None if kind == OPERATOR else f"status query from {kind} {sender!r} (only the operator asks)"
    if plane_kind in ("ctrl/status", "ctrl/snapshot", "ctrl/receipt") and not query:
        return None if sender == target else f"reply on {target!r}'s key signed by {sender!r}"
    if plane_kind == "ctrl/receipt":  # a query: how far the learner got the asker's chunks
        return None if kind == "rollout" else f"receipt query from {kind} {sender!r} (only rollouts ask)"
    if plane_kind == "ctrl/eval":
        return None if sender == target and kind == "evaluator" else f"eval result on {target!r}'s key from {kind} {sender!r}"
    if plane_kind == "data/traj":
        return None if sender == target and kind == "rollout" else f"trajectory on {target!r}'s key from {kind} {sender!r}"
    if plane_kind == "ctrl/ledger":
        return None if sender == target and kind == "rollout" else f"ledger record on {target!r}'s key from {kind} {sender!r}"
    return None  # snapshot queries and keys dvla does not define: any certified member


def read_revoked(run_dir: str | os.PathLike[str]) -> set[str]:
    """The names revoked in `run_dir`'s :data:`REVOKED_FILE` (empty when there is none)."""
    try:
        with open(os.path.join(run_dir, REVOKED_FILE), encoding="utf-8") as f:
            return {line.strip() for line in f if line.strip()}
    except FileNotFoundError:
        return set()
