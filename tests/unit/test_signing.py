"""Tests of dvla.fabric.signing: envelope round trip, tamper/replay/staleness rejection,
bounded replay memory, thread safety and secret loading."""

from __future__ import annotations

import struct
import threading

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dvla.fabric.errors import FabricError
from dvla.fabric.signing import (
    MAGIC,
    MIN_SECRET_BYTES,
    SecretError,
    SignatureError,
    Signer,
    Verifier,
    load_secret,
    new_secret,
)

SECRET = bytes(range(32))
KEY = "dvla/run1/ctrl/cmd/all"
SEC = 1_000_000_000
T0 = 1_700_000_000 * SEC


class Clock:
    """A settable ns clock shared by a signer and a verifier."""

    def __init__(self, now: int = T0) -> None:
        self.now = now

    def __call__(self) -> int:
        return self.now


def opened(verifier: Verifier, key: str, envelope) -> tuple[str, bytes]:
    o = verifier.open(key, envelope)
    return o.sender, bytes(o.payload)


def reason_of(verifier: Verifier, key: str, envelope) -> str | None:
    try:
        verifier.open(key, envelope)
    except SignatureError as err:
        assert isinstance(err, FabricError) and isinstance(err, ValueError)
        return err.reason
    return None


def test_round_trip():
    signer, verifier = Signer(SECRET, "actor"), Verifier(SECRET)
    for payload in (b"", b"hello", bytes(range(256)) * 100):
        o = verifier.open(KEY, signer.seal(KEY, payload))
        assert o.sender == "actor" and o.kind == "" and o.payload == payload and isinstance(o.payload, memoryview)


def test_accepts_buffer_types():
    signer, verifier = Signer(SECRET, "rollout-ü"), Verifier(SECRET)
    env = signer.seal(KEY, memoryview(bytearray(b"payload")))
    assert opened(verifier, KEY, memoryview(bytearray(env))) == ("rollout-ü", b"payload")


def test_envelope_layout_matches_documentation():
    clock = Clock()
    env = Signer(SECRET, "actor", clock=clock).seal(KEY, b"xyz")
    import hashlib

    import blake3
    assert env[:4] == MAGIC == b"DVS4" and env[4:8] == hashlib.sha256(b"dvla-key-id" + SECRET).digest()[:4]
    assert env[8] == 0 and env[9] == 5 and env[10:15] == b"actor"
    ts, _nonce, plen = struct.unpack_from("<Q16sI", env, 15)
    assert ts == T0 and plen == 3 and env[43:48] == bytes(5)  # zero padding: payload 8-byte aligned
    assert env[48:51] == b"xyz" and len(env) == 51 + 32
    key = KEY.encode()
    mac_key = blake3.blake3(SECRET, derive_key_context="dvla 2026-11 envelope tag v4").digest()
    tag = blake3.blake3(struct.pack("<H", len(key)) + key + b"\x00" + env[:51], key=mac_key).digest()
    assert env[51:] == tag
    padded = bytearray(env)
    padded[44] = 1
    assert reason_of(Verifier(SECRET, clock=clock), KEY, bytes(padded)) == "malformed"


def test_an_older_envelope_version_is_refused_by_name():
    """A DVS3 (HMAC-SHA256) sender talking to a DVS4 receiver: refused as unsigned, the error
    naming both versions (an upgrade problem, not an attack)."""
    env = bytearray(Signer(SECRET, "actor").seal(KEY, b"xyz"))
    env[:4] = b"DVS3"
    with pytest.raises(SignatureError, match="DVS3 is no longer accepted.*DVS4") as err:
        Verifier(SECRET).open(KEY, bytes(env))
    assert err.value.reason == "unsigned"


def flip(env: bytes, index: int) -> bytes:
    out = bytearray(env)
    out[index] ^= 0x01
    return bytes(out)


def test_tampering_is_detected():
    signer = Signer(SECRET, "actor")
    env = signer.seal(KEY, b"payload-bytes")
    verifier = Verifier(SECRET)
    assert reason_of(verifier, KEY, flip(env, len(env) - 32 - 3)) == "bad_signature"  # payload
    assert reason_of(verifier, KEY, flip(env, 11)) == "bad_signature"  # sender "actor" -> "aator"
    assert reason_of(verifier, KEY, flip(env, 17)) == "bad_signature"  # timestamp
    assert reason_of(verifier, KEY, flip(env, 25)) == "bad_signature"  # nonce
    assert reason_of(verifier, KEY, flip(env, 5)) == "key_id"  # key id
    assert reason_of(verifier, KEY, flip(env, len(env) - 1)) == "bad_signature"  # tag
    assert reason_of(verifier, "dvla/run1/ctrl/cmd/actor", env) == "bad_signature"  # other key
    assert reason_of(Verifier(b"x" * 32), KEY, env) == "key_id"  # other secret: named as such
    assert reason_of(verifier, KEY, env) is None  # the original still verifies


def test_sender_is_authenticated():
    env = Signer(SECRET, "rollout-1").seal(KEY, b"p")
    forged = env[:9] + bytes([9]) + b"rollout-2" + env[19:]
    assert reason_of(Verifier(SECRET), KEY, forged) == "bad_signature"


def test_unsigned_and_malformed():
    verifier = Verifier(SECRET)
    env = Signer(SECRET, "a").seal(KEY, b"p")
    assert reason_of(verifier, KEY, b"") == "unsigned"
    assert reason_of(verifier, KEY, b"\x83\xa1v\x01") == "unsigned"  # a bare codec message
    assert reason_of(verifier, KEY, b"DVS") == "unsigned"
    assert reason_of(verifier, KEY, "DVS1 text") == "unsigned"
    assert reason_of(verifier, KEY, None) == "unsigned"
    assert reason_of(verifier, KEY, MAGIC + b"\x01a") == "malformed"  # too short
    assert reason_of(verifier, KEY, env[:-1]) == "malformed"  # payload length disagrees
    assert reason_of(verifier, KEY, env + b"\x00") == "malformed"
    assert reason_of(verifier, KEY, env[:9] + b"\x00" + env[10:]) == "malformed"  # empty sender
    assert reason_of(verifier, KEY, env[:8] + b"\x02" + env[9:]) == "malformed"  # unknown flag
    bad_utf8 = bytearray(env)
    bad_utf8[10] = 0xFF
    assert reason_of(verifier, KEY, bytes(bad_utf8)) == "malformed"


def test_replay_is_rejected():
    signer, verifier = Signer(SECRET, "actor"), Verifier(SECRET)
    env = signer.seal(KEY, b"cmd")
    assert reason_of(verifier, KEY, env) is None
    assert reason_of(verifier, KEY, env) == "replay"
    assert reason_of(verifier, KEY, signer.seal(KEY, b"cmd")) is None  # same payload, new nonce


def test_stale_and_future_timestamps():
    clock = Clock()
    verifier = Verifier(SECRET, max_age_s=30.0, clock=clock)
    old = Signer(SECRET, "a", clock=Clock(T0 - 31 * SEC)).seal(KEY, b"p")
    future = Signer(SECRET, "a", clock=Clock(T0 + 31 * SEC)).seal(KEY, b"p")
    edge = Signer(SECRET, "a", clock=Clock(T0 - 29 * SEC)).seal(KEY, b"p")
    assert reason_of(verifier, KEY, old) == "stale"
    assert reason_of(verifier, KEY, future) == "stale"
    assert reason_of(verifier, KEY, edge) is None
    clock.now += 2 * SEC  # the accepted envelope has aged out: a replay is now stale
    assert reason_of(verifier, KEY, edge) == "stale"


def test_age_is_judged_at_arrival_when_the_receiver_queued_the_envelope():
    # An envelope that arrived fresh and then waited in the receiver's own bounded queue (a busy
    # learner) is not stale; a receive time never lengthens a life: it cannot be later than now.
    clock = Clock()
    sealed = Signer(SECRET, "rollout-0", clock=Clock(T0)).seal(KEY, b"chunk")
    later = Signer(SECRET, "rollout-0", clock=Clock(T0 + SEC)).seal(KEY, b"chunk")
    verifier = Verifier(SECRET, max_age_s=30.0, clock=clock)
    clock.now = T0 + 200 * SEC  # read 200 s after it was sealed
    assert reason_of(verifier, KEY, sealed) == "stale"
    with pytest.raises(SignatureError, match="stale"):
        verifier.open(KEY, sealed, received_ns=T0 + 500 * SEC)  # a "receive time" after now counts as now
    assert verifier.open(KEY, sealed, received_ns=T0 + 2 * SEC).payload == b"chunk"
    with pytest.raises(SignatureError, match="replay"):
        verifier.open(KEY, sealed, received_ns=T0 + 2 * SEC)  # its nonce is held as any other
    assert verifier.open(KEY, later, received_ns=T0 + 3 * SEC).payload == b"chunk"
    with pytest.raises(SignatureError, match="stale"):
        verifier.open(KEY, later, received_ns=T0 + 40 * SEC)  # it had aged out when it arrived


def test_replay_memory_is_bounded_and_evicted_nonces_stay_rejected():
    clock = Clock()
    signer = Signer(SECRET, "actor", clock=clock)
    verifier = Verifier(SECRET, max_age_s=30.0, replay_window=4, clock=clock)
    envs = []
    for _ in range(10):
        clock.now += 1000
        envs.append(signer.seal(KEY, b"p"))
        assert reason_of(verifier, KEY, envs[-1]) is None
        assert verifier.nonces_held <= 4
    assert reason_of(verifier, KEY, envs[-1]) == "replay"
    # Forgotten nonces are behind the sender's horizon: still refused.
    assert reason_of(verifier, KEY, envs[0]) == "stale"
    assert reason_of(verifier, KEY, envs[5]) == "stale"
    # Another sender is not affected by this sender's horizon.
    other = Signer(SECRET, "other", clock=Clock(T0 + 1)).seal(KEY, b"p")
    assert reason_of(verifier, KEY, other) is None


def test_expired_nonces_are_forgotten():
    clock = Clock()
    signer = Signer(SECRET, "a", clock=clock)
    verifier = Verifier(SECRET, max_age_s=1.0, replay_window=1000, clock=clock)
    for _ in range(50):
        assert reason_of(verifier, KEY, signer.seal(KEY, b"p")) is None
    assert verifier.nonces_held == 50
    clock.now += 2 * SEC
    assert reason_of(verifier, KEY, signer.seal(KEY, b"p")) is None
    assert verifier.nonces_held == 1


def test_concurrent_replays_accept_exactly_once():
    signer, verifier = Signer(SECRET, "a"), Verifier(SECRET)
    envs = [signer.seal(KEY, bytes([i])) for i in range(20)]
    results: list[str | None] = []
    lock = threading.Lock()

    def worker():
        for env in envs:
            r = reason_of(verifier, KEY, env)
            with lock:
                results.append(r)

    threads = [threading.Thread(target=worker) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert results.count(None) == len(envs)
    assert results.count("replay") == len(envs) * 5


def test_constructor_checks():
    with pytest.raises(SecretError):
        Signer(b"short", "a")
    with pytest.raises(SecretError):
        Verifier(b"short")
    with pytest.raises(SecretError):
        Verifier("not bytes" * 4)  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        Signer(SECRET, "")
    with pytest.raises(ValueError):
        Signer(SECRET, "x" * 256)
    with pytest.raises(ValueError):
        Verifier(SECRET, max_age_s=0)


@settings(max_examples=150, deadline=None, database=None)
@given(st.binary(max_size=200))
def test_fuzz_random_bytes(data):
    assert reason_of(Verifier(SECRET), KEY, data) in {"unsigned", "malformed", "bad_signature", "key_id"}
    assert reason_of(Verifier(SECRET), KEY, MAGIC + data) in {"malformed", "bad_signature", "key_id"}


ENVELOPE = Signer(SECRET, "actor").seal(KEY, b"some control payload")


@settings(max_examples=150, deadline=None, database=None)
@given(st.integers(0, len(ENVELOPE) - 1), st.integers(1, 255))
def test_fuzz_any_byte_change_is_rejected(index, xor):
    out = bytearray(ENVELOPE)
    out[index] ^= xor
    assert reason_of(Verifier(SECRET), KEY, bytes(out)) in {"unsigned", "malformed", "bad_signature", "key_id"}


@settings(max_examples=100, deadline=None, database=None)
@given(st.integers(0, len(ENVELOPE) - 1))
def test_fuzz_truncation_is_rejected(cut):
    assert reason_of(Verifier(SECRET), KEY, ENVELOPE[:cut]) in {"unsigned", "malformed"}


# ----------------------------------------------------------------------------- secrets

def test_new_secret_is_hex_and_loadable(tmp_path, monkeypatch):
    s = new_secret()
    assert len(s) == 64 and bytes.fromhex(s)
    assert new_secret() != s
    path = tmp_path / "secret"
    path.write_text(s + "\n")
    assert load_secret(str(path)) == bytes.fromhex(s)
    monkeypatch.setenv("DVLA_SECRET", s)
    assert load_secret(None) == bytes.fromhex(s)


def test_load_secret_raw_file_and_whitespace(tmp_path):
    raw = tmp_path / "raw"
    raw.write_bytes(b"  a passphrase that is long enough \n")
    assert load_secret(str(raw)) == b"a passphrase that is long enough"
    binary = tmp_path / "bin"
    binary.write_bytes(bytes(range(100, 132)))
    assert load_secret(str(binary)) == bytes(range(100, 132))
    # Whitespace at the edges is stripped even from binary content (documented); still >= 16 bytes.
    binary.write_bytes(b"\n" + bytes(range(100, 132)) + b" ")
    assert load_secret(str(binary)) == bytes(range(100, 132))


def test_file_takes_precedence_over_env(tmp_path, monkeypatch):
    monkeypatch.setenv("DVLA_SECRET", "e" * 32)
    path = tmp_path / "s"
    path.write_text("f" * 32)
    assert load_secret(str(path)) == bytes.fromhex("f" * 32)
    assert load_secret(None) == bytes.fromhex("e" * 32)


def test_load_secret_errors_name_their_source(tmp_path, monkeypatch):
    missing = tmp_path / "nope"
    with pytest.raises(SecretError, match="nope"):
        load_secret(str(missing))
    short = tmp_path / "short"
    short.write_text("abcd")  # hex: 2 bytes
    with pytest.raises(SecretError, match="short"):
        load_secret(str(short))
    monkeypatch.delenv("MY_SECRET_VAR", raising=False)
    with pytest.raises(SecretError, match="MY_SECRET_VAR"):
        load_secret(None, env_var="MY_SECRET_VAR")
    monkeypatch.setenv("MY_SECRET_VAR", "")
    with pytest.raises(SecretError, match="MY_SECRET_VAR"):
        load_secret(None, env_var="MY_SECRET_VAR")
    monkeypatch.setenv("MY_SECRET_VAR", "x" * (MIN_SECRET_BYTES - 1))
    with pytest.raises(SecretError, match="MY_SECRET_VAR"):
        load_secret(None, env_var="MY_SECRET_VAR")
    monkeypatch.setenv("MY_SECRET_VAR", "x" * MIN_SECRET_BYTES)
    assert load_secret(None, env_var="MY_SECRET_VAR") == b"x" * MIN_SECRET_BYTES
    assert issubclass(SecretError, ValueError)


def test_signer_and_verifier_share_a_loaded_secret(tmp_path):
    path = tmp_path / "s"
    path.write_text(new_secret())
    secret = load_secret(str(path))
    env = Signer(secret, "a").seal(KEY, b"x")
    assert opened(Verifier(load_secret(str(path))), KEY, env) == ("a", b"x")
