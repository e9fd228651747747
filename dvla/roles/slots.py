"""The actor's trajectory pool: fixed-size slots allocated once (pinned host memory on CUDA).

`ingest` decodes a chunk straight into a free slot; `batch` stacks slots into a learner batch and
releases them. No allocation happens per chunk in steady state; when every slot is taken,
`acquire` waits, the data-plane inbox fills, and backpressure reaches the rollouts.
"""

from __future__ import annotations

import queue
import threading

import numpy as np
import torch

from ..fabric.messages import TrajectoryChunk

_FIELDS_TN = ("logprobs", "rewards", "terminated", "truncated", "success")


class SlotPool:
    """`n_slots` slots of [T, n_max, ...] arrays; a chunk may use fewer than n_max env columns."""

    def __init__(self, *, n_slots: int, T: int, n_max: int, obs_dim: int, act_dim: int, pin: bool = False) -> None:
        self.n_slots, self.T, self.n_max = n_slots, T, n_max

        def alloc(shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
            t = torch.zeros(shape, dtype=dtype)
            return t.pin_memory() if pin else t

        S = n_slots
        self.obs = alloc((S, T, n_max, obs_dim), torch.float32)
        self.final_obs = alloc((S, T, n_max, obs_dim), torch.float32)
        self.next_obs = alloc((S, n_max, obs_dim), torch.float32)
        self.actions = alloc((S, T, n_max, act_dim), torch.float32)
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
        self._free: queue.Queue[int] = queue.Queue()
        for i in range(S):
            self._free.put(i)

    def acquire(self, stop: threading.Event) -> int | None:
        while not stop.is_set():
            try:
                return self._free.get(timeout=0.05)
            except queue.Empty:
                continue
        return None

    def release(self, slot: int) -> None:
        self._free.put(slot)

    def free_count(self) -> int:
        return self._free.qsize()

    def fill(self, slot: int, c: TrajectoryChunk) -> str | None:
        """Copy a chunk into `slot`; returns a reason string when its shape does not fit."""
        state = c.obs.get("state")
        if state is None or "state" not in c.next_obs or "state" not in c.final_obs:
            return "no 'state' observation"
        T, n = c.rewards.shape
        if T != self.T or not 1 <= n <= self.n_max:
            return f"chunk shape T={T}, N={n} does not fit slots of T={self.T}, N<={self.n_max}"
        if state.shape[2:] != self.obs.shape[3:] or c.actions.shape[2:] != self.actions.shape[3:]:
            return f"obs {state.shape} / actions {c.actions.shape} do not match the policy"
        self.obs[slot, :, :n] = torch.from_numpy(np.ascontiguousarray(state))
        self.final_obs[slot, :, :n] = torch.from_numpy(np.ascontiguousarray(c.final_obs["state"]))
        self.next_obs[slot, :n] = torch.from_numpy(np.ascontiguousarray(c.next_obs["state"]))
        self.actions[slot, :, :n] = torch.from_numpy(np.ascontiguousarray(c.actions))
        for name in _FIELDS_TN:
            self.tn[name][slot, :, :n] = torch.from_numpy(np.ascontiguousarray(getattr(c, name)))
        self._n[slot] = n
        self._version[slot] = c.policy_version
        self._rollout[slot] = c.rollout
        return None

    def steps(self, slot: int) -> int:
        return self.T * self._n[slot]

    def version(self, slot: int) -> int:
        return self._version[slot]

    def rollout(self, slot: int) -> str:
        return self._rollout[slot]

    def stack(self, slots: list[int], device: torch.device) -> dict[str, torch.Tensor]:
        """One [T, N_total, ...] batch on `device` from the given slots (env columns side by side)."""
        out: dict[str, torch.Tensor] = {}

        def cat(src: torch.Tensor, env_axis: int) -> torch.Tensor:
            parts = [src[s].narrow(env_axis, 0, self._n[s]) for s in slots]
            return torch.cat(parts, dim=env_axis).to(device, non_blocking=True)

        out["obs"] = cat(self.obs, 1)
        out["final_obs"] = cat(self.final_obs, 1)
        out["actions"] = cat(self.actions, 1)
        out["next_obs"] = cat(self.next_obs, 0)
        for name, src in self.tn.items():
            out[name] = cat(src, 1)
        out["steps"] = torch.tensor(sum(self.steps(s) for s in slots))
        return out
