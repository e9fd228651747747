"""Evaluator role: plays deterministic episodes with the latest weights on its own envs and
publishes the success rates, so evaluation never stalls training.

Lanes:
- ``sync``: verified weight versions from the parent (as a rollout does).
- ``eval``: whenever the newest version enters a new window of `every_versions` versions
            (version // every_versions grows), loads it and plays its block of the evaluation's
            `episodes` episodes (ManiSkill's `success_once` and `success_at_end`), each to the
            time limit, or to the env's termination (success) with `full_episodes: false`.

Several evaluators split every evaluation into contiguous blocks of episodes, which the
orchestrator joins per window (docs/evaluation.md): an evaluator that missed a version
evaluates the next one of the same window.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import torch

from ..config import RoleConfig, resolve_device
from ..fabric import Fabric
from ..fabric.messages import EvalResult
from ..learn import make_env_group, make_policy, run_eval_episodes
from ..replication import HeldWeights, ParamLayout, unflatten_into
from .runtime import main
from .swimlane import LaneContext, Swimlane
from .weightsync import WeightSync

log = logging.getLogger("dvla.evaluator")


class Evaluator:
    def __init__(self, cfg: RoleConfig, fabric: Fabric) -> None:
        self.cfg = cfg
        self.fabric = fabric
        task = cfg.task
        self.shard, self.shards = cfg.eval_shard
        first, end = eval_block(task.eval.episodes, self.shard, self.shards)
        #: this evaluator's episodes: [first, first + n_episodes) of every evaluation
        self.first_episode, self.n_episodes = first, end - first
        # one ManiSkill scene on a CUDA node (ManiSkill's rule), one-env simulators elsewhere
        self.group = make_env_group(task, min(task.eval.envs, self.n_episodes), cfg.eval_seed + first,
                                    ignore_terminations=task.eval.full_episodes, batching="auto")
        self.device = torch.device(resolve_device(task.eval_device))
        policy = make_policy(task.policy, self.group.obs_spec, self.group.act_dim, **task.policy_kwargs)
        self.policy = policy.to(self.device).eval()
        self.layout = ParamLayout.from_state_dict(self.policy)
        self.policy_version = -1
        self.env_steps = 0
        #: sync -> eval: the newest verified version (replaced, not queued) and a flag that it changed
        self.held = HeldWeights(self.layout)
        self._new = threading.Event()
        self.results: list[dict[str, float]] = []

    def build(self, sl: Swimlane) -> None:
        self.weights = WeightSync.of_role(  # verified versions from the parent -> held
            self.cfg, self.fabric, self.held, lambda _v: self._new.set(), policy=self.policy)
        sl.lane("sync", self.weights.run)
        sl.lane("eval", self._eval)

    def _eval(self, ctx: LaneContext) -> None:
        every = self.cfg.task.eval.every_versions
        window = -1  # the window of the last evaluation (version // every)
        while ctx.running:
            with ctx.waiting():
                if not self._new.wait(0.1):
                    continue
            self._new.clear()
            if self.held.version // every <= window:
                continue
            with ctx.busy():
                with self.held.lock:  # the sync lane swaps in a newer version only after this copy
                    version = self.held.version
                    unflatten_into(self.held.active, self.policy, self.layout)
                self.policy_version = version
                t0 = time.perf_counter()
                res = run_eval_episodes(
                    self.policy, self.cfg.task, self.n_episodes, self.cfg.eval_seed + self.first_episode, self.device,
                    group=self.group, stop=ctx.stop,
                )
                if res is None:  # stopped part-way: nothing to report
                    break
                self.env_steps += int(res["env_steps"])
                window = version // every
            per_task = res.get("per_task", {})
            msg = EvalResult(
                sender=self.cfg.name, policy_version=version, episodes=int(res["episodes"]),
                success_once=float(res["success_once"]), success_at_end=float(res["success_at_end"]),
                return_mean=float(res["return_mean"]), success_low=float(res["success_once_low"]),
                success_high=float(res["success_once_high"]), shard=self.shard, shards=self.shards,
                task_episodes={k: n for k, (n, _ok) in per_task.items()},
                task_successes={k: ok for k, (_n, ok) in per_task.items()},
                time_ns=time.time_ns(),
            )
            self.fabric.publish_ctrl(self.fabric.keys.eval(self.cfg.name), msg)
            # the scalars (status's last_eval); per_task and failed_episodes are not
            self.results.append({"version": version, **{k: float(v) for k, v in res.items()
                                                         if isinstance(v, (int, float))}})
            log.info("eval v%d: success_once %.2f [%.2f, %.2f] success_at_end %.2f (%d episodes, %.1f s)", version,
                     res["success_once"], res["success_once_low"], res["success_once_high"], res["success_at_end"],
                     res["episodes"], time.perf_counter() - t0)
            ctx.count()

    def status_extra(self) -> dict[str, Any]:
        last = self.results[-1] if self.results else {}
        return {"evals": len(self.results), "last_eval": last, "shard": [self.shard, self.shards],
                "weights": self.weights.status()}

    def close(self) -> None:
        self.group.close()


def eval_block(episodes: int, shard: int, shards: int) -> tuple[int, int]:
    """[first, end) of the episodes evaluator `shard` of `shards` plays in every evaluation:
    contiguous blocks as equal as can be, every block at least one episode."""
    if not 0 <= shard < shards or shards > episodes:
        raise ValueError(f"evaluator {shard} of {shards} cannot take a block of {episodes} episodes")
    return shard * episodes // shards, (shard + 1) * episodes // shards


if __name__ == "__main__":
    raise SystemExit(main(Evaluator))
