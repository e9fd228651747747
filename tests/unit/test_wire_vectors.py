"""The worked vectors of docs/wire-format.md section 7, read out of the document itself and
checked in both directions: dvla reproduces them byte for byte from the stated inputs, and they
open (tag, certificate, signature, binding) and decode with dvla's verifier and decoder."""

from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path

import numpy as np
import pytest

import dvla.fabric.signing as signing
from dvla.fabric.codec import decode, encode
from dvla.fabric.identity import Identity
from dvla.fabric.keys import KeySpace
from dvla.fabric.messages import Command, SnapshotRequest, WeightChunk, WeightManifest, WeightSnapshot
from dvla.fabric.signing import Signer, Verifier, nonce_of
from dvla.replication.encoding import checksum

DOC = Path(__file__).resolve().parents[2] / "docs" / "wire-format.md"
RUN = "run1"
KEYS = KeySpace(RUN)
SECRET = bytes.fromhex("00112233445566778899aabbccddeeff")
TS = 1_700_000_000_000_000_000
OPERATOR_SEED = bytes([0x01] * 32)
ROLLOUT_SEED = bytes([0x02] * 32)
ACTOR_SEED = bytes([0x03] * 32)
ACTOR = "actor-node0-0"
PARAMS = np.array([0.5, -1.0, 2.0, 0.25], np.float32)


def doc_vectors() -> dict[str, bytes]:
    """Every ``Vector `name```` paragraph's following ```hex block, as bytes."""
    text = DOC.read_text(encoding="utf-8")
    found = re.findall(r"Vector `([a-z0-9-]+)`.*?```hex\n(.*?)```", text, flags=re.S)
    return {name: bytes.fromhex("".join(body.split())) for name, body in found}


def identities() -> tuple[Identity, Identity, Identity]:
    op = Identity.operator(RUN, seed=OPERATOR_SEED)
    return op, op.issue("rollout", "r0", seed=ROLLOUT_SEED), op.issue("actor", ACTOR, seed=ACTOR_SEED)


def manifest() -> WeightManifest:
    return WeightManifest(sender=ACTOR, version=1, base_version=-1, encoding="full", layout_hash="00" * 16,
                          n_chunks=1, total_bytes=16, checksum=checksum(PARAMS),
                          digest=hashlib.sha256(PARAMS.tobytes()).hexdigest(), numel=4, base_hash="", created_ns=TS)


def _seal(signer: Signer, key: str, payload: bytes, first_nonce_byte: int, bind: bytes = b"") -> bytes:
    """``signer.seal`` with the nonce ``first_nonce_byte, +1, ... +15`` (the only random input)."""
    nonce = bytes(range(first_nonce_byte, first_nonce_byte + 16))
    real = os.urandom
    os.urandom = lambda n: nonce  # seal draws exactly one nonce, nothing else runs meanwhile
    try:
        return signer.seal(key, payload, bind=bind)
    finally:
        os.urandom = real


def build() -> dict[str, bytes]:
    """The vectors, sealed by dvla from the inputs the document states."""
    clock = lambda: TS  # noqa: E731
    _, rollout, actor = identities()
    out = {}
    out["signed-command"] = _seal(Signer(SECRET, "orch", clock=clock), KEYS.cmd("all"),
                                  encode(Command(target="all", verb="stop", args={}, issued_ns=TS)), 0x00)
    query_key = KEYS.snapshot(ACTOR)
    out["snapshot-query"] = _seal(Signer(SECRET, "r0", identity=rollout, clock=clock), query_key,
                                  encode(SnapshotRequest(requester="r0", have_version=-1)), 0x10)
    actor_signer = Signer(SECRET, ACTOR, identity=actor, clock=clock)
    out["weight-manifest"] = _seal(actor_signer, KEYS.weights_signed(), encode(manifest()), 0x30)
    out["weight-chunk"] = _seal(actor_signer, KEYS.weights_signed(), encode(
        WeightChunk(sender=ACTOR, version=1, index=0, n_chunks=1, data=PARAMS.tobytes())), 0x40)
    reply = WeightSnapshot(sender=ACTOR, version=1, manifest=out["weight-manifest"], n_chunks=1, created_ns=TS)
    out["snapshot-reply"] = _seal(actor_signer, query_key, encode(reply), 0x50, bind=nonce_of(out["snapshot-query"]))
    return out


def test_the_document_holds_every_vector():
    assert set(doc_vectors()) == {"signed-command", "snapshot-query", "snapshot-reply", "weight-manifest", "weight-chunk"}


def test_dvla_reproduces_the_documented_vectors():
    built, documented = build(), doc_vectors()
    for name, data in built.items():
        assert documented.get(name, b"").hex() == data.hex(), name


def test_the_documented_vectors_open_and_decode():
    vec = doc_vectors()
    op, _, _ = identities()
    verifier = Verifier(SECRET, operator=op.public, run=RUN, clock=lambda: TS)
    plain = Verifier(SECRET, clock=lambda: TS)  # no identities required: the flag-clear command
    sender, kind, payload, _ = plain.open(KEYS.cmd("all"), vec["signed-command"])
    assert (sender, kind) == ("orch", "") and decode(payload) == Command(target="all", verb="stop", args={}, issued_ns=TS)

    query = verifier.open(KEYS.snapshot(ACTOR), vec["snapshot-query"])
    assert (query.sender, query.kind, query.nonce) == ("r0", "rollout", bytes(range(16, 32)))
    assert decode(query.payload) == SnapshotRequest(requester="r0", have_version=-1)
    reply = verifier.open(KEYS.snapshot(ACTOR), vec["snapshot-reply"], bind=query.nonce)
    header = decode(reply.payload, expect=WeightSnapshot)
    assert (reply.sender, reply.kind, header.version, header.n_chunks) == (ACTOR, "actor", 1, 1)
    with pytest.raises(signing.SignatureError, match="tag mismatch"):  # bound to that query only
        Verifier(SECRET, operator=op.public, run=RUN, clock=lambda: TS).open(
            KEYS.snapshot(ACTOR), vec["snapshot-reply"], bind=bytes(16))
    # The header's manifest is the actor's manifest envelope, checked without freshness.
    assert bytes(header.manifest) == vec["weight-manifest"]
    proof = verifier.open(KEYS.weights_signed(), header.manifest, fresh=False)
    assert decode(proof.payload) == manifest()

    m = verifier.open(KEYS.weights_signed(), vec["weight-manifest"])
    c = verifier.open(KEYS.weights_signed(), vec["weight-chunk"])
    chunk = decode(c.payload, expect=WeightChunk)
    assert decode(m.payload) == manifest() and (m.sender, c.sender) == (ACTOR, ACTOR)
    assert np.array_equal(np.frombuffer(chunk.data, "<f4"), PARAMS)
    opened = {"signed-command": payload, "snapshot-query": query.payload, "snapshot-reply": reply.payload,
              "weight-manifest": m.payload, "weight-chunk": c.payload}
    for name, env in vec.items():  # every payload starts 8-byte aligned inside its envelope
        start = len(env) - len(opened[name]) - 32 - (64 if env[8] & 1 else 0)
        assert start % 8 == 0 and env[start:start + 3] == b"\x83\xa1\x76", name  # {"v": ...
