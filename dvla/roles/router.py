"""Router: a node's Zenoh routers for producers outside the topology (``router:`` in the
topology; a robot behind NAT runs `dvla join` and dials in as a Zenoh client).

The role's two fabric sessions *are* the routers (mode "router", planned by
dvla/orchestrator/plan.py): the ctrl one is linked to the root actor's ctrl router, the data one
to every actor's data listener, so weights, commands and status reach the outside rollouts and
their chunks reach the learners, routed by Zenoh and forwarded untouched (envelopes are signed
end to end; a router verifies nothing and holds no data). It has no lanes: `main` gives it
what every role has (status, liveliness, `stop`, SIGTERM, supervision by `dvla up`).
"""

from __future__ import annotations

from typing import Any

from ..config import RoleConfig
from ..fabric import Fabric
from .runtime import main
from .swimlane import Swimlane


class Router:
    """Nothing but the sessions `main` opens; status says where they listen and what they link."""

    policy_version = -1
    env_steps = 0

    def __init__(self, cfg: RoleConfig, fabric: Fabric) -> None:
        self.cfg = cfg
        self.fabric = fabric

    def build(self, swimlane: Swimlane) -> None:
        pass  # no lanes: Zenoh routes on its own threads

    def status_extra(self) -> dict[str, Any]:
        return {"listen": {"ctrl": list(self.cfg.ctrl.listen), "data": list(self.cfg.data.listen)},
                "connect": {"ctrl": list(self.cfg.ctrl.connect), "data": list(self.cfg.data.connect)}}

    def close(self) -> None:
        pass


if __name__ == "__main__":
    raise SystemExit(main(Router))
