"""Weights over real Zenoh sessions when only part of a policy replicates: a receiver whose frozen
base checkpoint differs from the actor's refuses every version (counted, one log line naming both
bases) and never applies it, while one with the same base applies it; a relay given no layout
learns it from the actor's signed manifest."""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
import pytest

from dvla.config import ReplicationConfig
from dvla.replication import HeldWeights, ParamLayout
from dvla.roles.swimlane import LaneContext, LaneStats
from dvla.roles.weightsync import WeightPublisher, WeightSync
from tests.integration.test_fabric import Pair, wait_for, wait_route

LAYOUT = ParamLayout(names=("lora_A", "lora_B", "head"), shapes=((4, 16), (16, 4), (3,)), dtypes=("float32",) * 3)


@pytest.mark.timeout(60)
def test_another_base_is_refused_the_same_base_applies_and_a_relay_learns_the_layout(caplog) -> None:
    pair = Pair()
    stop = threading.Event()
    threads: list[threading.Thread] = []
    try:
        actor = pair.actor
        publisher = WeightPublisher(actor, actor.name, LAYOUT, ReplicationConfig(), base_hash="base-a")
        publisher.serve()
        got: dict[str, list[int]] = {"same": [], "other": [], "relay": []}
        syncs = {
            "same": WeightSync(pair.client("rollout-0"), HeldWeights(LAYOUT), (actor.name,), got["same"].append,
                               base_hash="base-a", base_source="/models/a"),
            "other": WeightSync(pair.client("rollout-1"), HeldWeights(LAYOUT), (actor.name,), got["other"].append,
                                base_hash="base-b", base_source="/models/b"),
            "relay": WeightSync(pair.client("replicator-0"), None, (actor.name,), got["relay"].append),
        }
        for name, sync in syncs.items():
            ctx = LaneContext(name, "sync", stop, LaneStats())
            t = threading.Thread(target=lambda s=sync, c=ctx: [s.step(c) for _ in iter(lambda: stop.is_set(), True)],
                                 name=f"sync-{name}", daemon=True)
            t.start()
            threads.append(t)
        for sync in syncs.values():
            wait_route(sync.fabric.ctrl, actor.ctrl)
        time.sleep(0.5)  # the first snapshot queries (nothing held yet) are answered
        rng = np.random.default_rng(0)
        with caplog.at_level(logging.ERROR, logger="dvla.weights"):
            for _ in range(3):
                publisher.send(publisher.encode(rng.standard_normal(LAYOUT.numel).astype(np.float32)))
                time.sleep(0.05)
            assert wait_for(lambda: len(got["same"]) >= 1 and got["same"][-1] == 3 and got["relay"][-1:] == [3], 10)
            time.sleep(0.3)
        assert got["other"] == [] and syncs["other"].version == -1
        assert syncs["other"].counters["refused_base"] >= 3
        refusals = [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]
        assert len(refusals) == 1, refusals  # one line per distinct base, not per version
        assert "base-a" in refusals[0] and "base-b" in refusals[0] and "/models/b" in refusals[0]
        assert syncs["same"].counters["refused_base"] == 0
        relay = syncs["relay"]
        assert relay.held.layout.numel == LAYOUT.numel and relay.layout_hash == LAYOUT.hash
        for sync in (relay, syncs["same"]):
            assert sync.held.id == publisher.held.id
            np.testing.assert_array_equal(sync.held.active, publisher.held.active)
    finally:
        stop.set()
        for t in threads:
            t.join(5)
        pair.close()


@pytest.mark.timeout(60)
def test_a_late_receiver_catches_up_from_a_relays_snapshot_and_refuses_a_forged_one() -> None:
    """A receiver that missed the stream fetches the relay's held version whole (header with the
    actor's signed manifest, then chunks) and holds exactly the actor's weights; a relay serving
    other parameters under the actor's genuine manifest is refused and counted."""
    from dvla.roles.weightsync import serve_snapshots

    pair = Pair()
    stop = threading.Event()
    threads: list[threading.Thread] = []

    def run(sync: WeightSync) -> None:
        ctx = LaneContext(sync.fabric.name, "sync", stop, LaneStats())
        t = threading.Thread(target=lambda: [sync.step(ctx) for _ in iter(lambda: stop.is_set(), True)], daemon=True)
        t.start()
        threads.append(t)

    try:
        actor = pair.actor
        publisher = WeightPublisher(actor, actor.name, LAYOUT, ReplicationConfig(encoding="delta-bf16"))
        publisher.serve()
        relay = WeightSync(pair.client("replicator-0"), None, (actor.name,))
        relay.serve("replicator-0", 64)  # small chunks: one version whole is many replies
        run(relay)
        wait_route(relay.fabric.ctrl, actor.ctrl)
        time.sleep(0.5)
        rng = np.random.default_rng(1)
        for _ in range(3):  # a full version, then two deltas: a receiver that missed them needs a snapshot
            publisher.send(publisher.encode(rng.standard_normal(LAYOUT.numel).astype(np.float32)))
        assert wait_for(lambda: relay.version == 3, 10)
        forged = HeldWeights(LAYOUT)  # the actor's genuine proof of v3, other parameters
        forged.staging[:] = 1.0
        forged.publish(3, relay.held.checksum, relay.held.proof)
        serve_snapshots(pair.client("replicator-1"), "replicator-1", lambda: forged, 64)
        late = WeightSync(pair.client("rollout-0"), HeldWeights(LAYOUT), ("replicator-0",), base_hash="")
        victim = WeightSync(pair.client("rollout-1"), HeldWeights(LAYOUT), ("replicator-1",), base_hash="")
        run(late)
        run(victim)
        assert wait_for(lambda: late.version == 3 and victim.counters["rejected"] >= 1, 15)
        assert late.counters["snapshots"] == 1 and late.held.id == publisher.held.id
        np.testing.assert_array_equal(late.held.active, publisher.held.active)
        assert victim.version == -1 and victim.counters["snapshots"] == 0
    finally:
        stop.set()
        for t in threads:
            t.join(5)
        pair.close()
