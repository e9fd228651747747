"""The vision-language-action path: instruction tokenisers (:mod:`.tokenizer`), default
instructions (:mod:`.instructions`), ``tiny-vla`` (:mod:`.model`) and the Hugging Face families
(:mod:`.checkpoint`, :mod:`.build`, :mod:`.hf_backbone`, :mod:`.token_action`, :mod:`.flow`;
torch, transformers and peft imported on first use). docs/policies.md describes the protocol.
"""

from .instructions import INSTRUCTIONS, instruction_for
from .tokenizer import tokenize

__all__ = ["INSTRUCTIONS", "instruction_for", "tokenize"]
