"""Environments of the learning task: creation, grouped stepping and evaluation.

This module owns everything that touches a simulator:

* :func:`make_env` builds one Gymnasium env from a :class:`~dvla.config.TaskConfig` (a ManiSkill3
  id, or a user ``"module:factory"``).
* :class:`EnvGroup` steps ``n`` such envs sequentially in one process and hides the simulator's
  types: callers get float32/bool numpy arrays with a leading env axis, auto-reset included.
* :func:`run_eval_episodes` plays deterministic episodes and reports success rates.

Torch is used only to unwrap ManiSkill's tensors and to call the policy during evaluation.
"""

from __future__ import annotations

import importlib
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from dvla.config import TaskConfig

__all__ = ["make_env", "resolve_sim_backend", "EnvGroup", "StepResult", "run_eval_episodes"]


def resolve_sim_backend(name: str) -> str:
    """'auto' -> 'physx_cuda' when a CUDA device is present, else 'physx_cpu'."""
    if name != "auto":
        return name
    import torch

    return "physx_cuda" if torch.cuda.is_available() else "physx_cpu"


def _load_factory(spec: str) -> Callable[[TaskConfig, int], Any]:
    module_name, _, attr = spec.partition(":")
    if not module_name or not attr:
        raise ValueError(f"env factory must look like 'module:function', got {spec!r}")
    factory = getattr(importlib.import_module(module_name), attr, None)
    if not callable(factory):
        raise ValueError(f"{spec!r} does not name a callable")
    return factory


def make_env(task: TaskConfig, seed: int) -> Any:
    """One Gymnasium env for ``task``.

    ``task.env`` is either a ManiSkill3 id (``"PushCube-v1"``) or ``"module:factory"``, where
    ``factory(task, seed)`` returns a Gymnasium env. ``seed`` is only forwarded to factories;
    ManiSkill envs are seeded at reset by :class:`EnvGroup`.
    """
    if ":" in task.env:
        return _load_factory(task.env)(task, seed)
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401  (registers the ManiSkill ids; slow, so imported lazily)

    backend = resolve_sim_backend(task.sim_backend)
    kwargs: dict[str, Any] = dict(
        obs_mode=task.obs_mode,
        control_mode=task.control_mode,
        sim_backend=backend,
        num_envs=1,
        max_episode_steps=task.max_episode_steps,
    )
    if backend == "physx_cpu":
        # The default render backend wants a GPU; state obs never render, rgb uses the CPU path.
        kwargs["render_backend"] = "cpu"
    return gym.make(task.env, **kwargs)


def _to_numpy(x: Any) -> np.ndarray:
    if hasattr(x, "detach"):  # torch tensor (ManiSkill), possibly on a GPU
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def _flat_obs(obs: Any) -> np.ndarray:
    """A flat float32 vector from one env's observation (drops ManiSkill's batch dim of 1)."""
    if isinstance(obs, dict):
        raise TypeError(
            "EnvGroup needs array observations; wrap dict observations (e.g. obs_mode='rgb') "
            "in a flattening wrapper inside a 'module:factory' env"
        )
    return _to_numpy(obs).astype(np.float32, copy=False).reshape(-1)


def _scalar(x: Any, dtype: type) -> Any:
    return dtype(_to_numpy(x).reshape(-1)[0])


def _single_space(env: Any, name: str) -> Any:
    """The per-env space: ManiSkill exposes ``single_*_space`` next to its batched one."""
    space = getattr(env.unwrapped, f"single_{name}", None)
    return space if space is not None else getattr(env, name)


@dataclass(frozen=True)
class StepResult:
    """What :meth:`EnvGroup.step` returns; every array has a leading env axis of length n."""

    #: observations to act on next, float32 [n, D]; already reset where the episode ended
    next_obs: np.ndarray
    #: rewards, float32 [n]
    reward: np.ndarray
    #: the episode reached a terminal state (no bootstrap), bool [n]
    terminated: np.ndarray
    #: the episode hit its time limit (bootstrap from final_obs), bool [n]
    truncated: np.ndarray
    #: observation reached before the auto-reset, float32 [n, D]; zeros where not episode_done
    final_obs: np.ndarray
    #: info["success"] of this step (False when the env reports none), bool [n]
    success: np.ndarray
    #: the episode ended at this step and the env was reset, bool [n]
    episode_done: np.ndarray


class EnvGroup:
    """``n`` envs of one task stepped one after another in this process.

    Seeding: env ``i`` plays its ``k``-th episode (counted from the last seeded reset) with seed
    ``base + k * n + i``, so episode ``j = k * n + i`` of the group always uses ``base + j``
    whatever ``n`` is, and no two episodes of the group repeat an initial state. ``base`` is the
    constructor seed until :meth:`reset` is given another. Groups in different processes must
    therefore get seeds further apart than the episodes they will play (e.g. ``seed * 10**6``),
    or they replay each other's initial states.

    ``ignore_terminations=True`` plays every episode to its time limit (success does not end
    it); ``terminated`` is then always False. Evaluation uses this so "success at end" means
    something for tasks that terminate on success.
    """

    def __init__(self, task: TaskConfig, n: int, seed: int, *, ignore_terminations: bool = False):
        if n < 1:
            raise ValueError(f"an EnvGroup needs at least one env, got n={n}")
        self.task = task
        self.n = n
        self.ignore_terminations = ignore_terminations
        self._envs: list[Any] = []
        try:
            for i in range(n):
                self._envs.append(make_env(task, seed + i))
        except BaseException:
            self.close()
            raise
        act_space = _single_space(self._envs[0], "action_space")
        obs_space = _single_space(self._envs[0], "observation_space")
        if getattr(act_space, "shape", None) is None or len(act_space.shape) != 1:
            raise TypeError(f"EnvGroup needs a flat Box action space, got {act_space}")
        self.act_dim = int(act_space.shape[0])
        self.action_low = np.asarray(act_space.low, dtype=np.float32).reshape(self.act_dim)
        self.action_high = np.asarray(act_space.high, dtype=np.float32).reshape(self.act_dim)
        shape = getattr(obs_space, "shape", None)
        self.obs_dim = int(np.prod(shape)) if shape else None
        self._base = seed
        self._episode_index = np.zeros(n, dtype=np.int64)
        self._episode_seeds = np.zeros(n, dtype=np.int64)
        self._obs: np.ndarray | None = None

    # --- resets -------------------------------------------------------------------------------

    @property
    def episode_seeds(self) -> np.ndarray:
        """Reset seed of the episode each env is playing, int64 [n] (for grouping episodes)."""
        return self._episode_seeds.copy()

    def reset(self, seed: int | None = None) -> np.ndarray:
        """Start a fresh episode in every env; obs float32 [n, D].

        With ``seed`` the seed schedule restarts from it (episode j of the group uses seed + j),
        so two resets with the same seed replay the same initial states.
        """
        if seed is not None:
            self._base = seed
            self._episode_index[:] = 0
        obs = [self._reset_one(i, self._next_seed(i)) for i in range(self.n)]
        self._obs = np.stack(obs)
        return self._obs.copy()

    def reset_seeded(self, seeds: Any) -> np.ndarray:
        """Reset env i with ``seeds[i]`` now (e.g. several envs sharing one initial state).

        Later auto-resets continue the group's own schedule.
        """
        seeds = np.asarray(seeds, dtype=np.int64).reshape(-1)
        if seeds.shape[0] != self.n:
            raise ValueError(f"need {self.n} seeds, got {seeds.shape[0]}")
        obs = [self._reset_one(i, int(s)) for i, s in enumerate(seeds)]
        self._obs = np.stack(obs)
        return self._obs.copy()

    def _next_seed(self, i: int) -> int:
        s = self._base + int(self._episode_index[i]) * self.n + i
        self._episode_index[i] += 1
        return s

    def _reset_one(self, i: int, seed: int) -> np.ndarray:
        obs, _info = self._envs[i].reset(seed=seed)
        self._episode_seeds[i] = seed
        return self._check_obs(_flat_obs(obs))

    def _check_obs(self, obs: np.ndarray) -> np.ndarray:
        if self.obs_dim is None:
            self.obs_dim = obs.shape[0]
        elif obs.shape[0] != self.obs_dim:
            raise ValueError(f"observation has {obs.shape[0]} values, expected {self.obs_dim}")
        return obs

    # --- stepping -----------------------------------------------------------------------------

    def step(self, actions: Any) -> StepResult:
        """Apply ``actions`` [n, A] (clipped to the action space); auto-reset ended episodes."""
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        actions = np.asarray(actions, dtype=np.float32).reshape(self.n, self.act_dim)
        actions = np.clip(actions, self.action_low, self.action_high)
        n, d = self.n, self.obs_dim
        next_obs = np.empty((n, d), dtype=np.float32)
        final_obs = np.zeros((n, d), dtype=np.float32)
        reward = np.empty(n, dtype=np.float32)
        terminated = np.zeros(n, dtype=bool)
        truncated = np.zeros(n, dtype=bool)
        success = np.zeros(n, dtype=bool)
        for i, env in enumerate(self._envs):
            obs, r, term, trunc, info = env.step(actions[i])
            obs = self._check_obs(_flat_obs(obs))
            reward[i] = _scalar(r, float)
            terminated[i] = _scalar(term, bool) and not self.ignore_terminations
            truncated[i] = _scalar(trunc, bool)
            if "success" in info:
                success[i] = _scalar(info["success"], bool)
            if terminated[i] or truncated[i]:
                final_obs[i] = obs
                obs = self._reset_one(i, self._next_seed(i))
            next_obs[i] = obs
        self._obs = next_obs
        done = terminated | truncated
        return StepResult(next_obs.copy(), reward, terminated, truncated, final_obs, success, done)

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


# --- evaluation -------------------------------------------------------------------------------


def run_eval_episodes(
    policy: Any,
    task: TaskConfig,
    n_episodes: int,
    seed: int,
    device: Any = "cpu",
    group: EnvGroup | None = None,
    n_envs: int = 8,
) -> dict[str, float]:
    """Play ``n_episodes`` episodes with deterministic actions (the policy mean).

    Episode j starts from seed ``seed + j``, so two calls with the same seed see the same
    initial states. Pass ``group`` to reuse envs between evaluations (it is reset here; create it
    with ``ignore_terminations=True`` to play episodes to the time limit, which is what a group
    made here does). Env i plays episodes i, i + n, ...: every episode that is started is
    counted, so short (successful) episodes are not over-represented.

    Returns success_once (fraction of episodes with a success at any step), success_at_end
    (success at the last step), return_mean, episodes and env_steps.
    """
    import torch

    if n_episodes < 1:
        raise ValueError(f"n_episodes must be >= 1, got {n_episodes}")
    own = group is None
    if own:
        group = EnvGroup(task, min(n_envs, n_episodes), seed, ignore_terminations=True)
    try:
        return _play_eval(policy, group, n_episodes, seed, torch.device(device))
    finally:
        if own:
            group.close()


def _play_eval(policy: Any, group: EnvGroup, n_episodes: int, seed: int, device: Any) -> dict[str, float]:
    import torch

    n = group.n
    obs = group.reset(seed=seed)
    episode = np.arange(n)  # index of the episode each env is playing
    ret = np.zeros(n)
    once = np.zeros(n, dtype=bool)
    returns, successes_once, successes_end = [], [], []
    env_steps = 0
    started = time.perf_counter()
    while len(returns) < n_episodes:
        with torch.no_grad():
            action, _, _ = policy.act(torch.as_tensor(obs, device=device), deterministic=True)
        res = group.step(action.cpu().numpy())
        active = episode < n_episodes
        env_steps += int(active.sum())
        ret += res.reward
        once |= res.success
        for i in np.flatnonzero(res.episode_done & active):
            returns.append(ret[i])
            successes_once.append(once[i])
            successes_end.append(res.success[i])
        ret[res.episode_done] = 0.0
        once[res.episode_done] = False
        episode[res.episode_done] += n
        obs = res.next_obs
    return {
        "success_once": float(np.mean(successes_once)),
        "success_at_end": float(np.mean(successes_end)),
        "return_mean": float(np.mean(returns)),
        "episodes": len(returns),
        "env_steps": env_steps,
        "eval_s": time.perf_counter() - started,
    }
