"""Predicted time to deliver one weight version through a plan's tree (and as a star).

Model (what `dvla plan` prints and `dvla bench replication` compares against):

- every tree node sends each version once per child (Zenoh routes one put to every child
  session); a child on the sender's own node costs no link (loopback);
- a copy between nodes occupies the sender node's NIC (egress) and the child node's NIC
  (ingress); between racks it also occupies the sender rack's uplink (egress) and the child
  rack's uplink (ingress); each direction of each link is its own resource (full duplex);
- forwarding is cut-through chunk by chunk and publishers block on their slowest child, so the
  whole tree moves at the pace of its most loaded link: ``T = max over links of bytes / rate``,
  plus one chunk's time per extra tree level (the pipeline filling).

CPU time (hashing, signing, copies) is not modelled: on a real cluster every node has its own
CPUs, but an emulated cluster shares one machine's, so measured times there can exceed it.
"""

from __future__ import annotations

from collections import defaultdict
from typing import Any

from ..config import Topology
from .plan import Plan

LEAF_KINDS = ("rollout", "evaluator")


def link_loads(topo: Topology, plan: Plan, edges: list[tuple[str, str]], size_bytes: int) -> dict[str, float]:
    """Seconds each loaded link direction is busy moving one version along `edges` (sender, child)."""
    where = {p.config.name: (p.config.rack, p.config.node) for p in plan.processes}
    load: dict[str, float] = defaultdict(float)
    for sender, child in edges:
        (rs, ns), (rc, nc) = where[sender], where[child]
        if ns == nc:
            continue
        load[f"{ns} NIC out"] += size_bytes
        load[f"{nc} NIC in"] += size_bytes
        if rs != rc:
            load[f"{rs} uplink out"] += size_bytes
            load[f"{rc} uplink in"] += size_bytes
    rate = {"NIC": topo.links.node_gbit * 1e9 / 8, "uplink": topo.links.rack_uplink_gbit * 1e9 / 8}
    return {link: b / rate[link.split()[1]] for link, b in load.items()}


def delivery_estimate(topo: Topology, plan: Plan, size_bytes: int) -> dict[str, Any]:
    """Predicted seconds until every leaf holds a version of `size_bytes`, tree and star."""
    procs = plan.processes
    tree_edges = [(p.config.parent, p.config.name) for p in procs if p.config.parent]
    leaves = [p.config.name for p in procs if p.config.kind in LEAF_KINDS]
    star_edges = [(plan.root_actor, leaf) for leaf in leaves]
    depth = max((len(p.config.ancestors) for p in procs if p.config.kind in LEAF_KINDS), default=1)
    slowest_bps = min(topo.links.node_gbit, topo.links.rack_uplink_gbit if len(topo.racks) > 1 else topo.links.node_gbit) * 1e9
    chunk_s = min(size_bytes, topo.replication.chunk_bytes) * 8 / slowest_bps
    out: dict[str, Any] = {"size_bytes": size_bytes, "depth": depth, "leaves": len(leaves)}
    for name, edges, levels in (("tree", tree_edges, depth), ("star", star_edges, 1)):
        loads = link_loads(topo, plan, edges, size_bytes)
        bottleneck = max(loads, key=loads.get) if loads else None
        out[f"{name}_s"] = (loads[bottleneck] if bottleneck else 0.0) + (levels - 1) * chunk_s
        out[f"{name}_bottleneck"] = bottleneck
        out[f"{name}_root_copies"] = sum(1 for s, _c in edges if s == plan.root_actor)
    out["bound_s"] = size_bytes * 8 / slowest_bps
    return out
