"""Tests of dvla.fabric.identity and identity-carrying envelopes: certificates, credentials,
who may send what, and a receiver that requires identities."""

from __future__ import annotations

import pytest

from dvla.fabric.errors import SignatureError
from dvla.fabric.identity import OPERATOR, Identity, IdentityError, authorize
from dvla.fabric.keys import KeySpace
from dvla.fabric.signing import Signer, Verifier, nonce_of

SECRET = bytes(range(32))
RUN = "run1"
KEYS = KeySpace(RUN)


@pytest.fixture(scope="module")
def op() -> Identity:
    return Identity.operator(RUN)


def reason(verifier: Verifier, key: str, env: bytes, **kw) -> str | None:
    try:
        verifier.open(key, env, **kw)
    except SignatureError as err:
        return err.reason
    return None


def test_credential_round_trip_and_checks(op):
    rollout = op.issue("rollout", "rollout-a")
    back = Identity.from_text(rollout.to_text())
    assert (back.run, back.kind, back.name, back.public) == (RUN, "rollout", "rollout-a", rollout.public)
    assert back.operator_public == op.public
    text = rollout.to_text().split(":")
    for i, value in ((2, "actor"), (3, "rollout-b"), (1, "run2")):  # claim another kind, name or run
        forged = ":".join(text[:i] + [value] + text[i + 1:])
        with pytest.raises(IdentityError, match="does not verify"):
            Identity.from_text(forged)
    with pytest.raises(IdentityError, match="not a dvla identity"):
        Identity.from_text("garbage")
    with pytest.raises(IdentityError, match="bad key material"):
        Identity.from_text(":".join(text[:4] + ["zz"] + text[5:]))
    with pytest.raises(IdentityError, match="only the operator"):
        rollout.issue("actor", "actor-x")


def test_identity_envelopes_verify_and_name_their_sender(op):
    actor = op.issue("actor", "actor-0")
    verifier = Verifier(SECRET, operator=op.public, run=RUN)
    env = Signer(SECRET, "ignored", identity=actor).seal(KEYS.weights_signed(), b"w")
    o = verifier.open(KEYS.weights_signed(), env)
    assert (o.sender, o.kind, bytes(o.payload)) == ("actor-0", "actor", b"w")


def test_receiver_requiring_identities_refuses_the_rest(op):
    verifier = Verifier(SECRET, operator=op.public, run=RUN)
    key = KEYS.cmd("all")
    assert reason(verifier, key, Signer(SECRET, "operator").seal(key, b"c")) == "no_identity"
    other_op = Identity.operator(RUN)  # another operator: its certificates mean nothing here
    assert reason(verifier, key, Signer(SECRET, "x", identity=other_op).seal(key, b"c")) == "bad_identity"
    other_run = Identity.operator("run2").issue("rollout", "rollout-a")
    assert reason(verifier, key, Signer(SECRET, "x", identity=other_run).seal(key, b"c")) == "bad_identity"
    env = bytearray(Signer(SECRET, "x", identity=op).seal(key, b"c"))
    env[-1] ^= 1  # the identity signature
    assert reason(verifier, key, bytes(env)) == "bad_identity"
    env = bytearray(Signer(SECRET, "x", identity=op).seal(key, b"c"))
    env[bytes(env).index(op.certificate) + 5] ^= 1  # a certificate byte: also covered by the tag
    assert reason(verifier, key, bytes(env)) in ("bad_signature", "bad_identity")
    assert reason(verifier, key, Signer(SECRET, "x", identity=op).seal(key, b"c")) is None


def test_replies_are_bound_to_their_query(op):
    verifier = Verifier(SECRET, operator=op.public, run=RUN)
    rollout = op.issue("rollout", "rollout-a")
    query = Signer(SECRET, "x", identity=op).seal(KEYS.status_all(), b"")
    other = Signer(SECRET, "x", identity=op).seal(KEYS.status_all(), b"")
    reply = Signer(SECRET, "x", identity=rollout).seal(KEYS.status("rollout-a"), b"st", bind=nonce_of(query))
    assert reason(verifier, KEYS.status("rollout-a"), reply, bind=nonce_of(other)) == "bad_signature"
    assert reason(verifier, KEYS.status("rollout-a"), reply, bind=nonce_of(query)) is None


def test_proof_envelopes_skip_freshness_only(op):
    verifier = Verifier(SECRET, operator=op.public, run=RUN)
    actor = op.issue("actor", "actor-0")
    env = Signer(SECRET, "x", identity=actor, clock=lambda: 1).seal(KEYS.weights_signed(), b"m")  # 1970
    assert reason(verifier, KEYS.weights_signed(), env) == "stale"
    assert reason(verifier, KEYS.weights_signed(), env, fresh=False) is None
    assert reason(verifier, KEYS.weights_signed(), env, fresh=False) is None  # no replay check either


def test_authorize_rules():
    def ok(key: str, sender: str, kind: str, **kw) -> bool:
        return authorize(KEYS, key, sender, kind, **kw) is None

    w = KEYS.weights_signed()
    assert ok(w, "actor-0", "actor") and ok(w, "actor-0", "actor", weights_source="actor-0")
    assert not ok(w, "actor-1", "actor", weights_source="actor-0")  # another rank of the group
    assert not ok(w, "rollout-a", "rollout") and not ok(w, "replicator-a", "replicator")
    assert ok(KEYS.cmd("all"), OPERATOR, OPERATOR) and not ok(KEYS.cmd("all"), "rollout-a", "rollout")
    assert ok(KEYS.status_all(), OPERATOR, OPERATOR, query=True)
    assert not ok(KEYS.status_all(), "rollout-a", "rollout", query=True)
    assert ok(KEYS.status("actor-0"), "actor-0", "actor") and not ok(KEYS.status("actor-0"), "rollout-a", "rollout")
    assert ok(KEYS.eval("ev-0"), "ev-0", "evaluator") and not ok(KEYS.eval("ev-0"), "rollout-a", "rollout")
    assert not ok(KEYS.eval("rollout-a"), "rollout-a", "rollout")  # an eval result needs an evaluator
    assert ok(KEYS.traj("rollout-a"), "rollout-a", "rollout")
    assert not ok(KEYS.traj("rollout-b"), "rollout-a", "rollout")  # another rollout's name
    assert not ok(KEYS.traj("actor-0"), "actor-0", "actor")
    assert ok(KEYS.ledger("robot-1"), "robot-1", "rollout")  # a rollout's own counter record
    assert not ok(KEYS.ledger("robot-1"), "robot-2", "rollout") and not ok(KEYS.ledger("robot-1"), "robot-1", "evaluator")
    assert ok(KEYS.snapshot("replicator-a"), "rollout-a", "rollout", query=True)  # any member asks
    assert ok(KEYS.receipt("actor-0"), "rollout-a", "rollout", query=True)  # a stopping rollout asks
    assert not ok(KEYS.receipt("actor-0"), "ev-0", "evaluator", query=True)
    assert ok(KEYS.receipt("actor-0"), "actor-0", "actor")  # the learner answers on its own key
    assert not ok(KEYS.receipt("actor-0"), "actor-1", "actor")
    assert not ok(KEYS.receipt("actor-0"), "rollout-a", "rollout")
    assert ok(KEYS.snapshot("replicator-a"), "replicator-a", "replicator")
    assert not ok(KEYS.snapshot("replicator-a"), "replicator-b", "replicator")


_OP = Identity.operator(RUN)
_IDENT_ENV = Signer(SECRET, "x", identity=_OP.issue("actor", "actor-0")).seal(KEYS.weights_signed(), b"weights")


def _only_signature_errors(env: bytes) -> None:
    verifier = Verifier(SECRET, operator=_OP.public, run=RUN)
    try:
        verifier.open(KEYS.weights_signed(), env)
    except SignatureError:
        pass


from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@settings(max_examples=200, deadline=None, database=None)
@given(st.integers(0, len(_IDENT_ENV) - 1), st.integers(1, 255))
def test_fuzz_identity_envelopes_raise_only_signature_errors(index, xor):
    out = bytearray(_IDENT_ENV)
    out[index] ^= xor
    _only_signature_errors(bytes(out))


@settings(max_examples=200, deadline=None, database=None)
@given(st.integers(0, len(_IDENT_ENV)), st.binary(max_size=80))
def test_fuzz_truncated_or_extended_identity_envelopes(cut, tail):
    _only_signature_errors(_IDENT_ENV[:cut] + tail)


def test_a_captured_envelope_with_a_flipped_signature_bit_counts_as_a_replay(op):
    # Without credentials, flipping one bit of the Ed25519 signature of an envelope already
    # accepted must not make receivers count bad_identity: the cheaper replay check comes first.
    key = KEYS.traj("r0")
    verifier = Verifier(SECRET, operator=op.operator_public, run=RUN)
    env = Signer(SECRET, "r0", identity=op.issue("rollout", "r0")).seal(key, b"chunk")
    assert reason(verifier, key, env) is None
    flipped = bytearray(env)
    flipped[-1] ^= 1
    assert reason(verifier, key, bytes(flipped)) == "replay"
    assert reason(verifier, key, env) == "replay"
    # Seen first, a bad signature is bad_identity and leaves the nonce free for the real one.
    fresh = Signer(SECRET, "r0", identity=op.issue("rollout", "r0")).seal(key, b"chunk")
    bad = bytearray(fresh)
    bad[-1] ^= 1
    assert reason(verifier, key, bytes(bad)) == "bad_identity"
    assert reason(verifier, key, fresh) is None
