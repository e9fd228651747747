"""The vision-language-action path: instruction tokenisers, default instructions, ``tiny-vla`` and
the Hugging Face families.

* :mod:`.tokenizer`: text -> fixed-length int32 ids: hashed words (offline, deterministic), or a
  policy checkpoint's own tokenizer.
* :mod:`.instructions`: a default instruction per ManiSkill3 task (``task.instruction`` overrides).
* :mod:`.model`: the ``tiny-vla`` policy (imported on first use by the policy registry).
* :mod:`.checkpoint` (no torch): the checkpoint directory of the Hugging Face policies, its checks
  and content hash; :mod:`.build` writes random ones.
* :mod:`.hf_backbone`, :mod:`.token_action` (``vla-tokens``), :mod:`.flow` (``vla-flow``): the
  policies on ``transformers`` models, LoRA through ``peft`` (imported on first use).

The env side (images, proprioception and tokens as one observation dict) is
:class:`dvla.learn.envs.EnvGroup`; docs/policies.md describes the policy protocol.
"""

from .instructions import INSTRUCTIONS, instruction_for
from .tokenizer import tokenize

__all__ = ["INSTRUCTIONS", "instruction_for", "tokenize"]
