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

    def add(self, plane: str, counter: str, peer: str | None = None, n: int = 1, nbytes: int = 0) -> None:
        """Count `n` messages (of `nbytes` bytes in all, kept as ``<counter>_bytes``)."""
        with self._lock:
            _bump(self._plane[plane], counter, n, nbytes)
            if peer is not None:
                _bump(self._peer[plane][peer], counter, n, nbytes)

    def sent(self, plane: str, nbytes: int, peer: str | None = None) -> None:
        self.add(plane, "sent", peer, 1, nbytes)

    def received(self, plane: str, nbytes: int, peer: str | None = None) -> None:
        self.add(plane, "received", peer, 1, nbytes)

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


def _bump(counters: dict[str, int], counter: str, n: int, nbytes: int) -> None:
    counters[counter] += n
    if nbytes:
        counters[counter + "_bytes"] += nbytes
