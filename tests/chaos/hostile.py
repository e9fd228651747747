"""A hostile client of a running dvla cluster: it reaches both planes but holds no cluster secret.

It signs with a key of its own (under the names of real roles), so everything it sends on either
plane must be refused (``key_id``: not the run's secret); it sends well-formed trajectory chunks
under a real rollout's name (with NaN values and a far-future version), garbage, oversized
payloads, 200 MB envelopes and puts on 100,000 made-up keys; it queries status and snapshots
without signing; and it captures genuinely signed traffic from the wire (weights, eval results,
commands) to replay it later, on its own keys and on other weight senders' keys and as replies
to the run's own queries, which replay protection and reply binding must refuse. Counting what
was sent lets a test compare it with what each role reports having rejected, per reason, in its
status (``planes``).

    from .hostile import Attacker  # in a test module of tests/chaos
    with Attacker.for_run(run_dir) as atk:
        atk.start_capture()
        ...
        sent = atk.flood(seconds=10)
"""

from __future__ import annotations

import json
import os
import struct
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from dvla.fabric import plane_config
from dvla.fabric.codec import encode
from dvla.fabric.keys import KeySpace
from dvla.fabric.signing import MAGIC
from dvla.fabric.messages import (
    Command,
    EvalResult,
    RoleStatus,
    SnapshotRequest,
    WeightChunk,
    WeightManifest,
    WeightSnapshot,
)
from dvla.fabric.messages import TrajectoryChunk
from dvla.fabric.signing import Signer

#: a version number far above anything a run reaches: applied anywhere, it would show
FORGED_VERSION = 10**9
#: size of the string in an oversized chunk: above the decoder's 1 MiB string limit
OVERSIZE_STR = 2 << 20


def _msgpack_str(b: bytes) -> bytes:
    if len(b) < 32:
        return bytes((0xA0 | len(b),)) + b
    if len(b) < 256:
        return b"\xd9" + bytes((len(b),)) + b
    return b"\xdb" + struct.pack(">I", len(b)) + b


def oversized_chunk() -> bytes:
    """A trajectory message whose rollout name is longer than the decoder accepts (hand-built
    msgpack: the encoder refuses to write it)."""
    body = b"\x81" + _msgpack_str(b"rollout") + _msgpack_str(b"x" * OVERSIZE_STR)
    return b"\x83" + _msgpack_str(b"v") + b"\x01" + _msgpack_str(b"t") + _msgpack_str(b"traj") + _msgpack_str(b"b") + body


def poisoned_chunk(rollout: str, obs_dim: int, act_dim: int, version: int, t: int = 4, n: int = 2) -> TrajectoryChunk:
    """A well-formed chunk whose rewards are NaN and log-probs -inf (and `version` as given)."""
    import numpy as np

    obs = {"state": np.zeros((t, n, obs_dim), np.float32)}
    return TrajectoryChunk(
        rollout=rollout, seq=0, policy_version=version, env_steps=t * n, obs=obs,
        actions=np.zeros((t, n, act_dim), np.float32), logprobs=np.full((t, n), -np.inf, np.float32),
        rewards=np.full((t, n), np.nan, np.float32), terminated=np.zeros((t, n), bool),
        truncated=np.zeros((t, n), bool), success=np.zeros((t, n), bool),
        next_obs={"state": np.zeros((n, obs_dim), np.float32)}, final_obs={"state": np.zeros((t, n, obs_dim), np.float32)},
    )


def garbage(n: int) -> bytes:
    return os.urandom(n)


@dataclass
class Sent:
    """What the attacker sent, per attack."""

    counts: dict[str, int] = field(default_factory=dict)

    def add(self, what: str, n: int = 1) -> None:
        self.counts[what] = self.counts.get(what, 0) + n


class Attacker:
    """Two Zenoh sessions of its own (ctrl: a client of the entry routers; data: a peer of the
    actors' data listeners) and a signing key that is not the cluster's."""

    def __init__(self, run: str, ctrl_entry: tuple[str, ...], data_entry: tuple[str, ...], roles: dict[str, str]) -> None:
        self.keys = KeySpace(run)
        self.roles = roles  # name -> kind
        self.ctrl = zenoh.open(plane_config(mode="client", connect=ctrl_entry))
        self.data = zenoh.open(plane_config(mode="peer", connect=data_entry))
        self.key = os.urandom(32)  # its own key: a well-formed envelope with a wrong tag
        self.captured: list[tuple[str, bytes]] = []
        self.sent = Sent()
        self._capture_subs: list[Any] = []
        self._lock = threading.Lock()
        self._queryables: list[Any] = []

    @classmethod
    def for_run(cls, run_dir: Path) -> "Attacker":
        """Endpoints from a running `dvla up`'s state file and role configs (no secret is read)."""
        state = json.loads((run_dir / "state.json").read_text())
        roles, data = {}, []
        for path in sorted((run_dir / "roles").glob("*.json")):
            cfg = json.loads(path.read_text())
            roles[cfg["name"]] = cfg["kind"]
            if cfg["kind"] == "actor":
                data.extend(cfg["data"]["listen"])
        return cls(state["run"], tuple(state["ctrl_entry"]), tuple(data), roles)

    def names(self, *kinds: str) -> list[str]:
        return sorted(n for n, k in self.roles.items() if k in kinds)

    # -- capture and replay -----------------------------------------------------------------
    def start_capture(self, limit: int = 400, evals: bool = True) -> None:
        """Record genuinely signed messages from the wire: weights, commands (and eval results)."""

        def on_sample(sample: zenoh.Sample) -> None:
            with self._lock:
                if len(self.captured) < limit:
                    self.captured.append((str(sample.key_expr), sample.payload.to_bytes()))

        root = self.keys.root
        patterns = [f"{root}/ctrl/weights/*", f"{root}/ctrl/cmd/*"] + ([f"{root}/ctrl/eval/*"] if evals else [])
        for pattern in patterns:
            self._capture_subs.append(self.ctrl.declare_subscriber(pattern, on_sample))

    def captured_count(self) -> int:
        with self._lock:
            return len(self.captured)

    def replay(self) -> int:
        """Re-publish everything captured, on the key it was captured from."""
        with self._lock:
            msgs = list(self.captured)
        for key, raw in msgs:
            self.ctrl.put(key, raw, congestion_control=zenoh.CongestionControl.DROP)
        self.sent.add("replay", len(msgs))
        return len(msgs)

    # -- forgeries --------------------------------------------------------------------------
    def _forge(self, key: str, msg: Any, sender: str) -> bytes:
        return Signer(self.key, sender).seal(key, encode(msg))

    def _put_ctrl(self, key: str, payload: bytes, what: str) -> None:
        self.ctrl.put(key, payload, congestion_control=zenoh.CongestionControl.DROP)
        self.sent.add(what)

    def forged_weights(self) -> None:
        """A full 'version' FORGED_VERSION from every weight sender's key, under its name."""
        for sender in self.names("actor", "replicator"):
            key = self.keys.weights(sender)
            data = os.urandom(4096)
            man = WeightManifest(sender=sender, version=FORGED_VERSION, base_version=-1, encoding="full",
                                 layout_hash="0" * 16, checksum="0" * 16, n_chunks=1, total_bytes=len(data))
            self._put_ctrl(key, self._forge(key, man, sender), "forged_weights")
            chunk = WeightChunk(sender=sender, version=FORGED_VERSION, index=0, n_chunks=1, data=data)
            self._put_ctrl(key, self._forge(key, chunk, sender), "forged_weights")

    def forged_commands(self) -> None:
        """`stop` to everyone and to each role, under the orchestrator's name."""
        for target in ["all", *self.roles]:
            key = self.keys.cmd(target)
            cmd = Command(target=target, verb="stop", args={}, issued_ns=time.time_ns())
            self._put_ctrl(key, self._forge(key, cmd, "orchestrator"), "forged_commands")

    def forged_status_and_evals(self, evals: bool = True) -> None:
        """Status reports (and eval results) published under the roles' names."""
        for name, kind in self.roles.items():
            st = RoleStatus(name=name, kind=kind, node="evil", rack="evil", pid=1, state="error",
                            policy_version=FORGED_VERSION, env_steps=0, steps_per_s=0.0)
            key = self.keys.status(name)
            self._put_ctrl(key, self._forge(key, st, name), "forged_status")
        for name in self.names("evaluator") if evals else []:
            key = self.keys.eval(name)
            ev = EvalResult(sender=name, policy_version=FORGED_VERSION, episodes=1, success_once=1.0,
                            success_at_end=1.0, return_mean=1e9)
            self._put_ctrl(key, self._forge(key, ev, name), "forged_evals")

    def forged_queries(self) -> None:
        """Queries carrying forged requests: every status queryable, every snapshot queryable."""
        for key, req in ((self.keys.status_all(), SnapshotRequest(requester="evil", have_version=-1)),
                         (f"{self.keys.root}/ctrl/snapshot/*", SnapshotRequest(requester="evil", have_version=-1))):
            replies = self.ctrl.get(key, payload=self._forge(key, req, "orchestrator"), timeout=1.0)
            self.sent.add("forged_queries")
            self.sent.add("replies_to_forged_queries", sum(1 for r in replies if r.ok is not None))

    def forged_chunks(self) -> None:
        """Well-formed chunks under every real rollout's name: NaN rewards at version 0 and a far
        future version, signed with the attacker's key and sent bare (the codec's bytes only)."""
        for name in self.names("rollout"):
            key = self.keys.traj(name)
            for version in (0, FORGED_VERSION):
                body = encode(poisoned_chunk(name, 8, 8, version))
                self.data.put(key, Signer(self.key, name).seal(key, body), congestion_control=zenoh.CongestionControl.BLOCK)
                self.data.put(key, body, congestion_control=zenoh.CongestionControl.BLOCK)
                self.sent.add("data_forged_chunks", 2)

    def many_keys(self, n: int = 100_000) -> None:
        """1-byte puts on `n` distinct made-up trajectory keys."""
        for i in range(n):
            self.data.put(self.keys.traj(f"r{i}"), b"x", congestion_control=zenoh.CongestionControl.DROP)
        self.sent.add("data_many_keys", n)

    def huge_envelopes(self, mb: int = 200) -> None:
        """One `mb` MB envelope on a trajectory key and on the commands key."""
        big = MAGIC + bytes(mb << 20)
        self.data.put(self.keys.traj(self.names("rollout")[0]), big, congestion_control=zenoh.CongestionControl.BLOCK)
        self.ctrl.put(self.keys.cmd("all"), big, congestion_control=zenoh.CongestionControl.BLOCK)
        self.sent.add("huge_envelopes", 2)

    def unsigned_queries(self) -> int:
        """Status and snapshot queries without any payload; returns the replies they got."""
        got = 0
        for key in (self.keys.status_all(), f"{self.keys.root}/ctrl/snapshot/*"):
            got += sum(1 for r in self.ctrl.get(key, timeout=1.0) if r.ok is not None)
            self.sent.add("unsigned_queries")
        return got

    def moved_weights(self) -> int:
        """Captured weight envelopes put again on every *other* weight sender's key."""
        with self._lock:
            msgs = [(k, raw) for k, raw in self.captured if "/ctrl/weights/" in k]
        n = 0
        for key, raw in msgs:
            for sender in self.names("actor", "replicator"):
                other = self.keys.weights(sender)
                if other != key:
                    self.ctrl.put(other, raw, congestion_control=zenoh.CongestionControl.DROP)
                    n += 1
        self.sent.add("moved_weights", n)
        return n

    def rogue_queryables(self) -> None:
        """Answer every status and snapshot query too, with forged replies (a forged snapshot
        claims FORGED_VERSION)."""
        status_key = f"{self.keys.root}/ctrl/status/*"
        snap_key = f"{self.keys.root}/ctrl/snapshot/*"

        def on_status(q: zenoh.Query) -> None:
            name = "actor-evil"
            st = RoleStatus(name=name, kind="actor", node="evil", rack="evil", pid=1, state="running",
                            policy_version=FORGED_VERSION, env_steps=10**12, steps_per_s=0.0,
                            extra={"published_version": FORGED_VERSION})
            key = self.keys.status(name)
            q.reply(key, self._forge(key, st, name))
            self.sent.add("forged_status_replies")
            with self._lock:  # and genuinely signed envelopes captured earlier, replayed as replies
                old = [raw for _k, raw in self.captured[:3]]
            for raw in old:
                try:
                    q.reply(key, raw)
                    self.sent.add("replayed_replies")
                except Exception:
                    pass

        def on_snapshot(q: zenoh.Query) -> None:
            for sender in self.names("actor", "replicator"):
                key = self.keys.snapshot(sender)
                snap = WeightSnapshot(sender=sender, version=FORGED_VERSION, manifest=os.urandom(256), n_chunks=1)
                try:
                    q.reply(key, self._forge(key, snap, sender))
                    self.sent.add("forged_snapshot_replies")
                except Exception:
                    pass  # the query's key does not match this sender's

        self._queryables.append(self.ctrl.declare_queryable(status_key, on_status))
        self._queryables.append(self.ctrl.declare_queryable(snap_key, on_snapshot))

    def ctrl_garbage(self, evals: bool = True) -> None:
        """Random bytes, a bare magic and a truncated envelope on every control key."""
        keys = [self.keys.cmd("all")]
        for name in self.roles:
            keys += [self.keys.cmd(name), self.keys.status(name), self.keys.weights(name)]
            keys += [self.keys.eval(name)] if evals else []
        for key in keys:
            self._put_ctrl(key, garbage(200), "ctrl_unsigned")
            self._put_ctrl(key, MAGIC + bytes(4) + garbage(20), "ctrl_malformed")

    def data_garbage(self) -> None:
        """Garbage and an oversized message on every rollout's trajectory key and on a made-up one."""
        big = oversized_chunk()
        for name in [*self.names("rollout"), "rollout-evil"]:
            key = self.keys.traj(name)
            self.data.put(key, garbage(512), congestion_control=zenoh.CongestionControl.DROP)
            self.sent.add("data_garbage")
            self.data.put(key, big, congestion_control=zenoh.CongestionControl.BLOCK)
            self.sent.add("data_oversize")

    def flood(self, seconds: float, rounds_per_s: float = 4.0, evals: bool = True) -> dict[str, int]:
        """Every attack, repeatedly, for `seconds`; returns what was sent per attack. `evals`
        False spares the eval-result keys (see docs/reliability.md: a flood there starves the
        orchestrator's eval inbox)."""
        self.rogue_queryables()
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            t0 = time.monotonic()
            self.forged_weights()
            self.forged_commands()
            self.forged_status_and_evals(evals)
            self.ctrl_garbage(evals)
            self.data_garbage()
            self.forged_chunks()
            self.forged_queries()
            time.sleep(max(0.0, 1.0 / rounds_per_s - (time.monotonic() - t0)))
        return dict(self.sent.counts)

    def close(self) -> None:
        for e in [*self._capture_subs, *self._queryables]:
            try:
                e.undeclare()
            except Exception:
                pass
        for s in (self.data, self.ctrl):
            try:
                s.close()
            except Exception:
                pass

    def __enter__(self) -> "Attacker":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def rss_kib(pid: int) -> int | None:
    """Resident set size of a process (KiB), or None when it is gone."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None
