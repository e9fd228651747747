"""A finished run's final policy evaluated on its own: the run directory's current checkpoint
loaded into the run's policy and played on episodes none of the run's evaluations played, so the
figure carries no selection by the stop rule (which looked at the run's fixed evaluation states
many times over). ``dvla bench e2e --final-eval N`` calls it after every run."""

from __future__ import annotations

from pathlib import Path
from typing import Any

#: first seed of the independent episodes of the run with master seed s: FRESH_SEED_BASE + s * 1000.
#: The run's evaluations start at s * 1000 + eval.seed_offset (1,001,000 for seed 1 by default) and
#: its rollouts' envs at (s * 1000 + rollout index) * 10,000 (10,000,000 for seed 1), so for seeds
#: 1 to 99 at the default offset none of the three ranges meets another
FRESH_SEED_BASE = 9_000_000


def fresh_seed(run_seed: int) -> int:
    """Seed of the first independent episode of the run with master seed ``run_seed``."""
    return FRESH_SEED_BASE + run_seed * 1000


def evaluate_run(run_dir: Path, episodes: int, seed: int) -> dict[str, Any]:
    """Play ``episodes`` deterministic episodes (episode j from seed ``seed + j``, to the time
    limit) with the policy of ``run_dir``'s current checkpoint; the version played, success_once
    with its 95 % Wilson interval, success_at_end, return_mean and env_steps."""
    import dataclasses

    import torch

    from dvla.learn import make_env_group, make_policy, run_eval_episodes
    from dvla.learn.checkpoint_files import read_current
    from dvla.orchestrator.topology import load_topology

    task = load_topology(run_dir / "topology.yaml").task
    current = read_current(run_dir / "checkpoints")
    if current is None:
        raise RuntimeError(f"{run_dir / 'checkpoints'}: no checkpoint written")
    version, tensors = current
    # every episode to the time limit, whatever the run's evaluations did
    task = dataclasses.replace(task, eval=dataclasses.replace(task.eval, full_episodes=True))
    group = make_env_group(task, min(task.eval.envs, episodes), seed, ignore_terminations=True, batching="auto")
    try:
        policy = make_policy(task.policy, group.obs_spec, group.act_dim, **task.policy_kwargs)
        _missing, unexpected = policy.load_state_dict(tensors, strict=False)
        if unexpected:
            raise RuntimeError(f"{run_dir / 'checkpoints'}: tensors the policy does not have: {sorted(unexpected)[:4]}")
        policy.eval()
        with torch.no_grad():
            res = run_eval_episodes(policy, task, episodes, seed, "cpu", group=group)
    finally:
        group.close()
    assert res is not None  # no stop event: every episode is played
    keys = ("episodes", "success_once", "success_once_low", "success_once_high", "success_at_end", "return_mean",
            "env_steps")
    return {"version": version, "seed": seed, **{k: res[k] for k in keys}}
