"""TensorBoard event files of a run (``runs/<run>/tb``), written by the orchestrator from what it
collects anyway (every role's status, every eval result), indexed by the learner's env steps.

Namespaces: ``train/`` (the actor's learning statistics, ``updates_refused_nonfinite``),
``rollout/`` (env steps/s, env steps produced, inference latency p50/p99), ``env/`` (training
episodes' success, return and length, weighted by episode counts), ``eval/`` (``success_once``
with ``success_low``/``success_high``, ``success_at_end``, ``return_mean``, version; per task for
LIBERO: ``eval/task/<task>/success`` and ``.../episodes``), ``time/`` (per role kind and lane:
busy and wait fractions, items/s), ``fabric/`` (per plane: bytes, rejected and dropped messages)
and ``weights/`` (published version, policy lag mean/p99, bytes per version). Both writers return
the scalars they wrote, so W&B (``wandb_log.py``) gets the same values without recomputing them.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

from ..fabric.messages import EvalResult, RoleStatus

#: counters of each plane summed into ``fabric/<plane>/<counter>``
FABRIC_COUNTERS = ("sent_bytes", "received_bytes", "rejected", "dropped")


class TensorBoardLog:
    """Scalars of one run into ``<run_dir>/tb`` (appended to when the run continues)."""

    def __init__(self, run_dir: Path) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.logdir = run_dir / "tb"
        self._writer = SummaryWriter(log_dir=str(self.logdir), flush_secs=10)
        self._published_bytes: tuple[int, int] | None = None  # (versions, bytes) at the last write

    def statuses(self, env_steps: int, statuses: dict[str, RoleStatus], steps_per_s: float,
                 produced: int) -> dict[str, float]:
        """Writes one collection round's scalars at `env_steps`; returns them by tag."""
        scalars = status_scalars(statuses, steps_per_s, produced)
        actor = _first_actor(statuses)
        if actor is not None:
            published = actor.extra.get("publish_bytes", {})
            versions = int(published.get("full_versions", 0)) + int(published.get("delta_versions", 0))
            sent = int(published.get("full_bytes", 0)) + int(published.get("delta_bytes", 0))
            if self._published_bytes is not None and versions > self._published_bytes[0]:
                scalars["weights/bytes_per_version"] = (sent - self._published_bytes[1]) / (versions - self._published_bytes[0])
            self._published_bytes = (versions, sent)
        for tag, value in scalars.items():
            self._writer.add_scalar(tag, value, env_steps)
        return scalars

    def evaluation(self, env_steps: int, ev: EvalResult) -> dict[str, float]:
        """Writes one evaluation's scalars at `env_steps`; returns them by tag."""
        scalars = eval_scalars(ev)
        for tag, value in scalars.items():
            self._writer.add_scalar(tag, value, env_steps)
        return scalars

    def close(self) -> None:
        self._writer.close()


def _first_actor(statuses: dict[str, RoleStatus]) -> RoleStatus | None:
    actors = sorted((s for s in statuses.values() if s.kind == "actor"), key=lambda s: s.extra.get("rank", 0))
    return actors[0] if actors else None


def eval_scalars(ev: EvalResult) -> dict[str, float]:
    """The scalars of one evaluation, by tag (pure)."""
    out = {f"eval/{name}": float(getattr(ev, name))
           for name in ("success_once", "success_at_end", "return_mean", "success_low", "success_high")}
    out["eval/version"] = float(ev.policy_version)
    for task, n in ev.task_episodes.items():  # e.g. libero_spatial/3 (the label keeps its slash)
        out[f"eval/task/{task}/success"] = ev.task_successes.get(task, 0) / max(n, 1)
        out[f"eval/task/{task}/episodes"] = float(n)
    return out


def status_scalars(statuses: dict[str, RoleStatus], steps_per_s: float, produced: int) -> dict[str, float]:
    """The scalars of one status round, by tag (pure: unit-tested)."""
    out: dict[str, float] = {"rollout/steps_per_s": steps_per_s, "rollout/produced_env_steps": produced}
    actor = _first_actor(statuses)
    if actor is not None:
        for k, v in actor.extra.get("learn", {}).items():
            if isinstance(v, (int, float)):
                out[f"train/{k}"] = float(v)
        out["train/updates_refused_nonfinite"] = float(actor.extra.get("updates_refused_nonfinite", 0))
        out["weights/version"] = float(actor.extra.get("published_version", actor.policy_version))
        out["weights/policy_lag_mean"] = float(actor.extra.get("policy_lag_mean", 0.0))
        out["weights/policy_lag_p99"] = float(actor.extra.get("policy_lag_p99", 0.0))
    rollouts = [s.extra for s in statuses.values() if s.kind == "rollout"]
    if rollouts:
        episodes = sum(int(e.get("episodes", 0)) for e in rollouts)
        for key, tag in (("train_success_rate", "success_rate"), ("episode_return_mean", "episode_return_mean"),
                         ("episode_len_mean", "episode_len_mean")):
            weighted = sum(float(e.get(key, 0.0)) * int(e.get("episodes", 0)) for e in rollouts)
            if episodes:
                out[f"env/{tag}"] = weighted / episodes
        out["rollout/infer_ms_p50"] = max(float(e.get("infer_ms_p50", 0.0)) for e in rollouts)
        out["rollout/infer_ms_p99"] = max(float(e.get("infer_ms_p99", 0.0)) for e in rollouts)
    lanes: dict[str, list[float]] = defaultdict(list)
    fabric: dict[str, float] = defaultdict(float)
    for s in statuses.values():
        for lane, metrics in s.lanes.items():
            for metric, name in (("utilisation", "busy"), ("wait_fraction", "wait"), ("items_per_s", "items_per_s")):
                if metric in metrics:
                    lanes[f"time/{s.kind}.{lane}/{name}"].append(float(metrics[metric]))
        for plane, counters in s.planes.items():
            for counter in FABRIC_COUNTERS:
                fabric[f"fabric/{plane}/{counter}"] += float(counters.get(counter, 0))
    out.update({tag: sum(v) / len(v) for tag, v in lanes.items()})
    out.update(fabric)
    return out
