"""Tests of dvla.fabric.Fabric on loopback: the send caps (an envelope over the plane's
max_message_size, which every receiver would drop while reassembling it, is not sent and is
counted) and zero-copy receipt (every array of a received chunk is an aligned view of the
received bytes)."""

from __future__ import annotations

import socket
import time

import numpy as np

from dvla.fabric import Fabric, TrajectoryChunk, plane_config
from dvla.fabric.accounting import UNAUTHENTICATED
from dvla.fabric.identity import Identity
from dvla.fabric.messages import Command


def _chunk(name: str, n_obs: int) -> TrajectoryChunk:
    f = np.zeros((1, 1), np.float32)
    b = np.zeros((1, 1), bool)
    return TrajectoryChunk(rollout=name, seq=0, policy_version=0, env_steps=1,
                           obs={"state": np.zeros((1, 1, n_obs), np.float32)}, actions=np.zeros((1, 1, 1), np.float32),
                           logprobs=f, rewards=f, terminated=b, truncated=b, success=b,
                           next_obs={"state": np.zeros((1, n_obs), np.float32)},
                           final_obs={"state": np.zeros((1, 1, n_obs), np.float32)})


def test_envelopes_over_the_plane_cap_are_counted_not_sent():
    cap = 64 << 10
    conf = lambda: plane_config(mode="peer", listen=("tcp/127.0.0.1:0",), max_message_size=cap)  # noqa: E731
    fabric = Fabric(run="caps", name="r0", ctrl_conf=conf(), data_conf=conf(), secret=b"k" * 32)
    try:
        assert fabric.send_cap == {"ctrl": cap, "data": cap}
        assert fabric.publish_traj(_chunk("r0", 8)) > 0
        assert fabric.publish_traj(_chunk("r0", cap // 4)) == 0  # ~3 x 64 KiB of obs
        big = Command(target="all", verb="stop", args={"x": np.zeros(cap, np.uint8)}, issued_ns=0)
        assert fabric.publish_ctrl(fabric.keys.cmd("all"), big) == 0
        snap = fabric.accounting.snapshot()
        assert fabric.accounting.get("data", "dropped.oversize") == 1
        assert fabric.accounting.get("ctrl", "dropped.oversize") == 1
        assert fabric.accounting.get("data", "sent") == 1, snap
    finally:
        fabric.close()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _owner(arr: np.ndarray) -> object:
    """The object at the end of an array's ``base`` chain (through memoryviews)."""
    base: object = arr
    while isinstance(base, (np.ndarray, memoryview)):
        nxt = base.base if isinstance(base, np.ndarray) else base.obj
        if nxt is None:
            return base
        base = nxt
    return base


def test_received_chunk_arrays_are_aligned_views_of_the_received_bytes():
    # "rollout-a" with an identity block: 38 + 9 + 104 = 151 header bytes, so without the
    # envelope's padding the payload (and every array in it) would sit off 8-byte alignment.
    op = Identity.operator("zc")
    port = _free_port()
    secret = b"k" * 32
    rx = Fabric(run="zc", name="actor-0", identity=op.issue("actor", "actor-0"), secret=secret,
                ctrl_conf=plane_config(mode="peer", listen=(f"tcp/127.0.0.1:{_free_port()}",)),
                data_conf=plane_config(mode="peer", listen=(f"tcp/127.0.0.1:{port}",)))
    tx = Fabric(run="zc", name="rollout-a", identity=op.issue("rollout", "rollout-a"), secret=secret,
                ctrl_conf=plane_config(mode="peer", listen=(f"tcp/127.0.0.1:{_free_port()}",)),
                data_conf=plane_config(mode="peer", connect=(f"tcp/127.0.0.1:{port}",)))
    try:
        inbox = rx.subscribe_traj(8, TrajectoryChunk)
        got, deadline = None, time.monotonic() + 10
        while got is None and time.monotonic() < deadline:
            tx.publish_traj(_chunk("rollout-a", 3))
            got = inbox.get(timeout=0.5)
        assert got is not None, rx.accounting.snapshot()
        chunk = got[1] if isinstance(got, tuple) else got
        arrays = [chunk.actions, chunk.logprobs, chunk.rewards, chunk.terminated, chunk.truncated, chunk.success,
                  *chunk.obs.values(), *chunk.next_obs.values(), *chunk.final_obs.values()]
        received = _owner(arrays[0])
        assert isinstance(received, bytes)  # the received envelope, as Zenoh handed it over
        whole = np.frombuffer(received, np.uint8)
        for arr in arrays:
            assert not arr.flags.owndata and not arr.flags.writeable
            assert _owner(arr) is received and np.shares_memory(arr, whole)
            assert arr.flags.aligned and (arr.ctypes.data - whole.ctypes.data) % 8 == 0
        # Once the operator revokes the name, its chunks are refused and counted as foreign.
        rx.revoked.add("rollout-a")
        before = rx.accounting.get("data", "rejected.revoked", UNAUTHENTICATED)
        tx.publish_traj(_chunk("rollout-a", 3))
        deadline = time.monotonic() + 10  # the reader verifies: its get() refuses and counts it
        while rx.accounting.get("data", "rejected.revoked", UNAUTHENTICATED) == before and time.monotonic() < deadline:
            assert inbox.get(timeout=0.2) is None
        assert rx.accounting.get("data", "rejected.revoked", UNAUTHENTICATED) == before + 1
        assert inbox.get(timeout=0.2) is None
    finally:
        tx.close()
        rx.close()
