"""Observation and action sizes of a task, for processes that build a policy without stepping
envs (actor, replicator): one env is made, read and closed."""

from __future__ import annotations

from ..config import TaskConfig


def probe_dims(task: TaskConfig) -> tuple[int, int]:
    """(obs_dim, act_dim) of `task`'s env."""
    from .envs import EnvGroup

    group = EnvGroup(task, 1, 0)
    try:
        return group.obs_dim, group.act_dim
    finally:
        group.close()
