"""The vision-language-action path: instruction tokeniser, default instructions, ``tiny-vla``.

* :mod:`.tokenizer`: text -> fixed-length int32 ids, offline and deterministic (hashed words).
* :mod:`.instructions`: a default instruction per ManiSkill3 task (``task.instruction`` overrides).
* :mod:`.model`: the ``tiny-vla`` policy (imported on first use by the policy registry).

The env side (images, proprioception and tokens as one observation dict) is
:class:`dvla.learn.envs.EnvGroup`; docs/policies.md describes the policy protocol.
"""

from .instructions import INSTRUCTIONS, instruction_for
from .tokenizer import tokenize

__all__ = ["INSTRUCTIONS", "instruction_for", "tokenize"]
