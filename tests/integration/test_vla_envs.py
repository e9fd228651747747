"""Real ManiSkill3 rgb observations through the env adapter and the wire: camera images stay
uint8 from the renderer to the decoded trajectory chunk, next to proprioception and the
tokenised instruction."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from dvla.config import TaskConfig
from dvla.fabric.codec import decode, encode
from dvla.fabric.messages import TrajectoryChunk
from dvla.learn.envs import EnvGroup, obs_to_torch, run_eval_episodes
from dvla.learn.policies import make_policy
from dvla.learn.vla.tokenizer import tokenize

TASK = TaskConfig(
    env="PushCube-v1", obs_mode="rgb", sim_backend="physx_cpu", max_episode_steps=4, image_size=32,
    instruction="Push the cube to the goal", instruction_tokens=8, policy="tiny-vla",
)


@pytest.fixture(scope="module")
def group():
    pytest.importorskip("mani_skill")
    g = EnvGroup(TASK, 2, seed=7)
    yield g
    g.close()


@pytest.mark.timeout(180)
def test_rgb_observations_and_a_chunk_on_the_wire(group):
    spec = group.obs_spec
    assert {k: (s.shape, s.dtype) for k, s in spec.items()} == {
        "rgb": ((32, 32, 3), "uint8"), "proprio": ((25,), "float32"), "tokens": ((8,), "int32"),
    }
    obs = group.reset(seed=7)
    assert obs["rgb"].dtype == np.uint8 and obs["rgb"].shape == (2, 32, 32, 3)
    assert obs["rgb"].std() > 5  # a rendered scene, not a blank frame
    np.testing.assert_array_equal(obs["tokens"], np.stack([tokenize("push the cube to the goal", 8)] * 2))
    policy = make_policy("tiny-vla", spec, group.act_dim, patch_size=8)
    T = 4
    frames = {k: [] for k in spec}
    for t in range(T):
        for k, v in obs.items():
            frames[k].append(v)
        action, _, _ = policy.act(obs_to_torch(obs))
        res = group.step(action.numpy())
        obs = res.next_obs
    assert res.truncated.all()
    assert res.final_obs["rgb"].dtype == np.uint8 and res.final_obs["rgb"].any()
    # A new episode started: its first frame is not the final one of the last.
    assert not np.array_equal(res.final_obs["rgb"], res.next_obs["rgb"])
    chunk_obs = {k: np.stack(v) for k, v in frames.items()}
    chunk = TrajectoryChunk(
        rollout="r", seq=0, policy_version=0, env_steps=T * 2, obs=chunk_obs,
        actions=np.zeros((T, 2, group.act_dim), np.float32), logprobs=np.zeros((T, 2), np.float32),
        rewards=np.zeros((T, 2), np.float32), terminated=np.zeros((T, 2), bool), truncated=np.zeros((T, 2), bool),
        success=np.zeros((T, 2), bool), next_obs=obs, final_obs={k: np.zeros_like(v) for k, v in chunk_obs.items()},
    )
    back = decode(encode(chunk), expect=TrajectoryChunk)
    for k in spec:
        assert back.obs[k].dtype == chunk_obs[k].dtype
        np.testing.assert_array_equal(back.obs[k], chunk_obs[k])
    # One uint8 byte per pixel: images dominate the chunk and were not widened to float.
    assert len(encode(chunk)) < 1.5 * sum(v.nbytes for v in chunk_obs.values()) * 2


@pytest.mark.timeout(180)
def test_eval_plays_rgb_episodes(group):
    torch.manual_seed(0)
    policy = make_policy("tiny-vla", group.obs_spec, group.act_dim, patch_size=8)
    out = run_eval_episodes(policy, TASK, 2, seed=1000, group=group)
    assert out["episodes"] == 2 and out["env_steps"] == 8


@pytest.mark.timeout(180)
def test_one_scene_group_gives_the_same_rgb_observations():
    """The one-scene group (dvla/learn/vector_env.py) reads ManiSkill's rgb observation as the
    loop group does: the same images, proprioception and tokens, as tensors with the env axis."""
    pytest.importorskip("mani_skill")
    from dvla.learn.vector_env import VectorEnvGroup

    loop, scene = EnvGroup(TASK, 1, seed=5), VectorEnvGroup(TASK, 1, seed=5, backend="physx_cpu")
    try:
        assert scene.obs_spec == loop.obs_spec
        a, b = loop.reset(), scene.reset()
        assert b["rgb"].dtype == torch.uint8 and b["tokens"].dtype == torch.int32
        for k in ("rgb", "proprio", "tokens"):
            assert np.array_equal(a[k], b[k].numpy()), k
        x, y = loop.step(np.zeros((1, 8), np.float32)), scene.step(torch.zeros(1, 8))
        for k in ("rgb", "proprio"):
            assert np.array_equal(x.next_obs[k], y.next_obs[k].numpy()), k
    finally:
        loop.close()
        scene.close()


@pytest.mark.timeout(240)
def test_rgb_plus_state_gives_the_state_vector_as_proprio():
    """obs_mode 'rgb+state': rendered images, and as proprio the privileged state vector (joints,
    tool pose, goal and cube poses) that a state-observation env of the same seed gives, step for
    step; the one-scene group reads it alike. obs_mode 'rgb' gives that vector's first 25 entries
    (joints 9 + 9, tool pose 7) and no object's pose."""
    pytest.importorskip("mani_skill")
    from dvla.learn.vector_env import VectorEnvGroup

    priv = replace(TASK, obs_mode="rgb+state")
    groups = (EnvGroup(replace(TASK, obs_mode="state", policy="mlp"), 1, seed=5), EnvGroup(priv, 1, seed=5),
              VectorEnvGroup(priv, 1, seed=5, backend="physx_cpu"), EnvGroup(TASK, 1, seed=5))
    state, loop, scene, plain = groups
    try:
        s, a, b, c = (g.reset() for g in groups)
        assert loop.obs_spec["proprio"].shape == (s.shape[1],) and s.shape[1] > 25  # more than joints and tool
        assert plain.obs_spec["proprio"].shape == (25,)
        assert scene.obs_spec == loop.obs_spec
        assert a["rgb"].std() > 5
        rng = np.random.default_rng(0)
        for _ in range(3):
            np.testing.assert_allclose(a["proprio"], s, atol=1e-5)
            np.testing.assert_allclose(c["proprio"], s[:, :25], atol=1e-5)
            assert np.array_equal(a["proprio"], b["proprio"].numpy()) and np.array_equal(a["rgb"], b["rgb"].numpy())
            act = rng.uniform(-1, 1, (1, state.act_dim)).astype(np.float32)
            s, a, b = state.step(act).next_obs, loop.step(act).next_obs, scene.step(torch.from_numpy(act)).next_obs
            c = plain.step(act).next_obs
    finally:
        for g in groups:
            g.close()
