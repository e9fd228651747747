"""Replicator role: a relay of the weight tree (one per rack, more where fan-out demands).

Lanes (and what flows between them):
- ``recv``:    verified weight messages from the parent, each queued for forwarding at once
               (cut-through), then assembled and verified into the held weights. The layout
               comes from the first verified manifest: a replicator builds no model.
- ``forward``: sends each message's signed envelope, unchanged, to the children.

The ``snapshot`` queryable answers from the held weights on a thread of its own
(weightsync.serve_snapshots).
"""

from __future__ import annotations

import logging
from typing import Any

from ..config import RoleConfig
from ..fabric import Fabric
from ..replication import HeldWeights, ParamLayout
from .runtime import main
from .swimlane import LaneContext, Swimlane
from .weightsync import WeightSync, held_status

log = logging.getLogger("dvla.replicator")


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

    def build(self, sl: Swimlane) -> None:
        f = self.fabric
        self.outbox = sl.queue("forward", 256)  # recv -> forward: signed envelopes (bytes)
        self.weights = WeightSync.of_role(  # parent -> recv (ancestors as fallback)
            self.cfg, f, HeldWeights(self.layout) if self.layout is not None else None, self._on_version,
            on_message=self._cut_through,
        )
        self.weights.serve(self.cfg.name, self.cfg.replication.chunk_bytes)  # children's catch-up: the held version
        self._stop = sl.stop_event
        sl.lane("recv", self.weights.run)
        sl.lane("forward", self._forward)

    def _cut_through(self, _msg: Any, envelope: bytes) -> None:
        # Forwarded as received: the actor signed it for every hop (keys.weights_signed()), so
        # the relay neither re-encodes nor re-signs, and its children verify the actor's tag.
        self.outbox.put(envelope, self._stop)

    def _on_version(self, version: int) -> None:
        self.policy_version = version

    def _forward(self, ctx: LaneContext) -> None:
        key = self.fabric.keys.weights(self.cfg.name)
        while ctx.running:
            envelope = self.outbox.get(ctx.stop, stats=ctx.stats)
            if envelope is None:
                return
            with ctx.busy():
                self.bytes_forwarded += self.fabric.publish_sealed(key, envelope, weights=True)
                self.forwarded += 1
            ctx.count()

    def status_extra(self) -> dict[str, Any]:
        return {
            "forwarded": self.forwarded,
            "bytes_forwarded": self.bytes_forwarded,
            "forward_depth": self.outbox.depth,
            "weights": self.weights.status(),
            **held_status(self.weights.held),
        }

    def close(self) -> None:
        pass


if __name__ == "__main__":
    raise SystemExit(main(Replicator))
