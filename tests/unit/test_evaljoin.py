"""Evaluations split over several evaluators: blocks, joining, the stop rule's statistic."""

from __future__ import annotations

from pathlib import Path

import pytest

from dvla.config import BudgetConfig
from dvla.fabric.codec import decode, encode
from dvla.fabric.errors import CodecError
from dvla.fabric.messages import EvalResult
from dvla.learn.envs import wilson_interval
from dvla.orchestrator.evaljoin import MAX_PENDING, EvalJoin, join_blocks
from dvla.orchestrator.monitor import EvalPoint, Monitor
from dvla.orchestrator.topology import TopologyError, parse_topology
from dvla.roles.evaluator import eval_block


def block(version: int, shard: int, shards: int, episodes: int, successes: int, ret: float = 1.0) -> EvalResult:
    low, high = wilson_interval(successes, episodes)
    return EvalResult(sender=f"evaluator-{shard}", policy_version=version, episodes=episodes,
                      success_once=successes / episodes, success_at_end=successes / episodes / 2,
                      return_mean=ret, success_low=low, success_high=high, shard=shard, shards=shards)


@pytest.mark.parametrize("episodes, shards", [(64, 1), (64, 2), (64, 3), (50, 4), (7, 7)])
def test_blocks_cover_every_episode_once(episodes, shards):
    blocks = [eval_block(episodes, i, shards) for i in range(shards)]
    assert blocks[0][0] == 0 and blocks[-1][1] == episodes
    assert all(a[1] == b[0] for a, b in zip(blocks, blocks[1:]))  # contiguous, no overlap
    sizes = [e - f for f, e in blocks]
    assert min(sizes) >= 1 and max(sizes) - min(sizes) <= 1


def test_a_block_needs_an_episode():
    with pytest.raises(ValueError, match="cannot take a block"):
        eval_block(3, 0, 4)


def test_one_evaluator_passes_through():
    j = EvalJoin(1, 4)
    ev = block(5, 0, 1, 16, 12)
    assert j.add(ev) is ev


def test_blocks_of_one_window_join_into_one_evaluation():
    j = EvalJoin(2, 4)
    assert j.add(block(8, 0, 2, 32, 30, ret=2.0)) is None
    # the other evaluator missed version 8 and played 9: the same window
    whole = j.add(block(9, 1, 2, 32, 22, ret=4.0))
    assert whole is not None
    assert whole.episodes == 64 and whole.success_once == pytest.approx(52 / 64)
    assert (whole.success_low, whole.success_high) == pytest.approx(wilson_interval(52, 64))
    assert whole.return_mean == pytest.approx(3.0)
    assert whole.success_at_end == pytest.approx((15 + 11) / 64)
    assert whole.policy_version == 8 and (whole.shard, whole.shards) == (0, 1)


def test_skipped_windows_are_dropped_and_counted():
    j = EvalJoin(2, 4)
    assert j.add(block(4, 0, 2, 8, 4)) is None  # shard 1 never evaluates window 1
    assert j.add(block(8, 1, 2, 8, 4)) is None
    assert j.add(block(8, 0, 2, 8, 8)) is not None  # window 2 completes: window 1 is given up
    assert j.incomplete == 1
    assert j.add(block(4, 1, 2, 8, 4)) is None  # a straggler of a window already given up waits
    for v in range(12, 12 + 4 * (MAX_PENDING + 2), 4):  # windows 3 .. 12, shard 0 only
        assert j.add(block(v, 0, 2, 8, 4)) is None
    # 11 windows wait (the straggler's 1, then 3 .. 12): the oldest 3 beyond MAX_PENDING are dropped
    assert MAX_PENDING == 8 and j.incomplete == 1 + 3
    assert j.add(block(16, 1, 2, 8, 4)) is None  # window 4 was dropped: its late block completes nothing
    assert j.incomplete == 1 + 3 + 1  # ... and is the oldest beyond MAX_PENDING again
    assert j.add(block(20, 1, 2, 8, 4)) is not None  # window 5 is still held and completes
    assert j.incomplete == 5


def test_blocks_naming_another_shard_count_are_refused():
    j = EvalJoin(2, 4)
    assert j.add(block(4, 0, 3, 8, 4)) is None
    assert j.refused == 1


def test_eval_result_values_are_checked_on_the_wire():
    ev = block(4, 1, 2, 16, 12)
    assert decode(encode(ev), EvalResult) == ev
    for bad in (dict(shard=2, shards=2), dict(success_once=float("nan")), dict(success_low=1.5),
                dict(return_mean=float("inf"))):
        fields = {**ev.__dict__, **bad}
        with pytest.raises(CodecError):
            EvalResult(**fields).validate()


def test_stop_rule_on_the_lower_bound(tmp_path: Path):
    def reached(budget: BudgetConfig, points: list[tuple[float, float]]) -> bool:
        m = Monitor.__new__(Monitor)
        m.budget = budget
        m.evals = [EvalPoint(0.0, i, 0, rate, rate, 0.0, 64, success_low=low) for i, (rate, low) in enumerate(points)]
        return m.success_reached()

    rate = BudgetConfig(until_success=0.8, consecutive=1)
    bound = BudgetConfig(until_success=0.8, consecutive=1, success_on="lower_bound")
    assert reached(rate, [(0.81, 0.70)]) and not reached(bound, [(0.81, 0.70)])
    assert reached(bound, [(0.95, 0.86)])
    assert not reached(BudgetConfig(until_success=0.8, consecutive=2), [(0.9, 0.8), (0.7, 0.6)])


TOPO = """
run: t
task: {{env: PushCube-v1, eval: {{episodes: {episodes}}}, budget: {{max_env_steps: 1000}}}}
racks:
  - name: r
    nodes:
      - name: n
        host: localhost
        roles: [{{role: actor}}, {{role: rollout}}, {{role: evaluator, count: {count}}}]
"""


def test_more_evaluators_than_episodes_is_one_line():
    with pytest.raises(TopologyError, match="3 evaluators but task.eval.episodes is 2"):
        parse_topology(TOPO.format(episodes=2, count=3), "t.yaml")
    topo = parse_topology(TOPO.format(episodes=64, count=2), "t.yaml")
    assert topo.task.eval.episodes == 64


def test_bad_stop_statistic_names_the_key():
    text = TOPO.format(episodes=16, count=1).replace("max_env_steps: 1000", "max_env_steps: 1000, success_on: median")
    with pytest.raises(TopologyError, match="success_on"):
        parse_topology(text, "t.yaml")
