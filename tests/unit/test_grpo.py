"""GRPO: group-relative advantages over whole-episode chunk columns, grouped seeded resets,
binary success reward, action chunks, and the topology rules that keep the layout valid."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from dvla.config import TaskConfig, grpo_layout_problems
from dvla.learn.envs import EnvGroup
from dvla.learn.grpo import episode_steps, group_advantages, group_stats, grpo_envs
from dvla.orchestrator.topology import TopologyError, parse_topology


class _SeedEnv(gym.Env):
    """obs = [reset seed, steps, sum of actions]; succeeds from step `success_at` on."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (3,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self, limit: int, success_at: int = 2):
        self.limit, self.success_at = limit, success_at
        self.seed_, self.steps, self.total = -1, 0, 0.0

    def _obs(self):
        return np.array([self.seed_, self.steps, self.total], np.float32)

    def reset(self, *, seed=None, options=None):
        self.seed_, self.steps, self.total = seed, 0, 0.0
        return self._obs(), {}

    def step(self, action):
        self.steps += 1
        self.total += float(action[0])
        ok = self.steps >= self.success_at
        return self._obs(), 0.5, ok, self.steps >= self.limit, {"success": ok}


def make_seed_env(task: TaskConfig, seed: int) -> gym.Env:
    return _SeedEnv(task.max_episode_steps)


ENV = f"{__name__}:make_seed_env"


def test_group_advantages_normalise_within_groups_and_broadcast_over_steps():
    T = 3
    # four episodes, groups of two: returns (per column) 1, 3 | 2, 2
    rewards = torch.tensor([[1.0, 1.0, 2.0, 0.0], [0.0, 1.0, 0.0, 1.0], [0.0, 1.0, 0.0, 1.0]])
    term = torch.zeros(T, 4, dtype=torch.bool)
    trunc = torch.zeros(T, 4, dtype=torch.bool)
    trunc[-1] = True
    adv = group_advantages(rewards, term, trunc, group_size=2)
    assert adv.shape == (T, 4)
    torch.testing.assert_close(adv[0], torch.tensor([-1.0, 1.0, 0.0, 0.0]))  # (R - mean) / std; equal -> 0
    torch.testing.assert_close(adv, adv[0].expand(T, 4))
    assert group_stats(rewards.numpy(), 2) == {"groups_informative": 0.5, "episode_return_mean": 2.0}


def test_group_advantages_refuse_broken_layouts():
    r = torch.zeros(2, 4)
    done = torch.zeros(2, 4, dtype=torch.bool)
    done[-1] = True
    with pytest.raises(ValueError, match="multiple of group_size 3"):
        group_advantages(r, done, done, 3)
    early = done.clone()
    early[0, 1] = True  # an episode ended mid-chunk: the column is not one episode
    with pytest.raises(ValueError, match="whole episodes"):
        group_advantages(r, early, done, 2)
    with pytest.raises(ValueError, match="whole episodes"):
        group_advantages(r, torch.zeros_like(done), torch.zeros_like(done), 2)


def test_grouped_seeds_give_each_group_one_initial_state_per_round():
    task = TaskConfig(env=ENV, max_episode_steps=3, algorithm="grpo", group_size=2)
    with EnvGroup(task, 4, seed=100, **grpo_envs(task)) as g:
        first = g.reset()
        np.testing.assert_array_equal(first[:, 0], [100, 100, 101, 101])
        for _ in range(3):  # terminations are ignored: every env plays to the limit together
            res = g.step(np.zeros((4, 1)))
        assert res.truncated.all() and not res.terminated.any()
        np.testing.assert_array_equal(res.next_obs[:, 0], [102, 102, 103, 103])
        np.testing.assert_array_equal(g.episode_seeds, [102, 102, 103, 103])
    with pytest.raises(ValueError, match="group_size"):
        EnvGroup(task, 3, seed=0, group_size=2)


def test_success_reward_pays_once_per_episode():
    task = TaskConfig(env=ENV, max_episode_steps=4, reward="success")
    with EnvGroup(task, 1, seed=0, ignore_terminations=True) as g:
        g.reset()
        rewards = [g.step([[0.0]]).reward[0] for _ in range(4)]
    assert rewards == [0.0, 1.0, 0.0, 0.0]  # success from step 2 on, paid at its first step
    dense = TaskConfig(env=ENV, max_episode_steps=4)
    with EnvGroup(dense, 1, seed=0, ignore_terminations=True) as g:
        g.reset()
        assert g.step([[0.0]]).reward[0] == 0.5


def test_action_chunks_play_k_steps_open_loop():
    task = TaskConfig(env=ENV, max_episode_steps=5, action_chunk=2)
    with EnvGroup(task, 1, seed=0, ignore_terminations=True) as g:
        assert (g.act_dim, g.env_act_dim) == (2, 1)
        g.reset()
        res = g.step([[0.25, 0.5]])
        assert res.next_obs[0, 1:].tolist() == [2, 0.75] and res.reward[0] == 1.0
        g.step([[0.0, 0.0]])
        res = g.step([[1.0, 1.0]])  # step 5 hits the limit after the first sub-step
        assert res.truncated[0] and res.final_obs[0, 1:].tolist() == [5, 1.75]
    assert episode_steps(task) == 3


def test_layout_rules_and_topology_errors():
    ok = TaskConfig(algorithm="grpo", group_size=2, chunk_steps=50, max_episode_steps=50, envs_per_rollout=4)
    assert grpo_layout_problems(ok) == []
    assert grpo_layout_problems(TaskConfig()) == []  # PPO: no constraint
    bad = TaskConfig(algorithm="grpo", group_size=4, chunk_steps=10, max_episode_steps=50, envs_per_rollout=4)
    assert [k for k, _ in grpo_layout_problems(bad)] == ["chunk_steps", "envs_per_rollout"]
    text = """
run: g
task: {env: PushCube-v1, algorithm: grpo, group_size: 4, chunk_steps: 10, envs_per_rollout: 4, reward: succes}
racks: [{name: r, nodes: [{name: n, roles: [{role: actor}, {role: rollout}]}]}]
"""
    with pytest.raises(TopologyError) as err:
        parse_topology(text, "g.yaml")
    msg = str(err.value)
    assert "task.chunk_steps: 10 must equal the transitions of one episode" in msg
    assert "task.envs_per_rollout: 4 splits into env groups of [2, 2]" in msg
    assert "task.reward" in msg and "succes" in msg
    good = text.replace("chunk_steps: 10, envs_per_rollout: 4, reward: succes", "chunk_steps: 50, envs_per_rollout: 8, reward: success")
    topo = parse_topology(good, "g.yaml")
    assert (topo.task.algorithm, topo.task.group_size, topo.task.reward) == ("grpo", 4, "success")
