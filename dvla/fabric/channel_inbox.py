"""`ChannelInbox`: the trajectory plane's bounded hand-off, with no Python code on Zenoh's threads.

A Python callback on Zenoh's receive thread costs the receiving process a GIL hand-over per
message between that thread and the lane that consumes (two Python threads taking turns): at
thousands of 64 KiB chunks per second that hand-over cost more CPU than Zenoh itself. Here
Zenoh's receive task pushes samples into a bounded FIFO channel implemented in Rust
(`zenoh.handlers.FifoChannel`), and only the consuming lane touches them from Python: it copies
each payload out, counts it and decodes it in `get`.

- **Backpressure**: when the channel is full, Zenoh's receive task waits, which stops it
  reading the link; TCP backpressure then slows the sender down through its BLOCK congestion
  control, exactly as `Inbox` does.
- **Never stalled for long**: a watchdog thread keeps `Inbox`'s promise. While the lane has not
  been in `get` for `block_s` and messages wait, it takes them out and drops them, counted as
  `dropped.backpressure`, so a stalled lane holds Zenoh's receive task for at most about
  `block_s` (plus half of it, the watchdog's period).
- **Accounting**: a message is `received` when it leaves the channel (taken by the lane or
  dropped by the watchdog); messages still inside the channel are in flight, at most `maxsize`.
"""

from __future__ import annotations

import threading
import time
from typing import Any, Callable

import zenoh

from .accounting import Accounting
from .keys import KeySpace


class ChannelInbox:
    """Bounded inbox of decoded messages from one subscription (see the module docstring)."""

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        maxsize: int,
        decoder: Callable[[str, bytes], Any],
        accounting: Accounting,
        plane: str,
        block_s: float = 1.0,
        name: str = "inbox",
    ) -> None:
        if maxsize < 1:
            raise ValueError(f"maxsize must be >= 1, got {maxsize}")
        self.maxsize = maxsize
        #: messages the lane found waiting at once (a lower bound of the channel's peak depth)
        self.high_watermark = 0
        self._decoder = decoder
        self._acct = accounting
        self._plane = plane
        self._block_s = block_s
        self._lock = threading.Lock()
        self._last_seen = time.monotonic()  # when the lane last took a message or found none
        self._run = 0  # messages taken in a row without finding the channel empty
        self._closed = threading.Event()
        self._sub = session.declare_subscriber(key, zenoh.handlers.FifoChannel(maxsize))
        self._watchdog = threading.Thread(target=self._watch, name=f"{name}-watchdog", daemon=True)
        self._watchdog.start()

    # -- the lane's side ----------------------------------------------------------------------
    def _take(self) -> tuple[str, bytes] | None:
        sample = self._sub.try_recv()
        if sample is None:
            return None
        key = str(sample.key_expr)
        raw = sample.payload.to_bytes()
        self._acct.received(self._plane, len(raw), KeySpace.last(key))
        return key, raw

    def get(self, timeout: float | None = None) -> Any | None:
        """Next valid message, or None after `timeout`. Invalid ones are counted and skipped.

        Waiting polls the channel with a sleep growing from 0.2 to 5 ms (the channel cannot be
        waited on with a timeout); messages already waiting are returned at once. Past the
        deadline at most ``maxsize`` more queued messages are looked at, as with `Inbox`.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        delay = 0.0002
        late = 0
        while True:
            with self._lock:
                item = self._take()
                now = time.monotonic()
                self._last_seen = now
                if item is None:
                    self._run = 0
                else:
                    self._run += 1
                    if self._run > self.high_watermark:
                        self.high_watermark = min(self._run, self.maxsize)
            if item is not None:
                msg = self._decoder(*item)
                if msg is not None:
                    return msg
                if deadline is not None and now >= deadline:
                    late += 1
                    if late > self.maxsize:
                        return None
                continue
            if self._closed.is_set() or (deadline is not None and now >= deadline):
                return None
            pause = delay if deadline is None else min(delay, max(0.0, deadline - now))
            time.sleep(pause)
            delay = min(delay * 2, 0.005)

    def get_nowait(self) -> Any | None:
        return self.get(timeout=0.0)

    def depth(self) -> int:
        """Messages taken from Zenoh and not yet handed to the lane: always 0 here (each is
        decoded and returned as it is taken); what waits inside the channel (at most
        ``maxsize``) cannot be observed."""
        return 0

    def drain_count(self) -> int:
        """Discard what waits in the channel (at shutdown); returns how many were discarded
        (counted as received; the caller counts them as dropped, as with `Inbox`)."""
        n = 0
        with self._lock:
            while self._take() is not None:
                n += 1
        return n

    # -- the watchdog -------------------------------------------------------------------------
    def _watch(self) -> None:
        period = min(max(self._block_s / 2, 0.005), 0.25)
        while not self._closed.wait(period):
            if time.monotonic() - self._last_seen < self._block_s:
                continue
            with self._lock:  # the lane is away: keep Zenoh reading, count what it misses
                while (item := self._take()) is not None:
                    self._acct.dropped(self._plane, "backpressure", KeySpace.last(item[0]))

    def close(self) -> None:
        self._closed.set()
        self._watchdog.join(timeout=2.0)
        try:
            self._sub.undeclare()
        except Exception:
            pass
