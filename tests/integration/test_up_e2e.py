"""End to end: `dvla up` on the tiny topology, real processes, real Zenoh, real ManiSkill.

While the run trains, `dvla status --format json` (a separate process, as from another
terminal) must list every role with its policy version. After it stops by itself: trajectories
flowed, every rollout's policy version advanced, the chunk accounting identity holds exactly,
the run directory holds what it should, and no process of the run is left.
"""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dvla.config import ROLE_LANES
from benchmarks.ports import free_port_block  # noqa: F401  (tests import it from here)

ROOT = Path(__file__).resolve().parents[2]
ROLES = {"actor-node0-0", "replicator-node0-0", "rollout-node0-0", "rollout-node0-1", "evaluator-node0-0"}


def dvla(*args: str, **kw) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dvla", *args], capture_output=True, text=True, cwd=ROOT, **kw)


def pids_of_run(run_dir: Path) -> list[str]:
    out = subprocess.run(["pgrep", "-f", str(run_dir)], capture_output=True, text=True).stdout.split()
    return [p for p in out if p != str(os.getpid())]


@pytest.mark.timeout(420)
def test_up_tiny_end_to_end(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    port = free_port_block()
    up = subprocess.Popen(
        [sys.executable, "-m", "dvla", "up", "topologies/tiny.yaml", "--runs", str(runs), "--base-port", str(port),
         "--max-env-steps", "4800", "--quiet"],  # tiny evaluates at v4 and v8: the status poll sees it
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    run_dir = runs / "tiny"
    seen: dict[str, dict] = {}
    try:
        deadline = time.monotonic() + 240
        # `dvla status` from another process, until every role has answered with a version >= 1.
        while time.monotonic() < deadline and up.poll() is None:
            if (run_dir / "state.json").exists():
                st = dvla("status", "tiny", "--runs", str(runs), "--format", "json", timeout=60)
                if st.returncode == 0:
                    doc = json.loads(st.stdout)
                    check_status_schema(doc)
                    for role in doc["roles"]:
                        if role["policy_version"] >= 1:
                            seen[role["name"]] = role
                    if ROLES <= set(seen):
                        break
            time.sleep(2)
        out, _ = up.communicate(timeout=300)
    finally:
        if up.poll() is None:
            up.kill()
            up.wait()
    assert up.returncode == 0, out
    assert ROLES <= set(seen), f"status never showed every role with a version: {sorted(seen)}\n{out}"
    for role in seen.values():
        assert {"kind", "node", "rack", "state", "steps_per_s", "lanes"} <= set(role)

    result = json.loads((run_dir / "result.json").read_text())
    assert result["reason"] == "max_env_steps"
    assert result["final_env_steps"] >= 4800

    acct = result["accounting"]
    assert acct["produced"] > 0 and acct["consumed"] > 0
    assert acct["unaccounted"] == 0, acct  # produced = consumed + dropped + rejected, exactly

    summaries = {p.stem: json.loads(p.read_text()) for p in (run_dir / "summaries").glob("*.json")}
    assert set(summaries) == ROLES
    for s in summaries.values():  # the lanes `lane_cpus` may name are the lanes each role runs
        assert set(s["lanes"]) == set(ROLE_LANES[s["kind"]]), (s["name"], list(s["lanes"]))
    actor_version = summaries["actor-node0-0"]["extra"]["published_version"]
    assert actor_version >= 3
    shipped = [summaries[name]["extra"]["chunks_shipped"] for name in ("rollout-node0-0", "rollout-node0-1")]
    # every rollout shipped; their status counts all the books' produced chunks but those flushed
    # as they closed (at most one each)
    assert min(shipped) > 0 and 0 <= acct["produced"] - sum(shipped) <= len(shipped), (shipped, acct)
    assert acct["incarnations"] == {"rollout": 2, "actor": 1} and acct["lost"] == 0
    for name in ("rollout-node0-0", "rollout-node0-1"):
        s = summaries[name]
        assert s["policy_version"] >= 2, f"{name} never advanced past its first version"
        assert s["error"] is None

    for rel in ("topology.yaml", "metrics.csv", "evals.csv", "versions.csv", "checkpoints/MANIFEST.json",
                "checkpoints/high_water.json", "plots/training.png"):
        assert (run_dir / rel).exists(), rel
    manifest = json.loads((run_dir / "checkpoints" / "MANIFEST.json").read_text())
    # the run's end is checkpointed: the last version published, with the checksum it was published with
    assert manifest["version"] == actor_version
    assert manifest["checksum"] == summaries["actor-node0-0"]["extra"]["published_checksum"]
    for f in ("policy.safetensors", "optimizer.safetensors"):
        assert (run_dir / "checkpoints" / manifest["dir"] / f).exists(), f
    assert all((run_dir / "logs" / f"{r}.log").stat().st_size > 0 for r in ROLES)
    assert not (run_dir / "state.json").exists()
    assert pids_of_run(run_dir) == []
    _check_tensorboard(run_dir, result["final_env_steps"])


def check_status_schema(doc: dict) -> None:
    """`doc` satisfies the JSON Schema printed in docs/status.md."""
    import jsonschema

    text = (ROOT / "docs" / "status.md").read_text()
    schema = json.loads(text.split("```json", 1)[1].split("```", 1)[0])
    jsonschema.validate(doc, schema)
    for role in doc["roles"]:  # every plane of every role carries its reject and drop counters
        for counters in role["planes"].values():
            assert all(isinstance(v, int) for k, v in counters.items() if k != "peers")


def _check_tensorboard(run_dir: Path, final_env_steps: int) -> None:
    """The run's event files, read back with TensorBoard's own reader: scalars of every
    namespace, indexed by env steps."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(run_dir / "tb"))
    acc.Reload()
    tags = acc.Tags()["scalars"]
    for namespace in ("train/", "rollout/", "env/", "time/", "fabric/", "weights/"):
        assert any(t.startswith(namespace) for t in tags), (namespace, tags)
    for tag in ("train/approx_kl", "train/lr", "env/episode_return_mean", "env/success_rate", "fabric/data/received_bytes",
                "weights/version", "time/actor.learn/busy"):
        assert tag in tags, (tag, tags)
    steps = [e.step for e in acc.Scalars("weights/version")]
    assert steps == sorted(steps) and 0 < steps[-1] <= final_env_steps
    versions = [e.value for e in acc.Scalars("weights/version")]
    assert versions[-1] >= 3 and versions == sorted(versions)


def up_tiny_variant(tmp_path: Path, text: str, max_env_steps: int) -> Path:
    """`dvla up` a variant of tiny.yaml to its step budget; the run directory, once the run has
    exited 0 with its chunk accounting closed and no process left."""
    topo = tmp_path / "tiny-variant.yaml"
    topo.write_text(text)
    runs = tmp_path / "runs"
    up = dvla("up", str(topo), "--runs", str(runs), "--base-port", str(free_port_block()),
              "--max-env-steps", str(max_env_steps), "--quiet", timeout=280)
    assert up.returncode == 0, up.stdout + up.stderr
    run_dir = runs / "tiny"
    result = json.loads((run_dir / "result.json").read_text())
    assert result["final_env_steps"] >= max_env_steps
    assert result["accounting"]["consumed"] > 0 and result["accounting"]["unaccounted"] == 0, result["accounting"]
    assert pids_of_run(run_dir) == []
    return run_dir


@pytest.mark.timeout(300)
def test_up_with_two_evaluators_sharing_evaluations(tmp_path: Path) -> None:
    """Two evaluators share every evaluation (3 episodes each): the orchestrator records whole
    evaluations of 6; weights still advance, and the chunk accounting closes exactly."""
    text = (ROOT / "topologies/tiny.yaml").read_text()
    assert "  algorithm: ppo\n" in text and text.endswith("          - role: evaluator\n")
    text = text.replace("  algorithm: ppo\n", "  algorithm: ppo\n  eval: {episodes: 6, every_versions: 2, envs: 3}\n",
                        1) + "            count: 2\n"
    run_dir = up_tiny_variant(tmp_path, text, 4800)  # room for both evaluators to finish one on a loaded machine
    blocks = []
    for name in ("evaluator-node0-0", "evaluator-node0-1"):
        s = json.loads((run_dir / "summaries" / f"{name}.json").read_text())
        blocks.append(s["extra"]["shard"])
        assert s["extra"]["evals"] >= 1 and s["extra"]["last_eval"]["episodes"] == 3, s["extra"]
    assert sorted(blocks) == [[0, 2], [1, 2]]
    with open(run_dir / "evals.csv") as f:
        evals = list(csv.DictReader(f))
    assert evals and all(int(e["episodes"]) == 6 for e in evals), evals
    for name in ("rollout-node0-0", "rollout-node0-1"):
        s = json.loads((run_dir / "summaries" / f"{name}.json").read_text())
        assert s["lanes"]["infer"]["items"] > 0 and s["lanes"]["sim"]["items"] > 0, s["lanes"]
        assert s["policy_version"] >= 2 and s["error"] is None
        p50, p99 = s["extra"]["infer_ms_p50"], s["extra"]["infer_ms_p99"]
        assert math.isfinite(p50) and math.isfinite(p99) and p50 <= p99  # acting is timed (it acted: items above)


@pytest.mark.timeout(300)
@pytest.mark.skipif(not {0, 1} <= os.sched_getaffinity(0), reason="needs cores 0 and 1")
def test_up_with_the_simulators_pinned_apart(tmp_path: Path) -> None:
    """`lane_cpus`: every role on core 1 but the rollouts' sim lanes, alone on core 0. The roles
    report each lane's affinity as the kernel holds it; training still closes its accounting."""
    text = (ROOT / "topologies/tiny.yaml").read_text()
    placed = "        host: localhost\n        roles:\n"
    assert placed in text and "            count: 2\n" in text
    text = text.replace(placed, "        host: localhost\n        cpus: [1]\n        roles:\n", 1)
    text = text.replace("            count: 2\n", "            count: 2\n            lane_cpus: {sim: [0]}\n", 1)
    run_dir = up_tiny_variant(tmp_path, text, 1200)
    for name in ROLES:
        s = json.loads((run_dir / "summaries" / f"{name}.json").read_text())
        placement = s["extra"]["placement"]
        assert placement["cpus"] == [1], (name, placement)
        want = {lane: [0] if lane == "sim" and name.startswith("rollout") else [1] for lane in s["lanes"]}
        assert placement["lanes"] == want, (name, placement)


SCENES = {
    # a batched torch env with ManiSkillVectorEnv's calls: four envs in one scene on this CPU. It
    # steps so fast that one rollout could fill a small budget while the other is still starting
    # on a loaded machine: the budget is several times what one rollout needs to start shipping.
    "batched-factory": ("  env: batched_reach:make\n  env_batching: scene\n  envs_per_rollout: 4\n", 4, 6000),
    # real ManiSkill through ManiSkillVectorEnv: one env per scene is all physx_cpu allows
    "maniskill-cpu": ("  env: PushCube-v1\n  env_batching: scene\n  envs_per_rollout: 1\n", 1, 1200),
}


@pytest.mark.timeout(300)
@pytest.mark.parametrize("kind", sorted(SCENES))
def test_up_with_one_scene_per_rollout(tmp_path: Path, kind: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """`env_batching: scene` (the GPU path, dvla/learn/vector_env.py) on a CPU: each rollout
    records its steps as tensors and ships chunks of all its envs, versions reach the rollouts and
    the accounting closes."""
    lines, n, budget = SCENES[kind]
    text = (ROOT / "topologies/tiny.yaml").read_text()
    for old in ("  env: PushCube-v1\n", "  envs_per_rollout: 2\n"):
        assert old in text
        text = text.replace(old, "", 1)
    text = text.replace("task:\n", "task:\n" + lines, 1)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(ROOT / "tests" / "plugin_env"), str(ROOT)]))
    run_dir = up_tiny_variant(tmp_path, text, budget)
    for name in ("rollout-node0-0", "rollout-node0-1"):
        s = json.loads((run_dir / "summaries" / f"{name}.json").read_text())
        assert s["error"] is None and s["extra"]["one_scene"] is True and s["extra"]["env_groups"] == [n], s["extra"]
        log_tail = (run_dir / "logs" / f"{name}.log").read_text()[-2000:]
        shipped = (s["extra"]["chunks_shipped"], s["extra"]["episodes"], s["policy_version"], s["wall_s"], s["lanes"],
                   log_tail)
        assert s["extra"]["chunks_shipped"] > 0 and s["extra"]["episodes"] > 0 and s["policy_version"] >= 2, shipped


@pytest.mark.timeout(300)
def test_up_warm_starts_from_another_runs_checkpoint(tmp_path: Path) -> None:
    """`task.init_weights` names a finished run's checkpoints: the new run's first version is
    exactly that checkpoint's weights (same checksum), and it learns on from there."""
    text = (ROOT / "topologies/tiny.yaml").read_text()
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    first = up_tiny_variant(tmp_path / "a", text, 800)
    manifest = json.loads((first / "checkpoints" / "MANIFEST.json").read_text())
    assert "task:\n" in text
    warm = text.replace("task:\n", f"task:\n  init_weights: {first / 'checkpoints'}\n", 1)
    second = up_tiny_variant(tmp_path / "b", warm, 800)
    with open(second / "versions.csv") as f:
        versions = list(csv.reader(f))
    assert versions[0][0] == "1" and versions[0][1] == manifest["checksum"], (versions[:2], manifest)
    assert len({row[1] for row in versions}) > 1  # and learning moved it on
    log = (second / "logs" / "actor-node0-0.log").read_text()
    assert f"warm start: policy weights from {first / 'checkpoints'} (checkpoint v{manifest['version']})" in log
