"""The rollout's dual-pool weights: one policy module plus a staging copy of its replicated
tensors; installing never waits for a staging write."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import torch

from dvla.replication import flatten
from dvla.roles.rollout import PolicyPool


def make_pool() -> PolicyPool:
    return PolicyPool(torch.nn.Linear(3, 2))


def test_stage_then_swap_installs_the_staged_weights():
    pool = make_pool()
    flat = np.arange(pool.layout.numel, dtype=np.float32)
    pool.stage(4, flat)
    assert pool.active_version == -1
    assert pool.maybe_swap() and pool.active_version == 4
    np.testing.assert_array_equal(flatten(pool.active.state_dict(), pool.layout), flat)
    assert not pool.maybe_swap()  # nothing pending


def test_swap_does_not_wait_for_a_staging_write(monkeypatch):
    pool = make_pool()
    pool.stage(1, np.zeros(pool.layout.numel, np.float32))  # pending, not swapped yet
    writing, release = threading.Event(), threading.Event()
    real = PolicyPool._write_staging

    def slow_write(*args, **kwargs):
        writing.set()
        release.wait(5)
        return real(*args, **kwargs)

    monkeypatch.setattr(PolicyPool, "_write_staging", slow_write)
    stager = threading.Thread(target=pool.stage, args=(2, np.ones(pool.layout.numel, np.float32)))
    stager.start()
    try:
        assert writing.wait(5)
        t0 = time.monotonic()
        assert not pool.maybe_swap()  # version 1 is pending, but staging holds the lock
        assert time.monotonic() - t0 < 0.5
        assert pool.swap_deferred == 1 and pool.active_version == -1
    finally:
        release.set()
        stager.join(5)
    assert pool.maybe_swap() and pool.active_version == 2  # the newer version won
    assert pool.overwritten == 1
    np.testing.assert_array_equal(flatten(pool.active.state_dict(), pool.layout), np.ones(pool.layout.numel))


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


def test_staging_is_one_flat_copy_and_the_module_still_works():
    """The module's weights live in one flat tensor: an installed version reaches every parameter
    and buffer in one copy, the module computes with it, and its state_dict reads it back."""
    from dvla.learn.policies import MLPPolicy

    pool = PolicyPool(MLPPolicy(5, 2, hidden=(8, 8), obs_norm=True))
    assert pool._bound is not None
    lo, hi = pool._bound.data_ptr(), pool._bound.data_ptr() + 4 * pool._bound.numel()
    tensors = list(pool.active.parameters()) + list(pool.active.buffers())
    assert all(lo <= t.data_ptr() < hi for t in tensors if t.is_floating_point())  # all inside it
    flat = np.random.default_rng(0).standard_normal(pool.layout.numel).astype(np.float32)
    pool.stage(1, flat)
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


def test_frozen_parameters_are_neither_staged_nor_replicated():
    """A frozen base (requires_grad False) stays out of the layout and the staging copy: the
    pool holds the model once plus the trainable tensors."""
    from dvla.replication import ParamLayout

    model = torch.nn.Sequential(torch.nn.Linear(64, 64), torch.nn.Linear(64, 2))
    model[0].requires_grad_(False)
    base = model[0].weight.clone()
    pool = PolicyPool(model)
    assert pool.layout.names == ("1.weight", "1.bias") and pool.staging.numel() == 64 * 2 + 2
    assert ParamLayout.from_state_dict(model).hash == pool.layout.hash
    pool.stage(2, np.ones(pool.layout.numel, np.float32))
    assert pool.maybe_swap()
    assert torch.equal(model[1].weight, torch.ones(2, 64)) and torch.equal(model[0].weight, base)


def test_a_bf16_policy_installs_through_one_flat_bf16_tensor():
    pool = PolicyPool(torch.nn.Linear(4, 3).to(torch.bfloat16))
    assert pool._bound is not None and pool._bound.dtype == torch.bfloat16
    flat = (np.arange(pool.layout.numel, dtype=np.float32) / 4).astype(np.float32)  # exact in bf16
    pool.stage(1, flat)
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
    pool.stage(3, flat)  # the per-tensor path
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
