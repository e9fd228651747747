"""Message accounting per plane and per peer: sent, received, rejected (by reason), dropped
(by reason). Every loss the fabric sees is counted here, so status can show it and tests can
check that nothing vanished silently."""

from __future__ import annotations

import threading
from collections import defaultdict
from typing import Any


class Accounting:
    """Thread-safe counters, written from Zenoh callbacks and lane threads alike."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        # plane -> counter name -> value
        self._plane: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
        # plane -> peer -> counter name -> value
        self._peer: dict[str, dict[str, dict[str, int]]] = defaultdict(lambda: defaultdict(lambda: defaultdict(int)))
        # (plane, peer) -> (plane counters, peer counters): the per-message fast path
        self._pairs: dict[tuple[str, str | None], tuple[dict[str, int], dict[str, int] | None]] = {}

    def add(self, plane: str, counter: str, peer: str | None = None, n: int = 1, nbytes: int = 0) -> None:
        with self._lock:
            p = self._plane[plane]
            p[counter] += n
            if nbytes:
                p[counter + "_bytes"] += nbytes
            if peer is not None:
                q = self._peer[plane][peer]
                q[counter] += n
                if nbytes:
                    q[counter + "_bytes"] += nbytes

    def _counters(self, plane: str, peer: str | None) -> tuple[dict[str, int], dict[str, int] | None]:
        """The counter dicts of a plane and of one of its peers (created on first use)."""
        with self._lock:
            pair = (self._plane[plane], None if peer is None else self._peer[plane][peer])
        self._pairs[(plane, peer)] = pair
        return pair

    def _count(self, counter: str, counter_bytes: str, plane: str, nbytes: int, peer: str | None) -> None:
        # The per-message path (every chunk on the data plane): the counter dicts come from one
        # lookup, not four nested ones, and the byte counter's name is not built per call.
        p, q = self._pairs.get((plane, peer)) or self._counters(plane, peer)
        with self._lock:
            p[counter] += 1
            if nbytes:
                p[counter_bytes] += nbytes
            if q is not None:
                q[counter] += 1
                if nbytes:
                    q[counter_bytes] += nbytes

    def sent(self, plane: str, nbytes: int, peer: str | None = None) -> None:
        self._count("sent", "sent_bytes", plane, nbytes, peer)

    def received(self, plane: str, nbytes: int, peer: str | None = None) -> None:
        self._count("received", "received_bytes", plane, nbytes, peer)

    def rejected(self, plane: str, reason: str, peer: str | None = None) -> None:
        """A message that failed decoding or verification (never applied)."""
        self.add(plane, "rejected", peer)
        self.add(plane, f"rejected.{reason}", peer)

    def dropped(self, plane: str, reason: str, peer: str | None = None, n: int = 1) -> None:
        """A valid message deliberately not used (stale, backpressure, ...)."""
        self.add(plane, "dropped", peer, n)
        self.add(plane, f"dropped.{reason}", peer, n)

    def get(self, plane: str, counter: str, peer: str | None = None) -> int:
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
