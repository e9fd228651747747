"""The one-scene env group (dvla/learn/vector_env.py) on CPU, against a batched torch env with
ManiSkillVectorEnv's calls (tests/plugin_env/batched_reach.py), and the layout rule that picks
it (sim_layout). Real ManiSkill through the same class: tests/integration/test_envs.py."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from dvla.config import TaskConfig
from dvla.learn.envs import EnvSetupError, chunk_envs, env_groups, make_env_group, run_eval_episodes, sim_layout
from dvla.learn.policies import make_policy
from dvla.learn.spec import ArraySpec, ChunkSpec
from dvla.learn.vector_env import DeviceChunk, VectorEnvGroup

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "plugin_env"))
from batched_reach import BatchedReach  # noqa: E402

TASK = TaskConfig(env="batched_reach:make", env_batching="scene", max_episode_steps=6)


def group(n: int = 4, seed: int = 3, task: TaskConfig = TASK, scene: BatchedReach | None = None, **kw) -> VectorEnvGroup:
    """A one-scene group over ``scene`` (the batched env the test holds), or a fresh one."""
    return VectorEnvGroup(task, n, seed, venv=scene or BatchedReach(n, task.max_episode_steps), **kw)


def test_outputs_are_tensors_with_the_env_axis_first() -> None:
    g = group()
    obs = g.reset()
    assert g.on_device and g.obs_spec["state"].shape == (4,) and g.act_dim == 2
    assert isinstance(obs, torch.Tensor) and obs.shape == (4, 4) and obs.dtype == torch.float32
    res = g.step(torch.zeros(4, 2))
    for x, dtype in ((res.reward, torch.float32), (res.terminated, torch.bool), (res.truncated, torch.bool),
                     (res.success, torch.bool), (res.episode_done, torch.bool)):
        assert x.shape == (4,) and x.dtype == dtype
    assert res.next_obs.shape == res.final_obs.shape == (4, 4)


def test_ended_episodes_are_reset_and_their_last_observation_kept() -> None:
    scene = BatchedReach(3, TASK.max_episode_steps)
    g = group(n=3, scene=scene)
    g.reset()
    # env 1 sits on its goal: it succeeds and terminates at once; the others keep going
    scene.pos[1] = scene.goal[1]
    before = scene._obs().clone()
    res = g.step(torch.zeros(3, 2))
    assert res.terminated.tolist() == [False, True, False] and res.episode_done.tolist() == [False, True, False]
    assert torch.equal(res.final_obs[1], before[1])  # zero action: the observation reached
    assert torch.all(res.final_obs[[0, 2]] == 0)
    assert torch.equal(res.next_obs[[0, 2]], before[[0, 2]])  # untouched envs
    assert not torch.equal(res.next_obs[1], before[1])  # env 1 starts anew
    assert g.episode_seeds.tolist() == [3, -1, 5]  # seeded reset: base + i; the reset one is not


def test_time_limit_truncates_every_env_and_ignore_terminations_plays_on() -> None:
    scene = BatchedReach(2, TASK.max_episode_steps)
    g = group(n=2, scene=scene, ignore_terminations=True)
    g.reset()
    scene.pos[0] = scene.goal[0]
    for t in range(6):
        res = g.step(torch.zeros(2, 2))
        assert not res.terminated.any()
        assert res.truncated.tolist() == [t == 5] * 2
    assert res.success[0]  # on its goal all along, never ended early


def test_success_reward_counts_the_first_success_of_an_episode_only() -> None:
    from dataclasses import replace

    scene = BatchedReach(2, TASK.max_episode_steps)
    g = group(n=2, task=replace(TASK, reward="success"), scene=scene, ignore_terminations=True)
    g.reset()
    scene.pos[0] = scene.goal[0]
    rewards = [g.step(torch.zeros(2, 2)).reward.tolist() for _ in range(3)]
    assert rewards == [[1.0, 0.0], [0.0, 0.0], [0.0, 0.0]]


def test_actions_are_clipped_to_the_action_space() -> None:
    scene = BatchedReach(1, TASK.max_episode_steps)
    g = group(n=1, scene=scene)
    g.reset()
    start = scene.pos.clone()
    g.step(torch.full((1, 2), 50.0))
    assert torch.allclose(scene.pos, torch.clamp(start + 0.2, -1, 1))


def test_a_seed_replays_the_run_and_the_global_rng_is_left_alone() -> None:
    def play(seed: int) -> list[torch.Tensor]:
        scene = BatchedReach(4, TASK.max_episode_steps)
        g = group(n=4, seed=seed, scene=scene)
        out = [g.reset()]
        rng = np.random.default_rng(0)
        for _ in range(20):  # ends and resets episodes at different steps
            out.append(g.step(rng.uniform(-1, 1, (4, 2)).astype(np.float32)).next_obs)
        assert scene.resets > 2
        return out

    state = torch.get_rng_state()
    a, b, c = play(3), play(3), play(4)
    assert torch.equal(torch.get_rng_state(), state)
    assert all(torch.equal(x, y) for x, y in zip(a, b))
    assert not all(torch.equal(x, y) for x, y in zip(a, c))


def test_evaluation_runs_on_a_scene() -> None:
    policy = make_policy("mlp", {"state": ArraySpec((4,), "float32")}, 2)
    out = run_eval_episodes(policy, TASK, 6, seed=11, group=group(n=3, ignore_terminations=True))
    assert out["episodes"] == 6 and out["env_steps"] == 6 * 6
    assert 0.0 <= out["success_once"] <= 1.0


def test_action_chunks_are_refused() -> None:
    from dataclasses import replace

    with pytest.raises(ValueError, match="action_chunk"):
        group(task=replace(TASK, action_chunk=2))


def test_device_chunk_copies_a_recorded_chunk_to_the_host() -> None:
    spec = ChunkSpec(obs={"state": ArraySpec((4,), "float32")}, act_dim=2, extras={"chain": ArraySpec((2, 2), "float32")},
                     T=2, N=5)
    host = spec.zeros(3)
    dev = DeviceChunk(spec, 3, "cpu")
    dev.obs["state"][1] = torch.arange(12, dtype=torch.float32).reshape(3, 4)
    dev.success[0] = torch.tensor([True, False, True])
    dev.extras["chain"][1, 2] = 7.0
    dev.next_obs["state"][...] = 2.0
    dev.copy_to(host)
    assert host.obs["state"][1].tolist() == np.arange(12).reshape(3, 4).tolist()
    assert host.success.tolist() == [[True, False, True], [False, False, False]]
    assert host.extras["chain"][1, 2].tolist() == [[7.0, 7.0], [7.0, 7.0]] and host.next_obs["state"].min() == 2.0
    assert spec.problem(host) is None


# --- which group: ManiSkill's rule -------------------------------------------------------------


@pytest.mark.parametrize(
    "kw, n, cuda, expected",
    [
        ({}, 8, False, ("physx_cpu", False)),  # the CPU path, as before
        ({}, 1, True, ("physx_cpu", False)),  # one env: ManiSkill's rule keeps it on the CPU
        ({}, 1024, True, ("physx_cuda", True)),  # many envs on a GPU: one scene
        ({"env_batching": "loop"}, 1024, True, ("physx_cpu", False)),
        ({"sim_backend": "physx_cuda", "env_batching": "loop"}, 8, True, ("physx_cuda", False)),
        ({"sim_backend": "physx_cuda"}, 1, True, ("physx_cuda", True)),
        ({"env_batching": "scene"}, 1, False, ("physx_cpu", True)),  # one env, one CPU scene
        ({"sim_backend": "physx_cpu"}, 1024, True, ("physx_cpu", False)),
        ({"algorithm": "grpo"}, 16, True, ("physx_cpu", False)),  # GRPO needs seeded groups
        ({"env": "libero", "obs_mode": "rgb"}, 4, True, ("", False)),
        ({"env": "m:f"}, 4, True, ("", False)),
        ({"env": "m:f", "env_batching": "scene"}, 4, False, ("", True)),
    ],
)
def test_sim_layout_follows_maniskills_rule(kw: dict, n: int, cuda: bool, expected: tuple) -> None:
    task = TaskConfig(**kw, envs_per_rollout=n)
    assert sim_layout(task, n, cuda) == expected
    # the rollout's groups on that machine: one scene, or two halves; a chunk holds one group
    sizes, one_scene = env_groups(task, cuda)
    assert one_scene == expected[1] and sizes == ([n] if one_scene or n < 2 else [n // 2, n - n // 2])
    # the actor's slots hold the largest chunk a rollout may ship on any machine
    fewest, most = chunk_envs(task)
    assert fewest <= min(sizes) and most >= max(sizes)
    if expected[1]:
        assert most == n


def test_a_scene_of_several_cpu_envs_is_refused_with_the_fix() -> None:
    with pytest.raises(EnvSetupError, match="env_batching: loop"):
        sim_layout(TaskConfig(env_batching="scene"), 4, cuda=False)
    with pytest.raises(EnvSetupError, match="grpo"):
        make_env_group(TASK, 4, 0, group_size=2)


@pytest.mark.parametrize(
    "kw, expected",
    [
        ({}, (8, 16)),  # auto: two halves without CUDA, one scene of 16 with it
        ({"env_batching": "loop"}, (8, 8)),
        ({"env_batching": "scene"}, (16, 16)),  # a machine without CUDA cannot run it at all
        ({"sim_backend": "physx_cuda"}, (16, 16)),
        ({"sim_backend": "physx_cpu"}, (8, 8)),
        ({"algorithm": "grpo", "group_size": 4, "max_episode_steps": 25}, (8, 8)),
        ({"envs_per_rollout": 1}, (1, 1)),
        ({"envs_per_rollout": 5, "env_batching": "loop"}, (2, 3)),
    ],
)
def test_chunk_envs_bounds_every_chunk_a_rollout_of_the_task_may_ship(kw: dict, expected: tuple) -> None:
    assert chunk_envs(TaskConfig(**{"envs_per_rollout": 16, **kw})) == expected
