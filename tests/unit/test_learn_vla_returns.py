"""The critic's targets of a cloned warm start (benchmarks/learn_vla.py: returns): discounted
rewards to each demonstration's end, then the last reward held, per episode, never across two."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.learn_vla import returns


def test_returns_discount_within_each_episode_and_hold_the_last_reward() -> None:
    demos = {"reward": np.array([1.0, 0.0, 2.0, 3.0, 1.0], np.float32), "episode": np.array([0, 0, 0, 1, 1])}
    g = 0.5
    got = returns(demos, g, reward_scale=2.0)
    tail0 = 4.0 / (1 - g)  # last reward of episode 0 (2.0 scaled) held forever
    want0 = [2.0 + g * (0.0 + g * tail0), 0.0 + g * tail0, tail0]
    tail1 = 2.0 / (1 - g)
    want1 = [6.0 + g * tail1, tail1]
    assert got.dtype == np.float32
    assert got == pytest.approx(np.array(want0 + want1, np.float32))


def test_undiscounted_returns_sum_the_rewards() -> None:
    demos = {"reward": np.array([1.0, 2.0, 3.0], np.float32), "episode": np.zeros(3, np.int32)}
    assert returns(demos, 1.0) == pytest.approx([6.0, 5.0, 3.0])
