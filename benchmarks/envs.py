"""`dvla bench envs`: for each env kind this machine can run, its simulators alone against training
in the same placement, and for LIBERO what one env costs.

* **Pipeline** (every kind): the swimlane bench's default workload (:func:`benchmarks.swimlane`,
  real ``dvla up`` runs) on the kind's topology: ``sim_only`` (the rollouts step uniform random
  actions, nothing is inferred, shipped or learned) bracketing ``async`` (training), the same
  processes on the same cores. ``async_over_sim_only`` = learner-consumed env steps/s over
  simulated env steps/s; ``..._equal_step_cost`` takes out that a learning policy's steps cost the
  simulator more (or less) than random actions do.
* **LIBERO env costs** (one env, in a child process, random actions): seconds per reset (the
  same task: a soft reset plus the init state) and per task switch (the scene rebuilt), and
  milliseconds per step with the cameras rendered and with the physics alone; their difference is
  the render time per step, next to the time of one camera image rendered on its own.

Kinds: ``maniskill-cpu`` (``topologies/local.yaml``: PushCube-v1, state observations, physx_cpu),
``maniskill-gpu`` (``topologies/gpu-maniskill.yaml``: 1024 envs in one physx_cuda scene per
rollout, inference and learning on the GPU; only where CUDA is present, with the placement of
the file) and ``libero`` (``topologies/local-libero.yaml``); a kind that cannot run here (no
simulator, no CUDA device) is reported as skipped with the reason.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import multiprocessing
import os
import shutil
import statistics
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any, Callable

from dvla.config import LIBERO_ENV, TaskConfig

from .swimlane import Profile, _default, machine_info

ROOT = Path(__file__).resolve().parents[1]

KINDS: dict[str, Path] = {
    "maniskill-cpu": ROOT / "topologies" / "local.yaml",
    "maniskill-gpu": ROOT / "topologies" / "gpu-maniskill.yaml",
    "libero": ROOT / "topologies" / "local-libero.yaml",
}
"""Env kind -> the topology its pipeline runs use."""

#: what a kind's result carries at the top of the document
HEADLINE = ("sim_only_sps", "async_sps", "async_over_sim_only", "step_cost_ratio", "async_over_sim_only_equal_step_cost")

GOALS = {"async_over_sim_only_equal_step_cost": (">=", 0.9)}

PROFILE = Profile(warmup_s=30.0, window_s=60.0, rss_window_s=60.0)
QUICK = Profile(warmup_s=6.0, window_s=12.0, rss_window_s=12.0, quick=True)


def unavailable(kind: str) -> str | None:
    """Why env kind ``kind`` cannot run here, or None."""
    if kind in ("maniskill-cpu", "maniskill-gpu"):
        if importlib.util.find_spec("mani_skill") is None:
            return "mani_skill is not installed"
        if kind == "maniskill-gpu":
            import torch

            if not torch.cuda.is_available():
                return "no CUDA device here (one physx_cuda scene of 1024 envs needs one)"
        return None
    if kind == "libero":
        if importlib.util.find_spec("libero") is None:
            return "hf-libero is not installed (bash scripts/setup.sh libero)"
        from dvla.orchestrator.topology import TopologyError, load_topology

        try:
            load_topology(KINDS["libero"])
        except TopologyError as err:
            return f"{KINDS['libero'].name}: {err.problems[0]}"
        return None
    raise ValueError(f"unknown env kind {kind!r} (expected one of {', '.join(KINDS)})")


# --- LIBERO: what one env costs ----------------------------------------------------------------


def libero_costs(task: TaskConfig, steps: int = 60, resets: int = 4) -> dict[str, Any]:
    """Reset, task-switch, step and render times of one LIBERO env of ``task`` (random actions).

    Runs in the calling process (MuJoCo's GL backend is chosen once per process: call it in a
    child, as :func:`run_bench` does)."""
    import numpy as np

    from dvla.learn.libero import LiberoEnv, libero_config, task_ids

    ids = task_ids(libero_config(task))
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    env = LiberoEnv(task, 0)
    out: dict[str, Any] = {"first_build_s": time.perf_counter() - t0, "image_size": task.image_size,
                           "cameras": 2 if libero_config(task).wrist_camera else 1,
                           "reflections": libero_config(task).reflections}
    try:
        k = len(ids)
        times = []
        for i in range(resets):  # seeds 0, k, 2k, ...: the same task, other init states
            t = time.perf_counter()
            env.reset(seed=i * k)
            times.append(time.perf_counter() - t)
        out["reset_s"] = statistics.median(times)
        if k > 1:
            t = time.perf_counter()
            env.reset(seed=1)  # the next task: the scene is rebuilt
            out["task_switch_s"] = time.perf_counter() - t
            env.reset(seed=0)
        out["step_ms_rendered"] = 1e3 * _time_steps(env.step, steps, rng)
        # One camera image on its own, as robosuite renders it for an observation.
        sim, size = env.sim, task.image_size
        t = time.perf_counter()
        for _ in range(steps):
            sim.render(width=size, height=size, camera_name="agentview")
        out["render_ms_per_image"] = 1e3 * (time.perf_counter() - t) / steps
        # The physics alone: the same task and controller without cameras or a renderer.
        from libero.libero.envs import OffScreenRenderEnv

        current = env.current
        env.close()
        bare = OffScreenRenderEnv(bddl_file_name=current.bddl_file, use_camera_obs=False, hard_reset=False,
                                  ignore_done=True, horizon=10**9)
        try:
            bare.reset()
            out["step_ms_physics"] = 1e3 * _time_steps(bare.step, steps, rng)
        finally:
            bare.close()
    finally:
        env.close()
    out["render_ms_per_step"] = out["step_ms_rendered"] - out["step_ms_physics"]
    out["steps_per_s_rendered"] = 1e3 / out["step_ms_rendered"]
    out["steps_per_s_physics"] = 1e3 / out["step_ms_physics"]
    out["render_share"] = out["render_ms_per_step"] / out["step_ms_rendered"]
    import resource

    out["max_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return out


def _time_steps(step: Callable[[Any], Any], steps: int, rng: Any) -> float:
    """Seconds per call of ``step`` with uniform random 7-d actions (one warm-up call first)."""
    step(rng.uniform(-1, 1, 7))
    t = time.perf_counter()
    for _ in range(steps):
        step(rng.uniform(-1, 1, 7))
    return (time.perf_counter() - t) / steps


def _libero_costs_in_child(task: TaskConfig, steps: int) -> dict[str, Any]:
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=1, mp_context=ctx) as pool:
        return pool.submit(libero_costs, task, steps).result(timeout=1800)


# --- the bench ----------------------------------------------------------------------------------


def run_bench(profile: Profile, kinds: tuple[str, ...] = tuple(KINDS), placement: str = "split",
              runs_root: Path | None = None, progress: Callable[[str], None] = lambda _m: None) -> dict[str, Any]:
    """Every kind's figures; the JSON document of the results."""
    from dvla.orchestrator.topology import load_topology

    t0 = time.monotonic()
    doc: dict[str, Any] = {"bench": "envs", "profile": dataclasses.asdict(profile), "placement": placement,
                           "machine": machine_info(), "argv": sys.argv, "goals": {k: list(v) for k, v in GOALS.items()},
                           "kinds": {}}
    tmp = None
    if runs_root is None:
        tmp = tempfile.mkdtemp(prefix="dvla-bench-envs-")
        runs_root = Path(tmp)
    two_cores = (os.cpu_count() or 1) >= 2 and {0, 1} <= set(os.sched_getaffinity(0))
    if placement.startswith("split") and not two_cores:
        progress("cores 0 and 1 are not both available: placement as in the files")
        placement = "file"
    try:
        for kind in kinds:
            why = unavailable(kind)
            if why is not None:
                progress(f"{kind}: skipped ({why})")
                doc["kinds"][kind] = {"skipped": why}
                continue
            topo = load_topology(KINDS[kind])
            entry: dict[str, Any] = {"topology": str(KINDS[kind].relative_to(ROOT))}
            if topo.task.env == LIBERO_ENV:
                progress(f"{kind}: one env's reset, step and render times")
                entry["env_costs"] = _libero_costs_in_child(topo.task, 12 if profile.quick else 60)
            # a GPU node's cores are many: its processes go where the file puts them
            where = "file" if kind == "maniskill-gpu" else placement
            progress(f"{kind}: sim_only vs async, placement {where}")
            entry["pipeline"] = _default(topo, profile, runs_root, None, progress, where)
            entry.update({k: entry["pipeline"].get(k) for k in HEADLINE})
            doc["kinds"][kind] = entry
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    doc["machine"]["load_avg_end"] = list(os.getloadavg())
    doc["elapsed_s"] = time.monotonic() - t0
    return doc


def _fmt(v: Any, digits: int) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def format_table(doc: dict[str, Any]) -> str:
    lines = [f"placement {doc.get('placement')}"]
    for kind, e in doc["kinds"].items():
        if "skipped" in e:
            lines.append(f"{kind:14s} skipped: {e['skipped']}")
            continue
        ratio, equal = e.get("async_over_sim_only"), e.get("async_over_sim_only_equal_step_cost")
        goal = GOALS["async_over_sim_only_equal_step_cost"][1]
        lines.append(f"{kind:14s} sim_only {_fmt(e.get('sim_only_sps'), 1)} env steps/s, training "
                     f"{_fmt(e.get('async_sps'), 1)}: ratio {_fmt(ratio, 3)}, at equal step cost {_fmt(equal, 3)} "
                     f"(goal >= {goal}: {'-' if equal is None else 'met' if equal >= goal else 'missed'})")
        c = e.get("env_costs")
        if c:
            lines.append(f"{'':14s} one env: reset {_fmt(c.get('reset_s'), 2)} s, task switch {_fmt(c.get('task_switch_s'), 2)} s; "
                         f"step {_fmt(c.get('step_ms_rendered'), 1)} ms rendered, {_fmt(c.get('step_ms_physics'), 1)} ms "
                         f"physics alone: render {_fmt(c.get('render_ms_per_step'), 1)} ms per step "
                         f"({_fmt(c.get('render_ms_per_image'), 1)} ms per {c.get('image_size')} px image, "
                         f"{c.get('cameras')} camera(s)); {_fmt(c.get('max_rss_mib'), 0)} MiB RSS")
    return "\n".join(lines)
