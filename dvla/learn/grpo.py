"""GRPO (group-relative policy optimisation) as dvla runs it: whole groups per rollout chunk.

Layout, chosen so no episode ever has to be reassembled from pieces:

* every env group of a rollout holds whole GRPO groups: envs ``G*m .. G*m + G-1`` reset with one
  shared seed (:class:`~dvla.learn.envs.EnvGroup` ``group_size``), so the G episodes of a group
  start from the same initial state;
* episodes play to the time limit (terminations ignored), so all envs of a group end together;
* one trajectory chunk is exactly one episode (``chunk_steps`` = transitions per episode).

A chunk's env column therefore is one whole episode and columns ``G*m .. G*m + G-1`` one group,
in the actor's stacked batch too. No critic; the two baselines (``task.grpo_baseline``) and the
std floor are described in docs/policies.md (GRPO).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from ..config import TaskConfig
from .ppo import Trajectories

__all__ = ["grpo_envs", "grpo_batch", "group_advantages", "grpo_advantages"]


def grpo_envs(task: TaskConfig) -> dict[str, Any]:
    """Extra :class:`~dvla.learn.envs.EnvGroup` keywords of a training rollout for ``task``."""
    if task.algorithm != "grpo":
        return {}
    return {"group_size": task.group_size, "ignore_terminations": True}


def grpo_batch(b: Trajectories, task: TaskConfig) -> dict[str, Any]:
    """The training batch of ``b`` with the GRPO advantages of ``task``; the value head is
    trained towards 0 (no critic), which keeps PPO's batch format."""
    adv = group_advantages(
        b.rewards * task.ppo.reward_scale, b.terminated, b.truncated, task.group_size,
        baseline=task.grpo_baseline, gamma=task.grpo_gamma, std_floor=task.grpo_std_floor,
    )
    zeros = torch.zeros(b.steps, device=adv.device)
    return b.training_batch(adv, zeros, zeros)


def group_advantages(
    rewards: torch.Tensor,
    terminated: torch.Tensor,
    truncated: torch.Tensor,
    group_size: int,
    *,
    baseline: str = "episode",
    gamma: float = 1.0,
    std_floor: float = 0.0,
) -> torch.Tensor:
    """Advantages ``[T, N]`` of a batch where each column is one whole episode.

    Columns ``G*m .. G*m + G-1`` are one group; ``baseline`` "episode" normalises the column's
    return within its group, "step" the reward-to-go from each step (docs/policies.md). Raises
    ValueError when a column is not exactly one episode or N is not a multiple of ``group_size``.
    """
    steps, n = rewards.shape
    if n % group_size:
        raise ValueError(f"GRPO batch has {n} episodes, not a multiple of group_size {group_size}")
    ended = (terminated | truncated).cpu().numpy()
    if not ended[-1].all() or ended[:-1].any():
        raise ValueError("GRPO batch columns are not whole episodes (chunk_steps must cover exactly one episode)")
    if baseline == "episode":
        returns = rewards.sum(0)
        adv = grpo_advantages(returns, torch.arange(n, device=rewards.device) // group_size, std_floor)
        return adv.to(rewards.dtype).unsqueeze(0).expand(steps, n).contiguous()
    if baseline != "step":
        raise ValueError(f"unknown GRPO baseline {baseline!r} (expected 'episode' or 'step')")
    r = rewards.detach().to(torch.float64)
    to_go = torch.empty_like(r)
    running = torch.zeros_like(r[0])
    for t in range(steps - 1, -1, -1):
        running = r[t] + gamma * running
        to_go[t] = running
    groups = to_go.reshape(steps, n // group_size, group_size)
    mean = groups.mean(2, keepdim=True)
    std = groups.std(2, unbiased=False, keepdim=True).clamp(min=std_floor)
    adv = (groups - mean) / (std + 1e-8)
    return adv.reshape(steps, n).to(rewards.dtype)


def grpo_advantages(episode_returns, group_ids, std_floor: float = 0.0):
    """Group-relative advantages: ``(R - mean_g) / (max(std_g, std_floor) + 1e-8)`` within each group.

    ``episode_returns`` and ``group_ids`` are 1-D (numpy or torch); episodes sharing a group id
    started from the same initial state. A group of one gets advantage 0; the std is the
    population std.
    """
    is_torch = isinstance(episode_returns, torch.Tensor)
    r = episode_returns.detach().cpu().numpy() if is_torch else np.asarray(episode_returns)
    r = r.astype(np.float64).reshape(-1)
    ids = group_ids.detach().cpu().numpy() if isinstance(group_ids, torch.Tensor) else np.asarray(group_ids)
    if ids.reshape(-1).shape != r.shape:
        raise ValueError(f"{r.shape[0]} returns but {ids.size} group ids")
    _, inverse = np.unique(ids.reshape(-1), return_inverse=True)
    counts = np.bincount(inverse)
    mean = np.bincount(inverse, weights=r) / counts
    var = np.bincount(inverse, weights=(r - mean[inverse]) ** 2) / counts
    adv = (r - mean[inverse]) / (np.maximum(np.sqrt(var[inverse]), std_floor) + 1e-8)
    if is_torch:
        return torch.as_tensor(adv, dtype=episode_returns.dtype, device=episode_returns.device)
    return adv.astype(np.float32)
