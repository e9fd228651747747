"""The default workload's ratio against a bracketing simulator baseline (pure logic: the runs
themselves are replaced by canned results; tests/integration/test_bench_swimlane.py runs them)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from dvla.bench import swimlane
from dvla.orchestrator.topology import load_topology

ROOT = Path(__file__).resolve().parents[2]


def test_each_async_run_is_compared_with_the_sim_only_runs_around_it(monkeypatch, tmp_path):
    # the host speeds up over the bench: sim_only 800, 1000, 1200 around async 700 and 900
    sims = iter([800.0, 1000.0, 1200.0])
    asyncs = iter([700.0, 900.0])
    calls = []

    def fake_run(topo, mode, warmup_s, window_s, runs_root, port, progress):
        calls.append(mode)
        if mode == "sim_only":
            return {"error": None, "produced_sps": next(sims), "consumed_sps": 0.0, "lanes": {}}
        return {"error": None, "produced_sps": 1.0, "consumed_sps": next(asyncs),
                "lanes": {"actor-0": {"learn": {"utilisation": 0.3}}}}

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


def test_a_failed_sim_only_run_leaves_the_other_as_the_baseline():
    assert swimlane._bracket(None, 900.0) == 900.0
    assert swimlane._bracket(700.0, None) == 700.0
    assert swimlane._bracket(None, None) is None
    assert swimlane._bracket(700.0, 900.0) == 800.0


def test_split_placement_gives_the_learner_its_own_core():
    base = load_topology(ROOT / "topologies" / "local.yaml")
    profile = swimlane.QUICK
    split = swimlane.default_workload(base, profile, "split")
    nodes = {n.name: n for _rack, n in split.nodes()}
    assert nodes["sim"].cpus == (0,) and nodes["learn"].cpus == (1,)
    assert [(r.role, r.count) for r in nodes["sim"].roles] == [("rollout", 2)]  # local.yaml's two rollouts
    assert {r.role for r in nodes["learn"].roles} == {"actor", "replicator"}
    assert not any(r.role == "evaluator" for _rack, n in split.nodes() for r in n.roles)
    assert split.task.ppo == dataclasses.replace(base.task.ppo, batch_steps=profile.batch_steps)  # the file's PPO
    assert swimlane.learner_ceiling(split, 0.3, 2) == 1.0  # the learner takes nothing from core 0

    as_written = swimlane.default_workload(base, profile, "file")
    assert all(not n.cpus for _rack, n in as_written.nodes())
    assert swimlane.learner_ceiling(as_written, 0.3, 2) == pytest.approx(0.85)  # 1 - 0.3 of 2 cores
    assert swimlane.learner_ceiling(as_written, None, 2) is None
    with pytest.raises(ValueError, match="placement"):
        swimlane.default_workload(base, profile, "everywhere")


def test_the_balanced_workload_keeps_the_replicator_beside_the_rollouts():
    topo = swimlane.balanced_workload(load_topology(ROOT / "topologies" / "local.yaml"), swimlane.QUICK, 16)
    nodes = {n.name: n for _rack, n in topo.nodes()}
    assert {r.role for r in nodes["sim"].roles} == {"rollout", "replicator"}
    assert [r.role for r in nodes["learn"].roles] == ["actor"]
    assert topo.task.ppo.update_epochs == 16 and topo.task.ppo.target_kl is None
