"""Integration tests of dvla.learn.envs against the real ManiSkill PushCube-v1 (CPU physics)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dvla.config import TaskConfig
from dvla.learn.envs import EnvGroup, run_eval_episodes
from dvla.learn.policies import MLPPolicy

pytest.importorskip("mani_skill")

TASK = TaskConfig(env="PushCube-v1", sim_backend="physx_cpu", max_episode_steps=50)


@pytest.fixture(scope="module")
def group():
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
def test_run_eval_episodes_counts_every_episode():
    torch.manual_seed(0)
    policy = MLPPolicy(35, 8, hidden=(32,))
    with EnvGroup(TASK, 2, seed=0, ignore_terminations=True) as g:
        out = run_eval_episodes(policy, TASK, 3, seed=1000, device="cpu", group=g)
    assert out["episodes"] == 3
    assert out["env_steps"] == 150  # three full 50-step episodes, the fourth slot is not counted
    assert 0.0 <= out["success_at_end"] <= out["success_once"] <= 1.0
    assert np.isfinite(out["return_mean"])
