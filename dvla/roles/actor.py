"""Actor role: one rank of the learner group. Consumes its rollouts' trajectory chunks, runs PPO
with the other ranks (dvla/learn/group.py); rank 0 publishes weight versions and checkpoints.

Lanes (and what flows between them):
- ``ingest``:  data-plane inbox -> the run's ChunkSpec and policy-lag checks -> a free slot of
               the preallocated pool.
- ``batch``:   gathers slots until one learner batch is full, re-checks lag, stacks it.
- ``learn``:   values and GAE with the current critic, PPO epochs, a new version.
- ``publish``: rank 0 reserves the version number on disk, encodes it (full / delta with error
               feedback), signs and sends it to the tree, logs it to ``versions.csv``, serves
               snapshots, writes checkpoints; other ranks record their checksum. Overlaps ``learn``.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..config import RoleConfig, resolve_device
from ..fabric import Fabric
from ..fabric.accounting import OTHER_PEER
from ..fabric.fabric import CTRL, DATA
from ..fabric.messages import ChunkSpec, LedgerRecord, ReceiptRequest, TrajectoryChunk
from ..learn import PPOLearner, gae_batch, make_policy
from ..learn.group import LearnerGroup
from ..learn.envs import chunk_envs, chunk_spec, probe_spec
from ..learn.grpo import grpo_batch
from ..learn.policies import extras_spec, policy_base_hash
from ..ledger import ActorLedger
from ..replication import ParamLayout, checksum, flatten, replicated_tensors, unflatten_into
from .checkpoint import (Checkpoint, load_checkpoint, load_init_weights, optimizer_tensors, reserve_versions,
                         save_checkpoint)
from .runtime import main
from .slots import SlotPool
from .swimlane import LaneContext, Swimlane, sample_percentile
from .weightsync import WeightPublisher

log = logging.getLogger("dvla.actor")


class Actor:
    #: set by the runtime when the role stopped on an error: its counter file is then not marked
    #: clean, so chunks in flight to it are accounted as lost with it, like a kill's
    failed = False

    def __init__(self, cfg: RoleConfig, fabric: Fabric) -> None:
        self.cfg = cfg
        self.fabric = fabric
        # The run's roles get counters of their own in the accounting, however many others show up.
        fabric.accounting.add_known_peers((*cfg.rollouts, *cfg.children, *(cfg.group.members if cfg.group else ())))
        task = cfg.task
        self.device = torch.device(resolve_device(task.device))
        # Blocks until every rank has joined (a group of one joins nothing).
        self.group = LearnerGroup(cfg.group, self.device, address=_listen_address(cfg))
        self.is_root = self.group.is_root
        torch.manual_seed(cfg.seed)
        obs_spec, act_dim = probe_spec(task)  # flat: {"state"}; rgb: rgb/proprio/tokens
        self.policy = make_policy(task.policy, obs_spec, act_dim, **task.policy_kwargs).to(self.device)
        #: what every chunk holds: the task's observations and actions, the policy's extras
        self.spec = chunk_spec(task, obs_spec, act_dim, extras_spec(self.policy))
        self.learner = PPOLearner(self.policy, task.ppo, self.device, seed=cfg.seed, group=self.group)
        self.layout = ParamLayout.from_state_dict(self.policy)
        self._n_parameters = sum(p.numel() for p in self.policy.parameters())
        self.ckpt_dir = Path(cfg.run_dir) / "checkpoints"
        # Rank 0 resumes from the last checkpoint and numbers versions above every one that may
        # have been published before (the persisted high-water mark); the others get its state.
        self.resumed: Checkpoint | None = None
        if self.is_root:
            self.resumed = load_checkpoint(self.ckpt_dir, self.policy, self.learner.optimizer, self._checksum)
            if self.resumed is None and task.init_weights:  # a warm start; a resumed run has its own
                log.info("warm start: policy weights from %s", load_init_weights(task.init_weights, self.policy))
        start = self.resumed.high_water if self.resumed else 0
        env_steps = self.resumed.env_steps if self.resumed else 0
        start, env_steps = self.group.sync_from_root(self.policy, self.learner.optimizer, [start, env_steps])
        if self.resumed:
            log.info("resumed from checkpoint v%d (%s), %d env steps; numbering continues above v%d",
                     self.resumed.version, self.resumed.checksum, env_steps, start)
        self._first_version = start + 1  # this incarnation's first (checkpointed at once)
        self.high_water = start  # the persisted high-water mark: no version up to it is numbered again
        self.publisher = WeightPublisher(
            fabric, cfg.name, self.layout, cfg.replication, start, base_hash=policy_base_hash(self.policy)
        ) if self.is_root else None
        # slots of N = the largest chunk any rollout may ship, enough of the smallest for three batches
        chunks_per_batch = -(-task.ppo.batch_steps // (task.chunk_steps * chunk_envs(task)[0]))
        self.slots = SlotPool(self.spec, 3 * chunks_per_batch + 8, pin=self.device.type == "cuda")
        #: newest version learned (the learn lane numbers the next one from here)
        self.policy_version = start
        #: (version, checksum) of the newest version through the publish lane (published by rank 0;
        #: recorded by the others); one assignment, so status never pairs a version with another's checksum
        self.published: tuple[int, str] = (start, "")
        #: newest version whose weights may have left the group (no chunk may claim a newer one):
        #: set before rank 0 sends it; other ranks record each version before rank 0 can send it.
        self.released_version = start
        #: (rollout, reason) -> chunks rejected at ingest (for the log, which names the sender)
        self._rejections: dict[tuple[str, str], int] = {}
        self.env_steps = env_steps  # consumed by the whole group's learners
        self.learn_stats: dict[str, float] = {}
        self.lags: list[int] = []
        #: chunks received per lag (newest published - behaviour version, at ingest), cumulative
        self.ingest_lag_counts: dict[int, int] = {}
        #: versions sent and their bytes, full versions and deltas apart
        self.publish_bytes = {"full_versions": 0, "full_bytes": 0, "delta_versions": 0, "delta_bytes": 0}
        #: version -> checksum of this rank's parameters after it (the newest few; equal on every rank)
        self.checksums: dict[int, str] = {}
        #: what became of every chunk got, in a counter file that survives a kill -9 (dvla/ledger.py)
        self.ledger = ActorLedger(cfg.run_dir, cfg.name, fabric.accounting, self.slots.n_slots, INBOX)
        self._versions_csv = open(Path(cfg.run_dir) / "versions.csv", "a", buffering=1) if self.is_root else None

    # -- wiring -------------------------------------------------------------------------------
    def build(self, sl: Swimlane) -> None:
        f, ppo = self.fabric, self.cfg.task.ppo
        self.inbox = f.subscribe_traj(maxsize=INBOX, expect=TrajectoryChunk,  # rollouts -> ingest
                                      on_dropped=lambda c: self.ledger.fabric_dropped(c.rollout, c.seq))
        # counter records of rollouts elsewhere (`dvla join`): the root keeps the run's copies
        self.ledgers = f.subscribe_ctrl(f.keys.ledger_all(), maxsize=64, expect=LedgerRecord) if self.is_root else None
        self._ledgers_polled = 0.0
        # a stopping rollout asks how far its chunks got before it closes its link (rollout.py)
        f.serve(f.keys.receipt(self.cfg.name), self.ledger.receipt, ReceiptRequest)
        self.filled = sl.queue("filled", self.slots.n_slots)  # ingest -> batch: slot ids
        self.batches = sl.queue("batches", 1)  # batch -> learn: one stacked Trajectories
        self.versions = sl.queue("versions", 2)  # learn -> publish: NewVersion
        if self.publisher is not None:
            self.publisher.serve()  # catch-up for children: the published version
        self.max_lag = ppo.max_policy_lag
        sl.lane("ingest", self._ingest)
        sl.lane("batch", self._batch)
        sl.lane("learn", self._learn)
        sl.lane("publish", self._publish)
        # The first version: the initial (or resumed) weights, so rollouts can act at once.
        self.versions.put(self._new_version(checkpoint=True), threading.Event())

    @property
    def published_version(self) -> int:
        return self.published[0]

    def _checksum(self, policy: torch.nn.Module) -> str:
        return checksum(self._flat_weights(policy))

    def _flat_weights(self, policy: torch.nn.Module | None = None) -> np.ndarray:
        flat = np.empty(self.layout.numel, np.float32)
        with torch.no_grad():
            flatten(policy or self.policy, self.layout, out=flat)
        return flat

    def _new_version(self, checkpoint: bool) -> "NewVersion":
        """The next version from the current weights (learn lane, between two updates)."""
        self.policy_version += 1
        opt = optimizer_tensors(self.learner.optimizer) if checkpoint and self.is_root else None
        return NewVersion(self.policy_version, self._flat_weights(), self.env_steps, opt)

    # -- lanes --------------------------------------------------------------------------------
    def _ingest(self, ctx: LaneContext) -> None:
        while ctx.running:
            if time.monotonic() - self._ledgers_polled >= 0.5:
                self._adopt_ledgers()
            with ctx.waiting():
                chunk = self.inbox.get(timeout=0.1)
            if chunk is None:
                self.ledger.tick()  # the fabric's own drops reach the counter file too
                continue
            with ctx.busy():
                src = self.ledger.got(chunk.rollout, chunk.seq)
                problem = chunk_problem(chunk, self.spec, self.released_version)
                if problem is not None:
                    self._reject(chunk, src, *problem)
                    continue
                lag = self.published_version - chunk.policy_version
                self.ingest_lag_counts[lag] = self.ingest_lag_counts.get(lag, 0) + 1
                if lag > self.max_lag:
                    self.ledger.settle(src, "dropped.stale")
                    continue
                slot = self.slots.acquire(ctx.stop)
                if slot is None:  # stopping while every slot is taken: the inbox is still drained below
                    self.ledger.settle(src, "dropped.shutdown")
                    break
                self.slots.fill(slot, chunk)
                self.ledger.hold(slot, src)
            if not self.filled.put(slot, ctx.stop, stats=ctx.stats):  # stopping with the batch lane full
                self.ledger.release(slot, "dropped.shutdown")
                self.slots.release(slot)
                break
            ctx.count()
        # Shutdown: chunks still arriving or queued are counted, never silently lost. Rollouts
        # are stopped first, so a short quiet period catches their last chunks.
        while (chunk := self.inbox.get(timeout=0.5)) is not None:
            self.ledger.settle(self.ledger.got(chunk.rollout, chunk.seq), "dropped.shutdown")
        self._adopt_ledgers()  # the last records of rollouts elsewhere, sent as they stopped

    def _adopt_ledgers(self) -> None:
        """Keep the counter records rollouts elsewhere sent (verified: signed by that rollout)."""
        self._ledgers_polled = time.monotonic()
        while self.ledgers is not None and (got := self.ledgers.get_nowait()) is not None:
            sender, record = got
            if record.role != sender:
                self.fabric.accounting.rejected(CTRL, "sender_mismatch", sender)
                log.warning("ledger record of %r sent by %r refused", record.role, sender)
                continue
            try:
                self.ledger.adopt(record)
            except OSError as err:
                log.warning("ledger record of %s not kept: %s", sender, err)

    def _reject(self, chunk: TrajectoryChunk, src: str, reason: str, detail: str) -> None:
        """Count a chunk that must not reach the learner; log the 1st, 10th, 100th, ... per sender
        and reason (the counters count every one)."""
        self.ledger.settle(src, f"rejected.{reason}")
        key = (chunk.rollout, reason)
        if key not in self._rejections and len(self._rejections) >= 1024:  # bounded: the rest together
            key = (OTHER_PEER, reason)
        n = self._rejections[key] = self._rejections.get(key, 0) + 1
        if n == 10 ** (len(str(n)) - 1):
            log.warning("chunk %d from %s rejected (%s, %d so far from it): %s", chunk.seq, chunk.rollout, reason, n, detail)

    def _batch(self, ctx: LaneContext) -> None:
        target = self.cfg.task.ppo.batch_steps
        held: list[int] = []
        steps = 0
        while ctx.running:
            slot = self.filled.get(ctx.stop, stats=ctx.stats)
            if slot is None:
                break
            with ctx.busy():
                held.append(slot)
                steps += self.slots.steps(slot)
                if steps < target:
                    continue
                keep = []
                for s in held:
                    # Re-check lag: a chunk may have aged while waiting for its batch.
                    if self.published_version - self.slots.version(s) > self.max_lag:
                        self.ledger.release(s, "dropped.stale")
                        self.slots.release(s)
                    else:
                        keep.append(s)
                held, steps = [], 0
                if not keep:
                    continue
                keep.sort(key=self.slots.order)  # the same batch whatever the arrival order
                batch = self.slots.stack(keep, self.device)
                for s in keep:
                    self.ledger.release(s, "consumed")
                    self.lags.append(self.published_version - self.slots.version(s))
                    self.slots.release(s)
                del self.lags[:-4096]
            self.batches.put(batch, ctx.stop, stats=ctx.stats)
            ctx.count()
        while (slot := self.filled.get_nowait()) is not None:
            held.append(slot)
        for s in held:  # never-learned slots at shutdown are counted, not lost
            self.ledger.release(s, "dropped.shutdown")
            self.slots.release(s)

    def _learn(self, ctx: LaneContext) -> None:
        task = self.cfg.task
        while ctx.running:
            batch = self.batches.get(ctx.stop, stats=ctx.stats)
            if batch is None:
                return
            with ctx.busy():
                t0 = time.perf_counter()
                try:
                    if task.algorithm == "grpo":
                        data = grpo_batch(batch, task)
                    else:
                        data = gae_batch(self.policy, batch, task.ppo)
                    stats = self.learner.update(data)
                    steps = int(self.group.sum([batch.steps])[0])  # the group's env steps
                except RuntimeError as err:
                    if not ctx.running:  # a rank that stopped first closed the group: not an error
                        log.info("learner group closed while stopping: %s", err)
                        return
                    raise
                self.env_steps += steps
                stats["learn_s"] = time.perf_counter() - t0
                self.learn_stats = {k: float(v) for k, v in stats.items()}
                if stats.get("refused_nonfinite"):  # the same on every rank: no rank numbers a version
                    log.warning("update refused as non-finite: no version from this batch (%d refused so far)",
                                self.learner.updates_refused_nonfinite)
                    continue
                item = self._new_version(checkpoint=(self.policy_version + 1) % self.cfg.task.checkpoint_every == 0)
            self.versions.put(item, ctx.stop, stats=ctx.stats)
            ctx.count()

    def _publish(self, ctx: LaneContext) -> None:
        while ctx.running:
            item = self.versions.get(ctx.stop, stats=ctx.stats)
            if item is None:
                break
            with ctx.busy():
                self.checksums[item.version] = checksum(item.flat)
                for old in [v for v in self.checksums if v <= item.version - 64]:
                    del self.checksums[old]
                self.released_version = item.version  # before sending: see __init__
                if self.publisher is not None:
                    self._send(item)
                # one assignment: status never pairs a version with another version's checksum
                self.published = self.publisher.held.id if self.publisher is not None else (item.version, "")
            ctx.count()

    def _send(self, item: "NewVersion") -> None:
        """Rank 0: reserve the version number on disk, encode, send, log, checkpoint."""
        assert self.publisher is not None and self._versions_csv is not None
        self.high_water = reserve_versions(self.ckpt_dir, item.version, self.high_water)
        v = self.publisher.encode(item.flat)
        m = v.manifest
        if m.version != item.version:
            raise RuntimeError(f"publisher numbered v{m.version} for learned v{item.version}")
        sent = self.publisher.send(v)
        kind = "full" if m.base_version < 0 else "delta"
        self.publish_bytes[f"{kind}_versions"] += 1
        self.publish_bytes[f"{kind}_bytes"] += sent
        self._versions_csv.write(f"{m.version},{m.checksum},{m.encoding},{item.env_steps},{time.time():.3f},{os.getpid()}\n")
        if item.optimizer is not None:
            self._checkpoint(item.version, item.env_steps, item.optimizer)

    def _checkpoint(self, version: int, env_steps: int, optimizer: tuple[dict[str, torch.Tensor], str]) -> None:
        """Checkpoint the weights *as published* with `version` (what every replica holds), with
        the optimizer state taken right after that version was learned."""
        assert self.publisher is not None
        # What replicates, nothing of a frozen base (loaded from its own checkpoint directory)
        sd = {k: v.detach().clone() for k, v in replicated_tensors(self.policy).items()}
        held = self.publisher.held
        with held.lock:
            unflatten_into(held.active, sd, self.layout)
            digest = held.checksum
        try:
            save_checkpoint(self.ckpt_dir, sd, optimizer, version, env_steps, digest)
        except OSError as err:
            log.warning("checkpoint of v%d failed: %s", version, err)

    # -- status -------------------------------------------------------------------------------
    def status_extra(self) -> dict[str, Any]:
        lags = self.lags[-1024:]
        acct = self.fabric.accounting
        published = self.published
        return {
            "published_version": published[0],
            "inbox_depth": self.inbox.depth(),
            "slots_free": self.slots.free_count(),
            "slots_total": self.slots.n_slots,
            "consumed_chunks": acct.get(DATA, "consumed"),
            "dropped_stale": acct.get(DATA, "dropped.stale"),
            "policy_lag_mean": float(np.mean(lags)) if lags else 0.0,
            "policy_lag_p99": sample_percentile(lags, 0.99),
            "policy_lag_counts": {str(k): v for k, v in sorted(dict(self.ingest_lag_counts).items())},
            "updates_refused_nonfinite": self.learner.updates_refused_nonfinite,
            "rank": self.group.rank,
            "world_size": self.group.world_size,
            "checksums": {str(v): c for v, c in sorted(dict(self.checksums).items())[-16:]},
            "resumed_from": None if self.resumed is None else {"version": self.resumed.version, "checksum": self.resumed.checksum},
            "publish_bytes": dict(self.publish_bytes),
            "published_checksum": published[1],
            # what a version carries: all parameters vs the replicated ones (LoRA: adapters, heads)
            "parameters": self._n_parameters,
            "replicated_values": self.layout.numel,
            "base_hash": policy_base_hash(self.policy),
            "learn": self.learn_stats,
        }

    def close(self) -> None:
        # Lanes are joined: when the last learned version is also the last published one, the
        # optimizer state belongs to it and the run's end is checkpointed.
        if self.publisher is not None and self.published_version == self.policy_version > self._first_version:
            self._checkpoint(self.published_version, self.env_steps, optimizer_tensors(self.learner.optimizer))
        if self._versions_csv is not None:
            self._versions_csv.close()
        self.group.close()
        self.ledger.close(clean=not self.failed)


@dataclass
class NewVersion:
    """learn -> publish: one version's weights, and what is checkpointed with it."""

    version: int
    flat: np.ndarray
    #: env steps the group had learned from when this version was made
    env_steps: int
    #: optimizer state right after this version was learned (rank 0, when it is checkpointed)
    optimizer: tuple[dict[str, torch.Tensor], str] | None


def chunk_problem(chunk: TrajectoryChunk, spec: ChunkSpec, newest_version: int) -> tuple[str, str] | None:
    """``(reason, detail)`` when ``chunk`` must not reach the learner, else None: a policy version
    no actor of this group released (``negative_version``, ``future_version``: newer than
    ``newest_version``), so the lag filter always sees a real lag, or what the run's
    :meth:`ChunkSpec.problem` finds (``shape``, ``nonfinite``, ``out_of_range``)."""
    v = chunk.policy_version
    if v < 0:
        return "negative_version", f"policy_version {v} < 0"
    if v > newest_version:
        return "future_version", f"policy_version {v} is newer than the newest released, {newest_version}"
    return spec.problem(chunk)


def _listen_address(cfg: RoleConfig) -> str | None:
    """The address this actor's data plane binds (where its rank talks to the others)."""
    if not cfg.data.listen:
        return None
    return cfg.data.listen[0].split("/", 1)[-1].rpartition(":")[0].strip("[]")


#: decoded chunks the data-plane inbox holds before backpressure
INBOX = 64


if __name__ == "__main__":
    raise SystemExit(main(Actor))
