"""Weights in the replication tree: `WeightPublisher` (the actor, the root: encode, send, serve
snapshots) and `WeightSync` (the receiving lane's logic shared by rollouts, evaluators and
replicators), with the one snapshot queryable both ends serve (`serve_snapshots`).

A receiver assembles each version's chunks and holds it once `HeldWeights.apply` verified it.
Anything that does not fit (a missed base, a bad checksum, a fresh start) is repaired by a
snapshot from the parent (or a further ancestor): the held version sent whole through the same
assembler and `apply`. When the parent's liveliness token goes it follows the nearest live
ancestor, and moves back when the parent returns.
"""

from __future__ import annotations

import hashlib
import logging
import threading
import time
from typing import Any, Callable

import numpy as np

from ..config import ReplicationConfig, RoleConfig
from ..fabric import Fabric
from ..fabric.codec import encode
from ..fabric.messages import SnapshotRequest, WeightChunk, WeightManifest, WeightSnapshot
from ..replication import (
    ChecksumMismatch,
    ChunkAssembler,
    HeldWeights,
    NeedSnapshot,
    ParamLayout,
    ReplicationError,
    StaleVersion,
    WeightEncoder,
    WeightVersion,
    split_chunks,
)
from .swimlane import LaneContext

log = logging.getLogger("dvla.weights")

#: verified weight messages waiting for the receiving lane
INBOX = 64


class WeightSync:
    """Follows one parent (with fallbacks) and fills `held` with verified weight versions.

    `on_message(msg, envelope)` sees every verified manifest and chunk with the signed envelope
    it came in, before it is assembled (a relay forwards that envelope to its children as is);
    `on_version(version)` is called once each new version is held.

    ``held`` None: its layout is learnt from the first verified manifest (relays). ``base_hash``
    (not None): this node's frozen base checkpoint hash ("" for a policy that replicates whole); a
    version whose manifest names another is refused, counted under ``refused_base`` and logged
    once per distinct base, and never applied. ``base_source`` names the local checkpoint there.
    """

    def __init__(
        self,
        fabric: Fabric,
        held: HeldWeights | None,
        parents: tuple[str, ...],
        on_version: Callable[[int], None] | None = None,
        *,
        on_message: Callable[[Any, bytes], None] | None = None,
        base_hash: str | None = None,
        base_source: str = "",
    ) -> None:
        if not parents:
            raise ValueError("WeightSync needs at least one parent")
        self.fabric = fabric
        self.parents = parents
        self.on_version = on_version
        self.on_message = on_message
        self.base_hash = base_hash
        self.base_source = base_source
        self._base_logged: set[str] = set()
        self.held: HeldWeights | None = None
        self._assembler: ChunkAssembler | None = None
        self._manifest: WeightManifest | None = None  # of the version being assembled
        #: how long one snapshot query waits for its reply (a full snapshot of a large model)
        self.fetch_timeout_s = 5.0
        if held is not None:
            self._adopt(held)
        self._proof: tuple[int, bytes] = (-1, b"")  # manifest envelope of the version being assembled
        self.counters = {"versions": 0, "snapshots": 0, "rejected": 0, "repairs": 0, "reattach": 0, "refused_base": 0}
        self._alive: set[str] = set(parents)
        self._lock = threading.Lock()
        self._want_snapshot = True
        self._fetch: threading.Thread | None = None
        #: fetch thread -> lane: (the first ancestor that answered, its replies); None: nobody did
        self._fetched: tuple[str, list[Any]] | None = None
        self._next_fetch = 0.0
        self._current: str | None = None
        # Only the current parent's key is subscribed (more would carry each version once per
        # ancestor); the lane switches it, and a switch asks for a snapshot.
        self._sub_parent: str | None = None
        self._inbox: Any = None
        fabric.watch_alive(self._on_alive)
        self._select()
        self._follow()

    @classmethod
    def of_role(cls, cfg: RoleConfig, fabric: Fabric, held: HeldWeights | None, on_version: Callable[[int], None],
                policy: Any = None, **kwargs: Any) -> "WeightSync":
        """Role `cfg`'s receiving side: its parent, further ancestors as fallbacks; with `policy`,
        versions made for another frozen base are refused."""
        if policy is not None:  # imported here: a replicator builds no policy
            from ..learn.policies import policy_base_hash

            kwargs.update(base_hash=policy_base_hash(policy), base_source=str(cfg.task.policy_kwargs.get("checkpoint", "")))
        return cls(fabric, held, (cfg.parent, *cfg.ancestors[1:]), on_version, **kwargs)

    def _adopt(self, held: HeldWeights) -> None:
        self.held = held
        self.fetch_timeout_s = 5.0 + held.layout.nbytes / 25e6

    @property
    def version(self) -> int:
        """The version held (-1: none yet)."""
        return self.held.version if self.held is not None else -1

    @property
    def layout_hash(self) -> str:
        """The layout's hash ("" while a relay has not learnt it)."""
        return self.held.layout.hash if self.held is not None else ""

    def _fits(self, m: WeightManifest) -> bool:
        """Whether a verified manifest is for this node: the same frozen base (when this node
        has one to compare), and a layout it holds or, for a relay, can adopt."""
        if self.base_hash is not None and m.base_hash != self.base_hash:
            self.counters["refused_base"] += 1
            if m.base_hash not in self._base_logged and len(self._base_logged) < 16:
                self._base_logged.add(m.base_hash)
                log.error("weights v%d from %s refused: made for base checkpoint %s, this node's base %s is %s",
                          m.version, m.sender, m.base_hash or "<none: full policy>", self.base_source or "<none>",
                          self.base_hash or "<none: full policy>")
            return False
        if self.held is None:
            if m.numel < 1:
                self.counters["rejected"] += 1
                return False
            self._adopt(HeldWeights(ParamLayout.opaque(m.layout_hash, m.numel)))
            log.info("weights: layout %s of %d elements learnt from v%d's manifest", m.layout_hash, m.numel, m.version)
        return True

    def _follow(self) -> None:
        """Subscribe to the current parent's weights (and drop the previous one's)."""
        parent = self.parent
        if parent == self._sub_parent:
            return
        if self._inbox is not None:
            self.fabric.unsubscribe(self._inbox)
        self._inbox = self.fabric.subscribe_ctrl(
            self.fabric.keys.weights(parent), INBOX, (WeightManifest, WeightChunk),
            sign_key=self.fabric.keys.weights_signed(), with_envelope=True,
        )
        self._sub_parent = parent

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
    def run(self, ctx: LaneContext) -> None:
        """The receiving lane."""
        while ctx.running:
            self.step(ctx)

    def step(self, ctx: LaneContext, timeout: float = 0.1) -> None:
        """One iteration of the receiving lane: catch up if needed, then handle one message.

        A snapshot fetch runs on a thread of its own while this lane keeps draining the stream,
        so it never fills the inbox nor holds Zenoh's receive thread (which its reply needs).
        """
        if self._want_snapshot and self._fetch is None and time.monotonic() >= self._next_fetch:
            self._start_fetch()
        if self._fetch is not None and not self._fetch.is_alive():
            with ctx.busy():
                self._finish_fetch()
        self._follow()
        with ctx.waiting():
            got = self._inbox.get(timeout=timeout)
        if got is None:
            return
        _sender, msg, envelope = got
        with ctx.busy():
            if self.on_message is not None:
                self.on_message(msg, envelope)
            if isinstance(msg, WeightManifest):
                self._proof = (msg.version, envelope)
            self._handle(msg)
            ctx.count()

    def _handle(self, msg: Any) -> None:
        if isinstance(msg, WeightManifest):
            self._manifest = None
            if not self._fits(msg):
                return
            try:
                if self._assembler is None:
                    self._assembler = ChunkAssembler(msg.n_chunks, msg.total_bytes, self.held.layout.nbytes)
                else:
                    self._assembler.reset(msg.n_chunks, msg.total_bytes)
                self._manifest = msg
            except ReplicationError as err:
                self.counters["rejected"] += 1
                log.warning("weights: manifest v%d from %s rejected: %s", msg.version, msg.sender, err)
            return
        m = self._manifest
        if m is None or msg.version != m.version:
            return  # chunk of a version whose manifest we missed: the next version repairs it
        try:
            self._assembler.add(msg.index, msg.data)
        except ReplicationError as err:
            self.counters["rejected"] += 1
            log.warning("weights: chunk %d of v%d rejected: %s", msg.index, msg.version, err)
            return
        if self._assembler.complete:
            self._manifest = None
            proof = self._proof[1] if self._proof[0] == m.version else b""
            self._apply(m, self._assembler.payload(), proof, "stream")

    def _apply(self, m: WeightManifest, payload: Any, proof: bytes, via: str) -> bool:
        """Hold one assembled version (stream or snapshot); False (counted) when it does not apply."""
        try:
            self.held.apply(m, payload, proof)
        except StaleVersion:
            return False
        except NeedSnapshot:
            self.counters["repairs"] += 1
            self._want_snapshot = True
            return False
        except ReplicationError as err:  # a failed checksum among them: a snapshot repairs it
            self.counters["rejected"] += 1
            self.counters["repairs"] += isinstance(err, ChecksumMismatch)
            log.warning("weights: v%d (%s) rejected, asking for a snapshot: %s", m.version, via, err)
            self._want_snapshot = True
            return False
        self.counters["snapshots" if via == "snapshot" else "versions"] += 1
        if self.on_version is not None:
            self.on_version(m.version)
        return True

    # -- catch-up -----------------------------------------------------------------------------
    def _start_fetch(self) -> None:
        order = [self.parent] + [p for p in self.parents if p != self.parent]
        request = SnapshotRequest(requester=self.fabric.name, have_version=self.version)
        self._fetched = None

        def fetch() -> None:
            # Parent first, then further ancestors; the first one that answers decides.
            for p in order:
                replies = self.fabric.query(self.fabric.keys.snapshot(p), request,
                                            expect=(WeightSnapshot, WeightChunk), timeout=self.fetch_timeout_s)
                if replies:
                    self._fetched = (p, [msg for _s, msg in replies])
                    return

        self._fetch = threading.Thread(target=fetch, name=f"{self.fabric.name}-catchup", daemon=True)
        self._fetch.start()

    def _finish_fetch(self) -> None:
        """Use what the finished fetch brought (on the lane's thread: `held` is the lane's)."""
        self._fetch = None
        if self._fetched is None:
            self._next_fetch = time.monotonic() + 0.5  # nobody answered: try again shortly
            return
        p, replies = self._fetched
        heads = [r for r in replies if isinstance(r, WeightSnapshot)]
        if len(heads) != 1:
            log.warning("weights: snapshot from %s incomplete: %d headers in %d replies", p, len(heads), len(replies))
            self._next_fetch = time.monotonic() + 0.5
            return
        head = heads[0]
        if head.version < 0 or head.version <= self.version:
            # Nothing newer (or nothing held yet: the stream's first version is a full one).
            self._want_snapshot = False
            return
        if not head.n_chunks:  # header-only although we are behind: it moved on meanwhile; ask again
            return
        try:
            m = self._check_proof(p, head)
            if not self._fits(m):
                self._next_fetch = time.monotonic() + 5.0
                return
            whole = m.whole(head.n_chunks)
            asm = ChunkAssembler(whole.n_chunks, whole.total_bytes, self.held.layout.nbytes)
            for c in replies:
                if isinstance(c, WeightChunk) and c.version == m.version:
                    asm.add(c.index, c.data)
            if not asm.complete:  # replies lost on the way (a query timing out): ask again shortly
                log.warning("weights: snapshot v%d from %s incomplete", m.version, p)
                self._next_fetch = time.monotonic() + 0.5
                return
            payload = asm.payload()
            if hashlib.sha256(payload).hexdigest() != m.digest:
                raise ReplicationError("data does not hash to the actor's digest")
        except ReplicationError as err:
            self.counters["rejected"] += 1
            log.warning("weights: snapshot v%d from %s rejected: %s", head.version, p, err)
            self._next_fetch = time.monotonic() + 0.5
            return
        if self._apply(whole, payload, head.manifest, "snapshot"):
            self._want_snapshot = False
            log.info("weights: caught up to v%d by snapshot from %s", m.version, p)
        else:
            self._next_fetch = time.monotonic() + 0.5

    def _check_proof(self, parent: str, head: WeightSnapshot) -> WeightManifest:
        """A snapshot is applied only if the actor signed its content: its manifest envelope
        verifies as the actor's and names the same version, and the data must hash (SHA-256) to
        that manifest's digest (a relay cannot make up weights)."""
        if not head.manifest:
            raise ReplicationError(f"snapshot v{head.version} from {parent} carries no signed manifest")
        got = self.fabric.open_signed(self.fabric.keys.weights_signed(), head.manifest, WeightManifest, fresh=False)
        if got is None:
            raise ReplicationError(f"snapshot v{head.version} from {parent}: its manifest does not verify as the actor's")
        m = got[1]
        if m.version != head.version or not m.digest:
            raise ReplicationError(f"snapshot v{head.version} from {parent} carries the manifest of v{m.version}")
        return m

    def serve(self, sender: str, chunk_bytes: int) -> None:
        """Answer children's snapshot queries with the version held (a relay)."""
        serve_snapshots(self.fabric, sender, lambda: self.held, chunk_bytes)

    def status(self) -> dict[str, Any]:
        return {"parent": self.parent, "version": self.version, **self.counters}


def held_status(held: HeldWeights | None) -> dict[str, Any]:
    """A role's ``held_version`` and ``held_checksum`` status fields (read together: never a
    version paired with another version's checksum)."""
    version, digest = held.id if held is not None else (-1, "")
    return {"held_version": version, "held_checksum": digest}


def serve_snapshots(
    fabric: Fabric, sender: str, held: Callable[[], HeldWeights | None], chunk_bytes: int = 1 << 20,
) -> None:
    """Declare ``sender``'s ``snapshot`` queryable (children's catch-up and repair).

    The reply is the version ``held()`` holds, whole: a :class:`WeightSnapshot` header with the
    actor's signed manifest, then its ``full`` payload as ``WeightChunk`` replies of at most
    `chunk_bytes`, encoded once per version (read under the held weights' lock). A requester
    that is up to date gets the header alone. Answered on a worker thread (Fabric.serve).
    """
    encoded: dict[int, list[bytes]] = {}

    def reply(request: Any) -> Any:
        have = request.have_version if isinstance(request, SnapshotRequest) else -1
        h = held()
        if h is None or h.version < 0 or have >= h.version:
            return WeightSnapshot(sender=sender, version=-1 if h is None else h.version, manifest=b"", n_chunks=0)
        with h.lock:
            version = h.version
            if version not in encoded:
                chunks = split_chunks(memoryview(h.active).cast("B"), chunk_bytes)
                n = len(chunks)
                encoded.clear()
                encoded[version] = [encode(WeightSnapshot(sender=sender, version=version, manifest=h.proof, n_chunks=n))]
                encoded[version] += [encode(WeightChunk(sender=sender, version=version, index=i, n_chunks=n, data=bytes(c)))
                                     for i, c in enumerate(chunks)]
            return list(encoded[version])

    fabric.serve(fabric.keys.snapshot(sender), reply, SnapshotRequest, worker=True)


class WeightPublisher:
    """The root of the weight tree: encodes each new version (full, or a delta against the last)
    and signs its manifest, sends it to the children, and answers their snapshot queries with the
    newest version (`held`, what every replica holds once it has it)."""

    def __init__(
        self, fabric: Fabric, sender: str, layout: ParamLayout, replication: ReplicationConfig, start_version: int = 0,
        base_hash: str = "",
    ) -> None:
        self.fabric = fabric
        self.sender = sender
        self.replication = replication
        # not signed for the key it travels on: relays forward it unchanged
        self.encoder = WeightEncoder.from_config(
            layout, replication, start_version=start_version, sender=sender, base_hash=base_hash,
            seal=lambda m: fabric.seal(fabric.keys.weights_signed(), m),
        )
        #: the newest version encoded, with its signed manifest
        self.held = self.encoder.held

    def serve(self) -> None:
        """Declare the ``snapshot`` queryable: children's catch-up with the newest version."""
        serve_snapshots(self.fabric, self.sender, lambda: self.held, self.replication.chunk_bytes)

    def encode(self, flat: np.ndarray) -> WeightVersion:
        """Encode the next version from the flat weights; snapshots served from now on are of it."""
        return self.encoder.encode(flat)

    def send(self, v: WeightVersion) -> int:
        """Publish one encoded version: its signed manifest, then each chunk in order.
        Returns the bytes put on the wire."""
        f, key = self.fabric, self.fabric.keys.weights(self.sender)
        signed = f.keys.weights_signed()  # not `key`: relays forward these envelopes unchanged
        sent = f.publish_sealed(key, v.proof, weights=True)
        m = v.manifest
        for i, data in enumerate(v.chunks):
            msg = WeightChunk(sender=self.sender, version=m.version, index=i, n_chunks=m.n_chunks, data=bytes(data))
            sent += f.publish_ctrl(key, msg, weights=True, sign_key=signed)
        return sent
