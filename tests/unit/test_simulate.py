"""The broadcast model (dvla.orchestrator.simulate): link sharing, pipelining, CPU, tree vs star."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from dvla.config import LinkConfig
from dvla.orchestrator.plan import make_plan
from dvla.orchestrator.simulate import WIRE_OVERHEAD, HostCosts, max_min_rates, simulate_broadcast
from dvla.orchestrator.topology import load_topology, parse_topology

ROOT = Path(__file__).resolve().parents[2]
MIB = 1 << 20


def _eight(node_gbit: float, uplink_gbit: float):
    topo = load_topology(ROOT / "topologies" / "8node.yaml")
    racks = tuple(dataclasses.replace(r, nodes=tuple(dataclasses.replace(
        n, roles=tuple(x for x in n.roles if x.role != "evaluator")) for n in r.nodes)) for r in topo.racks)
    topo = dataclasses.replace(topo, racks=racks, links=LinkConfig(node_gbit=node_gbit, rack_uplink_gbit=uplink_gbit))
    return topo, make_plan(topo, "runs/x")


def test_max_min_shares_links_fairly() -> None:
    rates = max_min_rates({0: ("a",), 1: ("a", "b"), 2: ()}, {"a": 10.0, "b": 2.0})
    assert rates[1] == pytest.approx(2.0)  # held by b
    assert rates[0] == pytest.approx(8.0)  # takes what flow 1 leaves on a
    assert rates[2] == float("inf")  # on no link: loopback


def test_tree_is_paced_by_the_uplink_and_the_star_by_four_copies_over_it() -> None:
    topo, plan = _eight(1.0, 0.2)
    size = 64 * MIB
    bc = simulate_broadcast(topo, plan, size)
    wire_s = size * 8 / 0.2e9 * WIRE_OVERHEAD
    assert bc.bound_s == pytest.approx(size * 8 / 0.2e9)
    assert "rack uplink" in bc.bound_link
    # one copy crosses the uplink; the pipeline adds a few 1 MiB chunks (one per hop)
    assert wire_s < bc.tree_s < wire_s + 4 * MIB * 8 / 0.2e9 * WIRE_OVERHEAD
    assert bc.tree_bottleneck in ("r0 uplink out", "r1 uplink in") and bc.tree_bottleneck_copies == 1
    # the star sends rack r1's four rollouts four copies across the uplink
    assert bc.star_s == pytest.approx(4 * wire_s, rel=0.02)
    assert len(bc.per_leaf_s) == 8


def test_fast_uplinks_move_the_bottleneck_to_a_replicator_nic() -> None:
    topo, plan = _eight(1.0, 10.0)
    size = 64 * MIB
    bc = simulate_broadcast(topo, plan, size)
    # r0n1's replicator sends three rollouts of its rack and rack r1's head a copy each
    assert bc.tree_bottleneck == "r0n1 NIC out" and bc.tree_bottleneck_copies == 4
    assert bc.tree_s == pytest.approx(4 * size * 8 / 1e9 * WIRE_OVERHEAD, rel=0.05)
    assert bc.bound_s == pytest.approx(size * 8 / 1e9)


def test_a_chain_pays_one_chunk_per_hop() -> None:
    nodes = "\n".join(f"      - {{name: n{i}, roles: [{{role: replicator}}, {{role: rollout}}]}}" for i in range(10))
    text = f"run: chain\nlinks: {{node_gbit: 1.0}}\nracks:\n  - name: r\n    nodes:\n      - {{name: a, roles: [{{role: actor}}]}}\n{nodes}\n"
    topo = parse_topology(text, "chain.yaml")
    plan = make_plan(topo, "runs/x")
    size, chunk_s = 64 * MIB, MIB * 8 / 1e9 * WIRE_OVERHEAD
    bc = simulate_broadcast(topo, plan, size, star=False)
    assert bc.depth == 11 and bc.star_s == 0.0
    stream = size * 8 / 1e9 * WIRE_OVERHEAD
    assert bc.tree_s == pytest.approx(stream + 9 * chunk_s, rel=0.02)
    # per-hop latency adds up along the chain (two link directions per hop)
    slow = simulate_broadcast(topo, plan, size, HostCosts(hop_latency_s=0.01), star=False)
    assert slow.tree_s == pytest.approx(bc.tree_s + 10 * 2 * 0.01, rel=0.02)


def test_shared_cores_make_an_emulated_cluster_cpu_bound() -> None:
    topo, plan = _eight(1.0, 0.2)
    size = 16 * MIB
    free = simulate_broadcast(topo, plan, size, star=False)
    costs = HostCosts(source_s_per_mib=0.01, relay_s_per_mib=0.05, sink_s_per_mib=0.05, shared_cores=2)
    busy = simulate_broadcast(topo, plan, size, costs, star=False)
    cpu_total = 16 * (0.01 + 2 * 0.05 + 8 * 0.05)
    assert busy.tree_s >= cpu_total / 2 > free.tree_s
    # the same costs on a real cluster (own cores per node) are a per-process pipeline stage
    own = simulate_broadcast(topo, plan, size, dataclasses.replace(costs, shared_cores=None), star=False)
    assert free.tree_s < own.tree_s < busy.tree_s


def test_bad_size_is_refused() -> None:
    topo, plan = _eight(1.0, 0.2)
    with pytest.raises(ValueError, match="version size"):
        simulate_broadcast(topo, plan, 0)
