"""The default workload's ratio against a bracketing simulator baseline (pure logic: the runs
themselves are replaced by canned results; tests/integration/test_bench_swimlane.py runs them)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from benchmarks import swimlane
from dvla.orchestrator.topology import load_topology

ROOT = Path(__file__).resolve().parents[2]


def test_each_async_run_is_compared_with_the_sim_only_runs_around_it(monkeypatch, tmp_path):
    # the host speeds up over the bench: sim_only 800, 1000, 1200 around async 700 and 900
    sims = iter([800.0, 1000.0, 1200.0])
    asyncs = iter([700.0, 900.0])
    # env.step CPU: random actions 1.0-1.2 ms, the learning policy's 1.32 ms
    costs = iter([1.0, 1.2, 1.0])
    calls = []

    def fake_run(topo, mode, warmup_s, window_s, runs_root, port, progress):
        calls.append(mode)
        if mode == "sim_only":
            return {"error": None, "produced_sps": next(sims), "consumed_sps": 0.0, "lanes": {},
                    "env_step_cpu_ms": next(costs), "episodes_per_1k_steps": 20.0}
        return {"error": None, "produced_sps": 1.0, "consumed_sps": next(asyncs), "env_step_cpu_ms": 1.32,
                "episodes_per_1k_steps": 45.0, "lanes": {"actor-0": {"learn": {"utilisation": 0.3}}}}

    monkeypatch.setattr(swimlane, "measure_run", fake_run)
    profile = dataclasses.replace(swimlane.QUICK, repeats=2)
    out = swimlane._default(load_topology(ROOT / "topologies" / "local.yaml"), profile, tmp_path, None, lambda _m: None)
    assert calls == ["sim_only", "async", "sim_only", "async", "sim_only"]
    assert out["sim_only_sps_runs"] == [800.0, 1000.0, 1200.0]
    assert out["sim_only_baselines"] == [900.0, 1100.0]
    assert out["ratios"] == [pytest.approx(700 / 900), pytest.approx(900 / 1100)]
    assert out["sim_only_drift"] == pytest.approx(1.5)
    # the previous method, each async run against the sim_only run before it, would have
    # reported 0.875 and 0.9: the drift, not the pipeline
    assert out["async_over_sim_only"] == pytest.approx((700 / 900 + 900 / 1100) / 2)
    # each async run's step cost against the bracketing sim_only runs' mean (1.1 both times)
    assert out["step_cost_ratios"] == [pytest.approx(1.2), pytest.approx(1.2)]
    assert out["async_over_sim_only_equal_step_cost"] == pytest.approx(1.2 * (700 / 900 + 900 / 1100) / 2)
    assert out["episodes_per_1k_steps"] == {"sim_only": 20.0, "async": 45.0}


def test_a_failed_sim_only_run_leaves_the_other_as_the_baseline():
    assert swimlane._bracket(None, 900.0) == 900.0
    assert swimlane._bracket(700.0, None) == 700.0
    assert swimlane._bracket(None, None) is None
    assert swimlane._bracket(700.0, 900.0) == 800.0


def test_split_placement_leaves_the_simulators_core_0_alone():
    base = load_topology(ROOT / "topologies" / "local.yaml")
    profile = swimlane.QUICK
    split = swimlane.default_workload(base, profile, "split")
    (node,) = [n for _rack, n in split.nodes()]
    assert node.cpus == (1,)  # every thread of every role on core 1 ...
    roles = {r.role: r for r in node.roles}
    assert set(roles) == {"actor", "replicator", "rollout"}  # no evaluator
    assert roles["rollout"].count == 2  # local.yaml's two rollouts
    assert roles["rollout"].lane_cpus == {"sim": (0,)}  # ... but the simulators, alone on core 0
    assert roles["actor"].lane_cpus is None and roles["actor"].cpus is None
    assert split.task.ppo == dataclasses.replace(base.task.ppo, batch_steps=profile.batch_steps)  # the file's PPO
    assert swimlane.learner_ceiling(split, 0.3, 2) == 1.0  # the learner takes nothing from core 0
    assert swimlane.placement_of(split) == [{"node": "host", "cpus": [1], "roles": {
        "actor": 1, "replicator": 1, "rollout": {"count": 2, "lane_cpus": {"sim": [0]}}}}]

    by_role = swimlane.default_workload(base, profile, "split-roles")
    nodes = {n.name: n for _rack, n in by_role.nodes()}
    assert nodes["sim"].cpus == (0,) and nodes["learn"].cpus == (1,)
    assert [(r.role, r.count) for r in nodes["sim"].roles] == [("rollout", 2)]
    assert {r.role for r in nodes["learn"].roles} == {"actor", "replicator"}
    assert swimlane.learner_ceiling(by_role, 0.3, 2) == 1.0

    as_written = swimlane.default_workload(base, profile, "file")
    assert all(not n.cpus for _rack, n in as_written.nodes())
    assert swimlane.learner_ceiling(as_written, 0.3, 2) == pytest.approx(0.85)  # 1 - 0.3 of 2 cores
    assert swimlane.learner_ceiling(as_written, None, 2) is None
    with pytest.raises(ValueError, match="placement"):
        swimlane.default_workload(base, profile, "everywhere")


def test_learner_ceiling_follows_lane_and_role_pinning():
    from dvla.config import NodeConfig, RackConfig, RolePlacement

    def topo(*roles: RolePlacement, cpus=(0, 1)):
        node = NodeConfig(name="n", cpus=cpus, roles=roles)
        return dataclasses.replace(load_topology(ROOT / "topologies" / "tiny.yaml"), racks=(RackConfig(name="r", nodes=(node,)),))

    # sim lanes on core 0, learner on the node's cores 0-1: they share core 0
    shared = topo(RolePlacement(role="actor"), RolePlacement(role="rollout", lane_cpus={"sim": (0,)}))
    assert swimlane.learner_ceiling(shared, 0.4, 2) == pytest.approx(0.6)  # 1 - 0.4 of the one sim core
    # the actor's learn lane pinned away from the simulators: disjoint
    apart = topo(RolePlacement(role="actor", lane_cpus={"learn": (1,)}), RolePlacement(role="rollout", lane_cpus={"sim": (0,)}))
    assert swimlane.learner_ceiling(apart, 0.4, 2) == 1.0
    # role-level cpus override the node's
    roles = topo(RolePlacement(role="actor", cpus=(1,)), RolePlacement(role="rollout", cpus=(0,)))
    assert swimlane.learner_ceiling(roles, 0.4, 2) == 1.0


def test_the_balanced_workload_keeps_the_replicator_beside_the_rollouts():
    topo = swimlane.balanced_workload(load_topology(ROOT / "topologies" / "local.yaml"), swimlane.QUICK, 16)
    nodes = {n.name: n for _rack, n in topo.nodes()}
    assert {r.role for r in nodes["sim"].roles} == {"rollout", "replicator"}
    assert [r.role for r in nodes["learn"].roles] == ["actor"]
    assert topo.task.ppo.update_epochs == 16 and topo.task.ppo.target_kl is None


def _status(name: str, kind: str, t_s: float, steps: int, lanes: dict, **extra):
    from dvla.fabric.messages import RoleStatus

    return RoleStatus(name=name, kind=kind, node="n", rack="r", pid=1, state="running", policy_version=0,
                      env_steps=steps, steps_per_s=0.0, lanes=lanes, extra=extra, time_ns=int(t_s * 1e9))


def test_sim_lane_cpu_per_step_separates_less_cpu_from_dearer_steps():
    # two rollouts over a 10-s window: their sim lanes busy the whole time (wall), each with half
    # a core of CPU (they share one), stepping 3000 envs each: 5 s / 3000 = 1.667 ms CPU a step
    def lanes(busy, cpu, items):
        return {"sim": {"busy_s": busy, "wait_s": 0.0, "items": items, "cpu_s": cpu},
                "infer": {"busy_s": busy / 10, "wait_s": 0.0, "items": items / 2}}  # no cpu_s: not reported

    topo = load_topology(ROOT / "topologies" / "local.yaml")
    a = {f"rollout-{i}": _status(f"rollout-{i}", "rollout", 100.0, 0, lanes(0.0, 1.0, 0), env_step_cpu_s=0.5,
                                 episodes=10) for i in (0, 1)}
    b = {f"rollout-{i}": _status(f"rollout-{i}", "rollout", 110.0, 3000, lanes(10.0, 6.0, 3000), env_step_cpu_s=4.7,
                                 episodes=70) for i in (0, 1)}
    out = swimlane.window_figures(a, b, topo)
    sim = out["lanes"]["rollout-0"]["sim"]
    assert sim["utilisation"] == 1.0 and sim["cpu_fraction"] == 0.5
    assert sim["cpu_ms_per_item"] == pytest.approx(5000 / 3000, rel=1e-3)
    assert "cpu_fraction" not in out["lanes"]["rollout-0"]["infer"]
    assert out["sim_cpu_cores"] == pytest.approx(1.0)
    assert out["sim_cpu_ms_per_step"] == pytest.approx(5000 / 3000)
    assert out["env_step_cpu_ms"] == pytest.approx(4200 / 3000)  # of it inside env.step
    assert out["episodes_per_1k_steps"] == pytest.approx(20.0)


def test_the_bench_starts_its_rollouts_with_the_swap_probe_and_the_other_roles_as_they_are():
    from benchmarks.swimlane_probe import ProbeWrapper

    wrap = ProbeWrapper()
    argv = ["python", "-m", "dvla.roles.rollout", "--config", "r.json"]
    assert wrap(None, argv) == ["python", "-m", "benchmarks.swimlane_probe", "--config", "r.json"]  # type: ignore[arg-type]
    actor = ["python", "-m", "dvla.roles.actor", "--config", "a.json"]
    assert wrap(None, actor) == actor  # type: ignore[arg-type]
