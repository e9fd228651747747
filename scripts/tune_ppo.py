#!/usr/bin/env python3
"""Tune PPO hyper-parameters in one process, with the data layout of the distributed system.

The distributed run samples 25-step trajectory chunks on rollout processes that hold slightly
stale weights, and the actor learns one policy version per ``batch_steps`` transitions. This
tool reproduces that on one core: an EnvGroup of ``--envs`` envs yields chunks acted on by the
policy of ``--lag`` versions ago, ``gae_batch`` + ``PPOLearner`` learn from them, and a
separate eval group plays ``--eval-episodes`` deterministic episodes every ``--eval-every``
versions. It stops once eval success_once >= ``--target`` for ``--consecutive`` evals in a row
(or at ``--max-steps`` / ``--max-wall``) and prints a final ``RESULT {json}`` line.

Env steps count training transitions only; ``train_s`` excludes evaluation time (in the real
system an evaluator process does that), ``wall_s`` includes it.

Defaults follow ``PPOConfig``; the other defaults mirror the distributed system: decoupled PPO
(``--plain`` for the clip against the behaviour policy), terminations bootstrapped like time limits
(``--terminations``), behaviour policy one version behind (``--lag``). Example::

    python scripts/tune_ppo.py --seed 1 --batch-steps 1600 --minibatches 4 --epochs 8 --lr 5e-4

Each run uses one core (``torch.set_num_threads(1)``); run one at a time on a shared machine.
"""

from __future__ import annotations

import argparse
import collections
import copy
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dvla.config import PPOConfig, TaskConfig  # noqa: E402
from dvla.learn.envs import EnvGroup, run_eval_episodes  # noqa: E402
from dvla.learn.policies import make_policy  # noqa: E402
from dvla.learn.ppo import PPOLearner, Trajectories, gae_batch  # noqa: E402


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    d = PPOConfig()
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", default="PushCube-v1")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--lr-end", type=float, default=None, help="decay the lr linearly to this (default: constant)")
    p.add_argument("--lr-decay-steps", type=int, default=100_000, help="env steps over which --lr-end is reached")
    p.add_argument("--envs", type=int, default=8, help="training envs (one EnvGroup)")
    p.add_argument("--chunk-steps", type=int, default=25)
    p.add_argument("--lag", type=int, default=1, help="versions the behaviour policy lags behind")
    p.add_argument("--batch-steps", type=int, default=d.batch_steps)
    p.add_argument("--minibatches", type=int, default=d.minibatches)
    p.add_argument("--epochs", type=int, default=d.update_epochs)
    p.add_argument("--lr", type=float, default=d.lr)
    p.add_argument("--gamma", type=float, default=d.gamma)
    p.add_argument("--lam", type=float, default=d.gae_lambda)
    p.add_argument("--clip", type=float, default=d.clip)
    p.add_argument("--target-kl", type=float, default=d.target_kl, help="<= 0 disables the early stop")
    p.add_argument("--ent-coef", type=float, default=d.ent_coef)
    p.add_argument("--vf-coef", type=float, default=d.vf_coef)
    p.add_argument("--max-grad-norm", type=float, default=d.max_grad_norm)
    p.add_argument("--reward-scale", type=float, default=d.reward_scale)
    p.add_argument("--plain", action="store_true",
                   help="clip the ratio against the behaviour policy (default: decoupled PPO)")
    # Decoupled PPO used to be opt-in; the flag is accepted so older command lines still run.
    p.add_argument("--decoupled", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--is-clip", type=float, default=d.is_clip, help="truncation of the decoupled IS weight")
    p.add_argument("--obs-norm", action="store_true", help="running observation normalisation")
    p.add_argument("--init-log-std", type=float, default=-0.5)
    p.add_argument("--terminations", choices=("reset", "bootstrap", "ignore"), default="bootstrap",
                   help="success ends the episode without bootstrap (reset), ends it but bootstraps "
                        "like a time limit (bootstrap), or does not end it (ignore)")
    p.add_argument("--eval-every", type=int, default=2, help="versions between evals")
    p.add_argument("--eval-episodes", type=int, default=16)
    p.add_argument("--eval-envs", type=int, default=8)
    p.add_argument("--target", type=float, default=0.8)
    p.add_argument("--consecutive", type=int, default=3)
    p.add_argument("--max-steps", type=int, default=200_000)
    p.add_argument("--max-wall", type=float, default=240.0, help="seconds")
    p.add_argument("--quiet", action="store_true", help="print only the RESULT line")
    return p.parse_args(argv)


def ppo_config(a: argparse.Namespace) -> PPOConfig:
    return PPOConfig(
        gamma=a.gamma,
        gae_lambda=a.lam,
        lr=a.lr,
        clip=a.clip,
        update_epochs=a.epochs,
        minibatches=a.minibatches,
        batch_steps=a.batch_steps,
        ent_coef=a.ent_coef,
        vf_coef=a.vf_coef,
        max_grad_norm=a.max_grad_norm,
        target_kl=a.target_kl if a.target_kl > 0 else None,
        reward_scale=a.reward_scale,
        terminal_bootstrap=a.terminations == "bootstrap",
    )


def side_by_side(chunks: list[dict[str, np.ndarray]]) -> Trajectories:
    """Chunks stacked along the env axis, as the actor's slots stack them."""
    out = {k: torch.as_tensor(np.concatenate([c[k] for c in chunks], axis=0 if k == "next_obs" else 1))
           for k in chunks[0]}
    for k in ("obs", "final_obs", "next_obs"):
        out[k] = {"state": out[k].float()}
    return Trajectories(**out)


class ChunkSampler:
    """Steps the training group and cuts its stream into chunks (the rollout side)."""

    def __init__(self, group: EnvGroup, chunk_steps: int):
        self.group = group
        self.chunk_steps = chunk_steps
        self.obs = group.reset()
        self.episode_success = np.zeros(group.n, dtype=bool)
        self.finished: collections.deque[bool] = collections.deque(maxlen=64)

    def chunk(self, policy: torch.nn.Module) -> dict[str, np.ndarray]:
        g, T = self.group, self.chunk_steps
        out = {
            "obs": np.empty((T, g.n, g.obs_dim), np.float32),
            "actions": np.empty((T, g.n, g.act_dim), np.float32),
            "logprobs": np.empty((T, g.n), np.float32),
            "rewards": np.empty((T, g.n), np.float32),
            "terminated": np.empty((T, g.n), bool),
            "truncated": np.empty((T, g.n), bool),
            "success": np.empty((T, g.n), bool),
            "final_obs": np.empty((T, g.n, g.obs_dim), np.float32),
        }
        for t in range(T):
            action, logprob, _ = policy.act(torch.from_numpy(self.obs))
            res = g.step(action.numpy())
            out["obs"][t] = self.obs
            out["actions"][t] = action.numpy()
            out["logprobs"][t] = logprob.numpy()
            out["rewards"][t] = res.reward
            out["terminated"][t] = res.terminated
            out["truncated"][t] = res.truncated
            out["success"][t] = res.success
            out["final_obs"][t] = res.final_obs
            self._track(res)
            self.obs = res.next_obs
        out["next_obs"] = self.obs.copy()
        return out

    def _track(self, res) -> None:
        self.episode_success |= res.success
        for i in np.flatnonzero(res.episode_done):
            self.finished.append(bool(self.episode_success[i]))
        self.episode_success[res.episode_done] = False

    def train_success(self) -> float:
        return float(np.mean(self.finished)) if self.finished else float("nan")


class Run:
    """One tuning run: training group, eval group, policy, learner and the version history."""

    def __init__(self, a: argparse.Namespace):
        self.a = a
        self.cfg = ppo_config(a)
        self.per_chunk = a.envs * a.chunk_steps
        if a.batch_steps % self.per_chunk:
            raise SystemExit(f"--batch-steps must be a multiple of envs*chunk_steps = {self.per_chunk}")
        self.task = TaskConfig(env=a.env, ppo=self.cfg, sim_backend="physx_cpu", device="cpu")
        self.group = EnvGroup(self.task, a.envs, a.seed * 10_000, ignore_terminations=a.terminations == "ignore")
        # Eval episodes play to the time limit so success_at_end is meaningful.
        self.eval_group = EnvGroup(self.task, a.eval_envs, a.seed * 10_000 + 1_000_000, ignore_terminations=True)
        g = self.group
        self.policy = make_policy("mlp", g.obs_dim, g.act_dim, obs_norm=a.obs_norm, init_log_std=a.init_log_std)
        self.behaviour = copy.deepcopy(self.policy)
        self.learner = PPOLearner(self.policy, self.cfg, "cpu", seed=a.seed, decoupled=not a.plain, is_clip=a.is_clip)
        # The behaviour policy is the oldest of the last lag+1 versions.
        self.history = collections.deque([copy.deepcopy(self.policy.state_dict())], maxlen=a.lag + 1)
        self.sampler = ChunkSampler(g, a.chunk_steps)

    def learn_one_version(self) -> dict[str, float]:
        a = self.a
        self.behaviour.load_state_dict(self.history[0])
        chunks = [self.sampler.chunk(self.behaviour) for _ in range(a.batch_steps // self.per_chunk)]
        batch = gae_batch(self.policy, side_by_side(chunks), self.cfg)
        stats = self.learner.update(batch)
        self.history.append(copy.deepcopy(self.policy.state_dict()))
        return stats

    def evaluate(self) -> dict[str, float]:
        # The distributed run's evaluation states: the same initial states for a given --seed as
        # `dvla up --seed`, so figures of both are comparable.
        seed = self.task.eval.first_seed(self.a.seed)
        return run_eval_episodes(self.policy, self.task, self.a.eval_episodes, seed, "cpu", group=self.eval_group)

    def close(self) -> None:
        self.group.close()
        self.eval_group.close()


def report_row(version, env_steps, wall, eval_s, ev, stats, train_success) -> dict:
    return dict(
        version=version, env_steps=env_steps, wall_s=round(wall, 1), train_s=round(wall - eval_s, 1),
        success_once=ev["success_once"], success_at_end=ev["success_at_end"],
        eval_return=round(ev["return_mean"], 2), train_success=round(train_success, 2),
        kl=round(stats["approx_kl"], 4), bkl=round(stats["behaviour_kl"], 4),
        epochs=stats["epochs_run"], lr=f'{stats["lr"]:.2e}', ent=round(stats["entropy"], 2), v_loss=round(stats["v_loss"], 4),
        # the evaluation episodes (the same initial states every time) that did not succeed
        failed=",".join(map(str, ev["failed_episodes"])) or "-",
    )


def train(a: argparse.Namespace) -> dict:
    torch.set_num_threads(1)  # the other core belongs to other processes
    torch.manual_seed(a.seed)
    np.random.seed(a.seed)
    started = time.perf_counter()
    run = Run(a)
    env_steps, version, streak, eval_s = 0, 0, 0, 0.0
    evals: list[dict] = []
    result: dict = {"reached": False}
    try:
        while env_steps < a.max_steps and time.perf_counter() - started < a.max_wall:
            if a.lr_end is not None:
                frac = min(1.0, env_steps / a.lr_decay_steps)
                for group in run.learner.optimizer.param_groups:
                    group["lr"] = a.lr + frac * (a.lr_end - a.lr)
            stats = run.learn_one_version()
            env_steps += a.batch_steps
            version += 1
            if version % a.eval_every:
                continue
            t0 = time.perf_counter()
            ev = run.evaluate()
            eval_s += time.perf_counter() - t0
            row = report_row(version, env_steps, time.perf_counter() - started, eval_s, ev, stats,
                             run.sampler.train_success())
            evals.append(row)
            if not a.quiet:
                print(" ".join(f"{k}={v}" for k, v in row.items()), flush=True)
            streak = streak + 1 if ev["success_once"] >= a.target else 0
            if streak >= a.consecutive:
                result = {"reached": True, **{k: row[k] for k in ("version", "env_steps", "wall_s", "train_s")}}
                break
    finally:
        run.close()
    if not result["reached"]:
        wall = time.perf_counter() - started
        result.update(version=version, env_steps=env_steps, wall_s=round(wall, 1), train_s=round(wall - eval_s, 1))
    best = max((e["success_once"] for e in evals), default=float("nan"))
    return {**result, "seed": a.seed, "best_success_once": best, "config": vars(a)}


def main(argv: list[str] | None = None) -> None:
    result = train(parse_args(argv))
    print("RESULT " + json.dumps(result), flush=True)


if __name__ == "__main__":
    main()
