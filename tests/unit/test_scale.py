"""The whole-pipeline scale model (dvla.orchestrator.scale) and `dvla plan --simulate`."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest

from dvla.orchestrator.plan import make_plan
from dvla.orchestrator.scale import ScaleError, check_inputs, simulate_pipeline, speedup_table, tile, version_bytes
from dvla.orchestrator.topology import load_topology

ROOT = Path(__file__).resolve().parents[2]


def _topo(name: str = "8node.yaml"):
    return load_topology(ROOT / "topologies" / name)


def test_tile_repeats_racks_and_keeps_one_evaluator() -> None:
    big = tile(_topo(), 64, 16)
    assert len(big.racks) == 16 and len(big.nodes()) == 64
    kinds = [p.config.kind for p in make_plan(big, "runs/x").processes]
    assert kinds.count("evaluator") == 1
    assert kinds.count("rollout") == 64
    assert kinds.count("actor") == 8  # rack r0's pattern (with the actor) repeats every other rack
    assert kinds.count("replicator") == 16
    assert big.emulate == "none"
    topo = _topo()
    assert tile(topo, None, None) is topo  # no size given: the topology as it is


def test_version_bytes_follow_dtype_trainable_share_and_encoding() -> None:
    topo = _topo()
    cfg = dataclasses.replace(topo.simulate, params=1e9, dtype="bf16")
    assert version_bytes(cfg, topo) == (2_000_000_000, 2_000_000_000)
    lora = dataclasses.replace(cfg, trainable_fraction=0.01)
    assert version_bytes(lora, topo)[0] == 20_000_000
    topk = dataclasses.replace(topo, replication=dataclasses.replace(topo.replication, encoding="delta-topk"))
    assert version_bytes(dataclasses.replace(cfg, dtype="fp32"), topk) == (4_000_000_000, 400_000_000)


@pytest.mark.parametrize(("change", "needle"), [
    ({"nodes": 0}, "simulate.nodes (--nodes)"),
    ({"env_steps_per_s": -5.0}, "simulate.env_steps_per_s (--env-rate)"),
    ({"learner_steps_per_s": float("nan")}, "simulate.learner_steps_per_s"),
    ({"params": 1e12, "dtype": "bf16", "node_memory_gib": 1024}, "more than simulate.node_memory_gib"),
    ({"nodes": 4, "racks": 8}, "simulate.racks (--racks)"),
])
def test_bad_inputs_name_the_key(change: dict, needle: str) -> None:
    topo = _topo()
    with pytest.raises(ScaleError, match=None) as err:
        check_inputs(dataclasses.replace(topo.simulate, **change), topo)
    assert needle in str(err.value) and "\n" not in str(err.value)


def test_async_pipeline_is_rollout_bound_and_sync_pays_every_stage() -> None:
    topo = _topo()
    fast_learner = dataclasses.replace(topo.simulate, learner_steps_per_s=1e6)
    a = simulate_pipeline(topo, fast_learner)
    assert a.limit == "rollouts"
    assert a.env_steps_per_s == pytest.approx(8 * fast_learner.env_steps_per_s, rel=0.02)
    sync = simulate_pipeline(dataclasses.replace(topo, mode="sync"), fast_learner)
    # lock-step: collect (1600 steps at 2,720/s), then learn, then broadcast, one after the other
    collect = topo.task.ppo.batch_steps / (8 * fast_learner.env_steps_per_s)
    interval = collect + topo.task.ppo.batch_steps / 1e6 + sync.broadcast.tree_s
    assert sync.version_interval_s == pytest.approx(interval, rel=0.02)
    assert sync.policy_lag_mean == 0.0
    slow_learner = dataclasses.replace(topo.simulate, learner_steps_per_s=500.0)
    s = simulate_pipeline(topo, slow_learner)
    assert s.limit == "learner" and s.learner_utilisation > 0.97
    assert s.env_steps_per_s == pytest.approx(500.0, rel=0.02)


def test_speedup_bends_where_the_learner_saturates() -> None:
    topo = _topo()
    # 8 nodes: one rank, fed 2,720 env steps/s of its 5,000; 16 nodes: two ranks whose gradient
    # all-reduce crosses the 0.2 Gbit/s rack uplinks 32 times per version
    cfg = dataclasses.replace(topo.simulate, learner_steps_per_s=5000.0, nodes=8, racks=2)
    rows, bend = speedup_table(topo, cfg, [8, 16, 32])
    assert [r.nodes for r in rows] == [8, 16, 32]
    assert rows[0].speedup == 1.0
    assert rows[0].limit == "rollouts"
    assert bend is not None and bend.nodes == 16 and bend.limit == "learner" and "all-reduce" in bend.limit_detail


def _dvla(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dvla", *args], capture_output=True, text=True, cwd=ROOT, timeout=120)


def test_plan_simulate_reports_and_plots(tmp_path: Path) -> None:
    png = tmp_path / "speedup.png"
    out = _dvla("plan", "topologies/8node.yaml", "--simulate", "--sizes", "8,16,32", "--plot", str(png))
    assert out.returncode == 0, out.stderr
    assert "env steps/s trained" in out.stdout and "S/B bound" in out.stdout
    assert "speedup, racks of 4 nodes" in out.stdout
    assert png.stat().st_size > 10_000


@pytest.mark.parametrize(("args", "needle"), [
    (["--nodes", "0"], "--nodes"),
    (["--env-rate", "-3"], "--env-rate"),
    (["--params", "lots"], "--params"),
    (["--params", "1T", "--dtype", "bf16", "--node-memory-gib", "512"], "node_memory_gib"),
    (["--encoding", "zip"], "--encoding"),
])
def test_plan_simulate_bad_flags_are_one_line(args: list[str], needle: str) -> None:
    out = _dvla("plan", "topologies/8node.yaml", "--simulate", "--sizes", "", *args)
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in out.stderr, out.stderr
