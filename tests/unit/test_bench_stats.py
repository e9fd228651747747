"""The benchmarks' one percentile definition (nearest rank), on samples and on counts."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time

import pytest

from benchmarks.stats import (
    LATENCY_BUCKET_RATIO,
    LatencyHistogram,
    bucket_upper_ms,
    histogram_diff,
    histogram_percentile,
    latency_bucket,
    percentile,
    process_cpu_s,
    weighted_percentile,
)


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


# -- latency histograms -------------------------------------------------------------------------


def test_latency_bucket_edges_bound_their_values() -> None:
    for ms in (0.0, 0.0005, 0.001, 0.0123, 0.5, 1.0, 1.7, 33.3, 2500.0):
        b = latency_bucket(ms)
        assert bucket_upper_ms(b) >= ms * (1 - 1e-9)
        if b > 0:
            assert bucket_upper_ms(b - 1) < ms
    assert bucket_upper_ms(latency_bucket(10.0)) <= 10.0 * LATENCY_BUCKET_RATIO


def test_latency_histogram_counts_per_label() -> None:
    h = LatencyHistogram(("swap", "no_swap"))
    for ms in (0.1, 0.1, 5.0):
        h.record("no_swap", ms)
    h.record("swap", 2.0)
    assert h.counts() == {"swap": {str(latency_bucket(2.0)): 1},
                          "no_swap": {str(latency_bucket(0.1)): 2, str(latency_bucket(5.0)): 1}}
    with pytest.raises(KeyError):
        h.record("other", 1.0)
    with pytest.raises(ValueError):
        LatencyHistogram(())


def test_latency_histogram_counts_every_sample_from_a_thread_while_read() -> None:
    h = LatencyHistogram(("no_swap",))
    n = 20_000

    def writer() -> None:
        for i in range(n):
            h.record("no_swap", 0.01 * (i % 100 + 1))

    t = threading.Thread(target=writer)
    t.start()
    while t.is_alive():
        json.dumps(h.counts())  # a status thread reading concurrently
    t.join()
    assert sum(h.counts()["no_swap"].values()) == n


def test_process_cpu_is_read_below_the_clock_tick() -> None:
    """A process's CPU is read from its own CPU clock, to the nanosecond, not from /proc's 10 ms
    ticks (which lag it): read for this process, it lies between this process's own clock read
    just before and just after; a child's reads as it runs, and nothing once it is gone."""
    t0 = time.process_time()
    mine = process_cpu_s(os.getpid())
    t1 = time.process_time()
    assert mine is not None and t0 <= mine <= t1, (t0, mine, t1)  # the same clock: no tick count behind it
    spin = "import time\nt = time.thread_time()\nwhile time.thread_time() - t < 0.004: pass\nprint(flush=True)\ntime.sleep(30)"
    child = subprocess.Popen([sys.executable, "-S", "-c", spin], stdout=subprocess.PIPE)
    try:
        before = process_cpu_s(child.pid)
        assert child.stdout is not None and child.stdout.readline() == b"\n"
        after = process_cpu_s(child.pid)
        assert before is not None and after is not None and before <= after, (before, after)  # its clock, as it runs
    finally:
        child.kill()
        child.wait()
    assert process_cpu_s(child.pid) is None
