"""Swimlanes: the named worker threads every role process runs, and their plumbing.

A role overlaps its work on a few named *lanes* (a rollout: ``sim``, ``infer``, ``ship``,
``sync``), each a thread looping until a shared stop event is set. An exception in any lane is
logged, kept as :attr:`Swimlane.error` and stops every lane: a role never limps on with a dead
thread. Lanes hand work over only through :class:`BoundedQueue`, whose waits end when the stop
event is set and are charged to the waiting lane's :class:`LaneStats`.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import os
import queue
import threading
import time
import traceback
from collections.abc import Callable, Iterable, Iterator
from typing import Any, ContextManager, Generic, TypeVar

__all__ = [
    "BoundedQueue", "LaneContext", "LaneError", "LaneStats", "Swimlane", "current_lane",
    "sample_percentile", "pin_cpus", "set_torch_threads",
]

log = logging.getLogger("dvla.swimlane")

T = TypeVar("T")

WAIT_SLICE_S = 0.05
"""Longest single blocking wait; a set stop event is noticed within this many seconds."""

DEFAULT_WINDOW_S = 10.0
"""Sliding window of :meth:`LaneStats.snapshot` rates (seconds)."""

_SAMPLES_PER_WINDOW = 20
"""How many (time, counters) samples a window keeps; bounds memory and sampling cost."""


class LaneStats:
    """Counters of one lane: busy and waiting seconds, items done, errors.

    Written by the lane's own thread only (no lock on the hot path), read through :meth:`snapshot`.
    Waiting inside a busy section pauses the busy clock, so ``busy_s`` is work, not blocking.
    """

    def __init__(
        self,
        window_s: float = DEFAULT_WINDOW_S,
        clock: Callable[[], float] = time.perf_counter,
    ) -> None:
        if window_s <= 0:
            raise ValueError(f"window_s must be > 0, got {window_s}")
        self._clock = clock
        self._window_s = window_s
        self._sample_every_s = window_s / _SAMPLES_PER_WINDOW
        self.busy_s = 0.0
        self.wait_s = 0.0
        self.items = 0
        self.errors = 0
        #: wall-clock time (time.time_ns) of the last counted item; 0 before the first
        self.last_item_ns = 0
        self._busy_depth = 0
        self._busy_since: float | None = None
        self._wait_depth = 0
        self._wait_since: float | None = None
        self._started = clock()
        # (time, items, busy_s, wait_s) samples: the oldest one is the window's baseline.
        self._samples: collections.deque[tuple[float, int, float, float]] = collections.deque(
            [(self._started, 0, 0.0, 0.0)]
        )
        self._last_sample_t = self._started
        self._samples_lock = threading.Lock()

    @contextlib.contextmanager
    def busy(self) -> Iterator[None]:
        """``with stats.busy():`` around real work."""
        self._busy_depth += 1
        if self._busy_depth == 1 and self._wait_depth == 0:
            self._busy_since = self._clock()
        try:
            yield
        finally:
            self._busy_depth -= 1
            if self._busy_depth == 0 and self._busy_since is not None:
                now = self._clock()
                self.busy_s += now - self._busy_since
                self._busy_since = None
                self._maybe_sample(now)

    @contextlib.contextmanager
    def waiting(self) -> Iterator[None]:
        """``with stats.waiting():`` around blocking on a queue, a peer or a timer."""
        now = self._clock()
        self._wait_depth += 1
        if self._wait_depth == 1:
            self._wait_since = now
            if self._busy_since is not None:  # pause the busy clock while blocked
                self.busy_s += now - self._busy_since
                self._busy_since = None
        try:
            yield
        finally:
            self._wait_depth -= 1
            if self._wait_depth == 0 and self._wait_since is not None:
                now = self._clock()
                self.wait_s += now - self._wait_since
                self._wait_since = None
                if self._busy_depth > 0:  # resume the enclosing busy section
                    self._busy_since = now
                self._maybe_sample(now)

    def count(self, n: int = 1) -> None:
        """Record ``n`` finished items (steps, batches, messages: the lane decides)."""
        self.items += n
        self.last_item_ns = time.time_ns()
        self._maybe_sample(self._clock())

    def _totals(self, now: float) -> tuple[float, float]:
        """Busy and wait seconds including a section still open at ``now``."""
        busy = self.busy_s
        since = self._busy_since
        if since is not None:
            busy += max(0.0, now - since)
        wait = self.wait_s
        since = self._wait_since
        if since is not None:
            wait += max(0.0, now - since)
        return busy, wait

    def _maybe_sample(self, now: float) -> None:
        """Append a window sample at most every ``window/20`` seconds and drop stale ones."""
        if now - self._last_sample_t < self._sample_every_s:
            return
        with self._samples_lock:
            if now - self._last_sample_t < self._sample_every_s:
                return
            busy, wait = self._totals(now)
            self._samples.append((now, self.items, busy, wait))
            self._last_sample_t = now
            self._prune(now)

    def _prune(self, now: float) -> None:
        # Keep exactly one sample at or before the window start: it is the rate baseline.
        horizon = now - self._window_s
        samples = self._samples
        while len(samples) >= 2 and samples[1][0] <= horizon:
            samples.popleft()

    def reading(self) -> dict[str, float | int]:
        """Counters plus rates over the last ``window_s`` seconds (or since start if shorter).

        Keys: ``busy_s``, ``wait_s``, ``items``, ``errors`` (totals since start);
        ``items_per_s``, ``utilisation`` (busy fraction), ``wait_fraction`` (over the window);
        ``uptime_s``; ``last_item_ns`` and ``last_item_age_s`` (-1.0 before the first item).
        """
        now = self._clock()
        self._maybe_sample(now)
        busy, wait = self._totals(now)
        items = self.items
        with self._samples_lock:
            self._prune(now)
            base_t, base_items, base_busy, base_wait = self._samples[0]
        span = now - base_t
        last_ns = self.last_item_ns
        return {
            "busy_s": busy,
            "wait_s": wait,
            "items": items,
            "errors": self.errors,
            "items_per_s": (items - base_items) / span if span > 0 else 0.0,
            "utilisation": _fraction(busy - base_busy, span),
            "wait_fraction": _fraction(wait - base_wait, span),
            "uptime_s": now - self._started,
            "last_item_ns": last_ns,
            "last_item_age_s": (time.time_ns() - last_ns) / 1e9 if last_ns else -1.0,
        }


def _fraction(part: float, whole: float) -> float:
    """``part / whole`` clamped to [0, 1] (sampling jitter must not report 101% busy)."""
    if whole <= 0:
        return 0.0
    return min(1.0, max(0.0, part / whole))


class BoundedQueue(Generic[T]):
    """A bounded FIFO with stop-aware, accounted waits.

    ``put``/``get`` block in :data:`WAIT_SLICE_S` slices and give up once the stop event is set;
    blocking is charged to the calling lane's ``wait_s``. ``None`` is what ``get`` returns when
    stopped or timed out, so it is not a valid item.
    """

    def __init__(self, maxsize: int, name: str = "") -> None:
        if not isinstance(maxsize, int) or maxsize < 1:
            raise ValueError(f"BoundedQueue {name!r}: maxsize must be an int >= 1, got {maxsize!r}")
        self.name = name
        self.maxsize = maxsize
        self._q: queue.Queue[T] = queue.Queue(maxsize)

    @property
    def depth(self) -> int:
        """Items queued right now."""
        return self._q.qsize()

    def put(
        self, item: T, stop: threading.Event, *, timeout: float | None = None, stats: LaneStats | None = None
    ) -> bool:
        """Enqueue ``item``, waiting while full; False if ``stop`` was set or ``timeout`` passed."""
        if item is None:
            raise ValueError(f"BoundedQueue {self.name!r}: None is reserved as the stop result")
        if stop.is_set():
            return False
        try:
            self._q.put_nowait(item)
            return True
        except queue.Full:
            return self._blocking(lambda wait: self._q.put(item, timeout=wait), queue.Full, stop, timeout, stats)[0]

    def get(
        self, stop: threading.Event, *, timeout: float | None = None, stats: LaneStats | None = None
    ) -> T | None:
        """Dequeue an item, waiting while empty; None if ``stop`` was set or ``timeout`` passed."""
        if stop.is_set():
            return None
        item = self.get_nowait()
        if item is not None:
            return item
        return self._blocking(lambda wait: self._q.get(timeout=wait), queue.Empty, stop, timeout, stats)[1]

    def _blocking(self, call: Callable[[float], Any], retry: type[Exception], stop: threading.Event,
                  timeout: float | None, stats: LaneStats | None) -> tuple[bool, Any]:
        """(True, ``call(wait)``) once a slice's call succeeds; (False, None) on stop or timeout."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with _wait_section(stats):
            while not stop.is_set():
                wait = _slice_until(WAIT_SLICE_S, deadline)
                if wait <= 0:
                    break
                try:
                    return True, call(wait)
                except retry:
                    pass
        return False, None

    def get_nowait(self) -> T | None:
        """Dequeue an item if one is ready, else None (for draining on shutdown)."""
        try:
            return self._q.get_nowait()
        except queue.Empty:
            return None


def _slice_until(slice_s: float, deadline: float | None) -> float:
    """Next wait length: one slice, shortened to end at ``deadline``."""
    if deadline is None:
        return slice_s
    return min(slice_s, deadline - time.monotonic())


def _wait_section(stats: LaneStats | None) -> ContextManager[None]:
    """The waiting section to charge: explicit stats, else the current lane's, else none."""
    if stats is None:
        ctx = current_lane()
        stats = ctx.stats if ctx is not None else None
    return stats.waiting() if stats is not None else contextlib.nullcontext()


_local = threading.local()


def current_lane() -> LaneContext | None:
    """The :class:`LaneContext` of the calling lane thread, or None outside a lane."""
    return getattr(_local, "lane", None)


class LaneError(RuntimeError):
    """The first exception raised by a lane, with the role and lane it came from."""

    def __init__(self, role: str, lane: str, exc: BaseException) -> None:
        super().__init__(f"{role}/{lane}: {type(exc).__name__}: {exc}")
        self.role = role
        self.lane = lane
        self.exc = exc
        self.traceback = "".join(traceback.format_exception(exc))


class LaneContext:
    """What a lane target gets: its name, the role-wide stop event and its own stats."""

    def __init__(self, role: str, name: str, stop: threading.Event, stats: LaneStats) -> None:
        self.role = role
        self.name = name
        self.stop = stop
        self.stats = stats

    @property
    def running(self) -> bool:
        """True until the role is stopping; lane loops are ``while ctx.running:``."""
        return not self.stop.is_set()

    def busy(self) -> ContextManager[None]:
        """``with ctx.busy():`` around real work."""
        return self.stats.busy()

    def waiting(self) -> ContextManager[None]:
        """``with ctx.waiting():`` around blocking that is not a :class:`BoundedQueue` call."""
        return self.stats.waiting()

    def count(self, n: int = 1) -> None:
        """Record ``n`` finished items."""
        self.stats.count(n)

    def sleep(self, seconds: float) -> bool:
        """Sleep up to ``seconds``, returning early (False) when the role stops; True otherwise.

        Not charged as busy or waiting: wrap it in ``waiting()`` if the pause is a wait.
        """
        if seconds <= 0:
            return not self.stop.is_set()
        return not self.stop.wait(seconds)


LaneTarget = Callable[[LaneContext], None]


class _Lane:
    """A registered lane: its context, target and thread."""

    def __init__(self, ctx: LaneContext, target: LaneTarget) -> None:
        self.ctx = ctx
        self.target = target
        self.thread: threading.Thread | None = None
        #: cores this lane's thread pins itself to when it starts (None: the process's)
        self.cpus: tuple[int, ...] | None = None
        #: the thread's CPU affinity once it runs (None: not started, or not reported here)
        self.affinity: list[int] | None = None
        #: the thread's CPU-time clock (readable from any thread; None where the OS has none)
        self.cpu_clock: int | None = None
        #: CPU seconds the thread had used when it ended (its clock is gone with it)
        self.cpu_s_final: float | None = None

    def cpu_s(self) -> float | None:
        """CPU seconds of the lane's thread so far (None where the OS cannot tell)."""
        if self.cpu_s_final is None and self.cpu_clock is not None:
            try:
                return time.clock_gettime(self.cpu_clock)
            except OSError:  # the thread ended between the check and the read
                pass
        return self.cpu_s_final


class Swimlane:
    """The lanes of one role: register, start, wait, stop, join; fail fast on any lane error.

    Typical use::

        with Swimlane("rollout") as sl:
            sl.lane("sim", sim_loop)
            sl.lane("infer", infer_loop)
            sl.start()
            sl.wait()          # until a lane fails, a lane ends, or stop() is called
        if sl.error: ...       # the first LaneError, already logged
    """

    def __init__(self, role: str, *, window_s: float = DEFAULT_WINDOW_S) -> None:
        self.role = role
        self.stop_event = threading.Event()
        self.error: LaneError | None = None
        self._window_s = window_s
        self._lanes: dict[str, _Lane] = {}
        self._error_lock = threading.Lock()
        self._started = False

    def lane(self, name: str, target: LaneTarget) -> LaneContext:
        """Register lane ``name`` running ``target(ctx)``; returns its context. A target that
        returns before stop is set stops the role (cleanly, no error): a lane that quietly ended
        would otherwise stall the pipeline."""
        if self._started:
            raise RuntimeError(f"swimlane {self.role!r}: cannot add lane {name!r} after start()")
        if not name or name in self._lanes:
            raise ValueError(f"swimlane {self.role!r}: lane name {name!r} is empty or taken")
        ctx = LaneContext(self.role, name, self.stop_event, LaneStats(self._window_s))
        self._lanes[name] = _Lane(ctx, target)
        return ctx

    def queue(self, name: str, maxsize: int) -> BoundedQueue[Any]:
        """A :class:`BoundedQueue` for a hand-off between two of this role's lanes."""
        return BoundedQueue(maxsize, f"{self.role}/{name}")

    def pin(self, lane_cpus: dict[str, Iterable[int]]) -> None:
        """Pin lanes to cores of their own (``{"sim": [0]}``), applied by each lane's thread as it
        starts. ValueError names a lane this role does not have or an empty set; a pinning the OS
        refuses fails that lane when it starts (stopping the role with an error naming it).
        """
        if self._started:
            raise RuntimeError(f"swimlane {self.role!r}: pin() after start()")
        for name, cpus in lane_cpus.items():
            if name not in self._lanes:
                have = ", ".join(self._lanes) or "none"
                raise ValueError(f"swimlane {self.role!r}: lane_cpus names lane {name!r}, which this role does not "
                                 f"run (its lanes: {have})")
            wanted = tuple(sorted({int(c) for c in cpus}))
            if not wanted:
                raise ValueError(f"swimlane {self.role!r}: lane_cpus.{name} is empty")
            self._lanes[name].cpus = wanted

    def affinity(self) -> dict[str, list[int] | None]:
        """Each lane's CPU affinity as its thread found it after pinning (None before it runs)."""
        return {name: lane.affinity for name, lane in self._lanes.items()}

    def start(self) -> None:
        """Start one daemon thread per lane, named ``"{role}/{lane}"``."""
        if self._started:
            raise RuntimeError(f"swimlane {self.role!r}: already started")
        if not self._lanes:
            raise ValueError(f"swimlane {self.role!r}: no lanes registered")
        self._started = True
        for lane in self._lanes.values():
            # Daemon: a lane stuck in foreign code must not keep the process alive; join()
            # reports it instead.
            lane.thread = threading.Thread(
                target=self._run_lane,
                args=(lane,),
                name=f"{self.role}/{lane.ctx.name}",
                daemon=True,
            )
            lane.thread.start()

    def _run_lane(self, lane: _Lane) -> None:
        ctx = lane.ctx
        _local.lane = ctx
        _name_os_thread(ctx.name)
        getclock = getattr(time, "pthread_getcpuclockid", None)  # readable from any thread
        lane.cpu_clock = getclock(threading.get_ident()) if getclock else None
        try:
            if lane.cpus is not None:
                pin_cpus(lane.cpus)
            if hasattr(os, "sched_getaffinity"):
                lane.affinity = sorted(os.sched_getaffinity(0))
            lane.target(ctx)
        except BaseException as exc:  # noqa: BLE001 - any lane failure must stop the role
            self._fail(ctx, exc)
        else:
            if not self.stop_event.is_set():
                log.info("lane %s/%s returned; stopping the role", self.role, ctx.name)
                self.stop_event.set()
        finally:
            _local.lane = None
            lane.cpu_s_final = time.thread_time()

    def _fail(self, ctx: LaneContext, exc: BaseException) -> None:
        ctx.stats.errors += 1
        log.error(
            "lane %s/%s failed: %s: %s; stopping all lanes",
            self.role, ctx.name, type(exc).__name__, exc, exc_info=exc,
        )
        with self._error_lock:
            if self.error is None:
                self.error = LaneError(self.role, ctx.name, exc)
        self.stop_event.set()

    def stop(self) -> None:
        """Ask every lane to finish (sets the shared stop event; does not wait)."""
        self.stop_event.set()

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the role is stopping (or ``timeout``); True if stop is set.

        Waits in short slices so the main thread stays responsive to signals.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self.stop_event.is_set():
            wait = _slice_until(0.1, deadline)
            if wait <= 0:
                break
            self.stop_event.wait(wait)
        return self.stop_event.is_set()

    def join(self, timeout: float = 2.0) -> list[str]:
        """Join every lane within ``timeout`` seconds in total; return lanes still running."""
        deadline = time.monotonic() + timeout
        stuck: list[str] = []
        for name, lane in self._lanes.items():
            if lane.thread is None:
                continue
            lane.thread.join(max(0.0, deadline - time.monotonic()))
            if lane.thread.is_alive():
                stuck.append(name)
        if stuck:
            log.warning("swimlane %s: lanes did not exit within %.1fs: %s",
                        self.role, timeout, ", ".join(stuck))
        return stuck

    def close(self, timeout: float = 2.0) -> list[str]:
        """stop() then join(); returns lanes that did not exit."""
        self.stop()
        return self.join(timeout)

    def __enter__(self) -> Swimlane:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def state(self) -> str:
        """``"idle"`` (not started), ``"running"``, ``"stopped"`` or ``"error"``."""
        if self.error is not None:
            return "error"
        if not self._started:
            return "idle"
        return "stopped" if self.stop_event.is_set() else "running"

    def stats(self) -> dict[str, dict[str, Any]]:
        """Per-lane :meth:`LaneStats.snapshot`, plus ``alive`` and the CPU seconds its thread has
        used (``cpu_s``: busy time is wall time, shared cores show in CPU time)."""
        out: dict[str, dict[str, Any]] = {}
        for name, lane in self._lanes.items():
            snap: dict[str, Any] = dict(lane.ctx.stats.reading())
            snap["alive"] = lane.thread is not None and lane.thread.is_alive()
            cpu = lane.cpu_s()
            if cpu is not None:
                snap["cpu_s"] = cpu
            out[name] = snap
        return out

def sample_percentile(values: list, q: float) -> float:
    """Nearest-rank ``q``-quantile (0-1) of ``values``; 0.0 for none."""
    s = sorted(values)
    return float(s[min(len(s) - 1, int(len(s) * q))]) if s else 0.0



def _name_os_thread(lane: str) -> None:
    """Name the calling thread ``dvla:<lane>`` for the OS (``top -H``, ``ps -L``; the kernel keeps
    15 bytes). Linux only; elsewhere the thread keeps its name."""
    try:
        with open(f"/proc/self/task/{threading.get_native_id()}/comm", "w") as comm:
            comm.write(f"dvla:{lane}"[:15])
    except OSError:
        pass


def pin_cpus(cpus: Iterable[int]) -> set[int] | None:
    """Restrict the calling thread (and threads it starts later) to ``cpus``.

    Call it before ``Swimlane.start()`` to pin the whole role, or inside a lane to pin just that
    lane. Returns the resulting affinity, or None (with a warning) where affinity is unsupported.
    """
    wanted = {int(c) for c in cpus}
    if not wanted:
        raise ValueError("pin_cpus: empty CPU set")
    setter = getattr(os, "sched_setaffinity", None)
    if setter is None:
        log.warning("pin_cpus: CPU affinity is not supported on this platform; not pinning")
        return None
    try:
        setter(0, wanted)
    except OSError as exc:
        allowed = sorted(os.sched_getaffinity(0))
        raise ValueError(
            f"pin_cpus: cannot pin to {sorted(wanted)} (allowed: {allowed}): {exc}"
        ) from exc
    return set(os.sched_getaffinity(0))


def set_torch_threads(n: int, interop: int | None = 1) -> dict[str, int] | None:
    """Set torch intra-op threads to ``n`` and inter-op threads to ``interop`` (1: the lanes are
    the concurrency); torch refuses the latter after its first parallel work, which is logged.
    Returns the effective ``{"intra": .., "interop": ..}``, or None if torch is not installed.
    """
    if n < 1:
        raise ValueError(f"set_torch_threads: n must be >= 1, got {n}")
    if interop is not None and interop < 1:
        raise ValueError(f"set_torch_threads: interop must be >= 1, got {interop}")
    try:
        import torch
    except ImportError:
        log.warning("set_torch_threads: torch is not installed; nothing to set")
        return None
    torch.set_num_threads(n)
    if interop is not None and torch.get_num_interop_threads() != interop:
        try:
            torch.set_num_interop_threads(interop)
        except RuntimeError as exc:
            log.warning("set_torch_threads: inter-op threads stay at %d: %s",
                        torch.get_num_interop_threads(), exc)
    return {"intra": torch.get_num_threads(), "interop": torch.get_num_interop_threads()}
