"""The benchmarks' one percentile definition (nearest rank), on samples and on counts."""

from __future__ import annotations

import pytest

from benchmarks.stats import histogram_diff, histogram_percentile, percentile, weighted_percentile
from dvla.roles.swimlane import LatencyHistogram, latency_bucket


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


def test_histogram_window_between_two_readings() -> None:
    h = LatencyHistogram(("swap", "no_swap"))
    for _ in range(50):
        h.record("no_swap", 100.0)  # warm-up: slow
    before = h.counts()
    for i in range(1, 101):
        h.record("no_swap", float(i) / 10)  # 0.1 .. 10.0 ms
    h.record("swap", 2.0)
    after = h.counts()
    window = histogram_diff(after["no_swap"], before["no_swap"])
    assert sum(window.values()) == 100
    assert histogram_percentile(window, 50) == pytest.approx(5.0, rel=0.021)
    assert histogram_percentile(window, 99) == pytest.approx(9.9, rel=0.021)
    assert histogram_percentile(window, 100) == pytest.approx(10.0, rel=0.021)
    # Without the diff the warm-up dominates the tail.
    assert histogram_percentile(after["no_swap"], 99) == pytest.approx(100.0, rel=0.021)
    assert histogram_diff(after["swap"], before["swap"]) == {str(latency_bucket(2.0)): 1}
    assert histogram_percentile({}, 99) == 0.0
    with pytest.raises(ValueError):
        histogram_diff(before["no_swap"], after["no_swap"])  # counts never go down
