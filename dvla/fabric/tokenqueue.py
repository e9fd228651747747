"""A bounded FIFO for hand-offs between threads, without Python-level locking.

``queue.Queue`` guards its bound with a ``threading.Condition`` written in Python: every put and
get juggles locks under the GIL, on the receive thread and on every lane's hand-off alike.
:class:`TokenQueue` is two C-implemented ``queue.SimpleQueue`` instead: one holds the items, the
other one token per free slot. A put takes a token (the bounded wait for space) and then
enqueues; a get dequeues and gives a token back. Both the fabric's
:class:`~dvla.fabric.fabric.Inbox` and the roles' :class:`~dvla.roles.swimlane.BoundedQueue`
are built on it.
"""

from __future__ import annotations

import queue
from typing import Generic, TypeVar

T = TypeVar("T")


class TokenQueue(Generic[T]):
    """Bounded FIFO of non-None items; ``None`` is what :meth:`get` returns when none came."""

    def __init__(self, maxsize: int) -> None:
        self.maxsize = maxsize
        self._items: queue.SimpleQueue[T] = queue.SimpleQueue()
        self._room: queue.SimpleQueue[None] = queue.SimpleQueue()
        for _ in range(maxsize):
            self._room.put(None)

    def put(self, item: T, timeout: float | None = 0.0) -> bool:
        """Enqueue ``item`` once a slot is free, waiting up to ``timeout`` seconds (0: not at
        all, None: for ever); False when no slot became free."""
        try:
            if timeout == 0:
                self._room.get_nowait()
            else:
                self._room.get(timeout=timeout)
        except queue.Empty:
            return False
        self._items.put(item)
        return True

    def get(self, timeout: float | None = 0.0) -> T | None:
        """The oldest item, waiting up to ``timeout`` seconds (0: not at all, None: for ever);
        None when nothing came."""
        try:
            item = self._items.get_nowait() if timeout == 0 else self._items.get(timeout=timeout)
        except queue.Empty:
            return None
        self._room.put(None)
        return item

    def qsize(self) -> int:
        """Items queued right now."""
        return self._items.qsize()
