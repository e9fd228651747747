"""Learning: task environments (``envs``), policies (``policies``) and the PPO/GRPO learner (``ppo``).

Names are imported on first use (PEP 562), so importing a light submodule (``spec``,
``vla.checkpoint``, ``vla.tokenizer``) does not import torch or the simulator: the CLI checks
topologies and checkpoints without either.
"""

from __future__ import annotations

import importlib
from typing import Any

_HOME = {
    "EnvGroup": "envs", "StepResult": "envs", "make_env": "envs", "run_eval_episodes": "envs",
    "make_env_group": "envs", "VectorEnvGroup": "vector_env",
    "MLPPolicy": "policies", "Policy": "policies", "make_policy": "policies", "register_policy": "policies",
    "PPOLearner": "ppo", "Trajectories": "ppo", "compute_gae": "ppo", "gae_batch": "ppo",
}

__all__ = list(_HOME)


def __getattr__(name: str) -> Any:
    if name not in _HOME:
        raise AttributeError(f"module 'dvla.learn' has no attribute {name!r}")
    return getattr(importlib.import_module(f"dvla.learn.{_HOME[name]}"), name)
