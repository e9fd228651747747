"""Integration tests of dvla.fabric over real Zenoh sessions on loopback (no mocks).

Every test wires two fabrics the way `dvla up` wires an actor and a rollout: the "actor" side
holds the ctrl router and listens on the data plane, the "rollout" side is a ctrl client and a
data peer connecting to it. Endpoints are explicit tcp/127.0.0.1 ports and multicast scouting
is off (`plane_config`), so nothing else on the machine can join.

What is checked: trajectory chunks arrive bit-identical and the accounting identity holds;
a slow consumer slows the sender down (or counts what it drops) without killing the session;
forged, unsigned, replayed, stale and garbage control messages are rejected and counted per
reason and never delivered; garbage and oversized data payloads are rejected and counted;
a SIGKILLed member disappears from `watch_alive` in well under a second; status request/reply
works and a wrong secret gets no accepted reply.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Any, Callable, Iterator

import msgpack
import numpy as np
import pytest

from dvla.fabric import (
    CTRL,
    DATA,
    Command,
    Fabric,
    RoleStatus,
    Signer,
    TrajectoryChunk,
    encode,
    plane_config,
)

from dvla.fabric.codec import SCHEMA_VERSION
from dvla.fabric.fabric import UNAUTHENTICATED

ROOT = Path(__file__).resolve().parents[2]
RUN = "fabtest"
SECRET = bytes.fromhex("5eed" * 16)
WRONG_SECRET = bytes.fromhex("bad0" * 16)


# --------------------------------------------------------------------------------------------
# helpers


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(pred: Callable[[], bool], timeout: float, step: float = 0.005) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(step)
    return pred()


def wait_route(receiver: Any, sender: Any, timeout: float = 5.0) -> None:
    """Block until puts from `sender` reach subscribers declared so far on `receiver`.

    `Publisher.matching_status` is not enough between two peers: it can read True before the
    remote subscriber's declaration has arrived, and puts sent meanwhile are lost. So a probe
    subscriber is declared after the ones under test and probed end to end; declarations
    travel in order on the link, so once a probe gets through, the earlier ones are known.
    """
    key = f"probe/{uuid.uuid4().hex}"
    seen = threading.Event()
    sub = receiver.declare_subscriber(key, lambda _sample: seen.set())
    try:
        deadline = time.monotonic() + timeout
        while not seen.is_set():
            assert time.monotonic() < deadline, "no route between the two sessions"
            sender.put(key, b"probe")
            seen.wait(0.02)
    finally:
        sub.undeclare()


def make_chunk(rollout: str, seq: int, *, T: int = 8, N: int = 2, D: int = 5, A: int = 3, rgb: bool = False) -> TrajectoryChunk:
    rng = np.random.default_rng(seq)
    obs = {"state": rng.standard_normal((T, N, D), dtype=np.float32)}
    next_obs = {"state": rng.standard_normal((N, D), dtype=np.float32)}
    final_obs = {"state": np.zeros((T, N, D), np.float32)}
    if rgb:
        obs["rgb"] = rng.integers(0, 256, (T, N, 32, 32, 3), dtype=np.uint8)
        next_obs["rgb"] = rng.integers(0, 256, (N, 32, 32, 3), dtype=np.uint8)
        final_obs["rgb"] = np.zeros((T, N, 32, 32, 3), np.uint8)
    terminated = rng.random((T, N)) < 0.1
    return TrajectoryChunk(
        rollout=rollout, seq=seq, policy_version=seq // 4, env_steps=T * N,
        obs=obs, actions=rng.standard_normal((T, N, A), dtype=np.float32),
        logprobs=rng.standard_normal((T, N), dtype=np.float32),
        rewards=rng.standard_normal((T, N), dtype=np.float32),
        terminated=terminated, truncated=np.zeros((T, N), bool), success=terminated.copy(),
        next_obs=next_obs, final_obs=final_obs,
    )


def big_chunk(rollout: str, seq: int, nbytes: int) -> TrajectoryChunk:
    """A chunk whose encoding is about `nbytes` (the bulk is a uint8 image observation)."""
    T, N = 4, 2
    # obs and final_obs hold T images per env, next_obs one: (2T + 1) * N images in all
    side = max(1, int((nbytes / ((2 * T + 1) * N * 3)) ** 0.5))
    c = make_chunk(rollout, seq, T=T, N=N)
    img = np.full((T, N, side, side, 3), seq % 251, np.uint8)
    return TrajectoryChunk(
        rollout=c.rollout, seq=c.seq, policy_version=c.policy_version, env_steps=c.env_steps,
        obs={**c.obs, "rgb": img}, actions=c.actions, logprobs=c.logprobs, rewards=c.rewards,
        terminated=c.terminated, truncated=c.truncated, success=c.success,
        next_obs={**c.next_obs, "rgb": img[0]}, final_obs={**c.final_obs, "rgb": img},
    )


def assert_same_chunk(got: TrajectoryChunk, want: TrajectoryChunk) -> None:
    for name in ("rollout", "seq", "policy_version", "env_steps", "created_ns"):
        assert getattr(got, name) == getattr(want, name), name
    for name in ("actions", "logprobs", "rewards", "terminated", "truncated", "success"):
        a, b = getattr(got, name), getattr(want, name)
        assert a.dtype == b.dtype and a.shape == b.shape, name
        np.testing.assert_array_equal(a, b, err_msg=name)
    for group in ("obs", "next_obs", "final_obs"):
        a, b = getattr(got, group), getattr(want, group)
        assert a.keys() == b.keys(), group
        for k in a:
            assert a[k].dtype == b[k].dtype
            np.testing.assert_array_equal(a[k], b[k], err_msg=f"{group}[{k}]")


def status_of(name: str, env_steps: int = 0) -> RoleStatus:
    return RoleStatus(
        name=name, kind="actor", node="node0", rack="rack0", pid=os.getpid(), state="running",
        policy_version=3, env_steps=env_steps, steps_per_s=1.5, extra={"k": "v"},
    )


def open_actor_side(ctrl_port: int, data_port: int, name: str = "actor") -> Fabric:
    return Fabric(
        run=RUN, name=name, secret=SECRET,
        ctrl_conf=plane_config(mode="router", listen=[f"tcp/127.0.0.1:{ctrl_port}"]),
        data_conf=plane_config(mode="peer", listen=[f"tcp/127.0.0.1:{data_port}"]),
    )


def open_client(ctrl_port: int, data_port: int | None, name: str, secret: bytes = SECRET) -> Fabric:
    data = None if data_port is None else plane_config(mode="peer", connect=[f"tcp/127.0.0.1:{data_port}"])
    return Fabric(
        run=RUN, name=name, secret=secret, open_timeout_s=10.0,
        ctrl_conf=plane_config(mode="client", connect=[f"tcp/127.0.0.1:{ctrl_port}"]),
        data_conf=data,
    )


class Pair:
    """An actor-side fabric and a rollout-side fabric connected to it."""

    def __init__(self) -> None:
        self.ctrl_port, self.data_port = free_port(), free_port()
        self.actor = open_actor_side(self.ctrl_port, self.data_port)
        self._extra: list[Fabric] = [self.actor]
        self.rollout = self.client("rollout-0", data=True)

    def client(self, name: str, *, data: bool = False, secret: bytes = SECRET) -> Fabric:
        f = open_client(self.ctrl_port, self.data_port if data else None, name, secret)
        self._extra.append(f)
        return f

    def close(self) -> None:
        for f in reversed(self._extra):
            f.close()


@pytest.fixture
def pair() -> Iterator[Pair]:
    p = Pair()
    try:
        yield p
    finally:
        p.close()


def data_identity(sender: Fabric, receiver: Fabric, consumed: int, queued: int) -> dict[str, int]:
    s, r = sender.accounting, receiver.accounting
    counts = {
        "sent": s.get(DATA, "sent"),
        "received": r.get(DATA, "received"),
        "consumed": consumed,
        "dropped": r.get(DATA, "dropped"),
        "rejected": r.get(DATA, "rejected"),
        "queued": queued,
    }
    return counts


# --------------------------------------------------------------------------------------------
# data plane


def test_a_rollout_learns_when_its_trajectory_link_loses_the_learner(tmp_path: Path) -> None:
    """The ledger's link breaks come from here: a real publisher's matching status going to
    none when the learner's data session goes away, once per loss (and again after it is back)."""
    from dvla.ledger import RolloutLedger

    pair = Pair()
    try:
        ledger = RolloutLedger(tmp_path, pair.rollout.name, queue_cap=8)
        pair.rollout.on_traj_unmatched(ledger.add_break)
        inbox = pair.actor.subscribe_traj(maxsize=16, expect=TrajectoryChunk)
        wait_route(pair.actor.data, pair.rollout.data)
        for i in range(3):
            ledger.add_shipped(pair.rollout.publish_traj(make_chunk(pair.rollout.name, i)))
        assert wait_for(lambda: inbox.depth() == 3, 5)
        assert ledger.breaks_total == 0
        pair.actor.close()  # the learner goes away: the link has nothing left to reach
        assert wait_for(lambda: ledger.breaks_total == 1, 10), "no link break seen"
        assert ledger.breaks[0][0] == 3  # three chunks had been shipped by then
        actor = open_actor_side(pair.ctrl_port, pair.data_port, name="actor-again")
        pair._extra.append(actor)
        actor.subscribe_traj(maxsize=16, expect=TrajectoryChunk)
        assert wait_for(pair.rollout.traj_matched, 10)
        actor.close()  # lost again, but nothing was shipped in between: not a second break
        assert wait_for(lambda: not pair.rollout.traj_matched(), 10)
        time.sleep(0.2)
        assert ledger.breaks_total == 1
        ledger.close()
        record = json.loads(next((tmp_path / "counters").iterdir()).read_bytes())
        assert record["breaks_total"] == 1 and record["breaks"][0][0] == 3
    finally:
        pair.close()


@pytest.mark.timeout(90)
@pytest.mark.parametrize("receipt", [False, True], ids=["close-at-once", "receipt-first"])
def test_a_rollout_closing_on_a_slow_learner_keeps_its_tail_only_if_it_waits(tmp_path: Path, receipt: bool) -> None:
    """Why a stopping rollout waits for its learner's receipt (docs/reliability.md, "Closing a
    rollout"). A put returns once Zenoh has queued the chunk; a learner that reads slowly leaves MBs
    of chunks in the rollout's socket buffers. Closing the session leaves them to a half-closed
    socket, which the kernel resets when the learner's Zenoh sends its next keep-alive (every lease
    / 4: 250 ms here, 2.5 s by default), dropping them: the learner never sees the last chunks.
    Asking for the receipt of the last chunk first (RolloutLedger.await_receipt, answered by
    ActorLedger.receipt as the actor serves it) loses nothing."""
    from dvla.fabric.messages import ReceiptRequest
    from dvla.ledger import ActorLedger, RolloutLedger

    ctrl_port, data_port = free_port(), free_port()
    actor = Fabric(run=RUN, name="actor", secret=SECRET,
                   ctrl_conf=plane_config(mode="router", listen=[f"tcp/127.0.0.1:{ctrl_port}"]),
                   data_conf=plane_config(mode="peer", listen=[f"tcp/127.0.0.1:{data_port}"], lease_ms=1000))
    rollout = open_client(ctrl_port, data_port, "rollout-0")
    try:
        received = ActorLedger(tmp_path / "actor", actor.name, actor.accounting, slots=1, inbox_cap=2)
        actor.serve(actor.keys.receipt(actor.name), received.receipt, ReceiptRequest)
        inbox = actor.subscribe_traj(maxsize=2, expect=TrajectoryChunk, block_s=30.0,
                                     on_dropped=lambda c: received.fabric_dropped(c.rollout, c.seq))
        wait_route(actor.data, rollout.data)
        shipped = RolloutLedger(tmp_path / "rollout", rollout.name, queue_cap=8)
        got: list[int] = []

        def learn() -> None:  # the slow learner: 20 chunks a second
            while (c := inbox.get(timeout=3.0)) is not None:
                received.settle(received.got(c.rollout, c.seq), "consumed")
                got.append(c.seq)
                time.sleep(0.05)

        learner = threading.Thread(target=learn, name="slow-learner", daemon=True)
        learner.start()
        n = 60  # 320 kB each: far more than the learner reads before the close
        for i in range(n):
            shipped.add_produced()
            shipped.add_shipped(rollout.publish_traj(big_chunk(rollout.name, shipped.first_seq + i, 320_000)))
        if receipt:
            wait = shipped.await_receipt(rollout, [actor.name])
            assert (wait.unconfirmed, wait.why) == (0, "") and wait.queries >= 1, wait
        rollout.close()
        learner.join(30)
        assert not learner.is_alive()
        assert got == list(range(len(got)))  # in order, and what is missing is the tail
        if receipt:
            assert len(got) == n and received.newest(rollout.name, shipped.last_seq) == shipped.last_seq
        else:  # the control: without the wait this setup does lose the tail (else it tests nothing)
            assert len(got) < n, "closing at once lost nothing: the receipt-first case proves nothing either"
    finally:
        rollout.close()
        actor.close()


@pytest.mark.timeout(30)
def test_traj_chunks_round_trip_and_accounting_identity(pair: Pair) -> None:
    actor, rollout = pair.actor, pair.rollout
    inbox = actor.subscribe_traj(maxsize=16, expect=TrajectoryChunk)
    wait_route(actor.data, rollout.data)
    # Small chunks and ~200 KB ones (fragmented by Zenoh), interleaved.
    sent = [make_chunk(rollout.name, i, rgb=(i % 3 == 0)) if i % 5 else big_chunk(rollout.name, i, 200_000) for i in range(60)]
    publisher = threading.Thread(target=lambda: [rollout.publish_traj(c) for c in sent], daemon=True)
    publisher.start()
    got: list[TrajectoryChunk] = []
    deadline = time.monotonic() + 15
    while len(got) < len(sent) and time.monotonic() < deadline:
        c = inbox.get(timeout=0.5)
        if c is not None:
            got.append(c)
    publisher.join(timeout=10)
    assert not publisher.is_alive()

    assert [c.seq for c in got] == list(range(len(sent)))  # one publisher: in order, none missing
    for g in got:
        assert_same_chunk(g, sent[g.seq])
    assert wait_for(lambda: actor.accounting.get(DATA, "received") >= rollout.accounting.get(DATA, "sent"), 5)
    counts = data_identity(rollout, actor, consumed=len(got), queued=inbox.depth())
    assert counts["sent"] == counts["received"] == len(sent), counts
    assert counts["received"] == counts["consumed"] + counts["dropped"] + counts["rejected"] + counts["queued"], counts
    assert counts["dropped"] == counts["rejected"] == counts["queued"] == 0, counts
    per_peer = actor.accounting.snapshot()[DATA]["peers"][rollout.name]
    assert per_peer["received"] == len(sent)
    assert rollout.accounting.get(DATA, "sent_bytes") == actor.accounting.get(DATA, "received_bytes")


@pytest.mark.timeout(30)
def test_a_chunk_refilled_in_place_arrives_as_each_new_chunk(pair: Pair) -> None:
    """A rollout's path: one chunk's arrays overwritten for every new chunk, each published
    with its own per-chunk fields; the encode copies the arrays, so none leaks into another."""
    actor, rollout = pair.actor, pair.rollout
    inbox = actor.subscribe_traj(maxsize=64, expect=TrajectoryChunk)
    wait_route(actor.data, rollout.data)
    template = make_chunk(rollout.name, 0, rgb=True)
    sent_actions, sizes = [], []
    for i in range(40):
        template.actions[...] = i  # the arrays are reused: each chunk overwrites the last
        template.obs["rgb"][0, 0, 0, 0, 0] = i
        chunk = dataclasses.replace(template, seq=i, policy_version=i // 4, created_ns=time.time_ns())
        sizes.append(rollout.publish_traj(chunk))
        sent_actions.append(float(i))
    got: list[TrajectoryChunk] = []
    deadline = time.monotonic() + 10
    while len(got) < 40 and time.monotonic() < deadline:
        c = inbox.get(timeout=0.5)
        if c is not None:
            got.append(c)
    assert [c.seq for c in got] == list(range(40))
    assert [float(c.actions[0, 0, 0]) for c in got] == sent_actions
    assert [c.policy_version for c in got] == [i // 4 for i in range(40)]
    assert all(int(c.obs["rgb"][0, 0, 0, 0, 0]) == c.seq for c in got)
    counts = data_identity(rollout, actor, consumed=len(got), queued=inbox.depth())
    assert counts["sent"] == counts["received"] == counts["consumed"] == 40, counts
    assert rollout.accounting.get(DATA, "sent_bytes") == sum(sizes) == actor.accounting.get(DATA, "received_bytes")
    # A chunk of another rollout is refused before it is sent (receivers would reject it).
    with pytest.raises(ValueError, match="rollout-9"):
        rollout.publish_traj(make_chunk("rollout-9", 0))
    assert rollout.accounting.get(DATA, "sent") == 40


@pytest.mark.timeout(40)
@pytest.mark.parametrize("block_s", [1.0, 0.01], ids=["blocks", "drops"])
def test_slow_consumer_backpressure_loses_nothing_silently(pair: Pair, block_s: float) -> None:
    actor, rollout = pair.actor, pair.rollout
    actor.serve(actor.keys.status(actor.name), lambda _req: status_of(actor.name))
    dropped: list[int] = []  # each drop, decoded for the reader (how far a sender's chunks got)
    inbox = actor.subscribe_traj(maxsize=2, expect=TrajectoryChunk, block_s=block_s,
                                 on_dropped=lambda c: dropped.append(c.seq))
    wait_route(actor.data, rollout.data)
    n, size, pause = 60, 1 << 20, 0.03
    done = threading.Event()
    consumed: list[int] = []
    consumed_when_done: list[int] = []

    def publish() -> None:
        for i in range(n):
            rollout.publish_traj(big_chunk(rollout.name, i, size))
        consumed_when_done.append(len(consumed))
        done.set()

    threading.Thread(target=publish, daemon=True).start()
    deadline = time.monotonic() + 25
    while time.monotonic() < deadline:
        c = inbox.get(timeout=0.3)
        if c is not None:
            consumed.append(c.seq)
            time.sleep(pause)  # the slow consumer
        elif done.is_set() and actor.accounting.get(DATA, "received") >= rollout.accounting.get(DATA, "sent"):
            break
    assert done.is_set(), "the publisher never finished: backpressure turned into a stall"

    counts = data_identity(rollout, actor, consumed=len(consumed), queued=inbox.depth())
    assert counts["sent"] == counts["received"] == n, counts
    assert counts["received"] == counts["consumed"] + counts["dropped"] + counts["rejected"] + counts["queued"], counts
    assert counts["rejected"] == 0
    assert actor.accounting.get(DATA, "dropped.backpressure") == counts["dropped"]
    assert consumed == sorted(consumed) and len(set(consumed)) == len(consumed)
    assert len(dropped) == counts["dropped"] and not set(dropped) & set(consumed)
    if block_s >= 1.0:
        # The callback waited for space instead of dropping, so the sender could only run
        # ahead of the consumer by what Zenoh's and the kernel's buffers hold (some MB).
        assert counts["dropped"] == 0, counts
        assert consumed_when_done[0] >= n // 3, f"publisher done after {consumed_when_done[0]} of {n} consumed"
    else:
        assert counts["dropped"] > 0, counts  # the consumer cannot keep up and drops are counted

    # The sessions survived: a ctrl round trip works and a later chunk still arrives.
    replies = rollout.query(actor.keys.status(actor.name), timeout=5.0)
    assert [s for s, _ in replies] == [actor.name]
    late = make_chunk(rollout.name, 1000)
    rollout.publish_traj(late)
    got = inbox.get(timeout=5.0)
    while got is not None and got.seq != 1000:
        got = inbox.get(timeout=5.0)
    assert got is not None, "a chunk sent after the slow phase never arrived"
    assert_same_chunk(got, late)


@pytest.mark.timeout(30)
def test_chunks_that_waited_in_the_inbox_longer_than_the_age_limit_are_accepted() -> None:
    # A learner busy with an update leaves chunks in its bounded inbox; they arrived fresh and are
    # verified when read, so their age is judged at arrival (before: refused as "stale" once the
    # wait passed max_age_s, 2-4 % of the chunks of a slow VLA run). Control inboxes do the same.
    ctrl_port, data_port = free_port(), free_port()
    actor = Fabric(run=RUN, name="actor", secret=SECRET, max_age_s=1.0,
                   ctrl_conf=plane_config(mode="router", listen=[f"tcp/127.0.0.1:{ctrl_port}"]),
                   data_conf=plane_config(mode="peer", listen=[f"tcp/127.0.0.1:{data_port}"]))
    rollout = open_client(ctrl_port, data_port, "rollout-0")
    try:
        inbox = actor.subscribe_traj(maxsize=8, expect=TrajectoryChunk)
        wait_route(actor.data, rollout.data)
        sent = [make_chunk(rollout.name, i) for i in range(3)]
        for c in sent:
            rollout.publish_traj(c)
        assert wait_for(lambda: inbox.depth() == len(sent), 5), inbox.depth()
        time.sleep(1.5)  # longer than max_age_s, in the actor's own queue
        got = [inbox.get(timeout=1.0) for _ in sent]
        assert [c.seq for c in got if c is not None] == [0, 1, 2]
        assert actor.accounting.get(DATA, "rejected") == 0
    finally:
        rollout.close()
        actor.close()


@pytest.mark.timeout(30)
def test_garbage_and_oversized_data_payloads_are_rejected_and_counted(pair: Pair) -> None:
    actor, rollout = pair.actor, pair.rollout
    inbox = actor.subscribe_traj(maxsize=32, expect=TrajectoryChunk)
    key = rollout.keys.traj(rollout.name)
    wait_route(actor.data, rollout.data)
    good = encode(make_chunk(rollout.name, 0))
    bad = {
        "garbage": bytes(range(256)) * 12,
        "not-a-map": b"\x00",
        "truncated": good[: len(good) // 2],
        "trailing": good + b"\x00",
        # msgpack whose one string is 2 MiB (> Limits.max_str_len): refused before any copy
        "oversized-string": msgpack.packb({"v": SCHEMA_VERSION, "t": "traj", "b": {"rollout": "x" * (2 << 20)}}),
        # a bin header that claims 300 MiB (> Limits.max_message_bytes/max_array_bytes)
        "oversized-claim": b"\x83\xa1v\x01\xa1t\xa4traj\xa1b\x81\xa4data\xc6" + (300 << 20).to_bytes(4, "big"),
        "wrong-type": encode(Command(target="all", verb="stop")),
        "other-sender": encode(make_chunk("rollout-9", 1)),  # claims another rollout's name
    }
    member = Signer(SECRET, rollout.name)
    for payload in bad.values():  # signed by a member of the run: they reach the decoder
        rollout.data.put(key, member.seal(key, payload))
    rollout.data.put(key, good)  # a well-formed chunk, unsigned
    rollout.data.put(key, Signer(b"k" * 32, rollout.name).seal(key, good))  # signed with another secret
    rollout.publish_traj(make_chunk(rollout.name, 7))  # the subscriber keeps working

    got = inbox.get(timeout=5.0)
    assert got is not None and got.seq == 7 and got.rollout == rollout.name
    assert inbox.get(timeout=0.3) is None
    acct = actor.accounting
    assert acct.get(DATA, "received") == len(bad) + 3
    assert acct.get(DATA, "rejected") == len(bad) + 2
    assert acct.get(DATA, "rejected.unsigned", UNAUTHENTICATED) == 1
    assert acct.get(DATA, "rejected.key_id", UNAUTHENTICATED) == 1
    assert acct.get(DATA, "rejected", rollout.name) == len(bad)  # a member's own bad data is its own
    assert acct.get(DATA, "rejected.oversize") == 2
    assert acct.get(DATA, "rejected.type") == 1
    assert acct.get(DATA, "rejected.sender_mismatch") == 1
    assert acct.get(DATA, "rejected.malformed") == 3
    assert acct.get(DATA, "rejected.schema") == 1
    assert acct.get(DATA, "received") == 1 + acct.get(DATA, "rejected") + acct.get(DATA, "dropped") + inbox.depth()


SINK_SCRIPT = """
import sys, time
from dvla.fabric import Fabric, TrajectoryChunk, plane_config
f = Fabric(run={run!r}, name="sink", secret=bytes.fromhex({secret!r}),
           ctrl_conf=plane_config(mode="peer", listen=["tcp/127.0.0.1:{ctrl}"]),
           data_conf=plane_config(mode="peer", listen=["tcp/127.0.0.1:{data}"]))
inbox = f.subscribe_traj(maxsize=8, expect=TrajectoryChunk)
print("ready", flush=True)
got = 0
deadline = time.monotonic() + 20
while got < 50 and time.monotonic() < deadline:
    got += inbox.get(timeout=0.1) is not None
print("got", got, flush=True)
{ending}
"""


@pytest.mark.timeout(60)
@pytest.mark.parametrize("ending", ["f.close()", "pass"], ids=["closed", "left-open"])
def test_a_receiving_process_exits_cleanly_while_chunks_still_arrive(ending: str) -> None:
    """Interpreter exit with chunks still arriving on Zenoh's receive thread (the inbox full,
    its callback waiting for room), the fabric closed or not: the process exits 0, without a
    fatal error."""
    ctrl, data = free_port(), free_port()
    script = SINK_SCRIPT.format(run=RUN, secret=SECRET.hex(), ctrl=ctrl, data=data, ending=ending)
    proc = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    stop = threading.Event()
    source = None
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
        source = Fabric(run=RUN, name="rollout-0", secret=SECRET, ctrl_conf=plane_config(),
                        data_conf=plane_config(mode="peer", connect=[f"tcp/127.0.0.1:{data}"]))

        def flood() -> None:
            i = 0
            while not stop.is_set():
                try:
                    source.publish_traj(make_chunk("rollout-0", i))
                except Exception:
                    return
                i += 1
                time.sleep(0.001)

        t = threading.Thread(target=flood, name="flood")
        t.start()
        out, err = proc.communicate(timeout=40)
        stop.set()
        t.join(10)
        assert out.split()[-2:-1] == ["got"] and int(out.split()[-1]) >= 50, (out, err)
        assert proc.returncode == 0, err
        assert "Fatal Python error" not in err and "panicked" not in err, err
    finally:
        stop.set()
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        if source is not None:
            source.close()


# --------------------------------------------------------------------------------------------
# control plane


@pytest.mark.timeout(30)
def test_forged_unsigned_replayed_and_garbage_ctrl_messages_are_rejected(pair: Pair) -> None:
    actor, rollout = pair.actor, pair.rollout
    key = actor.keys.cmd(actor.name)
    inbox = actor.subscribe_ctrl(key, maxsize=64, expect=Command)
    handled: list[tuple[str, Command]] = []
    actor.on_ctrl(actor.keys.cmd("all"), Command, lambda sender, cmd: handled.append((sender, cmd)))
    wait_route(actor.ctrl, rollout.ctrl)

    cmd = Command(target=actor.name, verb="pause", args={"why": "test"})
    body = encode(cmd)
    forged = Signer(WRONG_SECRET, rollout.name).seal(key, body)
    valid = rollout.seal(key, cmd)
    tampered = bytearray(rollout.seal(key, cmd))
    tampered[-40] ^= 0x01  # a payload byte: the tag no longer matches
    other_key = rollout.seal(actor.keys.cmd("someone-else"), cmd)  # signed for another key
    stale = Signer(SECRET, rollout.name, clock=lambda: time.time_ns() - 120 * 10**9).seal(key, body)
    signed_garbage = Signer(SECRET, rollout.name).seal(key, b"\xc1not msgpack")
    cases = [
        (forged, "key_id"),  # signed with another secret
        (bytes(tampered), "bad_signature"),
        (other_key, "bad_signature"),
        (body, "unsigned"),  # raw encoded bytes, no envelope
        (os.urandom(200).replace(b"DVS4", b"XXXX"), "unsigned"),  # garbage
        (b"DVS4" + os.urandom(60), "malformed"),  # garbage behind the magic
        (stale, "stale"),
        (signed_garbage, "malformed"),  # the envelope verifies, the payload does not decode
        (valid, None),
        (valid, "replay"),  # the same envelope again
    ]
    for payload, _ in cases:
        rollout.ctrl.put(key, payload)
    rollout.publish_ctrl(key, Command(target=actor.name, verb="resume"))

    delivered = []
    while (got := inbox.get(timeout=2.0)) is not None:
        delivered.append(got)
    # publish_ctrl sends at a higher priority than the raw puts: it may overtake them.
    assert sorted((s, c.verb) for s, c in delivered) == [(rollout.name, "pause"), (rollout.name, "resume")]
    assert next(c for _, c in delivered if c.verb == "pause").args == {"why": "test"}

    acct = actor.accounting
    assert acct.get(CTRL, "received") == len(cases) + 1
    expected: dict[str, int] = {}
    for _, reason in cases:
        if reason:
            expected[reason] = expected.get(reason, 0) + 1
    for reason, n in expected.items():
        assert acct.get(CTRL, f"rejected.{reason}") == n, (reason, acct.snapshot()[CTRL])
    assert acct.get(CTRL, "rejected") == sum(expected.values())

    # The callback path (on_ctrl) applies the same checks.
    all_key = actor.keys.cmd("all")
    rollout.ctrl.put(all_key, Signer(WRONG_SECRET, rollout.name).seal(all_key, body))
    rollout.ctrl.put(all_key, encode(cmd))
    rollout.publish_ctrl(all_key, Command(target="all", verb="checkpoint"))
    assert wait_for(lambda: len(handled) >= 1, 5)
    time.sleep(0.3)
    assert [(s, c.verb) for s, c in handled] == [(rollout.name, "checkpoint")]
    assert acct.get(CTRL, "rejected.key_id") == expected["key_id"] + 1
    assert acct.get(CTRL, "rejected.unsigned") == expected["unsigned"] + 1


@pytest.mark.timeout(30)
def test_status_request_reply_and_wrong_secret(pair: Pair) -> None:
    actor, rollout = pair.actor, pair.rollout
    requests: list[Any] = []

    def handler(req: Any) -> RoleStatus:
        requests.append(req)
        return status_of(actor.name, env_steps=1234)

    actor.serve(actor.keys.status(actor.name), handler)
    replies = rollout.query(actor.keys.status(actor.name), expect=RoleStatus, timeout=5.0)
    assert len(replies) == 1
    sender, st = replies[0]
    assert sender == actor.name and st.env_steps == 1234 and st.extra == {"k": "v"}
    # A wildcard selector reaches it too, with and without a request (always signed).
    assert [s for s, _ in rollout.query(actor.keys.status_all(), timeout=5.0)] == [actor.name]
    req = Command(target=actor.name, verb="checkpoint")
    assert [s for s, _ in rollout.query(actor.keys.status_all(), req, timeout=5.0)] == [actor.name]
    assert [s for s, _ in rollout.query(actor.keys.status(actor.name), req, timeout=5.0)] == [actor.name]
    assert requests[0] is None and [r.verb for r in requests[2:]] == ["checkpoint", "checkpoint"]

    # Wrong secret, with or without a request: the actor refuses the query and does not answer.
    intruder = pair.client("intruder", secret=WRONG_SECRET)
    before = len(requests)
    assert intruder.query(actor.keys.status(actor.name), timeout=3.0) == []
    assert intruder.query(actor.keys.status(actor.name), req, timeout=3.0) == []
    assert len(requests) == before
    assert actor.accounting.get(CTRL, "rejected.key_id") == 2
    assert intruder.accounting.get(CTRL, "received") == 0  # no reply came back
    # An unsigned query (a bare Zenoh get) gets nothing either, and is counted.
    assert [r for r in intruder.ctrl.get(actor.keys.status(actor.name), timeout=2.0) if r.ok is not None] == []
    assert actor.accounting.get(CTRL, "rejected.unsigned") == 1


# --------------------------------------------------------------------------------------------
# membership

MEMBER_SCRIPT = """
import sys, time
from dvla.fabric import Fabric, plane_config
f = Fabric(run={run!r}, name={name!r}, secret=bytes.fromhex({secret!r}), data_conf=None,
           ctrl_conf=plane_config(mode="client", connect=[{endpoint!r}]))
f.declare_alive()
print("alive", flush=True)
time.sleep(120)
"""


@pytest.mark.timeout(40)
def test_killed_member_is_seen_gone_within_a_second(pair: Pair) -> None:
    actor = pair.actor
    events: list[tuple[float, str, bool]] = []
    lock = threading.Lock()

    def on_alive(role: str, alive: bool) -> None:
        with lock:
            events.append((time.monotonic(), role, alive))

    actor.declare_alive()
    actor.watch_alive(on_alive)
    name = "member-0"
    script = MEMBER_SCRIPT.format(run=RUN, name=name, secret=SECRET.hex(), endpoint=f"tcp/127.0.0.1:{pair.ctrl_port}")
    proc = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "alive"
        assert wait_for(lambda: (name, True) in [(r, a) for _, r, a in events], 5), events
        assert name in actor.alive_members()
        proc.send_signal(signal.SIGKILL)
        # TCP close of the killed process ends its session at once; the lease (10 s) is only
        # the fallback for links that vanish without a close, so no lease tuning is needed: seen
        # gone well before the lease could have ended it
        assert wait_for(lambda: (name, False) in [(r, a) for _, r, a in events], 5, step=0.001), events
        assert name not in actor.alive_members()
        assert (actor.name, True) in [(r, a) for _, r, a in events]  # history: current members first
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=10)
        if proc.stdout is not None:
            proc.stdout.close()


@pytest.mark.timeout(30)
def test_a_snapshot_is_the_held_version_whole_in_chunks_bound_to_one_query(pair: Pair) -> None:
    """serve_snapshots answers one query with a header carrying the actor's signed manifest, then
    the held version's full payload as WeightChunks (each within the ctrl plane's message cap);
    they assemble and apply as the full version of that manifest."""
    import hashlib

    from dvla.fabric.messages import SnapshotRequest, WeightChunk, WeightManifest, WeightSnapshot
    from dvla.replication import ChunkAssembler, HeldWeights, ParamLayout, WeightEncoder
    from dvla.roles.weightsync import serve_snapshots

    actor, rollout = pair.actor, pair.rollout
    layout = ParamLayout(names=("w",), shapes=((2600,),), dtypes=("float32",))  # 10,400 bytes: 11 chunks of 1,000
    enc = WeightEncoder(layout, sender=actor.name, seal=lambda m: actor.seal(actor.keys.weights_signed(), m))
    for _ in range(3):
        v = enc.encode(np.arange(2600, dtype=np.float32) + enc.version)
    serve_snapshots(actor, actor.name, lambda: enc.held, chunk_bytes=1000)
    wait_route(actor.ctrl, rollout.ctrl)
    replies = rollout.query(actor.keys.snapshot(actor.name), SnapshotRequest(requester=rollout.name, have_version=-1),
                            expect=(WeightSnapshot, WeightChunk), timeout=5.0)
    assert len(replies) == 12 and {s for s, _ in replies} == {actor.name}
    (head,) = [m for _s, m in replies if isinstance(m, WeightSnapshot)]
    assert head.version == 3 and head.n_chunks == 11 and head.manifest == v.proof
    proof = rollout.open_signed(rollout.keys.weights_signed(), head.manifest, WeightManifest, fresh=False)[1]
    whole = proof.whole(head.n_chunks)
    asm = ChunkAssembler(whole.n_chunks, whole.total_bytes, layout.nbytes)
    for _s, c in replies:
        if isinstance(c, WeightChunk):
            assert len(c.data) <= 1000 and asm.add(c.index, c.data)
    assert hashlib.sha256(asm.payload()).hexdigest() == proof.digest
    held = HeldWeights(layout)
    held.apply(whole, asm.payload())
    assert held.id == enc.held.id and np.array_equal(held.active, enc.published)
    # Up to date: one header-only reply.
    replies = rollout.query(actor.keys.snapshot(actor.name), SnapshotRequest(requester=rollout.name, have_version=3),
                            expect=(WeightSnapshot, WeightChunk), timeout=5.0)
    assert [(s.version, s.manifest, s.n_chunks) for _n, s in replies] == [(3, b"", 0)]




def test_a_role_gets_a_zenoh_receive_thread_per_rollout_beside_the_default_ones() -> None:
    """An actor's trajectory links may each hold a receive thread while its inbox is full
    (backpressure); the ctrl session must still have threads of the shared pool to be read on."""
    import subprocess
    import sys

    code = """
import collections, os, socket, time, zenoh
from dvla.roles.runtime import ZENOH_RX_THREADS, size_zenoh_rx
from dvla.fabric import plane_config
size_zenoh_rx(3)
s = socket.socket(); s.bind(("127.0.0.1", 0)); port = s.getsockname()[1]; s.close()
a = zenoh.open(plane_config(listen=[f"tcp/127.0.0.1:{port}"]))
b = zenoh.open(plane_config(connect=[f"tcp/127.0.0.1:{port}"]))
deadline = time.monotonic() + 20
while time.monotonic() < deadline and not b.info.peers_zid():
    time.sleep(0.05)
def rx_threads():
    names = []
    for t in os.listdir("/proc/self/task"):
        try:
            names.append(open(f"/proc/self/task/{t}/comm").read().strip())
        except OSError:  # a thread that ended meanwhile
            pass
    return sum(n.startswith("rx-") for n in names)
# the pool's threads may start after the first link is up: wait for them (a wrong size never gets there)
while time.monotonic() < deadline + 10 and rx_threads() < ZENOH_RX_THREADS + 3:
    time.sleep(0.05)
print(rx_threads(), ZENOH_RX_THREADS + 3)
"""
    env = {k: v for k, v in os.environ.items() if k != "ZENOH_RUNTIME"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=env)
    assert out.returncode == 0, out.stderr
    got, want = out.stdout.split()
    assert got == want, out.stdout
