"""One ManiSkill scene of ``n`` envs stepped as a batch, its tensors kept on the sim device.

ManiSkill3's GPU path (``physx_cuda``): where :class:`~dvla.learn.envs.EnvGroup` loops over
one-env simulators and hands out numpy arrays, :class:`VectorEnvGroup` wraps one
``ManiSkillVectorEnv`` and hands out tensors on the simulator's device, and the rollout records
a whole chunk there (:class:`DeviceChunk`) before one copy to the host. Which group a rollout
gets is :func:`dvla.learn.envs.env_groups`' decision.

Same contract as ``EnvGroup``, but for seeding and ``task.action_chunk`` (which must be 1): both
are described in docs/envs.md.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import torch

from dvla.config import TaskConfig

from ..fabric.messages import TrajectoryChunk, chunk_arrays, nest
from .spec import (ArraySpec, ChunkSpec, ObsSpec, StepLater, StepResult, maniskill_proprio, not_maniskill_rgb,
                   structured_spec)

__all__ = ["VectorEnvGroup", "make_vector_env", "DeviceChunk"]


class DeviceChunk(SimpleNamespace):
    """A trajectory chunk's per-step fields for ``n`` envs, laid out by ``spec``, as zero tensors
    on ``device``: a one-scene group records its steps here, then :meth:`copy_to` the host chunk."""

    def __init__(self, spec: ChunkSpec, n: int, device: torch.device | str) -> None:
        super().__init__(**nest({path: torch.zeros(shape, dtype=getattr(torch, s.dtype), device=device)
                                 for path, (shape, s) in spec.layout(n).items()}))

    def copy_to(self, chunk: TrajectoryChunk) -> None:
        """Copy every recorded tensor into ``chunk``'s arrays (in place)."""
        host = chunk_arrays(chunk)
        for path, tensor in chunk_arrays(self).items():
            torch.from_numpy(host[path]).copy_(tensor)


def make_vector_env(task: TaskConfig, n: int, backend: str, ignore_terminations: bool) -> Any:
    """ManiSkill's ``ManiSkillVectorEnv`` over one scene of ``n`` envs of ``task.env`` (no
    auto-reset: :class:`VectorEnvGroup` resets ended episodes itself)."""
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401  (registers the ManiSkill ids)
    from mani_skill.vector.wrappers.gymnasium import ManiSkillVectorEnv

    kwargs: dict[str, Any] = dict(
        obs_mode=task.obs_mode, control_mode=task.control_mode, sim_backend=backend, num_envs=n,
        max_episode_steps=task.max_episode_steps,
    )
    if task.obs_mode != "state":
        kwargs["sensor_configs"] = dict(width=task.image_size, height=task.image_size)
    if not torch.cuda.is_available():
        kwargs["render_backend"] = "cpu"  # SAPIEN through a software Vulkan driver (see make_env)
    env = gym.make(task.env, **kwargs)
    return ManiSkillVectorEnv(env, auto_reset=False, ignore_terminations=ignore_terminations, record_metrics=False)


def _batched(x: Any, n: int, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """A [n] tensor from what a vector env returns (a tensor, a Python scalar for one env)."""
    return torch.as_tensor(x, device=device).reshape(n).to(dtype)


class VectorEnvGroup(StepLater):
    """``n`` envs in one simulator scene; see the module docstring.

    ``venv`` is a ``ManiSkillVectorEnv``-like object (``reset(seed=..., options={"env_idx":
    ...})``, ``step``, ``single_action_space``, ``single_observation_space``, ``device``); by
    default one is made from ``task`` with ``backend``.
    """

    #: observations, rewards and flags are torch tensors on :attr:`device` (EnvGroup: numpy)
    on_device = True

    def __init__(
        self, task: TaskConfig, n: int, seed: int, *, ignore_terminations: bool = False,
        backend: str = "physx_cuda", venv: Any = None,
    ):
        if n < 1:
            raise ValueError(f"a VectorEnvGroup needs at least one env, got n={n}")
        if task.action_chunk != 1:
            raise ValueError(
                f"task.action_chunk {task.action_chunk}: a one-scene env group plays one simulator step per "
                "transition (set action_chunk: 1, or env_batching: loop)"
            )
        self.task, self.n, self.group_size = task, n, 1
        self.ignore_terminations = ignore_terminations
        self._venv = venv if venv is not None else make_vector_env(task, n, backend, ignore_terminations)
        self.device = torch.device(self._venv.device)
        act_space, obs_space = self._venv.single_action_space, self._venv.single_observation_space
        if getattr(act_space, "shape", None) is None or len(act_space.shape) != 1:
            self.close()
            raise TypeError(f"VectorEnvGroup needs a flat Box action space, got {act_space}")
        self.env_act_dim = self.act_dim = int(act_space.shape[0])
        self.chunk = 1
        self.action_low = np.asarray(act_space.low, dtype=np.float32).reshape(self.act_dim)
        self.action_high = np.asarray(act_space.high, dtype=np.float32).reshape(self.act_dim)
        self._low = torch.as_tensor(self.action_low, device=self.device)
        self._high = torch.as_tensor(self.action_high, device=self.device)
        self.structured = hasattr(obs_space, "spaces")
        self.task_labels: list[str] = [""] * n
        if self.structured:
            from .vla.instructions import instruction_for
            from .vla.tokenizer import instruction_tokenizer

            self.tokenizer = instruction_tokenizer(task.policy_kwargs, task.instruction_tokens, task.policy)
            text = task.instruction if task.instruction is not None else instruction_for(task.env)
            self.instruction = text
            self.instructions: list[str | None] = [text] * n
            tokens = torch.as_tensor(self.tokenizer.encode(text), device=self.device)
            self._tokens = tokens.unsqueeze(0).expand(n, -1).contiguous()
            self.obs_spec: ObsSpec | None = structured_spec(obs_space, task.instruction_tokens, self.tokenizer.vocab)
        else:
            self.instruction, self.instructions = None, [None] * n
            self.obs_spec = {"state": ArraySpec((int(np.prod(obs_space.shape)),), "float32")}
        self._base = seed
        self._resets = 0  # partial resets since the last seeded reset (names the next one's RNG)
        self._episode_seeds = np.full(n, -1, dtype=np.int64)
        self._succeeded = torch.zeros(n, dtype=torch.bool, device=self.device)
        self._obs: Any = None

    @property
    def obs_dim(self) -> int | None:
        return None if self.structured else self.obs_spec["state"].shape[0]

    @property
    def episode_seeds(self) -> np.ndarray:
        """Seed of each env's episode when it started from a seeded reset, else -1."""
        return self._episode_seeds.copy()

    # --- observations -------------------------------------------------------------------------

    def _convert(self, raw: Any) -> Any:
        """A [n, D] float32 tensor, or the rgb / proprio / tokens dict, from the scene's obs."""
        if not self.structured:
            return raw.reshape(self.n, -1).to(torch.float32)
        try:
            cameras = raw["sensor_data"]
            images = [cameras[name]["rgb"] for name in sorted(cameras)]
            proprio = torch.cat([part.reshape(self.n, -1) for part in maniskill_proprio(raw)], dim=1)
        except (KeyError, TypeError) as err:
            raise not_maniskill_rgb("dict observation", raw) from err
        return {"rgb": torch.cat(images, dim=-1).to(torch.uint8), "proprio": proprio.to(torch.float32),
                "tokens": self._tokens}

    @staticmethod
    def _map(obs: Any, fn: Any) -> Any:
        return {k: fn(v) for k, v in obs.items()} if isinstance(obs, dict) else fn(obs)

    # --- resets -------------------------------------------------------------------------------

    def reset(self, seed: int | None = None) -> Any:
        """A seeded reset of every env (env i: ``base + i``); ``seed`` replaces the base."""
        if seed is not None:
            self._base = seed
        return self.reset_seeded(self._base + np.arange(self.n))

    def reset_seeded(self, seeds: Any) -> Any:
        seeds = [int(s) for s in np.asarray(seeds, dtype=np.int64).reshape(-1)]
        if len(seeds) != self.n:
            raise ValueError(f"need {self.n} seeds, got {len(seeds)}")
        raw, _ = self._venv.reset(seed=seeds if self.n > 1 else seeds[0])
        self._episode_seeds[:] = seeds
        self._resets = 0
        self._succeeded.zero_()
        self._obs = self._convert(raw)
        return self._obs

    def _reset_ended(self, done: torch.Tensor) -> Any:
        """Reset the envs where ``done``; the scene's torch RNG is forked and seeded so the new
        initial states are a function of the group's seed and how many resets came before."""
        idx = torch.nonzero(done).reshape(-1)
        self._resets += 1
        devices = [self.device.index or 0] if self.device.type == "cuda" else []
        with torch.random.fork_rng(devices=devices):
            torch.manual_seed((self._base * 1_000_003 + self._resets) % 2**63)
            raw, _ = self._venv.reset(options={"env_idx": idx})
        self._episode_seeds[idx.cpu().numpy()] = -1
        self._succeeded[idx] = False
        return self._convert(raw)

    # --- stepping -----------------------------------------------------------------------------

    def step(self, actions: Any) -> Any:
        """Apply ``actions`` [n, act_dim] (a tensor on any device or an array; clipped to the
        action space) to the whole scene at once; reset the envs whose episodes ended."""
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        n = self.n
        a = torch.as_tensor(actions, device=self.device, dtype=torch.float32).reshape(n, self.act_dim)
        a = torch.clamp(a, self._low, self._high)
        raw, reward, terminated, truncated, info = self._venv.step(a)
        obs = self._convert(raw)
        success = (_batched(info["success"], n, self.device, torch.bool) if "success" in info
                   else torch.zeros(n, dtype=torch.bool, device=self.device))
        if self.task.reward == "success":
            reward = (success & ~self._succeeded).to(torch.float32)
        else:
            reward = _batched(reward, n, self.device, torch.float32)
        self._succeeded |= success
        terminated = _batched(terminated, n, self.device, torch.bool)
        if self.ignore_terminations:
            terminated = torch.zeros_like(terminated)
        truncated = _batched(truncated, n, self.device, torch.bool)
        done = terminated | truncated
        # the observation reached, where an episode ended (zeros elsewhere, as EnvGroup's)
        final_obs = self._map(obs, lambda v: torch.where(done.reshape(n, *[1] * (v.dim() - 1)), v, torch.zeros_like(v)))
        if bool(done.any()):
            # the scene's observation after a partial reset holds every env's: the reset envs'
            # first observation, the others' as they were
            obs = self._reset_ended(done)
        self._obs = obs
        return StepResult(obs, reward, terminated, truncated, final_obs, success, done)

    def close(self) -> None:
        venv, self._venv = getattr(self, "_venv", None), None
        if venv is not None:
            try:
                venv.close()
            except Exception:  # closing is best effort
                pass

    def __enter__(self) -> "VectorEnvGroup":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
