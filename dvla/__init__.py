"""dvla: distributed asynchronous reinforcement learning for vision-language-action policies.

Layers (imports only go downwards): ``orchestrator`` -> ``roles`` -> ``learn`` / ``replication``
-> ``fabric``. ``dvla.fabric`` is usable on its own from any RL code.
"""

__version__ = "0.1.0"
