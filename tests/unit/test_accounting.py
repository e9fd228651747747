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
