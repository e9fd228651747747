"""Tests of dvla.orchestrator.tensorboard: which scalars a status round and an eval become, and
that TensorBoard's own reader finds them at the given env steps."""

from __future__ import annotations

from pathlib import Path

from dvla.fabric.messages import EvalResult, RoleStatus
from dvla.orchestrator.tensorboard import TensorBoardLog, status_scalars


def _status(name: str, kind: str, **extra) -> RoleStatus:
    return RoleStatus(name=name, kind=kind, node="n", rack="r", pid=1, state="running", policy_version=3,
                      env_steps=100, steps_per_s=1.0, extra=extra,
                      lanes={"learn": {"utilisation": 0.5, "wait_fraction": 0.25, "items_per_s": 2.0}},
                      planes={"data": {"received_bytes": 10, "rejected": 1, "peers": {"x": {"rejected": 1}}}})


def _round() -> dict[str, RoleStatus]:
    return {
        "a": _status("a", "actor", learn={"approx_kl": 0.01, "policy_loss": -0.2, "note": "x"}, published_version=3,
                     policy_lag_mean=0.5, policy_lag_p99=2, updates_refused_nonfinite=1),
        "r0": _status("r0", "rollout", episodes=3, train_success_rate=1.0, episode_return_mean=6.0,
                      episode_len_mean=10.0, infer_ms_p50=1.0, infer_ms_p99=4.0),
        "r1": _status("r1", "rollout", episodes=1, train_success_rate=0.0, episode_return_mean=2.0,
                      episode_len_mean=50.0, infer_ms_p50=2.0, infer_ms_p99=3.0),
    }


def test_status_scalars_cover_every_namespace():
    out = status_scalars(_round(), steps_per_s=123.0, produced=400)
    assert out["train/approx_kl"] == 0.01 and "train/note" not in out
    assert out["train/updates_refused_nonfinite"] == 1.0
    assert out["env/success_rate"] == 0.75 and out["env/episode_return_mean"] == 5.0  # weighted by episodes
    assert out["env/episode_len_mean"] == 20.0
    assert out["rollout/steps_per_s"] == 123.0 and out["rollout/infer_ms_p99"] == 4.0
    assert out["time/actor.learn/busy"] == 0.5 and out["time/rollout.learn/wait"] == 0.25
    assert out["fabric/data/received_bytes"] == 30.0 and out["fabric/data/rejected"] == 3.0
    assert out["weights/version"] == 3.0 and out["weights/policy_lag_p99"] == 2.0


def test_event_files_read_back_at_env_steps(tmp_path: Path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    log = TensorBoardLog(tmp_path)
    sts = _round()
    sts["a"].extra["publish_bytes"] = {"full_versions": 1, "full_bytes": 1000}
    log.statuses(100, sts, 10.0, 100)
    sts["a"].extra["publish_bytes"] = {"full_versions": 1, "full_bytes": 1000, "delta_versions": 2, "delta_bytes": 600}
    log.statuses(200, sts, 10.0, 200)
    log.evaluation(200, EvalResult(sender="e", policy_version=3, episodes=50, success_once=0.9, success_at_end=0.8,
                                   return_mean=4.0, success_low=0.79, success_high=0.96))
    log.close()
    acc = EventAccumulator(str(tmp_path / "tb"))
    acc.Reload()
    assert [(e.step, e.value) for e in acc.Scalars("weights/version")] == [(100, 3.0), (200, 3.0)]
    assert [(e.step, e.value) for e in acc.Scalars("weights/bytes_per_version")] == [(200, 300.0)]
    assert [(e.step, round(e.value, 3)) for e in acc.Scalars("eval/success_once")] == [(200, 0.9)]
    assert [(e.step, round(e.value, 3)) for e in acc.Scalars("eval/success_low")] == [(200, 0.79)]


def test_per_task_evaluations_get_scalars_of_their_own():
    from dvla.orchestrator.tensorboard import eval_scalars

    ev = EvalResult(sender="e", policy_version=4, episodes=6, success_once=0.5, success_at_end=0.5, return_mean=1.0,
                    success_low=0.2, success_high=0.8, task_episodes={"libero_spatial/0": 4, "libero_spatial/3": 2},
                    task_successes={"libero_spatial/0": 3, "libero_spatial/3": 0}, time_ns=1)
    out = eval_scalars(ev)
    assert out["eval/task/libero_spatial/0/success"] == 0.75 and out["eval/task/libero_spatial/0/episodes"] == 4.0
    assert out["eval/task/libero_spatial/3/success"] == 0.0
    plain = eval_scalars(EvalResult(sender="e", policy_version=4, episodes=6, success_once=0.5, success_at_end=0.5,
                                    return_mean=1.0, success_low=0.2, success_high=0.8, time_ns=1))
    assert not any(k.startswith("eval/task/") for k in plain)
