"""Resolves a `Topology` into one `RoleConfig` per process: names, ports, the weight tree and the
Zenoh link graph. Pure logic: nothing is started here.

Link graph (see docs/architecture.md):
- ctrl plane: the root actor's ctrl session is a Zenoh router; each replicator's ctrl session is
  a router connected to its parent's; leaves (rollouts, evaluators) are clients of their parent
  router, with their other ancestors as fallbacks (so they re-attach when the parent dies). The
  weight tree is therefore also the link tree: a version crosses each link once.
- data plane: each actor listens; each rollout connects straight to the actor it feeds.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass

from ..config import GroupRank, NodeConfig, PlaneEndpoints, RackConfig, RoleConfig, RolePlacement, Topology
from .netns import netns_name, node_ip
from .process import LOOPBACK, Plan, Process, is_local_host


@dataclass
class _Slot:
    name: str
    kind: str
    rack: RackConfig
    node: NodeConfig
    index: int
    placement: RolePlacement
    parent: str | None = None
    children: list[str] = dataclasses.field(default_factory=list)
    actors: list[str] = dataclasses.field(default_factory=list)
    rollouts: list[str] = dataclasses.field(default_factory=list)
    ctrl_port: int | None = None
    data_port: int | None = None
    #: children assigned so far while the tree is built
    load: int = 0


def node_address(topo: Topology, rack_index: int, node_index: int, node: NodeConfig) -> str:
    """Where a node's planes bind: explicit address, the netns address, the remote host's name,
    or loopback."""
    if node.address:
        return node.address
    if not is_local_host(node.host):  # remote (SSH): its own name, resolved by Zenoh on both ends
        return node.host
    if topo.emulate == "netns":
        return node_ip(rack_index, node_index)
    return LOOPBACK


def make_plan(topo: Topology, run_dir: str, base_port: int | None = None) -> Plan:
    """Names every process, builds the weight tree and the links, assigns ports."""
    port = base_port if base_port is not None else topo.base_port
    slots: list[_Slot] = []
    addresses: dict[str, str] = {}
    for ri, rack in enumerate(topo.racks):
        for ni, node in enumerate(rack.nodes):
            addresses[node.name] = node_address(topo, ri, ni, node)
            for placement in node.roles:
                for i in range(placement.count):
                    slots.append(_Slot(f"{placement.role}-{node.name}-{i}", placement.role, rack, node, len(slots), placement))
    by_name = {s.name: s for s in slots}
    actors = [s for s in slots if s.kind == "actor"]
    root = actors[0]
    warnings: list[str] = []

    # Weight tree: root actor -> rack heads (a tree of racks) -> the rack's replicators -> leaves.
    _relay_tree(topo, slots, root)
    for rack in topo.racks:
        reps = [s for s in slots if s.kind == "replicator" and s.rack is rack]
        leaves = [s for s in slots if s.kind in ("rollout", "evaluator") and s.rack is rack]
        for leaf in leaves:
            if not reps:
                leaf.parent = root.name
                continue
            same_node = [r for r in reps if r.node is leaf.node]
            candidates = same_node + [r for r in reps if r not in same_node]
            parent = min(candidates, key=lambda r: (r.load >= topo.replication.fanout, r not in same_node, r.load))
            parent.load += 1
            leaf.parent = parent.name
    for s in slots:
        if s.parent is not None:
            by_name[s.parent].children.append(s.name)
    for s in slots:
        if len(s.children) > topo.replication.fanout:
            warnings.append(
                f"{s.name} has {len(s.children)} children, above fanout {topo.replication.fanout}: add a replicator on its rack"
            )
    # Data plane: every rollout feeds one rank of the learner group.
    for rollout_name, actor_name in route_rollouts(topo, slots).items():
        by_name[rollout_name].actors.append(actor_name)
        by_name[actor_name].rollouts.append(rollout_name)

    # Ports: listeners only (actors: ctrl + data, replicators: ctrl).
    for s in slots:
        if s.kind == "actor":
            s.ctrl_port, s.data_port = port, port + 1
            port += 2
        elif s.kind == "replicator":
            s.ctrl_port = port
            port += 1
    # The learner group's rendezvous: torch.distributed's TCP store on rank 0's node.
    group_port = port if len(actors) > 1 else None
    if group_port is not None:
        port += 1

    tls_planes = topo.tls.planes if topo.tls is not None else ()

    def ep(s: _Slot, which: str) -> str:
        p = s.ctrl_port if which == "ctrl" else s.data_port
        scheme = "tls" if which in tls_planes else "tcp"
        return f"{scheme}/{addresses[s.node.name]}:{p}"

    def ancestors(s: _Slot) -> list[_Slot]:
        out, cur = [], s
        while cur.parent is not None:
            cur = by_name[cur.parent]
            out.append(cur)
        return out

    evaluators = [s for s in slots if s.kind == "evaluator"]
    order = {"actor": 0, "replicator": 1, "rollout": 2, "evaluator": 3}
    processes = []
    for s in sorted(slots, key=lambda s: (order[s.kind], s.index)):
        anc = ancestors(s)
        if s.kind == "actor":
            ctrl = PlaneEndpoints(mode="router", listen=(ep(s, "ctrl"),), connect=() if s is root else (ep(root, "ctrl"),))
            data = PlaneEndpoints(mode="peer", listen=(ep(s, "data"),))
        elif s.kind == "replicator":
            ctrl = PlaneEndpoints(mode="router", listen=(ep(s, "ctrl"),), connect=(ep(anc[0], "ctrl"),))
            data = PlaneEndpoints(mode="peer")
        else:
            ctrl = PlaneEndpoints(mode="client", connect=tuple(ep(a, "ctrl") for a in anc))
            # evaluators have no actors: an empty data plane
            data = PlaneEndpoints(mode="peer", connect=tuple(ep(by_name[a], "data") for a in s.actors))
        if "ctrl" in tls_planes:
            ctrl = dataclasses.replace(ctrl, tls=topo.tls)
        if "data" in tls_planes:
            data = dataclasses.replace(data, tls=topo.tls)
        cfg = RoleConfig(
            name=s.name, kind=s.kind, run=topo.run, node=s.node.name, rack=s.rack.name,  # type: ignore[arg-type]
            seed=topo.seed * 1000 + s.index, mode=topo.mode, run_dir=run_dir,
            data=data, ctrl=ctrl, shared_memory=topo.shared_memory,
            parent=s.parent, ancestors=tuple(a.name for a in anc), children=tuple(s.children),
            actors=tuple(s.actors), rollouts=tuple(s.rollouts),
            cpus=role_cpus(s.node, s.placement), lane_cpus=s.placement.lane_cpus,
            lockstep_steps=_lockstep_steps(topo, s, by_name),
            sim_workers=s.placement.sim_workers, node_rollouts=s.node.role_counts().get("rollout", 1), task=topo.task, replication=topo.replication,
            group=_group_rank(topo, actors, s, f"tcp://{addresses[root.node.name]}:{group_port}") if group_port else None,
            eval_shard=(evaluators.index(s), len(evaluators)) if s.kind == "evaluator" else (0, 1),
            eval_seed=topo.task.eval.first_seed(topo.seed),
        )
        netns = netns_name(topo.run, s.node.name) if topo.emulate == "netns" else None
        processes.append(Process(config=cfg, host=s.node.host, netns=netns))

    first_port = base_port if base_port is not None else topo.base_port
    processes += _routers(topo, run_dir, addresses, root, actors, ep, range(first_port, port), warnings)
    entry = [ep(root, "ctrl")] + [ep(s, "ctrl") for s in slots if s.kind == "replicator"]
    return Plan(processes=tuple(processes), ctrl_entry=tuple(entry), addresses=addresses, warnings=tuple(warnings))


def _routers(topo: Topology, run_dir: str, addresses: dict[str, str], root: _Slot, actors: list[_Slot], ep, planned: range,
             warnings: list[str]) -> list[Process]:
    """One process per node with ``router:``: a Zenoh router per plane, the ctrl one connected to
    the root actor's ctrl router, the data one to every actor's data listener, both listening
    where outside rollouts (``dvla join``) dial in."""
    out = []
    tls_planes = topo.tls.planes if topo.tls is not None else ()
    for ri, rack in enumerate(topo.racks):
        for node in rack.nodes:
            r = node.router
            if r is None:
                continue
            for plane, p in (("ctrl", r.ctrl), ("data", r.data)):
                if p in planned:
                    warnings.append(f"{node.name}: router.{plane} port {p} is also planned for a role "
                                    f"(ports {planned.start}-{planned.stop - 1}): pick one outside them")
            listen = r.address or addresses[node.name]

            def plane(which: str, port: int, connect: tuple[str, ...]) -> PlaneEndpoints:
                scheme = "tls" if which in tls_planes else "tcp"
                return PlaneEndpoints(mode="router", listen=(f"{scheme}/{listen}:{port}",), connect=connect,
                                      tls=topo.tls if which in tls_planes else None)

            cfg = RoleConfig(
                name=f"router-{node.name}-0", kind="router", run=topo.run, node=node.name, rack=rack.name,
                seed=topo.seed, mode=topo.mode, run_dir=run_dir,
                ctrl=plane("ctrl", r.ctrl, (ep(root, "ctrl"),)),
                data=plane("data", r.data, tuple(ep(a, "data") for a in actors)),
                shared_memory=False, parent=root.name, ancestors=(root.name,), children=(), actors=(), rollouts=(),
                task=topo.task, replication=topo.replication,
            )
            netns = netns_name(topo.run, node.name) if topo.emulate == "netns" else None
            out.append(Process(config=cfg, host=node.host, netns=netns))
    return out


def router_endpoints(plan: Plan, plane: str) -> tuple[str, ...]:
    """Where outside rollouts dial `plane`: every router's listener, a "0.0.0.0" one as its node's
    address."""
    out = []
    for p in plan.processes:
        if p.config.kind == "router":
            for locator in (p.config.ctrl if plane == "ctrl" else p.config.data).listen:
                out.append(locator.replace("/0.0.0.0:", f"/{plan.addresses[p.config.node]}:"))
    return tuple(out)


def _relay_tree(topo: Topology, slots: list[_Slot], root: _Slot) -> None:
    """Parents of the replicators. Inside a rack the replicators form a ``relay_fanout``-ary tree
    under the rack's head (its first replicator); racks with replicators form a ``relay_fanout``-ary
    tree too (the root actor's rack first), each rack's child racks fed by the rack's last
    replicator. The root actor feeds its own rack's head only (or, without one, the first racks'
    heads). With the default 1 the relays form one chain, so every NIC and rack uplink carries a
    version once towards other relays (docs/replication.md, "Tree shape")."""
    k = topo.replication.relay_fanout
    reps_of = {rack.name: [s for s in slots if s.kind == "replicator" and s.rack is rack] for rack in topo.racks}
    # position 0: the root actor's own rack (fed by the root actor itself; None: it has no
    # replicator, and the root feeds position 0's children directly); racks 1.. the k-ary tree
    others = [reps_of[r.name] for r in topo.racks if reps_of[r.name] and r is not root.rack]
    racks: list[list[_Slot] | None] = [reps_of[root.rack.name] or None, *others]
    for i, reps in enumerate(racks):
        if reps is None:
            continue
        up = None if i == 0 else racks[(i - 1) // k]
        reps[0].parent = up[-1].name if up is not None else root.name
        for j, r in enumerate(reps[1:], start=1):
            r.parent = reps[(j - 1) // k].name
    for s in slots:
        if s.kind == "replicator" and s.parent is not None:
            next(x for x in slots if x.name == s.parent).load += 1


def route_rollouts(topo: Topology, slots: list[_Slot]) -> dict[str, str]:
    """rollout name -> the actor (learner rank) it ships to.

    "nearest": an actor on the rollout's node, else on its rack, else any; among those the one
    fed by the fewest rollouts so far (then placement order), so a node placed at 3:1 feeds its
    own rank and rollouts on actor-less nodes spread evenly. "round_robin": placement order.
    """
    actors = [s for s in slots if s.kind == "actor"]
    load = {a.name: 0 for a in actors}
    out: dict[str, str] = {}
    for i, s in enumerate(x for x in slots if x.kind == "rollout"):
        if topo.learners.routing == "round_robin":
            pick = actors[i % len(actors)]
        else:
            near = [a for a in actors if a.node is s.node] or [a for a in actors if a.rack is s.rack] or actors
            pick = min(near, key=lambda a: load[a.name])
        load[pick.name] += 1
        out[s.name] = pick.name
    return out


def _group_rank(topo: Topology, actors: list[_Slot], s: _Slot, init_method: str) -> GroupRank | None:
    if s.kind != "actor":
        return None
    g = topo.learners
    return GroupRank(rank=actors.index(s), world_size=len(actors), init_method=init_method, backend=g.backend,
                     strategy=g.strategy, timeout_s=g.timeout_s, members=tuple(a.name for a in actors))


def _lockstep_steps(topo: Topology, s: _Slot, by_name: dict[str, _Slot]) -> int:
    """Env steps each rollout ships per version in sync mode: its share of one learner batch."""
    if s.kind != "rollout" or not s.actors:
        return 0
    n_rollouts = len(by_name[s.actors[0]].rollouts)
    return -(-topo.task.ppo.batch_steps // n_rollouts)


def role_cpus(node: NodeConfig, placement: RolePlacement) -> tuple[int, ...] | None:
    """Cores a role's processes are pinned to: the role's own ``cpus``, else the node's."""
    return placement.cpus if placement.cpus is not None else node.cpus


def pinning_problems(topo: Topology, allowed: set[int] | None = None) -> list[str]:
    """One line per pinned core a role on this machine cannot have: ``cpus`` (node or role)
    and ``lane_cpus`` checked against this host's usable cores (``os.sched_getaffinity``).
    Remote nodes' cores are theirs to check."""
    if allowed is None:
        if not hasattr(os, "sched_getaffinity"):
            return []
        allowed = set(os.sched_getaffinity(0))
    problems: list[str] = []
    for _rack, node in topo.nodes():
        if not is_local_host(node.host):
            continue
        for placement in node.roles:
            pinned = [("cpus", role_cpus(node, placement) or ())]
            pinned += [(f"lane_cpus.{lane}", cores) for lane, cores in (placement.lane_cpus or {}).items()]
            for key, cores in pinned:
                missing = set(cores) - allowed
                if missing:
                    problems.append(f"node {node.name}, role {placement.role}: {key} names core(s) {_core_list(missing)}, "
                                    f"which this host does not have (usable cores: {_core_list(allowed)})")
    return problems


def _core_list(cores: set[int]) -> str:
    return ",".join(str(c) for c in sorted(cores))
