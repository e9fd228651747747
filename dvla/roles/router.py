"""Router: a node's Zenoh routers for producers outside the topology (``router:`` in the
topology; a robot behind NAT runs `dvla join` and dials in as a Zenoh client).

The role's two fabric sessions *are* the routers (mode "router", planned by
dvla/orchestrator/plan.py): the ctrl one is linked to the root actor's ctrl router, the data one
to every actor's data listener, so weights, commands and status reach the outside rollouts and
their chunks reach the learners, routed by Zenoh and forwarded untouched (envelopes are signed
end to end; a router verifies nothing and holds no data). `main` gives it what every role has
(status, liveliness, `stop`, SIGTERM, supervision by `dvla up`); its one lane, ``links``, watches
its links into the run and logs a line when they go or come back.
"""

from __future__ import annotations

import logging
from typing import Any

from ..config import RoleConfig
from ..fabric import Fabric
from .runtime import main
from .swimlane import LaneContext, Swimlane

log = logging.getLogger("dvla.router")

#: seconds between two looks at the links
WATCH_S = 1.0


class Router:
    """Nothing but the sessions `main` opens; status says where they listen and what they link."""

    policy_version = -1
    env_steps = 0

    def __init__(self, cfg: RoleConfig, fabric: Fabric) -> None:
        self.cfg = cfg
        self.fabric = fabric
        #: Zenoh sessions of the run this router is linked to: ctrl routers (the root actor's),
        #: data peers (the actors' listeners)
        self.linked = {"ctrl": 0, "data": 0}

    def build(self, swimlane: Swimlane) -> None:
        swimlane.lane("links", self._watch)  # Zenoh routes on its own threads; this lane only watches

    def _watch(self, ctx: LaneContext) -> None:
        while ctx.running:
            now = {"ctrl": len(list(self.fabric.ctrl.info.routers_zid())),
                   "data": len(list(self.fabric.data.info.peers_zid())) if self.fabric.data is not None else 0}
            for plane in now:
                if (now[plane] == 0) != (self.linked[plane] == 0):
                    log.info("%s plane: %s", plane, "linked to the run" if now[plane] else "no link to the run (retrying)")
            self.linked = now
            ctx.count()
            with ctx.waiting():
                ctx.sleep(WATCH_S)

    def status_extra(self) -> dict[str, Any]:
        return {"listen": {"ctrl": list(self.cfg.ctrl.listen), "data": list(self.cfg.data.listen)},
                "connect": {"ctrl": list(self.cfg.ctrl.connect), "data": list(self.cfg.data.connect)},
                "linked": dict(self.linked)}

    def close(self) -> None:
        pass


if __name__ == "__main__":
    raise SystemExit(main(Router))
