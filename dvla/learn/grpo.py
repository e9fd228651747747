"""GRPO (group-relative policy optimisation) as dvla runs it: whole groups per rollout chunk.

Layout, chosen so no episode ever has to be reassembled from pieces:

* every env group of a rollout holds whole GRPO groups: envs ``G*m .. G*m + G-1`` reset with one
  shared seed (:class:`~dvla.learn.envs.EnvGroup` ``group_size``), so the G episodes of a group
  start from the same initial state;
* episodes play to the time limit (terminations ignored), so all envs of a group end together;
* one trajectory chunk is exactly one episode (``chunk_steps`` = transitions per episode).

A chunk's env column therefore is one whole episode and columns ``G*m .. G*m + G-1`` one group;
this holds in the actor's stacked batch too, since every chunk's env count is a multiple of G.
The advantage of every step of an episode is its group-normalised return
(:func:`~dvla.learn.ppo.grpo_advantages`); no critic is used. With ``task.reward: success`` the
return is 1 for a successful episode and 0 otherwise.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from ..config import TaskConfig, env_group_sizes, grpo_layout_problems
from .ppo import grpo_advantages

__all__ = [
    "grpo_envs", "grpo_layout_problems", "episode_steps", "group_advantages", "group_stats", "env_group_sizes",
]


def episode_steps(task: TaskConfig) -> int:
    """Transitions in one full episode (each plays up to ``action_chunk`` simulator steps)."""
    return math.ceil(task.max_episode_steps / task.action_chunk)


def grpo_envs(task: TaskConfig) -> dict[str, Any]:
    """Extra :class:`~dvla.learn.envs.EnvGroup` keywords of a training rollout for ``task``."""
    if task.algorithm != "grpo":
        return {}
    return {"group_size": task.group_size, "ignore_terminations": True}


def group_advantages(rewards: torch.Tensor, terminated: torch.Tensor, truncated: torch.Tensor, group_size: int) -> torch.Tensor:
    """Advantages ``[T, N]`` of a batch where each column is one whole episode.

    Raises ValueError when a column is not exactly one episode (ends only at its last step) or
    N is not a multiple of ``group_size``: the rollout broke the layout above.
    """
    steps, n = rewards.shape
    if n % group_size:
        raise ValueError(f"GRPO batch has {n} episodes, not a multiple of group_size {group_size}")
    ended = (terminated | truncated).cpu().numpy()
    if not ended[-1].all() or ended[:-1].any():
        raise ValueError("GRPO batch columns are not whole episodes (chunk_steps must cover exactly one episode)")
    returns = rewards.sum(0)
    adv = grpo_advantages(returns, torch.arange(n, device=rewards.device) // group_size)
    return adv.to(rewards.dtype).unsqueeze(0).expand(steps, n).contiguous()


def group_stats(rewards: np.ndarray, group_size: int) -> dict[str, float]:
    """Share of groups whose episodes disagree (the only ones that teach anything) and mean return."""
    returns = np.asarray(rewards).sum(0).reshape(-1, group_size)
    return {
        "groups_informative": float((returns.max(1) > returns.min(1)).mean()),
        "episode_return_mean": float(returns.mean()),
    }
