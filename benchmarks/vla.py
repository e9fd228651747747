"""`dvla bench vla`: what the rgb + language path costs on this machine.

The Hugging Face families (``vla-tokens``, ``vla-flow``: :mod:`benchmarks.vla_families`), and two
measurements of the built-in ``tiny-vla`` path, all on real parts:

* **rollout**: one process, one :class:`~dvla.learn.envs.EnvGroup` of rendered ManiSkill3 envs
  (``obs_mode="rgb"``), acting with ``tiny-vla`` at three sizes in turn, exactly as a rollout's
  infer + sim lanes do one after the other: env steps per second, and the latency of each
  ``policy.act`` call (p50, p99). A random-action pass gives the simulator-only rate beside it.
* **data plane**: a publisher process sends real image trajectory chunks (taken from those
  envs) through the fabric to a subscriber process that decodes them, with Zenoh shared memory
  on and off (``plane_config(shared_memory=...)``): bytes/s and chunks/s, medians of rounds
  that alternate between the two settings so background load hits both alike.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import platform
import socket
import statistics
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from dvla.config import TaskConfig

from .stats import percentile

__all__ = ["VLABenchConfig", "run_bench", "format_table"]

RUN = "benchvla"
SIZES = ("tiny", "small", "base")


@dataclass(frozen=True)
class VLABenchConfig:
    """What one bench run measures (`quick` shrinks the counts: checks the machinery only)."""

    #: ManiSkill3 task, rendered
    env: str = "PushCube-v1"
    #: camera width and height, pixels
    image_size: int = 64
    #: envs stepped in the measuring process (one rollout env group)
    envs: int = 2
    #: timed env-group steps per policy size (after `warmup_steps`)
    steps: int = 100
    warmup_steps: int = 5
    #: tiny-vla presets measured
    sizes: tuple[str, ...] = SIZES
    #: trajectory chunk length (steps); N = `envs`
    chunk_steps: int = 10
    #: chunks per data-plane round, and rounds per shared-memory setting
    chunks: int = 200
    rounds: int = 3

    @staticmethod
    def quick() -> "VLABenchConfig":
        return VLABenchConfig(steps=6, warmup_steps=1, chunks=10, rounds=1, image_size=32)


def _task(cfg: VLABenchConfig) -> TaskConfig:
    return TaskConfig(env=cfg.env, obs_mode="rgb", image_size=cfg.image_size, max_episode_steps=50, policy="tiny-vla")


# --- rollout: env steps/s and inference latency --------------------------------------------


def measure_rollout(cfg: VLABenchConfig, progress: Callable[[str], None]) -> tuple[dict[str, Any], Any]:
    """Per size: env steps/s and act() latency; also the sim-only rate and one image chunk."""
    import torch

    from dvla.learn.envs import EnvGroup, obs_as_dict, obs_to_torch
    from dvla.learn.policies import make_policy
    from dvla.learn.vla.model import count_parameters

    torch.manual_seed(0)
    torch.set_num_threads(1)  # as in a rollout process (dvla up sets OMP_NUM_THREADS=1)
    out: dict[str, Any] = {"envs": cfg.envs, "image_size": cfg.image_size, "sizes": {}}
    group = EnvGroup(_task(cfg), cfg.envs, seed=0)
    try:
        obs = group.reset()
        rng = np.random.default_rng(0)
        t0 = time.perf_counter()
        frames: list[dict[str, np.ndarray]] = []
        for _ in range(cfg.steps):
            frames.append(obs_as_dict(obs))
            obs = group.step(rng.uniform(group.action_low, group.action_high, (cfg.envs, group.act_dim))).next_obs
        out["sim_only_steps_per_s"] = cfg.envs * cfg.steps / (time.perf_counter() - t0)
        progress(f"sim only: {out['sim_only_steps_per_s']:.1f} env steps/s")
        for size in cfg.sizes:
            policy = make_policy("tiny-vla", group.obs_spec, group.act_dim, size=size).eval()
            act_ms: list[float] = []
            for i in range(cfg.warmup_steps + cfg.steps):
                if i == cfg.warmup_steps:
                    act_ms, t0 = [], time.perf_counter()
                t = time.perf_counter()
                with torch.no_grad():
                    action, _, _ = policy.act(obs_to_torch(obs))
                act_ms.append((time.perf_counter() - t) * 1e3)
                obs = group.step(action.numpy()).next_obs
            wall = time.perf_counter() - t0
            out["sizes"][size] = {
                "parameters": count_parameters(policy),
                "env_steps_per_s": cfg.envs * cfg.steps / wall,
                "infer_ms_p50": percentile(act_ms, 50),
                "infer_ms_p99": percentile(act_ms, 99),
            }
            progress(f"tiny-vla {size}: {out['sizes'][size]}")
    finally:
        group.close()
    T = cfg.chunk_steps
    chunk_obs = {k: np.stack([f[k] for f in frames[:T]]) for k in frames[0]}
    return out, chunk_obs


# --- data plane: image chunks with shared memory on and off -----------------------------------


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _chunk(chunk_obs: dict[str, np.ndarray]) -> Any:
    from dvla.fabric import TrajectoryChunk

    T, N = chunk_obs["rgb"].shape[:2]
    tn = lambda dt: np.zeros((T, N), dt)  # noqa: E731
    return TrajectoryChunk(
        rollout="src", seq=0, policy_version=1, env_steps=T * N, obs=chunk_obs,
        actions=np.zeros((T, N, 8), np.float32), logprobs=tn(np.float32), rewards=tn(np.float32),
        terminated=tn(bool), truncated=tn(bool), success=tn(bool),
        next_obs={k: v[-1].copy() for k, v in chunk_obs.items()},
        final_obs={k: np.zeros_like(v) for k, v in chunk_obs.items()},
    )


def _fabric(name: str, shm: bool, listen: list[str], connect: list[str]) -> Any:
    from dvla.fabric import Fabric, plane_config

    data = plane_config(mode="peer", listen=listen, connect=connect, shared_memory=shm)
    return Fabric(run=RUN, name=name, ctrl_conf=plane_config(), data_conf=data, secret=b"bench-vla-secret")


def _subscriber(shm: bool, port: int, total: int, ready: Any, done: Any, out: Any) -> None:
    from dvla.fabric import TrajectoryChunk

    fabric = _fabric("sink", shm, [f"tcp/127.0.0.1:{port}"], [])
    try:
        inbox = fabric.subscribe_traj(maxsize=64, expect=TrajectoryChunk)
        ready.set()
        got, first = 0, None
        deadline = time.monotonic() + 120
        while got < total and time.monotonic() < deadline:
            msg = inbox.get(timeout=0.5)
            if msg is not None:
                if first is None:
                    first = time.monotonic()
                got += 1
                int(msg.obs["rgb"][-1, -1, 0, 0, 0])  # touch the decoded image
        out.put((got, first, time.monotonic()))
    finally:
        done.set()
        fabric.close()


def _publisher(shm: bool, port: int, chunk_obs: dict[str, np.ndarray], n: int, done: Any, out: Any) -> None:
    fabric = _fabric("src", shm, [], [f"tcp/127.0.0.1:{port}"])
    try:
        chunk = _chunk(chunk_obs)
        time.sleep(1.0)  # let the route settle; the first chunk is excluded from the timing
        sent = 0
        t0 = time.monotonic()
        for _ in range(n):
            sent += fabric.publish_traj(chunk)
        out.put((sent // n, t0, time.monotonic()))
        # Closing the session while chunks are in flight loses them (with shared memory on,
        # their buffers go with it): stay until the subscriber has them all.
        done.wait(120)
    finally:
        fabric.close()


def _round(ctx: Any, shm: bool, chunk_obs: dict[str, np.ndarray], n: int) -> dict[str, float]:
    port = _free_port()
    ready, done, sub_out, pub_out = ctx.Event(), ctx.Event(), ctx.Queue(), ctx.Queue()
    sub = ctx.Process(target=_subscriber, args=(shm, port, n, ready, done, sub_out))
    sub.start()
    try:
        if not ready.wait(60):
            raise RuntimeError("bench vla: the subscriber did not start within 60 s")
        pub = ctx.Process(target=_publisher, args=(shm, port, chunk_obs, n, done, pub_out))
        pub.start()
        chunk_bytes, t_pub, _ = pub_out.get(timeout=180)
        got, first, last = sub_out.get(timeout=180)
        pub.join(30)
    finally:
        sub.join(30)
        for p in (sub,):
            if p.is_alive():
                p.terminate()
    if got < n:
        raise RuntimeError(f"bench vla: {got} of {n} chunks arrived (shared_memory={shm})")
    # From the first arrival to the last: n - 1 chunks (start-up latency excluded).
    seconds = max(last - first, 1e-9)
    return {"chunk_bytes": chunk_bytes, "bytes_per_s": (n - 1) * chunk_bytes / seconds, "chunks_per_s": (n - 1) / seconds}


def measure_data_plane(cfg: VLABenchConfig, chunk_obs: dict[str, np.ndarray], progress: Callable[[str], None]) -> dict[str, Any]:
    ctx = mp.get_context("spawn")
    rounds: dict[str, list[dict[str, float]]] = {"shm_off": [], "shm_on": []}
    for r in range(cfg.rounds):
        for name in (("shm_off", "shm_on") if r % 2 == 0 else ("shm_on", "shm_off")):
            res = _round(ctx, name == "shm_on", chunk_obs, cfg.chunks)
            rounds[name].append(res)
            progress(f"data plane {name} round {r}: {res['bytes_per_s'] / 1e6:.1f} MB/s")
    out: dict[str, Any] = {"chunks_per_round": cfg.chunks}
    for name, values in rounds.items():
        out[name] = {
            "chunk_bytes": values[0]["chunk_bytes"],
            "bytes_per_s": statistics.median(v["bytes_per_s"] for v in values),
            "chunks_per_s": statistics.median(v["chunks_per_s"] for v in values),
            "rounds_bytes_per_s": [v["bytes_per_s"] for v in values],
        }
    out["ratio_on_off"] = out["shm_on"]["bytes_per_s"] / out["shm_off"]["bytes_per_s"]
    return out


def run_bench(cfg: VLABenchConfig | None = None, *, quick: bool = False,
              progress: Callable[[str], None] = lambda m: None, families: Any = None,
              tiny: bool = True) -> dict[str, Any]:
    """``families``: a :class:`~benchmarks.vla_families.FamilyBenchConfig` (None: the default, or
    its quick form); ``tiny``: also measure tiny-vla and the data plane."""
    from .vla_families import FamilyBenchConfig, measure_families

    cfg = cfg or (VLABenchConfig.quick() if quick else VLABenchConfig())
    families = families or (FamilyBenchConfig.quick() if quick else FamilyBenchConfig())
    started = time.monotonic()
    fam = measure_families(families, progress) if families.families else None
    rollout, data = None, None
    if tiny:
        rollout, chunk_obs = measure_rollout(cfg, progress)
        data = measure_data_plane(cfg, chunk_obs, progress)
    return {
        "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in cfg.__dict__.items()},
        "hf_families": fam,
        "rollout": rollout,
        "data_plane": data,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
        "elapsed_s": time.monotonic() - started,
    }


def format_table(doc: dict[str, Any]) -> str:
    from .vla_families import format_families

    lines = format_families(doc["hf_families"]) if doc.get("hf_families") else []
    r, d = doc["rollout"], doc["data_plane"]
    if r is None:
        return "\n".join(lines)
    lines += [
        f"rollout, {r['envs']} rgb envs at {r['image_size']}x{r['image_size']} (one process):",
        f"  sim only (random actions)   {r['sim_only_steps_per_s']:8.1f} env steps/s",
    ]
    for size, s in r["sizes"].items():
        lines.append(f"  tiny-vla {size:<6} {s['parameters'] / 1e6:6.2f} M   {s['env_steps_per_s']:8.1f} env steps/s"
                     f"   act p50 {s['infer_ms_p50']:6.2f} ms  p99 {s['infer_ms_p99']:6.2f} ms")
    lines.append(f"data plane, image chunks of {d['shm_off']['chunk_bytes'] / 1e3:.0f} kB:")
    for name in ("shm_off", "shm_on"):
        lines.append(f"  {name:<8} {d[name]['bytes_per_s'] / 1e6:8.1f} MB/s  {d[name]['chunks_per_s']:8.1f} chunks/s")
    lines.append(f"  shared memory on / off: {d['ratio_on_off']:.2f}")
    return "\n".join(lines)
