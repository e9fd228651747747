"""Learning: task environments (``envs``), policies (``policies``) and the PPO/GRPO learner (``ppo``).

The simulator is imported lazily, so importing this package is cheap.
"""

from dvla.learn.envs import EnvGroup, StepResult, make_env, run_eval_episodes
from dvla.learn.policies import MLPPolicy, Policy, make_policy, register_policy
from dvla.learn.ppo import PPOLearner, Trajectories, compute_gae, gae_batch

__all__ = [
    "EnvGroup",
    "StepResult",
    "make_env",
    "run_eval_episodes",
    "MLPPolicy",
    "Policy",
    "make_policy",
    "register_policy",
    "PPOLearner",
    "Trajectories",
    "compute_gae",
    "gae_batch",
]
