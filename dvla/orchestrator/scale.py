"""`dvla plan --simulate`: a whole-pipeline model of a topology at any size (docs/scale.md).

:func:`tile` repeats a topology's racks up to N nodes; :func:`version_bytes` is one weight
version's wire size; :func:`simulate_pipeline` is a SimPy discrete-event run of rollouts, shared
data links, DDP learner ranks and the replication tree (:mod:`.simulate`), from which policy lag
results; :func:`speedup_table` runs it from 8 to 1,024 nodes and names where speedup stops being linear.
"""

from __future__ import annotations

import dataclasses
import math
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

import simpy

from ..config import RackConfig, SimulateConfig, Topology, range_problems
from .plan import Plan, make_plan
from .simulate import BroadcastPrediction, HostCosts, link_rate, max_min_rates, path_links, simulate_broadcast

BYTES_PER_PARAM = {"fp32": 4, "bf16": 2}
#: parameters assumed without `simulate.params`: 1.1 MB of fp32, about the default MLP policy's
DEFAULT_PARAMS = 275_000
#: versions simulated per run (the first few fill the pipeline and are not counted)
VERSIONS, WARMUP = 24, 4
#: a learner rank keeps at most this many batches of env steps waiting; older ones are dropped
POOL_BATCHES = 2
#: blocks per version in the speedup table's broadcasts (throughput exact, pipeline fill per chunk)
TABLE_BLOCKS = 16
#: below this share of linear speedup the curve has bent
LINEAR_SHARE = 0.9


class ScaleError(ValueError):
    """Bad simulation input; the message names the flag or key."""


@dataclass(frozen=True, kw_only=True)
class PipelinePrediction:
    """Predicted steady state of one topology (every figure over the counted versions)."""

    nodes: int
    racks: int
    rollouts: int
    learner_ranks: int
    #: env steps the learners train on per second, and the rollouts' production
    env_steps_per_s: float
    produced_env_steps_per_s: float
    #: share of wall time the ranks compute or communicate, and the communication part of it
    learner_utilisation: float
    comm_share: float
    #: versions between the behaviour policy of trained steps and the learner's
    policy_lag_mean: float
    policy_lag_max: float
    #: seconds between versions, and a version's trip through the tree
    version_interval_s: float
    broadcast: BroadcastPrediction
    #: what holds throughput: "learner", "rollouts", "data link <link>", or "weight broadcast"
    limit: str
    limit_detail: str
    #: per rank: data-plane env steps/s arriving
    data_link: str = ""
    extras: dict[str, Any] = field(default_factory=dict)


def version_bytes(cfg: SimulateConfig, topo: Topology) -> tuple[int, int]:
    """Bytes of a full version and of a delta version (equal for `full`)."""
    params = cfg.params if cfg.params is not None else DEFAULT_PARAMS
    trained = params * cfg.trainable_fraction
    full = int(trained * BYTES_PER_PARAM[cfg.dtype])
    enc = topo.replication.encoding
    if enc == "delta-bf16":
        delta = int(trained * 2)
    elif enc == "delta-topk":
        delta = int(math.ceil(trained * topo.replication.topk_fraction) * 8)
    else:
        delta = full
    return max(1, full), max(1, delta)


#: the `dvla plan` flag of each `simulate:` key (named in errors beside the key)
FLAG = {"nodes": "--nodes", "racks": "--racks", "params": "--params", "env_steps_per_s": "--env-rate",
        "step_bytes": "--step-bytes", "learner_steps_per_s": "--learner-rate", "trainable_fraction": "--trainable-fraction",
        "hop_latency_s": "--hop-latency-s", "node_memory_gib": "--node-memory-gib", "process_gbit": "--process-gbit"}


def _bad(key: str, text: str) -> ScaleError:
    return ScaleError(f"simulate.{key} ({FLAG[key]}): {text}")


def check_inputs(cfg: SimulateConfig, topo: Topology) -> None:
    """Raises ScaleError naming the key and its flag when the model cannot describe the cluster."""
    for key, message in range_problems(cfg):  # the flags override the topology's keys
        raise _bad(key, message)
    if cfg.nodes is not None and cfg.racks is not None and cfg.racks > cfg.nodes:
        raise _bad("racks", f"{cfg.racks} racks cannot hold {cfg.nodes} nodes")
    if cfg.node_memory_gib is not None:
        full, _ = version_bytes(cfg, topo)
        params = cfg.params if cfg.params is not None else DEFAULT_PARAMS
        # a rollout holds the whole model plus a staging copy of the trained weights
        need = params * BYTES_PER_PARAM[cfg.dtype] + full
        if need > cfg.node_memory_gib * (1 << 30):
            raise _bad("params", f"a {params:.3g}-parameter {cfg.dtype} model needs {need / (1 << 30):,.0f} GiB per rollout "
                       f"(model + staging copy), more than simulate.node_memory_gib = {cfg.node_memory_gib:g} GiB")


def tile(topo: Topology, nodes: int | None, racks: int | None) -> Topology:
    """The topology's racks repeated until it has `nodes` nodes in `racks` racks: rack i copies rack
    ``i mod R0``, node j that rack's node ``j mod n``; actors (learner ranks grow with the cluster)
    and replicators repeat, evaluators stay in the first; hosts become names (never started)."""
    template = [r for r in topo.racks if r.nodes]
    total0 = sum(len(r.nodes) for r in template)
    if nodes is None and racks is None:
        return topo
    n = nodes if nodes is not None else total0
    per_rack0 = max(len(r.nodes) for r in template)
    r_count = racks if racks is not None else max(1, math.ceil(n / per_rack0))
    out: list[RackConfig] = []
    for i in range(r_count):
        src = template[i % len(template)]
        count = n // r_count + (1 if i < n % r_count else 0)
        rack_nodes = []
        for j in range(count):
            node = src.nodes[j % len(src.nodes)]
            roles = tuple(p for p in node.roles if p.role != "evaluator" or (i == 0 and j < len(src.nodes)))
            rack_nodes.append(dataclasses.replace(node, name=f"r{i}n{j}", host=f"r{i}n{j}", address=f"r{i}n{j}",
                                                  roles=roles, cpus=None, ssh=None))
        out.append(RackConfig(name=f"r{i}", nodes=tuple(rack_nodes)))
    return dataclasses.replace(topo, racks=tuple(out), emulate="none", tls=None)


def _data_rates(topo: Topology, plan: Plan, cfg: SimulateConfig) -> tuple[dict[str, float], str]:
    """Env steps/s each rollout sustains once its data flow shares links max-min fairly."""
    where = {p.config.name: (p.config.rack, p.config.node) for p in plan.processes}
    flows: dict[int, tuple[str, ...]] = {}
    names = []
    demand = cfg.env_steps_per_s * cfg.step_bytes
    for p in plan.processes:
        if p.config.kind == "rollout" and p.config.actors:
            names.append(p.config.name)
            flows[len(flows)] = path_links(where, p.config.name, p.config.actors[0])
    # each flow also passes its own demand cap, modelled as a private link
    caps = {link: link_rate(topo, link) for links in flows.values() for link in links}
    for i in list(flows):
        flows[i] = (*flows[i], f"demand{i}")
        caps[f"demand{i}"] = demand
    rates = max_min_rates(flows, caps)
    busiest, share = "", 0.0
    load: dict[str, float] = defaultdict(float)
    for i, links in flows.items():
        for link in links[:-1]:
            load[link] += rates[i]
    for link, b in load.items():
        if b / caps[link] > share:
            busiest, share = link, b / caps[link]
    return {names[i]: rates[i] / cfg.step_bytes for i in flows}, (f"{busiest} {share:.0%} busy" if busiest else "none")


def allreduce_s(topo: Topology, plan: Plan, grad_bytes: float, hop_latency_s: float) -> float:
    """One ring all-reduce of `grad_bytes` over the learner ranks: 2(n-1)/n of the bytes through
    the slowest link the ring crosses, plus 2(n-1) latency steps."""
    actors = [p.config for p in plan.processes if p.config.kind == "actor"]
    n = len(actors)
    if n < 2:
        return 0.0
    links = set()
    for a, b in zip(actors, actors[1:] + actors[:1]):
        links.update(path_links({x.name: (x.rack, x.node) for x in actors}, a.name, b.name))
    rate = min((link_rate(topo, k) for k in links), default=math.inf)
    hops = 2 if any(" uplink " in k for k in links) else 1
    return 2 * (n - 1) / n * grad_bytes / rate + 2 * (n - 1) * hop_latency_s * (2 * hops)


def simulate_pipeline(topo: Topology, cfg: SimulateConfig, *, star: bool = True, max_blocks: int = 64) -> PipelinePrediction:
    """Simulates `VERSIONS` weight versions of the (already tiled) topology; the tree is simulated
    in `max_blocks` blocks per version, the star only when `star`."""
    check_inputs(cfg, topo)
    plan = make_plan(topo, run_dir="runs/simulate")
    full, delta = version_bytes(cfg, topo)
    costs = HostCosts(hop_latency_s=cfg.hop_latency_s, **_process_costs(cfg))
    bc_full = simulate_broadcast(topo, plan, full, costs, max_blocks=max_blocks, star=star)
    bc_delta = bc_full if delta == full else simulate_broadcast(topo, plan, delta, costs, max_blocks=max_blocks, star=False)
    rollout_rate, data_link = _data_rates(topo, plan, cfg)
    actors = [p.config for p in plan.processes if p.config.kind == "actor"]
    feed = {a.name: sum(rollout_rate[r] for r in a.rollouts) for a in actors}
    if not any(feed.values()):
        raise ScaleError(f"{topo.source}: no rollout feeds a learner: nothing to simulate")
    ppo = topo.task.ppo
    share = ppo.batch_steps  # env steps per rank per version
    grad_bytes = (cfg.params or DEFAULT_PARAMS) * cfg.trainable_fraction * BYTES_PER_PARAM[cfg.dtype]
    comm = allreduce_s(topo, plan, grad_bytes, cfg.hop_latency_s) * ppo.update_epochs * ppo.minibatches
    compute = share / cfg.learner_steps_per_s
    sync = topo.mode == "sync"

    env = simpy.Environment()
    arrivals: list[float] = [0.0]  # version v reaches every rollout at arrivals[v]
    arrived = [env.event() for _ in range(VERSIONS + 1)]
    arrived[0].succeed()
    published: list[float] = [0.0]
    rec: dict[str, list[float]] = defaultdict(list)
    pending: list[int] = []
    wake = {"ev": env.event()}

    def behaviour_version(t: float) -> int:
        return max(v for v, a in enumerate(arrivals) if a <= t) if arrivals else 0

    def learner():
        taken = {a: 0.0 for a in feed}
        t_prod = 0.0  # async: rollouts produce from the start
        for v in range(1, VERSIONS + 1):
            if sync:
                yield arrived[v - 1]  # lock-step: collect with the newest weights, then learn
                start = env.now
                wait = max(share / feed[a] for a in feed if feed[a] > 0)
                yield env.timeout(wait)
                span = (start, start + wait)
            else:
                # steps acted on by a policy more than max_policy_lag versions old are dropped,
                # so the learner can run at most that far ahead of the rollouts' weights
                old = v - 1 - ppo.max_policy_lag
                if old >= 1:
                    yield arrived[old]
                    for a in feed:
                        taken[a] = max(taken[a], feed[a] * (arrivals[old] - t_prod))
                # DDP: the update starts once every rank holds its batch
                need = max((taken[a] + share) / feed[a] for a in feed if feed[a] > 0)
                yield env.timeout(max(0.0, t_prod + need - env.now))
                for a in feed:  # the pool keeps the newest POOL_BATCHES batches; older steps drop
                    taken[a] = max(taken[a], feed[a] * (env.now - t_prod) - POOL_BATCHES * share)
                first = min((taken[a] / feed[a] for a in feed if feed[a] > 0), default=env.now)
                span = (t_prod + first, env.now)
                for a in feed:
                    taken[a] += share
            t0 = env.now
            yield env.timeout(compute + comm)
            rec["busy"].append(env.now - t0)
            rec["comm"].append(comm)
            lag = [v - 1 - behaviour_version(span[0] + (span[1] - span[0]) * q) for q in (0.0, 0.5, 1.0)]
            rec["lag"].append(sum(lag) / len(lag))
            rec["lag_max"].append(max(lag))
            published.append(env.now)
            pending.append(v)
            if not wake["ev"].triggered:
                wake["ev"].succeed()
        rec["end"].append(env.now)

    def publisher():
        """Rank 0 sends the newest version once the previous one left the tree."""
        sent = 0
        while sent < VERSIONS:
            if not pending:
                wake["ev"] = env.event()
                yield wake["ev"]
            v = pending[-1]
            skipped = len(pending) - 1
            pending.clear()
            bc = bc_full if (v - 1) % topo.replication.snapshot_every == 0 else bc_delta
            rec["skipped"].append(skipped)
            yield env.timeout(bc.tree_s)
            while len(arrivals) <= v:
                arrivals.append(env.now)
                arrived[len(arrivals) - 1].succeed()
            sent = v

    env.process(learner())
    env.process(publisher())
    env.run()
    end = rec["end"][0]
    t_from = published[WARMUP]
    counted = VERSIONS - WARMUP
    span_s = end - t_from
    trained = counted * share * len(feed) / span_s if span_s > 0 else math.inf
    produced = sum(feed.values())
    util = sum(rec["busy"][WARMUP:]) / span_s if span_s > 0 else 1.0
    limit, detail = _limit(util, produced, trained, cfg, len(rollout_rate), data_link, rec, bc_full, span_s / counted, sync)
    nodes = len(topo.nodes())
    return PipelinePrediction(
        nodes=nodes, racks=len(topo.racks), rollouts=len(rollout_rate), learner_ranks=len(feed),
        env_steps_per_s=trained, produced_env_steps_per_s=produced,
        learner_utilisation=min(1.0, util), comm_share=(comm / (compute + comm)) if compute + comm > 0 else 0.0,
        policy_lag_mean=sum(rec["lag"][WARMUP:]) / counted, policy_lag_max=max(rec["lag_max"][WARMUP:]),
        version_interval_s=span_s / counted, broadcast=bc_full, limit=limit, limit_detail=detail, data_link=data_link,
        extras={"version_bytes_full": full, "version_bytes_delta": delta, "compute_s_per_version": compute,
                "comm_s_per_version": comm, "delta_broadcast_s": bc_delta.tree_s,
                "versions_skipped": sum(rec["skipped"])},
    )


def _process_costs(cfg: SimulateConfig) -> dict[str, float]:
    if cfg.process_gbit is None:
        return {}
    s_per_mib = (1 << 20) * 8 / (cfg.process_gbit * 1e9)
    return {"relay_s_per_mib": s_per_mib, "sink_s_per_mib": s_per_mib}


def _limit(util: float, produced: float, trained: float, cfg: SimulateConfig, rollouts: int, data_link: str,
           rec: dict[str, list[float]], bc: BroadcastPrediction, interval: float, sync: bool) -> tuple[str, str]:
    """Names what holds throughput at this size."""
    if sync:
        return "lock-step", f"collect, learn and broadcast ({bc.tree_s:.2f} s) run one after the other"
    if util >= 0.97:
        comm = sum(rec["comm"][WARMUP:]) / max(1e-12, sum(rec["busy"][WARMUP:]))
        why = f"all-reduce {comm:.0%} of its time" if comm >= 0.2 else "compute"
        return "learner", f"ranks busy {util:.0%} ({why})"
    if bc.tree_s > interval * 1.01:
        return "weight broadcast", f"a version takes {bc.tree_s:.2f} s to reach the rollouts, one is ready every {interval:.2f} s"
    if produced < rollouts * cfg.env_steps_per_s * 0.99:
        return "data link", f"rollouts slowed to {produced / rollouts:.0f} of {cfg.env_steps_per_s:.0f} env steps/s each ({data_link})"
    return "rollouts", f"simulators at {cfg.env_steps_per_s:.0f} env steps/s each; learner ranks busy {util:.0%}"


@dataclass(frozen=True)
class SpeedupRow:
    nodes: int
    racks: int
    env_steps_per_s: float
    speedup: float
    linear: float
    share_of_linear: float
    broadcast_s: float
    bound_s: float
    policy_lag_mean: float
    learner_utilisation: float
    limit: str
    limit_detail: str


def speedup_table(topo: Topology, cfg: SimulateConfig, sizes: list[int]) -> tuple[list[SpeedupRow], SpeedupRow | None]:
    """The pipeline at each node count (racks scaled to keep the nodes per rack of `cfg`), speedup
    against the first size, and the first row below 0.9 of linear."""
    per_rack = (cfg.nodes / cfg.racks) if cfg.nodes and cfg.racks else max(len(r.nodes) for r in topo.racks)
    rows: list[SpeedupRow] = []
    base: PipelinePrediction | None = None
    for n in sizes:
        t = tile(topo, n, max(1, round(n / per_rack)))
        pred = simulate_pipeline(t, dataclasses.replace(cfg, nodes=None, racks=None), star=False, max_blocks=TABLE_BLOCKS)
        base = base or pred
        speed = pred.env_steps_per_s / base.env_steps_per_s
        linear = n / sizes[0]
        rows.append(SpeedupRow(n, len(t.racks), pred.env_steps_per_s, speed, linear, speed / linear,
                               pred.broadcast.tree_s, pred.broadcast.bound_s, pred.policy_lag_mean,
                               pred.learner_utilisation, pred.limit, pred.limit_detail))
    bend = next((r for r in rows if r.share_of_linear < LINEAR_SHARE), None)
    return rows, bend
