"""The rollout's weights: one policy module that installs the verified weights its sync lane
holds (HeldWeights); installing never waits for a version being written."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import torch

from dvla.replication import WeightEncoder, flatten
from dvla.roles.rollout import PolicyPool


def make_pool() -> PolicyPool:
    return PolicyPool(torch.nn.Linear(3, 2))


def hold(pool: PolicyPool, version: int, flat: np.ndarray) -> None:
    """What the sync lane does: apply a verified version to the pool's held weights."""
    enc = WeightEncoder(pool.layout, start_version=version - 1)
    v = enc.encode(np.ascontiguousarray(flat, dtype=np.float32))
    pool.held.apply(v.manifest, v.payload)


def test_hold_then_swap_installs_the_held_weights():
    pool = make_pool()
    flat = np.arange(pool.layout.numel, dtype=np.float32)
    hold(pool, 4, flat)
    assert pool.active_version == -1
    assert pool.maybe_swap() and pool.active_version == 4
    np.testing.assert_array_equal(flatten(pool.active.state_dict(), pool.layout), flat)
    assert not pool.maybe_swap()  # nothing newer


def test_install_never_waits_for_the_writer():
    """While the next version is written into staging, the installed one is read from active;
    while the held weights' lock is taken (a version being swapped in), the install is put off."""
    pool = make_pool()
    hold(pool, 1, np.zeros(pool.layout.numel, np.float32))
    pool.held.staging[:] = 7.0  # the sync lane decoding version 2, not swapped in yet
    assert pool.maybe_swap() and pool.active_version == 1
    np.testing.assert_array_equal(flatten(pool.active.state_dict(), pool.layout), np.zeros(pool.layout.numel))
    hold(pool, 2, np.ones(pool.layout.numel, np.float32))
    with pool.held.lock:  # taken: the install is deferred, not waited for
        assert not pool.maybe_swap()
        assert pool.swap_deferred == 1 and pool.active_version == 1
    hold(pool, 3, np.full(pool.layout.numel, 2.0, np.float32))  # replaces 2 before it is installed
    assert pool.maybe_swap() and pool.active_version == 3
    assert pool.overwritten == 1 and pool.swaps == 2
    np.testing.assert_array_equal(flatten(pool.active.state_dict(), pool.layout), np.full(pool.layout.numel, 2.0))


def test_sample_is_act_without_the_value():
    from dvla.learn.policies import MLPPolicy, sample_actions

    policy = MLPPolicy(6, 2, hidden=(16, 16))
    obs = torch.randn(5, 6)
    torch.manual_seed(3)
    a_act, lp_act, _ = policy.act(obs)
    torch.manual_seed(3)
    a_s, lp_s, extras = sample_actions(policy, obs)
    assert torch.equal(a_act, a_s) and torch.equal(lp_act, lp_s) and extras == {}
    assert torch.equal(sample_actions(policy, obs, deterministic=True)[0], policy.act(obs, deterministic=True)[0])

    class ActOnly(torch.nn.Module):  # a plug-in policy without `sample`
        def act(self, obs, deterministic=False):
            return obs[:, :2] * 2, obs[:, 0], obs[:, 1]

    a, lp, extras = sample_actions(ActOnly(), obs)
    assert torch.equal(a, obs[:, :2] * 2) and torch.equal(lp, obs[:, 0]) and extras == {}


def one_storage(module: torch.nn.Module) -> bool:
    """Whether every floating parameter and buffer of `module` lives in one storage."""
    tensors = [t for t in [*module.parameters(), *module.buffers()] if t.is_floating_point()]
    return len({t.untyped_storage().data_ptr() for t in tensors}) == 1


def test_the_installed_weights_are_one_flat_tensor_and_the_module_still_works():
    """The module's weights live in one flat tensor: an installed version reaches every parameter
    and buffer in one copy, the module computes with it, and its state_dict reads it back."""
    from dvla.learn.policies import MLPPolicy

    pool = PolicyPool(MLPPolicy(5, 2, hidden=(8, 8), obs_norm=True))
    assert one_storage(pool.active)
    flat = np.random.default_rng(0).standard_normal(pool.layout.numel).astype(np.float32)
    hold(pool, 1, flat)
    np.testing.assert_array_equal(flatten(pool.active, pool.layout)[:3] != flat[:3], [True] * 3)  # not yet
    assert pool.maybe_swap()
    np.testing.assert_array_equal(flatten(pool.active.state_dict(), pool.layout), flat)
    reference = MLPPolicy(5, 2, hidden=(8, 8), obs_norm=True)
    from dvla.replication import unflatten_into

    unflatten_into(flat, reference, pool.layout)
    obs = torch.randn(3, 5)
    with torch.no_grad():
        np.testing.assert_array_equal(pool.active.actor(obs).numpy(), reference.actor(obs).numpy())
    assert isinstance(pool.active.actor[0].weight, torch.nn.Parameter)


def test_frozen_parameters_are_neither_held_nor_replicated():
    """A frozen base (requires_grad False) stays out of the layout and the held weights: the
    pool holds the model once plus the trainable tensors."""
    from dvla.replication import ParamLayout

    model = torch.nn.Sequential(torch.nn.Linear(64, 64), torch.nn.Linear(64, 2))
    model[0].requires_grad_(False)
    base = model[0].weight.clone()
    pool = PolicyPool(model)
    assert pool.layout.names == ("1.weight", "1.bias") and pool.held.active.size == 64 * 2 + 2
    assert ParamLayout.from_state_dict(model).hash == pool.layout.hash
    hold(pool, 2, np.ones(pool.layout.numel, np.float32))
    assert pool.maybe_swap()
    assert torch.equal(model[1].weight, torch.ones(2, 64)) and torch.equal(model[0].weight, base)


def test_a_bf16_policy_installs_through_one_flat_bf16_tensor():
    pool = PolicyPool(torch.nn.Linear(4, 3).to(torch.bfloat16))
    assert one_storage(pool.active) and {p.dtype for p in pool.active.parameters()} == {torch.bfloat16}
    flat = (np.arange(pool.layout.numel, dtype=np.float32) / 4).astype(np.float32)  # exact in bf16
    hold(pool, 1, flat)
    assert pool.maybe_swap()
    np.testing.assert_array_equal(flatten(pool.active, pool.layout), flat)


def test_bind_flat_refuses_mixed_dtypes_and_leaves_the_module_alone():
    from dvla.replication import ParamLayout, bind_flat

    m = torch.nn.Sequential(torch.nn.Linear(3, 2), torch.nn.Linear(2, 2).to(torch.bfloat16))
    before = [p.data_ptr() for p in m.parameters()]
    assert bind_flat(m, ParamLayout.from_state_dict(m)) is None
    assert [p.data_ptr() for p in m.parameters()] == before
    pool = PolicyPool(torch.nn.Sequential(torch.nn.Linear(3, 2), torch.nn.Linear(2, 2).to(torch.bfloat16)))
    flat = np.arange(pool.layout.numel, dtype=np.float32)
    hold(pool, 3, flat)  # the per-tensor path
    assert pool.maybe_swap()
    np.testing.assert_array_equal(flatten(pool.active.state_dict(), pool.layout), flat)


def test_mlp_sample_matches_the_learners_normal_log_prob_and_distribution():
    """The written-out Gaussian of `MLPPolicy.sample` gives the log-probs `evaluate` (a torch
    Normal) gives the learner, and its actions have the policy's mean and std."""
    from dvla.learn.policies import MLPPolicy

    torch.manual_seed(0)
    policy = MLPPolicy(6, 3, hidden=(16, 16), init_log_std=-0.7, obs_norm=True)
    policy.observe(torch.randn(50, 6) * 3 + 1)
    obs = torch.randn(7, 6)
    for deterministic in (False, True):
        action, logprob = policy.sample(obs, deterministic)
        expected, _entropy, _value = policy.evaluate(obs, action)
        torch.testing.assert_close(logprob, expected, rtol=1e-5, atol=1e-5)
    mean = policy.sample(obs, True)[0]
    many = torch.stack([policy.sample(obs)[0] for _ in range(4000)])
    torch.testing.assert_close(many.mean(0), mean, atol=0.03, rtol=0)
    torch.testing.assert_close(many.std(0), torch.full_like(mean, math.exp(-0.7)), atol=0.03, rtol=0)


class _Recorder(gym.Env):
    """A factory env that records every action it is stepped with."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (1,), np.float32)
    action_space = gym.spaces.Box(-100.0, 100.0, (2,), np.float32)
    played: list[np.ndarray] = []

    def reset(self, *, seed=None, options=None):
        return np.zeros(1, np.float32), {}

    def step(self, action):
        _Recorder.played.append(np.array(action, np.float32))
        return np.zeros(1, np.float32), 0.0, False, False, {"success": False}



def make_recorder(task, seed):
    return _Recorder()


def test_a_weight_swap_never_lands_inside_an_executed_action_chunk():
    """The infer lane installs weights only before a decision, and the env plays a decision's K
    actions open loop in one step: a version that arrives while a chunk plays (every decision
    here) acts from the next decision on, and every simulator step of a chunk carries the
    version that chose it (RLinf #514 is the bug this rules out)."""
    from dvla.config import TaskConfig
    from dvla.learn.envs import EnvGroup

    k = 4
    task = TaskConfig(env=f"{__name__}:make_recorder", action_chunk=k, max_episode_steps=10_000)
    pool = PolicyPool(torch.nn.Linear(1, 2 * k))  # action = bias: the version's number in every element
    n = pool.layout.numel

    def version_weights(v: int) -> np.ndarray:
        flat = np.zeros(n, np.float32)
        flat[n - 2 * k:] = v  # weight [2k, 1] then bias [2k] in state-dict order
        return flat

    _Recorder.played.clear()
    chose = []
    with EnvGroup(task, 1, seed=0) as group:
        obs = group.reset()
        hold(pool, 1, version_weights(1))
        for decision in range(6):
            pool.maybe_swap()  # what the infer lane does before each decision (Rollout._act)
            chose.append(pool.active_version)
            with torch.no_grad():
                action = pool.active(torch.as_tensor(obs)).numpy()
            hold(pool, decision + 2, version_weights(decision + 2))  # arrives while the chunk plays
            obs = group.step(action).next_obs
    played = np.stack(_Recorder.played)
    assert played.shape == (6 * k, 2) and chose == [1, 2, 3, 4, 5, 6]
    for decision, version in enumerate(chose):
        np.testing.assert_array_equal(played[decision * k:(decision + 1) * k], float(version))
