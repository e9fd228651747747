"""Embedding dvla's fabric in a plain Gymnasium loop (no dvla roles): a Pendulum-v1 sampler that
ships trajectory chunks to a running dvla actor and loads the weight versions the actor sends back.

This file owns the example end to end:

* ``make_pendulum``: the Gymnasium factory the actor is configured with (``TaskConfig.env =
  "examples.embed_gym_loop:make_pendulum"``), so the actor's policy has Pendulum's sizes
  (obs 3, act 1);
* ``actor_config``: a one-actor topology resolved into the actor's ``RoleConfig``;
* ``WeightFollower``: weight versions from the actor's ``ctrl/weights/<actor>`` key, assembled,
  checksum-verified and loaded into a local torch policy (catching up through the actor's
  snapshot queryable when it joins late or misses a base version);
* ``run``: the sampling loop itself.

Run it from the repository root (see docs/embedding.md)::

    export DVLA_SECRET=$(python -c "from dvla.fabric import new_secret; print(new_secret())")
    python examples/embed_gym_loop.py actor-config /tmp/pendulum-actor.json --base-port 17600
    python -m dvla.roles.actor --config /tmp/pendulum-actor.json &
    python examples/embed_gym_loop.py run --ctrl tcp/127.0.0.1:17600 --data tcp/127.0.0.1:17601
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch

if __package__ in (None, ""):  # run as a script: make the repository importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dvla.config import (  # noqa: E402
    NodeConfig,
    PPOConfig,
    RackConfig,
    RoleConfig,
    RolePlacement,
    TaskConfig,
    Topology,
)
from dvla.fabric import (  # noqa: E402
    Fabric,
    TrajectoryChunk,
    WeightChunk,
    WeightManifest,
    load_secret,
    plane_config,
)
from dvla.fabric.messages import SnapshotRequest, WeightSnapshot  # noqa: E402
from dvla.learn.policies import MLPPolicy  # noqa: E402
from dvla.orchestrator.plan import make_plan  # noqa: E402
from dvla.replication import (  # noqa: E402
    ChunkAssembler,
    HeldWeights,
    NeedSnapshot,
    ParamLayout,
    ReplicationError,
    StaleVersion,
    checksum,
    flatten,
    unflatten_into,
)

ENV_FACTORY = "examples.embed_gym_loop:make_pendulum"
#: hidden layers of the policy, on both sides (the actor trains what the sampler runs)
HIDDEN = (64, 64)
#: steps per env in one chunk; the actor only accepts chunks of exactly its task's chunk_steps
CHUNK_STEPS = 25


def make_pendulum(task: TaskConfig, seed: int) -> gym.Env:
    """Gymnasium factory for `TaskConfig.env` (``factory(task, seed)``): Pendulum-v1."""
    return gym.make("Pendulum-v1", max_episode_steps=task.max_episode_steps)


def actor_config(run_dir: str, base_port: int, *, run: str = "pendulum", batch_steps: int = 200) -> RoleConfig:
    """The RoleConfig of the one actor of a topology training on Pendulum.

    Its ctrl session is a router on ``base_port`` and its data session listens on
    ``base_port + 1`` (what `dvla up` would give it). ``envs_per_rollout=2`` makes the actor
    accept chunks of one env each, which is what this sampler sends.
    """
    task = TaskConfig(
        env=ENV_FACTORY,
        max_episode_steps=200,
        policy="mlp",
        policy_kwargs={"hidden": list(HIDDEN)},
        ppo=PPOConfig(batch_steps=batch_steps, minibatches=4, update_epochs=2, reward_scale=0.1),
        envs_per_rollout=2,
        chunk_steps=CHUNK_STEPS,
        device="cpu",
    )
    node = NodeConfig(name="node0", roles=(RolePlacement(role="actor"),))
    topo = Topology(run=run, base_port=base_port, task=task, racks=(RackConfig(name="rack0", nodes=(node,)),))
    plan = make_plan(topo, run_dir)
    return plan.by_name(plan.root_actor).config


def open_fabric(run: str, name: str, ctrl: str, data: str, secret: bytes) -> Fabric:
    """Two plain Zenoh configs: a ctrl client of the actor's router, a data peer of its data plane."""
    return Fabric(
        run=run,
        name=name,
        ctrl_conf=plane_config(mode="client", connect=[ctrl]),
        data_conf=plane_config(mode="peer", connect=[data]),
        secret=secret,
    )


class WeightFollower:
    """Receives the actor's weight versions and loads each verified one into `policy`."""

    def __init__(self, fabric: Fabric, actor: str, policy: torch.nn.Module) -> None:
        self.fabric = fabric
        self.actor = actor
        self.policy = policy
        self.layout = ParamLayout.from_state_dict(policy.state_dict())
        self.held = HeldWeights(self.layout)
        self.assembler = ChunkAssembler(1, 1, self.layout.nbytes)  # reset by each manifest
        self.manifest: WeightManifest | None = None
        #: every version loaded: {"version", "manifest_checksum", "policy_checksum", "via"}
        self.loaded: list[dict[str, Any]] = []
        self.rejected = 0
        # Weight envelopes are signed for keys.weights_signed(), whichever relay carries them.
        self.inbox = fabric.subscribe_ctrl(fabric.keys.weights(actor), 64, (WeightManifest, WeightChunk),
                                           sign_key=fabric.keys.weights_signed())

    @property
    def version(self) -> int:
        return self.held.version

    def catch_up(self, timeout: float = 2.0) -> bool:
        """Load the actor's newest version whole from its snapshot queryable; True on success.

        The reply is a header carrying the actor's signed manifest of that version, then the
        version as a full one, in chunks: assembled and applied like any other version."""
        request = SnapshotRequest(requester=self.fabric.name, have_version=self.version)
        replies = [m for _s, m in self.fabric.query(self.fabric.keys.snapshot(self.actor), request,
                                                    expect=(WeightSnapshot, WeightChunk), timeout=timeout)]
        heads = [m for m in replies if isinstance(m, WeightSnapshot)]
        if len(heads) != 1 or not heads[0].n_chunks or heads[0].version <= self.version:
            return False  # nothing newer (or an incomplete reply)
        proof = self.fabric.open_signed(self.fabric.keys.weights_signed(), heads[0].manifest, WeightManifest, fresh=False)
        if proof is None:
            self.rejected += 1
            return False
        whole = proof[1].whole(heads[0].n_chunks)
        self.manifest = None  # the assembler is taken for this version
        try:
            self.assembler.reset(whole.n_chunks, whole.total_bytes)
            for c in replies:
                if isinstance(c, WeightChunk) and c.version == whole.version:
                    self.assembler.add(c.index, c.data)
            self.held.apply(whole, self.assembler.payload())
        except ReplicationError:
            self.rejected += 1
            return False
        self._load(whole.checksum, "snapshot")
        return True

    def poll(self) -> int:
        """Handle every message waiting, without blocking; returns how many versions were loaded."""
        loaded = 0
        while (got := self.inbox.get_nowait()) is not None:
            loaded += self._handle(got[1])
        return loaded

    def _handle(self, msg: WeightManifest | WeightChunk) -> int:
        if isinstance(msg, WeightManifest):
            try:
                self.assembler.reset(msg.n_chunks, msg.total_bytes)
                self.manifest = msg
            except ReplicationError:
                self.rejected += 1
                self.manifest = None
            return 0
        m = self.manifest
        if m is None or msg.version != m.version:
            return 0  # a chunk of a version whose manifest we missed
        try:
            self.assembler.add(msg.index, msg.data)
        except ReplicationError:
            self.rejected += 1
            return 0
        if not self.assembler.complete:
            return 0
        self.manifest = None
        return self._apply(m)

    def _apply(self, m: WeightManifest) -> int:
        try:
            self.held.apply(m, self.assembler.payload())
        except StaleVersion:
            return 0
        except NeedSnapshot:
            return int(self.catch_up())  # a delta whose base we do not hold
        except ReplicationError:
            self.rejected += 1  # bad checksum or layout: nothing was loaded
            return int(self.catch_up())
        self._load(m.checksum, "stream")
        return 1

    def _load(self, manifest_checksum: str, via: str) -> None:
        unflatten_into(self.held.active, self.policy, self.layout)
        with torch.no_grad():
            held = checksum(flatten(self.policy.state_dict(), self.layout))
        self.loaded.append(
            {"version": self.version, "manifest_checksum": manifest_checksum, "policy_checksum": held, "via": via}
        )


class ChunkBuilder:
    """Collects T steps of one env into the arrays of a TrajectoryChunk."""

    def __init__(self, T: int, obs_dim: int, act_dim: int) -> None:
        self.T = T
        self.obs = np.zeros((T, 1, obs_dim), np.float32)
        self.final_obs = np.zeros((T, 1, obs_dim), np.float32)
        self.actions = np.zeros((T, 1, act_dim), np.float32)
        self.tn = {k: np.zeros((T, 1), np.float32) for k in ("logprobs", "rewards")}
        self.flags = {k: np.zeros((T, 1), bool) for k in ("terminated", "truncated", "success")}
        self.t = 0
        self.versions: list[int] = []

    def add(self, obs: np.ndarray, action: np.ndarray, logprob: float, reward: float,
            terminated: bool, truncated: bool, final_obs: np.ndarray | None, version: int) -> bool:
        """Record one step; True when the chunk is full."""
        t = self.t
        self.obs[t, 0] = obs
        self.actions[t, 0] = action
        self.tn["logprobs"][t, 0] = logprob
        self.tn["rewards"][t, 0] = reward
        self.flags["terminated"][t, 0] = terminated
        self.flags["truncated"][t, 0] = truncated
        self.final_obs[t, 0] = 0.0 if final_obs is None else final_obs
        self.versions.append(version)
        self.t += 1
        return self.t == self.T

    def chunk(self, rollout: str, seq: int, next_obs: np.ndarray) -> TrajectoryChunk:
        """The full chunk (the arrays are handed over; start a new builder afterwards)."""
        return TrajectoryChunk(
            rollout=rollout, seq=seq, policy_version=min(self.versions), env_steps=self.T,
            obs={"state": self.obs}, actions=self.actions,
            logprobs=self.tn["logprobs"], rewards=self.tn["rewards"],
            terminated=self.flags["terminated"], truncated=self.flags["truncated"], success=self.flags["success"],
            next_obs={"state": next_obs.reshape(1, -1).astype(np.float32)}, final_obs={"state": self.final_obs},
        )


def wait_first_weights(follower: WeightFollower, timeout_s: float) -> None:
    """Acting with random weights would make the actor's importance ratios meaningless."""
    deadline = time.monotonic() + timeout_s
    while follower.version < 1:
        if time.monotonic() > deadline:
            raise TimeoutError(f"no weights from {follower.actor} within {timeout_s:.0f}s")
        follower.poll()
        if follower.version < 1 and not follower.catch_up(timeout=1.0):
            time.sleep(0.2)


def run(
    *,
    ctrl: str,
    data: str,
    run_id: str = "pendulum",
    actor: str = "actor-node0-0",
    name: str = "gym-sampler",
    steps: int = 3000,
    min_versions: int = 2,
    max_wall_s: float = 120.0,
    chunk_steps: int = CHUNK_STEPS,
    seed: int = 0,
    secret: bytes | None = None,
) -> dict[str, Any]:
    """Sample Pendulum until `steps` env steps are shipped and `min_versions` versions loaded
    (or `max_wall_s` passes); returns a summary."""
    env = gym.make("Pendulum-v1", max_episode_steps=200)
    obs_dim, act_dim = env.observation_space.shape[0], env.action_space.shape[0]
    low, high = env.action_space.low, env.action_space.high
    policy = MLPPolicy(obs_dim, act_dim, hidden=HIDDEN).eval()
    fabric = open_fabric(run_id, name, ctrl, data, secret if secret is not None else load_secret(None))
    started = time.monotonic()
    shipped = seq = 0
    try:
        follower = WeightFollower(fabric, actor, policy)
        wait_first_weights(follower, timeout_s=max_wall_s)
        obs, _ = env.reset(seed=seed)
        builder = ChunkBuilder(chunk_steps, obs_dim, act_dim)
        while time.monotonic() - started < max_wall_s:
            if shipped >= steps and len(follower.loaded) >= min_versions:
                break
            with torch.no_grad():
                action, logprob, _ = policy.act(torch.as_tensor(obs, dtype=torch.float32)[None])
            a = action[0].numpy()
            # The sampled action is what its logprob belongs to; only the env sees it clipped.
            next_obs, reward, terminated, truncated, _ = env.step(np.clip(a, low, high))
            final = next_obs if (terminated or truncated) else None
            if terminated or truncated:
                next_obs, _ = env.reset()
            full = builder.add(obs, a, float(logprob[0]), float(reward), terminated, truncated, final, follower.version)
            obs = next_obs
            if full:
                chunk = builder.chunk(name, seq, obs)
                fabric.publish_traj(chunk)
                shipped += chunk.env_steps
                seq += 1
                builder = ChunkBuilder(chunk_steps, obs_dim, act_dim)
                follower.poll()  # new weights are swapped in between chunks, never mid-chunk
        return {
            "env_steps": shipped,
            "chunks": seq,
            "policy_version": follower.version,
            "versions": follower.loaded,
            "weights_rejected": follower.rejected,
            "wall_s": time.monotonic() - started,
            "accounting": fabric.accounting.snapshot(),
        }
    finally:
        fabric.close()
        env.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    cfg = sub.add_parser("actor-config", help="write the RoleConfig JSON of a Pendulum actor")
    cfg.add_argument("path", type=Path)
    cfg.add_argument("--base-port", type=int, default=17600)
    cfg.add_argument("--run-dir", default="runs/pendulum")
    go = sub.add_parser("run", help="sample Pendulum against a running actor")
    go.add_argument("--ctrl", default="tcp/127.0.0.1:17600", help="the actor's ctrl router endpoint")
    go.add_argument("--data", default="tcp/127.0.0.1:17601", help="the actor's data endpoint")
    go.add_argument("--steps", type=int, default=3000)
    go.add_argument("--min-versions", type=int, default=2)
    go.add_argument("--max-wall-s", type=float, default=120.0)
    args = parser.parse_args(argv)
    if args.cmd == "actor-config":
        args.path.write_text(actor_config(args.run_dir, args.base_port).to_json())
        print(f"wrote {args.path}")
        return 0
    summary = run(ctrl=args.ctrl, data=args.data, steps=args.steps, min_versions=args.min_versions, max_wall_s=args.max_wall_s)
    summary.pop("accounting")
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
