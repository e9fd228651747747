"""The lock-step (``sync``) rollout on real ManiSkill envs: every chunk is acted on by one policy
version, the newest, whatever the number of env groups.

A rollout steps two env groups; with a share of one chunk per version, the group that did not ship
in a round must not act on that round's version (it would ship a chunk mixing two versions, one
version behind the learner). The test plays the learner: each shipped chunk completes a batch,
and a new version is published into the rollout's held weights, as WeightSync would.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dvla.config import PlaneEndpoints, PPOConfig, ReplicationConfig, RoleConfig, TaskConfig
from dvla.replication import WeightEncoder
from dvla.roles.rollout import Rollout
from dvla.roles.runtime import ExitStatus

from .lone_rollout import run_alone

T, ENVS = 4, 4  # two groups of two envs: a chunk is T * 2 env steps
TASK = TaskConfig(env="PushCube-v1", max_episode_steps=10, envs_per_rollout=ENVS, chunk_steps=T,
                  ppo=PPOConfig(batch_steps=T * ENVS // 2, minibatches=1))


def _run(tmp_path: Path, per_round: int, chunks: int) -> list[tuple[int, tuple[int, ...], int]]:
    """(group, versions its steps were acted on with, policy_version it shipped) of each chunk,
    in the order they were finished; the rollout's share is `per_round` chunks, and the test
    publishes a new version once it has them."""
    lockstep_steps = per_round * T * ENVS // 2
    cfg = RoleConfig(
        name="rollout-n0-0", kind="rollout", run="lockstep", node="n0", rack="r0", seed=3, mode="sync",
        run_dir=str(tmp_path / "rollout"), data=PlaneEndpoints(), ctrl=PlaneEndpoints(mode="peer"),
        shared_memory=False, parent="actor-n0-0", ancestors=("actor-n0-0",), children=(), actors=(), rollouts=(),
        task=TASK, replication=ReplicationConfig(), lockstep_steps=lockstep_steps,
    )
    Path(cfg.run_dir).mkdir(parents=True)
    finished: list[tuple[int, tuple[int, ...]]] = []
    shipped: list[int] = []
    rng = np.random.default_rng(0)

    class Learner(Rollout):
        def _finish_chunk(self, g, ctx):  # the versions this chunk's steps were acted on with
            finished.append((g.gid, tuple(sorted(set(g.versions)))))
            super()._finish_chunk(g, ctx)

        def _publish(self, shipment):  # the learner got its batch: the next version
            shipped.append(shipment.chunk.policy_version)
            shipment.pool.give(shipment.chunk)
            self.ledger.add_shipped(0)
            if len(shipped) >= chunks:
                self.stop_run()
            elif len(shipped) % per_round == 0:
                publish(self)

    encoder: list[WeightEncoder] = []  # one encoder: each version follows the last

    def publish(role: Rollout) -> None:
        if not encoder:
            encoder.append(WeightEncoder(role.pool.layout, start_version=0))
        v = encoder[0].encode(rng.normal(0, 0.3, role.pool.layout.numel).astype(np.float32))
        role.pool.held.apply(v.manifest, v.payload)

    def prepare(role: Rollout) -> None:
        assert [g.envs.n for g in role.groups] == [ENVS // 2, ENVS // 2]
        publish(role)

    code = run_alone(cfg, Learner, prepare)
    assert code == ExitStatus.OK
    assert len(shipped) >= chunks, f"only {len(shipped)} chunks shipped"
    return [(gid, versions, pv) for (gid, versions), pv in zip(finished, shipped)]


@pytest.mark.timeout(300)
def test_every_chunk_is_acted_on_by_the_newest_version_alone(tmp_path: Path) -> None:
    chunks = _run(tmp_path, per_round=1, chunks=6)  # a share of one chunk: the groups take turns
    for i, (gid, versions, shipped_as) in enumerate(chunks):
        assert len(versions) == 1, f"chunk {i} (group {gid}) mixes versions {versions}"
        assert shipped_as == versions[0]
        # round i acts with the version published after round i - 1: never one behind
        assert versions[0] == i + 1, (i, chunks)
    assert {gid for gid, _, _ in chunks} == {0, 1}, "both groups take turns"


@pytest.mark.timeout(300)
def test_a_share_of_two_chunks_is_one_chunk_of_each_group_per_version(tmp_path: Path) -> None:
    chunks = _run(tmp_path, per_round=2, chunks=6)
    for r in range(3):
        pair = chunks[2 * r: 2 * r + 2]
        assert [versions for _, versions, _ in pair] == [(r + 1,), (r + 1,)], (r, chunks)
        assert sorted(gid for gid, _, _ in pair) == [0, 1], (r, chunks)
