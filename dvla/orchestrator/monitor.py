"""The orchestrator's view of a running cluster: status collection, eval results, metrics files
and stop conditions. Collects first, renders elsewhere (view.py)."""

from __future__ import annotations

import csv
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..config import BudgetConfig
from ..fabric import Fabric
from ..fabric.messages import EvalResult, RoleStatus
from ..stats import wilson_interval
from .evaljoin import EvalJoin
from .tensorboard import TensorBoardLog
from .view import latest_version
from .wandb_log import WandbLog


@dataclass
class EvalPoint:
    time_s: float
    version: int
    env_steps: int
    success_once: float
    success_at_end: float
    return_mean: float
    episodes: int
    #: 95 % (Wilson) interval of success_once
    success_low: float = 0.0
    success_high: float = 1.0


@dataclass
class Snapshot:
    """One collection round: every role's status (None for a role that did not answer)."""

    time_s: float
    statuses: dict[str, RoleStatus]
    env_steps: int
    #: the learner's env steps per second over the last few seconds
    steps_per_s: float
    version: int


@dataclass
class Monitor:
    fabric: Fabric
    run_dir: Path
    budget: BudgetConfig
    #: joins the blocks of the run's evaluators into whole evaluations
    eval_join: EvalJoin = field(default_factory=lambda: EvalJoin(1, 1))
    t0: float = field(default_factory=time.monotonic)
    evals: list[EvalPoint] = field(default_factory=list)
    last: Snapshot | None = None
    first_step_s: float | None = None
    success_at_s: float | None = None
    success_at_steps: int | None = None
    _rate_mark: tuple[float, int] | None = None
    _rate: float = 0.0
    #: W&B copy of the TensorBoard scalars (None: `logging.wandb` not set); never waited on
    wandb: WandbLog | None = None

    def __post_init__(self) -> None:
        # A resumed run appends to its files, its clock continuing from their last row.
        self.t0 -= _last_time(self.run_dir / "metrics.csv")
        self._metrics, self._mw = _append_csv(self.run_dir / "metrics.csv", [
            "time_s", "env_steps", "produced_steps", "steps_per_s", "version", "policy_lag_mean", "roles_up",
            # rollouts' per-step inference latency, the slowest rollout's percentiles
            "infer_ms_p50", "infer_ms_p99"])
        self._evals, self._ew = _append_csv(self.run_dir / "evals.csv", [
            "time_s", "version", "env_steps", "success_once", "success_at_end", "return_mean", "episodes",
            "success_low", "success_high",
            # "all": the whole evaluation; else one task's episodes (LIBERO), on rows of their own
            "task"])
        self._inbox = self.fabric.subscribe_ctrl(self.fabric.keys.eval_all(), 64, EvalResult)
        self.tensorboard = TensorBoardLog(self.run_dir)

    def now(self) -> float:
        return time.monotonic() - self.t0

    def collect(self) -> Snapshot:
        replies = self.fabric.query(self.fabric.keys.status_all(), expect=RoleStatus, timeout=1.5, droppable=True)
        statuses = {msg.name: msg for _sender, msg in replies}
        actors = sorted((s for s in statuses.values() if s.kind == "actor"), key=lambda s: s.name)
        env_steps = max((s.env_steps for s in actors), default=0)  # every rank reports the group's
        produced = sum(s.env_steps for s in statuses.values() if s.kind == "rollout")
        if self.last is not None:
            env_steps = max(env_steps, self.last.env_steps)  # a restarting actor answers late
        version = latest_version(statuses)
        t = self.now()
        if self.first_step_s is None and produced > 0:
            self.first_step_s = t
        if self._rate_mark is None:
            self._rate_mark = (t, env_steps)
        elif t - self._rate_mark[0] >= 3.0:
            self._rate = (env_steps - self._rate_mark[1]) / (t - self._rate_mark[0])
            self._rate_mark = (t, env_steps)
        snap = Snapshot(t, statuses, env_steps, self._rate, version)
        lag = actors[0].extra.get("policy_lag_mean", 0.0) if actors else 0.0
        rollouts = [s.extra for s in statuses.values() if s.kind == "rollout"]
        p50 = max((float(e.get("infer_ms_p50", 0.0)) for e in rollouts), default=0.0)
        p99 = max((float(e.get("infer_ms_p99", 0.0)) for e in rollouts), default=0.0)
        self._mw.writerow([f"{t:.2f}", env_steps, produced, f"{self._rate:.1f}", version, f"{lag:.2f}", len(statuses),
                           f"{p50:.3f}", f"{p99:.3f}"])
        self._metrics.flush()
        scalars = self.tensorboard.statuses(env_steps, statuses, self._rate, produced)
        if self.wandb is not None:
            self.wandb.log(env_steps, scalars)
        self.last = snap
        self._drain_evals()
        return snap

    def _drain_evals(self) -> None:
        while (got := self._inbox.get_nowait()) is not None:
            ev = self.eval_join.add(got[1])
            if ev is None:
                continue
            steps = self.last.env_steps if self.last else 0
            p = EvalPoint(self.now(), ev.policy_version, steps, ev.success_once, ev.success_at_end, ev.return_mean,
                          ev.episodes, ev.success_low, ev.success_high)
            self.evals.append(p)
            self._ew.writerow([f"{p.time_s:.2f}", p.version, p.env_steps, f"{p.success_once:.4f}",
                               f"{p.success_at_end:.4f}", f"{p.return_mean:.4f}", p.episodes,
                               f"{p.success_low:.4f}", f"{p.success_high:.4f}", "all"])
            for task, n in ev.task_episodes.items():
                ok = ev.task_successes[task]
                low, high = wilson_interval(ok, n)
                self._ew.writerow([f"{p.time_s:.2f}", p.version, p.env_steps, f"{ok / max(n, 1):.4f}", "", "", n,
                                   f"{low:.4f}", f"{high:.4f}", task])
            self._evals.flush()
            scalars = self.tensorboard.evaluation(p.env_steps, ev)
            if self.wandb is not None:
                self.wandb.log(p.env_steps, scalars)
            if self.success_at_s is None and self.success_reached():
                self.success_at_s = p.time_s
                self.success_at_steps = p.env_steps

    def success_reached(self) -> bool:
        b = self.budget
        if b.until_success is None or len(self.evals) < b.consecutive:
            return False
        stat = "success_low" if b.success_on == "lower_bound" else "success_once"
        return all(getattr(e, stat) >= b.until_success for e in self.evals[-b.consecutive:])

    def stop_reason(self) -> str | None:
        """Why the run should stop now, or None."""
        b = self.budget
        if self.success_reached():
            return "success"
        if b.max_env_steps is not None and self.last is not None and self.last.env_steps >= b.max_env_steps:
            return "max_env_steps"
        if b.max_wall_s is not None and self.now() >= b.max_wall_s:
            return "max_wall_s"
        return None

    def close(self) -> None:
        self._metrics.close()
        self._evals.close()
        self.tensorboard.close()

    def result(self) -> dict[str, Any]:
        last, first = self.last, self.first_step_s
        end = self.success_at_s if self.success_at_s is not None else self.now()
        train_s = (end - first) if first is not None else None
        steps = self.success_at_steps if self.success_at_steps is not None else (last.env_steps if last else 0)
        return {
            "startup_s": first,
            "train_s": train_s,
            "env_steps": steps,
            "train_steps_per_s": (steps / train_s) if train_s else None,
            "final_env_steps": last.env_steps if last else 0,
            "final_version": last.version if last else 0,
            "evals": [e.__dict__ for e in self.evals],
            # windows some evaluator skipped, and blocks naming another number of evaluators
            "evals_incomplete": self.eval_join.incomplete,
            "evals_refused": self.eval_join.refused,
            "success_reached": self.success_reached() or self.success_at_s is not None,
        }


def _append_csv(path: Path, header: list[str]) -> tuple[Any, Any]:
    """(file, csv writer) appending to `path`; the header is written when the file is new."""
    new = not path.exists() or path.stat().st_size == 0
    f = open(path, "a", newline="")
    w = csv.writer(f)
    if new:
        w.writerow(header)
    return f, w


def _last_time(path: Path) -> float:
    """time_s of the last row of an existing metrics file (0.0 when there is none)."""
    try:
        last = path.read_text().strip().splitlines()[-1].split(",")[0]
        return float(last)
    except (OSError, IndexError, ValueError):
        return 0.0
