"""Receiving weights from a parent in the replication tree: the `sync`/`recv` lane logic shared by
rollouts, evaluators and replicators.

- Listens on the parent's weights key; assembles each version's chunks into a reusable buffer;
  decodes into the staging pool; verifies layout, base version and checksum; only a verified,
  complete version is handed to `on_version`.
- Anything that does not fit (a missed base version, a bad checksum, a fresh start) is repaired by
  asking the parent's `snapshot` queryable (falling back to further ancestors).
- When the parent's liveliness token goes, it re-subscribes to the nearest live ancestor; when
  the parent comes back it moves back (the tree heals).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, Callable

import numpy as np

from ..fabric import Fabric
from ..fabric.messages import SnapshotRequest, WeightChunk, WeightManifest, WeightSnapshot
from ..replication import (
    ChecksumMismatch,
    ChunkAssembler,
    EncodedVersion,
    NeedSnapshot,
    ParamLayout,
    ReplicationError,
    Snapshot,
    StaleVersion,
    WeightDecoder,
)
from .swimlane import LaneContext

log = logging.getLogger("dvla.weights")


class WeightSync:
    """Follows one parent (with fallbacks) and yields verified weight versions."""

    def __init__(
        self,
        fabric: Fabric,
        layout: ParamLayout,
        parents: tuple[str, ...],
        on_version: Callable[[int, np.ndarray], None],
        *,
        on_message: Callable[[Any], None] | None = None,
        inbox_size: int = 64,
    ) -> None:
        if not parents:
            raise ValueError("WeightSync needs at least one parent")
        self.fabric = fabric
        self.layout = layout
        self.parents = parents
        self.on_version = on_version
        self.on_message = on_message
        self.decoder = WeightDecoder(layout)
        self.assembler: ChunkAssembler | None = None
        self.manifest: WeightManifest | None = None
        # No encoding produces more than a full version: the assembler buffer is that big, once.
        self.max_bytes = layout.nbytes
        self.version = -1
        self.counters = {"versions": 0, "snapshots": 0, "rejected": 0, "repairs": 0, "reattach": 0}
        self._alive: set[str] = set(parents)
        self._lock = threading.Lock()
        self._want_snapshot = True
        self._current: str | None = None
        self._inboxes: dict[str, Any] = {}
        for p in parents:
            # One inbox per possible parent, declared up front: switching parent never
            # redeclares anything from a Zenoh callback.
            self._inboxes[p] = fabric.subscribe_ctrl(fabric.keys.weights(p), inbox_size, (WeightManifest, WeightChunk))
        fabric.watch_alive(self._on_alive)
        self._select()

    # -- membership ---------------------------------------------------------------------------
    def _on_alive(self, role: str, alive: bool) -> None:
        if role not in self.parents:
            return
        with self._lock:
            if alive:
                self._alive.add(role)
            else:
                self._alive.discard(role)
        self._select()

    def _select(self) -> None:
        with self._lock:
            best = next((p for p in self.parents if p in self._alive), self.parents[-1])
            if best != self._current:
                if self._current is not None:
                    log.warning("weights: parent %s -> %s", self._current, best)
                    self.counters["reattach"] += 1
                    self._want_snapshot = True
                self._current = best

    @property
    def parent(self) -> str:
        return self._current or self.parents[0]

    # -- the lane -----------------------------------------------------------------------------
    def step(self, ctx: LaneContext, timeout: float = 0.1) -> None:
        """One iteration of the receiving lane: catch up if needed, then handle one message."""
        if self._want_snapshot:
            with ctx.busy():
                self._catch_up()
        inbox = self._inboxes[self.parent]
        with ctx.waiting():
            got = inbox.get(timeout=timeout)
        # Messages from the non-current parents are discarded (they would duplicate versions).
        for p, other in self._inboxes.items():
            if p != self.parent:
                other.drain_count()
        if got is None:
            return
        _sender, msg = got
        with ctx.busy():
            if self.on_message is not None:
                self.on_message(msg)
            self._handle(msg)
            ctx.count()

    def _handle(self, msg: Any) -> None:
        if isinstance(msg, WeightManifest):
            if msg.total_bytes > self.max_bytes or msg.n_chunks < 1:
                self.counters["rejected"] += 1
                log.warning("weights: manifest v%d from %s rejected (size %d)", msg.version, msg.sender, msg.total_bytes)
                return
            self.manifest = msg
            if self.assembler is None:
                self.assembler = ChunkAssembler(msg.n_chunks, msg.total_bytes, self.max_bytes)
            else:
                self.assembler.reset(msg.n_chunks, msg.total_bytes)
            return
        m = self.manifest
        if m is None or self.assembler is None or msg.version != m.version:
            return  # chunk of a version whose manifest we missed: the next version repairs it
        try:
            self.assembler.add(msg.index, msg.data)
        except ReplicationError as err:
            self.counters["rejected"] += 1
            log.warning("weights: chunk %d of v%d rejected: %s", msg.index, msg.version, err)
            return
        if self.assembler.complete:
            self._apply(m, self.assembler.payload())
            self.manifest = None

    def _apply(self, m: WeightManifest, payload: Any) -> None:
        if m.version <= self.version:
            return
        try:
            flat = self.decoder.apply(manifest_dict(m), payload, swap=True)
        except StaleVersion:
            return
        except NeedSnapshot:
            self.counters["repairs"] += 1
            self._want_snapshot = True
            return
        except ChecksumMismatch:
            self.counters["rejected"] += 1
            self.counters["repairs"] += 1
            log.warning("weights: v%d failed its checksum: discarded, asking for a snapshot", m.version)
            self._want_snapshot = True
            return
        except ReplicationError as err:
            self.counters["rejected"] += 1
            log.warning("weights: v%d rejected: %s", m.version, err)
            self._want_snapshot = True
            return
        self.version = m.version
        self.counters["versions"] += 1
        self.on_version(m.version, flat)

    def _catch_up(self) -> bool:
        """Ask the current parent (then further ancestors) for its latest full weights."""
        order = [self.parent] + [p for p in self.parents if p != self.parent]
        for p in order:
            replies = self.fabric.query(
                self.fabric.keys.snapshot(p), SnapshotRequest(requester=self.fabric.name, have_version=self.version),
                expect=WeightSnapshot, timeout=5.0,
            )
            for _sender, snap in replies:
                if snap.version < 0:
                    continue  # parent has nothing yet
                if snap.version <= self.version:
                    self._want_snapshot = False
                    return True
                try:
                    if snap.layout_hash != self.layout.hash:
                        raise ReplicationError(f"layout {snap.layout_hash} != ours {self.layout.hash}")
                    self.decoder.reset()
                    flat = self.decoder.load_snapshot(Snapshot(snap.version, snap.data, snap.checksum))
                except ReplicationError as err:
                    self.counters["rejected"] += 1
                    log.warning("weights: snapshot v%d from %s rejected: %s", snap.version, p, err)
                    continue
                self.version = snap.version
                self.counters["snapshots"] += 1
                self._want_snapshot = False
                log.info("weights: caught up to v%d by snapshot from %s", snap.version, p)
                self.on_version(snap.version, flat)
                return True
        time.sleep(0.2)  # nobody has weights yet (the actor publishes v1 shortly)
        return False

    def status(self) -> dict[str, Any]:
        return {"parent": self.parent, "version": self.version, **self.counters}


def send_version(fabric: Fabric, key: str, sender: str, enc: EncodedVersion) -> int:
    """Sign and publish one encoded version on `key`: its manifest, then each chunk in order.

    Returns the bytes put on the wire. Used by the actor's ``publish`` lane (and by anything else
    that originates versions, such as the replication benchmark's source).
    """
    sent = fabric.publish_ctrl(key, WeightManifest(sender=sender, **enc.to_dict()), weights=True)
    for i, data in enumerate(enc.chunks):
        msg = WeightChunk(sender=sender, version=enc.version, index=i, n_chunks=enc.n_chunks, data=bytes(data))
        sent += fabric.publish_ctrl(key, msg, weights=True)
    return sent


def manifest_dict(m: WeightManifest) -> dict[str, Any]:
    """The replication manifest fields of a WeightManifest message."""
    return {
        "version": m.version, "base_version": m.base_version, "encoding": m.encoding,
        "layout_hash": m.layout_hash, "checksum": m.checksum, "n_chunks": m.n_chunks,
        "total_bytes": m.total_bytes,
    }
