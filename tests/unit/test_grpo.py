"""GRPO: group-relative advantages over whole-episode chunk columns, grouped seeded resets,
binary success reward, action chunks, and the topology rules that keep the layout valid."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from dvla.config import TaskConfig, grpo_layout_problems
from dvla.learn.envs import EnvGroup
from dvla.learn.grpo import group_advantages, grpo_batch, grpo_envs
from dvla.learn.ppo import Trajectories
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


def _whole_episodes(T: int, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    term = torch.zeros(T, n, dtype=torch.bool)
    trunc = torch.zeros(T, n, dtype=torch.bool)
    trunc[-1] = True
    return term, trunc


def test_episode_baseline_is_the_default_of_group_advantages_and_the_step_one_of_tasks():
    # equal returns (2, 2); reward-to-go: column 0 (2, 2, 1), column 1 (2, 0, 0)
    rewards = torch.tensor([[0.0, 2.0], [1.0, 0.0], [1.0, 0.0]])
    term, trunc = _whole_episodes(3, 2)
    assert (group_advantages(rewards, term, trunc, 2) == 0).all()
    task = TaskConfig(algorithm="grpo", group_size=2, grpo_gamma=1.0, grpo_std_floor=0.0)
    assert task.grpo_baseline == "step"
    want = torch.tensor([[0.0, 0.0], [1.0, -1.0], [1.0, -1.0]])
    obs = {"state": torch.zeros(3, 2, 1)}
    b = Trajectories(obs=obs, actions=torch.zeros(3, 2, 1), logprobs=torch.zeros(3, 2), rewards=rewards, terminated=term,
                     truncated=trunc, success=term, next_obs={"state": torch.zeros(2, 1)}, final_obs=obs)
    batch = grpo_batch(b, task)  # what the actor trains on: advantages [T*N], no critic
    torch.testing.assert_close(batch["advantages"].reshape(3, 2), want)
    assert (batch["returns"] == 0).all() and (batch["values"] == 0).all() and batch["obs"].shape == (6, 1)


def test_step_baseline_uses_the_groups_reward_to_go_at_each_step():
    T, G = 4, 3
    rng = np.random.default_rng(0)
    rewards = torch.tensor(rng.uniform(0, 1, (T, 2 * G)), dtype=torch.float32)
    term, trunc = _whole_episodes(T, 2 * G)
    gamma = 0.9
    adv = group_advantages(rewards, term, trunc, G, baseline="step", gamma=gamma)
    r = rewards.numpy().astype(np.float64)
    for t in range(T):
        to_go = sum(gamma ** (k - t) * r[k] for k in range(t, T))
        for g in range(2):
            cols = slice(g * G, (g + 1) * G)
            x = to_go[cols]
            np.testing.assert_allclose(adv[t, cols].numpy(), (x - x.mean()) / x.std(), rtol=1e-5, atol=1e-6)
    # group-relative: zero mean in every group at every step, and adding a constant to one
    # group's rewards (or any per-step offset shared by a group) changes nothing
    np.testing.assert_allclose(adv.reshape(T, 2, G).sum(2).numpy(), 0.0, atol=1e-5)
    shifted = rewards.clone()
    shifted[:, :G] += torch.arange(T, dtype=torch.float32).unsqueeze(1) * 5.0
    torch.testing.assert_close(group_advantages(shifted, term, trunc, G, baseline="step", gamma=gamma), adv, atol=1e-5, rtol=1e-4)
    # the step baseline differs from the episode one once rewards before t differ
    assert not torch.allclose(adv, group_advantages(rewards, term, trunc, G))


def test_step_baseline_does_not_credit_later_actions_with_earlier_rewards():
    # episode 0 collects a reward at t=0 only, episode 1 at t=2 only: with the episode baseline
    # every step of episode 0 looks as good as every step of episode 1; with the step baseline
    # the steps after episode 0's reward are worse than episode 1's
    rewards = torch.tensor([[1.0, 0.0], [0.0, 0.0], [0.0, 1.0]])
    term, trunc = _whole_episodes(3, 2)
    episode = group_advantages(rewards, term, trunc, 2, baseline="episode")
    assert (episode == 0).all()
    step = group_advantages(rewards, term, trunc, 2, baseline="step", gamma=1.0)
    torch.testing.assert_close(step, torch.tensor([[0.0, 0.0], [-1.0, 1.0], [-1.0, 1.0]]))


def test_std_floor_keeps_near_identical_groups_small():
    rewards = torch.tensor([[1.0, 1.001, 0.0, 1.0]])
    term, trunc = _whole_episodes(1, 4)
    for baseline in ("episode", "step"):
        raw = group_advantages(rewards, term, trunc, 2, baseline=baseline)
        floored = group_advantages(rewards, term, trunc, 2, baseline=baseline, std_floor=0.1)
        # without a floor a 0.001 difference becomes a full +-1 advantage
        torch.testing.assert_close(raw[0], torch.tensor([-1.0, 1.0, -1.0, 1.0]), atol=1e-4, rtol=0)
        # with it the tiny difference stays tiny (0.0005 / 0.1), a real one is untouched (std 0.5)
        torch.testing.assert_close(floored[0], torch.tensor([-0.005, 0.005, -1.0, 1.0]), atol=1e-5, rtol=0)


def test_success_reward_with_the_step_baseline():
    # binary success reward, groups of two: only the episode that succeeds (at t=1) gains
    rewards = torch.tensor([[0.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]])
    term, trunc = _whole_episodes(3, 4)
    adv = group_advantages(rewards, term, trunc, 2, baseline="step", gamma=0.5)
    torch.testing.assert_close(adv[:2, :2], torch.tensor([[1.0, -1.0], [1.0, -1.0]]))
    assert (adv[2] == 0).all() and (adv[:, 2:] == 0).all()  # after the success, and failed groups
    with pytest.raises(ValueError, match="baseline"):
        group_advantages(rewards, term, trunc, 2, baseline="critic")


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
    # episodes of different lengths in one batch are refused with the step baseline too
    with pytest.raises(ValueError, match="whole episodes"):
        group_advantages(r, early, done, 2, baseline="step")


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
    # a GRPO chunk is one episode: 5 simulator steps in chunks of 2 are 3 transitions
    one_episode = dict(algorithm="grpo", group_size=2, envs_per_rollout=4, max_episode_steps=5, action_chunk=2)
    assert grpo_layout_problems(TaskConfig(**one_episode, chunk_steps=3)) == []
    assert [k for k, _ in grpo_layout_problems(TaskConfig(**one_episode, chunk_steps=2))] == ["chunk_steps"]


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
    knobs = good.replace("reward: success}", "reward: success, grpo_baseline: critic, grpo_gamma: 0, grpo_std_floor: -1}")
    with pytest.raises(TopologyError) as err:
        parse_topology(knobs, "g.yaml")
    lines = str(err.value).splitlines()
    for key, what in (("grpo_baseline", "critic"), ("grpo_gamma", "0 is out of range"), ("grpo_std_floor", "-1.0 is out of range")):
        assert any(f"g.yaml" in line and f"task.{key}" in line and what in line for line in lines), (key, lines)
    knobs = good.replace("reward: success}", "reward: success, grpo_baseline: episode, grpo_gamma: 0.9, grpo_std_floor: 0.5}")
    task = parse_topology(knobs, "g.yaml").task
    assert (task.grpo_baseline, task.grpo_gamma, task.grpo_std_floor) == ("episode", 0.9, 0.5)
