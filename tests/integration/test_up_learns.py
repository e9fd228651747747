"""A VLA learns through `dvla up` itself: the rollout processes' recording, the data plane, the
actor's slots, advantages and update, the weight tree and the evaluator, at toy size.

The task is reach-to-colour in its multi-decision form (tests/plugin_env/reach_colour.py,
``make_sequence``): three decisions an episode, each with a new rendered colour and instruction
and its own reward, so a step's action or reward paired with a neighbouring step's observation
anywhere along the real path leaves nothing to learn. The untrained policy solves about 1 in 27
episodes; the run must stop on its success rule (the 95 % lower bound of one 48-episode
evaluation >= 0.8) well inside its step budget, in both modes (it does at ~1,500 env steps).

``gae_lambda: 0`` makes each step's advantage its own reward plus the next state's value: with
the default 0.9 the recursion carries a reward written one step late back to the step it belongs
to, and a rollout that recorded ``rewards[t + 1] = reward of step t`` still learned. With 0 that
broken rollout stayed at 0.02-0.06 success for the whole 12,000-step budget (the run then exits 1).
tests/unit/test_vla_learning.py is the same bar in one process, where the advantage sign and the
extras are broken on purpose.
"""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

import pytest

from tests.integration.test_up_e2e import ROOT, dvla, free_port_block, pids_of_run

pytestmark = pytest.mark.learning

TOPOLOGY = """
run: reach
mode: {mode}
task:
  env: reach_colour:make_sequence
  obs_mode: rgb
  max_episode_steps: 3
  instruction_tokens: 4
  policy: tiny-vla
  envs_per_rollout: 16
  chunk_steps: 6
  ppo: {{lr: 0.001, gamma: 0.8, gae_lambda: 0.0, batch_steps: 192, minibatches: 2, update_epochs: 4, target_kl: null}}
  eval: {{episodes: 48, every_versions: 3}}
  budget: {{max_env_steps: {budget}, until_success: 0.8, success_on: lower_bound, consecutive: 1}}
racks:
  - name: rack0
    nodes:
      - name: node0
        host: localhost
        roles:
          - role: actor
          - role: rollout
            count: 2
          - role: evaluator
"""

#: env steps the run may take; the in-process loop of the same settings solves the task in ~1,200
BUDGET = 12_000


@pytest.mark.timeout(400)
@pytest.mark.parametrize("mode", ["async", "sync"])
def test_up_learns_a_multi_step_rendered_task(tmp_path: Path, mode: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(ROOT / "tests" / "plugin_env"), str(ROOT)]))
    topo = tmp_path / "reach.yaml"
    topo.write_text(TOPOLOGY.format(mode=mode, budget=BUDGET))
    runs = tmp_path / "runs"
    up = dvla("up", str(topo), "--runs", str(runs), "--base-port", str(free_port_block()), "--seed", "1",
              "--quiet", timeout=380)
    run_dir = runs / "reach"
    assert up.returncode == 0, up.stdout + up.stderr
    result = json.loads((run_dir / "result.json").read_text())
    with open(run_dir / "evals.csv") as f:
        evals = [(int(r["env_steps"]), float(r["success_once"])) for r in csv.DictReader(f)]
    assert result["reason"] == "success", (result["reason"], evals)
    assert evals[0][1] < 0.3, f"the first evaluation already solved the task: {evals}"
    assert evals[-1][1] >= 0.8 and result["final_env_steps"] < BUDGET, evals
    # This cheap env makes the rollouts ship several times what the busy actor learns from (most
    # chunks are dropped stale, counted), so a stopping rollout has MBs still in its link: it waits
    # for the actor's receipt of its last chunk before it closes (docs/reliability.md, "Closing a
    # rollout"). Nothing is killed here, so nothing may be lost either.
    acct = result["accounting"]
    assert acct["unaccounted"] == 0 and acct["lost"] == 0, acct
    assert pids_of_run(run_dir) == []
