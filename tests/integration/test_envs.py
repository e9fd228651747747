"""Integration tests of dvla.learn.envs: a scripted "module:factory" env, then the real ManiSkill
PushCube-v1 (CPU physics)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch

from dvla.config import EvalConfig, TaskConfig
from dvla.learn.envs import EnvGroup, run_eval_episodes
from dvla.learn.policies import MLPPolicy

TASK = TaskConfig(env="PushCube-v1", sim_backend="physx_cpu", max_episode_steps=50)


@pytest.fixture(scope="module")
def group():
    pytest.importorskip("mani_skill")
    g = EnvGroup(TASK, 2, seed=123)
    yield g
    g.close()


@pytest.mark.timeout(120)
def test_group_steps_and_auto_resets(group):
    assert (group.obs_dim, group.act_dim) == (35, 8)
    assert group.action_low.shape == (8,) and np.all(group.action_low == -1) and np.all(group.action_high == 1)
    obs = group.reset(seed=123)
    assert obs.shape == (2, 35) and obs.dtype == np.float32
    assert list(group.episode_seeds) == [123, 124]
    rng = np.random.default_rng(0)
    ends = []
    for t in range(120):
        # Out-of-range actions must be clipped, not rejected.
        res = group.step(rng.uniform(-3, 3, size=(2, 8)))
        assert res.next_obs.shape == (2, 35) and res.next_obs.dtype == np.float32
        assert res.final_obs.shape == (2, 35) and res.final_obs.dtype == np.float32
        assert res.reward.shape == (2,) and res.reward.dtype == np.float32
        for a in (res.terminated, res.truncated, res.success, res.episode_done):
            assert a.shape == (2,) and a.dtype == bool
        np.testing.assert_array_equal(res.episode_done, res.terminated | res.truncated)
        assert np.all(res.final_obs[~res.episode_done] == 0)
        for i in np.flatnonzero(res.episode_done):
            ends.append((t, i, bool(res.truncated[i])))
            # The final observation is the pre-reset state, not the new episode's first one.
            assert np.any(res.final_obs[i] != 0)
            assert not np.allclose(res.final_obs[i], res.next_obs[i])
        obs = res.next_obs
    truncations = [(t, i) for t, i, trunc in ends if trunc]
    # Random actions rarely push the cube home: both envs hit the 50-step limit twice.
    assert (49, 0) in truncations and (49, 1) in truncations
    assert (99, 0) in truncations and (99, 1) in truncations
    # Auto-resets follow the schedule seed + k*n + i.
    assert list(group.episode_seeds) == [127, 128]


@pytest.mark.timeout(120)
def test_seeded_resets_replay_initial_states(group):
    a = group.reset(seed=5)
    b = group.reset_seeded([5, 5])
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(b[0], b[1])
    c = group.reset(seed=5)
    np.testing.assert_array_equal(a, c)


@pytest.mark.timeout(120)
def test_run_eval_episodes_counts_every_episode(group):
    torch.manual_seed(0)
    policy = MLPPolicy(35, 8, hidden=(32,))
    # The untrained policy's mean action barely moves the arm, so no episode ends early.
    out = run_eval_episodes(policy, TASK, 3, seed=1000, device="cpu", group=group)
    assert out["episodes"] == 3
    assert out["env_steps"] == 150  # three full 50-step episodes, the fourth slot is not counted
    assert 0.0 <= out["success_at_end"] <= out["success_once"] <= 1.0
    assert np.isfinite(out["return_mean"])


class _ScriptedEnv(gym.Env):
    """Succeeds (and terminates) at step 3; obs = [steps, reset seed, last action]."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (3,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self, limit: int):
        self.limit, self.steps, self.seed_ = limit, 0, -1

    def _obs(self, action: float = 0.0) -> np.ndarray:
        return np.array([self.steps, self.seed_, action], np.float32)

    def reset(self, *, seed=None, options=None):
        self.steps, self.seed_ = 0, seed
        return self._obs(), {}

    def step(self, action):
        self.steps += 1
        success = self.steps == 3
        return self._obs(float(action[0])), 1.0, success, self.steps >= self.limit, {"success": success}


def make_scripted_env(task: TaskConfig, seed: int) -> gym.Env:
    return _ScriptedEnv(task.max_episode_steps)


SCRIPTED = TaskConfig(env=f"{__name__}:make_scripted_env", max_episode_steps=5)


def test_factory_env_terminations_and_auto_reset():
    with EnvGroup(SCRIPTED, 2, seed=10) as g:
        assert (g.obs_dim, g.act_dim) == (3, 1)
        np.testing.assert_array_equal(g.reset()[:, 1], [10, 11])
        for _ in range(2):
            res = g.step([[5.0], [-5.0]])
            assert not res.episode_done.any()
        np.testing.assert_array_equal(res.next_obs[:, 2], [1.0, -1.0])  # clipped
        res = g.step(np.zeros((2, 1)))
        assert res.terminated.all() and res.success.all() and not res.truncated.any()
        np.testing.assert_array_equal(res.final_obs[:, 0], [3, 3])
        np.testing.assert_array_equal(res.next_obs[:, :2], [[0, 12], [0, 13]])  # seed + k*n + i


def test_factory_env_ignore_terminations_runs_to_the_limit():
    with EnvGroup(SCRIPTED, 1, seed=0, ignore_terminations=True) as g:
        g.reset()
        dones = [g.step([[0.0]]) for _ in range(5)]
        assert not any(r.terminated.any() for r in dones)
        assert dones[2].success[0] and not dones[2].episode_done[0]
        assert dones[4].truncated[0] and dones[4].final_obs[0, 0] == 5


def test_eval_on_factory_env():
    class Zero(torch.nn.Module):
        def act(self, obs, deterministic=False):
            z = torch.zeros(obs.shape[0])
            return torch.zeros(obs.shape[0], 1), z, z

    out = run_eval_episodes(Zero(), SCRIPTED, 3, seed=0, n_envs=2)
    assert out["episodes"] == 3 and out["env_steps"] == 15
    assert out["success_once"] == 1.0 and out["success_at_end"] == 0.0
    assert out["return_mean"] == 5.0


class _SeededEnv(gym.Env):
    """Succeeds (and terminates) at step ``seed % 4 + 1``, never for seeds divisible by 5;
    obs = [steps, reset seed]. ``calls`` counts the steps of every instance."""

    calls = 0
    observation_space = gym.spaces.Box(-np.inf, np.inf, (2,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def __init__(self, limit: int):
        self.limit, self.steps, self.seed_ = limit, 0, -1

    def reset(self, *, seed=None, options=None):
        self.steps, self.seed_ = 0, seed
        return np.array([0, seed], np.float32), {}

    def step(self, action):
        _SeededEnv.calls += 1
        self.steps += 1
        success = self.seed_ % 5 != 0 and self.steps >= self.seed_ % 4 + 1
        obs = np.array([self.steps, self.seed_], np.float32)
        return obs, 1.0, success, self.steps >= self.limit, {"success": success}


def make_seeded_env(task: TaskConfig, seed: int) -> gym.Env:
    return _SeededEnv(task.max_episode_steps)


def _seeded_task(full_episodes: bool) -> TaskConfig:
    return TaskConfig(env=f"{__name__}:make_seeded_env", max_episode_steps=6,
                      eval=EvalConfig(full_episodes=full_episodes))


class _Zero(torch.nn.Module):
    def act(self, obs, deterministic=False):
        z = torch.zeros(obs.shape[0])
        return torch.zeros(obs.shape[0], 1), z, z


def test_inactive_envs_are_not_stepped():
    with EnvGroup(SCRIPTED, 2, seed=10) as g:
        g.reset()
        res = g.step(np.zeros((2, 1)), active=[True, False])
        np.testing.assert_array_equal(res.next_obs[:, 0], [1, 0])  # env 1 did not take a step
        np.testing.assert_array_equal(res.reward, [1.0, 0.0])
        res = g.step(np.zeros((2, 1)))
        np.testing.assert_array_equal(res.next_obs[:, 0], [2, 1])


@pytest.mark.parametrize("envs", [1, 3, 8])
def test_eval_ending_episodes_at_termination_keeps_success_once(envs):
    """eval.full_episodes=False: the same episodes, the same success_once and failures, each
    episode played only to its success, and no env stepped once its episodes are all played."""
    full = run_eval_episodes(_Zero(), _seeded_task(True), 11, seed=20, n_envs=envs)
    _SeededEnv.calls = 0
    short = run_eval_episodes(_Zero(), _seeded_task(False), 11, seed=20, n_envs=envs)
    assert _SeededEnv.calls == short["env_steps"]  # what was simulated is what was counted
    seeds = range(20, 31)
    failed = [j for j, s in enumerate(seeds) if s % 5 == 0]
    assert full["failed_episodes"] == short["failed_episodes"] == failed
    assert full["success_once"] == short["success_once"] == 1 - len(failed) / 11
    assert full["env_steps"] == 11 * 6
    assert short["env_steps"] == sum(6 if s % 5 == 0 else s % 4 + 1 for s in seeds)
    assert full["success_at_end"] == full["success_once"]  # this env stays successful once it is
    assert short["success_at_end"] == short["success_once"]
    assert short["episodes"] == 11 and short["return_mean"] < full["return_mean"]


@pytest.mark.timeout(180)
def test_one_scene_group_plays_maniskill_like_the_loop_group():
    """VectorEnvGroup on real ManiSkill (ManiSkillVectorEnv over physx_cpu, which allows one env
    per scene): the same seed and actions give the loop group's first episode exactly, as
    tensors; the episode then ends, is reset, and the group plays on."""
    pytest.importorskip("mani_skill")
    from dvla.learn.vector_env import VectorEnvGroup

    task = TaskConfig(env="PushCube-v1", sim_backend="physx_cpu", max_episode_steps=10)
    loop, scene = EnvGroup(task, 1, seed=7), VectorEnvGroup(task, 1, seed=7, backend="physx_cpu")
    try:
        assert scene.obs_spec == loop.obs_spec and scene.act_dim == loop.act_dim
        a, b = loop.reset(), scene.reset()
        assert isinstance(b, torch.Tensor) and np.array_equal(a, b.numpy())
        rng = np.random.default_rng(1)
        for t in range(10):
            act = rng.uniform(-1, 1, (1, 8)).astype(np.float32)
            x, y = loop.step(act), scene.step(torch.from_numpy(act))
            for field in ("reward", "terminated", "truncated", "success", "episode_done", "final_obs"):
                assert np.array_equal(getattr(x, field), getattr(y, field).numpy()), (t, field)
        assert y.truncated.tolist() == [True] and not torch.equal(y.next_obs, y.final_obs)
        y = scene.step(torch.zeros(1, 8))
        assert y.next_obs.shape == (1, 35) and not y.episode_done.any()
    finally:
        loop.close()
        scene.close()
