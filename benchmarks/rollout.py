"""`dvla bench rollout`: env steps/s of one rollout as its simulator workers (W) and their envs
grow, next to the simulators alone with the same W and the policy alone at the same batch.

Every figure comes from a fresh child process running dvla's own rollout (:class:`Rollout` under
:class:`RoleHost`: its real lanes, workers, chunk recording and data-plane publishing; the
chunks are encoded and published on a real Zenoh session that no learner reads), in one of
three modes:

* ``sim_only``: the rollout's simulators step uniform random actions (the rollout's own
  benchmark mode): the simulators alone, with the same W and envs;
* ``train``: the rollout as in training (mode ``async``): infer, step, record, ship; the weights
  are the policy's initial ones, installed as a verified version would be;
* ``policy``: the policy alone: ``sample`` on a batch of one env group's observations, timed
  after warm-up; its env steps/s is batch / latency.

For each (W, envs per worker), runs are interleaved (sim_only, train, for each repeat) so a
drifting host biases neither. ``train_over_sim`` is train ÷ sim_only; the simulators' CPU per
env step in each mode (``thread_time`` of whoever steps them: the workers, or the rollout's sim
lane for W = 0) gives ``step_cost_ratio``, and ``train_over_sim_equal_step_cost`` takes out that
the policy's actions cost the simulator more (or less) than random ones. ``train_over_bound`` is
train ÷ min(sim_only, policy): 1 is a rollout that loses nothing to its own plumbing.
``sim_scaling`` is sim_only at each W over sim_only at the smallest W > 0 with the same envs per
worker.
"""

from __future__ import annotations

import dataclasses
import json
import os
import statistics
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_TOPOLOGY = ROOT / "topologies" / "local-vla.yaml"

GOALS = {"sim_scaling_w2": (">=", 1.7), "train_over_sim_equal_step_cost_w2": (">=", 0.85)}


@dataclass(frozen=True, kw_only=True)
class Profile:
    """The sweep and the windows of one invocation."""

    #: simulator worker counts (0: the envs stepped in the rollout process itself)
    workers: tuple[int, ...] = (0, 1, 2)
    #: envs each worker holds (both env groups together); with W = 0, the rollout's envs
    envs_per_worker: tuple[int, ...] = (2, 4, 8)
    #: seconds after the first env step before the window opens, and the window
    warmup_s: float = 10.0
    window_s: float = 20.0
    #: interleaved (sim_only, train) pairs per point
    repeats: int = 2
    #: seconds of timed policy calls for the policy-alone figure
    policy_s: float = 5.0
    quick: bool = False


QUICK = Profile(workers=(1, 2), envs_per_worker=(2,), warmup_s=4.0, window_s=8.0, repeats=1, policy_s=2.0, quick=True)


def envs_of(workers: int, per_worker: int) -> int:
    return max(workers, 1) * per_worker


# --------------------------------------------------------------------------------------------
# One measurement, in a child process
# --------------------------------------------------------------------------------------------


def _task(topology: Path, envs: int) -> Any:
    from dvla.orchestrator.topology import load_topology

    return dataclasses.replace(load_topology(topology).task, envs_per_rollout=envs)


def measure_rollout(topology: Path, mode: str, workers: int, envs: int, warmup_s: float, window_s: float) -> dict[str, Any]:
    """Run one rollout in this process for warm-up + window; its figures."""
    import numpy as np

    from dvla.config import PlaneEndpoints, ReplicationConfig, RoleConfig
    from dvla.fabric import Fabric, plane_config
    from dvla.replication import flatten
    from dvla.roles.rollout import Rollout
    from dvla.roles.runtime import RoleHost, set_torch_threads

    set_torch_threads(1)  # as a role process
    task = _task(topology, envs)
    run_dir = Path(os.environ.get("DVLA_BENCH_DIR", "/tmp")) / f"rollout-{os.getpid()}"
    run_dir.mkdir(parents=True, exist_ok=True)
    cfg = RoleConfig(
        name="rollout-bench-0", kind="rollout", run="benchrollout", node="bench", rack="bench", seed=1,
        mode="sim_only" if mode == "sim_only" else "async", run_dir=str(run_dir),
        data=PlaneEndpoints(mode="peer"), ctrl=PlaneEndpoints(mode="peer"), shared_memory=False,
        parent="actor-bench-0", ancestors=("actor-bench-0",), children=(), actors=(), rollouts=(),
        task=task, replication=ReplicationConfig(), sim_workers=workers,
    )
    local = lambda: plane_config(mode="peer", listen=("tcp/127.0.0.1:0",))  # noqa: E731
    fabric = Fabric(run=cfg.run, name=cfg.name, ctrl_conf=local(), data_conf=local(), secret=os.urandom(32))
    fabric.traj_matched = lambda: True  # publish every chunk (nobody reads them: Zenoh drops them)
    step_cpu = [0.0]
    try:
        role = Rollout(cfg, fabric)
        if workers == 0:  # the sim lane steps the envs: its own CPU clock inside step_wait
            for g in role.groups:
                g.envs.step_wait = _timed(g.envs.step_wait, step_cpu)
        from dvla.replication import WeightEncoder

        flat = flatten(role.pool.active.state_dict(), role.pool.layout)
        v = WeightEncoder(role.pool.layout, start_version=0).encode(np.ascontiguousarray(flat, dtype=np.float32))
        role.pool.held.apply(v.manifest, v.payload)
        role._ready.set()
        host = RoleHost(cfg, fabric, role)
        runner = threading.Thread(target=host.run, name="bench-rollout", daemon=True)
        t_start = time.monotonic()
        runner.start()
        try:
            while role.env_steps == 0:
                if not runner.is_alive() or time.monotonic() - t_start > 300:
                    raise RuntimeError(f"no env step within {time.monotonic() - t_start:.0f} s")
                time.sleep(0.05)
            first = time.monotonic()
            time.sleep(warmup_s)
            a = _reading(role, step_cpu)
            time.sleep(window_s)
            b = _reading(role, step_cpu)
        finally:
            host.swimlane.stop()
            runner.join(30)
        dt = b["t"] - a["t"]
        steps = b["env_steps"] - a["env_steps"]
        out = {
            "mode": mode, "workers": workers, "envs": envs, "sps": steps / dt, "window_s": dt,
            "startup_s": first - t_start,
            "env_step_cpu_ms": 1e3 * (b["step_cpu"] - a["step_cpu"]) / steps if steps else None,
            "rollout_cpu_cores": (b["cpu"] - a["cpu"]) / dt,
            "infer_ms_p50": role.status_extra()["infer_ms_p50"] if mode != "sim_only" else None,
            "env_groups": [g.envs.n for g in role.groups],
            "worker_busy": [(w1["busy_s"] - w0["busy_s"]) / dt for w0, w1 in zip(a["workers"], b["workers"])],
            "chunks_shipped": role.ledger.shipped,
        }
        role.close()
        return out
    finally:
        fabric.close()


def _timed(step_wait: Callable[[], Any], acc: list[float]) -> Callable[[], Any]:
    def timed() -> Any:
        t0 = time.thread_time()
        try:
            return step_wait()
        finally:
            acc[0] += time.thread_time() - t0
    return timed


def _reading(role: Any, step_cpu: list[float]) -> dict[str, Any]:
    workers = role.sim_workers.status() if role.sim_workers is not None else []
    return {"t": time.monotonic(), "env_steps": role.env_steps, "cpu": time.process_time(), "workers": workers,
            "step_cpu": sum(w["cpu_s"] for w in workers) if workers else step_cpu[0]}


def measure_policy(topology: Path, batch: int, seconds: float) -> dict[str, Any]:
    """The policy alone: ``sample`` on ``batch`` observations of the task's env, timed."""
    import numpy as np
    import torch

    from dvla.config import resolve_device
    from dvla.learn import make_policy
    from dvla.learn.envs import EnvGroup, obs_to_torch
    from dvla.learn.policies import sample_actions
    from dvla.roles.runtime import set_torch_threads

    set_torch_threads(1)
    task = _task(topology, batch)
    device = torch.device(resolve_device(task.rollout_device))
    group = EnvGroup(task, 1, 0)
    try:
        one = group.reset()
        policy = make_policy(task.policy, group.obs_spec, group.act_dim, **task.policy_kwargs).to(device).eval()
    finally:
        group.close()
    tile = lambda x: np.repeat(x, batch, axis=0)  # noqa: E731
    obs = {k: tile(v) for k, v in one.items()} if isinstance(one, dict) else tile(one)
    gen = torch.Generator(device=device)
    times = []
    with torch.no_grad():
        t_end = None
        while True:
            t0 = time.perf_counter()
            action, _, _ = sample_actions(policy, obs_to_torch(obs, device), generator=gen)
            action.cpu()
            times.append(time.perf_counter() - t0)
            if t_end is None and len(times) >= 3:  # warm-up done
                times, t_end = [], time.monotonic() + seconds
            if t_end is not None and time.monotonic() >= t_end and len(times) >= 5:
                break
    p50 = statistics.median(times)
    return {"mode": "policy", "batch": batch, "sps": batch / p50, "ms_p50": 1e3 * p50, "calls": len(times),
            "device": str(device)}


def _child(args: dict[str, Any]) -> dict[str, Any]:
    """Run one measurement in a fresh interpreter; its figures, or ``{"error": ...}``."""
    cmd = [sys.executable, "-m", "benchmarks.rollout", json.dumps(args)]
    try:
        p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=900)
    except subprocess.TimeoutExpired:
        return {**args, "error": "timed out after 900 s"}
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
    if p.returncode != 0 or not lines:
        tail = " | ".join(p.stderr.strip().splitlines()[-3:])
        return {**args, "error": f"exit {p.returncode}: {tail[-400:]}"}
    return json.loads(lines[-1])


# --------------------------------------------------------------------------------------------
# The sweep
# --------------------------------------------------------------------------------------------


def _median(xs: list[Any]) -> float | None:
    vals = [x for x in xs if isinstance(x, (int, float))]
    return statistics.median(vals) if vals else None


def _ratio(a: float | None, b: float | None) -> float | None:
    return a / b if a is not None and b else None


def run_bench(topology: Path, profile: Profile, progress: Callable[[str], None]) -> dict[str, Any]:
    from .swimlane import machine_info

    points = [(w, e) for e in profile.envs_per_worker for w in profile.workers]
    runs: dict[tuple[int, int], dict[str, list[dict[str, Any]]]] = {p: {"sim_only": [], "train": []} for p in points}
    policy: dict[int, dict[str, Any]] = {}
    for r in range(profile.repeats):
        for w, e in points:
            for mode in ("sim_only", "train"):
                progress(f"repeat {r + 1}/{profile.repeats}: W={w}, {envs_of(w, e)} envs, {mode}")
                res = _child({"kind": "rollout", "topology": str(topology), "mode": mode, "workers": w,
                              "envs": envs_of(w, e), "warmup_s": profile.warmup_s, "window_s": profile.window_s})
                if res.get("error"):
                    progress(f"  {res['error']}")
                runs[(w, e)][mode].append(res)
    for w, e in points:
        envs = envs_of(w, e)
        batch = max(next((r["env_groups"] for r in runs[(w, e)]["train"] if r.get("env_groups")), [envs - envs // 2]))
        if batch not in policy:
            progress(f"policy alone at batch {batch}")
            policy[batch] = _child({"kind": "policy", "topology": str(topology), "batch": batch, "seconds": profile.policy_s})
    rows = []
    for w, e in points:
        sim = _median([r.get("sps") for r in runs[(w, e)]["sim_only"]])
        train = _median([r.get("sps") for r in runs[(w, e)]["train"]])
        cost = _ratio(_median([r.get("env_step_cpu_ms") for r in runs[(w, e)]["train"]]),
                      _median([r.get("env_step_cpu_ms") for r in runs[(w, e)]["sim_only"]]))
        groups = next((r["env_groups"] for r in runs[(w, e)]["train"] if r.get("env_groups")), None)
        batch = max(groups) if groups else envs_of(w, e) - envs_of(w, e) // 2
        pol = policy.get(batch, {}).get("sps")
        bound = min(x for x in (sim, pol) if x) if (sim or pol) else None
        ratio = _ratio(train, sim)
        rows.append({
            "workers": w, "envs_per_worker": e, "envs": envs_of(w, e), "batch": batch,
            "sim_only_sps": sim, "train_sps": train, "policy_sps": pol,
            "train_over_sim": ratio, "step_cost_ratio": cost,
            "train_over_sim_equal_step_cost": ratio * cost if ratio is not None and cost is not None else None,
            "train_over_bound": _ratio(train, bound),
            "infer_ms_p50": _median([r.get("infer_ms_p50") for r in runs[(w, e)]["train"]]),
            "rollout_cpu_cores": _median([r.get("rollout_cpu_cores") for r in runs[(w, e)]["train"]]),
            "worker_busy": next((r["worker_busy"] for r in runs[(w, e)]["train"] if r.get("worker_busy")), []),
        })
    smallest = min((w for w in profile.workers if w > 0), default=None)
    for row in rows:
        base = next((x["sim_only_sps"] for x in rows if x["workers"] == smallest and x["envs_per_worker"] == row["envs_per_worker"]), None)
        row["sim_scaling"] = _ratio(row["sim_only_sps"], base) if row["workers"] > 0 else None
    doc: dict[str, Any] = {
        "bench": "rollout", "topology": str(topology), "profile": dataclasses.asdict(profile),
        "machine": machine_info(), "rows": rows, "runs": {f"W{w}-e{e}": v for (w, e), v in runs.items()},
        "policy": {str(b): p for b, p in policy.items()}, "goals": GOALS,
    }
    w2 = [r for r in rows if r["workers"] == 2]
    if w2:
        doc["sim_scaling_w2"] = _median([r["sim_scaling"] for r in w2])
        doc["train_over_sim_equal_step_cost_w2"] = _median([r["train_over_sim_equal_step_cost"] for r in w2])
        doc["train_over_sim_w2"] = _median([r["train_over_sim"] for r in w2])
    return doc


def plot(doc: dict[str, Any], path: Path) -> None:
    """env steps/s against envs per rollout: one colour per W; solid training, dashed the
    simulators alone; the policy alone dotted (black)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    rows = doc["rows"]
    for i, w in enumerate(sorted({r["workers"] for r in rows})):
        mine = sorted((r for r in rows if r["workers"] == w), key=lambda r: r["envs"])
        xs = [r["envs"] for r in mine]
        label = "in-process" if w == 0 else f"W={w}"
        ax.plot(xs, [r["train_sps"] or float("nan") for r in mine], "-o", color=f"C{i}", label=f"{label}: rollout")
        ax.plot(xs, [r["sim_only_sps"] or float("nan") for r in mine], "--x", color=f"C{i}", label=f"{label}: simulators alone")
    pol = sorted({(r["envs"], r["policy_sps"]) for r in rows if r["policy_sps"]})
    if pol:
        ax.plot([p[0] for p in pol], [p[1] for p in pol], ":", color="black", label="policy alone (batch: one env group)")
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("envs per rollout")
    ax.set_ylabel("env steps / s")
    ax.set_title(f"dvla bench rollout: {Path(doc['topology']).name}")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _fmt(v: Any, digits: int = 1) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def format_table(doc: dict[str, Any]) -> str:
    head = ["W", "envs", "batch", "sim alone/s", "rollout/s", "policy/s", "rollout/sim", "step cost", "equal cost",
            "rollout/bound", "infer ms", "workers busy"]
    lines = [head]
    for r in doc["rows"]:
        lines.append([str(r["workers"]), str(r["envs"]), str(r["batch"]), _fmt(r["sim_only_sps"]), _fmt(r["train_sps"]),
                      _fmt(r["policy_sps"]), _fmt(r["train_over_sim"], 2), _fmt(r["step_cost_ratio"], 2),
                      _fmt(r["train_over_sim_equal_step_cost"], 2), _fmt(r["train_over_bound"], 2),
                      _fmt(r["infer_ms_p50"]), " ".join(f"{100 * b:.0f}%" for b in r["worker_busy"])])
    widths = [max(len(x[i]) for x in lines) for i in range(len(head))]
    out = ["  ".join(c.rjust(wd) for c, wd in zip(x, widths)) for x in lines]
    for key, (op, goal) in GOALS.items():
        if key in doc:
            out.append(f"{key}: {_fmt(doc[key], 2)} (goal {op} {goal})")
    return "\n".join(out)


if __name__ == "__main__":
    spec = json.loads(sys.argv[1])
    if spec["kind"] == "policy":
        result = measure_policy(Path(spec["topology"]), spec["batch"], spec["seconds"])
    else:
        result = measure_rollout(Path(spec["topology"]), spec["mode"], spec["workers"], spec["envs"],
                                 spec["warmup_s"], spec["window_s"])
    print(json.dumps(result), flush=True)
    os._exit(0)  # Zenoh's and the simulators' threads must not hold the exit
