"""Builds the `zenoh.Config` of one plane session, with the defaults that bite made explicit.

See docs/architecture.md ("Zenoh settings") for why each value is what it is:
- multicast scouting and gossip off: links are exactly the `listen`/`connect` lists, so the link
  graph is the one the topology says (no surprise full mesh);
- shared memory is a deliberate choice (it hides network costs between local processes);
- BLOCK congestion control closes a transport after `wait_before_close`; we raise it well above
  any wait our bounded queues can cause, and never block a Zenoh callback for long anyway.
"""

from __future__ import annotations

import json
from typing import Iterable

import zenoh

#: with BLOCK, a sender stuck longer than this closes the transport (Zenoh default 5 s).
BLOCK_WAIT_BEFORE_CLOSE_US = 30_000_000
#: reconnect quickly to a restarted peer/router (ms).
RETRY_PERIOD_MS = (100, 1000)


def plane_config(
    *,
    mode: str = "peer",
    listen: Iterable[str] = (),
    connect: Iterable[str] = (),
    shared_memory: bool = False,
    lease_ms: int | None = None,
) -> zenoh.Config:
    """A Zenoh config for one plane session (data or ctrl) of a dvla process.

    `mode` is "peer", "client" or "router". A client tries `connect` endpoints in order and
    falls back to the next one when its router goes away (how rollouts re-attach to an ancestor).
    """
    if mode not in ("peer", "client", "router"):
        raise ValueError(f"zenoh mode must be peer, client or router, got {mode!r}")
    conf = zenoh.Config()
    _set(conf, "mode", mode)
    _set(conf, "listen/endpoints", list(listen))
    _set(conf, "connect/endpoints", list(connect))
    _set(conf, "scouting/multicast/enabled", False)
    _set(conf, "scouting/gossip/enabled", False)
    _set(conf, "transport/shared_memory/enabled", bool(shared_memory))
    _set(conf, "transport/link/tx/queue/congestion_control/block/wait_before_close", BLOCK_WAIT_BEFORE_CLOSE_US)
    # Keep trying to reach parents that are not up yet (start order is not guaranteed) or that
    # restart after a crash; never give up and exit.
    _set(conf, "connect/exit_on_failure", {"router": False, "peer": False, "client": False})
    _set(conf, "connect/timeout_ms", {"router": -1, "peer": -1, "client": 0})
    _set(
        conf,
        "connect/retry",
        {"period_init_ms": RETRY_PERIOD_MS[0], "period_max_ms": RETRY_PERIOD_MS[1], "period_increase_factor": 2},
    )
    if lease_ms is not None:
        _set(conf, "transport/link/tx/lease", int(lease_ms))
    return conf


def _set(conf: zenoh.Config, key: str, value: object) -> None:
    conf.insert_json5(key, json.dumps(value))
