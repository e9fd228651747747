"""OpenVLA and OpenVLA-OFT (the Prismatic layout) train through `dvla up` on CPU from the tiny
reference directories their upstream code wrote: every role loads the checkpoint natively with
LoRA, rollouts render RGB PushCube with the end-effector control mode (7 action dims), versions
carry only adapters and heads through a replicator and reach every rollout and the evaluator; in
lock-step the learner's log-probs of the rollouts' actions equal theirs within 1e-4; `dvla export`
writes the run's policy back in the same layout."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.integration.test_up_e2e import ROOT, free_port_block, pids_of_run
from tests.references.conftest import oft_reference_root

ROLLOUTS = ("rollout-node0-0", "rollout-node0-1")

TOPOLOGY = """
run: {run}
mode: sync
task:
  env: PushCube-v1
  obs_mode: rgb
  control_mode: pd_ee_delta_pose
  image_size: 32
  instruction_tokens: 32
  action_chunk: {chunk}
  max_episode_steps: 16
  policy: {family}
  policy_kwargs: {{checkpoint: {checkpoint}, lora: {{r: 4}}{extra}}}
  envs_per_rollout: 2
  chunk_steps: 4
  ppo: {{batch_steps: 32, minibatches: 2, update_epochs: 1, micro_batch: 16, lr: 0.0003}}
  eval: {{episodes: 2, envs: 2, every_versions: 2}}
  budget: {{max_env_steps: 128}}
replication: {{encoding: full}}
racks:
  - name: rack0
    nodes:
      - name: node0
        roles: [{{role: actor}}, {{role: replicator}}, {{role: rollout, count: 2}}, {{role: evaluator}}]
"""


@pytest.mark.timeout(900)
@pytest.mark.parametrize("family,folder,chunk,extra", [
    # openvla shares openvla-oft's base (backbone, LoRA, export) and ships token extras as
    # vla-tokens' dvla up test does: ~77 s, run with `make test-slow`
    pytest.param("openvla", "openvla-tiny", 1, "", marks=pytest.mark.slow),
    ("openvla-oft", "openvla-oft-tiny", 2, ", cameras: [0, 0]"),
])
def test_an_openvla_family_trains_through_dvla_up_and_exports(tmp_path: Path, family: str, folder: str, chunk: int,
                                                              extra: str) -> None:
    checkpoint = oft_reference_root() / folder
    run = family.replace("-", "")
    topo = tmp_path / f"{run}.yaml"
    topo.write_text(TOPOLOGY.format(run=run, family=family, checkpoint=checkpoint, chunk=chunk, extra=extra))
    runs = tmp_path / "runs"
    up = subprocess.run(
        [sys.executable, "-m", "dvla", "up", str(topo), "--runs", str(runs), "--base-port", str(free_port_block()),
         "--quiet"], cwd=ROOT, capture_output=True, text=True, timeout=840,
    )
    run_dir = runs / run
    logs = "".join(p.read_text(errors="replace")[-2000:] for p in sorted((run_dir / "logs").glob("*.log")))
    assert up.returncode == 0, up.stdout + up.stderr + logs
    result = json.loads((run_dir / "result.json").read_text())
    assert result["reason"] == "max_env_steps" and result["accounting"]["unaccounted"] == 0, result
    summaries = {p.stem: json.loads(p.read_text()) for p in (run_dir / "summaries").glob("*.json")}
    actor = summaries["actor-node0-0"]["extra"]
    assert actor["published_version"] >= 3 and actor["updates_refused_nonfinite"] == 0
    assert actor["base_hash"] and actor["replicated_values"] / actor["parameters"] <= 0.05, actor
    assert actor["learn"]["behaviour_gap"] <= 1e-4, actor["learn"]  # lock-step: the same weights
    assert summaries["replicator-node0-0"]["extra"]["held_version"] >= 2
    for name in ROLLOUTS:
        assert summaries[name]["policy_version"] >= 2, f"{name} never acted with a trained version"
        assert summaries[name]["extra"]["weights"]["refused_base"] == 0
    assert summaries["evaluator-node0-0"]["extra"]["evals"] >= 1
    assert pids_of_run(run_dir) == []

    out = tmp_path / "exported"
    exp = subprocess.run([sys.executable, "-m", "dvla", "export", run, str(out), "--runs", str(runs)], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert exp.returncode == 0, exp.stdout + exp.stderr
    from dvla.learn.vla.openvla_format import check_openvla, read_state_dict

    before = read_state_dict(check_openvla(str(checkpoint), family))
    after = read_state_dict(check_openvla(str(out), family))
    assert list(after) == list(before)
    changed = [k for k in before if not torch_equal(before[k], after[k])]
    assert changed and all(k.endswith(("q_proj.weight", "k_proj.weight", "v_proj.weight", "o_proj.weight"))
                           for k in changed), changed[:5]


def torch_equal(a, b) -> bool:
    import torch

    return bool(torch.equal(a, b))
