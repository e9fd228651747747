"""Builds the `zenoh.Config` of one plane session, with the defaults that bite made explicit.

See docs/architecture.md ("Zenoh settings") for why each value is what it is:
- multicast scouting and gossip off: links are exactly the `listen`/`connect` lists, so the link
  graph is the one the topology says (no surprise full mesh);
- shared memory is a deliberate choice (it hides network costs between local processes);
- BLOCK congestion control closes a transport after `wait_before_close`; we raise it well above
  any wait our bounded queues can cause, and never block a Zenoh callback for long anyway;
- the largest message a session reassembles (`max_message_size`, Zenoh default 1 GiB) can be
  capped to what the run's messages need (:func:`plane_max_message_size`).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from typing import Any, Iterable

import zenoh

#: with BLOCK, a sender stuck longer than this closes the transport (Zenoh default 5 s).
BLOCK_WAIT_BEFORE_CLOSE_US = 30_000_000
#: the data plane's: its receivers never hold a put longer than an inbox's `block_s` (1 s), so a
#: trajectory put stuck this long is on a dead link (a cut cable, a robot's lost uplink); closing
#: it lets the client reconnect as soon as the link is back (measured: a 10 s cut held the sender
#: 30 s with the ctrl plane's value, 10 s with this one)
DATA_BLOCK_WAIT_BEFORE_CLOSE_US = 10_000_000
#: reconnect quickly to a restarted peer/router (ms).
RETRY_PERIOD_MS = (100, 1000)
#: Zenoh's key for the largest message a session reassembles from fragments (default 1 GiB)
MAX_MESSAGE_SIZE_KEY = "transport/link/rx/max_message_size"


@dataclass(frozen=True, kw_only=True)
class TlsFiles:
    """TLS for one plane session: PEM files and whether both sides must show a certificate."""

    #: CA certificate that signed the peers' certificates (what this side trusts)
    root_ca: str
    #: this side's certificate: presented when listening, and when connecting with `mtls`
    cert: str
    #: private key of `cert`
    key: str
    #: mutual TLS: a listener refuses connections without a certificate signed by `root_ca`
    mtls: bool = True
    #: check that the certificate of what we connect to names the address we dialled
    verify_name: bool = True


def plane_config(
    *,
    mode: str = "peer",
    listen: Iterable[str] = (),
    connect: Iterable[str] = (),
    shared_memory: bool = False,
    lease_ms: int | None = None,
    tls: Any = None,
    max_message_size: int | None = None,
    block_close_us: int = BLOCK_WAIT_BEFORE_CLOSE_US,
) -> zenoh.Config:
    """A Zenoh config for one plane session (data or ctrl) of a dvla process.

    `mode` is "peer", "client" or "router". A client tries `connect` endpoints in order and
    falls back to the next one when its router goes away (how rollouts re-attach to an ancestor).
    `tls` (a :class:`TlsFiles`, or any object with `root_ca`, `cert`, `key` and `mtls`
    attributes such as dvla's `TlsConfig`) makes the session speak TLS: every endpoint must then
    be a ``tls/host:port`` locator, and without it none may be.

    `max_message_size` (bytes; None: Zenoh's 1 GiB) caps what this session reassembles from
    links (a larger message is dropped, the session stays up); shared memory is not bounded by it.
    `block_close_us`: how long a BLOCK put may wait for room before Zenoh closes that link
    (:data:`DATA_BLOCK_WAIT_BEFORE_CLOSE_US` for data sessions).
    """
    if mode not in ("peer", "client", "router"):
        raise ValueError(f"zenoh mode must be peer, client or router, got {mode!r}")
    listen, connect = list(listen), list(connect)
    _check_schemes(listen + connect, tls is not None)
    conf = zenoh.Config()
    _set(conf, "mode", mode)
    _set(conf, "listen/endpoints", listen)
    _set(conf, "connect/endpoints", connect)
    if tls is not None:
        _set_tls(conf, tls)
    _set(conf, "scouting/multicast/enabled", False)
    _set(conf, "scouting/gossip/enabled", False)
    _set(conf, "transport/shared_memory/enabled", bool(shared_memory))
    _set(conf, "transport/link/tx/queue/congestion_control/block/wait_before_close", int(block_close_us))
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
    if max_message_size is not None:
        if isinstance(max_message_size, bool) or not isinstance(max_message_size, int) or max_message_size < 1:
            raise ValueError(f"max_message_size must be a positive number of bytes, got {max_message_size!r}")
        _set(conf, MAX_MESSAGE_SIZE_KEY, max_message_size)
    return conf


def plane_max_message_size(largest_bytes: int, *, headroom: float = 1.25, overhead: int = 64 << 10,
                           floor: int = 1 << 20) -> int:
    """A `max_message_size` for a plane whose largest legitimate payload is ``largest_bytes``:
    with ``headroom`` for what the estimate leaves out, ``overhead`` bytes for the codec's
    framing and the signed envelope, and never below ``floor`` (status and small messages).
    ``roles/runtime.py`` sizes each plane's cap with it."""
    if largest_bytes < 0:
        raise ValueError(f"largest_bytes must be >= 0, got {largest_bytes}")
    return max(int(floor), int(largest_bytes * headroom) + int(overhead))


def _set(conf: zenoh.Config, key: str, value: object) -> None:
    conf.insert_json5(key, json.dumps(value))


def _check_schemes(endpoints: list[str], tls: bool) -> None:
    for endpoint in endpoints:
        scheme = endpoint.split("/", 1)[0]
        if tls and scheme != "tls":
            raise ValueError(f"endpoint {endpoint!r}: a TLS plane needs tls/host:port endpoints only")
        if not tls and scheme == "tls":
            raise ValueError(f"endpoint {endpoint!r}: a tls/ endpoint needs tls= (root_ca, cert, key)")


def _set_tls(conf: zenoh.Config, tls: Any) -> None:
    """Zenoh's `transport/link/tls/*` keys from the PEM files (checked to exist first)."""
    files = {}
    for attr in ("root_ca", "cert", "key"):
        path = getattr(tls, attr, None)
        if not isinstance(path, str) or not os.path.isfile(path):
            raise ValueError(f"tls.{attr}: file not found: {path!r}")
        files[attr] = os.path.abspath(path)
    mtls = bool(getattr(tls, "mtls", True))
    _set(conf, "transport/link/tls/root_ca_certificate", files["root_ca"])
    _set(conf, "transport/link/tls/listen_certificate", files["cert"])
    _set(conf, "transport/link/tls/listen_private_key", files["key"])
    _set(conf, "transport/link/tls/enable_mtls", mtls)
    _set(conf, "transport/link/tls/verify_name_on_connect", bool(getattr(tls, "verify_name", True)))
    if mtls:
        # The same certificate identifies this process when it is the connecting side.
        _set(conf, "transport/link/tls/connect_certificate", files["cert"])
        _set(conf, "transport/link/tls/connect_private_key", files["key"])
