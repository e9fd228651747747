"""The rollout's trajectory slot pool: preallocated wire buffers, filled in place, shipped, reused.

Each env group fills one chunk at a time, writing every step straight into a
:class:`~dvla.fabric.WireBuffer` (its arrays are views of the bytes that go on the wire). A
finished buffer goes to the ship lane, which publishes it (Zenoh copies the bytes) and gives it
back. Nothing is allocated per chunk in steady state, and shipping a chunk needs no encoding.

A group never waits for a buffer when the pool holds ``ship_queue + 2`` of them: one being
filled, at most ``ship_queue`` queued for the ship lane and one being published.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..fabric import TrajectoryChunk, WireBuffer
from .freelist import FreeList

#: TrajectoryChunk fields that change from chunk to chunk (64-bit slots in the wire bytes)
WIDE_FIELDS = ("seq", "policy_version", "created_ns")


def chunk_template(rollout: str, T: int, n: int, obs_spec: dict[str, Any], act_dim: int) -> TrajectoryChunk:
    """A zero-filled chunk of T steps of n envs: the shape every buffer of a group's pool has."""

    def obs(*lead: int) -> dict[str, np.ndarray]:
        # observations keep their dtype (uint8 images) all the way to the wire
        return {k: np.zeros((*lead, *s.shape), s.dtype) for k, s in obs_spec.items()}

    return TrajectoryChunk(
        rollout=rollout, seq=0, policy_version=0, env_steps=T * n,
        obs=obs(T, n), actions=np.zeros((T, n, act_dim), np.float32),
        logprobs=np.zeros((T, n), np.float32), rewards=np.zeros((T, n), np.float32),
        terminated=np.zeros((T, n), bool), truncated=np.zeros((T, n), bool), success=np.zeros((T, n), bool),
        next_obs=obs(n), final_obs=obs(T, n), created_ns=0,
    )


class ChunkPool(FreeList[WireBuffer]):
    """``size`` wire buffers shaped like ``template``: :meth:`take` one, :meth:`give` it back
    once its bytes have been published (or never will be)."""

    def __init__(self, template: TrajectoryChunk, size: int) -> None:
        if size < 1:
            raise ValueError(f"a chunk pool needs at least one buffer, got size={size}")
        super().__init__(WireBuffer(template, wide=WIDE_FIELDS) for _ in range(size))
