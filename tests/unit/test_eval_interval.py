"""The 95 % Wilson interval reported with every evaluation's success rate."""

from __future__ import annotations

import pytest

from dvla.learn.envs import wilson_interval


@pytest.mark.parametrize("k, n, low, high", [
    (8, 10, 0.4902, 0.9433),
    (16, 16, 0.8064, 1.0),  # all 16 succeed: the true rate may still be as low as ~0.81
    (0, 16, 0.0, 0.1936),
    (40, 50, 0.6696, 0.8876),
])
def test_known_values(k, n, low, high):
    lo, hi = wilson_interval(k, n)
    assert lo == pytest.approx(low, abs=1e-4) and hi == pytest.approx(high, abs=1e-4)


def test_bounds_and_width():
    assert wilson_interval(0, 0) == (0.0, 1.0)
    for n in (1, 5, 16, 50, 200):
        for k in range(n + 1):
            lo, hi = wilson_interval(k, n)
            assert 0.0 <= lo <= k / n <= hi <= 1.0
    # more episodes, a narrower interval at the same rate
    assert (lambda a, b: a[1] - a[0] > b[1] - b[0])(wilson_interval(13, 16), wilson_interval(40, 50))
