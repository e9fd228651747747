"""The instruction tokeniser: text -> a fixed-length int32 id vector, offline and deterministic.

Words are the maximal runs of ``[a-z0-9]`` in the lower-cased text. Each word maps to a bucket
``FIRST_WORD_ID + fnv1a_32(word) % (vocab_size - FIRST_WORD_ID)``; id 0 pads, id 1 starts the
sequence. Nothing is learned or downloaded, the same text gives the same ids on every machine and
Python version (FNV-1a is fixed, unlike ``hash()``), and any word has an id. The price is that two
words may share a bucket: with the default 4096 buckets, a 50-word instruction vocabulary has a
collision with probability about 0.26 (birthday bound), harmless for telling a few tasks apart.
Sequences longer than ``length`` are truncated (keeping the start).
"""

from __future__ import annotations

import re

import numpy as np

__all__ = ["PAD_ID", "BOS_ID", "FIRST_WORD_ID", "DEFAULT_VOCAB_SIZE", "words", "word_id", "tokenize"]

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
