"""The benchmarks' one percentile definition (nearest rank), on samples and on counts."""

from __future__ import annotations

import pytest

from benchmarks.stats import percentile, weighted_percentile


def test_nearest_rank_on_samples() -> None:
    values = [5.0, 1.0, 4.0, 2.0, 3.0]  # any order
    assert percentile(values, 0) == 1.0
    assert percentile(values, 50) == 3.0
    assert percentile(values, 60) == 3.0
    assert percentile(values, 61) == 4.0
    assert percentile(values, 100) == 5.0
    assert percentile(list(range(1, 101)), 99) == 99


def test_counts_agree_with_the_samples_they_count() -> None:
    counts = {0: 90, 1: 9, 7: 1}
    samples = [v for v, n in counts.items() for _ in range(n)]
    for q in (1, 50, 90, 91, 99, 99.5, 100):
        assert weighted_percentile(counts, q) == percentile(samples, q), q
    assert weighted_percentile(counts, 99) == 1
    assert weighted_percentile(counts, 99.5) == 7


def test_rejects_no_samples_and_bad_q() -> None:
    with pytest.raises(ValueError):
        percentile([], 50)
    with pytest.raises(ValueError):
        weighted_percentile({1: 1}, 101)
