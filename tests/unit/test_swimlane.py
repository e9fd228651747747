"""Unit tests of dvla.roles.swimlane: fail-fast lanes, prompt shutdown, bounded queues, stats."""

from __future__ import annotations

import functools
import json
import logging
import os
import re
import sys
import threading
import time
import types

import pytest

from dvla.roles import swimlane as swimlane_module
from dvla.roles.swimlane import (
    BoundedQueue,
    LaneContext,
    LaneError,
    LaneStats,
    Swimlane,
    current_lane,
    pin_cpus,
    set_torch_threads,
)

class FakeClock:
    """A settable clock so window arithmetic is tested exactly, not against wall time."""

    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


class TickClock:
    """A clock that moves one tick (1.0) per reading, from any thread: a section's seconds are
    the readings taken while it was open, so the accounting is tested whatever this machine's speed."""

    def __init__(self) -> None:
        self.t = 1000.0
        self._lock = threading.Lock()

    def __call__(self) -> float:
        with self._lock:
            self.t += 1.0
            return self.t


def _lanes_on(monkeypatch: pytest.MonkeyPatch, clock: object) -> None:
    """Lanes registered from now on keep their stats on `clock`."""
    monkeypatch.setattr(swimlane_module, "LaneStats", functools.partial(LaneStats, clock=clock))


def _time_at(clock: FakeClock) -> types.SimpleNamespace:
    """The `time` module as dvla.roles.swimlane sees it, its wall clock (time_ns) at `clock`."""
    fake = types.SimpleNamespace(**{k: getattr(time, k) for k in dir(time) if not k.startswith("_")})
    fake.time_ns = lambda: round(clock.t * 1e9)
    return fake


def _idle(ctx: LaneContext) -> None:
    while ctx.running:
        ctx.sleep(0.01)


# -- lanes --------------------------------------------------------------------------------------


def test_lane_exception_stops_all_lanes_and_names_the_lane(
    caplog: pytest.LogCaptureFixture,
) -> None:
    def boom(ctx: LaneContext) -> None:
        ctx.sleep(0.1)
        raise ValueError("sim exploded")

    sl = Swimlane("rollout")
    for name in ("infer", "ship", "sync"):
        sl.lane(name, _idle)
    sl.lane("sim", boom)
    with caplog.at_level(logging.ERROR, logger="dvla.swimlane"):
        sl.start()
        assert sl.wait(timeout=3.0), "a failing lane must set the stop event"
        stuck = sl.join(timeout=30.0)
    assert stuck == []
    assert isinstance(sl.error, LaneError)
    assert sl.error.lane == "sim" and sl.error.role == "rollout"
    assert "rollout/sim" in str(sl.error) and "sim exploded" in str(sl.error)
    assert isinstance(sl.error.exc, ValueError)
    assert "raise ValueError" in sl.error.traceback
    assert sl.state == "error"
    stats = sl.stats()
    assert stats["sim"]["errors"] == 1 and stats["infer"]["errors"] == 0
    assert not any(s["alive"] for s in stats.values())
    records = [
        r for r in caplog.records if r.name == "dvla.swimlane" and r.levelno == logging.ERROR
    ]
    assert len(records) == 1
    assert "rollout/sim" in records[0].getMessage()
    assert records[0].exc_info is not None and records[0].exc_info[0] is ValueError


def test_first_error_wins() -> None:
    def fail_first(ctx: LaneContext) -> None:
        raise KeyError("first")

    def fail_later(ctx: LaneContext) -> None:
        ctx.stop.wait(2.0)
        raise RuntimeError("second")

    sl = Swimlane("actor")
    sl.lane("a", fail_first)
    sl.lane("b", fail_later)
    sl.start()
    sl.wait(timeout=2.0)
    assert sl.join() == []
    assert sl.error is not None and sl.error.lane == "a"
    assert sl.stats()["b"]["errors"] == 1


def test_stop_joins_four_blocked_lanes_quickly(monkeypatch: pytest.MonkeyPatch) -> None:
    _lanes_on(monkeypatch, TickClock())
    empty: BoundedQueue[int] = BoundedQueue(2, "empty")
    full: BoundedQueue[int] = BoundedQueue(1, "full")
    assert full.put(0, threading.Event())
    entered = threading.Barrier(5, timeout=2.0)
    thread_names: list[str] = []

    def getter(ctx: LaneContext) -> None:
        thread_names.append(threading.current_thread().name)
        entered.wait()
        assert empty.get(ctx.stop) is None

    def putter(ctx: LaneContext) -> None:
        entered.wait()
        assert full.put(1, ctx.stop) is False

    def sleeper(ctx: LaneContext) -> None:
        entered.wait()
        assert ctx.sleep(60.0) is False

    def waiter(ctx: LaneContext) -> None:
        entered.wait()
        with ctx.waiting():
            ctx.stop.wait(60.0)

    sl = Swimlane("rollout")
    for name, fn in (("sim", getter), ("infer", putter), ("ship", sleeper), ("sync", waiter)):
        sl.lane(name, fn)
    sl.start()
    entered.wait()
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and not all(sl.stats()[n]["wait_s"] for n in ("sim", "infer", "sync")):
        time.sleep(0.01)  # let every lane actually block (an open wait counts in its reading)
    assert all(sl.stats()[n]["wait_s"] for n in ("sim", "infer", "sync")), sl.stats()
    assert all(s["alive"] for s in sl.stats().values())
    assert sl.state == "running"
    sl.stop()
    stuck = sl.join(timeout=30.0)  # their waits are 60 s: only stop ends them
    assert stuck == []
    assert sl.error is None, sl.error
    assert sl.state == "stopped"
    assert thread_names == ["rollout/sim"]
    # Blocking queue waits were charged to the lanes that blocked (ticks of the injected clock).
    stats = sl.stats()
    assert stats["sim"]["wait_s"] >= 1 and stats["infer"]["wait_s"] >= 1
    assert stats["sync"]["wait_s"] >= 1
    assert stats["ship"]["wait_s"] == 0.0  # ctx.sleep is not charged


def test_join_reports_a_lane_that_ignores_stop() -> None:
    release = threading.Event()

    def stubborn(ctx: LaneContext) -> None:
        release.wait(60.0)

    sl = Swimlane("replicator")
    sl.lane("fanout", stubborn)
    sl.lane("recv", _idle)
    sl.start()
    sl.stop()
    stuck = sl.join(timeout=0.3)
    assert stuck == ["fanout"]
    assert sl.stats()["fanout"]["alive"]  # join gave up on its timeout, not on the lane's end
    release.set()
    assert sl.join(timeout=2.0) == []


def test_lane_returning_stops_the_role_cleanly() -> None:
    sl = Swimlane("rollout")
    sl.lane("once", lambda ctx: ctx.count(3))
    sl.lane("loop", _idle)
    sl.start()
    assert sl.wait(timeout=2.0)
    assert sl.join() == []
    assert sl.error is None and sl.state == "stopped"
    assert sl.stats()["once"]["items"] == 3


def test_context_manager_stops_and_joins() -> None:
    with Swimlane("actor") as sl:
        ctx = sl.lane("learn", _idle)
        sl.start()
        assert not sl.wait(timeout=0.1)
        assert sl.stats()["learn"]["alive"]
    assert ctx.stop.is_set()
    assert not sl.stats()["learn"]["alive"]


def test_registration_errors() -> None:
    sl = Swimlane("rollout")
    with pytest.raises(ValueError):
        sl.start()  # no lanes
    sl.lane("sim", _idle)
    with pytest.raises(ValueError):
        sl.lane("sim", _idle)
    sl.start()
    with pytest.raises(RuntimeError):
        sl.lane("late", _idle)
    with pytest.raises(RuntimeError):
        sl.start()
    assert sl.close() == []


def test_current_lane_is_set_only_inside_lane_threads() -> None:
    seen: list[LaneContext | None] = []
    sl = Swimlane("rollout")
    ctx = sl.lane("probe", lambda c: seen.append(current_lane()))
    sl.start()
    sl.wait(timeout=2.0)
    sl.join()
    assert seen == [ctx]
    assert current_lane() is None


# -- queues -------------------------------------------------------------------------------------


def test_queue_stays_bounded_under_fast_producer_slow_consumer(monkeypatch: pytest.MonkeyPatch) -> None:
    _lanes_on(monkeypatch, TickClock())
    n_items, maxsize = 60, 4
    q: BoundedQueue[int] = BoundedQueue(maxsize, "obs")
    received: list[int] = []
    depths: list[int] = []

    def producer(ctx: LaneContext) -> None:
        for i in range(n_items):
            if not q.put(i, ctx.stop):
                return
            depths.append(q.depth)
        while ctx.running:  # stay alive so the role stops only when the consumer is done
            ctx.sleep(0.01)

    def consumer(ctx: LaneContext) -> None:
        while len(received) < n_items:
            item = q.get(ctx.stop)
            if item is None:
                return
            with ctx.busy():
                time.sleep(0.005)
            received.append(item)
            ctx.count()

    sl = Swimlane("rollout")
    sl.lane("sim", producer)
    sl.lane("ship", consumer)
    sl.start()
    assert sl.wait(timeout=5.0)
    assert sl.join() == [] and sl.error is None
    assert received == list(range(n_items))
    assert max(depths) == maxsize  # the producer filled the queue, never beyond
    stats = sl.stats()
    # The producer spent its run blocked on the full queue; the consumer did not. In ticks of the
    # injected clock: each of the consumer's busy sections is at least one.
    assert stats["sim"]["wait_s"] >= 1
    assert stats["ship"]["busy_s"] >= n_items
    assert stats["ship"]["wait_s"] < stats["sim"]["wait_s"]
    assert stats["ship"]["items"] == n_items


def test_queue_timeout_and_stop_without_a_lane() -> None:
    stop = threading.Event()
    q: BoundedQueue[int] = BoundedQueue(1)
    assert q.get(stop, timeout=0.12) is None  # timed out
    stats = LaneStats(clock=TickClock())
    assert q.put(1, stop, stats=stats) is True
    assert stats.wait_s == 0.0  # there was room: no wait
    assert q.put(2, stop, timeout=0.1, stats=stats) is False
    assert stats.wait_s == 1.0  # charged: one tick, from the wait's start to its end
    stop.set()
    assert q.get(stop) is None  # stop wins even with an item queued
    assert q.put(3, stop) is False
    assert q.depth == 1


def test_stop_ends_a_queue_wait_promptly() -> None:
    stop = threading.Event()
    q: BoundedQueue[int] = BoundedQueue(1)
    done = threading.Event()

    def block() -> None:
        q.get(stop)
        done.set()

    t = threading.Thread(target=block, daemon=True)
    t.start()
    time.sleep(0.1)
    assert not done.is_set()
    stop.set()
    assert done.wait(30.0)  # without stop, the get never ends
    t.join(1.0)


def test_queue_rejects_bad_input() -> None:
    for bad in (0, -1, None):
        with pytest.raises(ValueError):
            BoundedQueue(bad)  # type: ignore[arg-type]
    q: BoundedQueue[int | None] = BoundedQueue(1)
    with pytest.raises(ValueError):
        q.put(None, threading.Event())


# -- stats --------------------------------------------------------------------------------------


def test_busy_section_measures_busy_time_and_utilisation(monkeypatch: pytest.MonkeyPatch) -> None:
    clock = FakeClock()
    monkeypatch.setattr(swimlane_module, "time", _time_at(clock))
    stats = LaneStats(clock=clock)
    with stats.busy():
        clock.t += 0.2
    stats.count()
    clock.t += 0.2
    snap = stats.reading()
    assert snap["busy_s"] == pytest.approx(0.2)
    assert snap["wait_s"] == 0.0
    assert snap["items"] == 1
    assert snap["uptime_s"] == pytest.approx(0.4)
    assert snap["utilisation"] == pytest.approx(0.5)  # 0.2 busy of 0.4
    assert snap["last_item_age_s"] == pytest.approx(0.2)


def test_lane_busy_stats_through_swimlane(monkeypatch: pytest.MonkeyPatch) -> None:
    clock = FakeClock()
    _lanes_on(monkeypatch, clock)
    counted = threading.Event()

    def work(ctx: LaneContext) -> None:
        with ctx.busy():
            clock.t += 0.2  # 0.2 s of work
        ctx.count()
        counted.set()
        ctx.sleep(10.0)

    sl = Swimlane("actor")
    sl.lane("learn", work)
    sl.start()
    assert counted.wait(30.0)
    clock.t += 0.1
    snap = sl.stats()["learn"]
    sl.close()
    assert snap["busy_s"] == pytest.approx(0.2)
    assert snap["utilisation"] == pytest.approx(0.2 / 0.3)  # 0.2 busy of 0.3
    assert snap["items"] == 1


def test_waiting_inside_busy_pauses_the_busy_clock() -> None:
    clock = FakeClock()
    stats = LaneStats(clock=clock)
    with stats.busy():
        clock.t += 1.0
        with stats.waiting():
            clock.t += 3.0
        clock.t += 1.0
        with stats.busy():  # nested busy is a no-op, not double counted
            clock.t += 0.5
    snap = stats.reading()
    assert snap["busy_s"] == pytest.approx(2.5)
    assert snap["wait_s"] == pytest.approx(3.0)
    assert snap["utilisation"] == pytest.approx(2.5 / 5.5)
    assert snap["wait_fraction"] == pytest.approx(3.0 / 5.5)


def test_open_busy_section_counts_in_snapshot() -> None:
    clock = FakeClock()
    stats = LaneStats(clock=clock)
    with stats.busy():
        clock.t += 4.0
        snap = stats.reading()
        assert snap["busy_s"] == pytest.approx(4.0)
        assert snap["utilisation"] == pytest.approx(1.0)


def test_items_per_s_uses_a_sliding_window() -> None:
    clock = FakeClock()
    stats = LaneStats(window_s=10.0, clock=clock)
    for _ in range(100):  # 100 items/s for 5 s
        clock.t += 0.05
        stats.count(5)
    snap = stats.reading()
    assert snap["items"] == 500
    assert snap["items_per_s"] == pytest.approx(100.0, rel=0.02)
    for _ in range(20):  # then idle for 20 s, polled once a second
        clock.t += 1.0
        stats.reading()
    snap = stats.reading()
    assert snap["items_per_s"] == pytest.approx(0.0, abs=0.1)
    assert snap["items"] == 500
    for _ in range(20):  # then 2 items/s for 20 s: only the last window counts
        clock.t += 1.0
        stats.count(2)
    assert stats.reading()["items_per_s"] == pytest.approx(2.0, rel=0.1)
    assert stats.reading()["utilisation"] == 0.0


def test_lane_stats_rejects_bad_window() -> None:
    with pytest.raises(ValueError):
        LaneStats(window_s=0.0)


# -- placement helpers --------------------------------------------------------------------------


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no CPU affinity on this OS")
def test_pin_cpus_in_a_thread() -> None:
    allowed = os.sched_getaffinity(0)
    target = {min(allowed)}
    result: dict[str, object] = {}

    def pin() -> None:  # pin a helper thread so the test process keeps its affinity
        result["pinned"] = pin_cpus(target)
        result["seen"] = os.sched_getaffinity(0)

    t = threading.Thread(target=pin)
    t.start()
    t.join(2.0)
    assert result["pinned"] == target and result["seen"] == target
    assert os.sched_getaffinity(0) == allowed
    with pytest.raises(ValueError):
        pin_cpus([])


def _thread_table() -> dict[str, str]:
    """OS thread name -> Cpus_allowed_list of every thread of this process, from /proc."""
    out = {}
    for tid in os.listdir("/proc/self/task"):
        base = f"/proc/self/task/{tid}"
        try:
            comm = open(f"{base}/comm").read().strip()
            status = open(f"{base}/status").read()
        except OSError:  # the thread ended meanwhile
            continue
        out[comm] = status.split("Cpus_allowed_list:")[1].split()[0]
    return out


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="thread affinity and names are Linux's")
def test_pinned_lane_gets_its_cores_and_the_other_lanes_keep_the_process_affinity() -> None:
    allowed = sorted(os.sched_getaffinity(0))
    core = allowed[-1]
    started = threading.Barrier(3)

    def parked(ctx: LaneContext) -> None:
        started.wait(2.0)
        ctx.stop.wait(5.0)

    sl = Swimlane("rollout-n0-0")
    sl.lane("simulate", parked)
    sl.lane("infer", parked)
    assert sl.affinity() == {"simulate": None, "infer": None}
    sl.pin({"simulate": [core]})
    sl.start()
    try:
        started.wait(2.0)
        threads = _thread_table()  # what the kernel says, not what the lane believes
        assert threads["dvla:simulate"] == str(core)
        assert threads["dvla:infer"] == threads[open("/proc/self/comm").read().strip()]  # the process's set
        assert sl.affinity() == {"simulate": [core], "infer": allowed}
        assert sorted(os.sched_getaffinity(0)) == allowed  # the caller is untouched
    finally:
        assert sl.close() == []


def test_pin_rejects_unknown_lanes_and_empty_sets_naming_them() -> None:
    sl = Swimlane("actor-n0-0")
    sl.lane("learn", _idle)
    with pytest.raises(ValueError, match=r"'actor-n0-0'.*lane 'lern'.*its lanes: learn"):
        sl.pin({"lern": [0]})
    with pytest.raises(ValueError, match="lane_cpus.learn is empty"):
        sl.pin({"learn": []})
    sl.start()
    try:
        with pytest.raises(RuntimeError, match="after start"):
            sl.pin({"learn": [0]})
    finally:
        sl.close()


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="needs CPU affinity")
def test_a_lane_pinned_to_a_missing_core_fails_the_role_naming_the_lane() -> None:
    ran: list[str] = []
    sl = Swimlane("rollout-n0-0")
    sl.lane("sim", lambda ctx: ran.append("sim"))
    sl.lane("ship", _idle)
    sl.pin({"sim": [os.cpu_count() + 4096]})
    sl.start()
    assert sl.wait(5.0)
    assert sl.join() == []
    assert sl.error is not None and sl.error.lane == "sim" and "cannot pin" in str(sl.error)
    assert ran == []  # the lane's body never ran off its cores


def test_pin_cpus_unsupported_is_a_warning(monkeypatch: pytest.MonkeyPatch,
                                           caplog: pytest.LogCaptureFixture) -> None:
    monkeypatch.delattr(os, "sched_setaffinity", raising=False)
    with caplog.at_level(logging.WARNING, logger="dvla.swimlane"):
        assert pin_cpus([0]) is None
    assert any("not supported" in r.getMessage() for r in caplog.records)


class FakeTorch(types.ModuleType):
    """Stands in for torch: importing the real one costs seconds and its thread pools are global."""

    def __init__(self, intra: int, interop: int, interop_locked: bool) -> None:
        super().__init__("torch")
        self.intra, self.interop, self.interop_locked = intra, interop, interop_locked

    def set_num_threads(self, n: int) -> None:
        self.intra = n

    def get_num_threads(self) -> int:
        return self.intra

    def set_num_interop_threads(self, n: int) -> None:
        if self.interop_locked:  # what torch does once parallel work has started
            raise RuntimeError("Error: cannot set number of interop threads after parallel work")
        self.interop = n

    def get_num_interop_threads(self) -> int:
        return self.interop


def test_set_torch_threads_sets_intra_and_interop(monkeypatch: pytest.MonkeyPatch) -> None:
    fake = FakeTorch(intra=8, interop=8, interop_locked=False)
    monkeypatch.setitem(sys.modules, "torch", fake)
    assert set_torch_threads(2) == {"intra": 2, "interop": 1}
    assert (fake.intra, fake.interop) == (2, 1)
    with pytest.raises(ValueError):
        set_torch_threads(0)


def test_set_torch_threads_tolerates_locked_interop(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    fake = FakeTorch(intra=8, interop=4, interop_locked=True)
    monkeypatch.setitem(sys.modules, "torch", fake)
    with caplog.at_level(logging.WARNING, logger="dvla.swimlane"):
        assert set_torch_threads(1) == {"intra": 1, "interop": 4}
    assert any("inter-op threads stay at 4" in r.getMessage() for r in caplog.records)


def test_set_torch_threads_without_torch(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "torch", None)  # makes `import torch` raise ImportError
    assert set_torch_threads(1) is None


# -- a role whose lane fails --------------------------------------------------------------------


class _FailingRole:
    """A role with a healthy lane and one that raises after a few items."""

    policy_version = 0
    env_steps = 0

    def build(self, sl: Swimlane) -> None:
        sl.lane("ship", _idle)
        sl.lane("infer", self._infer)

    def _infer(self, ctx: LaneContext) -> None:
        for _ in range(3):
            with ctx.busy():
                ctx.count()
        raise RuntimeError("policy forward failed")

    def status_extra(self) -> dict[str, object]:
        return {}

    def close(self) -> None:
        pass


def test_role_with_a_failing_lane_exits_with_an_error_naming_the_lane(tmp_path) -> None:
    """RoleHost over a real (loopback-only) fabric: the lane error ends the role, not a thread."""
    from dvla.config import PlaneEndpoints, ReplicationConfig, RoleConfig, TaskConfig
    from dvla.fabric import Fabric, plane_config
    from dvla.roles.runtime import ExitStatus, RoleHost

    cfg = RoleConfig(
        name="rollout-n0-0", kind="rollout", run="lanefail", node="n0", rack="r0", seed=1, mode="async",
        run_dir=str(tmp_path), data=PlaneEndpoints(), ctrl=PlaneEndpoints(mode="peer"),
        shared_memory=False, parent="actor-n0-0", ancestors=("actor-n0-0",), children=(), actors=(),
        rollouts=(), task=TaskConfig(), replication=ReplicationConfig(),
    )
    conf = plane_config(mode="peer", listen=("tcp/127.0.0.1:0",))
    fabric = Fabric(run=cfg.run, name=cfg.name, ctrl_conf=conf, data_conf=None, secret=b"k" * 32)
    try:
        host = RoleHost(cfg, fabric, _FailingRole())
        code = host.run()
        status = host.status()
    finally:
        fabric.close()
    assert code == ExitStatus.ERROR
    assert host.state == "error"
    assert host.swimlane.error is not None and host.swimlane.error.lane == "infer"
    assert status.lanes["infer"]["errors"] == 1.0 and status.lanes["infer"]["items"] == 3.0
    assert status.lanes["ship"]["alive"] == 0.0, "the healthy lane must have been stopped too"
    summary = json.loads((tmp_path / "summaries" / "rollout-n0-0.json").read_text())
    assert "rollout-n0-0/infer" in summary["error"] and "policy forward failed" in summary["error"]


def _role_config(tmp_path, **kw):
    from dvla.config import PlaneEndpoints, ReplicationConfig, RoleConfig, TaskConfig

    return RoleConfig(
        name="rollout-n0-0", kind="rollout", run="lanepin", node="n0", rack="r0", seed=1, mode="async",
        run_dir=str(tmp_path), data=PlaneEndpoints(), ctrl=PlaneEndpoints(mode="peer"),
        shared_memory=False, parent="actor-n0-0", ancestors=("actor-n0-0",), children=(), actors=(),
        rollouts=(), task=TaskConfig(), replication=ReplicationConfig(), **kw,
    )


def _host_run(cfg, role):
    from dvla.fabric import Fabric, plane_config
    from dvla.roles.runtime import RoleHost

    fabric = Fabric(run=cfg.run, name=cfg.name, ctrl_conf=plane_config(mode="peer", listen=("tcp/127.0.0.1:0",)),
                    data_conf=None, secret=b"k" * 32)
    try:
        host = RoleHost(cfg, fabric, role)
        return host, host.run(), host.status()
    finally:
        fabric.close()


class _ShortRole(_FailingRole):
    """Two lanes that run briefly and return (which stops the role cleanly)."""

    def build(self, sl: Swimlane) -> None:
        sl.lane("ship", self._brief)
        sl.lane("infer", self._brief)

    def _brief(self, ctx: LaneContext) -> None:
        ctx.sleep(0.2)


def test_role_host_pins_lanes_from_the_config_and_reports_them(tmp_path) -> None:
    from dvla.roles.runtime import ExitStatus

    core = max(os.sched_getaffinity(0))
    host, code, status = _host_run(_role_config(tmp_path, lane_cpus={"infer": (core,)}), _ShortRole())
    assert code == ExitStatus.OK
    assert status.extra["placement"]["lanes"] == {"ship": sorted(os.sched_getaffinity(0)), "infer": [core]}


def test_role_host_refuses_lane_cpus_for_a_lane_it_does_not_run(tmp_path, caplog) -> None:
    from dvla.roles.runtime import ExitStatus

    with caplog.at_level(logging.ERROR, logger="dvla.role"):
        host, code, _status = _host_run(_role_config(tmp_path, lane_cpus={"sim": (0,)}), _ShortRole())
    assert code == ExitStatus.CONFIG
    assert any("lane 'sim'" in r.getMessage() and "its lanes: ship, infer" in r.getMessage() for r in caplog.records)


def test_stop_joins_every_lane_within_two_seconds_under_load() -> None:
    """Lanes busy in short work items, blocked on full and empty queues: all gone once stopped."""
    q_full: BoundedQueue[int] = BoundedQueue(2, "chunks")
    q_empty: BoundedQueue[int] = BoundedQueue(2, "obs")

    def producer(ctx: LaneContext) -> None:
        i = 0
        while ctx.running:
            if not q_full.put(i, ctx.stop):
                return
            i += 1

    def spinner(ctx: LaneContext) -> None:
        while ctx.running:
            with ctx.busy():
                sum(range(20_000))  # a short item of real work between stop checks
            ctx.count()

    sl = Swimlane("actor")
    sl.lane("ingest", producer)
    sl.lane("batch", lambda ctx: q_empty.get(ctx.stop) and None)
    sl.lane("learn", spinner)
    sl.lane("publish", spinner)
    sl.start()
    time.sleep(0.3)
    assert q_full.depth == 2 and sl.state == "running"
    stuck = sl.close(timeout=30.0)
    assert stuck == []
    assert not any(st["alive"] for st in sl.stats().values())
    assert sl.stats()["learn"]["items"] > 0


def test_swimlane_queues_are_bounded() -> None:
    sl = Swimlane("rollout")
    q = sl.queue("chunks", 3)
    stop = threading.Event()
    assert all(q.put(i, stop, timeout=0.01) for i in range(3))
    assert q.put(3, stop, timeout=0.01) is False
    assert q.depth == q.maxsize == 3


# -- lanes in `dvla status` ---------------------------------------------------------------------


def _status(name: str, kind: str, version: int, lanes: dict[str, float], **extra: object):
    from dvla.fabric.messages import RoleStatus

    sl = {lane: {"busy_s": u * 10, "wait_s": 0.0, "items": 5.0, "utilisation": u} for lane, u in lanes.items()}
    return RoleStatus(name=name, kind=kind, node="node0", rack="rack0", pid=1, state="running",
                      policy_version=version, env_steps=100, steps_per_s=10.0, lanes=sl, extra=dict(extra),
                      time_ns=time.time_ns())


def _table_cells(table: str) -> dict[str, dict[str, str]]:
    """Role -> {column header: cell} of `dvla status`'s table, cut where each header starts."""
    head, *lines = table.splitlines()
    cols = [(m.group(), m.start()) for m in re.finditer(r"\S+(?: \S+)*", head)]
    bounds = [(name, start, cols[i + 1][1] if i + 1 < len(cols) else None) for i, (name, start) in enumerate(cols)]
    rows = [{name: line[a:b].strip() for name, a, b in bounds} for line in lines]
    return {r["ROLE"]: r for r in rows}


def test_status_shows_every_lane_utilisation_and_rollout_lag() -> None:
    from dvla.orchestrator.view import render_json, render_table

    statuses = {
        "actor-node0-0": _status("actor-node0-0", "actor", 6, {"ingest": 0.05, "learn": 0.93},
                                 published_version=9, policy_lag_mean=1.25),
        "rollout-node0-0": _status("rollout-node0-0", "rollout", 7, {"sim": 0.81, "infer": 0.12}),
        "rollout-node0-1": _status("rollout-node0-1", "rollout", 9, {"sim": 0.5, "infer": 0.2},
                                   placement={"cpus": [1], "lanes": {"sim": [0], "infer": [1]}}),
    }
    rows = _table_cells(render_table(statuses, expected=[*statuses, "evaluator-node0-0"]))
    assert rows["rollout-node0-0"]["LAG"] == "2"  # published 9, acting with 7
    assert rows["rollout-node0-1"]["LAG"] == "0"
    assert (rows["actor-node0-0"]["VERSION"], rows["actor-node0-0"]["LAG"]) == ("9", "~1.2")
    assert "sim 81%" in rows["rollout-node0-0"]["LANES (busy)"] and "infer 12%" in rows["rollout-node0-0"]["LANES (busy)"]
    assert "ingest 5%" in rows["actor-node0-0"]["LANES (busy)"] and "learn 93%" in rows["actor-node0-0"]["LANES (busy)"]
    # a lane pinned apart from its process shows its cores; one on the process's cores does not
    assert "sim@0 50%" in rows["rollout-node0-1"]["LANES (busy)"] and "infer 20%" in rows["rollout-node0-1"]["LANES (busy)"]
    assert rows["evaluator-node0-0"]["STATE"] == "silent"
    doc = json.loads(render_json(statuses))
    by_name = {r["name"]: r for r in doc["roles"]}
    assert by_name["rollout-node0-0"]["policy_lag"] == 2
    assert by_name["rollout-node0-0"]["lane_utilisation"] == {"sim": 0.81, "infer": 0.12}
    assert by_name["actor-node0-0"]["policy_lag"] is None


def test_status_table_shows_each_sim_workers_busy_share() -> None:
    from dvla.orchestrator.view import render_table

    workers = [{"worker": 0, "pid": 11, "envs": 4, "alive": True, "busy": 0.97},
               {"worker": 1, "pid": 12, "envs": 4, "alive": False, "busy": 0.4}]
    statuses = {"rollout-node0-0": _status("rollout-node0-0", "rollout", 3, {"sim": 0.9}, sim_workers=workers),
                "rollout-node0-1": _status("rollout-node0-1", "rollout", 3, {"sim": 0.9}, sim_workers=[])}
    rows = _table_cells(render_table(statuses))
    assert rows["rollout-node0-0"]["LANES (busy)"].endswith("| workers 97%/dead")
    assert "workers" not in rows["rollout-node0-1"]["LANES (busy)"]
