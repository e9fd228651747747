"""Percentiles for every benchmark: one definition (nearest rank), so figures of different
benchmarks compare; cumulative latency buckets (:class:`LatencyHistogram`, kept by the rollouts
`dvla bench swimlane` runs) and the window between two readings of them; the CPU time of another
process (:func:`process_cpu_s`) for the benchmarks that charge CPU to processes."""

from __future__ import annotations

import ctypes
import ctypes.util
import math
import threading
import time
from collections import Counter
from typing import Iterable, Mapping


_LIBC = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)


def process_cpu_s(pid: int) -> float | None:
    """User + system CPU seconds process `pid` has used so far (its threads, live and exited), to
    the nanosecond from its POSIX CPU clock (``clock_getcpuclockid``); None once it is gone.
    (``/proc/PID/stat`` counts 10 ms ticks: a sink's few milliseconds per 4 MiB version read 0.)"""
    clock = ctypes.c_int()
    if _LIBC.clock_getcpuclockid(pid, ctypes.byref(clock)) != 0:
        return None
    try:
        return time.clock_gettime(clock.value)
    except OSError:
        return None


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


LATENCY_BUCKET_RATIO = 1.02
"""Upper edge of bucket ``i`` is ``LATENCY_MIN_MS * ratio**i``: percentiles are exact to 2%."""

LATENCY_MIN_MS = 0.001
"""Everything at or below 1 us lands in bucket 0."""

_LOG_RATIO = math.log(LATENCY_BUCKET_RATIO)


def latency_bucket(ms: float) -> int:
    """Index of the bucket holding ``ms`` (its upper edge is >= ``ms``)."""
    if ms <= LATENCY_MIN_MS:
        return 0
    return int(math.ceil(math.log(ms / LATENCY_MIN_MS) / _LOG_RATIO - 1e-9))


def bucket_upper_ms(index: int) -> float:
    """Upper edge of bucket ``index`` in milliseconds."""
    return LATENCY_MIN_MS * LATENCY_BUCKET_RATIO**index


class LatencyHistogram:
    """Cumulative latency counts per label, in log buckets (2% wide), since it was made.

    Counts only ever grow, so a reader that polls :meth:`counts` twice and subtracts
    (:func:`histogram_diff`) gets the distribution of exactly the batches in between: warm-up
    never leaks into a steady-state figure, and no sample is lost to a bounded buffer. Written by
    one lane thread; read (copied) from the status thread.
    """

    def __init__(self, labels: Iterable[str]) -> None:
        self._counts: dict[str, dict[int, int]] = {label: {} for label in labels}
        if not self._counts:
            raise ValueError("LatencyHistogram needs at least one label")
        self._lock = threading.Lock()

    def record(self, label: str, ms: float) -> None:
        """Count one batch of ``label`` that took ``ms`` milliseconds."""
        buckets = self._counts[label]  # KeyError for an undeclared label: a bug, not data
        b = latency_bucket(ms)
        with self._lock:
            buckets[b] = buckets.get(b, 0) + 1

    def counts(self) -> dict[str, dict[str, int]]:
        """``{label: {bucket index as str: count}}`` (str keys: status travels as msgpack maps)."""
        with self._lock:
            return {label: {str(b): n for b, n in sorted(c.items())} for label, c in self._counts.items()}
