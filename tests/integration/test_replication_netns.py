"""The weight tree on the emulated 8-node, 2-rack cluster: network namespaces, rate-limited links,
real TCP, one process per actor / replicator / rollout slot of topologies/8node.yaml (the
:mod:`benchmarks.repnode` processes: the real Replicator, the actor's WeightPublisher and the rollouts'
WeightSync, without simulators or learning).

One cluster, one story, checked step by step:
1. every rollout converges on each version with the actor's checksum;
2. a chunk corrupted by a replicator is rejected by its children and repaired, never applied;
3. kill -9 of a rack's replicator in the middle of a transfer: its rollouts hold the latest
   version again (re-attached to the actor), and move back once it is restarted;
4. a restarted rollout catches up by snapshot.
"""

from __future__ import annotations

import dataclasses
import shutil
import time
from pathlib import Path

import pytest

from benchmarks.repcluster import RepCluster
from dvla.config import LinkConfig
from dvla.orchestrator.netns import list_netns, run_prefix
from dvla.orchestrator.topology import load_topology

from .test_netns import _netns_usable

pytestmark = [
    pytest.mark.netns,
    pytest.mark.skipif(not _netns_usable(), reason="needs root and `ip netns`"),
]

ROOT = Path(__file__).resolve().parents[2]
NUMEL = 2 << 20  # 8 MiB versions: 8 chunks; ~0.3 s across a 0.2 Gbit/s rack uplink


def _held(extra: dict, version: int) -> dict:
    return extra["held"][str(version)]


@pytest.mark.timeout(240)
def test_tree_converges_repairs_and_heals(tmp_path: Path) -> None:
    topo = load_topology(ROOT / "topologies" / "8node.yaml")
    topo = dataclasses.replace(topo, run="reptest", links=LinkConfig(node_gbit=1.0, rack_uplink_gbit=0.2))
    relay1 = "replicator-r1n0-0"
    # v3: chunk 2 damaged by rack r1's replicator; v4: it stalls after chunk 3 (killed there).
    faults = {relay1: ["corrupt:3:2", "stall:4:3:30"]}
    cluster = RepCluster(topo, tmp_path / "run", NUMEL, faults=faults)
    cluster.start(timeout_s=120)
    try:
        rack1 = cluster.children_of(relay1)
        assert len(rack1) == 4 and all("r1n" in n for n in rack1)
        rack0 = [n for n in cluster.sinks if n not in rack1]

        # 1. convergence, bit for bit
        for v in (1, 2):
            cluster.publish(v)
            held = cluster.wait_held(v, timeout_s=60)
            want = cluster.published()[str(v)]["checksum"]
            assert {n: _held(e, v)["checksum"] for n, e in held.items()} == {n: want for n in cluster.sinks}

        # 2. a corrupted chunk: rejected by the checksum, repaired by snapshot, never applied
        cluster.publish(3)
        held = cluster.wait_held(3, timeout_s=60)
        want = cluster.published()[str(3)]["checksum"]
        for n, e in held.items():
            assert _held(e, 3)["checksum"] == want, n
            assert all(h["checksum"] == cluster.published()[k]["checksum"] for k, h in e["held"].items()), n
        for n in rack1:
            w = held[n]["weights"]
            assert w["rejected"] >= 1 and w["snapshots"] >= 1, (n, w)
        for n in rack0:
            assert held[n]["weights"]["rejected"] == 0, (n, held[n]["weights"])
        relay_status = cluster.status(relay1)
        assert relay_status is not None and relay_status.extra["faults_injected"] == 1

        # 3. kill -9 the rack's replicator in the middle of v4 (it stalls after chunk 3 of 8)
        cluster.publish(4)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            st = cluster.status(relay1, timeout=1.0)
            if st is not None and st.extra.get("faults_injected", 0) >= 2:
                break
            time.sleep(0.05)
        else:
            pytest.fail("the replicator never reached the stall point of v4")
        partial = {n: cluster.status(n).policy_version for n in rack1}  # type: ignore[union-attr]
        assert all(v == 3 for v in partial.values()), partial  # mid-transfer: nobody holds v4 yet
        cluster.kill(relay1)
        held = cluster.wait_held(4, names=rack1, timeout_s=60)
        want = cluster.published()[str(4)]["checksum"]
        for n in rack1:
            assert _held(held[n], 4)["checksum"] == want
            assert held[n]["weights"]["reattach"] >= 1, held[n]["weights"]
            # the next ancestor: the root rack's replicator, which feeds rack r1's head
            assert _held(held[n], 4)["parent"] == cluster.plan.by_name(n).config.ancestors[1]
        cluster.wait_held(4, timeout_s=30)

        # ... restarted (without faults this time), it catches up and its children come back
        cluster.launcher.faults.pop(relay1)
        cluster.restart(relay1)
        cluster.wait_alive([relay1], timeout_s=60)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            st = cluster.status(relay1, timeout=1.0)
            if st is not None and st.policy_version >= 4:
                break
            time.sleep(0.2)
        else:
            pytest.fail("the restarted replicator did not catch up to v4")
        time.sleep(1.0)  # children see its liveliness token and switch back
        cluster.publish(5)
        held = cluster.wait_held(5, timeout_s=60)
        want = cluster.published()[str(5)]["checksum"]
        for n in cluster.sinks:
            assert _held(held[n], 5)["checksum"] == want
        for n in rack1:
            assert _held(held[n], 5)["parent"] == relay1, (n, _held(held[n], 5))

        # 4. a rollout killed and restarted catches up by snapshot
        victim = rack0[-1]
        cluster.kill(victim)
        cluster.restart(victim)
        cluster.wait_alive([victim], timeout_s=60)
        held = cluster.wait_held(5, names=[victim], timeout_s=30)
        assert held[victim]["weights"]["snapshots"] >= 1
        assert _held(held[victim], 5)["checksum"] == want
        cluster.publish(6)
        held = cluster.wait_held(6, timeout_s=60)
        assert {_held(e, 6)["checksum"] for e in held.values()} == {cluster.published()["6"]["checksum"]}
    finally:
        cluster.close()
    assert not [n for n in list_netns() if n.startswith(run_prefix("reptest"))]
    shutil.rmtree(tmp_path / "run", ignore_errors=True)
