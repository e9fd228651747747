"""The rollout `dvla bench swimlane` runs: dvla's own rollout, plus two figures only the benchmark
reads: a histogram of its inference batch latency split by weight swaps (the role itself reports
plain p50/p99), and the CPU seconds its sim lane spends inside ``env.step`` (resets included:
what a step costs the simulator itself, apart from acting, recording and hand-offs). `python -m benchmarks.swimlane_probe --config FILE` is started in place of
`python -m dvla.roles.rollout` by :class:`ProbeWrapper`.

The dual pool promises that a swap costs inference nothing; two splits test it. "swap": the
batch *started* while a staging write was under way, or is the first on newly swapped weights;
decided before the batch runs, so its duration cannot pick the label. "overlap": a write
overlapped the batch or the one before; a long batch overlaps a write more often than a short
one whatever the write costs, so that split leans towards slow batches (length-biased) and is
kept as a second figure.
"""

from __future__ import annotations

import time
from typing import Any, Callable

from dvla.orchestrator.process import CommandWrapper, Process
from dvla.roles.rollout import Actions, Rollout
from dvla.roles.runtime import main

from .stats import LatencyHistogram

ROLLOUT_MODULE, PROBE_MODULE = "dvla.roles.rollout", "benchmarks.swimlane_probe"


class ProbedRollout(Rollout):
    """A rollout whose status ``extra`` adds ``infer_latency_counts`` (cumulative bucket counts per
    label: ``swap``/``no_swap``, ``overlap``/``no_overlap``; diff two readings) and
    ``env_step_cpu_s``."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.infer_latency = LatencyHistogram(("swap", "no_swap", "overlap", "no_overlap"))
        self._touched_before = False  # a staging write overlapped the previous inference batch
        self.step_cpu_s = 0.0
        for g in self.groups:
            g.envs.step_wait = self._timed(g.envs.step_wait)

    def _timed(self, step_wait: Callable[[], Any]) -> Callable[[], Any]:
        def timed() -> Any:
            t0 = time.thread_time()  # the sim lane's own CPU clock (envs stepped in this process)
            try:
                return step_wait()
            finally:
                self.step_cpu_s += time.thread_time() - t0
        return timed

    def _act(self, gid: int) -> Actions:
        # held.seq is odd while a staging write is in progress and bumped at its start and end
        seq0, swaps0 = self.pool.held.seq, self.pool.swaps
        t0 = time.perf_counter()
        out = super()._act(gid)
        ms = (time.perf_counter() - t0) * 1e3
        swapped = self.pool.swaps != swaps0
        seq1 = self.pool.held.seq
        self.infer_latency.record("swap" if swapped or seq0 % 2 == 1 else "no_swap", ms)
        touched = swapped or seq1 != seq0 or seq1 % 2 == 1
        self.infer_latency.record("overlap" if touched or self._touched_before else "no_overlap", ms)
        self._touched_before = touched
        return out

    def status_extra(self) -> dict[str, Any]:
        extra = super().status_extra()
        # with simulator workers the steps' CPU is theirs (the sim lane only waits for them)
        step_cpu = sum(w["cpu_s"] for w in extra["sim_workers"]) if extra["sim_workers"] else self.step_cpu_s
        return {**extra, "infer_latency_counts": self.infer_latency.counts(), "env_step_cpu_s": step_cpu}


class ProbeWrapper(CommandWrapper):
    """Starts every rollout of a local run as :class:`ProbedRollout` (set as ``Up.launcher.wrap``)."""

    def __call__(self, proc: Process, argv: list[str]) -> list[str]:
        return [PROBE_MODULE if a == ROLLOUT_MODULE else a for a in argv]


if __name__ == "__main__":
    raise SystemExit(main(ProbedRollout))
