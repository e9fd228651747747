"""Percentiles for every benchmark: one definition (nearest rank), so figures of different
benchmarks compare; and the window between two readings of a role's cumulative latency buckets
(:class:`dvla.roles.swimlane.LatencyHistogram`)."""

from __future__ import annotations

import math
from collections import Counter
from typing import Iterable, Mapping

from dvla.roles.swimlane import bucket_upper_ms


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


def histogram_diff(later: Mapping[str, int], earlier: Mapping[str, int]) -> dict[str, int]:
    """Counts recorded between two readings of one label's buckets (``{bucket index: count}``)."""
    out = {}
    for b in sorted(set(later) | set(earlier), key=int):
        d = int(later.get(b, 0)) - int(earlier.get(b, 0))
        if d < 0:
            raise ValueError(f"bucket {b} went down ({earlier.get(b)} -> {later.get(b)}): readings of different lanes?")
        if d:
            out[b] = d
    return out


def histogram_percentile(counts: Mapping[str, int], q: float) -> float:
    """The ``q``-th percentile (0-100) of bucketed latencies as its bucket's upper edge (ms);
    0.0 for no samples."""
    edges = {bucket_upper_ms(int(b)): int(n) for b, n in counts.items() if int(n) > 0}
    return weighted_percentile(edges, q) if edges else 0.0
