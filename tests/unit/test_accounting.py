"""The chunk ledger (dvla/ledger.py) as the roles keep it, and its input, the fabric's per-plane
counters (dvla/fabric/accounting.py): counts written from many threads add up exactly, and what a
rollout and an actor record reconciles to ``produced = consumed + dropped + rejected + lost``
with nothing unaccounted."""

from __future__ import annotations

import json
import os
import threading
import time

from pathlib import Path

import pytest

from dvla import ledger as ledger_module
from dvla.fabric.accounting import UNAUTHENTICATED, Accounting
from dvla.ledger import INCARNATION_SHIFT, ActorLedger, RolloutLedger, _Books, reconcile

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
    acct.add(DATA, "dropped.shutdown", "rollout-0")  # a reason's counter counts its total in the same step
    assert acct.get(DATA, "dropped", "rollout-0") == acct.get(DATA, "dropped") == 4
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


def _ship(run: Path, name: str, chunks: int, nbytes: int = 1000) -> RolloutLedger:
    """A rollout incarnation that produced and shipped `chunks`, then exited cleanly."""
    r = RolloutLedger(run, name, queue_cap=8)
    for _ in range(chunks):
        r.add_produced()
        r.add_shipped(nbytes)
    r.close()
    return r


def test_what_the_roles_record_closes_the_books_exactly(tmp_path: Path) -> None:
    acct = Accounting(known_peers=["rollout-a"])
    r = _ship(tmp_path, "rollout-a", 12)
    a = ActorLedger(tmp_path, "actor-0", acct, slots=4, inbox_cap=64)
    fates = ["consumed"] * 6 + ["dropped.stale"] * 2 + ["rejected.nonfinite", "dropped.shutdown", "fabric"] + ["consumed"]
    for i, fate in enumerate(fates):
        seq = r.first_seq + i
        acct.received(DATA, 1000, "rollout-a")
        if fate == "fabric":  # the inbox was full: the fabric dropped it, the actor never got it
            acct.dropped(DATA, "backpressure", "rollout-a")
            continue
        src = a.got("rollout-a", seq)
        if fate == "consumed":  # through a slot, as ingest and batch do
            a.hold(i % 4, src)
            a.release(i % 4, fate)
        else:
            a.settle(src, fate)
    for _ in range(3):  # another run's chunks on this run's key: refused by the envelope check
        acct.received(DATA, 1000, UNAUTHENTICATED)
        acct.rejected(DATA, "key_id", UNAUTHENTICATED)
    a.close()
    books = reconcile(tmp_path)
    assert {k: books[k] for k in ("produced", "consumed", "dropped", "rejected", "lost", "unaccounted")} == {
        "produced": 12, "consumed": 7, "dropped": 4, "rejected": 1, "lost": 0, "unaccounted": 0}
    assert books["dropped_by_reason"] == {"stale": 2, "shutdown": 1, "backpressure": 1}
    assert books["rejected_by_reason"] == {"nonfinite": 1}
    assert books["foreign_rejected"] == 3 and books["notes"] == []
    assert books["incarnations"] == {"rollout": 1, "actor": 1}
    # every settlement reached the plane counters status shows, under the rollout's name
    assert (acct.get(DATA, "consumed", "rollout-a"), acct.get(DATA, "dropped.stale", "rollout-a"),
            acct.get(DATA, "rejected.nonfinite", "rollout-a"), acct.get(DATA, "dropped", "rollout-a")) == (7, 2, 1, 4)


def test_a_killed_actor_takes_its_slots_and_the_next_incarnation_numbers_on(tmp_path: Path) -> None:
    acct = Accounting()
    r = _ship(tmp_path, "rollout-a", 10)
    a = ActorLedger(tmp_path, "actor-0", acct, slots=4, inbox_cap=64)
    for i in range(10):
        src = a.got("rollout-a", r.first_seq + i)
        a.hold(i % 4, src)
        if i < 7:
            a.release(i % 4, "consumed")
    # killed with three chunks in its slots: no close(), the file keeps its last record
    r2 = RolloutLedger(tmp_path, "rollout-a", queue_cap=8)  # the rollout restarted, shipping nothing yet
    assert r2.first_seq == 1 << INCARNATION_SHIFT  # the second incarnation, in seq's high bits
    r2.close()
    books = reconcile(tmp_path)
    (lost,) = books["lost_by_incarnation"]
    assert (lost["role"], lost["where"], lost["lost"], lost["in_actor"], lost["lost_bound"]) == ("actor-0", "actor", 3, 3, 4 + 2 + 64)
    assert books["produced"] == 10 == books["consumed"] + books["lost"] and books["unaccounted"] == 0
    assert books["lost_within_bounds"]


def test_a_chunk_held_at_a_clean_exit_is_unaccounted_and_named(tmp_path: Path) -> None:
    r = _ship(tmp_path, "rollout-a", 2)
    a = ActorLedger(tmp_path, "actor-0", Accounting(), slots=4, inbox_cap=64)
    a.settle(a.got("rollout-a", r.first_seq), "consumed")
    a.hold(0, a.got("rollout-a", r.first_seq + 1))  # never released, yet the actor exits cleanly
    a.close()
    books = reconcile(tmp_path)
    assert books["unaccounted"] == 1 and books["notes"] == ["actor-0.0.%d: 1 chunks held at a clean exit" % os.getpid()]


def _clean_tail_run(tmp_path: Path, unconfirmed: int, fabric_dropped: int = 0) -> dict:
    """A rollout that shipped 10 chunks and stopped cleanly with `unconfirmed` of them not
    confirmed by its learner; the actor got the first 7, and its fabric dropped the next
    `fabric_dropped` (backpressure) before its inbox."""
    acct = Accounting(known_peers=["rollout-a"])
    r = RolloutLedger(tmp_path, "rollout-a", queue_cap=8)
    for _ in range(10):
        r.add_produced()
        r.add_shipped(1000)
    r.unconfirmed = unconfirmed  # as await_receipt records it
    r.close()
    a = ActorLedger(tmp_path, "actor-0", acct, slots=4, inbox_cap=64)
    for i in range(7):
        a.settle(a.got("rollout-a", r.first_seq + i), "consumed")
    for i in range(7, 7 + fabric_dropped):
        acct.received(DATA, 1000, "rollout-a")
        acct.dropped(DATA, "backpressure", "rollout-a")
        a.fabric_dropped("rollout-a", r.first_seq + i)
    a.close()
    return reconcile(tmp_path)


def test_a_clean_rollout_s_unconfirmed_tail_is_lost_with_its_close(tmp_path: Path) -> None:
    books = _clean_tail_run(tmp_path / "a", unconfirmed=3)
    (lost,) = books["lost_by_incarnation"]
    assert (lost["role"], lost["where"], lost["lost"], lost["in_transit"], lost["lost_bound"]) == (
        "rollout-a", "close", 3, 3, 3)
    assert books["produced"] == 10 == books["consumed"] + books["lost"]
    assert books["unaccounted"] == 0 and books["notes"] == [] and books["lost_within_bounds"]
    # the learner confirmed all but 2: the third missing chunk no record explains
    books = _clean_tail_run(tmp_path / "b", unconfirmed=2)
    assert books["lost"] == 2 and books["unaccounted"] == 1
    assert books["notes"] == [f"rollout-a.0.{os.getpid()}: 1 chunks missing at the end of a clean incarnation"]
    # confirmed, yet missing: unaccounted, as before
    books = _clean_tail_run(tmp_path / "c", unconfirmed=0)
    assert books["lost"] == 0 and books["unaccounted"] == 3


def test_the_last_chunks_dropped_by_the_actor_s_fabric_are_its_drops_not_foreign(tmp_path: Path) -> None:
    books = _clean_tail_run(tmp_path, unconfirmed=0, fabric_dropped=3)
    assert (books["dropped"], books["dropped_by_reason"], books["foreign_rejected"]) == (3, {"backpressure": 3}, 0)
    assert books["unaccounted"] == 0 and books["lost"] == 0 and books["notes"] == []


def test_receipts_say_how_far_a_rollout_incarnation_s_chunks_got(tmp_path: Path) -> None:
    from dvla.fabric.messages import ReceiptRequest

    r = RolloutLedger(tmp_path, "rollout-a", queue_cap=8)
    assert r.last_seq == r.first_seq - 1  # nothing shipped
    for _ in range(5):
        r.add_shipped(1000)
    assert r.last_seq == r.first_seq + 4
    a = ActorLedger(tmp_path, "actor-0", Accounting(), slots=4, inbox_cap=64)
    ask = ReceiptRequest(rollout="rollout-a", seq=r.last_seq)
    assert a.receipt(ask).seq == -1  # nothing got yet
    for i in range(3):
        a.settle(a.got("rollout-a", r.first_seq + i), "consumed")
    assert a.receipt(ask).seq == r.first_seq + 2
    a.fabric_dropped("rollout-a", r.first_seq + 4)  # dropped before the inbox: it left the link all the same
    assert a.receipt(ask).seq == r.last_seq and a.receipt(ask).rollout == "rollout-a"
    later = 1 << INCARNATION_SHIFT  # another incarnation of the same name: its own count
    assert a.newest("rollout-a", later + 9) == -1
    a.settle(a.got("rollout-a", later + 2), "consumed")
    assert a.newest("rollout-a", later + 9) == later + 2 and a.newest("rollout-a", r.last_seq) == r.last_seq
    assert a.newest("rollout-b", 0) == -1
    r.close()
    a.close()


class _Learner:
    """Stands in for a rollout's fabric: a learner that has got chunks up to `seq` (-1: none)."""

    def __init__(self, seq: int, matched: bool = True) -> None:
        from dvla.fabric.keys import KeySpace

        self.keys, self.seq, self.matched, self.asked = KeySpace("run"), seq, matched, []

    def traj_matched(self) -> bool:
        return self.matched

    def query(self, key: str, request, *, expect, timeout: float):
        from dvla.fabric.messages import Receipt

        self.asked.append((key, request.rollout, request.seq))
        return [("actor-0", Receipt(rollout=request.rollout, seq=self.seq))]


class _Clock:
    """dvla.ledger's `time` with a monotonic clock that only its sleeps move (the rest is the real module)."""

    def __init__(self) -> None:
        self.t, self.slept = 100.0, []

    def monotonic(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        self.slept.append(seconds)
        self.t += seconds

    def __getattr__(self, name: str):
        return getattr(time, name)


def test_a_stopping_rollout_waits_for_its_learner_and_records_what_it_did_not_confirm(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    r = RolloutLedger(tmp_path, "rollout-a", queue_cap=8)
    idle = _Learner(-1)
    assert r.await_receipt(idle, ["actor-0"]) == (0, r.confirm_wait_s, 0, "") and idle.asked == []  # nothing shipped
    for _ in range(5):
        r.add_shipped(1000)
    done = _Learner(r.last_seq)
    wait = r.await_receipt(done, ["actor-0"])
    assert (wait.unconfirmed, wait.queries, wait.why) == (0, 1, "")
    assert done.asked == [("dvla/run/ctrl/receipt/actor-0", "rollout-a", r.first_seq + 4)]
    behind = _Learner(r.first_seq + 2)  # it has the first three, and never more
    clock = _Clock()
    monkeypatch.setattr(ledger_module, "time", clock)  # time passes only in the polls' sleeps
    wait = r.await_receipt(behind, ["actor-0"], wait_s=0.3, poll_s=0.04)
    # it asks, and polls again, until one more poll would end past the 0.3 s: 7 polls, 8 queries
    assert wait.unconfirmed == 2 and wait.queries == 8 and clock.slept == [0.04] * 7
    assert wait.waited_s == pytest.approx(0.28)  # what the clock moved from its start to its end
    assert wait.why == "no confirmation within 0.3 s"
    gone = _Learner(-1, matched=False)  # the learner left the link: no query, nothing confirmed
    assert r.await_receipt(gone, ["actor-0"])[::2] == (5, 0) and gone.asked == []
    assert r.await_receipt(done, [])[0] == 5  # nobody to ask
    r.unconfirmed = 2
    r.close()
    record = json.loads(next((tmp_path / "counters").iterdir()).read_bytes())
    # the last wait's seconds, as measured (on the injected clock, which did not move in it)
    assert (record["unconfirmed"], record["clean"]) == (2, True) and record["confirm_wait_s"] == round(r.confirm_wait_s, 3) == 0.0


def test_an_empty_run_has_empty_books(tmp_path: Path) -> None:
    books = reconcile(tmp_path)
    assert (books["produced"], books["unaccounted"], books["incarnations"]) == (0, 0, {"rollout": 0, "actor": 0})


def _robot_run(tmp_path: Path, gap: tuple[int, int], break_at: int | None, chunks: int = 400) -> dict:
    """A rollout that shipped `chunks` (1000 bytes each) and saw a link break after `break_at`
    of them; the actor got all but the chunk indices in `gap` (inclusive)."""
    r = RolloutLedger(tmp_path, "robot-1", queue_cap=8)
    a = ActorLedger(tmp_path, "actor-0", Accounting(), slots=4, inbox_cap=64)
    for i in range(chunks):
        r.add_produced()
        r.add_shipped(1000)
        if r.shipped == break_at:
            r.add_break()
            r.add_break()  # a second notice with nothing shipped in between is the same break
        if not gap[0] <= i <= gap[1]:
            a.settle(a.got("robot-1", r.first_seq + i), "consumed")
    r.close()
    a.close()
    return reconcile(tmp_path)


def test_chunks_missing_just_before_a_link_break_are_lost_with_the_link(tmp_path: Path) -> None:
    books = _robot_run(tmp_path, (250, 299), break_at=300)
    (lost,) = books["lost_by_incarnation"]
    assert (lost["role"], lost["where"], lost["lost"], lost["in_transit"], lost["breaks"]) == ("robot-1", "link", 50, 50, 1)
    assert books["unaccounted"] == 0 and books["notes"] == [] and books["lost_within_bounds"]
    assert books["produced"] == 400 == books["consumed"] + books["lost"]


def test_a_gap_no_link_break_explains_stays_unaccounted(tmp_path: Path) -> None:
    # no break at all; then a break, but the gap ends long before it (more than one window's
    # worth of chunks: no link's buffers held those)
    books = _robot_run(tmp_path / "a", (100, 109), break_at=None)
    assert books["unaccounted"] == 10 and books["lost"] == 0 and "missing mid-stream" in books["notes"][0]
    window = _Books().window // 1000 + 1  # chunks of 1000 bytes this host's link buffers hold
    books = _robot_run(tmp_path / "b", (100, 109), break_at=112 + window, chunks=120 + window)
    assert books["unaccounted"] == 10 and books["lost"] == 0
    # a gap after the break was not in the link when it broke
    books = _robot_run(tmp_path / "c", (300, 309), break_at=200)
    assert books["unaccounted"] == 10 and books["lost"] == 0


def test_the_learner_keeps_the_counter_record_of_a_rollout_elsewhere(tmp_path: Path) -> None:
    run, robot_machine = tmp_path / "run", tmp_path / "robot"
    r = _ship(robot_machine, "robot-1", 6)  # its counter file is on its own machine
    a = ActorLedger(run, "actor-0", Accounting(), slots=4, inbox_cap=64)
    for i in range(6):
        a.settle(a.got("robot-1", r.first_seq + i), "consumed")
    a.close()
    assert "no counter file" in reconcile(run)["notes"][0]  # before: consumed with no producer
    path = a.adopt(r.record())
    assert path == run / "counters" / f"robot-1.0.{os.getpid()}" and json.loads(path.read_text())["clean"]
    books = reconcile(run)
    assert (books["produced"], books["consumed"], books["unaccounted"], books["notes"]) == (6, 6, 0, [])
    assert not list(run.glob(".adopt-*"))  # written aside, renamed into place
    # on a shared file system the rollout's own file is there: nothing is written over it
    own = RolloutLedger(run, "rollout-b", queue_cap=8)
    assert a.adopt(own.record()) is None
    own.close()
