"""`dvla bench swimlane`: do the lanes overlap? Real runs of `dvla up` (real processes, real
ManiSkill, real Zenoh), each figure compared with a baseline measured in the same invocation.

Two workloads, each run in two modes on the same topology, env and policy:

* **default**: the topology given (``topologies/local.yaml``) without its evaluator (evaluation
  is not part of the training pipeline). Placement ``split`` (the default where cores 0 and 1
  exist): the rollouts' ``sim`` lanes alone on core 0, every other thread of every role (the
  rollouts' inference, shipping, weight sync and Zenoh I/O, the actor, the replicator) on core 1,
  as on a machine whose policy runs on an accelerator; ``split-roles``: whole rollout processes on
  core 0, the actor and the replicator on core 1; ``file``: where the file puts the roles (on two
  cores, unpinned, the learner's share of the CPU then caps the ratio: ``ceiling_from_learner``).
  ``sim_only`` (the same rollout processes stepping uniform random actions, nothing inferred,
  shipped or learned) against ``async`` (training): ``async_over_sim_only`` = learner-consumed
  env steps/s ÷ simulated env steps/s, where the simulated rate is the mean of the sim_only runs
  just before and just after the async run (a closing sim_only run follows the last pair). The
  bench's rollouts time their ``env.step`` calls in CPU seconds, so each run also reports what a step
  costs the simulator in that mode (``env_step_cpu_ms``): a learning policy's steps cost more than
  random actions' (shorter episodes, so more resets; contacts with the object), and
  ``async_over_sim_only_equal_step_cost`` is the ratio with that difference taken out. The async
  run also measures RSS growth over the steady state, policy lag and the inference latency split
  by weight swaps (its rollouts are :mod:`benchmarks.swimlane_probe`'s, which keep that split).
* **balanced**: the same task with the rollouts (and the replicator) pinned to core 0 and the
  actor to core 1, and PPO epochs chosen so that the learner needs about as long per batch as
  the rollouts need to sample one. ``sync`` (lock-step: sample a batch, ship, learn, publish,
  wait for the new weights) against ``async``: ``async_over_sync``; with equal halves the ideal
  is 2.

Every run is started through the orchestrator (:class:`dvla.orchestrator.run.Up`) and read
through its status collection: after the first env step and a warm-up, a reading of every
role's status opens the window and another closes it; rates, lane utilisation, latency and lag
distributions are differences between the two (the roles keep cumulative counters). RSS comes
from ``/proc/<pid>/status`` of every role process, sampled once per status round.
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import shutil
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from dvla.config import BudgetConfig, NodeConfig, RackConfig, RolePlacement, Topology
from dvla.fabric.messages import RoleStatus
from dvla.orchestrator.plan import role_cpus
from benchmarks.ports import free_port_block

from .stats import histogram_diff, histogram_percentile, weighted_percentile
from .swimlane_probe import ProbeWrapper

HEADLINE_KEYS = (
    "sim_only_sps",
    "async_sps",
    "async_over_sim_only",
    "ceiling_from_learner",
    "step_cost_ratio",
    "async_over_sim_only_equal_step_cost",
    "balanced_async_sps",
    "sync_sps",
    "async_over_sync",
    "infer_p99_ms_during_swap",
    "infer_p99_ms_no_swap",
    "swap_over_no_swap_p99",
    "rss_growth_pct",
    "policy_lag_mean",
    "policy_lag_p99",
)
"""Top-level figures every result holds (``balanced_async_sps`` is the balanced workload's
``async_sps``; the default workload's is ``async_sps``)."""

GOALS = {
    "async_over_sim_only": (">=", 0.85),
    "async_over_sync": (">=", 1.7),
    "swap_over_no_swap_p99": ("<=", 1.1),
}

STARTUP_LIMIT_S = 180.0
"""A run whose rollouts have not stepped by then is abandoned (an error, not a figure)."""


@dataclass(frozen=True, kw_only=True)
class Profile:
    """Windows of one bench invocation (seconds)."""

    #: after the first env step, before the window opens (first versions, caches, JIT)
    warmup_s: float = 30.0
    #: measurement window of each throughput run
    window_s: float = 60.0
    #: steady-state window of the default async run, over which RSS growth is measured
    rss_window_s: float = 600.0
    #: PPO update epochs of the balanced workload (the default workload keeps the file's); when
    #: the async run finds learner and rollouts more than 20% apart per batch, the epochs are
    #: rescaled by their ratio and the pair is measured again (once)
    balanced_epochs: int = 16
    #: learner batch override (None: the topology's)
    batch_steps: int | None = None
    #: each workload's pair of runs, this many times (alternating), for the spread
    repeats: int = 1
    #: tiny windows: checks the machinery, not the speed
    quick: bool = False


QUICK = Profile(warmup_s=6.0, window_s=12.0, rss_window_s=12.0, balanced_epochs=4, batch_steps=400, quick=True)


# --------------------------------------------------------------------------------------------
# Topologies
# --------------------------------------------------------------------------------------------


def _task(topo: Topology, profile: Profile, epochs: int | None) -> Any:
    ppo = topo.task.ppo
    if profile.batch_steps is not None:
        ppo = dataclasses.replace(ppo, batch_steps=profile.batch_steps)
    if epochs is not None:
        # Every epoch runs: with the KL early stop a learner batch takes anywhere from one epoch
        # to all of them, and the learner's time per batch could not be set by the epochs.
        ppo = dataclasses.replace(ppo, update_epochs=epochs, target_kl=None)
    # Runs end when the window does: no step or success budget may stop them first.
    budget = BudgetConfig(max_env_steps=None, until_success=None, max_wall_s=None)
    return dataclasses.replace(topo.task, ppo=ppo, budget=budget)


PLACEMENTS = ("split", "split-roles", "file")
"""Placements of the default workload; see :func:`default_workload`."""


def default_workload(topo: Topology, profile: Profile, placement: str = "file") -> Topology:
    """The topology's task without evaluators, budgets off, placed by ``placement``:

    * "split": the simulators alone on core 0 (the rollouts' ``sim`` lanes, ``lane_cpus``),
      everything else on core 1: the rollouts' inference, shipping and weight sync, their Zenoh
      I/O threads, the actor and the replicator (:func:`split_lanes`). The simulators' core then
      does nothing but simulate, as on a machine whose policy runs on an accelerator;
    * "split-roles": whole rollout processes on core 0, the actor and the replicator on core 1
      (:func:`split_nodes`): the rollouts' own inference and I/O share the simulators' core;
    * "file": the roles where the file puts them.
    """
    if placement == "split":
        return dataclasses.replace(topo, run="swl-default", task=_task(topo, profile, None), racks=(split_lanes(topo),))
    if placement == "split-roles":
        return dataclasses.replace(topo, run="swl-default", task=_task(topo, profile, None),
                                   racks=(split_nodes(topo, with_replicator_on_sim=False),))
    if placement != "file":
        raise ValueError(f"placement must be one of {', '.join(PLACEMENTS)}, got {placement!r}")
    racks = []
    for rack in topo.racks:
        nodes = []
        for node in rack.nodes:
            roles = tuple(r for r in node.roles if r.role != "evaluator")
            nodes.append(dataclasses.replace(node, roles=roles))
        racks.append(dataclasses.replace(rack, nodes=tuple(nodes)))
    return dataclasses.replace(topo, run="swl-default", task=_task(topo, profile, None), racks=tuple(racks))


def _rollout_count(topo: Topology) -> int:
    return max(1, sum(r.count for _rack, n in topo.nodes() for r in n.roles if r.role == "rollout"))


def split_lanes(topo: Topology) -> RackConfig:
    """One node on core 1 holding every role; the rollouts' ``sim`` lanes pinned to core 0."""
    rollout = RolePlacement(role="rollout", count=_rollout_count(topo), lane_cpus={"sim": (0,)})
    node = NodeConfig(name="host", cpus=(1,), roles=(RolePlacement(role="actor"), RolePlacement(role="replicator"), rollout))
    return RackConfig(name="rack0", nodes=(node,))


def balanced_workload(topo: Topology, profile: Profile, epochs: int) -> Topology:
    """Same task; rollouts and replicator on core 0, the actor alone on core 1."""
    return dataclasses.replace(topo, run="swl-balanced", task=_task(topo, profile, epochs),
                               racks=(split_nodes(topo, with_replicator_on_sim=True),))


def split_nodes(topo: Topology, *, with_replicator_on_sim: bool) -> RackConfig:
    """One rack of two nodes: `sim` on core 0 with the topology's rollouts, `learn` on core 1 with
    the actor; the replicator on either. The learner then never takes CPU from the simulators,
    as when it runs on its own GPU."""
    replicator = (RolePlacement(role="replicator"),)
    sim = NodeConfig(
        name="sim", cpus=(0,),
        roles=(replicator if with_replicator_on_sim else ()) + (RolePlacement(role="rollout", count=_rollout_count(topo)),),
    )
    learn = NodeConfig(name="learn", cpus=(1,),
                       roles=(RolePlacement(role="actor"),) + (() if with_replicator_on_sim else replicator))
    return RackConfig(name="rack0", nodes=(learn, sim))


def _cores_of(node: NodeConfig, role: RolePlacement, lane: str | None, cpus: int) -> set[int]:
    """Cores a role's thread runs on: its lane's pinning, else the role's, else the node's."""
    if lane is not None and role.lane_cpus and lane in role.lane_cpus:
        return set(role.lane_cpus[lane])
    pinned = role_cpus(node, role)
    return set(pinned) if pinned else set(range(cpus))


def learner_ceiling(topo: Topology, share: float | None, cpus: int) -> float | None:
    """The simulators' ceiling left by the learner: 1 - its share of a core / the cores they
    share, or 1.0 when the actor's cores and the simulators' (the rollouts' ``sim`` lanes) are
    disjoint."""
    if share is None:
        return None
    sim_cpus: set[int] = set()
    learn_cpus: set[int] = set()
    for _rack, node in topo.nodes():
        for role in node.roles:
            if role.role == "rollout":
                sim_cpus |= _cores_of(node, role, "sim", cpus)
            elif role.role == "actor":
                learn_cpus |= _cores_of(node, role, "learn", cpus)
    if sim_cpus and learn_cpus and not sim_cpus & learn_cpus:
        return 1.0
    return 1 - share / max(1, len(sim_cpus) or cpus)


def placement_of(topo: Topology) -> list[dict[str, Any]]:
    out = []
    for _rack, n in topo.nodes():
        roles: dict[str, Any] = {}
        for r in n.roles:
            entry: dict[str, Any] = {"count": r.count}
            if r.cpus is not None:
                entry["cpus"] = list(r.cpus)
            if r.lane_cpus:
                entry["lane_cpus"] = {k: list(v) for k, v in r.lane_cpus.items()}
            roles[r.role] = entry if len(entry) > 1 else r.count
        out.append({"node": n.name, "cpus": list(n.cpus) if n.cpus else "unpinned", "roles": roles})
    return out


# --------------------------------------------------------------------------------------------
# One measured run
# --------------------------------------------------------------------------------------------


def rss_kib(pid: int) -> int | None:
    """Resident set size of a process (KiB), or None once it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return None


@dataclass
class _Window:
    """State machine of one run: wait for steps, warm up, open, sample, close."""

    warmup_s: float
    window_s: float
    mode: str
    first_step: float | None = None
    opened: dict[str, RoleStatus] | None = None
    opened_at: float | None = None
    closed: dict[str, RoleStatus] | None = None
    rss: dict[str, list[tuple[float, int]]] = field(default_factory=dict)
    pids: dict[str, int] = field(default_factory=dict)
    ticks: list[tuple[float, int, int]] = field(default_factory=list)  # (t, consumed, produced)
    error: str | None = None
    last_consumed: int = -1


def _all_answered(statuses: dict[str, RoleStatus], expected: list[str]) -> bool:
    return all(n in statuses for n in expected)


def _consumed(statuses: dict[str, RoleStatus]) -> int:
    return sum(s.env_steps for s in statuses.values() if s.kind == "actor")


def measure_run(
    topo: Topology, mode: str, warmup_s: float, window_s: float, runs_root: Path, base_port: int | None,
    progress: Callable[[str], None],
) -> dict[str, Any]:
    """Start `topo` in `mode`, measure one window after warm-up, stop it; figures as a dict.

    ``base_port`` None: a block of ports free at this moment.
    """
    from dvla.orchestrator.run import Up, UpOptions

    topo = dataclasses.replace(topo, mode=mode)  # type: ignore[arg-type]
    w = _Window(warmup_s, window_s, mode)
    t_start = time.monotonic()

    def tick(u: Up) -> None:
        m = u.monitor
        if m is None or m.last is None:
            return
        now = time.monotonic()
        statuses = m.last.statuses
        expected = [p.config.name for p in u.plan.processes]
        if w.first_step is None:
            if any(s.kind == "rollout" and s.env_steps > 0 for s in statuses.values()):
                w.first_step = now
                progress(f"{topo.run}/{mode}: first env step after {now - t_start:.0f} s; warming up {warmup_s:.0f} s")
            elif now - t_start > STARTUP_LIMIT_S:
                w.error = f"no env step within {STARTUP_LIMIT_S:.0f} s"
                u.interrupt()
            return
        # The learner consumes whole batches: a window that opens and closes right after a batch
        # was learned holds a whole number of batches, so its rate is not quantised by them.
        batch_done = mode == "sim_only" or _consumed(statuses) != w.last_consumed
        w.last_consumed = _consumed(statuses)
        # Warm-up lasts warmup_s and, when learning, at least two learner batches: on a slow
        # machine one batch can take longer than the warm-up, and the first ones start cold.
        warm = mode == "sim_only" or _consumed(statuses) >= 2 * topo.task.ppo.batch_steps
        if w.opened is None:
            if now - w.first_step >= warmup_s and warm and batch_done and _all_answered(statuses, expected):
                w.opened, w.opened_at = dict(statuses), now
                w.pids = u.launcher.pids()
                progress(f"{topo.run}/{mode}: window open for {window_s:.0f} s")
            return
        if w.closed is not None:
            return
        for name, pid in w.pids.items():
            r = rss_kib(pid)
            if r is not None:
                w.rss.setdefault(name, []).append((now - w.opened_at, r))  # type: ignore[operator]
        consumed = _consumed(statuses)
        produced = sum(s.env_steps for s in statuses.values() if s.kind == "rollout")
        w.ticks.append((now - w.opened_at, consumed, produced))  # type: ignore[operator]
        elapsed = now - w.opened_at  # type: ignore[operator]
        overdue = elapsed >= 2 * window_s + 120  # a stalled learner must not hold the bench forever
        if elapsed >= window_s and (batch_done or overdue) and _all_answered(statuses, expected):
            w.closed = dict(statuses)
            u.interrupt()

    port = base_port if base_port is not None else free_port_block()
    opts = UpOptions(runs_root=runs_root, base_port=port, max_restarts=0, fresh=True)
    u = Up(topo, opts, on_tick=tick)
    u.launcher.wrap = ProbeWrapper()  # rollouts that also split their inference latency by swaps
    try:
        code: int | None = u.run()
    except (ConnectionError, RuntimeError, OSError) as err:  # e.g. the ctrl plane never came up
        code, w.error = None, f"{type(err).__name__}: {err}"
    result = json.loads((u.run_dir / "result.json").read_text()) if (u.run_dir / "result.json").exists() else {}
    if w.error is None and (w.opened is None or w.closed is None):
        w.error = f"run ended before the window closed ({u.reason}); events: {u.events[-3:]}"
    out: dict[str, Any] = {
        "run": topo.run, "mode": mode, "exit_code": code, "reason": u.reason,
        "wall_s": time.monotonic() - t_start,
        "startup_s": None if w.first_step is None else w.first_step - t_start,
        "accounting": result.get("accounting"), "error": w.error,
    }
    if w.error is not None:
        out["events"] = u.events[-10:]
        return out
    out.update(window_figures(w.opened, w.closed, topo))  # type: ignore[arg-type]
    out["rss"] = rss_figures(w.rss)
    # Produced, not consumed: the learner consumes in whole batches, which makes short intervals
    # of consumed steps jump between 0 and several batches.
    out["produced_sps_intervals"] = interval_rates(w.ticks, 15.0, "produced")
    return out


# --------------------------------------------------------------------------------------------
# Figures from two readings
# --------------------------------------------------------------------------------------------


def _dt(a: RoleStatus, b: RoleStatus) -> float:
    return max(1e-9, (b.time_ns - a.time_ns) / 1e9)


def lane_figures(a: RoleStatus, b: RoleStatus) -> dict[str, dict[str, float]]:
    """Per lane over the window: busy and wait fractions, items/s."""
    dt = _dt(a, b)
    out = {}
    for lane, sb in b.lanes.items():
        sa = a.lanes.get(lane, {})
        items = int(sb.get("items", 0.0) - sa.get("items", 0.0))
        out[lane] = {
            "utilisation": round((sb.get("busy_s", 0.0) - sa.get("busy_s", 0.0)) / dt, 4),
            "wait_fraction": round((sb.get("wait_s", 0.0) - sa.get("wait_s", 0.0)) / dt, 4),
            "items_per_s": round((sb.get("items", 0.0) - sa.get("items", 0.0)) / dt, 3),
            "items": items,
            "busy_s": sb.get("busy_s", 0.0) - sa.get("busy_s", 0.0),
        }
        if "cpu_s" in sb and "cpu_s" in sa:  # the lane thread's own CPU time (busy is wall time)
            cpu = sb["cpu_s"] - sa["cpu_s"]
            out[lane]["cpu_s"] = cpu
            out[lane]["cpu_fraction"] = round(cpu / dt, 4)
            out[lane]["cpu_ms_per_item"] = round(1e3 * cpu / items, 4) if items else None
    return out


def window_figures(a: dict[str, RoleStatus], b: dict[str, RoleStatus], topo: Topology) -> dict[str, Any]:
    """Rates, lane utilisation, batch times, latency and lag over the window [a, b]."""
    batch = topo.task.ppo.batch_steps
    roles = sorted(set(a) & set(b))
    actors = [n for n in roles if b[n].kind == "actor"]
    rollouts = [n for n in roles if b[n].kind == "rollout"]
    consumed = sum((b[n].env_steps - a[n].env_steps) / _dt(a[n], b[n]) for n in actors)
    produced = sum((b[n].env_steps - a[n].env_steps) / _dt(a[n], b[n]) for n in rollouts)
    lanes = {n: lane_figures(a[n], b[n]) for n in roles}
    out: dict[str, Any] = {
        "window_s": statistics.mean(_dt(a[n], b[n]) for n in roles),
        "consumed_sps": consumed,
        "produced_sps": produced,
        "lanes": lanes,
        "batch_steps": batch,
        "update_epochs": topo.task.ppo.update_epochs,
        "placement": {n: b[n].extra.get("placement") for n in roles},
    }
    if actors:
        ab, aa = b[actors[0]], a[actors[0]]
        out["versions"] = int(ab.extra.get("published_version", 0)) - int(aa.extra.get("published_version", 0))
        learn = lanes[actors[0]].get("learn", {})
        out["learner_batch_s"] = learn["busy_s"] / learn["items"] if learn.get("items") else None
        lag = histogram_diff(ab.extra.get("policy_lag_counts", {}), aa.extra.get("policy_lag_counts", {}))
        out["policy_lag"] = lag_figures(lag)
        out["dropped_stale"] = int(ab.extra.get("dropped_stale", 0)) - int(aa.extra.get("dropped_stale", 0))
    # Time the rollouts need to sample one learner batch, all of them together.
    out["rollout_batch_s"] = batch / produced if produced > 0 else None
    # CPU the simulators' threads spend per env step: what separates "the simulators got less
    # CPU" from "each step cost more" (a busy lane's wall time cannot tell them apart).
    sims = [lanes[n]["sim"] for n in rollouts if "cpu_s" in lanes[n].get("sim", {})]
    steps = sum(x["items"] for x in sims)
    out["sim_cpu_ms_per_step"] = 1e3 * sum(x["cpu_s"] for x in sims) / steps if sims and steps else None
    out["sim_cpu_cores"] = sum(x["cpu_fraction"] for x in sims) if sims else None
    # What one env step costs the simulator itself (CPU inside env.step, resets included), and
    # how often episodes end: a policy that solves the task ends episodes sooner (more resets)
    # and pushes the object (more contacts) than uniform random actions do.
    stepped = sum(b[n].env_steps - a[n].env_steps for n in rollouts)
    step_cpu = sum(float(b[n].extra.get("env_step_cpu_s", 0.0)) - float(a[n].extra.get("env_step_cpu_s", 0.0))
                   for n in rollouts if "env_step_cpu_s" in b[n].extra)
    episodes = sum(int(b[n].extra.get("episodes", 0)) - int(a[n].extra.get("episodes", 0)) for n in rollouts)
    out["env_step_cpu_ms"] = 1e3 * step_cpu / stepped if stepped and step_cpu > 0 else None
    out["episodes_per_1k_steps"] = 1e3 * episodes / stepped if stepped else None
    lat: dict[str, dict[str, int]] = {"swap": {}, "no_swap": {}, "overlap": {}, "no_overlap": {}}
    for n in rollouts:
        ca = a[n].extra.get("infer_latency_counts", {})
        cb = b[n].extra.get("infer_latency_counts", {})
        for label in lat:
            for k, v in histogram_diff(cb.get(label, {}), ca.get(label, {})).items():
                lat[label][k] = lat[label].get(k, 0) + v
    out["infer_latency"] = {
        label: {"n": sum(c.values()), "p50_ms": histogram_percentile(c, 50), "p99_ms": histogram_percentile(c, 99)}
        for label, c in lat.items()
    }
    return out


def lag_figures(counts: dict[str, int]) -> dict[str, Any]:
    """Mean, p99 and max of a lag histogram {lag: chunks}."""
    items = sorted((int(k), int(v)) for k, v in counts.items())
    total = sum(v for _k, v in items)
    if total == 0:
        return {"chunks": 0, "mean": None, "p99": None, "max": None, "counts": {}}
    mean = sum(k * v for k, v in items) / total
    return {"chunks": total, "mean": mean, "p99": weighted_percentile(dict(items), 99), "max": items[-1][0], "counts": {str(k): v for k, v in items}}


def rss_figures(samples: dict[str, list[tuple[float, int]]]) -> dict[str, Any]:
    """Per role: RSS at the start and end of the window (median of the first / last 5 samples)."""
    roles = {}
    for name, s in samples.items():
        if len(s) < 2:
            continue
        k = max(1, min(5, len(s) // 4))
        start = statistics.median(r for _t, r in s[:k])
        end = statistics.median(r for _t, r in s[-k:])
        roles[name] = {
            "start_kib": start, "end_kib": end, "max_kib": max(r for _t, r in s),
            "growth_pct": 100.0 * (end - start) / start if start else None, "samples": len(s),
            "span_s": s[-1][0] - s[0][0],
        }
    growths = [(r["growth_pct"], n) for n, r in roles.items() if r["growth_pct"] is not None]
    worst = max(growths) if growths else (None, None)
    return {"roles": roles, "max_growth_pct": worst[0], "max_growth_role": worst[1]}


def interval_rates(ticks: list[tuple[float, int, int]], every_s: float, which: str) -> list[float]:
    """Env steps/s over consecutive sub-windows (the spread within one window)."""
    idx = 1 if which == "consumed" else 2
    out, start = [], ticks[0] if ticks else None
    for t in ticks[1:]:
        if start is not None and t[0] - start[0] >= every_s:
            out.append(round((t[idx] - start[idx]) / (t[0] - start[0]), 1))
            start = t
    return out


# --------------------------------------------------------------------------------------------
# The bench
# --------------------------------------------------------------------------------------------


def machine_info() -> dict[str, Any]:
    info: dict[str, Any] = {
        "python": platform.python_version(), "platform": platform.platform(), "cpus": os.cpu_count(),
        "load_avg_start": list(os.getloadavg()),
    }
    try:
        import torch

        info["torch"] = torch.__version__
    except ImportError:
        pass
    try:
        import mani_skill

        info["mani_skill"] = getattr(mani_skill, "__version__", "?")
    except ImportError:
        pass
    try:
        info["cpu_model"] = next(
            line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
            if line.startswith("model name")
        )
    except (OSError, StopIteration):
        pass
    return info


def _ratio(x: float | None, y: float | None) -> float | None:
    return x / y if x is not None and y else None


def run_bench(
    topology: Path, profile: Profile, *, base_port: int | None = None, runs_root: Path | None = None,
    workloads: tuple[str, ...] = ("default", "balanced"), placement: str = "split",
    progress: Callable[[str], None] = lambda _m: None,
) -> dict[str, Any]:
    """Every run of the bench, in order; the JSON document of the results."""
    from dvla.orchestrator.topology import load_topology

    base = load_topology(topology)
    t0 = time.monotonic()
    tmp = None
    if runs_root is None:
        tmp = tempfile.mkdtemp(prefix="dvla-bench-swimlane-")
        runs_root = Path(tmp)
    doc: dict[str, Any] = {
        "bench": "swimlane", "topology": str(topology), "profile": dataclasses.asdict(profile),
        "machine": machine_info(), "argv": sys.argv, "goals": {k: list(v) for k, v in GOALS.items()},
        "workloads": {},
    }
    try:
        two_cores = (os.cpu_count() or 1) >= 2 and {0, 1} <= set(os.sched_getaffinity(0))
        if "default" in workloads:
            if placement.startswith("split") and not two_cores:
                progress("default: cores 0 and 1 are not both available: placement as in the file")
                placement = "file"
            doc["workloads"]["default"] = _default(base, profile, runs_root, base_port, progress, placement)
        if "balanced" in workloads:
            if not two_cores:
                doc["workloads"]["balanced"] = {"error": "needs cores 0 and 1"}
            else:
                doc["workloads"]["balanced"] = _balanced(base, profile, runs_root, base_port, progress)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    doc["machine"]["load_avg_end"] = list(os.getloadavg())
    doc["elapsed_s"] = time.monotonic() - t0
    doc.update(headline(doc["workloads"]))
    doc["goals_met"] = {
        k: (None if doc.get(k) is None else (doc[k] >= v if op == ">=" else doc[k] <= v))
        for k, (op, v) in GOALS.items()
    }
    return doc


def _pairs(
    first: tuple[str, Topology, float], second: tuple[str, Topology, float], profile: Profile,
    runs_root: Path, base_port: int | None, progress: Callable[[str], None],
) -> list[dict[str, dict[str, Any]]]:
    out = []
    for i in range(profile.repeats):
        pair = {}
        for mode, topo, window in (first, second):
            progress(f"{topo.run}: {mode} run {i + 1}/{profile.repeats}")
            pair[mode] = _measure(topo, mode, window, profile, runs_root, base_port, progress)
        out.append(pair)
    return out


def _measure(topo: Topology, mode: str, window: float, profile: Profile, runs_root: Path,
             base_port: int | None, progress: Callable[[str], None]) -> dict[str, Any]:
    run = measure_run(topo, mode, profile.warmup_s, window, runs_root, base_port, progress)
    if str(run.get("error")).startswith("ConnectionError"):
        # On a crowded machine the roles can take longer to open their planes than the
        # orchestrator waits for them; that says nothing about the lanes: try once more.
        progress(f"{topo.run}/{mode}: {run['error'][:120]}; starting it again")
        run = measure_run(topo, mode, profile.warmup_s, window, runs_root, base_port, progress)
    if run.get("error"):
        progress(f"{topo.run}/{mode}: {run['error']}")
    return run


def _median(xs: list[float | None]) -> float | None:
    vals = [x for x in xs if x is not None]
    return statistics.median(vals) if vals else None


def _default(base: Topology, profile: Profile, runs_root: Path, port: int | None, progress: Callable[[str], None],
             placement: str = "file") -> dict[str, Any]:
    topo = default_workload(base, profile, placement)
    steady = max(profile.window_s, profile.rss_window_s)
    pairs = _pairs(("sim_only", topo, profile.window_s), ("async", topo, steady), profile, runs_root, port, progress)
    # One more sim_only run after the last async one: each async run is then bracketed by a
    # simulator baseline before and after it, and its ratio is taken against their mean, so a
    # host whose speed drifts over the minutes of the bench (seen here: +-20% between
    # consecutive sim_only runs) does not bias the ratio in the direction of the drift.
    progress(f"{topo.run}: closing sim_only run")
    closing = _measure(topo, "sim_only", profile.window_s, profile, runs_root, port, progress)
    sims = [p["sim_only"].get("produced_sps") for p in pairs] + [closing.get("produced_sps")]
    baselines = [_bracket(sims[i], sims[i + 1]) for i in range(len(pairs))]
    ratios = [_ratio(p["async"].get("consumed_sps"), b) for p, b in zip(pairs, baselines)]
    # The simulators' step cost in each mode (bracketed like their rate): random actions are
    # cheaper to simulate than a learning policy's, so the random-action ceiling is above what
    # any pipeline can reach; the ratio at equal step cost takes that difference out.
    costs = [p["sim_only"].get("env_step_cpu_ms") for p in pairs] + [closing.get("env_step_cpu_ms")]
    cost_ratios = [_ratio(p["async"].get("env_step_cpu_ms"), _bracket(costs[i], costs[i + 1])) for i, p in enumerate(pairs)]
    equal_cost = [r * c if r is not None and c is not None else None for r, c in zip(ratios, cost_ratios)]
    # The learner's share of a core during training: the simulators can have at most the
    # machine's cores minus that share (before inference, shipping and Zenoh take theirs).
    shares = [_learn_share(p["async"]) for p in pairs]
    share = _median(shares)
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return {
        "placement_name": placement, "placement": placement_of(topo), "runs": pairs, "closing_sim_only": closing, "ratios": ratios,
        "sim_only_sps_runs": sims, "sim_only_baselines": baselines,
        "sim_only_drift": _ratio(sims[-1], sims[0]),
        "learner_core_share": share,
        "ceiling_from_learner": learner_ceiling(topo, share, cpus),
        "sim_only_sps": _median(baselines),
        "async_sps": _median([p["async"].get("consumed_sps") for p in pairs]),
        "async_over_sim_only": _median(ratios),
        "step_cost_ratios": cost_ratios,
        "step_cost_ratio": _median(cost_ratios),
        "async_over_sim_only_equal_step_cost": _median(equal_cost),
        "episodes_per_1k_steps": {
            "sim_only": _median([p["sim_only"].get("episodes_per_1k_steps") for p in pairs] + [closing.get("episodes_per_1k_steps")]),
            "async": _median([p["async"].get("episodes_per_1k_steps") for p in pairs]),
        },
        # Where the gap comes from: the simulators' CPU (cores) and CPU per env step in each mode.
        "sim_cpu": {
            mode: {
                "cores": _median([r.get("sim_cpu_cores") for r in runs]),
                "ms_per_step": _median([r.get("sim_cpu_ms_per_step") for r in runs]),
                "env_step_ms": _median([r.get("env_step_cpu_ms") for r in runs]),
            }
            for mode, runs in (("sim_only", [p["sim_only"] for p in pairs] + [closing]), ("async", [p["async"] for p in pairs]))
        },
    }


def _bracket(before: float | None, after: float | None) -> float | None:
    """The simulator baseline of a run measured between two sim_only runs: their mean, or the
    one that succeeded."""
    vals = [v for v in (before, after) if v]
    return sum(vals) / len(vals) if vals else None


def _learn_share(run: dict[str, Any]) -> float | None:
    for lanes in run.get("lanes", {}).values():
        if "learn" in lanes:
            return lanes["learn"]["utilisation"]
    return None


def _balanced(base: Topology, profile: Profile, runs_root: Path, port: int | None, progress: Callable[[str], None]) -> dict[str, Any]:
    epochs = profile.balanced_epochs
    w = profile.window_s
    rejected: list[dict[str, Any]] = []
    for attempt in range(2):
        topo = balanced_workload(base, profile, epochs)
        pairs = _pairs(("sync", topo, w), ("async", topo, w), profile, runs_root, port, progress)
        learner = _median([p["async"].get("learner_batch_s") for p in pairs])
        rollout = _median([p["async"].get("rollout_batch_s") for p in pairs])
        if attempt == 1 or learner is None or rollout is None or abs(learner / rollout - 1) <= 0.2:
            break
        scaled = max(1, round(epochs * rollout / learner))
        progress(f"balanced: learner {learner:.2f} s vs rollouts {rollout:.2f} s per batch with {epochs} "
                 f"epochs: measuring again with {scaled}")
        rejected.append({"update_epochs": epochs, "learner_batch_s": learner, "rollout_batch_s": rollout,
                         "runs": pairs})
        epochs = scaled
    ratios = [_ratio(p["async"].get("consumed_sps"), p["sync"].get("consumed_sps")) for p in pairs]
    return {
        "placement": placement_of(topo), "update_epochs": epochs, "runs": pairs, "ratios": ratios,
        "unbalanced_attempts": rejected,
        "async_sps": _median([p["async"].get("consumed_sps") for p in pairs]),
        "sync_sps": _median([p["sync"].get("consumed_sps") for p in pairs]),
        "async_over_sync": _median(ratios),
        "learner_batch_s": learner,
        "rollout_batch_s": rollout,
        "learner_over_rollout": _ratio(learner, rollout),
        "balanced_within_20pct": None if learner is None or rollout is None else abs(learner / rollout - 1) <= 0.2,
    }


def headline(workloads: dict[str, Any]) -> dict[str, Any]:
    """Top-level figures (see HEADLINE_KEYS) from the workloads' results."""
    d, b = workloads.get("default", {}), workloads.get("balanced", {})
    out: dict[str, Any] = {
        "default_placement": d.get("placement_name"),
        "sim_only_sps": d.get("sim_only_sps"),
        "async_sps": d.get("async_sps"),
        "async_over_sim_only": d.get("async_over_sim_only"),
        "ceiling_from_learner": d.get("ceiling_from_learner"),
        "step_cost_ratio": d.get("step_cost_ratio"),
        "async_over_sim_only_equal_step_cost": d.get("async_over_sim_only_equal_step_cost"),
        "balanced_async_sps": b.get("async_sps"),
        "sync_sps": b.get("sync_sps"),
        "async_over_sync": b.get("async_over_sync"),
        "learner_batch_s": b.get("learner_batch_s"),
        "rollout_batch_s": b.get("rollout_batch_s"),
    }
    # Latency, lag and memory: from the default workload's async runs (the training steady state).
    runs = [p["async"] for p in d.get("runs", []) if not p["async"].get("error")]
    out["infer_p99_ms_during_swap"] = _median([r["infer_latency"]["swap"]["p99_ms"] or None for r in runs])
    out["infer_p99_ms_no_swap"] = _median([r["infer_latency"]["no_swap"]["p99_ms"] or None for r in runs])
    out["swap_over_no_swap_p99"] = _ratio(out["infer_p99_ms_during_swap"], out["infer_p99_ms_no_swap"])
    out["infer_swap_batches"] = sum(r["infer_latency"]["swap"]["n"] for r in runs)
    # The length-biased split (a batch overlapping a staging write), beside it for comparison.
    out["infer_p99_ms_overlapping_swap"] = _median([r["infer_latency"]["overlap"]["p99_ms"] or None for r in runs])
    out["infer_p99_ms_not_overlapping"] = _median([r["infer_latency"]["no_overlap"]["p99_ms"] or None for r in runs])
    out["overlap_over_no_overlap_p99"] = _ratio(out["infer_p99_ms_overlapping_swap"], out["infer_p99_ms_not_overlapping"])
    out["rss_growth_pct"] = max((r["rss"]["max_growth_pct"] for r in runs if r["rss"]["max_growth_pct"] is not None), default=None)
    out["rss_window_s"] = _median([r.get("window_s") for r in runs])
    out["policy_lag_mean"] = _median([r["policy_lag"]["mean"] for r in runs])
    out["policy_lag_p99"] = _median([r["policy_lag"]["p99"] for r in runs])
    return out


def _fmt(v: float | None, digits: int) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def format_table(doc: dict[str, Any]) -> str:
    lines = [f"{'default_placement':36s} {doc.get('default_placement') or '-'}"]
    for k in HEADLINE_KEYS + ("learner_batch_s", "rollout_batch_s"):
        v = doc.get(k)
        goal = GOALS.get(k)
        met = doc["goals_met"].get(k)
        g = "" if goal is None else f"   (goal {goal[0]} {goal[1]}: {'-' if met is None else 'met' if met else 'missed'})"
        lines.append(f"{k:36s} {'-' if v is None else f'{v:.3f}'}{g}")
    for name, wl in doc["workloads"].items():
        for i, r in enumerate(wl.get("ratios", [])):
            lines.append(f"{name} repeat {i + 1}: ratio {'-' if r is None else f'{r:.3f}'}")
        sims = wl.get("sim_only_sps_runs")
        if sims:
            runs = ", ".join("-" if v is None else f"{v:.0f}" for v in sims)
            drift = wl.get("sim_only_drift")
            lines.append(f"{name} sim_only runs (env steps/s, in order): {runs}"
                         + ("" if drift is None else f"; last / first {drift:.2f}"))
        cpu = wl.get("sim_cpu") or {}
        if cpu:
            cells = [f"{mode} {_fmt(c.get('cores'), 2)} cores, {_fmt(c.get('ms_per_step'), 3)} ms CPU per env step "
                     f"({_fmt(c.get('env_step_ms'), 3)} of it in env.step)" for mode, c in cpu.items()]
            lines.append(f"{name} sim lanes: " + "; ".join(cells))
        eps = wl.get("episodes_per_1k_steps") or {}
        if eps:
            lines.append(f"{name} episodes per 1000 env steps: " + ", ".join(f"{m} {_fmt(v, 1)}" for m, v in eps.items()))
    return "\n".join(lines)
