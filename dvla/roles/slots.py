"""The actor's trajectory pool: slots allocated once (pinned host memory on CUDA), each with room
for one chunk of the run's :class:`~dvla.fabric.messages.ChunkSpec` (T steps of up to N envs).

`ingest` copies an accepted chunk into a free slot, once; `batch` stacks slots into the learner's
:class:`~dvla.learn.ppo.Trajectories` and releases them. Arrays keep their wire dtype. When every
slot is taken, `acquire` waits and backpressure reaches the rollouts through the inbox.
"""

from __future__ import annotations

import threading
import warnings

import torch

from ..fabric.messages import ChunkSpec, TrajectoryChunk, chunk_arrays, nest
from ..learn.ppo import Trajectories
from .freelist import FreeList

# `fill` wraps each received (read-only) array with torch.from_numpy only to copy from it; torch
# warns on the first such wrap in every actor's log that writing to it would be undefined. Nothing
# writes to it: the warning is silenced for this module's calls alone.
warnings.filterwarnings("ignore", message="The given NumPy array is not writable", category=UserWarning,
                        module=r"dvla\.roles\.slots")


class SlotPool:
    """``n_slots`` slots of ``spec``'s arrays with a leading slot axis; a chunk may fill fewer
    than N env columns of its slot."""

    def __init__(self, spec: ChunkSpec, n_slots: int, pin: bool = False) -> None:
        def alloc(shape: tuple[int, ...], dtype: str) -> torch.Tensor:
            t = torch.zeros((n_slots, *shape), dtype=getattr(torch, dtype))
            return t.pin_memory() if pin else t

        self.n_slots, self.T = n_slots, spec.T
        layout = spec.layout()
        self._arrays = {path: alloc(shape, s.dtype) for path, (shape, s) in layout.items()}
        #: path -> env axis within a slot: the last axis before the per-step shape ([T, N, ...], next_obs [N, ...])
        self._env_axis = {path: len(shape) - len(s.shape) - 1 for path, (shape, s) in layout.items()}
        self._n = [0] * n_slots
        self._version = [0] * n_slots
        self._rollout = [""] * n_slots
        self._seq = [0] * n_slots
        self._free: FreeList[int] = FreeList(range(n_slots))

    def acquire(self, stop: threading.Event) -> int | None:
        """A free slot, waiting while every one is out; None once `stop` is set."""
        return self._free.take(stop)

    def release(self, slot: int) -> None:
        self._free.give(slot)

    def free_count(self) -> int:
        return self._free.free()

    def fill(self, slot: int, c: TrajectoryChunk) -> None:
        """Copy ``c`` (a chunk its ChunkSpec accepted) into `slot`'s first columns, each array once
        (torch.from_numpy wraps the received view; torch's strided copy beats numpy's)."""
        n = c.num_envs
        for path, src in chunk_arrays(c).items():
            self._arrays[path][slot].narrow(self._env_axis[path], 0, n).copy_(torch.from_numpy(src))
        self._n[slot] = n
        self._version[slot] = c.policy_version
        self._rollout[slot] = c.rollout
        self._seq[slot] = c.seq

    def steps(self, slot: int) -> int:
        return self.T * self._n[slot]

    def version(self, slot: int) -> int:
        return self._version[slot]

    def order(self, slot: int) -> tuple[str, int]:
        """(rollout, seq) of the chunk in `slot`: a batch order that does not depend on arrival."""
        return self._rollout[slot], self._seq[slot]

    def stack(self, slots: list[int], device: torch.device) -> Trajectories:
        """The given slots' chunks side by side (env columns concatenated) on `device`."""

        def cat(path: tuple[str, ...]) -> torch.Tensor:
            axis = self._env_axis[path]
            parts = [self._arrays[path][s].narrow(axis, 0, self._n[s]) for s in slots]
            return torch.cat(parts, dim=axis).to(device, non_blocking=True)

        return Trajectories(**nest({path: cat(path) for path in self._arrays}))
