"""Weights in the replication tree: `WeightPublisher` (the actor, the root: encode, send, serve
snapshots) and `WeightSync` (the `sync`/`recv` lane logic shared by rollouts, evaluators and
replicators), with the one snapshot queryable both ends serve (`serve_snapshots`).

- Listens on the parent's weights key; assembles each version's chunks into a reusable buffer;
  decodes into the staging pool; verifies layout, base version and checksum; only a verified,
  complete version is handed to `on_version`.
- A relay (replicator) is given no layout: it learns the size and hash from the first verified
  manifest (or snapshot proof), never building the model. A receiver holding a model is given
  its frozen base's content hash and refuses versions made for another base.
- Anything that does not fit (a missed base version, a bad checksum, a fresh start) is repaired by
  asking the parent's `snapshot` queryable (falling back to further ancestors).
- When the parent's liveliness token goes, it re-subscribes to the nearest live ancestor; when
  the parent comes back it moves back (the tree heals).
"""

from __future__ import annotations

import hashlib
import logging
import threading
import time
from typing import Any, Callable, NamedTuple

import numpy as np

from ..config import ReplicationConfig
from ..fabric import Fabric
from ..fabric.codec import encode
from ..fabric.errors import CodecError
from ..fabric.messages import SnapshotRequest, WeightChunk, WeightManifest, WeightSnapshot, join_snapshot
from ..replication import (
    MANIFEST_FIELDS,
    ChecksumMismatch,
    ChunkAssembler,
    EncodedVersion,
    NeedSnapshot,
    ParamLayout,
    ReplicationError,
    Snapshot,
    StaleVersion,
    WeightDecoder,
    WeightEncoder,
)
from .swimlane import LaneContext

log = logging.getLogger("dvla.weights")


class Fetched(NamedTuple):
    """What a snapshot fetch brought: the first ancestor that answered, and its reply."""

    parent: str
    snapshot: WeightSnapshot


class WeightSync:
    """Follows one parent (with fallbacks) and yields verified weight versions.

    `on_message(msg, envelope)` sees every verified manifest and chunk with the signed envelope
    it came in, before it is assembled (a relay forwards that envelope to its children as is).

    ``layout`` None: learnt from the first verified manifest (relays). ``base_hash`` (not None):
    this node's frozen base checkpoint hash ("" for a policy that replicates whole); a version
    whose manifest names another is refused, counted under ``refused_base`` and logged once per
    distinct base, and never applied. ``base_source`` names the local checkpoint in that line.
    """

    def __init__(
        self,
        fabric: Fabric,
        layout: ParamLayout | None,
        parents: tuple[str, ...],
        on_version: Callable[[int, np.ndarray], None],
        *,
        on_message: Callable[[Any, bytes], None] | None = None,
        inbox_size: int = 64,
        base_hash: str | None = None,
        base_source: str = "",
    ) -> None:
        if not parents:
            raise ValueError("WeightSync needs at least one parent")
        self.fabric = fabric
        self.parents = parents
        self.on_version = on_version
        self.on_message = on_message
        self.inbox_size = inbox_size
        self.base_hash = base_hash
        self.base_source = base_source
        self._base_logged: set[str] = set()
        self.layout: ParamLayout | None = None
        self.decoder: WeightDecoder | None = None
        self.assembler: ChunkAssembler | None = None
        self.manifest: WeightManifest | None = None
        self.max_bytes = 0
        #: how long one snapshot query waits for its reply (a full snapshot of a large model)
        self.fetch_timeout_s = 5.0
        if layout is not None:
            self._adopt(layout)
        self.version = -1
        #: the actor's signed manifest envelope of `version` (served with snapshots of it)
        self.proof = b""
        self._pending_proof: tuple[int, bytes] = (-1, b"")  # manifest envelope of the version being assembled
        self.counters = {"versions": 0, "snapshots": 0, "rejected": 0, "repairs": 0, "reattach": 0, "refused_base": 0}
        self._alive: set[str] = set(parents)
        self._lock = threading.Lock()
        self._want_snapshot = True
        self._fetch: threading.Thread | None = None
        #: fetch thread -> lane: the snapshot the finished fetch brought (None: nobody answered)
        self._fetched: Fetched | None = None
        self._next_fetch = 0.0
        self._current: str | None = None
        # Only the current parent's key is subscribed: every further subscription would bring
        # each version once more over every link on the way (a chain of relays would carry a
        # version once per ancestor). The lane switches it (never a Zenoh callback), and a
        # switch asks for a snapshot, which covers what arrived meanwhile.
        self._sub_parent: str | None = None
        self._inbox: Any = None
        fabric.watch_alive(self._on_alive)
        self._select()
        self._follow()

    def _adopt(self, layout: ParamLayout) -> None:
        self.layout = layout
        self.decoder = WeightDecoder(layout)
        # No encoding produces more than a full version: the assembler buffer is that big, once.
        self.max_bytes = layout.nbytes
        self.fetch_timeout_s = 5.0 + layout.nbytes / 25e6

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
        if self.layout is None:
            if m.numel < 1:
                self.counters["rejected"] += 1
                return False
            self._adopt(ParamLayout.opaque(m.layout_hash, m.numel))
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
            self.fabric.keys.weights(parent), self.inbox_size, (WeightManifest, WeightChunk),
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
    def step(self, ctx: LaneContext, timeout: float = 0.1) -> None:
        """One iteration of the receiving lane: catch up if needed, then handle one message.

        A snapshot fetch runs on a helper thread while this lane keeps draining the stream, so
        a large snapshot in flight never fills the inbox and never holds Zenoh's receive thread
        (which the snapshot reply itself needs).
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
                self._pending_proof = (msg.version, envelope)
            self._handle(msg)
            ctx.count()

    def _handle(self, msg: Any) -> None:
        if isinstance(msg, WeightManifest):
            if not self._fits(msg):
                self.manifest = None
                return
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
        except ReplicationError as err:  # a failed checksum among them: a snapshot repairs it
            self.counters["rejected"] += 1
            self.counters["repairs"] += isinstance(err, ChecksumMismatch)
            log.warning("weights: v%d rejected, asking for a snapshot: %s", m.version, err)
            self._want_snapshot = True
            return
        self.version = m.version
        self.proof = self._pending_proof[1] if self._pending_proof[0] == m.version else b""
        self.counters["versions"] += 1
        self.on_version(m.version, flat)

    # -- catch-up -----------------------------------------------------------------------------
    def _start_fetch(self) -> None:
        order = [self.parent] + [p for p in self.parents if p != self.parent]
        request = SnapshotRequest(requester=self.fabric.name, have_version=self.version)
        self._fetched = None

        def fetch() -> None:
            # Parent first, then further ancestors; the first one that answers decides.
            for p in order:
                replies = self.fabric.query(
                    self.fabric.keys.snapshot(p), request, expect=WeightSnapshot, timeout=self.fetch_timeout_s
                )
                if replies:
                    try:
                        self._fetched = Fetched(p, join_snapshot([snap for _s, snap in replies]))
                    except CodecError as err:  # missing or disagreeing chunks: ask again shortly
                        log.warning("weights: snapshot from %s incomplete: %s", p, err)
                    return

        self._fetch = threading.Thread(target=fetch, name=f"{self.fabric.name}-catchup", daemon=True)
        self._fetch.start()

    def _finish_fetch(self) -> None:
        """Use what the finished fetch brought (on the lane's thread: the decoder is the lane's)."""
        self._fetch = None
        if self._fetched is None:
            self._next_fetch = time.monotonic() + 0.5  # nobody answered: try again shortly
            return
        p, snap = self._fetched.parent, self._fetched.snapshot
        if snap.version < 0:
            # The parent holds nothing yet: the stream's first version is a full one.
            self._want_snapshot = False
            return
        if snap.version <= self.version:
            self._want_snapshot = False
            return
        if not snap.data:  # header-only although we are behind: it moved on meanwhile; ask again
            return
        try:
            m = self._check_proof(p, snap)
            if not self._fits(m):
                self._next_fetch = time.monotonic() + 5.0
                return
            if snap.layout_hash != self.layout.hash:
                raise ReplicationError(f"layout {snap.layout_hash} != ours {self.layout.hash}")
            self.decoder.reset()
            flat = self.decoder.load_snapshot(Snapshot(snap.version, snap.data, snap.checksum))
        except ReplicationError as err:
            self.counters["rejected"] += 1
            log.warning("weights: snapshot v%d from %s rejected: %s", snap.version, p, err)
            self._next_fetch = time.monotonic() + 0.5
            return
        self.version = snap.version
        self.proof = snap.manifest
        self.counters["snapshots"] += 1
        self._want_snapshot = False
        log.info("weights: caught up to v%d by snapshot from %s", snap.version, p)
        self.on_version(snap.version, flat)

    def _check_proof(self, parent: str, snap: WeightSnapshot) -> WeightManifest:
        """A snapshot is applied only if the actor signed its content: its manifest envelope
        verifies as the actor's, names the same version and layout, and its SHA-256 digest is
        that of the data (a relay cannot make up weights)."""
        if not snap.manifest:
            raise ReplicationError(f"snapshot v{snap.version} from {parent} carries no signed manifest")
        got = self.fabric.open_signed(self.fabric.keys.weights_signed(), snap.manifest, WeightManifest, fresh=False)
        if got is None:
            raise ReplicationError(f"snapshot v{snap.version} from {parent}: its manifest does not verify as the actor's")
        m = got[1]
        if m.version != snap.version or m.layout_hash != snap.layout_hash:
            raise ReplicationError(f"snapshot v{snap.version} from {parent} carries the manifest of v{m.version}")
        if not m.digest or hashlib.sha256(snap.data).hexdigest() != m.digest:
            raise ReplicationError(f"snapshot v{snap.version} from {parent}: data does not hash to the actor's digest")
        return m

    def status(self) -> dict[str, Any]:
        return {"parent": self.parent, "version": self.version, **self.counters}

    @property
    def layout_hash(self) -> str:
        """The layout's hash ("" while a relay has not learnt it)."""
        return self.layout.hash if self.layout is not None else ""


def serve_snapshots(
    fabric: Fabric, sender: str, layout_hash: Callable[[], str], lock: threading.Lock, held: Callable[[], int],
    snapshot: Callable[[], Snapshot], proof: Callable[[], bytes], chunk_bytes: int = 1 << 20,
) -> None:
    """Declare ``sender``'s ``snapshot`` queryable (children's catch-up and repair).

    ``held()`` is the version the caller holds (-1: none yet) and ``snapshot()`` builds it in
    full; both are called under ``lock``, which the caller also holds while it changes what they
    read, so a reply never mixes two versions; ``proof()`` is the actor's signed manifest
    envelope of that version. A requester that is up to date (or asks before anything is held)
    gets a header-only reply and never costs a full copy of the weights; a full snapshot goes as
    replies of at most `chunk_bytes` of parameters each (within the ctrl plane's message cap),
    encoded once per version, however many children ask. Requests are answered by one thread
    of their own from a short queue (never on Zenoh's receive thread; see Fabric.serve).
    ``layout_hash()`` is read per reply (a relay learns it with its first version).
    """
    encoded: dict[int, list[bytes]] = {}
    step = max(4, chunk_bytes - chunk_bytes % 4)  # whole float32 values per reply

    def reply(request: Any) -> Any:
        have = request.have_version if isinstance(request, SnapshotRequest) else -1
        with lock:
            version = held()
            if version < 0 or have >= version:
                return WeightSnapshot(sender=sender, version=max(version, -1), layout_hash=layout_hash(), checksum="", data=b"")
            if version not in encoded:
                snap = snapshot()
                data, manifest, now = memoryview(snap.payload), proof(), time.time_ns()
                n = max(1, -(-len(data) // step))
                encoded.clear()
                encoded[version] = [encode(WeightSnapshot(
                    sender=sender, version=snap.version, layout_hash=layout_hash(), checksum=snap.checksum,
                    data=bytes(data[i * step:(i + 1) * step]), manifest=manifest, index=i, n_chunks=n, created_ns=now,
                )) for i in range(n)]
            return list(encoded[version])

    fabric.serve(fabric.keys.snapshot(sender), reply, SnapshotRequest, worker=True)


class WeightPublisher:
    """The root of the weight tree: encodes each new version (full, or a delta against the last),
    sends it to the children and answers their snapshot queries with the newest version."""

    def __init__(
        self, fabric: Fabric, sender: str, layout: ParamLayout, replication: ReplicationConfig, start_version: int = 0,
        base_hash: str = "",
    ) -> None:
        self.fabric = fabric
        self.sender = sender
        self.layout = layout
        #: content hash of the policy's frozen base ("" when it replicates whole)
        self.base_hash = base_hash
        self.replication = replication
        self.encoder = WeightEncoder.from_config(layout, replication, start_version=start_version)
        self._lock = threading.Lock()  # a snapshot being served never sees a half-encoded version
        #: the signed manifest envelope of the newest encoded version (sent first, and served
        #: with snapshots as the proof of their content)
        self._manifest = b""

    def serve(self) -> None:
        """Declare the ``snapshot`` queryable: children's catch-up with the newest version."""
        serve_snapshots(self.fabric, self.sender, lambda: self.layout.hash, self._lock,
                        lambda: self.encoder.latest, lambda: self.encoder.snapshot(), lambda: self._manifest,
                        self.replication.chunk_bytes)

    def renumber(self, start_version: int) -> None:
        """Continue numbering after `start_version` (the next version is a full one)."""
        with self._lock:
            self.encoder = WeightEncoder.from_config(self.layout, self.replication, start_version=start_version)

    def encode(self, flat: np.ndarray) -> EncodedVersion:
        """Encode the next version from the flat weights and sign its manifest (with the SHA-256
        digest of the weights every replica will hold); snapshots served from now on are of it."""
        with self._lock:
            enc = self.encoder.encode(flat)
            digest = hashlib.sha256(memoryview(self.encoder.published).cast("B")).hexdigest()
            manifest = WeightManifest(sender=self.sender, digest=digest, numel=self.layout.numel,
                                      base_hash=self.base_hash, **enc.to_dict())
            # not signed for the key it travels on: relays forward it unchanged
            self._manifest = self.fabric.seal(self.fabric.keys.weights_signed(), manifest)
            return enc

    def send(self, enc: EncodedVersion) -> int:
        """Sign and publish one encoded version: its manifest, then each chunk in order.
        Returns the bytes put on the wire."""
        f, key = self.fabric, self.fabric.keys.weights(self.sender)
        signed = f.keys.weights_signed()  # not `key`: relays forward these envelopes unchanged
        with self._lock:
            manifest = self._manifest
        sent = f.publish_sealed(key, manifest, weights=True)
        for i, data in enumerate(enc.chunks):
            msg = WeightChunk(sender=self.sender, version=enc.version, index=i, n_chunks=enc.n_chunks, data=bytes(data))
            sent += f.publish_ctrl(key, msg, weights=True, sign_key=signed)
        return sent

    @property
    def checksum(self) -> str:
        """Checksum of the newest encoded version ("" before the first)."""
        with self._lock:
            return self.encoder.checksum


def manifest_dict(m: WeightManifest) -> dict[str, Any]:
    """The replication manifest fields of a WeightManifest message (checked by the decoder)."""
    return {name: getattr(m, name) for name in MANIFEST_FIELDS}
