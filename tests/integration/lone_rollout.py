"""One rollout role run in the test's process with no actor and no data plane: its finished
chunks go to the test (a subclass's ``_publish``), which stops the run when it has enough."""

from __future__ import annotations

import threading
from typing import Callable

from dvla.config import RoleConfig
from dvla.fabric import Fabric, plane_config
from dvla.roles.rollout import Rollout
from dvla.roles.runtime import ExitStatus, RoleHost


def run_alone(cfg: RoleConfig, role_cls: type[Rollout], prepare: Callable[[Rollout], None],
              check: Callable[[Rollout], None] = lambda _role: None, timeout_s: float = 240.0) -> ExitStatus:
    """Build ``role_cls`` for ``cfg``, ``prepare`` it (install its first weights, as a verified
    version from the actor would), run it until it calls ``self.stop_run()`` (or `timeout_s`),
    ``check`` it while its lanes' state is still there, close it; returns its exit status."""
    fabric = Fabric(run=cfg.run, name=cfg.name, ctrl_conf=plane_config(mode="peer", listen=("tcp/127.0.0.1:0",)),
                    data_conf=None, secret=b"k" * 32)
    fabric.traj_matched = lambda: True  # no learner process: ship into the test at once
    try:
        role = role_cls(cfg, fabric)
        try:
            prepare(role)
            role._ready.set()
            host = RoleHost(cfg, fabric, role)
            role.stop_run = host.swimlane.stop  # type: ignore[attr-defined]
            timer = threading.Timer(timeout_s, host.swimlane.stop)
            timer.start()
            try:
                code = host.run()
            finally:
                timer.cancel()
            check(role)
        finally:
            role.close()
    finally:
        fabric.close()
    return code
