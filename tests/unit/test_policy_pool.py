"""The rollout's dual-pool weights: a swap never waits for a staging write."""

from __future__ import annotations

import threading
import time

import numpy as np
import torch

from dvla.replication import flatten
from dvla.roles import rollout
from dvla.roles.rollout import PolicyPool


def make_pool() -> PolicyPool:
    return PolicyPool(lambda: torch.nn.Linear(3, 2))


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
    real = rollout.unflatten_into

    def slow_unflatten(*args, **kwargs):
        writing.set()
        release.wait(5)
        return real(*args, **kwargs)

    monkeypatch.setattr(rollout, "unflatten_into", slow_unflatten)
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
    a_s, lp_s = sample_actions(policy, obs)
    assert torch.equal(a_act, a_s) and torch.equal(lp_act, lp_s)
    assert torch.equal(sample_actions(policy, obs, deterministic=True)[0], policy.act(obs, deterministic=True)[0])

    class ActOnly(torch.nn.Module):  # a plug-in policy without `sample`
        def act(self, obs, deterministic=False):
            return obs[:, :2] * 2, obs[:, 0], obs[:, 1]

    a, lp = sample_actions(ActOnly(), obs)
    assert torch.equal(a, obs[:, :2] * 2) and torch.equal(lp, obs[:, 0])
