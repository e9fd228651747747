"""Where every trajectory chunk of a finished run went: result.json's ``accounting``.

``produced = consumed + dropped + rejected + lost + unaccounted``, exactly.

When every role ran on this host, the counter files each rollout and actor incarnation leaves
even when killed (dvla/counters.py) are complete, and the accounting holds across kills: ``lost``
lists, per killed incarnation, the chunks that died with it and the bound its in-flight window
puts on them. For a rollout that is its ship queue (+ the chunk being shipped) and what its Zenoh
had not sent yet; for the actor, its slots and inbox, plus what was in the live rollouts' Zenoh
queues and the TCP buffers of their links when it died. A missing chunk no kill explains is
``unaccounted``. Remote roles write their counter files on their own hosts, so a run with remote
nodes is accounted from the roles' clean-exit summaries instead (no ``lost`` there).
"""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

from ..counters import read_counters

#: bytes a killed sender's Zenoh may hold unsent: the data priority's tx queue (2 batches, Zenoh's
#: default) plus the batch being filled, of at most 64 KiB each
ZENOH_TX_BYTES = 3 * 65535


def run_accounting(run_dir: Path, counters_complete: bool) -> dict[str, Any]:
    """From the counter files when they are all in `run_dir`, else from the summaries."""
    acct = accounting_from_counters(run_dir) if counters_complete else None
    return acct if acct is not None else accounting_from_summaries(run_dir)


def accounting_from_summaries(run_dir: Path) -> dict[str, Any]:
    """produced = consumed + dropped + rejected + unaccounted, from the roles' final summaries."""
    produced = consumed = dropped = rejected = 0
    for path in sorted((run_dir / "summaries").glob("*.json")):
        doc = json.loads(path.read_text())
        if doc["kind"] == "rollout":
            produced += int(doc["extra"].get("chunks_produced", 0))
        elif doc["kind"] == "actor":
            data = doc["planes"].get("data", {})
            consumed += int(data.get("consumed", 0))
            dropped += int(data.get("dropped", 0))
            rejected += int(data.get("rejected", 0))
    return {"produced": produced, "consumed": consumed, "dropped": dropped, "rejected": rejected,
            "unaccounted": produced - consumed - dropped - rejected}


def accounting_from_counters(run_dir: Path) -> dict[str, Any] | None:
    """The exact accounting across kills, from the counter files (None without any)."""
    docs = read_counters(run_dir)
    rollouts = [d for d in docs if d.get("kind") == "rollout"]
    actors = [d for d in docs if d.get("kind") == "actor"]
    if not rollouts and not actors:
        return None
    ledger = _Ledger()
    for a in actors:  # first: the rollouts' chunks are then looked for in what the actors received
        ledger.add_actor(a)
    by_name: dict[str, list[dict[str, Any]]] = {}
    for r in rollouts:
        by_name.setdefault(r["role"], []).append(r)
    shipped = sum(r.get("shipped", 0) for r in rollouts)
    # a rollout killed before it shipped anything: size its window with the run's mean chunk
    mean_bytes = sum(r.get("bytes", 0) for r in rollouts) / shipped if shipped else 1.0
    for name, incarnations in sorted(by_name.items()):
        ledger.add_rollout(name, incarnations, mean_bytes)
    for peer in ledger.fabric_drops.keys() | ledger.fabric_rejects.keys():
        if peer not in by_name:  # traffic under a name no rollout ever had
            ledger.foreign += ledger.fabric_drops[peer] + ledger.fabric_rejects[peer]

    produced = sum(r.get("produced", 0) for r in rollouts)
    lost = sum(x["lost"] for x in ledger.lost)
    dropped = {k: v for k, v in ledger.dropped.items() if v}
    rejected = {k: v for k, v in ledger.rejected.items() if v}
    unaccounted = produced - ledger.consumed - sum(dropped.values()) - sum(rejected.values()) - lost
    if unaccounted != ledger.unaccounted:  # the two ways of counting must agree; say so if they do not
        ledger.notes.append(f"identity residual {unaccounted} != {ledger.unaccounted} chunks found missing or held")
    return {
        "produced": produced,
        "consumed": ledger.consumed,
        "dropped": sum(dropped.values()),
        "dropped_by_reason": dropped,
        "rejected": sum(rejected.values()),
        "rejected_by_reason": rejected,
        "lost": lost,
        "lost_by_incarnation": sorted(ledger.lost, key=lambda x: x["died_ns"]),
        "lost_within_bounds": all(0 <= x["lost"] <= x["lost_bound"] for x in ledger.lost),
        "foreign_rejected": ledger.foreign,
        "unaccounted": unaccounted,
        "notes": ledger.notes,
        "incarnations": {"rollout": len(rollouts), "actor": len(actors)},
    }


class _Received(NamedTuple):
    """What one actor incarnation received of one rollout incarnation (seqs within it)."""

    #: (actor role, incarnation): a rollout feeds one rank, but several actors have incarnation 0
    actor: tuple[str, int]
    first: int
    last: int
    got: int


@dataclass
class _Missing:
    """A rollout incarnation's chunks that no actor received, by where they went missing."""

    #: inside an actor's received range: the fabric dropped them or could not decode them
    inner: int
    #: ((actor, incarnation), chunks) missing between two actor incarnations: died with the first
    between: list[tuple[tuple[str, int], int]]
    #: after the last chunk received: died with the rollout, or with the actor at the end
    tail: int
    #: the actor incarnation that received the last chunk (None: none received any)
    last_actor: tuple[str, int] | None


def _missing(produced: int, received: list[_Received]) -> _Missing:
    if not received:
        return _Missing(inner=0, between=[], tail=produced, last_actor=None)
    received = sorted(received)
    inner = sum(x.last - x.first + 1 - x.got for x in received)
    # chunks before the first receipt went missing in the absence of an actor: count them with
    # the first actor incarnation's predecessor (the one that died), else as mid-stream
    role, inc = received[0].actor
    between = [((role, inc - 1), received[0].first)] if received[0].first else []
    between += [(a.actor, b.first - a.last - 1) for a, b in zip(received, received[1:])]
    return _Missing(inner=inner, between=between, tail=produced - 1 - received[-1].last, last_actor=received[-1].actor)


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
class _Ledger:
    """Totals and findings while the counter files are read (actors first, then rollouts)."""

    consumed: int = 0
    #: reason -> chunks
    dropped: Counter[str] = field(default_factory=Counter)
    rejected: Counter[str] = field(default_factory=Counter)
    #: one entry per killed incarnation (result.json's lost_by_incarnation)
    lost: list[dict[str, Any]] = field(default_factory=list)
    #: (actor, incarnation) -> its entry in `lost`
    killed_actors: dict[tuple[str, int], dict[str, Any]] = field(default_factory=dict)
    #: "<rollout>#<incarnation>" -> what each actor incarnation received of it
    received: dict[str, list[_Received]] = field(default_factory=dict)
    #: rollout name -> chunks the actors' fabric dropped under backpressure / could not decode
    fabric_drops: Counter[str] = field(default_factory=Counter)
    fabric_rejects: Counter[str] = field(default_factory=Counter)
    #: rejected chunks no rollout produced (forged)
    foreign: int = 0
    #: chunks found missing (or held at a clean exit) that no kill explains
    unaccounted: int = 0
    notes: list[str] = field(default_factory=list)
    #: bytes in flight on a link to a killed actor: the sender's Zenoh queue and both TCP buffers
    window: int = field(default_factory=lambda: ZENOH_TX_BYTES + _tcp_buffer_max("tcp_wmem") + _tcp_buffer_max("tcp_rmem"))

    def add_actor(self, a: dict[str, Any]) -> None:
        held = 0  # received but never settled (consumed, dropped or rejected)
        own_rejects: Counter[str] = Counter()
        for src, c in a.get("sources", {}).items():
            self.received.setdefault(src, []).append(_Received((a["role"], a["incarnation"]), c["first"], c["last"], c["got"]))
            settled = 0
            for key, n in c.items():
                if key == "consumed":
                    self.consumed += n
                elif key.startswith("dropped."):
                    self.dropped[key.removeprefix("dropped.")] += n
                elif key.startswith("rejected."):
                    self.rejected[key.removeprefix("rejected.")] += n
                    own_rejects[src.rsplit("#", 1)[0]] += n
                else:
                    continue
                settled += n
            held += c["got"] - settled
        for peer, f in a.get("fabric", {}).items():
            self.fabric_drops[peer] += f.get("backpressure", 0)
            # the actor's own rejections (counted above) are in the fabric's count too
            self.fabric_rejects[peer] += f.get("rejected", 0) - own_rejects[peer]
        if a.get("clean"):
            if held:
                self.unaccounted += held
                self.notes.append(f"{a['file']}: {held} chunks held at a clean exit")
            return
        entry = {"role": a["role"], "incarnation": a["incarnation"], "pid": a["pid"], "where": "actor",
                 "died_ns": a["updated_ns"], "lost": held, "in_actor": held, "in_transit": 0,
                 "lost_bound": a["slots"] + 2 + a["inbox_cap"]}
        self.killed_actors[(a["role"], a["incarnation"])] = entry
        self.lost.append(entry)

    def add_rollout(self, name: str, incarnations: list[dict[str, Any]], mean_bytes: float) -> None:
        """Place the missing chunks of every incarnation of one rollout."""
        missing = {r["incarnation"]: _missing(r.get("produced", 0), self.received.get(f"{name}#{r['incarnation']}", []))
                   for r in incarnations}
        # The fabric's drops and rejects of this rollout explain chunks missing inside ranges;
        # rejects beyond those were never produced by it: forged.
        inner = sum(max(0, m.inner) for m in missing.values())
        drops = min(self.fabric_drops[name], inner)
        rejects = min(self.fabric_rejects[name], inner - drops)
        self.dropped["backpressure"] += drops
        self.rejected["undecodable"] += rejects
        self.foreign += self.fabric_drops[name] + self.fabric_rejects[name] - drops - rejects
        explained = drops + rejects
        for r in incarnations:
            m = missing[r["incarnation"]]
            take = max(0, min(explained, m.inner))
            m.inner -= take
            explained -= take
            chunk_bytes = r.get("bytes", 0) / r["shipped"] if r.get("shipped") else mean_bytes
            if m.inner:
                self.unaccounted += m.inner
                self.notes.append(f"{r['file']}: {m.inner} chunks missing mid-stream")
            for actor, n in m.between:  # died with actor incarnation `actor` (or in its absence)
                if n and actor in self.killed_actors:
                    killed = self.killed_actors[actor]
                    killed["lost"] += n
                    killed["in_transit"] += n
                    killed["lost_bound"] += _chunks_in(self.window, chunk_bytes)
                elif n:
                    self.unaccounted += n
                    self.notes.append(f"{r['file']}: {n} chunks missing across a clean actor restart")
            self._place_tail(name, r, m, chunk_bytes)

    def _place_tail(self, name: str, r: dict[str, Any], m: _Missing, chunk_bytes: float) -> None:
        """The chunks after the last one received: lost with a killed rollout, or with an actor
        killed at (about) the time this incarnation ended, else unaccounted."""
        if not r.get("clean"):
            in_queue = r.get("produced", 0) - r.get("shipped", 0)
            self.lost.append({"role": name, "incarnation": r["incarnation"], "pid": r["pid"], "where": "rollout",
                              "died_ns": r["updated_ns"], "lost": m.tail, "in_queue": in_queue,
                              "in_transit": m.tail - in_queue,
                              "lost_bound": r.get("queue_cap", 0) + 1 + _chunks_in(ZENOH_TX_BYTES, chunk_bytes)})
            return
        killed = self.killed_actors.get(m.last_actor) if m.last_actor is not None else None
        if m.tail and killed is not None and killed["died_ns"] >= r["updated_ns"] - 10**9:
            killed["lost"] += m.tail
            killed["in_transit"] += m.tail
        elif m.tail:
            self.unaccounted += m.tail
            self.notes.append(f"{r['file']}: {m.tail} chunks missing at the end of a clean incarnation")
