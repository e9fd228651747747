"""Both Hugging Face VLA families train through `dvla up` on CPU: a tiny random-initialised
checkpoint of real transformers classes (Llava for vla-tokens, PaliGemma + dvla's action expert for
vla-flow) is written to disk, every role loads it with LoRA adapters, rollouts render RGB +
language PushCube and ship each step's extras (action bins, the denoising chain), the learner
recomputes log-probs from them in micro-batches, versions carry only the adapters and heads
(<= 5 % of the model's bytes) through a replicator that builds no model, and reach every
rollout and the evaluator."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from dvla.learn.vla.build import save_random_checkpoint
from tests.integration.test_up_e2e import ROOT, free_port_block, pids_of_run

ROLLOUTS = ("rollout-node0-0", "rollout-node0-1")

TOPOLOGY = """
run: {run}
task:
  env: PushCube-v1
  obs_mode: rgb
  image_size: 32
  instruction_tokens: 12
  policy: {policy}
  policy_kwargs: {{checkpoint: {checkpoint}, lora: {{r: 4}}{extra}}}
  envs_per_rollout: 2
  chunk_steps: 10
  max_episode_steps: 50
  ppo: {{batch_steps: 200, minibatches: 2, update_epochs: 1, micro_batch: 32, lr: 0.0003}}
  eval: {{episodes: 2, envs: 2, every_versions: 3}}
  budget: {{max_env_steps: 1200}}
replication: {{encoding: full}}
racks:
  - name: rack0
    nodes:
      - name: node0
        roles: [{{role: actor}}, {{role: replicator}}, {{role: rollout, count: 2}}, {{role: evaluator}}]
"""


@pytest.mark.timeout(600)
@pytest.mark.parametrize("family,policy,extra,per_step_extras", [
    ("tokens", "vla-tokens", "", 4 * 8),                    # action_tokens int32 [8]
    ("flow", "vla-flow", ", method: sde", 4 * 5 * 8 + 4),   # chain float32 [K+1=5, 8] + denoise_index
])
def test_a_hf_vla_family_trains_through_dvla_up(tmp_path: Path, family: str, policy: str, extra: str,
                                                per_step_extras: int) -> None:
    ckpt = save_random_checkpoint(tmp_path / f"ckpt-{family}", family, action_dim=8, max_chunk=4)
    run = f"hf{family}"
    topo = tmp_path / f"{run}.yaml"
    topo.write_text(TOPOLOGY.format(run=run, policy=policy, checkpoint=ckpt, extra=extra))
    runs = tmp_path / "runs"
    up = subprocess.run(
        [sys.executable, "-m", "dvla", "up", str(topo), "--runs", str(runs), "--base-port", str(free_port_block()),
         "--quiet"], cwd=ROOT, capture_output=True, text=True, timeout=560,
    )
    run_dir = runs / run
    logs = "".join(p.read_text(errors="replace")[-2000:] for p in sorted((run_dir / "logs").glob("*.log")))
    assert up.returncode == 0, up.stdout + up.stderr + logs
    result = json.loads((run_dir / "result.json").read_text())
    assert result["reason"] == "max_env_steps" and result["accounting"]["unaccounted"] == 0, result
    summaries = {p.stem: json.loads(p.read_text()) for p in (run_dir / "summaries").glob("*.json")}
    actor = summaries["actor-node0-0"]["extra"]
    assert summaries["actor-node0-0"]["error"] is None
    assert actor["published_version"] >= 4 and actor["updates_refused_nonfinite"] == 0
    # LoRA: a version carries the adapters and heads only
    assert actor["base_hash"] and actor["replicated_values"] / actor["parameters"] <= 0.05, actor
    per_version = actor["publish_bytes"]["full_bytes"] / actor["publish_bytes"]["full_versions"]
    assert per_version <= 0.05 * 4 * actor["parameters"] + 4096, (per_version, actor["parameters"])
    # the learner's log-probs of the rollouts' actions start where the rollouts' were
    assert actor["learn"]["behaviour_kl"] < 0.5, actor["learn"]
    replicator = summaries["replicator-node0-0"]["extra"]
    assert replicator["held_version"] >= 3 and replicator["weights"]["refused_base"] == 0
    for name in ROLLOUTS:
        s = summaries[name]
        assert s["policy_version"] >= 3, f"{name} never acted with a trained version"
        assert s["extra"]["weights"]["refused_base"] == 0
        # per env step: two 32x32x3 images (obs, final_obs), the extras, and ~650 bytes of tokens,
        # proprio, scalars, next_obs (one image per chunk of 10 steps) and headers
        per_step = s["extra"]["bytes_shipped"] / s["env_steps"]
        assert 2 * 32 * 32 * 3 + per_step_extras < per_step < 2 * 32 * 32 * 3 + per_step_extras + 1000, per_step
    ev = summaries["evaluator-node0-0"]
    assert ev["extra"]["evals"] >= 1 and ev["policy_version"] >= 1
    assert pids_of_run(run_dir) == []
