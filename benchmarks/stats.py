"""Percentiles for every benchmark: one definition (nearest rank), so figures of different
benchmarks compare."""

from __future__ import annotations

import math
from collections import Counter
from typing import Iterable, Mapping


def weighted_percentile(counts: Mapping[float, int], q: float) -> float:
    """The ``q``-th percentile (0-100) of values given as ``{value: how many}``, nearest rank:
    the smallest value at or below which ``q``% of the samples lie."""
    if not 0.0 <= q <= 100.0:
        raise ValueError(f"percentile must be in [0, 100], got {q}")
    items = sorted((v, n) for v, n in counts.items() if n > 0)
    if not items:
        raise ValueError("percentile of no samples")
    rank = max(1, math.ceil(q / 100.0 * sum(n for _v, n in items)))
    seen = 0
    for value, n in items:
        seen += n
        if seen >= rank:
            return value
    return items[-1][0]


def percentile(values: Iterable[float], q: float) -> float:
    """The ``q``-th percentile (0-100) of `values` (any order), nearest rank."""
    return weighted_percentile(Counter(values), q)
