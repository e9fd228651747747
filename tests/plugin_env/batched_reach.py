"""A batched env with ManiSkillVectorEnv's calls, for tests of the one-scene path on machines
without a GPU (``task.env: batched_reach:make`` with ``env_batching: scene``).

``n`` point masses in one torch "scene" reach a goal on the plane: observation [position, goal],
action a 2-D velocity, reward ``1 - tanh(3 d)``, success (and, unless ignored, termination)
within 0.15 of the goal, truncation at ``task.max_episode_steps``. Initial states come from
torch's RNG, seeded (forked) by a seeded reset as ManiSkill does, so a partial reset made under
a seeded torch RNG is reproducible. ``make(task, seed)`` (no ``num_envs``) is the one-env scene
the actor probes for sizes.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch


class BatchedReach:
    def __init__(self, n: int, max_steps: int, device: str = "cpu") -> None:
        self.num_envs, self.max_steps, self.device = n, max_steps, torch.device(device)
        self.single_action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.single_observation_space = gym.spaces.Box(-np.inf, np.inf, (4,), np.float32)
        self.action_space, self.observation_space = self.single_action_space, self.single_observation_space
        self.pos = torch.zeros(n, 2, device=self.device)
        self.goal = torch.zeros(n, 2, device=self.device)
        self.t = torch.zeros(n, dtype=torch.int64, device=self.device)
        self.resets = 0  # reset calls (tests count partial resets)

    @property
    def unwrapped(self) -> "BatchedReach":
        return self

    def _obs(self) -> torch.Tensor:
        return torch.cat([self.pos, self.goal], dim=1)

    def reset(self, *, seed: Any = None, options: dict | None = None) -> tuple[torch.Tensor, dict]:
        idx = (options or {}).get("env_idx", torch.arange(self.num_envs, device=self.device))
        self.resets += 1
        if seed is not None:
            with torch.random.fork_rng():
                torch.manual_seed(int(seed[0] if isinstance(seed, (list, tuple)) else seed))
                draw = torch.rand(len(idx), 4)
        else:
            draw = torch.rand(len(idx), 4)  # the caller's torch RNG, as ManiSkill's unseeded resets
        draw = draw.to(self.device) * 1.6 - 0.8
        self.pos[idx], self.goal[idx], self.t[idx] = draw[:, :2], draw[:, 2:], 0
        return self._obs(), {}

    def step(self, action: Any) -> tuple:
        a = torch.as_tensor(action, dtype=torch.float32, device=self.device).reshape(self.num_envs, 2)
        self.pos = torch.clamp(self.pos + 0.2 * torch.clamp(a, -1, 1), -1, 1)
        self.t += 1
        d = torch.linalg.norm(self.pos - self.goal, dim=1)
        success = d < 0.15
        return self._obs(), 1 - torch.tanh(3 * d), success.clone(), self.t >= self.max_steps, {"success": success}

    def close(self) -> None:
        pass


def make(task: Any, seed: int, num_envs: int = 1) -> BatchedReach:
    return BatchedReach(num_envs, task.max_episode_steps)
