"""What the env layer promises its callers, apart from any simulator: the shape and dtype of each
observation array (:class:`ArraySpec`, :data:`ObsSpec`) and the error an env raises when it cannot
be made as configured (:class:`EnvSetupError`). :mod:`dvla.learn.envs` re-exports all three; env
adapters (:mod:`dvla.learn.libero`) import them from here."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["ArraySpec", "ObsSpec", "EnvSetupError", "PolicySetupError"]


class EnvSetupError(RuntimeError):
    """An env cannot be made as configured (e.g. LIBERO's assets or renderer): the message is one
    line naming the setting and its fix, and a role reports it as such, without a traceback."""


class PolicySetupError(ValueError):
    """A policy cannot be built as configured (e.g. its checkpoint directory is missing, incomplete
    or of another family): one line naming the path and what is wrong; a role reports it as
    such, without a traceback, and ``dvla plan``/``dvla up`` report it before starting anything."""


@dataclass(frozen=True)
class ArraySpec:
    """Shape (without the env axis) and dtype of one observation array."""

    #: per-env shape, e.g. (64, 64, 3)
    shape: tuple[int, ...]
    #: numpy dtype name: "float32", "uint8" or "int32"
    dtype: str
    #: token arrays: ids lie in [0, vocab) (None for other arrays)
    vocab: int | None = None


ObsSpec = dict[str, ArraySpec]
"""Observation name -> :class:`ArraySpec`; the names are the trajectory chunk's obs keys."""
