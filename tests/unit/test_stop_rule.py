"""The stop rule's pass probabilities (dvla/stats.py), the figures of docs/evaluation.md."""

import math

import pytest

from dvla.stats import pass_probability, successes_to_pass, wilson_interval


def test_successes_to_pass_on_the_rate_and_on_the_lower_bound():
    assert successes_to_pass(16, 0.8) == 13
    assert successes_to_pass(64, 0.8) == 52
    k = successes_to_pass(128, 0.75, "lower_bound")
    assert k == 106
    assert wilson_interval(k - 1, 128)[0] < 0.75 <= wilson_interval(k, 128)[0]


def test_a_bound_no_count_reaches_is_none_and_never_passes():
    assert wilson_interval(4, 4)[0] < 0.9
    assert successes_to_pass(4, 0.9, "lower_bound") is None
    assert pass_probability(1.0, 4, 0.9, success_on="lower_bound") == 0.0


def test_pass_probability_is_the_binomial_tail_to_the_power_of_consecutive():
    assert pass_probability(0.3, 1, 1.0) == pytest.approx(0.3)
    tail = sum(math.comb(16, i) * 0.85 ** i * 0.15 ** (16 - i) for i in range(13, 17))
    assert pass_probability(0.85, 16, 0.8) == pytest.approx(tail)
    assert pass_probability(0.85, 16, 0.8, consecutive=3) == pytest.approx(tail ** 3)
    assert pass_probability(0.0, 16, 0.8) == 0.0
    assert pass_probability(1.0, 16, 0.8) == pytest.approx(1.0)


def test_the_shipped_rule_passes_a_075_policy_rarely_and_a_090_one_almost_always():
    assert pass_probability(0.75, 128, 0.75, 1, "lower_bound") < 0.03
    assert pass_probability(0.90, 128, 0.75, 1, "lower_bound") > 0.99


def test_an_unknown_comparison_is_refused():
    with pytest.raises(ValueError, match="success_on"):
        successes_to_pass(16, 0.8, "mean")
