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
from dvla.replication import ParamLayout
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
            "same": WeightSync(pair.client("rollout-0"), LAYOUT, (actor.name,), lambda v, f: got["same"].append(v),
                               base_hash="base-a", base_source="/models/a"),
            "other": WeightSync(pair.client("rollout-1"), LAYOUT, (actor.name,), lambda v, f: got["other"].append(v),
                                base_hash="base-b", base_source="/models/b"),
            "relay": WeightSync(pair.client("replicator-0"), None, (actor.name,), lambda v, f: got["relay"].append(v)),
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
        assert relay.layout.numel == LAYOUT.numel and relay.layout_hash == LAYOUT.hash
        np.testing.assert_array_equal(relay.decoder.active, publisher.encoder.published)
        np.testing.assert_array_equal(syncs["same"].decoder.active, publisher.encoder.published)
    finally:
        stop.set()
        for t in threads:
            t.join(5)
        pair.close()
