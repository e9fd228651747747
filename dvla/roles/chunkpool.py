"""The rollout's chunk pool: preallocated trajectory chunks, filled in place, shipped, reused.

Each env group fills one chunk at a time, writing every step straight into the arrays of a
:class:`~dvla.fabric.TrajectoryChunk` taken from the group's pool. A finished chunk goes to the
ship lane as a :class:`Shipment`; the ship lane encodes and publishes it and gives it back, so
the arrays are allocated once per pool, not once per chunk.

A group whose envs share one simulator scene on a GPU (dvla/learn/vector_env.py) records its
steps into a :class:`DeviceChunk` instead, tensors shaped like the chunk on the sim device, and
copies them into the chunk taken from the pool once per chunk.

A group never waits for a chunk when the pool holds ``ship_queue + 2`` of them: one being
filled, at most ``ship_queue`` queued for the ship lane and one being published.
"""

from __future__ import annotations

import copy
from typing import Any, NamedTuple

import numpy as np
import torch

from ..fabric import TrajectoryChunk
from .freelist import FreeList


def chunk_template(rollout: str, T: int, n: int, obs_spec: dict[str, Any], act_dim: int,
                   extras_spec: dict[str, Any] | None = None) -> TrajectoryChunk:
    """A zero-filled chunk of T steps of n envs: the shape every chunk of a group's pool has
    (``extras_spec``: the policy's per-step extras, name -> ArraySpec)."""

    def obs(*lead: int) -> dict[str, np.ndarray]:
        # observations keep their dtype (uint8 images) all the way to the wire
        return {k: np.zeros((*lead, *s.shape), s.dtype) for k, s in obs_spec.items()}

    return TrajectoryChunk(
        rollout=rollout, seq=0, policy_version=0, env_steps=T * n,
        obs=obs(T, n), actions=np.zeros((T, n, act_dim), np.float32),
        logprobs=np.zeros((T, n), np.float32), rewards=np.zeros((T, n), np.float32),
        terminated=np.zeros((T, n), bool), truncated=np.zeros((T, n), bool), success=np.zeros((T, n), bool),
        next_obs=obs(n), final_obs=obs(T, n), created_ns=0,
        extras={k: np.zeros((T, n, *s.shape), s.dtype) for k, s in (extras_spec or {}).items()},
    )


class ChunkPool(FreeList[TrajectoryChunk]):
    """``size`` chunks shaped like ``template``, each with arrays of its own: :meth:`take` one,
    fill its arrays, :meth:`give` it back once it has been published (or never will be)."""

    def __init__(self, template: TrajectoryChunk, size: int) -> None:
        if size < 1:
            raise ValueError(f"a chunk pool needs at least one chunk, got size={size}")
        super().__init__(copy.deepcopy(template) for _ in range(size))  # no array shared


class Shipment(NamedTuple):
    """A finished chunk on its way to the ship lane, and the pool it goes back to."""

    chunk: TrajectoryChunk
    pool: ChunkPool


#: a chunk's per-step fields (array or name -> array), recorded on the device by a one-scene group
_STEP_FIELDS = ("obs", "actions", "logprobs", "rewards", "terminated", "truncated", "success",
                "next_obs", "final_obs", "extras")


class DeviceChunk:
    """Zero tensors on ``device`` shaped like ``template``'s arrays (same attribute names, dicts
    for obs / next_obs / final_obs / extras), written step by step with tensors that are already
    there; :meth:`copy_to` copies them into a host chunk's arrays, one copy per array."""

    def __init__(self, template: TrajectoryChunk, device: torch.device | str) -> None:
        def like(a: np.ndarray) -> torch.Tensor:
            return torch.zeros(a.shape, dtype=torch.from_numpy(a[:0].reshape(-1)).dtype, device=device)

        for name in _STEP_FIELDS:
            value = getattr(template, name)
            setattr(self, name, {k: like(v) for k, v in value.items()} if isinstance(value, dict) else like(value))

    def copy_to(self, chunk: TrajectoryChunk) -> None:
        """Copy every recorded tensor into ``chunk``'s arrays (in place)."""
        for name in _STEP_FIELDS:
            dev, host = getattr(self, name), getattr(chunk, name)
            pairs = [(dev[k], host[k]) for k in dev] if isinstance(dev, dict) else [(dev, host)]
            for d, h in pairs:
                torch.from_numpy(h).copy_(d)
