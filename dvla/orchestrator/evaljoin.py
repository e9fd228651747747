"""One evaluation from the blocks of several evaluators (``count: N``): the blocks of one window of
``every_versions`` versions join into one :class:`EvalResult`; a window some evaluator skipped is
dropped, and counted, once a later one completes (docs/evaluation.md).
"""

from __future__ import annotations

import logging
from dataclasses import replace

from ..fabric.messages import EvalResult
from ..stats import wilson_interval

log = logging.getLogger("dvla.orchestrator")

#: windows waiting for blocks; older ones are dropped (counted as incomplete)
MAX_PENDING = 8


class EvalJoin:
    """Blocks of `shards` evaluators in, whole evaluations out."""

    def __init__(self, shards: int, every_versions: int) -> None:
        if shards < 1 or every_versions < 1:
            raise ValueError(f"shards ({shards}) and every_versions ({every_versions}) must be >= 1")
        self.shards = shards
        self.every = every_versions
        #: window -> shard -> its block
        self._pending: dict[int, dict[int, EvalResult]] = {}
        #: windows dropped before every block arrived
        self.incomplete = 0
        #: blocks refused: they name another number of evaluators than the run has
        self.refused = 0

    def add(self, ev: EvalResult) -> EvalResult | None:
        """The whole evaluation once `ev` completes its window, else None."""
        if ev.shards != self.shards:
            self.refused += 1
            log.warning("eval result of %s refused: it is block %d of %d, the run has %d evaluators",
                        ev.sender, ev.shard, ev.shards, self.shards)
            return None
        if self.shards == 1:
            return ev
        window = ev.policy_version // self.every
        self._pending.setdefault(window, {})[ev.shard] = ev
        blocks = self._pending[window]
        if len(blocks) < self.shards:
            while len(self._pending) > MAX_PENDING:
                self._pending.pop(min(self._pending))
                self.incomplete += 1
            return None
        for w in [w for w in self._pending if w <= window]:
            self.incomplete += w != window
            del self._pending[w]
        return join_blocks(list(blocks.values()))


def join_blocks(blocks: list[EvalResult]) -> EvalResult:
    """One evaluation over every block's episodes (blocks of one window)."""
    episodes = sum(b.episodes for b in blocks)
    if episodes == 0:
        return replace(blocks[0], shard=0, shards=1)
    successes = sum(round(b.success_once * b.episodes) for b in blocks)
    low, high = wilson_interval(successes, episodes)
    tasks = sorted({t for b in blocks for t in b.task_episodes})
    return EvalResult(
        sender=blocks[0].sender, policy_version=min(b.policy_version for b in blocks), episodes=episodes,
        success_once=successes / episodes,
        success_at_end=sum(b.success_at_end * b.episodes for b in blocks) / episodes,
        return_mean=sum(b.return_mean * b.episodes for b in blocks) / episodes,
        success_low=low, success_high=high, shard=0, shards=1,
        task_episodes={t: sum(b.task_episodes.get(t, 0) for b in blocks) for t in tasks},
        task_successes={t: sum(b.task_successes.get(t, 0) for b in blocks) for t in tasks},
        time_ns=max(b.time_ns for b in blocks),
    )
