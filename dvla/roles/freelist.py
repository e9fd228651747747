"""A pool's free items: a lane takes one (waiting while none is free, until told to stop),
uses it and gives it back. The actor's trajectory slots and the rollouts' chunk buffers are
both pools of this kind."""

from __future__ import annotations

import queue
import threading
from typing import Generic, Iterable, TypeVar

T = TypeVar("T")


class FreeList(Generic[T]):
    """The free items of a pool whose items are all made up front."""

    def __init__(self, items: Iterable[T], poll_s: float = 0.05) -> None:
        self._free: queue.SimpleQueue[T] = queue.SimpleQueue()
        self._poll_s = poll_s
        for item in items:
            self._free.put(item)

    def take(self, stop: threading.Event) -> T | None:
        """A free item, waiting while every one is out; None once `stop` is set."""
        while not stop.is_set():
            try:
                return self._free.get(timeout=self._poll_s)
            except queue.Empty:
                continue
        return None

    def give(self, item: T) -> None:
        """Return an item taken from this pool."""
        self._free.put(item)

    def free(self) -> int:
        """Items available now."""
        return self._free.qsize()
