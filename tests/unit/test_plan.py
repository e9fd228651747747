"""The plan: names, weight tree, link graph and ports derived from a topology."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from dvla.config import LinkConfig, RoleConfig
from dvla.orchestrator.plan import make_plan
from dvla.orchestrator.topology import load_topology, parse_topology

ROOT = Path(__file__).resolve().parents[2]

TWO_RACKS = """
run: t2
replication: {fanout: 4}
racks:
  - name: ra
    nodes:
      - {name: a0, roles: [{role: actor}, {role: replicator}, {role: rollout}]}
      - {name: a1, roles: [{role: rollout, count: 2}]}
  - name: rb
    nodes:
      - {name: b0, roles: [{role: replicator}, {role: rollout}]}
      - {name: b1, roles: [{role: rollout}, {role: evaluator}]}
  - name: rc
    nodes:
      - {name: c0, roles: [{role: rollout}]}
"""


def test_local_plan_wires_tree_and_links() -> None:
    plan = make_plan(load_topology(ROOT / "topologies/local.yaml"), "/tmp/run", base_port=20000)
    names = [p.config.name for p in plan.processes]
    assert names[0] == "actor-node0-0"  # actors start first: they are the routers others reach
    actor = plan.by_name("actor-node0-0").config
    rep = plan.by_name("replicator-node0-0").config
    ro = plan.by_name("rollout-node0-1").config
    assert actor.ctrl.mode == "router" and actor.ctrl.listen == ("tcp/127.0.0.1:20000",)
    assert actor.data.listen == ("tcp/127.0.0.1:20001",)
    assert rep.parent == "actor-node0-0" and rep.ctrl.connect == actor.ctrl.listen
    assert ro.parent == "replicator-node0-0" and ro.ancestors == ("replicator-node0-0", "actor-node0-0")
    # client of its parent first, ancestors as fallbacks (re-attach on failure)
    assert ro.ctrl.mode == "client" and ro.ctrl.connect == rep.ctrl.listen + actor.ctrl.listen
    assert ro.data.connect == actor.data.listen and ro.actors == ("actor-node0-0",)
    assert set(actor.rollouts) == {"rollout-node0-0", "rollout-node0-1"}
    assert plan.ctrl_entry[0] == actor.ctrl.listen[0]


def test_tree_follows_racks_and_fanout() -> None:
    plan = make_plan(parse_topology(TWO_RACKS, "two.yaml"), "/tmp/run")
    cfg = {p.config.name: p.config for p in plan.processes}
    assert cfg["replicator-a0-0"].parent == "actor-a0-0"
    # the next rack hangs off the root rack's (last) replicator: the actor's NIC carries one copy
    assert cfg["replicator-b0-0"].parent == "replicator-a0-0"
    for leaf in ("rollout-a0-0", "rollout-a1-0", "rollout-a1-1"):
        assert cfg[leaf].parent == "replicator-a0-0"
    for leaf in ("rollout-b0-0", "rollout-b1-0", "evaluator-b1-0"):
        assert cfg[leaf].parent == "replicator-b0-0"
    # a rack without a replicator hangs off the actor directly
    assert cfg["rollout-c0-0"].parent == "actor-a0-0"
    # every listed child names its parent back
    for c in cfg.values():
        for child in c.children:
            assert cfg[child].parent == c.name
    # replicator-a0-0 has 4 children (3 rollouts + rack b's head): at the fanout cap, no warning
    assert plan.warnings == ()


def _racks(n_racks: int, reps_per_rack: int, relay_fanout: int) -> str:
    racks = []
    for r in range(n_racks):
        nodes = [f"      - {{name: n{r}x{j}, roles: [{{role: replicator}}, {{role: rollout}}]}}" for j in range(reps_per_rack)]
        if r == 0:
            nodes.insert(0, "      - {name: root, roles: [{role: actor}]}")
        racks.append(f"  - name: r{r}\n    nodes:\n" + "\n".join(nodes))
    return f"run: chain\nreplication: {{relay_fanout: {relay_fanout}}}\nracks:\n" + "\n".join(racks) + "\n"


def test_relay_fanout_one_chains_replicators_within_and_across_racks() -> None:
    plan = make_plan(parse_topology(_racks(3, 3, 1), "chain.yaml"), "/tmp/run")
    parent = {p.config.name: p.config.parent for p in plan.processes}
    chain = ["actor-root-0"] + [f"replicator-n{r}x{j}-0" for r in range(3) for j in range(3)]
    for up, down in zip(chain, chain[1:]):
        assert parent[down] == up, (down, parent[down], up)
    # every relay forwards to at most one relay on another node: one copy per NIC and uplink
    relay_children = {name: [c for c, p in parent.items() if p == name and c.startswith("replicator")] for name in chain}
    assert max(len(v) for v in relay_children.values()) == 1
    assert all(parent[f"rollout-n{r}x{j}-0"] == f"replicator-n{r}x{j}-0" for r in range(3) for j in range(3))


def test_relay_fanout_two_builds_binary_trees() -> None:
    plan = make_plan(parse_topology(_racks(5, 3, 2), "tree.yaml"), "/tmp/run")
    parent = {p.config.name: p.config.parent for p in plan.processes}
    # inside a rack: head -> two replicators
    assert parent["replicator-n0x1-0"] == parent["replicator-n0x2-0"] == "replicator-n0x0-0"
    # racks 1 and 2 hang off rack 0's last replicator, racks 3 and 4 off rack 1's
    assert parent["replicator-n1x0-0"] == parent["replicator-n2x0-0"] == "replicator-n0x2-0"
    assert parent["replicator-n3x0-0"] == parent["replicator-n4x0-0"] == "replicator-n1x2-0"
    assert parent["replicator-n0x0-0"] == "actor-root-0"


def test_fanout_overflow_is_warned() -> None:
    text = TWO_RACKS.replace("fanout: 4", "fanout: 2")
    plan = make_plan(parse_topology(text, "two.yaml"), "/tmp/run")
    assert any("above fanout 2" in w for w in plan.warnings)


def test_role_config_json_round_trip() -> None:
    plan = make_plan(parse_topology(TWO_RACKS, "two.yaml"), "/tmp/run")
    for p in plan.processes:
        assert RoleConfig.from_json(p.config.to_json()) == p.config


def test_role_and_lane_pinning_reach_each_process() -> None:
    text = """
run: pin
racks:
  - name: r
    nodes:
      - name: n
        cpus: [1]
        roles:
          - {role: actor}
          - {role: rollout, count: 2, lane_cpus: {sim: [0]}}
          - {role: evaluator, cpus: [0, 1]}
"""
    plan = make_plan(parse_topology(text, "pin.yaml"), "/tmp/run")
    by = {p.config.name: p.config for p in plan.processes}
    assert by["actor-n-0"].cpus == (1,) and by["actor-n-0"].lane_cpus is None  # the node's
    for name in ("rollout-n-0", "rollout-n-1"):
        assert by[name].cpus == (1,) and by[name].lane_cpus == {"sim": (0,)}
    assert by["evaluator-n-0"].cpus == (0, 1)  # the role's own cpus win over the node's
    for cfg in by.values():
        assert RoleConfig.from_json(cfg.to_json()) == cfg


def test_ports_are_unique() -> None:
    plan = make_plan(parse_topology(TWO_RACKS, "two.yaml"), "/tmp/run", base_port=30000)
    eps = [e for p in plan.processes for e in p.config.ctrl.listen + p.config.data.listen]
    assert len(eps) == len(set(eps)) == 2 + 2  # actor ctrl+data, two replicator ctrl


def _routing(text: str) -> dict[str, list[str]]:
    plan = make_plan(parse_topology(text), "/tmp/run", base_port=20000)
    return {p.config.name: list(p.config.rollouts) for p in plan.processes if p.config.kind == "actor"}


def _group_topology(nodes: str, learners: str = "") -> str:
    return f"run: g\n{learners}task: {{budget: {{max_env_steps: 1000}}}}\nracks:\n{nodes}"


def test_routing_at_3_to_1_per_node_keeps_each_rollout_on_its_nodes_rank() -> None:
    nodes = """  - name: r0
    nodes:
      - {name: n0, roles: [{role: actor}, {role: replicator}, {role: rollout, count: 3}]}
      - {name: n1, roles: [{role: actor}, {role: rollout, count: 3}]}
"""
    routes = _routing(_group_topology(nodes, 'learners: {ratio: "3:1"}\n'))
    assert routes == {"actor-n0-0": ["rollout-n0-0", "rollout-n0-1", "rollout-n0-2"],
                      "actor-n1-0": ["rollout-n1-0", "rollout-n1-1", "rollout-n1-2"]}
    plan = make_plan(parse_topology(_group_topology(nodes)), "/tmp/run", base_port=20000)
    ranks = [p.config.group for p in plan.processes if p.config.kind == "actor"]
    assert [(g.rank, g.world_size) for g in ranks] == [(0, 2), (1, 2)]
    # one rendezvous, on rank 0's node, at a port no plane uses
    assert len({g.init_method for g in ranks}) == 1 and ranks[0].init_method.startswith("tcp://127.0.0.1:")
    used = {ep for p in plan.processes for ep in p.config.ctrl.listen + p.config.data.listen}
    assert not any(ep.endswith(":" + ranks[0].init_method.rsplit(":", 1)[1]) for ep in used)
    # the weight tree stays rooted at rank 0 only
    assert plan.by_name("actor-n1-0").config.children == ()


def test_routing_at_1_to_1_on_one_node_and_to_the_least_loaded_nearby_rank() -> None:
    one_node = "  - name: r0\n    nodes:\n      - {name: n0, roles: [{role: actor, count: 2}, {role: rollout, count: 2}]}\n"
    assert _routing(_group_topology(one_node, 'learners: {ratio: "1:1"}\n')) == {
        "actor-n0-0": ["rollout-n0-0"], "actor-n0-1": ["rollout-n0-1"]}
    # rollouts on actor-less nodes go to a rank on their rack first, spread evenly
    racks = """  - name: ra
    nodes:
      - {name: a0, roles: [{role: actor, count: 2}]}
      - {name: a1, roles: [{role: rollout, count: 4}]}
  - name: rb
    nodes:
      - {name: b0, roles: [{role: actor}]}
      - {name: b1, roles: [{role: rollout}]}
"""
    routes = _routing(_group_topology(racks))
    assert routes == {"actor-a0-0": ["rollout-a1-0", "rollout-a1-2"], "actor-a0-1": ["rollout-a1-1", "rollout-a1-3"],
                      "actor-b0-0": ["rollout-b1-0"]}
    assert sorted(sum(_routing(_group_topology(racks, "learners: {routing: round_robin}\n")).values(), [])) == sorted(
        sum(routes.values(), []))


@pytest.mark.parametrize("learners, message", [
    ('learners: {ratio: "3:1"}\n', "ratio 3:1 but n0 places 2 rollout(s) and 2 actor(s)"),
    ('learners: {ratio: "3/1"}\n', "is not a rollout:learner ratio"),
    ('learners: {ratio: "1:1", ratio_per: run}\n', None),
    ('learners: {strategy: fsdp}\n', "strategy"),
    ('learners: {backend: nccl}\ntask: {device: cpu, budget: {max_env_steps: 10}}\n', "nccl needs CUDA"),
])
def test_learner_group_settings_are_checked(learners: str, message: str | None) -> None:
    nodes = "  - name: r0\n    nodes:\n      - {name: n0, roles: [{role: actor, count: 2}, {role: rollout, count: 2}]}\n"
    text = _group_topology(nodes, learners)
    if "task:" in learners:
        text = text.replace("task: {budget: {max_env_steps: 1000}}\n", "", 1)
    if message is None:
        parse_topology(text)
        return
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        parse_topology(text)


def test_sim_workers_reach_each_rollout_with_its_nodes_rollout_count() -> None:
    text = """
run: simw
racks:
  - name: r
    nodes:
      - name: a
        roles: [{role: actor}, {role: rollout, count: 2, sim_workers: auto}, {role: evaluator}]
      - name: b
        roles: [{role: rollout, sim_workers: 3}]
"""
    plan = make_plan(parse_topology(text, "simw.yaml"), "/tmp/run")
    by = {p.config.name: p.config for p in plan.processes}
    assert [(by[n].sim_workers, by[n].node_rollouts) for n in ("rollout-a-0", "rollout-a-1", "rollout-b-0")] == [
        ("auto", 2), ("auto", 2), (3, 1)]
    assert by["actor-a-0"].sim_workers == 0 and by["evaluator-a-0"].sim_workers == 0
    for cfg in by.values():
        assert RoleConfig.from_json(cfg.to_json()) == cfg


ROUTED = """
run: tr
learners: {routing: round_robin}
racks:
  - name: ra
    nodes:
      - {name: a0, roles: [{role: actor}, {role: rollout}], router: {ctrl: 7447, data: 7448, address: 0.0.0.0}}
      - {name: a1, roles: [{role: actor}, {role: rollout}]}
"""


def test_a_node_router_is_one_process_linking_outside_clients_to_both_planes() -> None:
    from dvla.orchestrator.plan import router_endpoints

    plan = make_plan(parse_topology(ROUTED, "r.yaml"), "/tmp/run", base_port=20000)
    router = plan.by_name("router-a0-0").config
    assert plan.processes[-1].config is router  # started last, once the actors listen
    assert (router.kind, router.ctrl.mode, router.data.mode) == ("router", "router", "router")
    assert router.ctrl.listen == ("tcp/0.0.0.0:7447",) and router.data.listen == ("tcp/0.0.0.0:7448",)
    assert router.ctrl.connect == (plan.ctrl_entry[0],)  # the root actor's ctrl router
    actors = [p.config for p in plan.processes if p.config.kind == "actor"]
    assert router.data.connect == tuple(a.data.listen[0] for a in actors)  # chunks can reach every rank
    assert router.name not in {c for a in actors for c in a.children}  # not a weight-tree member
    assert router_endpoints(plan, "ctrl") == ("tcp/127.0.0.1:7447",)  # 0.0.0.0: dialled at the node's address
    assert router_endpoints(plan, "data") == ("tcp/127.0.0.1:7448",)
    assert not plan.warnings


def test_a_router_port_among_the_planned_ports_is_warned() -> None:
    plan = make_plan(parse_topology(ROUTED, "r.yaml"), "/tmp/run", base_port=7446)
    assert any("router.ctrl port 7447 is also planned" in w for w in plan.warnings), plan.warnings
