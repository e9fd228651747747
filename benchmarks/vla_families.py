"""`dvla bench vla`, the Hugging Face families: what ``vla-tokens`` and ``vla-flow`` cost.

Per family, on a random-initialised checkpoint of real transformers classes written to a temporary
directory (``dvla.learn.vla.build``), with LoRA adapters:

* **rollout**: one process steps an env group of rendered ManiSkill3 envs, acting with the
  policy exactly as a rollout's infer + sim lanes do one after the other (``sample_actions``,
  numpy actions, ``EnvGroup.step``): env steps/s and act latency p50/p99. On CUDA the env
  steps stay on the CPU simulator; ``--size 0.5b`` on a GPU machine is the realistic setting.
* **data plane**: the bytes a trajectory chunk of the recorded steps takes on the wire per env
  step, with and without the policy's extras (the action bins, the denoising chain).
* **learner**: the time of one PPO update (``PPOLearner.update``, one epoch of two minibatches)
  on a batch built from the recorded observations, and the process's peak memory, with and
  without micro-batching; each setting runs in a fresh process so the peaks are its own (CPU:
  how far the RSS rises during the updates above the RSS just before the first, sampled every
  millisecond by a thread: the activations and gradients an update holds at once, and Adam's
  moments; CUDA:
  ``torch.cuda.max_memory_allocated``). The two settings alternate over
  ``rounds`` and the medians are reported. On CPU every process runs torch on one thread, as
  dvla's roles do.
* **replication**: values a version carries (adapters and heads) against the model's
  parameters, and bytes per full version.
* **calls**: one ``sample`` call on synthetic observations at each of ``call_batches``, without
  the simulator: the aten operators it dispatches (a ``TorchDispatchMode`` counter; on CUDA each
  is about one kernel launch, the figure that bounds a launch-bound call) and its latency p50.
"""

from __future__ import annotations

import multiprocessing as mp
import resource
import statistics
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .stats import percentile

__all__ = ["FamilyBenchConfig", "measure_families", "format_families"]

FAMILIES = {"tokens": "vla-tokens", "flow": "vla-flow"}


@dataclass(frozen=True)
class FamilyBenchConfig:
    """What the families part of ``dvla bench vla`` measures."""

    #: families measured (``tokens``, ``flow``)
    families: tuple[str, ...] = ("tokens", "flow")
    #: checkpoint size (``test``: CPU; ``0.5b``: ~0.46e9 parameters, for a GPU)
    size: str = "test"
    #: torch device of the policy and the learner (``cpu``, ``cuda``)
    device: str = "cpu"
    #: the checkpoint's weights (``float32``, ``bfloat16``)
    dtype: str = "float32"
    #: LoRA rank (0: full fine-tuning)
    lora_r: int = 4
    env: str = "PushCube-v1"
    image_size: int = 64
    envs: int = 2
    #: timed env-group steps (after ``warmup_steps``)
    steps: int = 60
    warmup_steps: int = 3
    #: trajectory chunk length for the bytes figure
    chunk_steps: int = 10
    #: transitions per learner batch, and per micro-batch in the micro-batched setting
    batch: int = 256
    micro_batch: int = 16
    #: timed updates per learner process; processes per setting (alternating)
    updates: int = 2
    rounds: int = 2
    #: batch sizes of the per-call figures (aten operators per ``sample``, latency p50)
    call_batches: tuple[int, ...] = (1, 16)
    #: timed ``sample`` calls per batch size (after one warm-up call)
    call_repeats: int = 20

    @staticmethod
    def quick() -> "FamilyBenchConfig":
        return FamilyBenchConfig(steps=6, warmup_steps=1, batch=32, micro_batch=8, updates=1, rounds=1, image_size=32,
                                 call_repeats=3)


def _task(cfg: FamilyBenchConfig, family: str, checkpoint: str) -> Any:
    from dvla.config import TaskConfig

    kwargs: dict[str, Any] = {"checkpoint": checkpoint, "dtype": cfg.dtype}
    if cfg.lora_r:
        kwargs["lora"] = {"r": cfg.lora_r}
    return TaskConfig(env=cfg.env, obs_mode="rgb", image_size=cfg.image_size, max_episode_steps=50,
                      policy=FAMILIES[family], policy_kwargs=kwargs, rollout_device=cfg.device,
                      eval_device=cfg.device, device=cfg.device)


def _policy(task: Any, obs_spec: Any, act_dim: int, device: str) -> Any:
    from dvla.learn.policies import make_policy

    return make_policy(task.policy, obs_spec, act_dim, **task.policy_kwargs).to(device)


def _rollout(cfg: FamilyBenchConfig, task: Any, progress: Callable[[str], None]) -> tuple[dict[str, Any], dict]:
    """Act + step as a rollout does; returns the figures and the recorded steps."""
    import torch

    from dvla.learn.envs import EnvGroup, obs_as_dict, obs_to_torch
    from dvla.learn.policies import extras_spec, sample_actions
    from dvla.replication import ParamLayout

    if cfg.device == "cpu":
        torch.set_num_threads(1)  # as in a rollout process
    group = EnvGroup(task, cfg.envs, seed=0)
    try:
        policy = _policy(task, group.obs_spec, group.act_dim, cfg.device).eval()
        layout = ParamLayout.from_state_dict(policy)
        params = sum(p.numel() for p in policy.parameters())
        gen = torch.Generator(device=cfg.device).manual_seed(0)
        obs = group.reset()
        rec: dict[str, list] = {"obs": [], "actions": [], "logprobs": [], "extras": []}
        act_ms: list[float] = []
        t0 = time.perf_counter()
        for i in range(cfg.warmup_steps + cfg.steps):
            if i == cfg.warmup_steps:
                act_ms, t0 = [], time.perf_counter()
            t = time.perf_counter()
            with torch.no_grad():
                action, logprob, extras = sample_actions(policy, obs_to_torch(obs, cfg.device), generator=gen)
                action, logprob = action.float().cpu().numpy(), logprob.float().cpu().numpy()
                extras = {k: v.cpu().numpy() for k, v in extras.items()}
            act_ms.append((time.perf_counter() - t) * 1e3)
            rec["obs"].append(obs_as_dict(obs))
            rec["actions"].append(action)
            rec["logprobs"].append(logprob)
            rec["extras"].append(extras)
            obs = group.step(action).next_obs
        wall = time.perf_counter() - t0
        out = {
            "parameters": params,
            "replicated_values": layout.numel,
            "replicated_fraction": layout.numel / params,
            "bytes_per_full_version": layout.nbytes,
            "env_steps_per_s": cfg.envs * cfg.steps / wall,
            "act_ms_p50": percentile(act_ms, 50),
            "act_ms_p99": percentile(act_ms, 99),
        }
        out["calls"] = measure_calls(policy, group.obs_spec, cfg.call_batches, cfg.call_repeats, cfg.device)
        rec.update(obs_spec=group.obs_spec, act_dim=group.act_dim, extras_spec=extras_spec(policy))
        return out, rec
    finally:
        group.close()


def synthetic_obs(obs_spec: Any, batch: int, device: str, seed: int = 0) -> dict[str, Any]:
    """A batch of random observations of ``obs_spec`` (uint8 images, float32, token ids)."""
    import torch

    g = torch.Generator().manual_seed(seed)
    out = {}
    for name, spec in obs_spec.items():
        shape = (batch, *spec.shape)
        if spec.dtype == "uint8":
            t = torch.randint(0, 256, shape, generator=g).to(torch.uint8)
        elif spec.dtype.startswith("int"):
            t = torch.randint(1, int(spec.vocab or 2), shape, generator=g).to(getattr(torch, spec.dtype))
        else:
            t = torch.randn(shape, generator=g)
        out[name] = t.to(device)
    return out


def count_aten_ops(fn: Callable[[], Any]) -> int:
    """Aten operators ``fn`` dispatches (views and metadata calls included: what the dispatcher sees)."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class _Count(TorchDispatchMode):
        n = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # noqa: ANN001
            _Count.n += 1
            return func(*args, **(kwargs or {}))

    with _Count():
        fn()
    return _Count.n


def measure_calls(policy: Any, obs_spec: Any, batches: tuple[int, ...], repeats: int, device: str) -> dict[str, Any]:
    """Per batch size: aten operators per ``sample`` call and its latency p50 (ms)."""
    import torch

    cuda = device.startswith("cuda")
    out: dict[str, Any] = {}
    for b in batches:
        obs = synthetic_obs(obs_spec, b, device)
        gen = torch.Generator(device=device).manual_seed(0)
        call = lambda: policy.sample(obs, generator=gen)  # noqa: E731
        call()  # warm-up
        ops = count_aten_ops(call)
        ms = []
        for _ in range(repeats):
            if cuda:
                torch.cuda.synchronize()
            t = time.perf_counter()
            call()
            if cuda:
                torch.cuda.synchronize()
            ms.append((time.perf_counter() - t) * 1e3)
        out[str(b)] = {"aten_ops": ops, "sample_ms_p50": percentile(ms, 50)}
    return out


def _bytes_per_step(cfg: FamilyBenchConfig, rec: dict) -> dict[str, float]:
    """Wire bytes of one chunk of the recorded steps, per env step, with and without extras."""
    import dataclasses

    from dvla.fabric.codec import encode
    from dvla.fabric.messages import ChunkSpec

    T, n = min(cfg.chunk_steps, len(rec["actions"])), cfg.envs
    c = ChunkSpec(obs=rec["obs_spec"], act_dim=rec["act_dim"], extras=rec["extras_spec"], T=T, N=n).zeros()
    for t in range(T):
        for k, v in rec["obs"][t].items():
            c.obs[k][t] = v
        c.actions[t], c.logprobs[t] = rec["actions"][t], rec["logprobs"][t]
        for k, v in rec["extras"][t].items():
            c.extras[k][t] = v
    with_extras = len(encode(c)) / (T * n)
    without = len(encode(dataclasses.replace(c, extras={}))) / (T * n)
    return {"bytes_per_env_step": with_extras, "extras_bytes_per_env_step": with_extras - without}


def _learner_process(cfg: FamilyBenchConfig, task: Any, rec: dict, micro: int | None, out: Any) -> None:
    """One learner setting in a fresh process: the update time and the peak memory."""
    import torch

    from dvla.config import PPOConfig
    from dvla.learn.ppo import PPOLearner

    torch.manual_seed(0)
    if cfg.device == "cpu":
        torch.set_num_threads(1)
    policy = _policy(task, rec["obs_spec"], rec["act_dim"], cfg.device)
    n, steps = cfg.batch, len(rec["actions"])
    rows = [(i % steps, i % cfg.envs) for i in range(n)]

    def stack(key: str) -> Any:
        return {k: torch.as_tensor(np.stack([rec[key][t][k][e] for t, e in rows])) for k in rec[key][0]}

    batch = {
        "obs": stack("obs"), "extras": stack("extras"),
        "actions": torch.as_tensor(np.stack([rec["actions"][t][e] for t, e in rows])),
        "logprobs": torch.as_tensor(np.stack([rec["logprobs"][t][e] for t, e in rows])),
        "advantages": torch.randn(n), "returns": torch.randn(n), "values": torch.zeros(n),
    }
    ppo = PPOConfig(batch_steps=n, minibatches=2, update_epochs=1, target_kl=None, micro_batch=micro)
    learner = PPOLearner(policy, ppo, cfg.device, seed=0)
    cuda = cfg.device.startswith("cuda")
    # The sampler starts before the first update: freed activations stay resident in the
    # allocator, so the rise shows up once, in the first update (with Adam's moments, small
    # for LoRA); the timed updates then reuse that memory.
    sampler = _RssPeak()
    learner.update(batch)  # warm-up: allocator, autograd graph, Adam's moments
    if cuda:
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
    times = []
    for _ in range(cfg.updates):
        t0 = time.perf_counter()
        learner.update(batch)
        if cuda:
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    base, peak = sampler.stop()
    out.put({
        "update_s": statistics.median(times),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "rss_before_mb": base,
        "update_rss_mb": peak - base,
        "peak_gpu_mb": torch.cuda.max_memory_allocated() / 2**20 if cuda else None,
    })


class _RssPeak:
    """The process's RSS now and its highest value until :meth:`stop`, sampled every ms."""

    def __init__(self) -> None:
        import psutil

        self._proc = psutil.Process()
        self.base = self.peak = self._proc.memory_info().rss
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rss-peak", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._done.wait(0.001):
            self.peak = max(self.peak, self._proc.memory_info().rss)

    def stop(self) -> tuple[float, float]:
        self._done.set()
        self._thread.join()
        return self.base / 2**20, self.peak / 2**20


def _learner(cfg: FamilyBenchConfig, task: Any, rec: dict, progress: Callable[[str], None]) -> dict[str, Any]:
    ctx = mp.get_context("spawn")
    runs: dict[str, list[dict]] = {"whole": [], "micro": []}
    rec = {k: v for k, v in rec.items()}
    for r in range(cfg.rounds):
        for name in (("whole", "micro") if r % 2 == 0 else ("micro", "whole")):
            q = ctx.Queue()
            p = ctx.Process(target=_learner_process, args=(cfg, task, rec, cfg.micro_batch if name == "micro" else None, q))
            p.start()
            try:
                res = q.get(timeout=900)
            finally:
                p.join(60)
                if p.is_alive():
                    p.terminate()
            runs[name].append(res)
            memory = (f"peak GPU memory {res['peak_gpu_mb']:.0f} MB" if res["peak_gpu_mb"] is not None
                      else f"updates add {res['update_rss_mb']:.0f} MB RSS")
            progress(f"learner {task.policy} {name}: {res['update_s'] * 1e3:.0f} ms, {memory}")
    out: dict[str, Any] = {"batch": cfg.batch, "minibatch": cfg.batch // 2, "micro_batch": cfg.micro_batch}
    for name, values in runs.items():
        out[name] = {k: (statistics.median(v[k] for v in values) if values[0][k] is not None else None)
                     for k in values[0]}
    return out


def measure_families(cfg: FamilyBenchConfig, progress: Callable[[str], None]) -> dict[str, Any]:
    from dvla.learn.vla.build import save_random_checkpoint

    out: dict[str, Any] = {"size": cfg.size, "device": cfg.device, "dtype": cfg.dtype, "lora_r": cfg.lora_r,
                           "envs": cfg.envs, "image_size": cfg.image_size, "families": {}}
    with tempfile.TemporaryDirectory(prefix="dvla-bench-vla-") as tmp:
        for family in cfg.families:
            from dvla.learn.envs import probe_spec
            from dvla.config import TaskConfig

            _, act_dim = probe_spec(TaskConfig(env=cfg.env, obs_mode="rgb", image_size=cfg.image_size))
            ckpt = save_random_checkpoint(Path(tmp) / family, family, action_dim=act_dim, max_chunk=4, size=cfg.size,
                                          dtype=cfg.dtype)
            task = _task(cfg, family, str(ckpt))
            rollout, rec = _rollout(cfg, task, progress)
            progress(f"{FAMILIES[family]} rollout: {rollout['env_steps_per_s']:.1f} env steps/s, "
                     f"act p50 {rollout['act_ms_p50']:.1f} ms")
            out["families"][family] = {
                "policy": FAMILIES[family], **rollout, **_bytes_per_step(cfg, rec),
                "learner": _learner(cfg, task, rec, progress),
            }
    return out


def format_families(doc: dict[str, Any]) -> list[str]:
    lines = [f"Hugging Face families ({doc['size']}, {doc['dtype']}, LoRA r={doc['lora_r']}, {doc['device']}; "
             f"{doc['envs']} rgb envs at {doc['image_size']} px):"]
    for f in doc["families"].values():
        lr = f["learner"]
        lines += [
            f"  {f['policy']:<10} {f['parameters'] / 1e6:6.2f} M params, versions carry {f['replicated_fraction']:.3f} "
            f"({f['bytes_per_full_version'] / 1e3:.0f} kB)",
            f"    rollout {f['env_steps_per_s']:7.1f} env steps/s   act p50 {f['act_ms_p50']:6.2f} ms  p99 {f['act_ms_p99']:6.2f} ms"
            f"   wire {f['bytes_per_env_step']:.0f} B/env step ({f['extras_bytes_per_env_step']:.0f} B extras)",
        ]
        for b, c in f.get("calls", {}).items():
            lines.append(f"    sample at batch {b:>4}: {c['aten_ops']:6d} aten ops per call"
                         f"   p50 {c['sample_ms_p50']:7.2f} ms")
        for name in ("whole", "micro"):
            m = lr[name]
            gpu = f"  peak GPU {m['peak_gpu_mb']:.0f} MB" if m.get("peak_gpu_mb") is not None else ""
            what = f"micro-batches of {lr['micro_batch']}" if name == "micro" else f"minibatches of {lr['minibatch']}"
            lines.append(f"    learner {what:<22} update {m['update_s'] * 1e3:7.0f} ms   RSS +{m['update_rss_mb']:5.0f} MB "
                         f"(peak {m['peak_rss_mb']:.0f} MB){gpu}")
    return lines
