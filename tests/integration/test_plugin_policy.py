"""A user policy class from outside the package (tests/plugin_policy/my_policy.py, put on
PYTHONPATH) trained through `dvla up`: versions advance and reach every rollout, and the
checkpoint holds that class's weights (not the built-in mlp's)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from safetensors.torch import load_file

from tests.integration.test_up_e2e import ROOT, free_port_block, pids_of_run

TOPOLOGY = """
run: plugin
task:
  env: PushCube-v1
  obs_mode: state
  policy: my_policy:SharedTrunkPolicy
  policy_kwargs: {width: 48}
  envs_per_rollout: 2
  chunk_steps: 10
  ppo: {batch_steps: 400, minibatches: 4, update_epochs: 2}
  budget: {max_env_steps: 3000}
replication: {encoding: full}
racks:
  - name: rack0
    nodes:
      - name: node0
        roles: [{role: actor}, {role: replicator}, {role: rollout, count: 2}]
"""


@pytest.mark.timeout(600)
def test_user_policy_trains_through_dvla_up(tmp_path: Path) -> None:
    topo = tmp_path / "plugin.yaml"
    topo.write_text(TOPOLOGY)
    runs = tmp_path / "runs"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT / "tests" / "plugin_policy"), str(ROOT)]))
    up = subprocess.run(
        [sys.executable, "-m", "dvla", "up", str(topo), "--runs", str(runs), "--base-port", str(free_port_block()),
         "--quiet"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=560,
    )
    run_dir = runs / "plugin"
    assert up.returncode == 0, up.stdout + up.stderr
    result = json.loads((run_dir / "result.json").read_text())
    assert result["reason"] == "max_env_steps" and result["final_env_steps"] >= 3000
    assert result["accounting"]["unaccounted"] == 0
    summaries = {p.stem: json.loads(p.read_text()) for p in (run_dir / "summaries").glob("*.json")}
    published = summaries["actor-node0-0"]["extra"]["published_version"]
    assert published >= 5
    for name in ("rollout-node0-0", "rollout-node0-1"):
        assert summaries[name]["policy_version"] >= 3, f"{name} never received the trained versions"
    # every rollout shipped, and their status counts the books' produced chunks but those flushed
    # as they closed (at most one each)
    shipped = [summaries[name]["extra"]["chunks_shipped"] for name in ("rollout-node0-0", "rollout-node0-1")]
    acct = result["accounting"]
    assert min(shipped) > 0 and 0 <= acct["produced"] - sum(shipped) <= len(shipped), (shipped, acct)
    manifest = json.loads((run_dir / "checkpoints" / "MANIFEST.json").read_text())
    weights = load_file(str(run_dir / "checkpoints" / manifest["dir"] / "policy.safetensors"))
    assert set(weights) == {"trunk.0.weight", "trunk.0.bias", "trunk.2.weight", "trunk.2.bias", "mean.weight",
                            "mean.bias", "critic.weight", "critic.bias", "log_std"}
    assert tuple(weights["trunk.0.weight"].shape) == (48, 35)  # policy_kwargs reached the constructor
    assert pids_of_run(run_dir) == []
