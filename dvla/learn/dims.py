"""Observation and action sizes of a task, for processes that build a policy without stepping
envs (actor, replicator): one env is made, read and closed."""

from __future__ import annotations

from typing import Any

from ..config import TaskConfig
from .envs import ObsSpec


def probe_spec(task: TaskConfig) -> tuple[ObsSpec, int]:
    """(observation spec, act_dim) of `task`'s env (act_dim includes `task.action_chunk`)."""
    from .envs import EnvGroup

    group = EnvGroup(task, 1, 0)
    try:
        if group.obs_spec is None:
            group.reset()
        return dict(group.obs_spec), group.act_dim
    finally:
        group.close()


def probe_dims(task: TaskConfig) -> tuple[Any, int]:
    """(obs, act_dim) as :func:`~dvla.learn.policies.make_policy` takes them: obs is the int D
    for flat observations, the ObsSpec for structured ones."""
    from .policies import policy_obs_arg

    spec, act_dim = probe_spec(task)
    return policy_obs_arg(spec), act_dim
