"""`dvla bench fabric`'s throughput rounds end on what arrived: all of it, or, once the publisher
is done, whatever came before the subscriber went idle (the rest is reported lost)."""

from __future__ import annotations

import threading

from benchmarks.fabric import Arrivals


def test_a_round_ends_as_soon_as_every_chunk_sent_has_arrived() -> None:
    arrivals = Arrivals()
    for _ in range(3):
        arrivals.add()
    result: list[tuple[int, float]] = []
    waiter = threading.Thread(target=lambda: result.append(arrivals.wait_for(3, idle_s=3600.0)), daemon=True)
    waiter.start()
    waiter.join(timeout=30)
    assert not waiter.is_alive(), "the round waited for the idle bound though every chunk had arrived"
    got, last = result[0]
    assert got == 3 and last == arrivals.last  # when the last chunk came, as recorded


def test_a_lost_chunk_ends_the_round_after_the_idle_bound_instead_of_stalling() -> None:
    arrivals = Arrivals()
    arrivals.add()
    arrivals.add()
    got, _last = arrivals.wait_for(3, idle_s=0.2)  # one of three never comes
    assert got == 2


def test_chunks_arriving_while_waiting_are_all_counted() -> None:
    arrivals = Arrivals()
    feeder = threading.Thread(target=lambda: [arrivals.add() for _ in range(500)])
    feeder.start()
    got, _last = arrivals.wait_for(500, idle_s=60.0)
    feeder.join()
    assert got == 500
