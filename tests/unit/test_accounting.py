"""dvla.fabric.accounting: per-message counters written from many threads must add up exactly."""

from __future__ import annotations

import threading

from dvla.fabric.accounting import Accounting

DATA = "data"


def test_counters_per_plane_and_peer() -> None:
    acct = Accounting()
    acct.sent(DATA, 100, "rollout-0")
    acct.received(DATA, 40, "rollout-1")
    acct.received(DATA, 60, "rollout-1")
    acct.rejected(DATA, "malformed", "rollout-1")
    acct.dropped(DATA, "stale", "rollout-0", n=3)
    assert acct.get(DATA, "sent") == 1 and acct.get(DATA, "sent_bytes") == 100
    assert acct.get(DATA, "received", "rollout-1") == 2 and acct.get(DATA, "received_bytes", "rollout-1") == 100
    assert acct.get(DATA, "received", "rollout-0") == 0
    assert acct.get(DATA, "rejected.malformed") == acct.get(DATA, "rejected") == 1
    assert acct.get(DATA, "dropped.stale", "rollout-0") == 3
    snap = acct.snapshot()
    assert snap[DATA]["received"] == 2 and snap[DATA]["peers"]["rollout-1"]["received_bytes"] == 100


def test_totals_are_exact_with_four_writers_and_a_reader() -> None:
    acct = Accounting()
    per_thread = 12_305
    start = threading.Barrier(5)
    seen: list[int] = []

    def write(i: int) -> None:
        start.wait()
        for _ in range(per_thread):
            acct.received(DATA, 2, f"peer-{i % 2}")
            acct.sent(DATA, 1, None)

    def read() -> None:
        start.wait()
        for _ in range(200):
            seen.append(acct.get(DATA, "received"))  # while the writers count

    threads = [threading.Thread(target=write, args=(i,), name=f"writer-{i}") for i in range(4)]
    threads.append(threading.Thread(target=read, name="reader"))
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    total = 4 * per_thread
    assert acct.get(DATA, "received") == total and acct.get(DATA, "received_bytes") == 2 * total
    assert acct.get(DATA, "received", "peer-0") == acct.get(DATA, "received", "peer-1") == total // 2
    assert acct.get(DATA, "sent") == total
    assert seen == sorted(seen) and seen[-1] <= total  # a reader never sees a count go back


def test_peers_are_bounded_and_totals_stay_exact() -> None:
    from dvla.fabric.accounting import OTHER_PEER
    from dvla.fabric.codec import encode
    from dvla.fabric.keys import check_name
    from dvla.fabric.messages import RoleStatus

    acct = Accounting(known_peers=["rollout-0"], max_other_peers=4)
    for i in range(100_000):  # 1-byte puts on as many distinct data/traj/<name> keys
        acct.received(DATA, 1, f"intruder-{i}")
    acct.received(DATA, 7, "rollout-0")
    acct.rejected(DATA, "malformed", "bad/name*")  # not a role name: aggregated at once
    snap = acct.snapshot()[DATA]
    assert snap["received"] == 100_001 and snap["received_bytes"] == 100_007
    peers = snap["peers"]
    assert set(peers) == {"rollout-0", OTHER_PEER, *(f"intruder-{i}" for i in range(4))}
    assert peers[OTHER_PEER]["received"] == 100_000 - 4 and peers[OTHER_PEER]["rejected.malformed"] == 1
    assert sum(c.get("received", 0) for c in peers.values()) == snap["received"]
    assert acct.get(DATA, "received", "intruder-99999") == 0 and acct.get(DATA, "received", "intruder-3") == 1
    acct.received(DATA, 3, "<unauthenticated>")  # the fabric's own aggregate keeps its key
    assert acct.get(DATA, "received", "<unauthenticated>") == 1
    # known peers keep counters of their own past the cap, added late too
    acct.add_known_peers(["rollout-1"])
    acct.received(DATA, 5, "rollout-1")
    assert acct.get(DATA, "received", "rollout-1") == 1 and acct.get(DATA, "received", "rollout-0") == 1
    # the aggregate can never be taken for a rollout (or any role) name
    try:
        check_name("role", OTHER_PEER)
        raise AssertionError(f"{OTHER_PEER!r} must not be a valid role name")
    except ValueError:
        pass
    # with the default cap, a status carrying the peers still encodes
    flood = Accounting()
    for i in range(70_000):
        flood.received(DATA, 1, f"p{i}")
    assert len(flood.snapshot()[DATA]["peers"]) == 65
    status = RoleStatus(name="actor-0", kind="actor", node="n", rack="r", pid=1, state="running",
                        policy_version=0, env_steps=0, steps_per_s=0.0, planes=flood.snapshot())
    assert encode(status)
