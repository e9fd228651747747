"""Replicator role: a relay of the weight tree (one per rack, more where fan-out demands).

Lanes (and what flows between them):
- ``recv``:    weight messages from the parent (signature checked by the fabric); each one is
               queued for forwarding at once (cut-through, chunk by chunk), then assembled and
               verified (layout, base version, checksum) into the local dual pool. The layout's
               size and hash come from the first verified manifest: a replicator builds no
               model and no environment, and needs neither torch's policy code nor a GPU.
- ``forward``: sends each message's signed envelope, unchanged, to the children (the actor
               signed it for every hop: ``keys.weights_signed()``).
- ``serve``:   answers snapshot queries from the verified active pool (catch-up, repair), and
               keeps the last verified version's snapshot ready.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, NamedTuple

import numpy as np

from ..config import RoleConfig
from ..fabric import Fabric
from ..fabric.messages import WeightChunk, WeightManifest
from ..replication import ParamLayout, Snapshot
from .runtime import main
from .swimlane import LaneContext, Swimlane
from .weightsync import WeightSync, serve_snapshots

log = logging.getLogger("dvla.replicator")


class Forward(NamedTuple):
    """recv -> forward: one signed weight message to send on to the children."""

    version: int
    envelope: bytes
    received_ns: int


class Replicator:
    def __init__(self, cfg: RoleConfig, fabric: Fabric, layout: ParamLayout | None = None) -> None:
        self.cfg = cfg
        self.fabric = fabric
        #: None until the first verified manifest names it (see WeightSync)
        self.layout = layout
        self.policy_version = -1
        self.env_steps = 0
        self.forwarded = 0
        self.bytes_forwarded = 0
        #: held while the verified version below changes, so a snapshot never mixes two
        self._snap_lock = threading.Lock()
        self._flat: np.ndarray | None = None
        #: checksum of the newest verified weights (status: replicas compared with the actor's)
        self.held_checksum = ""
        #: the actor's signed manifest of the held version (proof served with snapshots)
        self._proof = b""
        #: version -> forwarding times of its chunks (see _timing)
        self.timing: dict[int, dict[str, Any]] = {}

    def build(self, sl: Swimlane) -> None:
        f = self.fabric
        self.outbox = sl.queue("forward", 256)  # recv -> forward: Forward (signed envelopes)
        self.weights = WeightSync(  # parent -> recv (ancestors as fallback)
            f, self.layout, (self.cfg.parent, *self.cfg.ancestors[1:]), self._on_version, on_message=self._cut_through
        )
        serve_snapshots(  # children's catch-up: the verified active version
            f, self.cfg.name, lambda: self.weights.layout_hash, self._snap_lock, lambda: self.policy_version, self._held_snapshot,
            lambda: self._proof, self.cfg.replication.chunk_bytes,
        )
        self._stop = sl.stop_event
        sl.lane("recv", self._recv)
        sl.lane("forward", self._forward)

    def _cut_through(self, msg: Any, envelope: bytes) -> None:
        # Forwarded as received: the actor signed it for every hop (keys.weights_signed()), so
        # the relay neither re-encodes nor re-signs, and its children verify the actor's tag.
        if isinstance(msg, (WeightManifest, WeightChunk)):
            self.outbox.put(Forward(msg.version, envelope, time.time_ns()), self._stop)

    def _on_version(self, version: int, flat: np.ndarray) -> None:
        with self._snap_lock:
            self._flat = flat
            self.held_checksum = self.weights.decoder.checksum
            self._proof = self.weights.proof
            self.policy_version = version

    def _held_snapshot(self) -> Snapshot:
        return Snapshot(self.policy_version, self._flat.tobytes(), self.held_checksum)

    def _recv(self, ctx: LaneContext) -> None:
        while ctx.running:
            self.weights.step(ctx)

    def _forward(self, ctx: LaneContext) -> None:
        key = self.fabric.keys.weights(self.cfg.name)
        while ctx.running:
            item = self.outbox.get(ctx.stop, stats=ctx.stats)
            if item is None:
                return
            with ctx.busy():
                self.bytes_forwarded += self.fabric.publish_sealed(key, item.envelope, weights=True)
                self.forwarded += 1
                self._timing(item.version, item.received_ns, time.time_ns())
            ctx.count()

    def _timing(self, version: int, received_ns: int, sent_ns: int) -> None:
        """Per version: when its last chunk came in and went out, and the longest a chunk
        waited here (received -> put to the children returned)."""
        t = self.timing.get(version)
        if t is None:
            t = self.timing[version] = {"first_in_ns": received_ns, "max_lag_ms": 0.0}
            while len(self.timing) > 4:
                self.timing.pop(min(self.timing))
        t["last_in_ns"], t["last_out_ns"] = received_ns, sent_ns
        t["max_lag_ms"] = max(t["max_lag_ms"], (sent_ns - received_ns) / 1e6)

    def status_extra(self) -> dict[str, Any]:
        return {
            "forwarded": self.forwarded,
            "bytes_forwarded": self.bytes_forwarded,
            "forward_depth": self.outbox.depth,
            "forward_timing": {str(v): t for v, t in self.timing.items()},
            "weights": self.weights.status(),
            "held_version": self.policy_version,
            "held_checksum": self.held_checksum,
        }

    def close(self) -> None:
        pass


if __name__ == "__main__":
    raise SystemExit(main(Replicator))
