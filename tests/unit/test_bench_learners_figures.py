"""`dvla bench learners`' figures from what its ranks measured: the formulas fed known rounds (no
rank process, no clock), so that what the bench reports is checked exactly whatever this
machine's speed; the figures themselves are `dvla bench learners`' to report."""

from __future__ import annotations

import types

import pytest

from benchmarks.learners import LearnersBenchConfig, _rate, _summary, _timed_group_class


def _report(wall_s: float, update_s: list[float], comm_s: list[float], scalar_sum_s: float) -> dict:
    return {"wall_s": wall_s, "update_s": update_s, "comm_s": comm_s, "scalar_sum_s": scalar_sum_s,
            "grad_bytes": 1000, "allreduces": 4}


def test_summary_of_two_ranks_over_two_rounds() -> None:
    cfg = LearnersBenchConfig(batch=32, updates=4, round_updates=2)
    rounds = [
        {0: _report(2.0, [0.9, 1.0], [0.2, 0.3], 0.01), 1: _report(2.5, [1.1, 1.2], [0.1, 0.2], 0.03)},
        {0: _report(1.5, [0.7, 0.8], [0.1, 0.1], 0.02), 1: _report(1.0, [0.5, 0.6], [0.05, 0.15], 0.02)},
    ]
    final = {r: {"checksum": "abc", "parameters": 10, "pid": 100 + r} for r in (0, 1)}
    s = _summary(cfg, 2, rounds, final)
    assert s["wall_s"] == 2.5 + 1.5  # the slowest rank of each round
    assert s["samples_per_s"] == 2 * 32 * 4 / 4.0
    assert s["round_samples_per_s"] == [_rate(cfg, 2, rnd) for rnd in rounds] == [2 * 32 * 2 / 2.5, 2 * 32 * 2 / 1.5]
    assert s["update_s_median"] == pytest.approx((0.8 + 0.9) / 2)  # over every update of every rank
    assert s["allreduce_s_per_update"] == pytest.approx(1.2 / 8)
    assert s["comm_share"] == pytest.approx(1.2 / 6.8)  # all-reduce seconds over update seconds
    assert s["scalar_sum_s_per_update"] == pytest.approx(0.08 / 8)
    assert (s["grad_bytes_per_update"], s["allreduces_per_update"]) == (500.0, 2.0)
    assert s["params_identical"] is True
    assert s["per_rank"][1] == {"rank": 1, "update_s": [1.1, 1.2, 0.5, 0.6], "comm_s": [0.1, 0.2, 0.05, 0.15],
                                "checksum": "abc", "parameters": 10, "pid": 101}
    final[1]["checksum"] = "abd"
    assert _summary(cfg, 2, rounds, final)["params_identical"] is False


def test_comm_seconds_are_the_union_of_the_all_reduces_in_flight() -> None:
    group = types.SimpleNamespace(comm=[(0.5, 1.5, 20), (0.0, 1.0, 10), (3.0, 3.25, 30), (3.1, 3.2, 5)])
    busy, nbytes, ops = _timed_group_class().take_comm(group)
    assert busy == pytest.approx(1.5 + 0.25) and (nbytes, ops) == (65, 4)
    assert group.comm == []  # taken
