"""The chunk ledger: where every trajectory chunk of a run went (result.json's ``accounting``).

    produced = consumed + dropped + rejected + lost, exactly (``unaccounted``: what no kill explains)

The roles count through it (:class:`RolloutLedger`, :class:`ActorLedger`), into counter files that
survive a ``kill -9`` (:class:`CounterFile`), and the orchestrator calls :func:`reconcile`. The
fabric, which imports nothing of dvla, keeps its own per-plane counters (``fabric/accounting.py``);
the actor copies their per-rollout drops and rejects into its file.

A counter file, ``RUN_DIR/counters/<role>.<incarnation>.<pid>``, is rewritten in place with one
``pwrite`` per event and no fsync (the kernel keeps the pages when the process dies). The n-th
file of a role is its n-th incarnation (they never overlap); a rollout puts it in the high bits of
each chunk's ``seq``. Remote roles send their files back when they exit (orchestrator/ssh.py).

Receipts: a stopping rollout asks its learner how far its chunks got
(:meth:`RolloutLedger.await_receipt`, answered by :meth:`ActorLedger.receipt`) and closes its data
session only once the learner has its last chunk, or records what was not confirmed in time.
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

from .fabric.accounting import Accounting
from .fabric.fabric import DATA, Fabric
from .fabric.messages import LedgerRecord, Receipt, ReceiptRequest

COUNTERS_DIR = "counters"
#: low bits of a chunk's seq count chunks within one incarnation; the high bits are the incarnation
INCARNATION_SHIFT = 32
#: bytes a killed sender's Zenoh may hold unsent: the data priority's tx queue (2 batches, Zenoh's
#: default) plus the batch being filled, of at most 64 KiB each
ZENOH_TX_BYTES = 3 * 65535
#: link breaks and gaps a counter file keeps positions of (more are counted, not placed)
MAX_EVENTS = 64
#: at most this long a stopping rollout waits for its learner to confirm its last chunk before it
#: closes its data session (`dvla up` gives a stopping rollout 15 s to exit), asking every
#: RECEIPT_POLL_S seconds
RECEIPT_WAIT_S = 10.0
RECEIPT_POLL_S = 0.1


def split_seq(seq: int) -> tuple[int, int]:
    """(incarnation, chunk index within it) of a chunk's seq."""
    return seq >> INCARNATION_SHIFT, seq & ((1 << INCARNATION_SHIFT) - 1)


def source_key(rollout: str, seq: int) -> str:
    """``<rollout>#<incarnation>``: one rollout incarnation, as counter files name it."""
    return f"{rollout}#{seq >> INCARNATION_SHIFT}"


class CounterFile:
    """The counters of this process, rewritten whole on every `write` (thread-safe)."""

    def __init__(self, run_dir: str | Path, role: str) -> None:
        folder = Path(run_dir) / COUNTERS_DIR
        folder.mkdir(parents=True, exist_ok=True)
        self.incarnation = len(list(folder.glob(f"{role}.*")))
        while True:  # O_EXCL: a leftover of the same number is never overwritten
            self.path = folder / f"{role}.{self.incarnation}.{os.getpid()}"
            try:
                self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
                break
            except FileExistsError:
                self.incarnation += 1
        self.role = role
        self.start_ns = time.time_ns()
        #: the record last written, as JSON text
        self.text = ""
        self._len = 0
        self._lock = threading.Lock()
        self._closed = False

    def write(self, doc: dict[str, Any]) -> None:
        record = {"role": self.role, "incarnation": self.incarnation, "pid": os.getpid(),
                  "start_ns": self.start_ns, "updated_ns": time.time_ns(), **doc}
        text = json.dumps(record, separators=(",", ":"))
        data = text.encode()
        with self._lock:
            if self._closed:
                return
            self.text = text
            data = data.ljust(self._len)
            self._len = len(data)
            os.pwrite(self._fd, data, 0)

    def close(self) -> None:
        with self._lock:
            if not self._closed:
                self._closed = True
                os.close(self._fd)


def read_counters(run_dir: str | Path) -> list[dict[str, Any]]:
    """Every counter record of a run (unreadable ones are reported with an ``error`` key)."""
    out = []
    for path in sorted((Path(run_dir) / COUNTERS_DIR).glob("*.*.*")):
        try:
            doc = json.loads(path.read_bytes().decode().strip() or "{}")
        except (OSError, ValueError) as err:
            doc = {"error": f"{path.name}: {err}"}
        doc["file"] = path.name
        out.append(doc)
    return out


# -- what the roles count -------------------------------------------------------------------------


class RolloutLedger:
    """A rollout incarnation's chunks: *produced* (handed to its ship lane), *shipped* (published)
    and the bytes shipped, in its counter file. ``queue_cap`` (chunks its ship queue holds) bounds
    what a kill can take with it. A *link break* (its trajectory publisher lost every subscriber
    after shipping something: the link to the actor, or the actor, went away) is recorded with
    the number of chunks shipped by then: what was still in the link's buffers at that moment
    went with it (:func:`reconcile` places the gap just before it). At a clean stop the rollout
    records how many of the last chunks it shipped its learner had not confirmed when it closed
    its link (*unconfirmed*, :meth:`set_unconfirmed`): those may be lost with the close."""

    def __init__(self, run_dir: str | Path, rollout: str, queue_cap: int) -> None:
        self.file = CounterFile(run_dir, rollout)
        #: the seq of this incarnation's first chunk (its incarnation in the high bits)
        self.first_seq = self.file.incarnation << INCARNATION_SHIFT
        self.queue_cap = queue_cap
        self.produced = self.shipped = self.bytes_shipped = 0
        #: shipped chunks the learner had not confirmed when the rollout closed, and how long it waited
        self.unconfirmed = 0
        self.confirm_wait_s = 0.0
        #: [shipped by then, time_ns] of each link break (the first MAX_EVENTS), and how many in all
        self.breaks: list[list[int]] = []
        self.breaks_total = 0
        self._last_break_at = 0
        self._lock = threading.Lock()
        self._write()

    def add_break(self) -> None:
        """The trajectory publisher lost its last subscriber (called from a Zenoh callback)."""
        with self._lock:
            if self.shipped == self._last_break_at:  # nothing shipped since the last one
                return
            self._last_break_at = self.shipped
            self.breaks_total += 1
            if len(self.breaks) < MAX_EVENTS:
                self.breaks.append([self.shipped, time.time_ns()])
        self._write()

    def add_produced(self) -> None:
        self.produced += 1
        self._write()

    def add_shipped(self, nbytes: int) -> None:
        self.shipped += 1
        self.bytes_shipped += nbytes
        self._write()

    @property
    def last_seq(self) -> int:
        """The seq of the last chunk shipped (chunks are shipped in seq order); first_seq - 1: none."""
        return self.first_seq + self.shipped - 1

    def await_receipt(self, fabric: Fabric, learners: tuple[str, ...] | list[str], wait_s: float = RECEIPT_WAIT_S,
                      poll_s: float = RECEIPT_POLL_S) -> "ReceiptWait":
        """Ask the learners (``ctrl/receipt/<learner>``) until one has the last chunk shipped, at
        most `wait_s`; record the chunks still unconfirmed then (``unconfirmed`` in the counter
        file, which :func:`reconcile` places as lost ``where: close`` if they never arrived).

        Why: ``put`` returns once Zenoh has queued a chunk, and with a learner that reads slowly
        (its inbox full) MBs of chunks then wait in the rollout's socket buffers. Closing the data
        session leaves them to a half-closed socket, and the kernel resets that connection, dropping
        them, as soon as the learner sends anything on it (its Zenoh keep-alive, every 2.5 s):
        docs/reliability.md, "Closing a rollout"."""
        last = self.last_seq
        t0 = time.monotonic()
        confirmed, queries, why = self.first_seq - 1, 0, "no learner to ask"
        if last >= self.first_seq and learners:  # else nothing shipped, or nobody to ask
            request = ReceiptRequest(rollout=self.file.role, seq=last)
            deadline = t0 + wait_s
            why = f"no confirmation within {wait_s:g} s"
            while True:
                if not fabric.traj_matched():  # no learner on the link: nothing more gets there
                    why = "no learner on the trajectory link"
                    break
                for learner in learners:
                    timeout = max(0.1, min(1.0, deadline - time.monotonic()))
                    try:
                        replies = fabric.query(fabric.keys.receipt(learner), request, expect=Receipt, timeout=timeout)
                    except Exception as err:  # the ctrl link is down: ask again until the deadline
                        why, replies = f"receipt query to {learner} failed: {err}", []
                    queries += 1
                    for sender, receipt in replies:
                        if sender == learner and receipt.rollout == self.file.role and receipt.seq <= last:
                            confirmed = max(confirmed, receipt.seq)
                if confirmed >= last or time.monotonic() + poll_s >= deadline:
                    break
                time.sleep(poll_s)
        self.unconfirmed = last - confirmed
        self.confirm_wait_s = time.monotonic() - t0
        self._write()
        return ReceiptWait(self.unconfirmed, self.confirm_wait_s, queries, "" if not self.unconfirmed else why)

    def _write(self, clean: bool = False) -> None:
        with self._lock:
            breaks = list(self.breaks)  # appended to by a Zenoh thread
        self.file.write({"kind": "rollout", "produced": self.produced, "shipped": self.shipped,
                         "bytes": self.bytes_shipped, "queue_cap": self.queue_cap, "breaks": breaks,
                         "breaks_total": self.breaks_total, "unconfirmed": self.unconfirmed,
                         "confirm_wait_s": round(self.confirm_wait_s, 3), "clean": clean})

    def close(self) -> None:
        self._write(clean=True)
        self.file.close()

    def record(self) -> LedgerRecord:
        """The record last written, as a message for the learner (``report_ledger``)."""
        return LedgerRecord(role=self.file.role, incarnation=self.file.incarnation, pid=os.getpid(),
                            record=self.file.text)


class ReceiptWait(NamedTuple):
    """What :meth:`RolloutLedger.await_receipt` found."""

    #: chunks shipped that no learner confirmed (0: it has them all)
    unconfirmed: int
    waited_s: float
    #: receipt queries sent
    queries: int
    #: why some are unconfirmed ("" when none is)
    why: str


class ActorLedger:
    """What an actor incarnation did with each rollout incarnation's chunks: *got* (out of the
    inbox), then exactly one of ``consumed``, ``dropped.<reason>`` or ``rejected.<reason>``; a
    chunk got but not settled is in a slot (or between lanes) and dies with the process.

    Every settlement is counted twice from here, in the counter file and in the fabric's data-plane
    counters (what status shows); the fabric's own per-rollout drops and rejects (backpressure,
    undecodable) are copied into the file, so :func:`reconcile` can close the books exactly."""

    def __init__(self, run_dir: str | Path, actor: str, accounting: Accounting, slots: int, inbox_cap: int) -> None:
        self.file = CounterFile(run_dir, actor)
        self.accounting = accounting
        self.bounds = {"slots": slots, "inbox_cap": inbox_cap}
        self._lock = threading.Lock()
        self._src: dict[str, dict[str, int]] = {}
        self._slot: dict[int, str] = {}
        #: per source, the newest chunk index the fabric dropped before the inbox (receipts only:
        #: the fabric counts those drops itself)
        self._fabric_dropped: dict[str, int] = {}
        self._last_tick = 0.0
        #: counter files this actor keeps for rollouts elsewhere (:meth:`adopt`)
        self._adopted: set[Path] = set()
        self._write()

    def got(self, rollout: str, seq: int) -> str:
        """A chunk out of the inbox; returns its source key for :meth:`settle` / :meth:`hold`."""
        src = source_key(rollout, seq)
        index = split_seq(seq)[1]
        with self._lock:
            c = self._src.setdefault(src, {"got": 0, "first": index, "last": index})
            if index > c["last"] + 1:  # chunks of one rollout arrive in order: a jump is a gap
                gaps = c.setdefault("gaps", [])
                if len(gaps) < MAX_EVENTS:
                    gaps.append([c["last"] + 1, index - 1])
            c["got"] += 1
            c["first"] = min(c["first"], index)
            c["last"] = max(c["last"], index)
        return src

    def settle(self, src: str, what: str) -> None:
        """One chunk of `src` is ``consumed``, ``dropped.<reason>`` or ``rejected.<reason>``."""
        self.accounting.add(DATA, what, src.rsplit("#", 1)[0])  # the plane's counters: what status shows
        with self._lock:
            c = self._src[src]
            c[what] = c.get(what, 0) + 1
        self._write()

    def fabric_dropped(self, rollout: str, seq: int) -> None:
        """The fabric dropped this chunk before the inbox (backpressure; it counts the drop): it
        left the link all the same (:meth:`newest`). Called on a Zenoh thread."""
        src, index = source_key(rollout, seq), split_seq(seq)[1]
        with self._lock:
            self._fabric_dropped[src] = max(index, self._fabric_dropped.get(src, -1))

    def receipt(self, req: ReceiptRequest) -> Receipt:
        """The answer to a stopping rollout's receipt query (served on ``ctrl/receipt/<actor>``, on
        Zenoh's thread: one look-up under the lock)."""
        return Receipt(rollout=req.rollout, seq=self.newest(req.rollout, req.seq))

    def newest(self, rollout: str, seq: int) -> int:
        """The seq of the newest chunk of the incarnation `seq` belongs to that came off the link
        (got, or dropped by the fabric before the inbox); -1: none (a stopping rollout asks)."""
        src = source_key(rollout, seq)
        with self._lock:
            c = self._src.get(src)
            index = max(-1 if c is None else c["last"], self._fabric_dropped.get(src, -1))
        return -1 if index < 0 else (split_seq(seq)[0] << INCARNATION_SHIFT) + index

    def hold(self, slot: int, src: str) -> None:
        """A chunk of `src` now lives in `slot` (settled by :meth:`release`)."""
        with self._lock:
            self._slot[slot] = src
        self._write()

    def release(self, slot: int, what: str) -> None:
        with self._lock:
            src = self._slot.pop(slot)
        self.settle(src, what)

    def tick(self) -> None:
        """Rewrite the file at most twice a second, so the fabric's own drops reach it too."""
        now = time.monotonic()
        if now - self._last_tick >= 0.5:
            self._last_tick = now
            self._write()

    def _write(self, clean: bool = False) -> None:
        with self._lock:  # snapshot and write together: a newer record is never overwritten by an older one
            peers = self.accounting.snapshot().get(DATA, {}).get("peers", {})
            fabric = {p: {"received": c.get("received", 0), "rejected": c.get("rejected", 0),
                          "backpressure": c.get("dropped.backpressure", 0)} for p, c in peers.items()}
            sources = {k: dict(v) for k, v in self._src.items()}
            self.file.write({"kind": "actor", "sources": sources, "fabric": fabric, **self.bounds, "clean": clean})

    def close(self, clean: bool = True) -> None:
        self._write(clean=clean)
        self.file.close()

    def adopt(self, msg: LedgerRecord) -> Path | None:
        """Keep a rollout's counter record (a verified :class:`LedgerRecord` from that rollout) in
        this run's counter directory, as ``<role>.<incarnation>.<pid>``, unless that rollout's own
        file of that incarnation is already there (a shared file system): None then. Newer
        records replace the copy whole (written aside, then renamed)."""
        folder = self.file.path.parent
        path = folder / f"{msg.role}.{msg.incarnation}.{msg.pid}"
        with self._lock:
            if path not in self._adopted:
                if any(folder.glob(f"{msg.role}.{msg.incarnation}.*")):
                    return None
                self._adopted.add(path)
        tmp = folder.parent / f".adopt-{path.name}.tmp"  # outside the counter directory: never read half-written
        tmp.write_text(msg.record)
        os.replace(tmp, path)
        return path


# -- reconciliation (the orchestrator, at the end of a run) ---------------------------------------


def reconcile(run_dir: str | Path) -> dict[str, Any]:
    """The run's accounting from every counter file in `run_dir` (result.json's ``accounting``)."""
    docs = read_counters(run_dir)
    rollouts = [d for d in docs if d.get("kind") == "rollout"]
    actors = [d for d in docs if d.get("kind") == "actor"]
    books = _Books(notes=[d["error"] for d in docs if "error" in d])  # unreadable: named, never skipped silently
    for a in actors:  # first: the rollouts' chunks are then looked for in what the actors received
        books.add_actor(a)
    by_name: dict[str, list[dict[str, Any]]] = {}
    for r in rollouts:
        by_name.setdefault(r["role"], []).append(r)
    shipped = sum(r.get("shipped", 0) for r in rollouts)
    # a rollout killed before it shipped anything: size its window with the run's mean chunk
    mean_bytes = sum(r.get("bytes", 0) for r in rollouts) / shipped if shipped else 1.0
    for name, incarnations in sorted(by_name.items()):
        books.add_rollout(name, incarnations, mean_bytes)
    for peer in books.fabric_drops.keys() | books.fabric_rejects.keys():
        if peer not in by_name:  # traffic under a name no rollout ever had
            books.foreign += books.fabric_drops[peer] + books.fabric_rejects[peer]
    for src in sorted(books.received.keys() - {f"{r['role']}#{r['incarnation']}" for r in rollouts}):
        books.note(0, f"chunks of {src} received, but it left no counter file")

    produced = sum(r.get("produced", 0) for r in rollouts)
    lost = sum(x["lost"] for x in books.lost)
    dropped = {k: v for k, v in books.dropped.items() if v}
    rejected = {k: v for k, v in books.rejected.items() if v}
    unaccounted = produced - books.consumed - sum(dropped.values()) - sum(rejected.values()) - lost
    if unaccounted != books.unaccounted:  # the two ways of counting must agree; say so if they do not
        books.notes.append(f"identity residual {unaccounted} != {books.unaccounted} chunks found missing or held")
    return {
        "produced": produced, "consumed": books.consumed,
        "dropped": sum(dropped.values()), "dropped_by_reason": dropped,
        "rejected": sum(rejected.values()), "rejected_by_reason": rejected,
        "lost": lost, "lost_by_incarnation": sorted(books.lost, key=lambda x: x["died_ns"]),
        "lost_within_bounds": all(0 <= x["lost"] <= x["lost_bound"] for x in books.lost),
        "foreign_rejected": books.foreign, "unaccounted": unaccounted, "notes": books.notes,
        "incarnations": {"rollout": len(rollouts), "actor": len(actors)},
    }


def _tcp_buffer_max(name: str) -> int:
    """The kernel's largest TCP buffer of one direction (net.ipv4.tcp_rmem / tcp_wmem, third field)."""
    try:
        return int(Path(f"/proc/sys/net/ipv4/{name}").read_text().split()[2])
    except (OSError, ValueError, IndexError):
        return 6 << 20


def _chunks_in(window_bytes: int, chunk_bytes: float) -> int:
    """Chunks a window of bytes can hold, a partial one included."""
    return -(-window_bytes // max(1, int(chunk_bytes))) + 1


@dataclass
class _Books:
    """Totals and findings while the counter files are read (actors first, then rollouts)."""

    consumed: int = 0
    #: reason -> chunks
    dropped: Counter[str] = field(default_factory=Counter)
    rejected: Counter[str] = field(default_factory=Counter)
    #: one entry per killed incarnation (result.json's lost_by_incarnation)
    lost: list[dict[str, Any]] = field(default_factory=list)
    #: (actor, incarnation) -> its entry in `lost`
    killed_actors: dict[tuple[str, int], dict[str, Any]] = field(default_factory=dict)
    #: "<rollout>#<incarnation>" -> (first, last, got, (actor, incarnation), gaps) per actor
    #: incarnation that received of it (a rollout feeds one rank, but every rank has an incarnation 0)
    received: dict[str, list[tuple[int, int, int, tuple[str, int], list[list[int]]]]] = field(default_factory=dict)
    #: rollout name -> chunks the actors' fabric dropped under backpressure / could not decode
    fabric_drops: Counter[str] = field(default_factory=Counter)
    fabric_rejects: Counter[str] = field(default_factory=Counter)
    #: rejected chunks no rollout produced (forged, or another run's)
    foreign: int = 0
    #: chunks found missing (or held at a clean exit) that no kill explains, each with a note
    unaccounted: int = 0
    notes: list[str] = field(default_factory=list)
    #: bytes in flight on a link to a killed actor: the sender's Zenoh queue and both TCP buffers
    window: int = field(default_factory=lambda: ZENOH_TX_BYTES + _tcp_buffer_max("tcp_wmem") + _tcp_buffer_max("tcp_rmem"))

    def note(self, unaccounted: int, text: str) -> None:
        self.unaccounted += unaccounted
        self.notes.append(text)

    def add_actor(self, a: dict[str, Any]) -> None:
        held = 0  # received but never settled (consumed, dropped or rejected)
        own_rejects: Counter[str] = Counter()
        for src, c in a.get("sources", {}).items():
            self.received.setdefault(src, []).append(
                (c["first"], c["last"], c["got"], (a["role"], a["incarnation"]), c.get("gaps", [])))
            held += c["got"]
            for key, n in c.items():
                kind, _, reason = key.partition(".")
                if key == "consumed":
                    self.consumed += n
                elif kind == "dropped" and reason:
                    self.dropped[reason] += n
                elif kind == "rejected" and reason:
                    self.rejected[reason] += n
                    own_rejects[src.rsplit("#", 1)[0]] += n
                else:
                    continue
                held -= n
        for peer, f in a.get("fabric", {}).items():
            self.fabric_drops[peer] += f.get("backpressure", 0)
            # the actor's own rejections (counted above) are in the fabric's count too
            self.fabric_rejects[peer] += f.get("rejected", 0) - own_rejects[peer]
        if a.get("clean"):
            if held:
                self.note(held, f"{a['file']}: {held} chunks held at a clean exit")
            return
        entry = {"role": a["role"], "incarnation": a["incarnation"], "pid": a["pid"], "where": "actor",
                 "died_ns": a["updated_ns"], "lost": held, "in_actor": held, "in_transit": 0,
                 "lost_bound": a["slots"] + 2 + a["inbox_cap"]}
        self.killed_actors[(a["role"], a["incarnation"])] = entry
        self.lost.append(entry)

    def add_rollout(self, name: str, incarnations: list[dict[str, Any]], mean_bytes: float) -> None:
        """Place the missing chunks of every incarnation of one rollout: inside an actor's received
        range (the fabric dropped them or could not decode them), between two actor incarnations
        (died with the first), or after the last one received (died with the rollout, or with the
        actor at the end)."""
        ranges = {r["incarnation"]: sorted(self.received.get(f"{name}#{r['incarnation']}", [])) for r in incarnations}
        inner = {i: sum(last - first + 1 - got for first, last, got, *_ in rs) for i, rs in ranges.items()}
        tails = {r["incarnation"]: r.get("produced", 0) - 1 - ranges[r["incarnation"]][-1][1]
                 if ranges[r["incarnation"]] else r.get("produced", 0) for r in incarnations}
        # The fabric's drops and rejects of this rollout explain chunks missing inside ranges, and
        # at the end of a clean incarnation (its last chunks, dropped before the actor got them);
        # rejects beyond those were never produced by it: forged.
        inner_gaps = sum(max(0, n) for n in inner.values())
        gaps = inner_gaps + sum(max(0, tails[r["incarnation"]]) for r in incarnations if r.get("clean"))
        drops = min(self.fabric_drops[name], gaps)
        rejects = min(self.fabric_rejects[name], gaps - drops)
        self.dropped["backpressure"] += drops
        self.rejected["undecodable"] += rejects
        self.foreign += self.fabric_drops[name] + self.fabric_rejects[name] - drops - rejects
        explained = min(drops + rejects, inner_gaps)  # inside the ranges first, then the tails
        explained_tails = drops + rejects - explained
        for r in incarnations:
            rs, left = ranges[r["incarnation"]], inner[r["incarnation"]]
            take = max(0, min(explained, left))
            explained -= take
            chunk_bytes = r.get("bytes", 0) / r["shipped"] if r.get("shipped") else mean_bytes
            left -= take + self._place_breaks(name, r, rs, left - take, chunk_bytes)
            if left:
                self.note(left, f"{r['file']}: {left} chunks missing mid-stream")
            # chunks before the first receipt went missing in the absence of an actor: count them
            # with the first actor incarnation's predecessor (the one that died)
            between = [((rs[0][3][0], rs[0][3][1] - 1), rs[0][0])] if rs and rs[0][0] else []
            between += [(a[3], b[0] - a[1] - 1) for a, b in zip(rs, rs[1:])]
            for actor, n in between:
                killed = self.killed_actors.get(actor)
                if n and killed is not None:
                    killed["lost"] += n
                    killed["in_transit"] += n
                    killed["lost_bound"] += _chunks_in(self.window, chunk_bytes)
                elif n:
                    self.note(n, f"{r['file']}: {n} chunks missing across a clean actor restart")
            tail = tails[r["incarnation"]]
            if r.get("clean"):  # its last chunks may be among the fabric's drops too
                take = max(0, min(explained_tails, tail))
                explained_tails -= take
                tail -= take
            self._place_tail(name, r, tail, rs[-1][3] if rs else None, chunk_bytes)

    def _place_breaks(self, name: str, r: dict[str, Any], rs: list[tuple[Any, ...]], missing: int,
                      chunk_bytes: float) -> int:
        """Of `missing` chunks inside the actors' received ranges that the fabric's counts do not
        explain, those in a gap that ends where one of the incarnation's link breaks happened
        (within the chunks a link's buffers hold: the sender's Zenoh queue and both TCP buffers)
        went down with that link: one ``where: link`` entry in ``lost``. Returns how many."""
        breaks = r.get("breaks", [])
        if not missing or not breaks:
            return 0
        bound = _chunks_in(self.window, chunk_bytes)
        near, placed = 0, set()
        for *_, gaps in rs:
            for a, b in gaps:
                for i, (shipped, _t) in enumerate(breaks):
                    # the break was seen after chunk `shipped - 1` was published (the one whose put
                    # it interrupted may be counted either side): the gap ends there, within `bound`
                    if b <= shipped and a >= shipped - bound:
                        near += b - a + 1
                        placed.add(i)
                        break
        lost = min(missing, near)
        if lost:
            self.lost.append({"role": name, "incarnation": r["incarnation"], "pid": r["pid"], "where": "link",
                              "died_ns": breaks[min(placed)][1], "lost": lost, "in_transit": lost,
                              "breaks": r.get("breaks_total", len(breaks)), "lost_bound": bound * len(placed)})
        return lost

    def _place_tail(self, name: str, r: dict[str, Any], tail: int, last_actor: tuple[str, int] | None,
                    chunk_bytes: float) -> None:
        """The `tail` chunks after the last one received (by `last_actor`): lost with a killed
        rollout, or with an actor killed at (about) the time this incarnation ended, else unaccounted."""
        if not r.get("clean"):
            in_queue = r.get("produced", 0) - r.get("shipped", 0)
            self.lost.append({"role": name, "incarnation": r["incarnation"], "pid": r["pid"], "where": "rollout",
                              "died_ns": r["updated_ns"], "lost": tail, "in_queue": in_queue,
                              "in_transit": tail - in_queue,
                              "lost_bound": r.get("queue_cap", 0) + 1 + _chunks_in(ZENOH_TX_BYTES, chunk_bytes)})
            return
        killed = self.killed_actors.get(last_actor) if last_actor is not None else None
        if tail and killed is not None and killed["died_ns"] >= r["updated_ns"] - 10**9:
            killed["lost"] += tail
            killed["in_transit"] += tail
            return
        # the rollout closed its link with its last chunks not confirmed by the learner (it waited
        # for them, bounded): what was still in the link's buffers then went down with it
        unconfirmed = r.get("unconfirmed", 0)
        closed = min(tail, unconfirmed)
        if closed:
            self.lost.append({"role": name, "incarnation": r["incarnation"], "pid": r["pid"], "where": "close",
                              "died_ns": r["updated_ns"], "lost": closed, "in_transit": closed,
                              "lost_bound": unconfirmed})
        if tail - closed:
            self.note(tail - closed, f"{r['file']}: {tail - closed} chunks missing at the end of a clean incarnation")
