"""Reach-to-colour: a one-decision rendered task small enough to learn in a unit test
(``task.env: reach_colour:make``, ``obs_mode: rgb``; tests/unit/test_vla_learning.py).

Each episode draws one of three colours. The image (``IMAGE`` px square, dark grey) shows a patch
of that colour at a random place, and the instruction names it ("reach red"). The action is one
number in [-1, 1]: its third of the range (red, green, blue from the left) is the bin reached.
Reaching the named colour's bin succeeds with reward 1, anything else gets 0; either way the
episode ends after that one step. A policy that ignores its observation succeeds a third of the
time; one that reads the image or the words, every time.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

#: colour name -> RGB of its patch; the order is the order of the bins on the action axis
COLOURS = {"red": (220, 40, 40), "green": (40, 200, 60), "blue": (50, 70, 230)}
#: image side, px
IMAGE = 32
#: patch side, px
PATCH = 12
#: proprioception values (constant: the task has no arm)
PROPRIO = 2


def colour_bin(action: float) -> int:
    """The bin (0, 1, 2: the index in COLOURS) a one-number action reaches."""
    return int(np.clip(np.floor((float(action) + 1.0) * 1.5), 0, 2))


class ReachColour(gym.Env):
    def __init__(self) -> None:
        self.observation_space = gym.spaces.Dict({
            "rgb": gym.spaces.Box(0, 255, (IMAGE, IMAGE, 3), np.uint8),
            "proprio": gym.spaces.Box(-np.inf, np.inf, (PROPRIO,), np.float32),
        })
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.target = 0
        #: the episode's instruction (the env group tokenises it at every reset)
        self.instruction = "reach red"
        self._rgb = np.zeros((IMAGE, IMAGE, 3), np.uint8)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict[str, np.ndarray], dict]:
        super().reset(seed=seed)
        rng = self.np_random
        self.target = int(rng.integers(len(COLOURS)))
        name = list(COLOURS)[self.target]
        self.instruction = f"reach {name}"
        self._rgb = np.full((IMAGE, IMAGE, 3), 40, np.uint8)
        y, x = (int(v) for v in rng.integers(0, IMAGE - PATCH + 1, 2))
        self._rgb[y:y + PATCH, x:x + PATCH] = COLOURS[name]
        return self._obs(), {}

    def _obs(self) -> dict[str, np.ndarray]:
        return {"rgb": self._rgb.copy(), "proprio": np.zeros(PROPRIO, np.float32)}

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict]:
        success = colour_bin(np.asarray(action, np.float32).reshape(-1)[0]) == self.target
        return self._obs(), float(success), True, False, {"success": success}


def make(task: Any, seed: int) -> gym.Env:
    """Factory for ``task.env`` (``factory(task, seed)``); episodes are seeded at reset. The time
    limit ends an episode whose termination is ignored (evaluations played to the time limit)."""
    return gym.wrappers.TimeLimit(ReachColour(), max_episode_steps=task.max_episode_steps)
