"""Message accounting per plane and per peer: sent, received, rejected (by reason), dropped
(by reason). Every loss the fabric sees is counted here, so status can show it and tests can
check that nothing vanished silently."""

from __future__ import annotations

import threading
from collections import defaultdict
from collections.abc import Iterable
from typing import Any

from .keys import check_name

OTHER_PEER = "<other>"
"""Peer key under which every peer past the cap (or with a name no role can have) is counted.
'<' cannot start a role name (``^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$``), so it never collides with
one, and a reader that tells rollouts from foreign traffic by name counts it as foreign."""

MAX_OTHER_PEERS = 64
"""Default number of distinct peers outside the known set that get counters of their own."""

#: peer under which the fabric counts traffic that fails authentication (never a role name, so the
#: run's accounting reports it as foreign)
UNAUTHENTICATED = "<unauthenticated>"
#: aggregate peer keys, always counted under their own key (neither is a role name)
RESERVED_PEERS = frozenset({OTHER_PEER, UNAUTHENTICATED})


class Accounting:
    """Thread-safe counters, written from Zenoh callbacks and lane threads alike.

    Plane totals are exact. Per-peer counters are bounded: the peer name comes from the last chunk
    of a Zenoh key, which any session on the plane can choose, so only the ``known_peers`` (the
    run's roles, added with :meth:`add_known_peers` when learned later) and the first
    ``max_other_peers`` other valid role names get counters of their own; every further peer, and
    every name that is not a valid role name (except the :data:`RESERVED_PEERS`), is aggregated
    under :data:`OTHER_PEER`.
    """

    def __init__(self, known_peers: Iterable[str] = (), max_other_peers: int = MAX_OTHER_PEERS) -> None:
        self._lock = threading.Lock()
        # plane -> counter name -> value
        self._plane: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
        # plane -> peer -> counter name -> value
        self._peer: dict[str, dict[str, dict[str, int]]] = defaultdict(lambda: defaultdict(lambda: defaultdict(int)))
        self._known: set[str] = {*RESERVED_PEERS, *known_peers}
        self._others: set[str] = set()  # peers outside `_known` with counters of their own
        self.max_other_peers = max_other_peers

    def add_known_peers(self, names: Iterable[str]) -> None:
        """Give these peers counters of their own whatever the cap (what they sent before, past
        the cap, stays under :data:`OTHER_PEER`)."""
        with self._lock:
            self._known.update(names)

    def _key(self, peer: str) -> str:
        """The peer key `peer` is counted under (call with the lock held)."""
        if peer in self._known or peer in self._others:
            return peer
        if len(self._others) >= self.max_other_peers or not _valid_name(peer):
            return OTHER_PEER
        self._others.add(peer)
        return peer

    def add(self, plane: str, counter: str, peer: str | None = None, n: int = 1, nbytes: int = 0) -> None:
        """Count `n` messages (of `nbytes` bytes in all, kept as ``<counter>_bytes``). A counter
        ``<total>.<reason>`` counts its total too, in the same step (a reader never sees them apart)."""
        names = {counter, counter.partition(".")[0]}
        with self._lock:
            tables = [self._plane[plane]] + ([self._peer[plane][self._key(peer)]] if peer is not None else [])
            for table in tables:
                for name in names:
                    table[name] += n
                    if nbytes:
                        table[name + "_bytes"] += nbytes

    def sent(self, plane: str, nbytes: int, peer: str | None = None) -> None:
        self.add(plane, "sent", peer, 1, nbytes)

    def received(self, plane: str, nbytes: int, peer: str | None = None) -> None:
        self.add(plane, "received", peer, 1, nbytes)

    def rejected(self, plane: str, reason: str, peer: str | None = None) -> None:
        """A message that failed decoding or verification (never applied)."""
        self.add(plane, f"rejected.{reason}", peer)

    def dropped(self, plane: str, reason: str, peer: str | None = None, n: int = 1) -> None:
        """A valid message deliberately not used (stale, backpressure, ...)."""
        self.add(plane, f"dropped.{reason}", peer, n)

    def get(self, plane: str, counter: str, peer: str | None = None) -> int:
        """A plane total, or one peer's counter (0 for a peer aggregated under :data:`OTHER_PEER`)."""
        with self._lock:
            if peer is None:
                return int(self._plane.get(plane, {}).get(counter, 0))
            return int(self._peer.get(plane, {}).get(peer, {}).get(counter, 0))

    def snapshot(self) -> dict[str, Any]:
        """{plane: {counter: n, ..., "peers": {peer: {counter: n}}}} as plain dicts."""
        with self._lock:
            out: dict[str, Any] = {}
            for plane, counters in self._plane.items():
                entry: dict[str, Any] = dict(counters)
                peers = self._peer.get(plane)
                if peers:
                    entry["peers"] = {peer: dict(c) for peer, c in peers.items()}
                out[plane] = entry
            return out


def _valid_name(peer: str) -> bool:
    try:
        check_name("peer", peer)
    except ValueError:
        return False
    return True
