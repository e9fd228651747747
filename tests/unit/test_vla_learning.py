"""A VLA learns through dvla's own code path, at toy size: `vla-tokens` (a random test-size
Llava checkpoint, action bins shipped as extras) on reach-to-colour (tests/plugin_env/
reach_colour.py: a rendered patch and an instruction name one of three bins of a one-number
action).

The loop is `dvla up`'s, in one process and in lock-step: the rollout's env group, sampling
(`sample_actions`) and chunk (the run's `chunk_spec`, extras beside the action); the actor's
chunk check (`chunk_problem`), slots (`SlotPool.fill` / `stack`), advantages (`gae_batch`) and
update (`PPOLearner.update`, which hands the extras back to `evaluate`); the evaluator's
deterministic episodes (`run_eval_episodes`). What stands in for the fabric is a state-dict copy
into the rollout's own policy after every update.

The bar is only meaningful if a broken path misses it, so the same loop is run twice more with one
thing broken through a public seam: the advantages' sign flipped (`dvla.learn.ppo.compute_gae`
patched), and the extras shuffled between the steps of each batch (the loop's ``tamper``
parameter, between the slots and `gae_batch`). Neither may reach the bar.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Callable

import pytest
import torch

from dvla.config import PPOConfig, TaskConfig
from dvla.learn import ppo
from dvla.learn.envs import chunk_spec, env_groups, make_env_group, obs_as_dict, obs_to_torch, run_eval_episodes
from dvla.learn.policies import extras_spec, make_policy, sample_actions
from dvla.learn.ppo import PPOLearner, Trajectories, gae_batch
from dvla.learn.vla.build import save_random_checkpoint
from dvla.roles.actor import chunk_problem
from dvla.roles.slots import SlotPool

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "plugin_env"))
from reach_colour import COLOURS  # noqa: E402

pytestmark = [pytest.mark.learning, pytest.mark.usefixtures("one_torch_thread")]

#: envs of the one rollout (two double-buffered groups of 8: two chunks a version), steps per chunk
ENVS, STEPS = 16, 4
#: policy versions learned
VERSIONS = 12
#: deterministic evaluation episodes (fixed seeds, none a training env plays)
EVAL_EPISODES = 48
EVAL_SEED = 1_000_000
#: what a learning path must reach: evaluation success after VERSIONS versions. An untrained
#: policy reaches one bin of three (a third of the episodes, or none); see test_the_bar_*
BAR = 0.8

Tamper = Callable[[Trajectories], Trajectories]


@pytest.fixture(scope="module")
def task(tmp_path_factory) -> TaskConfig:
    ckpt = save_random_checkpoint(tmp_path_factory.mktemp("reach") / "tokens", "tokens", action_dim=1, max_chunk=1,
                                  n_bins=32, instruction_words=["reach", *COLOURS])
    return TaskConfig(
        env="reach_colour:make", obs_mode="rgb", max_episode_steps=1, instruction_tokens=4,
        policy="vla-tokens", policy_kwargs={"checkpoint": str(ckpt)},
        envs_per_rollout=ENVS, chunk_steps=STEPS, device="cpu",
        ppo=PPOConfig(lr=1e-3, update_epochs=4, minibatches=2, batch_steps=ENVS * STEPS, target_kl=None,
                      terminal_bootstrap=False),
    )


def train(task: TaskConfig, seed: int, tamper: Tamper | None = None) -> tuple[float, float]:
    """Learn VERSIONS versions; (evaluation success before, after)."""
    torch.manual_seed(seed)
    sizes, _one_scene = env_groups(task)  # the rollout's groups
    groups = [make_env_group(task, n, seed * 10_000 + gid * 1000) for gid, n in enumerate(sizes)]
    evals = make_env_group(task, 8, EVAL_SEED, ignore_terminations=True)
    try:
        spec_group = groups[0]
        learner_policy = make_policy(task.policy, spec_group.obs_spec, spec_group.act_dim, **task.policy_kwargs)
        rollout_policy = make_policy(task.policy, spec_group.obs_spec, spec_group.act_dim, **task.policy_kwargs).eval()
        rollout_policy.load_state_dict(learner_policy.state_dict())
        spec = chunk_spec(task, spec_group.obs_spec, spec_group.act_dim, extras_spec(learner_policy))
        slots = SlotPool(spec, len(groups))
        learner = PPOLearner(learner_policy, task.ppo, "cpu", seed=seed)
        noise = torch.Generator().manual_seed(seed)
        obs = [g.reset() for g in groups]

        def evaluate() -> float:
            res = run_eval_episodes(rollout_policy, task, EVAL_EPISODES, EVAL_SEED, group=evals)
            assert res is not None
            return float(res["success_once"])

        before = evaluate()
        for version in range(VERSIONS):
            for i, g in enumerate(groups):
                chunk = spec.zeros(g.n)
                for t in range(STEPS):  # the rollout's _record_step
                    with torch.no_grad():
                        action, logprob, extras = sample_actions(rollout_policy, obs_to_torch(obs[i]), generator=noise)
                    step = g.step(action.numpy())
                    for k, v in obs_as_dict(obs[i]).items():
                        chunk.obs[k][t] = v
                    chunk.actions[t], chunk.logprobs[t] = action.numpy(), logprob.numpy()
                    for k, v in extras.items():
                        chunk.extras[k][t] = v.numpy()
                    chunk.rewards[t], chunk.terminated[t] = step.reward, step.terminated
                    chunk.truncated[t], chunk.success[t] = step.truncated, step.success
                    for k, v in obs_as_dict(step.final_obs).items():
                        chunk.final_obs[k][t] = v
                    obs[i] = step.next_obs
                for k, v in obs_as_dict(obs[i]).items():
                    chunk.next_obs[k][...] = v
                chunk = dataclasses.replace(chunk, rollout=f"rollout{i}", seq=version, policy_version=version)
                problem = chunk_problem(chunk, spec, version)
                assert problem is None, problem
                slots.fill(i, chunk)
            traj = slots.stack(list(range(len(groups))), torch.device("cpu"))
            if tamper is not None:
                traj = tamper(traj)
            learner.update(gae_batch(learner_policy, traj, task.ppo))
            rollout_policy.load_state_dict(learner_policy.state_dict())
        return before, evaluate()
    finally:
        for g in [*groups, evals]:
            g.close()


def shuffle_extras(traj: Trajectories) -> Trajectories:
    """Every extras tensor's steps in another order (each step keeps its observation and action)."""
    perm = torch.randperm(traj.steps, generator=torch.Generator().manual_seed(1))
    shuffled = {k: v.reshape(traj.steps, *v.shape[2:])[perm].reshape(v.shape) for k, v in traj.extras.items()}
    return dataclasses.replace(traj, extras=shuffled)


compute_gae = ppo.compute_gae


def flipped_gae(*args, **kwargs):
    """compute_gae with the advantages' sign flipped (the returns the critic learns unchanged)."""
    adv, ret = compute_gae(*args, **kwargs)
    return -adv, ret


def test_vla_tokens_learns_reach_to_colour(task):
    before, after = train(task, seed=1)
    assert before < 0.5
    assert after >= BAR, f"evaluation success {before:.2f} -> {after:.2f} after {VERSIONS} versions, bar {BAR}"


def test_the_bar_is_missed_with_the_advantage_sign_flipped(task, monkeypatch):
    monkeypatch.setattr(ppo, "compute_gae", flipped_gae)
    before, after = train(task, seed=1)
    assert after < BAR, f"flipped advantages reached {after:.2f}"


def test_the_bar_is_missed_with_the_extras_shuffled_between_steps(task):
    before, after = train(task, seed=1, tamper=shuffle_extras)
    assert after < BAR, f"shuffled extras reached {after:.2f}"


def test_shuffle_extras_moves_every_extras_tensor_and_nothing_else():
    steps = torch.arange(12).reshape(3, 4)
    traj = Trajectories(obs={"state": steps[..., None].float()}, actions=steps[..., None].float(),
                        logprobs=steps.float(), rewards=steps.float(), terminated=steps > 99, truncated=steps > 99,
                        success=steps > 99, next_obs={"state": torch.zeros(4, 1)}, final_obs={"state": torch.zeros(3, 4, 1)},
                        extras={"bins": steps[..., None].clone()})
    out = shuffle_extras(traj)
    assert torch.equal(out.actions, traj.actions)
    assert not torch.equal(out.extras["bins"], traj.extras["bins"])
    assert sorted(out.extras["bins"].flatten().tolist()) == list(range(12))
