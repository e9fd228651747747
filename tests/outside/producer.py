"""A trajectory producer written from docs/wire-format.md alone: it imports nothing from dvla.

Its own msgpack messages (§2, §3), envelopes with an identity block (§4) and credential parsing
(§8). It asks the actor's snapshot queryable which version is current (a signed query; the reply
is checked: tag bound to the query's nonce, the actor's certificate against the operator key of
the credential, its signature), then publishes chunks of a Pendulum-shaped task (obs 3,
action 1) on its own trajectory key. Prints one JSON line: the version seen and chunks sent.

usage: producer.py RUN CTRL_ENDPOINT DATA_ENDPOINT SECRET_FILE CREDENTIAL_FILE ACTOR N_CHUNKS T WAIT_S [DATA_MODE]

DATA_MODE: `peer` (default: a peer of the actor's data listener) or `client` (through a router).
"""

from __future__ import annotations

import hashlib
import hmac
import json
import os
import struct
import sys
import time

import blake3
import msgpack
import zenoh
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey
from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

SCHEMA = 3


# ------------------------------------------------------------------ §3 arrays, §2 messages
def array(dtype: str, shape: tuple[int, ...], values: list) -> msgpack.ExtType:
    fmt = {"float32": "f", "bool": "?", "int32": "i"}[dtype]
    head = bytes([len(dtype)]) + dtype.encode() + bytes([len(shape)]) + b"".join(struct.pack("<I", d) for d in shape)
    head += bytes([0])  # pad 0: decoders honour any pad and must not assume alignment
    return msgpack.ExtType(1, head + struct.pack("<%d%s" % (len(values), fmt), *values))


def message(tag: str, body: dict) -> bytes:
    return msgpack.packb({"v": SCHEMA, "t": tag, "b": body}, use_bin_type=True)


def read_array(ext: msgpack.ExtType) -> tuple[str, list[int], bytes]:
    data = ext.data
    n = data[0]
    name = data[1:1 + n].decode()
    ndim = data[1 + n]
    p = 2 + n
    shape = [struct.unpack_from("<I", data, p + 4 * i)[0] for i in range(ndim)]
    p += 4 * ndim
    p += 1 + data[p]
    return name, shape, data[p:]


def unpack(payload: bytes) -> dict:
    return msgpack.unpackb(payload, raw=False, ext_hook=lambda code, data: msgpack.ExtType(code, data), strict_map_key=True)


# ------------------------------------------------------------------ §8 credential
class Credential:
    def __init__(self, text: str) -> None:
        prefix, self.run, self.kind, self.name, seed, cert, op = text.strip().split(":")
        assert prefix == "dvla-id1", prefix
        self.key = Ed25519PrivateKey.from_private_bytes(bytes.fromhex(seed))
        self.public = self.key.public_key().public_bytes(Encoding.Raw, PublicFormat.Raw)
        self.cert = bytes.fromhex(cert)
        self.operator = Ed25519PublicKey.from_public_bytes(bytes.fromhex(op))


def cert_message(run: str, kind: str, name: str, public: bytes) -> bytes:
    return b"dvla-cert1\0" + run.encode() + b"\0" + kind.encode() + b"\0" + name.encode() + b"\0" + public


# ------------------------------------------------------------------ §4 envelope
def secret_from_text(raw: bytes) -> bytes:
    text = raw.strip()
    if text and len(text) % 2 == 0 and all(c in b"0123456789abcdefABCDEF" for c in text):
        return bytes.fromhex(text.decode())
    return text


def mac_prefix(key: str, bind: bytes) -> bytes:
    k = key.encode()
    return struct.pack("<H", len(k)) + k + bytes([len(bind)]) + bind


def mac_key(secret: bytes) -> bytes:
    return blake3.blake3(secret, derive_key_context="dvla 2026-11 envelope tag v4").digest()


def seal(secret: bytes, cred: Credential, key: str, payload: bytes, bind: bytes = b"") -> tuple[bytes, bytes]:
    """(envelope, nonce)."""
    kid = hashlib.sha256(b"dvla-key-id" + secret).digest()[:4]
    sender = cred.name.encode()
    nonce = os.urandom(16)
    kind = cred.kind.encode()
    header = (b"DVS4" + kid + bytes([1, len(sender)]) + sender + struct.pack("<Q", time.time_ns()) + nonce
              + struct.pack("<I", len(payload)) + bytes([len(kind)]) + kind + cred.public + cred.cert)
    header += bytes(-len(header) % 8)
    tag = blake3.blake3(mac_prefix(key, bind) + header + payload, key=mac_key(secret)).digest()
    return header + payload + tag + cred.key.sign(b"dvla-sig1" + tag), nonce


def open_envelope(secret: bytes, cred: Credential, key: str, env: bytes, bind: bytes = b"") -> tuple[str, str, bytes]:
    """(sender, kind, payload) of an envelope that must carry an identity certified by our operator."""
    assert env[:4] == b"DVS4", "not an envelope"
    flags, s = env[8], env[9]
    sender = env[10:10 + s].decode()
    pos = 10 + s + 8 + 16
    (plen,) = struct.unpack_from("<I", env, pos)
    pos += 4
    assert flags == 1, "no identity block"
    k = env[pos]
    kind = env[pos + 1:pos + 1 + k].decode()
    pos += 1 + k
    public, cert = env[pos:pos + 32], env[pos + 32:pos + 96]
    pos += 96
    pos += -pos % 8
    assert len(env) == pos + plen + 32 + 64, "length"
    body_end = pos + plen
    tag = blake3.blake3(mac_prefix(key, bind) + env[:body_end], key=mac_key(secret)).digest()
    assert hmac.compare_digest(tag, env[body_end:body_end + 32]), "bad tag"
    cred.operator.verify(cert, cert_message(cred.run, kind, sender, public))
    Ed25519PublicKey.from_public_bytes(public).verify(env[body_end + 32:], b"dvla-sig1" + tag)
    return sender, kind, env[pos:body_end]


# ------------------------------------------------------------------ the producer
def config(mode: str, endpoint: str) -> zenoh.Config:
    conf = zenoh.Config()
    for key, value in (("mode", mode), ("connect/endpoints", [endpoint]), ("scouting/multicast/enabled", False),
                       ("scouting/gossip/enabled", False)):
        conf.insert_json5(key, json.dumps(value))
    return conf


def chunk(name: str, seq: int, version: int, t: int) -> bytes:
    f32 = lambda *shape: array("float32", shape, [0.0] * _n(shape))  # noqa: E731
    flags = lambda: array("bool", (t, 1), [False] * t)  # noqa: E731
    obs = array("float32", (t, 1, 3), [0.1 * (i % 7) for i in range(3 * t)])
    return message("traj", {
        "rollout": name, "seq": seq, "policy_version": version, "env_steps": t,
        "obs": {"state": obs}, "actions": array("float32", (t, 1, 1), [0.5] * t),
        "logprobs": array("float32", (t, 1), [-1.0] * t), "rewards": array("float32", (t, 1), [-0.5] * t),
        "terminated": flags(), "truncated": flags(), "success": flags(),
        "next_obs": {"state": f32(1, 3)}, "final_obs": {"state": f32(t, 1, 3)},
        "extras": {}, "created_ns": time.time_ns(),
    })


def _n(shape: tuple[int, ...]) -> int:
    n = 1
    for d in shape:
        n *= d
    return n


def main() -> None:
    run, ctrl, data, secret_file, cred_file, actor, n_chunks, t, wait_s = sys.argv[1:10]
    data_mode = sys.argv[10] if len(sys.argv) > 10 else "peer"
    secret = secret_from_text(open(secret_file, "rb").read())
    cred = Credential(open(cred_file).read())
    out = {"version": -1, "sent": 0, "replies": 0}
    with zenoh.open(config("client", ctrl)) as ctrl_s, zenoh.open(config(data_mode, data)) as data_s:
        key = f"dvla/{run}/ctrl/snapshot/{actor}"
        deadline = time.monotonic() + float(wait_s)
        while out["version"] < 1 and time.monotonic() < deadline:
            request, nonce = seal(secret, cred, key, message("snapshot.req", {"requester": cred.name, "have_version": 1 << 40}))
            for reply in ctrl_s.get(key, payload=request, timeout=2.0):
                if reply.ok is None:
                    continue
                try:
                    sender, kind, payload = open_envelope(secret, cred, str(reply.ok.key_expr), reply.ok.payload.to_bytes(), nonce)
                except Exception as err:  # a reply that does not verify is not believed
                    print(f"reply refused: {err!r}", file=sys.stderr)
                    continue
                msg = unpack(payload)
                if sender == actor and kind == "actor" and msg["t"] == "snapshot":
                    out["replies"] += 1
                    out["version"] = max(out["version"], msg["b"]["version"])
            if out["version"] < 1:
                time.sleep(0.5)
        pub = data_s.declare_publisher(f"dvla/{run}/data/traj/{cred.name}", congestion_control=zenoh.CongestionControl.BLOCK)
        time.sleep(1.0)  # the data link's routes settle
        for seq in range(int(n_chunks)):
            env, _ = seal(secret, cred, f"dvla/{run}/data/traj/{cred.name}", chunk(cred.name, seq, max(out["version"], 0), int(t)))
            pub.put(env)
            out["sent"] += 1
            time.sleep(0.05)
        time.sleep(1.0)
    print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
