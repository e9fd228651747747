"""Reach-to-colour: a one-decision rendered task small enough to learn in a unit test
(``task.env: reach_colour:make``, ``obs_mode: rgb``; tests/unit/test_vla_learning.py).

Each episode draws one of three colours. The image (``IMAGE`` px square, dark grey) shows a patch
of that colour at a random place, and the instruction names it ("reach red"). The action is one
number in [-1, 1]: its third of the range (red, green, blue from the left) is the bin reached.
Reaching the named colour's bin succeeds with reward 1, anything else gets 0; either way the
episode ends after that one step. A policy that ignores its observation succeeds a third of the
time; one that reads the image or the words, every time.

``reach_colour:make_sequence`` plays ``task.max_episode_steps`` such decisions in one episode: every
step shows a new colour (and words) and pays 1 for its bin, and the episode succeeds when every
step did. Each reward belongs to the observation and action of its own step, so a pipeline that
pairs a step's action or reward with a neighbouring step's observation cannot learn it.
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
    def __init__(self, decisions: int = 1) -> None:
        self.observation_space = gym.spaces.Dict({
            "rgb": gym.spaces.Box(0, 255, (IMAGE, IMAGE, 3), np.uint8),
            "proprio": gym.spaces.Box(-np.inf, np.inf, (PROPRIO,), np.float32),
        })
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.target = 0
        #: decisions per episode, made so far, and whether each so far was right
        self.decisions, self.made, self.all_right = int(decisions), 0, True
        #: the episode's instruction (the env group tokenises it at every reset)
        self.instruction = "reach red"
        self._rgb = np.zeros((IMAGE, IMAGE, 3), np.uint8)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict[str, np.ndarray], dict]:
        super().reset(seed=seed)
        self.made, self.all_right = 0, True
        self._draw()
        return self._obs(), {}

    def _draw(self) -> None:
        """A new target colour, its patch at a random place and its instruction."""
        rng = self.np_random
        self.target = int(rng.integers(len(COLOURS)))
        name = list(COLOURS)[self.target]
        self.instruction = f"reach {name}"
        self._rgb = np.full((IMAGE, IMAGE, 3), 40, np.uint8)
        y, x = (int(v) for v in rng.integers(0, IMAGE - PATCH + 1, 2))
        self._rgb[y:y + PATCH, x:x + PATCH] = COLOURS[name]

    def _obs(self) -> dict[str, np.ndarray]:
        return {"rgb": self._rgb.copy(), "proprio": np.zeros(PROPRIO, np.float32)}

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict]:
        right = colour_bin(np.asarray(action, np.float32).reshape(-1)[0]) == self.target
        self.made += 1
        self.all_right &= right
        done = self.made >= self.decisions
        if not done:
            self._draw()
        return self._obs(), float(right), done, False, {"success": done and self.all_right}


def make(task: Any, seed: int) -> gym.Env:
    """Factory for ``task.env`` (``factory(task, seed)``); episodes are seeded at reset. The time
    limit ends an episode whose termination is ignored (evaluations played to the time limit)."""
    return gym.wrappers.TimeLimit(ReachColour(), max_episode_steps=task.max_episode_steps)


def make_sequence(task: Any, seed: int) -> gym.Env:
    """Factory of the ``task.max_episode_steps``-decision episodes."""
    return gym.wrappers.TimeLimit(ReachColour(task.max_episode_steps), max_episode_steps=task.max_episode_steps)
