"""dvla.fabric.accounting: per-message counters written from many threads without a lock must
still add up exactly."""

from __future__ import annotations

import threading

from dvla.fabric.accounting import FOLD_AT, Accounting

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


def test_a_tally_counts_like_received() -> None:
    a, b = Accounting(), Accounting()
    count = a.tally(DATA, "received", "rollout-0")
    for size in (10, 20, 30):
        count(size)
        b.received(DATA, size, "rollout-0")
    assert a.snapshot() == b.snapshot()
    a.received(DATA, 5, "rollout-0")  # both paths feed one counter
    assert a.get(DATA, "received", "rollout-0") == 4 and a.get(DATA, "received_bytes") == 65


def test_pending_messages_are_folded_before_they_pile_up() -> None:
    acct = Accounting()
    count = acct.tally(DATA, "received", "p")
    for _ in range(FOLD_AT + 10):
        count(1)
    assert all(len(q) < FOLD_AT for q in acct._pending.values())
    assert acct.get(DATA, "received") == FOLD_AT + 10


def test_totals_are_exact_with_four_writers_and_a_reader() -> None:
    acct = Accounting()
    per_thread = 3 * FOLD_AT + 17
    start = threading.Barrier(5)
    seen: list[int] = []

    def write(i: int) -> None:
        count = acct.tally(DATA, "received", f"peer-{i % 2}")
        start.wait()
        for k in range(per_thread):
            if k % 2:
                count(2)
            else:
                acct.received(DATA, 2, f"peer-{i % 2}")
            acct.sent(DATA, 1, None)

    def read() -> None:
        start.wait()
        for _ in range(200):
            seen.append(acct.get(DATA, "received"))  # folds while the writers append

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
