"""Actor role: the learner. Consumes trajectory chunks, runs PPO, publishes weight versions.

Lanes (and what flows between them):
- ``ingest``:  data-plane inbox -> policy-lag filter -> a free slot of the preallocated pool.
- ``batch``:   gathers slots until one learner batch is full, re-checks lag, stacks it.
- ``learn``:   values and GAE with the current critic, PPO epochs, a new version.
- ``publish``: encodes the version (full / delta with error feedback), signs and sends it to the
               tree; serves snapshots; writes checkpoints. Overlaps the next ``learn``.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..config import RoleConfig, env_group_sizes, resolve_device
from ..fabric import Fabric
from ..fabric.fabric import DATA
from ..fabric.messages import RoleStatus, TrajectoryChunk
from ..learn import PPOLearner, Trajectories, gae_batch, make_policy
from ..learn.envs import probe_spec
from ..learn.grpo import grpo_batch
from ..replication import ParamLayout, flatten, unflatten_into
from .checkpoint import load_checkpoint, save_checkpoint
from ..counters import CounterFile, source_key, split_seq
from .runtime import main
from .slots import SlotPool
from .swimlane import LaneContext, Swimlane, sample_percentile
from .weightsync import WeightPublisher

log = logging.getLogger("dvla.actor")


class Actor:
    def __init__(self, cfg: RoleConfig, fabric: Fabric) -> None:
        self.cfg = cfg
        self.fabric = fabric
        task = cfg.task
        self.device = torch.device(resolve_device(task.device))
        torch.manual_seed(cfg.seed)
        self.obs_spec, self.act_dim = probe_spec(task)  # flat: {"state"}; rgb: rgb/proprio/tokens
        self.policy = make_policy(task.policy, self.obs_spec, self.act_dim, **task.policy_kwargs).to(self.device)
        self.learner = PPOLearner(self.policy, task.ppo, self.device)
        self.layout = ParamLayout.from_state_dict(self.policy.state_dict())
        self.ckpt_dir = Path(cfg.run_dir) / "checkpoints"
        # A restarted actor resumes from its last checkpoint: versions stay monotonic and the
        # first version it publishes is a full one.
        resumed = load_checkpoint(self.ckpt_dir, self.policy, self.learner)
        start = int(resumed["version"]) if resumed else 0
        if resumed:
            log.info("resumed from checkpoint: version %d, %d env steps", start, resumed["env_steps"])
        self.resumed = resumed is not None
        self.publisher = WeightPublisher(fabric, cfg.name, self.layout, cfg.replication, start)
        groups = env_group_sizes(task.envs_per_rollout)  # a chunk holds one env group's columns
        chunks_per_batch = -(-task.ppo.batch_steps // (task.chunk_steps * min(groups)))
        self.slots = SlotPool(
            n_slots=3 * chunks_per_batch + 8, T=task.chunk_steps, n_max=max(groups),
            obs_spec=self.obs_spec, act_dim=self.act_dim, pin=self.device.type == "cuda",
        )
        self.policy_version = start
        self.published_version = start
        self.env_steps = int(resumed["env_steps"]) if resumed else 0  # consumed by the learner
        self.learn_stats: dict[str, float] = {}
        self.lags: list[int] = []
        #: chunks received per lag (newest published version - behaviour version, at ingest),
        #: cumulative:
        #: a reader diffs two readings to get the lag distribution of a window
        self.ingest_lag_counts: dict[int, int] = {}
        self.bytes_published = 0
        #: bytes and count of versions sent, split into full versions and deltas
        self.publish_bytes = {"full_versions": 0, "full_bytes": 0, "delta_versions": 0, "delta_bytes": 0}
        self.receipts = Receipts(CounterFile(cfg.run_dir, cfg.name), fabric, self.slots.n_slots)
        if self.resumed:
            # Before the status queryable exists: status never shows the checkpoint's version
            # below what was published before the restart.
            self._skip_past_replicas()

    # -- wiring -------------------------------------------------------------------------------
    def build(self, sl: Swimlane) -> None:
        f, ppo = self.fabric, self.cfg.task.ppo
        self.inbox = f.subscribe_traj(maxsize=INBOX, expect=TrajectoryChunk)  # rollouts -> ingest
        self.filled = sl.queue("filled", self.slots.n_slots)  # ingest -> batch: slot ids
        self.batches = sl.queue("batches", 1)  # batch -> learn: one stacked Trajectories
        self.versions = sl.queue("versions", 2)  # learn -> publish: flat weights per version
        self.publisher.serve()  # catch-up for children: the published version
        self.max_lag = ppo.max_policy_lag
        sl.lane("ingest", self._ingest)
        sl.lane("batch", self._batch)
        sl.lane("learn", self._learn)
        sl.lane("publish", self._publish)
        # The first version: the initial (or resumed) weights, so rollouts can act at once.
        self.versions.put(self._flat_weights(), threading.Event())

    def _skip_past_replicas(self, wait_s: float = 5.0) -> None:
        """After a restart, continue numbering above every version a replica already holds.

        Versions published after the last checkpoint died with the old process; reusing their
        numbers would make replicas ignore the new weights as stale. Children report what they
        hold in their status (they reconnect to this router within about a second).
        """
        deadline = time.monotonic() + wait_s
        highest = self.published_version
        pending = set(self.cfg.children)
        while pending and time.monotonic() < deadline:
            for name in list(pending):
                for _sender, st in self.fabric.query(self.fabric.keys.status(name), expect=RoleStatus, timeout=0.5):
                    highest = max(highest, int(st.policy_version))
                    pending.discard(name)
            if pending:
                time.sleep(0.2)
        if highest > self.published_version:
            log.info("replicas hold v%d > checkpoint v%d: numbering continues from there", highest, self.published_version)
            self.publisher.renumber(highest)
            self.policy_version = self.published_version = highest

    def _flat_weights(self) -> np.ndarray:
        flat = np.empty(self.layout.numel, np.float32)
        with torch.no_grad():
            flatten(self.policy.state_dict(), self.layout, out=flat)
        return flat

    # -- lanes --------------------------------------------------------------------------------
    def _ingest(self, ctx: LaneContext) -> None:
        while ctx.running:
            with ctx.waiting():
                chunk = self.inbox.get(timeout=0.1)
            if chunk is None:
                self.receipts.tick()  # the fabric's own drops reach the counter file too
                continue
            with ctx.busy():
                src = self.receipts.got(chunk)
                lag = self.published_version - chunk.policy_version
                self.ingest_lag_counts[lag] = self.ingest_lag_counts.get(lag, 0) + 1
                if lag > self.max_lag:
                    self.fabric.accounting.dropped(DATA, "stale", chunk.rollout)
                    self.receipts.count(src, "dropped.stale")
                    continue
                slot = self.slots.acquire(ctx.stop)
                if slot is None:
                    self.receipts.count(src, "dropped.shutdown")
                    return
                err = self.slots.fill(slot, chunk)
                if err is not None:
                    self.slots.release(slot)
                    self.fabric.accounting.rejected(DATA, "shape", chunk.rollout)
                    self.receipts.count(src, "rejected.shape")
                    log.warning("chunk %d from %s rejected: %s", chunk.seq, chunk.rollout, err)
                    continue
                self.receipts.hold(slot, src)
            self.filled.put(slot, ctx.stop, stats=ctx.stats)
            ctx.count()
        # Shutdown: chunks still arriving or queued are counted, never silently lost. Rollouts
        # are stopped first, so a short quiet period catches their last chunks.
        while (chunk := self.inbox.get(timeout=0.5)) is not None:
            self.fabric.accounting.dropped(DATA, "shutdown", chunk.rollout)
            self.receipts.count(self.receipts.got(chunk), "dropped.shutdown")

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
                        self.fabric.accounting.dropped(DATA, "stale", self.slots.rollout(s))
                        self.receipts.release(s, "dropped.stale")
                        self.slots.release(s)
                    else:
                        keep.append(s)
                held, steps = [], 0
                if not keep:
                    continue
                batch = Trajectories.of(self.slots.stack(keep, self.device))
                for s in keep:
                    self.fabric.accounting.add(DATA, "consumed", self.slots.rollout(s))
                    self.receipts.release(s, "consumed")
                    self.lags.append(self.published_version - self.slots.version(s))
                    self.slots.release(s)
                del self.lags[:-4096]
            self.batches.put(batch, ctx.stop, stats=ctx.stats)
            ctx.count()
        while (slot := self.filled.get_nowait()) is not None:
            held.append(slot)
        for s in held:  # never-learned slots at shutdown are counted, not lost
            self.fabric.accounting.dropped(DATA, "shutdown", self.slots.rollout(s))
            self.receipts.release(s, "dropped.shutdown")
            self.slots.release(s)

    def _learn(self, ctx: LaneContext) -> None:
        task = self.cfg.task
        while ctx.running:
            batch = self.batches.get(ctx.stop, stats=ctx.stats)
            if batch is None:
                return
            with ctx.busy():
                t0 = time.perf_counter()
                if task.algorithm == "grpo":
                    data = grpo_batch(batch, task)
                else:
                    data = gae_batch(self.policy, batch, task.ppo)
                stats = self.learner.update(data)
                self.env_steps += batch.steps
                self.policy_version += 1
                stats["learn_s"] = time.perf_counter() - t0
                self.learn_stats = {k: float(v) for k, v in stats.items()}
                flat = self._flat_weights()
            self.versions.put(flat, ctx.stop, stats=ctx.stats)
            ctx.count()

    def _publish(self, ctx: LaneContext) -> None:
        every = 10  # checkpoint cadence (versions); the first version is checkpointed too
        last: np.ndarray | None = None
        while ctx.running:
            flat = self.versions.get(ctx.stop, stats=ctx.stats)
            if flat is None:
                break
            with ctx.busy():
                enc = self.publisher.encode(flat)
                self.published_version = enc.version
                sent = self.publisher.send(enc)
                self.bytes_published += sent
                kind = "full" if enc.encoding == "full" else "delta"
                self.publish_bytes[f"{kind}_versions"] += 1
                self.publish_bytes[f"{kind}_bytes"] += sent
                if enc.version % every == 0 or last is None:
                    self._checkpoint(flat)
                last = flat
            ctx.count()
        if last is not None:
            self._checkpoint(last)

    def _checkpoint(self, flat: np.ndarray) -> None:
        """Checkpoint the published version's weights (not the live, possibly mid-update ones)."""
        sd = {k: v.detach().clone() for k, v in self.policy.state_dict().items()}
        unflatten_into(flat, sd, self.layout)
        try:
            save_checkpoint(self.ckpt_dir, sd, self.learner, self.published_version, self.env_steps)
        except OSError as err:
            log.warning("checkpoint failed: %s", err)

    # -- status -------------------------------------------------------------------------------
    def status_extra(self) -> dict[str, Any]:
        lags = self.lags[-1024:]
        acct = self.fabric.accounting
        return {
            "published_version": self.published_version,
            "inbox_depth": self.inbox.depth(),
            "slots_free": self.slots.free_count(),
            "slots_total": self.slots.n_slots,
            "consumed_chunks": acct.get(DATA, "consumed"),
            "dropped_stale": acct.get(DATA, "dropped.stale"),
            "policy_lag_mean": float(np.mean(lags)) if lags else 0.0,
            "policy_lag_p99": sample_percentile(lags, 0.99),
            "policy_lag_counts": {str(k): v for k, v in sorted(dict(self.ingest_lag_counts).items())},
            "bytes_published": self.bytes_published,
            "publish_bytes": dict(self.publish_bytes),
            "published_checksum": self.publisher.checksum,
            "learn": self.learn_stats,
        }

    def close(self) -> None:
        self.receipts.close()


#: decoded chunks the data-plane inbox holds before backpressure
INBOX = 64


class Receipts:
    """What this actor incarnation did with each rollout incarnation's chunks, in a counter file
    that survives a kill (counters.py): got (out of the inbox), then exactly one of consumed,
    dropped.<reason> or rejected.<reason>; a chunk got but not yet settled is in a slot (or
    between lanes) and dies with the process. The fabric's own per-rollout drops and rejects
    (backpressure, undecodable) are copied along, so the orchestrator can reconcile exactly."""

    def __init__(self, file: CounterFile, fabric: Fabric, n_slots: int) -> None:
        self.file = file
        self.fabric = fabric
        self.n_slots = n_slots
        self._lock = threading.Lock()
        self._src: dict[str, dict[str, int]] = {}
        self._slot: dict[int, str] = {}
        self._last_tick = 0.0
        self._write(clean=False)

    def got(self, chunk: TrajectoryChunk) -> str:
        src = source_key(chunk.rollout, chunk.seq)
        index = split_seq(chunk.seq)[1]
        with self._lock:
            c = self._src.setdefault(src, {"got": 0, "first": index, "last": index})
            c["got"] += 1
            c["first"] = min(c["first"], index)
            c["last"] = max(c["last"], index)
        return src

    def hold(self, slot: int, src: str) -> None:
        with self._lock:
            self._slot[slot] = src
        self._write()

    def count(self, src: str, what: str) -> None:
        with self._lock:
            c = self._src[src]
            c[what] = c.get(what, 0) + 1
        self._write()

    def release(self, slot: int, what: str) -> None:
        with self._lock:
            src = self._slot.pop(slot)
            c = self._src[src]
            c[what] = c.get(what, 0) + 1
        self._write()

    def tick(self) -> None:
        now = time.monotonic()
        if now - self._last_tick >= 0.5:
            self._last_tick = now
            self._write()

    def _write(self, clean: bool = False) -> None:
        with self._lock:  # snapshot and write together: a newer record is never overwritten by an older one
            peers = self.fabric.accounting.snapshot().get(DATA, {}).get("peers", {})
            fabric = {p: {"received": c.get("received", 0), "rejected": c.get("rejected", 0),
                          "backpressure": c.get("dropped.backpressure", 0)} for p, c in peers.items()}
            sources = {k: dict(v) for k, v in self._src.items()}
            self.file.write({"kind": "actor", "sources": sources, "fabric": fabric, "inbox_cap": INBOX,
                             "slots": self.n_slots, "clean": clean})

    def close(self) -> None:
        self._write(clean=True)
        self.file.close()


if __name__ == "__main__":
    raise SystemExit(main(Actor))
