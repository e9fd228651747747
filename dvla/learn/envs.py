"""Environments of the learning task: :func:`make_env` (a ManiSkill3 id, ``"libero"`` or a user
``"module:factory"``), :class:`EnvGroup` (``n`` one-env simulators stepped in this process, numpy
arrays with the env axis first, auto-reset included) and :func:`run_eval_episodes`.

Observations are flat (``{"state": [n, D]}``) or structured (``rgb`` / ``proprio`` / ``tokens``,
the chunk's obs keys: docs/policies.md, "Observations a policy sees"); :attr:`EnvGroup.obs_spec`
describes them. An env that already gives ``rgb`` and ``proprio`` (LIBERO) is taken as it is.
"""

from __future__ import annotations

import importlib
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from dvla.config import LIBERO_ENV, TaskConfig, env_group_sizes

from ..stats import wilson_interval
from .spec import (ArraySpec, ChunkSpec, EnvSetupError, ObsSpec, StepLater, StepResult, maniskill_proprio,
                   not_maniskill_rgb, structured_spec)

__all__ = [
    "make_env", "EnvSetupError", "ArraySpec", "ObsSpec", "EnvGroup", "StepResult", "run_eval_episodes",
    "obs_as_dict", "obs_to_torch", "probe_spec", "make_env_group", "sim_layout", "is_maniskill",
    "env_groups", "chunk_envs", "chunk_spec",
]


def obs_as_dict(obs: Any) -> dict[str, np.ndarray]:
    """A flat observation array as ``{"state": obs}``; a dict as it is."""
    return obs if isinstance(obs, dict) else {"state": obs}


def obs_to_torch(obs: Any, device: Any = "cpu") -> Any:
    """What a policy is called with: a tensor (flat) or a dict of tensors; dtypes kept (uint8 images)."""
    import torch

    if isinstance(obs, dict):
        return {k: torch.as_tensor(v, device=device) for k, v in obs.items()}
    return torch.as_tensor(obs, device=device)


def _load_factory(spec: str) -> Callable[[TaskConfig, int], Any]:
    module_name, _, attr = spec.partition(":")
    if not module_name or not attr:
        raise ValueError(f"env factory must look like 'module:function', got {spec!r}")
    factory = getattr(importlib.import_module(module_name), attr, None)
    if not callable(factory):
        raise ValueError(f"{spec!r} does not name a callable")
    return factory


def is_maniskill(task: TaskConfig) -> bool:
    """``task.env`` names a ManiSkill3 id (not LIBERO, not a user factory)."""
    return ":" not in task.env and task.env != LIBERO_ENV


def sim_layout(task: TaskConfig, n: int, cuda: bool | None = None, batching: str | None = None) -> tuple[str, bool]:
    """``(sim backend, one scene?)`` for a group of ``n`` envs of ``task`` on this machine
    (``cuda``: whether it has a CUDA device; ``batching``: ``task.env_batching`` unless given).
    The rule and its table: docs/envs.md, "Two ways to hold a rollout's envs". Raises
    EnvSetupError for a layout ManiSkill cannot build (several envs in one CPU scene).
    """
    batching = batching or task.env_batching
    if not is_maniskill(task):
        return "", batching == "scene" and task.env != LIBERO_ENV
    if cuda is None:
        import torch

        cuda = torch.cuda.is_available()
    if batching == "auto" and task.algorithm == "grpo":
        batching = "loop"
    if batching == "loop":
        return (task.sim_backend if task.sim_backend != "auto" else "physx_cpu"), False
    backend = task.sim_backend
    if backend == "auto":
        backend = "physx_cuda" if cuda and (n > 1 or batching == "scene") else "physx_cpu"
    scene = batching == "scene" or backend == "physx_cuda"
    if scene and backend == "physx_cpu" and n > 1:
        raise EnvSetupError(
            f"task.env_batching: scene puts {n} envs in one simulator scene, which ManiSkill runs only on "
            f"physx_cuda (this {'machine has CUDA' if cuda else 'machine has no CUDA device'}, sim_backend is "
            f"{task.sim_backend!r}): use env_batching: loop here, or run on a CUDA node"
        )
    return backend, scene


def env_groups(task: TaskConfig, cuda: bool | None = None) -> tuple[list[int], bool]:
    """How a rollout of ``task`` groups its ``envs_per_rollout`` envs on a machine with (``cuda``)
    or without CUDA (None: this one): (envs per group, one scene?). One group of every env where
    they share one simulator scene (:func:`sim_layout`), else two double-buffered halves (one
    group below two envs). A trajectory chunk holds one group's envs."""
    one_scene = sim_layout(task, task.envs_per_rollout, cuda)[1]
    return env_group_sizes(task.envs_per_rollout, one_scene), one_scene


def chunk_envs(task: TaskConfig) -> tuple[int, int]:
    """(fewest, most) envs one chunk of ``task`` holds, whichever machine its rollout runs on:
    :func:`env_groups` with and without CUDA (``env_batching: auto`` puts a scene only on CUDA)."""
    sizes = []
    for cuda in (False, True):
        try:
            sizes += env_groups(task, cuda)[0]
        except EnvSetupError:  # a layout that machine cannot build (the topology check says so)
            pass
    return min(sizes, default=task.envs_per_rollout), max(sizes, default=task.envs_per_rollout)


def chunk_spec(task: TaskConfig, obs_spec: ObsSpec, act_dim: int, extras: dict[str, ArraySpec]) -> ChunkSpec:
    """The shape of every trajectory chunk of ``task`` whose policy ships ``extras`` per step: what
    a rollout fills, the actor checks and its slots hold. N is the most envs a chunk holds
    (:func:`chunk_envs`): the actor cannot know which machine each of its rollouts runs on."""
    return ChunkSpec(obs=dict(obs_spec), act_dim=act_dim, extras=dict(extras), T=task.chunk_steps,
                     N=chunk_envs(task)[1])


def make_env(task: TaskConfig, seed: int, backend: str | None = None) -> Any:
    """One Gymnasium env for ``task``.

    ``task.env`` is a ManiSkill3 id (``"PushCube-v1"``), ``"libero"`` or ``"module:factory"``,
    where ``factory(task, seed)`` returns a Gymnasium env. ``seed`` is only forwarded to factories
    and LIBERO (it picks the env's first task); ManiSkill envs are seeded at reset by :class:`EnvGroup`.
    ``backend`` overrides the ManiSkill sim backend :func:`sim_layout` picks for a one-env scene.
    """
    if ":" in task.env:
        return _load_factory(task.env)(task, seed)
    if task.env == LIBERO_ENV:
        from .libero import make_env as make_libero_env

        return make_libero_env(task, seed)
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401  (registers the ManiSkill ids; slow, so imported lazily)

    import torch

    cuda = torch.cuda.is_available()
    kwargs: dict[str, Any] = dict(
        obs_mode=task.obs_mode,
        control_mode=task.control_mode,
        sim_backend=backend or sim_layout(task, 1, cuda, batching="loop")[0],
        num_envs=1,
        max_episode_steps=task.max_episode_steps,
    )
    if task.obs_mode != "state":
        kwargs["sensor_configs"] = dict(width=task.image_size, height=task.image_size)
    if not cuda:
        # ManiSkill's default render backend wants a GPU; without one, render on the CPU
        # (SAPIEN through a software Vulkan driver). With CUDA the GPU renderer is kept.
        kwargs["render_backend"] = "cpu"
    return gym.make(task.env, **kwargs)


def make_env_group(
    task: TaskConfig, n: int, seed: int, *, ignore_terminations: bool = False, group_size: int = 1,
    batching: str | None = None,
) -> "EnvGroup | Any":
    """An :class:`EnvGroup` of ``n`` one-env simulators, or a
    :class:`~dvla.learn.vector_env.VectorEnvGroup` (one scene of ``n`` envs) where
    :func:`sim_layout` says so. Both take the same calls; the second's outputs are torch tensors
    on the sim device (``group.on_device``). With a user factory and ``env_batching: scene`` the
    scene is ``factory(task, seed, num_envs=n)``, a batched env with ``ManiSkillVectorEnv``'s
    calls (docs/envs.md)."""
    backend, scene = sim_layout(task, n, batching=batching)
    if not scene:
        return EnvGroup(task, n, seed, ignore_terminations=ignore_terminations, group_size=group_size,
                        backend=backend or None)
    if group_size != 1:
        raise EnvSetupError(
            f"algorithm grpo needs {group_size} envs per seeded initial state, which one simulator scene does "
            "not give: set task.env_batching: loop"
        )
    from .vector_env import VectorEnvGroup

    venv = _load_factory(task.env)(task, seed, num_envs=n) if ":" in task.env else None
    return VectorEnvGroup(task, n, seed, ignore_terminations=ignore_terminations, backend=backend, venv=venv)


def _to_numpy(x: Any) -> np.ndarray:
    if hasattr(x, "detach"):  # torch tensor (ManiSkill), possibly on a GPU
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def _flat_obs(obs: Any) -> np.ndarray:
    """A flat float32 vector from one env's observation (drops ManiSkill's batch dim of 1)."""
    return _to_numpy(obs).astype(np.float32, copy=False).reshape(-1)


def _structured_obs(obs: dict, tokens: np.ndarray) -> dict[str, np.ndarray]:
    """rgb / proprio / tokens of one env from ManiSkill's rgb observation dict (batch dim 1), or
    from an env that already gives rgb and proprio (LIBERO)."""
    if "rgb" in obs and "proprio" in obs:
        return {"rgb": obs["rgb"], "proprio": obs["proprio"], "tokens": tokens}
    try:
        cameras = obs["sensor_data"]
        images = [_to_numpy(cameras[name]["rgb"])[0] for name in sorted(cameras)]
        proprio = np.concatenate([_to_numpy(part).reshape(-1) for part in maniskill_proprio(obs)])
    except (KeyError, TypeError) as err:
        raise not_maniskill_rgb("dict observation", obs) from err
    if not images:
        raise TypeError("obs_mode='rgb' produced no camera image (sensor_data is empty)")
    return {
        "rgb": np.concatenate(images, axis=-1).astype(np.uint8, copy=False),
        "proprio": proprio.astype(np.float32, copy=False),
        "tokens": tokens,
    }


def _scalar(x: Any, dtype: type) -> Any:
    return dtype(_to_numpy(x).reshape(-1)[0])


def _single_space(env: Any, name: str) -> Any:
    """The per-env space: ManiSkill exposes ``single_*_space`` next to its batched one."""
    space = getattr(env.unwrapped, f"single_{name}", None)
    return space if space is not None else getattr(env, name)


class EnvGroup(StepLater):
    """``n`` envs of one task stepped one after another in this process.

    Seeding: env ``i`` plays its ``k``-th episode (counted from the last seeded reset) with seed
    ``base + (k * n + i) // group_size``. With ``group_size`` 1 (the default) episode
    ``j = k * n + i`` of the group always uses ``base + j`` whatever ``n`` is, and no two
    episodes of the group repeat an initial state. With ``group_size`` G (GRPO) envs
    ``G*m .. G*m + G-1`` play their k-th episodes from one shared seed: G episodes per initial
    state. ``base`` is the constructor seed until :meth:`reset` is given another. Groups in
    different processes must therefore get seeds further apart than the episodes they will play
    (e.g. ``seed * 10**6``), or they replay each other's initial states.

    ``ignore_terminations=True`` plays every episode to its time limit (``terminated`` always
    False), so evaluation's "success at end" means something for tasks that end on success.

    ``task.action_chunk`` K > 1 makes one :meth:`step` play K simulator steps open loop with the
    K actions laid side by side (``act_dim`` is K times the env's); rewards add up, success is
    any sub-step's, and the transition ends early when the episode does. ``task.reward ==
    "success"`` replaces the env's reward by 1 at the first successful step of an episode.
    """

    #: observations, rewards and flags are numpy arrays (VectorEnvGroup: torch tensors on its device)
    on_device = False

    def __init__(
        self, task: TaskConfig, n: int, seed: int, *, ignore_terminations: bool = False, group_size: int = 1,
        backend: str | None = None, part: tuple[int, int] | None = None,
    ):
        if n < 1:
            raise ValueError(f"an EnvGroup needs at least one env, got n={n}")
        #: (first, total): these n envs are envs first .. first + n - 1 of a group of `total` held by
        #: several processes (dvla/learn/simworkers.py); seeds follow the whole group's schedule
        self.first, self.total = part if part is not None else (0, n)
        if not 0 <= self.first <= self.total - n:
            raise ValueError(f"part {part}: envs {self.first} .. {self.first + n - 1} are not inside a group of {self.total}")
        if group_size < 1 or n % group_size or self.first % group_size:
            raise ValueError(f"group_size {group_size} must be >= 1 and divide the group's {n} envs (and its first, {self.first})")
        if task.action_chunk < 1:
            raise ValueError(f"task.action_chunk must be >= 1, got {task.action_chunk}")
        self.task = task
        self.n = n
        self.group_size = group_size
        self.ignore_terminations = ignore_terminations
        self._envs: list[Any] = []
        try:
            for i in range(n):
                self._envs.append(make_env(task, seed + self.first + i, backend=backend))
        except BaseException:
            self.close()
            raise
        act_space = _single_space(self._envs[0], "action_space")
        obs_space = _single_space(self._envs[0], "observation_space")
        if getattr(act_space, "shape", None) is None or len(act_space.shape) != 1:
            raise TypeError(f"EnvGroup needs a flat Box action space, got {act_space}")
        self.env_act_dim = int(act_space.shape[0])
        self.chunk = task.action_chunk
        self.act_dim = self.env_act_dim * self.chunk
        low = np.asarray(act_space.low, dtype=np.float32).reshape(self.env_act_dim)
        high = np.asarray(act_space.high, dtype=np.float32).reshape(self.env_act_dim)
        self.action_low, self.action_high = np.tile(low, self.chunk), np.tile(high, self.chunk)
        self.structured = hasattr(obs_space, "spaces")  # a gymnasium Dict space
        #: per env: the instruction of the episode in progress (None for flat observations)
        self.instructions: list[str | None] = [None] * n
        self._tokens: list[np.ndarray] = []
        #: per env: the env's name for the task of the episode in progress ("" when it has none)
        self.task_labels: list[str] = [""] * n
        if self.structured:
            from .vla.tokenizer import instruction_tokenizer

            #: the hashed tokenizer, or the policy checkpoint's own (docs/policies.md)
            self.tokenizer = instruction_tokenizer(task.policy_kwargs, task.instruction_tokens, task.policy)
            self._tokens = [self._instruction_tokens(env, i) for i, env in enumerate(self._envs)]
            self.instruction = self.instructions[0]
            self.obs_spec: ObsSpec | None = structured_spec(obs_space, task.instruction_tokens, self.tokenizer.vocab)
        else:
            self.instruction = None
            shape = getattr(obs_space, "shape", None)
            self.obs_spec = {"state": ArraySpec((int(np.prod(shape)),), "float32")} if shape else None
        self._base = seed
        self._episode_index = np.zeros(n, dtype=np.int64)
        self._episode_seeds = np.zeros(n, dtype=np.int64)
        self._succeeded = np.zeros(n, dtype=bool)
        self._obs: dict[str, np.ndarray] | None = None

    def _instruction_tokens(self, env: Any, i: int) -> np.ndarray:
        """Tokens of env i's instruction: ``task.instruction``, else the env's own (LIBERO: its
        current task's), else the table's default for ``task.env``; recorded in ``instructions``."""
        from .vla.instructions import instruction_for

        own = getattr(env.unwrapped, "instruction", None)
        text = self.task.instruction if self.task.instruction is not None else own
        text = text if text is not None else instruction_for(self.task.env)
        if text != self.instructions[i] or i >= len(self._tokens):
            self.instructions[i] = text
            return self.tokenizer.encode(text)
        return self._tokens[i]

    @property
    def obs_dim(self) -> int | None:
        """D of flat observations (None for structured ones, or before the first flat reset)."""
        if self.structured or self.obs_spec is None:
            return None
        return self.obs_spec["state"].shape[0]

    # --- resets -------------------------------------------------------------------------------

    @property
    def episode_seeds(self) -> np.ndarray:
        """Reset seed of the episode each env is playing, int64 [n] (for grouping episodes)."""
        return self._episode_seeds.copy()

    def reset(self, seed: int | None = None) -> Any:
        """Start a fresh episode in every env and return the observations; ``seed`` restarts the
        seed schedule from it (two resets with one seed replay the same initial states)."""
        if seed is not None:
            self._base = seed
            self._episode_index[:] = 0
        return self._reset_all([self._next_seed(i) for i in range(self.n)])

    def reset_seeded(self, seeds: Any) -> Any:
        """Reset env i with ``seeds[i]`` now; later auto-resets continue the group's own schedule."""
        seeds = np.asarray(seeds, dtype=np.int64).reshape(-1)
        if seeds.shape[0] != self.n:
            raise ValueError(f"need {self.n} seeds, got {seeds.shape[0]}")
        return self._reset_all([int(s) for s in seeds])

    def _reset_all(self, seeds: list[int]) -> Any:
        per_env = [self._reset_one(i, s) for i, s in enumerate(seeds)]
        self._obs = {k: np.stack([o[k] for o in per_env]) for k in per_env[0]}
        return self._out(self._obs, copy=True)

    def _next_seed(self, i: int) -> int:
        s = self._base + (int(self._episode_index[i]) * self.total + self.first + i) // self.group_size
        self._episode_index[i] += 1
        return s

    def _reset_one(self, i: int, seed: int) -> dict[str, np.ndarray]:
        env = self._envs[i]
        obs, _info = env.reset(seed=seed)
        self._episode_seeds[i] = seed
        self._succeeded[i] = False
        self.task_labels[i] = str(getattr(env.unwrapped, "task_label", ""))
        if self.structured:
            self._tokens[i] = self._instruction_tokens(env, i)
        return self._convert(obs, i)

    def _convert(self, obs: Any, i: int) -> dict[str, np.ndarray]:
        if self.structured:
            return _structured_obs(obs, self._tokens[i])
        flat = _flat_obs(obs)
        if self.obs_spec is None:
            self.obs_spec = {"state": ArraySpec((flat.shape[0],), "float32")}
        elif flat.shape[0] != self.obs_dim:
            raise ValueError(f"observation has {flat.shape[0]} values, expected {self.obs_dim}")
        return {"state": flat}

    def _out(self, obs: dict[str, np.ndarray], copy: bool = False) -> Any:
        if not self.structured:
            return obs["state"].copy() if copy else obs["state"]
        return {k: v.copy() for k, v in obs.items()} if copy else obs

    # --- stepping -----------------------------------------------------------------------------

    def step(self, actions: Any, active: Any = None) -> StepResult:
        """Apply ``actions`` [n, act_dim] (clipped to the action space); auto-reset ended episodes.

        ``active`` (bool [n], default all): envs left out are not stepped; their observation stays,
        their reward is 0 and their flags are False (an evaluation whose envs finish their
        episodes at different times steps only those still playing)."""
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        skip = np.zeros(self.n, dtype=bool) if active is None else ~np.asarray(active, dtype=bool).reshape(self.n)
        actions = np.asarray(actions, dtype=np.float32).reshape(self.n, self.act_dim)
        actions = np.clip(actions, self.action_low, self.action_high)
        n, a = self.n, self.env_act_dim
        next_obs = {k: np.empty_like(v) for k, v in self._obs.items()}
        final_obs = {k: np.zeros_like(v) for k, v in self._obs.items()}
        reward = np.zeros(n, dtype=np.float32)
        terminated = np.zeros(n, dtype=bool)
        truncated = np.zeros(n, dtype=bool)
        success = np.zeros(n, dtype=bool)
        for i, env in enumerate(self._envs):
            if skip[i]:
                for key, arr in self._obs.items():
                    next_obs[key][i] = arr[i]
                continue
            for k in range(self.chunk):
                raw, r, term, trunc, info = env.step(actions[i, k * a : (k + 1) * a])
                ok = "success" in info and _scalar(info["success"], bool)
                success[i] |= ok
                if self.task.reward == "success":
                    reward[i] += float(ok and not self._succeeded[i])
                else:
                    reward[i] += _scalar(r, float)
                self._succeeded[i] |= ok
                terminated[i] = _scalar(term, bool) and not self.ignore_terminations
                truncated[i] = _scalar(trunc, bool)
                if terminated[i] or truncated[i]:
                    break
            obs = self._convert(raw, i)
            if terminated[i] or truncated[i]:
                for key, arr in obs.items():
                    final_obs[key][i] = arr
                obs = self._reset_one(i, self._next_seed(i))
            for key, arr in obs.items():
                next_obs[key][i] = arr
        self._obs = next_obs
        done = terminated | truncated
        return StepResult(
            self._out(next_obs, copy=True), reward, terminated, truncated, self._out(final_obs), success, done
        )

    def close(self) -> None:
        for env in self._envs:
            try:
                env.close()
            except Exception:  # closing is best effort; a broken env must not block the rest
                pass
        self._envs = []

    def __enter__(self) -> "EnvGroup":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def probe_spec(task: TaskConfig) -> tuple[ObsSpec, int]:
    """(observation spec, act_dim) of ``task``'s env, for processes that build a policy without
    stepping envs (actor, replicator): one env is made, read and closed (LIBERO's sizes follow
    from the config, no env is made)."""
    if task.env == LIBERO_ENV:
        from .libero import obs_spec

        return obs_spec(task)
    # sizes are the same on every backend: probe on the CPU, whatever the node's GPU does
    group = EnvGroup(task, 1, 0, backend="physx_cpu" if is_maniskill(task) else None)
    try:
        if group.obs_spec is None:
            group.reset()
        return dict(group.obs_spec), group.act_dim
    finally:
        group.close()


# --- evaluation -------------------------------------------------------------------------------


def run_eval_episodes(
    policy: Any,
    task: TaskConfig,
    n_episodes: int,
    seed: int,
    device: Any = "cpu",
    group: Any = None,
    n_envs: int = 8,
    stop: Any = None,
) -> dict[str, Any] | None:
    """Play ``n_episodes`` episodes with deterministic actions (the policy mean); None when
    ``stop`` (a ``threading.Event``) is set before they are all played.

    Episode j starts from seed ``seed + j``. ``group`` reuses envs between evaluations (reset
    here); a group made here follows ``task.eval.full_episodes``. Env i plays episodes i, i + n,
    ...: every started episode is counted, so short (successful) ones are not over-represented.

    Returns success_once (fraction of episodes with a success at any step) with its 95 % Wilson
    interval (success_once_low, success_once_high), success_at_end (success at the last step),
    return_mean, episodes, failed_episodes (the indices j of the episodes without a success: with
    the same seed, the same initial states) and env_steps; with envs that name their tasks (LIBERO), also
    ``per_task``: task label -> (episodes, episodes with a success at any step).
    """
    import torch

    if n_episodes < 1:
        raise ValueError(f"n_episodes must be >= 1, got {n_episodes}")
    own = group is None
    if own:
        group = make_env_group(task, min(n_envs, n_episodes), seed, ignore_terminations=task.eval.full_episodes,
                               batching="auto")
    try:
        return _play_eval(policy, group, n_episodes, seed, torch.device(device), stop)
    finally:
        if own:
            group.close()


def _play_eval(policy: Any, group: EnvGroup, n_episodes: int, seed: int, device: Any, stop: Any) -> dict[str, Any] | None:
    import torch

    from .policies import sample_actions

    n = group.n
    obs = group.reset(seed=seed)
    episode = np.arange(n)  # index of the episode each env is playing
    ret = np.zeros(n)
    once = np.zeros(n, dtype=bool)
    returns, successes_once, successes_end = [], [], []
    failed: list[int] = []  # episodes (0 .. n_episodes - 1) without a success at any step
    per_task: dict[str, tuple[int, int]] = {}
    env_steps = 0
    started = time.perf_counter()
    while len(returns) < n_episodes:
        if stop is not None and stop.is_set():
            return None
        with torch.no_grad():
            action, _, _ = sample_actions(policy, obs_to_torch(obs, device), deterministic=True)
            action = action.float()
        labels = list(group.task_labels)  # the episodes in progress (a step may reset into another task)
        active = episode < n_episodes
        if group.on_device:  # one scene steps all its envs at once
            res = group.step(action)
        else:
            res = group.step(action.cpu().numpy(), active=active)
        reward, success, ended = _to_numpy(res.reward), _to_numpy(res.success), _to_numpy(res.episode_done)
        env_steps += int(active.sum())
        ret += reward
        once |= success
        for i in np.flatnonzero(ended & active):
            returns.append(ret[i])
            successes_once.append(once[i])
            successes_end.append(success[i])
            if not once[i]:
                failed.append(int(episode[i]))
            if labels[i]:
                done, ok = per_task.get(labels[i], (0, 0))
                per_task[labels[i]] = (done + 1, ok + int(once[i]))
        ret[ended] = 0.0
        once[ended] = False
        episode[ended] += n
        obs = res.next_obs
    low, high = wilson_interval(int(np.sum(successes_once)), len(successes_once))
    out: dict[str, Any] = {
        "success_once": float(np.mean(successes_once)),
        "success_once_low": low,
        "success_once_high": high,
        "success_at_end": float(np.mean(successes_end)),
        "return_mean": float(np.mean(returns)),
        "episodes": len(returns),
        "failed_episodes": sorted(failed),
        "env_steps": env_steps,
        "eval_s": time.perf_counter() - started,
    }
    if per_task:
        out["per_task"] = dict(sorted(per_task.items()))
    return out
