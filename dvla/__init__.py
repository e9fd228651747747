"""dvla: distributed asynchronous reinforcement learning for vision-language-action policies.

Layers (imports only go downwards): ``orchestrator`` (which starts the roles as processes and
never imports them) and ``roles`` -> ``learn`` / ``replication`` -> ``fabric``; ``config`` and
``ledger`` (the chunk accounting) are shared above the fabric. ``dvla.fabric`` is usable on its own from any RL code.
tests/unit/test_layers.py checks these rules and that no import cycle exists.
"""

__version__ = "0.1.0"
