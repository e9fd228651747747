"""TokenQueue: the bounded FIFO under the fabric's inbox and the swimlane queues."""

from __future__ import annotations

import threading
import time

from dvla.fabric.tokenqueue import TokenQueue


def test_fifo_order_and_the_bound():
    q: TokenQueue[int] = TokenQueue(3)
    assert [q.put(i) for i in (1, 2, 3, 4)] == [True, True, True, False]  # the 4th finds no slot
    assert q.qsize() == 3
    assert [q.get(), q.get()] == [1, 2]
    assert q.put(5) and q.put(6) and not q.put(7)
    assert [q.get() for _ in range(4)] == [3, 5, 6, None]
    assert q.qsize() == 0


def test_waits_end_at_the_timeout_or_when_the_other_side_acts():
    q: TokenQueue[str] = TokenQueue(1)
    t0 = time.monotonic()
    assert q.get(timeout=0.05) is None and time.monotonic() - t0 >= 0.04
    assert q.put("a") and not q.put("b", timeout=0.05)
    threading.Timer(0.05, q.get).start()  # frees the slot while put waits
    assert q.put("c", timeout=2.0)
    assert q.get(timeout=2.0) == "c"
