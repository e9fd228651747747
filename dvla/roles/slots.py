"""The actor's trajectory pool: fixed-size slots allocated once (pinned host memory on CUDA).

`ingest` copies a decoded chunk (its arrays are views of the received bytes) into a free slot,
once; `batch` stacks slots into a learner batch and releases them. Observations are one array
per obs key (``{"state"}`` for flat observations; ``rgb``/``proprio``/``tokens`` for structured
ones), each in its wire dtype (images stay uint8). No allocation happens per chunk in steady
state; when every slot is taken, `acquire` waits, the data-plane inbox fills, and backpressure
reaches the rollouts.
"""

from __future__ import annotations

import threading
from typing import Any, Mapping, NamedTuple

import numpy as np
import torch

from ..fabric.messages import TrajectoryChunk
from .freelist import FreeList

_FIELDS_TN = ("logprobs", "rewards", "terminated", "truncated", "success")
_TORCH_DTYPES = {"float32": torch.float32, "uint8": torch.uint8, "int32": torch.int32}
"""Observation dtypes a slot can hold (numpy name -> torch dtype)."""


class _Spec(NamedTuple):
    shape: tuple[int, ...]
    dtype: str


class SlotPool:
    """`n_slots` slots of [T, n_max, ...] arrays; a chunk may use fewer than n_max env columns."""

    def __init__(
        self, *, n_slots: int, T: int, n_max: int, act_dim: int, obs_dim: int | None = None,
        obs_spec: Mapping[str, Any] | None = None, pin: bool = False, extras_spec: Mapping[str, Any] | None = None,
    ) -> None:
        """``obs_spec`` (name -> spec with ``shape`` and numpy ``dtype``) or, for flat
        observations, ``obs_dim`` D (the same as ``{"state": ((D,), float32)}``); ``extras_spec``
        the policy's per-step extras (docs/policies.md), held like observations."""
        self.n_slots, self.T, self.n_max = n_slots, T, n_max
        if obs_spec is None:
            if obs_dim is None:
                raise ValueError("SlotPool needs obs_spec or obs_dim")
            obs_spec = {"state": _Spec((obs_dim,), "float32")}

        def alloc(shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
            t = torch.zeros(shape, dtype=dtype)
            return t.pin_memory() if pin else t

        S = n_slots
        dtypes = {k: _TORCH_DTYPES[np.dtype(v.dtype).name] for k, v in obs_spec.items()}
        self.obs = {k: alloc((S, T, n_max, *v.shape), dtypes[k]) for k, v in obs_spec.items()}
        self.final_obs = {k: alloc((S, T, n_max, *v.shape), dtypes[k]) for k, v in obs_spec.items()}
        self.next_obs = {k: alloc((S, n_max, *v.shape), dtypes[k]) for k, v in obs_spec.items()}
        self.actions = alloc((S, T, n_max, act_dim), torch.float32)
        extras_spec = extras_spec or {}
        self.extras = {k: alloc((S, T, n_max, *v.shape), _TORCH_DTYPES[np.dtype(v.dtype).name]) for k, v in extras_spec.items()}
        self.tn = {
            "logprobs": alloc((S, T, n_max), torch.float32),
            "rewards": alloc((S, T, n_max), torch.float32),
            "terminated": alloc((S, T, n_max), torch.bool),
            "truncated": alloc((S, T, n_max), torch.bool),
            "success": alloc((S, T, n_max), torch.bool),
        }
        self._n = [0] * S
        self._version = [0] * S
        self._rollout = [""] * S
        self._seq = [0] * S
        self._free: FreeList[int] = FreeList(range(S))

    def acquire(self, stop: threading.Event) -> int | None:
        """A free slot, waiting while every one is out; None once `stop` is set."""
        return self._free.take(stop)

    def release(self, slot: int) -> None:
        self._free.give(slot)

    def free_count(self) -> int:
        return self._free.free()

    def fill(self, slot: int, c: TrajectoryChunk) -> str | None:
        """Copy a decoded chunk into `slot` (each array once, from the received bytes into the
        slot's columns); returns a reason string when its shape does not fit."""
        if c.obs.keys() != self.obs.keys():
            return f"observation keys {sorted(c.obs)} != the policy's {sorted(self.obs)}"
        T, n = c.rewards.shape
        if T != self.T or not 1 <= n <= self.n_max:
            return (f"chunk shape T={T}, N={n} does not fit slots of T={self.T}, N<={self.n_max} (a rollout whose envs "
                    f"share one scene on a CUDA node, with an actor on a CPU one? say task.env_batching: scene)")
        if c.actions.shape[2:] != self.actions.shape[3:]:
            return f"actions {c.actions.shape} do not match the policy"
        for k, arr in c.obs.items():
            if arr.shape[2:] != self.obs[k].shape[3:] or _TORCH_DTYPES.get(arr.dtype.name) != self.obs[k].dtype:
                return f"obs[{k!r}] {arr.dtype}{list(arr.shape)} does not match the policy"
        if c.extras.keys() != self.extras.keys():
            return f"extras {sorted(c.extras)} != the policy's {sorted(self.extras)}"
        for k, arr in c.extras.items():
            if arr.shape[2:] != self.extras[k].shape[3:] or _TORCH_DTYPES.get(arr.dtype.name) != self.extras[k].dtype:
                return f"extras[{k!r}] {arr.dtype}{list(arr.shape)} does not match the policy"
        for k in self.obs:
            _copy(self.obs[k][slot, :, :n], c.obs[k])
            _copy(self.final_obs[k][slot, :, :n], c.final_obs[k])
            _copy(self.next_obs[k][slot, :n], c.next_obs[k])
        _copy(self.actions[slot, :, :n], c.actions)
        for k, arr in c.extras.items():
            _copy(self.extras[k][slot, :, :n], arr)
        for name in _FIELDS_TN:
            _copy(self.tn[name][slot, :, :n], getattr(c, name))
        self._n[slot] = n
        self._version[slot] = c.policy_version
        self._rollout[slot] = c.rollout
        self._seq[slot] = c.seq
        return None

    def steps(self, slot: int) -> int:
        return self.T * self._n[slot]

    def version(self, slot: int) -> int:
        return self._version[slot]

    def rollout(self, slot: int) -> str:
        return self._rollout[slot]

    def order(self, slot: int) -> tuple[str, int]:
        """(rollout, seq) of the chunk in `slot`: a batch order that does not depend on arrival."""
        return self._rollout[slot], self._seq[slot]

    def stack(self, slots: list[int], device: torch.device) -> dict[str, Any]:
        """One [T, N_total, ...] batch on `device` from the given slots (env columns side by side);
        ``obs``, ``final_obs`` and ``next_obs`` are dicts of tensors (one per obs key)."""
        out: dict[str, torch.Tensor] = {}

        def cat(src: torch.Tensor, env_axis: int) -> torch.Tensor:
            parts = [src[s].narrow(env_axis, 0, self._n[s]) for s in slots]
            return torch.cat(parts, dim=env_axis).to(device, non_blocking=True)

        out["obs"] = {k: cat(v, 1) for k, v in self.obs.items()}
        out["final_obs"] = {k: cat(v, 1) for k, v in self.final_obs.items()}
        out["actions"] = cat(self.actions, 1)
        out["extras"] = {k: cat(v, 1) for k, v in self.extras.items()}
        out["next_obs"] = {k: cat(v, 0) for k, v in self.next_obs.items()}
        for name, src in self.tn.items():
            out[name] = cat(src, 1)
        out["steps"] = torch.tensor(sum(self.steps(s) for s in slots))
        return out


def _copy(dst: torch.Tensor, src: np.ndarray) -> None:
    # torch.from_numpy wraps the decoded view without copying (the slot only reads it), and
    # torch's strided copy into the slot's columns is faster than numpy's.
    dst.copy_(torch.from_numpy(src))
