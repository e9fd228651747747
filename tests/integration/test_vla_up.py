"""End to end on the VLA path: `dvla up topologies/local-vla.yaml` (shortened) renders camera
images in the rollouts, trains tiny-vla on the actor, and every rollout acts with trained
versions; inference latency percentiles appear in `dvla status` and metrics.csv, and the
images travel as uint8."""

from __future__ import annotations

import csv
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.integration.test_up_e2e import ROOT, dvla, free_port_block, pids_of_run

ROLLOUTS = ("rollout-node0-0", "rollout-node0-1")


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_local_vla_end_to_end(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    up = subprocess.Popen(
        [sys.executable, "-m", "dvla", "up", "topologies/local-vla.yaml", "--runs", str(runs),
         "--base-port", str(free_port_block()), "--max-env-steps", "1200", "--quiet"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    run_dir = runs / "local-vla"
    latency: dict[str, float] = {}
    try:
        deadline = time.monotonic() + 600
        while time.monotonic() < deadline and up.poll() is None and len(latency) < len(ROLLOUTS):
            if (run_dir / "state.json").exists():
                st = dvla("status", "local-vla", "--runs", str(runs), "--format", "json", timeout=60)
                if st.returncode == 0:
                    for role in json.loads(st.stdout)["roles"]:
                        acted = role.get("lanes", {}).get("infer", {}).get("items", 0) > 0
                        if role["name"] in ROLLOUTS and acted and "infer_ms_p50" in role["extra"]:
                            latency[role["name"]] = role["extra"]["infer_ms_p99"]
            time.sleep(3)
        out, _ = up.communicate(timeout=600)
    finally:
        if up.poll() is None:
            up.kill()
            up.wait()
    assert up.returncode == 0, out
    assert set(latency) == set(ROLLOUTS), f"dvla status never showed inference latency: {latency}\n{out}"

    result = json.loads((run_dir / "result.json").read_text())
    assert result["reason"] == "max_env_steps" and result["accounting"]["unaccounted"] == 0
    summaries = {p.stem: json.loads(p.read_text()) for p in (run_dir / "summaries").glob("*.json")}
    assert summaries["actor-node0-0"]["extra"]["published_version"] >= 3
    assert summaries["actor-node0-0"]["extra"]["learn"]["batch_size"] == 400
    for name in ROLLOUTS:
        s = summaries[name]["extra"]
        assert summaries[name]["policy_version"] >= 2, f"{name} never acted with a trained version"
        assert summaries[name]["lanes"]["infer"]["items"] > 0  # it acted: the percentiles are of its timings
        assert math.isfinite(s["infer_ms_p50"]) and math.isfinite(s["infer_ms_p99"]) and s["infer_ms_p50"] <= s["infer_ms_p99"]
        # Per env step a chunk carries the 64x64x3 image twice (obs, final_obs) plus small
        # arrays: about 25 kB as uint8; float32 images would be four times that.
        per_step = s["bytes_shipped"] / summaries[name]["env_steps"]
        assert 2 * 64 * 64 * 3 < per_step < 3 * 64 * 64 * 3, per_step
    with open(run_dir / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    # the slowest rollout's percentiles in every row (p50 <= p99 as for each rollout's own)
    assert rows and all(math.isfinite(float(r["infer_ms_p50"])) and float(r["infer_ms_p50"]) <= float(r["infer_ms_p99"])
                        for r in rows)
    assert pids_of_run(run_dir) == []


GRPO_TOPOLOGY = """
run: grpo
task:
  env: PushCube-v1
  obs_mode: state
  algorithm: grpo
  group_size: 2
  envs_per_rollout: 4
  chunk_steps: 50
  max_episode_steps: 50
  ppo: {batch_steps: 400, minibatches: 4, update_epochs: 2}
  budget: {max_env_steps: 2400}
replication: {encoding: full}
racks:
  - name: rack0
    nodes:
      - name: node0
        roles: [{role: actor}, {role: rollout, count: 2}]
"""


@pytest.mark.timeout(600)
def test_grpo_end_to_end(tmp_path: Path) -> None:
    """GRPO through `dvla up`: whole-episode chunks of grouped seeds are learned from (the actor
    raises on a broken layout), every chunk is accounted for and versions reach the rollouts."""
    topo = tmp_path / "grpo.yaml"
    topo.write_text(GRPO_TOPOLOGY)
    runs = tmp_path / "runs"
    up = subprocess.run(
        [sys.executable, "-m", "dvla", "up", str(topo), "--runs", str(runs), "--base-port", str(free_port_block()), "--quiet"],
        cwd=ROOT, capture_output=True, text=True, timeout=560,
    )
    assert up.returncode == 0, up.stdout + up.stderr
    run_dir = runs / "grpo"
    result = json.loads((run_dir / "result.json").read_text())
    assert result["reason"] == "max_env_steps" and result["accounting"]["unaccounted"] == 0
    summaries = {p.stem: json.loads(p.read_text()) for p in (run_dir / "summaries").glob("*.json")}
    actor = summaries["actor-node0-0"]
    assert actor["error"] is None and actor["extra"]["published_version"] >= 4
    assert actor["extra"]["learn"]["v_loss"] < 5e-3  # no critic targets: GRPO trains the value head to 0
    for name in ROLLOUTS:
        assert summaries[name]["policy_version"] >= 3
