"""Evaluator role: plays deterministic episodes with the latest weights on its own envs and
publishes the success rates, so evaluation never stalls training.

Lanes:
- ``sync``: verified weight versions from the parent (as a rollout does).
- ``eval``: whenever `every_versions` new versions have arrived, loads the newest one and plays
            `episodes` episodes (ManiSkill's `success_once` and `success_at_end`).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import numpy as np

from ..config import RoleConfig
from ..fabric import Fabric
from ..fabric.messages import EvalResult
from ..learn import EnvGroup, make_policy, run_eval_episodes
from ..replication import ParamLayout, unflatten_into
from .runtime import main
from .swimlane import LaneContext, Swimlane
from .weightsync import WeightSync

log = logging.getLogger("dvla.evaluator")


class Evaluator:
    def __init__(self, cfg: RoleConfig, fabric: Fabric) -> None:
        self.cfg = cfg
        self.fabric = fabric
        task = cfg.task
        self.group = EnvGroup(task, min(8, task.eval.episodes), cfg.seed + task.eval.seed_offset, ignore_terminations=True)
        self.policy = make_policy(task.policy, self.group.obs_spec, self.group.act_dim, **task.policy_kwargs).eval()
        self.layout = ParamLayout.from_state_dict(self.policy.state_dict())
        self.policy_version = -1
        self.env_steps = 0
        #: sync -> eval: the newest verified version (a copy) and its number; replaced, not queued
        self._latest = np.empty(0, np.float32)
        self._latest_version = -1
        self._lock = threading.Lock()
        self._new = threading.Event()
        self.results: list[dict[str, float]] = []

    def build(self, sl: Swimlane) -> None:
        self.weights = WeightSync(  # verified versions from the parent
            self.fabric, self.layout, (self.cfg.parent, *self.cfg.ancestors[1:]), self._on_version
        )
        sl.lane("sync", self._sync)
        sl.lane("eval", self._eval)

    def _on_version(self, version: int, flat: np.ndarray) -> None:
        with self._lock:
            self._latest, self._latest_version = flat.copy(), version
        self._new.set()

    def _sync(self, ctx: LaneContext) -> None:
        while ctx.running:
            self.weights.step(ctx)

    def _eval(self, ctx: LaneContext) -> None:
        every = self.cfg.task.eval.every_versions
        evaluated = -(10**9)
        while ctx.running:
            with ctx.waiting():
                if not self._new.wait(0.1):
                    continue
            with self._lock:
                version, flat = self._latest_version, self._latest
                self._new.clear()
            if version < evaluated + every:
                continue
            with ctx.busy():
                unflatten_into(flat, self.policy, self.layout)
                self.policy_version = version
                t0 = time.perf_counter()
                res = run_eval_episodes(
                    self.policy, self.cfg.task, self.cfg.task.eval.episodes,
                    self.cfg.seed + self.cfg.task.eval.seed_offset, "cpu", group=self.group,
                )
                self.env_steps += int(res["env_steps"])
                evaluated = version
            msg = EvalResult(
                sender=self.cfg.name, policy_version=version, episodes=int(res["episodes"]),
                success_once=float(res["success_once"]), success_at_end=float(res["success_at_end"]),
                return_mean=float(res["return_mean"]), success_low=float(res["success_once_low"]),
                success_high=float(res["success_once_high"]), time_ns=time.time_ns(),
            )
            self.fabric.publish_ctrl(self.fabric.keys.eval(self.cfg.name), msg)
            self.results.append({"version": version, **{k: float(v) for k, v in res.items()}})
            log.info("eval v%d: success_once %.2f [%.2f, %.2f] success_at_end %.2f (%d episodes, %.1f s)", version,
                     res["success_once"], res["success_once_low"], res["success_once_high"], res["success_at_end"],
                     res["episodes"], time.perf_counter() - t0)
            ctx.count()

    def status_extra(self) -> dict[str, Any]:
        last = self.results[-1] if self.results else {}
        return {"evals": len(self.results), "last_eval": last, "weights": self.weights.status()}

    def close(self) -> None:
        self.group.close()


if __name__ == "__main__":
    raise SystemExit(main(Evaluator))
