"""The role counter-file format (re-exported until it moves here from dvla.roles.counters)."""

from .roles.counters import INCARNATION_SHIFT, CounterFile, read_counters, source_key, split_seq

__all__ = ["INCARNATION_SHIFT", "CounterFile", "read_counters", "source_key", "split_seq"]
