"""The instruction tokeniser: text -> a fixed-length int32 id vector, offline and deterministic.

Hashed words (FNV-1a, so every machine and Python version agrees; docs/policies.md,
"Instructions"); two words may share a bucket (with 4096 buckets, a 50-word vocabulary collides
with probability about 0.26), harmless for telling a few tasks apart. A Hugging Face checkpoint's
policy needs its own tokenizer's ids instead: :func:`instruction_tokenizer` loads it from the
checkpoint directory (``local_files_only``), right-padded with its pad id (0 when it has none).
"""

from __future__ import annotations

import functools
import os
import re
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import numpy as np

from .lerobot_format import LEROBOT_FAMILIES, TOKENIZER_FILES, check_lerobot

__all__ = ["PAD_ID", "BOS_ID", "FIRST_WORD_ID", "DEFAULT_VOCAB_SIZE", "words", "word_id", "tokenize",
           "InstructionTokenizer", "instruction_tokenizer", "checkpoint_tokenizer_dir", "pad_id_of",
           "tokenize_instruction", "decode_instructions"]

PAD_ID = 0
"""Fills the sequence after the last word; models mask it out."""
BOS_ID = 1
"""First id of every sequence, so an empty instruction still has one real token."""
FIRST_WORD_ID = 2
"""Smallest id a word can get."""
DEFAULT_VOCAB_SIZE = 4096
"""Ids are in [0, vocab_size)."""

_WORD_RE = re.compile(r"[a-z0-9]+")
_FNV_OFFSET = 0x811C9DC5
_FNV_PRIME = 0x01000193


def words(text: str) -> list[str]:
    """The words of ``text``: lower-cased runs of ASCII letters and digits."""
    return _WORD_RE.findall(text.lower())


def _fnv1a_32(data: bytes) -> int:
    h = _FNV_OFFSET
    for byte in data:
        h = ((h ^ byte) * _FNV_PRIME) & 0xFFFFFFFF
    return h


def word_id(word: str, vocab_size: int = DEFAULT_VOCAB_SIZE) -> int:
    """The id of one (already lower-cased) word."""
    if vocab_size <= FIRST_WORD_ID:
        raise ValueError(f"vocab_size must be > {FIRST_WORD_ID}, got {vocab_size}")
    return FIRST_WORD_ID + _fnv1a_32(word.encode("utf-8")) % (vocab_size - FIRST_WORD_ID)


def tokenize(text: str, length: int, vocab_size: int = DEFAULT_VOCAB_SIZE) -> np.ndarray:
    """``[BOS, w1, w2, ...]`` padded with PAD (or truncated) to ``length`` ids, int32."""
    if length < 1:
        raise ValueError(f"token length must be >= 1, got {length}")
    ids = [BOS_ID] + [word_id(w, vocab_size) for w in words(text)]
    out = np.full(length, PAD_ID, dtype=np.int32)
    ids = ids[:length]
    out[: len(ids)] = ids
    return out


def pad_id_of(tokenizer: Any) -> int:
    """A Hugging Face tokenizer's pad id (0 when it has none)."""
    return int(tokenizer.pad_token_id) if tokenizer.pad_token_id is not None else 0


def tokenize_instruction(tokenizer: Any, text: str, length: int) -> np.ndarray:
    """``text`` as ``length`` int32 ids of a checkpoint's tokenizer, right-padded with its pad id:
    what the ``tokens`` observation holds for the Hugging Face policies (the envs and the policies'
    tests both call this). The first id is always real (BOS, else UNK, for an empty text)."""
    ids = list(tokenizer(text)["input_ids"])[:length]
    if not ids:
        ids = [tokenizer.bos_token_id if tokenizer.bos_token_id is not None else tokenizer.unk_token_id]
    out = np.full(length, pad_id_of(tokenizer), dtype=np.int32)
    out[: len(ids)] = ids
    return out




@dataclass(frozen=True)
class InstructionTokenizer:
    """What an env tokenises instructions with: ``encode(text)`` -> int32 [length] ids in
    [0, vocab), right-padded with ``pad_id``."""

    #: ids per instruction (padded or truncated)
    length: int
    #: ids lie in [0, vocab)
    vocab: int
    #: the id that fills the sequence after the instruction
    pad_id: int
    #: "hashed" or the checkpoint directory whose tokenizer this is
    source: str
    _encode: Callable[[str], np.ndarray]

    def encode(self, text: str) -> np.ndarray:
        return self._encode(text)


def checkpoint_tokenizer_dir(policy_kwargs: Mapping[str, Any], policy: str = "") -> str | None:
    """The directory whose tokenizer the instructions use: for a LeRobot checkpoint (``policy``
    pi0, pi05 or smolvla) the one its policy loads (``policy_kwargs.tokenizer``, its
    ``tokenizer/``, its processor's ``tokenizer_name``); else ``policy_kwargs.checkpoint`` when it
    holds tokenizer files; else None (the hashed tokenizer)."""
    path = policy_kwargs.get("checkpoint")
    if policy in LEROBOT_FAMILIES and isinstance(path, str):
        found = check_lerobot(path, policy, tokenizer=policy_kwargs.get("tokenizer")).tokenizer_dir
        return None if found is None else str(found)
    if not isinstance(path, str) or not any(os.path.isfile(os.path.join(path, f)) for f in TOKENIZER_FILES):
        return None
    return path


def instruction_tokenizer(policy_kwargs: Mapping[str, Any], length: int, policy: str = "") -> InstructionTokenizer:
    """The hashed tokenizer, or the checkpoint's own (see :func:`checkpoint_tokenizer_dir`)."""
    path = checkpoint_tokenizer_dir(policy_kwargs, policy)
    if path is None:
        return InstructionTokenizer(length, DEFAULT_VOCAB_SIZE, PAD_ID, "hashed", lambda text: tokenize(text, length))
    return _hf_tokenizer(os.path.abspath(path), length)


@functools.lru_cache(maxsize=4)
def _hf_tokenizer(path: str, length: int) -> InstructionTokenizer:
    from transformers import AutoTokenizer  # only runs that point at a checkpoint pay for it

    try:
        tok = AutoTokenizer.from_pretrained(path, local_files_only=True)
    except (OSError, ValueError) as err:
        raise ValueError(f"{path}: cannot load its tokenizer ({str(err).splitlines()[0]})") from err
    return InstructionTokenizer(length, len(tok), pad_id_of(tok), path, lambda text: tokenize_instruction(tok, text, length))


def decode_instructions(tokenizer: Any, tokens: Any, cache: dict[bytes, str], limit: int = 4096) -> list[str]:
    """The instruction text of each row of ``tokens`` ([B, L] ids of ``tokenizer``, a torch tensor),
    special tokens dropped: what a policy that builds its own prompt reads from the env's ids.
    Rows seen before come from ``cache`` (at most ``limit`` entries: instructions repeat)."""
    out = []
    for row in tokens.to("cpu").numpy().astype(np.int64):
        key = row.tobytes()
        text = cache.get(key)
        if text is None:
            text = tokenizer.decode([int(i) for i in row], skip_special_tokens=True).strip()
            if len(cache) < limit:
                cache[key] = text
        out.append(text)
    return out
