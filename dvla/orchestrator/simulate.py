"""Discrete-event model of a weight version travelling a plan's replication tree (SimPy).

Links are resources shared max-min fairly, a version moves chunk by chunk (store-and-forward per
chunk, pipelined per version, a sender blocking on its slowest child) and each process pays
:class:`HostCosts` CPU per MiB. docs/scale.md has the derivation and the validation.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass, field
import simpy

from ..config import Topology
from .plan import Plan

MIB = 1 << 20
#: wire bytes per payload byte of a TCP stream: 1500-byte MTU carries 1448 payload bytes behind
#: IPv4 (20), TCP with timestamps (32) and an Ethernet header (14) that rate limiters count
WIRE_OVERHEAD = (1500 + 14) / (1500 - 20 - 32)
LEAF_KINDS = ("rollout", "evaluator")
#: chunks a child may lag behind its fastest sibling before the shared sender blocks
SEND_WINDOW = 2


@dataclass(frozen=True, kw_only=True)
class HostCosts:
    """CPU a version costs each process, and whose cores pay for it."""

    #: CPU seconds the actor spends per MiB it publishes (encode, sign, put)
    source_s_per_mib: float = 0.0
    #: CPU seconds a replicator spends per MiB it receives, verifies and forwards
    relay_s_per_mib: float = 0.0
    #: CPU seconds a rollout spends per MiB it receives, verifies and swaps in
    sink_s_per_mib: float = 0.0
    #: every process shares this many cores (an emulated cluster on one machine); None: every
    #: node has cores of its own and each process one lane
    shared_cores: int | None = None
    #: one-way latency of each link a copy crosses (propagation and switching), seconds
    hop_latency_s: float = 0.0

    def per_mib(self, kind: str) -> float:
        return {"actor": self.source_s_per_mib, "replicator": self.relay_s_per_mib}.get(kind, self.sink_s_per_mib)


@dataclass(frozen=True, kw_only=True)
class BroadcastPrediction:
    """Seconds until every leaf holds a version, through the tree and as a star."""

    size_bytes: int
    #: tree: until the last leaf holds it
    tree_s: float
    #: star: the root actor sends every leaf its own copy
    star_s: float
    #: size / the slowest link rate any copy must cross (no scheme is faster)
    bound_s: float
    #: that link kind and rate, e.g. "rack uplink (0.2 Gbit/s)"
    bound_link: str
    #: the tree's most loaded link (direction) and how many copies cross it per version
    tree_bottleneck: str
    tree_bottleneck_copies: int
    star_bottleneck: str
    #: relays between the root and the deepest leaf, and simulated blocks per version
    depth: int
    blocks: int
    #: per leaf, when it held the version (tree)
    per_leaf_s: dict[str, float] = field(default_factory=dict)


@dataclass
class _Node:
    """A process of the tree while a version is simulated."""

    name: str
    kind: str
    node: str
    rack: str
    children: list["_Edge"] = field(default_factory=list)
    #: per block: first chunk usable here (forwarding may start), block fully processed here
    first_ready: list[simpy.Event] = field(default_factory=list)
    done: list[simpy.Event] = field(default_factory=list)
    #: per block: fully received (receivers only)
    received: list[simpy.Event] = field(default_factory=list)


@dataclass
class _Edge:
    parent: _Node
    child: _Node
    links: tuple[str, ...]
    rate: float = math.inf  # payload bytes/s
    started: list[simpy.Event] = field(default_factory=list)


def path_links(topo_where: dict[str, tuple[str, str]], sender: str, child: str) -> tuple[str, ...]:
    """Link directions a copy from `sender` to `child` crosses (empty on one node)."""
    (rs, ns), (rc, nc) = topo_where[sender], topo_where[child]
    if ns == nc:
        return ()
    links = [f"{ns} NIC out"]
    if rs != rc:
        links += [f"{rs} uplink out", f"{rc} uplink in"]
    return (*links, f"{nc} NIC in")


def link_rate(topo: Topology, link: str) -> float:
    """Payload bytes/s of one link direction."""
    gbit = topo.links.node_gbit if " NIC " in link else topo.links.rack_uplink_gbit
    return gbit * 1e9 / 8 / WIRE_OVERHEAD


def max_min_rates(flows: dict[int, tuple[str, ...]], capacity: dict[str, float]) -> dict[int, float]:
    """Max-min fair rate of every flow (progressive filling); a flow on no link is unlimited."""
    rate = {f: math.inf for f, links in flows.items() if not links}
    on_link: dict[str, set[int]] = defaultdict(set)
    for f, links in flows.items():
        for link in links:
            on_link[link].add(f)
    left = dict(capacity)
    while on_link:
        link = min(on_link, key=lambda k: left[k] / len(on_link[k]))
        share = left[link] / len(on_link[link])
        for f in list(on_link[link]):
            rate[f] = share
            for other in flows[f]:
                left[other] -= share
                if other != link:
                    on_link[other].discard(f)
                    if not on_link[other]:
                        del on_link[other]
        del on_link[link]
    return rate


def _simulate(topo: Topology, plan: Plan, edges: list[tuple[str, str]], size_bytes: int, costs: HostCosts,
              max_blocks: int) -> tuple[dict[str, float], int, dict[str, int]]:
    """When each leaf holds the version, the number of simulated blocks, copies per link."""
    env = simpy.Environment()
    where = {p.config.name: (p.config.rack, p.config.node) for p in plan.processes}
    kinds = {p.config.name: p.config.kind for p in plan.processes}
    chunk = min(size_bytes, topo.replication.chunk_bytes)
    nb = min(max(1, math.ceil(size_bytes / chunk)), max_blocks)
    block = [size_bytes * (b + 1) // nb - size_bytes * b // nb for b in range(nb)]
    first = [min(chunk, x) for x in block]  # the real chunk that starts (and ends) each block
    nodes = {n: _Node(n, kinds[n], where[n][1], where[n][0]) for n in {plan.root_actor} | {n for e in edges for n in e}}
    for nd in nodes.values():
        nd.first_ready, nd.done, nd.received = ([env.event() for _ in range(nb)] for _ in range(3))
    all_edges = []
    for s, c in edges:
        e = _Edge(nodes[s], nodes[c], path_links(where, s, c), started=[env.event() for _ in range(nb)])
        nodes[s].children.append(e)
        all_edges.append(e)
    copies: dict[str, int] = defaultdict(int)
    for e in all_edges:
        for link in e.links:
            copies[link] += 1
    rates = max_min_rates({i: e.links for i, e in enumerate(all_edges)}, {k: link_rate(topo, k) for k in copies})
    for i, e in enumerate(all_edges):
        e.rate = rates[i]
    cores = simpy.Resource(env, capacity=costs.shared_cores) if costs.shared_cores else None
    done_at: dict[str, float] = {}

    def compute(nd: _Node, nbytes: float):
        """`nbytes` worth of the process's CPU work, on a shared core when the cluster is emulated."""
        t = costs.per_mib(nd.kind) * nbytes / MIB
        if t <= 0:
            return
        if cores is None:
            yield env.timeout(t)
            return
        with cores.request() as req:
            yield req
            yield env.timeout(t)

    def worker(nd: _Node):
        """One lane: each block is processed as it arrives, its last chunk once that is in."""
        for b in range(nb):
            if nd.name == plan.root_actor:
                yield from compute(nd, first[b])
                nd.first_ready[b].succeed()
                yield from compute(nd, block[b] - first[b])
            else:
                yield nd.first_ready[b]
                yield from compute(nd, block[b] - first[b])
                yield nd.received[b]
                yield from compute(nd, first[b])
            nd.done[b].succeed()
        done_at[nd.name] = env.now

    def mark(ev: simpy.Event, delay: float):
        yield env.timeout(delay)
        if not ev.triggered:
            ev.succeed()

    def sender(e: _Edge):
        par, child = e.parent, e.child
        lat = costs.hop_latency_s * len(e.links)
        # the child may hold SEND_WINDOW blocks unprocessed, plus what is in flight for one round
        # trip (TCP's window covers the bandwidth-delay product)
        window = SEND_WINDOW + (math.ceil(2 * lat * e.rate / max(1, min(block))) if lat > 0 and e.rate < math.inf else 0)
        for b in range(nb):
            waits = [par.first_ready[b]]
            if b >= SEND_WINDOW:  # Zenoh's put blocks on the slowest child: siblings stay close
                waits += [sib.started[b - SEND_WINDOW + 1] for sib in par.children]
            if b >= window:
                waits.append(child.done[b - window])
            yield env.all_of(waits)
            e.started[b].succeed()
            # the child can work on the block once its first chunk crossed (cut-through per chunk)
            env.process(mark(child.first_ready[b], first[b] / e.rate + lat))
            yield env.timeout(block[b] / e.rate)
            if not par.done[b].triggered:  # the parent was slower: its last chunk leaves once it is done
                yield par.done[b]
                yield env.timeout(first[b] / e.rate)
            env.process(mark(child.received[b], lat))  # in flight: the sender goes on

    for nd in nodes.values():
        env.process(worker(nd))
    for e in all_edges:
        env.process(sender(e))
    env.run()
    held = {nd.name: done_at[nd.name] for nd in nodes.values() if nd.kind in LEAF_KINDS}
    return held, nb, dict(copies)


def simulate_broadcast(topo: Topology, plan: Plan, size_bytes: int, costs: HostCosts = HostCosts(),
                       *, max_blocks: int = 64, star: bool = True) -> BroadcastPrediction:
    """Simulates one version of `size_bytes` through the plan's tree and (`star`) as a star, whose
    every copy leaves the root: 16 blocks resolve it (star_s is 0.0 when not simulated)."""
    if size_bytes <= 0:
        raise ValueError(f"version size must be positive, got {size_bytes} bytes")
    procs = plan.processes
    # routers carry versions only to rollouts outside the plan: not part of the modelled tree
    tree = [(p.config.parent, p.config.name) for p in procs if p.config.parent and p.config.kind != "router"]
    leaves = [p.config.name for p in procs if p.config.kind in LEAF_KINDS]
    tree_held, nb, tree_copies = _simulate(topo, plan, tree, size_bytes, costs, max_blocks)
    star_held: dict[str, float] = {}
    star_copies: dict[str, int] = {}
    if star:
        star_edges = [(plan.root_actor, leaf) for leaf in leaves]
        star_held, _nb, star_copies = _simulate(topo, plan, star_edges, size_bytes, costs, min(16, max_blocks))
    crossed = {k.split()[1] for k in tree_copies}
    kinds = {"NIC": ("node NIC", topo.links.node_gbit), "uplink": ("rack uplink", topo.links.rack_uplink_gbit)}
    slowest = min((kinds[k] for k in crossed), key=lambda x: x[1], default=("none (one node)", math.inf))
    depth = max((len(p.config.ancestors) for p in procs if p.config.kind in LEAF_KINDS), default=1)

    def busiest(copies: dict[str, int]) -> str:
        return max(copies, key=lambda k: copies[k] / link_rate(topo, k)) if copies else "none"

    tb = busiest(tree_copies)
    return BroadcastPrediction(
        size_bytes=size_bytes,
        tree_s=max(tree_held.values(), default=0.0),
        star_s=max(star_held.values(), default=0.0),
        bound_s=size_bytes * 8 / (slowest[1] * 1e9),
        bound_link=f"{slowest[0]} ({slowest[1]:g} Gbit/s)",
        tree_bottleneck=tb,
        tree_bottleneck_copies=tree_copies.get(tb, 0),
        star_bottleneck=busiest(star_copies),
        depth=depth,
        blocks=nb,
        per_leaf_s=tree_held,
    )
