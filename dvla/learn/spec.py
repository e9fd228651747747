"""What the env layer promises its callers, apart from any simulator: observation specs
(:data:`ObsSpec`, :func:`structured_spec`), one step's result (:class:`StepResult`) and the setup
errors. :mod:`dvla.learn.envs` re-exports them; env adapters import them from here."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..fabric.messages import ArraySpec, ChunkSpec

__all__ = ["ArraySpec", "ChunkSpec", "ObsSpec", "EnvSetupError", "PolicySetupError", "StepResult", "StepLater",
           "maniskill_proprio", "not_maniskill_rgb", "structured_spec"]


class EnvSetupError(RuntimeError):
    """An env cannot be made as configured (e.g. LIBERO's assets or renderer): the message is one
    line naming the setting and its fix, and a role reports it as such, without a traceback."""


class PolicySetupError(ValueError):
    """A policy cannot be built as configured (e.g. its checkpoint directory is missing, incomplete
    or of another family): one line naming the path and what is wrong; a role reports it as
    such, without a traceback, and ``dvla plan``/``dvla up`` report it before starting anything."""


ObsSpec = dict[str, ArraySpec]
"""Observation name -> :class:`ArraySpec`; the names are the trajectory chunk's obs keys."""


@dataclass(frozen=True)
class StepResult:
    """What an env group's ``step`` returns; every array has a leading env axis of length n (numpy
    arrays from an ``EnvGroup``, torch tensors on the sim device from a ``VectorEnvGroup``)."""

    #: observations to act on next, float32 [n, D] (a dict of [n, ...] arrays when structured);
    #: already reset where the episode ended
    next_obs: Any
    #: rewards, float32 [n]
    reward: np.ndarray
    #: the episode reached a terminal state (no bootstrap), bool [n]
    terminated: np.ndarray
    #: the episode hit its time limit (bootstrap from final_obs), bool [n]
    truncated: np.ndarray
    #: observation reached before the auto-reset, same form as next_obs; zeros where not episode_done
    final_obs: Any
    #: info["success"] of this step (False when the env reports none), bool [n]
    success: np.ndarray
    #: the episode ended at this step and the env was reset, bool [n]
    episode_done: np.ndarray


class StepLater:
    """``step_async(actions)`` then ``step_wait()`` for an env group that steps in the caller's
    thread: the actions are kept and played by ``step_wait``. (Simulator worker processes start
    stepping at ``step_async`` instead: dvla/learn/simworkers.py.)"""

    _pending: Any = None

    def step_async(self, actions: Any) -> None:
        """Hand over the next step's actions; :meth:`step_wait` plays them."""
        self._pending = actions

    def step_wait(self) -> StepResult:
        """The result of the actions given to :meth:`step_async`."""
        actions, self._pending = self._pending, None
        if actions is None:
            raise RuntimeError("step_wait() without step_async()")
        return self.step(actions)  # type: ignore[attr-defined]  (the group's own step)


def maniskill_proprio(obs: Any) -> list[Any]:
    """The parts of a ManiSkill observation dict (or of its space's ``.spaces``) that make the
    proprioception, in order: the whole state vector where the dict has one (``obs_mode``
    ``rgb+state``: object poses included), else the joints' positions and velocities followed by
    the task's ``extra`` entries in ManiSkill's order. Without ``state`` those extras are what a
    real robot knows of itself (PushCube: the tool's pose, ``tcp_pose``; object poses only come
    with ``state``), so an ``rgb`` policy reads what LIBERO's proprio also has: joints and tool pose."""
    if "state" in obs:
        return [obs["state"]]
    agent = obs["agent"]
    extra = obs.get("extra") if hasattr(obs, "get") else None
    return [agent["qpos"], agent["qvel"], *(extra.values() if extra is not None else ())]


def not_maniskill_rgb(what: str, keys: Any) -> TypeError:
    """The one-line error for an observation (or its space) that is not ManiSkill's rgb layout."""
    return TypeError(f"{what} without sensor_data/<camera>/rgb and agent/qpos, agent/qvel or state "
                     f"(keys {sorted(keys)}); only ManiSkill's obs_mode 'rgb' and 'rgb+state' are understood")


def structured_spec(space: Any, n_tokens: int, vocab: int) -> ObsSpec:
    """The spec of :func:`_structured_obs`'s output, read from ManiSkill's Dict space (or from
    one that already has rgb and proprio)."""
    tokens = ArraySpec((n_tokens,), "int32", vocab=vocab)
    if "rgb" in space.spaces and "proprio" in space.spaces:
        return {"rgb": ArraySpec(tuple(space["rgb"].shape), "uint8"),
                "proprio": ArraySpec(tuple(space["proprio"].shape), "float32"), "tokens": tokens}
    try:
        cameras = space["sensor_data"]
        shapes = [tuple(cameras[name]["rgb"].shape) for name in sorted(cameras.spaces)]
        n_proprio = int(sum(np.prod(part.shape) for part in maniskill_proprio(space.spaces)))
    except (KeyError, TypeError) as err:
        raise not_maniskill_rgb("observation space", space.spaces) from err
    if not shapes or len({s[:2] for s in shapes}) != 1:
        raise TypeError(f"cameras must share one image size, got {shapes}")
    h, w = shapes[0][:2]
    return {
        "rgb": ArraySpec((h, w, sum(s[2] for s in shapes)), "uint8"),
        "proprio": ArraySpec((n_proprio,), "float32"),
        "tokens": tokens,
    }
