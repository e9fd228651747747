"""The receive cap of `plane_config(max_message_size=...)` on real Zenoh sessions (loopback, peer
mode, explicit endpoints, no shared memory): a message above the cap is not delivered, messages
below it are, and the session survives the oversized one."""

from __future__ import annotations

import socket
import threading
import time
import uuid

import zenoh

from dvla.fabric.zconfig import plane_config

CAP = 256 << 10


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_message_above_the_cap_is_not_delivered_and_the_session_survives() -> None:
    port = free_port()
    rx = zenoh.open(plane_config(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], max_message_size=CAP))
    tx = zenoh.open(plane_config(mode="peer", connect=[f"tcp/127.0.0.1:{port}"]))
    try:
        key = f"cap/{uuid.uuid4().hex}"
        got: list[int] = []
        arrived = threading.Event()

        def on_sample(sample: zenoh.Sample) -> None:
            got.append(len(sample.payload.to_bytes()))
            arrived.set()

        sub = rx.declare_subscriber(key, on_sample)
        deadline = time.monotonic() + 10
        while not arrived.is_set():  # route established: the probe got through
            assert time.monotonic() < deadline, "no route between the two sessions"
            tx.put(key, b"p")
            arrived.wait(0.05)
        time.sleep(0.2)
        got.clear()
        for size in (CAP // 2, 4 * CAP, 64 * CAP, CAP - 4096, 10):  # BLOCK: the sender drops nothing
            tx.put(key, bytes(size), congestion_control=zenoh.CongestionControl.BLOCK)
        deadline = time.monotonic() + 10
        while 10 not in got and time.monotonic() < deadline:  # the last put: order is kept
            time.sleep(0.02)
        assert got == [CAP // 2, CAP - 4096, 10]
        sub.undeclare()
    finally:
        tx.close()
        rx.close()
