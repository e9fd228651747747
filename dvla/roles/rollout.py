"""Rollout role: simulators plus a frozen inference copy of the policy; streams trajectory chunks.

Lanes (and what flows between them):
- ``sim``:   steps env group A while ``infer`` computes actions for group B (double-buffered
             sampling); writes each transition into its group's chunk, taken from the
             group's pool of chunks allocated once (``ChunkSpec.zeros``).
- ``infer``: policy forward for one group's observations, then hands the group its actions
             (``step_async``: simulator workers start stepping at once); swaps in new weights
             between two batches, never during one.
- ``ship``:  encodes and publishes finished chunks on the data plane and gives them back to
             the pool.
- ``sync``:  receives weight versions into the held weights (see weightsync.py); ``infer``
             installs the newest between two batches (``PolicyPool``).

With ``sim_workers`` (dvla/learn/simworkers.py) the envs live in worker processes, each holding
a slice of both groups: a group's step runs on every worker at once, its arrays in shared
memory; the lanes, the chunks and the policy copy are the same.

Where all the rollout's envs share one simulator scene (ManiSkill on a GPU, docs/envs.md) there
is one group whose steps stay tensors on the sim device (a ``DeviceChunk``), copied to the host
once per chunk. The grouping is :func:`dvla.learn.envs.env_groups` (the actor sizes its slots
from it through ``chunk_envs``).

Modes: ``sync`` (the lock-step baseline) acts in rounds, one per policy version: a group starts
a chunk only while the chunks started in this round hold less than the rollout's share of one
learner batch (``lockstep_steps``); a group that may not start one waits, and once every group
waits, so does the rollout, for the next version. So every chunk is acted on by one version, the
newest, whatever the number of groups. ``sim_only`` (a benchmark baseline) steps the envs with
uniform random actions and infers and ships nothing.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
import torch

from ..config import RoleConfig, resolve_device
from ..fabric import Fabric, TrajectoryChunk
from ..learn import make_env_group, make_policy
from ..learn.policies import extras_spec, sample_actions
from ..learn.envs import EnvSetupError, chunk_spec, env_groups, obs_as_dict, obs_to_torch
from ..learn.grpo import grpo_envs
from ..learn.simworkers import SimWorkers, auto_workers
from ..learn.vector_env import DeviceChunk
from ..ledger import RolloutLedger
from ..replication import HeldWeights, ParamLayout, bind_flat, unflatten_into
from .freelist import FreeList
from .runtime import main
from .swimlane import LaneContext, Swimlane, sample_percentile
from .weightsync import WeightSync, held_status

log = logging.getLogger("dvla.rollout")

#: finished chunks waiting for the ship lane (with the one being shipped, what a killed rollout
#: can take with it). A group's pool holds SHIP_QUEUE + 2 chunks: one being filled, at most
#: SHIP_QUEUE queued and one being published, so the group never waits for a chunk.
SHIP_QUEUE = 8
#: seconds between two counter records sent to the learner (`report_ledger`)
LEDGER_REPORT_S = 2.0


class Shipment(NamedTuple):
    """sim -> ship: a finished chunk, and the pool it goes back to once published."""

    chunk: TrajectoryChunk
    pool: FreeList[TrajectoryChunk]


class Actions(NamedTuple):
    """infer -> sim: what the policy chose for one env group's observations."""

    gid: int
    #: numpy arrays, or tensors on the sim device for a one-scene group
    actions: Any
    logprobs: Any
    #: the policy version that chose them
    version: int
    #: the policy's per-step extras for them (name -> [n, ...]; empty for Gaussian policies)
    extras: dict[str, Any]
    #: the infer lane already handed them to the group (``step_async``); sync mode: the sim lane does
    dispatched: bool = False


@dataclass
class _Group:
    """One env group and the chunk being filled for it."""

    gid: int
    #: an EnvGroup, or a VectorEnvGroup (one scene; its observations are tensors on its device)
    envs: Any
    obs: Any
    t: int = 0
    #: steps recorded since the process started (names the sampling noise of the next one)
    steps: int = 0
    versions: list[int] = field(default_factory=list)
    #: this group's chunks, allocated once
    chunks: FreeList[TrajectoryChunk] | None = None
    #: the chunk being filled, one of `chunks`: each step is written into its arrays
    chunk: TrajectoryChunk | None = None
    #: a one-scene group's steps are recorded here on the sim device, then copied into `chunk`
    #: once per chunk (None: straight into `chunk`)
    dev: DeviceChunk | None = None
    #: per env: undiscounted return and length of the episode in progress
    ep_return: np.ndarray | None = None
    ep_len: np.ndarray | None = None


class PolicyPool:
    """The policy module that serves inference (`active`) and the verified weights it installs
    (`held`, filled by the sync lane).

    The infer lane copies the newest held version into `active` between two batches (one flat
    copy where `bind_flat` could bind the replicated tensors to one tensor). It never waits: when
    the held lock is taken the install is put off to the next batch. Only the replicated tensors
    are held (a LoRA policy's base is not).
    """

    def __init__(self, policy: torch.nn.Module) -> None:
        self.active = policy
        self.active_version = -1
        self.layout = ParamLayout.from_state_dict(policy)
        self.held = HeldWeights(self.layout)
        #: the replicated tensors of `active` as views of one flat tensor (None: per-tensor copies)
        self._bound = bind_flat(policy, self.layout)
        self._installed_updates = 0
        self.swaps = 0
        #: versions held but replaced by a newer one before they were installed
        self.overwritten = 0
        #: installs put off to the next batch because the held weights' lock was taken
        self.swap_deferred = 0

    def maybe_swap(self) -> bool:
        """Called between batches: install the newest held version if it is newer; never waits."""
        held = self.held
        if held.version <= self.active_version:
            return False
        if not held.lock.acquire(blocking=False):
            self.swap_deferred += 1
            return False
        try:
            if held.version <= self.active_version:  # another lane installed it first
                return False
            with torch.no_grad():
                if self._bound is not None:
                    self._bound.copy_(torch.from_numpy(held.active))
                else:
                    unflatten_into(held.active, self.active, self.layout)
            self.overwritten += held.updates - self._installed_updates - 1
            self._installed_updates = held.updates
            self.active_version = held.version
            self.swaps += 1
        finally:
            held.lock.release()
        return True


class Rollout:
    """State of one rollout process; `build` declares its lanes and wiring."""

    def __init__(self, cfg: RoleConfig, fabric: Fabric) -> None:
        self.cfg = cfg
        self.fabric = fabric
        task = cfg.task
        self.device = torch.device(resolve_device(task.rollout_device))
        # Argument validation on every call is a large share of a small batch's inference.
        torch.distributions.Distribution.set_default_validate_args(False)
        self.groups: list[_Group] = []
        self._noise = torch.Generator(device=self.device)
        seed = cfg.seed * 10_000
        # one simulator scene of every env (ManiSkill on a GPU), or two double-buffered groups,
        # stepped here or by simulator worker processes
        workers = auto_workers(cfg.node_rollouts) if cfg.sim_workers == "auto" else cfg.sim_workers
        sizes, one_scene = env_groups(task)
        if workers and one_scene:
            raise EnvSetupError(f"sim_workers {cfg.sim_workers}: worker processes step one-env scenes, and this "
                                "rollout's envs share one simulator scene (env_batching); set env_batching: loop")
        #: the simulator worker processes (None: the envs are stepped in this process)
        self.sim_workers = (SimWorkers(task, sizes, [seed + gid * 1000 for gid in range(len(sizes))], workers,
                                       label=f"{cfg.run_dir}/{cfg.name}", **grpo_envs(task)) if workers else None)
        for gid, size in enumerate(sizes):
            if self.sim_workers is not None:
                envs = self.sim_workers.groups[gid]
            else:
                envs = make_env_group(task, size, seed + gid * 1000, batching="scene" if one_scene else "loop",
                                      **grpo_envs(task))
            self.groups.append(_Group(gid, envs, envs.reset()))
        g0 = self.groups[0].envs
        policy = make_policy(task.policy, g0.obs_spec, g0.act_dim, **task.policy_kwargs)
        self.pool = PolicyPool(policy.to(self.device).eval())
        #: every chunk's arrays: observations, actions, the policy's extras (flow chain, action tokens)
        self.spec = chunk_spec(task, g0.obs_spec, g0.act_dim, extras_spec(policy))
        for g in self.groups:
            g.chunks = FreeList(self.spec.zeros(g.envs.n) for _ in range(SHIP_QUEUE + 2))
            g.chunk = g.chunks.take(threading.Event())
            if g.envs.on_device:
                g.dev = DeviceChunk(self.spec, g.envs.n, g.envs.device)
        #: chunks produced and shipped, in a counter file that survives a kill -9 (dvla/ledger.py)
        self.ledger = RolloutLedger(cfg.run_dir, cfg.name, SHIP_QUEUE)
        self.seq = self.ledger.first_seq
        self.env_steps = 0
        self.episodes = 0
        self.successes = 0
        #: returns and lengths of the most recent finished training episodes (status, TensorBoard)
        self.recent_returns: collections.deque[float] = collections.deque(maxlen=256)
        self.recent_lengths: collections.deque[int] = collections.deque(maxlen=256)
        #: the most recent inference batches' latency, ms (status: p50/p99)
        self.infer_ms: collections.deque[float] = collections.deque(maxlen=512)
        self.sync_mode = cfg.mode == "sync"
        self.sim_only = cfg.mode == "sim_only"
        # sync mode: the version the current round acts with (actions of older ones are recomputed)
        self._round_version = -1
        self._round_steps = 0  # sync mode: env steps of the chunks started in this round
        self._parked: list[int] = []  # sync mode: groups waiting for the next round
        self._ready = threading.Event()
        self._ledger_sent = 0.0

    @property
    def policy_version(self) -> int:
        return self.pool.active_version

    # -- wiring -------------------------------------------------------------------------------
    def build(self, sl: Swimlane) -> None:
        self.to_infer = sl.queue("obs", len(self.groups))  # group ids whose obs await actions
        self.to_sim = sl.queue("actions", len(self.groups))  # Actions for a group
        self.to_ship = sl.queue("chunks", SHIP_QUEUE)  # Shipment: a finished chunk and its pool
        self.weights = WeightSync.of_role(  # verified versions from the parent -> pool.held
            self.cfg, self.fabric, self.pool.held, lambda _v: self._ready.set(), policy=self.pool.active)
        sl.lane("sim", self._sim_random if self.sim_only else self._sim)
        sl.lane("infer", self._infer)
        sl.lane("ship", self._ship)
        sl.lane("sync", self.weights.run)
        self.fabric.on_traj_unmatched(self.ledger.add_break)  # a broken link: its buffers' chunks are lost

    # -- lanes --------------------------------------------------------------------------------
    def _wait_for_weights(self, ctx: LaneContext) -> None:
        # No acting before the first verified weights: random initial weights on every rollout
        # would make their log-probs meaningless to the learner.
        while ctx.running and not self._ready.is_set():
            with ctx.waiting():
                self._ready.wait(0.1)

    def _infer(self, ctx: LaneContext) -> None:
        self._wait_for_weights(ctx)
        while ctx.running:
            gid = self.to_infer.get(ctx.stop, stats=ctx.stats)
            if gid is None:
                return
            with ctx.busy():
                item = self._act(gid)
                if not self.sync_mode:  # sync: the sim lane first checks the version
                    self.groups[gid].envs.step_async(item.actions)
                    item = item._replace(dispatched=True)
            self.to_sim.put(item, ctx.stop, stats=ctx.stats)
            ctx.count()

    def _act(self, gid: int) -> Actions:
        """Install pending weights, then the actions of group ``gid`` for its observations. The
        latency recorded includes the install (a copy of the replicated tensors): what a new
        version costs the batch that first uses it."""
        t0 = time.perf_counter()
        self.pool.maybe_swap()
        g = self.groups[gid]
        # Sampling noise is a function of (process seed, group, step): the same seed replays the
        # same actions whatever the threads' timing (an action recomputed for new weights included).
        # (A generator of the infer lane's own: simulators may draw from torch's global one.)
        self._noise.manual_seed(noise_seed(self.cfg.seed, gid, g.steps))
        with torch.no_grad():
            obs = obs_to_torch(g.obs, self.device)  # no copy where the scene is on this device
            action, logprob, extras = sample_actions(self.pool.active, obs, generator=self._noise)
            action, logprob = action.float(), logprob.float()
            if not g.envs.on_device:
                action, logprob = action.cpu().numpy(), logprob.cpu().numpy()
                extras = {k: v.cpu().numpy() for k, v in extras.items()}
        ms = (time.perf_counter() - t0) * 1e3
        self.infer_ms.append(ms)
        return Actions(gid, action, logprob, self.pool.active_version, extras)

    def _sim(self, ctx: LaneContext) -> None:
        for g in self.groups:
            self._next_step(g, ctx)
        while ctx.running:
            if self._parked and len(self._parked) == len(self.groups):  # sync: the round is shipped
                self._next_round(ctx)
                continue
            a = self.to_sim.get(ctx.stop, stats=ctx.stats)
            if a is None:
                return
            g = self.groups[a.gid]
            if a.version < self._round_version:  # sync mode: computed before the round's weights
                self.to_infer.put(a.gid, ctx.stop, stats=ctx.stats)
                continue
            with ctx.busy():
                if not a.dispatched:
                    g.envs.step_async(a.actions)
                self._record_step(g, a, g.envs.step_wait())
                ctx.count(g.envs.n)
            if self.sync_mode:
                self._round_version = max(self._round_version, a.version)
            if g.t == self.spec.T:
                self._finish_chunk(g, ctx)
            self._next_step(g, ctx)

    def _next_step(self, g: _Group, ctx: LaneContext) -> None:
        """Send ``g`` for its next actions; in sync mode a group about to start a chunk waits
        (parked) when this round's chunks already hold the rollout's share."""
        if self.sync_mode and g.t == 0:
            if self._round_steps >= max(self.cfg.lockstep_steps, 1):  # (at least one chunk a round)
                self._parked.append(g.gid)
                return
            self._round_steps += self.spec.T * g.envs.n
        self.to_infer.put(g.gid, ctx.stop, stats=ctx.stats)

    def _next_round(self, ctx: LaneContext) -> None:
        """Sync mode, every group parked: wait for a version newer than this round's, then start
        the next round with the parked groups (in the order they finished)."""
        with ctx.waiting():
            while ctx.running and self.pool.active_version <= self._round_version:
                self.pool.maybe_swap()
                ctx.sleep(0.005)
        self._round_version = self.pool.active_version
        self._round_steps = 0
        parked, self._parked = self._parked, []
        for gid in parked:
            self._next_step(self.groups[gid], ctx)

    def _sim_random(self, ctx: LaneContext) -> None:
        """sim_only mode: step every group with uniform random actions; nothing leaves the process."""
        rng = np.random.default_rng(self.cfg.seed)

        def start(e: Any) -> None:  # every group in flight at once: all the workers step
            e.step_async(rng.uniform(e.action_low, e.action_high, (e.n, e.act_dim)).astype(np.float32))

        for g in self.groups:
            start(g.envs)
        while ctx.running:
            for g in self.groups:
                with ctx.busy():
                    e = g.envs
                    step = e.step_wait()
                    g.obs = step.next_obs
                    self.env_steps += e.n
                    self.episodes += int(step.episode_done.sum())
                    start(e)
                ctx.count(e.n)

    def _record_step(self, g: _Group, a: Actions, step: Any) -> None:
        """Write one transition of ``g``: the observations acted on (``g.obs``, still intact: a
        worker writes the next ones into the other buffer), ``a`` and the step's result."""
        actions, logprobs, version = a.actions, a.logprobs, a.version
        m, t = g.dev or g.chunk, g.t  # numpy into the chunk, or tensors on the sim device
        for k, v in obs_as_dict(g.obs).items():
            m.obs[k][t] = v
        m.actions[t] = actions  # as sampled: the log-probs are of these, the env clips
        m.logprobs[t] = logprobs
        for k, v in a.extras.items():
            m.extras[k][t] = v
        m.rewards[t] = step.reward
        m.terminated[t] = step.terminated
        m.truncated[t] = step.truncated
        m.success[t] = step.success
        for k, v in obs_as_dict(step.final_obs).items():
            m.final_obs[k][t] = v
        g.obs = step.next_obs
        g.versions.append(version)
        g.t += 1
        g.steps += 1
        self.env_steps += g.envs.n
        if g.ep_return is None:  # beside the rewards: numpy, or tensors on the sim device
            g.ep_return, g.ep_len = np.zeros(g.envs.n, np.float64), np.zeros(g.envs.n, np.int64)
            if g.envs.on_device:
                g.ep_return, g.ep_len = (torch.from_numpy(x).to(g.envs.device) for x in (g.ep_return, g.ep_len))
        g.ep_return += step.reward
        g.ep_len += 1
        done = int(step.episode_done.sum())
        if done:
            self.episodes += done
            self.successes += int((step.episode_done & step.success).sum())
            ended = step.episode_done
            self.recent_returns.extend(g.ep_return[ended].tolist())
            self.recent_lengths.extend(g.ep_len[ended].tolist())
            g.ep_return[ended] = 0.0
            g.ep_len[ended] = 0

    def _finish_chunk(self, g: _Group, ctx: LaneContext) -> None:
        for k, v in obs_as_dict(g.obs).items():
            (g.dev or g.chunk).next_obs[k][...] = v
        if g.dev is not None:
            g.dev.copy_to(g.chunk)  # the chunk's one device -> host copy
        # A new message object around the same arrays: the per-chunk fields are frozen.
        chunk = dataclasses.replace(g.chunk, rollout=self.cfg.name, seq=self.seq, policy_version=min(g.versions),
                                    created_ns=time.time_ns())
        self.seq += 1
        g.t = 0
        g.versions = []
        # Produced = handed to the ship lane; a chunk finished while stopping never is.
        if self.to_ship.put(Shipment(chunk, g.chunks), ctx.stop, stats=ctx.stats):
            self.ledger.add_produced()
        else:
            g.chunks.give(chunk)
        nxt = g.chunks.take(ctx.stop)  # never waits (SHIP_QUEUE)
        if nxt is None:
            return  # stopping
        g.chunk = nxt

    def _ship(self, ctx: LaneContext) -> None:
        while ctx.running:
            shipment = self.to_ship.get(ctx.stop, stats=ctx.stats)
            if shipment is None:
                break
            # While no learner subscribes (the actor is restarting), a put would go nowhere:
            # hold the chunk instead, and let the full ship queue pause the simulators.
            with ctx.waiting():
                while ctx.running and not self.fabric.traj_matched():
                    ctx.sleep(0.05)
            with ctx.busy():
                self._publish(shipment)
                if self.cfg.report_ledger and time.monotonic() - self._ledger_sent >= LEDGER_REPORT_S:
                    self._report_ledger()
            ctx.count()
        # Flush what is already finished so that the accounting identity holds at shutdown.
        while (shipment := self.to_ship.get_nowait()) is not None:
            self._publish(shipment)

    def _await_receipt(self) -> None:
        """Before the fabric closes: wait (bounded) until the learner has the last chunk shipped,
        since closing the data session can lose what is still in the link's buffers (RolloutLedger
        .await_receipt); say what it did not confirm."""
        learners = self.cfg.actors
        wait = self.ledger.await_receipt(self.fabric, learners)
        if wait.unconfirmed:
            log.warning("%s: the last %d of %d chunks shipped were not confirmed by %s after %.1f s (%d receipt "
                        "queries on %s: %s); closing the data session may lose them", self.cfg.name,
                        wait.unconfirmed, self.ledger.shipped, ", ".join(learners), wait.waited_s, wait.queries,
                        ", ".join(self.fabric.keys.receipt(a) for a in learners), wait.why)
        elif wait.queries:
            log.info("%s: %s has all %d chunks shipped (confirmed after %.2f s, %d receipt queries)", self.cfg.name,
                     ", ".join(learners), self.ledger.shipped, wait.waited_s, wait.queries)

    def _report_ledger(self) -> None:
        """Send the counter record to the learner (its copy is the run's: `report_ledger`)."""
        self._ledger_sent = time.monotonic()
        try:
            self.fabric.publish_ctrl(self.fabric.keys.ledger(self.cfg.name), self.ledger.record())
        except Exception as err:  # the link is down: the next report (or the last) carries it
            log.warning("%s: ledger record not sent: %s", self.cfg.name, err)

    def _publish(self, shipment: Shipment) -> None:
        try:
            nbytes = self.fabric.publish_traj(shipment.chunk)  # encoded: the arrays are free again
        finally:
            shipment.pool.give(shipment.chunk)
        self.ledger.add_shipped(nbytes)

    # -- status -------------------------------------------------------------------------------
    def status_extra(self) -> dict[str, Any]:
        ms = list(self.infer_ms)
        return {
            # envs per group; one_scene: they share one simulator scene stepped as a batch
            "env_groups": [g.envs.n for g in self.groups],
            "one_scene": bool(self.groups[0].envs.on_device),
            "chunks_shipped": self.ledger.shipped,
            "bytes_shipped": self.ledger.bytes_shipped,
            # times the trajectory link lost the learner after shipping (what was in it is lost)
            "link_breaks": self.ledger.breaks_total,
            "episodes": self.episodes,
            "train_success_rate": self.successes / self.episodes if self.episodes else 0.0,
            # copies first: the sim lane appends while status runs (list() of a deque is atomic)
            "episode_return_mean": _mean(list(self.recent_returns)),
            "episode_len_mean": _mean(list(self.recent_lengths)),
            "infer_ms_p50": sample_percentile(ms, 0.5),
            "infer_ms_p99": sample_percentile(ms, 0.99),
            "swaps": self.pool.swaps,
            "swap_deferred": self.pool.swap_deferred,
            "versions_overwritten": self.pool.overwritten,
            "weights": self.weights.status(),
            # per simulator worker: pid, envs, busy/wait seconds and shares of its lifetime
            "sim_workers": self.sim_workers.status() if self.sim_workers is not None else [],
            **held_status(self.pool.held),
        }

    def close(self) -> None:
        # A chunk queued by sim just as the ship lane finished its flush: ship it now (the lanes
        # are joined, the fabric is still open).
        while hasattr(self, "to_ship") and (chunk := self.to_ship.get_nowait()) is not None:
            self._publish(chunk)
        self._await_receipt()
        self.ledger.close()
        if self.cfg.report_ledger:  # the final, clean record
            self._report_ledger()
        for g in self.groups:
            g.envs.close()
        if self.sim_workers is not None:
            self.sim_workers.close()


def noise_seed(process_seed: int, group: int, step: int) -> int:
    """The seed of one step's sampling noise for one env group of one rollout: a 64-bit hash of
    all three numbers. (Packing them side by side is not enough: torch's CPU generator keeps only
    a seed's low 32 bits, so every group of every rollout of every run would draw the same noise
    at the same step.)"""
    entropy = (process_seed % 2**64, group % 2**64, step % 2**64)
    return int(np.random.SeedSequence(entropy).generate_state(1, np.uint64)[0])


def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else 0.0


if __name__ == "__main__":
    raise SystemExit(main(Rollout))
